"""Service actions: verified steps run by the loop thread, one step per cycle.

``ServiceActions`` defines what ``~/enable``, ``~/disable``, ``~/stop``,
``~/reset_fault`` and the parameter services do, as generators that yield
between steps, so a slow verification (a stop waiting for the ramp) never holds
up the watchdog or the status. ``ActionQueue`` takes requests from any thread
and answers each exactly once, in the order they came; identical trigger requests
waiting next to each other get the one result (a burst of ``~/enable`` calls is
one enable), never one that came after another kind (stop, enable, stop: the
last stop runs last).
"""

from __future__ import annotations

import logging
import queue
import threading
from concurrent.futures import Future
from typing import Callable, Generator, Iterator

from ..drives import Drive, Reading
from ..errors import ParameterError, ProtocolException, TransportError, quote
from .permit import Intent
from .state import ActionResult

log = logging.getLogger(__name__)

Action = Generator[None, None, ActionResult]

#: the answer while no control loop serves the queue (before it starts, after it ends)
NOT_SERVED = ('no control loop runs this drive (a managed node: configure it first; '
              'or the driver is shutting down)')


class ActionQueue:
    """Requests from any thread; ``advance`` (loop thread) runs the current one a step."""

    def __init__(self, name: str) -> None:
        self.name = name
        self.errors = 0                  # actions that raised an unexpected exception
        self._incoming: queue.SimpleQueue[tuple[str | None, Callable[[], Action], Future]] = \
            queue.SimpleQueue()
        self._backlog: list[tuple[str | None, Callable[[], Action], Future]] = []
        self._current: tuple[Iterator[None], list[Future]] | None = None
        # Why requests are answered at once instead of queued (None: a loop serves them).
        # A request queued while no loop runs would wait unanswered, then run whenever
        # one starts, long after its caller gave up (a stale fault reset, say).
        self._refusal: str | None = NOT_SERVED
        self._gate = threading.Lock()

    @property
    def serving(self) -> bool:
        """Whether requests are queued for a loop (not answered at once with a refusal)."""
        return self._refusal is None

    def open(self) -> None:
        """Queue requests from now on: a loop serves them (call before it advances)."""
        with self._gate:
            self._refusal = None

    def close(self, reason: str) -> None:
        """No loop serves the queue any more: answer everything waiting, refuse the rest."""
        with self._gate:
            self._refusal = NOT_SERVED
        self.fail_all(reason)

    def submit(self, key: str | None, factory: Callable[[], Action]) -> Future:
        """Queue an action; a run of requests with the same ``key`` shares one action."""
        future: Future = Future()
        with self._gate:
            refusal = self._refusal
            if refusal is None:
                self._incoming.put((key, factory, future))
                return future
        future.set_result(ActionResult(False, refusal))
        return future

    def _take_incoming(self) -> None:
        while True:
            try:
                self._backlog.append(self._incoming.get_nowait())
            except queue.Empty:
                return

    def advance(self) -> None:
        """Run the current action one step (start the next one if none runs).

        A TransportError fails the action and is raised again: the loop counts
        it against the link.
        """
        if self._current is None:
            self._take_incoming()
            if not self._backlog:
                return
            key, factory, future = self._backlog.pop(0)
            futures = [future]
            if key is not None:
                # Only the same requests right behind it: merging one from behind
                # another kind would run it early (disable, enable, disable: the
                # acknowledged last disable undone by the enable).
                same = 0
                while same < len(self._backlog) and self._backlog[same][0] == key:
                    same += 1
                futures += [f for _, _, f in self._backlog[:same]]
                del self._backlog[:same]
            try:
                self._current = (factory(), futures)
            except Exception as exc:  # noqa: BLE001 - a bug must not lose the reply
                self._internal_error(futures, exc)
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
            _resolve(futures, ActionResult(False, f'no valid reply from the drive: {exc}'))
            raise
        except Exception as exc:  # noqa: BLE001 - a bug must not lose the reply
            self._current = None
            self._internal_error(futures, exc)
            return
        self._current = None
        _resolve(futures, result)

    def fail_all(self, reason: str) -> None:
        """Answer the current and every waiting action with ``reason`` (the link is down)."""
        if self._current is not None:
            _resolve(self._current[1], ActionResult(False, reason))
            self._current = None
        self._take_incoming()
        backlog, self._backlog = self._backlog, []
        _resolve([future for _, _, future in backlog], ActionResult(False, reason))

    def _internal_error(self, futures: list[Future], exc: Exception) -> None:
        self.errors += 1
        log.exception('%s: action failed with an internal error: %s', self.name, exc)
        _resolve(futures, ActionResult(False, f'internal error (a bug, please report): '
                                              f'{exc!r}'))


