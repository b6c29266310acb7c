"""Modbus RTU and Modbus TCP transports on pymodbus.

``ModbusRtuTransport`` drives RTU transactions itself (``rtu_link.RtuLink``:
pymodbus' RTU framer and PDUs over pyserial, reads of exactly the reply's
length, deadlines from the baud rate). ``PymodbusRtuTransport`` is the same
API on pymodbus' stock synchronous serial client, kept for comparison (the
benchmark measures both in one run) and as a fallback. ``ModbusTcpTransport``
uses pymodbus' synchronous TCP client.
"""

from __future__ import annotations

import logging
import select
import socket
import struct
from contextlib import contextmanager
from typing import Any, Callable, Iterator, Mapping, NamedTuple

from . import modbus_library  # noqa: F401 - the pymodbus version check, before pymodbus

# isort: split

from pymodbus import FramerType
from pymodbus.client import ModbusSerialClient, ModbusTcpClient
from pymodbus.exceptions import ConnectionException, ModbusException, ModbusIOException
from pymodbus.pdu import ExceptionResponse, ModbusPDU
from pymodbus.pdu.register_message import (
    ReadHoldingRegistersRequest,
    WriteMultipleRegistersRequest,
    WriteSingleRegisterRequest,
)

from ..errors import BadFrame, CommTimeout, ParameterError, ProtocolException, TransportError
from ..protocol.rtu_timing import character_time, frame_gap, reply_size, transaction_time
from .base import RegisterTransport, TransportParameter, TransportStats
from .rtu_link import LinkBadFrame, LinkLost, LinkTimeout, RtuLink

# The driver counts and reports every failed exchange itself (status counters,
# diagnostics); pymodbus' own error logging would repeat each one per cycle.
logging.getLogger('pymodbus').setLevel(logging.CRITICAL)
log = logging.getLogger(__name__)

#: Modbus exception codes as the specification defines them; the drive layer
#: re-explains them with the drive's own manual (some drives use 3 for "CRC error").
STANDARD_EXCEPTIONS: dict[int, str] = {
    1: 'illegal function',
    2: 'illegal data address',
    3: 'illegal data value',
    4: 'server device failure',
    5: 'acknowledge',
    6: 'server device busy',
    8: 'memory parity error',
    10: 'gateway path unavailable',
    11: 'gateway target device failed to respond',
}


#: requests kept for reuse: a drive's status reads and its command writes (while the
#: command holds) are a few per drive; services and backups may name any address or
#: value, so the store is emptied when full
REQUESTS_KEPT = 512

#: transaction ids back a reply may be to be taken for a late one (Modbus TCP): the
#: reply to an earlier request, after its timeout, not a malformed one
LATE_REPLY_WINDOW = 64


