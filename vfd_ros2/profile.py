"""Drive profiles: a drive family described as data.

A profile is a YAML file in ``vfd_ros2/profiles/`` validated into frozen
dataclasses. It holds everything the driver and the simulated twin need to know
about a drive family: the parameter (register) table with scaling, ranges and
access; which registers carry the command, setpoint, status and measured values;
the command values; the fault and exception tables with the manual's words; and
the Modbus limits. A new family is a new file, never a new ``if`` in the code.

The schema is documented in ``vfd_ros2/profiles/README.md``.
"""

from __future__ import annotations

import dataclasses
import enum
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping

import yaml

from .errors import ParameterError, ProfileError, quote

PROFILE_DIR = Path(__file__).resolve().parent / 'profiles'


class Access(str, enum.Enum):
    """Who may write a parameter, and when."""

    READ_ONLY = 'ro'
    READ_WRITE = 'rw'
    WRITE_WHEN_STOPPED = 'rw_stopped'


class ValueType(str, enum.Enum):
    """How a parameter's raw value is laid out in 16-bit registers."""

    UINT16 = 'uint16'
    INT16 = 'int16'
    UINT32 = 'uint32'
    INT32 = 'int32'
    # CANopen objects only (e.g. 0x6060 modes of operation, INTEGER8): never Modbus registers.
    UINT8 = 'uint8'
    INT8 = 'int8'

    @property
    def register_count(self) -> int:
        return 2 if self in (ValueType.UINT32, ValueType.INT32) else 1

    @property
    def bits(self) -> int:
        """Width of the value on the wire (CANopen object size)."""
        if self in (ValueType.UINT8, ValueType.INT8):
            return 8
        return 16 * self.register_count

    @property
    def signed(self) -> bool:
        return self in (ValueType.INT8, ValueType.INT16, ValueType.INT32)

    @property
    def bounds(self) -> tuple[int, int]:
        bits = self.bits
        if self.signed:
            return -(1 << (bits - 1)), (1 << (bits - 1)) - 1
        return 0, (1 << bits) - 1


class WordOrder(str, enum.Enum):
    """Order of the two registers of a 32-bit value."""

    HIGH_FIRST = 'high_first'
    LOW_FIRST = 'low_first'


@dataclass(frozen=True)
class Parameter:
    """One entry of the drive's parameter table (a register or register pair)."""

    code: str
    address: int
    description: str
    type: ValueType = ValueType.UINT16
    scale: float = 1.0
    unit: str = ''
    minimum: float | None = None
    maximum: float | None = None
    default: float | None = None
    access: Access = Access.READ_WRITE
    options: Mapping[int, str] = field(default_factory=dict)
    name: str = ''
    word_order: WordOrder = WordOrder.HIGH_FIRST
    source: str = ''
    note: str = ''
    # CANopen object dictionary entry of the same value (None: not reachable over CANopen).
    index: int | None = None
    subindex: int = 0

    @property
    def register_count(self) -> int:
        return self.type.register_count

    @property
    def writable(self) -> bool:
        return self.access is not Access.READ_ONLY

    def from_raw(self, raw: int) -> float:
        """Engineering value of a raw (already sign-decoded) integer."""
        return raw * self.scale

    def to_raw(self, value: float) -> int:
        """Validate an engineering value and return the raw integer to write.

        Raises ParameterError (and nothing is written) when the value is not
        finite, outside the manual's range, not a multiple of the resolution, not
        one of the enumerated options, or does not fit the register type.
        """
        if not math.isfinite(value):
            raise ParameterError(f'{self.code}: value {value} is not a finite number')
        if self.minimum is not None and value < self.minimum - abs(self.scale) * 1e-6:
            raise ParameterError(
                f'{self.code}: {value:g}{self.unit} is below the minimum {self.minimum:g}'
                f'{self.unit}')
        if self.maximum is not None and value > self.maximum + abs(self.scale) * 1e-6:
            raise ParameterError(
                f'{self.code}: {value:g}{self.unit} is above the maximum {self.maximum:g}'
                f'{self.unit}')
        raw_float = value / self.scale
        low, high = self.type.bounds
        if not math.isfinite(raw_float) or not low - 1 <= raw_float <= high + 1:
            # Checked before rounding: 1e308 / 0.1 is inf, which round() cannot take.
            raise ParameterError(
                f'{self.code}: {value:g}{self.unit} is outside what the register can hold '
                f'({low * self.scale:g}..{high * self.scale:g}{self.unit})')
        raw = round(raw_float)
        if abs(raw_float - raw) > 1e-6 * max(1.0, abs(raw_float)):
            raise ParameterError(
                f'{self.code}: {value} is not a multiple of the resolution {self.scale:g}'
                f'{self.unit}')
        if self.options and raw not in self.options:
            allowed = ', '.join(f'{k} ({v})' for k, v in sorted(self.options.items()))
            raise ParameterError(f'{self.code}: {raw} is not one of the options: {allowed}')
        if not low <= raw <= high:
            raise ParameterError(
                f'{self.code}: raw value {raw} does not fit {self.type.value}')
        return raw

    def option_text(self, raw: int) -> str:
        return self.options.get(raw, '')


