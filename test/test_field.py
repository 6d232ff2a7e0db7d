"""
Tests of spacerobot_planner.field: the planner's harmonic field and the paper's solver.

The oracles (test/oracles.py) share no code with the solvers:
- ``connected``: the free nodes joined to the goal, over the test's own face-neighbour table
  (periodic axes wrap, bounded ones end in a wall, cut edges removed) by scipy's components;
- ``neighbour_max``: every node's largest face neighbour, brute force: a strictly higher one
  at every non-goal node is the condition under which steepest ascent reaches the goal;
- ``harmonic_log_u``: the converged harmonic field itself, a direct sparse solve of the
  Dirichlet problem set up from the grid alone; on a small grid it is checked in turn
  against the paper's Gauss–Seidel run to 1e-15.
"""
import math

import numpy as np
import pytest

import mazes
from oracles import connected, face_neighbours, harmonic_log_u, neighbour_max
from spacerobot_planner import field as F
from spacerobot_planner.cspace import build_cspace
from spacerobot_planner.descent import descend


def _goal_mask(shape, goals):
    mask = np.zeros(shape, bool)
    mask[tuple(np.asarray(goals).reshape(-1, len(shape)).T)] = True
    return mask


def _assert_valid_ascent(f, occ, per, goals, cut_edges=None):
    """
    Finite exactly on the goal-connected free nodes.

    Every such non-goal node has a strictly higher face neighbour (so steepest ascent from it
    reaches the goal); neighbours across a cut edge do not count.
    """
    conn = connected(occ, per, goals, cut_edges)
    assert np.array_equal(np.isfinite(f.log_u), conn)
    stuck = conn & ~_goal_mask(occ.shape, goals) & ~(neighbour_max(f.log_u, per, cut_edges) > f.log_u)
    assert not stuck.any(), f"{stuck.sum()} nodes without a strictly higher neighbour"


def _assert_matches_the_oracle(f, occ, per, goals, cut_edges=None):
    """Finite where the direct solve is, and |Δ log u| (≈ relative error of u) < 1e-4 at every node; returns it."""
    ref = harmonic_log_u(occ, per, goals, cut_edges)
    r = np.isfinite(ref)
    assert np.array_equal(np.isfinite(f.log_u), r)
    assert np.max(np.abs(f.log_u[r] - ref[r])) < 1e-4      # tiny values included
    return ref


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
    _assert_matches_the_oracle(F.solve_field(occ, per, goals), occ, per, goals)


def test_a_band_whose_window_would_hold_most_of_its_nodes_is_solved_whole():
    """
    A room behind a one-node corridor from the goal: band 1 keeps the corridor, band 2 is the room.

    The window of band 2 (32 steps from the corridor's mouth) holds three quarters of the room
    and its far side is not negligible: it is solved on the whole room at once (two bands; a
    window and then the wider one made three), and matches the direct solve.
    """
    occ = np.ones((40, 40), bool)
    occ[:14, 20] = False             # the corridor, one node wide
    occ[14:, :] = False              # the room
    goals = [(1, 20)]
    f = F.solve_field(occ, (False, False), goals)
    assert f.converged and f.stats["bands"] == 2
    _assert_matches_the_oracle(f, occ, (False, False), goals)
    _assert_valid_ascent(f, occ, (False, False), goals)


@pytest.mark.parametrize("scene", [mazes.seam_scene_2d(n0=181, n1=41), mazes.seam_scene_3d(n0=35, n1=23, n2=21)],
                         ids=["2d_181_periodic", "3d_35_periodic"])
def test_odd_periodic_counts_match_the_direct_solve(scene):
    """
    An odd number of nodes along the periodic axis: two nodes of one colour meet across the seam.

    The multigrid's levels (181, 91, 46, 23, ... and 35, 18, 9, ... nodes along that axis)
    are then partly not red-black: those levels are swept in order and restrict every
    residual.  The field must still be the direct solve's and ascend to the goal.
    """
    occ, per, start, goal = scene
    f = F.solve_field(occ, per, [goal])
    assert f.converged
    _assert_matches_the_oracle(f, occ, per, [goal])
    _assert_valid_ascent(f, occ, per, [goal])
    assert descend(f, start).reached


