"""Issue 9: a hostile but realistic plant against the node and the bus, over real frames.

Late replies, wrong echoes, refused registers, buses whose cycle is longer than a
drive's own comm-loss timeout, parameter services fed values that must not reach
the loop, and bursts of service calls.
"""

from __future__ import annotations

import math
import threading
import time
from contextlib import contextmanager

import pytest
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from rclpy.qos import QoSProfile
from std_srvs.srv import Trigger

from harness import wait_for
from unit_support import shipped_profile
from vfd_ros2.control.bus import Bus, parse_bus_config
from vfd_ros2.control.controller import STATUS_NOT_READ
from vfd_ros2.control.factory import build_controller
from vfd_ros2.control.state import RunState
from vfd_ros2.drives import modbus as modbus_drive
from vfd_ros2.drives.base import HOST_LOSS_JITTER, size_comm_timeout
from vfd_ros2.errors import CommTimeout, ParameterError
from vfd_ros2.msg import DriveStatus
from vfd_ros2.protocol.rtu_timing import character_time, frame_gap, transaction_time
from vfd_ros2.sim.model import SimulatedDrive
from vfd_ros2.sim.rtu_line import LineFaults, SimulatedRtuLine
from vfd_ros2.srv import GetDriveParameter, SetDriveParameter
from vfd_ros2.transports.modbus import ModbusRtuTransport

# --- 1. late replies never become phantom values or faults ----------------------------


def test_late_replies_never_raise_a_phantom_fault(make_harness):
    """10 % of replies come just after the timeout; the drive never has a fault."""
    faults = LineFaults(late_rate=0.1, late_delay=(0.035, 0.055))
    h = make_harness(node_parameters={'auto_enable': True, 'transport.timeout': 0.03},
                     line_faults=faults)
    h.stream(1.0)
    start = h.line.stats.frames
    wait_for(lambda: h.line.stats.frames - start > 400, 30.0, '400 transactions')
    assert h.line.stats.late_replies > 20
    assert h.sim.fault_code == 0
    assert not any(f.active for f in h.faults), [f.display for f in h.faults]
    assert not any(s.fault or s.dc_bus_voltage not in (540.0,) and
                   not math.isnan(s.dc_bus_voltage) for s in h.statuses)
    assert h.status.late_replies > 0


# --- 2. the drive's own comm-loss timeout fits the bus ------------------------------------


def test_comm_timeout_is_rounded_raised_and_clamped_with_a_reason():
    am = shipped_profile('boneng_am').parameter('C02.04')         # 0.0-60.0 s, 0.1 s steps
    assert size_comm_timeout(am, 0.3, 0.2) == (0.3, '')
    value, note = size_comm_timeout(am, 0.25, 0.2)
    assert value == pytest.approx(0.2) and 'not a multiple of 0.1 s' in note
    value, note = size_comm_timeout(am, 0.05, 0.0)
    assert value == pytest.approx(0.1) and 'no less than 0.1 s' in note
    value, note = size_comm_timeout(am, 100.0, 0.2)
    assert value == pytest.approx(60.0) and 'at most 60 s' in note
    value, note = size_comm_timeout(am, 0.3, 1.234)
    assert value == pytest.approx(1.3) and 'raised from 0.3 s' in note
    assert size_comm_timeout(am, 0.0, 1.0) == (0.0, 'off, as drive_comm_timeout 0 asks')
    with pytest.raises(ParameterError, match='at most 60 s: use a higher baud rate'):
        size_comm_timeout(am, 0.3, 61.0)
    veichi = shipped_profile('veichi_ehs100').parameter('FB.06')  # 0.1-100.0 s, no off value
    value, note = size_comm_timeout(veichi, 0.0, 0.5)
    assert value == pytest.approx(100.0) and 'no off value' in note


def am_bus(port: str, drives: int, baudrate: int, **drive_settings) -> Bus:
    return Bus(parse_bus_config({
        'bus': {'transport.type': 'modbus_rtu', 'transport.port': port,
                'transport.baudrate': baudrate, 'transport.timeout': 0.1},
        'drives': {f'd{unit}': {'drive.profile': 'boneng_am', 'transport.unit_id': unit,
                                'drive_comm_timeout': 0.3, **drive_settings}
                   for unit in range(1, drives + 1)}}))


