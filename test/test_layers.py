"""The package's layers are folders, and imports only point down (read from the source)."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / 'vfd_ros2'

#: layer -> the layers it may import (besides itself), lowest first in the README
ALLOWED: dict[str, set[str]] = {
    'errors': set(),
    'protocol': {'errors'},
    'profiles': {'errors', 'protocol'},
    'transports': {'errors', 'protocol'},
    'drives': {'errors', 'protocol', 'profiles', 'transports'},
    'control': {'errors', 'protocol', 'profiles', 'transports', 'drives'},
    'ros': {'errors', 'protocol', 'profiles', 'transports', 'drives', 'control', 'msg', 'srv'},
    # The simulated drives share the profiles and codecs (and the test-segment plumbing
    # of transports/netns.py); sim/node.py is a ROS node.
    'sim': {'errors', 'protocol', 'profiles', 'transports', 'ros', 'msg', 'srv'},
    'apps': {'errors', 'protocol', 'profiles', 'transports', 'drives', 'control', 'ros', 'sim',
             'msg', 'srv'},
}


def layer_of(path: Path) -> str:
    relative = path.relative_to(PACKAGE)
    return relative.parts[0] if len(relative.parts) > 1 else relative.stem


def imported_layers(path: Path) -> set[str]:
    """Layers of vfd_ros2 that ``path`` imports (absolute or relative imports)."""
    tree = ast.parse(path.read_text(encoding='utf-8'))
    package_parts = path.relative_to(PACKAGE.parent).with_suffix('').parts[:-1]
    layers = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package_parts[:len(package_parts) - node.level + 1]
                module = '.'.join(base + ((node.module,) if node.module else ()))
                names = [module] if node.module else [f'{module}.{a.name}' for a in node.names]
            else:
                names = [node.module or '']
        else:
            continue
        for name in names:
            parts = name.split('.')
            if parts[0] == 'vfd_ros2' and len(parts) > 1:
                layers.add(parts[1])
    return layers


def violations(root: Path = PACKAGE) -> list[str]:
    found = []
    for path in sorted(root.rglob('*.py')):
        layer = layer_of(path)
        if layer == '__init__':
            continue
        allowed = ALLOWED.get(layer)
        assert allowed is not None, f'{path}: not in a known layer (add it to ALLOWED)'
        for imported in imported_layers(path) - allowed - {layer}:
            found.append(f'{path.relative_to(root.parent)} ({layer}) imports {imported}')
    return found


def test_every_module_sits_in_a_layer_folder():
    top_level = sorted(p.name for p in PACKAGE.glob('*.py'))
    assert top_level == ['__init__.py', 'errors.py'], top_level


def test_no_module_imports_upward():
    assert violations() == []


@pytest.mark.parametrize('layer, source, upward', [
    ('transports', 'from ..profiles import Profile\n', 'profiles'),
    ('drives', 'from vfd_ros2.control.state import RunState\n', 'control'),
    ('protocol', 'import vfd_ros2.ros.messages\n', 'ros'),
    ('control', 'from ..sim.model import SimulatedDrive\n', 'sim'),
])
def test_the_checker_finds_an_upward_import(tmp_path, layer, source, upward):
    fake = tmp_path / 'vfd_ros2' / layer / 'offender.py'
    fake.parent.mkdir(parents=True)
    fake.write_text(source, encoding='utf-8')
    global PACKAGE
    saved, PACKAGE = PACKAGE, tmp_path / 'vfd_ros2'
    try:
        found = violations(PACKAGE)
    finally:
        PACKAGE = saved
    assert found == [f'vfd_ros2/{layer}/offender.py ({layer}) imports {upward}']
