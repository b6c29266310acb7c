"""A simulated CANopen drive (CiA 301 + CiA 402) on the ``canopen`` library's LocalNode.

Built from the same profile as the driver (its ``canopen`` section and the
parameters' objects). What it does, over real CAN frames:
- answers SDO from an object dictionary built from the profile: CiA 301 abort
  codes for an unknown index (0602 0000) or sub-index (0609 0011), a read-only
  object (0601 0002), a wrong length (0607 0010) and a value out of range
  (0609 0031 / 0609 0032 / 0609 0030);
- takes PDO communication and mapping parameters, receives RPDOs and sends its
  TPDOs itself (on change and on the event timer), in NMT Operational only;
- NMT commands, boot-up, heartbeat production at 0x1017;
- where the profile documents it (``heartbeat_consumer``), a heartbeat consumer
  (0x1016:01): monitoring starts with the host's first heartbeat; a heartbeat
  event sends EMCY 0x8130, takes the NMT reaction of 0x1029:01 (0: pre-operational,
  1: none, 2: stopped) and, as a CiA 402 fault reaction, stops an energised motor in
  FAULT (a command-word drive stops running). A profile without it has no 0x1016: the
  write is aborted with 0602 0000, as a real drive without the object does;
- the CiA 402 state machine (``vfd_ros2.protocol.cia402``) or a manufacturer command word
  (Kinco 0x2A00), a speed ramp, EMCY on faults and on their reset; the error code
  object (0x603F) holds the active fault, or keeps the last one after a reset
  (``keeps_last_error``), or stays 0 (``report_error_code = False``: only EMCY names it);
- fault injection, silence injection (cable unplugged), a drive that cannot be
  enabled, and a motor stop when the master's RPDOs stop (0x1400:05 deadline).

Several drives share one ``SimulatedCanBus``; one thread ticks them in turn.
"""

from __future__ import annotations

import math
import threading
import time
from typing import Any, Callable

import canopen
from canopen import objectdictionary as od
from canopen.sdo import SdoAbortedError

from ..errors import ParameterError
from ..profiles import (
    ControlStyle,
    EmcyFault,
    Parameter,
    Profile,
    ValueType,
)
from ..protocol.cia402 import STATUSWORD_OF, ControlBit, State, transition
from ..transports.canopen import (
    PDO_DISABLED,
    SYNC_COB_ID,
    SYNCHRONOUS_MAX,
    ObjectEntry,
    add_objects,
    add_pdo_objects,
    od_variable,
    quick_closing_network,
)

RPDO_TIMEOUT = 0x8250          # CiA 301 EMCY: RPDO timeout
HEARTBEAT_EVENT = 0x8130       # CiA 301 EMCY: life guard or heartbeat error
MANUFACTURER_EMCY = 0xFF00
GENERIC_REGISTER = 0x01        # error register bit 0: generic error
COMMUNICATION_REGISTER = 0x11  # ... + bit 4: communication error


class _TwinNode(canopen.LocalNode):
    """LocalNode whose heartbeat the twin produces itself (so silence silences it)."""

    def __init__(self, node_id: int, dictionary: od.ObjectDictionary) -> None:
        super().__init__(node_id, dictionary)
        self._write_callbacks.remove(self.nmt.on_write)


