"""The offline planner on the paper's scenes: exact ends, dense validity, codes, cache, cancel."""

import math
import threading
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from oracles import (arm_points, dense_samples, link3_and_normal_deg, ref_clearance, shapely_depth, shapely_penetration,
                     wrap_diff)
from spacerobot_planner.bench.scenes import plan_problems
from spacerobot_planner.collision import CollisionChecker
from spacerobot_planner.cspace import build_cspace
from spacerobot_planner.planner import CODES, STAGES, Planner
from spacerobot_planner.scene import Scene, Target

CONFIG = Path(__file__).resolve().parent.parent / "config"
HALF_DEG = np.radians(0.5)
D = np.radians


def dense_check(robot, scene, path, step_rad=np.radians(0.25)):
    """
    Independent check of a path.

    Linear samples at ≤ step_rad (test/oracles.py), CollisionChecker with the margin, bounded
    joints within bounds.

    Returns (all free, min clearance).
    """
    chk = CollisionChecker(robot, scene)
    q = dense_samples(path, step_rad)
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
    assert np.allclose(wrap_diff(p[-1][per], res.goal_rad[per]), 0.0, atol=1e-12)
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
def sc3(paper_scenario):
    return paper_scenario(3)


@pytest.fixture(scope="module")
def sc2(paper_scenario):
    return paper_scenario(2)


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
    assert np.allclose(wrap_diff(d["path_rad"][-1], sc3.goal_rad), 0.0, atol=1e-12)


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


def test_a_scene_keeps_its_own_obstacles_and_its_cache_key(sc3):
    """A debris array its caller changes after making the scene changes neither the scene nor its C-space."""
    square = np.array([[1.5, -2.3], [1.8, -2.3], [1.8, -2.0], [1.5, -2.0]])
    scene = Scene(target=sc3.scene.target, debris_m=(square,), safety_margin_m=sc3.scene.safety_margin_m)
    pl = Planner(replace(sc3, scene=scene))
    first = pl.plan(sc3.start_rad, sc3.goal_rad)
    key, made = scene.geometry_key(), square.copy()
    square += 0.4                                          # the caller's array, after the scene was made
    assert np.array_equal(scene.debris_m[0], made) and scene.geometry_key() == key
    again = pl.plan(sc3.start_rad, sc3.goal_rad)
    assert again.cspace is first.cspace
    moved = Scene(target=sc3.scene.target, debris_m=(square,), safety_margin_m=sc3.scene.safety_margin_m)
    assert moved.geometry_key() != key
    pl.set_scene(moved)
    assert pl.plan(sc3.start_rad, sc3.goal_rad).cspace is not first.cspace
    fresh = build_cspace(sc3.robot, moved, sc3.grid, extra_margin_m=pl.grid_extra_margin_m)
    assert np.array_equal(pl.plan(sc3.start_rad, sc3.goal_rad).cspace.occupied, fresh.occupied)


def test_target_move_rebuilds_cspace_on_the_kept_body_table(sc3):
    """
    A moved target rebuilds the C-space on the kept body table.

    A moved target rebuilds the C-space, reusing the spacecraft-body table, and the result equals a
    build from scratch; fields go with their evicted C-space.
    """
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


@pytest.mark.parametrize("dof", [2, 3])
def test_a_grasp_on_the_safety_margin_is_refused_as_such(dof, sc2, sc3):
    """
    A safety margin equal to the handle's side leaves the grasp no room.

    Oracle: the scene's geometry (``Target``): the grasp point lies the handle's side beyond
    the target body's face, so the tip's clearance at the grasp is that side, the margin,
    and it only rounds above it.  A margin a little smaller plans (a verified path).
    """
    sc = sc2 if dof == 2 else sc3
    side = sc.scene.target.handle_side_m
    res = Planner(sc.with_scene(sc.scene.with_margin(0.99 * side))).plan(sc.start_rad)
    assert res.ok, res.reason
    for margin in (side, 1.2 * side):        # on it, and beyond it (the tip's clearance is below the margin)
        res = Planner(sc.with_scene(sc.scene.with_margin(margin))).plan(sc.start_rad)
        assert res.code == "goal_unreachable" and "sits on the safety margin" in res.reason, (res.code, res.reason)
        assert "target.handle_side_m" in res.reason and f"{margin:g} m is not below" in res.reason, res.reason
        assert res.timings_s.get("field", 0.0) == 0.0          # refused before any grid is built


def test_a_refusal_off_the_normal_names_the_nearer_posture_that_collides():
    """
    "link 3 meets it X° off its normal" is the clear posture's; the one nearer the normal is named with why not.

    The paper's 2-DOF arm with the attitude locked at 140°: the two elbow branches meet the handle
    12.6° and 61.7° off its normal; a debris square on the nearer one's elbow.  The reason had
    quoted 61.7° alone (a hidden-scene audit: "true, but doesn't mention the closer branch").
    Oracle: the test's own two-link inverse kinematics, link angle and clearance.
    """
    import cmath
    from spacerobot_planner.config import load_params_file, scenario_from_params
    f = load_params_file(str(CONFIG / "paper_2dof.yaml"))
    sc = scenario_from_params(dict(f, **{"robot.locked_positions_deg": [140.0, 0.0, 0.0]}))
    robot, att = sc.robot, math.radians(140.0)
    shoulder = complex(*arm_points(robot, [att, 0.0, 0.0])[1])
    grasp = complex(*sc.scene.target.grasp_point_m)
    a, b = robot.link_lengths_m[1], robot.link_lengths_m[2]
    d = abs(grasp - shoulder)
    alpha = math.acos((a * a + d * d - b * b) / (2 * a * d))
    branches = []
    for sign in (1.0, -1.0):
        t1 = cmath.phase(grasp - shoulder) + sign * alpha
        elbow = shoulder + a * cmath.exp(1j * t1)
        t2 = cmath.phase(grasp - elbow)
        q = np.array([att, t1 - att, t2 - t1])
        q[1:] = (q[1:] + math.pi) % (2 * math.pi) - math.pi
        assert np.allclose(arm_points(robot, q)[-1], sc.scene.target.grasp_point_m, atol=1e-9)
        branches.append((link3_and_normal_deg(robot, sc.scene.target, q), q, elbow))
    (near, q_near, elbow), (far, q_far, _) = sorted(branches, key=lambda b: b[0])
    assert near < 20.0 < far                                    # both beyond the 5° bound
    box = [(elbow.real + dx, elbow.imag + dy) for dx, dy in ((-0.2, -0.2), (0.2, -0.2), (0.2, 0.2), (-0.2, 0.2))]
    blocked = sc.with_scene(replace(sc.scene, debris_m=(np.array(box),)))
    assert ref_clearance(robot, blocked.scene, q_near[1:]) <= 0.0 < blocked.scene.safety_margin_m < \
        ref_clearance(robot, blocked.scene, q_far[1:])
    res = Planner(blocked).plan(blocked.start_rad)
    assert res.code == "goal_unreachable", (res.code, res.reason)
    assert f"meets it {far:.1f}° off its normal (the posture {near:.1f}° off it collides)" in res.reason, res.reason


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


