"""The manuals' example frames are test vectors (test/vectors/*_frames.yaml).

For every printed request the driver must put exactly the printed bytes on the
wire, and it must decode the printed reply (values, or the exception with the
drive's own meaning). The driver talks to a scripted slave on a pseudo-terminal
(Modbus RTU) or a local TCP socket (Modbus TCP); the slave records the request
bytes and answers with the printed reply. The simulated twin must answer the
printed requests with the printed replies wherever its state determines them.

No fixed sleeps: every wait is a select() or join() with a deadline.
"""

from __future__ import annotations

import functools
import math
import os
import select
import socket
import threading
import time
import tty
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import pytest
import yaml

from vfd_ros2.drives.modbus import ModbusDrive
from vfd_ros2.errors import BadFrame, ProtocolException
from vfd_ros2.profiles import Profile
from vfd_ros2.profiles import load_profile as _load_profile
from vfd_ros2.protocol.scaling import RPM_PER_RAD_S, VelocityScaling
from vfd_ros2.sim.model import SimulatedDrive
from vfd_ros2.sim.rtu_line import SimulatedRtuLine
from vfd_ros2.transports.modbus import ModbusRtuTransport, ModbusTcpTransport

VECTOR_DIR = Path(__file__).parent / 'vectors'
DEADLINE = 2.0          # s: longest wait for a frame anywhere in this file
REPLY_TIMEOUT = 0.3     # s: the driver's reply timeout (bad-CRC replies wait this long)

#: vector file -> (profile, transport kind)
FAMILIES = {
    'boneng_am': ('boneng_am', 'rtu'),
    'boneng_mh': ('boneng_mh', 'rtu'),
    'veichi_ehs100': ('veichi_ehs100', 'rtu'),
    'kinco_ec': ('kinco_ec', 'rtu'),
    'imo_hd2': ('imo_hd2', 'tcp'),
}


# --- vectors ---------------------------------------------------------------------------

def crc16_modbus(data: bytes) -> bytes:
    """CRC-16/MODBUS, low byte first (independent of pymodbus on purpose)."""
    crc = 0xFFFF
    for byte in data:
        crc ^= byte
        for _ in range(8):
            crc = (crc >> 1) ^ 0xA001 if crc & 1 else crc >> 1
    return bytes([crc & 0xFF, crc >> 8])


def rtu(*body: int) -> bytes:
    data = bytes(body)
    return data + crc16_modbus(data)


def hexbytes(text: str) -> bytes:
    return bytes.fromhex(text)


@functools.lru_cache(maxsize=None)
def load_profile(name: str) -> Profile:
    """Profiles are parsed once per session (the tables are large; nothing mutates them)."""
    return _load_profile(name)


@functools.lru_cache(maxsize=None)
def _load_frames(family: str) -> tuple:
    with open(VECTOR_DIR / f'{family}_frames.yaml', encoding='utf-8') as stream:
        return tuple(yaml.safe_load(stream)['frames'])


def load_frames(family: str) -> list[dict[str, Any]]:
    return list(_load_frames(family))


def frame_map(family: str) -> dict[str, dict[str, Any]]:
    return {frame['id']: frame for frame in load_frames(family)}


def on_wire(frame: dict[str, Any]) -> bytes:
    """Return the bytes a correct device sends: the printed ones, or the corrected ones."""
    if frame.get('crc_ok') is False:
        return hexbytes(frame['corrected'])
    return hexbytes(frame['bytes'])


def all_frames(kind: str | None = None, direction: str | None = None) -> list[Any]:
    params = []
    for family, (_, transport) in FAMILIES.items():
        if kind is not None and transport != kind:
            continue
        for frame in load_frames(family):
            if direction is not None and frame['direction'] != direction:
                continue
            params.append(pytest.param(family, frame, id=f'{family}-{frame["id"]}'))
    return params


AM = frame_map('boneng_am')


# --- RTU framing on the test side ---------------------------------------------------------

