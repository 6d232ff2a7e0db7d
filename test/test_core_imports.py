"""
The planning core's imports run one way (issue 17).

Read from the source with ``ast`` (nothing is imported): every ``import`` and ``from ...
import`` of every module of ``spacerobot_planner`` outside ``ros/`` (module level and
inside functions, relative and absolute ``spacerobot_planner.*``), resolved to the module
it loads.  The core is the package less ``ros/`` (the ROS shell), ``tools/`` and
``bench/`` (programs built on the core); the graph holds the core and those programs.

- the graph has no cycle (the test names one, and the knot it belongs to, when it has);
- no core module imports rclpy, a ROS message package or ``spacerobot_planner.ros``;
- no core module imports a program (``tools``, ``bench``) or a compatibility re-export;
- the core's imports run down its :data:`LAYERS` (session and boundary → planner →
  pipeline → stages → physics and geometry);
- an import inside a function of the core that loads a core module is in
  :data:`LAZY_ALLOWED`, with the reason it is not at module level (never to dodge a cycle);
- every name ``ros/`` imports from the core exists there.

Before issue 17 the core had one knot, config → dynamics → config (``dynamics`` imported
``config`` inside ``scenario_joint_limits``), with pipeline, planner and problem in it,
and 20 imports of core modules inside functions.
"""

from __future__ import annotations

import ast
from pathlib import Path

PACKAGE = "spacerobot_planner"
ROOT = Path(__file__).resolve().parent.parent / PACKAGE
#: subpackages that are not the core: the ROS shell (not in the graph) and the programs
ROS = f"{PACKAGE}.ros"
PROGRAMS = (f"{PACKAGE}.tools", f"{PACKAGE}.bench")
#: top-level names a core module must not import (rclpy and the ROS message packages)
ROS_TOP = ("rclpy", "rcl_interfaces", "std_msgs", "sensor_msgs", "geometry_msgs", "trajectory_msgs",
           "visualization_msgs", "nav_msgs", "diagnostic_msgs", "lifecycle_msgs", "std_srvs",
           "action_msgs", "builtin_interfaces", "spacerobot_planner_interfaces")

#: (importing core module, imported core module) → why the import is inside a function.
LAZY_ALLOWED: dict = {
    (f"{PACKAGE}.field", f"{PACKAGE}.field.oracle"):
        "SciPy's sparse direct solve, the tests' and benches' reference only: a plan's start-up "
        "does not pay for importing scipy.sparse (bench coldstart)",
}

#: compatibility re-exports for code outside the core; no core module imports them
COMPAT = ()

#: the core's layers, lowest first: a module imports modules of its own layer or lower ones
#: (within a layer the graph is acyclic).  Every core module is in one.
LAYERS = (
    ("physics and geometry", ("joint_space", "termination", "robot", "scene", "collision", "spacecraft", "overlap",
                              "cores", "jit_cache")),
    ("stages", ("motion", "cspace", "field", "field.graph", "field.harmonic", "field.multigrid", "field.structured",
                "field.geometric", "field.krylov",
                "field.oracle", "field.paper", "descent", "repair", "swept", "contact", "smoothing", "ik", "redundant",
                "results", "trajectory", "published", "reaction", "timing", "replanning", "settings", "problem",
                "free_floating_capture")),
    ("pipeline", ("pipeline", "adapters")),
    ("planner", ("planner",)),
    ("session and boundary", ("config", "free_floating", "worker", "session", "offline", "")),
    ("sweeps", ("envelope", "envelope.sweep", "envelope.store", "envelope.engine", "envelope.plots")),
)


def _module_name(path: Path) -> str:
    parts = path.relative_to(ROOT.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _modules() -> dict:
    """Return {module name: path} of every module of the package."""
    return {_module_name(p): p for p in sorted(ROOT.rglob("*.py"))}


def _under(name: str, prefix: str) -> bool:
    return name == prefix or name.startswith(prefix + ".")


def _is_core(name: str) -> bool:
    return _under(name, PACKAGE) and not _under(name, ROS) and not any(_under(name, p) for p in PROGRAMS)


def _imports(name: str, path: Path, known: dict) -> list:
    """
    Return the imports of one module: (imported module, line, inside a function).

    ``from X import y`` loads ``X.y`` when that is a module of the package, else ``X``.
    Names outside the package are returned by their full dotted name.
    """
    tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    out = []

    def visit(node, in_function):
        for child in ast.iter_child_nodes(node):
            inner = in_function or isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda))
            if isinstance(child, ast.Import):
                out.extend((a.name, child.lineno, in_function) for a in child.names)
            elif isinstance(child, ast.ImportFrom):
                if child.level:
                    base = package.split(".")
                    base = base[:len(base) - (child.level - 1)]
                    mod = ".".join(base + ([child.module] if child.module else []))
                else:
                    mod = child.module
                for a in child.names:
                    sub = f"{mod}.{a.name}"
                    item = (sub if sub in known else mod, child.lineno, in_function)
                    if item not in out:
                        out.append(item)
            visit(child, inner)

    visit(tree, False)
    return out


def _graph():
    """Return (modules, {module: [(imported, line, inside a function)]}) of the core and the programs."""
    known = _modules()
    mods = {n: p for n, p in known.items() if not _under(n, ROS)}
    return mods, {n: _imports(n, p, known) for n, p in mods.items()}