@pytest.mark.parametrize("past_rad", [1e-10, 4.5e-16])
def test_a_start_or_goal_a_rounding_past_a_bound_plans_from_the_bound(sc2, sc3, past_rad):
    """
    An elbow at π plus a rounding (a bound of 180° in the file, a joint state in radians) plans from ±180°.

    It had been taken as it was, and every motion from it or to it refused as colliding:
    ``path_invalid`` where the same posture on the bound plans (a hidden-family audit).  Oracle:
    the files' bounds (±180° on the paper arms' elbows) and the independent 0.25° check.
    """
    bound = D(180.0)
    goal = np.array([sc2.goal_rad[0], bound + past_rad])           # the paper 2-DOF goal's elbow is at 180°
    res = Planner(sc2).plan(sc2.start_rad, goal)
    assert_valid_path(res, sc2)
    assert res.path_rad[-1, 1] == bound and np.all(np.abs(res.path_rad[:, 1]) <= bound)
    start = np.array([sc3.start_rad[0], sc3.start_rad[1], -bound - past_rad])
    res = Planner(sc3).plan(start, sc3.goal_rad)
    assert_valid_path(res, sc3)
    assert res.path_rad[0, 2] == -bound and np.all(np.abs(res.path_rad[:, 2]) <= bound)
    res = Planner(sc3).plan(np.array([sc3.start_rad[0], sc3.start_rad[1], -bound - 1e-8]), sc3.goal_rad)
    assert res.code == "invalid_input" and "'elbow' = -180.00000057° is outside its bounds" in res.reason, res.reason
    assert "by 5.7e-07°" in res.reason, res.reason                    # (the value shown is not the bound's)


@pytest.mark.parametrize("turns", [1e17, -2e6])
def test_an_attitude_of_more_turns_than_float64_moves_is_refused_naming_it(sc3, turns):
    """
    A start attitude of 1e17 rad had planned ``ok``, its trajectory's attitude still (float64's step there: 16 rad).

    The published motion is the path shifted by the joint state's whole turns; beyond 1e6 rad
    the start or goal answers invalid_input saying so.  A start at 900 000 rad still plans, its
    trajectory's attitude moving as from the same posture wrapped (oracle: ``math.remainder``).
    """
    import math
    for name, start, goal in (("start", [turns, *sc3.start_rad[1:]], sc3.goal_rad),
                              ("goal", sc3.start_rad, [turns, *sc3.goal_rad[1:]])):
        res = Planner(sc3).plan(np.array(start), np.array(goal))
        assert res.code == "invalid_input" and res.reason.startswith(f"{name}: joint 'attitude' = "), res.reason
        assert "more turns than a plan can carry" in res.reason and "[-π, π)" in res.reason, res.reason
    far = 9e5
    res = Planner(sc3).plan(np.array([far, *sc3.start_rad[1:]]), sc3.goal_rad)
    near = Planner(sc3).plan(np.array([math.remainder(far, 2 * math.pi), *sc3.start_rad[1:]]), sc3.goal_rad)
    assert res.ok and near.ok
    moved, moved_near = (r.trajectory.positions_rad[-1, 0] - r.trajectory.positions_rad[0, 0] for r in (res, near))
    assert res.trajectory.positions_rad[0, 0] == far and abs(moved - moved_near) < 1e-8, (moved, moved_near)


@pytest.mark.parametrize("value", ["abc", [np.float64(1.0), "x", 2.0], {"attitude": 1.0}, np.array(["a", "b", "c"])])
@pytest.mark.parametrize("config", ["paper_3dof", "free_floating_capture"])
def test_a_start_or_goal_that_is_not_numbers_is_named(value, config):
    """
    What is not a number answers invalid_input naming the start or the goal and what was given, no numpy repr.

    The fixed-base route and the free-floating capture's alike.
    """
    from spacerobot_planner.config import load_scenario
    sc = load_scenario(CONFIG / f"{config}.yaml")
    planner, dof = Planner(sc), sc.robot.dof
    for res, name in ((planner.plan(value, sc.goal_rad), "start"), (planner.plan(sc.start_rad, value), "goal")):
        assert res.code == "invalid_input", (name, res.code, res.reason)
        assert res.reason.startswith(f"{name}: expected {dof} joint values"), res.reason
        assert "np." not in res.reason and "array(" not in res.reason and "dtype" not in res.reason, res.reason


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
    """
    With no extra grid margin, adjacent free nodes can be joined by a colliding segment.

    The planner must still only return verified paths.

    Its grid walk takes only motions that pass (the steepest valid neighbour, cutting
    colliding grid edges when none does).
    """
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


def _random_target_plans(n_scenes: int = 200):
    """
    Plan to the target on random 3-DOF scenes at 36³.

    (scenario, start, goal, planner, result) of plans to the target on random 3-DOF scenes at 36³
    (the benchmark's scene family), in a fixed order.
    """
    from spacerobot_planner.bench.scenes import random_scenario
    rng = np.random.default_rng([0, 3])
    for _ in range(n_scenes):
        sc, start = random_scenario(rng, 3)
        if start is None:
            continue
        pl = Planner(sc)
        try:
            goal = pl.goal_from_target()
        except ValueError:
            continue
        yield sc, start, goal, pl, pl.plan(start, goal)


