"""Profile files -> ``Profile``: YAML, checked against ``schema.json``, then cross-checked.

The structure and types are the JSON Schema's job (``jsonschema``; editors that
understand ``# yaml-language-server: $schema=schema.json`` check it as you type);
what a schema cannot say is checked here: every code a section names is in the
parameter table, names and codes are unique, defaults are valid values, flags
use monitored signals, a CANopen object named by code has an index.

    python -m vfd_ros2.profiles            # check every shipped profile
    python -m vfd_ros2.profiles my.yaml    # check one file
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import json
from pathlib import Path
from typing import Any, Mapping

import jsonschema
import yaml

from ..errors import ParameterError, ProfileError
from .model import (
    Access,
    CanObject,
    CanopenIdentity,
    CanopenSpec,
    CommissioningWrite,
    CommTimeoutSpec,
    ControlSpec,
    ControlStyle,
    DirectionMode,
    EffortKind,
    EffortSpec,
    EmcyFault,
    EmcyMapping,
    EthercatIdentity,
    EthercatSpec,
    FaultEntry,
    FaultSpec,
    FlagRule,
    FlagRuleKind,
    FunctionCodeWindow,
    IdentifyCheck,
    IdentifyExpect,
    IdentifySpec,
    ModbusIdentity,
    ModbusSpec,
    ObjectSet,
    Parameter,
    ParameterAccess,
    Persistence,
    PersistenceKind,
    PositionSource,
    PositionSpec,
    Profile,
    SerialDefaults,
    Signal,
    SpeedUnit,
    StopAction,
    ValueType,
    VelocitySpec,
    WordOrder,
)

PROFILE_DIR = Path(__file__).resolve().parent
SCHEMA_FILE = PROFILE_DIR / 'schema.json'


@functools.lru_cache(maxsize=2)
def _validator(kind: str) -> jsonschema.protocols.Validator:
    """Return the validator of a 'profile' or a 'table' (a file named by parameter_tables)."""
    schema = json.loads(SCHEMA_FILE.read_text(encoding='utf-8'))
    return jsonschema.Draft202012Validator({**schema, '$ref': f'#/$defs/{kind}'})


def _message(error: jsonschema.ValidationError) -> str:
    where = '.'.join(str(part) for part in error.absolute_path) or '(top level)'
    if error.validator == 'additionalProperties':
        # "unknown key" names the key, as a profile author would say it.
        return f'{where}: {error.message.replace("Additional properties", "unknown keys")}'
    return f'{where}: {error.message}'


FileStamp = tuple[Path, bytes]    # a file read, and the digest of what it held


def _digest(content: bytes) -> bytes:
    return hashlib.blake2b(content, digest_size=16).digest()


def _read_yaml(path: Path, kind: str, files_read: list[FileStamp] | None = None) -> Any:
    try:
        content = path.read_bytes()
        if files_read is not None:
            files_read.append((path, _digest(content)))
        # libyaml's loader when available: the parameter tables run to ~750 rows.
        data = yaml.load(content.decode('utf-8'),
                         Loader=getattr(yaml, 'CSafeLoader', yaml.SafeLoader))
    except OSError as exc:
        raise ProfileError(f'cannot read profile file {path}: {exc}') from exc
    except UnicodeDecodeError as exc:
        raise ProfileError(f'profile file {path} is not UTF-8 text: {exc}') from exc
    except yaml.YAMLError as exc:
        raise ProfileError(f'profile file {path} is not valid YAML: {exc}') from exc
    if not isinstance(data, dict):
        raise ProfileError(f'{path.name}: expected a mapping, got {type(data).__name__}')
    errors = list(_validator(kind).iter_errors(data))
    if errors:
        # best_match goes into oneOf/anyOf branches: the message names the real defect.
        shown = [_message(jsonschema.exceptions.best_match([error])) for error in errors[:5]]
        more = f' (and {len(errors) - 5} more)' if len(errors) > 5 else ''
        raise ProfileError(f'{path.name} does not match the {kind} schema: '
                           f'{"; ".join(shown)}{more}')
    return data


#: path -> (its files as they were when read, the profile built from them). A
#: Profile is frozen and shared: parsing and validating a family's two files takes
#: ~0.25 s (the schema check most of it), and a bus of 32 drives of one family spent
#: 8 s of its start-up on the same files, once per drive. Reading them again to
#: compare digests costs well under a millisecond.
_loaded: dict[Path, tuple[list[FileStamp], Profile]] = {}


def _unchanged(files: list[FileStamp]) -> bool:
    try:
        return all(_digest(path.read_bytes()) == digest for path, digest in files)
    except OSError:
        return False


def load_profile_file(path: Path | str) -> Profile:
    """Load and validate one profile file (and the files it includes).

    Every defect of the data is reported as a ProfileError naming the file. A file
    loaded before and unchanged since (neither it nor its includes) is not parsed
    again: the same Profile is returned.
    """
    path = Path(path)
    cached = _loaded.get(path.absolute())
    if cached is not None and _unchanged(cached[0]):
        return cached[1]
    files_read: list[FileStamp] = []
    try:
        profile = _build(path, files_read)
    except ProfileError:
        raise
    except (ValueError, TypeError, KeyError) as exc:
        raise ProfileError(f'{path.name}: malformed value: {exc!r}') from exc
    _loaded[path.absolute()] = (files_read, profile)
    return profile


def _parameter(item: Mapping[str, Any]) -> Parameter:
    index = item.get('index')
    return Parameter(
        code=str(item['code']),
        address=int(item.get('address', -1)),     # -1: a CANopen-only object, no register
        description=str(item['description']),
        type=ValueType(item.get('type', 'uint16')),
        scale=float(item.get('scale', 1.0)),
        unit=str(item.get('unit') or ''),
        minimum=item.get('min'),
        maximum=item.get('max'),
        default=item.get('default'),
        access=Access(item.get('access', 'rw')),
        options={int(k): str(v) for k, v in (item.get('options') or {}).items()},
        name=str(item.get('name') or ''),
        word_order=WordOrder(item.get('word_order', 'high_first')),
        source=str(item.get('source') or ''),
        note=str(item.get('note') or ''),
        index=index,
        subindex=int(item.get('subindex', 0)),
    )


def _signal(role: str, item: Any) -> Signal:
    if isinstance(item, str):
        return Signal(role=role, code=item)
    bits = item.get('bits')
    return Signal(role=role, code=str(item['code']),
                  bits=(int(bits[0]), int(bits[1])) if bits is not None else None,
                  every=int(item.get('every', 1)))


def _can_object(item: Any, where: str, parameters: Mapping[str, Parameter]) -> CanObject:
    """Read a parameter code (its index, type, scale) or an inline {index, subindex, ...}."""
    if isinstance(item, str):
        parameter = parameters.get(item)
        if parameter is None or parameter.index is None:
            raise ProfileError(f'{where}: {item!r} is not a parameter with a CANopen index')
        return CanObject(parameter.index, parameter.subindex, parameter.type, parameter.scale,
                         parameter.unit, parameter.code)
    return CanObject(index=int(item['index']), subindex=int(item.get('subindex', 0)),
                     type=ValueType(item.get('type', 'uint16')),
                     scale=float(item.get('scale', 1.0)), unit=str(item.get('unit', '')))


def _object_set(name: str, item: Mapping[str, Any], where: str,
                parameters: Mapping[str, Parameter]) -> ObjectSet:
    mode = item.get('mode_of_operation')
    object_set = ObjectSet(
        name=name,
        control=ControlStyle(item['control']),
        controlword=_can_object(item['controlword'], f'{where}.controlword', parameters),
        statusword=_can_object(item['statusword'], f'{where}.statusword', parameters),
        target_velocity=_can_object(item['target_velocity'], f'{where}.target_velocity',
                                    parameters),
        velocity_unit=SpeedUnit(item.get('velocity_unit', 'rpm')),
        monitor={str(role): _can_object(obj, f'{where}.monitor.{role}', parameters)
                 for role, obj in item['monitor'].items()},
        commands={str(k): int(v) for k, v in (item.get('commands') or {}).items()},
        mode_of_operation=_can_object(mode, f'{where}.mode_of_operation', parameters)
        if mode is not None else None,
        mode_value=int(item.get('mode_value', 0)),
        stop_action=StopAction(item.get('stop_action', 'disable_operation')),
        controlword_bits=int(item.get('controlword_bits', 0)),
        note=str(item.get('note', '')),
    )
    if object_set.control is ControlStyle.COMMAND_WORD:
        for action in ('run', 'stop', 'fault_reset'):
            if action not in object_set.commands:
                raise ProfileError(f'{where}.commands needs {action!r}')
    return object_set


def _canopen(item: Mapping[str, Any], parameters: Mapping[str, Parameter]) -> CanopenSpec:
    spec = CanopenSpec(
        object_set=str(item['object_set']),
        object_sets={str(name): _object_set(str(name), data, f'canopen.object_sets.{name}',
                                            parameters)
                     for name, data in item['object_sets'].items()},
        heartbeat_ms=int(item.get('heartbeat_ms', 100)),
        heartbeat_timeout_factor=float(item.get('heartbeat_timeout_factor', 3.0)),
        rpdos=int(item.get('rpdos', 4)),
        tpdos=int(item.get('tpdos', 4)),
        transmission_type=int(item.get('transmission_type', 255)),
        tpdo_event_timer_ms=int(item.get('tpdo_event_timer_ms', 0)),
        rpdo_deadline=bool(item.get('rpdo_deadline', False)),
        heartbeat_consumer=bool(item.get('heartbeat_consumer', False)),
        emcy_fault=EmcyFault(item.get('emcy_fault', 'error_code')),
        note=str(item.get('note', '')),
    )
    if spec.object_set not in spec.object_sets:
        raise ProfileError(f'canopen.object_set {spec.object_set!r} is not in object_sets')
    if not (spec.transmission_type <= 240 or spec.transmission_type in (254, 255)):
        # 241-251 are reserved; 252/253 answer remote frames only, which the driver never sends
        raise ProfileError(f'canopen.transmission_type {spec.transmission_type}: use 0..240 '
                           '(synchronous) or 254/255 (event-driven)')
    return spec


def _commissioning(items: Any) -> tuple[CommissioningWrite, ...]:
    return tuple(CommissioningWrite(code=str(item['code']), value=float(item['value']),
                                    why=str(item.get('why', '')))
                 for item in items or [])


def _ethercat(item: Mapping[str, Any], parameters: Mapping[str, Parameter]) -> EthercatSpec:
    identity = item.get('identity') or {}
    window = item.get('function_codes')
    own: dict[str, Parameter] = {}
    names = {p.name for p in parameters.values() if p.name}
    for raw in item.get('parameters') or ():
        parameter = _parameter(raw)
        if parameter.code in parameters or parameter.code in own:
            raise ProfileError(f'ethercat.parameters: {parameter.code} defined twice')
        if parameter.index is None:
            raise ProfileError(f'ethercat.parameters: {parameter.code} needs its CoE index')
        if parameter.name and parameter.name in names:
            raise ProfileError(f'ethercat.parameters: readable name {parameter.name!r} used '
                               'twice')
        names.add(parameter.name)
        own[parameter.code] = parameter
    parameters = {**parameters, **own}      # commissioning may name them
    comm = item.get('comm_fault')
    spec = EthercatSpec(
        identity=EthercatIdentity(
            vendor_id=identity.get('vendor_id'), product_code=identity.get('product_code'),
            device_name=str(identity.get('device_name', '')), why=str(identity.get('why', ''))),
        rx_pdos=tuple(int(i) for i in item['rx_pdos']),
        tx_pdos=tuple(int(i) for i in item['tx_pdos']),
        objects=_object_set('ethercat', item['objects'], 'ethercat.objects', parameters),
        fixed_mapping=bool(item.get('fixed_mapping', False)),
        free_run=bool(item.get('free_run', True)),
        dc=bool(item.get('dc', False)),
        sync_cycles_us=tuple(int(c) for c in item.get('sync_cycles_us') or ()),
        parameter_access=ParameterAccess(item.get('parameter_access', 'objects')),
        function_codes=FunctionCodeWindow(
            read=int(window['read']), read_response=int(window['read_response']),
            write=int(window['write']), write_response=int(window['write_response']),
            success=int(window.get('success', 1)),
            errors={int(k): str(v) for k, v in (window.get('errors') or {}).items()},
            addresses=tuple(int(a) for a in window.get('addresses', (0, 0xFFFF))))
        if window else None,
        emcy_fault=EmcyFault(item.get('emcy_fault', 'error_code')),
        emcy_faults=tuple(EmcyMapping(int(m['error_code']), int(m['fault']),
                                      int(m.get('subcode', 0)), str(m.get('why', '')))
                          for m in item.get('emcy_faults') or ()),
        commissioning=_commissioning(item.get('commissioning')),
        comm_fault=(int(comm['fault']), int(comm.get('subcode', 0))) if comm else None,
        parameters=own,
        note=str(item.get('note', '')),
    )
    if spec.objects.control is not ControlStyle.CIA402:
        raise ProfileError('ethercat.objects.control: only cia402 is supported over EtherCAT')
    if spec.parameter_access is ParameterAccess.FUNCTION_CODES and spec.function_codes is None:
        raise ProfileError('ethercat.parameter_access function_codes needs '
                           'ethercat.function_codes')
    for write in spec.commissioning:
        if write.code not in parameters:
            raise ProfileError(f'ethercat.commissioning names {write.code!r}, not in the '
                               'parameter table')
    return spec


def _identify_read(item: Any, count: Any, where: str,
                   parameters: Mapping[str, Parameter]) -> tuple[int, int, str]:
    """Return (address, count, code) of a read named by a code or by a plain register address."""
    if isinstance(item, str):
        parameter = parameters.get(item)
        if parameter is None or parameter.address < 0:
            raise ProfileError(f'{where}: {item!r} is not a parameter with a Modbus address')
        return parameter.address, int(count or parameter.register_count), parameter.code
    return int(item), int(count or 1), ''


def _identify(item: Mapping[str, Any], parameters: Mapping[str, Parameter],
              where: str) -> IdentifySpec:
    for label in ('firmware', 'link_parameters'):
        for code in item.get(label) or []:
            if code not in parameters:
                raise ProfileError(f'{where}: identify.{label} names {code!r}, not in the '
                                   'parameter table')
    modbus = None
    if item.get('modbus'):
        data = item['modbus']
        probe_address, probe_count, _ = _identify_read(data['probe'], None,
                                                        f'{where}: identify.modbus.probe',
                                                        parameters)
        checks = []
        for number, check in enumerate(data['checks']):
            address, count, code = _identify_read(
                check['read'], check.get('count'),
                f'{where}: identify.modbus.checks[{number}]', parameters)
            checks.append(IdentifyCheck(
                address=address, count=count, code=code, expect=IdentifyExpect(check['expect']),
                values=tuple(int(v) for v in check.get('values') or ()),
                exception=int(check.get('exception', 0)), why=str(check['why'])))
        modbus = ModbusIdentity(probe_address, probe_count, tuple(checks),
                                baudrates=tuple(int(b) for b in data.get('baudrates') or ()),
                                formats=tuple(str(f) for f in data.get('formats') or ()))
    canopen = None
    if item.get('canopen'):
        data = item['canopen']
        canopen = CanopenIdentity(device_profile=data.get('device_profile'),
                                  vendor_id=data.get('vendor_id'),
                                  product_code=data.get('product_code'),
                                  why=str(data.get('why', '')))
    return IdentifySpec(firmware=tuple(str(c) for c in item.get('firmware') or ()),
                        link_parameters=tuple(str(c) for c in item.get('link_parameters') or ()),
                        modbus=modbus, canopen=canopen, note=str(item.get('note', '')),
                        source=str(item.get('source', '')))


def _position(item: Mapping[str, Any]) -> PositionSpec:
    return PositionSpec(source=PositionSource(item.get('source', 'integrated')),
                        signal=str(item.get('signal', '')),
                        counts_per_rev=float(item.get('counts_per_rev', 0.0)),
                        note=str(item.get('note', '')))


def _build(path: Path, files_read: list[FileStamp]) -> Profile:
    data = _read_yaml(path, 'profile', files_read)
    raw_parameters = list(data.get('parameters') or [])
    for include in data.get('parameter_tables') or []:
        raw_parameters.extend(
            _read_yaml(path.parent / include, 'table', files_read)['parameters'])
    parameters: dict[str, Parameter] = {}
    by_name: dict[str, str] = {}
    by_address: dict[int, str] = {}
    for item in raw_parameters:
        parameter = _parameter(item)
        if parameter.code in parameters:
            raise ProfileError(f'{path.name}: parameter {parameter.code} defined twice')
        parameters[parameter.code] = parameter
        if parameter.name:
            if parameter.name in by_name:
                raise ProfileError(f'{path.name}: readable name {parameter.name!r} used twice')
            by_name[parameter.name] = parameter.code
        if parameter.address >= 0:
            by_address.setdefault(parameter.address, parameter.code)

    modbus = data.get('modbus') or {}
    serial = modbus.get('serial') or {}
    persistence = modbus.get('persistence') or {}
    velocity = data['velocity']
    control = data['control']
    faults = data['faults']
    table: dict[int, FaultEntry] = {}
    for entry in faults.get('table') or []:
        fault = FaultEntry(
            code=int(entry['code']), name=str(entry['name']),
            remedy=str(entry.get('remedy') or ''), cause=str(entry.get('cause') or ''),
            subcodes={int(k): str(v) for k, v in (entry.get('subcodes') or {}).items()},
            confidence=str(entry.get('confidence', 'high')),
            source=str(entry.get('source') or ''), note=str(entry.get('note') or ''))
        if fault.code in table:
            raise ProfileError(f'{path.name}: fault code {fault.code} defined twice')
        table[fault.code] = fault
    comm = data.get('comm_timeout')
    profile = Profile(
        name=str(data['name']),
        vendor=str(data['vendor']),
        model=str(data['model']),
        manual=str(data['manual']),
        transports=tuple(str(t) for t in data.get('transports', ['modbus_rtu'])),
        parameters=parameters,
        modbus=ModbusSpec(
            function_codes=frozenset(int(c) for c in modbus.get('function_codes', [3, 6, 16])),
            max_read_registers=int(modbus.get('max_read_registers', 125)),
            max_write_registers=int(modbus.get('max_write_registers', 123)),
            gaps_readable=bool(modbus.get('gaps_readable', False)),
            serial=SerialDefaults(**serial),
            exception_codes={int(k): str(v)
                             for k, v in (modbus.get('exception_codes') or {}).items()},
            exception_for={str(k): int(v)
                           for k, v in (modbus.get('exception_for') or {}).items()},
            persistence=Persistence(
                kind=PersistenceKind(persistence.get('kind', 'none')),
                parameter=str(persistence.get('parameter', '')),
                volatile_value=int(persistence.get('volatile_value', 0)),
                persistent_value=int(persistence.get('persistent_value', 0)),
                offset=int(persistence.get('offset', 0)),
                flag=int(persistence.get('flag', 0)),
                applies_to=tuple((int(low), int(high))
                                 for low, high in persistence.get('applies_to') or []),
                note=str(persistence.get('note', ''))),
        ),
        velocity=VelocitySpec(
            setpoint=str(velocity['setpoint']),
            setpoint_unit=SpeedUnit(velocity['setpoint_unit']),
            feedback_unit=SpeedUnit(velocity['feedback_unit']),
            direction=DirectionMode(velocity.get('direction', 'setpoint_sign')),
            rated_speed=str(velocity.get('rated_speed', '')),
            rated_frequency=str(velocity.get('rated_frequency', '')),
            pole_pairs=str(velocity.get('pole_pairs', '')),
            acceleration_time=str(velocity.get('acceleration_time', '')),
            deceleration_time=str(velocity.get('deceleration_time', '')),
            note=str(velocity.get('note', ''))),
        control=ControlSpec(
            command=str(control['command']),
            values={str(k): int(v) for k, v in control['values'].items()},
            run_edge_from=control.get('run_edge_from'),
            note=str(control.get('note', ''))),
        monitor=tuple(_signal(str(role), item) for role, item in data['monitor'].items()),
        flags={str(name): FlagRule(signal=str(rule['signal']), rule=FlagRuleKind(rule['rule']),
                                   bit=int(rule.get('bit', 0)),
                                   values=tuple(int(v) for v in rule.get('values') or []))
               for name, rule in (data.get('flags') or {}).items()},
        status_words=tuple(str(c) for c in data.get('status_words') or []),
        faults=FaultSpec(
            code=str(faults['code']), subcode=str(faults.get('subcode', '')),
            warning_code=str(faults.get('warning_code', '')),
            warning_subcode=str(faults.get('warning_subcode', '')),
            display_format=str(faults.get('display_format', 'E{code}')), table=table,
            note=str(faults.get('note', ''))),
        comm_timeout=CommTimeoutSpec(
            parameter=str(comm['parameter']), fault_code=int(comm['fault_code']),
            fault_subcode=int(comm.get('fault_subcode', 0)), note=str(comm.get('note', '')))
        if comm is not None else None,
        commissioning=tuple(CommissioningWrite(code=str(item['code']),
                                               value=float(item['value']),
                                               why=str(item.get('why', '')),
                                               bus_control=bool(item.get('bus_control', True)))
                            for item in data.get('commissioning') or []),
        setpoints={str(k): str(v) for k, v in (data.get('setpoints') or {}).items()},
        notes=tuple(str(n) for n in data.get('notes') or []),
        source_file=str(path),
        canopen=_canopen(data['canopen'], parameters) if data.get('canopen') else None,
        ethercat=_ethercat(data['ethercat'], parameters) if data.get('ethercat') else None,
        identify=_identify(data['identify'], parameters, path.name)
        if data.get('identify') else None,
        position=_position(data.get('position') or {}),
        effort=EffortSpec(signal=str(data['effort']['signal']),
                          kind=EffortKind(data['effort']['kind']),
                          note=str(data['effort'].get('note', '')))
        if data.get('effort') else None,
        _by_name=by_name,
        _by_address=by_address,
        _by_folded_code={code.casefold(): code for code in parameters},
    )
    _check_references(profile)
    extra_owned = {str(k): str(v) for k, v in (data.get('control_owned') or {}).items()}
    channels = {str(k): str(v) for k, v in (data.get('motion_channels') or {}).items()}
    for key, codes in (('control_owned', extra_owned), ('motion_channels', channels)):
        for code in codes:
            if code not in parameters:
                raise ProfileError(f'{path.name}: {key} names {code!r}, not in the '
                                   'parameter table')
    profile = dataclasses.replace(profile, control_owned={
        **_control_owned(profile), **extra_owned}, motion_channels=channels)
    _check_defaults(profile)
    return profile


def _control_owned(profile: Profile) -> dict[str, str]:
    """Find the registers the control loop writes, from the profile's own references."""
    owned = {
        profile.control.command: "the command word is the control loop's: use ~/enable, "
                                 '~/disable, ~/stop and ~/reset_fault',
        profile.velocity.setpoint: "the speed setpoint is the control loop's: publish on "
                                   '~/velocity_command',
    }
    for topic, code in profile.setpoints.items():
        owned[code] = f'this setpoint is written from the ~/{topic} topic'
    if profile.comm_timeout is not None:
        owned[profile.comm_timeout.parameter] = (
            'the comm-loss timeout is written at connect from the drive_comm_timeout '
            'parameter, sized for the bus')
    if profile.canopen is not None:
        for parameter in profile.parameters.values():
            index = parameter.index
            if index in (0x1016, 0x1017) or (index is not None and 0x1400 <= index <= 0x1BFF):
                owned.setdefault(parameter.code, (
                    'a CANopen communication object the driver writes at connect (heartbeats, '
                    'PDOs): set transport.heartbeat_ms or drive_comm_timeout instead'))
    object_sets = list(profile.canopen.object_sets.values()) if profile.canopen else []
    if profile.ethercat is not None:
        object_sets.append(profile.ethercat.objects)
    if object_sets:
        # CiA 402 objects and their manufacturer twins, in every object set the
        # profile offers (another set may alias the same object).
        indices: dict[tuple[int, int], str] = {}
        for objects in object_sets:
            for obj, what in ((objects.controlword, 'the controlword'),
                              (objects.target_velocity, 'the target velocity'),
                              (objects.mode_of_operation, 'the mode of operation')):
                if obj is not None:
                    indices[(obj.index, obj.subindex)] = what
        for parameter in profile.parameters.values():
            what = indices.get((parameter.index, parameter.subindex)) \
                if parameter.index is not None else None
            if what is not None and parameter.code not in owned:
                owned[parameter.code] = (f"{what} is the control loop's (written every "
                                         'cycle or at connect): use the topics and services')
    return owned


