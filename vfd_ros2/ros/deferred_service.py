"""Services whose answer comes later, from another thread, on any executor.

A drive's services (enable, set a parameter, ...) are answered by the control
thread once the drive has confirmed the change, while the executor goes on
serving commands and status. rclpy's coroutine callbacks would do that on the
``SingleThreadedExecutor``, but the ``EventsExecutor`` of the Jazzy wheels does
not await them (ros2/rclpy#1473, fixed in later Jazzy releases). Here the
callback returns a ``Deferred`` instead of a response; both executors hand it,
with the request's header, to the service's ``send_response`` (an attribute
they look up on the service object), which this module wraps: the real
response goes out when the ``Deferred`` is completed, from whichever thread
completes it, exactly once.
"""

from __future__ import annotations

import threading
from typing import Any, Callable

from rclpy.node import Node
from rclpy.qos import QoSProfile
from rclpy.service import Service


class Deferred:
    """A response that is not known yet; ``complete`` sends it (once)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._send: Callable[[Any], None] | None = None
        self._response: Any = None
        self._done = False

    def complete(self, response: Any) -> None:
        """Send ``response`` now if the request's header arrived, else as soon as it does."""
        with self._lock:
            if self._done:
                return
            self._done, self._response, send = True, response, self._send
        if send is not None:
            send(response)

    def _attach(self, send: Callable[[Any], None]) -> None:
        with self._lock:
            self._send, done, response = send, self._done, self._response
        if done:
            send(response)


def create_deferred_service(node: Node, srv_type: Any, name: str,
                            callback: Callable[[Any, Any], Any],
                            qos_profile: QoSProfile) -> Service:
    """``node.create_service`` whose ``callback`` may return a ``Deferred``."""
    service = node.create_service(srv_type, name, callback, qos_profile=qos_profile)
    send_now = service.send_response

    def send_response(response: Any, header: Any) -> None:
        if not isinstance(response, Deferred):
            send_now(response, header)
            return

        def send_later(final: Any) -> None:
            try:
                send_now(final, header)
            except Exception:  # noqa: BLE001 - the node was destroyed meanwhile: no one to tell
                pass
        response._attach(send_later)  # noqa: SLF001

    service.send_response = send_response
    return service
