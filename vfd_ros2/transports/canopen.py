"""CANopen (CiA 301) transport: SDO, PDO, NMT, heartbeat and EMCY on python-can + canopen.

Moves raw object values to and from one node; knows nothing of drives or
scaling (``vfd_ros2.drives.canopen`` does). The bus is opened per transport, so
several drives on one physical bus are independent: a dead node only costs
its own controller its timeouts.

- SDO: expedited transfers through the ``canopen`` library's SDO client; abort
  codes are raised as ``SdoAbort`` (a ``ProtocolException``) with the CiA 301 text.
- PDO: configured over SDO by the drive at connect; RPDOs are sent as raw frames,
  TPDOs are received into a cache (no per-cycle round trip).
- NMT commands; boot-up and heartbeat consumed on 0x700 + id: ``check_alive``
  raises ``CommTimeout`` when no heartbeat arrived within the consumer timeout,
  and ``TransportError`` after a boot-up (the node reset and lost its configuration).
- EMCY frames on 0x80 + id are decoded and kept for the drive.
"""

from __future__ import annotations

import enum
import logging
import struct
import threading
import time
from dataclasses import dataclass
from typing import Any, Callable, Mapping

from ..errors import CommTimeout, ParameterError, ProtocolException, TransportError
from ..protocol.values import ValueType
from .base import Transport, TransportParameter

log = logging.getLogger(__name__)

#: SDO abort codes, CiA 301 v4.2 table 22 (the Kinco manual's list, L898-L914, is a subset)
SDO_ABORT_CODES: dict[int, str] = {
    0x05030000: 'Toggle bit not alternated',
    0x05040000: 'SDO protocol timed out',
    0x05040001: 'Client/server command specifier not valid or unknown',
    0x05040002: 'Invalid block size',
    0x05040003: 'Invalid sequence number',
    0x05040004: 'CRC error',
    0x05040005: 'Out of memory',
    0x06010000: 'Unsupported access to an object',
    0x06010001: 'Attempt to read a write only object',
    0x06010002: 'Attempt to write a read only object',
    0x06020000: 'Object does not exist in the object dictionary',
    0x06040041: 'Object cannot be mapped to the PDO',
    0x06040042: 'The number and length of the objects to be mapped would exceed PDO length',
    0x06040043: 'General parameter incompatibility reason',
    0x06040047: 'General internal incompatibility in the device',
    0x06060000: 'Access failed due to a hardware error',
    0x06070010: 'Data type does not match, length of service parameter does not match',
    0x06070012: 'Data type does not match, length of service parameter too high',
    0x06070013: 'Data type does not match, length of service parameter too low',
    0x06090011: 'Sub-index does not exist',
    0x06090030: 'Invalid value for parameter (download only)',
    0x06090031: 'Value of parameter written too high (download only)',
    0x06090032: 'Value of parameter written too low (download only)',
    0x06090036: 'Maximum value is less than minimum value',
    0x060A0023: 'Resource not available: SDO connection',
    0x08000000: 'General error',
    0x08000020: 'Data cannot be transferred or stored to the application',
    0x08000021: 'Data cannot be transferred or stored to the application because of local '
                'control',
    0x08000022: 'Data cannot be transferred or stored to the application because of the '
                'present device state',
    0x08000023: 'Object dictionary dynamic generation fails or no object dictionary is present',
    0x08000024: 'No data available',
}


def abort_text(code: int) -> str:
    return SDO_ABORT_CODES.get(code, f'unknown SDO abort code 0x{code:08X}')


class SdoAbort(ProtocolException):
    """The node answered an SDO request with an abort code (CiA 301)."""

    def __init__(self, code: int, request: str = '') -> None:
        super().__init__(code, abort_text(code), request)
        where = f' to {request}' if request else ''
        self.args = (f'SDO abort 0x{code:08X} ({self.text}){where}',)

    def __str__(self) -> str:
        return self.args[0]


