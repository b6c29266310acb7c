"""The Kinco manual's SDO frames, byte for byte, on python-can's virtual bus (no ROS).

A listener bus on the same channel captures what the driver sends; the drive
side is either the simulated twin or a responder that answers with the manual's
printed frames (test/vectors/kinco_ec_frames.yaml, sdo_frames).
"""

from __future__ import annotations

import logging
import threading
import time
import uuid
from pathlib import Path

import can
import canopen
import pytest
import yaml

from harness import wait_for
from vfd_ros2.drives import drive_class_for
from vfd_ros2.drives.canopen import CanopenDrive
from vfd_ros2.errors import CommTimeout, ProtocolException, TransportError
from vfd_ros2.profiles import ValueType, load_profile
from vfd_ros2.protocol.scaling import VelocityScaling
from vfd_ros2.sim.canopen_drive import SimulatedCanBus, SimulatedCanopenDrive
from vfd_ros2.transports import load_transport_class
from vfd_ros2.transports.canopen import CanopenTransport, abort_text

SDO_ABORT_CODES = canopen.SdoAbortedError.CODES      # the library's CiA 301 table

VECTORS = Path(__file__).parent / 'vectors' / 'kinco_ec_frames.yaml'
FRAMES = {f['id']: f for f in yaml.safe_load(VECTORS.read_text(encoding='utf-8'))['sdo_frames']}


def frame_bytes(frame_id: str) -> tuple[int, bytes]:
    frame = FRAMES[frame_id]
    return frame['cob_id'], bytes.fromhex(frame['data'])


class Sniffer(can.Listener):
    def __init__(self, channel: str) -> None:
        self.bus = can.Bus(interface='virtual', channel=channel)
        self.frames: list[tuple[int, bytes]] = []
        self.notifier = can.Notifier(self.bus, [self])

    def on_message_received(self, msg: can.Message) -> None:
        self.frames.append((msg.arbitration_id, bytes(msg.data)))

    def close(self) -> None:
        self.notifier.stop()
        self.bus.shutdown()


class Responder(can.Listener):
    """Answers an SDO request with a scripted reply (the manual's frame)."""

    def __init__(self, channel: str, reply: tuple[int, bytes]) -> None:
        self.bus = can.Bus(interface='virtual', channel=channel)
        self.reply = reply
        self.notifier = can.Notifier(self.bus, [self])

    def on_message_received(self, msg: can.Message) -> None:
        if 0x600 < msg.arbitration_id < 0x680:
            self.bus.send(can.Message(arbitration_id=self.reply[0], data=self.reply[1],
                                      is_extended_id=False))

    def close(self) -> None:
        self.notifier.stop()
        self.bus.shutdown()


@pytest.fixture
def channel():
    return f'frames{uuid.uuid4().hex[:8]}'


def kinco_drive(channel: str) -> CanopenDrive:
    profile = load_profile('kinco_ec')
    transport = CanopenTransport(interface='virtual', channel=channel, timeout=0.2)
    drive = CanopenDrive(profile, transport, 1, VelocityScaling(1.0, False, 3000.0, 2))
    drive.open()
    return drive


def test_registered_by_name():
    cls = load_transport_class('canopen')
    assert cls is CanopenTransport and drive_class_for(cls) is CanopenDrive


def test_s1_s2_write_a0_03_byte_for_byte(channel):
    sim_bus = SimulatedCanBus([SimulatedCanopenDrive(load_profile('kinco_ec'), 1)],
                              channel).start()
    sniffer = Sniffer(channel)
    drive = kinco_drive(channel)
    try:
        value, _ = drive.set_parameter('A0.03', 1000, persistent=False, running=False)
        assert value.raw == 1000
        wait_for(lambda: frame_bytes('S2') in sniffer.frames, 2.0, 'S2 reply')
        sdo = [f for f in sniffer.frames if 0x580 < f[0] < 0x680]
        assert sdo[0] == frame_bytes('S1')          # 601: 2B 00 28 04 E8 03 00 00
        assert sdo[1] == frame_bytes('S2')          # 581: 60 00 28 04 00 00 00 00
    finally:
        drive.close()
        sniffer.close()
        sim_bus.stop()


