"""
Time-optimal time parameterisation of a geometric joint path (TOPP-RA style).

The last stage of the chain (MoveIt's "time parameterisation adapter"): it takes the
planner's dense path (M×n joint positions, rad, start first, goal last, periodic
joints unwrapped) and returns the times at which to pass every point, with joint
velocities and accelerations, so that no joint exceeds its velocity limit (rad/s)
or its acceleration limit (rad/s²), scaled by MoveIt's ``velocity_scaling`` /
``acceleration_scaling`` factors, and, given a wheel model (``spacecraft.WheelModel``),
the reaction-wheel momentum (N·m·s) and torque (N·m) stay within their limits.  The
arm starts at rest or moving along the path's tangent (``start_path_speed`` or
``start_velocity_rad_s``) and ends at rest.

Method (reachability analysis, Pham & Pham's TOPP-RA):

1. A cubic spline through the path samples (not-a-knot, parameter s = joint-space chord
   length, rad) gives q', q'' and the (piecewise constant) q''' on a grid
   ``grid_refinement`` (2) times finer than the samples; the trajectory keeps one point
   per sample, at exactly the given positions.  (4 times finer: the paper paths' durations
   0.02-0.2 % shorter, for twice the work of every pass; the limits hold at any refinement.)
   Given the joints' bounds, the spline is kept within them: where it would pass one between
   the samples, the samples on that bound become knots where the joint's q' is 0 (C1 there,
   C2 elsewhere; ``_bounded_slopes``).
2. On each grid segment ``[s_i, s_{i+1}]`` the path acceleration ``u_i = s̈`` is constant,
   so ``x = ṡ²`` is linear: ``x_{i+1} = x_i + 2 Δ_i u_i``.  Every constraint is written
   at *both* ends of the segment with the segment's ``u_i`` ("first-order
   interpolation"):

   - velocity type, ``x_i ≤ xv_i``: ``|q'_j| ṡ ≤ v_j``, with |q'_j| raised by
     ``|q'''| Δ²/8``, the most it can grow inside the segment, and ``|H·q'| ṡ ≤ h_max``
     for the wheel momentum;
   - acceleration type, ``|A u + B x| + κ|u| ≤ C``: ``|q'_j u + q''_j x| ≤ a_j`` per
     joint, with κ = 2.5 |q'''| Δ²/4 the most the (quadratic in s) joint acceleration
     can exceed its end values inside the segment, and
     ``|(H·q') u + (d(H·q')/ds) x| ≤ τ_max`` for the wheel torque.

   In the variables ``(x_i, x_{i+1})`` all of them are half-planes.  So the joint
   velocity and acceleration stay within the limits everywhere along the spline, and
   so does every finite difference of the positions (a weighted mean of the
   acceleration over the neighbouring intervals), for the dense points and any subset.
3. A backward pass computes the controllable sets ``K_i = [0, k_i]`` (the speeds²
   from which the goal can still be reached at rest); a forward pass from the start
   speed² picks at each step the largest ``x_{i+1} ∈ K_{i+1}`` the constraints admit.
   Both passes use the same feasibility test: no uniform slow-down is applied or needed.
   A start above the velocity bound (``brake_to_limits``: limits lowered while the arm moves)
   is braked instead of refused: while x_i lies above K_i the forward pass takes the least
   x_{i+1} the acceleration rows admit, its ratio to the velocity bound never rising above the
   larger of 1 and x_i's, until it can enter K (``_forward_braking``).
   The published times are float64 and the finite differences amplify their rounding
   (by about |w| ulp(t) / Δt², which matters where samples are close in time, e.g.
   6·10⁻⁵ s apart at t = 1.65 s: 10⁻⁷ of the limit).  A bound on that rounding
   (``_rounding_margins``) is taken off the limits locally, where it exceeds 10⁻¹⁰ of
   them, and the passes rerun until the bound of the new solution fits (one rerun in
   practice; elsewhere nothing changes).
4. ``Δt_i = 2 Δ_i / (ṡ_i + ṡ_{i+1})``, summed per sample interval, then accumulated.
   Published velocities ``q' ṡ``; accelerations ``q' ū + q'' x`` with ``ū`` the
   Δt-weighted mean of the two neighbouring segments' ``u`` (a convex combination, so
   still within the limits; it is what the finite differences of the positions approach).

Finite differences (``finite_differences``): segment velocity
``w_k = (q_{k+1} - q_k) / (t_{k+1} - t_k)``; acceleration at an interior point
``(w_k - w_{k-1}) / ((Δt_{k-1} + Δt_k) / 2)``, at the first point
``(w_0 - v_0) / (Δt_0 / 2)`` and at the last ``-w_{M-2} / (Δt_{M-2} / 2)``; both obey
the limits (see 2.) and approach the published values as the samples get closer.

Which of the points are published, and the motion a controller makes of them (its
interpolation, certified on the exact geometry, its peaks against the limits), are the next
stage: ``published.py``.

No ROS imports here: NumPy/SciPy; every per-sample loop (densifying, the spline on the
grid, the constraint rows, the two passes, the rounding margins, the samples' states) is a
numba kernel that keeps NumPy's arithmetic operation for operation, so the trajectories are
the same bit for bit as the array code they replaced.
"""

from __future__ import annotations

import math
from contextlib import contextmanager
from contextvars import ContextVar
from dataclasses import dataclass, replace

import numpy as np
from numba import njit

from .collision import NO_REFCOUNT

__all__ = ["Trajectory", "Lowering", "Continuation", "time_parameterize", "finite_differences", "sample",
           "densify_path", "limit_ratios", "start_path_speed_from_velocity", "continuation",
           "horizon_index", "HorizonPassed", "chord_lengths_rad", "arc_lengths_rad", "lowering_factors",
           "check_start_tangent", "shared_path_models"]


@dataclass(frozen=True, eq=False)
class Trajectory:
    """
    A time-parameterised joint path.

    Attributes
    ----------
        joint_names: one name per column.
        times_s: (M,) strictly increasing, 0 first.
        positions_rad: (M, n); first row the start, last row the goal (exact).
        velocities_rad_s: (M, n); the start velocity first (zero when starting at
            rest), zero at the end.
        accelerations_rad_s2: (M, n).
        max_velocity_rad_s, max_acceleration_rad_s2: (n,) the (scaled) joint limits it obeys.
        path_speed: (M,) ṡ, joint-space chord length per second (rad/s).
        active_limit: (M,) str, the constraint closest to its limit at each point:
            ``"velocity:<joint>"``, ``"acceleration:<joint>"``, ``"wheel_momentum"``,
            ``"wheel_torque"`` (``limit_ratio`` says how close).
        limit_ratio: (M,) |value| / limit of that constraint (≤ 1; above 1 only where a start
            above the velocity limits brakes to them: ``time_parameterize(brake_to_limits=True)``).
        wheel_momentum_Nms, wheel_torque_Nm: (M,) h_wheel = −H·q̇ and its time
            derivative when a wheel model was given, else None.
        max_wheel_momentum_Nms, max_wheel_torque_Nm: the wheel limits obeyed (None: none).

    """

    joint_names: tuple
    times_s: np.ndarray
    positions_rad: np.ndarray
    velocities_rad_s: np.ndarray
    accelerations_rad_s2: np.ndarray
    max_velocity_rad_s: np.ndarray
    max_acceleration_rad_s2: np.ndarray
    path_speed: np.ndarray = None
    active_limit: np.ndarray = None
    limit_ratio: np.ndarray = None
    wheel_momentum_Nms: np.ndarray = None
    wheel_torque_Nm: np.ndarray = None
    max_wheel_momentum_Nms: float | None = None
    max_wheel_torque_Nm: float | None = None

    @property
    def duration_s(self) -> float:
        return float(self.times_s[-1])

    def __len__(self) -> int:
        return len(self.times_s)

    def subset(self, indices) -> "Trajectory":
        """Return the trajectory at the points ``indices`` (sorted, first and last included)."""
        idx = np.asarray(indices, dtype=np.int64)

        def pick(a):
            return None if a is None else a[idx]

        return replace(self, times_s=self.times_s[idx], positions_rad=self.positions_rad[idx],
                       velocities_rad_s=self.velocities_rad_s[idx],
                       accelerations_rad_s2=self.accelerations_rad_s2[idx],
                       path_speed=pick(self.path_speed), active_limit=pick(self.active_limit),
                       limit_ratio=pick(self.limit_ratio),
                       wheel_momentum_Nms=pick(self.wheel_momentum_Nms),
                       wheel_torque_Nm=pick(self.wheel_torque_Nm))

    def slowed(self, factor: float) -> "Trajectory":
        """
        Return this motion along the same path, ``factor`` (≥ 1) times as long: t → factor·t.

        Every point keeps its position; velocities are divided by ``factor``, accelerations by
        its square, as are the path speed, the wheel momentum (÷ factor) and torque (÷ factor²)
        and each point's ``limit_ratio`` by its constraint's kind.  A quintic (or any polynomial)
        through the points is then the one through the old points at t / factor, so the
        controller's motion keeps its curve and its peaks fall by the same factors.  Raises
        ValueError for a factor below 1 (or not finite).
        """
        k = float(factor)
        if not (math.isfinite(k) and k >= 1.0):
            raise ValueError(f"slowed: the factor must be a finite number >= 1, got {factor!r}")
        ratio = self.limit_ratio
        if ratio is not None and self.active_limit is not None:
            second = np.array([str(a).startswith(("acceleration", "wheel_torque")) for a in self.active_limit])
            ratio = np.where(second, ratio / (k * k), ratio / k)

        def div(a, d):
            return None if a is None else a / d

        return replace(self, times_s=self.times_s * k, velocities_rad_s=self.velocities_rad_s / k,
                       accelerations_rad_s2=self.accelerations_rad_s2 / (k * k),
                       path_speed=div(self.path_speed, k), limit_ratio=ratio,
                       wheel_momentum_Nms=div(self.wheel_momentum_Nms, k),
                       wheel_torque_Nm=div(self.wheel_torque_Nm, k * k))

    def then(self, other: "Trajectory") -> "Trajectory":
        """
        Append ``other``, which starts where this trajectory ends at rest.

        ``other``'s times are shifted by this one's duration; the shared point appears once
        (with ``other``'s acceleration, the one that follows).

        Raises
        ------
            ValueError: ``other`` does not start where this one ends, or either is not at
                rest there, or the joints differ.

        """
        if tuple(other.joint_names) != tuple(self.joint_names):
            raise ValueError(f"then: joints {other.joint_names} after {self.joint_names}")
        if np.max(np.abs(other.positions_rad[0] - self.positions_rad[-1])) > 1e-9:
            raise ValueError("then: the second trajectory does not start where the first ends")
        if np.any(self.velocities_rad_s[-1] != 0.0) or np.any(other.velocities_rad_s[0] != 0.0):
            raise ValueError("then: the trajectories must meet at rest")
        head = self.subset(np.arange(len(self) - 1))

        def cat(a, b):
            return None if a is None or b is None else np.concatenate([a, b])

        return replace(self, times_s=np.concatenate([head.times_s, other.times_s + self.duration_s]),
                       positions_rad=cat(head.positions_rad, other.positions_rad),
                       velocities_rad_s=cat(head.velocities_rad_s, other.velocities_rad_s),
                       accelerations_rad_s2=cat(head.accelerations_rad_s2, other.accelerations_rad_s2),
                       path_speed=cat(head.path_speed, other.path_speed),
                       active_limit=cat(head.active_limit, other.active_limit),
                       limit_ratio=cat(head.limit_ratio, other.limit_ratio),
                       wheel_momentum_Nms=cat(head.wheel_momentum_Nms, other.wheel_momentum_Nms),
                       wheel_torque_Nm=cat(head.wheel_torque_Nm, other.wheel_torque_Nm))

    def to_json_dict(self) -> dict:
        """
        Return a plain-JSON view.

        joint_names, times_s, positions_rad, velocities_rad_s, accelerations_rad_s2 (lists),
        plus the active limit per point.
        """
        return {"joint_names": list(self.joint_names),
                "times_s": self.times_s.tolist(),
                "positions_rad": self.positions_rad.tolist(),
                "velocities_rad_s": self.velocities_rad_s.tolist(),
                "accelerations_rad_s2": self.accelerations_rad_s2.tolist(),
                "duration_s": self.duration_s,
                "active_limit": None if self.active_limit is None else [str(a) for a in self.active_limit]}


