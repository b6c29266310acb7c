"""Unit tests of the controller's settings and its velocity-command intake (no thread, no ROS)."""

from __future__ import annotations

import dataclasses
import math

import pytest

from unit_support import MemoryTransport, shipped_profile
from vfd_ros2.control import settings as config
from vfd_ros2.control.controller import ControllerConfig, DriveController
from vfd_ros2.control.state import CommandOutcome
from vfd_ros2.drives.modbus import ModbusDrive
from vfd_ros2.errors import ParameterError
from vfd_ros2.protocol.scaling import VelocityScaling

# --- ControllerConfig ------------------------------------------------------------------------

POSITIVE_FIELDS = ('command_timeout', 'max_velocity', 'cycle_period', 'reconnect_period',
                   'action_timeout', 'stop_timeout')


def test_defaults_are_valid():
    cfg = ControllerConfig()
    assert cfg.command_timeout > 0 and cfg.max_velocity > 0 and cfg.cycle_period > 0


@pytest.mark.parametrize('name', POSITIVE_FIELDS)
@pytest.mark.parametrize('value', [0.0, -1.0, math.nan, math.inf, -math.inf])
def test_rejects_non_positive_or_non_finite(name, value):
    with pytest.raises(ParameterError, match=f'{name} must be > 0'):
        ControllerConfig(**{name: value})


@pytest.mark.parametrize('name', POSITIVE_FIELDS)
def test_accepts_small_positive_values(name):
    assert getattr(ControllerConfig(**{name: 1e-3}), name) == 1e-3


@pytest.mark.parametrize('value', [-0.1, math.nan, math.inf])
def test_drive_comm_timeout_rejects(value):
    with pytest.raises(ParameterError, match='drive_comm_timeout must be >= 0'):
        ControllerConfig(drive_comm_timeout=value)


def test_drive_comm_timeout_zero_disables():
    assert ControllerConfig(drive_comm_timeout=0.0).drive_comm_timeout == 0.0


@pytest.mark.parametrize('value', [0, -3])
def test_comm_loss_threshold_rejects(value):
    with pytest.raises(ParameterError, match='comm_loss_threshold must be >= 1'):
        ControllerConfig(comm_loss_threshold=value)


# --- DriveController.command_velocity ------------------------------------------------------------

class FakeClock:
    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


@pytest.fixture
def clock() -> FakeClock:
    return FakeClock()


def make_controller(clock: FakeClock, **settings) -> tuple[DriveController, MemoryTransport]:
    profile = shipped_profile('boneng_am')
    transport = MemoryTransport()
    drive = ModbusDrive(profile, transport, 1,
                        VelocityScaling(gear_ratio=10.0, rated_speed_rpm=1330.0))
    cfg = ControllerConfig(**{'command_timeout': 0.5, 'max_velocity': 2.0, **settings})
    return DriveController(drive, cfg, clock=clock), transport


@pytest.mark.parametrize('value', [math.nan, math.inf, -math.inf])
def test_non_finite_command_is_rejected_and_does_not_feed(clock, value):
    controller, _ = make_controller(clock)
    assert controller.command_velocity(value) is CommandOutcome.REJECTED
    assert not controller._watchdog.ever_fed
    controller._publish_state()
    state = controller.state
    assert state.rejected_commands == 1
    assert state.clamped_commands == 0
    assert state.commanded_velocity == 0.0


def test_rejected_command_keeps_the_last_valid_one_and_its_age(clock):
    controller, _ = make_controller(clock)
    assert controller.command_velocity(1.5) is CommandOutcome.ACCEPTED
    clock.now += 0.4
    assert controller.command_velocity(math.nan) is CommandOutcome.REJECTED
    assert controller._watchdog.age == pytest.approx(0.4)   # not refreshed by the NaN
    assert controller._velocity == 1.5                        # not replaced by the NaN
    clock.now += 0.2
    assert controller._watchdog.expired                       # 0.6 s > 0.5 s


@pytest.mark.parametrize('value', [0.0, 1.0, -1.0, 2.0, -2.0, 1e-9])
def test_accepted(clock, value):
    controller, _ = make_controller(clock)
    assert controller.command_velocity(value) is CommandOutcome.ACCEPTED
    assert controller._velocity == value
    assert controller._watchdog.ever_fed and not controller._watchdog.expired


@pytest.mark.parametrize('value, limited', [(2.5, 2.0), (-2.5, -2.0), (1e9, 2.0),
                                            (-1e9, -2.0), (2.0000001, 2.0)])
def test_clamped(clock, value, limited):
    controller, _ = make_controller(clock)
    assert controller.command_velocity(value) is CommandOutcome.CLAMPED
    assert controller._velocity == limited
    assert not controller._watchdog.expired                   # a clamped command is valid