class SimulatedCanopenDrive:
    """One simulated CANopen drive (thread-safe: the bus thread and tests share it)."""

    def __init__(self, profile: Profile, node_id: int = 1, object_set: str = '',
                 initial: dict[str, float] | None = None,
                 clock: Callable[[], float] = time.monotonic) -> None:
        if profile.canopen is None:
            raise ParameterError(f'profile {profile.name} has no canopen section')
        self.profile = profile
        self.node_id = self.unit_id = node_id   # (unit_id: as sim_drive names a line's drives)
        self.spec = profile.canopen
        self.objects = self.spec.selected(object_set)
        self.cia402 = self.objects.control is ControlStyle.CIA402
        self._clock = clock
        self.lock = threading.RLock()
        self.parameters: dict[tuple[int, int], Parameter] = {
            (p.index, p.subindex): p for p in profile.parameters.values() if p.index is not None}
        self.node = _TwinNode(node_id, self._dictionary())
        self.node.add_write_callback(self._on_sdo_write)
        self.node.add_read_callback(self._on_sdo_read)
        for code, value in (initial or {}).items():
            parameter = profile.parameter(code)
            obj = self.node._find_object(parameter.index, parameter.subindex)  # noqa: SLF001
            self.node.data_store.setdefault(parameter.index, {})[parameter.subindex] = \
                obj.encode_raw(parameter.to_raw(value))
        self.network: Any = None
        self.state = State.SWITCH_ON_DISABLED
        # Disable operation with 0x605C = 1: in operation enabled until the ramp ends.
        self._slowing_to_switched_on = False
        self.controlword = 0
        self.target_raw = 0
        self.speed_rpm = 0.0
        #: motor revolutions turned since start (the position counter's source)
        self.motor_revolutions = 0.0
        self.run_requested = False          # command_word style
        self.fault_code = 0
        self.last_error = 0                 # the fault before the last reset
        self.keeps_last_error = False       # 0x603F keeps the last error after a reset
        self.report_error_code = True       # False: 0x603F stays 0, only EMCY names faults
        self.fault_cause_present = False
        self.heartbeat_events = 0
        self._consumer_cob: int | None = None
        self._host_seen: float | None = None
        self.silent = False
        self.tpdos_off = False      # heartbeat and SDO go on, no TPDO (a dead PDO producer)
        self.heartbeat_off = False  # TPDOs and SDO go on, no heartbeat (0x1017 not obeyed)
        self.tpdo_bytes: int | None = None  # TPDOs cut to this length (a mapping gone wrong)
        self.enable_blocked = False         # e.g. safe torque off: cannot leave SWITCH_ON_DISABLED
        self.ignores_nmt_start = False      # NMT start (0x01) not obeyed: stays pre-operational
        self.emcy_sent: list[tuple[int, int, bytes]] = []
        self.rpdos_received = 0
        self._last_rpdo: float | None = None
        self._last_heartbeat = 0.0
        self._tpdo_sent: dict[int, tuple[bytes, float]] = {}
        self._rpdo_pending: dict[int, bytes] = {}   # synchronous RPDOs, applied at SYNC
        self._syncs = 0
        self.syncs_received = 0
        self._last_tick = clock()

    # --- object dictionary ----------------------------------------------------------------

    def _dictionary(self) -> od.ObjectDictionary:
        d = od.ObjectDictionary()
        d.add_object(od_variable('Device type', 0x1000, 0, ValueType.UINT32, 'ro', 0x00020192))
        d.add_object(od_variable('Error register', 0x1001, 0, ValueType.UINT8, 'ro'))
        d.add_object(od_variable('Producer heartbeat time', 0x1017, 0, ValueType.UINT16, 'rw'))
        add_pdo_objects(d, self.node_id, self.spec.rpdos, self.spec.tpdos)
        entries = [ObjectEntry(index, sub, p.code, p.type,
                               'ro' if p.access.value == 'ro' else 'rw',
                               p.to_raw(p.default) if p.default is not None else 0)
                   for (index, sub), p in self.parameters.items()]
        if self.spec.heartbeat_consumer:
            entries += [ObjectEntry(0x1016, 1, 'Consumer heartbeat time 1', ValueType.UINT32),
                        ObjectEntry(0x1029, 1, 'Error behaviour: communication error',
                                    ValueType.UINT8)]
        objs = [self.objects.controlword, self.objects.statusword, self.objects.target_velocity,
                *self.objects.monitor.values()]
        if self.objects.mode_of_operation is not None:
            objs.append(self.objects.mode_of_operation)
        writable = (self.objects.controlword, self.objects.target_velocity,
                    self.objects.mode_of_operation)
        entries += [ObjectEntry(obj.index, obj.subindex, str(obj), obj.type,
                                'rw' if obj in writable else 'ro') for obj in objs]
        add_objects(d, entries)
        return d

    def _stored(self, index: int, subindex: int) -> int:
        obj = self.node._find_object(index, subindex)   # noqa: SLF001 - the OD lookup
        data = self.node.data_store.get(index, {}).get(subindex)
        return obj.decode_raw(data) if data is not None else int(obj.default or 0)

    def value(self, code: str) -> float:
        """Engineering value of a parameter (for behaviour and tests)."""
        p = self.profile.parameter(code)
        with self.lock:
            return p.from_raw(self._raw(p.index, p.subindex))

    def _value_or(self, code: str, fallback: float) -> float:
        try:
            p = self.profile.parameter(code) if code else None
        except ParameterError:
            p = None
        if p is None or p.index is None:
            return fallback
        return p.from_raw(self._raw(p.index, p.subindex)) or fallback

    def _stored_value(self, code: str) -> float | None:
        """Engineering value of a parameter the profile may lack (None), 0 kept as 0."""
        try:
            p = self.profile.parameter(code)
        except ParameterError:
            return None
        return None if p.index is None else p.from_raw(self._raw(p.index, p.subindex))

    # --- dynamic objects ------------------------------------------------------------------

    def _fault_register(self) -> int:
        return 1 if self.fault_code else 0

    def statusword(self) -> int:
        if self.cia402:
            word = STATUSWORD_OF[self.state] | 0x0200
            if self.state in (State.SWITCH_ON_DISABLED, State.READY_TO_SWITCH_ON,
                              State.SWITCHED_ON, State.OPERATION_ENABLED):
                word |= 0x0020
            if self.state in (State.SWITCHED_ON, State.OPERATION_ENABLED,
                              State.QUICK_STOP_ACTIVE):
                word |= 0x0010
            if self.state is State.OPERATION_ENABLED and \
                    abs(self.speed_rpm - self._target_rpm()) < 1:
                word |= 0x0400
            return word
        word = 0
        if self.speed_rpm != 0 or (self.run_requested and not self.fault_code):
            word |= 0x01
        if self.speed_rpm < 0:
            word |= 0x02
        if self.run_requested and abs(self.speed_rpm - self._target_rpm()) < 1:
            word |= 0x04
        if self.fault_code:
            word |= 0x80 | ((self.fault_code & 0xFF) << 8)
        return word

    def _dynamic(self, index: int, subindex: int) -> int | None:
        """Live values (status, speed, fault code, ...) by object."""
        key = (index, subindex)
        if key == (0x1001, 0):
            return self._fault_register()
        if key == (self.objects.statusword.index, self.objects.statusword.subindex):
            return self.statusword()
        for role, obj in self.objects.monitor.items():
            if (obj.index, obj.subindex) != key:
                continue
            if role == 'status_word':
                return self.statusword()
            if role == 'motor_speed':
                return round(self.speed_rpm / obj.scale)
            if role == 'fault_code':
                return self.error_code()
            if role == 'output_current':
                load = abs(self.speed_rpm) / 3000.0
                return round((2.0 + 8.0 * load if self.speed_rpm else 0.0) / obj.scale)
            if role == 'dc_bus_voltage':
                return round(48.0 / obj.scale)
            if role == 'position' and self.profile.position.from_drive:
                raw = self.position_count % (1 << obj.type.bits)     # the counter rolls over
                signed = obj.type.bounds[0] < 0 and raw >= 1 << (obj.type.bits - 1)
                return raw - (1 << obj.type.bits) if signed else raw
            return 0
        if self.objects.mode_of_operation is not None and \
                key == (self.objects.mode_of_operation.index + 1, 0):
            mode = self.objects.mode_of_operation
            return self._stored(mode.index, mode.subindex)   # 0x6061 follows 0x6060
        return None

    @property
    def position_count(self) -> int:
        """The motor position counter as the drive counts it (before its roll-over)."""
        with self.lock:
            return math.floor(self.motor_revolutions * self.profile.position.counts_per_rev)

    def error_code(self) -> int:
        """Return the error code object's value (0x603F or the profile's fault code)."""
        if not self.report_error_code:
            return 0
        return self.fault_code or (self.last_error if self.keeps_last_error else 0)

    def _raw(self, index: int, subindex: int) -> int:
        live = self._dynamic(index, subindex)
        return live if live is not None else self._stored(index, subindex)

    def _on_sdo_read(self, index: int, subindex: int, od: Any) -> int | None:
        with self.lock:
            return self._dynamic(index, subindex)

    def _on_sdo_write(self, index: int, subindex: int, od: Any, data: bytes) -> None:
        with self.lock:
            raw = od.decode_raw(data)
            self._check_value(index, subindex, raw)
            self._apply_write(index, subindex, raw)

    def _check_value(self, index: int, subindex: int, raw: int) -> None:
        p = self.parameters.get((index, subindex))
        if p is not None and (index, subindex) not in (
                (self.objects.controlword.index, self.objects.controlword.subindex),):
            value = p.from_raw(raw)
            if p.minimum is not None and value < p.minimum - 1e-9:
                raise SdoAbortedError(0x06090032)
            if p.maximum is not None and value > p.maximum + 1e-9:
                raise SdoAbortedError(0x06090031)
            if p.options and raw not in p.options:
                raise SdoAbortedError(0x06090030)
        if 0x1800 <= index < 0x1800 + self.spec.tpdos or 0x1400 <= index < 0x1400 + \
                self.spec.rpdos:
            if subindex == 2 and raw not in (254, 255) and not (
                    raw <= SYNCHRONOUS_MAX and self.spec.transmission_type <= SYNCHRONOUS_MAX):
                # What the profile's drive takes: event-driven, or synchronous where the
                # profile says the drive runs on SYNC (the Kinco: 254/255 only, L964).
                raise SdoAbortedError(0x06090030)
        if (0x1A00 <= index < 0x1A00 + self.spec.tpdos or
                0x1600 <= index < 0x1600 + self.spec.rpdos) and subindex and raw:
            try:
                self.node._find_object(raw >> 16, (raw >> 8) & 0xFF)   # noqa: SLF001
            except SdoAbortedError:
                raise SdoAbortedError(0x06040041) from None

    def _apply_write(self, index: int, subindex: int, raw: int) -> None:
        key = (index, subindex)
        if key == (self.objects.controlword.index, self.objects.controlword.subindex):
            self._on_controlword(raw)
        elif key == (self.objects.target_velocity.index, self.objects.target_velocity.subindex):
            self.target_raw = raw
        elif key == (0x1017, 0):
            self._last_heartbeat = 0.0
        elif key == (0x1016, 1):
            self._watch_host(raw)

    # --- behaviour --------------------------------------------------------------------------

    def bus_control(self) -> bool:
        """Obeys the bus only once the commissioning values are set (Kinco A0.04 = 2)."""
        for item in self.profile.commissioning:
            if not item.bus_control:
                continue            # (0x6007, 0x605C: modelled for what they do)
            p = self.profile.parameter(item.code)
            if p.index is not None and self._stored(p.index, p.subindex) != p.to_raw(item.value):
                return False
        return True

    def _on_controlword(self, word: int) -> None:
        previous, self.controlword = self.controlword, word
        if self.cia402:
            if word & ControlBit.FAULT_RESET and not previous & ControlBit.FAULT_RESET and \
                    self.state is State.FAULT:
                if self.fault_cause_present:
                    return
                self._clear_fault()
            new = transition(self.state, word, previous)
            if self.enable_blocked or not self.bus_control():
                if new in (State.READY_TO_SWITCH_ON, State.SWITCHED_ON,
                           State.OPERATION_ENABLED):
                    new = State.SWITCH_ON_DISABLED if self.state is State.SWITCH_ON_DISABLED \
                        else self.state
            self._slowing_to_switched_on = (
                new is State.SWITCHED_ON and self.state is State.OPERATION_ENABLED and
                self._stored_value('disable_operation_option_code') == 1)
            if not self._slowing_to_switched_on:
                self.state = new
            return
        commands = self.objects.commands
        if word & commands['fault_reset'] and word == commands['fault_reset']:
            self.run_requested = False
            if self.fault_code and not self.fault_cause_present:
                self._clear_fault()
        elif word == commands['run']:
            if not self.fault_code and self.bus_control():
                self.run_requested = True
        else:
            self.run_requested = False

    def _clear_fault(self) -> None:
        self.last_error = self.fault_code
        self.fault_code = 0
        self.state = State.SWITCH_ON_DISABLED
        self._emcy(0)

    def inject_fault(self, code: int, subcode: int = 0, latched: bool = False,
                     register: int = GENERIC_REGISTER) -> None:
        """Raise a fault with an EMCY (code 0: the cause is gone, a reset will clear it)."""
        with self.lock:
            if code == 0:
                self.fault_cause_present = False
                return
            self.fault_code = code
            self.fault_cause_present = latched
            self.run_requested = False
            self.state = State.FAULT
            self._emcy(code, register)

    def send_emcy(self, code: int, register: int = GENERIC_REGISTER) -> None:
        """Send an EMCY without faulting (a warning: a temperature, say); 0: error reset."""
        with self.lock:
            self._emcy(code, register)

    def _emcy(self, code: int, register: int = GENERIC_REGISTER) -> None:
        if code == 0:
            frame = (0, 0, bytes(5))
        elif self.spec.emcy_fault is EmcyFault.MANUFACTURER_BYTE and code < 0x100:
            frame = (MANUFACTURER_EMCY, register, bytes((code & 0xFF, 0, 0, 0, 0)))
        else:
            frame = (code, register, bytes(5))     # a CiA error code (e.g. 0x8130)
        self.emcy_sent.append(frame)
        if self.network is not None and not self.silent:
            self.node.emcy.send(*frame)         # the library's EMCY producer

    def _target_rpm(self) -> float:
        return self.target_raw * self.objects.target_velocity.scale

    def _rates(self) -> tuple[float, float, float]:
        """(acceleration, deceleration, quick-stop deceleration) in rpm/s."""
        if self.cia402 and self.profile.velocity.acceleration_time == '':
            return (self._value_or('profile_acceleration', 3000.0),
                    self._value_or('profile_deceleration', 3000.0),
                    self._value_or('quick_stop_deceleration', 10000.0))
        velocity = self.profile.velocity
        rated = self._value_or(velocity.rated_speed, 3000.0)
        accel = rated / max(self._value_or(velocity.acceleration_time, 0.5), 0.05)
        decel = rated / max(self._value_or(velocity.deceleration_time, 0.5), 0.05)
        return accel, decel, decel * 4

    def tick(self) -> None:
        with self.lock:
            now = self._clock()
            dt = max(0.0, min(now - self._last_tick, 0.5))
            self._last_tick = now
            self._nmt_housekeeping()
            self._consume_heartbeat(now)
            self._supervise_master(now)
            if self.cia402:
                running = self.state is State.OPERATION_ENABLED and \
                    not self._slowing_to_switched_on
            else:
                running = self.run_requested and not self.fault_code and self.bus_control()
            target = self._target_rpm() if running else 0.0
            accel, decel, quick = self._rates()
            if self.state is State.QUICK_STOP_ACTIVE or self.fault_code:
                rate = quick
            else:
                rate = accel if abs(target) > abs(self.speed_rpm) and \
                    target * self.speed_rpm >= 0 else decel
            step = rate * dt
            delta = target - self.speed_rpm
            previous = self.speed_rpm
            self.speed_rpm = target if abs(delta) <= step else self.speed_rpm + (
                step if delta > 0 else -step)
            self.motor_revolutions += 0.5 * (previous + self.speed_rpm) / 60.0 * dt
            if self.state is State.QUICK_STOP_ACTIVE and self.speed_rpm == 0.0:
                self.state = State.SWITCH_ON_DISABLED
            if self._slowing_to_switched_on and self.speed_rpm == 0.0:
                self._slowing_to_switched_on = False
                if self.state is State.OPERATION_ENABLED:
                    self.state = State.SWITCHED_ON
            if not self.silent and self.network is not None:
                self._produce(now)

    def _nmt_housekeeping(self) -> None:
        if self.node.nmt.state == 'INITIALISING':      # after an NMT reset: boot-up sent
            for index in list(self.node.data_store):
                if index in (0x1016, 0x1017, 0x1029) or 0x1400 <= index <= 0x1BFF:
                    del self.node.data_store[index]
            self._watch_host(0)
            self.state = State.SWITCH_ON_DISABLED
            self.run_requested = False
            self.target_raw = 0
            self.node.nmt.state = 'PRE-OPERATIONAL'

    def _watch_host(self, consumer: int) -> None:
        """Consume the heartbeat of node ``consumer >> 16`` (0x1016:01); 0 = none."""
        node_id, ms = (consumer >> 16) & 0x7F, consumer & 0xFFFF
        cob = 0x700 + node_id if node_id and ms else None
        if self.network is not None and cob != self._consumer_cob:
            if self._consumer_cob is not None:
                self.network.unsubscribe(self._consumer_cob, self._on_host_heartbeat)
            if cob is not None:
                self.network.subscribe(cob, self._on_host_heartbeat)
        self._consumer_cob = cob
        self._host_seen = None      # CiA 301: monitoring starts with the first heartbeat

    def _on_host_heartbeat(self, can_id: int, data: bytearray, timestamp: float) -> None:
        if self.silent:
            return
        with self.lock:
            self._host_seen = self._clock()

    def _consume_heartbeat(self, now: float) -> None:
        """Heartbeat event when the host's heartbeat is late (CiA 301 0x1016)."""
        if self._consumer_cob is None or self._host_seen is None:
            return
        if now - self._host_seen <= (self._stored(0x1016, 1) & 0xFFFF) / 1000.0:
            return
        self._host_seen = None      # one event; monitoring resumes with the next heartbeat
        self.heartbeat_events += 1
        behaviour = self._stored(0x1029, 1)
        if behaviour == 0 and self.node.nmt.state == 'OPERATIONAL':
            self.node.nmt.state = 'PRE-OPERATIONAL'
        elif behaviour == 2:
            self.node.nmt.state = 'STOPPED'
        # The fault reaction stops an energised motor; an idle drive only reports it
        # (so a host that restarts finds its idle drives without a fault).
        if self.cia402 and self.state in (State.OPERATION_ENABLED, State.QUICK_STOP_ACTIVE):
            self._abort_connection(HEARTBEAT_EVENT, COMMUNICATION_REGISTER)
        else:
            self.run_requested = False
            self._emcy(HEARTBEAT_EVENT, COMMUNICATION_REGISTER)

    def _supervise_master(self, now: float) -> None:
        """Stop the motor when the master's RPDOs stop (0x1400:05) or NMT leaves Operational."""
        moving = self.state is State.OPERATION_ENABLED if self.cia402 else self.run_requested
        if not moving:
            return
        if self.node.nmt.state != 'OPERATIONAL':
            if self.cia402 and self._abort_option() == 0:
                return                  # "no action": the motor runs on, out of the host's reach
            self.state = State.QUICK_STOP_ACTIVE if self.cia402 else self.state
            self.run_requested = False
            return
        deadline = self._stored(0x1400, 5) / 1000.0
        if deadline > 0 and self._last_rpdo is not None and now - self._last_rpdo > deadline:
            if self.cia402:
                self._abort_connection(RPDO_TIMEOUT, COMMUNICATION_REGISTER)
            else:
                self.run_requested = False

    def _abort_option(self) -> int:
        """Return 0x6007 where the profile has it; 1 (fault) where it has not."""
        return self._stored(0x6007, 0) if (0x6007, 0) in self.parameters else 1

    def _abort_connection(self, code: int, register: int) -> None:
        """React to a lost master as 0x6007 says (CiA 402-2 abort connection option code).

        0 no action (the motor runs on, EMCY only), 1 fault, 2 disable voltage (coast),
        3 quick stop; a profile without the object: fault.
        """
        option = self._abort_option()
        if option == 1:
            self.inject_fault(code, register=register)
            return
        self._emcy(code, register)
        if option == 2:
            self.state = State.SWITCH_ON_DISABLED
        elif option == 3:
            self.state = State.QUICK_STOP_ACTIVE
        else:
            self._last_rpdo = None      # runs on; one EMCY, not one per tick

    def _produce(self, now: float) -> None:
        period = self._stored(0x1017, 0) / 1000.0
        if period > 0 and now - self._last_heartbeat >= period and not self.heartbeat_off:
            self._last_heartbeat = now
            self.network.send_message(0x700 + self.node_id, bytes((self.node.nmt._state,)))  # noqa: SLF001
        if self.node.nmt.state != 'OPERATIONAL' or self.tpdos_off:
            return
        for number in range(self.spec.tpdos):
            if self._stored(0x1800 + number, 2) <= SYNCHRONOUS_MAX:
                continue                        # sent at SYNC (_on_sync)
            payload = self._tpdo_payload(number)
            if payload is None:
                continue
            cob, data = payload
            timer = self._stored(0x1800 + number, 5) / 1000.0
            last = self._tpdo_sent.get(number)
            if last is None or last[0] != data or (timer > 0 and now - last[1] >= timer):
                self._tpdo_sent[number] = (data, now)
                self.network.send_message(cob & 0x7FF, data)

    def _tpdo_payload(self, number: int) -> tuple[int, bytes] | None:
        """Return (COB-ID, data) of TPDO ``number`` (0-based) as mapped, or None if off."""
        cob = self._stored(0x1800 + number, 1)
        count = self._stored(0x1A00 + number, 0)
        if cob & PDO_DISABLED or not count:
            return None
        value, shift = 0, 0
        for sub in range(1, count + 1):
            entry = self._stored(0x1A00 + number, sub)
            bits = entry & 0xFF
            raw = self._raw(entry >> 16, (entry >> 8) & 0xFF)
            value |= (raw & ((1 << bits) - 1)) << shift
            shift += bits
        return cob, value.to_bytes((shift + 7) // 8, 'little')[:self.tpdo_bytes]

    # --- frames from the bus ------------------------------------------------------------------

    def attach(self, network: Any) -> None:
        """Join ``network``: SDO, NMT and RPDOs pass through the silence gate."""
        self.network = network
        network.add_node(self.node)
        network.unsubscribe(self.node.sdo.rx_cobid, self.node.sdo.on_request)
        network.unsubscribe(0, self.node.nmt.on_command)
        network.subscribe(self.node.sdo.rx_cobid, self._gate(self._on_sdo_request))
        network.subscribe(0, self._gate(self._on_nmt))
        for number in range(self.spec.rpdos):
            network.subscribe(0x200 + 0x100 * number + self.node_id, self._on_rpdo)
        network.subscribe(SYNC_COB_ID, self._on_sync)
        self.node.nmt.state = 'PRE-OPERATIONAL'
        network.send_message(0x700 + self.node_id, bytes((0,)))      # boot-up

    def _on_sdo_request(self, can_id: int, data: bytearray, timestamp: float) -> None:
        if self.node.nmt.state != 'STOPPED':        # (CiA 301: no SDO while stopped)
            self.node.sdo.on_request(can_id, data, timestamp)

    def _on_nmt(self, can_id: int, data: bytearray, timestamp: float) -> None:
        if self.ignores_nmt_start and data[:1] == b'\x01':
            return              # a node that stays pre-operational whatever it is told
        self.node.nmt.on_command(can_id, data, timestamp)

    def _gate(self, callback: Callable[..., None]) -> Callable[..., None]:
        def gated(can_id: int, data: bytearray, timestamp: float) -> None:
            if not self.silent:
                callback(can_id, data, timestamp)
        return gated

    def _on_rpdo(self, can_id: int, data: bytearray, timestamp: float) -> None:
        if self.silent:
            return
        number = (can_id - self.node_id - 0x200) // 0x100
        with self.lock:
            if self.node.nmt.state != 'OPERATIONAL':
                return
            cob = self._stored(0x1400 + number, 1)
            count = self._stored(0x1600 + number, 0)
            if cob & PDO_DISABLED or not count:
                return
            self.rpdos_received += 1
            self._last_rpdo = self._clock()       # deadline monitoring counts reception
            if self._stored(0x1400 + number, 2) <= SYNCHRONOUS_MAX:
                self._rpdo_pending[number] = bytes(data)      # takes effect at the next SYNC
                return
            self._apply_rpdo(number, bytes(data))

    def _on_sync(self, can_id: int, data: bytearray, timestamp: float) -> None:
        """SYNC: apply the synchronous RPDOs received since the last one, send sync TPDOs."""
        if self.silent:
            return
        with self.lock:
            if self.node.nmt.state != 'OPERATIONAL':
                return
            self.syncs_received += 1
            self._syncs += 1
            pending, self._rpdo_pending = self._rpdo_pending, {}
            for number, payload in pending.items():
                self._apply_rpdo(number, payload)
            for number in range(self.spec.tpdos if not self.tpdos_off else 0):
                kind = self._stored(0x1800 + number, 2)
                if kind > SYNCHRONOUS_MAX:
                    continue
                tpdo = self._tpdo_payload(number)
                if tpdo is None:
                    continue
                cob, payload = tpdo
                last = self._tpdo_sent.get(number)
                # type 0: acyclic, sent at SYNC only when changed; n: every n-th SYNC
                due = (last is None or last[0] != payload) if kind == 0 else \
                    self._syncs % kind == 0
                if due:
                    self._tpdo_sent[number] = (payload, self._clock())
                    self.network.send_message(cob & 0x7FF, payload)

    def _apply_rpdo(self, number: int, data: bytes) -> None:
        count = self._stored(0x1600 + number, 0)
        value, shift = int.from_bytes(data, 'little'), 0
        for sub in range(1, count + 1):
            entry = self._stored(0x1600 + number, sub)
            index, subindex, bits = entry >> 16, (entry >> 8) & 0xFF, entry & 0xFF
            raw = (value >> shift) & ((1 << bits) - 1)
            if raw >= 1 << (bits - 1) and self._signed(index, subindex):
                raw -= 1 << bits
            shift += bits
            self.node.data_store.setdefault(index, {})[subindex] = \
                self.node._find_object(index, subindex).encode_raw(raw)  # noqa: SLF001
            self._apply_write(index, subindex, raw)

    def _signed(self, index: int, subindex: int) -> bool:
        obj = self.node._find_object(index, subindex)   # noqa: SLF001
        return obj.data_type in (od.INTEGER8, od.INTEGER16, od.INTEGER32)


class SimulatedCanBus:
    """Simulated drives on one CAN channel (python-can), ticked in turn by one thread."""

    def __init__(self, drives: list[SimulatedCanopenDrive], channel: str,
                 interface: str = 'virtual', period: float = 0.005) -> None:
        ids = [d.node_id for d in drives]
        if len(set(ids)) != len(ids):
            raise ParameterError(f'node ids on one bus must differ: {ids}')
        self.drives = drives
        self.channel = channel
        self.interface = interface
        self.period = period
        self.network: Any = None
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def start(self) -> 'SimulatedCanBus':
        import can
        self.network = quick_closing_network(can.Bus(interface=self.interface,
                                                     channel=self.channel))
        self.network.connect()
        for drive in self.drives:
            drive.attach(self.network)
        self._thread = threading.Thread(target=self._run, name=f'sim can {self.channel}',
                                        daemon=True)
        self._thread.start()
        return self

    def _run(self) -> None:
        while not self._stop.wait(self.period):
            for drive in self.drives:     # fair: every drive every period, in turn
                try:
                    drive.tick()
                except Exception:  # noqa: BLE001 - a bus error must not kill the twin
                    if self._stop.is_set():
                        return

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(2.0)
            self._thread = None
        if self.network is not None:
            self.network.disconnect()
            self.network = None
