"""SII EEPROM images built from plain data (pure, no I/O).

The Slave Information Interface (ETG.1000.6 section 5.4, tables 2-3; category
layouts in ETG.2010) is the slave's EEPROM: a fixed header of 64 words
(ESC configuration, identity, mailbox layout) followed by categories, each a
type word, a size word (in words) and the data, ended by type 0xFFFF.

The ESC loads words 0..7 at power-up and checks word 7: a CRC-8 over the
bytes of words 0..6, polynomial x^8 + x^2 + x + 1 (0x07), initial value
0xFF, not reflected, no final XOR (ETG.1000.6 5.4; IEC 61158-6-12).
"""

from __future__ import annotations

import enum
import struct
from dataclasses import dataclass, field

from ...protocol.ethercat import COE_DETAIL_SDO, MAILBOX_PROTOCOL_COE


class Category(enum.IntEnum):
    """SII category types (ETG.1000.6 table 3)."""

    STRINGS = 10
    DATA_TYPES = 20
    GENERAL = 30
    FMMU = 40
    SYNC_MANAGER = 41
    TXPDO = 50
    RXPDO = 51
    DC = 60
    END = 0xFFFF


class SyncManagerType(enum.IntEnum):
    """What a sync manager is used for (SII SyncM category, ETG.2010 table 10)."""

    UNUSED = 0
    MAILBOX_OUT = 1          # master -> slave (SM0)
    MAILBOX_IN = 2           # slave -> master (SM1)
    PROCESS_DATA_OUT = 3     # outputs, RxPDOs (SM2)
    PROCESS_DATA_IN = 4      # inputs, TxPDOs (SM3)


class FmmuUsage(enum.IntEnum):
    """FMMU category byte (ETG.2010 table 9)."""

    UNUSED = 0
    OUTPUTS = 1
    INPUTS = 2
    SYNC_MANAGER_STATUS = 3


#: word addresses of the SII header (ETG.1000.6 table 2)
WORD_PDI_CONTROL = 0x0000
WORD_ALIAS = 0x0004
WORD_CHECKSUM = 0x0007
WORD_VENDOR_ID = 0x0008
WORD_PRODUCT_CODE = 0x000A
WORD_REVISION = 0x000C
WORD_SERIAL = 0x000E
WORD_RX_MAILBOX = 0x0018            # standard receive mailbox (master -> slave): offset, size
WORD_TX_MAILBOX = 0x001A            # standard send mailbox (slave -> master): offset, size
WORD_MAILBOX_PROTOCOL = 0x001C
WORD_EEPROM_SIZE = 0x003E
WORD_VERSION = 0x003F
WORD_FIRST_CATEGORY = 0x0040


@dataclass(frozen=True)
class SyncManagerConfig:
    """One SyncManager as the SII describes it (8 bytes: start, length, control, enable, type)."""

    start: int
    length: int
    control: int
    type: SyncManagerType
    enable: int = 0x01


@dataclass(frozen=True)
class PdoEntryInfo:
    """One entry of a PDO in the SII (index 0 = padding gap)."""

    index: int
    subindex: int
    bit_length: int
    data_type: int = 0
    name_index: int = 0


@dataclass(frozen=True)
class PdoInfo:
    """A PDO in the SII TxPDO/RxPDO category; ``sync_manager`` 0xFF = not assigned."""

    index: int
    entries: tuple[PdoEntryInfo, ...]
    sync_manager: int
    name_index: int = 0
    flags: int = 0

    @property
    def bit_length(self) -> int:
        return sum(entry.bit_length for entry in self.entries)


@dataclass(frozen=True)
class SiiData:
    """Everything an SII image is built from."""

    vendor_id: int
    product_code: int
    revision: int
    serial: int
    rx_mailbox: tuple[int, int] = (0x1000, 128)       # SM0 offset, size
    tx_mailbox: tuple[int, int] = (0x1080, 128)       # SM1 offset, size
    mailbox_protocols: int = MAILBOX_PROTOCOL_COE
    alias: int = 0
    pdi_control: int = 0x0C80        # word 0: PDI type (low byte), ESC configuration (high)
    strings: tuple[str, ...] = ()    # string index 1 is the device name SOEM shows
    name_index: int = 1
    group_index: int = 0
    image_index: int = 0
    order_index: int = 0
    coe_details: int = COE_DETAIL_SDO
    general_flags: int = 0
    ebus_current_ma: int = 0
    fmmus: tuple[FmmuUsage, ...] = (FmmuUsage.OUTPUTS, FmmuUsage.INPUTS,
                                    FmmuUsage.SYNC_MANAGER_STATUS, FmmuUsage.UNUSED)
    sync_managers: tuple[SyncManagerConfig, ...] = ()
    tx_pdos: tuple[PdoInfo, ...] = ()
    rx_pdos: tuple[PdoInfo, ...] = ()
    eeprom_bytes: int = 2048         # a 16 kbit EEPROM
    extra_categories: tuple[tuple[int, bytes], ...] = field(default=(), repr=False)


