"""An emulated RS-485 line: simulated drives answering real Modbus RTU frames.

The line is a pseudo-terminal pair; the driver opens the slave side through a
stable symlink (e.g. ``/tmp/vfd_sim/line0``) exactly as it would open
``/dev/ttyUSB0``. Frames are cut and checked with pymodbus' RTU framer (CRC,
hunting over garbage) and answered with pymodbus PDUs, so every byte on the
line is real Modbus RTU. Faults of the line itself can be injected
(``LineFaults``): replies corrupted at a rate, late replies (a slave that
answers after the master's timeout, and either keeps or drops what it heard
meanwhile), write echoes that name another value, bytes trailing a reply;
drives that stop answering; and wire time at the baud rate.

Wire-time emulation (``emulate_wire_time``) makes the pseudo-terminal, which
has no baud rate, behave like an RS-485 line at ``baudrate``:

- a request occupies the wire for len x character time from the moment its
  bytes are written (the master's UART starts sending at once), and is taken
  as complete only at its last byte (``received`` stamps = that moment);
- the drive answers no earlier than t3.5 after the request's last byte (it
  detects the end of a frame by that silence; ``rtu_timing.frame_gap``: 3.5
  characters, 1.75 ms above 19200 baud) plus its own ``response_delay``;
- the reply's bytes are handed to the pty as each would finish on the wire
  (byte i at reply start + (i + 1) x character time; grouped at most every
  0.3 ms like a UART's receive FIFO; never earlier, late by the scheduler's
  wake-up at most), so a master sees it grow at the baud rate and its last
  byte at the true end of the frame;
- a request that starts less than t3.5 after the previous reply ended is
  served but counted (``stats.gap_violations``): a real slave may merge it.

The master's USB-RS485 adapter can be emulated too: ``adapter_latency`` holds
each reply for that long after its last byte (an FTDI adapter's latency timer,
16 ms by default on Linux, when the port is not in low-latency mode; the worst
case of a timer that runs independently), and ``adapter_echo`` sends the
master's own request bytes back as an adapter that hears its transmission does.

Drives at several baud rates on one line (``drive_baudrates``, unit id -> baud
rate): a pseudo-terminal moves bytes, not bits, so a frame sent at the wrong
baud rate cannot turn into garbage by itself. What it does keep is the
settings the master opened it with: Linux shares one termios between both
ends of a pty, so the line reads the master's baud rate (``tcgetattr`` on its
own end) when a frame's first bytes arrive, and a drive set to another baud
rate does not hear the frame (it would see garbage and drop it:
``stats.wrong_baud``). Parity is not emulated: the pty driver clears PARENB
and forces CS8 whatever the master asked for. Stop bits do not matter either,
as on a real line (a UART samples only the first stop bit). Without
``drive_baudrates`` every drive hears every baud rate (the default). With
wire-time emulation the character time follows the master's baud rate.
"""

from __future__ import annotations

import collections
import os
import random
import select
import termios
import threading
import time
import tty
from dataclasses import dataclass
from pathlib import Path
from typing import Mapping

from ..transports import modbus_library  # noqa: F401 - the pymodbus version check, before pymodbus

# isort: split

from pymodbus.exceptions import ModbusException
from pymodbus.framer import FramerRTU
from pymodbus.pdu import DecodePDU, ModbusPDU

from ..protocol.linux_thread import tighten_timer_slack
from ..protocol.rtu_timing import character_time, frame_gap
from .dispatch import answer
from .model import SimulatedDrive


@dataclass
class LineStats:
    frames: int = 0          # well-formed requests seen
    replies: int = 0
    crc_errors: int = 0      # requests dropped for a bad CRC or garbage
    corrupted_replies: int = 0
    late_replies: int = 0    # replies sent after the injected delay
    wrong_echoes: int = 0    # write replies altered to name another value / count
    trailing_garbage: int = 0  # replies followed by stray bytes
    dropped_while_late: int = 0  # requests not heard while answering late (deaf)
    ignored: int = 0         # requests for absent or silent drives
    gap_violations: int = 0  # requests that began < t3.5 after the previous reply (emulated)
    wrong_baud: int = 0      # requests a drive did not hear: sent at another baud rate
    #: how late the simulator itself handed over the last byte of timed replies
    #: (wire-time emulation): its own share of a measured turnaround, not the master's
    timed_replies: int = 0
    reply_lateness_total: float = 0.0
    reply_lateness_max: float = 0.0

    def record_lateness(self, seconds: float) -> None:
        self.timed_replies += 1
        self.reply_lateness_total += seconds
        self.reply_lateness_max = max(self.reply_lateness_max, seconds)