def test_s4_s5_read_status_word_1(channel):
    responder = Responder(channel, frame_bytes('S5'))
    sniffer = Sniffer(channel)
    drive = kinco_drive(channel)
    try:
        value = drive.get_parameter('0x3300')
        assert value.raw == 0x0001                  # running forward, no fault (L941)
        # The sniffer's notifier thread may still be delivering: wait, do not race it.
        wait_for(lambda: sniffer.frames, 2.0, 'the request on the bus')
        assert sniffer.frames[0] == frame_bytes('S4')
    finally:
        drive.close()
        sniffer.close()
        responder.close()


@pytest.mark.parametrize('reply, code', [('S3', 0x06070010), ('S6', 0x06020000)])
def test_s3_s6_abort_frames_are_decoded(channel, reply, code):
    responder = Responder(channel, frame_bytes(reply))
    drive = kinco_drive(channel)
    try:
        with pytest.raises(ProtocolException) as error:
            drive.get_parameter('0x3300')
        assert error.value.code == code and error.value.text == SDO_ABORT_CODES[code]
        assert f'0x{code:08X}' in str(error.value) and SDO_ABORT_CODES[code] in str(error.value)
    finally:
        drive.close()
        responder.close()


@pytest.mark.parametrize('index, sub, value_type, code', [
    (0x2D00, 0, ValueType.UINT16, 0x06020000),     # object does not exist
    (0x2800, 0x0B, ValueType.UINT16, 0x06090011),  # sub-index does not exist
    (0x2B00, 0, ValueType.UINT16, 0x06010002),     # status word 1 is read-only (write)
    (0x2800, 0x04, ValueType.UINT32, 0x06070010),  # 4 bytes to a 2-byte object
    (0x2800, 0x04, ValueType.UINT16, 0x06090031),  # A0.03 = 20000 > 10000
])
def test_twin_answers_spec_abort_codes(channel, index, sub, value_type, code):
    sim_bus = SimulatedCanBus([SimulatedCanopenDrive(load_profile('kinco_ec'), 1)],
                              channel).start()
    drive = kinco_drive(channel)
    try:
        with pytest.raises(ProtocolException) as error:
            if code == 0x06020000 or code == 0x06090011:
                drive.transport.read_object(1, index, sub, value_type)
            else:
                drive.transport.write_object(1, index, sub, value_type, 20000)
        assert error.value.code == code, str(error.value)
        assert error.value.text == abort_text(code)
    finally:
        drive.close()
        sim_bus.stop()


def test_no_reply_is_a_timeout_not_a_hang(channel):
    drive = kinco_drive(channel)
    try:
        with pytest.raises(CommTimeout) as error:
            drive.get_parameter('0x3300')
        assert 'no SDO reply' in str(error.value)
        assert drive.transport.stats.timeouts == 1 and drive.stats.timeouts == 1
    finally:
        drive.close()


def test_rpdo_frame_little_endian_and_signed(channel):
    """RPDO1 as the library's PdoMap packs it: control word, then target velocity (int32)."""
    sim_bus = SimulatedCanBus([SimulatedCanopenDrive(load_profile('cia402_velocity'), 1)],
                              channel).start()
    sniffer = Sniffer(channel)
    transport = CanopenTransport(interface='virtual', channel=channel, timeout=0.2)
    drive = CanopenDrive(load_profile('cia402_velocity'), transport, 1,
                         VelocityScaling(1.0, False, 3000.0, 2))
    try:
        drive.open()
        drive.configure(drive.host_loss_plan(0.3, 0.02), apply_commissioning=True)
        payload = transport.transmit(1, 1, [0x000F, -100])
        assert payload == bytes.fromhex('0F 00 9C FF FF FF')
        wait_for(lambda: (0x201, payload) in sniffer.frames, 2.0, 'RPDO1 on the bus')
    finally:
        drive.close()
        sniffer.close()
        sim_bus.stop()


def test_unknown_abort_code_text():
    assert 'unknown SDO abort code 0x12345678' == abort_text(0x12345678)
    assert abort_text(0x06020000) == SDO_ABORT_CODES[0x06020000]


def configured_cia402(channel: str, **settings) -> tuple[CanopenDrive, CanopenTransport]:
    transport = CanopenTransport(interface='virtual', channel=channel, timeout=0.2, **settings)
    drive = CanopenDrive(load_profile('cia402_velocity'), transport, 1,
                         VelocityScaling(1.0, False, 3000.0, 2))
    drive.open()
    drive.configure(drive.host_loss_plan(0.3, 0.02), apply_commissioning=True)
    return drive, transport


