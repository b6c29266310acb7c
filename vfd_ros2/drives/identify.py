"""Which drive family answers at a unit id: the profiles' ``identify`` data against a link.

No ROS, no threads. A scan (``vfd_ros2.apps.scan``) and a restore
(``vfd_ros2.apps.params``) ask the same question: given the answers a unit gives
to a few reads, which family is it, and how sure is that? Each family with an
``identify.modbus`` section names its reads and the answers that mark it
(an identification register's value, which registers answer, which exception
code the drive uses for an address it does not have); every family's checks
run against the same unit (reads are asked once and cached), and:

- one family whose checks all hold: that family, with its confidence (``high``
  for an identification value, ``medium`` for the shape of the answers), one
  level lower if the framing it answered at is not one its manual documents;
- several: ambiguous, the first named, confidence ``low``, the others listed;
- none: unknown, with what the unit answered.

The candidate framings of a serial line come from the same data: the factory
setting of every family first, then the options their manuals document.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import Callable, Iterable, Sequence

from ..errors import BadFrame, CommTimeout, ProtocolException
from ..profiles import IdentifyCheck, IdentifyExpect, Profile, load_profile
from ..transports.base import RegisterTransport


@functools.lru_cache(maxsize=None)
def profile_named(name: str) -> Profile:
    """Load a profile once per process (the tools look families up by name again and again)."""
    return load_profile(name)


#: confidence levels, weakest first
CONFIDENCE = ('none', 'low', 'medium', 'high')


def weaker(confidence: str) -> str:
    """Return the confidence one level below ``confidence`` (never below 'low')."""
    return CONFIDENCE[max(1, CONFIDENCE.index(confidence) - 1)]


@dataclass(frozen=True)
class Answer:
    """What a unit answered to one read: registers, an exception code, or nothing."""

    registers: tuple[int, ...] | None = None
    exception: int | None = None
    problem: str = ''          # 'no answer' or 'garbled reply' when neither came

    @property
    def heard(self) -> bool:
        """Return whether something was there (a reply or an exception, even a garbled one)."""
        return self.registers is not None or self.exception is not None or \
            self.problem == 'garbled reply'

    def describe(self) -> str:
        if self.registers is not None:
            return 'answers ' + ' '.join(f'0x{word:04X}' for word in self.registers)
        if self.exception is not None:
            return f'exception {self.exception}'
        return self.problem or 'no answer'


def read_answer(transport: RegisterTransport, unit: int, address: int, count: int) -> Answer:
    """Send one read (function 03) and return what came back; a lost port still raises."""
    try:
        return Answer(registers=tuple(transport.read_registers(unit, address, count)))
    except ProtocolException as exc:
        return Answer(exception=exc.code)
    except CommTimeout:
        return Answer(problem='no answer')
    except BadFrame:
        return Answer(problem='garbled reply')


Reader = Callable[[int, int], Answer]


@dataclass(frozen=True)
class Framing:
    """Serial settings: baud rate, parity, stop bits, data bits."""

    baudrate: int
    parity: str = 'N'
    stopbits: int = 1
    bytesize: int = 8

    @property
    def label(self) -> str:
        return f'{self.baudrate} {self.bytesize}{self.parity}{self.stopbits}'

    @property
    def key(self) -> tuple[int, str, int]:
        """Return what a receiver can tell apart: baud rate, parity, data bits (not stop bits).

        A frame sent with two stop bits is read by a receiver set for one (the
        second is idle line), and most UARTs (the 16550 and its descendants, USB
        adapters) check only the first stop bit of what they receive: the stop
        bits do not decide whether a drive understands the master. The scan
        therefore probes each key once, with 2 stop bits where any family uses 2.
        """
        return self.baudrate, self.parity, self.bytesize

    @classmethod
    def parse(cls, baudrate: int, text: str) -> 'Framing':
        """Build from a baud rate and a format such as '8N1'."""
        return cls(baudrate, text[1].upper(), int(text[2]), int(text[0]))


def documented_framings(profile: Profile) -> list[Framing]:
    """Return the framings a family's manual offers: the factory setting first, then options."""
    serial = profile.modbus.serial
    factory = Framing(serial.baudrate, serial.parity, serial.stopbits, serial.bytesize)
    found = [factory]
    identity = profile.identify.modbus if profile.identify else None
    if identity is not None:
        own = f'{serial.bytesize}{serial.parity}{serial.stopbits}'
        for baudrate in identity.baudrates or (serial.baudrate,):
            for text in identity.formats or (own,):
                framing = Framing.parse(baudrate, text)
                if framing not in found:
                    found.append(framing)
    return found


