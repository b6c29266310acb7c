"""The kept DriveStatus, updated field by field, shows what a new message shows."""

from __future__ import annotations

import math
import random
from types import MappingProxyType

from builtin_interfaces.msg import Time

from vfd_ros2.control.state import DriveState, RunState
from vfd_ros2.drives.base import HostLossProtection
from vfd_ros2.msg import DriveStatus
from vfd_ros2.profiles import NO_FAULT, FaultInfo
from vfd_ros2.ros.messages import StatusMessage, status_message

FAULT = FaultInfo(code=0x21, subcode=2, display='E.021', name='overcurrent', cause='c',
                  remedy='r', known=True)

#: values each DriveState field takes in the sequences below (a few per field, so that
#: consecutive states often share a value, as consecutive polls do)
CHOICES = {
    'hardware_id': ['am@/dev/ttyUSB0#1', 'am@/dev/ttyUSB0#2'],
    'run_state': list(RunState),
    'stop_reason': ['', 'disabled', 'watchdog: no command for 0.5 s'],
    'status_words': [(), (('status', 0x0037),), (('status', 0x1237), ('fault', 0xFFFF1))],
    'commanded_velocity': [0.0, 1.5, -2.25],
    'measured_velocity': [0.0, 1.25, math.nan],
    'setpoint_raw': [0, 1234, -77],
    'measured': [MappingProxyType({}), MappingProxyType({'output_frequency': 12.5}),
                 MappingProxyType({'output_current': 3.0, 'dc_bus_voltage': 48.0,
                                   'temperature': 31.0})],
    'position': [math.nan, 0.5, 2.0],
    'effort': [math.nan, 1.0],
    'active_fault': [NO_FAULT, FAULT],
    'warning_code': [0, 0x1_0005],
    'warning_subcode': [0, 3],
    'protection': [HostLossProtection(),
                   HostLossProtection('C02.04 comm-loss timeout', 0.5, 0.5),
                   HostLossProtection('', 0.0, 0.5, 'the profile has none')],
    'unavailable': [(), ('temperature: exception 2',)],
    'link_notes': [(), ('adapter latency 16 ms',)],
    'read_at': [1.0, 2.0],
    'link_error': ['', 'no reply'],
}


def random_state(rng: random.Random) -> DriveState:
    values = {}
    for name, default in zip(DriveState._fields, DriveState._field_defaults.values()):
        if name in CHOICES:
            values[name] = rng.choice(CHOICES[name])
        elif isinstance(default, bool):
            values[name] = rng.random() < 0.5
        elif isinstance(default, int):
            values[name] = rng.choice([0, 7, 2 ** 33])     # counters (beyond uint32 too)
        elif isinstance(default, str):
            values[name] = rng.choice(['', 'x'])
    values.setdefault('hardware_id', 'am@/dev/ttyUSB0#1')
    return DriveState(**values)


def mutate(rng: random.Random, state: DriveState) -> DriveState:
    """Change a few fields of ``state``, as one poll to the next does."""
    other = random_state(rng)
    names = rng.sample(DriveState._fields, rng.randint(0, 4))
    return state._replace(**{name: getattr(other, name) for name in names})


def same(a: DriveStatus, b: DriveStatus) -> list[str]:
    """Return the fields in which ``a`` and ``b`` differ (NaN equals NaN here)."""
    differ = []
    for field in DriveStatus.get_fields_and_field_types():
        x, y = getattr(a, field), getattr(b, field)
        if isinstance(x, float) and math.isnan(x) and math.isnan(y):
            continue
        if x != y:
            differ.append(field)
    return differ


def test_the_kept_message_updated_poll_by_poll_shows_what_a_new_message_shows():
    rng = random.Random(20261127)
    stamp = Time(sec=5, nanosec=6)
    for _ in range(50):
        kept = StatusMessage('base_link', 'boneng_am')
        state = random_state(rng)
        for _ in range(20):
            state = mutate(rng, state)
            updated = kept.update(state, stamp)
            fresh = status_message(state, stamp, 'base_link', 'boneng_am')
            assert same(updated, fresh) == [], state


def test_every_field_of_the_message_shows_something_of_the_state():
    # Two states that differ in everything the message shows: a field left out of
    # the update (or shown from the wrong field of the state) stays as it was.
    first = DriveState(hardware_id='a')
    second = DriveState(
        hardware_id='b', online=True, ready=True, enabled=True, running=True, reverse=True,
        fault=True, warning=True, at_speed=True, watchdog_tripped=True,
        run_state=RunState.RUNNING, stop_reason='r', status_words=(('status', 1),),
        commanded_velocity=1.0, measured_velocity=2.0, setpoint_raw=3,
        measured=MappingProxyType({'output_frequency': 1.0, 'output_current': 2.0,
                                   'dc_bus_voltage': 3.0, 'temperature': 4.0}),
        active_fault=FAULT, warning_code=5, warning_subcode=6,
        protection=HostLossProtection('C02.04', 0.5, 0.5), unavailable=('u',),
        **{name: 9 for name in ('transactions', 'comm_errors', 'timeouts', 'bad_frames',
                                'exceptions', 'reconnects', 'late_replies',
                                'rejected_commands', 'clamped_commands',
                                'unexpected_starts')})
    kept = StatusMessage('base_link', 'boneng_am')
    before = DriveStatus()
    for field in DriveStatus.get_fields_and_field_types():
        setattr(before, field, getattr(kept.update(first), field))
    after = kept.update(second)
    unchanged = set(DriveStatus.get_fields_and_field_types()) - set(same(before, after))
    assert unchanged == {'header', 'profile'}       # the node's, not the drive's
    assert after.fault_code == 0x21 and after.host_loss_timeout == 0.5
    assert list(after.status_words_raw) == [1] and after.transactions == 9