class _ModbusTransport(RegisterTransport):
    """What every Modbus transport shares: the requests, reply checks and counters.

    A subclass only implements ``_exchange``: put one request PDU on its link and
    return the reply PDU, raising CommTimeout / BadFrame / TransportError (and
    counting them with ``count``). Every reply is checked against its request as
    far as the protocol allows: unit (by the link), function, byte count of a
    read, echoed address and value of a single write, address and count of a
    multiple write.
    """

    def __init__(self) -> None:
        super().__init__()
        # (function, unit, address, count or values) -> its request: a drive's status reads
        # and, while a command holds, its command writes repeat every cycle, so their PDUs
        # (and, on RTU, their frames) are built once
        self._requests: dict[tuple[int, ...], ModbusPDU] = {}

    def _exchange(self, request: ModbusPDU, reply_bytes: int) -> ModbusPDU:
        raise NotImplementedError

    @staticmethod
    def _what(request: ModbusPDU) -> str:
        """Name an exchange for an error message (built only when one is raised)."""
        unit, address, registers = request.dev_id, request.address, request.registers
        if isinstance(request, ReadHoldingRegistersRequest):
            return f'read {request.count} @ {address:#06x} (unit {unit})'
        if isinstance(request, WriteSingleRegisterRequest):
            return f'write {registers[0]:#06x} @ {address:#06x} (unit {unit})'
        return f'write {len(registers)} @ {address:#06x} (unit {unit})'

    def _execute(self, request: ModbusPDU, reply_bytes: int) -> ModbusPDU:
        self.open()
        unit = request.dev_id
        # (``count`` by name would cost as much as the rest of the counting, twice a
        # transaction: these two counters are bumped in place)
        stats, unit_stats = self.stats, self.stats_for(unit)
        stats.frames_sent += 1
        unit_stats.frames_sent += 1
        reply = self._exchange(request, reply_bytes)
        stats.frames_received += 1
        unit_stats.frames_received += 1
        if (reply.function_code & 0x7F) != request.function_code:
            # pymodbus pairs a TCP reply by transaction id alone and decodes whatever
            # function it names: a reply to another function is not this one's value.
            raise self._mismatch(request, f'the reply is to function '
                                 f'{reply.function_code & 0x7F}, not {request.function_code}')
        if isinstance(reply, ExceptionResponse):
            raise self._refused(request, reply.exception_code)
        if reply.isError():
            self.count(unit, 'bad_frames')
            raise BadFrame(f'{self._what(request)}: error reply {reply}')
        return reply

    def _refused(self, request: ModbusPDU, code: int) -> ProtocolException:
        """Count an exception reply to ``request`` and return it as a ProtocolException."""
        self.count(request.dev_id, 'exceptions')
        return ProtocolException(code, STANDARD_EXCEPTIONS.get(code, 'unknown exception'),
                                 self._what(request))

    def _keep(self, key: tuple[int, ...], request: ModbusPDU) -> ModbusPDU:
        """Keep ``request`` for reuse under ``key`` (function, unit, address, count or values)."""
        if len(self._requests) >= REQUESTS_KEPT:
            self._requests.clear()
        self._requests[key] = request
        return request

    def _mismatch(self, request: ModbusPDU, problem: str) -> BadFrame:
        self.count(request.dev_id, 'bad_frames')
        return BadFrame(f'{self._what(request)}: {problem}')

    def read_registers(self, unit: int, address: int, count: int) -> list[int]:
        key = (3, unit, address, count)
        request = self._requests.get(key) or self._keep(
            key, ReadHoldingRegistersRequest(address=address, count=count, dev_id=unit))
        registers = self._execute(request, reply_size(3, count)).registers
        if len(registers) != count:
            raise self._mismatch(request, f'got {len(registers)} registers')
        self.count(unit, 'transactions')
        return list(registers)

    def write_register(self, unit: int, address: int, value: int) -> None:
        value &= 0xFFFF
        key = (6, unit, address, value)
        request = self._requests.get(key) or self._keep(
            key, WriteSingleRegisterRequest(address=address, registers=[value], dev_id=unit))
        reply = self._execute(request, reply_size(6))
        echoed = reply.registers[0] if reply.registers else None
        if reply.address != address or echoed != value:
            # The spec's reply to 06 is an echo of the request: anything else was
            # not this write's reply (or the drive did not store the value).
            shown = 'nothing' if echoed is None else f'{echoed:#06x}'
            raise self._mismatch(request, f'echo names {shown} @ {reply.address:#06x}')
        self.count(unit, 'transactions')

    def write_registers(self, unit: int, address: int, values: list[int]) -> None:
        registers = [v & 0xFFFF for v in values]
        key = (16, unit, address, *registers)
        request = self._requests.get(key) or self._keep(
            key, WriteMultipleRegistersRequest(address=address, registers=registers, dev_id=unit))
        reply = self._execute(request, reply_size(16))
        if reply.address != address or reply.count != len(values):
            raise self._mismatch(request,
                                 f'reply names {reply.count} @ {reply.address:#06x}')
        self.count(unit, 'transactions')


