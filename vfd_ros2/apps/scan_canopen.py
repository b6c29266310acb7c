"""vfd_scan on a CAN bus: listen for heartbeats and boot-ups, then read 0x1000 / 0x1018 by SDO.

Kept apart on purpose: it talks to the ``canopen`` library directly (a
``canopen.Network`` on a python-can bus: its notifier, ``subscribe`` and
``send_message``), not through ``vfd_ros2.transports.canopen``, so the scan does
not depend on how the driver's CANopen transport is built. It only listens and
reads: no NMT command, no SDO download. The SDO reads are expedited uploads
sent and matched here (``_Uploader``), not the library's ``SdoClient``: that
client answers its own timeout with an SDO abort frame to the silent id and
retries, which a scan of 127 ids must not put on a running bus. Only the text of
``--can-options`` goes through the transport's ``parse_can_options`` (what the
scan accepts, the bus file it writes must accept too), and the network is the
transport's ``quick_closing_network``.

1. Listen ``listen`` seconds on 0x701-0x77F: a boot-up (state 0) or a heartbeat
   (its NMT state) names a node.
2. With ``sdo_probe`` every other id in ``ids`` is asked too (SDO upload of 0x1000:00,
   one per id, timeout ``sdo_timeout``, no retry): nodes whose heartbeat is off
   (0x1017 = 0, a common factory setting) are found that way.
3. Each node found: 0x1000:00 (device type; bits 0-15 = device profile, 402 =
   drive) and 0x1018:01-04 (vendor id, product code, revision, serial number),
   matched against the profiles' ``identify.canopen`` data.
"""

from __future__ import annotations

import queue
import threading
import time
from typing import Any, Mapping, Sequence

from ..drives.identify import Identification
from ..profiles import Profile
from ..transports.canopen import parse_can_options, quick_closing_network
from .scan import Budget, Found, Progress, ScanError, ScanReport

#: NMT state byte of a heartbeat -> name (CiA 301 7.2.8.3.2.3); 0 = boot-up
NMT_STATES = {0: 'boot-up', 4: 'stopped', 5: 'operational', 0x7F: 'pre-operational'}

#: CiA 301 identity object 0x1018 sub-indices
IDENTITY = {1: 'vendor', 2: 'product', 3: 'revision', 4: 'serial'}


def _open(text: str, bitrate: int, extra: Mapping[str, Any]) -> tuple[Any, str]:
    interface, _, channel = text.partition(':')
    if not interface or not channel:
        raise ScanError(f'bad CAN bus {text!r}: use INTERFACE:CHANNEL, e.g. socketcan:can0')
    network = quick_closing_network()
    options: dict[str, Any] = {**extra, 'interface': interface, 'channel': channel}
    if bitrate:
        options['bitrate'] = bitrate
    try:
        network.connect(**options)
    except Exception as exc:  # noqa: BLE001 - python-can raises many kinds (CanError, OSError)
        raise ScanError(f'cannot open CAN bus {text}: {exc}') from exc
    return network, f'{interface}:{channel}'


class _Uploader:
    """Expedited SDO uploads (CiA 301 7.2.4.3.6) on one network, one at a time."""

    def __init__(self, network: Any, timeout: float) -> None:
        self.network = network
        self.timeout = timeout
        self.replies: queue.Queue[tuple[int, bytes]] = queue.Queue()

    def on_reply(self, can_id: int, data: bytearray, _timestamp: float) -> None:
        self.replies.put((can_id - 0x580, bytes(data)))

    def upload(self, node_id: int, index: int, subindex: int) -> int | str:
        """Return the value read (little-endian, unsigned), or why not (abort code, silence)."""
        request = bytes((0x40, index & 0xFF, index >> 8, subindex, 0, 0, 0, 0))
        while not self.replies.empty():
            self.replies.get_nowait()          # a late reply of an earlier id
        self.network.send_message(0x600 + node_id, request)
        deadline = time.monotonic() + self.timeout
        while (remaining := deadline - time.monotonic()) > 0:
            try:
                source, data = self.replies.get(timeout=remaining)
            except queue.Empty:
                break
            if source != node_id or len(data) < 8 or data[1:4] != request[1:4]:
                continue                       # another node's, or another object's
            command = data[0]
            if command == 0x80:
                return f'abort 0x{int.from_bytes(data[4:8], "little"):08X}'
            if command & 0xE3 == 0x43:         # expedited upload, size indicated
                size = 4 - ((command >> 2) & 0x3)
                return int.from_bytes(data[4:4 + size], 'little')
            if command & 0xE3 == 0x42:         # expedited, size not indicated
                return int.from_bytes(data[4:8], 'little')
            return f'not an expedited reply (command 0x{command:02X})'
        return 'no answer'


