"""
What a request means and how it ends (issue 17).

Every accepted plan_capture goal ends with a result, also when the node goes away; the
latest accepted request from any channel is the goal that a replan or a parameter
change plans to; ~/replan answers with the plan's outcome.  Oracles: the action protocol
(statuses and results an action client receives), the trajectories on joint_trajectory,
the service's response.  Long plans are made long by ``planner.test_stall_s``.
"""

from __future__ import annotations

import math
import os
import signal
import subprocess
import sys
import threading
import time

import numpy as np
import pytest
import rclpy
from action_msgs.msg import GoalStatus
from lifecycle_msgs.msg import Transition
from lifecycle_msgs.srv import ChangeState
from rclpy.action import ActionClient
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from sensor_msgs.msg import JointState
from spacerobot_planner_interfaces.action import PlanCapture

from spacerobot_planner.ros.conversions import joint_state_msg

from conftest import CONFIG_DIR
from node_helpers import diag_list, diag_values, planned_positions, scene_params
from test_action import _joint_goal, _start, _target_goal

R = PlanCapture.Result
ENDED = (GoalStatus.STATUS_ABORTED, GoalStatus.STATUS_CANCELED)


class _Client:
    """An action client on a node and an executor of its own (it keeps spinning when the planner's stops)."""

    def __init__(self, ctx):
        self.node = rclpy.create_node("goal_client", context=ctx)
        self.ex = SingleThreadedExecutor(context=ctx)
        self.ex.add_node(self.node)
        self.action = ActionClient(self.node, PlanCapture, "plan_capture")
        self._stop = threading.Event()
        self.thread = threading.Thread(target=self._spin, daemon=True)
        self.thread.start()
        assert self.action.wait_for_server(30.0), "no plan_capture server"

    def _spin(self):
        while not self._stop.is_set() and self.ex.context.ok():
            self.ex.spin_once(timeout_sec=0.05)

    def send(self, goal, timeout=30):
        """Send a goal, ask for its result at once (as clients do); return the result future."""
        fut = self.action.send_goal_async(goal)
        _wait(fut.done, timeout, "the goal response")
        handle = fut.result()
        assert handle.accepted, "goal rejected"
        return handle.get_result_async()

    def close(self):
        self._stop.set()
        self.thread.join(5)
        self.action.destroy()
        self.ex.shutdown()
        self.node.destroy_node()


def _wait(cond, timeout, what):
    t0 = time.monotonic()
    while not cond():
        if time.monotonic() - t0 > timeout:
            raise AssertionError(f"timed out after {timeout} s waiting for: {what}")
        time.sleep(0.01)


@pytest.fixture
def stalled(graph):
    """
    Make a planner plan a goal of a client of its own, stalled for 120 s.

    Longer than the waits of a test that ends it (a service discovered, a transition: 90 s at most),
    and never waited for: each test ends the plan.  Yields the graph, the client and the goal's
    result future.
    """
    g = graph(scene_params("3dof", **{"planner.test_stall_s": 120.0}), with_arm=False)
    _start(g)
    client = _Client(g.ctx)
    result = client.send(_target_goal())
    g.wait(lambda: g.planner.state == "planning", 30, "the goal planning")
    yield g, client, result
    client.close()


def _assert_ended_with_a_reason(result, fragment):
    _wait(result.done, 30, "the goal's result")
    r = result.result()
    assert r.status in ENDED, r.status
    assert r.result.error_code == R.CANCELLED and fragment in r.result.reason, r.result.reason


# ================================================================== 3. every accepted goal ends with a result
@pytest.mark.parametrize("transition, fragment", [
    (Transition.TRANSITION_ACTIVE_SHUTDOWN, "shutting down"),
    (Transition.TRANSITION_DEACTIVATE, "deactivated"),
], ids=["shutdown", "deactivate"])
def test_goal_in_flight_gets_a_result_on_a_lifecycle_transition(stalled, transition, fragment):
    g, client, result = stalled
    cli = g.drv.create_client(ChangeState, "/spacerobot_planner/change_state")
    assert cli.wait_for_service(30.0)
    fut = cli.call_async(ChangeState.Request(transition=Transition(id=transition)))
    g.wait(fut.done, 60, "the transition")
    assert fut.result().success
    _assert_ended_with_a_reason(result, fragment)


def test_goal_in_flight_gets_a_result_when_the_node_is_destroyed(stalled):
    g, client, result = stalled
    g.destroy_planner()                      # as planner_node's main does after Ctrl-C
    _assert_ended_with_a_reason(result, "shutting down")


