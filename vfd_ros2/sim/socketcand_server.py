"""A socketcand-protocol server: python-can buses of this process, reachable over TCP.

python-can's ``virtual`` bus lives inside one process. To put simulated drives in a
process of their own (so they do not share the driver's interpreter and GIL) the
driver needs a real, standard CAN transport that crosses processes: the socketcand
daemon's ASCII protocol over TCP (linux-can/socketcand, ``doc/protocol.md``), which
python-can speaks as a client (``interface='socketcand'``). This is the server side
of that protocol, bridging each TCP client to a python-can bus of this process.

What is served (the subset a CAN client needs, in socketcand's words):

- NO_BUS: ``< hi >`` on connect; ``< open name >`` -> ``< ok >`` and BCM mode; a bus
  this server does not offer -> ``< error could not open bus >`` and the connection
  is closed (as socketcand does);
- BCM: ``< send id dlc data* >``, ``< rawmode >``, ``< echo >``; the cyclic and
  filtering commands of the kernel's broadcast manager (add, update, delete, filter,
  subscribe, ...), control and ISO-TP modes answer ``< error ... not supported ... >``;
- RAW: every frame on the bus as ``< frame id secs.usecs data >`` (data: upper-case
  hex without spaces), ``< send ... >``, ``< bcmmode >``, ``< echo >``.

Each client has its own bus handle on the channel, so a frame one client sends
reaches the simulated drives, the other handles and the other clients, never
itself (as a frame sent on a CAN_RAW socket is not read back on it). Anything a
client sends that is not a well-formed command gets ``< error ... >`` and the
connection goes on (socketcand drops a malformed ``send`` silently; an answer
tells a client's author why the frame never appeared). A client that goes away is
dropped with its bus handle; the server keeps serving the others.

One deviation on purpose, at the switch to RAW mode: python-can's client reads the
``< ok >`` of ``< rawmode >`` with one ``recv`` and compares it whole, so a frame
arriving in the same TCP segment fails its handshake (SavvyCAN met the same race
with socketcand, collin80/SavvyCAN#495). Frames are therefore relayed once the
client has said anything after that ``< ok >`` (it has read it) or ``raw_hold``
seconds after it; frames of the bus meanwhile wait in the client's bus queue.

Listens on 127.0.0.1 by default; nothing here opens a non-loopback address unless
asked to.
"""

from __future__ import annotations

import enum
import logging
import select
import socket
import threading
import time
from dataclasses import dataclass, field
from typing import Any, Callable, Mapping

import can

log = logging.getLogger(__name__)

#: the longest command kept while waiting for its '>' (socketcand's MAXLEN is 4096)
MAX_COMMAND = 4096
#: BCM, control and ISO-TP commands of socketcand that this server does not implement
UNSUPPORTED = frozenset({'add', 'update', 'delete', 'filter', 'muxfilter', 'subscribe',
                         'unsubscribe', 'sendrtr', 'fdsend', 'controlmode', 'statistics',
                         'isotpmode', 'isotpconf', 'sendpdu'})


class Mode(enum.Enum):
    """The protocol's modes (socketcand's states) a connection can be in."""

    NO_BUS = 'no bus'
    BCM = 'bcm'
    RAW = 'raw'


class CommandError(ValueError):
    """A client's command that cannot be served; the text goes back in ``< error ... >``."""


