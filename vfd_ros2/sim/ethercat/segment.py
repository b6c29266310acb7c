"""A simulated EtherCAT segment: ESCs in a line behind one raw Ethernet interface.

``Segment`` is the wiring alone (no I/O): a frame enters slave 1's port 0,
passes every reachable ESC in order, turns around at the last one (whose port 1
has no link, so the ESC closes the loop) and returns. A slave can be unplugged
(the cable into it is pulled: it and everything behind it stop seeing frames,
its upstream neighbour closes its port 1), powered off and on again (its
registers reset: station address 0, INIT), and the link to the master can go
down.

``SegmentServer`` serves a segment on an AF_PACKET socket with one thread and
``select``: frames are answered as they come, the devices tick every
millisecond, and a control ``Connection`` carries test commands.

``SimulatedSegment`` runs a server in its own process (multiprocessing, spawn),
so that the master's process - SOEM waits only ``EC_TIMEOUTRET`` (2 ms) for a
reply - never competes with it for the GIL. Its methods send control commands.
"""

from __future__ import annotations

import importlib.util
import multiprocessing
import multiprocessing.connection
import select
import socket
import statistics
import sys
import time
import traceback
import types
from collections import deque
from typing import Any, Sequence

from ...protocol.ethercat import ETHERTYPE_ETHERCAT, ALState
from ...transports.netns import VethLink, open_packet_socket, set_link_state
from .drive import Cia402VelocityDrive, DriveSpec, sii_image
from .esc import HOP_DELAY_NS, Esc
from .frame import FrameError, decode_frame

PACKET_OUTGOING = 4          # sll_pkttype of frames this host sent (linux/if_packet.h)
TICK_S = 0.001


def build_esc(spec: DriveSpec, position: int) -> Esc:
    """Build an ESC with a simulated CiA 402 drive from ``spec``."""
    return Esc(sii_image(spec), Cia402VelocityDrive(spec),
               eeprom_read_bytes=spec.eeprom_read_bytes, name=f'{spec.name}#{position}')


class Segment:
    """ESCs in line order; ``process`` runs one frame through the reachable ones."""

    def __init__(self, escs: Sequence[Esc]) -> None:
        self.escs = list(escs)
        self._plugged = [True] * len(self.escs)
        self.link_up = True
        self.frames = 0
        self._update_links()

    @property
    def reachable(self) -> int:
        """How many ESCs a frame passes (up to the first unplugged one)."""
        if not self.link_up:
            return 0
        for position, plugged in enumerate(self._plugged):
            if not plugged:
                return position
        return len(self.escs)

    def _update_links(self) -> None:
        count = self.reachable
        for position, esc in enumerate(self.escs):
            esc.set_downstream_link(position < count - 1)

    def unplug(self, position: int) -> None:
        """Pull the cable into slave ``position``: it and the slaves behind it fall silent."""
        self._plugged[position] = False
        self._update_links()

    def replug(self, position: int) -> None:
        self._plugged[position] = True
        self._update_links()

    def power_cycle(self, position: int) -> None:
        """Switch slave ``position`` off and on: all its registers reset (INIT, address 0).

        The device behind it restarts too (its application's ``power_on``, if any): what
        the master wrote to it (PDO mappings, modes) is gone, as on a real drive.
        """
        esc = self.escs[position]
        power_on = getattr(esc.app, 'power_on', None)
        if power_on is not None:
            power_on()
        esc.power_on(time.monotonic_ns(), time.monotonic())

    def process(self, frame: bytes, now_ns: int | None = None) -> bytes | None:
        """Return the frame as it comes back to the master, or None if none comes back."""
        count = self.reachable
        if count == 0:
            return None
        try:
            parsed = decode_frame(frame)
        except FrameError:
            return None                  # an ESC forwards garbage unchanged; SOEM drops it
        now_ns = time.monotonic_ns() if now_ns is None else now_ns
        now = now_ns / 1e9
        datagrams = parsed.datagrams
        last = count - 1
        for position in range(count):
            esc = self.escs[position]
            # receive times: port 0 on the way out, port 1 on the way back
            arrival = now_ns + position * HOP_DELAY_NS
            back = now_ns + (2 * last - position) * HOP_DELAY_NS if position < last else None
            esc.begin_frame(arrival, back, now)
            for datagram in datagrams:
                esc.process(datagram)
        for position in range(count):
            self.escs[position].end_frame()
        # the first ESC marks the frame as processed: source MAC U/L bit (ETG.1000.4 5.2)
        parsed.source = bytes([parsed.source[0] | 0x02]) + parsed.source[1:]
        self.frames += 1
        return parsed.encode()

    def tick(self, now: float) -> None:
        for esc in self.escs:
            esc.tick(now)