class _PymodbusTransport(_ModbusTransport):
    """A transport on one of pymodbus' synchronous clients (TCP; RTU for comparison)."""

    def __init__(self) -> None:
        super().__init__()
        self._received = b''
        self._client: ModbusSerialClient | ModbusTcpClient = self._make_client()

    def _make_client(self) -> ModbusSerialClient | ModbusTcpClient:
        raise NotImplementedError

    def _trace_packet(self, sending: bool, data: bytes) -> bytes:
        # pymodbus hands over the accumulated receive buffer; remembering it
        # tells a silent drive (timeout) from a garbled reply (bad frame).
        if sending:
            self.stats.bytes_sent += len(data)
        else:
            self._received = data
        return data

    def _unpaired(self, request: ModbusPDU) -> TransportError:
        """Count and return the error for a reply pymodbus did not pair with ``request``."""
        self.count(request.dev_id, 'bad_frames')
        return BadFrame(f'{self._what(request)}: malformed reply {self._received.hex(" ")}')

    def open(self) -> None:
        try:
            connected = self._client.connect()
        except (OSError, ModbusException) as exc:
            self.count(None, 'connect_failures')
            raise TransportError(f'cannot open {self.description}: {exc}') from exc
        if not connected:
            self.count(None, 'connect_failures')
            raise TransportError(f'cannot open {self.description}')

    def close(self) -> None:
        try:
            self._client.close()
        except (OSError, ModbusException):
            pass

    def _client_execute(self, request: ModbusPDU) -> ModbusPDU:
        return self._client.execute(False, request)

    def _exchange(self, request: ModbusPDU, reply_bytes: int) -> ModbusPDU:
        self._received = b''
        unit = request.dev_id
        try:
            return self._client_execute(request)
        except (ConnectionException, ConnectionError) as exc:
            # (a reset by the peer, too: a gateway taking one connection; no bad frame)
            self.count(unit, 'connect_failures')
            self.close()
            raise TransportError(f'{self._what(request)}: link lost ({self.description}): '
                                 f'{exc}') from exc
        except ModbusIOException as exc:
            if self._received:
                raise self._unpaired(request) from exc
            self.count(unit, 'timeouts')
            raise CommTimeout(f'{self._what(request)}: {exc} from {self.description}') from exc
        except (ModbusException, OSError, ValueError) as exc:
            self.count(unit, 'bad_frames')
            self.close()
            raise TransportError(f'{self._what(request)}: {exc}') from exc
        finally:
            self.stats.bytes_received += len(self._received)


#: s per exchange for the slave's and the host's turnaround (a slave's response time
#: is not part of the wire time; drives answer within ~1 ms, the host adds ~0.3 ms)
TURNAROUND = 0.0015
#: s a reply may take to begin in a hurried pass (``hurried``: the stops at a bus's end),
#: against the transport's timeout: drives answer within milliseconds; a slower one is
#: asked again with the whole timeout after the others
HURRIED_REPLY = 0.05


