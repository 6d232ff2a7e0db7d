"""The offline planner: scene → C-space → field → descent → verified smooth path.

``Planner.plan`` chains the stages, each a pure function of its own module, and
caches what does not depend on the start:

- the C-space on (robot, scene geometry + margin, grid, extra grid margin);
- the field on (C-space, goal nodes, solver, tolerance) together with the grid
  nodes blocked by path repair (below).

So a second plan with only a new start reuses both and costs milliseconds.

Exact ends: the start and the goal are joined to nearby free grid nodes by
straight segments verified on the exact geometry.  Grid paths: the grid is built
with a small extra margin (``grid_extra_margin_m``) so grid paths keep away from
obstacles; the verification uses the scene's true margin.  When the straight
segment between two adjacent nodes of the descent still collides (possible at
coarse steps: 10° at 36³), the node nearer the obstacle is blocked and the field
re-solved ("repair"); the blocked nodes stay with the cached field.

The core never imports rclpy.
"""

from __future__ import annotations

import math
import threading
import time
import traceback as _traceback
from dataclasses import dataclass, field as dc_field
from typing import Callable

import numpy as np

from .collision import CollisionChecker
from .config import Scenario
from .cspace import CSpace, GridSpec, body_occupancy, build_cspace
from .descent import colliding_edges, descend
from .field import DEFAULT_BUDGET_S, DEFAULT_SOLVER, INTERNAL_SOLVERS, SOLVERS, Field, bfs_distance, solve_field
from .field import warm_up as field_warm_up
from .ik import grasp_ik
from .scene import Scene
from .motion import DEFAULT_VERIFY_STEP_RAD, SegmentTest, check_path, first_bad_segment
from .smoothing import DEFAULT_MAX_STEP_RAD, smooth_path, unwrap_path

__all__ = ["PlanResult", "Planner", "STAGES", "CODES", "warm_up"]

#: A repair cuts the colliding grid edges within this many index steps of the blocked node
#: (one more with each repair of the same plan, up to three more).
REPAIR_RADIUS = 2
STAGES = ("cspace", "field", "descent", "repair", "smoothing", "verify", "total")
CODES = ("ok", "invalid_input", "start_in_collision", "goal_in_collision", "goal_unreachable",
         "disconnected", "path_invalid", "cancelled", "internal_error")


@dataclass(frozen=True, eq=False)
class PlanResult:
    """What a plan produced (or why not).

    Attributes:
        ok: a verified path was found.
        reason: a sentence for people; None when ok.
        code: one of ``CODES``.
        joint_names: the planned joints.
        start_rad: (dof,) the start as given (periodic joints wrapped).
        goal_rad: (dof,) the goal (periodic joints wrapped), None if none was found.
        path_rad: (M, dof) smoothed path, samples ≤ 0.5° apart, exact start first and
            exact goal last; periodic joints unwrapped, so on those the last row
            equals the goal up to a multiple of 2π.  (0, dof) when no path.
        grid_path_rad: (m, dof) the descent's grid nodes (wrapped grid values).
        timings_s: seconds per stage (``STAGES``); a cached stage reports 0.0.
        cached: the stages served from cache.
        solver: field solver name.
        solver_stats: sweeps, residual, converged, left, bands, repairs (re-solves after cutting
            grid edges or blocking nodes whose motions collide), cut_edges, blocked_nodes.
        min_clearance_m: minimum clearance over the dense check (nan without path).
        cspace, field: the grid and the field used (None if not reached).
        smoothing: "shortcut_spline", "spline", "polyline" or "" without a path.
        path_length_rad: joint-space length of path_rad (nan without path).
        traceback: the formatted traceback when ``code == "internal_error"`` (an
            exception inside the pipeline, caught by ``plan``); "" otherwise.
    """

    ok: bool
    reason: str | None
    code: str
    joint_names: tuple
    start_rad: np.ndarray
    goal_rad: np.ndarray | None
    path_rad: np.ndarray
    grid_path_rad: np.ndarray
    timings_s: dict
    cached: tuple
    solver: str
    solver_stats: dict
    min_clearance_m: float
    cspace: CSpace | None
    field: Field | None
    smoothing: str = ""
    path_length_rad: float = math.nan
    traceback: str = ""

    def to_json_dict(self) -> dict:
        """Plain-JSON view (the CLI's output): lists and floats, NaN as null."""
        def arr(a):
            return None if a is None else np.asarray(a, dtype=float).tolist()

        def num(x):
            return None if x is None or not math.isfinite(x) else float(x)

        return {
            "ok": self.ok,
            "code": self.code,
            "error": self.reason,
            "joint_names": list(self.joint_names),
            "start_rad": arr(self.start_rad),
            "goal_rad": arr(self.goal_rad),
            "path_rad": arr(self.path_rad),
            "grid_path_rad": arr(self.grid_path_rad),
            "timings_s": {k: float(v) for k, v in self.timings_s.items()},
            "cached": list(self.cached),
            "solver": self.solver,
            "solver_stats": {k: (num(v) if isinstance(v, float) else v)
                             for k, v in self.solver_stats.items()},
            "min_clearance_m": num(self.min_clearance_m),
            "path_length_rad": num(self.path_length_rad),
            "smoothing": self.smoothing,
        }


