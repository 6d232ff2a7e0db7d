"""
Tests of spacerobot_planner.field: the planner's harmonic field and the paper's solver.

The oracles are written here, sharing no code with the solvers:
- ``_goal_connected`` a breadth-first flood fill in plain Python (periodic wrap included);
- ``_no_local_maximum`` a brute-force comparison of every node with its 2n face neighbours
  (numpy shifts), the condition under which steepest descent reaches the goal;
- the converged harmonic field itself by ``field.oracle`` (a sparse direct solve) and, on
  a small grid, by the paper's Gauss–Seidel run to 1e-13.
"""
import dataclasses
import math
import os
import sys
from collections import deque

import numpy as np
import pytest

sys.path.insert(0, os.path.dirname(__file__))
import mazes  # noqa: E402

from spacerobot_planner import field as F  # noqa: E402
from spacerobot_planner.cspace import build_cspace  # noqa: E402
from spacerobot_planner.descent import descend  # noqa: E402


def _goal_connected(occ, per, goals):
    """Free nodes joined to a goal node by face steps (a plain BFS)."""
    seen = np.zeros(occ.shape, dtype=bool)
    queue = deque()
    for g in goals:
        seen[tuple(g)] = True
        queue.append(tuple(g))
    while queue:
        node = queue.popleft()
        for a in range(occ.ndim):
            for d in (-1, 1):
                nb = list(node)
                nb[a] += d
                if per[a]:
                    nb[a] %= occ.shape[a]
                elif not 0 <= nb[a] < occ.shape[a]:
                    continue
                nb = tuple(nb)
                if not occ[nb] and not seen[nb]:
                    seen[nb] = True
                    queue.append(nb)
    return seen


def _neighbour_max(log_u, per):
    """Largest face-neighbour value of every node (walls beyond bounded axes: -inf)."""
    best = np.full(log_u.shape, -np.inf)
    for a in range(log_u.ndim):
        for d in (-1, 1):
            if per[a]:
                shifted = np.roll(log_u, -d, axis=a)
            else:
                pad = [(0, 0)] * log_u.ndim
                pad[a] = (0, 1) if d == 1 else (1, 0)
                padded = np.pad(log_u, pad, constant_values=-np.inf)
                sl = [slice(None)] * log_u.ndim
                sl[a] = slice(1, None) if d == 1 else slice(0, -1)
                shifted = padded[tuple(sl)]
            best = np.maximum(best, shifted)
    return best


def _assert_valid_ascent(f, occ, per, goals):
    """
    Finite exactly on the goal-connected free nodes.

    Every such non-goal node has a strictly higher face neighbour (so steepest ascent from it
    reaches the goal).
    """
    conn = _goal_connected(occ, per, goals)
    assert np.array_equal(np.isfinite(f.log_u), conn)
    goal_mask = np.zeros(occ.shape, bool)
    goal_mask[tuple(np.asarray(goals).T)] = True
    stuck = conn & ~goal_mask & ~(_neighbour_max(f.log_u, per) > f.log_u)
    assert not stuck.any(), f"{stuck.sum()} nodes without a strictly higher neighbour"


def _blocks_4d(n=24):
    occ = np.zeros((n, n, n, n), dtype=bool)
    occ[4:14, 6:18, 2:20, 3:12] = True
    occ[:, 19:21, :15, :] = True
    return occ, (True, False, False, False), (n - 2, 2, 22, 20)


def _problems():
    occ2, _, g2 = mazes.blocks_2d(181)
    occ3, per3, _, g3 = mazes.blocks_3d((36, 37, 37))
    occ4, per4, g4 = _blocks_4d()
    occm, _, gm = mazes.maze((181, 181), pitch=4, seed=3)
    return {"2d": (occ2, (False, False), [g2]), "3d_periodic": (occ3, per3, [g3]),
            "4d_periodic": (occ4, per4, [g4]), "maze_2d": (occm, (False, False), [gm])}


PROBLEMS = _problems()


@pytest.mark.parametrize("name", list(PROBLEMS))
def test_descent_reaches_the_goal_from_every_goal_connected_node(name):
    occ, per, goals = PROBLEMS[name]
    f = F.solve_field(occ, per, goals)
    assert f.solver == "log_harmonic" and f.converged and f.left == ""
    assert f.log_u[tuple(goals[0])] == 0.0 and np.all(f.log_u[occ] == -np.inf)
    _assert_valid_ascent(f, occ, per, goals)
    if name == "maze_2d":       # u falls far below a double's range: log u keeps it
        assert np.nanmin(np.where(np.isfinite(f.log_u), f.log_u, np.nan)) < math.log(10.0) * -500
        assert f.stats["bands"] > 10


@pytest.mark.parametrize("name", ["2d", "3d_periodic", "maze_2d"])
def test_field_matches_the_direct_solve_to_relative_precision(name):
    occ, per, goals = PROBLEMS[name]
    f = F.solve_field(occ, per, goals)
    ref = F.solve_field(occ, per, goals, solver="oracle")
    r = np.isfinite(ref.log_u)
    assert np.array_equal(np.isfinite(f.log_u), r)
    # |Δ log u| ≈ relative error of u, at every node, tiny values included
    assert np.max(np.abs(f.log_u[r] - ref.log_u[r])) < 1e-4


