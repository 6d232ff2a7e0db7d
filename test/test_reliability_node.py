"""
Issue 5, node side.

Bad input at every entrance, a target_pose flood, faults inside the worker, shutdown during a long
plan.

test_node.py already covers a NaN position, a wrong frame, an unreachable target, a
missing joint and rejected parameters; this file adds the rest of the table and the
load/fault/shutdown cases.  Figures (flood RSS, joint_states gaps, shutdown times) are
printed (``pytest -s``) and recorded as junit properties; only the explicit bounds
of the issue are asserted.  Stamps are not used by the node (no staleness check):
messages with zero stamps are accepted, as every message sent here shows.

Fault injection needs no hook in the node: in-thread mode monkeypatches Planner.plan or
a pipeline stage; child-process mode gives the first job a solver name the child's
Planner refuses with an exception, or kills the child with SIGKILL.
"""

from __future__ import annotations

import dataclasses
import math
import os
import re
import signal
import subprocess
import sys
import threading
import time

import numpy as np
import pytest
import rclpy
from diagnostic_msgs.msg import DiagnosticStatus
from geometry_msgs.msg import PoseStamped
from rcl_interfaces.srv import SetParameters
from rclpy.context import Context
from rclpy.parameter import Parameter
from sensor_msgs.msg import JointState

from spacerobot_planner import planner as planner_mod
from spacerobot_planner.ik import grasp_ik
from spacerobot_planner.config import scenario_from_params
from spacerobot_planner.planner import Planner
from spacerobot_planner.ros.executor import NodeExecutor
from spacerobot_planner.ros.planner_node import PlannerNode, params_to_overrides, spin_until_shutdown
from spacerobot_planner.ros.conversions import joint_state_msg
from spacerobot_planner.scene import Target

from node_helpers import (PLAN_CANCELLED_AT_SHUTDOWN, PROMPT_BOUND_S, START_TIMEOUT_S, Graph, assert_next_plan_grasps,
                          child_pids, diag_list, diag_values, pid_alive, planned_positions, rss_mb, scene_params)
from conftest import CONFIG_DIR

FLOOD_S = 10.0            # the issue's 10 s
FLOOD_HZ = 200.0
GOOD_TARGETS = [(-3.27, -2.60, 0.0), (-3.0, -2.8, 0.0)]   # alternated: each is a new target
LONG = {"planner.test_stall_s": 30.0}   # a long plan: the planning process stalls (uninterruptible) 30 s


def _threads():
    return {t for t in threading.enumerate() if t.is_alive()}


def _leftover_threads(before):
    return [t.name for t in _threads() - before]


# ================================================================== bad input table
def _set_param_via_service(g, name, value):
    """Set one parameter through the node's ~/set_parameters service (as `ros2 param set`)."""
    cli = g.drv.create_client(SetParameters, "/spacerobot_planner/set_parameters")
    assert cli.wait_for_service(30.0)
    fut = cli.call_async(SetParameters.Request(parameters=[Parameter(name, value=value).to_parameter_msg()]))
    g.wait(fut.done, 30, "set_parameters response")
    g.drv.destroy_client(cli)
    return fut.result().results[0]


class TableGraph(Graph):
    """One planner (3-DOF, 36³, default child process, no arm) for the whole table."""

    def __init__(self):
        super().__init__(scene_params("3dof"), with_arm=False)
        self.robot = self.scenario.robot
        self.good = 0
        self.good_js()

    def good_js(self):
        """Publish the arm's state until the planner took it (best effort: after a refused one, plans wait for it)."""
        self.send_joint_state(joint_state_msg(self.robot.joint_names, self.robot.full(self.scenario.start_rad)))

    def next_good_target(self):
        self.good += 1
        x, y, yaw = GOOD_TARGETS[self.good % 2]
        self.send_target(x, y, yaw)
        return x, y


@pytest.fixture(scope="class")
def table():
    g = TableGraph()
    yield g
    g.close()


