"""Unit tests of the transport plugin registry, with a fake installed plugin (no I/O)."""

from __future__ import annotations

import math
import sys
from types import SimpleNamespace

import pytest

from unit_support import MemoryTransport, shipped_profile
from vfd_ros2.drives import modbus as modbus_drive
from vfd_ros2.drives.modbus import ModbusDrive
from vfd_ros2.errors import CommTimeout, ProtocolException, TransportLoadError
from vfd_ros2.protocol.scaling import VelocityScaling
from vfd_ros2.transports import (
    BUILTIN_TRANSPORTS,
    RegisterTransport,
    TransportParameter,
    available_transports,
    load_transport_class,
)

# --- built-in transports ---------------------------------------------------------------------


@pytest.mark.parametrize('name, first_setting', [
    ('modbus_rtu', 'port'),
    ('modbus_tcp', 'host'),
])
def test_builtin_transports_load(name, first_setting):
    cls = load_transport_class(name)
    assert isinstance(cls, type) and issubclass(cls, RegisterTransport)
    assert cls.__name__ == BUILTIN_TRANSPORTS[name].rpartition(':')[2]
    assert cls.parameters, 'a transport declares its settings'
    assert all(isinstance(p, TransportParameter) for p in cls.parameters)
    names = [p.name for p in cls.parameters]
    assert names[0] == first_setting
    assert 'timeout' in names
    assert len(set(names)) == len(names)
    assert all(p.description for p in cls.parameters)


def test_rtu_and_tcp_are_different_classes():
    assert load_transport_class('modbus_rtu') is not load_transport_class('modbus_tcp')


def test_builtins_are_available():
    available = available_transports()
    assert {'modbus_rtu', 'modbus_tcp'} <= set(available)
    assert available == sorted(available)


@pytest.mark.parametrize('name', ['modbus_udp', '', 'MODBUS_RTU', 'loopback'])
def test_unknown_transport(name):
    with pytest.raises(TransportLoadError) as info:
        load_transport_class(name)
    message = str(info.value)
    assert f'unknown transport {name!r}' in message
    assert 'modbus_rtu' in message and 'modbus_tcp' in message


# --- an entry-point plugin (plugin_support.py installs it into tmp_path) ----------------



def test_plugin_is_listed(plugin):
    available = available_transports()
    assert 'loopback' in available
    assert {'modbus_rtu', 'modbus_tcp'} <= set(available)
    assert available.count('modbus_rtu') == 1
    assert available == sorted(available)


def test_plugin_is_not_listed_without_its_distribution():
    assert 'loopback' not in available_transports()


def test_plugins_are_looked_up_again_when_the_path_changes(plugin, monkeypatch):
    """Lookups are kept per sys.path: a distribution put on the path later is found."""
    assert 'loopback' in available_transports()
    without = [entry for entry in sys.path if entry != str(plugin)]
    monkeypatch.setattr(sys, 'path', without)
    assert 'loopback' not in available_transports()
    monkeypatch.setattr(sys, 'path', [*without, str(plugin)])
    assert 'loopback' in available_transports()


def test_plugin_loads(plugin):
    cls = load_transport_class('loopback')
    assert cls.__name__ == 'LoopbackTransport'
    assert cls.__module__ == 'fake_vfd_plugin'
    assert issubclass(cls, RegisterTransport)
    assert [p.name for p in cls.parameters] == ['size']
    transport = cls.from_settings({'size': 10})
    transport.write_registers(1, 0x10, [5, 6])
    assert transport.read_registers(1, 0x0F, 4) == [0, 5, 6, 0]
    assert transport.stats.transactions == 2


def test_builtin_wins_over_a_plugin_of_the_same_name(plugin):
    cls = load_transport_class('modbus_rtu')
    assert cls.__module__ == 'vfd_ros2.transports.modbus'


def test_unknown_transport_lists_plugins(plugin):
    with pytest.raises(TransportLoadError) as info:
        load_transport_class('can_open')
    assert 'loopback' in str(info.value)


@pytest.mark.parametrize('name', ['not_a_transport', 'not_a_class'])
def test_plugin_that_is_not_a_transport(plugin, name):
    with pytest.raises(TransportLoadError) as info:
        load_transport_class(name)
    assert f"transport '{name}' is not a" in str(info.value)


def test_plugin_whose_module_fails_to_import(plugin):
    with pytest.raises(TransportLoadError) as info:
        load_transport_class('broken_import')
    message = str(info.value)
    assert "transport 'broken_import' cannot be loaded" in message
    assert 'vfd_ros2_dependency_that_is_not_installed' in message


def test_plugin_whose_class_is_missing(plugin):
    with pytest.raises(TransportLoadError, match="'missing_class' cannot be loaded"):
        load_transport_class('missing_class')