def test_oracle_agrees_with_the_papers_gauss_seidel_run_to_convergence():
    """The direct solve (oracle of the other tests) against the paper's iteration."""
    occ = np.zeros((30, 33), dtype=bool)
    occ[8:20, 10:14] = True
    per = (True, False)
    goals = [(25, 30)]
    gs = F.solve_field(occ, per, goals, solver="gauss_seidel", tol=1e-15, max_sweeps=500_000)
    ref = harmonic_log_u(occ, per, goals)
    big = np.exp(ref) > 1e-6
    assert gs.converged
    assert np.max(np.abs(np.exp(gs.log_u[big]) - np.exp(ref[big]))) < 1e-10


def test_the_papers_gauss_seidel_takes_cut_edges_as_walls_as_the_oracle_does():
    """
    A repair's cut edges in the paper's solver: a wall between the two nodes, as in the oracle's direct solve.

    A wall of cut edges across the grid but for one gap (the field must go round through it);
    before, a plan that repaired with the gauss_seidel solver ended in internal_error.
    """
    occ = np.zeros((30, 33), dtype=bool)
    occ[8:20, 10:14] = True
    per = (True, False)
    goals = [(25, 30)]
    cut = np.array([[np.ravel_multi_index((i, 20), occ.shape), np.ravel_multi_index((i, 21), occ.shape)]
                    for i in range(30) if i not in (3, 4)], np.int64)
    gs = F.solve_field(occ, per, goals, solver="gauss_seidel", tol=1e-15, max_sweeps=500_000, cut_edges=cut)
    ref = harmonic_log_u(occ, per, goals, cut_edges=cut)
    plain = harmonic_log_u(occ, per, goals)
    big = np.exp(ref) > 1e-6
    assert gs.converged
    assert np.max(np.abs(np.exp(gs.log_u[big]) - np.exp(ref[big]))) < 1e-10
    assert np.max(np.abs(np.exp(plain[big]) - np.exp(ref[big]))) > 1e-2      # the cut changes the field


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
        _assert_matches_the_oracle(f, occ, per, [goal])


def _edge(shape, a, b):
    return np.ravel_multi_index(a, shape), np.ravel_multi_index(b, shape)


def test_cut_edges_on_a_3d_periodic_grid_match_the_oracle():
    """
    The planner's repairs cut grid edges: the field is then the one of the grid without them.

    On the 3-D seam scene (axis 0 periodic, the only route crosses the seam): the seam cut
    but for a 4 × 4 window, the goal's edges along axes 0 and 1 cut, and one free node cut
    off all round.
    """
    occ, per, start, goal = mazes.seam_scene_3d()
    n0, n1, n2 = occ.shape
    cuts = [_edge(occ.shape, (n0 - 1, j, k), (0, j, k)) for j in range(n1) for k in range(n2)
            if not (14 <= j < 18 and 14 <= k < 18)]
    cuts += [_edge(occ.shape, goal, (goal[0] + 1, goal[1], goal[2])),
             _edge(occ.shape, goal, (goal[0], goal[1] - 1, goal[2]))]
    closed = (28, 15, 5)
    cuts += [_edge(occ.shape, closed, tuple(c + d * (a == b) for b, c in enumerate(closed)))
             for a in range(3) for d in (-1, 1)]
    f = F.solve_field(occ, per, [goal], cut_edges=np.array(cuts))
    assert f.converged and f.stats["bands"] >= 1
    ref = _assert_matches_the_oracle(f, occ, per, [goal], cuts)
    _assert_valid_ascent(f, occ, per, [goal], cuts)
    assert not occ[closed] and f.log_u[closed] == -np.inf
    # the cuts change the field: without them the closed node has a value, and u at the
    # start (behind the seam's window) is far higher
    whole = harmonic_log_u(occ, per, [goal])
    assert np.isfinite(whole[closed]) and whole[start] > ref[start] + 1.0
    assert np.isfinite(f.log_u[start])


