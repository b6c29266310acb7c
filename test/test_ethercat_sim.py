"""The simulated EtherCAT segment: codec and ESC rules without I/O, then SOEM over real frames.

The integration tests run pysoem (SOEM) on one end of a veth pair in a namespace
the test creates and the simulated slaves on the other end, in their own
process; nothing stands in for the protocol. They skip (saying why) without
root or pysoem.
"""

from __future__ import annotations

import struct
import time

import pytest

from ethercat_support import bring_to_op, cycle_until, exchange, pysoem
from harness import wait_for
from vfd_ros2.protocol.ethercat import ALState, MailboxType, Register
from vfd_ros2.sim.ethercat.catalog import BONENG_MH_EC, IMO_HD2_EC_TX508
from vfd_ros2.sim.ethercat.coe import CoeServer
from vfd_ros2.sim.ethercat.drive import Cia402VelocityDrive, sii_data, sii_image
from vfd_ros2.sim.ethercat.esc import Esc
from vfd_ros2.sim.ethercat.frame import (
    Command,
    Datagram,
    Frame,
    FrameError,
    decode_frame,
    wkc_increment,
)
from vfd_ros2.sim.ethercat.mailbox import MailboxServer, decode_mailbox, encode_mailbox
from vfd_ros2.sim.ethercat.segment import Segment
from vfd_ros2.sim.ethercat.sii import Category, build_image, categories, sii_checksum

pytest_plugins = ['ethercat_harness']

SAFE_OP_ERROR = 0x14

# ---------------------------------------------------------------------------------------
# frame codec (ETG.1000.4 5.3-5.4)


def test_frame_encode_layout_byte_for_byte():
    frame = Frame([Datagram.physical(Command.APRD, 0x12, 0x0000, 0x0130, 2),
                   Datagram.logical(Command.LRW, 0x13, 0x00010000, b'\xaa\xbb', wkc=3)])
    raw = frame.encode()
    assert raw[:6] == b'\xff' * 6 and raw[6:12] == b'\x01' * 6 and raw[12:14] == b'\x88\xa4'
    # EtherCAT header: length 2 x (10 + data + 2) = 28, type 1
    assert struct.unpack_from('<H', raw, 14)[0] == 28 | 0x1000
    # first datagram: APRD, idx, ADP 0, ADO 0x0130, len 2 | more-follows, irq, data, wkc
    assert raw[16:28] == bytes.fromhex('0112 0000 3001 0280 0000 0000'.replace(' ', ''))
    assert raw[28:30] == b'\x00\x00'
    # second: LRW, logical 0x00010000 little endian, no more-follows, data, wkc 3
    assert raw[30:40] == bytes.fromhex('0c13 00000100 0200 0000'.replace(' ', ''))
    assert raw[40:44] == b'\xaa\xbb\x03\x00'
    assert len(raw) == 60                                   # padded to the Ethernet minimum


def test_frame_decode_round_trip_keeps_padding_and_flags():
    frame = Frame([Datagram.physical(Command.FPWR, 7, 0x1001, 0x0120, b'\x02\x00'),
                   Datagram.physical(Command.BRD, 8, 0, 0x0000, 2)])
    raw = frame.encode()
    parsed = decode_frame(raw)
    assert [d.command for d in parsed.datagrams] == [Command.FPWR, Command.BRD]
    assert parsed.datagrams[0].more and not parsed.datagrams[1].more
    assert parsed.datagrams[0].adp == 0x1001 and parsed.datagrams[0].ado == 0x0120
    assert parsed.encode() == raw                           # same length back, as a segment
    circulating = Frame([Datagram(Command.NOP, 0, 0, bytearray(1), circulating=True)]).encode()
    assert decode_frame(circulating).datagrams[0].circulating


@pytest.mark.parametrize('raw, why', [
    (b'\xff' * 12 + b'\x08\x00' + bytes(46), 'EtherType'),
    (b'\xff' * 12 + b'\x88\xa4' + struct.pack('<H', 40 | 0x1000) + bytes(20), 'announces'),
    (b'\xff' * 12 + b'\x88\xa4' + struct.pack('<H', 12 | 0x1000)
     + struct.pack('<BBIHH', 1, 0, 0, 30, 0) + bytes(2), 'runs past'),
    (b'\xff' * 12 + b'\x88\xa4' + struct.pack('<H', 12 | 0x5000) + bytes(12), 'type'),
])
def test_frame_decode_rejects_malformed(raw, why):
    with pytest.raises(FrameError, match=why):
        decode_frame(raw)


