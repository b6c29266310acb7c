"""DriveState -> ROS messages (pure functions, no node needed)."""

from __future__ import annotations

import math
from typing import Callable, Iterable

from builtin_interfaces.msg import Time
from diagnostic_msgs.msg import DiagnosticStatus, KeyValue
from sensor_msgs.msg import JointState

from vfd_ros2.msg import DriveFault, DriveStatus

from ..control.state import STATUS_NOT_READ, DriveState, RunState
from ..profiles import FaultInfo


def joint_state_message(joints: list[tuple[str, DriveState]], stamp: Time) -> JointState:
    """One JointState for wheels (name, state): rad, rad/s and N·m at the output shaft.

    ``effort`` is filled only when every wheel measures one (JointState allows an
    empty array, not a partial one); NaN marks a value not known (offline, or no
    position yet).
    """
    msg = JointState()
    msg.header.stamp = stamp
    msg.name = [name for name, _ in joints]
    update_joint_state(msg, [state for _, state in joints])
    return msg


def update_joint_state(msg: JointState, states: list[DriveState]) -> None:
    """Set ``msg``'s values from its joints' ``states`` (in the order of ``msg.name``)."""
    msg.position = [float(state.position) for state in states]
    msg.velocity = [float(state.measured_velocity) if state.online else math.nan
                    for state in states]
    efforts = [float(state.effort) for state in states]
    msg.effort = efforts if efforts and not any(math.isnan(value) for value in efforts) else []


def default_joint_name(namespace: str, node_name: str) -> str:
    """Return the namespace's last part (/agv/left_wheel -> left_wheel), else the node name."""
    parts = [part for part in namespace.split('/') if part]
    return parts[-1] if parts else node_name


def status_message(state: DriveState, stamp: Time, frame_id: str, profile: str) -> DriveStatus:
    """Return a new ``DriveStatus`` showing ``state``."""
    message = StatusMessage(frame_id, profile)
    return message.update(state, stamp)


class StatusMessage:
    """One drive's ``DriveStatus``, kept and brought up to date field by field.

    Building one from scratch sets each of its 41 fields twice (the constructor's
    defaults, then the values): ~200 us of CPU as the first thing after a 50 ms
    sleep, as a status timer runs it, against ~75 us to set the few that change
    from one poll to the next (the speed, the counters).
    ``update`` sets the fields that depend on the fields of ``DriveState`` that
    differ from the state it showed last (``_SHOWN_FROM`` maps one to the other).
    """

    def __init__(self, frame_id: str, profile: str) -> None:
        self.message = DriveStatus()
        self.message.header.frame_id = frame_id
        self.message.profile = profile
        self._shown: DriveState | None = None

    def update(self, state: DriveState, stamp: Time | None = None) -> DriveStatus:
        """Show ``state`` (and ``stamp``, when given) in the message and return it."""
        msg = self.message
        if stamp is not None:
            msg.header.stamp = stamp
        shown = self._shown
        if shown is None:
            changed: Iterable[str] = _SHOWN_FROM
        else:
            # (``is`` first: most fields are the very objects of the last snapshot; the
            # containers a poll builds anew, the measured values say, compare by value)
            changed = [name for name, new, old in zip(DriveState._fields, state, shown)
                       if new is not old and new != old and name in _SHOWN_FROM]
        for name in changed:
            _SHOWN_FROM[name](msg, state)
        self._shown = state
        return msg


def _copy(name: str) -> Callable[[DriveStatus, DriveState], None]:
    def fill(msg: DriveStatus, state: DriveState) -> None:
        setattr(msg, name, getattr(state, name))
    return fill


def _counter(name: str) -> Callable[[DriveStatus, DriveState], None]:
    def fill(msg: DriveStatus, state: DriveState) -> None:
        setattr(msg, name, min(getattr(state, name), 0xFFFFFFFF))   # (a uint32 field)
    return fill


def _fill_run_state(msg: DriveStatus, state: DriveState) -> None:
    msg.run_state = int(state.run_state)
    msg.state = state.state


def _fill_status_words(msg: DriveStatus, state: DriveState) -> None:
    msg.status_word_names = [name for name, _ in state.status_words]
    msg.status_words_raw = [value & 0xFFFF for _, value in state.status_words]


def _fill_measured(msg: DriveStatus, state: DriveState) -> None:
    measured = state.measured
    msg.output_frequency = float(measured.get('output_frequency', math.nan))
    msg.output_current = float(measured.get('output_current', math.nan))
    msg.dc_bus_voltage = float(measured.get('dc_bus_voltage', math.nan))
    msg.temperature = float(measured.get('temperature', math.nan))


