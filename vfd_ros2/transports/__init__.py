"""Transport plugins: how raw values reach a drive.

A transport is found by name: first in the built-in table below (imported only
when used), then in the ``vfd_ros2.transports`` entry-point group, so a new
transport plugs in from its own package without editing the node::

    [options.entry_points]
    vfd_ros2.transports =
        my_bus = my_package.my_module:MyTransport
"""

from __future__ import annotations

import functools
import importlib
import sys
from importlib import metadata
from typing import Any

from ..errors import TransportLoadError
from .base import RegisterTransport, Transport, TransportParameter, TransportStats

ENTRY_POINT_GROUP = 'vfd_ros2.transports'

BUILTIN_TRANSPORTS: dict[str, str] = {
    'modbus_rtu': 'vfd_ros2.transports.modbus:ModbusRtuTransport',
    'modbus_tcp': 'vfd_ros2.transports.modbus:ModbusTcpTransport',
    'canopen': 'vfd_ros2.transports.canopen:CanopenTransport',
    'ethercat': 'vfd_ros2.transports.ethercat:EthercatTransport',
}

__all__ = [
    'BUILTIN_TRANSPORTS', 'ENTRY_POINT_GROUP', 'RegisterTransport', 'Transport',
    'TransportParameter',
    'TransportStats', 'available_transports', 'load_transport_class',
]


def registered(group: str) -> dict[str, metadata.EntryPoint]:
    """Return the entry points of ``group`` the distributions on ``sys.path`` declare.

    Looked up once per group and ``sys.path``: a lookup reads the metadata of every
    installed distribution (~600 files here), and a bus asked it several times per
    drive (1.5 s of a 32-drive bus_node's start-up).
    """
    return dict(_entry_points_on(group, tuple(sys.path)))


@functools.lru_cache(maxsize=16)
def _entry_points_on(group: str, _path: tuple[str, ...]) -> tuple[tuple[str, Any], ...]:
    return tuple((ep.name, ep) for ep in metadata.entry_points(group=group))


def available_transports() -> list[str]:
    return sorted(set(BUILTIN_TRANSPORTS) | set(registered(ENTRY_POINT_GROUP)))


def load_transport_class(name: str) -> type[Transport]:
    """Return the transport class registered under ``name``; TransportLoadError if none."""
    try:
        if name in BUILTIN_TRANSPORTS:
            module_name, _, class_name = BUILTIN_TRANSPORTS[name].partition(':')
            cls = getattr(importlib.import_module(module_name), class_name)
        elif name in (plugins := registered(ENTRY_POINT_GROUP)):
            cls = plugins[name].load()
        else:
            raise TransportLoadError(
                f'unknown transport {name!r}; available: {", ".join(available_transports())}')
    except TransportLoadError:
        raise
    except Exception as exc:  # noqa: BLE001 - whatever a plugin's import raises
        raise TransportLoadError(f'transport {name!r} cannot be loaded: {exc!r}') from exc
    if not (isinstance(cls, type) and issubclass(cls, Transport)):
        raise TransportLoadError(f'transport {name!r} is not a vfd_ros2 Transport: {cls!r}')
    return cls
