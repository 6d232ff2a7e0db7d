"""Tests of spacerobot_planner.field (harmonic field solvers)."""
import dataclasses
import math
import os
import sys

import numpy as np
import pytest

sys.path.insert(0, os.path.dirname(__file__))
import mazes  # noqa: E402

from spacerobot_planner import field as F  # noqa: E402
from spacerobot_planner.config import load_scenario  # noqa: E402
from spacerobot_planner.cspace import build_cspace  # noqa: E402
from spacerobot_planner.descent import descend, reaches_goal_mask  # noqa: E402


def _reachable_free(occ, per, goal):
    return F.bfs_distance(occ, per, [goal]) >= 0


def test_gauss_seidel_and_sor_agree_on_181():
    occ, start, goal = mazes.blocks_2d(181)
    per = (False, False)
    phi, gs_sweeps, gs_change = F.gauss_seidel_phi(occ, per, [goal], tol=1e-11)
    u, sor_sweeps, _ = F.sor_u(occ, per, [goal], tol=1e-13)
    assert gs_change < 1e-11
    assert sor_sweeps < gs_sweeps / 5
    free = ~occ
    assert np.max(np.abs((1.0 - phi) - u)[free]) < 1e-6
    # obstacles and the closed pocket keep their boundary / initial values
    assert np.all(phi[occ] == 1.0) and np.all(u[occ] == 0.0)
    pocket = free & ~_reachable_free(occ, per, goal)
    assert pocket.any() and np.all(phi[pocket] == 1.0) and np.all(u[pocket] == 0.0)
    # the log form solves the same problem
    # (tol is the absolute change per sweep, rel_tol the relative one of the tail)
    lh = F.solve_field(occ, per, [goal], tol=1e-12, rel_tol=1e-8)
    big = u > 1e-6
    assert lh.converged and lh.solver == "log_harmonic"
    assert np.max(np.abs(lh.log_u[big] - np.log(u[big]))) < 1e-5
    assert np.all(lh.reachable == _reachable_free(occ, per, goal))


def test_sor_odd_periodic_axis_matches_gauss_seidel_3d():
    occ = np.zeros((35, 15, 13), dtype=bool)
    occ[10:20, 3:12, 2:11] = True
    per = (True, False, False)
    goal = (30, 7, 6)
    phi, _, change = F.gauss_seidel_phi(occ, per, [goal], tol=1e-12)
    u, _, _ = F.sor_u(occ, per, [goal], tol=1e-13)
    assert np.max(np.abs((1.0 - phi) - u)) < 1e-8
    u2, _, _ = F.sor_u(occ, per, [goal], tol=1e-13)
    assert np.array_equal(u, u2)            # deterministic despite threads


def _assert_no_local_max(field):
    defects = F.ascent_defects(field.log_u, field.goal_mask, field.periodic)
    assert defects.shape[0] == 0, f"local maxima at {defects[:5].tolist()}"
    ok = reaches_goal_mask(field)
    assert np.array_equal(ok, field.reachable)


def test_log_harmonic_no_interior_local_maximum_2d():
    occ, start, goal = mazes.blocks_2d(181)
    per = (False, False)
    f = F.solve_field(occ, per, [goal])
    assert f.solver == "log_harmonic" and f.converged
    assert f.log_u[goal] == 0.0 and np.all(f.log_u[occ] == -np.inf)
    _assert_no_local_max(f)
    assert descend(f, start).reached


def test_log_harmonic_no_interior_local_maximum_3d_periodic():
    occ, per, start, goal = mazes.blocks_3d((36, 37, 37))
    f = F.solve_field(occ, per, [goal])
    assert f.converged
    _assert_no_local_max(f)
    assert descend(f, start).reached


@pytest.mark.parametrize("passes", [0, 1, 2, 5])
def test_log_gs_is_anytime(passes):
    """Any plain GS iterate from the BFS lower bound is a valid ascent field."""
    occ, per, start, goal = mazes.blocks_3d((36, 37, 37))
    f = F.solve_field(occ, per, [goal], solver="log_gs", max_sweeps=passes)
    assert f.sweeps == passes and not f.converged
    _assert_no_local_max(f)


