"""The drive loop: one thread that owns the link to one drive.

Commands arrive from any thread (``command_velocity``, ``submit``); only the
loop thread touches the transport. Each cycle writes the command first, then
polls status, then advances at most one pending service action one step, so a
slow verification never holds up the watchdog or the status.

Safety rules kept here, in one place:
- start-up and every reconnect write a zero setpoint and the idle command
  before anything else, and forget all earlier velocity commands;
- the drive runs only while enabled, not stopped, fault-free, online and fed
  with fresh commands (the command watchdog);
- after a fault motion resumes only after a successful ``reset_fault``.
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

from .drive import Drive, ParameterValue, Reading
from .errors import ParameterError, ProtocolException, TransportError, VfdError
from .faults import NO_FAULT, FaultInfo
from .watchdog import CommandWatchdog

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
    state: str = 'offline'
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
    rejected_commands: int = 0
    clamped_commands: int = 0
    last_error: str = ''


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
        self._actions: queue.SimpleQueue[tuple[Callable[[], Action], Future]] = \
            queue.SimpleQueue()
        self._current: tuple[Iterator[None], Future] | None = None
        self._loop: CycleLoop | None = None
        self._cycle_ok = False
        self._command_pending = False
        self._failed_this_cycle = False
        #: called when a command should be written before the next cycle (set by the
        #: loop that runs this controller: its own, or a bus's)
        self.wake: Callable[[], None] | None = None
        #: run before each status read instead of this drive's own pending command
        #: (a bus writes every drive's new command first)
        self.between_reads: Callable[[], None] | None = None
        self._state = DriveState(hardware_id=drive.hardware_id)

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
            raise ParameterError(f'{topic!r} is not a setpoint of this drive')
        parameter = self.drive.profile.parameter(code)
        raw = parameter.to_raw(value)
        with self._lock:
            self._setpoints[code] = raw

    def submit(self, name: str, *args: object) -> Future:
        """Queue a service action; the Future resolves to an ActionResult."""
        factory = getattr(self, f'_action_{name}', None)
        future: Future = Future()
        if factory is None:
            future.set_result(ActionResult(False, f'unknown action {name!r}'))
            return future
        self._actions.put((lambda: factory(*args), future))
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
            self._loop = None

    # --- one cycle, in two phases (a bus writes every drive's command first) -----

    def step(self) -> None:
        self.command_phase()
        self.poll_phase()

    def command_phase(self) -> None:
        """Connect when due, then write the command and setpoints."""
        self._cycle_ok = False
        self._failed_this_cycle = False
        if not self._online and self._clock() >= self._next_connect:
            self._connect()
        if not self._online:
            return
        try:
            self._apply_command()
            self._write_setpoints()
            self._cycle_ok = True
        except (TransportError, ProtocolException) as exc:
            self._cycle_failed(exc)

    def _apply_command(self) -> None:
        with self._lock:
            velocity = self._velocity
            expired = self._watchdog.expired
            self._command_pending = False
        self.drive.apply(velocity, self._run_allowed(expired), self._idle_action)

    def write_pending_command(self) -> None:
        """Write a new velocity command now, between polls (commands preempt polls)."""
        if not (self._online and self._command_pending):
            return
        try:
            self._apply_command()
        except (TransportError, ProtocolException) as exc:
            self._cycle_failed(exc)

    def poll_phase(self) -> None:
        """Read the status, latch faults, advance a service action, publish the state."""
        if self._online and self._cycle_ok:
            try:
                self._reading = self.drive.poll(self._cycle, between=self._between_reads)
                self._cycle += 1
                if self._reading.fault.active and not self._fault_latched:
                    self._fault_latched = True
                    log.warning('%s fault %s %s', self.drive.hardware_id,
                                self._reading.fault.display, self._reading.fault.name)
                self._advance_action()
                self._failed_cycles = 0
            except (TransportError, ProtocolException) as exc:
                self._cycle_failed(exc)
        self._fail_pending_if_offline()
        self._publish_state()

    def _connect(self) -> None:
        drive = self.drive
        try:
            drive.forget_state()
            drive.open()
            # Start-up never moves the motor: zero setpoint and idle first.
            drive.apply(0.0, run=False, idle_action=self._idle_action)
            self._configure()
        except VfdError as exc:
            self._last_error = str(exc)
            drive.close()
            self._next_connect = self._clock() + self.config.reconnect_period
            return
        self._written_setpoints.clear()   # re-send auxiliary setpoints after a reconnect
        with self._lock:
            self._watchdog.reset()   # never resume from a command older than the link
        self._online = True
        self._failed_cycles = 0
        if self._was_online:
            self._reconnects += 1
        self._was_online = True
        self._last_error = ''
        log.info('%s online', drive.hardware_id)

    def _configure(self) -> None:
        for problem in self.drive.configure(self.config.drive_comm_timeout,
                                            self.config.apply_commissioning):
            # A setting the drive cannot take (e.g. 0 = "off" where the manual has
            # no off value) must not keep the drive offline: report and go on.
            log.error('%s: not applied at connect: %s', self.drive.hardware_id, problem)

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
            self._next_connect = self._clock() + self.config.reconnect_period

    def _between_reads(self) -> None:
        if self.between_reads is not None:
            self.between_reads()
        else:
            self.write_pending_command()

    def _run_allowed(self, watchdog_expired: bool) -> bool:
        return (self._online and self._enabled and not self._stopped
                and not self._fault_latched and not self._reading.fault.active
                and not watchdog_expired)

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

    def _advance_action(self) -> None:
        if self._current is None:
            try:
                factory, future = self._actions.get_nowait()
            except queue.Empty:
                return
            self._current = (factory(), future)
        steps, future = self._current
        try:
            next(steps)
            return
        except StopIteration as done:
            result = done.value
        except (ParameterError, ProtocolException) as exc:
            result = ActionResult(False, str(exc))
        except TransportError as exc:
            self._current = None
            future.set_result(ActionResult(False, f'no valid reply from the drive: {exc}'))
            raise
        self._current = None
        future.set_result(result)

    def _fail_pending_if_offline(self) -> None:
        if self._online:
            return
        reason = f'drive offline: {self._last_error or "not connected"}'
        if self._current is not None:
            self._current[1].set_result(ActionResult(False, reason))
            self._current = None
        while True:
            try:
                _, future = self._actions.get_nowait()
            except queue.Empty:
                return
            future.set_result(ActionResult(False, reason))

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
        running = self._flag('running', False)
        written, note = self.drive.set_parameter(key, value, persistent, running)
        parameter = written.parameter
        message = f'{parameter.code} = {written.value:g}{parameter.unit}'
        return ActionResult(True, f'{message} ({note})' if note else message, written)
        yield  # pragma: no cover - makes this a generator

    # --- snapshot ---------------------------------------------------------------

    def _stop_reason(self, wdg_expired: bool, wdg_age: float) -> tuple[str, str, bool]:
        reading = self._reading
        if not self._online:
            return 'offline', f'no valid reply from the drive: {self._last_error}', False
        if reading.fault.active or self._fault_latched:
            fault = reading.fault
            text = f'fault {fault.display} {fault.name}' if fault.active else 'fault (cleared)'
            return 'fault', f'{text}: call ~/reset_fault', False
        if not self._enabled:
            return 'disabled', 'disabled: call ~/enable', False
        if self._stopped:
            return 'stopped', 'stopped by ~/stop: call ~/enable to resume', False
        if reading.problem:
            return 'blocked', reading.problem, False
        if wdg_expired:
            age = 'none received' if math.isinf(wdg_age) else f'last {wdg_age:.2f} s ago'
            return ('watchdog', f'no velocity command within command_timeout '
                    f'{self.config.command_timeout:g} s ({age})', True)
        return 'running', '', False

    def _publish_state(self) -> None:
        reading = self._reading
        stats = self.drive.transport.stats
        with self._lock:
            wdg_expired = self._watchdog.expired
            wdg_age = self._watchdog.age
            commanded = self._velocity if self._run_allowed(wdg_expired) else 0.0
            rejected, clamped = self._rejected, self._clamped
        state, reason, tripped = self._stop_reason(wdg_expired, wdg_age)
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
            watchdog_tripped=tripped,
            state=state,
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
            rejected_commands=rejected,
            clamped_commands=clamped,
            last_error=self._last_error,
        )
        with self._lock:
            self._state = snapshot