def _quat_about_x(deg):
    return (math.sin(math.radians(deg) / 2), 0.0, 0.0, math.cos(math.radians(deg) / 2))


def _huge_grid(g):
    """grid.cells beyond planner.max_grid_nodes, through the parameter service."""
    child = g.planner._backend.proc.pid
    before = rss_mb(), rss_mb(child)
    res = _set_param_via_service(g, "grid.cells", [1000, 1000, 1000])     # 1000·1001² ≈ 1e9 nodes
    assert not res.successful and "planner.max_grid_nodes" in res.reason, res.reason
    time.sleep(0.3)
    grew = rss_mb() - before[0], rss_mb(child) - before[1]
    print(f"\nhuge grid refused: RSS growth test process {grew[0]:+.1f} MB, planning process {grew[1]:+.1f} MB")
    assert grew[0] < 200.0 and grew[1] < 200.0, f"RSS grew by {grew} MB: the grid was allocated"
    assert list(g.planner.get_parameter("grid.cells").value) == [36, 36, 36]


def _refused(g):
    """Return a test: the planner refused a joint state since the last good one (the table sends good ones between)."""
    return lambda: g.planner.session.joint_refused is not None


def _goal_out_of_bounds(g):
    g.pub_goal.publish(joint_state_msg(("attitude", "shoulder", "elbow"), np.radians([0.0, 200.0, 30.0])))


# (case id, action(g), fragments that the ERROR's message must contain)
BAD_INPUT = [
    ("inf_position", lambda g: g.send_target(math.inf, -2.6), ["target_pose", "NaN or inf"]),
    ("nan_orientation", lambda g: g.send_target(quat=(0.0, 0.0, math.nan, 1.0)), ["NaN or inf"]),
    ("quaternion_norm_2", lambda g: g.send_target(quat=(0.0, 0.0, 0.0, 2.0)), ["not a unit quaternion", "norm 2"]),
    ("quaternion_zero", lambda g: g.send_target(quat=(0.0, 0.0, 0.0, 0.0)), ["not a unit quaternion", "norm 0"]),
    ("quaternion_norm_1.05", lambda g: g.send_target(quat=(0.0, 0.0, 0.0, 1.05)), ["not a unit quaternion"]),
    ("tilted_5deg", lambda g: g.send_target(quat=_quat_about_x(5.0)), ["tilted out of the plane"]),
    ("joint_states_length_mismatch",
     lambda g: g.send_joint_state(JointState(name=["attitude", "shoulder", "elbow"], position=[0.0, 0.1]), _refused(g)),
     ["joint_states", "3 names but 2 positions"]),
    ("joint_states_nan",
     lambda g: g.send_joint_state(joint_state_msg(("attitude", "shoulder", "elbow"), [0.0, math.nan, 0.2]),
                                  _refused(g)),
     ["joint_states", "shoulder", "not finite"]),
    ("goal_joint_state_length_mismatch",
     lambda g: g.pub_goal.publish(JointState(name=["shoulder", "elbow"], position=[0.1])),
     ["goal_joint_state", "2 names but 1 positions"]),
    ("goal_joint_state_out_of_bounds", _goal_out_of_bounds,
     ["goal_joint_state", "shoulder", "outside its bounds"]),
    ("huge_grid_budget", _huge_grid, ["grid.cells", "planner.max_grid_nodes", "4000000"]),
]