def test_plugin_whose_module_raises_on_import(plugin):
    with pytest.raises(TransportLoadError, match='explodes_on_import'):
        load_transport_class('explodes_on_import')


# --- contract: the drive layer works over any RegisterTransport --------------------------------

def words(value: int) -> int:
    """Return the register word of a signed 16-bit value (two's complement, by hand)."""
    return value + 0x10000 if value < 0 else value


def test_drive_polls_over_the_plugin_transport(plugin):
    profile = shipped_profile('boneng_am')
    transport = load_transport_class('loopback').from_settings({})
    scaling = VelocityScaling(gear_ratio=10.0, rated_speed_rpm=1330.0, pole_pairs=2)
    drive = ModbusDrive(profile, transport, 3, scaling)
    assert drive.hardware_id == 'boneng_am@loopback#3'

    regs = transport.registers
    regs[0x2003] = words(-2217)           # A00.03 output frequency: -22.17 Hz (0.01 Hz)
    regs[0x2006] = words(-665)            # A00.06 motor speed: -665 rpm
    regs[0x2008] = 1234                   # A00.08 output current: 12.34 A
    regs[0x200E] = 5400                   # A00.14 DC bus: 540.0 V (0.1 V)
    regs[0x200F] = words(-12)             # A00.15 heatsink: -12 degC
    regs[0x2100] = 35                     # A01.00 fault code
    regs[0x2101] = 3                      # A01.01 sub-code
    regs[0xE100] = 1                      # P01.00 ready for switch-on (idle readiness)
    regs[0xE101] = 1                      # P01.01 ready to run (the run command is on)
    regs[0xE102] = 1                      # P01.02 running

    drive.open()
    assert transport.is_open
    reading = drive.poll(0)

    assert reading.values['motor_speed'] == -665
    assert reading.values['output_frequency'] == pytest.approx(-22.17)
    assert reading.values['output_current'] == pytest.approx(12.34)
    assert reading.values['dc_bus_voltage'] == pytest.approx(540.0)
    assert reading.values['temperature'] == -12
    # -665 rpm at the motor through 10:1 = -66.5 rpm at the wheel.
    assert reading.measured_velocity == pytest.approx(-66.5 * 2 * math.pi / 60)
    assert reading.flags == {'ready': True, 'run_requested': True, 'running': True,
                             'fault': True, 'warning': False, 'reverse': True}
    assert reading.fault.display == 'E35.03'
    assert reading.fault.name == 'Communication exception'
    assert reading.raw_words == {'A00.00': 0, 'P01.00': 1, 'P01.01': 1, 'P01.02': 1}

    # The reads honour the profile's limits: at most 5 registers, never an
    # undocumented address (gaps_readable is false for this drive).
    reads = [r for r in transport.requests if r[0] == 'read']
    assert reads and all(r[1] == 3 for r in reads)
    for _, _, start, count in reads:
        assert 1 <= count <= profile.modbus.max_read_registers
        for address in range(start, start + count):
            assert profile.parameter_at(address) is not None, hex(address)


class RefusingTransport(MemoryTransport):
    """Registers in a dict; reads that cover a refused register get exception 2."""

    def __init__(self, refused: set[int]) -> None:
        super().__init__()
        self.refused = refused

    def read_registers(self, unit: int, address: int, count: int) -> list[int]:
        if self.refused & set(range(address, address + count)):
            self.requests.append(('refused', unit, address, count))
            raise ProtocolException(2, 'illegal data address')
        return super().read_registers(unit, address, count)


