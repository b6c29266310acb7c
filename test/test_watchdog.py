"""Unit tests of the command watchdog with an injected clock (no sleeps)."""

from __future__ import annotations

import math

import pytest

from vfd_ros2.control.watchdog import CommandWatchdog


class FakeClock:
    def __init__(self, now: float = 1000.0) -> None:
        self.now = now

    def __call__(self) -> float:
        return self.now

    def advance(self, seconds: float) -> None:
        self.now += seconds


@pytest.fixture
def clock() -> FakeClock:
    return FakeClock()


def test_expired_before_the_first_feed(clock):
    watchdog = CommandWatchdog(0.5, clock)
    assert watchdog.expired
    assert not watchdog.ever_fed
    assert watchdog.age == math.inf
    clock.advance(1e6)
    assert watchdog.expired


def test_fresh_after_a_feed(clock):
    watchdog = CommandWatchdog(0.5, clock)
    watchdog.feed()
    assert watchdog.ever_fed
    assert not watchdog.expired
    assert watchdog.age == 0.0
    clock.advance(0.25)
    assert watchdog.age == pytest.approx(0.25)
    assert not watchdog.expired


def test_expires_after_the_timeout(clock):
    watchdog = CommandWatchdog(0.5, clock)
    watchdog.feed()
    clock.advance(0.5)
    assert not watchdog.expired              # "older than the timeout": exactly 0.5 s is not
    clock.advance(0.001)
    assert watchdog.expired
    assert watchdog.age == pytest.approx(0.501)


def test_a_longer_timeout_does_not_revive_a_command_that_expired(clock):
    """A command_timeout raised after the commands stopped does not revive the last.

    (Outside audit: the wheel ran again on a command seconds old.) The next
    command counts for the new timeout.
    """
    watchdog = CommandWatchdog(0.5, clock)
    watchdog.feed()
    clock.advance(1.5)
    assert watchdog.expired
    watchdog.timeout = 30.0
    assert watchdog.expired
    watchdog.feed()
    clock.advance(20.0)
    assert not watchdog.expired


def test_a_longer_timeout_does_not_lengthen_the_command_already_taken(clock):
    watchdog = CommandWatchdog(0.5, clock)
    watchdog.feed()
    clock.advance(0.3)
    watchdog.timeout = 30.0
    clock.advance(0.3)
    assert watchdog.expired
    assert watchdog.deadline == pytest.approx(1000.5)
    assert watchdog.limit == pytest.approx(0.5)         # (what ~/status names)


def test_a_shorter_timeout_applies_to_the_command_already_taken(clock):
    watchdog = CommandWatchdog(30.0, clock)
    watchdog.feed()
    clock.advance(0.3)
    assert not watchdog.expired
    watchdog.timeout = 0.25
    assert watchdog.expired
    assert watchdog.deadline == pytest.approx(1000.25)


def test_each_feed_restarts_the_timeout(clock):
    watchdog = CommandWatchdog(0.5, clock)
    for _ in range(10):
        watchdog.feed()
        clock.advance(0.4)
        assert not watchdog.expired
    clock.advance(0.2)
    assert watchdog.expired
    watchdog.feed()
    assert not watchdog.expired


def test_reset_forgets_all_commands(clock):
    watchdog = CommandWatchdog(0.5, clock)
    watchdog.feed()
    watchdog.reset()
    assert watchdog.expired
    assert not watchdog.ever_fed
    assert watchdog.age == math.inf
    watchdog.feed()
    assert not watchdog.expired


def test_uses_the_injected_clock_only(clock):
    watchdog = CommandWatchdog(30.0, clock)
    watchdog.feed()
    clock.advance(29.0)                      # no real time passes in this test
    assert not watchdog.expired
    clock.advance(2.0)
    assert watchdog.expired


def test_timeout_attribute():
    assert CommandWatchdog(0.25, FakeClock()).timeout == 0.25


@pytest.mark.parametrize('timeout', [0.0, -0.5, math.nan, math.inf, -math.inf])
def test_invalid_timeouts_raise(timeout):
    with pytest.raises(ValueError, match='command_timeout must be > 0'):
        CommandWatchdog(timeout, FakeClock())


def test_the_watchdog_reason_says_commands_from_before_the_connect_are_forgotten():
    """'none received' right after a reconnect read as if no planner were running."""
    import math

    from vfd_ros2.control.permit import Conditions, Intent, RunState, decide
    from vfd_ros2.profiles import NO_FAULT
    now = Conditions(online=True, link_error='', link_closed='', fault=NO_FAULT, unsafe='',
                     watchdog_expired=True, watchdog_age=math.inf, command_timeout=0.5)
    state, reason = decide(Intent(enabled=True), now)
    assert state is RunState.WATCHDOG and \
        reason.endswith('(none since the drive connected or was stopped)')
    state, reason = decide(Intent(enabled=True), now._replace(watchdog_age=0.73))
    assert reason.endswith('(last 0.73 s ago)')


def test_a_stop_reason_names_who_stopped_the_drive():
    """A lifecycle deactivate's hold said "stopped by ~/stop" (outside audit)."""
    from vfd_ros2.control.permit import Conditions, Intent, decide
    from vfd_ros2.profiles import NO_FAULT
    now = Conditions(online=True, link_error='', link_closed='', fault=NO_FAULT, unsafe='',
                     watchdog_expired=False, watchdog_age=0.1, command_timeout=0.5)
    assert decide(Intent(enabled=True, stopped=True, asked_stop=True), now)[1] == \
        'stopped by ~/stop: call ~/enable to resume'
    assert decide(Intent(enabled=True, stopped=True), now)[1] == \
        'stopped by a lifecycle deactivate: call ~/enable to resume'