def test_repairs_on_random_scenes_keep_paths_valid():
    """
    Every repaired path on random 3-DOF scenes passes the independent check.

    Random 3-DOF scenes at 36³ where grid walks meet colliding motions (repairs: cut grid edges,
    re-solved fields): every returned path passes the independent check.
    """
    repaired = checked = 0
    for sc, start, goal, pl, res in _random_target_plans():
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
    out[1] = out[0] + wrap_diff(out[1], out[0])
    return out


@pytest.mark.parametrize("code", CODES)
def test_codes_are_documented(code):
    readme = (CONFIG.parent / "README.md").read_text()
    assert f"`{code}`" in readme, f"README does not explain the result code {code!r}"


def test_path_as_good_as_on_the_fully_converged_field(paper_scenario):
    """
    Same pipeline on the oracle field (a direct solve to relative precision everywhere).

    Path length and minimum clearance within 1 % on both paper scenes.
    """
    for dof in (2, 3):
        sc = paper_scenario(dof)
        res = Planner(sc).plan(sc.start_rad, sc.goal_rad)
        ref = Planner(sc, solver="oracle").plan(sc.start_rad, sc.goal_rad)
        assert res.ok and ref.ok
        assert abs(res.path_length_rad / ref.path_length_rad - 1.0) < 0.01
        assert abs(res.min_clearance_m / ref.min_clearance_m - 1.0) < 0.01


# ------------------------------------------------------- caches never change a plan
def _same(a, b):
    assert a.code == b.code
    assert np.array_equal(a.path_rad, b.path_rad) and np.array_equal(a.grid_path_rad, b.grid_path_rad)
    assert {k: v for k, v in a.solver_stats.items()} == {k: v for k, v in b.solver_stats.items()}


def test_plan_a_b_a_gives_a_bit_for_bit(sc3):
    pl = Planner(sc3)
    other = sc3.start_rad + np.radians([40.0, -20.0, 10.0])
    assert CollisionChecker(sc3.robot, sc3.scene).is_free(other)
    a1 = pl.plan(sc3.start_rad, sc3.goal_rad)
    b = pl.plan(other, sc3.goal_rad)
    a2 = pl.plan(sc3.start_rad, sc3.goal_rad)
    assert a1.ok and b.ok and not np.array_equal(a1.path_rad, b.path_rad)
    _same(a1, a2)
    _same(a1, Planner(sc3).plan(sc3.start_rad, sc3.goal_rad))       # a fresh planner agrees


def test_replans_near_a_start_reuse_its_walks_and_equal_fresh_plans(sc3):
    """
    Replans from starts near the paper's keep the descent from their grid node and its grid path's interval checks.

    Each replan equals a fresh planner's plan bit for bit (path, grid path, trajectory); a
    replan whose start joins the same grid node as an earlier one takes its walk from the
    planner's store instead of descending again.
    """
    pl = Planner(sc3)
    pl.plan(sc3.start_rad, sc3.goal_rad)
    chk = CollisionChecker(sc3.robot, sc3.scene)
    rng = np.random.default_rng(5)
    near = [q for q in sc3.start_rad + np.radians(rng.uniform(-2.0, 2.0, size=(12, 3))) if chk.is_free(q)][:5]

    class Counted(dict):
        hits = 0

        def get(self, key, default=None):
            Counted.hits += key in self
            return super().get(key, default)

    pl._walks = Counted(pl._walks)
    for q in near + near[:2]:
        again = pl.plan(q, sc3.goal_rad)
        fresh = Planner(sc3).plan(q, sc3.goal_rad)
        assert again.ok
        _same(again, fresh)
        assert np.array_equal(again.trajectory.times_s, fresh.trajectory.times_s)
        assert again.min_clearance_m == fresh.min_clearance_m
    assert Counted.hits >= 2            # at least the two repeated starts walked from the store


def _first_repaired_plan():
    """Return (scenario, start, goal, planner, result) of the first of :func:`_random_target_plans` that repaired."""
    for sc, start, goal, pl, res in _random_target_plans():
        if res.solver_stats.get("repairs", 0) > 0:
            return sc, start, goal, pl, res
    pytest.fail("no scene needing repairs")


def test_plan_a_b_a_with_repairs_gives_a_bit_for_bit():
    """
    A scene whose plan cuts grid edges / blocks nodes.

    Planning another start in between (which repairs the field too) does not change the repaired
    plan.
    """
    sc, start, goal, pl, a1 = _first_repaired_plan()
    chk = CollisionChecker(sc.robot, sc.scene)
    others = [q for q in np.random.default_rng(1).uniform(sc.robot.planned_lower_rad, sc.robot.planned_upper_rad,
                                                          size=(40, 3)) if chk.is_free(q)][:4]
    for q in others:
        pl.plan(q, goal)
    a2 = pl.plan(start, goal)
    _same(a1, a2)
    _same(a1, Planner(sc).plan(start, goal))


def test_a_replan_that_repairs_as_the_plan_before_equals_a_fresh_planners():
    """
    A replan from a start near a repaired plan's start reuses its repairs' work.

    The planner keeps the colliding grid edges a repair found and the walks that failed, keyed
    by the field and the node (pure functions of those); the replan equals a fresh planner's
    plan from the same start bit for bit, and it walks into the same repairs.
    """
    sc, start, goal, pl, a1 = _first_repaired_plan()
    chk = CollisionChecker(sc.robot, sc.scene)
    rng = np.random.default_rng(3)
    near = [q for q in start + np.radians(rng.uniform(-3.0, 3.0, size=(40, 3))) if chk.is_free(q)
            and np.all(q >= sc.robot.planned_lower_rad) and np.all(q <= sc.robot.planned_upper_rad)]

    class Counted(dict):
        hits = 0

        def get(self, key, default=None):
            Counted.hits += key in self
            return super().get(key, default)

    pl._colliding, pl._failed_walks = Counted(pl._colliding), Counted(pl._failed_walks)
    repaired = 0
    for q in near[:6]:
        again = pl.plan(q, goal)
        _same(again, Planner(sc).plan(q, goal))
        repaired += again.solver_stats.get("repairs", 0) > 0
    assert repaired > 0
    assert Counted.hits > 0         # replans found an earlier plan's repair work in the caches


