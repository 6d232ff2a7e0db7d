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

Every function takes ``periodic`` as a sequence of bools, one per column.  ``wrap_rad`` and
``wrap_angle_rad`` take arrays of any leading axes; ``nearest_turn_rad`` one (n,) value;
``unwrap_path`` and ``align_to_state`` an (M, n) path (others are refused).  The path functions run small numba kernels
(``_wrap_rows``, ``_unwrap_rows``, ``_turn_rows``) that do NumPy's operations element by
element, in NumPy's order (a plan calls them a few times: the same values, without the
temporaries).
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
    per = np.array(periodic, dtype=bool).reshape(-1)         # a writeable copy (the kernels' signature)
    if per.shape != (n,):
        raise ValueError(f"periodic: expected {n} flags (one per joint), got {per.shape[0]}")
    return per


def _row(values, n: int) -> np.ndarray:
    """Return ``values`` (one per joint, or one for all) as a new (n,) float array (the kernels' signature)."""
    v = np.array(values, dtype=float)
    return v if v.shape == (n,) else np.array(np.broadcast_to(v, (n,)))


@njit(cache=True, nogil=True)
def _wrap_rows(q, lower_rad, per):
    """:func:`wrap_rad` in place on the rows of q (k, n): lower + (q - lower) mod 2π on the periodic columns."""
    for r in range(q.shape[0]):
        for a in range(q.shape[1]):
            if per[a]:
                q[r, a] = lower_rad[a] + (q[r, a] - lower_rad[a]) % TWO_PI


@njit(cache=True, nogil=True)
def _unwrap_rows(q, per):
    """
    Run :func:`unwrap_path` in place on q (M ≥ 2, n).

    On each periodic column the row-to-row differences wrapped into [-π, π), their running sum from
    the first, added to the first row (NumPy's diff, cumsum and sum, in that order).
    """
    for a in range(q.shape[1]):
        if not per[a]:
            continue
        first = q[0, a]
        prev = first
        total = 0.0
        for k in range(1, q.shape[0]):
            now = q[k, a]
            step = wrap_angle_scalar_rad(now - prev)
            total = step if k == 1 else total + step
            q[k, a] = first + total
            prev = now


@njit(cache=True, nogil=True)
def _turn_rows(p, reference_rad, per):
    """Shift the periodic columns of p (M, n) by the whole turns that bring row 0 nearest ``reference_rad`` (n,)."""
    for a in range(p.shape[1]):
        if per[a]:
            shift = TWO_PI * np.rint((reference_rad[a] - p[0, a]) / TWO_PI)
            for k in range(p.shape[0]):
                p[k, a] = p[k, a] + shift


def wrap_rad(q_rad, periodic, lower_rad) -> np.ndarray:
    """
    Periodic columns of ``q_rad`` (..., n) wrapped into [lower, lower + 2π); the others unchanged.

    Returns a new array.
    """
    q = np.array(q_rad, dtype=float, copy=True, order="C")
    n = q.shape[-1]
    per = _mask(periodic, n)
    _wrap_rows(q.reshape(-1, n), _row(lower_rad, n), per)
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
    q = np.array(path_rad, dtype=float, copy=True, order="C")
    if q.ndim != 2:
        raise ValueError(f"unwrap_path: expected an (M, n) path, got shape {q.shape}")
    per = _mask(periodic, q.shape[1])
    if len(q) > 1:
        _unwrap_rows(q, per)
    return q


def nearest_turn_rad(value_rad, reference_rad, periodic) -> np.ndarray:
    """
    ``value`` shifted by whole turns on periodic joints to lie nearest ``reference`` (within π of it).

    Bounded joints keep ``value``.

    (n,) → (n,).
    """
    v = np.array(value_rad, dtype=float, copy=True)
    if v.ndim != 1:
        raise ValueError(f"nearest_turn_rad: expected an (n,) value, got shape {v.shape}")
    _turn_rows(v.reshape(1, -1), _row(reference_rad, v.shape[0]), _mask(periodic, v.shape[0]))
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
    p = np.array(path_rad, dtype=float, copy=True, order="C")
    s = np.array(state_rad, dtype=float)
    if p.ndim != 2 or len(p) == 0 or s.shape != (p.shape[1],):
        raise ValueError(f"align_to_state: expected an (M, n) path and an (n,) state, got {p.shape} "
                         f"and {s.shape}")
    _turn_rows(p, s, _mask(periodic, p.shape[1]))
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


@njit(cache=True, nogil=True, inline="always")
def row_within_bounds(q_rad, lower_rad, upper_rad, periodic):
    """:func:`within_bounds` of one row q (n,) inside a numba kernel, tolerance 0 (the same comparisons: NaN is out)."""
    for a in range(q_rad.shape[0]):
        if not ((q_rad[a] >= lower_rad[a] and q_rad[a] <= upper_rad[a]) or periodic[a]):
            return False
    return True


def deg_text(q_rad) -> str:
    """Return a configuration for people: ``(160.7, 32.8, 76.5)°`` (one rounding to zero reads 0.0, not -0.0)."""
    return "(" + ", ".join(f"{v:.1f}".replace("-0.0", "0.0") if abs(v) < 0.05 else f"{v:.1f}"
                           for v in np.degrees(np.asarray(q_rad, dtype=float))) + ")°"