class NmtCommand(enum.IntEnum):
    """NMT command specifiers (CiA 301 7.2.8.3.1; Kinco L985-L997)."""

    START = 0x01
    STOP = 0x02
    ENTER_PRE_OPERATIONAL = 0x80
    RESET_NODE = 0x81
    RESET_COMMUNICATION = 0x82


class NmtState(enum.IntEnum):
    """NMT states as reported in heartbeat frames."""

    BOOT_UP = 0x00
    STOPPED = 0x04
    OPERATIONAL = 0x05
    PRE_OPERATIONAL = 0x7F


@dataclass(frozen=True)
class Emcy:
    """One EMCY frame: error code, error register and the 5 manufacturer bytes."""

    code: int
    register: int
    data: bytes
    timestamp: float

    @classmethod
    def decode(cls, data: bytes, timestamp: float) -> 'Emcy':
        padded = bytes(data) + bytes(8 - len(data)) if len(data) < 8 else bytes(data)
        code, register = struct.unpack_from('<HB', padded)
        return cls(code, register, padded[3:8], timestamp)


_STRUCT = {
    ValueType.UINT8: '<B', ValueType.INT8: '<b', ValueType.UINT16: '<H',
    ValueType.INT16: '<h', ValueType.UINT32: '<I', ValueType.INT32: '<i',
}


def encode_value(value_type: ValueType, raw: int) -> bytes:
    low, high = value_type.bounds
    if not low <= raw <= high:
        raise ParameterError(f'raw value {raw} does not fit {value_type.value}')
    return struct.pack(_STRUCT[value_type], raw)


def decode_value(value_type: ValueType, data: bytes) -> int:
    size = value_type.bits // 8
    if len(data) < size:
        raise TransportError(f'{len(data)} bytes received for a {value_type.value}')
    return struct.unpack(_STRUCT[value_type], bytes(data[:size]))[0]


