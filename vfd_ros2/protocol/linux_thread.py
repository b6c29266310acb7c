"""What a timing-sensitive thread asks Linux for (``prctl``): timer slack, a name.

Used by the RTU master and the simulated line (their waits are a few byte times
long) and by the control loops. On other systems, or where libc is not found,
these do nothing.
"""

from __future__ import annotations

import ctypes
import functools

_PR_SET_NAME = 15
_PR_SET_TIMERSLACK = 29


@functools.cache
def _libc() -> ctypes.CDLL | None:
    # The process's own symbols, not ctypes.util.find_library('c'): that runs
    # ldconfig in a child process, and a fork while another thread holds a
    # serial port open hands the child the port's exclusive lock until its exec
    # (a reopen in that moment fails with "Could not exclusively lock port").
    try:
        return ctypes.CDLL(None, use_errno=True)
    except OSError:
        return None


def _prctl(option: int, argument: int | bytes) -> None:
    libc = _libc()
    try:
        if libc is not None:
            libc.prctl(option, argument, 0, 0, 0)
    except AttributeError:          # no prctl: not Linux
        pass


def tighten_timer_slack() -> None:
    """Let the calling thread's sleeps end within ~1 us of their deadline.

    The default timer slack (50 us) would be added to every timed wait of the
    RTU master (t3.5) and of the simulated line (byte times); at 115200 baud a
    whole transaction is ~5 ms.
    """
    _prctl(_PR_SET_TIMERSLACK, 1000)


def name_os_thread(name: str) -> None:
    """Name the calling thread for the OS (``top -H``, ``ps -L``; 15 bytes on Linux).

    Python 3.11 names threads only for itself: without this, a driver's control
    thread shows up as one more ``python3`` next to the executor's.
    """
    _prctl(_PR_SET_NAME, name.encode(errors='replace')[:15])
