"""The benchmark's cases; each returns a plain dict (rows of the JSON file).

Times are ``time.monotonic()`` (CLOCK_MONOTONIC, shared by every process on
the machine), so the simulator's wire records and the driver's publish times
compare directly. The simulator always runs in its own process.
"""

from __future__ import annotations

import math
import os
import select
import statistics
import subprocess
import sys
import tempfile
import threading
import time
import tty
import uuid
from dataclasses import dataclass
from pathlib import Path
from types import SimpleNamespace
from typing import Any, Callable

import rclpy
import yaml
from pymodbus.framer.rtu import FramerRTU
from pymodbus.pdu import DecodePDU
from pymodbus.pdu.register_message import ReadHoldingRegistersRequest, WriteSingleRegisterRequest
from rclpy.context import Context
from rclpy.node import Node
from rclpy.parameter import Parameter
from std_msgs.msg import Float64

from vfd_ros2.control.bus import Bus, parse_bus_config
from vfd_ros2.control.controller import display_period
from vfd_ros2.control.factory import build_controller
from vfd_ros2.control.state import DriveState, RunState
from vfd_ros2.drives import modbus as modbus_drive
from vfd_ros2.msg import DriveStatus
from vfd_ros2.profiles import Profile, load_profile
from vfd_ros2.protocol.rtu_timing import character_time, frame_gap, reply_size, transaction_time
from vfd_ros2.ros.drive_node import DriveNode
from vfd_ros2.ros.executable import make_executor, spin_in_background
from vfd_ros2.ros.messages import StatusMessage
from vfd_ros2.transports.modbus import ModbusRtuTransport, PymodbusRtuTransport

from .simproc import SimProcess, wait_port

#: written to each drive's own comm-loss timeout: at 9600 baud four drives' cycle
#: exceeds the node's default 0.3 s, and the drive would (rightly) trip on it
DRIVE_COMM_TIMEOUT = 5.0

STACKS = {'vfd_ros2': ModbusRtuTransport, 'pymodbus': PymodbusRtuTransport}


def _percentile(values: list[float], fraction: float) -> float:
    ordered = sorted(values)
    if not ordered:
        return math.nan
    return ordered[min(len(ordered) - 1, math.ceil(fraction * len(ordered)) - 1)]


def _port_path(tag: str) -> str:
    base = Path(tempfile.gettempdir()) / 'vfd_ros2_bench'
    base.mkdir(parents=True, exist_ok=True)
    return str(base / f'{tag}-{uuid.uuid4().hex[:6]}')


def wait_for(condition: Callable[[], Any], timeout: float, what: str) -> Any:
    deadline = time.monotonic() + timeout
    while True:
        result = condition()
        if result:
            return result
        if time.monotonic() > deadline:
            raise RuntimeError(f'timed out after {timeout} s waiting for {what}')
        time.sleep(0.02)


# --- wire arithmetic ---------------------------------------------------------------


@dataclass(frozen=True)
class Framing:
    baudrate: int
    parity: str = 'N'
    stopbits: int = 1

    @property
    def name(self) -> str:
        return f'8{self.parity}{self.stopbits}'

    @property
    def char(self) -> float:
        return character_time(self.baudrate, self.parity, self.stopbits)

    @property
    def gap(self) -> float:
        return frame_gap(self.baudrate, self.char)

    def exchange_time(self, request: bytes, reply_bytes: int) -> float:
        return transaction_time(len(request), reply_bytes, self.char, self.gap)


def setpoint_request_bytes(profile: Profile) -> int:
    """Size of the setpoint write request: FC06, or FC16 for a 32-bit setpoint."""
    setpoint = profile.parameter(profile.velocity.setpoint)
    if setpoint.register_count == 1 and 6 in profile.modbus.function_codes:
        return 8
    return 9 + 2 * setpoint.register_count


def block_periods(drive: Any, between: int) -> list[tuple[Any, int]]:
    """Return each status read block of a Modbus drive and every how many cycles it is read.

    ``ModbusDrive.poll``: a block every N cycles (the profile's ``every``), and a
    block of values only shown in ``~/status`` at most once per ``between`` cycles.
    """
    return [(block, every * math.ceil(between / every) if shown_only else every)
            for block, every, shown_only in drive._schedule]  # noqa: SLF001 - the plan


def _cycles_between_shown_reads(cycle_seconds: float, status_period: float,
                                control_period: float) -> int:
    """Return the cycles of ``cycle_seconds`` until a shown-only block is due again.

    The controller has it read again once ``display_period`` has passed.
    """
    display = display_period(status_period, control_period)
    return max(1, math.ceil(display / cycle_seconds - 1e-9))


def static_cycle_time(profile: Profile, framing: Framing, units: int = 1,
                      status_period: float = 0.05, control_period: float = 0.0) -> float:
    """Wire time of a steady bus cycle of ``units`` drives from the profile alone.

    Per drive: the setpoint write (FC06, or FC16 for 32-bit setpoints) + the planned
    status reads, a block read every N cycles weighted 1/N (values only shown in
    ``~/status`` once per status: how many cycles that is depends on the cycle's own
    length, found by iterating); run commands are written only on change and do not
    count.
    """
    drive = build_controller({'drive.profile': profile.name, 'transport.port': '/dev/null'}).drive
    request = setpoint_request_bytes(profile)
    write = transaction_time(request, reply_size(6 if request == 8 else 16), framing.char,
                             framing.gap)
    reads = [(transaction_time(8, reply_size(3, block.count), framing.char, framing.gap))
             for block in drive.blocks]

    def cycle(between: int) -> float:
        periods = [period for _, period in block_periods(drive, between)]
        return units * (write + sum(t / p for t, p in zip(reads, periods)))
    total = cycle(1)
    for _ in range(5):
        total = cycle(_cycles_between_shown_reads(total, status_period, control_period))
    return total


# --- drive nodes in this process (a Bus: one thread owns the line) --------------------


