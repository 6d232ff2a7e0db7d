"""
The plan's termination token, polled inside the kernels (issue 17).

Each kernel is shown to poll by giving it a token that is already set and seeing it stop
itself: the result it returns is partial (a kernel that did not poll would finish, and
only a check after it would notice).  The planner-level tests put the cancel inside a
stage deterministically: the stage's test stall (``Planner.test_stall``) waits on a token
whose ``wait`` is where the cancel arrives.
"""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest

from spacerobot_planner import field as F
from spacerobot_planner.config import load_scenario
from spacerobot_planner.cspace import build_cspace
from spacerobot_planner.field import geometric, harmonic, multigrid, paper
from spacerobot_planner.field.graph import node_graph, validate_problem
from spacerobot_planner.planner import Planner, PlannerSettings
from spacerobot_planner.termination import Cancelled, Termination

import mazes
from conftest import CONFIG_DIR


class _Peek(Termination):
    """A set token whose ``check`` does not raise: the caller returns what the kernel left."""

    def __init__(self):
        super().__init__()
        self.set()

    def check(self):
        pass


class _CancelInStall(Termination):
    """A token cancelled while a test stall waits on it: the cancel arrives inside that stage."""

    def __init__(self):
        super().__init__()
        self.waited = 0

    def wait(self, timeout=None):
        self.waited += 1
        self.set()
        return True


@pytest.fixture(scope="module")
def sc3():
    import os
    return load_scenario(os.path.join(CONFIG_DIR, "paper_3dof.yaml"))


@pytest.fixture(scope="module")
def sc_elbow_locked():
    """Return the 3-link arm planning attitude and shoulder only (the node-by-node C-space kernel)."""
    import os
    from spacerobot_planner.config import load_params_file, scenario_from_params
    p = load_params_file(os.path.join(CONFIG_DIR, "paper_3dof.yaml"))
    p["robot.planned_joints"] = ["attitude", "shoulder"]
    p["grid.cells"] = [60, 60]
    for k in [k for k in p if k.startswith("scenario.")]:
        del p[k]                                  # 3-joint start and goal
    return scenario_from_params(p)


def test_token_is_an_event_whose_flag_the_kernels_read():
    t = Termination()
    assert not t.is_set() and t.flag[0] == 0 and not t.wait(0.0)
    t.set()
    assert t.is_set() and t.flag[0] == 1 and t.wait(0.0)
    with pytest.raises(Cancelled):
        t.check()
    t.clear()
    assert not t.is_set() and t.flag[0] == 0
    ev = threading.Event()
    linked = Termination.of(ev)
    assert not linked.is_set()
    ev.set()
    assert linked.is_set() and linked.flag[0] == 1      # raised for the kernels once seen


# ------------------------------------------------------------------ C-space
@pytest.mark.parametrize("cells", [20, 70])          # one thread; rows over threads (≥ 300k nodes)
def test_cspace_row_kernel_stops_itself_on_a_set_token(sc3, cells):
    grid = sc3.grid.with_cells(cells)
    full = build_cspace(sc3.robot, sc3.scene, grid)
    assert full.occupied.any()
    part = build_cspace(sc3.robot, sc3.scene, grid, token=_Peek())
    assert not part.occupied.any(), "the row kernel ran although its token was set"
    with pytest.raises(Cancelled):
        build_cspace(sc3.robot, sc3.scene, grid, token=_set())


def test_cspace_node_kernel_stops_itself_on_a_set_token(sc_elbow_locked):
    sc = sc_elbow_locked
    assert sc.robot.planned_joints[-1] != len(sc.robot.link_lengths_m) - 1    # not the row kernel
    full = build_cspace(sc.robot, sc.scene, sc.grid)
    assert full.occupied.any()
    part = build_cspace(sc.robot, sc.scene, sc.grid, token=_Peek())
    assert not part.occupied.any(), "the node kernel ran although its token was set"
    with pytest.raises(Cancelled):
        build_cspace(sc.robot, sc.scene, sc.grid, token=_set())


def _set():
    t = Termination()
    t.set()
    return t


# ------------------------------------------------------------------ field
def _maze_problem(shape=(181, 181)):
    occ, start, goal = mazes.maze(shape, pitch=4, seed=3)
    return occ, (False, False), np.array([goal])


