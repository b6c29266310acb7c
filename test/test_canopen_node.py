"""Drive node <-> simulated CANopen drives over python-can's virtual bus (real frames)."""

from __future__ import annotations

import dataclasses
import logging
import math
import time

import can
import pytest
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from rclpy.parameter import Parameter

from can_harness import can_harness_factory  # noqa: F401 - the make_can_harness fixture
from harness import diagnostic_levels_until_at, wait_for
from vfd_ros2.profiles import load_profile
from vfd_ros2.protocol.cia402 import State
from vfd_ros2.protocol.repeats import RepeatSummary
from vfd_ros2.sim.canopen_drive import HEARTBEAT_EVENT, SimulatedCanopenDrive
from vfd_ros2.srv import GetDriveParameter, SetDriveParameter
from vfd_ros2.transports.canopen import open_channels


def test_command_status_and_watchdog(make_can_harness):
    h = make_can_harness(node_parameters={'auto_enable': True})
    wheel, sim = h.wheels[1], h.sims[1]
    assert sim.state is not State.OPERATION_ENABLED and sim.speed_rpm == 0.0  # start-up: still
    wheel.stream(1.0)
    status = wheel.wait_status(lambda s: s.running and abs(s.measured_velocity - 1.0) < 0.02,
                               6.0, 'at 1 rad/s')
    assert status.online and not status.fault and status.commanded_velocity == 1.0
    assert sim.state is State.OPERATION_ENABLED and sim.speed_rpm > 0
    assert sim.rpdos_received > 10                      # cyclic control over PDOs
    wheel.stream(-1.0)
    wheel.wait_status(lambda s: abs(s.measured_velocity + 1.0) < 0.02 and s.reverse, 6.0,
                      'at -1 rad/s')
    wheel.stop_stream()
    wheel.wait_status(lambda s: s.watchdog_tripped, 2.0, 'watchdog')
    wait_for(lambda: sim.speed_rpm == 0.0 and sim.state is State.SWITCHED_ON, 5.0,
             'motor stopped, operation disabled')
    reply = wheel.trigger('disable')
    assert reply.success, reply.message
    wait_for(lambda: sim.state is State.SWITCH_ON_DISABLED, 2.0, 'voltage disabled')


def test_fault_emcy_and_reset(make_can_harness):
    h = make_can_harness()
    wheel, sim = h.wheels[1], h.sims[1]
    entry = h.profile.faults.table[0x2310]
    sim.inject_fault(0x2310, latched=True)
    fault = wait_for(lambda: next((f for f in reversed(wheel.faults) if f.active), None), 3.0,
                     'fault message')
    assert fault.code == 0x2310 and fault.name == entry.name and fault.known
    assert fault.remedy == entry.remedy and fault.display == '0x2310'
    assert not wheel.trigger('reset_fault').success          # cause still present
    sim.inject_fault(0)
    reply = wheel.trigger('reset_fault')
    assert reply.success, reply.message
    wheel.wait_status(lambda s: not s.fault, 3.0, 'fault cleared')
    assert sim.emcy_sent[-1][0] == 0                        # EMCY "error reset"
    sim.inject_fault(0x1234)                                # not in the profile's table
    fault = wait_for(lambda: next((f for f in reversed(wheel.faults)
                                   if f.active and f.code == 0x1234), None), 3.0, 'unknown')
    assert not fault.known and 'unknown' in fault.name
    assert wheel.status.online


def test_an_emcy_the_drive_does_not_fault_on_is_the_warning_until_its_error_reset(
        make_can_harness):
    """A temperature EMCY without a fault was only a log line (outside audit)."""
    h = make_can_harness()
    wheel, sim = h.wheels[1], h.sims[1]
    wheel.wait_status(lambda s: s.online and not s.warning, 5.0, 'online, no warning')
    sim.send_emcy(0x4310, 0x09)                    # excess temperature, drive (CiA 301)
    status = wheel.wait_status(lambda s: s.warning, 3.0, 'the warning in ~/status')
    assert status.warning_code == 0x4310 and not status.fault, status
    sim.send_emcy(0)                                # error reset
    wheel.wait_status(lambda s: not s.warning and s.warning_code == 0, 3.0, 'warning cleared')


def test_parameters_and_abort_codes(make_can_harness):
    h = make_can_harness()
    wheel, sim = h.wheels[1], h.sims[1]
    reply = wheel.call(SetDriveParameter, 'set_drive_parameter',
                       SetDriveParameter.Request(name='profile_acceleration', value=1500.0,
                                                 persistent=False))
    assert reply.success, reply.message
    assert sim.value('0x6083') == 1500.0
    got = wheel.call(GetDriveParameter, 'get_drive_parameter',
                     GetDriveParameter.Request(name='0x6083'))
    assert got.success and got.value == 1500.0
    for name, bad, why in (('0x6083', 2e6, 'above the maximum'),
                           ('0x6083', math.nan, 'not a finite number'),
                           ('statusword', 0.0, 'read-only'),
                           ('quick_stop_option_code', 3.0, 'not one of the options'),
                           ('operating_mode', 1.0, 'not written through parameters'),
                           ('controlword', 15.0, 'not written through parameters'),
                           ('no_such_parameter', 1.0, 'unknown parameter')):
        reply = wheel.call(SetDriveParameter, 'set_drive_parameter',
                           SetDriveParameter.Request(name=name, value=bad, persistent=False))
        assert not reply.success and why in reply.message, (name, reply.message)
    assert sim.value('0x6083') == 1500.0
    # The drive's own range (0x6080 max motor speed): the twin limits it to 0..100000 too;
    # a value the driver accepts but the drive refuses comes back as an SDO abort text.
    sim.parameters[(0x6080, 0)] = dataclasses.replace(sim.parameters[(0x6080, 0)],
                                                      maximum=5000)
    reply = wheel.call(SetDriveParameter, 'set_drive_parameter',
                       SetDriveParameter.Request(name='max_motor_speed', value=6000.0,
                                                 persistent=False))
    assert not reply.success
    assert 'SDO abort 0x06090031 (Value of parameter written too high' in reply.message


