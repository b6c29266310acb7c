"""Simulated drives in their own process, so the driver under test has the GIL to itself.

A real drive is separate hardware; a simulator sharing the driver's
interpreter would steal its time (and its wire-time emulation spins near
each byte's deadline). The child serves an RTU line (pty) or a TCP server
and answers a few queries over a pipe: the exchanges it saw (with their
times on the emulated wire, ``time.monotonic()``, which is system-wide) and
its counters.
"""

from __future__ import annotations

import dataclasses
import os
import pickle
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any, BinaryIO

ROOT = Path(__file__).resolve().parent.parent


class _Pipe:
    """Pickled messages over a pair of byte streams."""

    def __init__(self, reader: BinaryIO, writer: BinaryIO) -> None:
        self._reader, self._writer = reader, writer

    def send(self, message: Any) -> None:
        pickle.dump(message, self._writer)
        self._writer.flush()

    def recv(self) -> Any:
        return pickle.load(self._reader)


#: SCHED_FIFO priority of the simulator process where the system allows it: it stands
#: in for drive hardware, whose replies no scheduler holds back, so its own wake-up
#: latency should not be charged to the driver under test (its threads inherit it)
SIM_REALTIME_PRIORITY = 60


def child_main() -> None:
    """Entry point of the simulator process: arguments arrive as the first message."""
    conn = _Pipe(sys.stdin.buffer, sys.stdout.buffer)
    sys.stdout = sys.stderr         # nothing else may write into the message stream
    realtime = _go_realtime()
    _serve(conn, realtime, *conn.recv())


def _go_realtime() -> bool:
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(SIM_REALTIME_PRIORITY))
    except (OSError, AttributeError):      # not permitted (no CAP_SYS_NICE), not Linux
        return False
    return True


def _serve(conn: Any, realtime: bool, kind: str, profile: str, units: list[int], where: str,
           baudrate: int, parity: str, stopbits: int, emulate: bool,
           adapter_latency: float = 0.0) -> None:
    from vfd_ros2.profiles import load_profile
    from vfd_ros2.sim.model import SimulatedDrive

    loaded = load_profile(profile)
    drives = [SimulatedDrive(loaded, unit, _initial(loaded)) for unit in units]
    if kind == 'rtu':
        from vfd_ros2.sim.rtu_line import SimulatedRtuLine
        line: Any = SimulatedRtuLine(drives, where, baudrate=baudrate, parity=parity,
                                     stopbits=stopbits, emulate_wire_time=emulate,
                                     adapter_latency=adapter_latency).start()
        conn.send(('ready', where))
    else:
        from vfd_ros2.sim.tcp_server import SimulatedTcpServer
        line = SimulatedTcpServer(drives).start()
        conn.send(('ready', line.port))
    seen = 0
    try:
        while True:
            command, argument = conn.recv()
            if command == 'stop':
                break
            if command == 'exchanges':       # RTU with emulation: full wire records
                records = [(e.request_start, e.request_end, e.request, e.reply_bytes)
                           for e in list(line.exchanges) if e.request_start >= argument]
                conn.send(records)
            elif command == 'received':      # any: (time, request frame) since argument
                conn.send([(t, f) for t, f in list(line.received) if t >= argument])
            elif command == 'stats':
                stats = getattr(line, 'stats', None)
                conn.send({**(dataclasses.asdict(stats) if stats is not None else
                              {'frames': line.frames}), 'realtime': realtime})
            else:
                conn.send(None)
            seen += 1
    finally:
        line.stop()


def _initial(profile: Any) -> dict[str, float]:
    velocity = profile.velocity
    return {code: 0.5 for code in (velocity.acceleration_time, velocity.deceleration_time)
            if code}


class SimProcess:
    """Start with ``with SimProcess(...) as sim:``; ``sim.where`` is the port path or TCP port."""

    def __init__(self, kind: str, profile: str, units: list[int], where: str = '',
                 baudrate: int = 115200, parity: str = 'N', stopbits: int = 1,
                 emulate: bool = True, adapter_latency: float = 0.0) -> None:
        self._args = (kind, profile, units, where, baudrate, parity, stopbits, emulate,
                      adapter_latency)
        self._process: subprocess.Popen | None = None
        self._conn: _Pipe | None = None
        self.where: Any = None

    def __enter__(self) -> 'SimProcess':
        env = dict(os.environ)
        env['PYTHONPATH'] = os.pathsep.join(
            p for p in (env.get('PYTHONPATH', ''), str(ROOT)) if p)
        self._process = subprocess.Popen(
            [sys.executable, '-c', 'from bench.simproc import child_main; child_main()'],
            stdin=subprocess.PIPE, stdout=subprocess.PIPE, env=env, cwd=tempfile.gettempdir())
        self._conn = _Pipe(self._process.stdout, self._process.stdin)
        self._conn.send(self._args)
        _, self.where = self._conn.recv()
        return self

    def ask(self, command: str, argument: Any = None) -> Any:
        self._conn.send((command, argument))
        return self._conn.recv()

    @property
    def pid(self) -> int:
        return self._process.pid

    def __exit__(self, *exc: object) -> None:
        try:
            self._conn.send(('stop', None))
        except (BrokenPipeError, OSError):
            pass
        try:
            self._process.wait(5.0)
        except subprocess.TimeoutExpired:
            self._process.terminate()
            self._process.wait(2.0)


def wait_port(path: str, timeout: float = 5.0) -> None:
    import os
    deadline = time.monotonic() + timeout
    while not os.path.exists(path):
        if time.monotonic() > deadline:
            raise RuntimeError(f'{path} did not appear')
        time.sleep(0.01)
