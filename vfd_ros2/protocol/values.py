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

    @property
    def register_count(self) -> int:
        return 2 if self in (ValueType.UINT32, ValueType.INT32) else 1

    @property
    def bits(self) -> int:
        """Width of the value on the wire (CANopen object size)."""
        if self in (ValueType.UINT8, ValueType.INT8):
            return 8
        return 16 * self.register_count

    @property
    def signed(self) -> bool:
        return self in (ValueType.INT8, ValueType.INT16, ValueType.INT32)

    @property
    def bounds(self) -> tuple[int, int]:
        bits = self.bits
        if self.signed:
            return -(1 << (bits - 1)), (1 << (bits - 1)) - 1
        return 0, (1 << bits) - 1


class WordOrder(str, enum.Enum):
    """Order of the two registers of a 32-bit value."""

    HIGH_FIRST = 'high_first'
    LOW_FIRST = 'low_first'
