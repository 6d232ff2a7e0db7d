"""
Tests of trajectory.py's numba kernels against independent formulations.

The spline on the reachability grid against SciPy's ``CubicSpline`` (not-a-knot, and with a clamped
start or end; kept within the joints' bounds: SciPy's clamped pieces between the samples on a bound); densifying and
the rounding margins against the array (NumPy) formulation they replaced, which they must
reproduce bit for bit (the published trajectories do not change with the kernels); the backward
pass redone from the grid points whose limits changed against the whole pass on the new limits;
the controller re-timing's tapered factors against the array formulation they replaced.
"""

import numpy as np
import pytest
from scipy.interpolate import CubicSpline

from spacerobot_planner.trajectory import (_backward, _backward_from, _constraint_rows, _path_model, _rounding_margins,
                                           _rows, _spline_slopes, arc_lengths_rad, chord_lengths_rad,
                                           clamped_start_slopes, densify_path, lowering_factors)

EPS = float(np.finfo(float).eps)
SLACK = 1e-10


def _random_path(rng, m, n):
    return np.cumsum(rng.normal(0.0, 0.05, (m, n)), axis=0)


@pytest.mark.parametrize("seed", range(12))
def test_spline_on_the_grid_is_scipys_not_a_knot_spline(seed):
    rng = np.random.default_rng(seed)
    m, n, refine = int(rng.integers(3, 60)), int(rng.integers(1, 5)), int(rng.integers(1, 6))
    p = _random_path(rng, m, n)
    s, idx, q, d1, d2, d3 = _path_model(p, refine)
    knots = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(p, axis=0), axis=1))])
    cs = CubicSpline(knots, p, axis=0, bc_type="not-a-knot")
    assert s.shape == ((m - 1) * refine + 1,) and np.all(np.diff(s) > 0.0)
    np.testing.assert_array_equal(s[idx], knots)
    np.testing.assert_array_equal(q[idx], p)                   # the samples exactly
    scale = np.max(np.abs(p)) + 1.0
    np.testing.assert_allclose(q, cs(s), rtol=0, atol=1e-10 * scale)
    for got, nu in ((d1, 1), (d2, 2)):
        ref = cs(s, nu)
        np.testing.assert_allclose(got, ref, rtol=0, atol=1e-7 * (np.max(np.abs(ref)) + 1.0))
    mid = 0.5 * (s[:-1] + s[1:])
    ref3 = cs(mid, 3)
    np.testing.assert_allclose(d3, ref3, rtol=0, atol=1e-6 * (np.max(np.abs(ref3)) + 1.0))


@pytest.mark.parametrize("seed", range(10))
def test_a_clamped_start_is_scipys_spline_with_that_first_derivative(seed):
    """
    The path model leaving its start along a given derivative is SciPy's clamped spline.

    SciPy's ``CubicSpline`` with the boundary condition ``((1, slope), "not-a-knot")`` (3 knots
    included: no parabola then).
    """
    rng = np.random.default_rng(100 + seed)
    m = 3 if seed < 3 else int(rng.integers(4, 50))
    n, refine = int(rng.integers(1, 5)), int(rng.integers(1, 5))
    p = _random_path(rng, m, n)
    knots = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(p, axis=0), axis=1))])
    first = (p[1] - p[0]) / knots[1]
    slope = first + rng.normal(0.0, 0.2, n)             # off the first chord, as an arm's velocity can be
    cs = CubicSpline(knots, p, axis=0, bc_type=((1, slope), "not-a-knot"))
    got = clamped_start_slopes(knots, p, slope)
    np.testing.assert_allclose(got, cs(knots, 1), rtol=0, atol=1e-9 * (np.max(np.abs(got)) + 1.0))
    assert np.array_equal(got[0], slope)
    s, idx, q, d1, d2, d3 = _path_model(p, refine, slope)
    np.testing.assert_array_equal(q[idx], p)
    np.testing.assert_array_equal(d1[0], slope)
    np.testing.assert_allclose(q, cs(s), rtol=0, atol=1e-10 * (np.max(np.abs(p)) + 1.0))
    ref = cs(s, 2)
    np.testing.assert_allclose(d2, ref, rtol=0, atol=1e-7 * (np.max(np.abs(ref)) + 1.0))
    # the not-a-knot start differs: the clamp is not a no-op
    assert np.max(np.abs(_path_model(p, refine)[3][0] - slope)) > 1e-3


