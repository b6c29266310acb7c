"""CAN across processes: the socketcand-protocol server and ``transport.can_options``.

The server is checked against python-can's own socketcand client (real frames
both ways over loopback TCP) and against a raw socket speaking the protocol's
text; the end-to-end test drives simulated CiA 402 drives that run in another
process, through the server, with the transport's ``can_options``.
"""

from __future__ import annotations

import json
import logging
import socket
import time
import uuid

import can
import pytest

from harness import wait_for
from vfd_ros2.errors import ParameterError
from vfd_ros2.sim.canopen_process import CanopenSimProcess
from vfd_ros2.sim.socketcand_server import SocketcandServer, format_frame, parse_send
from vfd_ros2.transports.canopen import (
    _RECONNECTS,
    CanChannel,
    CanopenTransport,
    _ThrottleMessage,
    parse_can_options,
)

# --- transport.can_options (no I/O) ---------------------------------------------------------


def test_can_options_parse_json_objects_and_mappings():
    assert parse_can_options('') == {}
    assert parse_can_options(None) == {}
    assert parse_can_options('{"host": "127.0.0.1", "port": 29536, "tcp_tune": true}') == {
        'host': '127.0.0.1', 'port': 29536, 'tcp_tune': True}
    assert parse_can_options({'receive_own_messages': False}) == {
        'receive_own_messages': False}           # a bus file may give a YAML mapping


@pytest.mark.parametrize('text, why', [
    ('{"host": ', 'not valid JSON'),
    ('["host", "port"]', 'must be a JSON object'),
    ('29536', 'must be a JSON object'),
    ('{"channel": "can1"}', 'transport.channel'),
    ('{"bitrate": 500000}', 'transport.bitrate'),
    ('{"not a name": 1}', 'not a keyword argument name'),
])
def test_bad_can_options_are_refused_at_start_up(text, why):
    with pytest.raises(ParameterError, match=why):
        CanopenTransport.from_settings({'interface': 'socketcand', 'channel': 'can0',
                                        'can_options': text})


def test_can_options_reach_the_bus_and_are_part_of_the_channel_key():
    made = []

    def factory(**kwargs):
        made.append(kwargs)
        return can.Bus(interface='virtual', channel=kwargs['channel'])
    name = f'opts{uuid.uuid4().hex[:8]}'
    first = CanChannel.acquire('virtual', name, 0, factory, {'rx_queue_size': 0})
    same = CanChannel.acquire('virtual', name, 0, factory, {'rx_queue_size': 0})
    other = CanChannel.acquire('virtual', name, 0, factory, {'rx_queue_size': 100})
    try:
        assert same is first and other is not first
        assert made == [{'interface': 'virtual', 'channel': name, 'rx_queue_size': 0},
                        {'interface': 'virtual', 'channel': name, 'rx_queue_size': 100}]
    finally:
        for channel in (first, same, other):
            channel.release()


def test_an_option_the_interface_does_not_take_is_a_parameter_error():
    # socketcand without host and port: refused when the transport is made (it used to be
    # python-can's TypeError at every connect attempt, the node up and retrying)
    with pytest.raises(ParameterError, match='transport.can_options: host, port missing'):
        CanopenTransport(interface='socketcand', channel='can0',
                         can_options='{"tcp_tune": true}')


# --- the protocol's text ------------------------------------------------------------------


def test_send_commands_parse_as_socketcand_reads_them():
    msg = parse_send(['1AAAAAAA', '2', '1', 'F1'])
    assert (msg.arbitration_id, msg.is_extended_id, bytes(msg.data)) == (
        0x1AAAAAAA, True, b'\x01\xf1')
    msg = parse_send(['123', '0'])
    assert (msg.arbitration_id, msg.is_extended_id, msg.dlc) == (0x123, False, 0)
    for bad in (['123'], ['123', '2', '1'], ['800', '0'], ['12G', '0'], ['123', '9'] + ['0'] * 9,
                ['123', '1', '100']):
        with pytest.raises(ValueError):
            parse_send(bad)


def test_frames_are_written_as_socketcand_writes_them():
    msg = can.Message(arbitration_id=0x201, data=b'\x0f\x00\xe8\x03', is_extended_id=False,
                      timestamp=23.4242421)
    assert format_frame(msg) == '< frame 201 23.424242 0F00E803 >'
    msg = can.Message(arbitration_id=0x1AAAAAAA, data=b'', timestamp=1.9999999)
    assert format_frame(msg) == '< frame 1AAAAAAA 2.000000  >'


# --- the server, against python-can's client --------------------------------------------------


@pytest.fixture
def server():
    channel = f'sc{uuid.uuid4().hex[:8]}'
    with SocketcandServer({'can0': channel}) as running:
        local = can.Bus(interface='virtual', channel=channel)   # the simulator's side
        try:
            yield running, local
        finally:
            local.shutdown()