class NodeBus:
    """N drive nodes on one link, exactly as bus_node builds them, spinning in a thread."""

    def __init__(self, profile: str, units: int, link: dict[str, Any], control_rate: float,
                 stack: str = 'vfd_ros2', frame_gap_s: float | None = None,
                 status_rate: float = 20.0) -> None:
        self.context = Context()
        rclpy.init(context=self.context)
        self.tag = f'b{uuid.uuid4().hex[:6]}'
        drives = {f'd{u}': {'namespace': f'/{self.tag}/d{u}', 'drive.profile': profile,
                            'transport.unit_id': u, 'gear_ratio': 10.0, 'auto_enable': True,
                            'status_rate': status_rate, 'diagnostics_rate': 1.0,
                            'command_timeout': 0.5, 'drive_comm_timeout': DRIVE_COMM_TIMEOUT}
                  for u in range(1, units + 1)}
        config = parse_bus_config({'bus': {'name': self.tag, **link,
                                           'control_rate': control_rate}, 'drives': drives})
        self.bus = Bus(config)
        if link.get('transport.type', 'modbus_rtu') == 'modbus_rtu' and \
                (stack != 'vfd_ros2' or frame_gap_s is not None):
            self._swap_transport(stack, frame_gap_s)
        self.nodes = []
        for entry in config.drives:
            values = {**config.settings, **entry.settings}
            self.nodes.append(DriveNode(
                entry.name, controller=self.bus.controllers[entry.key],
                namespace=entry.namespace, context=self.context, use_global_arguments=False,
                parameter_overrides=[Parameter(k, value=v) for k, v in values.items()]))
        self.tester = Node('bench_tester', namespace=f'/{self.tag}', context=self.context)
        self.publishers = [self.tester.create_publisher(Float64, f'd{u}/drive/velocity_command',
                                                        10) for u in range(1, units + 1)]
        self.executor = make_executor(self.context)
        for node in [*self.nodes, self.tester]:
            self.executor.add_node(node)
        self._spin = spin_in_background(self.executor, self.context)
        self.bus.start()

    def _swap_transport(self, stack: str, frame_gap_s: float | None) -> None:
        old = self.bus.transport
        kwargs = dict(port=old.port, baudrate=old.baudrate, parity=old.parity,
                      stopbits=old.stopbits, bytesize=old.bytesize, timeout=old.timeout)
        if stack == 'vfd_ros2':
            new = ModbusRtuTransport(**kwargs, frame_gap=frame_gap_s)
        else:
            new = PymodbusRtuTransport(**kwargs)
        self.bus.transport = new
        for controller in self.bus.controllers.values():
            controller.drive.transport = new

    @property
    def controllers(self) -> list[Any]:
        return list(self.bus.controllers.values())

    def cycles(self) -> int:
        return min(c._cycle for c in self.controllers)   # noqa: SLF001

    def publish_all(self, velocity: float) -> None:
        for publisher in self.publishers:
            publisher.publish(Float64(data=velocity))

    def wait_online(self, timeout: float = 30.0) -> None:
        def ready() -> bool:
            self.publish_all(1.0)
            return all(c.state.online and c.state.state == 'running' for c in self.controllers)
        wait_for(ready, timeout, 'drives online and running')

    def close(self) -> None:
        self.bus.shutdown()
        self._spin.stop()
        self.executor.shutdown(timeout_sec=1.0)
        for node in [*self.nodes, self.tester]:
            node.destroy_node()
        rclpy.try_shutdown(context=self.context)


class Streamer:
    """Publishes velocity commands to every drive at ``rate`` Hz (a planner)."""

    def __init__(self, bus: NodeBus, rate: float, velocity: float = 1.0) -> None:
        self._bus, self._period, self.velocity = bus, 1.0 / rate, velocity
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        next_time = time.monotonic()
        while not self._stop.is_set():
            self._bus.publish_all(self.velocity)
            next_time += self._period
            self._stop.wait(max(0.0, next_time - time.monotonic()))

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(1.0)


# --- 1. bus efficiency ----------------------------------------------------------------


def bus_efficiency(profile_name: str, units: int, framing: Framing, window: float,
                   stack: str = 'vfd_ros2', adapter_latency: float = 0.0) -> dict[str, Any]:
    """Back-to-back command+status cycles on an emulated line vs the wire's limit.

    ``adapter_latency`` emulates the master's USB adapter holding each reply that
    long (an FTDI latency timer: 16 ms by default, 1 ms in low-latency mode).
    """
    profile = load_profile(profile_name)
    setpoint = profile.parameter(profile.velocity.setpoint).address
    port = _port_path('eff')
    with SimProcess('rtu', profile_name, list(range(1, units + 1)), port, framing.baudrate,
                    framing.parity, framing.stopbits, emulate=True,
                    adapter_latency=adapter_latency) as sim:
        wait_port(port)
        link = {'transport.type': 'modbus_rtu', 'transport.port': port,
                'transport.baudrate': framing.baudrate, 'transport.parity': framing.parity,
                'transport.stopbits': framing.stopbits, 'transport.timeout': 0.5}
        bus = NodeBus(profile_name, units, link, control_rate=10000.0, stack=stack)
        streamer = Streamer(bus, 50.0)
        try:
            bus.wait_online()
            time.sleep(min(1.0, window / 4))
            start = time.monotonic()
            time.sleep(window)
            records = sim.ask('exchanges', start)
            stats = sim.ask('stats')
        finally:
            streamer.stop()
            bus.close()
    static = 1.0 / static_cycle_time(profile, framing, units)
    return {
        'profile': profile_name, 'drives': units, 'baudrate': framing.baudrate,
        'framing': framing.name, 'stack': stack,
        **wire_ratio(records, setpoint, framing),
        'static_theoretical_cycles_per_s': round(static, 3),
        'target': 0.95 if framing.baudrate <= 19200 else 0.90 if framing.baudrate == 115200
        else None,
        'gap_violations': stats['gap_violations'], 'line_errors': stats['crc_errors'],
        'adapter_latency_ms': round(1000 * adapter_latency, 1),
        **sim_timing(stats),
    }


def sim_timing(stats: dict[str, Any]) -> dict[str, Any]:
    """Return how late the simulator itself handed over replies (its share of a turnaround)."""
    timed = stats.get('timed_replies', 0)
    return {'sim_realtime': stats.get('realtime', False),
            'sim_reply_late_us_mean': round(1e6 * stats['reply_lateness_total'] / timed, 1)
            if timed else None,
            'sim_reply_late_us_max': round(1e6 * stats['reply_lateness_max'], 1)}


def wire_ratio(records: list[Any], setpoint: int, framing: Framing) -> dict[str, Any]:
    """Return the fraction of the wire's limit whole bus cycles reached.

    Cycles run from one setpoint write of drive 1 to a later one in the
    simulator's records; the wire time is what their exchanges need.
    """
    marks = [i for i, (_, _, request, _) in enumerate(records)
             if request[0] == 1 and request[1] in (6, 16)
             and int.from_bytes(request[2:4], 'big') == setpoint]
    if len(marks) < 3:
        raise RuntimeError(f'only {len(marks)} cycles in the window: lengthen it')
    first, last = marks[0], marks[-1]
    cycles = len(marks) - 1
    span = records[last][0] - records[first][0]
    wire = sum(framing.exchange_time(request, reply)
               for _, _, request, reply in records[first:last])
    return {'cycles': cycles, 'seconds': round(span, 3),
            'transactions_per_cycle': round((last - first) / cycles, 2),
            'cycles_per_s': round(cycles / span, 3),
            'theoretical_cycles_per_s': round(cycles / wire, 3),
            'ratio': round(wire / span, 4)}