class CanopenTransport(Transport):
    """One CANopen node on a python-can bus (socketcan, virtual, ...)."""

    parameters = (
        TransportParameter('interface', 'socketcan',
                           'python-can interface: socketcan, virtual, ...'),
        TransportParameter('channel', 'can0', 'CAN channel (virtual: any name shared in-process)'),
        TransportParameter('bitrate', 0, 'bit/s; 0 = leave the interface as configured'),
        TransportParameter('eds_file', '', 'optional EDS/DCF of the node (SDO type hints)'),
        TransportParameter('timeout', 0.1, 's per SDO reply'),
        TransportParameter('heartbeat_ms', 0, "producer heartbeat written to 0x1017; 0 = the "
                           "profile's"),
        TransportParameter('heartbeat_timeout', 0.0, 's without heartbeat before offline; 0 = '
                           "the profile's factor x heartbeat_ms"),
    )
    shared_by_drives = False   # one handle per node; bus_node opens one per drive

    def __init__(self, interface: str = 'virtual', channel: str = 'vcan0', bitrate: int = 0,
                 timeout: float = 0.1, eds_file: str = '', heartbeat_ms: int = 0,
                 heartbeat_timeout: float = 0.0,
                 bus_factory: Callable[..., Any] | None = None) -> None:
        super().__init__()
        if not timeout > 0:
            raise ParameterError(f'transport.timeout must be > 0, got {timeout}')
        self.interface = interface
        self.channel = channel
        self.bitrate = int(bitrate)
        self.timeout = float(timeout)
        self.eds_file = eds_file
        self.heartbeat_ms = int(heartbeat_ms)
        self.heartbeat_timeout = float(heartbeat_timeout)
        self._bus_factory = bus_factory
        self.node_id = 0
        self.network: Any = None
        self.node: Any = None
        self._lock = threading.Lock()
        self._tpdo: dict[int, tuple[bytes, float]] = {}
        self._last_heartbeat: float | None = None
        self._nmt_state: NmtState | None = None
        self._booted = False
        self._not_operational = 0          # consecutive heartbeats not reporting Operational
        self._emcy: list[Emcy] = []
        self._supervise_timeout = 0.0
        self._supervise_from = 0.0

    @classmethod
    def from_settings(cls, settings: Mapping[str, Any]) -> 'CanopenTransport':
        return cls(interface=str(settings.get('interface', 'socketcan')),
                   channel=str(settings.get('channel', 'can0')),
                   bitrate=int(settings.get('bitrate', 0) or 0),
                   timeout=float(settings.get('timeout', 0.1) or 0.1),
                   eds_file=str(settings.get('eds_file', '') or ''),
                   heartbeat_ms=int(settings.get('heartbeat_ms', 0) or 0),
                   heartbeat_timeout=float(settings.get('heartbeat_timeout', 0.0) or 0.0))

    @property
    def description(self) -> str:
        return f'can:{self.interface}:{self.channel}'

    # --- link -----------------------------------------------------------------------

    def attach(self, node_id: int) -> None:
        """Select the node this transport talks to (called once by the drive)."""
        if not 1 <= node_id <= 127:
            raise ParameterError(f'CANopen node id {node_id} is outside 1..127')
        self.node_id = node_id

    def open(self) -> None:
        if self.network is not None:
            return
        import can
        import canopen  # imported here: the Modbus-only installs need not load it
        kwargs: dict[str, Any] = {'interface': self.interface, 'channel': self.channel}
        if self.bitrate:
            kwargs['bitrate'] = self.bitrate
        try:
            bus = (self._bus_factory or can.Bus)(**kwargs)
        except (can.CanError, OSError, ValueError, ImportError) as exc:
            self.stats.connect_failures += 1
            raise TransportError(f'cannot open CAN {self.description}: {exc}') from exc
        network = canopen.Network(bus)
        network.NOTIFIER_SHUTDOWN_TIMEOUT = 1.0
        od: Any = canopen.ObjectDictionary()
        if self.eds_file:
            try:
                od = canopen.import_od(self.eds_file, self.node_id)
            except Exception as exc:  # noqa: BLE001 - any parse error of a user file
                bus.shutdown()
                raise TransportError(f'cannot load EDS {self.eds_file}: {exc}') from exc
        node = canopen.RemoteNode(self.node_id, od)
        node.sdo.RESPONSE_TIMEOUT = self.timeout
        node.sdo.MAX_RETRIES = 1
        network.add_node(node)
        network.subscribe(0x700 + self.node_id, self._on_heartbeat)
        network.subscribe(0x80 + self.node_id, self._on_emcy)
        for cob in (0x180, 0x280, 0x380, 0x480):
            network.subscribe(cob + self.node_id, self._on_tpdo)
        with self._lock:
            self._tpdo.clear()
            self._last_heartbeat = None
            self._nmt_state = None
            self._booted = False
            self._supervise_timeout = 0.0
        network.connect()
        self.network, self.node = network, node

    def close(self) -> None:
        network, self.network, self.node = self.network, None, None
        if network is None:
            return
        try:
            network.disconnect()
        except Exception as exc:  # noqa: BLE001 - close never raises
            log.debug('closing %s: %s', self.description, exc)

    def _require(self) -> Any:
        if self.network is None:
            raise TransportError(f'{self.description} is not open')
        return self.node

    # --- SDO ------------------------------------------------------------------------

    def read_object(self, index: int, subindex: int, value_type: ValueType) -> int:
        """Expedited SDO upload of one typed value."""
        node = self._require()
        data = self._sdo(f'read 0x{index:04X}:{subindex:02X}',
                         lambda: node.sdo.upload(index, subindex))
        return decode_value(value_type, data)

    def write_object(self, index: int, subindex: int, value_type: ValueType, raw: int) -> None:
        """Expedited SDO download of one typed value (1, 2 or 4 bytes)."""
        node = self._require()
        data = encode_value(value_type, raw)
        self._sdo(f'write 0x{index:04X}:{subindex:02X} = {raw}',
                  lambda: node.sdo.download(index, subindex, data))

    def _sdo(self, what: str, call: Callable[[], Any]) -> Any:
        """One SDO exchange; aborts, silence and bus errors become the driver's errors."""
        import canopen
        self.stats.transactions += 1
        try:
            return call()
        except canopen.SdoAbortedError as exc:
            self.stats.exceptions += 1
            raise SdoAbort(exc.code, what) from exc
        except canopen.SdoCommunicationError as exc:
            self._count_comm_error(exc)
            raise CommTimeout(f'no SDO reply from node {self.node_id} to {what}: {exc}') from exc
        except Exception as exc:  # noqa: BLE001 - can.CanError and library errors
            self.stats.bad_frames += 1
            raise TransportError(f'{what} on node {self.node_id} failed: {exc}') from exc

    def _count_comm_error(self, exc: Exception) -> None:
        if 'No SDO response' in str(exc) or 'timed out' in str(exc).lower():
            self.stats.timeouts += 1
        else:
            self.stats.bad_frames += 1

    # --- PDO / NMT --------------------------------------------------------------------

    def send(self, cob_id: int, data: bytes) -> None:
        """Send one raw frame (RPDO, NMT)."""
        import can
        self._require()
        self.stats.transactions += 1
        try:
            self.network.send_message(cob_id, data)
        except (can.CanError, RuntimeError, OSError) as exc:
            self.stats.bad_frames += 1
            raise TransportError(f'cannot send 0x{cob_id:03X} on {self.description}: '
                                 f'{exc}') from exc

    def nmt(self, command: NmtCommand) -> None:
        self.send(0x000, bytes((int(command), self.node_id)))

    def tpdo(self, number: int) -> tuple[bytes, float] | None:
        """Last data of TPDO ``number`` (1..4) and when it arrived, or None."""
        with self._lock:
            return self._tpdo.get(number)

    def supervise(self, timeout: float) -> None:
        """Start the host-side heartbeat consumer (0 = off)."""
        with self._lock:
            self._supervise_timeout = timeout
            self._supervise_from = time.monotonic()
            self._booted = False
            self._not_operational = 0

    def check_alive(self) -> NmtState | None:
        """Raise when the node's heartbeat is lost or it rebooted; return its NMT state.

        The state is returned only once two heartbeats in a row agree (one may have
        been in flight when an NMT command was sent).
        """
        with self._lock:
            timeout = self._supervise_timeout
            last = self._last_heartbeat
            booted = self._booted
            state = self._nmt_state if (self._nmt_state is NmtState.OPERATIONAL or
                                        self._not_operational >= 2) else None
            since = self._supervise_from
        if booted:
            raise TransportError(f'node {self.node_id} sent a boot-up: it reset and must be '
                                 're-configured')
        if timeout > 0:
            age = time.monotonic() - max(last or 0.0, since)
            if age > timeout:
                self.stats.timeouts += 1
                raise CommTimeout(f'no heartbeat from node {self.node_id} for {age:.2f} s '
                                  f'(consumer timeout {timeout:.2f} s)')
        return state

    def take_emcy(self) -> list[Emcy]:
        with self._lock:
            frames, self._emcy = self._emcy, []
        return frames

    # --- receive callbacks (the notifier thread) ----------------------------------------

    def _on_heartbeat(self, can_id: int, data: bytearray, timestamp: float) -> None:
        if len(data) < 1:
            self.stats.bad_frames += 1
            return
        try:
            state = NmtState(data[0] & 0x7F)
        except ValueError:
            state = None
        with self._lock:
            self._last_heartbeat = time.monotonic()
            self._nmt_state = state
            self._not_operational = 0 if state is NmtState.OPERATIONAL else \
                self._not_operational + 1
            if state is NmtState.BOOT_UP and self._supervise_timeout > 0:
                self._booted = True

    def _on_emcy(self, can_id: int, data: bytearray, timestamp: float) -> None:
        frame = Emcy.decode(bytes(data), time.monotonic())
        with self._lock:
            self._emcy.append(frame)
            del self._emcy[:-16]

    def _on_tpdo(self, can_id: int, data: bytearray, timestamp: float) -> None:
        number = {0x180: 1, 0x280: 2, 0x380: 3, 0x480: 4}[can_id - self.node_id]
        with self._lock:
            self._tpdo[number] = (bytes(data), time.monotonic())
