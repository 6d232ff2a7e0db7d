"""The executables' shared main: create a node, spin it, shut down cleanly on Ctrl-C.

In rclpy 9 (Kilted) Ctrl-C makes ``spin`` raise ``ExternalShutdownException`` as well
as ``KeyboardInterrupt``; both end the spin quietly (no traceback under ``ros2 run``).
"""
from __future__ import annotations

from typing import Callable

import rclpy
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node


def spin_until_shutdown(node: Node, executor, on_shutdown: Callable[[], None] | None = None) -> None:
    """Spin ``node`` on ``executor`` until Ctrl-C or its context shuts down; then call
    ``on_shutdown`` (if given), shut the executor down and destroy the node."""
    executor.add_node(node)
    try:
        executor.spin()
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        if on_shutdown is not None:
            on_shutdown()
        executor.shutdown()
        node.destroy_node()


def run_node(make_node: Callable[[], Node], exe_name: str, args=None,
             on_shutdown: Callable[[Node], None] | None = None) -> int:
    """``rclpy.init``, ``make_node()``, spin in a SingleThreadedExecutor until Ctrl-C.

    A ValueError from ``make_node`` (bad parameters) is printed as
    ``<exe_name>: <reason>`` and gives exit code 1; otherwise 0.
    """
    try:
        with rclpy.init(args=args):
            try:
                node = make_node()
            except ValueError as e:
                print(f"{exe_name}: {e}")
                return 1
            spin_until_shutdown(node, SingleThreadedExecutor(),
                                None if on_shutdown is None else (lambda: on_shutdown(node)))
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    return 0