def client(port: int) -> can.BusABC:
    return can.Bus(interface='socketcand', channel='can0', host='127.0.0.1', port=port,
                   tcp_tune=True)


def receive(bus: can.BusABC, timeout: float = 2.0) -> can.Message:
    msg = bus.recv(timeout)
    assert msg is not None, 'no frame'
    return msg


def test_frames_cross_both_ways_and_between_clients_never_echoed(server):
    srv, local = server
    a, b = client(srv.port), client(srv.port)
    try:
        a.send(can.Message(arbitration_id=0x601, data=b'\x40\x41\x60\x00\0\0\0\0',
                           is_extended_id=False))
        got = receive(local)
        assert (got.arbitration_id, bytes(got.data)) == (0x601, b'\x40\x41\x60\x00\0\0\0\0')
        got = receive(b)
        assert (got.arbitration_id, got.is_extended_id, bytes(got.data)) == (
            0x601, False, b'\x40\x41\x60\x00\0\0\0\0')
        local.send(can.Message(arbitration_id=0x1ABCDEF0, data=b'\xff', is_extended_id=True))
        for bus in (a, b):
            got = receive(bus)
            assert (got.arbitration_id, got.is_extended_id, bytes(got.data)) == (
                0x1ABCDEF0, True, b'\xff')
        assert a.recv(0.2) is None             # its own frame never came back
        assert srv.frames_in == 1
    finally:
        a.shutdown()
        b.shutdown()


def raw_session(port: int) -> socket.socket:
    sock = socket.create_connection(('127.0.0.1', port), timeout=2.0)
    assert sock.recv(64) == b'< hi >'
    return sock


def read_until(sock: socket.socket, expected: bytes) -> bytes:
    data = b''
    deadline = time.monotonic() + 2.0
    while expected not in data:
        assert time.monotonic() < deadline, f'{expected!r} not in {data!r}'
        data += sock.recv(4096)
    return data


def test_malformed_and_unknown_commands_get_an_error_and_the_session_goes_on(server):
    srv, local = server
    sock = raw_session(srv.port)
    listener = client(srv.port)
    try:
        sock.sendall(b'< foo >')
        assert read_until(sock, b'>') == b'< error unknown command >'
        sock.sendall(b'garbage < open can0 >')
        assert read_until(sock, b'>') == b'< ok >'
        for bad in (b'< send 123 9 >', b'< send xyz 1 00 >', b'< send 123 2 01 >',
                    b'< subscribe 0 0 123 >', b'< \xff\xfe >', b'<>'):
            sock.sendall(bad)
            assert read_until(sock, b'>').startswith(b'< error '), bad
        sock.sendall(b'< echo >')
        assert read_until(sock, b'>') == b'< echo >'
        sock.sendall(b'< rawmode >')
        assert read_until(sock, b'>') == b'< ok >'
        sock.sendall(b'< send 7FF 2 a 0B >')
        got = receive(local)
        assert (got.arbitration_id, bytes(got.data)) == (0x7FF, b'\x0a\x0b')
        assert receive(listener).arbitration_id == 0x7FF
        local.send(can.Message(arbitration_id=0x181, data=b'\x37\x06', is_extended_id=False))
        assert b'< frame 181 ' in read_until(sock, b' 3706 >')
        assert srv.errors_sent == 7
    finally:
        sock.close()
        listener.shutdown()


def test_a_client_that_disconnects_is_dropped_and_the_others_go_on(server):
    srv, local = server
    gone, stays = client(srv.port), client(srv.port)
    try:
        wait_for(lambda: srv.clients == 2, 2.0, 'two clients')
        gone.shutdown()
        wait_for(lambda: srv.clients == 1, 2.0, 'the closed client dropped')
        local.send(can.Message(arbitration_id=0x701, data=b'\x05', is_extended_id=False))
        assert receive(stays).arbitration_id == 0x701
        unknown = raw_session(srv.port)      # a bus it does not serve: error, then hang-up
        unknown.sendall(b'< open can9 >')
        assert read_until(unknown, b'>') == b'< error could not open bus >'
        assert unknown.recv(64) == b''
        unknown.close()
        wait_for(lambda: srv.clients == 1, 2.0, 'the refused client dropped')
    finally:
        stays.shutdown()


# --- end to end: drives in another process ------------------------------------------------------