def test_ascent_repair_on_a_3d_periodic_grid_matches_the_oracle():
    """
    Where u is 1 beside the goal, the repair makes ascent strict and changes u by ~1e-9 only.

    The goal nodes are the shell of a 5³ cube across the seam of the periodic axis: inside it
    the harmonic u is 1 exactly (the oracle's log u: 0, the goal's own value), so no node
    there has a strictly higher neighbour until the repair lowers them.
    """
    occ = np.zeros((12, 9, 9), bool)
    occ[5:8, 1:4, 5:8] = True
    per = (True, False, False)
    cube = [((i % 12), j, k) for i in range(-2, 3) for j in range(2, 7) for k in range(2, 7)]
    shell = [n for n in cube if max(abs((n[0] + 2) % 12 - 2), abs(n[1] - 4), abs(n[2] - 4)) == 2]
    inner = tuple(np.array([n for n in cube if n not in shell]).T)
    f = F.solve_field(occ, per, shell)
    assert f.converged and f.stats["repaired_nodes"] >= len(inner[0])      # every node inside
    ref = _assert_matches_the_oracle(f, occ, per, shell)
    assert np.max(np.abs(ref[inner])) < 1e-12
    assert np.all(f.log_u[inner] < 0.0) and np.all(f.log_u[inner] > -1e-7)
    _assert_valid_ascent(f, occ, per, shell)


def test_the_oracles_neighbour_table_is_the_grids():
    """The oracles' face neighbours on a 3 × 2 grid, written out: axis 0 wraps, axis 1 ends in walls, one edge cut."""
    #            node:  (0,0) (0,1) (1,0) (1,1) (2,0) (2,1)   flat 0..5
    want = np.array([[4, 5, 0, 1, 2, 3],                   # axis 0, -1: wraps from row 0 to row 2
                     [2, 3, 4, 5, 0, 1],                   # axis 0, +1: wraps from row 2 to row 0
                     [-1, 0, -1, 2, -1, 4],                # axis 1, -1: a wall beyond column 0
                     [1, -1, 3, -1, 5, -1]])               # axis 1, +1: a wall beyond column 1
    assert np.array_equal(face_neighbours((3, 2), (True, False)).reshape(4, 6), want)
    cut = want.copy()
    cut[0, 0] = cut[1, 4] = -1                             # the seam edge (0,0)-(2,0)
    assert np.array_equal(face_neighbours((3, 2), (True, False), [(0, 4)]).reshape(4, 6), cut)
    with pytest.raises(ValueError, match="no face neighbours"):
        face_neighbours((3, 2), (True, False), [(0, 3)])


def test_a_repaired_field_solved_from_the_field_before_the_cuts_matches_the_oracle():
    """
    A repair's re-solve from the field before its cuts meets the oracle of the cut grid.

    It starts from that field (``guess``), meets the oracle as a solve from nothing does, and
    needs fewer iterations.  The 3-D seam scene with the seam cut but for a 4 × 4 window (the start's whole route turns)
    and a few edges cut near the start (what a repair cuts); the oracle is the direct solve of
    the cut grid, which knows nothing of the guess.
    """
    occ, per, start, goal = mazes.seam_scene_3d()
    n0, n1, n2 = occ.shape
    before = F.solve_field(occ, per, [goal])
    for cuts in ([_edge(occ.shape, start, tuple(c + (a == 1) for a, c in enumerate(start))),
                  _edge(occ.shape, start, tuple(c + (a == 2) for a, c in enumerate(start)))],
                 [_edge(occ.shape, (n0 - 1, j, k), (0, j, k)) for j in range(n1) for k in range(n2)
                  if not (14 <= j < 18 and 14 <= k < 18)]):
        cold = F.solve_field(occ, per, [goal], cut_edges=np.array(cuts))
        warm = F.solve_field(occ, per, [goal], cut_edges=np.array(cuts), guess=before.log_u)
        assert warm.converged
        _assert_matches_the_oracle(warm, occ, per, [goal], cuts)
        _assert_valid_ascent(warm, occ, per, [goal], cuts)
        assert warm.sweeps < cold.sweeps, (warm.sweeps, cold.sweeps)
        again = F.solve_field(occ, per, [goal], cut_edges=np.array(cuts), guess=before.log_u)
        assert np.array_equal(warm.log_u, again.log_u), "the same problem and guess gave other bits"
    with pytest.raises(ValueError, match="guess.*shape"):
        F.solve_field(occ, per, [goal], guess=before.log_u[1:])
    with pytest.raises(ValueError, match="guess.*shape"):          # whatever the solver
        F.solve_field(occ, per, [goal], solver="gauss_seidel", guess=before.log_u[1:])
    nan = before.log_u.copy()
    nan[start] = np.nan
    with pytest.raises(ValueError, match="guess: 1 NaN"):
        F.solve_field(occ, per, [goal], guess=nan)


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