@dataclass(frozen=True)
class SerialDefaults:
    """The drive's factory serial settings (used as transport defaults)."""

    baudrate: int = 19200
    parity: str = 'N'
    stopbits: int = 1
    bytesize: int = 8


class PersistenceKind(str, enum.Enum):
    """How a drive tells RAM-only writes from EEPROM writes."""

    NONE = 'none'                      # every write goes where the drive decides
    SWITCH_PARAMETER = 'switch_parameter'  # a parameter selects it for all writes
    ADDRESS_OFFSET = 'address_offset'  # EEPROM address = RAM address + offset
    ADDRESS_FLAG = 'address_flag'      # RAM-only address = address | flag


@dataclass(frozen=True)
class Persistence:
    kind: PersistenceKind = PersistenceKind.NONE
    parameter: str = ''
    volatile_value: int = 0
    persistent_value: int = 0
    offset: int = 0
    flag: int = 0
    # Address ranges [low, high] the RAM/EEPROM choice applies to (empty = all);
    # other registers (process values) take plain writes only.
    applies_to: tuple[tuple[int, int], ...] = ()
    note: str = ''

    def covers(self, address: int) -> bool:
        return not self.applies_to or any(low <= address <= high
                                          for low, high in self.applies_to)


@dataclass(frozen=True)
class ModbusSpec:
    """Modbus limits and conventions of the drive family."""

    function_codes: frozenset[int] = frozenset({3, 6, 16})
    max_read_registers: int = 125
    max_write_registers: int = 123
    gaps_readable: bool = False
    serial: SerialDefaults = SerialDefaults()
    # Exception code on the wire -> its meaning in this drive's manual.
    exception_codes: Mapping[int, str] = field(default_factory=dict)
    # What the drive answers in each situation (used by the simulated twin).
    exception_for: Mapping[str, int] = field(default_factory=dict)
    persistence: Persistence = Persistence()


class SpeedUnit(str, enum.Enum):
    """Engineering unit of a speed setpoint or feedback register."""

    PERCENT = 'percent'   # percent of the motor's rated speed
    HZ = 'hz'             # output / synchronous frequency
    RPM = 'rpm'           # motor shaft speed


class DirectionMode(str, enum.Enum):
    """How the drive is told the direction of rotation."""

    SETPOINT_SIGN = 'setpoint_sign'   # signed setpoint, one run command
    COMMAND = 'command'               # unsigned setpoint, run_forward / run_reverse


@dataclass(frozen=True)
class VelocitySpec:
    setpoint: str
    setpoint_unit: SpeedUnit
    feedback_unit: SpeedUnit
    direction: DirectionMode = DirectionMode.SETPOINT_SIGN
    rated_speed: str = ''      # parameter codes for the motor nameplate defaults
    rated_frequency: str = ''
    pole_pairs: str = ''
    acceleration_time: str = ''
    deceleration_time: str = ''
    note: str = ''


@dataclass(frozen=True)
class ControlSpec:
    """The command register and the value written for each action."""

    command: str
    values: Mapping[str, int]
    # Written just before a run command when the drive starts on a rising edge.
    run_edge_from: int | None = None
    note: str = ''

    def action_of(self, value: int) -> str | None:
        for action, action_value in self.values.items():
            if action_value == value:
                return action
        return None


@dataclass(frozen=True)
class Signal:
    """A value polled from the drive, by role name (e.g. 'motor_speed')."""

    role: str
    code: str
    bits: tuple[int, int] | None = None
    every: int = 1

    def extract(self, raw: int) -> int:
        if self.bits is None:
            return raw
        low, high = self.bits
        return (raw >> low) & ((1 << (high - low + 1)) - 1)


class FlagRuleKind(str, enum.Enum):
    NONZERO = 'nonzero'
    ZERO = 'zero'
    NEGATIVE = 'negative'
    BIT = 'bit'
    EQUALS = 'equals'


@dataclass(frozen=True)
class FlagRule:
    """How a decoded status flag follows from a polled signal."""

    signal: str
    rule: FlagRuleKind
    bit: int = 0
    values: tuple[int, ...] = ()

    def evaluate(self, value: float) -> bool:
        if self.rule is FlagRuleKind.NONZERO:
            return value != 0
        if self.rule is FlagRuleKind.ZERO:
            return value == 0
        if self.rule is FlagRuleKind.NEGATIVE:
            return value < 0
        if self.rule is FlagRuleKind.BIT:
            return bool(int(value) >> self.bit & 1)
        return int(value) in self.values


@dataclass(frozen=True)
class FaultEntry:
    code: int
    name: str
    remedy: str
    cause: str = ''
    subcodes: Mapping[int, str] = field(default_factory=dict)
    confidence: str = 'high'
    source: str = ''
    note: str = ''


