"""
Resolution where it is needed (issue 19).

The planner refines a grid that cannot join start and goal, and says what it tried when no
grid does.

The scenes are built here from the geometry of the paper's 2-DOF arm (attitude locked):
- a slot around the outer part of link 3 at the start, 0.08 m wider than the margin on each
  side: the arm leaves it only by sliding link 3 out (the elbow moving along the slot's
  axis), a sliver of C-space that a 4° grid (90 cells) cannot follow and a 2° grid can;
- a block on the elbow's circle that link 2 meets whatever the elbow does, between the
  start's and the goal's shoulder angles: no grid of any resolution joins them.
The paths are checked by the independent geometry of test/oracles.py, the separations by
its flood fill and its segment–polygon distances.
"""

import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from oracles import connected, dense_samples, ref_clearance, wrap_diff
from test_properties import honest_reason
from spacerobot_planner.config import load_scenario
from spacerobot_planner.planner import Planner
from spacerobot_planner.scene import Scene

CONFIG = Path(__file__).resolve().parent.parent / "config"
MARGIN_M = 0.02
START = np.radians([100.0, 90.0])            # link 3 at right angles to link 2


@pytest.fixture(scope="module")
def sc2():
    return load_scenario(CONFIG / "paper_2dof.yaml")


def _arm(robot, q):
    """Shoulder, elbow and link 3's direction (unit) of the planned posture q."""
    att, a2 = robot.full(q)[0], robot.full(q)[0] + robot.full(q)[1]
    shoulder = 1.4 * np.array([math.cos(att), math.sin(att)])
    elbow = shoulder + 2.0 * np.array([math.cos(a2), math.sin(a2)])
    a3 = a2 + robot.full(q)[2]
    return shoulder, elbow, np.array([math.cos(a3), math.sin(a3)])


def slot_walls(robot, q, clear_m: float, depth_m: float):
    """Two 5 cm walls along link 3's last ``depth_m``, ``MARGIN_M + clear_m`` from its axis."""
    _, elbow, d = _arm(robot, q)
    n = np.array([-d[1], d[0]])
    lo, hi = MARGIN_M + clear_m, MARGIN_M + clear_m + 0.05
    return tuple(np.array([elbow + s * d + side * o * n for s, o in
                           ((2.0 - depth_m, lo), (2.1, lo), (2.1, hi), (2.0 - depth_m, hi))])
                 for side in (1, -1))


def test_a_passage_only_a_finer_grid_resolves_is_planned(sc2):
    scene = Scene(target=sc2.scene.target, debris_m=slot_walls(sc2.robot, START, 0.08, 0.6),
                  safety_margin_m=MARGIN_M)
    sc = replace(sc2.with_scene(scene), grid=sc2.grid_with_cells(90))           # 4° steps
    assert ref_clearance(sc.robot, scene, START) > MARGIN_M
    coarse = Planner(sc, max_refinements=0).plan(START, sc2.goal_rad)
    assert coarse.code in ("disconnected", "path_invalid"), coarse.reason
    assert "91x91" in coarse.reason and "max_refinements = 0" in coarse.reason
    honest_reason(coarse.reason, coarse.solver)

    res = Planner(sc).plan(START, sc2.goal_rad)
    assert res.ok, res.reason
    assert res.solver_stats["refinements"] == 1 and res.solver_stats["grid"] == "181x181"
    assert res.cspace.grid.label() == "181x181"
    # exact ends, and free under the independent geometry (plain-Python distances)
    path = res.path_rad
    assert np.array_equal(path[0], START)
    assert np.allclose(wrap_diff(path[-1], sc2.goal_rad), 0.0, atol=1e-12)
    dense = dense_samples(path, np.radians(0.5))
    clearance = np.array([ref_clearance(sc.robot, scene, q) for q in dense])
    assert clearance.min() > MARGIN_M


def walled(sc2, cells: int):
    """
    Return the paper's 2-DOF scene with a block on the elbow's circle, on ``cells`` cells.

    Link 2 meets the block whatever the elbow does, so the bounded shoulder range splits in
    two, the start and the goal on opposite sides.
    """
    att = sc2.robot.locked_rad[0]
    shoulder = 1.4 * np.array([math.cos(att), math.sin(att)])
    u = np.array([math.cos(math.radians(245.0)), math.sin(math.radians(245.0))])
    block = shoulder + 2.0 * u + 0.15 * np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]])
    scene = Scene(target=sc2.scene.target, debris_m=(block,), safety_margin_m=MARGIN_M)
    return replace(sc2.with_scene(scene), grid=sc2.grid_with_cells(cells))


