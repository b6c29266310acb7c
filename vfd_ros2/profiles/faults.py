"""Fault codes -> the manual's words."""

from __future__ import annotations

from dataclasses import dataclass

from .model import FaultSpec


@dataclass(frozen=True)
class FaultInfo:
    """One fault as the driver reports it (code 0 = no fault)."""

    code: int
    subcode: int
    display: str
    name: str
    cause: str
    remedy: str
    known: bool

    @property
    def active(self) -> bool:
        return self.code != 0


NO_FAULT = FaultInfo(0, 0, '', '', '', '', True)


def describe_fault(spec: FaultSpec, code: int, subcode: int = 0) -> FaultInfo:
    """Return the manual's name, cause and remedy for a fault code; never raises."""
    if code == 0:
        return NO_FAULT
    try:
        display = spec.display_format.format(code=code, subcode=subcode)
    except Exception:  # noqa: BLE001 - a bad format string in a profile must not crash polling
        display = f'{code}.{subcode}'
    entry = spec.table.get(code)
    if entry is None:
        # (named as displayed: a CiA code 0x7310 read 'unknown fault 29456' beside it)
        return FaultInfo(code, subcode, display, f'unknown fault {display}',
                         f"fault code {code} (sub-code {subcode}) is not in the profile's "
                         'fault table', 'see the drive manual', known=False)
    detail = entry.subcodes.get(subcode, '')
    cause = entry.cause
    if detail:
        cause = f'{detail}. {cause}' if cause else detail
    elif subcode and entry.subcodes:
        cause = f"sub-code {subcode} (not in the manual's list). {cause}".strip()
    return FaultInfo(code, subcode, display, entry.name, cause, entry.remedy, known=True)
