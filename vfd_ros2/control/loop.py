"""The thread that runs a control cycle at a fixed period, and lets commands preempt it."""

from __future__ import annotations

import logging
import os
import threading
import time
import traceback
from typing import Callable

from ..protocol.linux_thread import name_os_thread
from ..protocol.repeats import RepeatThrottle

log = logging.getLogger(__name__)

#: s between two log lines of the same repeating loop error
LOOP_ERROR_LOG_PERIOD = 10.0
#: kinds of loop error remembered for that (more: the oldest is forgotten)
LOOP_ERROR_KINDS = 32


#: s a loop's end is waited for, besides two failed exchanges per drive (the one under way
#: when asked, and the stop it writes at its end: see DriveController.shutdown, Bus.shutdown)
SHUTDOWN_WAIT = 3.0

#: below this fraction of its rate over two windows running, a loop is said to run short
RATE_SHORTFALL = 0.9
#: s, the shortest window RateWatch judges, and the longest it waits for two cycles in one
RATE_WINDOW = 0.5
RATE_WINDOW_LONGEST = 10.0


class RateWatch:
    """The cycles per second a loop achieves, and whether it runs short of its rate.

    ``sample`` is called by a diagnostics timer. It judges windows of at least
    RATE_WINDOW, two periods and two cycles (up to RATE_WINDOW_LONGEST: a stalled loop
    is judged too; a faster timer gets the last judgement), and one slow window (a
    connect, a collection) is not enough: two in a row are.
    """

    def __init__(self, clock: Callable[[], float] = time.monotonic) -> None:
        self._clock = clock
        self._window: tuple[float, int, bool] = (clock(), 0, False)   # start, cycles, short
        self._last: tuple[float, bool] = (0.0, False)

    def sample(self, cycles: int, period: float) -> tuple[float, bool]:
        """Return (cycles/s in the last window judged, short in it and in the one before)."""
        now = self._clock()
        then, before, was_short = self._window
        elapsed = now - then
        if elapsed < max(RATE_WINDOW, 2 * period) or \
                (cycles - before < 2 and elapsed < RATE_WINDOW_LONGEST):
            return self._last       # (a figure of whole cycles: 0 or 1 in a window says little)
        rate = max(cycles - before, 0) / elapsed
        short = cycles >= before and rate < RATE_SHORTFALL / period
        self._window = (now, cycles, short)
        self._last = (rate, short and was_short)
        return self._last


