"""vfd_scan against simulated drives on their real wire protocols, and its identification logic.

The RS-485 line carries four drives of three makers at two baud rates (the
simulated line keys each drive on the baud rate the master opened the pty with:
a drive at another rate does not hear the frame); Modbus TCP runs on loopback;
CANopen on python-can's virtual bus. No ROS.
"""

from __future__ import annotations

import io

import pytest

from unit_support import shipped_profile
from vfd_ros2.apps.scan import (
    FAILED,
    FOUND,
    NOTHING,
    ScanError,
    parse_ids,
    parse_tcp,
    run,
)
from vfd_ros2.control.bus import load_bus_config
from vfd_ros2.drives.identify import (
    Answer,
    Framing,
    candidate_framings,
    identify,
    reported_framing,
)
from vfd_ros2.profiles import available_profiles
from vfd_ros2.sim.model import SimException, SimulatedDrive
from vfd_ros2.sim.rtu_line import SimulatedRtuLine
from vfd_ros2.sim.tcp_server import SimulatedTcpServer

MODBUS = [name for name in available_profiles()
          if {'modbus_rtu', 'modbus_tcp'} & set(shipped_profile(name).transports)]

#: the line of the scan tests: unit id -> (family, baud rate)
LINE = {1: ('boneng_am', 115200), 2: ('boneng_mh', 115200), 3: ('kinco_ec', 115200),
        4: ('veichi_ehs100', 9600)}


def scan(argv: list[str]) -> tuple[int, str, str]:
    out, err = io.StringIO(), io.StringIO()
    code = run(argv, stdout=out, stderr=err)
    return code, out.getvalue(), err.getvalue()


def rows(table: str) -> dict[int, list[str]]:
    """Return unit id -> the cells of its row (split on runs of two spaces)."""
    found = {}
    for line in table.splitlines()[1:]:
        if line.startswith('not covered') or not line.strip():
            continue
        cells = [cell.strip() for cell in line.split('  ') if cell.strip()]
        found[int(cells[2])] = cells
    return found


@pytest.fixture
def mixed_line(tmp_path):
    sims = {unit: SimulatedDrive(shipped_profile(family), unit)
            for unit, (family, _) in LINE.items()}
    line = SimulatedRtuLine(list(sims.values()), tmp_path / 'rs485',
                            drive_baudrates={unit: baud for unit, (_, baud) in LINE.items()})
    line.start()
    yield line, sims
    line.stop()


# --- identification, no I/O ------------------------------------------------------------------

def reader_for(profile_name: str):
    """Return a read function answering like the simulated twin of a family."""
    sim = SimulatedDrive(shipped_profile(profile_name))

    def read(address: int, count: int) -> Answer:
        try:
            return Answer(registers=tuple(sim.read(address, count)))
        except SimException as exc:
            return Answer(exception=exc.code)
    return read


@pytest.mark.parametrize('family', MODBUS)
def test_every_modbus_family_identifies_itself_and_only_itself(family):
    profiles = [shipped_profile(name) for name in MODBUS]
    result = identify(profiles, reader_for(family))
    assert result.profile == family, result
    expected = shipped_profile(family).identify.modbus.confidence
    assert result.confidence == expected and result.alternatives == ()


def test_identification_code_is_high_confidence_and_shape_is_medium():
    assert shipped_profile('imo_hd2').identify.modbus.confidence == 'high'
    assert shipped_profile('boneng_am').identify.modbus.confidence == 'medium'


def test_an_am_that_answers_a02_01_is_ambiguous_with_the_mh():
    # A firmware that answers 0x2201 would fit the MH's checks, not the AM's: named, not guessed.
    profiles = [shipped_profile('boneng_am'), shipped_profile('boneng_mh')]
    sim = SimulatedDrive(shipped_profile('boneng_mh'))

    def read(address: int, count: int) -> Answer:
        return Answer(registers=tuple(sim.read(address, count)))
    result = identify(profiles, read)
    assert result.profile == 'boneng_mh' and result.confidence == 'medium'


def test_a_device_that_fits_no_family_is_unknown_with_its_answers():
    result = identify([shipped_profile(n) for n in MODBUS],
                      lambda address, count: Answer(exception=1))
    assert not result.known and result.confidence == 'none'
    assert 'exception 1' in result.evidence


def test_a_framing_the_manual_does_not_offer_lowers_the_confidence():
    profiles = [shipped_profile('veichi_ehs100')]
    documented = identify(profiles, reader_for('veichi_ehs100'), Framing(9600, 'N', 1))
    odd = identify(profiles, reader_for('veichi_ehs100'), Framing(115200, 'N', 1))
    assert documented.confidence == 'medium' and odd.confidence == 'low'
    assert any('115200 8N1' in note for note in odd.notes)