def _resolve(futures: list[Future], result: ActionResult) -> None:
    for future in futures:
        future.set_result(result)


class ServiceActions:
    """The steps of each service, on one drive and the host's ``Intent`` for it."""

    def __init__(self, drive: Drive, intent: Intent, reading: Callable[[], Reading],
                 commands_fresh: Callable[[], bool], check_write: Callable[[str, float], None],
                 action_timeout: float, stop_timeout: float,
                 clock: Callable[[], float], standstill: float) -> None:
        self.drive = drive
        self.intent = intent
        self._reading = reading
        self._commands_fresh = commands_fresh
        self._check_write = check_write
        self.action_timeout = action_timeout
        self.stop_timeout = stop_timeout
        #: rad/s: a measured speed at most this is standstill (a verified stop)
        self.standstill = standstill
        self._clock = clock
        #: set when the idle command must be written again now, whatever was sent
        self.reassert_idle = False
        #: set by ~/enable: the run command is written again (a drive that lost it)
        self.reassert_run = False
        #: operators' stops and disables latched so far (an enable asked before one
        #: of them must not undo it when it runs after it)
        self.latches = 0
        self._steps: dict[str, Callable[..., Action]] = {
            'enable': self.enable, 'disable': self.disable, 'stop': self.stop,
            'reset_fault': self.reset_fault, 'get_parameter': self.get_parameter,
            'set_parameter': self.set_parameter}

    def factory(self, name: str, *args: object, operator: bool = True) -> Callable[[], Action]:
        """Return the action ``name`` with its arguments; ParameterError if unknown.

        ``operator``: a stop or disable an operator asked (latched as it is asked,
        and held by ``asked_stop``), not a managed node's own hold. An enable knows
        the latches so far: a stop or disable asked after it wins.
        """
        step = self._steps.get(name)
        if step is None:
            raise ParameterError(f'unknown action {quote(name)}')
        if name == 'enable':
            latches = self.latches
            return lambda: self.enable(latches)
        if name in ('stop', 'disable'):
            return lambda: step(operator)
        return lambda: step(*args)

    def latch(self, name: str) -> str:
        """Hold what ``~/stop`` or ``~/disable`` asks from the moment it is asked.

        Its action may never run (the drive offline, no loop serving): the drive
        must still not run again when the link returns. Returns what is held ('' for
        any other action).
        """
        intent = self.intent
        if name == 'stop':
            intent.stopped = intent.asked_stop = True
            self.latches += 1
            return 'the stop is latched'
        if name == 'disable':
            intent.enabled, intent.asked_stop = False, True
            intent.idle_action = self._disable_action()     # the coast, as when online
            self.latches += 1
            return 'the disable is latched'
        return ''

    def _disable_action(self) -> str:
        return 'disable' if 'disable' in self.drive.profile.control.values else 'stop'

    def _flag(self, name: str, fallback: bool) -> bool:
        return self._reading().flags.get(name, fallback)

    def _wait_for(self, condition: Callable[[], bool],
                  timeout: float) -> Generator[None, None, bool]:
        deadline = self._clock() + timeout
        while True:
            yield
            if condition():
                return True
            if self._clock() > deadline:
                return False

    def enable(self, latches: int | None = None) -> Action:
        """Enable; ``latches``: the operators' stops and disables when it was asked."""
        def superseded() -> bool:
            # A ~/stop or ~/disable asked after this enable holds from its asking: run
            # after it, the enable undid it (and a managed activate with auto_enable
            # then ran the motor again: outside audit); asked while it waits, it ends
            # the wait (the stop's answer waited out action_timeout: re-check).
            return latches is not None and latches != self.latches
        refused = ActionResult(False, 'not enabled: a ~/stop or ~/disable asked after this '
                               '~/enable holds the drive')
        if superseded():
            return refused
        reading = self._reading()
        if reading.fault.active:
            fault = reading.fault
            return ActionResult(False, f'drive has fault {fault.display} ({fault.name}): '
                                'call ~/reset_fault first')
        if self.intent.fault_latched:
            # The drive no longer shows the fault it had; the node holds it until reset,
            # so an enable could not run the drive (and must not change what it holds).
            return ActionResult(False, 'a fault is latched (the drive no longer reports it): '
                                'call ~/reset_fault first')
        if reading.unsafe:
            return ActionResult(False, f'not enabled: {reading.unsafe}')
        intent = self.intent
        intent.enabled, intent.stopped, intent.idle_action = True, False, 'stop'
        intent.asked_stop = False
        # A drive that lost its run command (it does not report running) gets it again;
        # one that runs is left alone (the run edge would pass through a stop).
        self.reassert_run = not self._flag('running', False)
        ok = yield from self._wait_for(lambda: superseded() or self._flag('ready', True) or
                                       self._flag('running', False), self.action_timeout)
        if superseded():
            return refused
        if not ok:
            intent.enabled = False
            return ActionResult(False, 'drive did not report ready: not enabled')
        if not self._commands_fresh():
            return ActionResult(True, 'enabled: the drive is ready and runs as soon as '
                                'velocity commands arrive')
        ok = yield from self._wait_for(lambda: superseded() or self._flag('running', True),
                                       self.action_timeout)
        if superseded():
            return refused
        if not ok:
            # A refused enable leaves the node not enabled: the drive must not start by
            # itself later, when whatever held it (a safe torque off) is released.
            intent.enabled = False
            return ActionResult(False, 'the drive does not report running: not enabled')
        return ActionResult(True, 'enabled and running')

    def _turning(self) -> float | None:
        """Return the measured speed (rad/s) while above standstill, else None."""
        measured = self._reading().measured_velocity
        return measured if abs(measured) > self.standstill else None   # (NaN: not measured)

    def _stopping(self, idle_action: str, what: str, to_standstill: bool) -> Action:
        """Write the idle command; verify the drive no longer runs (and stands still).

        A drive may drop its run state while the motor still turns: a CiA 402 drive
        whose disable operation coasts (0x605C = 0), or one that reports the run
        command rather than the motion. A stop is verified only at standstill, where
        the drive measures its speed; a disable coasts by design and says so.
        """
        self.intent.idle_action = idle_action
        self.reassert_idle = True      # written again now, whatever was sent before
        ok = yield from self._wait_for(
            lambda: not self._flag('running', False) and not (
                to_standstill and self._turning() is not None), self.stop_timeout)
        turning = self._turning()
        if not ok:
            if self._flag('running', False):
                return ActionResult(False, f'{what} commanded, but the drive still reports '
                                    f'running after {self.stop_timeout:g} s')
            return ActionResult(False, f'{what} commanded: the drive reports not running, but '
                                f'still measures {turning:.3g} rad/s after '
                                f'{self.stop_timeout:g} s')
        if turning is not None:
            return ActionResult(True, f'{what}: the drive reports not running; the motor still '
                                f'turns at {turning:.3g} rad/s (coasting)')
        return ActionResult(True, f'{what}: the drive reports not running')

    def disable(self, operator: bool = True) -> Action:
        self.intent.enabled = False
        self.intent.asked_stop |= operator     # (an earlier enable may have run since)
        return (yield from self._stopping(self._disable_action(), 'disabled', False))

    def stop(self, operator: bool = True) -> Action:
        self.intent.stopped = True
        self.intent.asked_stop |= operator
        return (yield from self._stopping('stop', 'stopped (call ~/enable to resume)', True))

    def reset_fault(self) -> Action:
        reading = self._reading()
        if not reading.fault.active:
            self.intent.fault_latched = False
            return ActionResult(True, 'no fault active')
        before = reading.fault
        self.drive.send_command('fault_reset')
        ok = yield from self._wait_for(lambda: not self._reading().fault.active,
                                       self.action_timeout)
        if not ok:
            now = self._reading().fault
            return ActionResult(False, f'fault still active after reset: {now.display} '
                                f'{now.name}. Remedy: {now.remedy}')
        self.intent.fault_latched = False
        return ActionResult(True, f'fault {before.display} ({before.name}) cleared')

    def get_parameter(self, key: str) -> Action:
        value = self.drive.get_parameter(key)
        return ActionResult(True, value.parameter.description, value)
        yield  # pragma: no cover - makes this a generator

    def set_parameter(self, key: str, value: float, persistent: bool) -> Action:
        self._check_write(key, value)
        running = self._flag('running', False)
        written, note = self.drive.set_parameter(key, value, persistent, running)
        parameter = written.parameter
        message = f'{parameter.code} = {written.value:g}{parameter.unit}'
        return ActionResult(True, f'{message} ({note})' if note else message, written)
        yield  # pragma: no cover - makes this a generator
