"""Time parameterisation of a geometric joint path under per-joint limits.

The last stage of the chain (MoveIt's "time parameterisation adapter"): it takes the
planner's dense path (M×n joint positions, rad, start first, goal last, periodic
joints unwrapped) and returns the times at which to pass every point, with joint
velocities and accelerations, so that no joint exceeds its velocity limit (rad/s)
or its acceleration limit (rad/s²).  The arm starts and ends at rest.

Method (time-optimal path parameterisation on the discretised path):

1. The path is parameterised by its joint-space arc length ``s`` (rad); the
   tangent ``q'(s)`` and curvature ``q''(s)`` come from finite differences.
2. At each point, the velocity limits and the condition that some path
   acceleration ``s̈`` keeps every ``|q'_j s̈ + q''_j ṡ²| ≤ a_j`` give the maximum
   velocity curve (an upper bound on ``ṡ²``).
3. A forward pass (accelerate as hard as allowed from rest) and a backward pass
   (decelerate as hard as allowed into the goal) under that curve give ``ṡ`` at
   every point; each segment then takes ``Δt = 2 Δs / (ṡ_k + ṡ_{k+1})``.
4. Safety net: the published velocities/accelerations *and* the finite
   differences of the positions are checked against the limits; if the
   discretisation left any excess, the whole trajectory is slowed uniformly
   (time × c scales velocities by 1/c and accelerations by 1/c²), so the limits
   hold by construction.

Finite differences, as used by the check (and by the tests): segment velocity
``w_k = (q_{k+1} - q_k) / (t_{k+1} - t_k)``; acceleration at an interior point
``(w_k - w_{k-1}) / ((Δt_{k-1} + Δt_k) / 2)``, at the first point ``w_0 / (Δt_0 / 2)``
and at the last ``-w_{M-2} / (Δt_{M-2} / 2)`` (rest at both ends: exact for a
constant acceleration from/to rest).

No ROS imports here: plain NumPy (numba for the two passes).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit

__all__ = ["Trajectory", "time_parameterize", "finite_differences", "sample",
           "densify_path", "limit_ratios"]

_EPS = 1e-12


@dataclass(frozen=True, eq=False)
class Trajectory:
    """A time-parameterised joint path.

    Attributes:
        joint_names: one name per column.
        times_s: (M,) strictly increasing, 0 first.
        positions_rad: (M, n); first row the start, last row the goal (exact).
        velocities_rad_s: (M, n); zero at both ends.
        accelerations_rad_s2: (M, n).
        max_velocity_rad_s, max_acceleration_rad_s2: (n,) the limits it obeys.
        time_scale: the uniform slow-down the safety net applied (1 = none).
    """

    joint_names: tuple
    times_s: np.ndarray
    positions_rad: np.ndarray
    velocities_rad_s: np.ndarray
    accelerations_rad_s2: np.ndarray
    max_velocity_rad_s: np.ndarray
    max_acceleration_rad_s2: np.ndarray
    time_scale: float = 1.0

    @property
    def duration_s(self) -> float:
        return float(self.times_s[-1])

    def __len__(self) -> int:
        return len(self.times_s)


def densify_path(path_rad, max_step_rad: float = np.radians(0.5), min_points: int = 3) -> np.ndarray:
    """Drop repeated points and subdivide so consecutive points are ≤ max_step_rad apart
    (in every joint) and there are at least ``min_points`` (when start ≠ goal).

    The first and last points are kept exactly.
    """
    p = np.asarray(path_rad, dtype=float)
    if p.ndim != 2 or p.shape[0] < 1:
        raise ValueError(f"path: expected an (M, n) array with M ≥ 1, got shape {p.shape}")
    if not np.all(np.isfinite(p)):
        raise ValueError("path: contains NaN or inf")
    if len(p) > 1:
        moved = np.max(np.abs(np.diff(p, axis=0)), axis=1) > 1e-12
        keep = np.concatenate([[True], moved])
        # compare with the last kept point, not the previous one (slow creeps)
        if not np.all(moved):
            idx = [0]
            for k in range(1, len(p)):
                if np.max(np.abs(p[k] - p[idx[-1]])) > 1e-12:
                    idx.append(k)
            keep = np.zeros(len(p), dtype=bool)
            keep[idx] = True
        last = np.flatnonzero(keep)[-1]
        if 0 < last != len(p) - 1:
            keep[last] = False
            keep[-1] = True                 # exact goal last
        p = p[keep]
    if len(p) == 1:
        return p
    steps = np.max(np.abs(np.diff(p, axis=0)), axis=1)
    subdiv = np.maximum(1, np.ceil(steps / max_step_rad - 1e-9)).astype(int)
    total = int(subdiv.sum())
    if total + 1 < min_points:
        subdiv[np.argmax(steps)] += min_points - 1 - total
    if np.all(subdiv == 1):
        return p
    seg = np.repeat(np.arange(len(subdiv)), subdiv)
    frac = (np.arange(total) - np.repeat(np.cumsum(subdiv) - subdiv, subdiv) + 1) / np.repeat(subdiv, subdiv)
    out = p[seg] + frac[:, None] * (p[seg + 1] - p[seg])
    out[np.cumsum(subdiv) - 1] = p[1:]     # segment ends exactly
    return np.concatenate([p[:1], out])


def _path_derivatives(p):
    """Arc length s (M,), tangent q'(s) (M, n), curvature q''(s) (M, n)."""
    ds = np.linalg.norm(np.diff(p, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(ds)])
    if len(p) >= 3:
        d1 = np.gradient(p, s, axis=0, edge_order=2)
        d2 = np.gradient(d1, s, axis=0, edge_order=2)
    else:
        d1 = np.repeat((np.diff(p, axis=0) / ds[:, None]), 2, axis=0)
        d2 = np.zeros_like(p)
    return s, ds, d1, d2