class SegmentServer:
    """Serves a ``Segment`` on a packet socket until told to stop (one thread)."""

    def __init__(self, segment: Segment, sock: socket.socket,
                 control: multiprocessing.connection.Connection | None = None) -> None:
        self.segment = segment
        self.sock = sock
        self.control = control
        self.running = True
        self.processing_ns: deque[int] = deque(maxlen=20000)
        self.frames_in = 0
        self.frames_out = 0
        self.send_errors = 0
        self.lose_until = 0.0        # frames until then are lost on the wire (never answered)

    def serve(self) -> None:
        self.sock.setblocking(False)
        sources: list[Any] = [self.sock] + ([self.control] if self.control else [])
        next_tick = time.monotonic()
        while self.running:
            timeout = max(0.0, next_tick - time.monotonic())
            ready, _, _ = select.select(sources, [], [], timeout)
            if self.sock in ready:
                self._drain()
            if self.control is not None and self.control in ready:
                self._command()
            now = time.monotonic()
            if now >= next_tick:
                self.segment.tick(now)
                next_tick = now + TICK_S

    def _drain(self) -> None:
        while True:
            try:
                frame, address = self.sock.recvfrom(2048)
            except (BlockingIOError, InterruptedError):
                return
            except OSError:
                return                   # e.g. ENETDOWN while the link is down
            if address[2] == PACKET_OUTGOING:
                continue
            self.frames_in += 1
            if self.lose_until and time.monotonic() < self.lose_until:
                continue
            start = time.monotonic_ns()
            reply = self.segment.process(frame, start)
            if reply is None:
                continue
            try:
                self.sock.send(reply)
                self.frames_out += 1
            except OSError:
                self.send_errors += 1
            self.processing_ns.append(time.monotonic_ns() - start)

    def _command(self) -> None:
        try:
            name, args = self.control.recv()
        except EOFError:
            self.running = False
            return
        try:
            result = self.execute(name, *args)
            self.control.send(('ok', result))
        except Exception as exc:  # noqa: BLE001 - reported to the caller
            self.control.send(('error', f'{type(exc).__name__}: {exc}'))

    def execute(self, name: str, *args: Any) -> Any:
        """Run one control command (see ``SimulatedSegment``)."""
        segment = self.segment
        if name == 'stop':
            self.running = False
            return None
        if name in ('unplug', 'replug', 'power_cycle'):
            getattr(segment, name)(*args)
            return None
        if name == 'fail':
            position, state, code = args
            segment.escs[position].application_error(ALState(state), code)
            return None
        if name == 'lose_frames':
            self.lose_until = time.monotonic() + float(args[0])
            return None
        if name == 'link':
            segment.link_up = bool(args[0])
            segment._update_links()
            return None
        if name == 'call':
            position, method, *rest = args
            app = segment.escs[position].app
            if method not in getattr(app, 'CONTROLS', ()):
                raise ValueError(f'{method!r} is not a control of {type(app).__name__}')
            return getattr(app, method)(*rest)
        if name == 'esc':
            esc = segment.escs[args[0]]
            return {'al_status': esc.al_status, 'al_status_code': esc.al_status_code,
                    'station_address': esc.station_address,
                    'watchdog_expired': esc.watchdog_expired,
                    'watchdog_s': esc.watchdog_time_s(),
                    'sync0_cycle_ns': esc.sync0_cycle_ns(),
                    'mailbox_received': esc.mailbox.received}
        if name == 'stats':
            samples = sorted(self.processing_ns)
            return {
                'frames_in': self.frames_in, 'frames_out': self.frames_out,
                'send_errors': self.send_errors,
                'processing_us_p50': statistics.median(samples) / 1e3 if samples else 0.0,
                'processing_us_p99': samples[int(0.99 * (len(samples) - 1))] / 1e3
                if samples else 0.0,
                'processing_us_max': samples[-1] / 1e3 if samples else 0.0,
            }
        raise ValueError(f'unknown segment command {name!r}')


def _serve_in_process(link: VethLink, specs: Sequence[DriveSpec],
                      control: multiprocessing.connection.Connection) -> None:
    try:
        segment = Segment([build_esc(spec, position) for position, spec in enumerate(specs)])
        sock = open_packet_socket(link.slave_interface, link.namespace, ETHERTYPE_ETHERCAT)
    except Exception:  # noqa: BLE001 - reported to the parent, which raises
        control.send(('error', traceback.format_exc()))
        return
    control.send(('ok', len(segment.escs)))
    try:
        SegmentServer(segment, sock, control).serve()
    finally:
        sock.close()


