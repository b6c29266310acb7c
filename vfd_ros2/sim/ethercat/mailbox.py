"""The slave's mailbox: header codec, protocol dispatch and the send queue.

Mailbox header (ETG.1000.6 table 29, 6 bytes little endian): length of the
service data (2), address (2), channel (6 bits) + priority (2), type (4 bits)
+ counter (3 bits) + reserved (1). The counter runs 1..7 (0 = unused); a
request that repeats the previous counter is a retry of a lost reply and is
not executed twice (ETG.1000.6 5.6.1). Replies are queued: the ESC moves the
next one into the SM1 buffer whenever the master has read the last one.
"""

from __future__ import annotations

import collections
import struct
from dataclasses import dataclass
from typing import Callable

from ...protocol.ethercat import MailboxErrorCode, MailboxType

HEADER = struct.Struct('<HHBB')
HEADER_SIZE = HEADER.size
MAILBOX_ERROR_SERVICE = 0x0001


@dataclass(frozen=True)
class MailboxHeader:
    length: int
    address: int
    channel: int
    priority: int
    type: int
    counter: int


class MailboxFormatError(ValueError):
    """A mailbox buffer too short for its header or its announced length."""


def decode_mailbox(buffer: bytes) -> tuple[MailboxHeader, bytes]:
    """Split a mailbox buffer into header and service data."""
    if len(buffer) < HEADER_SIZE:
        raise MailboxFormatError(f'{len(buffer)} bytes is too short for a mailbox header')
    length, address, channel_priority, type_counter = HEADER.unpack_from(buffer)
    if HEADER_SIZE + length > len(buffer):
        raise MailboxFormatError(f'mailbox header announces {length} bytes, '
                                 f'{len(buffer) - HEADER_SIZE} present')
    header = MailboxHeader(length, address, channel_priority & 0x3F, channel_priority >> 6,
                           type_counter & 0x0F, (type_counter >> 4) & 0x07)
    return header, bytes(buffer[HEADER_SIZE:HEADER_SIZE + length])


def encode_mailbox(kind: int, data: bytes, counter: int, address: int = 0, channel: int = 0,
                   priority: int = 0) -> bytes:
    """Return a mailbox message: header + service data."""
    return HEADER.pack(len(data), address, (channel & 0x3F) | (priority & 0x03) << 6,
                       (kind & 0x0F) | (counter & 0x07) << 4) + data


def next_counter(counter: int) -> int:
    """Mailbox counter sequence 1, 2, ..., 7, 1, ... (0 is never used by a sender)."""
    return 1 if counter >= 7 else counter + 1


#: a protocol handler: service data in -> service data of the replies (same protocol)
Handler = Callable[[bytes], list[bytes]]


class MailboxServer:
    """Receives SM0 mailbox writes, dispatches them, and queues replies for SM1."""

    def __init__(self, out_size: int, handlers: dict[int, Handler]) -> None:
        self.out_size = out_size
        self.handlers = handlers
        self._queue: collections.deque[bytes] = collections.deque()
        self._counter_out = 0
        self._last_counter_in = 0
        self.received = 0
        self.repeats_ignored = 0

    def reset(self) -> None:
        """Forget queued replies and counters (the slave left PRE-OP/SAFE-OP/OP for INIT)."""
        self._queue.clear()
        self._counter_out = 0
        self._last_counter_in = 0

    def post(self, kind: int, data: bytes) -> None:
        """Queue a message for the master (e.g. a CoE emergency), with the next counter."""
        self._counter_out = next_counter(self._counter_out)
        message = encode_mailbox(kind, data, self._counter_out)
        if len(message) > self.out_size:
            raise ValueError(f'mailbox message of {len(message)} bytes exceeds the '
                             f'{self.out_size}-byte SM1 buffer')
        self._queue.append(message)

    def pending(self) -> int:
        return len(self._queue)

    def pop(self) -> bytes | None:
        """Next message for the SM1 buffer, or None."""
        return self._queue.popleft() if self._queue else None

    def receive(self, buffer: bytes) -> None:
        """Handle one complete SM0 buffer from the master."""
        self.received += 1
        try:
            header, data = decode_mailbox(buffer)
        except MailboxFormatError:
            self._error(MailboxErrorCode.INVALID_HEADER)
            return
        if header.counter and header.counter == self._last_counter_in:
            self.repeats_ignored += 1        # a retry: the reply is already queued or sent
            return
        self._last_counter_in = header.counter
        if header.length < 2:
            self._error(MailboxErrorCode.SIZE_TOO_SHORT)
            return
        handler = self.handlers.get(header.type)
        if handler is None:
            self._error(MailboxErrorCode.UNSUPPORTED_PROTOCOL)
            return
        for reply in handler(data):
            self.post(header.type, reply)

    def _error(self, code: MailboxErrorCode) -> None:
        self.post(MailboxType.ERROR, struct.pack('<HH', MAILBOX_ERROR_SERVICE, code))
