"""
planner_node + mock_arm_node in-process: closed loop, preemption, grids, bad input, responsiveness.

Each test gets a private rclpy Context and a SingleThreadedExecutor spinning in a
thread (test/node_helpers.py); no launch_testing.  Reliability under bad input,
floods, faults and shutdown: test_reliability_node.py.
"""

from __future__ import annotations

import json
import math
import time

import numpy as np
import pytest
from diagnostic_msgs.msg import DiagnosticStatus
from nav_msgs.msg import OccupancyGrid
from rclpy.parameter import Parameter
from std_srvs.srv import Trigger

from spacerobot_planner.ros.planner_node import GRID_QOS
from spacerobot_planner.ros.conversions import joint_state_msg

from node_helpers import (PROMPT_BOUND_S, angle_err_deg, assert_next_plan_grasps, joint_states_free, next_plan,
                          planned_positions, scene_params, wait_at_goal)


# ---------------------------------------------------------------------------- tests
@pytest.mark.parametrize("name", ["2dof", "3dof"])
def test_closed_loop_reaches_goal_collision_free(graph, name):
    g = graph(scene_params(name))
    g.send_target()
    goal = wait_at_goal(g, 60)
    assert g.n_trajs() == 1
    traj = g.trajs[0][1]
    robot = g.scenario.robot
    arm = [n for n in robot.planned_names if n != "attitude"]
    assert traj.joint_names == arm                       # the attitude goes elsewhere
    att = g.att_trajs[0][1] if "attitude" in robot.planned_names else None
    assert (att is None) == (name == "2dof") and (att is None or att.joint_names == ["attitude"])
    assert len(g.att_trajs) == (0 if att is None else 1)
    # first point = the arm's state when planning started (the scenario start)
    np.testing.assert_allclose(planned_positions(robot, [traj, att], 0), g.scenario.start_rad, atol=1e-9)
    n, free = joint_states_free(g)
    assert n > 20 and np.all(free), f"{np.count_nonzero(~free)} of {n} joint states collide"
    assert angle_err_deg(robot, g.arm.positions, goal) < 0.5
    assert not g.errors()
    st = g.diags[-1][1].status[0]
    values = {kv.key: kv.value for kv in st.values}
    assert st.level == DiagnosticStatus.OK and values["state"] == "idle"
    assert "time_field_ms" in values and float(values["min_clearance_m"]) > 0.0
    assert g.markers, "no path markers"


def test_second_target_preempts(graph):
    g = graph(scene_params("3dof"))
    g.send_target()
    g.wait(lambda: g.arm.executing, 30, "the first trajectory executing")
    first_goal = g.planner.last_result.goal_rad.copy()
    time.sleep(0.3)
    t_switch = time.monotonic()
    g.send_target(-3.0, -2.8)
    g.wait(lambda: g.n_trajs() >= 2 and len(g.att_trajs) >= 2, 30, "a second trajectory")
    second = planned_positions(g.scenario.robot, [g.trajs[1][1], g.att_trajs[1][1]])
    goal2 = g.planner.last_result.goal_rad
    assert angle_err_deg(g.scenario.robot, g.scenario.robot.full(second), goal2) < 1e-6
    assert np.degrees(np.max(np.abs(goal2 - first_goal))) > 5.0
    wait_at_goal(g, 30)
    assert angle_err_deg(g.scenario.robot, g.arm.positions, goal2) < 0.5
    n, free = joint_states_free(g, since=t_switch)
    assert n > 5 and np.all(free)
    assert g.n_trajs() == 2


def test_potential_grid_late_subscriber(graph):
    flat = scene_params("2dof")
    g = graph(flat)
    g.send_target()
    g.wait(lambda: g.planner.last_result is not None, 60, "a plan")
    time.sleep(0.3)
    got = {}
    for topic in ("potential_grid", "cspace_grid"):         # late subscribers
        g.drv.create_subscription(OccupancyGrid, topic, lambda m, t=topic: got.__setitem__(t, m), GRID_QOS)
    g.wait(lambda: len(got) == 2, 10, "both grids for a late subscriber")
    pot, cs = got["potential_grid"], got["cspace_grid"]
    grid = g.planner.last_result.cspace.grid
    assert (pot.info.width, pot.info.height) == (181, 181) == grid.shape
    assert math.isclose(pot.info.resolution, math.radians(2.0), rel_tol=1e-6)
    assert math.isclose(pot.info.origin.position.x, -math.pi, rel_tol=1e-6)
    p = np.array(pot.data).reshape(pot.info.height, pot.info.width)     # [y, x]
    c = np.array(cs.data).reshape(cs.info.height, cs.info.width)
    assert set(np.unique(c)) <= {0, 100}
    np.testing.assert_array_equal(p == 100, c == 100)
    np.testing.assert_array_equal(c.T == 100, g.planner.last_result.cspace.occupied)
    ix, iy = grid.node_of(g.planner.last_result.goal_rad)
    assert p[iy, ix] == p.min() == 0
    assert p[c == 0].max() <= 99


