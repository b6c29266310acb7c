"""The drive-side CiA 402 control shared by every bus that carries it (CANopen, EtherCAT).

``vfd_ros2.protocol.cia402`` holds the pure state machine (decode, next command);
this class adds what a drive class needs around it, once for all buses: the goal
of the current cycle, one verified transition per cycle, a transition that takes
too long reported as stuck, the fault-reset edge and the flags derived from the
decoded state. A drive class feeds it statuswords and sends the controlwords it
returns, over whatever its bus moves them with (a CANopen RPDO, EtherCAT
process data).
"""

from __future__ import annotations

import logging
import time
from typing import Callable

from ..errors import ParameterError
from ..profiles import StopAction
from ..protocol.cia402 import Command, Goal, State, StatusBit, decode_state, next_command

log = logging.getLogger(__name__)

#: controlwords of the driver's actions (CiA 402-2 table 30)
ACTION_COMMANDS: dict[str, int] = {
    'fault_reset': int(Command.FAULT_RESET),
    'stop': int(Command.SWITCH_ON),
    'disable': int(Command.DISABLE_VOLTAGE),
    'quick_stop': int(Command.QUICK_STOP),
    'run': int(Command.ENABLE_OPERATION),
}

#: where each goal is complete (None: any state without motion will do)
_DONE: dict[Goal, State | None] = {
    Goal.OPERATION_ENABLED: State.OPERATION_ENABLED,
    Goal.SWITCHED_ON: None,
    Goal.QUICK_STOP: None,
    Goal.SWITCH_ON_DISABLED: State.SWITCH_ON_DISABLED,
}


class Cia402Control:
    """Walks one drive's CiA 402 state machine towards the goal of each cycle."""

    def __init__(self, name: str, transition_timeout: float,
                 stop_action: StopAction = StopAction.DISABLE_OPERATION,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.name = name
        self.transition_timeout = transition_timeout
        self.stop_action = stop_action
        self._clock = clock
        self.state: State | None = None
        self.stuck = ''                  # why the drive does not reach the wanted state
        self._goal: Goal | None = None
        self._goal_since = 0.0

    def reset(self) -> None:
        """Forget everything learnt (after a link loss)."""
        self.state = None
        self.stuck = ''
        self._goal = None

    def update(self, statusword: int | None) -> None:
        self.state = decode_state(statusword) if statusword is not None else None

    @property
    def faulted(self) -> bool:
        return self.state in (State.FAULT, State.FAULT_REACTION_ACTIVE)

    @property
    def enabled(self) -> bool:
        """Whether the drive follows a velocity (Operation Enabled)."""
        return self.state is State.OPERATION_ENABLED

    def goal_for(self, run: bool, idle_action: str) -> Goal:
        if run:
            return Goal.OPERATION_ENABLED
        if idle_action == 'disable':
            return Goal.SWITCH_ON_DISABLED
        if idle_action == 'quick_stop' or self.stop_action is StopAction.QUICK_STOP:
            return Goal.QUICK_STOP
        return Goal.SWITCHED_ON

    def controlword(self, run: bool, idle_action: str) -> int:
        """Return this cycle's controlword: one transition towards the goal, or hold."""
        goal = self.goal_for(run, idle_action)
        now = self._clock()
        if goal is not self._goal:
            self._goal, self._goal_since = goal, now
            self.stuck = ''
        command = next_command(self.state, goal)
        done = _DONE[goal]
        if done is not None and self.state is done:
            self._goal_since = now
            self.stuck = ''                  # got there after all (a slave back in OP)
        elif done is not None and now - self._goal_since > self.transition_timeout \
                and not self.stuck:
            where = self.state.name if self.state is not None else 'unknown'
            self.stuck = (f'CiA 402: the drive stays in {where}, not {done.name}, after '
                          f'{self.transition_timeout:g} s')
            log.warning('%s: %s', self.name, self.stuck)
        return int(command) if command is not None else int(Command.DISABLE_VOLTAGE)

    @staticmethod
    def action_words(action: str, last_controlword: int | None) -> list[int]:
        """Return the controlwords of one action, in order (a reset: a rising edge of bit 7)."""
        if action not in ACTION_COMMANDS:
            raise ParameterError(f'CiA 402 has no {action!r} command')
        words = []
        if action == 'fault_reset' and (last_controlword or 0) & 0x80:
            words.append(int(Command.DISABLE_VOLTAGE))          # bit 7 low first
        words.append(ACTION_COMMANDS[action])
        return words

    def flags(self, statusword: int | None, speed: float) -> dict[str, bool]:
        """Return ready, running, fault, warning, at_speed and reverse from the decoded state."""
        state = self.state
        return {
            # Switch on disabled counts: an idle drive is held there. (One held there by
            # a safe torque off cannot be told from it until it is told to run.)
            'ready': state in (State.SWITCH_ON_DISABLED, State.READY_TO_SWITCH_ON,
                               State.SWITCHED_ON, State.OPERATION_ENABLED),
            'running': state is State.OPERATION_ENABLED,
            'fault': self.faulted,
            'warning': bool(statusword is not None and statusword & StatusBit.WARNING),
            'at_speed': state is State.OPERATION_ENABLED and bool(
                statusword is not None and statusword & StatusBit.TARGET_REACHED),
            'reverse': speed < 0,
        }
