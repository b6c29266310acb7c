"""Managed (lifecycle) drive and bus nodes, driven through the standard lifecycle_msgs services.

Every transition is requested as a lifecycle manager does (``<node>/change_state``,
``<node>/get_state``) and checked at the simulated drive: nothing moves before
activate, deactivate stops the motor, shutdown writes the stop before the link
closes.
"""

from __future__ import annotations

import threading
import time

import pytest
import yaml
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from lifecycle_msgs.msg import State, Transition
from lifecycle_msgs.srv import ChangeState, GetState
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter
from std_msgs.msg import Float64
from std_srvs.srv import Trigger

from harness import DriveHarness, wait_for
from test_drive_node import write_frame
from vfd_ros2.profiles import load_profile
from vfd_ros2.protocol.scaling import RPM_PER_RAD_S
from vfd_ros2.ros.bus_node import ManagedBusNode
from vfd_ros2.ros.drive_node import ManagedDriveNode, make_drive_node
from vfd_ros2.ros.executable import spin_in_background
from vfd_ros2.ros.managed import LINK_CLOSED, NOT_ACTIVE
from vfd_ros2.sim.model import SimulatedDrive
from vfd_ros2.sim.rtu_line import SimulatedRtuLine

GEAR = 10.0
STOP = 4            # boneng_am P07.32 "decelerate to stop"


def call(tester: Node, srv_type, name: str, request, timeout: float = 20.0):
    client = tester.create_client(srv_type, name)
    try:
        assert client.wait_for_service(timeout_sec=5.0), f'{name} not available'
        future = client.call_async(request)
        wait_for(future.done, timeout, f'reply of {name}')
        return future.result()
    finally:
        tester.destroy_client(client)


def change(tester: Node, node: str, transition: int) -> bool:
    return call(tester, ChangeState, f'{node}/change_state',
                ChangeState.Request(transition=Transition(id=transition))).success


def state(tester: Node, node: str) -> int:
    return call(tester, GetState, f'{node}/get_state', GetState.Request()).current_state.id


def at_speed(sim: SimulatedDrive, velocity: float) -> bool:
    return abs(sim.speed_rpm - velocity * GEAR * RPM_PER_RAD_S) < 2.0


@pytest.fixture
def managed(ros_context, tmp_path):
    made = []

    def make(**parameters) -> DriveHarness:
        h = DriveHarness(ros_context, str(tmp_path / f'line{len(made)}'),
                         node_parameters=parameters, node_class=ManagedDriveNode)
        made.append(h)
        return h
    yield make
    for h in made:
        h.close()


def test_drive_every_transition_at_the_simulated_drive(managed):
    h = managed(auto_enable=True)
    node = f'{h.namespace}/drive'
    assert state(h.tester, node) == State.PRIMARY_STATE_UNCONFIGURED
    h.wait_status(lambda s: s.stop_reason == LINK_CLOSED, 2.0, 'unconfigured from the start')
    h.stream(2.0)                                    # a planner already commanding
    assert h.sim.requests == 0, 'unconfigured: the link is not even opened'
    reply = h.trigger('enable')
    assert not reply.success and 'configure it first' in reply.message, reply.message

    assert change(h.tester, node, Transition.TRANSITION_CONFIGURE)
    assert state(h.tester, node) == State.PRIMARY_STATE_INACTIVE
    h.wait_status(lambda s: s.online, 5.0, 'online after configure')
    h.wait_cycles(20)
    assert h.sim.speed_rpm == 0.0 and not h.sim.output_active, 'nothing moves before activate'
    reply = h.trigger('enable')
    assert not reply.success and 'activate it first' in reply.message, reply.message
    # ~/status names what holds it: activate, not a service that is refused now
    h.wait_status(lambda s: s.stop_reason == NOT_ACTIVE, 2.0, 'held by lifecycle, said so')

    assert change(h.tester, node, Transition.TRANSITION_ACTIVATE)
    assert state(h.tester, node) == State.PRIMARY_STATE_ACTIVE
    wait_for(lambda: at_speed(h.sim, 2.0), 6.0, 'motor at 2 rad/s after activate')

    assert change(h.tester, node, Transition.TRANSITION_DEACTIVATE)
    assert state(h.tester, node) == State.PRIMARY_STATE_INACTIVE
    wait_for(lambda: h.sim.speed_rpm == 0.0, 3.0, 'motor stopped by deactivate')
    h.wait_cycles(20)
    assert h.sim.speed_rpm == 0.0, 'held while inactive, commands still arriving'
    h.wait_status(lambda s: s.stop_reason == NOT_ACTIVE and s.state == 'stopped', 2.0,
                  'stopped and held by lifecycle, said so')

    assert change(h.tester, node, Transition.TRANSITION_ACTIVATE)   # auto_enable again
    wait_for(lambda: at_speed(h.sim, 2.0), 6.0, 'moving again after re-activate')
    assert change(h.tester, node, Transition.TRANSITION_DEACTIVATE)
    assert change(h.tester, node, Transition.TRANSITION_CLEANUP)
    assert state(h.tester, node) == State.PRIMARY_STATE_UNCONFIGURED
    # closed on purpose, not lost: said so, and no comm-loss ERROR on /diagnostics
    h.wait_status(lambda s: not s.online and s.stop_reason == LINK_CLOSED, 3.0,
                  'offline after cleanup, the link closed on purpose')
    entry = h.node.diagnostic_status()
    assert entry.level == DiagnosticStatus.STALE and LINK_CLOSED in entry.message, entry
    before = h.sim.requests
    h.wait_status(lambda s: True, 1.0)               # the executor went on
    time.sleep(0.2)
    assert h.sim.requests == before, 'the link is closed after cleanup'

    assert change(h.tester, node, Transition.TRANSITION_CONFIGURE)  # and back again
    assert change(h.tester, node, Transition.TRANSITION_ACTIVATE)
    wait_for(lambda: at_speed(h.sim, 2.0), 6.0, 'moving after a second configure')
    since = time.monotonic()
    assert change(h.tester, node, Transition.TRANSITION_ACTIVE_SHUTDOWN)
    assert state(h.tester, node) == State.PRIMARY_STATE_FINALIZED
    assert write_frame(0xE720, STOP) in h.frames_after(since), 'stop written at shutdown'
    wait_for(lambda: h.sim.speed_rpm == 0.0, 3.0, 'motor stopped by shutdown')