class TestBadInput:
    """The bad-input table against one planner (class-scoped: gone before the other tests)."""

    @pytest.mark.parametrize("action, fragments", [c[1:] for c in BAD_INPUT], ids=[c[0] for c in BAD_INPUT])
    def test_bad_input_is_an_error_then_the_next_good_target_plans(self, table, action, fragments):
        g = table
        g.good_js()
        n0, na0, e0 = g.n_trajs(), len(g.att_trajs), len(g.errors())
        action(g)
        g.wait(lambda: len(g.errors()) > e0, 15, f"a diagnostics ERROR with {fragments}")
        msg = g.errors()[-1][1]
        for frag in fragments:
            assert frag in msg, f"{frag!r} not in {msg!r}"
        st = g.error_diags()[-1][1]
        assert diag_values(st)["code"] in ("invalid_input", "invalid_parameter")
        # the node keeps serving: the next good target's plan is the first published since
        # (nothing went out for the bad input)
        g.good_js()
        x, y = g.next_good_target()
        assert_next_plan_grasps(g, n0, na0, x, y)
        g.wait(g.all_ok, 5, "diagnostics back to OK")

    @pytest.mark.parametrize("scale, tilt_deg, yaw_deg", [(1.005, 0.0, -3.0), (0.995, 0.5, -6.0)],
                             ids=["norm_1.005", "norm_0.995_tilt_0.5deg"])
    def test_almost_unit_quaternion_is_normalised_and_planned(self, table, scale, tilt_deg, yaw_deg):
        """A norm within 1 % of 1 (and a tilt within 1°) is accepted: normalised, planned."""
        g = table
        g.good_js()
        n0, e0 = g.n_trajs(), len(g.errors())
        yaw = math.radians(yaw_deg)                 # reachable yaws of the paper's target position
        # yaw about z, then a small tilt about the rotated x axis
        qz = np.array([0.0, 0.0, math.sin(yaw / 2), math.cos(yaw / 2)])
        qx = np.array(_quat_about_x(tilt_deg))
        x1, y1, z1, w1 = qz
        x2, y2, z2, w2 = qx
        q = np.array([w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2, w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
                      w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2, w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2])
        g.send_target(-3.27, -2.60, quat=tuple(scale * q))
        g.wait(lambda: g.n_trajs() == n0 + 1, 30, "a trajectory for the almost-unit quaternion")
        assert len(g.errors()) == e0
        g.wait(lambda: diag_values(g.diags[-1][1].status[0]).get("state") == "idle", 5, "idle diagnostics")
        vals = diag_values(g.diags[-1][1].status[0])
        assert abs(float(vals["target_yaw_deg"]) - math.degrees(yaw)) < 0.05, vals


# ================================================================== flood
def _random_target(rng):
    r, a, yaw = rng.uniform(3.0, 5.0), rng.uniform(-math.pi, math.pi), rng.uniform(-math.pi, math.pi)
    return r * math.cos(a), r * math.sin(a), yaw


def _random_graspable_target(rng, scenario):
    """
    Draw a random target with a collision-free grasp posture.

    A random target whose grasp point has a collision-free IK posture (it can still fail to plan,
    e.g. when the arm's current posture collides with it).
    """
    while True:
        x, y, yaw = _random_target(rng)
        scene = scenario.scene.with_target(Target(center_m=(x, y), yaw_rad=yaw))
        if grasp_ik(scenario.robot, scene):
            return x, y, yaw


