"""
Tests of trajectory.py.

Limits hold at every point (published values and finite differences of the positions, by the
test's own check), exact ends, time increases; durations against TOPP-RA (toppra); scaling
factors; a moving start; resampling and its certification (oracles in test/oracles.py).
"""

import os

import numpy as np
import pytest
from hypothesis import example, given, settings, strategies as st
from scipy.interpolate import CubicSpline

from oracles import (check_trajectory, controller_motion, dense_samples, shapely_clearance,
                     toppra_duration_s)
from paper_paths import joint_limits, new_path_from, turned
from spacerobot_planner.collision import CollisionChecker
from spacerobot_planner.published import resample
from spacerobot_planner.trajectory import Lowering, densify_path, sample, shared_path_models, time_parameterize

VMAX = np.radians([5.0, 15.0, 15.0])
AMAX = np.radians([5.0, 20.0, 20.0])


def _spline_path(rng, n_knots=6, dof=3, scale=1.0):
    knots = np.cumsum(rng.normal(0.0, scale, (n_knots, dof)), axis=0)
    cs = CubicSpline(np.linspace(0, 1, n_knots), knots)
    return cs(np.linspace(0, 1, 400))


def test_straight_line_is_trapezoidal_and_fast():
    path = np.array([[0.0, 0.0, 0.0], [1.0, 0.5, -0.2]])
    traj = time_parameterize(path, VMAX, AMAX, ("a", "b", "c"))
    check_trajectory(traj, path, VMAX, AMAX)
    assert traj.joint_names == ("a", "b", "c")
    # joint 0 is the bottleneck: 1 rad at 5°/s with 5°/s² → 1/v + v/a
    ideal = 1.0 / VMAX[0] + VMAX[0] / AMAX[0]
    assert ideal <= traj.duration_s <= 1.1 * ideal


def _one_joint_time_s(length, v, a, s1, s2, v2, n=200_000):
    """Return the time-optimal time of a 1-D motion over ``length``, rest to rest, v ≤ v2 on [s1, s2]: ∫ ds / v."""
    s = (np.arange(n) + 0.5) * (length / n)              # midpoints: 1/v is integrable at the ends
    lim = np.minimum.reduce([np.full(n, v), np.sqrt(2 * a * s), np.sqrt(2 * a * (length - s)),
                             np.sqrt(v2 ** 2 + 2 * a * np.clip(s1 - s, 0, None) + 2 * a * np.clip(s - s2, 0, None))])
    return float(np.sum(length / n / lim))


def test_a_lowered_stretch_is_timed_within_its_limits_and_the_rest_within_its_own():
    """
    ``time_parameterize(lowered=...)``: the limits lowered between two points of a trajectory, nowhere else.

    A straight line on which joint 0 binds (1 rad at 5°/s, 5°/s²); its velocity limit halved from
    the point a third of the way to the one two thirds of the way.  Oracle: the finite
    differences of the output's positions over its times (at most half the limit there, the
    full limit reached outside), and the time-optimal time of that 1-D motion by quadrature
    (cruise, brake into the stretch, half speed, speed up again), within 1 %.
    """
    path = np.array([[0.0, 0.0, 0.0], [1.0, 0.5, -0.2]])
    first = time_parameterize(path, VMAX, AMAX)
    q0 = first.positions_rad[:, 0]
    i, j = int(np.argmin(np.abs(q0 - 1 / 3))), int(np.argmin(np.abs(q0 - 2 / 3)))
    low = Lowering(first.positions_rad[i:j + 1], np.tile([0.5, 1.0, 1.0, 1.0], (j - i, 1)))
    traj = time_parameterize(path, VMAX, AMAX, lowered=(low,))
    check_trajectory(traj, path, VMAX, AMAX)
    q, t = traj.positions_rad[:, 0], traj.times_s
    v = np.diff(q) / np.diff(t)
    mid = 0.5 * (q[1:] + q[:-1])
    inside = (mid > q0[i]) & (mid < q0[j])
    assert np.max(v[inside]) <= 0.5 * VMAX[0] * (1 + 1e-6)
    assert np.max(v[~inside]) >= 0.99 * VMAX[0]
    expect = _one_joint_time_s(1.0, VMAX[0], AMAX[0], q0[i], q0[j], 0.5 * VMAX[0])
    assert expect <= traj.duration_s * (1 + 1e-6) and traj.duration_s <= 1.01 * expect, (traj.duration_s, expect)