def test_an_operators_stop_asked_after_an_enable_holds_through_a_re_activate(managed):
    """~/stop, ~/enable, ~/stop asked 50 ms apart: the last stop holds.

    The stop latches as it is asked, but the enable queued before it ran after and
    undid it: the stop's action then held it as a lifecycle hold only, and a
    deactivate-activate with auto_enable ran the motor again (outside audit).
    """
    h = managed(auto_enable=True)
    node = f'{h.namespace}/drive'
    h.stream(2.0)
    assert change(h.tester, node, Transition.TRANSITION_CONFIGURE)
    assert change(h.tester, node, Transition.TRANSITION_ACTIVATE)
    wait_for(lambda: at_speed(h.sim, 2.0), 6.0, 'motor at 2 rad/s')
    clients = {name: h.tester.create_client(Trigger, f'{node}/{name}')
               for name in ('stop', 'enable')}
    assert all(c.wait_for_service(timeout_sec=5.0) for c in clients.values())
    futures = []
    for name in ('stop', 'enable', 'stop'):
        futures.append((name, clients[name].call_async(Trigger.Request())))
        time.sleep(0.05)
    wait_for(lambda: all(f.done() for _, f in futures), 15.0, 'all three answered')
    answers = [(name, f.result().success, f.result().message) for name, f in futures]
    assert answers[1][1] is False and 'asked after this ~/enable' in answers[1][2], answers
    assert answers[2][1], answers
    h.wait_status(lambda s: s.stop_reason.startswith('stopped by ~/stop'), 2.0,
                  "the operator's stop, said so")
    assert change(h.tester, node, Transition.TRANSITION_DEACTIVATE)
    assert change(h.tester, node, Transition.TRANSITION_ACTIVATE)   # auto_enable
    h.wait_cycles(30)
    assert h.sim.speed_rpm == 0.0 and not h.sim.output_active, 'the stop held'
    for client in clients.values():
        h.tester.destroy_client(client)


def test_without_auto_enable_activate_only_allows_motion(managed):
    h = managed(auto_enable=False)
    node = f'{h.namespace}/drive'
    h.stream(1.0)
    assert change(h.tester, node, Transition.TRANSITION_CONFIGURE)
    assert change(h.tester, node, Transition.TRANSITION_ACTIVATE)
    h.wait_cycles(20)
    assert h.sim.speed_rpm == 0.0, 'activate does not enable without auto_enable'
    assert h.trigger('enable').success
    wait_for(lambda: at_speed(h.sim, 1.0), 6.0, 'moving after ~/enable')