def test_target_pose_flood(graph, record_property):
    # with the mock arm at 50 Hz.  Every trajectory stamped 1 s ahead (default 0.35 s): the flood starves the
    # graph's one executor thread, which also hands the arm its trajectories, and one that reaches the arm after
    # its stamp takes over at its arrival (joint_states stopped 0.3 s in a fresh clone's run beside a benchmark)
    g = graph(scene_params("3dof", **{"trajectory.start_lead_s": 1.0}))
    robot = g.scenario.robot
    g.send_target()                            # warm-up: the child imports, numba loads
    g.wait(lambda: g.n_trajs() >= 1, 60, "the warm-up trajectory")
    child = g.planner._backend.proc.pid
    assert child in child_pids(), "the planning process is not a child of this process"
    rss0 = rss_mb(), rss_mb(child)
    child_peak = rss0[1]
    rng = np.random.default_rng(5)
    n_traj0, n_err0 = g.n_trajs(), len(g.errors())
    t_start = time.monotonic()
    period = 1.0 / FLOOD_HZ
    sent = 0
    next_t = t_start
    last = None
    next_rss = t_start
    gen0 = g.planner._gen
    n_msgs = int(round(FLOOD_S * FLOOD_HZ))
    for i in range(n_msgs):
        # random poses, many unreachable; the last one graspable, so that both the flood's
        # failures and a final trajectory are exercised
        last = _random_target(rng) if i < n_msgs - 1 else _random_graspable_target(rng, g.scenario)
        g.send_target(*last)
        sent += 1
        now = time.monotonic()
        if now >= next_rss:
            child_peak = max(child_peak, rss_mb(child))
            next_rss = now + 0.25
        next_t += period
        time.sleep(max(0.0, next_t - time.monotonic()))
    t_end = time.monotonic()
    n_traj_flood = g.n_trajs() - n_traj0
    g.wait(lambda: g.planner._gen > gen0 and g.planner._requested_target is not None
           and math.hypot(g.planner._requested_target.center_m[0] - last[0],
                          g.planner._requested_target.center_m[1] - last[1]) < 1e-9, 30,
           "the last target received")
    received = g.planner._gen - gen0

    # the outcome for the LAST target: a trajectory whose end grasps it, or an ERROR naming it
    lx, ly, lyaw = last
    grasp = Target(center_m=(lx, ly), yaw_rad=lyaw).grasp_point_m

    def names_last(status):
        t = diag_list(status, "target_m")
        return t is not None and math.hypot(t[0] - lx, t[1] - ly) < 1e-3 and \
            abs(math.remainder(math.radians(float(diag_values(status)["target_yaw_deg"])) - lyaw,
                               2 * math.pi)) < 1e-3

    def settled(last_n=1):
        with g.lock:
            ds = [d.status[0] for t, d in g.diags if t >= t_end][-last_n:]
        return len(ds) == last_n and all(
            diag_values(st).get("state") in ("idle", "failed") and names_last(st) for st in ds)

    # the last target's outcome, and it stays: three diagnostics in a row (two heartbeats) name it
    # (a later outcome replacing it never settles this)
    g.wait(lambda: settled(3), 30, "the outcome of the last target on /diagnostics, for two heartbeats")
    with g.lock:
        final = g.diags[-1][1].status[0]
        last_traj = g.trajs[-1]
        last_att = g.att_trajs[-1][1] if g.att_trajs else None
        states = [t for t, _ in g.states if t_start - 0.5 <= t]
    if final.level == DiagnosticStatus.OK:
        assert last_traj[0] >= t_end - 0.5
        q_end = planned_positions(robot, [last_traj[1], last_att])
        tip = robot.tip_position(robot.full(q_end))
        miss = float(np.linalg.norm(tip - grasp))
        assert miss < 0.01, f"the last trajectory ends {miss:.4f} m from the last target's grasp point"
        outcome = f"trajectory (tip {1e3 * miss:.2f} mm from the grasp point)"
    else:
        outcome = f"failure: {final.message}"
        assert diag_values(final)["code"] not in ("internal_error", "invalid_input"), final.message
    rss1 = rss_mb(), rss_mb(child)
    child_peak = max(child_peak, rss1[1])
    gaps = np.diff(np.array(states))
    max_gap = float(gaps.max())
    figures = {
        "flood_sent": sent, "flood_rate_hz": round(sent / (t_end - t_start), 1),
        "flood_requests_received": received,
        "flood_trajectories_during": n_traj_flood, "flood_trajectories_total": g.n_trajs() - n_traj0,
        "flood_errors": len(g.errors()) - n_err0,
        # requests that came as the arm moved and could not take over from it (session.JOIN_FAILED: nothing sent)
        "flood_join_failed": g.log_text().count(": join_failed: "),
        "rss_test_process_mb": f"{rss0[0]:.1f} -> {rss1[0]:.1f} ({rss1[0] - rss0[0]:+.1f})",
        "rss_planning_process_mb": f"{rss0[1]:.1f} -> {rss1[1]:.1f} ({rss1[1] - rss0[1]:+.1f}), peak {child_peak:.1f}",
        "joint_states_received": len(states), "joint_states_max_gap_s": round(max_gap, 3),
        "last_outcome": outcome,
    }
    print("\nflood:", "; ".join(f"{k} = {v}" for k, v in figures.items()))
    for k, v in figures.items():
        record_property(k, v)
    # an executor blocked by the flood stops joint_states for seconds; on a loaded 2-core machine
    # (three test workers) a healthy one has shown gaps up to about 0.5 s
    assert max_gap < 2.0, f"joint_states stopped for {max_gap:.2f} s during the flood"
    assert rss1[0] - rss0[0] < 150.0 and child_peak - rss0[1] < 150.0, figures
    assert g.planner._worker.is_alive()


