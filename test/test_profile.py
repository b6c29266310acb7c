"""Unit tests of the profile schema, the strict loader and the shipped profiles (no ROS)."""

from __future__ import annotations

import math
import re
from pathlib import Path
from typing import Any, Callable

import pytest
import yaml

from unit_support import shipped_profile
from vfd_ros2.errors import ParameterError, ProfileError
from vfd_ros2.profiles import (
    Access,
    DirectionMode,
    Parameter,
    SpeedUnit,
    ValueType,
    available_profiles,
    load_profile,
    load_profile_file,
)
from vfd_ros2.profiles.faults import describe_fault

SHIPPED = available_profiles()


def has_register(parameter: Parameter) -> bool:
    """Tell whether the parameter has a Modbus address (-1: a CANopen object only)."""
    return parameter.address != -1


# --- a minimal valid profile, mutated by each rejection test -------------------------------

def minimal_profile() -> dict[str, Any]:
    return {
        'schema': 1,
        'name': 'mini',
        'vendor': 'ACME',
        'model': 'M1',
        'manual': 'none',
        'transports': ['modbus_rtu'],
        'parameters': [
            {'code': 'P0.00', 'address': 0x1000, 'description': 'command word',
             'options': {0: 'stop', 1: 'run', 2: 'reset'}},
            {'code': 'P0.01', 'address': 0x1001, 'description': 'speed setpoint',
             'type': 'int16', 'scale': 0.1, 'unit': '%', 'min': -100.0, 'max': 100.0,
             'name': 'speed_setpoint'},
            {'code': 'P0.02', 'address': 0x1002, 'description': 'motor speed',
             'type': 'int16', 'unit': 'rpm', 'access': 'ro', 'name': 'motor_speed'},
            {'code': 'P0.03', 'address': 0x1003, 'description': 'fault code', 'access': 'ro'},
            {'code': 'D0.05', 'address': 0x2005, 'description': 'rated speed', 'unit': 'rpm',
             'default': 1400, 'name': 'motor_rated_speed'},
        ],
        'velocity': {'setpoint': 'P0.01', 'setpoint_unit': 'percent',
                     'feedback_unit': 'rpm', 'rated_speed': 'D0.05'},
        'control': {'command': 'P0.00', 'values': {'run': 1, 'stop': 0, 'fault_reset': 2}},
        'monitor': {'motor_speed': 'P0.02', 'fault_code': 'P0.03'},
        'flags': {'fault': {'signal': 'fault_code', 'rule': 'nonzero'}},
        'faults': {'code': 'P0.03',
                   'table': [{'code': 1, 'name': 'Overcurrent', 'remedy': 'check wiring'}]},
    }


@pytest.fixture
def write_profile(tmp_path: Path) -> Callable[..., Path]:
    """Write minimal_profile(), changed by ``mutate``, to a YAML file; return its path."""
    def write(mutate: Callable[[dict[str, Any]], None] | None = None,
              name: str = 'mini.yaml') -> Path:
        data = minimal_profile()
        if mutate is not None:
            mutate(data)
        path = tmp_path / name
        path.write_text(yaml.safe_dump(data, sort_keys=False), encoding='utf-8')
        return path
    return write


def test_minimal_profile_loads(write_profile):
    profile = load_profile_file(write_profile())
    assert profile.name == 'mini'
    assert set(profile.parameters) == {'P0.00', 'P0.01', 'P0.02', 'P0.03', 'D0.05'}
    setpoint = profile.parameters['P0.01']
    assert setpoint.type is ValueType.INT16 and setpoint.scale == 0.1
    assert setpoint.minimum == -100.0 and setpoint.maximum == 100.0
    assert profile.parameters['P0.02'].access is Access.READ_ONLY
    assert profile.parameters['P0.00'].access is Access.READ_WRITE      # the default
    assert profile.velocity.setpoint_unit is SpeedUnit.PERCENT
    assert profile.velocity.direction is DirectionMode.SETPOINT_SIGN    # the default
    assert profile.control.values == {'run': 1, 'stop': 0, 'fault_reset': 2}
    assert profile.control.action_of(2) == 'fault_reset'
    assert profile.control.action_of(9) is None
    assert [s.role for s in profile.monitor] == ['motor_speed', 'fault_code']
    assert profile.signal('fault_code').code == 'P0.03'
    assert profile.signal('temperature') is None
    assert profile.flags['fault'].evaluate(3) and not profile.flags['fault'].evaluate(0)
    assert profile.faults.table[1].name == 'Overcurrent'
    assert profile.modbus.max_read_registers == 125          # documented default
    assert profile.parameter_at(0x1001).code == 'P0.01'
    assert profile.parameter_at(0x1004) is None


