"""vfd_scan: what is on this line? Find drives on RS-485, Modbus TCP and CAN, read-only.

    vfd_scan --port /dev/ttyUSB0                    # every framing the profiles document
    vfd_scan --port /dev/ttyUSB0 --ids 1-16 --yaml bus.yaml
    vfd_scan --tcp 192.168.0.10-20:502              # hosts / ports on a link you name
    vfd_scan --can socketcan:can0 --sdo-probe       # heartbeats, boot-ups, then 0x1000/0x1018

Modbus RTU: the candidate framings come from the profiles (each family's factory
setting first, then the options its manual documents; ``drives.identify``); at
each framing every unit id gets ONE cheap read (a family's ``identify.modbus.probe``)
with a timeout from the baud rate; a unit that answers (even with an exception)
gets its families' identification reads. A factory framing is swept over every
id; any other framing stops after ``--silent-ids`` ids in a row with nothing at all
on the line. A unit id found at a baud rate is not asked again at another parity
of that rate. The whole scan stops at ``--max-time`` / ``--max-requests`` and says
what it did not reach. It only ever reads (function 03): nothing is written.

Output: a table (link, framing, unit id, profile guessed, confidence, identity:
the family's firmware registers), and with ``--yaml`` a ``bus_node`` configuration
(one file per link; on a line with drives at several framings the framing with
the most drives is the bus, the others are listed in comments). Progress goes to
stderr. No ROS is needed.
"""

from __future__ import annotations

import argparse
import ipaddress
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Sequence, TextIO

import yaml

from ..control.bus import parse_bus_config
from ..drives.identify import (
    Answer,
    Framing,
    Identification,
    candidate_framings,
    documented_framings,
    identify,
    profile_named,
    read_answer,
    reported_framing,
)
from ..errors import TransportError, VfdError
from ..profiles import Profile, available_profiles
from ..protocol.registers import decode_words
from ..protocol.rtu_timing import character_time, frame_gap
from ..transports.base import RegisterTransport
from ..transports.modbus import ModbusRtuTransport, ModbusTcpTransport

#: exit codes: found something / found nothing / could not scan (bad input, port)
FOUND, NOTHING, FAILED = 0, 1, 2
#: the note of an id whose only answer was a frame that did not decode
GARBLED = 'garbled reply: line noise, or a device at a near framing'


class ScanError(VfdError):
    """The scan cannot run as asked (unknown port, bad range)."""


def parse_ids(text: str, lowest: int = 1, highest: int = 247) -> list[int]:
    """Parse '1-16,20,32-40' into ids within [lowest, highest]; ScanError if malformed."""
    ids: list[int] = []
    try:
        for part in text.split(','):
            first, _, last = part.strip().partition('-')
            low, high = int(first), int(last or first)
            if not lowest <= low <= high <= highest:
                raise ValueError(part)
            ids.extend(i for i in range(low, high + 1) if i not in ids)
    except ValueError as exc:
        raise ScanError(f'bad id range {text!r}: use e.g. 1-16,20 within '
                        f'{lowest}..{highest}') from exc
    return ids


@dataclass(frozen=True)
class TcpTarget:
    host: str
    port: int


def parse_tcp(text: str) -> list[TcpTarget]:
    """Parse 'HOST[-LAST][:PORT[-PORT]]': 192.168.0.10-20:502 = .10 to .20, port 502."""
    host, _, ports = text.partition(':')
    try:
        first_port, _, last_port = (ports or '502').partition('-')
        port_range = range(int(first_port), int(last_port or first_port) + 1)
        if not port_range or not 0 < port_range[0] <= port_range[-1] < 65536:
            raise ValueError(ports)
        first, dash, last = host.partition('-')
        if dash:
            start = ipaddress.IPv4Address(first)
            end = ipaddress.IPv4Address(last) if '.' in last else \
                ipaddress.IPv4Address('.'.join(first.split('.')[:3] + [last]))
            hosts = [str(ipaddress.IPv4Address(a)) for a in range(int(start), int(end) + 1)]
            if not hosts:
                raise ValueError(host)
        else:
            hosts = [first]
    except ValueError as exc:
        raise ScanError(f'bad TCP target {text!r}: use HOST[-LAST][:PORT[-PORT]], e.g. '
                        '192.168.0.10-20:502') from exc
    if len(hosts) * len(port_range) > 4096:
        raise ScanError(f'{text!r} names {len(hosts) * len(port_range)} endpoints: at most '
                        '4096 per scan')
    return [TcpTarget(h, p) for h in hosts for p in port_range]


