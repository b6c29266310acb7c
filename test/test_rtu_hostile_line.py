"""The RTU master against a hostile line: late replies, wrong echoes, trailing bytes.

Real frames over a pseudo-terminal (``SimulatedRtuLine`` with ``LineFaults``). A
phantom value is a read that returns registers the requested address does not
hold: the target is none, whatever the line does.
"""

from __future__ import annotations

import random

import pytest

from unit_support import shipped_profile
from vfd_ros2.errors import BadFrame, CommTimeout, ProtocolException, TransportError
from vfd_ros2.sim.model import SimulatedDrive
from vfd_ros2.sim.rtu_line import LineFaults, SimulatedRtuLine
from vfd_ros2.transports import modbus as modbus_transport
from vfd_ros2.transports import rtu_link
from vfd_ros2.transports.modbus import ModbusRtuTransport

TIMEOUT = 0.03
#: replies this much after the master's timeout (the guard, = timeout, covers them)
LATE = (TIMEOUT + 0.003, TIMEOUT + 0.028)
#: the guard where a late reply must never become a value: the simulated line's thread may
#: send one later than planned on a loaded machine, and one later than timeout + guard is
#: undetectable by the protocol (rtu_link's docstring); a late reply ends the guard early
GUARD = 0.08


def distinct_drive(unit: int) -> tuple[SimulatedDrive, list[tuple[int, list[int]]]]:
    """Make a drive whose read-write parameters hold distinct values, in 5-register blocks."""
    profile = shipped_profile('boneng_am')
    drive = SimulatedDrive(profile, unit)
    blocks: list[tuple[int, list[int]]] = []
    group = ['B00', 'B01', 'B02', 'B03', 'B04', 'B05', 'B06', 'B07']
    for prefix in group:
        codes = sorted((p for p in profile.parameters.values()
                        if p.code.startswith(prefix) and p.register_count == 1),
                       key=lambda p: p.address)
        for start in range(0, len(codes) - 5, 5):
            chunk = codes[start:start + 5]
            if chunk[-1].address - chunk[0].address != 4:
                continue
            values = [(unit << 12) ^ (p.address & 0x0FFF) for p in chunk]
            for parameter, value in zip(chunk, values):
                drive.words[parameter.address] = value
            blocks.append((chunk[0].address, values))
    assert len(blocks) >= 6, 'enough same-length blocks to confuse a naive master'
    return drive, blocks


def run_reads(transport, plan, transactions, rng):
    """Read random blocks; return (good, phantoms, failures)."""
    good = phantoms = failures = 0
    for _ in range(transactions):
        unit, address, expected = rng.choice(plan)
        try:
            words = transport.read_registers(unit, address, len(expected))
        except (CommTimeout, BadFrame):
            failures += 1
            continue
        if words == expected:
            good += 1
        else:
            phantoms += 1
    return good, phantoms, failures


@pytest.mark.parametrize('deaf', [False, True], ids=['buffering slave', 'deaf slave'])
def test_late_replies_never_become_phantom_values(tmp_path, deaf):
    drive, blocks = distinct_drive(1)
    faults = LineFaults(late_rate=0.1, late_delay=LATE, late_deaf=deaf)
    line = SimulatedRtuLine([drive], tmp_path / 'line', baudrate=115200, faults=faults,
                            seed=7, tick_period=0.001).start()
    transport = ModbusRtuTransport(str(tmp_path / 'line'), 115200, timeout=TIMEOUT,
                                   late_reply_guard=GUARD)
    try:
        plan = [(1, address, values) for address, values in blocks]
        good, phantoms, failures = run_reads(transport, plan, 1000, random.Random(3))
    finally:
        transport.close()
        line.stop()
    assert line.stats.late_replies >= 60, 'the line really answered late'
    assert phantoms == 0
    assert failures >= line.stats.late_replies * 0.9, 'each late reply costs its transaction'
    assert good + failures == 1000
    unit = transport.stats_for(1)
    assert unit.timeouts >= line.stats.late_replies * 0.9
    assert unit.late_replies >= line.stats.late_replies * 0.9, 'late replies seen and counted'


def test_late_replies_on_a_bus_of_two(tmp_path):
    """A late reply of one unit is never taken for another unit's, nor its own next."""
    drive1, blocks1 = distinct_drive(1)
    drive2, blocks2 = distinct_drive(2)
    faults = LineFaults(late_rate=0.1, late_delay=LATE)
    line = SimulatedRtuLine([drive1, drive2], tmp_path / 'line', baudrate=115200,
                            faults=faults, seed=11, tick_period=0.001).start()
    transport = ModbusRtuTransport(str(tmp_path / 'line'), 115200, timeout=TIMEOUT,
                                   late_reply_guard=GUARD)
    try:
        plan = [(1, a, v) for a, v in blocks1] + [(2, a, v) for a, v in blocks2]
        good, phantoms, failures = run_reads(transport, plan, 1000, random.Random(5))
    finally:
        transport.close()
        line.stop()
    assert line.stats.late_replies >= 60
    assert phantoms == 0
    assert good >= 800


