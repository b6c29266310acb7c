"""diff_drive: cmd_vel -> two wheel drive nodes, wheel positions (or speeds) -> odom.

Topics (relative names resolve in the node's namespace):
  cmd_vel                  geometry_msgs/TwistStamped (use_stamped_vel true, the default, as
                           Jazzy's diff_drive_controller) or geometry_msgs/Twist (false)
                                                   in: m/s (linear.x), rad/s (angular.z)
  <left/right>_wheel_command_topic   std_msgs/Float64   out at publish_rate: rad/s at the wheel
  <left/right>_wheel_status_topic    vfd_ros2/DriveStatus  in: measured_velocity, online
  <left/right>_wheel_joint_states_topic  sensor_msgs/JointState  in: the wheel's position
                           (its joint named by <left/right>_wheel_joint_name, or the only one)
  odom                     nav_msgs/Odometry       out at publish_rate: header.frame_id =
                                                   odom_frame, child_frame_id = base_frame
  /tf                      tf2_msgs/TFMessage      out with publish_tf (needs tf2_msgs)

Frames and units follow REP 103/105: the pose of base_frame in odom_frame, the
twist in base_frame, metres, radians, seconds.

Command timeout: without a valid cmd_vel for cmd_vel_timeout the target twist
becomes zero (ramped down within the acceleration limits, as ros2_controllers'
diff_drive_controller does) and zero wheel commands keep being published. The
drive nodes are fed on purpose: they hold zero speed, enabled and ready, instead
of tripping their own watchdog (which would need nothing to restart, but makes
each drive report watchdog_tripped). Their watchdogs still stop the wheels if
this node dies or its link breaks.

A stamped command older than cmd_vel_timeout (header.stamp against this node's
clock) is rejected and counted: it never starts the wheels, so a command queued
behind a network stall cannot move the robot late. So is one stamped more than
cmd_vel_timeout ahead (its sender's clock is off: its age would never tell). A
zero stamp is taken as "now", as diff_drive_controller does.

One wheel that does not follow its commands (its status stale or missing, its drive
offline, faulted, disabled, stopped, blocked or tripped) would turn the robot about it
at the commanded speed: both wheels are then commanded to zero, within the
acceleration limits, until both follow again (logged once per cause).

Odometry never uses the commands. With position_feedback (the default, as
diff_drive_controller) the pose follows the wheels' JointState positions (the
drive's own counter where the profile has one, else the speed the drive node
integrates each control cycle) and the twist their measured speeds; while a
wheel's JointState is missing or stale, the measured speeds
(DriveStatus.measured_velocity) are integrated instead. While a wheel's status
is older than wheel_status_timeout, offline or NaN, the pose is held and the
twist is reported as zero with a large covariance.
"""

from __future__ import annotations

import math
from typing import Any

from geometry_msgs.msg import TransformStamped, Twist, TwistStamped
from nav_msgs.msg import Odometry
from rclpy.node import Node
from rclpy.time import Time
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64

from vfd_ros2.msg import DriveStatus

from ..control.diff_drive import (
    DiffDriveKinematics,
    OdometryIntegrator,
    RateLimiter,
    VelocityLimits,
)
from ..errors import ParameterError
from .executable import only_ros_arguments, run_node
from .parameters import LiveParameters, check_value, descriptor

#: s between two looks for cmd_vel publishers of the other twist type
CMD_VEL_TYPE_CHECK_PERIOD = 2.0

