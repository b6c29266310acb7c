"""Command watchdog: AGV safety against a silent commander."""

from __future__ import annotations

import math
import time
from typing import Callable


class CommandWatchdog:
    """Tracks when the last valid command arrived.

    ``expired`` is true before the first command and whenever the newest one is
    older than ``timeout`` seconds; ``reset()`` forgets all commands (used after
    a reconnect, so motion never resumes from a stale command).
    """

    def __init__(self, timeout: float, clock: Callable[[], float] = time.monotonic) -> None:
        if not (math.isfinite(timeout) and timeout > 0):
            raise ValueError(f'command_timeout must be > 0 s, got {timeout}')
        self.timeout = timeout
        self._clock = clock
        self._last: float | None = None

    def feed(self) -> None:
        self._last = self._clock()

    def reset(self) -> None:
        self._last = None

    @property
    def ever_fed(self) -> bool:
        return self._last is not None

    @property
    def age(self) -> float:
        """Seconds since the last command (inf if none)."""
        return math.inf if self._last is None else self._clock() - self._last

    @property
    def expired(self) -> bool:
        return self.age > self.timeout

    @property
    def deadline(self) -> float | None:
        """When the newest command expires (clock time), None before the first one."""
        return None if self._last is None else self._last + self.timeout