@pytest.mark.parametrize('drives, baudrate', [(4, 9600), (16, 115200), (32, 115200)])
def test_bus_plan_raises_the_timeout_above_twice_the_worst_interval(drives, baudrate):
    bus = am_bus('/dev/null', drives, baudrate)
    char = character_time(baudrate)
    # The line's own floor: every drive's setpoint write and status reads, back to back.
    floor = sum(transaction_time(8, 8, char, frame_gap(baudrate, char)) +
                sum(transaction_time(8, 5 + 2 * block.count, char, frame_gap(baudrate, char))
                    for block in controller.drive.blocks)
                for controller in bus.controllers.values())
    assert bus.addressing_interval > floor
    for controller in bus.controllers.values():
        protection = controller.protection
        assert protection.active and protection.requested == 0.3
        assert protection.timeout >= 2 * bus.addressing_interval + HOST_LOSS_JITTER - 1e-9
        assert protection.timeout == pytest.approx(round(protection.timeout, 1))
        assert 'raised from 0.3 s' in protection.note and protection.weaker_than_requested


def test_a_single_fast_drive_keeps_the_timeout_it_asked_for():
    bus = am_bus('/dev/null', 1, 115200)
    protection = next(iter(bus.controllers.values())).protection
    assert protection.timeout == pytest.approx(0.3) and protection.note == ''


class CommandStream:
    """A planner in a thread: every controller gets ``velocity`` each ``period`` until stop()."""

    def __init__(self, controllers, velocity: float, period: float) -> None:
        self._running = threading.Event()
        self._running.set()

        def feed():
            while self._running.is_set():
                for controller in controllers:
                    controller.command_velocity(velocity)
                time.sleep(period)
        threading.Thread(target=feed, daemon=True).start()

    def stop(self) -> None:
        self._running.clear()


def test_four_drives_at_9600_run_without_tripping_their_own_timeout(tmp_path):
    """The issue's case: a ~0.6 s bus cycle and C02.04 = 0.3 s faulted every drive."""
    with four_am_drives_running(tmp_path, 9600, 0.5, 2.0, emulate_wire_time=True) as (sims, bus):
        written = sims[0].value('C02.04')
        assert written >= 2 * bus.addressing_interval
        deadline = time.monotonic() + 3 * written
        while time.monotonic() < deadline:
            assert all(s.fault_code == 0 for s in sims), [s.fault_code for s in sims]
            time.sleep(0.05)
        assert all(c.state.online and not c.state.fault for c in bus.controllers.values())


@contextmanager
def four_am_drives_running(tmp_path, baudrate: int, acceleration_time: float,
                           velocity: float, **line_options):
    """Four BONENG AM drives on one simulated line, a bus commanding all four to run."""
    profile = shipped_profile('boneng_am')
    sims = [SimulatedDrive(profile, unit, {'acceleration_time': acceleration_time})
            for unit in range(1, 5)]
    port = str(tmp_path / 'line')
    line = SimulatedRtuLine(sims, port, baudrate=baudrate, **line_options).start()
    bus = am_bus(port, 4, baudrate, auto_enable=True)
    commands = CommandStream(list(bus.controllers.values()), velocity, 0.05)
    bus.start()
    try:
        wait_for(lambda: all(s.run_requested for s in sims), 15.0, 'all four running')
        yield sims, bus
    finally:
        commands.stop()
        bus.shutdown()
        line.stop()