@pytest.mark.parametrize("seed", range(8))
def test_a_spline_clamped_at_its_end_is_scipys(seed):
    """Slopes with the end clamped, the start clamped or not-a-knot, are SciPy's ``CubicSpline``'s (two knots too)."""
    rng = np.random.default_rng(300 + seed)
    m, n = (2 if seed < 2 else int(rng.integers(3, 30))), int(rng.integers(1, 4))
    p = _random_path(rng, m, n)
    x = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(p, axis=0), axis=1))])
    start, end = rng.normal(0.0, 1.0, n), rng.normal(0.0, 1.0, n)
    both = _spline_slopes(x, p, start, True, end, True)
    ref = CubicSpline(x, p, axis=0, bc_type=((1, start), (1, end)))(x, 1)
    np.testing.assert_allclose(both, ref, rtol=0, atol=1e-9 * (np.max(np.abs(ref)) + 1.0))
    if m >= 3:
        got = _spline_slopes(x, p, start, False, end, True)
        ref = CubicSpline(x, p, axis=0, bc_type=("not-a-knot", (1, end)))(x, 1)
        np.testing.assert_allclose(got, ref, rtol=0, atol=1e-9 * (np.max(np.abs(ref)) + 1.0))
    else:                                   # a parabola from the clamped end
        got = _spline_slopes(x, p, start, True, end, False)
        a = (p[1] - p[0] - start * x[1]) / x[1] ** 2
        np.testing.assert_allclose(got[1], start + 2.0 * a * x[1], rtol=0, atol=1e-12)


def _touching(rng, n):
    """Return a densified V path whose column 0 touches its lower bound 0 at one sample (one side shallow), (M, n)."""
    depth = np.array([rng.uniform(0.003, 0.03), rng.uniform(0.1, 0.5)])[rng.permutation(2)]
    corners = np.zeros((3, n))
    corners[:, 0] = [depth[0], 0.0, depth[1]]
    corners[:, 1:] = np.cumsum(rng.uniform(0.2, 0.7, (3, n - 1)), axis=0)
    return densify_path(corners, np.radians(0.5))


@pytest.mark.parametrize("seed", range(8))
def test_the_spline_within_the_bounds_is_scipys_clamped_pieces_and_stays_within_them(seed):
    """
    A path touching a bound at one sample: its spline is SciPy's, clamped to slope 0 there, and stays within the bound.

    Oracle: SciPy's ``CubicSpline`` of each piece between the samples on the bound (slope 0 there,
    not-a-knot at the path's ends), evaluated 64 times per sample interval.  The not-a-knot spline
    of the same path passes the bound (the test's premise); a path whose spline stays within its
    bounds is modelled bit for bit as without them.
    """
    rng = np.random.default_rng(500 + seed)
    n, refine = int(rng.integers(2, 4)), int(rng.integers(1, 4))
    p = _touching(rng, n)
    lo, hi = np.full(n, -np.inf), np.full(n, np.inf)
    lo[0] = 0.0
    x = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(p, axis=0), axis=1))])
    fine = np.concatenate([np.linspace(a, b, 64, endpoint=False) for a, b in zip(x[:-1], x[1:])])
    assert CubicSpline(x, p[:, 0])(fine).min() < -1e-9                           # premise: it rang past the bound
    s, idx, q, d1, d2, d3 = _path_model(p, refine, None, (lo, hi))
    np.testing.assert_array_equal(q[idx], p)
    k = int(np.flatnonzero(p[:, 0] == 0.0)[0])
    assert d1[k * refine, 0] == 0.0                                             # at rest on the path there
    pieces = [CubicSpline(x[:k + 1], p[:k + 1, 0], bc_type=("not-a-knot", (1, 0.0))),
              CubicSpline(x[k:], p[k:, 0], bc_type=((1, 0.0), "not-a-knot"))]

    def ref(v, nu=0):
        return np.where(v <= x[k], pieces[0](v, nu), pieces[1](v, nu))
    tol = 1e-9 * (np.max(np.abs(p)) + 1.0)
    np.testing.assert_allclose(q[:, 0], ref(s), rtol=0, atol=tol)
    np.testing.assert_allclose(d1[:, 0], np.where(s < x[k], pieces[0](s, 1), pieces[1](s, 1)), rtol=0, atol=1e-7)
    assert ref(fine).min() >= -1e-12
    plain = _path_model(p, refine)
    for a, b in zip(plain[2:], (q, d1, d2, d3)):                                # the other columns as they were
        np.testing.assert_array_equal(a[:, 1:], b[:, 1:])
    inside = _path_model(p + np.array([0.05] + [0.0] * (n - 1)), refine, None, (lo, hi))
    for a, b in zip(_path_model(p + np.array([0.05] + [0.0] * (n - 1)), refine), inside):
        np.testing.assert_array_equal(a, b)


