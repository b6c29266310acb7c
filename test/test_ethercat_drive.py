"""Drive nodes with ``transport.type: ethercat`` <-> the simulated EtherCAT segment.

Real frames end to end: SOEM (pysoem) in this process on one end of a veth pair
in a namespace the test creates, the emulated ESCs with their CiA 402 drives in
a child process on the other end; the nodes are the real ``DriveNode`` and
``BusNode`` on DDS (loopback). Waits are conditions with deadlines.
"""

from __future__ import annotations

import contextlib
import logging
import threading
import time
import uuid
from typing import Any, Iterable, Iterator

import pytest
import yaml
from diagnostic_msgs.msg import DiagnosticArray
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter

from harness import DriveClient, wait_for
from vfd_ros2.profiles import load_profile
from vfd_ros2.protocol.ethercat import ALState, ALStatusCode
from vfd_ros2.ros.bus_node import BusNode
from vfd_ros2.ros.drive_node import DriveNode
from vfd_ros2.ros.executable import spin_in_background
from vfd_ros2.sim.ethercat.catalog import BONENG_MH_EC, IMO_HD2_EC_TX508
from vfd_ros2.srv import GetDriveParameter, SetDriveParameter

pytest_plugins = ['ethercat_harness']

BASE = {'gear_ratio': 10.0, 'status_rate': 50.0, 'diagnostics_rate': 5.0, 'stop_timeout': 3.0,
        'command_timeout': 0.5, 'reconnect_period': 0.2}


class EcWheel(DriveClient):
    """One DriveNode on the test segment plus the tester's view of it."""

    def __init__(self, context: Any, tester: Node, parameters: dict[str, Any]) -> None:
        self.namespace = f'/e{uuid.uuid4().hex[:8]}/wheel'
        self.node = DriveNode('drive', namespace=self.namespace, context=context,
                              parameter_overrides=[Parameter(k, value=v)
                                                   for k, v in parameters.items()])
        super().__init__(context, tester, f'{self.namespace}/drive')
        self.diagnostics: list[DiagnosticArray] = []
        tester.create_subscription(DiagnosticArray, '/diagnostics', self.diagnostics.append, 10)


@pytest.fixture
def make_wheel(ros_context, veth_link):
    """Return ``make(profile, unit_id=1, **parameters)`` -> an EcWheel on the test segment."""
    tester = Node('tester', namespace=f'/t{uuid.uuid4().hex[:8]}', context=ros_context)
    executor = SingleThreadedExecutor(context=ros_context)
    executor.add_node(tester)
    wheels: list[EcWheel] = []

    def make(profile: str, unit_id: int = 1, **parameters: Any) -> EcWheel:
        values = {'drive.profile': profile, 'transport.type': 'ethercat',
                  'transport.interface': veth_link.master_interface,
                  'transport.namespace': veth_link.namespace, 'transport.unit_id': unit_id,
                  **BASE, **parameters}
        wheel = EcWheel(ros_context, tester, values)
        executor.add_node(wheel.node)
        wheels.append(wheel)
        return wheel

    spin = spin_in_background(executor, ros_context)
    yield make
    for wheel in wheels:
        wheel.stop_stream()
    spin.stop()
    executor.shutdown(timeout_sec=1.0)
    for wheel in wheels:
        wheel.node.destroy_node()
    tester.destroy_node()


def test_drive_node_reaches_op_follows_velocity_and_reports(start_segment, make_wheel):
    sim = start_segment([IMO_HD2_EC_TX508])
    wheel = make_wheel('imo_hd2', auto_enable=True, drive_comm_timeout=0.3)
    status = wheel.wait_status(lambda s: s.online, 10.0, 'online')
    assert sim.drive(0)['al_state'] == 'OP' and sim.drive(0)['mode'] == 9   # csv, at PRE-OP
    assert sim.drive(0)['velocity_rpm'] == 0.0            # start-up never moves the motor
    # host-death protection: the SM watchdog, reported like drive_comm_timeout elsewhere
    assert status.host_loss_timeout == pytest.approx(0.3)
    assert 'SM watchdog' in status.host_loss_protection
    assert sim.esc(0)['watchdog_s'] == pytest.approx(0.3, abs=0.001)
    wheel.stream(2.0)
    status = wheel.wait_status(lambda s: s.running and abs(s.measured_velocity - 2.0) < 0.05,
                               6.0, 'at 2 rad/s')
    assert status.commanded_velocity == 2.0 and not status.fault
    assert sim.drive(0)['state'] == 'OPERATION_ENABLED'
    assert abs(sim.drive(0)['velocity_rpm'] - 2.0 * 10 * 60 / (2 * 3.141592653589793)) < 1.0
    wheel.stream(-1.0)
    wheel.wait_status(lambda s: s.reverse and abs(s.measured_velocity + 1.0) < 0.05, 6.0,
                      'at -1 rad/s')
    wheel.stop_stream()
    wheel.wait_status(lambda s: s.watchdog_tripped, 2.0, 'command watchdog')
    wait_for(lambda: sim.drive(0)['velocity_rpm'] == 0.0, 5.0, 'motor stopped')
    wait_for(lambda: any(s.hardware_id.endswith('#1') and 'imo_hd2' in s.hardware_id
                         for d in wheel.diagnostics for s in d.status), 3.0, 'diagnostics')