# --- watchdog on a bus -------------------------------------------------------------------


def watchdog_on_bus(profile_name: str, units: int, framing: Framing, trials: int,
                    command_timeout: float = 0.5) -> dict[str, Any]:
    """Measure when each drive receives its zero setpoint after commands stop (a Bus).

    The target is the timeout plus one transaction: a tripped watchdog preempts
    the bus cycle like a new command (it does not wait for the drive's turn).
    """
    profile = load_profile(profile_name)
    setpoint = profile.parameter(profile.velocity.setpoint).address
    port = _port_path('wdg')
    delays: list[float] = []
    with SimProcess('rtu', profile_name, list(range(1, units + 1)), port, framing.baudrate,
                    framing.parity, framing.stopbits, emulate=True) as sim:
        wait_port(port)
        bus = Bus(parse_bus_config({
            'bus': {'transport.type': 'modbus_rtu', 'transport.port': port,
                    'transport.baudrate': framing.baudrate, 'transport.parity': framing.parity,
                    'transport.stopbits': framing.stopbits},
            'drives': {f'd{u}': {'drive.profile': profile_name, 'transport.unit_id': u,
                                 'auto_enable': True, 'command_timeout': command_timeout,
                                 'drive_comm_timeout': DRIVE_COMM_TIMEOUT}
                       for u in range(1, units + 1)}}))
        controllers = list(bus.controllers.values())
        bus.start()
        try:
            for trial in range(trials):
                velocity = 1.0 + 0.1 * trial
                wait_for(lambda v=velocity: [c.command_velocity(v) for c in controllers] and
                         all(c.state.running and c.state.commanded_velocity == v
                             for c in controllers), 30.0, 'all drives running')
                time.sleep(0.3)               # a steady state, commands still streaming
                for c in controllers:
                    c.command_velocity(velocity)
                last = time.monotonic()
                time.sleep(command_timeout + 1.5)
                zero: dict[int, float] = {}
                for stamp, frame in sim.ask('received', last):
                    if frame[1] == 6 and int.from_bytes(frame[2:4], 'big') == setpoint and \
                            frame[4:6] == b'\0\0':
                        # A broadcast (unit 0) reaches every drive at once.
                        for unit in (range(1, units + 1) if frame[0] == 0 else (frame[0],)):
                            zero.setdefault(unit, stamp)
                delays += [zero[u] - last for u in sorted(zero)]
        finally:
            bus.shutdown()
    transaction = framing.exchange_time(bytes(8), 8)
    longest = framing.exchange_time(bytes(8), reply_size(3, profile.modbus.max_read_registers))
    return {'profile': profile_name, 'drives': units, 'baudrate': framing.baudrate,
            'trials': trials, 'command_timeout_s': command_timeout,
            'stops_seen': len(delays), 'median_s': round(statistics.median(delays), 4),
            'max_s': round(max(delays), 4),
            # the write itself, after the longest exchange that may be on the wire
            'target_s': round(command_timeout + longest + transaction, 4)}


# --- 2. software floor ------------------------------------------------------------------


def software_floor(profile_name: str, cycles: int, stack: str,
                   profiler: Any = None) -> dict[str, Any]:
    """Measure the drive layer on a pty with no wire time: transactions/s and us each."""
    port = _port_path('floor')
    profile = load_profile(profile_name)
    serial = profile.modbus.serial
    with SimProcess('rtu', profile_name, [1], port, serial.baudrate, serial.parity,
                    serial.stopbits, emulate=False):
        wait_port(port)
        kwargs = dict(baudrate=serial.baudrate, parity=serial.parity, stopbits=serial.stopbits,
                      bytesize=serial.bytesize, timeout=0.5)
        transport = ModbusRtuTransport(port, frame_gap=0.0, **kwargs) if stack == 'vfd_ros2' \
            else PymodbusRtuTransport(port, **kwargs)
        controller = build_controller({'drive.profile': profile_name, 'transport.port': port},
                                      transport=transport)
        drive = controller.drive
        transport.open()
        try:
            drive.apply(0.0, run=False)
            for cycle in range(20):          # warm-up
                drive.apply(0.1 * (cycle % 3), run=False)
                drive.poll(cycle)
            before = transport.stats.transactions
            cpu0, start = time.process_time(), time.perf_counter()
            if profiler is not None:
                profiler.enable()
            for cycle in range(cycles):
                drive.apply(0.1 * (cycle % 3), run=False)
                drive.poll(cycle)
            if profiler is not None:
                profiler.disable()
            elapsed, cpu = time.perf_counter() - start, time.process_time() - cpu0
            done = transport.stats.transactions - before
            errors = transport.stats.errors
        finally:
            transport.close()
    return {'profile': profile_name, 'stack': stack, 'level': 'drive (apply+poll)',
            'cycles': cycles, 'transactions': done, 'errors': errors,
            'transactions_per_s': round(done / elapsed, 1),
            'us_per_transaction': round(1e6 * elapsed / done, 1),
            'cpu_us_per_transaction': round(1e6 * cpu / done, 1)}


def software_floor_node(profile_name: str, window: float, stack: str) -> dict[str, Any]:
    """Measure the same through the drive node (ROS spinning), back-to-back cycles."""
    port = _port_path('floornode')
    profile = load_profile(profile_name)
    serial = profile.modbus.serial
    with SimProcess('rtu', profile_name, [1], port, serial.baudrate, serial.parity,
                    serial.stopbits, emulate=False):
        wait_port(port)
        link = {'transport.type': 'modbus_rtu', 'transport.port': port,
                'transport.timeout': 0.5}
        bus = NodeBus(profile_name, 1, link, control_rate=10000.0, stack=stack,
                      frame_gap_s=0.0 if stack == 'vfd_ros2' else None)
        streamer = Streamer(bus, 50.0)
        try:
            bus.wait_online()
            stats = bus.bus.transport.stats
            before, start = stats.transactions, time.monotonic()
            time.sleep(window)
            done, elapsed = stats.transactions - before, time.monotonic() - start
        finally:
            streamer.stop()
            bus.close()
    return {'profile': profile_name, 'stack': stack, 'level': 'drive node (ROS spinning)',
            'transactions': done, 'errors': stats.errors,
            'transactions_per_s': round(done / elapsed, 1),
            'us_per_transaction': round(1e6 * elapsed / done, 1),
            'cpu_us_per_transaction': None}