# ---------------------------------------------------- honest "disconnected"
def test_passage_between_margin_and_grid_margin_is_found(sc2):
    """
    The only way past a block leaves link 2 6 mm more than the safety margin from it.

    Less than the grid's extra margin (20 mm).

    The planner used to answer 'disconnected' at any grid size; now it tries again without
    the extra margin and finds the path.
    """
    from spacerobot_planner.scene import Scene
    m = sc2.scene.safety_margin_m
    att = sc2.robot.locked_rad[0]
    shoulder = 1.4 * np.array([np.cos(att), np.sin(att)])
    u = np.array([np.cos(np.radians(245.0)), np.sin(np.radians(245.0))])
    n = np.array([-u[1], u[0]])
    c = shoulder + (2.0 + m + 0.006 + 0.15) * u                  # a face 2.026 m from the shoulder
    block = np.array([c + 0.15 * (a * u + b * n) for a, b in [(-1, -1), (1, -1), (1, 1), (-1, 1)]])
    scene = Scene(target=sc2.scene.target, debris_m=(block,), safety_margin_m=m)
    for cells in (90, 180):
        sc = sc2.with_scene(scene).with_grid(sc2.grid_with_cells(cells))
        res = Planner(sc).plan(sc.start_rad, sc.goal_rad)
        assert_valid_path(res, sc)
        assert res.solver_stats["grid_extra_margin_m"] == 0.0
        # it went through the passage: the independent check sees the tight clearance
        assert dense_check(sc.robot, scene, res.path_rad)[1] < m + Planner(sc).grid_extra_margin_m


# ------------------------------------------------------------- grasp approach
def test_paper_2dof_grasp_is_near_perpendicular(sc2):
    pl = Planner(sc2)
    goal = pl.goal_from_target()
    err = link3_and_normal_deg(sc2.robot, sc2.scene.target, sc2.robot.full(goal))
    assert err <= 5.0
    res = pl.plan(sc2.start_rad)
    assert res.ok and abs(res.approach_error_deg - err) < 1e-6
    assert res.to_json_dict()["approach_error_deg"] == pytest.approx(err)


def test_random_targets_under_locked_attitude_grasp_perpendicular_or_say_which_attitude(sc2):
    """
    Random targets, attitude locked.

    A goal from the target meets the handle within 5° of its normal, or the answer is
    goal_unreachable naming an attitude at which locking the arm gives a perpendicular grasp
    (checked by planning a goal there), or saying none does.
    """
    import re
    rng = np.random.default_rng(11)
    accepted = refused = advised = 0
    for _ in range(60):
        r, a, yaw = rng.uniform(2.5, 5.2), rng.uniform(-np.pi, np.pi), rng.uniform(-np.pi, np.pi)
        target = Target(center_m=(r * np.cos(a), r * np.sin(a)), yaw_rad=yaw)
        sc = sc2.with_scene(sc2.scene.with_target(target))
        pl = Planner(sc)
        try:
            goal = pl.goal_from_target()
        except ValueError as e:
            msg = str(e)
            if "perpendicular" not in msg:
                continue                      # out of reach or every posture collides
            refused += 1
            res = pl.plan(sc.start_rad)
            assert res.code == "goal_unreachable" and "grasp.max_approach_error_deg" in res.reason
            m = re.search(r"an attitude of (-?[\d.]+)°", msg)
            if m is None:
                assert "attitude" in msg
                continue
            advised += 1
            robot = replace(sc.robot, locked_rad=np.array([np.radians(float(m.group(1))), 0.0, 0.0]))
            relocked = replace(sc, robot=robot)
            q = Planner(relocked).goal_from_target()
            assert link3_and_normal_deg(robot, target, robot.full(q)) < 0.2    # the printed 0.1° rounding
            continue
        accepted += 1
        assert link3_and_normal_deg(sc.robot, target, sc.robot.full(goal)) <= 5.0 + 1e-9
    assert accepted >= 1 and refused >= 5 and advised >= 1, (accepted, refused, advised)


def _random_targets(sc, seed: int, count: int, radii=(2.5, 5.5)):
    """Return ``count`` scenes of ``sc`` with a random target (centre within ``radii`` m of the origin, any yaw)."""
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(count):
        r, a, yaw = rng.uniform(*radii), rng.uniform(-np.pi, np.pi), rng.uniform(-np.pi, np.pi)
        out.append(sc.scene.with_target(Target(center_m=(r * np.cos(a), r * np.sin(a)), yaw_rad=yaw)))
    return out


@pytest.mark.parametrize("case", ["paper_2dof", "servicer_4joint"])
def test_a_kept_planner_finds_the_capture_goal_a_fresh_one_finds(case, sc2):
    """
    The target's capture goal is kept between plans and renewed with the scene and the bound.

    One planner follows random targets and margins (``set_scene``) and approach bounds
    (``configure``: the same bound on a new scene, then changed on it), asked twice each time;
    every answer (the goal's bits, or the refusal's text) is a fresh planner's for the same
    scenario and bound, and the posture meets the handle within the bound (oracle: the link's
    angle to the handle's normal from the test's own geometry).  The kept goal's arrays cannot be
    written by a caller.  The paper's 3-joint arm (one approach angle) and the 4-joint servicer
    (its self-motion sweep, and the approach angles tried up to the bound: one of its targets is
    grasped a few degrees off the normal under a bound of 3° and refused under 1°).
    """
    from spacerobot_planner.config import load_scenario
    if case == "paper_2dof":
        sc, bounds = sc2, (20.0, 5.0, 0.0, 20.0)
        scenes = _random_targets(sc, 5, 12)
    else:
        sc, bounds = load_scenario(CONFIG / "servicer_4joint.yaml"), (6.0, 1.0, 3.0, 6.0)
        scenes = _random_targets(sc, 0, 8, radii=(2.5, 5.0))
    scenes.insert(1, scenes[0].with_margin(scenes[0].target.handle_side_m))     # the same target, another margin
    kept = Planner(sc)
    answers = set()

    def answer(pl):
        try:
            return pl.goal_from_target().tobytes()
        except ValueError as e:
            return str(e)
    for k, scene in enumerate(scenes):
        kept.set_scene(scene)
        for bound in bounds:
            kept.configure(max_approach_error_deg=bound)
            want = answer(Planner(sc.with_scene(scene), max_approach_error_deg=bound))
            assert answer(kept) == want and answer(kept) == want, (k, bound)
            answers.add(isinstance(want, str))
            if isinstance(want, bytes):
                goal = kept.goal_from_target()
                pts = arm_points(sc.robot, sc.robot.full(goal))          # the last link against the normal
                link = (pts[-1] - pts[-2]) / np.linalg.norm(pts[-1] - pts[-2])
                inward = np.array([np.sin(scene.target.yaw_rad), -np.cos(scene.target.yaw_rad)])
                assert np.degrees(np.arccos(np.clip(link @ inward, -1.0, 1.0))) <= bound + 1e-9
                with pytest.raises(ValueError, match="read-only"):
                    kept.capture_goal().q[0] = 0.0
    assert answers == {True, False}                 # both goals and refusals were kept and renewed


