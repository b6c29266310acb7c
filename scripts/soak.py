"""Soak test, on demand: N simulated drives on one RS-485 line, hours of commands, random faults.

    scripts/soak [--drives 4] [--minutes 120] [--seed 1]

Everything runs in this process over real Modbus RTU frames on a pty: a bus of
DriveControllers (what bus_node runs) against the simulated line. A commander
changes every drive's velocity every few hundred milliseconds; a chaos monkey
injects drive faults (reset afterwards by an operator), pulls drives off the
line for a while, and corrupts replies in bursts. The report at the end counts
commands sent and acknowledged by the drives, faults injected, seen and reset,
reconnects, and every loss it cannot explain by an injected event (the exit
code is 1 if there is one).
"""

from __future__ import annotations

import argparse
import json
import random
import sys
import tempfile
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

from vfd_ros2.bus import Bus, parse_bus_config
from vfd_ros2.profile import load_profile
from vfd_ros2.sim.model import SimulatedDrive
from vfd_ros2.sim.rtu_line import SimulatedRtuLine


@dataclass
class Report:
    seconds: float = 0.0
    drives: int = 0
    commands_sent: int = 0
    commands_acknowledged: int = 0      # the drive's setpoint register reached the command
    faults_injected: int = 0
    faults_seen: int = 0                # published by the driver with the manual's name
    faults_reset: int = 0
    unplugs: int = 0
    reconnects: int = 0
    corruption_bursts: int = 0
    bad_frames: int = 0
    timeouts: int = 0
    unexplained: list[str] = field(default_factory=list)


def run(drives: int, seconds: float, seed: int, out=sys.stdout) -> Report:
    rng = random.Random(seed)
    profile = load_profile('boneng_am')
    workdir = Path(tempfile.mkdtemp(prefix='vfd_soak_'))
    sims = [SimulatedDrive(profile, unit, {'acceleration_time': 0.2, 'deceleration_time': 0.2})
            for unit in range(1, drives + 1)]
    line = SimulatedRtuLine(sims, workdir / 'rs485', seed=seed).start()
    config = parse_bus_config({
        'bus': {'transport.type': 'modbus_rtu', 'transport.port': str(workdir / 'rs485'),
                'transport.timeout': 0.05, 'control_rate': 50.0},
        'drives': {f'd{unit}': {'transport.unit_id': unit, 'gear_ratio': 10.0,
                                'auto_enable': True, 'drive_comm_timeout': 1.0,
                                'comm_loss_threshold': 3}
                   for unit in range(1, drives + 1)}})
    bus = Bus(config)
    controllers = list(bus.controllers.values())
    report = Report(drives=drives)
    unplugged: dict[int, float] = {}       # drive index -> plug back at
    pending_faults: dict[int, int] = {}    # drive index -> injected code
    # An injected cause explains an offline drive until it ended plus a grace period
    # (reconnect period and the comm-loss threshold's cycles).
    grace = 2.0
    offline_episode = [False] * drives
    commands = [0.0] * drives
    bus.start()
    start = time.monotonic()
    next_change = next_chaos = start
    explained_until = [start + grace] * drives     # the first connect
    try:
        while (now := time.monotonic()) - start < seconds:
            if now >= next_change:
                for index in range(drives):
                    commands[index] = round(rng.uniform(-3.0, 3.0), 2)
                next_change = now + rng.uniform(0.2, 0.6)
            for index, controller in enumerate(controllers):
                controller.command_velocity(commands[index])
                report.commands_sent += 1
                expected = controller.drive._native_setpoint(commands[index])[0]
                state = controller.state
                if state.online and not state.fault and sims[index].words.get(0xE721) == \
                        expected & 0xFFFF:
                    report.commands_acknowledged += 1
            if now >= next_chaos and now - start < seconds - 3 * grace:   # then cool down
                _chaos(rng, now, sims, line, unplugged, pending_faults, report)
                next_chaos = now + rng.uniform(1.0, 3.0)
            for index, back_at in list(unplugged.items()):
                explained_until[index] = now + grace
                if now >= back_at:
                    sims[index].silent = False
                    del unplugged[index]
            if line.corrupt_rate:
                explained_until = [now + grace] * drives
                if rng.random() < 0.02:
                    line.corrupt_rate = 0.0
            for index, controller in enumerate(controllers):
                state = controller.state
                if state.online:
                    offline_episode[index] = False
                elif now > explained_until[index] and not offline_episode[index]:
                    offline_episode[index] = True
                    report.unexplained.append(f'drive {index + 1} offline at '
                                              f'{now - start:.1f} s: {state.last_error}')
                if state.fault:
                    code = state.active_fault.code
                    if index in pending_faults and code == pending_faults[index]:
                        report.faults_seen += 1
                        sims[index].inject_fault(0)          # the operator fixes the cause
                        del pending_faults[index]
                    if controller.submit('reset_fault').result(timeout=5).success:
                        report.faults_reset += 1
            time.sleep(0.05)
    finally:
        bus.shutdown()
        line.stop()
    for index, controller in enumerate(controllers):
        state = controller.state
        report.reconnects += state.reconnects
        report.bad_frames += state.bad_frames
        report.timeouts += state.timeouts
        if index in pending_faults:
            report.unexplained.append(f'drive {index + 1}: injected fault '
                                      f'{pending_faults[index]} never reported')
    report.seconds = round(time.monotonic() - start, 1)
    return report


def _chaos(rng, now, sims, line, unplugged, pending_faults, report) -> None:
    index = rng.randrange(len(sims))
    event = rng.choice(('fault', 'unplug', 'garbage'))
    if event == 'fault' and index not in pending_faults and index not in unplugged:
        code = rng.choice(sorted(sims[index].profile.faults.table))
        sims[index].inject_fault(code, 1, latched=True)
        pending_faults[index] = code
        report.faults_injected += 1
    elif event == 'unplug' and index not in unplugged and index not in pending_faults:
        sims[index].silent = True
        unplugged[index] = now + rng.uniform(0.3, 2.0)
        report.unplugs += 1
    elif event == 'garbage':
        line.corrupt_rate = rng.uniform(0.02, 0.1)
        report.corruption_bursts += 1


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--drives', type=int, default=4)
    parser.add_argument('--minutes', type=float, default=120.0)
    parser.add_argument('--seed', type=int, default=1)
    parser.add_argument('--json', help='also write the report here')
    args = parser.parse_args(argv)
    report = run(args.drives, args.minutes * 60.0, args.seed)
    text = json.dumps(asdict(report), indent=2)
    print(text)
    if args.json:
        Path(args.json).write_text(text)
    return 1 if report.unexplained else 0


if __name__ == '__main__':
    raise SystemExit(main())
