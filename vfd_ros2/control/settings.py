"""The driver's settings: one table, shared by the ROS parameters and the factory.

Every entry is declared as a ROS parameter by the nodes (plus the selected
transport's ``transport.*`` and drive class's ``drive.*`` settings); the factory
(``factory.py``) fills in the defaults from here. Tools and tests use the same
names without ROS.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Mapping

from ..errors import ParameterError
from ..profiles import Profile
from ..protocol.scaling import VelocityScaling
from .controller import ControllerConfig


@dataclass(frozen=True)
class Setting:
    """One setting: name, default, what it means, its valid range, whether it is live.

    ``minimum``/``maximum`` (inclusive, ``None`` = unbounded) become the ROS
    parameter's range; ``live`` settings can be changed while the driver runs
    (``DriveController.reconfigure``), all others are read-only once started.
    """

    name: str
    default: Any
    description: str
    minimum: float | None = None
    maximum: float | None = None
    live: bool = False


SETTINGS: tuple[Setting, ...] = (
    Setting('drive.profile', 'boneng_am', 'drive family: a shipped profile name or a YAML path'),
    Setting('transport.type', 'modbus_rtu', 'transport plugin: modbus_rtu, modbus_tcp, ...'),
    Setting('transport.unit_id', 1,
            "the drive's address on the link (Modbus slave id, CANopen node id)", 0, 255),
    Setting('gear_ratio', 1.0, 'motor turns per output-shaft turn', 0.001, 10000.0),
    Setting('invert_direction', False, 'reverse the sign between ROS and the drive'),
    Setting('motor.rated_speed_rpm', 0.0,
            "motor rpm of a 100 % setpoint; 0 = the profile's nameplate default (the rated "
            'speed, or where the profile says so, the synchronous speed of the rated frequency)',
            0.0, 100000.0),
    Setting('motor.pole_pairs', 0, 'motor pole pairs (Hz <-> rpm); 0 = profile default', 0, 100),
    Setting('max_velocity', 10.0, 'rad/s at the output shaft; larger commands are clamped',
            0.001, 10000.0, live=True),
    Setting('command_timeout', 0.5, 's without a valid velocity command before the drive stops',
            0.01, 60.0, live=True),
    Setting('control_rate', 50.0, 'Hz of the command/poll cycle (of the bus thread on a bus)',
            0.5, 10000.0, live=True),
    Setting('realtime_priority', 0,
            'SCHED_FIFO priority (1..99) of the control thread, so that a loaded machine '
            'cannot delay its cycles; 0 = normal scheduling. Needs CAP_SYS_NICE or an '
            'rtprio limit; a refusal is a diagnostics warning', 0, 99),
    Setting('status_rate', 20.0, 'Hz of ~/status (a Modbus drive reads the values only '
            'shown there and in /diagnostics at the faster rate, not every cycle)', 0.1, 1000.0,
            live=True),
    Setting('diagnostics_rate', 1.0, 'Hz of /diagnostics', 0.01, 100.0, live=True),
    Setting('comm_loss_threshold', 2, 'consecutive failed cycles before the drive is offline',
            1, 1000),
    Setting('reconnect_period', 0.5, 's between reconnect attempts', 0.01, 60.0),
    Setting('drive_comm_timeout', 0.3,
            "s written to the drive's own comm-loss timeout at connect (raised to fit the bus, "
            'and reported); 0 = disable it', 0.0, 60.0),
    Setting('apply_commissioning', True,
            "write the profile's bus-control settings at connect when they differ"),
    Setting('auto_enable', False,
            'enable at start-up and, on a managed node, at each activate (motion still '
            'needs fresh commands)', live=True),
    Setting('action_timeout', 2.0, 's to verify enable and reset_fault', 0.01, 600.0, live=True),
    Setting('stop_timeout', 10.0, 's to verify stop and disable (covers the deceleration)',
            0.01, 600.0, live=True),
    Setting('frame_id', '', 'header.frame_id of ~/status'),
    Setting('joint_name', '',
            "JointState name of this wheel ('' = the namespace's last part, e.g. "
            "left_wheel for /agv/left_wheel, else the node name)"),
    Setting('position.counts_per_rev', 0.0,
            "counts per motor revolution of the drive's position counter; 0 = the "
            "profile's value (unused where the profile integrates the speed)", 0.0, 1e9),
    Setting('motor.rated_torque', 0.0,
            "N·m, the motor's rated torque: converts a torque in % to JointState.effort; "
            '0 = no effort from a percent torque', 0.0, 1e6),
)


def prefixed(values: Mapping[str, Any], prefix: str) -> dict[str, Any]:
    """Return the ``<prefix>.*`` values with the prefix removed."""
    return {key.split('.', 1)[1]: value for key, value in values.items()
            if key.startswith(f'{prefix}.')}


def velocity_scaling(profile: Profile, values: Mapping[str, Any]) -> VelocityScaling:
    """Return gear, direction and motor nameplate (0 = the profile's default)."""
    def nameplate(setting: str, code: str, fallback: float) -> float:
        configured = float(values.get(setting, 0) or 0)
        if configured:
            return configured
        if code and profile.parameters[code].default:
            return float(profile.parameters[code].default)
        return fallback
    pole_pairs = int(nameplate('motor.pole_pairs', profile.velocity.pole_pairs, 2))
    base = float(values.get('motor.rated_speed_rpm', 0) or 0) or \
        profile.velocity.percent_base_rpm(
            lambda code: pole_pairs if code == profile.velocity.pole_pairs else
            float(profile.parameters[code].default or 0), 1500.0)
    return VelocityScaling(
        gear_ratio=float(values['gear_ratio']),
        invert_direction=bool(values['invert_direction']),
        rated_speed_rpm=base, pole_pairs=pole_pairs,
        rated_from_profile=not float(values.get('motor.rated_speed_rpm', 0) or 0),
        pole_pairs_from_profile=not int(values.get('motor.pole_pairs', 0) or 0))


def shown_period(status_rate: float, diagnostics_rate: float) -> float:
    """Return the period of the messages that show the measured values, the faster's."""
    return 1.0 / max(status_rate, diagnostics_rate)


def controller_config(values: Mapping[str, Any]) -> ControllerConfig:
    rate = float(values['control_rate'])
    if not rate > 0:
        raise ParameterError(f'control_rate must be > 0, got {rate}')
    return ControllerConfig(
        command_timeout=float(values['command_timeout']),
        max_velocity=float(values['max_velocity']),
        cycle_period=1.0 / rate,
        comm_loss_threshold=int(values['comm_loss_threshold']),
        reconnect_period=float(values['reconnect_period']),
        drive_comm_timeout=float(values['drive_comm_timeout']),
        apply_commissioning=bool(values['apply_commissioning']),
        auto_enable=bool(values['auto_enable']),
        action_timeout=float(values['action_timeout']),
        stop_timeout=float(values['stop_timeout']),
        realtime_priority=int(values['realtime_priority']),
        shown_period=shown_period(float(values['status_rate']),
                                  float(values['diagnostics_rate'])),
    )
