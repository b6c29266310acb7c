"""EtherCAT segment master on pysoem (SOEM): process data, SDO, AL states, emergencies, recovery.

Moves raw bytes and object values; knows nothing of drives, profiles or ROS.
One ``EthercatSegment`` owns one ``pysoem.Master`` (one network interface) and:

- ONE process-data thread serving every slave of the segment: each cycle it
  copies the outputs every slave handle holds into SOEM's IO map, sends the
  LRW (plus the DC reference-time datagram in DC mode), waits for the frame,
  checks the working counter against SOEM's expected value and copies the
  inputs out; it counts missed cycles and WKC errors and records the wake-up
  jitter. Nothing else runs in it: no mailbox, no state handling.
- a supervisor thread for everything that may block for milliseconds: reading
  AL states when the WKC drops, acknowledging errors and re-entering OP, finding
  a slave that vanished and came back (SOEM recover, then SOEM's reconfiguration
  one step per pass, never waiting inside pysoem: see ``_bring_up``), and polling
  the mailboxes for CoE emergencies (SOEM reads them only during mailbox access).
- per-slave handles (``EthercatSlave``): identity from the SII, SDO upload/download
  (expedited and segmented; aborts raise ``SdoAbortError`` with the CiA 301 code
  and text), PDO assignment/mapping at PRE-OP, outputs/inputs (thread-safe),
  AL state with the AL status code, emergencies.

Positions in this API are 0-based (pysoem's ``master.slaves`` index); messages and
logs number slaves from 1, as SOEM and configuration tools do.

Every call is bounded in time (SOEM's frame/state/mailbox timeouts, set from the
settings) and raises the package's errors (``vfd_ros2.errors``): AL state
failures carry the ETG.1000.6 AL status code and its text.

SOEM needs raw-socket rights (root or CAP_NET_RAW). For tests the interface can
live in a network namespace (``vfd_ros2.transports.netns``).
"""

from __future__ import annotations

import enum
import fcntl
import logging
import math
import os
import re
import statistics
import struct
import tempfile
import threading
import time
import warnings
from collections import deque
from dataclasses import dataclass, field
from typing import Any, Callable, Mapping, NamedTuple

from ..errors import BadFrame, CommTimeout, ProtocolException, TransportError
from ..protocol.ethercat import (
    AL_ERROR_FLAG,
    AL_STATE_MASK,
    ALState,
    al_state_name,
    al_status_text,
    sdo_abort_text,
)
from .base import Transport, TransportParameter
from .netns import run_in_namespace

try:
    import pysoem
except ImportError:                     # reported by EthercatSegment.open
    pysoem = None

log = logging.getLogger(__name__)

#: how long an AL error flag must persist before a state request counts as refused
ERROR_SETTLE_S = 0.02
#: SDO uploads are tried this often when a frame is lost (WKC error): reading twice
#: changes nothing. Downloads are not repeated; the caller decides.
READ_ATTEMPTS = 2
#: s after the last missed process-data cycle that a drive's diagnostics still warn of it
MISSED_CYCLES_RECENT = 10.0

#: where a master process marks the NIC it drives (an flock, which the kernel drops
#: when the process dies, however it dies)
LOCK_DIR = '/run/lock' if os.path.isdir('/run/lock') else tempfile.gettempdir()


#: s between two tries of a slave's set-up that failed at PRE-OP (SDO aborts)
SETUP_RETRY_S = 1.0
#: ESC registers (ETG.1000.4 table 31): FMMU and sync manager counts, their settings
ESC_COUNTS = 0x0004
ESC_FMMUS = 0x0600
ESC_SYNC_MANAGERS = 0x0800
FMMU_BYTES, SYNC_MANAGER_BYTES = 16, 8


def _read_esc_setup(slave: 'EthercatSlave', quietly: bool = False
                    ) -> tuple[bytes, bytes] | None:
    """Read a configured slave's sync manager and FMMU registers (None if unanswered).

    SOEM's reconfiguration writes the same from its own tables; pysoem does not
    show those, the ESC does. Tried three times (a frame lost); the supervisor
    tries again while the slave is in its state.
    """
    soem = slave._soem   # noqa: SLF001 - pysoem's FPRD primitive
    for _ in range(3):
        try:
            fmmus, sync_managers = soem._fprd(ESC_COUNTS, 2)
            fmmus, sync_managers = min(fmmus, 16), min(sync_managers, 16)
            return (soem._fprd(ESC_SYNC_MANAGERS, SYNC_MANAGER_BYTES * sync_managers)
                    if sync_managers else b'',
                    soem._fprd(ESC_FMMUS, FMMU_BYTES * fmmus) if fmmus else b'')
        except pysoem.WkcError:
            continue
    if not quietly:
        log.warning('EtherCAT slave %d: its sync managers could not be read (read again '
                    "while it runs); a power cycle before that is brought back by SOEM's "
                    'reconfiguration, which holds the process while it waits', slave.position + 1)
    return None


class MasterLock:
    """One EtherCAT master per NIC: an flock on a file named after the interface.

    Two masters on one segment (two ``drive_node`` processes for two slaves of one
    NIC, the easy mistake) would each reset and drive every slave, the other's
    too. The second is refused with a clear error instead. The namespace is part
    of the name: the same interface name in two network namespaces is two NICs.
    """

    def __init__(self, interface: str, namespace: str = '') -> None:
        label = re.sub(r'[^A-Za-z0-9_.-]', '_', f'{namespace or "host"}-{interface}')
        self.interface = interface
        self.path = os.path.join(LOCK_DIR, f'vfd_ros2-ethercat-{label}.lock')
        self._fd: int | None = None

    def acquire(self) -> None:
        """Take the lock, or raise EthercatError naming who holds it (idempotent)."""
        while self._fd is None:
            fd = self._open()
            if fd is None:
                return
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                holder = os.pread(fd, 64, 0).decode(errors='replace').strip() or 'a process'
                os.close(fd)
                raise EthercatError(
                    f'{self.interface} is driven by another EtherCAT master ({holder}): one '
                    'process drives a segment; run all of its drives in one bus_node') from None
            try:
                current = os.stat(self.path).st_ino
            except FileNotFoundError:
                current = None
            if current != os.fstat(fd).st_ino:
                os.close(fd)       # its holder removed it as we opened it: take the new one
                continue
            try:
                os.ftruncate(fd, 0)
                os.pwrite(fd, f'pid {os.getpid()}'.encode(), 0)
            except OSError:
                pass                             # read-only: the lock holds all the same
            self._fd = fd

    def _open(self) -> int | None:
        """Open (or create) the lock file; None when neither works (warned)."""
        problem: OSError | None = None
        for flags in (os.O_RDWR | os.O_CREAT, os.O_RDONLY):
            try:
                return os.open(self.path, flags, 0o644)
            except PermissionError as exc:   # another user's file: locking needs no writing
                problem = exc
            except OSError as exc:
                problem = exc
                break
        # No lock file possible here: drive on, without the guard, and say so.
        log.warning('cannot open %s (%s): a second EtherCAT master on %s would not be noticed',
                    self.path, problem, self.interface)
        return None

    def release(self) -> None:
        fd, self._fd = self._fd, None
        if fd is None:
            return
        try:
            os.unlink(self.path)     # while still held (acquire checks it took a live file)
        except OSError:
            pass
        os.close(fd)                             # closing drops the flock


class SyncMode(enum.Enum):
    """How slaves run their cycle: on their own clock, or on DC SYNC0 (ETG.1020)."""

    FREE_RUN = 'free_run'
    DC = 'dc'


@dataclass(frozen=True)
class SegmentSettings:
    """Plain settings of one EtherCAT segment (no drive knowledge)."""

    interface: str
    namespace: str | None = None           # network namespace of the interface (tests)
    cycle_time_s: float = 0.002
    sync_mode: SyncMode = SyncMode.FREE_RUN
    dc_shift_s: float = 0.0                # SYNC0 shift relative to the cycle start
    watchdog_s: float | None = 0.1         # SM (process-data) watchdog; None: slave default
    state_timeout_s: float = 2.0           # each AL state change
    sdo_timeout_s: float = 0.7             # each SDO exchange
    mailbox_poll_s: float = 0.05           # emergency polling period; 0 = only during SDOs
    supervise_s: float = 0.05              # state check period while something is wrong
    # AL states read this often while all looks well: a slave that drops to SAFE-OP by
    # itself (an application error) may keep answering the cycle frame's working counter
    state_poll_s: float = 0.1
    lost_after_s: float = 0.25             # a slave silent this long is lost (not one frame)
    recover: bool = True                   # bring back slaves that vanished
    realtime_priority: int | None = None   # SCHED_FIFO priority of the process-data thread


