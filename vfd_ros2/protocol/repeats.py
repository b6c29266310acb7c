"""Events that repeat without end, and which of them a log tells.

A flapping drive, a loop error on every cycle, a babbling CAN node: the log must
show each kind once and how often it came, not each event. Two policies, one
class each; callers serialise their calls (a lock, or one thread) and pass the
monotonic time.
"""

from __future__ import annotations

from typing import Hashable, NamedTuple


class RepeatSummary:
    """Which of a stream of repeating events to log: the first of each kind, then sums.

    For a stream where one line per kind is enough for good (a babbling node's
    frames, its EMCY codes): ``first(key)`` is True for a key not seen since
    ``forget`` (while fewer than ``max_keys`` are known); any other event is a
    repeat, and ``due()`` returns how many repeats, of all kinds together, to sum
    up in one line, at most once per ``period`` s after the last line (0 otherwise).
    """

    def __init__(self, period: float = 10.0, max_keys: int | None = None) -> None:
        self.period = period
        self._max_keys = max_keys
        self._seen: set[Hashable] = set()
        self._repeats = 0
        self._quiet_until = 0.0     # no summary line before this (monotonic s)

    def first(self, key: Hashable, now: float) -> bool:
        """Return whether to log this event in full; otherwise it is counted as a repeat."""
        if key in self._seen or (self._max_keys is not None and
                                 len(self._seen) >= self._max_keys):
            self._repeats += 1
            return False
        self._seen.add(key)
        self._quiet_until = max(self._quiet_until, now + self.period)
        return True

    def due(self, now: float) -> int:
        """Return the repeats to sum up now (then counted afresh), or 0."""
        if not self._repeats or now < self._quiet_until:
            return 0
        repeats, self._repeats = self._repeats, 0
        self._quiet_until = now + self.period
        return repeats

    def forget(self) -> None:
        """Log each kind in full once more (e.g. after the drive's error reset)."""
        self._seen.clear()


class Untold(NamedTuple):
    """Repeats of one kind counted and not logged yet."""

    kind: Hashable
    repeats: int
    seconds: float          # since the kind was last told
    first: bool = False     # a kind not seen before (or forgotten): tell it in full


class RepeatThrottle:
    """Tell each kind of a repeating event at most once per ``period`` s, with its count.

    For events that matter each time they come back (a drive going offline, a loop
    error): ``note(kind)`` returns None for a repeat inside the kind's period (it is
    counted), otherwise the repeats counted since the kind was last told (``first``
    for a kind not seen: the caller tells it in full) and the period starts again.
    ``due()`` hands over the repeats whose period is over (all of them at the end),
    so a kind that repeated a few times and stopped is told too, not only one that
    comes back. At most ``max_kinds`` kinds are kept (texts may name values that
    vary freely): a new kind beyond them makes the least recently seen forgotten.
    """

    def __init__(self, period: float = 10.0, max_kinds: int = 32) -> None:
        self.period = period
        self.max_kinds = max_kinds
        self.untold = 0             # repeats counted and not handed over (cheap to test)
        self._kinds: dict[Hashable, list] = {}     # kind -> [last told, repeats since]

    def note(self, kind: Hashable, now: float) -> Untold | None:
        """Count one event; return the repeats to tell with it, or None: not to tell."""
        seen = self._kinds.pop(kind, None)
        if seen is not None:
            self._kinds[kind] = seen        # the least recently seen kind goes first
        else:
            if len(self._kinds) >= self.max_kinds:
                self.untold -= self._kinds.pop(next(iter(self._kinds)))[1]
            self._kinds[kind] = [now, 0]
            return Untold(kind, 0, 0.0, first=True)
        if now - seen[0] < self.period:
            seen[1] += 1
            self.untold += 1
            return None
        told = Untold(kind, seen[1], now - seen[0])
        self.untold -= seen[1]
        seen[:] = [now, 0]
        return told

    def due(self, now: float, at_end: bool = False) -> list[Untold]:
        """Return (and count as told) the repeats whose period is over, or all ``at_end``."""
        told = []
        for kind, seen in self._kinds.items():
            if seen[1] and (at_end or now - seen[0] >= self.period):
                told.append(Untold(kind, seen[1], now - seen[0]))
                self.untold -= seen[1]
                seen[:] = [now, 0]
        return told
