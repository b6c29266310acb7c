"""Managed (lifecycle) operation of drive and bus nodes: what each transition does.

    unconfigured --configure--> inactive: the link is opened and every drive
        commissioned (online); nothing may move (velocity commands are ignored,
        ~/enable is refused)
    inactive --activate--> active: motion allowed; drives with auto_enable are
        enabled (the others wait for ~/enable)
    active --deactivate--> inactive: motion refused again, every drive stopped
        (verified) and held
    inactive --cleanup--> unconfigured: the loop ends: stop written, link closed
    any --shutdown--> finalized: stop written first, then the link closed

A transition that cannot be done (a drive does not answer at configure, an
enable is refused) fails with the reason logged and the state unchanged; an
unexpected error (a stop that is not verified, an exception) goes to
ErrorProcessing, which stops the loop (stop written, link closed) and returns
to unconfigured. Transitions block the executor for at most the drive's
action or stop timeout; Ctrl-C or SIGTERM ends the wait at once (the node goes,
and its loop's end writes the stop).

The executables take ``--managed`` (a lifecycle node; plain is the default)
and ``--autostart`` (configure and activate at start, as a lifecycle manager
with autostart would).
"""

from __future__ import annotations

import argparse
import time
from concurrent.futures import Future
from concurrent.futures import wait as futures_wait
from typing import Callable, Mapping

from lifecycle_msgs.srv import ChangeState
from rclpy.impl.rcutils_logger import RcutilsLogger
from rclpy.lifecycle import LifecycleState, TransitionCallbackReturn

from ..control.controller import DriveController
from ..control.state import ActionResult
from ..errors import ParameterError
from .executable import non_ros_arguments

SUCCESS = TransitionCallbackReturn.SUCCESS
FAILURE = TransitionCallbackReturn.FAILURE
ERROR = TransitionCallbackReturn.ERROR

#: ~/status's stop reason while the node is configured but not active
NOT_ACTIVE = 'the node is not active (lifecycle): activate it to move the drive'
#: ~/status's stop reason while it is unconfigured (cleanup, error processing)
LINK_CLOSED = 'the link is closed (lifecycle: unconfigured): configure the node to connect'


def parse_options(args: list[str] | None) -> argparse.Namespace:
    """Return --managed / --autostart from the command line (ROS arguments removed).

    Anything else is refused (ParameterError): a mistyped ``--managed`` must not
    start a plain node, enabled at once where ``auto_enable`` is set.
    """
    parser = argparse.ArgumentParser(add_help=False)
    parser.add_argument('--managed', action='store_true',
                        help='run as a managed (lifecycle) node')
    parser.add_argument('--autostart', action='store_true',
                        help='with --managed: configure and activate at start')
    options, unknown = parser.parse_known_args(non_ros_arguments(args))
    if unknown:
        raise ParameterError(f'unknown argument(s) {" ".join(unknown)}: the options are '
                             '--managed and --autostart; ROS arguments go after --ros-args')
    if options.autostart and not options.managed:
        # (a plain node starts at once anyway: the integrator meant a managed one)
        raise ParameterError('--autostart is for a managed node: give --managed too')
    return options


#: s between two looks at what a transition waits for (and at the node's context)
WAIT_STEP = 0.01


def wait_online(controllers: Mapping[str, DriveController], timeout: float,
                keep_waiting: Callable[[], bool] = lambda: True) -> dict[str, str]:
    """Wait until every controller's drive is online; return {name: why} of the others.

    Ends early once ``keep_waiting()`` is false (the node's context shut down by
    Ctrl-C or SIGTERM: nobody waits for the transition any more).
    """
    deadline = time.monotonic() + timeout
    while True:
        offline = {name: c.state.link_error or c.link.error or 'no reply yet'
                   for name, c in controllers.items() if not c.state.online}
        if not offline or time.monotonic() > deadline or not keep_waiting():
            return offline
        time.sleep(WAIT_STEP)


