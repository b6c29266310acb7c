"""Shared helpers of the unit tests: cached shipped profiles, an in-memory transport."""

from __future__ import annotations

import functools
from typing import Any, Mapping

from vfd_ros2.profiles import Profile, load_profile
from vfd_ros2.transports.base import RegisterTransport


@functools.lru_cache(maxsize=None)
def shipped_profile(name: str) -> Profile:
    """Load a shipped profile once per test session (parsing the tables takes ~0.5 s)."""
    return load_profile(name)


class MemoryTransport(RegisterTransport):
    """Registers in a dict; records every request; no I/O."""

    def __init__(self) -> None:
        super().__init__()
        self.registers: dict[int, int] = {}
        self.requests: list[tuple[str, int, int, Any]] = []
        self.is_open = False

    @classmethod
    def from_settings(cls, settings: Mapping[str, Any]) -> MemoryTransport:
        return cls()

    @property
    def description(self) -> str:
        return 'memory'

    def open(self) -> None:
        self.is_open = True

    def close(self) -> None:
        self.is_open = False

    def read_registers(self, unit: int, address: int, count: int) -> list[int]:
        self.count(unit, 'transactions')
        self.requests.append(('read', unit, address, count))
        return [self.registers.get(address + i, 0) for i in range(count)]

    def write_register(self, unit: int, address: int, value: int) -> None:
        self.count(unit, 'transactions')
        self.requests.append(('write', unit, address, value))
        self.registers[address] = value

    def write_registers(self, unit: int, address: int, values: list[int]) -> None:
        self.count(unit, 'transactions')
        self.requests.append(('write_many', unit, address, list(values)))
        for offset, value in enumerate(values):
            self.registers[address + offset] = value

    def writes_to(self, address: int) -> list[int]:
        """Every value written to ``address``, in order."""
        values = []
        for kind, _unit, start, data in self.requests:
            if kind == 'write' and start == address:
                values.append(data)
            elif kind == 'write_many' and start <= address < start + len(data):
                values.append(data[address - start])
        return values