def parse_send(tokens: list[str]) -> can.Message:
    """Return the frame of ``send id dlc data*`` (tokens after 'send'); raise CommandError.

    socketcand's rules: the id is hex, 8 digits mean an extended (29-bit) id; the dlc
    is 0..8 and exactly that many data bytes follow, each one or two hex digits.
    """
    if len(tokens) < 2:
        raise CommandError('syntax error in send command: needs an id and a dlc')
    ident, dlc_text, data_tokens = tokens[0], tokens[1], tokens[2:]
    extended = len(ident) == 8
    try:
        arbitration_id = int(ident, 16)
        dlc = int(dlc_text, 16)
        data = bytes(int(byte, 16) for byte in data_tokens)
    except ValueError:
        raise CommandError('syntax error in send command: not hex') from None
    if any(len(byte) > 2 for byte in data_tokens):
        raise CommandError('syntax error in send command: a data byte has more than 2 digits')
    if not (len(ident) <= 3 and arbitration_id <= 0x7FF or
            extended and arbitration_id <= 0x1FFFFFFF):
        raise CommandError(f'syntax error in send command: bad can id {ident}')
    if not 0 <= dlc <= 8 or len(data) != dlc:
        raise CommandError(f'syntax error in send command: dlc {dlc_text} with {len(data)} '
                           'data bytes')
    return can.Message(arbitration_id=arbitration_id, is_extended_id=extended, data=data,
                       dlc=dlc)


def format_frame(msg: can.Message) -> str | None:
    """Return a received frame as RAW mode sends it; None for a frame it cannot carry."""
    seconds, micros = divmod(round(msg.timestamp * 1e6), 1_000_000)
    stamp = f'{seconds}.{micros:06d}'
    ident = f'{msg.arbitration_id:08X}' if msg.is_extended_id else f'{msg.arbitration_id:03X}'
    if msg.is_error_frame:
        return f'< error {msg.arbitration_id & 0x1FFFFFFF:03X} {stamp} >'
    if msg.is_remote_frame:
        return f'< rtr {ident} {stamp} {msg.dlc} >'
    if msg.is_fd:
        return None          # classical CAN only
    return f'< frame {ident} {stamp} {bytes(msg.data).hex().upper()} >'


def extract_commands(buffer: bytearray) -> tuple[list[bytes], str | None]:
    """Take the complete ``< ... >`` commands out of ``buffer`` (in place).

    Bytes before a '<' are dropped, as socketcand does; a '<' without its '>' after
    ``MAX_COMMAND`` bytes is dropped with an error text (second value).
    """
    commands: list[bytes] = []
    while True:
        start = buffer.find(b'<')
        if start < 0:
            buffer.clear()
            return commands, None
        del buffer[:start]
        stop = buffer.find(b'>')
        if stop < 0:
            if len(buffer) > MAX_COMMAND:
                buffer.clear()
                return commands, 'command too long'
            return commands, None
        commands.append(bytes(buffer[:stop + 1]))
        del buffer[:stop + 1]


@dataclass(eq=False)
class _Client:
    """One TCP connection: its mode, its bus handle and its two threads."""

    sock: socket.socket
    peer: str
    mode: Mode = Mode.NO_BUS
    bus: Any = None
    bus_name: str = ''
    hold_until: float = 0.0
    released: threading.Event = field(default_factory=threading.Event)
    closing: threading.Event = field(default_factory=threading.Event)
    send_lock: threading.Lock = field(default_factory=threading.Lock)
    reader: threading.Thread | None = None
    relay: threading.Thread | None = None
    frames_in: int = 0
    frames_out: int = 0