@pytest.mark.parametrize('command, read, written, increment', [
    (Command.APRD, True, False, 1), (Command.FPRD, False, False, 0),
    (Command.BRD, True, False, 1), (Command.LRD, True, False, 1),
    (Command.APWR, False, True, 1), (Command.BWR, False, True, 1),
    (Command.LWR, False, True, 1),
    (Command.APRW, True, True, 3), (Command.FPRW, True, False, 1),
    (Command.BRW, False, True, 2),
    (Command.LRW, True, True, 3), (Command.LRW, True, False, 1), (Command.LRW, False, True, 2),
    (Command.ARMW, True, False, 1), (Command.FRMW, False, True, 1),
    (Command.NOP, True, True, 0),
])
def test_wkc_increment_rules(command, read, written, increment):
    assert wkc_increment(command, read, written) == increment


# ---------------------------------------------------------------------------------------
# SII (ETG.1000.6 5.4)


def test_sii_checksum_matches_a_real_eeprom_image():
    # words 0..6 and the checksum byte of a slave EEPROM image shipped with a
    # public EtherCAT stack's simulator: 0x22 is what the slave's ESC checked
    words = bytes.fromhex('8003006eff00ff000000000000002200')
    assert sii_checksum(words[:14]) == words[14]
    # the bit-serial form (data shifted through the register, then 8 zero bits) agrees
    crc = 0x48                               # 0xFF pre-shifted by one byte
    for byte in words[:14] + bytes(1):
        for bit in range(8):
            top = crc & 0x80
            crc = ((crc << 1) | (byte >> (7 - bit)) & 1) & 0xFF
            if top:
                crc ^= 0x07
    assert crc == 0x22


def test_sii_image_header_and_categories():
    image = sii_image(IMO_HD2_EC_TX508)
    assert image[14] == sii_checksum(image[:14]) and image[15] == 0
    vendor, product, revision, serial = struct.unpack_from('<IIII', image, 0x08 * 2)
    assert (vendor, product, revision, serial) == (0x4D8, 0x9252, 1, 1)
    assert struct.unpack_from('<HHHHH', image, 0x18 * 2) == (0x1000, 512, 0x1400, 512, 0x0004)
    found = categories(image)
    assert found[Category.STRINGS][:14] == b'\x01\x0cIMO-EtherCAT'
    assert found[Category.GENERAL][5] & 0x01                 # CoE: SDO supported
    sms = [struct.unpack_from('<HHBBBB', found[Category.SYNC_MANAGER], 8 * n) for n in range(4)]
    assert [(s[0], s[1], s[2], s[5]) for s in sms] == [
        (0x1000, 512, 0x26, 1), (0x1400, 512, 0x22, 2), (0x1800, 21, 0x64, 3),
        (0x1C00, 23, 0x20, 4)]
    # TxPDO 0x1A00 first: index, 8 entries, SM3; first entry 0x6041:0, 16 bits
    tx = found[Category.TXPDO]
    assert struct.unpack_from('<HBB', tx) == (0x1A00, 8, 3)
    assert struct.unpack_from('<HBBBB', tx, 8) == (0x6041, 0, 0, 0, 16)
    assert image.endswith(b'\xff')


def test_esc_refuses_an_image_with_a_bad_checksum():
    image = bytearray(sii_image(BONENG_MH_EC))
    image[0x04 * 2] = 0x34                                    # alias changed, CRC not
    esc = Esc(bytes(image), Cia402VelocityDrive(BONENG_MH_EC))
    status = struct.unpack_from('<H', esc.memory, Register.EEPROM_CONTROL)[0]
    assert status & 0x0800                                    # checksum error
    assert struct.unpack_from('<H', esc.memory, Register.STATION_ALIAS)[0] == 0
    good = build_image(sii_data(BONENG_MH_EC))
    assert not struct.unpack_from('<H', Esc(good, Cia402VelocityDrive(BONENG_MH_EC)).memory,
                                  Register.EEPROM_CONTROL)[0] & 0x0800


# ---------------------------------------------------------------------------------------
# ESC datagram rules, without I/O


def run(segment: Segment, *datagrams: Datagram) -> list[Datagram]:
    reply = segment.process(Frame(list(datagrams)).encode())
    assert reply is not None
    return decode_frame(reply).datagrams