# ---------------------------------------------------------------- obstacles thinner than a grid step
def test_the_narrowest_obstacle_is_its_convex_hulls_least_width():
    """
    ``motion.narrowest_obstacle_m`` against GEOS: the hull's least width is over one of its edges.

    Oracle: shapely's convex hull; for each hull edge, its farthest hull vertex (rotating calipers).
    """
    from shapely.geometry import MultiPoint
    from spacerobot_planner.bench.scenes import random_polygon
    from spacerobot_planner.motion import narrowest_obstacle_m
    from spacerobot_planner.config import load_scenario
    robot = load_scenario(CONFIG / "paper_3dof.yaml").robot
    rng = np.random.default_rng(3)
    for _ in range(100):
        polys = [random_polygon(rng) for _ in range(int(rng.integers(1, 4)))]
        margin = float(rng.choice([0.0, 0.02, 0.05]))
        widths = []
        for poly in polys:
            hull = np.asarray(MultiPoint([tuple(v) for v in poly]).convex_hull.exterior.coords)[:-1]
            edges = [(hull[i], hull[(i + 1) % len(hull)]) for i in range(len(hull))]
            widths.append(min(max(abs((b - a)[0] * (v - a)[1] - (b - a)[1] * (v - a)[0]) / np.linalg.norm(b - a)
                                  for v in hull) for a, b in edges))
        chk = CollisionChecker(robot, Scene(target=None, debris_m=tuple(polys), safety_margin_m=margin))
        assert abs(narrowest_obstacle_m(chk) - (min(widths) + 2.0 * margin)) < 1e-9


def test_a_small_piece_of_debris_is_planned_around():
    """
    A 2.5 cm piece of debris, no margin: its C-space image is a sheet thinner than a grid step.

    No grid node marks it; the descent's quick test (1° apart, the arm's tip moving 9 cm) walked
    into it, and the certified check found it one edge, one repair, at a time: 8 repairs at 36³,
    30 at 72³, then path_invalid after about 2 s.  Oracle: the path sampled every 0.05° (no point of
    the arm moves 1 cm between samples), each sample's clearance from GEOS (shapely).
    """
    from oracles import shapely_clearance
    debris = np.array([[-3.34364139256689, -0.7060792574415967], [-3.3350233642188707, -0.6925398322251097],
                       [-3.3452370055803584, -0.6801596877211464], [-3.3601674114386793, -0.6860477628485488],
                       [-3.359181268363464, -0.7020669379095598]])
    from spacerobot_planner.config import load_scenario
    sc0 = load_scenario(CONFIG / "paper_3dof.yaml")          # the paper's 3-DOF robot and 36³ grid
    scene = Scene(target=Target(center_m=(-0.24740833823140237, -3.5203275566171555), yaw_rad=-2.2613788413648406),
                  debris_m=(debris,), safety_margin_m=0.0)
    sc = sc0.with_scene(scene)
    start = np.array([-2.0355858579368826, -1.2257807960226417, -0.007660296994867366])
    goal = np.array([2.7683838305675694, -0.8376114905650383, 1.5786748344857875])
    res = Planner(sc).plan(start, goal)
    assert res.ok, res.reason
    q = dense_samples(res.path_rad, np.radians(0.05))
    clr = min(shapely_clearance(sc.robot, scene, row) for row in q)
    assert clr > 0.0, clr


#: a scene of the stress test's "thin" family (3-DOF seed 1 case 22): a sliver of debris 1.57 m long
#: and 8 mm wide, six small pieces, margin 0.02 m; the start and the target as drawn (rounded to 1e-6)
_SLIVERS = ([[-0.336766, 2.942833], [-0.928301, 1.488241], [-0.920984, 1.485265], [-0.329448, 2.939857]],
            [[5.140157, -1.465255], [5.142723, -1.468708], [5.1468, -1.467334], [5.146754, -1.463033],
             [5.142648, -1.461747]],
            [[-0.340021, -1.567596], [-0.332067, -1.57489], [-0.322672, -1.569579], [-0.32482, -1.559003],
             [-0.335542, -1.557777]],
            [[2.707003, 4.55052], [2.688087, 4.563509], [2.675098, 4.544594], [2.694014, 4.531605]],
            [[-1.850504, 0.618128], [-1.848036, 0.657494], [-1.883362, 0.639948]],
            [[-0.657964, -3.866635], [-0.692452, -3.872502], [-0.686585, -3.90699], [-0.652097, -3.901123]],
            [[-0.331208, 1.972986], [-0.300301, 1.989657], [-0.330192, 2.008088]])


def test_a_long_thin_sliver_is_planned_around():
    """
    A wall of debris thinner than a grid step: its C-space image is a sheet of thousands of grid edges.

    Each repair cut the colliding edges it found within 2 000 tested ones: a hundred at a time,
    30 repairs at 72³, then path_invalid after about 5 s (a path keeping 51 mm exists).  The
    budget doubles with each repair of a plan.  Oracle: the path sampled every 0.05°, each
    sample's clearance from GEOS (shapely) above the margin.
    """
    from oracles import shapely_clearance
    from spacerobot_planner.config import load_scenario
    scene = Scene(target=Target(center_m=(-2.518980, 2.375767), yaw_rad=-3.040064),
                  debris_m=tuple(np.array(d) for d in _SLIVERS), safety_margin_m=0.02)
    sc = load_scenario(CONFIG / "paper_3dof.yaml").with_scene(scene)
    res = Planner(sc).plan(np.array([-0.163281, 2.134411, -1.042154]))      # the goal: the target's capture
    assert res.ok, res.reason
    clr = min(shapely_clearance(sc.robot, scene, row) for row in dense_samples(res.path_rad, np.radians(0.05)))
    assert clr > 0.02, clr


