"""Differential drive: kinematics, limits and odometry (pure), and the diff_drive node.

The node tests run DiffDriveNode in-process against a tester node that plays
the two drive nodes: it records the wheel commands and publishes DriveStatus
with measured velocities (and, when given, JointState with wheel positions), as a
real drive_node would.
"""

from __future__ import annotations

import math
import threading
import time
import uuid
from typing import Any

import pytest
from geometry_msgs.msg import Twist, TwistStamped
from nav_msgs.msg import Odometry
from rclpy.duration import Duration
from rclpy.exceptions import ParameterException
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.time import Time
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64

from harness import wait_for
from vfd_ros2.control.diff_drive import (
    START_VARIANCE,
    UNKNOWN_VARIANCE,
    DiffDriveKinematics,
    OdometryIntegrator,
    RateLimiter,
    VelocityLimits,
    normalize_angle,
)
from vfd_ros2.errors import ParameterError
from vfd_ros2.msg import DriveStatus

R = 0.1        # m wheel radius
TRACK = 0.5    # m

# --- kinematics -----------------------------------------------------------------


def test_straight_line_wheel_speeds():
    kin = DiffDriveKinematics(R, TRACK)
    assert kin.wheel_speeds(1.0, 0.0) == pytest.approx((10.0, 10.0))
    assert kin.wheel_speeds(-0.5, 0.0) == pytest.approx((-5.0, -5.0))
    assert kin.body_velocity(10.0, 10.0) == pytest.approx((1.0, 0.0))


def test_pure_rotation_wheel_speeds():
    kin = DiffDriveKinematics(R, TRACK)
    # Counter-clockwise (REP 103, +z up): the right wheel forward, the left backward.
    assert kin.wheel_speeds(0.0, 1.0) == pytest.approx((-2.5, 2.5))
    assert kin.body_velocity(-2.5, 2.5) == pytest.approx((0.0, 1.0))


def test_arc_wheel_speeds_and_round_trip():
    kin = DiffDriveKinematics(R, TRACK)
    assert kin.wheel_speeds(0.5, 0.4) == pytest.approx((4.0, 6.0))
    for linear, angular in ((0.3, -1.2), (-0.7, 0.25), (1.5, 3.0)):
        assert kin.body_velocity(*kin.wheel_speeds(linear, angular)) == \
            pytest.approx((linear, angular))


@pytest.mark.parametrize('radius, track', [(0.0, 0.5), (-0.1, 0.5), (0.1, 0.0),
                                           (math.nan, 0.5), (0.1, math.inf)])
def test_kinematics_refuses_bad_geometry(radius, track):
    with pytest.raises(ParameterError):
        DiffDriveKinematics(radius, track)


def test_limits_refuse_negative_and_treat_zero_as_none():
    limits = VelocityLimits.from_parameters(1.0, 0.0, 2.0, 0.0, 0.0)
    assert limits.max_linear_m_s == 1.0 and limits.max_angular_rad_s == math.inf
    assert limits.max_wheel_rad_s == math.inf
    with pytest.raises(ParameterError, match='max_angular_acceleration'):
        VelocityLimits.from_parameters(1.0, 1.0, 1.0, -1.0)
    with pytest.raises(ParameterError):
        VelocityLimits.from_parameters(math.nan, 1.0, 1.0, 1.0)


# --- limiter --------------------------------------------------------------------


def curvature(linear: float, angular: float) -> float:
    return angular / linear


def test_speed_limits_scale_twist_and_keep_curvature():
    kin = DiffDriveKinematics(R, TRACK)
    limiter = RateLimiter(kin, VelocityLimits(max_linear_m_s=1.0, max_angular_rad_s=0.5))
    linear, angular = limiter.limit_speed(2.0, 0.8)          # linear limit: factor 0.5
    assert (linear, angular) == pytest.approx((1.0, 0.4))
    linear, angular = limiter.limit_speed(0.5, 1.0)          # angular limit: factor 0.5
    assert (linear, angular) == pytest.approx((0.25, 0.5))
    assert curvature(linear, angular) == pytest.approx(2.0)
    assert limiter.limit_speed(-2.0, 0.8) == pytest.approx((-1.0, 0.4))
    assert limiter.limit_speed(0.3, 0.2) == (0.3, 0.2)       # inside: untouched


def test_wheel_limit_scales_both_wheels_together():
    kin = DiffDriveKinematics(R, TRACK)
    limiter = RateLimiter(kin, VelocityLimits(max_wheel_rad_s=5.0))
    linear, angular = limiter.limit_speed(0.5, 0.4)          # wheels (4, 6): right too fast
    left, right = kin.wheel_speeds(linear, angular)
    assert right == pytest.approx(5.0)
    assert left == pytest.approx(4.0 * 5.0 / 6.0)            # slowed too, same ratio
    assert curvature(linear, angular) == pytest.approx(curvature(0.5, 0.4))
    # Pure rotation hits the limit on both wheels.
    assert kin.wheel_speeds(*limiter.limit_speed(0.0, 4.0)) == pytest.approx((-5.0, 5.0))


def test_acceleration_limit_over_time():
    kin = DiffDriveKinematics(R, TRACK)
    limiter = RateLimiter(kin, VelocityLimits(max_linear_accel_m_s2=1.0,
                                              max_angular_accel_rad_s2=2.0))
    dt = 0.02
    outputs = [limiter.step(0.5, 0.0, dt)[0] for _ in range(30)]
    for index, value in enumerate(outputs):                   # 1 m/s² * 0.02 s per step
        assert value == pytest.approx(min(0.02 * (index + 1), 0.5))
    assert outputs[23] < 0.5 and outputs[24] == pytest.approx(0.5)
    # Braking obeys the same limit.
    assert limiter.step(0.0, 0.0, 0.1)[0] == pytest.approx(0.4)
    # No time, no change; negative time (clock jump) is no time.
    assert limiter.step(-1.0, 1.0, 0.0) == pytest.approx((0.4, 0.0))
    assert limiter.step(-1.0, 1.0, -0.5) == pytest.approx((0.4, 0.0))
    limiter.reset()
    assert (limiter.linear_m_s, limiter.angular_rad_s) == (0.0, 0.0)