@njit(cache=True, nogil=True)
def _densified(p, max_step_rad, min_points):
    """
    Return :func:`densify_path` of an (M, n) array (M ≥ 2): the kept rows, then subdivided.

    No rows: p has a NaN or inf.  A row is kept when it is more than 1e-12 rad (in some joint) from the last kept row,
    the first always and the last in place of the last kept one (exact goal).
    """
    m, n = p.shape
    for k in range(m):
        for a in range(n):
            if not np.isfinite(p[k, a]):
                return np.empty((0, n))     # refused by the caller
    keep = np.empty(m, np.int64)
    keep[0] = 0
    n_keep = 1
    for k in range(1, m):
        last = keep[n_keep - 1]
        for a in range(n):
            if abs(p[k, a] - p[last, a]) > 1e-12:
                keep[n_keep] = k
                n_keep += 1
                break
    if n_keep > 1:
        keep[n_keep - 1] = m - 1            # exact goal last
    if n_keep == 1:
        return p[:1].copy()
    steps = np.empty(n_keep - 1)
    subdiv = np.empty(n_keep - 1, np.int64)
    total = 0
    widest = 0
    for k in range(n_keep - 1):
        st = 0.0
        for a in range(n):
            st = max(st, abs(p[keep[k + 1], a] - p[keep[k], a]))
        steps[k] = st
        if st > steps[widest]:
            widest = k
        subdiv[k] = max(1, int(np.ceil(st / max_step_rad - 1e-9)))
        total += subdiv[k]
    if total + 1 < min_points:
        subdiv[widest] += min_points - 1 - total
        total = min_points - 1
    out = np.empty((total + 1, n))
    out[0] = p[keep[0]]
    row = 1
    for k in range(n_keep - 1):
        sub = subdiv[k]
        i0, i1 = keep[k], keep[k + 1]
        for j in range(sub - 1):
            f = (j + 1) / sub
            for a in range(n):
                out[row, a] = p[i0, a] + f * (p[i1, a] - p[i0, a])
            row += 1
        out[row] = p[i1]                    # segment ends exactly
        row += 1
    return out


def densify_path(path_rad, max_step_rad: float = np.radians(0.5), min_points: int = 3) -> np.ndarray:
    """
    Drop repeated points and subdivide the path.

    Consecutive points end ≤ max_step_rad apart (in every joint), and there are at least
    ``min_points`` (when start ≠ goal).  The first and last points are kept exactly.
    """
    p = np.asarray(path_rad, dtype=float)
    if p.ndim != 2 or p.shape[0] < 1:
        raise ValueError(f"path: expected an (M, n) array with M ≥ 1, got shape {p.shape}")
    out = _densified(np.ascontiguousarray(p), float(max_step_rad), int(min_points)) if len(p) > 1 else p.copy()
    if len(out) == 0 or (len(p) == 1 and not np.all(np.isfinite(p))):
        raise ValueError("path: contains NaN or inf")
    return out


@njit(cache=True, nogil=True)
def not_a_knot_slopes(x, y):
    """
    Return the slopes (M, n) at the knots of the not-a-knot cubic spline through (x (M,), y (M, n)), M ≥ 3.

    M = 3: the parabola through the three knots (SciPy's ``CubicSpline`` does the same).
    M ≥ 4: SciPy's ``CubicSpline`` system (the same rows), solved by LAPACK's ``gtsv``
    elimination (tridiagonal, partial pivoting); the matrix is the same for every column, so
    it is eliminated once and the columns' right-hand sides follow it.  The one not-a-knot
    solve of the package (:func:`_spline_slopes`): the trajectory's path model and the smoothed
    path's spline.
    """
    m, n = y.shape
    dx = x[1:] - x[:-1]
    if m == 3:
        out = np.empty((3, n))
        for col in range(n):
            s0 = (y[1, col] - y[0, col]) / dx[0]
            s1 = (y[2, col] - y[1, col]) / dx[1]
            c = (s1 - s0) / (x[2] - x[0])
            out[0, col] = s0 - c * dx[0]
            out[1, col] = s0 + c * dx[0]
            out[2, col] = s1 + c * dx[1]
        return out
    return _spline_slopes(x, y, y[0], False, y[0], False)


@njit(cache=True, nogil=True)
def clamped_start_slopes(x, y, start_slope):
    """
    Return the knot slopes (M, n) of the cubic spline through (x (M,), y (M, n)), M ≥ 3, leaving at ``start_slope``.

    The first derivative at x[0] is ``start_slope`` (n,) (clamped), the end is not-a-knot: SciPy's
    ``CubicSpline(x, y, bc_type=((1, start_slope), "not-a-knot"))``, by :func:`_spline_slopes`.
    A path that must leave its start along a given direction (a replan joined to a moving arm:
    the arm's velocity over its path speed).
    """
    return _spline_slopes(x, y, start_slope, True, start_slope, False)


@njit(cache=True, nogil=True)
def _spline_slopes(x, y, start_slope, clamped, end_slope, clamped_end):
    """
    Solve SciPy's ``CubicSpline`` system for the knot slopes (M, n): M ≥ 3 where an end is not-a-knot.

    At the start not-a-knot, or (``clamped``) the first slope is ``start_slope`` (n,), SciPy's
    ``bc_type`` ``(1, start_slope)`` row; at the end not-a-knot, or (``clamped_end``) the last
    slope is ``end_slope`` (n,).  M = 2: the slopes given at a clamped end, the parabola's at
    the other.  LAPACK's ``gtsv`` elimination (tridiagonal, partial pivoting), the matrix
    eliminated once for every column.
    """
    m, n = y.shape
    dx = x[1:] - x[:-1]
    if m == 2:
        out = np.empty((2, n))
        for col in range(n):
            sec = (y[1, col] - y[0, col]) / dx[0]
            out[0, col] = start_slope[col] if clamped else 2.0 * sec - end_slope[col]
            out[1, col] = end_slope[col] if clamped_end else 2.0 * sec - out[0, col]
        return out
    d = np.empty(m)
    du = np.empty(m - 1)
    dl = np.empty(m - 1)
    du2 = np.zeros(m)
    b = np.empty((m, n))
    sl = np.empty((m - 1, n))
    for i in range(m - 1):
        for col in range(n):
            sl[i, col] = (y[i + 1, col] - y[i, col]) / dx[i]
    for i in range(1, m - 1):
        d[i] = 2.0 * (dx[i - 1] + dx[i])
        du[i] = dx[i - 1]
        dl[i - 1] = dx[i]
        for col in range(n):
            b[i, col] = 3.0 * (dx[i] * sl[i - 1, col] + dx[i - 1] * sl[i, col])
    if clamped:                         # the slope itself
        d[0] = 1.0
        du[0] = 0.0
        for col in range(n):
            b[0, col] = start_slope[col]
    else:
        w = x[2] - x[0]
        d[0] = dx[1]
        du[0] = w
        for col in range(n):
            b[0, col] = ((dx[0] + 2.0 * w) * dx[1] * sl[0, col] + dx[0] ** 2 * sl[1, col]) / w
    if clamped_end:
        d[m - 1] = 1.0
        dl[m - 2] = 0.0
        for col in range(n):
            b[m - 1, col] = end_slope[col]
    else:
        w = x[m - 1] - x[m - 3]
        d[m - 1] = dx[m - 3]
        dl[m - 2] = w
        for col in range(n):
            b[m - 1, col] = (dx[m - 2] ** 2 * sl[m - 3, col] + (2.0 * w + dx[m - 2]) * dx[m - 3] * sl[m - 2, col]) / w
    for i in range(m - 1):
        if abs(d[i]) >= abs(dl[i]):
            f = dl[i] / d[i]
            d[i + 1] -= f * du[i]
            for col in range(n):
                b[i + 1, col] -= f * b[i, col]
        else:
            f = d[i] / dl[i]
            d[i] = dl[i]
            t = d[i + 1]
            d[i + 1] = du[i] - f * t
            if i < m - 2:
                du2[i] = du[i + 1]
                du[i + 1] = -f * du2[i]
            du[i] = t
            for col in range(n):
                t = b[i, col]
                b[i, col] = b[i + 1, col]
                b[i + 1, col] = t - f * b[i + 1, col]
    for col in range(n):
        b[m - 1, col] /= d[m - 1]
        b[m - 2, col] = (b[m - 2, col] - du[m - 2] * b[m - 1, col]) / d[m - 2]
    for i in range(m - 3, -1, -1):
        for col in range(n):
            b[i, col] = (b[i, col] - du[i] * b[i + 1, col] - du2[i] * b[i + 2, col]) / d[i]
    return b


@njit(cache=True, nogil=True, inline="always")
def hermite_coefficients(x, y, slopes, k, c0, c1):
    """
    Fill c0, c1 (n,) with the cubic's leading coefficients on the knot interval [x[k], x[k+1]].

    The cubic through y[k], y[k+1] (x (M,), y (M, n)) with the slopes there is
    ``((c0 z + c1) z + slopes[k]) z + y[k]`` in z = s - x[k]: SciPy's ``CubicHermiteSpline``
    coefficients in its local power basis (the trajectory's path model and the smoothed path's
    spline).
    """
    h = x[k + 1] - x[k]
    for col in range(y.shape[1]):
        sl = (y[k + 1, col] - y[k, col]) / h
        t = (slopes[k, col] + slopes[k + 1, col] - 2.0 * sl) / h
        c0[col] = t / h
        c1[col] = (sl - slopes[k, col]) / h - t


#: a cubic of the bounded spline may pass a bound by this much (its extremum's rounding: a monotone
#: piece that ends on the bound has its root a few ulp short of the end, one ulp past the bound), rad
_SPLINE_SLACK_RAD = 1e-14


@njit(cache=True, nogil=True)
def _cubic_leaves(y0, y1, m0, m1, h, lo, hi):
    """
    Tell where the cubic through y0, y1 with slopes m0, m1 over an interval of length h leaves [lo, hi] in it.

    Returns -1 (below lo), 1 (above hi) or 0 (within, or past by at most ``_SPLINE_SLACK_RAD``).
    """
    sl = (y1 - y0) / h
    t = (m0 + m1 - 2.0 * sl) / h
    c0 = t / h
    c1 = (sl - m0) / h - t
    a, b = 3.0 * c0, 2.0 * c1          # the slope's roots: a z² + b z + m0 = 0
    roots = np.empty(2)
    k = 0
    if a == 0.0:
        if b != 0.0:
            roots[0] = -m0 / b
            k = 1
    else:
        disc = b * b - 4.0 * a * m0
        if disc >= 0.0:
            q = -0.5 * (b + math.copysign(math.sqrt(disc), b))
            if q != 0.0:
                roots[0] = q / a
                roots[1] = m0 / q
                k = 2
            else:
                roots[0] = 0.0
                k = 1
    for i in range(k):
        z = roots[i]
        if 0.0 < z < h:
            y = ((c0 * z + c1) * z + m0) * z + y0
            if y < lo - _SPLINE_SLACK_RAD:
                return -1
            if y > hi + _SPLINE_SLACK_RAD:
                return 1
    return 0


@njit(cache=True, nogil=True)
def _pieces_solved(x, y, slopes, start_slope, clamped, anchor, col):
    """
    Solve column ``col``'s slopes again piece by piece between its anchors (slope 0 there).

    A piece's other ends keep the spline's own conditions: the start not-a-knot or clamped to
    ``start_slope`` (``clamped``), the end not-a-knot.
    """
    m = y.shape[0]
    zero, given = np.zeros(1), np.empty(1)
    given[0] = start_slope[col]
    a = 0
    while a < m - 1:
        b = a + 1
        while b < m - 1 and not anchor[b, col]:
            b += 1
        cs = anchor[a, col] or (a == 0 and clamped)
        piece = np.ascontiguousarray(y[a:b + 1, col:col + 1])
        got = _spline_slopes(x[a:b + 1], piece, zero if anchor[a, col] else given, cs, zero, anchor[b, col])
        for i in range(b - a + 1):
            slopes[a + i, col] = got[i, 0]
        a = b


