"""A simulated drive built from a profile: register image plus behaviour.

No I/O here: the line (``rtu_line.py``, ``tcp_server.py``) feeds it requests.
What it models, all from the profile data:
- the register image, initialised with the manual's defaults;
- access rules: unknown address, read-only, write-when-stopped, out-of-range
  values and too many registers answered with the drive's own exception codes;
- the command register (rising-edge start where the drive needs it, stop,
  fault reset that only clears a fault whose cause is gone);
- bus control only once the commissioning parameters are set;
- a speed ramp with the drive's acceleration / deceleration times;
- measured values (speed, frequency, current, bus voltage, temperature, the
  motor position counter where the profile has one) and the status flags the
  driver decodes;
- the drive's own comm-loss timeout raising the manual's fault.
"""

from __future__ import annotations

import math
import threading
import time
from typing import Callable

from ..errors import ParameterError
from ..profiles import (
    DirectionMode,
    FlagRule,
    FlagRuleKind,
    Parameter,
    PersistenceKind,
    Profile,
    SpeedUnit,
)
from ..protocol.registers import decode_words, encode_words

#: roles whose values come from the physics, not from inverting a flag rule
PHYSICAL_ROLES = frozenset({
    'motor_speed', 'output_frequency', 'output_current', 'dc_bus_voltage', 'temperature',
    'fault_code', 'fault_subcode', 'warning_code', 'warning_subcode', 'position'})

#: Modbus specification codes used where a profile does not say otherwise
class SimException(Exception):
    """A request the simulated drive answers with a protocol exception."""

    def __init__(self, situation: str, code: int) -> None:
        super().__init__(f'{situation} (exception {code})')
        self.situation = situation
        self.code = code


