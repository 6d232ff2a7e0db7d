"""
One plan, stage by stage: :func:`run_pipeline` reads top to bottom.

    inputs → exit (leave a contact) → C-space → goal nodes → field → descent/repair
           → smoothing → trajectory

Free floating (``acs.mode: free_floating``) with a target and no goal, or with the attitude
a planned joint: ``free_floating_capture.plan_capture`` replaces the stages up to smoothing (its
search is timed as "descent", its inertial certification as "verify"), then the trajectory.

Each stage is a method of :class:`PlanRun` (one call of ``Planner.plan``) that calls
the stage's own module, is timed by :meth:`PlanRun.stage` and fails by raising
:class:`Fail` with a :class:`~spacerobot_planner.results.Code`.  The run reads the
planner's caches and adds entries to them, but never changes an entry: a repaired field
is a new field, cached under a key that names its cut edges and blocked nodes, so the
same input gives the same path whatever the planner planned before.

Cancel: the run's one termination token (``termination.Termination``, from the
``cancel`` given to ``Planner.plan``) is checked between the stages and handed to the
long ones, whose kernels poll it inside their loops (the C-space rows, the field's CG
iterations and sweeps) and between their steps (descent candidates and repairs,
smoothing rounds).  A stage stopped by it raises :class:`Cancelled` before it stores
anything, so the caches hold only complete C-spaces and fields.
"""

from __future__ import annotations

import functools
import math
import time
import traceback as _traceback

import numba as nb
import numpy as np

from .contact import leave_contact, what_is_hit
from .descent import WalkJoins
from .field import bfs_distance, validate_problem
from .field.graph import _next_coord, bfs as field_bfs, grid_strides
from .free_floating_capture import apparent_scene, captures_free_floating, check_capture_scenario, plan_capture
from .joint_space import align_to_state, deg_text, nearest_turn_rad, unwrap_path, wrap_angle_scalar_rad
from .motion import MotionValidator
from .repair import MAX_TESTS, CutEdges, sheet_edges
from . import swept
from .results import STAGES, Code, PlanResult
from .smoothing import SmoothPath, path_length_rad, smooth_path, start_direction
from .spacecraft import free_floating_response
from .termination import Cancelled, Termination
from .timing import timed_motion, trajectory_limits_known

#: timed_motion, trajectory_limits_known: the trajectory stage (``timing.py``), also importable
#: from here (tests do; the node's chain, ``adapters.py``, imports it from ``timing``)
__all__ = ["run_pipeline", "PlanRun", "Fail", "NotCached", "grid_margins", "timed_motion", "trajectory_limits_known"]

#: A repair cuts the colliding grid edges within this many index steps of the blocked node
#: (one more with each repair of the same plan, up to REPAIR_WIDENING more) and those joined
#: to them (``repair.sheet_edges``).
REPAIR_RADIUS = 2
REPAIR_WIDENING = 3
#: ... and follows their sheet for up to ``repair.MAX_TESTS`` tested edges, twice as many with each
#: repair of the same plan, up to 2^REPAIR_DOUBLINGS times as many: a long thin wall (a sliver of
#: debris) is a sheet of thousands of edges, which 2 000 tests a repair cut a hundred at a time
#: (30 repairs at 72³, then path_invalid after 5 s, where a path kept 51 mm; now 5 repairs at 36³)
REPAIR_DOUBLINGS = 5
#: the start and the goal are joined to (at most) this many of their nearest free grid nodes
#: (``PlanRun.candidates``); the goal to the rest of its window where none of them joins
NEAR_NODES = 8
#: a refined grid has twice the cells per joint, or, where that grid is above the node limits,
#: the most cells one common factor gives within them: never less than this factor (a grid
#: barely finer than one that failed is not worth its solve)
MIN_REFINEMENT = 1.25


class Fail(Exception):
    """
    A stage's answer that there is no (acceptable) plan: a code and a reason.

    ``brief``: for a failure on one grid, a short phrase for the summary of the grids tried
    (``PlanRun.find_grid_path``); the reason when empty.
    """

    def __init__(self, code: Code, reason: str, brief: str = ""):
        super().__init__(reason)
        self.code, self.reason, self.brief = code, reason, brief or reason


class Refine(Fail):
    """A grid given up for a finer one (repairs piled up): ``PlanRun.find_grid_path`` refines at once."""


class NotCached(Exception):
    """
    A plan from the caches alone (``Planner.plan(cached_only=True)``) met a stage they do not hold: its name.

    Raised before the stage's work (a C-space, a field solve, the grid's connectivity search
    before a solve, a repair, a free-floating capture's search); never turned into a result
    (:meth:`PlanRun.run`).
    """


def grid_margins(settings, level: int = 0) -> tuple:
    """
    Return the grid's extra margins, m, a plan tries on a grid of refinement ``level``, in order.

    On the scenario's grid the configured one (``settings.grid_extra_margin_m``), then 0 (a grid
    with the extra margin can close a passage that the safety margin leaves open); on a refined
    grid 0 only (it is tried because a coarser one did not give a path: the extra margin would
    narrow the passages it looks for).
    """
    extra = settings.grid_extra_margin_m
    return (extra, 0.0) if extra > 0.0 and level == 0 else (0.0,)


def run_pipeline(run: "PlanRun", start_rad, goal_rad) -> PlanResult:
    """Run the stages in order; see the module docstring.  Raises Fail or Cancelled."""
    if run.free_floating_capture(goal_rad):
        return run.time_parameterize(run.capture_free_floating(start_rad, goal_rad))
    run.check_inputs(start_rad, goal_rad)            # invalid_input, goal_unreachable, *_in_collision
    run.leave_contact()                              # a start touching an obstacle: the exit stretch
    waypoints = run.find_grid_path()                 # C-space → field → descent/repair, refined if need be
    smooth = run.smooth(waypoints)
    return run.time_parameterize(smooth)


def _count(n: int, word: str) -> str:
    """Return '1 repair', '3 repairs'."""
    return f"{n} {word}" + ("" if n == 1 else "s")


def _repair_limit(max_repairs: int) -> str:
    """Return the reason's note that the repairs' limit, not the grid, ended a plan that could repair further."""
    if max_repairs == 0:
        return " (no repair tried: planner.max_repairs = 0)"
    return f" (planner.max_repairs = {max_repairs} reached)"


def _repairs_text(repairs: int, cut, blocked) -> str:
    """Return '3 repairs (12 cut edges, 1 blocked node)'."""
    return (f"{_count(repairs, 'repair')} ({_count(len(cut), 'cut edge')}, "
            f"{_count(len(blocked), 'blocked node')})")


