"""Fixtures: simulated CANopen drives on a python-can virtual bus and real drive nodes.

The CAN variant of ``harness.py``: every frame crosses python-can's in-process
``virtual`` bus (SDO, PDO, NMT, heartbeat, EMCY), the nodes are the real
``DriveNode`` on real DDS (loopback); waits are conditions with deadlines.
"""

from __future__ import annotations

import threading
import time
import uuid
from typing import Any, Callable

import pytest
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, QoSProfile
from std_msgs.msg import Float64
from std_srvs.srv import Trigger

from harness import wait_for
from vfd_ros2.msg import DriveFault, DriveStatus
from vfd_ros2.node import DriveNode
from vfd_ros2.profile import load_profile
from vfd_ros2.sim.canopen_drive import SimulatedCanBus, SimulatedCanopenDrive


class CanWheel:
    """One DriveNode plus the tester's view of it."""

    def __init__(self, harness: 'CanHarness', node_id: int, parameters: dict[str, Any]) -> None:
        self.harness = harness
        self.node_id = node_id
        self.namespace = f'/t{uuid.uuid4().hex[:8]}/wheel{node_id}'
        self.node = DriveNode('drive', namespace=self.namespace, context=harness.context,
                              parameter_overrides=[Parameter(k, value=v)
                                                   for k, v in parameters.items()])
        tester = harness.tester
        self.statuses: list[DriveStatus] = []
        self.faults: list[DriveFault] = []
        tester.create_subscription(DriveStatus, f'{self.namespace}/drive/status',
                                   self.statuses.append, 50)
        tester.create_subscription(
            DriveFault, f'{self.namespace}/drive/fault', self.faults.append,
            QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL))
        self.velocity_pub = tester.create_publisher(
            Float64, f'{self.namespace}/drive/velocity_command', 10)
        self._streaming = threading.Event()
        self._streamer: threading.Thread | None = None
        self._stream_value = 0.0

    @property
    def status(self) -> DriveStatus | None:
        return self.statuses[-1] if self.statuses else None

    def wait_status(self, predicate: Callable[[DriveStatus], bool], timeout: float = 5.0,
                    what: str = 'status') -> DriveStatus:
        def check():
            status = self.status
            return status if status is not None and predicate(status) else None
        return wait_for(check, timeout, f'{what} (node {self.node_id})')

    def stream(self, velocity: float, period: float = 0.05) -> None:
        self._stream_value = velocity
        if self._streamer is None:
            self._streaming.set()
            self._streamer = threading.Thread(target=self._stream_loop, args=(period,),
                                              daemon=True)
            self._streamer.start()

    def _stream_loop(self, period: float) -> None:
        while self._streaming.is_set() and self.harness.context.ok():
            self.velocity_pub.publish(Float64(data=self._stream_value))
            time.sleep(period)

    def stop_stream(self) -> None:
        self._streaming.clear()
        if self._streamer is not None:
            self._streamer.join(1.0)
            self._streamer = None

    def call(self, srv_type: Any, name: str, request: Any, timeout: float = 10.0) -> Any:
        client = self.harness.tester.create_client(srv_type, f'{self.namespace}/drive/{name}')
        try:
            assert client.wait_for_service(timeout_sec=5.0), f'service {name} not available'
            future = client.call_async(request)
            wait_for(future.done, timeout, f'reply of {name}')
            return future.result()
        finally:
            self.harness.tester.destroy_client(client)

    def trigger(self, name: str) -> Trigger.Response:
        return self.call(Trigger, name, Trigger.Request())


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
        self.executor = SingleThreadedExecutor(context=context)
        self.executor.add_node(self.tester)
        self.wheels: dict[int, CanWheel] = {}
        for node_id in node_ids:
            parameters = {
                'drive.profile': profile, 'transport.type': 'canopen',
                'transport.interface': 'virtual', 'transport.channel': self.channel,
                'transport.unit_id': node_id, 'transport.object_set': object_set,
                'gear_ratio': 10.0, 'status_rate': 50.0, 'diagnostics_rate': 5.0,
                'stop_timeout': 3.0, 'command_timeout': 0.5, 'reconnect_period': 0.2,
            }
            parameters.update(node_parameters or {})
            wheel = CanWheel(self, node_id, parameters)
            self.executor.add_node(wheel.node)
            self.wheels[node_id] = wheel
        self._spin = threading.Thread(target=self._spin_loop, daemon=True)
        self._spin.start()

    def _spin_loop(self) -> None:
        while self.context.ok():
            try:
                self.executor.spin_once(timeout_sec=0.05)
            except Exception:  # noqa: BLE001 - context shut down under us
                if not self.context.ok():
                    return
                raise

    def close(self) -> None:
        for wheel in self.wheels.values():
            wheel.stop_stream()
            self.executor.remove_node(wheel.node)
            wheel.node.destroy_node()
        self.tester.destroy_node()
        self.executor.shutdown(timeout_sec=1.0)
        self.bus.stop()


@pytest.fixture(name='make_can_harness')
def can_harness_factory(ros_context):
    """Return a factory: profile=, node_ids=, sim_initial=, node_parameters=, object_set=."""
    made: list[CanHarness] = []

    def make(**kwargs: Any) -> CanHarness:
        harness = CanHarness(ros_context, **kwargs)
        made.append(harness)
        for wheel in harness.wheels.values():
            wheel.wait_status(lambda s: s.online, 10.0, 'drive online')
        return harness
    yield make
    for harness in made:
        harness.close()
