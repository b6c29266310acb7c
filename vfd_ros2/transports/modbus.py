"""Modbus RTU and Modbus TCP transports on pymodbus' synchronous clients."""

from __future__ import annotations

import logging
from typing import Any, Callable, Mapping

from pymodbus import FramerType
from pymodbus.client import ModbusSerialClient, ModbusTcpClient
from pymodbus.exceptions import ConnectionException, ModbusException, ModbusIOException
from pymodbus.pdu import ExceptionResponse

from ..errors import BadFrame, CommTimeout, ProtocolException, TransportError
from ..profile import Profile
from .base import RegisterTransport, TransportParameter

# The driver counts and reports every failed exchange itself (status counters,
# diagnostics); pymodbus' own error logging would repeat each one per cycle.
logging.getLogger('pymodbus').setLevel(logging.CRITICAL)

#: Modbus exception codes as the specification defines them; a profile's own
#: meanings (some drives use 3 for "CRC error") take precedence.
STANDARD_EXCEPTIONS: dict[int, str] = {
    1: 'illegal function',
    2: 'illegal data address',
    3: 'illegal data value',
    4: 'server device failure',
    5: 'acknowledge',
    6: 'server device busy',
    8: 'memory parity error',
    10: 'gateway path unavailable',
    11: 'gateway target device failed to respond',
}


class _PymodbusTransport(RegisterTransport):
    """What RTU and TCP share: request execution, error classification, counters."""

    def __init__(self, exception_codes: Mapping[int, str]) -> None:
        super().__init__()
        self._exception_text = {**STANDARD_EXCEPTIONS, **exception_codes}
        self._received = b''
        self._client: ModbusSerialClient | ModbusTcpClient = self._make_client()

    def _make_client(self) -> ModbusSerialClient | ModbusTcpClient:
        raise NotImplementedError

    def _trace_packet(self, sending: bool, data: bytes) -> bytes:
        # pymodbus hands over the accumulated receive buffer; remembering it
        # tells a silent drive (timeout) from a garbled reply (bad frame).
        if sending:
            self.stats.bytes_sent += len(data)
        else:
            self._received = data
        return data

    def open(self) -> None:
        try:
            connected = self._client.connect()
        except (OSError, ModbusException) as exc:
            self.stats.connect_failures += 1
            raise TransportError(f'cannot open {self.description}: {exc}') from exc
        if not connected:
            self.stats.connect_failures += 1
            raise TransportError(f'cannot open {self.description}')

    def close(self) -> None:
        try:
            self._client.close()
        except (OSError, ModbusException):
            pass

    def _execute(self, what: str, call: Callable[[], Any]) -> Any:
        self.open()
        self._received = b''
        try:
            reply = call()
        except ConnectionException as exc:
            self.stats.connect_failures += 1
            self.close()
            raise TransportError(f'{what}: link lost ({self.description}): {exc}') from exc
        except ModbusIOException as exc:
            if self._received:
                self.stats.bad_frames += 1
                raise BadFrame(f'{what}: malformed reply {self._received.hex(" ")}') from exc
            self.stats.timeouts += 1
            raise CommTimeout(f'{what}: no reply from {self.description}') from exc
        except (ModbusException, OSError, ValueError) as exc:
            self.stats.bad_frames += 1
            self.close()
            raise TransportError(f'{what}: {exc}') from exc
        finally:
            self.stats.bytes_received += len(self._received)
        if isinstance(reply, ExceptionResponse):
            self.stats.exceptions += 1
            code = reply.exception_code
            raise ProtocolException(code, self._exception_text.get(code, 'unknown exception'),
                                    what)
        if reply.isError():
            self.stats.bad_frames += 1
            raise BadFrame(f'{what}: error reply {reply}')
        self.stats.transactions += 1
        return reply

    def read_registers(self, unit: int, address: int, count: int) -> list[int]:
        what = f'read {count} @ {address:#06x} (unit {unit})'
        reply = self._execute(what, lambda: self._client.read_holding_registers(
            address, count=count, device_id=unit))
        if len(reply.registers) != count:
            self.stats.bad_frames += 1
            raise BadFrame(f'{what}: got {len(reply.registers)} registers')
        return list(reply.registers)

    def write_register(self, unit: int, address: int, value: int) -> None:
        what = f'write {value:#06x} @ {address:#06x} (unit {unit})'
        reply = self._execute(what, lambda: self._client.write_register(
            address, value & 0xFFFF, device_id=unit))
        if reply.address != address:
            self.stats.bad_frames += 1
            raise BadFrame(f'{what}: echo names address {reply.address:#06x}')

    def write_registers(self, unit: int, address: int, values: list[int]) -> None:
        what = f'write {len(values)} @ {address:#06x} (unit {unit})'
        self._execute(what, lambda: self._client.write_registers(
            address, [v & 0xFFFF for v in values], device_id=unit))