def results(futures: Mapping[str, Future], timeout: float,
            keep_waiting: Callable[[], bool] = lambda: True) -> dict[str, ActionResult]:
    """Wait for the controllers' action results (concurrent futures, not the executor).

    Ends early, as ``wait_online`` does, once ``keep_waiting()`` is false.
    """
    deadline = time.monotonic() + timeout
    done = {}
    for name, future in futures.items():
        while not future.done() and keep_waiting() and time.monotonic() < deadline:
            futures_wait([future], WAIT_STEP)
        try:
            done[name] = future.result(0.0)
        except Exception as exc:  # noqa: BLE001 - a timeout is a failed action
            done[name] = ActionResult(False, f'no result: {exc!r}')
    return done


def failures(done: Mapping[str, ActionResult]) -> str:
    return '; '.join(f'{name}: {r.message}' for name, r in done.items() if not r.success)


class DriveTransitions:
    """The transitions of one or several drives on one loop (a drive's or a bus's)."""

    def __init__(self, logger: RcutilsLogger, start: Callable[[], None],
                 stop_loop: Callable[[], None],
                 gates: Mapping[str, tuple[DriveController, Callable[[bool], None]]],
                 keep_waiting: Callable[[], bool] = lambda: True) -> None:
        """``keep_waiting``: false once the node's context is shut down (Ctrl-C, SIGTERM)."""
        self._logger = logger
        self._keep_waiting = keep_waiting
        self._start = start
        self._stop_loop = stop_loop
        self._gates = gates
        self.last_error = ''

    def _fail(self, transition: str, reason: str, code: TransitionCallbackReturn
              ) -> TransitionCallbackReturn:
        self.last_error = f'{transition} failed: {reason}'
        self._logger.error(self.last_error)
        return code

    def _allow(self, allowed: bool) -> None:
        for controller, allow in self._gates.values():
            allow(allowed)
            # The drive layer holds it too, and ~/status says why: ~/enable is refused
            # until activate.
            controller.intent.held = '' if allowed else NOT_ACTIVE

    def mark_unconfigured(self) -> None:
        """Have every drive's ~/status say its link is closed (no loop runs it now)."""
        for controller, _ in self._gates.values():
            controller.mark_closed(LINK_CLOSED)

    def _close(self) -> None:
        self._stop_loop()            # the loop's end writes the stop, then closes the link
        self.mark_unconfigured()     # ~/status says offline, and why, not the last cycle's

    def configure(self) -> TransitionCallbackReturn:
        self._allow(False)
        controllers = {name: gate[0] for name, gate in self._gates.items()}
        for controller in controllers.values():
            controller.intent.enabled = False      # nothing moves before activate
        self._start()
        timeout = max(max(c.config.action_timeout for c in controllers.values()), 1.0) + \
            max(c.addressing_interval() for c in controllers.values())
        offline = wait_online(controllers, timeout, self._keep_waiting)
        if offline:
            self._close()
            if not self._keep_waiting():
                return FAILURE  # the node goes: no error to log (and no /rosout to log to)
            return self._fail('configure', 'drive(s) not online: ' + '; '.join(
                f'{name}: {why}' for name, why in offline.items()), FAILURE)
        return SUCCESS

    def activate(self) -> TransitionCallbackReturn:
        self._allow(True)
        # auto_enable enables, unless an operator's ~/stop or ~/disable holds (until
        # ~/enable, whatever the lifecycle does meanwhile)
        enabling = {}
        for name, (controller, _) in self._gates.items():
            if controller.config.auto_enable and controller.intent.asked_stop:
                # (as the operator asked: a warning, not an error)
                self._logger.warning(f'activate: {name} not enabled: a ~/stop or ~/disable '
                                     'asked earlier holds until ~/enable')
            elif controller.config.auto_enable:
                enabling[name] = controller
        done = results({name: c.submit('enable') for name, c in enabling.items()},
                       max((c.config.action_timeout for c in enabling.values()), default=0)
                       * 2 + 1.0, self._keep_waiting)
        # An operator's ~/stop or ~/disable asked meanwhile holds, as one asked earlier
        held = {name for name, result in done.items()
                if not result.success and enabling[name].intent.asked_stop}
        for name in held:
            self._logger.warning(f'activate: {name} not enabled: a ~/stop or ~/disable asked '
                                 'meanwhile holds until ~/enable')
        problem = failures({name: r for name, r in done.items() if name not in held})
        if problem:
            self._hold()
            if not self._keep_waiting():        # (as in configure)
                return FAILURE
            return self._fail('activate', f'enable refused: {problem}', FAILURE)
        return SUCCESS

    def _hold(self) -> dict[str, ActionResult]:
        self._allow(False)
        controllers = {name: gate[0] for name, gate in self._gates.items()}
        return results({name: c.submit('stop', latch=False)
                        for name, c in controllers.items()},
                       max(c.config.stop_timeout for c in controllers.values()) + 1.0,
                       self._keep_waiting)

    def deactivate(self) -> TransitionCallbackReturn:
        problem = failures(self._hold())
        if problem and not self._keep_waiting():
            return FAILURE      # the node goes, and its loop's end writes the stop
        if problem:
            return self._fail('deactivate', f'stop not verified: {problem}', ERROR)
        return SUCCESS

    def cleanup(self) -> TransitionCallbackReturn:
        self._allow(False)
        self._close()
        return SUCCESS

    def shutdown(self) -> TransitionCallbackReturn:
        return self.cleanup()

    def error(self) -> TransitionCallbackReturn:
        self._logger.error(f'error processing ({self.last_error or "unexpected error"}): '
                           'stop written, link closed')
        return self.cleanup()


