"""Modbus TCP against a slave that is not the simulator: late, wrong, refusing, silent.

The slave here is a plain socket server that builds its MBAP frames by hand, so
it can break them the ways a foreign Ethernet card or a gateway does. Whatever a
reply does wrong, the transport either returns the right registers or raises a
clear TransportError / ProtocolException within its timeout, and the next reads
on the same transport get the right values (no reply is ever taken for another).
"""

from __future__ import annotations

import os
import socket
import struct
import threading
import time
from typing import Callable

import pytest

from vfd_ros2.errors import BadFrame, CommTimeout, ProtocolException, TransportError
from vfd_ros2.transports.modbus import ModbusTcpTransport

TIMEOUT = 0.2

#: a reply builder: (transaction id, unit, request PDU, the correct reply PDU) -> bytes sent
Misbehaviour = Callable[[int, int, bytes, bytes], bytes]


def _mbap(tid: int, unit: int, pdu: bytes, protocol: int = 0, length: int | None = None
          ) -> bytes:
    return struct.pack('>HHHB', tid, protocol, len(pdu) + 1 if length is None else length,
                       unit) + pdu


def _correct_pdu(pdu: bytes) -> bytes:
    """Return the right reply: holding register n holds n; a write is echoed."""
    function, address, count = struct.unpack('>BHH', pdu[:5])
    if function == 3:
        return bytes([3, 2 * count]) + b''.join(struct.pack('>H', (address + i) & 0xFFFF)
                                                for i in range(count))
    return pdu[:5]


class HostileSlave:
    """Answers each request with ``self.behaviour`` (None: correctly)."""

    def __init__(self, port: int = 0) -> None:
        self.behaviour: Misbehaviour | None = None
        self.close_after_reply = False       # as some gateways do: one reply per connection
        self.reset_on_request = False        # RST instead of a reply (a gateway that is full)
        self._server = socket.create_server(('127.0.0.1', port))
        self.port = self._server.getsockname()[1]
        self._connections: list[socket.socket] = []
        self._threads = [threading.Thread(target=self._accept, daemon=True)]
        self._threads[0].start()

    def _accept(self) -> None:
        while True:
            try:
                connection, _ = self._server.accept()
            except OSError:
                return
            self._connections.append(connection)
            self._threads.append(threading.Thread(target=self._serve, args=(connection,),
                                                  daemon=True))
            self._threads[-1].start()

    def _serve(self, connection: socket.socket) -> None:
        received = b''
        while True:
            try:
                data = connection.recv(4096)
            except OSError:
                return
            if not data:
                return
            received += data
            while len(received) >= 8:
                tid, _protocol, length, unit = struct.unpack('>HHHB', received[:7])
                pdu, received = received[7:6 + length], received[6 + length:]
                if self.reset_on_request:
                    connection.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER,
                                          struct.pack('ii', 1, 0))
                    connection.close()
                    return
                behaviour = self.behaviour
                correct = _correct_pdu(pdu)
                reply = _mbap(tid, unit, correct) if behaviour is None else \
                    behaviour(tid, unit, pdu, correct)
                if reply is None:            # close the connection instead
                    connection.close()
                    return
                try:
                    connection.sendall(reply)
                except OSError:
                    return
                if self.close_after_reply:
                    connection.close()
                    return

    def close(self) -> None:
        # shutdown() wakes a thread blocked in accept() or recv(); close() alone does not.
        for sock in (self._server, *self._connections):
            try:
                sock.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass
            sock.close()
        for thread in self._threads:
            thread.join(2.0)


def _late(tid: int, unit: int, pdu: bytes, correct: bytes) -> bytes:
    time.sleep(1.5 * TIMEOUT)                # after the master gave up
    return _mbap(tid, unit, correct)


