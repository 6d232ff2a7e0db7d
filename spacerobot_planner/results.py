"""
What a plan returns: the result codes, the stage names and ``PlanResult``.

The codes are a ``str`` enum: ``Code.OK == "ok"``, and ``str()``, f-strings and JSON
give the plain value, so the strings on the wire stay as they were.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from enum import Enum

import numpy as np

from .cspace import CSpace
from .field import Field

__all__ = ["Code", "CODES", "STAGES", "PlanResult"]


class Code(str, Enum):
    """Why a plan ended (README, "Result codes")."""

    OK = "ok"
    INVALID_INPUT = "invalid_input"
    START_IN_COLLISION = "start_in_collision"
    GOAL_IN_COLLISION = "goal_in_collision"
    GOAL_UNREACHABLE = "goal_unreachable"
    DISCONNECTED = "disconnected"
    PATH_INVALID = "path_invalid"
    CANCELLED = "cancelled"
    INTERNAL_ERROR = "internal_error"
    REACTION_REFUSED = "reaction_refused"

    def __str__(self) -> str:
        return self.value

    __format__ = str.__format__


#: every code's string, in the order above
CODES = tuple(c.value for c in Code)
#: the stages in pipeline order (``timings_s`` keys); "exit" is leaving a contact at the start
STAGES = ("exit", "cspace", "field", "descent", "repair", "smoothing", "verify", "trajectory", "total")


@dataclass(frozen=True, eq=False)
class PlanResult:
    """
    What a plan produced (or why not).

    Attributes
    ----------
        ok: a verified path was found (and, with a trajectory stage, the spacecraft's
            reaction accepts it).
        reason: a sentence for people; None when ok.
        code: a :class:`Code` (a str: ``res.code == "ok"``).
        joint_names: the planned joints.
        start_rad: (dof,) the start as given (periodic joints wrapped).
        goal_rad: (dof,) the goal (periodic joints wrapped), None if none was found.
        path_rad: (M, dof) smoothed path, samples ≤ 0.5° apart, exact start first and
            exact goal last; periodic joints unwrapped, so on those the last row
            equals the goal up to a multiple of 2π.  (0, dof) when no path.  When the
            start touched an obstacle, its first ``len(exit_path_rad) - 1`` steps are
            the exit stretch (below).
        grid_path_rad: (m, dof) the descent's grid nodes (wrapped grid values).
        timings_s: seconds per stage (``STAGES``); a cached stage reports 0.0.
        cached: the stages served from cache.
        solver: field solver name.
        solver_stats: sweeps, residual, converged, left, bands, repairs (re-solves after
            cutting grid edges or blocking nodes whose motions collide), cut_edges,
            blocked_nodes, grid_extra_margin_m (the grid's margin beyond the safety margin
            that gave the answer: the planner retries at 0 before answering
            ``disconnected``), grid (the grid's label, e.g. "72x73x73") and refinements
            (how many times the scenario's grid was doubled to get it).
        min_clearance_m: minimum clearance over the certified check, metres (nan
            without path); the exit stretch is not part of it.
        cspace, field: the grid and the field used (None if not reached).
        smoothing: "shortcut_spline", "spline", "polyline" or "" without a path.
        path_length_rad: joint-space length of path_rad (nan without path).
        traceback: the formatted traceback when ``code == "internal_error"``; "" otherwise.
        trajectory: ``trajectory.Trajectory`` of path_rad aligned to the start as given
            (whole turns on periodic joints), None without limits or path.
        reaction: ``reaction.ReactionReport`` when the trajectory stage assessed the
            spacecraft's reaction (ACS or wheel settings), else None.
        approach_error_deg: angle between link 3 and the handle's inward normal at the
            goal when the goal is a grasp of the scene's target (tip within
            ``grasp.position_tolerance_m`` of the grasp point), else nan.
        exit_path_rad: (K, dof) the uncertified exit stretch from a start touching an
            obstacle (penetration ≤ ``planner.max_start_penetration_m``) to the first
            free posture, ≤ 0.5° steps along increasing signed distance; (0, dof) when
            the start was free.
        start_penetration_m: how deep the start's links were inside an obstacle (0 when
            they were not), metres.
        free_floating: ``acs.mode: free_floating``: the ``spacecraft.FreeFloatingResponse``
            along path_rad (every joint with the attitude as it drifts, the body's
            position); else None.  ``smoothing`` is "free_floating_capture" when
            ``free_floating_capture.plan_capture`` planned the path.

    """

    ok: bool
    reason: str | None
    code: Code
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
    trajectory: object = None
    reaction: object = None
    approach_error_deg: float = math.nan
    exit_path_rad: np.ndarray | None = None
    start_penetration_m: float = 0.0
    free_floating: object = None

    def with_chain(self, chain_s: float) -> "PlanResult":
        """
        Return this result with the node's chain (``adapters.post_process``) as its trajectory stage.

        The chain makes the trajectory that is published (from the node, or from
        ``spacerobot-plan`` for the same request), so its seconds join the ``trajectory``
        stage (after the planner's own time parameterisation, where one ran) and the total.
        """
        t = self.timings_s
        return replace(self, timings_s={**t, "trajectory": t.get("trajectory", 0.0) + chain_s,
                                        "total": t.get("total", 0.0) + chain_s})

    def to_json_dict(self) -> dict:
        """
        Plain-JSON view (the CLI's output): lists and floats, NaN as null.

        ``trajectory`` (joint_names, times_s, positions_rad, velocities_rad_s,
        accelerations_rad_s2, duration_s, active_limit) and ``reaction`` only when
        the trajectory stage ran; ``exit`` only when the start left a contact.  Free
        floating: ``path_rad`` holds every joint (``path_joint_names``), the attitude as it
        drifts, and ``free_floating`` the body's position along it and the figures at its end.
        """
        def arr(a):
            return None if a is None else np.asarray(a, dtype=float).tolist()

        def num(x):
            return None if x is None or not math.isfinite(x) else float(x)

        doc = {
            "ok": self.ok,
            "code": str(self.code),
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
            "approach_error_deg": num(self.approach_error_deg),
        }
        if self.exit_path_rad is not None and len(self.exit_path_rad):
            doc["exit"] = {"path_rad": arr(self.exit_path_rad),
                           "start_penetration_m": float(self.start_penetration_m),
                           "certified": False}
        ff = self.free_floating
        if ff is not None:
            doc["path_joint_names"] = list(ff.joint_names)
            doc["path_rad"] = arr(ff.q_full_rad)
            doc["free_floating"] = {"body_position_m": arr(ff.body_position_m),
                                    "body_displacement_m": float(ff.body_displacement_m),
                                    "attitude_change_deg": float(ff.attitude_change_deg),
                                    "tip_m": arr(ff.tip_m), "tip_miss_m": float(ff.tip_miss_m)}
        if self.trajectory is not None:
            doc["trajectory"] = self.trajectory.to_json_dict()
        if self.reaction is not None:
            doc["reaction"] = self.reaction.to_json_dict()
        return doc