#: name, default, description, minimum, maximum, live (applied at once when set)
PARAMETERS: tuple[tuple[str, Any, str, float | None, float | None, bool], ...] = (
    ('wheel_radius', 0.1, 'm, rolling radius of the drive wheels', 0.001, 10.0, False),
    ('track_width', 0.5, 'm between the wheel contact points', 0.01, 100.0, False),
    ('left_wheel_command_topic', 'left_wheel/drive/velocity_command',
     'std_msgs/Float64 out: left wheel rad/s', None, None, False),
    ('right_wheel_command_topic', 'right_wheel/drive/velocity_command',
     'std_msgs/Float64 out: right wheel rad/s', None, None, False),
    ('left_wheel_status_topic', 'left_wheel/drive/status',
     'vfd_ros2/DriveStatus in: left wheel measured_velocity', None, None, False),
    ('right_wheel_status_topic', 'right_wheel/drive/status',
     'vfd_ros2/DriveStatus in: right wheel measured_velocity', None, None, False),
    ('left_wheel_joint_states_topic', 'left_wheel/joint_states',
     'sensor_msgs/JointState in: left wheel position (rad), for position_feedback', None, None,
     False),
    ('right_wheel_joint_states_topic', 'right_wheel/joint_states',
     'sensor_msgs/JointState in: right wheel position (rad), for position_feedback', None,
     None, False),
    ('left_wheel_joint_name', '', "the left wheel's joint in its JointState ('' = the "
     "message's only joint: a message with several is refused)", None, None, False),
    ('right_wheel_joint_name', '', "the right wheel's joint in its JointState ('' = the "
     "message's only joint: a message with several is refused)", None, None, False),
    ('position_feedback', True, 'odometry from the wheel positions (JointState) while both '
     'report them; false: always integrate the measured speeds', None, None, False),
    ('use_stamped_vel', True, "cmd_vel is geometry_msgs/TwistStamped (as Jazzy's "
     'diff_drive_controller); false: geometry_msgs/Twist', None, None, False),
    ('invert_left', False, 'negate the left wheel command and measurement (normally false: '
     'the drive nodes handle mirrored mounting with invert_direction)', None, None, False),
    ('invert_right', False, 'negate the right wheel command and measurement', None, None,
     False),
    ('max_linear_velocity', 1.0, 'm/s; 0 = no limit', 0.0, 100.0, True),
    ('max_angular_velocity', 2.0, 'rad/s; 0 = no limit', 0.0, 100.0, True),
    ('max_linear_acceleration', 1.0, 'm/s^2, also when braking; 0 = no limit', 0.0, 1000.0,
     True),
    ('max_angular_acceleration', 3.0, 'rad/s^2, also when braking; 0 = no limit', 0.0,
     1000.0, True),
    ('max_wheel_velocity', 0.0, 'rad/s per wheel, both wheels scaled together (set it to the '
     "drive nodes' max_velocity); 0 = no limit", 0.0, 10000.0, True),
    ('cmd_vel_timeout', 0.5, 's without a valid cmd_vel before the target becomes zero '
     '(zero wheel commands keep being published); a stamped cmd_vel older than this is '
     'rejected', 0.01, 60.0, True),
    ('wheel_status_timeout', 0.5, 's after the last wheel status before odometry holds',
     0.01, 60.0, True),
    ('publish_rate', 50.0, "Hz of the wheel commands and odom; faster than 1 / the drive "
     "nodes' command_timeout (their watchdogs stop the wheels between slower commands)",
     5.0, 1000.0, True),
    ('odom_frame', 'odom', 'header.frame_id of odom (REP 105)', None, None, False),
    ('base_frame', 'base_link', 'child_frame_id of odom (REP 105)', None, None, False),
    ('publish_tf', False, 'also publish odom_frame -> base_frame on /tf (needs tf2_msgs)',
     None, None, False),
)
LIMITS = ('max_linear_velocity', 'max_angular_velocity', 'max_linear_acceleration',
          'max_angular_acceleration', 'max_wheel_velocity')


#: JointStates without a wheel's joint name, none with it, before that is told (a misspelt
#: name; on a topic of several joints the wheel's own comes within a few messages)
MISSES_TOLD = 20

#: s a wheel stays in "watchdog" (no command yet) before the halt it causes is told
WATCHDOG_TELL_AFTER = 1.0

#: DriveStatus.state of a drive that does not follow its velocity commands
NOT_FOLLOWING = frozenset({'offline', 'fault', 'disabled', 'stopped', 'blocked', 'watchdog'})


