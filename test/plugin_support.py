"""A third-party transport plugin, installed as a distribution into tmp_path (fixture)."""

from __future__ import annotations

import sys
import textwrap
from pathlib import Path

import pytest

from vfd_ros2.transports import ENTRY_POINT_GROUP

PLUGIN_SOURCE = """
# A tiny in-memory register transport, shipped as a separate distribution.
from vfd_ros2.transports.base import RegisterTransport, TransportParameter


class LoopbackTransport(RegisterTransport):
    parameters = (TransportParameter('size', 65536, 'number of registers'),)

    def __init__(self):
        super().__init__()
        self.registers = {}
        self.requests = []
        self.is_open = False

    @classmethod
    def from_settings(cls, settings):
        return cls()

    @property
    def description(self):
        return 'loopback'

    def open(self):
        self.is_open = True

    def close(self):
        self.is_open = False

    def read_registers(self, unit, address, count):
        self.count(unit, 'transactions')
        self.requests.append(('read', unit, address, count))
        return [self.registers.get(address + i, 0) for i in range(count)]

    def write_register(self, unit, address, value):
        self.count(unit, 'transactions')
        self.requests.append(('write', unit, address, value))
        self.registers[address] = value

    def write_registers(self, unit, address, values):
        self.count(unit, 'transactions')
        self.requests.append(('write_many', unit, address, list(values)))
        for offset, value in enumerate(values):
            self.registers[address + offset] = value


class NotATransport:
    pass  # has the right shape of name, but is not a RegisterTransport


not_even_a_class = 42
"""

ENTRY_POINTS = f"""\
[{ENTRY_POINT_GROUP}]
loopback = fake_vfd_plugin:LoopbackTransport
not_a_transport = fake_vfd_plugin:NotATransport
not_a_class = fake_vfd_plugin:not_even_a_class
missing_class = fake_vfd_plugin:NoSuchTransport
broken_import = fake_vfd_broken:Transport
explodes_on_import = fake_vfd_explodes:Transport
modbus_rtu = fake_vfd_plugin:NotATransport
"""

PLUGIN_MODULES = ('fake_vfd_plugin', 'fake_vfd_broken', 'fake_vfd_explodes')


@pytest.fixture
def plugin(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """Install the fake distribution: a dist-info folder plus its modules, on sys.path."""
    dist_info = tmp_path / 'fake_vfd_plugin-0.1.dist-info'
    dist_info.mkdir()
    (dist_info / 'METADATA').write_text(
        'Metadata-Version: 2.1\nName: fake-vfd-plugin\nVersion: 0.1\n', encoding='utf-8')
    (dist_info / 'entry_points.txt').write_text(ENTRY_POINTS, encoding='utf-8')
    (tmp_path / 'fake_vfd_plugin.py').write_text(textwrap.dedent(PLUGIN_SOURCE),
                                                 encoding='utf-8')
    (tmp_path / 'fake_vfd_broken.py').write_text(
        'import vfd_ros2_dependency_that_is_not_installed  # noqa: F401\n', encoding='utf-8')
    (tmp_path / 'fake_vfd_explodes.py').write_text(
        "raise RuntimeError('plugin initialisation failed')\n", encoding='utf-8')
    for module in PLUGIN_MODULES:
        monkeypatch.delitem(sys.modules, module, raising=False)
    monkeypatch.syspath_prepend(str(tmp_path))
    yield tmp_path
    for module in PLUGIN_MODULES:
        sys.modules.pop(module, None)
