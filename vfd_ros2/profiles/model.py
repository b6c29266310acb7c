"""A drive family as frozen dataclasses (built by ``loader`` from the YAML data).

Everything the driver and the simulated twins need to know about a drive family:
the parameter (register / object) table with scaling, ranges and access; which
registers carry the command, setpoint, status and measured values; the command
values; the fault and exception tables with the manual's words; the Modbus and
CANopen limits. A new family is a new data file, never a new ``if`` in the code.
"""

from __future__ import annotations

import dataclasses
import enum
import functools
import math
import re
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Callable, Mapping

from ..errors import ParameterError, quote
from ..protocol.scaling import SpeedUnit
from ..protocol.values import ValueType, WordOrder

__all__ = [
    'Access', 'CanObject', 'CanopenIdentity', 'CanopenSpec', 'CommTimeoutSpec',
    'CommissioningWrite', 'ControlSpec', 'ControlStyle', 'DirectionMode', 'EffortKind',
    'EffortSpec', 'EmcyFault', 'EmcyMapping', 'EthercatIdentity', 'EthercatSpec',
    'FaultEntry', 'FaultSpec', 'FlagRule', 'FlagRuleKind', 'FunctionCodeWindow',
    'IdentifyCheck', 'IdentifyExpect', 'IdentifySpec', 'ModbusIdentity', 'ModbusSpec',
    'ObjectSet', 'Parameter', 'ParameterAccess', 'Persistence', 'PersistenceKind',
    'PositionSource', 'PositionSpec', 'Profile', 'SerialDefaults', 'Signal', 'SpeedUnit',
    'StopAction', 'ValueType', 'VelocitySpec', 'WordOrder',
]

class Access(str, enum.Enum):
    """Who may write a parameter, and when."""

    READ_ONLY = 'ro'
    READ_WRITE = 'rw'
    WRITE_WHEN_STOPPED = 'rw_stopped'


@functools.lru_cache(maxsize=64)
def _decimals(scale: float) -> int:
    """Return the decimals that write ``scale`` exactly (0.1: 1, 0.05: 2; at most 12)."""
    return next((d for d in range(13) if round(scale, d) == scale), 12)