def test_acceleration_limit_from_rest_keeps_curvature():
    kin = DiffDriveKinematics(R, TRACK)
    limiter = RateLimiter(kin, VelocityLimits(max_linear_accel_m_s2=1.0,
                                              max_angular_accel_rad_s2=1.0))
    # Angular needs twice the change of linear: both are held to the angular rate.
    for step in range(1, 50):
        linear, angular = limiter.step(0.5, 1.0, 0.02)
        assert curvature(linear, angular) == pytest.approx(2.0)
        assert angular == pytest.approx(0.02 * step)
    assert (linear, angular) == pytest.approx((0.49, 0.98))   # 49 steps of 0.02 rad/s


# --- odometry -------------------------------------------------------------------


def test_odometry_straight_line():
    kin = DiffDriveKinematics(R, TRACK)
    odom = OdometryIntegrator(kin)
    for _ in range(100):
        odom.update(10.0, 10.0, 0.02)                         # 1 m/s for 2 s
    estimate = odom.estimate
    assert (estimate.x_m, estimate.y_m, estimate.yaw_rad) == pytest.approx((2.0, 0.0, 0.0))
    assert (estimate.linear_m_s, estimate.angular_rad_s) == pytest.approx((1.0, 0.0))
    assert estimate.twist_valid


def test_odometry_pure_rotation_stays_in_place_and_wraps_yaw():
    odom = OdometryIntegrator(DiffDriveKinematics(R, TRACK))
    for _ in range(30):
        odom.update(-2.5, 2.5, 0.1)                           # 1 rad/s for 3 s
    estimate = odom.estimate
    assert (estimate.x_m, estimate.y_m) == pytest.approx((0.0, 0.0), abs=1e-12)
    assert estimate.yaw_rad == pytest.approx(normalize_angle(3.0))
    odom.update(-2.5, 2.5, 0.3)                               # past pi: wraps to negative
    assert odom.estimate.yaw_rad == pytest.approx(3.3 - 2 * math.pi)


@pytest.mark.parametrize('steps', [8, 1000])
def test_odometry_full_circle_returns_to_start(steps):
    kin = DiffDriveKinematics(R, TRACK)
    odom = OdometryIntegrator(kin)
    linear, angular = 0.5, 0.5                                # radius 1 m, counter-clockwise
    left, right = kin.wheel_speeds(linear, angular)
    period = 2 * math.pi / angular
    for step in range(steps):
        odom.update(left, right, period / steps)
        if step == steps // 2 - 1:                            # half way: top of the circle
            half = odom.estimate
            assert (half.x_m, half.y_m) == pytest.approx((0.0, 2.0), abs=1e-9)
            assert abs(half.yaw_rad) == pytest.approx(math.pi)
    end = odom.estimate
    # Exact arcs: even 8 coarse steps close the circle (Euler steps would not).
    assert (end.x_m, end.y_m, end.yaw_rad) == pytest.approx((0.0, 0.0, 0.0), abs=1e-9)


def test_odometry_arc_matches_geometry():
    kin = DiffDriveKinematics(R, TRACK)
    odom = OdometryIntegrator(kin)
    odom.update(*kin.wheel_speeds(1.0, 0.5), math.pi)        # radius 2 m, a quarter turn
    estimate = odom.estimate
    assert (estimate.x_m, estimate.y_m) == pytest.approx((2.0, 2.0), abs=1e-9)
    assert estimate.yaw_rad == pytest.approx(math.pi / 2)
    # Reversing while turning left: about the centre (4, 2), back down to (4, 0).
    odom.update(*kin.wheel_speeds(-1.0, 0.5), math.pi)
    estimate = odom.estimate
    assert (estimate.x_m, estimate.y_m) == pytest.approx((4.0, 0.0), abs=1e-9)
    assert abs(estimate.yaw_rad) == pytest.approx(math.pi)


def test_odometry_hold_and_covariance():
    odom = OdometryIntegrator(DiffDriveKinematics(R, TRACK), position_variance_per_m=0.01)
    at_start = odom.estimate.pose_covariance      # not zero: no filter takes it as perfect
    assert at_start[0] == at_start[7] == at_start[35] == START_VARIANCE > 0.0
    odom.update(10.0, 10.0, 1.0)
    moving = odom.estimate
    assert moving.pose_covariance[0] == pytest.approx(START_VARIANCE + 0.01)   # 1 m
    assert moving.pose_covariance[14] == UNKNOWN_VARIANCE        # z
    assert moving.twist_covariance[0] < 1.0 and moving.twist_valid
    odom.hold()
    held = odom.estimate
    assert (held.x_m, held.y_m, held.yaw_rad) == (moving.x_m, moving.y_m, moving.yaw_rad)
    assert (held.linear_m_s, held.angular_rad_s, held.twist_valid) == (0.0, 0.0, False)
    assert held.twist_covariance[0] == UNKNOWN_VARIANCE
    assert held.twist_covariance[35] == UNKNOWN_VARIANCE
    odom.update(10.0, 10.0, 1.0)
    assert odom.estimate.pose_covariance[0] == pytest.approx(START_VARIANCE + 0.02)
    assert len(odom.estimate.pose_covariance) == 36


# --- the node -------------------------------------------------------------------