def test_bad_input_then_good_request(graph):
    g = graph(scene_params("3dof"), with_arm=False)
    robot = g.scenario.robot

    def js(names=robot.joint_names, q=None, cond=None):
        q = robot.full(g.scenario.start_rad) if q is None else q
        g.send_joint_state(joint_state_msg(names, q), cond)

    js()

    def expect_error(action, fragment):
        # the one that names it (an ERROR still set is published again every diagnostics period)
        e0 = len(g.errors())
        action()
        g.wait(lambda: any(fragment in m for _, m in g.errors()[e0:]), 30,
               lambda: f"a diagnostics error for {fragment}; the errors since: {[m for _, m in g.errors()[e0:]]}")

    expect_error(lambda: g.send_target(math.nan, -2.6), "NaN")
    expect_error(lambda: g.send_target(frame="map"), "frame 'map'")
    expect_error(lambda: g.send_target(3.0, 2.5), "out of the arm's reach")
    expect_error(lambda: js(names=("attitude", "shoulder"), q=[0.0, 0.0],
                            cond=lambda: g.planner.session.joint_refused is not None), "missing joint")
    js()

    def bad_param():
        res = g.planner.set_parameters([Parameter("safety_margin_m", value=-1.0)])[0]
        assert not res.successful and "safety_margin_m" in res.reason
    expect_error(bad_param, "safety_margin_m")

    def bad_array():
        res = g.planner.set_parameters([Parameter("grid.cells", value=[36, 36])])[0]
        assert not res.successful and "grid.cells" in res.reason
    expect_error(bad_array, "grid.cells")

    # the node keeps serving: a good target plans, and its plan is the first published (none for
    # the bad inputs above)
    g.send_target()
    assert_next_plan_grasps(g, 0, 0, -3.27, -2.60)
    g.wait(g.all_ok, 5, "diagnostics back to OK")
    # a runtime parameter change validates and replans
    res = g.planner.set_parameters([Parameter("safety_margin_m", value=0.03)])[0]
    assert res.successful
    g.wait(lambda: g.n_trajs() == 2, 30, "a trajectory after the parameter change")
    # ~/replan from a new joint state (field cached)
    cli = g.drv.create_client(Trigger, "/spacerobot_planner/replan")
    assert cli.wait_for_service(30.0)
    fut = cli.call_async(Trigger.Request())
    g.wait(fut.done, 30, "~/replan response")
    assert fut.result().success
    g.wait(lambda: g.n_trajs() == 3, 30, "a trajectory after ~/replan")
    assert "cspace" in g.planner.last_result.cached and "field" in g.planner.last_result.cached
    # ... planned in the worker thread from what the planning process sent (worker.HybridBackend)
    g.wait_log("planned in the worker thread", 30)


def test_joint_goal(graph):
    g = graph(scene_params("2dof"))
    goal = np.radians([32.8, 76.5])
    g.wait(lambda: g.planner._joint_q is not None, 10, "joint_states seen")
    g.pub_goal.publish(joint_state_msg(("shoulder", "elbow", "extra"), [*goal, 0.0]))
    got = wait_at_goal(g, 60)
    np.testing.assert_allclose(got, goal, atol=1e-9)


