"""The driver's Python logging reaches ROS logging (/rosout) through the executables."""

from __future__ import annotations

import logging

from rcl_interfaces.msg import Log
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile

from harness import wait_for
from vfd_ros2.ros.executable import RosLogBridge, spin_in_background


def test_a_drive_going_offline_is_on_rosout_at_its_level(ros_context):
    """The layers below ROS (link, controller, transports) log with Python logging.

    Their records went to stderr unformatted (INFO not at all) and never to /rosout:
    rqt_console and a robot's log recorder did not see a drive go offline.
    """
    node = Node('drive', namespace='/log_bridge_test', context=ros_context)
    tester = Node('tester', context=ros_context)
    heard: list[Log] = []
    tester.create_subscription(Log, '/rosout', heard.append, QoSProfile(
        depth=100, durability=DurabilityPolicy.TRANSIENT_LOCAL))
    executor = SingleThreadedExecutor(context=ros_context)
    executor.add_node(tester)
    spin = spin_in_background(executor, ros_context)
    python_logger = logging.getLogger('vfd_ros2')
    before = (python_logger.level, python_logger.propagate)
    bridge = RosLogBridge(node)
    try:
        logging.getLogger('vfd_ros2.control.link').warning('%s offline: %s', 'drive x', 'no reply')
        logging.getLogger('vfd_ros2.control.link').info('drive x online')
        logging.getLogger('vfd_ros2.control.link').debug('not shown at INFO')

        def from_node() -> list[tuple[int, str]]:
            return [(m.level, m.msg) for m in heard if m.name == node.get_logger().name]
        wait_for(lambda: len(from_node()) >= 2, 5.0, 'both records on /rosout')
        assert from_node() == [(Log.WARN, 'drive x offline: no reply'),
                               (Log.INFO, 'drive x online')]
    finally:
        bridge.remove()
        spin.stop()
        executor.shutdown(timeout_sec=1.0)
        node.destroy_node()
        tester.destroy_node()
    assert (python_logger.level, python_logger.propagate) == before
    assert bridge not in python_logger.handlers