def test_single_write_echo_must_name_the_written_value(tmp_path):
    drive, _ = distinct_drive(1)
    line = SimulatedRtuLine([drive], tmp_path / 'line', faults=LineFaults(wrong_echo_rate=1.0),
                            tick_period=0.001).start()
    transport = ModbusRtuTransport(str(tmp_path / 'line'), 115200, timeout=TIMEOUT)
    address = drive.profile.parameter('B04.02').address
    try:
        with pytest.raises(BadFrame, match='echo names'):
            transport.write_register(1, address, 25)
        with pytest.raises(BadFrame, match='reply names'):
            transport.write_registers(1, address, [25, 26])
        line.faults.wrong_echo_rate = 0.0
        transport.write_register(1, address, 27)     # an honest echo is accepted
    finally:
        transport.close()
        line.stop()
    assert transport.stats_for(1).bad_frames == 2
    assert transport.stats_for(1).transactions == 1


def test_bytes_after_a_reply_make_it_a_bad_frame(tmp_path):
    drive, blocks = distinct_drive(1)
    line = SimulatedRtuLine([drive], tmp_path / 'line', faults=LineFaults(trailing_rate=1.0),
                            tick_period=0.001).start()
    transport = ModbusRtuTransport(str(tmp_path / 'line'), 115200, timeout=TIMEOUT)
    address, values = blocks[0]
    try:
        with pytest.raises(BadFrame, match='bytes after the reply'):
            transport.read_registers(1, address, len(values))
        line.faults.trailing_rate = 0.0
        assert transport.read_registers(1, address, len(values)) == values
    finally:
        transport.close()
        line.stop()
    assert transport.stats_for(1).bad_frames == 1


def test_refused_register_is_a_protocol_exception_not_a_comm_failure(tmp_path):
    drive, _ = distinct_drive(1)
    drive.refuse(['A00.15'])
    line = SimulatedRtuLine([drive], tmp_path / 'line', tick_period=0.001).start()
    transport = ModbusRtuTransport(str(tmp_path / 'line'), 115200, timeout=TIMEOUT)
    address = drive.profile.parameter('A00.15').address
    try:
        with pytest.raises(ProtocolException) as info:
            transport.read_registers(1, address, 1)
    finally:
        transport.close()
        line.stop()
    assert info.value.code == 2 and 'illegal data address' in info.value.text
    assert not isinstance(info.value, TransportError)
    assert transport.stats_for(1).exceptions == 1 and transport.stats_for(1).timeouts == 0


def test_an_echoing_adapter_is_read_back_and_checked(tmp_path):
    drive, blocks = distinct_drive(1)
    line = SimulatedRtuLine([drive], tmp_path / 'line', adapter_echo=True,
                            tick_period=0.001).start()
    plain = ModbusRtuTransport(str(tmp_path / 'line'), 115200, timeout=TIMEOUT)
    echoing = ModbusRtuTransport(str(tmp_path / 'line'), 115200, timeout=TIMEOUT, echo=True)
    address, values = blocks[0]
    try:
        # Without echo handling the master reads its own request as the reply.
        with pytest.raises((BadFrame, CommTimeout)):
            plain.read_registers(1, address, len(values))
        plain.close()
        for _ in range(20):
            assert echoing.read_registers(1, address, len(values)) == values
        echoing.write_register(1, address, 99)
    finally:
        plain.close()
        echoing.close()
        line.stop()
    assert echoing.stats_for(1).bad_frames == 0 and echoing.stats_for(1).transactions == 21


def test_low_latency_is_not_asked_of_a_pseudo_terminal(tmp_path):
    drive, _ = distinct_drive(1)
    line = SimulatedRtuLine([drive], tmp_path / 'line').start()
    transport = ModbusRtuTransport(str(tmp_path / 'line'), 115200, timeout=TIMEOUT)
    try:
        transport.open()
        assert transport.link_notes == ()
    finally:
        transport.close()
        line.stop()


def test_low_latency_refused_by_a_real_serial_driver_is_reported():
    """A driver without TIOCSSERIAL (pyserial raises ValueError): the refusal is a note."""
    from vfd_ros2.transports.rtu_link import RtuLink

    class RefusingPort:
        def set_low_latency_mode(self, on: bool) -> None:
            raise ValueError('Failed to update ASYNC_LOW_LATENCY flag to True: [Errno 25]')

    class AcceptingPort:
        def __init__(self) -> None:
            self.asked = None

        def set_low_latency_mode(self, on: bool) -> None:
            self.asked = on

    link = RtuLink('/dev/ttyUSB7', 115200)
    notes = link._request_low_latency(RefusingPort())
    assert len(notes) == 1 and 'low-latency mode refused' in notes[0] and '16 ms' in notes[0]
    accepting = AcceptingPort()
    assert link._request_low_latency(accepting) == () and accepting.asked is True


