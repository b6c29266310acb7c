"""Unit tests of the register codecs and the read planner."""

from __future__ import annotations

import random

import pytest

from vfd_ros2.profiles import Parameter, ValueType, WordOrder
from vfd_ros2.protocol.modbus_crc import crc16
from vfd_ros2.protocol.registers import (
    ReadBlock,
    decode_words,
    encode_words,
    plan_reads,
    to_signed,
)


def param(value_type: ValueType, order: WordOrder = WordOrder.HIGH_FIRST) -> Parameter:
    return Parameter(code='X', address=0x100, description='test', type=value_type,
                     word_order=order)


def everything(_address: int) -> bool:
    return True


def nothing(_address: int) -> bool:
    return False


# --- to_signed --------------------------------------------------------------------------

@pytest.mark.parametrize('raw, bits, expected', [
    (0, 16, 0), (1, 16, 1), (0x7FFF, 16, 32767), (0x8000, 16, -32768), (0xFFFF, 16, -1),
    (0xFFFE, 16, -2), (0x1_0001, 16, 1),            # bits above 16 are dropped
    (0x7FFFFFFF, 32, 2147483647), (0x80000000, 32, -2147483648), (0xFFFFFFFF, 32, -1),
    (0x80, 8, -128), (-1, 16, -1),
])
def test_to_signed(raw, bits, expected):
    assert to_signed(raw, bits) == expected


# --- decode / encode ----------------------------------------------------------------------

def test_known_vector_high_first():
    p = param(ValueType.UINT32, WordOrder.HIGH_FIRST)
    assert encode_words(p, 0x12345678) == [0x1234, 0x5678]
    assert decode_words(p, [0x1234, 0x5678]) == 0x12345678


def test_known_vector_low_first():
    p = param(ValueType.UINT32, WordOrder.LOW_FIRST)
    assert encode_words(p, 0x12345678) == [0x5678, 0x1234]
    assert decode_words(p, [0x5678, 0x1234]) == 0x12345678


@pytest.mark.parametrize('order, words', [
    (WordOrder.HIGH_FIRST, [0xFFFF, 0xFFFE]),
    (WordOrder.LOW_FIRST, [0xFFFE, 0xFFFF]),
])
def test_int32_negative(order, words):
    p = param(ValueType.INT32, order)
    assert encode_words(p, -2) == words
    assert decode_words(p, words) == -2


def test_int32_sign_comes_from_the_high_word():
    # -100000 = 0xFFFE7960: the low word alone (0x7960) looks positive.
    assert decode_words(param(ValueType.INT32), [0xFFFE, 0x7960]) == -100000
    assert decode_words(param(ValueType.UINT32), [0xFFFE, 0x7960]) == 0xFFFE7960
    assert decode_words(param(ValueType.INT32), [0x0001, 0x86A0]) == 100000


def test_16_bit_values():
    assert decode_words(param(ValueType.INT16), [0xFFFF]) == -1
    assert decode_words(param(ValueType.UINT16), [0xFFFF]) == 65535
    assert decode_words(param(ValueType.INT16), [0x8000]) == -32768
    assert decode_words(param(ValueType.INT16), [0x7FFF]) == 32767
    assert encode_words(param(ValueType.INT16), -1) == [0xFFFF]
    assert encode_words(param(ValueType.INT16), -32768) == [0x8000]
    assert encode_words(param(ValueType.UINT16), 65535) == [0xFFFF]


def test_16_bit_ignores_extra_words():
    assert decode_words(param(ValueType.UINT16), [0x0042, 0x9999]) == 0x42


# The Modbus register types (the 8-bit types are CANopen objects, never registers).
ROUND_TRIP = {
    ValueType.INT16: [-32768, -1000, -1, 0, 1, 1000, 32767],
    ValueType.UINT16: [0, 1, 0x1234, 0x8000, 0xFFFF],
    ValueType.INT32: [-(1 << 31), -100000, -65536, -65535, -1, 0, 1, 65535, 65536,
                      (1 << 31) - 1],
    ValueType.UINT32: [0, 1, 0xFFFF, 0x10000, 0x12345678, 0xFFFFFFFF],
}


@pytest.mark.parametrize('order', list(WordOrder))
@pytest.mark.parametrize('value_type', list(ROUND_TRIP))
def test_round_trip(value_type, order):
    p = param(value_type, order)
    for raw in ROUND_TRIP[value_type]:
        words = encode_words(p, raw)
        assert len(words) == value_type.register_count
        assert all(0 <= w <= 0xFFFF for w in words)
        assert decode_words(p, words) == raw


@pytest.mark.parametrize('value_type', [ValueType.INT32, ValueType.UINT32])
def test_word_orders_are_mirror_images(value_type):
    high = param(value_type, WordOrder.HIGH_FIRST)
    low = param(value_type, WordOrder.LOW_FIRST)
    for raw in (0x00010002, 0x7FFF0001):
        assert encode_words(low, raw) == list(reversed(encode_words(high, raw)))


# --- plan_reads ------------------------------------------------------------------------------

def covered(blocks: list[ReadBlock], address: int) -> bool:
    return any(block.covers(address) for block in blocks)


def test_read_block_covers():
    block = ReadBlock(10, 3)
    assert block.covers(10) and block.covers(12) and block.covers(11, 2)
    assert not block.covers(9) and not block.covers(13) and not block.covers(12, 2)


def test_nothing_wanted():
    assert plan_reads([], 125, everything) == []