def test_heartbeat_loss_and_recovery(make_can_harness):
    h = make_can_harness(node_parameters={'auto_enable': True})
    wheel, sim = h.wheels[1], h.sims[1]
    wheel.stream(1.0)
    wheel.wait_status(lambda s: s.running, 6.0, 'running')
    sim.silent = True                                       # cable unplugged
    status = wheel.wait_status(lambda s: not s.online, 3.0, 'offline')
    assert 'heartbeat' in status.stop_reason or status.timeouts > 0, status.stop_reason
    # The drive hears neither the host heartbeat (0x1016:01) nor RPDOs (0x1400:05, both =
    # drive_comm_timeout): whichever expires first, it stops the motor by itself.
    wait_for(lambda: sim.fault_code in (0x8130, 0x8250) and sim.speed_rpm == 0.0, 3.0,
             'heartbeat event or RPDO timeout')
    code = sim.fault_code
    sim.silent = False
    status = wheel.wait_status(lambda s: s.online, 6.0, 'back online (same node process)')
    assert status.reconnects >= 1
    wheel.wait_status(lambda s: s.fault and s.fault_code == code, 3.0, "the drive's fault")
    # ~/fault follows ~/status from the same callback: it may arrive a moment later
    wait_for(lambda: wheel.faults and wheel.faults[-1].display == f'0x{code:04X}', 3.0,
             'the fault published as a CiA code')
    assert sim.state is State.FAULT                          # never resumes by itself
    assert wheel.trigger('reset_fault').success
    wheel.wait_status(lambda s: s.running and abs(s.measured_velocity - 1.0) < 0.02, 6.0,
                      'moving again')


def test_two_drives_one_bus_dead_node_does_not_stall_the_other(make_can_harness, caplog):
    caplog.set_level('WARNING')
    h = make_can_harness(node_ids=(1, 2), node_parameters={'auto_enable': True})
    left, right = h.wheels[1], h.wheels[2]
    left.stream(1.0)
    right.stream(-0.5)
    left.wait_status(lambda s: s.running and abs(s.measured_velocity - 1.0) < 0.02, 6.0, 'left')
    right.wait_status(lambda s: abs(s.measured_velocity + 0.5) < 0.02, 6.0, 'right')
    h.sims[2].silent = True
    right.wait_status(lambda s: not s.online, 3.0, 'right offline')
    count = len(left.statuses)
    left.wait_status(lambda s: s.online and s.running and len(left.statuses) > count + 25,
                     3.0, 'left keeps running with fresh status')
    left.stream(0.5)
    left.wait_status(lambda s: abs(s.measured_velocity - 0.5) < 0.02, 3.0, 'left follows')
    assert h.sims[1].fault_code == 0
    # The dead node's reconnect attempts each abort an SDO transfer: the driver reports
    # it (offline, stop_reason); the library's own line per abort is not repeated.
    assert right.wait_status(lambda s: True, 1.0, 'status').timeouts > 1
    assert not [r for r in caplog.records if r.name.startswith('canopen')], \
        [r.getMessage() for r in caplog.records if r.name.startswith('canopen')]


def test_drive_that_cannot_be_enabled_is_refused_and_not_started_later(make_can_harness):
    """An enable refused by a drive held in SWITCH_ON_DISABLED leaves it not enabled.

    Safe torque off, say: ~/enable fails, and the drive does not start by itself
    when the hold is released (it did: the node stayed enabled).
    """
    h = make_can_harness(node_parameters={'action_timeout': 1.0})
    wheel, sim = h.wheels[1], h.sims[1]
    sim.enable_blocked = True                               # e.g. safe torque off active
    wheel.stream(1.0)
    reply = wheel.trigger('enable')
    assert not reply.success and 'not enabled' in reply.message, reply.message
    status = wheel.wait_status(lambda s: not s.enabled, 1.0, 'not enabled')
    assert status.online and not status.running
    words = dict(zip(status.status_word_names, status.status_words_raw))
    assert words['cia402_state'] == State.SWITCH_ON_DISABLED
    sim.enable_blocked = False                              # the hold is released
    time.sleep(1.0)
    assert sim.state is not State.OPERATION_ENABLED and sim.speed_rpm == 0.0
    assert wheel.trigger('enable').success
    wheel.wait_status(lambda s: s.running, 5.0, 'running after a new ~/enable')


def test_an_enabled_drive_held_in_switch_on_disabled_is_reported_blocked(make_can_harness):
    h = make_can_harness(node_parameters={'action_timeout': 1.0, 'auto_enable': True})
    wheel, sim = h.wheels[1], h.sims[1]
    sim.enable_blocked = True
    wheel.stream(1.0)
    status = wheel.wait_status(lambda s: s.state == 'blocked', 3.0, 'blocked state')
    assert 'SWITCH_ON_DISABLED' in status.stop_reason or 'stays in' in status.stop_reason
    assert sim.speed_rpm == 0.0


@pytest.mark.parametrize('object_set', ['manufacturer', 'ds402'])
def test_kinco_over_canopen(make_can_harness, object_set):
    h = make_can_harness(profile='kinco_ec', object_set=object_set,
                         node_parameters={'auto_enable': True})
    wheel, sim = h.wheels[1], h.sims[1]
    assert sim.bus_control()                      # A0.04 = 2 written at connect (SDO)
    wheel.stream(1.0)
    wheel.wait_status(lambda s: s.running and abs(s.measured_velocity - 1.0) < 0.02, 6.0,
                      'kinco at 1 rad/s')
    entry = h.profile.faults.table[8]
    sim.inject_fault(8, latched=False)
    fault = wait_for(lambda: next((f for f in reversed(wheel.faults) if f.active), None), 3.0,
                     'kinco fault')
    assert fault.code == 8 and fault.name == entry.name and fault.display == 'E008'
    reply = wheel.trigger('reset_fault')
    assert reply.success, reply.message


def test_fault_follows_the_statusword_not_the_error_code(make_can_harness):
    """0x603F names the fault; the statusword says whether there is one (it may keep a code)."""
    h = make_can_harness(node_parameters={'auto_enable': True})
    wheel, sim = h.wheels[1], h.sims[1]
    sim.keeps_last_error = True                 # CiA 402 allows 0x603F to keep the last error
    wheel.stream(1.0)
    wheel.wait_status(lambda s: s.running, 6.0, 'running')
    sim.inject_fault(0x3210, latched=True)
    status = wheel.wait_status(lambda s: s.fault and s.fault_code == 0x3210, 3.0, 'fault')
    published = wait_for(lambda: wheel.faults and wheel.faults[-1].display == '0x3210' and
                         wheel.faults[-1], 3.0, 'the fault published')
    assert published.name == h.profile.faults.table[0x3210].name
    assert not wheel.trigger('reset_fault').success      # the cause is still there
    sim.inject_fault(0)
    reply = wheel.trigger('reset_fault')
    assert reply.success, reply.message                 # the state machine left FAULT ...
    got = wheel.call(GetDriveParameter, 'get_drive_parameter',
                     GetDriveParameter.Request(name='0x603F'))
    assert got.success and got.raw_value == 0x3210           # ... although 0x603F keeps its code
    status = wheel.wait_status(lambda s: s.running and not s.fault, 6.0, 'running again')
    wheel.stop_stream()                                 # watchdog: disable operation
    status = wheel.wait_status(lambda s: dict(zip(s.status_word_names, s.status_words_raw))
                               .get('cia402_state') == State.SWITCHED_ON, 3.0, 'switched on')
    words = dict(zip(status.status_word_names, status.status_words_raw))
    assert words['0x6041'] & 0x006F == 0x0023 and sim.error_code() == 0x3210
    assert not status.fault and status.fault_code == 0 and status.state != 'fault'


