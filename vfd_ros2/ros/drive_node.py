"""drive_node: one ROS 2 node per drive.

Topics (relative to the node, e.g. /agv/left_wheel/drive/...):
  ~/velocity_command  std_msgs/Float64        in: rad/s at the output shaft
  ~/<setpoint>        std_msgs/Float64        in: the profile's extra setpoints (e.g.
                                              ~/pressure_setpoint), engineering units
  ~/status            vfd_ros2/DriveStatus    out: at status_rate
  ~/fault             vfd_ros2/DriveFault     out: on change, transient local
  joint_states        sensor_msgs/JointState  out: at status_rate, one joint named by
                                              joint_name: position rad, velocity rad/s,
                                              effort N·m (empty where not measured)
  /diagnostics        diagnostic_msgs/DiagnosticArray
Services:
  ~/get_drive_parameter, ~/set_drive_parameter   vfd_ros2/srv/...
  ~/enable, ~/disable, ~/stop, ~/reset_fault     std_srvs/Trigger

All drive I/O happens in the controller's own thread. Callbacks here only hand
over commands; a service callback submits its action to the controller and is
answered from the control thread when it is done (``deferred_service``), so one
executor thread serves everything and a slow service (a stop that waits for the
ramp) never holds up status or commands. None of them lets an exception reach
the executor.
"""

from __future__ import annotations

import math
from typing import Any, Callable

from builtin_interfaces.msg import Time as TimeMsg
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from rclpy.lifecycle import LifecycleNode, TransitionCallbackReturn
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64
from std_srvs.srv import Trigger

from vfd_ros2.msg import DriveFault, DriveStatus
from vfd_ros2.srv import GetDriveParameter, SetDriveParameter

from ..control.actions import NOT_SERVED
from ..control.bus import BUS_KEYS
from ..control.controller import DriveController
from ..control.factory import build_controller
from ..control.loop import RateWatch
from ..control.settings import SETTINGS, shown_period
from ..control.state import CommandOutcome, DriveState
from ..drives import drive_class_for
from ..errors import ParameterError, VfdError, quote
from ..profiles import NO_FAULT
from ..transports import load_transport_class
from .deferred_service import Deferred, create_deferred_service
from .executable import run_node
from .managed import DriveTransitions, ManagedTransitions, parse_options
from .messages import (
    StatusMessage,
    add_loop_rate,
    default_joint_name,
    diagnostic_status,
    drive_diagnostic_name,
    fault_message,
    update_joint_state,
)
from .parameters import (
    LiveParameters,
    check_value,
    descriptor,
    meant_for,
    unknown_overrides,
)

FAULT_QOS = QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL,
                       reliability=ReliabilityPolicy.RELIABLE)

#: Requests a service holds before the executor takes them. The default (10) drops
#: requests of a burst silently (200 concurrent ~/enable calls from 16 clients got 41
#: answers); every request is taken at once and answered (duplicates together), so a
#: deep queue costs nothing while idle.
SERVICE_QOS = QoSProfile(depth=256, reliability=ReliabilityPolicy.RELIABLE)


