"""The CiA 402 drive state machine as explicit enums and transitions (pure, no I/O).

CiA 402-2 v4.1, section 6.2: the statusword (0x6041) encodes the state, the
controlword (0x6040) carries the commands. ``next_command`` returns the one
command that moves a drive one transition towards a wanted state; the caller
sends it, waits for the statusword to confirm and asks again (verified,
one step at a time). Fault reset is a rising edge of controlword bit 7.
"""

from __future__ import annotations

import enum


class State(enum.IntEnum):
    """Drive states (CiA 402-2 figure 10), numbered for ``status_words``."""

    NOT_READY_TO_SWITCH_ON = 0
    SWITCH_ON_DISABLED = 1
    READY_TO_SWITCH_ON = 2
    SWITCHED_ON = 3
    OPERATION_ENABLED = 4
    QUICK_STOP_ACTIVE = 5
    FAULT_REACTION_ACTIVE = 6
    FAULT = 7


class StatusBit(enum.IntFlag):
    READY_TO_SWITCH_ON = 1 << 0
    SWITCHED_ON = 1 << 1
    OPERATION_ENABLED = 1 << 2
    FAULT = 1 << 3
    VOLTAGE_ENABLED = 1 << 4
    QUICK_STOP = 1 << 5            # 0 = quick stop active
    SWITCH_ON_DISABLED = 1 << 6
    WARNING = 1 << 7
    REMOTE = 1 << 9
    TARGET_REACHED = 1 << 10
    INTERNAL_LIMIT = 1 << 11


class ControlBit(enum.IntFlag):
    SWITCH_ON = 1 << 0
    ENABLE_VOLTAGE = 1 << 1
    QUICK_STOP = 1 << 2            # 0 = quick stop
    ENABLE_OPERATION = 1 << 3
    FAULT_RESET = 1 << 7
    HALT = 1 << 8


class Command(enum.IntEnum):
    """Controlword values of the device-control commands (CiA 402-2 table 30)."""

    SHUTDOWN = 0x0006
    SWITCH_ON = 0x0007
    DISABLE_VOLTAGE = 0x0000
    QUICK_STOP = 0x0002
    DISABLE_OPERATION = 0x0007
    ENABLE_OPERATION = 0x000F
    FAULT_RESET = 0x0080


# (mask, value) -> state, checked in this order (CiA 402-2 table 31)
_DECODE: tuple[tuple[int, int, State], ...] = (
    (0x4F, 0x00, State.NOT_READY_TO_SWITCH_ON),
    (0x4F, 0x40, State.SWITCH_ON_DISABLED),
    (0x6F, 0x21, State.READY_TO_SWITCH_ON),
    (0x6F, 0x23, State.SWITCHED_ON),
    (0x6F, 0x27, State.OPERATION_ENABLED),
    (0x6F, 0x07, State.QUICK_STOP_ACTIVE),
    (0x4F, 0x0F, State.FAULT_REACTION_ACTIVE),
    (0x4F, 0x08, State.FAULT),
)

#: statusword bits a drive reports in each state (used by simulated twins)
STATUSWORD_OF: dict[State, int] = {
    State.NOT_READY_TO_SWITCH_ON: 0x0000,
    State.SWITCH_ON_DISABLED: 0x0040,
    State.READY_TO_SWITCH_ON: 0x0021,
    State.SWITCHED_ON: 0x0023,
    State.OPERATION_ENABLED: 0x0027,
    State.QUICK_STOP_ACTIVE: 0x0007,
    State.FAULT_REACTION_ACTIVE: 0x000F,
    State.FAULT: 0x0008,
}


def decode_state(statusword: int) -> State | None:
    """Return the state a statusword reports (None: a pattern CiA 402 does not define)."""
    for mask, value, state in _DECODE:
        if statusword & mask == value:
            return state
    return None


class Goal(enum.Enum):
    """Where the driver wants the drive to be."""

    OPERATION_ENABLED = 'operation_enabled'   # run
    SWITCHED_ON = 'switched_on'               # stop: disable operation, stay switched on
    QUICK_STOP = 'quick_stop'                 # stop through the quick-stop ramp
    SWITCH_ON_DISABLED = 'switch_on_disabled'  # disable voltage


