"""CANopen cases: PDO cycle rate, missed cycles and command latency on python-can's virtual bus.

Imports the CANopen transport and simulator at module level: if they are not
there (or not importable), ``bench/run.py`` reports the section as skipped.
python-can's ``virtual`` interface is in-process, so the simulated drives run in
this process (one ticking thread); a listener on the same channel timestamps
every frame the driver sends. The drive nodes share one CAN channel (one
python-can handle, one ``canopen.Network``, one host heartbeat): each row records
the handles the drivers held and the host heartbeat frames seen.
"""

from __future__ import annotations

import math
import statistics
import threading
import time
import uuid
from typing import Any

import can
import rclpy
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter
from std_msgs.msg import Float64

from vfd_ros2.profiles import load_profile
from vfd_ros2.ros.drive_node import DriveNode
from vfd_ros2.sim.canopen_drive import SimulatedCanBus, SimulatedCanopenDrive
from vfd_ros2.transports.canopen import open_channels

from .cases import _percentile, wait_for

PROFILE = 'cia402_velocity'


class _Recorder(can.Listener):
    def __init__(self) -> None:
        self.frames: list[tuple[float, int, bytes]] = []

    def on_message_received(self, msg: can.Message) -> None:
        self.frames.append((time.monotonic(), msg.arbitration_id, bytes(msg.data)))


def pdo_cycles(units: int, rate: float, window: float, commands: int = 0) -> dict[str, Any]:
    channel = f'bench{uuid.uuid4().hex[:8]}'
    profile = load_profile(PROFILE)
    sims = [SimulatedCanopenDrive(profile, node_id) for node_id in range(1, units + 1)]
    line = SimulatedCanBus(sims, channel).start()
    listen = can.Bus(interface='virtual', channel=channel)
    recorder = _Recorder()
    notifier = can.Notifier(listen, [recorder])
    context = Context()
    rclpy.init(context=context)
    tag = f'co{uuid.uuid4().hex[:6]}'
    nodes = []
    try:
        for node_id in range(1, units + 1):
            parameters = {'drive.profile': PROFILE, 'transport.type': 'canopen',
                          'transport.interface': 'virtual', 'transport.channel': channel,
                          'transport.unit_id': node_id, 'gear_ratio': 10.0,
                          'auto_enable': True, 'control_rate': rate, 'status_rate': 20.0,
                          'command_timeout': 0.5}
            nodes.append(DriveNode('drive', namespace=f'/{tag}/d{node_id}', context=context,
                                   parameter_overrides=[Parameter(k, value=v)
                                                        for k, v in parameters.items()]))
        tester = Node('bench_can', namespace=f'/{tag}', context=context)
        publishers = [tester.create_publisher(Float64, f'd{n}/drive/velocity_command', 10)
                      for n in range(1, units + 1)]
        executor = SingleThreadedExecutor(context=context)
        for node in [*nodes, tester]:
            executor.add_node(node)
        spin = threading.Thread(target=lambda: _spin(executor, context), daemon=True)
        spin.start()
        controllers = [node.controller for node in nodes]

        def online() -> bool:
            for publisher in publishers:
                publisher.publish(Float64(data=1.0))
            return all(c.state.online and c.state.state == 'running' for c in controllers)
        wait_for(online, 20.0, 'CANopen drives online and running')
        # Stream commands at the cycle rate; for latency, alternate values on drive 1.
        sent: list[tuple[float, float]] = []
        period = 1.0 / rate
        cycles0 = [c._cycle for c in controllers]             # noqa: SLF001
        overruns0 = [c._loop.overruns for c in controllers]   # noqa: SLF001
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
        handles = sum(1 for c in open_channels() if c.key[1] == channel)
        heartbeat_period = max((c.heartbeat_period for c in open_channels()
                                if c.key[1] == channel), default=0.0)
        cycles = [c._cycle - c0 for c, c0 in zip(controllers, cycles0)]           # noqa: SLF001
        overruns = [c._loop.overruns - o0 for c, o0 in zip(controllers, overruns0)]  # noqa
        frames = list(recorder.frames)
    finally:
        for node in nodes:
            node.destroy_node()
        rclpy.try_shutdown(context=context)
        notifier.stop()
        listen.shutdown()
        line.stop()
    expected = rate * elapsed
    # Latency: the first RPDO1 of node 1 (COB-ID 0x201) after a publish whose payload
    # differs from the one before it (the commanded value alternates every command).
    rpdo = [(t, data) for t, cob, data in frames if cob == 0x201]
    heartbeats = [t for t, cob, _ in frames if cob == 0x77F]     # host node 127
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
        'drives': units, 'rate_hz': rate, 'seconds': round(elapsed, 2),
        'cycles_per_s': round(min(cycles) / elapsed, 1),
        'missed_cycles': max(0, round(expected - min(cycles))),
        'overruns': max(overruns), 'rpdo_frames': len(rpdo),
        'can_handles': handles, 'host_heartbeat_ms': round(heartbeat_period * 1000, 1),
        'host_heartbeat_frames': len(heartbeats),
        'latency_median_ms': round(statistics.median(latencies), 3) if latencies else None,
        'latency_p99_ms': round(_percentile(latencies, 0.99), 3) if latencies else None,
        'latency_max_ms': round(max(latencies), 3) if latencies else None,
        'latency_samples': len(latencies),
    }


def _spin(executor: SingleThreadedExecutor, context: Context) -> None:
    while context.ok():
        try:
            executor.spin_once(timeout_sec=0.05)
        except Exception:  # noqa: BLE001 - context shut down under us
            if not context.ok():
                return
            raise


def run(quick: bool) -> dict[str, Any]:
    rows = []
    for units in (1, 2, 4):
        window = 3.0 if quick else (60.0 if units == 4 else 10.0)
        try:
            rows.append(pdo_cycles(units, 250.0, window))
        except Exception as exc:  # noqa: BLE001 - report, keep the other rows
            rows.append({'drives': units, 'rate_hz': 250.0,
                         'error': f'{type(exc).__name__}: {exc}'})
    note = ('Target: 4 drives at 250 Hz with 0 missed cycles over 60 s. Missed = 250 Hz x '
            'elapsed - cycles completed by the slowest drive; latency = publish -> first '
            'changed RPDO1 (0x201) on the virtual bus.')
    if any(math.isnan(r.get('cycles_per_s', math.nan)) for r in rows if 'error' not in r):
        note += ' Some rows have no cycles.'
    return {'rows': rows, 'note': note}