@pytest.mark.parametrize('profile, code, display', [('cia402_velocity', 0x2310, '0x2310'),
                                                    ('kinco_ec', 8, 'E008')])
def test_emcy_names_the_fault_when_the_code_object_is_empty(make_can_harness, profile, code,
                                                           display):
    """EMCY through the library's consumer gives the profile's fault texts."""
    h = make_can_harness(profile=profile)
    wheel, sim = h.wheels[1], h.sims[1]
    sim.report_error_code = False               # 0x603F / 0x2B09 read 0: only EMCY says which
    sim.inject_fault(code, latched=True)
    fault = wait_for(lambda: next((f for f in reversed(wheel.faults) if f.active), None), 3.0,
                     'fault from EMCY')
    entry = h.profile.faults.table[code]
    assert (fault.code, fault.display, fault.name, fault.remedy, fault.known) == \
        (code, display, entry.name, entry.remedy, True)
    sim.inject_fault(0)
    assert wheel.trigger('reset_fault').success          # EMCY 0000 (error reset) follows
    wheel.wait_status(lambda s: not s.fault, 3.0, 'cleared')


def test_a_flood_of_one_emcy_is_logged_once_and_kept_bounded(make_can_harness, caplog):
    """A node that repeats an EMCY (a warning it sends on every event, or a babbling node).

    The library appends every EMCY to its active list until an error reset: the
    driver keeps that list short, logs the EMCY once and sums up the repeats.
    """
    h = make_can_harness()
    wheel = h.wheels[1]
    wheel.wait_status(lambda s: s.online, 5.0, 'online')
    transport = wheel.node.controller.drive.transport
    wheel.node.controller.drive.emcy_log.period = 1.0    # repeats summed up 1 s on
    sender = can.Bus(interface='virtual', channel=h.channel)
    caplog.set_level('INFO', logger='vfd_ros2.drives.canopen')
    try:
        for _ in range(2000):              # 0x4210: excess temperature (a warning here)
            sender.send(can.Message(arbitration_id=0x81, data=bytes([0x10, 0x42, 0x08, 0, 0, 0,
                                                                     0, 0]),
                                    is_extended_id=False))
        consumer = transport._links[1].node.emcy               # noqa: SLF001

        def lines(text: str) -> list[str]:
            return [r.getMessage() for r in caplog.records if text in r.getMessage()]
        wait_for(lambda: lines('EMCY 0x4210'), 5.0, 'the first EMCY logged')
        wait_for(lambda: not consumer.log, 5.0, 'the EMCYs taken by the drive loop')
        # the repeats summed up past the summary period (more than one line if the
        # library's notifier took longer than a period to hand the 2000 frames over)
        summed = wait_for(lambda: lines('more EMCY frames'), 3.0, 'the repeats summed up')
        status = wheel.wait_status(lambda s: s.online, 2.0, 'still online')
        assert not status.fault
        assert len(consumer.active) <= 8
        assert len(lines('EMCY 0x4210')) == 1 and len(summed) <= 3, lines('EMCY')
        assert sum(int(line.split(': ')[1].split()[0]) for line in summed) <= 1999
    finally:
        sender.shutdown()


def test_malformed_frames_are_counted_and_logged_once_per_cob_id(make_can_harness, caplog):
    """A node sending frames too short for their object (a broken or babbling node).

    The library raises on each (EMCY, heartbeat) and logs its exception text at
    ERROR, naming neither frame nor node: a flood. The driver logs the first of
    each COB-ID with its bytes, sums up the repeats, counts them as the node's bad
    frames, and the drive stays online.
    """
    h = make_can_harness()
    wheel = h.wheels[1]
    wheel.wait_status(lambda s: s.online, 5.0, 'online')
    channel = wheel.node.controller.drive.transport.channel
    channel.network.malformed.repeats.period = 0.5
    caplog.set_level('WARNING')
    sender = can.Bus(interface='virtual', channel=h.channel)

    def send(count: int) -> None:
        for _ in range(count):
            for cob_id, data in ((0x81, b'\x10\x42'), (0x701, b'')):   # EMCY 2 of 8 bytes
                sender.send(can.Message(arbitration_id=cob_id, data=data, is_extended_id=False))
    try:
        send(200)
        status = wheel.wait_status(lambda s: s.bad_frames >= 400, 5.0, 'bad frames counted')
        assert status.online and not status.fault, status
        time.sleep(0.6)
        send(10)                # after the summary period: the repeats are summed up
        wheel.wait_status(lambda s: s.bad_frames >= 420, 5.0, 'more bad frames counted')
        ours = [r.getMessage() for r in caplog.records if channel.description in r.getMessage()]
        firsts = [m for m in ours if 'malformed frame 0x' in m]
        assert len(firsts) == 2, ours
        assert any('0x081 [2] 10 42 from node 1' in m for m in firsts), firsts
        assert any('0x701 [0] - from node 1' in m for m in firsts), firsts
        summaries = [m for m in ours if 'more malformed frames' in m]
        assert len(summaries) == 1 and int(summaries[0].split(': ')[1].split()[0]) >= 398, ours
        assert not [r for r in caplog.records if r.name == 'canopen.network'], \
            'the library logged the frames itself'
        assert wheel.wait_status(lambda s: s.online, 2.0, 'still online').reconnects == 0
    finally:
        sender.shutdown()