def test_counters(clock):
    controller, _ = make_controller(clock)
    outcomes = [controller.command_velocity(v)
                for v in (1.0, 3.0, math.nan, -5.0, 0.5, math.inf, 2.0, -math.inf)]
    assert outcomes.count(CommandOutcome.ACCEPTED) == 3
    assert outcomes.count(CommandOutcome.CLAMPED) == 2
    assert outcomes.count(CommandOutcome.REJECTED) == 3
    controller._publish_state()
    state = controller.state
    assert state.clamped_commands == 2
    assert state.rejected_commands == 3


def test_state_is_published_only_on_publish(clock):
    controller, _ = make_controller(clock)
    controller.command_velocity(math.nan)
    assert controller.state.rejected_commands == 0           # the snapshot is not live
    controller._publish_state()
    assert controller.state.rejected_commands == 1
    assert controller.state.state == 'offline' and not controller.state.online


def test_nan_alone_never_starts_the_motor(clock):
    """One loop step on an in-memory drive: enabled, online, but only NaN commands."""
    controller, transport = make_controller(clock, auto_enable=True)
    run = shipped_profile('boneng_am').control.values['run']
    controller.command_velocity(math.nan)
    controller.step()                       # connect, then one control cycle
    state = controller.state
    assert state.online
    assert state.state == 'watchdog' and state.watchdog_tripped
    assert run not in transport.writes_to(0xE720)
    assert transport.registers[0xE721] == 0

    controller.command_velocity(1.0)        # a valid command does start it
    controller.step()
    assert controller.state.state == 'running'
    assert transport.writes_to(0xE720)[-2:] == [0, run]     # rising edge, then run
    assert transport.registers[0xE721] != 0


# --- config: settings -> scaling and controller config --------------------------------------

def settings(**values):
    merged = {s.name: s.default for s in config.SETTINGS}
    merged.update(values)
    return merged


def test_velocity_scaling_uses_nameplate_defaults():
    # The AM's 100 % is the synchronous speed of its rated frequency D00.04 (50 Hz at
    # 2 pole pairs), not its rated speed D00.05 (1330 rpm): outside audit of the profile.
    profile = shipped_profile('boneng_am')
    scaling = config.velocity_scaling(profile, settings(gear_ratio=10.0))
    assert profile.parameters[profile.velocity.rated_frequency].default == 50.0
    assert scaling.rated_speed_rpm == 1500.0
    assert scaling.pole_pairs == profile.parameters[profile.velocity.pole_pairs].default == 2
    assert scaling.gear_ratio == 10.0 and not scaling.invert_direction
    # More pole pairs, a slower synchronous speed; a configured 100 % wins.
    assert config.velocity_scaling(profile, settings(**{'motor.pole_pairs': 4})) \
        .rated_speed_rpm == 750.0
    assert config.velocity_scaling(profile, settings(**{'motor.rated_speed_rpm': 1400.0})) \
        .rated_speed_rpm == 1400.0
    # Without rated_frequency, a percent is of the rated speed (D00.05, 1330 rpm).
    of_rated_speed = dataclasses.replace(
        profile, velocity=dataclasses.replace(profile.velocity, rated_frequency=''))
    assert config.velocity_scaling(of_rated_speed, settings()).rated_speed_rpm == 1330.0


def test_velocity_scaling_prefers_configured_values():
    profile = shipped_profile('boneng_am')
    scaling = config.velocity_scaling(profile, settings(**{
        'motor.rated_speed_rpm': 1450.0, 'motor.pole_pairs': 3, 'invert_direction': True,
        'gear_ratio': 4.0}))
    assert scaling.rated_speed_rpm == 1450.0 and scaling.pole_pairs == 3
    assert scaling.invert_direction and scaling.gear_ratio == 4.0


def test_velocity_scaling_pole_pairs_from_another_profile():
    profile = shipped_profile('veichi_ehs100')
    expected = profile.parameters[profile.velocity.pole_pairs].default
    assert expected
    assert config.velocity_scaling(profile, settings()).pole_pairs == int(expected)


def test_velocity_scaling_falls_back_without_nameplate():
    profile = shipped_profile('imo_hd2')
    assert not profile.velocity.rated_speed and not profile.velocity.pole_pairs
    scaling = config.velocity_scaling(profile, settings())
    assert scaling.rated_speed_rpm == 1500.0 and scaling.pole_pairs == 2


def test_velocity_scaling_rejects_bad_values():
    profile = shipped_profile('boneng_am')
    with pytest.raises(ParameterError, match='gear_ratio'):
        config.velocity_scaling(profile, settings(gear_ratio=0.0))
    with pytest.raises(ParameterError, match='rated_speed_rpm'):
        config.velocity_scaling(profile, settings(**{'motor.rated_speed_rpm': -1.0}))


