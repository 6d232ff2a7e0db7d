"""
The offline planner: scene → C-space → field → descent → certified smooth path → trajectory.

``Planner.plan`` runs ``pipeline.run_pipeline`` (the stages in order, one module each)
with the planner's :class:`PlannerSettings` (immutable; the setters replace it) and
caches what does not depend on the start:

- the C-space on (scene geometry + margin, grid, extra grid margin);
- the field on (C-space, goal nodes, solver settings) and, for repaired fields, the cut
  grid edges and blocked nodes as well.

A plan only *adds* cache entries, never changes one: the same start, goal and scene give
the same path bit for bit whatever the planner planned before.  A second plan with only
a new start reuses both and costs milliseconds.

Exact ends: the start and the goal are joined to nearby free grid nodes by straight
segments certified on the exact geometry.  Grid paths: the grid is built with a small
extra margin (``grid_extra_margin_m``) so grid paths keep away from obstacles; the
certification uses the scene's true margin.  When that grid separates start and goal
(or leaves no grid path), the planner tries again without the extra margin, then on a grid
with twice the cells per joint, or as many more as ``max_grid_nodes`` and
``max_refined_nodes`` allow (``max_refinements``; docs/field.md, "the refinement rule"),
before it answers.  When the
straight segment between two nodes of the descent collides, the colliding grid edges are
cut (or the node blocked) and the field re-solved ("repair").

The core never imports rclpy.
"""

from __future__ import annotations

import math
import threading
import time
from dataclasses import fields, replace
from typing import Callable

import numpy as np

from .collision import CollisionChecker
from .contact import warm_up as contact_warm_up
from .cores import fit_threads
from .cspace import GridSpec, body_occupancy, build_cspace, loops_at_any_size
from .cspace import warm_up as cspace_warm_up
from .descent import descend
from .field import solve_field
from .field import reserve_heap, warm_up as field_warm_up
from .free_floating_capture import warm_up as free_floating_warm_up
from .ik import approach_error_rad, grasp_ik, meets_approach_angle, perpendicular_attitudes
from .motion import MotionValidator
from .pipeline import NotCached, PlanRun
from .problem import Scenario
from .repair import CutEdges
from .repair import warm_up as repair_warm_up
from .results import CODES, STAGES, Code, PlanResult
from .scene import Scene
from .settings import PlannerSettings
from .smoothing import warm_up as smoothing_warm_up
from .swept import warm_up as swept_warm_up
from .termination import stall
from .timing import timed_motion, trajectory_limits_known

__all__ = ["PlanResult", "Planner", "PlannerSettings", "Code", "STAGES", "CODES", "warm_up", "warm_up_unreached",
           "timed_motion", "GRASP_ROOM_M"]

#: a capture posture must clear the safety margin by more than this, m: one that sits on it
#: (a margin equal to the handle's length; its clearance only rounds above) leaves no motion
#: that reaches it, and is refused as such rather than planned on grid after grid
GRASP_ROOM_M = 1e-9
#: the item after a solve's key that makes it a repaired field's key (:meth:`Planner.repaired_field_key`)
REPAIRED = "repaired"
#: a field's cut grid edges before any repair (``Planner._solve``)
_NO_CUTS = CutEdges()


