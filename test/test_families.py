"""The same integration suite for every drive family, against its simulated twin.

Modbus RTU families over a pty line, Modbus TCP families over a loopback TCP
server; what differs between them (registers, units, commands, fault codes,
parameters) comes from the profile data only.
"""

from __future__ import annotations

import math

import pytest

from harness import wait_for
from vfd_ros2.profiles import Access, available_profiles, load_profile
from vfd_ros2.srv import GetDriveParameter, SetDriveParameter

# Modbus families here; CANopen-only profiles run the same suite in test_canopen_node.py.
FAMILIES = [name for name in available_profiles()
            if load_profile(name).transports[0] in ('modbus_rtu', 'modbus_tcp')]


def writable_parameter(profile):
    """Find a writable, ranged, non-enumerated parameter an integrator would tune."""
    for key in ('acceleration_time', 'deceleration_time'):
        try:
            return profile.parameter(key)
        except Exception:  # noqa: BLE001 - not every family has it
            continue
    for parameter in profile.parameters.values():
        if parameter.access is Access.READ_WRITE and not parameter.options and \
                parameter.minimum is not None and parameter.maximum is not None and \
                parameter.maximum - parameter.minimum >= 2 * parameter.scale and \
                parameter.code not in (profile.control.command, profile.velocity.setpoint):
            return parameter
    raise AssertionError('no writable parameter')