def sii_checksum(data: bytes) -> int:
    """CRC-8 of the first 14 bytes (words 0..6) as the ESC checks it (ETG.1000.6 5.4)."""
    crc = 0xFF
    for byte in data[:14]:
        crc ^= byte
        for _ in range(8):
            crc = ((crc << 1) ^ 0x07) & 0xFF if crc & 0x80 else (crc << 1) & 0xFF
    return crc


def _category(kind: int, payload: bytes) -> bytes:
    if len(payload) % 2:
        payload += b'\x00'          # categories are whole words
    return struct.pack('<HH', kind, len(payload) // 2) + payload


def _strings(strings: tuple[str, ...]) -> bytes:
    out = bytearray([len(strings)])
    for text in strings:
        raw = text.encode('ascii')
        if len(raw) > 255:
            raise ValueError(f'SII string {text[:20]!r}... is longer than 255 bytes')
        out += bytes([len(raw)]) + raw
    return bytes(out)


def _general(data: SiiData) -> bytes:
    # ETG.2010 table 8: group, image, order, name indices; CoE/FoE/EoE/SoE details;
    # DS402 channels; SysmanClass; flags; EBus current; ... (32 bytes)
    general = bytearray(32)
    general[0] = data.group_index
    general[1] = data.image_index
    general[2] = data.order_index
    general[3] = data.name_index
    general[5] = data.coe_details
    general[11] = data.general_flags
    struct.pack_into('<h', general, 12, data.ebus_current_ma)
    general[14] = data.group_index
    return bytes(general)


def _pdos(pdos: tuple[PdoInfo, ...]) -> bytes:
    out = bytearray()
    for pdo in pdos:
        # PDO header (8 bytes): index, entry count, SM, synchronization, name, flags
        out += struct.pack('<HBBBBH', pdo.index, len(pdo.entries), pdo.sync_manager, 0,
                           pdo.name_index, pdo.flags)
        for entry in pdo.entries:
            # entry (8 bytes): index, subindex, name, data type, bit length, flags
            out += struct.pack('<HBBBBH', entry.index, entry.subindex, entry.name_index,
                               entry.data_type, entry.bit_length, 0)
    return bytes(out)


def build_image(data: SiiData) -> bytes:
    """Return the EEPROM bytes for ``data``: header, checksum, categories, 0xFF fill."""
    header = bytearray(WORD_FIRST_CATEGORY * 2)
    struct.pack_into('<H', header, WORD_PDI_CONTROL * 2, data.pdi_control)
    struct.pack_into('<H', header, WORD_ALIAS * 2, data.alias)
    struct.pack_into('<IIII', header, WORD_VENDOR_ID * 2, data.vendor_id, data.product_code,
                     data.revision, data.serial)
    struct.pack_into('<HHHHH', header, WORD_RX_MAILBOX * 2, data.rx_mailbox[0],
                     data.rx_mailbox[1], data.tx_mailbox[0], data.tx_mailbox[1],
                     data.mailbox_protocols)
    struct.pack_into('<HH', header, WORD_EEPROM_SIZE * 2, data.eeprom_bytes * 8 // 1024 - 1, 1)
    struct.pack_into('<H', header, WORD_CHECKSUM * 2, sii_checksum(bytes(header)))

    body = bytearray()
    if data.strings:
        body += _category(Category.STRINGS, _strings(data.strings))
    body += _category(Category.GENERAL, _general(data))
    if data.fmmus:
        body += _category(Category.FMMU, bytes(data.fmmus))
    if data.sync_managers:
        body += _category(Category.SYNC_MANAGER, b''.join(
            struct.pack('<HHBBBB', sm.start, sm.length, sm.control, 0, sm.enable, sm.type)
            for sm in data.sync_managers))
    if data.tx_pdos:
        body += _category(Category.TXPDO, _pdos(data.tx_pdos))
    if data.rx_pdos:
        body += _category(Category.RXPDO, _pdos(data.rx_pdos))
    for kind, payload in data.extra_categories:
        body += _category(kind, payload)
    body += struct.pack('<H', Category.END)

    image = bytes(header) + bytes(body)
    if len(image) > data.eeprom_bytes:
        raise ValueError(f'SII image of {len(image)} bytes does not fit {data.eeprom_bytes}')
    return image + b'\xff' * (data.eeprom_bytes - len(image))


def categories(image: bytes) -> dict[int, bytes]:
    """Return ``{category type: data}`` of an image (the first of each type)."""
    found: dict[int, bytes] = {}
    offset = WORD_FIRST_CATEGORY * 2
    while offset + 4 <= len(image):
        kind, words = struct.unpack_from('<HH', image, offset)
        if kind == Category.END:
            break
        found.setdefault(kind, image[offset + 4:offset + 4 + words * 2])
        offset += 4 + words * 2
    return found