def test_controller_config_from_settings():
    cfg = config.controller_config(settings(control_rate=50.0, max_velocity=3.0))
    assert cfg.cycle_period == pytest.approx(0.02)
    assert cfg.max_velocity == 3.0
    for value in (0.0, -10.0, math.nan):
        with pytest.raises(ParameterError, match='control_rate must be > 0'):
            config.controller_config(settings(control_rate=value))


def test_prefixed_settings_strip_the_prefix():
    values = {'transport.port': '/dev/x', 'transport.unit_id': 2, 'gear_ratio': 3.0,
              'drive.object_set': 'ds402'}
    assert config.prefixed(values, 'transport') == {'port': '/dev/x', 'unit_id': 2}
    assert config.prefixed(values, 'drive') == {'object_set': 'ds402'}


@pytest.mark.parametrize('value', [-1, 100])
def test_realtime_priority_outside_sched_fifo_range_is_refused(value):
    with pytest.raises(ParameterError, match='realtime_priority must be 0..99'):
        ControllerConfig(realtime_priority=value)


def test_every_numeric_setting_has_a_range():
    """ros2 param describe shows each number's valid range (none was missing a limit)."""
    unbounded = [s.name for s in config.SETTINGS
                 if isinstance(s.default, (int, float)) and not isinstance(s.default, bool)
                 and (s.minimum is None or s.maximum is None)]
    assert unbounded == []


def test_standstill_is_five_motor_rpm_or_the_at_speed_tolerance_not_a_share_of_the_limit():
    """A stop is verified at standstill (outside audit of the first version).

    2 % of max_velocity made a direct-drive wheel reading 1 rpm at rest (0.105 rad/s)
    fail every stop with max_velocity 5, and called a motor coasting at 16 rpm still
    with max_velocity 100.
    """
    from vfd_ros2.control.controller import standstill
    one_rpm = 2 * math.pi / 60
    for limit in (5.0, 100.0):
        direct = standstill(ControllerConfig(max_velocity=limit), VelocityScaling())
        assert direct == pytest.approx(5 * one_rpm)            # 1-3 rpm at rest is still
        assert direct < 16 * one_rpm                            # 16 rpm coasting is not
        geared = standstill(ControllerConfig(max_velocity=limit),
                            VelocityScaling(gear_ratio=10.0, invert_direction=True))
        assert geared == pytest.approx(0.1)                     # at_speed_tolerance
    assert standstill(ControllerConfig(), None) == pytest.approx(0.1)   # a plugin's drive


def _follow(controller: DriveController, clock: FakeClock, command: float,
            measured: float, seconds: float, period: float = 0.02) -> list[str]:
    """Run _check_following over ``seconds`` of polls; return what it said at each."""
    from vfd_ros2.drives.base import Reading
    said = []
    for _ in range(round(seconds / period)):
        clock.now += period
        controller._velocity = command() if callable(command) else command  # noqa: SLF001
        value = measured() if callable(measured) else measured
        controller._reading = Reading(flags={'running': True},             # noqa: SLF001
                                      measured_velocity=value)
        controller._check_following()                                     # noqa: SLF001
        said.append(controller._not_following)                            # noqa: SLF001
    return said


def test_a_noisy_stall_under_a_command_of_alternating_sign_is_told(clock):
    # A reading's noise (a motor at rest read as 1-3 rpm) counted as progress each time
    # the command changed sign, and the stall was never told (outside re-check).
    import random
    controller, _ = make_controller(clock, max_velocity=5.0, stop_timeout=1.0)
    controller._run_written = True                                         # noqa: SLF001
    noise = random.Random(7)
    polls = iter(range(10 ** 6))
    said = _follow(controller, clock, lambda: 3.0 if next(polls) // 25 % 2 else -3.0,
                   lambda: noise.gauss(0.0, 0.1), 20.0)
    first = next(i for i, text in enumerate(said) if text)
    assert first * 0.02 < 1.5, first
    assert sum(1 for text in said[first:] if not text) == 0       # and stays told
    # A healthy reversal through zero at a slow ramp is no stall, noise or not.
    controller, _ = make_controller(clock, max_velocity=5.0, stop_timeout=1.0)
    controller._run_written = True                                         # noqa: SLF001
    speed = [3.0]

    def ramping() -> float:
        speed[0] = max(speed[0] - 0.6 * 0.02, -3.0)      # 10 s from +3 to -3
        return speed[0] + noise.gauss(0.0, 0.03)
    assert not any(_follow(controller, clock, -3.0, ramping, 12.0))