def rtu_length(buffer: bytes, request: bool) -> int | None:
    """Total length of the RTU frame at the start of ``buffer`` (None: need more bytes)."""
    if len(buffer) < 2:
        return None
    function = buffer[1]
    if request:
        if function in (3, 6, 8):
            return 8
        if function == 16:
            return 9 + buffer[6] if len(buffer) >= 7 else None
    else:
        if function & 0x80:
            return 5
        if function == 3:
            return 5 + buffer[2] if len(buffer) >= 3 else None
        if function in (6, 8, 16):
            return 8
    return len(buffer)      # unknown function code: take what arrived


def read_rtu_frame(fd: int, request: bool, timeout: float = DEADLINE) -> bytes:
    """Read exactly one RTU frame from ``fd``; fail after ``timeout``."""
    deadline = time.monotonic() + timeout
    buffer = b''
    while True:
        need = rtu_length(buffer, request)
        if need is not None and len(buffer) >= need:
            return buffer
        remaining = deadline - time.monotonic()
        if remaining <= 0:
            raise AssertionError(f'no complete frame within {timeout} s, got {buffer.hex(" ")!r}')
        ready, _, _ = select.select([fd], [], [], remaining)
        if ready:
            chunk = os.read(fd, (need - len(buffer)) if need else 1)
            if not chunk:
                raise AssertionError(f'line closed after {buffer.hex(" ")!r}')
            buffer += chunk


def nothing_pending(fd: int) -> bool:
    ready, _, _ = select.select([fd], [], [], 0)
    return not ready


# --- scripted slaves ------------------------------------------------------------------------

class ScriptedSlave:
    """Reads each request (deadline-bound) and answers the next scripted reply."""

    def __init__(self) -> None:
        self.requests: list[bytes] = []
        self._error: BaseException | None = None
        self._thread: threading.Thread | None = None

    def _read_request(self) -> bytes:
        raise NotImplementedError

    def _write(self, data: bytes) -> None:
        raise NotImplementedError

    def _pending(self) -> bool:
        raise NotImplementedError

    def serve(self, replies: list[bytes | None]) -> None:
        self.requests = []
        self._error = None

        def run() -> None:
            try:
                for reply in replies:
                    self.requests.append(self._read_request())
                    if reply is not None:
                        self._write(reply)
            except BaseException as exc:    # handed to the test thread in finish()
                self._error = exc

        self._thread = threading.Thread(target=run, daemon=True)
        self._thread.start()

    def finish(self) -> list[bytes]:
        assert self._thread is not None
        self._thread.join(DEADLINE + 1.0)
        assert not self._thread.is_alive(), 'scripted slave still waiting for a request'
        if self._error is not None:
            raise self._error
        assert not self._pending(), 'the driver sent bytes beyond the expected frames'
        return self.requests

    def exchange(self, replies: list[bytes | None], call: Callable[[], Any]) -> tuple[
            list[bytes], Any]:
        """Run ``call`` against the scripted replies: (request bytes, result or exception)."""
        self.serve(replies)
        try:
            outcome = call()
        except Exception as exc:    # the test asserts on the exception itself
            outcome = exc
        return self.finish(), outcome


class RtuSlave(ScriptedSlave):
    def __init__(self, master_fd: int) -> None:
        super().__init__()
        self.fd = master_fd

    def _read_request(self) -> bytes:
        return read_rtu_frame(self.fd, request=True)

    def _write(self, data: bytes) -> None:
        os.write(self.fd, data)

    def _pending(self) -> bool:
        return not nothing_pending(self.fd)


