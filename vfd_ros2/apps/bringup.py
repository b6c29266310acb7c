"""Bringup logic shared by the launch files and the demo (kept here, tested).

A launch file only turns these NodeSpecs into launch_ros ``Node`` actions, so
everything a launch test would have to check is plain Python.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import yaml

from ..control.settings import SETTINGS

DEFAULT_SIM_DIR = '/tmp/vfd_ros2/sim_agv'
#: the demo's lines: apart from the simulated AGV's, so both can run side by side
DEFAULT_DEMO_DIR = '/tmp/vfd_ros2/demo'
#: executables that can run as managed (lifecycle) nodes: ``--managed [--autostart]``
MANAGEABLE = ('drive_node', 'bus_node')


def flag(value: Any) -> bool:
    """Return a launch argument ('true'/'false', any case, or a bool) as a bool."""
    if isinstance(value, bool):
        return value
    text = str(value).strip().lower()
    if text not in ('true', 'false', '1', '0'):
        raise ValueError(f'expected true or false, got {value!r}')
    return text in ('true', '1')


def lifecycle_arguments(managed: Any, autostart: Any) -> tuple[str, ...]:
    """Return the command-line options of a drive/bus node for ``managed``/``autostart``."""
    if not flag(managed):
        return ()
    return ('--managed', '--autostart') if flag(autostart) else ('--managed',)


@dataclass(frozen=True)
class NodeSpec:
    """One node to start: executable of this package, name, namespace, parameters."""

    executable: str
    name: str
    namespace: str
    parameters: dict[str, Any] = field(default_factory=dict)
    arguments: tuple[str, ...] = ()

    def managed(self, managed: Any, autostart: Any = True) -> NodeSpec:
        """Return this spec as a managed node (drive_node, bus_node; others unchanged)."""
        if self.executable not in MANAGEABLE:
            return self
        return replace(self, arguments=lifecycle_arguments(managed, autostart))

    def launch_kwargs(self) -> dict[str, Any]:
        """Return the keyword arguments of a launch_ros ``Node`` action for this spec.

        ``emulate_tty`` is off: a piped or logged launch output carries no ANSI codes.
        """
        return {'package': 'vfd_ros2', 'executable': self.executable, 'name': self.name,
                'namespace': self.namespace, 'parameters': [dict(self.parameters)],
                'arguments': list(self.arguments), 'output': 'screen', 'emulate_tty': False}

    @property
    def fully_qualified_name(self) -> str:
        return f'{self.namespace.rstrip("/")}/{self.name}'

    def params_document(self) -> dict[str, Any]:
        """Return the ``--params-file`` YAML document for this node."""
        return {self.fully_qualified_name: {'ros__parameters': dict(self.parameters)}}

    def write_params_file(self, directory: Path) -> Path:
        path = Path(directory) / f'{self.fully_qualified_name.strip("/").replace("/", "__")}.yaml'
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(yaml.safe_dump(self.params_document(), sort_keys=False))
        return path

    def command(self, params_file: Path) -> list[str]:
        """Return the argv for running the node as a process (``ros2 run`` equivalent)."""
        return [self.executable, *self.arguments, '--ros-args', '-r', f'__ns:={self.namespace}',
                '-r', f'__node:={self.name}', '--params-file', str(params_file)]


def drive_spec(namespace: str, parameters: dict[str, Any], name: str = 'drive') -> NodeSpec:
    """Describe a drive_node; unknown parameter names are refused here, not at run time."""
    known = {s.name for s in SETTINGS}
    unknown = [key for key in parameters if key not in known and
               not key.startswith('transport.')]
    if unknown:
        raise ValueError(f'unknown drive_node parameters: {unknown}')
    return NodeSpec('drive_node', name, namespace, dict(parameters))


def sim_wheels(directory: str = DEFAULT_DEMO_DIR, profile: str = 'boneng_am',
               wheels: tuple[str, ...] = ('left_wheel', 'right_wheel'),
               gear_ratio: float = 10.0, ramp_time: float = 1.0) -> list[NodeSpec]:
    """Per wheel, a simulated drive on its own pty line and its own drive_node.

    The right wheel is mounted mirrored, so its driver inverts the direction:
    both wheels then turn "forward" for a positive command (REP 103).
    """
    specs: list[NodeSpec] = []
    for index, wheel in enumerate(wheels):
        port = f'{directory}/{wheel}'
        namespace = f'/agv/{wheel}'
        specs.append(NodeSpec('sim_drive', 'sim_drive', namespace, {
            'profile': profile,
            'port': port,
            'unit_ids': [1],
            'initial_values': [f'acceleration_time={ramp_time}',
                               f'deceleration_time={ramp_time}'],
        }))
        specs.append(drive_spec(namespace, {
            'drive.profile': profile,
            'transport.type': 'modbus_rtu',
            'transport.port': port,
            'transport.unit_id': 1,
            **_wheel_settings(wheel, index, gear_ratio),
        }))
    return specs


#: rad/s at a simulated wheel: the drives' max_velocity, and what diff_drive's limits derive from
WHEEL_LIMIT = 5.0


def _wheel_settings(wheel: str, index: int, gear_ratio: float) -> dict[str, Any]:
    return {
        'gear_ratio': gear_ratio,
        'invert_direction': index % 2 == 1,
        'max_velocity': WHEEL_LIMIT,
        'command_timeout': 0.5,
        # The drives' own comm-loss timeout: 1 s tolerates a loaded 2-core machine
        # running simulators and drivers side by side (0.3 s on a real robot).
        'drive_comm_timeout': 1.0,
        'frame_id': f'{wheel}_link',
    }


def sim_agv_bus(directory: str = DEFAULT_SIM_DIR, profile: str = 'boneng_am',
                wheels: tuple[str, ...] = ('left_wheel', 'right_wheel'),
                gear_ratio: float = 10.0) -> dict[str, Any]:
    """Return the simulated AGV's bus file: every wheel's drive on one RS-485 line."""
    return {
        'bus': {'name': 'rs485_0', 'transport.type': 'modbus_rtu',
                'transport.port': f'{directory}/rs485', 'transport.timeout': 0.05,
                'control_rate': 50.0},
        'drives': {wheel: {'namespace': f'/agv/{wheel}', 'drive.profile': profile,
                           'transport.unit_id': unit, 'auto_enable': True,
                           **_wheel_settings(wheel, unit - 1, gear_ratio)}
                   for unit, wheel in enumerate(wheels, start=1)},
    }


def write_bus_file(document: dict[str, Any], directory: str) -> Path:
    path = Path(directory) / 'bus.yaml'
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(yaml.safe_dump(document, sort_keys=False))
    return path


def sim_agv(directory: str = DEFAULT_SIM_DIR, profile: str = 'boneng_am',
            wheels: tuple[str, ...] = ('left_wheel', 'right_wheel'), gear_ratio: float = 10.0,
            ramp_time: float = 1.0, wheel_radius: float = 0.1,
            track_width: float = 0.5) -> list[NodeSpec]:
    """Return the simulated AGV's nodes: one RS-485 line, one bus_node, diff_drive.

    The wheels' drives sit on ONE simulated line (slave ids 1..n), one bus_node
    serves a drive node per wheel, and diff_drive turns cmd_vel (TwistStamped)
    into wheel commands and the wheels' joint states into odom. The bus file must exist: see
    ``write_bus_file``.
    """
    bus = sim_agv_bus(directory, profile, wheels, gear_ratio)
    return [
        NodeSpec('sim_drive', 'sim_drive', '/agv', {
            'profile': profile, 'port': bus['bus']['transport.port'],
            'unit_ids': list(range(1, len(wheels) + 1)),
            'initial_values': [f'acceleration_time={ramp_time}',
                               f'deceleration_time={ramp_time}']}),
        NodeSpec('bus_node', 'bus', '/agv', {'config_file': f'{directory}/bus.yaml'}),
        NodeSpec('diff_drive', 'diff_drive', '/agv', {
            'wheel_radius': wheel_radius, 'track_width': track_width,
            'left_wheel_command_topic': f'/agv/{wheels[0]}/drive/velocity_command',
            'right_wheel_command_topic': f'/agv/{wheels[1]}/drive/velocity_command',
            'left_wheel_status_topic': f'/agv/{wheels[0]}/drive/status',
            'right_wheel_status_topic': f'/agv/{wheels[1]}/drive/status',
            'left_wheel_joint_states_topic': f'/agv/{wheels[0]}/joint_states',
            'right_wheel_joint_states_topic': f'/agv/{wheels[1]}/joint_states',
            'use_stamped_vel': True, 'max_wheel_velocity': WHEEL_LIMIT,
            # the twist within what the wheels can do: straight ahead, and on the spot
            'max_linear_velocity': WHEEL_LIMIT * wheel_radius,
            'max_angular_velocity': 2.0 * WHEEL_LIMIT * wheel_radius / track_width}),
    ]
