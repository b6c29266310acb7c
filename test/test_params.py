"""vfd_params: dump -> change -> diff -> restore for every family on its real wire protocol.

Modbus RTU families on a pty line, the IMO HD2 on Modbus TCP, the generic CiA 402
profile on python-can's virtual bus; the restore plan and its halts also without
I/O (a dictionary drive). No ROS here except the one test through a drive node.
"""

from __future__ import annotations

import io
import math
from pathlib import Path

import pytest
import yaml

from harness import wait_for
from unit_support import shipped_profile
from vfd_ros2.apps.params import DIFFERENT, DONE, FAILED, run
from vfd_ros2.drives.backup import (
    FORMAT,
    Backup,
    Entry,
    compare,
    execute,
    plan_restore,
    take_backup,
)
from vfd_ros2.drives.base import ParameterValue
from vfd_ros2.errors import ParameterError, ProtocolException
from vfd_ros2.profiles import Access, PersistenceKind
from vfd_ros2.protocol.registers import encode_words
from vfd_ros2.sim.model import SimulatedDrive
from vfd_ros2.sim.rtu_line import SimulatedRtuLine
from vfd_ros2.sim.tcp_server import SimulatedTcpServer

MODBUS_FAMILIES = ['boneng_am', 'boneng_mh', 'veichi_ehs100', 'kinco_ec', 'imo_hd2']

#: how each family's round trip writes (every persistence scheme is exercised)
WRITE_MODE = {'boneng_am': 'ram', 'boneng_mh': 'eeprom', 'veichi_ehs100': 'eeprom',
              'kinco_ec': 'ram', 'imo_hd2': 'ram'}


def params(argv: list[str]) -> tuple[int, str, str]:
    out, err = io.StringIO(), io.StringIO()
    code = run([str(a) for a in argv], stdout=out, stderr=err)
    return code, out.getvalue(), err.getvalue()


class Line:
    """One simulated drive on its family's own link, and the vfd_params link options."""

    def __init__(self, family: str, tmp_path: Path, initial: dict[str, float] | None = None,
                 unit: int = 1) -> None:
        self.profile = shipped_profile(family)
        self.sim = SimulatedDrive(self.profile, unit, initial)
        if self.profile.transports[0] == 'modbus_tcp':
            self.server = SimulatedTcpServer([self.sim]).start()
            self.link = ['--host', '127.0.0.1', '--tcp-port', self.server.port]
        else:
            self.server = SimulatedRtuLine([self.sim], tmp_path / f'line_{family}').start()
            self.link = ['--port', self.server.link_path]
        self.link += ['--unit', unit]

    def frames(self) -> list[bytes]:
        """Every request PDU seen (RTU: unit + PDU + CRC; TCP: MBAP + PDU), oldest first."""
        return [frame for _, frame in list(self.server.received)]

    def writes(self) -> list[tuple[int, int]]:
        """Return (function, address) of every write request seen."""
        found = []
        for frame in self.frames():
            pdu = frame[7:] if self.profile.transports[0] == 'modbus_tcp' else frame[1:]
            if pdu[0] in (6, 16):
                found.append((pdu[0], int.from_bytes(pdu[1:3], 'big')))
        return found

    def set(self, code: str, value: float) -> None:
        """Change a parameter on the drive itself (a technician at the keypad)."""
        parameter = self.profile.parameter(code)
        self.sim.write(parameter.address, encode_words(parameter, parameter.to_raw(value)))

    def close(self) -> None:
        self.server.stop()


@pytest.fixture
def make_line(tmp_path):
    made: list[Line] = []

    def make(family: str, **kwargs) -> Line:
        line = Line(family, tmp_path, **kwargs)
        made.append(line)
        return line
    yield make
    for line in made:
        line.close()


