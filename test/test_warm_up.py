"""
The planning process's warm-up covers the routes that only some plans take.

A fresh process runs ``worker.warm_up`` on the paper scenario (what the node's planning
process does before it serves), then plans random scenes of the property-test family
(``bench scenes``): scenes that are disconnected on the first grid, that repair, that solve
several bands.  Oracle: numba's own record of the signatures each kernel holds, before and
after those plans: a signature that appears after the warm-up is a kernel loaded or
compiled in the middle of a plan (milliseconds to a second of a user's plan).
"""

import json
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent

#: each spacerobot_planner kernel's signatures in this process (numba's own record): the scripts' oracle
_SIGNATURES = r"""
import sys
import numba


def signatures():
    out = {}
    for name, mod in list(sys.modules.items()):
        if name.startswith("spacerobot_planner"):
            for obj in vars(mod).values():
                if isinstance(obj, numba.core.dispatcher.Dispatcher) and obj.__module__ == name:
                    out[f"{name}.{obj.py_func.__name__}"] = {str(s) for s in obj.signatures}
    return out
"""

_CHECK = _SIGNATURES + r"""
import json
import numpy as np
from spacerobot_planner.bench.scenes import plan_problems
from spacerobot_planner.config import load_scenario
from spacerobot_planner.planner import Planner
from spacerobot_planner.worker import warm_up

dof, count = int(sys.argv[1]), int(sys.argv[2])
warm_up(Planner(load_scenario(f"{sys.argv[3]}/config/paper_{dof}dof.yaml")))
before = signatures()
codes, repaired, banded, refined = {}, 0, 0, 0
for _, (_, start, planner, goal) in zip(range(count), plan_problems(np.random.default_rng([0, dof]), dof)):
    res = planner.plan(start, goal)
    codes[str(res.code)] = codes.get(str(res.code), 0) + 1
    repaired += bool(res.solver_stats.get("repairs"))
    banded += (res.solver_stats.get("bands") or 0) > 1
    refined += bool(res.solver_stats.get("refinements"))
after = signatures()
new = {k: sorted(v - before.get(k, set())) for k, v in after.items() if v - before.get(k, set())}
print(json.dumps({"codes": codes, "repaired": repaired, "banded": banded, "refined": refined, "new": new}))
"""


@pytest.mark.slow
@pytest.mark.parametrize("dof", [2, 3])
def test_random_plans_after_the_warm_up_meet_no_kernel_signature_it_did_not_load(dof):
    # 3-DOF: the first 100 scenes hold a refinement to 72³ (the parallel C-space rows; scene 95)
    r = subprocess.run([sys.executable, "-c", _CHECK, str(dof), "80" if dof == 2 else "100", str(ROOT)], cwd=ROOT,
                       capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-3000:]
    out = json.loads(r.stdout.strip().splitlines()[-1])
    # the plans took the rare routes: a disconnected first grid (2-DOF), repairs and a finer grid (3-DOF),
    # later bands
    assert out["banded"] > 0, out
    assert (out["codes"].get("disconnected", 0) if dof == 2 else min(out["repaired"], out["refined"])) > 0, out
    assert not out["new"], f"kernels loaded or compiled after the warm-up: {out['new']}"


_JOINED_INPUTS = r"""
import pickle, sys
from pathlib import Path
import numpy as np
from spacerobot_planner.adapters import post_process
from spacerobot_planner.config import load_scenario
from spacerobot_planner.planner import Planner
from spacerobot_planner.replanning import Executing, join_direction, plan_start
from spacerobot_planner.settings import SessionSettings

S = 1_000_000_000
sc = load_scenario(Path(sys.argv[2]) / "config" / sys.argv[3])
settings = SessionSettings()
planner = Planner(sc)
first = planner.plan(sc.start_rad, sc.goal_rad)
published = post_process(sc, first.path_rad, start_rad=sc.start_rad)
ex = Executing(published.dense, published.indices, 100 * S)
calls = [(first.path_rad, {"start_rad": sc.start_rad})]
for frac in np.linspace(0.05, 0.85, 10):
    now = ex.start_ns + int(frac * published.dense.duration_s * S)
    q = ex.expected_at(now)
    start, join, _ = plan_start(ex, now, q, now, settings.horizon_s, settings.follow_tolerance_rad,
                                sc.robot.planned_periodic)
    if join is None:
        continue
    res = planner.plan(start, sc.goal_rad, start_tangent=join_direction(join))
    if res.ok:
        for took_s in (0.01, 0.25):
            calls.append((res.path_rad, {"join": join, "now_ns": now + int(took_s * S), "lead_s": 0.3}))
with open(sys.argv[1], "wb") as f:
    pickle.dump((sc, calls), f)
"""

