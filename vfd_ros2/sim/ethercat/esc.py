"""One simulated EtherCAT slave controller (ESC) and the generic part of its slave stack.

The ESC answers datagrams the way the chip does (ETG.1000.4 section 5-6; the
Beckhoff ESC datasheet section I/II describes the same registers):

- 4 KiB of registers plus process RAM (0x1000...), read/written by the physical
  commands (APxx, FPxx, Bxx, ARMW/FRMW) and, through FMMUs, the logical ones;
- addressing: auto increment (the slave that sees ADP 0; every slave increments
  ADP), configured station address 0x0010 or alias 0x0012 (if enabled in DL
  control), broadcast;
- working counter per ETG.1000.4 table 6 (``frame.wkc_increment``);
- SyncManagers 0x0800+: mailbox mode (one buffer, full/empty handshake, repeat
  request/ack) for SM0/SM1, 3-buffer mode for SM2/SM3; blocked accesses do not
  count in the working counter;
- SII EEPROM interface 0x0500-0x050F (read 4 or 8 bytes per command, write,
  reload), configuration words loaded at power-up with the CRC-8 check;
- AL control/status 0x0120/0x0130/0x0134 with the AL state machine of
  ETG.1000.6 6.4 (checks of the mailbox and process-data SyncManagers);
- watchdog divider 0x0400, PDI 0x0410 and process-data 0x0420 watchdogs; the
  process-data watchdog restarts on every completed SM2 write and, when it
  expires in OP, sends the slave to SAFE-OP with AL status code 0x001B;
- distributed clocks: receive-time latches 0x0900-0x090C and 0x0918 (written
  by any write to 0x0900), system time 0x0910 (local time + offset 0x0920;
  a write runs a simple time-control loop into 0x092C), delay 0x0928, SYNC
  activation 0x0981, start time 0x0990, cycle times 0x09A0/0x09A4.

Device firmware (object dictionary, process data, device-specific checks) is
the ``SlaveApplication``. Outputs and mailbox requests are handed to it after
the frame has passed (``end_frame``), as real firmware sees them after the ESC
raised its PDI interrupt: inputs answer the master one cycle later.

Not modelled: bit-granular FMMUs, ports 2/3, frame forwarding errors and
their counters (0x0300 only resets), SYNC0 pulses, the PDI watchdog expiring.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

from ...protocol.ethercat import (
    AL_ERROR_FLAG,
    AL_STATE_MASK,
    FMMU_SIZE,
    SM_SIZE,
    ALState,
    ALStatusCode,
    MailboxType,
    Register,
)
from .application import SlaveApplication, TransitionContext
from .coe import CoeServer, emergency
from .frame import (
    AUTO_INCREMENT_COMMANDS,
    BROADCAST_COMMANDS,
    CONFIGURED_ADDRESS_COMMANDS,
    LOGICAL_COMMANDS,
    READ_COMMANDS,
    WRITE_COMMANDS,
    Command,
    Datagram,
    wkc_increment,
)
from .mailbox import MailboxServer
from .sii import (
    WORD_ALIAS,
    WORD_CHECKSUM,
    WORD_PDI_CONTROL,
    WORD_RX_MAILBOX,
    sii_checksum,
)

REGISTER_SPACE = 0x1000
FMMU_COUNT = 8
SM_COUNT = 8

# SyncManager control register (0x0804) fields, ETG.1000.4 table 59
SM_MODE_MASK = 0x03
SM_MODE_BUFFERED = 0x00
SM_MODE_MAILBOX = 0x02
SM_DIRECTION_MASK = 0x0C
SM_DIRECTION_READ = 0x00          # ECAT reads (slave -> master)
SM_DIRECTION_WRITE = 0x04         # ECAT writes (master -> slave)
SM_WATCHDOG_TRIGGER = 0x40
SM_STATUS_MAILBOX_FULL = 0x08
SM_ACTIVATE_ENABLE = 0x01
SM_ACTIVATE_REPEAT = 0x02
SM_PDI_DEACTIVATE = 0x01
SM_PDI_REPEAT_ACK = 0x02

# EEPROM control/status register (0x0502), ESC datasheet section II 3.45
EEPROM_WRITE_ENABLE = 0x0001
EEPROM_READ_8_BYTES = 0x0040
EEPROM_COMMAND_MASK = 0x0700
EEPROM_CMD_NOP = 0x0000
EEPROM_CMD_READ = 0x0100
EEPROM_CMD_WRITE = 0x0200
EEPROM_CMD_RELOAD = 0x0400
EEPROM_CHECKSUM_ERROR = 0x0800
EEPROM_COMMAND_ERROR = 0x2000
EEPROM_WRITE_ERROR = 0x4000

# ECAT event request bits (0x0210), ETG.1000.4 6.3
EVENT_DL_STATUS = 0x0004
EVENT_AL_STATUS = 0x0008
EVENT_SM0 = 0x0010

#: valid AL transitions (ETG.1000.6 figure 19 / table 9); bootstrap is not offered
_TRANSITIONS = frozenset({
    (ALState.INIT, ALState.PRE_OP), (ALState.PRE_OP, ALState.SAFE_OP),
    (ALState.SAFE_OP, ALState.OP), (ALState.OP, ALState.SAFE_OP),
    (ALState.OP, ALState.PRE_OP), (ALState.OP, ALState.INIT),
    (ALState.SAFE_OP, ALState.PRE_OP), (ALState.SAFE_OP, ALState.INIT),
    (ALState.PRE_OP, ALState.INIT),
})

#: how long a SAFE-OP -> OP request waits for the first valid outputs
SAFE_OP_TO_OP_TIMEOUT_S = 1.0
#: DC propagation model: receive-time delay per ESC passed, ns
HOP_DELAY_NS = 500


def _writable_map() -> bytearray:
    """Bytes of the register space an EtherCAT master may write (ESC datasheet II table 2)."""
    flags = bytearray(REGISTER_SPACE)

    def allow(start: int, length: int) -> None:
        flags[start:start + length] = b'\x01' * length

    allow(Register.STATION_ADDRESS, 2)
    allow(Register.DL_CONTROL, 4)
    allow(0x0108, 2)                                   # physical read/write offset
    allow(Register.AL_CONTROL, 2)
    allow(Register.ECAT_EVENT_MASK, 2)
    allow(Register.RX_ERROR_COUNTER, 0x14)             # any write clears the counters
    allow(Register.WATCHDOG_DIVIDER, 2)
    allow(Register.WATCHDOG_TIME_PDI, 2)
    allow(Register.WATCHDOG_TIME_PROCESS_DATA, 2)
    allow(Register.WATCHDOG_COUNTER_PROCESS_DATA, 2)   # any write clears the counters
    allow(Register.EEPROM_CONFIG, 1)
    allow(Register.EEPROM_CONTROL, 14)
    allow(0x0510, 6)                                   # MII management
    allow(Register.FMMU0, FMMU_SIZE * 16)
    for sm in range(16):
        base = Register.SM0 + SM_SIZE * sm
        allow(base, 5)                                 # start, length, control
        allow(base + 6, 1)                             # activate (status 5, PDI control 7: RO)
    allow(Register.DC_RECEIVE_TIME_PORT0, 4)           # a write latches the receive times
    allow(Register.DC_SYSTEM_TIME, 8)                  # a write feeds the time-control loop
    allow(Register.DC_SYSTEM_TIME_OFFSET, 12)          # offset (8) + delay (4)
    allow(Register.DC_SPEED_COUNTER_START, 2)
    allow(Register.DC_TIME_FILTER, 2)
    allow(Register.DC_CYCLIC_UNIT_CONTROL, 2)
    allow(Register.DC_SYNC0_START_TIME, 8)
    allow(Register.DC_SYNC0_CYCLE_TIME, 10)            # SYNC0/1 cycle, latch control
    allow(0x0F00, 4)                                   # digital output data
    allow(0x0F80, 0x80)                                # user RAM
    return flags


_WRITABLE = _writable_map()


@dataclass
class _Fmmu:
    logical_start: int
    logical_end: int
    physical_start: int
    read: bool
    write: bool


@dataclass
class _SyncManager:
    number: int
    start: int
    end: int
    control: int

    @property
    def mailbox(self) -> bool:
        return self.control & SM_MODE_MASK == SM_MODE_MAILBOX

    @property
    def ecat_writes(self) -> bool:
        return self.control & SM_DIRECTION_MASK == SM_DIRECTION_WRITE


class Esc:
    """One ESC with its slave stack; all methods are called from the segment's thread."""

    def __init__(self, sii: bytes, application: SlaveApplication, *,
                 eeprom_read_bytes: int = 8, ram_bytes: int = 0x2000, name: str = '',
                 esc_type: int = 0x11, esc_revision: int = 0x00, esc_build: int = 0x0003) -> None:
        if eeprom_read_bytes not in (4, 8):
            raise ValueError('an ESC reads 4 or 8 EEPROM bytes per command')
        self.name = name
        self.app = application
        self.sii = bytearray(sii)
        self.eeprom_read_bytes = eeprom_read_bytes
        self.ram_bytes = ram_bytes
        self._identity = (esc_type, esc_revision, esc_build)
        self.memory = bytearray(REGISTER_SPACE + ram_bytes)
        self.downstream_link = False          # port 1 has a neighbour
        self._power_on_ns = 0
        self._frame_time_ns = 0
        self._frame_return_ns: int | None = None
        self._dc_correction_ns = 0
        self._fmmus: list[_Fmmu] = []
        self._sms: list[_SyncManager] = []
        self._mailbox_full = [False] * SM_COUNT          # per SM: mailbox buffer state
        self._sm1_last: bytes | None = None               # for the repeat request
        self._pending_mailbox: bytes | None = None       # completed SM0 buffer, for end_frame
        self._pending_outputs: bytes | None = None       # completed SM2 buffer, for end_frame
        self._outputs_valid = False                       # outputs received since SAFE-OP
        self._op_deadline: float | None = None            # SAFE-OP -> OP waiting for outputs
        self._watchdog_deadline: float | None = None
        self._watchdog_expired = False
        self._now = 0.0
        rx_offset, rx_size, tx_offset, tx_size = struct.unpack_from(
            '<HHHH', self.sii, WORD_RX_MAILBOX * 2)
        self.mailbox_layout = (rx_offset, rx_size, tx_offset, tx_size)
        self.coe = CoeServer(application.read_object, application.write_object, tx_size)
        self.mailbox = MailboxServer(tx_size or 1, {MailboxType.COE: self.coe.handle})
        self.power_on(0, 0.0)

    # -- power, reset ----------------------------------------------------------

    def power_on(self, now_ns: int, now: float) -> None:
        """Reset every register as after power-up and load the SII configuration area."""
        esc_type, revision, build = self._identity
        memory = self.memory
        memory[:] = bytes(len(memory))
        struct.pack_into('<BBHBBBB', memory, Register.TYPE, esc_type, revision, build,
                         FMMU_COUNT, SM_COUNT, self.ram_bytes // 1024, 0x0F)
        # features: FMMU bytewise, DC supported, DC 64 bit (ETG.1000.4 table 32)
        struct.pack_into('<H', memory, Register.FEATURES, 0x000C)
        struct.pack_into('<I', memory, Register.DL_CONTROL, 0x00000001)
        struct.pack_into('<H', memory, Register.AL_STATUS, ALState.INIT)
        struct.pack_into('<H', memory, Register.AL_CONTROL, ALState.INIT)
        # watchdog divider 2498 -> 100 us; both watchdogs 1000 x 100 us (datasheet defaults)
        struct.pack_into('<HHH', memory, Register.WATCHDOG_DIVIDER, 0x09C2, 0, 0)
        struct.pack_into('<H', memory, Register.WATCHDOG_TIME_PDI, 0x03E8)
        struct.pack_into('<H', memory, Register.WATCHDOG_TIME_PROCESS_DATA, 0x03E8)
        struct.pack_into('<H', memory, Register.WATCHDOG_STATUS_PROCESS_DATA, 0x0001)
        struct.pack_into('<H', memory, Register.EEPROM_CONTROL,
                         EEPROM_READ_8_BYTES if self.eeprom_read_bytes == 8 else 0)
        struct.pack_into('<H', memory, Register.DC_SPEED_COUNTER_START, 0x1000)
        struct.pack_into('<H', memory, Register.DC_TIME_FILTER, 0x0C00)
        for sm in range(SM_COUNT):
            memory[Register.SM0 + SM_SIZE * sm + 7] = SM_PDI_DEACTIVATE
        self._power_on_ns = now_ns
        self._dc_correction_ns = 0
        self._fmmus = []
        self._sms = []
        self._mailbox_full = [False] * SM_COUNT
        self._sm1_last = None
        self._pending_mailbox = None
        self._pending_outputs = None
        self._outputs_valid = False
        self._op_deadline = None
        self._watchdog_deadline = None
        self._watchdog_expired = False
        self._now = now
        self.mailbox.reset()
        self.coe.reset()
        self._reload_eeprom()
        self._update_dl_status()
        self.app.state_changed(ALState.INIT)

    def _reload_eeprom(self) -> None:
        """Load SII words 0..7 into the registers if the checksum is right (ETG.1000.6 5.4)."""
        control = self._u16(Register.EEPROM_CONTROL)
        stored = self.sii[WORD_CHECKSUM * 2]
        if sii_checksum(bytes(self.sii[:14])) != stored:
            self._set_u16(Register.EEPROM_CONTROL, control | EEPROM_CHECKSUM_ERROR)
            return
        self._set_u16(Register.EEPROM_CONTROL, control & ~EEPROM_CHECKSUM_ERROR)
        pdi_control = struct.unpack_from('<H', self.sii, WORD_PDI_CONTROL * 2)[0]
        self._set_u16(Register.PDI_CONTROL, pdi_control)
        self._set_u16(Register.STATION_ALIAS,
                      struct.unpack_from('<H', self.sii, WORD_ALIAS * 2)[0])

    # -- small helpers ---------------------------------------------------------

    def _u16(self, address: int) -> int:
        return struct.unpack_from('<H', self.memory, address)[0]

    def _set_u16(self, address: int, value: int) -> None:
        struct.pack_into('<H', self.memory, address, value & 0xFFFF)

    def _u32(self, address: int) -> int:
        return struct.unpack_from('<I', self.memory, address)[0]

    @property
    def station_address(self) -> int:
        return self._u16(Register.STATION_ADDRESS)

    @property
    def al_status(self) -> int:
        return self._u16(Register.AL_STATUS)

    @property
    def al_state(self) -> ALState:
        return ALState(self.al_status & AL_STATE_MASK)

    @property
    def al_status_code(self) -> int:
        return self._u16(Register.AL_STATUS_CODE)

    @property
    def watchdog_expired(self) -> bool:
        return self._watchdog_expired

    def set_downstream_link(self, present: bool) -> None:
        """Port 1 gained or lost its neighbour (the segment's topology changed)."""
        if present != self.downstream_link:
            self.downstream_link = present
            self._update_dl_status()
            self._raise_event(EVENT_DL_STATUS)

    def _update_dl_status(self) -> None:
        # 0x0110: PDI operational, PDI watchdog ok, link port 0, communication port 0;
        # port 1: link + communication, or loop closed; ports 2/3 absent: loop closed
        value = 0x0001 | 0x0002 | 0x0010 | 0x0200 | 0x5000
        if self._u16(Register.EEPROM_CONTROL) & EEPROM_CHECKSUM_ERROR:
            value &= ~0x0001
        value |= 0x0020 | 0x0800 if self.downstream_link else 0x0400
        self._set_u16(Register.DL_STATUS, value)

    def _raise_event(self, bits: int) -> None:
        self._set_u16(Register.ECAT_EVENT_REQUEST,
                      self._u16(Register.ECAT_EVENT_REQUEST) | bits)

    def _clear_event(self, bits: int) -> None:
        self._set_u16(Register.ECAT_EVENT_REQUEST,
                      self._u16(Register.ECAT_EVENT_REQUEST) & ~bits)

    # -- frame processing ------------------------------------------------------

    def begin_frame(self, arrival_ns: int, return_ns: int | None, now: float) -> None:
        """Start a frame reaching port 0 at ``arrival_ns`` (port 1 at ``return_ns``)."""
        self._frame_time_ns = arrival_ns
        self._frame_return_ns = return_ns
        self._now = now

    def process(self, datagram: Datagram) -> None:
        """Process one datagram as the frame passes this ESC."""
        command = datagram.command
        if command in AUTO_INCREMENT_COMMANDS:
            hit = datagram.adp == 0
            datagram.address = (datagram.address & 0xFFFF0000) | ((datagram.adp + 1) & 0xFFFF)
        elif command in CONFIGURED_ADDRESS_COMMANDS:
            adp = datagram.adp
            hit = adp == self.station_address or (
                bool(self.memory[Register.DL_CONTROL + 3] & 0x01)
                and adp == self._u16(Register.STATION_ALIAS))
        elif command in BROADCAST_COMMANDS:
            hit = True
            datagram.address = (datagram.address & 0xFFFF0000) | ((datagram.adp + 1) & 0xFFFF)
        elif command in LOGICAL_COMMANDS:
            self._logical(datagram)
            return
        else:
            return                                            # NOP and unknown commands
        if command in (Command.ARMW, Command.FRMW):
            if hit:
                data = self._physical_read(datagram.ado, len(datagram.data))
                if data is not None:
                    datagram.data[:] = data
                    datagram.wkc += 1
            elif self._physical_write(datagram.ado, bytes(datagram.data)):
                datagram.wkc += 1
            return
        if not hit:
            return
        read_ok = written = False
        incoming = bytes(datagram.data)
        if command in READ_COMMANDS:
            data = self._physical_read(datagram.ado, len(datagram.data))
            if data is not None:
                read_ok = True
                if command in BROADCAST_COMMANDS:                 # BRD/BRW: ORed in
                    datagram.data[:] = bytes(a | b for a, b in zip(datagram.data, data))
                else:
                    datagram.data[:] = data
        if command in WRITE_COMMANDS:
            written = self._physical_write(datagram.ado, incoming)
        datagram.wkc += wkc_increment(command, read_ok, written)
        datagram.irq |= self._u16(Register.ECAT_EVENT_REQUEST) & self._u16(
            Register.ECAT_EVENT_MASK)

    def _logical(self, datagram: Datagram) -> None:
        command = datagram.command
        start, length = datagram.address, len(datagram.data)
        end = start + length
        incoming = bytes(datagram.data)
        read_ok = written = False
        for fmmu in self._fmmus:
            low, high = max(start, fmmu.logical_start), min(end, fmmu.logical_end)
            if low >= high:
                continue
            physical = fmmu.physical_start + (low - fmmu.logical_start)
            if fmmu.write and command in (Command.LWR, Command.LRW):
                if self._physical_write(physical, incoming[low - start:high - start]):
                    written = True
            if fmmu.read and command in (Command.LRD, Command.LRW):
                data = self._physical_read(physical, high - low)
                if data is not None:
                    datagram.data[low - start:high - start] = data
                    read_ok = True
        datagram.wkc += wkc_increment(command, read_ok, written)

    def end_frame(self) -> None:
        """Finish a frame: firmware takes completed SM0/SM2 buffers (PDI interrupt)."""
        if self._pending_mailbox is not None:
            request, self._pending_mailbox = self._pending_mailbox, None
            self.mailbox.receive(request)
            self._mailbox_full[0] = False                        # the firmware read it
            self._set_sm_status(0, full=False)
            self._feed_sm1()
        if self._pending_outputs is not None:
            outputs, self._pending_outputs = self._pending_outputs, None
            if self.al_state in (ALState.SAFE_OP, ALState.OP):
                self.app.rx_pdo(outputs)
                self._outputs_valid = True
                if self._op_deadline is not None:
                    self._enter(ALState.OP)
            self._refresh_inputs()

    # -- physical memory access --------------------------------------------------

    def _physical_read(self, address: int, length: int) -> bytes | None:
        end = address + length
        if end > len(self.memory):
            return None
        if address < REGISTER_SPACE:
            if end > REGISTER_SPACE:
                head = self._register_read(address, REGISTER_SPACE - address)
                tail = self._ram_read(REGISTER_SPACE, end - REGISTER_SPACE)
                return None if tail is None else head + tail
            return self._register_read(address, length)
        return self._ram_read(address, length)

    def _physical_write(self, address: int, data: bytes) -> bool:
        end = address + len(data)
        if end > len(self.memory):
            return False
        if address < REGISTER_SPACE:
            split = min(end, REGISTER_SPACE) - address
            self._register_write(address, data[:split])
            if end > REGISTER_SPACE:
                return self._ram_write(REGISTER_SPACE, data[split:])
            return True
        return self._ram_write(address, data)

    def _register_read(self, address: int, length: int) -> bytes:
        end = address + length
        if address < Register.DC_SYSTEM_TIME + 8 and end > Register.DC_SYSTEM_TIME:
            struct.pack_into('<Q', self.memory, Register.DC_SYSTEM_TIME,
                             self._system_time() & 0xFFFFFFFFFFFFFFFF)
        data = bytes(self.memory[address:end])
        if address <= Register.AL_STATUS < end:
            self._clear_event(EVENT_AL_STATUS)                   # reading AL status acks it
        if address <= Register.DL_STATUS < end:
            self._clear_event(EVENT_DL_STATUS)
        return data

    def _register_write(self, address: int, data: bytes) -> None:
        memory = self.memory
        end = address + len(data)
        eeprom_status = self._u16(Register.EEPROM_CONTROL)
        for offset, value in enumerate(data, address):
            if _WRITABLE[offset]:
                memory[offset] = value
        if address < Register.RX_ERROR_COUNTER + 0x14 and end > Register.RX_ERROR_COUNTER:
            memory[Register.RX_ERROR_COUNTER:Register.RX_ERROR_COUNTER + 0x14] = bytes(0x14)
        if address < Register.WATCHDOG_COUNTER_PROCESS_DATA + 2 and (
                end > Register.WATCHDOG_COUNTER_PROCESS_DATA):
            memory[Register.WATCHDOG_COUNTER_PROCESS_DATA:
                   Register.WATCHDOG_COUNTER_PROCESS_DATA + 2] = b'\x00\x00'
        if address < Register.FMMU0 + FMMU_SIZE * 16 and end > Register.FMMU0:
            self._load_fmmus()
        if address < Register.SM0 + SM_SIZE * 16 and end > Register.SM0:
            self._sm_registers_written(address, end)
        if address < Register.EEPROM_CONTROL + 2 and end > Register.EEPROM_CONTROL:
            self._eeprom_command(eeprom_status)
        if address < Register.DC_RECEIVE_TIME_PORT0 + 4 and end > Register.DC_RECEIVE_TIME_PORT0:
            self._latch_receive_times()
        if address < Register.DC_SYSTEM_TIME + 8 and end > Register.DC_SYSTEM_TIME:
            received = int.from_bytes(bytes(data[max(0, Register.DC_SYSTEM_TIME - address):][:8])
                                      .ljust(8, b'\x00'), 'little')
            self._time_control(received)
        if address <= Register.AL_CONTROL < end:
            self._al_control(self._u16(Register.AL_CONTROL))

    # -- RAM and SyncManagers ------------------------------------------------------

    def _sync_manager_at(self, address: int, end: int) -> _SyncManager | None:
        for sm in self._sms:
            if address < sm.end and end > sm.start:
                return sm
        return None

    def _sm_active(self, sm: _SyncManager) -> bool:
        base = Register.SM0 + SM_SIZE * sm.number
        return bool(self.memory[base + 6] & SM_ACTIVATE_ENABLE) and not (
            self.memory[base + 7] & SM_PDI_DEACTIVATE)

    def _ram_read(self, address: int, length: int) -> bytes | None:
        end = address + length
        sm = self._sync_manager_at(address, end)
        if sm is None:
            return bytes(self.memory[address:end])               # RAM outside any SM
        if not self._sm_active(sm) or sm.ecat_writes:
            return None
        if sm.mailbox:
            if not self._mailbox_full[sm.number]:
                return None                                      # empty mailbox: no WKC
            data = bytes(self.memory[address:end])
            if end >= sm.end:                                    # last byte read: empty
                self._mailbox_full[sm.number] = False
                self._set_sm_status(sm.number, full=False)
                self._feed_sm1()
            return data
        return bytes(self.memory[address:end])

    def _ram_write(self, address: int, data: bytes) -> bool:
        end = address + len(data)
        sm = self._sync_manager_at(address, end)
        if sm is None:
            self.memory[address:end] = data
            return True
        if not self._sm_active(sm) or not sm.ecat_writes:
            return False
        if sm.mailbox:
            if self._mailbox_full[sm.number]:
                return False                                     # full: write refused
            self.memory[address:end] = data
            if end >= sm.end:                                    # last byte: buffer full
                self._mailbox_full[sm.number] = True
                self._set_sm_status(sm.number, full=True)
                self._pending_mailbox = bytes(self.memory[sm.start:sm.end])
            return True
        self.memory[address:end] = data
        if end >= sm.end:                                        # buffer complete
            self._pending_outputs = bytes(self.memory[sm.start:sm.end])
            if sm.control & SM_WATCHDOG_TRIGGER:
                self._trigger_watchdog()
        return True

    def _set_sm_status(self, number: int, full: bool) -> None:
        status = Register.SM0 + SM_SIZE * number + 5
        if full:
            self.memory[status] |= SM_STATUS_MAILBOX_FULL
            self._raise_event(EVENT_SM0 << number)
        else:
            self.memory[status] &= ~SM_STATUS_MAILBOX_FULL
            self._clear_event(EVENT_SM0 << number)

    def _feed_sm1(self, repeat: bool = False) -> None:
        """Move the next queued mailbox message (or the last one, on repeat) into SM1."""
        sm = next((s for s in self._sms if s.number == 1), None)
        if sm is None or not self._sm_active(sm) or self._mailbox_full[1]:
            return
        message = self._sm1_last if repeat else self.mailbox.pop()
        if message is None:
            return
        self._sm1_last = message
        size = sm.end - sm.start
        self.memory[sm.start:sm.end] = message[:size] + bytes(max(0, size - len(message)))
        self._mailbox_full[1] = True
        self._set_sm_status(1, full=True)

    def _load_fmmus(self) -> None:
        fmmus = []
        for number in range(FMMU_COUNT):
            base = Register.FMMU0 + FMMU_SIZE * number
            logical, length, _, _, physical, _, kind, active = struct.unpack_from(
                '<IHBBHBBB', self.memory, base)
            if active & 0x01 and length:
                fmmus.append(_Fmmu(logical, logical + length, physical, bool(kind & 0x01),
                                   bool(kind & 0x02)))
        self._fmmus = fmmus

    def _sm_registers_written(self, address: int, end: int) -> None:
        sms = []
        for number in range(SM_COUNT):
            base = Register.SM0 + SM_SIZE * number
            start, length, control = struct.unpack_from('<HHB', self.memory, base)
            activate = self.memory[base + 6]
            if not activate & SM_ACTIVATE_ENABLE:
                self._mailbox_full[number] = False               # disabling resets the buffer
                self.memory[base + 5] &= ~SM_STATUS_MAILBOX_FULL
            if length and activate & SM_ACTIVATE_ENABLE:
                sms.append(_SyncManager(number, start, start + length, control))
            repeat = activate & SM_ACTIVATE_REPEAT
            if address <= base + 6 < end and repeat != self.memory[base + 7] & SM_PDI_REPEAT_ACK:
                # repeat request toggled (ETG.1000.4 6.7.2): resend the last reply, then ack
                self._sms = sms
                if number == 1:
                    self._mailbox_full[1] = False
                    self._feed_sm1(repeat=True)
                self.memory[base + 7] = (self.memory[base + 7] & ~SM_PDI_REPEAT_ACK) | repeat
        self._sms = sms

    # -- EEPROM ----------------------------------------------------------------------

    def _eeprom_command(self, previous: int) -> None:
        value = self._u16(Register.EEPROM_CONTROL)
        command = value & EEPROM_COMMAND_MASK
        # only write enable and the command are writable; the status bits stay the ESC's
        status = previous & (EEPROM_CHECKSUM_ERROR | EEPROM_READ_8_BYTES)
        address = self._u32(Register.EEPROM_ADDRESS) * 2
        if command == EEPROM_CMD_READ:
            chunk = bytes(self.sii[address:address + self.eeprom_read_bytes])
            chunk += b'\xff' * (self.eeprom_read_bytes - len(chunk))   # beyond the image
            self.memory[Register.EEPROM_DATA:Register.EEPROM_DATA + self.eeprom_read_bytes] = chunk
        elif command == EEPROM_CMD_WRITE:
            if not value & EEPROM_WRITE_ENABLE or address + 2 > len(self.sii):
                status |= EEPROM_WRITE_ERROR
            else:
                self.sii[address:address + 2] = self.memory[Register.EEPROM_DATA:
                                                            Register.EEPROM_DATA + 2]
        elif command == EEPROM_CMD_RELOAD:
            self._set_u16(Register.EEPROM_CONTROL, status)
            self._reload_eeprom()
            return
        elif command != EEPROM_CMD_NOP:
            status |= EEPROM_COMMAND_ERROR
        # commands complete at once: the command bits read back 0, busy is never seen
        self._set_u16(Register.EEPROM_CONTROL, status)

    # -- distributed clocks ------------------------------------------------------------

    def _local_time(self, monotonic_ns: int) -> int:
        return monotonic_ns - self._power_on_ns

    def _system_time(self) -> int:
        offset = struct.unpack_from('<q', self.memory, Register.DC_SYSTEM_TIME_OFFSET)[0]
        return self._local_time(self._frame_time_ns) + offset + self._dc_correction_ns

    def _latch_receive_times(self) -> None:
        port0 = self._local_time(self._frame_time_ns)
        port1 = self._local_time(self._frame_return_ns) if self._frame_return_ns else 0
        struct.pack_into('<IIII', self.memory, Register.DC_RECEIVE_TIME_PORT0,
                         port0 & 0xFFFFFFFF, port1 & 0xFFFFFFFF, 0, 0)
        struct.pack_into('<Q', self.memory, Register.DC_RECEIVE_TIME_PU, port0)

    def _time_control(self, received: int) -> None:
        """Compare a written reference time and trim (ESC datasheet section I 9.1.3)."""
        delay = self._u32(Register.DC_SYSTEM_TIME_DELAY)
        difference = self._system_time() - delay - received
        magnitude = min(abs(difference), 0x7FFFFFFF)
        struct.pack_into('<I', self.memory, Register.DC_SYSTEM_TIME_DIFFERENCE,
                         magnitude | (0x80000000 if difference >= 0 else 0))
        # a bounded slew per update instead of modelling the oscillator trim: a wild
        # value (e.g. the zeros a master broadcasts at start) cannot make the clock jump
        self._dc_correction_ns -= max(-4096, min(4096, difference))

    def sync0_cycle_ns(self) -> int:
        """SYNC0 cycle time if cyclic operation and SYNC0 are activated (0x0981), else 0."""
        if self.memory[Register.DC_SYNC_ACTIVATION] & 0x03 == 0x03:
            return self._u32(Register.DC_SYNC0_CYCLE_TIME)
        return 0

    # -- watchdog ------------------------------------------------------------------------

    def watchdog_time_s(self) -> float:
        """Process-data watchdog time from 0x0400/0x0420 (0 = disabled)."""
        divider = self._u16(Register.WATCHDOG_DIVIDER)
        ticks = self._u16(Register.WATCHDOG_TIME_PROCESS_DATA)
        return ticks * 40e-9 * (divider + 2)

    def _trigger_watchdog(self) -> None:
        timeout = self.watchdog_time_s()
        self._watchdog_deadline = self._now + timeout if timeout else None
        if self._watchdog_expired:
            self._watchdog_expired = False
            self._set_u16(Register.WATCHDOG_STATUS_PROCESS_DATA, 0x0001)

    def tick(self, now: float) -> None:
        """Advance time: watchdog, SAFE-OP -> OP timeout, the application, its emergencies."""
        self._now = now
        if self._watchdog_deadline is not None and now > self._watchdog_deadline:
            self._watchdog_deadline = None
            self._watchdog_expired = True
            self._set_u16(Register.WATCHDOG_STATUS_PROCESS_DATA, 0x0000)
            counter = Register.WATCHDOG_COUNTER_PROCESS_DATA
            self.memory[counter] = min(255, self.memory[counter] + 1)
            if self.al_state is ALState.OP:
                self._fail(ALState.SAFE_OP, ALStatusCode.SYNC_MANAGER_WATCHDOG)
                self.app.watchdog_expired()
        if self._op_deadline is not None and now > self._op_deadline:
            self._fail(ALState.SAFE_OP, ALStatusCode.NO_VALID_OUTPUTS)
        self.app.tick(now)
        self._post_emergencies()
        if self.al_state in (ALState.SAFE_OP, ALState.OP):
            self._refresh_inputs()

    def _post_emergencies(self) -> None:
        emergencies = self.app.take_emergencies()
        if not emergencies or self.al_state is ALState.INIT:
            return                                    # no mailbox in INIT: they are lost
        for item in emergencies:
            self.mailbox.post(MailboxType.COE,
                              emergency(item.error_code, item.error_register, item.data))
        self._feed_sm1()

    def _refresh_inputs(self) -> None:
        sm = next((s for s in self._sms if s.number == 3), None)
        if sm is None or not self._sm_active(sm):
            return
        data = self.app.tx_pdo()
        size = sm.end - sm.start
        self.memory[sm.start:sm.end] = data[:size] + bytes(max(0, size - len(data)))

    # -- AL state machine (ETG.1000.6 6.4) --------------------------------------------------

    def _al_control(self, control: int) -> None:
        requested = control & AL_STATE_MASK
        acknowledge = bool(control & AL_ERROR_FLAG)
        status = self.al_status
        current = status & AL_STATE_MASK
        if status & AL_ERROR_FLAG:
            if acknowledge:
                self._set_status(current, 0)                      # error acknowledged
            elif requested >= current:
                return                                            # must be acknowledged first
        if requested == current:
            return
        if requested not in (ALState.INIT, ALState.PRE_OP, ALState.SAFE_OP, ALState.OP):
            code = (ALStatusCode.BOOTSTRAP_NOT_SUPPORTED if requested == ALState.BOOT
                    else ALStatusCode.UNKNOWN_REQUESTED_STATE)
            self._fail(ALState(current), code)
            return
        target = ALState(requested)
        transition = (ALState(current), target)
        if transition not in _TRANSITIONS:
            self._fail(ALState(current), ALStatusCode.INVALID_REQUESTED_STATE_CHANGE)
            return
        if target > current:
            code = self._check_up(ALState(current), target)
            if code:
                self._fail(ALState(current), code)
                return
            if target is ALState.OP and self._op_needs_outputs():
                self._op_deadline = self._now + SAFE_OP_TO_OP_TIMEOUT_S   # wait for outputs
                return
        self._enter(target)

    def _context(self) -> TransitionContext:
        lengths = {sm.number: sm.end - sm.start for sm in self._sms}
        return TransitionContext(lengths.get(2, 0), lengths.get(3, 0), self.sync0_cycle_ns(),
                                 self.watchdog_time_s())

    def _check_up(self, current: ALState, target: ALState) -> int:
        if target is ALState.PRE_OP:
            code = self._check_mailbox()
        elif target is ALState.SAFE_OP:
            code = self._check_process_data()
        else:
            code = 0
        return code or self.app.request_state(current, target, self._context())

    def _check_mailbox(self) -> int:
        rx_offset, rx_size, tx_offset, tx_size = self.mailbox_layout
        if not rx_size:
            return 0
        expected = {0: (rx_offset, rx_size, SM_DIRECTION_WRITE),
                    1: (tx_offset, tx_size, SM_DIRECTION_READ)}
        for number, (offset, size, direction) in expected.items():
            sm = next((s for s in self._sms if s.number == number), None)
            if (sm is None or sm.start != offset or sm.end - sm.start != size
                    or not sm.mailbox or sm.control & SM_DIRECTION_MASK != direction):
                return ALStatusCode.INVALID_MAILBOX_CONFIGURATION
        return 0

    def _check_process_data(self) -> int:
        output_bytes, input_bytes = self.app.process_data_sizes()
        for number, size, direction, code in (
                (2, output_bytes, SM_DIRECTION_WRITE, ALStatusCode.INVALID_OUTPUT_CONFIGURATION),
                (3, input_bytes, SM_DIRECTION_READ, ALStatusCode.INVALID_INPUT_CONFIGURATION)):
            if not size:
                continue
            sm = next((s for s in self._sms if s.number == number), None)
            if (sm is None or sm.mailbox or sm.control & SM_DIRECTION_MASK != direction
                    or sm.start < REGISTER_SPACE or sm.end > len(self.memory)):
                return ALStatusCode.INVALID_SYNC_MANAGER_CONFIGURATION
            if sm.end - sm.start != size:
                return code                                # length does not fit the mapping
        return 0

    def _op_needs_outputs(self) -> bool:
        return self.app.process_data_sizes()[0] > 0 and not self._outputs_valid

    def _set_status(self, state: int, code: int, error: bool = False) -> None:
        previous = self.al_status
        self._set_u16(Register.AL_STATUS, state | (AL_ERROR_FLAG if error else 0))
        self._set_u16(Register.AL_STATUS_CODE, code)
        if previous != self.al_status:
            self._raise_event(EVENT_AL_STATUS)

    def application_error(self, state: ALState, code: int) -> None:
        """Fall back to ``state`` with the error flag and ``code`` on the slave's own account."""
        self._fail(state, code)

    def _fail(self, state: ALState, code: int) -> None:
        """Stay in (or fall back to) ``state`` with the error flag and ``code``."""
        previous = self.al_state
        self._op_deadline = None
        if state < previous:
            self._leave(previous, state)
        self._set_status(state, code, error=True)
        if state != previous:
            self.app.state_changed(state)

    def _enter(self, target: ALState) -> None:
        previous = self.al_state
        self._op_deadline = None
        if target < previous:
            self._leave(previous, target)
        else:
            self._arrive(previous, target)
        if self.al_status & AL_ERROR_FLAG:          # a step down keeps an unacknowledged error
            self._set_status(target, self.al_status_code, error=True)
        else:
            self._set_status(target, 0)
        self.app.state_changed(target)

    def _pdi_enable(self, numbers: tuple[int, ...], enable: bool) -> None:
        for number in numbers:
            control = Register.SM0 + SM_SIZE * number + 7
            if enable:
                self.memory[control] &= ~SM_PDI_DEACTIVATE
            else:
                self.memory[control] |= SM_PDI_DEACTIVATE

    def _arrive(self, previous: ALState, target: ALState) -> None:
        if previous < ALState.PRE_OP <= target:
            self._pdi_enable((0, 1), True)
            self._feed_sm1()
        if previous < ALState.SAFE_OP <= target:
            self._pdi_enable((2, 3), True)
            self._outputs_valid = False
            self._refresh_inputs()

    def _leave(self, previous: ALState, target: ALState) -> None:
        if target < ALState.SAFE_OP <= previous:
            self._pdi_enable((2, 3), False)
            self._watchdog_deadline = None
            self._outputs_valid = False
        if target < ALState.OP <= previous:
            self._outputs_valid = False
        if target < ALState.PRE_OP <= previous:
            self._pdi_enable((0, 1), False)
            self.mailbox.reset()
            self.coe.reset()
            self._mailbox_full[0] = self._mailbox_full[1] = False
            self._set_sm_status(0, full=False)
            self._set_sm_status(1, full=False)