def _fill_fault(msg: DriveStatus, state: DriveState) -> None:
    msg.fault_code = state.active_fault.code & 0xFFFF
    msg.fault_subcode = state.active_fault.subcode & 0xFFFF


def _fill_protection(msg: DriveStatus, state: DriveState) -> None:
    protection = state.protection
    msg.host_loss_timeout = float(protection.timeout) if protection.active else 0.0
    msg.host_loss_protection = protection.describe()


def _fill_commanded(msg: DriveStatus, state: DriveState) -> None:
    msg.commanded_velocity = float(state.commanded_velocity)


def _fill_measured_velocity(msg: DriveStatus, state: DriveState) -> None:
    msg.measured_velocity = float(state.measured_velocity)


def _fill_setpoint(msg: DriveStatus, state: DriveState) -> None:
    msg.setpoint_raw = int(state.setpoint_raw)


def _fill_warning_code(msg: DriveStatus, state: DriveState) -> None:
    msg.warning_code = state.warning_code & 0xFFFF


def _fill_warning_subcode(msg: DriveStatus, state: DriveState) -> None:
    msg.warning_subcode = state.warning_subcode & 0xFFFF


def _fill_unavailable(msg: DriveStatus, state: DriveState) -> None:
    msg.unavailable = list(state.unavailable)


#: DriveState field -> what sets the DriveStatus fields shown from it (the fields
#: of DriveState not named here are not in DriveStatus: position, link_error, ...)
_SHOWN_FROM: dict[str, Callable[[DriveStatus, DriveState], None]] = {
    **{name: _copy(name) for name in (
        'hardware_id', 'online', 'ready', 'enabled', 'running', 'reverse', 'fault',
        'warning', 'at_speed', 'watchdog_tripped', 'stop_reason')},
    'run_state': _fill_run_state,
    'status_words': _fill_status_words,
    'commanded_velocity': _fill_commanded,
    'measured_velocity': _fill_measured_velocity,
    'setpoint_raw': _fill_setpoint,
    'measured': _fill_measured,
    'active_fault': _fill_fault,
    'warning_code': _fill_warning_code,
    'warning_subcode': _fill_warning_subcode,
    'protection': _fill_protection,
    'unavailable': _fill_unavailable,
    **{name: _counter(name) for name in (
        'transactions', 'comm_errors', 'timeouts', 'bad_frames', 'exceptions',
        'reconnects', 'late_replies', 'rejected_commands', 'clamped_commands',
        'unexpected_starts')},
}


def fault_message(fault: FaultInfo, active: bool, stamp: Time, hardware_id: str) -> DriveFault:
    msg = DriveFault()
    msg.stamp = stamp
    msg.hardware_id = hardware_id
    msg.active = active
    msg.code = fault.code & 0xFFFF
    msg.subcode = fault.subcode & 0xFFFF
    msg.display = fault.display
    msg.name = fault.name
    msg.cause = fault.cause
    msg.remedy = fault.remedy
    msg.known = fault.known
    return msg


def add_loop_rate(status: DiagnosticStatus, cycles_per_second: float, short: bool,
                  control_rate: float, drives: int = 1) -> None:
    """Show a control loop's achieved rate; WARN while it runs short of ``control_rate``.

    Every status read, watchdog stop and host-loss margin comes later than the rate
    implies: the link (or the host) does not sustain it.
    """
    status.values.append(KeyValue(key='cycles/s', value=f'{cycles_per_second:.1f}'))
    if not short or status.level not in (DiagnosticStatus.OK, DiagnosticStatus.WARN):
        return
    remedy = 'fewer drives on the link, ' if drives > 1 else ''
    text = (f'the control loop runs {cycles_per_second:.1f} cycles/s of control_rate '
            f'{control_rate:g} Hz: the link or the host does not sustain it (lower '
            f'control_rate, or {remedy}a faster link or a less loaded host)')
    status.message = text if status.level == DiagnosticStatus.OK else \
        f'{status.message}; {text}'
    status.level = DiagnosticStatus.WARN


def drive_diagnostic_name(node_fqn: str) -> str:
    """`<namespace>/<node>: drive`, grouped by config/diagnostics_aggregator.yaml."""
    return f'{node_fqn.lstrip("/")}: drive'


def bus_diagnostic_name(node_fqn: str, bus: str) -> str:
    """`<namespace>/<node>: bus <name>`, grouped by config/diagnostics_aggregator.yaml."""
    return f'{node_fqn.lstrip("/")}: bus {bus}'


