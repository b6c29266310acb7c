"""How a raw value is laid out: integer type and width, and the order of 16-bit words."""

from __future__ import annotations

import enum


class ValueType(str, enum.Enum):
    """How a parameter's raw value is laid out in 16-bit registers."""

    UINT16 = 'uint16'
    INT16 = 'int16'
    UINT32 = 'uint32'
    INT32 = 'int32'
    # CANopen objects only (e.g. 0x6060 modes of operation, INTEGER8): never Modbus registers.
    UINT8 = 'uint8'
    INT8 = 'int8'

    # Looked up, not computed: these run for every register of every transaction.
    @property
    def register_count(self) -> int:
        return _LAYOUT[self][0]

    @property
    def bits(self) -> int:
        """Width of the value on the wire (CANopen object size)."""
        return _LAYOUT[self][1]

    @property
    def signed(self) -> bool:
        return _LAYOUT[self][2]

    @property
    def bounds(self) -> tuple[int, int]:
        return _LAYOUT[self][3]


def _layout(bits: int, signed: bool) -> tuple[int, int, bool, tuple[int, int]]:
    """Return (registers, bits, signed, (lowest, highest)) of an integer type."""
    bounds = (-(1 << (bits - 1)), (1 << (bits - 1)) - 1) if signed else (0, (1 << bits) - 1)
    return max(1, bits // 16), bits, signed, bounds


_LAYOUT = {
    ValueType.UINT16: _layout(16, False), ValueType.INT16: _layout(16, True),
    ValueType.UINT32: _layout(32, False), ValueType.INT32: _layout(32, True),
    ValueType.UINT8: _layout(8, False), ValueType.INT8: _layout(8, True),
}


class WordOrder(str, enum.Enum):
    """Order of the two registers of a 32-bit value."""

    HIGH_FIRST = 'high_first'
    LOW_FIRST = 'low_first'