class _Cancelled(Exception):
    pass


class _Fail(Exception):
    def __init__(self, code, reason):
        super().__init__(reason)
        self.code, self.reason = code, reason


@dataclass
class _FieldEntry:
    field: Field
    blocked: set = dc_field(default_factory=set)        # grid nodes taken out
    cut_edges: set = dc_field(default_factory=set)      # grid edges (flat pairs) taken out
    repairs: int = 0


def _scene_geometry_key(scene: Scene) -> tuple:
    polys = tuple(np.asarray(p, dtype=float).tobytes() for p in scene.obstacle_polygons_m)
    return polys, float(scene.safety_margin_m)


def _deg(q) -> str:
    return "(" + ", ".join(f"{v:.1f}" for v in np.degrees(np.asarray(q, dtype=float))) + ")°"


class Planner:
    """Harmonic-potential planner with cached C-space and field.

    Caches: C-space keyed on (scene geometry + margin, grid); field keyed on (that
    C-space key, goal nodes, solver, tolerance), evicted with its C-space; the
    spacecraft-body table keyed on (grid, margin), kept across target moves.

    Args:
        scenario: robot, scene and grid (``config.Scenario``).
        solver: field solver name (``field.SOLVERS``).
        field_tolerance: gauss_seidel's stopping tolerance (largest change per sweep).
        field_budget_s: wall-time budget of one field solve (log_harmonic), seconds.
        max_grid_nodes: refuse larger grids (before allocating).
        grid_extra_margin_m: added to the safety margin for the grid only.
        shortcut: try a shortcut spline before the paper's every-second-node spline.
        shortcut_keep_clearance_m: shortcuts keep at least margin + this (or the
            clearance of the stretch they replace, if smaller).
        max_step_rad: spacing of the returned samples (≤ 0.5°).
        verify_step_rad: largest spacing of the certified collision checks along the path.
        max_repairs: node-blocking re-solves allowed per plan.
    """

    def __init__(self, scenario: Scenario, solver: str = DEFAULT_SOLVER, field_tolerance: float = 1e-6,
                 max_grid_nodes: int = 4_000_000, *, field_budget_s: float = DEFAULT_BUDGET_S,
                 grid_extra_margin_m: float = 0.02,
                 shortcut: bool = True, shortcut_keep_clearance_m: float = 0.05,
                 max_step_rad: float = DEFAULT_MAX_STEP_RAD,
                 verify_step_rad: float = DEFAULT_VERIFY_STEP_RAD, max_repairs: int = 30):
        self.scenario = scenario
        self.max_grid_nodes = int(max_grid_nodes)
        self.grid_extra_margin_m = float(grid_extra_margin_m)
        self.shortcut = bool(shortcut)
        self.shortcut_keep_clearance_m = float(shortcut_keep_clearance_m)
        self.max_step_rad = float(max_step_rad)
        self.verify_step_rad = float(verify_step_rad)
        self.max_repairs = int(max_repairs)
        self._lock = threading.Lock()
        self._cspaces: dict = {}         # (scene geometry, grid, extra margin) -> CSpace
        self._fields: dict = {}          # (C-space key, goal nodes, solver, tol) -> _FieldEntry
        self._body_tables: dict = {}     # (grid, total margin) -> cspace.body_occupancy
        self._goal_nodes: dict = {}      # (C-space key, goal, verify step) -> free nodes joined to the goal
        self.set_solver(solver, field_tolerance, field_budget_s)
        self._checker = CollisionChecker(scenario.robot, scenario.scene)

    # --------------------------------------------------------------- settings
    def set_scene(self, scene: Scene) -> None:
        """Replace the scene; the caches go only when geometry or margin changed."""
        with self._lock:
            if _scene_geometry_key(scene) != _scene_geometry_key(self.scenario.scene):
                self._cspaces.clear()
                self._fields.clear()
                self._goal_nodes.clear()
            self.scenario = self.scenario.with_scene(scene)
            self._checker = CollisionChecker(self.scenario.robot, scene)

    def set_grid(self, grid: GridSpec) -> None:
        """Replace the grid (C-spaces of other grids stay cached)."""
        if grid.ndim != self.scenario.robot.dof:
            raise ValueError(f"grid.cells: expected {self.scenario.robot.dof} values (one per planned "
                             f"joint), got {grid.ndim}")
        with self._lock:
            from dataclasses import replace
            self.scenario = replace(self.scenario, grid=grid)

    def set_solver(self, solver: str, field_tolerance: float, field_budget_s: float | None = None) -> None:
        """Choose the field solver; ValueError for unknown names, a bad tolerance or budget.

        ``field_budget_s`` None keeps the current budget.
        """
        if solver not in SOLVERS + INTERNAL_SOLVERS:
            raise ValueError(f"planner.solver: unknown solver {solver!r}; expected one of {list(SOLVERS)}")
        tol = float(field_tolerance)
        if not (math.isfinite(tol) and tol > 0.0):
            raise ValueError(f"planner.field_tolerance: must be a positive number, got {field_tolerance!r}")
        if field_budget_s is not None:
            budget = float(field_budget_s)
            if not (math.isfinite(budget) and budget > 0.0):
                raise ValueError(f"planner.field_budget_s: must be a positive number of seconds, "
                                 f"got {field_budget_s!r}")
            self.field_budget_s = budget
        self.solver = solver
        self.field_tolerance = tol

    # ------------------------------------------------------------------- goal
    def goal_from_target(self) -> np.ndarray:
        """Best free IK branch (highest manipulability) of the scene's target, (dof,) rad.

        Raises ValueError with a reason when there is no target, the grasp pose
        is out of reach, or every branch collides.
        """
        sc = self.scenario
        if sc.scene.target is None:
            raise ValueError("no goal given and the scene has no target")
        try:
            every = grasp_ik(sc.robot, sc.scene, free_only=False)
        except ValueError as e:
            raise ValueError(f"no capture posture: {e}") from None
        free = [s for s in every if s.free]
        if free:
            return free[0].q.copy()
        gp = np.round(sc.scene.target.grasp_point_m, 3).tolist()
        if not every:
            raise ValueError(f"the target's grasp point {gp} m is out of the arm's reach "
                             f"(no inverse-kinematics solution within the joint bounds)")
        clr = ", ".join(f"{s.clearance_m:.3f} m" for s in every)
        raise ValueError(f"every capture posture for the grasp point {gp} m collides "
                         f"(clearances {clr}; margin {sc.scene.safety_margin_m} m)")

    # ------------------------------------------------------------------ caches
    def _cspace(self, grid: GridSpec):
        """(C-space, its cache key, cache hit) for the current scene on ``grid``.

        The spacecraft-body table (``cspace.body_occupancy``) depends on the grid and
        the margin only, so it is kept across target and debris moves as well.
        """
        sc = self.scenario
        margin = float(sc.scene.safety_margin_m + self.grid_extra_margin_m)
        key = (_scene_geometry_key(sc.scene), grid, self.grid_extra_margin_m)
        cs = self._cspaces.get(key)
        if cs is not None:
            return cs, key, True
        body_key = (grid, margin)
        if body_key not in self._body_tables:
            if len(self._body_tables) >= 4:
                self._body_tables.pop(next(iter(self._body_tables)))
            self._body_tables[body_key] = body_occupancy(sc.robot, grid, margin)
        cs = build_cspace(sc.robot, sc.scene, grid, extra_margin_m=self.grid_extra_margin_m,
                          body_table=self._body_tables[body_key])
        if len(self._cspaces) >= 4:
            evicted = next(iter(self._cspaces))
            del self._cspaces[evicted]
            for k in [k for k in self._fields if k[0] == evicted]:     # its fields go with it
                del self._fields[k]
            for k in [k for k in self._goal_nodes if k[0] == evicted]:
                del self._goal_nodes[k]
        self._cspaces[key] = cs
        return cs, key, False

    def _field_key(self, cspace_key, goal_nodes):
        return (cspace_key, tuple(map(tuple, goal_nodes)), self.solver, self.field_tolerance,
                self.field_budget_s)

    def _solve(self, cs, goal_nodes, blocked=(), cut_edges=()):
        occ = cs.occupied
        if blocked:
            occ = occ.copy()
            occ[tuple(np.array(sorted(blocked)).T)] = True
        edges = np.array(sorted(cut_edges), dtype=np.int64).reshape(-1, 2)
        return solve_field(occ, cs.grid.periodic, np.asarray(goal_nodes), solver=self.solver,
                           tol=self.field_tolerance, budget_s=self.field_budget_s,
                           cut_edges=edges if len(edges) else None)

    # ------------------------------------------------------------------- plan
    def plan(self, start_rad, goal_rad=None, cancel: threading.Event | None = None,
             progress: Callable[[str], None] | None = None) -> PlanResult:
        """Plan from ``start_rad`` to ``goal_rad`` (default: :meth:`goal_from_target`).

        Never raises for bad input or when there is no path: returns ``ok=False``
        with ``code`` and ``reason``.
        """
        with self._lock:
            return _PlanRun(self, cancel, progress).run(start_rad, goal_rad)


