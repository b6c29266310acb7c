"""Simulated drives behind a Modbus TCP server on a loopback port.

MBAP framing is pymodbus' socket framer, the replies come from the same
dispatch as the RTU line, so a Modbus TCP card (e.g. the IMO HD2's) is
emulated with real frames. It listens on 127.0.0.1 only.
"""

from __future__ import annotations

import collections
import socket
import threading
import time

from ..transports import modbus_library  # noqa: F401 - the pymodbus version check, before pymodbus

# isort: split

from pymodbus.exceptions import ModbusException
from pymodbus.framer import FramerSocket
from pymodbus.pdu import DecodePDU

from .dispatch import answer
from .model import SimulatedDrive


class SimulatedTcpServer:
    """Serves simulated drives (by unit id) on ``127.0.0.1:port`` (0 = any free port)."""

    def __init__(self, drives: list[SimulatedDrive], port: int = 0,
                 tick_period: float = 0.005) -> None:
        self.drives = {drive.unit_id: drive for drive in drives}
        self.requested_port = port
        self.port = 0
        self.tick_period = tick_period
        self.frames = 0
        self.received: collections.deque[tuple[float, bytes]] = collections.deque(maxlen=4096)
        self._listener: socket.socket | None = None
        self._clients: list[socket.socket] = []
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []

    def start(self) -> 'SimulatedTcpServer':
        listener = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        listener.bind(('127.0.0.1', self.requested_port))
        listener.listen(8)
        listener.settimeout(0.1)
        self._listener = listener
        self.port = listener.getsockname()[1]
        self._stop.clear()
        for target in (self._accept, self._tick):
            thread = threading.Thread(target=target, daemon=True,
                                      name=f'sim tcp {self.port} {target.__name__}')
            thread.start()
            self._threads.append(thread)
        return self

    def stop(self) -> None:
        """Stop serving and drop every connection (the driver sees the peer vanish)."""
        self._stop.set()
        for sock in [self._listener, *self._clients]:
            if sock is not None:
                try:
                    sock.close()
                except OSError:
                    pass
        for thread in self._threads:
            thread.join(2.0)
        self._threads.clear()
        self._clients.clear()
        self._listener = None

    def __enter__(self) -> 'SimulatedTcpServer':
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def _tick(self) -> None:
        while not self._stop.wait(self.tick_period):
            for drive in self.drives.values():
                drive.tick()

    def _accept(self) -> None:
        while not self._stop.is_set():
            try:
                client, _ = self._listener.accept()
            except socket.timeout:
                continue
            except OSError:
                return
            client.settimeout(0.1)
            self._clients.append(client)
            thread = threading.Thread(target=self._serve, args=(client,), daemon=True)
            thread.start()
            self._threads.append(thread)

    def _serve(self, client: socket.socket) -> None:
        framer = FramerSocket(DecodePDU(is_server=True))
        buffer = b''
        while not self._stop.is_set():
            try:
                chunk = client.recv(4096)
            except socket.timeout:
                continue
            except OSError:
                return
            if not chunk:
                return
            buffer += chunk
            while buffer:
                try:
                    used, request = framer.handleFrame(buffer, 0, 0)
                except ModbusException:
                    buffer = b''
                    break
                if request is None:
                    buffer = buffer[used:]
                    break
                self.received.append((time.monotonic(), buffer[:used]))
                buffer = buffer[used:]
                self.frames += 1
                reply = answer(self.drives, request)
                if reply is not None:
                    try:
                        client.sendall(framer.buildFrame(reply))
                    except OSError:
                        return