def test_services_of_an_unconfigured_node_answer_at_once_and_never_run_later(managed):
    """Unconfigured, every service answers "not configured" at once; none is queued.

    Queued, they ran at the next configure, long after their callers gave up: a
    fault found at connect (which latches until ~/reset_fault) was cleared by a
    stale reset, and a parameter write landed.
    """
    from vfd_ros2.srv import SetDriveParameter
    h = managed(auto_enable=False)
    node = f'{h.namespace}/drive'
    h.sim.inject_fault(7, 1)                          # on the drive before configure
    for name in ('reset_fault', 'stop', 'disable'):
        reply = h.trigger(name)
        assert not reply.success and 'configure it first' in reply.message, (name, reply)
    reply = h.call(SetDriveParameter, 'set_drive_parameter',
                   SetDriveParameter.Request(name='B04.02', value=7.0))
    assert not reply.success and 'configure it first' in reply.message, reply.message
    assert change(h.tester, node, Transition.TRANSITION_CONFIGURE)
    status = h.wait_status(lambda s: s.online and s.fault, 5.0, 'the fault, latched')
    h.wait_cycles(20)
    assert h.wait_status(lambda s: True, 1.0).fault and h.sim.fault_code == 7, \
        'a reset sent before configure cleared the fault'
    assert h.sim.value('B04.02') != 7.0
    assert status.fault_code == 7


def test_commands_to_an_inactive_node_are_told_at_any_log_level(managed, capfd):
    # A zero is a debug line, another value a warning: one call site at two severities
    # made rclpy raise at debug level, and every command after a zero was an ERROR
    # "velocity command failed" instead (outside re-check).
    from rclpy.logging import LoggingSeverity
    from std_msgs.msg import Float64
    h = managed(auto_enable=False)
    h.node.get_logger().set_level(LoggingSeverity.DEBUG)
    for value in (0.0, 1.0, 0.0, 2.0):
        h.node._on_velocity(Float64(data=value))      # noqa: SLF001 - the callback alone
    out = ''.join(capfd.readouterr())
    assert 'velocity command 1.0 ignored: the node is not active' in out
    assert 'velocity command 0.0 ignored' in out and 'failed' not in out, out


def test_configure_fails_while_the_drive_is_silent_and_errors_go_to_error_processing(managed):
    h = managed(auto_enable=True, action_timeout=0.5)
    node = f'{h.namespace}/drive'
    h.sim.silent = True
    assert not change(h.tester, node, Transition.TRANSITION_CONFIGURE)
    assert state(h.tester, node) == State.PRIMARY_STATE_UNCONFIGURED
    assert 'not online' in h.node.transitions.last_error
    h.sim.silent = False
    assert change(h.tester, node, Transition.TRANSITION_CONFIGURE)

    # A stop that cannot be verified in time (8 rad/s: a ramp down of ~0.3 s, stop_timeout
    # 0.05 s) is an error: ErrorProcessing writes the stop, closes the link, ends
    # unconfigured.
    h.stream(8.0)
    assert change(h.tester, node, Transition.TRANSITION_ACTIVATE)
    wait_for(lambda: at_speed(h.sim, 8.0), 6.0, 'running')
    h.node.controller.reconfigure(stop_timeout=0.05)
    assert not change(h.tester, node, Transition.TRANSITION_DEACTIVATE)
    assert state(h.tester, node) == State.PRIMARY_STATE_UNCONFIGURED
    assert 'stop not verified' in h.node.transitions.last_error
    wait_for(lambda: h.sim.speed_rpm == 0.0, 3.0, 'stopped after error processing')


def test_autostart_configures_and_activates(ros_context, tmp_path):
    sim = SimulatedDrive(load_profile('boneng_am'), 1, {'acceleration_time': 0.5,
                                                        'deceleration_time': 0.5})
    port = str(tmp_path / 'line')
    line = SimulatedRtuLine([sim], port).start()
    node = make_drive_node(['drive_node', '--managed', '--autostart'], namespace='/auto',
                           context=ros_context, parameter_overrides=[
                               Parameter('transport.port', value=port),
                               Parameter('gear_ratio', value=GEAR),
                               Parameter('auto_enable', value=True)])
    try:
        assert isinstance(node, ManagedDriveNode)
        assert node.motion_allowed and node.controller.state.online
        node.controller.command_velocity(1.0)
        wait_for(lambda: (node.controller.command_velocity(1.0), at_speed(sim, 1.0))[1],
                 6.0, 'moving after autostart')
    finally:
        node.destroy_node()
        line.stop()


