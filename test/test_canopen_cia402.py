"""CiA 402 state machine: statusword decode, commands and transitions, one by one (pure)."""

from __future__ import annotations

import pytest

from vfd_ros2.protocol.cia402 import (
    STATUSWORD_OF,
    Command,
    Goal,
    State,
    decode_state,
    next_command,
    transition,
)


@pytest.mark.parametrize('word, state', [
    (0x0000, State.NOT_READY_TO_SWITCH_ON),
    (0x0040, State.SWITCH_ON_DISABLED),
    (0x0250, State.SWITCH_ON_DISABLED),          # remote + voltage bits do not matter
    (0x0021, State.READY_TO_SWITCH_ON),
    (0x0231, State.READY_TO_SWITCH_ON),
    (0x0023, State.SWITCHED_ON),
    (0x0027, State.OPERATION_ENABLED),
    (0x0637, State.OPERATION_ENABLED),           # + target reached, remote, voltage
    (0x0007, State.QUICK_STOP_ACTIVE),
    (0x000F, State.FAULT_REACTION_ACTIVE),
    (0x0008, State.FAULT),
    (0x0288, State.FAULT),                       # + warning, remote
])
def test_statusword_decode(word, state):
    assert decode_state(word) is state


def test_undefined_statusword_is_none():
    assert decode_state(0x0001) is None


def test_statusword_table_round_trips():
    for state, word in STATUSWORD_OF.items():
        assert decode_state(word) is state


def test_command_values():
    assert Command.SHUTDOWN == 0x06 and Command.SWITCH_ON == 0x07
    assert Command.ENABLE_OPERATION == 0x0F and Command.DISABLE_VOLTAGE == 0x00
    assert Command.QUICK_STOP == 0x02 and Command.FAULT_RESET == 0x80


@pytest.mark.parametrize('state, word, after', [
    (State.SWITCH_ON_DISABLED, 0x06, State.READY_TO_SWITCH_ON),        # 2 shutdown
    (State.READY_TO_SWITCH_ON, 0x07, State.SWITCHED_ON),               # 3 switch on
    (State.SWITCHED_ON, 0x0F, State.OPERATION_ENABLED),                # 4 enable operation
    (State.OPERATION_ENABLED, 0x07, State.SWITCHED_ON),                # 5 disable operation
    (State.SWITCHED_ON, 0x06, State.READY_TO_SWITCH_ON),               # 6 shutdown
    (State.READY_TO_SWITCH_ON, 0x00, State.SWITCH_ON_DISABLED),        # 7 disable voltage
    (State.OPERATION_ENABLED, 0x06, State.READY_TO_SWITCH_ON),         # 8 shutdown
    (State.OPERATION_ENABLED, 0x00, State.SWITCH_ON_DISABLED),         # 9 disable voltage
    (State.SWITCHED_ON, 0x00, State.SWITCH_ON_DISABLED),               # 10 disable voltage
    (State.OPERATION_ENABLED, 0x02, State.QUICK_STOP_ACTIVE),          # 11 quick stop
    (State.QUICK_STOP_ACTIVE, 0x00, State.SWITCH_ON_DISABLED),         # 12 disable voltage
    (State.SWITCH_ON_DISABLED, 0x0F, State.SWITCH_ON_DISABLED),        # no shortcut
    (State.FAULT, 0x0F, State.FAULT),                                  # only reset leaves
])
def test_transitions(state, word, after):
    assert transition(state, word) is after


def test_fault_reset_needs_a_rising_edge():
    assert transition(State.FAULT, 0x80, previous_controlword=0x00) is State.SWITCH_ON_DISABLED
    assert transition(State.FAULT, 0x80, previous_controlword=0x80) is State.FAULT
    # bit 7 high: other commands ignored
    assert transition(State.SWITCHED_ON, 0x8F, previous_controlword=0x07) is State.SWITCHED_ON


def test_enable_walks_one_transition_at_a_time():
    state, seen = State.SWITCH_ON_DISABLED, []
    for _ in range(5):
        command = next_command(state, Goal.OPERATION_ENABLED)
        seen.append(command)
        state = transition(state, command)
    assert seen[:3] == [Command.SHUTDOWN, Command.SWITCH_ON, Command.ENABLE_OPERATION]
    assert state is State.OPERATION_ENABLED


@pytest.mark.parametrize('state, goal, command', [
    (State.OPERATION_ENABLED, Goal.SWITCHED_ON, Command.DISABLE_OPERATION),
    (State.OPERATION_ENABLED, Goal.QUICK_STOP, Command.QUICK_STOP),
    (State.OPERATION_ENABLED, Goal.SWITCH_ON_DISABLED, Command.DISABLE_VOLTAGE),
    (State.QUICK_STOP_ACTIVE, Goal.OPERATION_ENABLED, Command.DISABLE_VOLTAGE),
    (State.SWITCH_ON_DISABLED, Goal.SWITCHED_ON, Command.DISABLE_VOLTAGE),   # stays idle
    (State.READY_TO_SWITCH_ON, Goal.SWITCHED_ON, Command.SHUTDOWN),          # never enables
    (State.FAULT, Goal.OPERATION_ENABLED, None),        # reset is the caller's decision
    (State.FAULT_REACTION_ACTIVE, Goal.OPERATION_ENABLED, None),
    (State.NOT_READY_TO_SWITCH_ON, Goal.OPERATION_ENABLED, None),
    (None, Goal.OPERATION_ENABLED, None),
    (State.SWITCH_ON_DISABLED, Goal.SWITCH_ON_DISABLED, None),
])
def test_next_command(state, goal, command):
    assert next_command(state, goal) == command


def test_stop_goals_never_enable_operation():
    for state in State:
        for goal in (Goal.SWITCHED_ON, Goal.QUICK_STOP, Goal.SWITCH_ON_DISABLED):
            command = next_command(state, goal)
            if command is not None:
                assert transition(state, command) is not State.OPERATION_ENABLED


def test_a_stuck_transition_is_reported_and_cleared_once_the_drive_gets_there():
    """An EtherCAT slave back in OP reached Operation Enabled: 'blocked' stayed shown."""
    from vfd_ros2.drives.cia402 import Cia402Control
    now = [0.0]
    control = Cia402Control('d', transition_timeout=1.0, clock=lambda: now[0])
    control.update(0x0040)                              # switch on disabled
    control.controlword(True, 'stop')
    now[0] = 1.5
    control.controlword(True, 'stop')
    assert 'stays in SWITCH_ON_DISABLED, not OPERATION_ENABLED' in control.stuck
    control.update(0x0027)                              # operation enabled after all
    control.controlword(True, 'stop')
    assert control.stuck == ''