@njit(cache=True, nogil=True)
def _bounded_slopes(x, y, slopes, start_slope, clamped, lo, hi):
    """
    Keep the cubic spline through (x (M,), y (M, n)) within the bounds lo, hi (n,): its knot slopes (M, n) in place.

    Where a column's spline leaves a bound between two knots (a path that touches a joint's bound
    at a sample and turns back: the not-a-knot spline rings there and passes the bound), the knots
    on that bound next to it (the whole run of them, where the path runs along the bound) become
    anchors, with slope 0, and the spline is solved again piece by piece between them
    (:func:`_pieces_solved`: C2 inside each piece, C1 at an anchor, where the slope is 0); an
    interval that still leaves a bound with no such knot has its end nearer the bound anchored.
    The first and last knots are never anchored: the path starts and ends at rest there, and a
    joint held at rest on the path as well would start as t⁴, which the controller's quintics do
    not follow without passing the bound (a helper's audit: 2.9e-9 rad); with every other knot
    anchored, each interval lies between its ends (the end pieces are parabolas, monotone), but
    for a first piece whose start is clamped to the arm's slope: an interval nothing more can mend
    is left as it is and the scan goes on past it.  Returns the anchors (M, n) bool; a column that
    stays within is left as it is, bit for bit.
    """
    m, n = y.shape
    anchor = np.zeros((m, n), np.bool_)
    for col in range(n):
        lo_c, hi_c = lo[col], hi[col]
        if not (lo_c > -np.inf or hi_c < np.inf):
            continue
        given_up = np.zeros(m - 1, np.bool_)
        while True:
            bad, side = -1, 0
            for k in range(m - 1):
                if given_up[k]:
                    continue
                y0, y1, m0, m1, h = y[k, col], y[k + 1, col], slopes[k, col], slopes[k + 1, col], x[k + 1] - x[k]
                # the cubic lies within h max(|m0 - sl|, |m1 - sl|) / 4 of its chord (sl the chord's slope)
                sl = (y1 - y0) / h
                off = 0.25 * h * max(abs(m0 - sl), abs(m1 - sl))
                if min(y0, y1) - off >= lo_c and max(y0, y1) + off <= hi_c:
                    continue
                side = _cubic_leaves(y0, y1, m0, m1, h, lo_c, hi_c)
                if side != 0:
                    bad = k
                    break
            if bad < 0:
                break
            bound = lo_c if side < 0 else hi_c
            grew = False
            for e in (bad, bad + 1):
                if y[e, col] != bound:
                    continue
                i, j = e, e                 # the run of knots on that bound through e
                while i > 0 and y[i - 1, col] == bound:
                    i -= 1
                while j < m - 1 and y[j + 1, col] == bound:
                    j += 1
                for k in range(max(i, 1), min(j, m - 2) + 1):
                    if not anchor[k, col]:
                        anchor[k, col] = True
                        grew = True
            if not grew:
                pick, near = -1, np.inf
                for k in (bad, bad + 1):
                    d = min(y[k, col] - lo_c, hi_c - y[k, col])
                    if 0 < k < m - 1 and not anchor[k, col] and d < near:
                        pick, near = k, d
                if pick < 0:
                    given_up[bad] = True
                    continue
                anchor[pick, col] = True
            _pieces_solved(x, y, slopes, start_slope, clamped, anchor, col)
    return anchor


@njit(**NO_REFCOUNT)
def _hermite_on_grid(x, y, slopes, s, refine, q, d1, d2, d3, c0, c1):
    """
    Evaluate the cubic through the knots with these slopes on the refined grid s (G,), G = (M-1)·refine + 1.

    Fills q, its first and second derivatives (G, n), its third derivative per grid segment
    (G-1, n); SciPy's ``CubicHermiteSpline`` coefficients, evaluated in its local power
    basis (scratch c0, c1 (n,)).
    """
    m, n = y.shape
    g = s.shape[0]
    for k in range(m - 1):
        hermite_coefficients(x, y, slopes, k, c0, c1)
        for r in range(refine + (1 if k == m - 2 else 0)):
            j = k * refine + r
            z = s[j] - x[k]
            for col in range(n):
                c2 = slopes[k, col]
                q[j, col] = ((c0[col] * z + c1[col]) * z + c2) * z + y[k, col]
                d1[j, col] = (3.0 * c0[col] * z + 2.0 * c1[col]) * z + c2
                d2[j, col] = 6.0 * c0[col] * z + 2.0 * c1[col]
                if j < g - 1:
                    d3[j, col] = 6.0 * c0[col]


@njit(cache=True, nogil=True)
def _chords(p):
    """Return the joint-space chord length of each step of p (M, n): (M-1,), rad (summed in joint order)."""
    m, n = p.shape
    ds = np.empty(m - 1)
    for k in range(m - 1):
        acc = 0.0
        for a in range(n):
            d = p[k + 1, a] - p[k, a]
            acc += d * d
        ds[k] = np.sqrt(acc)
    return ds


@njit(cache=True, nogil=True)
def _running_sum(ds):
    """Return 0 and the running sums of ds (K,): (K + 1,), in order (NumPy's ``concatenate([[0], cumsum(ds)])``)."""
    m = ds.shape[0] + 1
    out = np.empty(m)
    out[0] = 0.0
    for k in range(m - 1):
        out[k + 1] = out[k] + ds[k]
    return out


@njit(cache=True, nogil=True)
def _grid(ds, refine):
    """Return the knots' chord lengths (M,) and the grid's s (G,), G = (M-1)·refine + 1, knots exact."""
    m = ds.shape[0] + 1
    s_knots = _running_sum(ds)
    s = np.empty((m - 1) * refine + 1)
    for k in range(m - 1):
        s[k * refine] = s_knots[k]
        for r in range(1, refine):
            s[k * refine + r] = s_knots[k] + ds[k] * (r / refine)
    s[-1] = s_knots[-1]
    return s_knots, s


def _spline_on_grid(p, ds, refine, start_slope=None, bounds=None):
    """
    Return the spline through p (M ≥ 3) on the grid: (s, q, d1, d2, d3, other) as :func:`_path_model`.

    Not-a-knot; with ``start_slope`` (n,) its first derivative at the start is that (clamped).
    With ``bounds`` (lo (n,), hi (n,)) the spline is kept within them (:func:`_bounded_slopes`);
    at an anchor, where q' = 0 and q'' jumps, d2 holds the larger of its two sides, so that a
    joint's acceleration there (q'' ṡ²) is bounded for both, and ``other`` (G, n) the smaller
    (``other`` is d2 elsewhere; None where nothing is anchored): the wheel's torque, which mixes
    the joints, is bounded for both sides by :func:`_rows`.
    """
    s_knots, s = _grid(ds, refine)
    g, n = s.shape[0], p.shape[1]
    q, d1, d2, d3 = np.empty((g, n)), np.empty((g, n)), np.empty((g, n)), np.empty((g - 1, n))
    slopes = (not_a_knot_slopes(s_knots, p) if start_slope is None
              else clamped_start_slopes(s_knots, p, start_slope))
    anchor = None
    if bounds is not None:
        anchor = _bounded_slopes(s_knots, p, slopes, p[0] if start_slope is None else start_slope,
                                 start_slope is not None, bounds[0], bounds[1])
    _hermite_on_grid(s_knots, p, slopes, s, refine, q, d1, d2, d3, np.empty(n), np.empty(n))
    other = None
    if anchor is not None and anchor[1:-1].any():
        other = d2.copy()
        ks, cols = np.nonzero(anchor[1:-1])
        ks = ks + 1
        # each side's q'' at the knot from its own cubic (SciPy's CubicHermiteSpline coefficients):
        # the left interval's at its end (z = h), the right one's at its start (z = 0)
        sides = []
        for a, z_at_end in ((ks - 1, True), (ks, False)):
            h = s_knots[a + 1] - s_knots[a]
            sl = (p[a + 1, cols] - p[a, cols]) / h
            m0, m1 = slopes[a, cols], slopes[a + 1, cols]
            t = (m0 + m1 - 2.0 * sl) / h
            c0, c1 = t / h, (sl - m0) / h - t
            sides.append(6.0 * c0 * h + 2.0 * c1 if z_at_end else 2.0 * c1)
        left, right = sides
        big = np.abs(left) > np.abs(right)
        d2[ks * refine, cols] = np.where(big, left, right)
        other[ks * refine, cols] = np.where(big, right, left)
    q[::refine] = p                     # the samples exactly
    return s, q, d1, d2, d3, other


#: joints from which NumPy's row norms and sums (pairwise summation) are not plain left-to-right
#: sums: the kernels keep to NumPy's arithmetic below it (the same trajectories bit for bit)
_SEQUENTIAL_SUM_MAX = 7


def chord_lengths_rad(p) -> np.ndarray:
    """
    Return the Euclidean length of each step of a path p (M ≥ 1, n): (M-1,), rad.

    NumPy's ``np.linalg.norm(np.diff(p, axis=0), axis=1)`` bit for bit, by :func:`_chords` up to
    ``_SEQUENTIAL_SUM_MAX`` joints (NumPy's row sums are plain left-to-right sums there).
    """
    p = np.ascontiguousarray(p, dtype=float)
    if p.shape[1] <= _SEQUENTIAL_SUM_MAX and len(p) >= 1:
        return _chords(p if p.flags.writeable else p.copy())      # one kernel signature
    return np.linalg.norm(np.diff(p, axis=0), axis=1)


def arc_lengths_rad(p) -> np.ndarray:
    """
    Return the path's length up to each row of p (M ≥ 1, n): (M,), rad, 0 first.

    NumPy's ``concatenate([[0.0], cumsum(chord_lengths)])`` bit for bit (:func:`chord_lengths_rad`).
    """
    return _running_sum(chord_lengths_rad(p))


def _path_model(p, refine: int, start_slope=None, bounds=None, sides: bool = False):
    """
    Fit the cubic spline through the samples p (M, n) on a grid refined ``refine`` times.

    Returns (s, idx, q, d1, d2, d3): grid chord lengths s (G,), the grid indices of the
    samples idx (M,), the spline's q, q', q'' at the grid points (G, n) (q[idx] == p
    exactly) and its q''' per grid segment (G-1, n) (constant on each spline piece).
    SciPy's not-a-knot ``CubicSpline``, by the kernels above from 3 samples on; with
    ``start_slope`` (n,) float64, its derivative at the start clamped to it (from 3 samples on);
    with ``bounds`` (lo, hi), each (n,) float64 (±inf: unbounded), kept within them
    (:func:`_spline_on_grid`; a straight segment between samples within them is).  ``sides``:
    also return q'' on the other side of each anchor (:func:`_spline_on_grid`'s ``other``, None
    where none) last.
    """
    idx = np.arange(len(p)) * refine
    ds = chord_lengths_rad(p)
    if len(p) >= 3:
        s, q, d1, d2, d3, other = _spline_on_grid(p, ds, refine, start_slope, bounds)
        return (s, idx, q, d1, d2, d3, other) if sides else (s, idx, q, d1, d2, d3)
    s_knots, s = _grid(ds, refine)          # a straight segment
    chord = (p[1] - p[0]) / ds[0]
    q = p[0] + s[:, None] * chord
    d1 = np.repeat(chord[None, :], len(s), axis=0)
    d2 = np.zeros_like(q)
    d3 = np.zeros((len(s) - 1, p.shape[1]))
    q[idx] = p
    return (s, idx, q, d1, d2, d3, None) if sides else (s, idx, q, d1, d2, d3)


#: the models :func:`shared_path_models` keeps: None outside it
_SHARED_MODELS: ContextVar[dict | None] = ContextVar("shared_path_models", default=None)


@contextmanager
def shared_path_models():
    """
    Within it, :func:`time_parameterize` models each path once: the re-timings of one path share its model.

    The densified path and its spline on the grid (a tenth to a third of a parameterisation)
    do not depend on the limits: a chain that times the same path again under lowered
    scaling factors (``adapters.post_process``) makes them once.  Keyed by the path's
    values, the densification step and the grid refinement, so a different path gets its
    own; the models are dropped on leaving (nothing outlives the chain).  The trajectories
    are the same, bit for bit.  So are ``published.segment_wheel_peaks``' peaks of a segment the
    chain met before (``published._PeakMemo``).
    """
    token = _SHARED_MODELS.set({})
    try:
        yield
    finally:
        _SHARED_MODELS.reset(token)