@dataclass(frozen=True)
class SlaveIdentity:
    """What a slave's SII says it is."""

    position: int                          # 0-based, in line order
    name: str
    vendor_id: int
    product_code: int
    revision: int


@dataclass(frozen=True)
class PdoConfiguration:
    """PDO assignment for SM2/SM3, and mapping objects to (re)write first.

    ``rx``/``tx`` are the mapping-object indices for 0x1C12/0x1C13; ``mappings``
    maps a mapping-object index to its entries (0xIIIISSLL: index, subindex,
    bit length). A drive whose assignment is fixed (read-only) is accepted when
    it already holds the wanted assignment (e.g. BONENG's 0x1701/0x1B01).
    """

    rx: tuple[int, ...]
    tx: tuple[int, ...]
    mappings: dict[int, tuple[int, ...]] = field(default_factory=dict)


@dataclass(frozen=True)
class Emergency:
    """A CoE emergency received from a slave (ETG.1000.6 5.6.2.4; codes CiA 301 table 21)."""

    position: int
    error_code: int
    error_register: int
    data: bytes
    time: float                            # monotonic, when the master read it


class CycleCounts(NamedTuple):
    """The process-data thread's counters since ``start``."""

    cycles: int
    missed_cycles: int
    wkc_errors: int
    lost_frames: int


@dataclass(frozen=True)
class CycleStats:
    """Counters of the process-data thread since ``start``."""

    cycles: int
    missed_cycles: int                     # cycle slots that passed without a frame sent
    wkc_errors: int                        # frames back with WKC < expected
    lost_frames: int                       # no frame back within the cycle
    expected_wkc: int
    last_wkc: int
    jitter_p50_s: float                    # wake-up lateness against the schedule
    jitter_p99_s: float
    jitter_max_s: float
    cycle_cpu_s: float                     # CPU time of the process-data thread
    elapsed_s: float


class EthercatError(TransportError):
    """Something on the EtherCAT segment failed."""


class AlStateError(EthercatError):
    """A slave did not reach a requested AL state; carries its AL status code and text."""

    def __init__(self, position: int, requested: ALState, status: int, code: int) -> None:
        self.position = position
        self.requested = requested
        self.status = status
        self.code = code
        self.text = al_status_text(code)
        now = 'it does not answer' if status & AL_STATE_MASK == ALState.NONE else \
            f'it is {al_state_name(status)}, AL status code 0x{code:04X} ({self.text})'
        super().__init__(f'slave {position + 1} did not reach {requested.name}: {now}')


class SdoAbortError(ProtocolException):
    """A slave aborted an SDO transfer with a CiA 301 abort code."""

    def __init__(self, position: int, index: int, subindex: int, code: int) -> None:
        self.position = position
        self.index = index
        self.subindex = subindex
        super().__init__(code, sdo_abort_text(code),
                         f'slave {position + 1} 0x{index:04X}:{subindex}')
        self.args = (f'SDO abort 0x{code:08X} ({self.text}) from slave {position + 1} at '
                     f'0x{index:04X}:{subindex}',)

    def __str__(self) -> str:
        return self.args[0]


def _state(value: int) -> ALState:
    try:
        return ALState(value & AL_STATE_MASK)
    except ValueError:
        return ALState.NONE


class EthercatSlave:
    """Handle of one slave on a segment; positions are 0-based in line order."""

    def __init__(self, segment: 'EthercatSegment', position: int, soem_slave: Any) -> None:
        self._segment = segment
        self._soem = soem_slave
        self.position = position
        self.identity = SlaveIdentity(position, soem_slave.name, soem_slave.man, soem_slave.id,
                                      soem_slave.rev)
        self._outputs = b''
        self._outputs_time = 0.0
        self._safe_outputs = b''
        self._hold_s = 0.0
        self._held_cycles = 0
        self._inputs = b''
        self._inputs_time = 0.0
        self._emergencies: deque[Emergency] = deque(maxlen=256)
        self.state = ALState.PRE_OP
        self.al_status = 0
        self.al_status_code = 0
        self.lost = False
        self.unanswered_since: float | None = None   # its state reads unanswered since
        self.target = ALState.PRE_OP          # the state the supervisor keeps it in
        #: its sync manager and FMMU registers as config_map left them (written again
        #: when it comes back in INIT); None: not read, SOEM's reconfig does it
        self.esc_setup: tuple[bytes, bytes] | None = None
        #: writes its set-up again at PRE-OP (PDO mapping, start-up objects); raises
        self.preop_setup: Callable[[], None] | None = None
        self.setup_due = False                # came back through INIT: preop_setup first
        self.sync0: tuple[int, int] | None = None   # (cycle, shift) ns of its SYNC0, if any
        #: why preop_setup failed last ('' = it did not), and when it may be tried again
        self.setup_error = ''
        self.setup_retry_at = 0.0
        soem_slave.add_emergency_callback(self._on_emergency)

    # -- mailbox -----------------------------------------------------------------------

    def _on_emergency(self, emcy: Any) -> None:
        data = struct.pack('<BHH', emcy.b1 & 0xFF, emcy.w1 & 0xFFFF, emcy.w2 & 0xFFFF)
        item = Emergency(self.position, emcy.error_code, emcy.error_reg, data, time.monotonic())
        self._emergencies.append(item)
        callback = self._segment.on_emergency
        if callback is not None:
            try:
                callback(item)
            except Exception:  # noqa: BLE001 - a user callback must not break the mailbox
                log.exception('emergency callback failed')

    def sdo_read(self, index: int, subindex: int, size: int = 0) -> bytes:
        """SDO upload (expedited or segmented); ``size`` = room for objects > 256 bytes."""
        return self._segment._mailbox(self, 'read 0x%04X:%d' % (index, subindex), index,
                                      subindex, lambda: self._soem.sdo_read(index, subindex,
                                                                            size),
                                      attempts=READ_ATTEMPTS)

    def sdo_write(self, index: int, subindex: int, data: bytes) -> None:
        """SDO download; more than the mailbox holds is sent segmented."""
        self._segment._mailbox(self, 'write 0x%04X:%d' % (index, subindex), index, subindex,
                               lambda: self._soem.sdo_write(index, subindex, bytes(data)))

    def poll_mailbox(self) -> None:
        """Read the slave's mailbox once (collects a pending emergency)."""
        self._segment._mailbox(self, 'mailbox poll', 0, 0, self._soem.mbx_receive)

    def take_emergencies(self) -> list[Emergency]:
        """Emergencies received since the last call, oldest first."""
        items = []
        while self._emergencies:
            items.append(self._emergencies.popleft())
        return items

    # -- process data -----------------------------------------------------------------

    @property
    def output_size(self) -> int:
        return len(self._outputs)

    @property
    def input_size(self) -> int:
        return len(self._soem.input)

    def set_outputs(self, data: bytes) -> None:
        """Send ``data`` (RxPDO bytes) from the next cycle on; the length must match."""
        if len(data) != len(self._outputs):
            raise ValueError(f'slave {self.position + 1} takes {len(self._outputs)} output bytes, '
                             f'got {len(data)}')
        with self._segment._io_lock:
            self._outputs = bytes(data)
            self._outputs_time = time.monotonic()

    def guard_outputs(self, safe: bytes, hold_s: float) -> None:
        """Send ``safe`` instead of outputs older than ``hold_s`` (0 = never).

        The process-data thread keeps sending whatever was set last; if the code
        that sets outputs stops (a hung control loop), the slave's SM watchdog
        never trips. With a guard, outputs nobody refreshed within ``hold_s`` are
        replaced by ``safe`` (e.g. disable operation, velocity 0) until the next
        ``set_outputs``.
        """
        if hold_s and len(safe) != len(self._outputs):
            raise ValueError(f'slave {self.position + 1} takes {len(self._outputs)} output bytes, '
                             f'got {len(safe)} safe ones')
        with self._segment._io_lock:
            self._safe_outputs = bytes(safe)
            self._hold_s = float(hold_s)
            self._outputs_time = time.monotonic()

    @property
    def outputs_held(self) -> int:
        """Cycles in which stale outputs were replaced by the safe ones (since start)."""
        return self._held_cycles

    def outputs(self) -> bytes:
        with self._segment._io_lock:
            return self._outputs

    def inputs(self) -> bytes:
        """Return the inputs (TxPDO bytes) of the last cycle whose frame came back.

        After a WKC drop the supervisor finds the slave that stopped answering
        within ``supervise_s`` and marks it ``lost``; from then on its inputs and
        ``inputs_time`` stay as they were, so a caller sees their age grow.
        """
        with self._segment._io_lock:
            return self._inputs

    @property
    def inputs_time(self) -> float:
        """Monotonic time the inputs were last refreshed (0: never)."""
        return self._inputs_time

    # -- state ---------------------------------------------------------------------------

    def read_state(self) -> ALState:
        """Read AL status and status code now (bounded by one frame timeout)."""
        self._segment._read_states()
        return self.state

    def request_state(self, state: ALState, timeout: float | None = None) -> None:
        """Request ``state`` for this slave; AlStateError with the AL status code if refused."""
        self.target = state
        self._segment._request(self, state, timeout)

    def __repr__(self) -> str:
        ident = self.identity
        return (f'EthercatSlave({self.position}, {ident.name!r}, vendor 0x{ident.vendor_id:X}, '
                f'product 0x{ident.product_code:X}, {self.state.name})')