def all_at(controllers: Iterable[Any], velocity: float) -> bool:
    """Command ``velocity`` to each drive; return whether all run at it (within 0.05)."""
    controllers = list(controllers)
    for controller in controllers:
        controller.command_velocity(velocity)
    return all(c.state.running and abs(c.state.measured_velocity - velocity) < 0.05
               for c in controllers)


@contextlib.contextmanager
def bus_node_on_segment(ros_context, veth_link, tmp_path, profiles: tuple[str, str],
                        *settings: dict[str, Any]) -> Iterator[BusNode]:
    """Spin a bus_node over the emulated segment: wheels 'left' (slave 1), 'right' (2).

    ``settings``: each wheel's own drive settings beside the common ones, in order.
    """
    prefix = f'/b{uuid.uuid4().hex[:6]}'
    config = tmp_path / 'ec_bus.yaml'
    config.write_text(yaml.safe_dump({
        'bus': {'name': 'ec0', 'transport.type': 'ethercat',
                'transport.interface': veth_link.master_interface,
                'transport.namespace': veth_link.namespace, 'control_rate': 50.0},
        'drives': {name: {'namespace': f'{prefix}/{name}', 'drive.profile': profile,
                          'transport.unit_id': unit, 'auto_enable': True, **BASE,
                          **(settings[unit - 1] if len(settings) >= unit else {})}
                   for unit, (name, profile) in enumerate(zip(('left', 'right'), profiles),
                                                          start=1)}}))
    bus = BusNode(context=ros_context, namespace=prefix, parameter_overrides=[
        Parameter('config_file', value=str(config))])
    executor = SingleThreadedExecutor(context=ros_context)
    for node in (bus, *bus.drive_nodes):
        executor.add_node(node)
    spin = spin_in_background(executor, ros_context)
    try:
        yield bus
    finally:
        spin.stop()
        executor.shutdown(timeout_sec=1.0)
        bus.destroy_node()


def test_the_first_connect_does_not_fail_on_a_segment_just_opened(start_segment, make_wheel,
                                                                   caplog):
    """A connect right after the segment opened waits for the first cycle's inputs.

    It failed on "no process data yet" and closed the segment again: one to three
    more opens each time (outside audit).
    """
    start_segment([IMO_HD2_EC_TX508])
    with caplog.at_level(logging.INFO):
        wheel = make_wheel('imo_hd2')
        wheel.wait_status(lambda s: s.online, 10.0, 'online')
    failed = [r.getMessage() for r in caplog.records if 'process data' in r.getMessage()]
    assert not failed, failed


def test_bus_node_serves_two_drives_on_one_segment(ros_context, start_segment, veth_link,
                                                   tmp_path):
    sim = start_segment([IMO_HD2_EC_TX508, BONENG_MH_EC])
    with bus_node_on_segment(ros_context, veth_link, tmp_path, ('imo_hd2', 'boneng_mh')) as bus:
        controllers = bus.bus.controllers
        wait_for(lambda: all(c.state.online for c in controllers.values()), 10.0, 'both online')
        assert len(bus.bus.transports) == 1                      # one segment ...
        cycle_threads = [t for t in threading.enumerate()
                         if t.name == f'ethercat-{veth_link.master_interface}']
        assert len(cycle_threads) == 1                           # ... one process-data thread
        wait_for(lambda: all_at(controllers.values(), 1.0), 8.0, 'both at 1 rad/s')
        for c in controllers.values():      # drive_comm_timeout 0.3 s holds on a bus too
            assert c.state.protection.timeout == pytest.approx(0.3), c.state.protection
        assert sim.drive(0)['mode'] == 9                         # HD2 in csv
        assert sim.drive(1)['controlword'] & 0x70 == 0x70        # MH CoE_VL: ramp bits set
        assert sim.drive(1)['velocity_rpm'] > 90.0


def test_each_slave_of_a_bus_holds_its_own_drives_sm_watchdog(ros_context, start_segment,
                                                               veth_link, tmp_path):
    """A drive that asks for no SM watchdog gets none, beside one that asks for 0.3 s.

    The smallest asked for went to every slave: the first reported "off" while its
    slave held the other's 0.3 s (outside audit).
    """
    sim = start_segment([IMO_HD2_EC_TX508, IMO_HD2_EC_TX508])
    with bus_node_on_segment(ros_context, veth_link, tmp_path, ('imo_hd2', 'imo_hd2'),
                             {'drive_comm_timeout': 0.0}, {'drive_comm_timeout': 0.3}) as bus:
        left, right = bus.bus.controllers['left'], bus.bus.controllers['right']
        wait_for(lambda: left.state.online and right.state.online, 10.0, 'both online')
        assert sim.esc(0)['watchdog_s'] == 0.0, sim.esc(0)
        assert sim.esc(1)['watchdog_s'] == pytest.approx(0.3, abs=0.001), sim.esc(1)
        assert not left.state.protection.active, left.state.protection
        assert right.state.protection.timeout == pytest.approx(0.3), right.state.protection