def _modelled_path(path_rad, max_step_rad: float, refine: int, start_slope=None, bounds=None):
    """
    Return (the densified path p (M, n), its model (q, d1, d2, d3, ds, other) or None when M = 1).

    :func:`densify_path` and :func:`_path_model` (C-contiguous, ``ds`` the grid steps (G-1,);
    ``start_slope``: the start's clamped derivative or None; ``bounds``: the joints' (lo, hi) or
    None); within :func:`shared_path_models`, made once per path, start and bounds (the arrays
    are only read).
    """
    path = np.ascontiguousarray(path_rad, dtype=float)
    shared = _SHARED_MODELS.get()
    key = None
    if shared is not None:
        key = (path.shape, path.tobytes(), float(max_step_rad), int(refine),
               None if start_slope is None else start_slope.tobytes(),
               None if bounds is None else (bounds[0].tobytes(), bounds[1].tobytes()))
        got = shared.get(key)
        if got is not None:
            return got[0].copy(), got[1]         # the positions go into a Trajectory: its own
    p = densify_path(path, max_step_rad)
    model = None
    if len(p) > 1:
        s, _, qg, d1, d2, d3, other = _path_model(p, refine, start_slope, bounds, sides=True)
        model = (qg, np.ascontiguousarray(d1), np.ascontiguousarray(d2), np.ascontiguousarray(d3), np.diff(s), other)
    if key is not None:
        shared[key] = (p.copy(), model)          # not the positions returned (nor the caller's path)
    return p, model


@njit(cache=True, nogil=True)
def _constraint(i, end, r, var, a_row, b_row, c_row, kappa, inv):
    """
    One constraint of grid segment i on (x_i, x_{i+1}), written ``|β x_{i+1} + σ x_i| ≤ c``.

    Rows r of the constraints ``|a[p, r] u + b[p, r] x_p| + kappa[i, r] |u| ≤ c[p, r]`` at
    the segment's end p = i + ``end`` (0, 1), with u = (x_{i+1} - x_i) / (2Δ_i) (``inv`` =
    0.5 / Δ_i); ``|f| + κ|u| ≤ c`` is ``|f + κu| ≤ c`` (``var`` 0) and ``|f − κu| ≤ c``
    (``var`` 1, only where κ > 0).  Returns (β, σ, c with the sign of β (c where β = 0),
    active: False where c is not finite or the constraint is var 1 of a κ = 0 row).
    """
    p = i + end
    c = c_row[p, r]
    kap = kappa[i, r]
    if not c < np.inf or (var == 1 and not kap > 0.0):
        return 1.0, 0.0, c, False
    a = a_row[p, r] + (kap if var == 0 else -kap)
    if end == 0:
        beta = a * inv
        sr = b_row[p, r] - a * inv
    else:
        beta = a * inv + b_row[p, r]
        sr = -a * inv
    return beta, sr, (-c if beta < 0.0 else c), True


@njit(cache=True, nogil=True, inline="always")
def _bounds(i, x, a_row, b_row, c_row, kappa, xv, delta, k_next):
    """
    Return the bounds on x_{i+1} from x_i = x on segment i, and their slopes in x.

    The constraints :func:`_constraint` and 0 ≤ x_{i+1} ≤ xv[i+1], x_{i+1} ≤ k_next.  Each
    bound on x_{i+1} is affine in x; a constraint without an x_{i+1} term (β = 0) bounds x
    alone.  Returns (lo, its slope, hi, its slope, g, its slope): the largest lower bound,
    the smallest upper bound, and the largest violation ``|σ| x - c`` of the constraints on
    x alone (-inf: none).
    """
    inv = 0.5 / delta[i]
    lo, hi = 0.0, min(xv[i + 1], k_next)
    g, s_g = -np.inf, 0.0
    lo_beta = lo_sr = hi_beta = hi_sr = 0.0     # the constraints that set lo and hi (β = 0: none)
    for end in range(2):
        for r in range(a_row.shape[1]):
            for var in range(2):
                beta, sr, cc, active = _constraint(i, end, r, var, a_row, b_row, c_row, kappa, inv)
                if not active:
                    continue
                rest = sr * x
                if beta != 0.0:
                    up = (cc - rest) / beta
                    dn = (-cc - rest) / beta
                    if up < hi:
                        hi, hi_beta, hi_sr = up, beta, sr
                    if dn > lo:
                        lo, lo_beta, lo_sr = dn, beta, sr
                else:
                    v = abs(rest) - cc
                    if v > g:
                        g, s_g = v, abs(sr)
    s_lo = -lo_sr / lo_beta if lo_beta != 0.0 else 0.0
    s_hi = -hi_sr / hi_beta if hi_beta != 0.0 else 0.0
    return lo, s_lo, hi, s_hi, g, s_g


@njit(cache=True, nogil=True, inline="always")
def _admits(i, x, a_row, b_row, c_row, kappa, xv, delta, k_next):
    """
    Tell whether x_i = x admits some x_{i+1} on segment i (the passes' test).

    0 ≤ x ≤ xv[i], and :func:`_bounds`' lo ≤ hi and g ≤ 0.
    """
    if x > xv[i] or x < 0.0:
        return False
    lo, _, hi, _, g, _ = _bounds(i, x, a_row, b_row, c_row, kappa, xv, delta, k_next)
    return lo <= hi and not g > 0.0


@njit(cache=True, nogil=True)
def _violation(i, x, a_row, b_row, c_row, kappa, xv, delta, k_next):
    """
    How far x_i = x (≥ 0) is from admitting an x_{i+1} (≤ 0: it does), and its slope in x.

    ``lo(x) - hi(x)`` and the constraints on x alone (:func:`_bounds`) make up a convex
    piecewise linear function of x; returns its value and the slope of the piece that
    attains it.
    """
    lo, s_lo, hi, s_hi, g, s_g = _bounds(i, x, a_row, b_row, c_row, kappa, xv, delta, k_next)
    f = lo - hi
    if g > f:
        return g, s_g
    return f, s_lo - s_hi


@njit(cache=True, nogil=True)
def _largest_feasible(i, a_row, b_row, c_row, kappa, xv, delta, k_next):
    """
    Return the largest x_i ≤ xv[i] from which some x_{i+1} ∈ [0, k_next] is admissible (0: none).

    Newton's method from above on the convex piecewise linear :func:`_violation` (each step
    lands on or above the root, exactly on it once on the last piece: a few steps; a
    non-positive violation is :func:`_admits`), else lowered by ulps until :func:`_admits`
    (the passes' own test) holds.
    """
    x = xv[i]
    for _ in range(64):
        f, slope = _violation(i, x, a_row, b_row, c_row, kappa, xv, delta, k_next)
        if f <= 0.0:                # 0 ≤ x ≤ xv[i], lo ≤ hi and g ≤ 0: admitted
            return x
        if not slope > 0.0:
            return 0.0
        x_new = x - f / slope
        if x_new < 0.0:
            return 0.0
        if x_new >= x:
            break
        x = x_new
    for _ in range(64):
        if _admits(i, x, a_row, b_row, c_row, kappa, xv, delta, k_next):
            return x
        x = x - max(4.0 * 2.220446049250313e-16 * x, 1e-300)
        if x <= 0.0:
            return 0.0
    a, b = 0.0, x                   # not reached in practice: bisection below the estimate
    for _ in range(200):
        mid = 0.5 * (a + b)
        if mid <= a or mid >= b:
            break
        if _admits(i, mid, a_row, b_row, c_row, kappa, xv, delta, k_next):
            a = mid
        else:
            b = mid
    return a


def _backward(a_row, b_row, c_row, kappa, xv, delta, x_end):
    """Return the controllable sets' k (G,): K_i = [0, k_i], the x_i from which x_N = x_end is reachable."""
    k = np.empty(xv.shape[0])
    _backward_from(k, a_row, b_row, c_row, kappa, xv, delta, float(x_end), xv.shape[0] - 1)
    return k


@njit(**NO_REFCOUNT)
def _backward_from(k, a_row, b_row, c_row, kappa, xv, delta, x_end, top):
    """
    Run the backward pass (:func:`_backward`) into k (G,), from grid point ``top`` down.

    ``top`` ≥ G - 1: the whole pass.  Else the rows changed at ``top`` and below only: k holds the
    pass on rows that equal these above ``top``, and its k_{top+1..} stand (k_i depends on rows i
    and i + 1 and on k_{i+1} alone); k_top .. k_0 are computed again, each as the whole pass
    computes it (the same test first where k_{i+1} was not limited): the same values to the bit in
    top + 1 steps instead of G (a joined timing raising the lowering where the arm's speed must be
    entered, :func:`time_parameterize`).
    """
    m = xv.shape[0]
    if top >= m - 1:
        k[m - 1] = min(x_end, xv[m - 1])
        top = m - 2
        limited = False
    else:
        limited = top < m - 2 and k[top + 1] < xv[top + 1]
    for i in range(top, -1, -1):
        # after a limited k_{i+1} (runs of them: where the acceleration limits bind), Newton's
        # first step is the test itself (f(xv[i]) ≤ 0 is admission): the same k_i either way
        if not limited and _admits(i, xv[i], a_row, b_row, c_row, kappa, xv, delta, k[i + 1]):
            k[i] = xv[i]
        else:                       # the feasible x_i form an interval [0, k_i]
            k[i] = _largest_feasible(i, a_row, b_row, c_row, kappa, xv, delta, k[i + 1])
        limited = k[i] < xv[i]


@njit(**NO_REFCOUNT)
def _forward(x, a_row, b_row, c_row, kappa, xv, delta, k, x0):
    """
    Greedy forward pass: the largest admissible x_{i+1} ∈ K_{i+1} at every step, into x (G,).

    :func:`_bounds`' upper bound and g, by a loop of its own: the values only, half the
    divisions (the lower bounds are not needed).  An x_i outside [0, xv[i]] or violating a
    constraint on x alone (not reached: x_i ∈ K_i) is followed by 0.
    """
    x[0] = x0
    _forward_from(x, a_row, b_row, c_row, kappa, xv, delta, k, 0)


@njit(**NO_REFCOUNT)
def _forward_braking(x, a_row, b_row, c_row, kappa, xv, delta, k, x0, no_cap):
    """
    Run the forward pass from x0 above the velocity bound xv[0], braked at the acceleration limits into K, into x (G,).

    While x_i lies above K_i, x_{i+1} is the least value the acceleration rows admit from it (the
    hardest braking: :func:`_bounds` without the velocity bounds, ``no_cap`` (G,) all inf), and its
    ratio to the velocity bound may not rise above the larger of 1 and x_i's (x / xv is the largest
    joint's speed over its limit, squared: no joint comes closer to or further above its limit than
    the fastest one was); where K_{i+1} can be reached, the largest value in it, and from there
    :func:`_forward`'s steps.  Returns the grid index where x enters K, or -1: the acceleration rows
    admit no x_{i+1} (the arm too fast for the path's bend), the hardest braking would raise that
    ratio (a bound further on, a bend that turns the motion onto a slower joint), or it does not
    reach K before the end.
    """
    m = xv.shape[0]
    x[0] = x0
    for i in range(m - 1):
        if x[i] <= k[i]:
            _forward_from(x, a_row, b_row, c_row, kappa, xv, delta, k, i)
            return i
        lo, _, hi, _, g, _ = _bounds(i, x[i], a_row, b_row, c_row, kappa, no_cap, delta, np.inf)
        if g > 0.0 or lo > hi:
            return -1
        cap = min(xv[i + 1], k[i + 1])
        if lo <= cap:
            x[i + 1] = min(hi, cap)
        elif lo > max(xv[i + 1], x[i] * (xv[i + 1] / xv[i])):
            return -1
        else:
            x[i + 1] = lo
    if x[m - 1] <= k[m - 1]:
        return m - 1
    return -1


@njit(**NO_REFCOUNT)
def _forward_from(x, a_row, b_row, c_row, kappa, xv, delta, k, first):
    """:func:`_forward`'s steps from grid point ``first`` on (x[first] given), into x."""
    m = xv.shape[0]
    for i in range(first, m - 1):
        xi = x[i]
        if xi > xv[i] or xi < 0.0:
            x[i + 1] = 0.0
            continue
        inv = 0.5 / delta[i]
        hi = min(xv[i + 1], k[i + 1])
        g = -np.inf
        for end in range(2):
            for r in range(a_row.shape[1]):
                for var in range(2):
                    beta, sr, cc, active = _constraint(i, end, r, var, a_row, b_row, c_row, kappa, inv)
                    if not active:
                        continue
                    rest = sr * xi
                    if beta != 0.0:
                        up = (cc - rest) / beta
                        if up < hi:
                            hi = up
                    else:
                        g = max(g, abs(rest) - cc)
        x[i + 1] = 0.0 if g > 0.0 else max(hi, 0.0)     # lo ≤ hi up to rounding: x_i ∈ K_i


