"""CANopen cases: PDO cycle rate, missed cycles and command latency, drives in another process.

Imports the CANopen transport and simulator at module level: if they are not
there (or not importable), ``bench/run.py`` reports the section as skipped.
The simulated drives and a frame recorder run in a process of their own
(``vfd_ros2.sim.canopen_process``: a python-can ``virtual`` channel there, bridged
to this process by a socketcand-protocol server on loopback TCP), so the driver
here has its interpreter and GIL to itself, as it would with drives on a wire.
The driver opens the bridge as python-can's ``socketcand`` interface with
``transport.can_options``. The recorder stamps every frame on the monotonic clock,
which this process shares: the moment the frame was put on the simulated bus
(for a frame of the driver, once the bridge had read it from TCP) is compared
with this process's publish times. The drive nodes share one CAN channel (one
python-can handle, so one TCP connection, one ``canopen.Network``, one host
heartbeat): each row records the handles the drivers held and the connections
the bridge saw.
"""

from __future__ import annotations

import json
import logging
import math
import statistics
import tempfile
import threading
import time
import uuid
from pathlib import Path
from typing import Any

import rclpy
import yaml
from rclpy.context import Context
from rclpy.executors import Executor
from rclpy.node import Node
from rclpy.parameter import Parameter
from std_msgs.msg import Float64

from vfd_ros2.ros.bus_node import BusNode
from vfd_ros2.ros.drive_node import DriveNode
from vfd_ros2.ros.executable import make_executor
from vfd_ros2.sim.canopen_process import CanopenSimProcess
from vfd_ros2.transports.canopen import open_channels

from .cases import _percentile, wait_for

PROFILE = 'cia402_velocity'

# python-can's socketcand client warns for every TCP read that ends inside a frame
# (ordinary on a stream: it keeps the rest for the next read); at 250 Hz x 4 drives
# that is a steady flood on stderr, written from the driver's receive thread.
logging.getLogger('can.interfaces.socketcand.socketcand').setLevel(logging.ERROR)