def test_parameter_tables_are_included(write_profile, tmp_path):
    (tmp_path / 'extra.yaml').write_text(yaml.safe_dump({'parameters': [
        {'code': 'B4.02', 'address': 0x3402, 'description': 'acceleration', 'scale': 0.1,
         'unit': 's', 'name': 'acceleration_time'}]}), encoding='utf-8')

    def include(data):
        data['parameter_tables'] = ['extra.yaml']
        data['velocity']['acceleration_time'] = 'B4.02'
    profile = load_profile_file(write_profile(include))
    assert profile.parameter('acceleration_time').address == 0x3402
    assert len(profile.parameters) == 6


def test_an_unchanged_profile_is_parsed_once_and_a_changed_one_anew(write_profile, tmp_path):
    """A bus of many drives of one family shares one Profile; an edited file is read again."""
    table = tmp_path / 'extra.yaml'

    def write_table(scale: float) -> None:
        table.write_text(yaml.safe_dump({'parameters': [
            {'code': 'B4.02', 'address': 0x3402, 'description': 'acceleration',
             'scale': scale, 'unit': 's', 'name': 'acceleration_time'}]}), encoding='utf-8')

    def include(data):
        data['parameter_tables'] = ['extra.yaml']
    write_table(0.1)
    path = write_profile(include)
    first = load_profile_file(path)
    assert load_profile_file(path) is first
    assert load_profile_file(str(path)) is first
    write_table(0.2)            # the same size and, within the clock's tick, the same mtime
    second = load_profile_file(path)
    assert second is not first and second.parameter('acceleration_time').scale == 0.2
    path.write_text(path.read_text().replace('Overcurrent', 'Overkurrent'))
    assert load_profile_file(path).faults.table[1].name == 'Overkurrent'
    path.write_text('name: [')  # an edit that breaks the file is reported, not served
    with pytest.raises(ProfileError, match='not valid YAML'):
        load_profile_file(path)
    table.unlink()
    path.write_text(yaml.safe_dump({**minimal_profile(), 'parameter_tables': ['extra.yaml']}))
    with pytest.raises(ProfileError, match='cannot read'):
        load_profile_file(path)


# --- lookups ------------------------------------------------------------------------------

@pytest.fixture(scope='module')
def am():
    return shipped_profile('boneng_am')


@pytest.mark.parametrize('key', ['B04.02', 'b04.02', ' B04.02 ', 'b04.02\n'])
def test_lookup_by_code_any_case(am, key):
    parameter = am.parameter(key)
    assert parameter.code == 'B04.02'
    assert parameter.address == 0x3402


def test_lookup_by_readable_name(am):
    assert am.parameter('acceleration_time').code == 'B04.02'
    assert am.parameter('deceleration_time').code == 'B04.03'
    assert am.parameter('speed_setpoint') is am.parameters['P07.33']
    assert am.names['motor_rated_speed'] == 'D00.05'


@pytest.mark.parametrize('key', ['Z99.99', 'acceleration', '', 'B04.020'])
def test_lookup_unknown_is_a_parameter_error(am, key):
    with pytest.raises(ParameterError) as info:
        am.parameter(key)
    message = str(info.value)
    assert repr(key) in message
    assert 'boneng_am' in message
    assert 'readable name' in message


@pytest.mark.parametrize('name', SHIPPED)
def test_every_readable_name_and_code_resolves(name):
    profile = shipped_profile(name)
    for readable, code in profile.names.items():
        assert profile.parameter(readable).code == code
    for code, parameter in profile.parameters.items():
        assert profile.parameter(code) is parameter
        if has_register(parameter):
            assert profile.parameter_at(parameter.address) is parameter


