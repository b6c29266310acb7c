"""Drive verbs over EtherCAT (CoE, CiA 402): a profile's ``ethercat`` section + a transport.

Implements the ``vfd_ros2.drives.base.Drive`` protocol, so the controller, the
bus and the nodes are the same as for Modbus and CANopen. At the segment's
start the transport identifies the slave (vendor/product from the profile
against the SII), writes the PDO assignment/mapping and the mode of operation
at PRE-OP and brings it to OP; afterwards each control cycle writes the RxPDO
bytes (controlword + target velocity) that the segment's process-data thread
sends every ``cycle_time``, and each poll decodes the TxPDO bytes it received:
no mailbox traffic per cycle. Parameters go over SDO, either each parameter's
own object or the drive's function-code window (IMO 0x2000-0x2003).

The CiA 402 state machine is the one CANopen drives use (``drives.cia402``).
Host death is covered by the slave's SM (process-data) watchdog, set from
``drive_comm_timeout``: when frames stop, the drive stops by itself.
"""

from __future__ import annotations

import logging
import math
import struct
from typing import Any, Callable, ClassVar, Mapping

from ..errors import ParameterError, ProfileError, ProtocolException, TransportError
from ..profiles import (
    NO_FAULT,
    CanObject,
    CommissioningWrite,
    EmcyFault,
    FaultInfo,
    Parameter,
    ParameterAccess,
    PersistenceKind,
    Profile,
    ValueType,
    describe_fault,
)
from ..protocol.cia402 import Command, State
from ..protocol.scaling import VelocityScaling
from ..transports.base import TransportParameter
from ..transports.ethercat import (
    Emergency,
    EthercatTransport,
    PdoConfiguration,
    SlaveSetup,
)
from .base import (
    HOST_LOSS_JITTER,
    DriveOnLink,
    HostLossProtection,
    ObjectDictionaryParameters,
    Reading,
    beyond_register,
)
from .canopen import GENERIC_ERROR, cia_fault
from .cia402 import Cia402Control

log = logging.getLogger(__name__)

_FORMATS = {
    ValueType.UINT8: '<B', ValueType.INT8: '<b', ValueType.UINT16: '<H',
    ValueType.INT16: '<h', ValueType.UINT32: '<I', ValueType.INT32: '<i',
}
#: the longest SM watchdog an ESC holds with the default divider (65535 x 100 us)
WATCHDOG_MAX_S = 6.5535


def pack(value_type: ValueType, raw: int) -> bytes:
    return struct.pack(_FORMATS[value_type], raw)


def unpack(value_type: ValueType, data: bytes) -> int:
    size = struct.calcsize(_FORMATS[value_type])
    if len(data) < size:
        raise TransportError(f'{len(data)} bytes where a {value_type.value} takes {size}')
    return struct.unpack(_FORMATS[value_type], data[:size])[0]


