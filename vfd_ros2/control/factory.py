"""The composition root: flat settings -> profile + transport + drive + controller.

The only place that knows every layer: it loads the profile, picks the
transport plugin and the drive class that serves it, fills the drive's factory
link values into the transport settings, and wires a ``DriveController``.
``bus.py`` builds several on one shared transport.
"""

from __future__ import annotations

from typing import Any, Mapping

from ..drives import drive_class_for
from ..profiles import load_profile
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


def build_transport(values: Mapping[str, Any]) -> Transport:
    """Build the transport of a drive's (or a bus's) settings; raises VfdError."""
    merged = with_defaults(values)
    profile = load_profile(str(merged['drive.profile']))
    transport_class = load_transport_class(str(merged['transport.type']))
    settings = drive_class_for(transport_class).link_settings(
        profile, prefixed(merged, 'transport'))
    return transport_class.from_settings(settings)


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
    drive_class = drive_class_for(type(transport))
    scaling = velocity_scaling(profile, merged)
    drive = drive_class(profile, transport, int(merged['transport.unit_id']),
                        scaling, prefixed(merged, 'drive'), owns_transport=not shared)
    controller = DriveController(drive, controller_config(merged))
    controller.joint = JointTracker(joint_config(
        profile, scaling, float(merged['position.counts_per_rev']),
        float(merged['motor.rated_torque'])))
    controller.plan_host_loss()     # alone on its link; a bus re-plans for all its drives
    return controller