def test_oracle_agrees_with_the_papers_gauss_seidel_run_to_convergence():
    """The direct solve (oracle of the other tests) against the paper's iteration."""
    occ = np.zeros((30, 33), dtype=bool)
    occ[8:20, 10:14] = True
    per = (True, False)
    goals = [(25, 30)]
    gs = F.solve_field(occ, per, goals, solver="gauss_seidel", tol=1e-15, max_sweeps=500_000)
    ref = F.solve_field(occ, per, goals, solver="oracle")
    big = np.exp(ref.log_u) > 1e-6
    assert gs.converged
    assert np.max(np.abs(np.exp(gs.log_u[big]) - np.exp(ref.log_u[big]))) < 1e-10


def test_same_input_same_field_bit_for_bit():
    for occ, per, goals in PROBLEMS.values():
        a = F.solve_field(occ, per, goals)
        b = F.solve_field(occ.copy(), per, [tuple(g) for g in goals])
        assert np.array_equal(a.log_u, b.log_u)


@pytest.mark.parametrize("name", ["2d", "3d_periodic", "maze_2d"])
def test_a_tiny_budget_still_gives_a_valid_field_and_says_it_did_not_converge(name):
    occ, per, goals = PROBLEMS[name]
    f = F.solve_field(occ, per, goals, budget_s=1e-4)
    assert not f.converged and "budget" in f.left
    _assert_valid_ascent(f, occ, per, goals)


def test_cancel_stops_between_bands_with_a_valid_field():
    occ, per, goals = PROBLEMS["maze_2d"]
    calls = []

    def cancel():
        calls.append(1)
        return len(calls) > 3
    f = F.solve_field(occ, per, goals, cancel=cancel)
    assert not f.converged and f.stats["bands"] == 3
    _assert_valid_ascent(f, occ, per, goals)


def test_descent_crosses_the_periodic_seam():
    for occ, per, start, goal in (mazes.seam_scene_2d(), mazes.seam_scene_3d()):
        f = F.solve_field(occ, per, [goal])
        path = descend(f, start)
        assert path.reached
        jumps = np.abs(np.diff(path.nodes[:, 0]))
        assert np.any(jumps == occ.shape[0] - 1), "the path must step across the seam"
        g = F.solve_field(occ, (False,) + tuple(per[1:]), [goal])
        assert not descend(g, start).reached      # without the wrap: no route


def test_papers_form_is_flat_on_a_maze_where_log_harmonic_is_not():
    occ, start, goal = mazes.maze((181, 181), pitch=4, seed=3)
    per = (False, False)
    paper = F.solve_field(occ, per, [goal], solver="gauss_seidel", max_sweeps=300)
    assert paper.potential()[start] == np.inf          # Φ == Φ0 exactly at the start
    bad = descend(paper, start)
    assert not bad.reached and "flat" in bad.reason
    # ... although by the paper's own stop (change < 1e-6 per sweep) it has converged
    assert paper.converged
    assert descend(F.solve_field(occ, per, [goal]), start).reached


def test_paper_scene_field_is_valid_and_matches_the_oracle(paper_scenario):
    for dof, cells in ((2, 180), (3, 36)):
        sc = paper_scenario(dof)
        cs = build_cspace(sc.robot, sc.scene, sc.grid_with_cells(cells), extra_margin_m=0.02)
        goal = cs.grid.node_of(sc.goal_rad)
        occ = cs.occupied.copy()
        occ[goal] = False
        per = cs.grid.periodic
        f = F.solve_field(occ, per, [goal])
        assert f.converged
        _assert_valid_ascent(f, occ, per, [goal])
        ref = F.solve_field(occ, per, [goal], solver="oracle")
        r = np.isfinite(ref.log_u)
        assert np.max(np.abs(f.log_u[r] - ref.log_u[r])) < 1e-4


def test_solve_field_errors():
    occ = np.zeros((10, 12), dtype=bool)
    occ[3, 4] = True
    with pytest.raises(ValueError, match="solver.*'sor'"):
        F.solve_field(occ, (False, False), [(0, 0)], solver="sor")
    with pytest.raises(ValueError, match="goal_nodes.*obstacle"):
        F.solve_field(occ, (False, False), [(3, 4)])
    with pytest.raises(ValueError, match="periodic"):
        F.solve_field(occ, (False,), [(0, 0)])
    with pytest.raises(ValueError, match="goal_nodes"):
        F.solve_field(occ, (False, False), [(0, 0, 0)])
    with pytest.raises(ValueError, match="goal_nodes.*out of"):
        F.solve_field(occ, (False, False), [(10, 0)])
    with pytest.raises(ValueError, match="occupied"):
        F.solve_field(np.zeros((1, 5), dtype=bool), (False, False), [(0, 0)])
    with pytest.raises(ValueError, match="occupied"):
        F.solve_field(occ.astype(int), (False, False), [(0, 0)])
    with pytest.raises(ValueError, match="budget_s"):
        F.solve_field(occ, (False, False), [(0, 0)], budget_s=0.0)
    assert F.SOLVERS == ("log_harmonic", "gauss_seidel") and F.DEFAULT_SOLVER == "log_harmonic"


@pytest.mark.parametrize("solver", F.SOLVERS)
def test_every_solver_returns_a_consistent_field(solver):
    occ, per, start, goal = mazes.seam_scene_2d()
    f = F.solve_field(occ, per, [goal], solver=solver)
    assert f.solver == solver and f.log_u.shape == occ.shape
    assert f.log_u[goal] == 0.0 and np.all(f.log_u[occ] == -np.inf)
    assert np.all(f.potential()[occ] == np.inf) and f.potential()[goal] == 0.0
    assert f.sweeps > 0 and f.seconds > 0 and f.converged
    with pytest.raises(dataclasses.FrozenInstanceError):
        f.sweeps = 3
