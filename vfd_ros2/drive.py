"""Drive verbs in SI units: a profile plus a register transport.

No ROS here. Every method completes within a few transport timeouts or raises
a ``VfdError``; the caller (``controller.py``) owns threads, timing and policy.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Callable, Mapping, Protocol, TypeVar

from .errors import BadFrame, ParameterError, ProfileError, ProtocolException
from .faults import NO_FAULT, FaultInfo, describe_fault
from .profile import Access, DirectionMode, Parameter, PersistenceKind, Profile, Signal, SpeedUnit
from .registers import ReadBlock, decode_words, encode_words, plan_reads
from .rtu_timing import reply_size
from .scaling import VelocityScaling
from .transports.base import RegisterTransport, Transport, TransportStats

T = TypeVar('T')

#: s added to twice the worst-case addressing interval when sizing a drive's own
#: comm-loss timeout: the host's scheduling jitter on a loaded machine
HOST_LOSS_JITTER = 0.05

#: transactions one service action may add to a cycle (a RAM/EEPROM switch read and
#: write, the write, its read-back)
ACTION_TRANSACTIONS = 4


@dataclass
class Reading:
    """What one poll cycle learnt (values keep their last reading between polls)."""

    values: dict[str, float] = field(default_factory=dict)      # role -> engineering value
    raw_words: dict[str, int] = field(default_factory=dict)     # code -> raw register value
    flags: dict[str, bool] = field(default_factory=dict)
    fault: FaultInfo = NO_FAULT
    warning_code: int = 0
    warning_subcode: int = 0
    measured_velocity: float = math.nan
    # Why the drive does not do what it is told, as far as the drive layer knows
    # (e.g. a CiA 402 drive stuck before Operation Enabled); '' when nothing.
    problem: str = ''
    # Values the drive refuses to give (role -> the register and the drive's own
    # text): reported unavailable, control goes on.
    unavailable: dict[str, str] = field(default_factory=dict)
    # Why motion must not be allowed although the link is up (e.g. the fault or
    # run state cannot be read); '' when it may run.
    unsafe: str = ''


@dataclass(frozen=True)
class HostLossProtection:
    """What stops the drive by itself when the host falls silent, as set at connect."""

    mechanism: str = ''      # e.g. 'C02.04 comm-loss timeout'; '' = none
    timeout: float = 0.0     # s after the last valid request; 0 = none
    requested: float = 0.0   # drive_comm_timeout as configured
    note: str = ''           # why it differs from the request, or why there is none

    @property
    def active(self) -> bool:
        return bool(self.mechanism) and self.timeout > 0

    @property
    def weaker_than_requested(self) -> bool:
        if not self.active:
            return self.requested > 0
        return self.requested > 0 and self.timeout > self.requested + 1e-9

    def describe(self) -> str:
        if not self.active:
            return f'none: {self.note}' if self.note else 'none'
        text = f'{self.mechanism}: {self.timeout:g} s'
        return f'{text} ({self.note})' if self.note else text


def size_comm_timeout(parameter: Parameter, requested: float,
                      minimum: float) -> tuple[float, str]:
    """Choose the value of a drive's comm-loss timeout parameter; (seconds, note).

    The request is rounded to the parameter's resolution, raised to ``minimum``
    (what the bus needs so that a healthy drive never trips) and kept within the
    parameter's range; the note says why the result differs from the request.
    ``requested`` 0 asks for no timeout. Raises ParameterError when the bus needs
    more than the parameter allows.
    """
    step = abs(parameter.scale)
    low_raw, high_raw = parameter.type.bounds
    highest = parameter.maximum if parameter.maximum is not None else high_raw * step
    lowest = max(parameter.minimum if parameter.minimum is not None else 0.0, step)
    code = parameter.code
    if requested == 0:
        try:
            parameter.to_raw(0.0)
            return 0.0, 'off, as drive_comm_timeout 0 asks'
        except ParameterError:
            return highest, f'{code} has no off value: its longest, {highest:g} s'
    if minimum > highest + 1e-9:
        raise ParameterError(
            f'{code}: this drive is addressed at worst every {minimum / 2:.3g} s on its bus, '
            f'so its comm-loss timeout must be at least {minimum:.3g} s, but {code} allows '
            f'at most {highest:g} s: use a higher baud rate, fewer drives on the line or '
            'fewer polled values')
    value = round(requested / step) * step
    notes = []
    if abs(value - requested) > 1e-9:
        notes.append(f'{requested:g} s is not a multiple of {step:g} s')
    if value < minimum - 1e-9:
        value = math.ceil(minimum / step - 1e-9) * step
        notes.append(f'raised from {requested:g} s: the bus addresses this drive at worst '
                     f'every {(minimum - HOST_LOSS_JITTER) / 2 * 1000:.0f} ms, and less than '
                     f'{minimum:.3g} s would fault a healthy drive')
    if value < lowest - 1e-9:
        value = lowest
        notes.append(f'{code} allows no less than {lowest:g} s')
    if value > highest + 1e-9:
        value = highest
        notes.append(f'{code} allows at most {highest:g} s')
    value = round(value / step) * step
    return value, '; '.join(notes)


@dataclass(frozen=True)
class ParameterValue:
    parameter: Parameter
    raw: int
    value: float

    @property
    def text(self) -> str:
        return self.parameter.option_text(self.raw)


class Drive(Protocol):
    """What the controller needs from a drive, whatever the bus.

    ``ModbusDrive`` below implements it on a register transport; other buses
    (e.g. CANopen) implement the same verbs. Every method finishes within a few
    transport timeouts or raises a VfdError.
    """

    profile: Profile
    transport: Transport
    last_setpoint_raw: int

    @property
    def hardware_id(self) -> str: ...

    @property
    def stats(self) -> TransportStats:
        """This drive's own counters (a shared link also counts the others')."""

    def cycle_seconds(self) -> float:
        """Time one full command + status cycle of this drive occupies its link."""

    def connect_seconds(self) -> float:
        """Time this drive's connect sequence occupies its link (worst case)."""

    def action_seconds(self) -> float:
        """Time one service action may add to a cycle."""

    def host_loss_plan(self, requested: float, interval: float) -> HostLossProtection:
        """Plan the drive-side protection against host death (no I/O; ParameterError)."""

    def check_write(self, key: str, value: float, running: bool) -> tuple[Parameter, int]:
        """Validate a parameter write without touching the drive (ParameterError)."""

    def open(self) -> None: ...

    def close(self) -> None: ...

    def forget_state(self) -> None: ...

    def configure(self, protection: HostLossProtection,
                  apply_commissioning: bool) -> list[str]:
        """Connect-time writes; returns the problems that did not stop the connect.

        A drive may also set ``protection_applied`` (a HostLossProtection) to what
        it could set of ``protection``: the controller reports that one (optional;
        CanopenDrive does, when the drive aborts 0x1016 or 0x1400:05).
        """

    def apply(self, velocity: float, run: bool, idle_action: str = 'stop',
              reassert: bool = False) -> None: ...

    def send_command(self, action: str) -> None: ...

    def write_setpoint_parameter(self, code: str, raw: int) -> None:
        """Write an already validated auxiliary setpoint (volatile where possible)."""

    def poll(self, cycle: int, between: Callable[[], None] | None = None) -> Reading:
        """Read the status due this cycle; ``between()`` runs before each request."""

    def get_parameter(self, key: str) -> ParameterValue: ...

    def set_parameter(self, key: str, value: float, persistent: bool,
                      running: bool) -> tuple[ParameterValue, str]: ...