#: the largest angle between a clamped start tangent and the path's first step, rad
MAX_START_TANGENT_TURN_RAD = float(np.radians(30.0))


def check_start_tangent(tangent, path_rad) -> None:
    """Refuse a start tangent (n,) that the path (M, n) cannot leave its start along (ValueError)."""
    p = np.asarray(path_rad, dtype=float)
    n = p.shape[1] if p.ndim == 2 else -1
    if tangent.shape != (n,) or not math.isfinite(float(tangent @ tangent)):
        raise ValueError(f"start_tangent: expected {n} finite values (one per path column), got {tangent.tolist()}")
    norm = math.sqrt(float(tangent @ tangent))
    if not 0.5 <= norm <= 2.0:
        raise ValueError(f"start_tangent: its length is {norm:.4g}; the derivative with respect to the chord "
                         f"length is about 1 (0.5 to 2)")
    k = 1                               # the path's first step (densified: the same direction)
    while k < len(p) and np.array_equal(p[k], p[0]):
        k += 1
    if k < len(p):
        step = p[k] - p[0]
        turn = math.acos(min(1.0, max(-1.0, float(tangent @ step) / (norm * math.sqrt(float(step @ step))))))
        if turn > MAX_START_TANGENT_TURN_RAD:
            raise ValueError(f"start_tangent: {np.degrees(turn):.1f}° off the path's first step (at most "
                             f"{np.degrees(MAX_START_TANGENT_TURN_RAD):g}°)")


def start_path_speed_from_velocity(path_rad, start_velocity_rad_s, tolerance: float = 1e-3, bounds=None) -> float:
    """
    Return the path speed ṡ that reproduces a start joint velocity along the path.

    ṡ in rad/s of chord length: the velocity's projection on the path's initial tangent.

    Args:
        path_rad: (M, n) the path (its first rows give the tangent).
        start_velocity_rad_s: (n,) joint velocity at the start.
        tolerance: largest allowed part of the velocity across the tangent, relative to
            its norm (plus 1e-9 rad/s).
        bounds: the joints' (lo, hi) (n,) each, or None: the tangent of the spline kept within
            them (:func:`time_parameterize`'s ``lower_rad``, ``upper_rad``).

    Raises
    ------
        ValueError (``start_velocity_rad_s``) when the velocity is not along the path's
        start tangent (within ``tolerance``) or points backwards along it.

    """
    p = densify_path(path_rad)
    v0 = np.asarray(start_velocity_rad_s, dtype=float).reshape(-1)
    if v0.shape != (p.shape[1],) or not np.all(np.isfinite(v0)):
        raise ValueError(f"start_velocity_rad_s: expected {p.shape[1]} finite values, got {v0.tolist()}")
    speed = float(np.linalg.norm(v0))
    if speed == 0.0:
        return 0.0
    if len(p) < 2:
        raise ValueError("start_velocity_rad_s: the path has no length, the arm cannot keep moving")
    _, _, _, d1, _, _ = _path_model(p, 1, None, bounds)
    t0 = d1[0] / np.linalg.norm(d1[0])
    sd = float(v0 @ t0)
    across = float(np.linalg.norm(v0 - sd * t0))
    if across > tolerance * speed + 1e-9 or sd < 0.0:
        ang = np.degrees(np.arctan2(across, sd))
        raise ValueError(f"start_velocity_rad_s: {np.round(v0, 6).tolist()} rad/s is {ang:.2f}° off the "
                         f"path's start tangent {np.round(t0, 4).tolist()} (allowed "
                         f"{np.degrees(np.arctan(tolerance)):.3f}°): the arm cannot follow this path "
                         f"without a velocity jump")
    return sd / float(np.linalg.norm(d1[0]))


#: the longest trajectory, s: builtin_interfaces/Duration (a point's ``time_from_start``) holds
#: whole seconds in an int32.  Longer is refused (a limit set near 0 by mistake), never published
#: with times that wrap around.
MAX_DURATION_S = float(2**31 - 1)
#: rounding effects on the finite differences up to this fraction of a limit are not
#: given a margin (the test tolerance and every consumer are far coarser)
_ROUNDING_SLACK = 1e-10
#: rounds of margins and passes at most (one or two suffice: the margins only grow)
_ROUNDING_ROUNDS = 8
_EPS = float(np.finfo(float).eps)


@njit(**NO_REFCOUNT)
def _timed_forward(x, dt, t, per, a_row, b_row, c_row, kappa, xv, ds, k, x0, refine, no_cap):
    """
    Run the forward pass from x0 (clipped to K_0) to rest, and time it; returns 0 (ok), 1 or 2.

    ``no_cap`` (G,) all inf: x0 above the velocity bound is braked into K (:func:`_forward_braking`,
    not clipped); empty: clipped.  Fills x (G,), the grid durations dt (G-1,) s, the sample times
    t (M,) s and the sample intervals per (M-1,) s: ``dt = 2 Δ / (ṡ_i + ṡ_{i+1})``; each sample
    interval the sum of its ``refine`` grid durations in order, the times their running sum from 0
    (NumPy's row sums and ``cumsum`` for ``refine`` ≤ 7).  Returns 1 where a stretch has ṡ = 0 at
    both ends, 2 where the braking cannot reach K.
    """
    if no_cap.shape[0] > 0 and x0 > k[0]:
        if _forward_braking(x, a_row, b_row, c_row, kappa, xv, ds, k, x0, no_cap) < 0:
            return 2
    else:
        _forward(x, a_row, b_row, c_row, kappa, xv, ds, k, min(x0, k[0]))
    g = x.shape[0]
    x[g - 1] = 0.0
    ok = 0
    prev = np.sqrt(x[0])
    for j in range(g - 1):
        nxt = np.sqrt(x[j + 1])
        den = prev + nxt
        if den <= 0.0:
            ok = 1
        dt[j] = 2.0 * ds[j] / den if den > 0.0 else np.inf
        prev = nxt
    m = (g - 1) // refine + 1
    t[0] = 0.0
    for k_s in range(m - 1):
        acc = dt[k_s * refine]
        for r in range(1, refine):
            acc += dt[k_s * refine + r]
        per[k_s] = acc
        t[k_s + 1] = t[k_s] + acc
    return ok


def _solve(a_row, b_row, c_row, kappa, xv, ds, k, x0, refine, brake: bool = False):
    """
    Forward pass from x0 (clipped to K_0; ``brake``: above K_0, braked into it) to rest (:func:`_timed_forward`).

    Returns (x (G,), grid durations dt (G-1,) s, sample times (M,) s, 0 first, sample
    intervals (M-1,) s).  Raises ValueError where ṡ = 0 at both ends of a grid segment, or
    where the braking cannot bring the speed within the limits (:func:`_forward_braking`).
    """
    g = xv.shape[0]
    m = (g - 1) // refine + 1
    x, dt, t, per = np.empty(g), np.empty(g - 1), np.empty(m), np.empty(m - 1)
    no_cap = np.full(g, np.inf) if brake else np.empty(0)
    code = _timed_forward(x, dt, t, per, a_row, b_row, c_row, kappa, xv, ds, k, float(x0), int(refine), no_cap)
    if code == 2:
        raise ValueError(f"start_path_speed: {np.sqrt(x0):.6g} rad/s along the path is above the velocity "
                         f"limits, and braking at the acceleration limits does not bring the arm within them "
                         f"on this path (its bend at that speed, a bound further on or a slower joint the motion turns "
                         f"onto, or the goal too near)")
    if code:
        raise ValueError("path: a stretch cannot be followed at any speed within the limits")
    if refine > _SEQUENTIAL_SUM_MAX:        # NumPy's pairwise row sums
        per = dt.reshape(-1, refine).sum(axis=1)
        t = np.concatenate([[0.0], np.cumsum(per)])
    return x, dt, t, per


@njit(cache=True, nogil=True)
def _rounding_margins(t, dt, p, d1, x, amax, refine, m_acc, m_vel):
    """
    Bound the effect of float rounding on the published samples' finite differences.

    How far rounding can move them away from the exact motion's (which obey the limits).

    Args:
        t: (M,) published sample times, s; dt: (M-1,) sample intervals, s; p: (M, n)
        positions, rad; d1: (G, n) the path's tangent q' and x: (G,) ṡ² on the grid (the
        start velocity is |q'(0)| ṡ(0)); amax: (n,) rad/s²; refine: grid segments per
        sample interval; m_acc (G, n), m_vel (G,): the margins taken so far.

    Returns
    -------
        (acc (G, n) rad/s²: per grid point, the most rounding can add to a finite-difference
        acceleration whose interval covers it; vel (G,): the most it can add to a segment
        velocity, as a fraction of it; both 0 where at most ``_ROUNDING_SLACK`` of the limit,
        and carrying a factor 2 for second-order terms; grown: some exceeds its margin so far).

    """
    m, n = p.shape
    g = (m - 1) * refine + 1
    sd0 = np.sqrt(x[0])
    # |published Δt_k − exact Δt_k|: the sum of `refine` durations (relative eps each, plus
    # those of the durations themselves) and, after the first, the time's rounding
    err_t = np.empty(m - 1)
    rel = np.empty(m - 1)
    t_up = (t.view(np.int64) + 1).view(np.float64)      # the next double above each t ≥ 0
    for k in range(m - 1):
        err_t[k] = (refine + 6) * _EPS * dt[k]
        if k >= 1:
            err_t[k] += 0.5 * (t_up[k + 1] - t[k + 1])
        rel[k] = err_t[k] / dt[k] + 2.0 * _EPS          # of Δt_k, and of the quotient
    # per sample k: (w_after − w_before) / half, w the segment speeds (the start velocity
    # before the first, rest after the last): the velocities' errors, the difference's own
    # rounding, and the relative error of `half` times the (bounded) value
    fd = np.empty((m, n))
    for k in range(m):
        dt_b = dt[k - 1] if k > 0 else 0.0
        dt_a = dt[k] if k < m - 1 else 0.0
        half = 0.5 * (dt_b + dt_a)
        t_b = err_t[k - 1] if k > 0 else 0.0
        t_a = err_t[k] if k < m - 1 else 0.0
        tt = (t_b + t_a) / (2.0 * half)
        for a in range(n):
            if k > 0:
                w_b = abs(p[k, a] - p[k - 1, a]) / dt[k - 1]
                e_b = w_b * rel[k - 1]
            else:
                w_b = abs(d1[0, a]) * sd0
                e_b = 2.0 * _EPS * w_b
            if k < m - 1:
                w_a = abs(p[k + 1, a] - p[k, a]) / dt[k]
                e_a = w_a * rel[k]
            else:
                w_a = 0.0
                e_a = 0.0
            fd[k, a] = 2.0 * ((e_b + e_a + _EPS * (w_b + w_a)) / half + amax[a] * tt)
    # the finite difference at sample k averages the motion over intervals k-1 and k: grid
    # point j = k·refine + r of interval k (the last point: of the last interval)
    acc = np.empty((g, n))
    vel = np.empty(g)
    grown = False
    for k in range(m - 1):
        for r in range(refine + 1 if k == m - 2 else refine):
            j = k * refine + r
            shared = r == 0 and k > 0
            for a in range(n):
                v = max(fd[k, a], fd[k + 1, a])
                if shared:
                    v = max(max(fd[k - 1, a], fd[k, a]), v)
                if v <= _ROUNDING_SLACK * amax[a]:
                    v = 0.0
                acc[j, a] = v
                if not v <= m_acc[j, a]:
                    grown = True
            e = 2.0 * max(rel[k - 1], rel[k]) if shared else 2.0 * rel[k]
            if e <= _ROUNDING_SLACK:
                e = 0.0
            vel[j] = e
            if not e <= m_vel[j]:
                grown = True
    return acc, vel, grown