@dataclass(frozen=True)
class FaultSpec:
    code: str                  # parameter codes of the fault registers
    subcode: str = ''
    warning_code: str = ''
    warning_subcode: str = ''
    display_format: str = 'E{code}'
    table: Mapping[int, FaultEntry] = field(default_factory=dict)
    note: str = ''


@dataclass(frozen=True)
class CommTimeoutSpec:
    """The drive's own comm-loss watchdog (written at connect)."""

    parameter: str
    fault_code: int
    fault_subcode: int = 0
    note: str = ''


@dataclass(frozen=True)
class CommissioningWrite:
    """A parameter that must hold a value for the drive to obey the bus."""

    code: str
    value: float
    why: str = ''


class ControlStyle(str, enum.Enum):
    """How a CANopen drive is commanded."""

    CIA402 = 'cia402'              # CiA 402 state machine on a control/status word pair
    COMMAND_WORD = 'command_word'  # a manufacturer command word (values as in `control`)


class StopAction(str, enum.Enum):
    """What the CiA 402 `stop` action commands while operation is enabled."""

    DISABLE_OPERATION = 'disable_operation'   # ramp down, stay switched on
    QUICK_STOP = 'quick_stop'                 # quick-stop ramp (0x605A decides)


@dataclass(frozen=True)
class CanObject:
    """One CANopen object the driver maps into a PDO or writes at connect."""

    index: int
    subindex: int = 0
    type: ValueType = ValueType.UINT16
    scale: float = 1.0
    unit: str = ''
    code: str = ''      # the parameter it was taken from, if any

    @property
    def mapping(self) -> int:
        """The 32-bit PDO mapping entry (index, sub-index, length in bits)."""
        return (self.index << 16) | (self.subindex << 8) | self.type.bits

    def __str__(self) -> str:
        return f'0x{self.index:04X}:{self.subindex:02X}'


@dataclass(frozen=True)
class ObjectSet:
    """The objects that carry control and status over CANopen, and how they are used."""

    name: str
    control: ControlStyle
    controlword: CanObject
    statusword: CanObject
    target_velocity: CanObject
    velocity_unit: SpeedUnit
    # role -> object, mapped into the TPDOs in this order (roles as in `monitor`;
    # `status_word` and `motor_speed` first, they share TPDO1)
    monitor: Mapping[str, CanObject]
    # command_word style: the values written for run/stop/disable/fault_reset
    commands: Mapping[str, int] = field(default_factory=dict)
    mode_of_operation: CanObject | None = None
    mode_value: int = 0
    stop_action: StopAction = StopAction.DISABLE_OPERATION
    note: str = ''


class EmcyFault(str, enum.Enum):
    """Where an EMCY frame carries the drive's own fault code."""

    ERROR_CODE = 'error_code'       # bytes 0-1, the CiA 301/402 error code
    MANUFACTURER_BYTE = 'byte3'     # byte 3 (first manufacturer byte), e.g. Kinco E001 = 1


@dataclass(frozen=True)
class CanopenSpec:
    """CiA 301 limits of the drive family and the object sets it can be driven through."""

    object_set: str
    object_sets: Mapping[str, ObjectSet]
    heartbeat_ms: int = 100                 # written to 0x1017 at connect
    heartbeat_timeout_factor: float = 3.0   # host consumer timeout = factor x producer time
    rpdos: int = 4
    tpdos: int = 4
    transmission_type: int = 255
    tpdo_event_timer_ms: int = 0            # 0x18xx:05 (0 = send on change only)
    rpdo_deadline: bool = False             # 0x14xx:05 supervises RPDO reception
    heartbeat_consumer: bool = False        # 0x1016: the drive documents a heartbeat consumer
    expedited_only: bool = True
    emcy_fault: EmcyFault = EmcyFault.ERROR_CODE
    note: str = ''

    def selected(self, name: str = '') -> ObjectSet:
        key = name or self.object_set
        if key not in self.object_sets:
            raise ParameterError(
                f'unknown CANopen object set {key!r}; available: {", ".join(self.object_sets)}')
        return self.object_sets[key]


