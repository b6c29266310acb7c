"""Command watchdog: AGV safety against a silent commander."""

from __future__ import annotations

import math
import time
from typing import Callable


class CommandWatchdog:
    """Tracks when the last valid command arrived, and until when it counts.

    ``expired`` is true before the first command and once the newest one is
    older than ``timeout`` seconds; ``reset()`` forgets all commands (used after
    a reconnect, so motion never resumes from a stale command). A command counts
    for the timeout in force when it came, or a shorter one set since: raising
    ``command_timeout`` while commands have stopped must not revive the last one
    (it restarted a wheel the watchdog had stopped, on a command seconds old).
    """

    def __init__(self, timeout: float, clock: Callable[[], float] = time.monotonic) -> None:
        self._clock = clock
        self._last: float | None = None
        self._deadline: float | None = None
        self.timeout = timeout

    @property
    def timeout(self) -> float:
        return self._timeout

    @timeout.setter
    def timeout(self, timeout: float) -> None:
        if not (math.isfinite(timeout) and timeout > 0):
            raise ValueError(f'command_timeout must be > 0 s, got {timeout}')
        self._timeout = timeout
        if self._deadline is not None:      # shortened at once, never lengthened
            self._deadline = min(self._deadline, self._last + timeout)

    def feed(self) -> None:
        self._last = self._clock()
        self._deadline = self._last + self._timeout

    def reset(self) -> None:
        self._last = self._deadline = None

    @property
    def ever_fed(self) -> bool:
        return self._last is not None

    @property
    def age(self) -> float:
        """Seconds since the last command (inf if none)."""
        return math.inf if self._last is None else self._clock() - self._last

    @property
    def expired(self) -> bool:
        return self._deadline is None or self._clock() > self._deadline

    @property
    def limit(self) -> float:
        """The timeout the newest command counts for (``timeout`` before the first)."""
        return self._timeout if self._deadline is None else self._deadline - self._last

    @property
    def deadline(self) -> float | None:
        """When the newest command expires (clock time), None before the first one."""
        return self._deadline
