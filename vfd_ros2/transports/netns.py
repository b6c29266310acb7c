"""Network namespaces and veth pairs for test segments, and sockets opened inside them.

An emulated EtherCAT segment needs two Ethernet ends: the master's and the
simulated slaves'. ``create_veth_link`` makes a fresh namespace holding both
ends of a veth pair (names unique per call, so concurrent runs never collide),
with IPv6 disabled and no address configured, so that nothing but the frames
the test sends ever appears on them and nothing leaves the namespace.

Python 3.11 has no ``os.setns``: ``run_in_namespace`` calls setns(2) through
ctypes on a short-lived thread (namespace membership is per thread), runs a
callable there and returns its result. A socket keeps the namespace it was
created in, so ``open_packet_socket`` / SOEM's ``Master.open`` run that way
work from any thread afterwards.

Needs root (CAP_SYS_ADMIN for setns, CAP_NET_ADMIN for links) and iproute2.
"""

from __future__ import annotations

import ctypes
import os
import secrets
import shutil
import socket
import subprocess
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, TypeVar

from ..errors import TransportError
from ..protocol.ethercat import ETHERTYPE_ETHERCAT

CLONE_NEWNET = 0x40000000
NETNS_DIR = Path('/run/netns')
#: every namespace this module creates starts with this (cleanup can find leftovers)
NAMESPACE_PREFIX = 'vfdec-'

T = TypeVar('T')

_libc = ctypes.CDLL(None, use_errno=True)


class NamespaceError(TransportError):
    """A namespace or veth link could not be created, entered or removed."""


@dataclass(frozen=True)
class VethLink:
    """A namespace with both ends of a veth pair: the master's end and the slaves' end."""

    namespace: str
    master_interface: str
    slave_interface: str


def namespace_support() -> str | None:
    """Return why namespaces cannot be used here, or None if they can."""
    if os.geteuid() != 0:
        return 'not root: network namespaces and raw sockets need CAP_SYS_ADMIN/CAP_NET_ADMIN'
    if shutil.which('ip') is None:
        return 'iproute2 (the ip command) is not installed'
    if not hasattr(_libc, 'setns'):
        return 'the C library has no setns()'
    return None


def _ip(*args: str, timeout: float = 10.0) -> None:
    result = subprocess.run(['ip', *args], capture_output=True, text=True, timeout=timeout)
    if result.returncode != 0:
        raise NamespaceError(f'ip {" ".join(args)} failed: {result.stderr.strip()}')


def run_in_namespace(namespace: str, function: Callable[..., T], *args: Any,
                     timeout: float = 10.0) -> T:
    """Call ``function(*args)`` on a thread that has entered ``namespace``; return its result."""
    path = NETNS_DIR / namespace
    outcome: dict[str, Any] = {}

    def body() -> None:
        try:
            fd = os.open(path, os.O_RDONLY | os.O_CLOEXEC)
        except OSError as exc:
            outcome['error'] = NamespaceError(f'cannot open namespace {namespace}: {exc}')
            return
        try:
            if _libc.setns(fd, CLONE_NEWNET) != 0:
                errno = ctypes.get_errno()
                outcome['error'] = NamespaceError(
                    f'setns({namespace}) failed: {os.strerror(errno)}')
                return
            outcome['result'] = function(*args)
        except BaseException as exc:  # noqa: BLE001 - handed to the calling thread
            outcome['error'] = exc
        finally:
            os.close(fd)

    # the thread ends after the call, so no thread of this process stays in the namespace
    thread = threading.Thread(target=body, name=f'netns-{namespace}', daemon=True)
    thread.start()
    thread.join(timeout)
    if thread.is_alive():
        raise NamespaceError(f'call in namespace {namespace} did not return within {timeout} s')
    if 'error' in outcome:
        raise outcome['error']
    return outcome['result']


def open_packet_socket(interface: str, namespace: str | None = None,
                       protocol: int = ETHERTYPE_ETHERCAT) -> socket.socket:
    """Open a raw AF_PACKET socket on ``interface`` (in ``namespace``) for one EtherType."""
    def make() -> socket.socket:
        sock = socket.socket(socket.AF_PACKET, socket.SOCK_RAW, socket.htons(protocol))
        try:
            sock.bind((interface, protocol))
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 20)
        except OSError:
            sock.close()
            raise
        return sock

    try:
        return run_in_namespace(namespace, make) if namespace else make()
    except OSError as exc:
        raise NamespaceError(f'cannot open a packet socket on {interface}: {exc}') from exc


def _write_sysctl(path: str, value: str) -> None:
    with open(path, 'w', encoding='ascii') as handle:
        handle.write(value)


def create_veth_link(tag: str = '') -> VethLink:
    """Create a namespace with a veth pair in it, both ends up, IPv6 off; return their names."""
    reason = namespace_support()
    if reason:
        raise NamespaceError(reason)
    token = secrets.token_hex(3)
    namespace = f'{NAMESPACE_PREFIX}{tag + "-" if tag else ""}{os.getpid()}-{token}'
    link = VethLink(namespace, f'ecm{token}', f'ecs{token}')   # interface names <= 15 chars
    _ip('netns', 'add', namespace)
    try:
        # /proc/sys/net belongs to the namespace of whoever opens it: set the defaults
        # inside, before the links exist, so they never carry an IPv6 link-local address
        for name in ('all', 'default'):
            run_in_namespace(namespace, _write_sysctl,
                             f'/proc/sys/net/ipv6/conf/{name}/disable_ipv6', '1')
        _ip('-n', namespace, 'link', 'add', link.master_interface, 'type', 'veth', 'peer',
            'name', link.slave_interface)
        for interface in (link.master_interface, link.slave_interface):
            _ip('-n', namespace, 'link', 'set', 'dev', interface, 'up')
    except BaseException:
        destroy_veth_link(link)
        raise
    return link


def set_link_state(link: VethLink, up: bool, interface: str | None = None) -> None:
    """Take an end of the pair (the slaves' end by default) down or up."""
    _ip('-n', link.namespace, 'link', 'set', 'dev', interface or link.slave_interface,
        'up' if up else 'down')


def destroy_veth_link(link: VethLink) -> None:
    """Delete the namespace (its veth pair goes with it); no error if already gone."""
    if (NETNS_DIR / link.namespace).exists():
        _ip('netns', 'delete', link.namespace)


def leftover_namespaces() -> list[str]:
    """Namespaces this module created that still exist (e.g. after a killed test run)."""
    if not NETNS_DIR.exists():
        return []
    return sorted(p.name for p in NETNS_DIR.iterdir() if p.name.startswith(NAMESPACE_PREFIX))
