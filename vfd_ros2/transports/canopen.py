"""CANopen (CiA 301) transport on the ``canopen`` library: one ``Network`` per CAN channel.

Moves raw object values to and from the nodes of one CAN channel; knows nothing
of drives, profiles or scaling (``vfd_ros2.drives.canopen`` does). The library does the
protocol work:

- ``CanChannel``: one python-can bus and one ``canopen.Network`` (one notifier
  thread) per (interface, channel, bitrate, ``transport.can_options``) in this
  process, shared by every node and every transport on it, and closed with the last
  node (adapters such as PCAN or Kvaser allow one open handle per channel). The
  host heartbeat is produced once per channel with ``Network.send_periodic``.
- per node a ``canopen.RemoteNode``: ``sdo`` (expedited transfers; aborts arrive
  as ``SdoAbortedError`` and keep its CiA 301 text table), ``nmt`` (commands,
  heartbeat and boot-up reception), ``emcy`` (``EmcyConsumer``: active errors,
  error reset), ``rpdo``/``tpdo`` (``PdoMap``: the mapping saved over SDO, TPDOs
  received by the library, RPDOs transmitted from its map).

What the library does not do is all that is left here: a host-side heartbeat
consumer with a timeout (``check_alive``), the library's errors mapped by type
onto the driver's exception tree, per-node counters, and an object dictionary
built from the drive's objects when no EDS is given (``node_dictionary``, also
used by the simulated twin).
"""

from __future__ import annotations

import json
import logging
import math
import queue
import struct
import threading
import time
from dataclasses import dataclass, field
from typing import Any, Callable, Iterable, Mapping, NamedTuple

import can
import canopen
from canopen import objectdictionary as od
from canopen.emcy import EmcyError
from canopen.nmt import NMT_STATES

from ..errors import (
    BadFrame,
    CommTimeout,
    ParameterError,
    ProfileError,
    ProtocolException,
    TransportError,
)
from ..protocol.repeats import RepeatSummary
from ..protocol.values import ValueType
from .base import Transport, TransportParameter

log = logging.getLogger(__name__)

PDO_DISABLED = 0x80000000
#: the highest synchronous PDO transmission type (CiA 301: 0 acyclic, 1..240 every n-th SYNC)
SYNCHRONOUS_MAX = 240
#: COB-ID of the SYNC object (CiA 301 default 0x1005 = 0x80)
SYNC_COB_ID = 0x80
#: CiA 301 predefined COB-ID of a node's RPDO1 (+ node id)
RPDO1_BASE = 0x200
#: s a frame only this host should send, heard from another device, stays reported
FOREIGN_FRAMES_SHOWN = 10.0
#: the newest active EMCYs kept per node (the driver shows the last one)
ACTIVE_EMCY_KEPT = 8
#: the longest SDO upload the driver accepts (its values are 1..4 bytes; a
#: segmented transfer brings at most 7 per segment)
MAX_UPLOAD_BYTES = 8
#: CiA 301 SDO abort codes: data type does not match, length of service parameter
#: too high; client/server command specifier not valid or unknown
SDO_ABORT_LENGTH_TOO_HIGH = 0x06070012
SDO_ABORT_COMMAND_SPECIFIER = 0x05040001
#: CiA 301 SDO command bytes: initiate download, expedited, size indicated (the two
#: bits n = 4 - data bytes go in bits 2-3); the server's initiate download response
SDO_EXPEDITED_DOWNLOAD = 0x23
SDO_DOWNLOAD_CONFIRMED = 0x60
#: host heartbeats logged at INFO (channel, node id, period ms): each once per process
_HEARTBEATS_TOLD: set[tuple[str, int, int]] = set()

#: NMT state byte of Operational in a heartbeat (CiA 301); the host reports it too
NMT_OPERATIONAL = 0x05
#: s between two looks at a node's heartbeat while a connect waits for it
HEARTBEAT_POLL = 0.005
#: host heartbeat period bounds when derived from the control rate (s)
HOST_HEARTBEAT_MIN = 0.01
HOST_HEARTBEAT_MAX = 0.1

_DATA_TYPE = {
    ValueType.UINT8: od.UNSIGNED8, ValueType.INT8: od.INTEGER8,
    ValueType.UINT16: od.UNSIGNED16, ValueType.INT16: od.INTEGER16,
    ValueType.UINT32: od.UNSIGNED32, ValueType.INT32: od.INTEGER32,
}


def abort_text(code: int) -> str:
    """Return the CiA 301 text of an SDO abort code (the library's table)."""
    return canopen.SdoAbortedError.CODES.get(code, f'unknown SDO abort code 0x{code:08X}')


class SdoAbort(ProtocolException):
    """The node answered an SDO request with an abort code (CiA 301)."""

    def __init__(self, code: int, request: str = '') -> None:
        super().__init__(code, abort_text(code), request)
        where = f' to {request}' if request else ''
        self.args = (f'SDO abort 0x{code:08X} ({self.text}){where}',)

    def __str__(self) -> str:
        return self.args[0]


# --- object dictionaries (the driver's view of a node, and the twin's) -------------------


class ObjectEntry(NamedTuple):
    """One object of a node's dictionary: address, name, type, access, default."""

    index: int
    subindex: int
    name: str
    type: ValueType
    access: str = 'rw'
    default: int = 0


def od_variable(name: str, index: int, subindex: int, value_type: ValueType,
                access: str = 'rw', default: int = 0) -> od.ODVariable:
    """Return a typed object dictionary variable."""
    var = od.ODVariable(name, index, subindex)
    var.data_type = _DATA_TYPE[value_type]
    var.access_type = access
    var.default = default
    return var


def add_objects(dictionary: od.ObjectDictionary, entries: Iterable[ObjectEntry]) -> None:
    """Add variables; several sub-indices of one index become a record."""
    grouped: dict[int, list[ObjectEntry]] = {}
    for entry in entries:
        subs = grouped.setdefault(entry.index, [])
        if all(e.subindex != entry.subindex for e in subs):
            subs.append(entry)
    for index, subs in sorted(grouped.items()):
        if index in dictionary:
            continue
        if len(subs) == 1 and subs[0].subindex == 0:
            e = subs[0]
            dictionary.add_object(od_variable(e.name, index, 0, e.type, e.access, e.default))
            continue
        record = od.ODRecord(f'0x{index:04X}', index)
        record.add_member(od_variable('Number of entries', index, 0, ValueType.UINT8, 'ro',
                                      max(e.subindex for e in subs)))
        for e in subs:
            if e.subindex:
                record.add_member(od_variable(e.name, index, e.subindex, e.type, e.access,
                                              e.default))
        dictionary.add_object(record)


