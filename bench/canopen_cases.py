"""CANopen cases: PDO cycle rate, missed cycles and command latency, each side its own process.

Imports the CANopen transport and simulator at module level: if they are not
there (or not importable), ``bench/run.py`` reports the section as skipped.
Three processes, as on a robot with drives on a wire: the simulated drives and a
frame recorder (``vfd_ros2.sim.canopen_process``: a python-can ``virtual`` channel
there, bridged by a socketcand-protocol server on loopback TCP), the driver
(bus_node, or the drive_nodes of the previous design in one process:
``bench/drive_nodes.py``), which opens the bridge as python-can's ``socketcand``
interface with ``transport.can_options``, and this process, which publishes the
commands (a planner) and reads the recorder's frames at the end. The recorder
stamps every frame on the monotonic clock, which all three share: the moment the
frame was put on the simulated bus (for a frame of the driver, once the bridge had
read it from TCP) is compared with this process's publish times, and every count
(cycles, SYNCs, heartbeats) is taken from the frames.
"""

from __future__ import annotations

import json
import math
import statistics
import time
import uuid
from typing import Any

from std_msgs.msg import Float64

from vfd_ros2.sim.canopen_process import CanopenSimProcess

from .cases import DriverProcess, _percentile, _proc_cpu_seconds, bus_node_process, wait_for
from .drive_nodes import SPEC_FILE

PROFILE = 'cia402_velocity'


def pdo_cycles(units: int, rate: float, window: float, commands: int = 0,
               design: str = 'bus', priority: int = 0) -> dict[str, Any]:
    """``design``: 'bus' = one bus_node thread for the channel; 'nodes' = a drive_node each.

    The driver runs in a process of its own (bus_node, or the drive_nodes in one
    process), as on a robot; this process only publishes the commands (a planner)
    and reads the frames the simulator recorded: every count below is taken on the
    simulated bus.
    """
    # At normal priority, unlike the RTU simulator: answering ~3000 frames/s in Python it
    # takes most of a core, and at SCHED_FIFO it pre-empts the driver under test.
    sim = CanopenSimProcess(PROFILE, range(1, units + 1), record=True).start()
    tag = f'co{uuid.uuid4().hex[:6]}'
    driver = None
    try:
        drive_settings = {'drive.profile': PROFILE, 'gear_ratio': 10.0, 'auto_enable': True,
                          'status_rate': 20.0, 'command_timeout': 0.5}
        link = {'transport.type': 'canopen', 'transport.interface': 'socketcand',
                'transport.channel': sim.bus,
                'transport.can_options': json.dumps(sim.can_options)}
        if design == 'bus':
            driver = bus_node_process({
                'bus': {'name': 'can0', **link, 'control_rate': rate,
                        'realtime_priority': priority},
                'drives': {f'd{n}': {'namespace': f'/{tag}/d{n}', 'transport.unit_id': n,
                                     **drive_settings} for n in range(1, units + 1)}},
                units, tag, command_rate=None)
        else:
            spec = [{'namespace': f'/{tag}/d{n}',
                     'parameters': {**drive_settings, **link, 'transport.unit_id': n,
                                    'control_rate': rate, 'realtime_priority': priority}}
                    for n in range(1, units + 1)]
            driver = DriverProcess('bench.drive_nodes', [], units, tag, command_rate=None,
                                   files={SPEC_FILE: spec})
        publishers = driver.publishers

        def online() -> bool:
            for publisher in publishers:
                publisher.publish(Float64(data=1.0))
            driver.spin_for(0.05)
            return len(driver.last) == units and all(
                s.online and s.state == 'running' for s in driver.last.values())
        wait_for(online, 30.0, 'CANopen drives online and running')
        # Stream commands at the cycle rate; for latency, alternate values on drive 1.
        sent: list[tuple[float, float]] = []
        period = 1.0 / rate
        start = next_time = time.monotonic()
        cpu0 = _proc_cpu_seconds(driver.child.pid)
        index = 0
        while time.monotonic() - start < window:
            velocity = 1.0 + 0.5 * (index % 2)
            now = time.monotonic()
            for publisher in publishers:
                publisher.publish(Float64(data=velocity))
            if commands == 0 or len(sent) < commands:
                sent.append((now, velocity))
            index += 1
            next_time += period
            time.sleep(max(0.0, next_time - time.monotonic()))
        elapsed = time.monotonic() - start
        driver_cpu = 100.0 * (_proc_cpu_seconds(driver.child.pid) - cpu0) / elapsed
        bridge = sim.status()
    finally:
        # The driver's socketcand connection closes first: python-can's client spins on
        # a connection whose server has gone.
        if driver is not None:
            driver.close()
        frames = sim.stop()
    expected = rate * elapsed
    # Every time is the frame's moment on the simulated bus (``sent``), on the
    # monotonic clock this process shares: not when the recorder thread got to it.
    begin, end = start, start + elapsed
    # A cycle of a drive = its RPDO1 (the driver sends it every cycle, and a command
    # waits for the cycle on a SYNC-driven bus)
    cycles = [sum(1 for f in frames if f.cob_id == 0x200 + n and begin <= f.sent <= end)
              for n in range(1, units + 1)]
    # Latency: the first RPDO1 of node 1 (COB-ID 0x201) after a publish whose payload
    # differs from the one before it (the commanded value alternates every command).
    rpdo = [(f.sent, f.data) for f in frames if f.cob_id == 0x201]
    stamps = [t for t, _ in rpdo if begin <= t <= end]
    # a late slot: node 1's RPDOs more than 1.5 periods apart (the loop woke late; it
    # catches up within a period, or counts a missed cycle beyond)
    late_slots = sum(round((b - a) / period) - 1 for a, b in zip(stamps, stamps[1:])
                     if b - a > 1.5 / rate)
    in_window = [(f.cob_id, f.data) for f in frames if begin <= f.sent <= end]
    syncs = sum(1 for cob, _ in in_window if cob == 0x80)
    # what these frames would occupy on a real 1 Mbit/s bus (11-bit ids, worst-case stuffing)
    wire_bits = sum(_frame_bits(len(data)) for _, data in in_window)
    heartbeats = [f.sent for f in frames if f.cob_id == 0x77F]     # host node 127
    heartbeat_period = statistics.median(b - a for a, b in zip(heartbeats, heartbeats[1:])) \
        if len(heartbeats) > 1 else 0.0
    # the simulator process's own lag: bus moment -> its recorder thread
    lag = [1e3 * (f.received - f.sent) for f in frames if begin <= f.sent <= end]
    latencies = []
    cursor = 0
    for published, _ in sent:
        while cursor < len(rpdo) and rpdo[cursor][0] < published:
            cursor += 1
        if cursor == 0 or cursor >= len(rpdo):
            continue
        before = rpdo[cursor - 1][1]
        hit = next((t for t, data in rpdo[cursor:cursor + 20] if data != before), None)
        if hit is not None and hit - published < 0.5:
            latencies.append(1e3 * (hit - published))
    return {
        'design': 'bus_node (one thread per channel)' if design == 'bus'
        else 'drive_node per drive (previous design)',
        'realtime_priority': priority,
        'drives': units, 'rate_hz': rate, 'seconds': round(elapsed, 2),
        'cycles_per_s': round(min(cycles) / elapsed, 1),
        'missed_cycles': max(0, round(expected - min(cycles))),
        'rpdo_frames': len(rpdo), 'sync_frames': syncs,
        'driver_cpu_percent': round(driver_cpu, 1),
        'node1_late_rpdo_slots': late_slots,
        'frames_per_s': round(len(in_window) / elapsed, 1),
        'bus_load_percent_at_1mbit': round(100.0 * wire_bits / elapsed / 1e6, 1),
        'bridge_connections': bridge['connections'],
        'recorder_lag_p99_ms': round(_percentile(lag, 0.99), 3) if lag else None,
        'host_heartbeat_ms': round(heartbeat_period * 1000, 1),
        'host_heartbeat_frames': len(heartbeats),
        'latency_median_ms': round(statistics.median(latencies), 3) if latencies else None,
        'latency_p99_ms': round(_percentile(latencies, 0.99), 3) if latencies else None,
        'latency_max_ms': round(max(latencies), 3) if latencies else None,
        'latency_samples': len(latencies),
    }


