"""Fixtures for EtherCAT tests: a veth pair in a fresh namespace, a simulated segment, SOEM.

Everything runs inside a namespace the test creates (both veth ends live there);
the finalisers stop the segment's process and delete the namespace even when a
test fails. Tests skip, saying why, where namespaces or pysoem are unavailable.
Load with ``pytest_plugins = ['ethercat_harness']``.
"""

from __future__ import annotations

from typing import Any, Sequence

import pytest

from ethercat_support import pysoem, require_segment_support
from vfd_ros2.sim.ethercat.drive import DriveSpec
from vfd_ros2.sim.ethercat.segment import SimulatedSegment
from vfd_ros2.transports import netns


@pytest.fixture
def veth_link() -> Any:
    """Create a namespace with a veth pair; delete it afterwards, whatever happened."""
    require_segment_support()
    link = netns.create_veth_link('test')
    try:
        yield link
    finally:
        netns.destroy_veth_link(link)


@pytest.fixture
def start_segment(veth_link: netns.VethLink) -> Any:
    """``start_segment(specs)`` -> a running ``SimulatedSegment``; stopped afterwards."""
    segments: list[SimulatedSegment] = []

    def start(specs: Sequence[DriveSpec]) -> SimulatedSegment:
        segment = SimulatedSegment(veth_link, specs)
        segments.append(segment)
        return segment

    try:
        yield start
    finally:
        for segment in segments:
            segment.close()


@pytest.fixture
def soem_master(veth_link: netns.VethLink) -> Any:
    """Open a pysoem Master on the master's veth end (inside the test namespace)."""
    if pysoem is None:
        pytest.skip('pysoem is not installed (pip install pysoem)')
    master = pysoem.Master()
    netns.run_in_namespace(veth_link.namespace, master.open, veth_link.master_interface)
    try:
        yield master
    finally:
        master.close()