def add_pdo_objects(dictionary: od.ObjectDictionary, node_id: int, rpdos: int,
                    tpdos: int) -> None:
    """Add the PDO communication and mapping records (CiA 301 0x1400-0x1BFF)."""
    for kind, count, comm, mapping, cob_base in (('RPDO', rpdos, 0x1400, 0x1600, 0x200),
                                                 ('TPDO', tpdos, 0x1800, 0x1A00, 0x180)):
        for number in range(count):
            cob = cob_base + 0x100 * number + node_id if number < 4 else 0
            record = od.ODRecord(f'{kind}{number + 1} communication', comm + number)
            record.add_member(od_variable('Highest sub-index', comm + number, 0,
                                          ValueType.UINT8, 'ro', 5))
            record.add_member(od_variable('COB-ID', comm + number, 1, ValueType.UINT32, 'rw',
                                          PDO_DISABLED | cob))
            record.add_member(od_variable('Transmission type', comm + number, 2,
                                          ValueType.UINT8, 'rw', 255))
            if kind == 'TPDO':
                record.add_member(od_variable('Inhibit time', comm + number, 3,
                                              ValueType.UINT16, 'rw'))
            # RPDO: deadline monitoring; TPDO: event timer
            record.add_member(od_variable('Event timer', comm + number, 5, ValueType.UINT16,
                                          'rw'))
            dictionary.add_object(record)
            record = od.ODRecord(f'{kind}{number + 1} mapping', mapping + number)
            record.add_member(od_variable('Number of mapped objects', mapping + number, 0,
                                          ValueType.UINT8, 'rw'))
            for sub in range(1, 9):
                record.add_member(od_variable(f'Mapped object {sub}', mapping + number, sub,
                                              ValueType.UINT32, 'rw'))
            dictionary.add_object(record)


def node_dictionary(node_id: int, objects: Iterable[ObjectEntry], rpdos: int,
                    tpdos: int) -> od.ObjectDictionary:
    """Return the dictionary the library needs for a node: PDO records and mapped objects."""
    dictionary = od.ObjectDictionary()
    add_pdo_objects(dictionary, node_id, rpdos, tpdos)
    add_objects(dictionary, objects)
    return dictionary


def _codec(index: int, subindex: int, value_type: ValueType) -> od.ODVariable:
    return od_variable(f'0x{index:04X}:{subindex:02X}', index, subindex, value_type)


#: ``can.Bus`` arguments that have their own transport settings (a second value in the
#: options would make the call fail with a TypeError, or silently win)
_OWN_ARGUMENTS = {'interface': 'transport.interface', 'channel': 'transport.channel',
                  'bitrate': 'transport.bitrate'}


class MalformedFrames:
    """Frames the library could not take (an EMCY or heartbeat too short, ...), by node.

    The library's receive path logs every such frame at ERROR with its exception
    text only ("unpack requires a buffer of 8 bytes"), naming neither the frame
    nor the node: a babbling node floods the console. Here the first frame of
    each COB-ID is logged with its bytes, repeats are summed up at most every
    ``repeats.period`` s, and each node's count reaches its transport's
    ``bad_frames`` (``take``).
    """

    def __init__(self, label: str = 'CAN') -> None:
        self.label = label          # the channel, in log lines
        self.repeats = RepeatSummary()
        self._lock = threading.Lock()
        self._untaken: dict[int, int] = {}       # node id -> frames not yet counted

    def record(self, can_id: int, data: bytes, exc: Exception) -> None:
        """Count one frame the library raised on (its notifier thread)."""
        now = time.monotonic()
        with self._lock:
            node = can_id & 0x7F
            self._untaken[node] = self._untaken.get(node, 0) + 1
            first = self.repeats.first(can_id, now)
            summary = self.repeats.due(now)
        if first:
            log.warning('%s: malformed frame 0x%03X [%d] %s from node %d ignored (%s); '
                        'repeats are summed up every %g s', self.label, can_id,
                        len(data), bytes(data).hex(' ') or '-', node, exc,
                        self.repeats.period)
        if summary:
            log.warning('%s: %d more malformed frames ignored', self.label, summary)

    def take(self, node: int) -> int:
        """Return how many frames of ``node`` were malformed since the last call."""
        with self._lock:
            return self._untaken.pop(node, 0)


class GuardedNetwork(canopen.Network):
    """``canopen.Network`` that hands a frame the library raises on to ``malformed``.

    It also counts frames only this host should send (``watch``): heard from the
    bus, another device sends them (this process does not hear its own).
    """

    def __init__(self, bus: Any = None) -> None:
        super().__init__(bus)
        self.malformed = MalformedFrames()
        self.watch: frozenset[int] = frozenset()    # COB-IDs only this host sends
        self.foreign: dict[int, tuple[int, float]] = {}   # -> (frames heard, last when)

    def notify(self, can_id: int, data: bytearray, timestamp: float) -> None:
        if can_id in self.watch:
            count = self.foreign.get(can_id, (0, 0.0))[0] + 1
            self.foreign[can_id] = (count, time.monotonic())
        try:
            super().notify(can_id, data, timestamp)
        except Exception as exc:  # noqa: BLE001 - whatever a callback raises on bad bytes
            self.malformed.record(can_id, bytes(data), exc)


def quick_closing_network(bus: Any = None) -> GuardedNetwork:
    """Return a ``GuardedNetwork`` whose ``disconnect`` joins its notifier thread.

    The library waits ``NOTIFIER_SHUTDOWN_TIMEOUT`` for the notifier thread and then
    closes the bus anyway; a thread still blocked in a receive that long (its
    ``NOTIFIER_CYCLE``, 1 s by default: as long as the 1 s wait kept for quick closing)
    then reads a closed socket and dies with an exception (python-can's socketcand
    client: EBADF). A receive cycle well inside the wait leaves no thread behind.
    """
    network = GuardedNetwork(bus)
    network.NOTIFIER_CYCLE = 0.2
    network.NOTIFIER_SHUTDOWN_TIMEOUT = 1.0
    return network


