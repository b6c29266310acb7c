"""LinkSupervisor: when a drive goes offline, and what the log says of it."""

from __future__ import annotations

import logging

from vfd_ros2.control.link import CONNECT_FAILURES_TOLD, OFFLINE_LOG_PERIOD, LinkSupervisor
from vfd_ros2.errors import CommTimeout


class StepClock:
    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


def flap(link: LinkSupervisor, clock: StepClock, reason: str) -> None:
    """Online, then offline after threshold failed cycles, 0.5 s later."""
    link.connected()
    for _ in range(link.threshold):
        link.new_cycle()
        link.cycle_failed(CommTimeout(reason))
    assert not link.online
    clock.now += 0.5


def test_a_flapping_drive_is_logged_once_per_reason_and_period_with_the_repeats(caplog):
    """A drive refusing a read went offline and back every 0.5 s: 444 lines in 2 min."""
    clock = StepClock()
    link = LinkSupervisor('drive x', threshold=2, retry_period=0.5, clock=clock)
    caplog.set_level(logging.INFO, logger='vfd_ros2.control.link')
    for _ in range(int(OFFLINE_LOG_PERIOD / 0.5) + 1):     # one period and one more
        flap(link, clock, 'exception 6: busy')
    flap(link, clock, 'no reply')                            # another reason: told at once
    offline = [r.getMessage() for r in caplog.records if 'offline' in r.getMessage()]
    assert offline == ['drive x offline: exception 6: busy',
                       'drive x offline: exception 6: busy (and 19 times more in the last '
                       f'{OFFLINE_LOG_PERIOD:.0f} s)',
                       'drive x offline: no reply']
    online = [r for r in caplog.records if r.getMessage() == 'drive x online']
    assert len(online) == 3, 'the reconnects after an offline not logged are not logged'
    assert link.reconnects == 21                       # every one counted all the same


def test_offlines_not_logged_are_summed_up_once_the_drive_stays_online(caplog):
    """Flapping that stopped: the repeats counted in its last period are not lost."""
    clock = StepClock()
    link = LinkSupervisor('drive x', threshold=2, retry_period=0.5, clock=clock)
    caplog.set_level(logging.INFO, logger='vfd_ros2.control.link')
    for _ in range(5):
        flap(link, clock, 'no reply')
    link.connected()
    link.cycle_ok()                                 # healthy, inside the period: quiet
    lines = [r.getMessage() for r in caplog.records if 'offline' in r.getMessage()]
    assert lines == ['drive x offline: no reply']
    clock.now += OFFLINE_LOG_PERIOD
    link.cycle_ok()
    link.cycle_ok()                                 # told once
    lines = [r.getMessage() for r in caplog.records if 'offline' in r.getMessage()]
    assert lines == ['drive x offline: no reply',
                     f'drive x was offline 4 times more in the last '
                     f'{OFFLINE_LOG_PERIOD + 2.0:.0f} s: no reply']


def test_failed_connects_count_in_a_row_until_online_or_closed():
    """Their count orders a bus's connects; a drive closed on purpose starts afresh."""
    link = LinkSupervisor('drive x', threshold=2, retry_period=0.5, clock=StepClock())
    for _ in range(3):
        link.connect_failed(CommTimeout('no reply'))
    assert link.failed_connects == 3
    link.closed('deactivated')
    assert link.failed_connects == 0
    link.connect_failed(CommTimeout('no reply'))
    link.connected()
    assert link.failed_connects == 0


def test_connect_failures_are_logged_once_per_kind_while_the_drive_stays_offline(caplog):
    """Two reasons that alternate, or one naming the bytes received: a line per attempt.

    A second drive on a gateway that takes one connection logged 55 lines in 12 s
    (outside audit), and a reply with another transaction id one per attempt.
    """
    link = LinkSupervisor('drive x', threshold=2, retry_period=0.5, clock=StepClock())
    caplog.set_level(logging.INFO, logger='vfd_ros2.control.link')
    for attempt in range(20):
        link.connect_failed(CommTimeout('write 0x0005 @ 0x2000 (unit 2): [Errno 104] '
                                        'Connection reset by peer'))
        link.connect_failed(CommTimeout('cannot open tcp://127.0.0.1:15502'))
        link.connect_failed(CommTimeout(f'write 0x{1200 + attempt:04x} @ 0x2001 (unit 1): '
                                        f'malformed reply 04 {attempt:02x} 00 00 00 06 01 06'))
    lines = [r.getMessage() for r in caplog.records if 'connect failed' in r.getMessage()]
    assert lines == [
        'drive x: connect failed: write 0x0005 @ 0x2000 (unit 2): [Errno 104] Connection '
        'reset by peer',
        'drive x: connect failed: cannot open tcp://127.0.0.1:15502',
        'drive x: connect failed: write 0x04b0 @ 0x2001 (unit 1): malformed reply 04 00 00 '
        '00 00 06 01 06']
    for n in range(2 * CONNECT_FAILURES_TOLD):            # kinds without end: bounded
        link.connect_failed(CommTimeout(f'refused value {"x" * n}'))
    assert len([r for r in caplog.records if 'connect failed' in r.getMessage()]) == \
        CONNECT_FAILURES_TOLD
    link.connected()                                      # online again: told afresh
    link.connect_failed(CommTimeout('cannot open tcp://127.0.0.1:15502'))
    assert caplog.records[-1].getMessage() == \
        'drive x: connect failed: cannot open tcp://127.0.0.1:15502'
