"""Drive verbs over CANopen: a profile's ``canopen`` section plus a ``CanopenTransport``.

Implements the ``vfd_ros2.drives.base.Drive`` protocol, so the controller and the node
are the same as for Modbus. At connect everything is set up over SDO (PDO
mappings and transmission types, heartbeat, the drive-side protection against
host death, mode of operation, command source); afterwards each control cycle
sends one RPDO (control word + target velocity) and each poll decodes the TPDOs
the drive sent by itself: no SDO per cycle.

Two control styles, chosen by the profile's object set:
- ``cia402``: the CiA 402 state machine (``vfd_ros2.protocol.cia402``), walked one verified
  transition per cycle; the target velocity stays 0 until the drive reports
  Operation Enabled; fault reset is a rising edge of bit 7;
- ``command_word``: a manufacturer command word (Kinco 0x2A00: 0x07 run, ...).

The fault state follows the drive's status (CiA 402: the FAULT states of the
statusword; otherwise the profile's ``fault`` flag); the fault code object
(0x603F, ...) and EMCY only say which fault it is.
"""

from __future__ import annotations

import contextlib
import logging
import math
import time
from dataclasses import replace
from typing import Any, Callable, ClassVar, Iterable, Mapping

from canopen.emcy import EmcyError

from ..errors import (
    BadFrame,
    CommTimeout,
    ParameterError,
    ProfileError,
    ProtocolException,
    TransportError,
    VfdError,
)
from ..profiles import (
    NO_FAULT,
    CanObject,
    ControlStyle,
    EmcyFault,
    FaultInfo,
    FaultSpec,
    Parameter,
    Profile,
    ValueType,
    describe_fault,
)
from ..protocol.cia402 import State
from ..protocol.repeats import RepeatSummary
from ..protocol.scaling import VelocityScaling
from ..transports.base import TransportParameter
from ..transports.canopen import SYNCHRONOUS_MAX, CanopenTransport, ObjectEntry
from .base import (
    HOST_LOSS_JITTER,
    DriveOnLink,
    HostLossProtection,
    ObjectDictionaryParameters,
    Reading,
    beyond_register,
)
from .cia402 import Cia402Control

log = logging.getLogger(__name__)

#: the CiA 301 generic error code, used when a drive reports FAULT without a code
GENERIC_ERROR = 0x1000
#: distinct EMCYs logged between two error resets; repeats are summed up instead
EMCY_LOGGED_MAX = 32
#: a TPDO the drive sends at a known rate (each SYNC, or its event timer) is missing
#: after this many of its periods, and at least TPDO_SLACK s more: its values are stale
TPDO_PERIODS_MISSED = 3
TPDO_SLACK = 0.25
#: a heartbeat consumer's timeout must span this many producer periods (one may be late)
HEARTBEAT_TIMEOUT_PERIODS_MIN = 1.5
#: s between two SYNCs at most that another SYNC producer is trusted with (sync_producer false)
FOREIGN_SYNC_PERIOD = 0.5
#: s a connect waits at most for the heartbeats that say whether NMT start was obeyed (it
#: takes two to tell a refusal: a heartbeat period up to 2 s; a node that obeys answers
#: within one period)
OPERATIONAL_WAIT_LONGEST = 5.0
#: CiA 301 objects of the drive-side protection against host death
HEARTBEAT_CONSUMER = (0x1016, 1)      # consumer heartbeat time 1: node id << 16 | ms
RPDO1_DEADLINE = (0x1400, 5)          # RPDO1 event timer = deadline monitoring, ms
#: CiA 402 abort connection option code: what the drive does when those see the host gone
ABORT_CONNECTION = 0x6007


def cia_fault(code: int, register: int | None = None) -> FaultInfo:
    """Describe a CiA 301 error code no profile table knows: ``0x8130`` and its class."""
    text = EmcyError(code, register or 0, b'', 0.0).get_desc() or 'Unknown'
    where = f', error register 0x{register:02X}' if register is not None else ''
    return FaultInfo(code, 0, f'0x{code:04X}', f'{text} error (CiA 301 class)',
                     f'CiA 301 error code 0x{code:04X}{where}', 'see the drive manual',
                     known=False)