def pdo_cycles(units: int, rate: float, window: float, commands: int = 0,
               design: str = 'bus', priority: int = 0) -> dict[str, Any]:
    """``design``: 'bus' = one bus_node thread for the channel; 'nodes' = a drive_node each."""
    # At normal priority, unlike the RTU simulator: answering ~3000 frames/s in Python it
    # takes most of a core, and at SCHED_FIFO it pre-empts the driver under test.
    sim = CanopenSimProcess(PROFILE, range(1, units + 1), record=True).start()
    channel = sim.bus
    context = Context()
    rclpy.init(context=context)
    tag = f'co{uuid.uuid4().hex[:6]}'
    nodes: list[Node] = []
    tmp = tempfile.TemporaryDirectory()
    try:
        drive_settings = {'drive.profile': PROFILE, 'gear_ratio': 10.0, 'auto_enable': True,
                          'status_rate': 20.0, 'command_timeout': 0.5}
        link = {'transport.type': 'canopen', 'transport.interface': 'socketcand',
                'transport.channel': channel,
                'transport.can_options': json.dumps(sim.can_options)}
        if design == 'bus':
            path = Path(tmp.name) / 'bus.yaml'
            path.write_text(yaml.safe_dump({
                'bus': {'name': 'can0', **link, 'control_rate': rate,
                        'realtime_priority': priority},
                'drives': {f'd{n}': {'namespace': f'/{tag}/d{n}', 'transport.unit_id': n,
                                     **drive_settings} for n in range(1, units + 1)}}))
            bus_node = BusNode(context=context, namespace=f'/{tag}', parameter_overrides=[
                Parameter('config_file', value=str(path))])
            nodes.append(bus_node)          # it destroys its drive nodes itself
            controllers = list(bus_node.bus.controllers.values())
            loops = [bus_node.bus]
        else:
            for node_id in range(1, units + 1):
                parameters = {**drive_settings, **link, 'transport.unit_id': node_id,
                              'control_rate': rate, 'realtime_priority': priority}
                nodes.append(DriveNode('drive', namespace=f'/{tag}/d{node_id}', context=context,
                                       parameter_overrides=[Parameter(k, value=v)
                                                            for k, v in parameters.items()]))
            controllers = [node.controller for node in nodes]
            loops = controllers
        tester = Node('bench_can', namespace=f'/{tag}', context=context)
        publishers = [tester.create_publisher(Float64, f'd{n}/drive/velocity_command', 10)
                      for n in range(1, units + 1)]
        executor = make_executor(context)
        for node in [*nodes, *getattr(nodes[0], 'drive_nodes', []), tester]:
            executor.add_node(node)
        spin = threading.Thread(target=lambda: _spin(executor, context), daemon=True)
        spin.start()

        def online() -> bool:
            for publisher in publishers:
                publisher.publish(Float64(data=1.0))
            return all(c.state.online and c.state.state == 'running' for c in controllers)
        wait_for(online, 20.0, 'CANopen drives online and running')
        # Stream commands at the cycle rate; for latency, alternate values on drive 1.
        sent: list[tuple[float, float]] = []
        period = 1.0 / rate
        cycles0 = [c._cycle for c in controllers]             # noqa: SLF001
        overruns0 = [loop._loop.overruns for loop in loops]   # noqa: SLF001
        start = next_time = time.monotonic()
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
        mine = [c for c in open_channels() if c.key[:2] == ('socketcand', channel)]
        handles = len(mine)
        bridge = sim.status()
        heartbeat_period = max((c.heartbeat_period for c in mine), default=0.0)
        cycles = [c._cycle - c0 for c, c0 in zip(controllers, cycles0)]           # noqa: SLF001
        overruns = [loop._loop.overruns - o0 for loop, o0 in zip(loops, overruns0)]  # noqa
        notes = sorted({note for c in controllers for note in c.loop_notes})
    finally:
        for node in nodes:
            node.destroy_node()
        rclpy.try_shutdown(context=context)
        tmp.cleanup()
        # the drivers' socketcand connections are closed above: python-can's client
        # spins on a connection whose server has gone
        frames = sim.stop()
    expected = rate * elapsed
    # Every time is the frame's moment on the simulated bus (``sent``), on the
    # monotonic clock this process shares: not when the recorder thread got to it.
    begin, end = start, start + elapsed
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
        'realtime_priority': priority, 'loop_notes': notes,
        'drives': units, 'rate_hz': rate, 'seconds': round(elapsed, 2),
        'cycles_per_s': round(min(cycles) / elapsed, 1),
        'missed_cycles': max(0, round(expected - min(cycles))),
        'overruns': max(overruns), 'rpdo_frames': len(rpdo), 'sync_frames': syncs,
        'node1_late_rpdo_slots': late_slots,
        'frames_per_s': round(len(in_window) / elapsed, 1),
        'bus_load_percent_at_1mbit': round(100.0 * wire_bits / elapsed / 1e6, 1),
        'can_handles': handles, 'bridge_connections': bridge['connections'],
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


def _spin(executor: Executor, context: Context) -> None:
    while context.ok():
        try:
            executor.spin_once(timeout_sec=0.05)
        except Exception:  # noqa: BLE001 - context shut down under us
            if not context.ok():
                return
            raise


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
            'elapsed - cycles completed by the slowest drive; late slots = node 1 RPDO gaps '
            'of more than 1.5 periods (jitter); bus load = the frames seen, on a 1 Mbit/s bus '
            'with worst-case bit stuffing; latency = publish -> first changed RPDO1 '
            '(0x201) on the simulated bus. The simulated drives now run in their own process '
            '(python-can virtual bus there) behind a socketcand-protocol bridge on loopback '
            "TCP, which the driver opens as python-can's socketcand interface "
            '(transport.can_options): the driver no longer shares its GIL with them, and '
            'every frame crosses TCP (and the bridge) once, which the latency includes. '
            'Connections = the TCP connections the bridge accepted: 1, unless drives went '
            'offline (a heartbeat timeout) and the channel was opened again.')
    if any(math.isnan(r.get('cycles_per_s', math.nan)) for r in rows if 'error' not in r):
        note += ' Some rows have no cycles.'
    return {'rows': rows, 'note': note}
