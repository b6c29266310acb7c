"""Several drives on one link: one thread owns the port and serves every drive.

Each cycle writes every drive's command first, then polls every drive's
status, so a command never waits behind another drive's slow status read.
A drive that does not answer costs one short timeout per reconnect period
(its controller retries only every ``reconnect_period``), so it never stalls
the others; it alone goes offline.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass
from typing import Any, Callable, Mapping

import yaml

from .config import SETTINGS, build_controller
from .controller import CycleLoop, DriveController
from .errors import ParameterError
from .transports.base import Transport, TransportStats

#: settings that belong to the bus, not to one drive
BUS_KEYS = ('control_rate',)


@dataclass(frozen=True)
class BusStatistics:
    """Per-bus figures for /diagnostics."""

    transactions_per_second: float
    errors: int
    timeouts: int
    bad_frames: int
    utilisation: float | None   # fraction of the wire's capacity in use (RTU), None if unknown
    overruns: int


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
    if not isinstance(data, Mapping) or 'bus' not in data or 'drives' not in data:
        raise ParameterError('a bus file needs a "bus" mapping and a "drives" mapping')
    bus = dict(data['bus'])
    name = str(bus.pop('name', 'bus'))
    known = {s.name for s in SETTINGS}
    for key in bus:
        if not (key.startswith('transport.') or key in BUS_KEYS):
            raise ParameterError(f'bus setting {key!r}: only transport.* and {BUS_KEYS}')
    if not isinstance(data['drives'], Mapping) or not data['drives']:
        raise ParameterError('"drives" must map a name to each drive\'s settings')
    drives = []
    unit_ids = set()
    for key, entry in data['drives'].items():
        settings = dict(entry)
        namespace = str(settings.pop('namespace', f'/{key}'))
        node_name = str(settings.pop('name', 'drive'))
        for setting in settings:
            if setting.startswith('transport.') and setting != 'transport.unit_id':
                raise ParameterError(f'drive {key}: {setting} belongs to the bus')
            if not setting.startswith('transport.') and setting not in known:
                raise ParameterError(f'drive {key}: unknown setting {setting!r}')
        unit = settings.get('transport.unit_id', 1)
        if unit in unit_ids:
            raise ParameterError(f'drive {key}: unit id {unit} used twice on bus {name}')
        unit_ids.add(unit)
        drives.append(DriveEntry(str(key), namespace, node_name, settings))
    return BusConfig(name, bus, tuple(drives))


def load_bus_config(path: str) -> BusConfig:
    try:
        with open(path, encoding='utf-8') as stream:
            return parse_bus_config(yaml.safe_load(stream))
    except OSError as exc:
        raise ParameterError(f'cannot read bus file {path}: {exc}') from exc


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
        first = build_controller({**config.settings, **config.drives[0].settings})
        self.transport: Transport = first.drive.transport
        self.controllers[config.drives[0].key] = first
        shared = type(self.transport).shared_by_drives
        if shared:
            first.drive.owns_transport = False
        for entry in config.drives[1:]:
            self.controllers[entry.key] = build_controller(
                {**config.settings, **entry.settings},
                transport=self.transport if shared else None)
        self.transports = list({id(c.drive.transport): c.drive.transport
                                for c in self.controllers.values()}.values())
        for controller in self.controllers.values():
            # On one line, any drive's new command goes out before the next status read.
            controller.between_reads = self.write_pending_commands
        rate = float(config.settings.get('control_rate', 50.0))
        self.period = 1.0 / rate
        self.addressing_interval = self._addressing_interval()
        for controller in self.controllers.values():
            controller.plan_host_loss(self.addressing_interval)
        self._loop: CycleLoop | None = None
        self._lock = threading.Lock()
        self._window: tuple[float, float, int] = (clock(), 0.0, 0)
        self._connect_turn = 0

    def _addressing_interval(self) -> float:
        """Worst-case time between two requests to any drive of this bus.

        One cycle of every drive (or the control period, if longer), plus what a
        cycle may add: one connect or one failed exchange (a bus connects or
        retries at most one offline drive per cycle) and one service action.
        """
        controllers = list(self.controllers.values())
        drives = [c.drive for c in controllers]
        cycle = sum(drive.cycle_seconds() for drive in drives)
        extra = max(max(d.connect_seconds() for d in drives),
                    max(t.failed_exchange_seconds() for t in self.transports))
        return max(self.period, cycle) + extra + max(d.action_seconds() for d in drives)

    def step(self) -> None:
        controllers = list(self.controllers.values())
        due = [c for c in controllers if c.connect_due]
        chosen = due[self._connect_turn % len(due)] if due else None
        self._connect_turn += 1
        for controller in controllers:          # commands first, for every drive ...
            controller.command_phase(connect_allowed=controller is chosen)
        for controller in controllers:          # ... then the slower status polls
            controller.poll_phase()

    def write_pending_commands(self) -> None:
        for controller in self.controllers.values():
            controller.write_pending_command()

    def finish(self) -> None:
        for controller in self.controllers.values():
            controller.finish()
        for transport in self.transports:
            transport.close()

    def start(self) -> None:
        if self._loop is None:
            self._loop = CycleLoop(f'bus {self.config.name}', self.period, self.step,
                                   self.finish, self._clock, urgent=self.write_pending_commands)
            for controller in self.controllers.values():
                controller.wake = self._loop.wake
            self._loop.start()

    def shutdown(self, timeout: float = 3.0) -> None:
        if self._loop is not None:
            self._loop.stop(timeout)
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
        with self._lock:
            then, wire_before, before = self._window
            elapsed = max(now - then, 1e-6)
            rate = (stats.transactions - before) / elapsed
            utilisation = None if wire is None else (wire - wire_before) / elapsed
            self._window = (now, wire or 0.0, stats.transactions)
        return BusStatistics(
            transactions_per_second=rate, errors=stats.errors, timeouts=stats.timeouts,
            bad_frames=stats.bad_frames, utilisation=utilisation,
            overruns=self._loop.overruns if self._loop else 0)
