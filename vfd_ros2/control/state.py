"""What the control loop reports: the run state, a consistent snapshot, action results."""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass
from types import MappingProxyType
from typing import Mapping, NamedTuple

from ..drives import HostLossProtection, ParameterValue
from ..profiles import NO_FAULT, FaultInfo

#: why a drive that just connected may not run yet (its ``stop_reason`` until then)
STATUS_NOT_READ = 'no status read since the drive connected'


class RunState(enum.IntEnum):
    """Why the drive does or does not follow velocity commands (DriveStatus.RUN_STATE_*)."""

    OFFLINE = 0
    FAULT = 1
    DISABLED = 2
    STOPPED = 3
    BLOCKED = 4
    WATCHDOG = 5
    RUNNING = 6

    @property
    def label(self) -> str:
        return self.name.lower()


class CommandOutcome(enum.Enum):
    ACCEPTED = 'accepted'
    CLAMPED = 'clamped'
    REJECTED = 'rejected'


@dataclass(frozen=True)
class ActionResult:
    success: bool
    message: str
    value: ParameterValue | None = None


class DriveState(NamedTuple):
    """A consistent snapshot of everything the node publishes.

    A named tuple, not a frozen dataclass: the control loop builds one per drive
    and cycle, and a frozen dataclass sets its 40-odd fields one ``object.__setattr__``
    at a time (6 us against 1.7 us, the largest single step of publishing a cycle).
    """

    hardware_id: str
    online: bool = False
    ready: bool = False
    enabled: bool = False
    running: bool = False
    reverse: bool = False
    fault: bool = False
    warning: bool = False
    at_speed: bool = False
    watchdog_tripped: bool = False
    run_state: RunState = RunState.OFFLINE
    stop_reason: str = 'not connected yet'
    status_words: tuple[tuple[str, int], ...] = ()
    commanded_velocity: float = 0.0
    measured_velocity: float = math.nan
    setpoint_raw: int = 0
    measured: Mapping[str, float] = MappingProxyType({})     # role -> engineering value
    position: float = math.nan          # rad at the output shaft (JointState.position)
    position_source: str = 'integrated'   # 'drive' (a counter it reports) or 'integrated'
    effort: float = math.nan            # N·m at the output shaft; NaN = not measured
    active_fault: FaultInfo = NO_FAULT
    warning_code: int = 0
    warning_subcode: int = 0
    transactions: int = 0
    comm_errors: int = 0
    timeouts: int = 0
    bad_frames: int = 0
    exceptions: int = 0
    reconnects: int = 0
    late_replies: int = 0
    rejected_commands: int = 0
    clamped_commands: int = 0
    unexpected_starts: int = 0      # the drive started although the host had it idle
    comm_faults_cleared: int = 0    # comm-loss faults of the driver's absence reset at connect
    loop_errors: int = 0            # exceptions inside the loop: each one is a bug
    link_error: str = ''            # why the link failed last ('' while healthy)
    link_closed: str = ''           # why the host closed the link on purpose ('' = it did not)
    protection: HostLossProtection = HostLossProtection()
    unavailable: tuple[str, ...] = ()      # values and settings the drive refuses
    link_notes: tuple[str, ...] = ()       # what to know about the link (adapter latency, a
                                           # nameplate that scales speed otherwise)
    read_at: float = math.nan       # the controller's clock when it was taken (after a poll)
    not_stopping: str = ''          # held idle, the drive has run on past stop_timeout: why
    not_following: str = ''         # running, the drive has missed its command that long: why
    command_gaps: int = 0           # commands that came soon after a watchdog stop
    command_gap: str = ''           # the last of them, described, while recent

    @property
    def state(self) -> str:
        """The run state as one lower-case word (DriveStatus.state)."""
        return self.run_state.label
