"""Drive verbs per kind of bus: a profile plus a transport = a drive the loop can run.

The drive class that serves a transport is found from the transport's base
class, so a third-party ``RegisterTransport`` plugin is driven by ``ModbusDrive``
without naming it; a new kind of link registers its drive class here (or through
the ``vfd_ros2.drives`` entry-point group: ``"module:TransportBase" =
"module:DriveClass"``).
"""

from __future__ import annotations

import importlib

from ..errors import TransportLoadError
from ..transports import registered
from .base import Drive, HostLossProtection, ParameterValue, Reading, size_comm_timeout

ENTRY_POINT_GROUP = 'vfd_ros2.drives'

#: transport base class -> drive class, most specific first ("module:Class" both)
BUILTIN_DRIVES: dict[str, str] = {
    'vfd_ros2.transports.base:RegisterTransport': 'vfd_ros2.drives.modbus:ModbusDrive',
    'vfd_ros2.transports.canopen:CanopenTransport': 'vfd_ros2.drives.canopen:CanopenDrive',
    'vfd_ros2.transports.ethercat:EthercatTransport': 'vfd_ros2.drives.ethercat:EthercatDrive',
}

__all__ = ['BUILTIN_DRIVES', 'Drive', 'HostLossProtection', 'ParameterValue', 'Reading',
           'drive_class_for', 'size_comm_timeout']


def _load(path: str) -> type:
    module_name, _, name = path.partition(':')
    return getattr(importlib.import_module(module_name), name)


def drive_class_for(transport_class: type) -> type[Drive]:
    """Return the drive class for a transport class (by its nearest registered base)."""
    table = dict(BUILTIN_DRIVES)
    table.update({name: ep.value for name, ep in registered(ENTRY_POINT_GROUP).items()})
    candidates = {_load(base_path): drive_path for base_path, drive_path in table.items()}
    for base in transport_class.__mro__:
        if base in candidates:
            try:
                return _load(candidates[base])
            except Exception as exc:  # noqa: BLE001 - whatever a plugin's import raises
                raise TransportLoadError(f'drive class {candidates[base]} for '
                                         f'{transport_class.__name__} cannot be loaded: '
                                         f'{exc!r}') from exc
    raise TransportLoadError(f'no drive class serves the transport {transport_class.__name__}; '
                             f'register one in the {ENTRY_POINT_GROUP} entry-point group')