# ================================================================== faults inside the worker
def _raise_once(real, what):
    state = {"armed": True}

    def wrapper(*a, **k):
        if state["armed"]:
            state["armed"] = False
            raise RuntimeError(what)
        return real(*a, **k)
    return wrapper


def _expect_fault_then_recovery(g, capfd, fragments, log_fragments):
    g.wait(lambda: g.planner._joint_q is not None, 10, "joint_states seen")
    e0 = len(g.errors())
    g.send_target(*GOOD_TARGETS[0][:2])
    g.wait(lambda: len(g.errors()) > e0, 30, "an ERROR for the injected fault")
    st = g.error_diags()[-1][1]
    vals = diag_values(st)
    assert vals["code"] == "internal_error", vals
    for frag in fragments:
        assert frag in st.message, st.message
    assert diag_list(st, "target_m") == list(GOOD_TARGETS[0][:2])
    # the next request plans normally, and its plan is the first published (none for the fault)
    g.send_target(*GOOD_TARGETS[1][:2])
    assert_next_plan_grasps(g, 0, 0, *GOOD_TARGETS[1][:2], timeout=60)
    g.wait(g.all_ok, 5, "diagnostics back to OK")
    out = capfd.readouterr()                   # the fault's log lines came before the good plan
    log = out.err + out.out
    assert "Traceback (most recent call last)" in log, log[-3000:]
    for frag in log_fragments:
        assert frag in log, f"{frag!r} not in the log"


@pytest.mark.parametrize("where", ["Planner.plan", "pipeline_stage"])
def test_exception_in_worker_thread_is_logged_reported_and_survived(graph, monkeypatch, capfd, where):
    """
    In-thread mode.

    An exception escaping Planner.plan (caught by the backend) and one inside a pipeline stage
    (caught by plan's own net) both log a traceback.
    """
    if where == "Planner.plan":
        monkeypatch.setattr(Planner, "plan", _raise_once(Planner.plan, "injected fault"))
        log_fragments = ["RuntimeError: injected fault", "run_job"]
    else:
        monkeypatch.setattr(planner_mod, "descend", _raise_once(planner_mod.descend, "injected fault"))
        log_fragments = ["RuntimeError: injected fault", "descend_and_repair"]
    g = graph(scene_params("3dof", **{"planner.separate_process": False}))
    _expect_fault_then_recovery(g, capfd, ["injected fault"], log_fragments)


def test_exception_in_planning_process_is_logged_reported_and_survived(graph, capfd):
    """
    Child-process mode, no test hook.

    The first job carries a solver name the child's Planner refuses with an exception; its traceback
    (formatted in the child) is logged.
    """
    g = graph(scene_params("3dof"))
    backend = g.planner._backend
    backend.run = _bad_first_job(backend.run)
    _expect_fault_then_recovery(g, capfd, ["ValueError", "injected_fault"], ["set_solver", "child_main"])


def _bad_first_job(real):
    state = {"armed": True}

    def run(job, progress=None):
        if state["armed"]:
            state["armed"] = False
            job = dataclasses.replace(job, solver="injected_fault")
        return real(job, progress)
    return run