def test_identity_mismatch_is_a_clear_error(start_segment, make_wheel):
    start_segment([BONENG_MH_EC])
    wheel = make_wheel('imo_hd2')
    status = wheel.wait_status(lambda s: 'not the drive of the profile' in s.stop_reason, 10.0,
                               'identity error')
    assert not status.online
    assert 'vendor 0x0, not 0x4D8' in status.stop_reason
    assert 'product 0x0, not 0x9252' in status.stop_reason


def test_unknown_nic_is_a_clear_error(make_wheel):
    wheel = make_wheel('imo_hd2', **{'transport.interface': 'nosuchnic0'})
    status = wheel.wait_status(lambda s: 'nosuchnic0' in s.stop_reason, 10.0, 'NIC error')
    assert not status.online and 'cannot open nosuchnic0' in status.stop_reason


def test_a_second_drive_node_on_the_nic_is_refused_and_says_use_a_bus_node(start_segment,
                                                                             make_wheel):
    """One drive_node per slave of one NIC (two masters on one segment) is refused.

    The first keeps its drive; the second stays offline with the reason, instead
    of resetting and driving both slaves as a second master would.
    """
    sim = start_segment([IMO_HD2_EC_TX508, BONENG_MH_EC])
    first = make_wheel('imo_hd2', auto_enable=True)
    first.wait_status(lambda s: s.online, 10.0, 'first online')
    second = make_wheel('boneng_mh', unit_id=2, auto_enable=True)
    status = second.wait_status(lambda s: 'another EtherCAT master' in s.stop_reason, 10.0,
                                'refused')
    assert not status.online and 'one bus_node' in status.stop_reason
    first.stream(1.0)
    first.wait_status(lambda s: s.running and abs(s.measured_velocity - 1.0) < 0.05, 6.0,
                      'the first still drives its slave')
    assert first.wait_status(lambda s: True, 1.0, 'status').reconnects == 0
    assert sim.drive(1)['velocity_rpm'] == 0.0


def test_slave_stuck_below_op_then_recovers(start_segment, make_wheel):
    sim = start_segment([IMO_HD2_EC_TX508])
    code = int(ALStatusCode.INVALID_OUTPUT_MAPPING)
    sim.call(0, 'refuse_state', int(ALState.OP), code)
    wheel = make_wheel('imo_hd2')
    status = wheel.wait_status(lambda s: 'AL status code' in s.stop_reason, 10.0,
                               'stuck below OP')
    assert not status.online and f'0x{code:04X}' in status.stop_reason
    sim.call(0, 'refuse_state', int(ALState.OP), 0)
    wheel.wait_status(lambda s: s.online, 10.0, 'in OP after the refusal ends')


def test_cable_pulled_mid_motion_recovers_stopped(start_segment, make_wheel):
    sim = start_segment([IMO_HD2_EC_TX508])
    wheel = make_wheel('imo_hd2', auto_enable=True, drive_comm_timeout=0.2)
    wheel.wait_status(lambda s: s.online, 10.0, 'online')
    wheel.stream(2.0)
    wheel.wait_status(lambda s: s.running and abs(s.measured_velocity - 2.0) < 0.05, 6.0,
                      'running')
    sim.link_down()
    status = wheel.wait_status(lambda s: not s.online, 3.0, 'offline')
    assert status.stop_reason
    # the SM watchdog stops the drive by itself: fault 0x8250 (= 66 E-CAT in the profile)
    wait_for(lambda: sim.drive(0)['error_code'] == 0x8250 and
             sim.drive(0)['velocity_rpm'] == 0.0, 5.0, 'drive stopped by its SM watchdog')
    wheel.stop_stream()                      # the planner stops publishing meanwhile
    time.sleep(0.6)                          # > command_timeout: the last command is stale
    sim.link_up()
    status = wheel.wait_status(lambda s: s.online and s.reconnects >= 1, 10.0, 'back online')
    # its own comm fault found at connect is reset once; the motor stays stopped
    wheel.wait_status(lambda s: not s.fault, 3.0, 'comm fault reset at connect')
    deadline = time.monotonic() + 1.0
    while time.monotonic() < deadline:
        snapshot = sim.drive(0)
        assert snapshot['velocity_rpm'] == 0.0 and snapshot['state'] != 'OPERATION_ENABLED', \
            snapshot
        time.sleep(0.05)
    assert wheel.status.run_state == wheel.status.RUN_STATE_WATCHDOG
    wheel.stream(1.0)                        # a fresh command moves it again
    wheel.wait_status(lambda s: s.running and abs(s.measured_velocity - 1.0) < 0.05, 6.0,
                      'moving on a fresh command')


