"""
From a grid path to a smooth, densely verified joint path.

The grid path (descent nodes) is joined to the exact start and goal, unwrapped on
periodic joints, and turned into a cubic spline as in the paper (knots at every
second node).  The spline is checked on the *exact* geometry, not the grid: it is
sampled so that consecutive samples are at most ``max_step_rad`` apart (Euclidean
norm in joint space) and the piecewise-linear path through the samples is
*certified* by the scene's motion validator (``motion.MotionValidator``): the whole path,
not only the samples, keeps clearance above the scene's safety margin.  Bounded joints stay
within bounds.  Where the spline
cuts a corner, knots are added in that stretch only (first the skipped nodes,
then midpoints of the polyline) until it is clean.

All configurations are planned-joint vectors in radians; paths are (M, dof)
arrays.  Periodic joints are *unwrapped* (continuous, may leave [-π, π)).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit

from .collision import NO_REFCOUNT, config_clearance
from .motion import DEFAULT_VERIFY_STEP_RAD, QUICK_STEP_RAD, MotionValidator, certify_segments, motion_scratch, sweep_m
from .trajectory import (arc_lengths_rad, chord_lengths_rad, clamped_start_slopes, hermite_coefficients,
                         not_a_knot_slopes)

__all__ = ["SmoothPath", "path_length_rad", "densify_polyline", "shortcut_indices",
           "spline_through", "smooth_path", "start_direction", "warm_up", "DEFAULT_MAX_STEP_RAD"]

DEFAULT_MAX_STEP_RAD = float(np.radians(0.5))     # spacing of the returned samples


@dataclass(frozen=True, eq=False)
class SmoothPath:
    """
    A verified dense path.

    Attributes
    ----------
        path_rad: (M, dof) samples ≤ max_step_rad apart, exact start first and the
            exact goal last (periodic joints unwrapped, so the goal up to 2π·k).
        knots_rad: (k, dof) the spline's knots (the polyline vertices for "polyline").
        method: "shortcut_spline", "spline" (the paper's) or "polyline".
        min_clearance_m: smallest clearance over the dense check, metres.
        length_rad: joint-space length (Euclidean), rad.
        refinements: knot-refinement rounds used.
        n_checked: clearance evaluations of the final check (the vertex clearances it
            reused from the quick test that chose the path are not counted).

    """

    path_rad: np.ndarray
    knots_rad: np.ndarray
    method: str
    min_clearance_m: float
    length_rad: float
    refinements: int
    n_checked: int


# --------------------------------------------------------------------- helpers
def path_length_rad(path_rad) -> float:
    """Euclidean joint-space length of an (M, dof) path, rad."""
    p = np.asarray(path_rad, dtype=float)
    if len(p) < 2:
        return 0.0
    return float(np.sum(chord_lengths_rad(p)))


def densify_polyline(points_rad, max_step_rad: float) -> np.ndarray:
    """
    Linear interpolation of an (m, dof) polyline: consecutive rows ≤ max_step_rad apart.

    Every input vertex is kept exactly.
    """
    pts = np.asarray(points_rad, dtype=float)
    if len(pts) < 2:
        return pts.copy()
    seg = np.diff(pts, axis=0)
    n = np.maximum(1, np.ceil(np.linalg.norm(seg, axis=1) / max_step_rad - 1e-12).astype(np.int64))
    idx = np.repeat(np.arange(len(seg)), n)
    frac = np.concatenate([np.arange(k) / k for k in n])
    out = pts[idx] + frac[:, None] * seg[idx]
    return np.vstack([out, pts[-1:]])


def snap_to_bounds(q, lower, upper, periodic, tol_rad: float = 1e-9) -> np.ndarray:
    """
    Put rows barely outside a bounded joint's range exactly on the bound.

    Put rows that leave a bounded joint's range by at most ``tol_rad`` (rounding in the spline or
    the interpolation along a bound) exactly on the bound.

    Larger excursions are left as they are, so the bounds check rejects them.
    (m, dof) → a new (m, dof) array.
    """
    q = np.array(q, dtype=float, order="C")
    _snap_kernel(q, np.asarray(lower, dtype=float), np.asarray(upper, dtype=float),
                 np.asarray(periodic, dtype=np.bool_), float(tol_rad))
    return q


@njit(cache=True, nogil=True)
def _snap_kernel(q, lower, upper, periodic, tol_rad):
    """:func:`snap_to_bounds` in place on q (m, dof): per bounded joint, the lower bound's snap, then the upper's."""
    for r in range(q.shape[0]):
        for a in range(q.shape[1]):
            if periodic[a]:
                continue
            x = q[r, a]
            if x < lower[a] and x >= lower[a] - tol_rad:
                x = lower[a]
            if x > upper[a] and x <= upper[a] + tol_rad:
                x = upper[a]
            q[r, a] = x


def _validator(motions, lower_rad, upper_rad, periodic, step_rad):
    """Return the scene's MotionValidator: ``motions`` itself, or a CollisionChecker's with these bounds."""
    if isinstance(motions, MotionValidator):
        if lower_rad is not None or upper_rad is not None or periodic is not None:
            raise TypeError("a MotionValidator holds its bounds: give none")
        return motions if step_rad is None else motions.with_step(step_rad)
    return MotionValidator(motions, lower_rad, upper_rad, periodic,
                           DEFAULT_VERIFY_STEP_RAD if step_rad is None else step_rad)


def shortcut_indices(motions, points_rad, lower_rad=None, upper_rad=None, periodic=None,
                     verify_step_rad: float | None = None,
                     keep_clearance_m: float = 0.05, certified: bool = True,
                     polyline_check=None) -> np.ndarray:
    """
    Greedy, clearance-keeping shortcut of a verified polyline: indices of the vertices kept.

    A straight segment from vertex i to vertex j may replace the polyline between
    them when it is verified and its clearance never drops below the smaller of
    the replaced stretch's own minimum clearance and ``margin + keep_clearance_m``
    (so shortcuts do not trade the field's distance from obstacles for length).
    From each kept vertex the farthest such j is found by binary search.  Returns
    increasing indices, first and last kept.

    ``motions``: the scene's ``motion.MotionValidator`` (checks at its step unless
    ``verify_step_rad`` is given), or a ``CollisionChecker`` with the bounds.
    ``certified``: candidates certified (``MotionValidator.check``), else the quick test:
    clearance above the threshold at samples the validator's step apart along the segment
    (a sample that a clearance ball of an earlier one covers passes without being evaluated:
    the same answer).  ``polyline_check``: a ``PathCheck`` of these very rows (the certified
    check that verified the polyline): its interval clearances (the stretches' own) and
    vertex clearances are used instead of a check of the polyline here.
    """
    v = _validator(motions, lower_rad, upper_rad, periodic, verify_step_rad)
    pts = np.ascontiguousarray(points_rad, dtype=float)
    if polyline_check is None:
        polyline_check = v.check(pts, certified=certified)
    elif len(polyline_check.interval_clearance_m) != len(pts) - 1:
        raise ValueError(f"polyline_check: a check of {len(polyline_check.interval_clearance_m) + 1} rows, "
                         f"not of these {len(pts)}")
    known = polyline_check.vertex_clearance_m
    vertex_clr = np.full(len(pts), np.nan) if known is None else np.array(known, dtype=float)
    # a segment between two in-bounds points stays in bounds (the bounds are a box)
    return _shortcut(pts, polyline_check.interval_clearance_m, v.margin_m + keep_clearance_m, v.kernel_arrays,
                     v.margin_m, v.reach_m, v.step_rad, bool(certified), vertex_clr)


def _shortcut(pts, iv_clr, cap, kernel_arrays, margin_m, reach_m, step_rad, certified, vertex_clr) -> np.ndarray:
    """Run :func:`_shortcut_kernel` with its scratch (``kernel_arrays``: ``MotionValidator.kernel_arrays``)."""
    m, dof = pts.shape
    keep = np.empty(m, np.int64)
    # the quick test's samples of a segment: at most its length / step + 1, and no chord is longer
    # than the polyline (its length with a margin far above the rounding of either)
    n_samples = int(math.ceil(float(np.sum(chord_lengths_rad(pts))) * (1.0 + 1e-9) / step_rad)) + 2
    n_keep = _shortcut_kernel(pts, iv_clr, cap, *kernel_arrays, margin_m, reach_m, step_rad, certified, vertex_clr,
                              keep, np.empty((2, dof)), np.zeros(1, np.bool_), np.zeros(1), np.empty(2),
                              np.empty(n_samples, np.bool_), np.empty((2 * n_samples + 1, 2), np.int64),
                              *motion_scratch(kernel_arrays[0], kernel_arrays[2], kernel_arrays[4]))
    return keep[:n_keep].copy()


def _quick_segment_ok(points, i, j, vertex_clr, q_template, planned, lengths, checked, body, verts, starts,
                      centres, radii, threshold_m, reach_m, step_rad, q_full, pts, body_w):
    """Run :func:`_quick_segment_kernel` with its scratch (``covered``, ``queue``)."""
    seg_len = float(np.linalg.norm(points[j] - points[i]))
    n = max(1, int(math.ceil(seg_len * (1.0 + 1e-9) / step_rad))) + 1
    return _quick_segment_kernel(points, i, j, vertex_clr, q_template, planned, lengths, checked, body, verts,
                                 starts, centres, radii, threshold_m, reach_m, step_rad, q_full, pts, body_w,
                                 np.empty(n + 1, np.bool_), np.empty((2 * n + 1, 2), np.int64))


@njit(**NO_REFCOUNT)
def _quick_segment_kernel(points, i, j, vertex_clr, q_template, planned, lengths, checked, body, verts, starts,
                          centres, radii, threshold_m, reach_m, step_rad, q_full, pts, body_w, covered, queue):
    """
    Quick test of the straight segment points[i] → points[j]: clearance > threshold at its samples.

    The samples of the quick test (``certify_segments`` with ``certified`` false): at arc
    lengths k·step_rad below the length, and the end.  Evaluated ends first, then by
    bisection (coarse to fine, as OMPL's discrete motion validator), so a segment that
    collides is usually rejected after a few evaluations; a sample within the clearance ball
    (c - threshold)·ℓ/D of an evaluated one (ℓ the segment's joint-space length, D
    ``motion.sweep_m`` with ``reach_m``: the most a checked point moves along it; less 0.1 %)
    passes without being evaluated.  The answer is that of evaluating every sample.  The
    ends' clearances are read from ``vertex_clr`` where known (not NaN) and written there
    when evaluated.  Scratch: ``covered`` (≥ n_last + 1,) bool and ``queue`` (≥ 2 n_last + 1, 2)
    int64, n_last = ⌈length / step_rad⌉.
    """
    dof = points.shape[1]
    seg_len = 0.0
    for a in range(dof):
        d = points[j, a] - points[i, a]
        seg_len += d * d
    seg_len = np.sqrt(seg_len)
    span = sweep_m(points[i], points[j], reach_m)
    rad_per_m = seg_len / span if span > 0.0 else 0.0       # rad of the segment per m of motion (0: no length)
    n_last = max(1, int(np.ceil(seg_len / step_rad)))        # samples 0 .. n_last (the end)
    if n_last + 1 > covered.shape[0] or 2 * n_last + 1 > queue.shape[0]:
        raise ValueError("_quick_segment_kernel: scratch too small for the segment")
    for k in range(n_last + 1):
        covered[k] = False
    head = 0
    tail = 0
    for e in range(2):
        k = 0 if e == 0 else n_last
        if covered[k]:
            continue
        v = i if e == 0 else j
        c = vertex_clr[v]
        if np.isnan(c):
            for a in range(dof):
                q_full[planned[a]] = points[v, a]
            c = config_clearance(q_full, lengths, checked, body, verts, starts, centres, radii, pts, body_w)
            vertex_clr[v] = c
        if not c > threshold_m:
            return False
        _cover(covered, n_last, k, 0.0 if e == 0 else seg_len, 0.999 * (c - threshold_m) * rad_per_m, step_rad, seg_len)
    queue[tail, 0] = 0
    queue[tail, 1] = n_last
    tail += 1
    while head < tail:
        lo = queue[head, 0]
        hi = queue[head, 1]
        head += 1
        if hi - lo < 2:
            continue
        k = (lo + hi) // 2
        if not covered[k]:
            t = min(k * step_rad, seg_len)
            f = t / seg_len
            for a in range(dof):
                q_full[planned[a]] = points[i, a] + f * (points[j, a] - points[i, a])
            c = config_clearance(q_full, lengths, checked, body, verts, starts, centres, radii, pts, body_w)
            if not c > threshold_m:
                return False
            _cover(covered, n_last, k, t, 0.999 * (c - threshold_m) * rad_per_m, step_rad, seg_len)
        queue[tail, 0] = lo
        queue[tail, 1] = k
        queue[tail + 1, 0] = k
        queue[tail + 1, 1] = hi
        tail += 2
    return True


@njit(cache=True, nogil=True, inline="always")
def _cover(covered, n_last, k, t, radius, step_rad, seg_len):
    """Mark the samples 0 .. n_last of :func:`_quick_segment_kernel` within ``radius`` (rad) of sample k (at t)."""
    covered[k] = True
    lo = max(0, int(np.ceil((t - radius) / step_rad)))
    hi = min(n_last - 1, int(np.floor((t + radius) / step_rad)))
    for m in range(lo, hi + 1):
        covered[m] = True
    if seg_len - t <= radius:
        covered[n_last] = True


@njit(**NO_REFCOUNT)
def _shortcut_kernel(pts, iv_clr, cap, q_template, planned, lengths, checked, body, verts, starts, centres,
                     radii, margin_m, reach_m, step_rad, certified, vertex_clr, keep, seg, ok_iv, clr_iv, ends_clr,
                     covered, queue, q_full, chain, body_w):
    """
    Run the greedy binary search of :func:`shortcut_indices` (see there), in one kernel.

    The kept indices into keep (m,) int64; returns their count.  Scratch: seg (2, dof), one
    interval's certificate ok_iv (1,) bool, clr_iv (1,) and ends_clr (2,) (``certify_segments``), the
    quick test's covered and queue (:func:`_quick_segment_kernel`), the motion scratch q_full,
    chain, body_w (``motion.motion_scratch``).
    """
    m = pts.shape[0]
    n_keep = 1
    keep[0] = 0
    i = 0
    last = m - 1
    while i < last:
        lo = i + 1
        hi = last + 1                 # hi: rejected (last + 1 = none yet); lo: accepted
        j = last
        while True:
            if j == i + 1:
                good = True
            else:
                need = cap
                for k in range(i, j):
                    if iv_clr[k] < need:
                        need = iv_clr[k]
                threshold = max(margin_m, need)
                if certified:
                    for a in range(pts.shape[1]):
                        seg[0, a] = pts[i, a]
                        seg[1, a] = pts[j, a]
                    ends_clr[0] = vertex_clr[i]
                    ends_clr[1] = vertex_clr[j]
                    certify_segments(seg, q_template, planned, lengths, checked, body, verts, starts, centres,
                                     radii, threshold, reach_m, step_rad, 1e-6, ok_iv, clr_iv, True, ends_clr, True,
                                     q_full, chain, body_w)
                    vertex_clr[i] = ends_clr[0]
                    vertex_clr[j] = ends_clr[1]
                    good = ok_iv[0]
                else:
                    good = _quick_segment_kernel(pts, i, j, vertex_clr, q_template, planned, lengths, checked,
                                                 body, verts, starts, centres, radii, threshold, reach_m, step_rad,
                                                 q_full, chain, body_w, covered, queue)
            if good:
                lo = j
            else:
                hi = j
            if hi - lo <= 1:
                break
            j = (lo + hi) // 2
        keep[n_keep] = lo
        n_keep += 1
        i = lo
    return n_keep


# ---------------------------------------------------------------------- spline
def _polyline_at(pts, t_pts, t):
    """Points of the polyline (vertices pts at arc lengths t_pts) at arc lengths t."""
    out = np.empty((len(t), pts.shape[1]))
    for a in range(pts.shape[1]):
        out[:, a] = np.interp(t, t_pts, pts[:, a])
    return out


def spline_through(knots_rad, max_step_rad: float = DEFAULT_MAX_STEP_RAD, start_tangent=None):
    """
    Cubic spline (chord-length parameter, not-a-knot ends) through (k, dof) knots.

    Returns (samples (M, dof), knot_param (k' ≤ k,), sample_param (M,)): samples ≤
    max_step_rad apart, every knot a sample (exactly; a knot within ``MIN_KNOT_CHORD_RAD`` of
    the one before is dropped, never the first or the last).  ``start_tangent``:
    (dof,) a unit direction the spline leaves its first knot along (its derivative there,
    clamped; from 3 knots on), or None.
    """
    q, s, u, _ = _spline_samples(knots_rad, max_step_rad, start_tangent)
    return q, s, u


#: A knot closer than this (rad, Euclidean) to the last knot kept before it is dropped: the
#: not-a-knot spline through two knots a hair apart turns through their difference's arbitrary
#: direction.  Knots about 1 rad apart with one pair 1e-9 rad apart took up to 330 000 samples (the
#: spline swinging out and back), 1e-8: 2 400; from 1e-7 on as many as with distinct knots.
MIN_KNOT_CHORD_RAD = 1e-7


def _kept_knots(knots_rad, min_chord_rad: float = MIN_KNOT_CHORD_RAD) -> np.ndarray:
    """
    Return which rows of a polyline (k, dof) to keep: (k,) bool (the spline's knots by default).

    The first; then each farther than ``min_chord_rad`` from the last one kept; the last row
    always (in place of the last one kept when that is too close, unless that is the first).
    """
    k = np.asarray(knots_rad, dtype=float)
    keep = np.ones(len(k), dtype=bool)
    if len(k) < 2 or np.all(chord_lengths_rad(k) > min_chord_rad):
        return keep
    last = 0
    for i in range(1, len(k)):
        if np.linalg.norm(k[i] - k[last]) > min_chord_rad:
            last = i
        else:
            keep[i] = False
    if not keep[-1]:
        if last > 0:
            keep[last] = False
        keep[-1] = True
    return keep


def _spline_samples(knots_rad, max_step_rad, start_tangent=None):
    """
    Return :func:`spline_through`'s (samples, knot_param, sample_param) and each sample's knot interval.

    The knot interval (M,) int64 of sample r is the i with knot_param[i] ≤ sample_param[r] <
    knot_param[i + 1] (the last sample: the last interval).  Knots too close to the one before
    are dropped (:func:`_kept_knots`; knot_param holds the kept ones').
    """
    k = np.ascontiguousarray(knots_rad, dtype=float)
    keep = _kept_knots(k)
    if not keep.all():
        k = k[keep]
    s = arc_lengths_rad(k)
    if len(k) == 1 or s[-1] <= 1e-12:
        return k[[0, -1]].copy(), s[[0, -1]], s[[0, -1]].copy(), np.zeros(2, np.int64)
    if len(k) == 2:
        dense = densify_polyline(k, max_step_rad)
        u = arc_lengths_rad(dense)
        return dense, s, u, np.zeros(len(dense), np.int64)
    clamped = start_tangent is not None
    slope = np.ascontiguousarray(start_tangent if clamped else k[0], dtype=float)
    q, u, iv = _spline_kernel(s, k, float(max_step_rad), slope, clamped)
    return q, s, u, iv


@njit(cache=True, nogil=True)
def _spline_kernel(s, y, max_step_rad, start_slope, clamped):
    """
    Sample the not-a-knot cubic spline through y (n ≥ 3, dof) at the chord parameters s (n,).

    With ``clamped`` its derivative at the start is ``start_slope`` (dof,) instead
    (``trajectory.clamped_start_slopes``).
    Each knot interval i is sampled on its own: at N_i equal parameter steps from s[i] (its
    knot, y[i] itself) towards s[i + 1], N_i = ⌈(s[i+1] − s[i]) / max_step_rad⌉ at first and,
    while two consecutive samples of it (its last with the next knot) are farther apart than
    ``max_step_rad`` (Euclidean), ⌈N_i·(largest step / max_step_rad)·1.05⌉ + 1; the last sample
    is the last knot.  So every knot is a sample and a stretch where the spline runs faster
    than its chord parameter (a short interval's overshoot near a corner) is sampled finer
    without making the rest finer.  Each sample is the cubic of its knot interval by Horner's
    rule in the interval's local parameter.  Returns (samples (N, dof), sample parameters (N,),
    knot interval of each (N,): the last sample's is the last interval).
    """
    n, dof = y.shape
    m = clamped_start_slopes(s, y, start_slope) if clamped else not_a_knot_slopes(s, y)
    c0 = np.empty((n - 1, dof))
    c1 = np.empty((n - 1, dof))
    for i in range(n - 1):
        hermite_coefficients(s, y, m, i, c0[i], c1[i])
    counts = np.empty(n - 1, np.int64)
    prev = np.empty(dof)
    for i in range(n - 1):
        h = s[i + 1] - s[i]
        cnt = max(1, int(np.ceil(h / max_step_rad)))
        while True:
            largest = 0.0
            for a in range(dof):
                prev[a] = y[i, a]
            for j in range(1, cnt + 1):
                x = j * (h / cnt)
                d2 = 0.0
                for a in range(dof):
                    v = y[i + 1, a] if j == cnt else ((c0[i, a] * x + c1[i, a]) * x + m[i, a]) * x + y[i, a]
                    d = v - prev[a]
                    d2 += d * d
                    prev[a] = v
                largest = max(largest, np.sqrt(d2))
            if largest <= max_step_rad:
                break
            cnt = int(np.ceil(cnt * largest / max_step_rad * 1.05)) + 1
        counts[i] = cnt
    total = 1
    for i in range(n - 1):
        total += counts[i]
    q = np.empty((total, dof))
    u = np.empty(total)
    iv = np.empty(total, np.int64)
    r = 0
    for i in range(n - 1):
        h = s[i + 1] - s[i]
        cnt = counts[i]
        for j in range(cnt):
            x = j * (h / cnt)
            u[r] = s[i] + x
            iv[r] = i
            for a in range(dof):
                q[r, a] = y[i, a] if j == 0 else ((c0[i, a] * x + c1[i, a]) * x + m[i, a]) * x + y[i, a]
            r += 1
    u[r] = s[n - 1]
    iv[r] = n - 2
    for a in range(dof):
        q[r, a] = y[n - 1, a]
    return q, u, iv


#: A failing knot interval shorter than this many sample steps is not split (in any round: the
#: halving before it split it in the first; the spline already follows the polyline there at the
#: samples' resolution, and where it fails the polyline is what passes), nor split into parts
#: shorter than it.
FINEST_KNOT_INTERVAL = 1.0 / 16.0


def _split(ta, tb, rounds, finest):
    """
    Return the knots that split a failing knot interval [ta, tb] (no polyline vertex in it) in round ``rounds``.

    In 2 parts in the first round (its midpoint), then 4, then 8, by the refinement's round, not
    by how often this interval was split (contact starts' refinements 9 -> 4 rounds: a stretch
    that fails again needs the spline close to the polyline), never into parts shorter than
    ``finest`` but in two.
    """
    parts = max(2, min(2 ** min(rounds + 1, 3), int((tb - ta) / finest)))
    return [0.5 * (ta + tb)] if parts == 2 else list(ta + (tb - ta) * np.arange(1, parts) / parts)


def _refined_spline(v, poly, t_poly, t_knots, max_step_rad, max_rounds, cancel, certified, start_tangent=None):
    """
    Spline through polyline points at arc lengths t_knots, refined where it collides.

    ``t_poly``: the polyline's arc length at each vertex (``trajectory.arc_lengths_rad``);
    ``start_tangent``: as :func:`spline_through`'s.  Returns (samples, knots, check, rounds) of
    the first clean spline, or None.
    """
    t_knots = np.unique(t_knots)
    finest = max_step_rad * FINEST_KNOT_INTERVAL
    for rounds in range(max_rounds + 1):
        if cancel is not None and cancel.is_set():
            return None
        knots = _polyline_at(poly, t_poly, t_knots)
        keep = _kept_knots(knots)      # the spline's knots, so that its knot intervals are these
        if not keep.all():
            t_knots, knots = t_knots[keep], knots[keep]
        # vertices map exactly onto themselves (np.interp is exact at its nodes)
        samples, s_knots, s_samples = spline_through(knots, max_step_rad, start_tangent)
        samples = snap_to_bounds(samples, v.lower_rad, v.upper_rad, v.periodic)
        chk = v.check(samples, certified=certified)
        if chk.ok:
            return samples, knots, chk, rounds
        bad = np.flatnonzero(~chk.interval_ok)
        # knot intervals holding a bad sample interval (by the spline parameter)
        bad_iv = np.unique(np.clip(np.searchsorted(s_knots, s_samples[bad], side="right") - 1,
                                   0, len(s_knots) - 2))
        new_t = []
        for iv in bad_iv:
            for j in (iv - 1, iv, iv + 1):        # the corner's neighbours bend it too
                if not 0 <= j < len(t_knots) - 1:
                    continue
                ta, tb = t_knots[j], t_knots[j + 1]
                inner = t_poly[(t_poly > ta + 1e-12) & (t_poly < tb - 1e-12)]
                if len(inner):
                    new_t.extend(inner)
                elif j == iv and tb - ta >= finest:
                    new_t.extend(_split(ta, tb, rounds, finest))
        if not new_t:
            return None
        t_knots = np.unique(np.concatenate([t_knots, new_t]))
    return None


def smooth_path(motions, waypoints_rad, lower_rad=None, upper_rad=None, periodic=None, *,
                shortcut: bool = True, knot_stride: int = 2, keep_clearance_m: float = 0.05,
                max_step_rad: float = DEFAULT_MAX_STEP_RAD,
                verify_step_rad: float | None = None,
                quick_step_rad: float = QUICK_STEP_RAD,
                max_rounds: int = 12, cancel=None, waypoint_check=None, start_tangent=None) -> SmoothPath | None:
    """
    Smooth a polyline into a dense path whose certified check passed.

    Args:
        motions: the scene's ``motion.MotionValidator`` (exact geometry, the scene's margin,
            the joint bounds: bounded joints must stay in; its step certifies unless
            ``verify_step_rad`` is given), or a ``CollisionChecker`` with
            ``lower_rad, upper_rad, periodic``.
        waypoints_rad: (m, dof) exact start, grid nodes, exact goal; unwrapped
            (see ``joint_space.unwrap_path``) and joined by straight segments.
        shortcut: first try a spline along the greedily shortcut polyline.
        keep_clearance_m: shortcuts keep at least margin + this (or the replaced
            stretch's own clearance, if smaller), metres.
        knot_stride: the paper's "every second node" (2).
        quick_step_rad: spacing of the quick test of candidates.
        waypoint_check: the certified check (``MotionValidator.check``) of these very
            waypoints, if the caller made one: the shortcut pass uses its interval and vertex
            clearances instead of checking the polyline again.
        start_tangent: (dof,) the direction the path must leave its start along (a plan from
            a moving arm: its velocity), or None.  The splines are clamped to it (their
            derivative by the chord length: its unit vector); the polyline, the last resort,
            is not.

    Returns
    -------
        the first result of: spline along the shortcut polyline, spline through every
        ``knot_stride``-th waypoint (the paper), the polyline itself; None when even the
        polyline fails (or on cancel).  Candidates (shortcuts, spline refinements) are
        chosen by the quick test at ``quick_step_rad``; the chosen path alone is then
        certified (``MotionValidator.check``, reusing the clearances the quick test
        evaluated at the path's own rows: the certificate needs only the clearance at each
        of its samples, whoever evaluated it), and only if that fails is the choice made
        again with certified tests throughout.  ``n_checked`` and ``min_clearance_m`` are
        the certified check's.

    """
    v = _validator(motions, lower_rad, upper_rad, periodic, verify_step_rad)
    start_tangent = start_direction(start_tangent, np.shape(waypoints_rad)[-1])
    first = _smooth(v.with_step(quick_step_rad), waypoints_rad, shortcut, knot_stride,
                    keep_clearance_m, max_step_rad, max_rounds, cancel, False, waypoint_check, start_tangent)
    if first is not None:
        path, knots, method, rounds, quick = first
        chk = v.check(path, vertex_clearance_m=quick)     # the quick check's vertices reused
        if chk.ok:
            return SmoothPath(path, knots, method, chk.min_clearance_m, path_length_rad(path),
                              rounds, chk.n_checked)
    if cancel is not None and cancel.is_set():
        return None
    again = _smooth(v, waypoints_rad, shortcut, knot_stride, keep_clearance_m, max_step_rad,
                    max_rounds, cancel, True, waypoint_check, start_tangent)
    if again is None:
        return None
    path, knots, method, rounds, known = again
    chk = v.check(path, vertex_clearance_m=known)
    if not chk.ok:          # the choice was certified piece by piece: not expected
        return None
    return SmoothPath(path, knots, method, chk.min_clearance_m, path_length_rad(path), rounds,
                      chk.n_checked)


@njit(cache=True, nogil=True)
def _median(x):
    """Return ``np.median`` of a 1-D float array (numba's: the middle value, or the mean of the middle two)."""
    return np.median(x)


@njit(cache=True, nogil=True)
def _stretch_knots(t, spacing):
    """
    Return knot parameters along a polyline: each stretch t[k] .. t[k + 1] evenly split, about ``spacing`` apart.

    t (m ≥ 2,) increasing arc lengths of the polyline's vertices.  Stretch k gets
    ``np.linspace(t[k], t[k + 1], max(2, ⌈(t[k + 1] - t[k]) / max(spacing, 1e-9)⌉ + 1))``
    by NumPy's arithmetic (i·step + start, the end exact; (i / div)·delta where the step
    is 0), and the stretches follow one another, ends repeated: NumPy's concatenation of
    those linspaces, (Σ counts,).
    """
    sp = max(spacing, 1e-9)
    counts = np.empty(t.shape[0] - 1, np.int64)
    total = 0
    for k in range(t.shape[0] - 1):
        counts[k] = max(2, int(np.ceil((t[k + 1] - t[k]) / sp)) + 1)
        total += counts[k]
    out = np.empty(total)
    r = 0
    for k in range(t.shape[0] - 1):
        a = t[k]
        delta = t[k + 1] - a
        div = counts[k] - 1
        step = delta / div
        for i in range(div):
            out[r + i] = (i * step if step != 0.0 else (i / div) * delta) + a
        out[r + div] = t[k + 1]
        r += div + 1
    return out


def start_direction(direction, dof: int):
    """Return a start direction (dof,) as a unit vector, None for None (ValueError naming ``start_tangent``)."""
    if direction is None:
        return None
    d = np.array(direction, dtype=float).reshape(-1)
    norm = float(np.linalg.norm(d)) if d.shape == (dof,) else math.nan
    if not (math.isfinite(norm) and norm > 0.0):
        raise ValueError(f"start_tangent: expected {dof} finite values, not all 0, got {d.tolist()}")
    return d / norm


def _smooth(v, waypoints_rad, shortcut, knot_stride, keep_clearance_m, max_step_rad, max_rounds, cancel,
            certified, waypoint_check=None, start_tangent=None):
    """
    Choose a path with tests at the step of ``v`` (certified or quick).

    Returns (path, knots, method, rounds, vertex clearances), or None.  The vertex
    clearances (one per path row, NaN where not evaluated) are those of the test that
    accepted the path, for the final check to reuse.

    See :func:`smooth_path`.
    """
    w = np.ascontiguousarray(waypoints_rad, dtype=float)
    ends = w[[0, -1]].copy()
    keep = _kept_knots(w, 1e-12)        # repeated rows dropped, the exact ends kept
    if not keep.all():
        w = w[keep]
        waypoint_check = None           # a check of other rows
    steps = chord_lengths_rad(w)
    if len(w) == 1 or np.linalg.norm(w[-1] - w[0]) <= 1e-12:    # start == goal: two exact rows
        return ends, ends.copy(), "polyline", 0, None

    def attempts():                     # each made only when the one before failed
        if shortcut and len(w) > 2:
            keep_idx = shortcut_indices(v, w, keep_clearance_m=keep_clearance_m, certified=certified,
                                        polyline_check=waypoint_check)
            sc = w[keep_idx]
            t_sc = arc_lengths_rad(sc)
            # knots: the shortcut vertices plus points about two grid steps apart on
            # long straight stretches, so corners are rounded but not cut
            yield "shortcut_spline", sc, t_sc, _stretch_knots(t_sc, knot_stride * _median(steps))
        t_w = arc_lengths_rad(w)
        stride_idx = np.unique(np.concatenate([np.arange(0, len(w), max(1, knot_stride)), [len(w) - 1]]))
        yield "spline", w, t_w, t_w[stride_idx]

    for method, poly, t_poly, t_knots in attempts():
        res = _refined_spline(v, poly, t_poly, t_knots, max_step_rad, max_rounds, cancel, certified, start_tangent)
        if res is not None:
            samples, knots, chk, rounds = res
            known = None if chk.vertex_clearance_m is None else chk.vertex_clearance_m.copy()
            for k, end in ((0, w[0]), (-1, w[-1])):
                if known is not None and not (samples[k] == end).all():
                    known[k] = np.nan           # moved: evaluated again
            samples[0], samples[-1] = w[0], w[-1]
            return samples, knots, method, rounds, known
        if cancel is not None and cancel.is_set():
            return None
    dense = snap_to_bounds(densify_polyline(w, max_step_rad), v.lower_rad, v.upper_rad, v.periodic)
    chk = v.check(dense, certified=certified)
    if not chk.ok:
        return None
    return dense, w.copy(), "polyline", 0, chk.vertex_clearance_m


def warm_up() -> None:
    """
    Compile (or load from numba's cache) this module's kernels: spline, knots, bounds' snap and the shortcut pass.

    On a made-up three-link arm (planned joints 1 and 2) and one square obstacle, with the
    argument types of a plan; a coarse warm-up plan may not reach them (a straight shortcut
    needs no spline).
    """
    _spline_samples(np.radians([[0.0, 0.0], [20.0, 10.0], [40.0, 5.0], [55.0, -3.0]]), DEFAULT_MAX_STEP_RAD)
    _stretch_knots(np.array([0.0, 0.1, 0.3]), 2 * _median(np.array([0.1, 0.2])))
    square = np.array([[1.0, 0.0], [0.0, 1.0], [-1.0, 0.0], [0.0, -1.0]])
    arrays = (np.zeros(3), np.array([1, 2], dtype=np.int64), np.array([1.4, 2.0, 2.0]),
              np.array([1, 2], dtype=np.int64), square.copy(), square + 6.0, np.array([0, 4], dtype=np.int64),
              np.array([[6.0, 6.0]]), np.array([1.0]))
    pts = np.radians([[0.0, 0.0], [5.0, 5.0], [10.0, 5.0], [15.0, 0.0]])
    snap_to_bounds(pts, np.zeros(2), np.ones(2), (False, True))
    iv_clr = np.ones(len(pts) - 1)
    reach_m = np.array([4.0, 2.0])
    for certified in (False, True):
        _shortcut(pts, iv_clr, 0.07, arrays, 0.02, reach_m, QUICK_STEP_RAD, certified, np.full(len(pts), np.nan))