class _RtuSettings:
    """Settings, factory defaults and wire arithmetic shared by both RTU transports."""

    parameters = (
        TransportParameter('port', '/dev/ttyUSB0', 'serial device of the RS-485 line'),
        TransportParameter('baudrate', 0, "bit/s; 0 = the drive's factory setting", 0,
                           10_000_000),
        TransportParameter('parity', '', "N, E or O; empty = the drive's factory setting"),
        TransportParameter('stopbits', 0, "1 or 2; 0 = the drive's factory setting", 0, 2),
        TransportParameter('timeout', 0.1, 'reply timeout in seconds', 0.001, 10.0),
        TransportParameter('frame_gap', -1.0,
                           's of line silence kept before each request; -1 = t3.5 for the '
                           'baud rate (3.5 characters, 1.75 ms above 19200 baud), 0 = none',
                           -1.0, 1.0),
        TransportParameter('late_reply_guard', -1.0,
                           's a unit is not asked again after it timed out, so that a late '
                           'reply is discarded, not taken for the next one; -1 = timeout',
                           -1.0, 10.0),
        TransportParameter('low_latency', True,
                           'ask the serial driver for low-latency mode (USB adapters hold '
                           'replies for their latency timer otherwise); refusal is reported'),
        TransportParameter('echo', False,
                           'the adapter hears its own transmission: read it back and check it'),
        TransportParameter('broadcast_turnaround', 0.02,
                           's of silence after a broadcast write, for the slaves to process it',
                           0.0, 1.0),
        TransportParameter('broadcast_stops', True,
                           'a bus stops all its drives in one broadcast frame (unit 0) where '
                           'they share the stop writes (all watchdogs tripped, the end); false '
                           'on a line shared with other Modbus devices, which would execute '
                           'the same writes'),
    )
    port: str
    baudrate: int
    parity: str
    stopbits: int
    bytesize: int

    @classmethod
    def from_settings(cls, settings: Mapping[str, Any]) -> Any:
        gap = float(settings.get('frame_gap', -1.0))
        guard = float(settings.get('late_reply_guard', -1.0))
        baudrate, parity, stopbits = (int(settings['baudrate']), str(settings['parity']),
                                      int(settings['stopbits']))
        if not baudrate or not parity or not stopbits:
            raise ParameterError(f'{cls.__name__}: baudrate, parity and stopbits must be set '
                                 '(the drive layer fills in the factory values for 0 / "")')
        if parity not in ('N', 'E', 'O'):
            raise ParameterError(f'transport.parity {parity!r}: N, E or O (empty = the '
                                 "drive's factory setting)")
        return cls(port=str(settings['port']), baudrate=baudrate, parity=parity,
                   stopbits=stopbits, bytesize=int(settings.get('bytesize', 8)),
                   timeout=float(settings['timeout']),
                   frame_gap=gap if gap >= 0 else None,
                   late_reply_guard=guard if guard >= 0 else None,
                   low_latency=bool(settings.get('low_latency', True)),
                   echo=bool(settings.get('echo', False)),
                   broadcast_turnaround=float(settings.get('broadcast_turnaround', 0.02)),
                   broadcast_stops=bool(settings.get('broadcast_stops', True)))

    @property
    def description(self) -> str:
        return f'{self.port}@{self.baudrate}-{self.bytesize}{self.parity}{self.stopbits}'

    def wire_seconds(self, byte_count: int, frames: int) -> float:
        """Characters on the wire plus the t3.5 silence each frame needs (rtu_timing)."""
        char = character_time(self.baudrate, self.parity, self.stopbits, self.bytesize)
        return byte_count * char + frames * frame_gap(self.baudrate, char)

    def exchange_seconds(self, request_bytes: int, reply_bytes: int) -> float:
        """Both frames, both t3.5 silences, and the turnarounds of slave and host."""
        char = character_time(self.baudrate, self.parity, self.stopbits, self.bytesize)
        return transaction_time(request_bytes, reply_bytes, char,
                                frame_gap(self.baudrate, char)) + TURNAROUND

    def failed_exchange_seconds(self) -> float:
        """Return the request and the timeout (the late-reply guard holds only that unit)."""
        return self.exchange_seconds(8, 0) + self.timeout


class _KeptRequest(NamedTuple):
    """A request the RTU transport sends again and again, ready to go."""

    request: ModbusPDU
    frame: bytes
    unit_stats: TransportStats


#: register count -> a function unpacking that many big-endian words from a read reply
_WORDS: dict[int, Callable[[bytes, int], tuple[int, ...]]] = {}


def _words(count: int) -> Callable[[bytes, int], tuple[int, ...]]:
    _WORDS[count] = unpack = struct.Struct(f'>{count}H').unpack_from
    return unpack


