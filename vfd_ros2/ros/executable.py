"""What every executable's main() does: the Jazzy spin and shutdown idiom, once.

Executables spin on rclpy's ``EventsExecutor`` (``rclpy.experimental``, in the
Jazzy wheels): the ``SingleThreadedExecutor`` rebuilds its wait set from every
entity of every node on each wake-up, which was most of a ``bus_node``'s CPU
(a drive node has a subscription, timers and a dozen services). The events
executor is driven by ``spin_once`` in a loop: its ``spin()`` runs in C++ without
ever releasing the GIL, which starves the drives' control threads.
``VFD_ROS2_EXECUTOR=single`` selects the previous executor (benchmarks compare).
"""

from __future__ import annotations

import gc
import logging
import os
import signal
import sys
import threading
import traceback
from contextlib import contextmanager
from typing import Callable, Iterable, Iterator

import rclpy
from rclpy.context import Context
from rclpy.exceptions import NameValidationException, ParameterException
from rclpy.executors import Executor, ExternalShutdownException, SingleThreadedExecutor
from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
from rclpy.impl.rcutils_logger import RcutilsLogger
from rclpy.node import Node
from rclpy.utilities import remove_ros_args

from ..errors import ParameterError, VfdError

#: start-up errors reported in one line (bad configuration), not as a traceback
CONFIGURATION_ERRORS = (VfdError, ParameterException, NameValidationException, ValueError)


def run_node(name: str, make_node: Callable[[], Node], args: list[str] | None = None,
             extra_nodes: Callable[[Node], Iterable[Node]] = lambda node: (),
             cleanup: str = 'the drives are stopped first') -> int:
    """Create the node, spin it (and the nodes it owns) until Ctrl-C / SIGTERM, clean up.

    ``destroy_node`` runs on every exit path, so a drive is commanded to stop
    before its port closes. ``cleanup`` says what the shutdown does, to a second
    Ctrl-C. Returns the process exit code.
    """
    # A control thread woken by a reply waits for the GIL until the thread holding it
    # lets go: after the switch interval (5 ms by default) when the executor is busy
    # with callbacks. That wait went into every transaction of a 32-drive bus.
    sys.setswitchinterval(GIL_SWITCH_INTERVAL)
    with interrupts_through_rclpy(name, cleanup) as interrupts:
        return _run_node(name, make_node, args, extra_nodes, interrupts)


def _run_node(name: str, make_node: Callable[[], Node], args: list[str] | None,
              extra_nodes: Callable[[Node], Iterable[Node]],
              interrupts: Interrupts | None) -> int:
    try:
        rclpy.init(args=args)
    except _rclpy.RCLError as exc:      # e.g. a --params-file that does not parse
        print(f'{name}: cannot start (check --ros-args and --params-file): {exc}')
        return 1
    if interrupts is not None and interrupts.interrupted:
        rclpy.try_shutdown()        # (Ctrl-C before rclpy's handler was there to take it)
        return 0
    node = executor = None
    bridge = RosLogBridge()
    try:
        node = make_node()
        bridge.attach(node)
        executor = make_executor()
        for each in (node, *extra_nodes(node)):
            executor.add_node(each)
        settle_heap()
        spin_until_shutdown(executor, node.context)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except Exception as exc:
        if rclpy.ok():
            if isinstance(exc, CONFIGURATION_ERRORS):
                print(f'{name}: {exc}')
                return 1
            raise
        # Ctrl-C or SIGTERM while the node was being built: rclpy's handler shut the
        # context down under it, and what it was building refused to go on (one line,
        # not a traceback: a bug would still be seen).
        print(f'{name}: while shutting down: {exc!r}', file=sys.stderr)
    finally:
        # The executor lets go of the nodes first: it must not be waiting on entities
        # that are being destroyed (the events executor raises then).
        if executor is not None:
            executor.shutdown(timeout_sec=1.0)
        if node is not None:
            node.destroy_node()
        bridge.remove()
        rclpy.try_shutdown()
    return 0


