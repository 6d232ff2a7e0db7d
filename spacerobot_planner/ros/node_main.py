"""
The executables' shared main: create a node, spin it, shut down cleanly on Ctrl-C.

rclpy's own SIGINT handler shuts the context down at once, so whatever the node logs
while it stops (a plan being cancelled) fails to reach rosout and rcl prints "Failed to
publish log message to rosout", and its clients get no answers.  So ``run_node`` installs
its own: Ctrl-C (and SIGTERM) only ask the spin loop to stop (a KeyboardInterrupt could
land inside any callback or coroutine step, e.g. an action goal's, which then never
sends its result); the node shuts down while the context still works, then the context
goes.  A context shut down from elsewhere makes ``spin`` raise
``ExternalShutdownException``; both end the spin quietly (no traceback under ``ros2 run``).
A process that starts with SIGINT ignored (a background job of a script) keeps it ignored.
"""
from __future__ import annotations

from typing import Callable

import signal
import sys
import threading

import rclpy
from rclpy.exceptions import ParameterException
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node

from .executor import NodeExecutor


#: the longest the main thread waits in rcl before it sees a Ctrl-C, seconds
SPIN_WAKE_S = 0.1


def spin_until_shutdown(node: Node, executor, on_shutdown: Callable[[], None] | None = None,
                        stop: threading.Event | None = None) -> None:
    """
    Spin ``node`` on ``executor`` until ``stop`` is set (Ctrl-C), Ctrl-C or its context shuts down.

    Then call ``on_shutdown`` (if given), shut the executor down and destroy the node.
    """
    executor.add_node(node)
    try:
        # not executor.spin(): a Python signal handler runs only between bytecodes, and
        # spin() can wait in rcl for as long as nothing happens (up to the diagnostics
        # period), so Ctrl-C would wait that long; this wakes every SPIN_WAKE_S
        ctx = executor.context
        while ctx.ok() and not (stop is not None and stop.is_set()):
            executor.spin_once(timeout_sec=SPIN_WAKE_S)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        if on_shutdown is not None:
            on_shutdown()
        executor.shutdown()
        node.destroy_node()


def run_node(make_node: Callable[[], Node], exe_name: str, args=None,
             on_shutdown: Callable[[Node], None] | None = None) -> int:
    """
    ``rclpy.init``, ``make_node()``, spin in a :class:`.executor.NodeExecutor` until Ctrl-C.

    A refused start (a ValueError or RuntimeError from ``make_node``: bad parameters, a
    failed autostart; or rclpy's own parameter exceptions) is printed as one line
    ``<exe_name>: <reason>`` on stderr, without a traceback, and gives exit code 1;
    otherwise 0.
    """
    stop = threading.Event()

    def interrupt(signum, frame):
        raise KeyboardInterrupt

    def request_stop(signum, frame):
        stop.set()

    signal.signal(signal.SIGTERM, interrupt)          # while the node starts: stop at once
    try:
        try:
            init = rclpy.init(args=args, signal_handler_options=rclpy.signals.SignalHandlerOptions.NO)
        except RuntimeError as e:     # rcl refused the arguments: a params file that does not parse, a bad rule
            print(f"{exe_name}: {e}", file=sys.stderr, flush=True)
            return 1
        with init:
            try:
                node = make_node()
            except (ValueError, RuntimeError, ParameterException) as e:
                print(f"{exe_name}: {e}", file=sys.stderr, flush=True)
                return 1
            # from now on a signal asks the spin loop to stop
            signal.signal(signal.SIGTERM, request_stop)
            if signal.getsignal(signal.SIGINT) is signal.default_int_handler:     # not ignored
                signal.signal(signal.SIGINT, request_stop)
            spin_until_shutdown(node, NodeExecutor(),
                                None if on_shutdown is None else (lambda: on_shutdown(node)), stop)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    return 0
