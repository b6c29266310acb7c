"""Unit tests of velocity scaling: output-shaft rad/s <-> rpm, percent, Hz."""

from __future__ import annotations

import math

import pytest

from vfd_ros2.errors import ParameterError
from vfd_ros2.profiles import SpeedUnit
from vfd_ros2.protocol.scaling import RPM_PER_RAD_S, VelocityScaling

TWO_PI = 2.0 * math.pi


def rad_s_for_motor_rpm(rpm: float, gear_ratio: float) -> float:
    """Output-shaft rad/s at which the motor turns ``rpm`` (computed from first principles)."""
    return rpm / gear_ratio * TWO_PI / 60.0


def test_rpm_per_rad_s():
    # One revolution per second is 2 pi rad/s and 60 rpm.
    assert RPM_PER_RAD_S * TWO_PI == pytest.approx(60.0)


def test_am_example_100_percent_is_rated_speed_at_the_motor():
    """100 % of 1330 rpm (AM D00.05) through a 10:1 gear."""
    scaling = VelocityScaling(gear_ratio=10.0, rated_speed_rpm=1330.0)
    velocity = rad_s_for_motor_rpm(1330.0, 10.0)          # ~13.93 rad/s at the wheel
    assert velocity == pytest.approx(13.9277, abs=1e-4)
    assert scaling.to_native(velocity, SpeedUnit.PERCENT) == pytest.approx(100.0)
    assert scaling.to_native(velocity, SpeedUnit.RPM) == pytest.approx(1330.0)
    assert scaling.to_native(velocity / 2, SpeedUnit.PERCENT) == pytest.approx(50.0)
    assert scaling.to_native(-velocity, SpeedUnit.PERCENT) == pytest.approx(-100.0)
    assert scaling.from_native(100.0, SpeedUnit.PERCENT) == pytest.approx(velocity)


@pytest.mark.parametrize('gear_ratio', [1.0, 10.0, 0.5, 37.5])
def test_motor_rpm_follows_the_gear(gear_ratio):
    scaling = VelocityScaling(gear_ratio=gear_ratio)
    # 1 rad/s at the output is 60 / 2pi rpm at the output, gear_ratio times that at the motor.
    assert scaling.output_to_motor_rpm(1.0) == pytest.approx(gear_ratio * 60.0 / TWO_PI)
    assert scaling.motor_rpm_to_output(600.0) == pytest.approx(600.0 / gear_ratio * TWO_PI / 60)


@pytest.mark.parametrize('pole_pairs, rpm, hertz', [
    (2, 1500.0, 50.0),      # 4-pole motor: 1500 rpm synchronous at 50 Hz
    (1, 3000.0, 50.0),
    (3, 1200.0, 60.0),
    (4, 900.0, 60.0),
])
def test_hz_is_synchronous_speed(pole_pairs, rpm, hertz):
    scaling = VelocityScaling(pole_pairs=pole_pairs)
    assert scaling.rpm_to_native(rpm, SpeedUnit.HZ) == pytest.approx(hertz)
    assert scaling.native_to_rpm(hertz, SpeedUnit.HZ) == pytest.approx(rpm)


def test_hz_with_gear():
    scaling = VelocityScaling(gear_ratio=20.0, pole_pairs=2)
    # 50 Hz on a 4-pole motor = 1500 rpm at the motor = 75 rpm at the wheel.
    expected = 75.0 * TWO_PI / 60.0
    assert scaling.from_native(50.0, SpeedUnit.HZ) == pytest.approx(expected)
    assert scaling.frequency_to_output(50.0) == pytest.approx(expected)
    assert scaling.to_native(expected, SpeedUnit.HZ) == pytest.approx(50.0)


def test_percent_of_rated_speed():
    scaling = VelocityScaling(rated_speed_rpm=1450.0)
    assert scaling.rpm_to_native(1450.0, SpeedUnit.PERCENT) == pytest.approx(100.0)
    assert scaling.rpm_to_native(725.0, SpeedUnit.PERCENT) == pytest.approx(50.0)
    assert scaling.native_to_rpm(-20.0, SpeedUnit.PERCENT) == pytest.approx(-290.0)


def test_rpm_is_native_rpm():
    scaling = VelocityScaling(rated_speed_rpm=1450.0, pole_pairs=3)
    assert scaling.rpm_to_native(1234.5, SpeedUnit.RPM) == 1234.5
    assert scaling.native_to_rpm(-42.0, SpeedUnit.RPM) == -42.0


@pytest.mark.parametrize('unit', list(SpeedUnit))
def test_invert_direction_flips_the_sign_only(unit):
    plain = VelocityScaling(gear_ratio=7.0, rated_speed_rpm=1400.0, pole_pairs=2)
    inverted = VelocityScaling(gear_ratio=7.0, rated_speed_rpm=1400.0, pole_pairs=2,
                               invert_direction=True)
    for velocity in (2.5, -1.0):
        native = plain.to_native(velocity, unit)
        assert native != 0
        assert inverted.to_native(velocity, unit) == pytest.approx(-native)
        assert inverted.from_native(-native, unit) == pytest.approx(velocity)


@pytest.mark.parametrize('unit', list(SpeedUnit))
@pytest.mark.parametrize('invert', [False, True])
@pytest.mark.parametrize('velocity', [0.0, 1e-3, 1.0, -3.7, 25.0, -120.0])
def test_round_trip(unit, invert, velocity):
    scaling = VelocityScaling(gear_ratio=12.5, invert_direction=invert,
                              rated_speed_rpm=1330.0, pole_pairs=2)
    assert scaling.from_native(scaling.to_native(velocity, unit), unit) == \
        pytest.approx(velocity, abs=1e-12)


def test_zero_is_zero_in_every_unit():
    scaling = VelocityScaling(gear_ratio=3.0, invert_direction=True)
    for unit in SpeedUnit:
        assert scaling.to_native(0.0, unit) == 0.0
        assert scaling.from_native(0.0, unit) == 0.0


def test_defaults():
    scaling = VelocityScaling()
    assert scaling.gear_ratio == 1.0 and not scaling.invert_direction
    assert scaling.rated_speed_rpm == 1500.0 and scaling.pole_pairs == 2


@pytest.mark.parametrize('kwargs, name', [
    ({'gear_ratio': 0.0}, 'gear_ratio'),
    ({'gear_ratio': -10.0}, 'gear_ratio'),
    ({'gear_ratio': math.nan}, 'gear_ratio'),
    ({'gear_ratio': math.inf}, 'gear_ratio'),
    ({'rated_speed_rpm': 0.0}, 'rated_speed_rpm'),
    ({'rated_speed_rpm': -1500.0}, 'rated_speed_rpm'),
    ({'rated_speed_rpm': math.nan}, 'rated_speed_rpm'),
    ({'rated_speed_rpm': math.inf}, 'rated_speed_rpm'),
    ({'pole_pairs': 0}, 'pole_pairs'),
    ({'pole_pairs': -2}, 'pole_pairs'),
])
def test_bad_settings_raise(kwargs, name):
    with pytest.raises(ParameterError, match=name):
        VelocityScaling(**kwargs)
