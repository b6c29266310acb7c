"""Link supervision of one drive: online or not, when to try again, and why it failed."""

from __future__ import annotations

import logging
import re
import time
from typing import Callable

from ..errors import VfdError
from ..protocol.repeats import RepeatThrottle

log = logging.getLogger(__name__)

#: s during which the same reason for going offline is logged once (a flapping drive:
#: offline, reconnected, offline again, every retry period); the repeats are counted
OFFLINE_LOG_PERIOD = 10.0

#: kinds of connect failure logged while a drive stays offline (each kind once)
CONNECT_FAILURES_TOLD = 8

#: what varies between two failures of one kind: a dump of the bytes received (a
#: transaction id), a number (a value written); '#' in the kind
_VARYING = re.compile(r'(?:\b[0-9a-fA-F]{2}\b ?){3,}|\b(?:0x)?[0-9a-fA-F]*[0-9][0-9a-fA-F]*\b')


def failure_kind(reason: str) -> str:
    """Return ``reason`` without the bytes and numbers that vary between its repeats."""
    return _VARYING.sub('#', reason)


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
        self.failed_connects = 0     # in a row, since it was last online
        self.error = ''              # why the link failed last ('' while healthy)
        self.closed_reason = ''      # why the host closed it on purpose ('' = it did not)
        self._ever_online = False
        self._failed_cycles = 0
        self._failed_this_cycle = False
        self._next_attempt = 0.0
        self._connect_failures_told: set[str] = set()   # kinds, since it was last online
        # going offline, per reason; quiet: the last offline was not logged, nor is
        # the reconnect after it
        self._offline_log = RepeatThrottle(OFFLINE_LOG_PERIOD)
        self._quiet = False

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
        self.failed_connects = 0
        self._failed_cycles = 0
        self.error = self.closed_reason = ''
        self._connect_failures_told.clear()
        if not self._quiet:
            log.info('%s online', self.name)

    def connect_failed(self, exc: VfdError) -> None:
        self.error = str(exc)
        self.closed_reason = ''
        self.failed_connects += 1
        self._next_attempt = self._clock() + self.retry_period
        # Why a drive stays offline (a value it refuses at connect, a silent node)
        # goes to the log once per kind of reason, not once per attempt: two that
        # alternate, or one naming the bytes received, were a line per attempt
        # (outside audit: 55 in 12 s).
        kind = failure_kind(self.error)
        told = self._connect_failures_told
        if kind not in told and len(told) < CONNECT_FAILURES_TOLD:
            told.add(kind)
            log.warning('%s: connect failed: %s', self.name, self.error)
        if self._offline_log.untold:
            self._tell_untold()

    def drop(self, reason: str) -> None:
        """Go offline now and connect afresh at once (the drive must be configured again)."""
        self._tell_offline(reason)
        self.online = False
        self.error = reason
        self._next_attempt = self._clock()

    def _tell_offline(self, reason: str) -> None:
        """Log going offline: once per reason and OFFLINE_LOG_PERIOD, with the repeats since."""
        told = self._offline_log.note(reason, self._clock())
        self._quiet = told is None
        if told is None:
            return
        repeats = f' (and {told.repeats} times more in the last {told.seconds:.0f} s)' \
            if told.repeats else ''
        log.warning('%s offline: %s%s', self.name, reason, repeats)

    def _tell_untold(self) -> None:
        """Log the offlines not logged yet once their period is over (the flapping stopped)."""
        for untold in self._offline_log.due(self._clock()):
            log.warning('%s was offline %d times more in the last %.0f s: %s', self.name,
                        untold.repeats, untold.seconds, untold.kind)

    @property
    def answering(self) -> bool:
        """Online and no exchange failed since the last good cycle."""
        return self.online and self._failed_cycles == 0 and not self._failed_this_cycle

    def cycle_ok(self) -> None:
        self._failed_cycles = 0
        if self._offline_log.untold:
            self._tell_untold()

    def cycle_failed(self, exc: VfdError) -> bool:
        """Count a failed exchange; return True when the drive just went offline."""
        if self._failed_this_cycle:
            return False
        self._failed_this_cycle = True
        self._failed_cycles += 1
        self.error = str(exc)
        if self.online and self._failed_cycles >= self.threshold:
            self._tell_offline(str(exc))
            self.online = False
            self._next_attempt = self._clock() + self.retry_period
            return True
        return False

    def closed(self, reason: str = 'the link is closed: the control loop ended') -> None:
        """Mark the link closed by the host on purpose (not a comm loss); ``reason`` says why."""
        self.online = False
        self.closed_reason = reason
        self.failed_connects = 0     # reopened later, it takes its turn afresh