@pytest.mark.parametrize('name', ['imo_hd2', 'kinco_ec'])
def test_lookup_of_hex_codes_is_case_insensitive(name):
    """Hexadecimal codes ('0x200A') are found as '0x200a' and '0X200A' too."""
    profile = shipped_profile(name)
    hex_codes = [c for c in profile.parameters
                 if re.fullmatch(r'0x[0-9A-F]*[A-F][0-9A-F]*', c)]
    assert hex_codes
    for code in hex_codes:
        assert profile.parameter(code.lower()).code == code
        assert profile.parameter(code.upper()).code == code


# --- the shipped profiles -------------------------------------------------------------------

def test_profiles_are_shipped():
    assert 'boneng_am' in SHIPPED
    assert not [n for n in SHIPPED if n.endswith('_parameters')]


@pytest.mark.parametrize('name', SHIPPED)
def test_shipped_profile_loads_and_is_consistent(name):
    profile = shipped_profile(name)
    assert profile.name == name
    assert profile.parameters
    setpoint = profile.parameter(profile.velocity.setpoint)
    assert setpoint.writable
    assert profile.parameter(profile.control.command).writable
    # The command values fit the command register (the driver writes them raw).
    low, high = profile.parameter(profile.control.command).type.bounds
    for value in profile.control.values.values():
        assert low <= value <= high
    if profile.velocity.direction is DirectionMode.COMMAND:
        assert 'run_reverse' in profile.control.values
    assert 1 <= profile.modbus.max_read_registers <= 125
    assert 1 <= profile.modbus.max_write_registers <= 123
    assert profile.modbus.function_codes & {3, 4}, 'no read function'
    assert profile.modbus.function_codes & {6, 16}, 'no write function'
    for parameter in profile.parameters.values():
        if not has_register(parameter):
            assert parameter.index is not None, f'{parameter.code}: no address at all'
            continue
        assert 0 <= parameter.address <= 0xFFFF - (parameter.register_count - 1)
        if parameter.minimum is not None and parameter.maximum is not None:
            assert parameter.minimum <= parameter.maximum, parameter.code
    if profile.comm_timeout is not None:
        assert profile.parameter(profile.comm_timeout.parameter).writable


@pytest.mark.parametrize('name', SHIPPED)
def test_shipped_registers_do_not_overlap(name):
    profile = shipped_profile(name)
    owner: dict[int, str] = {}
    for parameter in profile.parameters.values():
        if not has_register(parameter):
            continue
        for address in range(parameter.address, parameter.address + parameter.register_count):
            assert address not in owner, (
                f'{parameter.code} and {owner.get(address)} share address {address:#x}')
            owner[address] = parameter.code


@pytest.mark.parametrize('name', SHIPPED)
def test_shipped_defaults_are_writable_or_explained(name):
    """A default the loader would refuse to write must carry a note that says so."""
    profile = shipped_profile(name)
    for parameter in profile.parameters.values():
        if parameter.default is None:
            continue
        try:
            parameter.to_raw(parameter.default)
        except ParameterError:
            assert 'default' in parameter.note, (
                f'{parameter.code}: default {parameter.default} is not a valid value and '
                'its note does not explain why')


@pytest.mark.parametrize('name', SHIPPED)
def test_shipped_fault_tables_describe_themselves(name):
    profile = shipped_profile(name)
    assert profile.faults.table
    for code, entry in profile.faults.table.items():
        assert code == entry.code and code != 0
        assert entry.name
        info = describe_fault(profile.faults, code, 1)
        assert info.known and info.active and info.name == entry.name
        assert str(code) in info.display or f'{code:04X}' in info.display.upper()  # 0x3210
        assert entry.confidence in ('high', 'medium', 'low')
    timeout = profile.comm_timeout
    if timeout is not None and timeout.fault_code in profile.faults.table:
        assert describe_fault(profile.faults, timeout.fault_code, timeout.fault_subcode).known


# --- BONENG AM: the manual's address rule and fault table ---------------------------------

LETTER_NIBBLE = {'A': 0x2, 'B': 0x3, 'C': 0x4, 'D': 0x5, 'E': 0x6, 'F': 0x7, 'P': 0xE}


def am_formula_address(code: str) -> int:
    """Address rule of the AM manual: letter nibble, group byte-ish, index, all from the code."""
    match = re.fullmatch(r'([A-Z])(\d{2})\.(\d{2})', code)
    assert match, f'{code} is not a function code of the form X00.00'
    letter, group, index = match.group(1), int(match.group(2)), int(match.group(3))
    return (LETTER_NIBBLE[letter] << 12) | (group << 8) | index