def test_planning_process_killed_mid_plan_is_reported_and_replaced(graph):
    g = graph(scene_params("3dof", **LONG), with_arm=False)
    robot = g.scenario.robot
    g.send_joint_state(joint_state_msg(robot.joint_names, robot.full(g.scenario.start_rad)))
    old = g.planner._backend.proc.pid
    e0 = len(g.errors())
    g.send_target()
    g.wait(lambda: g.planner.state == "planning", 10, "planning started")
    time.sleep(1.5)
    os.kill(old, signal.SIGKILL)
    g.wait(lambda: len(g.errors()) > e0, 10, "an ERROR for the dead planning process")
    st = g.error_diags()[-1][1]
    assert diag_values(st)["code"] == "internal_error" and "planning process" in st.message, st.message
    assert "-9" in st.message
    # no stall and a parameter change that replans, in a fresh planning process
    res = g.planner.set_parameters([Parameter("planner.test_stall_s", value=0.0),
                                    Parameter("safety_margin_m", value=0.021)])[0]
    assert res.successful, res.reason
    g.wait(lambda: g.n_trajs() == 1, 60, "a trajectory from the new planning process")
    new = g.planner._backend.proc.pid
    assert new != old and pid_alive(new) and not pid_alive(old)


# ================================================================== shutdown during a long plan
def _start_long_plan(g):
    robot = g.scenario.robot
    g.send_joint_state(joint_state_msg(robot.joint_names, robot.full(g.scenario.start_rad)))
    g.send_target()
    g.wait(lambda: g.planner.state == "planning", 10, "planning started")
    time.sleep(1.5)                            # the child has loaded its kernels: inside the field solve
    assert g.planner.state == "planning", "the long plan finished too soon to test anything"


def test_destroy_node_during_long_plan_child_process(graph, record_property):
    before = _threads()
    g = graph(scene_params("3dof", **LONG), with_arm=False)
    _start_long_plan(g)
    child = g.planner._backend.proc.pid
    worker = g.planner._worker
    dt = g.destroy_planner()
    print(f"\ndestroy_node during a stalled plan (child process): {dt:.3f} s")
    record_property("shutdown_destroy_child_process_s", round(dt, 3))
    assert dt < PROMPT_BOUND_S, f"destroy_node took {dt:.2f} s"
    assert not worker.is_alive() and not pid_alive(child)
    g.close()
    assert _leftover_threads(before) == []


def test_destroy_node_during_long_plan_in_thread(graph, record_property):
    """
    In-thread mode (planner.separate_process:=false).

    A running numba kernel cannot be interrupted (it releases the GIL, though), so shutdown waits
    for the running stage -- NOT within 1 s; documented in the README.

    Asserted: the plan is abandoned (nothing published), the worker ends, and no thread is
    left.
    """
    before = _threads()
    # a stall far longer than a loaded machine can hold this thread back after its 0.5 s sleep (3 s had left 2.5)
    g = graph(scene_params("3dof", **{"planner.separate_process": False, "planner.test_stall_s": 10.0}),
              with_arm=False)
    robot = g.scenario.robot
    g.send_joint_state(joint_state_msg(robot.joint_names, robot.full(g.scenario.start_rad)))
    g.send_target()
    g.wait(lambda: g.planner.state == "planning", 10, "planning started")
    worker = g.planner._worker
    t_want = time.monotonic() + 0.5            # inside the plan (this thread may not run then)
    time.sleep(0.5)
    g.destroy_planner()
    worker.join(60)
    dt = time.monotonic() - t_want
    print(f"\nshutdown during a 10 s stalled plan (in-thread): {dt:.3f} s after it was due")
    record_property("shutdown_destroy_in_thread_s", round(dt, 3))
    assert not worker.is_alive()
    assert g.planner.last_result is None and g.n_trajs() == 0, "the plan finished before the shutdown"
    g.close()
    assert _leftover_threads(before) == []