def test_the_master_keeps_t35_after_every_reply_on_a_timed_wire(tmp_path):
    """The silence after a reply runs from its last byte; never shorter than t3.5 on the wire.

    The simulated line times each byte at the baud rate and counts any request that
    begins less than t3.5 after the previous reply ended (``gap_violations``).
    """
    drives = [distinct_drive(unit) for unit in (1, 2)]
    line = SimulatedRtuLine([drive for drive, _ in drives], tmp_path / 'line',
                            emulate_wire_time=True).start()
    transport = ModbusRtuTransport(str(tmp_path / 'line'), 115200, timeout=0.1)
    try:
        transport.open()
        for turn in range(100):
            for unit, (_, blocks) in enumerate(drives, 1):
                address, expected = blocks[turn % len(blocks)]
                assert transport.read_registers(unit, address, len(expected)) == expected
        assert line.stats.frames == 200
        assert line.stats.gap_violations == 0
    finally:
        transport.close()
        line.stop()


def test_a_port_another_process_holds_is_refused_with_the_reason():
    """Two drive_nodes on one RS-485 line: the second cannot open it, and says why."""
    import os
    import pty
    master, slave = pty.openpty()
    name = os.ttyname(slave)
    first = ModbusRtuTransport(name, baudrate=19200, parity='N', stopbits=1, timeout=0.1)
    second = ModbusRtuTransport(name, baudrate=19200, parity='N', stopbits=1, timeout=0.1)
    try:
        first.open()
        with pytest.raises(TransportError, match='another process or node holds the port'):
            second.open()
        first.close()
        second.open()                        # free once the first let go
    finally:
        first.close()
        second.close()
        os.close(master)
        os.close(slave)


def test_reads_stay_right_while_the_reused_requests_are_replaced(tmp_path, monkeypatch):
    # The transport reuses each read's request and the link its frame; with stores of
    # 3, every few reads empties them: a stale frame would read another block.
    monkeypatch.setattr(modbus_transport, 'REQUESTS_KEPT', 3)
    monkeypatch.setattr(rtu_link, 'FRAMES_KEPT', 3)
    drive, blocks = distinct_drive(1)
    line = SimulatedRtuLine([drive], tmp_path / 'line', baudrate=115200, seed=7).start()
    transport = ModbusRtuTransport(str(tmp_path / 'line'), 115200, timeout=0.2)
    rng = random.Random(5)
    plan = [(1, address + offset, values[offset:offset + count])
            for address, values in blocks for offset in range(5)
            for count in range(1, 6 - offset)]
    try:
        good, phantoms, failures = run_reads(transport, plan, 300, rng)
        assert len(transport._frames) <= 3            # noqa: SLF001
        assert len(transport._link._frames) <= 3            # noqa: SLF001
    finally:
        transport.close()
        line.stop()
    assert (good, phantoms, failures) == (300, 0, 0)


def test_writes_stay_right_while_the_reused_requests_are_replaced(tmp_path, monkeypatch):
    # Writes are reused too (a command that holds is the same frame every cycle), keyed
    # by their values: with stores of 3, a stale frame would write an earlier value.
    monkeypatch.setattr(modbus_transport, 'REQUESTS_KEPT', 3)
    monkeypatch.setattr(rtu_link, 'FRAMES_KEPT', 3)
    profile = shipped_profile('boneng_am')
    drive = SimulatedDrive(profile, 1)
    # read-write, one register, stopped or running: any value in range is stored as sent
    targets = [p for p in sorted(profile.parameters.values(), key=lambda p: p.address)
               if p.writable and p.register_count == 1 and p.minimum is not None
               and p.maximum is not None and p.maximum - p.minimum >= 4 * p.scale
               and p.code != profile.control.command][:4]
    assert len(targets) == 4
    line = SimulatedRtuLine([drive], tmp_path / 'line', baudrate=115200, seed=7).start()
    transport = ModbusRtuTransport(str(tmp_path / 'line'), 115200, timeout=0.2)
    rng = random.Random(11)
    try:
        for _ in range(120):
            parameter = rng.choice(targets)
            values = [parameter.to_raw(parameter.minimum + parameter.scale * rng.randrange(4))
                      for _ in range(2)]
            if rng.random() < 0.5:
                transport.write_register(1, parameter.address, values[0])
                assert drive.words[parameter.address] == values[0], parameter.code
            else:       # two registers from this one: the next address must take one too
                following = profile.parameter_at(parameter.address + 1)
                if following is None or following not in targets:
                    continue
                values[1] = following.to_raw(following.minimum + following.scale)
                transport.write_registers(1, parameter.address, values)
                assert [drive.words[parameter.address + n] for n in (0, 1)] == values
        assert len(transport._requests) <= 3               # noqa: SLF001
        assert len(transport._frames) <= 3                 # noqa: SLF001
        assert len(transport._link._frames) <= 3            # noqa: SLF001
        assert transport.stats_for(1).errors == 0
    finally:
        transport.close()
        line.stop()


