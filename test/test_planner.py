"""The offline planner on the paper's scenes: exact ends, dense validity, codes, cache, cancel."""

import threading
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from spacerobot_planner.collision import CollisionChecker
from spacerobot_planner.config import load_scenario
from spacerobot_planner.cspace import build_cspace
from spacerobot_planner.planner import CODES, STAGES, Planner
from spacerobot_planner.scene import Target

CONFIG = Path(__file__).resolve().parent.parent / "config"
HALF_DEG = np.radians(0.5)


def wrap(a):
    return (np.asarray(a) + np.pi) % (2 * np.pi) - np.pi


def dense_check(robot, scene, path, step_rad=np.radians(0.25)):
    """Independent check: linear interpolation at ≤ step_rad, CollisionChecker with the margin,
    bounded joints within bounds.  Returns (all free, min clearance)."""
    chk = CollisionChecker(robot, scene)
    samples = [path[:1]]
    for a, b in zip(path[:-1], path[1:]):
        n = max(1, int(np.ceil(np.linalg.norm(b - a) / step_rad)))
        t = np.arange(1, n + 1)[:, None] / n
        samples.append(a + t * (b - a))
    q = np.vstack(samples)
    lo, hi = robot.planned_lower_rad, robot.planned_upper_rad
    for k, per in enumerate(robot.planned_periodic):
        if not per:
            assert np.all((q[:, k] >= lo[k] - 1e-9) & (q[:, k] <= hi[k] + 1e-9))
    return bool(np.all(chk.is_free(q))), float(np.min(chk.clearance_m(q)))


def assert_valid_path(res, sc):
    assert res.ok and res.code == "ok" and res.reason is None
    p = res.path_rad
    assert p.ndim == 2 and p.shape[1] == sc.robot.dof and len(p) >= 2
    # exact ends: the start bit for bit, the goal bit for bit on bounded joints, mod 2π on periodic
    assert np.array_equal(p[0], res.start_rad)
    per = np.array(sc.robot.planned_periodic)
    assert np.array_equal(p[-1][~per], res.goal_rad[~per])
    assert np.allclose(wrap(p[-1][per] - res.goal_rad[per]), 0.0, atol=1e-12)
    # dense and continuous (unwrapped): no step above 0.5°
    assert np.max(np.linalg.norm(np.diff(p, axis=0), axis=1)) <= HALF_DEG + 1e-12
    free, clr = dense_check(sc.robot, sc.scene, p)
    assert free, f"path collides under the independent 0.25° check (min clearance {clr})"
    assert clr > sc.scene.safety_margin_m
    # the planner's minimum is over its own check samples, the returned rows among them
    rows_clr = CollisionChecker(sc.robot, sc.scene).clearance_m(p).min()
    assert clr - 1e-9 <= rows_clr and res.min_clearance_m <= rows_clr + 1e-9
    assert np.isclose(res.path_length_rad, np.sum(np.linalg.norm(np.diff(p, axis=0), axis=1)))
    assert len(res.grid_path_rad) >= 1
    assert set(res.timings_s) == set(STAGES)
    for key in ("sweeps", "residual", "converged"):
        assert key in res.solver_stats


@pytest.fixture(scope="module")
def sc3():
    return load_scenario(CONFIG / "paper_3dof.yaml")


@pytest.fixture(scope="module")
def sc2():
    return load_scenario(CONFIG / "paper_2dof.yaml")


@pytest.fixture(scope="module")
def planner3(sc3):
    return Planner(sc3)


@pytest.fixture(scope="module")
def plan3(planner3, sc3):
    return planner3.plan(sc3.start_rad, sc3.goal_rad)


@pytest.fixture(scope="module")
def planner2(sc2):
    return Planner(sc2)


@pytest.fixture(scope="module")
def plan2(planner2, sc2):
    return planner2.plan(sc2.start_rad, sc2.goal_rad)


# ------------------------------------------------------------ the paper's scenes
def test_paper_3dof_path_exact_ends_and_free(plan3, sc3):
    assert_valid_path(plan3, sc3)
    # neither end is a grid node, yet the path starts and ends on them exactly
    grid = sc3.grid
    for q in (sc3.start_rad, sc3.goal_rad):
        assert not np.allclose(grid.config_of(grid.node_of(q)), q)