def test_a_path_back_over_the_same_samples_is_not_lowered_by_a_stretch_of_the_path_out():
    """
    A stretch lowers the path whose points it holds in their order, not a path back through them.

    A stop on the executing path and the new path back over it share samples: the chain's
    stretches (from the published points of such a trajectory) matched on positions alone
    lowered the way back too, and a servicer_3dof replan's re-timings grew 268 s to 1 916 s
    before the session gave up on them.  Here: the lowered path out is slower, the path back
    (its samples reversed) timed exactly as without the stretch.
    """
    out = densify_path(np.array([[0.0, 0.0, 0.0], [1.0, 0.5, -0.2], [1.2, 1.0, 0.3]]))
    first = time_parameterize(out, VMAX, AMAX)
    n = len(first.times_s)
    low = Lowering(first.positions_rad[n // 4:3 * n // 4], np.tile([0.5, 0.5, 1.0, 1.0], (3 * n // 4 - n // 4 - 1, 1)))
    assert time_parameterize(out, VMAX, AMAX, lowered=(low,)).duration_s > 1.2 * first.duration_s
    back = first.positions_rad[::-1]
    plain, lowered = time_parameterize(back, VMAX, AMAX), time_parameterize(back, VMAX, AMAX, lowered=(low,))
    np.testing.assert_array_equal(lowered.times_s, plain.times_s)


def test_a_stretch_the_timing_cannot_read_is_refused():
    """A Lowering without K + 1 ≥ 2 points and K rows of 4 factors in (0, 1], or of other joints: ValueError."""
    pts = np.column_stack([np.linspace(0.0, 1.0, 5), np.zeros(5)])
    bad = ((pts, np.full((3, 4), 0.5), "factors"), (pts[:1], np.full((0, 4), 0.5), "points"),
           (pts, np.full((4, 4), 1.5), r"\(0, 1\]"), (pts, np.full((4, 4), np.nan), r"\(0, 1\]"))
    for points, factors, what in bad:
        with pytest.raises(ValueError, match=what):
            Lowering(points, factors)
    low = Lowering(np.column_stack([pts, pts[:, :1]]), np.full((4, 4), 0.5))
    with pytest.raises(ValueError, match="joints"):
        time_parameterize(pts, np.ones(2), np.ones(2), lowered=(low,))


def test_a_moving_start_is_kept_from_a_stretch_it_cannot_enter_however_far_ahead():
    """
    A moving arm's speed is given: where a stretch ahead leaves no way to brake for it, that stretch is not lowered.

    1 rad along joint 0 (2 rad/s, 1 rad/s²), the arm entering at 1.3 rad/s (stopping takes 0.845
    rad); the acceleration lowered to 0.3 over the last 30 % of the path would need the arm at
    most at 0.42 rad/s by 0.7 rad, 0.755 rad of braking: it cannot enter.  The time
    parameterisation keeps more and more of the path from the lowering, from the start, until
    the arm's speed enters: here the whole path (the stretch lies beyond the first 256 of its
    401 grid points, where that search used to end and refuse).  Oracle: the timing without
    the stretch, bit for bit; a slower arm (0.5 rad/s) is lowered there (slower than without).
    """
    path = np.column_stack([np.linspace(0.0, 1.0, 201), np.zeros(201)])
    vmax, amax = np.array([2.0, 2.0]), np.array([1.0, 1.0])
    low = Lowering(path[140:], np.tile([1.0, 0.3, 1.0, 1.0], (60, 1)))
    plain = time_parameterize(path, vmax, amax, start_path_speed=1.3)
    kept = time_parameterize(path, vmax, amax, start_path_speed=1.3, lowered=(low,))
    np.testing.assert_array_equal(kept.times_s, plain.times_s)
    slow = time_parameterize(path, vmax, amax, start_path_speed=0.5, lowered=(low,))
    assert slow.duration_s > time_parameterize(path, vmax, amax, start_path_speed=0.5).duration_s * 1.05


@pytest.mark.parametrize("seed", range(6))
def test_curved_paths_obey_limits(seed):
    rng = np.random.default_rng(seed)
    path = _spline_path(rng)
    traj = time_parameterize(path, VMAX, AMAX)
    check_trajectory(traj, path, VMAX, AMAX)


@settings(max_examples=25, deadline=None)
@given(st.integers(0, 10_000), st.floats(0.01, 2.0), st.floats(0.1, 100.0))
@example(706, 1.0, 4.0)     # samples 6e-5 s apart at t = 1.65 s: the times' rounding exceeded amax by 1e-7
def test_limits_hold_for_any_path_and_limits(seed, scale, speed):
    rng = np.random.default_rng(seed)
    path = _spline_path(rng, n_knots=int(rng.integers(2, 8)), dof=int(rng.integers(1, 4)), scale=scale)
    vmax = rng.uniform(0.2, 2.0, path.shape[1]) * speed * 0.1
    amax = rng.uniform(0.2, 2.0, path.shape[1]) * speed * 0.1
    traj = time_parameterize(path, vmax, amax)
    check_trajectory(traj, path, vmax, amax)


def test_a_trajectory_longer_than_a_message_holds_is_refused_naming_its_limit():
    """
    A joint limit near 0 (a slip of the finger) makes the motion last more than a message holds.

    Oracle: joint 'a' moves 1 rad, so at v rad/s the motion lasts at least 1 / v s; a
    trajectory message's ``time_from_start`` holds at most 2^31 - 1 whole seconds.
    """
    path = np.array([[0.0, 0.0, 0.0], [1.0, 0.5, -0.2]])
    limit_s = 2.0 ** 31 - 1
    slow = VMAX.copy()
    slow[0] = 1.0 / (2.0 * limit_s)                  # at least twice what a message holds
    with pytest.raises(ValueError, match=r"longer than a trajectory message can hold \(2147483647 s\); "
                                         r"the velocity limit of joint 'a' \(or its scaling factor\) holds it "
                                         r"back for (99|100) % of that time"):
        time_parameterize(path, slow, AMAX, ("a", "b", "c"))
    slow[0] = 2.0 / limit_s                          # at least half of what a message holds: kept
    traj = time_parameterize(path, slow, AMAX, ("a", "b", "c"))
    assert 0.5 * limit_s <= traj.duration_s <= limit_s
    assert np.all(np.diff(traj.times_s) > 0.0)


@pytest.mark.parametrize("seed", range(6))
def test_a_path_touching_a_joint_bound_is_timed_within_its_limits_and_at_rest_there(seed):
    """
    A path whose joint touches its bound at one sample and turns back, timed with the joints' bounds.

    The spline through the samples is kept within the bound (C1 there: q' = 0, q'' jumps): the
    limits still hold by the test's own finite differences and published values
    (``oracles.check_trajectory``), the joint is at rest at that sample, the positions are the
    samples as without the bounds, and a path that stays clear of its bounds is timed bit for bit
    as without them.
    """
    rng = np.random.default_rng(40 + seed)
    lo, hi = np.radians([-170.0, -180.0, -180.0]), np.radians([170.0, 180.0, 180.0])
    depth = np.radians([rng.uniform(0.2, 2.0), rng.uniform(5.0, 30.0)])[rng.permutation(2)]
    path = np.zeros((3, 3))
    path[:, 0] = np.radians(10.0) + np.cumsum(np.radians(rng.uniform(10.0, 40.0, 3)))
    path[:, 1] = lo[1] + np.array([depth[0], 0.0, depth[1]])
    path[1, 1] = lo[1]
    path[:, 2] = np.radians(rng.uniform(-20.0, 20.0, 3))
    traj = time_parameterize(path, VMAX, AMAX, lower_rad=lo, upper_rad=hi)
    check_trajectory(traj, path, VMAX, AMAX)
    on = np.flatnonzero(traj.positions_rad[:, 1] == lo[1])
    assert len(on) == 1 and traj.velocities_rad_s[on[0], 1] == 0.0
    free = time_parameterize(path, VMAX, AMAX)
    np.testing.assert_array_equal(traj.positions_rad, free.positions_rad)
    assert free.velocities_rad_s[on[0], 1] != 0.0                      # the not-a-knot spline's slope there
    clear = path + np.array([0.0, 0.1, 0.0])
    a, b = time_parameterize(clear, VMAX, AMAX, lower_rad=lo, upper_rad=hi), time_parameterize(clear, VMAX, AMAX)
    for x, y in ((a.times_s, b.times_s), (a.velocities_rad_s, b.velocities_rad_s),
                 (a.accelerations_rad_s2, b.accelerations_rad_s2)):
        np.testing.assert_array_equal(x, y)


def _left_right_path_acceleration(traj, k, x_knots):
    """
    Return s̈ on the grid segments before and after knot k (grid refinement 2), by the published times and speeds.

    On each half of a sample interval s̈ is constant, so ṡ² is linear in s there and the half lasts
    2 Δ / (ṡ_a + ṡ_b): the midpoint's ṡ is what makes the two halves add up to the interval's time
    (a root the test finds by bisection); s̈ = (ṡ_b² - ṡ_a²) / (2 Δ).
    """
    from scipy.optimize import brentq
    sd, t = traj.path_speed, traj.times_s

    def mid(i):
        half = 0.5 * (x_knots[i + 1] - x_knots[i])
        f = lambda m: 2 * half / (sd[i] + m) + 2 * half / (m + sd[i + 1]) - (t[i + 1] - t[i])   # noqa: E731
        return half, (brentq(f, 0.0, 1e3) if f(0.0) > 0.0 else 0.0)      # 0: the path stops there
    half, m = mid(k - 1)
    before = (sd[k] ** 2 - m ** 2) / (2 * half)
    half, m = mid(k)
    after = (m ** 2 - sd[k] ** 2) / (2 * half)
    return before, after


@pytest.mark.parametrize("seed", range(4))
def test_the_wheel_torque_is_bounded_on_both_sides_of_a_sample_held_on_a_bound(seed):
    """
    A path of the paper 3-DOF arm touching the shoulder's bound, timed with a wheel torque limit: both sides within it.

    The spline is C1 where it is held on the bound (q' = 0 there in that joint, q'' jumps); the
    wheel's torque mixes the joints, so each side's q'' must be bounded, not only the larger (a
    review: 2.9 × the limit just before such a sample).  Oracle: the spline's two sides from SciPy's
    clamped pieces, s̈ on each side from the published times and path speeds, and the wheel's torque
    by the test's own momentum sum (``oracles.wheel_load``).
    """
    from oracles import wheel_load
    from scipy.interpolate import CubicSpline
    from spacerobot_planner.config import load_scenario
    from spacerobot_planner.spacecraft import WheelModel
    sc = load_scenario(os.path.join(os.path.dirname(__file__), "..", "config", "paper_3dof.yaml"))
    robot = sc.robot
    lo, hi = robot.planned_bounds_rad
    b = int(np.flatnonzero(np.isfinite(lo))[0])
    n = len(lo)
    vmax, amax = np.full(n, 1.0), np.full(n, 2.0)
    rng = np.random.default_rng(90 + seed)
    checked = 0
    while checked < 3:
        depth = np.radians([rng.uniform(0.2, 2.0), rng.uniform(5.0, 30.0)])[rng.permutation(2)]
        corners = np.radians(rng.uniform(-40.0, 40.0, (3, n)))
        corners[:, b] = lo[b] + np.array([depth[0], 0.0, depth[1]])
        p = densify_path(corners, np.radians(0.5))
        k = int(np.flatnonzero(p[:, b] == lo[b])[0])
        report = time_parameterize(p, vmax, amax, wheel=WheelModel(robot, sc.masses), lower_rad=lo, upper_rad=hi)
        if report.velocities_rad_s[k, b] != 0.0 or not 2 <= k <= len(p) - 3:
            continue                                    # not held on the bound: its spline did not pass it
        tau = 0.5 * abs(float(report.wheel_torque_Nm[k])) + 1e-3
        traj = time_parameterize(p, vmax, amax, wheel=WheelModel(robot, sc.masses, None, tau),
                                 lower_rad=lo, upper_rad=hi)
        x = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(p, axis=0), axis=1))])
        whole = CubicSpline(x, p, axis=0)
        pieces = (CubicSpline(x[:k + 1], p[:k + 1, b], bc_type=("not-a-knot", (1, 0.0))),
                  CubicSpline(x[k:], p[k:, b], bc_type=((1, 0.0), "not-a-knot")))
        d1 = whole(x[k], 1)
        d1[b] = 0.0
        u_before, u_after = _left_right_path_acceleration(traj, k, x)
        sd = traj.path_speed[k]
        for piece, u in zip(pieces, (u_before, u_after)):
            d2 = whole(x[k], 2)
            d2[b] = piece(x[k], 2)
            qdd = d1 * u + d2 * sd ** 2
            torque = wheel_load(robot, sc.masses, robot.full(p[k])[None], robot.full(d1 * sd)[None] * 1.0,
                                robot.full(qdd)[None] - robot.full(np.zeros(n))[None])[1][0]
            assert abs(torque) <= tau * (1 + 1e-4), (abs(torque) / tau, seed)
        checked += 1


