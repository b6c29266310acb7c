"""Test-wide setup: DDS stays on loopback, or nothing runs."""

import os
import threading
import time

import pytest

if os.environ.get('ROS_AUTOMATIC_DISCOVERY_RANGE') != 'LOCALHOST':
    pytest.exit(
        'ROS_AUTOMATIC_DISCOVERY_RANGE must be LOCALHOST: DDS discovery must not leave this '
        'machine. Run the tests with scripts/test (it sets it), or export it yourself.',
        returncode=4)

pytest_plugins = ['harness', 'plugin_support']


def _open_fds() -> set[tuple[str, str]]:
    """Return (fd, what it points at): a closed and reused number is not the same file."""
    fds = set()
    for fd in os.listdir('/proc/self/fd'):
        try:
            fds.add((fd, os.readlink(f'/proc/self/fd/{fd}')))
        except OSError:
            pass      # the listing's own descriptor, or closed meanwhile
    return fds


@pytest.fixture(scope='session', autouse=True)
def _dds_warmed_up():
    """Create the process-wide sockets and pipes once, so no test is blamed for them.

    DDS keeps shared sockets after the first participant; multiprocessing starts
    one resource tracker (a pipe) for the first spawned process (the simulated
    EtherCAT segment runs in one).
    """
    import multiprocessing.resource_tracker
    multiprocessing.resource_tracker.ensure_running()
    import rclpy
    from rclpy.context import Context
    context = Context()
    rclpy.init(context=context)
    node = rclpy.create_node('warm_up', context=context)
    node.destroy_node()
    rclpy.try_shutdown(context=context)
    yield


@pytest.fixture(autouse=True)
def _no_leaks(request):
    """Fail a test that leaves a thread running or a file descriptor open behind it."""
    threads_before = {thread.ident for thread in threading.enumerate()}
    fds_before = _open_fds()
    yield
    deadline = time.monotonic() + 3.0
    while True:
        threads = [t for t in threading.enumerate()
                   if t.ident not in threads_before and t.is_alive()]
        fds = _open_fds() - fds_before
        if not (threads or fds) or time.monotonic() > deadline:
            break
        time.sleep(0.02)
    targets = sorted(target for _, target in fds)
    assert not threads and not targets, (
        f'{request.node.nodeid} leaked threads {sorted(t.name for t in threads)} and '
        f'file descriptors {targets}')
