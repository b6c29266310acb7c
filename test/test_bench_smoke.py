"""The benchmark runs: its cheapest --quick case, in-process, writes sane JSON.

Speed is measured by ``scripts/bench``, never asserted here: these checks are
about shape and sanity only (counts add up, no errors, positive rates).
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
if str(ROOT) not in sys.path:
    sys.path.append(str(ROOT))   # after the colcon install: vfd_ros2 comes from there

from bench import run  # noqa: E402
from bench.report import render_table  # noqa: E402

FLOOR_KEYS = {'profile', 'stack', 'level', 'transactions', 'errors', 'transactions_per_s',
              'us_per_transaction', 'cpu_us_per_transaction'}


def test_quick_software_floor_writes_json(tmp_path):
    output = tmp_path / 'latest.json'
    markdown = tmp_path / 'RESULTS.md'
    assert run.main(['--quick', '--only', 'software_floor', '--case', 'floor vfd_ros2',
                     '--case', 'floor pymodbus', '--output', str(output),
                     '--markdown', str(markdown)]) == 0
    results = json.loads(output.read_text())
    assert results['meta']['mode'] == 'quick'
    assert results['meta']['command'] == 'scripts/bench --quick'
    rows = results['software_floor']
    assert [row['stack'] for row in rows] == ['vfd_ros2', 'pymodbus']
    for row in rows:
        assert FLOOR_KEYS <= set(row), row
        assert row['errors'] == 0
        assert row['transactions'] > 0
        assert row['transactions_per_s'] > 0
        assert row['us_per_transaction'] > 0
        # Counts add up: every cycle wrote the setpoint and read at least the fast block.
        assert row['transactions'] >= 2 * row['cycles']
    assert 'Software floor' in markdown.read_text()
    assert '## Performance' in markdown.read_text()


def test_table_renders_every_section_and_errors():
    results = {
        'meta': {'mode': 'quick'},
        'bus_efficiency': [{'case': 'x', 'error': 'RuntimeError: boom'}],
        'command_latency': [],
        'canopen': {'skipped': 'not importable'},
        'cpu': [],
    }
    table = render_table(results)
    assert 'error: RuntimeError: boom' in table
    assert 'CANopen**: skipped' in table


def test_a_partial_run_merged_into_an_earlier_one_says_when(tmp_path):
    earlier = tmp_path / 'earlier.json'
    earlier.write_text(json.dumps({
        'meta': {'mode': 'full', 'date': '2026-01-01T00:00:00+00:00'},
        'software_floor': [{'case': 'old floor', 'error': 'RuntimeError: earlier'}],
        'command_latency': [{'case': 'old latency', 'error': 'RuntimeError: earlier'}],
    }))
    output, markdown = tmp_path / 'latest.json', tmp_path / 'RESULTS.md'
    assert run.main(['--quick', '--only', 'software_floor', '--case', 'floor vfd_ros2',
                     '--merge-into', str(earlier), '--output', str(output),
                     '--markdown', str(markdown)]) == 0
    merged = json.loads(output.read_text())
    assert merged['command_latency'] == [{'case': 'old latency',
                                          'error': 'RuntimeError: earlier'}]
    assert [row['stack'] for row in merged['software_floor']] == ['vfd_ros2']
    assert merged['meta']['date'] == '2026-01-01T00:00:00+00:00'
    [again] = merged['meta']['remeasured']
    assert again['sections'] == ['software_floor']
    assert f"re-measured {again['date']}: software_floor" in markdown.read_text()


def test_the_io_floor_sends_the_drives_cycles_at_their_pace():
    """The I/O alone: each drive's setpoint write and due reads, 50 cycles/s, all answered."""
    from bench import cases
    row = cases.io_floor('boneng_am', 2, 1.0, control_rate=50.0)
    assert 40 <= row['approx_cycles_per_s'] <= 51, row
    # 2 drives x (1 write + 3 reads, the shown-only state block every 2nd cycle at a
    # 20 Hz status, 2 slow reads every 5th cycle) = 9.8 per cycle, as the driver reads
    per_cycle = row['transactions_per_s'] / row['approx_cycles_per_s']
    assert abs(per_cycle - 9.8) < 0.4, row
    assert 0 < row['cpu_percent'] < 100, row
    assert 'the same I/O alone, no driver' in render_table({'cpu': [dict(row, case='x')]})


def test_interpreted_steps_count_the_cycles_python_and_name_where_it_goes():
    from bench import cases
    row = cases.interpreted_steps('boneng_am', 2, cycles=10)
    # A cycle runs thousands of bytecode steps per drive (8-9k on 2026-11-24); 0 or a
    # few would mean the trace saw nothing, 10x more that it counted the simulator.
    assert 2000 < row['steps_per_drive_cycle'] < 40000, row
    names = [name for name, _ in row['top']]
    assert any(name.startswith('transports/rtu_link.py:') for name in names), names
    assert 'Interpreted steps' in render_table({'steps': [dict(row, case='x')]})


def test_the_cpu_case_runs_a_drive_node_of_its_own():
    """The single-drive CPU row: a drive_node process, fed commands, cycling at 50 Hz."""
    from bench import cases
    row = cases.cpu_usage('boneng_am', 1, 1.0, node='drive_node')
    assert row['node'] == 'drive_node'
    # (the rate is taken between the stamps of two ~/status, so it is the drive's own;
    # a busy test host may still make the loop overrun a few cycles)
    assert 40 <= row['approx_cycles_per_s'] <= 55, row
    assert row['comm_errors'] == 0 and 0 < row['cpu_percent'] < 100, row
    assert 'EventsExecutor, a drive_node' in render_table({'cpu': [dict(row, case='x')]})


def test_the_cpu_case_slows_the_ros_traffic_around_the_same_cycle():
    """Status at 1 Hz, commands at 2 Hz: the drive keeps running and cycling at 50 Hz.

    Its cycle rate comes from the status stamps: counts that arrive once a second,
    divided by a 1.5 s window, would say 33 or 67 cycles/s (one or two seconds'
    worth).
    """
    from bench import cases
    row = cases.cpu_usage('boneng_am', 1, 1.5, node='drive_node', status_rate=1.0,
                          command_rate=2.0)
    assert (row['status_rate_hz'], row['command_rate_hz']) == (1.0, 2.0)
    assert 40 <= row['approx_cycles_per_s'] <= 55, row
    assert row['comm_errors'] == 0, row
    assert 'a drive_node, status 1 Hz, commands 2 Hz' in \
        render_table({'cpu': [dict(row, case='x')]})


def test_the_wake_cost_case_times_first_and_following_messages():
    """Section 5's note: a DriveStatus built and published after a sleep, then nine more."""
    from bench import cases
    row = cases.wake_cost(samples=3, pause=0.01)
    figures = [row[f'{kind}_{which}_us'] for kind in ('message', 'publish')
               for which in ('first', 'following')]
    # Each is a thread's CPU time for real work: never zero, never a second.
    assert all(0 < value < 1e6 for value in figures), row
    cpu_row = {'profile': 'boneng_am', 'drives': 1, 'executor': 'events', 'cpu_percent': 6.0,
               'cpu_percent_per_drive': 6.0, 'approx_cycles_per_s': 50.0,
               'transactions_per_s': 270.0, 'rss_mb': 95.0, 'target_percent_per_drive': 5.0}
    table = render_table({'cpu': [dict(cpu_row, case='x'), dict(row, case='y')]})
    assert f"another process) {row['publish_first_us']:g} µs;" in table, table
    assert table.count('EventsExecutor') == 1, table     # the note is not a table row