def two_slaves() -> Segment:
    segment = Segment([Esc(sii_image(spec), Cia402VelocityDrive(spec))
                       for spec in (IMO_HD2_EC_TX508, BONENG_MH_EC)])
    for position in range(2):                      # as a master does: APWR station addresses
        (answer,) = run(segment, Datagram.physical(Command.APWR, 1, -position, 0x0010,
                                                   struct.pack('<H', 0x1001 + position)))
        assert answer.wkc == 1
    return segment


def test_auto_increment_addresses_slaves_in_order_and_counts_adp():
    segment = two_slaves()
    first, second, both = run(segment,
                              Datagram.physical(Command.APRD, 1, 0, 0x0010, 2),
                              Datagram.physical(Command.APRD, 2, 0xFFFF, 0x0010, 2),
                              Datagram.physical(Command.BRD, 3, 0, 0x0000, 2))
    assert (first.wkc, bytes(first.data)) == (1, b'\x01\x10')
    assert (second.wkc, bytes(second.data)) == (1, b'\x02\x10')
    assert first.adp == 2 and second.adp == 1                 # every slave incremented ADP
    assert both.wkc == 2 and both.adp == 2
    (nobody,) = run(segment, Datagram.physical(Command.APRD, 4, 5, 0x0010, 2))
    assert nobody.wkc == 0


def test_configured_address_read_write_and_read_only_registers():
    segment = two_slaves()
    hit, miss, type_write = run(
        segment,
        Datagram.physical(Command.FPRD, 1, 0x1002, Register.AL_STATUS, 2),
        Datagram.physical(Command.FPRD, 2, 0x1003, Register.AL_STATUS, 2),
        Datagram.physical(Command.FPWR, 3, 0x1001, Register.TYPE, b'\x99'))
    assert (hit.wkc, bytes(hit.data)) == (1, b'\x01\x00')      # INIT
    assert miss.wkc == 0
    assert type_write.wkc == 1                                # addressed and processed ...
    (check,) = run(segment, Datagram.physical(Command.FPRD, 4, 0x1001, Register.TYPE, 1))
    assert check.data[0] == 0x11                              # ... but type is read-only
    (swap,) = run(segment, Datagram.physical(Command.FPRW, 5, 0x1001, 0x0F80, b'\x5a'))
    assert swap.wkc == 3 and swap.data[0] == 0                 # read old, wrote new
    (armw,) = run(segment, Datagram.physical(Command.ARMW, 6, 0, 0x0F80, b'\x00'))
    assert armw.wkc == 2 and armw.data[0] == 0x5A             # 1 read + 1 write
    (frmw,) = run(segment, Datagram.physical(Command.FRMW, 7, 0x1002, 0x0F80, b'\x00'))
    assert frmw.wkc == 2 and frmw.data[0] == 0x5A             # slave 2 got it from the ARMW


def test_broadcast_read_ors_and_write_reaches_all():
    segment = two_slaves()
    (write,) = run(segment, Datagram.physical(Command.BWR, 1, 0, 0x0F81, b'\x03'))
    assert write.wkc == 2
    run(segment, Datagram.physical(Command.FPWR, 2, 0x1002, 0x0F81, b'\x0c'))
    (read,) = run(segment, Datagram.physical(Command.BRD, 3, 0, 0x0F81, 1))
    assert read.wkc == 2 and read.data[0] == 0x0F


def fmmu(logical: int, length: int, physical: int, kind: int) -> bytes:
    return struct.pack('<IHBBHBBB3x', logical, length, 0, 7, physical, 0, kind, 1)


def sm(start: int, length: int, control: int) -> bytes:
    return struct.pack('<HHBBBB', start, length, control, 0, 1, 0)


def test_logical_rw_counts_one_for_read_and_two_for_write_per_slave():
    segment = two_slaves()
    for address, base in ((0x1001, 0x1100), (0x1002, 0x1100)):
        # buffered SMs outside the PDI's control: plain process RAM behind FMMUs
        run(segment,
            Datagram.physical(Command.FPWR, 1, address, Register.FMMU0,
                              fmmu(0 if address == 0x1001 else 2, 2, base, 2)
                              + fmmu(4 if address == 0x1001 else 6, 2, base + 0x80, 1)))
    out_only, in_only, both = run(
        segment,
        Datagram.logical(Command.LRW, 1, 0, b'\x11\x22\x33\x44'),      # outputs of both
        Datagram.logical(Command.LRW, 2, 4, 4),                        # inputs of both
        Datagram.logical(Command.LRW, 3, 0, 8))
    assert out_only.wkc == 4                                  # 2 slaves x write (+2)
    assert in_only.wkc == 2                                   # 2 slaves x read (+1)
    assert both.wkc == 6                                      # 2 slaves x 3
    (lrd,) = run(segment, Datagram.logical(Command.LRD, 4, 0, 4))
    assert lrd.wkc == 0                                       # no read FMMU over outputs
    (readback,) = run(segment, Datagram.physical(Command.FPRD, 5, 0x1002, 0x1100, 2))
    assert bytes(readback.data) == b'\x00\x00'                # the last LRW wrote zeros