def test_ctrl_c_during_autostart_stops_the_loop_before_the_node_goes(ros_context, tmp_path,
                                                                      monkeypatch):
    """KeyboardInterrupt out of activate's wait: the node is destroyed, its loop ended.

    It left make_drive_node before run_node had the node: nothing destroyed it, and
    the control loop ran on (no stop written) until the process died.
    """
    import vfd_ros2.ros.managed as managed

    def interrupted(*_args, **_kwargs):
        raise KeyboardInterrupt
    monkeypatch.setattr(managed, 'results', interrupted)
    sim = SimulatedDrive(load_profile('boneng_am'), 1)
    port = str(tmp_path / 'line')
    line = SimulatedRtuLine([sim], port).start()
    try:
        with pytest.raises(KeyboardInterrupt):
            make_drive_node(['drive_node', '--managed', '--autostart'], namespace='/ctrlc',
                            context=ros_context, parameter_overrides=[
                                Parameter('transport.port', value=port),
                                Parameter('auto_enable', value=True)])
        assert not [t.name for t in threading.enumerate()
                    if t.name.startswith('drive ') and port in t.name]
        assert sim.requests > 0 and not sim.run_requested
    finally:
        line.stop()


def test_managed_bus_moves_every_drive_through_the_transitions(ros_context, tmp_path):
    profile = load_profile('boneng_am')
    sims = [SimulatedDrive(profile, unit, {'acceleration_time': 0.5,
                                           'deceleration_time': 0.5}) for unit in (1, 2)]
    port = str(tmp_path / 'rs485')
    line = SimulatedRtuLine(sims, port).start()
    config = tmp_path / 'bus.yaml'
    config.write_text(yaml.safe_dump({
        'bus': {'name': 'rs485_0', 'transport.type': 'modbus_rtu', 'transport.port': port,
                'transport.timeout': 0.05, 'control_rate': 50.0},
        'drives': {w: {'namespace': f'/mb/{w}', 'drive.profile': 'boneng_am',
                       'transport.unit_id': unit, 'gear_ratio': GEAR, 'auto_enable': True}
                   for unit, w in ((1, 'left'), (2, 'right'))}}))
    bus = ManagedBusNode(context=ros_context, namespace='/mb', parameter_overrides=[
        Parameter('config_file', value=str(config))])
    tester = Node('tester', context=ros_context)
    pubs = [tester.create_publisher(Float64, f'/mb/{w}/drive/velocity_command', 10)
            for w in ('left', 'right')]
    executor = SingleThreadedExecutor(context=ros_context)
    for each in (bus, *bus.drive_nodes, tester):
        executor.add_node(each)
    spin = spin_in_background(executor, ros_context)

    def moving(velocity: float) -> bool:
        for pub in pubs:
            pub.publish(Float64(data=velocity))
        return all(at_speed(sim, velocity) for sim in sims)
    try:
        assert state(tester, '/mb/bus') == State.PRIMARY_STATE_UNCONFIGURED
        assert all(sim.requests == 0 for sim in sims)
        # unconfigured: the link is closed on purpose, said so; no comm-loss ERROR
        assert all(c.state.stop_reason == LINK_CLOSED for c in bus.bus.controllers.values())
        diagnostics: list[DiagnosticArray] = []
        tester.create_subscription(DiagnosticArray, '/diagnostics', diagnostics.append, 10)
        wait_for(lambda: any(s.name == 'mb/bus: bus rs485_0' for d in diagnostics
                             for s in d.status), 3.0, 'the bus on /diagnostics')
        entry = next(s for d in diagnostics for s in d.status if s.name == 'mb/bus: bus rs485_0')
        assert entry.level == DiagnosticStatus.STALE and entry.message == LINK_CLOSED, entry
        assert not change(tester, '/mb/bus', Transition.TRANSITION_DEACTIVATE)  # not offered
        assert change(tester, '/mb/bus', Transition.TRANSITION_CONFIGURE)
        assert not change(tester, '/mb/bus', Transition.TRANSITION_CONFIGURE)   # not again
        assert all(c.state.online for c in bus.bus.controllers.values())
        for _ in range(20):
            moving(1.0)
            time.sleep(0.02)
        assert all(sim.speed_rpm == 0.0 for sim in sims), 'nothing moves before activate'
        reply = call(tester, Trigger, '/mb/left/drive/enable', Trigger.Request())
        assert not reply.success
        assert change(tester, '/mb/bus', Transition.TRANSITION_ACTIVATE)
        wait_for(lambda: moving(1.0), 6.0, 'both wheels at 1 rad/s', period=0.05)
        assert change(tester, '/mb/bus', Transition.TRANSITION_DEACTIVATE)
        wait_for(lambda: (moving(1.0), all(s.speed_rpm == 0.0 for s in sims))[1], 3.0,
                 'both stopped by deactivate', period=0.05)
        assert change(tester, '/mb/bus', Transition.TRANSITION_CLEANUP)
        assert state(tester, '/mb/bus') == State.PRIMARY_STATE_UNCONFIGURED
        assert change(tester, '/mb/bus', Transition.TRANSITION_UNCONFIGURED_SHUTDOWN)
        assert state(tester, '/mb/bus') == State.PRIMARY_STATE_FINALIZED
    finally:
        spin.stop()
        executor.shutdown(timeout_sec=1.0)
        bus.destroy_node()
        tester.destroy_node()
        line.stop()


