"""
The plan_capture action (Nav2's ComputePathToPose pattern), with an in-process client.

Oracles: the trajectory published on joint_trajectory (the same message must come back
as the result), forward kinematics written here (the last point grasps the target),
the goal statuses of the action protocol itself.  Long plans are made long by the
``planner.test_stall_s`` stall (uninterruptible, like a numba kernel), not by a big grid.
"""

from __future__ import annotations

import math
import time

import numpy as np
import pytest
from action_msgs.msg import GoalStatus
from sensor_msgs.msg import JointState
from spacerobot_planner_interfaces.action import PlanCapture

from spacerobot_planner.ros.conversions import duration_to_s, joint_state_msg

from node_helpers import PROMPT_BOUND_S, next_plan, planned_positions, scene_params

R = PlanCapture.Result
#: limits that make the paper's 3-DOF first motion about 10 s long (half test_replanning_node's moderate ones):
#: a goal sent while the arm follows it is planned, on a loaded machine too, before the arm stops
SLOW = {"trajectory.max_velocity_deg_s": [15.0, 30.0, 30.0],
        "trajectory.max_acceleration_deg_s2": [30.0, 60.0, 60.0]}
#: the stall of a plan that a newer request supersedes: far longer than a loaded machine takes to send that
#: request (it had been 2 s), never waited for (the supersession ends it at once)
STALL_S = 60.0
#: how long such a plan's result is waited for: half the stall (a plan that waited for it fails the wait)
SUPERSEDED_WITHIN_S = STALL_S / 2


def _tip_m(link_lengths_m, q_full):
    """Planar chain: link k points along the sum of the first k+1 joint angles."""
    c = np.cumsum(q_full)
    L = np.asarray(link_lengths_m)
    return np.array([(L * np.cos(c)).sum(), (L * np.sin(c)).sum()])


def _target_goal(x=-3.27, y=-2.60, yaw=0.0, frame="world"):
    g = PlanCapture.Goal()
    g.target_pose.header.frame_id = frame
    g.target_pose.pose.position.x, g.target_pose.pose.position.y = float(x), float(y)
    g.target_pose.pose.orientation.z, g.target_pose.pose.orientation.w = math.sin(yaw / 2), math.cos(yaw / 2)
    return g


def _joint_goal(names, q):
    g = PlanCapture.Goal()
    g.use_joint_goal = True
    g.joint_goal = joint_state_msg(names, q)
    return g


def _without_flag(goal):
    goal.use_joint_goal = False
    return goal


def _start(g):
    robot = g.scenario.robot
    g.send_joint_state(joint_state_msg(robot.joint_names, robot.full(g.scenario.start_rad)))


