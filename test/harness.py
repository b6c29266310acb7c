"""Fixtures: a simulated drive on a pty line and the real drive node, in-process.

Everything crosses the real wire format (Modbus RTU frames over a
pseudo-terminal) and real DDS on loopback; each test gets its own rclpy
Context, namespace and line, and waits on conditions with deadlines.
"""

from __future__ import annotations

import threading
import time
import uuid
from typing import Any, Callable

import pytest
import rclpy
from rclpy.context import Context
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, QoSProfile
from std_msgs.msg import Float64
from std_srvs.srv import Trigger

from vfd_ros2.msg import DriveFault, DriveStatus
from vfd_ros2.profiles import load_profile
from vfd_ros2.ros.drive_node import DriveNode
from vfd_ros2.ros.executable import make_executor, spin_in_background
from vfd_ros2.sim.model import SimulatedDrive
from vfd_ros2.sim.rtu_line import LineFaults, SimulatedRtuLine
from vfd_ros2.sim.tcp_server import SimulatedTcpServer


def wait_for(condition: Callable[[], Any], timeout: float = 5.0, what: str = 'condition',
             period: float = 0.01) -> Any:
    """Poll ``condition`` until it returns something truthy; fail after ``timeout``."""
    deadline = time.monotonic() + timeout
    while True:
        result = condition()
        if result:
            return result
        if time.monotonic() > deadline:
            raise AssertionError(f'timed out after {timeout} s waiting for {what}')
        time.sleep(period)


def diagnostic_levels_until_at(client: Any, velocity: float, timeout: float) -> list[int]:
    """Sample ``client.node``'s /diagnostics level every 50 ms until it measures ``velocity``.

    Within 0.1 rad/s; fails if the drive does not get there within ``timeout``.
    """
    levels = []
    deadline = time.monotonic() + timeout
    while abs(client.status.measured_velocity - velocity) >= 0.1:
        assert time.monotonic() < deadline, f'never reached {velocity} rad/s'
        levels.append(client.node.diagnostic_status().level)
        time.sleep(0.05)
    return levels


class DriveClient:
    """The tester's side of one drive node: its topics and services."""

    def __init__(self, context: Context, tester: Node, drive: str) -> None:
        """Subscribe and publish on ``drive``'s topics (e.g. 'drive' or '/ns/drive')."""
        self.context = context
        self.tester = tester
        self.drive_topics = drive
        self.statuses: list[DriveStatus] = []
        self.faults: list[DriveFault] = []
        tester.create_subscription(DriveStatus, f'{drive}/status', self.statuses.append, 50)
        tester.create_subscription(
            DriveFault, f'{drive}/fault', self.faults.append,
            QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL))
        self.velocity_pub = tester.create_publisher(Float64, f'{drive}/velocity_command', 10)
        self._streaming = threading.Event()
        self._stream_value = 0.0
        self._streamer: threading.Thread | None = None

    @property
    def status(self) -> DriveStatus | None:
        return self.statuses[-1] if self.statuses else None

    def wait_status(self, predicate: Callable[[DriveStatus], bool], timeout: float = 5.0,
                    what: str = 'status') -> DriveStatus:
        def check():
            status = self.status
            return status if status is not None and predicate(status) else None
        return wait_for(check, timeout, f'{what} ({self.drive_topics})')

    def publish(self, velocity: float) -> None:
        self.velocity_pub.publish(Float64(data=velocity))

    def stream(self, velocity: float, period: float = 0.05) -> None:
        """Keep publishing ``velocity`` (like a planner) until stop_stream()."""
        self._stream_value = velocity
        if self._streamer is None:
            self._streaming.set()
            self._streamer = threading.Thread(target=self._stream_loop, args=(period,),
                                              daemon=True)
            self._streamer.start()

    def _stream_loop(self, period: float) -> None:
        while self._streaming.is_set() and self.context.ok():
            self.publish(self._stream_value)
            time.sleep(period)

    def stop_stream(self) -> None:
        self._streaming.clear()
        if self._streamer is not None:
            self._streamer.join(1.0)
            self._streamer = None

    def call(self, srv_type: Any, name: str, request: Any, timeout: float = 10.0) -> Any:
        client = self.tester.create_client(srv_type, f'{self.drive_topics}/{name}')
        try:
            assert client.wait_for_service(timeout_sec=5.0), f'service {name} not available'
            future = client.call_async(request)
            wait_for(future.done, timeout, f'reply of {name}')
            return future.result()
        finally:
            self.tester.destroy_client(client)

    def trigger(self, name: str) -> Trigger.Response:
        return self.call(Trigger, name, Trigger.Request())


