"""Runtime parameters through the real rcl SetParameters service: applied or refused.

What `ros2 param set` does: a SetParameters request to ``<node>/set_parameters``.
Live parameters take effect at the simulated drive at once; bad values and
read-only parameters are refused with a reason and change nothing.
"""

from __future__ import annotations

import math
import time

import pytest
import yaml
from rcl_interfaces.srv import DescribeParameters, GetParameters, SetParameters
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter

from harness import wait_for
from vfd_ros2.profiles import load_profile
from vfd_ros2.protocol.scaling import RPM_PER_RAD_S
from vfd_ros2.ros.bus_node import BusNode
from vfd_ros2.ros.executable import make_executor, spin_in_background
from vfd_ros2.sim.model import SimulatedDrive
from vfd_ros2.sim.rtu_line import SimulatedRtuLine

GEAR = 10.0


def service(tester: Node, srv_type, name: str, request):
    client = tester.create_client(srv_type, name)
    try:
        assert client.wait_for_service(timeout_sec=5.0), f'{name} not available'
        future = client.call_async(request)
        wait_for(future.done, 5.0, f'reply of {name}')
        return future.result()
    finally:
        tester.destroy_client(client)


def set_parameter(tester: Node, node: str, name: str, value):
    """One parameter through <node>/set_parameters; returns its SetParametersResult."""
    request = SetParameters.Request(
        parameters=[Parameter(name, value=value).to_parameter_msg()])
    return service(tester, SetParameters, f'{node}/set_parameters', request).results[0]


def get_parameter(tester: Node, node: str, name: str):
    reply = service(tester, GetParameters, f'{node}/get_parameters',
                    GetParameters.Request(names=[name]))
    return Parameter.from_parameter_msg(
        type('P', (), {'name': name, 'value': reply.values[0]})()).value


def describe(tester: Node, node: str, name: str):
    return service(tester, DescribeParameters, f'{node}/describe_parameters',
                   DescribeParameters.Request(names=[name])).descriptors[0]


def test_drive_node_max_velocity_is_applied_at_the_drive(make_harness):
    h = make_harness(node_parameters={'auto_enable': True})
    node = f'{h.namespace}/drive'
    h.stream(2.0)
    h.wait_status(lambda s: s.running and abs(s.measured_velocity - 2.0) < 0.02, 6.0,
                  'motor at 2 rad/s')
    result = set_parameter(h.tester, node, 'max_velocity', 1.0)
    assert result.successful, result.reason
    h.wait_status(lambda s: abs(s.measured_velocity - 1.0) < 0.02, 6.0, 'capped at 1 rad/s')
    wait_for(lambda: abs(h.sim.speed_rpm - 1.0 * GEAR * RPM_PER_RAD_S) < 2.0, 3.0,
             'the simulated motor at 1 rad/s')
    assert get_parameter(h.tester, node, 'max_velocity') == 1.0

    # Bad values: refused with the reason, nothing changes (still capped at 1 rad/s).
    for value in (math.nan, math.inf, -1.0, 0.0):
        result = set_parameter(h.tester, node, 'max_velocity', value)
        assert not result.successful and 'max_velocity' in result.reason, (value, result)
    assert get_parameter(h.tester, node, 'max_velocity') == 1.0
    assert h.node.controller.config.max_velocity == 1.0
    h.wait_cycles(10)
    assert abs(h.sim.speed_rpm - 1.0 * GEAR * RPM_PER_RAD_S) < 2.0

    # Read-only: refused, whatever the value.
    for name, value in (('gear_ratio', 0.0), ('gear_ratio', 20.0), ('transport.type', 'foo'),
                        ('drive.profile', 'imo_hd2'), ('auto_enable', False)):
        result = set_parameter(h.tester, node, name, value)
        assert not result.successful and 'read-only' in result.reason, (name, result)
    assert get_parameter(h.tester, node, 'gear_ratio') == GEAR
    # A wrong type is refused too.
    assert not set_parameter(h.tester, node, 'max_velocity', 'fast').successful
    # A rate the drive's own comm-loss timeout (0.3 s, written at connect) cannot serve.
    result = set_parameter(h.tester, node, 'control_rate', 2.0)
    assert not result.successful and 'protection' in result.reason, result.reason
    assert h.node.controller.config.cycle_period == 0.02
    assert set_parameter(h.tester, node, 'control_rate', 100.0).successful
    assert h.node.controller.config.cycle_period == 0.01