def test_mailbox_sm_blocks_reads_when_empty_and_writes_when_full():
    segment = two_slaves()
    esc = segment.escs[1]                                      # BONENG: mailbox 0x1000/0x1080
    run(segment, Datagram.physical(Command.FPWR, 1, 0x1002, Register.SM0,
                                   sm(0x1000, 128, 0x26) + sm(0x1080, 128, 0x22)))
    run(segment, Datagram.physical(Command.FPWR, 2, 0x1002, Register.AL_CONTROL, b'\x02\x00'))
    assert esc.al_state is ALState.PRE_OP
    (empty,) = run(segment, Datagram.physical(Command.FPRD, 3, 0x1002, 0x1080, 128))
    assert empty.wkc == 0                                     # nothing to read: no WKC
    # an SDO upload of 0x1018:1 through SM0, the reply appears in SM1
    request = encode_mailbox(MailboxType.COE, bytes.fromhex('0020') + bytes([0x40]) +
                             struct.pack('<HB', 0x1018, 1) + bytes(4), counter=1)
    (write,) = run(segment, Datagram.physical(Command.FPWR, 4, 0x1002, 0x1000,
                                              request.ljust(128, b'\x00')))
    assert write.wkc == 1
    (status,) = run(segment, Datagram.physical(Command.FPRD, 5, 0x1002, 0x080D, 1))
    assert status.data[0] & 0x08                              # SM1 full
    (read,) = run(segment, Datagram.physical(Command.FPRD, 6, 0x1002, 0x1080, 128))
    header, data = decode_mailbox(bytes(read.data))
    assert read.wkc == 1 and header.type == MailboxType.COE
    assert data[2] == 0x43 and data[6:10] == bytes(4)         # expedited, 4 bytes: vendor 0
    (again,) = run(segment, Datagram.physical(Command.FPRD, 7, 0x1002, 0x1080, 128))
    assert again.wkc == 0                                     # read empties the buffer


def test_al_state_machine_refuses_invalid_transitions_with_codes():
    segment = two_slaves()
    esc = segment.escs[0]
    run(segment, Datagram.physical(Command.FPWR, 1, 0x1001, Register.AL_CONTROL, b'\x08\x00'))
    assert esc.al_status == 0x11 and esc.al_status_code == 0x0011   # INIT -> OP invalid
    run(segment, Datagram.physical(Command.FPWR, 2, 0x1001, Register.AL_CONTROL, b'\x02\x00'))
    assert esc.al_status == 0x11                              # not acknowledged: ignored
    run(segment, Datagram.physical(Command.FPWR, 3, 0x1001, Register.AL_CONTROL, b'\x12\x00'))
    assert esc.al_status == 0x11 and esc.al_status_code == 0x0016   # no mailbox SMs set up
    run(segment, Datagram.physical(Command.FPWR, 4, 0x1001, Register.AL_CONTROL, b'\x13\x00'))
    assert esc.al_status == 0x11 and esc.al_status_code == 0x0013   # bootstrap
    run(segment, Datagram.physical(Command.FPWR, 5, 0x1001, Register.AL_CONTROL, b'\x11\x00'))
    assert (esc.al_status, esc.al_status_code) == (0x01, 0)           # acknowledged


# ---------------------------------------------------------------------------------------
# mailbox and CoE server, without I/O


