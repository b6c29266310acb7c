"""A drive's parameters as a file: take a backup, compare two, restore one onto a drive.

No ROS, no argument parsing (``vfd_ros2.apps.params`` is the command line). The
drive is reached through a ``ParameterAccess``: directly on its link (a
``Drive`` from ``vfd_ros2.drives``) or through a running drive node's services;
everything here works the same for both.

A restore is planned before anything is written (``plan_restore``): only values
that differ from the drive's, in the order the manuals require:

1. the profile's ``commissioning`` selectors, in the profile's order (what makes
   the drive obey the bus, and what other parameters depend on);
2. parameters writable only while stopped (each written only after the drive
   reported, just before, that it is not running);
3. parameters writable at any time;
4. the RAM/EEPROM switch parameter (``modbus.persistence.parameter``), so that it
   ends as the file has it and does not change under the other writes;
5. the link parameters (``identify.link_parameters``: address, baud rate, framing,
   IP), only when asked: they change how the drive is reached, so they go last
   and cannot be read back.

Read-only and control-owned parameters are skipped with the reason, and so is
what the access refuses by policy (a node's commissioning values). Each write is
read back. A write the drive refuses, a read-back that differs or a lost link
halts the restore: what was written and what was not is reported, and the
drive is commanded to stop (``ParameterAccess.stop``).
"""

from __future__ import annotations

import datetime
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Mapping, Protocol

import yaml

from ..errors import (
    CommTimeout,
    ParameterError,
    ProfileError,
    ProtocolException,
    TransportError,
    VfdError,
)
from ..profiles import PROFILE_DIR, Access, Parameter, PersistenceKind, Profile
from .base import ParameterValue
from .identify import profile_named

#: the file format this module writes and reads
FORMAT = 'vfd_params/1'

#: consecutive unanswered reads after which a backup gives up (the drive is gone)
SILENCE_LIMIT = 3
#: the largest magnitude a backup file may give a value: beyond every register's range
#: (a value of 1e308 overflowed the raw conversion)
MAX_FILE_VALUE = 1e12


class ParameterAccess(Protocol):
    """What a backup and a restore need from a drive, directly or through a node."""

    profile: Profile
    description: str

    def read(self, code: str) -> ParameterValue:
        """Read one parameter; ProtocolException if the drive refuses, VfdError otherwise."""

    # Optional: ``read_many(codes) -> dict[code, ParameterValue]``, a best-effort bulk read
    # (e.g. Modbus block reads); whatever it does not return is read with ``read``.

    def write(self, code: str, value: float, persistent: bool) -> tuple[ParameterValue, str]:
        """Validate, write (EEPROM if ``persistent``), read back; returns (value, note)."""

    def refusal(self, code: str) -> str:
        """Return why this access will not write ``code`` ('' = it will)."""

    def running(self) -> bool | None:
        """Return whether the drive reports running (None: it cannot tell)."""

    def stop(self) -> str:
        """Command the drive to stop and say what was done (never raises)."""


def _clean(value: float) -> float | int:
    """Return a value for a file: no float noise (0.30000000000000004), ints as ints."""
    shown = float(f'{value:.10g}')
    return int(shown) if shown.is_integer() and abs(shown) < 1e15 else shown


@dataclass(frozen=True)
class Entry:
    """One parameter as a backup holds it."""

    code: str
    value: float                 # engineering units: what a restore writes
    raw: int                     # as read (a value edited by hand wins over it)
    name: str = ''
    unit: str = ''
    text: str = ''               # the option's meaning, for enumerations
    access: str = 'rw'

    def raw_of(self, parameter: Parameter) -> int:
        """Return the raw value ``value`` stands for on ``parameter`` (no range check)."""
        return round(self.value / parameter.scale)

    def shown(self) -> str:
        text = f'{_clean(self.value)}{self.unit}'
        return f'{text} ({self.text})' if self.text else text


