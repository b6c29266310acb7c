"""The README's demo command runs end to end (real processes, real frames, real DDS).

The demo prints a live table; these tests read the measured wheel speeds from
it and check them against the commands themselves, not the demo's own verdict.
"""

import os
import re
import shutil
import subprocess

NUMBER = r'(-?\d+\.\d+)'
TOLERANCE = 0.1        # rad/s at the end of each step of the profile


def last_rows_per_step(rows: list[tuple]) -> list[tuple]:
    """Return the last printed row of each step (consecutive rows with one command)."""
    last = []
    for row in rows:
        if last and row[0] == last[-1][0]:
            last[-1] = row
        else:
            last.append(row)
    return last


def run_demo(*args: str) -> str:
    """Run the demo executable on loopback DDS; its output, after checking it exited 0."""
    executable = shutil.which('demo')
    assert executable, 'the demo executable is not on PATH (run through scripts/test)'
    env = dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST')
    result = subprocess.run([executable, *args], env=env, capture_output=True, text=True,
                            timeout=90)
    output = result.stdout + result.stderr
    assert result.returncode == 0, output
    return output


def test_demo_drives_both_wheels_through_the_profile():
    output = run_demo()
    assert 'enable left_wheel: enabled' in output and 'stop right_wheel: stopped' in output
    # "  2.1s |    3.00 |    2.99    9.5Hz  0.69A running  |    2.99   -9.5Hz ..."
    pattern = re.compile(rf'^\s*[\d.]+s \|\s+{NUMBER} \|\s+{NUMBER} .*\|\s+{NUMBER} ')
    rows = [tuple(float(v) for v in m.groups()) for line in output.splitlines()
            if (m := pattern.match(line))]
    steps = last_rows_per_step(rows)
    assert [command for command, *_ in steps] == [1.0, 3.0, -2.0, 0.0], output
    for command, left, right in steps:
        assert abs(left - command) <= TOLERANCE and abs(right - command) <= TOLERANCE, output


def test_demo_refuses_to_run_without_loopback_discovery():
    env = {k: v for k, v in os.environ.items() if k != 'ROS_AUTOMATIC_DISCOVERY_RANGE'}
    result = subprocess.run([shutil.which('demo'), '--attach'], env=env, capture_output=True,
                            text=True, timeout=30)
    assert result.returncode == 2 and 'LOCALHOST' in result.stdout


def test_agv_demo_cmd_vel_moves_both_wheels_on_one_line_and_survives_an_unplug():
    """Issue 5's done-when, without ros2 launch: bus_node + diff_drive on one RS-485 line."""
    output = run_demo('--agv')
    # "  7.6s |   0.30   0.00   |    3.00  running  |    3.00  running "
    pattern = re.compile(rf'^\s*[\d.]+s \|\s+{NUMBER}\s+{NUMBER}\s+\|\s+{NUMBER}\s+(\w+)\s+'
                         rf'\|\s+(\S+)\s+(\w+)')
    rows = [(float(m[1]), float(m[2]), float(m[3]), m[4], m[5], m[6])
            for line in output.splitlines() if (m := pattern.match(line))]
    steps = last_rows_per_step([((v, w), left, state_l, right, state_r)
                                for v, w, left, state_l, right, state_r in rows])
    assert [command for command, *_ in steps] == [(0.3, 0.0), (0.2, 0.8), (0.3, 0.0),
                                                  (0.2, -0.4), (0.0, 0.0)], output
    radius, track = 0.1, 0.5
    for index, ((v, w), left, state_l, right, state_r) in enumerate(steps):
        if index == 2:        # the right drive is pulled off the line in this step:
            assert state_r == 'offline', output
            # diff_drive stops the left wheel too (alone it would turn the robot)
            assert abs(left) <= TOLERANCE and state_l == 'running', output
        else:                 # ... and both follow again after, without a service call
            assert abs(left - (v - w * track / 2) / radius) <= TOLERANCE, output
            assert abs(float(right) - (v + w * track / 2) / radius) <= TOLERANCE, output
    assert '1 reconnect(s), fault none' in output


def test_canopen_demo():
    output = run_demo('--canopen')
    assert 'CiA 402 drives on a virtual CAN bus' in output
    assert 'both wheels followed the profile' in output


def test_ethercat_demo():
    """Run demo --ethercat: two simulated HD2 drives on one EtherCAT segment, one bus_node."""
    from ethercat_support import require_segment_support
    require_segment_support()
    output = run_demo('--ethercat')
    assert 'one bus_node serving both' in output
    assert 'both wheels followed the profile' in output