_JOINED_CHAINS = _SIGNATURES + r"""
import json, pickle
from spacerobot_planner.adapters import post_process, warm_up
from spacerobot_planner.trajectory import HorizonPassed

with open(sys.argv[1], "rb") as f:
    sc, calls = pickle.load(f)
warm_up(sc)                         # the node's configure
before = signatures()
joined = 0
for path, kw in calls:
    try:
        out = post_process(sc, path, **kw)
        joined += out.continuation is not None
    except (ValueError, HorizonPassed):
        pass
after = signatures()
new = {k: sorted(v - before.get(k, set())) for k, v in after.items() if v - before.get(k, set())}
print(json.dumps({"chains": len(calls), "joined": joined, "new": new}))
"""


@pytest.mark.slow
@pytest.mark.parametrize("config", ["paper_3dof.yaml", "servicer_3dof.yaml"])
def test_joined_chains_after_the_nodes_chain_warm_up_meet_no_kernel_signature_it_did_not_load(config, tmp_path):
    """
    The node's process (``adapters.warm_up`` at configure) has loaded every kernel a joined replan's chain runs.

    The paths and joins come from a planning process of their own (as in the node: the plans are
    the child's), replans joined to the scene's plan at ten instants of it, each chained twice
    (the plan taking 10 ms and 250 ms); the chains then run in a fresh process after the warm-up.
    Oracle: numba's record of each kernel's signatures before and after them.
    """
    inputs = tmp_path / "joined.pkl"
    r = subprocess.run([sys.executable, "-c", _JOINED_INPUTS, str(inputs), str(ROOT), config], cwd=ROOT,
                       capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-3000:]
    r = subprocess.run([sys.executable, "-c", _JOINED_CHAINS, str(inputs)], cwd=ROOT,
                       capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-3000:]
    out = json.loads(r.stdout.strip().splitlines()[-1])
    assert out["joined"] >= 5, out          # the chains joined the moving arm
    assert not out["new"], f"kernels loaded or compiled in a joined replan's chain after the warm-up: {out['new']}"


_CAPTURE_AFTER_WARM_UP = _SIGNATURES + r"""
import json
from spacerobot_planner import free_floating_capture as ffc
from spacerobot_planner import planner as planner_module
from spacerobot_planner import worker
from spacerobot_planner.config import load_scenario
from spacerobot_planner.planner import Planner

sc = load_scenario(f"{sys.argv[1]}/config/free_floating_capture.yaml")
if sys.argv[2] == "worker":
    worker.warm_up(Planner(sc))           # the node's planning process, before it serves
else:
    planner_module.warm_up(sc)            # the public warm-up (the CLI's callers, the benches)
before = signatures()
ran, kernels = {}, {}
for name in ("_attitude_profiles_parallel", "_family_changes_parallel"):   # counted as the plan calls them
    kernels[name] = kernel = getattr(ffc, name)
    setattr(ffc, name, lambda *a, kernel=kernel, name=name: ran.update({name: ran.get(name, 0) + 1}) or kernel(*a))
# no goal: the free-floating capture; numba's threads whatever the machine's load (its batches' parallel form)
res = Planner(sc, threads_follow_load=False).plan(sc.start_rad)
for name, kernel in kernels.items():
    setattr(ffc, name, kernel)              # the dispatchers back, for their signatures
after = signatures()
new = {k: sorted(v - before.get(k, set())) for k, v in after.items() if v - before.get(k, set())}
print(json.dumps({"code": str(res.code), "new": new, "parallel": sorted(ran)}))
"""


@pytest.mark.parametrize("which", ["worker", "planner"])
def test_a_free_floating_capture_after_the_warm_up_meets_no_kernel_signature_it_did_not_load(which):
    """
    Both warm-ups load the capture's attitude kernel in both forms (one thread, numba's threads).

    No plan of the warm-ups reaches the capture's search (the planning process's warm-up plans with
    goals); its batches run on numba's threads where the thread has more than one.  The capture
    scene's plan in a fresh process after the warm-up, on numba's threads whatever the load
    (``threads_follow_load: false``; both parallel forms ran).  Oracle: numba's record of each
    kernel's signatures before and after the plan.
    """
    import numba
    if numba.config.NUMBA_NUM_THREADS < 2:
        pytest.skip("numba runs one thread here")
    r = subprocess.run([sys.executable, "-c", _CAPTURE_AFTER_WARM_UP, str(ROOT), which], cwd=ROOT,
                       capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-3000:]
    out = json.loads(r.stdout.strip().splitlines()[-1])
    assert out["code"] == "ok", out
    assert out["parallel"] == ["_attitude_profiles_parallel", "_family_changes_parallel"], out   # (not vacuous)
    assert not out["new"], f"kernels loaded or compiled in a capture after the warm-up: {out['new']}"