class TcpSlave(ScriptedSlave):
    """A one-connection Modbus TCP server on 127.0.0.1 (MBAP framing)."""

    def __init__(self) -> None:
        super().__init__()
        self.listener = socket.create_server(('127.0.0.1', 0))
        self.port = self.listener.getsockname()[1]
        self.conn: socket.socket | None = None

    def _recv_exactly(self, count: int, deadline: float) -> bytes:
        assert self.conn is not None
        data = b''
        while len(data) < count:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                raise AssertionError(f'no complete MBAP frame, got {data.hex(" ")!r}')
            ready, _, _ = select.select([self.conn], [], [], remaining)
            if ready:
                chunk = self.conn.recv(count - len(data))
                if not chunk:
                    raise AssertionError(f'connection closed after {data.hex(" ")!r}')
                data += chunk
        return data

    def _read_request(self) -> bytes:
        deadline = time.monotonic() + DEADLINE
        if self.conn is None:
            ready, _, _ = select.select([self.listener], [], [], DEADLINE)
            assert ready, 'the driver did not connect'
            self.conn, _ = self.listener.accept()
        header = self._recv_exactly(6, deadline)
        length = int.from_bytes(header[4:6], 'big')
        return header + self._recv_exactly(length, deadline)

    def _write(self, data: bytes) -> None:
        assert self.conn is not None
        self.conn.sendall(data)

    def _pending(self) -> bool:
        if self.conn is None:
            return False
        ready, _, _ = select.select([self.conn], [], [], 0)
        return bool(ready) and self.conn.recv(1, socket.MSG_PEEK) != b''

    def close(self) -> None:
        if self.conn is not None:
            self.conn.close()
        self.listener.close()


def raw_pty() -> tuple[int, int]:
    master, slave = os.openpty()
    tty.setraw(master)
    tty.setraw(slave)
    return master, slave


@dataclass
class Link:
    profile: Profile
    transport: Any
    slave: ScriptedSlave


def open_link(profile_name: str, kind: str):
    """Yield a transport for ``profile_name`` wired to a scripted slave."""
    profile = load_profile(profile_name)
    if kind == 'tcp':
        tcp_slave = TcpSlave()
        transport = ModbusTcpTransport('127.0.0.1', tcp_slave.port, timeout=REPLY_TIMEOUT)
        try:
            yield Link(profile, transport, tcp_slave)
        finally:
            transport.close()
            tcp_slave.close()
        return
    master, slave_fd = raw_pty()
    serial = profile.modbus.serial
    transport = ModbusRtuTransport(os.ttyname(slave_fd), baudrate=serial.baudrate,
                                   parity=serial.parity, stopbits=serial.stopbits,
                                   bytesize=serial.bytesize, timeout=REPLY_TIMEOUT)
    try:
        yield Link(profile, transport, RtuSlave(master))
    finally:
        transport.close()
        os.close(slave_fd)
        os.close(master)


@pytest.fixture
def link_for():
    """Make links by family name; all are closed at teardown."""
    opened = []

    def make(family: str) -> Link:
        profile_name, kind = FAMILIES[family]
        generator = open_link(profile_name, kind)
        opened.append(generator)
        return next(generator)

    yield make
    for generator in opened:
        generator.close()


@pytest.fixture
def am(link_for) -> tuple[Link, ModbusDrive]:
    """Build the boneng_am driver: transport + ModbusDrive, 100 % = 1000 rpm, gear 1."""
    link = link_for('boneng_am')
    scaling = VelocityScaling(gear_ratio=1.0, rated_speed_rpm=1000.0)
    return link, ModbusDrive(link.profile, link.transport, 1, scaling)


# --- requests and replies -----------------------------------------------------------------

def perform(transport: Any, request: dict[str, Any]) -> Callable[[], Any]:
    unit, function, address = request['unit'], request['function'], request['address']
    if function == 3:
        return lambda: transport.read_registers(unit, address, request['count'])
    if function == 6:
        return lambda: transport.write_register(unit, address, request['value'])
    if function == 16:
        return lambda: transport.write_registers(unit, address, list(request['values']))
    raise AssertionError(f'no driver call for function {function}')


