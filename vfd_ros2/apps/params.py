"""vfd_params: back up a drive's parameters, compare, and restore them onto a replacement.

    vfd_params dump    --port /dev/ttyUSB0 --unit 1 --profile boneng_am -o left.yaml
    vfd_params diff    left.yaml --port /dev/ttyUSB0 --unit 1      # file against the drive
    vfd_params diff    left.yaml right.yaml                          # two files
    vfd_params restore left.yaml --port /dev/ttyUSB0 --unit 1       # dry run: the plan
    vfd_params restore left.yaml --port /dev/ttyUSB0 --unit 1 --write eeprom
    vfd_params restore left.yaml --node /agv/left_wheel/drive --write ram

Directly on a line (``--port`` RS-485, ``--host`` Modbus TCP, ``--can`` CANopen; no
ROS needed) or through a running drive_node / bus_node (``--node``: its
~/get_drive_parameter, ~/set_drive_parameter and ~/stop services, its ~/status;
rclpy is imported only then). The backup file holds every readable parameter
(code, name, value in engineering units, raw, unit, option text) and the
profile and firmware it came from (``identify.firmware``).

A restore refuses a file of another family (a direct Modbus link runs the
family's identification reads; a node must run the file's profile), a drive
whose firmware values differ (``--allow-firmware-change`` to override) and a
drive that reports running. It writes only what differs, in the order of
``vfd_ros2.drives.backup`` (commissioning selectors, stopped-only, the rest, the
RAM/EEPROM switch, link settings only with ``--link-settings``), RAM or EEPROM
as ``--write`` says, reads each write back, and halts at the first refusal,
leaving the drive commanded to stop and saying what was written and what not.

Exit status: 0 done (diff: no difference), 1 differences found or a restore
halted, 2 nothing done (bad input, wrong family, unreachable drive).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import Any, Sequence, TextIO

from ..control.factory import build_transport, with_defaults
from ..control.settings import prefixed, velocity_scaling
from ..drives import drive_class_for
from ..drives.backup import (
    Backup,
    ParameterAccess,
    compare,
    execute,
    firmware_differences,
    is_setting,
    plan_restore,
    take_backup,
)
from ..drives.base import Drive, ParameterValue
from ..drives.identify import identify, profile_named, read_answer
from ..errors import (
    BadFrame,
    CommTimeout,
    ProfileError,
    ProtocolException,
    TransportError,
    VfdError,
)
from ..profiles import Profile, available_profiles
from ..protocol.registers import decode_words, plan_reads
from ..transports.base import RegisterTransport

DONE, DIFFERENT, FAILED = 0, 1, 2

#: s a drive may take to report not running after the stop command (its ramp)
STOP_WAIT = 5.0


class Refused(VfdError):
    """The tool will not do what was asked (wrong family, running drive, bad file)."""


# --- reaching the drive directly ---------------------------------------------------------------

class DirectAccess:
    """A ``ParameterAccess`` on a drive object (``vfd_ros2.drives``) on its own link."""

    def __init__(self, drive: Drive) -> None:
        self.drive = drive
        self.profile = drive.profile
        self.description = drive.hardware_id

    def read(self, code: str) -> ParameterValue:
        return self.drive.get_parameter(code)

    def read_many(self, codes: list[str]) -> dict[str, ParameterValue]:
        """Read register drives in blocks (the profile's read limit, never over a gap).

        Best effort: a block the drive refuses or garbles is left out (its values
        are then read one by one, which names the culprit); three silent blocks
        in a row end it.
        """
        transport = _modbus_transport(self)
        if transport is None:
            return {}
        profile = self.profile
        parameters = [profile.parameter(code) for code in codes]
        parameters = [p for p in parameters if p.address >= 0]
        blocks = plan_reads({(p.address, p.register_count) for p in parameters},
                            profile.modbus.max_read_registers,
                            lambda address: profile.modbus.gaps_readable or
                            profile.parameter_at(address) is not None)
        words: dict[int, int] = {}
        silent = 0
        for block in blocks:
            try:
                for offset, word in enumerate(transport.read_registers(
                        self.drive.unit_id, block.start, block.count)):
                    words[block.start + offset] = word
                silent = 0
            except CommTimeout:
                silent += 1
                if silent >= 3:
                    break
            except (ProtocolException, BadFrame):
                silent = 0
        found = {}
        for parameter in parameters:
            span = [words.get(parameter.address + i) for i in range(parameter.register_count)]
            if None not in span:
                raw = decode_words(parameter, span)
                found[parameter.code] = ParameterValue(parameter, raw, parameter.from_raw(raw))
        return found

    def write(self, code: str, value: float, persistent: bool) -> tuple[ParameterValue, str]:
        # The restore asked the drive whether it runs just before each stopped-only write.
        return self.drive.set_parameter(code, value, persistent, running=False)

    def refusal(self, code: str) -> str:
        return ''

    def running(self) -> bool | None:
        """Evaluate the profile's ``running`` flag from one read of its signal."""
        rule = self.profile.flags.get('running')
        signal = self.profile.signal(rule.signal) if rule else None
        if signal is None:
            return None
        try:
            value = self.drive.get_parameter(signal.code)
        except VfdError:
            return None
        raw = signal.extract(value.raw)
        return rule.evaluate(raw if signal.bits else value.parameter.from_raw(raw))

    def stop(self) -> str:
        """Zero setpoint, the stop command, then wait for the drive to report not running."""
        try:
            if hasattr(self.drive, 'write_setpoint'):
                self.drive.write_setpoint(0.0)
            self.drive.send_command('stop')
        except VfdError as exc:
            return f'stop command not sent: {exc}'
        deadline = time.monotonic() + STOP_WAIT
        while (running := self.running()) and time.monotonic() < deadline:
            time.sleep(0.1)
        code = self.profile.control.command
        if running is None:
            return f'stop command written ({code}); the run state cannot be read'
        if running:
            return f'stop command written ({code}), but the drive still reports running'
        return f'stop command written ({code}); the drive reports not running'

    def close(self) -> None:
        self.drive.close()


def _link_values(args: argparse.Namespace, profile: str) -> dict[str, Any]:
    values: dict[str, Any] = {'drive.profile': profile, 'transport.unit_id': args.unit}
    if args.port:
        values.update({'transport.type': 'modbus_rtu', 'transport.port': args.port,
                       'transport.baudrate': args.baudrate or 0,
                       'transport.parity': args.parity or '',
                       'transport.stopbits': args.stopbits or 0})
    elif args.host:
        values.update({'transport.type': 'modbus_tcp', 'transport.host': args.host,
                       'transport.port': args.tcp_port})
    else:
        interface, _, channel = args.can.partition(':')
        if not interface or not channel:
            raise Refused(f'bad CAN bus {args.can!r}: use INTERFACE:CHANNEL, e.g. socketcan:can0')
        values.update({'transport.type': 'canopen', 'transport.interface': interface,
                       'transport.channel': channel, 'transport.can_options': args.can_options})
    if args.timeout:
        values['transport.timeout'] = args.timeout
    return values


def open_direct(args: argparse.Namespace, profile: Profile) -> DirectAccess:
    """Build the drive of ``profile`` on the link the arguments name, and open it."""
    if args.port and not Path(args.port).exists():
        raise Refused(f'no such serial port: {args.port}')
    merged = with_defaults(_link_values(args, profile.source_file or profile.name))
    transport = build_transport(merged)
    drive = drive_class_for(type(transport))(profile, transport, args.unit,
                                             velocity_scaling(profile, merged),
                                             prefixed(merged, 'drive'))
    try:
        drive.open()
    except TransportError as exc:
        drive.close()
        raise Refused(f'cannot reach the drive: {exc}') from exc
    return DirectAccess(drive)


def _modbus_transport(access: ParameterAccess) -> RegisterTransport | None:
    transport = getattr(getattr(access, 'drive', None), 'transport', None)
    return transport if isinstance(transport, RegisterTransport) else None


def check_family(access: ParameterAccess, unit: int) -> str:
    """Refuse a drive that is not of the access's family (Modbus: its identify checks)."""
    transport = _modbus_transport(access)
    profile = access.profile
    if transport is None:
        return 'family not checked: no identification reads on this link'
    if not (profile.identify and profile.identify.modbus):
        return f'family not checked: {profile.name} has no identify section'

    def read(address: int, count: int):
        return read_answer(transport, unit, address, count)
    probe = read(profile.identify.modbus.probe_address, profile.identify.modbus.probe_count)
    if not probe.heard:
        raise Refused(f'nothing answers at unit {unit} on {transport.description}: check the '
                      'unit id, the framing (vfd_scan finds both) and the wiring')
    own = identify([profile], read)
    if own.profile == profile.name:
        return f'identifies as {profile.name} ({own.evidence})'
    others = [profile_named(n) for n in available_profiles()]
    seen = identify([p for p in others if {'modbus_rtu', 'modbus_tcp'} & set(p.transports)],
                    read)
    shown = f'{seen.profile} ({seen.confidence})' if seen.known else \
        f'no known family ({seen.evidence})'
    raise Refused(f'the drive at unit {unit} does not identify as {profile.name} (it answers '
                  f'like {shown}): a {profile.name} file or profile does not fit it')


def detect_profile(args: argparse.Namespace) -> Profile:
    """Find the family at the unit when --profile is not given (Modbus: identify reads)."""
    if args.can:
        raise Refused('over CANopen name the family with --profile')
    if args.port and not args.baudrate:
        raise Refused('name the family (--profile: its factory framing is used) or the framing '
                      '(--baudrate, --parity, --stopbits; vfd_scan finds them)')
    modbus = [profile_named(n) for n in available_profiles()]
    modbus = [p for p in modbus if {'modbus_rtu', 'modbus_tcp'} & set(p.transports)]
    access = open_direct(args, modbus[0])
    try:
        transport = _modbus_transport(access)
        seen = identify(modbus, lambda a, c: read_answer(transport, args.unit, a, c))
    finally:
        access.close()
    if not seen.known or seen.confidence not in ('medium', 'high'):
        raise Refused(f'cannot tell the family at unit {args.unit} '
                      f'({seen.profile or "unknown"}, {seen.confidence}: {seen.evidence}): '
                      'name it with --profile')
    return profile_named(seen.profile)


# --- commands ----------------------------------------------------------------------------------

def _open(args: argparse.Namespace, profile: Profile | None, out: TextIO) -> Any:
    """Return an open access: through the node, or directly (checked against the family)."""
    if args.node:
        try:
            from .params_node import NodeAccess  # rclpy only in this mode
        except ImportError as exc:
            raise Refused(f'--node needs ROS 2 (rclpy and the vfd_ros2 interfaces): {exc}; '
                          'on a line without ROS use --port, --host or --can') from exc
        access = NodeAccess(args.node, timeout=args.node_timeout)
        if profile is None and args.profile:
            profile = profile_named(args.profile)
        if profile is not None and access.profile.name != profile.name:
            access.close()
            raise Refused(f'{args.node} runs profile {access.profile.name}, not '
                          f'{profile.name}: a {profile.name} file does not fit it')
        return access
    if profile is None:
        profile = profile_named(args.profile) if args.profile else detect_profile(args)
    access = open_direct(args, profile)
    try:
        note = check_family(access, args.unit)
    except VfdError:
        access.close()
        raise
    print(f'{access.description}: {note}', file=out)
    return access


def _live(access: ParameterAccess, codes: list[str], err: TextIO) -> Backup:
    """Read the drive's current values of ``codes`` (progress on ``err``)."""
    return take_backup(access, codes, lambda text: print(f'  {text}', file=err))


def cmd_dump(args: argparse.Namespace, out: TextIO) -> int:
    if not args.output:
        raise Refused('dump needs -o FILE')
    access = _open(args, None, out)
    try:
        backup = take_backup(access, progress=lambda text: print(f'  {text}', file=args.err))
    finally:
        access.close()
    backup.save(args.output)
    identity = ' '.join(f'{code}={value:g}' for code, value in backup.identity.items())
    print(f'wrote {args.output}: {backup.profile}, {len(backup.entries)} parameters, '
          f'{len(backup.unreadable)} not readable' + (f'; identity {identity}' if identity
                                                       else ''), file=out)
    for code, why in list(backup.unreadable.items())[:10]:
        print(f'  not read: {code}: {why}', file=out)
    return DONE


def _print_differences(differences, left: str, right: str, out: TextIO) -> None:
    rows = [('code', 'name', left, right)] + [(d.code, d.name, d.left, d.right)
                                              for d in differences]
    widths = [max(len(row[i]) for row in rows) for i in range(3)]
    for row in rows:
        print('  '.join(cell.ljust(width) for cell, width in zip(row, widths)) + '  ' + row[3],
              file=out)


def cmd_diff(args: argparse.Namespace, out: TextIO) -> int:
    left = Backup.load(args.file)
    if args.other:
        right, names = Backup.load(args.other), (str(args.file), str(args.other))
    else:
        profile = left.family
        codes = [c for c in left.entries if args.all or is_setting(profile, c)]
        access = _open(args, profile, out)
        try:
            right = _live(access, codes, args.err)
        finally:
            access.close()
        names = (str(args.file), 'drive')
    differences = compare(left, right, settings_only=not args.all)
    if not differences:
        print('no differences' + ('' if args.all else ' in the settings (--all: every value)'),
              file=out)
        return DONE
    _print_differences(differences, *names, out)
    print(f'{len(differences)} differ', file=out)
    return DIFFERENT


def cmd_restore(args: argparse.Namespace, out: TextIO) -> int:
    backup = Backup.load(args.file)
    profile = backup.family
    if args.profile and profile_named(args.profile).name != profile.name:
        raise Refused(f'--profile {args.profile} but the file is for {profile.name}')
    access = _open(args, profile, out)
    try:
        return _restore(args, backup, access, out)
    finally:
        access.close()


def _restore(args: argparse.Namespace, backup: Backup, access: Any, out: TextIO) -> int:
    profile = access.profile
    codes = list(backup.identity) + [c for c in backup.entries if is_setting(profile, c)]
    live = _live(access, list(dict.fromkeys(codes)), args.err)
    changed = firmware_differences(backup, live.identity)
    if changed and not args.allow_firmware_change:
        raise Refused("the drive's firmware differs from the file's (" + '; '.join(changed)
                      + '): parameter tables may differ between firmware versions; check the '
                      'manual and pass --allow-firmware-change to restore anyway')
    plan = plan_restore(backup, live, access, include_link=args.link_settings)
    mode = f'writes to {args.write.upper()}' if args.write else \
        'dry run: nothing is written (--write ram|eeprom writes)'
    print(f'restore {args.file} ({backup.profile}, from {backup.source or "?"}, '
          f'{backup.taken or "?"}) onto {access.description}: {mode}', file=out)
    for line in changed:
        print(f'  firmware differs, allowed: {line}', file=out)
    print(f'  {len(plan.steps)} to write, {plan.unchanged} already equal, '
          f'{len(plan.skipped)} skipped, {plan.read_only} read-only (for reference, never '
          'written)', file=out)
    for number, step in enumerate(plan.steps, 1):
        print(f'  {number:3d}. [{step.group}] {step.shown(profile)}', file=out)
    for skip in plan.skipped:
        print(f'  skip {skip.code}: {skip.why}', file=out)
    for warning in plan.warnings:
        print(f'  warning: {warning}', file=out)
    for invalid in plan.invalid:
        print(f'  not valid {invalid.code}: {invalid.why}', file=out)
    if plan.invalid:
        raise Refused(f'{len(plan.invalid)} value(s) of {args.file} cannot be written to '
                      f'{profile.name} (listed above): fix the file; nothing was written')
    if not args.write or not plan.steps:
        return DONE
    running = access.running()
    if running:
        raise Refused('the drive reports running: stop it first (a restore writes only to a '
                      'stopped drive)')
    if running is None:
        raise Refused("the drive's run state cannot be read (offline, or it refuses its "
                      'running flag): a restore writes only to a drive that reports stopped')
    before = access.stop()
    print(f'  before writing: {before}', file=out)
    result = execute(plan, access, args.write == 'eeprom',
                     progress=lambda text: print(f'  {text}', file=out))
    planned = sum(1 for step, _, _ in result.written if step in plan.steps)
    print(f'written: {planned} of {len(plan.steps)} ({args.write.upper()})'
          + (' and the RAM/EEPROM switch set back' if planned < len(result.written) and
             not result.warnings else ''), file=out)
    for warning in result.warnings:
        print(f'  warning: {warning}', file=out)
    for step, value, note in result.written:
        if value is None:
            print(f'  {step.code}: {note}', file=out)
    if result.failed is not None:
        step, why = result.failed
        print(f'HALTED at {step.code}: {why}', file=out)
        print(f'  not written ({len(result.not_written) + 1}): ' + ', '.join(
            [step.code] + [s.code for s in result.not_written]), file=out)
        print(f'  drive: {result.stop}', file=out)
        return DIFFERENT
    if result.not_written:
        print(f'  not sent ({len(result.not_written)}): '
              + ', '.join(s.code for s in result.not_written) + f'; {result.stop}', file=out)
        return DIFFERENT
    return DONE


# --- command line ------------------------------------------------------------------------------

def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog='vfd_params', description=__doc__.splitlines()[0],
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog='Exit status: 0 done / no difference, 1 differences or a halted restore, '
               '2 nothing done.')
    link = argparse.ArgumentParser(add_help=False)
    group = link.add_argument_group('the drive (one of)')
    group.add_argument('--port', help='RS-485 serial device')
    group.add_argument('--host', help='Modbus TCP address')
    group.add_argument('--can', metavar='INTERFACE:CHANNEL', help='CANopen bus, e.g. '
                       'socketcan:can0')
    group.add_argument('--node', help='a running drive node, e.g. /agv/left_wheel/drive')
    link.add_argument('--unit', type=int, default=1, help='unit id / node id (default 1)')
    link.add_argument('--profile', help='drive family (dump: identified when omitted; '
                      'diff/restore: must match the file)')
    link.add_argument('--baudrate', type=int, default=0, help="RTU: 0 = the family's factory")
    link.add_argument('--parity', default='', help='RTU: N, E or O')
    link.add_argument('--stopbits', type=int, default=0, help='RTU: 1 or 2')
    link.add_argument('--tcp-port', type=int, default=502)
    link.add_argument('--can-options', default='', metavar='JSON',
                      help='CANopen: extra can.Bus arguments as a JSON object, as '
                      'transport.can_options (e.g. host and port for socketcand)')
    link.add_argument('--timeout', type=float, default=0.0, help='s per reply (0 = default)')
    link.add_argument('--node-timeout', type=float, default=10.0,
                      help='--node: s to wait for its status and each service reply')
    commands = parser.add_subparsers(dest='command', required=True)
    dump = commands.add_parser('dump', parents=[link], help='every readable parameter to a file')
    dump.add_argument('-o', '--output', type=Path, help='backup file to write')
    diff = commands.add_parser('diff', parents=[link],
                               help='a file against the drive, or two files')
    diff.add_argument('file', type=Path)
    diff.add_argument('other', type=Path, nargs='?', help='a second file (no drive needed)')
    diff.add_argument('--all', action='store_true', help='also read-only values (measurements, '
                      'status, identity) and the control-owned registers')
    restore = commands.add_parser('restore', parents=[link], help='write a file to a drive')
    restore.add_argument('file', type=Path)
    restore.add_argument('--write', choices=('ram', 'eeprom'),
                         help='write for real, to RAM or EEPROM (default: dry run)')
    restore.add_argument('--link-settings', action='store_true',
                         help='also write address / baud rate / framing / IP, last')
    restore.add_argument('--allow-firmware-change', action='store_true',
                         help='restore onto a drive whose firmware values differ')
    return parser


def run(argv: Sequence[str] | None = None, stdout: TextIO = sys.stdout,
        stderr: TextIO = sys.stderr) -> int:
    """Run one vfd_params command; return the exit status."""
    args = _parser().parse_args(argv)
    args.err = stderr
    links = [name for name in ('port', 'host', 'can', 'node') if getattr(args, name)]
    needs_link = args.command == 'dump' or args.command == 'restore' or \
        (args.command == 'diff' and not args.other)
    try:
        if needs_link and len(links) != 1:
            raise Refused('name the drive with exactly one of --port, --host, --can, --node')
        if args.command == 'dump':
            return cmd_dump(args, stdout)
        if args.command == 'diff':
            return cmd_diff(args, stdout)
        return cmd_restore(args, stdout)
    except (VfdError, ProfileError) as exc:
        print(f'vfd_params: {exc}', file=stderr)
        return FAILED
    except KeyboardInterrupt:
        # (a restore's writes handle it themselves: halted, switch back, stopped)
        print('vfd_params: interrupted (Ctrl-C)', file=stderr)
        return FAILED


def main(argv: Sequence[str] | None = None) -> int:
    return run(argv)


if __name__ == '__main__':
    raise SystemExit(main())