class ModbusRtuTransport(_RtuSettings, _ModbusTransport):
    """Modbus RTU over a serial port (RS-485 adapter, or a pseudo-terminal).

    Transactions run on ``RtuLink``: pymodbus frames and decodes, the reply is
    read by its known length with deadlines derived from the baud rate, and the
    line is kept silent for t3.5 between frames (``frame_gap``: None = the
    spec's value for the baud rate, 0 = none).
    """

    def __init__(self, port: str, baudrate: int = 19200, parity: str = 'N',
                 stopbits: int = 1, bytesize: int = 8, timeout: float = 0.1,
                 frame_gap: float | None = None, late_reply_guard: float | None = None,
                 low_latency: bool = True, echo: bool = False,
                 broadcast_turnaround: float = 0.02, broadcast_stops: bool = True) -> None:
        super().__init__()
        self.broadcast_turnaround = broadcast_turnaround
        self.broadcast_stops = broadcast_stops
        self.port = port
        self.baudrate = baudrate
        self.parity = parity
        self.stopbits = stopbits
        self.bytesize = bytesize
        self.timeout = timeout
        # (function, unit, address, count or value) -> its request, frame and counters: the
        # cycle's reads and single writes (read_registers, write_register)
        self._frames: dict[tuple[int, ...], _KeptRequest] = {}
        self._link = RtuLink(port, baudrate, parity, stopbits, bytesize, timeout,
                             frame_gap_s=frame_gap, late_reply_guard=late_reply_guard,
                             low_latency=low_latency, echo=echo,
                             counters=self.stats, on_discard=self._count_discarded)

    broadcasts = True

    @property
    def link_notes(self) -> tuple[str, ...]:
        return self._link.link_notes

    def broadcast_register(self, address: int, value: int) -> None:
        """Write one register of every slave at once (unit 0: executed by all, unanswered)."""
        self.open()
        request = WriteSingleRegisterRequest(address=address, registers=[value & 0xFFFF],
                                             dev_id=0)
        self.count(None, 'frames_sent')
        try:
            self._link.broadcast(request, self.broadcast_turnaround)
        except LinkLost as exc:
            self.count(None, 'connect_failures')
            self.close()
            raise TransportError(f'broadcast @ {address:#06x}: link lost '
                                 f'({self.description}): {exc}') from exc

    @property
    def late_reply_guard(self) -> float:
        return self._link.late_reply_guard

    @contextmanager
    def hurried(self) -> Iterator[None]:
        link, kept = self._link, self._link.timeout
        link.timeout = min(kept, HURRIED_REPLY)
        try:
            yield
        finally:
            link.timeout = kept

    def _count_discarded(self, unit: int | None, kind: str) -> None:
        self.count(unit, 'late_replies' if kind == 'late' else 'bad_frames')

    def open(self) -> None:
        if self._link.is_open:
            return
        try:
            self._link.open()
        except LinkLost as exc:
            self.count(None, 'connect_failures')
            raise TransportError(f'cannot open {self.description}: {exc}') from exc

    def close(self) -> None:
        self._link.close()

    # The two requests of every cycle, a status read (03) and a command write (06), go
    # as kept frames and their replies are checked and unpacked from the frame here:
    # building and decoding pymodbus PDUs was a quarter of a drive-cycle's interpreted
    # steps (bench section 5a). Any other request, and any reply not of this request's
    # function and unit, still goes through pymodbus' PDU classes.

    def read_registers(self, unit: int, address: int, count: int) -> list[int]:
        key = (3, unit, address, count)
        kept = self._frames.get(key) or self._keep_frame(
            key, ReadHoldingRegistersRequest(address=address, count=count, dev_id=unit))
        reply = self._exchange_frame(kept, 5 + 2 * count)
        if reply[2] != 2 * count:
            raise self._mismatch(kept.request, f'byte count {reply[2]}, not {2 * count}')
        registers = (_WORDS.get(count) or _words(count))(reply, 3)
        self.stats.transactions += 1
        kept.unit_stats.transactions += 1
        return list(registers)

    def write_register(self, unit: int, address: int, value: int) -> None:
        value &= 0xFFFF
        key = (6, unit, address, value)
        kept = self._frames.get(key) or self._keep_frame(
            key, WriteSingleRegisterRequest(address=address, registers=[value], dev_id=unit))
        reply = self._exchange_frame(kept, 8)
        if reply[2:6] != kept.frame[2:6]:
            # The spec's reply to 06 is an echo of the request: anything else was
            # not this write's reply (or the drive did not store the value).
            raise self._mismatch(kept.request, f'echo names {reply[4] << 8 | reply[5]:#06x} @ '
                                 f'{reply[2] << 8 | reply[3]:#06x}')
        self.stats.transactions += 1
        kept.unit_stats.transactions += 1

    def _keep_frame(self, key: tuple[int, ...], request: ModbusPDU) -> _KeptRequest:
        """Keep ``request``, its frame and its unit's counters under ``key`` (see ``_keep``)."""
        if len(self._frames) >= REQUESTS_KEPT:
            self._frames.clear()
        kept = self._frames[key] = _KeptRequest(request, self._link.build_frame(request),
                                                self.stats_for(request.dev_id))
        return kept

    def _exchange_frame(self, kept: _KeptRequest, reply_bytes: int) -> bytes:
        """Exchange a kept request's frame; return a normal reply of its function and unit."""
        if not self._link.is_open:
            self.open()
        stats, unit_stats = self.stats, kept.unit_stats
        stats.frames_sent += 1
        unit_stats.frames_sent += 1
        try:
            reply = self._link.exchange(kept.frame, reply_bytes)
        except (LinkLost, LinkTimeout, LinkBadFrame) as exc:
            raise self._link_failure(kept.request, exc) from exc
        stats.frames_received += 1
        unit_stats.frames_received += 1
        if reply[1] & 0x80:
            raise self._refused(kept.request, reply[2])
        return reply

    def _exchange(self, request: ModbusPDU, reply_bytes: int) -> ModbusPDU:
        try:
            return self._link.transact(request, reply_bytes)
        except (LinkLost, LinkTimeout, LinkBadFrame) as exc:
            raise self._link_failure(request, exc) from exc

    def _link_failure(self, request: ModbusPDU,
                      exc: LinkLost | LinkTimeout | LinkBadFrame) -> TransportError:
        """Count a failed exchange and return the transport's error for it."""
        unit = request.dev_id
        if isinstance(exc, LinkLost):
            self.count(unit, 'connect_failures')
            self.close()
            return TransportError(f'{self._what(request)}: link lost ({self.description}): '
                                  f'{exc}')
        if isinstance(exc, LinkTimeout):
            self.count(unit, 'timeouts')
            return CommTimeout(f'{self._what(request)}: {exc} from {self.description}')
        self.count(unit, 'bad_frames')
        return BadFrame(f'{self._what(request)}: {exc} {exc.data.hex(" ")}')