class DriveHarness(DriveClient):
    """A simulated drive + DriveNode + a tester node (the DriveClient), spinning in a thread."""

    def __init__(self, context: Context, port: str, profile: str = 'boneng_am',
                 sim_initial: dict[str, float] | None = None,
                 node_parameters: dict[str, Any] | None = None,
                 line_faults: LineFaults | None = None,
                 refused: tuple[str, ...] = (), node_class: type = DriveNode) -> None:
        self.profile = load_profile(profile)
        velocity = self.profile.velocity
        initial = {code: 0.5 for code in (velocity.acceleration_time, velocity.deceleration_time)
                   if code}
        initial.update(sim_initial or {})
        self.sim = SimulatedDrive(self.profile, 1, initial)
        self.sim.refuse(list(refused))
        self.transport = self.profile.transports[0]
        if self.transport == 'modbus_tcp':
            self.line = SimulatedTcpServer([self.sim]).start()
            link = {'transport.host': '127.0.0.1', 'transport.port': self.line.port}
        else:
            self.line = SimulatedRtuLine([self.sim], port, faults=line_faults).start()
            link = {'transport.port': port}
        self.namespace = f'/t{uuid.uuid4().hex[:8]}/wheel'
        parameters = {
            'drive.profile': profile, 'transport.type': self.transport, **link,
            'transport.unit_id': 1, 'gear_ratio': 10.0, 'status_rate': 50.0,
            'diagnostics_rate': 5.0, 'stop_timeout': 3.0, 'command_timeout': 0.5,
        }
        parameters.update(node_parameters or {})
        self.node = node_class('drive', namespace=self.namespace, context=context,
                              parameter_overrides=[Parameter(k, value=v)
                                                   for k, v in parameters.items()])
        super().__init__(context, Node('tester', namespace=self.namespace, context=context),
                         'drive')
        self.executor = make_executor(context)
        self.executor.add_node(self.node)
        self.executor.add_node(self.tester)
        self._spin = spin_in_background(self.executor, self.context)

    def wait_cycles(self, count: int = 10, timeout: float = 5.0) -> None:
        """Wait until the drive has answered ``count`` more requests (the loop went on).

        For negative checks ("nothing moved"): a number of control cycles, not a
        time that a slow machine might not fill.
        """
        target = self.sim.requests + count
        wait_for(lambda: self.sim.requests >= target, timeout, f'{count} more requests')

    def frames_after(self, since: float) -> list[bytes]:
        return [frame for stamp, frame in list(self.line.received) if stamp >= since]

    def close(self) -> None:
        self.stop_stream()
        self._spin.stop()
        self.executor.shutdown(timeout_sec=1.0)
        self.node.destroy_node()
        # Every test doubles as a bug catcher: nothing may raise inside the drive loop.
        assert self.node.controller.loop_errors == 0, 'exceptions inside the drive loop'
        self.tester.destroy_node()
        self.line.stop()


@pytest.fixture
def ros_context():
    context = Context()
    rclpy.init(context=context)
    yield context
    rclpy.try_shutdown(context=context)


@pytest.fixture
def make_harness(ros_context, tmp_path):
    """Return a harness factory; it takes profile=, sim_initial= and node_parameters=.

    It waits until the drive is online, unless told ``online=False``.
    """
    made: list[DriveHarness] = []

    def make(online: bool = True, **kwargs: Any) -> DriveHarness:
        harness = DriveHarness(ros_context, str(tmp_path / f'line{len(made)}'), **kwargs)
        made.append(harness)
        if online:
            harness.wait_status(lambda s: s.online, 10.0, 'drive online')
        return harness
    yield make
    for harness in made:
        harness.close()
