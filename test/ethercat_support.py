"""Helpers for EtherCAT tests: skip reasons and SOEM process-data loops with deadlines."""

from __future__ import annotations

import time
from typing import Any, Callable

import pytest

from vfd_ros2.transports import netns

try:
    import pysoem
except ImportError:          # the codec tests run without it
    pysoem = None


def require_segment_support() -> None:
    reason = netns.namespace_support()
    if reason:
        pytest.skip(f'EtherCAT segment tests need network namespaces: {reason}')


def exchange(master: Any) -> int:
    """One process-data cycle; returns the working counter."""
    master.send_processdata()
    return master.receive_processdata(2000)


def cycle_until(master: Any, condition: Callable[[], Any], timeout: float, what: str,
                period: float = 0.002) -> Any:
    """Exchange process data every ``period`` until ``condition()`` is truthy."""
    deadline = time.monotonic() + timeout
    while True:
        exchange(master)
        result = condition()
        if result:
            return result
        if time.monotonic() > deadline:
            raise AssertionError(f'timed out after {timeout} s waiting for {what}')
        time.sleep(period)


def bring_to_op(master: Any, timeout: float = 3.0) -> int:
    """Map, reach SAFE-OP, exchange outputs, request OP; return the expected WKC."""
    master.config_map()
    assert master.state_check(pysoem.SAFEOP_STATE, 500_000) == pysoem.SAFEOP_STATE, [
        (s.state, hex(s.al_status)) for s in master.slaves]
    master.state = pysoem.OP_STATE
    master.write_state()
    cycle_until(master, lambda: master.state_check(pysoem.OP_STATE, 1000) == pysoem.OP_STATE,
                timeout, 'all slaves in OP')
    return master.expected_wkc