def test_context_shutdown_during_long_plan_main_path(record_property):
    """
    Ctrl-C in `main`.

    rclpy's SIGINT handler shuts the context down and `spin_until_shutdown` (main's own code) stops
    the worker and the child.
    """
    before = _threads()
    ctx = Context()
    rclpy.init(context=ctx)
    flat = scene_params("3dof", **LONG)
    node = PlannerNode(context=ctx, parameter_overrides=params_to_overrides(flat))
    drv = rclpy.create_node("test_driver", context=ctx)
    ex = NodeExecutor(context=ctx)
    spinner = threading.Thread(target=spin_until_shutdown, args=(node, ex), name="main-like")
    spinner.start()
    try:
        pub_t = drv.create_publisher(PoseStamped, "target_pose", 10)
        pub_j = drv.create_publisher(JointState, "joint_states", 10)
        t0 = time.monotonic()
        while pub_t.get_subscription_count() == 0 or pub_j.get_subscription_count() == 0:
            assert time.monotonic() - t0 < 60, "planner not subscribed"
            time.sleep(0.01)
        robot = node.robot
        js = joint_state_msg(robot.joint_names, robot.full(scenario_from_params(flat).start_rad))
        t0 = time.monotonic()                    # each phase its own bound (a loaded machine)
        while node._joint_q is None:             # sent again until taken: joint_states are heard best effort
            assert time.monotonic() - t0 < 30, "the joint state never taken"
            pub_j.publish(js)
            time.sleep(0.1)
        m = PoseStamped()
        m.header.frame_id = "world"
        m.pose.position.x, m.pose.position.y, m.pose.orientation.w = -3.27, -2.60, 1.0
        pub_t.publish(m)
        t0 = time.monotonic()
        while node.state != "planning":
            assert time.monotonic() - t0 < 30, "the plan never started"
            time.sleep(0.01)
        time.sleep(1.5)
        assert node.state == "planning"
        child, worker = node._backend.proc.pid, node._worker
        drv.destroy_node()
        t1 = time.monotonic()
        rclpy.shutdown(context=ctx)
        spinner.join(PROMPT_BOUND_S)
        dt = time.monotonic() - t1
    finally:
        if rclpy.ok(context=ctx):
            rclpy.shutdown(context=ctx)
        spinner.join(10)
    print(f"\ncontext shutdown (Ctrl-C path) during a stalled plan: {dt:.3f} s")
    record_property("shutdown_ctrl_c_path_s", round(dt, 3))
    assert not spinner.is_alive()
    assert dt < PROMPT_BOUND_S, f"shutdown took {dt:.2f} s"
    assert not worker.is_alive() and not pid_alive(child)
    assert _leftover_threads(before) == []