def test_a_start_velocity_is_kept_or_refused_on_a_path_held_on_a_bound_near_its_start():
    """
    A start velocity on a path whose spline is held on a bound near the start: published as given, or refused.

    The bounded spline leaves its start along another tangent than the plain one (its first piece
    solved again); the start speed is the velocity's projection on the tangent the trajectory
    follows, so the published first velocity is the one given (a review: projected on the plain
    tangent, it jumped from [0.0039, 0.0092] to [0, 0.0092] rad/s).  Here the first piece, a cubic
    through the three samples up to the touch with slope 0 there, leaves the start along the second
    joint alone: a velocity along the first chord (the test's own) is refused, one along the second
    joint is published as given (``oracles.check_trajectory``).
    """
    corners = np.array([[0.004, 0.0], [0.0, 0.012], [0.2, 0.06]])     # joint 0 touches its bound 0 at a sample
    path = densify_path(corners, np.radians(0.5))
    lo, hi = np.array([0.0, -np.inf]), np.array([np.inf, np.inf])
    chord = (corners[1] - corners[0]) / np.linalg.norm(corners[1] - corners[0])
    with pytest.raises(ValueError, match="start_velocity_rad_s: .* off the path's start tangent"):
        time_parameterize(path, np.ones(2), np.ones(2), start_velocity_rad_s=0.01 * chord, lower_rad=lo, upper_rad=hi)
    v0 = np.array([0.0, 0.01])
    traj = time_parameterize(path, np.ones(2), np.ones(2), start_velocity_rad_s=v0, lower_rad=lo, upper_rad=hi)
    check_trajectory(traj, path, np.ones(2), np.ones(2), v0=v0)


def test_bad_joint_bounds_are_refused_naming_them():
    path = np.zeros((2, 3))
    path[1] = 0.5
    with pytest.raises(ValueError, match="lower_rad: expected 3 bounds"):
        time_parameterize(path, VMAX, AMAX, lower_rad=[-1.0, -1.0])
    with pytest.raises(ValueError, match="each lower bound must lie below its upper bound"):
        time_parameterize(path, VMAX, AMAX, lower_rad=[-1.0, 1.0, -1.0], upper_rad=[1.0, 1.0, 1.0])
    with pytest.raises(ValueError, match="upper_rad: expected 3 bounds"):
        time_parameterize(path, VMAX, AMAX, upper_rad=[1.0, float("nan"), 1.0])


