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
    bridge = RosLogBridge()       # as run_node: before the node (a loop may start in it)
    try:
        link_log = logging.getLogger('vfd_ros2.control.link')
        link_log.warning('drive x: connect failed: %s', 'cannot open /dev/ttyUSB0')  # held
        bridge.attach(node)
        link_log.warning('%s offline: %s', 'drive x', 'no reply')
        link_log.info('drive x online')
        link_log.debug('not shown at INFO')

        def from_node() -> list[tuple[int, str]]:
            return [(m.level, m.msg) for m in heard if m.name == node.get_logger().name]
        wait_for(lambda: len(from_node()) >= 3, 5.0, 'the records on /rosout')
        assert from_node() == [(Log.WARN, 'drive x: connect failed: cannot open /dev/ttyUSB0'),
                               (Log.WARN, 'drive x offline: no reply'),
                               (Log.INFO, 'drive x online')]
    finally:
        bridge.remove()
        spin.stop()
        executor.shutdown(timeout_sec=1.0)
        node.destroy_node()
        tester.destroy_node()
    assert (python_logger.level, python_logger.propagate) == before
    assert bridge not in python_logger.handlers


def test_records_held_for_a_node_that_never_came_go_to_stderr(capsys):
    """A node refused at start: what its layers logged meanwhile is not lost."""
    bridge = RosLogBridge()
    logging.getLogger('vfd_ros2.drives.modbus').warning('C02.04 refused')
    bridge.remove()
    assert '[WARN] C02.04 refused' in capsys.readouterr().err


def test_records_after_the_context_shut_down_go_to_stderr(capfd):
    """Ctrl-C shut the context down while a drive's loop still logs its last words.

    ROS logging printed them, and with each a "Failed to publish log message to
    rosout" line: they go to stderr in the console's form, without it.
    """
    import rclpy
    from rclpy.context import Context

    context = Context()
    rclpy.init(context=context)
    node = Node('drive', namespace='/log_bridge_shutdown', context=context)
    bridge = RosLogBridge()
    try:
        bridge.attach(node)
        context.try_shutdown()
        logging.getLogger('vfd_ros2.control.controller').warning('could not stop %s', 'x')
    finally:
        bridge.remove()
        node.destroy_node()
    err = capfd.readouterr().err
    assert '[WARN] [log_bridge_shutdown.drive]: could not stop x' in err, err
    assert 'rosout' not in err, err
