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

_CHECK = r"""
import json, sys
import numba
import numpy as np
from spacerobot_planner.bench.scenes import plan_problems
from spacerobot_planner.config import load_scenario
from spacerobot_planner.planner import Planner
from spacerobot_planner.worker import warm_up

dof, count = int(sys.argv[1]), int(sys.argv[2])


def signatures():
    out = {}
    for name, mod in list(sys.modules.items()):
        if name.startswith("spacerobot_planner"):
            for obj in vars(mod).values():
                if isinstance(obj, numba.core.dispatcher.Dispatcher) and obj.__module__ == name:
                    out[f"{name}.{obj.py_func.__name__}"] = {str(s) for s in obj.signatures}
    return out


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
