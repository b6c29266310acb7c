"""A CoE object dictionary for simulated slaves: typed entries, access rules, abort codes.

Values are kept as Python ints (or bytes/str for string types) and packed
little endian on access, as CoE transfers them (ETG.1000.6 5.6.2; data types
CiA 301 table 44). Every refused access returns the CiA 301 abort code a real
slave sends, never raises: the CoE server turns it into an SDO abort.
"""

from __future__ import annotations

import enum
import struct
from dataclasses import dataclass
from typing import Callable, Iterable

from ...protocol.ethercat import ALState, SdoAbortCode


class DataType(enum.IntEnum):
    """CiA 301 data type indices (table 44) used by the simulated drives."""

    BOOLEAN = 0x0001
    INTEGER8 = 0x0002
    INTEGER16 = 0x0003
    INTEGER32 = 0x0004
    UNSIGNED8 = 0x0005
    UNSIGNED16 = 0x0006
    UNSIGNED32 = 0x0007
    REAL32 = 0x0008
    VISIBLE_STRING = 0x0009
    OCTET_STRING = 0x000A
    INTEGER64 = 0x0015
    UNSIGNED64 = 0x001B


_FORMATS: dict[DataType, struct.Struct] = {
    DataType.BOOLEAN: struct.Struct('<B'),
    DataType.INTEGER8: struct.Struct('<b'),
    DataType.INTEGER16: struct.Struct('<h'),
    DataType.INTEGER32: struct.Struct('<i'),
    DataType.UNSIGNED8: struct.Struct('<B'),
    DataType.UNSIGNED16: struct.Struct('<H'),
    DataType.UNSIGNED32: struct.Struct('<I'),
    DataType.REAL32: struct.Struct('<f'),
    DataType.INTEGER64: struct.Struct('<q'),
    DataType.UNSIGNED64: struct.Struct('<Q'),
}


def type_size(data_type: DataType) -> int | None:
    """Size in bytes of a fixed-size type (None for strings)."""
    fmt = _FORMATS.get(data_type)
    return fmt.size if fmt else None


class Access(enum.Enum):
    """Who may read/write an entry (ETG.1000.6 object access; ``RW_PREOP`` = wr_preop)."""

    RO = 'ro'
    WO = 'wo'
    RW = 'rw'
    RW_PREOP = 'rw_preop'     # writable in PRE-OP only (PDO assignment and mapping)


@dataclass
class Entry:
    """One object entry (index, subindex) with its current value."""

    index: int
    subindex: int
    name: str
    data_type: DataType
    access: Access
    value: int | float | bytes | str = 0
    pdo_mappable: bool = False
    minimum: int | None = None
    maximum: int | None = None
    max_length: int = 0         # strings: the longest value a write may set

    def pack(self) -> bytes:
        if self.data_type is DataType.VISIBLE_STRING:
            return str(self.value).encode('ascii')
        if self.data_type is DataType.OCTET_STRING:
            return bytes(self.value)                             # type: ignore[arg-type]
        return _FORMATS[self.data_type].pack(self.value)

    @property
    def bit_length(self) -> int:
        size = type_size(self.data_type)
        return 8 * (size if size is not None else len(self.pack()))


#: called before a write is committed; returns an abort code (0 = accept)
WriteCheck = Callable[[Entry, int | float | bytes | str], int]


class ObjectDictionary:
    """Entries by (index, subindex) with CoE access rules.

    ``al_state`` is the slave's AL state, kept current by its application:
    ``RW_PREOP`` entries refuse writes outside PRE-OP (abort 0x08000022).
    """

    def __init__(self, entries: Iterable[Entry] = ()) -> None:
        self._entries: dict[tuple[int, int], Entry] = {}
        self._indices: set[int] = set()
        self._checks: dict[int, WriteCheck] = {}
        self.al_state = ALState.INIT
        for entry in entries:
            self.add(entry)

    def add(self, entry: Entry) -> Entry:
        self._entries[(entry.index, entry.subindex)] = entry
        self._indices.add(entry.index)
        return entry

    def add_check(self, index: int, check: WriteCheck) -> None:
        """Validate writes to ``index`` (all subindices) with ``check`` before they commit."""
        self._checks[index] = check

    def entry(self, index: int, subindex: int) -> Entry:
        """Return an entry (KeyError if absent)."""
        return self._entries[(index, subindex)]

    def find(self, index: int, subindex: int) -> Entry | None:
        return self._entries.get((index, subindex))

    def __contains__(self, key: tuple[int, int]) -> bool:
        return key in self._entries

    def value(self, index: int, subindex: int = 0) -> int | float | bytes | str:
        return self._entries[(index, subindex)].value

    def set_value(self, index: int, subindex: int, value: int | float | bytes | str) -> None:
        """Set a value from the device side (no access check: the drive updating itself)."""
        self._entries[(index, subindex)].value = value

    def _lookup(self, index: int, subindex: int) -> tuple[int, Entry | None]:
        entry = self._entries.get((index, subindex))
        if entry is not None:
            return 0, entry
        if index in self._indices:
            return SdoAbortCode.SUBINDEX_DOES_NOT_EXIST, None
        return SdoAbortCode.OBJECT_DOES_NOT_EXIST, None

    def read(self, index: int, subindex: int) -> tuple[int, bytes]:
        """SDO upload: ``(0, data)`` or ``(abort code, b'')``."""
        code, entry = self._lookup(index, subindex)
        if entry is None:
            return code, b''
        if entry.access is Access.WO:
            return SdoAbortCode.READ_WRITE_ONLY, b''
        return 0, entry.pack()

    def write(self, index: int, subindex: int, data: bytes) -> int:
        """SDO download: 0 or the abort code; the value changes only on 0."""
        code, entry = self._lookup(index, subindex)
        if entry is None:
            return code
        if entry.access is Access.RO:
            return SdoAbortCode.WRITE_READ_ONLY
        if entry.access is Access.RW_PREOP and self.al_state is not ALState.PRE_OP:
            return SdoAbortCode.DEVICE_STATE
        value: int | float | bytes | str
        if entry.data_type is DataType.VISIBLE_STRING:
            if entry.max_length and len(data) > entry.max_length:
                return SdoAbortCode.LENGTH_TOO_HIGH
            value = data.decode('ascii', errors='replace')
        elif entry.data_type is DataType.OCTET_STRING:
            if entry.max_length and len(data) > entry.max_length:
                return SdoAbortCode.LENGTH_TOO_HIGH
            value = bytes(data)
        else:
            fmt = _FORMATS[entry.data_type]
            if len(data) < fmt.size:
                return SdoAbortCode.LENGTH_TOO_LOW
            if len(data) > fmt.size:
                return SdoAbortCode.LENGTH_TOO_HIGH
            (value,) = fmt.unpack(data)
            if entry.minimum is not None and value < entry.minimum:
                return SdoAbortCode.VALUE_TOO_LOW
            if entry.maximum is not None and value > entry.maximum:
                return SdoAbortCode.VALUE_TOO_HIGH
        check = self._checks.get(index)
        if check is not None:
            code = check(entry, value)
            if code:
                return code
        entry.value = value
        return 0