class FakeWheel:
    """What one drive node looks like from outside: commands in, status out."""

    def __init__(self, tester: Node, prefix: str) -> None:
        self.commands: list[float] = []
        self.measured = 0.0
        self.online = True
        self.fault = False
        self.state = ''             # DriveStatus.state; '' says nothing either way
        self.publishing = True
        tester.create_subscription(Float64, f'{prefix}/drive/velocity_command',
                                   lambda msg: self.commands.append(msg.data), 50)
        self.status_pub = tester.create_publisher(DriveStatus, f'{prefix}/drive/status', 10)
        self.position: float | None = None     # rad; None: no JointState published
        self.joint_every = 1                    # publish the JointState every n-th status
        self._statuses = 0
        self.joint_pub = tester.create_publisher(JointState, f'{prefix}/joint_states', 10)

    def publish_status(self, stamp: Any) -> None:
        if self.publishing:
            status = DriveStatus(online=self.online, measured_velocity=self.measured,
                                 fault=self.fault, state=self.state)
            status.header.stamp = stamp
            self.status_pub.publish(status)
            self._statuses += 1
            if self.position is not None and self._statuses % self.joint_every == 0:
                joint = JointState(name=['wheel'], position=[self.position],
                                   velocity=[self.measured])
                joint.header.stamp = stamp
                self.joint_pub.publish(joint)


class DiffDriveRig:
    """DiffDriveNode + a tester (fake drives, cmd_vel, odom) spinning in a thread."""

    def __init__(self, context: Any, parameters: dict[str, Any] | None = None) -> None:
        from vfd_ros2.ros.diff_drive_node import DiffDriveNode
        self.context = context
        self.namespace = f'/t{uuid.uuid4().hex[:8]}'
        ns = self.namespace
        values = {
            # the wheels' topics are the defaults: relative, so in the rig's namespace
            'wheel_radius': R, 'track_width': TRACK,
            'max_linear_acceleration': 0.0, 'max_angular_acceleration': 0.0,
            'max_linear_velocity': 2.0, 'max_angular_velocity': 4.0,
        }
        values.update(parameters or {})
        self.node = DiffDriveNode('diff_drive', namespace=ns, context=context,
                                  parameter_overrides=[Parameter(k, value=v)
                                                       for k, v in values.items()])
        self.tester = Node('tester', namespace=ns, context=context)
        self.left = FakeWheel(self.tester, f'{ns}/left_wheel')
        self.right = FakeWheel(self.tester, f'{ns}/right_wheel')
        self.odom: list[Odometry] = []
        self.tester.create_subscription(Odometry, f'{ns}/odom', self.odom.append, 100)
        self.stamped = bool(values.get('use_stamped_vel', True))
        self.stamp_age = 0.0       # s subtracted from the stamp of each TwistStamped sent
        self.cmd_pub = self.tester.create_publisher(TwistStamped if self.stamped else Twist,
                                                    f'{ns}/cmd_vel', 10)
        self.executor = SingleThreadedExecutor(context=context)
        self.executor.add_node(self.node)
        self.executor.add_node(self.tester)
        self._running = threading.Event()
        self._running.set()
        self.feeding = threading.Lock()     # held while one tick's messages go out
        self.twist: tuple[float, float] | None = None
        self._threads = [threading.Thread(target=self._spin, daemon=True),
                         threading.Thread(target=self._feed, daemon=True)]
        for thread in self._threads:
            thread.start()

    def _spin(self) -> None:
        while self._running.is_set() and self.context.ok():
            self.executor.spin_once(timeout_sec=0.05)

    def _feed(self) -> None:
        """Drive statuses at 50 Hz (like status_rate) and cmd_vel at 20 Hz while set."""
        tick = 0
        while self._running.is_set() and self.context.ok():
            stamp = self.tester.get_clock().now().to_msg()
            with self.feeding:
                self.left.publish_status(stamp)
                self.right.publish_status(stamp)
            if self.twist is not None and tick % 2 == 0:
                self.send(*self.twist)
            tick += 1
            time.sleep(0.02)

    def set_positions(self, left: float | None, right: float | None) -> None:
        """Both wheels' positions at once: never one wheel's new and the other's old."""
        with self.feeding:
            self.left.position, self.right.position = left, right

    def set_measured(self, left: float, right: float) -> None:
        """Both wheels' measured speeds at once (a tick between them mixes old and new)."""
        with self.feeding:
            self.left.measured, self.right.measured = left, right

    def send(self, linear: float, angular: float) -> None:
        twist = Twist()
        twist.linear.x, twist.angular.z = linear, angular
        if not self.stamped:
            self.cmd_pub.publish(twist)
            return
        msg = TwistStamped(twist=twist)
        now = self.tester.get_clock().now().nanoseconds - round(self.stamp_age * 1e9)
        msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(now, 1_000_000_000)
        self.cmd_pub.publish(msg)

    def wait_commands(self, left: float, right: float, timeout: float = 3.0,
                      what: str = 'wheel commands') -> None:
        def reached():
            return self.left.commands and self.right.commands and \
                self.left.commands[-1] == pytest.approx(left, abs=1e-9) and \
                self.right.commands[-1] == pytest.approx(right, abs=1e-9)
        wait_for(reached, timeout, f'{what} ({left}, {right})')

    def close(self) -> None:
        self._running.clear()
        for thread in self._threads:
            thread.join(2.0)
        self.executor.remove_node(self.node)
        self.node.destroy_node()
        self.tester.destroy_node()
        self.executor.shutdown(timeout_sec=1.0)


@pytest.fixture
def make_rig(ros_context):
    rigs: list[DiffDriveRig] = []

    def make(**parameters: Any) -> DiffDriveRig:
        rig = DiffDriveRig(ros_context, parameters)
        rigs.append(rig)
        return rig
    yield make
    for rig in rigs:
        rig.close()