#: name -> (behaviour, the error expected: None = the right value)
READ_CASES: dict[str, tuple[Misbehaviour, type[Exception] | None]] = {
    'another transaction id': (lambda t, u, p, c: _mbap(t + 7, u, c), BadFrame),
    'another unit': (lambda t, u, p, c: _mbap(t, u + 1, c), BadFrame),
    'another function': (lambda t, u, p, c: _mbap(t, u, bytes([4]) + c[1:]), BadFrame),
    'exception to another function': (lambda t, u, p, c: _mbap(t, u, bytes([0x84, 2])),
                                      BadFrame),
    'fewer registers than asked': (lambda t, u, p, c: _mbap(t, u, bytes([3, 2]) + c[2:4]),
                                   BadFrame),
    'byte count beyond the frame': (lambda t, u, p, c: _mbap(t, u, bytes([3, 8]) + c[2:]),
                                    TransportError),
    'protocol id not 0': (lambda t, u, p, c: _mbap(t, u, c, protocol=5), TransportError),
    'length field too long': (lambda t, u, p, c: _mbap(t, u, c, length=255), TransportError),
    'length field 0': (lambda t, u, p, c: _mbap(t, u, c, length=0), TransportError),
    'half a frame': (lambda t, u, p, c: _mbap(t, u, c)[:8], TransportError),
    'garbage': (lambda t, u, p, c: os.urandom(20), TransportError),
    'silent': (lambda t, u, p, c: b'', CommTimeout),
    'late': (_late, CommTimeout),
    'connection closed': (lambda t, u, p, c: None, TransportError),
    'exception 2': (lambda t, u, p, c: _mbap(t, u, bytes([0x83, 2])), ProtocolException),
    'undefined exception code': (lambda t, u, p, c: _mbap(t, u, bytes([0x83, 0x77])),
                                 ProtocolException),
    'the reply twice': (lambda t, u, p, c: _mbap(t, u, c) * 2, None),
    'a babbling slave': (lambda t, u, p, c: os.urandom(20000), TransportError),
    'bytes after the reply': (lambda t, u, p, c: _mbap(t, u, c) + b'\x00\x01', None),
}


@pytest.fixture
def slave():
    made = HostileSlave()
    yield made
    made.close()


@pytest.fixture
def transport(slave):
    made = ModbusTcpTransport('127.0.0.1', slave.port, timeout=TIMEOUT)
    yield made
    made.close()


def _reads_back_right(transport: ModbusTcpTransport) -> None:
    for offset in range(3):
        address = 0x200 + 16 * offset
        assert transport.read_registers(1, address, 2) == [address, address + 1]


@pytest.mark.parametrize('case', sorted(READ_CASES))
def test_a_read_gets_the_right_value_or_a_clear_error_and_the_next_reads_recover(
        slave, transport, case):
    behaviour, expected = READ_CASES[case]
    _reads_back_right(transport)             # connected and working first
    slave.behaviour = behaviour
    started = time.monotonic()
    if expected is None:
        assert transport.read_registers(1, 0x100, 2) == [0x100, 0x101]
    else:
        with pytest.raises(expected):
            transport.read_registers(1, 0x100, 2)
    assert time.monotonic() - started < TIMEOUT + 0.5
    slave.behaviour = None
    if case == 'late':
        time.sleep(1.5 * TIMEOUT)            # the late reply arrives before the next request
    _reads_back_right(transport)


def test_a_timeout_that_heard_only_an_earlier_requests_late_reply_is_a_timeout(slave,
                                                                                transport):
    """A slave whose replies come 1.5 timeouts late: each wait hears the one before.

    pymodbus skips it (another transaction id) and times out; the bytes it heard were
    counted as a malformed reply (outside audit). Now: a timeout and a late reply.
    """
    _reads_back_right(transport)
    delays = [1.5 * TIMEOUT, 1.5 * TIMEOUT]

    def late(tid: int, unit: int, pdu: bytes, correct: bytes) -> bytes:
        if delays:
            time.sleep(delays.pop(0))
        return _mbap(tid, unit, correct)
    slave.behaviour = late
    with pytest.raises(CommTimeout):
        transport.read_registers(1, 0x100, 2)
    with pytest.raises(CommTimeout, match='only a late one to an earlier request'):
        transport.read_registers(1, 0x110, 2)
    stats = transport.stats
    assert (stats.timeouts, stats.late_replies, stats.bad_frames) == (2, 1, 0)
    time.sleep(1.5 * TIMEOUT)               # the second late reply arrives before the next
    _reads_back_right(transport)


