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

import re
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


def _ros_args(argv):
    """Yield (option, its value) of ``argv``'s ``--ros-args`` sections: ``-p``/``--param``, ``--params-file``."""
    argv, inside, k = list(argv or ()), False, 0
    while k < len(argv):
        arg = argv[k]
        if arg == "--ros-args":
            inside = True
        elif arg == "--":
            inside = False
        elif inside and arg in ("-p", "--param", "--params-file") and k + 1 < len(argv):
            k += 1
            yield ("--params-file" if arg == "--params-file" else "-p"), argv[k]
        k += 1


def command_line_parameters(argv) -> dict:
    """
    Return the ``-p NAME:=VALUE`` (``--param``) of ``--ros-args`` sections that name no node: {NAME: text}.

    A later one of a name replaces an earlier one, as rcl applies them; ``-p node:NAME:=VALUE``
    (one node's) are left out.
    """
    given = {}
    for option, value in _ros_args(argv):
        name, sep, text = value.partition(":=")
        if option == "-p" and sep and ":" not in name:
            given[name] = text
    return given


def _section_matches(key: str, fqn: str) -> bool:
    """Tell whether a parameter file's section ``key`` is ``fqn``'s own (not ``/**``): rcl's ``/**`` and ``/*``."""
    key = key if key.startswith("/") else "/" + key
    if key in ("/**", "/*"):
        return False
    pattern = "".join("(/[^/]+)*" if part == "**" else "/[^/]+" if part == "*" else "/" + re.escape(part)
                      for part in key.strip("/").split("/"))
    return re.fullmatch(pattern, fqn) is not None


def _flat(doc: dict, prefix: str = "") -> dict:
    out = {}
    for k, v in doc.items():
        if isinstance(v, dict):
            out.update(_flat(v, f"{prefix}{k}."))
        else:
            out[f"{prefix}{k}"] = v
    return out


def _file_sections(path: str):
    """Yield (section key, {NAME: value}) of a parameter file (nothing where it cannot be read)."""
    import yaml
    try:
        with open(path, encoding="utf-8") as f:
            doc = yaml.safe_load(f) or {}
    except (OSError, yaml.YAMLError):
        return
    for key, body in (doc.items() if isinstance(doc, dict) else ()):
        if isinstance(key, str) and isinstance(body, dict):
            yield key, _flat(body.get("ros__parameters") or {})


def files_node_sections(argv, fqn: str) -> dict:
    """Return what the ``--params-file`` of ``argv`` set in sections of node ``fqn`` (not ``/**``): {NAME: value}."""
    found = {}
    for option, path in _ros_args(argv):
        if option == "--params-file":
            for key, params in _file_sections(path):
                if _section_matches(key, fqn):
                    found.update(params)
    return found


def set_for_every_node_after(argv) -> set:
    """
    Return the names a ``--params-file``'s ``/**`` section sets after the last ``-p NAME`` of ``argv``.

    rcl applies ``-p`` and the files' sections for every node in their order, so such a file's
    value wins over the ``-p`` before it (``-p`` that name a node left out, as
    :func:`command_line_parameters`).
    """
    events = list(_ros_args(argv))
    last = {}
    for k, (option, value) in enumerate(events):
        name, sep, _ = value.partition(":=")
        if option == "-p" and sep and ":" not in name:
            last[name] = k
    after = set()
    for k, (option, path) in enumerate(events):
        if option == "--params-file":
            for key, params in _file_sections(path):
                if (key if key.startswith("/") else "/" + key) in ("/**", "/*"):
                    after.update(name for name in params if last.get(name, k) < k)
    return after


def _same(have, text: str) -> bool:
    """Tell whether a parameter's value ``have`` is what ``-p NAME:=text`` gives (YAML, numbers as rcl reads them)."""
    import yaml
    try:
        want = yaml.safe_load(text)
    except yaml.YAMLError:
        return False
    if isinstance(have, (list, tuple)) or type(have).__name__ == "array":
        have = list(have)
    if isinstance(want, str) and isinstance(have, (int, float)) and not isinstance(have, bool):
        try:
            want = float(text)
        except ValueError:
            return False
    return have == want


def not_taken(node: Node, given: dict, argv=()) -> list:
    """
    Say which command-line ``-p`` (``given``: :func:`command_line_parameters`) ``node`` does not hold.

    A parameter file's section for a node (``/**/spacerobot_planner``, ``/**/mock_arm``) wins over a
    ``-p`` that names no node, wherever it comes (rcl's rule: a node's own values over the
    wildcard's), so ``--params-file config/paper_3dof.yaml -p grid.cells:=[72,72,72]`` starts with the
    file's cells, silently.  One line for each ``-p`` whose name such a section of a
    ``--params-file`` of ``argv`` sets and whose value the node does not hold, naming the ways that
    work (``-p NODE:NAME:=VALUE`` only in the root namespace: rcl takes no namespace there).  So
    too where a ``--params-file`` given after the ``-p`` sets the name for every node (``/**``: rcl
    applies those in order, :func:`set_for_every_node_after`).
    """
    fqn = node.get_fully_qualified_name()
    sections = files_node_sections(argv, fqn)
    later = set_for_every_node_after(argv)
    lines = []
    for name, text in given.items():
        if (name not in sections and name not in later) or not node.has_parameter(name):
            continue
        have = node.get_parameter(name).value
        if _same(have, text):
            continue
        shown = list(have) if type(have).__name__ == "array" else have
        if name in sections:
            hint = f"-p {node.get_name()}:{name}:={text}, or " if node.get_namespace() == "/" else ""
            lines.append(f"-p {name}:={text} was not taken ({name} is {shown}): this node's section of the "
                         f"parameter file sets it and wins over a -p that names no node (ROS 2's rule); give "
                         f"{hint}set it now: ros2 param set {fqn} {name} {text}")
        else:
            lines.append(f"-p {name}:={text} was not taken ({name} is {shown}): a --params-file given after it "
                         f"sets it for every node (/**), and ROS 2 applies those in order; give the -p after the "
                         f"file, or set it now: ros2 param set {fqn} {name} {text}")
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
            argv = sys.argv if args is None else args
            for line in not_taken(node, command_line_parameters(argv), argv):
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