def test_paper_3dof_path_crosses_attitude_seam(plan3, sc3):
    th1 = plan3.path_rad[:, 0]
    # the paper's path crosses ±180°: the unwrapped attitude leaves [-π, π) and stays continuous
    assert th1.min() < -np.pi or th1.max() >= np.pi
    assert np.max(np.abs(np.diff(th1))) <= HALF_DEG
    # the grid path itself is wrapped (grid values), so it jumps at the seam
    assert np.max(np.abs(np.diff(plan3.grid_path_rad[:, 0]))) > np.pi


def test_paper_2dof_path_exact_ends_and_free(plan2, sc2):
    assert_valid_path(plan2, sc2)
    assert plan2.path_length_rad < 2.6       # straight-line distance is 1.80 rad


def test_json_dict_keys(plan3, sc3):
    d = plan3.to_json_dict()
    for key in ("ok", "joint_names", "start_rad", "goal_rad", "path_rad", "grid_path_rad",
                "timings_s", "solver", "min_clearance_m", "error", "code"):
        assert key in d
    assert d["error"] is None and d["ok"] is True and d["code"] == "ok"
    assert d["path_rad"][0] == list(sc3.start_rad)
    assert np.allclose(wrap(np.array(d["path_rad"][-1]) - sc3.goal_rad), 0.0, atol=1e-12)


# ---------------------------------------------------------------------- cache
def test_replan_with_new_start_reuses_cache(planner3, plan3, sc3):
    chk = CollisionChecker(sc3.robot, sc3.scene)
    new_start = sc3.start_rad + np.radians([12.0, -4.0, 3.0])
    assert chk.is_free(new_start)
    res = planner3.plan(new_start, sc3.goal_rad)
    assert_valid_path(res, sc3)
    assert "field" in res.cached and "cspace" in res.cached
    assert res.cspace is plan3.cspace
    assert res.timings_s["cspace"] == 0.0 and res.timings_s["field"] == 0.0
    assert res.field is plan3.field


def test_set_scene_keeps_cache_only_for_same_geometry(sc3):
    pl = Planner(sc3)
    first = pl.plan(sc3.start_rad, sc3.goal_rad)
    pl.set_scene(sc3.scene.with_target(Target(center_m=sc3.scene.target.center_m)))   # equal geometry
    again = pl.plan(sc3.start_rad, sc3.goal_rad)
    assert again.cspace is first.cspace and "field" in again.cached
    pl.set_scene(sc3.scene.with_margin(0.03))
    moved = pl.plan(sc3.start_rad, sc3.goal_rad)
    assert moved.cspace is not first.cspace and "cspace" not in moved.cached


def test_target_move_rebuilds_cspace_on_the_kept_body_table(sc3):
    """A moved target rebuilds the C-space, reusing the spacecraft-body table, and the
    result equals a build from scratch; fields go with their evicted C-space."""
    pl = Planner(sc3)
    pl.plan(sc3.start_rad, sc3.goal_rad)
    tables = dict(pl._body_tables)
    moved_scene = sc3.scene.with_target(Target(center_m=(-3.22, -2.65)))
    pl.set_scene(moved_scene)
    res = pl.plan(sc3.start_rad, None)
    assert res.ok and "cspace" not in res.cached
    assert pl._body_tables.keys() == tables.keys()
    assert all(pl._body_tables[k] is tables[k] for k in tables)
    fresh = build_cspace(sc3.robot, moved_scene, sc3.grid, extra_margin_m=pl.grid_extra_margin_m)
    assert np.array_equal(res.cspace.occupied, fresh.occupied)
    for cells in (12, 14, 16, 18, 20):                      # five more grids: evictions
        pl.set_grid(sc3.grid_with_cells(cells))
        pl.plan(sc3.start_rad, sc3.goal_rad)
    assert len(pl._cspaces) == 4
    assert {k[0] for k in pl._fields} <= set(pl._cspaces)


def test_set_solver_rejects_unknown(planner3):
    with pytest.raises(ValueError, match="solver"):
        planner3.set_solver("multigrid_magic", 1e-6)