#: a CANopen / CoE object as ``0x6083:00`` (index and subindex in hex, as the manuals write)
OBJECT_ADDRESS = re.compile(r'0[xX]([0-9a-fA-F]{1,4}):(?:0[xX])?([0-9a-fA-F]{1,2})')


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
        """Engineering value of a raw (already sign-decoded) integer.

        On the resolution's decimals: 3 x 0.1 s is 0.3 s, not 0.30000000000000004
        (an integrator comparing a read value with what was written gets equality).
        """
        value = raw * self.scale
        return value if self.scale == 1.0 else round(value, _decimals(self.scale))

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
                f'{self.code}: {value!r}{self.unit} is below the minimum {self.minimum:g}'
                f'{self.unit}')
        if self.maximum is not None and value > self.maximum + abs(self.scale) * 1e-6:
            raise ParameterError(
                f'{self.code}: {value!r}{self.unit} is above the maximum {self.maximum:g}'
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


#: the Modbus application protocol's exception code for each situation, where a
#: manual names none (V1.1b3, 7: 01 illegal function, 02 illegal data address, 03
#: illegal data value, a count out of range included; 04 server device failure)
STANDARD_EXCEPTION_FOR: Mapping[str, int] = MappingProxyType({
    'illegal_function': 1, 'illegal_address': 2, 'illegal_value': 3,
    'too_many_registers': 3, 'read_only': 2, 'stopped_only': 4,
})
#: the exception codes the Modbus standard gives a condition that passes (V1.1b3, 7):
#: 05 acknowledge (still working), 06 server busy, 0A gateway path unavailable, 0B
#: gateway target device failed to respond
PASSING = frozenset({5, 6, 10, 11})


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

    def exception_code(self, situation: str) -> int:
        """Return the code this drive answers in ``situation`` (its manual's, else standard)."""
        codes = self.exception_for
        code = codes.get(situation)
        if code is None and situation == 'too_many_registers':
            code = codes.get('illegal_value', codes.get('illegal_address'))
        if code is None and situation in ('read_only', 'stopped_only'):
            code = codes.get('illegal_address')
        return STANDARD_EXCEPTION_FOR[situation] if code is None else code

    def lasting_refusal(self, code: int, write: bool = True) -> bool:
        """Return whether exception ``code`` is this drive's answer to the request itself.

        Asked again, it refuses again: every code but those the standard gives a
        passing condition (busy, acknowledge, a gateway whose drive does not
        answer), unless this drive's manual gives the code a meaning of its own
        (the BONENG AM's 05 is "read only", its 06 "modify only while stopped").
        A meaning only a write can have is not the answer to a read: an AM's 06 to
        a status read is the standard's busy.
        """
        if code not in PASSING:
            return True
        if code not in self.exception_codes:
            return False
        return write or code not in (self.exception_code('read_only'),
                                     self.exception_code('stopped_only'))


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
    pole_pairs: str = ''
    acceleration_time: str = ''
    deceleration_time: str = ''
    note: str = ''
    #: where a percent setpoint's 100 % is the motor's rated frequency, not its rated
    #: speed: that parameter; 100 % = its synchronous speed, rated_frequency x 60 / pole_pairs
    rated_frequency: str = ''

    def percent_base_rpm(self, value_of: Callable[[str], float], fallback: float) -> float:
        """Return the motor rpm a percent setpoint's 100 % stands for.

        ``value_of(code)`` gives a nameplate parameter's value (0 where unknown);
        ``fallback`` where the profile names none or the value is 0.
        """
        if self.rated_frequency:
            hertz = value_of(self.rated_frequency)
            pairs = value_of(self.pole_pairs) if self.pole_pairs else 0.0
            return hertz * 60.0 / pairs if hertz > 0 and pairs > 0 else fallback
        if self.rated_speed:
            return value_of(self.rated_speed) or fallback
        return fallback


class PositionSource(str, enum.Enum):
    """Where a wheel's joint position comes from."""

    DRIVE = 'drive'              # a counter the drive reports (encoder counts, 0x6064)
    INTEGRATED = 'integrated'    # none documented: the driver integrates the measured speed


@dataclass(frozen=True)
class PositionSpec:
    """The joint position: a monitored counter, or the measured speed integrated."""

    source: PositionSource = PositionSource.INTEGRATED
    signal: str = ''              # monitor role carrying the count (source drive)
    counts_per_rev: float = 0.0   # counts per MOTOR revolution (the gear ratio is the node's)
    note: str = ''

    @property
    def from_drive(self) -> bool:
        return self.source is PositionSource.DRIVE


class EffortKind(str, enum.Enum):
    """What the effort signal measures."""

    TORQUE = 'torque'                    # N·m at the motor shaft
    TORQUE_PERCENT = 'torque_percent'    # % of the motor's rated torque


@dataclass(frozen=True)
class EffortSpec:
    """The monitored value that gives JointState.effort."""

    signal: str
    kind: EffortKind
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
    """A parameter that must hold a value for the drive to obey the bus, or for the driver.

    ``bus_control`` false: a setting the driver relies on (a display unit, the reaction
    to a lost master) that does not itself hand the drive to the bus; the simulated
    twins obey the bus whatever its value.
    """

    code: str
    value: float
    why: str = ''
    bus_control: bool = True


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
    # controlword bits OR-ed into every command (CiA 402 vl mode: bits 4-6 = 0x70,
    # ramp function generator enable / unlock / use reference)
    controlword_bits: int = 0
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
    transmission_type: int = 255            # 1..240: on SYNC (the host sends one per cycle)
    tpdo_event_timer_ms: int = 0            # 0x18xx:05 (0 = send on change only)
    rpdo_deadline: bool = False             # 0x14xx:05 supervises RPDO reception
    heartbeat_consumer: bool = False        # 0x1016: the drive documents a heartbeat consumer
    emcy_fault: EmcyFault = EmcyFault.ERROR_CODE
    note: str = ''

    def selected(self, name: str = '') -> ObjectSet:
        key = name or self.object_set
        if key not in self.object_sets:
            raise ParameterError(
                f'unknown CANopen object set {key!r}; available: {", ".join(self.object_sets)}')
        return self.object_sets[key]


class ParameterAccess(str, enum.Enum):
    """How an EtherCAT drive's parameters are reached over CoE."""

    OBJECTS = 'objects'                # each parameter's own object (``index``), SDO
    FUNCTION_CODES = 'function_codes'  # a vendor window: address in, value out (IMO 0x2000)


@dataclass(frozen=True)
class FunctionCodeWindow:
    """Vendor objects that read and write function codes by address (UINT32 each).

    Read: write ``address << 16`` to ``read``, read ``status << 16 | value`` from
    ``read_response``; write: ``address << 16 | value`` to ``write``, the result
    from ``write_response``. ``success`` is the status of a good answer; any
    other status carries an error code (``errors``: code -> text).
    """

    read: int
    read_response: int
    write: int
    write_response: int
    success: int = 0x0001
    errors: Mapping[int, str] = field(default_factory=dict)
    #: the addresses it reaches (low, high): function codes, not another card's registers
    addresses: tuple[int, int] = (0x0000, 0xFFFF)


@dataclass(frozen=True)
class EmcyMapping:
    """A CoE emergency error code that means one of the profile's own faults."""

    error_code: int
    fault: int
    subcode: int = 0
    why: str = ''


@dataclass(frozen=True)
class EthercatIdentity:
    """What the slave's SII must say (None: the manual does not give it, not checked)."""

    vendor_id: int | None = None
    product_code: int | None = None
    device_name: str = ''               # checked only when vendor and product are unknown
    why: str = ''


@dataclass(frozen=True)
class EthercatSpec:
    """A CoE (CiA 402 over EtherCAT) drive: identity, process data, sync, parameters, faults.

    The RxPDO carries ``objects.controlword`` then ``objects.target_velocity``; the
    TxPDO carries ``objects.monitor`` in its order (status word first).
    """

    identity: EthercatIdentity
    rx_pdos: tuple[int, ...]            # SM2 assignment 0x1C12
    tx_pdos: tuple[int, ...]            # SM3 assignment 0x1C13
    objects: ObjectSet
    fixed_mapping: bool = False         # the mapping objects are read-only: not written
    free_run: bool = True
    dc: bool = False
    sync_cycles_us: tuple[int, ...] = ()   # cycle times the drive accepts (empty: any)
    parameter_access: ParameterAccess = ParameterAccess.OBJECTS
    function_codes: FunctionCodeWindow | None = None
    emcy_fault: EmcyFault = EmcyFault.ERROR_CODE
    emcy_faults: tuple[EmcyMapping, ...] = ()
    commissioning: tuple[CommissioningWrite, ...] = ()
    # the fault the drive raises when process data stops (its SM watchdog / comm timeout)
    comm_fault: tuple[int, int] | None = None
    # Objects reachable only over this bus (no Modbus register), e.g. the BONENG MH EC's
    # CiA 402 ramps: added to the profile's parameters by the EtherCAT drive only.
    parameters: Mapping[str, Parameter] = field(default_factory=dict)
    note: str = ''

    @property
    def rx_entries(self) -> tuple[CanObject, ...]:
        return (self.objects.controlword, self.objects.target_velocity)

    @property
    def tx_entries(self) -> tuple[tuple[str, CanObject], ...]:
        return tuple(self.objects.monitor.items())


class IdentifyExpect(str, enum.Enum):
    """What answer to an identification read identifies the family."""

    ANSWERS = 'answers'        # a normal reply of the right length
    EQUALS = 'equals'          # a normal reply holding one of the values
    EXCEPTION = 'exception'    # the drive's own exception code for that read


@dataclass(frozen=True)
class IdentifyCheck:
    """One read (function 03) and the answer that belongs to the family."""

    address: int
    count: int
    expect: IdentifyExpect
    code: str = ''                       # the parameter read ('' = an undocumented address)
    values: tuple[int, ...] = ()         # EQUALS: raw values (the first register)
    exception: int = 0                   # EXCEPTION: the code on the wire
    why: str = ''

    @property
    def where(self) -> str:
        return self.code or f'0x{self.address:04X}'

    def describe(self) -> str:
        if self.expect is IdentifyExpect.EQUALS:
            shown = ' or '.join(f'0x{v:04X}' for v in self.values)
            return f'{self.where} = {shown}'
        if self.expect is IdentifyExpect.EXCEPTION:
            return f'{self.where} answers exception {self.exception}'
        return f'{self.where} answers'


@dataclass(frozen=True)
class ModbusIdentity:
    """Where a scan looks for the family on a Modbus line and how it recognises it."""

    probe_address: int
    probe_count: int
    checks: tuple[IdentifyCheck, ...]
    baudrates: tuple[int, ...] = ()      # documented options, most likely first
    formats: tuple[str, ...] = ()        # e.g. ('8N1', '8E1'); data bits, parity, stop bits

    @property
    def confidence(self) -> str:
        """What a full match is worth: an identification value is proof, a shape is not."""
        if any(check.expect is IdentifyExpect.EQUALS for check in self.checks):
            return 'high'
        return 'medium'


@dataclass(frozen=True)
class CanopenIdentity:
    """What 0x1000 / 0x1018 of the family's drives hold (None: not documented)."""

    device_profile: int | None = None    # 0x1000 bits 0-15 (402 = drive)
    vendor_id: int | None = None         # 0x1018:01
    product_code: int | None = None      # 0x1018:02
    why: str = ''


@dataclass(frozen=True)
class IdentifySpec:
    """How commissioning tools find, recognise and reach a drive of the family."""

    # Codes whose values identify the firmware / parameter table: recorded in a
    # parameter dump and compared before a restore.
    firmware: tuple[str, ...] = ()
    # Codes that change how the drive is reached (address, baud rate, framing, IP):
    # a restore writes them last, and only when asked.
    link_parameters: tuple[str, ...] = ()
    modbus: ModbusIdentity | None = None
    canopen: CanopenIdentity | None = None
    note: str = ''
    source: str = ''


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
    ethercat: EthercatSpec | None = None
    # Registers the control loop writes (command word, setpoints, the comm-loss
    # timeout it manages, CiA 402 objects): code -> what to use instead. The
    # parameter services refuse them, so nothing moves the motor around the loop.
    control_owned: Mapping[str, str] = field(default_factory=dict)
    # Settings that open another way to move the motor (a second setpoint source, a jog
    # or direction input, an automatic fault reset or restart): code -> why. A running
    # node's parameter services refuse them; a commissioning tool (vfd_params) may set them.
    motion_channels: Mapping[str, str] = field(default_factory=dict)
    # How vfd_scan / vfd_params find and recognise the family (None: not described).
    identify: IdentifySpec | None = None
    # The joint position (JointState.position, odometry) and effort (None: not measured).
    position: PositionSpec = PositionSpec()
    effort: EffortSpec | None = None
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
        if (found := OBJECT_ADDRESS.fullmatch(stripped)) is not None:
            index, subindex = int(found[1], 16), int(found[2], 16)
            for parameter in self.parameters.values():
                if (parameter.index, parameter.subindex) == (index, subindex):
                    return parameter
        objects = any(parameter.index is not None for parameter in self.parameters.values())
        hint = ''
        if stripped.isdigit() and any(parameter.index == int(stripped)
                                      for parameter in self.parameters.values()):
            # ros2 service call's YAML reads an unquoted 0x6083 as the number 24707
            hint = (f'; 0x{int(stripped):04X} unquoted in YAML is the number {stripped}: '
                    f"quote it, '0x{int(stripped):04X}'")
        raise ParameterError(
            f'unknown parameter {quote(key)} for profile {self.name} '
            '(use a function code such as those in the manual'
            + (", one of the table's objects as 0xINDEX or 0xINDEX:SUBINDEX" if objects else '')
            + f', or a readable name{hint})')

    def parameter_at(self, address: int) -> Parameter | None:
        code = self._by_address.get(address)
        return self.parameters[code] if code else None

    def signal(self, role: str) -> Signal | None:
        for signal in self.monitor:
            if signal.role == role:
                return signal
        return None

    def extended(self, extra: Mapping[str, Parameter]) -> 'Profile':
        """Return this profile with ``extra`` parameters added (a bus's own objects)."""
        if not extra:
            return self
        by_name = dict(self._by_name)
        for code, parameter in extra.items():
            if parameter.name:
                by_name[parameter.name] = code
        return dataclasses.replace(
            self, parameters={**self.parameters, **extra}, _by_name=by_name,
            _by_folded_code={**self._by_folded_code,
                             **{code.casefold(): code for code in extra}})

    @property
    def names(self) -> Mapping[str, str]:
        """Readable name -> function code."""
        return self._by_name
