"""The drive loop: one thread that owns the link to one drive.

Commands arrive from any thread (``command_velocity``, ``submit``); only the
loop thread touches the transport. Each cycle writes the command first, then
polls status, then advances at most one pending service action one step, so a
slow verification never holds up the watchdog or the status.

Safety rules kept here, in one place:
- start-up and every reconnect write a zero setpoint and the idle command
  before anything else, and forget all earlier velocity commands;
- the drive runs only while enabled, not stopped, fault-free, online, its run
  and fault state readable, and fed with fresh commands (the command watchdog):
  one rule, ``_permit``, decides both what is written and what is reported;
- after a fault motion resumes only after a successful ``reset_fault``; the one
  exception is the drive's own comm-loss fault found at connect, which the
  driver's absence caused: it is reset once the stop is written;
- a drive that reports running while the host has it idle gets the idle command
  again every cycle (counted as an unexpected start), whatever was sent last;
- the drive's own comm-loss timeout is sized for the bus it is on
  (``plan_host_loss``), and reported.
"""

from __future__ import annotations

import enum
import logging
import math
import queue
import threading
import time
from concurrent.futures import Future
from dataclasses import dataclass, field
from typing import Callable, Generator, Iterator

from .drive import Drive, HostLossProtection, ParameterValue, Reading
from .errors import ParameterError, ProtocolException, TransportError, VfdError, quote
from .faults import NO_FAULT, FaultInfo
from .watchdog import CommandWatchdog


class RunState(enum.IntEnum):
    """Why the drive does or does not follow velocity commands (DriveStatus.STATE_*)."""

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

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class ControllerConfig:
    command_timeout: float = 0.5      # s without a valid command -> stop
    max_velocity: float = 10.0        # rad/s at the output shaft; commands are clamped
    cycle_period: float = 0.02        # s per control cycle
    comm_loss_threshold: int = 2      # consecutive failed cycles -> offline
    reconnect_period: float = 0.5     # s between reconnect attempts
    drive_comm_timeout: float = 0.3   # s, written to the drive's own watchdog; 0 = off
    apply_commissioning: bool = True  # write the profile's bus-control settings
    auto_enable: bool = False         # enable at start-up (still needs fresh commands)
    action_timeout: float = 2.0       # s to verify enable / reset
    stop_timeout: float = 10.0        # s to verify stop / disable (deceleration)
    at_speed_tolerance: float = 0.1   # rad/s

    def __post_init__(self) -> None:
        for name in ('command_timeout', 'cycle_period', 'reconnect_period', 'action_timeout',
                     'stop_timeout'):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ParameterError(f'{name} must be > 0, got {value}')
        if not (math.isfinite(self.max_velocity) and self.max_velocity > 0):
            raise ParameterError(f'max_velocity must be > 0, got {self.max_velocity}')
        if not (math.isfinite(self.drive_comm_timeout) and self.drive_comm_timeout >= 0):
            raise ParameterError(f'drive_comm_timeout must be >= 0, got {self.drive_comm_timeout}')
        if self.comm_loss_threshold < 1:
            raise ParameterError('comm_loss_threshold must be >= 1')


class CommandOutcome(enum.Enum):
    ACCEPTED = 'accepted'
    CLAMPED = 'clamped'
    REJECTED = 'rejected'


@dataclass(frozen=True)
class ActionResult:
    success: bool
    message: str
    value: ParameterValue | None = None


@dataclass(frozen=True)
class DriveState:
    """A consistent snapshot of everything the node publishes."""

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
    mode: RunState = RunState.OFFLINE
    stop_reason: str = 'not connected yet'
    status_words: tuple[tuple[str, int], ...] = ()
    commanded_velocity: float = 0.0
    measured_velocity: float = math.nan
    setpoint_raw: int = 0
    measured: dict[str, float] = field(default_factory=dict)
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
    last_error: str = ''
    protection: HostLossProtection = HostLossProtection()
    unavailable: tuple[str, ...] = ()      # values and settings the drive refuses

    @property
    def state(self) -> str:
        """The run state as one lower-case word (DriveStatus.state)."""
        return self.mode.label