def test_a_slave_that_falls_from_op_by_itself_comes_back_on_safe_outputs(start_segment,
                                                                        make_wheel):
    """It fell to SAFE-OP+ERROR while running; the supervisor brings it back to OP.

    It must not come back on the last run command (and the drive be walked back to
    Operation Enabled on it): its safe outputs stand, and its drive is told of the
    fall (offline, with the AL state and code) until it has reconnected.
    """
    sim = start_segment([IMO_HD2_EC_TX508])
    wheel = make_wheel('imo_hd2', auto_enable=True)
    wheel.wait_status(lambda s: s.online, 10.0, 'online')
    wheel.stream(2.0)
    wheel.wait_status(lambda s: s.running and abs(s.measured_velocity - 2.0) < 0.05, 6.0,
                      'running')
    transport = wheel.node.controller.drive.transport
    safe = transport._setups[1].safe_outputs                    # noqa: SLF001
    reconnects = wheel.status.reconnects
    sim.fail(0, ALState.SAFE_OP, 0x001B)
    fallen = []
    deadline = time.monotonic() + 3.0
    while time.monotonic() < deadline and wheel.status.reconnects == reconnects:
        if 1 in transport._fell:                                # noqa: SLF001
            fallen.append(transport._slave(1).outputs())        # noqa: SLF001
        time.sleep(0.002)
    assert fallen and all(outputs == safe for outputs in fallen), fallen[:3]
    wheel.wait_status(lambda s: s.reconnects > reconnects, 5.0, 'reconnected')
    assert any('fell to SAFE_OP+ERROR, AL status code 0x001B' in s.stop_reason
               for s in wheel.statuses), 'the fall was not reported'
    wheel.wait_status(lambda s: s.running and abs(s.measured_velocity - 2.0) < 0.05, 6.0,
                      'running again on the commands that kept coming')


def test_emergency_gives_the_profile_fault_text(start_segment, make_wheel):
    sim = start_segment([IMO_HD2_EC_TX508, BONENG_MH_EC])
    hd2 = make_wheel('imo_hd2', unit_id=1)
    hd2.wait_status(lambda s: s.online, 10.0, 'online')
    entry = load_profile('imo_hd2').faults.table[66]
    sim.call(0, 'inject_fault', 0x8250, 0x11)
    status = hd2.wait_status(lambda s: s.fault and s.fault_code == 66, 5.0, 'fault 66')
    fault = wait_for(lambda: next((f for f in reversed(hd2.faults) if f.active), None), 3.0,
                     'fault message')
    assert fault.name == entry.name and 'E-CAT' in fault.name and fault.known
    assert status.run_state == status.RUN_STATE_FAULT
    reply = hd2.trigger('reset_fault')
    assert reply.success, reply.message
    hd2.wait_status(lambda s: not s.fault, 3.0, 'fault cleared')
    # a code the profile does not map: the CiA 301 class text, marked unknown
    sim.call(0, 'inject_fault', 0x4310, 0x09)
    fault = wait_for(lambda: next((f for f in reversed(hd2.faults)
                                   if f.active and f.code == 0x4310), None), 5.0, 'CiA fault')
    assert not fault.known and 'CiA 301' in fault.cause


def test_mh_fault_byte_and_its_coe_parameters(start_segment, make_wheel):
    sim = start_segment([BONENG_MH_EC])
    mh = make_wheel('boneng_mh')
    mh.wait_status(lambda s: s.online, 10.0, 'online')
    # no function-code objects in the EC dictionary: its CiA 402 objects over SDO
    reply = mh.call(SetDriveParameter, 'set_drive_parameter',
                    SetDriveParameter.Request(name='vl_acceleration_delta_time', value=3.0,
                                              persistent=False))
    assert reply.success, reply.message
    got = mh.call(GetDriveParameter, 'get_drive_parameter',
                  GetDriveParameter.Request(name='0x6048:2'))
    assert got.success and got.value == 3.0
    got = mh.call(GetDriveParameter, 'get_drive_parameter',
                  GetDriveParameter.Request(name='C02.04'))
    assert not got.success and 'not reachable over EtherCAT' in got.message
    # an emergency whose first manufacturer byte is the drive's own fault number
    entry = load_profile('boneng_mh').faults.table[35]
    sim.call(0, 'inject_fault', 0xFF00, 0x81, bytes([35, 0, 0, 0, 0]))
    fault = wait_for(lambda: next((f for f in reversed(mh.faults)
                                   if f.active and f.code == 35), None), 5.0, 'fault 35')
    assert fault.name == entry.name and fault.known
    assert mh.status.fault and mh.status.fault_code == 35