def test_am_formula_examples():
    assert am_formula_address('B04.02') == 0x3402
    assert am_formula_address('P07.33') == 0xE721
    assert am_formula_address('A01.00') == 0x2100
    assert am_formula_address('D00.05') == 0x5005


def test_am_addresses_follow_the_manual_rule(am):
    deviations = []
    for code, parameter in am.parameters.items():
        expected = am_formula_address(code)
        if parameter.address != expected and 'address' not in parameter.note:
            deviations.append(f'{code}: {parameter.address:#06x} != {expected:#06x}')
    assert not deviations, 'addresses off the manual rule without a note:\n' + \
        '\n'.join(deviations)


@pytest.mark.parametrize('code', ['B00.23', 'B00.24', 'P02.36'])
def test_am_misprinted_addresses_use_the_rule(am, code):
    """Rows where the manual prints another address use the rule and say why."""
    parameter = am.parameters[code]
    assert parameter.address == am_formula_address(code)
    assert 'printed address' in parameter.note


def test_am_cyclic_registers(am):
    assert am.parameter(am.velocity.setpoint).address == 0xE721
    assert am.parameter(am.control.command).address == 0xE720
    setpoint = am.parameter(am.velocity.setpoint)
    assert setpoint.to_raw(100.0) == 1000          # 1000 = 100 % (0.1 % per LSB)
    assert setpoint.to_raw(-50.0) == -500


def test_am_fault_table(am):
    info = describe_fault(am.faults, 35, 3)
    assert info.known
    assert info.name == 'Communication exception'
    assert info.cause.startswith('Modbus communication fault')
    assert info.display == 'E35.03'
    assert am.faults.table[35].subcodes[3] == 'Modbus communication fault'
    assert am.faults.table[1].name == 'Overcurrent'
    assert am.faults.table[8].subcodes[1] == 'U phase output loss'
    assert am.comm_timeout.fault_code == 35 and am.comm_timeout.fault_subcode == 3
    assert 4 not in am.faults.table
    assert not describe_fault(am.faults, 4, 1).known


# --- the loader's rejections ------------------------------------------------------------------

def _set(path: str, value: Any) -> Callable[[dict[str, Any]], None]:
    """Mutation: set a dotted path (list indices as numbers) to value."""
    def mutate(data):
        *parents, last = path.split('.')
        node = data
        for key in parents:
            node = node[int(key)] if isinstance(node, list) else node[key]
        if isinstance(node, list):
            node[int(last)] = value
        else:
            node[last] = value
    return mutate


def _delete(path: str) -> Callable[[dict[str, Any]], None]:
    def mutate(data):
        *parents, last = path.split('.')
        node = data
        for key in parents:
            node = node[int(key)] if isinstance(node, list) else node[key]
        del node[int(last) if isinstance(node, list) else last]
    return mutate


def _append_parameter(**entry: Any) -> Callable[[dict[str, Any]], None]:
    def mutate(data):
        data['parameters'].append(entry)
    return mutate


