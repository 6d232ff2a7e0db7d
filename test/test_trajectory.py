"""trajectory.py: limits hold (published values and finite differences), exact ends, time increases."""

import numpy as np
import pytest
from hypothesis import given, settings, strategies as st
from scipy.interpolate import CubicSpline

from spacerobot_planner.trajectory import (densify_path, finite_differences, sample,
                                           time_parameterize)

VMAX = np.radians([5.0, 15.0, 15.0])
AMAX = np.radians([5.0, 20.0, 20.0])
TOL = 1e-9


def _check(traj, path, vmax, amax):
    t, q = traj.times_s, traj.positions_rad
    assert t[0] == 0.0 and np.all(np.diff(t) > 0.0)
    np.testing.assert_array_equal(q[0], np.asarray(path)[0])
    np.testing.assert_array_equal(q[-1], np.asarray(path)[-1])
    assert np.all(traj.velocities_rad_s[[0, -1]] == 0.0)
    assert np.all(np.abs(traj.velocities_rad_s) <= vmax * (1 + TOL))
    assert np.all(np.abs(traj.accelerations_rad_s2) <= amax * (1 + TOL))
    w, a = finite_differences(t, q)
    assert np.all(np.abs(w) <= vmax * (1 + TOL))
    assert np.all(np.abs(a) <= amax * (1 + TOL))
    assert np.max(np.abs(np.diff(q, axis=0))) <= np.radians(0.5) + 1e-12


def _spline_path(rng, n_knots=6, dof=3, scale=1.0):
    knots = np.cumsum(rng.normal(0.0, scale, (n_knots, dof)), axis=0)
    cs = CubicSpline(np.linspace(0, 1, n_knots), knots)
    return cs(np.linspace(0, 1, 400))


def test_straight_line_is_trapezoidal_and_fast():
    path = np.array([[0.0, 0.0, 0.0], [1.0, 0.5, -0.2]])
    traj = time_parameterize(path, VMAX, AMAX, ("a", "b", "c"))
    _check(traj, path, VMAX, AMAX)
    assert traj.joint_names == ("a", "b", "c")
    # joint 0 is the bottleneck: 1 rad at 5°/s with 5°/s² → 1/v + v/a
    ideal = 1.0 / VMAX[0] + VMAX[0] / AMAX[0]
    assert ideal <= traj.duration_s <= 1.1 * ideal


@pytest.mark.parametrize("seed", range(6))
def test_curved_paths_obey_limits(seed):
    rng = np.random.default_rng(seed)
    path = _spline_path(rng)
    traj = time_parameterize(path, VMAX, AMAX)
    _check(traj, path, VMAX, AMAX)


@settings(max_examples=25, deadline=None)
@given(st.integers(0, 10_000), st.floats(0.01, 2.0), st.floats(0.1, 100.0))
def test_limits_hold_for_any_path_and_limits(seed, scale, speed):
    rng = np.random.default_rng(seed)
    path = _spline_path(rng, n_knots=int(rng.integers(2, 8)), dof=int(rng.integers(1, 4)), scale=scale)
    vmax = rng.uniform(0.2, 2.0, path.shape[1]) * speed * 0.1
    amax = rng.uniform(0.2, 2.0, path.shape[1]) * speed * 0.1
    traj = time_parameterize(path, vmax, amax)
    _check(traj, path, vmax, amax)


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
