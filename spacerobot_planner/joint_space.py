"""
The joint space: the rules for bounded and periodic joints, in one place.

OMPL's state-space role.  A configuration is a vector of joint angles in radians
(one entry per planned joint); a path is an (M, n) array.  A *periodic* joint (the
spacecraft attitude) spans one turn, [lower, lower + 2π), and θ and θ + 2π·k are the
same posture; a *bounded* joint stays within [lower, upper].

Two forms of periodic values:

- *wrapped*: in the joint's range (what the grid, the collision checker and the
  results' ``start_rad``/``goal_rad`` hold);
- *unwrapped*: continuous along a path (no 2π jumps), possibly outside the range (what
  the smoothing, the trajectory and the motion checks work on).

Every function takes ``periodic`` as a sequence of bools, one per column; arrays
broadcast over leading axes.  No numba here: the hot loops have their own inline
copies of the one-line wrap (cspace, descent kernels).
"""

from __future__ import annotations

import numpy as np
from numba import njit

__all__ = ["TWO_PI", "wrap_angle_rad", "wrap_angle_scalar_rad", "wrap_rad", "difference_rad", "distance_rad",
           "interpolate_rad", "unwrap_path", "nearest_turn_rad", "align_to_state", "within_bounds", "deg_text"]

TWO_PI = 2.0 * np.pi


def wrap_angle_rad(angle_rad):
    """Angles wrapped to [-π, π): scalars or arrays of any shape."""
    return (np.asarray(angle_rad, dtype=float) + np.pi) % TWO_PI - np.pi


@njit(cache=True, nogil=True, inline="always")
def wrap_angle_scalar_rad(angle_rad):
    """:func:`wrap_angle_rad` of one float inside a numba kernel (the same rule and operations)."""
    return (angle_rad + np.pi) % TWO_PI - np.pi


def _mask(periodic, n: int) -> np.ndarray:
    per = np.asarray(periodic, dtype=bool).reshape(-1)
    if per.shape != (n,):
        raise ValueError(f"periodic: expected {n} flags (one per joint), got {per.shape[0]}")
    return per


def wrap_rad(q_rad, periodic, lower_rad) -> np.ndarray:
    """
    Periodic columns of ``q_rad`` (..., n) wrapped into [lower, lower + 2π); the others unchanged.

    Returns a new array.
    """
    q = np.array(q_rad, dtype=float, copy=True)
    per = _mask(periodic, q.shape[-1])
    lo = np.broadcast_to(np.asarray(lower_rad, dtype=float), (q.shape[-1],))
    q[..., per] = lo[per] + (q[..., per] - lo[per]) % TWO_PI
    return q


def difference_rad(a_rad, b_rad, periodic) -> np.ndarray:
    """Return b − a per joint, the short way round on periodic joints (in [-π, π)): (..., n)."""
    d = np.asarray(b_rad, dtype=float) - np.asarray(a_rad, dtype=float)
    d = np.array(d, dtype=float, copy=True)
    per = _mask(periodic, d.shape[-1])
    d[..., per] = wrap_angle_rad(d[..., per])
    return d


def distance_rad(a_rad, b_rad, periodic) -> np.ndarray | float:
    """Euclidean joint-space distance along the shortest difference, rad: (...,)."""
    d = np.linalg.norm(difference_rad(a_rad, b_rad, periodic), axis=-1)
    return float(d) if np.ndim(d) == 0 else d


def interpolate_rad(a_rad, b_rad, t, periodic) -> np.ndarray:
    """
    Return a + t·(b − a) along the shortest difference; t scalar or (k,) → (n,) or (k, n).

    The result is continuous from ``a`` (unwrapped): wrap it with :func:`wrap_rad`
    for a value in range.
    """
    a = np.asarray(a_rad, dtype=float)
    d = difference_rad(a, b_rad, periodic)
    t = np.asarray(t, dtype=float)
    return a + (t[..., None] if t.ndim else t) * d


def unwrap_path(path_rad, periodic) -> np.ndarray:
    """
    Return the periodic columns of an (M, n) path made continuous (no 2π jumps between rows).

    The first row is kept exactly; bounded columns are untouched.  Returns a new array.
    """
    q = np.array(path_rad, dtype=float, copy=True)
    per = _mask(periodic, q.shape[-1])
    if len(q) > 1 and per.any():
        step = wrap_angle_rad(np.diff(q[:, per], axis=0))
        q[1:, per] = q[0, per] + np.cumsum(step, axis=0)
    return q


def nearest_turn_rad(value_rad, reference_rad, periodic) -> np.ndarray:
    """
    ``value`` shifted by whole turns on periodic joints to lie nearest ``reference`` (within π of it).

    Bounded joints keep ``value``.

    (n,) → (n,).
    """
    v = np.array(value_rad, dtype=float, copy=True)
    per = _mask(periodic, v.shape[-1])
    ref = np.asarray(reference_rad, dtype=float)
    turns = np.round((ref[..., per] - v[..., per]) / TWO_PI)
    v[..., per] = v[..., per] + TWO_PI * turns
    return v


def align_to_state(path_rad, state_rad, periodic, tol_rad: float = 1e-6) -> np.ndarray:
    """
    Return the path as the arm will follow it from where it is.

    Periodic columns shifted by whole turns so the first row equals the joint state (e.g. an
    unwrapped ``joint_states`` attitude of 370°), then the first row set to the state exactly.

    Args:
        path_rad: (M, n) continuous path (unwrapped), first row the start posture.
        state_rad: (n,) the current joint positions (any number of turns).
        periodic: (n,) flags.
        tol_rad: largest allowed gap between the shifted first row and the state.

    Returns
    -------
        a new (M, n) array.

    Raises
    ------
        ValueError: the path does not start at the state (up to whole turns).

    """
    p = np.array(path_rad, dtype=float, copy=True)
    s = np.asarray(state_rad, dtype=float)
    if p.ndim != 2 or len(p) == 0 or s.shape != (p.shape[1],):
        raise ValueError(f"align_to_state: expected an (M, n) path and an (n,) state, got {p.shape} "
                         f"and {s.shape}")
    per = _mask(periodic, p.shape[1])
    turns = np.round((s[per] - p[0, per]) / TWO_PI)
    p[:, per] += TWO_PI * turns
    gap = np.abs(p[0] - s)
    if np.any(gap > tol_rad):
        k = int(np.argmax(gap))
        raise ValueError(f"align_to_state: the path starts {gap[k]:.3g} rad away from the state on "
                         f"joint {k} (not a whole number of turns)")
    p[0] = s
    return p


def within_bounds(q_rad, lower_rad, upper_rad, periodic, tol_rad: float = 0.0) -> np.ndarray:
    """Per row of q (..., n): every bounded joint within [lower − tol, upper + tol]."""
    q = np.asarray(q_rad, dtype=float)
    per = _mask(periodic, q.shape[-1])
    lo = np.asarray(lower_rad, dtype=float) - tol_rad
    hi = np.asarray(upper_rad, dtype=float) + tol_rad
    inside = (q >= lo) & (q <= hi)
    return np.all(inside | per, axis=-1)


def deg_text(q_rad) -> str:
    """Return a configuration for people: ``(160.7, 32.8, 76.5)°``."""
    return "(" + ", ".join(f"{v:.1f}" for v in np.degrees(np.asarray(q_rad, dtype=float))) + ")°"