def test_cmd_vel_to_wheel_commands_and_timeout_to_zero(make_rig):
    rig = make_rig()
    rig.wait_commands(0.0, 0.0, what='zeros before any cmd_vel')
    rig.twist = (0.5, 0.4)
    rig.wait_commands(4.0, 6.0, what='arc')
    rig.twist = (0.0, 1.0)
    rig.wait_commands(-2.5, 2.5, what='turn on the spot')
    rig.twist = (3.0, 0.0)                                    # above max_linear_velocity 2
    rig.wait_commands(20.0, 20.0, what='clamped straight line')
    # Commands stop: zeros after cmd_vel_timeout (0.5 s), and they keep coming.
    rig.twist = None
    stopped = time.monotonic()
    rig.wait_commands(0.0, 0.0, 2.0, 'zeros after the timeout')
    elapsed = time.monotonic() - stopped
    assert 0.35 < elapsed < 1.5, elapsed
    count = len(rig.left.commands)
    wait_for(lambda: len(rig.left.commands) > count + 10, 2.0, 'zeros keep flowing')
    assert set(rig.left.commands[count:]) == {0.0}
    assert set(rig.right.commands[count:]) == {0.0}


def test_inversion_applies_to_commands_and_measurements(make_rig):
    rig = make_rig(invert_right=True)
    rig.twist = (0.5, 0.4)
    rig.wait_commands(4.0, -6.0, what='right wheel inverted')
    # A drive that follows: it reports its command as measured (right: inverted again).
    rig.set_measured(4.0, -6.0)
    odom = wait_for(lambda: rig.odom and rig.odom[-1].twist.twist.linear.x > 0.1 and
                    rig.odom[-1], 3.0, 'odom twist')
    assert odom.twist.twist.linear.x == pytest.approx(0.5)
    assert odom.twist.twist.angular.z == pytest.approx(0.4)


def test_acceleration_limit_ramps_wheel_commands(make_rig):
    rig = make_rig(max_linear_acceleration=1.0, publish_rate=50.0)
    rig.wait_commands(0.0, 0.0)
    count = len(rig.left.commands)
    rig.twist = (0.5, 0.0)
    start = time.monotonic()
    rig.wait_commands(5.0, 5.0, 3.0, 'ramp to 0.5 m/s')
    elapsed = time.monotonic() - start
    ramp = [value for value in rig.left.commands[count:] if 0.0 < value < 5.0]
    assert elapsed > 0.4                                      # 0.5 m/s at 1 m/s² = 0.5 s
    assert len(ramp) >= 15
    assert ramp == sorted(ramp)
    steps = [b - a for a, b in zip(ramp, ramp[1:])]
    assert max(steps) <= 1.0 * 5 * 0.02 / R + 1e-9           # <= 5 periods' worth


def test_nan_and_inf_cmd_vel_rejected_and_do_not_feed_timeout(make_rig):
    rig = make_rig()
    rig.twist = (0.5, 0.0)
    rig.wait_commands(5.0, 5.0)
    rig.twist = (math.nan, 0.0)
    rig.wait_commands(0.0, 0.0, 2.0, 'zeros despite a NaN stream')
    assert rig.node.rejected_commands > 3
    before = rig.node.rejected_commands
    rig.twist = (0.2, math.inf)
    wait_for(lambda: rig.node.rejected_commands > before + 3, 2.0, 'inf rejected')
    assert rig.left.commands[-1] == 0.0 and rig.right.commands[-1] == 0.0
    before = rig.node.rejected_commands
    rig.twist = (1e308, 1e308)              # finite, but its wheel speeds overflow
    wait_for(lambda: rig.node.rejected_commands > before + 3, 2.0, 'overflow rejected')
    assert rig.left.commands[-1] == 0.0 and rig.right.commands[-1] == 0.0
    rig.twist = (0.2, 0.0)                                    # valid again: moves again
    rig.wait_commands(2.0, 2.0)


def test_odometry_integrates_measured_speeds_in_rep105_frames(make_rig):
    rig = make_rig()
    # The drives report 3 rad/s (0.3 m/s) whatever is commanded: odom must follow them.
    rig.twist = (0.5, 0.0)
    wait_for(lambda: rig.odom and rig.odom[-1].twist.covariance[0] < 1.0, 3.0,
             'odom with valid twist')
    assert rig.odom[-1].pose.pose.position.x == 0.0
    start = time.monotonic()
    rig.set_measured(3.0, 3.0)
    wait_for(lambda: time.monotonic() - start > 1.0, 2.0, '1 s of driving')
    rig.set_measured(0.0, 0.0)
    driven = time.monotonic() - start
    wait_for(lambda: rig.odom[-1].twist.twist.linear.x == 0.0, 2.0, 'stopped')
    final = rig.odom[-1]
    # (driven is this thread's time: the feeder's start and stop may lag it differently)
    assert final.pose.pose.position.x == pytest.approx(0.3 * driven, abs=0.045)
    # Straight ahead. The two wheels' statuses come on two topics: a cycle may fall
    # between them as the speeds change (3 rad/s on one wheel, 0 on the other for one
    # period at start and stop: at most ~0.012 rad of yaw each time; seen in CI: 2e-5 m).
    assert final.pose.pose.position.y == pytest.approx(0.0, abs=1e-3)
    assert abs(final.pose.pose.orientation.z) < math.sin(0.015)
    # Message to message, the pose advances by v * (stamp difference); a cycle the
    # executor delayed counts at most 5 periods (0.1 s at 50 Hz, the node's cap).
    moving = [m for m in rig.odom if m.twist.twist.linear.x == pytest.approx(0.3)]
    assert len(moving) > 20
    for a, b in zip(moving[5:], moving[6:]):
        dt = (b.header.stamp.sec - a.header.stamp.sec) + \
            (b.header.stamp.nanosec - a.header.stamp.nanosec) * 1e-9
        assert b.pose.pose.position.x - a.pose.pose.position.x == \
            pytest.approx(0.3 * min(dt, 0.1), abs=1e-6)
    assert final.header.frame_id == 'odom' and final.child_frame_id == 'base_link'
    assert final.pose.covariance[0] > 0.0