class WheelInput:
    """The latest measured speed and state of one wheel, and when they arrived."""

    def __init__(self, name: str, invert: bool) -> None:
        self.name = name
        self.sign = -1.0 if invert else 1.0
        self.velocity_rad_s = math.nan
        self.online = False
        self.fault = False
        self.state = ''
        self.received: Time | None = None
        self.timeout_s = math.inf   # the status's timeout (see ``_unheard``)

    def update(self, msg: DriveStatus, now: Time, timeout_s: float) -> None:
        self.velocity_rad_s = self.sign * float(msg.measured_velocity)
        self.online = bool(msg.online)
        self.fault = bool(msg.fault)
        self.state = str(msg.state)
        self.received = now
        self.timeout_s = timeout_s

    def _unheard(self, now: Time) -> str:
        """Return why nothing current is known of this wheel ('' if its status is fresh).

        A status counts for the wheel_status_timeout in force when it came, or a
        shorter one set since (``DiffDriveNode._apply_parameters``): a raised one must
        not make a dead wheel's last status fresh again (the other wheel ran alone, the
        robot turning about the dead one).
        """
        if self.received is None:
            return f'no status from the {self.name} wheel yet'
        age = (now - self.received).nanoseconds * 1e-9
        if age > self.timeout_s:
            # (no age in the text: a halt is told once per cause, not once per cycle)
            return (f'{self.name} wheel status older than wheel_status_timeout '
                    f'{self.timeout_s:g} s')
        if age < 0.0:
            return f'{self.name} wheel status is from before the clock jumped back'
        if not self.online:
            return f'{self.name} wheel drive is offline'
        return ''

    def not_following(self, now: Time) -> str:
        """Return why this wheel may not follow its commands ('' if nothing says so)."""
        if unheard := self._unheard(now):
            return unheard
        if self.fault:
            return f'{self.name} wheel drive has a fault'
        if self.state in NOT_FOLLOWING:
            return f'{self.name} wheel drive is {self.state}'
        return ''

    def problem(self, now: Time) -> str:
        """Return why this wheel's speed cannot be used ('' if it can)."""
        if unheard := self._unheard(now):
            return unheard
        if not math.isfinite(self.velocity_rad_s):
            return f'{self.name} wheel measured_velocity is not a number'
        return ''


class WheelPosition:
    """The latest position of one wheel from its JointState: when measured, when arrived."""

    def __init__(self, sign: float, joint: str = '') -> None:
        self.sign = sign
        self.joint = joint      # its name in the JointState ('' = the message's only joint)
        self.seen = ''          # without ``joint``: the name of the joint it took first
        self.misses = 0         # messages without ``joint`` before the first with it
        self.position_rad = math.nan
        self.velocity_rad_s = math.nan     # at the same moment (NaN: not given)
        self.measured: Time | None = None  # its header stamp (None: zero, not known)
        self.received: Time | None = None
        self.timeout_s = math.inf          # the position's timeout (as WheelInput's)
        self.updates = 0        # positions received so far

    def update(self, msg: JointState, now: Time, timeout_s: float) -> str:
        """Take this wheel's position from ``msg``; return why it was refused ('' if not).

        A message naming several joints (a shared joint_states topic) is used only
        with ``joint`` set: another joint's position would be taken as this wheel's.
        A message without this wheel's joint is another's (ignored, not refused).
        """
        if self.joint:
            if self.joint not in msg.name:
                # another joint's message, unless many came and none named it (misspelt)
                self.misses += 1
                return '' if self.updates or self.misses < MISSES_TOLD else \
                    f'no {self.joint!r} in it (it names {", ".join(msg.name[:4]) or "none"})'
            index = list(msg.name).index(self.joint)
        elif len(msg.name) > 1 or len(msg.position) > 1:
            return (f'a JointState of {len(msg.name)} joints ({", ".join(msg.name[:4])}): '
                    'set the wheel_joint_name parameters to pick the wheels')
        else:
            # One joint per message: always the same one (another's on a shared topic
            # would be taken as this wheel's position).
            name = msg.name[0] if msg.name else ''
            self.seen = self.seen or name
            if name != self.seen:
                return (f'joint {name!r} after {self.seen!r}: several joints on one topic; '
                        'set the wheel_joint_name parameters to pick the wheels')
            index = 0
        if len(msg.position) > index:
            self.position_rad = self.sign * float(msg.position[index])
            self.velocity_rad_s = self.sign * float(msg.velocity[index]) \
                if len(msg.velocity) > index else math.nan
            stamp = Time.from_msg(msg.header.stamp, clock_type=now.clock_type)
            self.measured = stamp if stamp.nanoseconds else None
            self.received = now
            self.timeout_s = timeout_s
            self.updates += 1
        return ''

    def at(self, moment: Time, limit_s: float) -> float:
        """Return the position at ``moment``: carried on at the measured speed.

        From when it was measured, for at most ``limit_s``; as measured when either
        the moment or the speed is not known.
        """
        if self.measured is None or not math.isfinite(self.velocity_rad_s):
            return self.position_rad
        ahead = (moment - self.measured).nanoseconds * 1e-9
        return self.position_rad + self.velocity_rad_s * min(max(ahead, 0.0), limit_s)

    def usable(self, now: Time) -> bool:
        """Return whether the position is fresh (its timeout as ``WheelInput``'s)."""
        return self.received is not None and math.isfinite(self.position_rad) and \
            0.0 <= (now - self.received).nanoseconds * 1e-9 <= self.timeout_s