@dataclass(frozen=True)
class Profile:
    name: str
    vendor: str
    model: str
    manual: str
    transports: tuple[str, ...]
    parameters: Mapping[str, Parameter]
    modbus: ModbusSpec
    velocity: VelocitySpec
    control: ControlSpec
    monitor: tuple[Signal, ...]
    flags: Mapping[str, FlagRule]
    status_words: tuple[str, ...]
    faults: FaultSpec
    comm_timeout: CommTimeoutSpec | None = None
    commissioning: tuple[CommissioningWrite, ...] = ()
    # Extra setpoints published as ~/<topic> (Float64, engineering units), e.g.
    # the pressure and flow commands of a servo-pump drive: topic -> code.
    setpoints: Mapping[str, str] = field(default_factory=dict)
    notes: tuple[str, ...] = ()
    source_file: str = ''
    canopen: CanopenSpec | None = None
    # Registers the control loop writes (command word, setpoints, the comm-loss
    # timeout it manages, CiA 402 objects): code -> what to use instead. The
    # parameter services refuse them, so nothing moves the motor around the loop.
    control_owned: Mapping[str, str] = field(default_factory=dict)
    _by_name: Mapping[str, str] = field(default_factory=dict, repr=False)
    _by_address: Mapping[int, str] = field(default_factory=dict, repr=False)
    _by_folded_code: Mapping[str, str] = field(default_factory=dict, repr=False)

    def parameter(self, key: str) -> Parameter:
        """Look a parameter up by function code (any case) or readable name."""
        if key in self.parameters:
            return self.parameters[key]
        stripped = key.strip()
        code = self._by_folded_code.get(stripped.casefold())
        if code is not None:
            return self.parameters[code]
        if stripped in self._by_name:
            return self.parameters[self._by_name[stripped]]
        raise ParameterError(
            f'unknown parameter {quote(key)} for profile {self.name} '
            '(use a function code such as those in the manual, or a readable name)')

    def parameter_at(self, address: int) -> Parameter | None:
        code = self._by_address.get(address)
        return self.parameters[code] if code else None

    def signal(self, role: str) -> Signal | None:
        for signal in self.monitor:
            if signal.role == role:
                return signal
        return None

    @property
    def names(self) -> Mapping[str, str]:
        """Readable name -> function code."""
        return self._by_name


# --- loading ---------------------------------------------------------------

class _Reader:
    """Strict access to one YAML mapping: unknown keys are errors."""

    def __init__(self, data: Any, where: str) -> None:
        if not isinstance(data, Mapping):
            raise ProfileError(f'{where}: expected a mapping, got {type(data).__name__}')
        self.data = dict(data)
        self.where = where
        self.used: set[str] = set()

    def get(self, key: str, default: Any = ..., kind: type | tuple[type, ...] | None = None):
        self.used.add(key)
        if key not in self.data:
            if default is ...:
                raise ProfileError(f'{self.where}: missing key {key!r}')
            return default
        value = self.data[key]
        if kind is not None and not isinstance(value, kind):
            raise ProfileError(f'{self.where}.{key}: expected {kind}, got {value!r}')
        return value

    def sub(self, key: str, default: Any = ...) -> '_Reader':
        return _Reader(self.get(key, {} if default is ... else default), f'{self.where}.{key}')

    def done(self) -> None:
        extra = set(self.data) - self.used
        if extra:
            raise ProfileError(f'{self.where}: unknown keys {sorted(extra)}')


def _number(value: Any, where: str) -> float | None:
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ProfileError(f'{where}: expected a number, got {value!r}')
    return value


def _enum(cls: type[enum.Enum], value: Any, where: str):
    try:
        return cls(value)
    except ValueError:
        allowed = ', '.join(member.value for member in cls)
        raise ProfileError(f'{where}: {value!r} is not one of {allowed}') from None


def _parameter(data: Any, where: str) -> Parameter:
    r = _Reader(data, where)
    code = str(r.get('code'))
    value_type = _enum(ValueType, r.get('type', 'uint16'), f'{where}.type')
    options = {int(k): str(v) for k, v in (r.get('options', {}) or {}).items()}
    index = r.get('index', None, kind=(int, type(None)))
    # CANopen-only profiles name objects, not registers: address -1 = no Modbus register.
    address = r.get('address', ... if index is None else -1, kind=int)
    parameter = Parameter(
        code=code,
        address=int(address),
        description=str(r.get('description')),
        type=value_type,
        scale=float(_number(r.get('scale', 1.0), f'{where}.scale')),
        unit=str(r.get('unit', '') or ''),
        minimum=_number(r.get('min', None), f'{where}.min'),
        maximum=_number(r.get('max', None), f'{where}.max'),
        default=_number(r.get('default', None), f'{where}.default'),
        access=_enum(Access, r.get('access', 'rw'), f'{where}.access'),
        options=options,
        name=str(r.get('name', '') or ''),
        word_order=_enum(WordOrder, r.get('word_order', 'high_first'), f'{where}.word_order'),
        source=str(r.get('source', '') or ''),
        note=str(r.get('note', '') or ''),
        index=index,
        subindex=int(r.get('subindex', 0, kind=int)),
    )
    r.done()
    if parameter.scale == 0:
        raise ProfileError(f'{where}: scale must not be 0')
    if parameter.address != -1 and not 0 <= parameter.address <= 0xFFFF:
        raise ProfileError(f'{where}: address {parameter.address:#x} out of 16-bit range')
    if index is not None and not (0 <= index <= 0xFFFF and 0 <= parameter.subindex <= 0xFF):
        raise ProfileError(f'{where}: object {index:#x}:{parameter.subindex} out of range')
    return parameter


