"""Drive verbs over CANopen: a profile's ``canopen`` section plus a ``CanopenTransport``.

Implements the ``vfd_ros2.drives.modbus.Drive`` protocol, so the controller and the node
are the same as for Modbus. At connect everything is set up over SDO (PDO
mappings and transmission types, heartbeat, mode of operation, command source);
afterwards each control cycle sends one RPDO (control word + target velocity)
and each poll decodes the TPDOs the drive sent by itself: no SDO per cycle.

Two control styles, chosen by the profile's object set:
- ``cia402``: the CiA 402 state machine (``vfd_ros2.protocol.cia402``), walked one verified
  transition per cycle; the target velocity stays 0 until the drive reports
  Operation Enabled; fault reset is a rising edge of bit 7;
- ``command_word``: a manufacturer command word (Kinco 0x2A00: 0x07 run, ...).
"""

from __future__ import annotations

import logging
import math
import time
from typing import Any, Callable, ClassVar, Mapping

from ..errors import ParameterError, ProfileError, ProtocolException, TransportError
from ..profiles import (
    NO_FAULT,
    CanObject,
    ControlStyle,
    EmcyFault,
    FaultInfo,
    Parameter,
    Profile,
    StopAction,
    ValueType,
    describe_fault,
)
from ..protocol.cia402 import Command, Goal, State, StatusBit, decode_state, next_command
from ..protocol.scaling import VelocityScaling
from ..transports.base import TransportParameter, TransportStats
from ..transports.canopen import CanopenTransport, NmtCommand, NmtState
from .base import HOST_LOSS_JITTER, HostLossProtection, ParameterValue, Reading, check_write

log = logging.getLogger(__name__)

#: the CiA 301 generic error code, used when a drive reports FAULT without a code
GENERIC_ERROR = 0x1000
PDO_DISABLED = 0x80000000