# ---------------------------------------------------------------- leaving a contact
def _captured_then_moved(sc, d_m):
    """Return the capture posture of sc's target, and sc with the target moved d_m towards the arm."""
    q_cap = Planner(sc).goal_from_target()
    t = sc.scene.target
    a = t.approach_angle_rad
    centre = np.asarray(t.center_m) - d_m * np.array([np.cos(a), np.sin(a)])
    return q_cap, sc.with_scene(sc.scene.with_target(Target(center_m=tuple(centre), yaw_rad=t.yaw_rad)))


@pytest.mark.parametrize("dof, d_m", [(3, 0.10), (3, 0.13), (2, 0.10)])
def test_target_moved_into_the_captured_posture_is_left(paper_scenario, dof, d_m):
    sc0 = paper_scenario(dof)
    q_cap, sc = _captured_then_moved(sc0, d_m)
    chk = CollisionChecker(sc.robot, sc.scene)
    assert not chk.is_free(q_cap)
    res = Planner(sc).plan(q_cap, sc0.start_rad)
    assert res.ok, res.reason
    ex = res.exit_path_rad
    assert len(ex) >= 2 and np.array_equal(ex[0], res.start_rad)
    assert abs(res.start_penetration_m - shapely_depth(sc.robot, sc.scene, q_cap)) < 1.5e-3
    # the exit stretch is the start of the path, in ≤ 0.5° steps, bounded, ending free
    assert np.array_equal(res.path_rad[:len(ex)], ex)
    assert np.max(np.linalg.norm(np.diff(ex, axis=0), axis=1)) <= HALF_DEG + 1e-12
    assert np.sum(np.linalg.norm(np.diff(ex, axis=0), axis=1)) <= np.radians(30.0)
    assert chk.clearance_m(ex[-1]) > sc.scene.safety_margin_m
    # everything after it passes the independent dense check
    rest = res.path_rad[len(ex) - 1:]
    free, clr = dense_check(sc.robot, sc.scene, rest)
    assert free and clr > sc.scene.safety_margin_m
    assert np.allclose(wrap_diff(rest[-1], sc0.start_rad), 0.0, atol=1e-12)
    assert res.to_json_dict()["exit"]["certified"] is False


def test_an_answer_after_a_way_out_of_contact_names_both_starts(sc2):
    """
    The arm starts in contact (the target moved onto the captured arm) on the far side of a wall.

    The answer names where the way out ends (the plan's start) and where the arm was: a user
    reading only the first would not recognise their start.  The wall: a debris block on the
    elbow's circle that link 2 cannot sweep past (as in ``test_disconnected_regions``).
    """
    q_cap, sc = _captured_then_moved(sc2, 0.10)
    shoulder = 1.4 * np.array([np.cos(np.radians(160.7)), np.sin(np.radians(160.7))])
    c = shoulder + 2.0 * np.array([np.cos(np.radians(245.0)), np.sin(np.radians(245.0))])
    block = c + 0.15 * np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]])
    sc = replace(sc.with_scene(Scene(target=sc.scene.target, debris_m=(block,),
                                     safety_margin_m=sc.scene.safety_margin_m)), grid=sc2.grid_with_cells(90))
    assert not CollisionChecker(sc.robot, sc.scene).is_free(q_cap)
    res = Planner(sc).plan(q_cap, sc2.start_rad)
    assert res.code == "disconnected", (res.code, res.reason)
    arm_deg = ", ".join(f"{v:.1f}" for v in np.degrees(q_cap))
    assert f"(where the way out of contact from ({arm_deg})° ends)" in res.reason, res.reason


@pytest.mark.parametrize("dof", [2, 3])
def test_penetration_depths_meet_a_shapely_oracle_on_random_postures(dof):
    """
    The exit's penetration depth (``contact.penetration_depths_m``) against GEOS's geometry.

    Random scenes of the ``bench scenes`` family and random postures, many of them with a link
    inside the spacecraft body (turned by the attitude) or an obstacle: each depth within
    1.2 mm of the oracle's (the kernel samples links every 2 mm, within 1 mm; the oracle every
    0.25 mm), and 0 exactly where no link enters a polygon.  Scenes with a
    self-intersecting obstacle (about 2 in 100 of the family) are passed over: GEOS has no
    inside for them, the kernel the even-odd one.
    """
    from shapely.geometry import Polygon
    from spacerobot_planner.bench.scenes import random_scenario
    from spacerobot_planner.contact import penetration_depth_m, penetration_depths_m
    rng = np.random.default_rng([41, dof])
    inside = outside = 0
    for _ in range(14):
        sc, _start = random_scenario(rng, dof)
        if not all(Polygon(p).is_valid for p in sc.scene.obstacle_polygons_m):
            continue
        chk = CollisionChecker(sc.robot, sc.scene)
        qs = rng.uniform(sc.robot.planned_lower_rad, sc.robot.planned_upper_rad, size=(25, dof))
        got = penetration_depths_m(chk, qs)
        for q, depth in zip(qs, got):
            ref = shapely_penetration(sc.robot, sc.scene, q)
            assert abs(depth - ref) < 1.2e-3, (q, depth, ref)
            if ref == 0.0:
                assert depth == 0.0, (q, depth)
                outside += 1
            else:
                inside += 1
        assert penetration_depth_m(chk, qs[0]) == got[0]          # one posture: the same value
    assert inside >= 40 and outside >= 40, (inside, outside)