def test_a_synchronous_rpdo_takes_effect_at_the_sync_that_ends_the_burst(channel):
    """cia402_velocity runs on SYNC: the twin applies RPDO1 only when the host's SYNC comes."""
    twin = SimulatedCanopenDrive(load_profile('cia402_velocity'), 1)
    sim_bus = SimulatedCanBus([twin], channel).start()
    sniffer = Sniffer(channel)
    drive, transport = configured_cia402(channel)
    try:
        assert transport.read_object(1, 0x1400, 2, ValueType.UINT8) == 1
        received = twin.rpdos_received
        transport.transmit(1, 1, [0x0006, 500])
        wait_for(lambda: twin.rpdos_received > received, 2.0, 'RPDO1 received')
        time.sleep(0.05)
        assert twin.target_raw == 0 and (0x80, b'') not in sniffer.frames   # not yet
        transport.end_command_burst()
        wait_for(lambda: twin.target_raw == 500, 2.0, 'RPDO1 applied at SYNC')
        assert transport.syncs == 1 and twin.syncs_received == 1
        # the sniffer's notifier thread may record the SYNC after the twin has applied it
        wait_for(lambda: (0x80, b'') in sniffer.frames, 2.0, 'SYNC seen by the sniffer')
        rpdo_at = sniffer.frames.index((0x201, bytes.fromhex('0600 F4010000')))
        assert sniffer.frames.index((0x80, b'')) > rpdo_at
        # the twin answers the SYNC with its synchronous TPDO1 (status word first)
        wait_for(lambda: any(cob == 0x181 for cob, _ in
                             sniffer.frames[sniffer.frames.index((0x80, b'')):]), 2.0,
                 'TPDO1 after the SYNC')
    finally:
        drive.close()
        sniffer.close()
        sim_bus.stop()


def test_no_sync_where_the_drive_is_event_driven_or_another_device_produces_it(channel):
    kinco_twin = SimulatedCanopenDrive(load_profile('kinco_ec'), 1)
    sim_bus = SimulatedCanBus([kinco_twin], channel).start()
    sniffer = Sniffer(channel)
    drive = kinco_drive(channel)
    try:
        drive.configure(drive.host_loss_plan(0.3, 0.02), apply_commissioning=True)
        assert drive.transport.read_object(1, 0x1400, 2, ValueType.UINT8) == 255
        drive.transport.end_command_burst()
        # the Kinco takes asynchronous PDOs only (manual L964): type 1 is refused
        with pytest.raises(ProtocolException, match='0x06090030'):
            drive.transport.write_object(1, 0x1400, 2, ValueType.UINT8, 1)
    finally:
        drive.close()
        sim_bus.stop()
    # another device produces SYNC (every 20 ms): the drive's TPDOs come on it, and the
    # host sends none of its own
    other = f'{channel}b'
    twin = SimulatedCanopenDrive(load_profile('cia402_velocity'), 1)
    sim_bus = SimulatedCanBus([twin], other).start()
    sniffer_b = Sniffer(other)
    producer = can.Bus(interface='virtual', channel=other)
    produced, producing = [0], threading.Event()

    def produce() -> None:
        while not producing.wait(0.02):
            producer.send(can.Message(arbitration_id=0x80, data=b'', is_extended_id=False))
            produced[0] += 1
    thread = threading.Thread(target=produce, daemon=True)
    thread.start()
    try:
        drive, transport = configured_cia402(other, sync_producer=False)
        try:
            transport.transmit(1, 1, [0x0006, 0])
            transport.end_command_burst()
            time.sleep(0.05)
            assert transport.syncs == 0
        finally:
            drive.close()
    finally:
        producing.set()
        thread.join(1.0)
        producer.shutdown()
        sim_bus.stop()
    assert not any(cob == 0x80 for cob, _ in sniffer.frames)
    # the sniffer's notifier thread may still be taking the last SYNCs off its queue
    wait_for(lambda: sum(cob == 0x80 for cob, _ in sniffer_b.frames) == produced[0], 2.0,
             'every SYNC produced seen by the sniffer')
    assert produced[0] > 0
    sniffer.close()
    sniffer_b.close()