def other_value(parameter, current: float) -> float:
    """Return a valid value of ``parameter`` other than ``current`` (on the grid, in range)."""
    if parameter.options:
        return float(next(raw for raw in sorted(parameter.options)
                          if raw * parameter.scale != current)) * parameter.scale
    low = parameter.minimum if parameter.minimum is not None else 0.0
    high = parameter.maximum if parameter.maximum is not None else low + 100 * parameter.scale
    steps = max(1, round((high - low) / parameter.scale) // 3)
    value = round(low / parameter.scale + steps) * parameter.scale
    return value if not math.isclose(value, current) else low


def settings_to_change(profile) -> dict[str, str]:
    """Pick, per family: a commissioning selector, a stopped-only and a run-time parameter."""
    identify = profile.identify
    special = set(identify.link_parameters) | set(profile.control_owned) | \
        set(profile.motion_channels) | {profile.modbus.persistence.parameter}
    commissioning = {item.code for item in profile.commissioning}
    chosen = {}
    persistence = profile.modbus.persistence

    def candidates(access):
        for code, parameter in profile.parameters.items():
            if parameter.access is access and code not in special and \
                    code not in commissioning and parameter.address >= 0 and \
                    (persistence.covers(parameter.address)) and \
                    (parameter.options or parameter.maximum is not None):
                yield code
    chosen['commissioning'] = profile.commissioning[-1].code
    chosen['run_time'] = next(candidates(Access.READ_WRITE))
    stopped = next(candidates(Access.WRITE_WHEN_STOPPED), None)
    if stopped is not None:
        chosen['stopped_only'] = stopped
    return chosen


# --- the round trip, every family on its own wire ---------------------------------------------

@pytest.mark.parametrize('family', MODBUS_FAMILIES)
def test_dump_change_diff_restore_round_trip(make_line, tmp_path, family):
    line = make_line(family)
    profile = line.profile
    backup_file = tmp_path / f'{family}.yaml'
    code, out, err = params(['dump', *line.link, '--profile', family, '-o', backup_file])
    assert code == DONE, out + err
    assert f'identifies as {family}' in out
    document = yaml.safe_load(backup_file.read_text())
    assert document['format'] == FORMAT and document['profile'] == family
    assert set(document['identity']) == set(profile.identify.firmware)
    entries = {item['code']: item for item in document['parameters']}
    assert len(entries) == len(profile.parameters) and not document['unreadable']
    some = next(item for item in document['parameters'] if 'unit' in item)
    assert {'code', 'value', 'raw', 'access'} <= set(some)
    assert line.writes() == []                         # a dump never writes

    # The drive changes: a commissioning selector, a stopped-only and a run-time value.
    chosen = settings_to_change(profile)
    if family != 'veichi_ehs100':
        # The manuals mark no parameter "only while stopped" except the Veichi's (○).
        assert 'stopped_only' not in chosen
    changed = {}
    for code in chosen.values():
        parameter = profile.parameter(code)
        changed[code] = other_value(parameter, entries[code]['value'])
        line.set(code, changed[code])

    code, out, _ = params(['diff', backup_file, *line.link])
    assert code == DIFFERENT, out
    listed = {row.split()[0] for row in out.splitlines()[2:-1]}
    assert listed == set(chosen.values()), out

    # Dry run: the plan in the manual's order, nothing on the wire but reads.
    before = len(line.writes())
    code, out, _ = params(['restore', backup_file, *line.link])
    assert code == DONE and 'dry run' in out, out
    assert len(line.writes()) == before
    groups = [row.split('[')[1].split(']')[0] for row in out.splitlines() if '. [' in row]
    expected = [g for g in ('commissioning', 'stopped_only', 'run_time') if g in chosen]
    assert groups == expected, out
    for owned in profile.control_owned:
        assert f'skip {owned}: control-owned' in out

    mode = WRITE_MODE[family]
    code, out, err = params(['restore', backup_file, *line.link, '--write', mode])
    assert code == DONE, out + err
    assert f'written: {len(chosen)} of {len(chosen)}' in out
    for code_ in chosen.values():
        assert line.sim.value(code_) == pytest.approx(entries[code_]['value']), code_
    # RAM or EEPROM, as the family's manual does it.
    persistence = profile.modbus.persistence
    run_time = profile.parameter(chosen['run_time'])
    addresses = {address for _, address in line.writes()}
    if persistence.kind is PersistenceKind.ADDRESS_OFFSET:
        assert run_time.address + persistence.offset in addresses    # EEPROM = + 0x1000
    elif persistence.kind is PersistenceKind.ADDRESS_FLAG:
        assert run_time.address | persistence.flag in addresses       # RAM = | 0x8000
    elif persistence.kind is PersistenceKind.SWITCH_PARAMETER:
        switch = profile.parameter(persistence.parameter)
        # RAM writes flip it on the way (EEPROM ones need no flip from the factory 0); it
        # ends as the file has it.
        assert line.sim.value(switch.code) == pytest.approx(entries[switch.code]['value'])
        assert ((6, switch.address) in line.writes()) == (mode == 'ram')
    else:
        assert 'does not distinguish RAM and EEPROM' in out
    # The drive was held stopped, and the diff is empty now.
    assert not line.sim.run_requested
    code, out, _ = params(['diff', backup_file, *line.link])
    assert code == DONE and 'no differences' in out, out


@pytest.mark.parametrize('family', ['boneng_am', 'veichi_ehs100'])
def test_restore_onto_a_replacement_drive_with_factory_values(make_line, tmp_path, family):
    # The old drive was commissioned (the profile's bus-control values); the new one is not.
    profile = shipped_profile(family)
    commissioned = {item.code: item.value for item in profile.commissioning}
    old = make_line(family, initial=commissioned)
    backup_file = tmp_path / 'old.yaml'
    assert params(['dump', *old.link, '--profile', family, '-o', backup_file])[0] == DONE
    new = make_line(family)
    assert not new.sim.bus_control()
    code, out, err = params(['restore', backup_file, *new.link, '--write', 'eeprom'])
    assert code == DONE, out + err
    steps = [row for row in out.splitlines() if '. [' in row]
    differing = [item.code for item in profile.commissioning
                 if profile.parameter(item.code).default != item.value]
    assert [row.split(']')[1].split()[0].rstrip(':') for row in steps] == differing
    assert new.sim.bus_control()                          # the new drive obeys the bus now


# --- refusals and halts ------------------------------------------------------------------------

def test_a_drive_that_refuses_a_write_midway_halts_and_is_left_stopped(make_line, tmp_path):
    profile = shipped_profile('boneng_am')
    line = make_line('boneng_am')
    backup_file = tmp_path / 'am.yaml'
    assert params(['dump', *line.link, '--profile', 'boneng_am', '-o', backup_file])[0] == DONE
    first, refused, last = 'B01.03', 'B04.02', 'B04.03'        # commissioning, then run time
    for code in (first, refused, last):
        parameter = profile.parameter(code)
        line.set(code, other_value(parameter, line.sim.value(code)))
    changed = {code: line.sim.value(code) for code in (refused, last)}
    line.sim.refuse_writes([refused])
    code, out, _ = params(['restore', backup_file, *line.link, '--write', 'ram'])
    assert code == DIFFERENT, out
    assert f'HALTED at {refused}: the drive refused {refused}' in out
    assert 'exception 5 (read only' in out                     # the AM's own meaning of 5
    assert 'written: 1 of 3' in out and f'not written (2): {refused}, {last}' in out
    assert 'drive: stop command written (P07.32); the drive reports not running' in out
    assert line.sim.value(first) == profile.parameter(first).default   # written
    for code, value in changed.items():
        assert line.sim.value(code) == value                           # not written
    assert line.sim.value('C02.07') == 0            # the RAM write's switch, set back
    assert line.sim.last_command_value == profile.control.values['stop']
    assert not line.sim.run_requested and not line.sim.output_active


def test_a_halt_at_the_first_write_still_sets_the_ram_switch_back(make_line, tmp_path):
    """A restore halted at its first write still sets the RAM/EEPROM switch back.

    The AM's RAM write flips C02.07 before the write the drive refuses: nothing is
    written, and the switch stayed on RAM-only (later changes lost at power-off).
    """
    profile = shipped_profile('boneng_am')
    line = make_line('boneng_am')
    backup_file = tmp_path / 'am.yaml'
    assert params(['dump', *line.link, '--profile', 'boneng_am', '-o', backup_file])[0] == DONE
    refused = 'B04.02'
    line.set(refused, other_value(profile.parameter(refused), line.sim.value(refused)))
    line.sim.refuse_writes([refused])
    code, out, _ = params(['restore', backup_file, *line.link, '--write', 'ram'])
    assert code == DIFFERENT and f'HALTED at {refused}' in out, out
    assert line.sim.value('C02.07') == 0, out


def test_a_file_with_a_value_no_write_can_take_is_refused_whole(make_line, tmp_path):
    """A file with a value no write can take is refused whole, before any write.

    Out of range, off the resolution: the others were written and the restore
    ended 0.
    """
    line = make_line('boneng_am')
    backup_file = tmp_path / 'am.yaml'
    assert params(['dump', *line.link, '--profile', 'boneng_am', '-o', backup_file])[0] == DONE
    document = yaml.safe_load(backup_file.read_text())
    for item in document['parameters']:
        if item['code'] == 'B04.02':
            item['value'], item['raw'] = 12.5, 125          # a good edit
        if item['code'] == 'B04.03':
            item['value'], item['raw'] = 99999.0, 999990    # above the maximum
    backup_file.write_text(yaml.safe_dump(document))
    before = line.sim.value('B04.02')
    for argv in (['restore', backup_file, *line.link],
                 ['restore', backup_file, *line.link, '--write', 'ram']):
        code, out, err = params(argv)
        assert code == FAILED and 'not valid B04.03' in out and 'fix the file' in err, \
            (out, err)
    assert line.writes() == [] and line.sim.value('B04.02') == before


@pytest.mark.parametrize(('edit', 'message'), [
    (lambda d: d['parameters'][0].update(raw='abc'), 'raw'),
    (lambda d: d['parameters'][0].update(value=True), 'not a number'),
    (lambda d: d['parameters'][0].update(value='12.5'), 'not a number'),
    (lambda d: d['parameters'][0].update(value=1e308), 'finite number a drive can hold'),
    (lambda d: d.update(identity=['A02.00']), 'identity and unreadable must be mappings'),
    (lambda d: d['identity'].update({'A02.00': 'v1.02'}), 'not a number'),
    (lambda d: d.update(parameters=5), 'parameters must be a list'),
    (lambda d: d['parameters'].append(dict(d['parameters'][0])), 'keep one'),
])
def test_a_malformed_backup_file_is_a_clear_error_not_a_traceback(make_line, tmp_path, edit,
                                                                  message):
    line = make_line('boneng_am')
    backup_file = tmp_path / 'am.yaml'
    assert params(['dump', *line.link, '--profile', 'boneng_am', '-o', backup_file])[0] == DONE
    document = yaml.safe_load(backup_file.read_text())
    edit(document)
    backup_file.write_text(yaml.safe_dump(document))
    for argv in (['restore', backup_file, *line.link, '--write', 'ram'],
                 ['diff', backup_file, backup_file]):
        code, out, err = params(argv)
        assert code == FAILED and message in err, (argv, out, err)
    assert line.writes() == []


def test_a_file_that_is_not_utf8_is_a_clear_error(tmp_path):
    backup_file = tmp_path / 'latin1.yaml'
    backup_file.write_bytes(b'format: vfd_params/1\nmodel: caf\xe9\n')
    code, _, err = params(['diff', backup_file, backup_file])
    assert code == FAILED and 'not UTF-8' in err, err


def test_the_tools_run_as_python_modules(tmp_path):
    """The tools run with `python -m` (vfd_ros2.apps.params / .scan did nothing, exit 0)."""
    import subprocess
    import sys
    for module in ('vfd_ros2.apps.params', 'vfd_ros2.apps.scan'):
        done = subprocess.run([sys.executable, '-m', module, '--help'], capture_output=True,
                              text=True, timeout=60)
        assert done.returncode == 0 and 'usage:' in done.stdout, (module, done.stdout)
    done = subprocess.run([sys.executable, '-m', 'vfd_ros2.apps.params', 'diff',
                           str(tmp_path / 'none.yaml'), str(tmp_path / 'none.yaml')],
                          capture_output=True, text=True, timeout=60)
    assert done.returncode == FAILED and 'cannot read' in done.stderr, done.stderr


def test_a_running_drive_is_not_restored(make_line, tmp_path):
    profile = shipped_profile('veichi_ehs100')
    commissioned = {item.code: item.value for item in profile.commissioning}
    line = make_line('veichi_ehs100', initial=commissioned)
    backup_file = tmp_path / 'v.yaml'
    assert params(['dump', *line.link, '--profile', 'veichi_ehs100', '-o',
                   backup_file])[0] == DONE
    line.set('F0.04', other_value(profile.parameter('F0.04'), line.sim.value('F0.04')))
    with line.sim.lock:                                  # the pump runs
        line.set(profile.velocity.setpoint, 20.0)
        line.sim.run_requested = True
    wait_for(lambda: line.sim.output_active, 3.0, 'simulated drive running')
    before = len(line.writes())
    code, out, err = params(['restore', backup_file, *line.link, '--write', 'eeprom'])
    assert code == FAILED and 'the drive reports running: stop it first' in err, out + err
    assert len(line.writes()) == before                  # nothing written, not even a stop
    assert line.sim.output_active


def test_a_file_of_another_family_is_refused(make_line, tmp_path):
    am = make_line('boneng_am', unit=1)
    backup_file = tmp_path / 'am.yaml'
    assert params(['dump', *am.link, '--profile', 'boneng_am', '-o', backup_file])[0] == DONE
    for family, looks_like in (('veichi_ehs100', 'veichi_ehs100 (medium)'),
                               ('boneng_mh', 'boneng_mh (medium)')):
        other = make_line(family)
        code, out, err = params(['restore', backup_file, *other.link, '--write', 'eeprom'])
        assert code == FAILED, out + err
        assert 'does not identify as boneng_am' in err and looks_like in err, err
        assert other.writes() == []
    code, _, err = params(['diff', backup_file, tmp_path / 'missing.yaml'])
    assert code == FAILED and 'cannot read' in err


def test_a_firmware_change_is_refused_unless_allowed(make_line, tmp_path):
    line = make_line('kinco_ec')
    backup_file = tmp_path / 'k.yaml'
    assert params(['dump', *line.link, '--profile', 'kinco_ec', '-o', backup_file])[0] == DONE
    version = line.profile.parameter('D0.51')
    line.sim.words[version.address] = 7                      # the new drive's firmware
    line.set('A0.06', other_value(line.profile.parameter('A0.06'), line.sim.value('A0.06')))
    code, _, err = params(['restore', backup_file, *line.link, '--write', 'ram'])
    assert code == FAILED and 'D0.51: 0 in the file, 7 on the drive' in err, err
    assert line.writes() == []
    code, out, _ = params(['restore', backup_file, *line.link, '--write', 'ram',
                           '--allow-firmware-change'])
    assert code == DONE and 'firmware differs, allowed' in out, out


def test_link_settings_are_written_last_and_only_when_asked(make_line, tmp_path):
    line = make_line('boneng_mh')
    backup_file = tmp_path / 'mh.yaml'
    assert params(['dump', *line.link, '--profile', 'boneng_mh', '-o', backup_file])[0] == DONE
    line.set('C02.02', 9)                                    # the replacement's address
    line.set('B04.02', 12.5)
    code, out, _ = params(['restore', backup_file, *line.link, '--write', 'ram'])
    assert code == DONE and 'skip C02.02: link setting' in out, out
    assert line.sim.value('C02.02') == 9
    code, out, _ = params(['restore', backup_file, *line.link, '--write', 'ram',
                           '--link-settings'])
    assert code == DONE, out
    steps = [row for row in out.splitlines() if '. [' in row]
    assert '[link] C02.02' in steps[-1], steps
    assert line.sim.value('C02.02') == 1


def test_bad_input_gives_a_clear_message(make_line, tmp_path):
    line = make_line('boneng_am')
    garbage = tmp_path / 'garbage.yaml'
    garbage.write_text('just: [a, list')
    wrong = tmp_path / 'wrong.yaml'
    wrong.write_text(yaml.safe_dump({'format': FORMAT, 'profile': 'no_such_drive'}))
    other = tmp_path / 'other.yaml'
    other.write_text(yaml.safe_dump({'some': 'file'}))
    for argv, message in (
            (['dump', '--port', tmp_path / 'ttyNONE', '--profile', 'boneng_am', '-o',
              tmp_path / 'x.yaml'], 'no such serial port'),
            (['dump', *line.link, '-o', tmp_path / 'x.yaml'], 'name the family'),
            (['dump', '--profile', 'boneng_am', '-o', tmp_path / 'x.yaml'],
             'exactly one of --port, --host, --can, --node'),
            (['restore', garbage, *line.link], 'is not valid YAML'),
            (['restore', wrong, *line.link], "unknown drive profile 'no_such_drive'"),
            (['restore', other, *line.link], 'is not a vfd_params backup'),
            (['dump', '--host', '127.0.0.1', '--tcp-port', '1', '--profile', 'imo_hd2', '-o',
              tmp_path / 'x.yaml'], 'cannot'),
            (['dump', *line.link, '--unit', 7, '--profile', 'boneng_am', '-o',
              tmp_path / 'x.yaml'], 'nothing answers at unit 7')):
        code, out, err = params(argv)
        assert code == FAILED and message in err, (argv, out, err)
    assert line.writes() == []


def test_two_files_diff_in_engineering_units(make_line, tmp_path):
    line = make_line('veichi_ehs100')
    a, b = tmp_path / 'a.yaml', tmp_path / 'b.yaml'
    assert params(['dump', *line.link, '--profile', 'veichi_ehs100', '-o', a])[0] == DONE
    line.set('F3.14', 12.34)
    line.set('F0.01', 2)
    assert params(['dump', *line.link, '--profile', 'veichi_ehs100', '-o', b])[0] == DONE
    code, out, _ = params(['diff', a, b])
    assert code == DIFFERENT, out
    rows = {row.split()[0]: row for row in out.splitlines()[1:-1]}
    assert set(rows) == {'F3.14', 'F0.01'}
    assert '12.34s' in rows['F3.14'] and '(RS485 communication)' in rows['F0.01']
    assert params(['diff', a, a])[0] == DONE


def test_a_family_is_detected_when_not_named(make_line, tmp_path):
    line = make_line('boneng_mh')
    code, out, err = params(['dump', *line.link, '--baudrate', 115200, '-o', tmp_path / 'm.yaml'])
    assert code == DONE, out + err
    assert yaml.safe_load((tmp_path / 'm.yaml').read_text())['profile'] == 'boneng_mh'


# --- CANopen: the generic CiA 402 profile on the virtual bus -----------------------------------

def test_round_trip_over_canopen(tmp_path):
    import uuid

    from vfd_ros2.sim.canopen_drive import SimulatedCanBus, SimulatedCanopenDrive
    profile = shipped_profile('cia402_velocity')
    channel = f'par{uuid.uuid4().hex[:8]}'
    sim = SimulatedCanopenDrive(profile, 3)
    bus = SimulatedCanBus([sim], channel).start()
    link = ['--can', f'virtual:{channel}', '--unit', '3']
    try:
        backup_file = tmp_path / 'c.yaml'
        code, out, err = params(['dump', *link, '--profile', 'cia402_velocity', '-o',
                                 backup_file])
        assert code == DONE, out + err
        assert 'family not checked' in out
        backup = Backup.load(backup_file)
        assert backup.entries['0x6083'].value == 3000
        parameter = profile.parameter('0x6083')
        sim.node.sdo.download(parameter.index, parameter.subindex,
                              (4500).to_bytes(4, 'little'))
        code, out, _ = params(['diff', backup_file, *link])
        assert code == DIFFERENT and '0x6083' in out, out
        code, out, err = params(['restore', backup_file, *link, '--write', 'ram'])
        assert code == DONE, out + err
        assert sim.value('0x6083') == 3000
        assert params(['diff', backup_file, *link])[0] == DONE
    finally:
        bus.stop()


# --- the plan and its execution, no I/O ---------------------------------------------------------

class DictAccess:
    """A ParameterAccess over a dict of raw values, for the planner and the executor."""

    def __init__(self, profile, refuse: str = '', running_after: int | None = None) -> None:
        self.profile = profile
        self.description = 'memory'
        self.raw = {code: round((p.default or 0) / p.scale)
                    for code, p in profile.parameters.items()}
        self.refuse = refuse
        self.running_after = running_after
        self.running_calls = 0
        self.stops = 0
        self.written: list[str] = []

    def read(self, code):
        parameter = self.profile.parameter(code)
        return ParameterValue(parameter, self.raw[code], parameter.from_raw(self.raw[code]))

    def write(self, code, value, persistent):
        parameter = self.profile.parameter(code)
        if code == self.refuse:
            raise ProtocolException(6, 'parameter cannot be changed while running')
        self.raw[code] = parameter.to_raw(value)
        self.written.append(code)
        return self.read(code), 'EEPROM write' if persistent else 'RAM write'

    def refusal(self, code):
        return ''

    def running(self):
        self.running_calls += 1
        return self.running_after is not None and self.running_calls > self.running_after

    def stop(self):
        self.stops += 1
        return 'stopped'


def _changed_backup(profile, access, changes):
    backup = take_backup(access)
    for code, value in changes.items():
        entry = backup.entries[code]
        backup.entries[code] = Entry(code, value, entry.raw, entry.name, entry.unit, '',
                                     entry.access)
    return backup


def test_the_plan_orders_commissioning_stopped_only_run_time_switch_and_link():
    profile = shipped_profile('veichi_ehs100')
    access = DictAccess(profile)
    backup = _changed_backup(profile, access, {'F3.14': 9.0, 'F0.04': 1, 'FB.07': 0,
                                               'FB.08': 0, 'FB.01': 7, 'F0.01': 2})
    plan = plan_restore(backup, take_backup(access), access, include_link=True)
    assert [(s.group, s.code) for s in plan.steps] == [
        ('commissioning', 'F0.01'), ('commissioning', 'FB.07'), ('stopped_only', 'F0.04'),
        ('run_time', 'F3.14'), ('link', 'FB.01')]
    assert plan.unchanged > 0 and plan.read_only > 0
    result = execute(plan, access, persistent=True)
    assert result.complete and access.written == [s.code for s in plan.steps]
    # Every stopped-only write asked the drive first (F0.01, F0.04 and FB.01 are ○).
    assert access.running_calls == 3


def test_the_executor_halts_when_the_drive_starts_running():
    profile = shipped_profile('veichi_ehs100')
    access = DictAccess(profile, running_after=1)
    backup = _changed_backup(profile, access, {'F0.01': 2, 'F0.04': 1, 'F3.14': 9.0})
    plan = plan_restore(backup, take_backup(access), access)
    result = execute(plan, access, persistent=False)
    assert [s.code for s, _, _ in result.written] == ['F0.01']
    assert result.failed[0].code == 'F0.04' and 'reports running' in result.failed[1]
    assert [s.code for s in result.not_written] == ['F3.14'] and access.stops == 1


def test_the_ram_eeprom_switch_ends_as_the_file_has_it():
    profile = shipped_profile('boneng_am')
    access = DictAccess(profile)
    backup = _changed_backup(profile, access, {'B04.02': 9.0})
    plan = plan_restore(backup, take_backup(access), access)
    assert plan.switch == ('C02.07', 0)

    class Flipping(DictAccess):
        def write(self, code, value, persistent):      # as ModbusDrive does for a RAM write
            if code != 'C02.07':
                self.raw['C02.07'] = 1
            return super().write(code, value, persistent)
    flipping = Flipping(profile)
    result = execute(plan, flipping, persistent=False)
    assert flipping.written == ['B04.02', 'C02.07'] and flipping.raw['C02.07'] == 0
    assert result.complete


def test_backup_files_survive_a_round_trip_and_an_edited_value_wins(tmp_path):
    profile = shipped_profile('kinco_ec')
    access = DictAccess(profile)
    backup = take_backup(access)
    path = tmp_path / 'k.yaml'
    backup.save(path)
    text = path.read_text()
    assert text.startswith('# vfd_params backup of kinco_ec')
    document = yaml.safe_load(text)
    for item in document['parameters']:
        if item['code'] == 'A0.06':
            item['value'] = 1.5                        # edited by hand; raw left as it was
    document['parameters'].append({'code': 'Z9.99', 'value': 1})
    path.write_text(yaml.safe_dump(document))
    loaded = Backup.load(path)
    assert loaded.entries['A0.06'].value == 1.5 and 'Z9.99' in loaded.unknown
    differences = compare(backup, loaded)
    assert [d.code for d in differences] == ['A0.06']
    plan = plan_restore(loaded, backup, access)
    assert [s.code for s in plan.steps] == ['A0.06']
    assert any(s.code == 'Z9.99' for s in plan.skipped)
    with pytest.raises(ParameterError, match='different families'):
        compare(backup, take_backup(DictAccess(shipped_profile('boneng_am'))))


# --- through a running drive node ----------------------------------------------------------------

def test_dump_diff_restore_through_a_running_drive_node(make_harness, tmp_path):
    # The IMO HD2 on Modbus TCP: a short control cycle, so a parameter per cycle is quick.
    h = make_harness(profile='imo_hd2', node_parameters={'control_rate': 200.0})
    node = f'{h.namespace}/drive'
    backup_file = tmp_path / 'node.yaml'
    code, out, err = params(['dump', '--node', node, '-o', backup_file])
    assert code == DONE, out + err
    backup = Backup.load(backup_file)
    assert backup.profile == 'imo_hd2' and backup.identity == {'0x2103': 416}
    tuned = settings_to_change(h.profile)['run_time']
    commissioning = h.profile.commissioning[0].code
    for code_ in (tuned, commissioning):
        parameter = h.profile.parameter(code_)
        h.sim.write(parameter.address, encode_words(parameter, parameter.to_raw(
            other_value(parameter, h.sim.value(code_)))))
    code, out, _ = params(['diff', backup_file, '--node', node])
    assert code == DIFFERENT and tuned in out and commissioning in out, out
    code, out, err = params(['restore', backup_file, '--node', node, '--write', 'ram'])
    assert code == DONE, out + err
    # The node's own policy: it writes the commissioning values itself at every connect.
    assert f'skip {commissioning}: the node writes it at every connect' in out
    assert 'before writing: ~/stop' in out
    assert h.sim.value(tuned) == pytest.approx(backup.entries[tuned].value)
    # RAM, as asked: the node wrote the function code at its RAM-only address (| 0x8000).
    address = h.profile.parameter(tuned).address | 0x8000
    assert any(frame[7] == 6 and int.from_bytes(frame[8:10], 'big') == address
               for _, frame in list(h.line.received))
    assert '~/stop: stopped (call ~/enable to resume)' in out and 'held stopped' in out
    h.wait_status(lambda s: not s.running and s.online, 3.0, 'not running')
    code, out, _ = params(['diff', backup_file, '--node', node])
    assert code == DIFFERENT and commissioning in out and tuned not in out, out
    # A file of another family is refused by the node's profile.
    other = tmp_path / 'am.yaml'
    take_backup(DictAccess(shipped_profile('boneng_am'))).save(other)
    code, _, err = params(['restore', other, '--node', node])
    assert code == FAILED and 'runs profile imo_hd2, not boneng_am' in err, err


def test_a_backup_of_a_profile_from_its_own_file_finds_that_file_again(tmp_path):
    import shutil

    from vfd_ros2.profiles import PROFILE_DIR, load_profile
    for name in ('kinco_ec.yaml', 'kinco_ec_parameters.yaml', 'schema.json'):
        shutil.copy(PROFILE_DIR / name, tmp_path / name)
    custom = tmp_path / 'my_kinco.yaml'
    (tmp_path / 'kinco_ec.yaml').rename(custom)
    custom.write_text(custom.read_text().replace('name: kinco_ec', 'name: my_kinco', 1))
    profile = load_profile(str(custom))
    backup = take_backup(DictAccess(profile))
    backup.save(tmp_path / 'b.yaml')
    loaded = Backup.load(tmp_path / 'b.yaml')
    assert loaded.profile == 'my_kinco' and loaded.profile_file == str(custom.resolve())
    assert loaded.family.name == 'my_kinco' and compare(backup, loaded) == []


def test_a_drive_whose_run_state_cannot_be_read_is_not_restored(make_line, tmp_path):
    line = make_line('boneng_am')
    backup_file = tmp_path / 'am.yaml'
    assert params(['dump', *line.link, '--profile', 'boneng_am', '-o', backup_file])[0] == DONE
    line.set('B04.02', 9.0)
    line.sim.refuse(['P01.02'])              # a firmware that does not give its running flag
    assert params(['restore', backup_file, *line.link])[0] == DONE      # the plan is shown
    code, _, err = params(['restore', backup_file, *line.link, '--write', 'ram'])
    assert code == FAILED and 'run state cannot be read' in err, err
    assert line.writes() == []