def check_outcome(profile: Profile, request: dict[str, Any], response: dict[str, Any],
                  outcome: Any) -> None:
    """Check the driver's decoding of a correct reply ``response`` to ``request``."""
    if 'exception' in response:
        assert isinstance(outcome, ProtocolException), f'expected an exception, got {outcome!r}'
        assert outcome.code == response['exception']
        # The drive layer names it with the drive's own manual (some differ from the spec).
        drive = ModbusDrive(profile, None, 1, VelocityScaling())
        assert drive.explain(outcome).text == profile.modbus.exception_codes[outcome.code]
        return
    if response['function'] == 3 and len(response['values']) != request['count']:
        # e.g. IMO F1/F2: the printed request asks for 4 words, the reply carries 2.
        assert isinstance(outcome, BadFrame), f'expected BadFrame, got {outcome!r}'
        return
    assert not isinstance(outcome, Exception), f'driver raised {outcome!r}'
    if response['function'] == 3:
        assert outcome == list(response['values'])
    else:
        assert outcome is None


def normal_reply_to(frames: list[dict[str, Any]], request_frame: dict[str, Any]) -> bytes:
    """Return the printed normal reply to a request, else what the protocol makes of it."""
    for frame in frames:
        if frame.get('reply_to') == request_frame['id'] and \
                'exception' not in frame['response']:
            return on_wire(frame)
    request = request_frame['request']
    wire = on_wire(request_frame)
    if request['function'] == 6:
        return wire                       # a 06H reply is the echo of the request
    if request['function'] == 3:          # nothing printed: zeros complete the exchange
        return rtu(request['unit'], 3, 2 * request['count'], *([0] * 2 * request['count']))
    return rtu(*wire[:6])                 # 10H: unit, function, address, count


def request_for(frames: dict[str, dict[str, Any]], response_frame: dict[str, Any]) -> dict:
    """Return the request a response answers (its reply_to, or built from the response)."""
    if response_frame.get('reply_to'):
        return frames[response_frame['reply_to']]['request']
    response = response_frame['response']
    request = {'unit': response['unit'], 'function': response['function'],
               'address': response['address']}
    if response['function'] == 16:
        request['values'] = [0] * response['count']
    elif response['function'] == 6:
        request['value'] = response['value']
    return request


def skip_unless_register_function(function: int) -> None:
    if function == 8:
        pytest.skip('function 08H (diagnostics loop-back): the driver never sends it; '
                    'the frame is checked by its CRC in test_vector_file_is_consistent')
    if function not in (3, 6, 16):
        pytest.skip(f'function {function:#04x} is not one the driver uses (03H/06H/10H)')


# --- 1. the vector files themselves ---------------------------------------------------------

@pytest.mark.parametrize('family,frame', all_frames())
def test_vector_file_is_consistent(family, frame):
    """crc_ok tells the truth, corrections only fix the CRC, templates keep their prefix."""
    printed = hexbytes(frame['bytes'])
    if FAMILIES[family][1] == 'tcp':
        # MBAP: protocol id 0, length = bytes after the length field, unit = PDU's unit.
        assert printed[2:4] == b'\x00\x00'
        assert int.from_bytes(printed[4:6], 'big') == len(printed) - 6
        body = frame.get('request') or frame.get('response')
        assert printed[6] == body['unit'] and printed[7] == body['function']
        return
    assert (crc16_modbus(printed[:-2]) == printed[-2:]) is frame['crc_ok']
    if not frame['crc_ok']:
        corrected = hexbytes(frame['corrected'])
        assert corrected[:-2] == printed[:-2]
        assert crc16_modbus(corrected[:-2]) == corrected[-2:]
    body = frame.get('request') or frame.get('response')
    assert printed[0] == body['unit']
    assert printed[1] == body['function'] | (0x80 if 'exception' in body else 0)
    if 'exception' in body:
        assert printed[2] == body['exception'] and len(printed) == 5
    if frame.get('printed') == 'template':
        assert printed.startswith(hexbytes(frame['printed_prefix']))


def test_am_vector_file_has_every_printed_frame():
    """F1-F26 of the extraction, with the one bad CRC (F3) corrected."""
    assert list(AM) == [f'F{n}' for n in range(1, 27)]
    assert [f['id'] for f in AM.values() if not f['crc_ok']] == ['F3']
    assert hexbytes(AM['F3']['corrected']) == hexbytes('01 83 02 C0 F1')
    assert {f['id'] for f in AM.values() if f.get('printed') == 'template'} == \
        {'F2', 'F7', 'F26'}