@pytest.mark.parametrize('profile', ['cia402_velocity', 'kinco_ec'])
def test_tpdos_that_stop_while_the_heartbeat_goes_on_are_stale_not_status(make_can_harness,
                                                                          profile):
    """A node whose heartbeat and SDO go on but whose TPDOs stop (a dead PDO producer).

    Its last status would otherwise stand for ever. A TPDO sent at a known rate
    (each SYNC for cia402_velocity) that stops takes the drive offline, and it
    comes back when they resume; the Kinco's TPDOs come on change only, so their
    silence is normal and the drive stays online.
    """
    h = make_can_harness(profile=profile)
    wheel, sim = h.wheels[1], h.sims[1]
    wheel.wait_status(lambda s: s.online, 5.0, 'online')
    sim.tpdos_off = True
    if profile == 'kinco_ec':
        time.sleep(1.0)
        assert wheel.wait_status(lambda s: True, 1.0, 'status').online
        return
    status = wheel.wait_status(lambda s: not s.online, 3.0, 'offline: TPDOs stale')
    assert 'no TPDO1 from node 1' in status.stop_reason and 'stale' in status.stop_reason
    assert status.timeouts > 0
    sim.tpdos_off = False
    status = wheel.wait_status(lambda s: s.online, 5.0, 'online again')
    assert status.reconnects >= 1


def test_a_drive_the_link_loses_that_still_hears_gets_a_stop_at_once(make_can_harness):
    """Its TPDOs stop while it still takes RPDOs: offline, and it must not run on.

    Without drive-side protection (drive_comm_timeout 0) it ran on its last command
    until the reconnect's stop: 3-8 s behind a neighbour's slow connect (outside
    audit). The stop now goes out as the link closes.
    """
    h = make_can_harness(node_parameters={'auto_enable': True, 'drive_comm_timeout': 0.0,
                                          'reconnect_period': 5.0})
    wheel, sim = h.wheels[1], h.sims[1]
    wheel.stream(2.0)
    wheel.wait_status(lambda s: s.running and abs(s.measured_velocity - 2.0) < 0.05, 6.0,
                      'at 2 rad/s')
    sim.tpdos_off = True                     # status gone, commands still heard
    wheel.wait_status(lambda s: not s.online, 3.0, 'offline: TPDOs stale')
    wait_for(lambda: sim.state is not State.OPERATION_ENABLED or sim.target_raw == 0, 1.0,
             'the stop heard as the link closed (the reconnect is 5 s away)')
    wheel.stop_stream()


def test_a_node_that_goes_to_nmt_stopped_by_itself_is_stopped_and_taken_back(
        make_can_harness):
    """The node enters STOPPED while running: it takes neither SDO nor PDOs (CiA 301).

    The stop as the link closed went over SDO and was ignored, so it ran on, and every
    reconnect failed on its first SDO read until the node was reset by hand (outside
    audit). The driver now tells it PRE-OPERATIONAL before any SDO: stopped at once,
    reconfigured, and running again only on the commands that come after. (0x6007 = 0
    and no host-loss protection: the drive itself does not stop, as the audit's did not.)
    """
    h = make_can_harness(sim_initial={'0x6007': 0},
                         node_parameters={'auto_enable': True, 'drive_comm_timeout': 0.0,
                                          'apply_commissioning': False,
                                          'reconnect_period': 0.5})
    wheel, sim = h.wheels[1], h.sims[1]
    wheel.stream(2.0)
    wheel.wait_status(lambda s: s.running and abs(s.measured_velocity - 2.0) < 0.05, 6.0,
                      'at 2 rad/s')
    wheel.stop_stream()
    with sim.lock:
        sim.node.nmt.state = 'STOPPED'
    status = wheel.wait_status(lambda s: not s.online, 3.0, 'offline: node stopped')
    assert 'NMT state STOPPED' in status.stop_reason, status.stop_reason
    wait_for(lambda: sim.state is not State.OPERATION_ENABLED, 1.0, 'the stop heard')
    status = wheel.wait_status(lambda s: s.online, 5.0, 'taken back without a restart')
    assert status.reconnects >= 1 and not status.running
    wait_for(lambda: sim.speed_rpm == 0.0, 3.0, 'at rest, no command since')
    wheel.stream(1.0)
    wheel.wait_status(lambda s: s.running and abs(s.measured_velocity - 1.0) < 0.05, 6.0,
                      'running on the commands after it')
    wheel.stop_stream()


def test_a_node_whose_heartbeat_stops_stays_offline_until_it_comes_back(make_can_harness):
    """Its SDO and TPDOs go on: each connect took it online without a heartbeat.

    The supervision dropped it at once and it was connected again, twice a second:
    ~/status and /diagnostics alternated online and offline (outside audit). A
    connect now needs a heartbeat after NMT start.
    """
    h = make_can_harness(node_parameters={'reconnect_period': 0.2})
    wheel, sim = h.wheels[1], h.sims[1]
    wheel.wait_status(lambda s: s.online, 5.0, 'online')
    sim.heartbeat_off = True
    status = wheel.wait_status(lambda s: not s.online, 3.0, 'offline: no heartbeat')
    reconnects = status.reconnects
    wheel.wait_status(lambda s: 'within' in s.stop_reason, 3.0, 'a connect refused')
    start = len(wheel.statuses)
    time.sleep(1.5)                                  # several reconnect periods
    seen = wheel.statuses[start:]
    assert seen and not any(s.online for s in seen), 'taken online without a heartbeat'
    assert seen[-1].reconnects == reconnects
    assert 'no heartbeat from node 1 within' in seen[-1].stop_reason, seen[-1].stop_reason
    sim.heartbeat_off = False
    wheel.wait_status(lambda s: s.online, 5.0, 'online again')


def test_a_connect_that_is_not_completed_leaves_the_node_pre_operational(make_can_harness):
    """Started and not heard, the node stayed OPERATIONAL until the next attempt.

    There it tripped on the RPDO deadline the connect had set and came back with a
    fault to reset by hand (outside re-check). It is put back to PRE-OPERATIONAL.
    """
    h = make_can_harness(node_parameters={'reconnect_period': 4.0,
                                          'drive_comm_timeout': 0.0})   # (no consumer)
    wheel, sim = h.wheels[1], h.sims[1]
    wheel.wait_status(lambda s: s.online, 5.0, 'online')
    sim.heartbeat_off = True
    wheel.wait_status(lambda s: 'within' in s.stop_reason, 8.0, 'a connect not completed')
    wait_for(lambda: sim.node.nmt.state == 'PRE-OPERATIONAL', 1.0,
             'pre-operational, the next attempt 4 s away')


