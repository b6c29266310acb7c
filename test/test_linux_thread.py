"""What a timing-sensitive thread asks Linux for, and that asking never forks."""

from __future__ import annotations

import ctypes
import subprocess
import threading
from pathlib import Path

from vfd_ros2.protocol.linux_thread import name_os_thread, tighten_timer_slack

_PR_GET_TIMERSLACK = 30


def test_a_thread_is_tuned_and_named_without_starting_a_process(monkeypatch):
    # A fork while another thread holds a serial port open hands the child the
    # port's exclusive lock until its exec: a reopen then fails (seen in a full run).
    started = []

    class NoProcess(subprocess.Popen):
        def __init__(self, args, *more, **options):
            started.append(args)
            raise OSError('no process may be started here')
    monkeypatch.setattr(subprocess, 'Popen', NoProcess)
    seen = {}

    def tuned():
        tighten_timer_slack()
        name_os_thread('vfd-tuned-thread')     # cut to 15 bytes, as Linux keeps them
        seen['slack_ns'] = ctypes.CDLL(None).prctl(_PR_GET_TIMERSLACK, 0, 0, 0, 0)
        seen['name'] = Path('/proc/thread-self/comm').read_text().strip()
    thread = threading.Thread(target=tuned)
    thread.start()
    thread.join(5)
    assert started == []
    assert seen == {'slack_ns': 1000, 'name': 'vfd-tuned-threa'}