def test_odometry_turns_counter_clockwise_for_positive_yaw_rate(make_rig):
    rig = make_rig(odom_frame='map_odom', base_frame='robot_base')
    wait_for(lambda: rig.odom and rig.odom[-1].twist.covariance[0] < 1.0, 3.0, 'valid odom')
    rig.set_measured(-2.5, 2.5)                                    # 1 rad/s on the spot
    wait_for(lambda: rig.odom[-1].pose.pose.orientation.z > math.sin(0.25), 3.0,
             'yaw past 0.5 rad')
    odom = rig.odom[-1]
    assert odom.twist.twist.angular.z == pytest.approx(1.0)
    # On the spot: no more than the one period a cycle may fall between the two wheels'
    # statuses as they start (one wheel at 2.5 rad/s alone: 2.5 mm)
    assert odom.pose.pose.position.x == pytest.approx(0.0, abs=5e-3)
    assert (odom.header.frame_id, odom.child_frame_id) == ('map_odom', 'robot_base')


def test_stale_or_offline_wheel_holds_pose_with_unknown_twist(make_rig):
    rig = make_rig()
    rig.set_measured(2.0, 2.0)
    wait_for(lambda: rig.odom and rig.odom[-1].pose.pose.position.x > 0.05, 3.0, 'moving')
    rig.right.publishing = False                              # right drive's status stops
    held = wait_for(lambda: rig.odom[-1].twist.covariance[0] == UNKNOWN_VARIANCE and
                    rig.odom[-1], 2.0, 'twist unknown after wheel_status_timeout')
    assert held.twist.twist.linear.x == 0.0 and held.twist.covariance[35] == UNKNOWN_VARIANCE
    count = len(rig.odom)
    wait_for(lambda: len(rig.odom) > count + 10, 2.0, 'more odom')
    assert {m.pose.pose.position.x for m in rig.odom[count:]} == {held.pose.pose.position.x}
    rig.right.publishing = True
    wait_for(lambda: rig.odom[-1].twist.twist.linear.x == pytest.approx(0.2), 2.0, 'recovered')
    rig.left.online = False                                   # left drive reports offline
    wait_for(lambda: rig.odom[-1].twist.covariance[0] == UNKNOWN_VARIANCE, 2.0,
             'held while offline')
    rig.left.online = True
    rig.left.measured = math.nan                              # drive has no measurement
    rig.left.online = True
    wait_for(lambda: rig.odom[-1].twist.covariance[0] == UNKNOWN_VARIANCE, 2.0, 'held on NaN')


def test_publish_tf(make_rig, ros_context):
    try:
        from tf2_msgs.msg import TFMessage
    except ImportError:
        TFMessage = None
    rig = make_rig(publish_tf=True, base_frame='base_footprint')
    wait_for(lambda: rig.odom, 3.0, 'odom published with publish_tf')
    if TFMessage is None:
        # Not installed here: the node says so and runs without TF.
        assert rig.node.tf_pub is None
        return
    received: list[Any] = []
    rig.tester.create_subscription(TFMessage, '/tf', received.append, 100)
    transform = wait_for(lambda: next((t for m in list(received) for t in m.transforms
                                       if t.child_frame_id == 'base_footprint'), None),
                         3.0, 'odom -> base_footprint on /tf')
    assert transform.header.frame_id == 'odom'


def test_bad_parameters_are_refused(ros_context):
    from vfd_ros2.ros.diff_drive_node import DiffDriveNode
    for name, value in (('wheel_radius', 0.0), ('cmd_vel_timeout', -1.0),
                        ('max_linear_velocity', -1.0), ('publish_rate', 1.0)):
        # Out of the declared range: rclpy refuses the override (a ParameterException,
        # reported in one line by run_node); what the range cannot express: ParameterError.
        with pytest.raises((ParameterError, ParameterException), match=name):
            DiffDriveNode('diff_drive', namespace=f'/t{uuid.uuid4().hex[:8]}',
                          context=ros_context,
                          parameter_overrides=[Parameter(name, value=value)])


# --- stamped commands and position feedback ---------------------------------------


@pytest.mark.parametrize('stamped', [True, False])
def test_a_cmd_vel_publisher_of_the_other_type_is_named(make_rig, stamped):
    """DDS never matches a Twist publisher with a TwistStamped subscription: said, not silent."""
    import rclpy
    from rclpy.context import Context
    rig = make_rig(use_stamped_vel=stamped)
    assert rig.node.foreign_cmd_vel == ''
    other = Twist if stamped else TwistStamped
    # Another process's participant (one participant takes one type per topic)
    planner_context = Context()
    rclpy.init(context=planner_context)
    planner = Node('planner', namespace=rig.namespace, context=planner_context)
    try:
        planner.create_publisher(other, f'{rig.namespace}/cmd_vel', 10)
        wanted = f'{rig.namespace}/planner (geometry_msgs/msg/{other.__name__})'
        wait_for(lambda: rig.node.foreign_cmd_vel == wanted, 6.0, 'the other type named')
    finally:
        planner.destroy_node()
        rclpy.shutdown(context=planner_context)


def test_plain_twist_still_works_with_use_stamped_vel_false(make_rig):
    rig = make_rig(use_stamped_vel=False)
    rig.twist = (0.5, 0.4)
    rig.wait_commands(4.0, 6.0, what='arc from a Twist')


def test_stale_stamped_cmd_vel_is_rejected_and_the_wheels_stay_stopped(make_rig):
    rig = make_rig(cmd_vel_timeout=0.5)
    rig.stamp_age = 2.0                     # queued somewhere for 2 s
    rig.twist = (0.5, 0.0)
    wait_for(lambda: rig.node.stale_commands > 5, 3.0, 'stale commands counted')
    assert rig.left.commands and set(rig.left.commands) == {0.0}
    assert set(rig.right.commands) == {0.0}
    rig.stamp_age = 0.1                     # fresh enough: the same stream moves the wheels
    rig.wait_commands(5.0, 5.0, what='fresh stamped commands')
    stale = rig.node.stale_commands
    rig.stamp_age = -100.0                  # a sender whose clock runs 100 s ahead
    rig.wait_commands(0.0, 0.0, what='stopped: commands from the future are refused')
    assert rig.node.stale_commands > stale