REJECTIONS = {
    # unknown keys, at every level
    'unknown top-level key': (_set('colour', 'red'), ['unknown keys', 'colour']),
    'unknown parameter key': (_set('parameters.1.sclae', 0.1), ['unknown keys', 'sclae']),
    'unknown velocity key': (_set('velocity.setpiont', 'P0.01'), ['velocity', 'setpiont']),
    'unknown control key': (_set('control.edge', 0), ['control', 'edge']),
    'unknown fault key': (_set('faults.table.0.severity', 3), ['severity']),
    'unknown flag key': (_set('flags.fault.bits', 3), ['flags.fault', 'unknown keys', 'bits']),
    # missing required keys
    'missing name': (_delete('name'), ["'name' is a required property"]),
    'missing schema': (_delete('schema'), ["'schema' is a required property"]),
    'missing monitor': (_delete('monitor'), ["'monitor' is a required property"]),
    'missing parameter address': (_delete('parameters.1.address'),
                                  ['parameters.1', "'address' is a required property"]),
    'missing parameter description': (_delete('parameters.0.description'),
                                      ["'description' is a required property"]),
    'missing velocity setpoint': (_delete('velocity.setpoint'),
                                  ["velocity: 'setpoint' is a required property"]),
    'missing control values': (_delete('control.values'),
                               ["control: 'values' is a required property"]),
    'missing fault name': (_delete('faults.table.0.name'),
                           ["faults.table.0: 'name' is a required property"]),
    # references to codes that are not in the table
    'monitor names unknown code': (_set('monitor.temperature', 'X9.99'),
                                   ['monitor.temperature', "'X9.99'", 'not in the parameter']),
    'velocity setpoint unknown': (_set('velocity.setpoint', 'P0.09'),
                                  ['velocity.setpoint', "'P0.09'"]),
    'velocity rated speed unknown': (_set('velocity.rated_speed', 'D0.99'),
                                     ['velocity.rated_speed', "'D0.99'"]),
    'control command unknown': (_set('control.command', 'P9.00'),
                                ['control.command', "'P9.00'"]),
    'fault code register unknown': (_set('faults.code', 'P0.99'), ['faults.code', "'P0.99'"]),
    'status word unknown': (_set('status_words', ['P0.02', 'Q1.00']),
                            ['status_words[1]', "'Q1.00'"]),
    'commissioning unknown': (_set('commissioning', [{'code': 'B0.01', 'value': 2}]),
                              ["'B0.01'"]),
    'comm timeout unknown': (_set('comm_timeout', {'parameter': 'C2.04', 'fault_code': 35}),
                             ['comm_timeout.parameter', "'C2.04'"]),
    # duplicates
    'duplicate code': (_append_parameter(code='P0.02', address=0x1009, description='again'),
                       ['P0.02', 'defined twice']),
    'duplicate readable name': (_append_parameter(code='P0.09', address=0x1009,
                                                  description='x', name='motor_speed'),
                                ["'motor_speed'", 'used twice']),
    'duplicate fault code': (_set('faults.table', [{'code': 1, 'name': 'a'},
                                                   {'code': 1, 'name': 'b'}]),
                             ['fault code 1', 'defined twice']),
    # values
    'scale 0': (_set('parameters.1.scale', 0), ['parameters.1.scale', 'should not be valid']),
    'address above 16 bits': (_set('parameters.2.address', 0x10000),
                              ['parameters.2.address', '65536', 'maximum of 65535']),
    'negative address': (_set('parameters.2.address', -5),
                         ['parameters.2.address', 'minimum of 0']),
    'address not a number': (_set('parameters.2.address', '0x1002'), ['address']),
    'scale not a number': (_set('parameters.1.scale', 'tenth'), ['scale', 'tenth']),
    'bad value type': (_set('parameters.1.type', 'float64'), ['float64', 'uint16']),
    'bad access': (_set('parameters.1.access', 'rx'), ['rx', 'rw_stopped']),
    'bad speed unit': (_set('velocity.setpoint_unit', 'furlongs'), ['furlongs', 'percent']),
    'bad flag rule': (_set('flags.fault.rule', 'odd'), ['odd', 'nonzero']),
    'unsupported schema': (_set('schema', 2), ['schema']),
    'every below 1': (_set('monitor.fault_code', {'code': 'P0.03', 'every': 0}),
                      ['monitor.fault_code.every', 'minimum of 1']),
    # cross-checks
    'flag on undefined signal': (_set('flags.running', {'signal': 'run_flag', 'rule': 'nonzero'}),
                                 ['flags.running', "'run_flag'", 'monitor does not define']),
    'command direction without reverse': (_set('velocity.direction', 'command'),
                                          ['run_reverse']),
}


@pytest.mark.parametrize('mutate, expected', REJECTIONS.values(), ids=REJECTIONS.keys())
def test_loader_rejects(write_profile, mutate, expected):
    path = write_profile(mutate)
    with pytest.raises(ProfileError) as info:
        load_profile_file(path)
    message = str(info.value)
    for fragment in expected:
        assert fragment in message, f'{fragment!r} not in {message!r}'


@pytest.mark.parametrize('action', ['run', 'stop', 'fault_reset'])
def test_loader_requires_the_basic_commands(write_profile, action):
    path = write_profile(_delete(f'control.values.{action}'))
    with pytest.raises(ProfileError, match=f"control.values: '{action}' is a required property"):
        load_profile_file(path)


def test_loader_accepts_optional_commands(write_profile):
    def add(data):
        data['control']['values'].update({'run_reverse': 3, 'disable': 4})
        data['velocity']['direction'] = 'command'
    profile = load_profile_file(write_profile(add))
    assert profile.velocity.direction is DirectionMode.COMMAND
    assert profile.control.values['run_reverse'] == 3


