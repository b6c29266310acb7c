"""Drive verbs in SI units over registers: a profile plus a register transport (Modbus).

No ROS here. Every method completes within a few transport timeouts or raises
a ``VfdError``; the caller (``vfd_ros2.control``) owns threads, timing and policy.
"""

from __future__ import annotations

import contextlib
import logging
import math
import time
from dataclasses import replace
from functools import partial
from typing import Any, Callable, ClassVar, Mapping, TypeVar

from ..errors import (
    BadFrame,
    ParameterError,
    PassingRefusal,
    ProfileError,
    ProtocolException,
    VfdError,
)
from ..profiles import (
    DirectionMode,
    Parameter,
    PersistenceKind,
    Profile,
    Signal,
    SpeedUnit,
    describe_fault,
)
from ..protocol.registers import ReadBlock, decode_words, encode_words, plan_reads
from ..protocol.rtu_timing import reply_size
from ..protocol.scaling import VelocityScaling
from ..protocol.values import ValueType
from ..transports.base import RegisterTransport, TransportParameter
from .base import (
    ACTION_TRANSACTIONS,
    HOST_LOSS_JITTER,
    DriveOnLink,
    HostLossProtection,
    ParameterValue,
    Reading,
    beyond_register,
    check_write,
    size_comm_timeout,
)

T = TypeVar('T')

#: s after a status register was refused before it is asked again, alone: a refusal that
#: lasts costs one exception reply this often; one that passed (a burst of frame errors)
#: stops being reported, and blocking a drive, within it.
REFUSAL_RETRY = 5.0

#: relative difference from which the drive's nameplate and the node's scaling disagree
#: (above the 0.1 % of a setpoint step and a nameplate's rounding)
NAMEPLATE_TOLERANCE = 0.01

#: the commands that make a drive run (a profile's command values by action name)
RUN_ACTIONS = ('run', 'run_reverse')

log = logging.getLogger(__name__)