def test_a_reply_from_another_unit_is_named_in_the_timeout(tmp_path):
    """A drive set to another address answers a request to unit 1 as unit 2.

    Discarded (it cannot be unit 1's reply), the wait times out: the error says a
    reply from unit 2 came instead, not only 'no reply' (a dead cable, it read). It
    stays a timeout, not retried: it cost one already, and a bus plans a failed
    exchange at one timeout.
    """
    import os
    import pty
    import struct
    import threading
    import time
    import tty

    from vfd_ros2.protocol.modbus_crc import crc16
    master, slave = pty.openpty()
    tty.setraw(master)
    stop = threading.Event()

    def answer_as_unit_2() -> None:
        while not stop.is_set():
            try:
                request = os.read(master, 256)
            except OSError:
                return
            if len(request) >= 8:
                pdu = bytes([2, 3, 2, 0x12, 0x34])
                os.write(master, pdu + struct.pack('<H', crc16(pdu)))
    thread = threading.Thread(target=answer_as_unit_2, daemon=True)
    thread.start()
    timeout = 0.25      # long beside a loaded machine's stalls, so that two show
    transport = ModbusRtuTransport(os.ttyname(slave), 115200, timeout=timeout)
    try:
        started = time.monotonic()
        with pytest.raises(CommTimeout, match='a reply from unit 2 came instead'):
            transport.read_registers(1, 0x100, 1)
        assert time.monotonic() - started < 1.8 * timeout, 'one timeout, not two'
    finally:
        transport.close()
        stop.set()
        os.close(master)
        os.close(slave)
        thread.join(1.0)
    assert transport.stats_for(1).timeouts == 1
    assert transport.stats_for(2).late_replies == 1


def test_a_frame_is_sized_as_pymodbus_sizes_it():
    """The link takes each function's sizing rule from pymodbus' PDU class once.

    Against pymodbus' own ``calculateRtuFrameSize`` for every function code (normal,
    exception, sub-functions) on random headers of every length up to a frame's.
    """
    from pymodbus.pdu import DecodePDU

    link = rtu_link.RtuLink('/dev/null', 115200)
    decoder = DecodePDU(is_server=False)
    rng = random.Random(3)
    for function in range(256):
        for _ in range(20):
            header = bytes([rng.randrange(256), function]) + bytes(
                rng.randrange(256) for _ in range(rng.randrange(0, 12)))
            try:
                pdu_class = decoder.lookupPduClass(header)
                expected = pdu_class.calculateRtuFrameSize(header) if pdu_class else 0
            except Exception:  # noqa: BLE001 - pymodbus raises on an unknown size
                expected = 0
            expected = expected if 4 <= expected <= rtu_link.MAX_FRAME else 0
            assert link._frame_size(header) == expected, header.hex(' ')   # noqa: SLF001


def test_a_read_reply_with_a_wrong_byte_count_is_a_bad_frame_not_values(tmp_path):
    """A well-formed frame (good CRC) whose byte count is not the request's: no values."""
    import os
    import pty
    import struct
    import threading
    import tty

    from vfd_ros2.protocol.modbus_crc import crc16
    master, slave = pty.openpty()
    tty.setraw(master)
    stop = threading.Event()

    def answer_one_register_short() -> None:
        while not stop.is_set():
            try:
                request = os.read(master, 64)
            except OSError:             # closed at the end of the test
                return
            unit, _function, _address, count = struct.unpack('>BBHH', request[:6])
            body = bytes([unit, 3, 2 * (count - 1)]) + bytes(2 * (count - 1))
            os.write(master, body + crc16(body).to_bytes(2, 'little'))

    server = threading.Thread(target=answer_one_register_short, daemon=True)
    server.start()
    transport = ModbusRtuTransport(os.ttyname(slave), 115200, timeout=0.2)
    try:
        with pytest.raises(BadFrame, match='byte count 4, not 6'):
            transport.read_registers(1, 0x100, 3)
        assert transport.stats_for(1).bad_frames == 1
        assert transport.stats_for(1).transactions == 0
    finally:
        stop.set()
        transport.close()
        os.close(master)
        os.close(slave)
