"""An emulated RS-485 line: simulated drives answering real Modbus RTU frames.

The line is a pseudo-terminal pair; the driver opens the slave side through a
stable symlink (e.g. ``/tmp/vfd_sim/line0``) exactly as it would open
``/dev/ttyUSB0``. Frames are cut and checked with pymodbus' RTU framer (CRC,
hunting over garbage) and answered with pymodbus PDUs, so every byte on the
line is real Modbus RTU. Faults of the line itself can be injected: replies
corrupted at a rate, drives that stop answering, and wire time at the baud rate.
"""

from __future__ import annotations

import collections
import os
import random
import select
import threading
import time
import tty
from dataclasses import dataclass
from pathlib import Path

from pymodbus.exceptions import ModbusException
from pymodbus.framer import FramerRTU
from pymodbus.pdu import DecodePDU, ModbusPDU

from .dispatch import answer
from .model import SimulatedDrive


@dataclass
class LineStats:
    frames: int = 0          # well-formed requests seen
    replies: int = 0
    crc_errors: int = 0      # requests dropped for a bad CRC or garbage
    corrupted_replies: int = 0
    ignored: int = 0         # requests for absent or silent drives


def character_time(baudrate: int, parity: str = 'N', stopbits: int = 1) -> float:
    """Seconds per character on the wire (start + 8 data + parity + stop bits)."""
    return (1 + 8 + (0 if parity.upper() == 'N' else 1) + stopbits) / baudrate


class SimulatedRtuLine:
    """Serves simulated drives (one per slave id) on a pseudo-terminal."""

    def __init__(self, drives: list[SimulatedDrive], link_path: str | Path,
                 baudrate: int = 115200, parity: str = 'N', stopbits: int = 1,
                 emulate_wire_time: bool = False, corrupt_rate: float = 0.0,
                 tick_period: float = 0.005, seed: int | None = None) -> None:
        self.drives = {drive.unit_id: drive for drive in drives}
        self.link_path = Path(link_path)
        self.char_time = character_time(baudrate, parity, stopbits)
        self.emulate_wire_time = emulate_wire_time
        self.corrupt_rate = corrupt_rate
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

    # --- serving --------------------------------------------------------------------

    def _serve(self) -> None:
        buffer = b''
        last_byte = time.monotonic()
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
                    buffer += chunk
                    last_byte = now
            buffer = self._consume(buffer)
            if buffer and now - last_byte > silence:
                # RTU: 3.5 characters of silence end a frame; what is left is garbage.
                self.stats.crc_errors += 1
                buffer = b''
            for drive in self.drives.values():
                drive.tick()

    def _consume(self, buffer: bytes) -> bytes:
        while buffer:
            try:
                used, pdu = self._framer.handleFrame(buffer, 0, 0)
            except ModbusException:
                self.stats.crc_errors += 1
                return b''
            if pdu is None:
                if used:
                    self.stats.crc_errors += 1
                return buffer[used:]
            request, buffer = buffer[:used], buffer[used:]
            self.stats.frames += 1
            self.received.append((time.monotonic(), request))
            reply = self._answer(pdu)
            if reply is not None:
                self._send(request, reply)
        return buffer

    def _answer(self, request: ModbusPDU) -> bytes | None:
        reply = answer(self.drives, request)
        if reply is None:
            self.stats.ignored += 1
            return None
        return self._framer.buildFrame(reply)

    def _send(self, request: bytes, reply: bytes) -> None:
        if self.corrupt_rate and self._random.random() < self.corrupt_rate:
            reply = self._corrupt(reply)
            self.stats.corrupted_replies += 1
        if self.emulate_wire_time:
            # The request took len*char to arrive, then a 3.5-char gap, then the reply.
            time.sleep((len(request) + 3.5 + len(reply)) * self.char_time)
        try:
            os.write(self._master_fd, reply)
            self.stats.replies += 1
        except OSError:
            pass

    def _corrupt(self, reply: bytes) -> bytes:
        kind = self._random.choice(('crc', 'truncate', 'wrong_id'))
        if kind == 'crc':
            index = self._random.randrange(len(reply))
            return reply[:index] + bytes([reply[index] ^ 0x5A]) + reply[index + 1:]
        if kind == 'truncate':
            return reply[:max(1, len(reply) // 2)]
        wrong = FramerRTU.compute_CRC(bytes([(reply[0] % 247) + 1]) + reply[1:-2])
        return bytes([(reply[0] % 247) + 1]) + reply[1:-2] + wrong.to_bytes(2, 'big')