def some_value(parameter):
    """Pick a valid value different from the default, on the resolution grid."""
    steps = round((parameter.maximum - parameter.minimum) / parameter.scale)
    raw = round(parameter.minimum / parameter.scale) + max(1, steps // 3)
    return raw * parameter.scale


@pytest.mark.parametrize('family', FAMILIES)
def test_command_status_and_watchdog(make_harness, family):
    h = make_harness(profile=family, node_parameters={'auto_enable': True})
    h.stream(1.0)
    status = h.wait_status(lambda s: s.running and abs(s.measured_velocity - 1.0) < 0.05, 6.0,
                           f'{family} at 1 rad/s')
    assert status.online and not status.fault and status.commanded_velocity == 1.0
    assert h.sim.speed_rpm > 0
    h.stream(-1.0)
    status = h.wait_status(lambda s: abs(s.measured_velocity + 1.0) < 0.05, 6.0,
                           f'{family} at -1 rad/s')
    assert h.sim.speed_rpm < 0
    if 'reverse' in h.profile.flags:
        assert status.reverse
    h.stop_stream()
    h.wait_status(lambda s: s.watchdog_tripped, 2.0, 'watchdog')
    wait_for(lambda: h.sim.speed_rpm == 0.0 and not h.sim.run_requested, 5.0,
             'simulated motor stopped by the watchdog')


@pytest.mark.parametrize('family', FAMILIES)
def test_fault_and_reset(make_harness, family):
    h = make_harness(profile=family)
    entry = next(iter(h.profile.faults.table.values()))
    subcode = next(iter(entry.subcodes), 0)
    h.sim.inject_fault(entry.code, subcode, latched=True)
    fault = wait_for(lambda: next((f for f in reversed(h.faults) if f.active), None), 3.0,
                     'fault message')
    assert fault.code == entry.code and fault.name == entry.name and fault.known
    assert fault.remedy == entry.remedy
    assert not h.trigger('reset_fault').success
    h.sim.inject_fault(0)
    reply = h.trigger('reset_fault')
    assert reply.success, reply.message
    h.wait_status(lambda s: not s.fault, 3.0, 'fault cleared')


@pytest.mark.parametrize('family', FAMILIES)
def test_parameters_and_bad_inputs(make_harness, family):
    h = make_harness(profile=family)
    parameter = writable_parameter(h.profile)
    value = some_value(parameter)
    reply = h.call(SetDriveParameter, 'set_drive_parameter',
                   SetDriveParameter.Request(name=parameter.code, value=value, persistent=False))
    assert reply.success, reply.message
    assert reply.value == pytest.approx(value)
    assert h.sim.value(parameter.code) == pytest.approx(value)
    got = h.call(GetDriveParameter, 'get_drive_parameter',
                 GetDriveParameter.Request(name=parameter.name or parameter.code))
    assert got.success and got.value == pytest.approx(value) and got.code == parameter.code

    read_only = next(p for p in h.profile.parameters.values() if p.access is Access.READ_ONLY)
    before = dict(h.sim.words)
    for name, bad, why in ((parameter.code, parameter.maximum + 1000 * parameter.scale,
                            'above the maximum'),
                           (parameter.code, math.nan, 'not a finite number'),
                           (read_only.code, 0.0, 'read-only'),
                           ('no_such_parameter', 1.0, 'unknown parameter')):
        reply = h.call(SetDriveParameter, 'set_drive_parameter',
                       SetDriveParameter.Request(name=name, value=bad, persistent=False))
        assert not reply.success and why in reply.message, (name, bad, reply.message)
    assert h.sim.value(parameter.code) == pytest.approx(value)
    changed = {a for a in before if h.sim.words.get(a) != before[a] and
               (p := h.profile.parameter_at(a)) is not None and p.writable and
               p.code not in (h.profile.control.command, h.profile.velocity.setpoint)}
    assert changed == set()


@pytest.mark.parametrize('family', FAMILIES)
def test_comm_loss_and_recovery(make_harness, family):
    h = make_harness(profile=family, node_parameters={'auto_enable': True})
    h.stream(1.0)
    h.wait_status(lambda s: s.running, 6.0, 'running')
    h.sim.silent = True
    status = h.wait_status(lambda s: not s.online, 3.0, 'offline')
    assert status.timeouts > 0
    spec = h.profile.comm_timeout
    if spec is not None:
        # The drive's own timeout (written at connect) stops the motor by itself.
        wait_for(lambda: h.sim.fault_code == spec.fault_code and h.sim.speed_rpm == 0.0, 3.0,
                 'drive comm-loss fault')
    h.stop_stream()                                # the planner waits for the drive
    h.sim.silent = False
    status = h.wait_status(lambda s: s.online, 6.0, 'back online')
    assert status.reconnects >= 1
    if spec is not None and h.profile.faults.table[spec.fault_code].confidence == 'low':
        # A number the manual does not print (Veichi) may be another fault's: it latches.
        h.wait_status(lambda s: s.fault and s.fault_code == spec.fault_code, 3.0, 'latched')
        assert h.sim.fault_code == spec.fault_code
        assert h.trigger('reset_fault').success
    if spec is not None:
        # The comm-loss fault is the host's absence: reset at connect, after the stop.
        wait_for(lambda: h.sim.fault_code == 0, 3.0, 'comm-loss fault reset')
    h.wait_cycles(10)
    assert not h.sim.run_requested                 # never resumes from a stale command
    h.stream(1.0)
    h.wait_status(lambda s: s.running and abs(s.measured_velocity - 1.0) < 0.05, 6.0,
                  'moving again on fresh commands')


def test_every_family_is_covered():
    assert {'boneng_am', 'boneng_mh', 'veichi_ehs100', 'kinco_ec', 'imo_hd2'} <= set(FAMILIES)
    assert load_profile('imo_hd2').transports == ('modbus_tcp', 'ethercat')   # TCP card first


@pytest.mark.parametrize('family', [f for f in FAMILIES if load_profile(f).setpoints])
def test_auxiliary_setpoint_topics(make_harness, family):
    from std_msgs.msg import Float64
    h = make_harness(profile=family)
    for topic, code in h.profile.setpoints.items():
        parameter = h.profile.parameter(code)
        value = some_value(parameter)
        publisher = h.tester.create_publisher(Float64, f'drive/{topic}', 10)
        wait_for(lambda: publisher.get_subscription_count() > 0, 5.0, f'{topic} subscriber')
        for bad in (math.nan, parameter.maximum + 100 * parameter.scale):
            publisher.publish(Float64(data=bad))
        publisher.publish(Float64(data=value))
        wait_for(lambda: h.sim.value(code) == pytest.approx(value), 3.0, f'{topic} written')
        # The invalid values were dropped: the only writes on the wire carry the valid one.
        written = {int.from_bytes(frame[4:6], 'big') for _, frame in list(h.line.received)
                   if frame[1] == 6 and int.from_bytes(frame[2:4], 'big') == parameter.address}
        assert written == {round(value / parameter.scale)}   # the manual's scaling
