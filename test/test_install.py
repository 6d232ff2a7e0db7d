"""The ROS 2 install layout: `make venv` lays it out in .venv; ament_install does the same anywhere."""

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
PKG = "spacerobot_planner"


def _check_prefix(prefix: Path):
    assert (prefix / "share/ament_index/resource_index/packages" / PKG).is_file()
    assert (prefix / "share" / PKG / "package.xml").is_file()
    assert (prefix / "share" / PKG / "config/paper_3dof.yaml").is_file()
    for exe in ("planner_node", "mock_arm_node"):
        path = prefix / "lib" / PKG / exe
        assert path.is_file() and os.access(path, os.X_OK), f"{path} is not executable"


def test_venv_has_the_ament_layout():
    venv = ROOT / ".venv"
    if not (venv / ".installed").exists():
        pytest.skip("run `make venv` first")
    _check_prefix(venv)


def test_ament_install_into_a_temp_prefix(tmp_path):
    r = subprocess.run([sys.executable, "-m", "spacerobot_planner.tools.ament_install", "--prefix", str(tmp_path)],
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    _check_prefix(tmp_path)
    launcher = (tmp_path / "lib" / PKG / "planner_node").read_text()
    from spacerobot_planner.tools.ament_install import console_scripts
    module, func = console_scripts()["planner_node"].split(":")       # the installed console script's target
    assert f"from {module} import {func}" in launcher and f"{func}()" in launcher, launcher
    # it starts the planner node (a refused start: one line, at once)
    run = subprocess.run([sys.executable, str(tmp_path / "lib" / PKG / "planner_node"), "--ros-args", "-p",
                          "safety_margin_m:=-1.0"], capture_output=True, text=True, timeout=300)
    assert run.returncode == 1 and run.stderr.startswith("planner_node: ") and "safety_margin_m" in run.stderr, run


# run in the installed tree: the default route (the planning process's warm-up, then a full
# plan with its trajectory and the chain after it, as spacerobot-plan and the node's first target
# run them), and numba's own count of the kernels it loaded from the cache (hits) and compiled
# because the cache had nothing valid (misses)
_CACHE_CHECK = r"""
import json, os, sys
import numba
from spacerobot_planner.config import load_params_file, scenario_from_params
from spacerobot_planner.planner import Planner
from spacerobot_planner.offline import plan_offline
from spacerobot_planner.worker import warm_up
import spacerobot_planner
sc = scenario_from_params(load_params_file(sys.argv[1]))
warm_up(Planner(sc, trajectory=False))
out = plan_offline(Planner(sc, reaction=True), sc.start_rad)
res = out.result
assert out.processed is not None
hits, misses = 0, {}
for name, mod in list(sys.modules.items()):
    if name.startswith("spacerobot_planner"):
        for obj in vars(mod).values():
            if isinstance(obj, numba.core.dispatcher.Dispatcher) and obj.__module__ == name:
                hits += sum(obj.stats.cache_hits.values())
                if obj.stats.cache_misses:
                    misses[f"{name}.{obj.py_func.__name__}"] = len(obj.stats.cache_misses)
print(json.dumps({"file": spacerobot_planner.__file__, "ok": res.ok, "has_trajectory": res.trajectory is not None,
                  "hits": hits, "misses": misses}))
"""


@pytest.mark.slow
def test_setup_py_install_leaves_a_valid_numba_cache_in_the_installed_tree(tmp_path):
    """
    The numba cache that `setup.py install` leaves is valid, and the bytecode beside it.

    `setup.py install` as colcon runs it, then a fresh process importing the installed copy plans
    the paper's 3-DOF target with every kernel loaded from numba's cache.
    """
    build, prefix = tmp_path / "build", tmp_path / "prefix"
    build.mkdir()
    env = dict(os.environ)
    env.pop("SPACEROBOT_PLANNER_WARM_CACHE", None)
    # the interface package's CMake step (~30 s) is test_workspace's
    env["SPACEROBOT_PLANNER_BUILD_INTERFACES"] = "0"
    cmd = [sys.executable, "setup.py", "egg_info", "--egg-base", str(build), "build", "--build-base",
           str(build / "build"), "install", "--prefix", str(prefix), "--record", str(build / "install.log"),
           "--single-version-externally-managed"]
    r = subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    site = next(prefix.glob("lib/python*/site-packages"))
    cache = sorted(p for p in (site / PKG).rglob("*.nb[ic]"))
    assert cache, "no numba cache in the installed tree:\n" + r.stdout[-2000:]
    recorded = set((build / "install.log").read_text().split())
    assert {str(p) for p in cache} <= recorded, "the cache files are not in the install record"
    # the bytecode of every installed module beside it (a start under PYTHONDONTWRITEBYTECODE, as
    # here, would compile the package again every time), recorded too
    modules = sorted((site / PKG).rglob("*.py"))
    pyc = [p.parent / "__pycache__" / f"{p.stem}.{sys.implementation.cache_tag}.pyc" for p in modules]
    assert modules and all(p.is_file() for p in pyc), [str(p) for p in pyc if not p.is_file()][:5]
    assert {str(p) for p in pyc} <= recorded, "the bytecode is not in the install record"
    before = {p: p.stat().st_mtime_ns for p in cache}
    check_env = dict(env, PYTHONPATH=str(site))
    r = subprocess.run([sys.executable, "-c", _CACHE_CHECK, str(ROOT / "config/paper_3dof.yaml")], cwd=site,
                       env=check_env, capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-3000:]
    out = json.loads(r.stdout.strip().splitlines()[-1])
    assert out["file"].startswith(str(site)), out["file"]
    assert out["ok"] and out["has_trajectory"]
    assert out["hits"] > 0 and out["misses"] == {}, out
    # a second oracle, from outside: nothing was compiled, so no cache file was added or rewritten
    after = {p: p.stat().st_mtime_ns for p in sorted((site / PKG).rglob("*.nb[ic]"))}
    assert after == before