def test_executor_responsive_during_slow_plan(graph):
    g = graph(scene_params("3dof", **{"planner.test_stall_s": 30.0}))   # a long plan (stalled)
    g.send_target()
    g.wait(lambda: g.planner.state == "planning", 10, "planning started")
    t0 = time.monotonic()
    time.sleep(3.0)
    t1 = time.monotonic()
    assert g.planner.state == "planning", "the stalled plan finished too quickly to test anything"
    # the executor keeps delivering the arm's 50 Hz joint_states while the plan runs: no gap near a hang (a
    # blocked executor sends none for the 30 s stall).  A bound on gaps, not on the rate over the window: a
    # loaded machine slows the stream, it does not stop it
    with g.lock:
        arrivals = [t for t, _ in g.states if t0 <= t <= t1]
    gaps = np.diff([t0, *arrivals, t1])
    assert len(arrivals) >= 4 and gaps.max() < 1.5, \
        (f"{len(arrivals)} joint_states reached the driver in 3 s of the plan (50 Hz sent), "
         f"largest gap {gaps.max():.2f} s")
    t_close = time.monotonic()
    g.close()
    assert time.monotonic() - t_close < PROMPT_BOUND_S, "shutdown did not stop the long (30 s) plan promptly"


def test_diagnostics_describe_only_the_last_finished_request(graph):
    """
    A failed request, then rejected input, then a good target.

    The input status is OK again and the planner status carries the good request's keys only;
    reasons whole.
    """
    from node_helpers import diag_values
    g = graph(scene_params("3dof"), with_arm=False)
    robot = g.scenario.robot
    g.send_joint_state(joint_state_msg(robot.joint_names, robot.full(g.scenario.start_rad)))
    # 1. a request that fails: its planner status names the reason, whole
    g.send_target(3.0, 2.5)
    g.wait(lambda: g.level("planner") == DiagnosticStatus.ERROR, 15, "the failed request")
    failed = g.status("planner")
    fv = diag_values(failed)
    assert fv["code"] == "goal_unreachable"
    assert fv["reason"].endswith("(no inverse-kinematics solution within the joint bounds at approach angles "
                                 "within ±5° of the handle's normal (grasp.max_approach_error_deg))"), fv["reason"]
    assert failed.message.endswith(fv["reason"]) and "..." not in failed.message
    assert g.level("input") == DiagnosticStatus.OK
    # 2. rejected input: the input status, with its age; the planner status is unchanged
    g.send_target(frame="map")
    g.wait(lambda: g.level("input") == DiagnosticStatus.ERROR, 10, "the input status ERROR")
    iv = diag_values(g.status("input"))
    assert iv["source"] == "target_pose" and "frame 'map'" in iv["reason"] and float(iv["age_s"]) >= 0.0
    assert diag_values(g.status("planner"))["request"] == fv["request"]
    # 3. a good target: input OK, planner status = that request's keys only
    g.send_target()
    g.wait(lambda: g.n_trajs() == 1, 30, "a trajectory for the good target")
    g.wait(g.all_ok, 5, "every status OK")
    pv = diag_values(g.status("planner"))
    iv = diag_values(g.status("input"))
    assert set(iv) == {"rejected_total"} and iv["rejected_total"] == "1"
    assert pv["request"] != fv["request"] and pv["code"] == "ok"
    ok_keys = {"state", "controller_switch", "controller_switch_source", "request", "request_reason", "target_m",
               "target_yaw_deg", "code", "goal_deg",
               "min_clearance_m", "trajectory_duration_s", "trajectory_points", "cached", "solver", "latency_s",
               "field_converged", "field_bands", "repairs", "approach_error_deg", "trajectory_dense_points",
               "trajectory_retimings", "joined_moving_arm", "trajectory_clearance_m", "trajectory_certified"}
    timing_keys = {k for k in pv if k.startswith("time_") and k.endswith("_ms")}
    assert timing_keys and set(pv) == ok_keys | timing_keys, set(pv) ^ (ok_keys | timing_keys)
    assert json.loads(pv["target_m"]) == [-3.27, -2.6]
    assert pv["field_converged"] == "true" and float(pv["approach_error_deg"]) < 5.0
    assert int(pv["trajectory_points"]) < int(pv["trajectory_dense_points"])     # resampled
    assert int(pv["trajectory_retimings"]) >= 0
    assert pv["trajectory_certified"] == "true" and float(pv["trajectory_clearance_m"]) > 0.02   # the file's margin


