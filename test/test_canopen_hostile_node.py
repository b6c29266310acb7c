"""CANopen SDO against a node that is not the simulator: wrong, endless, refusing, silent.

The node here is a hand-built SDO server on a python-can virtual bus: it answers
each request with the frame a test picks. Whatever the reply does wrong, the
transport returns the right value or raises a clear error within its timeout,
never hangs the caller, and the next exchanges with the node get the right values.
"""

from __future__ import annotations

import struct
import threading
import time
import uuid
from typing import Callable

import can
import pytest

from vfd_ros2.errors import BadFrame, CommTimeout, ProtocolException
from vfd_ros2.protocol.values import ValueType
from vfd_ros2.transports.canopen import CanopenTransport, ObjectEntry

NODE = 5
INDEX = 0x2000
VALUE = 0x12345678
TIMEOUT = 0.1

#: (request data, the right reply) -> frames to send as (COB-ID, data)
Answer = Callable[[bytes, bytes], list[tuple[int, bytes]]]


def _right_reply(request: bytes) -> bytes:
    multiplexer = request[1:4]
    if request[0] >> 5 == 2:                     # initiate upload: expedited, 4 bytes
        return bytes([0x43]) + multiplexer + struct.pack('<I', VALUE)
    return bytes([0x60]) + multiplexer + bytes(4)     # initiate download: confirmed


def _sdo_reply(data: bytes) -> list[tuple[int, bytes]]:
    return [(0x580 + NODE, data)]


class HostileNode:
    """An SDO server for node ``NODE``; ``answer`` None answers right."""

    def __init__(self, channel: str) -> None:
        self.answer: Answer | None = None
        self.segment_requests = 0
        self._bus = can.Bus(interface='virtual', channel=channel)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._serve, daemon=True)
        self._thread.start()

    def _serve(self) -> None:
        while not self._stop.is_set():
            message = self._bus.recv(0.02)
            if message is None or message.arbitration_id != 0x600 + NODE:
                continue
            request = bytes(message.data)
            if request[0] >> 5 == 3:             # upload segment request
                self.segment_requests += 1
                toggle = request[0] & 0x10
                frames = _sdo_reply(bytes([toggle]) + b'SEGMENT')  # never the last one
            elif request[0] >> 5 == 4:           # the client's abort: nothing to answer
                continue
            elif self.answer is None:
                frames = _sdo_reply(_right_reply(request))
            else:
                frames = self.answer(request, _right_reply(request))
            for cob_id, data in frames:
                self._bus.send(can.Message(arbitration_id=cob_id, data=data,
                                           is_extended_id=False))

    def close(self) -> None:
        self._stop.set()
        self._thread.join(2.0)
        self._bus.shutdown()


def _late(request: bytes, right: bytes) -> list[tuple[int, bytes]]:
    time.sleep(1.5 * TIMEOUT)
    return _sdo_reply(right)


def _other_object(request: bytes, right: bytes) -> list[tuple[int, bytes]]:
    return _sdo_reply(right[:1] + struct.pack('<H', INDEX + 1) + right[3:])


READ_CASES: dict[str, tuple[Answer, type[Exception] | None]] = {
    'another object': (_other_object, BadFrame),
    'another subindex': (lambda q, r: _sdo_reply(r[:3] + bytes([1]) + r[4:]), BadFrame),
    'fewer bytes than the type': (lambda q, r: _sdo_reply(bytes([0x4F]) + r[1:]), BadFrame),
    'a frame of 4 bytes': (lambda q, r: _sdo_reply(r[:4]), BadFrame),
    'an empty frame': (lambda q, r: _sdo_reply(b''), BadFrame),
    'a download reply': (lambda q, r: _sdo_reply(bytes([0x60]) + r[1:]), BadFrame),
    'an undefined command': (lambda q, r: _sdo_reply(bytes([0xE0]) + r[1:]), BadFrame),
    'a segmented transfer that never ends': (
        lambda q, r: _sdo_reply(bytes([0x41]) + r[1:4] + struct.pack('<I', 100000)), BadFrame),
    'an abort with an undefined code': (
        lambda q, r: _sdo_reply(bytes([0x80]) + r[1:4] + struct.pack('<I', 0x0BADC0DE)),
        ProtocolException),
    'the reply from another node': (lambda q, r: [(0x580 + NODE + 1, r)], CommTimeout),
    'silent': (lambda q, r: [], CommTimeout),
    'late': (_late, CommTimeout),
    'no size indicated': (lambda q, r: _sdo_reply(bytes([0x42]) + r[1:]), None),
    'the reply twice': (lambda q, r: _sdo_reply(r) * 2, None),
}

WRITE_CASES: dict[str, tuple[Answer, type[Exception] | None]] = {
    'another object': (_other_object, BadFrame),
    'an upload reply': (lambda q, r: _sdo_reply(bytes([0x43]) + r[1:]), BadFrame),
    'an empty frame': (lambda q, r: _sdo_reply(b''), BadFrame),
    'an abort': (lambda q, r: _sdo_reply(bytes([0x80]) + r[1:4] + struct.pack('<I', 0x06010002)),
                 ProtocolException),
    'silent': (lambda q, r: [], CommTimeout),
}


@pytest.fixture
def wired():
    channel = f'hostile{uuid.uuid4().hex[:8]}'
    node = HostileNode(channel)
    transport = CanopenTransport(interface='virtual', channel=channel, timeout=TIMEOUT)
    transport.attach(NODE, [ObjectEntry(INDEX, 0, 'value', ValueType.UINT32)], 0, 0)
    transport.open_node(NODE)
    yield node, transport
    transport.close()
    node.close()


def _exchanges_right(transport: CanopenTransport) -> None:
    for _ in range(3):
        assert transport.read_object(NODE, INDEX, 0, ValueType.UINT32) == VALUE
        transport.write_object(NODE, INDEX, 0, ValueType.UINT32, 7)


def _outcome(call: Callable[[], object], expected: type[Exception] | None) -> None:
    started = time.monotonic()
    if expected is None:
        call()
    else:
        with pytest.raises(expected):
            call()
    assert time.monotonic() - started < 2 * TIMEOUT + 0.5     # never a hang


@pytest.mark.parametrize('case', sorted(READ_CASES))
def test_a_read_gets_the_right_value_or_a_clear_error_and_the_next_exchanges_recover(
        wired, case):
    node, transport = wired
    answer, expected = READ_CASES[case]
    _exchanges_right(transport)
    node.answer = answer

    def read() -> None:
        assert transport.read_object(NODE, INDEX, 0, ValueType.UINT32) == VALUE
    _outcome(read, expected)
    node.answer = None
    if case == 'late':
        time.sleep(1.5 * TIMEOUT)
    _exchanges_right(transport)


@pytest.mark.parametrize('case', sorted(WRITE_CASES))
def test_a_write_is_confirmed_for_its_own_object_or_is_a_clear_error(wired, case):
    node, transport = wired
    answer, expected = WRITE_CASES[case]
    node.answer = answer
    _outcome(lambda: transport.write_object(NODE, INDEX, 0, ValueType.UINT32, 7), expected)
    node.answer = None
    _exchanges_right(transport)


def test_an_endless_segmented_upload_is_aborted_after_two_segments(wired):
    node, transport = wired
    node.answer = READ_CASES['a segmented transfer that never ends'][0]
    with pytest.raises(BadFrame, match='more than 8 bytes'):
        transport.read_object(NODE, INDEX, 0, ValueType.UINT32)
    assert node.segment_requests == 2