def test_goal_plans_returns_the_published_trajectory_with_feedback(graph, monkeypatch):
    from rclpy.action.server import ServerGoalHandle
    published = []                 # what the node's goal handle publishes (the client's copy can lose the last)
    send = ServerGoalHandle.publish_feedback
    monkeypatch.setattr(ServerGoalHandle, "publish_feedback",
                        lambda self, fb: (published.append(fb.stage), send(self, fb))[1])
    g = graph(scene_params("3dof"), with_arm=False)
    _start(g)
    feedback = []
    handle = g.send_goal(_target_goal(), feedback=lambda m: feedback.append(m.feedback))
    status, res, _ = g.goal_result(handle)
    assert status == GoalStatus.STATUS_SUCCEEDED, res.reason
    assert res.error_code == R.OK and res.error_name == "ok" and res.reason == ""
    g.wait(lambda: g.n_trajs() == 1, 30, "the trajectory on joint_trajectory")
    g.wait(lambda: len(g.att_trajs) == 1, 30, "the attitude trajectory on attitude_trajectory")
    for mine, pub in ((res.trajectory, g.trajs[0][1]), (res.attitude_trajectory, g.att_trajs[0][1])):
        assert list(mine.joint_names) == list(pub.joint_names)
        assert len(mine.points) == len(pub.points) > 2
        for a, b in zip(mine.points, pub.points):
            assert list(a.positions) == list(b.positions)
            assert duration_to_s(a.time_from_start) == duration_to_s(b.time_from_start)
    assert list(res.trajectory.joint_names) == ["shoulder", "elbow"]
    assert list(res.attitude_trajectory.joint_names) == ["attitude"]
    # the last point grasps the target (forward kinematics written above)
    robot = g.scenario.robot
    q_end = planned_positions(robot, [res.trajectory, res.attitude_trajectory])
    tip = _tip_m(robot.link_lengths_m, robot.full(q_end))
    grasp = np.array(g.scenario.scene.target.grasp_point_m)
    assert np.linalg.norm(tip - grasp) < 1e-6
    assert res.min_clearance_m > 0.0
    assert "total" in res.stage_names and len(res.stage_times_s) == len(res.stage_names)
    assert all(t >= 0.0 for t in res.stage_times_s)
    # the node's trajectory stage is the chain after the path: timed (it had said 0.00), within the total
    stage = dict(zip(res.stage_names, res.stage_times_s))
    assert stage["trajectory"] > 0.0, stage
    assert sum(t for name, t in stage.items() if name != "total") <= stage["total"] + 1e-9, stage
    # the node publishes every stage, the chain's "trajectory" last; rclpy's action client drops a
    # feedback that comes with or after the result (it forgets the goal's feedback callback then),
    # so the client holds those published before the last, in order
    assert published and published[0] == "cspace" and published[-1] == "trajectory", published
    stages = [f.stage for f in feedback]
    assert stages and stages == published[:len(stages)] and len(stages) >= len(published) - 1, (stages, published)
    assert [f.progress for f in feedback] == sorted(f.progress for f in feedback)


def test_a_goal_planned_again_sends_its_stages_again_and_its_progress_never_goes_back(graph, monkeypatch):
    """
    The arm moves; the plan takes longer than the 1 s horizon (a stall), so it is planned again with 2 s.

    The goal's plan must begin while the arm still follows the first trajectory (else it plans once, from
    rest): the first motion is made about 10 s long by slow limits (with the fast ones it took about 2 s,
    and a loaded machine spent that between the arm moving and the goal's plan), and the action client is
    made (its server discovered) before it starts.
    """
    from rclpy.action.server import ServerGoalHandle
    from rclpy.parameter import Parameter
    published = []
    send = ServerGoalHandle.publish_feedback
    monkeypatch.setattr(ServerGoalHandle, "publish_feedback",
                        lambda self, fb: (published.append((fb.stage, fb.progress)), send(self, fb))[1])
    g = graph(scene_params("3dof", **SLOW))         # with the mock arm: it follows the first trajectory
    g.action_client()                               # discovered now, not while the arm moves
    g.send_target()
    g.wait(lambda: g.n_trajs() >= 1 and g.arm.executing, 60, "the arm moving on the first trajectory")
    assert g.planner.set_parameters([Parameter("planner.test_stall_s", value=1.5)])[0].successful
    handle = g.send_goal(_target_goal(-3.22, -2.65))
    # the test's precondition (the ~10 s motion leaves room for a loaded machine), said plainly where it fails
    assert g.arm.executing, "the first motion ended before the goal was accepted: its plan starts from rest"
    status, res, _ = g.goal_result(handle)
    assert status == GoalStatus.STATUS_SUCCEEDED, res.reason
    stages = [s for s, _ in published]
    assert stages.count("cspace") >= 2 and stages[-1] == "trajectory", stages      # the stages again
    progress = [p for _, p in published]
    assert progress == sorted(progress) and progress[-1] == max(progress), published