@dataclass
class Backup:
    """A drive's parameters at one moment, with the family and firmware they came from."""

    profile: str
    model: str = ''
    identity: dict[str, float] = field(default_factory=dict)   # firmware code -> value
    source: str = ''
    taken: str = ''
    entries: dict[str, Entry] = field(default_factory=dict)    # code -> entry, table order
    unreadable: dict[str, str] = field(default_factory=dict)   # code -> why
    unknown: dict[str, str] = field(default_factory=dict)      # codes the profile lacks
    profile_file: str = ''       # the profile's file when it is not a shipped one

    @property
    def family(self) -> Profile:
        """Return the profile the values belong to (shipped by name, else by its file)."""
        return profile_named(self.profile_file or self.profile)

    def to_document(self) -> dict[str, Any]:
        return {
            'format': FORMAT,
            'profile': self.profile,
            **({'profile_file': self.profile_file} if self.profile_file else {}),
            'model': self.model,
            'identity': {code: _clean(value) for code, value in self.identity.items()},
            'source': self.source,
            'taken': self.taken,
            'parameters': [
                {'code': e.code, **({'name': e.name} if e.name else {}),
                 'value': _clean(e.value), 'raw': e.raw,
                 **({'unit': e.unit} if e.unit else {}), **({'text': e.text} if e.text else {}),
                 'access': e.access}
                for e in self.entries.values()],
            'unreadable': dict(self.unreadable),
        }

    def save(self, path: Path | str) -> None:
        header = (f'# vfd_params backup of {self.profile} ({self.model}) from {self.source}, '
                  f'{self.taken}\n# value: engineering units (what a restore writes); raw: '
                  'as read\n')
        Path(path).write_text(header + yaml.safe_dump(self.to_document(), sort_keys=False,
                                                      allow_unicode=True), encoding='utf-8')

    @classmethod
    def load(cls, path: Path | str) -> 'Backup':
        """Read a backup file; ParameterError names what is wrong with it."""
        try:
            data = yaml.safe_load(Path(path).read_text(encoding='utf-8'))
        except OSError as exc:
            raise ParameterError(f'cannot read {path}: {exc}') from exc
        except UnicodeDecodeError as exc:
            raise ParameterError(f'{path} is not UTF-8 text: {exc}') from exc
        except yaml.YAMLError as exc:
            raise ParameterError(f'{path} is not valid YAML: {exc}') from exc
        return cls.from_document(data, str(path))

    @classmethod
    def from_document(cls, data: Any, where: str = 'the file') -> 'Backup':
        if not isinstance(data, Mapping) or data.get('format') != FORMAT:
            raise ParameterError(f'{where} is not a vfd_params backup (format: {FORMAT})')
        try:
            profile = profile_named(str(data.get('profile_file') or data['profile']))
        except (KeyError, ProfileError) as exc:
            raise ParameterError(f'{where}: its drive profile cannot be loaded: {exc}') from exc
        identity, unreadable, parameters = (data.get(key) or default for key, default in (
            ('identity', {}), ('unreadable', {}), ('parameters', [])))
        if not isinstance(identity, Mapping) or not isinstance(unreadable, Mapping):
            raise ParameterError(f'{where}: identity and unreadable must be mappings '
                                 '(code: value)')
        if not isinstance(parameters, list):
            raise ParameterError(f'{where}: parameters must be a list')
        try:
            identity = {str(k): _number(v, f'identity {k}') for k, v in identity.items()}
        except ValueError as exc:
            raise ParameterError(f'{where}: {exc}') from exc
        backup = cls(profile=profile.name, profile_file=str(data.get('profile_file') or ''),
                     model=str(data.get('model', '')), identity=identity,
                     source=str(data.get('source', '')), taken=str(data.get('taken', '')),
                     unreadable={str(k): str(v) for k, v in unreadable.items()})
        seen: dict[str, int] = {}
        for number, item in enumerate(parameters):
            try:
                if not isinstance(item, Mapping):
                    raise ValueError('not a mapping')
                code, value = str(item['code']), _number(item['value'], 'value')
                raw = None if item.get('raw') is None else _integer(item['raw'], 'raw')
            except (KeyError, ValueError) as exc:
                raise ParameterError(f'{where}: parameters[{number}] needs a code and a '
                                     f'numeric value ({exc})') from exc
            try:
                parameter = profile.parameter(code)
            except ParameterError:
                backup.unknown[code] = f'not a parameter of {profile.name}'
                continue
            if parameter.code in seen:
                # Which one a hand edit meant cannot be told: neither is taken.
                raise ParameterError(
                    f'{where}: parameters[{number}] ({code}) and parameters['
                    f'{seen[parameter.code]}] are both {parameter.code}: keep one')
            seen[parameter.code] = number
            if raw is None:
                raw = round(value / parameter.scale)
            backup.entries[parameter.code] = Entry(
                parameter.code, value, raw, parameter.name, parameter.unit,
                str(item.get('text', '')), parameter.access.value)
        return backup