def test_a_clamped_start_past_the_bound_leaves_the_rest_of_the_spline_within_it():
    """
    A start slope (the arm's) that points past a bound cannot be mended; a touch further on still is.

    Oracle: SciPy's ``CubicHermiteSpline`` through the samples with the model's knot slopes, 64
    samples an interval: within the bound after the first interval, and at rest at the touch.
    """
    from scipy.interpolate import CubicHermiteSpline
    rng = np.random.default_rng(7)
    p = _touching(rng, 2)
    p = np.vstack([[0.002, p[0, 1] - 0.02], p])                  # a first sample near the bound ...
    lo, hi = np.array([0.0, -np.inf]), np.array([np.inf, np.inf])
    slope = np.array([-0.6, 0.8])                                # ... left towards it and past it
    s, idx, q, d1, d2, d3 = _path_model(p, 2, slope, (lo, hi))
    x = s[idx]
    f = CubicHermiteSpline(x, p[:, 0], d1[idx, 0])
    fine = np.concatenate([np.linspace(a, b, 64, endpoint=False) for a, b in zip(x[:-1], x[1:])])
    assert f(fine[fine < x[1]]).min() < 0.0                      # premise: the first interval passes it
    assert f(fine[fine >= x[1]]).min() >= -1e-14
    k = int(np.flatnonzero(p[:, 0] == 0.0)[0])
    assert d1[idx[k], 0] == 0.0


def test_the_second_derivative_along_a_run_on_the_bound_is_0_at_any_refinement():
    """A path along a bound (its spline passing it between the knots on it): q'' 0 at the run's knots, refine 1 or 2."""
    rng = np.random.default_rng(8)
    corners = np.array([[0.05, 0.0], [0.0, 0.3], [0.0, 0.6], [0.2, 1.0]])
    p = densify_path(corners + np.array([0.0, rng.uniform(0.0, 0.1)]), np.radians(0.5))
    lo, hi = np.array([0.0, -np.inf]), np.array([np.inf, np.inf])
    run = np.flatnonzero(p[:, 0] == 0.0)
    assert len(run) > 3
    assert CubicSpline(np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(p, axis=0), axis=1))]),
                       p[:, 0])(np.linspace(0.0, 1.0, 4001)).min() < -1e-9         # premise
    for refine in (1, 2):
        s, idx, q, d1, d2, d3 = _path_model(p, refine, None, (lo, hi))
        inner = idx[run[1:-1]]
        assert np.all(d1[inner, 0] == 0.0) and np.all(d2[inner, 0] == 0.0), refine


def _densify_numpy(path, max_step):
    """Densify as the array formulation did: keep rows more than 1e-12 from the last kept one, exact goal, subdivide."""
    p = np.asarray(path, dtype=float)
    keep = [0]
    for k in range(1, len(p)):
        if np.max(np.abs(p[k] - p[keep[-1]])) > 1e-12:
            keep.append(k)
    if len(keep) > 1:
        keep[-1] = len(p) - 1
    p = p[keep]
    if len(p) == 1:
        return p
    steps = np.max(np.abs(np.diff(p, axis=0)), axis=1)
    subdiv = np.maximum(1, np.ceil(steps / max_step - 1e-9)).astype(int)
    total = int(subdiv.sum())
    if total + 1 < 3:
        subdiv[np.argmax(steps)] += 3 - 1 - total
        total = int(subdiv.sum())
    seg = np.repeat(np.arange(len(subdiv)), subdiv)
    frac = (np.arange(total) - np.repeat(np.cumsum(subdiv) - subdiv, subdiv) + 1) / np.repeat(subdiv, subdiv)
    out = p[seg] + frac[:, None] * (p[seg + 1] - p[seg])
    out[np.cumsum(subdiv) - 1] = p[1:]
    return np.concatenate([p[:1], out])