def _first_band(problem):
    """Return the first band's linear problem (every node but the goal's), as ``harmonic.solve`` poses it."""
    occ, per, goals = validate_problem(*problem)
    g = node_graph(occ, per, goals)
    log_u = np.full(g.size + 1, -np.inf)
    log_u[:g.n_goal] = 0.0
    known = np.zeros(g.size, bool)
    known[:g.n_goal] = True
    active = np.arange(g.n_goal, g.size)
    sub, rhs, _ = harmonic._band_problem(g.nbr, active, known, log_u)
    return sub, g.coords[active], g.shape, rhs


def test_multigrid_cg_stops_itself_on_a_set_flag():
    args = _first_band(_maze_problem())
    _, its, _ = multigrid.solve(*args, tol=1e-10)
    assert its > 0
    for beside in (False, True):        # the coarse levels in this thread, or on a second one
        x, its, res = multigrid.solve(*args, tol=1e-10, stop=_set().flag, beside=beside)
        assert its == 0 and res == np.inf and not np.any(x), f"CG iterated although its flag was set ({beside})"


def test_a_flag_set_while_the_coarse_levels_are_built_beside_stops_the_solve(monkeypatch):
    """
    The split set-up (coarse levels on a second thread, the fine cells laid out meanwhile) stops too.

    The flag is set by the second thread as its coarse levels begin (``_levels`` polls it between
    levels): the solve returns nothing, as a stop at the first level does.  A layout that raises
    is raised in the solve's thread, and the second thread has ended by then either way.
    """
    args = _first_band(_maze_problem())
    flag = np.zeros(1, np.int64)
    real = multigrid.Hierarchy.coarsen

    def coarsen_stopped(self, stop=None):
        flag[0] = 1                       # the plan cancelled just as the coarse levels begin
        return real(self, stop)
    monkeypatch.setattr(multigrid.Hierarchy, "coarsen", coarsen_stopped)
    # the aggregation levels' route (a 2-D band's "auto" takes the geometric levels, built in the solve's thread)
    x, its, res = multigrid.solve(*args, tol=1e-10, stop=flag, beside=True, route="structured")
    assert its == 0 and res == np.inf and not np.any(x)
    assert not any(t.name == "field-beside" for t in threading.enumerate())
    monkeypatch.setattr(multigrid.Hierarchy, "coarsen", real)

    def broken_layout(*a):
        raise RuntimeError("layout failed")
    monkeypatch.setattr(multigrid, "_fine_layout_alone", broken_layout)
    with pytest.raises(RuntimeError, match="layout failed"):
        multigrid.solve(*args, tol=1e-10, beside=True, route="structured")
    assert not any(t.name == "field-beside" for t in threading.enumerate())


def test_a_flag_set_while_the_geometric_levels_are_built_stops_the_solve(monkeypatch):
    """A 2-D band's geometric levels: a flag set during their set-up stops the solve before CG (nothing returned)."""
    args = _first_band(_maze_problem())
    flag = np.zeros(1, np.int64)
    real = geometric.levels

    def levels_stopped(*a):
        flag[0] = 1                       # the plan cancelled while the levels are built
        return real(*a)
    monkeypatch.setattr(geometric, "levels", levels_stopped)
    x, its, res = multigrid.solve(*args, tol=1e-10, stop=flag)
    assert flag[0] == 1, "the band did not take the geometric levels"
    assert its == 0 and res == np.inf and not np.any(x)


def test_a_set_flag_stops_the_multigrid_set_up_before_it_builds_its_levels():
    """A set-up stopped before its first level builds nothing: no packed levels, no dense matrix of the fine level."""
    sub, coords, shape, _ = _first_band(_maze_problem())
    flag = _set().flag
    out = multigrid._levels(sub.astype(np.uint32), 0, coords.astype(np.int64), np.array(shape, np.int64), flag)
    packed, dense, stopped = out[2], out[-2], out[-1]
    assert stopped and packed.size == 0 and dense.size == 0
    with pytest.raises(multigrid.Stopped):
        multigrid.Hierarchy(sub, coords, shape, flag)