# --- 3. command latency ------------------------------------------------------------------


def command_latency(profile_name: str, commands: int, kind: str,
                    framing: Framing | None = None, rate: float | None = None
                    ) -> dict[str, Any]:
    """Publish ~/velocity_command -> last byte of the setpoint write at the simulator."""
    profile = load_profile(profile_name)
    setpoint = profile.parameter(profile.velocity.setpoint)
    # The driver's scaling and status reads, rebuilt here from the same settings.
    reference = build_controller({'drive.profile': profile_name, 'gear_ratio': 10.0,
                                  'transport.port': '/dev/null'})
    if kind == 'rtu' and framing is not None:
        cycle_rate = 1.0 / static_cycle_time(profile, framing)
        rate = rate or float(math.floor(0.9 * cycle_rate))
        port = _port_path('lat')
        sim = SimProcess('rtu', profile_name, [1], port, framing.baudrate, framing.parity,
                         framing.stopbits, emulate=True)
    else:
        rate = rate or 100.0
        sim = SimProcess('tcp', profile_name, [1])
    with sim:
        if kind == 'rtu':
            wait_port(port)
            link = {'transport.type': 'modbus_rtu', 'transport.port': port,
                    'transport.baudrate': framing.baudrate, 'transport.parity': framing.parity,
                    'transport.stopbits': framing.stopbits, 'transport.timeout': 0.5}
        else:
            link = {'transport.type': 'modbus_tcp', 'transport.host': '127.0.0.1',
                    'transport.port': sim.where, 'transport.timeout': 0.5}
        # The driver has a process of its own, as on a robot (the planner that publishes
        # is another process): the bench's publishing loop does not share its GIL.
        tag = f'lat{uuid.uuid4().hex[:6]}'
        driver = bus_node_process(_bus_document(tag, profile_name, 1, link, rate), 1, tag)
        try:
            # Its planner timer feeds the start-up; from here on this process never
            # spins, so the timer is silent and only the commands below are published.
            driver.wait_all_running(30.0)
            # Distinct raw setpoints: each command is recognisable on the wire.
            velocities, raws = [], []
            for step in range(2000):
                velocity = 0.5 + 0.013 * step
                raw = reference.drive._native_setpoint(velocity)[0]     # noqa: SLF001
                if (not raws or raw != raws[-1]) and velocity < reference.config.max_velocity:
                    velocities.append(velocity)
                    raws.append(raw)
            period = 1.0 / rate
            sent: list[tuple[float, int]] = []
            start = next_time = time.monotonic()
            for index in range(commands):
                velocity = velocities[index % len(velocities)]
                now = time.monotonic()
                driver.publishers[0].publish(Float64(data=velocity))
                sent.append((now, raws[index % len(raws)]))
                next_time += period
                time.sleep(max(0.0, next_time - time.monotonic()))
            time.sleep(0.3)
            frames = sim.ask('received', start - 1.0)
        finally:
            driver.close()
    writes = []
    for stamp, frame in frames:
        pdu = frame[7:] if kind == 'tcp' else frame[1:-2]
        if pdu[0] == 6 and int.from_bytes(pdu[1:3], 'big') == setpoint.address:
            writes.append((stamp, int.from_bytes(pdu[3:5], 'big', signed=True)))
        elif pdu[0] == 16 and int.from_bytes(pdu[1:3], 'big') == setpoint.address:
            writes.append((stamp, int.from_bytes(pdu[6:8], 'big', signed=True)))
    latencies, superseded = [], 0
    cursor = 0
    for published, raw in sent:
        while cursor < len(writes) and writes[cursor][0] < published:
            cursor += 1
        # The first write of this command's value after it was published (within 1 s):
        # a command replaced by the next one before any cycle picked it up has none.
        hit = next((stamp for stamp, value in writes[cursor:]
                    if value == raw and stamp < published + 1.0), None)
        if hit is None:
            superseded += 1
        else:
            latencies.append(hit - published)
    wire = framing.exchange_time(bytes(8), 8) if framing else None
    bound = None
    if framing:
        # The worst case the wire allows: the command arrives as the longest status read
        # starts (that transaction, with its two t3.5, runs to its end), then the setpoint
        # request goes out; the time ends at the request's last byte.
        longest = max(transaction_time(8, reply_size(3, b.count), framing.char, framing.gap)
                      for b in reference.drive.blocks)
        bound = longest + setpoint_request_bytes(profile) * framing.char
    ms = [1e3 * x for x in latencies]
    return {
        'transport': kind, 'profile': profile_name,
        'baudrate': framing.baudrate if framing else None,
        'command_rate_hz': rate, 'commands': commands, 'matched': len(ms),
        'superseded': superseded,
        'median_ms': round(statistics.median(ms), 3) if ms else None,
        'p99_ms': round(_percentile(ms, 0.99), 3) if ms else None,
        'max_ms': round(max(ms), 3) if ms else None,
        'write_transaction_ms': round(1e3 * wire, 3) if wire else None,
        'wire_bound_ms': round(1e3 * bound, 3) if bound else None,
        'target_p99_ms': round(1e3 * bound + 1.0, 3) if bound else None,
    }


# --- 5. CPU and memory -------------------------------------------------------------------


def _proc_cpu_seconds(pid: int) -> float:
    fields = Path(f'/proc/{pid}/stat').read_text().rsplit(')', 1)[1].split()
    ticks = os.sysconf('SC_CLK_TCK')
    return (int(fields[11]) + int(fields[12])) / ticks


def _proc_rss_mb(pid: int) -> float:
    for line in Path(f'/proc/{pid}/status').read_text().splitlines():
        if line.startswith('VmRSS:'):
            return int(line.split()[1]) / 1024.0
    return math.nan


def _thread_name(comm: str) -> str:
    """Group a thread by its name: Fast DDS's by name, 'control loop', other 'python'."""
    return 'python' if comm.startswith('python') else 'control loop' \
        if comm.startswith('vfd ') else comm.rstrip('0123456789.')