def test_coe_segmented_download_and_upload_with_toggle_check():
    drive = Cia402VelocityDrive(BONENG_MH_EC)
    drive.state_changed(ALState.PRE_OP)
    coe = CoeServer(drive.read_object, drive.write_object, mailbox_size=128)
    blob = bytes(range(256)) + bytes(range(44))
    head = bytes.fromhex('0020')
    first = coe.handle(head + struct.pack('<BHBI', 0x21, 0x2FFF, 0, 300) + blob[:112])
    assert first == [bytes.fromhex('0030') + struct.pack('<BHB', 0x60, 0x2FFF, 0) + bytes(4)]
    rest, toggle = blob[112:], 0
    while rest:
        chunk, rest = rest[:119], rest[119:]
        last = 0 if rest else 1
        (reply,) = coe.handle(head + bytes([toggle << 4 | last]) + chunk)
        assert reply[2] == 0x20 | toggle << 4
        toggle ^= 1
    assert drive.od.value(0x2FFF) == blob
    (init,) = coe.handle(head + struct.pack('<BHB', 0x40, 0x2FFF, 0) + bytes(4))
    assert init[2] == 0x41 and struct.unpack_from('<I', init, 6)[0] == 300
    assert init[10:] == blob[:112]
    (bad,) = coe.handle(head + bytes([0x70]) + bytes(7))   # toggle 1 where 0 is due
    assert bad[2] == 0x80 and struct.unpack_from('<I', bad, 6)[0] == 0x05030000


def test_mailbox_repeated_counter_is_not_executed_twice():
    calls = []
    server = MailboxServer(128, {MailboxType.COE: lambda data: calls.append(data) or [b'ok']})
    message = encode_mailbox(MailboxType.COE, b'\x00\x20xyz', counter=3)
    server.receive(message)
    server.receive(message)
    assert len(calls) == 1 and server.repeats_ignored == 1 and server.pending() == 1
    server.receive(encode_mailbox(MailboxType.EOE, b'\x00\x00', counter=4))
    server.pop()
    header, data = decode_mailbox(server.pop())
    assert header.type == MailboxType.ERROR and data == struct.pack('<HH', 1, 2)


# ---------------------------------------------------------------------------------------
# SOEM (pysoem) against the simulated segment over real frames


pytestmark_integration = pytest.mark.skipif(pysoem is None, reason='pysoem is not installed')

MIXED = (IMO_HD2_EC_TX508, BONENG_MH_EC, BONENG_MH_EC, IMO_HD2_EC_TX508)


@pytestmark_integration
@pytest.mark.parametrize('count', [1, 2, 4])
def test_soem_finds_slaves_in_order_and_reads_identity_from_sii(count, start_segment,
                                                                soem_master):
    specs = MIXED[:count]
    segment = start_segment(specs)
    assert soem_master.config_init() == count
    assert [(s.name, s.man, s.id, s.rev) for s in soem_master.slaves] == [
        (spec.name, spec.vendor_id, spec.product_code, spec.revision) for spec in specs]
    # SOEM gave station addresses 0x1001... in line order; the ESCs hold them
    assert [segment.esc(n)['station_address'] for n in range(count)] == [
        0x1001 + n for n in range(count)]
    assert soem_master.state_check(pysoem.PREOP_STATE, 500_000) == pysoem.PREOP_STATE


@pytestmark_integration
def test_soem_maps_pdos_reaches_op_and_exchanges_process_data(start_segment, soem_master):
    segment = start_segment([BONENG_MH_EC, IMO_HD2_EC_TX508])
    soem_master.config_init()
    assert soem_master.config_map() == 4 + 4 + 21 + 23        # 0x1701/0x1B01 + 0x1600/0x1A00
    expected = bring_to_op(soem_master)
    assert expected == 6                                      # 2 slaves x (2 write + 1 read)
    boneng, imo = soem_master.slaves
    # BONENG CoE_VL: 0x7E ready, 0x7F run with 750 rpm (manual L3717-3751)
    boneng.output = struct.pack('<Hh', 0x7E, 750)
    imo.output = struct.pack('<HiiHHbIH', 0x06, 0, -300, 0, 0, 9, 0, 0)
    def ready():
        return (struct.unpack_from('<H', boneng.input)[0] & 0x6F == 0x21
                and struct.unpack_from('<H', imo.input)[0] & 0x6F == 0x21)

    cycle_until(soem_master, ready, 2.0, 'both drives READY_TO_SWITCH_ON')
    boneng.output = struct.pack('<Hh', 0x7F, 750)
    imo.output = struct.pack('<HiiHHbIH', 0x0F, 0, -300, 0, 0, 9, 0, 0)
    cycle_until(soem_master, lambda: struct.unpack_from('<H', boneng.input)[0] & 0x6F == 0x27,
                2.0, 'BONENG operation enabled')
    start = time.monotonic()
    cycle_until(soem_master, lambda: struct.unpack_from('<h', boneng.input, 2)[0] >= 30, 2.0,
                'BONENG speeding up')
    # 1500 rpm per 5 s (0x6048): ~300 rpm/s; the ramp must not jump to the setpoint
    assert struct.unpack_from('<h', boneng.input, 2)[0] < 300 * (time.monotonic() - start) + 60
    cycle_until(soem_master, lambda: struct.unpack_from('<i', imo.input, 6)[0] <= -30, 2.0,
                'IMO turning backwards in csv mode')
    assert struct.unpack_from('<b', imo.input, 16)[0] == 9    # 0x6061 follows 0x6060
    wkc = [exchange(soem_master) for _ in range(50)]
    assert wkc == [expected] * 50
    assert segment.drive(0)['state'] == 'OPERATION_ENABLED'