def test_no_parameter_moves_the_wheel_on_a_command_taken_before_it(make_harness):
    """A raised command_timeout, a lowered max_velocity: each applies from now on.

    Found by an outside audit: a raised command_timeout revived the last command
    after the watchdog had stopped the wheel, and a lowered max_velocity waited for
    the next command while the last one drove the wheel over the new limit.
    """
    h = make_harness(node_parameters={'auto_enable': True, 'command_timeout': 10.0})
    node = f'{h.namespace}/drive'
    h.stream(2.0)
    h.wait_status(lambda s: s.running and abs(s.measured_velocity - 2.0) < 0.02, 6.0,
                  'motor at 2 rad/s')
    h.stop_stream()                     # the last command holds for 10 s
    assert set_parameter(h.tester, node, 'max_velocity', 1.0).successful
    h.wait_status(lambda s: s.commanded_velocity == 1.0 and
                  abs(s.measured_velocity - 1.0) < 0.02, 3.0, 'the last command capped')

    assert set_parameter(h.tester, node, 'command_timeout', 0.2).successful   # at once
    h.wait_status(lambda s: s.watchdog_tripped and s.commanded_velocity == 0.0, 3.0,
                  'watchdog trip')
    h.wait_status(lambda s: not s.running and s.measured_velocity == 0.0, 6.0, 'stopped')
    assert set_parameter(h.tester, node, 'command_timeout', 30.0).successful
    h.wait_cycles(25)
    status = h.wait_status(lambda s: True, 1.0, 'a status')
    assert status.watchdog_tripped and not status.running, status
    assert 'command_timeout 0.2 s' in status.stop_reason, status.stop_reason   # (its own)
    assert h.sim.speed_rpm == 0.0 and not h.sim.run_requested

    h.stream(0.5)                       # a new command counts for the new timeout
    h.wait_status(lambda s: s.running and abs(s.measured_velocity - 0.5) < 0.02, 6.0,
                  'running again on a new command')


def test_a_command_from_before_a_stop_or_a_fault_does_not_resume_the_drive(make_harness):
    """~/enable after ~/stop, ~/reset_fault after a fault: only a later command moves it.

    Outside audit: with a long command_timeout, the command taken before the
    stop or the fault was still fresh, and the wheel ran on it again.
    """
    h = make_harness(node_parameters={'auto_enable': True, 'command_timeout': 30.0})
    h.stream(2.0)
    h.wait_status(lambda s: s.running and abs(s.measured_velocity - 2.0) < 0.02, 6.0,
                  'motor at 2 rad/s')
    h.stop_stream()
    for service in ('stop', 'disable'):
        assert h.trigger(service).success
        reply = h.trigger('enable')
        h.wait_cycles(25)
        status = h.wait_status(lambda s: True, 1.0, 'a status')
        assert not status.running and status.watchdog_tripped, (service, reply, status)
        assert not h.sim.run_requested, service
    h.sim.inject_fault(9, 1)                # (its cause gone: ~/reset_fault clears it)
    h.wait_status(lambda s: s.fault, 3.0, 'the fault')
    reply = h.trigger('reset_fault')
    assert reply.success, reply.message
    h.wait_cycles(25)
    status = h.wait_status(lambda s: True, 1.0, 'a status')
    assert not status.running and status.watchdog_tripped, status
    h.stream(1.0)                           # a new command: runs
    h.wait_status(lambda s: s.running and abs(s.measured_velocity - 1.0) < 0.02, 6.0,
                  'running on a new command')