def test_candidate_framings_put_the_factory_settings_first():
    profiles = [shipped_profile(n) for n in MODBUS]
    framings = candidate_framings(profiles)
    factory = [f for f, is_factory in framings if is_factory]
    assert [f.key for f in factory] == [(115200, 'N', 8), (9600, 'N', 8)]
    assert not any(is_factory for _, is_factory in framings[len(factory):])
    keys = [f.key for f, _ in framings]
    assert len(keys) == len(set(keys))                      # one probe per baud/parity
    assert (1200, 'N', 8) in keys and (57600, 'E', 8) in keys
    # Sent with 2 stop bits where a family offers 2 there; reported with the drive's own.
    sent = next(f for f, _ in framings if f.key == (115200, 'N', 8))
    assert sent.stopbits == 2
    assert reported_framing(shipped_profile('boneng_am'), sent).label == '115200 8N1'
    assert reported_framing(shipped_profile('kinco_ec'), sent).label == '115200 8N2'


def test_id_and_target_parsing():
    assert parse_ids('1-3,7,2') == [1, 2, 3, 7]
    for bad in ('0-3', '5-2', 'x', '1-300'):
        with pytest.raises(ScanError):
            parse_ids(bad)
    targets = parse_tcp('10.0.0.5-7:502-503')
    assert [(t.host, t.port) for t in targets][:3] == [('10.0.0.5', 502), ('10.0.0.5', 503),
                                                        ('10.0.0.6', 502)]
    assert len(targets) == 6
    assert parse_tcp('drive.local')[0].port == 502
    with pytest.raises(ScanError):
        parse_tcp('10.0.0.9-1')


# --- Modbus RTU over the emulated line --------------------------------------------------------

def test_scan_finds_three_families_at_two_baud_rates_and_writes_a_bus_file(mixed_line,
                                                                           tmp_path):
    line, sims = mixed_line
    bus_file = tmp_path / 'bus.yaml'
    code, out, err = scan(['--port', str(line.link_path), '--ids', '1-6', '--silent-ids', '2',
                           '--response-time', '0.1', '--yaml', str(bus_file)])
    assert code == FOUND, out + err
    found = rows(out)
    assert set(found) == set(LINE), out
    for unit, (family, baud) in LINE.items():
        cells = found[unit]
        assert cells[3] == family and cells[4] == 'medium', cells
        assert cells[1].startswith(str(baud)), cells
    assert found[1][1] == '115200 8N1' and found[3][1] == '115200 8N2'
    assert found[4][1] == '9600 8N1'
    assert 'A02.00=' in found[1][5] and 'C-28=' in found[4][5]
    # Never a write: every request on the wire was a read (function 03).
    functions = {frame[1] for _, frame in line.received}
    assert functions == {3}, functions
    # The drives at one baud rate did not hear the master at the other.
    assert line.stats.wrong_baud > 0
    # Progress went to stderr, framing by framing; silent framings stopped early.
    assert 'a factory setting' in err and 'nothing on the line for 2 ids in a row' in err
    # The bus file is what bus_node accepts: the 115200 drives; the Veichi in a comment.
    config = load_bus_config(str(bus_file))
    assert config.settings['transport.baudrate'] == 115200
    assert config.settings['transport.stopbits'] == 2        # the Kinco needs 2, 1-stop reads 2
    assert {e.settings['drive.profile']: e.settings['transport.unit_id']
            for e in config.drives} == {'boneng_am': 1, 'boneng_mh': 2, 'kinco_ec': 3}
    text = bus_file.read_text()
    assert 'NOT on this bus' in text and 'veichi_ehs100 id 4' in text


def test_silent_framings_cost_only_the_silent_limit(mixed_line):
    line, _ = mixed_line
    code, out, _ = scan(['--port', str(line.link_path), '--ids', '1-10', '--silent-ids', '3',
                         '--baudrates', '38400,19200', '--response-time', '0.02'])
    assert code == NOTHING and 'nothing answered' in out
    # Every framing the profiles offer at these two rates, 3 ids each, then the next.
    framings = [f for f, _ in candidate_framings([shipped_profile(n) for n in MODBUS])
                if f.baudrate in (38400, 19200)]
    assert line.stats.frames == 3 * len(framings)