class SegmentError(RuntimeError):
    """The simulated segment's process failed or refused a command."""


class SimulatedSegment:
    """A segment of simulated drives served by a child process on ``link``'s slave end.

    Positions are 0-based in line order (pysoem's ``master.slaves`` index).
    """

    def __init__(self, link: VethLink, specs: Sequence[DriveSpec],
                 start_timeout: float = 20.0) -> None:
        self.link = link
        self.specs = list(specs)
        self._closed = False
        context = multiprocessing.get_context('spawn')
        self._conn, child = context.Pipe()
        self._process = context.Process(target=_serve_in_process,
                                        args=(link, self.specs, child), daemon=True,
                                        name='ethercat-segment')
        # A spawned child re-runs the parent's main module unless told otherwise; a
        # script without a __main__ guard (an installed console script, a benchmark
        # runner) would run again there. The child needs only this module.
        main_module = sys.modules['__main__']
        stand_in = types.ModuleType('__main__')
        stand_in.__spec__ = importlib.util.find_spec(__name__)
        sys.modules['__main__'] = stand_in
        try:
            self._process.start()
        finally:
            sys.modules['__main__'] = main_module
        child.close()
        if not self._conn.poll(start_timeout):
            self.close()
            raise SegmentError(f'simulated segment did not start within {start_timeout} s')
        status, detail = self._conn.recv()
        if status != 'ok':
            self.close()
            raise SegmentError(f'simulated segment failed to start:\n{detail}')

    @property
    def pid(self) -> int | None:
        """Process id of the serving process (CPU accounting)."""
        return self._process.pid

    def _request(self, name: str, *args: Any, timeout: float = 5.0) -> Any:
        if not self._process.is_alive():
            raise SegmentError('the simulated segment process is not running')
        self._conn.send((name, args))
        if not self._conn.poll(timeout):
            raise SegmentError(f'segment command {name!r} got no answer within {timeout} s')
        status, result = self._conn.recv()
        if status != 'ok':
            raise SegmentError(f'segment command {name!r} failed: {result}')
        return result

    def unplug(self, position: int) -> None:
        self._request('unplug', position)

    def replug(self, position: int) -> None:
        self._request('replug', position)

    def power_cycle(self, position: int) -> None:
        self._request('power_cycle', position)

    def lose_frames(self, seconds: float) -> None:
        """Lose every frame the master sends for ``seconds`` (EMI, a loose connector)."""
        self._request('lose_frames', seconds)

    def link_down(self) -> None:
        """Carrier off: the slaves' veth end goes down (the master sees no carrier)."""
        self._request('link', False)
        set_link_state(self.link, False)

    def link_up(self) -> None:
        set_link_state(self.link, True)
        self._request('link', True)

    def fail(self, position: int, state: ALState, code: int) -> None:
        """Make slave ``position`` fall back to ``state`` with the AL error flag and ``code``.

        By itself, as on an application error: the master is not told, and the slave
        goes on answering the cycle frame in its new state.
        """
        self._request('fail', position, int(state), code)

    def call(self, position: int, method: str, *args: Any) -> Any:
        """Call a control method of slave ``position``'s application (its ``CONTROLS``)."""
        return self._request('call', position, method, *args)

    def drive(self, position: int) -> dict[str, Any]:
        """Return the simulated drive's state (``Cia402VelocityDrive.snapshot``)."""
        return self.call(position, 'snapshot')

    def esc(self, position: int) -> dict[str, Any]:
        """AL status and code, station address, watchdog, SYNC0 of slave ``position``'s ESC."""
        return self._request('esc', position)

    def stats(self) -> dict[str, Any]:
        return self._request('stats')

    def close(self) -> None:
        """Stop the server process (idempotent)."""
        if self._closed:
            return
        self._closed = True
        if self._process.is_alive():
            try:
                self._conn.send(('stop', ()))
                self._conn.poll(2.0) and self._conn.recv()
            except (OSError, EOFError):
                pass
            self._process.join(3.0)
            if self._process.is_alive():
                self._process.terminate()
                self._process.join(2.0)
        self._conn.close()
        if not self._process.is_alive():
            self._process.close()           # its sentinel pipe

    def __enter__(self) -> 'SimulatedSegment':
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