def test_rate_and_auto_enable_set_before_configure_are_in_force(managed):
    from test_runtime_parameters import set_parameter
    h = managed(auto_enable=False)
    node = f'{h.namespace}/drive'
    # Before configure nothing is written yet: a slow rate re-sizes the drive-side
    # comm-loss timeout as at start-up (running, the same change is refused).
    assert set_parameter(h.tester, node, 'control_rate', 0.5).successful
    assert h.node.controller.protection.timeout > 2.0
    assert set_parameter(h.tester, node, 'control_rate', 100.0).successful
    assert h.node.controller.protection.timeout == pytest.approx(0.3)
    assert set_parameter(h.tester, node, 'auto_enable', True).successful   # live when managed
    assert change(h.tester, node, Transition.TRANSITION_CONFIGURE)
    assert h.node.controller._loop.period == pytest.approx(0.01)
    h.stream(1.0)
    assert change(h.tester, node, Transition.TRANSITION_ACTIVATE)       # auto_enable now
    wait_for(lambda: at_speed(h.sim, 1.0), 6.0, 'moving: auto_enable set before activate')


@pytest.mark.parametrize('action', ['stop', 'disable'])
def test_an_operators_stop_holds_through_activate_with_auto_enable(managed, action):
    """~/stop before configure said "latched until ~/enable"; activate enabled it anyway."""
    h = managed(auto_enable=True)
    node = f'{h.namespace}/drive'
    assert not h.trigger(action).success                 # answered: not verified, latched
    h.stream(2.0)
    assert change(h.tester, node, Transition.TRANSITION_CONFIGURE)
    assert change(h.tester, node, Transition.TRANSITION_ACTIVATE)
    h.wait_cycles(40)
    assert not h.sim.run_requested and h.sim.speed_rpm == 0.0, 'moved without ~/enable'
    assert h.trigger('enable').success
    wait_for(lambda: at_speed(h.sim, 2.0), 6.0, 'moving after ~/enable')
    # the lifecycle's own hold is not an operator's: deactivate, activate moves again
    assert change(h.tester, node, Transition.TRANSITION_DEACTIVATE)
    assert change(h.tester, node, Transition.TRANSITION_ACTIVATE)
    wait_for(lambda: at_speed(h.sim, 2.0), 6.0, 'moving again after re-activate')


def test_a_transition_not_available_is_refused_and_the_node_lives_on(managed):
    """A lifecycle manager's transition by id that the state does not offer: false, no crash.

    rclpy raised on it ("Transition is not registered") and the exception ended the
    process; here the running drive must go on running, then still obey.
    """
    h = managed(auto_enable=True)
    node = f'{h.namespace}/drive'
    assert not change(h.tester, node, Transition.TRANSITION_ACTIVATE)   # unconfigured
    assert not change(h.tester, node, Transition.TRANSITION_DEACTIVATE)
    assert state(h.tester, node) == State.PRIMARY_STATE_UNCONFIGURED
    assert change(h.tester, node, Transition.TRANSITION_CONFIGURE)
    assert change(h.tester, node, Transition.TRANSITION_ACTIVATE)
    h.stream(2.0)
    wait_for(lambda: at_speed(h.sim, 2.0), 6.0, 'running after activate')
    for refused in (Transition.TRANSITION_CONFIGURE, Transition.TRANSITION_CLEANUP, 99):
        assert not change(h.tester, node, refused), refused
    by_label = ChangeState.Request(transition=Transition(label='configure'))
    assert not call(h.tester, ChangeState, f'{node}/change_state', by_label).success
    assert state(h.tester, node) == State.PRIMARY_STATE_ACTIVE
    h.wait_cycles(10)
    assert at_speed(h.sim, 2.0), 'the drive runs on: nothing happened to it'
    assert change(h.tester, node, Transition.TRANSITION_DEACTIVATE)
    wait_for(lambda: h.sim.speed_rpm == 0.0, 3.0, 'stopped by deactivate')
