"""Drive families as data: the YAML files here, their schema, and the loader.

``load_profile('boneng_am')`` returns a frozen ``Profile``; ``python -m
vfd_ros2.profiles`` checks every shipped file. The data format is in README.md
next to this file, its machine form in schema.json.
"""

from .faults import NO_FAULT, FaultInfo, describe_fault
from .loader import PROFILE_DIR, available_profiles, load_profile, load_profile_file
from .model import *  # noqa: F401,F403 - the dataclasses and enums are this package's API
from .model import __all__ as _model_names

__all__ = ['NO_FAULT', 'PROFILE_DIR', 'FaultInfo', 'available_profiles', 'describe_fault',
           'load_profile', 'load_profile_file', *_model_names]