def pack_pdo(items: list[tuple[CanObject, int]]) -> bytes:
    """Little-endian PDO payload of (object, raw value) pairs in mapping order."""
    value, shift = 0, 0
    for obj, raw in items:
        bits = obj.type.bits
        value |= (raw & ((1 << bits) - 1)) << shift
        shift += bits
    return value.to_bytes((shift + 7) // 8, 'little')


def unpack_pdo(objects: list[CanObject], data: bytes) -> list[int]:
    """Raw (sign-decoded) values of ``objects`` from a PDO payload."""
    value = int.from_bytes(data, 'little')
    out, shift = [], 0
    for obj in objects:
        bits = obj.type.bits
        raw = (value >> shift) & ((1 << bits) - 1)
        if obj.type.signed and raw >= 1 << (bits - 1):
            raw -= 1 << bits
        out.append(raw)
        shift += bits
    return out


class CanopenDrive:
    """One drive on a CANopen transport, driven through its profile."""

    settings: ClassVar[tuple[TransportParameter, ...]] = (
        TransportParameter('object_set', '', "CANopen object set of the profile (Kinco: "
                           "manufacturer | ds402); '' = the profile's choice"),
        TransportParameter('velocity_scale', 0.0, "rpm per count of the target/actual velocity "
                           "objects; 0 = the profile's"),
        TransportParameter('transition_timeout', 1.0, 's a CiA 402 transition may take before '
                           'it is reported as stuck'),
    )

    @classmethod
    def link_settings(cls, profile: Profile, settings: Mapping[str, Any]) -> dict[str, Any]:
        """Return the ``transport.*`` settings as given: the bus settings are the interface's."""
        if profile.canopen is None:
            raise ProfileError(f'profile {profile.name} has no canopen section')
        return dict(settings)

    def __init__(self, profile: Profile, transport: CanopenTransport, unit_id: int,
                 scaling: VelocityScaling, settings: Mapping[str, Any] | None = None,
                 owns_transport: bool = True) -> None:
        if profile.canopen is None:
            raise ProfileError(f'profile {profile.name} has no canopen section')
        if not isinstance(transport, CanopenTransport):
            raise ParameterError('CanopenDrive needs a CanopenTransport')
        transport.attach(unit_id)
        self.profile = profile
        self.transport = transport
        self.unit_id = unit_id
        self.scaling = scaling
        self.spec = profile.canopen
        values = {p.name: p.default for p in self.settings}
        values.update(settings or {})
        self.objects = self.spec.selected(str(values['object_set']))
        self.cia402 = self.objects.control is ControlStyle.CIA402
        self.velocity_scale = float(values['velocity_scale']) or \
            self.objects.target_velocity.scale
        self.transition_timeout = float(values['transition_timeout'])
        self.tpdo_layout = self._plan_tpdos()
        self.last_setpoint_raw = 0
        self.state: State | None = None
        self.stuck = ''                      # why the drive does not reach the wanted state
        self._configured = False
        self._values: dict[str, int] = {}    # role -> raw
        self._last_controlword: int | None = None
        self._emcy_fault: FaultInfo = NO_FAULT
        self._goal: Goal | None = None
        self._goal_since = 0.0

    def _plan_tpdos(self) -> list[list[tuple[str, CanObject]]]:
        """Pack the monitored objects into TPDOs (64 bits each), status + speed first."""
        roles = sorted(self.objects.monitor.items(),
                       key=lambda item: {'status_word': 0, 'motor_speed': 1}.get(item[0], 2))
        layout: list[list[tuple[str, CanObject]]] = [[]]
        for role, obj in roles:
            if sum(o.type.bits for _, o in layout[-1]) + obj.type.bits > 64:
                if len(layout) == self.spec.tpdos:
                    log.warning('%s: %s does not fit the %d TPDOs; not monitored',
                                self.profile.name, role, self.spec.tpdos)
                    continue
                layout.append([])
            layout[-1].append((role, obj))
        return layout

    # --- link -------------------------------------------------------------------------

    @property
    def hardware_id(self) -> str:
        return f'{self.profile.name}@{self.transport.description}#{self.unit_id}'

    @property
    def stats(self) -> TransportStats:
        return self.transport.stats

    def open(self) -> None:
        self.transport.open()

    def close(self) -> None:
        self._configured = False
        self.transport.close()

    # --- timing (an RPDO per cycle; SDO only at connect and for services) ---------------

    def cycle_seconds(self) -> float:
        return 0.0

    def connect_seconds(self) -> float:
        return 0.0

    def action_seconds(self) -> float:
        return 4 * self.transport.exchange_seconds(8, 8)     # SDO request and reply frames

    def host_loss_plan(self, requested: float, interval: float) -> HostLossProtection:
        """RPDO deadline monitoring (0x1400:05) where the profile has it."""
        if not self.spec.rpdo_deadline:
            return HostLossProtection(requested=requested, note=(
                f'{self.profile.name} documents no RPDO deadline over CANopen: only the host '
                'watchdog stops the motor, not a dead host'))
        if requested == 0:
            return HostLossProtection(requested=0.0, note='off, as drive_comm_timeout 0 asks')
        minimum = 2 * interval + HOST_LOSS_JITTER
        value = max(requested, minimum)
        note = '' if value == requested else (
            f'raised from {requested:g} s: the RPDO is sent every {interval * 1000:.0f} ms')
        value = min(math.ceil(value * 1000) / 1000, 65.535)
        return HostLossProtection('RPDO1 deadline 0x1400:05', value, requested, note)

    def forget_state(self) -> None:
        self._configured = False
        self.state = None
        self._values.clear()
        self._last_controlword = None
        self._emcy_fault = NO_FAULT
        self._goal = None
        self.stuck = ''

    def _write(self, obj: CanObject, raw: int) -> None:
        self.transport.write_object(obj.index, obj.subindex, obj.type, raw)

    def _read(self, obj: CanObject) -> int:
        return self.transport.read_object(obj.index, obj.subindex, obj.type)

    def configure(self, protection: HostLossProtection,
                  apply_commissioning: bool) -> list[str]:
        """Map the PDOs, set heartbeat and mode over SDO, then start the node (NMT)."""
        t = self.transport
        node = self.unit_id
        spec = self.spec
        problems: list[str] = []
        u8, u16, u32 = ValueType.UINT8, ValueType.UINT16, ValueType.UINT32
        t.nmt(NmtCommand.ENTER_PRE_OPERATIONAL)
        heartbeat = t.heartbeat_ms or spec.heartbeat_ms
        t.write_object(0x1017, 0, u16, heartbeat)
        # RPDO1: control word + target velocity; the others off.
        rpdo = [self.objects.controlword, self.objects.target_velocity]
        for number in range(spec.rpdos):
            comm, mapping, cob = 0x1400 + number, 0x1600 + number, 0x200 + 0x100 * number + node
            t.write_object(comm, 1, u32, PDO_DISABLED | cob)
            if number > 0:
                continue
            t.write_object(comm, 2, u8, spec.transmission_type)
            t.write_object(mapping, 0, u8, 0)
            for sub, obj in enumerate(rpdo, 1):
                t.write_object(mapping, sub, u32, obj.mapping)
            t.write_object(mapping, 0, u8, len(rpdo))
            if spec.rpdo_deadline:
                t.write_object(comm, 5, u16, min(round(protection.timeout * 1000), 0xFFFF))
            t.write_object(comm, 1, u32, cob)
        for number in range(spec.tpdos):
            comm, mapping, cob = 0x1800 + number, 0x1A00 + number, 0x180 + 0x100 * number + node
            t.write_object(comm, 1, u32, PDO_DISABLED | cob)
            if number >= len(self.tpdo_layout):
                continue
            t.write_object(comm, 2, u8, spec.transmission_type)
            if spec.tpdo_event_timer_ms:
                t.write_object(comm, 5, u16, spec.tpdo_event_timer_ms)
            t.write_object(mapping, 0, u8, 0)
            for sub, (_, obj) in enumerate(self.tpdo_layout[number], 1):
                t.write_object(mapping, sub, u32, obj.mapping)
            t.write_object(mapping, 0, u8, len(self.tpdo_layout[number]))
            t.write_object(comm, 1, u32, cob)
        if self.objects.mode_of_operation is not None:
            self._write(self.objects.mode_of_operation, self.objects.mode_value)
        if apply_commissioning:
            problems += self._commission()
        for group in self.tpdo_layout:        # the values before the first TPDO arrives
            for role, obj in group:
                self._values[role] = self._read(obj)
        self._update_state()
        t.nmt(NmtCommand.START)
        timeout = t.heartbeat_timeout or heartbeat * spec.heartbeat_timeout_factor / 1000.0
        if heartbeat <= 0:
            problems.append('heartbeat is off (heartbeat_ms 0): link loss is not detected')
            timeout = 0.0
        t.supervise(timeout)
        self._configured = True
        return problems

    def _commission(self) -> list[str]:
        problems = []
        for item in self.profile.commissioning:
            parameter = self.profile.parameter(item.code)
            if parameter.index is None:
                problems.append(f'{item.code} has no CANopen object: not written')
                continue
            try:
                raw = parameter.to_raw(item.value)
                if self._read_parameter(parameter) != raw:
                    self.transport.write_object(parameter.index, parameter.subindex,
                                                parameter.type, raw)
            except (ParameterError, ProtocolException) as exc:   # e.g. an SDO abort
                problems.append(f'{item.code} = {item.value:g}: {exc}')
        return problems

    # --- control ----------------------------------------------------------------------

    def _native(self, velocity: float) -> int:
        native = self.scaling.to_native(velocity, self.objects.velocity_unit)
        raw = round(native / self.velocity_scale)
        low, high = self.objects.target_velocity.type.bounds
        setpoint = self.profile.parameters.get(self.profile.velocity.setpoint)
        if setpoint is not None and setpoint.index == self.objects.target_velocity.index:
            if setpoint.minimum is not None:
                low = max(low, math.ceil(setpoint.minimum / setpoint.scale))
            if setpoint.maximum is not None:
                high = min(high, math.floor(setpoint.maximum / setpoint.scale))
        return min(max(raw, low), high)

    def _goal_for(self, run: bool, idle_action: str) -> Goal:
        if run:
            return Goal.OPERATION_ENABLED
        if idle_action == 'disable':
            return Goal.SWITCH_ON_DISABLED
        if idle_action == 'quick_stop' or self.objects.stop_action is StopAction.QUICK_STOP:
            return Goal.QUICK_STOP
        return Goal.SWITCHED_ON

    def apply(self, velocity: float, run: bool, idle_action: str = 'stop',
              reassert: bool = False) -> None:
        """One control cycle: one RPDO with control word and target velocity.

        The RPDO carries the control word every cycle, so ``reassert`` needs nothing more.
        """
        if not self._configured:
            # Connect: before the PDOs exist, zero the setpoint and idle over SDO.
            if self.cia402:
                self._values[self._status_role] = self._read(self.objects.statusword)
                self._update_state()
            self._write(self.objects.target_velocity, 0)
            self.last_setpoint_raw = 0
            self._write(self.objects.controlword, self._controlword(False, idle_action))
            return
        controlword = self._controlword(run, idle_action)
        moving = run and (not self.cia402 or self.state is State.OPERATION_ENABLED)
        raw = self._native(velocity) if moving else 0
        self._send_rpdo(controlword, raw)

    @property
    def _status_role(self) -> str:
        return 'status_word'

    def _controlword(self, run: bool, idle_action: str) -> int:
        if not self.cia402:
            commands = self.objects.commands
            return commands['run'] if run else commands.get(idle_action, commands['stop'])
        goal = self._goal_for(run, idle_action)
        now = time.monotonic()
        if goal is not self._goal:
            self._goal, self._goal_since = goal, now
            self.stuck = ''
        command = next_command(self.state, goal)
        done = {Goal.OPERATION_ENABLED: State.OPERATION_ENABLED,
                Goal.SWITCHED_ON: None, Goal.QUICK_STOP: None,
                Goal.SWITCH_ON_DISABLED: State.SWITCH_ON_DISABLED}[goal]
        if done is not None and self.state is done:
            self._goal_since = now
        elif done is not None and now - self._goal_since > self.transition_timeout \
                and not self.stuck:
            where = self.state.name if self.state is not None else 'unknown'
            self.stuck = (f'CiA 402: the drive stays in {where}, not {done.name}, after '
                          f'{self.transition_timeout:g} s')
            log.warning('%s: %s', self.hardware_id, self.stuck)
        return int(command) if command is not None else int(Command.DISABLE_VOLTAGE)

    def _send_rpdo(self, controlword: int, velocity_raw: int) -> None:
        self.transport.send(0x200 + self.unit_id, pack_pdo(
            [(self.objects.controlword, controlword),
             (self.objects.target_velocity, velocity_raw)]))
        self._last_controlword = controlword
        self.last_setpoint_raw = velocity_raw

    def _send_controlword(self, controlword: int) -> None:
        if self._configured:
            self._send_rpdo(controlword, 0)
        else:
            self._write(self.objects.controlword, controlword)
            self._last_controlword = controlword

    def send_command(self, action: str) -> None:
        """Send one command now (fault_reset: a rising edge of bit 7 on CiA 402 drives)."""
        if self.cia402:
            values = {'fault_reset': int(Command.FAULT_RESET), 'stop': int(Command.SWITCH_ON),
                      'disable': int(Command.DISABLE_VOLTAGE),
                      'quick_stop': int(Command.QUICK_STOP), 'run': int(Command.ENABLE_OPERATION)}
        else:
            values = dict(self.objects.commands)
        if action not in values:
            raise ParameterError(f'{self.profile.name} has no {action!r} command')
        value = values[action]
        if self.cia402 and action == 'fault_reset' and (self._last_controlword or 0) & 0x80:
            self._send_controlword(int(Command.DISABLE_VOLTAGE))     # bit 7 low first
        self._send_controlword(value)

    # --- status -----------------------------------------------------------------------

    def _update_state(self) -> None:
        if self.cia402 and self._status_role in self._values:
            self.state = decode_state(self._values[self._status_role])

    def poll(self, cycle: int, preempt: Callable[[], None] | None = None) -> Reading:
        """Decode what the drive sent (TPDOs, EMCY); raise if its heartbeat is lost."""
        nmt = self.transport.check_alive()
        if self._configured and nmt is not None and nmt not in (NmtState.OPERATIONAL,):
            raise TransportError(f'node {self.unit_id} reports NMT state {nmt.name}')
        for number, group in enumerate(self.tpdo_layout, 1):
            received = self.transport.tpdo(number)
            if received is None:
                continue
            objects = [obj for _, obj in group]
            if len(received[0]) * 8 < sum(o.type.bits for o in objects):
                self.transport.stats.bad_frames += 1
                continue
            for (role, _), raw in zip(group, unpack_pdo(objects, received[0])):
                self._values[role] = raw
        self._update_state()
        self._take_emcy()
        return self._reading()

    def _take_emcy(self) -> None:
        for frame in self.transport.take_emcy():
            if frame.code == 0:
                self._emcy_fault = NO_FAULT          # error reset / no error
                continue
            code = frame.data[0] if self.spec.emcy_fault is EmcyFault.MANUFACTURER_BYTE \
                else frame.code
            self._emcy_fault = describe_fault(self.profile.faults, code)
            log.warning('%s EMCY %04Xh register %02Xh data %s: %s %s', self.hardware_id,
                        frame.code, frame.register, frame.data.hex(' '),
                        self._emcy_fault.display, self._emcy_fault.name)

    def _reading(self) -> Reading:
        reading = Reading(stuck=self.stuck)
        monitor = self.objects.monitor
        for role, raw in self._values.items():
            obj = monitor[role]
            scale = self.velocity_scale if role == 'motor_speed' else obj.scale
            reading.values[role] = raw * scale
        status = self._values.get(self._status_role)
        if status is not None:
            reading.raw_words[obj_code(self.objects.statusword)] = status
        if self.cia402:
            state = self.state
            if state is not None:
                reading.raw_words['cia402_state'] = int(state)
            reading.flags = {
                'ready': state in (State.SWITCH_ON_DISABLED, State.READY_TO_SWITCH_ON,
                                   State.SWITCHED_ON, State.OPERATION_ENABLED),
                'running': state is State.OPERATION_ENABLED,
                'fault': state in (State.FAULT, State.FAULT_REACTION_ACTIVE),
                'warning': bool(status is not None and status & StatusBit.WARNING),
                'at_speed': state is State.OPERATION_ENABLED and bool(
                    status is not None and status & StatusBit.TARGET_REACHED),
                'reverse': reading.values.get('motor_speed', 0.0) < 0,
            }
        else:
            for name, rule in self.profile.flags.items():
                if rule.signal in reading.values:
                    reading.flags[name] = rule.evaluate(reading.values[rule.signal])
        code = int(reading.values.get('fault_code', 0))
        faulted = reading.flags.get('fault', code != 0)
        if code:
            reading.fault = describe_fault(self.profile.faults, code)
        elif faulted:
            reading.fault = self._emcy_fault if self._emcy_fault.active else \
                describe_fault(self.profile.faults, GENERIC_ERROR)
        speed = reading.values.get('motor_speed')
        if speed is not None:
            reading.measured_velocity = self.scaling.from_native(speed,
                                                                 self.objects.velocity_unit)
        return reading

    # --- parameters ---------------------------------------------------------------------

    def _object_of(self, parameter: Parameter) -> Parameter:
        if parameter.index is None:
            raise ParameterError(f'{parameter.code} ({parameter.description}) has no CANopen '
                                 'object: not reachable over CANopen')
        return parameter

    def _read_parameter(self, parameter: Parameter) -> int:
        return self.transport.read_object(parameter.index, parameter.subindex, parameter.type)

    def get_parameter(self, key: str) -> ParameterValue:
        parameter = self._object_of(self.profile.parameter(key))
        raw = self._read_parameter(parameter)
        return ParameterValue(parameter, raw, parameter.from_raw(raw))

    def check_write(self, key: str, value: float, running: bool) -> tuple[Parameter, int]:
        """Validate a write without touching the drive; ParameterError says why not."""
        parameter = self._object_of(self.profile.parameter(key))
        return parameter, check_write(self.profile, parameter, value, running)

    def set_parameter(self, key: str, value: float, persistent: bool,
                      running: bool) -> tuple[ParameterValue, str]:
        """Validate (access, range, resolution, type), SDO download, read back."""
        parameter, raw = self.check_write(key, value, running)
        self.transport.write_object(parameter.index, parameter.subindex, parameter.type, raw)
        readback = self._read_parameter(parameter)
        if readback != raw:
            raise ParameterError(f'{parameter.code}: wrote {raw} but the drive holds {readback}')
        note = ('SDO write; whether it survives power-off is up to the drive'
                if persistent else '')
        return ParameterValue(parameter, readback, parameter.from_raw(readback)), note


def obj_code(obj: CanObject) -> str:
    return obj.code or str(obj)
