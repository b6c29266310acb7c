r"""Simulated CANopen drives in a process of their own, behind a socketcand-protocol server.

A real drive is separate hardware: a simulator that shares the driver's
interpreter takes the driver's time (the GIL), and python-can's ``virtual`` bus
cannot leave its process. Here the simulated drives (``SimulatedCanBus``) and an
optional frame recorder sit on a ``virtual`` channel of this process, and a
``SocketcandServer`` on 127.0.0.1 bridges it to drivers in other processes, which
open it as python-can's ``socketcand`` interface (``transport.interface:
socketcand``, ``transport.can_options: {"host": ..., "port": ..., "tcp_tune":
true}``).

Command line (also what ``CanopenSimProcess`` runs)::

    python -m vfd_ros2.sim.canopen_process --profile cia402_velocity --nodes 1-4 \
        [--port 0] [--bus can0] [--record FILE]

When ready it prints one JSON line on stdout (``host``, ``port``, ``bus``, ``pid``).
It then reads stdin lines: ``status`` prints one JSON line (server counters, each
drive's state); ``stop``, end of input, SIGTERM or SIGINT stop it. At the end
the recording (if asked) is written to FILE, one frame a line:
``received sent cob_id data`` (times in seconds of ``time.monotonic()``, which on
Linux is one clock for every process, so another process can compare them with
its own; ``sent`` is when the frame was put on the simulated bus, ``received``
when the recorder got it; cob_id and data in hex), and a last JSON line reports
the number of frames.
"""

from __future__ import annotations

import argparse
import json
import os
import select
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from types import TracebackType
from typing import Any, NamedTuple

import can

#: the GIL hand-over interval of the driver's executables (ros/executable.py), so the
#: server's threads answer promptly while the drives tick
SWITCH_INTERVAL = 0.0005


class Frame(NamedTuple):
    """One frame seen on the simulated bus (times: ``time.monotonic()``)."""

    received: float
    sent: float
    cob_id: int
    data: bytes


class FrameRecorder(can.Listener):
    """Every frame on a channel, stamped on this host's monotonic clock.

    python-can's virtual bus stamps a frame with ``time.time()`` when it is sent;
    the offset to ``time.monotonic()`` is taken once (the two clocks run at the
    same rate; only a step of the wall clock would shift it).
    """

    def __init__(self, channel: str, interface: str = 'virtual') -> None:
        self.frames: list[Frame] = []
        self._offset = min((time.time() - time.monotonic() for _ in range(5)))
        self._bus = can.Bus(interface=interface, channel=channel)
        self._notifier = can.Notifier(self._bus, [self], timeout=0.1)

    def on_message_received(self, msg: can.Message) -> None:
        self.frames.append(Frame(time.monotonic(), msg.timestamp - self._offset,
                                 msg.arbitration_id, bytes(msg.data)))

    def close(self) -> None:
        self._notifier.stop()
        self._bus.shutdown()


def write_frames(frames: list[Frame], path: str) -> None:
    with open(path, 'w', encoding='ascii') as stream:
        for f in frames:
            stream.write(f'{f.received:.6f} {f.sent:.6f} {f.cob_id:X} {f.data.hex()}\n')


def read_frames(path: str) -> list[Frame]:
    frames = []
    with open(path, encoding='ascii') as stream:
        for line in stream:
            received, sent, cob_id, *data = line.split()
            frames.append(Frame(float(received), float(sent), int(cob_id, 16),
                                bytes.fromhex(data[0] if data else '')))
    return frames


def parse_nodes(text: str) -> list[int]:
    """Return node ids from '1-4', '1,3,5' or '2'."""
    nodes: list[int] = []
    for part in text.split(','):
        first, _, last = part.partition('-')
        nodes.extend(range(int(first), int(last or first) + 1))
    return nodes


# --- the child ------------------------------------------------------------------------------


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    parser.add_argument('--profile', default='cia402_velocity')
    parser.add_argument('--nodes', default='1', help="node ids: '1-4' or '1,3'")
    parser.add_argument('--object-set', default='')
    parser.add_argument('--bus', default='can0', help='the bus name clients open')
    parser.add_argument('--host', default='127.0.0.1')
    parser.add_argument('--port', type=int, default=0, help='0 = any free port')
    parser.add_argument('--record', default='', help='write every frame seen to this file')
    args = parser.parse_args(argv)

    from ..profiles import load_profile
    from .canopen_drive import SimulatedCanBus, SimulatedCanopenDrive
    from .socketcand_server import SocketcandServer

    sys.setswitchinterval(SWITCH_INTERVAL)
    # SIGTERM ends it like end of input (the finally below closes everything)
    signal.signal(signal.SIGTERM, signal.default_int_handler)
    out = sys.stdout
    sys.stdout = sys.stderr         # nothing else may write into the reply stream
    profile = load_profile(args.profile)
    channel = f'{args.bus}-sim{os.getpid()}'
    drives = [SimulatedCanopenDrive(profile, node, args.object_set)
              for node in parse_nodes(args.nodes)]
    recorder = FrameRecorder(channel) if args.record else None
    line = SimulatedCanBus(drives, channel).start()
    server = SocketcandServer({args.bus: channel}, host=args.host, port=args.port)
    try:
        server.start()
        _reply(out, {'host': args.host, 'port': server.port, 'bus': args.bus,
                     'pid': os.getpid()})
        for command in sys.stdin:
            command = command.strip()
            if command == 'stop':
                break
            if command == 'status':
                _reply(out, _status(server, drives))
            else:
                _reply(out, {'error': f'unknown command {command!r}'})
    except KeyboardInterrupt:
        pass
    finally:
        server.stop()
        line.stop()
        if recorder is not None:
            recorder.close()
            write_frames(recorder.frames, args.record)
    _reply(out, {'stopped': True, 'frames': len(recorder.frames) if recorder else 0})
    return 0


