"""A thin Modbus RTU master over pyserial, framed by pymodbus.

pymodbus builds every request frame (``FramerRTU.buildFrame`` over its request
PDUs, so the bytes on the wire are exactly the stock client's; a request the
transport sends again and again, a status read or an unchanged command, is built
once) and tells the length of a reply from its first bytes (its PDU classes'
sizing rule, ``calculateRtuFrameSize``). ``exchange`` returns the reply frame
checked as a frame (length, CRC, unit, function): the transport unpacks the
cycle's read and write replies itself; ``transact`` decodes any reply with
pymodbus' PDU classes. The CRC is ``protocol.modbus_crc`` (the same CRC, in
fewer steps).
What this layer replaces is only how a transaction is driven, because the stock
synchronous client (pymodbus 3.16 ``ModbusSerialClient``) does not know how long
the reply is: it polls ``in_waiting`` with ``time.sleep`` of four character times
(at least 1 ms) until the byte count stops growing, which costs two or more
polling periods per reply.

Here every reply is one frame that must match its request:

- the reply is read by its own length (from its header) in ``select``, no sleeps;
  the first byte must arrive within ``timeout`` after the request left the wire,
  the rest within its own wire time plus a margin (``completion_margin``: USB
  adapters deliver in bursts);
- a frame ends with t3.5 of silence (Modbus over Serial Line V1.02, 2.5.1.1): bytes
  that follow a complete reply within t3.5 make it a bad frame, never a good
  reply with garbage silently dropped;
- a well-formed frame from another unit, or from this unit with another function
  code, is a late reply to an earlier request: it is discarded (counted per unit)
  and the wait for this request's reply goes on within the same deadline;
- after a timeout on unit U the line is held for ``late_reply_guard``
  before U is asked again: a reply that U sends late arrives in that window and is
  discarded, instead of being read as the reply to U's next request of the same
  length (which no field of a read reply could tell apart). Other units are
  served meanwhile: a late reply of U cannot pass their unit id check;
- before each request the line must have been silent for t3.5; whatever arrived
  since the last transaction is stale and drained until t3.5 of silence.

What stays undetectable, by the protocol: a read reply from U that comes later than
``timeout + late_reply_guard`` and has the same function code and length as U's
next request. ``late_reply_guard`` is therefore sized with ``timeout``.

USB-RS485 adapters: most (FTDI and friends) hold received bytes for a latency
timer (16 ms by default on Linux) unless the port is in low-latency mode, which
``low_latency`` asks the kernel driver for at open (``link_notes`` says when it is
refused); some adapters hear their own transmission (``echo``): the frame is then
read back and checked byte for byte before the reply (a mismatch is a collision
on the bus: a bad frame).
"""

from __future__ import annotations

import os
import select
import threading
import time
from typing import Callable

from . import modbus_library  # noqa: F401 - the pymodbus version check, before pymodbus

# isort: split

import serial
from pymodbus.framer import FramerRTU
from pymodbus.pdu import DecodePDU, ExceptionResponse, ModbusPDU

from ..protocol.linux_thread import tighten_timer_slack
from ..protocol.modbus_crc import crc16
from ..protocol.rtu_timing import character_time, frame_gap
from .base import TransportStats

#: pymodbus' sizing rule for the PDU classes that state it as data (see _frame_size)
_BASE_SIZING = ModbusPDU.calculateRtuFrameSize.__func__

#: longest RTU frame (Modbus over Serial Line V1.02, 2.5.1.1: 256 bytes)
MAX_FRAME = 256
#: bytes that name a reply's length: unit, function code, byte count
_HEADER = 3
#: reply headers whose announced length is kept (see RtuLink._frame_size)
HEADERS_KEPT = 256
#: request frames kept for reuse (a drive's status reads and command writes: a few per drive)
FRAMES_KEPT = 512
#: the functions whose frames are kept: read holding registers, write single / multiple
_KEPT_FUNCTIONS = frozenset((3, 6, 16))


class LinkTimeout(Exception):
    """No byte of the reply arrived in time."""


class LinkBadFrame(Exception):
    """Bytes arrived but they are not the expected reply."""

    def __init__(self, message: str, data: bytes) -> None:
        super().__init__(message)
        self.data = data


class LinkLost(Exception):
    """The port failed (unplugged adapter, closed pty)."""


#: ``on_discard(unit, kind)``: a frame was dropped; ``unit`` is None for garbage
DiscardCallback = Callable[[int | None, str], None]