def test_start_equals_goal_gives_one_point():
    traj = time_parameterize(np.zeros((5, 2)), VMAX[:2], AMAX[:2])
    assert len(traj) == 1 and traj.duration_s == 0.0


def test_sample_interpolates_and_clamps():
    path = np.array([[0.0, 0.0], [0.2, -0.1]])
    traj = time_parameterize(path, VMAX[:2], AMAX[:2])
    np.testing.assert_array_equal(sample(traj, -1.0)[0], path[0])
    np.testing.assert_array_equal(sample(traj, 1e6)[0], path[-1])
    q, _ = sample(traj, 0.5 * traj.duration_s)
    assert 0.0 < q[0] < 0.2


def test_sample_between_some_points_is_the_linear_interpolation_of_those_points():
    """``sample(traj, t, points)``: numpy's own interpolation of the chosen points, and the subset's bits."""
    path = np.array([[0.0, 0.0, 0.1], [0.4, -0.3, 0.2], [0.1, 0.5, -0.2], [0.6, 0.2, 0.3]])
    traj = time_parameterize(path, VMAX, AMAX)
    rng = np.random.default_rng(3)
    points = np.unique(np.concatenate([[0, len(traj) - 1], rng.choice(len(traj), 12, replace=False)]))
    sub = traj.subset(points)
    for t_s in np.concatenate([[-1.0, 0.0, traj.duration_s, traj.duration_s + 1.0], sub.times_s,
                               rng.uniform(0.0, traj.duration_s, 200)]):
        q, v = sample(traj, t_s, points)
        for j in range(3):
            assert q[j] == pytest.approx(np.interp(t_s, sub.times_s, sub.positions_rad[:, j]), abs=1e-12)
        if t_s < traj.duration_s:
            for j in range(3):
                assert v[j] == pytest.approx(np.interp(t_s, sub.times_s, sub.velocities_rad_s[:, j]), abs=1e-12)
        q0, v0 = sample(sub, t_s)
        assert np.array_equal(q, q0) and np.array_equal(v, v0)


def test_densify_keeps_exact_ends_and_drops_repeats():
    p = np.array([[0.0, 0.0], [0.0, 0.0], [1.0, 0.5], [1.0, 0.5 + 1e-15]])
    out = densify_path(p, 0.3)
    np.testing.assert_array_equal(out[0], p[0])
    np.testing.assert_array_equal(out[-1], p[-1])
    assert np.max(np.abs(np.diff(out, axis=0))) <= 0.3 + 1e-12


@pytest.mark.parametrize("bad", [np.array([[0.0, np.nan], [1.0, 1.0]]), np.zeros((0, 2))])
def test_bad_paths_raise(bad):
    with pytest.raises(ValueError):
        time_parameterize(bad, VMAX[:2], AMAX[:2])


def test_bad_limits_raise():
    with pytest.raises(ValueError, match="max_velocity"):
        time_parameterize(np.zeros((2, 2)) + [[0, 0], [1, 1]], [1.0, 0.0], [1.0, 1.0])
    with pytest.raises(ValueError, match="max_acceleration"):
        time_parameterize(np.zeros((2, 2)) + [[0, 0], [1, 1]], [1.0, 1.0], [1.0])


@pytest.mark.parametrize("dof", [2, 3], ids=["paper_2dof", "paper_3dof"])
def test_durations_within_one_percent_of_toppra_and_limits_hold(dof, paper_scenario, paper_path):
    sc, path = paper_scenario(dof), paper_path(dof)
    vmax, amax = joint_limits(sc)
    traj = time_parameterize(path, vmax, amax, sc.robot.planned_names)
    check_trajectory(traj, path, vmax, amax, consistency=0.02)
    ref = toppra_duration_s(path, vmax, amax)
    assert 0.99 * ref <= traj.duration_s <= 1.01 * ref, (traj.duration_s, ref)
    assert set(traj.active_limit) <= {f"{k}:{j}" for k in ("velocity", "acceleration")
                                      for j in sc.robot.planned_names}
    assert np.all(traj.limit_ratio <= 1 + 1e-9) and np.median(traj.limit_ratio) > 0.999


@pytest.mark.parametrize("dof", [2, 3])
def test_a_start_from_rest_has_zero_velocities_without_a_sign(dof, paper_scenario, paper_path):
    """The first point from rest publishes 0, not -0.0 (``ros2 topic echo`` prints the sign) on joints moving down."""
    sc, path = paper_scenario(dof), paper_path(dof)
    vmax, amax = joint_limits(sc)
    traj = time_parameterize(path, vmax, amax, sc.robot.planned_names)
    first = traj.velocities_rad_s[0]
    assert np.any(path[1] < path[0])                         # a joint that moves down from the start
    assert np.all(first == 0.0) and not np.any(np.signbit(first)), first


def test_scaling_factors_scale_time_exactly(paper_scenario, paper_path):
    """Velocities × k and accelerations × k² make the same profile 1/k slower."""
    sc, path = paper_scenario(3), paper_path(3)
    vmax, amax = joint_limits(sc)
    base = time_parameterize(path, vmax, amax)
    slow = time_parameterize(path, vmax, amax, velocity_scaling=0.5, acceleration_scaling=0.25)
    np.testing.assert_allclose(slow.times_s, 2.0 * base.times_s, rtol=1e-9)
    check_trajectory(slow, path, 0.5 * vmax, 0.25 * amax)
    only_v = time_parameterize(path, vmax, amax, velocity_scaling=0.3)
    check_trajectory(only_v, path, 0.3 * vmax, amax)
    assert only_v.duration_s > 2.5 * base.duration_s
    for bad in (0.0, 1.5, -0.1):
        with pytest.raises(ValueError, match="velocity_scaling"):
            time_parameterize(path, vmax, amax, velocity_scaling=bad)
        with pytest.raises(ValueError, match="acceleration_scaling"):
            time_parameterize(path, vmax, amax, acceleration_scaling=bad)