@dataclass
class Budget:
    """Time and traffic the whole scan may take; ``exhausted`` says which ran out."""

    max_seconds: float
    max_requests: int
    clock: Callable[[], float] = time.monotonic
    started: float = field(default=0.0)
    requests: int = 0

    def __post_init__(self) -> None:
        self.started = self.clock()

    @property
    def elapsed(self) -> float:
        return self.clock() - self.started

    @property
    def exhausted(self) -> str:
        if self.requests >= self.max_requests:
            return f'request budget ({self.max_requests}) used up'
        if self.elapsed >= self.max_seconds:
            return f'time budget ({self.max_seconds:g} s) used up'
        return ''


class Progress:
    """Progress lines on stderr (or nowhere)."""

    def __init__(self, stream: TextIO | None) -> None:
        self.stream = stream

    def __call__(self, text: str) -> None:
        if self.stream is not None:
            print(f'[vfd_scan] {text}', file=self.stream, flush=True)


@dataclass(frozen=True)
class Found:
    """One device that answered."""

    kind: str                      # modbus_rtu | modbus_tcp | canopen
    link: str                      # serial port, host:port, interface:channel
    unit: int
    identification: Identification
    framing: Framing | None = None
    host: str = ''
    port: int = 0
    identity: str = ''             # firmware values, 0x1000 / 0x1018
    notes: tuple[str, ...] = ()
    # transport settings the link was opened with, for the bus file (e.g. CAN options)
    link_settings: tuple[tuple[str, Any], ...] = ()


@dataclass
class ScanReport:
    found: list[Found] = field(default_factory=list)
    skipped: list[str] = field(default_factory=list)    # what the budget or silence left out
    requests: int = 0
    seconds: float = 0.0


def probe_timeout(framing: Framing, response_time: float) -> float:
    """Seconds from a request's last byte to its reply's first: t3.5 plus the drive's delay."""
    char = character_time(framing.baudrate, framing.parity, framing.stopbits, framing.bytesize)
    return frame_gap(framing.baudrate, char) + response_time


def _identity_text(profile: Profile, read: Callable[[int, int], Answer]) -> str:
    """Return the family's firmware registers as 'code=value' (with the option's text)."""
    parts = []
    for code in profile.identify.firmware if profile.identify else ():
        parameter = profile.parameter(code)
        answer = read(parameter.address, parameter.register_count)
        if answer.registers is None:
            parts.append(f'{code}: {answer.describe()}')
            continue
        raw = decode_words(parameter, list(answer.registers))
        text = parameter.option_text(raw)
        parts.append(f'{code}={parameter.from_raw(raw):g}' + (f' ({text})' if text else ''))
    return ' '.join(parts)


def _examine(transport: RegisterTransport, unit: int, first: Answer, probe: tuple[int, int],
             profiles: Sequence[Profile], budget: Budget,
             framing: Framing | None) -> tuple[Identification, str]:
    """Identify the unit that answered ``first`` to the probe; read its firmware identity."""
    cache = {probe: first}

    def read(address: int, count: int) -> Answer:
        if (address, count) not in cache:
            budget.requests += 1
            cache[(address, count)] = read_answer(transport, unit, address, count)
        return cache[(address, count)]
    identification = identify(profiles, read, framing)
    identity = ''
    if identification.known:
        identity = _identity_text(profile_named(identification.profile), read)
    return identification, identity


def _probe_of(profiles: Sequence[Profile], framing: Framing | None) -> tuple[int, int]:
    """Return the read every unit id gets: the probe of the family likeliest at the framing."""
    def rank(profile: Profile) -> int:
        if framing is None:
            return 0
        framings = [f.key for f in documented_framings(profile)]
        return 0 if framings[0] == framing.key else 1 if framing.key in framings else 2
    for profile in sorted(profiles, key=rank):
        if profile.identify and profile.identify.modbus:
            identity = profile.identify.modbus
            return identity.probe_address, identity.probe_count
    raise ScanError('no profile has an identify.modbus section to probe with')