def next_command(state: State | None, goal: Goal) -> Command | None:
    """Return the one command that moves ``state`` a transition towards ``goal``.

    None means: send nothing new (hold).

    A drive in FAULT stays there (only ``Command.FAULT_RESET`` leaves it, and that
    is the caller's explicit decision); states in transition are waited for.
    """
    if state is None or state in (State.NOT_READY_TO_SWITCH_ON, State.FAULT_REACTION_ACTIVE,
                                  State.FAULT):
        return None
    if goal is Goal.SWITCH_ON_DISABLED:
        return None if state is State.SWITCH_ON_DISABLED else Command.DISABLE_VOLTAGE
    if goal is Goal.QUICK_STOP:
        if state is State.OPERATION_ENABLED:
            return Command.QUICK_STOP                       # transition 11
        return None if state is State.QUICK_STOP_ACTIVE else _hold(state)
    if goal is Goal.SWITCHED_ON:
        if state is State.OPERATION_ENABLED:
            return Command.DISABLE_OPERATION                # transition 5
        if state is State.QUICK_STOP_ACTIVE:
            return Command.DISABLE_VOLTAGE                  # transition 12
        return _hold(state)
    # Goal.OPERATION_ENABLED
    return {
        State.SWITCH_ON_DISABLED: Command.SHUTDOWN,         # transition 2
        State.READY_TO_SWITCH_ON: Command.SWITCH_ON,        # transition 3
        State.SWITCHED_ON: Command.ENABLE_OPERATION,        # transition 4
        State.OPERATION_ENABLED: Command.ENABLE_OPERATION,  # stay
        State.QUICK_STOP_ACTIVE: Command.DISABLE_VOLTAGE,   # transition 12, then 2, 3, 4
    }[state]


def _hold(state: State) -> Command:
    """Return the command that keeps a drive where it is (no motion possible there)."""
    return {
        State.SWITCH_ON_DISABLED: Command.DISABLE_VOLTAGE,
        State.READY_TO_SWITCH_ON: Command.SHUTDOWN,
        State.SWITCHED_ON: Command.SWITCH_ON,
    }.get(state, Command.DISABLE_VOLTAGE)


def transition(state: State, controlword: int, previous_controlword: int = 0) -> State:
    """Return the state a compliant drive enters on ``controlword`` (for simulated twins).

    Fault reset acts on the rising edge of bit 7 and only leaves FAULT (the
    caller decides whether the cause is gone); other commands are ignored
    while bit 7 is set.
    """
    if controlword & ControlBit.FAULT_RESET:
        if state is State.FAULT and not previous_controlword & ControlBit.FAULT_RESET:
            return State.SWITCH_ON_DISABLED                 # transition 15
        return state
    if state in (State.NOT_READY_TO_SWITCH_ON, State.FAULT_REACTION_ACTIVE, State.FAULT):
        return state
    if not controlword & ControlBit.ENABLE_VOLTAGE:
        return State.SWITCH_ON_DISABLED                     # 7, 9, 10, 12
    if not controlword & ControlBit.QUICK_STOP:
        if state is State.OPERATION_ENABLED:
            return State.QUICK_STOP_ACTIVE                  # 11
        if state is State.QUICK_STOP_ACTIVE:
            return state
        return State.SWITCH_ON_DISABLED                     # 7, 10
    command = controlword & 0x0F
    if state is State.QUICK_STOP_ACTIVE:
        return state     # leaves only with disable voltage (quick stop option 1/2 style)
    if command & 0x07 == 0x06:                              # shutdown: 2, 6, 8
        return State.READY_TO_SWITCH_ON
    if command == 0x07:                                     # switch on 3 / disable op 5
        if state in (State.READY_TO_SWITCH_ON, State.OPERATION_ENABLED, State.SWITCHED_ON):
            return State.SWITCHED_ON
        return state
    if command == 0x0F:                                     # enable operation 4 (3+4)
        if state in (State.SWITCHED_ON, State.OPERATION_ENABLED):
            return State.OPERATION_ENABLED
        if state is State.READY_TO_SWITCH_ON:
            return State.SWITCHED_ON
        return state
    return state