def test_stale_stamped_cmd_vel_keeps_a_simulated_motor_stopped(ros_context, tmp_path):
    """End to end: diff_drive -> drive_node -> simulated drive on a pty line."""
    from harness import DriveHarness
    drive = DriveHarness(ros_context, str(tmp_path / 'line'),
                         node_parameters={'auto_enable': True})
    rig = None
    try:
        drive.wait_status(lambda s: s.online, 10.0, 'drive online')
        topic = f'{drive.namespace}/drive'
        rig = DiffDriveRig(ros_context, {
            'left_wheel_command_topic': f'{topic}/velocity_command',
            'left_wheel_status_topic': f'{topic}/status'})
        rig.stamp_age = 1.0
        rig.twist = (0.5, 0.0)
        seen = len(drive.statuses)
        wait_for(lambda: rig.node.stale_commands > 10, 3.0, 'stale commands')
        drive.wait_cycles(20)
        # diff_drive holds the wheel at zero (fresh zero commands): it never turns.
        window = drive.statuses[seen:]
        assert len(window) > 5 and drive.sim.speed_rpm == 0.0
        assert all(s.commanded_velocity == 0.0 and s.measured_velocity == 0.0 for s in window)
        rig.stamp_age = 0.0
        wait_for(lambda: drive.sim.speed_rpm > 100.0, 6.0, 'fresh commands move the motor')
    finally:
        if rig is not None:
            rig.close()
        drive.close()


def test_odometry_follows_wheel_positions_when_the_drives_report_them(make_rig):
    rig = make_rig()
    rig.set_positions(0.0, 0.0)
    wait_for(lambda: rig.node.odometry_source == 'position', 3.0, 'position feedback')
    # The positions advance (10 rad = 1 m) while the measured speeds say 0: the pose
    # follows the positions, the twist the speeds.
    rig.set_positions(10.0, 10.0)
    wait_for(lambda: rig.odom and rig.odom[-1].pose.pose.position.x == pytest.approx(1.0),
             3.0, 'pose from positions')
    assert rig.odom[-1].twist.twist.linear.x == 0.0
    # Left turned -2.5 rad and right +2.5 rad: 1 rad counter-clockwise on the spot.
    rig.set_positions(7.5, 12.5)
    wait_for(lambda: rig.odom[-1].pose.pose.orientation.z == pytest.approx(math.sin(0.5)),
             3.0, 'yaw 1 rad from positions')
    assert rig.odom[-1].pose.pose.position.x == pytest.approx(1.0)
    # Without positions (the JointState stops) the speeds are integrated again; the
    # positions' jump while they were missing is not counted twice.
    rig.set_positions(None, None)
    wait_for(lambda: rig.node.odometry_source == 'velocity', 3.0, 'speeds integrated')
    x = rig.odom[-1].pose.pose.position.x
    rig.set_positions(100.0, 100.0)
    wait_for(lambda: rig.node.odometry_source == 'position', 3.0, 'positions again')
    count = len(rig.odom)
    wait_for(lambda: len(rig.odom) > count + 10, 2.0, 'more odom')
    assert rig.odom[-1].pose.pose.position.x == pytest.approx(x, abs=1e-9)


def test_a_wheel_reporting_late_does_not_bend_the_path(make_rig):
    """Positions come on two topics: one wheel's new position alone is not a turn."""
    rig = make_rig()
    rig.right.joint_every = 10                  # the right wheel reports 5 times a second
    rig.set_positions(0.0, 0.0)
    wait_for(lambda: rig.node.odometry_source == 'position', 3.0, 'position feedback')
    rig.set_positions(10.0, 10.0)               # 1 m straight ahead
    wait_for(lambda: rig.odom and rig.odom[-1].pose.pose.position.x == pytest.approx(1.0),
             3.0, 'pose from positions')
    pose = rig.odom[-1].pose.pose
    assert pose.position.y == pytest.approx(0.0, abs=1e-9)
    assert pose.orientation.z == pytest.approx(0.0, abs=1e-9)


def test_position_feedback_false_integrates_speeds(make_rig):
    rig = make_rig(position_feedback=False)
    rig.set_positions(0.0, 0.0)
    wait_for(lambda: rig.odom and rig.odom[-1].twist.covariance[0] < 1.0, 3.0, 'valid odom')
    rig.set_positions(10.0, 10.0)
    count = len(rig.odom)
    wait_for(lambda: len(rig.odom) > count + 10, 2.0, 'more odom')
    assert rig.odom[-1].pose.pose.position.x == 0.0 and rig.node.odometry_source == 'velocity'


def test_odometry_advance_from_wheel_increments():
    kin = DiffDriveKinematics(R, TRACK)
    odom = OdometryIntegrator(kin)
    odom.advance(10.0, 10.0, 3.0, 3.0)              # 1 m straight; 0.3 m/s measured
    assert (odom.x_m, odom.y_m, odom.yaw_rad) == (pytest.approx(1.0), 0.0, 0.0)
    assert odom.estimate.linear_m_s == pytest.approx(0.3) and odom.twist_valid
    quarter = math.pi / 2 * TRACK / 2 / R           # each wheel's angle for a quarter turn
    odom.advance(-quarter, quarter, 0.0, 0.0)
    assert odom.yaw_rad == pytest.approx(math.pi / 2) and odom.x_m == pytest.approx(1.0)