def test_tpdos_of_the_wrong_length_are_named_not_taken_for_silence(make_can_harness, caplog):
    """TPDO1 keeps coming, three bytes short of its mapping: the reason says so."""
    caplog.set_level('WARNING')
    h = make_can_harness()
    wheel, sim = h.wheels[1], h.sims[1]
    bad_frames = wheel.wait_status(lambda s: s.online, 5.0, 'online').bad_frames
    sim.tpdo_bytes = 3
    status = wheel.wait_status(lambda s: not s.online, 3.0, 'offline: TPDO1 malformed')
    assert 'TPDO1 from node 1 has 3 bytes where its mapping needs' in status.stop_reason, \
        status.stop_reason
    assert status.bad_frames > bad_frames
    assert any('has 3 bytes' in r.getMessage() for r in caplog.records)
    sim.tpdo_bytes = None
    wheel.wait_status(lambda s: s.online, 5.0, 'online again')


def test_host_heartbeat_on_the_bus_at_its_period(make_can_harness):
    """One producer per channel (two drive nodes here), 0x700 + 127, state 05, periodic."""
    h = make_can_harness(node_ids=(1, 2))
    listener = can.Bus(interface='virtual', channel=h.channel)
    try:
        [channel] = [c for c in open_channels() if c.key[1] == h.channel]
        period = channel.heartbeat_period
        controller = h.wheels[1].node.controller
        assert period == pytest.approx(min(max(controller.addressing_interval(), 0.01), 0.1),
                                       abs=0.001)
        stamps = []
        deadline = 40 * period + 5.0
        while len(stamps) < 40:
            message = listener.recv(timeout=deadline)
            assert message is not None, 'no host heartbeat'
            if message.arbitration_id == 0x77F:
                assert bytes(message.data) == b'\x05'   # NMT operational
                stamps.append(message.timestamp)
        gaps = [b - a for a, b in zip(stamps, stamps[1:])]
        median = sorted(gaps)[len(gaps) // 2]
        assert median == pytest.approx(period, rel=0.25)       # one producer, not two
        timeout = controller.state.protection.timeout          # what the drives consume
        assert max(gaps) < timeout, (max(gaps), timeout)
    finally:
        listener.shutdown()


def test_a_drive_set_to_run_on_without_its_master_is_commissioned_to_fault(make_can_harness):
    # CiA 402 0x6007 = 0 ("no action"): a drive that loses the master's heartbeat runs on
    # at its last target velocity, whatever the host-loss protection set up (outside
    # audit); 0x605C = 0 lets ~/stop coast. The profile's commissioning writes 1 and 1.
    h = make_can_harness(sim_initial={'0x6007': 0, '0x605C': 0},
                         node_parameters={'auto_enable': True, 'drive_comm_timeout': 0.3})
    wheel, sim = h.wheels[1], h.sims[1]
    wait_for(lambda: sim.value('0x6007') == 1 and sim.value('0x605C') == 1, 3.0,
             'commissioned')
    wheel.stream(1.0)
    wheel.wait_status(lambda s: s.running, 6.0, 'running')
    wheel.node.controller.drive.transport.channel.stop_heartbeat()
    wait_for(lambda: sim.state is State.FAULT and sim.speed_rpm == 0.0, 3.0,
             'the drive stops by itself')
    assert sim.fault_code == 0x8130


def test_a_drive_that_takes_no_action_on_a_lost_master_has_no_host_loss_protection(
        make_can_harness):
    # With apply_commissioning false nothing writes 0x6007: read at connect, 0 ("no
    # action") leaves heartbeat consumer and RPDO deadline without effect on the motor,
    # and the status said they protected it (outside audit).
    h = make_can_harness(sim_initial={'0x6007': 0},
                         node_parameters={'drive_comm_timeout': 0.3,
                                          'apply_commissioning': False})
    wheel = h.wheels[1]
    status = wheel.wait_status(lambda s: s.online, 6.0, 'online')
    assert status.host_loss_timeout == 0.0
    assert '0x6007 abort connection option = 0, no action' in status.host_loss_protection
    diagnostic = wheel.node.diagnostic_status()
    assert diagnostic.level == DiagnosticStatus.WARN
    assert 'no drive-side host-loss protection' in diagnostic.message


@pytest.mark.parametrize('option, state, fault', [
    (0, State.OPERATION_ENABLED, 0),          # no action: runs on
    (1, State.FAULT, HEARTBEAT_EVENT),
    (2, State.SWITCH_ON_DISABLED, 0),        # disable voltage: coasts
    (3, State.QUICK_STOP_ACTIVE, 0)])
def test_the_twin_reacts_to_a_lost_master_as_0x6007_says(option, state, fault):
    # So that the commissioning test above can fail: a twin that always faulted would
    # pass it with or without the write.
    sim = SimulatedCanopenDrive(load_profile('cia402_velocity'), 1, '', {'0x6007': option})
    sim.state = State.OPERATION_ENABLED
    sim._abort_connection(HEARTBEAT_EVENT, 0x11)       # noqa: SLF001 - the reaction alone
    assert (sim.state, sim.fault_code) == (state, fault)
    assert sim.emcy_sent == [(HEARTBEAT_EVENT, 0x11, bytes(5))]


def test_consumer_heartbeat_set_and_the_drive_stops_when_the_host_heartbeat_stops(
        make_can_harness):
    h = make_can_harness(node_parameters={'auto_enable': True, 'drive_comm_timeout': 0.3})
    wheel, sim = h.wheels[1], h.sims[1]
    assert sim.node.sdo[0x1016][1].raw == (127 << 16) | 300      # host node 127, 300 ms
    status = wheel.status
    assert status.host_loss_timeout == pytest.approx(0.3)
    assert 'heartbeat consumer 0x1016:01' in status.host_loss_protection
    assert 'RPDO1 deadline 0x1400:05' in status.host_loss_protection
    wheel.stream(1.0)
    wheel.wait_status(lambda s: s.running, 6.0, 'running')
    transport = wheel.node.controller.drive.transport
    transport.channel.stop_heartbeat()          # the host's heartbeat dies; RPDOs go on
    wait_for(lambda: sim.state is State.FAULT and sim.speed_rpm == 0.0, 3.0,
             'the drive stops by itself')
    assert sim.fault_code == 0x8130 and sim.heartbeat_events == 1
    assert (0x8130, 0x11, bytes(5)) in sim.emcy_sent      # EMCY: heartbeat event
    fault = wheel.wait_status(lambda s: s.fault and s.fault_code == 0x8130, 6.0, 'reported')
    assert fault.fault_code == 0x8130
    wait_for(lambda: wheel.faults and wheel.faults[-1].display == '0x8130', 3.0,
             'the fault published')
    assert not wheel.status.running
    # The driver took the drive's NMT reaction (pre-operational) as a link loss and
    # reconnected, which restarts the heartbeat: a reset then brings the wheel back.
    wheel.wait_status(lambda s: s.online, 6.0, 'online')
    assert wheel.trigger('reset_fault').success
    wheel.wait_status(lambda s: s.running, 6.0, 'running again')


def test_drive_stops_by_itself_when_the_driver_process_dies(make_can_harness):
    """SIGKILL in-process: the loop ends mid-cycle (nothing written) and the socket closes."""
    h = make_can_harness(node_parameters={'auto_enable': True})
    wheel, sim = h.wheels[1], h.sims[1]
    wheel.stream(1.0)
    wheel.wait_status(lambda s: s.running and abs(s.measured_velocity - 1.0) < 0.05, 6.0,
                      'running')
    controller = wheel.node.controller
    transport = controller.drive.transport
    try:
        controller._loop._finish = lambda: None    # noqa: SLF001 - a killed process writes no stop
        controller.shutdown()
        network = transport.channel.network        # the process's threads are gone, and
        network.notifier.stop(1.0)                 # the OS closes its CAN socket (heartbeat too)
        network.bus.shutdown()
        wait_for(lambda: sim.state is State.FAULT and sim.speed_rpm == 0.0, 3.0,
                 'the drive stops by itself')
        assert sim.fault_code in (0x8130, 0x8250)  # heartbeat event or RPDO timeout
    finally:
        transport.close()


def test_kinco_refuses_the_consumer_heartbeat_and_diagnostics_warn(make_can_harness):
    """The Kinco EC documents no 0x1016 (manual L970): its twin aborts the write."""
    h = make_can_harness(profile='kinco_ec', node_parameters={'diagnostics_rate': 5.0})
    wheel, sim = h.wheels[1], h.sims[1]
    diagnostics: list[DiagnosticArray] = []
    h.tester.create_subscription(DiagnosticArray, '/diagnostics', diagnostics.append, 10)
    status = wheel.wait_status(lambda s: s.host_loss_protection.startswith('none'), 3.0,
                               'no drive-side protection')
    assert status.host_loss_timeout == 0.0
    assert '0x1016:01' in status.host_loss_protection and \
        'SDO abort 0x06020000' in status.host_loss_protection
    assert 0x1016 not in sim.node.object_dictionary
    warn = wait_for(lambda: next((st for d in diagnostics for st in d.status
                                  if st.hardware_id == status.hardware_id and
                                  st.level == DiagnosticStatus.WARN), None), 3.0,
                    'diagnostics WARN')
    assert 'no drive-side host-loss protection' in warn.message
    values = {kv.key: kv.value for kv in warn.values}
    assert values['host-loss protection'].startswith('none')


def test_new_commands_wait_for_the_sync_cycle_but_a_watchdog_stop_does_not(make_can_harness):
    """On a SYNC-driven bus a new value goes out with the next cycle's SYNC.

    An early burst would add a SYNC off the cycle period (the drives' communication
    cycle) and, with a planner streaming new values, one extra burst per command;
    the watchdog's stop still goes out at once.
    """
    h = make_can_harness(node_parameters={'auto_enable': True, 'control_rate': 4.0,
                                          'command_timeout': 0.5})
    wheel, sim = h.wheels[1], h.sims[1]
    wheel.stream(1.0)
    wheel.wait_status(lambda s: s.running, 6.0, 'running')
    wheel.stop_stream()
    listener = can.Bus(interface='virtual', channel=h.channel)
    try:
        start = time.monotonic()
        for index in range(40):                     # a new value every 25 ms for 1 s
            wheel.publish(1.0 + 0.1 * (index % 2))
            time.sleep(0.025)
        last_command = time.monotonic()
        syncs = 0
        while (message := listener.recv(timeout=0)) is not None:
            syncs += message.arbitration_id == 0x80
        assert syncs <= 4.0 * (last_command - start) + 2, syncs     # 4 Hz, not per command
        wait_for(lambda: sim.target_raw == 0, 2.0, 'the watchdog stop applied')
        stopped_after = time.monotonic() - last_command
    finally:
        listener.shutdown()
    # within command_timeout and a margin (a loaded machine's stall), not up to a cycle
    # (0.25 s) later
    assert stopped_after < 0.5 + 0.15, stopped_after


def test_repeat_summary_logs_each_kind_once_and_sums_the_rest_once_per_period():
    lines = RepeatSummary(period=10.0, max_keys=2)
    assert lines.first('a', 0.0) and lines.first('b', 1.0)
    assert not lines.first('a', 2.0)            # a repeat
    assert not lines.first('c', 3.0)            # a third kind: over max_keys, a repeat too
    assert lines.due(10.5) == 0                 # 10 s after the last full line ('b' at 1.0)
    assert lines.due(11.0) == 2
    assert not lines.first('a', 12.0)
    assert lines.due(20.9) == 0 and lines.due(21.0) == 1     # 10 s after the summary
    assert lines.due(40.0) == 0                 # nothing new: no line
    lines.forget()                              # the drive's error reset
    assert lines.first('a', 41.0) and lines.first('c', 41.0)


def test_a_kincos_can_settings_are_not_written_over_its_own_can_link(make_can_harness):
    """B0.35/B0.36 (CAN bit rate, node id): written over SDO, the drive leaves the bus."""
    h = make_can_harness(profile='kinco_ec')
    wheel = h.wheels[1]
    for code, value in (('B0.36', 5.0), ('B0.35', 1.0)):
        reply = wheel.call(SetDriveParameter, 'set_drive_parameter',
                           SetDriveParameter.Request(name=code, value=value))
        assert not reply.success and 'how this link reaches the drive' in reply.message, \
            (code, reply.message)
        got = wheel.call(GetDriveParameter, 'get_drive_parameter',
                         GetDriveParameter.Request(name=code))
        assert not got.writable, code
    assert wheel.wait_status(lambda s: s.online, 2.0, 'still online').reconnects == 0


def test_the_heartbeat_and_pdo_objects_written_at_connect_are_not_parameters(make_can_harness):
    """The CANopen objects the driver writes at connect are refused as parameters.

    0x1017 through ~/set_drive_parameter took a running drive offline (its heartbeat
    stopped) and was reverted at the reconnect; now refused, reported not writable.
    """
    h = make_can_harness()
    wheel = h.wheels[1]
    reply = wheel.call(SetDriveParameter, 'set_drive_parameter',
                       SetDriveParameter.Request(name='heartbeat_time', value=0.0))
    assert not reply.success and 'writes at connect' in reply.message, reply.message
    got = wheel.call(GetDriveParameter, 'get_drive_parameter',
                     GetDriveParameter.Request(name='0x1017'))
    assert got.success and not got.writable
    assert wheel.wait_status(lambda s: s.online, 2.0, 'online').reconnects == 0


def _set(wheel, name: str, value: float) -> None:
    reply = wheel.call(SetDriveParameter, 'set_drive_parameter',
                       SetDriveParameter.Request(name=name, value=value, persistent=False))
    assert reply.success, (name, reply.message)


def _motor_rpm_to_wheel(rpm: float) -> float:
    return rpm * 2 * math.pi / 60 / 10.0          # the harness's gear_ratio 10


def test_a_stop_is_verified_at_standstill_not_when_the_drive_drops_its_run_state(
        make_can_harness):
    """``~/stop`` answers once the measured speed is down, not at the state change alone.

    With 0x605C = 1 (the twin's default) a CiA 402 drive stays in operation enabled
    through the ramp; with 0 it switches on at once and the motor coasts on. The
    stop is verified by standstill either way; a motor still turning at
    stop_timeout fails the stop, naming the speed.
    """
    h = make_can_harness(node_parameters={'auto_enable': True})
    wheel, sim = h.wheels[1], h.sims[1]
    _set(wheel, 'profile_deceleration', 400.0)             # 2 rad/s = 191 rpm: ~0.5 s
    for option in (1, 0):
        # (a commissioning value: the services refuse it, so it is set at the drive, as
        # if by its keypad or another tool after the connect)
        sim.node.sdo[0x605C].raw = option
        wheel.trigger('enable')
        wheel.stream(2.0)
        wheel.wait_status(lambda s: s.running and abs(s.measured_velocity - 2.0) < 0.05, 6.0,
                          'at 2 rad/s')
        reply = wheel.trigger('stop')
        speed = _motor_rpm_to_wheel(sim.speed_rpm)
        assert reply.success, (option, reply.message)
        assert abs(speed) <= 0.1 + 1e-9, (option, speed, reply.message)
        wait_for(lambda: sim.state is State.SWITCHED_ON, 2.0, 'operation disabled')
        wheel.stop_stream()
    # A coast slower than stop_timeout: not verified, and the answer says why.
    _set(wheel, 'profile_deceleration', 20.0)              # 191 rpm: ~10 s
    wheel.node.set_parameters([Parameter('stop_timeout', value=0.5)])
    wheel.trigger('enable')
    wheel.stream(2.0)
    wheel.wait_status(lambda s: s.running and abs(s.measured_velocity - 2.0) < 0.05, 6.0,
                      'at 2 rad/s')
    reply = wheel.trigger('stop')
    wheel.stop_stream()
    assert not reply.success
    assert 'the drive reports not running, but still measures' in reply.message, reply.message
    assert sim.state is State.SWITCHED_ON and _motor_rpm_to_wheel(sim.speed_rpm) > 1.0


def test_a_reversal_in_the_middle_of_a_long_ramp_is_not_taken_for_a_stall(make_can_harness):
    # A speed-controlled drive (no slip allowance) reversed at +2 rad/s towards -5 on a
    # 300 rpm/s ramp needs 2.2 s, more than stop_timeout: timed from the error's last
    # shrinking, it was told as a limit in the drive (re-check). The measured speed
    # moves towards the command all the way: not told.
    h = make_can_harness(node_parameters={'auto_enable': True, 'stop_timeout': 1.0})
    wheel = h.wheels[1]
    _set(wheel, 'profile_acceleration', 300.0)
    _set(wheel, 'profile_deceleration', 300.0)
    wheel.stream(5.0)
    wheel.wait_status(lambda s: s.measured_velocity > 2.0, 6.0, 'half way up to +5 rad/s')
    wheel.stream(-5.0)
    levels = diagnostic_levels_until_at(wheel, -5.0, 6.0)
    assert len(levels) > 20 and set(levels) == {DiagnosticStatus.OK}, levels


def test_a_ramp_slower_than_stop_timeout_is_told_not_counted_as_a_start_from_elsewhere(
        make_can_harness, caplog):
    """A CiA 402 drive stays in operation enabled through its ramp (0x605C = 1).

    Ramping down past stop_timeout was counted as an unexpected start and shown as an
    ERROR, "look for another run source" (outside audit). A speed falling fast enough
    to reach zero within two more stop_timeouts is a ramp: one warning. One falling
    slower (which a runaway drifting down looks like too: the re-check's ran 30 s
    unreported) is the ERROR, naming both, and not counted as a start.
    """
    h = make_can_harness(node_parameters={'auto_enable': True, 'stop_timeout': 0.5})
    wheel, sim = h.wheels[1], h.sims[1]

    def ramp_from_2_rad_s(deceleration: float) -> None:
        _set(wheel, 'profile_deceleration', deceleration)
        wheel.stream(2.0)
        wheel.wait_status(lambda s: s.running and abs(s.measured_velocity - 2.0) < 0.05, 6.0,
                          'at 2 rad/s (191 rpm)')
        wheel.stop_stream()
        wheel.wait_status(lambda s: s.watchdog_tripped, 2.0, 'watchdog')

    with caplog.at_level(logging.WARNING):
        ramp_from_2_rad_s(160.0)                            # 1.2 s
        wait_for(lambda: sim.speed_rpm == 0.0 and sim.state is State.SWITCHED_ON, 4.0,
                 'ramped down')
    assert not any('stop_timeout' in s.stop_reason for s in wheel.statuses)
    told = [r.getMessage() for r in caplog.records if 'still ramping down' in r.getMessage()]
    assert len(told) == 1, told
    assert wheel.status.unexpected_starts == 0
    ramp_from_2_rad_s(40.0)                                 # 4.8 s: ten stop_timeouts
    status = wheel.wait_status(lambda s: 'stop_timeout' in s.stop_reason, 3.0, 'the ERROR')
    assert 'its speed falling slowly' in status.stop_reason and \
        'a run source elsewhere' in status.stop_reason, status.stop_reason
    assert wheel.node.diagnostic_status().level == DiagnosticStatus.ERROR
    wait_for(lambda: sim.speed_rpm == 0.0, 8.0, 'ramped down')
    wheel.wait_status(lambda s: 'stop_timeout' not in s.stop_reason, 2.0, 'cleared')
    assert wheel.status.unexpected_starts == 0


def test_an_idle_drive_is_enabled_before_any_command(make_can_harness):
    """Enable first, then commands: the order an integrator uses.

    An idle CiA 402 drive waits in SWITCH_ON_DISABLED, which counts as ready.
    """
    h = make_can_harness(node_parameters={'action_timeout': 1.0})
    wheel = h.wheels[1]
    reply = wheel.trigger('enable')
    assert reply.success and 'runs as soon as velocity commands arrive' in reply.message, \
        reply.message
    wheel.stream(1.0)
    wheel.wait_status(lambda s: s.running and abs(s.measured_velocity - 1.0) < 0.05, 6.0,
                      'running on the commands')


def test_synchronous_pdos_without_a_sync_producer_are_not_shown_as_live(make_can_harness):
    """sync_producer false and nobody else sends SYNC: no TPDO ever comes.

    Its status (read once at connect) used to be shown online for ever, a drive
    started from elsewhere reported as standing still.
    """
    h = make_can_harness(online=False, node_parameters={'transport.sync_producer': False})
    wheel = h.wheels[1]
    wheel.wait_status(lambda s: 'sync_producer is false' in s.stop_reason, 6.0,
                      'no TPDO named, with its likely cause')
    first = len(wheel.statuses)
    time.sleep(3.0)             # reconnects come and fail: never online in between
    later = wheel.statuses[first:]
    assert len(later) > 50 and not any(s.online for s in later), \
        sum(s.online for s in later)
    assert 'no TPDO1 from node 1' in later[-1].stop_reason


def test_canopen_settings_that_cannot_work_are_refused_at_start():
    from vfd_ros2.control.factory import build_controller
    from vfd_ros2.errors import ParameterError
    base = {'drive.profile': 'cia402_velocity', 'transport.type': 'canopen',
            'transport.interface': 'virtual', 'transport.channel': 'refused',
            'gear_ratio': 10.0}
    # rpm per count off by 1000: 0.5 rad/s became 47746 counts, clamped to the drive's
    # top speed, while the measured speed (scaled the same way) looked slow
    with pytest.raises(ParameterError, match=r'max_velocity 10 rad/s: .* beyond its range'
                                             r'.*drive\.velocity_scale'):
        build_controller({**base, 'drive.velocity_scale': 0.001})
    with pytest.raises(ParameterError, match='heartbeat_timeout 0.1 s is shorter than 1.5 '
                                             'heartbeat periods'):
        build_controller({**base, 'transport.heartbeat_ms': 1000,
                          'transport.heartbeat_timeout': 0.1})
    build_controller({**base, 'transport.heartbeat_ms': 100,       # 1.5 periods: the least
                      'transport.heartbeat_timeout': 0.15})
    controller = build_controller(base)
    with pytest.raises(ParameterError, match='beyond its range'):
        controller.reconfigure(max_velocity=1e6)
    assert controller.config.max_velocity == 10.0


def test_a_can_channel_that_no_setting_could_open_is_refused_at_start():
    """These used to be retried for ever with the node up and exit code 0."""
    from vfd_ros2.errors import ParameterError
    from vfd_ros2.transports.canopen import CanopenTransport
    with pytest.raises(ParameterError, match="'socketcann' is not a python-can interface"):
        CanopenTransport('socketcann', 'can0')
    with pytest.raises(ParameterError, match='socketcand needs .* host, port missing'):
        CanopenTransport('socketcand', 'can0')
    with pytest.raises(ParameterError, match="port 'x': a TCP port number"):
        CanopenTransport('socketcand', 'can0', can_options={'host': '127.0.0.1', 'port': 'x'})
    # a bit rate the interface does not take is said not to be applied (a WARN)
    note, = CanopenTransport('socketcan', 'can0', bitrate=125000).link_notes
    assert 'transport.bitrate 125000 is not applied' in note and 'ip link set can0' in note
    assert CanopenTransport('virtual', 'x').link_notes == ()


def test_a_second_host_on_the_channel_is_named(make_can_harness):
    """Frames only this host sends, heard from another device: SYNC, RPDOs to its drives.

    Two hosts on one node id, or commanding one drive, fought over it unnamed (both
    online, one reporting an "unexpected start" the other had commanded).
    """
    h = make_can_harness()
    wheel = h.wheels[1]
    time.sleep(0.3)
    assert 'another device' not in wheel.node.diagnostic_status().message   # the sim alone
    other = can.Bus(interface='virtual', channel=h.channel)
    try:
        for cob_id, data in ((0x80, b''), (0x77F, b'\x05'), (0x201, b'\x0f\x00\x00\x00\x00\x00')):
            other.send(can.Message(arbitration_id=cob_id, data=data, is_extended_id=False))
    finally:
        other.shutdown()
    wait_for(lambda: wheel.node.diagnostic_status().message.count('another device') == 2, 3.0,
             'both named')
    message = wheel.node.diagnostic_status().message
    assert 'two SYNC producers' in message and 'a second host commands this drive' in message
    # not the host heartbeat's COB-ID: socketcan loops a periodic task's own frames back
    assert 'node 127' not in message


def test_repeat_throttle_tells_each_kind_once_per_period_and_what_was_left():
    from vfd_ros2.protocol.repeats import RepeatThrottle
    throttle = RepeatThrottle(period=10.0, max_kinds=2)
    assert throttle.note('a', 0.0).first
    assert throttle.note('a', 1.0) is None and throttle.note('a', 2.0) is None
    assert throttle.untold == 2 and throttle.due(5.0) == []
    told = throttle.note('a', 10.5)                 # its period is over: told, with the rest
    assert (told.repeats, told.seconds, told.first) == (2, 10.5, False)
    assert throttle.untold == 0
    assert throttle.note('b', 11.0).first and throttle.note('b', 12.0) is None
    assert throttle.note('c', 13.0).first           # a third kind: 'a', the oldest, goes
    assert throttle.note('a', 14.0).first           # ... and 'b' with its untold repeat
    assert throttle.untold == 0
    assert throttle.note('a', 15.0) is None
    assert throttle.due(20.0) == [] and throttle.due(24.0) == [('a', 1, 10.0, False)]
    assert throttle.note('c', 16.0) is None
    assert throttle.due(16.5, at_end=True) == [('c', 1, 3.5, False)]


def test_repeat_throttle_forgets_the_least_recently_seen_kind():
    from vfd_ros2.protocol.repeats import RepeatThrottle
    throttle = RepeatThrottle(period=10.0, max_kinds=2)
    throttle.note('a', 0.0)
    throttle.note('b', 1.0)
    assert throttle.note('a', 2.0) is None          # 'a' seen again: 'b' is the older now
    assert throttle.note('c', 3.0).first            # 'b' goes, with nothing untold
    assert throttle.untold == 1                     # 'a''s repeat is kept
    assert throttle.note('a', 4.0) is None
