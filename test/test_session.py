"""
The capture session (session.py) without ROS: requests, the current goal, start, retries, stamp, at-goal.

Plans run in this thread (``run_once``) with a ``worker.ThreadBackend``; the ROS clock is a
fake the test sets.  Oracles: the target's grasp geometry (tip by the robot's forward
kinematics), the executing trajectory's own points, the clock.
"""

from __future__ import annotations

import math
import os
import re
import subprocess
import sys
import threading
import time
from dataclasses import replace
from types import SimpleNamespace

import numpy as np
import pytest

from spacerobot_planner.adapters import AT_GOAL_TOL_RAD
from spacerobot_planner.config import load_params_file, scenario_from_params, session_settings_from_params
from spacerobot_planner.scene import Target
from spacerobot_planner.session import CaptureSession, stamp_for
from spacerobot_planner.worker import ThreadBackend

S = 1_000_000_000
CONFIG = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "config")
FAST = {"trajectory.max_velocity_deg_s": [90.0, 180.0, 180.0],
        "trajectory.max_acceleration_deg_s2": [360.0, 720.0, 720.0]}


def test_the_session_imports_no_rclpy():
    code = ("import sys; import spacerobot_planner.session; "
            "assert 'rclpy' not in sys.modules, sorted(m for m in sys.modules if m.startswith('rcl'))")
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stderr


class Clock:
    """A ROS clock the test moves: ``step_ns`` more at every reading."""

    def __init__(self, t_ns=1_000 * S, step_ns=0):
        self.t, self.step, self.last = int(t_ns), int(step_ns), None

    def __call__(self):
        self.t += self.step
        self.last = self.t
        return self.t


class SlowBackend(ThreadBackend):
    """A ThreadBackend whose plans take ``plan_s`` of the fake clock; ``meanwhile(ns)`` then runs (joint states)."""

    def __init__(self, scenario, clock, plan_s):
        super().__init__(scenario)
        self.clock, self.plan_s, self.meanwhile = clock, plan_s, None

    def run(self, job, progress=None):
        out = super().run(job, progress)
        self.clock.t += int(self.plan_s * S)
        if self.meanwhile is not None:
            self.meanwhile(self.clock.t)
        return out


@pytest.fixture(scope="module")
def flat():
    f = load_params_file(os.path.join(CONFIG, "paper_3dof.yaml"))
    f.update(FAST)
    f["grid.cells"] = [36, 36, 36]
    return f


@pytest.fixture(scope="module")
def backend(flat):
    be = ThreadBackend(scenario_from_params(flat))
    yield be
    be.close()


def _session(flat, backend, clock=None, **settings):
    sc = scenario_from_params(flat)
    st = replace(session_settings_from_params(flat), **settings)
    log, published, recorded = [], [], []
    ses = CaptureSession(sc, st, now_ns=clock or Clock(), log=lambda lvl, text: log.append((lvl, text)),
                         publish=lambda req, out: published.append((req, out, (clock.last if clock else None))),
                         record=lambda req, out: recorded.append((req, out)))
    ses.start(backend, thread=False)
    ses.accept(True)
    ses.log_lines, ses.published, ses.recorded = log, published, recorded
    return ses


def _end_full(ses, out):
    """Return the robot's full joint vector at the end of the published trajectory."""
    robot = ses.scenario.robot
    q = out.trajectory.positions_rad[-1]
    return robot.full(q)


def _grasp_miss_m(ses, out, target):
    robot = ses.scenario.robot
    return float(np.linalg.norm(robot.tip_position(_end_full(ses, out)) - target.grasp_point_m))


def _target(ses, x, y):
    return replace(ses.scenario.scene.target, center_m=(x, y))


def test_the_latest_request_wins(flat, backend):
    ses = _session(flat, backend)
    ses.joint_state(ses.scenario.start_rad, 999 * S)
    done = []
    first, second = _target(ses, -3.27, -2.60), _target(ses, -3.20, -2.70)
    a = ses.submit("first", target=first, on_done=done.append)
    b = ses.submit("second", target=second, on_done=done.append)
    assert [o.code for o in done] == ["superseded"] and f"request #{b.gen}" in done[0].reason
    out = ses.run_once()
    assert out.ok and done[-1] is out and a.gen < b.gen
    assert ses.run_once() is None                                   # nothing else queued
    assert len(ses.published) == 1 and ses.published[0][1] is out
    assert _grasp_miss_m(ses, out, second) < 1e-3
    assert ses.target is second and ses.requested_target is second


def test_which_goal_a_replan_or_a_parameter_change_uses(flat, backend):
    ses = _session(flat, backend)
    robot = ses.scenario.robot
    ses.joint_state(ses.scenario.start_rad, 999 * S)
    topic = _target(ses, -3.20, -2.70)
    assert ses.submit("topic target", target=topic).gen == 1 and ses.run_once().ok
    # a joint goal: planned in the scene of the current target (the topic's), not the parameters'
    goal = ses.last_result.goal_rad + np.radians([0.0, -10.0, 5.0])
    req = ses.submit("joint goal", joint_goal=goal)
    assert req.scenario.scene.target is topic
    assert ses.run_once().ok
    executing = ses.executing
    # an action goal with its own start: planned and returned, not executed; the goal stays
    other = _target(ses, -3.30, -2.55)
    own = ses.submit("goal with its own start", target=other, start_rad=ses.scenario.start_rad)
    out = ses.run_once()
    assert out.ok and not out.publication.execute and not out.publication.sent
    assert ses.executing is executing and own.scenario.scene.target is other
    np.testing.assert_array_equal(ses.joint_goal, goal)
    assert ses.target is topic
    # a replan: the joint goal, in the current target's scene
    replan = ses.submit("~/replan")
    np.testing.assert_array_equal(replan.joint_goal, goal)
    assert replan.scenario.scene.target is topic and replan.start_rad is None
    # a parameter change of something else than the target: the same goal and obstacle
    moved = dict(flat, **{"safety_margin_m": 0.03})
    ses.configure(scenario_from_params(moved), ses.settings)
    change = ses.submit("parameter change (safety_margin_m)")
    np.testing.assert_array_equal(change.joint_goal, goal)
    assert change.scenario.scene.target is topic and change.scenario.scene.safety_margin_m == 0.03
    # a change of the target's sizes alone: the current target (the topic's) keeps its place, takes the sizes
    ses.configure(scenario_from_params(dict(moved, **{"target.handle_side_m": 0.2})), ses.settings,
                  target_resized=True)
    resized = ses.submit("parameter change (target.handle_side_m)")
    np.testing.assert_array_equal(resized.joint_goal, goal)
    got = resized.scenario.scene.target
    assert (got.center_m, got.yaw_rad, got.handle_side_m) == (topic.center_m, topic.yaw_rad, 0.2)
    assert ses.requested_target.center_m == topic.center_m and ses.requested_target.handle_side_m == 0.2
    # a change of target.*: the parameters' target becomes current (a target request plans to it)
    ses.configure(scenario_from_params(dict(moved, **{"target.center_m": [-3.25, -2.62]})), ses.settings,
                  target_changed=True)
    ses.submit("topic target", target=ses.target)
    again = ses.submit("~/replan")
    assert again.joint_goal is None and again.scenario.scene.target.center_m == (-3.25, -2.62)
    assert robot.dof == 3


