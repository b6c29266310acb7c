"""What every executable's main() does: the Jazzy spin and shutdown idiom, once."""

from __future__ import annotations

from typing import Callable, Iterable

import rclpy
from rclpy.exceptions import ParameterException
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node

from .errors import VfdError

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
