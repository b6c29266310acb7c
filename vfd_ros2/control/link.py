"""Link supervision of one drive: online or not, when to try again, and why it failed."""

from __future__ import annotations

import logging
import time
from typing import Callable

from ..errors import VfdError

log = logging.getLogger(__name__)


class LinkSupervisor:
    """Counts failed cycles, declares a drive offline, schedules the reconnects.

    A cycle counts once however many exchanges failed in it; ``threshold``
    consecutive failed cycles take the drive offline. A drive that is offline is
    retried every ``retry_period`` (the caller keeps a drive with a comm-loss
    timeout addressed within it).
    """

    def __init__(self, name: str, threshold: int, retry_period: float,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.name = name
        self.threshold = threshold
        self.retry_period = retry_period
        self._clock = clock
        self.online = False
        self.reconnects = 0
        self.error = ''              # why the link failed last ('' while healthy)
        self.closed_reason = ''      # why the host closed it on purpose ('' = it did not)
        self._ever_online = False
        self._failed_cycles = 0
        self._failed_this_cycle = False
        self._next_attempt = 0.0
        self._connect_error = ''     # the last connect failure logged (each reason once)

    @property
    def connect_due(self) -> bool:
        return not self.online and self._clock() >= self._next_attempt

    @property
    def first_connect(self) -> bool:
        return not self._ever_online

    def new_cycle(self) -> None:
        self._failed_this_cycle = False

    def connected(self) -> None:
        if self._ever_online:
            self.reconnects += 1
        self._ever_online = True
        self.online = True
        self._failed_cycles = 0
        self.error = self._connect_error = self.closed_reason = ''
        log.info('%s online', self.name)

    def connect_failed(self, exc: VfdError) -> None:
        self.error = str(exc)
        self.closed_reason = ''
        self._next_attempt = self._clock() + self.retry_period
        # Why a drive stays offline (a value it refuses at connect, a silent node)
        # goes to the log once per reason, not once per attempt.
        if self.error != self._connect_error:
            self._connect_error = self.error
            log.warning('%s: connect failed: %s', self.name, self.error)

    def drop(self, reason: str) -> None:
        """Go offline now and connect afresh at once (the drive must be configured again)."""
        log.warning('%s offline: %s', self.name, reason)
        self.online = False
        self.error = reason
        self._next_attempt = self._clock()

    def cycle_ok(self) -> None:
        self._failed_cycles = 0

    def cycle_failed(self, exc: VfdError) -> bool:
        """Count a failed exchange; return True when the drive just went offline."""
        if self._failed_this_cycle:
            return False
        self._failed_this_cycle = True
        self._failed_cycles += 1
        self.error = str(exc)
        if self.online and self._failed_cycles >= self.threshold:
            log.warning('%s offline: %s', self.name, exc)
            self.online = False
            self._next_attempt = self._clock() + self.retry_period
            return True
        return False

    def closed(self, reason: str = 'the link is closed: the control loop ended') -> None:
        """Mark the link closed by the host on purpose (not a comm loss); ``reason`` says why."""
        self.online = False
        self.closed_reason = reason