class SimulatedDrive:
    """One simulated drive (thread-safe: the line and the ROS node share it)."""

    def __init__(self, profile: Profile, unit_id: int = 1,
                 initial: dict[str, float] | None = None,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.profile = profile
        self.unit_id = unit_id
        self._clock = clock
        self.lock = threading.RLock()
        self.words: dict[int, int] = {}
        for parameter in profile.parameters.values():
            raw = round((parameter.default or 0.0) / parameter.scale)
            low, high = parameter.type.bounds
            self._store(parameter, min(max(raw, low), high))
        for code, value in (initial or {}).items():
            parameter = profile.parameter(code)
            self._store(parameter, parameter.to_raw(value))
        self.speed_rpm = 0.0
        #: motor revolutions turned since start (the position counter's source)
        self.motor_revolutions = 0.0
        self.output_active = False   # output stage on (running or ramping down)
        self.run_requested = False
        self.reverse_requested = False
        self.fault_code = 0
        self.fault_subcode = 0
        self.fault_cause_present = False
        self.warning_code = 0
        self.silent = False
        self.mute = False       # hears and obeys, its replies never arrive (a broken TX wire)
        # Registers this unit refuses (answered "illegal address"), as a stricter or
        # older firmware of the family would: e.g. a monitor value it does not have.
        self.refused: set[int] = set()
        # Registers this unit will not store (answered like a read-only register), as a
        # drive with a parameter lock or a stricter firmware would: reads still answer.
        self.write_refused: set[int] = set()
        self.write_ignored: set[int] = set()   # acknowledged, not stored (a faulty drive)
        self.requests = 0
        self.last_command_value: int | None = None
        self._last_request: float | None = None
        self._last_tick = clock()
        self._refresh_monitor()

    # --- helpers ----------------------------------------------------------------

    def _store(self, parameter: Parameter, raw: int) -> None:
        for offset, word in enumerate(encode_words(parameter, raw)):
            self.words[parameter.address + offset] = word

    def _raw(self, parameter: Parameter) -> int:
        words = [self.words.get(parameter.address + i, 0) for i in
                 range(parameter.register_count)]
        return decode_words(parameter, words)

    def value(self, code: str) -> float:
        """Engineering value of a parameter (for the twin's behaviour and tests)."""
        parameter = self.profile.parameter(code)
        with self.lock:
            return parameter.from_raw(self._raw(parameter))

    def _value_or(self, code: str, fallback: float) -> float:
        if not code:
            return fallback
        try:
            return self.value(code)
        except ParameterError:
            return fallback

    def exception(self, situation: str) -> SimException:
        """Return the exception this drive answers in ``situation`` (see modbus.exception_for)."""
        return SimException(situation, self.profile.modbus.exception_code(situation))

    # --- requests -----------------------------------------------------------------

    def note_request(self) -> None:
        with self.lock:
            self.requests += 1
            self._last_request = self._clock()

    def check_function(self, function_code: int) -> None:
        if function_code not in self.profile.modbus.function_codes:
            raise self.exception('illegal_function')

    def refuse(self, codes: list[str]) -> None:
        """Make the registers of these parameters answer "illegal address" from now on."""
        with self.lock:
            self.refused = set()
            for code in codes:
                parameter = self.profile.parameter(code)
                self.refused.update(range(parameter.address,
                                          parameter.address + parameter.register_count))

    def refuse_writes(self, codes: list[str]) -> None:
        """Make writes to these parameters answer the drive's read-only exception from now on."""
        with self.lock:
            self.write_refused = set()
            for code in codes:
                parameter = self.profile.parameter(code)
                self.write_refused.update(range(parameter.address,
                                                parameter.address + parameter.register_count))

    def read(self, address: int, count: int) -> list[int]:
        with self.lock:
            if count < 1 or count > self.profile.modbus.max_read_registers:
                raise self.exception('too_many_registers')
            if self.refused.intersection(range(address, address + count)):
                raise self.exception('illegal_address')
            if not self.profile.modbus.gaps_readable:
                for offset in range(count):
                    if not self._documented(address + offset):
                        raise self.exception('illegal_address')
            return [self.words.get(address + i, 0) for i in range(count)]

    def _documented(self, address: int) -> bool:
        if self.profile.parameter_at(address) is not None:
            return True
        previous = self.profile.parameter_at(address - 1)
        return previous is not None and previous.register_count == 2

    def _resolve_write_address(self, address: int) -> int:
        persistence = self.profile.modbus.persistence
        if persistence.kind is PersistenceKind.ADDRESS_OFFSET and \
                self.profile.parameter_at(address) is None and \
                self.profile.parameter_at(address - persistence.offset) is not None:
            return address - persistence.offset
        if persistence.kind is PersistenceKind.ADDRESS_FLAG and address & persistence.flag:
            return address & ~persistence.flag
        return address

    def write(self, address: int, values: list[int]) -> None:
        with self.lock:
            if len(values) > max(1, self.profile.modbus.max_write_registers):
                raise self.exception('too_many_registers')
            address = self._resolve_write_address(address)
            if self.refused.intersection(range(address, address + len(values))):
                raise self.exception('illegal_address')
            if self.write_refused.intersection(range(address, address + len(values))):
                raise self.exception('read_only')
            offset = 0
            pending: list[tuple[Parameter, int]] = []
            while offset < len(values):
                parameter = self.profile.parameter_at(address + offset)
                if parameter is None:
                    raise self.exception('illegal_address')
                count = parameter.register_count
                if offset + count > len(values):
                    raise self.exception('illegal_address')
                raw = decode_words(parameter, values[offset:offset + count])
                self._check_write(parameter, raw)
                pending.append((parameter, raw))
                offset += count
            for parameter, raw in pending:     # all or nothing
                if parameter.address in self.write_ignored:
                    continue
                self._store(parameter, raw)
                self._on_write(parameter, raw)

    def _check_write(self, parameter: Parameter, raw: int) -> None:
        if not parameter.writable:
            raise self.exception('read_only')
        if parameter.access.value == 'rw_stopped' and self.output_active:
            raise self.exception('stopped_only')
        if parameter.code in (self.profile.control.command,):
            return
        try:
            parameter.to_raw(parameter.from_raw(raw))
        except ParameterError:
            raise self.exception('illegal_value') from None

    # --- behaviour ------------------------------------------------------------------

    def bus_control(self) -> bool:
        """Return whether the drive obeys the bus: only once the commissioning values are set."""
        for item in self.profile.commissioning:
            if not item.bus_control:
                continue            # (a display unit: Veichi FA.12)
            parameter = self.profile.parameter(item.code)
            if self._raw(parameter) != round(item.value / parameter.scale):
                return False
        return True

    def _on_write(self, parameter: Parameter, raw: int) -> None:
        if parameter.code != self.profile.control.command:
            return
        control = self.profile.control
        action = control.action_of(raw)
        previous = self.last_command_value
        self.last_command_value = raw
        if action in ('run', 'run_reverse'):
            edge_needed = control.run_edge_from is not None
            is_edge = previous != raw
            if self.fault_code or not self.bus_control() or (edge_needed and not is_edge):
                return
            self.run_requested = True
            self.reverse_requested = action == 'run_reverse'
        elif action == 'fault_reset':
            self.run_requested = False
            if self.fault_code and not self.fault_cause_present:
                self.fault_code = 0
                self.fault_subcode = 0
        elif action == 'jog':
            return
        else:   # stop, disable, quick_stop and values the manual calls "other"
            self.run_requested = False

    def inject_fault(self, code: int, subcode: int = 0, latched: bool = False) -> None:
        """Raise a fault (code 0: the cause is gone, a reset will clear it)."""
        with self.lock:
            if code == 0:
                self.fault_cause_present = False
                return
            self.fault_code = code
            self.fault_subcode = subcode
            self.fault_cause_present = latched
            self.run_requested = False
            self._refresh_monitor()

    def _target_rpm(self, rated_rpm: float, pole_pairs: float) -> float:
        velocity = self.profile.velocity
        setpoint = self.profile.parameter(velocity.setpoint)
        native = setpoint.from_raw(self._raw(setpoint))
        if velocity.setpoint_unit is SpeedUnit.RPM:
            rpm = native
        elif velocity.setpoint_unit is SpeedUnit.PERCENT:
            rpm = native / 100.0 * rated_rpm
        else:
            rpm = native * 60.0 / pole_pairs
        if velocity.direction is DirectionMode.COMMAND:
            rpm = -abs(rpm) if self.reverse_requested else abs(rpm)
        return rpm

    def tick(self) -> None:
        """Advance the simulation to now."""
        with self.lock:
            now = self._clock()
            dt = max(0.0, min(now - self._last_tick, 0.5))
            self._last_tick = now
            self._check_comm_timeout(now)
            velocity = self.profile.velocity
            # (the ramp times run from zero to the rated speed, MH L1255; a percent
            # setpoint's 100 % may be the rated frequency's synchronous speed instead)
            rated_rpm = self._value_or(velocity.rated_speed, 1500.0) or 1500.0
            pole_pairs = self._value_or(velocity.pole_pairs, 2.0) or 2.0
            percent_base = velocity.percent_base_rpm(lambda code: self._value_or(code, 0.0),
                                                     rated_rpm)
            running = self.run_requested and not self.fault_code and self.bus_control()
            target = self._target_rpm(percent_base, pole_pairs) if running else 0.0
            accel = self._value_or(velocity.acceleration_time, 1.0)
            decel = self._value_or(velocity.deceleration_time, 1.0)
            if self.fault_code:
                decel = min(decel, 0.2)        # output off: the motor coasts down fast
            speeding_up = abs(target) > abs(self.speed_rpm) and \
                (target * self.speed_rpm >= 0)
            ramp_time = accel if speeding_up else decel
            step = rated_rpm * dt / ramp_time if ramp_time > 0 else math.inf
            delta = target - self.speed_rpm
            previous = self.speed_rpm
            self.speed_rpm = target if abs(delta) <= step else self.speed_rpm + math.copysign(
                step, delta)
            self.motor_revolutions += 0.5 * (previous + self.speed_rpm) / 60.0 * dt
            if running:
                self.output_active = True
            elif self.speed_rpm == 0.0:
                self.output_active = False
            self._refresh_monitor(target, percent_base, pole_pairs)

    def _check_comm_timeout(self, now: float) -> None:
        spec = self.profile.comm_timeout
        if spec is None or self._last_request is None or self.fault_code:
            return
        timeout = self.value(spec.parameter)
        if timeout > 0 and now - self._last_request > timeout:
            self.fault_code = spec.fault_code
            self.fault_subcode = spec.fault_subcode
            self.fault_cause_present = False
            self.run_requested = False

    # --- register image -------------------------------------------------------------

    def _set_role(self, role: str, value: float) -> None:
        signal = self.profile.signal(role)
        if signal is None:
            return
        parameter = self.profile.parameter(signal.code)
        if signal.bits is not None:
            low, high = signal.bits
            mask = ((1 << (high - low + 1)) - 1) << low
            raw = (self._raw(parameter) & ~mask) | ((int(value) << low) & mask)
        else:
            raw = round(value / parameter.scale)
            if parameter.type.bounds[0] == 0:
                # Unsigned register: the drive reports the magnitude and gives the
                # direction in its status flags.
                raw = abs(raw)
        type_low, type_high = parameter.type.bounds
        self._store(parameter, min(max(raw, type_low), type_high))

    @property
    def position_count(self) -> int:
        """The motor position counter as the drive counts it (before its roll-over)."""
        with self.lock:
            return math.floor(self.motor_revolutions * self.profile.position.counts_per_rev)

    def _set_counter(self) -> None:
        spec = self.profile.position
        signal = self.profile.signal(spec.signal) if spec.from_drive else None
        if signal is None:
            return
        parameter = self.profile.parameter(signal.code)
        bits = parameter.type.bits
        raw = self.position_count % (1 << bits)        # the counter rolls over
        low, _high = parameter.type.bounds
        if low < 0 and raw >= 1 << (bits - 1):
            raw -= 1 << bits
        self._store(parameter, raw)

    def _refresh_monitor(self, target: float = 0.0, rated_rpm: float = 1500.0,
                         pole_pairs: float = 2.0) -> None:
        feedback = self.profile.velocity.feedback_unit
        if feedback is SpeedUnit.RPM:
            speed = self.speed_rpm
        elif feedback is SpeedUnit.PERCENT:
            speed = self.speed_rpm / rated_rpm * 100.0
        else:
            speed = self.speed_rpm * pole_pairs / 60.0
        load = abs(self.speed_rpm) / rated_rpm if rated_rpm else 0.0
        rated_current = self._value_or('motor_rated_current', 10.0) or 10.0
        self._set_role('motor_speed', speed)
        self._set_role('output_frequency', self.speed_rpm * pole_pairs / 60.0)
        self._set_role('output_current',
                       rated_current * (0.3 + 0.6 * load) if self.output_active else 0.0)
        self._set_role('dc_bus_voltage', 540.0)
        self._set_role('temperature', 35.0 + 10.0 * load)
        self._set_role('fault_code', self.fault_code)
        self._set_role('fault_subcode', self.fault_subcode)
        self._set_role('warning_code', self.warning_code)
        self._set_counter()
        wanted = {
            'ready': not self.fault_code,
            'run_requested': self.run_requested and not self.fault_code,
            'running': self.output_active,
            'fault': bool(self.fault_code),
            'warning': bool(self.warning_code),
            'reverse': self.speed_rpm < 0,
            'at_speed': self.output_active and abs(self.speed_rpm - target) < 1.0,
        }
        enumerated: dict[str, list[tuple[FlagRule, bool]]] = {}
        for name, rule in self.profile.flags.items():
            if rule.signal in PHYSICAL_ROLES or name not in wanted:
                continue
            if rule.rule is FlagRuleKind.EQUALS:
                enumerated.setdefault(rule.signal, []).append((rule, wanted[name]))
            else:
                self._set_flag(rule, wanted[name])
        for signal, rules in enumerated.items():
            self._set_state_value(signal, rules)

    def _set_state_value(self, signal: str, rules: list[tuple[FlagRule, bool]]) -> None:
        """Pick the state value that makes every `equals` flag on ``signal`` come out right.

        Candidates are the values the rules name and the register's documented
        options (e.g. IMO 2100H: 1 forward, 2 reverse, 3 stopped, 4 fault).
        """
        parameter = self.profile.parameter(self.profile.signal(signal).code)
        candidates = sorted({v for rule, _ in rules for v in rule.values} |
                            set(parameter.options) | {0})
        for value in candidates:
            if all(rule.evaluate(value) == state for rule, state in rules):
                self._set_role(signal, value)
                return

    def _set_flag(self, rule: FlagRule, state: bool) -> None:
        signal = self.profile.signal(rule.signal)
        parameter = self.profile.parameter(signal.code)
        raw = self._raw(parameter)
        if rule.rule is FlagRuleKind.BIT:
            bit = 1 << (rule.bit + (signal.bits[0] if signal.bits else 0))
            self._store(parameter, raw | bit if state else raw & ~bit)
        elif rule.rule is FlagRuleKind.NONZERO:
            self._set_role(rule.signal, 1 if state else 0)
        elif rule.rule is FlagRuleKind.ZERO:
            self._set_role(rule.signal, 0 if state else 1)
