"""Fixtures: simulated CANopen drives on a python-can virtual bus and real drive nodes.

The CAN variant of ``harness.py``: every frame crosses python-can's in-process
``virtual`` bus (SDO, PDO, NMT, heartbeat, EMCY), the nodes are the real
``DriveNode`` on real DDS (loopback); waits are conditions with deadlines.
"""

from __future__ import annotations

import uuid
from typing import Any

import pytest
from rclpy.context import Context
from rclpy.node import Node
from rclpy.parameter import Parameter

from harness import DriveClient
from vfd_ros2.profiles import load_profile
from vfd_ros2.ros.drive_node import DriveNode
from vfd_ros2.ros.executable import make_executor, spin_in_background
from vfd_ros2.sim.canopen_drive import SimulatedCanBus, SimulatedCanopenDrive


class CanWheel(DriveClient):
    """One DriveNode plus the tester's view of it."""

    def __init__(self, harness: 'CanHarness', node_id: int, parameters: dict[str, Any]) -> None:
        self.harness = harness
        self.node_id = node_id
        self.namespace = f'/t{uuid.uuid4().hex[:8]}/wheel{node_id}'
        self.node = DriveNode('drive', namespace=self.namespace, context=harness.context,
                              parameter_overrides=[Parameter(k, value=v)
                                                   for k, v in parameters.items()])
        super().__init__(harness.context, harness.tester, f'{self.namespace}/drive')


class CanHarness:
    """Simulated drives on one virtual CAN channel + one DriveNode per drive."""

    def __init__(self, context: Context, profile: str = 'cia402_velocity',
                 node_ids: tuple[int, ...] = (1,), sim_initial: dict[str, float] | None = None,
                 node_parameters: dict[str, Any] | None = None, object_set: str = '') -> None:
        self.context = context
        self.profile = load_profile(profile)
        self.channel = f'vfd{uuid.uuid4().hex[:8]}'
        self.sims = {node_id: SimulatedCanopenDrive(self.profile, node_id, object_set,
                                                    sim_initial)
                     for node_id in node_ids}
        self.bus = SimulatedCanBus(list(self.sims.values()), self.channel).start()
        self.tester = Node('tester', namespace=f'/t{uuid.uuid4().hex[:8]}', context=context)
        self.executor = make_executor(context)
        self.executor.add_node(self.tester)
        self.wheels: dict[int, CanWheel] = {}
        for node_id in node_ids:
            parameters = {
                'drive.profile': profile, 'transport.type': 'canopen',
                'transport.interface': 'virtual', 'transport.channel': self.channel,
                'transport.unit_id': node_id, 'drive.object_set': object_set,
                'gear_ratio': 10.0, 'status_rate': 50.0, 'diagnostics_rate': 5.0,
                'stop_timeout': 3.0, 'command_timeout': 0.5, 'reconnect_period': 0.2,
            }
            parameters.update(node_parameters or {})
            wheel = CanWheel(self, node_id, parameters)
            self.executor.add_node(wheel.node)
            self.wheels[node_id] = wheel
        self._spin = spin_in_background(self.executor, self.context)

    def close(self) -> None:
        for wheel in self.wheels.values():
            wheel.stop_stream()
        self._spin.stop()
        self.executor.shutdown(timeout_sec=1.0)
        for wheel in self.wheels.values():
            wheel.node.destroy_node()
        self.tester.destroy_node()
        self.bus.stop()


@pytest.fixture(name='make_can_harness')
def can_harness_factory(ros_context):
    """Return a factory: profile=, node_ids=, sim_initial=, node_parameters=, object_set=."""
    made: list[CanHarness] = []

    def make(online: bool = True, **kwargs: Any) -> CanHarness:
        harness = CanHarness(ros_context, **kwargs)
        made.append(harness)
        for wheel in harness.wheels.values() if online else ():
            wheel.wait_status(lambda s: s.online, 10.0, 'drive online')
        return harness
    yield make
    for harness in made:
        harness.close()
