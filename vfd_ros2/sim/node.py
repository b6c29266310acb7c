"""sim_drive: simulated drives on an emulated line, controllable from ROS.

Parameters:
  profile            drive profile of the simulated drives
  transport          modbus_rtu (a pseudo-terminal behind ``port``), modbus_tcp
                     (a server on 127.0.0.1:``tcp_port``) or canopen (node ids = unit_ids
                     on python-can ``interface``/``channel``, default virtual/vcan0;
                     ``socketcand_port`` >= 0 serves that channel to drivers in other
                     processes as a socketcand daemon on 127.0.0.1, 0 = any free port)
  port               stable path the driver opens (a symlink to the pty)
  unit_ids           slave ids served on the line, e.g. [1, 2]
  baudrate           0 = the profile's factory setting (used for wire time)
  emulate_wire_time  delay replies by their time on the wire at the baud rate
  corrupt_rate       fraction of replies corrupted (bad CRC, truncated, wrong id)
  late_rate          fraction of replies sent late, late_delay [min, max] s after
                     the request (set it just beyond the driver's transport.timeout);
                     late_deaf: the slave drops what it hears meanwhile
  wrong_echo_rate    fraction of write replies naming another value / count
  trailing_rate      fraction of replies followed by stray bytes
  silent_unit_ids    drives that do not hear or answer (cable unplugged)
  refused            ["A00.15", ...] registers every drive refuses (illegal address)
  initial_values     ["B04.02=1.0", ...] parameter values at power-up
  shutdown_grace     s the line stays open after Ctrl-C while drivers still talk
The line faults, silent_unit_ids and refused can be changed at run time with
`ros2 param set`, in both directions (an empty list "[]" clears them).
Services:
  ~/inject_fault     vfd_ros2/srv/InjectFault
"""

from __future__ import annotations

import math
import sys
import time
from typing import Any

from rcl_interfaces.msg import ParameterDescriptor, SetParametersResult
from rclpy.node import Node

from vfd_ros2.srv import InjectFault

from ..errors import VfdError
from ..profiles import load_profile
from ..ros.executable import only_ros_arguments, run_node
from ..ros.parameters import LIVE_NOTE, describe_read_only_except, descriptor
from .canopen_drive import SimulatedCanBus, SimulatedCanopenDrive
from .model import SimulatedDrive
from .rtu_line import LineFaults, SimulatedRtuLine
from .tcp_server import SimulatedTcpServer

#: s without a request after which the line counts as quiet at shutdown
QUIET_LINE = 0.5


def parse_initial_values(items: list[str]) -> dict[str, float]:
    """["B04.02=1.0", ...] -> {"B04.02": 1.0}; ValueError names the bad item."""
    values: dict[str, float] = {}
    for item in items:
        code, sep, value = item.partition('=') if isinstance(item, str) else ('', '', '')
        if not sep:
            raise ValueError(f'initial value {item!r} is not CODE=VALUE')
        values[code.strip()] = float(value)
    return values


