"""Transport plugins: how raw values reach a drive.

A transport is found by name: first in the built-in table below (imported only
when used), then in the ``vfd_ros2.transports`` entry-point group, so a new
transport plugs in from its own package without editing the node::

    [options.entry_points]
    vfd_ros2.transports =
        my_bus = my_package.my_module:MyTransport
"""

from __future__ import annotations

import importlib
from importlib import metadata

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


def _entry_points() -> dict[str, metadata.EntryPoint]:
    return {ep.name: ep for ep in metadata.entry_points(group=ENTRY_POINT_GROUP)}


def available_transports() -> list[str]:
    return sorted(set(BUILTIN_TRANSPORTS) | set(_entry_points()))


def load_transport_class(name: str) -> type[Transport]:
    """Return the transport class registered under ``name``; TransportLoadError if none."""
    try:
        if name in BUILTIN_TRANSPORTS:
            module_name, _, class_name = BUILTIN_TRANSPORTS[name].partition(':')
            cls = getattr(importlib.import_module(module_name), class_name)
        elif name in (plugins := _entry_points()):
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