def test_a_garbled_line_never_lets_the_drive_time_out(tmp_path):
    """Going offline on garbage must not let the drive's own timer expire (keep-alive)."""
    profile = shipped_profile('boneng_am')
    sim = SimulatedDrive(profile, 1, {'acceleration_time': 0.5})
    port = str(tmp_path / 'line')
    line = SimulatedRtuLine([sim], port, seed=4).start()
    controller = build_controller({'transport.port': port, 'auto_enable': True,
                                   'drive_comm_timeout': 0.3, 'reconnect_period': 0.5})
    commands = CommandStream([controller], 1.0, 0.05)
    controller.start()
    try:
        wait_for(lambda: sim.run_requested, 5.0, 'running')
        line.corrupt_rate = 0.2
        deadline = time.monotonic() + 5.0
        while time.monotonic() < deadline:
            assert sim.fault_code == 0, 'the drive tripped its own comm-loss timeout'
            time.sleep(0.02)
        line.corrupt_rate = 0.0
        wait_for(lambda: controller.state.running, 5.0, 'running after the garbage')
        assert controller.loop_errors == 0
    finally:
        commands.stop()
        controller.shutdown()
        line.stop()


def test_planned_timeout_is_written_and_reported(make_harness):
    h = make_harness(node_parameters={'drive_comm_timeout': 0.25})
    status = h.wait_status(lambda s: s.host_loss_timeout > 0, 3.0, 'protection reported')
    assert status.host_loss_timeout == pytest.approx(0.2)
    assert h.sim.value('C02.04') == pytest.approx(0.2)
    assert 'C02.04' in status.host_loss_protection
    assert 'not a multiple of 0.1 s' in status.host_loss_protection


def test_a_bus_that_cannot_be_protected_refuses_to_start():
    with pytest.raises(ParameterError, match='allows at most'):
        Bus(parse_bus_config({
            'bus': {'transport.type': 'modbus_rtu', 'transport.port': '/dev/null',
                    'transport.baudrate': 1200, 'transport.timeout': 0.5},
            'drives': {f'd{unit}': {'drive.profile': 'boneng_am', 'transport.unit_id': unit}
                       for unit in range(1, 33)}}))


# --- 3. nothing moves the motor around the driver ------------------------------------------


@pytest.mark.parametrize('code, value, hint', [
    ('P07.32', 1.0, '~/enable'),                 # the command word: "run"
    ('P07.33', 50.0, '~/velocity_command'),      # the speed setpoint
    ('C02.04', 0.0, 'drive_comm_timeout'),       # the comm-loss timeout the driver manages
    ('P07.34', 50.0, 'second setpoint channel'),  # from the profile's control_owned
    ('B01.03', 0.0, 'apply_commissioning'),      # a commissioning value, rewritten at connect
    ('B02.02', 1.0, 'a way to move the motor'),  # the profile's motion_channels: adds B03.16
])
def test_control_owned_registers_are_refused(make_harness, code, value, hint):
    h = make_harness()
    before = dict(h.sim.words)
    reply = h.call(SetDriveParameter, 'set_drive_parameter',
                   SetDriveParameter.Request(name=code, value=value, persistent=False))
    assert not reply.success and hint in reply.message, reply.message
    h.wait_cycles(5)
    assert not h.sim.run_requested
    assert {a: v for a, v in h.sim.words.items() if a == h.profile.parameter(code).address} \
        == {a: v for a, v in before.items() if a == h.profile.parameter(code).address}
    got = h.call(GetDriveParameter, 'get_drive_parameter', GetDriveParameter.Request(name=code))
    assert got.success and not got.writable


@pytest.mark.parametrize('profile_name, transport', [
    ('boneng_am', 'modbus_rtu'), ('boneng_mh', 'modbus_rtu'), ('veichi_ehs100', 'modbus_rtu'),
    ('kinco_ec', 'canopen'), ('imo_hd2', 'modbus_tcp')])
