"""package.xml installs on a ROS Jazzy apt machine: every key exists, pymodbus is new enough.

The keys were checked by hand against ros/rosdistro at commit
8468e88ccd523427f9131e39d2af0938f1c298b2 (2026-08-22):
https://github.com/ros/rosdistro/blob/8468e88ccd523427f9131e39d2af0938f1c298b2/rosdep/python.yaml
https://github.com/ros/rosdistro/blob/8468e88ccd523427f9131e39d2af0938f1c298b2/jazzy/distribution.yaml
A new dependency needs its key checked there and added below (no network in tests).
"""

from __future__ import annotations

import ast
import xml.etree.ElementTree as ElementTree
from pathlib import Path

import pytest

from vfd_ros2.transports.modbus_library import version_problem

ROOT = Path(__file__).resolve().parent.parent

#: system keys: rosdep/python.yaml at the commit above (none needed from base.yaml)
ROSDEP_KEYS = {
    'python3-yaml', 'python3-jsonschema', 'python3-serial', 'python3-can',
    'python3-pytest', 'python3-pytest-timeout',
    'python3-pymodbus-pip',  # pip: Debian/Ubuntu python3-pymodbus are 3.0-3.6 (too old)
    'canopen-pip',           # there is no python3-canopen key
    'python3-ruff-pip',      # there is no python3-ruff key
}
#: ROS packages released for Jazzy (jazzy/distribution.yaml at the commit above)
JAZZY_PACKAGES = {
    'ament_cmake', 'ament_cmake_python', 'ament_cmake_pytest', 'rosidl_default_generators',
    'rosidl_default_runtime', 'builtin_interfaces', 'std_msgs', 'std_srvs', 'rclpy',
    'rcl_interfaces', 'diagnostic_msgs', 'geometry_msgs', 'nav_msgs', 'sensor_msgs',
    'tf2_msgs', 'lifecycle_msgs', 'launch', 'launch_ros', 'ros2launch',
}
#: keys that must not be used: three do not exist although they look right (the
#: mistakes made before); python3-pymodbus exists but is the distributions' 3.0-3.6
NOT_KEYS = {'python3-canopen', 'python3-ruff', 'ruff-pip', 'python3-pymodbus'}
DEPENDENCY_TAGS = ('depend', 'build_depend', 'buildtool_depend', 'exec_depend',
                   'test_depend', 'build_export_depend')


def dependencies() -> dict[str, set[str]]:
    root = ElementTree.parse(ROOT / 'package.xml').getroot()
    return {tag: {element.text.strip() for element in root.findall(tag)}
            for tag in DEPENDENCY_TAGS}


def test_every_key_exists_in_rosdistro():
    declared = set().union(*dependencies().values())
    unknown = declared - ROSDEP_KEYS - JAZZY_PACKAGES
    assert not unknown, f'not a rosdep key or Jazzy package (check ros/rosdistro): {unknown}'
    assert not declared & NOT_KEYS


def test_test_tools_are_declared():
    """Colcon test runs the lint and the timeouts: their keys are test dependencies."""
    tests = dependencies()['test_depend']
    assert {'python3-pytest', 'python3-pytest-timeout', 'python3-ruff-pip',
            'ament_cmake_pytest'} <= tests


def test_every_imported_library_is_declared():
    """Third-party imports of vfd_ros2 map to a declared key (a missed one breaks apt)."""
    keys = {'yaml': 'python3-yaml', 'jsonschema': 'python3-jsonschema',
            'serial': 'python3-serial', 'pymodbus': 'python3-pymodbus-pip',
            'can': 'python3-can', 'canopen': 'canopen-pip', 'rclpy': 'rclpy',
            'lifecycle_msgs': 'lifecycle_msgs'}
    declared = set().union(*dependencies().values())
    for path in (ROOT / 'vfd_ros2').rglob('*.py'):
        for node in ast.walk(ast.parse(path.read_text(encoding='utf-8'))):
            names = [a.name for a in node.names] if isinstance(node, ast.Import) else \
                [node.module] if isinstance(node, ast.ImportFrom) and node.level == 0 and \
                node.module else []
            for name in names:
                key = keys.get(name.split('.')[0])
                assert key is None or key in declared, f'{path.name}: {name} needs {key}'


@pytest.mark.parametrize(('version', 'ok'), [
    ('3.0.0', False), ('3.6.9', False), ('3.7.4', False), ('3.8.0', True), ('3.16.1', True),
    ('4.0.0.dev1', True), ('banana', False)])
def test_pymodbus_version_floor(version, ok):
    assert (version_problem(version) == '') is ok


def test_every_pymodbus_import_comes_after_the_version_check():
    """An old pymodbus fails with the version needed, not with a missing name."""
    for path in (ROOT / 'vfd_ros2').rglob('*.py'):
        lines = path.read_text(encoding='utf-8').splitlines()
        first = next((i for i, line in enumerate(lines)
                      if line.startswith(('from pymodbus', 'import pymodbus'))), None)
        if first is None or path.name == 'modbus_library.py':
            continue
        check = next((i for i, line in enumerate(lines) if 'import modbus_library' in line),
                     None)
        assert check is not None and check < first, f'{path}: import modbus_library first'