def _fault(data: Any, where: str) -> FaultEntry:
    r = _Reader(data, where)
    entry = FaultEntry(
        code=int(r.get('code', kind=int)),
        name=str(r.get('name')),
        remedy=str(r.get('remedy', '') or ''),
        cause=str(r.get('cause', '') or ''),
        subcodes={int(k): str(v) for k, v in (r.get('subcodes', {}) or {}).items()},
        confidence=str(r.get('confidence', 'high')),
        source=str(r.get('source', '') or ''),
        note=str(r.get('note', '') or ''),
    )
    r.done()
    return entry


def _signal(role: str, data: Any, where: str) -> Signal:
    if isinstance(data, str):
        return Signal(role=role, code=data)
    r = _Reader(data, where)
    bits = r.get('bits', None)
    signal = Signal(
        role=role,
        code=str(r.get('code')),
        bits=(int(bits[0]), int(bits[1])) if bits is not None else None,
        every=int(r.get('every', 1)),
    )
    r.done()
    return signal


def _flag(data: Any, where: str) -> FlagRule:
    r = _Reader(data, where)
    rule = FlagRule(
        signal=str(r.get('signal')),
        rule=_enum(FlagRuleKind, r.get('rule'), f'{where}.rule'),
        bit=int(r.get('bit', 0)),
        values=tuple(int(v) for v in r.get('values', []) or []),
    )
    r.done()
    return rule


def _can_object(data: Any, where: str, parameters: Mapping[str, Parameter]) -> CanObject:
    """Read a parameter code (its index, type, scale) or an inline {index, subindex, ...}."""
    if isinstance(data, str):
        parameter = parameters.get(data)
        if parameter is None or parameter.index is None:
            raise ProfileError(f'{where}: {data!r} is not a parameter with a CANopen index')
        return CanObject(parameter.index, parameter.subindex, parameter.type, parameter.scale,
                         parameter.unit, parameter.code)
    r = _Reader(data, where)
    obj = CanObject(
        index=int(r.get('index', kind=int)),
        subindex=int(r.get('subindex', 0, kind=int)),
        type=_enum(ValueType, r.get('type', 'uint16'), f'{where}.type'),
        scale=float(_number(r.get('scale', 1.0), f'{where}.scale')),
        unit=str(r.get('unit', '') or ''),
    )
    r.get('note', '')
    r.done()
    if obj.scale == 0:
        raise ProfileError(f'{where}: scale must not be 0')
    return obj


def _object_set(name: str, data: Any, where: str,
                parameters: Mapping[str, Parameter]) -> ObjectSet:
    r = _Reader(data, where)
    mode = r.get('mode_of_operation', None)
    object_set = ObjectSet(
        name=name,
        control=_enum(ControlStyle, r.get('control'), f'{where}.control'),
        controlword=_can_object(r.get('controlword'), f'{where}.controlword', parameters),
        statusword=_can_object(r.get('statusword'), f'{where}.statusword', parameters),
        target_velocity=_can_object(r.get('target_velocity'), f'{where}.target_velocity',
                                    parameters),
        velocity_unit=_enum(SpeedUnit, r.get('velocity_unit', 'rpm'), f'{where}.velocity_unit'),
        monitor={str(role): _can_object(obj, f'{where}.monitor.{role}', parameters)
                 for role, obj in r.get('monitor', kind=Mapping).items()},
        commands={str(k): int(v) for k, v in (r.get('commands', {}) or {}).items()},
        mode_of_operation=_can_object(mode, f'{where}.mode_of_operation', parameters)
        if mode is not None else None,
        mode_value=int(r.get('mode_value', 0)),
        stop_action=_enum(StopAction, r.get('stop_action', 'disable_operation'),
                          f'{where}.stop_action'),
        note=str(r.get('note', '') or ''),
    )
    r.done()
    for role in ('status_word', 'motor_speed'):
        if role not in object_set.monitor:
            raise ProfileError(f'{where}.monitor needs {role!r}')
    if object_set.control is ControlStyle.COMMAND_WORD:
        for action in ('run', 'stop', 'fault_reset'):
            if action not in object_set.commands:
                raise ProfileError(f'{where}.commands needs {action!r}')
    return object_set


def _canopen(data: Any, where: str, parameters: Mapping[str, Parameter]) -> CanopenSpec:
    r = _Reader(data, where)
    sets = r.get('object_sets', kind=Mapping)
    spec = CanopenSpec(
        object_set=str(r.get('object_set')),
        object_sets={str(name): _object_set(str(name), item, f'{where}.object_sets.{name}',
                                            parameters) for name, item in sets.items()},
        heartbeat_ms=int(r.get('heartbeat_ms', 100, kind=int)),
        heartbeat_timeout_factor=float(_number(r.get('heartbeat_timeout_factor', 3.0),
                                               f'{where}.heartbeat_timeout_factor')),
        rpdos=int(r.get('rpdos', 4, kind=int)),
        tpdos=int(r.get('tpdos', 4, kind=int)),
        transmission_type=int(r.get('transmission_type', 255, kind=int)),
        tpdo_event_timer_ms=int(r.get('tpdo_event_timer_ms', 0, kind=int)),
        rpdo_deadline=bool(r.get('rpdo_deadline', False, kind=bool)),
        heartbeat_consumer=bool(r.get('heartbeat_consumer', False, kind=bool)),
        expedited_only=bool(r.get('expedited_only', True, kind=bool)),
        emcy_fault=_enum(EmcyFault, r.get('emcy_fault', 'error_code'), f'{where}.emcy_fault'),
        note=str(r.get('note', '') or ''),
    )
    r.done()
    if spec.object_set not in spec.object_sets:
        raise ProfileError(f'{where}.object_set {spec.object_set!r} is not in object_sets')
    if not 1 <= spec.rpdos <= 512 or not 1 <= spec.tpdos <= 512:
        raise ProfileError(f'{where}: rpdos/tpdos must be 1..512')
    if spec.heartbeat_ms < 0 or spec.heartbeat_timeout_factor <= 1.0:
        raise ProfileError(f'{where}: heartbeat_ms >= 0 and heartbeat_timeout_factor > 1')
    return spec