def _unstalled(g):
    """
    Plan the requests that come from now on without the stall.

    The plan in progress keeps its own (a request's settings are those at its arrival): it stalls
    until a newer request supersedes it, which ends it at once (the stall answers the cancel
    token, as the kernels do); the newer one plans without a stall.
    """
    from rclpy.parameter import Parameter
    assert g.planner.set_parameters([Parameter("planner.test_stall_s", value=0.0)])[0].successful


def test_newer_goal_aborts_the_older_with_a_reason(graph):
    # the stall far longer than a loaded machine takes to send the second goal: the first is still planning
    g = graph(scene_params("3dof", **{"planner.test_stall_s": STALL_S}), with_arm=False)
    _start(g)
    first = g.send_goal(_target_goal())
    g.wait(lambda: g.planner.state == "planning", 30, "the first goal planning")
    _unstalled(g)
    second = g.send_goal(_target_goal(-3.0, -2.8))
    status1, res1, _ = g.goal_result(first, timeout=SUPERSEDED_WITHIN_S)       # not after its stall
    assert status1 == GoalStatus.STATUS_ABORTED
    assert res1.error_code == R.SUPERSEDED and "superseded by request" in res1.reason, res1.reason
    assert "plan_capture goal" in res1.reason          # names the newer request
    assert len(res1.trajectory.points) == 0
    status2, res2, _ = g.goal_result(second)
    assert status2 == GoalStatus.STATUS_SUCCEEDED and res2.error_code == R.OK, res2.reason


def test_topic_target_supersedes_a_goal(graph):
    g = graph(scene_params("3dof", **{"planner.test_stall_s": STALL_S}), with_arm=False)
    _start(g)
    handle = g.send_goal(_target_goal())
    g.wait(lambda: g.planner.state == "planning", 30, "the goal planning")
    _unstalled(g)
    g.send_target(-3.0, -2.8)
    status, res, _ = g.goal_result(handle, timeout=SUPERSEDED_WITHIN_S)         # not after its stall
    assert status == GoalStatus.STATUS_ABORTED and res.error_code == R.SUPERSEDED
    assert "new target (-3.000, -2.800)" in res.reason, res.reason


def test_cancel_mid_plan_ends_the_plan_promptly(graph, record_property):
    g = graph(scene_params("3dof", **{"planner.test_stall_s": 30.0}), with_arm=False)
    _start(g)
    handle = g.send_goal(_target_goal())
    g.wait(lambda: g.planner.state == "planning", 30, "the goal planning")
    time.sleep(0.5)                                  # inside the stall
    t0 = time.monotonic()
    fut = handle.cancel_goal_async()
    g.wait(fut.done, PROMPT_BOUND_S, "the cancel response")      # (the result too is judged by this bound)
    assert len(fut.result().goals_canceling) == 1
    status, res, t_result = g.goal_result(handle, timeout=10)
    dt = t_result - t0
    print(f"\ncancel during a stalled plan: result after {dt:.3f} s")
    record_property("action_cancel_s", round(dt, 3))
    assert status == GoalStatus.STATUS_CANCELED and res.error_code == R.CANCELLED, res.reason
    assert dt < PROMPT_BOUND_S                       # not the 30 s stall
    assert g.n_trajs() == 0
    # the node goes on: the next goal plans (without the stall)
    from rclpy.parameter import Parameter
    assert g.planner.set_parameters([Parameter("planner.test_stall_s", value=0.0)])[0].successful
    status, res, _ = g.goal_result(g.send_goal(_target_goal()))
    assert status == GoalStatus.STATUS_SUCCEEDED, res.reason