def parse_can_options(options: str | Mapping[str, Any] | None) -> dict[str, Any]:
    """Return the extra ``can.Bus`` keyword arguments of ``transport.can_options``.

    A ROS parameter cannot be a mapping, so the setting is a JSON object in a string
    ('' = none); a bus file may also give a YAML mapping. Raises ParameterError for bad
    JSON, a non-object, or an argument that has its own setting.
    """
    if options is None or options == '':
        return {}
    if isinstance(options, str):
        try:
            parsed = json.loads(options)
        except ValueError as exc:
            raise ParameterError(f'transport.can_options is not valid JSON ({exc}): '
                                 f'{options!r}') from exc
    else:
        parsed = options
    if not isinstance(parsed, Mapping):
        raise ParameterError('transport.can_options must be a JSON object of can.Bus keyword '
                             f'arguments (e.g. {{"host": "127.0.0.1", "port": 29536}}), got '
                             f'{type(parsed).__name__}: {options!r}')
    for key in parsed:
        if not isinstance(key, str) or not key.isidentifier():
            raise ParameterError(f'transport.can_options: {key!r} is not a keyword argument name')
        if key in _OWN_ARGUMENTS:
            raise ParameterError(f'transport.can_options: set {key!r} with '
                                 f'{_OWN_ARGUMENTS[key]}, not here')
    return dict(parsed)


def check_interface(interface: str, options: Mapping[str, Any]) -> None:
    """Refuse what no channel could ever open (ParameterError), instead of retrying it.

    An interface python-can does not know, and socketcand without the bridge's
    address (its ``host`` and ``port`` are can.Bus arguments: ``transport.can_options``).
    """
    if interface not in can.VALID_INTERFACES:
        raise ParameterError(f'transport.interface {interface!r} is not a python-can '
                             f'interface (it has: {", ".join(sorted(can.VALID_INTERFACES))})')
    if interface == 'socketcand':
        missing = [key for key in ('host', 'port') if key not in options]
        if missing:
            raise ParameterError(
                "transport.interface socketcand needs the bridge's address in "
                f'transport.can_options: {", ".join(missing)} missing (e.g. '
                '{"host": "127.0.0.1", "port": 29536})')
        port = options['port']
        if isinstance(port, bool) or not isinstance(port, int) or not 0 < port < 65536:
            raise ParameterError(f'transport.can_options port {port!r}: a TCP port number')


#: python-can interfaces whose bus takes no bit rate: the interface keeps its own
#: (socketcan: ``ip link set can0 type can bitrate ...``; socketcand: its host's)
BITRATE_NOT_TAKEN = frozenset({'socketcan', 'socketcand', 'virtual', 'udp_multicast'})


# --- the channel: one bus, one Network, one host heartbeat --------------------------------

class _DropMessage(logging.Filter):
    """Drop a library's log records whose message starts with ``prefix``; others pass."""

    def __init__(self, prefix: str) -> None:
        super().__init__()
        self.prefix = prefix

    def filter(self, record: logging.LogRecord) -> bool:
        return not str(record.msg).startswith(self.prefix)


class _ThrottleMessage(logging.Filter):
    """Pass a library's record whose message starts with ``prefix`` once per ``period`` s.

    The one that passes says how many were dropped since; other records pass.
    """

    def __init__(self, prefix: str, period: float) -> None:
        super().__init__()
        self.prefix, self.period = prefix, period
        self._passed_at = -math.inf
        self._dropped = 0
        self._lock = threading.Lock()

    def filter(self, record: logging.LogRecord) -> bool:
        if not str(record.msg).startswith(self.prefix):
            return True
        now = time.monotonic()
        with self._lock:
            if now - self._passed_at < self.period:
                self._dropped += 1
                return False
            dropped, self._dropped, self._passed_at = self._dropped, 0, now
        if dropped:
            record.msg = f'{record.msg} ({dropped} more like it in the last {self.period:g} s)'
        return True


#: python-can socketcand's warning for a TCP read that ends inside a frame. Ordinary on
#: a stream (the client keeps the rest for the next read), it came for most reads at a
#: few thousand frames/s: a flood on bus_node's console, written from the receive
#: thread. The client's other warnings (a frame it cannot parse) pass.
_PARTIAL_READS = _DropMessage('Got incomplete message')

#: ... and its warning for each failed reconnect: once the daemon is gone it retries in a
#: tight loop for 10 s (184,351 lines in 3 s when a simulated drive's process ended
#: first: outside re-check). One a second says it, with the count.
_RECONNECTS = _ThrottleMessage('Failed to connect to server', 1.0)

#: the canopen library's ERROR line for each SDO transfer this host aborts. Every abort
#: comes from a call of this transport (a timeout, an endless upload), which reports it
#: itself, with the node and the object, as an error of that drive. The library's line
#: names neither; with a node unplugged it came at each reconnect attempt, several a
#: second, for as long as the node stayed away.
_CLIENT_ABORTS = _DropMessage('Transfer aborted by client')

_CHANNELS: dict[tuple[str, str, int, str], 'CanChannel'] = {}
_CHANNELS_LOCK = threading.Lock()


def open_channels() -> list['CanChannel']:
    """Return the CAN channels this process has open (for diagnostics and tests)."""
    with _CHANNELS_LOCK:
        return list(_CHANNELS.values())