class DriveNode(Node):
    """ROS face of one drive; all drive logic lives in DriveController."""

    def __init__(self, node_name: str = 'drive', controller: DriveController | None = None,
                 managed: bool = False, own_timers: bool = True,
                 on_rate_change: Callable[[], None] | None = None, **kwargs: Any) -> None:
        """Make a drive node; with ``controller`` given, a bus runs that controller's loop.

        ``managed``: the loop starts at configure and motion is allowed only while
        active (``ManagedDriveNode``, or a managed bus's drives); see ``managed.py``.
        ``own_timers=False``: the owner calls ``publish_status`` and collects
        ``diagnostic_status`` on its own timers (a bus serves all its drives from
        one timer per rate instead of two per drive: every timer is an executor
        wake-up) and is told of a changed rate by ``on_rate_change``.
        """
        super().__init__(node_name, **kwargs)
        try:
            #: velocity commands and ~/enable are taken (a managed node: only while active)
            self.motion_allowed = not managed
            # Live: validated and applied at once. A bus's rate and priority belong to the
            # bus node (read-only here); auto_enable acts at start-up only on a plain node,
            # at every activate on a managed one.
            fixed_here = (set() if managed else {'auto_enable'}) | \
                (set(BUS_KEYS) if controller is not None else set())
            live = {s.name for s in SETTINGS if s.live and s.name not in fixed_here}
            values = {s.name: self._declare(s.name, s.default, s.description, s.minimum,
                                            s.maximum, s.name in live) for s in SETTINGS}
            for setting in SETTINGS:
                check_value(setting.name, values[setting.name], setting.minimum, setting.maximum)
            transport_class = load_transport_class(str(values['transport.type']))
            for prefix, settings in (('transport', transport_class.parameters),
                                     ('drive', drive_class_for(transport_class).settings)):
                for setting in settings:
                    name = f'{prefix}.{setting.name}'
                    values[name] = self._declare(name, setting.default, setting.description,
                                                 setting.minimum, setting.maximum)
                    check_value(name, values[name], setting.minimum, setting.maximum)
            self._refuse_misspelt_parameters()
            self._owns_controller = controller is None
            self.controller: DriveController = controller or build_controller(values)
            self.profile_name = self.controller.drive.profile.name
            self.frame_id = str(values['frame_id'])
            self._ever_online = False
            self._last_fault = NO_FAULT
            self._fault_published = False
            # the snapshot ~/status and joint_states were last built from, and those messages
            # (kept and updated: see StatusMessage)
            self._published_state: DriveState | None = None
            self._status = StatusMessage(self.frame_id, self.profile_name)

            self.status_pub = self.create_publisher(DriveStatus, '~/status', 10)
            self.fault_pub = self.create_publisher(DriveFault, '~/fault', FAULT_QOS)
            self.joint_name = str(values['joint_name']) or \
                default_joint_name(self.get_namespace(), self.get_name())
            self.joint_pub = self.create_publisher(JointState, 'joint_states', 10)
            self._joint_msg = JointState(name=[self.joint_name])
            self.create_subscription(Float64, '~/velocity_command', self._on_velocity, 10)
            for topic in self.controller.drive.profile.setpoints:
                self.create_subscription(Float64, f'~/{topic}',
                                         lambda msg, t=topic: self._on_setpoint(t, msg), 10)
            create_deferred_service(self, GetDriveParameter, '~/get_drive_parameter',
                                    self._on_get_parameter, SERVICE_QOS)
            create_deferred_service(self, SetDriveParameter, '~/set_drive_parameter',
                                    self._on_set_parameter, SERVICE_QOS)
            for action in ('enable', 'disable', 'stop', 'reset_fault'):
                create_deferred_service(self, Trigger, f'~/{action}',
                                        self._trigger_handler(action), SERVICE_QOS)
            self.status_rate = float(values['status_rate'])
            self.diagnostics_rate = float(values['diagnostics_rate'])
            self._on_rate_change = on_rate_change
            self._rate_timers = {}
            self._loop_rate = RateWatch()
            if own_timers:
                self.diagnostics_pub = self.create_publisher(DiagnosticArray, '/diagnostics', 10)
                self._rate_timers = {
                    'status_rate': self.create_timer(1.0 / self.status_rate, self.publish_status),
                    'diagnostics_rate': self.create_timer(1.0 / self.diagnostics_rate,
                                                          self._publish_diagnostics)}
            self.live_parameters = LiveParameters(
                self, live, self._apply_parameters,
                {s.name: (s.minimum, s.maximum) for s in SETTINGS})
            if managed:
                self.controller.intent.enabled = False       # enabled at activate, per policy
            elif self._owns_controller:
                self.controller.start()
            self.get_logger().info(
                f'driving {self.controller.drive.hardware_id} (profile {self.profile_name})')
        except BaseException:
            # Refused (a setting that cannot work): the node goes, nothing opened.
            self._release()
            raise

    def _refuse_misspelt_parameters(self) -> None:
        """Refuse given parameters this node does not know that look meant for it.

        rclpy drops unknown overrides: a misspelt ``comand_timeout`` would leave the
        watchdog at its default without a word. Any other (a params file shared by
        several nodes) is named in a warning.
        """
        unknown = unknown_overrides(self)
        ours = meant_for(unknown, self._parameters)
        if ours:
            raise ParameterError(f'unknown parameter(s) {", ".join(ours.values())}: '
                                 'nothing started')
        if unknown:
            self.get_logger().warning(f'parameters given but not known to drive_node, not '
                                      f'applied: {", ".join(unknown)}')

    def _release(self) -> None:
        """Destroy what rclpy made of a node refused while it was being built."""
        super().destroy_node()

    def _declare(self, name: str, default: Any, description: str,
                 minimum: float | None = None, maximum: float | None = None,
                 live: bool = False) -> Any:
        return self.declare_parameter(
            name, default, descriptor(description, default, minimum, maximum, live)).value

    def show_bus_rate(self, rate: float) -> None:
        """Show the bus thread's new rate in this drive's read-only ``control_rate``."""
        self._parameters['control_rate'] = Parameter('control_rate', value=float(rate))

    def _apply_parameters(self, changes: dict[str, Any]) -> None:
        """Apply live parameters at once (all validated first; raises, changing nothing)."""
        config: dict[str, Any] = {}
        for name, value in changes.items():
            if name == 'control_rate':
                config['cycle_period'] = 1.0 / float(value)
            elif name == 'auto_enable':
                config['auto_enable'] = bool(value)
            elif name in ('max_velocity', 'command_timeout', 'action_timeout', 'stop_timeout'):
                config[name] = float(value)
        rates = {name: float(changes[name]) for name in ('status_rate', 'diagnostics_rate')
                 if name in changes}
        if rates:       # the values shown are read as often as the messages show them
            config['shown_period'] = shown_period(
                rates.get('status_rate', self.status_rate),
                rates.get('diagnostics_rate', self.diagnostics_rate))
        if config:
            self.controller.reconfigure(**config)
        for name, rate in rates.items():
            setattr(self, name, rate)
            if name in self._rate_timers:
                timer = self._rate_timers[name]
                timer.timer_period_ns = round(1e9 / rate)
                timer.reset()       # the new period from now, not after the old one's end
        if rates and self._on_rate_change is not None:
            self._on_rate_change()          # a bus regroups its drives' timers

    # --- topics -----------------------------------------------------------------

    def _on_velocity(self, msg: Float64) -> None:
        try:
            if not self.motion_allowed:
                # A zero asks for nothing an inactive node does not do: a diff_drive's
                # stream of zeros while a managed bus waits to be configured is not a
                # warning every 2 s per wheel (outside audit). (Two calls: rclpy refuses
                # one call site logging at two severities.)
                text = (f'velocity command {msg.data} ignored: the node is not active '
                        '(lifecycle: configure and activate it)')
                if msg.data != 0.0:
                    self.get_logger().warning(text, throttle_duration_sec=2.0)
                else:
                    self.get_logger().debug(text, throttle_duration_sec=2.0)
                return
            outcome = self.controller.command_velocity(msg.data)
            if outcome is CommandOutcome.REJECTED:
                self.get_logger().warning(
                    f'rejected velocity command {msg.data}: not a finite number',
                    throttle_duration_sec=1.0)
            elif outcome is CommandOutcome.CLAMPED:
                self.get_logger().warning(
                    f'velocity command {msg.data} clamped to max_velocity '
                    f'{self.controller.config.max_velocity}', throttle_duration_sec=1.0)
        except Exception as exc:  # noqa: BLE001 - never raise into the executor
            self.get_logger().error(f'velocity command failed: {exc}')

    def _on_setpoint(self, topic: str, msg: Float64) -> None:
        try:
            self.controller.command_setpoint(topic, msg.data)
        except VfdError as exc:
            self.get_logger().warning(f'rejected {topic} {msg.data}: {exc}',
                                      throttle_duration_sec=1.0)
        except Exception as exc:  # noqa: BLE001 - never raise into the executor
            self.get_logger().error(f'{topic} failed: {exc}')

    def publish_status(self) -> None:
        """Publish ``~/status`` and, when it changed, ``~/fault``."""
        try:
            state = self.controller.state
            self._ever_online |= state.online
            now = self.get_clock().now().nanoseconds
            status = self._status.message
            _set_stamp(status.header.stamp, now)
            measured = state is not self._published_state
            if measured:
                self._status.update(state)
                update_joint_state(self._joint_msg, [state])
                _set_stamp(self._joint_msg.header.stamp, self._measured_at(state, now))
                self._published_state = state
            # else: the loop has not polled since (a drive on a long bus cycle): the same
            # snapshot gives the same status with a new stamp. joint_states carries when
            # its position was measured, so it waits for the next: the same stamp twice
            # is TF_REPEATED_DATA to robot_state_publisher's listeners.
            self.status_pub.publish(status)
            if measured:
                self.joint_pub.publish(self._joint_msg)
            fault = state.active_fault
            if not self._fault_published or (fault.code, fault.subcode) != \
                    (self._last_fault.code, self._last_fault.subcode):
                # A cleared fault is published once as inactive with its last code.
                shown, active = (fault, True) if fault.active else (self._last_fault, False)
                stamp = TimeMsg(sec=status.header.stamp.sec, nanosec=status.header.stamp.nanosec)
                self.fault_pub.publish(fault_message(shown, active, stamp, state.hardware_id))
                self._last_fault = fault
                self._fault_published = True
        except Exception as exc:  # noqa: BLE001
            if self.context.ok():       # (a timer that fired as Ctrl-C shut the context)
                self.get_logger().error(f'status publishing failed: {exc}',
                                        throttle_duration_sec=5.0)

    def _measured_at(self, state: DriveState, now: int) -> int:
        """Return when ``state`` was measured, in ns on the node's clock (``now``: its time).

        JointState's stamp: two wheels' positions then pair up by time (diff_drive),
        although the bus read them a cycle apart and their nodes publish them
        together. Under simulated time, or for a state older than a second, ``now``.
        """
        age = self.controller.age_of(state)
        if self.get_clock().ros_time_is_active or not 0.0 <= age < 1.0:
            return now
        return now - round(age * 1e9)

    def diagnostic_status(self) -> DiagnosticStatus:
        """Return this drive's entry on /diagnostics."""
        name = drive_diagnostic_name(self.get_fully_qualified_name())
        return diagnostic_status(self.controller.state, name, self._ever_online)

    def _publish_diagnostics(self) -> None:
        try:
            array = DiagnosticArray()
            array.header.stamp = self.get_clock().now().to_msg()
            status = self.diagnostic_status()
            cycles = self.controller.loop_cycles
            if cycles is not None and self._owns_controller:     # (a bus shows its own)
                rate, short = self._loop_rate.sample(cycles, self.controller.config.cycle_period)
                add_loop_rate(status, rate, short, 1.0 / self.controller.config.cycle_period)
            array.status = [status]
            self.diagnostics_pub.publish(array)
        except Exception as exc:  # noqa: BLE001
            if self.context.ok():
                self.get_logger().error(f'diagnostics failed: {exc}', throttle_duration_sec=5.0)

    # --- services ---------------------------------------------------------------

    def _answer(self, action: str, args: tuple, response: Any,
                fill: Callable[[Any, Any], None]) -> Deferred:
        """Submit ``action`` to the control thread; ``fill`` the response when it is done."""
        deferred = Deferred()

        def done(result: Any) -> None:
            try:
                fill(response, result.result())
            except Exception as exc:  # noqa: BLE001 - the caller gets an answer, always
                response.success, response.message = False, f'{action} failed: {exc}'
            deferred.complete(response)
        self.controller.submit(action, *args).add_done_callback(done)
        return deferred

    def _trigger_handler(self, action: str):
        def fill(response: Trigger.Response, result: Any) -> None:
            response.success, response.message = result.success, result.message
            if response.success:
                self.get_logger().info(f'{action}: {response.message}')
            else:
                self.get_logger().warning(f'{action} refused: {response.message}')

        def handle(_request: Trigger.Request, response: Trigger.Response) -> Any:
            try:
                if action == 'enable' and not self.motion_allowed:
                    response.success = False
                    response.message = 'the node is not active (lifecycle): activate it ' \
                        'first' if self.controller.serving_actions else NOT_SERVED
                    self.get_logger().warning(f'enable refused: {response.message}')
                    return response
                return self._answer(action, (), response, fill)
            except Exception as exc:  # noqa: BLE001
                response.success, response.message = False, f'{action} failed: {exc}'
                return response
        return handle

    def _on_get_parameter(self, request: GetDriveParameter.Request,
                          response: GetDriveParameter.Response) -> Any:
        def fill(response: GetDriveParameter.Response, result: Any) -> None:
            response.success, response.message = result.success, result.message
            if result.value is None:
                return
            value = result.value
            parameter = value.parameter
            response.name = parameter.name
            response.code = parameter.code
            response.value = float(value.value)
            response.raw_value = int(value.raw)
            response.unit = parameter.unit
            response.value_text = value.text
            response.minimum = float(parameter.minimum) if parameter.minimum is not None \
                else -math.inf
            response.maximum = float(parameter.maximum) if parameter.maximum is not None \
                else math.inf
            response.writable = self.controller.parameter_writable(parameter.code)
        try:
            self.controller.drive.profile.parameter(request.name)   # unknown: answer at once
            return self._answer('get_parameter', (request.name,), response, fill)
        except ParameterError as exc:
            response.success, response.message = False, str(exc)
        except Exception as exc:  # noqa: BLE001
            response.success, response.message = False, f'get failed: {exc}'
        return response

    def _on_set_parameter(self, request: SetDriveParameter.Request,
                          response: SetDriveParameter.Response) -> Any:
        def fill(response: SetDriveParameter.Response, result: Any) -> None:
            response.success, response.message = result.success, result.message
            if result.value is not None:
                response.value = float(result.value.value)
                response.raw_value = int(result.value.raw)
                response.unit = result.value.parameter.unit
            if not response.success:
                self._log_refused_set(request, response.message)
        try:
            # Everything that can be judged without the drive is judged here, so a bad
            # request never reaches the control loop (and is answered at once).
            self.controller.check_parameter_write(request.name, float(request.value))
            return self._answer('set_parameter', (request.name, float(request.value),
                                                  bool(request.persistent)), response, fill)
        except ParameterError as exc:
            response.success, response.message = False, str(exc)
        except Exception as exc:  # noqa: BLE001
            response.success, response.message = False, f'set failed: {exc}'
        self._log_refused_set(request, response.message)
        return response

    def _log_refused_set(self, request: SetDriveParameter.Request, message: str) -> None:
        self.get_logger().warning(f'set {quote(request.name)} = {request.value}: {message}')

    def destroy_node(self) -> None:
        # Commands the drive to stop before the port closes (a bus does it for its drives).
        if self._owns_controller:
            self.controller.shutdown()
        super().destroy_node()


