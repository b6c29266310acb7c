"""Wheels as joints: JointState per drive, position from the drive or integrated.

Also the topic contract of topic_based_ros2_control on a bus; simulated drives, real
frames, rclpy.
"""

from __future__ import annotations

import math
import threading
import time
import uuid
from types import SimpleNamespace

import pytest
import yaml
from geometry_msgs.msg import TwistStamped
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter
from sensor_msgs.msg import JointState

from can_harness import can_harness_factory  # noqa: F401 - the make_can_harness fixture
from harness import wait_for
from vfd_ros2.control.joint import JointConfig, JointTracker, joint_config
from vfd_ros2.drives import Reading
from vfd_ros2.errors import ParameterError, ProfileError
from vfd_ros2.profiles import PROFILE_DIR, available_profiles, load_profile, load_profile_file
from vfd_ros2.protocol.scaling import VelocityScaling
from vfd_ros2.ros.bus_node import BusNode
from vfd_ros2.ros.diff_drive_node import DiffDriveNode
from vfd_ros2.ros.executable import spin_in_background
from vfd_ros2.ros.joint_topics import JointCommandBridge
from vfd_ros2.sim.model import SimulatedDrive
from vfd_ros2.sim.rtu_line import SimulatedRtuLine

GEAR = 10.0     # the harnesses' gear_ratio


def expected_position(counts: int, counts_per_rev: float, gear: float = GEAR) -> float:
    return 2.0 * math.pi * counts / counts_per_rev / gear


# --- no ROS: the tracker and the profile data ------------------------------------------------

def reading(velocity: float = math.nan, **values: float) -> Reading:
    return Reading(values=dict(values), measured_velocity=velocity)


def test_counter_unwraps_its_roll_over_and_scales_by_gear_and_direction():
    config = JointConfig(from_drive=True, signal='position', counts_per_rev=1000.0,
                         counter_bits=32, gear_ratio=10.0, invert_direction=True)
    tracker = JointTracker(config)
    assert math.isnan(tracker.position)                    # nothing read yet
    tracker.update(reading(position=2**31 - 300), 0.0, True)   # near the int32 top
    assert tracker.position == 0.0                         # the first count is the origin
    tracker.update(reading(position=-(2**31) + 700), 0.1, True)   # rolled over: +1000 counts
    assert tracker.position == pytest.approx(-2.0 * math.pi / 10.0)   # 1 motor rev, inverted
    tracker.update(reading(position=2**31 - 300), 0.2, True)   # and back
    assert tracker.position == pytest.approx(0.0, abs=1e-12)
    tracker.update(reading(), 0.3, False)                  # offline: the last position stays
    assert tracker.position == pytest.approx(0.0, abs=1e-12) and math.isnan(tracker.velocity)


def test_integrated_position_follows_the_measured_speed_while_online():
    tracker = JointTracker(JointConfig(from_drive=False))
    tracker.update(reading(2.0, position=12345.0), 10.0, True)   # a counter is not used
    assert tracker.position == 0.0
    tracker.update(reading(2.0), 10.5, True)
    assert tracker.position == pytest.approx(1.0)
    tracker.update(reading(2.0), 11.5, False)              # offline: nothing integrated
    tracker.update(reading(2.0), 12.0, True)
    assert tracker.position == pytest.approx(2.0)


def test_effort_from_torque_percent_needs_the_rated_torque():
    profile = load_profile('kinco_ec')
    scaling = VelocityScaling(gear_ratio=10.0)
    assert joint_config(profile, scaling).effort_signal == ''      # no rated torque: none
    tracker = JointTracker(joint_config(profile, scaling, rated_torque=2.0))
    tracker.update(reading(0.0, output_torque=50.0, position=0.0), 0.0, True)
    assert tracker.effort == pytest.approx(0.5 * 2.0 * 10.0)     # 50 % x 2 N·m x gear
    veichi = JointTracker(joint_config(load_profile('veichi_ehs100'), scaling))
    veichi.update(reading(0.0, output_torque=-1.5), 0.0, True)     # N·m at the motor
    assert veichi.effort == pytest.approx(-15.0)
    with pytest.raises(ParameterError):
        joint_config(profile, scaling, counts_per_rev=-1.0)


@pytest.mark.parametrize('name', available_profiles())
def test_every_profile_says_where_the_position_comes_from(name):
    profile = load_profile(name)
    position = profile.position
    assert position.note, 'the profile must say why (or how to configure it)'
    if not position.from_drive:
        return
    signal = profile.signal(position.signal)
    assert signal is not None and position.counts_per_rev > 0
    for objects in (profile.canopen.object_sets.values() if profile.canopen else ()):
        assert position.signal in objects.monitor


