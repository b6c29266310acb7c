"""EtherCAT cycle benchmark: the segment master against 1, 2, 4 simulated drives.

Runs ``vfd_ros2.transports.ethercat.EthercatSegment`` (pysoem) on one end of a
veth pair in a namespace this script creates, the simulated segment
(``vfd_ros2.sim.ethercat``) in its own process on the other end, and prints per
case: achieved cycle time, missed cycles, WKC errors, lost frames, wake-up
jitter p50/p99/max, CPU of the master process, of its process-data thread and
of the simulator process, and the simulator's per-frame processing time.

Needs root (namespaces, raw sockets). Usage::

    python bench/ethercat_cycle.py --duration 10 --cycles 2,1 --drives 1,2,4
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import sys
import time
from pathlib import Path

os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')    # no ROS here; the rule
# Appended: with the environment active vfd_ros2 comes from the colcon install (it has the
# generated messages the latency case needs); the bench package from this checkout.
if str(Path(__file__).resolve().parent.parent) not in sys.path:
    sys.path.append(str(Path(__file__).resolve().parent.parent))

from vfd_ros2.sim.ethercat.catalog import BONENG_MH_EC, IMO_HD2_EC_TX508  # noqa: E402
from vfd_ros2.sim.ethercat.segment import SimulatedSegment  # noqa: E402
from vfd_ros2.transports import netns  # noqa: E402
from vfd_ros2.transports.ethercat import (  # noqa: E402
    EthercatSegment,
    PdoConfiguration,
    SegmentSettings,
    SyncMode,
)

LINE = (IMO_HD2_EC_TX508, BONENG_MH_EC, IMO_HD2_EC_TX508, BONENG_MH_EC)
PDOS = {IMO_HD2_EC_TX508.name: PdoConfiguration(rx=(0x1600,), tx=(0x1A00,)),
        BONENG_MH_EC.name: PdoConfiguration(rx=(0x1701,), tx=(0x1B01,))}


def process_cpu_s(pid: int) -> float:
    """User + system CPU seconds of another process (from /proc)."""
    fields = Path(f'/proc/{pid}/stat').read_text().rsplit(')', 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf('SC_CLK_TCK')


def own_cpu_s() -> float:
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_utime + usage.ru_stime


def run_case(drives: int, cycle_s: float, duration: float, sync: SyncMode,
             priority: int | None = None) -> dict:
    link = netns.create_veth_link('bench')
    try:
        with SimulatedSegment(link, LINE[:drives]) as sim:
            settings = SegmentSettings(interface=link.master_interface,
                                       namespace=link.namespace, cycle_time_s=cycle_s,
                                       sync_mode=sync, mailbox_poll_s=0.1,
                                       realtime_priority=priority)
            with EthercatSegment(settings) as master:
                master.open()
                for position, spec in enumerate(LINE[:drives]):
                    master.configure_pdos(position, PDOS[spec.name])
                master.start()
                time.sleep(0.2)                                # settle after OP
                before = master.stats()
                cpu0, sim0, wall0 = own_cpu_s(), process_cpu_s(sim.pid), time.monotonic()
                time.sleep(duration)
                after = master.stats()
                cpu1, sim1, wall1 = own_cpu_s(), process_cpu_s(sim.pid), time.monotonic()
                sim_stats = sim.stats()
        wall = wall1 - wall0
        cycles = after.cycles - before.cycles
        return {
            'drives': drives, 'cycle_ms': cycle_s * 1e3, 'sync': sync.value,
            'realtime_priority': priority,
            'duration_s': round(wall, 2), 'cycles': cycles,
            'achieved_cycle_ms': round(wall / cycles * 1e3, 4) if cycles else None,
            'missed': after.missed_cycles - before.missed_cycles,
            'wkc_errors': after.wkc_errors - before.wkc_errors,
            'lost_frames': after.lost_frames - before.lost_frames,
            'jitter_p50_us': round(after.jitter_p50_s * 1e6, 1),
            'jitter_p99_us': round(after.jitter_p99_s * 1e6, 1),
            'jitter_max_us': round(after.jitter_max_s * 1e6, 1),
            'master_cpu_pct': round(100 * (cpu1 - cpu0) / wall, 1),
            'cycle_thread_cpu_pct': round(100 * (after.cycle_cpu_s - before.cycle_cpu_s)
                                          / wall, 1),
            'sim_cpu_pct': round(100 * (sim1 - sim0) / wall, 1),
            'sim_frame_us_p50': round(sim_stats['processing_us_p50'], 1),
            'sim_frame_us_p99': round(sim_stats['processing_us_p99'], 1),
        }
    finally:
        netns.destroy_veth_link(link)


def command_latency(drives: int, cycle_s: float, commands: int = 300,
                    rate: float = 50.0) -> dict:
    """Publish ~/velocity_command -> the new RxPDO bytes handed to the process-data thread.

    Drive nodes exactly as bus_node builds them (``bench.cases.NodeBus``) on a simulated
    segment of HD2 drives; a sampler thread reads drive 1's output bytes every 0.2 ms and
    stamps the first appearance of each command's raw velocity. The frame leaves within
    one more cycle (the thread copies the outputs at its next wake-up): ``wire_bound_ms``.
    """
    import statistics
    import threading

    from std_msgs.msg import Float64

    from bench.cases import NodeBus

    link = netns.create_veth_link('benchlat')
    try:
        with SimulatedSegment(link, [IMO_HD2_EC_TX508] * drives):
            bus = NodeBus('imo_hd2', drives, {
                'transport.type': 'ethercat', 'transport.interface': link.master_interface,
                'transport.namespace': link.namespace, 'transport.cycle_time': cycle_s},
                control_rate=rate)
            try:
                bus.wait_online()
                drive = bus.controllers[0].drive
                transport = drive.transport
                seen: list[tuple[float, int]] = []
                stop = threading.Event()

                def sample() -> None:
                    last = None
                    while not stop.is_set():
                        data = transport._slave(1).outputs()       # noqa: SLF001
                        raw = int.from_bytes(data[2:6], 'little', signed=True)
                        if raw != last:
                            seen.append((time.monotonic(), raw))
                            last = raw
                        time.sleep(0.0002)
                sampler = threading.Thread(target=sample, daemon=True)
                sampler.start()
                sent = []
                period = 1.0 / rate
                for index in range(commands):
                    velocity = 0.5 + 0.01 * (index % 200)
                    raw = drive._native(velocity)                  # noqa: SLF001
                    sent.append((time.monotonic(), raw))
                    bus.publishers[0].publish(Float64(data=velocity))
                    time.sleep(period)
                time.sleep(0.2)
                stop.set()
                sampler.join(1.0)
            finally:
                bus.close()
    finally:
        netns.destroy_veth_link(link)
    latencies = []
    for published, raw in sent:
        hit = next((t for t, value in seen if value == raw and published <= t < published + 1),
                   None)
        if hit is not None:
            latencies.append(1e3 * (hit - published))
    latencies.sort()
    return {
        'case': f'latency x{drives} {cycle_s * 1e3:g} ms', 'drives': drives,
        'cycle_ms': cycle_s * 1e3, 'command_rate_hz': rate, 'commands': commands,
        'matched': len(latencies),
        'median_ms': round(statistics.median(latencies), 3) if latencies else None,
        'p99_ms': round(latencies[int(0.99 * (len(latencies) - 1))], 3) if latencies else None,
        'max_ms': round(latencies[-1], 3) if latencies else None,
        'wire_bound_ms': round(cycle_s * 1e3, 3),
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--duration', type=float, default=10.0, help='seconds per case')
    parser.add_argument('--cycles', default='2,1', help='cycle times in ms, comma separated')
    parser.add_argument('--drives', default='1,2,4', help='drive counts, comma separated')
    parser.add_argument('--dc', action='store_true', help='DC SYNC0 mode instead of free run')
    parser.add_argument('--rt', type=int, metavar='PRIORITY',
                        help='SCHED_FIFO priority for the process-data thread')
    parser.add_argument('--json', type=Path, help='also write the results here')
    args = parser.parse_args(argv)
    reason = netns.namespace_support()
    if reason:
        print(f'cannot run: {reason}', file=sys.stderr)
        return 2
    sync = SyncMode.DC if args.dc else SyncMode.FREE_RUN
    rows = []
    header = ('drives', 'cycle ms', 'achieved ms', 'cycles', 'missed', 'WKC err', 'lost',
              'jitter p50/p99/max us', 'CPU master/thread/sim %', 'sim frame p50/p99 us')
    print(' | '.join(header))
    for cycle_ms in (float(v) for v in args.cycles.split(',')):
        for drives in (int(v) for v in args.drives.split(',')):
            row = run_case(drives, cycle_ms / 1e3, args.duration, sync, args.rt)
            rows.append(row)
            print(' | '.join(str(v) for v in (
                row['drives'], row['cycle_ms'], row['achieved_cycle_ms'], row['cycles'],
                row['missed'], row['wkc_errors'], row['lost_frames'],
                f"{row['jitter_p50_us']}/{row['jitter_p99_us']}/{row['jitter_max_us']}",
                f"{row['master_cpu_pct']}/{row['cycle_thread_cpu_pct']}/{row['sim_cpu_pct']}",
                f"{row['sim_frame_us_p50']}/{row['sim_frame_us_p99']}")), flush=True)
    if args.json:
        args.json.write_text(json.dumps(rows, indent=2) + '\n', encoding='utf-8')
    return 0


if __name__ == '__main__':
    sys.exit(main())
