"""Several drive_nodes in one process, each with its own control thread.

The bench's previous CANopen design (a robot would start them from one launch file).
Run as a child by ``bench.cases.DriverProcess``: reads ``drive_nodes.yaml`` (a list
of ``{namespace, parameters}``) from the working directory, spins every node in one
executor until SIGTERM, then destroys them (each commands its drive to stop).
"""

from __future__ import annotations

import sys
from pathlib import Path

import rclpy
import yaml
from rclpy.executors import ExternalShutdownException
from rclpy.parameter import Parameter

from vfd_ros2.ros.drive_node import DriveNode
from vfd_ros2.ros.executable import (
    GIL_SWITCH_INTERVAL,
    make_executor,
    settle_heap,
    spin_until_shutdown,
)

SPEC_FILE = 'drive_nodes.yaml'


def main() -> int:
    sys.setswitchinterval(GIL_SWITCH_INTERVAL)      # as every vfd_ros2 executable
    spec = yaml.safe_load(Path(SPEC_FILE).read_text())
    rclpy.init()
    nodes: list[DriveNode] = []
    executor = make_executor()
    try:
        for item in spec:
            nodes.append(DriveNode('drive', namespace=item['namespace'], parameter_overrides=[
                Parameter(key, value=value) for key, value in item['parameters'].items()]))
            executor.add_node(nodes[-1])
        settle_heap()
        spin_until_shutdown(executor, nodes[0].context)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        executor.shutdown(timeout_sec=1.0)
        for node in nodes:
            node.destroy_node()
        rclpy.try_shutdown()
    return 0