def _thread_usage(pid: int) -> dict[str, tuple[float, int]]:
    """Return CPU seconds and context switches (its wake-ups) per thread group of ``pid``.

    A thread that blocks and is woken again switches out once per wake-up (voluntary);
    one the scheduler takes the CPU from counts too (involuntary): together, how often
    the thread started running again, each time with caches another thread has used.
    """
    ticks = os.sysconf('SC_CLK_TCK')
    result: dict[str, tuple[float, int]] = {}
    for task in Path(f'/proc/{pid}/task').iterdir():
        try:
            head, tail = (task / 'stat').read_text().rsplit(')', 1)
            switches = _context_switches(task / 'status')
        except OSError:
            continue
        fields = tail.split()
        name = _thread_name(head.split('(', 1)[1])
        cpu, wakes = result.get(name, (0.0, 0))
        result[name] = (cpu + (int(fields[11]) + int(fields[12])) / ticks, wakes + switches)
    return result


def _context_switches(status: Path) -> int:
    """Voluntary + involuntary context switches from a /proc .../status file."""
    return sum(int(line.split()[1]) for line in status.read_text().splitlines()
               if line.partition(':')[0].endswith('ctxt_switches'))


class DriverProcess:
    """The driver in a process of its own (as a robot runs it), fed and watched over ROS.

    ``module``: the executable's module (its ``main`` runs), with ``ros_arguments``;
    ``files`` are YAML documents written first, by name, into its working directory,
    which the arguments name as ``{dir}``. A tester node in this process has a velocity
    command publisher per drive (``publishers``; with ``command_rate`` a timer publishes
    1.0 rad/s on all of them, a planner) and keeps the last ``~/status`` of each drive.
    """

    def __init__(self, module: str, ros_arguments: list[str], units: int, tag: str,
                 command_rate: float | None = 50.0, executor: str = 'events',
                 files: dict[str, Any] | None = None) -> None:
        self._tmp = tempfile.TemporaryDirectory()
        self._log = open(Path(self._tmp.name) / 'driver.log', 'w+b')  # noqa: SIM115
        for name, document in (files or {}).items():
            (Path(self._tmp.name) / name).write_text(yaml.safe_dump(document))
        env = dict(os.environ, VFD_ROS2_EXECUTOR=executor)
        env['PYTHONPATH'] = os.pathsep.join(
            p for p in (env.get('PYTHONPATH', ''), str(Path(__file__).resolve().parent.parent))
            if p)
        self.launched = time.monotonic()
        self.child = subprocess.Popen(
            [sys.executable, '-c', f'import sys; from {module} import main; sys.exit(main())',
             '--ros-args', *(a.replace('{dir}', self._tmp.name) for a in ros_arguments),
             '--log-level', 'warn'],
            stdout=subprocess.DEVNULL, stderr=self._log, env=env, cwd=self._tmp.name)
        self.units = units
        self.all_online_s: float | None = None
        self.context = Context()
        rclpy.init(context=self.context)
        self.node = Node('bench_driver', namespace=f'/{tag}', context=self.context)
        self.publishers = [self.node.create_publisher(Float64, f'd{u}/drive/velocity_command', 10)
                           for u in range(1, units + 1)]
        self.last: dict[int, DriveStatus] = {}
        for u in range(1, units + 1):
            self.node.create_subscription(DriveStatus, f'd{u}/drive/status',
                                          lambda msg, u=u: self.last.__setitem__(u, msg), 10)
        if command_rate:
            self.node.create_timer(1.0 / command_rate, lambda: [
                p.publish(Float64(data=1.0)) for p in self.publishers])
        self.executor = make_executor(self.context)
        self.executor.add_node(self.node)

    def spin_for(self, seconds: float) -> None:
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            self.executor.spin_once(timeout_sec=0.02)

    def wait_all_running(self, timeout: float) -> float:
        """Return the seconds from launch until every drive reports online and running.

        ``all_online_s`` keeps when the last drive was first seen online (before its
        ramp).
        """
        deadline = time.monotonic() + timeout
        first_online: dict[int, float] = {}
        while True:
            now = time.monotonic() - self.launched
            for unit, status in self.last.items():
                if status.online:
                    first_online.setdefault(unit, now)
            if len(first_online) == self.units:
                self.all_online_s = max(first_online.values())
            if len(self.last) == self.units and all(s.online and s.running
                                                    for s in self.last.values()):
                return now
            if time.monotonic() > deadline or self.child.poll() is not None:
                self._log.seek(0)
                states = {u: (s.online, s.state) for u, s in self.last.items()}
                raise RuntimeError(f'the driver did not bring the drives online: {states} '
                                   + self._log.read().decode(errors='replace')[-800:])
            self.spin_for(0.05)

    def transaction_counts(self) -> dict[int, tuple[int, float]]:
        """Return each drive's transaction count and the stamp of the status that carried it.

        Each drive's status carries its own counters (Transport.stats_for): the
        line's rate is the sum of theirs, each over its own stamps, so a slow
        ``status_rate`` does not blur it.
        """
        return {unit: (s.transactions, s.header.stamp.sec + 1e-9 * s.header.stamp.nanosec)
                for unit, s in self.last.items()}

    @staticmethod
    def transaction_rate(before: dict[int, tuple[int, float]],
                         after: dict[int, tuple[int, float]]) -> float:
        """Transactions per second on the line between two ``transaction_counts``."""
        return sum((count - before[unit][0]) / (stamp - before[unit][1])
                   for unit, (count, stamp) in after.items()
                   if unit in before and stamp > before[unit][1])

    def close(self) -> None:
        self.child.terminate()
        try:
            self.child.wait(10.0)
        except subprocess.TimeoutExpired:
            self.child.kill()
        self.executor.shutdown(timeout_sec=1.0)
        self.node.destroy_node()
        rclpy.try_shutdown(context=self.context)
        self._log.close()
        self._tmp.cleanup()


def bus_node_process(document: dict[str, Any], units: int, tag: str,
                     command_rate: float | None = 50.0,
                     executor: str = 'events') -> DriverProcess:
    """bus_node in its own process with ``document`` as its bus file."""
    return DriverProcess('vfd_ros2.ros.bus_node', ['-p', 'config_file:={dir}/bus.yaml'], units,
                         tag, command_rate, executor, files={'bus.yaml': document})


def drive_node_process(document: dict[str, Any], tag: str, command_rate: float | None = 50.0,
                       executor: str = 'events') -> DriverProcess:
    """Run the first drive of a bus ``document`` as a drive_node in its own process.

    Its settings and the bus's link and control rate become the node's parameters;
    it takes the name the bus would give it (``/<tag>/d1/drive``).
    """
    config = parse_bus_config(document)
    drive = config.drives[0]
    settings = {**config.settings, **drive.settings}
    return DriverProcess('vfd_ros2.ros.drive_node',
                         ['-r', f'__ns:={drive.namespace}', '-r', f'__node:={drive.name}',
                          '--params-file', '{dir}/params.yaml'], 1, tag, command_rate,
                         executor=executor,
                         files={'params.yaml': {'/**': {'ros__parameters': settings}}})


