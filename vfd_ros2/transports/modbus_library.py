"""The pymodbus version this package needs, checked once, before pymodbus is used.

Every module that imports pymodbus imports this one first (``# isort: split``),
so an old pymodbus fails at import with what to install instead of an
``ImportError`` about a missing name. Debian bookworm ships 3.0, Ubuntu noble
3.6: neither has ``FramerType``, ``DecodePDU``, ``FramerRTU`` or
``pymodbus.pdu.register_message`` (all present from 3.8.0, checked against the
v3.8.0 sources; tested with the version pinned in requirements.txt). On a ROS
machine the rosdep key ``python3-pymodbus-pip`` installs it from PyPI.
"""

from __future__ import annotations

import re

MINIMUM = (3, 8)


def version_problem(version: str) -> str:
    """Return why ``version`` of pymodbus cannot serve this package ('' if it can)."""
    match = re.match(r'(\d+)\.(\d+)', version)
    if match is None:
        return f'pymodbus version {version!r} is not understood'
    if (int(match.group(1)), int(match.group(2))) < MINIMUM:
        return f'pymodbus {version} is too old'
    return ''


def require_pymodbus() -> None:
    """Raise ImportError naming the version needed if pymodbus is missing or too old."""
    needed = f'vfd_ros2 needs pymodbus >= {MINIMUM[0]}.{MINIMUM[1]}'
    fix = ('install it with pip (pip install "pymodbus>=3.8"), or on ROS with rosdep '
           '(key python3-pymodbus-pip)')
    try:
        import pymodbus
    except ImportError as exc:
        raise ImportError(f'{needed}: it is not installed; {fix}') from exc
    problem = version_problem(str(getattr(pymodbus, '__version__', '?')))
    if problem:
        raise ImportError(f'{needed} (FramerType, DecodePDU, FramerRTU, '
                          f'pdu.register_message): {problem} ({pymodbus.__file__}); {fix}')


require_pymodbus()
