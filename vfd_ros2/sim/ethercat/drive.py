"""A simulated CiA 402 velocity drive behind an ESC, described by plain data (``DriveSpec``).

What it does, and from where:
- CiA 402 device control (CiA 402-2 section 6.2) through ``vfd_ros2.protocol.cia402``:
  controlword 0x6040 -> state, statusword 0x6041 from the state (+ voltage
  enabled, remote, target reached); fault reset on the rising edge of bit 7.
- Velocity in vl mode (6060 = 2: 0x6042 target, 0x6043 demand, 0x6044 actual,
  INT16 rpm; ramps 0x6048/0x6049/0x604A, limit 0x6046) and in pv/csv mode
  (6060 = 3/9: 0x60FF target, 0x606C actual, INT32); other modes hold still.
  The speed follows a ramp; quick stop and fault reaction use the quick-stop ramp.
- PDO assignment 0x1C12/0x1C13 and mapping objects 0x1600.../0x1A00... written
  in PRE-OP with the CiA 301 procedure (sub 0 = 0, entries, sub 0 = n), or
  fixed mapping objects (e.g. BONENG 0x1701/0x1B01) selected by assignment.
- Faults: ``inject_fault`` -> fault reaction (quick-stop ramp) -> FAULT, 0x603F
  and 0x1001 set, a CoE emergency; a reset sends the emergency 0x0000.
- SM watchdog expiry (ESC) -> fault 0x8250 "RPDO timeout" (CiA 301 table 21)
  with an emergency, as a drive that lost its master must stop.
- Optional vendor function-code access over SDO 0x2000-0x2003 (IMO HD2 card,
  manual section 4.6): write 0x2000 = address << 16, read 0x2001.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass, field
from typing import Any

from ...protocol.cia402 import STATUSWORD_OF, ControlBit, State, StatusBit, transition
from ...protocol.ethercat import ALState, ALStatusCode, SdoAbortCode
from .application import Emergency, TransitionContext
from .objects import Access, DataType, Entry, ObjectDictionary
from .sii import PdoEntryInfo, PdoInfo, SiiData, SyncManagerConfig, SyncManagerType, build_image

#: CiA 402 modes of operation (0x6060) the simulation moves in
MODE_VL = 2
MODE_PV = 3
MODE_CSV = 9
VELOCITY_MODES = (MODE_VL, MODE_PV, MODE_CSV)

#: CiA 301 error register bits (0x1001) and emergency codes (table 21)
ERROR_REGISTER_GENERIC = 0x01
ERROR_REGISTER_COMMUNICATION = 0x10
EMCY_NO_ERROR = 0x0000
EMCY_RPDO_TIMEOUT = 0x8250

_PDO_RANGES = {'rx': (0x1600, 0x17FF), 'tx': (0x1A00, 0x1BFF)}


@dataclass(frozen=True)
class ObjectSpec:
    """An object entry as data; ``value`` is the default."""

    index: int
    subindex: int
    name: str
    data_type: DataType
    access: Access
    value: Any = 0
    pdo_mappable: bool = False
    minimum: int | None = None
    maximum: int | None = None
    max_length: int = 0


@dataclass(frozen=True)
class PdoSpec:
    """A PDO mapping object: its default entries ``(index, subindex, bits)``."""

    index: int
    entries: tuple[tuple[int, int, int], ...]
    fixed: bool = False                  # mapping read-only (e.g. BONENG 0x1701)
    max_entries: int = 8


@dataclass(frozen=True)
class DriveSpec:
    """Everything that makes one drive family: identity, layout, objects, behaviour."""

    name: str
    vendor_id: int
    product_code: int
    revision: int
    serial: int
    device_type: int
    rx_pdos: tuple[PdoSpec, ...]
    tx_pdos: tuple[PdoSpec, ...]
    rx_assign: tuple[int, ...]
    tx_assign: tuple[int, ...]
    assign_writable: bool = True
    modes: tuple[int, ...] = (MODE_VL,)
    default_mode: int = MODE_VL
    mode_writable: bool = True
    rated_rpm: float = 1500.0
    max_rpm: float = 1500.0
    accel_time_s: float = 5.0            # 0 -> rated speed
    decel_time_s: float = 5.0
    quick_stop_time_s: float = 1.0
    quick_stop_option: int = 2           # 0x605A
    counts_per_revolution: int = 65536   # 0x6064 increments
    reverse_bit: int | None = None       # vendor: controlword bit that negates the setpoint
    vl_ramp_bits: bool = False           # vl mode obeys controlword bits 4-6
    mailbox: tuple[int, int, int, int] = (0x1000, 128, 0x1080, 128)
    process_data_starts: tuple[int, int] = (0x1100, 0x1180)     # SM2, SM3
    sync0_cycles_ns: tuple[int, ...] | None = None   # DC SYNC0 cycles accepted; None: no DC
    free_run: bool = True
    eeprom_read_bytes: int = 8
    function_codes: tuple[tuple[int, int], ...] = ()  # vendor function-code access 0x2000
    alias: int = 0                                    # configured station alias (SII word 4)
    objects: tuple[ObjectSpec, ...] = ()              # vendor objects and overrides
    sources: tuple[str, ...] = field(default=(), compare=False)


def _entry(spec: ObjectSpec) -> Entry:
    return Entry(spec.index, spec.subindex, spec.name, spec.data_type, spec.access, spec.value,
                 spec.pdo_mappable, spec.minimum, spec.maximum, spec.max_length)


def standard_objects(spec: DriveSpec) -> list[ObjectSpec]:
    """Return the CiA 301/402 objects of every simulated velocity drive (spec overrides)."""
    o = ObjectSpec
    u8, u16, u32 = DataType.UNSIGNED8, DataType.UNSIGNED16, DataType.UNSIGNED32
    i8, i16, i32 = DataType.INTEGER8, DataType.INTEGER16, DataType.INTEGER32
    ro, rw = Access.RO, Access.RW
    vis = DataType.VISIBLE_STRING
    rated = int(spec.rated_rpm)
    objects = [
        o(0x1000, 0, 'Device type', u32, ro, spec.device_type),
        o(0x1001, 0, 'Error register', u8, ro, 0),
        o(0x1008, 0, 'Manufacturer device name', vis, ro, spec.name),
        o(0x1009, 0, 'Manufacturer hardware version', vis, ro, 'sim'),
        o(0x100A, 0, 'Manufacturer software version', vis, ro, 'vfd_ros2 sim'),
        o(0x1018, 0, 'Identity: number of entries', u8, ro, 4),
        o(0x1018, 1, 'Vendor ID', u32, ro, spec.vendor_id),
        o(0x1018, 2, 'Product code', u32, ro, spec.product_code),
        o(0x1018, 3, 'Revision number', u32, ro, spec.revision),
        o(0x1018, 4, 'Serial number', u32, ro, spec.serial),
        o(0x1C00, 0, 'SM communication type: entries', u8, ro, 4),
        *[o(0x1C00, n + 1, f'SM{n} communication type', u8, ro, n + 1) for n in range(4)],
        o(0x1C32, 0, 'SM2 synchronization: entries', u8, ro, 5),
        o(0x1C32, 1, 'Synchronization type', u16, ro, 0),
        o(0x1C32, 2, 'Cycle time', u32, ro, 0),
        o(0x1C32, 4, 'Synchronization types supported', u16, ro,
          0x0001 | (0x0004 if spec.sync0_cycles_ns else 0)),
        o(0x1C32, 5, 'Minimum cycle time', u32, ro,
          min(spec.sync0_cycles_ns) if spec.sync0_cycles_ns else 0),
        o(0x603F, 0, 'Error code', u16, ro, 0, True),
        o(0x6040, 0, 'Controlword', u16, rw, 0, True),
        o(0x6041, 0, 'Statusword', u16, ro, 0, True),
        o(0x6060, 0, 'Modes of operation', i8, rw if spec.mode_writable else ro,
          spec.default_mode, True),
        o(0x6061, 0, 'Modes of operation display', i8, ro, spec.default_mode, True),
        o(0x6042, 0, 'vl target velocity', i16, rw, 0, True),
        o(0x6043, 0, 'vl velocity demand', i16, ro, 0, True),
        o(0x6044, 0, 'vl velocity actual value', i16, ro, 0, True),
        o(0x6046, 0, 'vl velocity min max amount: entries', u8, ro, 2),
        o(0x6046, 1, 'vl velocity min amount', u32, rw, 0),
        o(0x6046, 2, 'vl velocity max amount', u32, rw, int(spec.max_rpm)),
        o(0x6048, 0, 'vl velocity acceleration: entries', u8, ro, 2),
        o(0x6048, 1, 'Delta speed', u32, rw, rated, minimum=1),
        o(0x6048, 2, 'Delta time', u16, rw, max(1, round(spec.accel_time_s)), minimum=1),
        o(0x6049, 0, 'vl velocity deceleration: entries', u8, ro, 2),
        o(0x6049, 1, 'Delta speed', u32, rw, rated, minimum=1),
        o(0x6049, 2, 'Delta time', u16, rw, max(1, round(spec.decel_time_s)), minimum=1),
        o(0x604A, 0, 'vl velocity quick stop: entries', u8, ro, 2),
        o(0x604A, 1, 'Delta speed', u32, rw, rated, minimum=1),
        o(0x604A, 2, 'Delta time', u16, rw, max(1, round(spec.quick_stop_time_s)), minimum=1),
        o(0x605A, 0, 'Quick stop option code', i16, rw, spec.quick_stop_option),
        o(0x6064, 0, 'Position actual value', i32, ro, 0, True),
        o(0x606C, 0, 'Velocity actual value', i32, ro, 0, True),
        o(0x6077, 0, 'Torque actual value', i16, ro, 0, True),
        o(0x60FF, 0, 'Target velocity', i32, rw, 0, True),
        o(0x6502, 0, 'Supported drive modes', u32, ro,
          sum(1 << (mode - 1) for mode in spec.modes if mode > 0)),
        # not a drive object: a writable buffer longer than a mailbox, so that tests
        # exercise segmented SDO transfers both ways
        o(0x2FFF, 0, 'Simulator scratch buffer', DataType.OCTET_STRING, rw, bytes(300),
          max_length=1024),
    ]
    if spec.function_codes:
        objects += [
            o(0x2000, 0, 'Read function codes', u32, rw, 0),
            o(0x2001, 0, 'Read response', u32, ro, 0),
            o(0x2002, 0, 'Write function codes', u32, rw, 0),
            o(0x2003, 0, 'Write response', u32, ro, 0),
        ]
    return objects


def _mapping_value(index: int, subindex: int, bits: int) -> int:
    return index << 16 | subindex << 8 | bits


class Cia402VelocityDrive:
    """A ``SlaveApplication``: one CiA 402 velocity drive built from a ``DriveSpec``."""

    #: methods the segment's control channel may call (test and demo hooks)
    CONTROLS = frozenset({'inject_fault', 'clear_fault_cause', 'refuse_state', 'abort_writes',
                          'snapshot'})

    def __init__(self, spec: DriveSpec) -> None:
        self.spec = spec
        # Kept through a power cycle, as firmware is: SDO writes refused by index.
        self._aborting: dict[int, int] = {}
        self.sdo_writes = 0
        self.power_on()

    def power_on(self) -> None:
        """Start as after power-up: defaults everywhere (PDO mappings written in PRE-OP lost)."""
        spec = self.spec
        self.od = ObjectDictionary()
        for item in standard_objects(spec):
            self.od.add(_entry(item))
        for item in spec.objects:
            self.od.add(_entry(item))               # vendor objects and overrides
        self._add_pdo_objects()
        self._function_codes = dict(spec.function_codes)
        if spec.function_codes:
            self.od.add_check(0x2000, self._function_code_read)
            self.od.add_check(0x2002, self._function_code_write)
        self.od.add_check(0x6060, self._check_mode)
        self.state = State.SWITCH_ON_DISABLED
        self.al_state = ALState.INIT
        self.velocity = 0.0                  # rpm, ramp output = actual (no slip modelled)
        self.position = 0.0                  # increments
        self._controlword = 0
        self._last_tick: float | None = None
        self._fault_persistent = False
        self._emergencies: list[Emergency] = []
        self._refusals: dict[int, int] = {}
        self._layout_cache: dict[str, list[tuple[int, int, int]]] = {}
        self.outputs_received = 0
        self._update_status()

    # -- object dictionary -----------------------------------------------------------

    def _add_pdo_objects(self) -> None:
        spec, od = self.spec, self.od
        map_access = Access.RW_PREOP
        for pdo in (*spec.rx_pdos, *spec.tx_pdos):
            access = Access.RO if pdo.fixed else map_access
            od.add(Entry(pdo.index, 0, 'Number of mapped objects', DataType.UNSIGNED8, access,
                         len(pdo.entries), maximum=pdo.max_entries))
            for sub in range(1, pdo.max_entries + 1):
                value = _mapping_value(*pdo.entries[sub - 1]) if sub <= len(pdo.entries) else 0
                od.add(Entry(pdo.index, sub, f'Mapped object {sub}', DataType.UNSIGNED32,
                             access, value))
            if not pdo.fixed:
                od.add_check(pdo.index, self._check_mapping)
        assign_access = map_access if spec.assign_writable else Access.RO
        for index, default, pool in ((0x1C12, spec.rx_assign, spec.rx_pdos),
                                     (0x1C13, spec.tx_assign, spec.tx_pdos)):
            od.add(Entry(index, 0, 'Number of assigned PDOs', DataType.UNSIGNED8, assign_access,
                         len(default), maximum=len(pool)))
            for sub in range(1, len(pool) + 1):
                value = default[sub - 1] if sub <= len(default) else 0
                od.add(Entry(index, sub, f'PDO mapping index {sub}', DataType.UNSIGNED16,
                             assign_access, value))
            od.add_check(index, self._check_assignment)

    def read_object(self, index: int, subindex: int) -> tuple[int, bytes]:
        return self.od.read(index, subindex)

    def write_object(self, index: int, subindex: int, data: bytes) -> int:
        self.sdo_writes += 1
        code = self._aborting.get(index) or self.od.write(index, subindex, data)
        if code == 0:
            if 0x1600 <= index <= 0x1BFF or index in (0x1C12, 0x1C13):
                self._layout_cache.clear()
            if index == 0x6040:
                self._apply_controlword(int(self.od.value(0x6040)))
        return code

    def _check_mapping(self, entry: Entry, value: Any) -> int:
        od = self.od
        if entry.subindex == 0:
            for sub in range(1, int(value) + 1):
                code = self._check_mapped(int(od.value(entry.index, sub)))
                if code:
                    return code
            return 0
        if od.value(entry.index, 0):
            return SdoAbortCode.SUBINDEX_0_MUST_BE_0         # ETG.1000.6 table 43
        return 0

    def _check_mapped(self, mapping: int) -> int:
        index, subindex, bits = mapping >> 16, (mapping >> 8) & 0xFF, mapping & 0xFF
        if index == 0:
            return 0                                         # a gap of ``bits``
        target = self.od.find(index, subindex)
        if target is None:
            return SdoAbortCode.OBJECT_DOES_NOT_EXIST
        if not target.pdo_mappable or target.bit_length != bits:
            return SdoAbortCode.NOT_MAPPABLE
        return 0

    def _check_assignment(self, entry: Entry, value: Any) -> int:
        low, high = _PDO_RANGES['rx' if entry.index == 0x1C12 else 'tx']
        if entry.subindex == 0:
            for sub in range(1, int(value) + 1):
                pdo = int(self.od.value(entry.index, sub))
                if not (low <= pdo <= high and (pdo, 0) in self.od):
                    return SdoAbortCode.VALUE_RANGE_EXCEEDED
            return 0
        if self.od.value(entry.index, 0):
            return SdoAbortCode.SUBINDEX_0_MUST_BE_0
        if value and not (low <= int(value) <= high and (int(value), 0) in self.od):
            return SdoAbortCode.VALUE_RANGE_EXCEEDED
        return 0

    def _check_mode(self, entry: Entry, value: Any) -> int:
        return 0 if int(value) in self.spec.modes else SdoAbortCode.VALUE_RANGE_EXCEEDED

    def _function_code_read(self, entry: Entry, value: Any) -> int:
        address = int(value) >> 16
        if address in self._function_codes:
            result = 0x0001 << 16 | self._function_codes[address] & 0xFFFF
        else:
            result = 0x0003 << 16 | 0x0002                     # illegal data address
        self.od.set_value(0x2001, 0, result)
        return 0

    def _function_code_write(self, entry: Entry, value: Any) -> int:
        # the address's MSB asks for a RAM-only write (IMO manual L2098): same value here
        address, data = (int(value) >> 16) & 0x7FFF, int(value) & 0xFFFF
        if address in self._function_codes:
            self._function_codes[address] = data
            result = 0x0001 << 16 | data
        else:
            result = 0x0003 << 16 | 0x0002
        self.od.set_value(0x2003, 0, result)
        return 0

    # -- process data ------------------------------------------------------------------

    def _layout(self, direction: str) -> list[tuple[int, int, int]]:
        """``(index, subindex, bits)`` of the assigned PDOs, in order (index 0 = gap)."""
        cached = self._layout_cache.get(direction)
        if cached is not None:
            return cached
        assign = 0x1C12 if direction == 'rx' else 0x1C13
        layout = []
        for sub in range(1, int(self.od.value(assign, 0)) + 1):
            pdo = int(self.od.value(assign, sub))
            for entry in range(1, int(self.od.value(pdo, 0)) + 1):
                mapping = int(self.od.value(pdo, entry))
                layout.append((mapping >> 16, (mapping >> 8) & 0xFF, mapping & 0xFF))
        self._layout_cache[direction] = layout
        return layout

    def process_data_sizes(self) -> tuple[int, int]:
        return (sum(bits for *_, bits in self._layout('rx')) // 8,
                sum(bits for *_, bits in self._layout('tx')) // 8)

    def rx_pdo(self, data: bytes) -> None:
        if self.al_state is not ALState.OP:
            return                        # SAFE-OP: outputs arrive but are not applied
        self.outputs_received += 1
        offset = 0
        for index, subindex, bits in self._layout('rx'):
            size = bits // 8
            if index:
                entry = self.od.entry(index, subindex)
                raw = data[offset:offset + size]
                if len(raw) == size:
                    entry.value = struct.unpack('<' + _CODES[entry.data_type], raw)[0]
            offset += size
        self._apply_controlword(int(self.od.value(0x6040)))

    def tx_pdo(self) -> bytes:
        out = bytearray()
        for index, subindex, bits in self._layout('tx'):
            if index:
                out += self.od.entry(index, subindex).pack()
            else:
                out += bytes(bits // 8)
        return bytes(out)

    # -- AL state ----------------------------------------------------------------------

    def request_state(self, current: ALState, requested: ALState,
                      context: TransitionContext) -> int:
        refusal = self._refusals.get(int(requested))
        if refusal:
            return refusal
        if requested is ALState.SAFE_OP:
            for direction, code in (('rx', ALStatusCode.INVALID_OUTPUT_MAPPING),
                                    ('tx', ALStatusCode.INVALID_INPUT_MAPPING)):
                if any(self._check_mapped(_mapping_value(*item)) for item in
                       self._layout(direction)):
                    return code
            if context.sync0_cycle_ns:
                if not self.spec.sync0_cycles_ns:
                    return ALStatusCode.INVALID_DC_SYNC_CONFIGURATION
                if context.sync0_cycle_ns not in self.spec.sync0_cycles_ns:
                    return ALStatusCode.DC_INVALID_SYNC0_CYCLE_TIME
            elif not self.spec.free_run:
                return ALStatusCode.FREE_RUN_NOT_SUPPORTED
            self.od.set_value(0x1C32, 1, 2 if context.sync0_cycle_ns else 0)
            self.od.set_value(0x1C32, 2, context.sync0_cycle_ns)
        return 0

    def state_changed(self, state: ALState) -> None:
        previous, self.al_state = self.al_state, state
        self.od.al_state = state
        if previous is ALState.OP and state is not ALState.OP and self.state in (
                State.OPERATION_ENABLED, State.QUICK_STOP_ACTIVE):
            # outputs are no longer valid: a drive that was asked to leave OP disables
            # itself (the watchdog case becomes a fault in ``watchdog_expired``)
            self.state = State.SWITCH_ON_DISABLED
            self._update_status()

    def watchdog_expired(self) -> None:
        self.inject_fault(EMCY_RPDO_TIMEOUT, ERROR_REGISTER_GENERIC | ERROR_REGISTER_COMMUNICATION)

    # -- device control ----------------------------------------------------------------

    def _apply_controlword(self, controlword: int) -> None:
        previous, self._controlword = self._controlword, controlword
        rising_reset = controlword & ControlBit.FAULT_RESET and not (
            previous & ControlBit.FAULT_RESET)
        if self.state is State.FAULT and rising_reset:
            if self._fault_persistent:
                return                                       # cause still present
            self.od.set_value(0x603F, 0, 0)
            self.od.set_value(0x1001, 0, 0)
            self._emergencies.append(Emergency(EMCY_NO_ERROR, 0))
        self.state = transition(self.state, controlword, previous)
        self._update_status()

    def inject_fault(self, error_code: int, error_register: int = ERROR_REGISTER_GENERIC,
                     data: bytes = b'', persistent: bool = False) -> None:
        """Raise a drive fault: fault reaction, 0x603F/0x1001, and a CoE emergency."""
        self._fault_persistent = persistent
        self.od.set_value(0x603F, 0, error_code & 0xFFFF)
        self.od.set_value(0x1001, 0, error_register & 0xFF)
        if self.state is not State.FAULT:
            self.state = State.FAULT_REACTION_ACTIVE            # CiA 402 transition 13
        self._emergencies.append(Emergency(error_code, error_register, bytes(data)))
        self._update_status()

    def clear_fault_cause(self) -> None:
        """Remove the cause of a persistent fault: a fault reset is accepted again."""
        self._fault_persistent = False

    def abort_writes(self, index: int, code: int) -> None:
        """Abort SDO writes to ``index`` with ``code`` (0 = take them again), power cycles too."""
        if code:
            self._aborting[int(index)] = int(code)
        else:
            self._aborting.pop(int(index), None)

    def refuse_state(self, state: int, code: int) -> None:
        """Refuse requests for AL ``state`` with AL status ``code`` (0 = accept again)."""
        if code:
            self._refusals[int(state)] = int(code)
        else:
            self._refusals.pop(int(state), None)

    def take_emergencies(self) -> list[Emergency]:
        emergencies, self._emergencies = self._emergencies, []
        return emergencies

    # -- dynamics ------------------------------------------------------------------------

    def _ramp(self, index: int) -> float:
        """rpm/s from a CiA 402 vl ramp object (delta speed / delta time)."""
        return float(self.od.value(index, 1)) / max(1.0, float(self.od.value(index, 2)))

    def _target(self) -> float:
        od = self.od
        mode = int(od.value(0x6060))
        controlword = self._controlword
        if mode == MODE_VL:
            target = float(od.value(0x6042))
            if self.spec.vl_ramp_bits and not (controlword & 0x0040):
                target = 0.0                     # bit 6 "reference ramp": setpoint to zero
            limit = float(od.value(0x6046, 2))
        elif mode in (MODE_PV, MODE_CSV):
            target = float(od.value(0x60FF))
            if mode == MODE_PV and controlword & ControlBit.HALT:
                target = 0.0
            limit = self.spec.max_rpm
        else:
            return 0.0
        if self.spec.reverse_bit is not None and controlword & (1 << self.spec.reverse_bit):
            target = -target
        return max(-limit, min(limit, target))

    def tick(self, now: float) -> None:
        dt = 0.0 if self._last_tick is None else max(0.0, min(0.1, now - self._last_tick))
        self._last_tick = now
        state = self.state
        if state is State.OPERATION_ENABLED:
            target = self._target()
            frozen = (self.spec.vl_ramp_bits and int(self.od.value(0x6060)) == MODE_VL
                      and not self._controlword & 0x0020)     # bit 5 "unlock ramp"
            if self.spec.vl_ramp_bits and int(self.od.value(0x6060)) == MODE_VL and not (
                    self._controlword & 0x0010):
                self.velocity = 0.0                          # bit 4 "enable ramp" = 0
            elif not frozen:
                speeding_up = abs(target) > abs(self.velocity) and target * self.velocity >= 0
                rate = self._ramp(0x6048 if speeding_up else 0x6049)
                self.velocity = _approach(self.velocity, target, rate * dt)
        elif state in (State.QUICK_STOP_ACTIVE, State.FAULT_REACTION_ACTIVE):
            self.velocity = _approach(self.velocity, 0.0, self._ramp(0x604A) * dt)
            if self.velocity == 0.0:
                if state is State.FAULT_REACTION_ACTIVE:
                    self.state = State.FAULT                 # CiA 402 transition 14
                elif int(self.od.value(0x605A)) in (1, 2, 3, 4):
                    self.state = State.SWITCH_ON_DISABLED    # quick stop options 1-4
        else:
            self.velocity = _approach(self.velocity, 0.0, self._ramp(0x6049) * dt)
        self.position += self.velocity / 60.0 * self.spec.counts_per_revolution * dt
        self._update_status()

    def _update_status(self) -> None:
        od, state = self.od, self.state
        statusword = STATUSWORD_OF[state]
        if state not in (State.NOT_READY_TO_SWITCH_ON, State.SWITCH_ON_DISABLED, State.FAULT):
            statusword |= StatusBit.VOLTAGE_ENABLED
        if self.al_state is ALState.OP:
            statusword |= StatusBit.REMOTE
        demand = self._target() if state is State.OPERATION_ENABLED else 0.0
        if state is State.OPERATION_ENABLED and abs(self.velocity - demand) < 0.5:
            statusword |= StatusBit.TARGET_REACHED
        od.set_value(0x6041, 0, int(statusword))
        mode = int(od.value(0x6060))
        od.set_value(0x6061, 0, mode)
        rpm = round(self.velocity)
        od.set_value(0x6043, 0, max(-32768, min(32767, round(demand))))
        od.set_value(0x6044, 0, max(-32768, min(32767, rpm)))
        od.set_value(0x606C, 0, rpm)
        od.set_value(0x6064, 0, (int(self.position) + 2**31) % 2**32 - 2**31)

    def snapshot(self) -> dict[str, Any]:
        """Plain-data view for tests and demos."""
        return {
            'state': self.state.name,
            'al_state': self.al_state.name,
            'velocity_rpm': self.velocity,
            'controlword': self._controlword,
            'statusword': int(self.od.value(0x6041)),
            'error_code': int(self.od.value(0x603F)),
            'mode': int(self.od.value(0x6060)),
            'outputs_received': self.outputs_received,
            'sdo_writes': self.sdo_writes,
        }


_CODES = {
    DataType.BOOLEAN: 'B', DataType.INTEGER8: 'b', DataType.INTEGER16: 'h',
    DataType.INTEGER32: 'i', DataType.UNSIGNED8: 'B', DataType.UNSIGNED16: 'H',
    DataType.UNSIGNED32: 'I', DataType.REAL32: 'f', DataType.INTEGER64: 'q',
    DataType.UNSIGNED64: 'Q',
}


def _approach(value: float, target: float, step: float) -> float:
    if abs(target - value) <= step:
        return target
    return value + step if target > value else value - step


def sii_data(spec: DriveSpec) -> SiiData:
    """Return the SII contents of a drive: identity, mailbox, SyncManagers, PDOs."""
    rx_offset, rx_size, tx_offset, tx_size = spec.mailbox
    drive = Cia402VelocityDrive(spec)
    out_bytes, in_bytes = drive.process_data_sizes()
    sync_managers = (
        SyncManagerConfig(rx_offset, rx_size, 0x26, SyncManagerType.MAILBOX_OUT),
        SyncManagerConfig(tx_offset, tx_size, 0x22, SyncManagerType.MAILBOX_IN),
        # 3-buffer, ECAT writes, AL event, watchdog trigger (ETG.1000.4 table 59)
        SyncManagerConfig(spec.process_data_starts[0], out_bytes, 0x64,
                          SyncManagerType.PROCESS_DATA_OUT),
        SyncManagerConfig(spec.process_data_starts[1], in_bytes, 0x20,
                          SyncManagerType.PROCESS_DATA_IN),
    )

    def pdo_info(pdos: tuple[PdoSpec, ...], assigned: tuple[int, ...], sm: int) -> tuple:
        return tuple(PdoInfo(pdo.index, tuple(PdoEntryInfo(i, s, b) for i, s, b in pdo.entries),
                             sm if pdo.index in assigned else 0xFF) for pdo in pdos)

    return SiiData(
        alias=spec.alias,
        vendor_id=spec.vendor_id, product_code=spec.product_code, revision=spec.revision,
        serial=spec.serial, rx_mailbox=(rx_offset, rx_size), tx_mailbox=(tx_offset, tx_size),
        strings=(spec.name,),
        coe_details=0x01 | 0x04 | (0x08 if spec.assign_writable else 0),
        sync_managers=sync_managers,
        rx_pdos=pdo_info(spec.rx_pdos, spec.rx_assign, 2),
        tx_pdos=pdo_info(spec.tx_pdos, spec.tx_assign, 3),
    )


def sii_image(spec: DriveSpec) -> bytes:
    return build_image(sii_data(spec))