def _sweep(transport: RegisterTransport, ids: Sequence[int], probe: tuple[int, int],
           profiles: Sequence[Profile], budget: Budget, progress: Progress, where: str,
           silent_limit: int | None, framing: Framing | None,
           skip: set[int]) -> tuple[list[tuple[int, Identification, str, str]], str]:
    """Probe every id; return ([(unit, identification, identity, note)], why it stopped)."""
    results = []
    silent = 0
    for index, unit in enumerate(ids):
        if unit in skip:
            continue
        if reason := budget.exhausted:
            return results, f'{where}: {reason} at id {unit}'
        if silent_limit is not None and silent >= silent_limit:
            progress(f'{where}: nothing on the line for {silent} ids in a row, skipped '
                     f'ids {unit}-{ids[-1]}')
            return results, ''
        heard_before = transport.stats.bytes_received
        budget.requests += 1
        answer = read_answer(transport, unit, *probe)
        if not answer.heard:
            silent = 0 if transport.stats.bytes_received > heard_before else silent + 1
        else:
            silent = 0
            if answer.problem:
                results.append((unit, Identification(evidence=answer.describe()), '',
                                GARBLED))
            else:
                identification, identity = _examine(transport, unit, answer, probe, profiles,
                                                    budget, framing)
                results.append((unit, identification, identity, ''))
                shown = identification.profile or 'unknown device'
                progress(f'{where}: id {unit}: {shown} ({identification.confidence})')
        if (index + 1) % 32 == 0:
            progress(f'{where}: id {unit} of {ids[-1]} ...')
    return results, ''


def scan_rtu(port: str, profiles: Sequence[Profile], ids: Sequence[int], budget: Budget,
             progress: Progress, response_time: float = 0.05, silent_ids: int = 16,
             thorough: bool = False, baudrates: Sequence[int] = ()) -> ScanReport:
    """Probe a serial line at every candidate framing (see the module docstring)."""
    report = ScanReport()
    rtu = [p for p in profiles if 'modbus_rtu' in p.transports]
    framings = [(f, factory) for f, factory in candidate_framings(rtu)
                if not baudrates or f.baudrate in baudrates]
    if not framings:
        raise ScanError('no candidate framing: check --baudrates and --profiles')
    found_at_baud: dict[int, set[int]] = {}
    for number, (framing, factory) in enumerate(framings):
        if reason := budget.exhausted:
            report.skipped.append(f'{port}: {reason}; not scanned: '
                                  + ', '.join(f.label for f, _ in framings[number:]))
            break
        where = f'{port} {framing.label}'
        timeout = probe_timeout(framing, response_time)
        progress(f'{where}{" (a factory setting)" if factory else ""}: ids '
                 f'{ids[0]}-{ids[-1]}, {timeout * 1000:.0f} ms per silent id')
        transport = ModbusRtuTransport(port, framing.baudrate, framing.parity, framing.stopbits,
                                       framing.bytesize, timeout=timeout)
        try:
            transport.open()
        except TransportError as exc:
            raise ScanError(f'cannot open the serial port {port}: {exc} (another program, '
                            'e.g. a bus_node, may hold it)') from exc
        try:
            skip = found_at_baud.setdefault(framing.baudrate, set())
            results, stopped = _sweep(
                transport, ids, _probe_of(rtu, framing), rtu, budget, progress, where,
                None if factory or thorough else silent_ids, framing, skip)
            late = sorted(u for u in ids if transport.stats_for(u).late_replies)
        finally:
            transport.close()
        for unit, identification, identity, note in results:
            profile = profile_named(identification.profile) if identification.known else None
            notes = tuple(n for n in (note, *identification.notes) if n)
            report.found.append(Found('modbus_rtu', port, unit, identification,
                                      reported_framing(profile, framing), identity=identity,
                                      notes=notes))
            skip.add(unit)
        if late:
            report.skipped.append(f'{where}: ids {late} answered after the timeout: scan '
                                  'again with a longer --response-time')
        if stopped:
            report.skipped.append(stopped + '; not scanned: ' + ', '.join(
                f.label for f, _ in framings[number + 1:]))
            break
    return report