@njit(cache=True)
def _accel_bounds(x, d1, d2, amax):
    """Admissible path acceleration [lo, hi] at one point for ṡ² = x."""
    lo = -1e300
    hi = 1e300
    for j in range(d1.shape[0]):
        a = d1[j]
        b = d2[j] * x
        if abs(a) > 1e-9:
            l = (-amax[j] - b) / a
            h = (amax[j] - b) / a
            if a < 0.0:
                l, h = h, l
            if l > lo:
                lo = l
            if h < hi:
                hi = h
        elif abs(b) > amax[j]:
            return 1.0, -1.0        # infeasible
    return lo, hi


@njit(cache=True)
def _mvc(d1, d2, vmax, amax):
    """Maximum velocity curve: the largest ṡ² per point (velocity limits and
    existence of an admissible path acceleration)."""
    m, n = d1.shape
    out = np.empty(m)
    for k in range(m):
        xv = 1e300
        for j in range(n):
            if abs(d1[k, j]) > 1e-12:
                v = vmax[j] / abs(d1[k, j])
                if v * v < xv:
                    xv = v * v
        lo, hi = _accel_bounds(xv, d1[k], d2[k], amax)
        if lo <= hi:
            out[k] = xv
            continue
        a, b = 0.0, xv              # feasible set in x is an interval [0, x*]
        for _ in range(60):
            mid = 0.5 * (a + b)
            lo, hi = _accel_bounds(mid, d1[k], d2[k], amax)
            if lo <= hi:
                a = mid
            else:
                b = mid
        out[k] = a
    return out


@njit(cache=True)
def _passes(ds, d1, d2, mvc, amax):
    m = mvc.shape[0]
    x = mvc.copy()
    x[0] = 0.0
    x[m - 1] = 0.0
    for _ in range(50):
        before = x.copy()
        _one_pass(x, ds, d1, d2, amax)
        if np.max(np.abs(x - before)) <= 1e-12 * (1.0 + np.max(x)):
            break
    return x


@njit(cache=True)
def _one_pass(x, ds, d1, d2, amax):
    m = x.shape[0]
    for k in range(m - 1):                       # forward: accelerate
        lo, hi = _accel_bounds(x[k], d1[k], d2[k], amax)
        nxt = max(0.0, x[k] + 2.0 * hi * ds[k]) if lo <= hi else x[k]
        if nxt < x[k + 1]:
            x[k + 1] = nxt
    for k in range(m - 2, -1, -1):               # backward: decelerate
        lo, hi = _accel_bounds(x[k + 1], d1[k + 1], d2[k + 1], amax)
        prv = max(0.0, x[k + 1] - 2.0 * lo * ds[k]) if lo <= hi else x[k + 1]
        if prv < x[k]:
            x[k] = prv


def finite_differences(times_s, positions_rad):
    """Finite-difference velocities (M-1, n) per segment and accelerations (M, n)
    per point, rest at both ends (see the module docstring)."""
    t = np.asarray(times_s, dtype=float)
    q = np.asarray(positions_rad, dtype=float)
    dt = np.diff(t)
    w = np.diff(q, axis=0) / dt[:, None]
    acc = np.empty_like(q)
    acc[0] = w[0] / (0.5 * dt[0])
    acc[-1] = -w[-1] / (0.5 * dt[-1])
    if len(q) > 2:
        acc[1:-1] = np.diff(w, axis=0) / (0.5 * (dt[:-1] + dt[1:]))[:, None]
    return w, acc


def limit_ratios(times_s, positions_rad, velocities, accelerations, vmax, amax):
    """Largest |value| / limit over the published values and the finite differences:
    (velocity ratio, acceleration ratio); ≤ 1 means within the limits."""
    w, fa = finite_differences(times_s, positions_rad)
    rv = max(np.max(np.abs(w) / vmax), np.max(np.abs(velocities) / vmax))
    ra = max(np.max(np.abs(fa) / amax), np.max(np.abs(accelerations) / amax))
    return float(rv), float(ra)


