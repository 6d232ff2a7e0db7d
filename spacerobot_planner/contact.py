"""
Leaving a contact: from a start that touches an obstacle to the nearest free posture.

After a capture the arm holds the handle; when the target then moves a little, the
current posture overlaps it and no certified motion starts there.  This stage walks out
along increasing *signed distance* (the clearance outside the obstacles, minus the
penetration depth inside them) in small joint steps until the posture is free with a
little room to spare; the planner certifies everything after that.  The walk itself is
not certified (it starts in collision): it is bounded (``max_length_rad``), reported
apart, and only allowed when the start is inside by at most ``max_penetration_m``.

The walk is one numba kernel (:func:`_walk_out`): each step's candidates' clearances, and their
penetration depths only where none of them is clear (a clear one is then the step's choice),
each depth given up once it reaches the least of the step so far (that candidate cannot be the
choice): the walks of the NumPy loop it replaced, to the bit (1 560 walks from contact starts of
the paper, servicer and random scenes), 0.37 / 1.15 / 1.86 → 0.09 / 0.36 / 1.09 ms (median /
p90 / max, 540 walks from the paper and servicer scenes' contact starts).  The penetration depth
(:func:`_config_depth`) takes about 2.4 us a posture (12 us while it visited every link sample:
now only those where the link crosses a polygon's box, and of those only where the depth so far
can be passed, by the distance's Lipschitz bound, each coarse sample evaluated once; a NumPy loop
took 350 us, so a walk out of a deep contact took up to 70 ms; the same depths to the bit on 4 800
random postures of random scenes; a link's length is sqrt(dx² + dy²), one ulp from NumPy's norm
at times, which could move the 2 mm sample count only where length / 2 mm is within an ulp of an
integer).

Configurations are planned-joint vectors (rad); lengths in metres.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass, replace

import numpy as np
from numba import njit

from .collision import (NO_REFCOUNT, CollisionChecker, config_clearance, link_points, point_in_polygon,
                        point_segment_dist2, rotate_body)
from .joint_space import deg_text, row_within_bounds
from .motion import MotionValidator
from .scene import Scene

__all__ = ["penetration_depth_m", "penetration_depths_m", "signed_distance_m", "Exit", "leave_contact"]

_SAMPLE_M = 0.002      # spacing of the link samples of the penetration depth (error ≤ 1 mm)


#: the penetration depth's first pass visits every this many link samples (:func:`_segment_depth`)
_COARSE = 16


@njit(cache=True, nogil=True, inline="always")
def _sample_depth(i, n, step, ax, ay, bx, by, lox, loy, hix, hiy, verts, start, stop):
    """Return sample i's distance to the polygon's edges when it is inside (``_segment_depth``), else -1."""
    t = i * step if i < n - 1 else 1.0
    px, py = ax + t * (bx - ax), ay + t * (by - ay)
    if px < lox or px > hix or py < loy or py > hiy:
        return -1.0
    if not point_in_polygon(px, py, verts, start, stop):
        return -1.0
    best = np.inf
    j = stop - 1
    for v in range(start, stop):
        best = min(best, point_segment_dist2(px, py, verts[j, 0], verts[j, 1], verts[v, 0], verts[v, 1]))
        j = v
    return np.sqrt(best)


@njit(cache=True, nogil=True)
def _segment_depth(ax, ay, bx, by, n, verts, start, stop, floor, coarse, cap):
    """
    Return the larger of ``floor`` and how deep segment AB reaches into polygon verts[start:stop], metres.

    AB's ``n`` samples ``a + t (b - a)``, t = 0, 1/(n-1), ..., 1 (NumPy's ``linspace``), those in
    the polygon's bounding box tested for inside (even-odd, ``collision.point_in_polygon``);
    the largest distance from an inside sample to the polygon's edges.  Only the samples whose t
    lies where the line crosses the box (one more on either side, for rounding) are visited:
    the others are outside it (a link's 750 samples against a box it crosses on a few dozen).
    A point's distance to the edges changes by at most the distance it moves (and is at most its
    distance to any point outside), so first every :data:`_COARSE`-th sample is taken; then, between
    two of them, the samples only where that bound reaches past the depth so far (less 1e-12 m for
    rounding), and after an inside sample at distance d none within ``depth − d`` of it: the same
    result as every sample's.  ``coarse``: scratch, at least ``(n + _COARSE - 1) // _COARSE + 1`` long
    (the coarse samples' distances, each evaluated once).  Once the depth reaches ``cap`` it is
    returned as it is (≥ cap; below ``cap`` the result is the one ``cap = inf`` gives).
    """
    lox, loy = verts[start, 0], verts[start, 1]
    hix, hiy = lox, loy
    for v in range(start + 1, stop):
        lox, hix = min(lox, verts[v, 0]), max(hix, verts[v, 0])
        loy, hiy = min(loy, verts[v, 1]), max(hiy, verts[v, 1])
    step = 1.0 / (n - 1)
    depth = floor
    apart = math.sqrt((bx - ax) ** 2 + (by - ay) ** 2) * step      # between two samples, m
    # the t where a + t (b - a) is in the box: [t0, t1] (empty: t0 > t1)
    t0, t1 = 0.0, 1.0
    for lo, hi, a0, d in ((lox, hix, ax, bx - ax), (loy, hiy, ay, by - ay)):
        if d != 0.0:
            ta, tb = (lo - a0) / d, (hi - a0) / d
            t0, t1 = max(t0, min(ta, tb)), min(t1, max(ta, tb))
        elif a0 < lo or a0 > hi:
            t0 = 2.0
    if not t0 <= t1:
        return depth
    i_lo = max(0, int(math.floor(t0 * (n - 1))) - 1)
    i_hi = min(n - 1, int(math.ceil(t1 * (n - 1))) + 1)
    m = (i_hi - i_lo + _COARSE - 1) // _COARSE       # blocks; coarse samples i_lo + k·_COARSE and i_hi
    # their distances, 0 outside (the bound from it)
    for k in range(m + 1):
        d = _sample_depth(min(i_lo + k * _COARSE, i_hi), n, step, ax, ay, bx, by, lox, loy, hix, hiy, verts, start,
                          stop)
        depth = max(depth, d)
        if depth >= cap:
            return depth
        coarse[k] = max(d, 0.0)
    for k in range(m):
        a, b = i_lo + k * _COARSE, min(i_lo + (k + 1) * _COARSE, i_hi)
        d_a, d_b = coarse[k], coarse[k + 1]
        # the most a sample between a and b can be: within (d_a + d_b + (b - a)·apart) / 2
        if 0.5 * (d_a + d_b + (b - a) * apart) < depth - 1e-12:
            continue
        i = a + 1
        while i < b:
            d = _sample_depth(i, n, step, ax, ay, bx, by, lox, loy, hix, hiy, verts, start, stop)
            i += 1
            if d < 0.0:
                continue
            depth = max(depth, d)
            if depth >= cap:
                return depth
            gap = depth - d - 1e-12
            if gap > 0.0 and apart > 0.0:
                i += int(min(gap / apart, float(n)))
    return depth


@njit(**NO_REFCOUNT)
def _config_depth(q_full, lengths, checked, body, verts, starts, sample_m, pts, body_w, coarse, cap):
    """
    Return the penetration depth of the full configuration ``q_full``, metres, or a value ≥ ``cap``.

    The checked links, each sampled every ``sample_m`` at most, against the body posed at
    the attitude ``q_full[0]`` and the packed obstacles (``scene.pack_polygons``); scratch
    pts (n_links + 1, 2), body_w like body, coarse (:func:`_coarse_scratch`).  The depth so far
    only grows, link by link and polygon by polygon: once it reaches ``cap`` the rest is not
    evaluated and that partial depth (≥ cap) is returned; below ``cap`` the depth is the one
    ``cap = inf`` gives, to the bit.
    """
    link_points(q_full, lengths, pts)
    rotate_body(body, q_full[0], body_w)
    depth = 0.0
    for c in range(checked.shape[0]):
        k = checked[c]
        ax, ay, bx, by = pts[k, 0], pts[k, 1], pts[k + 1, 0], pts[k + 1, 1]
        n = max(2, int(math.ceil(math.sqrt((bx - ax) ** 2 + (by - ay) ** 2) / sample_m)) + 1)
        depth = _segment_depth(ax, ay, bx, by, n, body_w, 0, body_w.shape[0], depth, coarse, cap)
        if depth >= cap:
            return depth
        for p in range(starts.shape[0] - 1):
            depth = _segment_depth(ax, ay, bx, by, n, verts, starts[p], starts[p + 1], depth, coarse, cap)
            if depth >= cap:
                return depth
    return depth


@njit(**NO_REFCOUNT)
def _depths_into(out, q_full, lengths, checked, body, verts, starts, sample_m, pts, body_w, coarse):
    """Fill out (N,) with the penetration depth of each full configuration q_full[i], metres (:func:`_config_depth`)."""
    for i in range(q_full.shape[0]):
        out[i] = _config_depth(q_full[i], lengths, checked, body, verts, starts, sample_m, pts, body_w, coarse,
                               np.inf)


#: :func:`leave_contact` walks in chunks of at most this many steps (its default 30° is 120 steps)
WALK_CHUNK = 256
#: :func:`_walk_out`'s endings: the room was reached, no candidate increased the signed distance,
#: no candidate within the bounds, the steps ran out (these two: the caller checks the last row)
_REACHED, _NO_INCREASE, _NO_CANDIDATE, _STEPS_OUT = 0, 1, 2, 3


@njit(**NO_REFCOUNT)
def _walk_out(sd0, dirs, lower, upper, periodic, template, planned, lengths, checked, body, verts, starts, centres,
              radii, sample_m, target_m, path, sds, cand, clr, q_full, pts, body_w, coarse):
    """
    Walk from ``path[0]`` (signed distance ``sd0``) until the signed distance is at least ``target_m``.

    Each step takes, among ``path[k] + dirs[d]`` (dirs (D, dof), rad; those within the bounds:
    lower, upper (dof,), a periodic joint has none), the first with the largest signed distance
    (the clearance where it is positive, else minus the penetration depth; a NaN clearance counts
    0), and must increase it.  ``template`` (n_joints,): the full configuration's locked values,
    ``planned`` (dof,) the planned joints' indices in it; the checker's packed arrays.  Writes the
    rows into path (S + 1, dof) and their signed distances into sds (S + 1,), at most S steps;
    scratch cand (D, dof), clr (D,), q_full like template, pts, body_w, coarse as
    :func:`_config_depth`'s.  Returns (rows written, ending: ``_REACHED`` .. ``_STEPS_OUT``).
    """
    n_steps = path.shape[0] - 1
    dof = path.shape[1]
    sds[0] = sd0
    k = 0
    for _ in range(n_steps):
        if sds[k] >= target_m:
            return k + 1, _REACHED
        m = 0                                   # the candidates within the bounds, in order
        for d in range(dirs.shape[0]):
            for a in range(dof):
                cand[m, a] = path[k, a] + dirs[d, a]
            if row_within_bounds(cand[m], lower, upper, periodic):
                m += 1
        if m == 0:
            return k + 1, _NO_CANDIDATE
        for i in range(template.shape[0]):
            q_full[i] = template[i]
        best, best_sd = -1, -np.inf
        for j in range(m):
            for a in range(dof):
                q_full[planned[a]] = cand[j, a]
            clr[j] = config_clearance(q_full, lengths, checked, body, verts, starts, centres, radii, pts, body_w)
            if clr[j] > 0.0 and clr[j] > best_sd:
                best, best_sd = j, clr[j]
        if best < 0:                            # none clear: a NaN clearance counts 0, a touching one -depth
            for j in range(m):
                if clr[j] <= 0.0:
                    for a in range(dof):
                        q_full[planned[a]] = cand[j, a]
                    cap = -best_sd              # a depth at or past it cannot be the choice
                    depth = _config_depth(q_full, lengths, checked, body, verts, starts, sample_m, pts, body_w,
                                          coarse, cap)
                    if depth < cap:
                        best, best_sd = j, -depth
                elif not clr[j] > 0.0 and 0.0 > best_sd:
                    best, best_sd = j, 0.0
        if not best_sd > sds[k]:
            return k + 1, _NO_INCREASE
        k += 1
        for a in range(dof):
            path[k, a] = cand[best, a]
        sds[k] = best_sd
    return k + 1, _STEPS_OUT


def penetration_depths_m(checker, q) -> np.ndarray:
    """
    Return how deep the checked links of each planned configuration reach into the body or an obstacle, metres.

    q (N, dof) planned configurations (rad) → (N,): for each, the largest distance from a link
    point inside a polygon (the spacecraft body at the configuration's attitude, or an
    obstacle) to that polygon's boundary (0 when no link point is inside).  Links are sampled
    every 2 mm, so each depth is exact to within 1 mm.  ``checker``: the scene's
    ``collision.CollisionChecker`` (its packed geometry).
    """
    q_full = np.ascontiguousarray(checker.robot.full(np.atleast_2d(np.asarray(q, dtype=float))))
    out = np.empty(q_full.shape[0])
    _depths_into(out, q_full, checker.lengths, checker.checked, checker.body, checker.verts, checker.starts,
                 _SAMPLE_M, np.empty((checker.lengths.shape[0] + 1, 2)), np.empty_like(checker.body),
                 _coarse_scratch(checker.lengths))
    return out


def _coarse_scratch(lengths) -> np.ndarray:
    """Return :func:`_segment_depth`'s scratch for links of ``lengths`` (m): the longest one's coarse samples."""
    longest = float(np.max(lengths)) if len(lengths) else 0.0
    n = max(2, int(math.ceil(longest / _SAMPLE_M)) + 1) + 1      # _depths_into's count, one more for rounding
    return np.empty((n + _COARSE - 1) // _COARSE + 2)


def penetration_depth_m(checker, q) -> float:
    """Return how deep the checked links of ``q`` (dof,) reach in, metres (:func:`penetration_depths_m`)."""
    return float(penetration_depths_m(checker, np.asarray(q, dtype=float)[None, :])[0])


def signed_distance_m(checker, q) -> float:
    """Clearance of ``q`` when the links touch nothing, else minus the penetration depth, m."""
    c = float(checker.clearance_m(q))
    return c if c > 0.0 else -penetration_depth_m(checker, q)


@dataclass(frozen=True, eq=False)
class Exit:
    """
    The way out of a contact.

    Attributes
    ----------
        ok: a free posture was reached within the bounds.
        path_rad: (K, dof) from the start (first row, exact) to the free posture (last
            row), consecutive rows ``step_rad`` apart, signed distance increasing.
        start_penetration_m: the start's penetration depth, metres.
        signed_distance_m: (K,) signed distance along ``path_rad``.
        reason: why not (None when ok).

    """

    ok: bool
    path_rad: np.ndarray
    start_penetration_m: float
    signed_distance_m: np.ndarray
    reason: str | None = None


def leave_contact(motions, start_rad, *, max_penetration_m: float,
                  room_m: float = 0.01, step_rad: float = math.radians(0.25),
                  max_length_rad: float = math.radians(30.0), hit: str = "an obstacle") -> Exit:
    """
    Walk from a colliding ``start_rad`` to a posture with clearance ≥ margin + ``room_m``.

    ``motions``: the scene's ``motion.MotionValidator`` (its checker and joint bounds).

    Each step moves ``step_rad`` (joint-space norm) towards the neighbour, among the
    3^dof − 1 directions of the joint-space grid, with the largest signed distance, and
    must increase it; joint bounds are kept.  Refused (``ok`` False) when the start is
    deeper than ``max_penetration_m``, when no direction increases the signed distance,
    or after ``max_length_rad``.  ``hit``: what the start's links reach into, for the reason
    (:func:`what_is_hit`).
    """
    checker = motions.checker
    q = np.asarray(start_rad, dtype=float)
    dof = len(q)
    margin = checker.margin_m
    sd0 = signed_distance_m(checker, q)
    depth = max(0.0, -sd0)
    dirs = np.array([d for d in itertools.product((-1.0, 0.0, 1.0), repeat=dof) if any(d)])
    dirs = step_rad * dirs / np.linalg.norm(dirs, axis=1, keepdims=True)
    if depth > max_penetration_m:
        return Exit(False, q[None, :].copy(), depth, np.array([sd0]),
                    f"the links reach {depth:.3f} m into {hit}, more than "
                    f"planner.max_start_penetration_m = {max_penetration_m} m")
    left = max(0, int(math.ceil(max_length_rad / step_rad)))           # steps allowed
    scratch = (np.empty_like(dirs), np.empty(len(dirs)), np.empty(checker.robot.n_joints),
               np.empty((checker.lengths.shape[0] + 1, 2)), np.empty_like(checker.body),
               _coarse_scratch(checker.lengths))
    rows, sd_rows, ending = [q[None, :]], [np.array([sd0])], _STEPS_OUT
    while True:                 # in chunks of WALK_CHUNK steps (a long max_length_rad allocates as it goes)
        chunk = min(left, WALK_CHUNK)
        got = np.empty((chunk + 1, dof))
        got[0] = rows[-1][-1]
        got_sd = np.empty(chunk + 1)
        k, ending = _walk_out(sd_rows[-1][-1], dirs, motions.lower_rad, motions.upper_rad,
                              np.array(motions.periodic, np.bool_), *motions.kernel_arrays, _SAMPLE_M,
                              margin + room_m, got, got_sd, *scratch)
        rows.append(got[1:k])
        sd_rows.append(got_sd[1:k])
        left -= k - 1
        if ending != _STEPS_OUT or left <= 0:
            break
    path, sds = np.concatenate(rows), np.concatenate(sd_rows)
    if ending == _NO_INCREASE:
        return Exit(False, path, depth, sds, f"no joint motion increases the clearance from {deg_text(path[-1])}")
    if ending == _REACHED or sds[-1] >= margin + room_m:
        return Exit(True, path, depth, sds)
    return Exit(False, path, depth, sds,
                f"no free posture within {math.degrees(max_length_rad):.0f}° of joint motion "
                f"(clearance {max(sds[-1], 0.0):.3f} m after it)")


def what_is_hit(robot, scene, q_rad) -> tuple:
    """
    Name what posture ``q_rad`` (planned joints, rad) comes within the safety margin of, for a reason.

    A tuple of "the spacecraft body", "the target body", "debris polygon k" (k: its index in the
    scene's obstacles); empty when none is alone.  Each is the scene's checker with
    that obstacle alone (the spacecraft body is in every one: an obstacle is named where its
    clearance is below the body's, or the body is clear).
    """
    q = np.asarray(q_rad, dtype=float)
    margin = scene.safety_margin_m
    alone = Scene(target=None, debris_m=(), safety_margin_m=margin)     # the spacecraft body only

    def clearance(sc) -> float:
        return float(CollisionChecker(robot, sc).clearance_m(q))

    body = clearance(alone)
    names = ["the spacecraft body"] if not body > margin else []
    others = ([("the target body", replace(alone, target=scene.target))] if scene.target is not None else [])
    others += [(f"debris polygon {k}", replace(alone, debris_m=(poly,))) for k, poly in enumerate(scene.debris_m)]
    for name, sc in others:
        d = clearance(sc)
        if not d > margin and (d < body or body > margin):
            names.append(name)
    return tuple(names)


def warm_up(robot, scene) -> None:
    """Compile (or load from numba's cache) the walk's and the depth's kernels (a plan from a contact runs them)."""
    motions = MotionValidator.for_scene(robot, scene)
    q = np.asarray(robot.planned_lower_rad, dtype=float)
    penetration_depths_m(motions.checker, q[None, :])
    leave_contact(motions, q, max_penetration_m=np.inf, max_length_rad=1e-3)