class CanChannel:
    """One CAN channel of this process: python-can bus, ``canopen.Network``, host heartbeat.

    Reference-counted: ``acquire`` opens the bus the first time and ``release``
    closes it with the last user, so every node on the channel shares one handle
    and one notifier thread, whichever transport or thread drives it.
    """

    def __init__(self, key: tuple[str, str, int, str], network: canopen.Network) -> None:
        self.key = key
        self.network = network
        if isinstance(network, GuardedNetwork):
            network.malformed.label = self.description
        self.users = 0
        self.lock = threading.Lock()
        self.host_node_id: int | None = None
        self.heartbeat_period = 0.0
        self._heartbeat: Any = None
        self._sequence = 0          # RPDOs and SYNCs sent by this process, in order
        self._last_sync = -1

    def rpdo_sent(self) -> int:
        """Count an RPDO sent on this channel; return its place in the order."""
        with self.lock:
            self._sequence += 1
            return self._sequence

    def sync_after(self, rpdo: int) -> bool:
        """Send a SYNC unless one went out after RPDO ``rpdo`` already; return if sent.

        Several transports of this process on one channel (drive_nodes) then send
        one SYNC per burst between them, not one each.
        """
        with self.lock:
            if self._last_sync > rpdo:
                return False
            self.network.sync.transmit()
            self._sequence += 1
            self._last_sync = self._sequence
            return True

    @property
    def description(self) -> str:
        return f'can:{self.key[0]}:{self.key[1]}'

    @classmethod
    def acquire(cls, interface: str, channel: str, bitrate: int = 0,
                bus_factory: Callable[..., Any] | None = None,
                options: Mapping[str, Any] | None = None) -> 'CanChannel':
        """Return the open channel (opening it if needed) with one more user.

        ``options``: extra ``can.Bus`` keyword arguments (``parse_can_options``). They
        are part of the channel's identity: 'can0' behind two socketcand servers (two
        host/port pairs) is two buses.
        """
        extra = dict(options or {})
        key = (interface, channel, int(bitrate), json.dumps(extra, sort_keys=True))
        with _CHANNELS_LOCK:
            found = _CHANNELS.get(key)
            if found is None:
                logging.getLogger('canopen.sdo.client').addFilter(_CLIENT_ABORTS)
                kwargs: dict[str, Any] = {**extra, 'interface': interface, 'channel': channel}
                if interface == 'socketcand':
                    client_log = logging.getLogger('can.interfaces.socketcand.socketcand')
                    client_log.addFilter(_PARTIAL_READS)
                    client_log.addFilter(_RECONNECTS)
                if bitrate:
                    kwargs['bitrate'] = int(bitrate)
                try:
                    bus = (bus_factory or can.Bus)(**kwargs)
                except (can.CanError, OSError, ValueError, ImportError) as exc:
                    raise TransportError(f'cannot open CAN {interface}:{channel}: {exc}') from exc
                except TypeError as exc:     # an option the interface does not take
                    raise ParameterError(f'cannot open CAN {interface}:{channel} with '
                                         f'transport.can_options {extra}: {exc}') from exc
                network = quick_closing_network(bus)
                network.connect()
                found = _CHANNELS[key] = cls(key, network)
            found.users += 1
            return found

    def release(self) -> None:
        """Drop one user; the last one stops the heartbeat and closes the bus."""
        with _CHANNELS_LOCK:
            self.users -= 1
            if self.users > 0:
                return
            if _CHANNELS.get(self.key) is self:
                del _CHANNELS[self.key]
        self.stop_heartbeat()
        try:
            self.network.disconnect()
        except Exception as exc:  # noqa: BLE001 - close never raises
            log.debug('closing %s: %s', self.description, exc)

    def produce_heartbeat(self, node_id: int, period: float) -> None:
        """Produce the host heartbeat (0x700 + node_id) every ``period`` s, or faster.

        One producer per channel: a shorter period asked later replaces a longer
        one (a faster heartbeat satisfies every consumer sized for the slower).
        """
        with self.lock:
            if self._heartbeat is not None:
                if node_id != self.host_node_id:
                    raise ParameterError(
                        f'{self.description} already produces the host heartbeat as node '
                        f'{self.host_node_id}; transport.host_node_id {node_id} differs')
                if period >= self.heartbeat_period - 1e-9:
                    return
                self._heartbeat.stop()
                self._heartbeat = None
            try:
                self._heartbeat = self.network.send_periodic(
                    0x700 + node_id, bytes((NMT_OPERATIONAL,)), period)
            except (can.CanError, OSError, RuntimeError, NotImplementedError) as exc:
                raise TransportError(f'cannot produce the host heartbeat on '
                                     f'{self.description}: {exc}') from exc
            self.host_node_id, self.heartbeat_period = node_id, period
            # Once per channel and period: a drive offline reopens the channel at each
            # attempt, and this was an INFO line three times a second (outside audit).
            told = (self.description, node_id, round(period * 1000))
            log.log(logging.DEBUG if told in _HEARTBEATS_TOLD else logging.INFO,
                    '%s: host heartbeat as node %d every %.0f ms', *told)
            _HEARTBEATS_TOLD.add(told)

    def stop_heartbeat(self) -> None:
        """Stop the host heartbeat (at close; tests use it to play a dead host)."""
        with self.lock:
            task, self._heartbeat = self._heartbeat, None
            self.heartbeat_period = 0.0
        if task is not None:
            try:
                task.stop()
            except Exception as exc:  # noqa: BLE001 - a dead bus may refuse
                log.debug('stopping the heartbeat on %s: %s', self.description, exc)


# --- the transport ------------------------------------------------------------------------


@dataclass
class _Link:
    """One node of this transport: its dictionary, its RemoteNode and its supervision."""

    unit: int
    dictionary: od.ObjectDictionary
    node: Any = None
    last_heartbeat: float | None = None
    nmt_state: int | None = None
    not_operational: int = 0       # consecutive heartbeats not reporting Operational
    booted: bool = False
    supervise_timeout: float = 0.0
    supervise_from: float = 0.0
    subscriptions: list[tuple[int, Callable[..., None]]] = field(default_factory=list)
    bad_tpdo: dict[int, float] = field(default_factory=dict)
    tpdo_stamp: dict[int, float] = field(default_factory=dict)   # the last frame's stamp
    tpdo_heard: dict[int, float] = field(default_factory=dict)   # when it was taken (host)
    synchronous: bool = False      # its RPDOs take effect at the next SYNC