class CycleLoop:
    """Calls ``step`` every ``period`` seconds in its own thread, then ``finish``.

    Between cycles, ``request_preempt()`` (e.g. a new velocity command) runs
    ``preempt`` at once instead of waiting for the next period: commands preempt
    polls without raising the poll rate. ``preempt_at()`` names a moment at which
    ``preempt`` must run by itself (the command watchdog's expiry: a tripped
    watchdog is as urgent as a new command). An exception in a step is logged and
    counted (``errors``: each one is a bug) and the loop goes on: nothing may
    stop the thread that keeps a traction drive under control. An overrun
    restarts the schedule instead of bursting to catch up.

    ``priority`` (1..99) runs the thread under ``SCHED_FIFO`` so that other
    processes on a busy machine cannot delay its wake-ups (0: the default
    scheduler); ``notes`` says when the kernel refused it.
    """

    def __init__(self, name: str, period: float, step: Callable[[], None],
                 finish: Callable[[], None], clock: Callable[[], float] = time.monotonic,
                 preempt: Callable[[], None] | None = None,
                 preempt_at: Callable[[], float | None] | None = None,
                 priority: int = 0) -> None:
        self.name = name
        self.priority = priority
        self.notes: tuple[str, ...] = ()
        self.period = period
        self._step = step
        self._finish = finish
        self._preempt = preempt
        self._preempt_at = preempt_at
        self._clock = clock
        self._stop = threading.Event()
        self._preempt_requested = threading.Event()
        self._rescheduled = threading.Event()
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        self.overruns = 0
        self.cycles = 0                 # steps run (the rate achieved, beside control_rate)
        self.errors = 0
        self._error_log = RepeatThrottle(LOOP_ERROR_LOG_PERIOD, LOOP_ERROR_KINDS)

    def start(self) -> None:
        self._thread.start()
        if self.priority:
            self.notes = self._request_priority()

    def _request_priority(self) -> tuple[str, ...]:
        try:
            os.sched_setscheduler(self._thread.native_id or 0, os.SCHED_FIFO,
                                  os.sched_param(self.priority))
        except (OSError, AttributeError) as exc:
            # Unprivileged (no CAP_SYS_NICE, no rtprio limit) or not Linux: the loop
            # still runs, with wake-ups as late as the machine's load makes them.
            note = (f'realtime_priority {self.priority} refused ({exc}): the control '
                    'thread runs at normal priority')
            log.warning('%s: %s', self.name, note)
            return (note,)
        return ()

    def request_preempt(self) -> None:
        """Run ``preempt`` now (thread-safe; a no-op without ``preempt``)."""
        if self._preempt is not None:
            self._preempt_requested.set()

    @property
    def stopping(self) -> bool:
        """Whether ``stop`` was asked: a step may end early, ``finish`` comes next."""
        return self._stop.is_set()

    def set_period(self, period: float) -> None:
        """Change the period from any thread; a cycle waiting longer is brought forward."""
        self.period = period
        self._rescheduled.set()
        self._preempt_requested.set()

    def stop(self, timeout: float = 2.0) -> None:
        self._stop.set()
        self._preempt_requested.set()
        if self._thread.is_alive():
            self._thread.join(timeout)

    def _guarded(self, call: Callable[[], None]) -> None:
        try:
            call()
            if self._error_log.untold:
                self._tell_repeats()
        except Exception as exc:  # noqa: BLE001 - the loop must survive anything
            self.errors += 1
            # Each kind of error (its type and where it was raised: the text may carry
            # a time or a value) with its traceback once; a repeat (every cycle, say) as
            # one line at most every LOOP_ERROR_LOG_PERIOD, with its count.
            where = traceback.extract_tb(exc.__traceback__)[-1]
            kind = f'{type(exc).__name__} at {where.filename}:{where.lineno}'
            told = self._error_log.note(kind, time.monotonic())
            if told is None:            # a repeat: another kind's may be due (no good step)
                self._tell_repeats()
                return
            if told.first:
                log.exception('%s: loop error: %s', self.name, exc)
            else:           # its period is over: this one and those counted since
                log.error('%s: loop error again (%d more times, %s)', self.name,
                          told.repeats + 1, kind)

    def _tell_repeats(self, at_end: bool = False) -> None:
        """Log the repeats counted and not yet told, once their period is over.

        Called after a good step while some are untold: an error that repeated a few
        times and stopped is told too (at the latest when the loop ends), not only
        one that comes back after the period.
        """
        for untold in self._error_log.due(time.monotonic(), at_end):
            log.error('%s: loop error again (%d more times, %s)', self.name, untold.repeats,
                      untold.kind)

    def _run(self) -> None:
        name_os_thread(f'vfd {self.name}')
        next_cycle = self._clock()
        while not self._stop.is_set():
            self._guarded(self._step)
            self.cycles += 1
            next_cycle += self.period
            if next_cycle - self._clock() < -self.period:
                self.overruns += 1
                next_cycle = self._clock()
            while not self._stop.is_set():
                now = self._clock()
                due = self._preempt_at() if self._preempt_at is not None else None
                if due is not None and due < next_cycle:
                    if due <= now or not self._preempt_requested.wait(due - now):
                        self._guarded(self._preempt)          # the moment has come
                        continue
                else:
                    delay = next_cycle - now
                    if delay <= 0 or not self._preempt_requested.wait(delay):
                        break
                self._preempt_requested.clear()
                if self._rescheduled.is_set():
                    self._rescheduled.clear()
                    next_cycle = min(next_cycle, self._clock() + self.period)
                if self._preempt is not None and not self._stop.is_set():
                    self._guarded(self._preempt)
        self._guarded(self._finish)
        if self._error_log.untold:
            self._tell_repeats(at_end=True)