def find_cycle(edges: dict) -> list | None:
    """Return one cycle of a directed graph as [a, b, ..., a], or None (iterative DFS)."""
    WHITE, GREY, BLACK = 0, 1, 2
    colour = {n: WHITE for n in edges}
    for root in sorted(edges):
        if colour[root] != WHITE:
            continue
        stack = [(root, iter(sorted(edges[root])))]
        colour[root] = GREY
        while stack:
            node, it = stack[-1]
            nxt = next(it, None)
            if nxt is None:
                colour[node] = BLACK
                stack.pop()
            elif colour.get(nxt, BLACK) == GREY:
                path = [n for n, _ in stack]
                return path[path.index(nxt):] + [nxt]
            elif colour.get(nxt) == WHITE:
                colour[nxt] = GREY
                stack.append((nxt, iter(sorted(edges[nxt]))))
    return None


def _reach(edges: dict, start: str) -> set:
    seen, todo = {start}, [start]
    while todo:
        for m in edges.get(todo.pop(), ()):
            if m not in seen:
                seen.add(m)
                todo.append(m)
    return seen


def knot(edges: dict, node: str) -> list:
    """Return the strongly connected component of ``node``: the modules it reaches that reach it."""
    return sorted(m for m in _reach(edges, node) if node in _reach(edges, m))


def test_the_cycle_finder_finds_a_cycle_and_accepts_a_dag():
    assert find_cycle({"a": {"b"}, "b": {"c"}, "c": set()}) is None
    assert find_cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == ["a", "b", "c", "a"]
    assert find_cycle({"a": {"a"}}) == ["a", "a"]
    assert knot({"a": {"b"}, "b": {"c", "a"}, "c": set(), "d": {"a"}}, "a") == ["a", "b"]


def test_the_graph_reads_every_kind_of_import():
    mods, imports = _graph()
    assert f"{PACKAGE}.planner" in mods and f"{PACKAGE}.field.graph" in mods and f"{PACKAGE}.tools.cli" in mods
    assert not any(_under(n, ROS) for n in mods)
    field_init = {m for m, _, _ in imports[f"{PACKAGE}.field"]}
    assert {f"{PACKAGE}.termination", f"{PACKAGE}.field.harmonic", f"{PACKAGE}.field.graph"} <= field_init


def test_the_core_import_graph_is_acyclic():
    mods, imports = _graph()
    edges = {n: {m for m, _, _ in imps if m in mods and m != n} for n, imps in imports.items()}
    cycle = find_cycle(edges)
    if cycle is not None:
        steps = []
        for a, b in zip(cycle, cycle[1:]):
            lines = sorted({(line, lazy) for m, line, lazy in imports[a] if m == b})
            where = ", ".join(f"line {line}{' (in a function)' if lazy else ''}" for line, lazy in lines)
            steps.append(f"  {a} imports {b} ({where})")
        short = [m.removeprefix(PACKAGE + ".") for m in knot(edges, cycle[0])]
        raise AssertionError("import cycle: " + " -> ".join(c.removeprefix(PACKAGE + ".") for c in cycle)
                             + "\n" + "\n".join(steps)
                             + f"\nthe modules that import each other (one knot): {', '.join(short)}")


def test_the_core_imports_no_ros_and_no_program():
    mods, imports = _graph()
    bad = []
    for n, imps in imports.items():
        if not _is_core(n):
            continue
        for m, line, _ in imps:
            if m.split(".")[0] in ROS_TOP or _under(m, ROS) or any(_under(m, p) for p in PROGRAMS):
                bad.append(f"{n} line {line}: imports {m}")
    assert bad == [], "\n".join(bad)


def _layer_of() -> dict:
    return {(f"{PACKAGE}.{m}" if m else PACKAGE): k for k, (_, ms) in enumerate(LAYERS) for m in ms}


def test_the_core_imports_run_down_its_layers():
    mods, imports = _graph()
    layer = _layer_of()
    core = sorted(n for n in mods if _is_core(n))
    missing = [n for n in core if n not in layer]
    assert missing == [], f"core modules in no layer of LAYERS: {missing}"
    bad = []
    for n in core:
        for m, line, _ in imports[n]:
            if m in layer and layer[m] > layer[n]:
                bad.append(f"{n} ({LAYERS[layer[n]][0]}) line {line}: imports {m} ({LAYERS[layer[m]][0]})")
    assert bad == [], "imports up the layers:\n" + "\n".join(bad)


def test_no_core_module_imports_a_compatibility_module():
    mods, imports = _graph()
    bad = [f"{n} line {line}: imports {m}" for n, imps in imports.items() if _is_core(n) and n not in COMPAT
           for m, line, _ in imps if m in COMPAT]
    assert bad == [], "\n".join(bad)


def test_the_names_the_ros_shell_imports_from_the_core_exist():
    """What ``ros/`` imports from the core (read from its source; rclpy is not imported here)."""
    import importlib

    known = _modules()
    missing = []
    for n, path in known.items():
        if not _under(n, ROS):
            continue
        tree = ast.parse(path.read_text(encoding="utf-8"))
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom) and node.level >= 2:
                mod = ".".join([PACKAGE] + ([node.module] if node.module else []))
                target = importlib.import_module(mod)
                missing += [f"{n} line {node.lineno}: {mod}.{a.name}" for a in node.names
                            if not hasattr(target, a.name) and f"{mod}.{a.name}" not in known]
    assert missing == [], "\n".join(missing)


def test_function_level_imports_of_core_modules_are_documented():
    mods, imports = _graph()
    bad = []
    for n, imps in imports.items():
        if not _is_core(n):
            continue
        for m, line, lazy in imps:
            if lazy and _is_core(m) and (n, m) not in LAZY_ALLOWED:
                bad.append(f"{n} line {line}: imports {m} inside a function")
    assert bad == [], ("imports of core modules inside functions (move them to module level, or add "
                       "them to LAZY_ALLOWED with the reason):\n" + "\n".join(bad))
    for (a, b), why in LAZY_ALLOWED.items():
        assert why.strip(), f"LAZY_ALLOWED[{a}, {b}] gives no reason"