def test_a_position_signal_that_is_not_monitored_is_refused(tmp_path):
    text = (PROFILE_DIR / 'cia402_velocity.yaml').read_text(encoding='utf-8')
    broken = tmp_path / 'broken.yaml'
    broken.write_text(text.replace('  signal: position\n', '  signal: encoder\n'),
                      encoding='utf-8')
    with pytest.raises(ProfileError, match='position.signal'):
        load_profile_file(broken)


# --- one drive node: JointState from the drive's counter or integrated -----------------------

def joint_states(harness, namespace: str) -> list[JointState]:
    received: list[JointState] = []
    harness.tester.create_subscription(JointState, f'{namespace}/joint_states',
                                       received.append, 50)
    return received


def settle(harness, sim) -> None:
    """Stop the wheel and wait until it stands (the watchdog stops it)."""
    harness.stop_stream()
    harness.wait_status(lambda s: s.watchdog_tripped, 3.0, 'watchdog')
    wait_for(lambda: sim.speed_rpm == 0.0, 5.0, 'motor at rest')


def test_modbus_drive_position_comes_from_its_counter(make_harness):
    h = make_harness(profile='kinco_ec', node_parameters={
        'auto_enable': True, 'motor.rated_torque': 2.0})
    received = joint_states(h, h.namespace)
    first = wait_for(lambda: received and received[-1], 3.0, 'a JointState')
    assert list(first.name) == ['wheel']          # the namespace's last part
    assert h.node.controller.state.position_source == 'drive'     # as in /diagnostics
    assert len(first.position) == len(first.velocity) == len(first.effort) == 1
    h.stream(2.0)
    wait_for(lambda: received[-1].velocity[0] == pytest.approx(2.0, abs=0.05), 6.0,
             'JointState velocity 2 rad/s')
    settle(h, h.sim)
    counts_per_rev = h.profile.position.counts_per_rev
    count = h.sim.position_count
    assert count > counts_per_rev                   # it moved more than a motor turn
    wait_for(lambda: received[-1].position[0] == pytest.approx(
        expected_position(count, counts_per_rev), abs=1e-3), 3.0, 'position = the counter')
    # Turned by hand while standing: only a counter can know.
    with h.sim.lock:
        h.sim.motor_revolutions += 5.0
    wait_for(lambda: received[-1].position[0] == pytest.approx(
        expected_position(count + 5 * counts_per_rev, counts_per_rev), abs=1e-3), 3.0,
        'position follows the counter at rest')
    assert received[-1].velocity[0] == 0.0


def test_drive_without_a_counter_integrates_its_measured_speed(make_harness):
    h = make_harness(profile='boneng_am', node_parameters={
        'auto_enable': True, 'joint_name': 'left_wheel_joint'})
    assert not h.profile.position.from_drive
    assert h.node.controller.state.position_source == 'integrated'
    received = joint_states(h, h.namespace)
    h.stream(2.0)
    wait_for(lambda: received and received[-1].velocity[0] == pytest.approx(2.0, abs=0.05),
             6.0, 'at 2 rad/s')
    assert list(received[-1].name) == ['left_wheel_joint'] and not received[-1].effort
    settle(h, h.sim)
    turned = 2.0 * math.pi * h.sim.motor_revolutions / GEAR
    assert turned > 1.0
    position = wait_for(lambda: received[-1].position[0] if received[-1].velocity[0] == 0.0
                        else None, 3.0, 'at rest')
    # Integration of the polled speed is close to, but not exactly, what the motor did.
    assert position == pytest.approx(turned, rel=0.05)
    with h.sim.lock:
        h.sim.motor_revolutions += 5.0                # turned by hand: not seen
    h.wait_cycles(20)
    assert received[-1].position[0] == pytest.approx(position, abs=1e-9)


def test_canopen_drive_position_comes_from_0x6064(make_can_harness):
    h = make_can_harness(node_parameters={'auto_enable': True, 'joint_name': 'rear'})
    wheel, sim = h.wheels[1], h.sims[1]
    received: list[JointState] = []
    h.tester.create_subscription(JointState, f'{wheel.namespace}/joint_states',
                                 received.append, 50)
    wheel.stream(1.5)
    wait_for(lambda: received and received[-1].velocity[0] == pytest.approx(1.5, abs=0.05),
             6.0, 'at 1.5 rad/s')
    assert list(received[-1].name) == ['rear']
    wheel.stop_stream()
    wait_for(lambda: sim.speed_rpm == 0.0, 5.0, 'motor at rest')
    counts_per_rev = h.profile.position.counts_per_rev
    count = sim.position_count
    wait_for(lambda: received[-1].position[0] == pytest.approx(
        expected_position(count, counts_per_rev), abs=1e-3), 3.0, 'position = 0x6064')
    with sim.lock:
        sim.motor_revolutions -= 3.0
    wait_for(lambda: received[-1].position[0] == pytest.approx(
        expected_position(count - 3 * counts_per_rev, counts_per_rev), abs=1e-3), 3.0,
        'position follows 0x6064 at rest')


