"""ROS parameter descriptors that tell the truth: description, range, read-only or live.

``ros2 param describe`` shows what these build. A parameter that cannot change
while the node runs is declared ``read_only`` (rclpy then refuses a set with
that reason); a live one carries its range, and the node's set-parameters
callback validates and applies it (``LiveParameters``).
"""

from __future__ import annotations

import difflib
import math
import re
from typing import Any, Callable, Iterable, Sequence

import yaml
from rcl_interfaces.msg import (
    FloatingPointRange,
    IntegerRange,
    ParameterDescriptor,
    SetParametersResult,
)
from rclpy.node import Node
from rclpy.parameter import Parameter

from ..errors import VfdError

LIVE_NOTE = ' [live: applied at once]'


def descriptor(description: str, default: Any, minimum: float | None = None,
               maximum: float | None = None, live: bool = False) -> ParameterDescriptor:
    """Return a descriptor: read-only unless ``live``, with the range where there is one."""
    text = description + (LIVE_NOTE if live else '')
    result = ParameterDescriptor(description=text, read_only=not live)
    if minimum is not None or maximum is not None:
        if isinstance(default, bool):
            pass
        elif isinstance(default, int):
            result.integer_range = [IntegerRange(
                from_value=int(minimum if minimum is not None else -2 ** 63),
                to_value=int(maximum if maximum is not None else 2 ** 63 - 1), step=0)]
        elif isinstance(default, float):
            result.floating_point_range = [FloatingPointRange(
                from_value=float(minimum if minimum is not None else -math.inf),
                to_value=float(maximum if maximum is not None else math.inf), step=0.0)]
    return result


def check_value(name: str, value: Any, minimum: float | None = None,
                maximum: float | None = None) -> None:
    """Raise ValueError naming ``name`` for NaN, inf or a value out of range."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return
    if not math.isfinite(value):
        raise ValueError(f'{name} must be a finite number, got {value}')
    # (the value as given: 0.499999999 shown as 0.5 would not say what is wrong with it)
    if minimum is not None and value < minimum:
        raise ValueError(f'{name} must be >= {minimum:g}, got {value!r}')
    if maximum is not None and value > maximum:
        raise ValueError(f'{name} must be <= {maximum:g}, got {value!r}')


def unknown_overrides(node: Node) -> list[str]:
    """Return the parameters given to ``node`` (params file, -p) that it never declared.

    rclpy drops them silently; a misspelt ``comand_timeout`` would leave the
    watchdog at its default without a word. (rclpy keeps the overrides in
    ``Node._parameter_overrides``: there is no public accessor.)
    """
    return sorted(set(node._parameter_overrides) - set(node._parameters))


#: difflib's similarity from which an unknown name is taken for a misspelt known one
#: (comand_timeout 0.97, gear_ration 0.95; diff_drive's max_wheel_velocity against
#: max_velocity, 0.8, is another node's in a shared params file)
MISSPELT_CUTOFF = 0.9


def meant_for(unknown: Iterable[str], known: Iterable[str]) -> dict[str, str]:
    """Return the unknown names that look meant as known ones: name -> how it reads.

    One known exactly (given where it reaches nothing), one close to a known name
    (misspelt: ``comand_timeout``), or one under a group of the known dotted names
    (``transport.bitrat``). The others belong to other nodes (a shared params file).
    """
    known = set(known)
    groups = tuple({name.split('.')[0] + '.' for name in known if '.' in name})
    meant = {}
    for name in unknown:
        close = difflib.get_close_matches(name, known, n=1, cutoff=MISSPELT_CUTOFF)
        if name in known:
            meant[name] = name
        elif close:
            meant[name] = f'{name} (did you mean {close[0]}?)'
        elif name.startswith(groups):
            meant[name] = name
    return meant


def params_files(argv: Sequence[str]) -> list[str]:
    """Return the ``--params-file`` paths among the ROS arguments of a command line."""
    files, ros = [], False
    for index, token in enumerate(argv):
        if token == '--ros-args':
            ros = True
        elif token == '--':
            ros = False
        elif ros and token == '--params-file' and index + 1 < len(argv):
            files.append(argv[index + 1])
    return files


def params_sections(path: str) -> list[str]:
    """Return the node patterns (sections) of params file ``path``.

    A file that does not parse has none here (rcl refuses it anyway).
    """
    try:
        with open(path, encoding='utf-8') as stream:
            document = yaml.safe_load(stream)
    except (OSError, UnicodeDecodeError, yaml.YAMLError):
        return []
    return [str(key) for key in document] if isinstance(document, dict) else []


def section_matches(section: str, node: str) -> bool:
    """Return whether a params file section names ``node`` (a fully qualified name).

    A section is a node name, '/' first or not, with rcl's wildcards (``*`` one
    name part, ``**`` any).
    """
    pattern = '/'.join('.*' if part == '**' else '[^/]*' if part == '*' else re.escape(part)
                       for part in section.strip('/').split('/'))
    return re.fullmatch(pattern, node.strip('/')) is not None


def describe_read_only_except(node: Node, live: Iterable[str]) -> None:
    """Describe read-only every parameter of ``node`` but ``live`` that rclpy left writable.

    ``use_sim_time`` (rclpy's own) is set at start-up only (``-p``); described
    writable, tools offered a change that the node's callback always refuses.
    """
    live = set(live)
    for name in node.list_parameters([], 0).names:
        if name in live:
            continue
        current = node.describe_parameter(name)
        if current.read_only:
            continue
        text = current.description
        node.set_descriptor(name, ParameterDescriptor(
            description=(text + ' ' if text else '') + '[set at start-up only]',
            type=current.type, read_only=True,
            additional_constraints=current.additional_constraints,
            integer_range=current.integer_range,
            floating_point_range=current.floating_point_range))


class LiveParameters:
    """The set-parameters callback of a node: validate everything, then apply, or refuse.

    ``apply`` receives ``{name: value}`` of the live parameters in one request
    and must raise (ValueError, VfdError) before changing anything when a value
    is bad. A parameter this object does not know as live is refused, so a set
    can never be reported successful and ignored.
    """

    def __init__(self, node: Node, live: Iterable[str],
                 apply: Callable[[dict[str, Any]], None],
                 ranges: dict[str, tuple[float | None, float | None]] | None = None) -> None:
        self.node = node
        self.live = set(live)
        self.ranges = ranges or {}
        self._apply = apply
        describe_read_only_except(node, self.live)  # (before this callback would refuse it)
        node.add_on_set_parameters_callback(self)

    def __call__(self, parameters: list[Parameter]) -> SetParametersResult:
        changes: dict[str, Any] = {}
        try:
            for parameter in parameters:
                if parameter.name not in self.live:
                    return SetParametersResult(
                        successful=False,
                        reason=f'{parameter.name} cannot be changed at run time')
                check_value(parameter.name, parameter.value,
                            *self.ranges.get(parameter.name, (None, None)))
                changes[parameter.name] = parameter.value
            if changes:
                self._apply(changes)
        except (ValueError, TypeError, VfdError) as exc:
            self.node.get_logger().warning(f'parameter change refused: {exc}')
            return SetParametersResult(successful=False, reason=str(exc))
        except Exception as exc:  # noqa: BLE001 - a bad value must not crash the node
            self.node.get_logger().error(f'parameter change failed: {exc!r}')
            return SetParametersResult(successful=False, reason=f'internal error: {exc!r}')
        if changes:
            self.node.get_logger().info(
                'parameters applied: ' + ', '.join(f'{k}={v}' for k, v in changes.items()))
        return SetParametersResult(successful=True)
