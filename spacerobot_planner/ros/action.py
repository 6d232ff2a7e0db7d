"""
The planner node's ``plan_capture`` action server (Nav2's ``ComputePathToPose`` pattern).

A goal becomes a request of the node's capture session (``session.CaptureSession``): a
target pose or a joint goal, and optionally its own ``start`` (then it is planned and
returned, not executed).  A newer goal (or a topic request) supersedes it (one with its own
start: only a newer one with its own start, ``session``'s two streams): it aborts with code
SUPERSEDED and the reason; a cancel ends its plan; feedback carries the stage and a
progress fraction (``waiting_for_joint_states`` while it waits for the first
joint_states); a bad goal aborts with INVALID_INPUT and the reason.  The result carries
the published trajectories (``conversions.publication_msgs``; free floating, the predicted
drift in ``attitude_trajectory``: ``conversions.predicted_drift_msg``) and the plan's figures.
"""

from __future__ import annotations

import numpy as np
from rclpy.action import ActionServer, CancelResponse, GoalResponse
from rclpy.qos import QoSProfile, qos_profile_services_default
from rclpy.task import Future
from spacerobot_planner_interfaces.action import PlanCapture

from ..session import target_why
from . import conversions as conv

__all__ = ["PlanCaptureServer", "SERVICE_DEPTH", "RESULT_TIMEOUT_S"]

#: requests the action's goal, cancel and result services keep before they are taken (rclpy's
#: default, 10, lost a client's 20 result requests sent at once: 11 were answered)
SERVICE_DEPTH = 100
#: how long a finished goal's result is kept for a client that asks later, s (rclpy's default 10 s)
RESULT_TIMEOUT_S = 60


class PlanCaptureServer:
    """The action server of ``node`` (a ``planner_node.PlannerNode``): goals in, the session's outcomes out."""

    def __init__(self, node):
        self.node = node
        d = qos_profile_services_default
        services = QoSProfile(history=d.history, depth=SERVICE_DEPTH, reliability=d.reliability,
                              durability=d.durability)
        self.server = ActionServer(node, PlanCapture, "plan_capture", execute_callback=self._execute,
                                   goal_callback=self._on_goal, cancel_callback=self._on_cancel,
                                   handle_accepted_callback=lambda h: h.execute(),
                                   goal_service_qos_profile=services, result_service_qos_profile=services,
                                   cancel_service_qos_profile=services, result_timeout=RESULT_TIMEOUT_S)

    def destroy(self) -> None:
        self.server.destroy()

    async def _execute(self, goal_handle):
        """One plan_capture goal: validate, hand to the session, await its outcome."""
        node = self.node
        node._pending_answers.running()
        done = Future()

        def on_done(outcome):
            done.set_result(outcome)
            node._wake_goals()

        highest = [0.0]          # progress never goes back: a plan planned again repeats its stages

        def on_progress(p):
            highest[0] = max(highest[0], float(p.fraction))
            try:
                goal_handle.publish_feedback(PlanCapture.Feedback(stage=p.stage, progress=highest[0]))
            except Exception:      # noqa: BLE001 - goal already finished / server gone
                pass

        try:
            why, kw = self._request_of(goal_handle.request)
        except ValueError as e:
            node._reject("plan_capture", "invalid_input", str(e))
            goal_handle.abort()
            return conv.plan_result(PlanCapture.Result, "invalid_input", str(e))
        req = node.session.request(why, on_done=on_done, on_progress=on_progress, **kw)
        key = bytes(goal_handle.goal_id.uuid)
        node._goals[key] = req
        try:
            node._submit(req)
            outcome = await done
        finally:
            node._goals.pop(key, None)
        arm, att = conv.publication_msgs(outcome.publication)
        if att is None:                # free floating: the predicted drift (never published)
            att = conv.predicted_drift_msg(outcome.publication)
        result = conv.plan_result(PlanCapture.Result, outcome.code, outcome.reason, arm, outcome.result, att)
        try:
            if outcome.ok:
                goal_handle.succeed()
            elif outcome.code == "cancelled" and goal_handle.is_cancel_requested:
                goal_handle.canceled()
            else:
                goal_handle.abort()
        except Exception as e:     # noqa: BLE001 - the server went away (shutdown)
            node._log("warning", f"plan_capture: goal ended during shutdown: {e}")
        return result

    def _request_of(self, goal) -> tuple:
        """Return (why, keywords of ``CaptureSession.request``) of a goal; ValueError names the field."""
        node, robot = self.node, self.node.robot
        start = None
        if len(goal.start.name) or len(goal.start.position):
            start = conv.joint_state_positions(goal.start, robot.planned_names, "goal.start")
            start = robot.validate_q(start, "goal.start")
        if goal.use_joint_goal:
            q = node.inputs.joint_goal_from_msg(goal.joint_goal, "goal.joint_goal")
            return (f"plan_capture goal: joint goal {np.round(np.degrees(q), 2).tolist()}°",
                    {"joint_goal": q, "start_rad": start})
        try:
            target = node.inputs.target_from_pose(goal.target_pose, "goal.target_pose")
        except ValueError as e:
            if len(goal.joint_goal.name) and not goal.target_pose.header.frame_id:     # the flag left out
                raise ValueError(f"{e} (the goal's joint_goal is filled but use_joint_goal is false: set "
                                 f"use_joint_goal: true to plan to it)") from None
            raise
        return f"plan_capture goal: {target_why(target)}", {"target": target, "start_rad": start}

    def _on_goal(self, goal):
        node = self.node
        if not node.session.accepting:
            node.get_logger().warning("plan_capture: goal rejected: the node is not active "
                                      f"(lifecycle state '{node.lifecycle_state}')")
            return GoalResponse.REJECT
        return GoalResponse.ACCEPT

    def _on_cancel(self, goal_handle):
        req = self.node._goals.get(bytes(goal_handle.goal_id.uuid))
        if req is not None:
            self.node.session.cancel(req, "cancelled by the action client")
        return CancelResponse.ACCEPT
