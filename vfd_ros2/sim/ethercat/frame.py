"""EtherCAT frame codec: Ethernet header, EtherCAT header, datagram list (pure, no I/O).

Layout (ETG.1000.4 section 5.3/5.4, little endian on the wire):

- Ethernet II header: destination (6), source (6), EtherType 0x88A4 (2).
- EtherCAT header (2): length of the datagrams (11 bits), reserved (1), type (4; 1 = DLPDUs).
- Each datagram: command (1), index (1), address (4: ADP + ADO, or a 32-bit logical
  address), length (11 bits) + reserved (3) + circulating (1) + more-follows (1),
  IRQ (2), data (length), working counter (2).

Frames shorter than 60 bytes are padded (IEEE 802.3 minimum without FCS); the
padding is kept on decode so that a reply has the length of its request, as
a real segment returns it.
"""

from __future__ import annotations

import enum
import struct
from dataclasses import dataclass, field

from ...protocol.ethercat import ETHERTYPE_ETHERCAT

ETHERNET_HEADER = struct.Struct('<6s6sH')          # EtherType is big endian: swapped below
ECAT_HEADER = struct.Struct('<H')
DATAGRAM_HEADER = struct.Struct('<BBIHH')           # cmd, idx, address, len/flags, irq
WKC = struct.Struct('<H')
ETHERNET_MIN_LENGTH = 60
ECAT_TYPE_DLPDU = 0x1

_LENGTH_MASK = 0x07FF
_CIRCULATING = 0x4000
_MORE = 0x8000


class FrameError(ValueError):
    """Bytes that are not a well-formed EtherCAT frame."""


class Command(enum.IntEnum):
    """Datagram commands (ETG.1000.4 table 6)."""

    NOP = 0
    APRD = 1
    APWR = 2
    APRW = 3
    FPRD = 4
    FPWR = 5
    FPRW = 6
    BRD = 7
    BWR = 8
    BRW = 9
    LRD = 10
    LWR = 11
    LRW = 12
    ARMW = 13
    FRMW = 14


#: commands that read slave memory into the datagram / write datagram data into it
READ_COMMANDS = frozenset({Command.APRD, Command.APRW, Command.FPRD, Command.FPRW, Command.BRD,
                           Command.BRW, Command.LRD, Command.LRW})
WRITE_COMMANDS = frozenset({Command.APWR, Command.APRW, Command.FPWR, Command.FPRW, Command.BWR,
                            Command.BRW, Command.LWR, Command.LRW})
#: commands whose read-write semantic counts +1 for the read and +2 for the write
READ_WRITE_COMMANDS = frozenset({Command.APRW, Command.FPRW, Command.BRW, Command.LRW})
AUTO_INCREMENT_COMMANDS = frozenset({Command.APRD, Command.APWR, Command.APRW, Command.ARMW})
CONFIGURED_ADDRESS_COMMANDS = frozenset({Command.FPRD, Command.FPWR, Command.FPRW, Command.FRMW})
BROADCAST_COMMANDS = frozenset({Command.BRD, Command.BWR, Command.BRW})
LOGICAL_COMMANDS = frozenset({Command.LRD, Command.LWR, Command.LRW})


def wkc_increment(command: int, read: bool, written: bool) -> int:
    """Return what one slave adds to the working counter (ETG.1000.4 table 6).

    Read commands count 1 for a successful read, write commands 1 for a
    successful write; the read-write commands count 1 for the read plus 2
    for the write, so a slave that did both adds 3 (the LRW +1/+2 rule).
    ARMW/FRMW count 1 at the slave that reads and 1 at each slave that writes.
    """
    if command in READ_WRITE_COMMANDS:
        return (1 if read else 0) + (2 if written else 0)
    if command in (Command.ARMW, Command.FRMW):
        return 1 if read or written else 0
    if command in READ_COMMANDS:
        return 1 if read else 0
    if command in WRITE_COMMANDS:
        return 1 if written else 0
    return 0


