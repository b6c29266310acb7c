"""Modbus RTU wire timing: character time, inter-frame gap, frame sizes.

Pure functions shared by the RTU transport (deadlines, the silence it keeps
before a request), the simulated line (when a reply may appear) and the
benchmark (the theoretical cycle rate). Rules from "Modbus over Serial Line
V1.02" section 2.5.1.1:

- a character is start + 8 data + parity + stop bits (11 bits in the spec's
  8E1 / 8N2 framing, 10 bits in 8N1);
- frames are separated by at least 3.5 character times of silence (t3.5);
  above 19200 baud the spec recommends the fixed value 1.750 ms (and 750 us
  for t1.5), because 3.5 characters become too short for slave firmware.
"""

from __future__ import annotations

#: the spec's fixed t3.5 above 19200 baud, in seconds
FIXED_GAP = 0.00175
FIXED_GAP_ABOVE_BAUD = 19200


def character_time(baudrate: int, parity: str = 'N', stopbits: int = 1,
                   bytesize: int = 8) -> float:
    """Seconds per character on the wire (start + data + parity + stop bits)."""
    return (1 + bytesize + (0 if parity.upper() == 'N' else 1) + stopbits) / baudrate


def frame_gap(baudrate: int, char_time: float) -> float:
    """Return t3.5, the silence between frames: 3.5 characters, 1.75 ms above 19200 baud."""
    return FIXED_GAP if baudrate > FIXED_GAP_ABOVE_BAUD else 3.5 * char_time


def reply_size(function_code: int, count: int = 1) -> int:
    """Bytes of a normal RTU reply (unit + function + data + CRC); exceptions are 5."""
    if function_code in (1, 2):
        return 5 + (count + 7) // 8
    if function_code in (3, 4):
        return 5 + 2 * count
    if function_code in (5, 6, 8, 15, 16):
        return 8
    raise ValueError(f'no fixed reply size for function {function_code}')


def transaction_time(request_bytes: int, reply_bytes: int, char_time: float,
                     gap: float) -> float:
    """Wire time of one request/reply pair plus the two t3.5 silences it needs.

    One silence separates the request from the reply (the slave detects the end
    of the request by it), the other the reply from the next request. The
    drive's own response delay is not included.
    """
    return (request_bytes + reply_bytes) * char_time + 2 * gap