class _PlanRun:
    """One call of Planner.plan: the stages, their timings and the failure codes."""

    def __init__(self, planner: Planner, cancel, progress):
        self.p = planner
        self.sc = planner.scenario
        self.robot = self.sc.robot
        self.checker = planner._checker
        self.motions = SegmentTest.of(self.checker)
        self.cancel = cancel
        self.progress = progress
        self.timings = {k: 0.0 for k in STAGES}
        self.cached = []
        self.cs = None
        self.field = None
        self.start = None
        self.goal = None
        self.grid_path = np.zeros((0, self.robot.dof))
        self.stats = {}
        self.lower = self.robot.planned_lower_rad
        self.upper = self.robot.planned_upper_rad
        self.periodic = self.robot.planned_periodic

    # ---------------------------------------------------------------- helpers
    def say(self, text):
        if self.progress is not None:
            self.progress(text)

    def check_cancel(self):
        if self.cancel is not None and self.cancel.is_set():
            raise _Cancelled()

    def result(self, ok, code, reason, path=None, smooth=None, t0=0.0, tb=""):
        self.timings["total"] = time.perf_counter() - t0
        dof = self.robot.dof
        start = self.start if self.start is not None else np.full(dof, np.nan)
        return PlanResult(
            ok=ok, reason=reason, code=code, joint_names=self.robot.planned_names,
            start_rad=start, goal_rad=self.goal,
            path_rad=path if path is not None else np.zeros((0, dof)),
            grid_path_rad=self.grid_path, timings_s=dict(self.timings), cached=tuple(self.cached),
            solver=self.p.solver, solver_stats=dict(self.stats),
            min_clearance_m=smooth.min_clearance_m if smooth is not None else math.nan,
            cspace=self.cs, field=self.field,
            smoothing=smooth.method if smooth is not None else "",
            path_length_rad=smooth.length_rad if smooth is not None else math.nan, traceback=tb)

    def segment_ok(self, a, b) -> bool:
        seg = unwrap_path(np.vstack([a, b]), self.periodic)
        t = time.perf_counter()
        ok = check_path(self.checker, seg, self.lower, self.upper, self.periodic,
                        self.p.verify_step_rad).ok
        self.timings["verify"] += time.perf_counter() - t
        return ok

    def candidates(self, q, grid, free_mask, max_count=8):
        """Free grid nodes near q (within 2 steps per axis), nearest first."""
        base = np.floor((q - np.asarray(grid.lower_rad)) / grid.step_rad).astype(np.int64)
        offs = np.stack(np.meshgrid(*[np.arange(-1, 3)] * grid.ndim, indexing="ij"), -1).reshape(-1, grid.ndim)
        nodes = base + offs
        shape = np.asarray(grid.shape)
        keep = np.ones(len(nodes), dtype=bool)
        for a, p in enumerate(grid.periodic):
            if p:
                nodes[:, a] %= shape[a]
            else:
                keep &= (nodes[:, a] >= 0) & (nodes[:, a] < shape[a])
        nodes = np.unique(nodes[keep], axis=0)
        d = grid.config_of(nodes) - q
        for a, p in enumerate(grid.periodic):
            if p:
                d[:, a] = (d[:, a] + np.pi) % (2.0 * np.pi) - np.pi
        order = np.argsort(np.linalg.norm(d, axis=1), kind="stable")
        nodes = nodes[order]
        nodes = nodes[free_mask[tuple(nodes.T)]]
        return nodes[:max_count]

    # ------------------------------------------------------------------- run
    def run(self, start_rad, goal_rad):
        t0 = time.perf_counter()
        try:
            return self._run(start_rad, goal_rad, t0)
        except _Cancelled:
            self.say("cancelled")
            return self.result(False, "cancelled", "planning was cancelled", t0=t0)
        except _Fail as f:
            self.say(f"failed ({f.code}): {f.reason}")
            return self.result(False, f.code, f.reason, t0=t0)
        except Exception as e:     # the contract: plan() never raises; say what broke
            reason = f"internal error while planning: {type(e).__name__}: {e}"
            self.say(reason)
            return self.result(False, "internal_error", reason, t0=t0, tb=_traceback.format_exc())

    def _run(self, start_rad, goal_rad, t0):
        p, sc, robot = self.p, self.sc, self.robot
        margin = sc.scene.safety_margin_m
        # ---- input
        try:
            self.start = robot.validate_q(np.asarray(start_rad, dtype=float), "start")
        except (ValueError, TypeError) as e:
            raise _Fail("invalid_input", str(e)) from None
        grid = sc.grid
        if grid.n_nodes > p.max_grid_nodes:
            raise _Fail("invalid_input", f"grid.cells {list(grid.cells)} gives {grid.n_nodes:,} nodes, "
                        f"above the budget planner.max_grid_nodes = {p.max_grid_nodes:,}")
        if goal_rad is None:
            try:
                self.goal = p.goal_from_target()
            except ValueError as e:
                raise _Fail("goal_unreachable", str(e)) from None
            self.say(f"goal from the target's IK: {_deg(self.goal)}")
        else:
            try:
                self.goal = robot.validate_q(np.asarray(goal_rad, dtype=float), "goal")
            except (ValueError, TypeError) as e:
                raise _Fail("invalid_input", str(e)) from None
        clr_s = self.checker.clearance_m(self.start)
        if not clr_s > margin:
            raise _Fail("start_in_collision", f"the start {_deg(self.start)} is in collision: clearance "
                        f"{clr_s:.3f} m, the safety margin is {margin} m")
        clr_g = self.checker.clearance_m(self.goal)
        if not clr_g > margin:
            raise _Fail("goal_in_collision", f"the goal {_deg(self.goal)} is in collision: clearance "
                        f"{clr_g:.3f} m, the safety margin is {margin} m")
        self.check_cancel()
        # ---- C-space
        t = time.perf_counter()
        self.cs, cs_key, hit = p._cspace(grid)
        if hit:
            self.cached.append("cspace")
        else:
            self.timings["cspace"] = time.perf_counter() - t
        ms = "cached" if hit else f"{1e3 * self.timings['cspace']:.1f} ms"
        self.say(f"cspace {grid.label()}: {ms}, {100 * self.cs.free_fraction:.1f} % free")
        self.check_cancel()
        free = ~self.cs.occupied
        # ---- goal nodes: free nodes near the goal joined to it by a verified segment
        goal_key = (cs_key, self.goal.tobytes(), p.verify_step_rad)
        goal_nodes = p._goal_nodes.get(goal_key)
        if goal_nodes is None:
            goal_nodes = [n for n in self.candidates(self.goal, grid, free)
                          if self.segment_ok(grid.config_of(n), self.goal)][:4]
            if len(p._goal_nodes) >= 16:
                p._goal_nodes.pop(next(iter(p._goal_nodes)))
            p._goal_nodes[goal_key] = goal_nodes
        if not goal_nodes:
            raise _Fail("path_invalid", f"no free grid node near the goal {_deg(self.goal)} can be joined "
                        f"to it by a collision-free straight segment (grid {grid.label()}); "
                        "try a finer grid")
        goal_nodes = np.array(goal_nodes)
        # ---- field (cached per goal nodes) + descent + repair
        key = p._field_key(cs_key, goal_nodes)
        entry = p._fields.get(key)
        if entry is not None:
            self.cached.append("field")
            self.say(f"field: cached ({entry.field.solver})")
        else:
            self.check_cancel()
            t = time.perf_counter()
            entry = _FieldEntry(p._solve(self.cs, goal_nodes))
            self.timings["field"] += time.perf_counter() - t
            if len(p._fields) >= 8:
                p._fields.pop(next(iter(p._fields)))
            p._fields[key] = entry
            fld = entry.field
            self.say(f"field ({fld.solver}): {1e3 * self.timings['field']:.1f} ms, {fld.sweeps} "
                     f"{'sweeps' if fld.solver == 'gauss_seidel' else 'iterations'}, residual "
                     f"{fld.residual:.2e}" + ("" if fld.converged else f"; NOT converged: {fld.left}"))
        self.field = entry.field
        waypoints = self.descend_and_repair(entry, goal_nodes, key)
        self.field = entry.field
        f = entry.field
        self.stats = {"sweeps": int(f.sweeps), "residual": float(f.residual),
                      "converged": bool(f.converged), "left": f.left, **f.stats,
                      "repairs": int(entry.repairs), "blocked_nodes": len(entry.blocked),
                      "cut_edges": len(entry.cut_edges)}
        # ---- smoothing + verify
        self.check_cancel()
        t = time.perf_counter()
        smooth = smooth_path(self.checker, waypoints, self.lower, self.upper, self.periodic,
                             shortcut=p.shortcut, keep_clearance_m=p.shortcut_keep_clearance_m,
                             max_step_rad=p.max_step_rad,
                             verify_step_rad=p.verify_step_rad, cancel=self.cancel)
        t_smooth = time.perf_counter() - t
        self.check_cancel()
        if smooth is None:
            self.timings["smoothing"] = t_smooth
            raise _Fail("path_invalid", "no smoothed path passed the dense collision check")
        self.timings["smoothing"] = t_smooth
        self.say(f"smoothing ({smooth.method}, {smooth.refinements} refinements): "
                 f"{1e3 * t_smooth:.1f} ms; {len(smooth.path_rad)} samples, length "
                 f"{smooth.length_rad:.3f} rad, min clearance {smooth.min_clearance_m:.4f} m")
        res = self.result(True, "ok", None, path=smooth.path_rad, smooth=smooth, t0=t0)
        self.say(f"total {1e3 * res.timings_s['total']:.1f} ms")
        return res

    def no_field_path_failure(self, f, entry):
        """Why no start node has a field value: 'disconnected' only when the grid's own free
        space (without nodes blocked by repairs) separates every free node near the start
        from every free node near the goal."""
        grid, occ = self.sc.grid, self.cs.occupied
        goal_nodes = self.candidates(self.goal, grid, ~occ)
        start_nodes = self.candidates(self.start, grid, ~occ)
        if len(start_nodes) == 0:
            return _Fail("path_invalid", f"every grid node near the start {_deg(self.start)} is an "
                         f"obstacle on the grid {grid.label()}; try a finer grid")
        dist = bfs_distance(occ, grid.periodic, goal_nodes)
        if np.all(dist[tuple(start_nodes.T)] < 0):
            return _Fail("disconnected", f"the start {_deg(self.start)} and the goal {_deg(self.goal)} "
                         f"lie in separate free regions of the configuration space "
                         f"(grid {grid.label()}): no collision-free motion joins them")
        if entry.blocked:
            return _Fail("path_invalid", f"start and goal are connected on the grid {grid.label()}, but "
                         f"after blocking {len(entry.blocked)} node(s) whose straight joins collide no "
                         "verified grid path remains; try a finer grid")
        return _Fail("path_invalid", f"the field of solver '{f.solver}' is zero (flat in float64) at the "
                     "start although the grid joins start and goal; use the log_harmonic solver")

    def descend_and_repair(self, entry, goal_nodes, key):
        """Descent from a start node, then block nodes until the polyline verifies.

        Returns the unwrapped waypoints: exact start, grid nodes, exact goal.
        """
        p, grid = self.p, self.sc.grid
        for attempt in range(p.max_repairs + 1):
            self.check_cancel()
            f = entry.field
            t = time.perf_counter()
            free = ~f.occupied
            starts = self.candidates(self.start, grid, free)
            if len(starts) == 0:
                self.timings["descent"] += time.perf_counter() - t
                raise _Fail("path_invalid", f"every grid node near the start {_deg(self.start)} is "
                            f"blocked (grid {grid.label()}, margin {self.cs.margin_m:.3f} m); try a finer grid")
            reach = f.reachable[tuple(starts.T)]
            if not reach.any():
                self.timings["descent"] += time.perf_counter() - t
                raise self.no_field_path_failure(f, entry)
            path = None
            blocked = None
            reasons = []
            for node in starts[reach]:
                if not self.segment_ok(self.start, grid.config_of(node)):
                    reasons.append(f"segment to node {tuple(node)} collides")
                    continue
                t1 = time.perf_counter()
                gp = descend(f, node, self.motions, grid.lower_rad, grid.step_rad)
                self.timings["descent"] += time.perf_counter() - t1
                if gp.reached:
                    path = gp
                    break
                if gp.blocked and blocked is None:
                    blocked = gp
                reasons.append(gp.reason)
            if path is None and blocked is not None and attempt < p.max_repairs:
                # every way up from that node collides: cut the colliding grid edges around
                # it (the node itself when there are none to cut) and re-solve
                self.cut_and_resolve(entry, goal_nodes, tuple(int(v) for v in blocked.nodes[-1]),
                                     blocked.reason)
                continue
            if path is None:
                raise _Fail("path_invalid", "no grid path from the start: " + "; ".join(reasons[:3]))
            nodes_rad = grid.config_of(path.nodes)
            self.grid_path = nodes_rad
            wp = unwrap_path(np.vstack([self.start, nodes_rad, self.goal]), self.periodic)
            turns = np.round((wp[-1] - self.goal) / (2.0 * np.pi))
            wp[-1] = self.goal + 2.0 * np.pi * turns     # exactly the goal (mod 2π on periodic joints)
            t = time.perf_counter()
            bad = first_bad_segment(self.checker, wp, self.lower, self.upper, self.periodic,
                                    p.verify_step_rad)
            self.timings["verify"] += time.perf_counter() - t
            if bad < 0:
                return wp
            # segment bad joins waypoint bad and bad+1; waypoint k ≥ 1 is path node k-1
            cand = [k - 1 for k in (bad, bad + 1) if 1 <= k <= len(path.nodes)]
            goal_set = {tuple(g) for g in goal_nodes}
            cand = [c for c in cand if tuple(path.nodes[c]) not in goal_set]
            if not cand or attempt == p.max_repairs:
                raise _Fail("path_invalid", f"the straight segment between grid nodes "
                            f"{_deg(wp[bad])} and {_deg(wp[bad + 1])} collides and the grid path "
                            f"could not be repaired ({entry.repairs} repairs); try a finer grid")
            clr = [self.checker.clearance_m(nodes_rad[c]) for c in cand]
            block = tuple(int(v) for v in path.nodes[cand[int(np.argmin(clr))]])
            self.block_and_resolve(entry, goal_nodes, block, f"segment {_deg(wp[bad])} → "
                                   f"{_deg(wp[bad + 1])} collides")
        raise AssertionError("unreachable")

    def cut_and_resolve(self, entry, goal_nodes, node, why):
        """Repair of a blocked walk: cut the grid edges near ``node`` whose motions collide
        (both ends free), or block the node when all of those are cut already; re-solve."""
        grid = self.sc.grid
        t = time.perf_counter()
        radius = REPAIR_RADIUS + min(entry.repairs, 3)     # a wider look each time
        edges = colliding_edges(entry.field.occupied, grid.periodic, node, self.motions,
                                grid.lower_rad, grid.step_rad, radius=radius)
        self.timings["repair"] += time.perf_counter() - t
        new = {(int(a), int(b)) for a, b in edges} - entry.cut_edges
        if not new:
            self.block_and_resolve(entry, goal_nodes, node, why)
            return
        entry.cut_edges |= new
        entry.repairs += 1
        self.say(f"repair: {why}; cutting {len(new)} colliding grid edge(s) around it and "
                 "re-solving the field")
        self.resolve(entry, goal_nodes)

    def block_and_resolve(self, entry, goal_nodes, node, why):
        """Repair: take grid ``node`` out of the field's free space and solve the field again."""
        entry.blocked.add(node)
        entry.repairs += 1
        self.say(f"repair: {why}; blocking node {node} and re-solving the field")
        self.resolve(entry, goal_nodes)

    def resolve(self, entry, goal_nodes):
        t = time.perf_counter()
        entry.field = self.p._solve(self.cs, goal_nodes, entry.blocked, entry.cut_edges)
        self.timings["repair"] += time.perf_counter() - t
        if "field" in self.cached:
            self.cached.remove("field")


def warm_up(scenario: Scenario, cells: int = 6) -> float:
    """Compile (or load from numba's cache) every kernel a plan uses; return the seconds.

    Plans on a coarse copy of the scenario's grid from random free postures, so the
    first real plan's stage timings are the planner's, not the JIT's.
    """
    from dataclasses import replace
    t0 = time.perf_counter()
    coarse = replace(scenario, grid=scenario.grid.with_cells(cells))
    planner = Planner(coarse)
    rng = np.random.default_rng(0)
    lo, hi = coarse.robot.planned_lower_rad, coarse.robot.planned_upper_rad
    q = rng.uniform(lo, hi, size=(64, coarse.robot.dof))
    free = q[CollisionChecker(coarse.robot, coarse.scene).is_free(q)]
    if len(free) < 2:
        free = q
    for start, goal in zip(free[:-1:2], free[1::2]):
        if planner.plan(start, goal).ok:
            break
    field_warm_up()             # the solver kernels a coarse grid does not reach
    return time.perf_counter() - t0