def test_hd2_function_codes_over_sdo(start_segment, make_wheel):
    start_segment([IMO_HD2_EC_TX508])
    hd2 = make_wheel('imo_hd2')
    hd2.wait_status(lambda s: s.online, 10.0, 'online')
    got = hd2.call(GetDriveParameter, 'get_drive_parameter',
                   GetDriveParameter.Request(name='P00.10'))
    assert got.success and got.value == pytest.approx(50.0), got.message
    reply = hd2.call(SetDriveParameter, 'set_drive_parameter',
                     SetDriveParameter.Request(name='P00.10', value=42.5, persistent=False))
    assert reply.success, reply.message
    got = hd2.call(GetDriveParameter, 'get_drive_parameter',
                   GetDriveParameter.Request(name='P00.10'))
    assert got.value == pytest.approx(42.5)
    reply = hd2.call(SetDriveParameter, 'set_drive_parameter',       # not in this drive
                     SetDriveParameter.Request(name='P14.00', value=3.0, persistent=True))
    assert not reply.success and 'illegal data address' in reply.message, reply.message
    reply = hd2.call(SetDriveParameter, 'set_drive_parameter',
                     SetDriveParameter.Request(name='P00.10', value=1e9, persistent=False))
    assert not reply.success and 'above the maximum' in reply.message
    # The Modbus card's communication registers are no function codes: the window's
    # "illegal data address" read like a Modbus reply (outside audit); said up front.
    got = hd2.call(GetDriveParameter, 'get_drive_parameter',
                   GetDriveParameter.Request(name='status_word_1'))
    assert not got.success and 'is not a function code' in got.message and \
        'not reachable over EtherCAT' in got.message, got.message
    # The card's own comm-loss timeout: 0.0 ("invalid") took that protection away, and
    # was written (outside audit).
    reply = hd2.call(SetDriveParameter, 'set_drive_parameter',
                     SetDriveParameter.Request(name='P16.18', value=0.0, persistent=False))
    assert not reply.success and "card's own comm-loss timeout" in reply.message, reply.message


def test_a_short_frame_loss_is_ridden_through(ros_context, start_segment, veth_link,
                                              tmp_path):
    """A frame loss shorter than stale_after leaves every drive online and running.

    80 ms without frames (interference), less than stale_after (0.25 s) and the SM
    watchdog: the first unanswered state read took every slave for lost (all
    drives offline, the slaves reset).
    """
    sim = start_segment([IMO_HD2_EC_TX508, IMO_HD2_EC_TX508])
    with bus_node_on_segment(ros_context, veth_link, tmp_path, ('imo_hd2', 'imo_hd2')) as bus:
        drives = list(bus.bus.controllers.values())
        wait_for(lambda: all_at(drives, 1.0), 10.0, 'both at 1 rad/s')
        sim.lose_frames(0.08)
        end = time.monotonic() + 1.0
        while time.monotonic() < end:
            all_at(drives, 1.0)
            assert all(c.state.online for c in drives), [c.state.stop_reason for c in drives]
            time.sleep(0.02)
        assert all(c.state.reconnects == 0 and c.state.running for c in drives)


def test_bus_slave_unplugged_the_other_keeps_running(ros_context, start_segment, veth_link,
                                                      tmp_path):
    """One slave of a bus lost and found again by the segment's supervisor, not a restart."""
    sim = start_segment([IMO_HD2_EC_TX508, IMO_HD2_EC_TX508])
    with bus_node_on_segment(ros_context, veth_link, tmp_path, ('imo_hd2', 'imo_hd2')) as bus:
        left, right = bus.bus.controllers['left'], bus.bus.controllers['right']
        wait_for(lambda: all_at((left, right), 1.0), 10.0, 'both at 1 rad/s')
        sim.unplug(1)                                     # the cable into the second slave
        wait_for(lambda: (left.command_velocity(1.0), not right.state.online)[1], 3.0,
                 'right offline')
        assert left.state.online and left.state.running, left.state   # the left keeps going
        assert bus.bus.link_stats().bad_frames > 0, bus.bus.link_stats()  # saw WKC drops
        sim.replug(1)
        wait_for(lambda: (left.command_velocity(1.0), right.state.online and
                          right.state.reconnects >= 1)[1], 10.0, 'right back')
        # right has had no fresh command since it came back: it stays stopped
        assert not right.state.running and right.state.run_state != 6, right.state
        assert sim.drive(1)['velocity_rpm'] == 0.0 or sim.drive(1)['state'] != \
            'OPERATION_ENABLED', sim.drive(1)
        wait_for(lambda: all_at((left, right), 1.0), 8.0, 'both moving again on fresh commands')
        # powered off and on: the slave comes back with the ESC's default watchdog and its
        # default PDO mapping and mode; the transport writes its set-up and watchdog again
        left_reconnects = left.state.reconnects
        sim.power_cycle(1)
        wait_for(lambda: (left.command_velocity(1.0), not right.state.online)[1], 3.0,
                 'right offline after the power cycle')
        wait_for(lambda: (left.command_velocity(1.0), right.state.online)[1], 10.0,
                 'right back after the power cycle')
        assert sim.esc(1)['watchdog_s'] == pytest.approx(0.3, abs=0.001), sim.esc(1)
        assert right.state.protection.timeout == pytest.approx(0.3), right.state.protection
        assert sim.drive(1)['mode'] == 9, sim.drive(1)    # csv written again at PRE-OP
        # by the supervisor, in place: the left wheel never went offline meanwhile
        assert left.state.online and left.state.reconnects == left_reconnects, left.state
        wait_for(lambda: all_at((left, right), 1.0), 8.0, 'both moving after the power cycle')