def test_motion_channels_are_refused_by_the_node_and_left_to_commissioning(profile_name,
                                                                           transport):
    """A second setpoint source, a jog input, an automatic restart: not through a node."""
    from vfd_ros2.control.factory import build_controller
    # (with apply_commissioning, a channel the commissioning closes is refused as such)
    settings = {'drive.profile': profile_name, 'transport.type': transport,
                'apply_commissioning': False}
    if transport == 'modbus_rtu':
        settings['transport.port'] = '/dev/null'
    controller = build_controller(settings)
    channels = controller.drive.profile.motion_channels
    assert len(channels) >= 2
    for code, why in channels.items():
        parameter = controller.drive.profile.parameter(code)
        value = parameter.default if parameter.default is not None else 0.0
        with pytest.raises(ParameterError, match='a way to move the motor') as refused:
            controller.check_parameter_write(code, value)
        assert why in str(refused.value)
        assert not controller.parameter_writable(code)
        controller.drive.check_write(code, value, running=False)     # vfd_params may
    # Nor the set-up for bus control an integrator manages (apply_commissioning false):
    # another value gives the motor to the terminals (MH B00.06: a DI reverses it).
    for item in controller.drive.profile.commissioning:
        with pytest.raises(ParameterError, match=r'left to you \(apply_commissioning false\)'):
            controller.check_parameter_write(item.code, item.value)


def test_no_run_before_the_first_status_read_after_connect(tmp_path):
    """Connected, but the status reads fail: nothing known, so idle and not "fault-free".

    (Before, the empty reading of a fresh connect let the next cycle write run to a
    drive whose fault state nobody had read yet, e.g. its own comm-loss fault.)
    """
    profile = shipped_profile('boneng_am')
    sim = SimulatedDrive(profile, 1, {'acceleration_time': 0.5})
    port = str(tmp_path / 'line')
    line = SimulatedRtuLine([sim], port).start()
    controller = build_controller({'transport.port': port, 'auto_enable': True,
                                   'comm_loss_threshold': 12})
    real_poll, failing = controller.drive.poll, [8]
    seen: list[tuple[bool, object]] = []

    def poll(*args, **kwargs):
        # what the drive was told before each status read (the loop thread: no race)
        seen.append((sim.run_requested, controller.state))
        if failing[0]:          # the status reads of the first cycles get no reply
            failing[0] -= 1
            raise CommTimeout('no reply (test: status reads lost)')
        return real_poll(*args, **kwargs)
    controller.drive.poll = poll
    commands = CommandStream([controller], 1.0, 0.005)
    controller.start()
    try:
        wait_for(lambda: sim.run_requested, 5.0, 'running once the status is read')
        # 8 lost reads, then the first that succeeds: run was written before none of them
        assert not any(run for run, _ in seen[:9]), 'run written before any status was read'
        for _, state in seen[1:9]:
            assert state.online and state.run_state is RunState.BLOCKED
            assert state.stop_reason == STATUS_NOT_READ
    finally:
        commands.stop()
        controller.shutdown()
        line.stop()


def test_a_start_from_elsewhere_is_stopped_and_counted(make_harness):
    h = make_harness()                                        # disabled: must not run
    command = h.profile.parameter('P07.32').address
    h.sim.write(command, [0])
    h.sim.write(command, [1])                                 # e.g. another master or a keypad
    wait_for(lambda: h.sim.run_requested or h.sim.output_active, 2.0, 'started from outside')
    status = h.wait_status(lambda s: s.unexpected_starts >= 1, 3.0, 'unexpected start seen')
    wait_for(lambda: not h.sim.run_requested, 2.0, 'stop written again')
    wait_for(lambda: h.sim.speed_rpm == 0.0, 5.0, 'motor stopped')
    assert status.state == 'disabled'
    reply = h.trigger('stop')
    assert reply.success, reply.message