def test_grids_are_in_the_grid_frame(graph):
    g = graph(scene_params("2dof", **{"grid_frame": "joint_space"}), with_arm=False)
    robot = g.scenario.robot
    g.send_joint_state(joint_state_msg(robot.joint_names, robot.full(g.scenario.start_rad)))
    g.send_target()
    g.wait(lambda: g.planner.last_result is not None, 60, "a plan")
    got = {}
    for topic in ("potential_grid", "cspace_grid"):
        g.drv.create_subscription(OccupancyGrid, topic, lambda m, t=topic: got.__setitem__(t, m), GRID_QOS)
    g.wait(lambda: len(got) == 2, 10, "both grids")
    assert {m.header.frame_id for m in got.values()} == {"joint_space"}
    g.wait(lambda: g.markers, 5, "markers")
    assert all(m.header.frame_id == "world" for m in g.markers[-1][1].markers)   # workspace things stay


def test_an_in_process_node_leaves_the_garbage_collector_alone(graph):
    """
    Only a node that owns its process (main()) freezes start-up objects out of the collector.

    A node built in a test process must not: frozen garbage (an earlier test's rclpy context
    and its DDS participant) is never freed, and in a full test run the participants left
    behind kept a later node process from being discovered.
    """
    import gc
    import weakref

    class Marked:                       # a cycle, garbage before the node is configured
        pass

    a, b = Marked(), Marked()
    a.other, b.other = b, a
    gone = weakref.ref(a)
    del a, b
    frozen = gc.get_freeze_count()
    g = graph(scene_params("2dof"), with_arm=False)
    g.wait(lambda: g.planner.last_result is None, 5, "the node")       # configured and active
    assert gc.get_freeze_count() == frozen
    gc.collect()
    assert gone() is None, "garbage made before the node's configure was frozen, never freed"


def test_at_the_goal_no_trajectory_and_it_says_so(graph):
    g = graph(scene_params("2dof"))
    g.send_target()
    wait_at_goal(g, 60)
    n0 = g.n_trajs()
    cli = g.drv.create_client(Trigger, "/spacerobot_planner/replan")
    assert cli.wait_for_service(30.0)
    fut = cli.call_async(Trigger.Request())
    g.wait(fut.done, 30, "~/replan response")
    from node_helpers import diag_values
    g.wait(lambda: diag_values(g.status("planner")).get("at_goal") == "true", 10, "at_goal on /diagnostics")
    st = g.status("planner")
    assert st.level == DiagnosticStatus.OK and "request #" in st.message
    values = diag_values(st)                  # no trajectory went out: none is described
    assert values["trajectory_points"] == "0" and values["trajectory_duration_s"] == "0.000", values
    assert values["trajectory_dense_points"] == "0" and values["trajectory_retimings"] == "0", values
    assert g.n_trajs() == n0
    # a joint goal next: its plan is the first published since (none went out at the goal)
    away = np.radians([120.0, 80.0])
    g.pub_goal.publish(joint_state_msg(("shoulder", "elbow"), away))
    end, _ = next_plan(g, n0)
    np.testing.assert_allclose(end, away, atol=1e-9, err_msg="a trajectory was published at the goal")
    g.wait_log("already at the goal", 10)


@pytest.mark.parametrize("period_s, stall_s, expect_some", [(0.5, 0.3, True), (0.0, 3.0, False)],
                         ids=["min_period_0.5s", "latest_wins"])
def test_a_stream_of_targets_still_gets_trajectories(graph, period_s, stall_s, expect_some):
    """
    Targets drifting 2 cm/s at 20 Hz while each plan takes ``stall_s`` at least (a stall).

    Latest-wins alone publishes nothing; with replan.min_publish_period_s a plan is let finish once
    no trajectory went out for that long.  (Latest-wins' plans take 3 s: a pause of the test's
    sends as long as a plan, on a loaded machine, would let one finish; 1 s had been near a loaded
    machine's pauses.)
    """
    params = {"planner.test_stall_s": stall_s, "replan.min_publish_period_s": period_s,
              "replan.target_tolerance_m": 0.0}
    g = graph(scene_params("3dof", **params))
    g.wait(lambda: g.planner._joint_q is not None, 10, "joint_states seen")
    t0 = time.monotonic()
    k = 0
    while time.monotonic() - t0 < 4.0:
        g.send_target(-3.27 + 0.02 * 0.05 * k, -2.60)
        k += 1
        time.sleep(0.05)
    n_stream = g.n_trajs()
    print(f"\nstream of {k} targets in 4 s, min publish period {period_s} s: {n_stream} trajectories")
    if expect_some:
        assert n_stream >= 2
    else:
        assert n_stream == 0
    g.wait(lambda: g.n_trajs() > n_stream, 30, "the last target's trajectory after the stream")