@pytest.mark.parametrize("make_goal, fragments", [
    (lambda: _target_goal(math.nan, -2.6), ["goal.target_pose", "NaN"]),
    (lambda: _target_goal(frame="map"), ["goal.target_pose", "frame 'map'", "'world'"]),
    (lambda: _joint_goal(("attitude", "shoulder", "elbow"), np.radians([0.0, 200.0, 30.0])),
     ["goal.joint_goal", "shoulder", "outside its bounds"]),
    (lambda: _joint_goal(("attitude", "shoulder"), [0.0, 0.0]), ["goal.joint_goal", "missing joint", "elbow"]),
    (lambda: _without_flag(_joint_goal(("attitude", "shoulder", "elbow"), [0.0, 2.0, 1.0])),
     ["goal.target_pose", "joint_goal is filled but use_joint_goal is false"]),
], ids=["nan_pose", "wrong_frame", "joint_goal_out_of_bounds", "joint_goal_missing_joint", "joint_goal_flag_left_out"])
def test_bad_goal_is_aborted_with_the_reason_and_the_node_serves_on(graph, make_goal, fragments):
    g = graph(scene_params("3dof"), with_arm=False)
    _start(g)
    status, res, _ = g.goal_result(g.send_goal(make_goal()))
    assert status == GoalStatus.STATUS_ABORTED and res.error_code == R.INVALID_INPUT
    for frag in fragments:
        assert frag in res.reason, (frag, res.reason)
    assert g.n_trajs() == 0
    g.wait(lambda: g.level("input") == b"\x02", 30, "the input status ERROR")
    status, res, _ = g.goal_result(g.send_goal(_target_goal()))
    assert status == GoalStatus.STATUS_SUCCEEDED, res.reason


def test_a_joint_goal_that_moves_a_held_joint_is_refused_naming_it(graph):
    """
    The paper 2-DOF scene holds the attitude at 160.7°: a joint goal with it at 0° is refused naming it.

    It had been planned without it, OK, the attitude left where it was; a goal with the attitude at
    its lock plans to the goal.
    """
    g = graph(scene_params("2dof"), with_arm=False)
    _start(g)
    status, res, _ = g.goal_result(g.send_goal(_joint_goal(("attitude", "shoulder", "elbow"),
                                                           np.radians([0.0, 32.8, 76.5]))))
    assert status == GoalStatus.STATUS_ABORTED and res.error_code == R.INVALID_INPUT, res.reason
    assert "attitude at 0.0° (held at 160.7°): not a planned joint" in res.reason, res.reason
    status, res, _ = g.goal_result(g.send_goal(_joint_goal(("attitude", "shoulder", "elbow"),
                                                           np.radians([160.7, 32.8, 76.5]))))
    assert status == GoalStatus.STATUS_SUCCEEDED, res.reason
    np.testing.assert_allclose(res.trajectory.points[-1].positions, np.radians([32.8, 76.5]), atol=1e-9)


def test_goal_with_its_own_start(graph):
    """An explicit start plans from there (not from joint_states)."""
    g = graph(scene_params("2dof"), with_arm=False)
    _start(g)
    goal = _joint_goal(("shoulder", "elbow"), np.radians([32.8, 76.5]))
    start = np.radians([120.0, 80.0])
    goal.start = JointState(name=["shoulder", "elbow"], position=[float(v) for v in start])
    status, res, _ = g.goal_result(g.send_goal(goal))
    assert status == GoalStatus.STATUS_SUCCEEDED, res.reason
    np.testing.assert_allclose(res.trajectory.points[0].positions, start, atol=1e-9)
    np.testing.assert_allclose(res.trajectory.points[-1].positions, np.radians([32.8, 76.5]), atol=1e-9)
    # a topic target next: its plan, from the arm's joint state, is the first sent to the
    # controller (the plan from the goal's own start was not)
    g.send_target()
    _, first = next_plan(g, 0)
    np.testing.assert_allclose(first, g.scenario.start_rad, atol=1e-9,
                               err_msg="a plan from another start was sent to the controller")