class Planner:
    """
    Harmonic-potential planner with cached C-space and fields.

    Caches: C-space keyed on (scene geometry + margin, grid, extra margin); field keyed
    on (that C-space key, goal nodes, solver settings[, blocked nodes, cut edges]),
    evicted with its C-space; the spacecraft-body table keyed on (grid, margin), kept
    across target moves.  Entries are never modified after they are stored.

    Parameters
    ----------
        scenario: robot, scene and grid (``problem.Scenario``).
        solver, field_tolerance, max_grid_nodes, field_budget_s, and any other
            :class:`PlannerSettings` field as a keyword, over ``settings`` (default: the
            scenario's, ``Scenario.planner_settings``).

    """

    def __init__(self, scenario: Scenario, solver: str | None = None, field_tolerance: float | None = None,
                 max_grid_nodes: int | None = None, *, settings: PlannerSettings | None = None, **options):
        base = settings if settings is not None else scenario.planner_settings
        given = {"solver": solver, "field_tolerance": field_tolerance, "max_grid_nodes": max_grid_nodes}
        changes = {k: v for k, v in given.items() if v is not None}
        unknown = set(options) - {f.name for f in fields(PlannerSettings)}
        if unknown:
            raise TypeError(f"Planner: unknown option(s) {sorted(unknown)}")
        changes.update(options)
        self.settings = replace(base, **changes)
        self.scenario = scenario
        self._lock = threading.Lock()
        self._fits = []                 # the current plan's thread choices (cores.Fit)
        self._cspaces: dict = {}         # (scene geometry, grid, extra margin) -> CSpace
        self._fields: dict = {}          # (C-space key, goal nodes, solver settings[, repairs]) -> Field
        self._body_tables: dict = {}     # (grid, total margin) -> cspace.body_occupancy
        self._goal_nodes: dict = {}      # (C-space key, goal, verify step) -> free nodes joined to the goal
        self._colliding: dict = {}       # (field key, blocked nodes, node, radius) -> a repair's colliding edges
        self._failed_walks: dict = {}    # (field key, blocked nodes, cut edges, node) -> a descent that failed
        self._walks: dict = {}           # (field key, blocked nodes, cut edges, node) -> a descent that reached
        self._apparent: dict = {}        # scene geometry -> Planner (free-floating capture's guides)
        self._checker = CollisionChecker(scenario.robot, scenario.scene)
        self._validator = MotionValidator(self._checker)    # the scene's motion validator
        self._last_goal = None           # (scenario, checker, goal bytes, its clearance, approach error)
        self._capture = None             # (scenario, approach bound, IKSolution or the ValueError's text)
        #: test aid: (stage, seconds, polls, on_start) -- that stage ("cspace", "field":
        #: before its kernels, when not cached; "descent", "smoothing") calls
        #: ``on_start(stage)`` (or None) and spends ``seconds``, answering the termination
        #: token when ``polls`` (``termination.stall``)
        self.test_stall: tuple | None = None

    # --------------------------------------------------------------- settings
    def configure(self, **changes) -> PlannerSettings:
        """Replace the settings by a copy with ``changes`` (validated); returns the new ones."""
        new = replace(self.settings, **changes)
        with self._lock:
            self.settings = new
        return new

    # read-only views of the settings (the node reads them); max_grid_nodes may be assigned
    solver = property(lambda self: self.settings.solver)
    field_tolerance = property(lambda self: self.settings.field_tolerance)
    field_budget_s = property(lambda self: self.settings.field_budget_s)
    grid_extra_margin_m = property(lambda self: self.settings.grid_extra_margin_m)
    max_grid_nodes = property(lambda self: self.settings.max_grid_nodes,
                              lambda self, value: self.configure(max_grid_nodes=value),
                              doc="Refuse larger grids; assigning it replaces the settings.")

    def set_solver(self, solver: str, field_tolerance: float, field_budget_s: float | None = None) -> None:
        """
        Choose the field solver; ValueError for unknown names, a bad tolerance or budget.

        ``field_budget_s`` None keeps the current budget.
        """
        changes = {"solver": solver, "field_tolerance": field_tolerance}
        if field_budget_s is not None:
            changes["field_budget_s"] = field_budget_s
        self.configure(**changes)

    def set_settings(self, settings: PlannerSettings, acs, masses, joint_limits) -> None:
        """
        Take a scenario's settings: its ``planner_settings``, ``acs``, ``masses`` and ``joint_limits``.

        What the planner was made with beyond the scenario's settings (``trajectory``,
        ``reaction``) stays; the cached C-spaces and fields stay (their keys hold what they
        depend on), the free-floating capture's planners go (made with the old settings).
        """
        new = replace(settings, trajectory=self.settings.trajectory, reaction=self.settings.reaction)
        with self._lock:
            self.scenario = replace(self.scenario, planner_settings=settings, acs=acs, masses=masses,
                                    joint_limits=joint_limits)
            self.settings = new
            self._apparent.clear()

    def set_scene(self, scene: Scene) -> None:
        """Replace the scene; the caches go only when geometry or margin changed."""
        with self._lock:
            geometry = scene.geometry_key()
            if geometry != self.scenario.scene.geometry_key():
                self._keep_cached(lambda cs_key: cs_key[0] == geometry)     # (a held scene's: :meth:`hold_only`)
            self.scenario = self.scenario.with_scene(scene)
            self._checker = CollisionChecker(self.scenario.robot, scene)
            self._validator = MotionValidator(self._checker)

    def set_grid(self, grid: GridSpec) -> None:
        """Replace the grid (C-spaces of other grids stay cached)."""
        if grid.ndim != self.scenario.robot.dof:
            raise ValueError(f"grid.cells: expected {self.scenario.robot.dof} values (one per planned "
                             f"joint), got {grid.ndim}")
        with self._lock:
            self.scenario = self.scenario.with_grid(grid)

    # ------------------------------------------------------------------- goal
    def approach_error_deg(self, goal_rad) -> float:
        """
        Return the approach error (degrees) of a goal that grasps the target.

        Approach error (degrees) of a goal that grasps the scene's target (its tip within
        ``grasp.position_tolerance_m`` of the grasp point); nan for any other goal.
        """
        sc = self.scenario
        target = sc.scene.target
        if target is None:
            return math.nan
        q_full = sc.robot.full(np.asarray(goal_rad, dtype=float))
        miss = float(np.linalg.norm(sc.robot.tip_position(q_full) - target.grasp_point_m))
        tol = max(sc.acs.position_tolerance_m, 1e-6)
        return math.degrees(approach_error_rad(sc.robot, target, q_full)) if miss <= tol else math.nan

    def goal_clearance_and_approach(self, goal_rad) -> tuple:
        """
        Return (clearance m, :meth:`approach_error_deg`) of a goal (planned joints, rad).

        The last goal's are kept: a replan's goal repeats (same scenario, checker and goal bits).
        """
        goal = np.asarray(goal_rad, dtype=float)
        last = self._last_goal
        if last is not None and last[0] is self.scenario and last[1] is self._checker and last[2] == goal.tobytes():
            return last[3], last[4]
        clr, err = float(self._checker.clearance_m(goal)), self.approach_error_deg(goal)
        self._last_goal = (self.scenario, self._checker, goal.tobytes(), clr, err)
        return clr, err

    def goal_from_target(self) -> np.ndarray:
        """Return the best free IK branch of the scene's target, (dof,) rad (:meth:`capture_goal`)."""
        return self.capture_goal().q.copy()

    def capture_goal(self):
        """
        Return the best free IK branch of the scene's target, an ``ik.IKSolution``.

        Best free IK branch (highest manipulability) of the scene's target among those whose
        approach error is within ``max_approach_error_deg``; its ``method`` says how it was
        found (a redundant chain's self-motion sweep, ``redundant.py``).

        Raises ValueError with a reason when there is no target, the grasp pose is out of
        reach, every branch collides, or no branch meets the handle near perpendicular
        (the reason then names the attitudes that would, from the 3-joint IK).

        Kept while the scenario (by identity) and ``max_approach_error_deg`` are the same: a
        replan to the same target does not solve its IK again (its arrays read-only), nor
        find again that it has no capture posture.
        """
        sc, bound = self.scenario, self.settings.max_approach_error_deg
        held = self._capture
        if held is None or held[0] is not sc or held[1] != bound:
            try:
                found = self._capture_goal(sc, bound)
                found.q.flags.writeable = found.q_full.flags.writeable = False
            except ValueError as e:
                found = str(e)
            held = self._capture = (sc, bound, found)
        if isinstance(held[2], str):
            raise ValueError(held[2])
        return held[2]

    def _capture_goal(self, sc, bound):
        """:meth:`capture_goal`, found (``sc``: the scenario, ``bound``: ``max_approach_error_deg``)."""
        if sc.scene.target is None:
            raise ValueError("no goal given and the scene has no target")
        gp = np.round(sc.scene.target.grasp_point_m, 3).tolist()
        margin = sc.scene.safety_margin_m
        side = sc.scene.target.handle_side_m
        if margin >= side:     # the tip at the grasp is the handle's length from the target body
            raise ValueError(f"every capture posture for the grasp point {gp} m sits on the safety margin or "
                             f"within it: the tip at the grasp is the handle's length (target.handle_side_m = "
                             f"{side:g} m) from the target body, and safety_margin_m = {margin:g} m is not below "
                             f"it; a safety_margin_m below {side:g} m allows the grasp")
        found, free = [], []             # the branches of each approach angle tried; the clear ones
        offsets = self._approach_offsets_deg(sc, bound)
        for offset_deg in offsets:
            psi = None if offset_deg == 0.0 else sc.scene.target.approach_angle_rad + math.radians(offset_deg)
            try:
                every = grasp_ik(sc.robot, sc.scene, free_only=False, approach_angle_rad=psi)
            except ValueError as e:
                raise ValueError(f"no capture posture: {e}") from None
            found += every
            free = [s for s in every if s.free and s.clearance_m > margin + GRASP_ROOM_M]
            if free and offset_deg != 0.0:
                free = [replace(s, method=f"{s.method}; {offset_deg:+.3g}° off the handle's normal (the "
                                "perpendicular grasp out of reach or not clear)") for s in free]
            if free:
                break
        tried = (f" at approach angles within ±{bound:g}° of the handle's normal (grasp.max_approach_error_deg)"
                 if len(offsets) > 1 else "")
        if not found:
            raise ValueError(f"the target's grasp point {gp} m is out of the arm's reach "
                             f"(no inverse-kinematics solution within the joint bounds{tried})")
        if not free and not any(s.free for s in found):
            clr = ", ".join(f"{s.clearance_m:.3f} m" for s in found[:6])
            raise ValueError(f"every capture posture for the grasp point {gp} m collides{tried} "
                             f"(clearances {clr}; margin {margin:g} m)")
        if not free:
            raise ValueError(f"every capture posture for the grasp point {gp} m sits on the safety margin "
                             f"(its clearance is the margin, {margin:g} m, to within {GRASP_ROOM_M:g} m): no room "
                             f"to approach it; a safety_margin_m below {margin:g} m allows the grasp")
        errs = [math.degrees(approach_error_rad(sc.robot, sc.scene.target, s.q_full)) for s in free]
        good = [s for s, e in zip(free, errs) if e <= bound]
        if good:
            return good[0]
        # the posture nearest the normal of all found: where it is nearer than the clear ones', it is not clear
        nearer = min(((math.degrees(approach_error_rad(sc.robot, sc.scene.target, s.q_full)), s) for s in found),
                     key=lambda es: es[0], default=None)
        closer = ("" if nearer is None or nearer[0] >= min(errs) else
                  f" (the posture {nearer[0]:.1f}° off it collides)" if not nearer[1].clearance_m > 0.0 else
                  f" (the posture {nearer[0]:.1f}° off it comes within the safety margin {margin:g} m: clearance "
                  f"{nearer[1].clearance_m:.3f} m)")
        raise ValueError(f"no capture posture grasps the handle perpendicularly: link 3 meets it "
                         f"{min(errs):.1f}° off its normal{closer}, above grasp.max_approach_error_deg = "
                         f"{bound:g}°; {self._attitude_advice(sc)}")

    @staticmethod
    def _approach_offsets_deg(sc, bound: float) -> list:
        """
        Return the approach angles to try in scenario ``sc``, off the handle's normal, degrees: 0, ±1, ±2, … ±bound.

        The perpendicular grasp where it is in reach and clear; else the least tilt within
        ``grasp.max_approach_error_deg`` that is (a redundant arm whose perpendicular posture
        leaves its joint bounds a few degrees off it).  One angle only where the IK is
        position-only.
        """
        if bound <= 0.0 or not meets_approach_angle(sc.robot):
            return [0.0]
        last = bound * (1.0 - 1e-9)           # the bound itself, a rounding inside it
        steps = [float(k) for k in range(1, int(math.ceil(last))) if k < last] + [last]
        return [0.0] + [sign * k for k in steps for sign in (1.0, -1.0)]

    @staticmethod
    def _attitude_advice(sc) -> str:
        """Which attitude (joint 1) would allow a perpendicular grasp in scenario ``sc``, for a reason text."""
        if meets_approach_angle(sc.robot):
            return "no attitude change can help (the attitude is planned already)"
        atts = perpendicular_attitudes(sc.robot, sc.scene)
        free = [a for a, ok in atts if ok]
        if free:
            return ("an attitude of " + " or ".join(f"{math.degrees(a):.1f}°" for a in free)
                    + " would allow a perpendicular grasp (robot.locked_positions_deg)")
        if atts:
            return "at every attitude that allows a perpendicular grasp the arm collides"
        return "no attitude allows a perpendicular grasp (the handle is out of reach)"

    # ------------------------------------------------------------------ caches
    def apparent_planner(self, scene: Scene) -> "Planner":
        """
        Return a planner (geometry only) of this scenario in ``scene``, cached by its geometry (at most 4).

        The free-floating capture's field guides (``pipeline.PlanRun.field_guide``): the scene
        as the drifted body sees it at the end of the motion.
        """
        key = scene.geometry_key()
        sub = self._apparent.get(key)
        if sub is None:
            sub = Planner(self.scenario.with_scene(scene), settings=replace(self.settings, trajectory=False))
            self._remember(self._apparent, key, sub, 4)
        return sub

    def cache_sizes(self) -> dict:
        """Return the number of cached C-spaces, fields and body tables."""
        return {"cspaces": len(self._cspaces), "fields": len(self._fields),
                "body_tables": len(self._body_tables)}

    def _test_stall(self, stage: str, token) -> None:
        st = self.test_stall
        if st is not None and st[0] == stage:
            if st[3] is not None:
                st[3](stage)
            stall(token, st[1], st[2])

    @staticmethod
    def _remember(cache: dict, key, value, size: int) -> None:
        """Store a new entry (oldest out beyond ``size``); existing entries stay as they are."""
        if key in cache:
            return
        if len(cache) >= size:
            cache.pop(next(iter(cache)))
        cache[key] = value

    def _cspace(self, grid: GridSpec, extra_m: float, token=None, cached_only: bool = False):
        """
        (C-space, its cache key, cache hit) of the current scene on ``grid``.

        The spacecraft-body table (``cspace.body_occupancy``) depends on the grid and the
        margin only, so it is kept across target and debris moves as well.  ``token``:
        the plan's termination token; a build it stops raises ``termination.Cancelled``
        and stores nothing (nor evicts anything).  ``cached_only``: one not cached raises
        ``pipeline.NotCached`` instead.
        """
        sc = self.scenario
        margin = float(sc.scene.safety_margin_m + extra_m)
        key = (sc.scene.geometry_key(), grid, float(extra_m))
        cs = self._cspaces.get(key)
        if cs is not None:
            return cs, key, True
        if cached_only:
            raise NotCached("cspace")
        body_key = (grid, margin)
        self._fit_threads(grid.n_nodes, any_size=loops_at_any_size(sc.robot))    # the body table's loops too
        if body_key not in self._body_tables:
            self._remember(self._body_tables, body_key, body_occupancy(sc.robot, grid, margin, token=token), 4)
        self._test_stall("cspace", token)
        cs = build_cspace(sc.robot, sc.scene, grid, extra_margin_m=extra_m,
                          body_table=self._body_tables[body_key], token=token)
        if len(self._cspaces) >= 4:
            evicted = next(iter(self._cspaces))
            self._keep_cached(lambda cs_key: cs_key != evicted)
        self._cspaces[key] = cs
        return cs, key, False

    def _keep_cached(self, keep) -> None:
        """
        Drop the cached C-spaces whose key ``keep(key)`` refuses, and everything cached on them.

        Their fields, goal nodes, repairs' edges and descents go with them (the caller holds the lock).
        """
        for k in [k for k in self._cspaces if not keep(k)]:
            del self._cspaces[k]
        for cache in (self._fields, self._goal_nodes):                    # keyed on (C-space key, ...)
            for k in [k for k in cache if not keep(k[0])]:
                del cache[k]
        for cache in (self._colliding, self._failed_walks, self._walks):  # on (field key, ...)
            for k in [k for k in cache if not keep(k[0][0])]:
                del cache[k]

    def cache_key_of(self, entry):
        """Return the key the C-space or field ``entry`` (the object) is cached under, or None where it is not."""
        for cache in (self._cspaces, self._fields):
            for key, held in cache.items():
                if held is entry:
                    return key
        return None

    def hold_only(self, cspace_entry, field_entry) -> None:
        """
        Make the caches hold one C-space and one field of another planner's, and what this one made on them.

        ``cspace_entry``, ``field_entry``: (key, object) as that planner caches them
        (:meth:`cache_key_of`), or None; a field of another C-space is not held.  For a planner
        that plans from its caches alone (``plan(cached_only=True)``: ``worker.HybridBackend``).
        The entries are never changed, as this planner's own; the goal nodes made on that
        C-space stay, and the descents made on that field (the same object: a field solved again
        under the same key after its budget ended may differ), the rest goes.  The scene may
        become the C-space's afterwards (:meth:`set_scene` keeps the entries of the scene it
        changes to).
        """
        with self._lock:
            cs_key = None if cspace_entry is None else cspace_entry[0]
            field_key = None if field_entry is None or field_entry[0][0] != cs_key else field_entry[0]
            same_field = field_key is not None and self._fields.get(field_key) is field_entry[1]
            self._keep_cached(lambda k: k == cs_key)
            if not same_field:      # the descents and repairs' edges were made on another field object
                for cache in (self._colliding, self._failed_walks, self._walks):
                    cache.clear()
            self._fields.clear()
            if cspace_entry is None:
                return
            self._cspaces[cs_key] = cspace_entry[1]
            if field_key is not None:
                self._fields[field_key] = field_entry[1]

    def _fit_threads(self, nodes: int, any_size: bool = False, note: bool = True) -> None:
        """
        Give the stage about to run on ``nodes`` grid nodes the threads the CPU limit and load leave; note it.

        ``any_size``: the stage's loops run on threads at every grid size (``cores.fit_threads``).
        ``note``: False: not noted in the plan's ``solver_stats`` (:meth:`threads_note`).
        """
        s = self.settings
        fit = fit_threads(s.max_threads, nodes, s.threads_follow_load, any_size)
        if note:
            self._fits.append(fit)

    def threads_note(self) -> dict:
        """
        Return the current plan's thread counts for its ``solver_stats``: {} where none were counted or limited.

        ``threads``: the fewest threads a stage of the plan ran its parallel loops on,
        ``threads_limit``: the most it could, ``busy_cores``: the most cores it found busy
        with other work (0 where none was counted), and where the process's CPU limit took
        threads, ``cpu_limit``: that limit in whole CPUs (``cores.fit_threads``).  The stages
        are the C-space's and the field's solves: a first repair's swept edges take their
        count the same way but are not noted (a plan that finds them cached runs none, and a
        plan's stats on a small grid are the same whatever the caches and the load).
        """
        fits = [f for f in self._fits if f.busy is not None or f.cpu_limit is not None]
        if not fits:
            return {}
        note = {"threads": min(f.threads for f in fits), "threads_limit": max(f.limit for f in fits),
                "busy_cores": max(f.busy or 0 for f in fits)}
        limits = [f.cpu_limit for f in fits if f.cpu_limit is not None]
        return dict(note, cpu_limit=min(limits)) if limits else note

    @staticmethod
    def _field_key(cspace_key, goal_nodes, settings: PlannerSettings) -> tuple:
        return (cspace_key, tuple(map(tuple, np.asarray(goal_nodes).tolist())), settings.solver,
                settings.field_tolerance, settings.field_budget_s)

    @staticmethod
    def repaired_field_key(field_key: tuple, blocked, cut) -> tuple:
        """
        Return the key of the field under ``field_key`` repaired: ``blocked`` nodes out, ``cut`` edges cut.

        :meth:`_field_key`'s items, then :data:`REPAIRED`, the blocked nodes, sorted, and the cut
        edges (``repair.CutEdges``; ``pipeline.PlanRun.resolve``).
        """
        return field_key + (REPAIRED, tuple(sorted(blocked)), cut)

    @staticmethod
    def repaired_key(field_key: tuple) -> bool:
        """
        Tell whether a field's key (:meth:`cache_key_of`) is a repaired field's (:meth:`repaired_field_key`).

        A plan from the caches alone looks up the solve's key first, so a repaired field alone
        answers none.
        """
        return REPAIRED in field_key

    def _solve(self, cs, key, goal_nodes, settings: PlannerSettings, blocked=(), cut_edges=_NO_CUTS, token=None,
               guess=None):
        """
        Return the field under ``key`` (solved and stored when absent).

        The C-space's free nodes less ``blocked``, its grid edges less ``cut_edges`` (a ``repair.CutEdges``).
        ``token``: the plan's termination token; a solve it stops raises
        ``termination.Cancelled`` and stores nothing.  ``guess``: a field of the same grid and
        goal whose values the log_harmonic solve starts from (``solve_field``'s guess).
        """
        fld = self._fields.get(key)
        if fld is not None:
            return fld
        occ = cs.occupied
        if blocked:
            occ = occ.copy()
            occ[tuple(np.array(sorted(blocked)).T)] = True
        edges = cut_edges.array
        self._test_stall("field", token)
        self._fit_threads(occ.size)
        fld = solve_field(occ, cs.grid.periodic, np.asarray(goal_nodes), solver=settings.solver,
                          tol=settings.field_tolerance, budget_s=settings.field_budget_s,
                          cut_edges=edges if len(edges) else None, token=token,
                          guess=None if guess is None else guess.log_u)
        self._remember(self._fields, key, fld, 16)
        return fld

    @staticmethod
    def _descend(field, node, motions, lower_rad, step_rad, joins=None):
        """
        Run the descent stage (``descent.descend``; ``joins``: its ``WalkJoins``), looked up in this module.

        The node's tests inject a fault by patching ``planner.descend``.
        """
        return descend(field, node, motions, lower_rad, step_rad, joins=joins)

    # ------------------------------------------------------------------- plan
    def plan(self, start_rad, goal_rad=None, cancel: threading.Event | None = None,
             progress: Callable[[str], None] | None = None, start_tangent=None,
             cached_only: bool = False) -> PlanResult:
        """
        Plan from ``start_rad`` to ``goal_rad`` (default: :meth:`goal_from_target`).

        ``start_rad`` is the arm's state (periodic joints may be unwrapped: the trajectory
        starts there).  Never raises for bad input or when there is no path: returns
        ``ok=False`` with ``code`` and ``reason``.

        ``cancel``: a ``termination.Termination`` is polled inside the C-space and field
        kernels, so a cancel ends any stage within one kernel step; any other object
        with ``is_set()`` (e.g. a ``threading.Event``) is polled between steps only.
        A cancelled plan returns code ``cancelled`` and leaves the caches with complete
        entries only (what finished before the cancel is kept and reused).

        ``start_tangent``: (dof,) the direction the arm moves in at the start (a replan from a
        moving arm: its velocity), or None: the smoothed path leaves the start along it
        (``smoothing.smooth_path``); bad values answer ``invalid_input``.

        ``cached_only``: a plan from the caches alone: where it would build a C-space, solve a
        field, search the grid's connectivity before a solve, repair or search a free-floating capture, it raises
        ``pipeline.NotCached`` instead (the goal nodes and descents it made before stay cached).
        """
        with self._lock:
            self._fits = []
            if not cached_only:     # (one runs no parallel loop: setting the count would start numba's pool)
                self._fit_threads(0, note=False)     # the numba count of this thread; noted where a stage runs loops
            run = PlanRun(self, self.settings, cancel, progress, start_tangent, cached_only)
            return run.run(start_rad, goal_rad)

    def add_trajectory(self, result: PlanResult, state_rad=None) -> PlanResult:
        """Run the trajectory stage on an existing ok result (e.g. a drift-compensated plan)."""
        if not result.ok or not trajectory_limits_known(self.scenario):
            return result
        t = time.perf_counter()
        traj, reaction = timed_motion(self.scenario, result.path_rad, state_rad, self.settings.reaction,
                                      motions=self._validator)
        timings = dict(result.timings_s, trajectory=time.perf_counter() - t)
        if reaction is not None and not reaction.ok:
            return replace(result, ok=False, code=Code.REACTION_REFUSED, reason=reaction.reason,
                           trajectory=traj, reaction=reaction, timings_s=timings)
        return replace(result, trajectory=traj, reaction=reaction, timings_s=timings)