def scan_tcp(targets: Sequence[TcpTarget], profiles: Sequence[Profile], ids: Sequence[int],
             budget: Budget, progress: Progress, timeout: float = 0.2,
             silent_ids: int = 16, thorough: bool = False) -> ScanReport:
    """Connect to each host:port; where something listens, probe the unit ids."""
    report = ScanReport()
    tcp = [p for p in profiles if 'modbus_tcp' in p.transports]
    if not tcp:
        raise ScanError('no Modbus TCP profile among --profiles')
    probe = _probe_of(tcp, None)
    # Any Modbus family may answer through a TCP gateway: all of them are candidates.
    modbus = [p for p in profiles if {'modbus_rtu', 'modbus_tcp'} & set(p.transports)]
    for number, target in enumerate(targets):
        if reason := budget.exhausted:
            report.skipped.append(f'{reason}; not reached: ' + ', '.join(
                f'{t.host}:{t.port}' for t in targets[number:]))
            break
        where = f'{target.host}:{target.port}'
        transport = ModbusTcpTransport(target.host, target.port, timeout)
        budget.requests += 1
        try:
            transport.open()
        except TransportError:
            transport.close()
            continue            # nothing listens there
        progress(f'{where}: a Modbus TCP server listens, ids {ids[0]}-{ids[-1]}')
        try:
            results, stopped = _sweep(transport, ids, probe, modbus, budget, progress, where,
                                      None if thorough else silent_ids, None, set())
        except TransportError as exc:       # the server dropped us: report it, go on
            results, stopped = [], ''
            report.skipped.append(f'{where}: {exc}')
        finally:
            transport.close()
        for unit, identification, identity, note in results:
            notes = [n for n in (note, *identification.notes) if n]
            if identification.known and \
                    'modbus_tcp' not in profile_named(identification.profile).transports:
                notes.append('a serial drive: behind a Modbus TCP gateway?')
            report.found.append(Found('modbus_tcp', where, unit, identification,
                                      host=target.host, port=target.port, identity=identity,
                                      notes=tuple(notes)))
        if stopped:
            report.skipped.append(stopped)
            break
    return report


# --- output -----------------------------------------------------------------------------------

COLUMNS = ('link', 'framing', 'id', 'profile', 'confidence', 'identity', 'notes')


def table_rows(found: Sequence[Found]) -> list[tuple[str, ...]]:
    rows = []
    for item in found:
        ident = item.identification
        profile = ident.profile or 'unknown'
        if ident.alternatives and ident.confidence == 'low':
            profile += ' (or ' + ', '.join(ident.alternatives) + ')'
        notes = list(item.notes)
        if not ident.known and ident.evidence:
            notes.append(ident.evidence)
        rows.append((item.link, item.framing.label if item.framing else item.kind,
                     str(item.unit), profile, ident.confidence, item.identity or '-',
                     '; '.join(notes)))
    return rows


def format_table(found: Sequence[Found]) -> str:
    rows = [COLUMNS, *table_rows(found)]
    widths = [max(len(row[i]) for row in rows) for i in range(len(COLUMNS) - 1)]
    lines = []
    for row in rows:
        cells = [cell.ljust(width) for cell, width in zip(row, widths)] + [row[-1]]
        lines.append('  '.join(cells).rstrip())
    return '\n'.join(lines)


def _drive_key(item: Found) -> str:
    return f'{item.identification.profile or "unknown"}_{item.unit}'