def test_twenty_results_asked_at_once_are_all_answered(graph):
    """
    A client that sends 20 goals and then asks for their 20 results at once gets every one.

    With rclpy's defaults the result service kept 10 requests (a ROS user's client got 11 of 20
    answers; the others' clients waited until their own timeout).  The goals have their own start
    (the latest supersedes the others at once); the results are asked once every goal has ended.
    """
    g = graph(scene_params("2dof"), with_arm=False)
    _start(g)
    handles = []
    for k in range(20):
        goal = _joint_goal(("shoulder", "elbow"), np.radians([32.8, 76.5]))
        goal.start = JointState(name=["shoulder", "elbow"], position=[float(v) for v in np.radians([120.0, 80.0 - k])])
        handles.append(g.send_goal(goal))
    ended = (GoalStatus.STATUS_SUCCEEDED, GoalStatus.STATUS_ABORTED, GoalStatus.STATUS_CANCELED)
    g.wait(lambda: all(h.status in ended for h in handles), 60, "every goal's end")
    futures = [h.get_result_async() for h in handles]
    g.wait(lambda: all(f.done() for f in futures), 30, "the 20 results")
    got = [f.result() for f in futures]
    assert got[-1].status == GoalStatus.STATUS_SUCCEEDED, got[-1].result.reason
    assert all(r.result.error_code == R.SUPERSEDED for r in got[:-1] if r.status == GoalStatus.STATUS_ABORTED)


def test_a_goal_that_nothing_can_take_over_the_moving_arm_for_fails_join_failed_and_sends_nothing(graph, monkeypatch):
    """
    The arm moves; every timing that would take over from it is refused (injected): JOIN_FAILED, nothing sent.

    The session's own test covers the ladder; this one the action's answer: the goal aborted with
    ``JOIN_FAILED`` and its name, a reason that says what was tried and that nothing was sent, no
    trajectory on either topic, and the node serving on (the next goal, the injection gone,
    succeeds).  Oracles: the trajectories the test's subscribers received, the action protocol's
    statuses, the mock arm's own motion state.
    """
    import spacerobot_planner.session as session_module
    real = session_module.post_process

    def no_join(*args, join=None, **kwargs):
        if join is not None:
            raise ValueError("injected: no timing enters the arm's speed")
        return real(*args, join=join, **kwargs)

    g = graph(scene_params("3dof", **SLOW))         # with the mock arm: it follows the first trajectory
    g.action_client()                               # discovered now, not while the arm moves
    g.send_target()
    g.wait(lambda: g.n_trajs() >= 1 and _moving(g), 60, "the arm moving on the first trajectory")
    sent = g.n_trajs()
    with g.lock:
        attitudes = len(g.att_trajs)
    monkeypatch.setattr(session_module, "post_process", no_join)
    status, res, _ = g.goal_result(g.send_goal(_target_goal(-3.22, -2.65)))
    # the test's precondition (the ~10 s motion leaves room for a loaded machine), said plainly where it fails
    assert g.arm.executing, "the first motion ended before the goal was planned: its plan starts from rest"
    assert status == GoalStatus.STATUS_ABORTED, (status, res.reason)
    assert res.error_code == R.JOIN_FAILED and res.error_name == "join_failed", (res.error_code, res.error_name)
    for said in ("stopping on the executing path", "from the end of the executing", "injected", "nothing was sent"):
        assert said in res.reason, res.reason
    assert len(res.trajectory.points) == 0 and len(res.attitude_trajectory.points) == 0
    g.wait_log(": join_failed: ")
    assert g.n_trajs() == sent, "a trajectory was sent for a request that failed"
    with g.lock:
        assert len(g.att_trajs) == attitudes, "an attitude trajectory was sent for a request that failed"
    monkeypatch.setattr(session_module, "post_process", real)
    status, res, _ = g.goal_result(g.send_goal(_target_goal(-3.22, -2.65)))
    assert status == GoalStatus.STATUS_SUCCEEDED and res.error_code == R.OK, res.reason
    assert g.n_trajs() > sent


def _moving(g) -> bool:
    """Tell whether the last joint_states message has a joint moving (faster than 0.1°/s)."""
    with g.lock:
        last = g.states[-1][1] if g.states else None
    return last is not None and max((abs(v) for v in last.velocity), default=0.0) > math.radians(0.1)