def test_log_harmonic_matches_converged_log_gs():
    occ, per, start, goal = mazes.blocks_3d((36, 37, 37))
    a = F.solve_field(occ, per, [goal], tol=1e-12, rel_tol=1e-9)
    b = F.solve_field(occ, per, [goal], solver="log_gs", tol=1e-10)
    r = a.reachable
    assert np.array_equal(r, b.reachable)
    assert np.max(np.abs(a.log_u[r] - b.log_u[r])) < 1e-4


@pytest.mark.parametrize("scene", [mazes.seam_scene_2d, mazes.seam_scene_3d])
def test_descent_crosses_periodic_seam(scene):
    occ, per, start, goal = scene()
    n0 = occ.shape[0]
    f = F.solve_field(occ, per, [goal])
    path = descend(f, start)
    assert path.reached
    rows = path.nodes[:, 0]
    jumps = np.abs(np.diff(rows))
    assert np.any(jumps == n0 - 1), "the path must step across the seam n0-1 <-> 0"
    assert np.all((jumps == 1) | (jumps == 0) | (jumps == n0 - 1))
    # without the wrap the goal is unreachable
    g = F.solve_field(occ, (False,) + tuple(per[1:]), [goal])
    assert not descend(g, start).reached


def test_maze_721_log_harmonic_reaches_goal_where_paper_form_is_flat():
    occ, start, goal = mazes.maze((721, 721), pitch=4, seed=3)
    per = (False, False)
    dist = F.bfs_distance(occ, per, [goal])
    assert dist[start] > 10_000                       # a long winding route
    f = F.solve_field(occ, per, [goal], max_sweeps=40)
    path = descend(f, start)
    assert path.reached and path.steps >= dist[start]
    rng = np.random.default_rng(0)
    reach = np.argwhere(dist >= 0)
    for node in reach[rng.choice(len(reach), 200, replace=False)]:
        assert descend(f, node).reached
    # u at the start is far below what 1 - Phi can hold in float64, so the
    # paper's Phi form is exactly flat there at any number of sweeps
    assert f.log_u[start] < math.log(2.0 ** -53)
    paper = F.solve_field(occ, per, [goal], solver="gauss_seidel", max_sweeps=300)
    assert paper.potential()[start] == np.inf          # Phi == Phi0 exactly
    bad = descend(paper, start)
    assert not bad.reached and "flat" in bad.reason
    flat = (paper.log_u == -np.inf) & (dist >= 0)
    assert flat.mean() > 0.5


def test_solve_field_errors():
    occ = np.zeros((10, 12), dtype=bool)
    occ[3, 4] = True
    with pytest.raises(ValueError, match="solver.*'multigridx'"):
        F.solve_field(occ, (False, False), [(0, 0)], solver="multigridx")
    with pytest.raises(ValueError, match="goal_nodes.*obstacle"):
        F.solve_field(occ, (False, False), [(3, 4)])
    with pytest.raises(ValueError, match="periodic"):
        F.solve_field(occ, (False,), [(0, 0)])
    with pytest.raises(ValueError, match="goal_nodes"):
        F.solve_field(occ, (False, False), [(0, 0, 0)])
    with pytest.raises(ValueError, match="goal_nodes.*outside|goal_nodes.*out of"):
        F.solve_field(occ, (False, False), [(10, 0)])
    with pytest.raises(ValueError, match="occupied"):
        F.solve_field(np.zeros(5, dtype=bool), (False,), [(0,)])
    with pytest.raises(ValueError, match="occupied"):
        F.solve_field(occ.astype(int), (False, False), [(0, 0)])
    assert set(F.SOLVERS) >= {"gauss_seidel", "sor", "log_harmonic"}
    assert F.DEFAULT_SOLVER == "log_harmonic"


@pytest.mark.parametrize("solver", F.SOLVERS)
def test_every_solver_returns_consistent_field(solver):
    occ, per, start, goal = mazes.seam_scene_2d()
    f = F.solve_field(occ, per, [goal], solver=solver)
    assert f.solver.startswith(solver) and f.log_u.shape == occ.shape
    assert f.log_u[goal] == 0.0 and np.all(f.log_u[occ] == -np.inf)
    assert np.all(f.potential()[occ] == np.inf) and f.potential()[goal] == 0.0
    assert f.sweeps > 0 and f.seconds > 0 and f.converged
    with pytest.raises(dataclasses.FrozenInstanceError):
        f.sweeps = 3


