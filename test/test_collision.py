"""
Exact collision tests and the C-space against independent brute-force checks.

The oracles (test/oracles.py) share nothing with the numba kernels: ``ref_clearance``
(parametric intersection by Cramer's rule, winding-number containment, projection
distances, plain Python floats) and ``shapely_clearance`` (GEOS), both on the arm's joint
points from complex numbers.
"""

import os

import numpy as np
import pytest
from conftest import CONFIG_DIR
from oracles import ref_clearance, shapely_clearance

from spacerobot_planner.collision import CollisionChecker
from spacerobot_planner.config import load_scenario
from spacerobot_planner.cspace import GridSpec, build_cspace
from spacerobot_planner.scene import Scene

D = np.radians


# ------------------------------------------------------------------- scenes
DEBRIS = (
    [[-1.0, 2.2], [0.0, 2.0], [0.2, 2.8], [-0.8, 3.0]],                      # convex quad
    [[2.0, -1.0], [3.2, -1.0], [3.2, 0.2], [2.6, -0.4], [2.0, 0.2]],         # non-convex (notch)
    [[-4.5, 0.5], [-3.9, 0.5], [-4.2, 1.2]],                                  # triangle
)


@pytest.fixture(scope="module", params=["paper_2dof", "paper_3dof"])
def scenario(request):
    sc = load_scenario(os.path.join(CONFIG_DIR, f"{request.param}.yaml"))
    scene = Scene(target=sc.scene.target, debris_m=tuple(np.array(p) for p in DEBRIS), safety_margin_m=0.05)
    return sc.with_scene(scene)


def test_start_postures_clear_the_body_as_the_paper_draws_them():
    for name in ("paper_2dof", "paper_3dof"):
        sc = load_scenario(os.path.join(CONFIG_DIR, f"{name}.yaml"))
        chk = CollisionChecker(sc.robot, sc.scene)
        c = chk.clearance_m(sc.start_rad)
        assert 0.08 <= c <= 0.12, (name, c)
        assert chk.is_free(sc.start_rad)
        assert chk.is_free(sc.goal_rad), name


def test_clearance_matches_reference_on_random_configurations(scenario):
    rng = np.random.default_rng(1)
    chk = CollisionChecker(scenario.robot, scenario.scene)
    q = rng.uniform(scenario.robot.planned_lower_rad, scenario.robot.planned_upper_rad,
                    size=(400, scenario.robot.dof))
    got = chk.clearance_m(q)
    want = np.array([ref_clearance(scenario.robot, scenario.scene, qi) for qi in q])
    assert np.allclose(got, want, atol=1e-9)
    # both kinds were exercised (clearance never exceeds 0.127 m: the shoulder sits that far
    # beyond the body corner)
    assert (want == 0).sum() > 20 and (want > 0.05).sum() > 20


def test_clearance_and_freedom_match_shapely(scenario):
    rng = np.random.default_rng(5)
    chk = CollisionChecker(scenario.robot, scenario.scene)
    q = rng.uniform(scenario.robot.planned_lower_rad, scenario.robot.planned_upper_rad,
                    size=(300, scenario.robot.dof))
    want = np.array([shapely_clearance(scenario.robot, scenario.scene, qi) for qi in q])
    assert np.allclose(chk.clearance_m(q), want, atol=1e-9)
    margin = scenario.scene.safety_margin_m
    away = np.abs(want - margin) > 1e-9
    assert np.array_equal(chk.is_free(q)[away], want[away] > margin)
    assert (want == 0).sum() > 20 and (want > margin).sum() > 20


@pytest.mark.parametrize("oracle, cells, n_nodes, seed", [
    (ref_clearance, (36, 90), 1500, 2), (shapely_clearance, (24, 60), 600, 6)])
def test_cspace_occupancy_equals_brute_force(scenario, oracle, cells, n_nodes, seed):
    """Random grid nodes: occupied exactly when the oracle's clearance is within the margin."""
    grid = scenario.grid.with_cells(cells[0] if scenario.robot.dof == 3 else cells[1])
    cs = build_cspace(scenario.robot, scenario.scene, grid)
    assert cs.occupied.shape == grid.shape
    rng = np.random.default_rng(seed)
    nodes = np.stack([rng.integers(0, n, size=n_nodes) for n in grid.shape], axis=1)
    margin = scenario.scene.safety_margin_m
    checked = 0
    for node in nodes:
        c = oracle(scenario.robot, scenario.scene, grid.config_of(node))
        if abs(c - margin) < 1e-9:
            continue       # on the margin itself: either answer is exact to rounding
        assert cs.occupied[tuple(node)] == (c <= margin), (node, c)
        checked += 1
    occ = cs.occupied[tuple(nodes.T)]
    assert checked > 0.93 * n_nodes and 0.05 < occ.mean() < 0.95