@pytestmark_integration
def test_pdo_assignment_written_in_pre_op_changes_the_mapping(start_segment, soem_master):
    start_segment([IMO_HD2_EC_TX508])
    soem_master.config_init()
    slave = soem_master.slaves[0]
    # CiA 301 procedure: clear the count, write the entries, set the count
    slave.sdo_write(0x1C12, 0, b'\x00')
    slave.sdo_write(0x1C12, 1, struct.pack('<H', 0x1601))        # controlword + 0x607A
    slave.sdo_write(0x1C12, 0, b'\x01')
    slave.sdo_write(0x1A01, 0, b'\x00')
    slave.sdo_write(0x1A01, 1, struct.pack('<I', 0x60410010))
    slave.sdo_write(0x1A01, 2, struct.pack('<I', 0x606C0020))
    slave.sdo_write(0x1A01, 0, b'\x02')
    slave.sdo_write(0x1C13, 0, b'\x00')
    slave.sdo_write(0x1C13, 1, struct.pack('<H', 0x1A01))
    slave.sdo_write(0x1C13, 0, b'\x01')
    def abort_of(call) -> int:
        with pytest.raises(pysoem.SdoError) as caught:
            call()
        return caught.value.abort_code

    # entries can only change while the count is 0 (ETG.1000.6 abort 0x06010003)
    assert abort_of(lambda: slave.sdo_write(0x1A01, 1, bytes(4))) == 0x06010003
    assert abort_of(lambda: slave.sdo_write(0x1C12, 1, struct.pack('<H', 0x1600))) == 0x06010003
    # entries are checked when the count is set: 0x6042 is 16 bits, not 32
    slave.sdo_write(0x1A02, 0, b'\x00')
    slave.sdo_write(0x1A02, 1, struct.pack('<I', 0x60420020))
    assert abort_of(lambda: slave.sdo_write(0x1A02, 0, b'\x01')) == 0x06040041
    assert soem_master.config_map() == 6 + 6
    assert bring_to_op(soem_master) == 3
    assert abort_of(lambda: slave.sdo_write(0x1C12, 0, b'\x00')) == 0x08000022   # PRE-OP only


@pytestmark_integration
def test_link_down_silences_the_segment_and_up_restores_it(start_segment, soem_master):
    segment = start_segment([BONENG_MH_EC])
    soem_master.config_init()
    expected = bring_to_op(soem_master)
    segment.link_down()
    assert exchange(soem_master) < 0                          # no frame came back
    segment.link_up()
    assert cycle_until(soem_master, lambda: exchange(soem_master) > 0, 2.0, 'frames again')
    assert exchange(soem_master) == expected


@pytestmark_integration
def test_soem_sdo_expedited_and_aborts(start_segment, soem_master):
    start_segment([IMO_HD2_EC_TX508])
    soem_master.config_init()
    slave = soem_master.slaves[0]
    assert struct.unpack('<I', slave.sdo_read(0x1018, 1))[0] == 0x4D8
    assert slave.sdo_read(0x1008, 0) == b'IMO-EtherCAT'
    slave.sdo_write(0x6048, 2, struct.pack('<H', 3))
    assert struct.unpack('<H', slave.sdo_read(0x6048, 2))[0] == 3
    # vendor function-code access: write 0x2000 = P00.10 << 16, read 0x2001 (L1818)
    slave.sdo_write(0x2000, 0, struct.pack('<I', 0x000A << 16))
    assert struct.unpack('<I', slave.sdo_read(0x2001, 0))[0] == 0x00011388
    for call, code in ((lambda: slave.sdo_read(0x5555, 0), 0x06020000),
                       (lambda: slave.sdo_read(0x1018, 9), 0x06090011),
                       (lambda: slave.sdo_write(0x1018, 1, b'\x01\x00\x00\x00'), 0x06010002),
                       (lambda: slave.sdo_write(0x6048, 2, b'\x01'), 0x06070013),
                       (lambda: slave.sdo_write(0x6060, 0, b'\x07'), 0x06090030)):
        with pytest.raises(pysoem.SdoError) as caught:
            call()
        assert caught.value.abort_code == code, caught.value.desc