def test_loader_rejects_bad_files(tmp_path):
    with pytest.raises(ProfileError, match='cannot read'):
        load_profile_file(tmp_path / 'absent.yaml')
    broken = tmp_path / 'broken.yaml'
    broken.write_text('schema: 1\nname: [unclosed\n', encoding='utf-8')
    with pytest.raises(ProfileError, match='not valid YAML'):
        load_profile_file(broken)
    scalar = tmp_path / 'scalar.yaml'
    scalar.write_text('42\n', encoding='utf-8')
    with pytest.raises(ProfileError, match='expected a mapping'):
        load_profile_file(scalar)


def test_unknown_profile_name_lists_the_shipped_ones():
    with pytest.raises(ProfileError) as info:
        load_profile('no_such_drive')
    assert 'no_such_drive' in str(info.value)
    for name in SHIPPED:
        assert name in str(info.value)


def test_load_profile_accepts_a_path(write_profile):
    assert load_profile(str(write_profile())).name == 'mini'


MALFORMED = {
    'every not a number': _set('monitor.fault_code', {'code': 'P0.03', 'every': 'often'}),
    'bits not a pair': _set('monitor.fault_code', {'code': 'P0.03', 'bits': 3}),
    'options as a list': _set('parameters.0.options', ['stop', 'run']),
    'command value not a number': _set('control.values.run', 'go'),
}


@pytest.mark.parametrize('mutate', MALFORMED.values(), ids=MALFORMED.keys())
def test_loader_reports_malformed_values_as_profile_errors(write_profile, mutate):
    """Values of the wrong shape are ProfileErrors too, never a bare ValueError/TypeError."""
    path = write_profile(mutate)
    with pytest.raises(ProfileError, match='mini.yaml'):
        load_profile_file(path)



# --- Parameter.to_raw ---------------------------------------------------------------------

@pytest.fixture
def percent() -> Parameter:
    return Parameter(code='P1', address=0, description='setpoint', type=ValueType.INT16,
                     scale=0.1, unit='%', minimum=-100.0, maximum=100.0)


@pytest.mark.parametrize('value, raw', [
    (0.0, 0), (12.5, 125), (-12.5, -125), (100.0, 1000), (-100.0, -1000),
    (0.3, 3),          # 0.3 / 0.1 = 2.9999999999999996: float noise is not a resolution error
    (33.3, 333), (7, 70),
])
def test_to_raw_in_range(percent, value, raw):
    result = percent.to_raw(value)
    assert result == raw and isinstance(result, int)
    assert percent.from_raw(result) == pytest.approx(value)


@pytest.mark.parametrize('value', [-100.1, -1000.0, -1e9])
def test_to_raw_below_minimum(percent, value):
    with pytest.raises(ParameterError, match='below the minimum -100%'):
        percent.to_raw(value)


@pytest.mark.parametrize('value', [100.1, 250.0, 1e9])
def test_to_raw_above_maximum(percent, value):
    with pytest.raises(ParameterError, match='above the maximum 100%'):
        percent.to_raw(value)


@pytest.mark.parametrize('value', [math.nan, math.inf, -math.inf])
def test_to_raw_not_finite(percent, value):
    with pytest.raises(ParameterError, match='not a finite number'):
        percent.to_raw(value)


@pytest.mark.parametrize('value', [1.25, 0.05, -99.99, 12.34])
def test_to_raw_not_a_multiple_of_the_resolution(percent, value):
    with pytest.raises(ParameterError, match='not a multiple of the resolution 0.1%'):
        percent.to_raw(value)


def test_to_raw_options():
    mode = Parameter(code='B0.13', address=0, description='mode',
                     options={0: 'invalid', 1: 'valid', 10: 'Modbus'})
    assert mode.to_raw(10) == 10
    assert mode.to_raw(0) == 0
    assert mode.option_text(10) == 'Modbus'
    assert mode.option_text(5) == ''
    with pytest.raises(ParameterError) as info:
        mode.to_raw(5)
    assert 'not one of the options' in str(info.value)
    assert '0 (invalid), 1 (valid), 10 (Modbus)' in str(info.value)