def time_parameterize(path_rad, max_velocity_rad_s, max_acceleration_rad_s2, joint_names=None,
                      max_step_rad: float = np.radians(0.5), margin: float = 0.98) -> Trajectory:
    """Time-parameterise a joint path, rest to rest, within per-joint limits.

    Args:
        path_rad: (M, n) joint positions, rad; start first, goal last (kept exactly).
            Periodic joints must be unwrapped (continuous): the path is followed as given.
        max_velocity_rad_s, max_acceleration_rad_s2: (n,) positive limits.
        joint_names: names for the columns (default j0, j1, ...).
        max_step_rad: the path is subdivided so no joint moves more than this per point.
        margin: the profile is planned at ``margin ×`` the limits (the safety net
            then guarantees the limits themselves).
    Returns:
        Trajectory; a one-point trajectory (t = 0) when start == goal.
    Raises:
        ValueError: bad shapes, NaN, non-positive limits.
    """
    p = densify_path(path_rad, max_step_rad)
    n = p.shape[1]
    vmax = np.asarray(max_velocity_rad_s, dtype=float).reshape(-1)
    amax = np.asarray(max_acceleration_rad_s2, dtype=float).reshape(-1)
    for name, lim in (("max_velocity", vmax), ("max_acceleration", amax)):
        if lim.shape != (n,):
            raise ValueError(f"{name}: expected {n} values (one per joint), got {lim.shape[0]}")
        if not np.all(np.isfinite(lim)) or np.any(lim <= 0.0):
            raise ValueError(f"{name}: every limit must be a finite number > 0, got {list(lim)}")
    names = tuple(joint_names) if joint_names is not None else tuple(f"j{i}" for i in range(n))
    if len(names) != n:
        raise ValueError(f"joint_names: expected {n} names, got {len(names)}")
    if len(p) == 1:
        z = np.zeros_like(p)
        return Trajectory(names, np.zeros(1), p, z, z.copy(), vmax, amax)

    s, ds, d1, d2 = _path_derivatives(p)
    vplan, aplan = vmax * margin, amax * margin
    mvc = _mvc(np.ascontiguousarray(d1), np.ascontiguousarray(d2), vplan, aplan)
    x = np.maximum(_passes(ds, np.ascontiguousarray(d1), np.ascontiguousarray(d2), mvc, aplan), 0.0)
    sd = np.sqrt(x)

    # segment durations: constant path acceleration per segment
    den = sd[:-1] + sd[1:]
    dirs = np.diff(p, axis=0) / ds[:, None]
    a_seg = np.min(aplan[None, :] / np.maximum(np.abs(dirs), _EPS), axis=1)
    dt = np.where(den > 1e-9, 2.0 * ds / np.maximum(den, 1e-300), 2.0 * np.sqrt(ds / a_seg))
    dt = np.maximum(dt, 1e-6)
    t = np.concatenate([[0.0], np.cumsum(dt)])

    sdd_seg = (sd[1:] - sd[:-1]) / dt
    sdd = np.empty(len(p))
    sdd[0], sdd[-1] = sdd_seg[0], sdd_seg[-1]
    sdd[1:-1] = 0.5 * (sdd_seg[:-1] + sdd_seg[1:])
    vel = d1 * sd[:, None]
    acc = d1 * sdd[:, None] + d2 * x[:, None]
    vel[0] = 0.0
    vel[-1] = 0.0

    # safety net: uniform slow-down until both the published values and the
    # finite differences are within the limits
    rv, ra = limit_ratios(t, p, vel, acc, vmax, amax)
    c = max(1.0, rv, np.sqrt(ra))
    if c > 1.0:
        c *= 1.0 + 1e-9
        t, vel, acc = t * c, vel / c, acc / (c * c)
    return Trajectory(names, t, p, vel, acc, vmax, amax, float(c))


def sample(traj: Trajectory, t_s: float):
    """Position and velocity at time ``t_s`` (clamped to [0, duration]): linear
    interpolation of the positions between points (the arm stays on the dense,
    collision-checked polyline) and of the velocities."""
    t = traj.times_s
    if len(t) == 1 or t_s <= 0.0:
        return traj.positions_rad[0].copy(), traj.velocities_rad_s[0].copy()
    if t_s >= t[-1]:
        return traj.positions_rad[-1].copy(), np.zeros(traj.positions_rad.shape[1])
    k = int(np.searchsorted(t, t_s, side="right") - 1)
    f = (t_s - t[k]) / (t[k + 1] - t[k])
    q = traj.positions_rad[k] + f * (traj.positions_rad[k + 1] - traj.positions_rad[k])
    v = traj.velocities_rad_s[k] + f * (traj.velocities_rad_s[k + 1] - traj.velocities_rad_s[k])
    return q, v
