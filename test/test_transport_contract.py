"""One contract, every register transport: the built-in links and a third-party plugin.

What the drive layer relies on, whatever the link: built from its declared
settings alone; open idempotent, close idempotent and silent; a write reads back;
each good exchange counted once, for the link and for its unit; a silent peer is
a CommTimeout within the timeout (never a hang); a refusal is a ProtocolException
with the wire code; a peer that vanishes is a TransportError.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any, Callable

import pytest

from unit_support import shipped_profile
from vfd_ros2.errors import CommTimeout, ProtocolException, TransportError
from vfd_ros2.sim.model import SimulatedDrive
from vfd_ros2.sim.rtu_line import SimulatedRtuLine
from vfd_ros2.sim.tcp_server import SimulatedTcpServer
from vfd_ros2.transports import RegisterTransport, load_transport_class
from vfd_ros2.transports.modbus import PymodbusRtuTransport

TIMEOUT = 0.1


@dataclass
class Link:
    """A transport under test and the far end it talks to."""

    transport: RegisterTransport
    register: int                          # a writable register of unit 1
    refused: int | None = None             # a register the peer refuses (None: no peer)
    silence: Callable[[bool], None] | None = None
    vanish: Callable[[], None] | None = None
    closers: list[Callable[[], None]] = field(default_factory=list)


def _sim(profile: str) -> SimulatedDrive:
    drive = SimulatedDrive(shipped_profile(profile), 1)
    drive.refuse(['A00.15'] if profile == 'boneng_am' else ['P00.06'])
    return drive


def rtu_link(tmp_path, transport_class: type) -> Link:
    drive = _sim('boneng_am')
    line = SimulatedRtuLine([drive], tmp_path / 'line').start()
    settings = {p.name: p.default for p in transport_class.parameters}
    settings.update(port=str(tmp_path / 'line'), baudrate=115200, parity='N', stopbits=1,
                    timeout=TIMEOUT)
    transport = transport_class.from_settings(settings)
    profile = drive.profile
    return Link(transport, profile.parameter('B04.02').address,
                refused=profile.parameter('A00.15').address,
                silence=lambda on: setattr(drive, 'silent', on), vanish=line.stop,
                closers=[transport.close, line.stop])


def tcp_link(tmp_path) -> Link:
    drive = _sim('imo_hd2')
    server = SimulatedTcpServer([drive]).start()
    cls = load_transport_class('modbus_tcp')
    settings = {p.name: p.default for p in cls.parameters}
    settings.update(host='127.0.0.1', port=server.port, timeout=TIMEOUT)
    transport = cls.from_settings(settings)
    profile = drive.profile
    return Link(transport, profile.parameter('0x2001').address,
                refused=profile.parameter('P00.06').address,
                silence=lambda on: setattr(drive, 'silent', on), vanish=server.stop,
                closers=[transport.close, server.stop])


def plugin_link(tmp_path, plugin: Any) -> Link:
    cls = load_transport_class('loopback')        # the third-party plugin (test_transports)
    transport = cls.from_settings({p.name: p.default for p in cls.parameters})
    return Link(transport, 0x0100, closers=[transport.close])


LINKS: dict[str, Callable[..., Link]] = {
    'modbus_rtu': lambda tmp_path, plugin: rtu_link(
        tmp_path, load_transport_class('modbus_rtu')),
    'pymodbus_rtu': lambda tmp_path, plugin: rtu_link(tmp_path, PymodbusRtuTransport),
    'modbus_tcp': lambda tmp_path, plugin: tcp_link(tmp_path),
    'loopback_plugin': plugin_link,
}


@pytest.fixture(params=sorted(LINKS))
def link(request, tmp_path):
    plugin = request.getfixturevalue('plugin') if request.param == 'loopback_plugin' else None
    made = LINKS[request.param](tmp_path, plugin)
    yield made
    for close in made.closers:
        close()


def test_built_from_its_declared_settings(link):
    assert isinstance(link.transport, RegisterTransport)
    assert isinstance(link.transport.description, str) and link.transport.description


def test_open_and_close_are_idempotent(link):
    transport = link.transport
    transport.close()                   # before any open: no error
    transport.open()
    transport.open()
    transport.close()
    transport.close()
    with transport as same:             # the context manager opens and closes
        assert same is transport
        assert transport.read_registers(1, link.register, 1) is not None


def test_writes_read_back_and_each_exchange_counts_once(link):
    transport = link.transport
    transport.open()
    before, unit_before = transport.stats.transactions, transport.stats_for(1).transactions
    transport.write_register(1, link.register, 12)
    assert transport.read_registers(1, link.register, 1) == [12]
    transport.write_registers(1, link.register, [13])
    assert transport.read_registers(1, link.register, 1) == [13]
    assert transport.stats.transactions - before == 4
    assert transport.stats_for(1).transactions - unit_before == 4
    assert transport.stats_for(2).transactions == 0


def test_a_silent_peer_is_a_timeout_within_the_timeout(link):
    if link.silence is None:
        pytest.skip('an in-memory plugin has no peer to fall silent')
    transport = link.transport
    transport.open()
    link.silence(True)
    start = time.monotonic()
    with pytest.raises(CommTimeout):
        transport.read_registers(1, link.register, 1)
    assert time.monotonic() - start < TIMEOUT + 0.5
    assert transport.stats_for(1).timeouts == 1
    link.silence(False)
    deadline = time.monotonic() + 2.0          # the late-reply guard may hold the unit a while
    while True:
        try:
            assert transport.read_registers(1, link.register, 1) is not None
            break
        except CommTimeout:
            assert time.monotonic() < deadline, 'the link did not recover'


def test_a_refusal_is_a_protocol_exception_with_the_wire_code(link):
    if link.refused is None:
        pytest.skip('an in-memory plugin has no peer to refuse')
    link.transport.open()
    with pytest.raises(ProtocolException) as info:
        link.transport.read_registers(1, link.refused, 1)
    assert info.value.code == 2 and not isinstance(info.value, TransportError)
    assert link.transport.stats_for(1).exceptions == 1


def test_a_vanished_peer_is_a_transport_error_not_a_hang(link):
    if link.vanish is None:
        pytest.skip('an in-memory plugin has no peer to vanish')
    transport = link.transport
    transport.open()
    link.vanish()
    start = time.monotonic()
    with pytest.raises(TransportError):
        for _ in range(3):        # the first may still be answered from a buffer
            transport.read_registers(1, link.register, 1)
    assert time.monotonic() - start < 3 * (TIMEOUT + 0.5)