@nb.njit(cache=True, nogil=True)
def _near_free_nodes(q_rad, lower_rad, step_rad, shape, periodic, occupied_flat, max_count):
    """
    ``PlanRun.candidates``' kernel: free nodes within index offsets -1 .. 2 of q's cell, nearest first.

    q_rad, lower_rad, step_rad: (ndim,) float (rad); shape: (ndim,) int64 nodes per axis;
    periodic: (ndim,) bool; occupied_flat: (n_nodes,) bool, row-major.  Node indices wrap
    on periodic axes and are dropped outside bounded ones; distinct free nodes are taken
    in row-major order and sorted stably by their joint-space distance to q (the short way
    round on periodic axes; squares summed axis by axis, then the root: the float
    operations of ``numpy.linalg.norm`` over ``difference_rad``).  Returns (k, ndim) int64,
    k ≤ max_count.
    """
    ndim = q_rad.shape[0]
    vals = np.empty((ndim, 4), np.int64)         # each axis' distinct in-range indices, ascending
    dsq = np.empty((ndim, 4))                    # their squared differences to q
    counts = np.zeros(ndim, np.int64)
    strides = grid_strides(shape)
    for a in range(ndim - 1, -1, -1):
        base = np.int64(math.floor((q_rad[a] - lower_rad[a]) / step_rad[a]))
        for o in range(-1, 3):
            v = base + o
            if periodic[a]:
                v = v % shape[a]
            elif v < 0 or v >= shape[a]:
                continue
            j = counts[a]
            while j > 0 and vals[a, j - 1] > v:   # insert in order, skipping repeats
                j -= 1
            if j > 0 and vals[a, j - 1] == v:
                continue
            for m in range(counts[a], j, -1):
                vals[a, m] = vals[a, m - 1]
            vals[a, j] = v
            counts[a] += 1
        if counts[a] == 0:
            return np.empty((0, ndim), np.int64)
        for j in range(counts[a]):
            d = (lower_rad[a] + vals[a, j] * step_rad[a]) - q_rad[a]
            if periodic[a]:
                d = wrap_angle_scalar_rad(d)
            dsq[a, j] = d * d
    n_all = 1
    for a in range(ndim):
        n_all *= counts[a]
    flat_of = np.empty(n_all, np.int64)
    dist = np.empty(n_all)
    pick = np.zeros(ndim, np.int64)              # odometer over the axes' indices, last axis fastest
    k = 0
    for _ in range(n_all):
        flat = 0
        for a in range(ndim):
            flat += vals[a, pick[a]] * strides[a]
        if not occupied_flat[flat]:
            s = 0.0
            for a in range(ndim):
                s += dsq[a, pick[a]]
            flat_of[k] = flat
            dist[k] = math.sqrt(s)
            k += 1
        _next_coord(pick, counts)
    n_out = min(k, max_count)
    out = np.empty((n_out, ndim), np.int64)
    taken = np.zeros(k, np.bool_)
    for r in range(n_out):                       # the nearest not yet taken; the first in row-major order on ties
        best = -1
        for i in range(k):
            if not taken[i] and (best < 0 or dist[i] < dist[best]):
                best = i
        taken[best] = True
        flat = flat_of[best]
        for a in range(ndim):
            out[r, a] = (flat // strides[a]) % shape[a]
    return out


@functools.lru_cache(maxsize=64)
def _grid_arrays(grid):
    """(lower_rad, step_rad, shape, periodic) of a ``GridSpec`` as the arrays ``_near_free_nodes`` takes."""
    return (np.asarray(grid.lower_rad, dtype=float), np.asarray(grid.step_rad, dtype=float),
            np.asarray(grid.shape, dtype=np.int64), np.asarray(grid.periodic, dtype=np.bool_))


class _StageTimer:
    """:meth:`PlanRun.stage`'s context manager: the time spent in its block added to ``timings[name]``."""

    __slots__ = ("timings", "name", "t")

    def __init__(self, timings: dict, name: str):
        self.timings, self.name = timings, name

    def __enter__(self) -> None:
        self.t = time.perf_counter()

    def __exit__(self, *exc) -> None:
        self.timings[self.name] += time.perf_counter() - self.t


def scaled_grid(grid, factor: float):
    """Return ``grid`` with its cells per joint times ``factor`` (> 1), rounded down, at least one more."""
    return grid.with_cells(tuple(max(int(c) + 1, int(math.floor(factor * int(c)))) for c in grid.cells))


def refined(grid, max_nodes: int | None = None):
    """
    Return the grid a refinement of ``grid`` tries (``cspace.GridSpec``), or None.

    Twice the cells along every axis; where that grid has more than ``max_nodes`` nodes, the
    cells times the largest common factor in [``MIN_REFINEMENT``, 2) whose grid has at most
    ``max_nodes`` (:func:`scaled_grid`; a 4-joint 16x17x17x17 grid: 25x26x26x26, 439 400
    nodes within 500 000, where the doubled one has 1.15 million); None where even
    ``MIN_REFINEMENT`` times the cells is above ``max_nodes``.
    """
    if max_nodes is None or scaled_grid(grid, 2.0).n_nodes <= max_nodes:
        return scaled_grid(grid, 2.0)
    if scaled_grid(grid, MIN_REFINEMENT).n_nodes > max_nodes:
        return None
    lo, hi = MIN_REFINEMENT, 2.0        # n_nodes grows with the factor: the largest within the limit
    for _ in range(40):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if scaled_grid(grid, mid).n_nodes <= max_nodes else (lo, mid)
    return scaled_grid(grid, lo)


class PlanRun:
    """
    One call of ``Planner.plan``: the stages' state, timings and cache look-ups.

    Parameters
    ----------
        planner: the ``Planner`` (its caches and checker).
        settings: the ``PlannerSettings`` of this plan (a snapshot).
        cancel: a ``termination.Termination`` (polled inside the kernels), any object with
            ``is_set()`` (polled between steps only) or None; progress: a callable(str) or None.

    """

    def __init__(self, planner, settings, cancel, progress, start_tangent=None, cached_only: bool = False):
        self.p = planner
        self.cached_only = cached_only           # raise NotCached rather than build what the caches lack
        self.start_tangent_given = start_tangent  # the direction to leave the start along (check_inputs)
        self.start_tangent = None
        self.s = settings
        self.sc = planner.scenario
        self.robot = self.sc.robot
        self.checker = planner._checker
        #: the scene's motion validator at this plan's certified step
        self.validator = MotionValidator.of(planner._validator, settings.verify_step_rad)
        self.cancel = Termination.of(cancel)       # the run's one termination token
        self.progress = progress
        self.timings = {k: 0.0 for k in STAGES}
        self.cached = []
        self.stats = {}
        self.cs = self.fld = None
        self.start = self.goal = self.start_given = None
        self.plan_start = None                   # the start of the certified plan (after an exit)
        self.exit_path = np.zeros((0, self.robot.dof))
        self.start_clearance_m = math.nan        # the start's clearance (check_inputs), m
        self.penetration_m = 0.0
        self.approach_error_deg = math.nan
        self.grid_path = np.zeros((0, self.robot.dof))
        self.waypoint_check = None               # the certified check of the verified waypoints
        self.periodic = self.validator.periodic
        self.t0 = time.perf_counter()
        self.level = 0                             # refinements of the grid now tried

    # ---------------------------------------------------------------- helpers
    @functools.cached_property
    def motions(self):
        """Return the descent's quick segment test (``MotionValidator.segment_test``), made when a walk needs it."""
        return self.validator.segment_test()

    def stage(self, name: str) -> "_StageTimer":
        """Add the time spent in the ``with`` block to ``timings_s[name]``."""
        return _StageTimer(self.timings, name)

    def say(self, text: str) -> None:
        if self.progress is not None:
            self.progress(text)

    def check_cancel(self) -> None:
        self.cancel.check()

    def result(self, code: Code, reason: str | None, smooth=None, path=None, tb: str = "",
               trajectory=None, reaction=None) -> PlanResult:
        self.timings["total"] = time.perf_counter() - self.t0
        dof = self.robot.dof
        ok = code == Code.OK
        return PlanResult(
            ok=ok, reason=reason, code=code, joint_names=self.robot.planned_names,
            start_rad=self.start if self.start is not None else np.full(dof, np.nan),
            goal_rad=self.goal, path_rad=path if path is not None else np.zeros((0, dof)),
            grid_path_rad=self.grid_path, timings_s=dict(self.timings), cached=tuple(self.cached),
            solver=self.s.solver, solver_stats=dict(self.stats, **self.p.threads_note()),
            min_clearance_m=smooth.min_clearance_m if smooth is not None else math.nan,
            cspace=self.cs, field=self.fld, smoothing=smooth.method if smooth is not None else "",
            path_length_rad=(math.nan if path is None else smooth.length_rad if path is smooth.path_rad
                             else path_length_rad(path)),
            traceback=tb, trajectory=trajectory, reaction=reaction,
            approach_error_deg=self.approach_error_deg, exit_path_rad=self.exit_path,
            start_penetration_m=self.penetration_m, free_floating=self.drift_of(path))

    def drift_of(self, path):
        """Free floating: the response (``spacecraft.FreeFloatingResponse``) along ``path``; else None."""
        if self.sc.acs.mode != "free_floating" or path is None or not len(path):
            return None
        grasp = None if self.sc.scene.target is None else self.sc.scene.target.grasp_point_m
        return free_floating_response(self.robot, self.sc.masses, path, grasp)

    def segment_ok(self, a, b, keep: bool = False) -> bool:
        """Run the certified motion check of the straight (shortest) segment a → b (``keep``: its certificate kept)."""
        with self.stage("verify"):
            return self.validator.segment_ok(a, b, keep=keep)

    def candidates(self, q, grid, occupied, max_count: int = NEAR_NODES) -> np.ndarray:
        """
        Free grid nodes near q, nearest first: (k ≤ max_count, dof) int64.

        Within index offsets -1 .. 2 per axis of q's cell (wrapped on periodic axes, inside
        bounded ones; ``occupied``: the grid's), by joint-space distance the short way round,
        ties in row-major order (``_near_free_nodes``).
        """
        lower, step, shape, per = _grid_arrays(grid)
        return _near_free_nodes(np.ascontiguousarray(q, dtype=float), lower, step, shape, per,
                                np.ascontiguousarray(occupied, dtype=np.bool_).ravel(), max_count)

    # ----------------------------------------------------------------- stages
    def validated_q(self, q_rad, name: str) -> np.ndarray:
        """Return ``q_rad`` validated (``robot.validate_q``), or raise ``invalid_input`` naming ``name``."""
        try:
            return self.robot.validate_q(q_rad, name)
        except (ValueError, TypeError) as e:
            raise Fail(Code.INVALID_INPUT, str(e)) from None

    def take_start(self, start_rad) -> None:
        """Set ``start`` (:meth:`validated_q`) and ``start_given`` (as given, rad)."""
        self.start = self.validated_q(start_rad, "start")
        self.start_given = np.asarray(start_rad, dtype=float)     # numbers: validate_q says so

    def check_inputs(self, start_rad, goal_rad) -> None:
        """
        Start and goal valid and in bounds.

        The goal from the target when none is given; the goal free; the start free or (see
        :meth:`leave_contact`) touching only.
        """
        robot, margin = self.robot, self.sc.scene.safety_margin_m
        self.take_start(start_rad)
        try:
            self.start_tangent = start_direction(self.start_tangent_given, robot.dof)
        except ValueError as e:
            raise Fail(Code.INVALID_INPUT, str(e)) from None
        clr_s = self.start_clearance_m = self.checker.clearance_m(self.start)
        if not clr_s > margin and not self.s.max_start_penetration_m > 0.0:
            raise Fail(Code.START_IN_COLLISION, f"the start {deg_text(self.start)} is in collision: "
                       f"clearance {clr_s:.3f} m, the safety margin is {margin} m")
        grid = self.sc.grid
        if grid.n_nodes > self.s.max_grid_nodes:
            raise Fail(Code.INVALID_INPUT, f"grid.cells {list(grid.cells)} gives {grid.n_nodes:,} nodes, "
                       f"above the budget planner.max_grid_nodes = {self.s.max_grid_nodes:,}")
        if goal_rad is None:
            try:
                chosen = self.p.capture_goal()
            except ValueError as e:
                raise Fail(Code.GOAL_UNREACHABLE, str(e)) from None
            self.goal = chosen.q.copy()
            self.say(f"goal from the target's IK: {deg_text(self.goal)}, manipulability "
                     f"{chosen.manipulability:.3f} m² ({chosen.method})")
        else:
            self.goal = self.validated_q(goal_rad, "goal")
        clr_g, self.approach_error_deg = self.p.goal_clearance_and_approach(self.goal)
        if not clr_g > margin:
            raise Fail(Code.GOAL_IN_COLLISION, f"the goal {deg_text(self.goal)} is in collision: clearance "
                       f"{clr_g:.3f} m, the safety margin is {margin} m")
        self.plan_start = self.start
        self.check_cancel()

    def free_floating_capture(self, goal_rad) -> bool:
        """Tell whether this plan is a free-floating capture (``free_floating_capture.captures_free_floating``)."""
        return captures_free_floating(self.sc, goal_rad is not None)

    def capture_free_floating(self, start_rad, goal_rad):
        """
        Free floating: the arm's path that ends in the grasp, the body drifted (``free_floating_capture.plan_capture``).

        Returns a ``smoothing.SmoothPath`` of it (clearance: the inertial check's); refused
        (``reaction_refused``) with the attitude change needed and what the arm's motions
        achieve, or the inertial clearance; ``goal_unreachable`` for a chain it does not handle
        and for a grasp no capture posture reaches.
        """
        if self.cached_only:
            raise NotCached("free-floating capture")
        robot, margin = self.robot, self.sc.scene.safety_margin_m
        self.take_start(start_rad)
        goal = None if goal_rad is None else self.validated_q(goal_rad, "goal")
        clr_s = self.checker.clearance_m(self.start)
        if not clr_s > margin:
            raise Fail(Code.START_IN_COLLISION, f"the start {deg_text(self.start)} is in collision: "
                       f"clearance {clr_s:.3f} m, the safety margin is {margin} m")
        self.plan_start = self.start
        guide = self.field_guide if goal is None and 0 not in robot.planned_joints else None
        try:
            check_capture_scenario(self.sc)
        except ValueError as e:
            raise Fail(Code.GOAL_UNREACHABLE, str(e)) from None
        # the scans' batches run on numba's threads: the cores other work leaves (as a repair's swept edges)
        cap = plan_capture(self.sc, self.start, goal, base_path=guide, check=self.check_cancel,
                           fit_threads=lambda: self.p._fit_threads(0, any_size=True, note=False))
        self.timings["descent"] += cap.search_s
        self.timings["verify"] += cap.verify_s
        self.stats.update(free_floating_candidates=cap.candidates, free_floating_checked=cap.checked)
        if not cap.ok:
            # no capture posture at all (the grasp out of the arm's reach, wherever the body drifts): the
            # target's goal, as on a held spacecraft; else what the drift does to the capture
            raise Fail(Code.GOAL_UNREACHABLE if not cap.needed_deg else Code.REACTION_REFUSED, cap.reason)
        self.goal = cap.goal_rad
        self.approach_error_deg = cap.approach_error_deg
        self.say(f"free-floating capture: attitude change {cap.response.attitude_change_deg:.2f}°, body "
                 f"displacement {cap.response.body_displacement_m:.3f} m, tip miss {cap.tip_miss_m:.2e} m, "
                 f"approach error {cap.approach_error_deg:.2e}°; {cap.candidates} candidate paths, "
                 f"{cap.checked} certified in the inertial frame (clearance {cap.drift.min_clearance_m:.3f} m)")
        self.say(f"free-floating capture: the {cap.family} family's path")
        path = align_to_state(cap.path_rad, self.start_given, self.periodic)
        length = float(np.sum(np.linalg.norm(np.diff(path, axis=0), axis=1)))
        return SmoothPath(path, path[[0, -1]], "free_floating_capture", cap.drift.min_clearance_m, length, 0,
                          cap.drift.n_checked)

    def field_guide(self, posture):
        """
        Return the harmonic field's path to a free-floating capture posture's arm joints, or None.

        Planned in the scene as the body sees it at the end of the motion (turned by the
        posture's attitude change about the body centre, after the body moved:
        ``free_floating_capture.apparent_scene``), where the posture grasps the handle; the planner's
        planners of those scenes are cached (``Planner.apparent_planner``).  Its stage times
        add to this run's.
        """
        sub = self.p.apparent_planner(apparent_scene(self.sc.scene, posture.attitude_change_rad, posture.body_m))
        res = sub.plan(self.start, posture.q_full[list(self.robot.planned_joints)], cancel=self.cancel)
        for k in ("cspace", "field", "descent", "repair", "smoothing", "verify"):
            self.timings[k] += res.timings_s.get(k, 0.0)
        if res.code == Code.CANCELLED:
            raise Cancelled()
        return res.path_rad if res.ok else None

    def leave_contact(self) -> None:
        """
        Handle a start within the margin of an obstacle.

        Walk out (``contact.leave_contact``) when its links reach at most
        ``max_start_penetration_m`` into it, else start_in_collision.
        """
        margin = self.sc.scene.safety_margin_m
        clr_s = self.start_clearance_m          # check_inputs' (the same start)
        if clr_s > margin:
            return
        refusal = (f"the start {deg_text(self.start)} is in collision: clearance {clr_s:.3f} m, the "
                   f"safety margin is {margin} m")
        names = what_is_hit(self.robot, self.sc.scene, self.start)
        hit = " and ".join(names) or "an obstacle"
        with self.stage("exit"):
            ex = leave_contact(self.validator, self.start, max_penetration_m=self.s.max_start_penetration_m, hit=hit)
        self.penetration_m = ex.start_penetration_m
        if not ex.ok:
            movable = [h for h in names if h != "the spacecraft body"]
            hint = (f"move {' and '.join(movable).replace('the target body', 'the target')} away from the arm, or "
                    "plan from another start" if movable else "plan from another start")
            raise Fail(Code.START_IN_COLLISION, f"{refusal}; no way out: {ex.reason} ({hint})")
        self.exit_path = ex.path_rad
        self.plan_start = self.robot.validate_q(ex.path_rad[-1], "exit")
        self.say(f"exit: the start touches {hit} ({ex.start_penetration_m:.3f} m deep); "
                 f"{len(ex.path_rad) - 1} steps out to {deg_text(ex.path_rad[-1])}, clearance "
                 f"{ex.signed_distance_m[-1]:.3f} m (not certified)")

    def find_grid_path(self) -> np.ndarray:
        """
        Return the waypoints of a verified grid path (:meth:`descend_and_repair`), refined if need be.

        The scenario's grid first, with the extra grid margin and then without.  Where that
        grid does not join start and goal (``disconnected``), leaves no verified grid path
        (``path_invalid``), or its repairs pile up (``refine_after_repairs``), a finer grid
        at the safety margin (:func:`refined`: twice the cells per joint, or as many more as
        ``max_grid_nodes`` and ``max_refined_nodes`` allow, at least ``MIN_REFINEMENT``
        times), up to ``max_refinements`` times (:meth:`refinement_refused`).  The answer
        after the last grid says which grids were tried and why no finer one was.
        """
        grid, level, tried = self.sc.grid, 0, []
        while True:
            self.level = level
            failure = None
            for k, extra_m in enumerate(self.grid_margins(level)):
                try:
                    cs, cs_key = self.cspace(grid, extra_m)
                    goal_nodes = self.goal_nodes(cs, cs_key)
                    if level or k:             # a grid tried after one that failed
                        self.check_joined(cs, cs_key, goal_nodes)
                    field, field_key = self.field(cs, cs_key, goal_nodes)
                    return self.descend_and_repair(cs, field, field_key, goal_nodes)
                except Fail as f:
                    if f.code not in (Code.DISCONNECTED, Code.PATH_INVALID):
                        raise
                    failure = f
                    self.say(f"{f.code} on the grid {grid.label()} (grid margin "
                             f"{self.sc.scene.safety_margin_m + extra_m:.3f} m): {f.reason}")
                    if isinstance(f, Refine):
                        break
            tried.append((grid.label(), failure))
            stop = self.refinement_refused(grid)
            if stop:
                raise self.unresolved(tried, stop)
            grid, level = self.finer(grid), level + 1
            self.say(f"refining the grid to {grid.label()}")

    def grid_margins(self, level: int = 0) -> tuple:
        """Return the grid's extra margins to try on a grid of refinement ``level`` (:func:`grid_margins`)."""
        return grid_margins(self.s, level)

    def refinement_refused(self, grid) -> str:
        """
        Return '' when a grid finer than ``grid`` may be tried (:meth:`finer`), else why not.

        Refused beyond ``max_refinements``, and where not even ``MIN_REFINEMENT`` times the
        cells per joint is within ``max_grid_nodes`` and ``max_refined_nodes``: counts, not
        the clock, so the same input gives the same answer (each field solve has the budget
        ``field_budget_s`` of one solve, as on the first grid).
        """
        s = self.s
        if self.level >= s.max_refinements:
            return f"no finer grid tried (planner.max_refinements = {s.max_refinements})"
        if self.finer(grid) is not None:
            return ""
        doubled, least = refined(grid), scaled_grid(grid, MIN_REFINEMENT)
        name, limit = min((("planner.max_grid_nodes", s.max_grid_nodes),
                           ("max_refined_nodes", s.max_refined_nodes)), key=lambda nl: nl[1])
        return (f"{doubled.label()} not tried: {doubled.n_nodes:,} nodes, above {name} = {limit:,}, "
                f"as is {least.label()} ({MIN_REFINEMENT:g} times the cells per joint, {least.n_nodes:,} nodes)")

    def finer(self, grid):
        """Return the refined grid to try after ``grid`` within the node limits (:func:`refined`), or None."""
        return refined(grid, min(self.s.max_grid_nodes, self.s.max_refined_nodes))

    def start_text(self) -> str:
        """Return the plan's start for a reason: after a way out of contact, where it ends and where it began."""
        if self.plan_start is self.start:
            return f"the start {deg_text(self.start)}"
        return (f"the start {deg_text(self.plan_start)} (where the way out of contact from "
                f"{deg_text(self.start)} ends)")

    def unresolved(self, tried, stop: str) -> Fail:
        """Return the answer when no grid tried gave a path: the finest grid's code, and what was tried."""
        last = tried[-1][1]
        grids = " and ".join(label for label, _ in tried)
        what = "; ".join(f"{label}: {f.brief}" for label, f in tried)
        if self.fld is not None and not self.fld.converged:
            stop += (f"; the last field did not converge within planner.field_budget_s = "
                     f"{self.s.field_budget_s:g} s")
        ends = f"{self.start_text()} and the goal {deg_text(self.goal)}"
        if last.code == Code.DISCONNECTED:
            step = deg_text(self.cs.grid.step_rad).replace("(", "").replace(")°", "")
            return Fail(last.code, f"{ends} are not joined on the grids {grids} ({what}); {stop}; a passage "
                        f"narrower than a grid step ({step}°) can be missed", last.brief)
        return Fail(last.code, f"no verified path joins {ends} on the grids {grids} ({what}); {stop}", last.brief)

    def cspace(self, grid, extra_m: float):
        """Return (C-space, its cache key) of the current scene on ``grid`` with the extra margin ``extra_m``."""
        self.cached = []
        before = self.timings["cspace"]
        with self.stage("cspace"):
            cs, key, hit = self.p._cspace(grid, extra_m, token=self.cancel, cached_only=self.cached_only)
        if hit:
            self.timings["cspace"] = before           # a cached stage costs nothing
            self.cached.append("cspace")
        self.cs = cs
        if self.progress is not None:             # the free fraction is a pass over the grid
            ms = "cached" if hit else f"{1e3 * (self.timings['cspace'] - before):.1f} ms"
            self.say(f"cspace {grid.label()} (grid margin {cs.margin_m:.3f} m): {ms}, "
                     f"{100 * cs.free_fraction:.1f} % free")
        self.check_cancel()
        return cs, key

    def goal_nodes(self, cs, cs_key) -> np.ndarray:
        """
        Free grid nodes near the goal joined to it by a certified segment (≤ 4), cached.

        The ``NEAR_NODES`` nearest free nodes first (offsets -1 .. 2 of the goal's cell per axis),
        the first 4 that pass; where none does, the window's other free nodes, nearest first (a goal
        close to the target on a coarse grid: 22.5° steps on the 4-joint servicer's, where
        every one of the 8 nearest was cut off and the answer was path_invalid).
        """
        key = (cs_key, self.goal.tobytes(), self.s.verify_step_rad)
        nodes = self.p._goal_nodes.get(key)
        if nodes is None:
            nodes = []
            near = self.candidates(self.goal, cs.grid, cs.occupied, max_count=4 ** cs.grid.ndim)
            for k, n in enumerate(near):          # nearest first, the first 4 that pass
                if k == NEAR_NODES and nodes:
                    break
                if self.segment_ok(cs.grid.config_of(n), self.goal):
                    nodes.append(n)
                    if len(nodes) == 4:
                        break
            self.p._remember(self.p._goal_nodes, key, nodes, 16)
        if not nodes:
            raise Fail(Code.PATH_INVALID, f"no free grid node near the goal {deg_text(self.goal)} can be "
                       f"joined to it by a collision-free straight segment (grid {cs.grid.label()})",
                       "no free grid node near the goal is joined to it by a collision-free segment")
        return np.array(nodes)

    def check_joined(self, cs, cs_key, goal_nodes) -> None:
        """
        Raise, without a field solve, the answer a solve would lead to when the grid separates start and goal nodes.

        Where no free grid node near the start is joined to the goal nodes by the grid's free
        nodes (a breadth-first search, a millisecond), the field would have no value at those
        nodes and :meth:`descend_and_repair` would answer ``no_field_path_failure``: that
        answer, the same code and reason, without the solve.  Run on the grids tried after
        one that failed (the second margin, a refined grid), where a separation is likely
        and a field solve costs tens of milliseconds; not when the field is cached.
        """
        if self.cached_only or self.p._field_key(cs_key, goal_nodes, self.s) in self.p._fields:
            return                  # (from the caches alone: :meth:`field` says whether it is held)
        grid = cs.grid
        self.stats = {"repairs": 0, "blocked_nodes": 0, "cut_edges": 0,
                      "grid_extra_margin_m": float(cs.margin_m - self.sc.scene.safety_margin_m),
                      "grid": grid.label(), "refinements": self.level}
        with self.stage("descent"):
            starts = self.candidates(self.plan_start, grid, cs.occupied)
            if len(starts) == 0:
                return                   # descend_and_repair says so, after the solve
            joined = bool(np.any(bfs_distance(cs.occupied, grid.periodic, goal_nodes)[tuple(starts.T)] >= 0))
        if not joined:
            self.fld = None
            raise self.no_field_path_failure(cs, None, frozenset(), frozenset(), 0)

    def field(self, cs, cs_key, goal_nodes):
        """(field, its key) on the C-space's free nodes towards the goal nodes, cached."""
        self.check_cancel()
        key = self.p._field_key(cs_key, goal_nodes, self.s)
        hit = key in self.p._fields
        if not hit and self.cached_only:
            raise NotCached("field")
        before = self.timings["field"]
        with self.stage("field"):
            fld = self.p._solve(cs, key, goal_nodes, self.s, token=self.cancel)
        spent = self.timings["field"] - before
        if hit:
            self.timings["field"] = before
            self.cached.append("field")
            if self.progress is not None:
                self.say(f"field: cached ({fld.solver})")
        elif self.progress is not None:
            self.say(f"field ({fld.solver}): {1e3 * spent:.1f} ms, {fld.sweeps} "
                     f"{'sweeps' if fld.solver == 'gauss_seidel' else 'iterations'}, residual "
                     f"{fld.residual:.2e}" + ("" if fld.converged else f"; NOT converged: {fld.left}"))
        self.fld = fld
        return fld, key

    def descend_and_repair(self, cs, fld, key, goal_nodes) -> np.ndarray:
        """
        Descent from a start node.

        Where a walk is blocked or its polyline does not verify, cut grid edges or block nodes (a
        plan-local field, cached under its own key) and descend again: up to ``max_repairs``
        times, or ``refine_after_repairs`` times when a finer grid may follow (then
        :class:`Refine`).

        Returns the unwrapped waypoints: exact start, grid nodes, exact goal.
        """
        grid, s = cs.grid, self.s
        blocked, cut = frozenset(), CutEdges()
        base = fld                       # every repaired field starts its iterations from this one
        repairs = 0
        start_ok = {}                    # grid node -> whether the straight segment from the start passes
        start = self.plan_start
        with self.stage("descent"):
            self.p._test_stall("descent", self.cancel)
        for attempt in range(s.max_repairs + 1):
            self.check_cancel()
            self.fld = fld
            self.stats = {"sweeps": int(fld.sweeps), "residual": float(fld.residual),
                          "converged": bool(fld.converged), "left": fld.left, **fld.stats,
                          "repairs": repairs, "blocked_nodes": len(blocked), "cut_edges": len(cut),
                          "grid_extra_margin_m": float(cs.margin_m - self.sc.scene.safety_margin_m),
                          "grid": grid.label(), "refinements": self.level}
            with self.stage("descent"):
                starts = self.candidates(start, grid, fld.occupied)
            if len(starts) == 0:
                raise Fail(Code.PATH_INVALID, f"every grid node near {self.start_text()} is "
                           f"blocked (grid {grid.label()}, margin {cs.margin_m:.3f} m)",
                           "every grid node near the start is blocked")
            reach = np.isfinite(fld.log_u[tuple(starts.T)])       # fld.reachable at these nodes
            if not reach.any():
                raise self.no_field_path_failure(cs, fld, blocked, cut, repairs)
            path, stuck, reasons, collide = None, None, [], []
            joins = WalkJoins(fld)           # this field's walks: a later start's walk joins an earlier one
            for node in starts[reach]:
                self.check_cancel()
                tn = tuple(int(v) for v in node)
                if tn not in start_ok:                   # the same start and node each repair round
                    # kept: the grid path's first interval
                    start_ok[tn] = self.segment_ok(start, grid.config_of(node), keep=True)
                if not start_ok[tn]:
                    collide.append(deg_text(grid.config_of(node)))
                    continue
                with self.stage("descent"):
                    gp = self.descend(grid, fld, key, blocked, cut, node, joins)
                if gp.reached:
                    path = gp
                    break
                if gp.blocked and stuck is None:
                    stuck = gp
                reasons.append(gp.reason)
            if path is None and stuck is not None and attempt < s.max_repairs:
                self.may_repair(grid, repairs, cut, blocked)
                # every way up from that node collides
                node = tuple(int(v) for v in stuck.nodes[-1])
                blocked, cut, done = self.cut_or_block(grid, fld, key, blocked, cut, node, repairs, base)
                self.say(f"repair: {stuck.reason}; {done} and re-solving the field")
                repairs += 1
                fld = self.resolve(cs, key, goal_nodes, blocked, cut, base)
                continue
            if path is None:
                if collide:
                    reasons.insert(0, f"the straight segment from the start to each of the grid nodes "
                                   f"{', '.join(collide[:3])} collides")
                limit = _repair_limit(s.max_repairs) if stuck is not None else ""   # a repair could go on
                raise Fail(Code.PATH_INVALID, f"no grid path from {self.start_text()} on the grid "
                           f"{grid.label()}{limit}: " + "; ".join(reasons[:3]),
                           (f"after {_count(repairs, 'repair')}, " if repairs else "") + "no grid path from the start"
                           + (": every straight segment to a nearby free node collides" if not stuck else "")
                           + limit)
            nodes_rad = grid.config_of(path.nodes)
            self.grid_path = nodes_rad
            wp = unwrap_path(np.vstack([start, nodes_rad, self.goal]), self.periodic)
            wp[-1] = nearest_turn_rad(self.goal, wp[-1], self.periodic)   # exactly the goal (mod 2π)
            with self.stage("verify"):
                chk = self.validator.check_kept(wp)     # the intervals a plan before checked: reused
            if chk.ok:
                self.waypoint_check = chk            # the smoothing's shortcut pass reuses it
                return wp
            bad = int(np.flatnonzero(~chk.interval_ok)[0])
            # segment bad joins waypoint bad and bad+1; waypoint k ≥ 1 is path node k-1
            cand = [k - 1 for k in (bad, bad + 1) if 1 <= k <= len(path.nodes)]
            goal_set = {tuple(g) for g in goal_nodes}
            cand = [c for c in cand if tuple(path.nodes[c]) not in goal_set]
            if not cand or attempt == s.max_repairs:
                limit = _repair_limit(s.max_repairs) if cand else ""
                raise Fail(Code.PATH_INVALID, f"the straight segment between grid nodes "
                           f"{deg_text(wp[bad])} and {deg_text(wp[bad + 1])} collides and the grid "
                           f"path could not be repaired ({_count(repairs, 'repair')}, grid {grid.label()}){limit}",
                           f"{_count(repairs, 'repair')}, a grid path whose straight segments collide{limit}")
            self.may_repair(grid, repairs, cut, blocked)
            clr = [self.checker.clearance_m(nodes_rad[c]) for c in cand]
            node = tuple(int(v) for v in path.nodes[cand[int(np.argmin(clr))]])
            blocked, cut, done = self.cut_or_block(grid, fld, key, blocked, cut, node, repairs, base)
            repairs += 1
            self.say(f"repair: segment {deg_text(wp[bad])} → {deg_text(wp[bad + 1])} collides; "
                     f"{done} and re-solving the field")
            fld = self.resolve(cs, key, goal_nodes, blocked, cut, base)
        raise AssertionError("unreachable")

    def descend(self, grid, fld, key, blocked, cut, node, joins=None):
        """
        Return the descent from ``node`` on the field under ``key`` less ``blocked`` and ``cut`` (``descent.GridPath``).

        ``joins``: the walks on ``fld`` so far (``descent.WalkJoins``): a walk that stands on a node one
        of them stood on takes the rest of its path (the same path, sooner).

        A walk (a pure function of the field and the node) is kept by the planner, keyed by that
        field and the node: one that does not reach the goal in ``Planner._failed_walks`` (the
        next plan that repairs the same way, a replan from a nearby start, tries the same nodes
        on the same fields first), one that reaches it in ``Planner._walks`` (a replan from a
        start near the same grid node descends no more).
        """
        dkey = (key, tuple(sorted(blocked)), cut, tuple(int(v) for v in node))
        gp = self.p._walks.get(dkey)
        if gp is None:
            gp = self.p._failed_walks.get(dkey)
        if gp is None:
            gp = self.p._descend(fld, node, self.motions, grid.lower_rad, grid.step_rad, joins=joins)
            gp.nodes.flags.writeable = False
            self.p._remember(self.p._walks if gp.reached else self.p._failed_walks, dkey, gp, 256)
        return gp

    def cut_or_block(self, grid, fld, key, blocked, cut, node, repairs: int, base) -> tuple:
        """
        Return ``(blocked, cut, what was done)`` after one repair at grid node ``node``.

        The colliding grid edges around it and their sheet are cut (:meth:`colliding_edges`,
        within ``REPAIR_RADIUS`` steps, one more per repair before, up to ``REPAIR_WIDENING``; the
        sheet followed for twice as many tested edges per repair before, ``REPAIR_DOUBLINGS``);
        where they are all cut already, the node itself is blocked.  A plan's first repair on a
        grid cuts every colliding edge along the axes but the last (:meth:`swept_edges`: the
        obstacles thinner than a grid step are then cut everywhere at once, not one sheet per
        repair and field solve) and those within ``REPAIR_RADIUS`` steps of the node (its box
        only: the sheet's tests along the last axis wait for a second repair).  The one rule of both
        repairs: a descent that every way on collides, and a grid path whose straight segment
        does (an obstacle thinner than a grid step, e.g. a small piece of debris, is a sheet
        of such edges that no node marks: blocking one node per repair did not get past it).
        ``fld``: the field the descent was blocked on; ``base``: the field before the plan's
        repairs, under ``key``.
        """
        if self.cached_only:
            raise NotCached("repair")
        everywhere = repairs == 0 and swept.applies(self.motions, grid.ndim)
        with self.stage("repair"):
            if everywhere:
                # every colliding edge along the axes but the last, and the box around the node
                edges = np.vstack([self.swept_edges(grid, base, key),
                                   self.colliding_edges(grid, fld, key, blocked, node, REPAIR_RADIUS, 0)])
            else:
                edges = self.colliding_edges(grid, fld, key, blocked, node,
                                             REPAIR_RADIUS + min(repairs, REPAIR_WIDENING),
                                             MAX_TESTS << min(repairs, REPAIR_DOUBLINGS))
        grown, new = cut.with_edges(edges)
        if new:
            where = "off the last axis and around" if everywhere else "around"
            return blocked, grown, f"cutting {new} colliding grid edge(s) {where} node {node}"
        return blocked | {node}, cut, f"blocking node {node}"

    def swept_edges(self, grid, base, key) -> np.ndarray:
        """
        Return every colliding grid edge along the axes but the last (``swept.swept_edges``), cached.

        Between the free nodes of ``base``, the field under ``key`` (before any repair: its
        C-space's free nodes); a pure function of the key, kept by the planner with the sheet
        searches' edges.  (k, 2) int64, read-only.
        """
        ekey = (key, "swept")
        edges = self.p._colliding.get(ekey)
        if edges is None:
            self.p._fit_threads(base.occupied.size, any_size=True, note=False)   # the cores other work leaves
            edges = swept.swept_edges(base.occupied, grid.periodic, grid.lower_rad, grid.step_rad, self.motions,
                                      token=self.cancel)
            edges.flags.writeable = False
            self.p._remember(self.p._colliding, ekey, edges, 64)
        return edges

    def colliding_edges(self, grid, fld, key, blocked, node, radius: int, max_tests: int = MAX_TESTS) -> np.ndarray:
        """
        Return the colliding grid edges within ``radius`` of ``node`` and their sheet (``repair.sheet_edges``), cached.

        On the field under ``key`` with the ``blocked`` nodes (its occupancy; cut edges do not
        change it): a pure function of those, the node, the radius and the sheet's budget of
        tested edges (``max_tests``), so kept by the planner (``Planner._colliding``) for the
        next plan that repairs the same way (a replan from a nearby start walks into the same
        blocked node).  (k, 2) int64, read-only.
        """
        ekey = (key, tuple(sorted(blocked)), node, int(radius), int(max_tests))
        edges = self.p._colliding.get(ekey)
        if edges is None:
            edges = sheet_edges(fld.occupied, grid.periodic, node, self.motions, grid.lower_rad,
                                grid.step_rad, radius=radius, max_tests=max_tests)
            edges.flags.writeable = False
            self.p._remember(self.p._colliding, ekey, edges, 64)
        return edges

    def may_repair(self, grid, repairs: int, cut, blocked) -> None:
        """Raise :class:`Refine` instead of a further repair: ``refine_after_repairs`` done, a finer grid next."""
        if repairs >= self.s.refine_after_repairs and not self.refinement_refused(grid):
            done = _repairs_text(repairs, cut, blocked)
            raise Refine(Code.PATH_INVALID, f"{done} on the grid {grid.label()} gave no verified grid path; "
                         "a finer grid is tried instead of more repairs", f"{done}, then a finer grid")

    def resolve(self, cs, key, goal_nodes, blocked, cut, base):
        """
        Return the field with ``blocked`` nodes and ``cut`` edges taken out (cached by them).

        Solved from the field under ``key`` (``base``, before any repair) as its guess: a function
        of the key, the nodes and the edges alone, whichever repairs came before.
        """
        rkey = self.p.repaired_field_key(key, blocked, cut)
        hit = rkey in self.p._fields
        with self.stage("repair"):
            fld = self.p._solve(cs, rkey, goal_nodes, self.s, blocked, cut, token=self.cancel, guess=base)
        if not hit and "field" in self.cached:
            self.cached.remove("field")
        return fld

    def no_field_path_failure(self, cs, fld, blocked, cut, repairs: int) -> Fail:
        """
        Why no start node has a field value.

        'disconnected' only when the grid's own free space (without the repairs' blocked
        nodes and cut edges) separates every free node near the start from every free node
        near the goal; otherwise what separated them: the repairs, the goal's joins, or (the
        paper's solver only) a field flat in float64.
        """
        grid, occ = cs.grid, cs.occupied
        start = self.plan_start
        goal_nodes = self.candidates(self.goal, grid, occ)
        start_nodes = self.candidates(start, grid, occ)
        where = f"the grid {grid.label()}, grid margin {cs.margin_m:.3f} m"
        if len(start_nodes) == 0:
            return Fail(Code.PATH_INVALID, f"every grid node near {self.start_text()} is an "
                        f"obstacle on {where}", "every grid node near the start is an obstacle")
        dist = bfs_distance(occ, grid.periodic, goal_nodes)
        if np.all(dist[tuple(start_nodes.T)] < 0):
            return Fail(Code.DISCONNECTED, f"{self.start_text()} and the goal {deg_text(self.goal)} "
                        f"lie in separate free regions of {where}",
                        f"separate free regions (grid margin {cs.margin_m:.3f} m)")
        if fld is None:                  # check_joined: no field, no repairs; its goal nodes separated
            return self.unjoined_failure(where)
        # the grid joins them: does the field's own graph (repairs, goal joins) join them?
        f_occ, per, f_goals = validate_problem(fld.occupied, grid.periodic, fld.goal_nodes)
        f_dist = field_bfs(f_occ, per, f_goals, cut.array)[0]
        f_starts = self.candidates(start, grid, fld.occupied)
        joined = len(f_starts) and np.any(f_dist.reshape(occ.shape)[tuple(f_starts.T)] >= 0)
        if joined and fld.solver == "gauss_seidel":
            return Fail(Code.PATH_INVALID, f"the field of solver 'gauss_seidel' is zero (flat in float64) at "
                        f"the start although {where} joins start and goal; the log_harmonic solver has no "
                        "flat field", "the gauss_seidel field is flat (zero in float64) at the start")
        if joined:
            return Fail(Code.PATH_INVALID, f"the field of solver '{fld.solver}' has no value at the start's "
                        f"grid nodes although its graph joins them to the goal ({where})",
                        "no field value at the start")
        if repairs:
            done = _repairs_text(repairs, cut, blocked)
            return Fail(Code.PATH_INVALID, f"{where} joins start and goal, but {done} whose straight motions "
                        "collide separated them", f"joined, but {done} separated them")
        return self.unjoined_failure(where)

    def unjoined_failure(self, where: str) -> Fail:
        """Return the answer when the grid joins start and goal but not to a goal node joined to the goal."""
        return Fail(Code.PATH_INVALID, f"on {where} the start's free region reaches only grid nodes near the "
                    f"goal {deg_text(self.goal)} whose straight segment to it collides",
                    "the start's free region holds no grid node joined to the goal by a collision-free "
                    "segment")

    def smooth(self, waypoints) -> object:
        """Spline through the waypoints, certified on the exact geometry (``smoothing``)."""
        self.check_cancel()
        s = self.s
        with self.stage("smoothing"):
            self.p._test_stall("smoothing", self.cancel)
            # a start tangent is the arm's direction at the start: not that of an exit stretch's end
            sm = smooth_path(self.validator, waypoints, shortcut=s.shortcut,
                             keep_clearance_m=s.shortcut_keep_clearance_m, max_step_rad=s.max_step_rad,
                             cancel=self.cancel, waypoint_check=self.waypoint_check,
                             start_tangent=self.start_tangent if len(self.exit_path) == 0 else None)
        self.check_cancel()
        if sm is None:
            raise Fail(Code.PATH_INVALID, "no smoothed path passed the dense collision check")
        if self.progress is not None:
            self.say(f"smoothing ({sm.method}, {sm.refinements} refinements): "
                     f"{1e3 * self.timings['smoothing']:.1f} ms; {len(sm.path_rad)} samples, length "
                     f"{sm.length_rad:.3f} rad, min clearance {sm.min_clearance_m:.4f} m")
        return sm

    def full_path(self, smooth) -> np.ndarray:
        """Return the exit stretch (if any) followed by the certified path, continuous."""
        if len(self.exit_path) == 0:
            return smooth.path_rad
        rest = align_to_state(smooth.path_rad, self.exit_path[-1], self.periodic)
        return np.vstack([self.exit_path[:-1], rest])

    def time_parameterize(self, smooth) -> PlanResult:
        """Return the ok result, with the trajectory (and reaction) when the limits are known."""
        path = self.full_path(smooth)
        traj = reaction = None
        if self.s.trajectory and trajectory_limits_known(self.sc):
            self.check_cancel()
            try:
                with self.stage("trajectory"):
                    traj, reaction = timed_motion(self.sc, path, self.start_given, self.s.reaction,
                                                  motions=self.validator)
            except ValueError as e:
                raise Fail(Code.INVALID_INPUT, str(e)) from None
            if self.progress is not None:
                self.say(f"trajectory (time-optimal): {traj.duration_s:.2f} s, {len(traj)} points "
                         f"({1e3 * self.timings['trajectory']:.1f} ms)")
            if reaction is not None and not reaction.ok:
                return self.result(Code.REACTION_REFUSED, reaction.reason, smooth=smooth, path=path,
                                   trajectory=traj, reaction=reaction)
        res = self.result(Code.OK, None, smooth=smooth, path=path, trajectory=traj, reaction=reaction)
        if self.progress is not None:
            self.say(f"total {1e3 * res.timings_s['total']:.1f} ms")
        return res

    def run(self, start_rad, goal_rad) -> PlanResult:
        """:func:`run_pipeline`, with its failures turned into results (never raises)."""
        try:
            return run_pipeline(self, start_rad, goal_rad)
        except Cancelled:
            self.say("cancelled")
            return self.result(Code.CANCELLED, "planning was cancelled")
        except NotCached:
            raise
        except Fail as f:
            self.say(f"failed ({f.code}): {f.reason}")
            return self.result(f.code, f.reason)
        except Exception as e:     # the contract: plan() never raises; say what broke
            reason = f"internal error while planning: {type(e).__name__}: {e}"
            self.say(reason)
            return self.result(Code.INTERNAL_ERROR, reason, tb=_traceback.format_exc())