@pytest.mark.parametrize("seed", range(12))
def test_densify_is_the_array_formulation_bit_for_bit(seed):
    rng = np.random.default_rng(100 + seed)
    m, n = int(rng.integers(2, 30)), int(rng.integers(1, 5))
    p = _random_path(rng, m, n)
    p[rng.integers(0, m, m // 3)] = p[0]                        # repeats
    p = np.repeat(p, rng.integers(1, 3, m), axis=0)
    if seed % 3 == 0:
        p[1:-1] += rng.normal(0.0, 1e-13, p[1:-1].shape)      # creeping below the 1e-12 rad threshold
    max_step = float(rng.choice([np.radians(0.5), 0.2, 1e-3]))
    got, ref = densify_path(p, max_step), _densify_numpy(p, max_step)
    assert got.shape == ref.shape
    assert got.tobytes() == ref.tobytes()


def _margins_numpy(t, dt, p, v0, amax, refine):
    """Return the rounding margins by the array formulation, thresholded at SLACK of the limits."""
    m, n = p.shape
    err_t = (refine + 6) * EPS * dt
    err_t[1:] += 0.5 * np.spacing(t[2:])
    rel = err_t / dt + 2.0 * EPS
    w = np.abs(np.diff(p, axis=0)) / dt[:, None]
    e = w * rel[:, None]
    zero = np.zeros((1, n))
    e_b, e_a = np.vstack([2.0 * EPS * v0[None, :], e]), np.vstack([e, zero])
    w_b, w_a = np.vstack([v0[None, :], w]), np.vstack([w, zero])
    t_b, t_a = np.concatenate([[0.0], err_t]), np.concatenate([err_t, [0.0]])
    half = 0.5 * (np.concatenate([[0.0], dt]) + np.concatenate([dt, [0.0]]))
    fd = 2.0 * ((e_b + e_a + EPS * (w_b + w_a)) / half[:, None]
                + amax[None, :] * ((t_b + t_a) / (2.0 * half))[:, None])
    per_int = np.maximum(fd[:-1], fd[1:])
    acc = np.empty(((m - 1) * refine + 1, n))
    acc[:-1] = np.repeat(per_int, refine, axis=0)
    acc[-1] = per_int[-1]
    acc[refine:-1:refine] = np.maximum(per_int[:-1], per_int[1:])
    vel = np.empty(len(acc))
    vel[:-1] = np.repeat(2.0 * rel, refine)
    vel[-1] = 2.0 * rel[-1]
    vel[refine:-1:refine] = 2.0 * np.maximum(rel[:-1], rel[1:])
    acc[acc <= SLACK * amax] = 0.0
    vel[vel <= SLACK] = 0.0
    return acc, vel


@pytest.mark.parametrize("seed", range(12))
def test_rounding_margins_are_the_array_formulation_bit_for_bit(seed):
    rng = np.random.default_rng(200 + seed)
    m, n, refine = int(rng.integers(2, 40)), int(rng.integers(1, 5)), int(rng.integers(1, 6))
    p = _random_path(rng, m, n)
    dt = 10.0 ** rng.uniform(-7, 0, m - 1)                      # some samples very close in time
    t = np.concatenate([[0.0], np.cumsum(dt)]) + (0.0 if seed % 2 else 100.0) * (np.arange(m) > 0)
    dt = np.diff(t)
    g = (m - 1) * refine + 1
    d1 = rng.normal(0.0, 1.0, (g, n))
    x = rng.uniform(0.0, 0.01, g)
    amax = rng.uniform(0.1, 1.0, n)
    m_acc = np.where(rng.random((g, n)) < 0.5, 0.0, rng.uniform(0.0, 1e-3, (g, n)))
    m_vel = np.zeros(g)
    acc, vel, grown = _rounding_margins(t, dt, p, d1, x, amax, refine, m_acc, m_vel)
    ref_acc, ref_vel = _margins_numpy(t, dt, p, np.abs(d1[0]) * np.sqrt(x[0]), amax, refine)
    assert acc.tobytes() == ref_acc.tobytes() and vel.tobytes() == ref_vel.tobytes()
    assert grown == (not (np.all(ref_acc <= m_acc) and np.all(ref_vel <= m_vel)))


@pytest.mark.parametrize("seed", range(6))
def test_chord_and_arc_lengths_are_numpys_row_norms_and_running_sums(seed):
    # NumPy's formulation, which every caller used before (path lengths, the chord parameters
    # of the splines): the same values bit for bit, below and above 7 joints
    rng = np.random.default_rng(seed)
    for _ in range(200):
        m, n = int(rng.integers(1, 40)), int(rng.integers(1, 10))
        p = rng.normal(size=(m, n)) * 10.0 ** rng.uniform(-4, 2)
        chords = np.linalg.norm(np.diff(p, axis=0), axis=1)
        np.testing.assert_array_equal(chord_lengths_rad(p), chords)
        np.testing.assert_array_equal(arc_lengths_rad(p), np.concatenate([[0.0], np.cumsum(chords)]))


@pytest.mark.parametrize("seed", range(16))
def test_a_backward_pass_redone_below_the_changed_rows_is_the_whole_pass_bit_for_bit(seed):
    """
    A backward pass redone from the highest grid point whose limits changed is the whole pass.

    ``_backward_from``: after the limits change at grid points ``top`` and below only (a joined
    timing raising the lowering where the arm's speed must be entered), redoing the pass from
    ``top`` down gives the whole pass on the new limits to the bit; with a wheel (its momentum
    and torque rows) and without, lowerings at random stretches, ``top`` anywhere (the last
    point: the whole pass; below every change: nothing redone).
    """
    rng = np.random.default_rng(300 + seed)
    m, n, refine = int(rng.integers(3, 80)), int(rng.integers(1, 4)), int(rng.integers(1, 4))
    p = _random_path(rng, m, n)
    s, _, q, d1, d2, d3 = _path_model(p, refine)
    d1, d2, d3, ds = (np.ascontiguousarray(a) for a in (d1, d2, d3, np.diff(s)))
    vmax, amax = rng.uniform(0.2, 2.0, n), rng.uniform(0.2, 2.0, n)
    xv, kappa, c_row = _constraint_rows(d1, d3, ds, vmax, amax)
    g_n = len(s)
    wheel = seed % 2 == 1
    g = rng.normal(0.0, 1.0, g_n) if wheel else None
    gp = rng.normal(0.0, 1.0, g_n) if wheel else None
    h_max, tau_max = (rng.uniform(0.5, 3.0), rng.uniform(0.5, 3.0)) if wheel else (np.inf, np.inf)
    low = np.ones((g_n, 4))
    for _ in range(3):                                   # lowered stretches
        a = int(rng.integers(0, g_n))
        b = int(rng.integers(a, g_n)) + 1
        low[a:b] = np.minimum(low[a:b], rng.uniform(0.3, 1.0, 4))
    k = _backward(*_rows(xv, c_row, kappa, d1, d2, g, gp, h_max, tau_max, low)[:5], ds, 0.0)
    for free in (1, 2, 5, g_n // 2, g_n - 1, g_n, g_n + 3):
        changed = np.flatnonzero((low[:free] != 1.0).any(axis=1))
        low = low.copy()
        low[:free] = 1.0
        rows = _rows(xv, c_row, kappa, d1, d2, g, gp, h_max, tau_max, low)
        whole = _backward(*rows[:5], ds, 0.0)
        top = int(changed[-1]) if changed.size else -1
        _backward_from(k, *rows[:5], ds, 0.0, top)
        np.testing.assert_array_equal(k, whole)


def _array_lowering(over, tol, shrink, taper):
    """Return the factors as ``adapters.overshot_stretches`` computed them with NumPy before the kernel."""
    core = np.where(over > 1.0 + tol, shrink / np.maximum(over, 1e-300), 1.0)
    core[:, 0] = np.where(core[:, 1] < 1.0, np.minimum(core[:, 0], shrink), core[:, 0])
    f = np.ones_like(core)
    seg = np.arange(len(core))
    for col in range(core.shape[1]):
        for k in np.flatnonzero(core[:, col] < 1.0):
            np.minimum(f[:, col], core[k, col] + taper * np.abs(seg - k), out=f[:, col])
    return f


@pytest.mark.parametrize("seed", range(16))
def test_lowering_factors_are_the_array_formulation_bit_for_bit(seed):
    rng = np.random.default_rng(seed)
    m = int(rng.integers(1, 150))
    tol, shrink, taper = 1e-3, float(rng.choice([0.99, 0.97])), float(rng.choice([0.0025, 0.01, 0.3]))
    over = rng.uniform(0.5, 1.0, (m, 4))
    hot = rng.random((m, 4)) < rng.choice([0.0, 0.03, 0.2])
    over[hot] = rng.uniform(1.0, 1.3, hot.sum())
    over[rng.random((m, 4)) < 0.02] = 1.0 + tol                # at the tolerance: not lowered
    over[rng.random((m, 4)) < 0.02] = np.nan                   # a ratio not measured: not lowered
    got = lowering_factors(over, tol, shrink, taper)
    want = _array_lowering(over, tol, shrink, taper)
    np.testing.assert_array_equal(got, want)
    # the definition: 1 where nothing is lowered within reach, the lowered segment's own factor there
    lowered = np.isfinite(over) & (over > 1.0 + tol)
    assert np.all(got <= 1.0) and np.all(got[lowered] <= shrink / np.where(lowered, over, 1.0)[lowered])
    if not lowered.any():
        assert np.all(got == 1.0)
