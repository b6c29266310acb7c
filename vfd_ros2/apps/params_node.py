"""vfd_params through a running drive_node / bus_node: its services and its status.

The only module of the commissioning tools that imports rclpy (``vfd_params
--node``). The drive stays under the node's control: parameters are read and
written with ~/get_drive_parameter and ~/set_drive_parameter (the node checks
access, range and its own policy, writes RAM or EEPROM, reads back), the run
state comes from ~/status, and ~/stop holds the drive stopped (latched until
~/enable) before a restore writes and after a restore halts.
"""

from __future__ import annotations

import os
import threading
import time
from typing import Any

import rclpy
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from std_srvs.srv import Trigger

from vfd_ros2.msg import DriveStatus
from vfd_ros2.srv import GetDriveParameter, SetDriveParameter

from ..drives.base import ParameterValue
from ..errors import CommTimeout, ParameterError, TransportError
from ..profiles import load_profile
from ..ros.executable import spin_in_background


class NodeAccess:
    """A ``ParameterAccess`` through a drive node's services (see the module docstring)."""

    def __init__(self, node: str, timeout: float = 10.0) -> None:
        self.target = node.rstrip('/')
        self.timeout = timeout
        self.context = Context()
        rclpy.init(context=self.context)
        self._status: DriveStatus | None = None
        self._got_status = threading.Event()
        self._writable: dict[str, bool] = {}
        try:
            self.node = rclpy.create_node(f'vfd_params_{os.getpid()}', context=self.context)
            self.executor = SingleThreadedExecutor(context=self.context)
            self.executor.add_node(self.node)
            self.node.create_subscription(DriveStatus, f'{self.target}/status',
                                          self._on_status, 10)
            self._spin = spin_in_background(self.executor, self.context)
            self._get = self.node.create_client(GetDriveParameter,
                                                f'{self.target}/get_drive_parameter')
            self._set = self.node.create_client(SetDriveParameter,
                                                f'{self.target}/set_drive_parameter')
            self._stop = self.node.create_client(Trigger, f'{self.target}/stop')
            if not self._got_status.wait(timeout):
                raise TransportError(f'no {self.target}/status within {timeout:g} s: is the '
                                     'drive node running (and on this ROS_DOMAIN_ID)?')
            self.profile = load_profile(self._status.profile)
            self.description = f'{self.target} ({self._status.hardware_id})'
            for client, name in ((self._get, 'get_drive_parameter'),
                                 (self._set, 'set_drive_parameter'), (self._stop, 'stop')):
                if not client.wait_for_service(timeout_sec=timeout):
                    raise TransportError(f'{self.target}/{name} is not offered')
        except BaseException:
            self.close()
            raise

    def _on_status(self, status: DriveStatus) -> None:
        self._status = status
        self._got_status.set()

    def _call(self, client: Any, request: Any, what: str) -> Any:
        future = client.call_async(request)
        deadline = time.monotonic() + self.timeout
        while not future.done():
            if time.monotonic() > deadline:
                client.remove_pending_request(future)
                raise CommTimeout(f'{self.target}: no reply to {what} within {self.timeout:g} s')
            time.sleep(0.002)
        return future.result()

    # --- ParameterAccess ------------------------------------------------------------------

    def read(self, code: str) -> ParameterValue:
        parameter = self.profile.parameter(code)
        reply = self._call(self._get, GetDriveParameter.Request(name=parameter.code),
                           f'get {parameter.code}')
        if not reply.success:
            raise ParameterError(f'{parameter.code}: {reply.message}')
        self._writable[parameter.code] = reply.writable
        return ParameterValue(parameter, int(reply.raw_value), float(reply.value))

    def write(self, code: str, value: float, persistent: bool) -> tuple[ParameterValue, str]:
        parameter = self.profile.parameter(code)
        reply = self._call(self._set, SetDriveParameter.Request(
            name=parameter.code, value=float(value), persistent=persistent),
            f'set {parameter.code}')
        if not reply.success:
            raise ParameterError(reply.message)
        return ParameterValue(parameter, int(reply.raw_value), float(reply.value)), reply.message

    def refusal(self, code: str) -> str:
        if self._writable.get(code, True):
            return ''
        if any(item.code == code for item in self.profile.commissioning):
            return ('the node writes it at every connect (apply_commissioning): set '
                    'apply_commissioning false on the node to restore it')
        return 'the node does not write it'

    def running(self) -> bool | None:
        status = self._status
        if status is None or not status.online:
            return None
        return bool(status.running)

    def stop(self) -> str:
        try:
            reply = self._call(self._stop, Trigger.Request(), 'stop')
        except CommTimeout as exc:
            return f'~/stop not answered: {exc}'
        state = 'held stopped until ~/enable' if reply.success else 'NOT confirmed'
        return f'~/stop: {reply.message} ({state})'

    def close(self) -> None:
        executor = getattr(self, 'executor', None)
        node = getattr(self, 'node', None)
        spin = getattr(self, '_spin', None)
        if spin is not None:
            spin.stop()
        if executor is not None:
            executor.shutdown(timeout_sec=1.0)
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown(context=self.context)