# --------------------------------------------------------------- no-path codes
def test_start_in_collision(planner3, sc3):
    bad = sc3.start_rad + np.radians([0.0, 3.0, 3.0])      # elbow folds into the body
    assert not CollisionChecker(sc3.robot, sc3.scene).is_free(bad)
    res = planner3.plan(bad, sc3.goal_rad)
    assert not res.ok and res.code == "start_in_collision"
    assert "start" in res.reason and "collision" in res.reason
    assert res.path_rad.shape == (0, 3) and np.isnan(res.min_clearance_m)


def test_goal_in_collision(planner3, sc3):
    bad_goal = sc3.start_rad + np.radians([0.0, 3.0, 3.0])      # elbow folds into the body
    assert not CollisionChecker(sc3.robot, sc3.scene).is_free(bad_goal)
    res = planner3.plan(sc3.start_rad, bad_goal)
    assert not res.ok and res.code == "goal_in_collision" and "goal" in res.reason


def test_goal_out_of_reach(sc3):
    far = sc3.with_scene(sc3.scene.with_target(Target(center_m=(9.0, 9.0))))
    pl = Planner(far)
    with pytest.raises(ValueError, match="out of the arm's reach"):
        pl.goal_from_target()
    res = pl.plan(far.start_rad)                # goal from the target: none exists
    assert not res.ok and res.code == "goal_unreachable" and "reach" in res.reason


def test_goal_from_target_is_papers_branch(planner3):
    q = np.degrees(planner3.goal_from_target())
    assert np.allclose(q, [160.9, 32.3, 76.8], atol=0.2)


def test_plan_to_target_goal(planner3, sc3):
    res = planner3.plan(sc3.start_rad)          # goal_rad None → IK goal
    assert_valid_path(res, sc3)
    assert np.allclose(res.goal_rad, planner3.goal_from_target())


def test_disconnected_regions(sc2):
    # a debris block on the elbow's circle: link 2 can never sweep past it, so the
    # shoulder range splits in two; start and goal lie on opposite sides
    shoulder = 1.4 * np.array([np.cos(np.radians(160.7)), np.sin(np.radians(160.7))])
    c = shoulder + 2.0 * np.array([np.cos(np.radians(245.0)), np.sin(np.radians(245.0))])
    block = c + 0.15 * np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]])
    from spacerobot_planner.scene import Scene
    scene = Scene(target=sc2.scene.target, debris_m=(block,), safety_margin_m=sc2.scene.safety_margin_m)
    sc = replace(sc2.with_scene(scene), grid=sc2.grid_with_cells(90))
    chk = CollisionChecker(sc.robot, scene)
    assert chk.is_free(sc.start_rad) and chk.is_free(sc.goal_rad)
    res = Planner(sc).plan(sc.start_rad, sc.goal_rad)
    assert not res.ok and res.code == "disconnected"
    assert "separate free regions" in res.reason


# ------------------------------------------------------------------ bad input
@pytest.mark.parametrize("start, word", [
    ([0.1, 0.2], "expected 3 joint values"),
    ([np.nan, 2.0, 1.0], "not a finite number"),
    ([0.0, 4.0, 1.0], "shoulder"),
])
def test_invalid_start(planner3, sc3, start, word):
    res = planner3.plan(start, sc3.goal_rad)
    assert not res.ok and res.code == "invalid_input" and word in res.reason


def test_invalid_goal(planner3, sc3):
    res = planner3.plan(sc3.start_rad, [0.0, 0.0, 3.5])
    assert res.code == "invalid_input" and "goal" in res.reason and "elbow" in res.reason


def test_grid_budget_refused_before_allocating(sc3):
    big = replace(sc3, grid=sc3.grid_with_cells(400))          # 400 × 401 × 401 nodes
    res = Planner(big, max_grid_nodes=4_000_000).plan(sc3.start_rad, sc3.goal_rad)
    assert res.code == "invalid_input" and "grid.cells" in res.reason and "4,000,000" in res.reason
    assert res.cspace is None and res.timings_s["cspace"] == 0.0


# ------------------------------------------------------------------- cancel
def test_cancel_before_start(planner3, sc3):
    ev = threading.Event()
    ev.set()
    res = planner3.plan(sc3.start_rad, sc3.goal_rad, cancel=ev)
    assert not res.ok and res.code == "cancelled"