class ModbusDrive(DriveOnLink):
    """One drive on a register transport, driven through its profile."""

    settings: ClassVar[tuple[TransportParameter, ...]] = ()
    #: a profile's ``transports`` entries this class can drive (its register map)
    profile_transports: ClassVar[tuple[str, ...]] = ('modbus_rtu', 'modbus_tcp')

    @classmethod
    def link_settings(cls, profile: Profile, settings: Mapping[str, Any]) -> dict[str, Any]:
        """Fill the drive's factory serial settings where ``transport.*`` is 0 or empty."""
        factory = profile.modbus.serial
        filled = dict(settings)
        for name, value in (('baudrate', factory.baudrate), ('parity', factory.parity),
                            ('stopbits', factory.stopbits), ('bytesize', factory.bytesize)):
            if not filled.get(name):
                filled[name] = value
        return filled

    def __init__(self, profile: Profile, transport: RegisterTransport, unit_id: int,
                 scaling: VelocityScaling, settings: Mapping[str, Any] | None = None,
                 owns_transport: bool = True) -> None:
        if not 0 <= unit_id <= 247:
            raise ParameterError(f'unit id {unit_id} is outside 0..247')
        if unit_id == 0 and getattr(transport, 'broadcasts', False):
            raise ParameterError('unit id 0 is the broadcast address on a serial line: every '
                                 'drive executes its writes and none answers; give the drive '
                                 'its own address (1..247)')
        self.profile = profile
        self.transport = transport
        self.owns_transport = owns_transport
        self.unit_id = unit_id
        self.scaling = scaling
        self._setpoint = profile.parameter(profile.velocity.setpoint)
        self._command = profile.parameter(profile.control.command)
        self._signals: list[tuple[Signal, Parameter]] = [
            (signal, profile.parameter(signal.code)) for signal in profile.monitor]
        # How poll decodes each value, worked out once: it runs for every value of
        # every drive each cycle. (role, code, span, first register, sign bit of a
        # one-register value (0: unsigned; None: two registers, decode_words), bit
        # field (shift, mask) or None, scale, parameter)
        self._decoding = [
            (signal.role, parameter.code,
             tuple(range(parameter.address, parameter.address + parameter.register_count)),
             parameter.address,
             None if parameter.register_count != 1 else
             0x8000 if parameter.type is ValueType.INT16 else 0,
             None if signal.bits is None else
             (signal.bits[0], (1 << (signal.bits[1] - signal.bits[0] + 1)) - 1),
             parameter.scale, parameter)
            for signal, parameter in self._signals]
        self._status_words = [profile.parameter(code) for code in profile.status_words]
        # (address, register count) of every value polled, once each
        self._spans = list(dict.fromkeys(
            [(p.address, p.register_count) for _, p in self._signals] +
            [(p.address, p.register_count) for p in self._status_words]))
        self._refused: dict[int, str] = {}      # register -> why the drive refuses it
        # When the refused values are asked again, each alone (_retry_refusals): a
        # burst of exception replies (a frame error, a device failure) would otherwise
        # keep a value unavailable, and a drive whose run state it was blocked, until
        # the next connect.
        self._retry_refused_at = math.inf
        self._read_at: dict[int, float] = {}    # a shown-only block's start -> when read
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
        self._configured: list[tuple[Parameter, int]] = []     # what configure() set
        #: a RAM/EEPROM switch a parameter write could not set back (the link failed
        #: between): set back at the next connect
        self._switch_pending: tuple[Parameter, int] | None = None
        #: what configure() found where the drive's nameplate and the node's scaling differ
        self.nameplate_note = ''
        #: the host-loss protection, where the drive refused the planned one (None: it
        #: holds as planned; see DriveController.protection_applied)
        self.protection_applied: HostLossProtection | None = None
        self._next_setting = 0          # the one settings_lost(one=True) reads back next

    @property
    def link_parameters(self) -> tuple[str, ...]:
        """Its address, baud rate, framing, IP settings (the profile's identify section)."""
        return self.profile.identify.link_parameters if self.profile.identify else ()

    def _plan_reads(self, split: ReadBlock | None = None) -> None:
        """Plan the status reads around refused registers; ``split`` is read span by span."""
        profile = self.profile
        spans = [(a, n) for a, n in self._spans if not self._refuses(a, n)]
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
        used = self._cycle_roles()
        used_at = [p.address for s, p in self._signals if s.role in used]
        # (block, every N cycles, only shown: read at most once per display_period)
        self._schedule = [(block, self._block_every[block],
                           not any(block.covers(address) for address in used_at))
                          for block in self.blocks]

    def _refuses(self, address: int, count: int) -> bool:
        """Tell whether the drive refused any of these registers."""
        return any(address + i in self._refused for i in range(count))

    def _cycle_roles(self) -> set[str]:
        """Roles the cycle itself uses: run and fault state, speed, position counter.

        The other values (currents, voltages, the raw state words) are only shown
        in ``~/status`` and ``/diagnostics``: reading them more often than those are
        published buys nothing.
        """
        profile = self.profile
        roles = {'fault_code', 'fault_subcode'} | {rule.signal for rule in profile.flags.values()}
        if profile.position.from_drive:
            roles.add(profile.position.signal)
        speeds = [signal.role for signal, parameter in self._signals
                  if signal.role in ('motor_speed', 'output_frequency')
                  and not self._refuses(parameter.address, parameter.register_count)]
        # The speed _measured_velocity takes: motor_speed where it can be read.
        roles.update(sorted(speeds, key=('motor_speed', 'output_frequency').index)[:1])
        return roles

    # --- link ---------------------------------------------------------------

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
        self._read_at.clear()
        self.asserted_command = None
        self._retry_refused_at = math.inf
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
        """Wire time of a connect: zero setpoint, idle command, settings read, written, read."""
        exchange = self.transport.exchange_seconds
        total = exchange(*self._write_requests(self._setpoint))
        total += 2 * exchange(*self._write_requests(self._command))
        settings = len(self.profile.commissioning) + (self.profile.comm_timeout is not None)
        total += settings * (2 * exchange(8, reply_size(3, 2)) + exchange(8, reply_size(6)))
        total += len(self._nameplate_codes()) * exchange(8, reply_size(3, 2))
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
        pending = self._switch_pending
        if pending is not None:
            wanted.append((pending[0].code, pending[0].from_raw(pending[1])))
        if self.profile.comm_timeout is not None:
            wanted.append((self.profile.comm_timeout.parameter, protection.timeout))
        if apply_commissioning:
            wanted += [(item.code, item.value) for item in self.profile.commissioning]
        problems = []
        self._configured = []
        self.protection_applied = None
        for code, value in wanted:
            parameter = self.profile.parameter(code)
            why, held = '', None
            try:
                raw = parameter.to_raw(value)
                held = self.read_value(parameter).raw
                if held != raw:
                    self.write_raw(parameter, raw)
                    held = self.read_value(parameter).raw     # (a write taken, not stored)
                if pending is not None and parameter is pending[0]:
                    self._switch_pending = None
                    continue                # (the switch is no setting the node keeps)
                # settings_lost() compares with what the drive holds: one that stores a
                # value otherwise must not look reset at every check
                self._configured.append((parameter, held))
                if held != raw:
                    why = f'written, the drive holds {parameter.from_raw(held):g}{parameter.unit}'
            except (ParameterError, ProtocolException) as exc:
                why = f'not set: {exc}'
            if not why:
                continue
            problems.append(f'{code} = {value:g}{parameter.unit} {why}')
            if self.profile.comm_timeout is not None and \
                    code == self.profile.comm_timeout.parameter and protection.active:
                # ~/status showed the planned protection as written (outside audit): what
                # the drive holds instead, where it was read (0: none)
                kept = parameter.from_raw(held) if held is not None else 0.0
                self.protection_applied = replace(
                    protection, mechanism=f"{code} comm-loss timeout, the drive's own" if
                    kept > 0 else '', timeout=max(kept, 0.0),
                    note=f'at connect {code} = {value:g}{parameter.unit} {why}')
        self.nameplate_note = self._nameplate_note()
        return problems

    def _nameplate_note(self) -> str:
        """Say where the drive's own nameplate scales speed otherwise than the node ('' if not).

        Only where the node took its 100 % or pole pairs from the profile's defaults: a
        drive set up for another motor (60 Hz, four poles) makes another 100 % or
        another rpm per Hz, and the wheel would run faster or slower than commanded
        with nothing said (outside audit). Advisory: a value the drive refuses or does
        not answer is not compared (pole pairs: the node's are taken), and never keeps
        the drive offline.
        """
        velocity, scaling = self.profile.velocity, self.scaling
        units = {velocity.setpoint_unit, velocity.feedback_unit}
        read: dict[str, float] = {}

        def value_of(code: str) -> float:
            if code not in read:
                try:
                    read[code] = self.read_value(self.profile.parameter(code)).value
                except VfdError as exc:     # refused, or no answer: not compared
                    log.debug('%s: nameplate %s not read: %s', self.hardware_id, code, exc)
                    read[code] = math.nan
            value = read[code]
            if code == velocity.pole_pairs and not value > 0:
                return float(scaling.pole_pairs)    # (unreadable: the node's own)
            return value if value > 0 else 0.0
        notes = []
        if SpeedUnit.PERCENT in units and scaling.rated_from_profile and (
                velocity.rated_frequency or velocity.rated_speed):
            theirs = velocity.percent_base_rpm(value_of, 0.0)
            ours = scaling.rated_speed_rpm
            if theirs > 0 and not math.isclose(theirs, ours, rel_tol=NAMEPLATE_TOLERANCE):
                shown = ', '.join(f'{code} {value:g}' for code, value in read.items()
                                  if math.isfinite(value))
                notes.append(
                    f"the drive's nameplate ({shown}) makes a 100 % setpoint {theirs:g} rpm, "
                    f'this node scales 100 % as {ours:g} rpm: the wheel would run at '
                    f'{theirs / ours:.0%} of the commanded speed; set motor.rated_speed_rpm: '
                    f'{theirs:g}')
        if SpeedUnit.HZ in units and scaling.pole_pairs_from_profile and velocity.pole_pairs:
            pairs = value_of(velocity.pole_pairs)
            if pairs > 0 and pairs != scaling.pole_pairs:
                notes.append(
                    f"the drive's nameplate has {pairs:g} pole pairs ({velocity.pole_pairs}), "
                    f'this node scales with {scaling.pole_pairs}: the wheel would run at '
                    f'{scaling.pole_pairs / pairs:.0%} of the commanded speed; set '
                    f'motor.pole_pairs: {pairs:g}')
        return '; '.join(notes)

    def _nameplate_codes(self) -> list[str]:
        """Return the parameters _nameplate_note reads (for the wire time of a connect)."""
        velocity, scaling = self.profile.velocity, self.scaling
        units = {velocity.setpoint_unit, velocity.feedback_unit}
        codes = []
        if SpeedUnit.PERCENT in units and scaling.rated_from_profile:
            codes += [velocity.rated_frequency, velocity.pole_pairs] \
                if velocity.rated_frequency else [velocity.rated_speed]
        if SpeedUnit.HZ in units and scaling.pole_pairs_from_profile:
            codes.append(velocity.pole_pairs)
        return list(dict.fromkeys(code for code in codes if code))

    def refresh_host_loss(self, protection: HostLossProtection) -> None:
        """Write a new comm-loss timeout while online (the bus's real timing outgrew the plan).

        Raises ProtocolException if the drive refuses it, TransportError if the link fails.
        """
        spec = self.profile.comm_timeout
        if spec is None:
            return
        parameter = self.profile.parameter(spec.parameter)
        raw = parameter.to_raw(protection.timeout)
        self.write_raw(parameter, raw)
        self._configured = [(p, r) for p, r in self._configured if p is not parameter]
        self._configured.append((parameter, raw))

    def settings_lost(self, one: bool = False) -> str:
        """Read back what ``configure`` set; say what differs now ('' if nothing does).

        A drive that lost them reset (a power cycle keeps only what its EEPROM
        holds); one that kept them was stopped by other means (its keypad, an
        input). A value it now refuses to read is not evidence either way. ``one``:
        only the next of them, in turn (a slow check that costs one read).
        """
        settings = self._configured
        if one and settings:
            self._next_setting = (self._next_setting + 1) % len(settings)
            settings = settings[self._next_setting:self._next_setting + 1]
        for parameter, raw in settings:
            try:
                now = self.read_value(parameter).raw
            except ProtocolException:
                continue
            if now != raw:
                return (f'{parameter.code} reads {parameter.from_raw(now):g}{parameter.unit}, '
                        f'{parameter.from_raw(raw):g}{parameter.unit} was set at connect')
        return ''

    # --- register access ------------------------------------------------------

    def explain(self, exc: ProtocolException) -> ProtocolException:
        """Return the exception with this drive's own meaning of the code (drives differ)."""
        text = self.profile.modbus.exception_codes.get(exc.code, exc.text)
        return ProtocolException(exc.code, text, exc.request)

    def _transact(self, call: Callable[[], T], write: bool = False) -> T:
        """One exchange; a garbled reply is retried once at once (the line resyncs).

        A timeout is not retried: it already cost a full timeout, and the next
        cycle asks again anyway. An exception reply is the drive's answer
        (ProtocolException), except the codes the Modbus standard gives a passing
        condition and the drive's manual no other meaning (busy, a gateway's:
        ``ModbusSpec.lasting_refusal``): those are failed exchanges.
        """
        try:
            try:
                return call()
            except BadFrame:
                return call()
        except ProtocolException as exc:
            explained = self.explain(exc)
            if not self.profile.modbus.lasting_refusal(exc.code, write):
                # Busy, a device failure, a gateway whose drive is silent: it may pass,
                # so a failed exchange (offline after comm_loss_threshold, reconnected),
                # never a status value refused until the next connect.
                raise PassingRefusal(f'{explained} (taken as a failed exchange)') from exc
            raise explained from exc

    def _read(self, address: int, count: int) -> list[int]:
        limit = self.profile.modbus.max_read_registers
        if count <= limit:           # (a status block: one read, no closure per chunk)
            return self._transact(partial(self.transport.read_registers, self.unit_id,
                                          address, count))
        words: list[int] = []
        for offset in range(0, count, limit):
            chunk = min(limit, count - offset)
            words += self._transact(lambda a=address + offset, n=chunk:
                                    self.transport.read_registers(self.unit_id, a, n))
        return words

    def _write(self, address: int, words: list[int]) -> None:
        self._transact(lambda: self._write_words(address, words), write=True)

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

    def setpoint_beyond(self, velocity: float) -> str:
        """Return why ``velocity`` would be clamped in the setpoint register ('' if not)."""
        spec, p = self.profile.velocity, self._setpoint
        native = self.scaling.to_native(velocity, spec.setpoint_unit)
        if spec.direction is DirectionMode.COMMAND:
            native = abs(native)
        type_low, type_high = (bound * p.scale for bound in p.type.bounds)
        low = max(p.minimum if p.minimum is not None else -math.inf, min(type_low, type_high))
        high = min(p.maximum if p.maximum is not None else math.inf, max(type_low, type_high))
        return beyond_register(velocity, native, low, high, f'{p.code} ({p.unit or "raw"})',
                               'gear_ratio and motor.rated_speed_rpm / motor.pole_pairs')

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

    def stop_broadcast(self) -> tuple[tuple[int, int], ...]:
        """Return the (address, value) writes that stop every drive of this profile at once.

        The zero setpoint first (the motor ramps to 0 even before the command
        changes), then the stop command; () where the setpoint is not a single
        register written by 06 (a broadcast has no read-back).
        """
        zero, _ = self._native_setpoint(0.0)
        if self._setpoint.register_count != 1 or 6 not in self.profile.modbus.function_codes:
            return ()
        return ((self._setpoint.address, zero & 0xFFFF),
                (self._command.address, self.profile.control.values['stop']))

    def write_setpoint_parameter(self, code: str, raw: int) -> None:
        parameter = self.profile.parameter(code)
        persistence = self.profile.modbus.persistence
        address = parameter.address
        if persistence.kind is PersistenceKind.ADDRESS_FLAG and persistence.covers(address):
            address |= persistence.flag   # RAM only: cyclic values must not wear the EEPROM
        self.write_raw(parameter, raw, address)

    def apply(self, velocity: float, run: bool, idle_action: str = 'stop',
              reassert: bool = False) -> None:
        """One control cycle: write the setpoint, then (re)assert run; idle: see _apply_idle.

        A run command is written only on a change (with the rising edge the
        drive needs) or when ``reassert`` says the drive does not do what was
        last written; the setpoint is written every cycle, which also feeds the
        drive's own comm-loss timer.
        """
        raw, run_action = self._native_setpoint(velocity if run else 0.0)
        if not run:
            self._apply_idle(raw, idle_action, reassert)
            return
        # A running drive that refuses a new setpoint or direction runs on at the old
        # speed, maybe the other way (outside audit): it is idled until one is taken.
        try:
            self.write_raw(self._setpoint, raw)   # (a refused setpoint never (re)starts it)
        except (ProtocolException, PassingRefusal):
            if raw != self.last_setpoint_raw:
                self._idle_after_refusal(idle_action)
            raise
        self.last_setpoint_raw = raw
        wanted = run_action
        if wanted == self.asserted_command and not reassert:
            return
        try:
            if (reassert or self.asserted_command not in RUN_ACTIONS) and \
                    self.profile.control.run_edge_from is not None:
                self.write_raw(self._command, self.profile.control.run_edge_from)
            self.send_command(wanted)
        except (ProtocolException, PassingRefusal):
            self._idle_after_refusal(idle_action)
            raise

    def _idle_after_refusal(self, idle_action: str) -> None:
        """Idle a drive told to run whose new command was refused (best effort)."""
        if self.asserted_command in RUN_ACTIONS:
            with contextlib.suppress(ProtocolException, PassingRefusal):
                self.send_command(idle_action)

    def _apply_idle(self, raw: int, idle_action: str, reassert: bool) -> None:
        """Idle: the stop command first where it is due, then the zero setpoint.

        The stop first: a drive whose replies are lost still hears it, where a
        timed-out zero setpoint ahead of it left it unsent, at every reconnect too,
        and the drive held its run command at 0 Hz, its comm-loss timer fed by those
        writes (outside re-check). Each is written even when the drive refuses the
        other; the refusal is raised after both. The setpoint goes out every cycle
        (it feeds the drive's own comm-loss timer).
        """
        if idle_action != self.asserted_command or reassert:
            try:
                self.send_command(idle_action)
            except (ProtocolException, PassingRefusal):
                with contextlib.suppress(ProtocolException, PassingRefusal):
                    self.write_raw(self._setpoint, raw)
                    self.last_setpoint_raw = raw
                raise
        self.write_raw(self._setpoint, raw)
        self.last_setpoint_raw = raw

    # --- status ---------------------------------------------------------------

    def poll(self, cycle: int, preempt: Callable[[], None] | None = None) -> Reading:
        """Read the blocks due this cycle and decode everything known so far.

        ``preempt()`` runs before each read, so a command that arrived meanwhile
        goes on the wire ahead of the remaining status reads.
        """
        known, read_at, display_period = self._words, self._read_at, self.display_period
        now = time.monotonic() if display_period or self._refused else 0.0
        if self._refused and now >= self._retry_refused_at:
            self._retry_refusals(known, preempt)
        for block, every, shown_only in self._schedule:   # (_refuse plans anew: a new list)
            if block.start in known and (cycle % every or shown_only and display_period and
                                         now < read_at.get(block.start, -math.inf)
                                         + display_period):
                continue
            if preempt is not None:
                preempt()
            try:
                words = self._read(block.start, block.count)
            except ProtocolException as exc:
                self._refuse(block, exc)
                continue
            known.update(zip(range(block.start, block.start + len(words)), words))
            read_at[block.start] = now
        reading = Reading()
        refusals, values = self._refused, reading.values
        for role, code, span, first, sign, bits, scale, parameter in self._decoding:
            if refusals:
                refused = next((refusals[a] for a in span if a in refusals), None)
                if refused is not None:
                    reading.unavailable[role] = f'{code}: {refused}'
                    continue
            if sign is not None:                  # one register
                raw = known.get(first)
                if raw is None:
                    continue
                if raw & sign:
                    raw -= 0x10000
            else:
                words = [known.get(address) for address in span]
                if None in words:
                    continue
                raw = decode_words(parameter, words)
            values[role] = raw * scale if bits is None else (raw >> bits[0]) & bits[1]
        vital = reading.unavailable and sorted(self._vital_roles & set(reading.unavailable))
        if vital:
            reading.unsafe = ('the drive refuses ' + '; '.join(
                reading.unavailable[role] for role in vital) + ': its run or fault state '
                'is unknown, so it is not run')
        for parameter in self._status_words:
            if parameter.address in known:
                reading.raw_words[parameter.code] = known[parameter.address]
        for name, rule in self.profile.flags.items():
            if rule.signal in values:
                reading.flags[name] = rule.evaluate(values[rule.signal])
        reading.fault = describe_fault(self.profile.faults, int(values.get('fault_code', 0)),
                                       int(values.get('fault_subcode', 0)))
        reading.warning_code = int(values.get('warning_code', 0))
        reading.warning_subcode = int(values.get('warning_subcode', 0))
        reading.measured_velocity = self._measured_velocity(
            values, reading.flags.get('reverse', False))
        return reading

    def _retry_refusals(self, known: dict[int, int],
                        preempt: Callable[[], None] | None) -> None:
        """Ask each refused value again, alone; one read again joins the planned reads.

        Alone, so that a refusal that lasts (a firmware without the register) costs
        one exception reply per REFUSAL_RETRY and never the values read with it.
        """
        self._retry_refused_at = math.inf
        answered = False
        for address, count in self._spans:
            if not self._refuses(address, count):
                continue
            if preempt is not None:
                preempt()
            try:
                words = self._read(address, count)
            except ProtocolException as exc:
                for register in range(address, address + count):
                    self._refused[register] = exc.text
                self._retry_refused_at = time.monotonic() + REFUSAL_RETRY
                continue
            for register in range(address, address + count):
                self._refused.pop(register, None)
            known.update(zip(range(address, address + len(words)), words))
            answered = True
        if answered:
            if not any(self._refuses(address, count) for address, count in self._spans):
                self._refused.clear()       # (a refused block's undocumented gaps too)
            self._plan_reads()

    def _refuse(self, block: ReadBlock, exc: ProtocolException) -> None:
        """Handle a refused status read: read its values one by one, drop the refused."""
        if sum(block.covers(address, count) for address, count in self._spans) > 1:
            self._plan_reads(split=block)        # next cycle: each value on its own
            return
        for address in range(block.start, block.start + block.count):
            self._refused[address] = exc.text
            self._words.pop(address, None)
        self._retry_refused_at = min(self._retry_refused_at,
                                     time.monotonic() + REFUSAL_RETRY)
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
        refusal = self.write_refusal(parameter)
        if refusal:
            raise ParameterError(f'{parameter.code}: {refusal}')
        return parameter, check_write(self.profile, parameter, value, running)

    def write_refusal(self, parameter: Parameter) -> str:
        """Return why this link cannot write ``parameter`` whole ('' if it can)."""
        count = parameter.register_count
        modbus = self.profile.modbus
        if count > 1 and not (16 in modbus.function_codes and count <= modbus.max_write_registers):
            # One register at a time, the drive would hold a half-written value between
            # the writes, and keep it if the second is refused (a Kinco A0.30: outside
            # audit; the simulated drive refuses half a value, as a careful one does).
            return (f'it spans {count} registers and {self.profile.name} takes them one '
                    'write at a time only (no function 16): a half-written value would '
                    'stand between the writes: not written (set it at the keypad)')
        return ''

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
        restore: tuple[Parameter, int] | None = None
        if persistence.kind is PersistenceKind.SWITCH_PARAMETER and \
                persistence.covers(parameter.address) and parameter.code != persistence.parameter:
            # Set for this write and set back after it, whatever its outcome: a refused
            # write changed the drive (the switch), and every later Modbus write, the
            # driver's own at each connect too, went where the last service call chose
            # (outside audit).
            switch = self.profile.parameter(persistence.parameter)
            wanted = persistence.persistent_value if persistent else persistence.volatile_value
            before = self.read_value(switch).raw
            if before != wanted:
                self.write_raw(switch, wanted)
                restore = (switch, before)
                note = f'{switch.code} set to {wanted} for it and back to {before}'
        try:
            self.write_raw(parameter, raw, address)
            readback = self.read_value(parameter)
            if readback.raw != raw:
                raise ParameterError(
                    f'{parameter.code}: wrote {raw} but the drive holds {readback.raw}')
        except VfdError:
            if restore is not None:
                try:
                    self.write_raw(*restore)
                except VfdError:       # (the write's own error is the news)
                    self._switch_pending = restore
            raise
        if restore is not None:
            try:
                self.write_raw(*restore)
            except VfdError as exc:
                self._switch_pending = restore
                note = (f'{restore[0].code} set to {wanted} for it, not back to '
                        f'{restore[1]} (at the next connect): {exc}')
        where = 'EEPROM' if persistent else 'RAM'
        if persistence.kind is not PersistenceKind.NONE and persistence.covers(parameter.address):
            note = f'{where} write' + (f'; {note}' if note else '')
        return readback, note
