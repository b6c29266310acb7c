"""Pure register codecs: signedness, 32-bit word order, read planning."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Iterable, Protocol

from .values import ValueType, WordOrder


class RegisterLayout(Protocol):
    """What the codecs need to know of a value: its type and word order."""

    @property
    def type(self) -> ValueType: ...

    @property
    def word_order(self) -> WordOrder: ...


def to_signed(raw: int, bits: int) -> int:
    raw &= (1 << bits) - 1
    return raw - (1 << bits) if raw >> (bits - 1) else raw


def decode_words(parameter: RegisterLayout, words: list[int]) -> int:
    """Decode registers as read into the parameter's raw integer (sign applied)."""
    if parameter.type.register_count == 1:
        raw = words[0] & 0xFFFF
    else:
        high, low = (words[0], words[1]) if parameter.word_order is WordOrder.HIGH_FIRST \
            else (words[1], words[0])
        raw = ((high & 0xFFFF) << 16) | (low & 0xFFFF)
    if parameter.type is ValueType.INT16:
        return to_signed(raw, 16)
    if parameter.type is ValueType.INT32:
        return to_signed(raw, 32)
    return raw


def encode_words(parameter: RegisterLayout, raw: int) -> list[int]:
    """Encode the parameter's raw integer as the registers to write."""
    if parameter.type.register_count == 1:
        return [raw & 0xFFFF]
    value = raw & 0xFFFFFFFF
    high, low = value >> 16, value & 0xFFFF
    return [high, low] if parameter.word_order is WordOrder.HIGH_FIRST else [low, high]


@dataclass(frozen=True)
class ReadBlock:
    """One read request: ``count`` registers from ``start``."""

    start: int
    count: int

    def covers(self, address: int, count: int = 1) -> bool:
        return self.start <= address and address + count <= self.start + self.count


def plan_reads(spans: Iterable[tuple[int, int]], max_registers: int,
               readable: Callable[[int], bool]) -> list[ReadBlock]:
    """Fewest read requests covering every (address, count) span.

    A span (e.g. the two registers of a 32-bit value) is never split over two
    requests. A block grows over the gap to the next span only if it stays
    within ``max_registers`` and every address in the gap is ``readable``
    (documented), because many drives refuse reads across undocumented ones.
    """
    units: list[list[int]] = []     # [first, last] of overlapping spans, sorted
    for address, count in sorted(spans):
        last = address + max(count, 1) - 1
        if units and address <= units[-1][1]:
            units[-1][1] = max(units[-1][1], last)
        else:
            units.append([address, last])
    blocks: list[ReadBlock] = []
    start = end = None
    for first, last in units:
        if start is not None and last - start < max_registers and all(
                readable(gap) for gap in range(end + 1, first)):
            end = last
            continue
        if start is not None:
            blocks.append(ReadBlock(start, end - start + 1))
        start, end = first, last
    if start is not None:
        blocks.append(ReadBlock(start, end - start + 1))
    return blocks