def test_log_harmonic_converges_on_paper_2dof_scene():
    """The paper's 2-DOF C-space has pockets with u ~ 1e-17..1e-20 where
    over-relaxation alone keeps oscillating; the GS phase must converge them."""
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    sc = load_scenario(os.path.join(root, "config", "paper_2dof.yaml"))
    cs = build_cspace(sc.robot, sc.scene, sc.grid_with_cells(180))
    goal, start = cs.grid.node_of(sc.goal_rad), cs.grid.node_of(sc.start_rad)
    f = F.solve_field(cs.occupied, cs.grid.periodic, [goal], tol=1e-12, rel_tol=1e-8)
    assert f.solver == "log_harmonic" and f.converged
    _assert_no_local_max(f)
    assert descend(f, start).reached
    u, _, _ = F.sor_u(cs.occupied, cs.grid.periodic, [goal], tol=1e-14)
    big = u > 1e-8
    assert np.max(np.abs(f.log_u[big] - np.log(u[big]))) < 1e-5


@pytest.mark.parametrize("case", ["2d", "3d_odd_periodic", "3d_blocks"])
def test_multigrid_linear_solve_matches_sor(case):
    """The aggregation-multigrid CG solve gives the linear form's solution."""
    if case == "2d":
        occ, start, goal = mazes.blocks_2d(181)
        per = (False, False)
    elif case == "3d_odd_periodic":
        occ = np.zeros((35, 15, 13), dtype=bool)
        occ[10:20, 3:12, 2:11] = True
        per = (True, False, False)
        goal = (30, 7, 6)
    else:
        occ, per, start, goal = mazes.blocks_3d((36, 37, 37))
    ref, _, _ = F.sor_u(occ, per, [goal], tol=1e-14)
    u, its, res = F.multigrid_u(occ, per, [goal], tol=1e-13)
    assert res < 1e-13 and its < 100
    assert np.max(np.abs(u - ref)) < 1e-9
    assert u[goal] == 1.0 and np.all(u[occ] == 0.0)
    assert np.all(u[~_reachable_free(occ, per, goal)] == 0.0)
    u2, _, _ = F.multigrid_u(occ, per, [goal], tol=1e-13)
    assert np.array_equal(u, u2)


@pytest.mark.parametrize("dims", [2, 3])
def test_log_harmonic_phase1_multigrid_and_sor_agree(dims):
    """Both first phases lead to the same field, valid for descent everywhere."""
    if dims == 2:
        occ, start, goal = mazes.blocks_2d(181)
        per = (False, False)
    else:
        occ, per, start, goal = mazes.blocks_3d((36, 37, 37))
    a = F.solve_field(occ, per, [goal], phase1="multigrid", rel_tol=1e-8)
    b = F.solve_field(occ, per, [goal], phase1="sor", tol=1e-12, rel_tol=1e-8)
    for f in (a, b):
        assert f.solver == "log_harmonic" and f.converged
        _assert_no_local_max(f)
    r = a.reachable
    assert np.array_equal(r, b.reachable)
    assert np.max(np.abs(a.log_u[r] - b.log_u[r])) < 1e-4


def test_log_harmonic_rejects_unknown_phase1():
    occ, start, goal = mazes.blocks_2d(41)
    with pytest.raises(ValueError, match="phase1"):
        F.solve_field(occ, (False, False), [goal], phase1="jacobi")


def test_log_harmonic_multigrid_route_on_a_maze_gives_the_sor_route_field():
    """A maze's u falls to 1e-561, far below what the linear solve resolves: the
    multigrid route must still end in the converged, valid field (via the SOR route)."""
    occ, start, goal = mazes.maze((181, 181), pitch=4, seed=3)
    per = (False, False)
    a = F.solve_field(occ, per, [goal], phase1="multigrid")
    b = F.solve_field(occ, per, [goal], phase1="sor")
    assert a.solver == "log_harmonic" and a.converged
    _assert_no_local_max(a)
    r = b.reachable
    assert np.array_equal(a.reachable, r)
    assert a.log_u[r].min() < math.log(10.0) * -500           # the deep part: u ~ 1e-561
    assert np.max(np.abs(a.log_u[r] - b.log_u[r]) / np.maximum(1.0, np.abs(b.log_u[r]))) < 1e-3
    assert descend(a, start).reached