Action = Generator[None, None, ActionResult]



class CycleLoop:
    """Calls ``step`` every ``period`` seconds in its own thread, then ``finish``.

    Between cycles, ``wake()`` (e.g. a new velocity command) runs ``urgent`` at
    once instead of waiting for the next period: commands preempt polls without
    raising the poll rate. An exception in ``step`` is logged and the loop goes
    on: nothing may stop the thread that keeps a traction drive under control.
    An overrun restarts the schedule instead of bursting to catch up.
    """

    def __init__(self, name: str, period: float, step: Callable[[], None],
                 finish: Callable[[], None], clock: Callable[[], float] = time.monotonic,
                 urgent: Callable[[], None] | None = None) -> None:
        self.name = name
        self.period = period
        self._step = step
        self._finish = finish
        self._urgent = urgent
        self._clock = clock
        self._stop = threading.Event()
        self._wake = threading.Event()
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        self.overruns = 0
        self.errors = 0

    def start(self) -> None:
        self._thread.start()

    def wake(self) -> None:
        """Run ``urgent`` now (thread-safe; a no-op without ``urgent``)."""
        if self._urgent is not None:
            self._wake.set()

    def stop(self, timeout: float = 2.0) -> None:
        self._stop.set()
        self._wake.set()
        if self._thread.is_alive():
            self._thread.join(timeout)

    def _guarded(self, call: Callable[[], None]) -> None:
        try:
            call()
        except Exception as exc:  # noqa: BLE001 - the loop must survive anything
            self.errors += 1
            log.exception('%s: loop error: %s', self.name, exc)

    def _run(self) -> None:
        next_cycle = self._clock()
        while not self._stop.is_set():
            self._guarded(self._step)
            next_cycle += self.period
            if next_cycle - self._clock() < -self.period:
                self.overruns += 1
                next_cycle = self._clock()
            while not self._stop.is_set():
                delay = next_cycle - self._clock()
                if delay <= 0 or not self._wake.wait(delay):
                    break
                self._wake.clear()
                if self._urgent is not None and not self._stop.is_set():
                    self._guarded(self._urgent)
        self._guarded(self._finish)