def test_a_slave_that_refuses_its_set_up_after_a_power_cycle_stays_in_pre_op_and_says_why(
        ros_context, start_segment, veth_link, tmp_path, caplog):
    """A slave whose set-up aborts after a power cycle must not run in its power-on mode.

    Its mode of operation write aborts: it stays in PRE-OP, its drive offline naming
    the abort; the set-up is tried again once a second and told once (each
    supervisor pass wrote it and logged a line, 1000 in 3 s: outside audit); the
    other wheel runs on.
    """
    sim = start_segment([IMO_HD2_EC_TX508, IMO_HD2_EC_TX508])
    with bus_node_on_segment(ros_context, veth_link, tmp_path, ('imo_hd2', 'imo_hd2')) as bus:
        left, right = bus.bus.controllers['left'], bus.bus.controllers['right']
        wait_for(lambda: all_at((left, right), 1.0), 10.0, 'both at 1 rad/s')
        sim.call(0, 'abort_writes', 0x6060, 0x06090030)
        with caplog.at_level(logging.WARNING):
            sim.power_cycle(0)
            wait_for(lambda: (right.command_velocity(1.0), 'is not written again at PRE-OP'
                              in left.state.stop_reason)[1], 5.0, 'left offline, saying why')
            writes = sim.drive(0)['sdo_writes']
            deadline = time.monotonic() + 2.0
            while time.monotonic() < deadline:
                right.command_velocity(1.0)
                assert not left.state.online and right.state.running, (left.state, right.state)
                time.sleep(0.05)
            assert sim.drive(0)['al_state'] == 'PRE_OP', sim.drive(0)
            # ~16 writes a try, one try a second: not one a pass (40 passes in 2 s)
            assert sim.drive(0)['sdo_writes'] - writes < 80, sim.drive(0)
        told = [r.getMessage() for r in caplog.records if 'set-up not written' in
                r.getMessage()]
        assert len(told) == 1, told
        assert '0x06090030' in left.state.stop_reason, left.state.stop_reason
        sim.call(0, 'abort_writes', 0x6060, 0)
        wait_for(lambda: all_at((left, right), 1.0), 10.0, 'both moving once the set-up is taken')
        assert sim.drive(0)['mode'] == 9, sim.drive(0)


def test_sync_mode_dc(start_segment, make_wheel):
    sim = start_segment([IMO_HD2_EC_TX508])
    hd2 = make_wheel('imo_hd2', **{'transport.sync_mode': 'dc', 'transport.cycle_time': 0.001})
    hd2.wait_status(lambda s: s.online, 10.0, 'HD2 online in DC mode')
    assert sim.esc(0)['sync0_cycle_ns'] == 1_000_000


def test_simulated_drives_and_profiles_agree():
    """The simulator reads identity, assignment and sync from the profiles; mappings match."""
    for spec, profile in ((BONENG_MH_EC, 'boneng_mh'), (IMO_HD2_EC_TX508, 'imo_hd2')):
        ec = load_profile(profile).ethercat
        assert spec.rx_assign == ec.rx_pdos and spec.tx_assign == ec.tx_pdos
        assert spec.name == ec.identity.device_name
        if ec.fixed_mapping:          # what the driver expects is what the drive holds
            rx = {p.index: p for p in spec.rx_pdos}[ec.rx_pdos[0]]
            tx = {p.index: p for p in spec.tx_pdos}[ec.tx_pdos[0]]
            assert [(i << 16) | (s << 8) | b for i, s, b in rx.entries] == \
                [obj.mapping for obj in ec.rx_entries]
            assert [(i << 16) | (s << 8) | b for i, s, b in tx.entries] == \
                [obj.mapping for _, obj in ec.tx_entries]
    assert IMO_HD2_EC_TX508.vendor_id == 0x4D8 and IMO_HD2_EC_TX508.product_code == 0x9252


def test_shipped_ethercat_bus_config_and_bad_settings():
    """config/ethercat_bus.yaml is valid; bad transport settings are clear errors (no I/O)."""
    from pathlib import Path

    from vfd_ros2.control.bus import parse_bus_config
    from vfd_ros2.control.factory import build_transport
    from vfd_ros2.errors import TransportError
    path = Path(__file__).resolve().parents[1] / 'config' / 'ethercat_bus.yaml'
    config = parse_bus_config(yaml.safe_load(path.read_text()))
    assert [d.settings['drive.profile'] for d in config.drives] == ['imo_hd2', 'boneng_mh']
    transport = build_transport({**config.settings, **config.drives[0].settings})
    assert transport.description == 'ethercat:enp3s0' and transport.shared_by_drives
    base = {'drive.profile': 'imo_hd2', 'transport.type': 'ethercat',
            'transport.interface': 'eth9'}
    for bad, why in (({'transport.interface': ''}, 'transport.interface is empty'),
                     ({'transport.sync_mode': 'sometimes'}, 'use free_run or dc'),
                     ({'transport.cycle_time': 0.0}, 'transport.cycle_time'),
                     ({'transport.realtime_priority': 120}, 'use 0..99')):
        with pytest.raises(TransportError, match=why):
            build_transport({**base, **bad})
    with pytest.raises(Exception, match='profile boneng_am is for modbus_rtu, not ethercat'):
        build_transport({**base, 'drive.profile': 'boneng_am'})