def test_gauss_seidel_sweeps_stop_themselves_on_a_set_flag():
    occ, per, goals = validate_problem(*_maze_problem((41, 41)))
    _, sweeps, _ = paper.gauss_seidel_phi(occ, per, goals, 1.0, 1e-12, 50, stop=_set().flag)
    assert sweeps == 0
    with pytest.raises(Cancelled):
        F.solve_field(occ, per, goals, solver="gauss_seidel", token=_set())


@pytest.mark.parametrize("solver", ["log_harmonic", "gauss_seidel", "oracle"])
def test_solve_field_raises_on_a_set_token_and_returns_no_field(solver):
    occ, per, goals = _maze_problem((41, 41))
    with pytest.raises(Cancelled):
        F.solve_field(occ, per, goals, solver=solver, token=_set())


def test_the_soft_cancel_callable_still_completes_the_field():
    """``cancel=`` (a callable) keeps its meaning: stop the bands, return a valid field."""
    occ, per, goals = _maze_problem()
    f = F.solve_field(occ, per, goals, cancel=lambda: True, token=Termination())
    assert not f.converged and f.stats["bands"] == 0 and np.isfinite(f.log_u[tuple(goals[0])])


# ------------------------------------------------------------------ planner caches
def _independent_cspace(sc, grid):
    return build_cspace(sc.robot, sc.scene, grid, extra_margin_m=PlannerSettings().grid_extra_margin_m)


def test_cancel_mid_cspace_stores_no_cspace_and_the_next_plan_builds_it_whole(sc3):
    grid = sc3.grid.with_cells(30)
    p = Planner(sc3.with_grid(grid), trajectory=False)
    tok = _CancelInStall()
    p.test_stall = ("cspace", 60.0, True, None)
    t0 = time.monotonic()
    res = p.plan(sc3.start_rad, sc3.goal_rad, cancel=tok)
    dt = time.monotonic() - t0
    p.test_stall = None
    assert tok.waited == 1, "the plan did not reach the C-space stage"
    assert res.code == "cancelled" and not res.ok, res.reason
    assert dt < 30.0                                  # not the 60 s stall
    assert p.cache_sizes()["cspaces"] == 0 and p.cache_sizes()["fields"] == 0
    res = p.plan(sc3.start_rad, sc3.goal_rad)
    assert res.ok and "cspace" not in res.cached
    np.testing.assert_array_equal(res.cspace.occupied, _independent_cspace(sc3, grid).occupied)


def test_cancel_mid_field_keeps_the_cspace_and_stores_no_field(sc3):
    grid = sc3.grid.with_cells(30)
    p = Planner(sc3.with_grid(grid), trajectory=False)
    tok = _CancelInStall()
    p.test_stall = ("field", 60.0, True, None)
    res = p.plan(sc3.start_rad, sc3.goal_rad, cancel=tok)
    p.test_stall = None
    assert tok.waited == 1 and res.code == "cancelled", res.reason
    assert res.field is None
    assert p.cache_sizes()["cspaces"] == 1 and p.cache_sizes()["fields"] == 0
    again = p.plan(sc3.start_rad, sc3.goal_rad)
    assert again.ok and "cspace" in again.cached and "field" not in again.cached
    assert again.cspace is res.cspace                 # the very C-space built before the cancel
    fresh = Planner(sc3.with_grid(grid), trajectory=False).plan(sc3.start_rad, sc3.goal_rad)
    np.testing.assert_array_equal(again.field.log_u, fresh.field.log_u)
    np.testing.assert_array_equal(again.path_rad, fresh.path_rad)


def test_cancel_mid_smoothing_keeps_the_cspace_and_the_field(sc3):
    grid = sc3.grid.with_cells(30)
    p = Planner(sc3.with_grid(grid), trajectory=False)
    tok = _CancelInStall()
    p.test_stall = ("smoothing", 60.0, True, None)
    res = p.plan(sc3.start_rad, sc3.goal_rad, cancel=tok)
    p.test_stall = None
    assert tok.waited == 1 and res.code == "cancelled", res.reason
    again = p.plan(sc3.start_rad, sc3.goal_rad)
    assert again.ok and {"cspace", "field"} <= set(again.cached)