def test_margin_grows_the_obstacles(scenario):
    grid = scenario.grid.with_cells(36 if scenario.robot.dof == 3 else 90)
    tight = build_cspace(scenario.robot, scenario.scene.with_margin(0.0), grid)
    wide = build_cspace(scenario.robot, scenario.scene.with_margin(0.2), grid)
    assert np.all(wide.occupied >= tight.occupied) and wide.occupied.sum() > tight.occupied.sum()


def test_attitude_wraps_minus_180_is_plus_180():
    sc = load_scenario(os.path.join(CONFIG_DIR, "paper_3dof.yaml"))
    g = sc.grid
    assert g.shape == (36, 37, 37)
    assert g.node_of(D([-180.0, 0.0, 0.0])) == g.node_of(D([180.0, 0.0, 0.0])) == (0, 18, 18)
    assert g.node_of(D([179.0, 0.0, 0.0]))[0] == 0           # nearer to +180 ≡ -180 than to 170
    assert g.node_of(D([-176.0, 0.0, 0.0]))[0] == 0
    assert g.node_of(D([174.0, 0.0, 0.0]))[0] == 35
    cs = build_cspace(sc.robot, sc.scene, g)
    # the occupancy at the -180 node is the occupancy of the +180 configuration
    chk = CollisionChecker(sc.robot, sc.scene)
    for j, k in [(18, 18), (30, 27), (5, 33), (20, 10)]:
        q_plus = np.array([np.pi, *g.config_of((0, j, k))[1:]])
        assert cs.occupied[0, j, k] == (not chk.is_free(q_plus))


def test_node_of_rejects_out_of_bounds_and_nan():
    g = GridSpec((10, 10), (0.0, -1.0), (1.0, 1.0), (False, False))
    with pytest.raises(ValueError, match="axis 1"):
        g.node_of(np.array([0.5, 1.2]))
    with pytest.raises(ValueError, match="axis 0 is nan"):
        g.node_of(np.array([np.nan, 0.0]))
    assert g.node_of(np.array([1.0, 1.0])) == (10, 10)


def test_touching_counts_as_collision_with_zero_margin():
    sc = load_scenario(os.path.join(CONFIG_DIR, "paper_2dof.yaml"))
    # a debris square whose edge passes exactly through the start posture's elbow
    q = sc.start_rad
    elbow = sc.robot.forward_kinematics(sc.robot.full(q))[2]
    sq = np.array([[0, 0], [0.5, 0], [0.5, 0.5], [0, 0.5]]) + elbow
    chk = CollisionChecker(sc.robot, Scene(sc.scene.target, (sq,), 0.0))
    assert chk.clearance_m(q) == 0.0 and not chk.is_free(q)


def test_cached_body_table_gives_the_same_occupancy():
    from spacerobot_planner.cspace import body_occupancy
    from spacerobot_planner.scene import Target
    sc = load_scenario(os.path.join(CONFIG_DIR, "paper_3dof.yaml"))
    table = body_occupancy(sc.robot, sc.grid, sc.scene.safety_margin_m)
    assert table.shape == sc.grid.shape[1:]
    # the table serves another target pose unchanged (it only knows the body)
    moved = sc.scene.with_target(Target(center_m=(-2.0, 3.0), yaw_rad=0.7))
    fresh = build_cspace(sc.robot, moved, sc.grid)
    reused = build_cspace(sc.robot, moved, sc.grid, body_table=table)
    assert np.array_equal(fresh.occupied, reused.occupied)
    with pytest.raises(ValueError, match="body_table"):
        build_cspace(sc.robot, moved, sc.grid, body_table=table[:-1])


@pytest.mark.parametrize("seed", range(4))
@pytest.mark.parametrize("locked_elbow", [False, True])
def test_cspace_rows_and_node_fallback_equal_brute_force_on_random_scenes(seed, locked_elbow):
    """
    Random debris and margins.

    The row-interval fill (last axis = the last joint) and, with the elbow locked, the node-by-node
    fill, both against the reference clearance.
    """
    from dataclasses import replace

    from spacerobot_planner.bench.scenes import random_scenario
    rng = np.random.default_rng(100 + seed)
    sc, _ = random_scenario(rng, 2 + seed % 2)
    robot = sc.robot
    if locked_elbow:
        locked = np.array(robot.locked_rad)
        locked[2] = D(40.0)
        robot = replace(robot, planned_joints=tuple(j for j in robot.planned_joints if j != 2),
                        locked_rad=locked)
    from spacerobot_planner.cspace import grid_for_robot
    grid = grid_for_robot(robot, [24] * robot.dof if robot.dof == 3 else [60] * robot.dof)
    for margin in (0.0, 0.05):
        scene = sc.scene.with_margin(margin)
        cs = build_cspace(robot, scene, grid)
        nodes = np.stack([rng.integers(0, n, size=600) for n in grid.shape], axis=1)
        for node in nodes:
            c = ref_clearance(robot, scene, grid.config_of(node))
            if abs(c - margin) < 1e-9:
                continue
            assert cs.occupied[tuple(node)] == (c <= margin), (node, c, margin)