def _check_defaults(profile: Profile) -> None:
    """Every factory default must be a value the driver would accept for its parameter."""
    for parameter in profile.parameters.values():
        if parameter.default is None:
            continue
        try:
            parameter.to_raw(parameter.default)
        except ParameterError as exc:
            raise ProfileError(f'{profile.source_file}: the factory default of '
                               f'{parameter.code} is not a valid value: {exc}') from exc


def _check_references(profile: Profile) -> None:
    """Every code the profile names must be in its parameter table."""
    where = profile.source_file
    referenced = [
        ('velocity.setpoint', profile.velocity.setpoint),
        ('control.command', profile.control.command),
        ('faults.code', profile.faults.code),
    ]
    for label in ('rated_speed', 'rated_frequency', 'pole_pairs', 'acceleration_time',
                  'deceleration_time'):
        code = getattr(profile.velocity, label)
        if code:
            referenced.append((f'velocity.{label}', code))
    for label in ('subcode', 'warning_code', 'warning_subcode'):
        code = getattr(profile.faults, label)
        if code:
            referenced.append((f'faults.{label}', code))
    referenced += [(f'monitor.{s.role}', s.code) for s in profile.monitor]
    referenced += [(f'status_words[{i}]', c) for i, c in enumerate(profile.status_words)]
    referenced += [(f'commissioning.{c.code}', c.code) for c in profile.commissioning]
    referenced += [(f'setpoints.{topic}', code) for topic, code in profile.setpoints.items()]
    if profile.comm_timeout:
        referenced.append(('comm_timeout.parameter', profile.comm_timeout.parameter))
    if profile.modbus.persistence.kind is PersistenceKind.SWITCH_PARAMETER:
        referenced.append(('modbus.persistence.parameter', profile.modbus.persistence.parameter))
    for label, code in referenced:
        if code not in profile.parameters:
            raise ProfileError(f'{where}: {label} names {code!r}, not in the parameter table')
    roles = {s.role for s in profile.monitor}
    for name, rule in profile.flags.items():
        if rule.signal not in roles:
            raise ProfileError(f'{where}: flags.{name} uses signal {rule.signal!r}, '
                               'which monitor does not define')
    _check_joint_signals(profile, roles)
    if profile.velocity.direction is DirectionMode.COMMAND and \
            'run_reverse' not in profile.control.values:
        raise ProfileError(f'{where}: direction "command" needs control.values.run_reverse')
    for topic, code in profile.setpoints.items():
        if not profile.parameters[code].writable:
            raise ProfileError(f'{where}: setpoints.{topic} names read-only {code}')