@pytest.mark.parametrize('value_type, good, bad', [
    (ValueType.INT16, [-32768, 0, 32767], [-32769, 32768]),
    (ValueType.UINT16, [0, 65535], [-1, 65536]),
    (ValueType.INT32, [-(1 << 31), (1 << 31) - 1], [-(1 << 31) - 1, 1 << 31]),
    (ValueType.UINT32, [0, (1 << 32) - 1], [-1, 1 << 32]),
    (ValueType.INT8, [-128, 127], [-129, 128]),
    (ValueType.UINT8, [0, 255], [-1, 256]),
])
def test_to_raw_type_bounds(value_type, good, bad):
    parameter = Parameter(code='X', address=0, description='unbounded', type=value_type)
    for value in good:
        assert parameter.to_raw(value) == value
    for value in bad:
        with pytest.raises(ParameterError, match=f'does not fit {value_type.value}'):
            parameter.to_raw(value)


def test_to_raw_type_bounds_apply_after_scaling():
    # 3276.7 is the largest int16 value at 0.1 per LSB.
    parameter = Parameter(code='X', address=0, description='d', type=ValueType.INT16,
                          scale=0.1)
    assert parameter.to_raw(3276.7) == 32767
    with pytest.raises(ParameterError, match='does not fit int16'):
        parameter.to_raw(3276.8)


def test_value_type_layout():
    assert ValueType.UINT16.register_count == 1 and ValueType.INT32.register_count == 2
    assert ValueType.INT16.bounds == (-32768, 32767)
    assert ValueType.UINT32.bounds == (0, 4294967295)


@pytest.mark.parametrize('name', SHIPPED)
def test_values_come_on_the_resolution_without_float_noise(name):
    """3 x 0.1 s reads as 0.3 s (it read 0.30000000000000004), and goes back to 3."""
    profile = shipped_profile(name)
    for parameter in profile.parameters.values():
        for raw in (1, 3, 7, 123):
            value = parameter.from_raw(raw)
            assert value == float(f'{raw * parameter.scale:.12g}'), (parameter.code, value)
            if parameter.maximum is not None and parameter.minimum is not None and \
                    parameter.minimum <= value <= parameter.maximum and not parameter.options:
                assert parameter.to_raw(value) == raw, parameter.code


@pytest.mark.parametrize(('name', 'lasting', 'passing'), [
    ('boneng_am', {1, 2, 3, 4, 5, 6}, {10, 11}),        # its 05/06: read only, only stopped
    ('boneng_mh', {4, 5, 6, 8, 9}, {10, 11}),
    ('imo_hd2', {4, 5, 6, 7, 8, 9}, {10, 11}),          # 09: system locked (password)
    ('kinco_ec', {1, 2, 3, 4}, {5, 6, 10, 11}),         # the manual lists the standard 1-4
])
def test_an_exception_code_passes_only_where_the_standard_says_so_and_the_manual_agrees(
        name, lasting, passing):
    """Busy and a gateway's codes pass (a failed exchange); a manual's own meaning lasts."""
    modbus = shipped_profile(name).modbus
    assert {c for c in lasting | passing if modbus.lasting_refusal(c)} == lasting


def test_a_code_whose_meaning_only_a_write_can_have_passes_on_a_read():
    """A code whose manual meaning only a write can have passes when it answers a read.

    The AM's 06 is 'modify only while stopped': to a status read it is the
    standard's busy (it blocked the drive until a restart), to a write the AM's
    own refusal.
    """
    modbus = shipped_profile('boneng_am').modbus
    assert modbus.lasting_refusal(6, write=True) and not modbus.lasting_refusal(6, write=False)
    assert modbus.lasting_refusal(2, write=False)          # illegal address: lasting anyway


def test_objects_are_found_as_index_and_subindex_too():
    profile = load_profile('cia402_velocity')
    for key in ('0x6083', '0x6083:00', '0X6083:0x00', ' 0x6083:0 ', 'profile_acceleration'):
        assert profile.parameter(key).code == '0x6083', key
    with pytest.raises(ParameterError, match=r"objects as 0xINDEX or 0xINDEX:SUBINDEX.*"
                                             r"0x6083 unquoted in YAML is the number 24707: "
                                             r"quote it, '0x6083'"):
        profile.parameter('24707')
    with pytest.raises(ParameterError, match='unknown parameter'):
        profile.parameter('0x6083:01')          # no such subindex
