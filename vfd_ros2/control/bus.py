"""Several drives on one link: one thread owns the port and serves every drive.

Each cycle writes every drive's command first, then polls every drive's
status, so a command never waits behind another drive's slow status read.
A drive that does not answer costs one short timeout per reconnect period
(its controller retries only every ``reconnect_period``), so it never stalls
the others; it alone goes offline.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from dataclasses import dataclass, replace
from typing import Any, Callable, Mapping, Sequence

import yaml

from ..drives import drive_class_for
from ..errors import ParameterError, TransportError, VfdError
from ..transports import load_transport_class
from ..transports.base import Transport, TransportStats
from .controller import DriveController
from .factory import build_controller, build_transport, link_settings
from .loop import SHUTDOWN_WAIT, CycleLoop, RateWatch
from .settings import SETTINGS

log = logging.getLogger(__name__)

#: settings that belong to the bus, not to one drive
BUS_KEYS = ('control_rate', 'realtime_priority')
#: s the end of the loop waits for a connect running beside it: the connect wrote the
#: drive's stop first, and a slow node's remaining SDO exchanges must not hold a Ctrl-C
CONNECT_JOIN_TIMEOUT = 2.0


@dataclass(frozen=True)
class BusStatistics:
    """Per-bus figures for /diagnostics."""

    transactions_per_second: float
    errors: int
    timeouts: int
    bad_frames: int
    utilisation: float | None   # fraction of the wire's capacity in use (RTU), None if unknown
    overruns: int
    cycles_per_second: float = 0.0
    #: the loop runs short of control_rate (RateWatch)
    rate_short: bool = False


@dataclass(frozen=True)
class DriveEntry:
    key: str
    namespace: str
    name: str
    settings: dict[str, Any]


@dataclass(frozen=True)
class BusConfig:
    name: str
    settings: dict[str, Any]
    drives: tuple[DriveEntry, ...]


def parse_bus_config(data: Mapping[str, Any]) -> BusConfig:
    """Validate a bus YAML document (see config/sim_agv_bus.yaml)."""
    if not isinstance(data, Mapping) or not isinstance(data.get('bus'), Mapping) or \
            'drives' not in data:
        raise ParameterError('a bus file needs a "bus" mapping and a "drives" mapping')
    bus = dict(data['bus'])
    name = str(bus.pop('name', 'bus'))
    transport_type = str(bus.get('transport.type', 'modbus_rtu'))
    transport_class = load_transport_class(transport_type)
    link_keys = {'transport.type'} | {f'transport.{p.name}' for p in transport_class.parameters}
    # what a drive entry may set: any drive_node setting, its drive class's drive.* ones;
    # each with its default, whose kind (number, flag, text) a value must have
    defaults = {s.name: s.default for s in SETTINGS} | \
        {f'drive.{p.name}': p.default for p in drive_class_for(transport_class).settings} | \
        {f'transport.{p.name}': p.default for p in transport_class.parameters}
    known = {name for name in defaults if not name.startswith('transport.')} | \
        {'transport.unit_id'}
    for key, value in bus.items():
        if not (key.startswith('transport.') or key in BUS_KEYS):
            raise ParameterError(f'bus setting {key!r}: only transport.* and {BUS_KEYS}')
        if key.startswith('transport.') and key not in link_keys:
            raise ParameterError(f'bus setting {key!r}: {transport_type} has no such setting '
                                 f'(it has {", ".join(sorted(link_keys))})')
        if why := _wrong_kind(defaults.get(key), value):
            raise ParameterError(f'bus setting {key}: {why}')
    if not isinstance(data['drives'], Mapping) or not data['drives']:
        raise ParameterError('"drives" must map a name to each drive\'s settings')
    drives = []
    unit_ids = set()
    for key, entry in data['drives'].items():
        if not isinstance(entry, Mapping):
            raise ParameterError(f'drive {key}: its settings must be a mapping (at least '
                                 f'transport.unit_id), not {entry!r}')
        settings = dict(entry)
        # Relative (the default: the drive's key) resolves in the bus node's namespace.
        namespace = str(settings.pop('namespace', key))
        node_name = str(settings.pop('name', 'drive'))
        for setting in settings:
            if (setting.startswith('transport.') and setting != 'transport.unit_id') or \
                    setting in BUS_KEYS:
                raise ParameterError(f'drive {key}: {setting} belongs to the bus')
            if not setting.startswith('transport.') and setting not in known:
                raise ParameterError(f'drive {key}: unknown setting {setting!r}')
            if why := _wrong_kind(defaults.get(setting), settings[setting]):
                raise ParameterError(f'drive {key}: {setting}: {why}')
        unit = settings.get('transport.unit_id', 1)
        if unit in unit_ids:
            raise ParameterError(f'drive {key}: unit id {unit} used twice on bus {name}')
        unit_ids.add(unit)
        drives.append(DriveEntry(str(key), namespace, node_name, settings))
    return BusConfig(name, bus, tuple(drives))


def _wrong_kind(default: Any, value: Any) -> str:
    """Return why ``value`` cannot stand for a setting whose default is ``default``."""
    if default is None:
        return ''
    if isinstance(default, bool):
        return '' if isinstance(value, bool) else f'true or false, not {value!r}'
    if isinstance(default, (int, float)):
        return '' if isinstance(value, (int, float)) and not isinstance(value, bool) else \
            f'a number, not {value!r}'
    if isinstance(default, str):
        return '' if isinstance(value, (str, Mapping)) else f'a text, not {value!r}'
    return ''


def load_bus_config(path: str) -> BusConfig:
    try:
        with open(path, encoding='utf-8') as stream:
            return parse_bus_config(yaml.safe_load(stream))
    except (OSError, UnicodeDecodeError) as exc:
        raise ParameterError(f'cannot read bus file {path}: {exc}') from exc
    except yaml.YAMLError as exc:
        raise ParameterError(f'bus file {path} is not valid YAML: {exc}') from exc


class Bus:
    """One link, several drive controllers, one thread.

    A transport is normally one link shared by every drive (a serial port, a CAN
    channel). A transport that addresses one device per handle
    (``shared_by_drives = False``) gets one handle per drive, still served by
    this one thread and process.
    """

    def __init__(self, config: BusConfig, clock: Callable[[], float] = time.monotonic) -> None:
        self.config = config
        self._clock = clock
        self.controllers: dict[str, DriveController] = {}
        first_values = {**config.settings, **config.drives[0].settings}
        self._check_one_link(config)
        shared = load_shared(first_values)
        self.transport: Transport = build_transport(first_values)
        for entry in config.drives:
            try:
                self.controllers[entry.key] = build_controller(
                    {**config.settings, **entry.settings},
                    transport=self.transport if shared or entry is config.drives[0] else None)
            except VfdError as exc:
                raise ParameterError(f'drive {entry.key}: {exc}') from exc
        self._all = tuple(self.controllers.values())   # fixed from here on
        self.transports = list({id(c.drive.transport): c.drive.transport
                                for c in self.controllers.values()}.values())
        for controller in self.controllers.values():
            # On one line, any drive's new command goes out before the next status read.
            controller.preempt_hook = self.preempt_between_reads
            controller.request_preempt = self._command_arrived
        rate = float(config.settings.get('control_rate', 50.0))
        self.period = 1.0 / rate
        self.addressing_interval = self._addressing_interval()
        for controller in self.controllers.values():
            controller.plan_host_loss(self.addressing_interval)
        self._loop: CycleLoop | None = None
        self._stepping: CycleLoop | None = None      # the last started (see _ending)
        self._lock = threading.Lock()
        self._window: tuple[float, float, int] = (clock(), 0.0, 0)  # when, wire s, transactions
        self._rate = RateWatch(clock)
        self._connect_turn = 0
        # The drive connecting on a thread of its own (connects_beside_the_cycle), if any:
        # the bus thread leaves it alone until that thread has ended.
        self._beside: tuple[DriveController, threading.Thread] | None = None
        self._broadcast_for: tuple[float, ...] = ()
        self.broadcast_stops = 0      # watchdog trips of every running drive, stopped at once
        # What the checks before every status read look at, so that they cost nothing
        # when there is nothing to do (scanning every drive before every read was most
        # of a 32-drive bus's time): a new command arrived, and the earliest moment a
        # running drive's watchdog can expire (feeding only moves it later, so an old
        # value errs towards checking too early).
        self._command_waiting = False
        self._watchdog_check_at = 0.0
        self._keep_alive_check_at = math.inf     # see _plan_keep_alive (after the first polls)

    @staticmethod
    def _check_one_link(config: BusConfig) -> None:
        """Refuse drives whose factory link settings (baud rate, framing) differ.

        The bus section's ``transport.*`` left at 0/'' means the drive's factory
        value; on one line every drive must have the same, or the line would run at
        whichever drive is listed first.
        """
        links = {}
        for entry in config.drives:
            try:
                links[entry.key] = link_settings({**config.settings, **entry.settings})
            except VfdError as exc:
                raise ParameterError(f'drive {entry.key}: {exc}') from exc
        # only what the transport takes (a TCP link has no baud rate to agree on)
        names = {p.name for p in load_transport_class(
            str(config.settings.get('transport.type', 'modbus_rtu'))).parameters}
        first = config.drives[0].key
        for key, link in links.items():
            differ = sorted(name for name in names
                            if link.get(name) != links[first].get(name))
            if differ:
                raise ParameterError(
                    f'drives {first} and {key} differ in their factory link settings ('
                    + ', '.join(f'{name} {links[first].get(name)} against {link.get(name)}'
                                for name in differ)
                    + '): set ' + ', '.join(f'transport.{name}' for name in differ)
                    + ' in the bus section, and the drives to match')

    def _addressing_interval(self) -> float:
        """Worst-case time between two requests to any drive of this bus.

        One cycle of every drive (or the control period, if longer), plus what a
        cycle may add: one connect or one failed exchange, and one service action.
        More connects in one cycle use only the offline drives' part of it
        (``_connect_candidates``).
        """
        drives = [c.drive for c in self.controllers.values()]
        cycle = sum(drive.cycle_seconds() for drive in drives)
        extra = 0.0
        if len(drives) > 1:      # another drive's connect or failure (a drive's own is not)
            extra = max(max(d.connect_seconds() for d in drives),
                        max(t.failed_exchange_seconds() for t in self.transports))
        return max(self.period, cycle) + extra + max(d.action_seconds() for d in drives)

    def set_rate(self, rate: float) -> None:
        """Change the bus thread's cycle rate (Hz) at once; ParameterError why not.

        Every drive's controller gets the new period too (what it reports and
        sizes with); while running, refused, changing nothing, when a drive's
        comm-loss timeout written at connect would not fit the new addressing
        interval (before the bus starts, the timeouts are sized anew).
        """
        if not (math.isfinite(rate) and rate > 0):
            raise ParameterError(f'control_rate must be a finite number > 0, got {rate}')
        period = 1.0 / rate
        previous = self.period
        self.period = period
        try:
            interval = self._addressing_interval()
            for controller in self.controllers.values():
                if self._loop is not None:
                    controller.check_cycle_period(period, interval)
                else:   # not running yet (a managed bus): nothing written, plan anew
                    controller.drive.host_loss_plan(controller.config.drive_comm_timeout,
                                                    interval)
        except Exception:
            self.period = previous
            raise
        self.addressing_interval = interval
        for controller in self.controllers.values():
            controller.config = replace(controller.config, cycle_period=period)
            if self._loop is None:
                controller.plan_host_loss(interval)
        if self._loop is not None:
            self._loop.set_period(period)

    def step(self) -> None:
        controllers = self._serving()
        if self.transport.connects_beside_the_cycle:
            self._connect_beside(controllers)
            controllers = self._serving()       # not the one whose connect just started
            candidates, budget = {}, 0.0
        else:
            candidates, budget = self._connect_candidates(controllers)
        spent, tried = 0.0, 0   # the link time this cycle's connects took, measured
        # The first in connect order is tried whatever its place on the bus; the others
        # must leave it room until it has been (the drives are served in bus order).
        head = next(iter(candidates), None)
        reserved = candidates.get(head, 0.0)
        self._command_waiting = False           # every command is written now
        self._plan_watchdog_check()
        for controller in controllers:          # commands first, for every drive ...
            if self._ending():
                return
            # A watchdog may expire mid-phase: then all drives at once, not in turn.
            self._broadcast_stop_if_all_tripped()
            cost = candidates.get(controller)
            # Besides the head, a connect must still fit what the others really took
            # (a slow drive's connect takes its timeouts, not the wire's time).
            if controller is head:
                connect, reserved = True, 0.0
            else:
                connect = cost is not None and spent + cost + reserved <= budget
            if connect:
                # A connect is several exchanges: a new command or a tripped
                # watchdog of a drive already done goes out before it.
                self.preempt_between_reads()
                started = self._clock()
            controller.command_phase(connect_allowed=connect)
            if connect:
                # (its first status poll, later this cycle, counted as planned)
                spent += self._clock() - started + controller.drive.cycle_seconds()
                tried += 1
        self._connect_turn += tried
        for transport in self.transports:       # (CANopen: one SYNC applies them all)
            transport.end_command_burst()
        self._plan_watchdog_check()             # drives may have started running
        for controller in controllers:          # ... then the slower status polls
            if self._ending():
                return
            controller.poll_phase()
        self._plan_keep_alive(controllers)

    def _ending(self) -> bool:
        """Whether the loop is asked to end: the rest of the cycle gives way to the stops.

        A silent drive costs its timeouts in every exchange: the cycle under way
        when Ctrl-C came held back the running drives' stops by as many (re-check).
        (The loop that runs the steps: ``shutdown`` forgets it even if it outlives
        the wait.)
        """
        return self._stepping is not None and self._stepping.stopping

    def _serving(self) -> Sequence[DriveController]:
        """Return the drives this thread serves: all but one connecting beside the cycle.

        Called before every status read and wait (``preempt_at``): while nothing
        connects beside the cycle, every bus but a reconnecting CANopen one, it
        builds nothing.
        """
        beside = self._beside
        if beside is not None and not beside[1].is_alive():
            self._beside = beside = None
        if beside is None:
            return self._all
        return [c for c in self._all if c is not beside[0]]

    def _connect_beside(self, controllers: Sequence[DriveController]) -> None:
        """Start the next due drive's connect on a thread of its own (one at a time).

        On a link that allows it (``Transport.connects_beside_the_cycle``), a connect
        (CANopen: some fifty SDO exchanges, each up to the SDO timeout when the node
        is slow or silent) would otherwise hold every other drive's commands,
        watchdog stops and RPDO deadline for as long. That drive is left out of
        the cycle until its thread ends; the next cycle serves it as usual.
        """
        if self._beside is not None:
            return
        due = self._connect_order(controllers)
        if not due:
            return
        controller = due[0]
        self._connect_turn += 1
        thread = threading.Thread(target=self._connect_alone, args=(controller,),
                                  name=f'vfd connect {controller.drive.hardware_id}',
                                  daemon=True)
        self._beside = (controller, thread)
        thread.start()

    @staticmethod
    def _connect_alone(controller: DriveController) -> None:
        try:
            controller.connect_now()
        except Exception as exc:  # noqa: BLE001 - the thread must end with the drive offline
            log.exception('%s: connect failed: %s', controller.drive.hardware_id, exc)

    def _connect_order(self, controllers: Sequence[DriveController]) -> list[DriveController]:
        """Return the drives due to connect in the order to try them.

        Each in turn, but the fewer connects a drive has failed in a row, the sooner:
        a healthy drive that rebooted (or whose first tries came while it was still
        silent) must not wait behind every silent or refusing drive's attempt (each
        up to its timeouts) on a bus of many. Drives that keep failing take turns,
        as each failure puts the drive behind the others.
        """
        due = [c for c in controllers if c.connect_due]
        if not due:
            return []
        first = self._connect_turn % len(due)
        return sorted(due[first:] + due[:first], key=lambda c: c.link.failed_connects)

    def _connect_candidates(self, controllers: Sequence[DriveController]
                            ) -> tuple[dict[DriveController, float], float]:
        """Offline drives due to connect this cycle, with their planned cost, and the budget.

        The drives' host-loss timeouts were sized for a cycle of every drive plus
        one connect (``addressing_interval``). While drives are offline their part of
        that cycle is free: connects may use it, so a bus starting 32 drives does not
        take 32 ever longer cycles to bring them online. In turn, as many as fit
        (each counted at its worst, a silent drive's timeout), at least one; ``step``
        tries the first whatever its place on the bus, and checks each other against
        the time the others really took.
        """
        due = self._connect_order(controllers)
        if not due:
            return {}, 0.0
        budget = (self.addressing_interval
                  - max(c.drive.action_seconds() for c in controllers)
                  - sum(c.drive.cycle_seconds() for c in controllers if c.link.online))
        chosen: dict[DriveController, float] = {}
        planned = 0.0
        for controller in due:
            cost = max(controller.drive.connect_seconds(),
                       controller.drive.transport.failed_exchange_seconds())
            if chosen and planned + cost > budget:
                break
            chosen[controller] = cost
            planned += cost
        return chosen, budget

    def _command_arrived(self) -> None:
        """Note a drive's new command (any thread): it goes out before the next status read."""
        self._command_waiting = True
        if self._loop is not None:
            self._loop.request_preempt()

    def preempt_between_reads(self) -> None:
        """``preempt`` before a status read, when a command waits or a watchdog may be due.

        Also before it: a drive whose comm-loss timeout the cycle is about to outlast
        (slow replies) has it raised now (``DriveController.keep_alive``).
        """
        now = self._clock()
        if now >= self._keep_alive_check_at:
            serving = self._serving()
            for controller in serving:
                if controller.keep_alive_at() <= now:
                    controller.keep_alive()
            self._plan_keep_alive(serving)
        if not self._command_waiting and now < self._watchdog_check_at:
            return
        self._command_waiting = False
        self.preempt()
        self._plan_watchdog_check()

    def _plan_keep_alive(self, controllers: Sequence[DriveController]) -> None:
        """Note the earliest moment a drive nears its comm-loss timeout unaddressed."""
        self._keep_alive_check_at = min((c.keep_alive_at() for c in controllers),
                                        default=math.inf)

    def _plan_watchdog_check(self) -> None:
        """Note the earliest moment a running drive's watchdog can expire (or never)."""
        self._watchdog_check_at = self.preempt_at() or math.inf

    def preempt(self) -> None:
        """Write every drive's new command now, before the next status read."""
        self._broadcast_stop_if_all_tripped()
        wrote = [controller.preempt() for controller in self._serving()]
        if any(wrote):
            for transport in self.transports:
                transport.end_command_burst()

    def _broadcast_stop_if_all_tripped(self) -> None:
        """When every running drive's watchdog trips at once, stop them in one frame.

        The planner died, say: on a slow shared line, one stop after the other
        would reach the last drive several transactions late. A broadcast (unit 0,
        unanswered) reaches all at once; each drive's own stop follows as usual
        and is verified by its status. Only where every drive on the line shares
        the same stop writes, so no drive gets another's meaning of a register.
        """
        if not getattr(self.transport, 'broadcast_stops', False) or len(self.controllers) < 2:
            return              # (checked first: this runs before every drive's command)
        horizon = self._clock() + 0.002
        if horizon < self._watchdog_check_at:
            return              # no running drive's watchdog expires this soon
        running = [c for c in self.controllers.values() if c.runs]
        if len(running) < 2 or not all(c.watchdog_due(horizon) for c in running):
            return
        key = tuple(sorted(c.preempt_at() or 0.0 for c in running))
        if key == self._broadcast_for:
            return          # this trip was broadcast already
        self._broadcast_for = key       # (once, sent or not: a failure is not retried)
        if self._broadcast_stop():
            self.broadcast_stops += 1

    def _broadcast_stop(self) -> bool:
        """Write the stop to every drive of the line in one unanswered frame; return if sent.

        Only where the line broadcasts, ``transport.broadcast_stops`` allows it, and
        every drive on it shares the same stop writes, so no drive gets another's
        meaning of a register.
        """
        transport = self.transport
        if not getattr(transport, 'broadcast_stops', False) or len(self.controllers) < 2:
            return False
        plans = {c.drive.stop_broadcast() if hasattr(c.drive, 'stop_broadcast') else ()
                 for c in self.controllers.values()}
        if len(plans) != 1 or not (plan := plans.pop()):
            return False
        try:
            for address, value in plan:
                transport.broadcast_register(address, value)
        except TransportError as exc:
            log.warning('bus %s: broadcast stop failed: %s', self.config.name, exc)
            return False
        return True

    def preempt_at(self) -> float | None:
        """Return the earliest moment a drive's command watchdog expires (see CycleLoop)."""
        moments = [m for c in self._serving() if (m := c.preempt_at()) is not None]
        return min(moments, default=None)

    def finish(self) -> None:
        # The drives this thread serves get their stop first: a connect beside the
        # cycle (dozens of SDO exchanges) must not hold it back. Then that connect is
        # waited for (it wrote its drive's stop first), and its drive finished too.
        # One still running after the wait stays noted, so a restarted loop does not
        # start a second connect of the same drive beside it.
        # A drive gone silent costs its timeouts, and the drives after it keep running
        # meanwhile: one broadcast frame reaches every drive at once (where they share
        # the stop writes), then a hurried pass (a reply must begin within what a
        # healthy drive takes), those that answered last first; a drive that did not
        # take its stop then is asked again with its whole timeout.
        serving = self._serving()
        if any(controller.runs for controller in serving):
            self._broadcast_stop()
        stopped = set()
        for controller in sorted(serving, key=lambda c: not c.link.answering):
            with controller.drive.transport.hurried():
                if controller.write_stop(quietly=True):
                    stopped.add(controller)
        for controller in serving:
            controller.finish(stop=controller not in stopped)
        beside = self._beside
        if beside is not None:
            beside[1].join(CONNECT_JOIN_TIMEOUT)
            beside[0].finish()
            self._serving()             # forgets it once its thread has ended
        for transport in self.transports:
            transport.close()

    def start(self) -> None:
        if self._loop is None:
            self._loop = self._stepping = CycleLoop(
                f'bus {self.config.name}', self.period, self.step, self.finish, self._clock,
                preempt=self.preempt, preempt_at=self.preempt_at,
                priority=int(self.config.settings.get('realtime_priority', 0)))
            for controller in self.controllers.values():
                controller.open_for_actions()
            self._loop.start()
            for controller in self.controllers.values():
                controller.loop_notes = self._loop.notes

    def shutdown(self, timeout: float | None = None) -> None:
        """Stop the loop; every drive is commanded to stop before the links close.

        Waits (by default) as long as those stops can take with every drive silent:
        a loop thread given up on dies with the process, and the drives it had not
        reached yet would keep running (re-check: 6 silent drives of 8 at 0.6 s,
        and the 2 that answered were never stopped in 3 s).
        """
        if self._loop is not None:
            self._loop.stop(timeout if timeout is not None else SHUTDOWN_WAIT + 2 * sum(
                c.drive.transport.failed_exchange_seconds() for c in self._all))
            self._loop = None

    def link_stats(self) -> TransportStats:
        """Return the counters of the whole link (every drive, and traffic no drive owns)."""
        all_stats = [t.stats for t in self.transports]
        return TransportStats(**{name: sum(getattr(s, name) for s in all_stats)
                                 for name in TransportStats.__dataclass_fields__})

    def statistics(self) -> BusStatistics:
        """Figures since the previous call (transactions/s, wire utilisation)."""
        stats = self.link_stats()
        now = self._clock()
        wire = self.transport.wire_seconds(stats.bytes_sent + stats.bytes_received,
                                           stats.frames_sent + stats.frames_received)
        loop = self._loop
        with self._lock:
            then, wire_before, before = self._window
            elapsed = max(now - then, 1e-6)
            rate = (stats.transactions - before) / elapsed
            utilisation = None if wire is None else (wire - wire_before) / elapsed
            self._window = (now, wire or 0.0, stats.transactions)
            cycle_rate, short = self._rate.sample(loop.cycles, self.period) if loop \
                else (0.0, False)
        return BusStatistics(
            transactions_per_second=rate, errors=stats.errors, timeouts=stats.timeouts,
            bad_frames=stats.bad_frames, utilisation=utilisation,
            overruns=loop.overruns if loop else 0,
            cycles_per_second=cycle_rate, rate_short=short)


def load_shared(values: Mapping[str, Any]) -> bool:
    """Return whether the bus's transport kind serves several drives on one instance."""
    return load_transport_class(str(values.get('transport.type', 'modbus_rtu'))).shared_by_drives