@pytest.mark.parametrize('motor_speed_readable', [True, False])
def test_values_only_shown_in_the_status_are_read_once_per_display_period(
        monkeypatch, motor_speed_readable):
    """The run and fault state and the speed are read every cycle; the rest once per status.

    Where the drive refuses the speed register, the output frequency gives the speed
    and is read every cycle instead.
    """
    profile = shipped_profile('boneng_am')
    address = {code: profile.parameter(code).address
               for code in ('A00.00', 'A00.06', 'A00.08', 'A01.00', 'P01.00')}
    transport = RefusingTransport(set() if motor_speed_readable else {address['A00.06']})
    drive = ModbusDrive(profile, transport, 1,
                        VelocityScaling(gear_ratio=10.0, rated_speed_rpm=1330.0, pole_pairs=2))
    clock = [100.0]
    monkeypatch.setattr(modbus_drive, 'time', SimpleNamespace(monotonic=lambda: clock[0]))
    drive.display_period = 0.03               # ~/status at 20 Hz, a cycle of 50 Hz
    transport.registers[address['A00.00'] + 3] = 123      # A00.03 output frequency
    read_in: dict[int, list[int]] = {}
    for cycle in range(10):
        transport.requests.clear()
        reading = drive.poll(cycle)
        for kind, _, start, count in transport.requests:
            for register in range(start, start + count) if kind == 'read' else ():
                read_in.setdefault(register, []).append(cycle)
        clock[0] += 0.02
    every_cycle = list(range(10))
    for code in ('A01.00', 'P01.00'):                     # fault, readiness and run flags
        assert read_in[address[code]] == every_cycle, code
    assert reading.values['output_frequency'] == pytest.approx(1.23)   # kept between reads
    if motor_speed_readable:
        assert read_in[address['A00.06']] == every_cycle
        assert read_in[address['A00.00']] == [0, 2, 4, 6, 8]       # state, output frequency
    else:
        # Cycle 0 finds the block refused, cycle 1 the speed register alone: from
        # then on the output frequency gives the speed, every cycle.
        assert 'motor_speed' in reading.unavailable
        assert read_in[address['A00.00']][-8:] == every_cycle[2:]
    drive.display_period = 0.0                # a status each cycle (or none known): all
    transport.requests.clear()
    drive.poll(11)
    assert address['A00.00'] in {r[2] for r in transport.requests if r[0] == 'read'}


def test_drive_writes_over_the_plugin_transport(plugin):
    profile = shipped_profile('boneng_am')
    transport = load_transport_class('loopback').from_settings({})
    scaling = VelocityScaling(gear_ratio=10.0, rated_speed_rpm=1330.0, pole_pairs=2)
    drive = ModbusDrive(profile, transport, 1, scaling)
    half_rated = 665.0 / 10.0 * 2 * math.pi / 60          # rad/s: 50 % of 1330 rpm
    drive.apply(half_rated, run=True)
    assert transport.registers[0xE721] == 500              # P07.33: 50.0 % at 0.1 %
    # Run needs a rising edge on this drive: 0 then 1 on P07.32.
    command_writes = [r[3] for r in transport.requests if r[:3] == ('write', 1, 0xE720)]
    assert command_writes == [0, 1]
    drive.apply(-half_rated, run=True)                     # direction by setpoint sign
    assert transport.registers[0xE721] == words(-500)
    assert [r[3] for r in transport.requests if r[:3] == ('write', 1, 0xE720)] == [0, 1]
    drive.apply(half_rated, run=False)                     # idle: zero setpoint, stop
    assert transport.registers[0xE721] == 0
    assert transport.registers[0xE720] == profile.control.values['stop']


class NameplateSilence(MemoryTransport):
    """A drive that does not answer (or refuses) the reads of some registers."""

    def __init__(self, silent: dict[int, Exception]) -> None:
        super().__init__()
        self.silent = silent

    def read_registers(self, unit: int, address: int, count: int) -> list[int]:
        for register in range(address, address + count):
            if register in self.silent:
                raise self.silent[register]
        return super().read_registers(unit, address, count)


@pytest.mark.parametrize('failure', [CommTimeout('no reply'), ProtocolException(2, 'refused')])
def test_a_nameplate_the_drive_does_not_give_never_keeps_it_offline(failure):
    # The nameplate check is advisory: an unanswered read of D00.04 failed the whole
    # connect, for ever, on a bus where the others came online (outside audit).
    from vfd_ros2.drives.base import HostLossProtection
    profile = shipped_profile('boneng_am')
    transport = NameplateSilence({0x5004: failure})
    drive = ModbusDrive(profile, transport, 1, VelocityScaling(
        gear_ratio=10.0, rated_speed_rpm=1500.0, rated_from_profile=True,
        pole_pairs_from_profile=True))
    drive.configure(HostLossProtection(), apply_commissioning=False)
    assert drive.nameplate_note == ''
    # Pole pairs unreadable: the node's own are taken, so a 60 Hz drive is still told.
    transport = NameplateSilence({0x5009: failure})
    transport.registers[0x5004] = 6000                      # D00.04 = 60.00 Hz
    drive = ModbusDrive(profile, transport, 1, VelocityScaling(
        gear_ratio=10.0, rated_speed_rpm=1500.0, rated_from_profile=True,
        pole_pairs_from_profile=True))
    drive.configure(HostLossProtection(), apply_commissioning=False)
    assert "the drive's nameplate (D00.04 60) makes a 100 % setpoint 1800 rpm" in \
        drive.nameplate_note
    # What the node was told by its integrator is not second-guessed.
    drive = ModbusDrive(profile, transport, 1, VelocityScaling(
        gear_ratio=10.0, rated_speed_rpm=1800.0, pole_pairs_from_profile=True))
    drive.configure(HostLossProtection(), apply_commissioning=False)
    assert drive.nameplate_note == ''
