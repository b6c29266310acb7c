"""CoE mailbox server: SDO upload/download (expedited, normal, segmented), aborts, emergencies.

CoE service data (ETG.1000.6 5.6.2): a 2-byte CoE header (number, 9 bits; 3
reserved; service, 4 bits) followed by the SDO frame of CiA 301 7.2.4.3: a
command byte, index (2), subindex (1), then 4 bytes of data/size, and for
normal transfers the data after them. EtherCAT lets a normal transfer carry as
much data as the mailbox holds (mailbox size - 16 in the initiate frame, - 9
in a segment) instead of CAN's 7 bytes; segments that carry fewer than 7 bytes
are padded to 7 and say how many bytes are unused.

Command bytes (CiA 301 figures 36-46):
- initiate download request 0x20 | n << 2 | e << 1 | s (bit 4: complete access),
  response 0x60;
- download segment request t << 4 | n << 1 | c, response 0x20 | t << 4;
- initiate upload request 0x40 (bit 4: complete access), response
  0x40 | n << 2 | e << 1 | s;
- upload segment request 0x60 | t << 4, response t << 4 | n << 1 | c;
- abort 0x80 with the 4-byte abort code.
Block transfers are not supported (abort 0x05040001), nor complete access
(0x06010000): the SII does not announce either.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from typing import Callable

from ...protocol.ethercat import CoeService, SdoAbortCode

COE_HEADER = struct.Struct('<H')
SDO = struct.Struct('<BHB')            # command, index, subindex
ABORT = 0x80

#: reads an object: (abort code, data); writes one: abort code (0 = done)
ObjectReader = Callable[[int, int], tuple[int, bytes]]
ObjectWriter = Callable[[int, int, bytes], int]


def coe_header(service: int, number: int = 0) -> bytes:
    return COE_HEADER.pack((number & 0x01FF) | (service & 0x0F) << 12)


def sdo_abort(index: int, subindex: int, code: int) -> bytes:
    """CoE service data of an SDO abort."""
    return coe_header(CoeService.SDO_REQUEST) + SDO.pack(ABORT, index, subindex) + struct.pack(
        '<I', code)


def emergency(error_code: int, error_register: int, data: bytes = b'') -> bytes:
    """CoE service data of an emergency: code (2), error register (1), 5 data bytes."""
    return coe_header(CoeService.EMERGENCY) + struct.pack('<HB', error_code, error_register) + (
        bytes(data) + bytes(5))[:5]


@dataclass
class _Transfer:
    """A segmented transfer in progress."""

    index: int
    subindex: int
    upload: bool
    data: bytearray
    size: int
    toggle: int = 0


class CoeServer:
    """Answers CoE SDO requests from an object dictionary's read/write callables."""

    def __init__(self, read: ObjectReader, write: ObjectWriter, mailbox_size: int) -> None:
        self.read = read
        self.write = write
        self.mailbox_size = mailbox_size            # the SM1 buffer (replies)
        self._transfer: _Transfer | None = None
        self.requests = 0
        self.aborts = 0

    def reset(self) -> None:
        self._transfer = None

    def handle(self, data: bytes) -> list[bytes]:
        """Handle the service data of one CoE mailbox message; return the replies."""
        if len(data) < COE_HEADER.size:
            return []
        (header,) = COE_HEADER.unpack_from(data)
        service = header >> 12
        if service != CoeService.SDO_REQUEST:
            # SDO information, remote PDO requests: not offered (SII CoE details)
            return [self._abort(0, 0, SdoAbortCode.COMMAND_SPECIFIER_UNKNOWN)]
        self.requests += 1
        body = data[COE_HEADER.size:]
        if len(body) < 1:
            return [self._abort(0, 0, SdoAbortCode.COMMAND_SPECIFIER_UNKNOWN)]
        command = body[0]
        specifier = command >> 5
        if specifier == 1:
            return [self._initiate_download(body)]
        if specifier == 2:
            return [self._initiate_upload(body)]
        if specifier == 0:
            return [self._download_segment(body)]
        if specifier == 3:
            return [self._upload_segment(body)]
        index, subindex = self._address(body)
        self._transfer = None
        if command == ABORT:
            return []                       # the master aborted its own transfer
        return [self._abort(index, subindex, SdoAbortCode.COMMAND_SPECIFIER_UNKNOWN)]

    @staticmethod
    def _address(body: bytes) -> tuple[int, int]:
        if len(body) < SDO.size:
            return 0, 0
        _, index, subindex = SDO.unpack_from(body)
        return index, subindex

    def _abort(self, index: int, subindex: int, code: int) -> bytes:
        self.aborts += 1
        self._transfer = None
        return sdo_abort(index, subindex, code)

    def _response(self, command: int, index: int, subindex: int, payload: bytes) -> bytes:
        return coe_header(CoeService.SDO_RESPONSE) + SDO.pack(command, index, subindex) + payload

    # -- download (master writes) -------------------------------------------------

    def _initiate_download(self, body: bytes) -> bytes:
        if len(body) < SDO.size + 4:
            return self._abort(*self._address(body), SdoAbortCode.COMMAND_SPECIFIER_UNKNOWN)
        command, index, subindex = SDO.unpack_from(body)
        self._transfer = None
        if command & 0x10:
            return self._abort(index, subindex, SdoAbortCode.UNSUPPORTED_ACCESS)
        expedited, size_indicated = command & 0x02, command & 0x01
        if expedited:
            size = 4 - ((command >> 2) & 0x03) if size_indicated else 4
            return self._commit(index, subindex, body[SDO.size:SDO.size + size])
        (size,) = struct.unpack_from('<I', body, SDO.size)
        data = body[SDO.size + 4:]
        if len(data) >= size:
            return self._commit(index, subindex, data[:size])
        # more segments follow: keep what came and confirm the initiate
        self._transfer = _Transfer(index, subindex, False, bytearray(data), size)
        return self._response(0x60, index, subindex, bytes(4))

    def _commit(self, index: int, subindex: int, data: bytes) -> bytes:
        code = self.write(index, subindex, bytes(data))
        if code:
            return self._abort(index, subindex, code)
        return self._response(0x60, index, subindex, bytes(4))

    def _download_segment(self, body: bytes) -> bytes:
        transfer = self._transfer
        if transfer is None or transfer.upload:
            return self._abort(0, 0, SdoAbortCode.COMMAND_SPECIFIER_UNKNOWN)
        command = body[0]
        toggle = (command >> 4) & 0x01
        if toggle != transfer.toggle:
            return self._abort(transfer.index, transfer.subindex,
                               SdoAbortCode.TOGGLE_BIT_NOT_ALTERNATED)
        last = command & 0x01
        segment = body[1:]
        if last and len(segment) == 7:
            segment = segment[:7 - ((command >> 1) & 0x07)]   # unused bytes of a short segment
        transfer.data += segment
        transfer.toggle ^= 1
        reply_command = 0x20 | toggle << 4
        if not last:
            if len(transfer.data) > transfer.size:
                return self._abort(transfer.index, transfer.subindex,
                                   SdoAbortCode.LENGTH_TOO_HIGH)
            return coe_header(CoeService.SDO_RESPONSE) + bytes([reply_command]) + bytes(7)
        self._transfer = None
        if len(transfer.data) != transfer.size:
            return self._abort(transfer.index, transfer.subindex, SdoAbortCode.LENGTH_MISMATCH)
        code = self.write(transfer.index, transfer.subindex, bytes(transfer.data))
        if code:
            return self._abort(transfer.index, transfer.subindex, code)
        return coe_header(CoeService.SDO_RESPONSE) + bytes([reply_command]) + bytes(7)

    # -- upload (master reads) ----------------------------------------------------

    def _initiate_upload(self, body: bytes) -> bytes:
        if len(body) < SDO.size:
            return self._abort(0, 0, SdoAbortCode.COMMAND_SPECIFIER_UNKNOWN)
        command, index, subindex = SDO.unpack_from(body)
        self._transfer = None
        if command & 0x10:
            return self._abort(index, subindex, SdoAbortCode.UNSUPPORTED_ACCESS)
        code, data = self.read(index, subindex)
        if code:
            return self._abort(index, subindex, code)
        if 0 < len(data) <= 4:
            expedited = 0x40 | (4 - len(data)) << 2 | 0x02 | 0x01
            return self._response(expedited, index, subindex, data + bytes(4 - len(data)))
        # normal transfer: size, then as much data as the SM1 buffer holds
        room = self.mailbox_size - 6 - 10
        first = data[:room]
        if len(data) > room:
            self._transfer = _Transfer(index, subindex, True, bytearray(data[room:]), len(data))
        return self._response(0x41, index, subindex, struct.pack('<I', len(data)) + first)

    def _upload_segment(self, body: bytes) -> bytes:
        transfer = self._transfer
        command = body[0]
        index, subindex = self._address(body)
        if transfer is None or not transfer.upload:
            return self._abort(index, subindex, SdoAbortCode.COMMAND_SPECIFIER_UNKNOWN)
        toggle = (command >> 4) & 0x01
        if toggle != transfer.toggle:
            return self._abort(transfer.index, transfer.subindex,
                               SdoAbortCode.TOGGLE_BIT_NOT_ALTERNATED)
        room = self.mailbox_size - 6 - 3
        segment = bytes(transfer.data[:room])
        del transfer.data[:room]
        transfer.toggle ^= 1
        last = not transfer.data
        if last:
            self._transfer = None
        unused = 0
        if len(segment) < 7:
            unused = 7 - len(segment)
            segment += bytes(unused)
        reply = toggle << 4 | unused << 1 | (1 if last else 0)
        return coe_header(CoeService.SDO_RESPONSE) + bytes([reply]) + segment