class EthercatSegment:
    """One EtherCAT segment (one interface, one SOEM master, one process-data thread)."""

    def __init__(self, settings: SegmentSettings,
                 on_emergency: Callable[[Emergency], None] | None = None,
                 on_slave_lost: Callable[[int], None] | None = None,
                 on_slave_returned: Callable[[int], None] | None = None,
                 on_slave_fell: Callable[[int, int, int], None] | None = None) -> None:
        if settings.cycle_time_s <= 0:
            raise ValueError('cycle_time_s must be positive')
        self.settings = settings
        self._master_lock = MasterLock(settings.interface, settings.namespace)
        self.on_emergency = on_emergency
        self.on_slave_lost = on_slave_lost
        self.on_slave_returned = on_slave_returned
        #: (position, AL status, AL status code) of a slave found below its target state,
        #: called before the supervisor brings it back (under the state lock: quick, and
        #: no lock of the caller's)
        self.on_slave_fell = on_slave_fell
        self._master: Any = None
        self._slaves: list[EthercatSlave] = []
        self._io_lock = threading.Lock()
        self._mailbox_lock = threading.Lock()       # SOEM's error list is not thread-safe
        self._state_lock = threading.Lock()         # AL state reads/writes and recovery
        self._stop = threading.Event()
        self._trouble = threading.Event()
        self._cycle_thread: threading.Thread | None = None
        self._supervisor: threading.Thread | None = None
        self._expected_wkc = 0
        self._reset_stats()

    # -- lifecycle -----------------------------------------------------------------------

    def open(self) -> list[SlaveIdentity]:
        """Open the interface, enumerate the slaves (INIT -> PRE-OP), return their identities."""
        if pysoem is None:
            raise EthercatError('pysoem is not installed (pip install pysoem)')
        if self._master is not None:
            return [slave.identity for slave in self._slaves]
        self._master_lock.acquire()
        master = pysoem.Master()
        master.always_release_gil = True            # never stall the process-data thread
        timeout_us = int(self.settings.sdo_timeout_s * 1e6)
        master.sdo_read_timeout = timeout_us
        master.sdo_write_timeout = timeout_us
        try:
            if self.settings.namespace:
                run_in_namespace(self.settings.namespace, master.open, self.settings.interface)
            else:
                master.open(self.settings.interface)
        except (ConnectionError, OSError, TransportError) as exc:
            try:
                master.close()                  # SOEM may keep the socket it made
            except Exception:  # noqa: BLE001 - best effort on a failed open
                log.debug('close after a failed open', exc_info=True)
            self._master_lock.release()
            raise EthercatError(f'cannot open {self.settings.interface}: {exc}') from exc
        self._master = master
        try:
            found = master.config_init()
            if found <= 0:
                raise CommTimeout(f'no EtherCAT slave answered on {self.settings.interface}')
            self._slaves = [EthercatSlave(self, position, soem)
                            for position, soem in enumerate(master.slaves)]
            self._await(ALState.PRE_OP, self._slaves, self.settings.state_timeout_s)
        except BaseException:
            self.close()
            raise
        return [slave.identity for slave in self._slaves]

    @property
    def slaves(self) -> tuple[EthercatSlave, ...]:
        return tuple(self._slaves)

    def slave(self, position: int) -> EthercatSlave:
        return self._slaves[position]

    def configure_pdos(self, position: int, config: PdoConfiguration) -> None:
        """Write mapping objects and the SM2/SM3 PDO assignment of one slave (PRE-OP)."""
        slave = self._slaves[position]
        for index, entries in config.mappings.items():
            slave.sdo_write(index, 0, b'\x00')              # CiA 301: count 0, entries, count
            for sub, entry in enumerate(entries, 1):
                slave.sdo_write(index, sub, struct.pack('<I', entry))
            slave.sdo_write(index, 0, bytes([len(entries)]))
        for assign, indices in ((0x1C12, config.rx), (0x1C13, config.tx)):
            try:
                slave.sdo_write(assign, 0, b'\x00')
            except SdoAbortError as exc:
                if exc.code not in (0x06010002, 0x08000022):
                    raise
                current = self._assignment(slave, assign)
                if current != tuple(indices):
                    raise EthercatError(
                        f'slave {position + 1} has a fixed assignment 0x{assign:04X} = '
                        f'{[hex(i) for i in current]}; {[hex(i) for i in indices]} was '
                        f'asked for') from exc
                continue                                    # fixed and already right
            for sub, index in enumerate(indices, 1):
                slave.sdo_write(assign, sub, struct.pack('<H', index))
            slave.sdo_write(assign, 0, bytes([len(indices)]))

    @staticmethod
    def _assignment(slave: EthercatSlave, assign: int) -> tuple[int, ...]:
        count = slave.sdo_read(assign, 0)[0]
        return tuple(struct.unpack('<H', slave.sdo_read(assign, sub)[:2])[0]
                     for sub in range(1, count + 1))

    def start(self, free_running: frozenset[int] = frozenset()) -> None:
        """Map process data, set watchdog and sync, reach SAFE-OP and OP, run the cycle.

        In DC mode every slave gets SYNC0 except those in ``free_running``
        (0-based positions of slaves known to have no DC sync).
        """
        master = self._require_open()
        settings = self.settings
        cycle_ns = int(settings.cycle_time_s * 1e9)
        if settings.watchdog_s is not None:
            for slave in self._slaves:
                self._set_watchdog(slave, settings.watchdog_s)
        if settings.sync_mode is SyncMode.DC:
            if not master.config_dc():
                raise EthercatError('DC sync requested but no slave has distributed clocks')
            for slave in self._slaves:
                if slave.position not in free_running:
                    slave.sync0 = (cycle_ns, int(settings.dc_shift_s * 1e9))
                    slave._soem.dc_sync(True, *slave.sync0)
        with self._mailbox_lock:
            try:
                master.config_map()                         # requests SAFE-OP
            except pysoem.ConfigMapError as exc:
                raise EthercatError(f'PDO mapping failed: {exc.error_list}') from exc
        with self._io_lock:
            for slave in self._slaves:
                slave._outputs = bytes(len(slave._soem.output))
                slave._inputs = bytes(len(slave._soem.input))
        self._expected_wkc = master.expected_wkc
        # One slave that stays below SAFE-OP must not keep the others from running: it
        # is left to the supervisor (its drive reports the AL status code meanwhile).
        # It kept every drive of the segment offline (outside audit).
        refusals = self._await_each(ALState.SAFE_OP, settings.state_timeout_s)
        if len(refusals) == len(self._slaves):
            raise refusals[0]
        for slave in self._slaves:
            slave.target = ALState.SAFE_OP
            slave.esc_setup = _read_esc_setup(slave)
        self._stop.clear()
        self._reset_stats()
        self._cycle_thread = threading.Thread(target=self._cycle, daemon=True,
                                              name=f'ethercat-{settings.interface}')
        self._cycle_thread.start()
        self._supervisor = threading.Thread(target=self._supervise, daemon=True,
                                            name=f'ethercat-supervisor-{settings.interface}')
        self._supervisor.start()
        # SAFE-OP -> OP once valid outputs flow (ETG.1000.6 6.4.1: "SO: master sends
        # valid outputs"): the cycle is running now
        self.request_state(ALState.OP, refusals=refusals)

    def request_state(self, state: ALState, timeout: float | None = None,
                      refusals: list[AlStateError] | None = None) -> None:
        """Request ``state`` for every slave; AlStateError (first failing slave) if refused.

        ``refusals``: of slaves already known below the state's way (not waited for
        again; the supervisor keeps asking them), raised first.
        """
        self._require_open()
        errors = list(refusals or ())
        refused = {exc.position for exc in errors}
        for slave in self._slaves:
            slave.target = state
            if slave.position in refused:
                continue
            try:
                self._request(slave, state, timeout)
            except AlStateError as exc:
                errors.append(exc)
        if errors:
            raise errors[0]

    def close(self) -> None:
        """Stop the threads, send every slave to INIT, close the interface (idempotent)."""
        self._stop.set()
        for thread in (self._cycle_thread, self._supervisor):
            if thread is not None and thread is not threading.current_thread():
                thread.join(2.0)
        self._cycle_thread = self._supervisor = None
        master, self._master = self._master, None
        if master is None:
            return
        try:
            if self._slaves:
                master.state = ALState.INIT
                master.write_state()
        except Exception:  # noqa: BLE001 - best effort on the way out
            log.debug('could not request INIT on close', exc_info=True)
        master.close()
        self._master_lock.release()

    def __enter__(self) -> 'EthercatSegment':
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- statistics -------------------------------------------------------------------------

    def _reset_stats(self) -> None:
        self._cycles = self._missed = self._wkc_errors = self._lost_frames = 0
        self._last_wkc = 0
        self._jitter: deque[float] = deque(maxlen=100_000)
        self._cpu = 0.0
        self._started = time.monotonic()

    def counts(self) -> CycleCounts:
        """Return the counters alone, for each drive's cycle (stats() sorts the jitter)."""
        return CycleCounts(self._cycles, self._missed, self._wkc_errors, self._lost_frames)

    def stats(self) -> CycleStats:
        """Counters and wake-up jitter (sorts up to 100 000 samples: not for each cycle)."""
        jitter = sorted(self._jitter)
        return CycleStats(
            cycles=self._cycles, missed_cycles=self._missed, wkc_errors=self._wkc_errors,
            lost_frames=self._lost_frames, expected_wkc=self._expected_wkc,
            last_wkc=self._last_wkc,
            jitter_p50_s=statistics.median(jitter) if jitter else 0.0,
            jitter_p99_s=jitter[int(0.99 * (len(jitter) - 1))] if jitter else 0.0,
            jitter_max_s=jitter[-1] if jitter else 0.0,
            cycle_cpu_s=self._cpu, elapsed_s=time.monotonic() - self._started)

    # -- the process-data thread --------------------------------------------------------------

    def _cycle(self) -> None:
        master = self._master
        settings = self.settings
        period = settings.cycle_time_s
        receive_us = max(200, int(period * 0.8e6))
        if settings.realtime_priority:
            try:
                os.sched_setscheduler(0, os.SCHED_FIFO,
                                      os.sched_param(settings.realtime_priority))
            except OSError as exc:
                log.warning('no real-time priority for the EtherCAT cycle: %s', exc)
        dc = settings.sync_mode is SyncMode.DC
        cycle_ns = int(period * 1e9)
        shift_ns = int(settings.dc_shift_s * 1e9)
        slaves = self._slaves
        cpu_start = time.thread_time()
        next_time = time.monotonic()
        while not self._stop.is_set():
            delay = next_time - time.monotonic()
            if delay > 0:
                time.sleep(delay)
            woke = time.monotonic()
            self._jitter.append(woke - next_time)
            with self._io_lock:
                for slave in slaves:
                    if slave._outputs:
                        if slave._hold_s and woke - slave._outputs_time > slave._hold_s:
                            slave._soem.output = slave._safe_outputs      # nobody refreshes
                            slave._held_cycles += 1
                        else:
                            slave._soem.output = slave._outputs
            master.send_processdata()
            wkc = master.receive_processdata(receive_us)
            self._cycles += 1
            self._last_wkc = wkc
            if wkc < 0:
                self._lost_frames += 1
                self._trouble.set()
            else:
                if wkc < self._expected_wkc:
                    self._wkc_errors += 1
                    self._trouble.set()
                now = time.monotonic()
                with self._io_lock:
                    for slave in slaves:
                        if not slave.lost:
                            slave._inputs = slave._soem.input
                            slave._inputs_time = now
            next_time += period
            if dc and wkc >= 0:
                # keep the cycle start at a fixed phase of the DC reference time, so that
                # frames arrive before SYNC0 (a proportional step, as SOEM's examples do)
                phase = (master.dc_time - shift_ns) % cycle_ns
                error = phase - cycle_ns if phase > cycle_ns // 2 else phase
                next_time -= 0.1 * error / 1e9
            late = time.monotonic() - next_time
            if late > period:                       # overran whole slots: skip, count them
                skipped = int(late // period)
                self._missed += skipped
                next_time += skipped * period
            self._cpu = time.thread_time() - cpu_start

    # -- the supervisor thread --------------------------------------------------------------------

    def _supervise(self) -> None:
        settings = self.settings
        next_poll = next_state_check = time.monotonic()
        checked = -math.inf
        while not self._stop.is_set():
            troubled = self._trouble.wait(settings.supervise_s)
            # At most one state check per supervise_s: while a slave is below its state
            # the WKC drops every cycle, and each drop ran a check (480/s, each one
            # writing the slave's set-up again: outside audit).
            if self._stop.wait(max(0.0, checked + settings.supervise_s - time.monotonic())):
                return
            if troubled or any(slave.lost for slave in self._slaves) or \
                    time.monotonic() >= next_state_check:
                self._trouble.clear()
                checked = time.monotonic()
                next_state_check = checked + settings.state_poll_s
                try:
                    self._check_states()
                except TransportError as exc:
                    log.debug('state check failed: %s', exc)
            if settings.mailbox_poll_s and time.monotonic() >= next_poll:
                next_poll = time.monotonic() + settings.mailbox_poll_s
                for slave in self._slaves:
                    if slave.lost or slave.state is ALState.INIT:
                        continue
                    try:
                        slave.poll_mailbox()
                    except TransportError as exc:
                        log.debug('mailbox poll of slave %d failed: %s', slave.position + 1, exc)

    def _check_states(self) -> None:
        """SOEM's recovery sequence: re-enter the target state, find lost slaves again."""
        self._read_states()
        for slave in self._slaves:
            target = slave.target
            if slave.state is target and not slave.al_status & AL_ERROR_FLAG:
                if slave.lost:
                    self._mark_returned(slave)
                if slave.esc_setup is None and target >= ALState.SAFE_OP:
                    slave.esc_setup = _read_esc_setup(slave, quietly=True)
                continue
            with self._state_lock:
                soem = slave._soem
                if slave.state is ALState.NONE:            # no answer: gone
                    if not slave.lost:
                        slave.lost = True
                        log.warning('EtherCAT slave %d lost', slave.position + 1)
                        if self.on_slave_lost:
                            self.on_slave_lost(slave.position)
                    if self.settings.recover and soem.recover(timeout=3000) > 0:
                        # (in INIT now: the next passes bring it up)
                        log.info('EtherCAT slave %d found again', slave.position + 1)
                    continue
                if self.on_slave_fell:
                    self.on_slave_fell(slave.position, slave.al_status, slave.al_status_code)
                if slave.al_status & AL_ERROR_FLAG:        # acknowledge, then go on
                    soem.state = (slave.al_status & AL_STATE_MASK) | AL_ERROR_FLAG
                    soem.write_state()
                below_safe_op = slave.state in (ALState.INIT, ALState.PRE_OP) and \
                    target >= ALState.SAFE_OP
                if not below_safe_op:
                    soem.state = int(target)
                    soem.write_state()
                    continue
            self._bring_up(slave)

    def _bring_up(self, slave: EthercatSlave) -> None:
        """Take one step of SOEM's reconfiguration of a slave below SAFE-OP; never wait.

        SOEM's ``reconfig`` waits up to 2 s for each of INIT, PRE-OP and SAFE-OP
        inside one pysoem call that keeps the GIL: a slave slow to get there (a drive
        busy after a power cycle, one stuck in PRE-OP) froze the whole process for
        2 s per retry, its process-data thread and every drive's loop with it (an
        outside audit: the other slaves' SM watchdogs tripped, a watchdog stop and
        ``~/stop`` came 2 s late). The same steps, one per supervisor pass: in INIT
        the sync managers and FMMUs as config_map left them, then PRE-OP is asked;
        in PRE-OP the set-up is written again if the slave came through INIT, then
        SAFE-OP is asked. The state is read again at the next pass.
        """
        soem = slave._soem
        if slave.state is ALState.INIT:
            slave.setup_due = True
            if slave.esc_setup is None:
                # Never read (no answer at start, nor since in OP): SOEM's own, which
                # waits (up to 2 s per state, the process with it), the set-up as its hook.
                setup = slave.preop_setup
                soem.config_func = (lambda position: setup()) if setup else None
                with self._state_lock:
                    soem.reconfig(timeout=3000)
                return
            try:
                for address, data in zip((ESC_SYNC_MANAGERS, ESC_FMMUS), slave.esc_setup):
                    if data:
                        soem._fpwr(address, data)   # noqa: SLF001 - pysoem's FPWR primitive
            except pysoem.WkcError:
                log.debug('slave %d: sync managers not written, next pass', slave.position + 1)
                return
            following = ALState.PRE_OP
        else:
            if slave.setup_due and slave.preop_setup is not None:
                if time.monotonic() < slave.setup_retry_at:
                    return
                try:
                    slave.preop_setup()
                except (TransportError, ProtocolException) as exc:
                    # Tried again every SETUP_RETRY_S, told once: each pass wrote it
                    # and logged a line (1000 lines in 3 s: outside audit).
                    slave.setup_retry_at = time.monotonic() + SETUP_RETRY_S
                    if not slave.setup_error:
                        log.warning('EtherCAT slave %d: set-up not written again at PRE-OP, '
                                    'so it stays there: %s', slave.position + 1, exc)
                    slave.setup_error = f'its set-up is not written again at PRE-OP: {exc}'
                    return
            if slave.setup_due:
                if slave.sync0 is not None:
                    # A power cycle lost its SYNC0 too: it ran free, or a drive that
                    # needs it refused SAFE-OP for good (outside re-check). Started again
                    # from its own clock (SOEM's reconfig did not restore it either).
                    soem.dc_sync(True, *slave.sync0)
            slave.setup_due, slave.setup_error = False, ''
            following = ALState.SAFE_OP
        with self._state_lock:
            soem.state = int(following)
            soem.write_state()

    def _mark_returned(self, slave: EthercatSlave) -> None:
        slave.lost = False
        log.info('EtherCAT slave %d is back in %s', slave.position + 1, slave.state.name)
        if self.on_slave_returned:
            self.on_slave_returned(slave.position)

    # -- helpers ----------------------------------------------------------------------------------

    def _require_open(self) -> Any:
        if self._master is None:
            raise EthercatError('the EtherCAT segment is not open')
        return self._master

    def _read_states(self) -> None:
        master = self._require_open()
        now = time.monotonic()
        with self._state_lock:
            master.read_state()
            for slave in self._slaves:
                soem = slave._soem
                state = _state(soem.state)
                if state is ALState.NONE and not slave.lost:
                    # No answer. A frame or a few lost (interference; SOEM resends within
                    # ~30 ms) is not a lost slave: its last state stands until it has
                    # been silent for lost_after_s. Taking the first unanswered read as
                    # lost stopped every drive of the segment and reset the slaves.
                    if slave.unanswered_since is None:
                        slave.unanswered_since = now
                    if now - slave.unanswered_since < self.settings.lost_after_s:
                        continue
                else:
                    slave.unanswered_since = None
                slave.al_status = soem.state
                slave.state = state
                slave.al_status_code = soem.al_status

    def _request(self, slave: EthercatSlave, state: ALState, timeout: float | None) -> None:
        self._require_open()
        timeout = self.settings.state_timeout_s if timeout is None else timeout
        with self._state_lock:
            soem = slave._soem
            # an unacknowledged error blocks every request upwards: acknowledge with it
            soem.state = int(state) | (AL_ERROR_FLAG if slave.al_status & AL_ERROR_FLAG else 0)
            soem.write_state()
        self._await(state, [slave], timeout)

    def _await_each(self, state: ALState, timeout: float) -> list[AlStateError]:
        """Wait until every slave reports ``state``; return the refusals (in line order)."""
        deadline = time.monotonic() + timeout
        refusals: list[AlStateError] = []
        for slave in self._slaves:
            try:
                self._await(state, [slave], max(0.0, deadline - time.monotonic()))
            except AlStateError as exc:
                refusals.append(exc)
            except CommTimeout:                             # (says "it does not answer")
                refusals.append(AlStateError(slave.position, state, 0, 0))
        return refusals

    def _await(self, state: ALState, slaves: list[EthercatSlave], timeout: float) -> None:
        """Wait until every slave reports ``state``; AlStateError with the code if not."""
        deadline = time.monotonic() + timeout
        pending = list(slaves)
        error_since: dict[int, float] = {}
        while True:
            with self._state_lock:
                for slave in list(pending):
                    soem = slave._soem
                    reached = soem.state_check(int(state), 1000)
                    slave.al_status = soem.state
                    slave.state = _state(soem.state)
                    slave.al_status_code = soem.al_status
                    if reached == state and not soem.state & AL_ERROR_FLAG:
                        pending.remove(slave)
                    elif soem.state & AL_ERROR_FLAG:
                        # firmware may take a moment to take back an acknowledged error:
                        # an error that stays is the slave's answer
                        first = error_since.setdefault(slave.position, time.monotonic())
                        if time.monotonic() - first > ERROR_SETTLE_S:
                            raise AlStateError(slave.position, state, soem.state,
                                               soem.al_status)
            if not pending:
                return
            if time.monotonic() > deadline:
                slave = pending[0]
                if slave.al_status == 0:
                    raise CommTimeout(f'slave {slave.position + 1} did not answer while waiting '
                                      f'for {state.name}')
                raise AlStateError(slave.position, state, slave.al_status, slave.al_status_code)
            time.sleep(0.002)

    def _set_watchdog(self, slave: EthercatSlave, seconds: float) -> None:
        with self._mailbox_lock, warnings.catch_warnings():
            warnings.simplefilter('ignore')            # rounding to the divider's resolution
            try:
                slave._soem.set_watchdog('processdata', seconds * 1000.0)
            except (AttributeError, pysoem.WkcError) as exc:
                raise EthercatError(f'slave {slave.position + 1}: SM watchdog of {seconds} s not '
                                    f'set: {exc}') from exc

    def _mailbox(self, slave: EthercatSlave, what: str, index: int, subindex: int,
                 call: Callable[[], Any], attempts: int = 1) -> Any:
        self._require_open()
        with self._mailbox_lock:
            try:
                for attempt in range(attempts - 1):
                    try:
                        return call()
                    except pysoem.WkcError as exc:    # a frame lost: an upload starts over
                        log.info('slave %d: %s lost a frame (WKC %s), attempt %d of %d',
                                 slave.position + 1, what, exc.wkc, attempt + 1, attempts)
                return call()
            except pysoem.SdoError as exc:
                raise SdoAbortError(slave.position, index, subindex, exc.abort_code) from exc
            except pysoem.WkcError as exc:
                raise CommTimeout(f'slave {slave.position + 1}: no mailbox answer to {what} '
                                  f'(WKC {exc.wkc})') from exc
            except pysoem.MailboxError as exc:
                raise EthercatError(f'slave {slave.position + 1}: mailbox error {exc.error_code} '
                                    f'({exc.desc}) on {what}') from exc
            except pysoem.PacketError as exc:
                raise BadFrame(f'slave {slave.position + 1}: unexpected mailbox reply to {what} '
                               f'(packet error {exc.error_code})') from exc
            except pysoem.Emergency as exc:            # without a callback pysoem raises it
                slave._on_emergency(exc)
                return None


# -- the transport plugin: one segment shared by the drives on it ------------------------------


@dataclass(frozen=True)
class SlaveSetup:
    """What a drive needs of its slave, given at attach (plain values, no drive knowledge).

    ``position`` is 1-based in line order, as SOEM and configuration tools number
    slaves; with ``alias`` set it is only the drive's key (its unit), and the slave is
    the one whose configured station alias (SII word 4) is ``alias``.
    Identity values of None are not checked; ``device_name`` is checked
    only when given. ``startup`` SDO writes happen at PRE-OP, after the PDO
    assignment and before SAFE-OP; ``safe_outputs`` are sent while no drive owns
    the slave (closed, lost), so a returning slave never sees a stale command.
    """

    position: int
    pdos: PdoConfiguration
    output_size: int
    input_size: int
    safe_outputs: bytes
    vendor_id: int | None = None
    product_code: int | None = None
    device_name: str = ''
    fixed_mapping: bool = False
    startup: tuple[tuple[int, int, bytes], ...] = ()
    sync_cycles_s: tuple[float, ...] = ()      # SYNC0 cycles the slave accepts (empty: any)
    alias: int = 0                             # find the slave by its SII station alias
    dc: bool = True                            # the slave supports DC SYNC0
    free_run: bool = True


class EthercatTransport(Transport):
    """``transport.type: ethercat``: one EtherCAT segment (one NIC) and its slaves.

    Every drive of a bus shares one instance, hence one ``EthercatSegment`` with
    one process-data thread. The segment is opened (and every attached slave
    identified, mapped and brought to OP) by the first ``open_slave`` and closed
    when the last slave is closed; a slave lost and found again meanwhile is
    brought back by the segment's supervisor. ``unit`` = slave position, 1-based.
    """

    parameters = (
        TransportParameter('interface', '', 'network interface of the EtherCAT segment (e.g. '
                           'enp3s0); raw-socket rights needed (root or CAP_NET_RAW)'),
        TransportParameter('namespace', '', 'network namespace of the interface (tests); '
                           "'' = the node's own"),
        TransportParameter('cycle_time', 0.002, 's per process-data cycle (one thread per '
                           'segment)'),
        TransportParameter('sync_mode', 'free_run', 'free_run (slaves on their own clock) or dc '
                           '(distributed clocks, SYNC0 every cycle_time)'),
        TransportParameter('state_timeout', 2.0, 's each AL state change may take'),
        TransportParameter('sdo_timeout', 0.7, 's each SDO exchange may take'),
        TransportParameter('realtime_priority', 0, 'SCHED_FIFO priority (1..99) of the '
                           'process-data thread; 0 = normal scheduling (a refusal is logged)'),
        TransportParameter('stale_after', 0.25, 's without fresh inputs from a slave before it '
                           'counts as silent (a loaded host may skip some cycles)'),
    )
    shared_by_drives = True

    def __init__(self, settings: SegmentSettings, stale_after: float = 0.25) -> None:
        super().__init__()
        self.settings = settings
        self.stale_after = stale_after
        self.timeout = settings.sdo_timeout_s
        self._setups: dict[int, SlaveSetup] = {}
        self._watchdogs: dict[int, float] = {}
        self._holds: dict[int, float] = {}
        self._errors: dict[int, str] = {}          # position -> why it cannot be used
        self._open_units: set[int] = set()
        self._where: dict[int, int] = {}          # unit -> 1-based position (alias lookup)
        self._segment: EthercatSegment | None = None
        self._lock = threading.RLock()
        self._missed_seen = (0, 0.0)      # missed cycles as last seen, and when they grew
        # unit -> why: its slave fell below OP by itself since its drive opened it (plain
        # dict operations: the supervisor sets it holding the segment's state lock)
        self._fell: dict[int, str] = {}

    @classmethod
    def from_settings(cls, settings: Mapping[str, Any]) -> 'EthercatTransport':
        interface = str(settings.get('interface', '') or '')
        if not interface:
            raise TransportError('transport.interface is empty: name the network interface of '
                                 'the EtherCAT segment (e.g. enp3s0)')
        try:
            mode = SyncMode(str(settings.get('sync_mode', 'free_run')))
        except ValueError:
            raise TransportError(f'transport.sync_mode {settings.get("sync_mode")!r}: use '
                                 'free_run or dc') from None
        cycle = float(settings.get('cycle_time', 0.002))
        if not 0.0001 <= cycle <= 0.1:
            raise TransportError(f'transport.cycle_time {cycle:g} s: use 0.0001..0.1 s')
        priority = int(settings.get('realtime_priority', 0) or 0)
        if not 0 <= priority <= 99:
            raise TransportError(f'transport.realtime_priority {priority}: use 0..99')
        stale = float(settings.get('stale_after', 0.25))
        if stale < 2 * cycle:
            raise TransportError(f'transport.stale_after {stale:g} s must be at least two '
                                 f'cycles ({2 * cycle:g} s)')
        return cls(SegmentSettings(
            interface=interface, namespace=str(settings.get('namespace', '') or '') or None,
            cycle_time_s=cycle, sync_mode=mode,
            state_timeout_s=float(settings.get('state_timeout', 2.0)),
            sdo_timeout_s=float(settings.get('sdo_timeout', 0.7)),
            realtime_priority=priority or None, lost_after_s=stale), stale)

    @property
    def description(self) -> str:
        where = f'@{self.settings.namespace}' if self.settings.namespace else ''
        return f'ethercat:{self.settings.interface}{where}'

    @property
    def link_notes(self) -> tuple[str, ...]:
        segment = self._segment
        if segment is None:
            return ()
        stats = segment.counts()
        now = time.monotonic()
        if stats.missed_cycles != self._missed_seen[0]:
            self._missed_seen = (stats.missed_cycles, now)
        notes = []
        # A warning while cycles go missing, not for the rest of the run after one did.
        if stats.missed_cycles and now - self._missed_seen[1] < MISSED_CYCLES_RECENT:
            notes.append(f'{stats.missed_cycles} missed process-data cycles of '
                         f'{stats.cycles} ({self.settings.cycle_time_s * 1000:g} ms), the '
                         f'last {now - self._missed_seen[1]:.0f} s ago')
        return tuple(notes)

    def exchange_seconds(self, request_bytes: int, reply_bytes: int) -> float:
        return self.settings.cycle_time_s

    def failed_exchange_seconds(self) -> float:
        # A drive whose slave is gone fails its connect on the AL state read (one frame,
        # a few ms), not on an SDO timeout: its drive is offline before any mailbox use.
        return max(0.02, 5 * self.settings.cycle_time_s)

    # -- drives attach their slaves before the segment opens --------------------------------

    def attach(self, setup: SlaveSetup) -> None:
        """Register what the drive at ``setup.position`` needs (before the segment opens)."""
        if setup.position < 1:
            raise TransportError(f'EtherCAT slave position {setup.position}: positions start '
                                 'at 1 (the first slave after the master)')
        # Known from the profile before any frame: refused now, not retried for ever.
        where = f'slave alias {setup.alias}' if setup.alias else f'slave {setup.position}'
        cycle, mode = self.settings.cycle_time_s, self.settings.sync_mode
        if mode is SyncMode.DC and not setup.dc:
            raise TransportError(f'{where} has no DC sync (free run only): set '
                                 'transport.sync_mode free_run')
        if mode is SyncMode.FREE_RUN and not setup.free_run:
            raise TransportError(f'{where} does not run free: set transport.sync_mode dc')
        if mode is SyncMode.DC and setup.sync_cycles_s and not any(
                abs(cycle - c) < 1e-9 for c in setup.sync_cycles_s):
            allowed = ', '.join(f'{c * 1e6:g} us' for c in setup.sync_cycles_s)
            raise TransportError(f'{where} accepts cycle times {allowed}, not '
                                 f'transport.cycle_time {cycle * 1e6:g} us')
        with self._lock:
            if setup.position in self._setups:
                raise TransportError(f'EtherCAT slave {setup.position} is attached twice')
            self._setups[setup.position] = setup

    def set_watchdog(self, unit: int, seconds: float, hold_s: float = 0.0) -> None:
        """Ask for the SM (process-data) watchdog of one slave (0 = off), set at open.

        ``hold_s`` > 0: outputs the drive has not refreshed for that long are replaced
        by its safe outputs in the process-data thread (see ``guard_outputs``).
        """
        with self._lock:
            self._watchdogs[unit] = seconds
            self._holds[unit] = hold_s
            segment = self._segment
            setup = self._setups.get(unit)
        position = self._where.get(unit, unit)
        if segment is not None and setup is not None and position <= len(segment.slaves):
            segment.slave(position - 1).guard_outputs(setup.safe_outputs, hold_s)

    def outputs_held(self, unit: int) -> int:
        slave = self._slave(unit, check=False)
        return slave.outputs_held if slave is not None else 0

    def watchdog(self, unit: int) -> float | None:
        """Return the SM watchdog time the slave holds now (s; None: unknown)."""
        slave = self._slave(unit, check=False)
        if slave is None:
            return None
        try:
            with self._segment._mailbox_lock:              # type: ignore[union-attr]
                return float(slave._soem.get_watchdog('processdata')) / 1000.0
        except Exception:  # noqa: BLE001 - pysoem raises several kinds here
            return None

    # -- lifecycle ---------------------------------------------------------------------------

    def open(self) -> None:
        """Open the segment: identify, map and start every attached slave (idempotent)."""
        with self._lock:
            if self._segment is not None:
                return
            self._errors.clear()
            # Each slave its own drive's SM watchdog (0 = off; a slave no drive drives
            # keeps its ESC's): the smallest for all made a drive that asked for none
            # report "off" while its slave held another's 0.3 s (outside audit).
            settings = SegmentSettings(**{**self.settings.__dict__, 'watchdog_s': None})
            segment = EthercatSegment(settings, on_slave_lost=self._on_lost,
                                      on_slave_returned=self._on_returned,
                                      on_slave_fell=self._on_fell)
            try:
                identities = segment.open()
                self._locate(segment)
                for unit, setup in sorted(self._setups.items()):
                    if unit not in self._errors:
                        self._prepare(segment, identities, setup, self._where[unit])
                        seconds = self._watchdogs.get(unit)
                        if seconds is not None:
                            segment._set_watchdog(segment.slave(self._where[unit] - 1),
                                                  seconds)
                # no SYNC0 for a slave without DC, nor for one its drive cannot use (a
                # refused cycle would keep the whole segment below SAFE-OP)
                free_running = frozenset(self._where[unit] - 1
                                         for unit, setup in self._setups.items()
                                         if unit in self._where and
                                         (not setup.dc or unit in self._errors))
                try:
                    segment.start(free_running)
                except AlStateError as exc:
                    if segment._cycle_thread is None:
                        raise                    # the segment never reached SAFE-OP
                    # One slave below OP must not keep the others from running: the
                    # supervisor keeps asking it, its drive reports the AL status code.
                    log.warning('EtherCAT %s: %s', self.settings.interface, exc)
            except BaseException as exc:
                segment.close()
                self.count(None, 'connect_failures')
                if isinstance(exc, (TransportError, ProtocolException)):
                    raise
                if isinstance(exc, Exception):
                    raise EthercatError(f'{self.description}: {exc}') from exc
                raise
            self._segment = segment
            for unit, setup in self._setups.items():
                if unit not in self._errors:
                    try:
                        slave = segment.slave(self._where[unit] - 1)
                        slave.set_outputs(setup.safe_outputs)
                        slave.guard_outputs(setup.safe_outputs, self._holds.get(unit, 0.0))
                    except ValueError as exc:       # mapped other than the drive expects
                        self._errors[unit] = str(exc)
                        continue
                    # Written again when the slave comes back through INIT (after a
                    # power cycle), at PRE-OP: what was written there at start.
                    slave.preop_setup = self._preop_setup(slave, setup)

    @staticmethod
    def _preop_setup(slave: EthercatSlave, setup: SlaveSetup) -> Callable[[], None]:
        """Return what writes the slave's set-up again at PRE-OP, before SAFE-OP.

        The supervisor runs it (``EthercatSegment._bring_up``); an SDO failure raises,
        and the slave then stays in PRE-OP, with its drive offline, until it takes it.
        """
        def write_again() -> None:
            EthercatTransport._write_setup(slave._segment, slave.position, setup)
            log.info('EtherCAT slave %d: PDO set-up written again', slave.position + 1)
        return write_again

    @staticmethod
    def _write_setup(segment: EthercatSegment, position: int, setup: SlaveSetup) -> None:
        """Write a slave's PDO assignment (its mapping too, unless fixed) and start-up objects.

        At PRE-OP, at open and after a power cycle alike. ``position`` is 0-based.
        """
        segment.configure_pdos(position, setup.pdos if not setup.fixed_mapping else
                               PdoConfiguration(setup.pdos.rx, setup.pdos.tx))
        slave = segment.slave(position)
        for index, subindex, data in setup.startup:
            slave.sdo_write(index, subindex, data)

    def _locate(self, segment: EthercatSegment) -> None:
        """Find each attached slave: by position, or by its station alias (SII word 4)."""
        self._where.clear()
        aliases: list[int] | None = None
        taken: dict[int, int] = {}
        for unit, setup in sorted(self._setups.items()):
            position = unit
            if setup.alias:
                if aliases is None:
                    aliases = [_sii_alias(slave) for slave in segment.slaves]
                matches = [n + 1 for n, alias in enumerate(aliases) if alias == setup.alias]
                if len(matches) != 1:
                    shown = ', '.join(f'{n + 1}: 0x{a:04X}' for n, a in enumerate(aliases))
                    self._errors[unit] = (
                        f'{"no" if not matches else "more than one"} EtherCAT slave with '
                        f'station alias 0x{setup.alias:04X} on {self.settings.interface} '
                        f'(aliases by position: {shown})')
                    continue
                position = matches[0]
            if position in taken:
                self._errors[unit] = (f'EtherCAT slave {position} is already driven by unit '
                                      f'{taken[position]}')
                continue
            taken[position] = unit
            self._where[unit] = position

    def _prepare(self, segment: EthercatSegment, identities: list[SlaveIdentity],
                 setup: SlaveSetup, position: int) -> None:
        unit = setup.position
        if position > len(identities):
            found = ', '.join(f'{i.position + 1}: {i.name}' for i in identities)
            self._errors[unit] = (f'no EtherCAT slave at position {position}: the segment '
                                  f'on {self.settings.interface} has {len(identities)} '
                                  f'({found})')
            return
        ident = identities[position - 1]
        problem = identity_mismatch(ident, setup)
        if problem:
            self._errors[unit] = problem
            return
        try:
            self._write_setup(segment, position - 1, setup)
        except (TransportError, ProtocolException) as exc:
            self._errors[unit] = f'slave {position} set-up at PRE-OP failed: {exc}'

    def _on_lost(self, position: int) -> None:
        # A lost slave gets its safe outputs, so that it never sees the last command
        # again when it comes back before its drive has reconnected.
        unit = next((u for u, p in self._where.items() if p == position + 1), None)
        setup = self._setups.get(unit) if unit is not None else None
        segment = self._segment
        if setup is not None and segment is not None:
            try:
                segment.slave(position).set_outputs(setup.safe_outputs)
            except ValueError:
                pass

    def _on_fell(self, position: int, al_status: int, code: int) -> None:
        # A slave its drive drives fell below OP by itself: it gets its safe outputs
        # before the supervisor brings it back, and its drive is told of the fall (reads
        # and writes fail) until it reconnects. Back in OP on the last command, it would
        # run on it, and the drive would be walked back to Operation Enabled on it.
        unit = next((u for u, p in self._where.items() if p == position + 1), None)
        if unit is None or unit not in self._open_units or unit in self._fell:
            return
        self._on_lost(position)
        self._fell[unit] = (f'EtherCAT slave {unit} left OP: it fell to '
                            f'{al_state_name(al_status)}, AL status code 0x{code:04X} '
                            f'({al_status_text(code)})')
        log.warning('%s; it is brought back with safe outputs, its drive reconnects',
                    self._fell[unit])

    def _on_returned(self, position: int) -> None:
        # A slave that was powered off comes back with its ESC defaults: set its SM
        # watchdog again (its drive reads it back and reports it when it reconnects).
        unit = next((u for u, p in self._where.items() if p == position + 1), None)
        segment = self._segment
        seconds = self._watchdogs.get(unit) if unit is not None else None
        if segment is None or seconds is None:
            return
        try:
            segment._set_watchdog(segment.slave(position), seconds)
        except TransportError as exc:
            log.warning('EtherCAT slave %d: SM watchdog not set again: %s', position + 1, exc)

    def open_slave(self, unit: int) -> None:
        """Open the segment if needed and check that slave ``unit`` is usable (in OP)."""
        self.open()
        with self._lock:
            error = self._errors.get(unit)
        if error:
            raise EthercatError(error)
        slave = self._slave(unit)
        slave.read_state()
        if slave.state is not ALState.OP or slave.al_status & AL_ERROR_FLAG:
            refused = AlStateError(slave.position, ALState.OP, slave.al_status,
                                   slave.al_status_code)
            if slave.setup_error:
                raise EthercatError(f'{refused}; {slave.setup_error}') from refused
            raise refused
        # Back in OP before the supervisor's next pass marks it back: that pass is
        # waited for (the connect failed on "lost" and cost one more: outside audit).
        back_by = time.monotonic() + 4 * self.settings.supervise_s
        while slave.lost and time.monotonic() < back_by:
            time.sleep(self.settings.supervise_s / 4)
        if slave.lost:
            raise CommTimeout(f'EtherCAT slave {unit} is back in OP but still lost to the '
                              "segment's supervisor")
        with self._lock:
            self._fell.pop(unit, None)
            self._open_units.add(unit)

    def close_slave(self, unit: int) -> None:
        """Hand slave ``unit`` its safe outputs; close the segment with the last slave."""
        with self._lock:
            self._open_units.discard(unit)
            setup = self._setups.get(unit)
            segment = self._segment
            position = self._where.get(unit, unit)
            if segment is not None and setup is not None and position <= len(segment.slaves):
                try:
                    segment.slave(position - 1).set_outputs(setup.safe_outputs)
                except ValueError:
                    pass
            if not self._open_units:
                self.close()

    def close(self) -> None:
        with self._lock:
            segment, self._segment = self._segment, None
            self._open_units.clear()
            self._fell.clear()
        if segment is not None:
            segment.close()

    # -- per-slave data ---------------------------------------------------------------------

    def _slave(self, unit: int, check: bool = True) -> Any:
        segment = self._segment
        if segment is None:
            if not check:
                return None
            raise EthercatError(f'{self.description} is not open')
        position = self._where.get(unit, unit)
        if not 1 <= position <= len(segment.slaves):
            if not check:
                return None
            raise EthercatError(f'no EtherCAT slave at position {position}')
        return segment.slave(position - 1)

    def write_outputs(self, unit: int, data: bytes) -> None:
        """Send ``data`` as slave ``unit``'s RxPDO bytes from the next cycle on."""
        slave = self._slave(unit)
        fell = self._fell.get(unit)
        if fell:                            # its safe outputs stand until it reconnects
            raise EthercatError(fell)
        try:
            slave.set_outputs(data)
        except ValueError as exc:
            raise EthercatError(str(exc)) from exc

    def wait_cycles(self, count: int) -> None:
        """Return once ``count`` more process-data cycles ran (bounded: never raises)."""
        segment = self._segment
        if segment is None:
            return
        target = segment._cycles + count
        deadline = time.monotonic() + count * self.settings.cycle_time_s * 5 + 0.05
        while segment._cycles < target and time.monotonic() < deadline:
            time.sleep(self.settings.cycle_time_s / 2)

    def read_inputs(self, unit: int) -> bytes:
        """Return slave ``unit``'s TxPDO bytes; TransportError if lost, below OP or stale."""
        slave = self._slave(unit)
        segment = self._segment
        if segment is not None:
            stats = segment.counts()
            self.stats.transactions = stats.cycles
            self.stats.bad_frames = stats.wkc_errors
            self.stats.timeouts = stats.lost_frames
        self.count_unit(unit, 'transactions')
        if not slave.inputs_time and not slave.lost:
            # The segment has just opened (its first cycles are under way): a connect
            # right after it failed on "no process data yet", closed the segment, and
            # took one to three more opens (outside audit).
            first = time.monotonic() + self.stale_after
            while not slave.inputs_time and time.monotonic() < first:
                time.sleep(self.settings.cycle_time_s / 2)
        age = time.monotonic() - slave.inputs_time
        if slave.lost:
            self.count_unit(unit, 'timeouts')
            raise CommTimeout(f'EtherCAT slave {unit} lost (no answer on '
                              f'{self.settings.interface})')
        fell = self._fell.get(unit)
        if fell:
            self.count_unit(unit, 'exceptions')
            raise EthercatError(fell)
        if slave.state is ALState.NONE:        # no state read yet, or silent past lost_after_s
            self.count_unit(unit, 'timeouts')
            raise CommTimeout(f'EtherCAT slave {unit} does not answer on '
                              f'{self.settings.interface}')
        if slave.state is not ALState.OP or slave.al_status & AL_ERROR_FLAG:
            self.count_unit(unit, 'exceptions')
            raise EthercatError(f'EtherCAT slave {unit} left OP: it is '
                                f'{al_state_name(slave.al_status)}, AL status code '
                                f'0x{slave.al_status_code:04X} '
                                f'({al_status_text(slave.al_status_code)})')
        if age > self.stale_after:
            self.count_unit(unit, 'timeouts')
            since = f'for {age:.2f} s' if slave.inputs_time else 'yet'
            raise CommTimeout(f'EtherCAT slave {unit}: no process data {since} '
                              f'(link down or working-counter errors on '
                              f'{self.settings.interface})')
        return slave.inputs()

    def count_unit(self, unit: int, counter: str) -> None:
        unit_stats = self.stats_for(unit)
        setattr(unit_stats, counter, getattr(unit_stats, counter) + 1)

    def sdo_read(self, unit: int, index: int, subindex: int) -> bytes:
        try:
            return self._slave(unit).sdo_read(index, subindex)
        except (TransportError, ProtocolException):
            self.count_unit(unit, 'exceptions')
            raise

    def sdo_write(self, unit: int, index: int, subindex: int, data: bytes) -> None:
        try:
            self._slave(unit).sdo_write(index, subindex, data)
        except (TransportError, ProtocolException):
            self.count_unit(unit, 'exceptions')
            raise

    def take_emergencies(self, unit: int) -> list[Emergency]:
        slave = self._slave(unit, check=False)
        return slave.take_emergencies() if slave is not None else []

    def identity(self, unit: int) -> SlaveIdentity | None:
        slave = self._slave(unit, check=False)
        return slave.identity if slave is not None else None


def _sii_alias(slave: EthercatSlave) -> int:
    """Return the configured station alias of a slave's SII (word 4; 0 = none)."""
    try:
        return int.from_bytes(bytes(slave._soem.eeprom_read(4))[:2], 'little')
    except Exception:  # noqa: BLE001 - an unreadable SII has no alias to match
        return 0


def identity_mismatch(ident: SlaveIdentity, setup: SlaveSetup) -> str:
    """Say why a slave is not the one a drive expects ('' when it is)."""
    where = f'EtherCAT slave {ident.position + 1} ({ident.name!r})'
    wrong = []
    if setup.vendor_id is not None and ident.vendor_id != setup.vendor_id:
        wrong.append(f'vendor 0x{ident.vendor_id:X}, not 0x{setup.vendor_id:X}')
    if setup.product_code is not None and ident.product_code != setup.product_code:
        wrong.append(f'product 0x{ident.product_code:X}, not 0x{setup.product_code:X}')
    if setup.vendor_id is None and setup.product_code is None and setup.device_name and \
            ident.name != setup.device_name:
        wrong.append(f'device name {ident.name!r}, not {setup.device_name!r}')
    if not wrong:
        return ''
    return f'{where} is not the drive of the profile: {"; ".join(wrong)}'