class EthercatDrive(DriveOnLink, ObjectDictionaryParameters):
    """One CiA 402 drive on an EtherCAT segment, driven through its profile."""

    #: a profile's ``transports`` entries this class can drive (its ``ethercat`` section)
    profile_transports: ClassVar[tuple[str, ...]] = ('ethercat',)

    settings: ClassVar[tuple[TransportParameter, ...]] = (
        TransportParameter('velocity_scale', 0.0, "rpm per count of the target/actual velocity "
                           "objects; 0 = the profile's"),
        TransportParameter('transition_timeout', 1.0, 's a CiA 402 transition may take before '
                           'it is reported as stuck'),
        TransportParameter('station_alias', 0, 'find the slave by its configured station '
                           'alias (SII) instead of its position; 0 = transport.unit_id is the '
                           'position (1 = first slave)'),
    )

    @classmethod
    def link_settings(cls, profile: Profile, settings: Mapping[str, Any]) -> dict[str, Any]:
        """Return the ``transport.*`` settings as given (the segment's are the NIC's)."""
        if profile.ethercat is None:
            raise ProfileError(f'profile {profile.name} has no ethercat section')
        return dict(settings)

    def __init__(self, profile: Profile, transport: EthercatTransport, unit_id: int,
                 scaling: VelocityScaling, settings: Mapping[str, Any] | None = None,
                 owns_transport: bool = True) -> None:
        if profile.ethercat is None:
            raise ProfileError(f'profile {profile.name} has no ethercat section')
        if not isinstance(transport, EthercatTransport):
            raise ParameterError('EthercatDrive needs an EthercatTransport')
        # the objects only this bus reaches (e.g. the BONENG MH EC's CiA 402 ramps) join
        # the parameters the services know
        self.profile = profile.extended(profile.ethercat.parameters)
        self.transport = transport
        self.owns_transport = owns_transport
        self.unit_id = unit_id
        self.scaling = scaling
        self.spec = spec = profile.ethercat
        self.objects = spec.objects
        values = {p.name: p.default for p in self.settings}
        values.update(settings or {})
        self.velocity_scale = float(values['velocity_scale']) or \
            self.objects.target_velocity.scale
        self.cia = Cia402Control(self.hardware_id, float(values['transition_timeout']),
                                 self.objects.stop_action)
        self._bits = self.objects.controlword_bits
        self._tx: list[tuple[str, CanObject, int]] = []      # role, object, byte offset
        offset = 0
        for role, obj in spec.tx_entries:
            self._tx.append((role, obj, offset))
            offset += obj.type.bits // 8
        input_size = offset
        output_size = sum(obj.type.bits // 8 for obj in spec.rx_entries)
        mappings = {} if spec.fixed_mapping else {
            spec.rx_pdos[0]: tuple(obj.mapping for obj in spec.rx_entries),
            spec.tx_pdos[0]: tuple(obj.mapping for _, obj in spec.tx_entries)}
        startup = ()
        if self.objects.mode_of_operation is not None:
            mode = self.objects.mode_of_operation
            startup = ((mode.index, mode.subindex, pack(mode.type, self.objects.mode_value)),)
        ident = spec.identity
        transport.attach(SlaveSetup(
            position=unit_id,
            pdos=PdoConfiguration(spec.rx_pdos, spec.tx_pdos, mappings),
            output_size=output_size, input_size=input_size,
            safe_outputs=self._outputs(int(Command.DISABLE_OPERATION), 0),
            vendor_id=ident.vendor_id, product_code=ident.product_code,
            device_name=ident.device_name, fixed_mapping=spec.fixed_mapping, startup=startup,
            sync_cycles_s=tuple(c / 1e6 for c in spec.sync_cycles_us), dc=spec.dc,
            free_run=spec.free_run, alias=int(values['station_alias'])))
        self.last_setpoint_raw = 0
        #: the host-loss protection configure() found in the slave (None: not connected)
        self.protection_applied: HostLossProtection | None = None
        #: the fault the drive raises by itself when the host falls silent
        self.own_absence_fault = spec.comm_fault
        self._configured = False
        self._values: dict[str, int] = {}
        self._last_controlword: int | None = None
        self._emcy_fault: FaultInfo = NO_FAULT
        self._read_code: int | None = None       # 0x603F read over SDO for this fault
        self._was_faulted = False
        # the last emergency's meaning, kept across a reconnect: after a link loss the
        # fault is still the one the emergency named (0x603F only has its CiA code)
        self._last_emcy: FaultInfo = NO_FAULT

    # --- link -------------------------------------------------------------------------

    @property
    def state(self) -> State | None:
        return self.cia.state

    def open(self) -> None:
        self.transport.open_slave(self.unit_id)

    def close(self) -> None:
        self._configured = False
        self.transport.close_slave(self.unit_id)

    def cycle_seconds(self) -> float:
        return 0.0                       # the process-data thread moves the bytes

    def connect_seconds(self) -> float:
        return 0.0

    def action_seconds(self) -> float:
        # a service action: up to four SDO exchanges (a function-code write is two
        # downloads and two uploads), each a few process-data cycles on a healthy segment
        return 4 * 4 * self.transport.settings.cycle_time_s

    def host_loss_plan(self, requested: float, interval: float) -> HostLossProtection:
        """Plan the SM watchdog: the drive stops when process data stops (no I/O).

        The process-data thread sends every ``cycle_time`` whatever the control
        rate, so the minimum is two cycles plus the host's jitter; the ESC holds
        at most 6.5535 s. Set when the segment starts; configure() reads it back.
        """
        mechanism = (f'SM watchdog (process data) of slave {self.unit_id} + stale RxPDO '
                     'replaced by disable operation')
        if requested == 0:
            self.transport.set_watchdog(self.unit_id, 0.0)
            return HostLossProtection(requested=0.0, note='off, as drive_comm_timeout 0 asks')
        cycle = self.transport.settings.cycle_time_s
        minimum = 2 * cycle + HOST_LOSS_JITTER
        # The process-data thread outlives a hung control loop and would keep sending
        # its last command: outputs the loop has not refreshed for this long (two of its
        # cycles + jitter at least) are replaced by disable operation + velocity 0.
        hold = max(requested, 2 * interval + HOST_LOSS_JITTER)
        minimum = max(minimum, hold if requested else minimum)
        value = min(max(requested, minimum), WATCHDOG_MAX_S)
        value = math.ceil(value * 10000 - 1e-6) / 10000          # 100 us steps
        notes = []
        if value > requested + 1e-9:
            notes.append(f'raised from {requested:g} s: frames come every {cycle * 1000:g} ms, '
                         f'commands every {interval * 1000:.0f} ms, and the host may be late')
        elif value < requested - 1e-9:
            notes.append(f'the ESC holds at most {WATCHDOG_MAX_S:g} s')
        self.transport.set_watchdog(self.unit_id, value, hold_s=value)
        return HostLossProtection(mechanism, value, requested, '; '.join(notes))

    def forget_state(self) -> None:
        self._configured = False
        self.cia.reset()
        self._values.clear()
        self._last_controlword = None
        self._emcy_fault = self._last_emcy     # kept: see __init__
        self._read_code = None
        self._was_faulted = False

    def configure(self, protection: HostLossProtection,
                  apply_commissioning: bool) -> list[str]:
        """Commission over SDO, read back the SM watchdog; the slave is in OP already."""
        problems: list[str] = []
        if apply_commissioning:
            problems += self._commission()
        self.protection_applied = self._check_protection(protection, problems)
        self._decode(self.transport.read_inputs(self.unit_id))
        self._configured = True
        return problems

    def _check_protection(self, protection: HostLossProtection,
                          problems: list[str]) -> HostLossProtection:
        held = self.transport.watchdog(self.unit_id)
        if held is None or not protection.active:
            return protection
        if held <= 0:
            problems.append(f'slave {self.unit_id} holds no SM watchdog although '
                            f'{protection.timeout:g} s was set')
            return HostLossProtection(requested=protection.requested, note=(
                'the SM watchdog is off in the slave: only the host watchdog stops the motor, '
                'not a dead host'))
        if abs(held - protection.timeout) > 0.0002:
            note = f'{protection.timeout:g} s asked, the slave holds {held:g} s'
            return HostLossProtection(protection.mechanism, held, protection.requested,
                                      '; '.join(n for n in (protection.note, note) if n))
        return protection

    def _commission(self) -> list[str]:
        problems = []
        for item in self.spec.commissioning:
            parameter = self.profile.parameter(item.code)
            try:
                raw = parameter.to_raw(item.value)
                if self._read_raw(parameter) != raw:
                    self._write_raw(parameter, raw, persistent=True)
            except (ParameterError, ProtocolException) as exc:
                problems.append(f'{item.code} = {item.value:g}: {exc}')
        return problems

    # --- control ----------------------------------------------------------------------

    def _outputs(self, controlword: int, velocity_raw: int) -> bytes:
        return pack(self.objects.controlword.type, controlword | self._bits) + \
            pack(self.objects.target_velocity.type, velocity_raw)

    def _send(self, controlword: int, velocity_raw: int) -> None:
        self.transport.write_outputs(self.unit_id, self._outputs(controlword, velocity_raw))
        self._last_controlword = controlword
        self.last_setpoint_raw = velocity_raw

    @property
    def commissioning(self) -> tuple[CommissioningWrite, ...]:
        """What this drive writes at connect: the EtherCAT start-up list, not Modbus's."""
        return tuple(self.spec.commissioning)

    def setpoint_beyond(self, velocity: float) -> str:
        """Return why ``velocity`` would be clamped in the target velocity ('' if not)."""
        native = self.scaling.to_native(velocity, self.objects.velocity_unit)
        return beyond_register(velocity, native / self.velocity_scale,
                               *self.objects.target_velocity.type.bounds,
                               f'0x{self.objects.target_velocity.index:04X}',
                               'drive.velocity_scale (rpm per count) and gear_ratio')

    def _native(self, velocity: float) -> int:
        native = self.scaling.to_native(velocity, self.objects.velocity_unit)
        low, high = self.objects.target_velocity.type.bounds
        return min(max(round(native / self.velocity_scale), low), high)

    def apply(self, velocity: float, run: bool, idle_action: str = 'stop',
              reassert: bool = False) -> None:
        """One control cycle: the RxPDO bytes (controlword + target velocity).

        The process data carries both every cycle, so ``reassert`` needs nothing more.
        """
        if not self._configured:
            self._decode(self.transport.read_inputs(self.unit_id))   # state before commanding
        controlword = self.cia.controlword(run, idle_action)
        moving = run and self.cia.enabled
        self._send(controlword, self._native(velocity) if moving else 0)

    def send_command(self, action: str) -> None:
        """Send one command now (fault_reset: a rising edge of bit 7)."""
        for word in self.cia.action_words(action, self._last_controlword):
            self._send(word, 0)
            # the slave must see each word (an edge, a one-off command) before the
            # next control cycle may overwrite it, however late that cycle runs
            self.transport.wait_cycles(2)

    def write_setpoint_parameter(self, code: str, raw: int) -> None:
        self._write_raw(self.profile.parameter(code), raw, persistent=False)

    # --- status -----------------------------------------------------------------------

    def _decode(self, data: bytes) -> None:
        for role, obj, offset in self._tx:
            self._values[role] = unpack(obj.type, data[offset:])
        self.cia.update(self._values.get('status_word'))

    def poll(self, cycle: int, preempt: Callable[[], None] | None = None) -> Reading:
        """Decode the last TxPDO and the emergencies; raise if the slave fell silent."""
        self._decode(self.transport.read_inputs(self.unit_id))
        for emcy in self.transport.take_emergencies(self.unit_id):
            self._take_emcy(emcy)
        faulted = self.cia.faulted
        if self._was_faulted and not faulted:
            # left FAULT (a reset): what named the old fault is history. An emergency
            # that arrives before the statusword shows the fault is kept.
            self._emcy_fault = self._last_emcy = NO_FAULT
            self._read_code = None
        self._was_faulted = faulted
        return self._reading()

    def describe_code(self, code: int, register: int | None = None,
                      data: bytes = b'') -> FaultInfo:
        """Name a CiA 301/402 error code (EMCY or 0x603F) in the profile's own fault terms."""
        for mapping in self.spec.emcy_faults:
            if mapping.error_code == code:
                return describe_fault(self.profile.faults, mapping.fault, mapping.subcode)
        if self.spec.emcy_fault is EmcyFault.MANUFACTURER_BYTE and data[:1] not in (b'', b'\0'):
            return describe_fault(self.profile.faults, data[0])
        return cia_fault(code, register)

    def _take_emcy(self, emcy: Emergency) -> None:
        if not emcy.error_code & 0xFF00:
            log.info('%s EMCY error reset', self.hardware_id)
            return
        info = self.describe_code(emcy.error_code, emcy.error_register, emcy.data)
        log.warning('%s EMCY 0x%04X register 0x%02X data %s: %s %s', self.hardware_id,
                    emcy.error_code, emcy.error_register, emcy.data.hex(' '), info.display,
                    info.name)
        self._emcy_fault = self._last_emcy = info

    def _fault(self) -> FaultInfo:
        if not self.cia.faulted:
            return NO_FAULT
        code = self._values.get('fault_code', 0)
        if code:
            return self.describe_code(code)
        if self._emcy_fault.active:
            return self._emcy_fault
        if self._read_code is None:
            # no emergency named it and 0x603F is not in the process data: ask once
            try:
                self._read_code = unpack(ValueType.UINT16,
                                         self.transport.sdo_read(self.unit_id, 0x603F, 0))
            except (TransportError, ProtocolException) as exc:
                log.info('%s: 0x603F not readable: %s', self.hardware_id, exc)
                self._read_code = 0
            # the mailbox exchange collects an emergency that was on its way: it names
            # the fault better than 0x603F
            for emcy in self.transport.take_emergencies(self.unit_id):
                self._take_emcy(emcy)
            if self._emcy_fault.active:
                return self._emcy_fault
        return self.describe_code(self._read_code or GENERIC_ERROR)

    def _reading(self) -> Reading:
        reading = Reading(stuck=self.cia.stuck)
        monitor = self.objects.monitor
        for role, raw in self._values.items():
            scale = self.velocity_scale if role == 'motor_speed' else monitor[role].scale
            reading.values[role] = raw * scale
        status = self._values.get('status_word')
        if status is not None:
            reading.raw_words[f'0x{self.objects.statusword.index:04X}'] = status
        if self.cia.state is not None:
            reading.raw_words['cia402_state'] = int(self.cia.state)
        reading.flags = self.cia.flags(status, reading.values.get('motor_speed', 0.0))
        reading.fault = self._fault()
        speed = reading.values.get('motor_speed')
        if speed is not None:
            reading.measured_velocity = self.scaling.from_native(speed,
                                                                 self.objects.velocity_unit)
        return reading

    # --- parameters (SDO) ---------------------------------------------------------------

    def _reachable(self, parameter: Parameter) -> Parameter:
        if parameter.index is not None:
            return parameter
        window = self.spec.function_codes
        if self.spec.parameter_access is ParameterAccess.FUNCTION_CODES and window is not None \
                and parameter.address >= 0:
            low, high = window.addresses
            if not low <= parameter.address <= high:
                # (the drive answered "illegal data address", read as a Modbus reply:
                # outside audit)
                raise ParameterError(
                    f'{parameter.code} ({parameter.description}) at 0x{parameter.address:04X} '
                    f'is not a function code: the EtherCAT card reaches function codes only '
                    f'(0x{low:04X}-0x{high:04X} through 0x{window.read:04X}-'
                    f'0x{window.write_response:04X}); not reachable over EtherCAT')
            if parameter.register_count != 1:
                raise ParameterError(f'{parameter.code} is two registers wide: the function-code '
                                     'window carries 16 bits')
            return parameter
        raise ParameterError(f'{parameter.code} ({parameter.description}) has no CoE object: '
                             'not reachable over EtherCAT')

    def _window_answer(self, parameter: Parameter, response: int, what: str) -> int:
        window = self.spec.function_codes
        answer = unpack(ValueType.UINT32, self.transport.sdo_read(self.unit_id, response, 0))
        status, value = answer >> 16, answer & 0xFFFF
        if status != window.success:
            text = window.errors.get(value, 'error code not in the manual')
            raise ProtocolException(value, text, f'{what} {parameter.code} (0x{response:04X} = '
                                    f'0x{answer:08X})')
        if parameter.type.signed and value & 0x8000:
            value -= 0x10000
        return value

    def _read_raw(self, parameter: Parameter) -> int:
        parameter = self._reachable(parameter)
        if parameter.index is not None:
            return unpack(parameter.type, self.transport.sdo_read(
                self.unit_id, parameter.index, parameter.subindex))
        window = self.spec.function_codes
        self.transport.sdo_write(self.unit_id, window.read, 0,
                                 pack(ValueType.UINT32, parameter.address << 16))
        return self._window_answer(parameter, window.read_response, 'read of')

    def _write_raw(self, parameter: Parameter, raw: int, persistent: bool) -> None:
        parameter = self._reachable(parameter)
        if parameter.index is not None:
            self.transport.sdo_write(self.unit_id, parameter.index, parameter.subindex,
                                     pack(parameter.type, raw))
            return
        window = self.spec.function_codes
        address = parameter.address
        persistence = self.profile.modbus.persistence
        if persistence.kind is PersistenceKind.ADDRESS_FLAG and not persistent and any(
                low <= address <= high for low, high in persistence.applies_to):
            address |= persistence.flag                   # RAM only (e.g. IMO 8007H)
        self.transport.sdo_write(self.unit_id, window.write, 0, pack(
            ValueType.UINT32, (address << 16) | (raw & 0xFFFF)))
        self._window_answer(parameter, window.write_response, 'write of')

    def _write_note(self, parameter: Parameter, persistent: bool) -> str:
        if parameter.index is not None:
            return super()._write_note(parameter, True)
        return 'EEPROM' if persistent else 'RAM'