def test_re_timings_that_share_a_path_model_keep_to_each_path_and_its_limits(paper_scenario, paper_path):
    """
    Within shared_path_models (the chain's re-timings), every timing is that of its own path and limits.

    The same path under lowered scaling factors is 1/k slower (the exact relation) and within
    the lowered limits (the independent check); another path of the same shape is timed on its
    own samples, not the first one's model; changing one trajectory's positions changes no other.
    """
    sc, path = paper_scenario(3), paper_path(3)
    vmax, amax = joint_limits(sc)
    other = path.copy()
    other[1:-1] += np.radians(0.5) * np.sin(np.linspace(0.0, np.pi, len(path)))[1:-1, None]
    with shared_path_models():
        base = time_parameterize(path, vmax, amax)
        base.positions_rad[:] = 0.0                       # a caller's change to its trajectory
        slow = time_parameterize(path, vmax, amax, velocity_scaling=0.5, acceleration_scaling=0.25)
        moved = time_parameterize(other, vmax, amax)
    alone = time_parameterize(path, vmax, amax)
    np.testing.assert_allclose(slow.times_s, 2.0 * alone.times_s, rtol=1e-9)
    check_trajectory(slow, path, 0.5 * vmax, 0.25 * amax)
    check_trajectory(moved, other, vmax, amax)
    assert not np.array_equal(moved.positions_rad, slow.positions_rad)


def test_moving_start_continues_an_executing_trajectory(paper_scenario, paper_path):
    """
    Cut a trajectory at a point where the arm moves, re-parameterise the rest from that velocity.

    Continuous velocity at the switch, limits held (finite differences from the start velocity),
    never slower than starting the rest from rest.
    """
    sc, path = paper_scenario(3), paper_path(3)
    vmax, amax = joint_limits(sc)
    first = time_parameterize(path, vmax, amax)
    k = int(np.searchsorted(first.times_s, 0.4 * first.duration_s))
    v_switch = first.velocities_rad_s[k]
    assert np.linalg.norm(v_switch) > 0.05
    rest = first.positions_rad[k:]
    second = time_parameterize(rest, vmax, amax, start_velocity_rad_s=v_switch)
    np.testing.assert_allclose(second.velocities_rad_s[0], v_switch, rtol=1e-3, atol=1e-6)
    check_trajectory(second, rest, vmax, amax, v0=second.velocities_rad_s[0], consistency=0.02)
    from_rest = time_parameterize(rest, vmax, amax)
    assert second.duration_s < from_rest.duration_s
    assert abs(second.duration_s - (first.duration_s - first.times_s[k])) < 0.01 * first.duration_s
    by_speed = time_parameterize(rest, vmax, amax, start_path_speed=second.path_speed[0])
    np.testing.assert_allclose(by_speed.times_s, second.times_s, rtol=1e-12)


def test_start_velocities_that_cannot_be_followed_are_refused():
    path = np.array([[0.0, 0.0], [1.0, 0.0]])
    vmax, amax = np.array([1.0, 1.0]), np.array([1.0, 1.0])
    with pytest.raises(ValueError, match="start_velocity_rad_s.*tangent"):
        time_parameterize(path, vmax, amax, start_velocity_rad_s=[0.1, 0.1])
    with pytest.raises(ValueError, match="start_velocity_rad_s"):
        time_parameterize(path, vmax, amax, start_velocity_rad_s=[-0.1, 0.0])
    with pytest.raises(ValueError, match="start_path_speed.*faster"):
        time_parameterize(path, vmax, amax, start_path_speed=1.5)      # above the velocity limit
    # 1 rad to stop in: from 0.9 rad/s at 1 rad/s² that needs 0.405 rad
    ok = time_parameterize(path, vmax, amax, start_path_speed=0.9)
    check_trajectory(ok, path, vmax, amax, v0=[0.9, 0.0])
    short = np.array([[0.0, 0.0], [0.05, 0.0]])
    with pytest.raises(ValueError, match="start_path_speed"):
        time_parameterize(short, vmax, amax, start_path_speed=0.9)    # cannot stop within 0.05 rad


@pytest.mark.parametrize("over", [1.02, 1.6, 2.2])
def test_a_start_above_the_velocity_limits_brakes_to_them_when_asked(over):
    """
    ``brake_to_limits``: a start ``over`` times the velocity limits (lowered as the arm moves) brakes, then obeys them.

    Without it the same start is refused (the test above).  Oracle: the finite differences of the
    positions (``oracles.finite_differences``, not the published values): every acceleration within
    its limit throughout; the speed along the path (chord / Δt) never rises while any joint is above
    its velocity limit, and from the first segment within the limits on every segment is; that comes
    soon after braking joint 0 (which binds at the start) at its own acceleration limit would (the
    test's bound: its excess speed over its limit, plus a fifth and 50 ms).
    """
    from oracles import finite_differences
    path = np.column_stack([np.linspace(0.0, 3.0, 120), 0.15 * np.sin(np.linspace(0.0, 3.0, 120))])
    vmax, amax = np.array([0.5, 0.5]), np.array([0.4, 0.4])
    tangent = path[1] - path[0]
    speed_at_limit = vmax[0] / (tangent[0] / np.linalg.norm(tangent))     # joint 0 binds at the start
    sd0 = over * speed_at_limit
    with pytest.raises(ValueError, match="start_path_speed.*faster"):
        time_parameterize(path, vmax, amax, start_path_speed=sd0)
    traj = time_parameterize(path, vmax, amax, start_path_speed=sd0, brake_to_limits=True)
    t, q = traj.times_s, traj.positions_rad
    np.testing.assert_array_equal(q[0], path[0])
    np.testing.assert_array_equal(q[-1], path[-1])
    v0 = traj.velocities_rad_s[0]
    np.testing.assert_allclose(np.linalg.norm(v0), sd0, rtol=2e-2)        # |q'| = 1 along the chord length
    assert np.max(np.abs(v0) / vmax) > over * 0.98
    w, a = finite_differences(t, q, v0)
    assert np.all(np.abs(a) <= amax * (1 + 1e-9)), np.max(np.abs(a) / amax)
    ratio = np.max(np.abs(w) / vmax, axis=1)
    within = np.flatnonzero(ratio <= 1.0 + 1e-9)
    first = int(within[0])
    assert np.all(ratio[first:] <= 1.0 + 1e-9), ratio[first:].max()
    speed = np.linalg.norm(w, axis=1)
    assert np.all(np.diff(speed[:first + 1]) <= 1e-9 * speed[0]), np.diff(speed[:first + 1]).max()
    bound = 1.2 * (over - 1.0) * vmax[0] / amax[0] + 0.05      # s: joint 0 (it binds) braked at its limit, slack
    assert t[first] <= bound, (t[first], bound)
    assert traj.limit_ratio[0] > 1.0