@dataclass
class LineFaults:
    """What a hostile line does to replies; every rate is a fraction of replies (0..1).

    ``late_delay`` is (min, max) seconds from the end of the request to the start
    of a late reply (set it just beyond the master's timeout). A late slave with
    ``late_deaf`` drops every request that arrives while it is busy (a
    half-duplex transceiver that does not listen while it waits); otherwise it
    answers them afterwards in order.
    """

    corrupt_rate: float = 0.0
    late_rate: float = 0.0
    late_delay: tuple[float, float] = (0.0, 0.0)
    late_deaf: bool = False
    wrong_echo_rate: float = 0.0
    trailing_rate: float = 0.0


@dataclass(frozen=True)
class Exchange:
    """One request on the emulated wire (times: time.monotonic())."""

    request_start: float
    request_end: float
    request: bytes
    reply_bytes: int         # 0: no reply
    reply_end: float


#: hand reply bytes over at most this often (a UART's receive FIFO also batches)
_CHUNK = 0.0003
#: drives advanced per tick period (a line of more drives advances each less often)
TICKS_PER_WAKE = 4

#: termios speed constant -> bit/s (the rates this platform names)
_BAUD_OF = {getattr(termios, f'B{rate}'): rate for rate in (
    50, 75, 110, 134, 150, 200, 300, 600, 1200, 1800, 2400, 4800, 9600, 19200, 38400, 57600,
    115200, 230400, 460800, 500000, 576000, 921600, 1000000, 1152000, 1500000, 2000000)
    if hasattr(termios, f'B{rate}')}

__all__ = ['Exchange', 'LineFaults', 'LineStats', 'SimulatedRtuLine', 'character_time']


