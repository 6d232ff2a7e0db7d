"""
The published points of a timed trajectory, and the motion a controller makes of them.

The stage after the time parameterisation (``trajectory.py``) in the node's chain
(``adapters.post_process``):

- **Which points are published** (:func:`resample`): a subset of the dense points (exact
  start and goal, at most ``time_step_s`` apart and/or within ``path_tolerance_rad`` of the
  dense path), the motion a controller makes of them certified on the exact geometry (the
  scene's ``motion.MotionValidator``), points added back where it fails.
- **The controller's interpolation** (:func:`sample_points`): joint_trajectory_controller's
  spline between published points (linear, cubic Hermite or quintic by the fields the points
  carry), which the mock arm follows too; :func:`controller_motion` samples it,
  :func:`controller_check` certifies it, :func:`segment_peaks` finds each segment's velocity
  and acceleration peaks against the limits (exact for the acceleration: the roots of the
  quintic's jerk), :func:`segment_wheel_peaks` the reaction wheels' momentum and torque peaks
  along it.  Where a peak is over a limit, the chain re-times the path with the limits lowered
  there (``trajectory.Lowering``).

No ROS imports here: NumPy; the per-segment loops are numba kernels.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
from numba import njit

from .motion import MotionValidator
from .spacecraft import _momentum_tables, _sample_momentum
from .trajectory import _SHARED_MODELS, Trajectory, _bits_hash

__all__ = ["Resampled", "resample", "sample_points", "controller_motion", "controller_times",
           "controller_check", "CONTROLLER_SAMPLES",
           "segment_peaks", "segment_wheel_peaks"]


@dataclass(frozen=True, eq=False)
class Resampled:
    """
    A resampled trajectory and the certification of the controller's motion through its points.

    Attributes
    ----------
        trajectory: the kept points (a subset of the dense trajectory's: exact states).
        indices: (K,) their indices in the dense trajectory (0 and M-1 included).
        check: ``motion.PathCheck`` of the controller's motion through ``trajectory``'s
            points (:func:`controller_check`) on the exact geometry (None when no checker was
            given).
        refinements: rounds in which points were added back where the check failed.

    """

    trajectory: Trajectory
    indices: np.ndarray
    check: object
    refinements: int

    @property
    def ok(self) -> bool:
        """Certified collision-free (True when not checked)."""
        return self.check is None or bool(self.check.ok)


@njit(cache=True, nogil=True)
def _within_chord(q, i, j, tol):
    """Tell whether every q[i..j] lies within ``tol`` (rad, Euclidean) of the segment q[i] → q[j]."""
    n = q.shape[1]
    den = 0.0
    for a in range(n):
        den += (q[j, a] - q[i, a]) ** 2
    for k in range(i, j + 1):
        dot = 0.0
        for a in range(n):
            dot += (q[k, a] - q[i, a]) * (q[j, a] - q[i, a])
        f = min(max(dot / den, 0.0), 1.0) if den > 0.0 else 0.0
        r2 = 0.0
        for a in range(n):
            r = (q[k, a] - q[i, a]) - f * (q[j, a] - q[i, a])
            r2 += r * r
        if not np.sqrt(r2) <= tol:
            return False
    return True


@njit(cache=True, nogil=True)
def _select(t, q, time_step_s, path_tolerance_rad):
    """
    Greedy: from each kept point, go on while the next point still meets both criteria.

    ``time_step_s`` / ``path_tolerance_rad``: inf when not given.  Returns the kept indices
    (int64, first and last included).
    """
    m = t.shape[0]
    keep = np.empty(m, np.int64)
    keep[0] = 0
    n_keep = 1
    i, j = 0, 1
    while j < m - 1:
        k = j + 1
        if t[k] - t[i] <= time_step_s and (path_tolerance_rad == np.inf
                                           or _within_chord(q, i, k, path_tolerance_rad)):
            j = k
        else:
            keep[n_keep] = j
            n_keep += 1
            i, j = j, j + 1
    keep[n_keep] = m - 1
    return keep[:n_keep + 1].copy()


def resample(traj: Trajectory, checker=None, *, time_step_s: float | None = None,
             path_tolerance_rad: float | None = np.radians(0.1), max_rounds: int = 30, keep=None) -> Resampled:
    """
    Fewer points, same guarantee: keep a subset of the trajectory's points.

    The kept points are exact points of ``traj`` (times, positions, velocities,
    accelerations unchanged), start and goal included.  Consecutive kept points are at
    most ``time_step_s`` apart (when given) and the dense path between them stays within
    ``path_tolerance_rad`` (Euclidean, joint space) of the straight segment joining them
    (when given).  With a ``checker`` (the scene's ``motion.MotionValidator``, or its
    ``collision.CollisionChecker``: then the bounds of ``checker.robot`` and the default
    step) the motion a controller makes of the kept points (:func:`controller_check`: its
    quintics, not the chords between the points) is certified on the exact geometry; where
    a segment fails, the dense point in its middle is added back, until it passes or only
    dense segments fail.

    Args:
        traj: a dense trajectory from :func:`time_parameterize`.
        checker: optional MotionValidator (or CollisionChecker) of the scene the path was
            planned in.
        time_step_s: largest time between kept points, s (> 0) or None.
        path_tolerance_rad: largest deviation from the dense path, rad (> 0) or None.
        keep: indices of points kept whatever the criteria, or None (the chain's: where a joint
            reaches its bound and turns, whose quintics between farther points would pass it).

    Returns
    -------
        Resampled (``.trajectory``, ``.indices``, ``.check``; ``.ok`` is the verdict).

    Raises
    ------
        ValueError: a non-positive ``time_step_s`` / ``path_tolerance_rad``, or neither given.

    """
    for name, v in (("time_step_s", time_step_s), ("path_tolerance_rad", path_tolerance_rad)):
        if v is not None and not (np.isfinite(v) and v > 0.0):
            raise ValueError(f"{name}: must be a finite number > 0, got {v}")
    if time_step_s is None and path_tolerance_rad is None:
        raise ValueError("time_step_s: give time_step_s and/or path_tolerance_rad")
    t, q = traj.times_s, traj.positions_rad
    if len(t) <= 2:
        idx = np.arange(len(t))
    else:
        idx = _select(np.ascontiguousarray(t, dtype=float), np.ascontiguousarray(q, dtype=float),
                      np.inf if time_step_s is None else float(time_step_s),
                      np.inf if path_tolerance_rad is None else float(path_tolerance_rad))
    if keep is not None and len(keep):
        idx = np.union1d(idx, np.asarray(keep, dtype=np.int64))
    check, rounds = None, 0
    if checker is not None:
        motions = MotionValidator.of(checker)
        while True:
            check, seg_ok = controller_check(traj.subset(idx), motions)
            if check.ok or rounds >= max_rounds:
                break
            bad = np.flatnonzero(~seg_ok)
            mids = [(idx[b] + idx[b + 1]) // 2 for b in bad if idx[b + 1] - idx[b] > 1]
            if not mids:
                break
            idx = np.unique(np.concatenate([idx, mids]))
            rounds += 1
    return Resampled(traj.subset(idx), idx, check, rounds)


@njit(cache=True, nogil=True, inline="always")
def _segment_of(t, s, k):
    """Return the segment [t_k, t_k+1) of the time s (t (M,) increasing, t[0] ≤ s < t[M-1]), searched from k."""
    m = t.shape[0]
    if s != s:                          # NaN: NumPy's searchsorted puts it last
        return m - 2
    if k >= 0 and t[k] <= s and (k == m - 2 or s < t[k + 1]):
        return k                        # the last k with t[k] <= s, as the bisection finds it
    lo, hi = 0, m
    while lo < hi:
        mid = (lo + hi) // 2
        if t[mid] <= s:
            lo = mid + 1
        else:
            hi = mid
    return min(max(lo - 1, 0), m - 2)


@njit(cache=True, nogil=True, inline="always")
def _segment_coefficients(q, v, a, fields, k, dur, c):
    """Fill c (6, n) with segment k's polynomial in the normalised time (``fields`` as :func:`_controller_states`)."""
    for j in range(q.shape[1]):
        d = q[k + 1, j] - q[k, j]
        c[0, j] = q[k, j]
        if fields == 1:
            c[1, j] = d
        else:
            w0, w1 = dur * v[k, j], dur * v[k + 1, j]
            c[1, j] = w0
            if fields == 2:
                c[2, j] = 3.0 * d - 2.0 * w0 - w1
                c[3, j] = -2.0 * d + w0 + w1
            else:
                b0, b1 = dur * dur * a[k, j], dur * dur * a[k + 1, j]
                c[2, j] = 0.5 * b0
                c[3, j] = 10.0 * d - 6.0 * w0 - 4.0 * w1 - 1.5 * b0 + 0.5 * b1
                c[4, j] = -15.0 * d + 8.0 * w0 + 7.0 * w1 + 1.5 * b0 - b1
                c[5, j] = 6.0 * d - 3.0 * w0 - 3.0 * w1 - 0.5 * b0 + 0.5 * b1


@njit(cache=True, nogil=True)
def _unit_roots(qa, qb, qc):
    """Return the roots of qa x² + qb x + qc inside (0, 1): a tuple of two, 0.0 where there is none."""
    r0 = r1 = 0.0
    if qa == 0.0:
        if qb != 0.0:
            r0 = -qc / qb
    else:
        disc = qb * qb - 4.0 * qa * qc
        if disc >= 0.0:
            w = -0.5 * (qb + math.copysign(math.sqrt(disc), qb))
            r0 = w / qa
            r1 = qc / w if w != 0.0 else 0.0
    return (r0 if 0.0 < r0 < 1.0 else 0.0), (r1 if 0.0 < r1 < 1.0 else 0.0)


@njit(cache=True, nogil=True, inline="always")
def _horner(c, j, x):
    """Return (p, p', p'') of column j of the polynomial c (6, n) at x (Horner's rule with its derivatives)."""
    p, dp, ddp = c[5, j], 0.0, 0.0
    for r in range(4, -1, -1):
        ddp = ddp * x + 2.0 * dp
        dp = dp * x + p
        p = p * x + c[r, j]
    return p, dp, ddp


@njit(cache=True, nogil=True)
def _controller_states(t, q, v, a, fields, ts, pos, vel, acc):
    """
    Fill pos, vel, acc (K, n) with the controller's interpolation of the points at the times ts (K,).

    ``fields``: 1 positions only (linear segments), 2 with velocities (cubic Hermite), 3
    with accelerations too (quintic); v, a are ignored where not given.  See
    :func:`sample_points` for the rules at and beyond the ends; the polynomial on
    [t_k, t_k+1] is in the normalised time x ∈ [0, 1], evaluated by Horner's rule with its
    first two derivatives.
    """
    m, n = q.shape
    c = np.zeros((6, n))
    k_coef = -1
    for i in range(ts.shape[0]):
        s = ts[i]
        if s < t[0] or s >= t[m - 1]:
            last = s >= t[m - 1]
            for j in range(n):
                pos[i, j] = q[m - 1, j] if last else q[0, j]
                vel[i, j] = v[m - 1, j] if s == t[m - 1] and fields >= 2 else 0.0
                acc[i, j] = a[m - 1, j] if s == t[m - 1] and fields == 3 else 0.0
            continue
        k = _segment_of(t, s, -1)
        dur = t[k + 1] - t[k]
        x = (s - t[k]) / dur
        if k != k_coef:                 # the segment's coefficients (kept while ts stay in it)
            k_coef = k
            _segment_coefficients(q, v, a, fields, k, dur, c)
        for j in range(n):
            p, dp, ddp = _horner(c, j, x)
            pos[i, j] = p
            vel[i, j] = dp / dur
            acc[i, j] = ddp / (dur * dur)


@njit(cache=True, nogil=True, inline="always")
def _nan_max(top, x):
    """max(top, x), NaN once either is (as NumPy's max)."""
    return x if top == top and (x > top or x != x) else top


@njit(cache=True, nogil=True)
def _segment_peaks(t, q, v, a, u, vlim, alim, out, c):
    """
    Fill out (M - 1, 2) with each segment's peak |velocity| / vlim and |acceleration| / alim of the quintics.

    The largest over the joints; at the segment's ends, at ``t_k + (t_k+1 - t_k) · u`` (u (S,) in
    [0, 1)) and, the acceleration exact, at its extrema inside (the roots of the third
    derivative).  t (M,) increasing strictly (:func:`_require_increasing`), q, v, a (M, n), vlim,
    alim (n,), c (8, n) scratch; NaN where a ratio is.
    """
    m, n = q.shape
    for k in range(m - 1):
        h = t[k + 1] - t[k]
        _segment_coefficients(q, v, a, 3, k, h, c)
        top_v = top_a = 0.0
        for j in range(n):
            for e in (k, k + 1):
                top_v = _nan_max(top_v, abs(v[e, j]) / vlim[j])
                top_a = _nan_max(top_a, abs(a[e, j]) / alim[j])
            for i in range(u.shape[0]):
                dp, ddp = _horner(c, j, u[i])[1:]
                top_v = _nan_max(top_v, abs(dp / h) / vlim[j])
                top_a = _nan_max(top_a, abs(ddp / (h * h)) / alim[j])
            for x in _unit_roots(60.0 * c[5, j], 24.0 * c[4, j], 6.0 * c[3, j]):
                if x > 0.0:
                    top_a = _nan_max(top_a, abs(_horner(c, j, x)[2] / (h * h)) / alim[j])
        out[k, 0] = top_v
        out[k, 1] = top_a


def segment_peaks(traj: "Trajectory", fractions, vlim, alim) -> np.ndarray:
    """
    Return each segment's peak velocity and acceleration ratios (M - 1, 2) of the controller's quintics.

    |velocity| / vlim sampled at ``fractions`` (S,) of each segment and its ends, |acceleration| /
    alim exact (also at its extrema inside: the quintic's acceleration is a cubic, whose peak near
    a point falls between samples, 0.15 % above 16 of them on the paper 3-DOF path); the largest
    over the joints (vlim, alim (n,)); NaN where a ratio is.

    Raises
    ------
        ValueError: times that do not increase strictly.

    """
    q = np.ascontiguousarray(traj.positions_rad, dtype=float)
    out = np.zeros((max(len(q) - 1, 0), 2))
    _require_increasing(traj.times_s, "segment_peaks")
    given = (traj.times_s, q, traj.velocities_rad_s, traj.accelerations_rad_s2, fractions, vlim, alim)
    if len(q) > 1:
        _segment_peaks(*[np.ascontiguousarray(x, dtype=float) for x in given], out, np.empty((8, q.shape[1])))
    return out


def _require_increasing(times_s, who: str) -> None:
    """Raise ValueError (naming ``who``) unless the times (M,) increase strictly (NaN does not)."""
    if not np.all(np.diff(np.asarray(times_s, dtype=float)) > 0.0):
        raise ValueError(f"{who}: times must increase strictly")


def sample_points(times_s, positions, velocities, accelerations, t_s):
    """
    Sample published trajectory points as joint_trajectory_controller interpolates them.

    Each segment between consecutive points is a polynomial in time chosen by the fields
    the points have (ros2_controllers' spline interpolation): positions only → linear;
    positions and velocities → cubic Hermite (position and velocity match at both ends);
    positions, velocities and accelerations → quintic (position, velocity and acceleration
    match at both ends).  A segment covers [t_k, t_k+1), as in the controller; at the last
    point's time exactly the result is that point (its velocities and accelerations, zero
    where absent).  Before the first point the arm holds the first, after the last point
    the last, at rest (zero velocity and acceleration).  Vectorised over the joints and
    over ``t_s``.

    Args:
        times_s: (M,) the points' times from the trajectory's start, s, strictly increasing.
        positions: (M, n) joint positions (rad, or m for a prismatic joint).
        velocities: (M, n) joint velocities per s, or None (positions only: linear).
        accelerations: (M, n) joint accelerations per s², or None; used only with
            ``velocities`` (a controller's quintic needs both).
        t_s: a time (float) or times (K,) from the trajectory's start, s.

    Returns
    -------
        (positions, velocities, accelerations): each (n,) for a float ``t_s``, (K, n) for
        an array; accelerations are zero on linear segments.

    Raises
    ------
        ValueError: shapes that do not match, times that do not increase, accelerations
        without velocities.

    """
    t = np.asarray(times_s, dtype=float)
    q = np.asarray(positions, dtype=float)
    if t.ndim != 1 or len(t) == 0 or q.ndim != 2 or q.shape[0] != len(t):
        raise ValueError(f"sample_points: times {t.shape} and positions {q.shape} must be (M,) and (M, n)")
    _require_increasing(t, "sample_points")
    v = None if velocities is None else np.asarray(velocities, dtype=float)
    a = None if accelerations is None else np.asarray(accelerations, dtype=float)
    for name, arr in (("velocities", v), ("accelerations", a)):
        if arr is not None and arr.shape != q.shape:
            raise ValueError(f"sample_points: {name} {arr.shape} must be shaped as the positions {q.shape}")
    if a is not None and v is None:
        raise ValueError("sample_points: accelerations without velocities")
    ts = np.asarray(t_s, dtype=float)
    scalar = ts.ndim == 0
    ts = np.ascontiguousarray(np.atleast_1d(ts))
    n_t, n = len(ts), q.shape[1]
    pos, vel, acc = np.empty((n_t, n)), np.empty((n_t, n)), np.empty((n_t, n))
    fields = 1 if v is None else 2 if a is None else 3
    q = np.ascontiguousarray(q)
    _controller_states(np.ascontiguousarray(t), q, q if v is None else np.ascontiguousarray(v),
                       q if a is None else np.ascontiguousarray(a), fields, ts, pos, vel, acc)
    if scalar:
        return pos[0], vel[0], acc[0]
    return pos, vel, acc


#: the controller's motion between two published points is certified as the polyline through
#: this many samples of it per segment (:func:`controller_check`): the quintic then lies within
#: about 1/64 of its deviation from the segment's chord (of ≤ 0.1°, the resampling's tolerance)
#: of a certified polyline
CONTROLLER_SAMPLES = 8


def controller_times(traj: Trajectory, samples_per_segment: int = CONTROLLER_SAMPLES) -> np.ndarray:
    """Return :func:`controller_motion`'s sample times (S (M - 1) + 1,), s: S a segment from its start, and the end."""
    t = np.asarray(traj.times_s, dtype=float)
    if len(t) < 2:
        return t.copy()
    u = np.arange(samples_per_segment) / samples_per_segment
    return np.append((t[:-1, None] + np.diff(t)[:, None] * u).ravel(), t[-1])


def controller_motion(traj: Trajectory, samples_per_segment: int = CONTROLLER_SAMPLES) -> tuple:
    """
    Sample the motion joint_trajectory_controller makes of a trajectory's points (:func:`sample_points`).

    At ``samples_per_segment`` (S) evenly spaced times of each segment, from its first point
    (exact: the point itself), and at the last point (:func:`controller_times`): (positions,
    velocities, accelerations), each (S (M - 1) + 1, dof), rad, rad/s, rad/s²; the trajectory's
    own point when M = 1.
    """
    t = np.asarray(traj.times_s, dtype=float)
    if len(t) < 2:
        return traj.positions_rad.copy(), traj.velocities_rad_s.copy(), traj.accelerations_rad_s2.copy()
    return sample_points(t, traj.positions_rad, traj.velocities_rad_s, traj.accelerations_rad_s2,
                         controller_times(traj, samples_per_segment))


#: the controller's motion may pass a joint's bound by this much and count as within it (rounding), rad
BOUND_SLACK_RAD = 1e-12


#: power basis (in the normalised time) to Bernstein basis, degree 5: b_r = Σ_{i ≤ r} C(r, i) / C(5, i) c_i
_TO_BERNSTEIN = np.array([[math.comb(r, i) / math.comb(5, i) if i <= r else 0.0 for i in range(6)] for r in range(6)])


@njit(cache=True, nogil=True, inline="always")
def _halve(w, left, right):
    """Split Bernstein coefficients w (6,) at 1/2 (de Casteljau): the halves' into left and right (w overwritten)."""
    for i in range(6):
        left[i] = w[0]
        right[5 - i] = w[5 - i]
        for k in range(5 - i):
            w[k] = 0.5 * (w[k] + w[k + 1])
        # after level i, w[0..5-i-1] hold level i+1


@njit(cache=True, nogil=True)
def _hull_peak(b, sign, stack, w, left, right):
    """
    Return (the largest value of sign · p on [0, 1], where): p the polynomial of Bernstein coefficients b (6,).

    Branch and bound on the coefficients' hull: a piece whose largest coefficient is no more than
    the best end value found (plus 1e-15 of the coefficients' scale) is dropped, the others halved
    (:func:`_halve`) down to 50 halvings; the value is an end value, so it lies within that of the
    peak.  ``stack`` (128, 8) scratch: a piece's coefficients, depth and start; ``w``, ``left``,
    ``right`` (6,) scratch.
    """
    scale = 0.0
    for i in range(6):
        scale = max(scale, abs(b[i]))
    tol = 1e-15 * max(scale, 1e-300)
    best, at = sign * b[0], 0.0
    if sign * b[5] > best:
        best, at = sign * b[5], 1.0
    top = 0
    for i in range(6):
        stack[0, i] = sign * b[i]
    stack[0, 6] = stack[0, 7] = 0.0
    while top >= 0:
        for i in range(6):
            w[i] = stack[top, i]
        depth, x0 = stack[top, 6], stack[top, 7]
        top -= 1
        if w.max() <= best + tol or depth >= 50.0:
            continue
        width = 0.5 ** (depth + 1.0)
        _halve(w, left, right)
        if left[5] > best:                  # the halves' common end
            best, at = left[5], x0 + width
        if top >= 125:
            continue                        # (never at 50 halvings: one piece per depth waits)
        for i in range(6):
            stack[top + 1, i] = right[i]
            stack[top + 2, i] = left[i]     # the left half first
        stack[top + 1, 6] = stack[top + 2, 6] = depth + 1.0
        stack[top + 1, 7], stack[top + 2, 7] = x0 + width, x0
        top += 2
    return best, at


@njit(cache=True, nogil=True, inline="always")
def _bernstein(c, j, b):
    """
    Write column j of the power-basis polynomial c (6, n) into b (6,) in the Bernstein basis; return b's (min, max).

    The normalised time of :func:`_segment_coefficients`; the curve lies within [min, max].
    """
    low, high = np.inf, -np.inf
    for r in range(6):
        acc = 0.0
        for i in range(r + 1):
            acc += _TO_BERNSTEIN[r, i] * c[i, j]
        b[r] = acc
        low, high = min(low, acc), max(high, acc)
    return low, high


@njit(cache=True, nogil=True, inline="always")
def _past_by(b, low, high, lo, hi, stack, w, left, right):
    """
    Return (how far the quintic of Bernstein coefficients b (6,) passes [lo, hi], where in [0, 1], side): exactly.

    ``low``, ``high``: b's least and largest (the curve lies within them).  Where they are within
    the bounds: (0, 0, 0); else the larger of the peak past hi and the dip past lo
    (:func:`_hull_peak`, to about 1e-15 of the quintic's scale; ≤ 0: within) and its side (1 the upper
    bound, -1 the lower).  The one rule of the controller check's bounds and of a refusal's text.
    """
    past, x, side = 0.0, 0.0, 0
    if high > hi:
        top, xt = _hull_peak(b, 1.0, stack, w, left, right)
        past, x, side = top - hi, xt, 1
    if low < lo:
        top, xt = _hull_peak(b, -1.0, stack, w, left, right)
        if side == 0 or lo + top > past:
            past, x, side = lo + top, xt, -1
    return past, x, side


@njit(cache=True, nogil=True)
def _segments_within_bounds(t, q, v, a, lo, hi, out):
    """
    Set out[k] (M-1,) False where segment k's quintic passes a joint's bound (lo, hi (n,); ±inf: none), exactly.

    By more than BOUND_SLACK_RAD (:func:`_past_by`: the segment's polynomial, normalised time, in the
    Bernstein basis, its hull first: within it, the curve is).
    """
    m, n = q.shape
    c = np.zeros((6, n))
    b, w, left, right = np.empty(6), np.empty(6), np.empty(6), np.empty(6)
    stack = np.empty((128, 8))
    for k in range(m - 1):
        _segment_coefficients(q, v, a, 3, k, t[k + 1] - t[k], c)
        for j in range(n):
            if lo[j] == -np.inf and hi[j] == np.inf:
                continue
            low, high = _bernstein(c, j, b)
            if low >= lo[j] - BOUND_SLACK_RAD and high <= hi[j] + BOUND_SLACK_RAD:
                continue                # the hull within: the curve is
            if _past_by(b, low, high, lo[j], hi[j], stack, w, left, right)[0] > BOUND_SLACK_RAD:
                out[k] = False
                break


@njit(cache=True, nogil=True)
def _segments_past_bounds(t, q, v, a, lo, hi, excess, at, side):
    """
    Fill excess (M-1, n): how far segment k's quintic passes joint j's bound (lo, hi (n,)), rad, exactly; at: when, s.

    Each segment's :func:`_past_by` (0 at its start where its Bernstein hull stays within both
    bounds), its time and side (side int8 (M-1, n): 1 the upper bound, -1 the lower, 0 the hull
    within): the controller check's own rule (:func:`_segments_within_bounds`).
    """
    m, n = q.shape
    c = np.zeros((6, n))
    b, w, left, right = np.empty(6), np.empty(6), np.empty(6), np.empty(6)
    stack = np.empty((128, 8))
    for k in range(m - 1):
        dur = t[k + 1] - t[k]
        _segment_coefficients(q, v, a, 3, k, dur, c)
        for j in range(n):
            excess[k, j], at[k, j], side[k, j] = 0.0, t[k], 0
            if lo[j] == -np.inf and hi[j] == np.inf:
                continue
            low, high = _bernstein(c, j, b)
            past, x, sd = _past_by(b, low, high, lo[j], hi[j], stack, w, left, right)
            excess[k, j], at[k, j], side[k, j] = past, t[k] + x * dur, sd


def past_bounds(traj: Trajectory, lo, hi) -> tuple:
    """
    Return how far the controller's motion of ``traj`` passes each joint's bounds, exactly: (excess, at, side).

    Each (n,): the largest over the segments' quintics (:func:`_segments_past_bounds`) joint by
    joint, rad, its time from the trajectory's start, s, and the bound's side (1 upper, -1 lower, 0
    none); an excess ≤ 0 where a joint stays within (lo, hi (n,) rad, ±inf for none).  It names
    what :func:`controller_check` refuses (an excess above :data:`BOUND_SLACK_RAD`).
    """
    t = np.ascontiguousarray(traj.times_s, dtype=float)
    n = traj.positions_rad.shape[1]
    if len(t) < 2:
        return np.zeros(n), np.zeros(n), np.zeros(n, np.int8)
    excess, at = np.empty((len(t) - 1, n)), np.empty((len(t) - 1, n))
    side = np.empty((len(t) - 1, n), np.int8)
    _segments_past_bounds(t, np.ascontiguousarray(traj.positions_rad, dtype=float),
                          np.ascontiguousarray(traj.velocities_rad_s, dtype=float),
                          np.ascontiguousarray(traj.accelerations_rad_s2, dtype=float),
                          np.asarray(lo, dtype=float), np.asarray(hi, dtype=float), excess, at, side)
    k = np.argmax(excess, axis=0)
    cols = np.arange(n)
    return excess[k, cols], at[k, cols] - t[0], side[k, cols]


def controller_check(traj: Trajectory, motions, samples_per_segment: int = CONTROLLER_SAMPLES) -> tuple:
    """
    Certify the arm's motion as the controller moves it through ``traj``'s points, on the exact geometry.

    The polyline through :func:`controller_motion`'s samples, checked by ``motions`` (the scene's
    ``motion.MotionValidator``): the curve, not the chords between the points (a quintic bulges
    off its chord, up to about 2 mm towards an obstacle on the paper-family scenes).  One
    certified walk past the samples (``every_row=False``: eight a segment are far closer than
    the walk's steps; a paper 3-DOF replan's 900 samples take about 340 clearances instead of
    900, 80 instead of 190 us), so the clearance reported is the least at the walk's own samples
    and at the first and last (``MotionValidator.check``).  The joints' bounds are checked on the quintics themselves,
    exactly (:func:`_segments_within_bounds`: a quintic can pass a bound between the samples and be
    back within at the next).  Returns
    (``motion.PathCheck`` of that polyline, its ``ok`` and ``interval_ok`` False too where a segment's
    quintic passes a bound, segment_ok bool (M - 1,): each segment's samples passed, and its quintic
    stays within the bounds).
    """
    validator = MotionValidator.of(motions)
    check = validator.check(controller_motion(traj, samples_per_segment)[0], every_row=False)
    if len(traj.times_s) < 2:
        return check, np.zeros(0, bool)
    seg_ok = np.asarray(check.interval_ok, dtype=bool).reshape(-1, samples_per_segment).all(axis=1)
    within = np.ones(len(traj.times_s) - 1, dtype=bool)
    _segments_within_bounds(np.ascontiguousarray(traj.times_s, dtype=float),
                            np.ascontiguousarray(traj.positions_rad, dtype=float),
                            np.ascontiguousarray(traj.velocities_rad_s, dtype=float),
                            np.ascontiguousarray(traj.accelerations_rad_s2, dtype=float), *validator.bounds_rad, within)
    if not within.all():
        seg_ok &= within
        interval_ok = np.asarray(check.interval_ok, dtype=bool) & np.repeat(within, samples_per_segment)
        check = replace(check, ok=False, interval_ok=interval_ok)
    return check, seg_ok


@njit(cache=True, nogil=True)
def _load_at(pair, inertia, c, dur, x, joints, qf, qdf, qddf, w):
    """Return (|h|, |dh/dt|) at x in [0, 1] of the quintic segment c (6, dof) (:func:`_segment_coefficients`)."""
    for j in range(joints.size):
        p, dp, ddp = _horner(c, j, x)
        qf[joints[j]] = p
        qdf[joints[j]] = dp / dur
        qddf[joints[j]] = ddp / (dur * dur)
    h, rate = _sample_momentum(pair, inertia, qf, qdf, qddf, w)
    return abs(h), abs(rate)


@njit(cache=True, nogil=True, inline="always")
def _vertex(f, i, step):
    """
    Return the fraction of a segment where the parabola through samples i - 1, i, i + 1 of f peaks.

    f (S + 1,) the samples at fractions k · step, i in [1, S - 1]; -1.0 where the three do not
    bend down (no peak between them).
    """
    bend = f[i - 1] - 2.0 * f[i] + f[i + 1]
    if not bend < 0.0:
        return -1.0
    return (i + 0.5 * (f[i - 1] - f[i + 1]) / bend) * step


#: :func:`segment_wheel_peaks` also searches between the samples around each local maximum of the
#: samples within this fraction of their largest (where a second hump may peak higher between them)
PEAK_SEARCH_BAND = 0.05


@njit(cache=True, nogil=True)
def _segment_row(t, q, v, a, k, row, bits):
    """
    Fill row (1 + 6 dof,) with segment k's duration and its ends' q, v, a; return a hash of its bits (uint64).

    What a controller segment's motion depends on (its quintic, :func:`_segment_coefficients`): two
    segments with the same row, bit for bit, move the same.  ``bits``: row's own memory as uint64 (the
    caller's NumPy view of it).
    """
    dof = q.shape[1]
    row[0] = t[k + 1] - t[k]
    for j in range(dof):
        row[1 + j] = q[k, j]
        row[1 + dof + j] = q[k + 1, j]
        row[1 + 2 * dof + j] = v[k, j]
        row[1 + 3 * dof + j] = v[k + 1, j]
        row[1 + 4 * dof + j] = a[k, j]
        row[1 + 5 * dof + j] = a[k + 1, j]
    return _bits_hash(bits)


@njit(cache=True, nogil=True)
def _memo_slot(keys, row_bits, used, h, bits):
    """Return the memo's slot of a row (its bits, hash h): its own (found: the same bits) or the free one it takes."""
    mask = np.uint64(keys.size - 1)
    slot = np.int64(h & mask)
    while used[slot]:
        if keys[slot] == h:
            same = True
            for i in range(bits.size):
                if row_bits[slot, i] != bits[i]:
                    same = False
                    break
            if same:
                return slot
        slot = (slot + 1) & np.int64(mask)
    return slot


@njit(cache=True, nogil=True)
def _segment_wheel_peaks(t, q, v, a, samples, joints, q_full, pair, inertia, out, c, keys, row_bits, vals, used,
                         count, row, bits):
    """
    Fill out (M - 1, 2) with each segment's peak |h_wheel| and |τ_wheel| of the controller's quintics.

    At ``samples`` + 1 evenly spaced fractions of each segment (its ends included) and, for
    each of the two, at the vertex of the parabola through the largest sample and its two
    neighbours, and around every other local maximum within :data:`PEAK_SEARCH_BAND` of it (the
    peak between samples).  t (M,), q, v, a (M, dof) the planned joints,
    which are ``joints`` (dof,) of the full configuration ``q_full`` (n,) (the locked joints'
    positions; at rest); pair, inertia: ``spacecraft._momentum_tables``; c (6, dof) scratch; t increasing
    strictly (:func:`_require_increasing`).  NaN where a load is.  keys, row_bits, vals, used, count: a
    memo of segments met before (:class:`_PeakMemo`; size 0: none): a segment whose row
    (:func:`_segment_row`) it holds, bit for bit, takes its peaks; one it does not is added while the
    memo is at most half full.  row (1 + 6 dof,) scratch, bits its uint64 view.
    """
    mpts = t.shape[0]
    n = q_full.shape[0]
    qf = q_full.copy()
    qdf = np.zeros(n)
    qddf = np.zeros(n)
    w = np.empty((4, n))
    fh = np.empty(samples + 1)
    ft = np.empty(samples + 1)
    step = 1.0 / samples
    memo = keys.size > 0
    slot = np.int64(0)
    h_row = np.uint64(0)
    for k in range(mpts - 1):
        if memo:
            h_row = _segment_row(t, q, v, a, k, row, bits)
            slot = _memo_slot(keys, row_bits, used, h_row, bits)
            if used[slot]:
                out[k, 0] = vals[slot, 0]
                out[k, 1] = vals[slot, 1]
                continue
        dur = t[k + 1] - t[k]
        _segment_coefficients(q, v, a, 3, k, dur, c)
        top_h = top_t = 0.0
        ih = it = 0
        for i in range(samples + 1):
            fh[i], ft[i] = _load_at(pair, inertia, c, dur, i * step, joints, qf, qdf, qddf, w)
            if fh[i] > top_h:
                top_h, ih = fh[i], i
            if ft[i] > top_t:
                top_t, it = ft[i], i
            top_h = _nan_max(top_h, fh[i])
            top_t = _nan_max(top_t, ft[i])
        if samples >= 2 and top_h == top_h and top_t == top_t:
            for f, i_top, top in ((fh, ih, top_h), (ft, it, top_t)):
                # around the largest sample (its neighbours within the segment at an end) and every
                # other local maximum within PEAK_SEARCH_BAND of it (a second hump may be the higher)
                for i in range(1, samples):
                    near = i == min(max(i_top, 1), samples - 1) or (
                        f[i] >= f[i - 1] and f[i] >= f[i + 1] and f[i] >= (1.0 - PEAK_SEARCH_BAND) * top)
                    if not near:
                        continue
                    x = _vertex(f, i, step)
                    if 0.0 < x < 1.0:
                        h, tau = _load_at(pair, inertia, c, dur, x, joints, qf, qdf, qddf, w)
                        top_h = _nan_max(top_h, h)
                        top_t = _nan_max(top_t, tau)
        out[k, 0] = top_h
        out[k, 1] = top_t
        if memo and 2 * (count[0] + 1) <= keys.size:
            used[slot] = True
            keys[slot] = h_row
            row_bits[slot, :] = bits
            vals[slot, 0] = top_h
            vals[slot, 1] = top_t
            count[0] += 1


class _PeakMemo:
    """
    :func:`segment_wheel_peaks`' memo within :func:`shared_path_models`: each segment's peaks, by its row.

    A chain's re-timings lower the limits along stretches: most of the re-timed trajectory's
    segments are the last round's, bit for bit (the servicer's: a third of them in the second
    round, 97 % in the third), and their quintics' loads need not be sampled again.  Open
    addressing over ``slots`` (a power of two), at most half of them used.
    """

    def __init__(self, slots: int, width: int):
        self.keys = np.zeros(slots, np.uint64)
        self.row_bits = np.zeros((slots, width), np.uint64)
        self.vals = np.zeros((slots, 2))
        self.used = np.zeros(slots, np.bool_)
        self.count = np.zeros(1, np.int64)

    def arrays(self) -> tuple:
        return self.keys, self.row_bits, self.vals, self.used, self.count


#: no memo (outside :func:`shared_path_models`)
_NO_MEMO = _PeakMemo(0, 1)


def _peak_memo(ident: tuple, segments: int, width: int) -> _PeakMemo:
    """Return the chain's memo of wheel peaks for ``ident`` (the tables, the locked joints, the samples), else none."""
    shared = _SHARED_MODELS.get()
    if shared is None:
        return _NO_MEMO
    key = ("segment_wheel_peaks",) + ident
    memo = shared.get(key)
    if memo is None:
        slots = 1 << max(10, int(8 * segments).bit_length())
        memo = shared[key] = _PeakMemo(slots, width)
    return memo


def segment_wheel_peaks(robot, masses, traj, samples_per_segment: int = 16) -> np.ndarray:
    """
    Return each segment's peak wheel momentum |h_wheel| (N·m·s) and torque |τ_wheel| (N·m), (M - 1, 2).

    The load (``spacecraft.wheel_load``) of the motion joint_trajectory_controller makes of
    ``traj``'s points (its quintic between two points, :func:`sample_points`), with the attitude
    held: at ``samples_per_segment`` + 1 evenly spaced times of each segment (its ends included)
    and where the parabola through the largest of them and its neighbours peaks, and through
    every other local maximum within :data:`PEAK_SEARCH_BAND` of it (a peak between samples: up
    to 0.4 % of a limit above 16 of them on the servicer's trajectories).  One pass, no arrays of
    samples.

    Raises
    ------
        ValueError: times that do not increase strictly.

    """
    if int(samples_per_segment) < 1:
        raise ValueError(f"samples_per_segment: must be at least 1, got {samples_per_segment}")
    pair, inertia = _momentum_tables(robot, masses)
    q = np.ascontiguousarray(traj.positions_rad, dtype=float)
    out = np.zeros((max(len(q) - 1, 0), 2))
    if len(q) < 2:
        return out
    _require_increasing(traj.times_s, "segment_wheel_peaks")
    given = (traj.times_s, q, traj.velocities_rad_s, traj.accelerations_rad_s2)
    q_full = robot.full(q[0])
    memo = _peak_memo((pair.tobytes(), inertia.tobytes(), q_full.tobytes(), int(samples_per_segment)),
                      len(q) - 1, 1 + 6 * q.shape[1])
    row = np.zeros(1 + 6 * q.shape[1])
    _segment_wheel_peaks(*[np.ascontiguousarray(x, dtype=float) for x in given], int(samples_per_segment),
                         np.asarray(robot.planned_joints, np.int64), q_full, pair, inertia, out,
                         np.zeros((6, q.shape[1])), *memo.arrays(), row, row.view(np.uint64))
    return out
