"""The control of one drive: command, poll, supervise the link, publish a snapshot.

Commands arrive from any thread (``command_velocity``, ``submit``); only the
loop thread touches the transport (``step``, or a bus's loop calling the two
phases). Each cycle writes the command first, then polls status, then advances
at most one pending service action one step (``actions``).

Safety rules kept here, in one place:
- start-up and every reconnect write a zero setpoint and the idle command
  before anything else, and forget all earlier velocity commands;
- the drive runs only while the one rule in ``permit`` says so (enabled, not
  stopped, fault-free, online, run and fault state readable, fresh commands);
  it decides both what is written and what is reported;
- after a fault motion resumes only after a successful ``reset_fault``; the one
  exception is the drive's own comm-loss fault found at connect, which the
  host's absence caused: it is reset once, after the stop is written;
- a drive that reports running while the host has it idle gets the idle command
  again every cycle (counted as an unexpected start), whatever was sent last;
- the drive's own comm-loss timeout is sized for the bus it is on
  (``plan_host_loss``), and reported.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections import deque
from concurrent.futures import Future
from dataclasses import dataclass, replace
from typing import Callable

from ..drives import Drive, HostLossProtection, Reading
from ..drives.base import HOST_LOSS_JITTER
from ..errors import ParameterError, ProtocolException, TransportError, VfdError, quote
from ..profiles import Parameter
from ..protocol.scaling import SpeedUnit, VelocityScaling
from .actions import NOT_SERVED, ActionQueue, ServiceActions
from .joint import JointTracker, joint_config
from .link import LinkSupervisor
from .loop import SHUTDOWN_WAIT, CycleLoop
from .permit import Conditions, Intent, decide
from .state import STATUS_NOT_READ, ActionResult, CommandOutcome, DriveState, RunState
from .watchdog import CommandWatchdog

log = logging.getLogger(__name__)


#: a gap between two polls using this share of the drive's comm-loss timeout (less the
#: jitter allowance) has it re-planned: one more such cycle and the drive would trip
NEAR_TRIP = 0.75
#: the interval a re-plan is sized for, as a multiple of the gap that prompted it
ADDRESSING_HEADROOM = 1.25

#: a command that comes after the watchdog stopped the running drive, within this
#: multiple of command_timeout (or COMMAND_GAP_SPAN) after the one before, shows a
#: commander slower than the timeout (``ros2 topic pub -r 1`` against 0.5 s: the
#: wheel stops between commands)
COMMAND_GAP_FACTOR = 4.0
COMMAND_GAP_SPAN = 3.0
#: s within which a second such gap makes a WARN in /diagnostics (for as long again) and
#: a log line (at most one per this): one pause alone is only counted
COMMAND_GAP_MEMORY = 10.0
#: motor rpm still taken as standstill (a speed read in whole rpm shows a motor at rest
#: as 1-3 rpm, steadily on some): at the output shaft, if more than at_speed_tolerance
STANDSTILL_MOTOR_RPM = 5.0
#: stop_timeout windows more given to a drive held idle that is ramping down towards
#: zero within them (see _check_not_stopping)
RAMP_WINDOWS = 2
#: share of the command a running drive's measured speed may miss it by (beyond the
#: standstill band) before, lasting stop_timeout, it is told (see _check_following)
FOLLOWING_SHARE = 0.2
#: share of the motor's nominal speed a frequency-commanded motor may slip under load
SLIP_SHARE = 0.12
#: s over which the measured speed is smoothed when judging progress towards a command
FOLLOWING_SMOOTHING = 0.3

#: s between two read-backs of one setting written at connect (in turn), and at least
#: between two of all of them after a failed exchange (see _check_settings)
SETTINGS_CHECK_PERIOD = 10.0
SETTINGS_CHECK_AFTER_FAILURE = 1.0

#: the service actions that forget the commands taken before them (see forget_commands)
FORGETTING_ACTIONS = frozenset({'stop', 'disable'})

#: what ``DriveController.reconfigure`` may change while the loop runs
LIVE_FIELDS = frozenset({'command_timeout', 'max_velocity', 'cycle_period', 'auto_enable',
                         'action_timeout', 'stop_timeout', 'shown_period'})


def display_period(shown_period: float, cycle_period: float) -> float:
    """Return how long a value only shown in messages may go unread (``display_period``).

    Read one cycle before the next message is due at the latest, every message
    carries a value read since the last.
    """
    return max(0.0, shown_period - cycle_period)


@dataclass(frozen=True)
class ControllerConfig:
    command_timeout: float = 0.5      # s without a valid command -> stop
    max_velocity: float = 10.0        # rad/s at the output shaft; commands are clamped
    cycle_period: float = 0.02        # s per control cycle
    comm_loss_threshold: int = 2      # consecutive failed cycles -> offline
    reconnect_period: float = 0.5     # s between reconnect attempts
    drive_comm_timeout: float = 0.3   # s requested for the drive's own watchdog; 0 = off
    apply_commissioning: bool = True  # write the profile's bus-control settings
    auto_enable: bool = False         # enable at start-up (still needs fresh commands)
    action_timeout: float = 2.0       # s to verify enable / reset
    stop_timeout: float = 10.0        # s to verify stop / disable (deceleration)
    at_speed_tolerance: float = 0.1   # rad/s
    realtime_priority: int = 0        # SCHED_FIFO priority of the control thread; 0 = off
    # s between the messages that show the measured values (~/status or /diagnostics,
    # whichever comes more often): values only shown there are read once per message.
    shown_period: float = 0.05

    def __post_init__(self) -> None:
        for name in ('command_timeout', 'cycle_period', 'reconnect_period', 'action_timeout',
                     'stop_timeout', 'shown_period'):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ParameterError(f'{name} must be > 0, got {value}')
        if not (math.isfinite(self.max_velocity) and self.max_velocity > 0):
            raise ParameterError(f'max_velocity must be > 0, got {self.max_velocity}')
        if not (math.isfinite(self.drive_comm_timeout) and self.drive_comm_timeout >= 0):
            raise ParameterError(f'drive_comm_timeout must be >= 0, got {self.drive_comm_timeout}')
        if self.comm_loss_threshold < 1:
            raise ParameterError('comm_loss_threshold must be >= 1')
        if not 0 <= self.realtime_priority <= 99:
            raise ParameterError(f'realtime_priority must be 0..99, got {self.realtime_priority}')


def standstill(config: ControllerConfig, scaling: VelocityScaling | None) -> float:
    """Return the measured speed (rad/s) at or below which a stopped drive stands still.

    at_speed_tolerance, or STANDSTILL_MOTOR_RPM at the output shaft where that is more
    (a direct-drive wheel's 1 rpm is 0.105 rad/s: a stop must not fail on it). Not a
    share of max_velocity: a high limit made a motor coasting at 16 rpm "still".
    """
    motor = abs(scaling.motor_rpm_to_output(STANDSTILL_MOTOR_RPM)) if scaling else 0.0
    return max(config.at_speed_tolerance, motor)


def settings_the_driver_depends_on(drive: Drive) -> dict[str, str]:
    """Return the drive parameters a running node depends on, with why: code -> why.

    Its link (address, baud rate, framing: written, the drive stops answering on
    this link) and its velocity scaling (the rated speed where a speed is in
    percent, the pole pairs where it is in Hz: written, the wheel no longer runs
    at the commanded speed, and max_velocity no longer bounds it), and that there
    is no other way to move the motor than its commands (the profile's
    ``motion_channels``). A commissioning tool may write them (vfd_params); the
    node's parameter services refuse them.
    """
    found = {code: (f"{why}: a way to move the motor besides this node's commands; set "
                    'it with vfd_params or at the keypad, if at all')
             for code, why in drive.profile.motion_channels.items()}
    for code in getattr(drive, 'link_parameters', ()):    # (a plugin may not say)
        found[code] = ('it sets how this link reaches the drive (written, the drive stops '
                       "answering here): change it with vfd_params or at the keypad, with "
                       "the node's transport settings")
    velocity = drive.profile.velocity
    units = {velocity.setpoint_unit, velocity.feedback_unit}
    # (a percent of the rated frequency is of its synchronous speed: the pole pairs too,
    # and the rated speed, from which a drive that prints its pole pairs read-only works
    # them out: outside audit)
    percent_of = (velocity.rated_frequency, velocity.pole_pairs, velocity.rated_speed) \
        if velocity.rated_frequency else (velocity.rated_speed, '', '')
    for code, unit, setting in ((percent_of[0], SpeedUnit.PERCENT, 'motor.rated_speed_rpm'),
                                (percent_of[1], SpeedUnit.PERCENT, 'motor.pole_pairs'),
                                (percent_of[2], SpeedUnit.PERCENT, 'motor.pole_pairs'),
                                (velocity.pole_pairs, SpeedUnit.HZ, 'motor.pole_pairs')):
        if code and unit in units:
            found[code] = (f"the node's velocity scaling uses it ({setting}): written here, the "
                           'wheel would no longer run at the commanded speed; change it with '
                           f'vfd_params or at the keypad, with {setting}, and restart the node')
    return found


class DriveController:
    """Runs one drive: connect, command, poll, watchdog, service actions."""

    def __init__(self, drive: Drive, config: ControllerConfig,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.drive = drive
        self.config = config
        self._check_velocity_fits(config.max_velocity)
        self._clock = clock
        self._lock = threading.Lock()
        self._watchdog = CommandWatchdog(config.command_timeout, clock)
        self._velocity = 0.0
        self._setpoints: dict[str, int] = {}
        self._written_setpoints: dict[str, int] = {}
        self._rejected = 0
        self._clamped = 0
        self._watchdog_stopped = False    # the watchdog withdrew a run: the next command?
        self._command_gaps = 0            # commands after a watchdog stop (a slow commander)
        self._command_gap_times: deque[float] = deque(maxlen=2)
        self._command_gap = ''            # the last one, described, when repeated
        self._command_gap_at = -math.inf  # ... and when it came
        self._command_gap_logged_at = -math.inf
        self.intent = Intent(enabled=config.auto_enable)
        self.link = LinkSupervisor(drive.hardware_id, config.comm_loss_threshold,
                                   config.reconnect_period, clock)
        self._cycle = 0
        self._reading = Reading()
        self._settings_refused: tuple[str, ...] = ()
        self._nameplate_notes: tuple[str, ...] = ()   # the drive's nameplate against the scaling
        self._command_refused = ''      # why the last command write was refused, if it was
        self._actions = ActionQueue(drive.hardware_id)
        self._driver_settings = settings_the_driver_depends_on(drive)
        self.services = ServiceActions(
            drive, self.intent, lambda: self._reading, self._commands_fresh,
            self.check_parameter_write, config.action_timeout, config.stop_timeout, clock,
            standstill(config, getattr(drive, 'scaling', None)))
        self._loop: CycleLoop | None = None
        #: what to know about the thread that runs this drive (its own, or a bus's)
        self.loop_notes: tuple[str, ...] = ()
        self._stopped_loop_errors = 0
        self._cycle_ok = False
        self._command_pending = False
        self._run_written = False        # what the last command write asked: run or idle
        self._run_asked_at = -math.inf   # when a command write last asked it to run
        self._preempted_deadline: float | None = None   # watchdog expiry already acted on
        self._last_running = False
        self._not_running_since: float | None = None  # told to run, not running since
        self._lost_run = ''             # why a drive told to run does not, once it is clear
        self._exchange_failed = False   # since the settings were last read back
        self._settings_checked_at = -math.inf
        self._running_idle_since: float | None = None   # running while held idle, since
        self._running_idle_speed = math.nan  # |measured speed| then (a ramp brings it down)
        self._ramp_windows = 0          # stop_timeout windows given to a ramp so far
        self._running_idle_counted = False  # that episode is in unexpected_starts already
        self._not_stopping = ''         # why a drive held idle still runs, once it is clear
        self._not_following = ''        # why a running drive misses its command, once clear
        self._off_command_since: float | None = None     # last progress towards it
        self._off_command = 0.0         # the (smoothed) measured speed then (rad/s)
        self._off_smoothed = 0.0        # the measured speed smoothed since it is off
        self._off_polled = 0.0          # when that was last updated
        self._off_direction = 0.0       # the sign of command - speed
        self._unexpected_starts = 0
        self._polled_at: float | None = None   # when the last poll of this connection began
        self._near_trips = 0            # gaps in a row near the comm-loss timeout
        self._near_trip_after = math.inf   # s unpolled that is near it (_note_near_trip)
        self._raise_refused = 0.0       # a comm-loss timeout this connection could not write
        self._check_comm_fault = False   # the first reading after a connect is not read yet
        self._comm_fault_grace_until = -math.inf
        self._comm_faults_cleared = 0
        self.protection = self.plan_host_loss(0.0)
        #: what the last connect could set (a drive may refuse part of the plan)
        self.protection_applied: HostLossProtection | None = None
        #: asks the loop running this controller (its own, or a bus's) to write a
        #: new command before the next cycle
        self.request_preempt: Callable[[], None] | None = None
        #: run before each status read instead of this drive's own ``preempt``
        #: (a bus writes every drive's new command first)
        self.preempt_hook: Callable[[], None] | None = None
        #: the wheel as a joint (position, velocity, effort); the factory sets the node's
        #: counts_per_rev and rated torque
        self.joint = JointTracker(joint_config(
            drive.profile, getattr(drive, 'scaling', None) or VelocityScaling()))
        self._state = DriveState(hardware_id=drive.hardware_id,
                                 protection=self._protection_written())

    # --- sizing -------------------------------------------------------------------

    def _check_velocity_fits(self, max_velocity: float) -> None:
        """Refuse a max_velocity the drive's setpoint cannot carry unclamped (ParameterError).

        Within it every command is written as commanded; beyond it the setpoint
        would be clamped, which with a wrong scaling runs the motor flat out.
        (A drive class of a plugin without ``setpoint_beyond`` is trusted.)
        """
        beyond = getattr(self.drive, 'setpoint_beyond', None)
        if beyond is None:
            return
        problem = beyond(max_velocity) or beyond(-max_velocity)
        if problem:
            raise ParameterError(f'max_velocity {max_velocity:g} rad/s: {problem}')

    def addressing_interval(self) -> float:
        """Worst-case time between two requests to this drive when it runs alone on its link."""
        return max(self.config.cycle_period, self.drive.cycle_seconds()) + \
            self.drive.action_seconds()

    def plan_host_loss(self, interval: float | None = None) -> HostLossProtection:
        """Size the drive's own comm-loss protection for ``interval`` (default: alone).

        Raises ParameterError when no valid setting fits (the node refuses to
        start with the reason); the plan is written at every connect.
        """
        if interval is None:
            interval = self.addressing_interval()
        self.protection = self.drive.host_loss_plan(self.config.drive_comm_timeout, interval)
        self.link.retry_period = self._reconnect_delay()
        return self.protection

    # --- thread-safe API ------------------------------------------------------

    @property
    def loop_cycles(self) -> int | None:
        """Cycles this controller's own loop has run (None: none, e.g. a bus runs it)."""
        return self._loop.cycles if self._loop is not None else None

    @property
    def state(self) -> DriveState:
        with self._lock:
            return self._state

    def command_velocity(self, velocity: float) -> CommandOutcome:
        """Accept an output-shaft velocity (rad/s). NaN/inf never feed the watchdog."""
        if not math.isfinite(velocity):
            with self._lock:
                self._rejected += 1
            return CommandOutcome.REJECTED
        with self._lock:
            # (the limit under the lock: reconfigure bounds the command taken with it)
            limit = self.config.max_velocity
            clamped = min(max(velocity, -limit), limit)
            # A new value, or the first command after a watchdog stop, preempts the
            # cycle; a repeated one waits for it, and so does any on a link whose
            # cycle applies the commands (CANopen SYNC).
            watchdog = self._watchdog
            expired = watchdog.expired
            urgent = (clamped != self._velocity or expired) and \
                not self.drive.transport.commands_keep_the_cycle
            gap_note = self._note_command_gap(watchdog.age, watchdog.limit) if \
                self._watchdog_stopped and expired else ''
            self._watchdog_stopped = False
            self._velocity = clamped
            watchdog.feed()
            self._command_pending |= urgent
            outcome = CommandOutcome.ACCEPTED
            if clamped != velocity:
                self._clamped += 1
                outcome = CommandOutcome.CLAMPED
        if urgent and self.request_preempt is not None:
            self.request_preempt()
        if gap_note:
            log.warning('%s: %s', self.drive.hardware_id, gap_note)
        return outcome

    def _note_command_gap(self, gap: float, limit: float) -> str:
        """Count the first command after the watchdog stopped the running drive.

        Called under the lock with the gap to the command before (inf after a
        connect, a stop or a fault: those forget the commands). Counted when the
        gap is short enough to be a commander's period; a second within
        COMMAND_GAP_MEMORY is described (WARN) and returned to be logged, at most
        one line per COMMAND_GAP_MEMORY: a single pause is only counted.
        """
        if gap > max(COMMAND_GAP_FACTOR * limit, COMMAND_GAP_SPAN):
            return ''
        self._command_gaps += 1
        now = self._clock()
        times = self._command_gap_times
        times.append(now)
        if len(times) < 2 or now - times[0] > COMMAND_GAP_MEMORY:
            return ''
        self._command_gap = (f'velocity commands reached the node {gap:.2g} s apart, longer '
                             f'than command_timeout {limit:g} s: the watchdog stopped the '
                             f'drive between them ({self._command_gaps} so far); unless '
                             'the commander paused, publish them more often or raise '
                             'command_timeout')
        self._command_gap_at = now
        if now - self._command_gap_logged_at < COMMAND_GAP_MEMORY:
            return ''
        self._command_gap_logged_at = now
        return self._command_gap

    def command_setpoint(self, topic: str, value: float) -> None:
        """Accept an auxiliary setpoint (profile ``setpoints``); ParameterError if invalid.

        Validated here, written by the loop when it changes (RAM write).
        """
        code = self.drive.profile.setpoints.get(topic)
        if code is None:
            raise ParameterError(f'{quote(topic)} is not a setpoint of this drive')
        parameter = self.drive.profile.parameter(code)
        raw = parameter.to_raw(value)
        with self._lock:
            self._setpoints[code] = raw

    def parameter_writable(self, key: str) -> bool:
        """Return whether the parameter services would write this parameter at all."""
        profile = self.drive.profile
        parameter = profile.parameter(key)
        return parameter.writable and parameter.code not in profile.control_owned and \
            not self._refused_while_driven(parameter)

    def _refused_while_driven(self, parameter: Parameter) -> str:
        """Return why the node refuses to write ``parameter`` itself ('' if it does not)."""
        # what this drive writes at connect (an EtherCAT drive has its own list): where
        # the drive takes its commands and speed from, and how it reacts to the bus
        for item in getattr(self.drive, 'commissioning', self.drive.profile.commissioning):
            if item.code == parameter.code:
                if self.config.apply_commissioning:
                    return (f'it is set to {item.value:g} at every connect ({item.why}): '
                            'set apply_commissioning false to manage it yourself')
                # Managed by the integrator, still not through a running node: another
                # value may give the motor to the terminals or the keypad.
                return (f'it is part of the set-up for bus control ({item.value:g}: '
                        f'{item.why}), left to you (apply_commissioning false): set it with '
                        'vfd_params or at the keypad')
        link = getattr(self.drive, 'write_refusal', None)     # (a drive class may not say)
        return self._driver_settings.get(parameter.code, '') or (link(parameter) if link else '')

    def check_parameter_write(self, key: str, value: float) -> None:
        """Refuse a parameter write that must not reach the loop (ParameterError says why).

        Unknown names, control-owned registers, commissioning values the driver
        manages, read-only parameters and bad values are refused here, before
        anything is queued; whether the drive is running is checked again when
        the write is done.
        """
        parameter = self.drive.profile.parameter(key)
        refused = self._refused_while_driven(parameter)
        if refused:
            raise ParameterError(f'{parameter.code} is not written by this node: {refused}')
        self.drive.check_write(key, value, running=False)

    def reconfigure(self, **changes: object) -> ControllerConfig:
        """Apply live settings (``LIVE_FIELDS``) at once, all or none; ParameterError why not.

        The new settings are validated as a whole before anything changes. The
        loop reads one immutable ``ControllerConfig`` per use, and the watchdog's
        timeout changes under the same lock as the commands that feed it. A new
        ``cycle_period`` is refused when the drive's own comm-loss timeout,
        written at connect, would no longer fit (see ``check_cycle_period``).
        ``cycle_period`` only for a controller that runs its own loop (a bus sets
        its rate with ``Bus.set_rate``).
        """
        unknown = set(changes) - LIVE_FIELDS
        if unknown:
            raise ParameterError(f'not changeable at run time: {", ".join(sorted(unknown))}')
        new = replace(self.config, **changes)       # __post_init__ validates
        self._check_velocity_fits(new.max_velocity)
        replan = False
        if new.cycle_period != self.config.cycle_period:
            if self._loop is not None:
                self.check_cycle_period(new.cycle_period)
            else:       # not running (a managed node before configure): plan anew
                interval = max(new.cycle_period, self.drive.cycle_seconds()) + \
                    self.drive.action_seconds()
                self.drive.host_loss_plan(new.drive_comm_timeout, interval)   # may refuse
                replan = True
        with self._lock:
            self.config = new
            sooner = new.command_timeout < self._watchdog.timeout
            self._watchdog.timeout = new.command_timeout    # (never revives a stale command)
            # A lowered max_velocity bounds the command already taken too, at once: it
            # used to wait for the next command, and a wheel could run over the new
            # limit for up to command_timeout.
            limit = new.max_velocity
            bounded = min(max(self._velocity, -limit), limit)
            urgent = bounded != self._velocity and \
                not self.drive.transport.commands_keep_the_cycle
            self._velocity = bounded
            self._command_pending |= urgent
        if (urgent or sooner) and self.request_preempt is not None:
            self.request_preempt()      # (a loop also plans its watchdog stop anew)
        if replan:
            self.plan_host_loss()
        self.services.action_timeout = new.action_timeout
        self.services.stop_timeout = new.stop_timeout
        self.services.standstill = standstill(new, getattr(self.drive, 'scaling', None))
        if self._loop is not None:
            self._loop.set_period(new.cycle_period)
        return new

    def check_cycle_period(self, period: float, interval: float | None = None) -> None:
        """Refuse a cycle period the drive-side host-loss protection does not fit.

        ``interval`` is the new worst-case addressing interval (default: this
        drive alone at ``period``). The protection was sized and written at
        connect; a period that would need a longer one is refused (ParameterError)
        rather than left to trip the drive.
        """
        if interval is None:
            interval = max(period, self.drive.cycle_seconds()) + self.drive.action_seconds()
        plan = self.drive.host_loss_plan(self.config.drive_comm_timeout, interval)
        # A faster cycle may need a shorter timeout: the longer one written still fits
        # (the drive is addressed more often than it waits). Only a longer need trips it.
        if plan.active != self.protection.active or \
                plan.timeout > self.protection.timeout + 1e-9:
            raise ParameterError(
                f'a cycle of {period:g} s needs the drive-side protection '
                f'{plan.describe()} instead of {self.protection.describe()} written at '
                'connect: change control_rate and drive_comm_timeout with a restart')

    def submit(self, name: str, *args: object, latch: bool = True) -> Future:
        """Queue a service action; the Future resolves to an ActionResult.

        ``latch``: an operator's ``stop`` / ``disable`` holds from the moment it is
        asked (see ``ServiceActions.latch``); a managed node's own hold does not.
        """
        try:
            factory = self.services.factory(name, *args, operator=latch)
        except ParameterError as exc:
            future: Future = Future()
            future.set_result(ActionResult(False, str(exc)))
            return future
        latched = self.services.latch(name) if latch else ''
        if name in FORGETTING_ACTIONS:
            self.forget_commands()
        if latched and (not self.link.online or not self._actions.serving):
            # Not verified (nothing to ask), but held: the drive stays stopped when it
            # comes back, whatever commands keep coming.
            future = Future()
            why = NOT_SERVED if not self._actions.serving else \
                f'drive offline ({self.link.error or "not connected"})'
            future.set_result(ActionResult(False, f'{why}: {latched}: it stays stopped when '
                                                  'the link returns; ~/enable resumes'))
            return future
        return self._actions.submit(None if args else name, factory)

    def forget_commands(self) -> None:
        """Forget the velocity command taken so far: only a later one may move the drive.

        At a ~/stop or ~/disable asked (a managed deactivate asks a stop) and at a
        fault latched: with a long command_timeout, the command from before ran the
        wheel again at ~/enable, ~/reset_fault or activate (outside audit).
        Commands taken since still count: a planner still streaming wants motion.
        """
        with self._lock:
            self._watchdog.reset()
            self._watchdog_stopped = False

    def start(self) -> None:
        """Run this drive in its own thread (a bus runs several in one: see bus.py)."""
        if self._loop is None:
            self._loop = CycleLoop(f'drive {self.drive.hardware_id}', self.config.cycle_period,
                                   self.step, self.finish, self._clock,
                                   preempt=self.preempt_alone,
                                   preempt_at=self.preempt_at,
                                   priority=self.config.realtime_priority)
            self.request_preempt = self._loop.request_preempt
            self.open_for_actions()
            self._loop.start()
            self.loop_notes = self._loop.notes

    def shutdown(self, timeout: float | None = None) -> None:
        """Stop the loop; the drive is commanded to stop before the link closes.

        Waits (by default) as long as that stop can take with the drive silent: a
        loop thread given up on dies with the process (see Bus.shutdown).
        """
        if self._loop is not None:
            self._loop.stop(timeout if timeout is not None else
                            SHUTDOWN_WAIT + 2 * self.drive.transport.failed_exchange_seconds())
            self._stopped_loop_errors += self._loop.errors
            self._loop = None

    # --- one cycle, in two phases (a bus writes every drive's command first) -----

    @property
    def connect_due(self) -> bool:
        return self.link.connect_due

    def step(self) -> None:
        self.command_phase()
        self.drive.transport.end_command_burst()
        self.poll_phase()

    def command_phase(self, connect_allowed: bool = True) -> None:
        """Connect when due (and allowed: a bus chooses which drives connect), then command."""
        self._cycle_ok = False
        self.link.new_cycle()
        if connect_allowed and self.link.connect_due:
            self._connect()
        if not self.link.online:
            return
        try:
            self._write_command()
            self._write_setpoints()
            self._cycle_ok = True
        except TransportError as exc:
            self._link_failed(exc)
        except ProtocolException as exc:
            # The drive answered but refused the command: it is there, not offline.
            self.link.error = str(exc)
            self._cycle_ok = True

    def connect_now(self) -> None:
        """Connect when due, and nothing else (a bus runs it beside its cycle: see Bus)."""
        self.link.new_cycle()
        if self.link.connect_due:
            self._connect()

    def watchdog_due(self, horizon: float) -> bool:
        """Return whether the drive was told to run and its watchdog expires by ``horizon``."""
        if not (self._run_written and self.link.online):
            return False
        with self._lock:
            deadline = self._watchdog.deadline
        return deadline is not None and deadline <= horizon

    @property
    def runs(self) -> bool:
        """Return whether the last command written told the drive to run."""
        return self._run_written and self.link.online

    def preempt_at(self) -> float | None:
        """When the loop must write the stop by itself: the command watchdog's expiry.

        Only while the drive was last told to run; a small margin makes sure the
        watchdog has expired when the loop wakes.
        """
        if not (self._run_written and self.link.online):
            return None
        with self._lock:
            deadline = self._watchdog.deadline
        if deadline is None or deadline == self._preempted_deadline:
            return None         # handled once already (a failed write is the link's matter)
        return deadline + 1e-4

    def preempt(self) -> bool:
        """Write a new velocity command now, between polls (commands preempt polls).

        A watchdog that expired while the drive was told to run counts as a new
        command: the stop goes out at once, not a bus cycle later. Return whether
        a command was written (the caller ends the command burst).
        """
        if not self.link.online:
            return False
        with self._lock:
            tripped = self._run_written and self._watchdog.expired
            if tripped:
                self._preempted_deadline = self._watchdog.deadline
        if not (self._command_pending or tripped):
            return False
        try:
            self._write_command()
        except TransportError as exc:
            self._link_failed(exc)
        except ProtocolException as exc:
            self.link.error = str(exc)
        return True

    def preempt_alone(self) -> None:
        """``preempt`` for a drive that runs in its own loop: then end the burst."""
        if self.preempt():
            self.drive.transport.end_command_burst()

    def poll_phase(self) -> None:
        """Read the status, latch faults, advance a service action, publish the state."""
        if self.link.online and self._cycle_ok:
            config = self.config
            self.drive.display_period = display_period(config.shown_period, config.cycle_period)
            try:
                polled_at = self._clock()
                gap = None if self._polled_at is None else polled_at - self._polled_at
                self._polled_at = polled_at
                self._reading = self.drive.poll(self._cycle, preempt=self._preempt_reads)
                self._cycle += 1
                if gap is not None:
                    self._check_addressing(gap)
                self._check_fault()
                self._check_unexpected_motion()
                self._check_settings()
                self._check_following()
                self._actions.advance()
                self.link.cycle_ok()
            except TransportError as exc:
                self._link_failed(exc)
        if not self.link.online:
            held = '; a ~/stop or ~/disable asked holds until ~/enable' \
                if self.intent.asked_stop else ''
            self._actions.fail_all(f'drive offline: {self.link.error or "not connected"}{held}')
        self._publish_state()

    def write_stop(self, quietly: bool = False) -> bool:
        """Write the stop now; return whether the drive took it.

        A failure is logged, unless ``quietly`` (Bus.finish tries once more).
        """
        if not self.link.online:
            return False
        try:
            self._send_stop()
        except VfdError as exc:
            if quietly:
                pass
            elif getattr(self.drive, 'asserted_command', None) == 'stop':
                log.warning('%s at shutdown: the stop command is written, but %s',
                            self.drive.hardware_id, exc)
            else:
                log.warning('could not stop %s at shutdown: %s', self.drive.hardware_id, exc)
            return False
        return True

    def _send_stop(self) -> None:
        """Write the stop, whatever the driver believes the drive is doing (VfdError)."""
        self.drive.forget_state()
        self.drive.apply(0.0, run=False, idle_action='stop')
        self.drive.transport.end_command_burst()     # a SYNC-driven drive needs it

    def finish(self, stop: bool = True) -> None:
        """End of the loop: command the drive to stop (unless written already), close the link."""
        if stop:
            self.write_stop()
        self.drive.close()
        self.link.closed()
        self._actions.close('the control loop ended before this action ran')

    def age_of(self, state: DriveState) -> float:
        """Return s since ``state`` was taken (NaN for one built before any cycle)."""
        return self._clock() - state.read_at

    @property
    def serving_actions(self) -> bool:
        """Whether a loop (its own or a bus's) serves service actions now."""
        return self._actions.serving

    def open_for_actions(self) -> None:
        """Queue service actions from now on: a loop (its own or a bus's) serves them."""
        self._actions.open()

    def mark_closed(self, reason: str) -> None:
        """Publish an offline snapshot after the loop ended (a managed node's cleanup).

        Without it ``state`` keeps the last cycle's (online, maybe running) until
        the loop runs again; ``reason`` says why the link is closed (not a comm loss).
        Call only while no loop runs this controller.
        """
        self.link.closed(reason)
        self._reading = Reading()
        self._publish_state()

    # --- internals -----------------------------------------------------------------

    def _protection_written(self) -> HostLossProtection:
        """Return the drive-side protection as the last connect set it (none before any)."""
        if self.link.first_connect:
            return replace(self.protection, mechanism='', timeout=0.0,
                           note='not written yet: the drive has not been connected')
        return self.protection_applied or self.protection

    def _commands_fresh(self) -> bool:
        with self._lock:
            return not self._watchdog.expired

    def _conditions(self) -> Conditions:
        with self._lock:
            watchdog = self._watchdog
            expired, age, limit = watchdog.expired, watchdog.age, watchdog.limit
        return Conditions(online=self.link.online, link_error=self.link.error,
                          link_closed=self.link.closed_reason, fault=self._reading.fault,
                          unsafe=self._reading.unsafe,
                          watchdog_expired=expired, watchdog_age=age, command_timeout=limit)

    def _write_command(self) -> None:
        with self._lock:
            velocity = self._velocity
            self._command_pending = False
        state = decide(self.intent, self._conditions())[0]
        run = state is RunState.RUNNING
        services = self.services
        reassert = services.reassert_run if run else services.reassert_idle
        services.reassert_idle = services.reassert_run = False
        try:
            self.drive.apply(velocity, run, self.intent.idle_action, reassert=reassert)
        except (ProtocolException, TransportError) as exc:
            if getattr(self.drive, 'asserted_command', None) == self.intent.idle_action:
                # the stop went out, the zero setpoint did not; or a running drive that
                # refused its new setpoint was idled (ModbusDrive.apply)
                self._run_written = False
            if isinstance(exc, TransportError):
                raise
            # The drive answered but refused: not a link failure, and not to be lost in
            # link.error while online. Shown in ~/status and /diagnostics (WARN) until
            # a command write succeeds; logged once per reason.
            refused = f'command write refused: {exc}'
            if refused != self._command_refused:
                log.warning('%s: %s', self.drive.hardware_id, refused)
            self._command_refused = refused
            raise
        self._command_refused = ''
        if self._run_written and state is RunState.WATCHDOG:
            with self._lock:
                self._watchdog_stopped = True     # a run withdrawn for want of commands
        self._run_written = run
        if run:
            self._run_asked_at = self._clock()

    def _write_setpoints(self) -> None:
        with self._lock:
            pending = {code: raw for code, raw in self._setpoints.items()
                       if self._written_setpoints.get(code) != raw}
        for code, raw in pending.items():
            self.drive.write_setpoint_parameter(code, raw)
            self._written_setpoints[code] = raw

    def _preempt_reads(self) -> None:
        if self.preempt_hook is not None:
            self.preempt_hook()
        else:
            self.preempt_alone()

    def _connect(self) -> None:
        drive = self.drive
        try:
            drive.forget_state()
            drive.open()
            # Start-up never moves the motor: zero setpoint and idle first.
            drive.apply(0.0, run=False, idle_action=self.intent.idle_action)
            self._run_written = False
            problems = drive.configure(self.protection, self.config.apply_commissioning)
        except VfdError as exc:
            drive.close()
            self.link.connect_failed(exc)
            return
        for problem in problems:
            # A setting the drive refuses must not keep it offline: report and go on.
            log.error('%s: not applied at connect: %s', drive.hardware_id, problem)
        if self.link.first_connect and self.protection.weaker_than_requested:
            log.warning('%s: drive-side host-loss protection %s (drive_comm_timeout %g s '
                        'requested)', drive.hardware_id, self.protection.describe(),
                        self.config.drive_comm_timeout)
        self._settings_refused = tuple(problems)
        note = getattr(drive, 'nameplate_note', '')       # (a Modbus drive compares them)
        if note and (note,) != self._nameplate_notes:
            log.warning('%s: %s', drive.hardware_id, note)
        self._nameplate_notes = (note,) if note else ()
        # A drive may refuse (part of) the planned protection and say what holds;
        # Drive.protection_applied is optional (None: the plan holds as written).
        self.protection_applied = getattr(drive, 'protection_applied', None)
        self._written_setpoints.clear()   # re-send auxiliary setpoints after a reconnect
        with self._lock:
            self._watchdog.reset()   # never resume from a command older than the link
        self._last_running = False
        self._running_idle_since, self._running_idle_counted = None, False
        self._not_stopping = ''         # (nothing was written while it was offline)
        self._off_command_since, self._not_following = None, ''
        self._polled_at, self._near_trips, self._raise_refused = None, 0, 0.0
        self._check_comm_fault = True
        self._exchange_failed, self._settings_checked_at = False, self._clock()
        # Online from here, but nothing is known of the drive's state until a status
        # read succeeds (the first may fail): hold it idle, never report "no fault".
        self._reading = Reading(unsafe=STATUS_NOT_READ)
        self.link.connected()
        self._note_near_trip()          # (what was written counts from here: connected)

    def _check_addressing(self, gap: float, urgent: bool = False) -> None:
        """Raise the drive's comm-loss timeout when its cycle nears it (``gap``: s unpolled).

        The plan sizes the timeout from the wire time of a cycle; a drive that takes
        tens of ms to reply (legal within transport.timeout), or a loaded bus, stretches
        the cycle until the drive trips its own comm-loss fault although the host never
        fell silent. Two gaps in a row beyond NEAR_TRIP of the timeout (one is a hiccup),
        or one that is ``urgent`` (the bus found the drive about to trip mid-cycle), have
        it re-planned for the gap and written (logged; ~/status and /diagnostics show it
        weaker than requested, and why). A gap past the timeout is a stall the drive has
        answered with its comm-loss fault: raising would prevent nothing. Never lowered
        while the node runs; a raise the drive or the register refuses is not tried again
        until the next connect.
        """
        if gap <= self._near_trip_after:        # (every cycle: the one comparison)
            self._near_trips = 0
            return
        written = self._protection_written()
        if gap >= written.timeout:
            self._near_trips = 0
            return
        self._near_trips += 1
        if self._near_trips < 2 and not urgent:
            return
        try:
            plan = self.drive.host_loss_plan(self.config.drive_comm_timeout,
                                             gap * ADDRESSING_HEADROOM)
        except ParameterError as exc:           # beyond what the register takes
            self._refuse_raise(math.inf, gap, exc)
            return
        if not plan.active or plan.timeout <= max(written.timeout, self._raise_refused):
            return
        plan = replace(plan, note=f'raised from {written.timeout:g} s: {gap:.2f} s passed '
                       'between two polls (slow replies or a loaded link)' +
                       (f'; {plan.note}' if plan.note else ''))
        try:
            self.drive.refresh_host_loss(plan)
        except ProtocolException as exc:
            self._refuse_raise(plan.timeout, gap, exc)
            return
        self.protection, self.protection_applied = plan, None
        self._near_trips = 0
        self._note_near_trip()
        log.warning('%s: host-loss protection %s', self.drive.hardware_id, plan.describe())

    def _refuse_raise(self, target: float, gap: float, exc: VfdError) -> None:
        """Remember a raise that cannot be written (until the next connect), and say so once."""
        self._raise_refused = target
        log.error('%s: the comm-loss timeout cannot be raised for a cycle of %.2f s (%s): the '
                  'drive may trip its comm-loss fault', self.drive.hardware_id, gap, exc)

    def _note_near_trip(self) -> None:
        """Note how long the drive may go unpolled before ``_check_addressing`` acts (inf: never).

        Only a drive whose comm-loss timeout can be written while it runs
        (``refresh_host_loss``) and is written (active).
        """
        written = self._protection_written()
        self._near_trip_after = NEAR_TRIP * (written.timeout - HOST_LOSS_JITTER) \
            if written.active and hasattr(self.drive, 'refresh_host_loss') else math.inf

    def keep_alive_at(self) -> float:
        """When this drive, unpolled until then, nears its comm-loss timeout (inf: never).

        On a bus the others' exchanges come between two polls of a drive: when
        their replies are slow, one cycle can outlast its timeout. The bus asks
        this before each exchange and calls ``keep_alive`` once it has come.
        """
        if self._polled_at is None or not self.link.online:
            return math.inf
        return self._polled_at + self._near_trip_after

    def keep_alive(self) -> None:
        """Raise the comm-loss timeout of a drive about to go unaddressed too long, now.

        The write addresses the drive (any valid request restarts its timer), so
        the time since it was addressed starts again from here.
        """
        if self._polled_at is None or not self.link.online:
            return
        now = self._clock()
        try:
            self._check_addressing(now - self._polled_at, urgent=True)
        except TransportError as exc:
            self._link_failed(exc)
            return
        self._polled_at = now

    def _reconnect_delay(self) -> float:
        """Keep a drive with a comm-loss timeout addressed within it while reconnecting.

        A short glitch then never lets the drive's own timer expire; a drive that
        is really gone costs its link one failed exchange per attempt.
        """
        delay = self.config.reconnect_period
        if self.protection.active:
            delay = min(delay, self.protection.timeout / 3)
        return delay

    def _link_failed(self, exc: VfdError) -> None:
        self._polled_at = None      # a gap while the link fails is not the cycle's
        self._exchange_failed = True
        if self.link.cycle_failed(exc):
            self._reading = Reading()
            # A drive the link lost may still hear it (its heartbeat or TPDOs gone, a
            # broken receive wire): the stop goes out once, hurried, before the link
            # closes. It ran on its last command until the reconnect's stop, seconds
            # later behind a neighbour's slow connect (outside audit: 3-8 s).
            try:
                with self.drive.transport.hurried():
                    self._send_stop()
            except VfdError as stop_failed:
                log.debug('%s: no stop before closing the link: %s', self.drive.hardware_id,
                          stop_failed)
            self.drive.close()

    def _check_fault(self) -> None:
        fault = self._reading.fault
        first_after_connect, self._check_comm_fault = self._check_comm_fault, False
        if not fault.active or self.intent.fault_latched:
            return
        # The fault the drive raises when the host falls silent: the drive class may
        # name it for its bus (EtherCAT: the SM watchdog's), else the profile's.
        spec = self.drive.profile.comm_timeout
        own = getattr(self.drive, 'own_absence_fault', None)
        guessed = False
        if own is None and spec is not None:
            own = (spec.fault_code, spec.fault_subcode)
            entry = self.drive.profile.faults.table.get(spec.fault_code)
            guessed = entry is not None and entry.confidence == 'low'
        own_absence = own is not None and (fault.code, fault.subcode) == tuple(own)
        if own_absence and first_after_connect and guessed:
            # A number the manual does not print (Veichi: the fault table's row, outside
            # audit) may be another fault's, an overcurrent trip: it is not reset unasked.
            log.warning('%s: %s %s found at connect is not reset by itself: the profile '
                        "only guesses this fault's number (confidence low), so it may be "
                        'another fault; ~/reset_fault clears it', self.drive.hardware_id,
                        fault.display, fault.name)
            own_absence = False
        if own_absence and first_after_connect:
            # The drive stopped itself because this host was silent (a restart, an
            # unplugged cable): the stop is written, so the fault is reset once.
            self._comm_fault_grace_until = self._clock() + self.config.action_timeout
            self._comm_faults_cleared += 1
            log.warning('%s: reset %s %s found at connect: the drive stopped itself because '
                        'the host was silent', self.drive.hardware_id, fault.display, fault.name)
            self.drive.send_command('fault_reset')
            return
        if own_absence and self._clock() < self._comm_fault_grace_until:
            return       # the reset sent at connect is still taking effect
        self.intent.fault_latched = True
        self.forget_commands()
        log.warning('%s fault %s %s', self.drive.hardware_id, fault.display, fault.name)

    def _check_not_stopping(self, now: float) -> None:
        """Report a drive held idle that still reports running after stop_timeout.

        The idle command goes out every cycle; a drive that does not obey it (a local
        run source, a stuck run input, a write acknowledged and not applied) runs on
        while the status said "watchdog" or "stopped" with OK diagnostics. Counted
        once in unexpected_starts (unless it started so), logged, and shown in
        ~/status and /diagnostics (ERROR) until it stops.

        A drive still ramping down (a CiA 402 drive stays in operation enabled through
        its ramp) was counted and shown as one (outside audit): one whose speed, at the
        rate it fell over the last stop_timeout, reaches zero within RAMP_WINDOWS more
        is given those (a warning); past them, or falling slower, it is the ERROR, and
        not counted as a start while it falls (a ramp cannot be told from a runaway
        drifting down: the re-check's drifted for 30 s unreported).
        """
        speed = abs(self._reading.measured_velocity)     # (NaN: not measured)
        if self._running_idle_since is None:
            self._running_idle_since, self._running_idle_speed = now, speed
            self._ramp_windows = 0
        if self._not_stopping or now - self._running_idle_since <= self.config.stop_timeout:
            return
        fall = self._running_idle_speed - speed
        if fall > 0 and speed <= RAMP_WINDOWS * fall and self._ramp_windows < RAMP_WINDOWS:
            if not self._ramp_windows:
                log.warning('%s: held idle, the drive is still ramping down (%.3g rad/s) '
                            'after stop_timeout %g s: its deceleration is slower than '
                            'stop_timeout allows', self.drive.hardware_id, speed,
                            self.config.stop_timeout)
            self._ramp_windows += 1
            self._running_idle_since, self._running_idle_speed = now, speed
            return
        elapsed = now - self._running_idle_since + self._ramp_windows * self.config.stop_timeout
        if fall > 0:            # falling, too slowly (or too long) for a ramp
            self._not_stopping = (
                f'held idle, the drive has reported running for {elapsed:.3g} s, more than '
                f'stop_timeout {self.config.stop_timeout:g} s, its speed falling slowly '
                f'({speed:.3g} rad/s now): a deceleration far slower than stop_timeout '
                'allows, or a run source elsewhere (keypad, terminals): stop it locally')
        else:
            self._not_stopping = (
                f'held idle, the drive has reported running for more than stop_timeout '
                f'{self.config.stop_timeout:g} s although the idle command is written every '
                'cycle: stop it locally, and look for another run source (keypad, '
                'terminals) or a stuck run input')
            if not self._running_idle_counted:
                self._unexpected_starts += 1
                self._running_idle_counted = True
        log.error('%s: %s', self.drive.hardware_id, self._not_stopping)

    def _check_unexpected_motion(self) -> None:
        running = self._reading.flags.get('running', False)
        if running and not self._run_written:
            # Whatever was written last, the drive runs although the host has it
            # idle (a start from elsewhere, or a lost stop): write the idle command again.
            self.services.reassert_idle = True
            # A run asked for a cycle ago may show only now (withdrawn at once by a short
            # command_timeout, say): that start was the host's own.
            # Nor is one the host wants by now (enabled again since the idle write).
            now = self._clock()
            wanted = decide(self.intent, self._conditions())[0]
            if not self._last_running and wanted is not RunState.RUNNING and \
                    now - self._run_asked_at > 2 * self.addressing_interval():
                self._unexpected_starts += 1
                self._running_idle_counted = True
                log.warning('%s reports running although the host has it %s: idle command '
                            'written again', self.drive.hardware_id, wanted.label)
            self._check_not_stopping(now)
        else:
            self._running_idle_since, self._running_idle_counted = None, False
            self._not_stopping = ''
        self._last_running = running
        # The other way round: told to run, the drive does not (it reset, was stopped
        # at its keypad, an inhibit): report it rather than show "running" with OK
        # diagnostics. It is not restarted behind an operator's back: ~/enable writes
        # the run command again. Only at a setpoint other than zero: some drives do not
        # run at zero speed by design (Kinco EC with A0.19 = 0).
        if running or not self._run_written or not self.drive.last_setpoint_raw:
            self._not_running_since, self._lost_run = None, ''
            return
        now = self._clock()
        if self._not_running_since is None:
            self._not_running_since = now
        elif not self._lost_run and now - self._not_running_since > self.config.action_timeout:
            # Settings lost as well: it reset. Connected afresh (stop first, settings
            # written again), it runs on fresh commands, as a CANopen node that sent a
            # boot-up does; with its settings intact it was stopped by other means.
            settings_lost = getattr(self.drive, 'settings_lost', None)
            lost = settings_lost() if settings_lost is not None else ''
            if lost:
                self._connect_afresh(f'it stopped running and {lost}')
                return
            self._lost_run = (f'told to run, the drive has reported not running for '
                              f'{self.config.action_timeout:g} s (it reset, was stopped '
                              'locally, or is inhibited): call ~/enable to write the run '
                              'command again')
            log.warning('%s: %s', self.drive.hardware_id, self._lost_run)

    def _check_settings(self) -> None:
        """Read back the settings written at connect; a drive that lost them reset.

        An idle drive that reset within the comm-loss threshold (a short brown-out)
        came back with its factory settings, without the host-loss protection
        ~/status showed for it (outside audit), and a long bus cycle can hide a
        whole reset. All of them after a failed exchange (at most every
        SETTINGS_CHECK_AFTER_FAILURE), one in turn every SETTINGS_CHECK_PERIOD
        otherwise. A drive that lost them is connected afresh: the stop first,
        then its settings, and it runs only on the commands that come after.
        """
        settings_lost = getattr(self.drive, 'settings_lost', None)
        if settings_lost is None or not self.link.online:
            return
        now, after_failure = self._clock(), self._exchange_failed
        due = SETTINGS_CHECK_AFTER_FAILURE if after_failure else SETTINGS_CHECK_PERIOD
        if now - self._settings_checked_at < due:
            return
        self._exchange_failed, self._settings_checked_at = False, now
        lost = settings_lost(one=not after_failure)
        if lost:
            self._connect_afresh(lost)

    def _connect_afresh(self, lost: str) -> None:
        """Take a drive that reset offline: the next connect stops it and writes its settings."""
        self.link.drop(f'the drive reset: {lost}')
        self._reading = Reading()
        self.drive.close()

    def _check_following(self) -> None:
        """Tell a drive that runs but does not reach its command, for as long as it does not.

        Running and off its command (beyond ``_following_band``, or not turning, or
        turning the wrong way), with the measured speed (smoothed) no nearer the
        command by twice the standstill band for stop_timeout: a speed or torque limit
        in the drive, a command below its start frequency, a blocked wheel, a mode that
        ignores the speed setpoint. A velocity limit written
        to 0 stalled a wheel that said "running" with OK diagnostics while its robot
        veered (outside audit). Progress is the measured speed moving towards the
        command, not the command moving: a ramp longer than stop_timeout, or reversed
        in the middle, progresses; a stalled wheel under a command that varies or
        falls towards it does not (re-checks). A WARN, cleared once it follows or
        progresses; nothing is stopped: the wheel obeys what the drive allows.
        """
        reading = self._reading
        measured = reading.measured_velocity
        with self._lock:
            commanded = self._velocity
        still = self.services.standstill
        off = math.isfinite(measured) and (
            abs(measured - commanded) > self._following_band(commanded) or
            abs(commanded) > 2 * still and (abs(measured) <= still or measured * commanded < 0))
        if not (reading.flags.get('running', False) and self._run_written and off):
            self._off_command_since, self._not_following = None, ''
            return
        now = self._clock()
        direction = math.copysign(1.0, commanded - measured)
        if self._off_command_since is None:
            self._off_command_since, self._off_direction = now, direction
            self._off_command = self._off_smoothed = measured
            self._off_polled = now
            return
        # The speed smoothed over FOLLOWING_SMOOTHING s: a reading's noise (a motor at
        # rest read as 1-3 rpm) is no progress (re-check: a noisy stall under a command
        # of alternating sign was never told).
        weight = 1.0 - math.exp(-(now - self._off_polled) / FOLLOWING_SMOOTHING)
        self._off_smoothed += weight * (measured - self._off_smoothed)
        self._off_polled = now
        if direction != self._off_direction:
            # The command crossed the speed: aimed anew from here, which is no progress.
            self._off_direction, self._off_command = direction, self._off_smoothed
        elif (self._off_smoothed - self._off_command) * direction >= 2 * still:
            self._off_command_since, self._off_command = now, self._off_smoothed  # (progress)
            self._not_following = ''
            return
        if now - self._off_command_since > self.config.stop_timeout:
            told = bool(self._not_following)
            self._not_following = (
                f'running at {measured:.3g} rad/s against a command of {commanded:g} rad/s, '
                f'no nearer for over {self.config.stop_timeout:g} s (stop_timeout): a speed '
                'or torque limit in the drive (a velocity limit parameter), a command below '
                'its start or minimum frequency, a blocked wheel, or a mode that does not '
                'follow the speed setpoint')
            if not told:
                log.warning('%s: %s', self.drive.hardware_id, self._not_following)

    def _following_band(self, commanded: float) -> float:
        """Return how far (rad/s) a running drive may miss ``commanded`` as following it.

        The standstill band and FOLLOWING_SHARE of the command; where the setpoint is
        a frequency (the drive does not control the shaft speed), up to SLIP_SHARE of
        the motor's nominal speed more for a loaded induction motor's slip (the AM's
        1330 rpm rated at 1500 synchronous is 11 %), but never more than half the
        command: a wheel that does not turn is off its command at any speed.
        """
        band = max(self.services.standstill, FOLLOWING_SHARE * abs(commanded))
        scaling = getattr(self.drive, 'scaling', None)
        velocity = self.drive.profile.velocity
        if scaling is not None and (velocity.setpoint_unit is SpeedUnit.HZ or (
                velocity.setpoint_unit is SpeedUnit.PERCENT and velocity.rated_frequency)):
            slip = abs(scaling.motor_rpm_to_output(SLIP_SHARE * scaling.rated_speed_rpm))
            band = max(band, min(band + slip, 0.5 * abs(commanded)))
        return band

    # --- snapshot ---------------------------------------------------------------

    @property
    def loop_errors(self) -> int:
        loop = self._loop
        return self._actions.errors + self._stopped_loop_errors + \
            (loop.errors if loop is not None else 0)

    def _publish_state(self) -> None:
        reading = self._reading
        stats = self.drive.stats
        conditions = self._conditions()
        with self._lock:
            rejected, clamped, gaps = self._rejected, self._clamped, self._command_gaps
            gap, gap_at = self._command_gap, self._command_gap_at
        run_state, reason = decide(self.intent, conditions)
        commanded = self._velocity if run_state is RunState.RUNNING else 0.0
        if run_state is RunState.RUNNING and (reading.stuck or self._lost_run):
            # Commanded to run, but the drive does not get there (e.g. CiA 402 stuck).
            run_state, reason = RunState.BLOCKED, reading.stuck or self._lost_run
        not_stopping = self._not_stopping if run_state is not RunState.RUNNING and \
            self.link.online else ''
        if not_stopping:
            reason = f'{reason}; {not_stopping}' if reason else not_stopping
        flags = reading.flags
        measured = reading.measured_velocity
        joint = self.joint
        read_at = self._clock()
        joint.update(reading, read_at, self.link.online)
        running = flags.get('running', False)
        at_speed = flags.get('at_speed', running and math.isfinite(measured) and
                             abs(measured - commanded) <= self.config.at_speed_tolerance)
        snapshot = DriveState(
            hardware_id=self.drive.hardware_id,
            online=self.link.online,
            ready=flags.get('ready', False),
            enabled=self.intent.enabled and not self.intent.stopped,
            running=running,
            reverse=flags.get('reverse', False),
            fault=reading.fault.active,
            warning=flags.get('warning', reading.warning_code != 0),
            at_speed=at_speed,
            watchdog_tripped=run_state is RunState.WATCHDOG,
            run_state=run_state,
            stop_reason=reason,
            status_words=tuple(reading.raw_words.items()),
            commanded_velocity=commanded,
            measured_velocity=measured,
            setpoint_raw=self.drive.last_setpoint_raw,
            measured=dict(reading.values),
            position=joint.position,
            position_source=joint.config.source,
            effort=joint.effort,
            active_fault=reading.fault,
            warning_code=reading.warning_code,
            warning_subcode=reading.warning_subcode,
            transactions=stats.transactions,
            comm_errors=stats.errors,
            timeouts=stats.timeouts,
            bad_frames=stats.bad_frames,
            exceptions=stats.exceptions,
            reconnects=self.link.reconnects,
            late_replies=stats.late_replies,
            rejected_commands=rejected,
            clamped_commands=clamped,
            unexpected_starts=self._unexpected_starts,
            comm_faults_cleared=self._comm_faults_cleared,
            loop_errors=self.loop_errors,
            link_error=self.link.error,
            link_closed=self.link.closed_reason,
            protection=self._protection_written(),
            unavailable=tuple(reading.unavailable.values()) + self._settings_refused
            + ((self._command_refused,) if self._command_refused else ()),
            link_notes=self.drive.transport.link_notes + self.loop_notes + self._nameplate_notes,
            read_at=read_at,
            not_stopping=not_stopping,
            not_following=self._not_following if running else '',
            command_gaps=gaps,
            command_gap=gap if read_at - gap_at < COMMAND_GAP_MEMORY else '',
        )
        with self._lock:
            self._state = snapshot