def _came_instead(frame: bytes, unit: int) -> str:
    """Name a well-formed frame that came where unit's reply was awaited."""
    if frame[0] != unit:
        return (f'a reply from unit {frame[0]} came instead (a drive at another address than '
                f'{unit}, or a late reply)')
    return (f'a reply to function {frame[1] & 0x7F} came instead (a late reply, or a confused '
            'drive)')


class RtuLink:
    """One serial port, one transaction at a time (the caller serialises)."""

    def __init__(self, port: str, baudrate: int, parity: str = 'N', stopbits: int = 1,
                 bytesize: int = 8, timeout: float = 0.1, frame_gap_s: float | None = None,
                 completion_margin: float = 0.02, late_reply_guard: float | None = None,
                 low_latency: bool = True, echo: bool = False,
                 counters: TransportStats | None = None,
                 on_discard: DiscardCallback | None = None) -> None:
        self.port = port
        self.baudrate = baudrate
        self.parity = parity
        self.stopbits = stopbits
        self.bytesize = bytesize
        self.timeout = timeout
        self.char_time = character_time(baudrate, parity, stopbits, bytesize)
        self.gap = frame_gap(baudrate, self.char_time) if frame_gap_s is None else frame_gap_s
        self.completion_margin = completion_margin
        self.late_reply_guard = timeout if late_reply_guard is None else late_reply_guard
        self.low_latency = low_latency
        self.echo = echo
        #: what an operator should know about the port (e.g. low-latency mode refused)
        self.link_notes: tuple[str, ...] = ()
        #: where the bytes sent and received are counted (``bytes_sent``, ``bytes_received``)
        self.counters = counters or TransportStats()
        self._on_discard = on_discard or (lambda _unit, _kind: None)
        self._framer = FramerRTU(DecodePDU(is_server=False))
        # function code -> PDU class, for the codes without sub-functions (pymodbus'
        # lookupPduClass costs as much as the rest of sizing a frame, three times a reply)
        self._pdu_classes: dict[int, type[ModbusPDU] | None] = {}
        # function code -> how its frames announce their length (see _frame_size)
        self._sizing: dict[int, tuple[int, int]] = {}
        self._header_sizes: dict[bytes, int] = {}     # a frame's first bytes -> its length
        # (function, unit, address, count, values) -> the frame of that request (a drive's
        # status reads repeat each cycle, and its command writes while the command holds)
        self._frames: dict[tuple[int, ...], bytes] = {}
        self._serial: serial.Serial | None = None
        self._fd = -1
        self._quiet_from = 0.0     # monotonic time from which the line may be used again
        self._last_byte_at = 0.0   # monotonic time the last byte of a frame was read
        self._hold: dict[int, float] = {}   # unit -> no request to it before (late replies)
        self._tuned_thread: int | None = None

    @property
    def is_open(self) -> bool:
        return self._serial is not None

    def open(self) -> None:
        if self._serial is not None:
            return
        try:
            port = serial.Serial(self.port, baudrate=self.baudrate, bytesize=self.bytesize,
                                 parity=self.parity, stopbits=self.stopbits, timeout=0,
                                 write_timeout=self.timeout, exclusive=True)
        except (serial.SerialException, OSError, ValueError) as exc:
            hint = ''
            if 'exclusively lock' in str(exc):      # pyserial's flock of the device
                hint = (': another process or node holds the port (drives sharing one line belong '
                        'in one bus_node, not a drive_node each)')
            raise LinkLost(f'{exc}{hint}') from exc
        self._serial = port
        self._fd = port.fileno()
        os.set_blocking(self._fd, False)      # pyserial opens so; _read_available relies on it
        self._quiet_from = time.monotonic() + self.gap
        self._hold.clear()
        self.link_notes = self._request_low_latency(port) if self.low_latency else ()

    def _request_low_latency(self, port: serial.Serial) -> tuple[str, ...]:
        """Ask the serial driver not to hold received bytes (ASYNC_LOW_LATENCY)."""
        try:
            device = os.path.realpath(self.port)
            if device.startswith('/dev/pts/'):
                return ()          # a pseudo-terminal (a simulated line): no adapter to tune
            port.set_low_latency_mode(True)
        except (ValueError, OSError, NotImplementedError) as exc:
            return (f'low-latency mode refused by the serial driver of {self.port} ({exc}): '
                    'a USB adapter may hold each reply for its latency timer (FTDI: 16 ms); '
                    "set it with setserial or the adapter's latency_timer",)
        return ()

    def close(self) -> None:
        port, self._serial, self._fd = self._serial, None, -1
        if port is not None:
            try:
                port.close()
            except (serial.SerialException, OSError):
                pass

    def transact(self, request: ModbusPDU, reply_bytes: int) -> ModbusPDU:
        """Send ``request`` and return its reply PDU (a normal or an exception reply).

        ``reply_bytes`` is the length of the normal reply (the wait for a reply
        whose header is not readable). Raises LinkTimeout (nothing came),
        LinkBadFrame (something else came) or LinkLost (the port failed).
        """
        reply = self.exchange(self.frame(request), reply_bytes)
        pdu = self._decode(reply, len(reply))
        if pdu is None:
            raise LinkBadFrame('malformed reply', reply)
        return pdu

    def exchange(self, frame: bytes, reply_bytes: int) -> bytes:
        """Send a request ``frame`` and return its reply frame, checked as far as a frame goes.

        The reply is one frame of the announced length with a good CRC, from
        the request's unit, naming the request's function (a normal reply) or
        that function + 0x80 (an exception reply), followed by t3.5 of silence.
        What its data says is the caller's to check. ``reply_bytes`` and the
        exceptions are as for ``transact``.
        """
        if self._serial is None:
            self.open()
        if self._tuned_thread != threading.get_ident():
            tighten_timer_slack()
            self._tuned_thread = threading.get_ident()
        unit, function = frame[0], frame[1]
        try:
            self._wait_until_quiet(unit)
            sent_at = time.monotonic()
            self._write(frame)
            self.counters.bytes_sent += len(frame)
            if self.echo:
                self._check_echo(frame, sent_at)
            deadline = sent_at + len(frame) * self.char_time + self.timeout
            instead: list[bytes] = []   # frames that came instead of this request's reply
            while True:
                data, size = self._read_frame(deadline, reply_bytes)
                if not data:
                    self._hold[unit] = time.monotonic() + self.late_reply_guard
                    self._quiet_from = time.monotonic()
                    # A wrong reply that came instead (another unit's, another function's)
                    # is named, but the exchange is a timeout all the same: it cost one,
                    # and a retry would cost the late-reply guard and another (a bus plans
                    # a failed exchange at one timeout).
                    raise LinkTimeout('no reply' if not instead else
                                      f'no reply ({_came_instead(instead[-1], unit)})')
                if size != len(data) or crc16(data):   # (over a whole frame the CRC leaves 0)
                    self._resync()
                    raise LinkBadFrame('malformed reply', data)
                if data[0] != unit or (data[1] & 0x7F) != function:
                    # A late reply to an earlier request (of this or another unit): the
                    # one its unit's guard waits for, which ends it (a stop retried
                    # after a hurried pass sat out the whole guard: re-check).
                    self._hold.pop(data[0], None)
                    self._on_discard(data[0], 'late')
                    instead.append(data)
                    continue
                trailing = self._silence_after()
                if trailing:
                    raise LinkBadFrame('bytes after the reply', data + trailing)
                return data
        except (OSError, serial.SerialException) as exc:
            self.close()
            raise LinkLost(str(exc)) from exc

    def broadcast(self, request: ModbusPDU, turnaround: float) -> None:
        """Send a write to unit 0 (every slave executes it, none answers).

        The line is then kept quiet for ``turnaround`` (Modbus over Serial Line
        V1.02, 2.4.1: the slaves need time to process a broadcast before the next
        request). Raises LinkLost if the port failed.
        """
        if self._serial is None:
            self.open()
        frame = self._framer.buildFrame(request)
        try:
            self._wait_until_quiet(0)
            sent_at = time.monotonic()
            self._write(frame)
            self.counters.bytes_sent += len(frame)
            if self.echo:
                self._check_echo(frame, sent_at)
        except (OSError, serial.SerialException) as exc:
            self.close()
            raise LinkLost(str(exc)) from exc
        self._quiet_from = sent_at + len(frame) * self.char_time + self.gap + turnaround

    def frame(self, request: ModbusPDU) -> bytes:
        """Return the frame of ``request``: built once for a read or a write, which repeat.

        The frame of a read (03), a single write (06) or a multiple write (16) follows
        from its function, unit, address, count and values alone.
        """
        if request.function_code not in _KEPT_FUNCTIONS:
            return self.build_frame(request)
        key = (request.function_code, request.dev_id, request.address, request.count,
               *request.registers)
        frame = self._frames.get(key)
        if frame is None:
            if len(self._frames) >= FRAMES_KEPT:
                self._frames.clear()
            frame = self._frames[key] = self.build_frame(request)
        return frame

    def build_frame(self, request: ModbusPDU) -> bytes:
        """Return the frame of ``request`` as pymodbus builds it (not kept here)."""
        return self._framer.buildFrame(request)

    # --- internals ----------------------------------------------------------------

    def _check_echo(self, frame: bytes, sent_at: float) -> None:
        """Read back our own transmission (an echoing adapter); raise if it came back different."""
        deadline = sent_at + len(frame) * self.char_time + self.completion_margin + self.gap
        heard = b''
        while len(heard) < len(frame):
            remaining = deadline - time.monotonic()
            if remaining <= 0 or not select.select([self._fd], [], [], remaining)[0]:
                break
            chunk = os.read(self._fd, len(frame) - len(heard))
            if not chunk:
                raise OSError('port closed')
            heard += chunk
        self.counters.bytes_received += len(heard)
        if heard != frame:
            self._resync()
            raise LinkBadFrame('the echo of the request differs (a collision, or no echo: '
                               'check transport.echo)', heard)

    def _decode(self, data: bytes, size: int | None = None) -> ModbusPDU | None:
        """Return the PDU of exactly one well-formed frame (CRC checked), else None.

        pymodbus' frame decoder hunts over leading garbage and drops trailing
        bytes; a master must not, so the frame is checked here to start at byte 0
        and to end at the last byte, and then only the PDU is handed to pymodbus'
        PDU class. (Its ``handleFrame`` would check the CRC a second time and
        format the PDU for a debug log on every reply: a third of a
        transaction's CPU at 115200 baud.) ``size``: the length the header announced,
        when the caller has it already.
        """
        if len(data) < 4 or (size if size is not None else self._frame_size(data)) != len(data):
            return None
        if crc16(data) != 0:        # a frame's CRC over the whole frame leaves 0
            return None
        function_code = data[1]
        try:
            if function_code & 0x80:
                pdu = ExceptionResponse(function_code & 0x7F)
            else:
                pdu_class = self._pdu_class(data)
                if pdu_class is None:
                    return None
                pdu = pdu_class()
            pdu.decode(data[2:-2])
        except Exception:  # noqa: BLE001 - pymodbus raises several kinds on garbage
            return None
        pdu.dev_id = data[0]
        return pdu

    def _frame_size(self, header: bytes) -> int:
        """Return the length a frame announces in its first bytes (0: not yet / unknown).

        The rule is pymodbus' (``calculateRtuFrameSize`` of the frame's PDU class). Most
        classes state it as data, a fixed ``rtu_frame_size`` or the position of a byte
        count: those are taken once per function code, and the size a header of
        ``_HEADER`` bytes announces once per header (a link's replies have a few).
        """
        size = self._header_sizes.get(header)
        if size is not None:
            return size
        if len(header) < 2:
            return 0
        sizing = self._sizing.get(header[1])
        if sizing is None:
            return self._size_by_class(header)
        fixed, count_at = sizing
        if fixed:
            size = fixed
        elif len(header) > count_at:
            size = header[count_at] + count_at + 3
        else:
            return 0
        size = size if 4 <= size <= MAX_FRAME else 0
        if len(header) == _HEADER and count_at < _HEADER:     # (it says all there is)
            if len(self._header_sizes) >= HEADERS_KEPT:        # (garbage may vary freely)
                self._header_sizes.clear()
            self._header_sizes[header] = size
        return size

    def _size_by_class(self, header: bytes) -> int:
        """``_frame_size`` by pymodbus' PDU class; remember the rule where it is data."""
        try:
            pdu_class = self._pdu_class(header)
            size = pdu_class.calculateRtuFrameSize(header) if pdu_class else 0
        except Exception:  # noqa: BLE001 - an unknown or garbled header
            return 0
        if pdu_class is not None and header[1] in self._pdu_classes and \
                pdu_class.calculateRtuFrameSize.__func__ is _BASE_SIZING and \
                (pdu_class.rtu_frame_size or pdu_class.rtu_byte_count_pos):
            self._sizing[header[1]] = (pdu_class.rtu_frame_size, pdu_class.rtu_byte_count_pos)
        return size if 4 <= size <= MAX_FRAME else 0

    def _pdu_class(self, header: bytes) -> type[ModbusPDU] | None:
        """Return pymodbus' ``lookupPduClass``, remembered per function code where it can be."""
        function_code = header[1]
        try:
            return self._pdu_classes[function_code]
        except KeyError:
            pass
        decoder = self._framer.decoder
        pdu_class = decoder.lookupPduClass(header)
        if function_code & 0x80 or function_code not in decoder.pdu_sub_table:
            self._pdu_classes[function_code] = pdu_class   # (else: it names a sub-function)
        return pdu_class

    def _write(self, frame: bytes) -> None:
        written = os.write(self._fd, frame)
        if written != len(frame) and self._serial is not None:
            self._serial.write(frame[written:])

    def _read_frame(self, first_deadline: float, expected: int) -> tuple[bytes, int]:
        """Read one frame: its first byte by ``first_deadline``, then its own length.

        The length comes from the frame's header once its first bytes are in
        (``expected`` until then); the rest must follow at the baud rate. Returns
        the bytes and the length their header announced (0: not known): b'' when
        nothing came, possibly an incomplete frame when the rest did not.
        """
        fd = self._fd
        remaining = first_deadline - time.monotonic()
        if remaining <= 0 or not select.select([fd], [], [], remaining)[0]:
            return b'', 0
        data = os.read(fd, _HEADER)
        if not data:
            raise OSError('port closed')
        first_at = last_at = time.monotonic()
        size = 0
        while True:
            # The header first, then exactly the announced rest: never read into
            # the frame that may follow (a late reply is followed by the real one).
            size = size or self._frame_size(data)
            missing = (size or (_HEADER if len(data) < _HEADER else expected)) - len(data)
            if missing <= 0:
                break
            # The rest has usually arrived with the header: try the (non-blocking)
            # read before paying for a select.
            chunk = self._read_available(missing)
            if not chunk:
                # The rest follows at the baud rate; allow bursty USB adapters a margin.
                remaining = first_at + max(size or expected, len(data)) * self.char_time \
                    + self.completion_margin - time.monotonic()
                if remaining <= 0 or not select.select([fd], [], [], remaining)[0]:
                    break
                chunk = os.read(fd, missing)
                if not chunk:
                    raise OSError('port closed')
            last_at = time.monotonic()
            data += chunk
        self._last_byte_at = last_at
        self.counters.bytes_received += len(data)
        return data, size

    def _read_available(self, count: int) -> bytes:
        """Read up to ``count`` bytes that are already in; b'' if none are.

        (A serial port set up for polling reads, VMIN = VTIME = 0, returns b''
        rather than EAGAIN when nothing is in: only a read after ``select``
        tells a closed port.)
        """
        try:
            return os.read(self._fd, count)
        except BlockingIOError:
            return b''

    def _silence_after(self) -> bytes:
        """Wait t3.5 after a frame; return what arrived instead of silence (drained).

        Counted from when its last byte was read, not from after decoding it: the
        decoding overlaps the silence, as it would on the wire.
        """
        remaining = max(0.0, self._last_byte_at + self.gap - time.monotonic())
        if select.select([self._fd], [], [], remaining)[0]:
            return self._drain()
        self._quiet_from = time.monotonic()
        return b''

    def _wait_until_quiet(self, unit: int) -> None:
        """Keep the line silent for t3.5, and for unit's late-reply guard after a timeout.

        Anything that arrives meanwhile is stale: drained and counted (a late reply
        from ``unit`` ends its guard early: the line is known quiet then).
        """
        hold_until = self._hold.pop(unit, 0.0)
        if select.select([self._fd], [], [], 0)[0]:
            if unit in self._count_discarded(self._drain()):
                hold_until = 0.0
        while (remaining := max(self._quiet_from, hold_until) - time.monotonic()) > 0:
            if select.select([self._fd], [], [], remaining)[0]:
                if unit in self._count_discarded(self._drain()):
                    hold_until = 0.0

    def _drain(self) -> bytes:
        """Read whatever is arriving until the line has been silent for t3.5."""
        silence = max(self.gap, 0.002)
        limit = time.monotonic() + max(self.timeout, 0.05)
        data = b''
        while time.monotonic() < limit:
            if not select.select([self._fd], [], [], silence)[0]:
                break
            chunk = os.read(self._fd, 4096)
            if not chunk:
                raise OSError('port closed')
            data += chunk
        self.counters.bytes_received += len(data)
        self._quiet_from = time.monotonic()
        return data

    def _resync(self) -> None:
        """After a garbled reply: drop what is still arriving until t3.5 of silence."""
        self._count_discarded(self._drain())

    def _count_discarded(self, data: bytes) -> set[int]:
        """Report drained bytes as late frames (by unit) or garbage; return the units."""
        units: set[int] = set()
        while data:
            size = self._frame_size(data)
            pdu = self._decode(data[:size]) if size and size <= len(data) else None
            if pdu is None:
                self._on_discard(None, 'garbage')
                break
            units.add(pdu.dev_id)
            self._hold.pop(pdu.dev_id, None)        # (as in exchange)
            self._on_discard(pdu.dev_id, 'late')
            data = data[size:]
        return units