class SocketcandServer:
    """Serve python-can buses of this process to socketcand clients over TCP.

    ``buses`` maps the bus names clients may ``open`` to the python-can channel
    each stands for (a plain string: one bus, the same name for both). Every
    client that opens a bus gets its own handle from ``bus_factory(channel)``
    (default: ``can.Bus(interface=interface, channel=channel)``; the interface must
    allow several handles per channel, as ``virtual`` and ``socketcan`` do).
    """

    def __init__(self, buses: Mapping[str, str] | str, interface: str = 'virtual',
                 host: str = '127.0.0.1', port: int = 0, raw_hold: float = 0.1,
                 bus_factory: Callable[[str], Any] | None = None) -> None:
        self.buses = {buses: buses} if isinstance(buses, str) else dict(buses)
        self.interface = interface
        self.host = host
        self.requested_port = port
        self.port = 0
        self.raw_hold = raw_hold
        self._bus_factory = bus_factory or (
            lambda channel: can.Bus(interface=self.interface, channel=channel))
        self._listener: socket.socket | None = None
        self._accepter: threading.Thread | None = None
        self._clients: list[_Client] = []
        self._lock = threading.Lock()
        self._counts = threading.Lock()
        self._stop = threading.Event()
        self.connections = 0            # accepted since start
        self.frames_in = 0              # frames clients sent onto the bus (dropped clients too)
        self.frames_out = 0             # frames relayed to clients
        self.errors_sent = 0            # ``< error ... >`` answers

    # --- life cycle -------------------------------------------------------------------

    def start(self) -> 'SocketcandServer':
        listener = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        try:
            listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            listener.bind((self.host, self.requested_port))
            listener.listen(8)
        except OSError:
            listener.close()
            raise
        self._listener = listener
        self.port = listener.getsockname()[1]
        self._stop.clear()
        self._accepter = threading.Thread(target=self._accept_loop, daemon=True,
                                          name=f'socketcand :{self.port}')
        self._accepter.start()
        return self

    def stop(self) -> None:
        """Drop every client (closing its bus handle) and stop listening (idempotent)."""
        self._stop.set()
        if self._accepter is not None:
            self._accepter.join(2.0)
            self._accepter = None
        if self._listener is not None:
            self._listener.close()
            self._listener = None
        with self._lock:
            clients = list(self._clients)
        for client in clients:
            self._hang_up(client)
        for client in clients:
            if client.reader is not None:
                client.reader.join(2.0)

    def __enter__(self) -> 'SocketcandServer':
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    @property
    def clients(self) -> int:
        """Connections open now."""
        with self._lock:
            return len(self._clients)

    def _accept_loop(self) -> None:
        listener = self._listener
        while not self._stop.is_set():
            try:
                ready, _, _ = select.select([listener], [], [], 0.1)
                if not ready:
                    continue
                sock, address = listener.accept()
            except OSError as exc:
                if not self._stop.is_set():
                    log.warning('socketcand server :%d: accept failed: %s', self.port, exc)
                    time.sleep(0.1)
                continue
            # Frames are small and latency-bound: no Nagle delay (socketcand: TCP_QUICKACK).
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            client = _Client(sock, f'{address[0]}:{address[1]}')
            client.reader = threading.Thread(target=self._serve, args=(client,), daemon=True,
                                             name=f'socketcand {client.peer}')
            with self._lock:
                if self._stop.is_set():
                    sock.close()
                    return
                self._clients.append(client)
                self.connections += 1
            client.reader.start()

    def _hang_up(self, client: _Client) -> None:
        """Make the client's reader see the end of the connection (it cleans up)."""
        try:
            client.sock.shutdown(socket.SHUT_RDWR)
        except OSError:
            pass            # already gone

    # --- one connection -----------------------------------------------------------------

    def _serve(self, client: _Client) -> None:
        """Read the client's commands and answer them (its reader thread); clean up at the end."""
        buffer = bytearray()
        try:
            self._write(client, '< hi >')
            while not self._stop.is_set():
                data = client.sock.recv(4096)
                if not data:
                    break
                # socketcand acknowledges at once too (its tcp_quickack)
                client.sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_QUICKACK, 1)
                buffer += data
                commands, problem = extract_commands(buffer)
                if problem:
                    self._error(client, problem)
                if commands and client.mode is Mode.RAW:
                    client.released.set()       # it read the rawmode answer: relay frames
                for command in commands:
                    if not self._command(client, command):
                        return
        except OSError as exc:
            log.debug('socketcand client %s: %s', client.peer, exc)
        finally:
            self._drop(client)

    def _drop(self, client: _Client) -> None:
        client.closing.set()
        if client.relay is not None:
            client.relay.join(2.0)
        if client.bus is not None:
            try:
                client.bus.shutdown()
            except Exception as exc:  # noqa: BLE001 - closing never raises
                log.debug('closing the bus of %s: %s', client.peer, exc)
        client.sock.close()
        with self._lock:
            if client in self._clients:
                self._clients.remove(client)
        log.debug('socketcand client %s dropped (%d frames in, %d out)', client.peer,
                  client.frames_in, client.frames_out)

    def _write(self, client: _Client, text: str) -> None:
        with client.send_lock:
            client.sock.sendall(text.encode('ascii'))

    def _error(self, client: _Client, text: str) -> None:
        with self._counts:
            self.errors_sent += 1
        self._write(client, f'< error {text} >')

    def _command(self, client: _Client, raw: bytes) -> bool:
        """Serve one ``< ... >`` command; return False to close the connection."""
        try:
            text = raw.decode('ascii')
        except UnicodeDecodeError:
            self._error(client, 'malformed command: not ASCII')
            return True
        tokens = text[1:-1].split()
        verb = tokens[0] if tokens else ''
        try:
            if client.mode is Mode.NO_BUS:
                if verb == 'open':
                    return self._open(client, tokens[1:])
                raise CommandError('unknown command')
            if verb == 'send':
                self._send(client, tokens[1:])
            elif verb == 'echo':
                self._write(client, text)
            elif verb == 'rawmode':
                # RAW before the answer (no frame sent meanwhile may be lost), but held
                # until the client has read it: see the module's note on the handshake
                client.released.clear()
                client.hold_until = time.monotonic() + self.raw_hold
                client.mode = Mode.RAW
                self._write(client, '< ok >')
            elif verb == 'bcmmode':
                client.mode = Mode.BCM
                self._write(client, '< ok >')
            elif verb in UNSUPPORTED:
                raise CommandError(f'{verb} is not supported by this server')
            else:
                raise CommandError('unknown command')
        except CommandError as exc:
            self._error(client, str(exc))
        return True

    def _open(self, client: _Client, arguments: list[str]) -> bool:
        if len(arguments) != 1:
            self._error(client, 'syntax error in open command')
            return True
        channel = self.buses.get(arguments[0])
        if channel is None:
            self._error(client, 'could not open bus')   # socketcand then hangs up
            return False
        try:
            client.bus = self._bus_factory(channel)
        except (can.CanError, OSError, ValueError) as exc:
            log.warning('socketcand: cannot open %s for %s: %s', channel, client.peer, exc)
            self._error(client, f'could not start interface {arguments[0]}')
            return False
        client.bus_name = arguments[0]
        client.mode = Mode.BCM
        client.relay = threading.Thread(target=self._relay, args=(client,), daemon=True,
                                        name=f'socketcand {client.peer} relay')
        client.relay.start()
        self._write(client, '< ok >')
        return True

    def _send(self, client: _Client, arguments: list[str]) -> None:
        msg = parse_send(arguments)
        try:
            client.bus.send(msg)
        except can.CanError as exc:
            raise CommandError(f'could not send the frame: {exc}') from exc
        client.frames_in += 1
        with self._counts:
            self.frames_in += 1

    def _relay(self, client: _Client) -> None:
        """Relay every frame of the bus to the client in RAW mode (its bus thread)."""
        bus = client.bus
        pending: list[str] = []         # frames taken from the bus, not yet sent
        try:
            while not client.closing.is_set():
                if pending and not client.released.is_set():
                    wait = client.hold_until - time.monotonic()
                    if wait > 0 and not client.released.wait(min(wait, 0.05)):
                        continue        # later frames wait in the bus queue meanwhile
                    client.released.set()
                if pending:
                    self._write(client, ''.join(pending))
                    client.frames_out += len(pending)
                    with self._counts:
                        self.frames_out += len(pending)
                    pending.clear()
                msg = bus.recv(0.05)
                if msg is None or client.mode is not Mode.RAW:
                    continue            # BCM mode without subscriptions: nothing to relay
                line = format_frame(msg)
                if line is not None:
                    pending.append(line)
        except (OSError, can.CanError) as exc:
            # the reader sees the broken connection too and drops the client
            log.debug('socketcand relay to %s: %s', client.peer, exc)
            self._hang_up(client)