class Interrupts:
    """Ctrl-C for an executable: the first ends the spin through rclpy only, quietly.

    rclpy's SIGINT handler shuts the context down (the spin ends, run_node cleans
    up), then calls the handler that was there before it: Python's, which raised
    KeyboardInterrupt in the main thread wherever it was, often inside a timer's
    callback, which the events executor then logged as a FATAL "Exception in
    'timers' callback" (diff_drive: one exit in eight). This handler, installed
    before rclpy's, takes the first Ctrl-C quietly and ignores the others, with a
    word: a KeyboardInterrupt in the clean-up skipped the drives' stops (a double
    tap; a launcher that signals the processes its terminal already signalled), and
    the loop threads are daemons, killed with the interpreter. Every wait of the
    clean-up is bounded; SIGKILL is left for one that is not.
    """

    def __init__(self, name: str, cleanup: str = 'the drives are stopped first') -> None:
        self.name = name
        self.cleanup = cleanup
        self.interrupted = False
        self._told = False

    def __call__(self, _signal_number: int, _frame: object) -> None:
        if not self.interrupted:
            self.interrupted = True
        elif not self._told:
            self._told = True
            # (os.write: a print here could land inside the bridge's own stderr write)
            os.write(2, f'[WARN] [{self.name}]: shutting down: {self.cleanup}; '
                        'Ctrl-C again is ignored\n'.encode())


@contextmanager
def interrupts_through_rclpy(name: str, cleanup: str = 'the drives are stopped first'
                             ) -> Iterator[Interrupts | None]:
    """Handle SIGINT with ``Interrupts``; None in a thread, or if somebody chose a handler.

    Once interrupted, SIGINT is ignored after the clean-up: the interpreter's
    finalization resets a handler to the default, and a second Ctrl-C then (a
    double tap, or a launcher's SIGINT after its terminal's) made the exit status
    "killed by SIGINT", as a launch reports a crash.
    """
    previous = signal.getsignal(signal.SIGINT)
    if threading.current_thread() is not threading.main_thread() or \
            previous is not signal.default_int_handler:
        yield None
        return
    interrupts = Interrupts(name, cleanup)
    signal.signal(signal.SIGINT, interrupts)
    try:
        yield interrupts
    finally:
        signal.signal(signal.SIGINT, signal.SIG_IGN if interrupts.interrupted else previous)


class RosLogBridge(logging.Handler):
    """The driver's layers below ROS log with Python ``logging``; this hands it to ROS.

    Without it their records (a drive offline, a fault, a drive that does not stop)
    went to stderr unformatted, INFO not at all, and never to /rosout (rqt_console,
    a robot's log recorder). They go to the node's logger, at their level. Installed
    before the node is made: a plain node's loop starts in its constructor and logs
    its first connect at once; those records wait (``HELD_RECORDS`` at most) until
    ``attach`` names the node, or go to stderr if no node comes. Once Ctrl-C or
    SIGTERM has shut the node's context down (a drive's last words as its loop
    ends), they go to stderr in the console's form: ROS logging would add a
    "Failed to publish log message to rosout" line to each.
    """

    #: records kept until the node exists (a start-up's connect attempts and notes)
    HELD_RECORDS = 200

    def __init__(self, logger_name: str = 'vfd_ros2') -> None:
        super().__init__(logging.INFO)
        self._log: RcutilsLogger | None = None
        self._context: Context | None = None
        self._held: list[logging.LogRecord] = []
        self._python_logger = logging.getLogger(logger_name)
        self._kept = (self._python_logger.level, self._python_logger.propagate)
        self._python_logger.addHandler(self)
        self._python_logger.setLevel(logging.INFO)
        self._python_logger.propagate = False   # (else also Python's last-resort stderr)

    def attach(self, node: Node) -> None:
        """Send the records to ``node``'s logger from now on, those held first."""
        with self.lock:             # (emit runs under it, from any thread)
            self._log = node.get_logger()
            self._context = node.context
            held, self._held = self._held, []
            for record in held:
                self._to_ros(record)

    def emit(self, record: logging.LogRecord) -> None:
        try:
            if self._log is None:
                if len(self._held) < self.HELD_RECORDS:
                    self._held.append(record)
                return
            self._to_ros(record)
        except Exception:  # noqa: BLE001 - logging must never raise into a control thread
            self.handleError(record)

    def _to_ros(self, record: logging.LogRecord) -> None:
        message = record.getMessage()
        if record.exc_info:
            message += '\n' + ''.join(traceback.format_exception(*record.exc_info))
        level, log = record.levelno, self._log
        if not self._context.ok():
            # (rcutils' severities are Python's levels: --log-level still applies)
            if level >= int(log.get_effective_level()):
                print(f'[{ros_level_name(record)}] [{log.name}]: {message}', file=sys.stderr,
                      flush=True)
        elif level >= logging.CRITICAL:
            log.fatal(message)
        elif level >= logging.ERROR:
            log.error(message)
        elif level >= logging.WARNING:
            log.warning(message)
        elif level >= logging.INFO:
            log.info(message)
        else:
            log.debug(message)

    def remove(self) -> None:
        """Stop bridging (the node goes): Python logging as it was; held records to stderr."""
        with self.lock:
            held, self._held = self._held, []
        for record in held:
            print(f'[{ros_level_name(record)}] {record.getMessage()}', file=sys.stderr)
        self._python_logger.removeHandler(self)
        self._python_logger.setLevel(self._kept[0])
        self._python_logger.propagate = self._kept[1]