@pytest.mark.parametrize("solver", F.SOLVERS)
def test_every_solver_returns_a_consistent_field(solver):
    occ, per, start, goal = mazes.seam_scene_2d()
    f = F.solve_field(occ, per, [goal], solver=solver)
    assert f.solver == solver and f.log_u.shape == occ.shape
    assert f.log_u[goal] == 0.0 and np.all(f.log_u[occ] == -np.inf)
    assert np.all(f.potential()[occ] == np.inf) and f.potential()[goal] == 0.0
    assert f.sweeps > 0 and f.seconds > 0 and f.converged


@pytest.mark.parametrize("shape, periodic", [((7, 2, 5), (True, True, False)), ((2, 9), (True, False)),
                                             ((6, 5, 4, 3), (False, True, False, True)), ((11,), (True,))])
def test_the_node_graphs_neighbours_are_the_grids(shape, periodic):
    """
    The node graph's table against the oracle's face neighbours.

    Random obstacles, with and without cut edges (on two-node periodic axes too, where both
    directions reach the same node), every node with the oracle's neighbours where they are in
    the graph, and the graph's nodes exactly the goal-connected free ones.
    """
    from spacerobot_planner.field.graph import node_graph, validate_problem
    rng = np.random.default_rng(len(shape) * 31 + shape[0])
    occ = rng.random(shape) < 0.2
    goal = tuple(int(k) for k in np.argwhere(~occ)[0])
    full = face_neighbours(shape, periodic).reshape(2 * len(shape), -1)
    pick = rng.integers(0, occ.size, 12)
    cuts = np.array(sorted({tuple(sorted((int(p), int(full[d, p]))))
                            for p, d in zip(pick, rng.integers(0, full.shape[0], 12)) if full[d, p] >= 0}),
                    np.int64).reshape(-1, 2)
    for cut in (cuts, None):
        want = face_neighbours(shape, periodic, cut).reshape(2 * len(shape), -1)
        g = node_graph(*validate_problem(occ, periodic, [goal]), cut_edges=cut)
        conn = connected(occ, periodic, [goal], cut).ravel()
        assert np.array_equal(np.sort(g.order), np.flatnonzero(conn))
        assert g.order[0] == np.ravel_multi_index(goal, shape)
        pos = np.full(occ.size, g.size)
        pos[g.order] = np.arange(g.size)
        for k, f in enumerate(g.order):
            for d in range(2 * len(shape)):
                expect = g.size if want[d, f] < 0 or not conn[want[d, f]] else pos[want[d, f]]
                assert g.nbr[k, d] == expect
        assert np.array_equal(g.coords, np.array(np.unravel_index(g.order, shape)).T)