class PymodbusRtuTransport(_RtuSettings, _PymodbusTransport):
    """Modbus RTU on pymodbus' stock synchronous serial client (the reference).

    ``frame_gap``, ``late_reply_guard``, ``low_latency`` and ``echo`` are accepted
    for a common signature but have no effect: the stock client sends as soon as it
    is called.
    """

    def __init__(self, port: str, baudrate: int = 19200, parity: str = 'N',
                 stopbits: int = 1, bytesize: int = 8, timeout: float = 0.1,
                 frame_gap: float | None = None, late_reply_guard: float | None = None,
                 low_latency: bool = True, echo: bool = False,
                 broadcast_turnaround: float = 0.02, broadcast_stops: bool = True) -> None:
        self.port = port
        self.baudrate = baudrate
        self.parity = parity
        self.stopbits = stopbits
        self.bytesize = bytesize
        self.timeout = timeout
        super().__init__()

    def _make_client(self) -> ModbusSerialClient:
        return ModbusSerialClient(
            self.port, framer=FramerType.RTU, baudrate=self.baudrate, parity=self.parity,
            stopbits=self.stopbits, bytesize=self.bytesize, timeout=self.timeout, retries=0,
            trace_packet=self._trace_packet)


class ModbusTcpTransport(_PymodbusTransport):
    """Modbus TCP (e.g. a drive's Ethernet option card)."""

    parameters = (
        TransportParameter('host', '127.0.0.1', "IP address of the drive's Modbus TCP card"),
        TransportParameter('port', 502, 'TCP port', 1, 65535),
        TransportParameter('timeout', 0.2, 'reply timeout in seconds', 0.001, 10.0),
    )

    def __init__(self, host: str, port: int = 502, timeout: float = 0.2) -> None:
        self.host = host
        self.port = port
        self.timeout = timeout
        self._fresh = False       # the connection was made for the coming exchange
        super().__init__()

    @classmethod
    def from_settings(cls, settings: Mapping[str, Any]) -> 'ModbusTcpTransport':
        return cls(host=str(settings['host']), port=int(settings['port']),
                   timeout=float(settings['timeout']))

    def _make_client(self) -> ModbusTcpClient:
        return ModbusTcpClient(self.host, port=self.port, timeout=self.timeout, retries=0,
                               reconnect_delay=0, trace_packet=self._trace_packet)

    @property
    def description(self) -> str:
        return f'tcp://{self.host}:{self.port}'

    def open(self) -> None:
        if self._peer_closed():
            # The card or gateway closed the connection between two exchanges (some
            # close after every reply, or after an idle time): connect afresh now,
            # rather than send into it and fail every other exchange.
            log.debug('%s closed the connection: connecting again', self.description)
            self.close()
        if self._client.socket is None:
            super().open()
            self._fresh = True

    def _unpaired(self, request: ModbusPDU) -> TransportError:
        """Tell a timeout that heard only a late reply to an earlier request from a bad frame.

        pymodbus skips a reply whose transaction id is not the request's, then times
        out: the bytes it received were counted as a malformed reply (outside audit),
        where this request had none and an earlier one's came late.
        """
        received = self._received
        tid = int.from_bytes(received[:2], 'big') if len(received) >= 8 else -1
        if not 0 < request.transaction_id - tid <= LATE_REPLY_WINDOW:
            return super()._unpaired(request)
        self.count(request.dev_id, 'late_replies')
        self.count(request.dev_id, 'timeouts')
        return CommTimeout(f'{self._what(request)}: no reply from {self.description} in '
                           f'time (only a late one to an earlier request, transaction id '
                           f'{tid}, came: discarded)')

    def _client_execute(self, request: ModbusPDU) -> ModbusPDU:
        """Execute; on a reused connection the peer dropped meanwhile, once more afresh.

        A peer that closes after each reply may do so just after this side looked
        (``open``) and before it sent: the request then meets the close. Only a
        connection that was already in use is tried again, once, on a new one (a new
        connection that fails is the drive's failure); register reads and writes
        are idempotent, so the repeat changes nothing the first did.
        """
        reused, self._fresh = not self._fresh, False
        try:
            return self._client.execute(False, request)
        except (ConnectionException, ConnectionError) as exc:
            if not reused:
                raise
            log.debug('%s: %s on a reused connection: once more on a new one',
                      self.description, exc)
            self.close()
            if not self._client.connect():
                raise
            return self._client.execute(False, request)

    def _peer_closed(self) -> bool:
        """Return whether the open connection was closed (or reset) by the other end."""
        sock = self._client.socket
        if sock is None:
            return False
        try:
            if not select.select([sock], [], [], 0)[0]:
                return False                   # nothing arrived: still open
            return sock.recv(1, socket.MSG_PEEK) == b''      # b'': the peer's FIN
        except BlockingIOError:
            return False
        except OSError:
            return True                        # reset, or the socket is broken
