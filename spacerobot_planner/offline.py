"""
One offline plan as ``spacerobot-plan`` makes it: the plan, the drift compensation, the node's chain.

:func:`plan_offline` is the single-plan pipeline that the CLI runs for one request and the
envelope sweep (``envelope/sweep.py``) runs for every pose of a map, so a map's row is the
plan a person would get from ``spacerobot-plan`` for that pose:

1. ``Planner.plan`` (C-space, field, descent, smoothing, certification, trajectory and the
   spacecraft's reaction when the planner was made with ``reaction=True``);
2. with ``acs.mode: free_floating`` and ``acs.compensate_drift``, the drift-compensated plan
   (``free_floating.plan_free_floating``, geometry only) and the trajectory stage on it;
3. the node's chain after the path, from rest at the start (``adapters.post_process``): what
   the node publishes for the same request; its time joins the result's ``trajectory`` stage
   and total, as the node's (``PlanResult.with_chain``).

No rclpy here.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

from .adapters import Processed, post_process
from .free_floating import CompensatedPlan, plan_free_floating
from .motion import MotionValidator
from .planner import Planner
from .results import PlanResult

__all__ = ["OfflinePlan", "plan_offline"]


@dataclass(frozen=True, eq=False)
class OfflinePlan:
    """
    What :func:`plan_offline` made.

    Attributes
    ----------
        result: the ``PlanResult`` (the compensated plan's, with its trajectory, when the drift
            compensation found one).
        processed: ``adapters.Processed`` of the result's path from rest at the start (the
            published trajectory), None when the result has no trajectory.
        compensated: the ``free_floating.CompensatedPlan`` when the drift compensation ran, else None.
        chain_s: seconds the node's chain took (in ``result``'s trajectory stage and total), 0.0
            without a trajectory.

    """

    result: PlanResult
    processed: Processed | None
    compensated: CompensatedPlan | None
    chain_s: float = 0.0


def plan_offline(planner: Planner, start_rad, goal_rad=None, progress=None) -> OfflinePlan:
    """
    Plan one request the way ``spacerobot-plan`` does (see the module docstring).

    Args:
        planner: the ``Planner`` (its scenario: the scene, the ACS settings and the limits).
        start_rad: (dof,) the start, rad.
        goal_rad: (dof,) the goal, rad, or None for the grasp of the scene's target.
        progress: a callable(str) for the planner's stage lines, or None.

    Returns
    -------
        OfflinePlan.

    Raises
    ------
        ValueError: the drift compensation refuses the scenario (no target, or the attitude
            is planned); ``Planner.plan`` itself never raises.

    """
    scenario = planner.scenario
    res = planner.plan(start_rad, goal_rad, progress=progress)
    comp = None
    if res.code in ("ok", "reaction_refused") and scenario.acs.mode == "free_floating" \
            and scenario.acs.compensate_drift:
        # the compensation plans geometry only; the trajectory stage follows on its result
        comp = plan_free_floating(scenario, start_rad, goal_rad)
        if comp.plan.ok:
            res = planner.add_trajectory(comp.plan, start_rad)
    processed, chain_s = None, 0.0
    if res.trajectory is not None:
        # the node's chain, from rest at the start: what the node publishes for this request (its
        # seconds in the trajectory stage and the total, as the node's)
        t0 = time.perf_counter()
        processed = post_process(scenario, res.path_rad, start_rad=start_rad,
                                 motions=MotionValidator.for_scene(scenario.robot, scenario.scene))
        chain_s = time.perf_counter() - t0
        res = res.with_chain(chain_s)
    return OfflinePlan(res, processed, comp, chain_s)