def test_two_transports_of_one_process_send_one_sync_per_burst(channel):
    """drive_nodes of one process on one channel: one SYNC after both RPDOs, not one each."""
    profile = load_profile('cia402_velocity')
    twins = [SimulatedCanopenDrive(profile, n) for n in (1, 2)]
    sim_bus = SimulatedCanBus(twins, channel).start()
    drives = []
    try:
        for n in (1, 2):
            transport = CanopenTransport(interface='virtual', channel=channel, timeout=0.2)
            drive = CanopenDrive(profile, transport, n, VelocityScaling(1.0, False, 3000.0, 2))
            drive.open()
            drive.configure(drive.host_loss_plan(0.3, 0.02), apply_commissioning=True)
            drives.append(drive)
        first, second = (d.transport for d in drives)
        first.transmit(1, 1, [0x0006, 10])
        second.transmit(2, 1, [0x0006, 20])
        first.end_command_burst()
        second.end_command_burst()            # the SYNC above came after its RPDO too
        assert (first.syncs, second.syncs) == (1, 0)
        wait_for(lambda: [t.target_raw for t in twins] == [10, 20], 2.0, 'both applied')
        second.transmit(2, 1, [0x0006, 30])   # a later RPDO needs a SYNC of its own
        second.end_command_burst()
        assert second.syncs == 1
        wait_for(lambda: twins[1].target_raw == 30, 2.0, 'applied at the second SYNC')
    finally:
        for drive in drives:
            drive.close()
        sim_bus.stop()


def test_a_node_that_ignores_nmt_start_is_not_taken_as_started(channel):
    """Its heartbeat keeps saying pre-operational: the connect fails and says so.

    It was taken online (no PDOs exchanged), dropped two heartbeats later and
    connected again at once: online and offline by turns, a reconnect every 0.3 s.
    """
    twin = SimulatedCanopenDrive(load_profile('cia402_velocity'), 1)
    twin.ignores_nmt_start = True
    sim_bus = SimulatedCanBus([twin], channel).start()
    transport = CanopenTransport(interface='virtual', channel=channel, timeout=0.2)
    drive = CanopenDrive(load_profile('cia402_velocity'), transport, 1,
                         VelocityScaling(1.0, False, 3000.0, 2))
    try:
        drive.open()
        plan = drive.host_loss_plan(0.3, 0.02)
        started = time.monotonic()
        with pytest.raises(TransportError, match='node 1 stays PRE-OPERATIONAL after NMT '
                                                 'start'):
            drive.configure(plan, apply_commissioning=True)
        assert time.monotonic() - started < 2.0
        assert twin.node.nmt.state == 'PRE-OPERATIONAL'
        twin.ignores_nmt_start = False              # it obeys again: the connect succeeds
        drive.forget_state()
        drive.configure(plan, apply_commissioning=True)
        assert twin.node.nmt.state == 'OPERATIONAL'
        assert transport.check_alive(1) in (None, 'OPERATIONAL')
    finally:
        drive.close()
        sim_bus.stop()


def test_reconnects_leave_no_pdo_subscriptions_behind(channel):
    """save() subscribes RPDOs as well; only TPDO ones were removed at a reconnect.

    Each reconnect of a node, on a channel kept open, left one callback on 0x201
    holding the old RemoteNode (200 reconnects: 201 callbacks, about 26 KB each).
    """
    twin = SimulatedCanopenDrive(load_profile('cia402_velocity'), 1)
    sim_bus = SimulatedCanBus([twin], channel).start()
    drive, transport = configured_cia402(channel)
    try:
        plan = drive.host_loss_plan(0.3, 0.02)
        for _ in range(3):                          # what a reconnect does
            drive.forget_state()
            drive.open()
            drive.configure(plan, apply_commissioning=True)
        subscribers = transport.channel.network.subscribers
        assert subscribers.get(0x201, []) == []     # its own RPDO1: never taken in
        assert len(subscribers.get(0x181, [])) == 1     # TPDO1: the live node's only
    finally:
        drive.close()
        sim_bus.stop()


def test_the_host_heartbeat_is_told_once_not_at_every_reopen(channel, caplog):
    """An offline drive reopens its channel at each attempt: an INFO line 3 times a second."""
    caplog.set_level(logging.DEBUG, logger='vfd_ros2.transports.canopen')
    for _ in range(3):
        transport = CanopenTransport(interface='virtual', channel=channel, timeout=0.2)
        transport.open()
        try:
            transport.produce_heartbeat(0.04)
        finally:
            transport.close()
    told = [r.levelno for r in caplog.records if 'host heartbeat as node' in r.getMessage()]
    assert told == [logging.INFO, logging.DEBUG, logging.DEBUG], told
