"""A thin Modbus RTU master over pyserial, framed and decoded by pymodbus.

pymodbus builds every request frame (``FramerRTU.buildFrame`` over its request
PDUs, so the bytes on the wire are exactly the stock client's) and decodes
every reply (``FramerRTU.handleFrame``: CRC, PDU classes, exception replies).
What this layer replaces is only how a transaction is driven, because the
stock synchronous client (pymodbus 3.16 ``ModbusSerialClient``) does not know
how long the reply is: it polls ``in_waiting`` with ``time.sleep`` of four
character times (at least 1 ms) until the byte count stops growing, which
costs two or more polling periods per reply (measured: ~2.5 ms per
transaction over a pseudo-terminal with no wire delay, ~8 characters at low
baud). Here:

- the reply length is known from the request (``rtu_timing.reply_size``; an
  exception reply is recognised by its function byte after two bytes), so the
  read blocks in ``select`` until exactly that many bytes are in, no sleeps;
- deadlines follow the baud rate: the first byte must arrive within
  ``timeout`` after the request left the wire, the rest within its own wire
  time plus a margin (``completion_margin``: USB adapters deliver in bursts), so
  a truncated reply costs milliseconds, not the full timeout;
- before each request the line is kept silent for t3.5 after the last byte
  received (the spec's inter-frame gap; a fast master on a real UART would
  otherwise run two frames together);
- after a garbled reply the line is drained until it is silent for t3.5, so the
  next transaction starts in sync.
"""

from __future__ import annotations

import os
import select
import threading
import time
from typing import Callable

import serial
from pymodbus.framer import FramerRTU
from pymodbus.pdu import DecodePDU, ModbusPDU

from ..rtu_timing import character_time, frame_gap, tighten_timer_slack


class LinkTimeout(Exception):
    """No byte of the reply arrived in time."""


class LinkBadFrame(Exception):
    """Bytes arrived but they are not the expected reply."""

    def __init__(self, message: str, data: bytes) -> None:
        super().__init__(message)
        self.data = data


class LinkLost(Exception):
    """The port failed (unplugged adapter, closed pty)."""


class RtuLink:
    """One serial port, one transaction at a time (the caller serialises)."""

    def __init__(self, port: str, baudrate: int, parity: str = 'N', stopbits: int = 1,
                 bytesize: int = 8, timeout: float = 0.1, frame_gap_s: float | None = None,
                 completion_margin: float = 0.02,
                 on_bytes: Callable[[bool, int], None] | None = None) -> None:
        self.port = port
        self.baudrate = baudrate
        self.parity = parity
        self.stopbits = stopbits
        self.bytesize = bytesize
        self.timeout = timeout
        self.char_time = character_time(baudrate, parity, stopbits, bytesize)
        self.gap = frame_gap(baudrate, self.char_time) if frame_gap_s is None else frame_gap_s
        self.completion_margin = completion_margin
        self._on_bytes = on_bytes or (lambda _sending, _count: None)
        self._framer = FramerRTU(DecodePDU(is_server=False))
        self._serial: serial.Serial | None = None
        self._fd = -1
        self._quiet_from = 0.0     # monotonic time from which the line may be used again
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
            raise LinkLost(str(exc)) from exc
        self._serial = port
        self._fd = port.fileno()
        self._quiet_from = time.monotonic() + self.gap

    def close(self) -> None:
        port, self._serial, self._fd = self._serial, None, -1
        if port is not None:
            try:
                port.close()
            except (serial.SerialException, OSError):
                pass

    def build(self, request: ModbusPDU) -> bytes:
        """Return the request's RTU frame, exactly as pymodbus' client would send it."""
        return self._framer.buildFrame(request)

    def transact(self, request: ModbusPDU, reply_bytes: int) -> ModbusPDU:
        """Send ``request`` and return the reply PDU (a normal or an exception reply).

        Raises LinkTimeout (nothing came), LinkBadFrame (something else came)
        or LinkLost (the port failed).
        """
        if self._serial is None:
            self.open()
        if self._tuned_thread != threading.get_ident():
            tighten_timer_slack()
            self._tuned_thread = threading.get_ident()
        frame = self._framer.buildFrame(request)
        try:
            self._discard_stale_input()
            wait = self._quiet_from - time.monotonic()
            if wait > 0:
                time.sleep(wait)
            sent_at = time.monotonic()
            self._write(frame)
            self._on_bytes(True, len(frame))
            on_wire_until = sent_at + len(frame) * self.char_time
            data = self._receive(reply_bytes, on_wire_until + self.timeout)
            self._quiet_from = time.monotonic() + self.gap
            if not data:
                raise LinkTimeout('no reply')
            used, pdu = self._decode(data)
            if pdu is None or pdu.dev_id != request.dev_id or \
                    (pdu.function_code & 0x7F) != request.function_code or used < len(data):
                self._resync()
                raise LinkBadFrame('malformed reply', data)
        except (OSError, serial.SerialException) as exc:
            self.close()
            raise LinkLost(str(exc)) from exc
        return pdu

    # --- internals ----------------------------------------------------------------

    def _decode(self, data: bytes) -> tuple[int, ModbusPDU | None]:
        try:
            return self._framer.handleFrame(data, 0, 0)
        except Exception:  # noqa: BLE001 - pymodbus raises several kinds on garbage
            return len(data), None

    def _write(self, frame: bytes) -> None:
        written = os.write(self._fd, frame)
        if written != len(frame) and self._serial is not None:
            self._serial.write(frame[written:])

    def _discard_stale_input(self) -> None:
        # A late reply to an earlier (timed-out) request must not be taken for this one.
        while select.select([self._fd], [], [], 0)[0]:
            stale = os.read(self._fd, 4096)
            if not stale:
                raise OSError('port closed')
            self._on_bytes(False, len(stale))
            self._quiet_from = time.monotonic() + self.gap

    def _receive(self, expected: int, first_deadline: float) -> bytes:
        """Read exactly ``expected`` bytes (5 if it is an exception reply) or until a deadline."""
        fd = self._fd
        data = b''
        deadline = first_deadline
        while len(data) < expected:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                break
            if not select.select([fd], [], [], remaining)[0]:
                break
            chunk = os.read(fd, expected - len(data))
            if not chunk:
                raise OSError('port closed')
            if not data:
                # The rest follows at the baud rate; allow bursty USB adapters a margin.
                deadline = time.monotonic() + (expected - len(chunk)) * self.char_time \
                    + self.completion_margin
            data += chunk
            if len(data) >= 2 and data[1] & 0x80:
                expected = 5      # unit, function | 0x80, exception code, CRC
        self._on_bytes(False, len(data))
        return data

    def _resync(self) -> None:
        """Drop whatever is still arriving until the line has been silent for t3.5."""
        silence = max(self.gap, 0.002)
        limit = time.monotonic() + self.timeout
        while time.monotonic() < limit:
            if not select.select([self._fd], [], [], silence)[0]:
                break
            garbage = os.read(self._fd, 4096)
            if not garbage:
                raise OSError('port closed')
            self._on_bytes(False, len(garbage))
        self._quiet_from = time.monotonic() + self.gap
