"""
Tests of joint_space.

Wrap, shortest difference, interpolation, unwrapping and alignment for bounded and periodic joints,
against independent oracles (math.remainder, complex rotations).
"""

import cmath
import math

import numpy as np
from hypothesis import given
from hypothesis import strategies as st

from spacerobot_planner.joint_space import (align_to_state, difference_rad, distance_rad, interpolate_rad,
                                            nearest_turn_rad, unwrap_path, within_bounds, wrap_rad)

angles = st.floats(-50.0, 50.0, allow_nan=False)
PER = (True, False)
LOWER = np.array([-math.pi, -math.pi])


@given(angles, angles)
def test_difference_is_the_short_way_round(a, b):
    d = difference_rad([a, a], [b, b], PER)
    # periodic: the rotation taking a to b, from complex numbers; bounded: plain b − a
    oracle = cmath.phase(cmath.exp(1j * b) / cmath.exp(1j * a))
    assert abs(math.remainder(d[0] - oracle, 2 * math.pi)) < 1e-9 and -math.pi <= d[0] < math.pi
    assert d[1] == b - a
    assert math.isclose(distance_rad([a, 0.0], [b, 0.0], PER), abs(d[0]), abs_tol=1e-12)


@given(angles)
def test_wrap_keeps_the_posture_and_lands_in_range(a):
    w = wrap_rad([a, 0.3], PER, LOWER)
    assert -math.pi <= w[0] < math.pi and w[1] == 0.3
    assert abs(cmath.exp(1j * w[0]) - cmath.exp(1j * a)) < 1e-9


def test_interpolation_crosses_the_seam():
    a, b = np.radians([170.0, 10.0]), np.radians([-170.0, 30.0])
    mid = interpolate_rad(a, b, 0.5, PER)
    assert np.allclose(np.degrees(mid), [180.0, 20.0])          # through ±180°, not through 0°
    ts = interpolate_rad(a, b, np.linspace(0, 1, 5), PER)
    assert ts.shape == (5, 2) and np.allclose(ts[-1], [np.radians(190.0), b[1]])


@given(st.lists(angles, min_size=2, max_size=30))
def test_unwrap_path_is_continuous_and_the_same_posture(values):
    q = np.stack([wrap_rad(np.c_[values, values], PER, LOWER)[:, 0], np.asarray(values)], axis=1)
    u = unwrap_path(q, PER)
    assert np.array_equal(u[0], q[0]) and np.array_equal(u[:, 1], q[:, 1])
    assert np.all(np.abs(np.diff(u[:, 0])) <= math.pi + 1e-12)
    assert np.allclose([math.remainder(x, 2 * math.pi) for x in u[:, 0] - q[:, 0]], 0.0, atol=1e-9)


def test_align_to_state_shifts_whole_turns_to_the_state():
    path = np.radians([[170.0, 5.0], [185.0, 6.0], [200.0, 7.0]])
    state = path[0] + np.array([4 * math.pi, 0.0])               # the arm's raw attitude: two turns on
    out = align_to_state(path, state, PER)
    assert np.array_equal(out[0], state)
    assert np.allclose(out[1:] - path[1:], [[4 * math.pi, 0.0]] * 2)
    try:
        align_to_state(path, path[0] + [1.0, 0.0], PER)
    except ValueError as e:
        assert "not a whole number of turns" in str(e)
    else:
        raise AssertionError("a path that does not start at the state was aligned")


def test_nearest_turn_and_bounds():
    v = nearest_turn_rad([0.1, 0.1], [6.0, 6.0], PER)
    assert np.isclose(v[0], 0.1 + 2 * math.pi) and v[1] == 0.1
    q = np.array([[5.0, 1.0], [5.0, 4.0]])
    assert within_bounds(q, LOWER, -LOWER, PER).tolist() == [True, False]


def test_the_path_kernels_give_numpys_values_bit_for_bit():
    """wrap_rad, unwrap_path, nearest_turn_rad and align_to_state against the NumPy formulas, written here."""
    from spacerobot_planner import joint_space as js
    rng = np.random.default_rng(19)
    two_pi = 2.0 * np.pi
    for _ in range(300):
        n = int(rng.integers(1, 6))
        per = rng.random(n) < 0.6
        lo = rng.uniform(-4.0, 1.0, n)
        q = rng.uniform(-20.0, 20.0, (int(rng.integers(1, 30)), n))
        q[0, 0] = lo[0] + 3 * two_pi                             # a value on the wrap's edge
        want = q.copy()
        want[:, per] = lo[per] + (q[:, per] - lo[per]) % two_pi
        assert np.array_equal(js.wrap_rad(q, per, lo), want)
        path = np.cumsum(rng.normal(0.0, 1.5, (int(rng.integers(2, 40)), n)), axis=0)
        path[1:, per] += two_pi * rng.integers(-2, 3, (len(path) - 1, int(per.sum())))
        want = path.copy()
        step = (np.diff(path[:, per], axis=0) + np.pi) % two_pi - np.pi
        want[1:, per] = path[0, per] + np.cumsum(step, axis=0)
        assert np.array_equal(js.unwrap_path(path, per), want)
        ref = rng.uniform(-30.0, 30.0, n)
        v = path[0]
        want = v.copy()
        want[per] = v[per] + two_pi * np.round((ref[per] - v[per]) / two_pi)
        assert np.array_equal(js.nearest_turn_rad(v, ref, per), want)
        state = path[0] + np.where(per, two_pi * rng.integers(-3, 4, n), 0.0)
        want = path.copy()
        want[:, per] += two_pi * np.round((state[per] - path[0, per]) / two_pi)
        assert np.array_equal(js.align_to_state(path, state, per), want)


def test_deg_text_never_says_minus_zero():
    """A joint at -0.0098° read "(-56.6, -0.0)°" in a hidden-scene audit's disconnected reason."""
    from spacerobot_planner.joint_space import deg_text
    assert deg_text(np.radians([-56.6, -0.0098])) == "(-56.6, 0.0)°"
    assert deg_text(np.radians([-0.04, 0.04, -12.34])) == "(0.0, 0.0, -12.3)°"