@pytest.mark.parametrize("seed", range(6))
def test_a_braked_start_never_raises_a_joints_speed_over_its_limit_above_the_largest_ratio_before(seed):
    """
    ``brake_to_limits``: while braking, no joint's speed over its limit rises above the largest ratio before it.

    A review found a path that turns onto a slow joint just after the start: braked from 1.05 times
    the limits, its points' largest ratio went 1.015, 0.862, then 1.209 (the velocity rows were not
    applied while above them), 1.45 under the controller.  Such a start is refused now, or braked
    within the rule.  Random spline paths (seeded) and that path, at 1.01 to 2.5 times the limits.
    Oracle: the finite differences of the positions (``oracles.finite_differences``): each segment's
    largest joint ratio is at most the largest of 1 and those before it, and every acceleration is
    within its limit.
    """
    from oracles import finite_differences
    rng = np.random.default_rng(seed)
    cases = []
    if seed == 0:
        cases.append((np.array([[0.0, 0.0], [0.00736579, 0.0], [1.27496759, 0.9221674], [1.77496759, 0.9221674]]),
                      np.array([1.0, 0.06116611]), np.array([0.71887195, 3.45653608])))
    for _ in range(6):
        dof = int(rng.integers(2, 4))
        cases.append((_spline_path(rng, n_knots=5, dof=dof, scale=0.6)[::2], rng.uniform(0.2, 1.0, dof),
                      rng.uniform(0.3, 2.0, dof)))
    braked = 0
    for path, vmax, amax in cases:
        step = path[1] - path[0]
        at_limit = 1.0 / np.max(np.abs(step / np.linalg.norm(step)) / vmax)      # path speed at the limits
        for over in (1.01, 1.05, 1.2, 1.6, 2.5):
            try:
                traj = time_parameterize(path, vmax, amax, start_path_speed=over * at_limit, brake_to_limits=True)
            except ValueError as e:
                assert "braking at the acceleration limits does not bring" in str(e), e
                continue
            braked += 1
            w, a = finite_differences(traj.times_s, traj.positions_rad, traj.velocities_rad_s[0])
            ratio = np.concatenate([[np.max(np.abs(traj.velocities_rad_s[0]) / vmax)],
                                    np.max(np.abs(w) / vmax, axis=1)])
            before = np.maximum.accumulate(np.maximum(ratio, 1.0))
            assert np.all(ratio[1:] <= before[:-1] * (1.0 + 1e-9)), (over, ratio[:8])
            assert np.all(np.abs(a) <= amax * (1.0 + 1e-9)), (over, np.max(np.abs(a) / amax))
    assert braked >= 3                                   # the test's premise: some starts are braked


def test_a_start_above_the_velocity_limits_that_braking_cannot_bring_within_them_is_refused():
    """A start too fast for the path's bend (the acceleration rows), or for its length, is refused with braking too."""
    vmax, amax = np.array([0.5, 0.5]), np.array([0.4, 0.4])
    bend = np.column_stack([np.linspace(0.0, 2.0, 60), np.linspace(0.0, 1.0, 60) + 0.2 * np.sin(np.linspace(0, 3, 60))])
    with pytest.raises(ValueError, match="braking at the acceleration limits does not bring"):
        time_parameterize(bend, vmax, amax, start_path_speed=1.2, brake_to_limits=True)
    short = np.array([[0.0, 0.0], [0.05, 0.0]])
    with pytest.raises(ValueError, match="braking at the acceleration limits does not bring"):
        time_parameterize(short, vmax, amax, start_path_speed=0.9, brake_to_limits=True)


def test_a_start_tangent_sets_the_start_velocity_and_bad_ones_are_refused():
    """
    The path leaves its start along ``start_tangent``; bad tangents are refused.

    The first velocity is the tangent times the path speed, off the path's own (not-a-knot)
    tangent; the path still passes through every sample and the limits hold (the test's finite
    differences).  A tangent of the wrong length, not finite, too long or short, or turned away
    from the path is refused, naming it.
    """
    rng = np.random.default_rng(7)
    path = _spline_path(rng, scale=0.3)
    u = (path[1] - path[0]) / np.linalg.norm(path[1] - path[0])
    tangent = turned(u, 4.0)
    w = turned(u, 90.0)
    speed = 0.02
    own = time_parameterize(path, VMAX, AMAX, start_path_speed=speed)
    clamped = time_parameterize(path, VMAX, AMAX, start_path_speed=speed, start_tangent=tangent)
    np.testing.assert_allclose(clamped.velocities_rad_s[0], speed * tangent, rtol=0, atol=1e-12)
    assert np.linalg.norm(own.velocities_rad_s[0] - speed * tangent) > 0.05 * speed
    dense = densify_path(path)
    np.testing.assert_array_equal(clamped.positions_rad, dense)
    check_trajectory(clamped, path, VMAX, AMAX, v0=clamped.velocities_rad_s[0])
    for bad, what in (([1.0, 0.0], "3 finite values"), ([np.nan, 0.0, 0.0], "finite"), (3.0 * u, "length"),
                      (-u, "off the path's first step"), (w, "off the path's first step")):
        with pytest.raises(ValueError, match=f"start_tangent.*{what}"):
            time_parameterize(path, VMAX, AMAX, start_path_speed=speed, start_tangent=bad)
    with pytest.raises(ValueError, match="start_tangent"):
        time_parameterize(path, VMAX, AMAX, start_velocity_rad_s=speed * u, start_tangent=u)


@pytest.mark.parametrize("dof", [2, 3], ids=["paper_2dof", "paper_3dof"])
def test_resampled_trajectory_is_short_exact_and_certified(dof, paper_scenario, paper_path):
    sc, path = paper_scenario(dof), paper_path(dof)
    vmax, amax = joint_limits(sc)
    traj = time_parameterize(path, vmax, amax)
    checker = CollisionChecker(sc.robot, sc.scene)
    for kw in ({}, {"time_step_s": 0.25, "path_tolerance_rad": None},
               {"time_step_s": 1.0, "path_tolerance_rad": np.radians(0.05)}):
        res = resample(traj, checker, **kw)
        sub = res.trajectory
        assert res.ok and res.check.ok
        assert 5 <= len(sub) <= 200 and len(sub) < len(traj) / 3
        np.testing.assert_array_equal(sub.positions_rad[[0, -1]], traj.positions_rad[[0, -1]])
        np.testing.assert_array_equal(sub.times_s, traj.times_s[res.indices])
        check_trajectory(sub, path, vmax, amax, dense=False)          # the limits hold between kept points too
        if kw.get("time_step_s"):       # at most time_step_s apart, unless neighbours in traj
            assert np.all((np.diff(sub.times_s) <= kw["time_step_s"] + 1e-12) | (np.diff(res.indices) == 1))
        # oracle: the polyline through the kept points, sampled at 0.1°, clears the margin, and so
        # does the controller's motion through them (SciPy's quintic, 20 samples per segment, shapely)
        fine = dense_samples(sub.positions_rad, np.radians(0.1))
        assert np.all(checker.clearance_m(fine) > sc.scene.safety_margin_m)
        curve = controller_motion(sub, 20 * (len(sub) - 1) + 1)[0]
        assert min(shapely_clearance(sc.robot, sc.scene, q) for q in curve) > sc.scene.safety_margin_m
    if dof == 3:
        traj_s = time_parameterize(path, vmax, amax)
        assert 10 <= len(resample(traj_s, checker).trajectory) <= 200 and traj_s.duration_s > 20.0