@pytest.mark.parametrize('trouble', ['offline', 'fault', 'stopped', 'silent'])
def test_a_wheel_that_does_not_follow_stops_the_other_too(make_rig, trouble):
    """One wheel that does not follow stops the other too, until both follow again.

    Offline, faulted, stopped or silent: the other wheel alone would turn the robot
    about it at the commanded speed.
    """
    rig = make_rig()
    rig.twist = (0.5, 0.4)
    rig.wait_commands(4.0, 6.0, what='arc')
    if trouble == 'offline':
        rig.right.online = False
    elif trouble == 'fault':
        rig.right.fault = True
    elif trouble == 'stopped':
        rig.right.state = 'stopped'
    else:
        rig.right.publishing = False
    rig.wait_commands(0.0, 0.0, what='both wheels stopped')
    count = len(rig.left.commands)
    wait_for(lambda: len(rig.left.commands) > count + 10, 2.0, 'more commands')
    assert set(rig.left.commands[count:]) == {0.0}
    rig.right.online, rig.right.fault, rig.right.state = True, False, 'running'
    rig.right.publishing = True
    rig.wait_commands(4.0, 6.0, what='the arc again once both follow')


def test_raised_timeouts_revive_neither_an_old_cmd_vel_nor_a_silent_wheel(make_rig):
    """A timeout raised after it ran out applies to what comes next (outside audit).

    A raised cmd_vel_timeout restarted the robot on the cmd_vel it had timed out;
    a raised wheel_status_timeout made a dead wheel's last status fresh again, and
    the other wheel ran alone.
    """
    def stays_stopped(what: str) -> None:
        count = len(rig.left.commands)
        wait_for(lambda: len(rig.left.commands) > count + 10, 2.0, 'more commands')
        assert set(rig.left.commands[count:]) == {0.0}, what
        assert set(rig.right.commands[count:]) == {0.0}, what

    def set_parameter(name: str, value: float) -> None:
        result = rig.node.set_parameters([Parameter(name, value=value)])[0]
        assert result.successful, result.reason

    rig = make_rig(cmd_vel_timeout=2.0)
    rig.twist = (0.5, 0.4)
    rig.wait_commands(4.0, 6.0, what='arc')
    rig.twist = None
    set_parameter('cmd_vel_timeout', 0.05)          # lowered: at once
    rig.wait_commands(0.0, 0.0, 1.0, 'zeros after the lowered timeout')
    set_parameter('cmd_vel_timeout', 2.0)           # raised again within the old 2 s
    stays_stopped('cmd_vel_timeout lowered, then raised')
    set_parameter('cmd_vel_timeout', 60.0)
    stays_stopped('cmd_vel_timeout raised')

    rig.twist = (0.5, 0.4)                   # a new cmd_vel: the new timeout
    rig.wait_commands(4.0, 6.0, what='the arc on a new cmd_vel')
    rig.right.publishing = False
    rig.wait_commands(0.0, 0.0, what='both wheels stopped')
    set_parameter('wheel_status_timeout', 60.0)
    stays_stopped('wheel_status_timeout raised')
    rig.right.publishing = True
    rig.wait_commands(4.0, 6.0, what='the arc again once the wheel reports')


def test_wheel_positions_measured_apart_are_paired_at_one_moment(make_rig):
    """A bus reads the two wheels a cycle apart; each JointState carries its own moment.

    Straight ahead at 3 rad/s, one wheel measured 20 ms after the other, which one
    alternating: taken as they come, the pair said the robot turned 0.012 rad one
    way and back again every message (a yaw-rate spike of ~0.3 rad/s each time).
    """
    rig = make_rig()
    rig.set_measured(3.0, 3.0)
    publishers = {'left': rig.left.joint_pub, 'right': rig.right.joint_pub}
    start = rig.tester.get_clock().now()
    yaws = []
    for step in range(40):
        now = rig.tester.get_clock().now()
        late = 'left' if step % 2 else 'right'
        for wheel, publisher in publishers.items():
            measured = now - Duration(nanoseconds=20_000_000 if wheel == late else 0)
            joint = JointState(name=[wheel], velocity=[3.0], position=[
                3.0 * (measured - start).nanoseconds * 1e-9])
            joint.header.stamp = measured.to_msg()
            publisher.publish(joint)
        time.sleep(0.03)
        if rig.node.odometry_source == 'position' and rig.odom:
            yaws.append(2 * math.asin(rig.odom[-1].pose.pose.orientation.z))
    assert len(yaws) > 20, 'position feedback in use'
    assert max(abs(yaw) for yaw in yaws) < 0.002, max(abs(yaw) for yaw in yaws)


def test_odometry_counts_the_whole_of_a_late_cycle(make_rig):
    """The executor stalls 0.4 s: the wheels went on meanwhile, and so must the pose.

    Only the command limiter's step is capped (5 periods); the pose integrated the
    capped step too and lost three quarters of the distance.
    """
    rig = make_rig(position_feedback=False)
    rig.set_measured(3.0, 3.0)                                  # 0.3 m/s straight ahead
    wait_for(lambda: rig.odom and rig.odom[-1].twist.twist.linear.x > 0.29, 3.0, 'moving')
    first = rig.odom[-1]

    def stall() -> None:
        timer.cancel()
        time.sleep(0.4)
    timer = rig.tester.create_timer(0.01, stall)             # same executor as diff_drive
    time.sleep(0.8)
    last = rig.odom[-1]
    elapsed = (Time.from_msg(last.header.stamp) - Time.from_msg(first.header.stamp)
               ).nanoseconds * 1e-9
    travelled = last.pose.pose.position.x - first.pose.pose.position.x
    assert travelled == pytest.approx(0.3 * elapsed, rel=0.1), (travelled, elapsed)