def test_drive_node_command_timeout_and_rates_are_applied(make_harness):
    # No drive-side comm-loss timeout: the rate is free (see the next test for one).
    h = make_harness(node_parameters={'auto_enable': True, 'drive_comm_timeout': 0.0})
    node = f'{h.namespace}/drive'
    for bad in (-1.0, 0.0, math.nan):
        assert not set_parameter(h.tester, node, 'command_timeout', bad).successful
    assert set_parameter(h.tester, node, 'command_timeout', 0.2).successful
    h.stream(1.0)
    h.wait_status(lambda s: s.running, 6.0, 'running')
    h.stop_stream()
    status = h.wait_status(lambda s: s.watchdog_tripped, 3.0, 'watchdog trip')
    assert 'command_timeout 0.2 s' in status.stop_reason

    # control_rate changes the loop's period, and the drive sees the new rate.
    def request_rate(seconds: float) -> float:
        start, before = time.monotonic(), h.sim.requests
        time.sleep(seconds)
        return (h.sim.requests - before) / (time.monotonic() - start)
    fast = request_rate(1.0)
    assert set_parameter(h.tester, node, 'control_rate', 4.0).successful
    assert h.node.controller.config.cycle_period == 0.25
    h.wait_cycles(2)
    slow = request_rate(1.5)
    assert slow < fast / 3, (fast, slow)
    for bad in (0.0, -5.0, math.inf, 1e9):
        assert not set_parameter(h.tester, node, 'control_rate', bad).successful
    assert h.node.controller.config.cycle_period == 0.25

    assert set_parameter(h.tester, node, 'status_rate', 5.0).successful
    assert h.node._rate_timers['status_rate'].timer_period_ns == 200_000_000
    # The values only shown in ~/status and /diagnostics are read once per message of the
    # more frequent: with a status (0.2 s) more often than the cycle (0.25 s), every
    # cycle; with a status every 5 s, once per diagnostics message (1 Hz): 0.75 s apart.
    assert h.node.controller.config.shown_period == pytest.approx(0.2)
    h.wait_cycles(2)
    assert h.node.controller.drive.display_period == 0.0
    assert set_parameter(h.tester, node, 'diagnostics_rate', 1.0).successful
    assert set_parameter(h.tester, node, 'status_rate', 0.2).successful
    # (set by the loop at a cycle's start: wait_cycles counts the simulator's requests)
    wait_for(lambda: h.node.controller.drive.display_period == pytest.approx(0.75), 3.0,
             'display period 0.75 s')
    assert set_parameter(h.tester, node, 'diagnostics_rate', 0.5).successful
    assert h.node.controller.config.shown_period == pytest.approx(2.0)
    assert not set_parameter(h.tester, node, 'status_rate', 0.0).successful
    assert h.node._rate_timers['status_rate'].timer_period_ns == 5_000_000_000
    assert h.node.controller.config.shown_period == pytest.approx(2.0)
    # Faster again: at once, not after the 5 s period under way has run out.
    assert set_parameter(h.tester, node, 'status_rate', 20.0).successful
    count = len(h.statuses)
    wait_for(lambda: len(h.statuses) >= count + 5, 1.5, 'five statuses at 20 Hz')


def test_descriptors_tell_live_from_read_only_with_ranges(make_harness):
    h = make_harness()
    node = f'{h.namespace}/drive'
    live = describe(h.tester, node, 'max_velocity')
    assert not live.read_only and 'live' in live.description
    assert live.floating_point_range[0].from_value > 0.0
    fixed = describe(h.tester, node, 'gear_ratio')
    assert fixed.read_only and fixed.floating_point_range
    priority = describe(h.tester, node, 'realtime_priority')
    assert priority.read_only and priority.integer_range[0].to_value == 99
    assert describe(h.tester, node, 'transport.port').read_only
    timeout = describe(h.tester, node, 'transport.timeout')
    assert timeout.read_only and timeout.floating_point_range[0].to_value == 10.0
    # rclpy's own use_sim_time: refused at run time, so described read-only too
    sim_time = describe(h.tester, node, 'use_sim_time')
    assert sim_time.read_only and 'start-up' in sim_time.description
    assert not set_parameter(h.tester, node, 'use_sim_time', False).successful


