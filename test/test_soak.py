"""A short run of the on-demand soak test: the report adds up and nothing is unexplained."""

import importlib.util
import sys
from pathlib import Path


def test_short_soak_has_no_unexplained_losses():
    path = Path(__file__).resolve().parents[1] / 'scripts' / 'soak.py'
    spec = importlib.util.spec_from_file_location('soak', path)
    soak = importlib.util.module_from_spec(spec)
    sys.modules['soak'] = soak          # dataclasses look their module up
    spec.loader.exec_module(soak)
    report = soak.run(drives=2, seconds=12.0, seed=3)
    assert report.unexplained == []
    assert report.commands_sent > 200
    assert report.commands_acknowledged > report.commands_sent * 0.5
    assert report.faults_seen == report.faults_injected   # each reported with its code
    assert report.faults_injected + report.unplugs + report.corruption_bursts + \
        report.late_reply_bursts + report.wrong_echo_bursts >= 3