def _number(value: Any, what: str) -> float:
    """Return a finite number from a file (not a bool or a string); ValueError if not."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ValueError(f'{what} {value!r} is not a number')
    if not math.isfinite(value) or abs(value) > MAX_FILE_VALUE:
        raise ValueError(f'{what} {value!r} is not a finite number a drive can hold')
    return float(value)


def _integer(value: Any, what: str) -> int:
    if isinstance(value, bool) or not isinstance(value, int):
        raise ValueError(f'{what} {value!r} is not an integer')
    return value


def _entry(value: ParameterValue) -> Entry:
    p = value.parameter
    return Entry(p.code, value.value, value.raw, p.name, p.unit, value.text, p.access.value)


def take_backup(access: ParameterAccess, codes: list[str] | None = None,
                progress: Callable[[str], None] = lambda _text: None) -> Backup:
    """Read every readable parameter of the profile (or ``codes``) into a Backup.

    A parameter the drive refuses, or that this link cannot reach, is listed in
    ``unreadable`` with the reason; a drive that stops answering (SILENCE_LIMIT
    reads in a row) raises CommTimeout.
    """
    profile = access.profile
    shipped = Path(profile.source_file).resolve().parent == PROFILE_DIR
    backup = Backup(profile=profile.name, model=profile.model, source=access.description,
                    profile_file='' if shipped or not profile.source_file else
                    str(Path(profile.source_file).resolve()),
                    taken=datetime.datetime.now(datetime.timezone.utc).isoformat(
                        timespec='seconds'))
    wanted = codes if codes is not None else list(profile.parameters)
    bulk = getattr(access, 'read_many', None)
    known = bulk(wanted) if bulk is not None else {}
    silent = 0
    for number, code in enumerate(wanted):
        try:
            value = known.get(code) or access.read(code)
        except (ProtocolException, ParameterError) as exc:
            backup.unreadable[code] = str(exc)
            silent = 0
            continue
        except CommTimeout as exc:
            silent += 1
            backup.unreadable[code] = str(exc)
            if silent >= SILENCE_LIMIT:
                raise CommTimeout(f'{access.description}: no answer to {silent} reads in a '
                                  f'row (last: {code}): {exc}') from exc
            continue
        silent = 0
        backup.entries[value.parameter.code] = _entry(value)
        if (number + 1) % 100 == 0:
            progress(f'{number + 1} of {len(wanted)} parameters read')
    firmware = profile.identify.firmware if profile.identify else ()
    backup.identity = {code: backup.entries[code].value for code in firmware
                       if code in backup.entries}
    return backup


# --- comparing ---------------------------------------------------------------------------------

def is_setting(profile: Profile, code: str) -> bool:
    """Return whether a restore could write ``code`` (writable and not the control loop's)."""
    parameter = profile.parameter(code)
    return parameter.access is not Access.READ_ONLY and code not in profile.control_owned


@dataclass(frozen=True)
class Difference:
    code: str
    name: str
    left: str          # engineering units with the option's text, or why there is no value
    right: str


def compare(left: Backup, right: Backup, settings_only: bool = True) -> list[Difference]:
    """Return what differs between two backups of the same family (table order).

    ``settings_only``: only what a restore could write, i.e. not read-only values
    (measurements, status, identity) and not the registers the control loop
    owns (command word, setpoints), which differ from moment to moment.
    """
    if left.profile != right.profile:
        raise ParameterError(f'the two sides are different families ({left.profile} and '
                             f'{right.profile}): their parameters do not correspond')
    profile = left.family
    differences = []
    for code, parameter in profile.parameters.items():
        if settings_only and not is_setting(profile, code):
            continue
        a, b = left.entries.get(code), right.entries.get(code)
        if a is None and b is None:
            continue
        if a is not None and b is not None and a.raw_of(parameter) == b.raw_of(parameter):
            continue
        differences.append(Difference(
            code, parameter.name,
            a.shown() if a else f'(not read: {left.unreadable.get(code, "absent")})',
            b.shown() if b else f'(not read: {right.unreadable.get(code, "absent")})'))
    return differences


def firmware_differences(file: Backup, live: Mapping[str, float]) -> list[str]:
    """Return 'code: file X, drive Y' for each firmware value that differs."""
    return [f'{code}: {file.identity[code]:g} in the file, {live[code]:g} on the drive'
            for code in file.identity if code in live and
            not math.isclose(file.identity[code], live[code], abs_tol=1e-9)]


# --- restoring ---------------------------------------------------------------------------------

#: the groups of a restore, in the order they are written
GROUPS = ('commissioning', 'stopped_only', 'run_time', 'persistence', 'link')


@dataclass(frozen=True)
class Step:
    """One write of a restore."""

    code: str
    name: str
    value: float               # engineering units, from the file
    current: str               # the drive's value before, as shown
    group: str
    stopped_only: bool

    def shown(self, profile: Profile) -> str:
        parameter = profile.parameter(self.code)
        raw = round(self.value / parameter.scale)
        text = parameter.option_text(raw)
        target = f'{_clean(self.value)}{parameter.unit}' + (f' ({text})' if text else '')
        label = f'{self.code} {self.name}'.strip()
        return f'{label}: {self.current} -> {target}'


@dataclass(frozen=True)
class Skip:
    code: str
    why: str


@dataclass
class RestorePlan:
    profile: Profile
    steps: list[Step] = field(default_factory=list)
    skipped: list[Skip] = field(default_factory=list)
    unchanged: int = 0
    read_only: int = 0           # values in the file for reference (measurements, identity)
    warnings: list[str] = field(default_factory=list)
    # Values of the file that no write could take (out of range, off the resolution,
    # not an option): a file with any of them is refused whole (a hand edit gone wrong).
    invalid: list[Skip] = field(default_factory=list)
    # The RAM/EEPROM switch parameter and the file's value: a write of the other
    # kind flips it on the way (drives with a switch_parameter), so it is set
    # back to the file's value after the last write.
    switch: tuple[str, float] | None = None


def plan_restore(backup: Backup, live: Backup, access: ParameterAccess,
                 include_link: bool = False) -> RestorePlan:
    """Decide what a restore of ``backup`` writes onto the drive ``live`` was read from."""
    profile = access.profile
    plan = RestorePlan(profile)
    commissioning = [item.code for item in profile.commissioning]
    identify = profile.identify
    link = set(identify.link_parameters) if identify else set()
    persistence = profile.modbus.persistence
    switch = persistence.parameter if persistence.kind is PersistenceKind.SWITCH_PARAMETER \
        else ''
    for code, why in backup.unknown.items():
        plan.skipped.append(Skip(code, why))
    steps: list[Step] = []
    for code, entry in backup.entries.items():
        parameter = profile.parameter(code)
        if parameter.access is Access.READ_ONLY:
            plan.read_only += 1                          # recorded for reference only
            continue
        owner = profile.control_owned.get(code)
        if owner is not None:
            plan.skipped.append(Skip(code, f'control-owned: {owner}'))
            continue
        if code in link and not include_link:
            if code in live.entries and live.entries[code].raw_of(parameter) != \
                    entry.raw_of(parameter):
                plan.skipped.append(Skip(code, f'link setting ({entry.shown()} in the file, '
                                               f'{live.entries[code].shown()} on the drive): '
                                               'it changes how the drive is reached; '
                                               'written last only when asked'))
            continue
        current = live.entries.get(code)
        if current is None:
            plan.skipped.append(Skip(code, 'cannot be read on the drive: '
                                     f'{live.unreadable.get(code, "not read")}'))
            continue
        if current.raw_of(parameter) == entry.raw_of(parameter):
            plan.unchanged += 1
            continue
        try:
            parameter.to_raw(entry.value)
        except ParameterError as exc:
            plan.invalid.append(Skip(code, str(exc)))
            continue
        refusal = access.refusal(code)
        if refusal:
            plan.skipped.append(Skip(code, refusal))
            continue
        group = ('link' if code in link else 'persistence' if code == switch
                 else 'commissioning' if code in commissioning
                 else 'stopped_only' if parameter.access is Access.WRITE_WHEN_STOPPED
                 else 'run_time')
        steps.append(Step(code, parameter.name, entry.value, current.shown(), group,
                          parameter.access is Access.WRITE_WHEN_STOPPED))
        if group == 'commissioning':
            needed = next(item for item in profile.commissioning if item.code == code)
            if not math.isclose(entry.value, needed.value):
                plan.warnings.append(
                    f'{code} = {_clean(entry.value)} in the file, but '
                    f'{"bus control" if needed.bus_control else "the driver"} needs '
                    f'{_clean(needed.value)} ({needed.why}); a driver with '
                    'apply_commissioning writes it back at connect')
    if switch and switch in backup.entries and switch not in profile.control_owned and \
            not access.refusal(switch):
        plan.switch = (switch, backup.entries[switch].value)
    order = {code: number for number, code in enumerate(commissioning)}
    plan.steps = sorted(steps, key=lambda s: (GROUPS.index(s.group), order.get(s.code, 0)))
    return plan


@dataclass
class RestoreResult:
    written: list[tuple[Step, ParameterValue | None, str]] = field(default_factory=list)
    failed: tuple[Step, str] | None = None
    not_written: list[Step] = field(default_factory=list)
    stop: str = ''               # what was done to leave the drive stopped, after a halt
    warnings: list[str] = field(default_factory=list)

    @property
    def complete(self) -> bool:
        return self.failed is None and not self.not_written


def execute(plan: RestorePlan, access: ParameterAccess, persistent: bool,
            progress: Callable[[str], None] = lambda _text: None) -> RestoreResult:
    """Write the plan's steps in order, each read back; halt at the first problem.

    Before each stopped-only write the drive must report not running. On a halt
    the remaining steps are listed as not written and the drive is commanded to
    stop. A link parameter that goes unanswered is taken as sent (the drive may
    answer at its new address or baud rate by then): the remaining link
    parameters are not sent, and no stop is attempted on a link that moved.
    """
    result = RestoreResult()
    switched_back = False
    for number, step in enumerate(plan.steps):
        problem = ''
        try:
            if step.group == 'link' and not switched_back:
                # Before the link moves: afterwards the switch is out of reach.
                switched_back = True
                if plan.switch is not None:
                    _switch_back(plan, access, persistent, result, progress)
            if step.stopped_only:
                running = access.running()
                if running is None or running:
                    problem = ('the drive reports running' if running else
                               "the drive's run state cannot be read") + \
                        f': {step.code} may be written only while it is stopped'
            if not problem:
                value, note = access.write(step.code, step.value, persistent)
                result.written.append((step, value, note))
                progress(f'wrote {step.shown(plan.profile)}' + (f' ({note})' if note else ''))
        except ProtocolException as exc:
            problem = f'the drive refused {step.code}: {exc}'
        except ParameterError as exc:
            problem = f'{step.code} not written: {exc}'
        except TransportError as exc:
            if step.group == 'link':
                result.written.append((step, None, f'sent, not confirmed ({exc}): the drive may '
                                                   'answer at the new setting now'))
                result.not_written = plan.steps[number + 1:]
                result.stop = 'no stop command: the link settings changed'
                break
            problem = f'{step.code}: the link failed: {exc}'
        except VfdError as exc:
            problem = f'{step.code}: {exc}'
        except KeyboardInterrupt:
            # Ctrl-C: halt as on a refusal (switch set back, drive stopped, the lists
            # of what was and was not written), not a traceback and a half-told state.
            problem = f'interrupted (Ctrl-C) at {step.code}: it may or may not be written'
        if problem:
            result.failed = (step, problem)
            result.not_written = plan.steps[number + 1:]
            if plan.switch is not None:
                try:        # the writes so far, or the one that failed, may have flipped it
                    _switch_back(plan, access, persistent, result, progress)
                except VfdError as exc:
                    problem += f'; {plan.switch[0]} (RAM/EEPROM switch) not set back: {exc}'
                    result.failed = (step, problem)
            result.stop = access.stop()
            return result
    if switched_back and plan.switch is not None and any(
            step.group == 'link' for step, _, _ in result.written):
        # Set back before the link settings; a write of the other kind flips it again
        # on the way, and the drive answers at its new setting now, out of reach here.
        code = plan.switch[0]
        result.warnings.append(
            f"{code} (RAM/EEPROM switch) may be flipped again by the link settings' "
            f"writes: check it at the drive's new address or baud rate")
    if plan.switch is not None and result.written and not result.not_written and \
            not switched_back:
        try:
            _switch_back(plan, access, persistent, result, progress)
        except VfdError as exc:
            code, value = plan.switch
            parameter = plan.profile.parameter(code)
            result.failed = (Step(code, parameter.name, value, '?', 'persistence', False),
                             f'{code} (RAM/EEPROM switch) not set back: {exc}')
            result.stop = access.stop()
    return result


def _switch_back(plan: RestorePlan, access: ParameterAccess, persistent: bool,
                 result: RestoreResult, progress: Callable[[str], None]) -> None:
    """Set the RAM/EEPROM switch back to the file's value if the writes flipped it."""
    code, value = plan.switch
    parameter = plan.profile.parameter(code)
    current = access.read(code)
    if current.raw == round(value / parameter.scale):
        return
    step = Step(code, parameter.name, value, f'{_clean(current.value)}{parameter.unit}',
                'persistence', False)
    written, note = access.write(code, value, persistent)
    result.written.append((step, written, note or 'set back as in the file'))
    progress(f'wrote {step.shown(plan.profile)} (the RAM/EEPROM switch, as in the file)')