class SimDriveNode(Node):
    def __init__(self, node_name: str = 'sim_drive', **kwargs: Any) -> None:
        super().__init__(node_name, **kwargs)
        #: the parameters ``_apply`` changes at run time (the others: at start-up only)
        self.live_parameters: list[str] = []
        self.socketcand: Any = None     # canopen with socketcand_port: the daemon it serves
        declare = self._declare
        profile = load_profile(declare('profile', 'boneng_am', 'profile of the simulated drives'))
        transport = declare('transport', 'modbus_rtu',
                            'line type: modbus_rtu, modbus_tcp or canopen')
        port = declare('port', '/tmp/vfd_ros2/sim/line0', 'stable path of the emulated port')
        unit_ids = list(declare('unit_ids', [1], 'slave ids served on the line'))
        baudrate = int(declare('baudrate', 0, "bit/s; 0 = the profile's factory setting"))
        wire_time = bool(declare('emulate_wire_time', False, 'delay replies by wire time'))
        corrupt = float(declare('corrupt_rate', 0.0, 'fraction of replies corrupted (RTU)',
                                0.0, 1.0, live=True))
        # A value, if empty: a parameter declared without one answers no get_parameters
        # request that names it, not even one for all of them (ros2 param dump).
        initial = parse_initial_values(self.declare_parameter(
            'initial_values', [], ParameterDescriptor(
                description='CODE=VALUE parameter values at power-up, e.g. ["B04.02=1.0"]',
                dynamic_typing=True)).value)
        self._declare_list('silent_unit_ids', 'drives that do not hear or answer (cable '
                           'unplugged), e.g. [2]; [] plugs every drive back')
        self._declare_list('refused', 'parameter codes every drive answers with "illegal '
                           'address", e.g. ["A00.15"]')
        for name, default, description in (
                ('late_rate', 0.0, 'fraction of replies sent late (RTU)'),
                ('late_delay', [0.12, 0.14], 's [min, max] from the request to a late reply'),
                ('late_deaf', False, 'a late slave drops the requests it hears meanwhile'),
                ('wrong_echo_rate', 0.0, 'fraction of write echoes naming another value (RTU)'),
                ('trailing_rate', 0.0, 'fraction of replies followed by stray bytes (RTU)')):
            declare(name, default, description, *((0.0, 1.0) if name.endswith('_rate')
                                                  else (None, None)), live=True)
        tcp_port = int(declare('tcp_port', 1502, 'modbus_tcp: port on 127.0.0.1 (0 = any)'))
        self.shutdown_grace = float(declare(
            'shutdown_grace', 3.0, 's the line stays open after Ctrl-C/SIGTERM while the host '
            'still talks (its drivers write their stops); it closes once the line is quiet '
            f'for {QUIET_LINE:g} s', 0.0, 60.0))
        if transport == 'canopen':
            self.line, where = self._canopen(profile, unit_ids, initial)
        else:
            self.line, where = self._modbus(profile, transport, port, unit_ids, initial,
                                            baudrate, wire_time, corrupt, tcp_port)
        describe_read_only_except(self, self.live_parameters)
        self.add_on_set_parameters_callback(self._on_parameters)
        self._apply([self.get_parameter(name) for name in self.live_parameters])
        self.create_service(InjectFault, '~/inject_fault', self._on_inject_fault)
        self.get_logger().info(
            f'simulating {len(self.drives)} {profile.name} drive(s) {unit_ids} on {where}')

    def _canopen(self, profile: Any, unit_ids: list, initial: dict) -> tuple[Any, str]:
        """CANopen twins (node ids = unit_ids) on one python-can channel."""
        interface = self._declare('interface', 'virtual', 'canopen: python-can interface')
        channel = self._declare('channel', 'vcan0', 'canopen: CAN channel')
        object_set = self._declare('object_set', '', "canopen: object set ('' = profile's)")
        socketcand_port = int(self._declare(
            'socketcand_port', -1, 'canopen: serve the channel to drivers in other processes '
            "as a socketcand daemon on 127.0.0.1 (bus name = channel): python-can's virtual "
            'interface does not leave this process; -1 = off, 0 = any free port', -1, 65535))
        self.drives = [SimulatedCanopenDrive(profile, int(unit), object_set, initial)
                       for unit in unit_ids]
        line = SimulatedCanBus(self.drives, channel, interface).start()
        where = f'can:{interface}:{channel}'
        if socketcand_port >= 0:
            from .socketcand_server import SocketcandServer
            try:
                self.socketcand = SocketcandServer(channel, interface,
                                                   port=socketcand_port).start()
            except Exception:
                line.stop()
                raise
            where += (f', served as socketcand on 127.0.0.1:{self.socketcand.port} (a '
                      'driver: transport.interface socketcand, transport.channel '
                      f'{channel}, transport.can_options \'{{"host": "127.0.0.1", "port": '
                      f'{self.socketcand.port}, "tcp_tune": true}}\')')
        return line, where

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

    def _declare(self, name: str, default: Any, description: str,
                 minimum: float | None = None, maximum: float | None = None,
                 live: bool = False) -> Any:
        # Only what _apply handles is live; everything else is read-only once running.
        if live:
            self.live_parameters.append(name)
        return self.declare_parameter(
            name, default, descriptor(description, default, minimum, maximum, live)).value

    def _declare_list(self, name: str, description: str) -> None:
        # Dynamically typed: "[]" on the command line has no element type (ros2cli sends
        # a bool array, YAML files may give a string or byte array), and must clear the
        # list as well as "[2]" sets it.
        self.live_parameters.append(name)
        self.declare_parameter(name, [], ParameterDescriptor(
            description=description + LIVE_NOTE, dynamic_typing=True))

    def _on_parameters(self, parameters: list) -> SetParametersResult:
        try:
            self._apply(parameters)
        except (ValueError, TypeError, VfdError) as exc:
            return SetParametersResult(successful=False, reason=str(exc))
        return SetParametersResult(successful=True)

    def _apply(self, parameters: list) -> None:
        """Apply run-time settings; raises before changing anything on a bad value."""
        faults = getattr(self.line, 'faults', None) or LineFaults()    # (inert off RTU)
        rtu = getattr(self.line, 'faults', None) is not None

        def no_faults(name: str, active: bool) -> None:
            if active and not rtu:
                raise ValueError(f'{name}: line faults are simulated on modbus_rtu lines only')
        changes = []
        for parameter in parameters:
            name, value = parameter.name, parameter.value
            if value is None and name in self.live_parameters:
                # (NOT_SET would remove a dynamically typed one: no way back)
                raise ValueError(f'{name} cannot be unset ("[]" clears a list)')
            if name == 'silent_unit_ids':
                units = {d.unit_id for d in self.drives}
                if isinstance(value, (str, int, float)) or any(
                        isinstance(u, (bool, float)) or u not in units for u in value):
                    shown = value if isinstance(value, (str, int, float)) else list(value)
                    raise ValueError(f'silent_unit_ids: {shown!r} is not a list of the units '
                                     f'on this line ({sorted(units)})')
                silent = set(value)
                changes.append(lambda s=silent: [setattr(d, 'silent', d.unit_id in s)
                                                 for d in self.drives])
            elif name == 'refused':
                codes = [str(code) for code in (value or [])]
                if codes and not all(hasattr(d, 'refuse') for d in self.drives):
                    raise ValueError('refused: these simulated drives cannot refuse registers')
                for drive in self.drives:
                    for code in codes:
                        drive.profile.parameter(code)          # unknown code: refused
                changes.append(lambda c=codes: [d.refuse(c) for d in self.drives
                                                if hasattr(d, 'refuse')])
            elif name in ('corrupt_rate', 'late_rate', 'wrong_echo_rate', 'trailing_rate'):
                rate = float(value)
                if not 0.0 <= rate <= 1.0:
                    raise ValueError(f'{name} must be within 0..1, got {rate}')
                no_faults(name, rate != 0.0)
                changes.append(lambda n=name, r=rate: setattr(faults, n, r))
            elif name == 'late_delay':
                low, high = (float(v) for v in value)
                if not 0.0 <= low <= high < math.inf:
                    raise ValueError('late_delay must be [min, max] with 0 <= min <= max')
                no_faults(name, False)
                changes.append(lambda d=(low, high): setattr(faults, 'late_delay', d))
            elif name == 'late_deaf':
                no_faults(name, bool(value))
                changes.append(lambda v=bool(value): setattr(faults, 'late_deaf', v))
            else:
                raise ValueError(f'{name} cannot be changed at run time')
        for change in changes:
            change()

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

    def _activity(self) -> int:
        """Return the requests (Modbus) or frames (CANopen) the simulated drives received.

        On an RTU line, also those for silent or absent drives, and garbage: a host
        still trying a silent drive is not quiet (the line closed under a bus still
        writing its running drives' stops).
        """
        line = getattr(self.line, 'stats', None)
        return sum(getattr(d, 'requests', 0) + getattr(d, 'rpdos_received', 0) +
                   getattr(d, 'heartbeat_events', 0) for d in self.drives) + \
            getattr(line, 'frames', 0) + getattr(line, 'crc_errors', 0)

    def serve_until_quiet(self, grace: float, quiet: float = 0.5) -> float:
        """Keep serving until the host has been silent for ``quiet`` s (at most ``grace`` s).

        Ctrl-C reaches a launch file's processes in the same instant: the drivers
        write their stops as they shut down, so the line stays open for them.
        Returns the seconds waited.
        """
        start = time.monotonic()
        last, changed = self._activity(), start
        while time.monotonic() - start < grace:
            time.sleep(0.02)
            now = self._activity()
            if now != last:
                last, changed = now, time.monotonic()
            elif time.monotonic() - changed >= quiet:
                break
        return time.monotonic() - start

    def exit_report(self) -> list[str]:
        """Return one line per drive: what the host left it doing when the line closed."""
        return [f'unit {d.unit_id} at exit: run requested '
                f'{"yes" if getattr(d, "run_requested", False) else "no"}, speed '
                f'{getattr(d, "speed_rpm", 0.0):.1f} rpm' for d in self.drives]

    def _say(self, text: str) -> None:
        if self.context.ok():
            self.get_logger().info(text)
        else:       # /rosout is gone with the context: the log line still goes out
            print(f'[{self.get_fully_qualified_name()}] {text}', file=sys.stderr, flush=True)

    def destroy_node(self) -> None:
        if not self.context.ok():
            # Shut down by a signal (Ctrl-C, launch's SIGINT/SIGTERM), not by a caller.
            waited = self.serve_until_quiet(self.shutdown_grace, QUIET_LINE)
            self._say(f'line quiet after {waited:.2f} s: closing it')
        for line in self.exit_report():
            self._say(line)
        if self.socketcand is not None:
            self.socketcand.stop()
        self.line.stop()
        super().destroy_node()


def make_sim_drive_node(args: list[str] | None = None) -> SimDriveNode:
    only_ros_arguments(args)
    return SimDriveNode()


def main(args: list[str] | None = None) -> int:
    return run_node('sim_drive', lambda: make_sim_drive_node(args), args,
                    cleanup='the line is served until the driver has stopped the drives')


if __name__ == '__main__':      # python -m, as well as the ros2 run launcher
    raise SystemExit(main())