class CanopenTransport(Transport):
    """The CANopen nodes of one CAN channel (socketcan, virtual, pcan, ...).

    Shared by every drive on the channel (``shared_by_drives``): each drive
    ``attach``-es its node id; every per-node call takes that id first.
    """

    parameters = (
        TransportParameter('interface', 'socketcan',
                           'python-can interface: socketcan, virtual, ...'),
        TransportParameter('channel', 'can0', 'CAN channel (virtual: any name shared in-process)'),
        TransportParameter('bitrate', 0, 'bit/s; 0 = leave the interface as configured', 0,
                           10_000_000),
        TransportParameter('eds_file', '', 'optional EDS/DCF of the nodes (object types)'),
        TransportParameter('timeout', 0.1, 's per SDO reply', 0.001, 10.0),
        TransportParameter('heartbeat_ms', 0, "producer heartbeat written to 0x1017; 0 = the "
                           "profile's", 0, 65535),
        TransportParameter('heartbeat_timeout', 0.0, 's without heartbeat before offline; 0 = '
                           "the profile's factor x heartbeat_ms", 0.0, 60.0),
        TransportParameter('host_node_id', 127, "the host's node id: its heartbeat (0x700 + id) "
                           "and the drives' heartbeat consumer (0x1016) use it", 1, 127),
        TransportParameter('host_heartbeat_ms', 0, 'host heartbeat period; 0 = the control '
                           'period (10..100 ms)', 0, 65535),
        TransportParameter('sync_producer', True, "send SYNC (0x080) after each cycle's RPDOs "
                           'where the drives use synchronous PDOs; false when another device '
                           '(or process) on the bus produces SYNC'),
        TransportParameter('can_options', '', 'extra can.Bus keyword arguments as a JSON '
                           'object, e.g. {"host": "127.0.0.1", "port": 29536, "tcp_tune": '
                           'true} for socketcand; empty = none'),
    )
    shared_by_drives = True    # one transport per channel; bus_node opens the channel once
    connects_beside_the_cycle = True    # SDO per node: the others' RPDOs go on meanwhile

    def __init__(self, interface: str = 'virtual', channel: str = 'vcan0', bitrate: int = 0,
                 timeout: float = 0.1, eds_file: str = '', heartbeat_ms: int = 0,
                 heartbeat_timeout: float = 0.0, host_node_id: int = 127,
                 host_heartbeat_ms: int = 0, sync_producer: bool = True,
                 can_options: str | Mapping[str, Any] | None = None,
                 bus_factory: Callable[..., Any] | None = None) -> None:
        super().__init__()
        if not timeout > 0:
            raise ParameterError(f'transport.timeout must be > 0, got {timeout}')
        if not 1 <= int(host_node_id) <= 127:
            raise ParameterError(f'transport.host_node_id {host_node_id} is outside 1..127')
        if not 0 <= int(host_heartbeat_ms) <= 0xFFFF:
            raise ParameterError(f'transport.host_heartbeat_ms {host_heartbeat_ms} is outside '
                                 '0..65535')
        self.can_options = parse_can_options(can_options)
        if bus_factory is None:
            check_interface(interface, self.can_options)
        self.interface = interface
        self.channel_name = channel
        self.bitrate = int(bitrate)
        self.timeout = float(timeout)
        self.eds_file = eds_file
        self.heartbeat_ms = int(heartbeat_ms)
        self.heartbeat_timeout = float(heartbeat_timeout)
        self.host_node_id = int(host_node_id)
        self.host_heartbeat_ms = int(host_heartbeat_ms)
        self.sync_producer = bool(sync_producer)
        self.syncs = 0                 # SYNC frames sent
        self._last_rpdo = 0            # the channel's order number of this transport's last RPDO
        self._bus_factory = bus_factory
        self.channel: CanChannel | None = None
        self._links: dict[int, _Link] = {}
        self._lock = threading.Lock()

    @classmethod
    def from_settings(cls, settings: Mapping[str, Any]) -> 'CanopenTransport':
        return cls(interface=str(settings.get('interface', 'socketcan')),
                   channel=str(settings.get('channel', 'can0')),
                   bitrate=int(settings.get('bitrate', 0) or 0),
                   timeout=float(settings.get('timeout', 0.1) or 0.1),
                   eds_file=str(settings.get('eds_file', '') or ''),
                   heartbeat_ms=int(settings.get('heartbeat_ms', 0) or 0),
                   heartbeat_timeout=float(settings.get('heartbeat_timeout', 0.0) or 0.0),
                   host_node_id=int(settings.get('host_node_id', 127) or 127),
                   host_heartbeat_ms=int(settings.get('host_heartbeat_ms', 0) or 0),
                   sync_producer=bool(settings.get('sync_producer', True)),
                   can_options=settings.get('can_options', '') or '')

    @property
    def description(self) -> str:
        return f'can:{self.interface}:{self.channel_name}'

    @property
    def link_notes(self) -> tuple[str, ...]:
        """What the channel shows is wrong with its set-up (diagnostics WARN).

        A bit rate asked of an interface that takes none, and frames only this host
        sends coming from another device in the last FOREIGN_FRAMES_SHOWN s: a second
        SYNC producer, a second host commanding one of these drives. (Not the host
        heartbeat: socketcan loops a periodic task's frames back to this process.)
        """
        notes = []
        if self.bitrate and self.interface in BITRATE_NOT_TAKEN:
            notes.append(f"transport.bitrate {self.bitrate} is not applied: python-can's "
                         f'{self.interface} interface keeps the bit rate it has (socketcan: '
                         f'ip link set {self.channel_name} type can bitrate {self.bitrate})')
        channel = self.channel
        network = channel.network if channel is not None else None
        now = time.monotonic()
        for cob_id, (count, last) in sorted(getattr(network, 'foreign', {}).items()):
            if now - last < FOREIGN_FRAMES_SHOWN:      # a tool plugged in once: not for ever
                notes.append(self._foreign_note(cob_id, count))
        return tuple(note for note in notes if note)

    def _foreign_note(self, cob_id: int, count: int) -> str:
        heard = f'{count} heard on {self.description}'
        if cob_id == SYNC_COB_ID and self.sync_producer:
            return (f'another device sends SYNC ({heard}): two SYNC producers (a second host '
                    'or process?); transport.sync_producer false on all but one')
        unit = cob_id - RPDO1_BASE
        if unit in self._links:
            return (f'another device sends RPDO1 to node {unit} ({heard}): a second host '
                    'commands this drive')
        return ''

    def _watch_foreign(self) -> None:
        """Tell the channel which frames only this host sends (see ``link_notes``)."""
        network = self.channel.network if self.channel is not None else None
        if not isinstance(network, GuardedNetwork):
            return
        mine = {RPDO1_BASE + unit for unit in self._links}
        if self.sync_producer:
            mine.add(SYNC_COB_ID)
        network.watch = network.watch | mine

    # --- nodes and the channel --------------------------------------------------------

    def attach(self, unit: int, objects: Iterable[ObjectEntry], rpdos: int, tpdos: int) -> None:
        """Declare node ``unit`` and the objects its PDOs carry (no I/O)."""
        if not 1 <= unit <= 127:
            raise ParameterError(f'CANopen node id {unit} is outside 1..127')
        if unit == self.host_node_id:
            raise ParameterError(f"CANopen node id {unit} is the host's own "
                                 '(transport.host_node_id)')
        if unit in self._links:
            raise ParameterError(f'CANopen node id {unit} is used twice on {self.description}')
        self._links[unit] = _Link(unit, self._dictionary(unit, list(objects), rpdos, tpdos))

    def _dictionary(self, unit: int, objects: list[ObjectEntry], rpdos: int,
                    tpdos: int) -> od.ObjectDictionary:
        built = node_dictionary(unit, objects, rpdos, tpdos)
        if not self.eds_file:
            return built
        try:
            dictionary = canopen.import_od(self.eds_file, unit)
        except Exception as exc:  # noqa: BLE001 - any parse error of a user file
            raise ParameterError(f'cannot load EDS {self.eds_file}: {exc}') from exc
        for index in built:           # what the EDS lacks, the drive's objects supply
            if index not in dictionary:
                dictionary.add_object(built[index])
        return dictionary

    def open(self) -> None:
        """Join the channel (idempotent); the nodes are opened one by one."""
        if self.channel is not None:
            return
        try:
            self.channel = CanChannel.acquire(self.interface, self.channel_name, self.bitrate,
                                              self._bus_factory, self.can_options)
        except TransportError:
            self.stats.connect_failures += 1
            raise
        self._watch_foreign()

    def close(self) -> None:
        """Close every node of this transport and leave the channel (idempotent)."""
        for link in self._links.values():
            self._close_link(link)
        channel, self.channel = self.channel, None
        if channel is not None:
            channel.release()

    def open_node(self, unit: int) -> None:
        """Open node ``unit`` afresh: a new RemoteNode, nothing heard from it yet."""
        link = self._link(unit)
        self.open()
        if link.node is not None:
            self._close_link(link)
        channel = self.channel
        node = canopen.RemoteNode(unit, link.dictionary)
        node.sdo.RESPONSE_TIMEOUT = self.timeout
        node.sdo.MAX_RETRIES = 1
        node.nmt.add_heartbeat_callback(lambda state, link=link: self._on_heartbeat(link, state))
        with self._lock:              # nothing heard yet (before frames can arrive)
            link.last_heartbeat = link.nmt_state = None
            link.not_operational = 0
            link.booted = False
            link.supervise_timeout = 0.0
            link.bad_tpdo.clear()
            link.tpdo_stamp.clear()
            link.tpdo_heard.clear()
        with channel.lock:
            if channel.network.nodes.get(unit) is not None:
                raise ParameterError(f'CANopen node id {unit} is already driven on '
                                     f'{self.description} by another transport')
            channel.network.add_node(node)
        link.node = node

    def close_node(self, unit: int) -> None:
        """Close node ``unit``; the transport leaves the channel with its last node."""
        link = self._links.get(unit)
        if link is not None and link.node is not None:
            self._close_link(link)
        if all(other.node is None for other in self._links.values()):
            self.close()

    def _close_link(self, link: _Link) -> None:
        node, link.node = link.node, None
        channel = self.channel
        if node is None or channel is None:
            return
        network = channel.network
        with channel.lock:
            for cob_id, callback in link.subscriptions:
                try:
                    network.unsubscribe(cob_id, callback)
                except (KeyError, ValueError):
                    pass
            link.subscriptions.clear()
            if network.nodes.get(link.unit) is node:
                del network[link.unit]

    def _link(self, unit: int) -> _Link:
        link = self._links.get(unit)
        if link is None:
            raise ParameterError(f'CANopen node {unit} is not attached to {self.description}')
        return link

    def _node(self, unit: int) -> Any:
        node = self._link(unit).node
        if node is None:
            raise TransportError(f'node {unit} on {self.description} is not open')
        return node

    # --- SDO ------------------------------------------------------------------------

    def read_object(self, unit: int, index: int, subindex: int, value_type: ValueType) -> int:
        """Expedited SDO upload of one typed value."""
        node = self._node(unit)
        what = f'read 0x{index:04X}:{subindex:02X}'
        data = self._sdo(unit, what, lambda: self._bounded_upload(node, index, subindex))
        size = value_type.bits // 8
        try:
            return _codec(index, subindex, value_type).decode_raw(bytes(data[:size]))
        except od.ObjectDictionaryError as exc:
            self.count(unit, 'bad_frames')
            raise BadFrame(f'{len(data)} bytes from node {unit} to {what} for a '
                           f'{value_type.value}') from exc

    @staticmethod
    def _bounded_upload(node: Any, index: int, subindex: int) -> bytes:
        """Upload a value of at most 4 bytes: expedited, or a short segmented transfer.

        The library's ``upload`` reads segments until the node says it is done: a
        node that never does would hold the control thread (and with it every
        stop) for ever. A value the driver reads fits one or two segments.
        """
        data = b''
        with node.sdo.open(index, subindex, buffering=0) as stream:
            while chunk := stream.read(7):
                data += chunk
                if len(data) > MAX_UPLOAD_BYTES:
                    node.sdo.abort(SDO_ABORT_LENGTH_TOO_HIGH)
                    raise canopen.SdoCommunicationError(
                        f'the node sends more than {MAX_UPLOAD_BYTES} bytes')
        return data

    @staticmethod
    def _expedited_download(node: Any, index: int, subindex: int, data: bytes) -> None:
        """Write 1..4 bytes in one expedited download; the reply must confirm this object.

        The library's ``download`` takes any download reply as the confirmation,
        even one that names another object (CiA 301 7.2.4.3.3: it echoes the
        multiplexer).
        """
        request = bytearray(8)
        request[0] = SDO_EXPEDITED_DOWNLOAD | (4 - len(data)) << 2
        struct.pack_into('<HB', request, 1, index, subindex)
        request[4:4 + len(data)] = data
        reply = node.sdo.request_response(request)
        command, confirmed_index, confirmed_subindex = struct.unpack_from('<BHB', reply)
        if command != SDO_DOWNLOAD_CONFIRMED:
            node.sdo.abort(SDO_ABORT_COMMAND_SPECIFIER)
            raise canopen.SdoCommunicationError(f'Unexpected response 0x{command:02X}')
        if (confirmed_index, confirmed_subindex) != (index, subindex):
            raise canopen.SdoCommunicationError(
                f'the node confirmed a write of 0x{confirmed_index:04X}:'
                f'{confirmed_subindex:02X}')

    def write_object(self, unit: int, index: int, subindex: int, value_type: ValueType,
                     raw: int) -> None:
        """Expedited SDO download of one typed value (1, 2 or 4 bytes)."""
        node = self._node(unit)
        try:
            data = _codec(index, subindex, value_type).encode_raw(int(raw))
        except ValueError as exc:
            raise ParameterError(f'raw value {raw} does not fit {value_type.value}') from exc
        self._sdo(unit, f'write 0x{index:04X}:{subindex:02X} = {raw}',
                  lambda: self._expedited_download(node, index, subindex, bytes(data)))

    def _sdo(self, unit: int, what: str, call: Callable[[], Any]) -> Any:
        """Run SDO exchanges; aborts, silence and bus errors become the driver's errors."""
        self.count(unit, 'transactions')
        try:
            return call()
        except canopen.SdoAbortedError as exc:
            self.count(unit, 'exceptions')
            raise SdoAbort(exc.code, what) from exc
        except canopen.SdoCommunicationError as exc:
            # The library raises this one type for silence (raised while handling its
            # queue.Empty) and for an unexpected reply.
            if isinstance(exc.__context__, queue.Empty):
                self.count(unit, 'timeouts')
                raise CommTimeout(f'no SDO reply from node {unit} to {what}: {exc}') from exc
            self.count(unit, 'bad_frames')
            raise BadFrame(f'unexpected SDO reply from node {unit} to {what}: {exc}') from exc
        except struct.error as exc:      # the library unpacks a reply shorter than 8 bytes
            self.count(unit, 'bad_frames')
            raise BadFrame(f'a short SDO reply from node {unit} to {what}') from exc
        except (can.CanError, OSError, RuntimeError) as exc:
            self.count(unit, 'bad_frames')
            raise TransportError(f'{what} on node {unit} failed: {exc}') from exc
        except (KeyError, od.ObjectDictionaryError) as exc:     # e.g. an EDS without it
            raise ProfileError(f'{what} on node {unit}: not in its object dictionary: '
                               f'{exc}') from exc

    def _send(self, unit: int, what: str, call: Callable[[], None]) -> None:
        """Send frames (NMT, RPDO); a bus that refuses becomes a TransportError."""
        self.count(unit, 'transactions')
        try:
            call()
        except (can.CanError, OSError, RuntimeError) as exc:
            self.count(unit, 'bad_frames')
            raise TransportError(f'cannot send {what} on {self.description}: {exc}') from exc

    @property
    def commands_keep_the_cycle(self) -> bool:
        """Return whether this transport's SYNC applies the commands (see Transport)."""
        return self.sync_producer and any(link.synchronous and link.node is not None
                                          for link in self._links.values())

    def end_command_burst(self) -> None:
        """Send one SYNC after the cycle's RPDOs when a node applies them on SYNC."""
        channel = self.channel
        if channel is None or not self.commands_keep_the_cycle:
            return
        try:
            if channel.sync_after(self._last_rpdo):
                self.syncs += 1
        except (can.CanError, OSError, RuntimeError) as exc:
            # The RPDOs of the next cycle meet the same bus and report it per drive.
            log.debug('SYNC on %s: %s', self.description, exc)

    # --- NMT, PDO, EMCY ---------------------------------------------------------------

    def nmt(self, unit: int, state: str) -> None:
        """Command node ``unit`` into an NMT state ('OPERATIONAL', 'PRE-OPERATIONAL', ...)."""
        node = self._node(unit)
        self._send(unit, f'NMT {state} to node {unit}', lambda: setattr(node.nmt, 'state', state))

    def map_pdo(self, unit: int, kind: str, number: int, objects: list[ObjectEntry],
                transmission_type: int = 255, event_timer_ms: int = 0) -> None:
        """Configure PDO ``number`` ('rpdo'/'tpdo') over SDO; no objects: disable it."""
        node = self._node(unit)
        pdo = (node.rpdo if kind == 'rpdo' else node.tpdo).map[number]
        pdo.clear()
        for obj in objects:
            if pdo.add_variable(obj.index, obj.subindex) is None:
                raise ParameterError(f'{obj} is not in the object dictionary of node {unit}')
        pdo.enabled = bool(objects)
        pdo.trans_type = transmission_type if objects else None
        pdo.event_timer = event_timer_ms if objects and event_timer_ms else None
        if pdo.predefined_cob_id is not None:
            pdo.cob_id = pdo.predefined_cob_id
        else:
            pdo.cob_id = self._sdo(unit, f'read {pdo.com_record.od.name}',
                                   lambda: pdo.com_record[1].raw) & 0x1FFFFFFF
        self._sdo(unit, f'{kind.upper()}{number} mapping', pdo.save)
        link = self._link(unit)
        if pdo.enabled and kind == 'tpdo':      # save() subscribed it for reception
            link.subscriptions.append((pdo.cob_id, pdo.on_message))
        elif pdo.enabled and self.channel is not None:
            # save() subscribes an RPDO too, which this host sends and never takes in (a
            # second host's would be written into its map): each reconnect left one
            # behind, holding the node it was made for
            with self.channel.lock:
                try:
                    self.channel.network.unsubscribe(pdo.cob_id, pdo.on_message)
                except (KeyError, ValueError):
                    pass
        if kind == 'rpdo' and number == 1:
            link.synchronous = bool(objects) and transmission_type <= SYNCHRONOUS_MAX

    def transmit(self, unit: int, number: int, raws: list[int]) -> bytes:
        """Send RPDO ``number`` with the mapped objects' raw values; return its payload."""
        node = self._node(unit)
        pdo = node.rpdo.map[number]
        try:
            for var, raw in zip(pdo.map, raws):
                var.raw = int(raw)
        except ValueError as exc:
            raise ParameterError(f'RPDO{number} of node {unit}: {exc}') from exc
        self._send(unit, f'RPDO{number} to node {unit}', pdo.transmit)
        if self.channel is not None:
            self._last_rpdo = self.channel.rpdo_sent()
        return bytes(pdo.data)

    def received(self, unit: int, number: int) -> list[int] | None:
        """Raw values of TPDO ``number`` as last received (None: none yet, or malformed)."""
        link = self._link(unit)
        node = link.node
        if node is None:
            return None
        pdo = node.tpdo.map[number]
        stamp, data = pdo.timestamp, pdo.data      # one frame: the library replaces both
        if stamp is None:
            return None
        if len(data) * 8 < pdo.length:
            if link.bad_tpdo.get(number) != stamp:
                link.bad_tpdo[number] = stamp
                self.count(unit, 'bad_frames')
            return None
        if link.tpdo_stamp.get(number) != stamp:
            link.tpdo_stamp[number] = stamp
            link.tpdo_heard[number] = time.monotonic()
        values = []
        for var in pdo.map:
            start = var.offset // 8
            values.append(var.od.decode_raw(bytes(data[start:start + var.length // 8])))
        return values

    def tpdo_malformed(self, unit: int, number: int) -> str | None:
        """Say what was wrong with the newest TPDO ``number`` of ``unit``; None if nothing.

        Read after ``received``: a node that sends its TPDO too short (a mapping that
        differs from the one written) is then told from a node that sends none.
        """
        node = self._link(unit).node
        if node is None:
            return None
        pdo = node.tpdo.map[number]
        stamp, data = pdo.timestamp, pdo.data      # one frame: the library replaces both
        if stamp is None or len(data) * 8 >= pdo.length:
            return None
        return (f'TPDO{number} from node {unit} has {len(data)} bytes where its mapping '
                f'needs {pdo.length // 8}')

    def tpdo_heard(self, unit: int, number: int) -> float | None:
        """Return when ``received`` first took the newest well-formed TPDO ``number``.

        This host's monotonic clock; None: none from node ``unit`` since it opened.
        """
        return self._link(unit).tpdo_heard.get(number)

    def take_emcy(self, unit: int) -> tuple[list[EmcyError], list[EmcyError]]:
        """Return (EMCYs received since the last call, the active ones) of node ``unit``."""
        node = self._link(unit).node
        if node is None:
            return [], []
        consumer = node.emcy
        with consumer.emcy_received:
            new = list(consumer.log)
            consumer.log.clear()          # the library keeps every EMCY otherwise
            # ...and appends every EMCY to ``active`` until an error reset (code 00xx):
            # a drive that repeats a warning for hours would grow it without bound.
            del consumer.active[:-ACTIVE_EMCY_KEPT]
            active = list(consumer.active)
        return new, active

    # --- heartbeats -------------------------------------------------------------------

    def host_heartbeat_period(self, interval: float) -> float:
        """Host heartbeat period: the setting, or ``interval`` (the control period) in bounds."""
        if self.host_heartbeat_ms:
            return self.host_heartbeat_ms / 1000.0
        period = math.ceil(interval * 1000 - 1e-6) / 1000.0
        return min(max(period, HOST_HEARTBEAT_MIN), HOST_HEARTBEAT_MAX)

    def produce_heartbeat(self, period: float) -> None:
        """Produce the host heartbeat on this channel (once per channel; see CanChannel)."""
        if self.channel is None:
            raise TransportError(f'{self.description} is not open')
        self.channel.produce_heartbeat(self.host_node_id, period)

    def supervise(self, unit: int, timeout: float) -> None:
        """Start the host-side consumer of node ``unit``'s heartbeat (0 = off)."""
        link = self._link(unit)
        with self._lock:
            link.supervise_timeout = timeout
            link.supervise_from = time.monotonic()
            link.booted = False
            link.not_operational = 0

    def await_operational(self, unit: int, wait: float) -> str | None:
        """Wait up to ``wait`` s for node ``unit``'s heartbeats since ``supervise`` to agree.

        Return None once one reports Operational (or one that is not came, alone, in
        time: the supervision judges), else the state two in a row report instead
        (the first may have been in flight when NMT start was sent): a node that
        ignores NMT start, which must not be taken for a started one. Raise
        CommTimeout when none came: taken online, such a node was dropped by the
        supervision at once and connected again, twice a second (outside audit).
        """
        link = self._link(unit)
        deadline = time.monotonic() + wait
        while True:
            with self._lock:
                heard = link.last_heartbeat is not None and \
                    link.last_heartbeat >= link.supervise_from
                state, refused = link.nmt_state, link.not_operational >= 2
            if heard and state == NMT_OPERATIONAL:
                return None
            if refused and state is not None:
                return NMT_STATES.get(state, f'0x{state:02X}')
            if time.monotonic() >= deadline:
                if heard:
                    return None
                self.count(unit, 'timeouts')
                raise CommTimeout(f'no heartbeat from node {unit} within {wait:.2f} s of '
                                  'NMT start (its producer time 0x1017 was written)')
            time.sleep(HEARTBEAT_POLL)

    def check_alive(self, unit: int) -> str | None:
        """Raise when node ``unit``'s heartbeat is lost or it rebooted; return its NMT state.

        The state (the library's name, e.g. 'OPERATIONAL') is returned only once two
        heartbeats in a row agree (one may have been in flight when an NMT command
        was sent).
        """
        link = self._link(unit)
        if self.channel is not None:
            malformed = self.channel.network.malformed.take(unit)
            if malformed:
                self.count(unit, 'bad_frames', malformed)
        with self._lock:
            timeout, last, booted = link.supervise_timeout, link.last_heartbeat, link.booted
            since, state = link.supervise_from, link.nmt_state
            confirmed = state == NMT_OPERATIONAL or link.not_operational >= 2
        if booted:
            raise TransportError(f'node {unit} sent a boot-up: it reset and must be '
                                 're-configured')
        if timeout > 0:
            age = time.monotonic() - max(last or 0.0, since)
            if age > timeout:
                self.count(unit, 'timeouts')
                raise CommTimeout(f'no heartbeat from node {unit} for {age:.2f} s '
                                  f'(consumer timeout {timeout:.2f} s)')
        if state is None or not confirmed:
            return None
        return NMT_STATES.get(state, f'0x{state:02X}')

    def _on_heartbeat(self, link: _Link, state: int) -> None:
        """Library heartbeat callback (notifier thread): stamp it on this host's clock.

        ``nmt.timestamp`` is the frame's time from the adapter, which need not be
        this host's monotonic clock; the reception time here is.
        """
        with self._lock:
            link.last_heartbeat = time.monotonic()
            link.nmt_state = state
            link.not_operational = 0 if state == NMT_OPERATIONAL else link.not_operational + 1
            if state == 0 and link.supervise_timeout > 0:
                link.booted = True