def _set_stamp(stamp: TimeMsg, nanoseconds: int) -> None:
    stamp.sec, stamp.nanosec = divmod(nanoseconds, 1_000_000_000)


class ManagedDriveNode(ManagedTransitions, DriveNode, LifecycleNode):
    """drive_node as a managed (lifecycle) node: transitions as in ``managed.py``."""

    def __init__(self, node_name: str = 'drive', **kwargs: Any) -> None:
        super().__init__(node_name, managed=True, **kwargs)
        self.transitions = DriveTransitions(
            self.get_logger(), self.controller.start, self.controller.shutdown,
            {self.get_fully_qualified_name(): (self.controller, self._allow_motion)},
            self.context.ok)
        self.transitions.mark_unconfigured()       # as it starts: unconfigured
        self._refuse_unavailable_transitions()

    def _allow_motion(self, allowed: bool) -> None:
        self.motion_allowed = allowed


def make_drive_node(args: list[str] | None = None, **kwargs: Any) -> DriveNode:
    """Return the node the command line asks for: plain, or managed (and autostarted)."""
    options = parse_options(args)
    if not options.managed:
        return DriveNode(**kwargs)
    node = ManagedDriveNode(**kwargs)
    if options.autostart:
        autostart(node)
    return node


def autostart(node: LifecycleNode) -> None:
    """Configure and activate, as a lifecycle manager with autostart would; log a failure.

    Ctrl-C or SIGTERM during a transition shuts the context down: the transition's
    wait ends, and so does autostart, quietly; run_node stops the drive as it destroys
    the node. Whatever else ends it early (a second Ctrl-C's KeyboardInterrupt, an
    error) destroys the node first, so its drive is stopped before the port closes:
    the caller never got the node to destroy.
    """
    try:
        for transition in (node.trigger_configure, node.trigger_activate):
            try:
                result = transition()
            except Exception:
                if node.context.ok():
                    raise
                return      # (rclpy cannot tell a transition's end once the context is down)
            if not node.context.ok():
                return
            if result != TransitionCallbackReturn.SUCCESS:
                node.get_logger().error('autostart stopped: the node stays in its current '
                                        'state for a lifecycle manager or operator to retry')
                return
    except BaseException:
        node.destroy_node()
        raise


def main(args: list[str] | None = None) -> int:
    return run_node('drive_node', lambda: make_drive_node(args), args)


if __name__ == '__main__':      # python -m, as well as the ros2 run launcher
    raise SystemExit(main())