@pytest.fixture
def bus_rig(ros_context, tmp_path):
    profile = load_profile('boneng_am')
    sims = [SimulatedDrive(profile, unit, {'acceleration_time': 0.5,
                                           'deceleration_time': 0.5}) for unit in (1, 2)]
    port = str(tmp_path / 'rs485')
    line = SimulatedRtuLine(sims, port).start()
    prefix = f'/p{time.monotonic_ns() % 10 ** 8}'
    config = tmp_path / 'bus.yaml'
    config.write_text(yaml.safe_dump({
        'bus': {'name': 'rs485_0', 'transport.type': 'modbus_rtu', 'transport.port': port,
                'transport.timeout': 0.05, 'control_rate': 50.0},
        'drives': {w: {'namespace': f'{prefix}/{w}', 'drive.profile': 'boneng_am',
                       'transport.unit_id': unit, 'gear_ratio': GEAR, 'auto_enable': True}
                   for unit, w in ((1, 'left'), (2, 'right'))}}))
    bus = BusNode(context=ros_context, namespace=prefix, parameter_overrides=[
        Parameter('config_file', value=str(config))])
    tester = Node('tester', context=ros_context)
    from std_msgs.msg import Float64
    pubs = [tester.create_publisher(Float64, f'{prefix}/{w}/drive/velocity_command', 10)
            for w in ('left', 'right')]
    executor = make_executor(ros_context)
    for each in (bus, *bus.drive_nodes, tester):
        executor.add_node(each)
    spin = spin_in_background(executor, ros_context)
    rig = type('BusRig', (), {})()
    rig.__dict__.update(bus=bus, sims=sims, tester=tester, prefix=prefix, pubs=pubs)
    yield rig
    spin.stop()
    executor.shutdown(timeout_sec=1.0)
    bus.destroy_node()
    tester.destroy_node()
    line.stop()


def test_a_bus_drives_status_rate_is_applied_by_the_buss_shared_timers(bus_rig):
    """A bus publishes its drives' status from one timer per rate: a change regroups them."""
    rig = bus_rig

    def periods():
        return sorted(timer.timer_period_ns for timer in rig.bus._publish_timers)
    before = periods()
    assert set_parameter(rig.tester, f'{rig.prefix}/left/drive', 'status_rate', 5.0).successful
    assert 200_000_000 in periods() and 200_000_000 not in before
    assert rig.bus.drive_nodes[0].status_rate == 5.0
    assert not set_parameter(rig.tester, f'{rig.prefix}/left/drive', 'status_rate',
                             math.inf).successful
    assert rig.bus.drive_nodes[0].status_rate == 5.0


def test_bus_rate_is_the_bus_nodes_and_drive_limits_are_per_drive(bus_rig):
    from std_msgs.msg import Float64
    rig = bus_rig
    bus_name = f'{rig.prefix}/bus'
    left = f'{rig.prefix}/left/drive'
    assert set_parameter(rig.tester, bus_name, 'control_rate', 20.0).successful
    assert rig.bus.bus._loop.period == pytest.approx(0.05)
    assert get_parameter(rig.tester, left, 'control_rate') == 20.0      # shown, read-only
    result = set_parameter(rig.tester, left, 'control_rate', 10.0)
    assert not result.successful and 'read-only' in result.reason
    assert not set_parameter(rig.tester, bus_name, 'control_rate', math.nan).successful
    assert not set_parameter(rig.tester, bus_name, 'config_file', '/x.yaml').successful
    assert rig.bus.bus._loop.period == pytest.approx(0.05)

    assert set_parameter(rig.tester, left, 'max_velocity', 0.5).successful

    def speeds():
        for pub in rig.pubs:
            pub.publish(Float64(data=2.0))
        return [sim.speed_rpm / (GEAR * RPM_PER_RAD_S) for sim in rig.sims]
    wait_for(lambda: (s := speeds()) and abs(s[0] - 0.5) < 0.01 and abs(s[1] - 2.0) < 0.01,
             8.0, 'left capped at 0.5 rad/s, right at 2 rad/s', period=0.05)