def test_goal_in_flight_gets_a_result_on_ctrl_c(tmp_path):
    """SIGINT to a planner_node process planning a client's goal: the client gets the result."""
    log = tmp_path / "planner_node.log"
    cmd = [sys.executable, "-c", "import signal, sys; signal.signal(signal.SIGINT, signal.default_int_handler); "
           "from spacerobot_planner.ros.planner_node import main; sys.exit(main())",
           "--ros-args", "--params-file", os.path.join(CONFIG_DIR, "paper_3dof.yaml"),
           "-p", "planner.test_stall_s:=30.0"]
    with open(log, "wb") as out:
        proc = subprocess.Popen(cmd, stdout=out, stderr=subprocess.STDOUT, start_new_session=True)
    ctx = Context()
    rclpy.init(context=ctx)
    client = None
    try:
        drv = rclpy.create_node("js_driver", context=ctx)
        pub_j = drv.create_publisher(JointState, "joint_states", 10)
        _wait(lambda: pub_j.get_subscription_count() > 0 or proc.poll() is not None, 60, "planner_node subscribed")
        assert proc.poll() is None, log.read_text()
        client = _Client(ctx)
        js = joint_state_msg(("attitude", "shoulder", "elbow"), np.radians([-90.0, 135.0, 90.0]))
        pub_j.publish(js)
        result = client.send(_target_goal())          # (if before the joint_states: it waits for them)
        t0 = time.monotonic()
        while "planning #" not in log.read_text():
            assert time.monotonic() - t0 < 30, "no plan started\n" + log.read_text()
            pub_j.publish(js)
            time.sleep(0.2)
        os.killpg(proc.pid, signal.SIGINT)
        try:
            _assert_ended_with_a_reason(result, "shutting down")
        except AssertionError as e:
            raise AssertionError(f"{e}\n{log.read_text()[-3000:]}") from None
        rc = proc.wait(30)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
        if client is not None:
            client.close()
        rclpy.shutdown(context=ctx)
    text = log.read_text()
    assert rc == 0 and "Traceback" not in text, text
    assert "Failed to send result response" not in text, text


# ================================================================== 4. the latest request is the goal
A = (-3.27, -2.60)          # the paper's target (topic)
B = (-3.0, -2.8)            # another reachable one (action goal)


def _plan_end(g, k):
    """Return the planned-joint positions at the end of trajectory ``k`` (its arm and attitude parts)."""
    g.wait(lambda: g.n_trajs() > k and len(g.att_trajs) > k, 30, f"trajectory {k + 1}")
    with g.lock:
        return planned_positions(g.scenario.robot, [g.trajs[k][1], g.att_trajs[k][1]])


def _status_of_the_last_request(g, timeout=30):
    """
    Return the planner status once it reports the session's latest request (its record).

    The record goes out on /diagnostics with the plan's trajectory on joint_trajectory: it may arrive
    after it, and the latest /diagnostics message until then reports the request before.
    """
    want, got = f"#{g.planner.session.gen}", []

    def reported():
        st = g.status("planner")
        if diag_values(st).get("request") == want:
            got.append(st)
        return bool(got)
    g.wait(reported, timeout, lambda: f"the planner status of request {want}: {diag_values(g.status('planner'))}")
    return got[0]


def _assert_same_posture(g, got, want, msg):
    """Angles compared modulo a turn for the periodic joints (the attitude), 1e-6 rad."""
    d = np.asarray(got, dtype=float) - np.asarray(want, dtype=float)
    for k, periodic in enumerate(g.scenario.robot.planned_periodic):
        if periodic:
            d[k] = math.remainder(d[k], 2 * math.pi)
    assert np.max(np.abs(d)) < 1e-6, f"{msg}: {np.round(np.degrees(got), 3)} vs {np.round(np.degrees(want), 3)} deg"


def _replan_by_service(g):
    from std_srvs.srv import Trigger
    cli = g.drv.create_client(Trigger, "/spacerobot_planner/replan")
    assert cli.wait_for_service(30.0)
    fut = cli.call_async(Trigger.Request())
    g.wait(fut.done, 60, "the ~/replan response")
    return fut.result()


def _change_margin(g):
    from rclpy.parameter import Parameter
    assert g.planner.set_parameters([Parameter("safety_margin_m", value=0.03)])[0].successful


@pytest.mark.parametrize("kind", ["target", "joint_goal"])
@pytest.mark.parametrize("then", [_change_margin, _replan_by_service], ids=["parameter_change", "replan"])
def test_after_an_action_goal_a_replan_plans_to_the_goals_goal(graph, kind, then):
    g = graph(scene_params("3dof"), with_arm=False)
    robot = g.scenario.robot
    _start(g)
    g.send_target(*A)                                      # topic: target A
    end_a = _plan_end(g, 0)
    if kind == "target":                                   # then an action goal: target B
        goal = _target_goal(*B)
    else:
        goal = _joint_goal(robot.planned_names, np.radians([150.0, 40.0, 70.0]))
    status, res, _ = g.goal_result(g.send_goal(goal))
    assert status == GoalStatus.STATUS_SUCCEEDED, res.reason
    end_b = _plan_end(g, 1)
    with pytest.raises(AssertionError):
        _assert_same_posture(g, end_b, end_a, "")            # B's goal is not A's
    then(g)                                                # a replan: to the goal's goal, not A
    end = _plan_end(g, 2)
    _assert_same_posture(g, end, end_b, "the replan went back to the older topic target")
    if kind == "target":
        assert diag_list(_status_of_the_last_request(g), "target_m") == list(B)


