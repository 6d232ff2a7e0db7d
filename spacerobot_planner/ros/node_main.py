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


def command_line_parameters(argv) -> dict:
    """
    Return the ``-p NAME:=VALUE`` (``--param``) of ``--ros-args`` sections that name no node: {NAME: text}.

    A later one of a name replaces an earlier one, as rcl applies them; ``-p node:NAME:=VALUE``
    (one node's) are left out.
    """
    given, inside, k = {}, False, 0
    argv = list(argv or ())
    while k < len(argv):
        arg = argv[k]
        if arg == "--ros-args":
            inside = True
        elif arg == "--":
            inside = False
        elif inside and arg in ("-p", "--param") and k + 1 < len(argv):
            k += 1
            name, sep, value = argv[k].partition(":=")
            if sep and ":" not in name:
                given[name] = value
        k += 1
    return given


def not_taken(node: Node, given: dict) -> list:
    """
    Say which command-line ``-p`` (``given``: :func:`command_line_parameters`) ``node`` does not hold.

    A parameter file's section for a node (``/**/spacerobot_planner``, ``/**/mock_arm``) wins over a
    ``-p`` that names no node, wherever it comes (rcl's rule: a node's own values over the
    wildcard's), so ``--params-file config/paper_3dof.yaml -p grid.cells:=[72,72,72]`` starts with the
    file's cells, silently.  One line per declared parameter whose value is not the one given
    (read as rcl reads it: YAML), naming the two ways that work.
    """
    import yaml
    lines = []
    for name, text in given.items():
        if not node.has_parameter(name):
            continue
        try:
            want = yaml.safe_load(text)
        except yaml.YAMLError:
            continue
        have = node.get_parameter(name).value
        if isinstance(have, (list, tuple)) or type(have).__name__ == "array":
            have = list(have)
        if have != want:
            lines.append(f"-p {name}:={text} was not taken ({name} is {have}): this node's section of the "
                         f"parameter file sets it and wins over a -p that names no node (ROS 2's rule); give "
                         f"-p {node.get_name()}:{name}:={text}, or set it now: ros2 param set "
                         f"{node.get_fully_qualified_name()} {name} {text}")
    return lines


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
            for line in not_taken(node, command_line_parameters(sys.argv if args is None else args)):
                node.get_logger().warning(line)
            # from now on a signal asks the spin loop to stop
            signal.signal(signal.SIGTERM, request_stop)
            if signal.getsignal(signal.SIGINT) is signal.default_int_handler:     # not ignored
                signal.signal(signal.SIGINT, request_stop)
            spin_until_shutdown(node, NodeExecutor(),
                                None if on_shutdown is None else (lambda: on_shutdown(node)), stop)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    return 0
