"""What every executable's main() does: the Jazzy spin and shutdown idiom, once."""

from __future__ import annotations

import threading
from typing import Callable, Iterable

import rclpy
from rclpy.context import Context
from rclpy.exceptions import ParameterException
from rclpy.executors import Executor, ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node

from ..errors import VfdError

#: start-up errors reported in one line (bad configuration), not as a traceback
CONFIGURATION_ERRORS = (VfdError, ParameterException, ValueError)


def run_node(name: str, make_node: Callable[[], Node], args: list[str] | None = None,
             extra_nodes: Callable[[Node], Iterable[Node]] = lambda node: ()) -> int:
    """Create the node, spin it (and the nodes it owns) until Ctrl-C / SIGTERM, clean up.

    ``destroy_node`` runs on every exit path, so a drive is commanded to stop
    before its port closes. Returns the process exit code.
    """
    rclpy.init(args=args)
    node = None
    try:
        node = make_node()
        executor = SingleThreadedExecutor()
        for each in (node, *extra_nodes(node)):
            executor.add_node(each)
        executor.spin()
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except CONFIGURATION_ERRORS as exc:
        print(f'{name}: {exc}')
        return 1
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
    return 0


def spin_in_background(executor: Executor, context: Context) -> threading.Thread:
    """Spin ``executor`` in a daemon thread until ``context`` shuts down (tests, tools)."""
    def spin() -> None:
        while context.ok():
            try:
                executor.spin_once(timeout_sec=0.05)
            except Exception:  # noqa: BLE001 - the context shut down under us
                if not context.ok():
                    return
                raise
    thread = threading.Thread(target=spin, name='rclpy spin', daemon=True)
    thread.start()
    return thread
