"""bus_node: one process owns one link (RS-485 line, TCP connection).

It serves one ROS node per drive on it, with the same topics and services as drive_node.

    ros2 run vfd_ros2 bus_node --ros-args -p config_file:=config/sim_agv_bus.yaml

The bus file lists the link (``bus``: transport.* and control_rate) and the drives
(``drives``: namespace, drive.profile, transport.unit_id and any drive_node
setting). A per-bus entry on /diagnostics reports transactions/s, errors,
timeouts and, for RS-485, the share of the wire's capacity in use.

For ros2_control (topic_based_ros2_control), ``joint_commands_topic`` and
``joint_states_topic`` make the bus take sensor_msgs/JointState velocity
commands for its drives' joint names and publish their joint states together
(see joint_topics.py); both are off ('') by default.
"""

from __future__ import annotations

import sys
from typing import Any, Iterable, Sequence

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rcl_interfaces.msg import ParameterDescriptor
from rclpy.exceptions import NameValidationException
from rclpy.lifecycle import LifecycleNode
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.validate_namespace import validate_namespace
from rclpy.validate_node_name import validate_node_name

from ..control.bus import BUS_KEYS, Bus, BusStatistics, load_bus_config
from ..control.settings import SETTINGS
from ..drives import drive_class_for
from ..errors import ParameterError
from ..transports import load_transport_class
from .drive_node import DriveNode, autostart
from .executable import CONFIGURATION_ERRORS, run_node
from .joint_topics import JointCommandBridge
from .managed import DriveTransitions, ManagedTransitions, parse_options
from .messages import add_loop_rate, bus_diagnostic_name
from .parameters import (
    LiveParameters,
    check_value,
    descriptor,
    meant_for,
    params_files,
    params_sections,
    section_matches,
    unknown_overrides,
)


def bus_diagnostic(name: str, hardware_id: str, stats: BusStatistics,
                   drives_online: int, drives: int, control_rate: float,
                   closed: str = '') -> DiagnosticStatus:
    """Return the bus's /diagnostics entry; ``closed``: why the host closed its link."""
    status = DiagnosticStatus(name=name, hardware_id=hardware_id)
    if closed:          # a managed bus unconfigured: no data, not a comm loss
        status.level, status.message = DiagnosticStatus.STALE, closed
    elif drives_online == 0:
        status.level, status.message = DiagnosticStatus.ERROR, 'no drive answers'
    elif drives_online < drives:
        status.level = DiagnosticStatus.WARN
        status.message = f'{drives - drives_online} of {drives} drives offline'
    else:
        status.level, status.message = DiagnosticStatus.OK, f'{drives} drives online'
    utilisation = 'unknown' if stats.utilisation is None else f'{100 * stats.utilisation:.1f}'
    pairs = [('transactions/s', f'{stats.transactions_per_second:.1f}'),
             ('errors', stats.errors), ('timeouts', stats.timeouts),
             ('bad frames', stats.bad_frames), ('wire utilisation (%)', utilisation),
             ('cycle overruns', stats.overruns), ('drives online', f'{drives_online}/{drives}')]
    status.values = [KeyValue(key=k, value=str(v)) for k, v in pairs]
    add_loop_rate(status, stats.cycles_per_second, stats.rate_short and not closed,
                  control_rate, drives)
    return status