def test_the_budget_stops_the_scan_and_says_what_it_left_out(mixed_line):
    line, _ = mixed_line
    code, out, _ = scan(['--port', str(line.link_path), '--ids', '1-247', '--max-requests',
                         '12', '--response-time', '0.1'])
    assert code == FOUND                                     # ids 1-4 came first
    assert 'not covered' in out and 'request budget (12) used up' in out
    assert line.stats.frames <= 12 + 4 * 6     # the probes, plus the found units' own reads


def test_unknown_port_and_bad_arguments_are_clear_errors(tmp_path):
    for argv, message in (
            (['--port', str(tmp_path / 'ttyNONE')], 'no such serial port'),
            (['--port', str(tmp_path), '--ids', '0-9'], 'bad id range'),
            ([], 'name at least one link'),
            (['--tcp', '1.2.3.9-1'], 'bad TCP target'),
            (['--port', str(tmp_path), '--profiles', 'nope'], 'unknown drive profile')):
        code, out, err = scan(argv)
        assert code == FAILED and message in err, (argv, err)


def test_a_port_that_is_not_a_serial_device_is_a_clear_error(tmp_path):
    path = tmp_path / 'not_a_tty'
    path.write_text('')
    code, _, err = scan(['--port', str(path), '--ids', '1'])
    assert code == FAILED and 'cannot open the serial port' in err


# --- Modbus TCP -------------------------------------------------------------------------------

def test_tcp_scan_over_a_port_range(tmp_path):
    server = SimulatedTcpServer([SimulatedDrive(shipped_profile('imo_hd2'), 1)]).start()
    try:
        bus_file = tmp_path / 'tcp.yaml'
        code, out, err = scan(['--tcp', f'127.0.0.1:{server.port - 1}-{server.port + 1}',
                               '--ids', '1-5', '--silent-ids', '2', '--yaml', str(bus_file)])
    finally:
        server.stop()
    assert code == FOUND, err
    row = rows(out)[1]
    assert row[0] == f'127.0.0.1:{server.port}' and row[3] == 'imo_hd2' and row[4] == 'high'
    assert '0x2103=416 (HD2)' in row[5]
    config = load_bus_config(str(bus_file))
    assert config.settings['transport.port'] == server.port
    assert [e.settings['drive.profile'] for e in config.drives] == ['imo_hd2']


# --- CANopen ----------------------------------------------------------------------------------

def test_canopen_scan_hears_heartbeats_and_probes_the_silent_nodes(tmp_path):
    import uuid

    from canopen import objectdictionary as od

    from vfd_ros2.sim.canopen_drive import SimulatedCanBus, SimulatedCanopenDrive
    channel = f'scan{uuid.uuid4().hex[:8]}'
    generic = SimulatedCanopenDrive(shipped_profile('cia402_velocity'), 2)
    kinco = SimulatedCanopenDrive(shipped_profile('kinco_ec'), 5)
    # The twins carry no 0x1018; CiA 301 makes it mandatory, so node 2 gets one here.
    identity = od.ODRecord('Identity object', 0x1018)
    for sub, value in ((0, 4), (1, 0x12345678), (2, 0x402), (3, 1), (4, 77)):
        var = od.ODVariable(f'sub{sub}', 0x1018, sub)
        var.data_type = od.UNSIGNED8 if sub == 0 else od.UNSIGNED32
        var.access_type, var.default = 'ro', value
        identity.add_member(var)
    generic.node.object_dictionary.add_object(identity)
    bus = SimulatedCanBus([generic, kinco], channel).start()
    generic.node.data_store.setdefault(0x1017, {})[0] = (50).to_bytes(2, 'little')
    try:
        code, out, err = scan(['--can', f'virtual:{channel}', '--listen', '0.5',
                               '--sdo-probe', '--ids', '1-6', '--yaml', str(tmp_path / 'c.yaml')])
    finally:
        bus.stop()
    assert code == FOUND, err
    found = rows(out)
    assert set(found) == {2, 5}, out
    assert found[2][3] == 'cia402_velocity' and found[2][4] == 'medium'
    assert 'vendor=0x12345678' in found[2][5] and 'product=0x00000402' in found[2][5]
    assert 'NMT' in found[2][6]                                  # heard by its heartbeat
    assert 'answered the SDO probe' in found[5][6]                # heartbeat off: asked
    assert 'abort 0x06020000' in found[5][5]                      # no 0x1018 on that twin
    assert 'kinco_ec: no 0x1000/0x1018 values documented' in found[5][6]
    config = load_bus_config(str(tmp_path / 'c.yaml'))
    assert config.settings['transport.channel'] == channel