@njit(cache=True, nogil=True)
def _constraint_rows(d1, d3, ds, vmax, amax):
    """
    Return the velocity bound xv (G,) on x = ṡ², the acceleration rows' κ (G-1, n) and limits c (G, n).

    Velocity type: on a grid segment |q'_j| exceeds its larger end value by at most
    |q'''| Δ²/8 and ṡ stays below the larger end value, so bounding both ends with that
    margin bounds the velocity everywhere on the spline (xv ≤ 1e300).  Acceleration type:
    inside a segment q' u + q'' x is quadratic in s with leading coefficient 2.5 q''' u, so
    it exceeds the larger end value by at most κ |u| = 2.5 |q'''| |u| Δ²/4.
    """
    g, n = d1.shape
    xv = np.empty(g)
    kappa = np.empty((g - 1, n))
    c_row = np.empty((g, n))
    for i in range(g):
        lim = np.inf
        for a in range(n):
            c_row[i, a] = amax[a]
            tang = abs(d1[i, a])
            if i < g - 1:
                tang = max(tang, max(abs(d1[i, a]), abs(d1[i + 1, a])) + abs(d3[i, a]) * (ds[i] * ds[i] / 8.0))
                kappa[i, a] = 2.5 * abs(d3[i, a]) * (ds[i] * ds[i] / 4.0)
            if i > 0:
                tang = max(tang, max(abs(d1[i - 1, a]), abs(d1[i, a]))
                           + abs(d3[i - 1, a]) * (ds[i - 1] * ds[i - 1] / 8.0))
            if tang > 0.0:
                r = vmax[a] / tang
                lim = min(lim, r * r)
        xv[i] = min(lim, 1e300)
    return xv, kappa, c_row


@njit(cache=True, nogil=True)
def _sample_states(x, dt, ds, d1, d2, refine, vmax, amax, g_w, gp_w, h_max, tau_max):
    """
    Return the published samples' states and the constraint closest to its limit at each.

    Args:
        x: (G,) ṡ² on the grid; dt: (G-1,) grid durations, s; ds: (G-1,) grid steps, rad;
        d1, d2: (G, n) q', q''; refine: grid segments per sample; vmax, amax: (n,) the
        limits; g_w, gp_w: (G,) the wheel terms H·q' and d(H·q')/ds (empty: no wheel);
        h_max, tau_max: the wheel limits (inf: none).

    Returns
    -------
        (ṡ (M,), velocities (M, n) rad/s (0 at the end), accelerations (M, n) rad/s², the
        wheel momentum and torque (M,) (empty: no wheel), the index of the constraint closest
        to its limit (M,): velocity of joint j (j), acceleration of joint j (n + j), wheel
        momentum (2n), wheel torque (2n + 1), and its |value| / limit (M,)).  The
        acceleration is ``q' ū + q'' x`` with ``ū`` the Δt-weighted mean of the neighbouring
        grid segments' ``u``; the ratios take each segment's ``u``.

    """
    g, n = d1.shape
    m = (g - 1) // refine + 1
    wheel = g_w.shape[0] > 0
    sd = np.empty(m)
    vel = np.empty((m, n))
    acc = np.empty((m, n))
    h_w = np.empty(m if wheel else 0)
    tau_w = np.empty(m if wheel else 0)
    best = np.empty(m, np.int64)
    ratio = np.empty(m)
    for k in range(m):
        j = k * refine
        u_b = (x[j] - x[j - 1]) / (2.0 * ds[j - 1]) if j > 0 else (x[1] - x[0]) / (2.0 * ds[0])
        u_a = (x[j + 1] - x[j]) / (2.0 * ds[j]) if j < g - 1 else (x[g - 1] - x[g - 2]) / (2.0 * ds[g - 2])
        dt_b = dt[j - 1] if j > 0 else 0.0
        dt_a = dt[j] if j < g - 1 else 0.0
        u = (dt_b * u_b + dt_a * u_a) / (dt_b + dt_a)
        xs = x[j]
        s_d = np.sqrt(xs)
        sd[k] = s_d
        top, arg = -np.inf, -1
        for a in range(n):
            vel[k, a] = 0.0 if k == m - 1 else d1[j, a] * s_d + 0.0      # + 0.0: at rest 0, not -0.0
            acc[k, a] = d1[j, a] * u + d2[j, a] * xs
            r = abs(d1[j, a]) * s_d / vmax[a]
            if r > top:
                top, arg = r, a
        for a in range(n):
            r = max(abs(d1[j, a] * u_b + d2[j, a] * xs), abs(d1[j, a] * u_a + d2[j, a] * xs)) / amax[a]
            if r > top:
                top, arg = r, n + a
        if wheel:
            gs, gps = g_w[j], gp_w[j]
            h_w[k] = -gs * s_d + 0.0
            tau_w[k] = -(gps * xs + gs * u)
            r = abs(gs) * s_d / h_max
            if r > top:
                top, arg = r, 2 * n
            r = max(abs(gps * xs + gs * u_b), abs(gps * xs + gs * u_a)) / tau_max
            if r > top:
                top, arg = r, 2 * n + 1
        best[k] = arg
        ratio[k] = top
    return sd, vel, acc, h_w, tau_w, best, ratio


def _check_limits(name, lim, n):
    lim = np.asarray(lim, dtype=float).reshape(-1)
    if lim.shape != (n,):
        raise ValueError(f"{name}: expected {n} values (one per joint), got {lim.shape[0]}")
    if not all(0.0 < v < math.inf for v in lim.tolist()):      # a few joints: no array reductions
        raise ValueError(f"{name}: every limit must be a finite number > 0, got {list(lim)}")
    return lim


def _check_factor(name, f):
    f = float(f)
    if not (0.0 < f <= 1.0):
        raise ValueError(f"{name}: must be in (0, 1], got {f}")
    return f


def _limit_or_inf(v):
    return np.inf if v is None or not v > 0.0 else float(v)


#: :class:`Lowering`'s factors, in order (the limits they lower)
LOWERED_LIMITS = ("velocity", "acceleration", "wheel momentum", "wheel torque")


@dataclass(frozen=True, eq=False)
class Lowering:
    """
    Limits lowered along a stretch of a path: where the controller's motion overshot them.

    A segment is lowered on a path that holds both its points in that order; where the stretch's
    points leave the path after two or more of them in order (or reach it so: a trajectory
    joined of two timed paths), the path from the last of them to its end (from its start to
    the first).  Points a path holds out of order (a path back over some of the same samples)
    lower nothing there.

    Attributes
    ----------
        points_rad: (K + 1, n) consecutive points of a trajectory of the path (which are samples
            of it: ``densify_path``'s, unwrapped as timed), K ≥ 1.
        factors: (K, 4) in (0, 1]: for each segment between two of the points, the fractions of
            the velocity, acceleration, wheel momentum and wheel torque limits
            (:data:`LOWERED_LIMITS`) it is timed within.  Stretches that overlap multiply.

    """

    points_rad: np.ndarray
    factors: np.ndarray

    def __post_init__(self):
        """Refuse what the matching cannot read: K + 1 ≥ 2 points (rows), K rows of 4 factors in (0, 1]."""
        p, f = np.asarray(self.points_rad, dtype=float), np.asarray(self.factors, dtype=float)
        if p.ndim != 2 or len(p) < 2:
            raise ValueError(f"Lowering: points_rad must be (K + 1, n) with K >= 1, got shape {p.shape}")
        if f.shape != (len(p) - 1, 4):
            raise ValueError(f"Lowering: factors must be ({len(p) - 1}, 4) for {len(p)} points, got shape {f.shape}")
        if not np.all((f > 0.0) & (f <= 1.0)):
            raise ValueError("Lowering: factors must lie in (0, 1]")


@njit(cache=True, nogil=True)
def lowering_factors(over, tol, shrink, taper):
    """
    Return each segment's factors on the limits, float64 (M - 1, C), where the controller's motion overshoots them.

    ``over`` (M - 1, C): each segment's peak ratios to the limits (C = 4: joint velocity, joint
    acceleration, wheel momentum, wheel torque).  A segment whose ratio exceeds 1 + ``tol`` has that
    limit lowered to ``shrink`` over its ratio (where the acceleration is, the velocity to ``shrink``
    too); every segment takes, per limit, the least of 1 and each lowered segment's factor plus
    ``taper`` per segment between them (a step in a limit is a step in the time-optimal acceleration,
    which the controller's quintics overshoot in turn).
    """
    m, c_n = over.shape
    core = np.ones((m, c_n))
    for k in range(m):
        for c in range(c_n):
            if over[k, c] > 1.0 + tol:
                core[k, c] = shrink / max(over[k, c], 1e-300)
        if c_n > 1 and core[k, 1] < 1.0:
            core[k, 0] = min(core[k, 0], shrink)
    f = np.ones((m, c_n))
    for c in range(c_n):
        for k in range(m):
            if core[k, c] < 1.0:
                for j in range(m):
                    v = core[k, c] + taper * abs(j - k)
                    if v < f[j, c]:
                        f[j, c] = v
    return f


def _lowered_factors(p, refine: int, lowered) -> np.ndarray | None:
    """
    Return each grid point's factors on the limits, (G, 4), G = (M - 1)·refine + 1; None when none is lowered.

    p: (M, n) the path's samples; ``lowered``: :class:`Lowering` stretches, their points matched
    on the samples bit for bit (a trajectory's points are the samples themselves).  One kernel
    (:func:`_zone_factors`) for all the stretches.
    """
    if not lowered:
        return None
    m, n = p.shape
    for z in lowered:
        if np.shape(z.points_rad)[1] != n:
            raise ValueError(f"lowered: a stretch of {np.shape(z.points_rad)[1]} joints on a path of {n}")
    bits = np.ascontiguousarray(p, dtype=np.float64).view(np.uint64)
    pts = np.ascontiguousarray(np.concatenate([np.asarray(z.points_rad, dtype=np.float64) for z in lowered]))
    fac = np.ascontiguousarray(np.concatenate([np.asarray(z.factors, dtype=np.float64).reshape(-1, 4)
                                               for z in lowered]))
    starts = np.cumsum([0] + [len(z.points_rad) for z in lowered]).astype(np.int64)
    f = np.ones(((m - 1) * refine + 1, 4))
    hit = _zone_factors(bits, int(refine), pts.view(np.uint64).reshape(-1, n), starts, fac, f)
    return f if hit else None


@njit(cache=True, nogil=True, inline="always")
def _bits_hash(bits):
    """Return a hash (uint64) of the bit patterns bits (n,) uint64: mixed by products mod 2^64."""
    mult = np.uint64(0x100000001B3)
    shift = np.uint64(29)
    x = np.uint64(0x2545F4914F6CDD1D)
    for j in range(bits.size):
        x = (x ^ bits[j]) * mult
        x ^= x >> shift
    return x


@njit(cache=True, nogil=True)
def _row_hashes(bits):
    """Return a hash (uint64 (M,)) of each row of bits (M, n) uint64 (:func:`_bits_hash`)."""
    m = bits.shape[0]
    h = np.empty(m, np.uint64)
    for i in range(m):
        h[i] = _bits_hash(bits[i])
    return h