@pytest.mark.parametrize("bulge_deg", [-4.0, -1.0, 0.5, 1.0, 2.0, 4.0, 8.0])
def test_the_certification_is_of_the_controllers_curve_not_the_chord(paper_scenario, paper_path, bulge_deg):
    """
    Two points near the paper 2-DOF path's closest approach, their chord clear by 67 mm.

    With end velocities across the chord (bulge_deg: about how far the controller's quintic
    bulges off it, > 0 towards the obstacle) the controller's motion nears the obstacle.
    Oracle: shapely's clearance of SciPy's quintic through the two points; resample's verdict
    (two points: nothing to add back) must agree with it wherever it is 2 mm or more from the
    safety margin.  Certifying the chord alone passed every one of them.
    """
    from dataclasses import replace
    from spacerobot_planner.motion import MotionValidator
    sc, path = paper_scenario(2), paper_path(2)
    vmax, amax = joint_limits(sc)
    traj = time_parameterize(path, vmax, amax)
    clr = np.array([shapely_clearance(sc.robot, sc.scene, q) for q in traj.positions_rad])
    k = int(np.argmin(clr))
    pair = traj.subset([max(k - 3, 0), min(k + 3, len(traj) - 1)])
    chord = np.diff(pair.positions_rad, axis=0)[0]
    across = np.array([-chord[1], chord[0]]) / np.linalg.norm(chord)
    mid = pair.positions_rad.mean(axis=0)
    towards = 1.0 if shapely_clearance(sc.robot, sc.scene, mid + 0.02 * across) < clr[k] else -1.0
    v = towards * np.radians(bulge_deg) * 4.0 / np.diff(pair.times_s)[0] * across
    bent = replace(pair, velocities_rad_s=np.stack([v, -v]), accelerations_rad_s2=np.zeros((2, 2)))
    oracle = min(shapely_clearance(sc.robot, sc.scene, q) for q in controller_motion(bent, 401)[0])
    margin = sc.scene.safety_margin_m
    got = resample(bent, MotionValidator.for_scene(sc.robot, sc.scene), time_step_s=10.0)
    assert len(got.trajectory) == 2
    if oracle >= margin + 2e-3:
        assert got.ok, f"a clear curve refused: oracle clearance {oracle:.4f} m"
    elif oracle <= margin - 2e-3:
        assert not got.ok, f"a curve into the margin certified: oracle clearance {oracle:.4f} m"
    if bulge_deg >= 4.0:
        assert oracle <= margin - 2e-3          # the case the chord's certification missed
    if bulge_deg < 0.0:
        assert oracle >= margin + 2e-3


@pytest.mark.parametrize("seed", range(4))
def test_the_certification_holds_the_controllers_quintics_within_the_joint_bounds_between_its_samples(seed):
    """
    Segments of the paper 2-DOF arm near the elbow's -180° bound, in a free posture: certified exactly when within it.

    The controller's quintic between two points can dip past a bound between the check's samples
    (8 a segment) and be back within at the next: certified before.  Oracle: SciPy's quintic
    (``oracles.controller_interpolation``) at 4 096 samples a segment; the check's verdict must agree
    wherever the oracle's excess is 1e-9 rad or more from 0, and the premise (segments that pass
    the bound only between the samples) is counted.
    """
    from oracles import controller_interpolation
    from spacerobot_planner.config import load_scenario
    from spacerobot_planner.motion import MotionValidator
    from spacerobot_planner.published import controller_check, controller_motion as samples_of
    from spacerobot_planner.trajectory import Trajectory
    sc = load_scenario(os.path.join(os.path.dirname(__file__), "..", "config", "paper_2dof.yaml"))
    robot, validator = sc.robot, MotionValidator.for_scene(sc.robot, sc.scene)
    e = list(robot.planned_names).index("elbow")
    lo = robot.planned_lower_rad[e]
    rng = np.random.default_rng(70 + seed)
    between = 0
    for _ in range(60):
        dur = rng.uniform(0.05, 0.5)
        q = np.zeros((2, 2))
        q[:, 1 - e] = np.radians([60.0, 61.0])
        q[:, e] = lo + rng.uniform(0.0, 2e-5, 2) * (rng.random(2) < 0.7)
        v, a = np.zeros((2, 2)), np.zeros((2, 2))
        v[:, 1 - e] = np.radians(1.0) / dur
        v[:, e] = rng.normal(0.0, 5e-4, 2)
        a[:, e] = rng.normal(0.0, 2e-2, 2)
        if _ % 2:                   # out from the bound and back early in the segment, before its second sample
            q[0, e], v[0, e] = lo, -rng.uniform(1e-4, 1e-3)
            a[0, e] = -v[0, e] * rng.uniform(24.0, 48.0) / dur
        traj = Trajectory(tuple(robot.planned_names), np.array([0.0, dur]), q, v, a, np.ones(2), np.ones(2))
        ts = np.linspace(0.0, dur, 4097)
        excess = float(np.max(lo - controller_interpolation(traj.times_s, q, v, a)(ts)[0][:, e]))
        check, seg_ok = controller_check(traj, validator)
        if abs(excess) < 1e-9:
            continue
        assert check.ok == seg_ok[0] == (excess < 0.0), (excess, q[:, e] - lo, v[:, e], a[:, e], dur)
        between += excess > 0.0 and bool(np.all(samples_of(traj)[0][:, e] >= lo))
    assert between >= 10, between                               # the premise: passes between the samples


