"""The topic contract of topic_based_ros2_control, served by the drive nodes of a bus.

ros2_control's ``topic_based_ros2_control/TopicBasedSystem`` hardware plugin
publishes ``sensor_msgs/JointState`` commands on ``joint_commands_topic``
(default /robot_joint_commands; for a velocity command interface the joints'
``name`` and ``velocity`` arrays) and reads ``sensor_msgs/JointState`` from
``joint_states_topic`` (default /robot_joint_states), matching joints by name.
``JointCommandBridge`` is the other end, so a ros2_control system (e.g.
diff_drive_controller) drives the wheels without new C++:

- a command's velocity for a joint goes to that drive's controller through
  ``command_velocity``, exactly as ``~/velocity_command`` does: the command
  watchdog, enable state, fault latch and max_velocity apply; nothing bypasses
  them (a stream that stops lets the watchdog stop the wheel);
- names of other joints are ignored (one robot may have several buses); a
  message whose ``velocity`` array does not match its ``name`` array (e.g. a
  position command interface), that names one of these joints twice or gives one
  a velocity that is not a finite number is refused whole, with a warning: half
  a message applied would turn a differential-drive robot (outside audit: a NaN
  for the left wheel and 1e308 for the right ran the right wheel alone);
- the wheels' states are published together as one JointState at
  ``joint_states_rate`` (position rad, velocity rad/s, effort N·m where
  every wheel measures one).
"""

from __future__ import annotations

import math
from typing import Sequence

from rclpy.node import Node
from sensor_msgs.msg import JointState

from ..control.state import CommandOutcome
from ..errors import ParameterError
from .drive_node import DriveNode
from .messages import joint_state_message


class JointCommandBridge:
    """Joint commands in, aggregated joint states out, for the drive nodes of one node."""

    def __init__(self, node: Node, drives: Sequence[DriveNode], commands_topic: str,
                 states_topic: str, rate: float) -> None:
        """Subscribe to ``commands_topic`` ('' = none), publish on ``states_topic`` ('' = none).

        Raises ParameterError when two drives share a joint name or the rate is not > 0.
        """
        self.node = node
        self.drives: dict[str, DriveNode] = {}
        for drive in drives:
            if drive.joint_name in self.drives:
                raise ParameterError(f'joint name {drive.joint_name!r} is used by two drives: '
                                     'set joint_name on each')
            self.drives[drive.joint_name] = drive
        self.refused = 0
        self.states_pub = None
        if commands_topic:
            node.create_subscription(JointState, commands_topic, self._on_command, 10)
        if states_topic:
            if not (math.isfinite(rate) and rate > 0):
                raise ParameterError(f'joint_states_rate must be > 0, got {rate}')
            self.states_pub = node.create_publisher(JointState, states_topic, 10)
            node.create_timer(1.0 / rate, self._publish_states)

    def _refuse(self, why: str) -> None:
        self.refused += 1
        self.node.get_logger().warning(f'joint command refused: {why} ({self.refused} so far)',
                                       throttle_duration_sec=1.0)

    def _on_command(self, msg: JointState) -> None:
        try:
            if len(msg.velocity) != len(msg.name):
                self._refuse(f'{len(msg.name)} names but {len(msg.velocity)} velocities: '
                             'the wheels take a velocity command interface only')
                return
            ours = [(name, velocity) for name, velocity in zip(msg.name, msg.velocity)
                    if name in self.drives]      # (the others: another bus's joints)
            names = [name for name, _ in ours]
            twice = sorted({name for name in names if names.count(name) > 1})
            if twice:
                self._refuse(f'{", ".join(twice)} named more than once: none applied')
                return
            bad = [f'{name}: velocity {velocity}' for name, velocity in ours
                   if not math.isfinite(velocity)]
            if bad:
                self._refuse(f'{"; ".join(bad)} is not a finite number: none applied')
                return
            for name, velocity in ours:
                outcome = self.drives[name].controller.command_velocity(float(velocity))
                if outcome is CommandOutcome.REJECTED:      # (checked above: not expected)
                    self._refuse(f'{name}: velocity {velocity} is not a finite number')
        except Exception as exc:  # noqa: BLE001 - never raise into the executor
            self.node.get_logger().error(f'joint command failed: {exc}',
                                         throttle_duration_sec=1.0)

    def _publish_states(self) -> None:
        try:
            stamp = self.node.get_clock().now().to_msg()
            joints = [(name, drive.controller.state) for name, drive in self.drives.items()]
            self.states_pub.publish(joint_state_message(joints, stamp))
        except Exception as exc:  # noqa: BLE001
            self.node.get_logger().error(f'joint states failed: {exc}',
                                         throttle_duration_sec=5.0)
