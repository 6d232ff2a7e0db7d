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

from ..config import PARAMETERS, flatten_params, section_regex
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
            yield key, flatten_params(body.get("ros__parameters") or {})


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


def _param_key(arg: str) -> tuple:
    """Return (section key, NAME) of a ``-p``: ``NAME:=V`` is ``/**``'s, ``NODE:NAME:=V`` ``/NODE``'s (None: no :=)."""
    name, sep, _ = arg.partition(":=")
    if not sep:
        return None, None
    node, _, param = name.rpartition(":")
    return ("/" + node.lstrip("/") if node else "/**"), param


def parameter_sections(argv) -> list:
    """
    Return the parameter overrides of ``argv``'s ``--ros-args`` in the order rclpy applies them.

    [(section key, {NAME: origin})]: a ``-p NAME:=VALUE`` is section ``/**``'s, a ``-p
    NODE:NAME:=VALUE`` section ``/NODE``'s, a ``--params-file``'s sections their own; a section
    sits where its key first appears, a later value of a name in it replaces the earlier one.
    rclpy gives a node the sections that match it (``config.section_regex``) in that order, so the
    last one with a name wins: a file's own section for the node after its ``/**`` section beats a
    ``-p NAME:=VALUE`` wherever it comes, and a ``/**`` section of a later file one before it.
    origin: ("-p", the argument's text) or ("--params-file", the path, the section's key as written).
    """
    sections = {}
    for option, value in _ros_args(argv):
        if option == "-p":
            key, param = _param_key(value)
            if key is not None:
                sections.setdefault(key, {})[param] = ("-p", value)
        else:
            for key, params in _file_sections(value):
                section = sections.setdefault(key if key.startswith("/") else "/" + key, {})
                section.update({name: ("--params-file", value, key) for name in params})
    return list(sections.items())


def not_taken(node: Node, argv=()) -> list:
    """
    Say which command-line ``-p`` for ``node`` it does not hold: one line each, and the ways that work.

    rclpy applies the parameter sections that match a node in the order their keys first appear
    (:func:`parameter_sections`): ``--params-file config/paper_3dof.yaml -p grid.cells:=[72,72,72]``
    starts with the file's cells, silently, its section for the node coming after its ``/**``
    section, which the ``-p`` joins; so does a ``-p`` before a file that sets the name, a
    ``-p NODE:NAME:=VALUE`` too.  For each ``-p`` of a section that applies to the node, whose
    name a later section sets and whose value the node does not hold: a line naming what set it,
    ``-p NODE:NAME:=VALUE`` after the file (in the root namespace only: rcl takes no namespace
    there) and ``ros2 param set``.  A ``-p NODE:NAME:=VALUE`` naming this node's name while the node
    runs in a namespace applies to nothing (rcl matches it to ``/NODE``): a line saying so, and
    what works there.
    """
    fqn = node.get_fully_qualified_name()
    winner = {}
    for key, params in parameter_sections(argv):
        if section_regex(key).fullmatch(fqn):
            winner.update(params)
    given = {}                  # (section key, NAME) -> the last -p of it, of a section for this node
    for option, value in _ros_args(argv):
        key, param = _param_key(value) if option == "-p" else (None, None)
        if key is not None and section_regex(key).fullmatch(fqn):
            given[(key, param)] = ("-p", value)
        elif key == "/" + node.get_name() and fqn != key:
            given[(key, param)] = ("-p", value, "namespace")
    lines = []
    for (_, name), origin in given.items():
        text = origin[1].partition(":=")[2]
        if origin[2:] == ("namespace",):
            lines.append(f"-p {origin[1]} was not taken: it names the node /{node.get_name()} in the root namespace, "
                         f"and this node is {fqn} (ROS 2 matches a -p's node name in the root namespace only); "
                         f"set it now: ros2 param set {fqn} {name} {text}, or give it in a parameter file's section "
                         f"for {fqn} (or /**/{node.get_name()}) after the others")
            continue
        won = winner[name]
        if won == origin or not node.has_parameter(name) or _same(node.get_parameter(name).value, text):
            continue
        have = node.get_parameter(name).value
        shown = list(have) if type(have).__name__ == "array" else have
        by = (f"the parameter file {won[1]} sets it in its section {won[2]}" if won[0] == "--params-file"
              else f"-p {won[1]} sets it")
        hint = (f"give -p {node.get_name()}:{name}:={text} after the parameter file, or "
                if node.get_namespace() == "/" else "")
        lines.append(f"-p {origin[1]} was not taken ({name} is {shown}): {by}, and ROS 2 applies the parameter "
                     f"sections that match a node in the order they first appear on the command line (a -p that "
                     f"names no node is the /** section's); {hint}set it now: ros2 param set {fqn} {name} {text}")
    return lines