def _read_yaml(path: Path) -> Any:
    try:
        with path.open(encoding='utf-8') as stream:
            # libyaml's loader when available: the parameter tables run to ~750 rows.
            return yaml.load(stream, Loader=getattr(yaml, 'CSafeLoader', yaml.SafeLoader))
    except OSError as exc:
        raise ProfileError(f'cannot read profile file {path}: {exc}') from exc
    except yaml.YAMLError as exc:
        raise ProfileError(f'profile file {path} is not valid YAML: {exc}') from exc


def load_profile_file(path: Path | str) -> Profile:
    """Load and validate one profile file (and the files it includes).

    Every defect of the data is reported as a ProfileError naming the file.
    """
    path = Path(path)
    try:
        return _load_profile_file(path)
    except ProfileError:
        raise
    except (ValueError, TypeError, AttributeError, KeyError, IndexError) as exc:
        raise ProfileError(f'{path.name}: malformed value: {exc!r}') from exc


def _load_profile_file(path: Path) -> Profile:
    r = _Reader(_read_yaml(path), path.name)
    if r.get('schema') != 1:
        raise ProfileError(f'{path.name}: unsupported schema (expected schema: 1)')

    parameters: dict[str, Parameter] = {}
    raw_parameters = list(r.get('parameters', []) or [])
    for include in r.get('parameter_tables', []) or []:
        included = _Reader(_read_yaml(path.parent / include), include)
        raw_parameters.extend(included.get('parameters', []) or [])
        included.get('note', '')
        included.get('source', '')
        included.done()
    for index, item in enumerate(raw_parameters):
        parameter = _parameter(item, f'{path.name}.parameters[{index}]')
        if parameter.code in parameters:
            raise ProfileError(f'{path.name}: parameter {parameter.code} defined twice')
        parameters[parameter.code] = parameter

    by_name: dict[str, str] = {}
    by_address: dict[int, str] = {}
    for parameter in parameters.values():
        if parameter.name:
            if parameter.name in by_name:
                raise ProfileError(f'{path.name}: readable name {parameter.name!r} used twice')
            by_name[parameter.name] = parameter.code
        if parameter.address >= 0:
            by_address.setdefault(parameter.address, parameter.code)

    mb = r.sub('modbus', {})
    serial = mb.sub('serial', {})
    serial_defaults = SerialDefaults(
        baudrate=int(serial.get('baudrate', 19200)), parity=str(serial.get('parity', 'N')),
        stopbits=int(serial.get('stopbits', 1)), bytesize=int(serial.get('bytesize', 8)))
    serial.done()
    pers = mb.sub('persistence', {})
    persistence = Persistence(
        kind=_enum(PersistenceKind, pers.get('kind', 'none'), 'modbus.persistence.kind'),
        parameter=str(pers.get('parameter', '')),
        volatile_value=int(pers.get('volatile_value', 0)),
        persistent_value=int(pers.get('persistent_value', 0)),
        offset=int(pers.get('offset', 0)),
        flag=int(pers.get('flag', 0)),
        applies_to=tuple((int(low), int(high)) for low, high in pers.get('applies_to', []) or []),
        note=str(pers.get('note', '')),
    )
    pers.done()
    modbus = ModbusSpec(
        function_codes=frozenset(int(c) for c in mb.get('function_codes', [3, 6, 16])),
        max_read_registers=int(mb.get('max_read_registers', 125)),
        max_write_registers=int(mb.get('max_write_registers', 123)),
        gaps_readable=bool(mb.get('gaps_readable', False)),
        serial=serial_defaults,
        exception_codes={int(k): str(v) for k, v in (mb.get('exception_codes', {}) or {}).items()},
        exception_for={str(k): int(v) for k, v in (mb.get('exception_for', {}) or {}).items()},
        persistence=persistence,
    )
    mb.get('note', '')
    mb.done()

    vel = r.sub('velocity')
    velocity = VelocitySpec(
        setpoint=str(vel.get('setpoint')),
        setpoint_unit=_enum(SpeedUnit, vel.get('setpoint_unit'), 'velocity.setpoint_unit'),
        feedback_unit=_enum(SpeedUnit, vel.get('feedback_unit'), 'velocity.feedback_unit'),
        direction=_enum(DirectionMode, vel.get('direction', 'setpoint_sign'),
                        'velocity.direction'),
        rated_speed=str(vel.get('rated_speed', '')),
        rated_frequency=str(vel.get('rated_frequency', '')),
        pole_pairs=str(vel.get('pole_pairs', '')),
        acceleration_time=str(vel.get('acceleration_time', '')),
        deceleration_time=str(vel.get('deceleration_time', '')),
        note=str(vel.get('note', '')),
    )
    vel.done()

    ctl = r.sub('control')
    edge = ctl.get('run_edge_from', None)
    control = ControlSpec(
        command=str(ctl.get('command')),
        values={str(k): int(v) for k, v in ctl.get('values', kind=Mapping).items()},
        run_edge_from=int(edge) if edge is not None else None,
        note=str(ctl.get('note', '')),
    )
    ctl.done()

    mon = r.get('monitor', kind=Mapping)
    monitor = tuple(_signal(str(role), data, f'monitor.{role}') for role, data in mon.items())
    flags = {str(name): _flag(data, f'flags.{name}')
             for name, data in (r.get('flags', {}) or {}).items()}

    flt = r.sub('faults')
    faults_display = str(flt.get('display_format', 'E{code}'))
    table: dict[int, FaultEntry] = {}
    for index, item in enumerate(flt.get('table', []) or []):
        entry = _fault(item, f'faults.table[{index}]')
        if entry.code in table:
            raise ProfileError(f'{path.name}: fault code {entry.code} defined twice')
        table[entry.code] = entry
    faults = FaultSpec(
        code=str(flt.get('code')), subcode=str(flt.get('subcode', '')),
        warning_code=str(flt.get('warning_code', '')),
        warning_subcode=str(flt.get('warning_subcode', '')),
        display_format=faults_display, table=table, note=str(flt.get('note', '')))
    flt.done()

    comm_timeout = None
    if 'comm_timeout' in r.data:
        ct = r.sub('comm_timeout')
        comm_timeout = CommTimeoutSpec(
            parameter=str(ct.get('parameter')), fault_code=int(ct.get('fault_code')),
            fault_subcode=int(ct.get('fault_subcode', 0)), note=str(ct.get('note', '')))
        ct.done()
    else:
        r.get('comm_timeout', None)

    commissioning = []
    for index, item in enumerate(r.get('commissioning', []) or []):
        cr = _Reader(item, f'commissioning[{index}]')
        commissioning.append(CommissioningWrite(
            code=str(cr.get('code')), value=float(cr.get('value')), why=str(cr.get('why', ''))))
        cr.done()

    canopen = _canopen(r.get('canopen'), 'canopen', parameters) \
        if r.get('canopen', None) is not None else None
    extra_owned = {str(k): str(v) for k, v in (r.get('control_owned', {}) or {}).items()}

    profile = Profile(
        name=str(r.get('name')),
        vendor=str(r.get('vendor')),
        model=str(r.get('model')),
        manual=str(r.get('manual')),
        transports=tuple(str(t) for t in r.get('transports', ['modbus_rtu'])),
        parameters=parameters,
        modbus=modbus,
        velocity=velocity,
        control=control,
        monitor=monitor,
        flags=flags,
        status_words=tuple(str(c) for c in r.get('status_words', []) or []),
        faults=faults,
        comm_timeout=comm_timeout,
        commissioning=tuple(commissioning),
        setpoints={str(k): str(v) for k, v in (r.get('setpoints', {}) or {}).items()},
        notes=tuple(str(n) for n in r.get('notes', []) or []),
        source_file=str(path),
        canopen=canopen,
        _by_name=by_name,
        _by_address=by_address,
        _by_folded_code={code.casefold(): code for code in parameters},
    )
    r.done()
    _check_references(profile)
    for code in extra_owned:
        if code not in parameters:
            raise ProfileError(f'{path.name}: control_owned names {code!r}, not in the '
                               'parameter table')
    profile = dataclasses.replace(profile, control_owned={
        **_control_owned(profile), **extra_owned})
    _check_defaults(profile)
    return profile