def test_hung_control_loop_stops_the_drive(start_segment, veth_link):
    """The process-data thread outlives a hung control loop: stale outputs become a stop."""
    from vfd_ros2.control.factory import build_controller
    sim = start_segment([IMO_HD2_EC_TX508])
    controller = build_controller({
        'drive.profile': 'imo_hd2', 'transport.type': 'ethercat',
        'transport.interface': veth_link.master_interface,
        'transport.namespace': veth_link.namespace, 'auto_enable': True,
        'drive_comm_timeout': 0.2, 'command_timeout': 10.0, 'gear_ratio': 10.0})
    try:
        def cycle() -> bool:
            controller.command_velocity(2.0)
            controller.step()
            return sim.drive(0)['velocity_rpm'] > 150.0
        wait_for(cycle, 8.0, 'running at 2 rad/s', period=0.02)
        assert controller.state.protection.timeout == pytest.approx(0.2)
        # the loop hangs here (no more step()); frames keep flowing, so the SM watchdog
        # alone would never trip
        wait_for(lambda: sim.drive(0)['state'] == 'SWITCHED_ON', 2.0, 'operation disabled')
        wait_for(lambda: sim.drive(0)['velocity_rpm'] == 0.0, 5.0, 'ramped to a stop')
        assert controller.drive.transport.outputs_held(1) > 0
        assert sim.drive(0)['error_code'] == 0 and sim.drive(0)['al_state'] == 'OP'
    finally:
        controller.finish()


def test_identity_check_and_host_loss_plan_without_io():
    """Identity rules and the SM watchdog plan, on plain values (no segment)."""
    from vfd_ros2.drives.ethercat import EthercatDrive
    from vfd_ros2.protocol.scaling import VelocityScaling
    from vfd_ros2.transports.ethercat import (
        EthercatTransport,
        PdoConfiguration,
        SegmentSettings,
        SlaveIdentity,
        SlaveSetup,
        identity_mismatch,
    )
    setup = SlaveSetup(1, PdoConfiguration((0x1600,), (0x1A00,)), 6, 8, bytes(6),
                       vendor_id=0x4D8, product_code=0x9252, device_name='IMO-EtherCAT')
    assert identity_mismatch(SlaveIdentity(0, 'IMO-EtherCAT', 0x4D8, 0x9252, 1), setup) == ''
    text = identity_mismatch(SlaveIdentity(0, 'X', 0x4D8, 0x1, 1), setup)
    assert 'product 0x1, not 0x9252' in text and 'vendor' not in text
    by_name = SlaveSetup(2, PdoConfiguration((0x1701,), (0x1B01,)), 4, 4, bytes(4),
                         device_name='AD_Drive')
    assert identity_mismatch(SlaveIdentity(1, 'AD_Drive', 0, 0, 1), by_name) == ''
    assert "device name 'Other', not 'AD_Drive'" in identity_mismatch(
        SlaveIdentity(1, 'Other', 0, 0, 1), by_name)
    transport = EthercatTransport(SegmentSettings('eth9', cycle_time_s=0.002))
    drive = EthercatDrive(load_profile('imo_hd2'), transport, 1, VelocityScaling(10.0))
    plan = drive.host_loss_plan(0.3, 0.02)
    assert plan.active and plan.timeout == pytest.approx(0.3) and 'SM watchdog' in plan.mechanism
    plan = drive.host_loss_plan(0.01, 0.02)              # raised: frames, commands, jitter
    assert plan.timeout == pytest.approx(0.09) and 'raised from 0.01 s' in plan.note
    assert drive.host_loss_plan(100.0, 0.02).timeout == pytest.approx(6.5535)
    off = drive.host_loss_plan(0.0, 0.02)
    assert not off.active and 'off' in off.note
    with pytest.raises(Exception, match='attached twice'):
        EthercatDrive(load_profile('imo_hd2'), transport, 1, VelocityScaling(10.0))


def test_a_sync_the_drive_does_not_take_is_refused_at_start():
    """Known from the profile before any frame: it used to be retried for ever."""
    from vfd_ros2.control.factory import build_controller
    from vfd_ros2.errors import TransportError
    base = {'transport.type': 'ethercat', 'transport.interface': 'eth9',
            'transport.sync_mode': 'dc'}
    with pytest.raises(TransportError, match='slave 1 accepts cycle times 250 us, 500 us, '
                                             '1000 us, 2000 us, not transport.cycle_time '
                                             '3000 us'):
        build_controller({**base, 'drive.profile': 'imo_hd2', 'transport.cycle_time': 0.003})
    with pytest.raises(TransportError, match='slave 1 has no DC sync'):
        build_controller({**base, 'drive.profile': 'boneng_mh', 'transport.cycle_time': 0.002})
    assert build_controller({**base, 'drive.profile': 'imo_hd2',
                             'transport.cycle_time': 0.002}).drive.unit_id == 1


