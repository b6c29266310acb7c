"""CANopen fault decoding (pure): the status decides, the code names, CiA codes as 0x...."""

from __future__ import annotations

from vfd_ros2.drives.canopen import GENERIC_ERROR, cia_fault, decode_fault
from vfd_ros2.profiles import NO_FAULT, describe_fault, load_profile

CIA = load_profile('cia402_velocity').faults
KINCO = load_profile('kinco_ec').faults


def test_a_code_without_the_fault_bit_is_no_fault():
    # 0x603F = 0x3210 kept after a reset, statusword 0x0023 (switched on): not faulted
    assert decode_fault(False, 0x3210, NO_FAULT, CIA, cia_codes=True) is NO_FAULT
    # ... even with an EMCY still active
    assert decode_fault(False, 0, cia_fault(0x8130), CIA, cia_codes=True) is NO_FAULT


def test_the_code_names_the_fault_in_cia_notation():
    fault = decode_fault(True, 0x8250, NO_FAULT, CIA, cia_codes=True)
    assert (fault.code, fault.display, fault.name, fault.known) == \
        (0x8250, '0x8250', 'RPDO timeout', True)
    assert describe_fault(CIA, 0x3210).display == '0x3210'     # not 3210h (12816), not E12816


def test_without_a_code_the_emcy_then_the_generic_error_names_it():
    emcy = describe_fault(CIA, 0x2310)
    assert decode_fault(True, 0, emcy, CIA, cia_codes=True) is emcy
    generic = decode_fault(True, 0, NO_FAULT, CIA, cia_codes=True)
    assert (generic.code, generic.display, generic.name) == (GENERIC_ERROR, '0x1000',
                                                             'Generic error')
    # A profile whose table holds its own numbers (Kinco E001..) shows CiA codes as CiA codes.
    kinco = decode_fault(True, 0, NO_FAULT, KINCO, cia_codes=False)
    assert kinco.display == '0x1000' and not kinco.known


def test_a_fault_keeps_its_name_when_the_emcy_reset_comes_before_the_status_word():
    """EMCY 0000 first, the status word still in fault: not the generic error for a cycle."""
    named = describe_fault(CIA, 0x2310)
    before = decode_fault(True, 0, named, CIA, cia_codes=True)
    assert decode_fault(True, 0, NO_FAULT, CIA, cia_codes=True, before=before) is named
    assert decode_fault(False, 0, NO_FAULT, CIA, cia_codes=True, before=before) is NO_FAULT
    # a code the drive reports still names it
    assert decode_fault(True, 0x8250, NO_FAULT, CIA, cia_codes=True, before=before).code == \
        0x8250


def test_cia_codes_outside_the_profile_table():
    fault = cia_fault(0x8130, register=0x11)
    assert fault.display == '0x8130' and fault.name == 'Monitoring error (CiA 301 class)'
    assert 'error register 0x11' in fault.cause and not fault.known
    assert describe_fault(KINCO, 8).display == 'E008'           # the drive's own numbers stay
