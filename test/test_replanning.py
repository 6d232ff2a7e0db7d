"""
Tests of replanning.py.

Where a replan starts (the arm following its trajectory or not) and the joined trajectory (exact
state of the executing trajectory at the join, its certified points to the horizon, limits by the
test's own finite differences).
"""

from dataclasses import replace

import numpy as np
import pytest

from oracles import check_trajectory, controller_motion, controller_wheel_load, shapely_clearance
from paper_paths import joint_limits, new_path_from, turned

from spacerobot_planner.pipeline import timed_motion
from spacerobot_planner.replanning import BLEND_SAMPLES, Executing, joined_motion, plan_start
from spacerobot_planner.published import resample
from spacerobot_planner.trajectory import HorizonPassed

PERIODIC = (True, False, False)
S = 1_000_000_000          # ns per s


@pytest.fixture(scope="module")
def executing(paper_scenario, paper_path):
    sc = paper_scenario(3)
    first, _ = timed_motion(sc, paper_path(3))
    rs = resample(first, None, time_step_s=0.25)
    return sc, Executing(first, rs.indices, 100 * S)


def test_a_following_arm_starts_the_plan_on_its_trajectory(executing):
    _, ex = executing
    traj = ex.trajectory
    t_now = 0.3 * traj.duration_s
    now = ex.start_ns + int(t_now * S)
    measured = traj.positions_rad[np.searchsorted(traj.times_s, t_now - 0.01)]
    start, join, why = plan_start(ex, now, measured + np.radians(0.5), now - S // 100, 1.0, np.radians(2.0),
                                  PERIODIC)
    assert why is None and join is not None
    assert traj.times_s[join.horizon_index] >= t_now + 1.0 > traj.times_s[join.horizon_index - 1]
    np.testing.assert_array_equal(start, traj.positions_rad[join.horizon_index])