def _bus_document(tag: str, profile_name: str, units: int, link: dict[str, Any],
                  control_rate: float) -> dict[str, Any]:
    drives = {f'd{u}': {'namespace': f'/{tag}/d{u}', 'drive.profile': profile_name,
                        'transport.unit_id': u, 'gear_ratio': 10.0, 'auto_enable': True,
                        'status_rate': 20.0, 'drive_comm_timeout': DRIVE_COMM_TIMEOUT}
              for u in range(1, units + 1)}
    return {'bus': {'name': tag, **link, 'control_rate': control_rate}, 'drives': drives}


def _cpu_window(bus: DriverProcess, window: float,
                profile_with_pyspy: bool = False) -> dict[str, Any]:
    """CPU %, per thread, RSS and transactions/s of the bus_node process over ``window``."""
    tx0 = bus.transaction_counts()
    threads0 = _thread_usage(bus.child.pid)
    cpu0, start = _proc_cpu_seconds(bus.child.pid), time.monotonic()
    spy = _start_pyspy(bus.child.pid, window) if profile_with_pyspy else None
    bus.spin_for(window)
    cpu1, end = _proc_cpu_seconds(bus.child.pid), time.monotonic()
    threads1 = _thread_usage(bus.child.pid)
    elapsed = end - start
    used = {}
    for name, (cpu, wakes) in sorted(threads1.items()):
        cpu0_thread, wakes0_thread = threads0.get(name, (0.0, 0))
        used[name] = (cpu - cpu0_thread, wakes - wakes0_thread)
    result: dict[str, Any] = {
        'cpu_percent': round(100.0 * (cpu1 - cpu0) / elapsed, 2),
        'cpu_percent_by_thread': {name: round(100.0 * cpu / elapsed, 2)
                                  for name, (cpu, _) in used.items() if cpu > 0},
        'wakeups_per_s_by_thread': {name: round(wakes / elapsed)
                                    for name, (_, wakes) in used.items() if wakes > 0},
        'transactions_per_s': round(bus.transaction_rate(tx0, bus.transaction_counts()), 1),
        'comm_errors': sum(s.comm_errors for s in bus.last.values()),
        'rss_mb': round(_proc_rss_mb(bus.child.pid), 1),
    }
    if spy is not None:
        result['pyspy_top'] = _finish_pyspy(spy)
    return result


def _transactions_per_cycle(drive: Any, cycle_period: float, status_period: float) -> float:
    """Return the transactions one cycle of a Modbus drive makes, on average."""
    between = _cycles_between_shown_reads(cycle_period, status_period, cycle_period)
    return 1.0 + sum(1.0 / period for _, period in block_periods(drive, between))


def cpu_usage(profile_name: str, units: int, window: float, control_rate: float = 50.0,
              profile_with_pyspy: bool = False, executor: str = 'events',
              node: str = 'bus_node', status_rate: float = 20.0,
              command_rate: float = 50.0) -> dict[str, Any]:
    """Measure the driver in its own process at 50 Hz with status publishing: CPU %, RSS.

    ``executor``: ``events`` (what ships) or ``single`` (the previous design's
    SingleThreadedExecutor, for the side-by-side figure). ``node``: ``bus_node``
    (the drives of one line in one node) or ``drive_node`` (one drive, ``units`` 1).
    ``status_rate`` (each drive's) and ``command_rate`` (a planner's, per drive) set
    the ROS traffic around the same control cycle: rows that lower one of them show
    what it costs. Below 4 Hz of commands ``command_timeout`` is raised to three
    command periods, so the drives keep running.
    """
    port = _port_path('cpu')
    tag = f'c{uuid.uuid4().hex[:6]}'
    # No wire time and no t3.5 wait: this case measures the driver's CPU at the control
    # rate (four AM drives cannot reach 50 Hz on one real 115200-baud line: section 1).
    link = {'transport.type': 'modbus_rtu', 'transport.port': port, 'transport.timeout': 0.1,
            'transport.frame_gap': 0.0}
    result: dict[str, Any] = {'profile': profile_name, 'drives': units, 'executor': executor,
                              'node': node, 'control_rate_hz': control_rate,
                              'status_rate_hz': status_rate, 'command_rate_hz': command_rate}
    document = _bus_document(tag, profile_name, units, link, control_rate)
    for drive_settings in document['drives'].values():
        drive_settings['status_rate'] = status_rate
        if command_rate < 4.0:
            drive_settings['command_timeout'] = 3.0 / command_rate
    with SimProcess('rtu', profile_name, list(range(1, units + 1)), port, emulate=False):
        wait_port(port)
        if node == 'drive_node':
            if units != 1:
                raise ValueError('a drive_node drives one drive')
            bus = drive_node_process(document, tag, command_rate, executor=executor)
        else:
            bus = bus_node_process(document, units, tag, command_rate, executor=executor)
        try:
            bus.wait_all_running(30.0)
            bus.spin_for(1.0)
            result.update(_cpu_window(bus, window, profile_with_pyspy))
        finally:
            bus.close()
    drive = build_controller({'drive.profile': profile_name,
                              'transport.port': '/dev/null'}).drive
    per_cycle = _transactions_per_cycle(drive, 1.0 / control_rate, 1.0 / status_rate)
    result.update({
        'cpu_percent_per_drive': round(result['cpu_percent'] / units, 2),
        'approx_cycles_per_s': round(result['transactions_per_s'] / units / per_cycle, 1),
        'target_percent_per_drive': 3.0 if units > 1 else 5.0,
    })
    return result


#: a process that subscribes to the DriveStatus topic named by its argument until killed
_STATUS_SUBSCRIBER = """
import sys
import rclpy
from rclpy.node import Node
from vfd_ros2.msg import DriveStatus
rclpy.init()
node = Node('bench_status_subscriber')
node.create_subscription(DriveStatus, sys.argv[1], lambda message: None, 10)
try:
    rclpy.spin(node)
except BaseException:
    pass
"""


