"""A wheel as a joint: position (rad), velocity (rad/s) and effort (N·m) at the output shaft.

What ``sensor_msgs/JointState`` needs, from what one poll learnt (no ROS here).
The profile says where the position comes from (``position:``):
- ``source: drive``: a counter the drive reports (encoder counts, CiA 402 0x6064),
  unwrapped across the counter's roll-over and scaled by counts per motor
  revolution, the gear ratio and the direction;
- ``source: integrated``: the drive reports none, so the measured speed is
  integrated each control cycle (drifts like any dead reckoning).
Effort comes from the profile's ``effort:`` signal (a torque in N·m or in % of
the rated torque, times the gear ratio); NaN where the drive gives none.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from ..drives import Reading
from ..errors import ParameterError
from ..profiles import EffortKind, Profile
from ..protocol.scaling import VelocityScaling


@dataclass(frozen=True)
class JointConfig:
    """How to turn a drive's readings into joint values."""

    from_drive: bool = False        # position from a counter the drive reports
    signal: str = ''                # its monitor role
    counts_per_rev: float = 0.0     # counts per motor revolution
    counter_bits: int = 32          # the counter wraps at 2**bits
    effort_signal: str = ''         # '' = no effort
    effort_per_unit: float = 0.0    # N·m at the output shaft per unit of the effort signal
    gear_ratio: float = 1.0
    invert_direction: bool = False

    @property
    def source(self) -> str:
        """'drive' or 'integrated' (DriveStatus / diagnostics wording)."""
        return 'drive' if self.from_drive else 'integrated'


def joint_config(profile: Profile, scaling: VelocityScaling, counts_per_rev: float = 0.0,
                 rated_torque: float = 0.0) -> JointConfig:
    """Build from the profile, the node's scaling and its overrides (0 = profile's value).

    ``rated_torque`` (N·m at the motor) converts a percent torque; 0 leaves effort empty.
    Raises ParameterError on a counts_per_rev or rated_torque that is negative or not finite.
    """
    for name, value in (('position.counts_per_rev', counts_per_rev),
                        ('motor.rated_torque', rated_torque)):
        if not (math.isfinite(value) and value >= 0):
            raise ParameterError(f'{name} must be a finite number >= 0, got {value}')
    spec = profile.position
    bits = 32
    if spec.from_drive:
        signal = profile.signal(spec.signal)
        if signal is not None and signal.code in profile.parameters:
            bits = profile.parameters[signal.code].type.bits
    sign = -1.0 if scaling.invert_direction else 1.0
    effort_signal, per_unit = '', 0.0
    effort = profile.effort
    if effort is not None:
        if effort.kind is EffortKind.TORQUE:
            effort_signal, per_unit = effort.signal, 1.0
        elif rated_torque > 0:
            effort_signal, per_unit = effort.signal, rated_torque / 100.0
    return JointConfig(
        from_drive=spec.from_drive, signal=spec.signal,
        counts_per_rev=counts_per_rev or spec.counts_per_rev, counter_bits=bits,
        effort_signal=effort_signal, effort_per_unit=per_unit * scaling.gear_ratio * sign,
        gear_ratio=scaling.gear_ratio, invert_direction=scaling.invert_direction)


class JointTracker:
    """Position, velocity and effort of one wheel, updated once per control cycle.

    Only the loop thread calls ``update``; the values are copied into the
    controller's snapshot. The position starts at 0 rad at the first reading
    (a counter's absolute value has no meaning for a wheel); while the drive is
    offline nothing is integrated and a counter's jump across the gap is taken
    as it comes (the count keeps counting while the link is down).
    """

    def __init__(self, config: JointConfig) -> None:
        self.config = config
        self.position = math.nan
        self.velocity = math.nan
        self.effort = math.nan
        self._last_count: float | None = None
        self._last_time: float | None = None
        self._counts = 0.0

    def update(self, reading: Reading, now: float, online: bool) -> None:
        """Take one poll's values (called every cycle, also while offline)."""
        config = self.config
        self.velocity = reading.measured_velocity if online else math.nan
        raw_effort = reading.values.get(config.effort_signal) if config.effort_signal else None
        self.effort = raw_effort * config.effort_per_unit \
            if online and raw_effort is not None else math.nan
        if config.from_drive:
            self._update_counter(reading.values.get(config.signal) if online else None)
        else:
            self._integrate(now, online)

    def _update_counter(self, count: float | None) -> None:
        if count is None or not math.isfinite(count):
            return          # keep the last position (NaN before the first count)
        config = self.config
        if self._last_count is not None:
            modulus = float(1 << config.counter_bits)
            delta = (count - self._last_count) % modulus
            if delta >= modulus / 2:
                delta -= modulus
            self._counts += delta
        self._last_count = count
        revolutions = self._counts / config.counts_per_rev / config.gear_ratio
        sign = -1.0 if config.invert_direction else 1.0
        self.position = sign * 2.0 * math.pi * revolutions

    def _integrate(self, now: float, online: bool) -> None:
        last, self._last_time = self._last_time, now
        if math.isnan(self.position):
            self.position = 0.0
        if not online or last is None or not math.isfinite(self.velocity):
            return
        self.position += self.velocity * max(0.0, now - last)