@pytest.mark.parametrize("dof", [2, 3])
def test_each_step_out_of_a_contact_is_the_best_neighbour_by_the_tests_geometry(dof):
    """
    The walk out of a contact (``contact.leave_contact``) judged by GEOS (shapely) and the test's own steps.

    Random scenes of the ``bench scenes`` family, starts drawn within the margin of the body or an
    obstacle (many inside): every step is one of the test's 3^dof - 1 grid directions scaled to
    0.25°, the rows stay within the bounds, the signed distance the walk reports at each row
    (clearance outside, minus the penetration depth inside) is the oracle's (clearance to 1e-9 m,
    depth to 1.3 mm: the kernel samples links every 2 mm, the oracle every 0.5 mm), it increases,
    and no direction within the bounds has an oracle signed distance more than 2.6 mm above the
    one taken (the walk takes the best; its depths are within 1 mm).  A walk that ends in the room
    it asks for ends there.
    """
    import itertools
    from shapely.geometry import LineString, Polygon
    from oracles import _polygons
    from spacerobot_planner.bench.scenes import random_scenario
    from spacerobot_planner.contact import leave_contact
    from spacerobot_planner.motion import MotionValidator

    def signed(sc, q):
        q_full = sc.robot.full(q)
        pts = arm_points(sc.robot, q_full)
        clr = min(LineString([pts[k], pts[k + 1]]).distance(Polygon(poly))
                  for k in sc.robot.checked_links for poly in _polygons(sc.robot, sc.scene, q_full[0]))
        return clr if clr > 0.0 else -shapely_penetration(sc.robot, sc.scene, q, spacing_m=5e-4)

    step = np.radians(0.25)
    dirs = np.array([d for d in itertools.product((-1.0, 0.0, 1.0), repeat=dof) if any(d)])
    dirs = step * dirs / np.linalg.norm(dirs, axis=1, keepdims=True)
    rng = np.random.default_rng([43, dof])
    walks = steps = inside = 0
    while walks < 6:
        sc, _start = random_scenario(rng, dof)
        if not all(Polygon(p).is_valid for p in sc.scene.obstacle_polygons_m):
            continue                      # GEOS has no inside for a self-intersecting polygon
        motions = MotionValidator.for_scene(sc.robot, sc.scene)
        lo, hi, per = sc.robot.planned_lower_rad, sc.robot.planned_upper_rad, np.array(sc.robot.planned_periodic)
        qs = rng.uniform(lo, hi, size=(4000, dof))
        qs = qs[motions.clearance_m(qs) <= sc.scene.safety_margin_m]
        for q0 in qs[:2]:
            ex = leave_contact(motions, q0, max_penetration_m=0.05, max_length_rad=np.radians(5.0))
            if ex.start_penetration_m > 0.05:
                continue
            walks += 1
            rows = ex.path_rad
            assert np.array_equal(rows[0], q0)
            for k, row in enumerate(rows):
                got = ex.signed_distance_m[k]
                ref = signed(sc, row)
                assert abs(got - ref) <= (1e-9 if ref > 0.0 else 1.3e-3), (k, got, ref)
                inside += ref < 0.0
                assert np.all(per | ((row >= lo) & (row <= hi)))
                if k == 0:
                    continue
                assert got > ex.signed_distance_m[k - 1]
                d = row - rows[k - 1]
                assert np.min(np.max(np.abs(dirs - d), axis=1)) < 1e-12, d
                cands = rows[k - 1] + dirs
                cands = cands[np.all(per | ((cands >= lo) & (cands <= hi)), axis=1)]
                best = max(signed(sc, c) for c in cands)
                assert best <= ref + 2.6e-3, (k, best, ref)
                steps += 1
            if ex.ok:
                assert ex.signed_distance_m[-1] >= sc.scene.safety_margin_m + 0.01
    assert steps >= 20 and inside >= 5, (steps, inside)


def test_the_walks_length_limit_takes_any_number(paper_scenario):
    """
    ``leave_contact``'s ``max_length_rad``: negative walks nothing, a huge one allocates as it walks.

    From the captured posture with the target moved onto it (as above): no limit is reached by a
    walk that ends in the room it asks for, so 30° and 10⁶ rad give the same walk; a negative limit
    gives the start alone, refused with its clearance.  (The rows had been allocated for the limit
    up front: a negative one raised, 10⁶ rad asked for gigabytes.)
    """
    from spacerobot_planner.contact import leave_contact
    from spacerobot_planner.motion import MotionValidator
    q_cap, sc = _captured_then_moved(paper_scenario(3), 0.10)
    motions = MotionValidator.for_scene(sc.robot, sc.scene)
    short = leave_contact(motions, q_cap, max_penetration_m=0.05)
    assert short.ok and len(short.path_rad) > 1
    huge = leave_contact(motions, q_cap, max_penetration_m=0.05, max_length_rad=1e6)
    assert huge.ok and np.array_equal(huge.path_rad, short.path_rad)
    none = leave_contact(motions, q_cap, max_penetration_m=0.05, max_length_rad=-1.0)
    assert not none.ok and none.path_rad.shape == (1, 3) and np.array_equal(none.path_rad[0], q_cap)
    assert "no free posture within" in none.reason


def test_deep_start_collision_still_refused(paper_scenario):
    sc0 = paper_scenario(3)
    q_cap, sc = _captured_then_moved(sc0, 0.20)             # link 3 10 cm inside the body
    res = Planner(sc).plan(q_cap, sc0.start_rad)
    assert res.code == "start_in_collision" and "planner.max_start_penetration_m" in res.reason
    # what the arm reaches into, and what to do: the target (moved onto the captured arm here, the
    # scene's only obstacle; the test's own depth into it is beyond the 5 cm walked out of)
    assert sc.scene.debris_m == () and shapely_depth(sc.robot, sc.scene, q_cap) > 0.05
    assert "m into the target body" in res.reason and "(move the target away from the arm" in res.reason, res.reason
    off = Planner(sc, max_start_penetration_m=0.0).plan(Planner(sc0).goal_from_target(), sc0.start_rad)
    assert off.code == "start_in_collision"
    _, touching = _captured_then_moved(sc0, 0.10)
    assert Planner(touching, max_start_penetration_m=0.0).plan(q_cap, sc0.start_rad).code == "start_in_collision"