class ModbusRtuTransport(_PymodbusTransport):
    """Modbus RTU over a serial port (RS-485 adapter, or a pseudo-terminal)."""

    parameters = (
        TransportParameter('port', '/dev/ttyUSB0', 'serial device of the RS-485 line'),
        TransportParameter('baudrate', 0, "bit/s; 0 = the drive's factory setting"),
        TransportParameter('parity', '', "N, E or O; empty = the drive's factory setting"),
        TransportParameter('stopbits', 0, "1 or 2; 0 = the drive's factory setting"),
        TransportParameter('timeout', 0.1, 'reply timeout in seconds'),
    )

    def __init__(self, port: str, baudrate: int = 19200, parity: str = 'N',
                 stopbits: int = 1, bytesize: int = 8, timeout: float = 0.1,
                 exception_codes: Mapping[int, str] | None = None) -> None:
        self.port = port
        self.baudrate = baudrate
        self.parity = parity
        self.stopbits = stopbits
        self.bytesize = bytesize
        self.timeout = timeout
        super().__init__(exception_codes or {})

    @classmethod
    def from_settings(cls, settings: Mapping[str, Any], profile: Profile) -> 'ModbusRtuTransport':
        factory = profile.modbus.serial
        return cls(port=str(settings['port']),
                   baudrate=int(settings['baudrate']) or factory.baudrate,
                   parity=str(settings['parity']) or factory.parity,
                   stopbits=int(settings['stopbits']) or factory.stopbits,
                   bytesize=factory.bytesize, timeout=float(settings['timeout']),
                   exception_codes=profile.modbus.exception_codes)

    def _make_client(self) -> ModbusSerialClient:
        return ModbusSerialClient(
            self.port, framer=FramerType.RTU, baudrate=self.baudrate, parity=self.parity,
            stopbits=self.stopbits, bytesize=self.bytesize, timeout=self.timeout, retries=0,
            trace_packet=self._trace_packet)

    @property
    def description(self) -> str:
        return f'{self.port}@{self.baudrate}-{self.bytesize}{self.parity}{self.stopbits}'

    def wire_seconds(self, byte_count: int, frames: int) -> float:
        """Characters on the wire plus the 3.5-character silence before each frame."""
        bits = 1 + self.bytesize + (0 if self.parity.upper() == 'N' else 1) + self.stopbits
        return (byte_count + 3.5 * frames) * bits / self.baudrate


class ModbusTcpTransport(_PymodbusTransport):
    """Modbus TCP (e.g. a drive's Ethernet option card)."""

    parameters = (
        TransportParameter('host', '127.0.0.1', "IP address of the drive's Modbus TCP card"),
        TransportParameter('port', 502, 'TCP port'),
        TransportParameter('timeout', 0.2, 'reply timeout in seconds'),
    )

    def __init__(self, host: str, port: int = 502, timeout: float = 0.2,
                 exception_codes: Mapping[int, str] | None = None) -> None:
        self.host = host
        self.port = port
        self.timeout = timeout
        super().__init__(exception_codes or {})

    @classmethod
    def from_settings(cls, settings: Mapping[str, Any], profile: Profile) -> 'ModbusTcpTransport':
        return cls(host=str(settings['host']), port=int(settings['port']),
                   timeout=float(settings['timeout']),
                   exception_codes=profile.modbus.exception_codes)

    def _make_client(self) -> ModbusTcpClient:
        return ModbusTcpClient(self.host, port=self.port, timeout=self.timeout, retries=0,
                               reconnect_delay=0, trace_packet=self._trace_packet)

    @property
    def description(self) -> str:
        return f'tcp://{self.host}:{self.port}'