def test_a_drive_that_runs_on_when_held_idle_is_an_error_not_a_quiet_watchdog(make_harness):
    """Commands stop; the drive acknowledges every stop and runs on (a local run source).

    The status said "watchdog" with OK diagnostics for as long as it ran, nothing
    logged or counted. After stop_timeout: ERROR on /diagnostics, the reason in
    ~/status, counted once; cleared when it does stop.
    """
    h = make_harness(node_parameters={'auto_enable': True, 'stop_timeout': 1.0})
    command = h.profile.parameter('P07.32').address
    h.stream(1.0)
    h.wait_status(lambda s: s.running and abs(s.measured_velocity - 1.0) < 0.05, 6.0,
                  'running')
    real_write, stuck = h.sim.write, [True]

    def ignoring_stops(address: int, values: list[int]) -> None:
        if stuck[0] and address == command and values[0] != 1:
            return                      # acknowledged, not applied
        real_write(address, values)
    h.sim.write = ignoring_stops
    h.stop_stream()
    status = h.wait_status(lambda s: s.state == 'watchdog', 2.0, 'watchdog trips')
    assert status.running and not status.unexpected_starts
    status = h.wait_status(lambda s: 'stop_timeout' in s.stop_reason, 4.0, 'reported')
    assert status.state == 'watchdog' and status.unexpected_starts == 1, status
    entry = h.node.diagnostic_status()
    assert entry.level == DiagnosticStatus.ERROR and 'stop_timeout' in entry.message, entry
    stuck[0] = False                    # it obeys again
    h.wait_status(lambda s: not s.running and 'stop_timeout' not in s.stop_reason, 8.0,
                  'stopped, the report cleared')
    assert h.status.unexpected_starts == 1
    assert h.node.diagnostic_status().level != DiagnosticStatus.ERROR


def test_slow_replies_raise_the_drives_comm_loss_timeout_before_it_trips(tmp_path):
    """Four drives on one line start answering every request 60 ms late (legal: timeout 0.1 s).

    The comm-loss timeout was sized from the wire time of a cycle (0.8 s here); the
    real cycle became ~1.2 s, and a drive waited out the others' slow exchanges past
    its timeout: E35.03 with the host there. The bus raises each drive's timeout before
    it is reached, mid-cycle, and writes it; nothing trips.
    """
    with four_am_drives_running(tmp_path, 115200, 0.3, 1.0) as (sims, bus):
        planned = sims[0].value('C02.04')
        assert [s.value('C02.04') for s in sims] == [planned] * 4
        for sim in sims:
            real_read, real_write = sim.read, sim.write

            def slow_read(address, count, read=real_read):
                time.sleep(0.06)
                return read(address, count)

            def slow_write(address, values, write=real_write):
                time.sleep(0.06)
                return write(address, values)
            sim.read, sim.write = slow_read, slow_write
        wait_for(lambda: all(s.value('C02.04') > planned for s in sims), 5.0, 'all raised')
        deadline = time.monotonic() + 4.0
        while time.monotonic() < deadline:
            assert all(s.fault_code == 0 for s in sims), [s.fault_code for s in sims]
            time.sleep(0.05)
        for controller, sim in zip(bus.controllers.values(), sims):
            state = controller.state
            assert state.online and not state.fault and state.reconnects == 0
            assert state.protection.timeout == pytest.approx(sim.value('C02.04'))
            assert 'passed between two polls (slow replies' in state.protection.describe()


def test_a_drive_node_whose_loop_runs_short_of_control_rate_warns(make_harness):
    """A control_rate the link cannot sustain (a drive answering 30 ms late, 50 Hz asked).

    The drive's entry said OK; now it shows its cycles/s and warns while the loop runs
    below 90 % of control_rate. With replies on time, the same node is OK.
    """
    import time as clock
    h = make_harness(node_parameters={'control_rate': 50.0})
    name = h.node.diagnostic_status().name
    entries: list[DiagnosticStatus] = []
    h.tester.create_subscription(DiagnosticArray, '/diagnostics', lambda array: entries.extend(
        s for s in array.status if s.name == name), 50)

    def rate_of(entry: DiagnosticStatus) -> float:
        return float({kv.key: kv.value for kv in entry.values}.get('cycles/s', 'nan'))
    wait_for(lambda: entries and rate_of(entries[-1]) > 40, 5.0, 'cycles/s shown')
    clock.sleep(1.5)                    # two windows of 0.5 s and more
    assert entries[-1].level == DiagnosticStatus.OK, entries[-1].message
    real_read = h.sim.read

    def slow_read(address: int, count: int) -> list[int]:
        clock.sleep(0.03)
        return real_read(address, count)
    h.sim.read = slow_read
    wait_for(lambda: entries[-1].level == DiagnosticStatus.WARN and
             'cycles/s of control_rate 50 Hz' in entries[-1].message, 6.0,
             'the shortfall warned')
    assert 0 < rate_of(entries[-1]) < 45, entries[-1]