def test_a_plan_from_rest_is_stamped_the_lead_after_it_is_published(flat, backend):
    clock = Clock(step_ns=S // 100)                  # every reading 10 ms later
    ses = _session(flat, backend, clock)
    ses.joint_state(ses.scenario.start_rad, clock.t)
    ses.submit("target", target=ses.target)
    out = ses.run_once()
    (_, got, read_at_publish), = ses.published
    pub = got.publication
    lead_ns = int(ses.settings.start_lead_s * S)
    assert pub.stamp_ns == read_at_publish + lead_ns         # taken at the last reading before publishing
    assert pub.stamp_ns + out.trajectory.duration_s * S >= read_at_publish + lead_ns
    assert ses.executing.start_ns == pub.stamp_ns
    assert ses.settings.start_lead_s == pytest.approx(0.35)


def _executing(flat, backend, clock, **settings):
    """Return a session that planned and published its first target from rest, and its Executing."""
    ses = _session(flat, backend, clock, **settings)
    ses.joint_state(ses.scenario.start_rad, clock.t)
    ses.submit("first target", target=ses.target)
    assert ses.run_once().ok
    return ses, ses.executing


def _moving(flat, backend, clock, t_in_s=1.0, **settings):
    """Return a session whose first trajectory executes, ``t_in_s`` into it, the arm following it."""
    ses, ex = _executing(flat, backend, clock, **settings)
    clock.t = ex.start_ns + int(t_in_s * S)
    measured_ns = clock.t - S // 100
    ses.joint_state(ex.expected_at(measured_ns), measured_ns)
    return ses, ex


def test_a_replan_joins_the_executing_trajectory_at_a_stamp_the_lead_ahead(flat, backend):
    clock = Clock()
    ses, ex = _moving(flat, backend, clock)
    ses.submit("moved target", target=_target(ses, -3.22, -2.65))
    now = clock.t
    out = ses.run_once()
    assert out.ok and out.values["joined_moving_arm"].startswith("yes"), out.values
    c = out.processed.continuation
    pub = out.publication
    assert pub.stamp_ns == ex.start_ns + int(round(c.join_time_s * S))
    assert pub.stamp_ns >= now + ses.settings.start_lead_s * S
    np.testing.assert_array_equal(out.trajectory.positions_rad[0], ex.trajectory.positions_rad[c.index])
    assert ses.executing.previous is not None and ses.executing.start_ns == pub.stamp_ns


def test_a_plan_from_the_end_of_a_trajectory_ending_within_the_lead_starts_there_at_rest(flat, backend):
    """
    The executing trajectory ends before anything published now could start (within the lead).

    The new plan starts at its end from rest, stamped the lead after publishing (after that end),
    and it is recorded as following it (a later replan joins the chain).
    """
    clock = Clock()
    ses, ex = _executing(flat, backend, clock)
    end_ns = ex.start_ns + int(ex.trajectory.duration_s * S)
    clock.t = end_ns - S // 10                       # 0.1 s before its end
    ses.joint_state(ex.expected_at(clock.t - S // 100), clock.t - S // 100)
    ses.submit("moved target", target=_target(ses, -3.22, -2.65))
    out = ses.run_once()
    assert out.ok and out.values["joined_moving_arm"] == "no (from the end of the executing trajectory, at rest)"
    np.testing.assert_array_equal(out.trajectory.positions_rad[0], ex.trajectory.positions_rad[-1])
    assert not np.any(out.trajectory.velocities_rad_s[0])
    assert out.publication.stamp_ns == clock.last + int(ses.settings.start_lead_s * S) >= end_ns
    assert ses.executing.previous is not None and ses.executing.previous.trajectory is ex.trajectory


def test_the_retry_from_the_end_starts_there_at_rest_stamped_at_that_end(flat, backend):
    """
    The retry from the executing trajectory's end (after a join missed its time).

    From rest at the end, stamped at that end (not the lead after publishing, while the arm
    still moves), however long the chain took: no join that the clock can overtake.
    """
    from spacerobot_planner.adapters import AFTER_THE_END_S, post_process
    from spacerobot_planner.replanning import Join
    clock = Clock()
    ses, ex = _executing(flat, backend, clock)
    end_ns = ex.start_ns + int(round(ex.trajectory.duration_s * S))
    now = end_ns - 15 * S // 10                      # 1.5 s before its end
    join = Join(ex, len(ex.trajectory) - 1, 2.0)
    new_path = np.vstack([ex.trajectory.positions_rad[-1], ses.scenario.start_rad])
    out = post_process(ses.scenario, new_path, join=join, now_ns=now, lead_s=0.35, from_end_at_rest=True)
    after = end_ns + int(AFTER_THE_END_S * S)          # just after it: both at rest, with their own accelerations
    assert out.join_stamp_ns is None and out.continuation is None and out.not_before_ns == after
    np.testing.assert_array_equal(out.trajectory.positions_rad[0], ex.trajectory.positions_rad[-1])
    assert not np.any(out.trajectory.velocities_rad_s[0])
    assert stamp_for(out, now, 0.35) == after                    # published now: at the end
    assert stamp_for(out, end_ns, 0.35) == end_ns + int(0.35 * S)   # published at the end: the lead later


def test_a_plan_longer_than_the_horizon_is_planned_again_with_twice_the_horizon(flat):
    clock = Clock()
    paper = load_params_file(os.path.join(CONFIG, "paper_3dof.yaml"))     # the paper's limits: a 25 s motion
    paper["grid.cells"] = flat["grid.cells"]
    slow = SlowBackend(scenario_from_params(paper), clock, plan_s=1.05)   # each plan takes 1.05 s
    try:
        ses, ex = _moving(paper, slow, clock, t_in_s=0.5, horizon_s=1.0)
        # the arm follows its trajectory meanwhile: a fresh joint state after each plan
        slow.meanwhile = lambda ns: ses.joint_state(ex.expected_at(ns - S // 100), ns - S // 100)
        ses.submit("moved target", target=_target(ses, -3.22, -2.65))
        out = ses.run_once()
    finally:
        slow.close()
    retries = [t for lvl, t in ses.log_lines if "planning again" in t]
    assert len(retries) == 1 and "longer than the 1 s horizon" in retries[0] and "twice the horizon" in retries[0]
    assert out.ok and out.values["joined_moving_arm"].startswith("yes")
    assert any("2 s ahead on the executing trajectory" in t for _, t in ses.log_lines)


def test_after_ros_time_jumped_back_a_replan_starts_from_the_arm_at_rest_stamped_in_the_new_time(flat, backend):
    """
    ROS time jumps back 500 s while the arm moves (a bag played again): the trajectory last sent is forgotten.

    Joined to it, the replan would start where it was, stamped the old time's join (500 s ahead):
    instead it starts at the arm's measured state, from rest, the lead after it is published.
    """
    clock = Clock()
    ses, ex = _moving(flat, backend, clock, t_in_s=1.0)
    q_measured = ses.joint_q.copy()
    clock.t -= 500 * S
    ses.time_jumped("jumped back 500.000 s")
    assert ses.executing is None and any(lvl == "warning" and "jumped back 500.000 s" in t and "forgotten" in t
                                         for lvl, t in ses.log_lines), ses.log_lines
    ses.submit("moved target", target=_target(ses, -3.22, -2.65))
    out = ses.run_once()
    assert out.ok and out.values["joined_moving_arm"] == "no (the arm at rest)", out.values
    np.testing.assert_allclose(out.trajectory.positions_rad[0], q_measured, rtol=0, atol=1e-12)
    assert not np.any(out.trajectory.velocities_rad_s[0])
    assert out.publication.stamp_ns == clock.last + int(ses.settings.start_lead_s * S) < ex.start_ns


def _planned_through_jumps(flat, back_s, jumps):
    """
    Plan a new target while the arm moves, ROS time jumping back ``back_s`` during each of the first ``jumps`` plans.

    Returns (session, the executing trajectory before, outcome, how many plans met a jump).
    """
    clock = Clock()
    slow = SlowBackend(scenario_from_params(flat), clock, plan_s=0.01)
    met = []
    try:
        ses, ex = _moving(flat, slow, clock, t_in_s=1.0)

        def jump(ns):
            if len(met) < jumps:
                met.append(ns)
                clock.t -= int(back_s * S)
                ses.time_jumped(f"jumped back {back_s:.3f} s")
        slow.meanwhile = jump
        ses.submit("moved target", target=_target(ses, -3.22, -2.65))
        out = ses.run_once()
    finally:
        slow.close()
    return ses, ex, out, len(met)


def test_a_plan_under_way_when_ros_time_jumped_is_planned_again_from_rest(flat):
    """The jump comes while the job plans (joined to the moving arm): nothing of that plan is published."""
    ses, ex, out, _ = _planned_through_jumps(flat, 300.0, jumps=1)
    again = [t for lvl, t in ses.log_lines if "planning again" in t]
    assert len(again) == 1 and "ROS time jumped while it planned" in again[0] and "at rest" in again[0], again
    assert out.ok and out.values["joined_moving_arm"] == "no (the arm at rest)", out.values
    assert len(ses.published) == 2                 # the first target's, then the plan again's: one
    assert out.publication.stamp_ns < ex.start_ns and ses.executing.start_ns == out.publication.stamp_ns


def test_a_request_that_ros_time_keeps_sending_back_fails_saying_so(flat):
    """Every plan of it meets a jump back (two /clock sources): planned again twice, then it fails naming the cause."""
    ses, _, out, plans = _planned_through_jumps(flat, 10.0, jumps=100)
    assert plans == 3 and out.code == "invalid_input", (plans, out.code, out.reason)
    assert "jumped back 3 times" in out.reason and "/clock" in out.reason
    assert len(ses.published) == 1                # the first target's alone


def test_a_goal_with_its_own_start_is_not_stamped_so_neither_the_clock_nor_a_jump_stops_it(flat):
    clock = Clock()
    slow = SlowBackend(scenario_from_params(flat), clock, plan_s=0.01)
    try:
        ses = CaptureSession(scenario_from_params(flat), session_settings_from_params(flat), now_ns=clock,
                             clock_problem=lambda: "ROS time is 0: no /clock yet")
        ses.start(slow, thread=False)
        ses.accept(True)
        slow.meanwhile = lambda ns: ses.time_jumped("jumped back 10.000 s")
        ses.submit("goal with a start", target=ses.target, start_rad=ses.scenario.start_rad)
        out = ses.run_once()
    finally:
        slow.close()
    assert out.ok and not out.publication.sent and ses.executing is None, (out.code, out.reason)


def test_a_query_with_its_own_start_leaves_the_arms_request_planned_and_published(flat, backend):
    """
    A goal with its own start (a what-if query) neither supersedes nor cancels the request the arm executes.

    A ROS user's query 0.5 s after a topic target superseded the target's plan: the arm's goal was
    never planned nor sent.  Now, queued together, both are planned in the order they came (the
    target's published, the query's returned); a query submitted while the arm's plan runs
    leaves it running (its on_progress submits one); a target submitted while a query runs
    leaves the query; a newer query supersedes an older one only.  Oracle: which outcomes were
    published (the session's publish hook) and their codes.
    """
    ses = _session(flat, backend)
    start = ses.scenario.start_rad
    ses.joint_state(start, 999 * S)
    other = _target(ses, -3.30, -2.55)
    done = {}

    def finish(name):
        return lambda out: done.__setitem__(name, out)

    arm = ses.submit(ses.request("target", target=other, on_done=finish("arm")))
    query = ses.submit(ses.request("query", target=ses.target, start_rad=start, on_done=finish("query")))
    assert ses.run_once().ok and ses.run_once().ok and ses.run_once() is None
    assert done["arm"].ok and done["arm"].publication.sent, done["arm"].reason
    assert done["query"].ok and not done["query"].publication.sent, done["query"].reason
    assert [r for r, out, _ in ses.published if out.publication.sent] == [arm] and query.gen > arm.gen
    assert ses.target is other
    # a query while the arm's plan runs: the arm's plan goes on and is published
    asked = []

    def ask(progress):
        if not asked:
            asked.append(ses.submit(ses.request("query meanwhile", target=ses.target, start_rad=start,
                                                on_done=finish("meanwhile"))))

    ses.joint_state(done["arm"].trajectory.positions_rad[-1], 2_000 * S)      # long after: at rest at its end
    again = ses.submit(ses.request("target again", target=ses.target, on_done=finish("again"), on_progress=ask))
    assert ses.run_once().ok and asked and ses.run_once().ok
    assert done["again"].ok and done["again"].publication.sent, done["again"].reason
    assert done["meanwhile"].ok and not done["meanwhile"].publication.sent
    assert ses.published[-2][0] is again
    # a target while a query runs leaves the query; a newer query supersedes an older one only
    late = []

    def target_meanwhile(progress):
        if not late:
            late.append(ses.submit(ses.request("target meanwhile", target=other, on_done=finish("late"))))

    first = ses.submit(ses.request("query 1", target=ses.target, start_rad=start, on_done=finish("q1"),
                                   on_progress=target_meanwhile))
    out = ses.run_once()
    assert out.ok and done["q1"].ok and late and not out.publication.sent, (out.code, out.reason)
    second = ses.submit(ses.request("query 2", target=ses.target, start_rad=start, on_done=finish("q2")))
    third = ses.submit(ses.request("query 3", target=ses.target, start_rad=start, on_done=finish("q3")))
    assert done["q2"].code == "superseded" and f"#{third.gen}" in done["q2"].reason
    assert ses.run_once().ok and done["late"].ok and done["late"].publication.sent     # the older: the target
    assert ses.run_once().ok and done["q3"].ok and ses.run_once() is None
    assert first.gen < late[0].gen < second.gen < third.gen


def test_without_a_clock_a_request_fails_saying_so(flat, backend):
    sc = scenario_from_params(flat)
    ses = CaptureSession(sc, session_settings_from_params(flat), now_ns=lambda: 0,
                         clock_problem=lambda: "ROS time is 0: no /clock yet")
    ses.start(backend, thread=False)
    ses.accept(True)
    ses.joint_state(sc.start_rad, 0)
    ses.submit("target", target=ses.target)
    out = ses.run_once()
    assert out.code == "invalid_input" and out.reason == "ROS time is 0: no /clock yet"


def test_a_flood_of_requests_logs_a_few_lines_a_second_and_says_how_many_it_left_out(flat, backend, monkeypatch):
    """Each request of a flood planned, then superseded: two info lines each, at most FLOOD_LINES a second of each."""
    import spacerobot_planner.session as session_module
    now = [100.0]
    monkeypatch.setattr(session_module.time, "monotonic", lambda: now[0])
    ses = _session(flat, backend)
    for k in range(40):                           # 40 requests within 0.4 s
        ses._log_flood("planning", f"planning #{k}")
        ses._log_flood("superseded", f"plan #{k} superseded: superseded by request #{k + 1}")
        now[0] += 0.01
    lines = [t for _, t in ses.log_lines]
    assert [t for t in lines if t.startswith("planning")] == [f"planning #{k}" for k in range(5)]
    assert len([t for t in lines if "superseded" in t]) == 5
    now[0] += 1.0
    ses._log_flood("planning", "planning #40")
    assert ses.log_lines[-1][1] == "planning #40 (35 more such lines left out before this one)"
    ses._log_flood("planning", "planning #41")     # a new window's second line: as it is
    assert ses.log_lines[-1][1] == "planning #41"
    for k in range(42, 50):                       # 8 more within the window: 3 said, 5 left out
        ses._log_flood("planning", f"planning #{k}")
    assert ses.log_lines[-1][1] == "planning #44"
    ses._flush_flood()                            # the worker idle: each kind's latest line left out, and the count
    assert [t for _, t in ses.log_lines[-2:]] == [
        "planning #49 (4 more such lines left out before this one)",
        "plan #39 superseded: superseded by request #40 (34 more such lines left out before this one)"]


def test_a_plan_whose_planning_line_a_flood_held_back_says_it_before_its_result(flat, backend, monkeypatch):
    """The held-back "planning #N" line comes before "plan #N ok", not after it at the worker's idle (client audit)."""
    import spacerobot_planner.session as session_module
    now = [100.0]
    monkeypatch.setattr(session_module.time, "monotonic", lambda: now[0])
    ses = _session(flat, backend)
    ses.joint_state(ses.scenario.start_rad, 999 * S)
    for k in range(session_module.FLOOD_LINES + 3):           # the window's lines spent (earlier requests')
        ses._log_flood("planning", f"planning #{100 + k}")
    req = ses.submit("a target", target=_target(ses, -3.20, -2.70))
    assert ses.run_once().ok
    lines = [t for _, t in ses.log_lines]
    said = [i for i, t in enumerate(lines) if t.startswith(f"planning #{req.gen} ")]
    done = [i for i, t in enumerate(lines) if t.startswith(f"plan #{req.gen} ok")]
    assert len(said) == 1 and len(done) == 1 and said[0] < done[0], lines[-6:]
    assert "3 more such lines left out before this one" in lines[said[0]], lines[said[0]]


def test_a_goal_after_a_streams_kept_plan_supersedes_it_not_cancels_it(flat):
    """
    Target 1 planning (stalled), target 2 marks it kept (nothing published for the period), then a goal's request.

    The goal supersedes the kept plan: a superseded request is no outcome (docs/node.md).  It had
    been cancelled in the backend and left kept, so it ended as an outcome "cancelled: planning was
    cancelled" in /diagnostics (the record) that nobody asked for (a client audit).  Oracle: the
    session's record and log, the goal's outcome.  Target 1's stall is a minute, which only the
    goal's cancel ends: nothing here depends on how fast the machine is.
    """
    be = ThreadBackend(scenario_from_params(flat))
    ses = _session(flat, be, min_publish_period_s=0.2)
    try:
        ses.joint_state(ses.scenario.start_rad, 999 * S)
        ses.last_publish_t -= 10.0                      # nothing published for longer than the period
        ses.start(be, thread=True)                      # the worker thread, as in the node
        first = ses.request("target 1", target=_target(ses, -3.25, -2.60))
        first = ses.submit(replace(first, settings=replace(first.settings, test_stall_s=60.0)))
        deadline = time.monotonic() + 60
        while ses._active is not first:                 # target 1 planning (stalled)
            assert time.monotonic() < deadline, "target 1 never began"
            time.sleep(0.002)
        ses.submit("target 2", target=_target(ses, -3.23, -2.60))
        assert first.keep                               # a stream: target 1's plan is let finish
        done, outcomes = threading.Event(), []
        goal = ses.submit("a goal", target=_target(ses, -3.21, -2.60),
                          on_done=lambda out: (outcomes.append(out), done.set()))
        assert done.wait(120), "no outcome for the goal"
    finally:
        ses.stop()
    assert outcomes[0].ok, outcomes[0].reason
    assert [req.gen for req, _ in ses.recorded] == [goal.gen], [(r.gen, o.code, o.reason) for r, o in ses.recorded]
    text = "\n".join(t for _, t in ses.log_lines)
    assert f"plan #{first.gen} superseded: superseded by request #{goal.gen} (a goal)" in text, text
    assert f"plan #{first.gen} cancelled" not in text, text


@pytest.mark.parametrize("arm", ["waiting", "queued"])
def test_a_cancelled_query_ends_at_once_and_the_arms_older_request_still_plans(flat, arm):
    """
    A query's cancel ends its plan although a request of the arm's with a lower number is queued.

    The arm's request came first and waited for the first joint state; a query (its own start)
    was planned meanwhile; the client cancelled it.  The backends cancel every job up to a
    number: cancelling the query by its request number would have cancelled the arm's request
    too, so the cancel had been skipped and the query's plan ran to its end (a review measured
    2.5-2.9 s of a 3 s stall).  Jobs are numbered as they are taken now.  The query's stall is ten
    minutes, which only its cancel ends; the arm's request then plans and is published.
    """
    be = ThreadBackend(scenario_from_params(flat))
    ses = _session(flat, be)
    outcomes, ended = {}, threading.Event()

    def finish(name):
        return lambda out: (outcomes.__setitem__(name, out), ended.set() if len(outcomes) == 2 else None)

    try:
        ses.start(be, thread=True)                      # the worker thread, as in the node
        first = ses.submit(ses.request("arm's target", target=_target(ses, -3.25, -2.60), on_done=finish("arm")))
        assert first.waiting
        query = ses.request("query", target=ses.target, start_rad=ses.scenario.start_rad, on_done=finish("query"))
        query = ses.submit(replace(query, settings=replace(query.settings, test_stall_s=600.0)))
        deadline = time.monotonic() + 60
        while ses._active is not query:                 # the query planning (stalled)
            assert time.monotonic() < deadline, "the query never began"
            time.sleep(0.002)
        if arm == "queued":
            ses.joint_state(ses.scenario.start_rad, 999 * S)
        ses.cancel(query, "cancelled by the client")
        if arm == "waiting":
            ses.joint_state(ses.scenario.start_rad, 999 * S)
        assert ended.wait(120), outcomes                # not after the query's ten minutes
    finally:
        ses.stop()
    assert outcomes["query"].code == "cancelled" and "by the client" in outcomes["query"].reason
    assert outcomes["arm"].ok and outcomes["arm"].publication.sent, (outcomes["arm"].code, outcomes["arm"].reason)


def test_stamp_for_a_join_too_close_asks_for_another_plan():
    from spacerobot_planner.adapters import Processed
    traj = SimpleNamespace(duration_s=0.06)
    now, lead = 100 * S, 0.35

    def processed(join_ns=None, not_before_ns=None, exact=False):
        return Processed(None, traj, None, False, math.nan, None, None, None, join_ns, None, not_before_ns,
                         stamp_exact=exact)

    assert stamp_for(processed(), now, lead) == now + int(0.35 * S)
    # from rest at the end of an executing trajectory that ends later: at that end; one that ends sooner: the lead
    assert stamp_for(processed(not_before_ns=now + 2 * S), now, lead) == now + 2 * S
    assert stamp_for(processed(not_before_ns=now + S // 5), now, lead) == now + int(0.35 * S)
    # from rest where it stops before its end (the arm leaves that point after it): then, or plan again
    assert stamp_for(processed(not_before_ns=now + S // 2, exact=True), now, lead) == now + S // 2
    assert stamp_for(processed(not_before_ns=now + S // 5, exact=True), now, lead) is None
    assert stamp_for(processed(join_ns=now + S // 2), now, lead) == now + S // 2
    assert stamp_for(processed(join_ns=now + S // 5), now, lead) is None


def test_at_the_goal_nothing_is_published_and_it_says_so(flat, backend):
    ses = _session(flat, backend)
    q = ses.scenario.start_rad
    ses.joint_state(q, 999 * S)
    ses.submit("joint goal", joint_goal=q + AT_GOAL_TOL_RAD / 4)
    out = ses.run_once()
    assert out.ok and out.values["at_goal"] == "true" and "already at the goal" in out.reason
    assert out.publication.at_goal and not out.publication.sent and ses.executing is None


def test_a_request_waits_for_the_first_joint_state_and_can_expire(flat, backend):
    ses = _session(flat, backend)
    done, stages = [], []
    req = ses.submit("target", target=ses.target, on_done=done.append,
                     on_progress=lambda p: stages.append(p.stage))
    assert req.waiting and stages == ["waiting_for_joint_states"] and ses.run_once() is None
    assert ses.expire_waiting(req, "no joint_states within 1 s") and done[0].code == "invalid_input"
    later = ses.submit("target again", target=ses.target)
    ses.joint_state(ses.scenario.start_rad, 999 * S)
    assert not ses.expire_waiting(later, "late") and ses.run_once().ok


def test_refused_while_not_accepting(flat, backend):
    ses = _session(flat, backend)
    ses.accept(False, "deactivated")
    done = []
    assert ses.submit("target", target=ses.target, on_done=done.append).gen == 0
    assert done[0].code == "cancelled" and done[0].reason == "the node is not active"
    assert isinstance(ses.target, Target)


@pytest.mark.parametrize("case", ["a_newer_state_comes", "none_comes", "published_once", "stream_stopped"])
def test_a_late_state_is_waited_for_before_a_plan_starts_on_a_moving_arm(flat, case, monkeypatch):
    """
    The worker thread waits (up to ``replanning.STATE_WAIT_S``) for a newer joint state.

    The trajectory executes; the joint states came as a stream (20 ms apart), the last one (on
    the trajectory) 0.7 s ago.  When a newer one comes during the wait, 3° off the trajectory
    (the arm was stopped), the plan starts there at rest; when none comes, the plan joins the
    trajectory on the late state and the warning names its age.  A state published once (before
    the trajectory started) is no stream, and a stream whose last state is 1.6 s old stopped:
    nothing is waited for (the first plans from the state at rest, the second joins on it).
    """
    from spacerobot_planner.replanning import STATE_WAIT_S
    if case == "a_newer_state_comes":    # however late this thread sends it, the worker still waits
        monkeypatch.setattr("spacerobot_planner.session.STATE_WAIT_S", 60.0)
    clock = Clock()
    paper = load_params_file(os.path.join(CONFIG, "paper_3dof.yaml"))     # the paper's limits: a 25 s motion
    paper["grid.cells"] = flat["grid.cells"]
    be = ThreadBackend(scenario_from_params(paper))
    try:
        ses, ex = _executing(paper, be, clock)
        clock.t = ex.start_ns + 2 * S
        late_ns = clock.t - (16 if case == "stream_stopped" else 7) * S // 10
        if case != "published_once":
            for t_ns in (late_ns - S // 50, late_ns):
                ses.joint_state(ex.expected_at(t_ns), t_ns)
        once = ses.joint_q.copy()
        stopped = ex.expected_at(clock.t) + np.radians([0.0, 3.0, 0.0])
        done = threading.Event()
        outcomes = []
        ses.start(be, thread=True)                     # the worker thread, as in the node
        t0 = time.monotonic()
        ses.submit("moved target", target=_target(ses, -3.22, -2.65),
                   on_done=lambda out: (outcomes.append(out), done.set()))
        if case == "a_newer_state_comes":
            deadline = time.monotonic() + 30
            while not ses._state_wanted:               # the worker waits: then the state comes
                assert time.monotonic() < deadline, "the worker never waited"
                time.sleep(0.002)
            ses.joint_state(stopped, clock.t)
        assert done.wait(60), "no outcome"
        waited = time.monotonic() - t0
    finally:
        ses.stop()
    out, = outcomes
    assert out.ok, out.reason
    text = "\n".join(t for _, t in ses.log_lines)
    if case == "a_newer_state_comes":
        assert out.values["joined_moving_arm"].startswith("no"), out.values
        np.testing.assert_allclose(out.trajectory.positions_rad[0], stopped, atol=1e-12)
        assert not np.any(out.trajectory.velocities_rad_s[0])
        assert "(got one)" in text and "does not follow its trajectory" in text, text
    elif case == "none_comes":
        assert out.values["joined_moving_arm"].startswith("yes"), out.values
        assert waited >= STATE_WAIT_S and "(none came)" in text and "0.70 s old" in text, text
    elif case == "published_once":
        assert out.values["joined_moving_arm"].startswith("no"), out.values
        np.testing.assert_allclose(out.trajectory.positions_rad[0], once, atol=1e-12)
        assert "for a newer joint_states" not in text and "from before the trajectory started" in text, text
    else:
        assert out.values["joined_moving_arm"].startswith("yes"), out.values
        assert "for a newer joint_states" not in text and "1.60 s old" in text, text


def test_no_plan_starts_from_a_state_the_arm_has_left_after_its_latest_joint_state_was_refused(
        flat, backend, monkeypatch):
    """After a refused joint state a plan from the arm waits for one to be taken, else fails saying why."""
    from spacerobot_planner.replanning import STATE_WAIT_S
    ses = _session(flat, backend)
    ses.joint_state(ses.scenario.start_rad, 999 * S)
    ses.joint_state_refused("joint_states: joint 'shoulder' = 250.000° is outside its bounds [-180.0°, 180.0°]")
    ses.submit("target", target=ses.target)
    t0 = time.monotonic()
    out = ses.run_once()
    assert out.code == "invalid_input" and "shoulder' = 250.000°" in out.reason and "refused" in out.reason, out
    assert time.monotonic() - t0 >= STATE_WAIT_S and not ses.published    # it waited for a state to be taken
    own = ses.submit("goal with its start", target=ses.target, start_rad=ses.scenario.start_rad)
    assert ses.run_once().ok and own.start_rad is not None          # a start of its own: not the arm's
    ses.joint_state_refused("joint_states: joint(s) elbow not finite")       # a glitch; the driver's next state
    # ends the wait, however late a loaded machine runs the timer (not the 1 s wait's end)
    monkeypatch.setattr("spacerobot_planner.session.STATE_WAIT_S", 60.0)
    ses.submit("target again", target=ses.target)
    taken = threading.Timer(0.2, ses.joint_state, (ses.scenario.start_rad, 1000 * S))
    taken.start()
    try:
        assert ses.run_once().ok
    finally:
        taken.join()


@pytest.fixture(scope="module")
def slow_backend():
    """Return (params, backend) of the paper 3-DOF file with its own (slow) limits: seconds-long trajectories."""
    f = load_params_file(os.path.join(CONFIG, "paper_3dof.yaml"))
    f["grid.cells"] = [36, 36, 36]
    be = ThreadBackend(scenario_from_params(f))
    yield f, be
    be.close()


def _moved_onto_the_executing_path(slow_backend, t1_s, t2_s, acceleration_scaling=None):
    """
    Replay a closed-loop audit's targets: a plan, a goal joined into it, then a target 5 cm / 6° off it, joined.

    The third target lies on or near the second's executing path ahead (its estimate moved as the
    arm approached).  ``t1_s``: when the second comes, into the first trajectory; ``t2_s``: when
    the third comes, into the second; ``acceleration_scaling``: the joint limits' for the third
    (a parameter change as the arm moves).  Returns (session, the third's outcome, its scene, the
    trajectory it came into, now, ns).
    """
    f, be = slow_backend
    clock = Clock()
    ses = _session(f, be, clock)
    ses.joint_state(np.radians([-178.7, 41.05, 95.96]), clock.t)
    for k, (x, y, yaw_deg, at_s) in enumerate([(-3.1, -2.7, 5.0, None), (-3.2, -2.65, -4.0, t1_s),
                                               (-3.25, -2.62, 2.0, t2_s)]):
        ex = ses.executing
        if at_s is not None:
            clock.t = ex.start_ns + int(at_s * S)
            ses.joint_state(ex.expected_at(clock.t - S // 100), clock.t - S // 100)
        target = replace(ses.scenario.scene.target, center_m=(x, y), yaw_rad=math.radians(yaw_deg))
        if k == 2 and acceleration_scaling is not None:
            lim = replace(ses.scenario.joint_limits, acceleration_scaling=acceleration_scaling)
            ses.configure(replace(ses.scenario, joint_limits=lim), ses.settings)
        ses.submit(f"target {k}", target=target)
        out = ses.run_once()
        assert out.ok, (k, out.code, out.reason)
    return ses, out, ses.scenario.scene.with_target(target), ex, clock.t


#: (t1_s, t2_s) of _moved_onto_the_executing_path: moments of the closed-loop audit's grid with every verdict
AUDIT_MOMENTS = [(3.05, 0.0), (3.25, 0.2), (3.55, 0.0), (3.65, 0.0), (3.0, 0.4)]


def _on_the_chain(ex, t_ns):
    """
    Return where the arm is at ROS time ``t_ns`` on an executing chain: the test's own linear interpolation in time.

    Each link is followed from its start; before it, the one it was joined to; the oldest one is
    held at its first point before its start and every link at its last point after its end.
    """
    while ex.previous is not None and t_ns < ex.start_ns:
        ex = ex.previous
    tr = ex.trajectory
    t = 1e-9 * (t_ns - ex.start_ns)
    return np.array([np.interp(t, tr.times_s, tr.positions_rad[:, j]) for j in range(tr.positions_rad.shape[1])])


@pytest.mark.parametrize("t1_s, t2_s", AUDIT_MOMENTS)
def test_a_replan_is_certified_only_when_the_motion_it_commits_the_arm_to_keeps_the_margin(slow_backend, t1_s, t2_s):
    """
    A target moved onto the executing path: the motion the arm makes is judged whole, in the new scene.

    That motion is the executing path from the earliest a message can take over (now + the lead)
    to the published trajectory's stamp, then the controller's motion through its points.  Before,
    a joined trajectory the chain could not certify was published as "ok" with the new path's
    clearance (the audit measured 0.0178 m where the node said 0.034 m), and the retry from the
    executing trajectory's end drove the arm through the target, certified.  Now
    ``trajectory_certified`` is "true" exactly when that motion keeps the margin, and otherwise
    a warning says so.  Oracle: the test's geometry, the test's quintics and the executing
    chain interpolated in time by the test (``_on_the_chain``).
    """
    from oracles import controller_motion, ref_clearance
    ses, out, scene, ex, now = _moved_onto_the_executing_path(slow_backend, t1_s, t2_s)
    robot, margin = ses.scenario.robot, scene.safety_margin_m
    lead_ns = now + int(ses.settings.start_lead_s * S)
    stamp = out.publication.stamp_ns
    # the controller takes it where the arm is at its stamp (its first point at time 0 is the arm's state then)
    off = np.abs(out.trajectory.positions_rad[0] - _on_the_chain(ex, stamp)).max()
    assert off < math.radians(0.5), (math.degrees(off), out.values["joined_moving_arm"])
    old = [_on_the_chain(ex, t) for t in range(lead_ns, max(lead_ns, stamp) + 1, S // 200)]
    new, v, a = controller_motion(out.trajectory, 40 * len(out.trajectory.times_s))
    lim = ses.scenario.joint_limits
    vmax, amax = lim.planned(robot)
    peaks = np.max(np.abs(v) / (vmax * lim.velocity_scaling)), np.max(np.abs(a) / (amax * lim.acceleration_scaling))
    assert max(peaks) <= 1.0 + 2e-3, (peaks, out.values["joined_moving_arm"])     # the controller keeps the limits
    clr = min(ref_clearance(robot, scene, robot.full(q)) for q in list(new) + old)
    said = "\n".join(text for _, text in ses.log_lines[-4:])
    if abs(clr - margin) < 1e-3:
        pytest.skip(f"the motion's clearance {clr:.4f} m is within 1 mm of the margin: either verdict is sound")
    certified = out.values["trajectory_certified"] == "true"
    assert certified == (clr > margin), (clr, out.values["trajectory_certified"], said)
    assert ("published although not collision-free" in said) == (not certified), said
    if not certified:
        assert float(out.values["trajectory_clearance_m"]) < margin or "executing path" in said, (out.values, said)
    # on along the executing path to its end only where the motion is certified or no stop fits the limits
    assert "from the end of the executing trajectory" not in out.values["joined_moving_arm"] or certified \
        or "no stop on the executing path could be sent" in said, said


def test_the_replans_of_a_target_moved_onto_the_path_cover_every_verdict(slow_backend):
    """The cases above: one whose motion is certified, one that is not, and stops on the executing path."""
    seen, planning = {}, {}
    for t1_s, t2_s in AUDIT_MOMENTS:
        ses, out, _, _, _ = _moved_onto_the_executing_path(slow_backend, t1_s, t2_s)
        seen[(t1_s, t2_s)] = (out.values["trajectory_certified"], out.values["joined_moving_arm"])
        planning[(t1_s, t2_s)] = [t for _, t in ses.log_lines if t.startswith("planning #3 ")]
    assert {v for v, _ in seen.values()} == {"true", "false"}, seen
    # two stops that were published from the measured state at rest while the arm moved, then failed
    # (join_failed): (3.55, 0.0) needs more than three whole-path re-timings of its first segment, from the
    # arm's own acceleration (adapters.STOP_WHOLE_PATH_RETIMES); (3.0, 0.4) is a slow arm at a bend, whose stop
    # is found with the arm's own tangent and its start at the full limits (replanning.stopping_join).  The
    # stop's planning line says where the stop is (it had said "1 s ahead", the horizon, wherever the stop was)
    for moment in [(3.55, 0.0), (3.0, 0.4)]:
        assert "stopping on its path" in seen[moment][1], seen
        assert any(re.search(r"\(stopping on the executing trajectory \d+\.\d\d s ahead\)", t)
                   for t in planning[moment]), planning[moment]


def test_limits_lowered_as_the_arm_moves_and_no_stop_fits_them_plan_from_the_executing_trajectorys_end(slow_backend):
    """
    The acceleration limits lowered to a tenth as the arm moves, a target moved onto its path: from its end, said.

    No join or stop on the executing path fits the new limits; the arm reaches that trajectory's
    end whatever is sent, so the plan from there, at rest, is the least exposed motion: published
    with a warning, stamped no earlier than that end, its first point where the arm comes to rest.
    (Before, a trajectory from the measured state at rest was published while the arm moved on:
    its first point, at time 0, not where the arm was at its stamp.)  Oracle: the executing chain
    interpolated in time by the test.
    """
    ses, out, _, ex, now = _moved_onto_the_executing_path(slow_backend, 3.55, 0.0, acceleration_scaling=0.1)
    assert out.ok, (out.code, out.reason)
    assert out.values["joined_moving_arm"] == "no (from the end of the executing trajectory, at rest)", out.values
    said = "\n".join(text for _, text in ses.log_lines[-3:])
    assert out.values["trajectory_certified"] == "false" and "no stop on the executing path could be sent" in said, said
    stamp, end_ns = out.publication.stamp_ns, ex.start_ns + int(round(ex.trajectory.duration_s * S))
    assert stamp >= end_ns, (stamp, end_ns)
    off = np.abs(out.trajectory.positions_rad[0] - _on_the_chain(ex, stamp)).max()
    assert off < 1e-6, math.degrees(off)


def _following_its_first_trajectory(slow_backend, at):
    """
    Return (session, Executing, clock): the audit's first target planned, the arm following its trajectory.

    ``at(duration_s)``: how far into that trajectory (s) the clock is, the arm's state measured 10 ms before.
    """
    f, be = slow_backend
    clock = Clock()
    ses = _session(f, be, clock)
    ses.joint_state(np.radians([-178.7, 41.05, 95.96]), clock.t)
    ses.submit("first", target=ses.target)
    assert ses.run_once().ok
    ex = ses.executing
    clock.t = ex.start_ns + int(S * at(ex.trajectory.duration_s))
    ses.joint_state(ex.expected_at(clock.t - S // 100), clock.t - S // 100)
    return ses, ex, clock


def test_the_fallback_from_the_end_starts_at_the_running_trajectorys_end_not_after_the_waiting_ones(slow_backend):
    """
    The retry from the executing trajectory's end takes the end of the one that runs, stamped before the waiting ones.

    With trajectories waiting for later stamps (plans from the end, sent before), it had taken the
    newest one's end: each such plan queued after the last, and the arm was left a queue of motions
    to goals later requests had replaced (an audit on the servicer: five waiting, the last stamped
    585 s ahead).  Here one trajectory waits from the running one's end; the retry's start is the
    running one's last point.  Oracle: the running trajectory's own points.
    """
    from spacerobot_planner.session import FROM_THE_END
    ses, ex, clock = _following_its_first_trajectory(slow_backend, lambda duration_s: 0.4 * duration_s)
    traj = ex.trajectory
    end_ns = ex.start_ns + int(round(traj.duration_s * S))
    waiting = ex.joined_by(traj, ex.published, end_ns, clock.t)          # sent from the running one's end
    ses.executing = waiting.joined_by(traj, ex.published, end_ns + int(round(traj.duration_s * S)), clock.t)
    req = ses.request("retarget", target=ses.target)
    req.attempt = FROM_THE_END
    start, join = ses._start_of(req)
    assert join is not None and join.executing.start_ns == ex.start_ns, join
    assert join.horizon_index == len(traj.times_s) - 1
    np.testing.assert_array_equal(start, traj.positions_rad[-1])


def test_limits_lowered_below_the_moving_arms_speed_brake_it_to_them(slow_backend):
    """
    Velocity limits lowered to a sixteenth as the arm moves to its goal (``ros2 param set``): the arm brakes to them.

    Before, no join and no stop on the executing path could be timed from a speed above the new
    limits, and the arm finished the trajectory it followed at 16 times them for seconds (said in a
    warning).  Now the joined trajectory brakes to them (``brake_to_limits``) and keeps them to the
    goal; the log says so.  Oracle: the controller's quintics of the published points (SciPy's
    BPoly, ``oracles.controller_interpolation``) against the new limits and the arm's state at the
    stamp (the executing trajectory's own points): the speed is the arm's at first, every
    acceleration within its limit throughout, and every velocity within the new limits from some
    time on, which comes no later than the join's horizon and the test's braking bound (the arm's
    excess speed over the acceleration limit, joint by joint, with half again and 0.2 s).
    """
    from oracles import controller_interpolation
    ses, ex, clock = _following_its_first_trajectory(slow_backend, lambda duration_s: 0.4 * duration_s)
    lim = ses.scenario.joint_limits
    slower = replace(lim, max_velocity_rad_s=tuple(np.asarray(lim.max_velocity_rad_s) / 16.0))
    ses.configure(replace(ses.scenario, joint_limits=slower), ses.settings)
    vmax_new, amax = (np.asarray(x) for x in slower.planned(ses.scenario.robot))
    k = int(np.searchsorted(ex.trajectory.times_s, ex.time_s(clock.t)))
    assert np.max(np.abs(ex.trajectory.velocities_rad_s[k]) / vmax_new) > 2.0     # the test's premise: far too fast
    ses.submit("limits changed", target=ses.target)
    out = ses.run_once()
    assert out.ok and out.publication.sent, (out.code, out.reason)
    said = "\n".join(text for _, text in ses.log_lines[-3:])
    assert re.search(r"within the velocity limits from [0-9.]+ s on \(the arm at [0-9.]+ times them", said), said
    names = ses.scenario.robot.planned_names
    at_stamp = ex.trajectory.velocities_rad_s[k]
    v_stamp = None
    for part in (out.publication.arm, out.publication.attitude):
        cols = [names.index(n) for n in part.joint_names]
        f = controller_interpolation(part.times_s, part.positions_rad, part.velocities_rad_s,
                                     part.accelerations_rad_s2)
        ts = np.linspace(0.0, part.times_s[-1], 40 * len(part.times_s))
        _, v, a = f(ts)
        assert np.all(np.abs(a) <= amax[cols] * 1.002), np.max(np.abs(a) / amax[cols])
        above = np.flatnonzero(np.max(np.abs(v) / vmax_new[cols], axis=1) > 1.002)
        brakes_by = ses.settings.horizon_s + 0.2 + 1.5 * np.max(
            (np.abs(at_stamp[cols]) - vmax_new[cols]).clip(0.0) / amax[cols])
        assert not len(above) or ts[above[-1]] <= brakes_by, (ts[above[-1]], brakes_by)
        v_stamp = v[0] if v_stamp is None else v_stamp
    assert np.max(np.abs(v_stamp) / vmax_new[[names.index(n) for n in out.publication.arm.joint_names]]) > 1.0


def test_a_stop_on_the_executing_path_that_came_too_late_is_planned_again_once(slow_backend, monkeypatch):
    """
    The audit's 3.65 s moment, its first stop on the path made late (injected: the arm past it): stopped again.

    Before, a stop that came too late for its join went on to the plan from the executing
    trajectory's end (through the target on that path); now it is planned again once, from then.
    """
    import spacerobot_planner.session as session_module
    from spacerobot_planner.trajectory import HorizonPassed
    real, late = session_module.post_process, []

    def once_late(*args, join=None, **kwargs):
        if join is not None and join.stop and not late:
            late.append(join)
            raise HorizonPassed("injected: the arm is past the stop's join")
        return real(*args, join=join, **kwargs)

    monkeypatch.setattr(session_module, "post_process", once_late)
    ses, out, _, _, _ = _moved_onto_the_executing_path(slow_backend, 3.65, 0.0)
    said = "\n".join(text for _, text in ses.log_lines)
    assert late and "took longer than the" in said and "stopping on its path" in out.values["joined_moving_arm"], \
        (out.values, said)


@pytest.mark.parametrize("at_s", [2.0, -0.5], ids=["2 s in", "0.5 s before its end"])
def test_a_moving_arm_no_trajectory_can_take_over_finishes_its_own_and_the_next_request_plans_from_its_end(
        slow_backend, monkeypatch, at_s):
    """
    Every way to take over the moving arm fails (injected: no timing enters its speed): nothing is sent.

    ``at_s``: when the request comes, into the trajectory (negative: before its end).  0.5 s before
    its end, the trajectory ends after now + the lead but before the plan from rest would be stamped
    (a review's scenario: that plan was published, from the measured state, 0.79° from the arm at
    its stamp).

    Before, the last retry published a trajectory from the measured state at rest while the arm
    moved on (a controller refuses its first point, at time 0, not the arm's state).  Now the
    request fails with ``join_failed`` saying what was tried; the arm finishes the trajectory it
    follows (the session still takes it as the executing one), and a request after its end plans
    from where it came to rest.  Oracle: the executing chain interpolated in time by the test.
    """
    import spacerobot_planner.session as session_module
    real = session_module.post_process

    def no_join(*args, join=None, **kwargs):
        if join is not None:
            raise ValueError("injected: no timing enters the arm's speed")
        return real(*args, join=join, **kwargs)

    ses, ex, clock = _following_its_first_trajectory(
        slow_backend, lambda duration_s: at_s if at_s > 0 else duration_s + at_s)
    monkeypatch.setattr(session_module, "post_process", no_join)
    sent = len(ses.published)
    ses.submit("moved", target=replace(ses.target, center_m=tuple(np.asarray(ses.target.center_m) + 0.05)))
    out = ses.run_once()
    assert out.code == "join_failed" and len(ses.published) == sent, (out.code, out.reason)
    lead_ns = clock.t + int(ses.settings.start_lead_s * S)
    moved = np.abs(_on_the_chain(ex, lead_ns + S // 10) - _on_the_chain(ex, lead_ns)).max()
    assert moved > 1e-3, moved                              # the arm still moves when anything sent could start
    for said in ("the arm follows its trajectory", "stopping on the executing path", "from the end of the executing",
                 "injected", "nothing was sent"):
        assert said in out.reason, out.reason
    assert ses.executing is ex and ses.recorded[-1][1] is out, ses.recorded[-1]
    monkeypatch.setattr(session_module, "post_process", real)
    clock.t = ex.start_ns + int(ex.trajectory.duration_s * S) + S
    at_rest = _on_the_chain(ex, clock.t)
    ses.joint_state(at_rest, clock.t)
    ses.submit("after its end", target=ses.target)
    again = ses.run_once()
    assert again.ok and again.values["joined_moving_arm"] == "no (the arm at rest)", (again.code, again.reason)
    np.testing.assert_allclose(again.trajectory.positions_rad[0], at_rest, atol=1e-9)


def test_a_plan_from_rest_within_the_margin_says_so_and_reports_the_motions_clearance(flat, backend):
    """
    The target moved 9 cm towards the parked arm (its start 1 cm from it, inside the 2 cm margin): walked out, said.

    Before, nothing was said and the plan's clearance (0.031 m in the audit) was reported as the
    motion's.  Oracle: the start's clearance in the test's geometry.
    """
    from oracles import ref_clearance
    clock = Clock()
    ses = _session(flat, backend, clock)
    ses.joint_state(ses.scenario.start_rad, clock.t)
    ses.submit("first", target=ses.target)
    parked = ses.run_once().trajectory.positions_rad[-1]
    clock.t += 100 * S                                  # long after its trajectory ended: the arm at rest there
    ses.joint_state(parked, clock.t)
    t0 = ses.target
    normal = np.array([-math.sin(t0.yaw_rad), math.cos(t0.yaw_rad)])        # the handle's side, towards the arm
    moved = replace(t0, center_m=tuple(np.asarray(t0.center_m) + 0.09 * normal))
    robot = ses.scenario.robot
    start_clr = ref_clearance(robot, ses.scenario.scene.with_target(moved), robot.full(parked))
    assert 0.0 < start_clr < ses.scenario.scene.safety_margin_m, start_clr
    ses.submit("moved", target=moved)
    out = ses.run_once()
    assert out.ok and out.values["trajectory_certified"] == "false", out.values
    assert float(out.values["trajectory_clearance_m"]) == pytest.approx(start_clr, abs=2e-3), (out.values, start_clr)
    said = "\n".join(text for _, text in ses.log_lines[-3:])
    assert "published although not collision-free" in said and "starts within the margin and walks out" in said, said


def test_an_uncertified_plan_from_a_clear_start_does_not_say_it_walks_out(flat, backend, monkeypatch):
    """
    The warning of an uncertified motion from rest says "starts within the margin" only where the start is.

    A ROS user's free-floating ``~/replan`` was published uncertified (the chain's check was in
    the wrong frame, since mended) with "it starts within the margin and walks out" from a start
    0.13 m clear.  Injected here: the chain's result marked uncertified.  Oracle: the start's
    clearance in the test's geometry.
    """
    from oracles import ref_clearance
    from spacerobot_planner import session as session_module
    real = session_module.post_process
    monkeypatch.setattr(session_module, "post_process", lambda *a, **k: replace(real(*a, **k), certified=False))
    clock = Clock()
    ses = _session(flat, backend, clock)
    start = ses.scenario.start_rad
    robot = ses.scenario.robot
    assert ref_clearance(robot, ses.scenario.scene, robot.full(start)) > ses.scenario.scene.safety_margin_m
    ses.joint_state(start, clock.t)
    ses.submit("first", target=ses.target)
    out = ses.run_once()
    assert out.ok and out.values["trajectory_certified"] == "false", out.values
    said = "\n".join(text for _, text in ses.log_lines[-3:])
    assert "published although not collision-free" in said and "walks out" not in said, said
    assert "the controller's interpolation of every one of its points is not" in said, said


def _legacy_controller(messages, arrivals_ns, ts_ns):
    """
    Return the positions (len(ts_ns), k) a joint_trajectory_controller before 6.8 commands (the test's model).

    ``messages``: [(stamp ns, times s, q, v, a)] of one joint group, in order; each is installed when it
    arrives (``arrivals_ns``) and sampled from then: before its first point's time, a quintic from the
    commanded state at the arrival (``interpolate_from_desired_state``) to that point; after it, its own
    quintic segments (oracles.controller_interpolation: BPoly, not the package's sampler).
    """
    from oracles import controller_interpolation
    out = []
    for t in ts_ns:
        k = max(i for i, a in enumerate(arrivals_ns) if a <= t)
        out.append(_commanded(messages[:k + 1], arrivals_ns[:k + 1], t, controller_interpolation))
    return np.array(out)


def _commanded(messages, arrivals_ns, t_ns, interpolation):
    """Return (q) at ``t_ns`` of the last message installed (recursively: its connection starts on the one before)."""
    stamp, times, q, v, a = messages[-1]
    s = 1e-9 * (t_ns - stamp)
    if len(messages) > 1 and s < times[0]:
        arr = arrivals_ns[-1]
        eps = 1000                                             # the state at the arrival, by differences (1 us)
        q0 = _commanded(messages[:-1], arrivals_ns[:-1], arr, interpolation)
        qp = _commanded(messages[:-1], arrivals_ns[:-1], arr + eps, interpolation)
        qm = _commanded(messages[:-1], arrivals_ns[:-1], arr - eps, interpolation)
        v0, a0 = (qp - qm) / (2e-9 * eps), (qp - 2 * q0 + qm) / (1e-9 * eps) ** 2
        f = interpolation(np.array([1e-9 * (arr - stamp), times[0]]), np.vstack([q0, q[0]]), np.vstack([v0, v[0]]),
                          np.vstack([a0, a[0]]))
        return f(s)[0][0]
    return interpolation(times, q, v, a)(s)[0][0]


@pytest.mark.parametrize("arrive_after_s", [0.02, 0.15, 0.3])
@pytest.mark.parametrize("stream", [False, True], ids=["one_replan", "a_replan_before_the_last_one_started"])
def test_a_join_for_a_controller_that_switches_at_arrival_is_the_executing_motion_until_the_join(flat, backend,
                                                                                                 arrive_after_s,
                                                                                                 stream):
    """
    ``controller.switch: arrival`` (joint_trajectory_controller before 6.8, Kilted's): the arm follows the old motion.

    The message is stamped at the last point the controller has passed of the message it was
    sent last and holds its points up to the join; wherever it arrives before the join, the
    controller's motion is the one it had until the join, then the joined trajectory's.  With a
    stream of replans the one before may not have started yet (its prefix then comes from the
    message before it: the audit's 55 of 63 joined messages sent with nothing in front).  The same
    plans stamped at their joins ("stamp") make such a controller leave the executing motion at
    once (its connection from its state to the first point).  Oracle: the test's model of that
    controller, on the test's quintics.
    """
    clock = Clock()
    ses, ex = _moving(flat, backend, clock, controller_switch="arrival")
    outs = []
    for x, y in ([(-3.25, -2.62)] if stream else []) + [(-3.22, -2.65)]:
        ses.submit("moved target", target=_target(ses, x, y))
        outs.append(ses.run_once())
        assert outs[-1].ok and outs[-1].values["joined_moving_arm"].startswith("yes"), outs[-1].values
    now = clock.t                                               # (not moved: the first replan has not started)
    pubs = [p.publication for _, p, _ in ses.published]         # from rest, then the replans, as sent
    join_ns = outs[-1].processed.join_stamp_ns
    arrival = now + int(arrive_after_s * S)
    assert pubs[-1].stamp_ns <= now < arrival < join_ns          # stamped before it is sent
    if stream:
        assert outs[0].processed.join_stamp_ns > now, "the first replan had started: nothing tested"

    def msg(pub, part):
        p = getattr(pub, part)
        return pub.stamp_ns, p.times_s, p.positions_rad, p.velocities_rad_s, p.accelerations_rad_s2

    def at_join(out, part):                                     # the joined trajectory, stamped at its join
        p = getattr(out.processed, part)
        return out.processed.join_stamp_ns, p.times_s, p.positions_rad, p.velocities_rad_s, p.accelerations_rad_s2
    ts = np.linspace(arrival, join_ns + int(0.5 * S), 60).astype(np.int64)
    earlier = [0] + [now] * (len(pubs) - 2)                      # when the ones before arrived
    for part in ("arm", "attitude"):
        got = _legacy_controller([msg(p, part) for p in pubs], earlier + [arrival], ts)
        stamped = [msg(pubs[0], part)] + [at_join(o, part) for o in outs]
        intended = _legacy_controller(stamped, [0] + [o.processed.join_stamp_ns for o in outs], ts)
        np.testing.assert_allclose(got, intended, atol=1e-9, err_msg=part)
        as_stamped = _legacy_controller(stamped, earlier + [arrival], ts)     # "stamp": each stamped at its join
        if part == "arm":
            assert np.max(np.abs(as_stamped - intended)) > 1e-6, np.max(np.abs(as_stamped - intended))


def test_the_committed_path_runs_on_the_trajectory_before_a_joined_one_that_has_not_started(flat, backend):
    """
    A replan joined to the executing trajectory starts later, at its join: until then the arm is on the one before.

    ``committed_path`` (what a plan must keep clear, from now + the lead to its switch) clamped
    every earlier time to the newest trajectory's start: the stretch on the one before went
    unchecked (the audit's 0.0135 m, "certified").  Oracle: the test's own linear interpolation
    of the two dense trajectories in time.
    """
    from spacerobot_planner.replanning import Join, committed_path
    clock = Clock()
    ses, ex1 = _moving(flat, backend, clock)
    ses.submit("moved target", target=_target(ses, -3.25, -2.62))
    assert ses.run_once().values["joined_moving_arm"].startswith("yes")
    ex2 = ses.executing
    assert ex2.previous is not None and ex2.start_ns > clock.t        # joined ahead: not started
    a_ns, b_ns = clock.t + S // 10, ex2.start_ns + S // 2

    def interp(ex, t_ns):
        t = 1e-9 * (t_ns - ex.start_ns)
        tr = ex.trajectory
        return np.array([np.interp(t, tr.times_s, tr.positions_rad[:, j]) for j in range(tr.positions_rad.shape[1])])

    def inner(ex, lo_ns, hi_ns):
        t = ex.start_ns + 1e9 * ex.trajectory.times_s
        return list(ex.trajectory.positions_rad[(t > lo_ns) & (t < hi_ns)])
    want = np.array([interp(ex1, a_ns), *inner(ex1, a_ns, ex2.start_ns), interp(ex1, ex2.start_ns),
                     interp(ex2, ex2.start_ns), *inner(ex2, ex2.start_ns, b_ns), interp(ex2, b_ns)])
    got = committed_path(Join(ex2, 0, 1.0), a_ns, b_ns)

    def distinct(rows):       # a dense point at the switch's time is also its interpolation there (rounding)
        rows = np.asarray(rows)
        return rows[np.r_[True, np.any(np.abs(np.diff(rows, axis=0)) > 1e-9, axis=1)]]
    np.testing.assert_allclose(distinct(got), distinct(want), atol=1e-9)
    assert np.max(np.abs(want[0] - ex2.trajectory.positions_rad[0])) > 1e-3       # the two differ there


def test_a_plan_from_the_end_for_a_controller_that_switches_at_arrival_leaves_the_last_segment_as_it_was(flat,
                                                                                                         backend):
    """
    From the executing trajectory's end, at rest, ``AFTER_THE_END_S`` after it: the old last segment keeps its end.

    Both are at rest there, each with its own acceleration (braking into the end, speeding up out of
    it); with one point for both, the old last segment bent (a re-run audit: 1.045 x the elbow's
    limit).  Oracle: the test's model of a pre-6.8 controller: the message as sent, arriving before
    the end, against the old message run to its end and the new one from its stamp.
    """
    clock = Clock()
    ses, ex = _executing(flat, backend, clock, controller_switch="arrival")
    end_ns = ex.start_ns + int(ex.trajectory.duration_s * S)
    clock.t = end_ns - S // 10                       # 0.1 s before its end: within the lead, so from the end
    ses.joint_state(ex.expected_at(clock.t - S // 100), clock.t - S // 100)
    ses.submit("moved target", target=_target(ses, -3.22, -2.65))
    out = ses.run_once()
    assert out.ok and out.values["joined_moving_arm"] == "no (from the end of the executing trajectory, at rest)"
    first, second = (p.publication for _, p, _ in ses.published)
    arrival = clock.t + S // 50
    assert second.stamp_ns < arrival < end_ns
    acc_old, acc_new = first.arm.accelerations_rad_s2[-1], out.processed.arm.accelerations_rad_s2[0]
    assert np.max(np.abs(acc_old - acc_new)) > 1e-3, "the two accelerations agree: nothing tested"

    def msg(stamp, p):
        return stamp, p.times_s, p.positions_rad, p.velocities_rad_s, p.accelerations_rad_s2
    k = len(second.arm.times_s) - len(out.processed.arm.times_s)      # the new part's first point, as sent
    own_stamp = second.stamp_ns + int(round(1e9 * second.arm.times_s[k]))
    assert own_stamp >= first.stamp_ns + int(round(1e9 * first.arm.times_s[-1])) + 10 ** 6 - 1   # the gap
    ts = np.linspace(arrival, end_ns + S // 2, 80).astype(np.int64)
    got = _legacy_controller([msg(first.stamp_ns, first.arm), msg(second.stamp_ns, second.arm)], [0, arrival], ts)
    intended = _legacy_controller([msg(first.stamp_ns, first.arm), msg(own_stamp, out.processed.arm)],
                                  [0, own_stamp], ts)
    np.testing.assert_allclose(got, intended, atol=1e-6)


def test_a_replan_of_a_trajectory_sent_and_not_begun_starts_at_its_first_point(flat, backend):
    """
    The arm running to P's end, W sent from there (not begun), a new target: from W's first point, at its stamp.

    As a plan from the executing trajectory's end sends W: from rest at P's end, stamped just after
    it.  0.8 s before P ends (W within the 1 s horizon, its first point more than the lead and the
    chain's allowance ahead) a new target: the plan starts where the arm will rest, P's last point
    (the test's own record of P), stamped exactly W's stamp, which it replaces; it goes to the new
    target, not along W (the test's nearest-point distance to W's rows).  Before, it joined W there
    and followed W's path for the horizon, then turned.
    """
    from spacerobot_planner.adapters import post_process
    from spacerobot_planner.planner import Planner
    clock = Clock()
    ses, p = _executing(flat, backend, clock)
    sc = ses.scenario
    p_end = p.trajectory.positions_rad[-1].copy()
    end_ns = p.start_ns + int(round(p.trajectory.duration_s * S))
    w = post_process(sc, Planner(sc).plan(p_end, sc.start_rad).path_rad, start_rad=p_end)
    w_start = end_ns + S // 1000
    ses.executing = p.joined_by(w.dense, w.indices, w_start, clock.t)
    clock.t = end_ns - int(0.8 * S)
    ses.joint_state(p.expected_at(clock.t - S // 100), clock.t - S // 100)
    ses.submit("moved target", target=_target(ses, -3.22, -2.65))
    out = ses.run_once()
    assert out.ok, (out.code, out.reason)
    said = "\n".join(text for _, text in ses.log_lines[-3:])
    assert out.values["joined_moving_arm"] == \
        "no (from the start of the executing trajectory, sent and not begun, at rest)", (out.values, said)
    assert "(where the executing trajectory rests, " in said, said
    assert out.publication.stamp_ns == w_start
    np.testing.assert_array_equal(out.trajectory.positions_rad[0], p_end)
    assert np.all(out.trajectory.velocities_rad_s[0] == 0.0)
    assert ses.executing.start_ns == w_start and ses.executing.trajectory is out.processed.dense
    # W's rows within the horizon (which a join there would have followed exactly) are off the new path
    along_w = w.dense.positions_rad[1:][w.dense.times_s[1:] <= ses.settings.horizon_s]
    assert len(along_w), "W has no rows within the horizon: nothing tested"
    gap = np.min(np.linalg.norm(out.processed.dense.positions_rad[:, None, :] - along_w[None], axis=2), axis=0)
    assert np.all(gap > 1e-6), np.degrees(gap)


def test_a_replan_joined_where_the_one_before_begins_says_so(flat, backend):
    """Two replans at one instant: the second joins the first at its first point, before it begins (not "0.000 s")."""
    clock = Clock()
    ses, _ = _moving(flat, backend, clock)
    ses.submit("moved target", target=_target(ses, -3.25, -2.62))
    assert ses.run_once().values["joined_moving_arm"].startswith("yes, ")
    first = ses.executing
    ses.submit("moved again", target=_target(ses, -3.24, -2.63))
    joined = ses.run_once().values["joined_moving_arm"]
    assert ses.executing.start_ns == first.start_ns > clock.t, "not joined where the one before begins"
    assert joined.startswith("yes, at the start of the executing trajectory (sent, not begun"), joined