def _warnings(state: DriveState) -> list[str]:
    """List what an integrator must know although the drive runs (diagnostics WARN)."""
    warnings = []
    if state.warning:
        warnings.append(f'warning {state.warning_code}.{state.warning_subcode}')
    if state.run_state is RunState.BLOCKED and state.stop_reason != STATUS_NOT_READ:
        # commanded to run, it does not (a CiA 402 drive stuck, a lost run command);
        # not the one cycle after a connect before the first status read
        warnings.append(f'blocked: {state.stop_reason}')
    if state.loop_errors:
        warnings.append(f'{state.loop_errors} internal errors in the drive loop (a bug)')
    protection = state.protection
    if not protection.active:
        warnings.append(f'no drive-side host-loss protection: {protection.note}')
    elif protection.weaker_than_requested:
        warnings.append(f'host-loss protection weaker than requested: {protection.describe()}')
    if state.not_following:
        warnings.append(state.not_following)
    if state.unavailable:
        warnings.append(f'the drive refuses: {"; ".join(state.unavailable)}')
    warnings.extend(state.link_notes)
    if state.command_gap:
        warnings.append(state.command_gap)
    return warnings


def diagnostic_status(state: DriveState, name: str, ever_online: bool) -> DiagnosticStatus:
    """One /diagnostics entry for the drive (aggregator-friendly name and keys)."""
    status = DiagnosticStatus()
    status.name = name
    status.hardware_id = state.hardware_id
    if not state.online:
        # A link the host closed on purpose (a managed node unconfigured) has no data
        # to report; one that failed, before or after it was ever up, is a comm loss.
        status.level = DiagnosticStatus.STALE if state.link_closed or not (
            ever_online or state.link_error) else DiagnosticStatus.ERROR
        status.message = f'offline: {state.link_closed or state.link_error or "no reply yet"}'
    elif state.fault:
        fault = state.active_fault
        status.level = DiagnosticStatus.ERROR
        status.message = f'fault {fault.display} {fault.name}'
    elif state.not_stopping:
        status.level = DiagnosticStatus.ERROR
        status.message = f'{state.state}: {state.not_stopping}'
    elif warnings := _warnings(state):
        status.level = DiagnosticStatus.WARN
        status.message = '; '.join(warnings)
    else:
        status.level = DiagnosticStatus.OK
        reason = state.stop_reason
        status.message = reason if reason.startswith(state.state) else \
            f'{state.state}: {reason}' if reason else state.state
    fault = state.active_fault
    pairs = [
        ('state', state.state),
        ('stop reason', state.stop_reason),
        ('online', state.online),
        ('enabled', state.enabled),
        ('running', state.running),
        ('commanded velocity (rad/s)', f'{state.commanded_velocity:.4f}'),
        ('measured velocity (rad/s)', f'{state.measured_velocity:.4f}'),
        ('position (rad)', f'{state.position:.4f}'),
        ('position source', "the drive's counter" if state.position_source == 'drive'
         else 'measured speed integrated'),
        ('output frequency (Hz)', state.measured.get('output_frequency', math.nan)),
        ('output current (A)', state.measured.get('output_current', math.nan)),
        ('DC bus voltage (V)', state.measured.get('dc_bus_voltage', math.nan)),
        ('temperature (degC)', state.measured.get('temperature', math.nan)),
        ('fault', f'{fault.display} {fault.name}'.strip() if fault.active else 'none'),
        ('fault remedy', fault.remedy if fault.active else ''),
        ('warning code', state.warning_code),
        ('transactions', state.transactions),
        ('comm errors', state.comm_errors),
        ('timeouts', state.timeouts),
        ('bad frames', state.bad_frames),
        ('exceptions', state.exceptions),
        ('reconnects', state.reconnects),
        ('late replies', state.late_replies),
        ('rejected commands', state.rejected_commands),
        ('clamped commands', state.clamped_commands),
        ('commands after a watchdog stop', state.command_gaps),
        ('unexpected starts', state.unexpected_starts),
        ('comm-loss faults reset at connect', state.comm_faults_cleared),
        ('loop errors', state.loop_errors),
        ('host-loss protection', state.protection.describe()),
        ('drive_comm_timeout requested (s)', f'{state.protection.requested:g}'),
        ('unavailable', '; '.join(state.unavailable)),
        ('link error', state.link_error),
    ]
    status.values = [KeyValue(key=key, value=str(value)) for key, value in pairs]
    return status