def test_servicer_trajectory_keeps_the_wheel_limits(graph):
    """
    config/servicer_3dof.yaml through the node.

    The wheel momentum and torque of the planned trajectory, recomputed in the test from forward
    kinematics (test_dynamics' momentum sum), stay within the file's limits, and /diagnostics
    reports the reaction: its peak torque is the controller's motion's, within the chain's
    tolerance of the limit (``adapters.CONTROLLER_TOL``, 0.1 %: the quintics sampled).
    """
    from node_helpers import diag_values
    from test_dynamics import _load_oracle
    from spacerobot_planner.spacecraft import MassProperties
    g = graph(scene_params("servicer"), with_arm=False)
    robot = g.scenario.robot
    g.send_joint_state(joint_state_msg(robot.joint_names, robot.full(g.scenario.start_rad)))
    g.send_target()
    g.wait(lambda: g.planner.last_trajectory is not None, 60, "a trajectory")
    traj = g.planner.last_trajectory
    q = robot.full(traj.positions_rad)
    qd, qdd = np.zeros_like(q), np.zeros_like(q)
    idx = list(robot.planned_joints)
    qd[:, idx], qdd[:, idx] = traj.velocities_rad_s, traj.accelerations_rad_s2
    h, tau = _load_oracle(robot, MassProperties(), q, qd, qdd)
    assert np.max(np.abs(h)) <= 50.0 * (1 + 1e-6) and np.max(np.abs(tau)) <= 0.5 * (1 + 1e-6)
    g.wait(lambda: "peak_wheel_momentum_Nms" in diag_values(g.status("planner")), 10, "the reaction")
    pv = diag_values(g.status("planner"))
    assert float(pv["peak_wheel_torque_Nm"]) <= 0.5 * (1 + 1e-3) and pv["acs_mode"] == "held"


def _params_file(flat, path):
    """Write a flat dotted parameter dict as a ROS 2 parameter file (one ``/**`` section)."""
    import yaml
    nested = {}
    for name, value in flat.items():
        *parents, leaf = name.split(".")
        d = nested
        for p in parents:
            d = d.setdefault(p, {})
        d[leaf] = list(value) if isinstance(value, (list, tuple)) else value
    path.write_text(yaml.safe_dump({"/**": {"ros__parameters": nested}}))
    return str(path)


def test_the_cli_json_carries_the_trajectory_the_node_publishes(graph, tmp_path):
    """
    One scenario file, one request: from rest at the scenario's start to its target.

    ``spacerobot-plan --json`` carries the node's published trajectory point for point (same
    times and positions, both parts): the CLI and the node share the chain after the path.
    """
    from spacerobot_planner.tools.cli import main as cli_main
    flat = {k: v for k, v in scene_params("3dof").items() if k != "scenario.goal_deg"}   # the goal: the target's
    g = graph(flat, with_arm=False)
    robot = g.scenario.robot
    g.send_joint_state(joint_state_msg(robot.joint_names, robot.full(g.scenario.start_rad)))
    g.send_target(*g.scenario.scene.target.center_m)
    g.wait(lambda: g.n_trajs() == 1 and len(g.att_trajs) == 1, 60, "the trajectory")
    with g.lock:
        published = {"joint_trajectory": g.trajs[0][1], "attitude_trajectory": g.att_trajs[0][1]}
    js = tmp_path / "plan.json"
    assert cli_main(["--params-file", _params_file(flat, tmp_path / "scene.yaml"), "--json", str(js), "--quiet"]) == 0
    doc = json.loads(js.read_text())
    for topic, msg in published.items():
        part = doc["published_trajectory"][topic]
        assert part["joint_names"] == list(msg.joint_names)
        times = [p.time_from_start.sec + 1e-9 * p.time_from_start.nanosec for p in msg.points]
        np.testing.assert_allclose(part["times_s"], times, rtol=0, atol=1e-9)
        np.testing.assert_array_equal(part["positions_rad"], [list(p.positions) for p in msg.points])
        np.testing.assert_array_equal(part["velocities_rad_s"], [list(p.velocities) for p in msg.points])
    dense = doc["dense_trajectory"]
    assert len(dense["times_s"]) > len(doc["published_trajectory"]["joint_trajectory"]["times_s"])
    assert dense["times_s"][-1] == doc["published_trajectory"]["joint_trajectory"]["times_s"][-1]