# ------------------------------------------------------------------ trajectory stage
@pytest.mark.parametrize("turn_deg", [20.0, 90.0, 150.0])
def test_a_plan_given_the_arms_direction_leaves_its_start_along_it(planner3, sc3, plan3, turn_deg):
    """
    A replan from a moving arm leaves its start along the arm's direction (``start_tangent``).

    Directions ``turn_deg`` off the path the plan takes from rest: the path's direction at its
    start (the test's quadratic through its first three samples) is within 1.5° of the given
    one, the path ends exactly at start and goal, and every dense sample of its polyline keeps
    the scene's margin (shapely).  A direction of the wrong
    length or all zero answers invalid_input, naming it.
    """
    from oracles import shapely_clearance
    from paper_paths import turned
    d = turned(plan3.path_rad[1] - plan3.path_rad[0], turn_deg)
    res = planner3.plan(sc3.start_rad, sc3.goal_rad, start_tangent=3.0 * d)     # any length: its direction
    assert res.ok, res.reason
    p = res.path_rad
    # the path's direction at its start: the derivative at 0 of the quadratic through its first
    # three samples, by their chord lengths (the first step's chord alone turns off it by half
    # the curve's bend over the step)
    h1, h2 = np.linalg.norm(p[1] - p[0]), np.linalg.norm(p[2] - p[1])
    first = -(2 * h1 + h2) / (h1 * (h1 + h2)) * p[0] + (h1 + h2) / (h1 * h2) * p[1] - h1 / (h2 * (h1 + h2)) * p[2]
    first = first / np.linalg.norm(first)
    assert np.degrees(np.arccos(np.clip(first @ d, -1.0, 1.0))) < 1.5
    np.testing.assert_array_equal(p[0], sc3.start_rad)
    np.testing.assert_allclose(wrap_diff(p[-1], sc3.goal_rad), 0.0, atol=1e-9)
    assert min(shapely_clearance(sc3.robot, sc3.scene, q) for q in dense_samples(p)[::3]) > sc3.scene.safety_margin_m
    for bad in ([0.0, 0.0, 0.0], [1.0, 0.0], [np.nan, 1.0, 0.0]):
        out = planner3.plan(sc3.start_rad, sc3.goal_rad, start_tangent=bad)
        assert out.code == "invalid_input" and "start_tangent" in out.reason


def test_result_carries_a_trajectory_aligned_to_the_raw_state(planner3, sc3):
    raw = sc3.start_rad + np.array([4 * np.pi, 0.0, 0.0])       # joint_states: two turns on
    res = planner3.plan(raw, sc3.goal_rad)
    assert res.ok and res.trajectory is not None
    tr = res.trajectory
    assert np.array_equal(tr.positions_rad[0], raw)
    assert np.allclose(tr.positions_rad - 4 * np.pi * np.array([1, 0, 0]), res.path_rad, atol=1e-9)
    # limits from the scenario file, checked by finite differences written here
    vmax = np.radians([5.0, 15.0, 15.0])
    dt = np.diff(tr.times_s)
    v = np.diff(tr.positions_rad, axis=0) / dt[:, None]
    assert tr.times_s[0] == 0.0 and np.all(dt > 0) and np.all(np.abs(v) <= vmax * 1.001)
    d = res.to_json_dict()["trajectory"]
    for key in ("joint_names", "times_s", "positions_rad", "velocities_rad_s", "accelerations_rad_s2"):
        assert key in d
    assert res.reaction is None                  # held attitude, no wheel limits: no reaction stage


def test_no_trajectory_without_limits(sc3):
    res = Planner(replace(sc3, joint_limits=None)).plan(sc3.start_rad, sc3.goal_rad)
    assert res.ok and res.trajectory is None and "trajectory" not in res.to_json_dict()


def test_codes_are_strings_on_the_wire(plan3):
    from spacerobot_planner.planner import Code
    assert plan3.code is Code.OK and plan3.code == "ok" and f"{plan3.code}" == "ok"
    import json
    assert json.loads(json.dumps(plan3.to_json_dict()))["code"] == "ok"


@pytest.mark.parametrize("solver", ["log_harmonic", "gauss_seidel"])
def test_a_plan_that_repairs_answers_a_clear_path_with_either_solver(solver):
    """
    A descent blocked by colliding grid edges: the repair cuts them, with the paper's solver too.

    Scene 13 of ``bench scenes``' 3-DOF family, whose plan repairs (the cut edges are walls in
    either solver; before, gauss_seidel answered internal_error).  The path's dense samples clear
    the margin by the oracle's distances.
    """
    gen = plan_problems(np.random.default_rng([0, 3]), 3)
    for _ in range(14):
        sc, start, _, goal = next(gen)
    res = Planner(sc, solver=solver).plan(start, goal)
    assert res.ok, (res.code, res.reason)
    assert res.solver_stats["repairs"] >= 1 and res.solver_stats["cut_edges"] > 0
    clearance = min(ref_clearance(sc.robot, sc.scene, q) for q in dense_samples(res.path_rad, np.radians(0.25)))
    assert clearance > sc.scene.safety_margin_m - 1e-6


@pytest.mark.parametrize("seed, index, max_repairs, says", [
    (0, 13, 0, "no grid path from the start (no repair tried: planner.max_repairs = 0)"),
    (2, 104, 1, "after 1 repair, no grid path from the start (planner.max_repairs = 1 reached)"),
    (1, 22, 1, "1 repair, a grid path whose straight segments collide (planner.max_repairs = 1 reached)"),
])
def test_a_plan_stopped_by_the_repair_limit_says_so(seed, index, max_repairs, says):
    """
    A plan that the repairs' limit stopped answers path_invalid naming planner.max_repairs, not the grid alone.

    Scenes of ``bench scenes``' 3-DOF family that plan with more repairs (on the one grid: no
    refinement): a walk blocked, and a grid path whose straight segment collides.
    """
    gen = plan_problems(np.random.default_rng([seed, 3]), 3)
    for _ in range(index + 1):
        sc, start, _, goal = next(gen)
    res = Planner(sc, max_repairs=max_repairs, max_refinements=0).plan(start, goal)
    assert res.code == "path_invalid", (res.code, res.reason)
    assert says in res.reason, res.reason
    more = Planner(sc, max_refinements=0).plan(start, goal)
    assert more.ok and more.solver_stats["repairs"] > max_repairs, (more.code, more.reason)