def wake_cost(samples: int = 40, pause: float = 0.05) -> dict[str, Any]:
    """CPU of updating and publishing the first ``DriveStatus`` after a sleep, and the next.

    A node does its work in short bursts between sleeps (20 ms for a 50 Hz cycle,
    50 ms between status publishes); on a shared VM the caches are cold by then.
    Each sample sleeps ``pause``, then times (this thread's CPU) updating (the kept
    message of ``StatusMessage``, as a node does: the speed and counters moved) and
    publishing one message, then nine more back to back: medians of ``samples``.
    The topic has one subscriber, in a process of its own, as a robot's status has.
    """
    name = f'bench_wake_{uuid.uuid4().hex[:6]}'
    subscriber = subprocess.Popen(
        [sys.executable, '-c', _STATUS_SUBSCRIBER, f'/{name}/status'],
        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
        cwd=tempfile.gettempdir())      # not a source tree: vfd_ros2.msg is installed
    context = Context()
    rclpy.init(context=context)
    node = Node(name, context=context)
    try:
        publisher = node.create_publisher(DriveStatus, '~/status', 10)
        deadline = time.monotonic() + 20.0
        while publisher.get_subscription_count() < 1:
            if time.monotonic() > deadline or subscriber.poll() is not None:
                raise RuntimeError('the status subscriber process did not come up')
            time.sleep(0.1)
        # as a node's kept message sees them: each poll moves the speed and the counters
        polls = iter([DriveState(hardware_id='boneng_am@/dev/ttyUSB0#1', online=True,
                                 transactions=index, measured_velocity=0.001 * index)
                      for index in range(10 * samples)])
        kept = StatusMessage('frame', 'profile')
        stamp = node.get_clock().now().to_msg()
        figures: dict[str, list[float]] = {key: [] for key in (
            'message_first_us', 'message_following_us', 'publish_first_us',
            'publish_following_us')}
        clock = time.thread_time_ns
        for _ in range(samples):
            time.sleep(pause)
            t0 = clock()
            message = kept.update(next(polls), stamp)
            t1 = clock()
            publisher.publish(message)
            t2 = clock()
            for _ in range(9):
                kept.update(next(polls), stamp)
            t3 = clock()
            for _ in range(9):
                publisher.publish(message)
            t4 = clock()
            for key, nanoseconds in (('message_first_us', t1 - t0), ('publish_first_us', t2 - t1),
                                     ('message_following_us', (t3 - t2) / 9),
                                     ('publish_following_us', (t4 - t3) / 9)):
                figures[key].append(nanoseconds / 1e3)
    finally:
        subscriber.terminate()
        try:
            subscriber.wait(10.0)
        except subprocess.TimeoutExpired:
            subscriber.kill()
        node.destroy_node()
        rclpy.try_shutdown(context=context)
    return {'kind': 'wake_cost', 'samples': samples, 'pause_ms': 1e3 * pause,
            **{key: round(statistics.median(values), 1) for key, values in figures.items()}}