class ModbusDrive:
    """One drive on a register transport, driven through its profile."""

    def __init__(self, profile: Profile, transport: RegisterTransport, unit_id: int,
                 scaling: VelocityScaling, owns_transport: bool = True) -> None:
        if not 0 <= unit_id <= 247:
            raise ParameterError(f'unit id {unit_id} is outside 0..247')
        self.profile = profile
        self.transport = transport
        self.owns_transport = owns_transport
        self.unit_id = unit_id
        self.scaling = scaling
        self._setpoint = profile.parameter(profile.velocity.setpoint)
        self._command = profile.parameter(profile.control.command)
        self._signals: list[tuple[Signal, Parameter]] = [
            (signal, profile.parameter(signal.code)) for signal in profile.monitor]
        self._status_words = [profile.parameter(code) for code in profile.status_words]
        self._refused: dict[int, str] = {}      # register -> why the drive refuses it
        self._plan_reads()
        self._unsigned_roles = {signal.role: parameter.type.bounds[0] == 0 and not signal.bits
                                for signal, parameter in self._signals}
        # Roles the run and fault state are decoded from: without them the drive
        # cannot be run safely, whatever else it reports.
        self._vital_roles = {'fault_code'} | {
            rule.signal for name, rule in profile.flags.items() if name in ('running', 'fault')}
        self._words: dict[int, int] = {}
        self.asserted_command: str | None = None
        self.last_setpoint_raw = 0

    def _plan_reads(self, split: ReadBlock | None = None) -> None:
        """Plan the status reads around refused registers; ``split`` is read span by span."""
        profile = self.profile
        spans = [(p.address, p.register_count) for _, p in self._signals]
        spans += [(p.address, p.register_count) for p in self._status_words]
        spans = [(a, n) for a, n in dict.fromkeys(spans)
                 if not any(a + i in self._refused for i in range(n))]
        def readable(address: int) -> bool:
            # A block never reaches over a refused register, nor (on most drives) over
            # an undocumented one.
            return address not in self._refused and (
                profile.modbus.gaps_readable or profile.parameter_at(address) is not None)
        limit = profile.modbus.max_read_registers
        if split is None:
            self.blocks: list[ReadBlock] = plan_reads(spans, limit, readable)
        else:
            alone = [ReadBlock(a, n) for a, n in spans if split.covers(a, n)]
            self.blocks = sorted([block for block in self.blocks if block != split] + alone,
                                 key=lambda block: block.start)
        self._block_every = {
            block: min((s.every for s, p in self._signals if block.covers(p.address)),
                       default=1)
            for block in self.blocks}

    # --- link ---------------------------------------------------------------

    @property
    def hardware_id(self) -> str:
        return f'{self.profile.name}@{self.transport.description}#{self.unit_id}'

    @property
    def stats(self) -> TransportStats:
        return self.transport.stats_for(self.unit_id)

    def open(self) -> None:
        self.transport.open()

    def close(self) -> None:
        # On a shared bus one silent drive must not close the port of the others;
        # the transport reopens itself after a port-level failure anyway.
        if self.owns_transport:
            self.transport.close()

    def forget_state(self) -> None:
        """After a link loss nothing read or written before is trusted."""
        self._words.clear()
        self.asserted_command = None
        if self._refused:
            self._refused.clear()      # it may be another drive (or firmware) now
            self._plan_reads()

    # --- timing (for sizing the drive's own comm-loss timeout) -----------------

    def _write_requests(self, parameter: Parameter) -> tuple[int, int]:
        if parameter.register_count == 1 and 6 in self.profile.modbus.function_codes:
            return 8, reply_size(6)
        return 9 + 2 * parameter.register_count, reply_size(16)

    def cycle_seconds(self) -> float:
        """Wire time of one full cycle: the setpoint write and every status read."""
        exchange = self.transport.exchange_seconds
        total = exchange(*self._write_requests(self._setpoint))
        for block in self.blocks:
            total += exchange(8, reply_size(3, block.count))
        return total

    def connect_seconds(self) -> float:
        """Wire time of a connect: zero setpoint, idle command, settings read and written."""
        exchange = self.transport.exchange_seconds
        total = exchange(*self._write_requests(self._setpoint))
        total += 2 * exchange(*self._write_requests(self._command))
        settings = len(self.profile.commissioning) + (self.profile.comm_timeout is not None)
        total += settings * (exchange(8, reply_size(3, 2)) + exchange(8, reply_size(6)))
        return total + self.cycle_seconds()

    def action_seconds(self) -> float:
        """Wire time one service action may add to a cycle."""
        return ACTION_TRANSACTIONS * self.transport.exchange_seconds(8, reply_size(3, 2))

    def host_loss_plan(self, requested: float, interval: float) -> HostLossProtection:
        """Plan the comm-loss timeout to write: ``requested``, sized for the bus (README)."""
        spec = self.profile.comm_timeout
        if spec is None:
            return HostLossProtection(
                requested=requested,
                note=f'{self.profile.name} has no comm-loss timeout on this bus: only the '
                     'host watchdog stops the motor, not a dead host')
        parameter = self.profile.parameter(spec.parameter)
        minimum = 2 * interval + HOST_LOSS_JITTER
        value, note = size_comm_timeout(parameter, requested, minimum)
        mechanism = f'{parameter.code} comm-loss timeout' if value > 0 else ''
        return HostLossProtection(mechanism, value, requested, note)

    # --- connect ----------------------------------------------------------------

    def configure(self, protection: HostLossProtection,
                  apply_commissioning: bool) -> list[str]:
        """Write the drive's comm timeout and bus-control settings, only where they differ.

        A setting the drive refuses (an exception reply) is reported, not fatal:
        the drive stays online. A failed link still raises.
        """
        wanted: list[tuple[str, float]] = []
        if self.profile.comm_timeout is not None:
            wanted.append((self.profile.comm_timeout.parameter, protection.timeout))
        if apply_commissioning:
            wanted += [(item.code, item.value) for item in self.profile.commissioning]
        problems = []
        for code, value in wanted:
            parameter = self.profile.parameter(code)
            try:
                raw = parameter.to_raw(value)
                if self.read_value(parameter).raw != raw:
                    self.write_raw(parameter, raw)
            except (ParameterError, ProtocolException) as exc:
                problems.append(f'{code} = {value:g}{parameter.unit} not set: {exc}')
        return problems

    # --- register access ------------------------------------------------------

    def _explained(self, exc: ProtocolException) -> ProtocolException:
        """Return the exception with this drive's own meaning of the code (drives differ)."""
        text = self.profile.modbus.exception_codes.get(exc.code, exc.text)
        return ProtocolException(exc.code, text, exc.request)

    def _transact(self, call: Callable[[], T]) -> T:
        """One exchange; a garbled reply is retried once at once (the line resyncs).

        A timeout is not retried: it already cost a full timeout, and the next
        cycle asks again anyway.
        """
        try:
            try:
                return call()
            except BadFrame:
                return call()
        except ProtocolException as exc:
            raise self._explained(exc) from exc

    def _read(self, address: int, count: int) -> list[int]:
        limit = self.profile.modbus.max_read_registers
        words: list[int] = []
        for offset in range(0, count, limit):
            chunk = min(limit, count - offset)
            words += self._transact(lambda a=address + offset, n=chunk:
                                    self.transport.read_registers(self.unit_id, a, n))
        return words

    def _write(self, address: int, words: list[int]) -> None:
        self._transact(lambda: self._write_words(address, words))

    def _write_words(self, address: int, words: list[int]) -> None:
        codes = self.profile.modbus.function_codes
        if len(words) == 1 and 6 in codes:
            self.transport.write_register(self.unit_id, address, words[0])
        elif 16 in codes and len(words) <= self.profile.modbus.max_write_registers:
            self.transport.write_registers(self.unit_id, address, words)
        elif 6 in codes:
            # Drives without function 16 (e.g. 03/06 only): one write per register.
            for offset, word in enumerate(words):
                self.transport.write_register(self.unit_id, address + offset, word)
        else:
            raise ProfileError(f'{self.profile.name}: no write function code available')

    def read_value(self, parameter: Parameter) -> ParameterValue:
        raw = decode_words(parameter, self._read(parameter.address, parameter.register_count))
        return ParameterValue(parameter, raw, parameter.from_raw(raw))

    def write_raw(self, parameter: Parameter, raw: int, address: int | None = None) -> None:
        self._write(parameter.address if address is None else address,
                    encode_words(parameter, raw))

    # --- control --------------------------------------------------------------

    def _native_setpoint(self, velocity: float) -> tuple[int, str]:
        """Output-shaft rad/s -> (raw setpoint, run action) within the register range."""
        spec = self.profile.velocity
        native = self.scaling.to_native(velocity, spec.setpoint_unit)
        action = 'run'
        if spec.direction is DirectionMode.COMMAND:
            action = 'run_reverse' if native < 0 else 'run'
            native = abs(native)
        p = self._setpoint
        low = p.minimum if p.minimum is not None else -math.inf
        high = p.maximum if p.maximum is not None else math.inf
        native = min(max(native, low), high)
        raw = round(native / p.scale)
        type_low, type_high = p.type.bounds
        return min(max(raw, type_low), type_high), action

    def write_setpoint(self, velocity: float) -> int:
        raw, _ = self._native_setpoint(velocity)
        self.write_raw(self._setpoint, raw)
        self.last_setpoint_raw = raw
        return raw

    def send_command(self, action: str) -> None:
        """Write the command register for ``action`` (run/stop/fault_reset/...)."""
        values = self.profile.control.values
        if action not in values:
            raise ParameterError(f'{self.profile.name} has no {action!r} command')
        self.write_raw(self._command, values[action])
        self.asserted_command = action

    def write_setpoint_parameter(self, code: str, raw: int) -> None:
        parameter = self.profile.parameter(code)
        persistence = self.profile.modbus.persistence
        address = parameter.address
        if persistence.kind is PersistenceKind.ADDRESS_FLAG and persistence.covers(address):
            address |= persistence.flag   # RAM only: cyclic values must not wear the EEPROM
        self.write_raw(parameter, raw, address)

    def apply(self, velocity: float, run: bool, idle_action: str = 'stop',
              reassert: bool = False) -> None:
        """One control cycle: write the setpoint, then (re)assert run or idle.

        A run command is written only on a change (with the rising edge the
        drive needs) or when ``reassert`` says the drive does not do what was
        last written; the setpoint is written every cycle, which also feeds the
        drive's own comm-loss timer.
        """
        raw, run_action = self._native_setpoint(velocity if run else 0.0)
        self.write_raw(self._setpoint, raw)
        self.last_setpoint_raw = raw
        wanted = run_action if run else idle_action
        if wanted == self.asserted_command and not reassert:
            return
        if run and self.asserted_command not in ('run', 'run_reverse') and \
                self.profile.control.run_edge_from is not None:
            self.write_raw(self._command, self.profile.control.run_edge_from)
        self.send_command(wanted)

    # --- status ---------------------------------------------------------------

    def poll(self, cycle: int, between: Callable[[], None] | None = None) -> Reading:
        """Read the blocks due this cycle and decode everything known so far.

        ``between()`` runs before each read, so a command that arrived meanwhile
        goes on the wire ahead of the remaining status reads.
        """
        for block in list(self.blocks):
            if between is not None:
                between()
            if cycle % self._block_every[block] == 0 or block.start not in self._words:
                try:
                    words = self._read(block.start, block.count)
                except ProtocolException as exc:
                    self._refuse(block, exc)
                    continue
                for offset, word in enumerate(words):
                    self._words[block.start + offset] = word
        reading = Reading()
        for signal, parameter in self._signals:
            span = range(parameter.address, parameter.address + parameter.register_count)
            refused = next((self._refused[a] for a in span if a in self._refused), None)
            if refused is not None:
                reading.unavailable[signal.role] = f'{parameter.code}: {refused}'
                continue
            words = [self._words.get(address) for address in span]
            if None in words:
                continue
            raw = signal.extract(decode_words(parameter, words))
            reading.values[signal.role] = raw if signal.bits else parameter.from_raw(raw)
        vital = sorted(self._vital_roles & set(reading.unavailable))
        if vital:
            reading.unsafe = ('the drive refuses ' + '; '.join(
                reading.unavailable[role] for role in vital) + ': its run or fault state '
                'is unknown, so it is not run')
        for parameter in self._status_words:
            if parameter.address in self._words:
                reading.raw_words[parameter.code] = self._words[parameter.address]
        for name, rule in self.profile.flags.items():
            if rule.signal in reading.values:
                reading.flags[name] = rule.evaluate(reading.values[rule.signal])
        values = reading.values
        reading.fault = describe_fault(self.profile.faults, int(values.get('fault_code', 0)),
                                       int(values.get('fault_subcode', 0)))
        reading.warning_code = int(values.get('warning_code', 0))
        reading.warning_subcode = int(values.get('warning_subcode', 0))
        reading.measured_velocity = self._measured_velocity(
            values, reading.flags.get('reverse', False))
        return reading

    def _refuse(self, block: ReadBlock, exc: ProtocolException) -> None:
        """Handle a refused status read: read its values one by one, drop the refused."""
        spans = [(p.address, p.register_count) for _, p in self._signals
                 if block.covers(p.address, p.register_count)]
        spans += [(p.address, p.register_count) for p in self._status_words
                  if block.covers(p.address, p.register_count)]
        if len(set(spans)) > 1:
            self._plan_reads(split=block)        # next cycle: each value on its own
            return
        for address in range(block.start, block.start + block.count):
            self._refused[address] = exc.text
            self._words.pop(address, None)
        self._plan_reads()

    def _measured_velocity(self, values: Mapping[str, float], reverse: bool) -> float:
        for role, unit in (('motor_speed', self.profile.velocity.feedback_unit),
                           ('output_frequency', SpeedUnit.HZ)):
            if role not in values:
                continue
            native = values[role]
            if self._unsigned_roles.get(role) and reverse:
                native = -abs(native)   # unsigned register: direction from the status flags
            return self.scaling.from_native(native, unit)
        return math.nan

    # --- parameters -------------------------------------------------------------

    def get_parameter(self, key: str) -> ParameterValue:
        return self.read_value(self.profile.parameter(key))

    def check_write(self, key: str, value: float, running: bool) -> tuple[Parameter, int]:
        """Validate a write without touching the drive; ParameterError says why not."""
        parameter = self.profile.parameter(key)
        owner = self.profile.control_owned.get(parameter.code)
        if owner is not None:
            raise ParameterError(f'{parameter.code} ({parameter.description}) is not written '
                                 f'through parameters: {owner}')
        if parameter.access is Access.READ_ONLY:
            raise ParameterError(f'{parameter.code} ({parameter.description}) is read-only')
        if parameter.access is Access.WRITE_WHEN_STOPPED and running:
            raise ParameterError(
                f'{parameter.code} can only be changed while the drive is stopped')
        return parameter, parameter.to_raw(value)

    def set_parameter(self, key: str, value: float, persistent: bool,
                      running: bool) -> tuple[ParameterValue, str]:
        """Validate, write (RAM or EEPROM as asked), read back. Returns (value, note)."""
        parameter, raw = self.check_write(key, value, running)
        persistence = self.profile.modbus.persistence
        address = parameter.address
        note = ''
        if persistence.kind is PersistenceKind.NONE:
            note = 'this drive does not distinguish RAM and EEPROM writes'
        elif not persistence.covers(parameter.address):
            note = f'{parameter.code} is a process register: written without a RAM/EEPROM choice'
        elif persistence.kind is PersistenceKind.ADDRESS_OFFSET and persistent:
            address = parameter.address + persistence.offset
        elif persistence.kind is PersistenceKind.ADDRESS_FLAG and not persistent:
            address = parameter.address | persistence.flag
        elif persistence.kind is PersistenceKind.SWITCH_PARAMETER and \
                parameter.code != persistence.parameter:
            switch = self.profile.parameter(persistence.parameter)
            wanted = persistence.persistent_value if persistent else persistence.volatile_value
            if self.read_value(switch).raw != wanted:
                self.write_raw(switch, wanted)
                note = f'{switch.code} set to {wanted} first'
        self.write_raw(parameter, raw, address)
        readback = self.read_value(parameter)
        if readback.raw != raw:
            raise ParameterError(
                f'{parameter.code}: wrote {raw} but the drive holds {readback.raw}')
        where = 'EEPROM' if persistent else 'RAM'
        if persistence.kind is not PersistenceKind.NONE and persistence.covers(parameter.address):
            note = f'{where} write' + (f'; {note}' if note else '')
        return readback, note