# --- 2. the driver: printed requests, printed replies (every RTU/TCP family) ---------------

@pytest.mark.parametrize('family,frame', all_frames(direction='request'))
def test_driver_sends_printed_request(link_for, family, frame):
    request = frame['request']
    skip_unless_register_function(request['function'])
    link = link_for(family)
    frames = load_frames(family)
    sent, outcome = link.slave.exchange([normal_reply_to(frames, frame)],
                                        perform(link.transport, request))
    assert [b.hex(' ') for b in sent] == [on_wire(frame).hex(' ')]
    if frame.get('printed') == 'template':
        assert sent[0].startswith(hexbytes(frame['printed_prefix']))
    printed_reply = next((f for f in frames if f.get('reply_to') == frame['id'] and
                          'exception' not in f['response']), None)
    if printed_reply is not None:
        check_outcome(link.profile, request, printed_reply['response'], outcome)
    else:
        assert not isinstance(outcome, Exception), repr(outcome)


@pytest.mark.parametrize('family,frame', all_frames(direction='response'))
def test_driver_decodes_printed_reply(link_for, family, frame):
    skip_unless_register_function(frame['response']['function'])
    link = link_for(family)
    frames = frame_map(family)
    request = request_for(frames, frame)
    _, outcome = link.slave.exchange([on_wire(frame)], perform(link.transport, request))
    check_outcome(link.profile, request, frame['response'], outcome)


@pytest.mark.parametrize('family,frame', [
    p for p in all_frames('rtu') if p.values[1].get('crc_ok') is False])
def test_driver_rejects_printed_bad_crc(link_for, family, frame):
    """A reply with the manual's wrong CRC is a bad frame, never data or an exception."""
    link = link_for(family)
    request = request_for(frame_map(family), frame)
    _, outcome = link.slave.exchange([hexbytes(frame['bytes'])],
                                     perform(link.transport, request))
    assert isinstance(outcome, BadFrame), repr(outcome)
    assert link.transport.stats.bad_frames == 1


def test_imo_corrected_read_decodes_reply(link_for):
    """IMO F1 prints quantity 0004 but F2 carries 2 words; the 2-word read matches F2."""
    link = link_for('imo_hd2')
    frames = frame_map('imo_hd2')
    sent, outcome = link.slave.exchange([hexbytes(frames['F2']['bytes'])],
                                        lambda: link.transport.read_registers(1, 0x0004, 2))
    assert sent == [hexbytes('00 01 00 00 00 06 01 03 00 04 00 02')]
    assert outcome == [5000, 0]


# --- 3. the AM driver's own verbs put the printed frames on the wire --------------------

def velocity_for_percent(percent: float) -> float:
    """Output rad/s for a P07.33 percentage with gear 1 and 100 % = 1000 rpm."""
    return percent / 100.0 * 1000.0 / RPM_PER_RAD_S


def signed(word: int) -> int:
    return word - 0x10000 if word & 0x8000 else word


def verb_frames() -> list[Any]:
    """Every printed request a drive verb makes, annotated with the verb from its meaning."""
    return [pytest.param(family, frame, id=f'{family}-{frame["id"]}')
            for family in FAMILIES for frame in load_frames(family) if 'verb' in frame]


@pytest.mark.parametrize('family,frame', verb_frames())
def test_drive_verbs_put_the_printed_frames_on_the_wire(link_for, family, frame):
    """The manual's meaning, asked of the driver through the profile, gives its bytes.

    A wrong command value, setpoint scale or register in a profile fails here:
    the expected bytes are the manual's, the call is the verb the manual names.
    """
    link = link_for(family)
    unit = frame['request']['unit']
    drive = ModbusDrive(link.profile, link.transport, unit,
                        VelocityScaling(gear_ratio=1.0, rated_speed_rpm=1000.0))
    verb = frame['verb']
    if 'command' in verb:
        call = functools.partial(drive.send_command, verb['command'])
    else:
        call = functools.partial(drive.write_setpoint,
                                 velocity_for_percent(verb['setpoint_percent']))
    wire = on_wire(frame)
    sent, outcome = link.slave.exchange([wire], call)      # a 06 write is answered by its echo
    assert [b.hex(' ') for b in sent] == [wire.hex(' ')]
    assert not isinstance(outcome, Exception), repr(outcome)