# --- the topic_based_ros2_control contract on a bus ------------------------------------------

WHEELS = ('left_wheel', 'right_wheel')


@pytest.fixture
def joint_bus(ros_context, tmp_path):
    profile = load_profile('kinco_ec')
    sims = {wheel: SimulatedDrive(profile, unit, {'A0.06': 0.5, 'A0.07': 0.5})
            for unit, wheel in enumerate(WHEELS, start=1)}
    port = str(tmp_path / 'rs485')
    line = SimulatedRtuLine(list(sims.values()), port).start()
    prefix = f'/j{uuid.uuid4().hex[:6]}'
    config = tmp_path / 'bus.yaml'
    config.write_text(yaml.safe_dump({
        'bus': {'name': 'rs485_0', 'transport.type': 'modbus_rtu', 'transport.port': port,
                'transport.timeout': 0.05, 'control_rate': 50.0},
        'drives': {wheel: {'namespace': f'{prefix}/{wheel}', 'drive.profile': 'kinco_ec',
                           'transport.unit_id': unit, 'gear_ratio': GEAR, 'auto_enable': True,
                           'command_timeout': 0.5, 'invert_direction': wheel == 'right_wheel'}
                   for unit, wheel in enumerate(WHEELS, start=1)}}))
    topics = {'commands': f'{prefix}/robot_joint_commands',
              'states': f'{prefix}/robot_joint_states'}
    bus = BusNode(context=ros_context, namespace=prefix, parameter_overrides=[
        Parameter('config_file', value=str(config)),
        Parameter('joint_commands_topic', value=topics['commands']),
        Parameter('joint_states_topic', value=topics['states'])])
    tester = Node('tester', context=ros_context)
    states: list[JointState] = []
    tester.create_subscription(JointState, topics['states'], states.append, 50)
    commands = tester.create_publisher(JointState, topics['commands'], 10)
    executor = SingleThreadedExecutor(context=ros_context)
    for node in (bus, *bus.drive_nodes, tester):
        executor.add_node(node)
    spin = spin_in_background(executor, ros_context)
    command = {'message': None}
    streaming = threading.Event()

    def stream():
        while streaming.is_set() and ros_context.ok():
            if command['message'] is not None:
                commands.publish(command['message'])
            time.sleep(0.05)
    streaming.set()
    threading.Thread(target=stream, daemon=True).start()
    bench = type('JointBus', (), {})()
    bench.__dict__.update(sims=sims, bus=bus, states=states, command=command, prefix=prefix,
                          executor=executor, spin=spin, context=ros_context,
                          statuses=lambda: {w: n.controller.state for w, n in
                                            zip(WHEELS, bus.drive_nodes)})
    wait_for(lambda: all(s.online for s in bench.statuses().values()), 10.0, 'drives online')
    yield bench
    streaming.clear()
    spin.stop()
    executor.shutdown(timeout_sec=1.0)
    bus.destroy_node()
    tester.destroy_node()
    line.stop()


def velocity_command(**velocities: float) -> JointState:
    return JointState(name=list(velocities), velocity=list(velocities.values()))


def test_ros2_control_joint_commands_move_the_wheels_and_the_watchdog_stops_them(joint_bus):
    states = joint_bus.states
    first = wait_for(lambda: states and states[-1], 3.0, 'aggregated joint states')
    assert list(first.name) == list(WHEELS) and len(first.position) == 2
    # Another bus's joint in the same message is ignored; each wheel gets its own velocity.
    joint_bus.command['message'] = velocity_command(left_wheel=1.0, right_wheel=2.0,
                                                    arm_joint=5.0)
    wait_for(lambda: states[-1].velocity[0] == pytest.approx(1.0, abs=0.05) and
             states[-1].velocity[1] == pytest.approx(2.0, abs=0.05), 6.0, 'wheels at 1 and 2')
    sims = joint_bus.sims
    assert sims['left_wheel'].speed_rpm > 0 > sims['right_wheel'].speed_rpm   # mirrored
    assert states[-1].position[1] > 0.0
    joint_bus.command['message'] = None             # the stream stops: nothing else does
    wait_for(lambda: all(s.watchdog_tripped for s in joint_bus.statuses().values()), 3.0,
             'watchdog on both drives')
    wait_for(lambda: all(s.speed_rpm == 0.0 for s in sims.values()), 5.0, 'wheels stopped')


