"""The one rule that decides whether a drive may move, and if not, why.

It decides both what the loop writes (run or idle) and what ``~/status``
reports (``run_state``, ``stop_reason``), so the two can never disagree. The
order is the order of what an operator must do first: a drive that is offline
and faulted is reported offline.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

from ..profiles import FaultInfo
from .state import RunState


@dataclass
class Intent:
    """What the host wants of the drive: changed by services, read by the loop."""

    enabled: bool = False
    stopped: bool = False           # ~/stop latches until ~/enable
    idle_action: str = 'stop'       # what "not running" writes: stop, disable, quick_stop
    fault_latched: bool = False     # a fault was seen; only ~/reset_fault clears it
    held: str = ''                  # why motion is held beyond the services ('' = not held):
                                    # a managed node not active; the reason tells what to do
    asked_stop: bool = False        # an operator's ~/stop or ~/disable: only ~/enable ends
                                    # it (not a managed node's activate with auto_enable)


class Conditions(NamedTuple):
    """Everything the rule looks at, taken at one moment.

    A named tuple: the loop takes one or two per drive and cycle, and a frozen
    dataclass sets each field with ``object.__setattr__``.
    """

    online: bool
    link_error: str
    link_closed: str                 # why the host closed the link on purpose ('' = it did not)
    fault: FaultInfo
    unsafe: str                      # the drive layer's reason it must not run ('' = none)
    watchdog_expired: bool
    watchdog_age: float
    command_timeout: float


def decide(intent: Intent, now: Conditions) -> tuple[RunState, str]:
    """Return RUNNING and '', or the first state that holds the drive idle and why."""
    if not now.online:
        return RunState.OFFLINE, now.link_closed or \
            f'no valid reply from the drive: {now.link_error}'
    if now.fault.active or intent.fault_latched:
        fault = now.fault
        text = f'fault {fault.display} {fault.name}' if fault.active else 'fault (cleared)'
        return RunState.FAULT, f'{text}: call ~/reset_fault'
    if intent.held:
        return (RunState.STOPPED if intent.enabled else RunState.DISABLED), intent.held
    if not intent.enabled:
        return RunState.DISABLED, 'disabled: call ~/enable'
    if intent.stopped:
        by = '~/stop' if intent.asked_stop else 'a lifecycle deactivate'
        return RunState.STOPPED, f'stopped by {by}: call ~/enable to resume'
    if now.unsafe:
        return RunState.BLOCKED, now.unsafe
    if now.watchdog_expired:
        # (commands from before a connect or a stop are forgotten: none may resume it)
        age = 'none since the drive connected or was stopped' \
            if math.isinf(now.watchdog_age) else \
            f'last {now.watchdog_age:.2f} s ago'
        return RunState.WATCHDOG, (f'no velocity command within command_timeout '
                                   f'{now.command_timeout:g} s ({age})')
    return RunState.RUNNING, ''