def test_every_family_with_printed_commands_is_checked_through_its_verbs():
    families = {family for family, _ in (p.values for p in verb_frames())}
    assert families == {'boneng_am', 'boneng_mh', 'kinco_ec'}
    # Veichi prints only a write to the alias 3000H (the driver writes 2000H) and IMO
    # only parameter writes: their command words are checked by the families suite.


def test_am_other_command_value_frame(am):
    """F14: the "other" row of the P07.32 table has no verb; the register write itself."""
    link, drive = am
    wire = on_wire(AM['F14'])
    sent, outcome = link.slave.exchange([wire], lambda: drive.write_raw(
        drive.profile.parameter('P07.32'), 6))
    assert sent == [wire] and outcome is None


def test_am_apply_start_and_stop_sequence(am):
    """apply(): setpoint, the rising edge from 0 (F16), run (F15); then stop and 0 %.

    Idle, the stop command goes first: a drive whose replies are lost still hears it.
    """
    link, drive = am
    start = [on_wire(AM[i]) for i in ('F20', 'F16', 'F15')]
    sent, outcome = link.slave.exchange(start, lambda: drive.apply(velocity_for_percent(100.0),
                                                                   run=True))
    assert sent == start and outcome is None
    again = [on_wire(AM['F20'])]       # running: only the setpoint is refreshed
    sent, outcome = link.slave.exchange(again, lambda: drive.apply(velocity_for_percent(100.0),
                                                                   run=True))
    assert sent == again and outcome is None
    stop = [on_wire(AM[i]) for i in ('F12', 'F22')]
    sent, outcome = link.slave.exchange(stop, lambda: drive.apply(0.0, run=False))
    assert sent == stop and outcome is None


def test_am_get_parameter_speed_read(am):
    """F25 through get_parameter('A00.03'); F26 as completed, and with XX XX = 13 88."""
    link, drive = am
    sent, outcome = link.slave.exchange([on_wire(AM['F26'])],
                                        lambda: drive.get_parameter('A00.03'))
    assert sent == [on_wire(AM['F25'])]
    assert outcome.raw == 0 and outcome.value == 0.0
    sent, outcome = link.slave.exchange([rtu(1, 3, 2, 0x13, 0x88)],
                                        lambda: drive.get_parameter('A00.03'))
    assert sent == [on_wire(AM['F25'])]
    assert math.isclose(outcome.value, 50.0)


def test_am_read_block_F1_F2(am):
    link, _ = am
    sent, outcome = link.slave.exchange([on_wire(AM['F2'])],
                                        lambda: link.transport.read_registers(1, 0x2004, 3))
    assert sent == [on_wire(AM['F1'])]
    assert outcome == [1500, 0, 0]


@pytest.mark.parametrize('frame_id,call,words', [
    ('F3', lambda drive: drive.get_parameter('A00.04'), ('illegal address',)),
    ('F6', lambda drive: drive.write_setpoint(velocity_for_percent(100.0)),
     ('illegal data value',)),
    ('F9', lambda drive: drive.transport.write_registers(1, 0x3500, [1, 0, 0]),
     ('illegal data value',)),
])
def test_am_exception_frames_carry_the_manuals_meaning(am, frame_id, call, words):
    """F3 (corrected) code 2, F6 code 3, F9 code 3, with the AM's own texts (L3881ff)."""
    link, drive = am
    frame = AM[frame_id]
    _, outcome = link.slave.exchange([on_wire(frame)], lambda: call(drive))
    assert isinstance(outcome, ProtocolException), repr(outcome)
    assert outcome.code == frame['response']['exception']
    for word in words:
        assert word in outcome.text.lower()
    assert link.transport.stats.exceptions == 1