def test_contiguous_spans_merge():
    assert plan_reads([(10, 1), (11, 1), (12, 1)], 125, nothing) == [ReadBlock(10, 3)]


def test_max_registers_limits_a_block():
    spans = [(address, 1) for address in range(10)]
    assert plan_reads(spans, 4, everything) == [
        ReadBlock(0, 4), ReadBlock(4, 4), ReadBlock(8, 2)]
    assert plan_reads(spans, 1, everything) == [ReadBlock(a, 1) for a in range(10)]
    assert plan_reads(spans, 10, everything) == [ReadBlock(0, 10)]


def test_gaps_are_merged_only_when_readable():
    spans = [(0x2000, 1), (0x2003, 1)]
    assert plan_reads(spans, 125, everything) == [ReadBlock(0x2000, 4)]
    assert plan_reads(spans, 125, nothing) == [ReadBlock(0x2000, 1), ReadBlock(0x2003, 1)]
    # One undocumented address in the gap is enough to split.
    assert plan_reads(spans, 125, lambda a: a != 0x2002) == [
        ReadBlock(0x2000, 1), ReadBlock(0x2003, 1)]
    documented = {0x2000, 0x2001, 0x2002, 0x2003}
    assert plan_reads(spans, 125, documented.__contains__) == [ReadBlock(0x2000, 4)]


def test_gap_merge_respects_max_registers():
    assert plan_reads([(0, 1), (5, 1)], 5, everything) == [ReadBlock(0, 1), ReadBlock(5, 1)]
    assert plan_reads([(0, 1), (5, 1)], 6, everything) == [ReadBlock(0, 6)]


def test_gap_readability_is_asked_only_about_the_gap():
    asked: list[int] = []

    def readable(address: int) -> bool:
        asked.append(address)
        return True
    plan_reads([(100, 1), (104, 1)], 125, readable)
    assert sorted(set(asked)) == [101, 102, 103]


def test_unsorted_and_duplicate_spans():
    assert plan_reads([(12, 1), (10, 1), (11, 1), (10, 1), (12, 1)], 125, nothing) == [
        ReadBlock(10, 3)]
    assert plan_reads([(0x3300, 2), (0x3301, 1), (0x3300, 1)], 125, nothing) == [
        ReadBlock(0x3300, 2)]


def test_32_bit_spans():
    assert plan_reads([(100, 2), (102, 2)], 125, nothing) == [ReadBlock(100, 4)]
    assert plan_reads([(100, 2), (110, 2)], 125, nothing) == [
        ReadBlock(100, 2), ReadBlock(110, 2)]
    # The second word of a pair is wanted, not a gap: no readability question for it.
    assert plan_reads([(100, 2), (102, 1)], 125, nothing) == [ReadBlock(100, 3)]


@pytest.mark.parametrize('spans, limit', [
    ([(0, 1), (1, 2)], 2),
    ([(0, 2), (2, 2)], 3),
    ([(10, 1), (11, 1), (12, 1), (13, 1), (14, 2)], 5),
])
def test_32_bit_span_is_never_split(spans, limit):
    blocks = plan_reads(spans, limit, everything)
    for address, count in spans:
        assert any(block.covers(address, count) for block in blocks), (address, count, blocks)


def test_plan_properties_on_random_inputs():
    rng = random.Random(20240607)
    for _ in range(300):
        spans = [(rng.randrange(0, 60), rng.choice((1, 1, 1, 2)))
                 for _ in range(rng.randrange(1, 12))]
        limit = rng.randrange(2, 10)
        holes = {rng.randrange(0, 62) for _ in range(rng.randrange(0, 20))}

        def readable(address: int, holes: set[int] = holes) -> bool:
            return address not in holes
        blocks = plan_reads(spans, limit, readable)
        wanted = {a + i for a, n in spans for i in range(n)}
        for address in wanted:
            assert covered(blocks, address)
        for block in blocks:
            assert 1 <= block.count <= limit
            assert block.start in wanted and block.start + block.count - 1 in wanted
            for address in range(block.start, block.start + block.count):
                assert address in wanted or readable(address), (spans, limit, blocks)
        starts = [block.start for block in blocks]
        assert starts == sorted(starts)
        for first, second in zip(blocks, blocks[1:]):
            assert first.start + first.count <= second.start        # no overlap


# --- CRC-16/MODBUS --------------------------------------------------------------------


def test_crc16_equals_pymodbus_on_random_frames_of_every_length():
    from pymodbus.framer.rtu import FramerRTU

    rng = random.Random(7)
    for length in range(0, 257):
        for _ in range(3):
            data = bytes(rng.randrange(256) for _ in range(length))
            # pymodbus returns the two CRC bytes as a big-endian number, low byte first
            assert crc16(data).to_bytes(2, 'little') == \
                FramerRTU.compute_CRC(data).to_bytes(2, 'big'), data.hex()


def test_crc16_of_a_frame_with_its_crc_is_zero_and_one_flipped_bit_is_not():
    # Read 3 registers from 0x006B of unit 17, the usual RTU example frame (CRC 76 87)
    frame = bytes.fromhex('11 03 00 6B 00 03')
    crc = crc16(frame)
    assert crc == 0x8776            # sent as 76 87
    whole = frame + crc.to_bytes(2, 'little')
    assert crc16(whole) == 0
    for bit in range(8 * len(whole)):
        flipped = bytearray(whole)
        flipped[bit // 8] ^= 1 << (bit % 8)
        assert crc16(bytes(flipped)) != 0