def test_slave_found_by_station_alias(start_segment, make_wheel):
    """drive.station_alias finds the slave whatever its position (unit_id is only a key)."""
    import dataclasses
    sim = start_segment([IMO_HD2_EC_TX508, dataclasses.replace(IMO_HD2_EC_TX508, alias=0x0A2)])
    wheel = make_wheel('imo_hd2', unit_id=7, auto_enable=True, **{'drive.station_alias': 0xA2})
    wheel.wait_status(lambda s: s.online, 10.0, 'online')
    wheel.stream(1.0)
    wheel.wait_status(lambda s: s.running and abs(s.measured_velocity - 1.0) < 0.05, 6.0,
                      'running')
    assert sim.drive(1)['velocity_rpm'] > 50.0 and sim.drive(0)['velocity_rpm'] == 0.0


def test_a_station_alias_nobody_has_is_named(start_segment, make_wheel):
    import dataclasses
    start_segment([IMO_HD2_EC_TX508, dataclasses.replace(IMO_HD2_EC_TX508, alias=0x0A2)])
    wheel = make_wheel('imo_hd2', unit_id=3, **{'drive.station_alias': 0x0B0})
    status = wheel.wait_status(lambda s: 'station alias 0x00B0' in s.stop_reason, 10.0,
                               'alias error')
    assert not status.online
    assert 'aliases by position: 1: 0x0000, 2: 0x00A2' in status.stop_reason


def test_no_slaves_on_the_segment_is_a_clear_error(make_wheel):
    wheel = make_wheel('imo_hd2')                     # the veth exists, nothing answers on it
    status = wheel.wait_status(lambda s: 'no EtherCAT slave answered' in s.stop_reason, 15.0,
                               'no slaves')
    assert not status.online


def test_parameters_refused_as_commissioned_are_the_ones_this_transport_writes():
    """Over EtherCAT the node writes the profile's EtherCAT start-up list, not Modbus's."""
    from vfd_ros2.control.factory import build_controller
    from vfd_ros2.errors import ParameterError
    ec = build_controller({'drive.profile': 'imo_hd2', 'transport.type': 'ethercat',
                           'transport.interface': 'eth9'})
    with pytest.raises(ParameterError, match='P00.02 .* set to 3 at every connect'):
        ec.check_parameter_write('P00.02', 0)
    ec.check_parameter_write('P00.06', 8)       # Modbus's frequency channel: not written here
    tcp = build_controller({'drive.profile': 'imo_hd2', 'transport.type': 'modbus_tcp'})
    with pytest.raises(ParameterError, match='P00.06 .* set to 8 at every connect'):
        tcp.check_parameter_write('P00.06', 0)
    # the reaction to a comm timeout: 1 would keep the drive running when the host dies
    with pytest.raises(ParameterError, match='P14.05 .* set to 0 at every connect'):
        tcp.check_parameter_write('P14.05', 1)


def test_missed_cycles_warn_while_they_go_missing_not_for_good(monkeypatch):
    """One missed process-data cycle kept every drive's diagnostics at WARN for the run."""
    import types

    from vfd_ros2.transports import ethercat
    now, missed = [100.0], [0]
    monkeypatch.setattr(ethercat.time, 'monotonic', lambda: now[0])
    transport = ethercat.EthercatTransport(ethercat.SegmentSettings('eth9'))
    transport._segment = types.SimpleNamespace(     # noqa: SLF001 - the counters only
        counts=lambda: types.SimpleNamespace(missed_cycles=missed[0], cycles=5000))
    assert transport.link_notes == ()
    missed[0] = 3
    assert transport.link_notes == ('3 missed process-data cycles of 5000 (2 ms), the last '
                                    '0 s ago',)
    now[0] += ethercat.MISSED_CYCLES_RECENT - 1
    assert transport.link_notes and 'the last 9 s ago' in transport.link_notes[0]
    now[0] += 2
    assert transport.link_notes == ()                # none for 11 s: no warning
    missed[0] = 4
    assert transport.link_notes[0].startswith('4 missed')
    error = ethercat.AlStateError(2, ALState.OP, 0x00, 0x0000)
    assert str(error) == 'slave 3 did not reach OP: it does not answer'


def test_each_cycle_reads_the_counters_not_the_sorted_jitter():
    """Each drive's read takes the counters alone.

    read_inputs took stats(), which sorts up to 100 000 jitter samples, for every
    drive and cycle: a bus_node on EtherCAT went from 20 % to 83 % of a core in 35 s.
    """
    import types

    from vfd_ros2.transports import ethercat
    slave = types.SimpleNamespace(lost=False, state=ALState.OP, al_status=int(ALState.OP),
                                  al_status_code=0, inputs_time=time.monotonic(),
                                  inputs=lambda: b'\x27\x06')

    def sorting_stats() -> None:
        raise AssertionError('stats() called from the cycle')
    transport = ethercat.EthercatTransport(ethercat.SegmentSettings('eth9'))
    transport._segment = types.SimpleNamespace(     # noqa: SLF001
        slaves=[slave], slave=lambda index: slave, stats=sorting_stats,
        counts=lambda: ethercat.CycleCounts(1000, 0, 2, 1))
    assert transport.read_inputs(1) == b'\x27\x06'
    assert (transport.stats.transactions, transport.stats.bad_frames) == (1000, 2)
    assert transport.link_notes == ()