class BusNode(Node):
    def __init__(self, node_name: str = 'bus', managed: bool = False,
                 command_line: Sequence[str] = (), **kwargs: Any) -> None:
        """Serve one link and a drive node per drive; ``managed``: see ``ManagedBusNode``.

        ``command_line``: the process's arguments, whose params files are checked for
        sections meant for the drives' nodes (they reach none).
        """
        super().__init__(node_name, **kwargs)
        self.drive_nodes: list[DriveNode] = []
        try:
            path = self.declare_parameter('config_file', '', ParameterDescriptor(
                description='bus YAML: the link and its drives', read_only=True)).value
            self.config = load_bus_config(path)
            self.bus = Bus(self.config)
            # The bus thread's rate is the bus node's (live); the drives' nodes show it read-only.
            rates = {s.name: s for s in SETTINGS if s.name in BUS_KEYS}
            rate = rates['control_rate']
            configured = float(self.config.settings.get('control_rate', rate.default))
            value = self.declare_parameter('control_rate', configured, descriptor(
                rate.description, rate.default, rate.minimum, rate.maximum, live=True)).value
            check_value('control_rate', value, rate.minimum, rate.maximum)
            if value != configured:
                self.bus.set_rate(float(value))
            priority = rates['realtime_priority']
            in_file = int(self.config.settings.get('realtime_priority', 0))
            given = self.declare_parameter('realtime_priority', in_file, descriptor(
                priority.description + ' (set it in the bus file)', priority.default,
                priority.minimum, priority.maximum)).value
            if given != in_file:
                # Shown, and not what the bus thread runs at (outside audit): refused.
                raise ParameterError(
                    f'realtime_priority {given} given to the bus node: the bus thread takes '
                    f'it from the bus file only (bus: realtime_priority, {in_file} there)')
            # Declared before the live-parameter check is installed (it refuses the rest).
            joint_topics = {name: self.declare_parameter(name, default, descriptor(
                description, default, *limits)).value
                for name, default, description, *limits in (
                ('joint_commands_topic', '', 'sensor_msgs/JointState velocity commands in, by '
                 "joint name (topic_based_ros2_control's joint_commands_topic); '' = none"),
                ('joint_states_topic', '', "the drives' joint states out, together "
                 "(topic_based_ros2_control's joint_states_topic); '' = none"),
                ('joint_states_rate', 50.0, 'Hz of joint_states_topic', 0.01, 1000.0))}
            self._refuse_drive_settings_given_here()
            self.live_parameters = LiveParameters(
                self, {'control_rate'}, self._apply_parameters,
                {'control_rate': (rate.minimum, rate.maximum)})
            names: dict[str, str] = {}
            for entry in self.config.drives:
                values = {**self.config.settings, **entry.settings}
                values['control_rate'] = 1.0 / self.bus.period
                # One clock for the whole process: the drives' status and joint_states
                # stamps on the bus node's (a launch file's use_sim_time is given to it).
                values['use_sim_time'] = self.get_parameter('use_sim_time').value
                namespace = entry.namespace if entry.namespace.startswith('/') else \
                    f'{self.get_namespace().rstrip("/")}/{entry.namespace}'
                try:        # before rclpy makes a node of them (it warns on its way out)
                    validate_namespace(namespace)
                    validate_node_name(entry.name)
                except NameValidationException as exc:
                    raise ParameterError(f'drive {entry.key}: {exc}') from exc
                name = f'{namespace.rstrip("/")}/{entry.name}'
                if name in names:
                    # one velocity command topic would move both motors
                    raise ParameterError(f'drives {names[name]} and {entry.key} are both {name}: '
                                         'give each drive its own namespace')
                names[name] = entry.key
                try:
                    # use_global_arguments=False: a launch file's __ns/__node remaps are meant
                    # for the bus node, not for the drives' nodes (the bus file names them).
                    self.drive_nodes.append(DriveNode(
                        entry.name, controller=self.bus.controllers[entry.key], managed=managed,
                        own_timers=False, on_rate_change=self._schedule_publishing,
                        namespace=namespace, context=self.context, use_global_arguments=False,
                        parameter_overrides=[Parameter(k, value=v) for k, v in values.items()]))
                except CONFIGURATION_ERRORS as exc:
                    raise ParameterError(f'drive {entry.key}: {exc}') from exc
            self._refuse_sections_for(names, command_line)
            self.joints = JointCommandBridge(
                self, self.drive_nodes, str(joint_topics['joint_commands_topic']),
                str(joint_topics['joint_states_topic']), float(joint_topics['joint_states_rate']))
            self.diagnostics_pub = self.create_publisher(DiagnosticArray, '/diagnostics', 10)
            self._publish_timers: list = []
            self._schedule_publishing()
            if not managed:
                self.bus.start()
            self.get_logger().info(f'bus {self.config.name}: {len(self.drive_nodes)} drives on '
                                   f'{self.bus.transport.description}')
        except BaseException:
            # Refused (a bus file mistake): what was made so far goes, port unopened.
            self._release()
            raise

    def _refuse_drive_settings_given_here(self) -> None:
        """Refuse drive settings given to the bus node (params file, -p): they reach no drive.

        The drives' nodes take their settings from the bus file only, so a
        ``max_velocity`` or ``command_timeout`` meant for them would be dropped
        without a word; anything else unknown is only reported.
        """
        unknown = unknown_overrides(self)
        transport = load_transport_class(str(self.config.settings.get('transport.type',
                                                                      'modbus_rtu')))
        drive_settings = {s.name for s in SETTINGS} | \
            {f'transport.{p.name}' for p in transport.parameters} | \
            {f'drive.{p.name}' for p in drive_class_for(transport).settings}
        misplaced = meant_for(unknown, drive_settings | set(self._parameters))
        if misplaced:
            raise ParameterError(
                f'{", ".join(misplaced.values())} given to bus_node (params file or -p) would '
                f'reach no drive: set them per drive, or for the line, in the bus file '
                f'({self.get_parameter("config_file").value})')
        if unknown:
            self.get_logger().warning(f'parameters given but not known to bus_node, not '
                                      f'applied: {", ".join(unknown)}')

    def _release(self) -> None:
        """Destroy what was made of a node refused while it was being built."""
        for node in self.drive_nodes:
            node.destroy_node()
        super().destroy_node()

    def _refuse_sections_for(self, drives: Iterable[str], command_line: Sequence[str]) -> None:
        """Refuse a params file section meant for one of the ``drives``' nodes: it reaches none.

        A drive's node takes its settings from the bus file only (it ignores the
        process's arguments: a launch file's remaps are the bus node's). Sections that
        match the bus node too (``/**``) are checked as its own parameters.
        """
        own = self.get_fully_qualified_name()
        for path in params_files(command_line):
            sections = [key for key in params_sections(path) if not section_matches(key, own)]
            for drive in drives:
                meant = next((key for key in sections if section_matches(key, drive)), None)
                if meant is not None:
                    raise ParameterError(
                        f'params file {path}: section {meant} is for drive node {drive}, '
                        'which takes its settings from the bus file only: put them there '
                        f'({self.get_parameter("config_file").value})')

    def _schedule_publishing(self) -> None:
        """One timer per distinct rate serves every drive (again after a rate changed).

        A timer per drive node and rate was an executor wake-up each: most of a
        many-drive bus_node's CPU.
        """
        for timer in self._publish_timers:
            self.destroy_timer(timer)
        self._publish_timers = []
        for rate in sorted({node.status_rate for node in self.drive_nodes}):
            group = [node for node in self.drive_nodes if node.status_rate == rate]
            self._publish_timers.append(self.create_timer(
                1.0 / rate, lambda group=group: self._publish_status(group)))
        for rate in sorted({node.diagnostics_rate for node in self.drive_nodes} | {1.0}):
            group = [node for node in self.drive_nodes if node.diagnostics_rate == rate]
            self._publish_timers.append(self.create_timer(
                1.0 / rate, lambda group=group, rate=rate:
                self._publish_diagnostics(group, with_bus=rate == 1.0)))

    def _apply_parameters(self, changes: dict[str, Any]) -> None:
        rate = float(changes['control_rate'])
        self.bus.set_rate(rate)
        # What each drive's node shows follows the bus (read-only there: set internally).
        for node in self.drive_nodes:
            node.show_bus_rate(rate)

    def _publish_status(self, group: list[DriveNode]) -> None:
        for node in group:
            node.publish_status()       # never raises

    def _publish_diagnostics(self, group: list[DriveNode], with_bus: bool) -> None:
        """One DiagnosticArray: the drives of ``group`` and, once a second, the bus."""
        try:
            array = DiagnosticArray()
            array.header.stamp = self.get_clock().now().to_msg()
            array.status = [node.diagnostic_status() for node in group]
            if with_bus:
                states = [c.state for c in self.bus.controllers.values()]
                closed = states[0].link_closed if all(s.link_closed for s in states) else ''
                array.status.append(bus_diagnostic(
                    bus_diagnostic_name(self.get_fully_qualified_name(), self.config.name),
                    self.bus.transport.description, self.bus.statistics(),
                    sum(s.online for s in states), len(states), 1.0 / self.bus.period,
                    closed))
            self.diagnostics_pub.publish(array)
        except Exception as exc:  # noqa: BLE001 - never raise into the executor
            if self.context.ok():       # (a timer that fired as Ctrl-C shut the context)
                self.get_logger().error(f'bus diagnostics failed: {exc}',
                                        throttle_duration_sec=5.0)

    def destroy_node(self) -> None:
        self.bus.shutdown()      # every drive is commanded to stop before the port closes
        for node in self.drive_nodes:
            node.destroy_node()
        super().destroy_node()