def _check_joint_signals(profile: Profile, roles: set[str]) -> None:
    """position.signal and effort.signal name monitored values, on every bus the profile has."""
    where = profile.source_file
    wanted = []
    if profile.position.from_drive:
        wanted.append(('position.signal', profile.position.signal))
    if profile.effort is not None:
        wanted.append(('effort.signal', profile.effort.signal))
    for label, role in wanted:
        if role not in roles:
            raise ProfileError(f'{where}: {label} names {role!r}, which monitor does not define')
        if profile.canopen is None:
            continue
        for name, objects in profile.canopen.object_sets.items():
            if label == 'position.signal' and role not in objects.monitor:
                raise ProfileError(f'{where}: {label} names {role!r}, which '
                                   f'canopen.object_sets.{name}.monitor does not map')


def available_profiles() -> list[str]:
    """Names of the profiles shipped with the package."""
    return sorted(p.stem for p in PROFILE_DIR.glob('*.yaml')
                  if not p.stem.endswith('_parameters'))


def load_profile(name_or_path: str) -> Profile:
    """Load a shipped profile by name, or any profile file by path."""
    candidate = Path(name_or_path)
    if candidate.suffix in ('.yaml', '.yml'):
        return load_profile_file(candidate)
    path = PROFILE_DIR / f'{name_or_path}.yaml'
    if not path.exists():
        raise ProfileError(
            f'unknown drive profile {name_or_path!r}; shipped profiles: '
            f'{", ".join(available_profiles())}')
    return load_profile_file(path)


def main(argv: list[str] | None = None) -> int:
    """Check profile files: ``python -m vfd_ros2.profiles [name|path ...]``."""
    import sys
    names = (argv if argv is not None else sys.argv[1:]) or available_profiles()
    status = 0
    for name in names:
        try:
            profile = load_profile(name)
        except ProfileError as exc:
            print(f'FAIL {name}: {exc}')
            status = 1
            continue
        print(f'ok   {profile.name}: {len(profile.parameters)} parameters, '
              f'{len(profile.faults.table)} faults, {len(profile.monitor)} monitored signals')
    return status

