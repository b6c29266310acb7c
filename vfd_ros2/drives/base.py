"""What every drive class offers the control loop, whatever the bus.

``Drive`` is the protocol (drive verbs in SI units, no ROS, every call bounded
by the link's timeouts); ``Reading`` is what one poll learnt; the host-loss
protection types and the sizing of a drive's own comm-loss timeout are here
because every bus has one (a Modbus register, a CANopen consumer heartbeat, an
EtherCAT sync-manager watchdog).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Callable, ClassVar, Mapping, Protocol

from ..errors import ParameterError
from ..profiles import NO_FAULT, Access, FaultInfo, Parameter, Profile
from ..transports.base import Transport, TransportParameter, TransportStats

#: s added to twice the worst-case addressing interval when sizing a drive's own
#: comm-loss timeout: the host's scheduling jitter on a loaded machine
HOST_LOSS_JITTER = 0.05

#: transactions one service action may add to a cycle (a RAM/EEPROM switch read and
#: write, the write, its read-back)
ACTION_TRANSACTIONS = 4


@dataclass
class Reading:
    """What one poll cycle learnt (values keep their last reading between polls)."""

    values: dict[str, float] = field(default_factory=dict)      # role -> engineering value
    raw_words: dict[str, int] = field(default_factory=dict)     # code -> raw register value
    flags: dict[str, bool] = field(default_factory=dict)
    fault: FaultInfo = NO_FAULT
    warning_code: int = 0
    warning_subcode: int = 0
    measured_velocity: float = math.nan
    # Why the drive does not reach the state it is commanded to, as far as the drive
    # layer knows (e.g. a CiA 402 drive stuck before Operation Enabled); '' when it does.
    stuck: str = ''
    # Values the drive refuses to give (role -> the register and the drive's own
    # text): reported unavailable, control goes on.
    unavailable: dict[str, str] = field(default_factory=dict)
    # Why motion must not be allowed although the link is up (e.g. the fault or
    # run state cannot be read); '' when it may run.
    unsafe: str = ''


@dataclass(frozen=True)
class HostLossProtection:
    """What stops the drive by itself when the host falls silent, as set at connect."""

    mechanism: str = ''      # e.g. 'C02.04 comm-loss timeout'; '' = none
    timeout: float = 0.0     # s after the last valid request; 0 = none
    requested: float = 0.0   # drive_comm_timeout as configured
    note: str = ''           # why it differs from the request, or why there is none

    @property
    def active(self) -> bool:
        return bool(self.mechanism) and self.timeout > 0

    @property
    def weaker_than_requested(self) -> bool:
        if not self.active:
            return self.requested > 0
        return self.requested > 0 and self.timeout > self.requested + 1e-9

    def describe(self) -> str:
        if not self.active:
            return f'none: {self.note}' if self.note else 'none'
        text = f'{self.mechanism}: {self.timeout:g} s'
        return f'{text} ({self.note})' if self.note else text


def beyond_register(velocity: float, raw: float, low: float, high: float, register: str,
                    scaling_hint: str) -> str:
    """Return why ``velocity`` (rad/s) cannot be written unclamped ('' if it can).

    ``raw`` is its setpoint before any clamping, ``low``..``high`` what ``register``
    takes. A clamped setpoint runs the drive at the register's end, not at the
    command: with a wrong scaling (rpm per count off by 1000) a slow command runs
    the motor flat out while the measured speed, scaled the same wrong way, looks slow.
    """
    if low <= raw <= high:
        return ''
    return (f'{velocity:g} rad/s is {raw:.6g} in {register}, beyond its range {low:g}..'
            f'{high:g}: lower max_velocity, or check {scaling_hint}')


def size_comm_timeout(parameter: Parameter, requested: float,
                      minimum: float) -> tuple[float, str]:
    """Choose the value of a drive's comm-loss timeout parameter; (seconds, note).

    The request is rounded to the parameter's resolution, raised to ``minimum``
    (what the bus needs so that a healthy drive never trips) and kept within the
    parameter's range; the note says why the result differs from the request.
    ``requested`` 0 asks for no timeout. Raises ParameterError when the bus needs
    more than the parameter allows.
    """
    step = abs(parameter.scale)
    low_raw, high_raw = parameter.type.bounds
    highest = parameter.maximum if parameter.maximum is not None else high_raw * step
    lowest = max(parameter.minimum if parameter.minimum is not None else 0.0, step)
    code = parameter.code
    if requested == 0:
        try:
            parameter.to_raw(0.0)
            return 0.0, 'off, as drive_comm_timeout 0 asks'
        except ParameterError:
            return highest, f'{code} has no off value: its longest, {highest:g} s'
    if minimum > highest + 1e-9:
        raise ParameterError(
            f'{code}: this drive is addressed at worst every {minimum / 2:.3g} s on its bus, '
            f'so its comm-loss timeout must be at least {minimum:.3g} s, but {code} allows '
            f'at most {highest:g} s: use a higher baud rate, fewer drives on the line or '
            'fewer polled values')
    value = round(requested / step) * step
    notes = []
    if abs(value - requested) > 1e-9:
        notes.append(f'{requested:g} s is not a multiple of {step:g} s')
    if value < minimum - 1e-9:
        value = math.ceil(minimum / step - 1e-9) * step
        notes.append(f'raised from {requested:g} s: the bus addresses this drive at worst '
                     f'every {(minimum - HOST_LOSS_JITTER) / 2 * 1000:.0f} ms, and less than '
                     f'{minimum:.3g} s would fault a healthy drive')
    if value < lowest - 1e-9:
        value = lowest
        notes.append(f'{code} allows no less than {lowest:g} s')
    if value > highest + 1e-9:
        value = highest
        notes.append(f'{code} allows at most {highest:g} s')
    value = round(round(value / step) * step, 9)     # on the grid, without float noise
    return value, '; '.join(notes)


@dataclass(frozen=True)
class ParameterValue:
    parameter: Parameter
    raw: int
    value: float

    @property
    def text(self) -> str:
        return self.parameter.option_text(self.raw)


class DriveOnLink:
    """What every drive class says the same way: who it is on its link, and its counters."""

    profile: Profile
    transport: Transport
    unit_id: int
    #: s: values only shown in messages (not used by the cycle) are read at most this
    #: often; the controller sets it from the status and cycle periods. A drive whose
    #: values all come each cycle anyway (PDOs) has nothing to spare and ignores it.
    display_period: float = 0.0

    @property
    def hardware_id(self) -> str:
        return f'{self.profile.name}@{self.transport.description}#{self.unit_id}'

    @property
    def link_parameters(self) -> tuple[str, ...]:
        """The drive parameters that set how this link reaches it (none known here)."""
        return ()

    @property
    def stats(self) -> TransportStats:
        return self.transport.stats_for(self.unit_id)


class ObjectDictionaryParameters:
    """The parameter verbs of a drive whose parameters are objects behind SDO.

    CANopen and EtherCAT (CoE) share validation, write and read-back; a bus says
    how a parameter is reached (``_reachable``: ParameterError if it is not),
    read and written (``_read_raw``, ``_write_raw``), and what a write means for
    persistence (``_write_note``).
    """

    profile: Profile

    def _reachable(self, parameter: Parameter) -> Parameter:
        raise NotImplementedError

    def _read_raw(self, parameter: Parameter) -> int:
        raise NotImplementedError

    def _write_raw(self, parameter: Parameter, raw: int, persistent: bool) -> None:
        raise NotImplementedError

    def _write_note(self, parameter: Parameter, persistent: bool) -> str:
        return 'SDO write; whether it survives power-off is up to the drive' \
            if persistent else ''

    def get_parameter(self, key: str) -> ParameterValue:
        parameter = self._reachable(self.profile.parameter(key))
        raw = self._read_raw(parameter)
        return ParameterValue(parameter, raw, parameter.from_raw(raw))

    def check_write(self, key: str, value: float, running: bool) -> tuple[Parameter, int]:
        """Validate a write without touching the drive; ParameterError says why not."""
        parameter = self._reachable(self.profile.parameter(key))
        return parameter, check_write(self.profile, parameter, value, running)

    def set_parameter(self, key: str, value: float, persistent: bool,
                      running: bool) -> tuple[ParameterValue, str]:
        """Validate (access, range, resolution, type), write over SDO, read back."""
        parameter, raw = self.check_write(key, value, running)
        self._write_raw(parameter, raw, persistent)
        readback = self._read_raw(parameter)
        if readback != raw:
            raise ParameterError(f'{parameter.code}: wrote {raw} but the drive holds {readback}')
        return (ParameterValue(parameter, readback, parameter.from_raw(readback)),
                self._write_note(parameter, persistent))


class Drive(Protocol):
    """What the controller needs from a drive, whatever the bus.

    ``ModbusDrive`` below implements it on a register transport; other buses
    (e.g. CANopen) implement the same verbs. Every method finishes within a few
    transport timeouts or raises a VfdError.
    """

    #: settings the node declares for this drive class as ``drive.<name>``
    settings: ClassVar[tuple[TransportParameter, ...]]
    profile: Profile
    transport: Transport
    last_setpoint_raw: int
    display_period: float      # see DriveOnLink
    link_parameters: tuple[str, ...]    # see DriveOnLink

    @classmethod
    def link_settings(cls, profile: Profile, settings: Mapping[str, Any]) -> dict[str, Any]:
        """Fill the drive's factory link values into ``transport.*`` settings left at 0/''."""

    @property
    def hardware_id(self) -> str: ...

    @property
    def stats(self) -> TransportStats:
        """This drive's own counters (a shared link also counts the others')."""

    def cycle_seconds(self) -> float:
        """Time one full command + status cycle of this drive occupies its link."""

    def connect_seconds(self) -> float:
        """Time this drive's connect sequence occupies its link (worst case)."""

    def action_seconds(self) -> float:
        """Time one service action may add to a cycle."""

    def host_loss_plan(self, requested: float, interval: float) -> HostLossProtection:
        """Plan the drive-side protection against host death (no I/O; ParameterError)."""

    def check_write(self, key: str, value: float, running: bool) -> tuple[Parameter, int]:
        """Validate a parameter write without touching the drive (ParameterError)."""

    def open(self) -> None: ...

    def close(self) -> None: ...

    def forget_state(self) -> None: ...

    def configure(self, protection: HostLossProtection,
                  apply_commissioning: bool) -> list[str]:
        """Connect-time writes; returns the problems that did not stop the connect.

        A drive may also set ``protection_applied`` (a HostLossProtection) to what
        it could set of ``protection``: the controller reports that one (optional;
        CanopenDrive does, when the drive aborts 0x1016 or 0x1400:05).
        """

    def setpoint_beyond(self, velocity: float) -> str:
        """Return why ``velocity`` (rad/s) would be clamped in the setpoint ('' if not)."""

    def apply(self, velocity: float, run: bool, idle_action: str = 'stop',
              reassert: bool = False) -> None: ...

    def send_command(self, action: str) -> None: ...

    def write_setpoint_parameter(self, code: str, raw: int) -> None:
        """Write an already validated auxiliary setpoint (volatile where possible)."""

    def poll(self, cycle: int, preempt: Callable[[], None] | None = None) -> Reading:
        """Read the status due this cycle; ``preempt()`` runs before each request."""

    def get_parameter(self, key: str) -> ParameterValue: ...

    def set_parameter(self, key: str, value: float, persistent: bool,
                      running: bool) -> tuple[ParameterValue, str]: ...


def check_write(profile: Profile, parameter: Parameter, value: float,
                running: bool) -> int:
    """Return the raw value of a parameter write every bus accepts; ParameterError why not.

    Control-owned registers, read-only parameters and stopped-only ones while
    running are refused before the value itself is judged (range, resolution,
    options, register capacity).
    """
    owner = profile.control_owned.get(parameter.code)
    if owner is not None:
        raise ParameterError(f'{parameter.code} ({parameter.description}) is not written '
                             f'through parameters: {owner}')
    if parameter.access is Access.READ_ONLY:
        raise ParameterError(f'{parameter.code} ({parameter.description}) is read-only')
    if parameter.access is Access.WRITE_WHEN_STOPPED and running:
        raise ParameterError(f'{parameter.code} can only be changed while the drive is stopped')
    return parameter.to_raw(value)