class ManagedBusNode(ManagedTransitions, BusNode, LifecycleNode):
    """bus_node as a managed (lifecycle) node (transitions: ``managed.py``).

    Every drive of the bus moves through the transitions together; the drives'
    own nodes stay plain nodes, gated by the bus node's state.
    """

    def __init__(self, node_name: str = 'bus', **kwargs: Any) -> None:
        super().__init__(node_name, managed=True, **kwargs)
        self.transitions = DriveTransitions(
            self.get_logger(), self.bus.start, self.bus.shutdown,
            {node.get_fully_qualified_name(): (node.controller, self._gate(node))
             for node in self.drive_nodes}, self.context.ok)
        self.transitions.mark_unconfigured()       # as it starts: unconfigured
        self._refuse_unavailable_transitions()

    @staticmethod
    def _gate(node: DriveNode):
        def allow(allowed: bool) -> None:
            node.motion_allowed = allowed
        return allow


def make_bus_node(args: list[str] | None = None, **kwargs: Any) -> BusNode:
    """Return the node the command line asks for: plain, or managed (and autostarted)."""
    options = parse_options(args)
    command_line = args if args is not None else sys.argv
    if not options.managed:
        return BusNode(command_line=command_line, **kwargs)
    node = ManagedBusNode(command_line=command_line, **kwargs)
    if options.autostart:
        autostart(node)
    return node


def main(args: list[str] | None = None) -> int:
    return run_node('bus_node', lambda: make_bus_node(args), args,
                    extra_nodes=lambda node: node.drive_nodes)


if __name__ == '__main__':      # python -m, as well as the ros2 run launcher
    raise SystemExit(main())