def _guess(profiles: Sequence[Profile], device_type: int | str,
           identity: dict[str, int | str]) -> Identification:
    if not isinstance(device_type, int):
        return Identification(evidence=f'0x1000 {device_type}')
    evidence = f'0x1000 = 0x{device_type:08X} (device profile {device_type & 0xFFFF})'
    matches = []
    for profile in profiles:
        spec = profile.identify.canopen if profile.identify else None
        if spec is None or 'canopen' not in profile.transports:
            continue
        if spec.device_profile is not None and spec.device_profile != device_type & 0xFFFF:
            continue
        if spec.vendor_id is not None and spec.vendor_id != identity.get('vendor'):
            continue
        if spec.product_code is not None and spec.product_code != identity.get('product'):
            continue
        named = spec.vendor_id is not None or spec.product_code is not None
        matches.append((profile.name, 'high' if named else 'medium'))
    # CANopen families whose manuals print no identity cannot be told from these values.
    silent = [p.name for p in profiles if 'canopen' in p.transports and
              not (p.identify and p.identify.canopen)]
    unknown = (f'{", ".join(silent)}: no 0x1000/0x1018 values documented, not told apart',) \
        if silent else ()
    if not matches:
        return Identification(evidence=evidence,
                              notes=('no profile documents this identity', *unknown))
    matches.sort(key=lambda m: m[1] != 'high')
    best = [m for m in matches if m[1] == matches[0][1]]
    notes = (f'the identity fits {", ".join(m[0] for m in best)} alike',) if len(best) > 1 else ()
    return Identification(profile=matches[0][0], confidence='low' if notes else matches[0][1],
                          alternatives=tuple(m[0] for m in matches[1:]), evidence=evidence,
                          notes=notes + unknown)


def scan_canopen(text: str, profiles: Sequence[Profile], ids: Sequence[int], budget: Budget,
                 progress: Progress, listen: float = 2.0, sdo_probe: bool = False,
                 bitrate: int = 0, sdo_timeout: float = 0.1,
                 can_options: str = '') -> ScanReport:
    """Find the CANopen nodes on one bus (see the module docstring).

    ``can_options``: extra ``can.Bus`` arguments, a JSON object as in
    ``transport.can_options`` (validated the same way; the bus file keeps them).
    """
    report = ScanReport()
    network, link = _open(text, bitrate, parse_can_options(can_options))
    link_settings = tuple((key, value) for key, value in (
        ('transport.bitrate', bitrate), ('transport.can_options', can_options)) if value)
    heard: dict[int, str] = {}
    lock = threading.Lock()

    def on_heartbeat(can_id: int, data: bytearray, _timestamp: float) -> None:
        if data:
            with lock:
                heard.setdefault(can_id - 0x700, NMT_STATES.get(data[0] & 0x7F,
                                                                f'state 0x{data[0]:02X}'))
    uploader = _Uploader(network, sdo_timeout)
    try:
        for node_id in range(1, 128):
            network.subscribe(0x700 + node_id, on_heartbeat)
            network.subscribe(0x580 + node_id, uploader.on_reply)
        progress(f'{link}: listening {listen:g} s for heartbeats and boot-ups')
        deadline = time.monotonic() + listen
        while time.monotonic() < deadline and not budget.exhausted:
            time.sleep(0.02)
        with lock:
            nodes = dict(heard)
        progress(f'{link}: heard {sorted(nodes) or "no node"}')
        candidates = sorted(nodes) + ([i for i in ids if i not in nodes] if sdo_probe else [])
        for node_id in candidates:
            if reason := budget.exhausted:
                report.skipped.append(f'{link}: {reason} at node {node_id}')
                break
            budget.requests += 1
            device_type = uploader.upload(node_id, 0x1000, 0)
            if node_id not in nodes:
                if device_type == 'no answer':
                    continue
                nodes[node_id] = 'answered the SDO probe (no heartbeat heard)'
            identity: dict[str, int | str] = {}
            for sub, name in IDENTITY.items():
                budget.requests += 1
                identity[name] = uploader.upload(node_id, 0x1018, sub)
                if not isinstance(identity[name], int):
                    break              # no 0x1018 (or not this sub-index): stop asking
            identification = _guess(profiles, device_type, identity)
            shown = ' '.join(f'{k}=0x{v:08X}' if isinstance(v, int) else f'0x1018 {k}: {v}'
                             for k, v in identity.items())
            state = nodes[node_id]
            report.found.append(Found(
                'canopen', link, node_id, identification,
                identity=' '.join(p for p in (identification.evidence, shown) if p),
                link_settings=link_settings,
                notes=(f'NMT {state}' if state in NMT_STATES.values() else state,
                       *identification.notes)))
            progress(f'{link}: node {node_id}: {identification.profile or "unknown"} '
                     f'({identification.confidence})')
    finally:
        network.disconnect()
    return report