def test_sigint_to_node_process_during_long_plan(record_property, tmp_path):
    """
    A real Ctrl-C.

    SIGINT to the process group of `planner_node` (its planning child ignores SIGINT; the node stops
    it).

    The process exits within the bound, child included.
    """
    log = tmp_path / "planner_node.log"
    # SIGINT as in a terminal even when the test run was started with SIGINT ignored (e.g. `make test &`
    # or `nohup colcon test &` from a script: a background job of a non-interactive shell ignores
    # SIGINT and SIGQUIT), since an ignored signal stays ignored across exec
    cmd = [sys.executable, "-c", "import signal, sys; signal.signal(signal.SIGINT, signal.default_int_handler); "
           "from spacerobot_planner.ros.planner_node import main; sys.exit(main())",
           "--ros-args", "--params-file", os.path.join(CONFIG_DIR, "paper_3dof.yaml"),
           "-p", "planner.test_stall_s:=30.0"]
    with open(log, "wb") as out:
        proc = subprocess.Popen(cmd, stdout=out, stderr=subprocess.STDOUT, start_new_session=True)
    ctx = Context()
    rclpy.init(context=ctx)
    drv = rclpy.create_node("sigint_driver", context=ctx)
    try:
        pub_t = drv.create_publisher(PoseStamped, "target_pose", 10)
        pub_j = drv.create_publisher(JointState, "joint_states", 10)
        t0 = time.monotonic()
        while pub_t.get_subscription_count() == 0 or pub_j.get_subscription_count() == 0:
            assert proc.poll() is None, log.read_text()
            # a fresh interpreter's imports, the node's configure, a planning process, discovery
            assert time.monotonic() - t0 < START_TIMEOUT_S, "planner_node never subscribed\n" + log.read_text()
            time.sleep(0.05)
        m = PoseStamped()
        m.header.frame_id = "world"
        m.pose.position.x, m.pose.position.y, m.pose.orientation.w = -3.27, -2.60, 1.0
        t0 = time.monotonic()
        while "planning #" not in log.read_text():
            assert time.monotonic() - t0 < 30, "no plan started\n" + log.read_text()
            pub_j.publish(joint_state_msg(("attitude", "shoulder", "elbow"), np.radians([-90.0, 135.0, 90.0])))
            pub_t.publish(m)
            time.sleep(0.2)
        time.sleep(1.5)
        kids = child_pids(proc.pid)
        assert len(kids) == 1, kids
        t1 = time.monotonic()
        os.killpg(proc.pid, signal.SIGINT)
        try:
            rc = proc.wait(PROMPT_BOUND_S)
        except subprocess.TimeoutExpired:
            proc.kill()
            raise
        dt = time.monotonic() - t1
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
        drv.destroy_node()
        rclpy.shutdown(context=ctx)
    text = log.read_text()
    print(f"\nSIGINT to planner_node during a stalled plan: exit {rc} after {dt:.3f} s")
    record_property("shutdown_sigint_process_s", round(dt, 3))
    assert rc == 0, text
    assert "Traceback" not in text, text
    assert "Failed to publish log message to rosout" not in text, text
    assert PLAN_CANCELLED_AT_SHUTDOWN.search(text), text[-2000:]
    assert not pid_alive(kids[0]), "the planning process outlived the node"
    assert dt < PROMPT_BOUND_S, f"the node took {dt:.2f} s to exit after SIGINT\n{text[-2000:]}"


def test_a_worker_log_line_does_not_wait_for_a_context_shutdown_in_progress(capfd):
    """
    A log line of the session's worker while rclpy's context shutdown holds the context's lock returns at once.

    rclpy's context shutdown destroys the nodes holding the context's lock, and the node's destroy
    waits for its worker: a worker log line that asked ``context.ok()`` then waited for the thread
    that waited for it (5 s, and the worker outlived the node: seen under load, a Ctrl-C during a
    plan, ``test_context_shutdown_during_long_plan_main_path``).  Here the test holds the lock as the
    shutdown does while the worker thread logs: the line goes to stderr and the thread ends, in
    rcutils' format (level, a wall-clock time in seconds, the name) as the node's other lines.
    """
    ctx = Context()
    rclpy.init(context=ctx)
    node = PlannerNode(context=ctx, parameter_overrides=params_to_overrides({**scene_params("3dof"),
                                                                             "autostart": False}))
    said = (("info", "INFO"), ("warning", "WARN"), ("error", "ERROR"), ("debug", "INFO"))   # as rosout's levels

    def lines():
        for level, _ in said:
            node._log(level, f"a {level} line from the worker")
    worker = threading.Thread(target=lines, name="worker-like")
    held, node.session.worker = node.session.worker, worker
    try:
        with ctx._lock:                  # as Context.shutdown holds it while it destroys the nodes
            worker.start()
            worker.join(60.0)            # before: it waits for the lock, held until this block ends
            stuck = worker.is_alive()
        worker.join(60.0)
    finally:
        node.session.worker = held
        node.destroy_node()
        rclpy.shutdown(context=ctx)
    assert not stuck, "the worker's log line waited for the context's lock"
    err = capfd.readouterr().err.splitlines()
    for level, name in said:
        line = next(x for x in err if f"a {level} line from the worker" in x)
        m = re.fullmatch(rf"\[{name}\] \[(\d+\.\d{{9}})\] \[spacerobot_planner\]: a {level} line from the worker", line)
        assert m and abs(float(m.group(1)) - time.time()) < 600.0, line