def _control_owned(profile: Profile) -> dict[str, str]:
    """Find the registers the control loop writes, from the profile's own references."""
    owned = {
        profile.control.command: "the command word is the control loop's: use ~/enable, "
                                 '~/disable, ~/stop and ~/reset_fault',
        profile.velocity.setpoint: "the speed setpoint is the control loop's: publish on "
                                   '~/velocity_command',
    }
    for topic, code in profile.setpoints.items():
        owned[code] = f'this setpoint is written from the ~/{topic} topic'
    if profile.comm_timeout is not None:
        owned[profile.comm_timeout.parameter] = (
            'the comm-loss timeout is written at connect from the drive_comm_timeout '
            'parameter, sized for the bus')
    if profile.canopen is not None:
        # CiA 402 objects and their manufacturer twins, in every object set the
        # profile offers (another set may alias the same object).
        indices: dict[tuple[int, int], str] = {}
        for objects in profile.canopen.object_sets.values():
            for obj, what in ((objects.controlword, 'the controlword'),
                              (objects.target_velocity, 'the target velocity'),
                              (objects.mode_of_operation, 'the mode of operation')):
                if obj is not None:
                    indices[(obj.index, obj.subindex)] = what
        for parameter in profile.parameters.values():
            what = indices.get((parameter.index, parameter.subindex)) \
                if parameter.index is not None else None
            if what is not None and parameter.code not in owned:
                owned[parameter.code] = (f"{what} is the control loop's (written every "
                                         'cycle or at connect): use the topics and services')
    return owned