def test_a_plan_takes_over_the_running_trajectory_not_after_the_ones_waiting_far_ahead(executing):
    """
    Plans from the end of the running trajectory (stamped far ahead) do not make later plans wait for them.

    The arm runs on R (started 0.3 of its duration ago); A was sent from R's end (waiting for its
    stamp), B from A's end.  A new plan joins R at the horizon: a newer message stamped before
    the waiting ones drops them.  It had joined the newest at its first point (an audit on the
    4-joint servicer: a retarget stamped 141 s ahead, a target on the running path answered
    ``start_in_collision`` for a posture 140 s away), and once B was joined the chain had lost
    R (cut 2 s before B's start): the arm on R read as "no sign that it follows", planned from
    rest, a velocity step.  Oracle: the running trajectory's own samples.
    """
    _, ex = executing
    traj = ex.trajectory
    end_ns = ex.start_ns + int(round(traj.duration_s * S))
    t_now = 0.3 * traj.duration_s
    now = ex.start_ns + int(t_now * S)
    waiting = ex.joined_by(traj, ex.published, end_ns, now)                     # A: from R's end
    later = waiting.joined_by(traj, ex.published, end_ns + int(round(traj.duration_s * S)), now)    # B: from A's
    assert later.first_start_ns() == ex.start_ns                                 # R kept in the chain
    measured = ex.expected_at(now - S // 100)
    for newest in (waiting, later):
        start, join, why = plan_start(newest, now, measured, now - S // 100, 1.0, np.radians(2.0), PERIODIC)
        assert why is None and join is not None, why
        assert join.executing.start_ns == ex.start_ns                            # on R
        assert traj.times_s[join.horizon_index] >= t_now + 1.0 > traj.times_s[join.horizon_index - 1]
        np.testing.assert_array_equal(start, traj.positions_rad[join.horizon_index])
    # a trajectory waiting for a stamp within the horizon is the one joined, as before
    soon = ex.joined_by(traj, ex.published, now + S // 2, now)
    _, join, _ = plan_start(soon, now, measured, now - S // 100, 1.0, np.radians(2.0), PERIODIC)
    assert join.executing is soon and join.horizon_index == int(np.searchsorted(traj.times_s, 0.5))


@pytest.mark.parametrize("case", ["pushed_away", "stale_before_start", "before_start", "finished", "no_horizon"])
def test_otherwise_the_plan_starts_at_the_measured_state(executing, case):
    _, ex = executing
    traj = ex.trajectory
    now = ex.start_ns + int(0.3 * traj.duration_s * S)
    q = traj.positions_rad[np.searchsorted(traj.times_s, 0.3 * traj.duration_s)].copy()
    measured_ns, horizon = now - S // 100, 1.0
    if case == "pushed_away":
        q[2] += np.radians(3.0)
    elif case == "stale_before_start":                # at its first point, but 0.6 s before a start 0.05 s ago
        now, measured_ns = ex.start_ns + S // 20, ex.start_ns - 6 * S // 10
        q = traj.positions_rad[0].copy()
    elif case == "before_start":                      # the trajectory began 0.05 s ago
        now, measured_ns = ex.start_ns + S // 20, ex.start_ns - S // 10
    elif case == "finished":
        now = ex.start_ns + int((traj.duration_s + 1.0) * S)
        measured_ns = now - S // 100
    else:
        horizon = 0.0
    start, join, why = plan_start(ex, now, q, measured_ns, horizon, np.radians(2.0), PERIODIC)
    assert join is None
    np.testing.assert_array_equal(start, q)
    expect = {"pushed_away": "elbow 3.00°", "stale_before_start": "0.65 s old and from before the trajectory started",
              "before_start": "since the trajectory started",
              "finished": None, "no_horizon": None}[case]
    assert (why is None) if expect is None else (expect in why), why


def test_a_late_state_taken_on_the_moving_trajectory_joins_and_says_so(executing):
    """
    A loaded executor delivers joint_states late while the controller goes on.

    The last one, 1 s old, had the arm on its trajectory then: the plan joins at the horizon from
    now, and the warning names the state's age; the same late state 3° off plans from it at rest.
    """
    _, ex = executing
    traj = ex.trajectory
    t_now = 0.5 * traj.duration_s
    now = ex.start_ns + int(t_now * S)
    measured_ns = now - S
    q = ex.expected_at(measured_ns) + np.radians(0.5)
    start, join, why = plan_start(ex, now, q, measured_ns, 1.0, np.radians(2.0), PERIODIC)
    assert join is not None and "1.00 s old" in why and "assuming the arm still follows it" in why, why
    assert traj.times_s[join.horizon_index] >= t_now + 1.0 > traj.times_s[join.horizon_index - 1]
    np.testing.assert_array_equal(start, traj.positions_rad[join.horizon_index])
    q[0] += np.radians(3.0)
    start, join, why = plan_start(ex, now, q, measured_ns, 1.0, np.radians(2.0), PERIODIC)
    assert join is None and "does not follow its trajectory" in why, why
    np.testing.assert_array_equal(start, q)


@pytest.mark.parametrize("joined", [False, True], ids=["from_rest", "joined"])
def test_a_recent_state_from_before_the_start_at_its_first_point_follows(executing, joined):
    """
    Under load the first joint_states after a trajectory's start arrive late.

    The last one, taken before the start (the controller holds the first point until the stamp),
    is at the trajectory's first point: the arm counts as following, the plan joins.  (For a
    trajectory joined to an older one the state before its start is on the older one.)
    """
    _, ex = executing
    traj = ex.trajectory
    if joined:             # an older trajectory (the same one, earlier) that this one was joined to
        older = Executing(traj, ex.published, ex.start_ns - 10 * S)
        ex = older.joined_by(traj, ex.published, ex.start_ns)
    now, measured_ns = ex.start_ns + S // 10, ex.start_ns - S // 5      # 0.1 s in; the state 0.2 s before
    q = ex.expected_at(measured_ns) + np.radians(0.5)
    start, join, why = plan_start(ex, now, q, measured_ns, 1.0, np.radians(2.0), PERIODIC)
    assert why is None and join is not None
    np.testing.assert_array_equal(start, traj.positions_rad[join.horizon_index])
    # the same state 3° away from that first point: not following, planned from it at rest
    q[1] += np.radians(3.0)
    start, join, why = plan_start(ex, now, q, measured_ns, 1.0, np.radians(2.0), PERIODIC)
    expect = "does not follow its trajectory" if joined else "since the trajectory started"
    assert join is None and expect in why and "shoulder 3.50°" in why, why
    np.testing.assert_array_equal(start, q)


def test_a_periodic_attitude_a_turn_away_still_follows(executing):
    _, ex = executing
    traj = ex.trajectory
    now = ex.start_ns + int(0.3 * traj.duration_s * S)
    q = traj.positions_rad[np.searchsorted(traj.times_s, 0.3 * traj.duration_s)] + np.array([2 * np.pi, 0, 0])
    _, join, why = plan_start(ex, now, q, now, 1.0, np.radians(2.0), PERIODIC)
    assert join is not None and why is None


@pytest.mark.parametrize("frac", [0.1, 0.5, 0.85])
def test_the_joined_trajectory_continues_the_executing_one(executing, frac):
    sc, ex = executing
    old = ex.trajectory
    vmax, amax = joint_limits(sc)
    now = ex.start_ns + int(frac * old.duration_s * S)
    start, join, _ = plan_start(ex, now, old.positions_rad[np.searchsorted(old.times_s, frac * old.duration_s)],
                                now, 1.0, np.radians(2.0), PERIODIC)
    new = new_path_from(start)
    later = now + S // 5                              # the plan took 0.2 s
    lead_s = 0.02
    traj, _, stamp_ns, c = joined_motion(sc, join, new, later, lead_s=lead_s)
    # the join: the first published point of the executing trajectory lead_s after "later"
    assert c.index in set(ex.published.tolist())
    assert stamp_ns == ex.start_ns + int(round(old.times_s[c.index] * S)) and stamp_ns >= later + lead_s * S
    pub_times = old.times_s[ex.published]
    assert not np.any((pub_times >= 1e-9 * (later - ex.start_ns) + lead_s)
                      & (pub_times < old.times_s[c.index] - 1e-12))
    np.testing.assert_array_equal(traj.positions_rad[0], old.positions_rad[c.index])
    v_old = old.velocities_rad_s[c.index]
    assert np.linalg.norm(v_old) > np.radians(0.5)
    assert np.all(np.abs(traj.velocities_rad_s[0] - v_old) <= 1e-3 * vmax)
    # the executing path towards the horizon point (up to where a corner blend may begin),
    # then the new path to its goal; collision-free by shapely at every point
    m = max(1, join.horizon_index - c.index + 1 - max(BLEND_SAMPLES))
    np.testing.assert_array_equal(traj.positions_rad[:m], old.positions_rad[c.index:c.index + m])
    np.testing.assert_array_equal(traj.positions_rad[-1], new[-1])
    check_trajectory(traj, np.vstack([traj.positions_rad[0], new[-1]]), vmax, amax, v0=traj.velocities_rad_s[0])
    assert min(shapely_clearance(sc.robot, sc.scene, q) for q in traj.positions_rad[::3]) > sc.scene.safety_margin_m


def _following_at(ex, frac):
    """Return (now ns, start, join) of a replan with the arm on ``ex`` at ``frac`` of its duration (1 s horizon)."""
    old = ex.trajectory
    t = frac * old.duration_s
    now = ex.start_ns + int(t * S)
    start, join, _ = plan_start(ex, now, old.positions_rad[np.searchsorted(old.times_s, t)], now, 1.0,
                                np.radians(2.0), PERIODIC)
    return now, start, join


def _line_from(start, direction):
    """Return a new path: 0.3 rad straight from ``start`` along the unit ``direction``, 120 rows."""
    return start + np.linspace(0.0, 0.3, 120)[:, None] * direction


def test_a_replan_to_a_moved_target_does_not_stop_at_the_horizon_point(executing):
    """
    The planner's path from the horizon point to a target 10 cm away leaves it in another direction.

    The arm keeps most of its speed through that corner (the blend), and the joined motion stays
    collision-free (shapely) and within the limits.
    """
    from spacerobot_planner.planner import Planner
    from spacerobot_planner.scene import Target
    sc, ex = executing
    old = ex.trajectory
    vmax, amax = joint_limits(sc)
    now, start, join = _following_at(ex, 0.5)
    moved = sc.with_scene(sc.scene.with_target(Target(center_m=(-3.17, -2.60), yaw_rad=0.0)))
    res = Planner(moved).plan(start)
    assert res.ok
    traj, _, _, c = joined_motion(moved, join, res.path_rad, now + S // 20)
    speed_then = float(np.linalg.norm(old.velocities_rad_s[join.horizon_index]))
    near = np.abs(traj.times_s - (old.times_s[join.horizon_index] - c.join_time_s)) < 1.5
    slowest = float(np.min(np.linalg.norm(traj.velocities_rad_s[near], axis=1)))
    print(f"\narm speed at the horizon point {np.degrees(speed_then):.2f}°/s; slowest within 1.5 s of it "
          f"{np.degrees(slowest):.2f}°/s")
    assert slowest >= 0.75 * speed_then
    check_trajectory(traj, np.vstack([traj.positions_rad[0], res.path_rad[-1]]), vmax, amax,
                     v0=traj.velocities_rad_s[0])
    clr = min(shapely_clearance(sc.robot, moved.scene, q) for q in traj.positions_rad)
    assert clr > moved.scene.safety_margin_m


@pytest.mark.parametrize("turn_deg", [3.0, 6.0])
def test_a_join_a_few_rows_before_a_turn_starts_in_the_arms_direction(executing, turn_deg):
    """
    A joined trajectory starts with the arm's velocity, a few rows before a corner too.

    The plan took most of the horizon: three rows of executing path lie between the join and the
    new path, which leaves the horizon point ``turn_deg`` off the arm's direction.  The joined
    trajectory starts with the arm's velocity: its direction exactly (the velocity the test reads
    at the join on the executing trajectory), its size within the timing's start tolerance (1e-3).
    A spline re-fitted through those rows and the corner left at 0.39 % and 0.77 % off it.  The
    motion keeps to the limits (the test's finite differences) and clear of the scene (shapely).
    """
    sc, ex = executing
    old = ex.trajectory
    vmax, amax = joint_limits(sc)
    now, start, join = _following_at(ex, 0.4)
    new = _line_from(start, turned(old.velocities_rad_s[join.horizon_index], turn_deg))
    traj, _, _, c = joined_motion(sc, join, new, now + int(0.75 * S), lead_s=0.02)
    assert len(c.prefix_rad) == 3
    v_arm, v = old.velocities_rad_s[c.index], traj.velocities_rad_s[0]
    across = np.linalg.norm(v - (v @ v_arm) / (v_arm @ v_arm) * v_arm)
    assert across <= 1e-9 * np.linalg.norm(v_arm)
    assert abs(np.linalg.norm(v) / np.linalg.norm(v_arm) - 1.0) <= 1e-3
    check_trajectory(traj, np.vstack([traj.positions_rad[0], new[-1]]), vmax, amax, v0=v)
    assert min(shapely_clearance(sc.robot, sc.scene, q) for q in traj.positions_rad[::3]) > sc.scene.safety_margin_m


def test_a_turn_too_sharp_for_the_arms_direction_is_entered_along_the_paths_own_tangent(executing):
    """
    Where no candidate can be entered leaving the join along the arm's direction, the chain times it along its own.

    Three rows before a 15° turn at the arm's speed, every candidate (the corner and its blends)
    leaving along the arm's direction asks for a slower arm; along the spline's own tangent one
    can be entered.  The published trajectory starts exactly in the arm's state (position,
    velocity, acceleration), and the controller's motion through its points (the test's quintics)
    keeps the limits and the scene's margin (shapely).
    """
    from spacerobot_planner.adapters import post_process
    from spacerobot_planner.replanning import joined_paths, start_tangent
    sc, ex = executing
    old = ex.trajectory
    vmax, amax = joint_limits(sc)
    now, start, join = _following_at(ex, 0.4)
    new = _line_from(start, turned(old.velocities_rad_s[join.horizon_index], 15.0))
    later = now + int(0.75 * S)
    paths = joined_paths(sc, join, new, later, lead_s=0.02)
    c = paths.continuation
    for cand in paths.candidates:
        with pytest.raises(ValueError, match="start_path_speed"):
            timed_motion(sc, cand, start_path_speed=c.start_path_speed, start_tangent=start_tangent(c))
    out = post_process(sc, new, join=join, now_ns=later, lead_s=0.02)
    traj = out.trajectory
    assert out.continuation is not None and len(out.continuation.prefix_rad) == 3
    for got, want in ((traj.positions_rad[0], old.positions_rad[c.index]),
                      (traj.velocities_rad_s[0], old.velocities_rad_s[c.index]),
                      (traj.accelerations_rad_s2[0], old.accelerations_rad_s2[c.index])):
        np.testing.assert_array_equal(got, want)
    q, v, a = controller_motion(traj, 40 * len(traj.times_s))
    assert np.max(np.abs(v) / vmax) <= 1.0 + 2e-3 and np.max(np.abs(a) / amax) <= 1.0 + 2e-3
    assert min(shapely_clearance(sc.robot, sc.scene, p) for p in q[::5]) > sc.scene.safety_margin_m


def test_a_plan_that_took_longer_than_the_horizon_is_refused(executing):
    sc, ex = executing
    old = ex.trajectory
    now = ex.start_ns + int(0.3 * old.duration_s * S)
    start, join, _ = plan_start(ex, now, old.positions_rad[np.searchsorted(old.times_s, 0.3 * old.duration_s)],
                                now, 1.0, np.radians(2.0), PERIODIC)
    with pytest.raises(HorizonPassed, match="behind the arm"):
        joined_motion(sc, join, new_path_from(start), now + 2 * S)


def test_at_the_horizon_of_the_end_a_remainder_then_the_new_motion(executing):
    """
    The horizon at the executing trajectory's goal.

    Whatever the new path does there (here it turns straight back), the published motion continues
    the old one and ends at the new goal, within the limits.
    """
    sc, ex = executing
    old = ex.trajectory
    vmax, amax = joint_limits(sc)
    t = old.duration_s - 0.8
    now = ex.start_ns + int(t * S)
    start, join, _ = plan_start(ex, now, old.positions_rad[np.searchsorted(old.times_s, t)], now, 5.0,
                                np.radians(2.0), PERIODIC)
    assert join.horizon_index == len(old) - 1
    back = old.positions_rad[::-1][:60]                 # straight back along the old path
    traj, _, _, c = joined_motion(sc, join, back, now)
    np.testing.assert_array_equal(traj.positions_rad[0], old.positions_rad[c.index])
    assert np.all(np.abs(traj.velocities_rad_s[0] - old.velocities_rad_s[c.index]) <= 1e-3 * vmax)
    np.testing.assert_array_equal(traj.positions_rad[-1], back[-1])
    check_trajectory(traj, np.vstack([traj.positions_rad[0], back[-1]]), vmax, amax, v0=traj.velocities_rad_s[0])


# the servicer's slow, wheel-limited trajectories: published points seconds apart
SERVICER_JOINS = [((11.0, -18.0, -37.0), 0.1, "back"), ((-16.0, -6.0, -38.0), 0.4, "same"),
                  ((11.0, -18.0, -37.0), 0.1, "same"), ((5.0, -10.0, -20.0), 0.1, "same"),
                  ((-16.0, -6.0, -38.0), 0.1, "same"), ((0.0, 0.0, 0.0), 0.1, "other")]


def test_a_joined_servicer_replan_never_steps_the_velocity_nor_exceeds_the_wheel_limits():
    """
    Replans joined to servicer_3dof trajectories (wheels 50 N·m·s, 0.5 N·m), as the node joins them.

    Each is either published (joined) with the executing trajectory's state at the join (its
    position, velocity and acceleration at that published point, exactly) and the wheels'
    load of the controller's motion within the limits (SciPy's quintic, the test's momentum
    sum), or refused with ValueError, which the node answers by planning again (a longer
    horizon, the executing trajectory's end).  Before: 45 of 48 such joins stepped the velocity
    (17 reversed it: a path back, joined at the horizon point itself), and 7 of 48 drove the
    wheel torque to 1.15-1.37 times its limit (a re-timing that could not be entered was
    dropped and the over-limit round published); until the first point took the arm's state, a
    join with a two-row prefix started along the re-fitted spline's tangent (5.3 % off here).
    """
    import os
    from spacerobot_planner.adapters import post_process
    from spacerobot_planner.config import load_scenario
    from spacerobot_planner.planner import Planner
    sc = load_scenario(os.path.join(os.path.dirname(__file__), "..", "config", "servicer_3dof.yaml"))
    robot, planner = sc.robot, Planner(sc)
    published, refused = 0, 0
    for offset_deg, frac, goal in SERVICER_JOINS:
        start = sc.start_rad + np.radians(offset_deg)
        first = post_process(sc, planner.plan(start, sc.goal_rad).path_rad, start_rad=start)
        ex = Executing(first.dense, first.indices, 100 * S)
        now = ex.start_ns + int(frac * ex.trajectory.duration_s * S)
        q_from, join, why = plan_start(ex, now, ex.expected_at(now - S // 100), now - S // 100, 1.0,
                                       np.radians(2.0), robot.planned_periodic)
        assert join is not None, why
        res = planner.plan(q_from, {"back": start, "same": sc.goal_rad,
                                    "other": sc.goal_rad + np.radians([-30.0, 5.0, 10.0])}[goal])
        assert res.ok, res.reason
        try:
            out = post_process(sc, res.path_rad, join=join, now_ns=now + S // 4, lead_s=0.65)
        except ValueError:
            refused += 1
            continue
        published += 1
        traj, k = out.trajectory, out.continuation.index
        v_ex, v0 = ex.trajectory.velocities_rad_s[k], traj.velocities_rad_s[0]
        np.testing.assert_allclose(traj.positions_rad[0], ex.trajectory.positions_rad[k], atol=1e-9)
        # the arm's state exactly (the joined path's re-fitted tangent was 3.0° and 5.3 % off it here)
        np.testing.assert_array_equal(v0, v_ex, err_msg=f"{(offset_deg, frac, goal)}")
        np.testing.assert_array_equal(traj.accelerations_rad_s2[0], ex.trajectory.accelerations_rad_s2[k])
        h, tau = controller_wheel_load(sc, traj, 40 * len(traj.times_s))
        assert np.max(np.abs(h)) <= 50.0 * (1 + 2e-3) and np.max(np.abs(tau)) <= 0.5 * (1 + 2e-3), \
            (offset_deg, frac, goal, np.max(np.abs(tau)))
    assert published >= 2 and refused >= 2, (published, refused)


def test_a_servicer_replan_back_stops_on_the_executing_path_and_goes_back():
    """
    The session's third try (``stopping_join``): stop on the executing path as soon as the limits allow.

    servicer_3dof, at 10 % of a 241 s motion, a new goal back at its start: the new path cannot be
    entered at speed (it turns back; weak wheels brake slowly).  Published: the executing state at
    the join, the executing path to the stopping point, at rest there (44 s after the join: the
    wheels brake slowly, but not the 215 s of motion left), then the new path from rest to its
    goal; the wheels' load of the controller's motion within the limits (SciPy's quintic, the
    test's momentum sum).
    """
    import os
    from spacerobot_planner.adapters import post_process
    from spacerobot_planner.config import load_scenario
    from spacerobot_planner.planner import Planner
    from spacerobot_planner.replanning import stopping_join
    sc = load_scenario(os.path.join(os.path.dirname(__file__), "..", "config", "servicer_3dof.yaml"))
    robot, planner = sc.robot, Planner(sc)
    start = sc.start_rad + np.radians([11.0, -18.0, -37.0])
    first = post_process(sc, planner.plan(start, sc.goal_rad).path_rad, start_rad=start)
    ex = Executing(first.dense, first.indices, 100 * S)
    old = ex.trajectory
    now = ex.start_ns + int(0.1 * old.duration_s * S)
    _, join, _ = plan_start(ex, now, ex.expected_at(now - S // 100), now - S // 100, 1.0, np.radians(2.0),
                            robot.planned_periodic)
    stop = stopping_join(sc, join, now, 0.65)
    assert stop.stop and join.horizon_index <= stop.horizon_index < len(old) - 1
    res = planner.plan(stop.start_rad, start)
    assert res.ok, res.reason
    out = post_process(sc, res.path_rad, join=stop, now_ns=now + S // 4, lead_s=0.65)
    traj, c = out.trajectory, out.continuation
    assert out.certified and out.refused is None
    np.testing.assert_array_equal(traj.positions_rad[0], old.positions_rad[c.index])
    v_ex, v0 = old.velocities_rad_s[c.index], traj.velocities_rad_s[0]
    assert np.linalg.norm(v_ex) > 0 and np.linalg.norm(v0 - v_ex) <= 0.06 * np.linalg.norm(v_ex)
    at_stop = np.flatnonzero(np.all(np.abs(traj.positions_rad - old.positions_rad[stop.horizon_index]) <= 1e-9,
                                    axis=1))
    assert len(at_stop) == 1 and np.all(np.abs(traj.velocities_rad_s[at_stop[0]]) <= 1e-9)
    k = int(at_stop[0])
    stop_s = traj.times_s[k]
    assert stop_s < 0.3 * (old.duration_s - old.times_s[c.index]), stop_s       # not at the executing end
    on = old.positions_rad[c.index:stop.horizon_index + 1]
    gap = np.min(np.linalg.norm(traj.positions_rad[:k, None, :] - on[None], axis=2), axis=1)
    assert np.all(gap <= np.max(np.linalg.norm(np.diff(on, axis=0), axis=1)))   # on the executing path
    np.testing.assert_allclose(traj.positions_rad[-1], start, atol=1e-9)
    h, tau = controller_wheel_load(sc, traj, 40 * len(traj.times_s))
    assert np.max(np.abs(h)) <= 50.0 * (1 + 2e-3) and np.max(np.abs(tau)) <= 0.5 * (1 + 2e-3)


def _servicer_stopped_and_sent_back():
    """
    Return (scenario, planner, Executing, r): a servicer_3dof trajectory at rest at its point r, then on.

    A first trajectory from rest, stopped on its path at 10 % and sent back to its start (the
    session's stop rung): old path, at rest at the stop (r: its one published point at rest before
    its end, found here by its velocities), then the path back.
    """
    import os
    from spacerobot_planner.adapters import post_process
    from spacerobot_planner.config import load_scenario
    from spacerobot_planner.planner import Planner
    from spacerobot_planner.replanning import stopping_join
    sc = load_scenario(os.path.join(os.path.dirname(__file__), "..", "config", "servicer_3dof.yaml"))
    planner = Planner(sc)
    start = sc.start_rad + np.radians([11.0, -18.0, -37.0])
    first = post_process(sc, planner.plan(start, sc.goal_rad).path_rad, start_rad=start)
    ex = Executing(first.dense, first.indices, 100 * S)
    now = ex.start_ns + int(0.1 * ex.trajectory.duration_s * S)
    _, join, _ = plan_start(ex, now, ex.expected_at(now - S // 100), now - S // 100, 1.0, np.radians(2.0),
                            sc.robot.planned_periodic)
    stop = stopping_join(sc, join, now, 0.65)
    second = post_process(sc, planner.plan(stop.start_rad, start).path_rad, join=stop, now_ns=now + S // 4,
                          lead_s=0.65)
    ex2 = Executing(second.dense, second.indices, second.join_stamp_ns)
    old, pub = ex2.trajectory, np.asarray(second.indices)
    resting = pub[(np.linalg.norm(old.velocities_rad_s[pub], axis=1) == 0.0) & (pub < len(old) - 1)]
    assert len(resting) == 1, resting                   # the first trajectory's stop, then on
    return sc, planner, ex2, int(resting[0])


@pytest.mark.parametrize("before_s", [12.0, 8.0, 3.0])
def test_a_stop_on_a_trajectory_that_stops_itself_is_where_it_stops(before_s):
    """
    The stop rung on an executing trajectory that itself stops on the way (an earlier stop, then back): there.

    servicer_3dof (:func:`_servicer_stopped_and_sent_back`), ``before_s`` before the executing
    trajectory comes to rest, the session's stop rung for another goal.  The stop is where the
    executing trajectory comes to rest, the plan starts there from rest, stamped no earlier than
    the arm gets there (the executing trajectory is what it does until then), within the wheel
    limits.  Before, the stop was searched past that point: at 12 s and 8 s the search braked
    through it to the trajectory's end, 66 s later, where a re-timed braking could not be entered
    at the arm's speed (a servicer audit: a retarget waited for an executing trajectory 143 s
    long); at 3 s the arm, at rest there, was sent 12 s on along the old path before it stopped again.
    """
    from spacerobot_planner.adapters import AFTER_THE_END_S, post_process
    from spacerobot_planner.replanning import stopping_join
    sc, planner, ex2, r = _servicer_stopped_and_sent_back()
    old = ex2.trajectory
    rest_ns = ex2.start_ns + int(round(old.times_s[r] * S))
    now2 = rest_ns - int((before_s + 1.65) * S)
    _, join2, why = plan_start(ex2, now2, ex2.expected_at(now2 - S // 100), now2 - S // 100, 1.0,
                               np.radians(2.0), sc.robot.planned_periodic)
    assert join2 is not None, why
    stop = stopping_join(sc, join2, now2, 0.65)
    assert stop.stop and stop.horizon_index == r, (stop.horizon_index, r, len(old))
    goal = sc.goal_rad + np.radians([-10.0, 5.0, 10.0])
    res = planner.plan(stop.start_rad, goal)
    assert res.ok, res.reason
    out = post_process(sc, res.path_rad, join=stop, now_ns=now2 + S // 4, lead_s=0.65)
    traj = out.trajectory
    assert out.refused is None and out.certified and out.continuation is None
    assert out.stamp_exact and out.not_before_ns == rest_ns + int(round(AFTER_THE_END_S * S))
    np.testing.assert_array_equal(traj.positions_rad[0], old.positions_rad[r])
    assert np.all(traj.velocities_rad_s[0] == 0.0)
    np.testing.assert_allclose(traj.positions_rad[-1], goal, atol=1e-9)
    h, tau = controller_wheel_load(sc, traj, 40 * len(traj.times_s))
    assert np.max(np.abs(h)) <= 50.0 * (1 + 2e-3) and np.max(np.abs(tau)) <= 0.5 * (1 + 2e-3)


def test_a_replan_where_the_arm_rests_at_the_join_starts_there():
    """
    The first try's join is a point where the executing trajectory rests (a stop it was sent with): from there, at rest.

    servicer_3dof (:func:`_servicer_stopped_and_sent_back`), the join (the first published point
    the lead ahead) at the stop and the horizon point beyond it on the path back: the plan starts at
    the stop from rest (``replanning.resting_join``), stamped just after the arm is there
    (``adapters.starts_at_the_end``), and never goes on along the executing path after it (the test's
    nearest-point distance to the executing rows after the stop).  Without it the plan followed the
    executing path on past the stop to the horizon point and turned there.  A trajectory sent and
    not begun (the arm held at its first point at rest): the same, stamped at its very stamp.
    """
    from spacerobot_planner.adapters import AFTER_THE_END_S, post_process, starts_at_the_end
    from spacerobot_planner.replanning import resting_join
    sc, planner, ex2, r = _servicer_stopped_and_sent_back()
    old = ex2.trajectory
    rest_ns = ex2.start_ns + int(round(old.times_s[r] * S))
    now = rest_ns - int(0.66 * S)                     # the stop is the first point the lead (0.65 s) ahead
    _, join, why = plan_start(ex2, now, ex2.expected_at(now - S // 100), now - S // 100, 8.0, np.radians(2.0),
                              sc.robot.planned_periodic)
    assert join is not None and join.horizon_index > r + 1, (why, join and join.horizon_index, r)
    taken = resting_join(join, now, 0.65)
    assert taken.stop and taken.horizon_index == r
    goal = sc.goal_rad + np.radians([-10.0, 5.0, 10.0])
    res = planner.plan(taken.start_rad, goal)
    assert res.ok, res.reason
    out = post_process(sc, res.path_rad, join=taken, now_ns=now, lead_s=0.65)
    assert out.refused is None and out.certified and out.continuation is None and out.stamp_exact
    assert out.not_before_ns == rest_ns + int(round(AFTER_THE_END_S * S))
    dense = out.dense
    np.testing.assert_array_equal(dense.positions_rad[0], old.positions_rad[r])
    assert np.all(dense.velocities_rad_s[0] == 0.0)
    after = old.positions_rad[r + 1:join.horizon_index + 1]           # the executing path on past the stop
    gap = np.min(np.linalg.norm(dense.positions_rad[:, None, :] - after[None], axis=2), axis=0)
    assert np.all(gap >= 0.99 * np.linalg.norm(after - old.positions_rad[r], axis=1)), np.degrees(gap)
    # a goal there: a trajectory that holds the arm there, replacing the executing one (which goes on)
    hold = post_process(sc, np.vstack([taken.start_rad, taken.start_rad]), join=taken, now_ns=now, lead_s=0.65)
    assert not hold.at_goal and hold.arm is not None and hold.stamp_exact
    assert hold.not_before_ns == rest_ns + int(round(AFTER_THE_END_S * S))
    assert len(hold.trajectory) == 2 and hold.trajectory.times_s[-1] > 0.0
    np.testing.assert_array_equal(hold.trajectory.positions_rad, old.positions_rad[[r, r]])
    assert np.all(hold.trajectory.velocities_rad_s == 0.0) and np.all(hold.trajectory.accelerations_rad_s2 == 0.0)
    # not begun: the first point, held at rest until its stamp, is where the plan starts, at that stamp
    back = old.subset(np.arange(r, len(old)))                           # the path back, from rest at the stop
    pub = np.asarray(ex2.published)
    waiting = Executing(replace(back, times_s=back.times_s - back.times_s[0]), pub[pub >= r] - r, now + 2 * S)
    _, join0, _ = plan_start(waiting, now, back.positions_rad[0], now, 8.0, np.radians(2.0),
                             sc.robot.planned_periodic)
    first = resting_join(join0, now, 0.65)
    assert first.stop and first.horizon_index == 0
    assert starts_at_the_end(first, now, 0.65) == waiting.start_ns


@pytest.mark.parametrize("frac,goal", [(0.1, "back"), (0.4, "back"), (0.4, "other"), (0.7, "same")])
def test_an_arm_at_its_velocity_limit_is_joined_at_its_speed(frac, goal):
    """
    A replan of the paper 3-DOF arm, cruising at joint 1's velocity limit, joins it at its speed, within the limits.

    As the node's second try does: the horizon 2 s, the chain's lead.  The chain lowers a limit
    only where the controller's motion overshoots it, never at the arm's given state: the
    executing trajectory runs at its limits (joint 1 within 1 % of 5°/s at the join) and the
    joined one is entered at that speed.  Before, the limits were lowered along the whole path:
    the joined re-timing could not be entered at the arm's speed (0.2-1.7 % too fast), and a
    helper's 52 replans of this scene (4 starts, 10/40/70 %, 4 goals, the node's tries) fell to
    the executing trajectory's end in 11 (now 1).  Oracle: SciPy's quintic through the points
    (``oracles.controller_motion``) against the joint limits; the executing velocity at the join.
    """
    import os
    from spacerobot_planner.adapters import post_process
    from spacerobot_planner.config import load_scenario
    from spacerobot_planner.planner import Planner
    sc = load_scenario(os.path.join(os.path.dirname(__file__), "..", "config", "paper_3dof.yaml"))
    planner = Planner(sc)
    first = post_process(sc, planner.plan(sc.start_rad, sc.goal_rad).path_rad, start_rad=sc.start_rad)
    ex = Executing(first.dense, first.indices, 100 * S)
    now = ex.start_ns + int(frac * ex.trajectory.duration_s * S)
    q_from, join, why = plan_start(ex, now, ex.expected_at(now - S // 100), now - S // 100, 2.0,
                                   np.radians(2.0), sc.robot.planned_periodic)
    assert join is not None, why
    res = planner.plan(q_from, {"back": sc.start_rad, "same": sc.goal_rad,
                                "other": sc.goal_rad + np.radians([-30.0, 5.0, 10.0])}[goal])
    assert res.ok, res.reason
    out = post_process(sc, res.path_rad, join=join, now_ns=now + S // 4, lead_s=0.65)
    traj, k = out.trajectory, out.continuation.index
    vmax, amax = sc.joint_limits.planned(sc.robot)
    v_ex = ex.trajectory.velocities_rad_s[k]
    assert abs(v_ex[0]) >= 0.99 * vmax[0], f"the arm is not at joint 1's velocity limit: {v_ex / vmax}"
    np.testing.assert_allclose(traj.positions_rad[0], ex.trajectory.positions_rad[k], atol=1e-9)
    np.testing.assert_array_equal(traj.velocities_rad_s[0], v_ex)       # the arm's state, no step
    _, v, a = controller_motion(traj, 40 * len(traj.times_s))
    assert np.max(np.abs(v) / vmax) <= 1.0 + 2e-3 and np.max(np.abs(a) / amax) <= 1.0 + 2e-3, \
        (np.max(np.abs(v) / vmax), np.max(np.abs(a) / amax))