def test_cancel_between_stages(sc3):
    ev = threading.Event()
    lines = []

    def progress(line):
        lines.append(line)
        if line.startswith("cspace"):
            ev.set()

    res = Planner(sc3).plan(sc3.start_rad, sc3.goal_rad, cancel=ev, progress=progress)
    assert res.code == "cancelled" and res.field is None
    assert any(line.startswith("cspace") for line in lines)


# ------------------------------------------------- coarse grid: repair + exact check
def test_random_starts_always_verified(planner3, sc3):
    """Many starts on the 10° grid: every returned path passes the independent check."""
    rng = np.random.default_rng(7)
    chk = CollisionChecker(sc3.robot, sc3.scene)
    lo, hi = sc3.robot.planned_lower_rad, sc3.robot.planned_upper_rad
    done = ok = 0
    while done < 12:
        q = rng.uniform(lo, hi)
        if not chk.is_free(q):
            continue
        res = planner3.plan(q, sc3.goal_rad)
        assert res.code in ("ok", "disconnected", "path_invalid"), res.reason
        if res.ok:
            assert_valid_path(res, sc3)
            ok += 1
        done += 1
    assert ok >= 6                          # the check above really ran


def test_repair_without_grid_margin(sc3):
    """With no extra grid margin, adjacent free nodes can be joined by a colliding segment:
    the planner must still only return verified paths.  Its grid walk takes only motions
    that pass (the steepest valid neighbour, cutting colliding grid edges when none does)."""
    sc = replace(sc3, grid=sc3.grid_with_cells(24))       # 15° steps: corners get cut
    pl = Planner(sc, grid_extra_margin_m=0.0)
    chk = CollisionChecker(sc.robot, sc.scene)
    rng = np.random.default_rng(3)
    results = []
    while len(results) < 10:
        q = rng.uniform(sc.robot.planned_lower_rad, sc.robot.planned_upper_rad)
        if chk.is_free(q):
            results.append(pl.plan(q, sc.goal_rad))
    for res in results:
        assert res.code in ("ok", "disconnected", "path_invalid"), res.reason
        if not res.ok:
            continue
        assert_valid_path(res, sc)
        nodes = res.grid_path_rad
        steps = [nodes[[k, k + 1]] for k in range(len(nodes) - 1)]
        assert all(dense_check(sc.robot, sc.scene, unwrap(s))[0] for s in steps)
    assert sum(r.ok for r in results) >= 5


def test_repairs_on_random_scenes_keep_paths_valid():
    """Random 3-DOF scenes at 36³ where grid walks meet colliding motions (repairs: cut
    grid edges, re-solved fields): every returned path passes the independent check."""
    from spacerobot_planner.bench.scenes import random_scenario
    rng = np.random.default_rng([0, 3])
    repaired = checked = 0
    for _ in range(200):
        sc, start = random_scenario(rng, 3)
        if start is None:
            continue
        pl = Planner(sc)
        try:
            goal = pl.goal_from_target()
        except ValueError:
            continue
        res = pl.plan(start, goal)
        checked += 1
        if res.ok:
            assert_valid_path(res, sc)
        if res.solver_stats.get("repairs", 0) > 0:
            repaired += 1
            if repaired >= 2:
                break
    assert repaired >= 2, f"no repair in {checked} scenes"


def unwrap(q2):
    """Two wrapped rows as a continuous segment (the short way round a periodic joint)."""
    out = np.array(q2, dtype=float)
    d = (out[1] - out[0] + np.pi) % (2 * np.pi) - np.pi
    out[1] = out[0] + d
    return out


@pytest.mark.parametrize("code", CODES)
def test_codes_are_documented(code):
    readme = (CONFIG.parent / "README.md").read_text()
    assert f"`{code}`" in readme, f"README does not explain the result code {code!r}"


def test_path_as_good_as_on_the_fully_converged_field(paper_scenario):
    """Same pipeline on the oracle field (a direct solve to relative precision everywhere):
    path length and minimum clearance within 1 % on both paper scenes."""
    for dof in (2, 3):
        sc = paper_scenario(dof)
        res = Planner(sc).plan(sc.start_rad, sc.goal_rad)
        ref = Planner(sc, solver="oracle").plan(sc.start_rad, sc.goal_rad)
        assert res.ok and ref.ok
        assert abs(res.path_length_rad / ref.path_length_rad - 1.0) < 0.01
        assert abs(res.min_clearance_m / ref.min_clearance_m - 1.0) < 0.01