def test_a_shared_joint_states_topic_is_read_by_joint_name(make_rig):
    """One JointState for both wheels (a bus's joint_states_topic): each wheel by its name."""
    names = {'left_wheel_joint_states_topic': 'joints', 'right_wheel_joint_states_topic': 'joints'}
    with pytest.raises(ParameterError, match='set left_wheel_joint_name'):
        make_rig(**names)           # each wheel would take the other's positions as its own
    rig = make_rig(**names, left_wheel_joint_name='l', right_wheel_joint_name='r')
    publisher = rig.tester.create_publisher(JointState, f'{rig.namespace}/joints', 10)
    positions = [(0.0, 0.0)]        # (left, right) rad
    stop = threading.Event()

    def feed() -> None:
        while not stop.is_set():
            left, right = positions[0]     # the right wheel first: taken by name
            publisher.publish(JointState(name=['r', 'l'], position=[right, left],
                                         velocity=[0.0, 0.0]))
            time.sleep(0.02)
    thread = threading.Thread(target=feed, daemon=True)
    thread.start()
    try:
        wait_for(lambda: rig.node.odometry_source == 'position', 3.0, 'position feedback')
        positions[0] = (-2.5, 2.5)      # 1 rad counter-clockwise on the spot
        wait_for(lambda: rig.odom and rig.odom[-1].pose.pose.orientation.z ==
                 pytest.approx(math.sin(0.5)), 3.0, 'yaw 1 rad')
        assert rig.odom[-1].pose.pose.position.x == pytest.approx(0.0, abs=1e-9)
    finally:
        stop.set()
        thread.join(1.0)


def test_a_wheel_takes_only_its_own_joint():
    from vfd_ros2.ros.diff_drive_node import MISSES_TOLD, WheelPosition
    now = Time(nanoseconds=1)
    # Unnamed: a message of two joints is refused (either could be either wheel), and
    # of single-joint messages only the joint taken first.
    unnamed = WheelPosition(1.0)
    assert 'set the wheel_joint_name' in unnamed.update(
        JointState(name=['r', 'l'], position=[1.0, 2.0]), now, 0.5)
    assert unnamed.update(JointState(name=['l'], position=[2.0]), now, 0.5) == ''
    assert 'several joints on one topic' in unnamed.update(
        JointState(name=['r'], position=[1.0]), now, 0.5)
    assert unnamed.position_rad == 2.0 and unnamed.updates == 1
    # Named: others' messages are ignored, until so many came without it that the name
    # looks misspelt.
    named = WheelPosition(1.0, 'left')
    told = [named.update(JointState(name=['l'], position=[0.0]), now, 0.5)
            for _ in range(MISSES_TOLD)]
    assert told[:-1] == [''] * (MISSES_TOLD - 1) and "no 'left' in it" in told[-1]
    assert named.update(JointState(name=['r', 'left'], position=[1.0, 3.0]), now, 0.5) == ''
    assert named.position_rad == 3.0
    assert named.update(JointState(name=['l'], position=[0.0]), now, 0.5) == ''


def test_a_clock_that_jumps_back_ends_the_last_command(make_rig):
    """Simulated time restarting (a simulator reset): the last cmd_vel is not fresh for it."""
    from rosgraph_msgs.msg import Clock
    rig = make_rig(use_sim_time=True, use_stamped_vel=False)
    clock_pub = rig.tester.create_publisher(Clock, '/clock', 10)
    now = [100.0]
    stop = threading.Event()

    def tick() -> None:
        while not stop.is_set():
            now[0] += 0.02
            msg = Clock()
            msg.clock.sec, msg.clock.nanosec = divmod(round(now[0] * 1e9), 1_000_000_000)
            clock_pub.publish(msg)
            time.sleep(0.02)
    thread = threading.Thread(target=tick, daemon=True)
    thread.start()
    try:
        rig.twist = (0.2, 0.0)
        rig.wait_commands(2.0, 2.0, what='driving')
        rig.twist = None
        now[0] = 1.0                    # the simulation restarts
        rig.wait_commands(0.0, 0.0, what='stopped after the clock jumped back')
    finally:
        stop.set()
        thread.join(1.0)


def test_a_wheel_that_stopped_following_while_idle_is_told_when_motion_is_asked(
        make_rig, capfd):
    rig = make_rig()
    rig.right.fault = True          # while the robot stands
    wait_for(lambda: rig.node.halted, 3.0, 'halted')
    rig.twist = (0.3, 0.0)
    wait_for(lambda: 'stopping both wheels: right wheel drive has a fault' in
             ''.join(capfd.readouterr()), 3.0, 'the halt told')
    assert set(rig.left.commands[-10:]) == {0.0}


def test_a_wheel_in_watchdog_is_told_only_when_it_stays_there(make_rig, capfd):
    # At a start the drives are in "watchdog" (no command yet) until this node's first
    # commands reach them: that was a warning at every activation (outside audit). It
    # still halts both wheels, and one that stays there is told.
    rig = make_rig()
    rig.left.state = rig.right.state = 'watchdog'
    rig.twist = (0.3, 0.0)
    wait_for(lambda: rig.node.halted, 3.0, 'halted')
    time.sleep(0.3)
    rig.left.state = rig.right.state = 'running'      # the first commands arrived
    rig.wait_commands(3.0, 3.0, what='driving')
    assert 'stopping both wheels' not in ''.join(capfd.readouterr())
    rig.right.state = 'watchdog'                       # its commands no longer arrive
    wait_for(lambda: 'stopping both wheels: right wheel drive is watchdog' in
             ''.join(capfd.readouterr()), 3.0, 'a lasting watchdog told')
    assert rig.node.halted


def test_a_halt_is_told_once_per_cause_not_once_per_cycle(make_rig, capfd):
    rig = make_rig()
    rig.twist = (0.3, 0.0)
    rig.wait_commands(3.0, 3.0, what='driving')
    capfd.readouterr()
    rig.right.publishing = False    # its status grows older every cycle
    rig.wait_commands(0.0, 0.0, what='both stopped')
    time.sleep(1.0)                 # 50 cycles at publish_rate
    told = ''.join(capfd.readouterr()).count('stopping both wheels')
    assert told == 1, told