def _abort(exc: ProtocolException) -> str:
    return f'SDO abort 0x{exc.code:08X}: {exc.text}'


def decode_fault(faulted: bool, code: int, emcy: FaultInfo, faults: FaultSpec,
                 cia_codes: bool, before: FaultInfo = NO_FAULT) -> FaultInfo:
    """Return the active fault: only while the drive's status says it is faulted.

    ``code`` (0x603F or the profile's fault-code object) names the fault; a drive
    may keep its last error there after a reset, so a code alone is no fault.
    Without a code the last active EMCY names it, else the fault decoded ``before``
    (the EMCY's error reset may come before the status word leaves fault: for that
    cycle the cleared fault was named the generic error, outside re-check), else
    the CiA 301 generic error. ``cia_codes``: the profile's fault table holds CiA
    error codes (shown 0x....).
    """
    if not faulted:
        return NO_FAULT
    if code:
        return describe_fault(faults, code)
    if emcy.active:
        return emcy
    if before.active:
        return before
    return describe_fault(faults, GENERIC_ERROR) if cia_codes else cia_fault(GENERIC_ERROR)


class CanopenDrive(DriveOnLink, ObjectDictionaryParameters):
    """One drive on a CANopen transport, driven through its profile."""

    #: a profile's ``transports`` entries this class can drive (its ``canopen`` section)
    profile_transports: ClassVar[tuple[str, ...]] = ('canopen',)

    settings: ClassVar[tuple[TransportParameter, ...]] = (
        TransportParameter('object_set', '', "CANopen object set of the profile (Kinco: "
                           "manufacturer | ds402); '' = the profile's choice"),
        TransportParameter('velocity_scale', 0.0, "rpm per count of the target/actual velocity "
                           "objects; 0 = the profile's", 0.0, None),
        TransportParameter('transition_timeout', 1.0, 's a CiA 402 transition may take before '
                           'it is reported as stuck', 0.01, 60.0),
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
        self.profile = profile
        self.transport = transport
        # The transport leaves the channel with its last open node, so a drive that
        # shares it (bus_node) needs no special close; kept for build_controller.
        self.owns_transport = owns_transport
        self.unit_id = unit_id
        self.scaling = scaling
        self.spec = profile.canopen
        heartbeat = (transport.heartbeat_ms or self.spec.heartbeat_ms) / 1000.0
        if transport.heartbeat_timeout and heartbeat and \
                transport.heartbeat_timeout < HEARTBEAT_TIMEOUT_PERIODS_MIN * heartbeat - 1e-9:
            raise ParameterError(
                f'transport.heartbeat_timeout {transport.heartbeat_timeout:g} s is shorter than '
                f'{HEARTBEAT_TIMEOUT_PERIODS_MIN:g} heartbeat periods ({heartbeat * 1000:g} ms: '
                "transport.heartbeat_ms or the profile's): a healthy drive would go offline "
                "between two heartbeats; 0 = the profile's factor x the period")
        values = {p.name: p.default for p in self.settings}
        values.update(settings or {})
        self.objects = self.spec.selected(str(values['object_set']))
        self.cia402 = self.objects.control is ControlStyle.CIA402
        self.velocity_scale = float(values['velocity_scale']) or \
            self.objects.target_velocity.scale
        self.transition_timeout = float(values['transition_timeout'])
        self.tpdo_layout = self._plan_tpdos()
        mapped = [self.objects.controlword, self.objects.target_velocity,
                  self.objects.statusword, *self.objects.monitor.values()]
        transport.attach(unit_id, entries(mapped), self.spec.rpdos, self.spec.tpdos)
        self.last_setpoint_raw = 0
        self.cia = Cia402Control(self.hardware_id, self.transition_timeout,
                                 self.objects.stop_action)
        #: the host-loss protection configure() could set (None: not connected yet)
        self.protection_applied: HostLossProtection | None = None
        self._host_period = transport.host_heartbeat_period(0.0)
        self._interval: float | None = None    # the bus's addressing interval (a SYNC each)
        self._tpdo_periods: dict[int, float] = {}   # TPDO number -> s between two, at most
        self._tpdo_polls: dict[int, tuple[float, int]] = {}  # -> (heard, polls since)
        self._configured_at = 0.0
        self._configured = False
        self._values: dict[str, int] = {}    # role -> raw
        self._last_controlword: int | None = None
        self._emcy_fault: FaultInfo = NO_FAULT
        self._fault_emcy = 0            # the EMCY code a fault came with (no warning)
        self._fault_shown: FaultInfo = NO_FAULT     # the last reading's
        #: which EMCYs are logged in full (each distinct one until an error reset)
        self.emcy_log = RepeatSummary(max_keys=EMCY_LOGGED_MAX)

    @property
    def state(self) -> State | None:
        return self.cia.state

    @property
    def stuck(self) -> str:
        return self.cia.stuck

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

    def open(self) -> None:
        self.transport.open_node(self.unit_id)

    def close(self) -> None:
        self._configured = False
        self.transport.close_node(self.unit_id)

    # --- timing (an RPDO per cycle; SDO only at connect and for services) ---------------

    @property
    def link_parameters(self) -> tuple[str, ...]:
        """The profile's link settings (a Kinco's CAN bit rate and node id among them)."""
        return self.profile.identify.link_parameters if self.profile.identify else ()

    def cycle_seconds(self) -> float:
        return 0.0

    def connect_seconds(self) -> float:
        return 0.0

    def action_seconds(self) -> float:
        return 4 * self.transport.exchange_seconds(8, 8)     # SDO request and reply frames

    def host_loss_plan(self, requested: float, interval: float) -> HostLossProtection:
        """Plan the drive's own stop when the host dies (no I/O).

        The host heartbeat is produced every ``interval`` (the control period, 10..100
        ms, or transport.host_heartbeat_ms); the drive consumes it (0x1016:01) and,
        where the profile has it, supervises RPDO1 (0x1400:05). One timeout serves
        both: ``requested``, raised to twice the slower of the two periods plus the
        host's jitter, in whole ms. configure() tries it and reports what the drive
        refused.
        """
        period = self.transport.host_heartbeat_period(interval)
        self._host_period = period
        self._interval = interval
        if requested == 0:
            return HostLossProtection(requested=0.0, note='off, as drive_comm_timeout 0 asks')
        minimum = 2 * max(period, interval) + HOST_LOSS_JITTER
        value = min(math.ceil(max(requested, minimum) * 1000 - 1e-6) / 1000, 65.535)
        notes = []
        if value > requested + 1e-9:
            notes.append(f'raised from {requested:g} s: the host heartbeat and the RPDO come '
                         f'every {max(period, interval) * 1000:.0f} ms')
        if not self.spec.heartbeat_consumer:
            notes.append(f'{self.profile.name} documents no heartbeat consumer (0x1016): tried '
                         'at connect')
        mechanisms = [self._consumer_text(period)]
        if self.spec.rpdo_deadline:
            mechanisms.append('RPDO1 deadline 0x1400:05')
        return HostLossProtection(' + '.join(mechanisms), value, requested, '; '.join(notes))

    def _consumer_text(self, period: float) -> str:
        return (f'heartbeat consumer 0x1016:01 (host node {self.transport.host_node_id}, '
                f'heartbeat every {period * 1000:.0f} ms)')

    def forget_state(self) -> None:
        self._configured = False
        self.cia.reset()
        self._values.clear()
        self._last_controlword = None
        self._emcy_fault = self._fault_shown = NO_FAULT
        self._fault_emcy = 0
        self.emcy_log.forget()

    def _write(self, obj: CanObject, raw: int) -> None:
        self.transport.write_object(self.unit_id, obj.index, obj.subindex, obj.type, raw)

    def _read(self, obj: CanObject) -> int:
        return self.transport.read_object(self.unit_id, obj.index, obj.subindex, obj.type)

    def configure(self, protection: HostLossProtection,
                  apply_commissioning: bool) -> list[str]:
        """Map the PDOs, set heartbeats, protection and mode over SDO, then start the node."""
        t, unit, spec = self.transport, self.unit_id, self.spec
        problems: list[str] = []
        t.nmt(unit, 'PRE-OPERATIONAL')
        heartbeat = t.heartbeat_ms or spec.heartbeat_ms
        t.write_object(unit, 0x1017, 0, ValueType.UINT16, heartbeat)
        # RPDO1: control word + target velocity; TPDO1..: the monitored objects; the
        # others off. The library's PdoMap writes the mapping and subscribes the TPDOs.
        rpdo = [self.objects.controlword, self.objects.target_velocity]
        for number in range(1, spec.rpdos + 1):
            t.map_pdo(unit, 'rpdo', number, entries(rpdo) if number == 1 else [],
                      spec.transmission_type)
        for number in range(1, spec.tpdos + 1):
            group = self.tpdo_layout[number - 1] if number <= len(self.tpdo_layout) else []
            t.map_pdo(unit, 'tpdo', number, entries(obj for _, obj in group),
                      spec.transmission_type,
                      spec.tpdo_event_timer_ms)
        self.protection_applied = self._protect(protection, problems)
        if self.objects.mode_of_operation is not None:
            self._write(self.objects.mode_of_operation, self.objects.mode_value)
        if apply_commissioning:
            problems += self._commission()
        self.protection_applied = self._abort_reaction(self.protection_applied, problems)
        for group in self.tpdo_layout:        # the values before the first TPDO arrives
            for role, obj in group:
                self._values[role] = self._read(obj)
        self._update_state()
        t.nmt(unit, 'OPERATIONAL')
        timeout = t.heartbeat_timeout or heartbeat * spec.heartbeat_timeout_factor / 1000.0
        if heartbeat <= 0:
            problems.append('heartbeat is off (heartbeat_ms 0): link loss is not detected')
            timeout = 0.0
        t.supervise(unit, timeout)
        if heartbeat > 0:
            # Started only once its heartbeat says so: a node ignoring NMT start stayed
            # pre-operational (no PDOs) and was taken online, then dropped, in a loop.
            try:
                refused = t.await_operational(unit, min(2.5 * heartbeat / 1000.0,
                                                        OPERATIONAL_WAIT_LONGEST))
                if refused is not None:
                    raise TransportError(f'node {unit} stays {refused} after NMT start '
                                         '(its heartbeat): no PDOs are exchanged')
            except TransportError:
                # Not taken online: back to PRE-OPERATIONAL, or a node that did start
                # and is not heard trips on the RPDO deadline just set, and comes back
                # with a fault to reset by hand (outside re-check)
                with contextlib.suppress(TransportError):
                    t.nmt(unit, 'PRE-OPERATIONAL')
                raise
        self._tpdo_periods = self._tpdo_rates()
        self._tpdo_polls.clear()
        self._configured_at = time.monotonic()
        if not t.sync_producer and spec.transmission_type <= SYNCHRONOUS_MAX:
            self._await_first_tpdos()
        self._configured = True
        return problems

    def _await_first_tpdos(self) -> None:
        """Wait for the first synchronous TPDOs, sent on another device's SYNC.

        Without them the values read over SDO at connect would be shown as the
        drive's status until the supervision noticed, and after each reconnect
        again. Raises CommTimeout (the connect fails, the drive stays offline).
        """
        # One trusted SYNC period: within a connect's time budget (a managed configure
        # waits about 2 s), and short of a shutdown's wait for the loop.
        wait = FOREIGN_SYNC_PERIOD
        deadline = self._configured_at + wait
        t = self.transport
        while True:
            for number in self._tpdo_periods:       # (what is heard is noted on reading)
                t.received(self.unit_id, number)
            missing = [number for number in self._tpdo_periods
                       if (t.tpdo_heard(self.unit_id, number) or 0.0) <= self._configured_at]
            if not missing:
                return
            if time.monotonic() > deadline:
                t.count(self.unit_id, 'timeouts')
                raise CommTimeout(f'no TPDO{missing[0]} from node {self.unit_id} within '
                                  f'{wait:.2f} s of connecting: transport.sync_producer is '
                                  'false; is another device sending SYNC?')
            time.sleep(0.01)

    def _tpdo_rates(self) -> dict[int, float]:
        """Return the longest time between two TPDOs, for each one sent at a known rate.

        Synchronous TPDOs come with every n-th SYNC, which this host sends once per
        bus cycle (when it produces SYNC); asynchronous ones at least every event
        timer. Event-driven TPDOs without a timer (sent on change only, e.g. the
        Kinco's) may rightly stay silent: no rate, not supervised.
        """
        spec, rates = self.spec, {}
        for number, group in enumerate(self.tpdo_layout, 1):
            if not group:
                continue
            if spec.transmission_type <= SYNCHRONOUS_MAX:
                if self.transport.sync_producer and self._interval:
                    rates[number] = max(spec.transmission_type, 1) * self._interval
                elif not self.transport.sync_producer and spec.transmission_type >= 1:
                    # Another device's SYNC, at a rate not known here: at least this
                    # often, or its status would be shown for ever once it stopped.
                    # (Type 0, acyclic, comes on a change only: not supervised.)
                    rates[number] = spec.transmission_type * FOREIGN_SYNC_PERIOD
            elif spec.tpdo_event_timer_ms > 0:
                rates[number] = spec.tpdo_event_timer_ms / 1000.0
        return rates

    def _check_tpdos_arrive(self) -> None:
        """Raise CommTimeout when a TPDO sent at a known rate stopped: its values are stale.

        A node whose heartbeat goes on but whose TPDOs stop (a PDO producer that
        died, a mapping lost) would otherwise show its last status for ever. Missing
        means too long ago and, for a synchronous one, over several polls (each
        after a SYNC): a loop that paused (a long service action) sent no SYNC then.
        """
        now = time.monotonic()
        synchronous = self.spec.transmission_type <= SYNCHRONOUS_MAX
        for number, period in self._tpdo_periods.items():
            heard = max(self.transport.tpdo_heard(self.unit_id, number) or 0.0,
                        self._configured_at)
            polls = self._tpdo_polls.get(number, (0.0, 0))
            polls = (heard, polls[1] + 1) if polls[0] == heard else (heard, 0)
            self._tpdo_polls[number] = polls
            age = now - heard
            if age > max(TPDO_PERIODS_MISSED * period, period + TPDO_SLACK) and (
                    not synchronous or
                    polls[1] > TPDO_PERIODS_MISSED * self.spec.transmission_type):
                malformed = self.transport.tpdo_malformed(self.unit_id, number)
                if malformed:       # frames come, of the wrong length: not silence
                    raise BadFrame(f'{malformed} (PDO mapping 0x{0x1A00 + number - 1:04X} '
                                   'not as written at connect?): its status is stale')
                self.transport.count(self.unit_id, 'timeouts')
                hint = '' if not synchronous or self.transport.sync_producer else \
                    ': transport.sync_producer is false; is another device sending SYNC?'
                raise CommTimeout(f'no TPDO{number} from node {self.unit_id} for {age:.2f} s '
                                  f'(expected every {period * 1000:.0f} ms): its status is '
                                  f'stale{hint}')

    def _protect(self, protection: HostLossProtection, problems: list[str]) -> HostLossProtection:
        """Produce the host heartbeat and set what ``protection`` plans; return what holds.

        A write the drive aborts is reported in ``problems`` and dropped from the
        result: with nothing left, the result says so (diagnostics WARN).
        """
        t, unit = self.transport, self.unit_id
        u16, u32 = ValueType.UINT16, ValueType.UINT32
        t.produce_heartbeat(self._host_period)
        if not protection.active:
            # Off: clear what an earlier session may have left (a drive without the
            # objects refuses, which is fine).
            for (index, sub), value_type in ((HEARTBEAT_CONSUMER, u32), (RPDO1_DEADLINE, u16)):
                if index == RPDO1_DEADLINE[0] and not self.spec.rpdo_deadline:
                    continue
                try:
                    t.write_object(unit, index, sub, value_type, 0)
                except ProtocolException:
                    pass
            return protection
        ms = min(round(protection.timeout * 1000), 0xFFFF)
        held, refused = [], []
        consumer = (t.host_node_id << 16) | ms
        try:
            t.write_object(unit, *HEARTBEAT_CONSUMER, u32, consumer)
            readback = t.read_object(unit, *HEARTBEAT_CONSUMER, u32)
            if readback == consumer:
                held.append(self._consumer_text(self._host_period))
            else:
                refused.append(f'heartbeat consumer 0x1016:01 = 0x{consumer:08X} reads back '
                               f'0x{readback:08X}')
        except ProtocolException as exc:
            refused.append(f'the drive refused the heartbeat consumer 0x1016:01 ({_abort(exc)})')
        if self.spec.rpdo_deadline:
            try:
                t.write_object(unit, *RPDO1_DEADLINE, u16, ms)
                held.append('RPDO1 deadline 0x1400:05')
            except ProtocolException as exc:
                refused.append(f'the drive refused the RPDO1 deadline 0x1400:05 ({_abort(exc)})')
        problems.extend(refused)
        if not held:
            log.warning('%s: no drive-side protection against host death: %s',
                        self.hardware_id, '; '.join(refused))
            return HostLossProtection(requested=protection.requested, note=(
                '; '.join(refused) + ': only the host watchdog stops the motor, not a dead '
                'host'))
        notes = [note for note in (protection.note, *refused) if note]
        return HostLossProtection(' + '.join(held), ms / 1000, protection.requested,
                                  '; '.join(notes))

    def _abort_reaction(self, protection: HostLossProtection,
                        problems: list[str]) -> HostLossProtection:
        """Return ``protection`` as the drive's reaction to a lost master makes it.

        The heartbeat consumer and the RPDO deadline only tell the drive that the
        master is gone; CiA 402's 0x6007 (abort connection option code) says what it
        does then, and 0 is nothing: the motor runs on at its last target (outside
        audit). Read where the profile has the object (commissioning writes 1): 0 is
        no protection; a drive without it is told as the maker's reaction.
        """
        parameter = next((p for p in self.profile.parameters.values()
                          if p.index == ABORT_CONNECTION and p.subindex == 0), None)
        if parameter is None or not protection.active:
            return protection
        try:
            option = parameter.from_raw(self._read_raw(parameter))
        except VfdError as exc:     # refused, or no SDO answer: advisory, never offline
            # (a refused commissioning write of it is in problems already)
            note = (f'0x6007 (the reaction to a lost master) unreadable ({exc}): the '
                    "maker's reaction, not verified")
            return replace(protection, note='; '.join(n for n in (protection.note, note) if n))
        if option == 0:
            note = ('0x6007 abort connection option = 0, no action: the drive runs on at '
                    'its last target velocity when the host dies, whatever '
                    f'{protection.mechanism} sees; only the host watchdog stops the motor '
                    '(set 0x6007 to 1, or apply_commissioning: true)')
            log.warning('%s: %s', self.hardware_id, note)
            return HostLossProtection(requested=protection.requested, note=note)
        return protection

    def _commission(self) -> list[str]:
        problems = []
        for item in self.profile.commissioning:
            parameter = self.profile.parameter(item.code)
            if parameter.index is None:
                problems.append(f'{item.code} has no CANopen object: not written')
                continue
            try:
                raw = parameter.to_raw(item.value)
                if self._read_raw(parameter) != raw:
                    self.transport.write_object(self.unit_id, parameter.index,
                                                parameter.subindex, parameter.type, raw)
            except (ParameterError, ProtocolException) as exc:   # e.g. an SDO abort
                problems.append(f'{item.code} = {item.value:g}: {exc}')
        return problems

    # --- control ----------------------------------------------------------------------

    def _setpoint_range(self) -> tuple[int, int]:
        low, high = self.objects.target_velocity.type.bounds
        setpoint = self.profile.parameters.get(self.profile.velocity.setpoint)
        if setpoint is not None and setpoint.index == self.objects.target_velocity.index:
            if setpoint.minimum is not None:
                low = max(low, math.ceil(setpoint.minimum / setpoint.scale))
            if setpoint.maximum is not None:
                high = min(high, math.floor(setpoint.maximum / setpoint.scale))
        return low, high

    def setpoint_beyond(self, velocity: float) -> str:
        """Return why ``velocity`` would be clamped in the target velocity ('' if not)."""
        native = self.scaling.to_native(velocity, self.objects.velocity_unit)
        return beyond_register(velocity, native / self.velocity_scale, *self._setpoint_range(),
                               f'0x{self.objects.target_velocity.index:04X}',
                               'drive.velocity_scale (rpm per count) and gear_ratio')

    def _native(self, velocity: float) -> int:
        native = self.scaling.to_native(velocity, self.objects.velocity_unit)
        low, high = self._setpoint_range()
        return min(max(round(native / self.velocity_scale), low), high)

    def apply(self, velocity: float, run: bool, idle_action: str = 'stop',
              reassert: bool = False) -> None:
        """One control cycle: one RPDO with control word and target velocity.

        The RPDO carries the control word every cycle, so ``reassert`` needs nothing more.
        """
        if not self._configured:
            # Connect, or a stop as the link is lost: zero the setpoint and idle over SDO,
            # once the node is told to take SDO. A node in NMT STOPPED (by itself, or its
            # own comm-loss reaction) ignores SDO and PDOs: it ran on, and every reconnect
            # failed on its first SDO read, until the node was reset (outside audit).
            self.transport.nmt(self.unit_id, 'PRE-OPERATIONAL')
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
        return self.cia.controlword(run, idle_action)

    def _send_rpdo(self, controlword: int, velocity_raw: int) -> None:
        self.transport.transmit(self.unit_id, 1, [controlword, velocity_raw])
        self._last_controlword = controlword
        self.last_setpoint_raw = velocity_raw

    def _send_controlword(self, controlword: int) -> None:
        if self._configured:
            self._send_rpdo(controlword, 0)
            # A command outside the cycle (a service action) takes effect now: a SYNC-driven
            # drive applies only the last RPDO before each SYNC, and a fault reset is an edge.
            self.transport.end_command_burst()
        else:
            self._write(self.objects.controlword, controlword)
            self._last_controlword = controlword

    def send_command(self, action: str) -> None:
        """Send one command now (fault_reset: a rising edge of bit 7 on CiA 402 drives)."""
        if self.cia402:
            words = self.cia.action_words(action, self._last_controlword)
        else:
            if action not in self.objects.commands:
                raise ParameterError(f'{self.profile.name} has no {action!r} command')
            words = [self.objects.commands[action]]
        for word in words:
            self._send_controlword(word)

    # --- status -----------------------------------------------------------------------

    def _update_state(self) -> None:
        if self.cia402 and self._status_role in self._values:
            self.cia.update(self._values[self._status_role])

    def poll(self, cycle: int, preempt: Callable[[], None] | None = None) -> Reading:
        """Decode what the drive sent (TPDOs, EMCY); raise if its heartbeat is lost."""
        nmt = self.transport.check_alive(self.unit_id)
        if self._configured and nmt not in (None, 'OPERATIONAL'):
            raise TransportError(f'node {self.unit_id} reports NMT state {nmt}')
        for number, group in enumerate(self.tpdo_layout, 1):
            raws = self.transport.received(self.unit_id, number)
            if raws is None:
                continue
            for (role, _), raw in zip(group, raws):
                self._values[role] = raw
        if self._configured:
            self._check_tpdos_arrive()
        self._update_state()
        self._take_emcy()
        return self._reading()

    @property
    def _cia_codes(self) -> bool:
        """Whether the profile's fault table holds CiA error codes (EMCY bytes 0-1)."""
        return self.spec.emcy_fault is EmcyFault.ERROR_CODE

    def _describe_emcy(self, emcy: EmcyError) -> FaultInfo:
        if self.spec.emcy_fault is EmcyFault.MANUFACTURER_BYTE and emcy.data[:1] != b'\0':
            return describe_fault(self.profile.faults, emcy.data[0])
        if self._cia_codes:
            return describe_fault(self.profile.faults, emcy.code)
        return cia_fault(emcy.code, emcy.register)      # e.g. a Kinco's 0x8110 CAN overrun

    def _take_emcy(self) -> None:
        new, active = self.transport.take_emcy(self.unit_id)
        now = time.monotonic()
        for emcy in new:
            if not emcy.code & 0xFF00:
                log.info('%s EMCY error reset', self.hardware_id)
                self.emcy_log.forget()
                continue
            # Each distinct EMCY is logged once until the next error reset: a node that
            # repeats one (or floods the bus) must not flood the log.
            if not self.emcy_log.first((emcy.code, emcy.register, bytes(emcy.data)), now):
                continue
            info = self._describe_emcy(emcy)
            desc = emcy.get_desc()          # (the library's class text; '' for some codes)
            log.warning('%s EMCY 0x%04X%s register 0x%02X data %s: %s %s', self.hardware_id,
                        emcy.code, f' ({desc})' if desc else '', emcy.register,
                        emcy.data.hex(' '), info.display, info.name)
        repeats = self.emcy_log.due(now)
        if repeats:
            log.warning('%s: %d more EMCY frames, already logged since the last error reset',
                        self.hardware_id, repeats)
        self._emcy_fault = self._describe_emcy(active[-1]) if active else NO_FAULT
        if not active:
            self._fault_emcy = 0

    def _reading(self) -> Reading:
        reading = Reading(stuck=self.cia.stuck)
        monitor = self.objects.monitor
        for role, raw in self._values.items():
            obj = monitor[role]
            scale = self.velocity_scale if role == 'motor_speed' else obj.scale
            reading.values[role] = raw * scale
        status = self._values.get(self._status_role)
        if status is not None:
            reading.raw_words[obj_code(self.objects.statusword)] = status
        code = int(reading.values.get('fault_code', 0))
        if self.cia402:
            state = self.state
            if state is not None:
                reading.raw_words['cia402_state'] = int(state)
            faulted = self.cia.faulted
            reading.flags = self.cia.flags(status, reading.values.get('motor_speed', 0.0))
        else:
            for name, rule in self.profile.flags.items():
                if rule.signal in reading.values:
                    reading.flags[name] = rule.evaluate(reading.values[rule.signal])
            faulted = reading.flags.get('fault', code != 0)
        reading.fault = decode_fault(faulted, code, self._emcy_fault, self.profile.faults,
                                     self._cia_codes, self._fault_shown)
        self._fault_shown = reading.fault
        if reading.fault.active:
            self._fault_emcy = self._emcy_fault.code
        elif self._emcy_fault.active and self._emcy_fault.code != self._fault_emcy:
            # An EMCY the drive did not fault on (a warning: a temperature, say) is the
            # warning until its error reset; it was only logged (outside audit). The
            # one a fault came with is not, after the fault's reset, without an EMCY
            # error reset: some drives send none.
            reading.warning_code = self._emcy_fault.code
            reading.warning_subcode = self._emcy_fault.subcode
            reading.flags['warning'] = True
        speed = reading.values.get('motor_speed')
        if speed is not None:
            reading.measured_velocity = self.scaling.from_native(speed,
                                                                 self.objects.velocity_unit)
        return reading

    # --- parameters ---------------------------------------------------------------------

    def _reachable(self, parameter: Parameter) -> Parameter:
        if parameter.index is None:
            raise ParameterError(f'{parameter.code} ({parameter.description}) has no CANopen '
                                 'object: not reachable over CANopen')
        return parameter

    def _read_raw(self, parameter: Parameter) -> int:
        return self.transport.read_object(self.unit_id, parameter.index, parameter.subindex,
                                          parameter.type)

    def _write_raw(self, parameter: Parameter, raw: int, persistent: bool) -> None:
        self.transport.write_object(self.unit_id, parameter.index, parameter.subindex,
                                    parameter.type, raw)

def obj_code(obj: CanObject) -> str:
    return obj.code or str(obj)


def entries(objects: Iterable[CanObject]) -> list[ObjectEntry]:
    """Return the transport's view of profile objects: address, name and type."""
    return [ObjectEntry(obj.index, obj.subindex, obj_code(obj), obj.type) for obj in objects]
