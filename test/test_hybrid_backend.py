"""
The node's default backend: replans planned in the calling thread from what the planning process sent.

``worker.HybridBackend`` plans a job in the calling thread where the C-space and field the process
sent last answer it, and in the process otherwise.  The oracle of every plan planned here is the
same job planned by a plain ``worker.ProcessBackend`` (a separate process, its own caches): equal
bit for bit.  Where a job is planned is read from the backend's own count (``jobs_here``) and the
outcome's stats (the process's carry its pid).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from dataclasses import replace

import numpy as np
import pytest

from spacerobot_planner.collision import CollisionChecker
from spacerobot_planner.config import load_scenario
from spacerobot_planner.pipeline import NotCached
from spacerobot_planner.planner import Planner
from spacerobot_planner.worker import HybridBackend, PlanDone, PlanJob, ProcessBackend
from conftest import CONFIG_DIR


def _scenario(name):
    return load_scenario(os.path.join(CONFIG_DIR, f"{name}.yaml"))


def _moved(sc, dx_m, dy_m):
    """Return ``sc`` with its target moved by (dx, dy), m."""
    t = sc.scene.target
    return sc.with_scene(sc.scene.with_target(replace(t, center_m=(t.center_m[0] + dx_m, t.center_m[1] + dy_m))))


@pytest.fixture(scope="module")
def backends():
    """Return (a HybridBackend, a ProcessBackend) of the paper 3-DOF scenario, both warmed up."""
    sc = _scenario("paper_3dof")
    hybrid, plain = HybridBackend(sc), ProcessBackend(sc)
    assert hybrid.wait_ready(300) is not None and plain.wait_ready(300) is not None
    yield hybrid, plain
    hybrid.close()
    plain.close()


def _free_starts(sc, n, seed, near=None, spread_deg=None):
    """Return ``n`` collision-free starts within the joint bounds (uniform, or within ``spread_deg`` of ``near``)."""
    chk = CollisionChecker(sc.robot, sc.scene)
    lo, hi = sc.robot.planned_lower_rad, sc.robot.planned_upper_rad
    rng = np.random.default_rng(seed)
    out = []
    while len(out) < n:
        q = rng.uniform(lo, hi) if near is None else near + np.radians(rng.uniform(-spread_deg, spread_deg, len(lo)))
        if np.all(q >= lo) and np.all(q <= hi) and chk.is_free(q):
            out.append(q)
    return out


def _same(a, b, cached: bool = True):
    """
    Assert two plans' outcomes are the same plan: code, reason, paths bit for bit, solver stats.

    ``cached``: and what each found cached, where both backends saw the same jobs before (the
    module's pair does not: some tests run jobs on one of them only).
    """
    assert isinstance(a, PlanDone) and isinstance(b, PlanDone)
    ra, rb = a.result, b.result
    assert (ra.code, ra.reason) == (rb.code, rb.reason)
    assert np.array_equal(ra.path_rad, rb.path_rad) and np.array_equal(ra.grid_path_rad, rb.grid_path_rad)
    assert ra.solver_stats == rb.solver_stats and (not cached or ra.cached == rb.cached)


class _Gens:
    """Job numbers, increasing across the module (a backend's cancels are by number)."""

    n = 1000

    @classmethod
    def next(cls) -> int:
        cls.n += 1
        return cls.n


def _job(sc, start, **kw):
    return PlanJob.for_scenario(_Gens.next(), sc, start, **kw)


@pytest.mark.parametrize("name", ["paper_3dof", "paper_2dof"])
def test_replans_are_planned_here_and_are_the_planning_processs_plans(name):
    sc = _scenario(name)
    hybrid, plain = HybridBackend(sc), ProcessBackend(sc)
    try:
        first = _job(sc, sc.start_rad)
        a, b = hybrid.run(first), plain.run(first)
        _same(a, b)
        assert a.result.ok and "pid" in a.stats and hybrid.jobs_here == 0    # nothing held yet: the process's
        for k, q in enumerate(_free_starts(sc, 8, seed=5)):
            job = _job(sc, q)
            a, b = hybrid.run(job), plain.run(job)
            _same(a, b)
            assert hybrid.jobs_here == k + 1 and "pid" not in a.stats
            assert a.result.field is b.result.field or np.array_equal(a.result.field.log_u, b.result.field.log_u)
        assert sum(hybrid.here.cache_sizes()[k] for k in ("cspaces", "fields")) == 2    # what the process sent
    finally:
        hybrid.close()
        plain.close()


def test_a_new_target_is_planned_in_the_process_and_its_replans_here(backends):
    hybrid, plain = backends
    sc = _scenario("paper_3dof")
    _same(hybrid.run(_job(sc, sc.start_rad)), plain.run(_job(sc, sc.start_rad)), cached=False)
    first_field = hybrid.run(_job(sc, _free_starts(sc, 1, seed=7)[0])).result.field
    moved = _moved(sc, 0.02, -0.01)
    before = hybrid.jobs_here
    job = _job(moved, sc.start_rad)
    a = hybrid.run(job)
    _same(a, plain.run(job), cached=False)
    assert a.result.ok and "pid" in a.stats and hybrid.jobs_here == before
    # the first target's C-space and field are let go at once (the node holds the new pair only)
    assert hybrid.here.cache_key_of(first_field) is None and hybrid.here.cache_key_of(a.result.field) is not None
    for q in _free_starts(moved, 3, seed=8):
        job = _job(moved, q)
        a = hybrid.run(job)
        _same(a, plain.run(job), cached=False)
    assert hybrid.jobs_here == before + 3
    # the first target's replans: its C-space and field are no longer what the process sent last
    job = _job(sc, _free_starts(sc, 1, seed=9)[0])
    a = hybrid.run(job)
    _same(a, plain.run(job), cached=False)
    assert "pid" in a.stats and hybrid.jobs_here == before + 3
    assert hybrid.here.cache_sizes()["cspaces"] == 1 and hybrid.here.cache_sizes()["fields"] == 1


def _repairing_scene():
    """Return (scenario, goal, a start whose plan repairs, a start whose plan does not) on the random 3-DOF scenes."""
    from spacerobot_planner.bench.scenes import random_scenario
    rng = np.random.default_rng([0, 3])
    for _ in range(200):
        sc, start = random_scenario(rng, 3)
        if start is None:
            continue
        pl = Planner(sc, trajectory=False)
        try:
            goal = pl.goal_from_target()
        except ValueError:
            continue
        if pl.plan(start, goal).solver_stats.get("repairs", 0) == 0:
            continue
        for q in _free_starts(sc, 30, seed=1):
            other = Planner(sc, trajectory=False).plan(q, goal)
            if other.ok and other.solver_stats.get("repairs", 0) == 0:
                return sc, goal, start, q
    pytest.fail("no random scene with a repairing start and one that does not repair")


def test_a_replan_that_repairs_is_planned_in_the_process(backends):
    hybrid, plain = backends
    sc, goal, repairing, clear = _repairing_scene()
    for q in (clear, repairing):
        job = _job(sc, q, joint_goal=goal)
        before = hybrid.jobs_here
        a = hybrid.run(job)
        _same(a, plain.run(job), cached=False)
        assert "pid" in a.stats and hybrid.jobs_here == before     # new (then repaired): the process's
    assert a.result.solver_stats["repairs"] > 0
    # a repaired field is not held: no plan from the caches alone reads one (none is tried here)
    assert hybrid.here.cache_sizes()["fields"] == 0 and not hybrid._answers_here(job)
    # the process sent the repaired field last: a replan on the field before the repairs is its too
    job = _job(sc, clear, joint_goal=goal)
    a = hybrid.run(job)
    _same(a, plain.run(job), cached=False)
    assert "pid" in a.stats


def test_a_replan_cancelled_before_it_runs_here_answers_cancelled(backends):
    hybrid, plain = backends
    sc = _scenario("paper_3dof")
    hybrid.run(_job(sc, sc.start_rad))
    job = _job(sc, _free_starts(sc, 1, seed=11)[0])
    before = hybrid.jobs_here
    hybrid.cancel(job.gen)
    out = hybrid.run(job)
    assert isinstance(out, PlanDone) and out.result.code == "cancelled"
    assert hybrid.jobs_here == before + 1 and "pid" not in out.stats
    again = hybrid.run(_job(sc, job.start_rad))         # a newer job is not cancelled
    assert again.result.ok and hybrid.jobs_here == before + 2


def test_a_closed_backend_plans_nothing():
    sc = _scenario("paper_2dof")
    hybrid = HybridBackend(sc)
    hybrid.run(_job(sc, sc.start_rad))
    job = _job(sc, _free_starts(sc, 1, seed=16)[0])
    assert hybrid._answers_here(job)
    hybrid.close()
    assert hybrid.run(job) is None


def test_a_stalled_job_is_planned_in_the_process(backends):
    hybrid, _ = backends
    sc = _scenario("paper_3dof")
    hybrid.run(_job(sc, sc.start_rad))
    before = hybrid.jobs_here
    out = hybrid.run(_job(sc, _free_starts(sc, 1, seed=12)[0], stall_s=0.01, stall_stage="descent"))
    assert out.result.ok and "pid" in out.stats and hybrid.jobs_here == before


def test_a_plan_from_the_caches_alone_says_what_they_lack_and_stores_nothing_but_goal_nodes_and_walks():
    sc = _scenario("paper_3dof")
    pl = Planner(sc, trajectory=False)
    with pytest.raises(NotCached, match="cspace"):
        pl.plan(sc.start_rad, sc.goal_rad, cached_only=True)
    assert pl.cache_sizes()["cspaces"] == 0
    assert pl.plan(sc.start_rad, sc.goal_rad).ok
    other_goal = _free_starts(sc, 1, seed=13)[0]
    with pytest.raises(NotCached, match="field"):
        pl.plan(sc.start_rad, other_goal, cached_only=True)
    assert pl.cache_sizes()["fields"] == 1
    q = _free_starts(sc, 1, seed=14)[0]
    assert pl.plan(q, sc.goal_rad, cached_only=True).path_rad.tobytes() == \
        Planner(sc, trajectory=False).plan(q, sc.goal_rad).path_rad.tobytes()


def test_held_entries_stay_when_the_scene_becomes_theirs_and_go_with_another():
    sc = _scenario("paper_3dof")
    moved = _moved(sc, 0.02, 0.0)
    source = Planner(moved, trajectory=False)
    res = source.plan(sc.start_rad, source.goal_from_target())
    entries = [(source.cache_key_of(obj), obj) for obj in (res.cspace, res.field)]
    assert None not in [k for k, _ in entries]
    here = Planner(sc, trajectory=False)
    assert here.plan(sc.start_rad, sc.goal_rad).ok          # its own entries, of the first scene
    here.hold_only(*entries)
    assert here.cache_sizes()["cspaces"] == 1 and here.cache_sizes()["fields"] == 1
    here.set_scene(moved.scene)
    assert here.cache_sizes()["cspaces"] == 1 and here.cache_sizes()["fields"] == 1
    q = _free_starts(moved, 1, seed=15)[0]
    mine = here.plan(q, res.goal_rad, cached_only=True)
    assert mine.field is res.field and np.array_equal(mine.path_rad, source.plan(q, res.goal_rad).path_rad)
    here.set_scene(sc.scene)
    assert here.cache_sizes()["cspaces"] == 0 and here.cache_sizes()["fields"] == 0


def test_the_node_side_warm_up_plans_the_seed_from_the_caches_without_a_thread_pool():
    """
    ``HybridBackend.warm_up_here`` plans the planning process's seed from the caches in the calling process.

    In a fresh process (the node's, as configure runs it): a coarse replan from the C-space and field
    the planning process sent before its Ready (the node warms up while it does), and no numba thread
    pool started there, by the warm-up or a replan planned there, with ``planner.max_threads`` numba's
    number or its own (no C-space or field built: their parallel kernels start one, and so does a
    thread count set on numba).  The replans planned there after it, from rest and with the arm
    moving at the start (a joined replan's start tangent), load no kernel of numba's cache (the
    first joined replan loaded the spline's, 11 ms, when the warm-up planned the seed alone).
    """
    code = (
        "import json, os, sys\n"
        "from dataclasses import replace\n"
        "import numpy as np\n"
        "from spacerobot_planner.config import load_scenario\n"
        "from spacerobot_planner.worker import HybridBackend, PlanJob\n"
        "from numba.np.ufunc import parallel as pool\n"
        f"sc = load_scenario(os.path.join({CONFIG_DIR!r}, 'paper_3dof.yaml'))\n"
        "sc = replace(sc, planner_settings=replace(sc.planner_settings, max_threads=int(sys.argv[1])))\n"
        "b = HybridBackend(sc)\n"
        "res = b.warm_up_here(300)\n"
        "ready = b.ready\n"
        "assert b.wait_ready(300) is not None\n"
        "first = b.run(PlanJob.for_scenario(1, sc, sc.start_rad)).result\n"
        "import numba.core.caching as caching\n"
        "loads, load = [], caching.Cache.load_overload\n"
        "caching.Cache.load_overload = lambda self, *a: loads.append(self._name) or load(self, *a)\n"
        "q, tangent = first.path_rad[3], first.path_rad[4] - first.path_rad[2]\n"
        "again = b.run(PlanJob.for_scenario(2, sc, sc.start_rad + 0.01))\n"
        "joined = b.run(PlanJob.for_scenario(3, sc, q, start_tangent=tangent / np.linalg.norm(tangent)))\n"
        "b.close()\n"
        "print(json.dumps({'before_ready': ready is None, 'ok': bool(res.ok), 'cached': list(res.cached),\n"
        "                  'replans_here': all(r.result.ok and 'pid' not in r.stats for r in (again, joined)),\n"
        "                  'kernels_loaded_by_replans': loads, 'pool': bool(pool._is_initialized)}))\n")
    for threads in (0, 1):      # numba's number, and a count of its own (set on numba by a plan that builds)
        out = subprocess.run([sys.executable, "-c", code, str(threads)], capture_output=True, text=True, timeout=300)
        assert out.returncode == 0, out.stderr[-3000:]
        got = json.loads(out.stdout.strip().splitlines()[-1])
        assert got == {"before_ready": True, "ok": True, "cached": ["cspace", "field"], "replans_here": True,
                       "kernels_loaded_by_replans": [], "pool": False}, threads


def test_a_new_joint_goal_is_planned_in_the_process_and_its_replans_here(backends):
    hybrid, plain = backends
    sc = _scenario("paper_3dof")
    first = hybrid.run(_job(sc, sc.start_rad)).result
    goal = first.path_rad[len(first.path_rad) // 2]          # a free posture the target's plan passes
    job = _job(sc, sc.start_rad, joint_goal=goal)
    assert not hybrid._answers_here(job)                      # a field of its own: not tried here
    a = hybrid.run(job)
    _same(a, plain.run(job), cached=False)
    assert a.result.ok and "pid" in a.stats
    job = _job(sc, _free_starts(sc, 1, seed=18)[0], joint_goal=goal.copy())
    assert hybrid._answers_here(job)
    a = hybrid.run(job)
    _same(a, plain.run(job), cached=False)
    assert "pid" not in a.stats
    assert not hybrid._answers_here(_job(sc, sc.start_rad))   # the target's field is no longer held


def test_a_cspace_of_another_grid_margin_or_a_field_of_another_cspace_is_not_tried_here(backends):
    """
    Where no plan from the caches held would answer, the job is not tried here (only to fail there).

    A held C-space of another grid margin than the one a plan tries first (``grid_extra_margin_m``;
    a plan that needed the second margin leaves one of 0), and a field kept from before a C-space
    sent without one (a plan that failed before its field).
    """
    hybrid, plain = backends
    sc = _scenario("paper_3dof")
    first = hybrid.run(_job(sc, sc.start_rad)).result
    assert first.ok and first.solver_stats["grid_extra_margin_m"] > 0.0
    flat = replace(sc, planner_settings=replace(sc.planner_settings, grid_extra_margin_m=0.0))
    job = _job(flat, _free_starts(sc, 1, seed=19)[0])
    assert not hybrid._answers_here(job)                      # its first margin's C-space is not held
    a = hybrid.run(job)
    _same(a, plain.run(job), cached=False)
    assert "pid" in a.stats
    # a C-space sent without a field: the field held before is of another C-space, and goes
    hybrid.run(_job(sc, sc.start_rad))
    other = Planner(_moved(sc, 0.03, 0.0), trajectory=False)
    res = other.plan(sc.start_rad, other.goal_from_target())
    done = PlanDone(10 ** 6, replace(res, field=None), stats={}, keys=(("cspace", other.cache_key_of(res.cspace)),))
    hybrid._unpack(done)
    assert hybrid._hold[0][1] is res.cspace and hybrid._hold[1] is None
    assert hybrid.here.cache_sizes()["cspaces"] == 1 and hybrid.here.cache_sizes()["fields"] == 0
    assert not hybrid._answers_here(_job(_moved(sc, 0.03, 0.0), sc.start_rad))