class ManagedTransitions:
    """The lifecycle callbacks of a managed node, on its ``self.transitions``.

    Mixed in before the node class and ``LifecycleNode``: each callback runs
    the transition, logs an exception as the reason for ErrorProcessing (rclpy
    would turn it into ERROR silently).
    """

    transitions: DriveTransitions

    def _refuse_unavailable_transitions(self) -> None:
        """Answer a transition the current state does not offer with success = false.

        rclpy 7.1 raises on one requested by id alone (ros2/rclpy#1209: "Transition
        is not registered"), and the exception ends the process, a running drive's
        node with it. By label it answers false, as rclcpp does either way; Nav2's
        lifecycle_manager requests by id. Called once the node is built.
        """
        service = self._service_change_state
        change_state = service.callback
        machine = self._state_machine

        def guarded(request: ChangeState.Request,
                    response: ChangeState.Response) -> ChangeState.Response:
            transition = request.transition
            if not transition.label and transition.id not in {
                    available[0] for available in machine.available_transitions}:
                self.get_logger().warning(
                    f'transition {transition.id} refused: not available from the state '
                    f'{machine.current_state[1]}')
                response.success = False
                return response
            try:
                return change_state(request, response)
            except Exception:
                if self.context.ok():
                    raise
                # Ctrl-C or SIGTERM during the transition: rclpy cannot publish its
                # end on the shut-down context (the events executor logged it as FATAL).
                # The node goes; its loop's end writes the stop.
                response.success = False
                return response
        service.callback = guarded

    def _transition(self, name: str) -> TransitionCallbackReturn:
        try:
            result = getattr(self.transitions, name)()
        except Exception as exc:  # noqa: BLE001 - an error goes to ErrorProcessing, logged
            self.transitions.last_error = f'{name} failed: {exc!r}'
            self.get_logger().error(self.transitions.last_error)
            return ERROR
        if result == SUCCESS:
            self.get_logger().info(f'{name}: done')
        return result

    def on_configure(self, state: LifecycleState) -> TransitionCallbackReturn:
        return self._transition('configure')

    def on_activate(self, state: LifecycleState) -> TransitionCallbackReturn:
        return self._transition('activate')

    def on_deactivate(self, state: LifecycleState) -> TransitionCallbackReturn:
        return self._transition('deactivate')

    def on_cleanup(self, state: LifecycleState) -> TransitionCallbackReturn:
        return self._transition('cleanup')

    def on_shutdown(self, state: LifecycleState) -> TransitionCallbackReturn:
        return self._transition('shutdown')

    def on_error(self, state: LifecycleState) -> TransitionCallbackReturn:
        return self._transition('error')

    def destroy_node(self) -> None:
        super().destroy_node()          # the node's own: stop written, link closed
        # rclpy's LifecycleNode leaves its state machine (which holds the rcl node, and
        # with it the DDS participant) alive: release it too.
        self._state_machine.destroy_when_not_in_use()

    def _release(self) -> None:
        """Destroy a node refused while being built, its state machine too (as above)."""
        super()._release()
        self._state_machine.destroy_when_not_in_use()