def test_a_start_no_grid_joins_to_the_goal_is_disconnected_with_what_was_tried(sc2):
    sc = walled(sc2, 45)
    scene, att = sc.scene, sc.robot.locked_rad[0]
    # the oracle: at shoulder angles across the block link 2 collides for every elbow angle
    # (link 2's distance does not depend on the elbow), and start and goal lie either side
    a_start, a_goal = (att + q[0] for q in (sc.start_rad, sc.goal_rad))
    wall = [a for a in np.radians(np.arange(240.0, 250.0, 0.1))
            if ref_clearance(sc.robot, scene, [a - att, 0.0]) <= MARGIN_M
            and ref_clearance(sc.robot, scene, [a - att, math.pi / 2]) <= MARGIN_M]
    assert len(wall) > 10 and a_goal < min(wall) and max(wall) < a_start

    res = Planner(sc).plan(sc.start_rad, sc.goal_rad)
    assert res.code == "disconnected", res.reason
    assert "not joined" in res.reason and "46x46 and 91x91" in res.reason, res.reason
    assert "planner.max_refinements = 1" in res.reason
    assert "no collision-free motion" not in res.reason
    honest_reason(res.reason, res.solver)
    # the finest grid tried really separates them (the oracle's flood fill)
    grid, occ = res.cspace.grid, res.cspace.occupied
    assert grid.label() == "91x91"
    assert not connected(occ, grid.periodic, [grid.node_of(sc.start_rad)])[grid.node_of(sc.goal_rad)]


def test_no_refinement_beyond_the_node_budget_and_the_reason_says_so(sc2):
    sc = walled(sc2, 45)
    res = Planner(sc, max_refinements=3, max_grid_nodes=91 * 91).plan(sc.start_rad, sc.goal_rad)
    assert res.code == "disconnected"
    assert "46x46 and 91x91" in res.reason and "181x181 not tried" in res.reason
    assert "planner.max_grid_nodes" in res.reason
    res = Planner(sc, max_refinements=3, max_refined_nodes=91 * 91).plan(sc.start_rad, sc.goal_rad)
    assert "46x46 and 91x91" in res.reason and "181x181 not tried" in res.reason
    assert "max_refined_nodes = 8,281" in res.reason


def test_where_the_doubled_grid_is_above_the_node_limit_the_finest_grid_within_it_is_tried(sc2):
    # the slot of the first test needs a grid finer than 4°; 181x181 (2°) is above the limit,
    # 158x158 (157 cells, 2.29°) is the finest grid with one common factor of the cells within it
    scene = Scene(target=sc2.scene.target, debris_m=slot_walls(sc2.robot, START, 0.08, 0.6),
                  safety_margin_m=MARGIN_M)
    sc = replace(sc2.with_scene(scene), grid=sc2.grid_with_cells(90))
    res = Planner(sc, max_refined_nodes=25_000).plan(START, sc2.goal_rad)
    assert res.ok, res.reason
    assert res.solver_stats["refinements"] == 1 and res.solver_stats["grid"] == "158x158"
    assert res.cspace.grid.n_nodes <= 25_000 < 159 * 159
    dense = dense_samples(res.path_rad, np.radians(0.5))
    assert min(ref_clearance(sc.robot, scene, q) for q in dense) > MARGIN_M
    assert np.array_equal(res.path_rad[0], START)

    # below 1.25 times the cells (113x113) nothing finer is tried, and the reason says so
    res = Planner(sc, max_refined_nodes=112 * 112).plan(START, sc2.goal_rad)
    assert res.code in ("disconnected", "path_invalid"), res.reason
    assert "181x181 not tried" in res.reason and "as is 113x113" in res.reason, res.reason
    assert "max_refined_nodes = 12,544" in res.reason
    honest_reason(res.reason, res.solver)


@pytest.mark.parametrize("cells, periodic, limit", [((16, 16, 16, 16), (True, False, False, False), 500_000),
                                                    ((36, 36, 36), (True, False, False), 300_000),
                                                    ((90, 90), (False, False), 25_000),
                                                    ((7, 9), (True, True), 200)])
def test_the_refined_grid_is_the_finest_within_the_node_limit(sc2, cells, periodic, limit):
    from spacerobot_planner.cspace import GridSpec
    from spacerobot_planner.pipeline import refined
    dof = len(cells)
    grid = GridSpec(cells=cells, periodic=periodic, lower_rad=(-math.pi,) * dof, upper_rad=(math.pi,) * dof)

    def nodes(c):                      # the test's own count: cells on periodic axes, cells + 1 else
        return math.prod(n if p else n + 1 for n, p in zip(c, periodic))
    # brute force over common factors 1.25 ... 2 in steps of 1e-4 (cells rounded down, one more at least)
    best = None
    for f in np.arange(1.25, 2.0 + 1e-9, 1e-4):
        c = tuple(max(n + 1, int(math.floor(f * n))) for n in cells)
        if nodes(c) <= limit and (best is None or nodes(c) > nodes(best)):
            best = c
    got = refined(grid, limit)
    assert got.cells == best and got.n_nodes == nodes(best) <= limit
    assert refined(grid).cells == tuple(2 * n for n in cells)
    assert refined(grid, nodes(tuple(max(n + 1, int(1.25 * n)) for n in cells)) - 1) is None