@dataclass
class Datagram:
    """One EtherCAT datagram; ``data`` is mutable so slaves can process it in place."""

    command: int
    index: int
    address: int                  # ADP | ADO << 16, or the logical address
    data: bytearray
    wkc: int = 0
    irq: int = 0
    circulating: bool = False
    more: bool = False            # set by ``Frame.encode`` from the position in the list

    @property
    def adp(self) -> int:
        """Position (auto increment) or configured station address."""
        return self.address & 0xFFFF

    @property
    def ado(self) -> int:
        """Offset in the slave's memory."""
        return self.address >> 16

    @classmethod
    def physical(cls, command: int, index: int, adp: int, ado: int, data: bytes | int,
                 wkc: int = 0) -> 'Datagram':
        """Build a position/configured/broadcast datagram; ``data`` as bytes or a length."""
        return cls(command, index, (adp & 0xFFFF) | (ado & 0xFFFF) << 16, bytearray(data),
                   wkc)

    @classmethod
    def logical(cls, command: int, index: int, address: int, data: bytes | int,
                wkc: int = 0) -> 'Datagram':
        """Build an LRD/LWR/LRW datagram; ``data`` as bytes or a length."""
        return cls(command, index, address & 0xFFFFFFFF, bytearray(data), wkc)


@dataclass
class Frame:
    """An Ethernet frame carrying EtherCAT datagrams."""

    datagrams: list[Datagram]
    destination: bytes = b'\xff' * 6
    source: bytes = b'\x01\x01\x01\x01\x01\x01'
    padding: bytes = field(default=b'', repr=False)

    def encode(self) -> bytes:
        """Return the frame's bytes, padded to the Ethernet minimum."""
        if not self.datagrams:
            raise FrameError('an EtherCAT frame needs at least one datagram')
        body = bytearray()
        last = len(self.datagrams) - 1
        for position, datagram in enumerate(self.datagrams):
            length = len(datagram.data)
            if length > _LENGTH_MASK:
                raise FrameError(f'datagram data of {length} bytes exceeds 2047')
            flags = length | (_CIRCULATING if datagram.circulating else 0) | (
                _MORE if position < last else 0)
            body += DATAGRAM_HEADER.pack(datagram.command, datagram.index, datagram.address,
                                         flags, datagram.irq)
            body += datagram.data
            body += WKC.pack(datagram.wkc & 0xFFFF)
        if len(body) > _LENGTH_MASK:
            raise FrameError(f'EtherCAT payload of {len(body)} bytes exceeds 2047')
        out = bytearray(self.destination + self.source + ETHERTYPE_ETHERCAT.to_bytes(2, 'big'))
        out += ECAT_HEADER.pack(len(body) | ECAT_TYPE_DLPDU << 12)
        out += body
        out += self.padding
        if len(out) < ETHERNET_MIN_LENGTH:
            out += bytes(ETHERNET_MIN_LENGTH - len(out))
        return bytes(out)


def decode_frame(buffer: bytes | bytearray | memoryview) -> Frame:
    """Parse an EtherCAT frame; FrameError if it is not one or is truncated."""
    raw = bytes(buffer)
    if len(raw) < ETHERNET_HEADER.size + ECAT_HEADER.size:
        raise FrameError(f'{len(raw)} bytes is too short for an EtherCAT frame')
    destination, source = raw[0:6], raw[6:12]
    ethertype = int.from_bytes(raw[12:14], 'big')
    if ethertype != ETHERTYPE_ETHERCAT:
        raise FrameError(f'EtherType 0x{ethertype:04X} is not EtherCAT')
    (header,) = ECAT_HEADER.unpack_from(raw, 14)
    length, frame_type = header & _LENGTH_MASK, header >> 12
    if frame_type != ECAT_TYPE_DLPDU:
        raise FrameError(f'EtherCAT frame type {frame_type} is not a DLPDU frame')
    start = 16
    end = start + length
    if end > len(raw):
        raise FrameError(f'EtherCAT header announces {length} bytes, {len(raw) - start} present')
    datagrams: list[Datagram] = []
    offset = start
    while True:
        if offset + DATAGRAM_HEADER.size + WKC.size > end:
            raise FrameError('datagram header runs past the EtherCAT payload')
        command, index, address, flags, irq = DATAGRAM_HEADER.unpack_from(raw, offset)
        size = flags & _LENGTH_MASK
        data_start = offset + DATAGRAM_HEADER.size
        if data_start + size + WKC.size > end:
            raise FrameError('datagram data runs past the EtherCAT payload')
        (wkc,) = WKC.unpack_from(raw, data_start + size)
        datagrams.append(Datagram(command, index, address,
                                  bytearray(raw[data_start:data_start + size]), wkc, irq,
                                  bool(flags & _CIRCULATING), bool(flags & _MORE)))
        offset = data_start + size + WKC.size
        if not flags & _MORE:
            break
    return Frame(datagrams, destination, source, padding=raw[offset:])