def io_floor(profile_name: str, units: int, window: float,
             control_rate: float = 50.0, status_rate: float = 20.0) -> dict[str, Any]:
    """Measure the I/O of ``cpu_usage`` without the driver: the floor of any driver.

    The same request frames (each drive's setpoint write and the status reads due
    that cycle, from the profile's read plan, built by pymodbus) go to the same
    simulator, each reply is read by its known length with ``select``/``read`` and
    not decoded, and the cycles are paced at ``control_rate`` as the control loop
    paces them. What this thread costs is the pty's system calls and the scheduler's
    wake-ups at that pace; the rest of ``cpu_usage``'s figure is the driver's logic
    and ROS.
    """
    port = _port_path('iofloor')
    drive = build_controller({'drive.profile': profile_name,
                              'transport.port': '/dev/null'}).drive
    framer = FramerRTU(DecodePDU(False))
    setpoint = drive.profile.parameter(drive.profile.velocity.setpoint).address
    cycles: list[list[tuple[bytes, int]]] = []     # per cycle index: (frame, reply bytes)
    plan = block_periods(drive, _cycles_between_shown_reads(
        1.0 / control_rate, 1.0 / status_rate, 1.0 / control_rate))
    period_cycles = math.lcm(*(period for _, period in plan))
    for index in range(period_cycles):
        frames = []
        for unit in range(1, units + 1):
            frames.append((framer.buildFrame(WriteSingleRegisterRequest(
                address=setpoint, registers=[100], dev_id=unit)), reply_size(6)))
            frames += [(framer.buildFrame(ReadHoldingRegistersRequest(
                address=b.start, count=b.count, dev_id=unit)), reply_size(3, b.count))
                for b, period in plan if index % period == 0]
        cycles.append(frames)
    done = 0
    with SimProcess('rtu', profile_name, list(range(1, units + 1)), port, emulate=False):
        wait_port(port)
        fd = os.open(port, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
        try:
            tty.setraw(fd)
            period, cycle = 1.0 / control_rate, 0
            own_status = Path(f'/proc/self/task/{threading.get_native_id()}/status')
            wakes0 = _context_switches(own_status)
            cpu0, start = time.thread_time(), time.monotonic()
            while time.monotonic() < start + window:
                for frame, expected in cycles[cycle % period_cycles]:
                    os.write(fd, frame)
                    reply = b''
                    while len(reply) < expected:
                        if not select.select([fd], [], [], 0.5)[0]:
                            raise RuntimeError(f'no reply to {frame.hex()}')
                        reply += os.read(fd, expected - len(reply))
                    done += 1
                cycle += 1
                time.sleep(max(0.0, start + cycle * period - time.monotonic()))
            cpu, elapsed = time.thread_time() - cpu0, time.monotonic() - start
            wakes = _context_switches(own_status) - wakes0
        finally:
            os.close(fd)
    cpu_percent = 100.0 * cpu / elapsed
    return {'profile': profile_name, 'drives': units, 'executor': 'io_floor',
            'control_rate_hz': control_rate, 'cpu_percent': round(cpu_percent, 2),
            'cpu_percent_by_thread': {'control loop': round(cpu_percent, 2)},
            'wakeups_per_s_by_thread': {'control loop': round(wakes / elapsed)},
            'transactions_per_s': round(done / elapsed, 1), 'rss_mb': None,
            'cpu_percent_per_drive': round(cpu_percent / units, 2),
            'approx_cycles_per_s': round(cycle / elapsed, 1),
            'target_percent_per_drive': 3.0 if units > 1 else 5.0}


def interpreted_steps(profile_name: str, units: int, cycles: int = 200) -> dict[str, Any]:
    """Count the bytecode instructions the control loop runs per drive-cycle.

    A bus of ``units`` drives in this process (the Bus alone, no ROS node) runs
    ``cycles`` back-to-back cycles against the simulator with ``sys.settrace``
    counting every opcode of every Python frame. Unlike CPU time it does not move
    with the host (steal, cold caches), so it tells whether a change to the cycle's
    Python made it cheaper. Returns the total and the functions that run most.
    """
    port = _port_path('steps')
    link = {'transport.type': 'modbus_rtu', 'transport.port': port, 'transport.timeout': 0.1,
            'transport.frame_gap': 0.0}
    document = _bus_document('steps', profile_name, units, link, 50.0)
    for settings in document['drives'].values():
        del settings['namespace']
    counts: dict[str, int] = {}

    def trace(frame: Any, event: str, _arg: Any) -> Any:
        frame.f_trace_opcodes = True
        if event == 'opcode':
            code = frame.f_code
            path = Path(code.co_filename)    # '<string>': a dataclass's generated __init__
            key = f'{path.parent.name}/{path.name}:{code.co_name}' if path.parent.name \
                else f'dataclass {code.co_name}'
            counts[key] = counts.get(key, 0) + 1
        return trace

    # The cycles run back to back; the drives' clock advances one 50 Hz period per cycle,
    # so the values only shown in ~/status are read as often as at 50 Hz (every second).
    clock = SimpleNamespace(now=0.0)
    real_time, modbus_drive.time = modbus_drive.time, SimpleNamespace(monotonic=lambda: clock.now)
    try:
        with SimProcess('rtu', profile_name, list(range(1, units + 1)), port, emulate=False):
            wait_port(port)
            bus = Bus(parse_bus_config(document))
            controllers = list(bus.controllers.values())
            try:
                def cycle() -> None:
                    for controller in controllers:
                        controller.command_velocity(1.0)
                    bus.step()
                    clock.now += 0.02
                wait_for(lambda: (cycle(), all(c.state.run_state is RunState.RUNNING
                                                for c in controllers))[1], 10.0, 'drives running')
                for _ in range(20):
                    cycle()
                sys.settrace(trace)
                try:
                    for _ in range(cycles):
                        cycle()
                finally:
                    sys.settrace(None)
            finally:
                bus.finish()
    finally:
        modbus_drive.time = real_time
    per_cycle = units * cycles
    top = sorted(counts.items(), key=lambda item: -item[1])[:8]
    return {'profile': profile_name, 'drives': units, 'cycles': cycles,
            'steps_per_drive_cycle': round(sum(counts.values()) / per_cycle),
            'top': [(name, round(count / per_cycle)) for name, count in top]}


def fleet(profile_name: str, units: int, framing: Framing, window: float,
          realtime_priority: int = 0) -> dict[str, Any]:
    """Many drives on one wire-timed line, one bus_node process, as fast as the line allows.

    Reports the fraction of the wire's limit reached, the CPU it costs, and the
    time from launch until every drive is online and running. ``realtime_priority``
    is the bus's own setting (SCHED_FIFO for its control thread; 0 = normal).
    """
    profile = load_profile(profile_name)
    setpoint = profile.parameter(profile.velocity.setpoint).address
    port = _port_path('fleet')
    tag = f'f{uuid.uuid4().hex[:6]}'
    link = {'transport.type': 'modbus_rtu', 'transport.port': port,
            'transport.baudrate': framing.baudrate, 'transport.parity': framing.parity,
            'transport.stopbits': framing.stopbits, 'transport.timeout': 0.1}
    result: dict[str, Any] = {'profile': profile_name, 'drives': units,
                              'baudrate': framing.baudrate, 'framing': framing.name,
                              'realtime_priority': realtime_priority}
    document = _bus_document(tag, profile_name, units, link, 10000.0)
    document['bus']['realtime_priority'] = realtime_priority
    with SimProcess('rtu', profile_name, list(range(1, units + 1)), port, framing.baudrate,
                    framing.parity, framing.stopbits, emulate=True) as sim:
        wait_port(port)
        bus = bus_node_process(document, units, tag, command_rate=20.0)
        try:
            result['startup_to_all_running_s'] = round(bus.wait_all_running(120.0), 2)
            result['startup_to_all_online_s'] = round(bus.all_online_s or 0.0, 2)
            bus.spin_for(1.0)
            start = time.monotonic()
            result.update(_cpu_window(bus, window))
            records = sim.ask('exchanges', start)
            result.update(sim_timing(sim.ask('stats')))
        finally:
            bus.close()
    if records:
        span = records[-1][0] + framing.exchange_time(records[-1][2], records[-1][3]) - \
            records[0][0]
        busy = sum(framing.exchange_time(request, reply) for _, _, request, reply in records)
        result['wire_busy_ratio'] = round(busy / span, 4)     # the line's duty cycle
    try:
        result.update(wire_ratio(records, setpoint, framing))
    except RuntimeError as exc:         # too few whole cycles: the duty cycle still says it
        result['cycles_note'] = str(exc)
    result['target_ratio'], result['target_cpu_percent'] = 0.90, 50.0
    return result


def _start_pyspy(pid: int, seconds: float) -> Any:
    out = tempfile.NamedTemporaryFile(suffix='.txt', delete=False)
    out.close()
    spy = subprocess.Popen(['py-spy', 'record', '--gil', '--pid', str(pid), '--duration',
                            str(max(1, int(seconds))), '--rate', '250', '--format', 'raw',
                            '--nonblocking', '--output', out.name],
                           stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    return spy, out.name


def _finish_pyspy(spy: Any) -> list[tuple[str, float]]:
    process, path = spy
    try:
        process.wait(30.0)
    except subprocess.TimeoutExpired:
        process.kill()
        return []
    return summarise_collapsed(Path(path).read_text() if Path(path).exists() else '')


def summarise_collapsed(text: str, top: int = 8) -> list[tuple[str, float]]:
    """Share of samples by the innermost vfd_ros2/pymodbus/rclpy/serial frame of each stack."""
    counts: dict[str, int] = {}
    total = 0
    for line in text.splitlines():
        stack, _, number = line.rpartition(' ')
        if not number.isdigit():
            continue
        samples = int(number)
        total += samples
        frames = stack.split(';')
        label = frames[-1]
        for frame in reversed(frames):
            if any(key in frame for key in ('vfd_ros2', 'pymodbus', 'rclpy', 'serial')):
                label = frame
                break
        label = label.split(' (')[0] + ' ' + (label.split('(')[1].split(':')[0].rsplit('/', 1)[-1]
                                             if '(' in label else '')
        counts[label] = counts.get(label, 0) + samples
    if not total:
        return []
    ranked = sorted(counts.items(), key=lambda item: -item[1])[:top]
    return [(label.strip(), round(100.0 * n / total, 1)) for label, n in ranked]