def _check_defaults(profile: Profile) -> None:
    """Every factory default must be a value the driver would accept for its parameter."""
    for parameter in profile.parameters.values():
        if parameter.default is None:
            continue
        try:
            parameter.to_raw(parameter.default)
        except ParameterError as exc:
            raise ProfileError(f'{profile.source_file}: the factory default of '
                               f'{parameter.code} is not a valid value: {exc}') from exc


def _check_references(profile: Profile) -> None:
    """Every code the profile names must be in its parameter table."""
    where = profile.source_file
    referenced = [
        ('velocity.setpoint', profile.velocity.setpoint),
        ('control.command', profile.control.command),
        ('faults.code', profile.faults.code),
    ]
    for label in ('rated_speed', 'rated_frequency', 'pole_pairs',
                  'acceleration_time', 'deceleration_time'):
        code = getattr(profile.velocity, label)
        if code:
            referenced.append((f'velocity.{label}', code))
    for label in ('subcode', 'warning_code', 'warning_subcode'):
        code = getattr(profile.faults, label)
        if code:
            referenced.append((f'faults.{label}', code))
    referenced += [(f'monitor.{s.role}', s.code) for s in profile.monitor]
    referenced += [(f'status_words[{i}]', c) for i, c in enumerate(profile.status_words)]
    referenced += [(f'commissioning.{c.code}', c.code) for c in profile.commissioning]
    referenced += [(f'setpoints.{topic}', code) for topic, code in profile.setpoints.items()]
    if profile.comm_timeout:
        referenced.append(('comm_timeout.parameter', profile.comm_timeout.parameter))
    if profile.modbus.persistence.kind is PersistenceKind.SWITCH_PARAMETER:
        referenced.append(('modbus.persistence.parameter', profile.modbus.persistence.parameter))
    for label, code in referenced:
        if code not in profile.parameters:
            raise ProfileError(f'{where}: {label} names {code!r}, not in the parameter table')
    roles = {s.role for s in profile.monitor}
    for name, rule in profile.flags.items():
        if rule.signal not in roles:
            raise ProfileError(f'{where}: flags.{name} uses signal {rule.signal!r}, '
                               'which monitor does not define')
    for required in ('run', 'stop', 'fault_reset'):
        if required not in profile.control.values:
            raise ProfileError(f'{where}: control.values needs {required!r}')
    if profile.velocity.direction is DirectionMode.COMMAND and \
            'run_reverse' not in profile.control.values:
        raise ProfileError(f'{where}: direction "command" needs control.values.run_reverse')
    for topic, code in profile.setpoints.items():
        if not profile.parameters[code].writable:
            raise ProfileError(f'{where}: setpoints.{topic} names read-only {code}')
    for signal in profile.monitor:
        if signal.every < 1:
            raise ProfileError(f'{where}: monitor.{signal.role}.every must be >= 1')


def available_profiles() -> list[str]:
    """Names of the profiles shipped with the package."""
    return sorted(p.stem for p in PROFILE_DIR.glob('*.yaml')
                  if not p.stem.endswith('_parameters'))


def load_profile(name_or_path: str) -> Profile:
    """Load a shipped profile by name, or any profile file by path."""
    candidate = Path(name_or_path)
    if candidate.suffix in ('.yaml', '.yml'):
        return load_profile_file(candidate)
    path = PROFILE_DIR / f'{name_or_path}.yaml'
    if not path.exists():
        raise ProfileError(
            f'unknown drive profile {name_or_path!r}; shipped profiles: '
            f'{", ".join(available_profiles())}')
    return load_profile_file(path)


def main(argv: list[str] | None = None) -> int:
    """Check profile files: ``python -m vfd_ros2.profile [name|path ...]``."""
    import sys
    names = (argv if argv is not None else sys.argv[1:]) or available_profiles()
    status = 0
    for name in names:
        try:
            profile = load_profile(name)
        except ProfileError as exc:
            print(f'FAIL {name}: {exc}')
            status = 1
            continue
        print(f'ok   {profile.name}: {len(profile.parameters)} parameters, '
              f'{len(profile.faults.table)} faults, {len(profile.monitor)} monitored signals')
    return status


if __name__ == '__main__':
    raise SystemExit(main())