def test_canopen_scan_of_an_unknown_interface_is_a_clear_error():
    code, _, err = scan(['--can', 'no_such_interface:x'])
    assert code == FAILED and 'cannot open CAN bus' in err


# --- no ROS on the technician's laptop ---------------------------------------------------------

def test_both_tools_run_as_installed_executables_without_ros(mixed_line, tmp_path):
    import os
    import shutil
    import subprocess
    line, _ = mixed_line
    # An rclpy that cannot be imported: the tools must not need it on a line.
    poison = tmp_path / 'poison' / 'rclpy'
    poison.mkdir(parents=True)
    (poison / '__init__.py').write_text("raise ImportError('rclpy must not be imported')\n")
    env = {**os.environ, 'PYTHONPATH': os.pathsep.join(
        [str(poison.parent), os.environ.get('PYTHONPATH', '')])}
    scan_exe, params_exe = shutil.which('vfd_scan'), shutil.which('vfd_params')
    assert scan_exe and params_exe, 'vfd_scan / vfd_params not installed (setup.cfg)'
    done = subprocess.run([scan_exe, '--port', str(line.link_path), '--ids', '1-2',
                           '--baudrates', '115200', '--quiet'], env=env, capture_output=True,
                          text=True, timeout=60)
    assert done.returncode == FOUND, done.stdout + done.stderr
    assert 'boneng_am' in done.stdout and 'boneng_mh' in done.stdout
    done = subprocess.run([params_exe, 'dump', '--port', str(line.link_path), '--unit', '2',
                           '--profile', 'boneng_mh', '-o', str(tmp_path / 'mh.yaml')],
                          env=env, capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stdout + done.stderr
    assert (tmp_path / 'mh.yaml').exists()
    done = subprocess.run([params_exe, 'dump', '--node', '/nobody/drive', '-o',
                           str(tmp_path / 'x.yaml')], env=env, capture_output=True, text=True,
                          timeout=60)
    assert done.returncode == 2 and '--node needs ROS 2' in done.stderr, done.stderr
    assert 'rclpy must not be imported' in done.stderr


def test_canopen_scan_hears_a_boot_up_while_it_listens():
    import threading
    import uuid

    from vfd_ros2.sim.canopen_drive import SimulatedCanBus, SimulatedCanopenDrive

    class Watched(io.StringIO):
        """stderr that says when the scan has started listening."""

        listening = threading.Event()

        def write(self, text: str) -> int:
            if 'listening' in text:
                self.listening.set()
            return super().write(text)
    channel = f'boot{uuid.uuid4().hex[:8]}'
    out, err = io.StringIO(), Watched()
    codes = []
    scanner = threading.Thread(target=lambda: codes.append(run(
        ['--can', f'virtual:{channel}', '--listen', '1.5'], stdout=out, stderr=err)))
    scanner.start()
    bus = None
    try:
        assert err.listening.wait(5.0), 'the scan did not start listening'
        # The drive powers up while the scan listens: its boot-up names it.
        bus = SimulatedCanBus([SimulatedCanopenDrive(shipped_profile('cia402_velocity'), 9)],
                              channel).start()
        scanner.join(10.0)
    finally:
        scanner.join(10.0)
        if bus is not None:
            bus.stop()
    assert codes == [FOUND], out.getvalue() + err.getvalue()
    row = rows(out.getvalue())[9]
    assert row[3] == 'cia402_velocity' and 'NMT boot-up' in row[6], row


def test_a_line_of_garbled_replies_alone_is_nothing_found(tmp_path):
    """A line whose every reply is garbled: listed, but the exit status is 'nothing'.

    It said 'found', for a line with no usable drive.
    """
    from vfd_ros2.sim.rtu_line import LineFaults
    drive = SimulatedDrive(shipped_profile('boneng_am'), 1)
    # (seeded: a third of the simulator's corruptions relabel the reply as another
    # unit's with a good CRC, which is no garbled reply; unseeded, a run whose every
    # reply at 8N1 was relabelled so found none, one run in about fifty)
    line = SimulatedRtuLine([drive], tmp_path / 'noisy', faults=LineFaults(corrupt_rate=1.0),
                            tick_period=0.001, seed=1).start()
    try:
        # (a response time with room for a loaded machine: a garbled reply that came
        # after it is "answered after the timeout", not a garbled one)
        code, out, _ = scan(['--port', str(line.link_path), '--ids', '1-3',
                             '--baudrates', '115200', '--response-time', '0.15'])
    finally:
        line.stop()
    assert 'garbled reply' in out, out
    assert code == NOTHING, out