#: Python's level names as ROS's console shows them
ROS_LEVEL_NAMES = {'WARNING': 'WARN', 'CRITICAL': 'FATAL'}


def ros_level_name(record: logging.LogRecord) -> str:
    return ROS_LEVEL_NAMES.get(record.levelname, record.levelname)


def non_ros_arguments(args: list[str] | None) -> list[str]:
    """Return the command line's arguments but the program and the ROS ones."""
    return (remove_ros_args(args) if args is not None else remove_ros_args())[1:]


def only_ros_arguments(args: list[str] | None) -> None:
    """Refuse command-line arguments other than ROS ones (ParameterError, one line).

    A node without options of its own would start as if they were not there: a
    ``--managed`` meant for a drive node would give a plain node without a word.
    """
    unknown = non_ros_arguments(args)
    if unknown:
        raise ParameterError(f'unknown argument(s) {" ".join(unknown)}: this node takes ROS '
                             'arguments only (after --ros-args)')


def settle_heap() -> None:
    """Take what start-up built out of every later garbage collection (``gc.freeze``).

    A full collection holds the GIL for as long as it walks every container object:
    a CANopen bus_node's ~62 000 (rclpy, the profiles, the python-can and canopen
    modules) took 62 ms, 15 cycles of a 250 Hz bus, and one came unasked seconds
    after start-up. Frozen, the same collection walks only what was made since
    (0.6 ms measured). One collection first, so no garbage is kept for good.
    """
    gc.collect()
    gc.freeze()


#: seconds a thread may hold the GIL while another waits for it (Python's default: 0.005).
#: 0.1 ms: a 32-drive bus at 115200 reached ~3 points more of the wire's limit than at
#: 0.5 ms (fleet bench, both priorities), at the same CPU.
GIL_SWITCH_INTERVAL = 0.0001

#: the environment variable naming the executor (``events`` or ``single``)
EXECUTOR_VARIABLE = 'VFD_ROS2_EXECUTOR'


def make_executor(context: Context | None = None) -> Executor:
    """Return the executor to spin: events, unless ``VFD_ROS2_EXECUTOR=single``."""
    choice = os.environ.get(EXECUTOR_VARIABLE, 'events')
    if choice == 'single':
        return SingleThreadedExecutor(context=context)
    if choice != 'events':
        raise ValueError(f'{EXECUTOR_VARIABLE}={choice!r}: expected events or single')
    from rclpy.experimental import EventsExecutor
    return EventsExecutor(context=context)


def spin_until_shutdown(executor: Executor, context: Context) -> None:
    """Spin until Ctrl-C / SIGTERM shuts ``context`` down, the GIL released between events."""
    while context.ok():
        executor.spin_once(timeout_sec=IDLE_SPIN_TIMEOUT)


#: seconds an idle executor waits before checking the context again. A shutdown wakes
#: it at once (both executors wait on it), so this only sets how often an idle node
#: wakes for nothing: at 0.1 s that was ~0.1-0.2 % of a core for a parked drive_node.
IDLE_SPIN_TIMEOUT = 1.0


class BackgroundSpin(threading.Thread):
    """A thread spinning an executor until its context shuts down or ``stop()``."""

    def __init__(self, executor: Executor, context: Context) -> None:
        super().__init__(name='rclpy spin', daemon=True)
        self._executor, self._context = executor, context
        self._stopped = threading.Event()

    def run(self) -> None:
        while self._context.ok() and not self._stopped.is_set():
            try:
                self._executor.spin_once(timeout_sec=0.05)
            except Exception:  # noqa: BLE001 - the context shut down under us
                if not self._context.ok() or self._stopped.is_set():
                    return
                raise

    def stop(self, timeout: float = 2.0) -> None:
        """Stop spinning and wait: then nodes can leave the executor and be destroyed."""
        self._stopped.set()
        if self.is_alive() and self is not threading.current_thread():
            self.join(timeout)


def spin_in_background(executor: Executor, context: Context) -> BackgroundSpin:
    """Spin ``executor`` in a daemon thread until ``context`` shuts down (tests, tools).

    Call ``stop()`` before destroying the executor's nodes: an executor must not
    be waiting on entities that are being destroyed.
    """
    thread = BackgroundSpin(executor, context)
    thread.start()
    return thread