@pytest.mark.parametrize("seed", range(3))
def test_how_far_the_controllers_quintics_pass_a_joints_bound_is_found_exactly(seed):
    """
    ``published.past_bounds`` and the refusal's text: the quintics' exact peaks past a bound, their time and side.

    Trajectories of the paper 2-DOF arm's joints near the elbow's ±180° bounds (the shoulder
    unbounded in the call: never named).  Oracle: SciPy's quintic through the points
    (``scipy.interpolate.BPoly``) and its exact extrema (the roots of its derivative).  The chain's
    text for a refused motion had found the excess by 64 samples a segment, and said nothing of a
    bound passed only between them (the premise: such trajectories are counted).
    """
    from scipy.interpolate import BPoly, PPoly
    from spacerobot_planner.adapters import _past_bounds_text
    from spacerobot_planner.config import load_scenario
    from spacerobot_planner.published import BOUND_SLACK_RAD, past_bounds
    from spacerobot_planner.trajectory import Trajectory
    sc = load_scenario(os.path.join(os.path.dirname(__file__), "..", "config", "paper_2dof.yaml"))
    names = tuple(sc.robot.planned_names)
    e = names.index("elbow")
    lo_e, hi_e = sc.robot.planned_lower_rad[e], sc.robot.planned_upper_rad[e]
    lo, hi = np.full(2, -np.inf), np.full(2, np.inf)
    lo[e], hi[e] = lo_e, hi_e
    rng = np.random.default_rng(90 + seed)
    between = 0
    for case in range(80):
        m = int(rng.integers(2, 7))
        t = np.concatenate([[0.0], np.cumsum(rng.uniform(0.05, 2.0, m - 1))]) + rng.uniform(0.0, 5.0)
        bound = hi_e if case % 2 else lo_e
        inward = -1.0 if case % 2 else 1.0
        q = np.empty((m, 2))
        q[:, 1 - e] = np.radians(rng.uniform(-90.0, 90.0, m))
        q[:, e] = bound + inward * rng.uniform(0.0, 1e-4, m) * (rng.random(m) < 0.7)
        v = rng.normal(0.0, 1e-3, (m, 2))
        a = rng.normal(0.0, 1e-2, (m, 2))
        if case % 3 == 0:           # out from the bound and back early in the first segment, before 1/64 of it
            q[0, e], v[0, e] = bound, -inward * rng.uniform(1e-4, 1e-3)
            a[0, e] = inward * abs(v[0, e]) * rng.uniform(192.0, 384.0) / (t[1] - t[0])
        traj = Trajectory(names, t, q, v, a, np.ones(2), np.ones(2))
        excess, at, side = past_bounds(traj, lo, hi)
        assert excess[1 - e] <= 0.0 and side[1 - e] == 0                  # unbounded: never past
        bp = BPoly.from_derivatives(t, np.stack([q[:, e], v[:, e], a[:, e]], axis=1))
        roots = PPoly.from_bernstein_basis(bp).derivative().roots(extrapolate=False)
        ts = np.concatenate([t, roots[np.isfinite(roots)]])
        y = bp(ts)
        oracle = max(lo_e - y.min(), y.max() - hi_e)
        scale = 1e-12 * max(1.0, np.abs(q[:, e]).max())
        assert abs(excess[e] - oracle) <= scale or (oracle < 0.0 and excess[e] <= 0.0), (excess[e], oracle)
        if oracle > 1e-9:
            assert side[e] == (1 if case % 2 else -1)
            assert 0.0 <= at[e] <= t[-1] - t[0]
            assert abs(abs(bp(t[0] + at[e]) - bound) - oracle) <= 1e-9 * oracle + scale    # where it is
            text = _past_bounds_text(sc, traj)
            assert len(text) == 1 and f"elbow's bound {np.degrees(bound):g}°" in text[0], text
            dense = np.linspace(t[0], t[-1], 64 * (m - 1) + 1)
            between += bool(max(lo_e - bp(dense).min(), bp(dense).max() - hi_e) <= 0.0)
        elif oracle < -BOUND_SLACK_RAD:
            assert _past_bounds_text(sc, traj) == []
    assert between >= 5, between                 # the premise: passed only between 64 samples a segment


def test_resampling_adds_points_back_where_the_chord_collides(paper_scenario, paper_path):
    """
    A tolerance so loose that chords cut through the spacecraft body.

    The certification fails there and points are added back until it passes.
    """
    sc, path = paper_scenario(3), paper_path(3)
    vmax, amax = joint_limits(sc)
    traj = time_parameterize(path, vmax, amax)
    checker = CollisionChecker(sc.robot, sc.scene)
    loose = resample(traj, None, path_tolerance_rad=2.0)
    assert len(loose.trajectory) == 2 and loose.check is None
    from spacerobot_planner.motion import check_path
    r = sc.robot
    assert not check_path(checker, loose.trajectory.positions_rad, r.planned_lower_rad, r.planned_upper_rad,
                          r.planned_periodic).ok
    fixed = resample(traj, checker, path_tolerance_rad=2.0)
    assert fixed.ok and fixed.refinements > 0 and len(fixed.trajectory) > 2
    with pytest.raises(ValueError, match="time_step_s"):
        resample(traj, checker, time_step_s=0.0)
    with pytest.raises(ValueError, match="time_step_s"):
        resample(traj, checker, time_step_s=None, path_tolerance_rad=None)


def test_replanning_from_a_moving_arm_joins_continuously(paper_scenario, paper_path):
    """
    A replan from a moving arm joins the executing trajectory continuously.

    Keep the executing trajectory to a 1 s horizon, plan a different path from there (here: a
    spline to another goal), join and re-parameterise from the join's speed: same position, same
    velocity (to 1e-4 of the limits) at the join, limits held.
    """
    from spacerobot_planner.trajectory import continuation
    sc, path = paper_scenario(3), paper_path(3)
    vmax, amax = joint_limits(sc)
    first = time_parameterize(path, vmax, amax)
    for frac in (0.1, 0.4, 0.8):
        c = continuation(first, frac * first.duration_s, horizon_s=1.0)
        assert c.join_time_s >= frac * first.duration_s and len(c.prefix_rad) > 1
        new = new_path_from(c.prefix_rad[-1])
        joined = c.join(new)
        nxt = time_parameterize(joined, vmax, amax, start_path_speed=c.start_path_speed)
        np.testing.assert_array_equal(nxt.positions_rad[0], first.positions_rad[c.index])
        assert np.all(np.abs(nxt.velocities_rad_s[0] - c.start_velocity_rad_s) <= 1e-4 * vmax)
        assert np.linalg.norm(c.start_velocity_rad_s) > 0.01
        check_trajectory(nxt, joined, vmax, amax, v0=nxt.velocities_rad_s[0])
    end = continuation(first, 2 * first.duration_s)
    assert end.start_path_speed == 0.0 and np.all(end.start_velocity_rad_s == 0.0)
    with pytest.raises(ValueError, match="new_path_rad"):
        c.join(new + 1.0)
