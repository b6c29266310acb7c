"""sim_drive: simulated drives on an emulated line, controllable from ROS.

Parameters:
  profile            drive profile of the simulated drives
  transport          modbus_rtu (a pseudo-terminal behind ``port``), modbus_tcp
                     (a server on 127.0.0.1:``tcp_port``) or canopen (node ids = unit_ids
                     on python-can ``interface``/``channel``, default virtual/vcan0)
  port               stable path the driver opens (a symlink to the pty)
  unit_ids           slave ids served on the line, e.g. [1, 2]
  baudrate           0 = the profile's factory setting (used for wire time)
  emulate_wire_time  delay replies by their time on the wire at the baud rate
  corrupt_rate       fraction of replies corrupted (bad CRC, truncated, wrong id)
  silent_unit_ids    drives that do not hear or answer (cable unplugged);
                     can be changed at run time with `ros2 param set`
  initial_values     ["B04.02=1.0", ...] parameter values at power-up
Services:
  ~/inject_fault     vfd_ros2/srv/InjectFault
"""

from __future__ import annotations

from typing import Any

from rcl_interfaces.msg import ParameterDescriptor, SetParametersResult
from rclpy.node import Node
from rclpy.parameter import Parameter

from vfd_ros2.srv import InjectFault

from ..errors import VfdError
from ..executable import run_node
from ..profile import load_profile
from .canopen_drive import SimulatedCanBus, SimulatedCanopenDrive
from .model import SimulatedDrive
from .rtu_line import SimulatedRtuLine
from .tcp_server import SimulatedTcpServer


def parse_initial_values(items: list[str]) -> dict[str, float]:
    """["B04.02=1.0", ...] -> {"B04.02": 1.0}; ValueError names the bad item."""
    values: dict[str, float] = {}
    for item in items:
        code, sep, value = item.partition('=')
        if not sep:
            raise ValueError(f'initial value {item!r} is not CODE=VALUE')
        values[code.strip()] = float(value)
    return values


class SimDriveNode(Node):
    def __init__(self, node_name: str = 'sim_drive', **kwargs: Any) -> None:
        super().__init__(node_name, **kwargs)
        declare = self._declare
        profile = load_profile(declare('profile', 'boneng_am', 'profile of the simulated drives'))
        transport = declare('transport', 'modbus_rtu', 'line type: modbus_rtu')
        port = declare('port', '/tmp/vfd_ros2/sim/line0', 'stable path of the emulated port')
        unit_ids = list(declare('unit_ids', [1], 'slave ids served on the line'))
        baudrate = int(declare('baudrate', 0, "bit/s; 0 = the profile's factory setting"))
        wire_time = bool(declare('emulate_wire_time', False, 'delay replies by wire time'))
        corrupt = float(declare('corrupt_rate', 0.0, 'fraction of replies corrupted'))
        initial = parse_initial_values(declare(
            'initial_values', Parameter.Type.STRING_ARRAY,
            'CODE=VALUE parameter values at power-up') or [])
        declare('silent_unit_ids', Parameter.Type.INTEGER_ARRAY,
                'drives that do not hear or answer (cable unplugged)')
        tcp_port = int(declare('tcp_port', 1502, 'modbus_tcp: port on 127.0.0.1 (0 = any)'))
        if transport == 'canopen':
            self.line, where = self._canopen(profile, unit_ids, initial)
        else:
            self.line, where = self._modbus(profile, transport, port, unit_ids, initial,
                                            baudrate, wire_time, corrupt, tcp_port)
        self.add_on_set_parameters_callback(self._on_parameters)
        self.create_service(InjectFault, '~/inject_fault', self._on_inject_fault)
        self.get_logger().info(
            f'simulating {len(self.drives)} {profile.name} drive(s) {unit_ids} on {where}')

    def _canopen(self, profile: Any, unit_ids: list, initial: dict) -> tuple[Any, str]:
        """CANopen twins (node ids = unit_ids) on one python-can channel."""
        interface = self._declare('interface', 'virtual', 'canopen: python-can interface')
        channel = self._declare('channel', 'vcan0', 'canopen: CAN channel')
        object_set = self._declare('object_set', '', "canopen: object set ('' = profile's)")
        self.drives = [SimulatedCanopenDrive(profile, int(unit), object_set, initial)
                       for unit in unit_ids]
        line = SimulatedCanBus(self.drives, channel, interface).start()
        return line, f'can:{interface}:{channel}'

    def _modbus(self, profile: Any, transport: str, port: str, unit_ids: list, initial: dict,
                baudrate: int, wire_time: bool, corrupt: float,
                tcp_port: int) -> tuple[Any, str]:
        self.drives = [SimulatedDrive(profile, int(unit), initial) for unit in unit_ids]
        serial = profile.modbus.serial
        if transport == 'modbus_rtu':
            line = SimulatedRtuLine(
                self.drives, port, baudrate=baudrate or serial.baudrate, parity=serial.parity,
                stopbits=serial.stopbits, emulate_wire_time=wire_time, corrupt_rate=corrupt)
        elif transport == 'modbus_tcp':
            line = SimulatedTcpServer(self.drives, tcp_port)
        else:
            raise VfdError(f'sim_drive: transport {transport!r} is not simulated')
        line.start()
        return line, port if transport == 'modbus_rtu' else f'tcp://127.0.0.1:{line.port}'

    def _declare(self, name: str, default: Any, description: str) -> Any:
        return self.declare_parameter(
            name, default, ParameterDescriptor(description=description)).value

    def _on_parameters(self, parameters: list) -> SetParametersResult:
        for parameter in parameters:
            if parameter.name == 'silent_unit_ids':
                silent = {int(unit) for unit in parameter.value or []}
                for drive in self.drives:
                    drive.silent = drive.unit_id in silent
            elif parameter.name == 'corrupt_rate' and hasattr(self.line, 'corrupt_rate'):
                self.line.corrupt_rate = float(parameter.value)
        return SetParametersResult(successful=True)

    def _on_inject_fault(self, request: InjectFault.Request,
                         response: InjectFault.Response) -> InjectFault.Response:
        targets = [d for d in self.drives if request.unit_id in (0, d.unit_id)]
        if not targets:
            response.success = False
            response.message = f'no simulated drive with unit id {request.unit_id}'
            return response
        for drive in targets:
            drive.inject_fault(request.code, request.subcode, request.latched)
        response.success = True
        response.message = (f'fault {request.code}.{request.subcode} raised on '
                             f'{[d.unit_id for d in targets]}' if request.code else
                             'fault cause cleared: a fault reset will now succeed')
        return response

    def destroy_node(self) -> None:
        self.line.stop()
        super().destroy_node()


def main(args: list[str] | None = None) -> int:
    return run_node('sim_drive', SimDriveNode, args)