def file_problems(node: Node, argv=()) -> tuple:
    """
    Return (refusal or None, warnings) for the parameter files of ``argv`` as they apply to ``node``.

    A scenario file must state the robot (``config.PARAMETERS``' ``required_in_file`` names, those
    the node declares): where a ``--params-file`` applies to the node and none of the files nor a
    ``-p`` for it states one of them, the node would plan with the default robot (the paper's
    3-DOF arm) for a file that means another one (a key misspelled, left out): the refusal names
    them.  Without a file that applies, the defaults are the documented ones.  A file none of whose
    sections applies to the node (a section named for another node) is a warning: it sets nothing.
    """
    fqn = node.get_fully_qualified_name()
    applying, stated = set(), set()
    for key, params in parameter_sections(argv):
        if section_regex(key).fullmatch(fqn):
            stated.update(params)
            applying.update(origin[1] for origin in params.values() if origin[0] == "--params-file")
    # each file's sections, read once: (key, {NAME: value}) in file order
    files = {value: list(_file_sections(value)) for option, value in _ros_args(argv) if option == "--params-file"}
    warnings = []
    for path, sections in files.items():
        if path not in applying:
            keys = [key for key, _ in sections]
            warnings.append(f"the parameter file {path} sets nothing for {fqn}: none of its sections "
                            f"({', '.join(keys) or 'none'}) matches the node (/**, /**/{node.get_name()}, "
                            f"{fqn}); where no file applies, the node runs with the defaults of docs/parameters.md")
    required = [s.name for s in PARAMETERS if s.required_in_file and node.has_parameter(s.name)]
    missing = [name for name in required if name not in stated]
    if not applying or not missing:
        return None, warnings
    # sections that set a missing name for another node (a node renamed with __node:=, a namespace)
    elsewhere = sorted({key for sections in files.values() for key, params in sections
                        if not section_regex(key).fullmatch(fqn) and any(name in params for name in missing)})
    why = (f"the section(s) {', '.join(elsewhere)} set them, but not for this node's name (a node renamed "
           f"with __node:= needs a section of its own, e.g. /**/{node.get_name()})" if elsewhere else
           "a key misspelled or left out would plan the default arm")
    return (f"the parameter file(s) {', '.join(sorted(applying))} state no {', '.join(missing)} for {fqn}: {why}; "
            f"a scenario file must state the robot and grid (docs/parameters.md lists the required keys)"), warnings


def stray_arguments(argv) -> list | None:
    """
    Return the arguments of ``argv`` (its first, the program, left out) outside its ``--ros-args`` sections.

    None where rcl refuses the ROS arguments themselves (a parameter file it cannot parse): ``rclpy.init``
    says so then.
    """
    from rclpy.utilities import remove_ros_args
    try:
        return list(remove_ros_args(args=list(argv))[1:])
    except RuntimeError:            # rclpy's RCLInvalidROSArgsError
        return None


def usage(exe_name: str) -> str:
    """Return the executable's usage: where its parameters go."""
    return (f"usage: {exe_name} [--ros-args [--params-file FILE] [-p NAME:=VALUE] [-r __ns:=/NS] ...]\n"
            f"  ros2 run spacerobot_planner {exe_name} --ros-args --params-file config/paper_3dof.yaml\n"
            f"The scenario (robot, target, obstacles, grid) comes from a ROS 2 parameter file or -p; without\n"
            f"one, the defaults (the paper's 3-DOF scene). Every parameter: docs/parameters.md; the nodes: "
            f"docs/node.md.")


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


def run_node(make_node: Callable[[Callable[[Node], None]], Node], exe_name: str, args=None,
             on_shutdown: Callable[[Node], None] | None = None) -> int:
    """
    ``rclpy.init``, ``make_node(start_check)``, spin in a :class:`.executor.NodeExecutor` until Ctrl-C.

    ``start_check(node)``: the node calls it once its parameters are declared, before it starts
    anything; it raises ValueError where :func:`file_problems` refuses the parameter files.

    A refused start (a ValueError or RuntimeError from ``make_node``: bad parameters, a
    failed autostart; or rclpy's own parameter exceptions; a parameter file that applies to the
    node but does not state its robot, :func:`file_problems`) is printed as one line
    ``<exe_name>: <reason>`` on stderr, without a traceback, and gives exit code 1; arguments
    outside ``--ros-args`` exit 2 naming them (``-h``/``--help``: the usage, exit 0); otherwise 0.
    """
    stop = threading.Event()
    argv = sys.argv if args is None else args
    stray = stray_arguments(argv) or []
    if any(a in ("-h", "--help") for a in stray):
        print(usage(exe_name))
        return 0
    if stray:
        print(f"{exe_name}: unrecognised argument(s) {' '.join(stray)}: ROS arguments go after --ros-args "
              f"(e.g. {exe_name} --ros-args --params-file FILE); --help says more", file=sys.stderr, flush=True)
        return 2

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
            warnings = []

            def start_check(node: Node) -> None:
                refusal, said = file_problems(node, argv)
                if refusal is not None:
                    raise ValueError(refusal)
                warnings.extend(said)
            try:
                node = make_node(start_check)
            except (ValueError, RuntimeError, ParameterException) as e:
                print(f"{exe_name}: {e}", file=sys.stderr, flush=True)
                return 1
            for line in warnings + not_taken(node, argv):
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