@pytestmark_integration
def test_soem_sdo_segmented_transfers(start_segment, soem_master):
    start_segment([BONENG_MH_EC, IMO_HD2_EC_TX508])
    soem_master.config_init()
    for slave, size in zip(soem_master.slaves, (300, 1000)):
        # both exceed the slave's mailbox (128 / 512 bytes): segmented both ways
        blob = bytes((7 * n + size) & 0xFF for n in range(size))
        slave.sdo_write(0x2FFF, 0, blob)
        assert slave.sdo_read(0x2FFF, 0, size=2048) == blob
    with pytest.raises(pysoem.SdoError) as caught:
        soem_master.slaves[0].sdo_write(0x2FFF, 0, bytes(1500))
    assert caught.value.abort_code == 0x06070012              # longer than the object allows


@pytestmark_integration
def test_soem_receives_coe_emergency(start_segment, soem_master):
    segment = start_segment([BONENG_MH_EC])
    soem_master.config_init()
    slave = soem_master.slaves[0]
    received = []
    slave.add_emergency_callback(received.append)
    segment.call(0, 'inject_fault', 0x2310, 0x03, b'\x01\x02\x03\x04\x05')
    wait_for(lambda: slave.mbx_receive() is not None and received, 2.0, 'the emergency')
    emcy = received[0]
    assert (emcy.error_code, emcy.error_reg, emcy.b1, emcy.w1, emcy.w2) == (
        0x2310, 0x03, 0x01, 0x0302, 0x0504)
    assert struct.unpack('<H', slave.sdo_read(0x603F, 0))[0] == 0x2310
    wait_for(lambda: segment.drive(0)['state'] == 'FAULT', 2.0, 'FAULT')


@pytestmark_integration
def test_sm_watchdog_stops_the_drive_when_process_data_stops(start_segment, soem_master):
    segment = start_segment([BONENG_MH_EC])
    soem_master.config_init()
    slave = soem_master.slaves[0]
    slave.set_watchdog('processdata', 50)                     # 50 ms, divider 100 us
    bring_to_op(soem_master)
    slave.output = struct.pack('<Hh', 0x7E, 600)
    cycle_until(soem_master, lambda: segment.drive(0)['state'] == 'READY_TO_SWITCH_ON', 2.0,
                'ready')
    slave.output = struct.pack('<Hh', 0x7F, 600)
    cycle_until(soem_master, lambda: segment.drive(0)['velocity_rpm'] > 20, 2.0, 'running')
    # The last process data now, timed right after it: the check above may take a while
    # on a loaded machine, and the watchdog runs from the last frame, not from the check.
    exchange(soem_master)
    stopped_at = time.monotonic()
    esc = wait_for(lambda: (e := segment.esc(0))['al_status'] == SAFE_OP_ERROR and e, 2.0,
                   'SAFE-OP + error after the watchdog')
    assert esc['al_status_code'] == 0x001B and esc['watchdog_expired']
    assert time.monotonic() - stopped_at >= 0.045
    soem_master.read_state()
    assert (slave.state, slave.al_status) == (SAFE_OP_ERROR, 0x001B)
    assert pysoem.al_status_code_to_string(slave.al_status) == 'Sync manager watchdog'
    drive = wait_for(lambda: (d := segment.drive(0))['state'] == 'FAULT' and d, 3.0,
                     'the drive in FAULT after its fault reaction')
    assert drive['velocity_rpm'] == 0 and drive['error_code'] == 0x8250


@pytestmark_integration
def test_slave_vanishes_and_returns(start_segment, soem_master):
    segment = start_segment([IMO_HD2_EC_TX508, BONENG_MH_EC])
    soem_master.config_init()
    expected = bring_to_op(soem_master)
    assert exchange(soem_master) == expected
    segment.unplug(1)
    assert cycle_until(soem_master, lambda: exchange(soem_master) == 3, 1.0, 'WKC of one slave')
    # unplugged, the second slave gets no outputs: its watchdog (100 ms) expires
    cycle_until(soem_master, lambda: segment.esc(1)['al_status'] == SAFE_OP_ERROR, 2.0,
                "the unplugged slave's watchdog")
    soem_master.read_state()
    assert soem_master.slaves[0].state == pysoem.OP_STATE
    segment.replug(1)
    # back on the wire; its watchdog expired meanwhile: SAFE-OP + error until acknowledged
    second = soem_master.slaves[1]
    cycle_until(soem_master, lambda: soem_master.read_state() is not None
                and second.state == SAFE_OP_ERROR, 2.0, 'the returned slave in SAFE-OP+ERROR')
    assert second.al_status == 0x001B
    second.state = pysoem.SAFEOP_STATE + pysoem.STATE_ACK
    second.write_state()
    second.state = pysoem.OP_STATE
    second.write_state()
    cycle_until(soem_master, lambda: second.state_check(pysoem.OP_STATE, 1000)
                == pysoem.OP_STATE, 2.0, 'the returned slave in OP again')
    assert cycle_until(soem_master, lambda: exchange(soem_master) == expected, 1.0, 'full WKC')