# --- 4. degrade, don't drop ------------------------------------------------------------


def test_a_refused_commissioning_read_keeps_the_drive_online(make_harness):
    """A strict MH without C02.06: reported, and the drive is controlled anyway."""
    h = make_harness(profile='boneng_mh', refused=('C02.06',),
                     node_parameters={'auto_enable': True})
    status = h.wait_status(lambda s: s.unavailable, 3.0, 'refusal reported')
    assert any('C02.06' in item for item in status.unavailable)
    h.stream(1.0)
    h.wait_status(lambda s: s.running and abs(s.measured_velocity - 1.0) < 0.05, 6.0,
                  'controlled anyway')
    assert h.status.reconnects == 0


def test_a_refused_monitor_value_is_unavailable_not_offline(make_harness, ros_context):
    """The Kinco without D0.23 (heatsink temperature): NaN, a WARN, control goes on."""
    h = make_harness(profile='kinco_ec', refused=('D0.23',),
                     node_parameters={'auto_enable': True})
    diagnostics: list[DiagnosticArray] = []
    h.tester.create_subscription(DiagnosticArray, '/diagnostics', diagnostics.append, 10)
    h.stream(1.0)
    status = h.wait_status(lambda s: s.running and any('D0.23' in u for u in s.unavailable),
                           8.0, 'running with the temperature unavailable')
    assert math.isnan(status.temperature)
    h.wait_cycles(100)                      # more than one pass of every polled value
    assert h.status.online and h.status.reconnects == 0
    wait_for(lambda: any(st.level == DiagnosticStatus.WARN and 'D0.23' in st.message
                         for d in diagnostics for st in d.status
                         if st.hardware_id == status.hardware_id), 5.0, 'diagnostics WARN')


def test_an_unreadable_fault_register_blocks_motion(make_harness):
    h = make_harness(refused=('A01.00',), node_parameters={'auto_enable': True})
    h.stream(1.0)
    status = h.wait_status(lambda s: s.state == 'blocked', 5.0, 'blocked')
    assert 'A01.00' in status.stop_reason and status.online
    h.wait_cycles(20)
    assert not h.sim.run_requested
    reply = h.trigger('enable')
    assert not reply.success and 'A01.00' in reply.message


def test_a_refusal_that_passes_stops_blocking_the_drive(make_harness, monkeypatch):
    """Exception replies to the fault register for a while (a frame error, a device failure).

    It was refused until the next connect: the drive stood blocked, ~/enable refused,
    while every reply was good again. It is asked again, alone, every REFUSAL_RETRY,
    shown refused meanwhile (never as a value, never flickering in ~/status).
    """
    monkeypatch.setattr(modbus_drive, 'REFUSAL_RETRY', 0.5)
    h = make_harness(refused=('A01.00',), node_parameters={'auto_enable': True})
    h.stream(1.0)
    h.wait_status(lambda s: s.state == 'blocked', 5.0, 'blocked')
    first, exceptions = len(h.statuses), h.status.exceptions
    wait_for(lambda: h.status.exceptions >= exceptions + 3, 5.0, 'three retries refused')
    assert all(any('A01.00' in u for u in s.unavailable) for s in h.statuses[first:])
    assert not h.sim.run_requested
    h.sim.refuse([])                # it passed
    h.wait_status(lambda s: s.running and not s.unavailable, 5.0, 'running again')
    assert h.status.reconnects == 0


# --- 5. bad values never reach the control loop ------------------------------------------


@pytest.mark.parametrize('value, why', [(1e308, 'above the maximum'), (-1e308, 'below'),
                                        (math.inf, 'not a finite number'),
                                        (math.nan, 'not a finite number')])
def test_huge_values_are_refused_before_the_loop(make_harness, value, why):
    h = make_harness()
    reply = h.call(SetDriveParameter, 'set_drive_parameter',
                   SetDriveParameter.Request(name='B04.02', value=value, persistent=False))
    assert not reply.success and why in reply.message, reply.message
    assert h.node.controller.loop_errors == 0