class DiffDriveNode(Node):
    """cmd_vel -> wheel commands (limited), measured wheel speeds -> odometry."""

    def __init__(self, node_name: str = 'diff_drive', **kwargs: Any) -> None:
        super().__init__(node_name, **kwargs)
        values = {name: self.declare_parameter(
            name, default, descriptor(description, default, low, high, live)).value
            for name, default, description, low, high, live in PARAMETERS}
        for name, _, _, low, high, _ in PARAMETERS:
            check_value(name, values[name], low, high)
        self.kinematics = DiffDriveKinematics(values['wheel_radius'], values['track_width'])
        self.limiter = RateLimiter(self.kinematics, VelocityLimits.from_parameters(
            values['max_linear_velocity'], values['max_angular_velocity'],
            values['max_linear_acceleration'], values['max_angular_acceleration'],
            values['max_wheel_velocity']))
        self.odometry = OdometryIntegrator(self.kinematics)
        for name in ('cmd_vel_timeout', 'wheel_status_timeout', 'publish_rate'):
            value = float(values[name])
            if not math.isfinite(value) or value <= 0.0:
                raise ParameterError(f'{name} must be a finite number > 0, got {value}')
        self.cmd_vel_timeout_s = float(values['cmd_vel_timeout'])
        self.wheel_status_timeout_s = float(values['wheel_status_timeout'])
        self.period_s = 1.0 / float(values['publish_rate'])
        self.odom_frame = str(values['odom_frame'])
        self.base_frame = str(values['base_frame'])
        self.left = WheelInput('left', bool(values['invert_left']))
        self.right = WheelInput('right', bool(values['invert_right']))
        self.position_feedback = bool(values['position_feedback'])
        self.left_position = WheelPosition(self.left.sign, str(values['left_wheel_joint_name']))
        self.right_position = WheelPosition(self.right.sign,
                                            str(values['right_wheel_joint_name']))
        shared = self.resolve_topic_name(str(values['left_wheel_joint_states_topic']))
        if self.position_feedback and shared == self.resolve_topic_name(
                str(values['right_wheel_joint_states_topic'])) and not (
                self.left_position.joint and self.right_position.joint):
            # (each wheel would take the other's positions as its own)
            raise ParameterError(
                f"both wheels' joint states come on {shared}: set left_wheel_joint_name "
                'and right_wheel_joint_name (or position_feedback false)')
        # positions at the last update, and how many each wheel had received by then
        self._baseline: tuple[float, float] | None = None
        self._baseline_updates = (0, 0)
        #: what the pose followed in the last cycle: 'position', 'velocity' or 'hold'
        self.odometry_source = 'hold'
        self.stale_commands = 0

        self.rejected_commands = 0
        self.target: tuple[float, float] = (0.0, 0.0)
        self.last_command: Time | None = None
        self.last_command_timeout_s = math.inf     # its timeout (see _apply_parameters)
        self.timed_out = True
        self.halted = ''            # why both wheels are held at zero ('' while they follow)
        self._halt_told = ''        # the cause last logged
        self._halt_since: Time | None = None    # since when a wheel halts both
        self._watchdog_ended: Time | None = None   # when a wheel last left "watchdog"
        self._last_tick: Time | None = None

        self.left_pub = self.create_publisher(Float64, values['left_wheel_command_topic'], 10)
        self.right_pub = self.create_publisher(Float64, values['right_wheel_command_topic'], 10)
        self.odom_pub = self.create_publisher(Odometry, 'odom', 10)
        self.tf_pub = None
        self._tf_message_type = None
        if values['publish_tf']:
            self._setup_tf()
        self.use_stamped_vel = bool(values['use_stamped_vel'])
        if self.use_stamped_vel:
            cmd_vel = self.create_subscription(TwistStamped, 'cmd_vel',
                                               self._on_cmd_vel_stamped, 10)
        else:
            cmd_vel = self.create_subscription(Twist, 'cmd_vel', self._on_cmd_vel, 10)
        self._cmd_vel_topic = cmd_vel.topic_name
        #: publishers on cmd_vel of the other twist type, as last told ('' = none)
        self.foreign_cmd_vel = ''
        self.create_timer(CMD_VEL_TYPE_CHECK_PERIOD, self._check_cmd_vel_publishers)
        self.create_subscription(DriveStatus, values['left_wheel_status_topic'],
                                 lambda msg: self._on_status(self.left, msg), 10)
        self.create_subscription(DriveStatus, values['right_wheel_status_topic'],
                                 lambda msg: self._on_status(self.right, msg), 10)
        self.create_subscription(JointState, values['left_wheel_joint_states_topic'],
                                 lambda msg: self._on_joint(self.left_position, msg), 10)
        self.create_subscription(JointState, values['right_wheel_joint_states_topic'],
                                 lambda msg: self._on_joint(self.right_position, msg), 10)
        self._tick_timer = self.create_timer(self.period_s, self._on_tick)
        self._values = values
        self.live_parameters = LiveParameters(
            self, {name for name, *_, live in PARAMETERS if live}, self._apply_parameters,
            {name: (low, high) for name, _, _, low, high, _ in PARAMETERS})
        self.get_logger().info(
            f'diff drive: r={self.kinematics.wheel_radius_m} m, '
            f'track={self.kinematics.track_width_m} m, wheels '
            f"{values['left_wheel_command_topic']} / {values['right_wheel_command_topic']}")

    def _apply_parameters(self, changes: dict[str, Any]) -> None:
        """Apply live limits, timeouts and rate at once (validated first, all or none)."""
        values = {**self._values, **changes}
        limits = VelocityLimits.from_parameters(*(float(values[name]) for name in LIMITS))
        self._values = values
        self.limiter.limits = limits
        self.cmd_vel_timeout_s = float(values['cmd_vel_timeout'])
        self.wheel_status_timeout_s = float(values['wheel_status_timeout'])
        # What came before holds for the timeout in force when it came, or the shortest
        # set since: one raised, or lowered and raised again, cannot revive what timed
        # out (as CommandWatchdog). What comes later takes the timeout then in force.
        self.last_command_timeout_s = min(self.last_command_timeout_s, self.cmd_vel_timeout_s)
        for wheel in (self.left, self.right, self.left_position, self.right_position):
            wheel.timeout_s = min(wheel.timeout_s, self.wheel_status_timeout_s)
        if 'publish_rate' in changes:
            self.period_s = 1.0 / float(values['publish_rate'])
            self._tick_timer.timer_period_ns = round(self.period_s * 1e9)
            self._tick_timer.reset()    # the new period from now, not after the old one's end

    def _setup_tf(self) -> None:
        try:
            from tf2_msgs.msg import TFMessage
        except ImportError:
            self.get_logger().error(
                'publish_tf is true but tf2_msgs is not installed (ros-jazzy-tf2-msgs): '
                'no TF is published; odom is. Install tf2_msgs or publish '
                f'{self.odom_frame} -> {self.base_frame} elsewhere (e.g. robot_localization).')
            return
        self._tf_message_type = TFMessage
        self.tf_pub = self.create_publisher(TFMessage, '/tf', 100)

    # --- inputs -----------------------------------------------------------------

    def _on_cmd_vel(self, msg: Twist) -> None:
        try:
            fields = (msg.linear.x, msg.linear.y, msg.linear.z,
                      msg.angular.x, msg.angular.y, msg.angular.z)
            if not all(math.isfinite(value) for value in fields) or not all(
                    math.isfinite(speed) for speed in
                    self.kinematics.wheel_speeds(msg.linear.x, msg.angular.z)):
                # (a finite twist whose wheel speeds overflow, 1e308 m/s, is no number either)
                self.rejected_commands += 1
                self.get_logger().warning(
                    f'rejected cmd_vel with a non-finite field or wheel speed (linear.x='
                    f'{msg.linear.x}, angular.z={msg.angular.z}); {self.rejected_commands} '
                    'rejected so far', throttle_duration_sec=1.0)
                return
            self.target = (float(msg.linear.x), float(msg.angular.z))
            self.last_command = self.get_clock().now()
            self.last_command_timeout_s = self.cmd_vel_timeout_s
        except Exception as exc:  # noqa: BLE001 - never raise into the executor
            self.get_logger().error(f'cmd_vel failed: {exc}', throttle_duration_sec=1.0)

    def _on_cmd_vel_stamped(self, msg: TwistStamped) -> None:
        try:
            now = self.get_clock().now()
            stamp = Time.from_msg(msg.header.stamp, clock_type=now.clock_type)
            if stamp.nanoseconds == 0:
                self.get_logger().warning('cmd_vel with a zero stamp: taken as now',
                                          throttle_duration_sec=5.0)
            else:
                age = (now - stamp).nanoseconds * 1e-9
                if abs(age) > self.cmd_vel_timeout_s:
                    # Too old, or from the future: a clock off by more than the timeout
                    # would let a queued command through (its age never reaches it).
                    self.stale_commands += 1
                    when = f'{age:.3f} s ago' if age > 0 else \
                        f'{-age:.3f} s in the future (clocks not in sync?)'
                    self.get_logger().warning(
                        f'rejected cmd_vel stamped {when} (cmd_vel_timeout '
                        f'{self.cmd_vel_timeout_s} s); {self.stale_commands} stale so far',
                        throttle_duration_sec=1.0)
                    return
            if msg.header.frame_id not in ('', self.base_frame):
                self.get_logger().warning(
                    f'cmd_vel in frame {msg.header.frame_id!r}: taken as {self.base_frame!r} '
                    '(not transformed, as diff_drive_controller does)',
                    throttle_duration_sec=10.0)
            self._on_cmd_vel(msg.twist)
        except Exception as exc:  # noqa: BLE001 - never raise into the executor
            self.get_logger().error(f'cmd_vel failed: {exc}', throttle_duration_sec=1.0)

    def _on_joint(self, wheel: WheelPosition, msg: JointState) -> None:
        try:
            refused = wheel.update(msg, self.get_clock().now(), self.wheel_status_timeout_s)
            if refused:
                side = 'left' if wheel is self.left_position else 'right'
                self.get_logger().warning(f'{side} wheel joint state refused: {refused}',
                                          throttle_duration_sec=5.0)
        except Exception as exc:  # noqa: BLE001
            self.get_logger().error(f'joint state failed: {exc}', throttle_duration_sec=1.0)

    def _on_status(self, wheel: WheelInput, msg: DriveStatus) -> None:
        try:
            wheel.update(msg, self.get_clock().now(), self.wheel_status_timeout_s)
        except Exception as exc:  # noqa: BLE001
            self.get_logger().error(f'{wheel.name} wheel status failed: {exc}',
                                    throttle_duration_sec=1.0)

    # --- the cycle --------------------------------------------------------------

    def _on_tick(self) -> None:
        try:
            now = self.get_clock().now()
            elapsed = self._elapsed(now)
            # A late cycle may not permit a larger jump in speed than the acceleration
            # limits allow over 5 periods; the wheels moved all the time, though.
            self._command(now, min(elapsed, 5.0 * self.period_s))
            self._integrate(now, min(elapsed, self.wheel_status_timeout_s))
        except Exception as exc:  # noqa: BLE001
            self.get_logger().error(f'diff drive cycle failed: {exc}', throttle_duration_sec=1.0)

    def _check_cmd_vel_publishers(self) -> None:
        """Warn of cmd_vel publishers of the other twist type: DDS never delivers theirs.

        A planner publishing Twist (Jazzy's Nav2 without enable_stamped_cmd_vel,
        teleop_twist_keyboard) to this node taking TwistStamped, or the reverse,
        is otherwise a robot that does not move and logs nothing.
        """
        try:
            wanted = 'geometry_msgs/msg/TwistStamped' if self.use_stamped_vel else \
                'geometry_msgs/msg/Twist'
            foreign = sorted({f'{info.node_namespace.rstrip("/")}/{info.node_name} '
                              f'({info.topic_type})'
                              for info in self.get_publishers_info_by_topic(self._cmd_vel_topic)
                              if info.topic_type != wanted})
            told = ', '.join(foreign)
            if told and told != self.foreign_cmd_vel:
                self.get_logger().warning(
                    f'{self._cmd_vel_topic} has publishers of another type: {told}; this node '
                    f'takes {wanted} (use_stamped_vel {str(self.use_stamped_vel).lower()}): '
                    'their commands never arrive. Publish that type, or set use_stamped_vel '
                    '(Nav2: enable_stamped_cmd_vel)')
            self.foreign_cmd_vel = told
        except Exception as exc:  # noqa: BLE001 - a graph query must not stop the node
            self.get_logger().error(f'cmd_vel publisher check failed: {exc}',
                                    throttle_duration_sec=10.0)

    def _elapsed(self, now: Time) -> float:
        """Return s since the last cycle; 0 on the first one or after a clock jump back."""
        last, self._last_tick = self._last_tick, now
        if last is None:
            return 0.0
        dt = (now - last).nanoseconds * 1e-9
        return dt if dt > 0.0 else 0.0

    def _command(self, now: Time, dt: float) -> None:
        # (a command from before the clock jumped back, as simulated time does when a
        # simulation restarts, is no fresher for it: its age is not known; and one counts
        # for its own timeout (see _apply_parameters): a raised cmd_vel_timeout
        # restarted the robot on a cmd_vel it had timed out)
        timeout_s = self.last_command_timeout_s
        fresh = self.last_command is not None and \
            0.0 <= (now - self.last_command).nanoseconds * 1e-9 <= timeout_s
        if not fresh and not self.timed_out and self.last_command is not None:
            self.get_logger().warning(   # (a jittery sender: 25 lines in 20 s, re-check)
                f'no valid cmd_vel for {timeout_s:g} s: stopping the wheels (said at most '
                'every 10 s)', throttle_duration_sec=10.0)
        self.timed_out = not fresh
        # One wheel that does not follow (offline, faulted, stopped, ...) would turn the
        # robot about it at the commanded speed: both wheels are brought to zero
        # (within the acceleration limits) until both follow again.
        halt = self.left.not_following(now) or self.right.not_following(now)
        if halt and self._halt_since is None:
            self._halt_since = now
        # A drive in "watchdog" has had no command: at a start it leaves it on this
        # node's first ones, so it is told only once it lasts (a warning at every
        # activation with cmd_vel streaming: outside audit), or comes back within
        # WATCHDOG_TELL_AFTER x 10 of the last (a wheel whose commands keep lapsing).
        recent = self._watchdog_ended is not None and \
            (now - self._watchdog_ended).nanoseconds * 1e-9 < 10 * WATCHDOG_TELL_AFTER
        lasting = not halt.endswith(' is watchdog') or recent or \
            (now - self._halt_since).nanoseconds * 1e-9 >= WATCHDOG_TELL_AFTER
        if halt and halt != self._halt_told and fresh and any(self.target) and lasting:
            # (told when a command asks for motion: a wheel halted while the robot
            # stands is told once something is asked of it)
            self.get_logger().warning(f'stopping both wheels: {halt}')
            self._halt_told = halt
        if self.halted.endswith(' is watchdog') and not halt.endswith(' is watchdog'):
            self._watchdog_ended = now
        self.halted = halt
        if not halt:
            self._halt_told = ''
            self._halt_since = None

        target = self.target if fresh and not halt else (0.0, 0.0)
        linear, angular = self.limiter.step(target[0], target[1], dt)
        left, right = self.kinematics.wheel_speeds(linear, angular)
        self.left_pub.publish(Float64(data=self.left.sign * left))
        self.right_pub.publish(Float64(data=self.right.sign * right))

    def _integrate(self, now: Time, dt: float) -> None:
        problem = self.left.problem(now) or self.right.problem(now)
        positions = self._positions(now)
        if problem:
            self.odometry.hold()
            self.odometry_source = 'hold'
            self.get_logger().warning(f'odometry holds its pose: {problem}',
                                      throttle_duration_sec=10.0)
        elif positions is not None:
            updates = (self.left_position.updates, self.right_position.updates)
            # The wheels report on their own topics: advance only once both have a
            # position newer than the last step (one wheel's alone would be a turn).
            both_new = all(count > seen for count, seen in zip(updates, self._baseline_updates))
            if self._baseline is not None and both_new:
                self.odometry.advance(positions[0] - self._baseline[0],
                                      positions[1] - self._baseline[1],
                                      self.left.velocity_rad_s, self.right.velocity_rad_s)
            else:
                self.odometry.update(self.left.velocity_rad_s, self.right.velocity_rad_s, 0.0)
            if self._baseline is None or both_new:
                self._baseline, self._baseline_updates = positions, updates
            self.odometry_source = 'position'
        else:
            self.odometry.update(self.left.velocity_rad_s, self.right.velocity_rad_s, dt)
            self.odometry_source = 'velocity'
        if positions is None or problem:
            # Position increments count from the last cycle that used them: after a gap
            # (held, or integrated speeds) the next one starts from the positions then.
            self._baseline = None
        self._publish_odometry(now)

    def _positions(self, now: Time) -> tuple[float, float] | None:
        """Return both wheels' positions (rad) at one moment (None: not to be used).

        None unless position feedback is on and both are fresh. Each wheel reports on
        its own topic, measured a bus cycle or more apart (at 3 rad/s, 20 ms is 0.06
        rad of wheel): taken as they come, the pair would say the robot turned back
        and forth. The earlier is carried on to the later one's moment at its speed.
        """
        if not self.position_feedback:
            return None
        left, right = self.left_position, self.right_position
        if not all(w.usable(now) for w in (left, right)):
            return None
        if left.measured is None or right.measured is None:
            return left.position_rad, right.position_rad
        moment = max(left.measured, right.measured)
        limit = self.wheel_status_timeout_s
        return left.at(moment, limit), right.at(moment, limit)

    def _publish_odometry(self, now: Time) -> None:
        estimate = self.odometry.estimate
        stamp = now.to_msg()
        msg = Odometry()
        msg.header.stamp = stamp
        msg.header.frame_id = self.odom_frame
        msg.child_frame_id = self.base_frame
        pose = msg.pose.pose
        pose.position.x, pose.position.y = estimate.x_m, estimate.y_m
        pose.orientation.z = math.sin(0.5 * estimate.yaw_rad)
        pose.orientation.w = math.cos(0.5 * estimate.yaw_rad)
        msg.pose.covariance = list(estimate.pose_covariance)
        msg.twist.twist.linear.x = estimate.linear_m_s
        msg.twist.twist.angular.z = estimate.angular_rad_s
        msg.twist.covariance = list(estimate.twist_covariance)
        self.odom_pub.publish(msg)
        if self.tf_pub is not None:
            transform = TransformStamped()
            transform.header = msg.header
            transform.child_frame_id = self.base_frame
            transform.transform.translation.x = pose.position.x
            transform.transform.translation.y = pose.position.y
            transform.transform.rotation = pose.orientation
            self.tf_pub.publish(self._tf_message_type(transforms=[transform]))


def make_diff_drive_node(args: list[str] | None = None) -> DiffDriveNode:
    only_ros_arguments(args)
    return DiffDriveNode()


def main(args: list[str] | None = None) -> int:
    return run_node('diff_drive', lambda: make_diff_drive_node(args), args,
                    cleanup='the node ends (the wheels stop on their own command watchdogs)')


if __name__ == '__main__':      # python -m, as well as the ros2 run launcher
    raise SystemExit(main())
