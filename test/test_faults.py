"""Unit tests of fault descriptions (fault code -> the manual's words)."""

from __future__ import annotations

import pytest

from unit_support import shipped_profile
from vfd_ros2.profiles import FaultEntry, FaultSpec
from vfd_ros2.profiles.faults import NO_FAULT, describe_fault

TABLE = {
    35: FaultEntry(code=35, name='Communication exception', remedy='Check the cables.',
                   cause='The link was lost.',
                   subcodes={1: 'PC tool disconnected', 3: 'Modbus communication fault'}),
    7: FaultEntry(code=7, name='Input phase loss', remedy='Check the supply.',
                  cause='One phase is missing.'),
    12: FaultEntry(code=12, name='Earth fault', remedy='Check insulation.',
                   subcodes={2: 'leakage current too high'}),
}


def spec(display_format: str = 'E{code:02d}.{subcode:02d}') -> FaultSpec:
    return FaultSpec(code='A01.00', subcode='A01.01', display_format=display_format,
                     table=TABLE)


def test_code_zero_is_no_fault():
    info = describe_fault(spec(), 0)
    assert info == NO_FAULT
    assert not info.active and info.known
    assert info.display == '' and info.name == ''
    # Even a stray sub-code with code 0 means no fault.
    assert describe_fault(spec(), 0, 5) == NO_FAULT


def test_known_code_with_known_subcode():
    info = describe_fault(spec(), 35, 3)
    assert info.active and info.known
    assert (info.code, info.subcode) == (35, 3)
    assert info.display == 'E35.03'
    assert info.name == 'Communication exception'
    assert info.cause == 'Modbus communication fault. The link was lost.'
    assert info.remedy == 'Check the cables.'


def test_known_subcode_without_general_cause():
    info = describe_fault(spec(), 12, 2)
    assert info.cause == 'leakage current too high'
    assert info.name == 'Earth fault' and info.known


def test_known_code_with_unknown_subcode():
    info = describe_fault(spec(), 35, 9)
    assert info.known and info.name == 'Communication exception'
    assert info.display == 'E35.09'
    assert 'sub-code 9' in info.cause
    assert "not in the manual's list" in info.cause
    assert info.cause.endswith('The link was lost.')


def test_known_code_without_subcode_table():
    info = describe_fault(spec(), 7, 4)
    assert info.known and info.name == 'Input phase loss'
    assert info.cause == 'One phase is missing.'          # no sub-code list: no comment
    assert describe_fault(spec(), 35, 0).cause == 'The link was lost.'


@pytest.mark.parametrize('code, subcode', [(99, 0), (99, 4), (1, 1)])
def test_unknown_code(code, subcode):
    info = describe_fault(spec(), code, subcode)
    assert not info.known and info.active
    assert info.display == f'E{code:02d}.{subcode:02d}'
    assert info.name == f'unknown fault {info.display}'
    assert f'fault code {code}' in info.cause and f'sub-code {subcode}' in info.cause
    assert info.remedy == 'see the drive manual'


@pytest.mark.parametrize('display_format, expected', [
    ('E{code:02d}.{subcode:02d}', 'E07.01'),
    ('{code}.{subcode}', '7.1'),
    ('E{code:03d}', 'E007'),
    ('fault {code}', 'fault 7'),
    ('Err{code:X}', 'Err7'),
])
def test_display_formats(display_format, expected):
    assert describe_fault(spec(display_format), 7, 1).display == expected


@pytest.mark.parametrize('display_format', [
    'E{code:02d',          # unterminated field
    '{fault}',             # unknown field
    '{0}',                 # positional field
    '{code:s}',            # wrong format spec for an int
    '{code!z}',            # unknown conversion
    '}{',
])
def test_bad_display_format_never_raises(display_format):
    info = describe_fault(spec(display_format), 35, 3)
    assert info.display == '35.3'
    assert info.name == 'Communication exception' and info.known


@pytest.mark.parametrize('display_format', ['{code.nope}', '{code[0]}'])
def test_bad_display_format_with_field_access_never_raises(display_format):
    info = describe_fault(spec(display_format), 35, 3)
    assert info.display == '35.3'


def test_am_profile_fault():
    faults = shipped_profile('boneng_am').faults
    info = describe_fault(faults, 35, 3)
    assert info.display == 'E35.03'
    assert info.name == 'Communication exception'
    assert info.cause.startswith('Modbus communication fault')
    assert 'C02.04' in info.remedy