def bus_documents(found: Sequence[Found]) -> list[tuple[str, dict[str, Any], list[str]]]:
    """Return (bus name, bus_node document, comment lines) per link found.

    A serial line runs at one framing: the framing (baud rate, parity) with the
    most identified drives becomes the bus (stop bits: 2 if any drive needs 2; a
    drive set for 1 reads 2), the other drives are listed in the comments.
    Unknown devices are never put on a bus.
    """
    links: dict[tuple[str, str], list[Found]] = {}
    for item in found:
        links.setdefault((item.kind, item.link), []).append(item)
    documents = []
    for number, ((kind, link), items) in enumerate(links.items()):
        known = [i for i in items if i.identification.known]
        comments = [f'written by vfd_scan: {kind} {link}']
        if kind == 'modbus_rtu':
            groups: dict[tuple[int, str, int], list[Found]] = {}
            for item in known:
                groups.setdefault(item.framing.key, []).append(item)
            if not groups:
                continue
            key = max(groups, key=lambda k: len(groups[k]))
            members = groups[key]
            stopbits = max(item.framing.stopbits for item in members)
            bus = {'name': f'rs485_{number}', 'transport.type': 'modbus_rtu',
                   'transport.port': link, 'transport.baudrate': key[0],
                   'transport.parity': key[1], 'transport.stopbits': stopbits,
                   'control_rate': 50.0}
            for other_key, others in groups.items():
                if other_key != key:
                    comments.append(f'NOT on this bus (one line runs one framing), found at '
                                    f'{others[0].framing.label}: ' + ', '.join(
                                        f'{o.identification.profile} id {o.unit}'
                                        for o in others))
        elif kind == 'modbus_tcp':
            members = known
            if not members:
                continue
            bus = {'name': f'tcp_{number}', 'transport.type': 'modbus_tcp',
                   'transport.host': members[0].host, 'transport.port': members[0].port,
                   'control_rate': 50.0}
        else:
            members = known
            if not members:
                continue
            interface, _, channel = link.partition(':')
            bus = {'name': f'can_{number}', 'transport.type': 'canopen',
                   'transport.interface': interface, 'transport.channel': channel,
                   **dict(members[0].link_settings), 'control_rate': 100.0}
        drives = {}
        for item in members:
            ident = item.identification
            drives[_drive_key(item)] = {'namespace': f'/{_drive_key(item)}',
                                        'drive.profile': ident.profile,
                                        'transport.unit_id': item.unit}
            line = f'{_drive_key(item)}: {ident.profile} ({ident.confidence})'
            if ident.alternatives:
                line += f', could also be {", ".join(ident.alternatives)}'
            comments.append(line + (f'; {item.identity}' if item.identity else ''))
        for item in items:
            if not item.identification.known:
                comments.append(f'unknown device at id {item.unit}: '
                                f'{item.identification.evidence}')
        document = {'bus': bus, 'drives': drives}
        parse_bus_config(document)          # what bus_node will accept, checked here
        documents.append((bus['name'], document, comments))
    return documents


def write_yaml(found: Sequence[Found], path: Path, progress: Progress) -> list[Path]:
    """Write one bus_node file per link: ``path`` itself when there is one link."""
    documents = bus_documents(found)
    if not documents:
        progress('no identified drive: no bus file written')
    written = []
    for name, document, comments in documents:
        target = path if len(documents) == 1 else path.with_name(
            f'{path.stem}_{name}{path.suffix or ".yaml"}')
        header = ''.join(f'# {line}\n' for line in comments)
        header += ('# ros2 run vfd_ros2 bus_node --ros-args -p config_file:=' + str(target)
                   + '\n# Check gear_ratio, invert_direction and motor.* before the first '
                   'run.\n')
        target.write_text(header + yaml.safe_dump(document, sort_keys=False), encoding='utf-8')
        written.append(target)
        progress(f'wrote {target}')
    return written


# --- command line -----------------------------------------------------------------------------

def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog='vfd_scan', description=__doc__.splitlines()[0],
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog='Exit status: 0 found drives, 1 found nothing, 2 could not scan.')
    links = parser.add_argument_group('links (at least one)')
    links.add_argument('--port', action='append', default=[], metavar='DEVICE',
                       help='serial device of an RS-485 line (repeatable)')
    links.add_argument('--tcp', action='append', default=[], metavar='HOST[-LAST][:PORT[-PORT]]',
                       help='Modbus TCP endpoints, e.g. 192.168.0.10-20:502 (repeatable)')
    links.add_argument('--can', action='append', default=[], metavar='INTERFACE:CHANNEL',
                       help='CAN bus, e.g. socketcan:can0 (python-can interface and channel)')
    parser.add_argument('--ids', default='', help='unit ids to probe (default 1-247; '
                        'CANopen --sdo-probe: 1-127)')
    parser.add_argument('--profiles', default='', help='comma-separated families (default: '
                        'every shipped profile)')
    parser.add_argument('--baudrates', default='', help='only these baud rates, e.g. 9600,115200')
    parser.add_argument('--response-time', type=float, default=0.05,
                        help='s a drive may take to answer, beyond t3.5 (default 0.05)')
    parser.add_argument('--tcp-timeout', type=float, default=0.2, help='s per TCP request')
    parser.add_argument('--silent-ids', type=int, default=16,
                        help='skip the rest of a non-factory framing (or TCP server) after '
                        'this many silent ids in a row (default 16)')
    parser.add_argument('--thorough', action='store_true',
                        help='every id at every framing, no early stop')
    parser.add_argument('--max-time', type=float, default=900.0,
                        help='s the whole scan may take (default 900)')
    parser.add_argument('--max-requests', type=int, default=20000,
                        help='requests the whole scan may send (default 20000)')
    parser.add_argument('--listen', type=float, default=2.0,
                        help='CANopen: s to listen for heartbeats and boot-ups (default 2)')
    parser.add_argument('--sdo-probe', action='store_true',
                        help='CANopen: also ask every id not heard by an SDO read of 0x1000')
    parser.add_argument('--can-bitrate', type=int, default=0,
                        help='CANopen: bit/s to open the interface with (0 = as configured)')
    parser.add_argument('--can-options', default='', metavar='JSON',
                        help='CANopen: extra can.Bus arguments as a JSON object, as '
                        'transport.can_options, e.g. \'{"host": "10.0.0.5", "port": 29536}\' '
                        'for socketcand')
    parser.add_argument('--yaml', type=Path, metavar='FILE',
                        help='write a bus_node configuration (one file per link)')
    parser.add_argument('--quiet', action='store_true', help='no progress on stderr')
    return parser