class SimulatedRtuLine:
    """Serves simulated drives (one per slave id) on a pseudo-terminal."""

    def __init__(self, drives: list[SimulatedDrive], link_path: str | Path,
                 baudrate: int = 115200, parity: str = 'N', stopbits: int = 1,
                 emulate_wire_time: bool = False, corrupt_rate: float = 0.0,
                 tick_period: float = 0.005, seed: int | None = None,
                 response_delay: float = 0.0, faults: LineFaults | None = None,
                 adapter_latency: float = 0.0, adapter_echo: bool = False,
                 drive_baudrates: Mapping[int, int] | None = None) -> None:
        self.drives = {drive.unit_id: drive for drive in drives}
        self.link_path = Path(link_path)
        self.baudrate = baudrate
        self.parity = parity
        self.stopbits = stopbits
        self.char_time = character_time(baudrate, parity, stopbits)
        self.gap = frame_gap(baudrate, self.char_time)
        #: unit id -> the baud rate that drive listens at (None: every drive hears every rate)
        self.drive_baudrates = dict(drive_baudrates) if drive_baudrates is not None else None
        #: the baud rate the master has the port open at (read from the pty), 0 = unknown
        self.master_baudrate = 0
        self.response_delay = response_delay
        self.emulate_wire_time = emulate_wire_time
        #: emulated exchanges, newest last (only with emulate_wire_time)
        self.exchanges: collections.deque[Exchange] = collections.deque(maxlen=20000)
        self._wire_free = 0.0         # emulated: when the line's last byte ends
        self._last_reply_end = -1.0
        self._request_start: float | None = None
        self.adapter_latency = adapter_latency
        self.adapter_echo = adapter_echo
        self.faults = faults or LineFaults()
        if corrupt_rate:
            self.faults.corrupt_rate = corrupt_rate
        self.tick_period = tick_period
        self.stats = LineStats()
        self.received: collections.deque[tuple[float, bytes]] = collections.deque(maxlen=4096)
        self._random = random.Random(seed)
        self._framer = FramerRTU(DecodePDU(is_server=True))
        self._master_fd = -1
        self._slave_fd = -1
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    # --- lifecycle ----------------------------------------------------------------

    def start(self) -> 'SimulatedRtuLine':
        self._master_fd, self._slave_fd = os.openpty()
        tty.setraw(self._slave_fd)
        tty.setraw(self._master_fd)
        self.link_path.parent.mkdir(parents=True, exist_ok=True)
        if self.link_path.is_symlink() or self.link_path.exists():
            self.link_path.unlink()
        os.symlink(os.ttyname(self._slave_fd), self.link_path)
        self._stop.clear()
        self._thread = threading.Thread(target=self._serve, name=f'sim line {self.link_path}',
                                        daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        """Stop serving and remove the port (the driver sees the port disappear)."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(2.0)
            self._thread = None
        for fd in (self._master_fd, self._slave_fd):
            if fd >= 0:
                try:
                    os.close(fd)
                except OSError:
                    pass
        self._master_fd = self._slave_fd = -1
        if self.link_path.is_symlink():
            self.link_path.unlink()

    def __enter__(self) -> 'SimulatedRtuLine':
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    @property
    def corrupt_rate(self) -> float:
        return self.faults.corrupt_rate

    @corrupt_rate.setter
    def corrupt_rate(self, rate: float) -> None:
        self.faults.corrupt_rate = rate

    # --- serving --------------------------------------------------------------------

    def _serve(self) -> None:
        tighten_timer_slack()
        self._buffer = b''
        last_byte = last_tick = time.monotonic()
        self._tick_turn = 0
        silence = max(3.5 * self.char_time, 0.002)
        while not self._stop.is_set():
            try:
                ready, _, _ = select.select([self._master_fd], [], [], self.tick_period)
            except (OSError, ValueError):
                return
            now = time.monotonic()
            if ready:
                try:
                    chunk = os.read(self._master_fd, 4096)
                except OSError:
                    chunk = b''
                if chunk:
                    if self.adapter_echo:
                        self._echo(chunk)
                    if not self._buffer and self.drive_baudrates is not None:
                        self._follow_master_baudrate()
                    if self.emulate_wire_time:
                        start = max(now, self._wire_free)
                        if not self._buffer:
                            self._request_start = start
                        self._wire_free = start + len(chunk) * self.char_time
                    self._buffer += chunk
                    last_byte = now
            self._consume()
            if self._buffer and now - last_byte > silence:
                # RTU: 3.5 characters of silence end a frame; what is left is garbage.
                self.stats.crc_errors += 1
                self._buffer = b''
            if now - last_tick >= self.tick_period:
                # Once per period, not after every frame, and a few drives at a time:
                # ticking 32 drives at once held the next request's reply back by
                # milliseconds (the line's turnaround, not the master's).
                last_tick = now
                drives = list(self.drives.values())
                for _ in range(min(len(drives), TICKS_PER_WAKE)):
                    drives[self._tick_turn % len(drives)].tick()
                    self._tick_turn += 1

    def _consume(self) -> None:
        while self._buffer:
            try:
                used, pdu = self._framer.handleFrame(self._buffer, 0, 0)
            except ModbusException:
                self.stats.crc_errors += 1
                self._buffer = b''
                return
            if pdu is None:
                if used:
                    self.stats.crc_errors += 1
                self._buffer = self._buffer[used:]
                return
            request, self._buffer = self._buffer[:used], self._buffer[used:]
            self.stats.frames += 1
            end = self._wire_free if self.emulate_wire_time else time.monotonic()
            start = self._request_start if self._request_start is not None else \
                end - len(request) * self.char_time
            self._request_start = None
            if self.emulate_wire_time:
                if self._last_reply_end >= 0 and start < self._last_reply_end + self.gap - 1e-6:
                    self.stats.gap_violations += 1
                self._wait_until(end)
            self.received.append((end, request))
            reply = self._answer(pdu)
            if reply is None:
                if self.emulate_wire_time:
                    self.exchanges.append(Exchange(start, end, request, 0, end))
                continue
            reply, delay = self._inject(reply)
            reply_end = self._transmit(reply, end + delay)
            if self.emulate_wire_time:
                self.exchanges.append(Exchange(start, end, request, len(reply), reply_end))
            if delay and self.faults.late_deaf:
                self._drop_heard_meanwhile()

    def _inject(self, reply: bytes) -> tuple[bytes, float]:
        """Apply the line's faults to one reply: (bytes to send, delay after the request)."""
        faults, rng = self.faults, self._random
        delay = self.gap + self.response_delay if self.emulate_wire_time else 0.0
        if faults.late_rate and rng.random() < faults.late_rate:
            self.stats.late_replies += 1
            delay = rng.uniform(*faults.late_delay)
        if faults.wrong_echo_rate and reply[1] in (6, 16) and \
                rng.random() < faults.wrong_echo_rate:
            self.stats.wrong_echoes += 1
            reply = self._wrong_echo(reply)
        if faults.corrupt_rate and rng.random() < faults.corrupt_rate:
            self.stats.corrupted_replies += 1
            reply = self._corrupt(reply)
        if faults.trailing_rate and rng.random() < faults.trailing_rate:
            self.stats.trailing_garbage += 1
            reply += bytes(rng.randrange(256) for _ in range(rng.randint(1, 3)))
        return reply, delay

    def _transmit(self, reply: bytes, start: float) -> float:
        """Put ``reply`` on the line from ``start``; return when its last byte ends.

        With wire-time emulation the bytes reach the pty as each would finish on
        the wire (see the module docstring); otherwise all at once at ``start``.
        """
        if self.adapter_latency:
            # The adapter hands the reply over only when its latency timer fires.
            end = start + (len(reply) * self.char_time if self.emulate_wire_time else 0.0)
            self._wait_until(end + self.adapter_latency)
            try:
                os.write(self._master_fd, reply)
                self.stats.replies += 1
            except OSError:
                pass
            self.stats.record_lateness(time.monotonic() - end - self.adapter_latency)
            self._wire_free = self._last_reply_end = end
            return end
        self._wait_until(start)
        if not self.emulate_wire_time:
            try:
                os.write(self._master_fd, reply)
                self.stats.replies += 1
            except OSError:
                pass
            return time.monotonic()
        reply_end = start + len(reply) * self.char_time
        written = 0
        while written < len(reply):
            # Wake for the next byte's end on the wire (at most every _CHUNK), then
            # hand over every byte that has finished by now: never one too early.
            due_next = start + (written + 1) * self.char_time
            self._wait_until(min(max(due_next, time.monotonic() + _CHUNK), reply_end))
            due = min(len(reply), int((time.monotonic() - start) / self.char_time))
            if due <= written:
                continue
            try:
                os.write(self._master_fd, reply[written:due])
            except OSError:
                return reply_end
            written = due
        self.stats.record_lateness(time.monotonic() - reply_end)
        self._wire_free = self._last_reply_end = reply_end
        self.stats.replies += 1
        return reply_end

    def _echo(self, chunk: bytes) -> None:
        try:
            os.write(self._master_fd, chunk)
        except OSError:
            pass

    def _drop_heard_meanwhile(self) -> None:
        """Lose the requests that arrived while a deaf slave was busy answering late."""
        dropped = self._buffer
        while select.select([self._master_fd], [], [], 0)[0]:
            try:
                chunk = os.read(self._master_fd, 4096)
            except OSError:
                break
            if not chunk:
                break
            dropped += chunk
        if dropped:
            self.stats.dropped_while_late += 1
        self._buffer = b''

    @staticmethod
    def _wait_until(moment: float) -> None:
        # Sleep, never spin: a spinning process delays the kernel worker that moves
        # pty data, which would delay the very bytes being timed.
        while (remaining := moment - time.monotonic()) > 0:
            time.sleep(remaining)

    def _follow_master_baudrate(self) -> None:
        """Read the baud rate the master opened the port with (Linux: one termios per pty)."""
        try:
            attributes = termios.tcgetattr(self._master_fd)
        except (termios.error, OSError):
            return
        baudrate = _BAUD_OF.get(attributes[5], 0)
        if baudrate and baudrate != self.master_baudrate:
            stopbits = 2 if attributes[2] & termios.CSTOPB else 1
            self.char_time = character_time(baudrate, 'N', stopbits)
            self.gap = frame_gap(baudrate, self.char_time)
        self.master_baudrate = baudrate

    def _listeners(self, request: ModbusPDU) -> dict[int, SimulatedDrive]:
        """Return the drives that hear ``request``: all, or those at the master's baud rate."""
        if self.drive_baudrates is None:
            return self.drives
        heard = {unit: drive for unit, drive in self.drives.items()
                 if self.drive_baudrates.get(unit, self.baudrate) == self.master_baudrate}
        if request.dev_id in self.drives and request.dev_id not in heard:
            self.stats.wrong_baud += 1
        return heard

    def _answer(self, request: ModbusPDU) -> bytes | None:
        reply = answer(self._listeners(request), request)
        if reply is None:
            self.stats.ignored += 1
            return None
        return self._framer.buildFrame(reply)

    def _wrong_echo(self, reply: bytes) -> bytes:
        """Alter a write reply (06/16) to name another value (06) or count (16), CRC valid."""
        body = bytearray(reply[:-2])
        body[-1] ^= 0x01       # low byte of the echoed value / count
        return bytes(body) + FramerRTU.compute_CRC(bytes(body)).to_bytes(2, 'big')

    def _corrupt(self, reply: bytes) -> bytes:
        kind = self._random.choice(('crc', 'truncate', 'wrong_id'))
        if kind == 'crc':
            index = self._random.randrange(len(reply))
            return reply[:index] + bytes([reply[index] ^ 0x5A]) + reply[index + 1:]
        if kind == 'truncate':
            return reply[:max(1, len(reply) // 2)]
        wrong = FramerRTU.compute_CRC(bytes([(reply[0] % 247) + 1]) + reply[1:-2])
        return bytes([(reply[0] % 247) + 1]) + reply[1:-2] + wrong.to_bytes(2, 'big')