def _reply(out: Any, message: dict[str, Any]) -> None:
    out.write(json.dumps(message) + '\n')
    out.flush()


def _status(server: Any, drives: list[Any]) -> dict[str, Any]:
    states = {}
    for drive in drives:
        with drive.lock:
            states[str(drive.node_id)] = {
                'state': drive.state.name, 'nmt': drive.node.nmt.state,
                'speed_rpm': drive.speed_rpm, 'target_raw': drive.target_raw,
                'rpdos': drive.rpdos_received, 'syncs': drive.syncs_received}
    return {'clients': server.clients, 'connections': server.connections,
            'frames_in': server.frames_in, 'frames_out': server.frames_out,
            'errors_sent': server.errors_sent, 'drives': states}


# --- the parent's handle ----------------------------------------------------------------------


class CanopenSimProcess:
    """Start the simulator process; ``with CanopenSimProcess(nodes=[1, 2]) as sim: ...``.

    ``sim.can_options`` are the ``can.Bus`` arguments (``transport.can_options``) of
    its socketcand server; ``stop()`` ends it and returns the recorded frames.
    Close the drivers' buses first: python-can's socketcand client spins on a
    server that has gone (its ``recv`` reads end-of-file as "no frame yet").
    """

    def __init__(self, profile: str = 'cia402_velocity', nodes: Any = (1,),
                 object_set: str = '', bus: str = 'can0', record: bool = False,
                 start_timeout: float = 20.0) -> None:
        self.profile = profile
        self.nodes = list(nodes)
        self.object_set = object_set
        self.bus = bus
        self.record = record
        self.start_timeout = start_timeout
        self.host = '127.0.0.1'
        self.port = 0
        self.pid = 0
        self._process: subprocess.Popen | None = None
        self._tmp: tempfile.TemporaryDirectory | None = None
        self.frames: list[Frame] = []

    @property
    def can_options(self) -> dict[str, Any]:
        """python-can socketcand arguments; tcp_tune: no Nagle delay on small frames."""
        return {'host': self.host, 'port': self.port, 'tcp_tune': True}

    def start(self) -> 'CanopenSimProcess':
        self._tmp = tempfile.TemporaryDirectory(prefix='vfd-cansim-')
        command = [sys.executable, '-m', 'vfd_ros2.sim.canopen_process',
                   '--profile', self.profile, '--nodes', ','.join(map(str, self.nodes)),
                   '--bus', self.bus, '--host', self.host]
        if self.object_set:
            command += ['--object-set', self.object_set]
        if self.record:
            command += ['--record', str(Path(self._tmp.name) / 'frames.txt')]
        self._process = subprocess.Popen(command, stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                         text=True, cwd=self._tmp.name)
        try:
            ready = self._read(self.start_timeout)
            self.port, self.pid = int(ready['port']), int(ready['pid'])
        except Exception:
            self.stop()
            raise
        return self

    def status(self, timeout: float = 5.0) -> dict[str, Any]:
        """Return the server's counters and every simulated drive's state."""
        self._process.stdin.write('status\n')
        self._process.stdin.flush()
        return self._read(timeout)

    def _read(self, timeout: float) -> dict[str, Any]:
        stream = self._process.stdout
        ready, _, _ = select.select([stream], [], [], timeout)
        text = stream.readline() if ready else ''
        if not text:
            code = self._process.poll()
            raise RuntimeError(f'the CANopen simulator process did not answer within '
                               f'{timeout} s' + (f' (exit code {code})' if code is not None
                                                 else ''))
        return json.loads(text)

    def stop(self, timeout: float = 10.0) -> list[Frame]:
        """Stop the process (idempotent); return the recorded frames."""
        process, self._process = self._process, None
        if process is not None:
            try:
                process.stdin.write('stop\n')
                process.stdin.flush()
            except (BrokenPipeError, OSError, ValueError):
                pass
            try:
                process.stdin.close()
            except (BrokenPipeError, OSError):
                pass
            try:
                process.wait(timeout)
            except subprocess.TimeoutExpired:
                process.kill()
                process.wait(2.0)
            process.stdout.close()
            path = Path(self._tmp.name) / 'frames.txt'
            if self.record and path.exists():
                self.frames = read_frames(str(path))
        if self._tmp is not None:
            self._tmp.cleanup()
            self._tmp = None
        return self.frames

    def __enter__(self) -> 'CanopenSimProcess':
        return self.start()

    def __exit__(self, kind: type[BaseException] | None, exc: BaseException | None,
                 trace: TracebackType | None) -> None:
        self.stop()


if __name__ == '__main__':
    sys.exit(main())