def test_a_drive_goes_online_and_runs_against_drives_in_another_process():
    """A controller (no ROS) on ``socketcand`` + ``can_options``; the sims are a process away."""
    from vfd_ros2.control.factory import build_controller

    with CanopenSimProcess(nodes=[1, 2], record=True) as sim:
        controller = build_controller({
            'drive.profile': 'cia402_velocity', 'transport.type': 'canopen',
            'transport.interface': 'socketcand', 'transport.channel': sim.bus,
            'transport.can_options': json.dumps(sim.can_options), 'transport.unit_id': 2,
            'auto_enable': True, 'control_rate': 50.0, 'gear_ratio': 10.0,
            'command_timeout': 0.5})
        controller.start()
        try:
            def running() -> bool:
                controller.command_velocity(2.0)
                return controller.state.online and controller.state.state == 'running'
            wait_for(running, 10.0, 'the drive online and running')
            status = wait_for(lambda: (s := sim.status())['drives']['2']['target_raw'] and s,
                              5.0, 'the velocity at the simulated drive')
            assert status['drives']['2']['state'] == 'OPERATION_ENABLED'
            assert status['drives']['1']['rpdos'] == 0       # only node 2 is driven
            assert status['clients'] == 1
            # the client's warning for every partial TCP read is filtered, no other
            client_log = logging.getLogger('can.interfaces.socketcand.socketcand')

            def passes(text: str) -> bool:
                return bool(client_log.filter(logging.LogRecord(
                    client_log.name, logging.WARNING, __file__, 0, text, None, None)))
            assert not passes('Got incomplete message => waiting for more data')
            assert passes('Invalid Frame: < frame 123 >')
            # the reconnect warnings: one a second (test_reconnect_warnings_...)
            assert _RECONNECTS in client_log.filters
        finally:
            controller.shutdown()
        frames = sim.stop()
    cobs = {frame.cob_id for frame in frames}
    # what crossed the bridge, seen in the simulator's process: SDO both ways, the RPDO,
    # SYNC, the TPDO and the heartbeats of node 2 and of the host (node 127)
    assert {0x602, 0x582, 0x202, 0x080, 0x182, 0x702, 0x77F} <= cobs, sorted(map(hex, cobs))


def test_reconnect_warnings_pass_once_a_second_with_the_count():
    # python-can's client retries a vanished daemon in a tight loop for 10 s, one
    # warning each: 184,351 lines in 3 s (outside re-check).
    throttle = _ThrottleMessage('Failed to connect to server', 1.0)

    def record(text: str) -> logging.LogRecord:
        return logging.LogRecord('can', logging.WARNING, __file__, 0, text, None, None)
    first = record('Failed to connect to server: refused')
    assert throttle.filter(first) and first.msg == 'Failed to connect to server: refused'
    assert not any(throttle.filter(record('Failed to connect to server: refused'))
                   for _ in range(1000))
    assert throttle.filter(record('Invalid Frame: < frame 123 >'))     # others pass
    throttle._passed_at -= 1.0                                    # noqa: SLF001 - a second on
    later = record('Failed to connect to server: refused')
    assert throttle.filter(later)
    assert later.msg.endswith('(1000 more like it in the last 1 s)')


def test_vfd_scan_and_vfd_params_take_the_can_options(tmp_path):
    """The tools reach drives a process away too, and the bus file keeps the options."""
    import io

    from vfd_ros2.apps import params, scan
    from vfd_ros2.control.bus import load_bus_config

    def run(tool, argv: list[str]) -> tuple[int, str]:
        out, err = io.StringIO(), io.StringIO()
        code = tool.run([str(a) for a in argv], stdout=out, stderr=err)
        return code, out.getvalue() + err.getvalue()

    with CanopenSimProcess(nodes=[1, 3]) as sim:
        options = json.dumps(sim.can_options)
        code, text = run(scan, ['--can', f'socketcand:{sim.bus}', '--can-options', options,
                                '--listen', '0.5', '--sdo-probe', '--ids', '1-4',
                                '--yaml', tmp_path / 'bus.yaml', '--quiet'])
        assert code == 0, text
        config = load_bus_config(str(tmp_path / 'bus.yaml'))
        assert sorted(d.settings['transport.unit_id'] for d in config.drives) == [1, 3]
        assert parse_can_options(config.settings['transport.can_options']) == sim.can_options
        code, text = run(params, ['dump', '--can', f'socketcand:{sim.bus}', '--can-options',
                                  options, '--unit', 3, '--profile', 'cia402_velocity',
                                  '-o', tmp_path / 'node3.yaml'])
        assert code == 0 and (tmp_path / 'node3.yaml').exists(), text
    # bad options: refused with the setting's own message, before any bus is opened
    code, text = run(scan, ['--can', 'socketcand:can0', '--can-options', '{"host": ',
                            '--quiet'])
    assert code == 2 and 'transport.can_options is not valid JSON' in text, text
    code, text = run(params, ['dump', '--can', 'socketcand:can0', '--can-options', '[1]',
                              '--profile', 'cia402_velocity', '-o', tmp_path / 'no.yaml'])
    assert code != 0 and 'must be a JSON object' in text, text