@pytest.mark.parametrize("seed", range(40))
def test_the_node_graph_holds_the_goal_connected_nodes_of_random_grids(seed):
    """
    The graph's nodes against the oracle's components on random grids: 1 to 4 axes, any of them periodic.

    The graph joins runs along the last axis, then the runs of neighbouring rows: grids of up to
    40 nodes a row, up to half of them obstacles, one to three goals, which come first; each grid
    with a fifth of the face edges cut (along the last axis too, and across its seam where it is
    periodic), and whole.
    """
    from spacerobot_planner.field.graph import node_graph, validate_problem
    rng = np.random.default_rng(1000 + seed)
    ndim = 1 + seed % 4
    shape = tuple(int(k) for k in rng.integers(2, (40, 14, 7, 5)[ndim - 1] + 1, ndim))
    periodic = tuple(bool(b) for b in rng.random(ndim) < 0.5)
    occ = rng.random(shape) < rng.uniform(0.0, 0.5)
    free = np.argwhere(~occ)
    if not len(free):
        occ.flat[0] = False
        free = np.argwhere(~occ)
    goals = free[rng.choice(len(free), size=min(len(free), int(rng.integers(1, 4))), replace=False)]
    full = face_neighbours(shape, periodic).reshape(2 * ndim, -1)
    edges = {tuple(sorted((p, int(full[d, p])))) for d in range(2 * ndim) for p in range(occ.size) if full[d, p] >= 0}
    edges = sorted(e for e in edges if e[0] != e[1])
    pick = rng.random(len(edges)) < 0.2
    for cuts in (np.array([e for e, cut in zip(edges, pick) if cut], np.int64).reshape(-1, 2), None):
        g = node_graph(*validate_problem(occ, periodic, [tuple(int(k) for k in q) for q in goals]), cut_edges=cuts)
        conn = connected(occ, periodic, goals, cuts).ravel()
        assert np.array_equal(np.sort(g.order), np.flatnonzero(conn))
        assert g.n_goal == len(goals)
        assert np.array_equal(np.sort(g.order[:g.n_goal]), np.sort(np.ravel_multi_index(tuple(goals.T), shape)))


def test_a_large_node_graphs_neighbours_are_the_grids():
    """
    The table of a graph large enough to be filled on all of numba's threads, against the oracle.

    ``graph.PARALLEL_MIN_NODES`` nodes and more (the table in chunks): every node's neighbours
    the oracle's positions in the graph, or none.
    """
    from spacerobot_planner.field.graph import PARALLEL_MIN_NODES, node_graph, validate_problem
    shape, periodic = (72, 48, 40), (True, False, False)
    occ = np.random.default_rng(4).random(shape) < 0.2
    goal = tuple(int(k) for k in np.argwhere(~occ)[0])
    g = node_graph(*validate_problem(occ, periodic, [goal]))
    assert g.size >= PARALLEL_MIN_NODES
    assert np.array_equal(np.sort(g.order), np.flatnonzero(connected(occ, periodic, [goal]).ravel()))
    pos = np.full(occ.size, g.size)
    pos[g.order] = np.arange(g.size)
    want = face_neighbours(shape, periodic).reshape(2 * len(shape), -1)[:, g.order]
    assert np.array_equal(g.nbr.T, np.where(want < 0, g.size, pos[np.maximum(want, 0)]))


@pytest.mark.parametrize("shape, periodic, in_order", [((31, 23), (True, False), True),
                                                       ((9, 8, 7), (True, False, True), False),
                                                       ((300,), (True,), True),
                                                       ((2, 40, 9), (True, True, False), False)])