@pytestmark_integration
def test_power_cycled_slave_is_recovered_and_reconfigured(start_segment, soem_master):
    segment = start_segment([BONENG_MH_EC, BONENG_MH_EC])
    soem_master.config_init()
    expected = bring_to_op(soem_master)
    segment.power_cycle(1)                                    # back in INIT, address 0
    assert cycle_until(soem_master, lambda: exchange(soem_master) == 3, 1.0, 'WKC drop')
    second = soem_master.slaves[1]
    assert second.state_check(pysoem.OP_STATE, 1000) != pysoem.OP_STATE
    assert second.recover(timeout=5000) > 0                   # SOEM finds it by position
    assert segment.esc(1)['station_address'] == 0x1002
    assert second.reconfig(timeout=5000) == pysoem.SAFEOP_STATE
    second.state = pysoem.OP_STATE
    second.write_state()
    cycle_until(soem_master, lambda: exchange(soem_master) == expected
                and second.state_check(pysoem.OP_STATE, 1000) == pysoem.OP_STATE, 2.0,
                'OP with the full WKC')


@pytestmark_integration
def test_refused_state_changes_report_the_al_status_code(start_segment, soem_master):
    segment = start_segment([IMO_HD2_EC_TX508, BONENG_MH_EC])
    soem_master.config_init()
    first, second = soem_master.slaves
    first.state = pysoem.OP_STATE                             # PRE-OP -> OP is not allowed
    first.write_state()
    assert first.state_check(pysoem.OP_STATE, 50_000) == pysoem.PREOP_STATE
    assert (first.state, first.al_status) == (pysoem.PREOP_STATE | 0x10, 0x0011)
    assert pysoem.al_status_code_to_string(0x0011) == 'Invalid requested state change'
    first.state = pysoem.PREOP_STATE + pysoem.STATE_ACK
    first.write_state()
    # the device refuses SAFE-OP (e.g. its mapping does not fit its firmware)
    segment.call(1, 'refuse_state', int(ALState.SAFE_OP), 0x0025)
    soem_master.config_map()
    assert soem_master.state_check(pysoem.SAFEOP_STATE, 200_000) != pysoem.SAFEOP_STATE
    soem_master.read_state()
    assert (first.state, second.state) == (pysoem.SAFEOP_STATE, pysoem.PREOP_STATE | 0x10)
    assert second.al_status == 0x0025


@pytestmark_integration
def test_distributed_clocks_and_sync0_check(start_segment, soem_master):
    segment = start_segment([IMO_HD2_EC_TX508, BONENG_MH_EC])
    soem_master.config_init()
    assert soem_master.config_dc()
    first, second = soem_master.slaves
    first.dc_sync(True, 1_000_000)                            # 1 ms: in the IMO's list
    second.dc_sync(True, 1_000_000)                           # the BONENG has no DC sync
    soem_master.config_map()                                  # requests SAFE-OP
    assert soem_master.state_check(pysoem.SAFEOP_STATE, 200_000) != pysoem.SAFEOP_STATE
    soem_master.read_state()
    assert first.state == pysoem.SAFEOP_STATE, \
        (first.state, pysoem.al_status_code_to_string(first.al_status))
    assert (second.state, second.al_status) == (pysoem.PREOP_STATE | 0x10, 0x0030)
    # system time runs: the reference clock's time comes back in every cycle
    before = soem_master.dc_time
    cycle_until(soem_master, lambda: soem_master.dc_time > before + 1_000_000, 1.0,
                'DC time advancing')
    assert abs(soem_master.dc_time - (time.time() - 946684800) * 1e9) < 5e9
    assert segment.esc(0)['al_status'] == pysoem.SAFEOP_STATE