def test_ros2_control_commands_keep_the_drive_rules(joint_bus):
    sims = joint_bus.sims
    bridge = joint_bus.bus.joints
    # A position command interface (no velocities) is refused whole.
    joint_bus.command['message'] = JointState(name=list(WHEELS), position=[1.0, 1.0])
    wait_for(lambda: bridge.refused >= 3, 3.0, 'refused position commands')
    # A disabled drive does not move on joint commands: they use the same permit as cmd.
    disabled = joint_bus.bus.drive_nodes[0]
    done = disabled.controller.submit('disable')
    assert done.result(timeout=5.0).success
    joint_bus.command['message'] = velocity_command(left_wheel=1.0, right_wheel=1.0)
    wait_for(lambda: sims['right_wheel'].speed_rpm < -50, 6.0, 'right wheel moves')
    assert sims['left_wheel'].speed_rpm == 0.0
    assert joint_bus.statuses()['left_wheel'].run_state.label == 'disabled'


def test_a_joint_command_with_one_bad_wheel_moves_neither(joint_bus):
    # Half a message applied turns a differential-drive robot (outside audit: a NaN for
    # the left wheel and 1e308 for the right ran the right wheel alone, clamped to its
    # maximum). A non-finite velocity, or a wheel named twice, refuses the whole message.
    sims, bridge = joint_bus.sims, joint_bus.bus.joints
    for bad in (JointState(name=list(WHEELS), velocity=[math.nan, 1e308]),
                JointState(name=list(WHEELS), velocity=[1.0, math.inf]),
                JointState(name=['left_wheel', 'right_wheel', 'left_wheel'],
                           velocity=[1.0, 1.0, -1.0])):
        before = bridge.refused
        joint_bus.command['message'] = bad
        wait_for(lambda: bridge.refused >= before + 3, 3.0, 'refused whole')
        assert all(s.speed_rpm == 0.0 and not s.run_requested for s in sims.values()), bad
    joint_bus.command['message'] = velocity_command(left_wheel=1.0, right_wheel=1.0)
    wait_for(lambda: all(abs(s.speed_rpm) > 50 for s in sims.values()), 6.0, 'both move')


def test_joint_names_must_be_unique_on_a_bus():
    drives = [SimpleNamespace(joint_name='same'), SimpleNamespace(joint_name='same')]
    with pytest.raises(ParameterError, match='same'):
        JointCommandBridge(None, drives, '/robot_joint_commands', '', 50.0)


def test_diff_drive_odometry_follows_the_drives_counters(joint_bus):
    """diff_drive on the bus's drives: the pose is the wheels' counted turns."""
    prefix, radius = joint_bus.prefix, 0.1
    parameters = {'wheel_radius': radius, 'track_width': 0.5,
                  'max_linear_acceleration': 0.0, 'max_angular_acceleration': 0.0}
    for side in ('left', 'right'):
        wheel = f'{prefix}/{side}_wheel'
        parameters.update({f'{side}_wheel_command_topic': f'{wheel}/drive/velocity_command',
                           f'{side}_wheel_status_topic': f'{wheel}/drive/status',
                           f'{side}_wheel_joint_states_topic': f'{wheel}/joint_states'})
    diff = DiffDriveNode('diff_drive', namespace=prefix, context=joint_bus.context,
                         parameter_overrides=[Parameter(k, value=v)
                                              for k, v in parameters.items()])
    cmd_vel = diff.create_publisher(TwistStamped, f'{prefix}/cmd_vel', 10)
    joint_bus.executor.add_node(diff)
    try:
        wait_for(lambda: diff.odometry_source == 'position', 5.0, 'position feedback')
        end = time.monotonic() + 1.5
        while time.monotonic() < end:
            command = TwistStamped()
            command.header.stamp = diff.get_clock().now().to_msg()
            command.twist.linear.x = 0.3
            cmd_vel.publish(command)
            time.sleep(0.05)
        sims = joint_bus.sims
        wait_for(lambda: all(s.speed_rpm == 0.0 for s in sims.values()), 5.0, 'stopped')
        counts_per_rev = sims['left_wheel'].profile.position.counts_per_rev
        left = expected_position(sims['left_wheel'].position_count, counts_per_rev)
        right = -expected_position(sims['right_wheel'].position_count, counts_per_rev)
        assert left > 3.0 and right > 3.0                  # about 0.4 m each
        wait_for(lambda: diff.odometry.x_m == pytest.approx(radius * (left + right) / 2,
                                                            abs=1e-3), 3.0,
                 'odometry = the counted turns')
        assert diff.odometry_source == 'position'
    finally:
        # Stop spinning first: a wait in progress may still hold the node's entities.
        joint_bus.spin.stop()
        joint_bus.executor.remove_node(diff)
        diff.destroy_node()