def run(argv: Sequence[str] | None = None, stdout: TextIO = sys.stdout,
        stderr: TextIO = sys.stderr) -> int:
    """Run a scan as the command line asks; return the exit status."""
    args = _parser().parse_args(argv)
    progress = Progress(None if args.quiet else stderr)
    try:
        if not (args.port or args.tcp or args.can):
            raise ScanError('name at least one link: --port, --tcp or --can')
        names = [n.strip() for n in args.profiles.split(',') if n.strip()] or \
            available_profiles()
        profiles = [profile_named(name) for name in names]
        ids = parse_ids(args.ids or '1-247')
        baudrates = [int(b) for b in args.baudrates.split(',') if b.strip()] \
            if args.baudrates else []
        targets = [t for text in args.tcp for t in parse_tcp(text)]
        budget = Budget(args.max_time, args.max_requests)
        report = ScanReport()
        for port in args.port:
            if not Path(port).exists():
                raise ScanError(f'no such serial port: {port}')
            part = scan_rtu(port, profiles, ids, budget, progress, args.response_time,
                            args.silent_ids, args.thorough, baudrates)
            report.found += part.found
            report.skipped += part.skipped
        if targets:
            part = scan_tcp(targets, profiles, ids, budget, progress, args.tcp_timeout,
                            args.silent_ids, args.thorough)
            report.found += part.found
            report.skipped += part.skipped
        for text in args.can:
            from .scan_canopen import scan_canopen  # python-can only when asked for
            can_ids = parse_ids(args.ids or '1-127', 1, 127)
            part = scan_canopen(text, profiles, can_ids, budget, progress, args.listen,
                                args.sdo_probe, args.can_bitrate, can_options=args.can_options)
            report.found += part.found
            report.skipped += part.skipped
    except (VfdError, ValueError) as exc:
        print(f'vfd_scan: {exc}', file=stderr)
        return FAILED
    report.requests, report.seconds = budget.requests, budget.elapsed
    print(format_table(report.found) if report.found else 'nothing answered', file=stdout)
    for line in report.skipped:
        print(f'not covered: {line}', file=stdout)
    garbled = sum(1 for item in report.found if GARBLED in item.notes)
    progress(f'{len(report.found) - garbled} found'
             + (f' (and {garbled} garbled replies)' if garbled else '')
             + f', {report.requests} requests, {report.seconds:.1f} s')
    if args.yaml is not None and report.found:
        try:
            write_yaml(report.found, args.yaml, progress)
        except (OSError, VfdError) as exc:
            print(f'vfd_scan: cannot write {args.yaml}: {exc}', file=stderr)
            return FAILED
    # Garbled replies alone are no drive: a line of noise answers every id at every
    # baud rate, and 'found' would send a script on to configure nothing.
    return FOUND if len(report.found) > garbled else NOTHING


def main(argv: Sequence[str] | None = None) -> int:
    return run(argv)


if __name__ == '__main__':
    raise SystemExit(main())