# --- 4. the simulated twin answers as printed ----------------------------------------------

@pytest.fixture
def twin(tmp_path):
    """Run a SimulatedDrive(boneng_am) on a SimulatedRtuLine; the test holds the pty end."""
    profile = load_profile('boneng_am')
    sim = SimulatedDrive(profile, 1)
    line = SimulatedRtuLine([sim], tmp_path / 'line').start()
    fd = os.open(tmp_path / 'line', os.O_RDWR | os.O_NOCTTY)
    tty.setraw(fd)
    try:
        yield sim, fd
    finally:
        os.close(fd)
        line.stop()


def ask_twin(fd: int, request: bytes) -> bytes:
    os.write(fd, request)
    reply = read_rtu_frame(fd, request=False)
    assert nothing_pending(fd), 'the twin sent more than one frame'
    return reply


def test_twin_read_F1_answers_F2(twin):
    sim, fd = twin
    with sim.lock:          # A00.04 target speed 1500 rpm, as in the manual's example
        sim.words[0x2004] = 1500
    assert ask_twin(fd, on_wire(AM['F1'])).hex(' ') == AM['F2']['bytes'].lower()


def test_twin_speed_read_F25_answers_F26(twin):
    _, fd = twin
    assert ask_twin(fd, on_wire(AM['F25'])).hex(' ') == AM['F26']['bytes'].lower()


@pytest.mark.parametrize('frame_id', [i for i, f in AM.items()
                                      if f['direction'] == 'request' and
                                      f['request']['function'] == 6])
def test_twin_echoes_printed_writes(twin, frame_id):
    """06H: the reply is the echo (F5 for F4); the twin's register holds the value."""
    sim, fd = twin
    frame = AM[frame_id]
    wire = on_wire(frame)
    expected = on_wire(AM['F5']) if frame_id == 'F4' else wire
    assert ask_twin(fd, wire) == expected
    request = frame['request']
    with sim.lock:
        assert sim.words[request['address']] == request['value']
    if request['address'] == 0xE720:
        assert sim.last_command_value == request['value']


def test_twin_undocumented_read_gives_corrected_F3(twin):
    """A00.12 (0x200C) is not in the table: exception 2 with the correct CRC."""
    _, fd = twin
    reply = ask_twin(fd, rtu(1, 3, 0x20, 0x0C, 0, 1))
    assert reply == on_wire(AM['F3'])
    assert reply != hexbytes(AM['F3']['bytes'])


def test_twin_illegal_value_write_gives_F6(twin):
    """B05.00 control mode accepts 0/1 only: 06H with 5 -> exception 3, value kept."""
    sim, fd = twin
    before = sim.value('B05.00')
    assert ask_twin(fd, rtu(1, 6, 0x35, 0x00, 0, 5)) == on_wire(AM['F6'])
    assert sim.value('B05.00') == before


def test_twin_illegal_value_multiple_write_gives_F9(twin):
    """10H at 0x3500 with B05.00 = 5 -> exception 3 (F9), nothing written."""
    sim, fd = twin
    before = sim.value('B05.00')
    request = rtu(1, 0x10, 0x35, 0x00, 0, 3, 6, 0, 5, 0, 0, 0, 0)
    assert ask_twin(fd, request) == on_wire(AM['F9'])
    assert sim.value('B05.00') == before


@pytest.mark.xfail(strict=True, reason=(
    'The manual answers its 10H example (3 words from 0x3500) with 01 10 35 00 00 03 8F C4 '
    '(F8), but 0x3501 is not in the parameter table (there is no B05.01), so the twin '
    '(SimulatedDrive.write: parameter_at(0x3501) is None) answers exception 2 '
    '(01 90 02 CD C1) instead.'))
def test_twin_multiple_write_F7_answers_F8(twin):
    _, fd = twin
    assert ask_twin(fd, on_wire(AM['F7'])) == on_wire(AM['F8'])
