"""The interface between a simulated ESC and the device application behind its PDI.

A real EtherCAT slave is an ESC (the frame-processing chip: registers, SyncManagers,
FMMUs, SII) plus firmware on its PDI (object dictionary, process data, the AL
state machine's checks, the device itself). ``Esc`` plays the chip and the generic
part of the slave stack; everything device-specific sits behind
``SlaveApplication``, so a drive profile only has to supply one of these.

All calls come from the segment's single serving thread; none may block.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol, runtime_checkable

from ...protocol.ethercat import ALState


@dataclass(frozen=True)
class Emergency:
    """A CoE emergency for the master (ETG.1000.6 5.6.2.4; codes CiA 301 table 21)."""

    error_code: int
    error_register: int
    data: bytes = bytes(5)           # manufacturer-specific error field


@dataclass(frozen=True)
class TransitionContext:
    """What the ESC knows about its configuration when a state change is requested."""

    output_bytes: int                # SM2 length configured by the master
    input_bytes: int                 # SM3 length
    sync0_cycle_ns: int              # 0 = free run (DC SYNC0 not activated)
    watchdog_s: float                # process-data watchdog time, 0 = disabled


@runtime_checkable
class SlaveApplication(Protocol):
    """Device firmware behind an ESC: object dictionary, process data, AL hooks, time."""

    def read_object(self, index: int, subindex: int) -> tuple[int, bytes]:
        """SDO upload: ``(0, data)`` or ``(CiA 301 abort code, b'')``."""

    def write_object(self, index: int, subindex: int, data: bytes) -> int:
        """SDO download: 0, or the CiA 301 abort code (the value is then unchanged)."""

    def process_data_sizes(self) -> tuple[int, int]:
        """``(RxPDO bytes, TxPDO bytes)`` of the current PDO assignment."""

    def rx_pdo(self, data: bytes) -> None:
        """Take new outputs from the master (a complete SM2 buffer)."""

    def tx_pdo(self) -> bytes:
        """Return the current inputs for the master (the next SM3 buffer)."""

    def request_state(self, current: ALState, requested: ALState,
                      context: TransitionContext) -> int:
        """Accept a transition the ESC found valid (0) or refuse it with an AL status code."""

    def state_changed(self, state: ALState) -> None:
        """Note the new AL state (after a request, or an error such as the watchdog)."""

    def watchdog_expired(self) -> None:
        """React to the process-data (SM) watchdog expiring in OP: outputs are stale."""

    def tick(self, now: float) -> None:
        """Advance the device to ``now`` (seconds, monotonic clock)."""

    def take_emergencies(self) -> list[Emergency]:
        """Emergencies raised since the last call, oldest first."""