_PUBLIC_WARM_UP = _SIGNATURES + r"""
import json, resource
from dataclasses import replace
import spacerobot_planner.field as field
from spacerobot_planner.config import load_scenario
from spacerobot_planner.planner import Planner, warm_up

if sys.argv[2] == "no-reserve":
    field.HEAP_BYTES_PER_NODE = 0          # the warm-up without its heap reservation: the faults' baseline
sc = load_scenario(f"{sys.argv[1]}/config/paper_3dof.yaml")
warm_up(sc)                                # what an API user, the CLI's callers and the benches run first
before = signatures()
faults, ok = [], []
for cells in [int(c) for c in sys.argv[3:]]:
    grid_sc = replace(sc, grid=sc.grid_with_cells(cells))
    f0 = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    ok.append(bool(Planner(grid_sc).plan(grid_sc.start_rad, grid_sc.goal_rad).ok))
    faults.append(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - f0)
if sys.argv[2] == "reserve":              # and a plan whose field budget runs out (a loaded machine's)
    late = Planner(sc, field_budget_s=1e-4).plan(sc.start_rad, sc.goal_rad)
    ok.append(not late.solver_stats["converged"])
after = signatures()
new = {k: sorted(v - before.get(k, set())) for k, v in after.items() if v - before.get(k, set())}
print(json.dumps({"ok": ok, "faults": faults, "kept_heap": field.keep_heap(), "new": new}))
"""


def _public_warm_up(*args) -> dict:
    r = subprocess.run([sys.executable, "-c", _PUBLIC_WARM_UP, str(ROOT), *map(str, args)], cwd=ROOT,
                       capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-3000:]
    return json.loads(r.stdout.strip().splitlines()[-1])


def test_first_paper_plans_after_the_public_warm_up_meet_no_kernel_signature_it_did_not_load():
    """
    ``planner.warm_up`` loads the steps only large 3-D bands take: level 1 on its cells, coarse levels built beside.

    The paper 3-DOF scene at 36³ (its first band's level 1 goes on cells) and at 72³ (its coarse levels
    are built on a second thread while the fine level's cells are laid out), each the first plan of
    its grid in a fresh process after the warm-up on the scenario's own (36³) grid, then a plan whose
    field budget (0.1 ms) runs out, as a loaded machine's can (its field filled below the bands' and its
    ascent repaired).  Oracle: numba's record of each kernel's signatures before and after the plans.
    """
    out = _public_warm_up("reserve", 36, 72)
    assert out["ok"] == [True, True, True], out
    assert not out["new"], f"kernels loaded or compiled in a first plan after planner.warm_up: {out['new']}"


def test_the_public_warm_up_faults_in_the_heap_a_first_plan_fills():
    """
    After ``planner.warm_up`` a first paper 3-DOF plan on the warmed grid finds its memory in place.

    Oracle: the kernel's count of the process's minor page faults (``getrusage``) during that plan,
    against the same plan after the same warm-up without the heap's reservation (about 1 900 pages,
    7.4 MB, measured when this was written).  Where the heap is not kept (not glibc, or the user's
    own malloc settings) there is nothing to reserve.
    """
    warmed = _public_warm_up("reserve", 36)
    if not warmed["kept_heap"]:
        pytest.skip("the C library's heap is not kept here (field.keep_heap): no reservation to check")
    baseline = _public_warm_up("no-reserve", 36)
    assert warmed["ok"][0] and baseline["ok"] == [True]
    assert baseline["faults"][0] > 500, baseline          # the plan does fill a heap it never held
    assert warmed["faults"][0] < 0.5 * baseline["faults"][0], (warmed, baseline)


_ONE_SOLVE = r"""
import json, sys
import numpy as np
from spacerobot_planner.field import geometric, multigrid, solve_field
shape = tuple(int(v) for v in sys.argv[1:])
occ = np.zeros(shape, bool)
solve_field(occ, (True,) + (False,) * (len(shape) - 1), [tuple(s - 1 for s in shape)])
print(json.dumps({"geometric": len(geometric._gpcg.signatures), "cells": len(multigrid._spcg.signatures)}))
"""


@pytest.mark.parametrize("shape, geometric_loaded", [((10, 11, 11), False), ((30, 31), True)])
def test_a_first_solve_loads_the_warm_routes_of_its_own_dimension_only(shape, geometric_loaded):
    """
    A process's first solve loads the cells routes of its grid's dimension, not the other's (the CLI's cold start).

    A small 3-D solve in a fresh process: the aggregation levels on cells loaded, the 2-D geometric
    levels' PCG not; a small 2-D one: the geometric levels loaded.  Oracle: numba's record of the
    kernels' signatures.
    """
    r = subprocess.run([sys.executable, "-c", _ONE_SOLVE, *map(str, shape)], cwd=ROOT, capture_output=True,
                       text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-3000:]
    out = json.loads(r.stdout.strip().splitlines()[-1])
    assert (out["geometric"] > 0) == geometric_loaded, out
    if not geometric_loaded:
        assert out["cells"] > 0, out