def test_a_connection_reset_by_the_peer_is_a_lost_link_not_a_bad_frame(slave, transport):
    """A gateway that takes one connection resets the second: counted as bad frames before."""
    _reads_back_right(transport)
    slave.reset_on_request = True
    with pytest.raises(TransportError, match='link lost'):
        transport.read_registers(1, 0x100, 2)
    assert transport.stats.bad_frames == 0 and transport.stats.connect_failures >= 1
    slave.reset_on_request = False
    _reads_back_right(transport)


def test_a_write_whose_echo_names_another_value_is_refused(slave, transport):
    slave.behaviour = lambda t, u, p, c: _mbap(t, u, c[:3] + struct.pack('>H', 0x1234))
    with pytest.raises(BadFrame, match='echo names 0x1234'):
        transport.write_register(1, 0x300, 7)
    slave.behaviour = None
    transport.write_register(1, 0x300, 7)


def test_a_refused_connection_is_a_transport_error_and_a_later_listener_is_reached():
    probe = socket.create_server(('127.0.0.1', 0))
    port = probe.getsockname()[1]
    probe.close()                            # nothing listens on the port now
    transport = ModbusTcpTransport('127.0.0.1', port, timeout=TIMEOUT)
    with pytest.raises(TransportError, match='cannot open'):
        transport.read_registers(1, 0x100, 1)
    assert transport.stats.connect_failures == 1
    slave = HostileSlave(port)               # a slave starts listening there
    try:
        assert transport.read_registers(1, 0x100, 1) == [0x100]
    finally:
        transport.close()
        slave.close()


def test_a_slave_that_closes_after_every_reply_is_reconnected_not_failed(slave, transport):
    """A card or gateway that closes the connection after each reply (or when idle).

    Sent into a connection the peer closed, every other exchange failed (link
    lost); the transport sees the close before it sends and connects afresh.
    """
    slave.close_after_reply = True
    for _ in range(2):
        for offset in range(10):             # back to back, as a poll cycle reads
            address = 0x100 + offset
            assert transport.read_registers(1, address, 1) == [address]
        time.sleep(0.05)                     # and after a pause
    assert transport.stats.errors == 0, transport.stats


@pytest.mark.parametrize('code, lasting', [(0x0B, False), (0x0A, False), (2, True)])
def test_only_a_not_readable_exception_takes_a_status_value_out_of_the_poll(slave, code,
                                                                             lasting):
    """A gateway whose RS-485 drive is gone for a moment answers 0x0B (0x0A: no path).

    Such a refusal passes: it is a failed exchange (the drive goes offline after
    comm_loss_threshold cycles and is reconnected), never a value refused until
    the next connect: two of them used to leave the drive blocked, online and
    answering, until the node restarted. Illegal address (2) is the drive's
    lasting answer: that value is polled no more.
    """
    from vfd_ros2.control.factory import build_controller
    drive = build_controller({'drive.profile': 'imo_hd2', 'transport.type': 'modbus_tcp',
                              'transport.host': '127.0.0.1', 'transport.port': slave.port,
                              'transport.timeout': TIMEOUT}).drive
    drive.open()
    try:
        assert not drive.poll(0).unavailable
        slave.behaviour = lambda t, u, p, c: _mbap(t, u, bytes([p[0] | 0x80, code]))
        for cycle in (1, 2, 3):
            if lasting:
                drive.poll(cycle)
            else:
                with pytest.raises(TransportError, match='failed exchange'):
                    drive.poll(cycle)
        slave.behaviour = None
        reading = drive.poll(4)
        assert bool(reading.unavailable) is lasting and bool(reading.unsafe) is lasting, \
            reading.unavailable
    finally:
        drive.close()
