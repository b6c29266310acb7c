"""The composition root: flat settings -> profile + transport + drive + controller.

The only place that knows every layer: it loads the profile, picks the
transport plugin and the drive class that serves it, fills the drive's factory
link values into the transport settings, and wires a ``DriveController``.
``bus.py`` builds several on one shared transport.
"""

from __future__ import annotations

from typing import Any, Mapping

from ..drives import Drive, drive_class_for
from ..errors import ParameterError
from ..profiles import Profile, load_profile
from ..transports import Transport, load_transport_class
from .controller import DriveController
from .joint import JointTracker, joint_config
from .settings import SETTINGS, controller_config, prefixed, velocity_scaling


def with_defaults(values: Mapping[str, Any]) -> dict[str, Any]:
    """Return ``values`` over the defaults of the table, the transport and the drive class."""
    merged = {s.name: s.default for s in SETTINGS}
    merged.update(values)
    transport_class = load_transport_class(str(merged['transport.type']))
    for parameter in transport_class.parameters:
        merged.setdefault(f'transport.{parameter.name}', parameter.default)
    for parameter in drive_class_for(transport_class).settings:
        merged.setdefault(f'drive.{parameter.name}', parameter.default)
    return merged


def serving_drive_class(profile: Profile, transport_class: type,
                        transport_type: str) -> type[Drive]:
    """Return the drive class for the transport; ParameterError if the profile lacks its map.

    A profile names the transports its manual documents (``transports``); a drive
    class drives the ones whose map it reads (``profile_transports``; a plugin's class
    without it is trusted). A CANopen-only profile on a serial line would otherwise
    go out as register reads of no register map.
    """
    drive_class = drive_class_for(transport_class)
    served = getattr(drive_class, 'profile_transports', None)
    if served is not None and not set(served) & set(profile.transports):
        raise ParameterError(
            f'profile {profile.name} is for {", ".join(profile.transports)}, not '
            f'{transport_type}: it has no map for {drive_class.__name__} '
            f'({", ".join(served)})')
    return drive_class


def link_settings(values: Mapping[str, Any]) -> dict[str, Any]:
    """Return a drive's ``transport.*`` settings (unprefixed), its factory link values filled."""
    merged = with_defaults(values)
    profile = load_profile(str(merged['drive.profile']))
    transport_type = str(merged['transport.type'])
    drive_class = serving_drive_class(profile, load_transport_class(transport_type),
                                      transport_type)
    return drive_class.link_settings(profile, prefixed(merged, 'transport'))


def build_transport(values: Mapping[str, Any]) -> Transport:
    """Build the transport of a drive's (or a bus's) settings; raises VfdError."""
    merged = with_defaults(values)
    return load_transport_class(str(merged['transport.type'])).from_settings(
        link_settings(merged))


def build_controller(values: Mapping[str, Any],
                     transport: Transport | None = None) -> DriveController:
    """Build profile + transport + drive + controller from flat settings; raises VfdError.

    With ``transport`` given (several drives on one bus) the drive shares it and
    leaves opening and closing the port to the bus.
    """
    merged = with_defaults(values)
    profile = load_profile(str(merged['drive.profile']))
    shared = transport is not None
    if transport is None:
        transport = build_transport(merged)
    drive_class = serving_drive_class(profile, type(transport), str(merged['transport.type']))
    scaling = velocity_scaling(profile, merged)
    drive = drive_class(profile, transport, int(merged['transport.unit_id']),
                        scaling, prefixed(merged, 'drive'), owns_transport=not shared)
    controller = DriveController(drive, controller_config(merged))
    controller.joint = JointTracker(joint_config(
        profile, scaling, float(merged['position.counts_per_rev']),
        float(merged['motor.rated_torque'])))
    controller.plan_host_loss()     # alone on its link; a bus re-plans for all its drives
    return controller