class DriveController:
    """Runs one drive: connect, command, poll, watchdog, service actions."""

    def __init__(self, drive: Drive, config: ControllerConfig,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.drive = drive
        self.config = config
        self._clock = clock
        self._lock = threading.Lock()
        self._watchdog = CommandWatchdog(config.command_timeout, clock)
        self._velocity = 0.0
        self._setpoints: dict[str, int] = {}
        self._written_setpoints: dict[str, int] = {}
        self._rejected = 0
        self._clamped = 0
        self._enabled = config.auto_enable
        self._stopped = False
        self._fault_latched = False
        self._idle_action = 'stop'
        self._online = False
        self._was_online = False
        self._reconnects = 0
        self._failed_cycles = 0
        self._next_connect = 0.0
        self._cycle = 0
        self._last_error = ''
        self._reading = Reading()
        self._settings_refused: tuple[str, ...] = ()
        # (coalescing key or None, factory, future); trigger actions asked again while
        # one is waiting are answered with its result (a burst of ~/enable calls).
        self._actions: queue.SimpleQueue[tuple[str | None, Callable[[], Action], Future]] = \
            queue.SimpleQueue()
        self._backlog: list[tuple[str | None, Callable[[], Action], Future]] = []
        self._action_factories: dict[str, Callable[..., Action]] = {
            'enable': self._action_enable, 'disable': self._action_disable,
            'stop': self._action_stop, 'reset_fault': self._action_reset_fault,
            'get_parameter': self._action_get_parameter,
            'set_parameter': self._action_set_parameter}
        self._current: tuple[Iterator[None], list[Future]] | None = None
        self._loop: CycleLoop | None = None
        self._cycle_ok = False
        self._command_pending = False
        self._failed_this_cycle = False
        self._run_written = False        # what the last command write asked: run or idle
        self._reassert_idle = False      # the drive runs although the host has it idle
        self._last_running = False
        self._unexpected_starts = 0
        self._comm_fault_check = False   # the first reading after a connect is not read yet
        self._comm_fault_grace_until = -math.inf
        self._comm_faults_cleared = 0
        self._action_errors = 0
        self._stopped_loop_errors = 0
        self.protection = self.plan_host_loss(0.0)
        #: what the last connect could set (a drive may refuse part of the plan)
        self.protection_applied: HostLossProtection | None = None
        #: called when a command should be written before the next cycle (set by the
        #: loop that runs this controller: its own, or a bus's)
        self.wake: Callable[[], None] | None = None
        #: run before each status read instead of this drive's own pending command
        #: (a bus writes every drive's new command first)
        self.between_reads: Callable[[], None] | None = None
        self._state = DriveState(hardware_id=drive.hardware_id, protection=self.protection)

    # --- sizing -------------------------------------------------------------------

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
        if self.protection.weaker_than_requested:
            log.warning('%s: drive-side host-loss protection %s (drive_comm_timeout %g s '
                        'requested)', self.drive.hardware_id, self.protection.describe(),
                        self.config.drive_comm_timeout)
        return self.protection

    # --- thread-safe API ------------------------------------------------------

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
        limit = self.config.max_velocity
        clamped = min(max(velocity, -limit), limit)
        with self._lock:
            # A new value, or the first command after a watchdog stop, is written at
            # once (see write_pending_command); a repeated one waits for the cycle.
            urgent = clamped != self._velocity or self._watchdog.expired
            self._velocity = clamped
            self._watchdog.feed()
            self._command_pending |= urgent
            outcome = CommandOutcome.ACCEPTED
            if clamped != velocity:
                self._clamped += 1
                outcome = CommandOutcome.CLAMPED
        if urgent and self.wake is not None:
            self.wake()
        return outcome

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

    def check_parameter_write(self, key: str, value: float) -> None:
        """Refuse a parameter write that must not reach the loop (ParameterError says why).

        Unknown names, control-owned registers, commissioning values the driver
        manages, read-only parameters and bad values are refused here, before
        anything is queued; whether the drive is running is checked again when
        the write is done.
        """
        profile = self.drive.profile
        parameter = profile.parameter(key)
        if self.config.apply_commissioning:
            for item in profile.commissioning:
                if item.code == parameter.code:
                    raise ParameterError(
                        f'{parameter.code} is set to {item.value:g} at every connect '
                        f'({item.why}): set apply_commissioning false to manage it yourself')
        self.drive.check_write(key, value, running=False)

    def submit(self, name: str, *args: object) -> Future:
        """Queue a service action; the Future resolves to an ActionResult."""
        factory = self._action_factories.get(name)
        future: Future = Future()
        if factory is None:
            future.set_result(ActionResult(False, f'unknown action {quote(name)}'))
            return future
        self._actions.put((None if args else name, lambda: factory(*args), future))
        return future

    def start(self) -> None:
        """Run this drive in its own thread (a bus runs several in one: see bus.py)."""
        if self._loop is None:
            self._loop = CycleLoop(f'drive {self.drive.hardware_id}', self.config.cycle_period,
                                   self.step, self.finish, self._clock,
                                   urgent=self.write_pending_command)
            self.wake = self._loop.wake
            self._loop.start()

    def shutdown(self, timeout: float = 2.0) -> None:
        """Stop the loop; the drive is commanded to stop before the link closes."""
        if self._loop is not None:
            self._loop.stop(timeout)
            self._stopped_loop_errors += self._loop.errors
            self._loop = None

    # --- one cycle, in two phases (a bus writes every drive's command first) -----

    @property
    def connect_due(self) -> bool:
        return not self._online and self._clock() >= self._next_connect

    def step(self) -> None:
        self.command_phase()
        self.poll_phase()

    def command_phase(self, connect_allowed: bool = True) -> None:
        """Connect when due (and allowed: a bus connects one drive per cycle), then command."""
        self._cycle_ok = False
        self._failed_this_cycle = False
        if connect_allowed and self.connect_due:
            self._connect()
        if not self._online:
            return
        try:
            self._apply_command()
            self._write_setpoints()
            self._cycle_ok = True
        except TransportError as exc:
            self._cycle_failed(exc)
        except ProtocolException as exc:
            # The drive answered but refused the command: it is there, not offline.
            self._last_error = str(exc)
            self._cycle_ok = True

    def _apply_command(self) -> None:
        with self._lock:
            velocity = self._velocity
            expired = self._watchdog.expired
            self._command_pending = False
        run = self._permit(expired, 0.0)[0] is RunState.RUNNING
        reassert, self._reassert_idle = self._reassert_idle and not run, False
        self.drive.apply(velocity, run, self._idle_action, reassert=reassert)
        self._run_written = run

    def write_pending_command(self) -> None:
        """Write a new velocity command now, between polls (commands preempt polls)."""
        if not (self._online and self._command_pending):
            return
        try:
            self._apply_command()
        except TransportError as exc:
            self._cycle_failed(exc)
        except ProtocolException as exc:
            self._last_error = str(exc)

    def poll_phase(self) -> None:
        """Read the status, latch faults, advance a service action, publish the state."""
        if self._online and self._cycle_ok:
            try:
                self._reading = self.drive.poll(self._cycle, between=self._between_reads)
                self._cycle += 1
                self._check_fault()
                self._check_unexpected_motion()
                self._advance_action()
                self._failed_cycles = 0
            except TransportError as exc:
                self._cycle_failed(exc)
        self._fail_pending_if_offline()
        self._publish_state()

    def _check_fault(self) -> None:
        fault = self._reading.fault
        first_after_connect, self._comm_fault_check = self._comm_fault_check, False
        if not fault.active or self._fault_latched:
            return
        spec = self.drive.profile.comm_timeout
        own_absence = spec is not None and (fault.code, fault.subcode) == \
            (spec.fault_code, spec.fault_subcode)
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
        self._fault_latched = True
        log.warning('%s fault %s %s', self.drive.hardware_id, fault.display, fault.name)

    def _check_unexpected_motion(self) -> None:
        running = self._reading.flags.get('running', False)
        if running and not self._run_written:
            # Whatever was written last, the drive runs although the host has it
            # idle (a start from elsewhere, or a lost stop): write the idle command again.
            self._reassert_idle = True
            if not self._last_running:
                self._unexpected_starts += 1
                log.warning('%s reports running although the host has it %s: idle command '
                            'written again', self.drive.hardware_id,
                            self._permit(True, 0.0)[0].label)
        self._last_running = running

    def _connect(self) -> None:
        drive = self.drive
        try:
            drive.forget_state()
            drive.open()
            # Start-up never moves the motor: zero setpoint and idle first.
            drive.apply(0.0, run=False, idle_action=self._idle_action)
            self._run_written = False
            problems = drive.configure(self.protection, self.config.apply_commissioning)
        except VfdError as exc:
            self._last_error = str(exc)
            drive.close()
            self._next_connect = self._clock() + self._reconnect_delay()
            return
        for problem in problems:
            # A setting the drive refuses must not keep it offline: report and go on.
            log.error('%s: not applied at connect: %s', drive.hardware_id, problem)
        self._settings_refused = tuple(problems)
        # A drive may refuse (part of) the planned protection and say what holds;
        # Drive.protection_applied is optional (None: the plan holds as written).
        self.protection_applied = getattr(drive, 'protection_applied', None)
        self._written_setpoints.clear()   # re-send auxiliary setpoints after a reconnect
        with self._lock:
            self._watchdog.reset()   # never resume from a command older than the link
        self._online = True
        self._failed_cycles = 0
        self._last_running = False
        self._comm_fault_check = True
        if self._was_online:
            self._reconnects += 1
        self._was_online = True
        self._last_error = ''
        log.info('%s online', drive.hardware_id)

    def _reconnect_delay(self) -> float:
        """Keep a drive with a comm-loss timeout addressed within it while reconnecting.

        A short glitch then never lets the drive's own timer expire; a drive that
        is really gone costs its link one failed exchange per attempt.
        """
        delay = self.config.reconnect_period
        if self.protection.active:
            delay = min(delay, self.protection.timeout / 3)
        return delay

    def _cycle_failed(self, exc: VfdError) -> None:
        if self._failed_this_cycle:
            return          # one cycle counts once, however many exchanges failed in it
        self._failed_this_cycle = True
        self._failed_cycles += 1
        self._last_error = str(exc)
        if self._failed_cycles >= self.config.comm_loss_threshold:
            log.warning('%s offline: %s', self.drive.hardware_id, exc)
            self._online = False
            self._reading = Reading()
            self.drive.close()
            self._next_connect = self._clock() + self._reconnect_delay()

    def _between_reads(self) -> None:
        if self.between_reads is not None:
            self.between_reads()
        else:
            self.write_pending_command()

    def _permit(self, watchdog_expired: bool, watchdog_age: float) -> tuple[RunState, str]:
        """Decide motion: RUNNING, or the first reason that holds the drive idle (one rule)."""
        reading = self._reading
        if not self._online:
            return RunState.OFFLINE, f'no valid reply from the drive: {self._last_error}'
        if reading.fault.active or self._fault_latched:
            fault = reading.fault
            text = f'fault {fault.display} {fault.name}' if fault.active else 'fault (cleared)'
            return RunState.FAULT, f'{text}: call ~/reset_fault'
        if not self._enabled:
            return RunState.DISABLED, 'disabled: call ~/enable'
        if self._stopped:
            return RunState.STOPPED, 'stopped by ~/stop: call ~/enable to resume'
        if reading.unsafe:
            return RunState.BLOCKED, reading.unsafe
        if watchdog_expired:
            age = 'none received' if math.isinf(watchdog_age) else \
                f'last {watchdog_age:.2f} s ago'
            return RunState.WATCHDOG, (f'no velocity command within command_timeout '
                                       f'{self.config.command_timeout:g} s ({age})')
        return RunState.RUNNING, ''

    def _write_setpoints(self) -> None:
        with self._lock:
            pending = {code: raw for code, raw in self._setpoints.items()
                       if self._written_setpoints.get(code) != raw}
        for code, raw in pending.items():
            self.drive.write_setpoint_parameter(code, raw)
            self._written_setpoints[code] = raw

    def finish(self) -> None:
        """End of the loop: command the drive to stop, then close the link."""
        if self._online:
            try:
                # Whatever the driver believes the drive is doing: write the stop.
                self.drive.forget_state()
                self.drive.apply(0.0, run=False, idle_action='stop')
            except VfdError as exc:
                log.warning('could not stop %s at shutdown: %s', self.drive.hardware_id, exc)
        self.drive.close()
        self._online = False
        self._fail_pending_if_offline()

    # --- service actions (generators: one step per cycle) ---------------------

    def _take_queued(self) -> None:
        while True:
            try:
                self._backlog.append(self._actions.get_nowait())
            except queue.Empty:
                return

    def _advance_action(self) -> None:
        if self._current is None:
            self._take_queued()
            if not self._backlog:
                return
            key, factory, future = self._backlog.pop(0)
            futures = [future]
            if key is not None:
                futures += [f for k, _, f in self._backlog if k == key]
                self._backlog = [item for item in self._backlog if item[0] != key]
            try:
                self._current = (factory(), futures)
            except Exception as exc:  # noqa: BLE001 - a bug must not lose the reply
                self._action_failed(futures, exc)
                return
        steps, futures = self._current
        try:
            next(steps)
            return
        except StopIteration as done:
            result = done.value
        except (ParameterError, ProtocolException) as exc:
            result = ActionResult(False, str(exc))
        except TransportError as exc:
            self._current = None
            self._resolve(futures, ActionResult(False, f'no valid reply from the drive: {exc}'))
            raise
        except Exception as exc:  # noqa: BLE001 - a bug must not lose the reply
            self._current = None
            self._action_failed(futures, exc)
            return
        self._current = None
        self._resolve(futures, result)

    @staticmethod
    def _resolve(futures: list[Future], result: ActionResult) -> None:
        for future in futures:
            future.set_result(result)

    def _action_failed(self, futures: list[Future], exc: Exception) -> None:
        self._action_errors += 1
        log.exception('%s: action failed with an internal error: %s', self.drive.hardware_id,
                      exc)
        self._resolve(futures, ActionResult(False, f'internal error (a bug, please report): '
                                                   f'{exc!r}'))

    def _fail_pending_if_offline(self) -> None:
        if self._online:
            return
        reason = f'drive offline: {self._last_error or "not connected"}'
        if self._current is not None:
            self._resolve(self._current[1], ActionResult(False, reason))
            self._current = None
        self._take_queued()
        backlog, self._backlog = self._backlog, []
        self._resolve([future for _, _, future in backlog], ActionResult(False, reason))

    def _wait_for(self, condition: Callable[[], bool],
                  timeout: float) -> Generator[None, None, bool]:
        deadline = self._clock() + timeout
        while True:
            yield
            if condition():
                return True
            if self._clock() > deadline:
                return False

    def _flag(self, name: str, fallback: bool) -> bool:
        return self._reading.flags.get(name, fallback)

    def _action_enable(self) -> Action:
        if self._reading.fault.active:
            fault = self._reading.fault
            return ActionResult(False, f'drive has fault {fault.display} ({fault.name}): '
                                'call ~/reset_fault first')
        if self._reading.unsafe:
            return ActionResult(False, f'not enabled: {self._reading.unsafe}')
        self._enabled = True
        self._stopped = False
        self._idle_action = 'stop'
        ok = yield from self._wait_for(lambda: self._flag('ready', True) or
                                       self._flag('running', False), self.config.action_timeout)
        if not ok:
            self._enabled = False
            return ActionResult(False, 'drive did not report ready: not enabled')
        with self._lock:
            fresh = not self._watchdog.expired
        if not fresh:
            return ActionResult(True, 'enabled: the drive is ready and runs as soon as '
                                'velocity commands arrive')
        ok = yield from self._wait_for(lambda: self._flag('running', True),
                                       self.config.action_timeout)
        if not ok:
            return ActionResult(False, 'enabled, but the drive does not report running')
        return ActionResult(True, 'enabled and running')

    def _stop_action(self, idle_action: str, what: str) -> Action:
        self._idle_action = idle_action
        self._reassert_idle = True     # written again now, whatever was sent before
        ok = yield from self._wait_for(lambda: not self._flag('running', False),
                                       self.config.stop_timeout)
        if not ok:
            return ActionResult(False, f'{what} commanded, but the drive still reports running '
                                f'after {self.config.stop_timeout:g} s')
        return ActionResult(True, f'{what}: the drive reports not running')

    def _action_disable(self) -> Action:
        self._enabled = False
        values = self.drive.profile.control.values
        return (yield from self._stop_action('disable' if 'disable' in values else 'stop',
                                             'disabled'))

    def _action_stop(self) -> Action:
        self._stopped = True
        return (yield from self._stop_action('stop', 'stopped (call ~/enable to resume)'))

    def _action_reset_fault(self) -> Action:
        if not self._reading.fault.active:
            self._fault_latched = False
            return ActionResult(True, 'no fault active')
        before = self._reading.fault
        self.drive.send_command('fault_reset')
        ok = yield from self._wait_for(lambda: not self._reading.fault.active,
                                       self.config.action_timeout)
        if not ok:
            now = self._reading.fault
            return ActionResult(False, f'fault still active after reset: {now.display} '
                                f'{now.name}. Remedy: {now.remedy}')
        self._fault_latched = False
        return ActionResult(True, f'fault {before.display} ({before.name}) cleared')

    def _action_get_parameter(self, key: str) -> Action:
        value = self.drive.get_parameter(key)
        return ActionResult(True, value.parameter.description, value)
        yield  # pragma: no cover - makes this a generator

    def _action_set_parameter(self, key: str, value: float, persistent: bool) -> Action:
        self.check_parameter_write(key, value)
        running = self._flag('running', False)
        written, note = self.drive.set_parameter(key, value, persistent, running)
        parameter = written.parameter
        message = f'{parameter.code} = {written.value:g}{parameter.unit}'
        return ActionResult(True, f'{message} ({note})' if note else message, written)
        yield  # pragma: no cover - makes this a generator

    # --- snapshot ---------------------------------------------------------------

    @property
    def loop_errors(self) -> int:
        loop = self._loop
        return self._action_errors + self._stopped_loop_errors + \
            (loop.errors if loop is not None else 0)

    def _publish_state(self) -> None:
        reading = self._reading
        stats = self.drive.stats
        with self._lock:
            wdg_expired = self._watchdog.expired
            wdg_age = self._watchdog.age
            rejected, clamped = self._rejected, self._clamped
        mode, reason = self._permit(wdg_expired, wdg_age)
        commanded = self._velocity if mode is RunState.RUNNING else 0.0
        if mode is RunState.RUNNING and reading.problem:
            # Commanded to run, but the drive does not get there (e.g. CiA 402 stuck).
            mode, reason = RunState.BLOCKED, reading.problem
        flags = reading.flags
        measured = reading.measured_velocity
        running = flags.get('running', False)
        at_speed = flags.get('at_speed', running and math.isfinite(measured) and
                             abs(measured - commanded) <= self.config.at_speed_tolerance)
        snapshot = DriveState(
            hardware_id=self.drive.hardware_id,
            online=self._online,
            ready=flags.get('ready', False),
            enabled=self._enabled and not self._stopped,
            running=running,
            reverse=flags.get('reverse', False),
            fault=reading.fault.active,
            warning=flags.get('warning', reading.warning_code != 0),
            at_speed=at_speed,
            watchdog_tripped=mode is RunState.WATCHDOG,
            mode=mode,
            stop_reason=reason,
            status_words=tuple(reading.raw_words.items()),
            commanded_velocity=commanded,
            measured_velocity=measured,
            setpoint_raw=self.drive.last_setpoint_raw,
            measured=dict(reading.values),
            active_fault=reading.fault,
            warning_code=reading.warning_code,
            warning_subcode=reading.warning_subcode,
            transactions=stats.transactions,
            comm_errors=stats.errors,
            timeouts=stats.timeouts,
            bad_frames=stats.bad_frames,
            exceptions=stats.exceptions,
            reconnects=self._reconnects,
            late_replies=stats.late_replies,
            rejected_commands=rejected,
            clamped_commands=clamped,
            unexpected_starts=self._unexpected_starts,
            comm_faults_cleared=self._comm_faults_cleared,
            loop_errors=self.loop_errors,
            last_error=self._last_error,
            protection=self.protection_applied or self.protection,
            unavailable=tuple(reading.unavailable.values()) + self._settings_refused,
        )
        with self._lock:
            self._state = snapshot
