"""Differential-drive kinematics, command limiting and wheel odometry (no ROS).

Units follow REP 103: metres, seconds, radians; wheel speeds are rad/s at the
wheel (the drive nodes' ``~/velocity_command`` and ``measured_velocity``), body
velocities are m/s forward (+x) and rad/s counter-clockwise about +z.
A positive wheel speed drives the robot forward on both sides.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from ..errors import ParameterError

#: Variance reported for a quantity that is not measured (z, roll, pitch, and the
#: twist while a wheel status is stale or offline). Large, not infinite: many
#: consumers (robot_localization) refuse inf/NaN covariances.
UNKNOWN_VARIANCE = 1.0e6
#: The pose's variance before any travel (m², rad²): not zero, which would claim a
#: perfect pose to a filter fusing it.
START_VARIANCE = 1.0e-6


def _positive(name: str, value: float) -> float:
    value = float(value)
    if not math.isfinite(value) or value <= 0.0:
        raise ParameterError(f'{name} must be a finite number > 0, got {value}')
    return value


def _limit(name: str, value: float) -> float:
    """Return a limit: finite >= 0, where 0 means "no limit" (returned as inf)."""
    value = float(value)
    if not math.isfinite(value) or value < 0.0:
        raise ParameterError(f'{name} must be a finite number >= 0 (0 = no limit), got {value}')
    return math.inf if value == 0.0 else value


def normalize_angle(angle_rad: float) -> float:
    """Wrap an angle to [-pi, pi)."""
    return (angle_rad + math.pi) % (2.0 * math.pi) - math.pi


class DiffDriveKinematics:
    """Body twist <-> wheel speeds of a differential drive.

    ``wheel_radius_m`` is the rolling radius, ``track_width_m`` the distance
    between the two wheels' contact points.
    """

    def __init__(self, wheel_radius_m: float, track_width_m: float) -> None:
        self.wheel_radius_m = _positive('wheel_radius', wheel_radius_m)
        self.track_width_m = _positive('track_width', track_width_m)

    def wheel_speeds(self, linear_m_s: float, angular_rad_s: float) -> tuple[float, float]:
        """Return (left, right) wheel speeds in rad/s for a body twist."""
        half_track = 0.5 * self.track_width_m
        left = (linear_m_s - angular_rad_s * half_track) / self.wheel_radius_m
        right = (linear_m_s + angular_rad_s * half_track) / self.wheel_radius_m
        return left, right

    def body_velocity(self, left_rad_s: float, right_rad_s: float) -> tuple[float, float]:
        """Return (linear m/s, angular rad/s) of the body for wheel speeds in rad/s."""
        linear = 0.5 * self.wheel_radius_m * (left_rad_s + right_rad_s)
        angular = self.wheel_radius_m * (right_rad_s - left_rad_s) / self.track_width_m
        return linear, angular


@dataclass(frozen=True)
class VelocityLimits:
    """Limits on the commanded body twist; ``inf`` = no limit.

    ``max_wheel_rad_s`` bounds each wheel's speed (match it to the drive nodes'
    ``max_velocity``: the drive clamps one wheel alone, which bends the path;
    limiting here scales both wheels together).
    """

    max_linear_m_s: float = math.inf
    max_angular_rad_s: float = math.inf
    max_linear_accel_m_s2: float = math.inf
    max_angular_accel_rad_s2: float = math.inf
    max_wheel_rad_s: float = math.inf

    @classmethod
    def from_parameters(cls, max_linear_velocity: float, max_angular_velocity: float,
                        max_linear_acceleration: float, max_angular_acceleration: float,
                        max_wheel_velocity: float = 0.0) -> VelocityLimits:
        """Build from node parameters, where 0 means "no limit"; negatives are refused."""
        return cls(_limit('max_linear_velocity', max_linear_velocity),
                   _limit('max_angular_velocity', max_angular_velocity),
                   _limit('max_linear_acceleration', max_linear_acceleration),
                   _limit('max_angular_acceleration', max_angular_acceleration),
                   _limit('max_wheel_velocity', max_wheel_velocity))


class RateLimiter:
    """Speed and acceleration limits on a body twist that keep the path's shape.

    Speed limits: the twist is scaled by one common factor (both wheels
    together), so the curvature ``angular / linear`` of the commanded path is
    kept when the linear, angular or a wheel limit is hit — clamping each
    component alone would turn an arc into a different arc.

    Acceleration limits: the step from the last output towards the target is
    scaled by one common factor so that neither component changes faster than
    its limit. From rest every intermediate twist therefore lies on the target's
    curvature; the limits apply to braking as well. ``step`` keeps its own last
    output as state, so it must be called once per control cycle with the time
    since the previous call (injected, never read from a clock here).
    """

    def __init__(self, kinematics: DiffDriveKinematics, limits: VelocityLimits) -> None:
        self.kinematics = kinematics
        self.limits = limits
        self.linear_m_s = 0.0
        self.angular_rad_s = 0.0

    def reset(self) -> None:
        """Forget the last output (next ramp starts from rest)."""
        self.linear_m_s = 0.0
        self.angular_rad_s = 0.0

    def limit_speed(self, linear_m_s: float, angular_rad_s: float) -> tuple[float, float]:
        """Return the twist scaled by the largest factor <= 1 that meets every speed limit."""
        limits = self.limits
        left, right = self.kinematics.wheel_speeds(linear_m_s, angular_rad_s)
        scale = 1.0
        for value, bound in ((linear_m_s, limits.max_linear_m_s),
                             (angular_rad_s, limits.max_angular_rad_s),
                             (left, limits.max_wheel_rad_s), (right, limits.max_wheel_rad_s)):
            if abs(value) > bound:
                scale = min(scale, bound / abs(value))
        return linear_m_s * scale, angular_rad_s * scale

    def step(self, linear_m_s: float, angular_rad_s: float,
             dt_s: float) -> tuple[float, float]:
        """Move the output towards the (speed-limited) target within dt_s; return it."""
        target_linear, target_angular = self.limit_speed(linear_m_s, angular_rad_s)
        delta_linear = target_linear - self.linear_m_s
        delta_angular = target_angular - self.angular_rad_s
        dt_s = max(0.0, float(dt_s))
        scale = 1.0
        for delta, accel in ((delta_linear, self.limits.max_linear_accel_m_s2),
                             (delta_angular, self.limits.max_angular_accel_rad_s2)):
            allowed = accel * dt_s
            if abs(delta) > allowed:
                scale = min(scale, allowed / abs(delta))
        if scale >= 1.0:
            self.linear_m_s, self.angular_rad_s = target_linear, target_angular
        else:
            self.linear_m_s += delta_linear * scale
            self.angular_rad_s += delta_angular * scale
        return self.linear_m_s, self.angular_rad_s


@dataclass(frozen=True)
class OdometryEstimate:
    """Pose in the odometry frame and twist in the body frame, with 6x6 covariances.

    Covariances are row-major over (x, y, z, roll, pitch, yaw) as in
    ``nav_msgs/Odometry``: pose in m² / rad², twist in (m/s)² / (rad/s)².
    ``twist_valid`` is false while the wheel speeds are not known (the twist is
    then reported as zero with ``UNKNOWN_VARIANCE``).
    """

    x_m: float
    y_m: float
    yaw_rad: float
    linear_m_s: float
    angular_rad_s: float
    twist_valid: bool
    pose_covariance: tuple[float, ...]
    twist_covariance: tuple[float, ...]


def _diagonal(values: tuple[float, ...]) -> tuple[float, ...]:
    matrix = [0.0] * 36
    for index, value in enumerate(values):
        matrix[index * 7] = value
    return tuple(matrix)


class OdometryIntegrator:
    """Dead reckoning of a differential drive from wheel positions or measured speeds.

    Each ``update`` holds the wheel speeds constant over ``dt_s`` and integrates
    the resulting motion exactly: a circular arc (or a straight segment when the
    angular velocity is ~0), so driving a circle closes on itself however long
    the step is.

    Covariance model (simple, documented, not a calibration): the x/y variance
    grows by ``position_variance_per_m`` per metre travelled, the yaw variance
    by ``yaw_variance_per_rad`` per radian turned; z/roll/pitch are not measured
    (``UNKNOWN_VARIANCE``). The twist variances are constants while the wheels
    report, ``UNKNOWN_VARIANCE`` while they do not.
    """

    def __init__(self, kinematics: DiffDriveKinematics,
                 position_variance_per_m: float = 1.0e-3,
                 yaw_variance_per_rad: float = 1.0e-3,
                 linear_velocity_variance: float = 1.0e-3,
                 angular_velocity_variance: float = 1.0e-3) -> None:
        self.kinematics = kinematics
        self.position_variance_per_m = position_variance_per_m
        self.yaw_variance_per_rad = yaw_variance_per_rad
        self.linear_velocity_variance = linear_velocity_variance
        self.angular_velocity_variance = angular_velocity_variance
        self.reset()

    def reset(self, x_m: float = 0.0, y_m: float = 0.0, yaw_rad: float = 0.0) -> None:
        """Set the pose (and zero its uncertainty and the twist)."""
        self.x_m, self.y_m, self.yaw_rad = float(x_m), float(y_m), normalize_angle(yaw_rad)
        self.linear_m_s = 0.0
        self.angular_rad_s = 0.0
        self.twist_valid = False
        self.distance_m = 0.0
        self.rotation_rad = 0.0

    def update(self, left_rad_s: float, right_rad_s: float, dt_s: float) -> None:
        """Advance the pose by dt_s seconds at the given measured wheel speeds (rad/s)."""
        linear, angular = self.kinematics.body_velocity(left_rad_s, right_rad_s)
        self.linear_m_s, self.angular_rad_s, self.twist_valid = linear, angular, True
        dt_s = max(0.0, float(dt_s))
        if dt_s == 0.0:
            return
        self._move(linear * dt_s, angular * dt_s)

    def advance(self, left_delta_rad: float, right_delta_rad: float,
                left_rad_s: float, right_rad_s: float) -> None:
        """Advance the pose by the angles the wheels turned (rad), from their positions.

        As diff_drive_controller does with position feedback: the pose follows the
        wheels' position increments (no error from sampling the speed), the twist
        their measured speeds (rad/s).
        """
        distance, dtheta = self.kinematics.body_velocity(left_delta_rad, right_delta_rad)
        self.linear_m_s, self.angular_rad_s = self.kinematics.body_velocity(left_rad_s,
                                                                            right_rad_s)
        self.twist_valid = True
        self._move(distance, dtheta)

    def _move(self, distance: float, dtheta: float) -> None:
        """Move along an arc of length ``distance`` (m) turning by ``dtheta`` (rad)."""
        if abs(dtheta) < 1e-9:
            # Straight (to first order in dtheta): move along the mid-step heading.
            heading = self.yaw_rad + 0.5 * dtheta
            self.x_m += distance * math.cos(heading)
            self.y_m += distance * math.sin(heading)
        else:
            radius = distance / dtheta
            new_yaw = self.yaw_rad + dtheta
            self.x_m += radius * (math.sin(new_yaw) - math.sin(self.yaw_rad))
            self.y_m -= radius * (math.cos(new_yaw) - math.cos(self.yaw_rad))
        self.yaw_rad = normalize_angle(self.yaw_rad + dtheta)
        self.distance_m += abs(distance)
        self.rotation_rad += abs(dtheta)

    def hold(self) -> None:
        """Wheel speeds unknown: keep the pose, report zero twist as not measured."""
        self.linear_m_s = 0.0
        self.angular_rad_s = 0.0
        self.twist_valid = False

    @property
    def estimate(self) -> OdometryEstimate:
        position_variance = START_VARIANCE + self.position_variance_per_m * self.distance_m
        yaw_variance = START_VARIANCE + self.yaw_variance_per_rad * self.rotation_rad
        pose = _diagonal((position_variance, position_variance, UNKNOWN_VARIANCE,
                          UNKNOWN_VARIANCE, UNKNOWN_VARIANCE, yaw_variance))
        if self.twist_valid:
            linear, angular = self.linear_velocity_variance, self.angular_velocity_variance
        else:
            linear = angular = UNKNOWN_VARIANCE
        # vy is 0 by the non-holonomic constraint: as well known as vx.
        twist = _diagonal((linear, linear, UNKNOWN_VARIANCE, UNKNOWN_VARIANCE,
                           UNKNOWN_VARIANCE, angular))
        return OdometryEstimate(self.x_m, self.y_m, self.yaw_rad, self.linear_m_s,
                                self.angular_rad_s, self.twist_valid, pose, twist)