def test_a_goal_with_its_own_start_does_not_change_the_goal(graph):
    g = graph(scene_params("3dof"), with_arm=False)
    _start(g)
    g.send_target(*A)
    end_a = _plan_end(g, 0)
    goal = _target_goal(*B)
    goal.start = joint_state_msg(g.scenario.robot.planned_names, np.radians([-80.0, 130.0, 95.0]))
    status, res, _ = g.goal_result(g.send_goal(goal))
    assert status == GoalStatus.STATUS_SUCCEEDED, res.reason
    _change_margin(g)
    end = _plan_end(g, 1)                                  # planned, not executed: the next one is the replan
    _assert_same_posture(g, end, end_a, "the replan went to the goal with its own start")
    assert diag_list(_status_of_the_last_request(g), "target_m") == list(A)


# ================================================================== 5. ~/replan answers with the outcome
def _replan_client(g):
    from std_srvs.srv import Trigger
    cli = g.drv.create_client(Trigger, "/spacerobot_planner/replan")
    assert cli.wait_for_service(30.0)
    return cli


def _call(g, cli, timeout=60):
    from std_srvs.srv import Trigger
    fut = cli.call_async(Trigger.Request())
    g.wait(fut.done, timeout, "the ~/replan response")
    return fut.result()


def _published_trajectories(g, monkeypatch) -> list:
    """
    Return a list of the planner's publications on joint_trajectory from now on (their messages, as they go out).

    What the node has sent, not what the driver received: the trajectory travels on a topic of its
    own, and a response may overtake it on its way to the driver.
    """
    pub, sent = g.planner._pubs["traj"], []
    publish = pub.publish
    monkeypatch.setattr(pub, "publish", lambda msg: (publish(msg), sent.append(msg))[0])
    return sent


def test_replan_answers_with_the_plans_outcome(graph, monkeypatch):
    g = graph(scene_params("3dof"), with_arm=False)
    _start(g)
    cli = _replan_client(g)
    sent = _published_trajectories(g, monkeypatch)
    g.send_target(*A)
    g.wait(lambda: g.n_trajs() == 1, 30, "the first trajectory")
    resp = _call(g, cli)
    assert resp.success and "ok" in resp.message, resp.message
    assert len(sent) == 2, f"~/replan answered after {len(sent)} trajectories published, not 2 (its own the last)"
    g.wait(lambda: g.n_trajs() == 2, 30, "the replan's trajectory")
    g.send_target(3.0, 2.5)                                # out of the arm's reach
    g.wait(lambda: g.level("planner") == b"\x02", 30, "the failed request")
    resp = _call(g, cli)
    assert not resp.success, resp.message
    assert "goal_unreachable" in resp.message and "inverse-kinematics" in resp.message, resp.message


def test_replan_before_joint_states_says_it_is_queued(graph):
    g = graph(scene_params("3dof"), with_arm=False)
    resp = _call(g, _replan_client(g))
    assert not resp.success and "queued" in resp.message and "joint_states" in resp.message, resp.message


def test_replan_awaits_its_plan_and_the_node_serves_on(graph, monkeypatch):
    """
    A ~/replan call is answered when its plan ends, not before; meanwhile the node serves its inputs.

    Its plan stalls far longer than a loaded machine takes for what the test does meanwhile (a
    stall of 10 s had ended first); a second ~/replan, planned without the stall, then supersedes it
    at once (the stall answers the cancel token): the first call is answered with that outcome, the
    second with its plan's, once its trajectory was published.
    """
    from rclpy.parameter import Parameter
    g = graph(scene_params("3dof", **{"planner.test_stall_s": 60.0}), with_arm=False)
    _start(g)
    cli = _replan_client(g)
    sent = _published_trajectories(g, monkeypatch)
    from std_srvs.srv import Trigger
    fut = cli.call_async(Trigger.Request())
    g.wait(lambda: g.planner.state == "planning", 30, "the replan planning")
    g.send_target(frame="map")                             # rejected at once, while the plan stalls
    g.wait(lambda: g.level("input") == b"\x02", 30, "the input status ERROR during the replan")
    assert not fut.done(), f"the replan answered before its (stalled) plan ended: {fut.result()}"
    assert g.planner.set_parameters([Parameter("planner.test_stall_s", value=0.0)])[0].successful
    resp = _call(g, cli, timeout=30)                       # not the 60 s stall
    g.wait(fut.done, 30, "the first ~/replan response")
    assert not fut.result().success and "superseded by request" in fut.result().message, fut.result().message
    assert resp.success, resp.message
    assert len(sent) == 1, f"{len(sent)} trajectories published, not the second replan's one"
    g.wait(lambda: g.n_trajs() == 1, 30, "the second replan's trajectory")
