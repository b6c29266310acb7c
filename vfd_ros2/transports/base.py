"""The contract every transport fulfils: a link that moves raw values, nothing more.

A transport knows nothing of drives, profiles, scaling or ROS: it is built from
plain settings (``from_settings``), opens and closes its link, and moves raw
values (registers, objects) with bounded waits. The drive layer
(``vfd_ros2.drives``) turns a profile plus a transport into drive verbs.
"""

from __future__ import annotations

import abc
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any, ClassVar, Iterator, Mapping

from ..errors import TransportError


@dataclass(frozen=True)
class TransportParameter:
    """A setting the node declares as ``transport.<name>`` for this transport.

    ``minimum``/``maximum`` (inclusive; None = unbounded) become the ROS
    parameter's range, so ``ros2 param describe`` shows it.
    """

    name: str
    default: Any
    description: str
    minimum: float | None = None
    maximum: float | None = None


@dataclass
class TransportStats:
    """Counters of a transport (its whole link) or of one unit on it, since creation."""

    transactions: int = 0
    timeouts: int = 0
    bad_frames: int = 0
    exceptions: int = 0
    connect_failures: int = 0
    late_replies: int = 0      # well-formed replies that came after their timeout (discarded)
    bytes_sent: int = 0
    bytes_received: int = 0
    frames_sent: int = 0
    frames_received: int = 0

    @property
    def errors(self) -> int:
        return self.timeouts + self.bad_frames + self.exceptions + self.connect_failures


class Transport(abc.ABC):
    """A link to one or several drives, found by name through the plugin registry.

    Every method either completes within the configured timeout or raises a
    ``TransportError`` / ``ProtocolException``; none may block indefinitely.
    Calls come from one thread at a time. Which drive class serves a transport
    is decided by the drive registry from the transport's base class
    (``vfd_ros2.drives``): a ``RegisterTransport`` plugin gets ``ModbusDrive``.
    """

    #: settings the node declares for this transport (name, default, description)
    parameters: ClassVar[tuple[TransportParameter, ...]] = ()
    #: can several drives share one instance (one port, many slave ids)?
    shared_by_drives: ClassVar[bool] = True
    #: may one drive's connect run on a thread of its own while the link's thread
    #: serves the others? (A multi-master link with a channel per device, CANopen's
    #: SDO per node: a connect of dozens of SDO exchanges, or a silent node's
    #: timeouts, then never holds up the other drives' cycle. A half-duplex line,
    #: RS-485, has one exchange at a time: its connects take turns in the cycle.)
    connects_beside_the_cycle: ClassVar[bool] = False

    def __init__(self) -> None:
        self.stats = TransportStats()
        self._unit_stats: dict[int, TransportStats] = {}

    def stats_for(self, unit: int) -> TransportStats:
        """Return the counters of one unit (drive) on this link; ``stats`` sums the link."""
        found = self._unit_stats.get(unit)
        if found is None:       # (not setdefault: it would build a TransportStats each call)
            found = self._unit_stats[unit] = TransportStats()
        return found

    def count(self, unit: int | None, counter: str, amount: int = 1) -> None:
        """Add to a counter of the link and, when the unit is known, of that unit."""
        setattr(self.stats, counter, getattr(self.stats, counter) + amount)
        if unit is not None:
            unit_stats = self.stats_for(unit)
            setattr(unit_stats, counter, getattr(unit_stats, counter) + amount)

    @classmethod
    @abc.abstractmethod
    def from_settings(cls, settings: Mapping[str, Any]) -> 'Transport':
        """Build from plain ``transport.*`` values (every name of ``parameters`` is given).

        Drive-dependent defaults (e.g. a drive's factory baud rate where the
        setting is 0) are filled in by the drive layer before this is called.
        """

    @property
    @abc.abstractmethod
    def description(self) -> str:
        """Where this transport talks, for hardware ids and logs."""

    @property
    def link_notes(self) -> tuple[str, ...]:
        """What an operator should know about the link (shown in diagnostics as WARN)."""
        return ()

    def wire_seconds(self, byte_count: int, frames: int) -> float | None:
        """Time ``byte_count`` bytes in ``frames`` frames occupy the medium (None: unknown)."""
        return None

    def exchange_seconds(self, request_bytes: int, reply_bytes: int) -> float:
        """Worst-case time one healthy request/reply exchange occupies the link.

        Used to size the drive's own comm-loss timeout for the bus; links without
        a wire model (TCP) assume a LAN round trip plus the drive's processing.
        """
        return 0.005

    def failed_exchange_seconds(self) -> float:
        """Time one exchange with a silent drive occupies the link (its timeout)."""
        return float(getattr(self, 'timeout', 0.1))

    @contextmanager
    def hurried(self) -> Iterator[None]:
        """Within it, wait for a reply only as long as a healthy drive takes to begin one.

        For the pass of stops at a bus's end: a drive gone silent costs its whole
        timeout (raised for slow drives), and the drives after it keep running
        meanwhile. Where the link has no such wait to shorten, nothing changes.
        """
        yield

    @property
    def commands_keep_the_cycle(self) -> bool:
        """Return whether a new command should wait for the next cycle, not preempt it.

        True where the drives apply commands on a trigger the cycle produces at its
        own period (CANopen SYNC): an early burst would add a SYNC off the period
        (the drives' communication cycle) and, with commands streaming at the cycle
        rate, double the frames on the bus, to gain less than one period. A
        tripped watchdog's stop still preempts.
        """
        return False

    def end_command_burst(self) -> None:
        """Every drive on this link has written this cycle's command (or a preempt's).

        A link whose drives apply commands on a common trigger sends it here
        (CANopen: one SYNC after the RPDOs); the others need nothing. Never raises.
        """

    @abc.abstractmethod
    def open(self) -> None:
        """Open the link (idempotent). Raises TransportError if it cannot."""

    @abc.abstractmethod
    def close(self) -> None:
        """Close the link (idempotent, never raises)."""

    def __enter__(self) -> 'Transport':
        self.open()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class RegisterTransport(Transport):
    """Moves 16-bit register values to and from one unit on a link (Modbus style)."""

    @abc.abstractmethod
    def read_registers(self, unit: int, address: int, count: int) -> list[int]:
        """Read ``count`` holding registers starting at ``address``."""

    @abc.abstractmethod
    def write_register(self, unit: int, address: int, value: int) -> None:
        """Write one holding register (value 0..0xFFFF)."""

    @abc.abstractmethod
    def write_registers(self, unit: int, address: int, values: list[int]) -> None:
        """Write consecutive holding registers in one request."""

    #: can this link broadcast a write to every unit at once (unit 0, no reply)?
    broadcasts: ClassVar[bool] = False

    def broadcast_register(self, address: int, value: int) -> None:
        """Write one register of every unit at once, unanswered (only where ``broadcasts``)."""
        raise TransportError(f'{type(self).__name__} cannot broadcast')