@njit(cache=True, nogil=True)
def _zone_factors(bits, refine, pts, starts, fac, f):
    """
    Multiply f (G, 4) by every stretch's factors on the grid; return whether one matched the path.

    bits uint64 (M, n): the path's samples' float64 bit patterns; pts uint64 (P, n): the stretches'
    points' bit patterns, stretch z at rows ``starts[z]:starts[z + 1]``; fac (P - Z, 4): their
    segments' factors, stretch z at rows ``starts[z] - z:starts[z + 1] - z - 1``.  A point is
    the path's first sample with the same bits (the smallest index).  A segment between two
    matched points, the later further along the path, is lowered on the grid points between
    them; the first matched point's segment before it, when its own next segment is on the path,
    from the path's start (the stretch reached the path there), and the last's after it from
    the path's end (it left there); the grid points strictly inside a segment take its factors
    (in order: a later segment's over an earlier one's), its two ends the lower of theirs and
    any other segment's ending there.
    """
    m, n = bits.shape
    g_n = f.shape[0]
    h = _row_hashes(bits)
    order = np.argsort(h, kind="mergesort")        # equal hashes in index order: the first match is the smallest
    sh = h[order]
    qh = _row_hashes(pts)
    hit = False
    out = np.empty((g_n, 4))
    for z in range(starts.size - 1):
        z0, z1 = starts[z], starts[z + 1]
        k_n = z1 - z0
        idx = np.full(k_n, -1, np.int64)
        for i in range(k_n):
            at = np.searchsorted(sh, qh[z0 + i])
            while at < m and sh[at] == qh[z0 + i]:
                r = order[at]
                same = True
                for j in range(n):
                    if bits[r, j] != pts[z0 + i, j]:
                        same = False
                        break
                if same:
                    idx[i] = r
                    break
                at += 1
        first = last = -1
        for i in range(k_n):
            if idx[i] >= 0:
                if first < 0:
                    first = i
                last = i
        if first < 0:
            continue
        # the segments: (lo, hi, factor row) in order
        lo = np.empty(k_n + 1, np.int64)
        hi = np.empty(k_n + 1, np.int64)
        row = np.empty(k_n + 1, np.int64)
        s_n = 0
        f_row0 = z0 - z                          # the stretch's first factor row
        if 0 < first < k_n - 1 and idx[first + 1] > idx[first]:
            lo[s_n], hi[s_n], row[s_n] = 0, idx[first], f_row0 + first - 1      # from before the start
            s_n += 1
        for i in range(k_n - 1):
            if idx[i] >= 0 and idx[i + 1] > idx[i]:
                lo[s_n], hi[s_n], row[s_n] = idx[i], idx[i + 1], f_row0 + i
                s_n += 1
        if 0 < last < k_n - 1 and idx[last] > idx[last - 1] >= 0:
            lo[s_n], hi[s_n], row[s_n] = idx[last], m - 1, f_row0 + last            # on past the end
            s_n += 1
        if s_n == 0:
            continue
        out[:, :] = 1.0
        for k in range(s_n):
            for gi in range(lo[k] * refine + 1, hi[k] * refine):
                for c in range(4):
                    out[gi, c] = fac[row[k], c]
        for ends in (lo, hi):
            for k in range(s_n):
                gi = ends[k] * refine
                for c in range(4):
                    if fac[row[k], c] < out[gi, c]:
                        out[gi, c] = fac[row[k], c]
        for gi in range(g_n):
            for c in range(4):
                f[gi, c] *= out[gi, c]
        hit = True
    return hit