def test_every_register_of_every_parameter_fed_extreme_values(make_harness):
    """set_drive_parameter on every parameter with extremes: answers, never a crash."""
    h = make_harness()
    for parameter in list(h.profile.parameters.values())[::7]:
        for value in (1e308, -1e308, 0.5e-300):
            reply = h.call(SetDriveParameter, 'set_drive_parameter',
                           SetDriveParameter.Request(name=parameter.code, value=value),
                           timeout=5.0)
            assert reply.message, parameter.code
    assert not h.sim.run_requested
    assert h.node.controller.loop_errors == 0
    assert h.status.online


# --- 6. counters an operator can trust -----------------------------------------------


def test_wire_seconds_uses_the_spec_gap_at_every_baud_rate():
    for baud in (9600, 19200, 38400, 115200):
        transport = ModbusRtuTransport('/dev/null', baud)
        char = character_time(baud)
        # A 5-register read: request 8, reply 15 bytes, two frames, two t3.5.
        assert transport.wire_seconds(23, 2) == pytest.approx(
            transaction_time(8, 15, char, frame_gap(baud, char)))
    fast = ModbusRtuTransport('/dev/null', 115200)
    assert fast.wire_seconds(0, 2) == pytest.approx(2 * 0.00175)   # not 2 x 3.5 characters


# --- 8. data and small things ---------------------------------------------------------


@pytest.mark.parametrize('profile', ['boneng_am', 'boneng_mh'])
def test_enable_succeeds_on_an_idle_drive_without_commands(make_harness, profile):
    h = make_harness(profile=profile)
    reply = h.trigger('enable')
    assert reply.success, reply.message
    assert 'runs as soon as velocity commands arrive' in reply.message


def test_a_burst_of_service_calls_is_answered_every_time(make_harness):
    h = make_harness()
    # Each client has 12-13 calls outstanding, answered together (duplicates share one
    # action): its response queue must hold them all, or DDS drops the oldest (the
    # default KEEP_LAST 10 lost up to 6 answers on a loaded machine).
    clients = [h.tester.create_client(Trigger, 'drive/enable',
                                      qos_profile=QoSProfile(depth=256)) for _ in range(16)]
    assert all(c.wait_for_service(timeout_sec=5.0) for c in clients)
    futures = [clients[i % 16].call_async(Trigger.Request()) for i in range(200)]
    wait_for(lambda: all(f.done() for f in futures), 30.0, '200 answers')
    assert all(f.result().success for f in futures)


def test_user_input_is_capped_in_replies(make_harness):
    h = make_harness()
    name = 'x' * 10_000
    reply = h.call(GetDriveParameter, 'get_drive_parameter', GetDriveParameter.Request(
        name=name))
    assert not reply.success and 'unknown parameter' in reply.message
    assert len(reply.message) < 400 and '10002 characters' in reply.message
    reply = h.call(SetDriveParameter, 'set_drive_parameter', SetDriveParameter.Request(
        name=name, value=1.0))
    assert not reply.success and len(reply.message) < 400


def test_per_drive_counters_on_a_shared_line(tmp_path):
    """The unplugged right drive's timeouts are its own, not the left drive's."""
    profile = shipped_profile('boneng_am')
    sims = [SimulatedDrive(profile, unit) for unit in (1, 2)]
    port = str(tmp_path / 'line')
    line = SimulatedRtuLine(sims, port).start()
    bus = am_bus(port, 2, 115200, drive_comm_timeout=0.7)
    bus.start()
    left, right = bus.controllers.values()
    try:
        wait_for(lambda: left.state.online and right.state.online, 5.0, 'both online')
        sims[1].silent = True
        wait_for(lambda: right.state.timeouts >= 5, 10.0, 'right times out')
        assert left.state.timeouts == 0 and left.state.online
        assert bus.link_stats().timeouts >= right.state.timeouts
    finally:
        bus.shutdown()
        line.stop()


def test_status_counts_are_this_drives_own(make_harness):
    h = make_harness()
    status = h.wait_status(lambda s: s.transactions > 10, 3.0, 'some transactions')
    assert isinstance(status, DriveStatus)
    assert status.transactions <= h.line.stats.frames
