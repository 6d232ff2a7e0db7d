"""
Free-floating planning by drift compensation (``acs.compensate_drift``, the CLI's strategy).

With attitude control off during the motion the spacecraft turns and translates under the
arm (``spacecraft.free_floating_response``) and the tip misses the grasp.
:func:`plan_free_floating` predicts that drift and plans again for the scene as the body
will see it at the end (``free_floating_capture.apparent_scene``), until the drifted tip
reaches the grasp point and the drifted motion is certified in the inertial frame
(``reaction.check_drifted``).  It places the tip only: the approach follows from the drift
(judged by the reaction against ``grasp.max_approach_error_deg``).  The planner's own
free-floating capture, which steers the approach as well, is ``free_floating_capture.py``.
It plans with the ``Planner``, so it sits above it.  No ROS imports.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .free_floating_capture import apparent_scene
from .ik import grasp_ik
from .planner import Planner
from .reaction import DriftCheck, check_drifted
from .spacecraft import FreeFloatingResponse, MassProperties, free_floating_response

__all__ = ["CompensatedPlan", "plan_free_floating"]


@dataclass(frozen=True, eq=False)
class CompensatedPlan:
    """
    A plan whose free-floating execution reaches the grasp (see :func:`plan_free_floating`).

    Attributes
    ----------
        ok: the drifted tip ends within the tolerance of the grasp point and the drifted
            motion is certified collision-free in the inertial frame.
        reason: why not (None when ok).
        plan: the last ``PlanResult`` (planned in the apparent scene of that iteration).
        goal_rad: (dof,) its goal posture.
        response: FreeFloatingResponse of that plan in the real (inertial) scene.
        drift: DriftCheck of that plan in the real scene.
        history: per iteration (tip miss m, attitude change deg, drift certified).

    """

    ok: bool
    reason: str | None
    plan: object
    goal_rad: np.ndarray | None
    response: FreeFloatingResponse | None
    drift: DriftCheck | None
    history: tuple


def plan_free_floating(scenario, start_rad, goal_rad=None, *, masses: MassProperties | None = None,
                       position_tolerance_m: float | None = None, max_iterations: int = 12) -> CompensatedPlan:
    """
    Plan the arm so that, free floating, it still reaches the handle (the target's grasp).

    Plan once in the real scene; then, repeatedly, predict the drift of that plan
    (attitude change Δθ1 and body displacement b at its end), move the scene to where
    the body will see it at the end (turned by −Δθ1 about the body centre after the body
    moved by b: the *apparent* scene), take the grasp IK branch nearest the previous
    goal there and plan again (the planner certifies the path against the apparent
    scene).  Each plan is judged in the real inertial scene: its drifted tip against the
    grasp point and its drifted motion by :func:`check_drifted`.  It stops when the miss
    is below a tenth of the tolerance (or 1 mm) and the drifted motion is certified.

    Args:
        scenario: a ``config.Scenario`` with a target; the attitude (joint 1) must not be
            planned (free floating, nothing commands it).
        start_rad: (dof,) start posture.
        goal_rad: first goal (default: the target's IK).
        masses: default ``scenario.masses``; position_tolerance_m: default
            ``scenario.acs.position_tolerance_m``.

    Returns
    -------
        CompensatedPlan (``ok`` False with a reason when it did not converge).

    Raises
    ------
        ValueError: no target, or the attitude is a planned joint.

    """
    robot, scene = scenario.robot, scenario.scene
    if scene.target is None:
        raise ValueError("plan_free_floating: the scene has no target (nothing to reach)")
    if 0 in robot.planned_joints:
        raise ValueError("robot.planned_joints: free floating, the attitude is not commanded; plan the arm "
                         "joints only (lock the attitude at its start value)")
    masses = scenario.masses if masses is None else masses
    tol = scenario.acs.position_tolerance_m if position_tolerance_m is None else float(position_tolerance_m)
    grasp = scene.target.grasp_point_m
    # geometry only: the core refuses free-floating trajectories on their reaction
    # (reaction_refused); the caller adds the trajectory to the compensated plan
    res = Planner(scenario, trajectory=False).plan(start_rad, goal_rad)
    history = []
    resp = drift = None
    for _ in range(max_iterations + 1):
        if not res.ok:
            return CompensatedPlan(False, f"planning failed ({res.code}): {res.reason}", res, res.goal_rad,
                                   resp, drift, tuple(history))
        goal = res.goal_rad
        resp = free_floating_response(robot, masses, res.path_rad, grasp)
        drift = check_drifted(robot, masses, scene, res.path_rad)
        history.append((resp.tip_miss_m, resp.attitude_change_deg, drift.ok))
        if drift.ok and resp.tip_miss_m <= min(0.1 * tol, 1e-3) or len(history) > max_iterations:
            break
        apparent = apparent_scene(scene, math.radians(resp.attitude_change_deg), resp.body_position_m[-1])
        sols = grasp_ik(robot, apparent)
        if not sols:
            return CompensatedPlan(False, "no collision-free grasp posture for the drifted target", res, goal,
                                   resp, drift, tuple(history))
        goal = min(sols, key=lambda sol: float(np.linalg.norm(sol.q - goal))).q
        res = Planner(scenario.with_scene(apparent), trajectory=False).plan(start_rad, goal)
    ok = drift.ok and resp.tip_miss_m <= tol
    reason = None if ok else (
        f"free floating, compensated: after {len(history)} plans the drifted tip misses the grasp by "
        f"{resp.tip_miss_m:.3f} m (tolerance {tol} m){'' if drift.ok else ' and the drifted arm collides'}")
    return CompensatedPlan(ok, reason, res, goal, resp, drift, tuple(history))
