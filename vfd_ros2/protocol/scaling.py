"""Velocity scaling: rad/s at the output shaft <-> the drive's native speed unit.

REP 103: the ROS side speaks rad/s at the wheel (output) shaft. The motor turns
``gear_ratio`` times faster; the drive speaks percent (of ``rated_speed_rpm``: the
profile's 100 %, a rated speed or a rated frequency's synchronous speed), Hz or rpm.
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass

from ..errors import ParameterError


class SpeedUnit(str, enum.Enum):
    """Engineering unit of a speed setpoint or feedback register."""

    PERCENT = 'percent'   # percent of VelocityScaling.rated_speed_rpm (the profile's 100 %)
    HZ = 'hz'             # output / synchronous frequency
    RPM = 'rpm'           # motor shaft speed


RPM_PER_RAD_S = 60.0 / (2.0 * math.pi)


@dataclass(frozen=True)
class VelocityScaling:
    """Converts between output-shaft rad/s and a native speed unit."""

    gear_ratio: float = 1.0
    invert_direction: bool = False
    rated_speed_rpm: float = 1500.0     # 100 % for percent setpoints
    pole_pairs: int = 2                 # Hz <-> rpm (synchronous speed)
    #: the two above are the profile's defaults, not the integrator's: a drive whose own
    #: nameplate makes them otherwise is told at connect (ModbusDrive.configure)
    rated_from_profile: bool = False
    pole_pairs_from_profile: bool = False

    def __post_init__(self) -> None:
        if not (math.isfinite(self.gear_ratio) and self.gear_ratio > 0):
            raise ParameterError(f'gear_ratio must be > 0, got {self.gear_ratio}')
        if not (math.isfinite(self.rated_speed_rpm) and self.rated_speed_rpm > 0):
            raise ParameterError(f'motor.rated_speed_rpm must be > 0, got {self.rated_speed_rpm}')
        if self.pole_pairs < 1:
            raise ParameterError(f'motor.pole_pairs must be >= 1, got {self.pole_pairs}')

    @property
    def _sign(self) -> float:
        return -1.0 if self.invert_direction else 1.0

    def output_to_motor_rpm(self, velocity: float) -> float:
        """Output-shaft rad/s -> motor rpm (sign = drive's direction)."""
        return velocity * self.gear_ratio * RPM_PER_RAD_S * self._sign

    def motor_rpm_to_output(self, rpm: float) -> float:
        """Motor rpm (drive's sign) -> output-shaft rad/s."""
        return rpm / (self.gear_ratio * RPM_PER_RAD_S) * self._sign

    def rpm_to_native(self, rpm: float, unit: SpeedUnit) -> float:
        if unit is SpeedUnit.RPM:
            return rpm
        if unit is SpeedUnit.PERCENT:
            return rpm / self.rated_speed_rpm * 100.0
        return rpm * self.pole_pairs / 60.0

    def native_to_rpm(self, value: float, unit: SpeedUnit) -> float:
        if unit is SpeedUnit.RPM:
            return value
        if unit is SpeedUnit.PERCENT:
            return value / 100.0 * self.rated_speed_rpm
        return value * 60.0 / self.pole_pairs

    def to_native(self, velocity: float, unit: SpeedUnit) -> float:
        """Output-shaft rad/s -> native speed value (engineering units)."""
        return self.rpm_to_native(self.output_to_motor_rpm(velocity), unit)

    def from_native(self, value: float, unit: SpeedUnit) -> float:
        """Native speed value -> output-shaft rad/s."""
        return self.motor_rpm_to_output(self.native_to_rpm(value, unit))

    def frequency_to_output(self, hertz: float) -> float:
        """Output frequency (Hz, synchronous) -> output-shaft rad/s."""
        return self.from_native(hertz, SpeedUnit.HZ)