def candidate_framings(profiles: Iterable[Profile]) -> list[tuple[Framing, bool]]:
    """Return (framing, factory) to probe a serial line with, most likely first.

    One entry per baud rate, parity and data bits (``Framing.key``); the stop
    bits sent are 2 where a family documents 2 at that key, else 1 (2 are
    understood by every receiver, see ``Framing.key``). Factory settings come
    first (those shared by more families first), then the documented options
    (those more families offer first, no parity before even before odd, faster
    first); ``factory`` is True for the first group.
    """
    profiles = [p for p in profiles if 'modbus_rtu' in p.transports]
    factory_count: dict[tuple[int, str, int], int] = {}
    offered: dict[tuple[int, str, int], int] = {}
    stopbits: dict[tuple[int, str, int], int] = {}
    for profile in profiles:
        framings = documented_framings(profile)
        factory_key = framings[0].key
        factory_count[factory_key] = factory_count.get(factory_key, 0) + 1
        for framing in framings:
            offered[framing.key] = offered.get(framing.key, 0) + 1
            stopbits[framing.key] = max(stopbits.get(framing.key, 1), framing.stopbits)
    parity_rank = {'N': 0, 'E': 1, 'O': 2}

    def framing_of(key: tuple[int, str, int]) -> Framing:
        return Framing(key[0], key[1], stopbits[key], key[2])
    first = sorted(factory_count, key=lambda k: (-factory_count[k], -k[0]))
    rest = sorted((k for k in offered if k not in factory_count),
                  key=lambda k: (-offered[k], parity_rank.get(k[1], 3), -k[0]))
    return [(framing_of(k), True) for k in first] + [(framing_of(k), False) for k in rest]


def reported_framing(profile: Profile | None, probed: Framing) -> Framing:
    """Return the framing to configure for a drive found with ``probed``: its own stop bits.

    The family's factory stop bits where its factory setting has this baud
    rate and parity, else those of its first documented format with this
    parity; an unknown device keeps the probed ones.
    """
    if profile is None:
        return probed
    for framing in documented_framings(profile):
        if framing.key == probed.key:
            return framing
    return probed


@dataclass(frozen=True)
class CheckResult:
    check: IdentifyCheck
    passed: bool
    seen: str


@dataclass(frozen=True)
class Identification:
    """The family guessed for one unit, how sure, and why."""

    profile: str = ''                     # '' = unknown
    confidence: str = 'none'              # none | low | medium | high
    alternatives: tuple[str, ...] = ()    # other families that also match
    evidence: str = ''                    # the answers that decided it
    notes: tuple[str, ...] = ()

    @property
    def known(self) -> bool:
        return bool(self.profile)


def _evaluate(check: IdentifyCheck, answer: Answer) -> bool:
    if check.expect is IdentifyExpect.EXCEPTION:
        return answer.exception == check.exception
    if answer.registers is None or len(answer.registers) != check.count:
        return False
    if check.expect is IdentifyExpect.EQUALS:
        return answer.registers[0] in check.values
    return True


def identify(profiles: Sequence[Profile], read: Reader,
             framing: Framing | None = None) -> Identification:
    """Run every family's checks on one unit (``read(address, count)``) and judge.

    ``profiles`` are the families that may be on this link (those without an
    ``identify.modbus`` section are skipped); ``framing`` (serial lines) is the
    one the unit answered at: a family that does not document it is one
    confidence level less likely.
    """
    cache: dict[tuple[int, int], Answer] = {}

    def cached(address: int, count: int) -> Answer:
        if (address, count) not in cache:
            cache[(address, count)] = read(address, count)
        return cache[(address, count)]

    matches: list[tuple[Profile, list[CheckResult]]] = []
    for profile in profiles:
        identity = profile.identify.modbus if profile.identify else None
        if identity is None:
            continue
        results = []
        for check in identity.checks:
            answer = cached(check.address, check.count)
            results.append(CheckResult(check, _evaluate(check, answer),
                                       f'{check.where} {answer.describe()}'))
        matches.append((profile, results))
    full = [(p, r) for p, r in matches if all(result.passed for result in r)]
    if not full:
        seen = '; '.join(dict.fromkeys(r.seen for _, results in matches for r in results))
        return Identification(evidence=seen, notes=('no family matches all its checks',))

    def fits(profile: Profile) -> bool:
        return framing is None or 'modbus_rtu' not in profile.transports or \
            framing.key in {f.key for f in documented_framings(profile)}

    def level(profile: Profile) -> str:
        confidence = profile.identify.modbus.confidence
        return confidence if fits(profile) else weaker(confidence)
    ranked = sorted(full, key=lambda m: -CONFIDENCE.index(level(m[0])))
    profile, results = ranked[0]
    confidence = level(profile)
    top = [p.name for p, _ in ranked if level(p) == confidence]
    notes = []
    if not fits(profile):
        notes.append(f'{framing.label} is not a framing the {profile.name} manual offers')
    if len(top) > 1:
        notes.append(f'the answers fit {", ".join(top)} alike')
        confidence = 'low'
    evidence = '; '.join(r.seen for r in results)
    return Identification(profile=profile.name, confidence=confidence,
                          alternatives=tuple(p.name for p, _ in ranked[1:]),
                          evidence=evidence, notes=tuple(notes))
