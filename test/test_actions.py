"""Unit tests of the service action queue (no drive, no ROS): order and sharing."""

from __future__ import annotations

from vfd_ros2.control.actions import NOT_SERVED, Action, ActionQueue
from vfd_ros2.control.state import ActionResult


def recorder(ran: list[str], name: str, steps: int = 1):
    """Return an action factory that takes ``steps`` loop steps and records its run."""
    def action() -> Action:
        for _ in range(steps):
            yield
        ran.append(name)
        return ActionResult(True, f'{name} #{len(ran)}')
    return action


def served() -> ActionQueue:
    queue = ActionQueue('test')
    queue.open()
    return queue


def run_until_idle(queue: ActionQueue, limit: int = 100) -> None:
    for _ in range(limit):
        queue.advance()


def test_requests_of_another_kind_keep_their_place_behind_a_slow_action():
    """A slow stop, then disable, enable, disable: the last disable runs last."""
    queue, ran = served(), []
    slow = queue.submit('stop', recorder(ran, 'stop', steps=5))
    queue.advance()                                      # the stop is under way
    first = queue.submit('disable', recorder(ran, 'disable'))
    enable = queue.submit('enable', recorder(ran, 'enable'))
    last = queue.submit('disable', recorder(ran, 'disable'))
    run_until_idle(queue)
    assert ran == ['stop', 'disable', 'enable', 'disable']
    assert [f.result().message for f in (slow, first, enable, last)] == [
        'stop #1', 'disable #2', 'enable #3', 'disable #4']


def test_identical_requests_waiting_next_to_each_other_share_one_run():
    queue, ran = served(), []
    queue.submit('stop', recorder(ran, 'stop', steps=3))
    queue.advance()
    enables = [queue.submit('enable', recorder(ran, 'enable')) for _ in range(20)]
    stop = queue.submit('stop', recorder(ran, 'stop'))
    run_until_idle(queue)
    assert ran == ['stop', 'enable', 'stop']
    assert {f.result().message for f in enables} == {'enable #2'}
    assert stop.result().message == 'stop #3'


def test_requests_without_a_key_never_share():
    queue, ran = served(), []
    futures = [queue.submit(None, recorder(ran, 'set')) for _ in range(3)]
    run_until_idle(queue)
    assert ran == ['set'] * 3
    assert [f.result().message for f in futures] == ['set #1', 'set #2', 'set #3']


def test_no_request_waits_for_a_loop_that_does_not_run():
    """Requests are answered at once while no loop serves the queue, and never run later.

    Before a loop runs (a managed node not configured) and after it ended, a
    queued request would run whenever one starts: a stale fault reset, say.
    """
    queue, ran = ActionQueue('test'), []
    early = queue.submit('reset_fault', recorder(ran, 'reset_fault'))
    assert early.done() and not early.result().success
    assert early.result().message == NOT_SERVED
    queue.open()
    waiting = queue.submit('stop', recorder(ran, 'stop'))
    queue.close('the control loop ended before this action ran')
    assert waiting.result().message == 'the control loop ended before this action ran'
    late = queue.submit('enable', recorder(ran, 'enable'))
    assert late.result().message == NOT_SERVED
    queue.open()
    run_until_idle(queue)
    assert ran == []


def test_a_stop_asked_while_an_enable_waits_ends_the_wait_and_holds():
    """A ~/stop asked while an enable waits for the drive ends that wait at once.

    The enable waited out action_timeout before the stop behind it was answered, and
    then marked the node disabled over the operator's stop (outside re-check).
    """
    from vfd_ros2.control.actions import ServiceActions
    from vfd_ros2.control.permit import Intent
    from vfd_ros2.drives import Reading

    class Idle:                      # a drive that is ready and never reports running
        profile = None
    reading = Reading()
    reading.flags.update(ready=True, running=False)
    now = [0.0]
    intent = Intent(enabled=False)
    services = ServiceActions(Idle(), intent, lambda: reading, lambda: True,
                              lambda key, value: None, action_timeout=2.0, stop_timeout=10.0,
                              clock=lambda: now[0], standstill=0.1)
    enable = services.factory('enable')()
    next(enable)                     # asked, waiting for the drive to run
    now[0] = 0.1
    services.latch('stop')           # the operator's stop, asked meanwhile
    try:
        next(enable)
        raise AssertionError('the enable waited on')
    except StopIteration as done:
        result = done.value
    assert not result.success and 'asked after this ~/enable' in result.message, result
    assert intent.stopped and intent.asked_stop and intent.enabled    # "stopped by ~/stop"