def _rows(xv, c_row, kappa, d1, d2, g, gp, h_max, tau_max, low, gp_jump=None):
    """
    Return the passes' constraint rows (a_row, b_row, c_row, kappa, xv) with the wheel's and the lowering.

    xv (G,), c_row (G, n), kappa (G-1, n): :func:`_constraint_rows`' joint rows; d1, d2 (G, n) q', q'';
    g, gp (G,) the wheel's H·q' and its derivative along the path (None: no wheel); h_max, tau_max
    its limits (inf: none); low (G, 4) or None: :func:`_lowered_factors`.  ``gp_jump`` (G,) or None:
    where gp jumps (an anchor of the bounded spline: gp is then the middle of its two sides, δ the
    jump), the torque row |g u + gp x| + δ/2 x ≤ τ bounds both sides: written as x ≤ τ/δ and
    |g u + gp x| ≤ τ - δ/2 x_max (so at least τ/2).
    """
    if low is not None:
        xv = xv * low[:, 0] ** 2
        c_row = c_row * low[:, 1:2]
    if g is None:
        return d1, d2, np.ascontiguousarray(c_row), kappa, xv
    h_at = h_max if low is None else h_max * low[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        xv = np.minimum(xv, (h_at / np.abs(g)) ** 2)
    tau_at = np.full(len(g), tau_max) if low is None else tau_max * low[:, 3]
    if gp_jump is not None and np.isfinite(tau_max):
        with np.errstate(divide="ignore"):
            xv = np.minimum(xv, tau_at / gp_jump)
        tau_at = tau_at - 0.5 * gp_jump * np.where(gp_jump > 0.0, xv, 0.0)
    return (np.ascontiguousarray(np.hstack([d1, g[:, None]])), np.ascontiguousarray(np.hstack([d2, gp[:, None]])),
            np.ascontiguousarray(np.hstack([c_row, tau_at[:, None]])),
            np.ascontiguousarray(np.hstack([kappa, np.zeros((len(g) - 1, 1))])), xv)


def time_parameterize(path_rad, max_velocity_rad_s, max_acceleration_rad_s2, joint_names=None, *,
                      velocity_scaling: float = 1.0, acceleration_scaling: float = 1.0,
                      start_path_speed: float | None = None, start_velocity_rad_s=None, start_tangent=None,
                      wheel=None, max_step_rad: float = np.radians(0.5),
                      grid_refinement: int = 2, start_speed_tolerance: float = 1e-3,
                      lowered: tuple = (), brake_to_limits: bool = False, lower_rad=None,
                      upper_rad=None) -> Trajectory:
    """
    Time-optimal parameterisation of a joint path within joint (and wheel) limits.

    Args:
        path_rad: (M, n) joint positions, rad; start first, goal last (kept exactly).
            Periodic joints must be unwrapped (continuous): the path is followed as given.
        max_velocity_rad_s, max_acceleration_rad_s2: (n,) positive joint limits.
        joint_names: names for the columns (default j0, j1, ...).
        velocity_scaling, acceleration_scaling: factors in (0, 1] on the joint limits
            (MoveIt's max_velocity_scaling_factor / max_acceleration_scaling_factor).
        start_path_speed: ṡ at the start, rad/s of joint-space chord length (default 0:
            at rest); the start velocity is then ``q'(0) · start_path_speed``.
        start_velocity_rad_s: (n,) instead of ``start_path_speed``: a start joint
            velocity, projected on the path's start tangent (it must lie along it, see
            :func:`start_path_speed_from_velocity`).
        start_tangent: (n,) the path's derivative at its start with respect to its chord
            length (about unit length, pointing along the path's first step: within
            :data:`MAX_START_TANGENT_TURN_RAD`), or None: the path's spline leaves its start
            along it (clamped) instead of its own not-a-knot tangent.  A replan joined to a
            moving arm gives the arm's velocity over its path speed, so that the start velocity
            ``q'(0) · start_path_speed`` is the arm's (a few rows of executing path before a
            corner fit a tangent up to 7 % off it, which the controller's first quintic turned
            into an acceleration peak up to 1.9 times the limit).
        wheel: optional ``spacecraft.WheelModel``; adds the wheel momentum
            (``|H·q'| ṡ ≤ max_momentum_Nms``) and torque
            (``|d(H·q')/ds ṡ² + H·q' s̈| ≤ max_torque_Nm``) constraints (a None or 0
            limit: not enforced, only reported).
        max_step_rad: the path is subdivided so no joint moves more than this per point.
        grid_refinement: grid points per path segment for the reachability passes
            (the trajectory has one point per path sample).
        start_speed_tolerance: a start speed above the largest admissible one by at most
            this fraction is lowered to it (a path re-fitted through the same samples moves
            the velocity bound by a hair); more is refused.
        lowered: :class:`Lowering` stretches, where the limits are lower still (the chain's
            re-timings, where the controller's interpolation overshot them).
        brake_to_limits: a start speed above the velocity limits at the start (limits
            lowered while the arm moves) is braked at the acceleration (and wheel torque)
            limits until the limits admit it, instead of refused; the velocity (and wheel
            momentum) limits do not bind along that stretch (its ``limit_ratio`` above 1), but
            no joint's speed over its limit rises above the largest such ratio before it (on the
            grid's bounds), and the stretches the chain lowered near the start stay lowered.
            Refused still where that braking cannot reach the limits on the path.
        lower_rad, upper_rad: (n,) the joints' bounds, rad (±inf, or None for all: unbounded,
            e.g. a periodic joint).  The samples lie within them; the spline through them is
            kept within them too: where it would pass a bound between the samples (a path that
            touches a bound at a sample and turns back), the samples on the bound hold that
            joint at rest on the path (q' = 0) and the spline is C1 there (``_bounded_slopes``).

    Returns
    -------
        Trajectory, ending at rest; a one-point trajectory (t = 0) when start == goal.

    Raises
    ------
        ValueError: bad shapes, NaN, non-positive limits, a scaling factor outside
            (0, 1], a start velocity the path cannot be followed with (across the
            tangent, backwards, or too fast to stay within the limits and stop at the goal),
            or limits so low that the trajectory would last longer than
            :data:`MAX_DURATION_S` (the reason names the limit that holds it back).

    """
    refine = int(grid_refinement)
    tangent = None
    if start_tangent is not None:
        if start_velocity_rad_s is not None:
            raise ValueError("start_tangent: give it with start_path_speed, not start_velocity_rad_s")
        tangent = np.array(start_tangent, dtype=float).reshape(-1)
        check_start_tangent(tangent, path_rad)
    bounds = _joint_bounds(lower_rad, upper_rad, np.shape(path_rad))
    p, model = _modelled_path(path_rad, float(max_step_rad), refine, tangent, bounds)
    n = p.shape[1]
    vmax = _check_limits("max_velocity", max_velocity_rad_s, n)
    amax = _check_limits("max_acceleration", max_acceleration_rad_s2, n)
    vmax = vmax * _check_factor("velocity_scaling", velocity_scaling)
    amax = amax * _check_factor("acceleration_scaling", acceleration_scaling)
    names = tuple(joint_names) if joint_names is not None else tuple(f"j{i}" for i in range(n))
    if len(names) != n:
        raise ValueError(f"joint_names: expected {n} names, got {len(names)}")
    if start_path_speed is not None and start_velocity_rad_s is not None:
        raise ValueError("start_path_speed: give either start_path_speed or start_velocity_rad_s, not both")
    if start_velocity_rad_s is not None:
        sd0 = start_path_speed_from_velocity(p, start_velocity_rad_s, bounds=bounds)
    else:
        sd0 = 0.0 if start_path_speed is None else float(start_path_speed)
        if not (np.isfinite(sd0) and sd0 >= 0.0):
            raise ValueError(f"start_path_speed: must be a finite number ≥ 0, got {start_path_speed}")
    h_max = _limit_or_inf(getattr(wheel, "max_momentum_Nms", None))
    tau_max = _limit_or_inf(getattr(wheel, "max_torque_Nm", None))
    if len(p) == 1:
        if sd0 > 0.0:
            raise ValueError("start_path_speed: the path has no length, the arm cannot keep moving")
        z = np.zeros_like(p)
        zero = np.zeros(1)
        return Trajectory(names, zero, p, z, z.copy(), vmax, amax, zero.copy(), np.array(["none"]),
                          zero.copy(), zero.copy() if wheel is not None else None,
                          zero.copy() if wheel is not None else None,
                          None if h_max == np.inf else h_max, None if tau_max == np.inf else tau_max)

    qg, d1, d2, d3, ds, other = model
    g_n = len(qg)
    # velocity type x = ṡ² ≤ xv, the acceleration rows' κ and limits: see _constraint_rows
    xv, kappa, c_row = _constraint_rows(d1, d3, ds, vmax, amax)
    low = _lowered_factors(p, refine, lowered)          # (G, 4) or None
    g = gp = None
    if wheel is not None:
        g, gp = wheel.path_terms(qg, d1, d2)
    gp_rows, gp_jump = gp, None
    if g is not None and other is not None:       # q'' jumps at an anchor: both sides' torque bounded
        gp_other = wheel.path_terms(qg, d1, other)[1]
        gp_rows, gp_jump = 0.5 * (gp + gp_other), np.abs(gp - gp_other)
    rows = _rows(xv, c_row, kappa, d1, d2, g, gp_rows, h_max, tau_max, low, gp_jump)
    k = _backward(*rows[:5], ds, 0.0)
    # a start above the velocity limits themselves (not lowered) brakes into them (brake_to_limits)
    braking = bool(brake_to_limits) and sd0 > np.sqrt(xv[0]) * (1.0 + start_speed_tolerance)
    free = 1                         # a moving start keeps this many grid points' limits from the lowering
    while (not braking and low is not None and sd0 > np.sqrt(k[0]) * (1.0 + start_speed_tolerance)
           and free < 2 * g_n):
        # the arm's speed is given: lowered only where it can be entered (at last the whole path:
        # the limits themselves); a grid point's rows follow its own factors, so the pass is
        # redone from the last point whose factors this round raises (none: k stands)
        raised = np.flatnonzero((low[:free] != 1.0).any(axis=1))
        low = low.copy()
        low[:free] = 1.0
        if raised.size:
            rows = _rows(xv, c_row, kappa, d1, d2, g, gp_rows, h_max, tau_max, low, gp_jump)
            _backward_from(k, *rows[:5], ds, 0.0, int(raised[-1]))
        free *= 2
    a_row, b_row, c_row, kappa, xv = rows
    x0 = sd0 * sd0
    if not braking and sd0 > np.sqrt(k[0]) * (1.0 + start_speed_tolerance):
        raise ValueError(f"start_path_speed: {sd0:.6g} rad/s along the path is faster than the limits "
                         f"allow from the start (at most {np.sqrt(k[0]):.6g} rad/s there, to stay within "
                         f"the velocity and acceleration limits and stop at the goal)")
    # ---- the published times are float64: their rounding moves the finite differences
    # of the positions (by up to |w| ulp(t) / Δt² where samples are close in time).  Where
    # that could exceed _ROUNDING_SLACK of a limit, the limits there are lowered by a bound
    # on it and the passes rerun, until the bound from the new solution fits the margin.
    c_used, xv_used = c_row, xv
    m_acc, m_vel = np.zeros((g_n, n)), np.zeros(g_n)
    for _ in range(_ROUNDING_ROUNDS):
        x, dt, t, dt_samples = _solve(a_row, b_row, c_used, kappa, xv_used, ds, k, x0, refine, braking)
        acc_m, vel_m, grown = _rounding_margins(t, dt_samples, p, d1, x, amax, refine, m_acc, m_vel)
        if not grown:
            break
        m_acc = np.maximum(m_acc, np.minimum(2.0 * acc_m, 0.9 * amax))
        m_vel = np.maximum(m_vel, np.minimum(2.0 * vel_m, 0.9))
        c_used = c_row.copy()
        c_used[:, :n] = np.maximum(c_row[:, :n] - m_acc, 0.1 * c_row[:, :n])
        xv_used = np.ascontiguousarray(xv * (1.0 - m_vel) ** 2)
        k = _backward(a_row, b_row, c_used, kappa, xv_used, ds, 0.0)
    empty = np.zeros(0)
    sd, vel, acc, h_w, tau_w, best, ratio = _sample_states(
        x, dt, ds, d1, d2, refine, vmax, amax, empty if g is None else np.ascontiguousarray(g),
        empty if gp is None else np.ascontiguousarray(gp), h_max, tau_max)
    labels = [f"velocity:{nm}" for nm in names] + [f"acceleration:{nm}" for nm in names]
    if wheel is not None:
        labels += ["wheel_momentum", "wheel_torque"]
    else:
        h_w = tau_w = None
    active = np.array(labels)[best]
    if not t[-1] <= MAX_DURATION_S:
        raise ValueError(_too_long(t, active))
    return Trajectory(names, t, p, vel, acc, vmax, amax, sd, active, ratio, h_w, tau_w,
                      None if h_max == np.inf else h_max, None if tau_max == np.inf else tau_max)


def _joint_bounds(lower_rad, upper_rad, shape):
    """Return :func:`time_parameterize`'s bounds as (lo, hi), each (n,) float64 (None: none given)."""
    if (lower_rad is None and upper_rad is None) or len(shape) != 2:
        return None                     # (a path of another shape is refused by densify_path)
    n = shape[1]
    lo = np.full(n, -np.inf) if lower_rad is None else np.ascontiguousarray(lower_rad, dtype=float).reshape(-1)
    hi = np.full(n, np.inf) if upper_rad is None else np.ascontiguousarray(upper_rad, dtype=float).reshape(-1)
    if lo.shape == hi.shape == (n,) and (lo < hi).all():
        return lo, hi
    for name, b in (("lower_rad", lo), ("upper_rad", hi)):
        if b.shape != (n,) or np.isnan(b).any():
            raise ValueError(f"{name}: expected {n} bounds (rad, ±inf where a joint has none), got {b.tolist()}")
    raise ValueError(f"lower_rad, upper_rad: each lower bound must lie below its upper bound, got "
                     f"{lo.tolist()} and {hi.tolist()}")


def _too_long(times_s, active_limit) -> str:
    """Return why a trajectory longer than :data:`MAX_DURATION_S` is refused: its length and what holds it back."""
    share = {}
    for label, d in zip(active_limit[:-1], np.diff(times_s)):
        share[str(label)] = share.get(str(label), 0.0) + float(d)
    label = max(share, key=share.get)
    kind, _, joint = label.partition(":")
    what = (f"the {kind} limit of joint '{joint}' (or its scaling factor)" if joint else
            {"wheel_momentum": "the wheel momentum limit", "wheel_torque": "the wheel torque limit"}.get(kind, kind))
    return (f"the limits make this trajectory last {times_s[-1]:.4g} s, longer than a trajectory message can "
            f"hold ({MAX_DURATION_S:.0f} s); {what} holds it back for {100.0 * share[label] / times_s[-1]:.0f} % "
            "of that time and is too low")


def finite_differences(times_s, positions_rad, start_velocity_rad_s=None):
    """
    Return finite-difference velocities (M-1, n) and accelerations (M, n).

    Velocities per segment, accelerations per point, at rest at the end and at
    ``start_velocity_rad_s`` (default rest) at the start (see the module docstring).
    """
    t = np.asarray(times_s, dtype=float)
    q = np.asarray(positions_rad, dtype=float)
    v0 = np.zeros(q.shape[1]) if start_velocity_rad_s is None else np.asarray(start_velocity_rad_s, float)
    dt = np.diff(t)
    w = np.diff(q, axis=0) / dt[:, None]
    acc = np.empty_like(q)
    acc[0] = (w[0] - v0) / (0.5 * dt[0])
    acc[-1] = -w[-1] / (0.5 * dt[-1])
    if len(q) > 2:
        acc[1:-1] = np.diff(w, axis=0) / (0.5 * (dt[:-1] + dt[1:]))[:, None]
    return w, acc


def limit_ratios(times_s, positions_rad, velocities, accelerations, vmax, amax):
    """
    Return (velocity ratio, acceleration ratio): the largest |value| / limit.

    Over the published values and the finite-difference velocities, and over the published
    accelerations; ≤ 1 means within the limits.
    """
    w = np.diff(positions_rad, axis=0) / np.diff(times_s)[:, None]
    rv = max(np.max(np.abs(w) / vmax), np.max(np.abs(velocities) / vmax))
    ra = np.max(np.abs(accelerations) / amax)
    return float(rv), float(ra)


def sample(traj: Trajectory, t_s: float, points=None):
    """
    Position and velocity at time ``t_s`` (clamped to [0, duration]).

    Linear interpolation of the positions between points (the arm stays on the dense,
    collision-checked polyline) and of the velocities.  ``points``: (K,) sorted indices of the
    points to interpolate between (first and last included), as ``sample(traj.subset(points),
    t_s)`` without the subset's copies (None: every point).
    """
    t = traj.times_s if points is None else traj.times_s[points]
    first, last = (0, len(traj) - 1) if points is None else (points[0], points[-1])
    if len(t) == 1 or t_s <= 0.0:
        return traj.positions_rad[first].copy(), traj.velocities_rad_s[first].copy()
    if t_s >= t[-1]:
        return traj.positions_rad[last].copy(), np.zeros(traj.positions_rad.shape[1])
    k = int(np.searchsorted(t, t_s, side="right") - 1)
    f = (t_s - t[k]) / (t[k + 1] - t[k])
    a, b = (k, k + 1) if points is None else (points[k], points[k + 1])
    q = traj.positions_rad[a] + f * (traj.positions_rad[b] - traj.positions_rad[a])
    v = traj.velocities_rad_s[a] + f * (traj.velocities_rad_s[b] - traj.velocities_rad_s[a])
    return q, v


@dataclass(frozen=True, eq=False)
class Continuation:
    """
    Where a replacement trajectory joins an executing one (see :func:`continuation`).

    Attributes
    ----------
        index: the executing trajectory's point where the new one starts.
        join_time_s: that point's time in the executing trajectory (the new
            trajectory's time 0 is this instant).
        prefix_rad: (P, n) the executing path from that point to the horizon point
            (P ≥ 1; its last row is where the new plan must start).
        start_path_speed: ṡ at the join, for ``time_parameterize(start_path_speed=...)``.
        start_velocity_rad_s: (n,) the joint velocity at the join.

    """

    index: int
    join_time_s: float
    prefix_rad: np.ndarray
    start_path_speed: float
    start_velocity_rad_s: np.ndarray

    def join(self, new_path_rad) -> np.ndarray:
        """
        Return the path to time-parameterise, (P + K - 1, n).

        The prefix, then ``new_path_rad`` (which must start at ``prefix_rad[-1]``, the
        horizon point).
        """
        new = np.asarray(new_path_rad, dtype=float)
        if new.ndim != 2 or new.shape[1] != self.prefix_rad.shape[1]:
            raise ValueError(f"new_path_rad: expected (K, {self.prefix_rad.shape[1]}) rows, got {new.shape}")
        if np.max(np.abs(new[0] - self.prefix_rad[-1])) > 1e-9:
            raise ValueError("new_path_rad: must start at the continuation's horizon point prefix_rad[-1]")
        return np.vstack([self.prefix_rad, new[1:]])


class HorizonPassed(ValueError):
    """The executing trajectory is already past the point where the new plan starts."""


def horizon_index(traj: Trajectory, t_s: float, horizon_s: float) -> int:
    """
    Return where a replacement plan starts: an index of ``traj``.

    The first point at or after ``t_s + horizon_s`` (s from its start), the last point when
    that is beyond its end.
    """
    if not (np.isfinite(t_s) and np.isfinite(horizon_s) and horizon_s >= 0.0):
        raise ValueError(f"horizon_s: must be a finite number ≥ 0 (t_s finite), got {horizon_s}, {t_s}")
    return min(int(np.searchsorted(traj.times_s, t_s + horizon_s, side="left")), len(traj.times_s) - 1)


def continuation(traj: Trajectory, t_s: float, horizon_s: float = 1.0, *, horizon_at: int | None = None,
                 join_indices=None) -> Continuation:
    """
    Replanning from a moving arm: keep the executing trajectory to a horizon, join there.

    The new trajectory starts at the first point of ``traj`` at or after ``t_s`` (the
    join, an exact state: position, velocity, path speed) and follows ``traj``'s path to
    the point ``horizon_s`` later, where the new plan starts.  Time-parameterising
    ``c.join(new_path)`` with ``start_path_speed=c.start_path_speed`` and
    ``start_tangent=c.start_velocity_rad_s / c.start_path_speed`` (``replanning.start_tangent``)
    gives a trajectory continuous in position and velocity at the join (without the tangent,
    the velocity is projected on a re-fitted one: up to 7 % off where a few rows of executing
    path lead to a corner), within the limits; it raises ``ValueError`` when the new path turns too sharply after
    the horizon to be entered at that speed (take a longer horizon).

    Args:
        traj: the executing trajectory (dense: its polyline is the certified path).
        t_s: the current time in it (s from its start).
        horizon_s: how far ahead (s) the new plan starts, ≥ 0 (see :func:`horizon_index`).
        horizon_at: instead of ``horizon_s``, the index where the new plan starts (it was
            chosen when the plan began; the join is now, later).
        join_indices: the indices of ``traj`` the join may be at (default: any point).
            A controller given a subset of the points (``resample``) interpolates the
            velocity between them: joining at one of them keeps the velocity exact.

    Returns
    -------
        Continuation; at or beyond the end of ``traj`` it is the goal at rest.

    Raises
    ------
        HorizonPassed: the join would lie beyond ``horizon_at`` (the plan took too long).

    """
    t = traj.times_s
    h = horizon_index(traj, t_s, horizon_s) if horizon_at is None else int(horizon_at)
    if not 0 <= h < len(t):
        raise ValueError(f"horizon_at: {h} is not an index of the trajectory's {len(t)} points")
    cand = np.arange(len(t)) if join_indices is None else np.unique(np.append(np.asarray(join_indices), len(t) - 1))
    j = int(np.searchsorted(t[cand], t_s, side="left"))
    k = int(cand[min(j, len(cand) - 1)])
    if k > h:
        raise HorizonPassed(f"horizon_at: the join (t = {t[k]:.3f} s) is past the horizon point "
                            f"(t = {t[h]:.3f} s): the new plan starts behind the arm")
    speed = 0.0 if traj.path_speed is None else float(traj.path_speed[k])
    return Continuation(k, float(t[k]), traj.positions_rad[k:h + 1].copy(), speed,
                        traj.velocities_rad_s[k].copy())