def warm_up_unreached(coarse: Scenario) -> None:
    """
    Compile (or load from numba's cache) the kernels a plan on the ``coarse`` scenario may not reach.

    The C-space row kernel's other form (a refinement reaches it), the spline and shortcut
    kernels, a repair's (the sheet search, the swept edges), a start in contact's (the exit
    stage).  Both warm-ups run it (:func:`warm_up`, ``worker.warm_up``).
    """
    cspace_warm_up(coarse.robot, coarse.scene, coarse.grid)
    smoothing_warm_up()
    repair_warm_up()
    swept_warm_up(coarse.robot, coarse.scene, coarse.grid)
    contact_warm_up(coarse.robot, coarse.scene)


def warm_up(scenario: Scenario, cells: int = 6) -> float:
    """
    Compile (or load from numba's cache) every kernel a plan uses; return the seconds.

    Plans on a coarse copy of the scenario's grid from random free postures, so the
    first real plan's stage timings are the planner's, not the JIT's, and faults in the heap
    a plan on the scenario's own grid fills (``field.reserve_heap``), so they are not the
    page faults' either.
    """
    t0 = time.perf_counter()
    coarse = scenario.with_grid(scenario.grid.with_cells(cells))
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
    warm_up_unreached(coarse)
    field_warm_up()             # the solver kernels a coarse grid does not reach
    reserve_heap(scenario.grid.n_nodes, scenario.planner_settings.max_grid_nodes)   # the heap a plan there fills
    free_floating_warm_up(scenario)     # a free-floating capture's kernels, where the scenario plans one
    return time.perf_counter() - t0