def test_diff_drive_limits_are_live(ros_context):
    from test_diff_drive import DiffDriveRig
    rig = DiffDriveRig(ros_context)
    try:
        node = f'{rig.namespace}/diff_drive'
        rig.twist = (1.0, 0.0)
        radius = rig.node.kinematics.wheel_radius_m
        rig.wait_commands(1.0 / radius, 1.0 / radius, what='1 m/s')
        assert set_parameter(rig.tester, node, 'max_linear_velocity', 0.5).successful
        wheel = 0.5 / radius
        rig.wait_commands(wheel, wheel, what='capped at 0.5 m/s')
        for bad in (-1.0, math.nan):
            result = set_parameter(rig.tester, node, 'max_linear_velocity', bad)
            assert not result.successful and 'max_linear_velocity' in result.reason
        assert rig.node.limiter.limits.max_linear_m_s == 0.5
        assert not set_parameter(rig.tester, node, 'wheel_radius', 0.2).successful
        assert set_parameter(rig.tester, node, 'publish_rate', 10.0).successful
        assert rig.node._tick_timer.timer_period_ns == 100_000_000
    finally:
        rig.close()


def test_sim_drive_read_only_and_line_faults_only_where_simulated(ros_context):
    from vfd_ros2.sim.node import SimDriveNode
    node = SimDriveNode(namespace='/simro', context=ros_context, parameter_overrides=[
        Parameter('transport', value='modbus_tcp'), Parameter('tcp_port', value=0)])
    tester = Node('tester', namespace='/simro', context=ros_context)
    executor = SingleThreadedExecutor(context=ros_context)
    executor.add_node(node)
    executor.add_node(tester)
    spin = spin_in_background(executor, ros_context)
    try:
        assert not set_parameter(tester, '/simro/sim_drive', 'profile', 'imo_hd2').successful
        result = set_parameter(tester, '/simro/sim_drive', 'late_rate', 0.5)
        assert not result.successful and 'modbus_rtu' in result.reason
        assert set_parameter(tester, '/simro/sim_drive', 'silent_unit_ids', [1]).successful
        assert node.drives[0].silent
        # An untyped empty list (rclpy: byte array; ros2cli "[]": bool array) plugs it back.
        assert set_parameter(tester, '/simro/sim_drive', 'silent_unit_ids', []).successful
        assert not node.drives[0].silent
        result = set_parameter(tester, '/simro/sim_drive', 'silent_unit_ids', ['x'])
        assert not result.successful and not node.drives[0].silent
    finally:
        spin.stop()
        executor.shutdown(timeout_sec=1.0)
        node.destroy_node()
        tester.destroy_node()


def test_a_faster_rate_takes_effect_at_once_not_after_the_old_period():
    from vfd_ros2.control.loop import CycleLoop
    steps = []
    loop = CycleLoop('test', 30.0, lambda: steps.append(time.monotonic()), lambda: None)
    loop.start()
    try:
        wait_for(lambda: steps, 2.0, 'the first cycle')
        loop.set_period(0.01)
        wait_for(lambda: len(steps) >= 5, 5.0, 'cycles at the new period (not 30 s later)')
    finally:
        loop.stop()


def test_a_refused_value_is_shown_as_given():
    """0.499999999 refused as 'must be >= 0.5, got 0.5' did not say what was wrong."""
    from vfd_ros2.ros.parameters import check_value
    with pytest.raises(ValueError, match=r'control_rate must be >= 0.5, got 0.499999999$'):
        check_value('control_rate', 0.499999999, 0.5, 1000.0)
    with pytest.raises(ValueError, match=r'status_rate must be <= 1000, got 1000.000001$'):
        check_value('status_rate', 1000.000001, 0.1, 1000.0)
    check_value('status_rate', 1000.0, 0.1, 1000.0)