def test_the_multigrid_levels_are_the_galerkin_products_of_index_blocks(shape, periodic, in_order):
    """
    The multigrid set-up against dense matrices built from the grid's definition.

    The fine operator (2n on the diagonal, -1 per face step to another unknown) from the
    oracle's face neighbours; every coarse level is Pᵀ A P of the one below (P: each row's
    aggregate), its aggregates are the 2×2… index blocks of the fine coordinates, its red
    rows (even coordinate sum of the block) come first, its rows to restrict are the red
    ones unless two black rows are neighbours, and the coarsest factor is that level's
    Cholesky factor.  Input given red rows first (the node graph's order) or shuffled.
    """
    from spacerobot_planner.field import multigrid
    rng = np.random.default_rng(sum(shape))
    occ = rng.random(shape) < (0.15 if len(shape) > 1 else 0.0)
    occ.flat[occ.size // 2] = True                              # (a ring becomes a line)
    goal = tuple(int(k) for k in np.argwhere(~occ)[0])
    conn = connected(occ, periodic, [goal]).ravel()
    conn[np.ravel_multi_index(goal, shape)] = False            # the unknowns: all but the goal
    flat = np.flatnonzero(conn)
    coords = np.array(np.unravel_index(flat, shape)).T
    red_first = np.argsort(coords.sum(axis=1) % 2, kind="stable")
    flat = flat[red_first] if in_order else flat[rng.permutation(flat.size)]
    coords = np.array(np.unravel_index(flat, shape)).T
    n, deg = flat.size, 2 * len(shape)
    row_of = np.full(occ.size, n)
    row_of[flat] = np.arange(n)
    nbr = row_of[face_neighbours(shape, periodic).reshape(deg, -1)[:, flat].T.clip(0)]
    nbr[face_neighbours(shape, periodic).reshape(deg, -1)[:, flat].T < 0] = n
    h = multigrid.Hierarchy(nbr, coords, shape)
    assert h.levels >= 2 and h.in_order == in_order
    fine = np.arange(n) if h.fine_of_input is None else np.argsort(h.fine_of_input)   # input node of each row
    a = np.zeros((n, n))                                        # the fine operator, in the hierarchy's rows
    for r, i in enumerate(fine):
        a[r, r] = deg
        for j in nbr[i]:
            if j < n:
                a[r, np.flatnonzero(fine == j)[0]] -= 1.0
    block = coords[fine]                                        # each row's index block, level by level
    for lv in range(h.levels):
        size, o = h.sizes[lv], h.off[lv]
        par = block.sum(axis=1) % 2
        assert h.red[lv] == np.sum(par == 0) and np.all(par[:h.red[lv]] == 0)
        black = np.arange(size) >= h.red[lv]
        between = a - np.diag(np.diag(a))
        assert h.rrows[lv] == (size if np.any(between[np.ix_(black, black)] != 0) else h.red[lv])
        if lv + 1 == h.levels:
            assert np.allclose(h.chol @ h.chol.T, a, rtol=0, atol=1e-12 * deg)
            break
        agg = h.agg[o:o + size].astype(np.int64)
        nc = h.sizes[lv + 1]
        p = np.zeros((size, nc))
        p[np.arange(size), agg] = 1.0
        # the aggregates are the index blocks of this level's coordinates, halved
        halved = block >> 1
        assert len({tuple(b) for b in halved}) == nc
        for c in range(nc):
            assert len({tuple(b) for b in halved[agg == c]}) == 1
        want = p.T @ a @ p
        co = h.off[lv + 1]
        got = np.diag(h.diag[co:co + nc]).astype(float)
        for r in range(nc):
            for d in range(deg):
                j = h.nbr[co + r, d]
                if j < nc:
                    got[r, j] -= h.wt[co + r, d]
        assert np.array_equal(got, want)
        new_block = np.empty((nc, len(shape)), np.int64)
        new_block[agg] = halved
        a, block = want, new_block


_KEPT_HEAP_CHILD = """
import json, resource, sys
import numpy as np
from spacerobot_planner import field as F
if sys.argv[1] == "block":               # a block far above glibc's 32 MiB, freed and made again
    F.keep_heap()
    def step():
        a = np.ones(200 << 20, np.uint8)
        del a
    bound = 100                          # the old setting: 612 faults each time (huge pages), or 51 200
else:
    if sys.argv[1] == "2d":
        occ = np.zeros((180, 181), dtype=bool)
        occ[40:140, 60:70] = True
        per, goal = (False, False), (170, 170)
    else:                                # 729 000 nodes, six bands: blocks above 32 MiB
        occ = np.zeros((90, 90, 90), dtype=bool)
        per, goal = (False, False, False), (89, 89, 89)
    def step():
        F.solve_field(occ, per, [goal])
    bound = 8 * int((~occ).sum()) * 8 // 4096 // 4
for _ in range(2):                       # the heap grows to the peak
    step()
kept = F.keep_heap()
faults = []
for _ in range(int(sys.argv[2])):
    before = resource.getrusage(resource.RUSAGE_THREAD).ru_minflt
    step()
    faults.append(resource.getrusage(resource.RUSAGE_THREAD).ru_minflt - before)
print(json.dumps({"kept": kept, "again": F.keep_heap(), "faults": faults, "bound": bound}))
"""


@pytest.mark.parametrize("problem, solves", [("2d", 5), ("3d", 3), ("block", 3)])
def test_the_field_keeps_freed_memory_for_the_next_solve(problem, solves):
    """
    Once the heap has grown to a solve's peak (glibc only), the next solve of the same problem reuses it.

    In a fresh process (no earlier solve, no C-library setting left by another test or by a Dask
    cluster), on the solving thread alone: its page faults are counted by the kernel
    (``ru_minflt`` of ``RUSAGE_THREAD``), the oracle, and are far fewer than the pages of the
    float64 vectors over the graph that a solve allocates (the field, CG's four, the V-cycle's
    three: 8; a quarter of them is the bound: about 500 pages at 181², 11 000 on the 90³ grid).
    Without the kept heap every solve faults ~900 at 181².  The 90³ grid's solve has blocks
    above the 32 MiB that glibc's automatic mmap threshold stops at: while only that threshold
    was raised, it faulted ~61 000 pages a solve in half of ten runs (where the heap's layout
    let glibc map those blocks afresh).  ``block``: a 200 MiB block made and freed again, which
    the old setting mapped afresh every time (612 faults with huge pages, 51 200 without),
    whatever the layout; the bound is 100.  The fewest faults of the rounds: on a loaded machine
    the kernel may take back a kept page now and then (CI once counted 198 in one solve, where a
    quiet machine counts 0 or 1), which is not the heap's doing.
    """
    import json
    import os
    import subprocess
    import sys

    resource = pytest.importorskip("resource")
    if not hasattr(resource, "RUSAGE_THREAD"):
        pytest.skip("no per-thread resource usage on this system")
    env = {k: v for k, v in os.environ.items() if k not in F._GLIBC_HEAP_VARIABLES + ("GLIBC_TUNABLES",)}
    done = subprocess.run([sys.executable, "-c", _KEPT_HEAP_CHILD, problem, str(solves)], env=env,
                          capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-2000:]
    got = json.loads(done.stdout.strip().splitlines()[-1])
    if not got["kept"]:
        pytest.skip("not glibc")
    assert got["again"]                  # once per process, the same answer
    assert min(got["faults"]) < got["bound"], got


@pytest.mark.parametrize("shape, periodic, max_steps", [
    ((30, 26), (True, False), 5),
    ((12, 11, 10), (True, False, False), 4),
    ((12, 11, 10), (True, False, False), 0),        # no limit
])
def test_a_later_bands_window_counts_steps_as_a_breadth_first_search(shape, periodic, max_steps):
    """``harmonic._steps_from_known`` against a breadth-first search over the grid's face neighbours written here."""
    from spacerobot_planner.field import harmonic
    from spacerobot_planner.field.graph import node_graph, validate_problem
    rng = np.random.default_rng(len(shape) * 10 + max_steps)
    occ = rng.random(shape) < 0.2
    goal = np.unravel_index(np.flatnonzero(~occ.ravel())[0], shape)
    g = node_graph(*validate_problem(occ, periodic, [goal]))
    known = rng.random(g.size) < 0.05
    known[:g.n_goal] = True
    active = np.flatnonzero(~known).astype(np.int64)
    mark = np.full(g.size + 1, -1, np.int32)
    got = harmonic._steps_from_known(g.nbr, active, known, mark, max_steps)
    assert np.all(mark == -1), "the scratch is not left as it came"
    # the oracle: breadth-first from the known nodes, through the active ones, on the flat grid
    flat_nbr = face_neighbours(shape, periodic).reshape(2 * len(shape), -1)
    state = np.full(occ.size, -2)                   # -2: neither active nor known
    state[g.order[active]] = -1                     # -1: active, not reached
    known_flat = set(g.order[known].tolist())
    frontier = [f for f in g.order[active] if any(j >= 0 and j in known_flat for j in flat_nbr[:, f])]
    for f in frontier:
        state[f] = 1
    steps = 1
    while frontier:
        nxt = []
        for f in frontier:
            for j in flat_nbr[:, f]:
                if j >= 0 and state[j] == -1:
                    state[j] = steps + 1
                    nxt.append(j)
        frontier, steps = nxt, steps + 1
    far = (1 << 40) if max_steps == 0 else max_steps + 1
    want = state[g.order[active]]
    want = np.where((want < 0) | (want > far), far, want)
    assert np.array_equal(got, want)