def _frame_bits(data_bytes: int) -> int:
    """Bits of a classical CAN data frame with an 11-bit id, worst-case bit stuffing."""
    return 44 + 8 * data_bytes + (34 + 8 * data_bytes - 1) // 4 + 3     # + interframe space


#: (drives, Hz, design, realtime priority, full-run seconds): the previous design (a
#: drive_node per drive, each its own thread) next to one bus thread per channel
CASES = (
    (4, 250.0, 'nodes', 0, 60.0),
    (4, 250.0, 'bus', 0, 60.0),
    (4, 250.0, 'bus', 50, 60.0),
    (8, 500.0, 'bus', 50, 30.0),
)


def run(quick: bool) -> dict[str, Any]:
    rows = []
    for units, rate, design, priority, seconds in CASES:
        try:
            rows.append(pdo_cycles(units, rate, 3.0 if quick else seconds, design=design,
                                   priority=priority))
        except Exception as exc:  # noqa: BLE001 - report, keep the other rows
            rows.append({'drives': units, 'rate_hz': rate, 'design': design,
                         'realtime_priority': priority,
                         'error': f'{type(exc).__name__}: {exc}'})
    note = ('Target: 4 drives at 250 Hz with 0 missed cycles over 60 s. Missed = rate x '
            'elapsed - cycles completed by the slowest drive (its RPDO1 frames on the '
            'simulated bus: the driver sends one every cycle); late slots = node 1 RPDO gaps '
            'of more than 1.5 periods (jitter); bus load = the frames seen, on a 1 Mbit/s bus '
            'with worst-case bit stuffing; latency = publish -> first changed RPDO1 '
            '(0x201) on the simulated bus, which includes one crossing of loopback TCP and '
            'the bridge. The driver (bus_node, or the previous design: a drive_node per '
            'drive, in one process) has a process of its own, as on a robot; the bench '
            'process only publishes the commands, and the simulated drives run in a third '
            "(python-can virtual bus there), which the driver reaches as python-can's "
            'socketcand interface (transport.can_options). Driver CPU = its process, % of '
            'one core. Connections = the TCP connections the bridge accepted: 1, unless '
            'drives went offline (a heartbeat timeout) and the channel was opened again.')
    if any(math.isnan(r.get('cycles_per_s', math.nan)) for r in rows if 'error' not in r):
        note += ' Some rows have no cycles.'
    return {'rows': rows, 'note': note}
