"""
The colliding grid edges of a whole grid along each planned joint but the last, from obstacles swept about the joint.

A repair (``pipeline.PlanRun.cut_or_block``) cuts the grid edges whose straight motion
collides from the field's graph.  The sheet search (:mod:`.repair`) finds them edge by edge
around the node where the descent was blocked, and a grid whose obstacles are thinner than
its step in several places (a 10° attitude step moves a 3.5 m arm's tip 0.6 m) needs one
repair, one field solve, per sheet.  This module finds them all at once, along every axis
whose joint is not the chain's last (the attitude and the shoulder of a 3-joint grid),
in about the time of one C-space build per axis.

The geometry.  Along an axis with joint j, a grid edge moves joint j by the axis step Δ: the
links from j on turn by Δ about joint j's point P (the links before j, the rest of the chain
and, for j ≥ 1, the body stay put).  In the frame of the turning links, every obstacle (and,
for j ≥ 1, the body) turns by −Δ about P.  Where both ends of the edge are clear, the motion
collides only if the links come within the margin m of the region an obstacle's boundary
sweeps, and every point p of it sweeps an arc whose chord from p to its turned copy lies in
the convex hull H of the polygon and its turned copy (a non-convex polygon's concavities
filled: one hull per polygon row-tests faster than one per edge, though it lets more nodes
through to the edge tests); the arc is no farther than its sagitta
r (1 − cos Δ/2) from the chord (r: the point's distance from P, at most the turning links'
reach: a polygon beyond it is left out).  So the edge collides only
if, at its lower node, the turning links come within m + s of some H (s: the largest
sagitta), a test the C-space's row kernel (``cspace._fill_rows``) makes for every node of
the grid with the hulls as its polygons: one set of hulls per value of the axes before the
axis (they fix P), none for the attitude's (P is the origin).  The nodes that pass are the
candidates (a superset: the hull covers the sweep with a sliver to spare); each candidate
edge between two free nodes is then tested as the sheet search tests its edges
(``motion.segment_free_from``, the quick test at the scene's margin), so the edges returned
are the ones a sheet search would cut, on every axis but the last.

The last axis (the joint that turns the last link alone) is left to the sheet search: its
pivot moves with every other joint, so it would take a set of hulls per row.

The rows and the tests run on numba's threads where the calling thread has more than one, in
that thread where it has one (each row, each edge on its own; the edges sorted at the end: the
same edges either way, on any number of threads).  The planner gives the stage the cores other
work leaves, on every grid (``cores.fit_threads(any_size=True)``): on a team of numba's two
threads, a grid of 36³ repaired in 137 ms instead of 14.6 ms while another process kept one of
the development VM's two cores busy (each of the four parallel loops waited about 32 ms, a time
slice, for the team member that had lost its core; ``bench scenes --dof 3 --count 60``, the repair
stage's median), where on an idle machine the team takes 0.55-0.7 of one thread's time (36³ to
60³).  Editing ``cspace._fill_rows``: numba's cache keeps :func:`_candidate_rows` compiled against
the old one (delete this module's cached kernels, ``__pycache__/swept*.nbi``, ``*.nbc``).
"""
from __future__ import annotations

import math

import numba as nb
import numpy as np

from .collision import NO_REFCOUNT, CollisionChecker, link_points, rotate_body
from .cores import current_threads
from .cspace import ROW_EPS_RAD, _fill_rows, build_cspace
from .field.graph import grid_strides
from .motion import MotionValidator
from .repair import edge_up, in_row_order, motion_up_free
from .termination import Termination

#: Added to the candidates' margin (beyond the sagitta), m: no rounding of a hull reaches it.
ROUNDING_M = 1e-9


@nb.njit(cache=True, nogil=True, inline="always")
def _turn(x, y, px, py, c, s):
    """Return the point (x, y) turned about (px, py) by the angle of cosine c and sine s."""
    dx, dy = x - px, y - py
    return px + c * dx - s * dy, py + s * dx + c * dy


@nb.njit(cache=True, nogil=True, inline="always")
def _cross(h, a, b, x, y):
    """Return the cross product (h[b] − h[a]) × ((x, y) − h[a]): > 0 where the turn a → b → (x, y) is left."""
    return (h[b, 0] - h[a, 0]) * (y - h[a, 1]) - (h[b, 1] - h[a, 1]) * (x - h[a, 0])


@nb.njit(cache=True, nogil=True)
def _hull(pts, n, out):
    """
    Write the convex hull of ``pts[:n]`` (float64 (n, 2), n ≥ 2) into ``out`` (n rows); return its vertex count.

    Andrew's monotone chain: the vertices counter-clockwise, collinear ones dropped.
    """
    order = np.arange(n)
    for i in range(1, n):                               # by x, then y (n is small)
        k = i
        while k > 0 and (pts[order[k - 1], 0] > pts[order[k], 0] or (
                pts[order[k - 1], 0] == pts[order[k], 0] and pts[order[k - 1], 1] > pts[order[k], 1])):
            order[k - 1], order[k] = order[k], order[k - 1]
            k -= 1
    h = np.empty((2 * n, 2))
    m = 0
    for t in range(n):                                  # the lower chain
        x, y = pts[order[t], 0], pts[order[t], 1]
        while m >= 2 and _cross(h, m - 2, m - 1, x, y) <= 0.0:
            m -= 1
        h[m, 0], h[m, 1] = x, y
        m += 1
    low = m + 1
    for t in range(n - 2, -1, -1):                      # the upper chain
        x, y = pts[order[t], 0], pts[order[t], 1]
        while m >= low and _cross(h, m - 2, m - 1, x, y) <= 0.0:
            m -= 1
        h[m, 0], h[m, 1] = x, y
        m += 1
    count = m - 1                                       # the last point is the first one again
    for i in range(count):
        out[i, 0] = h[i, 0]
        out[i, 1] = h[i, 1]
    return count


@nb.njit(cache=True, nogil=True)
def _put_hull(tmp, n, hv, hs, hc, hr, p, nv):
    """Write the hull of tmp[:n] as polygon p from vertex nv (its bounding circle too); return the next vertex."""
    count = _hull(tmp, n, hv[nv:])
    cx = cy = 0.0
    for i in range(nv, nv + count):
        cx += hv[i, 0]
        cy += hv[i, 1]
    cx /= count
    cy /= count
    r = 0.0
    for i in range(nv, nv + count):
        r = max(r, math.hypot(hv[i, 0] - cx, hv[i, 1] - cy))
    hc[p, 0], hc[p, 1], hr[p] = cx, cy, r
    hs[p + 1] = nv + count
    return nv + count


@nb.njit(cache=True, nogil=True)
def _swept_hulls(verts, starts, centres, radii, body_w, with_body, px, py, c, s, reach_m, hv, hs, hc, hr, tmp):
    """
    Write the hulls that hold what each obstacle (and, ``with_body``, the posed body) sweeps turning about (px, py).

    The turn's cosine c and sine s.  One hull per polygon, of it and its turned copy (convex or
    not: a concavity is filled).  Polygons whose bounding circle (centres, radii) lies farther than
    ``reach_m`` from the pivot are left out (the turning links do not reach them).  Packed as
    ``scene.pack_polygons``' arrays into hv (vertices), hs (starts), hc (centres), hr (radii)
    (room for every polygon's); tmp: scratch (at least 2 × the largest polygon's vertices).
    Returns ``(polygons written, the largest distance from the pivot of a vertex written (m, at
    most reach_m))``.
    """
    npoly = starts.size - 1
    total = npoly + (1 if with_body else 0)
    nv = 0
    out = 0
    rmax = 0.0
    hs[0] = 0
    for p in range(total):
        src = verts if p < npoly else body_w
        a = starts[p] if p < npoly else 0
        k = (starts[p + 1] if p < npoly else body_w.shape[0]) - a
        if p < npoly and math.hypot(centres[p, 0] - px, centres[p, 1] - py) - radii[p] > reach_m:
            continue
        for i in range(k):
            rmax = max(rmax, min(reach_m, math.hypot(src[a + i, 0] - px, src[a + i, 1] - py)))
            x, y = src[a + i, 0], src[a + i, 1]
            tmp[i, 0], tmp[i, 1] = x, y
            tmp[k + i, 0], tmp[k + i, 1] = _turn(x, y, px, py, c, s)
        nv = _put_hull(tmp, 2 * k, hv, hs, hc, hr, out, nv)
        out += 1
    return out, rmax


@nb.njit(cache=True, nogil=True)
def _all_hulls(shape, lower, step, axis, q_template, planned, lengths, body, verts, starts, centres, radii,
               margin_m):
    """
    Return the hulls of every value of the axes before ``axis`` (:func:`_swept_hulls`), packed per value.

    ``(hv (values, V, 2), hs (values, P + 1), hc (values, P, 2), hr (values, P), count (values,), margin
    (values,))``: each value's hulls (its ``count`` polygons) and the margin its candidates are tested
    at, ``margin_m`` + the largest sagitta + :data:`ROUNDING_M`.
    """
    j = planned[axis]
    prefixes = 1
    for d in range(axis):
        prefixes *= shape[d]
    c, s = math.cos(-step[axis]), math.sin(-step[axis])
    sagitta = 1.0 - math.cos(0.5 * step[axis])
    with_body = j >= 1 and body.shape[0] >= 3
    npoly = starts.size - 1
    most = body.shape[0]
    for p in range(npoly):
        most = max(most, starts[p + 1] - starts[p])
    polys = npoly + 1                                # one hull per polygon (the body's too) ...
    vertices = 2 * (verts.shape[0] + body.shape[0])  # ... of at most twice its vertices
    hv = np.empty((prefixes, vertices, 2))
    hs = np.zeros((prefixes, polys + 1), np.int64)
    hc = np.empty((prefixes, polys, 2))
    hr = np.empty((prefixes, polys))
    count = np.zeros(prefixes, np.int64)
    margin = np.empty(prefixes)
    tmp = np.empty((max(4, 2 * most), 2))
    q_full = q_template.copy()
    pts = np.empty((lengths.size + 1, 2))
    body_w = np.empty_like(body)
    reach = 0.0                                         # how far the turning links reach from the pivot
    for k in range(j, lengths.size):
        reach += lengths[k]
    for p in range(prefixes):
        rem = p
        for d in range(axis - 1, -1, -1):
            q_full[planned[d]] = lower[d] + (rem % shape[d]) * step[d]
            rem //= shape[d]
        link_points(q_full, lengths, pts)               # joint j's point: the joints before it alone
        rotate_body(body, q_full[0], body_w)
        count[p], rmax = _swept_hulls(verts, starts, centres, radii, body_w, with_body, pts[j, 0], pts[j, 1], c, s,
                                      reach + margin_m, hv[p], hs[p], hc[p], hr[p], tmp)
        margin[p] = margin_m + rmax * sagitta + ROUNDING_M
    return hv, hs, hc, hr, count, margin


@nb.njit(cache=True, nogil=True)
def _candidate_rows(cand, r, end, rows_each, shape, lower, step, planned, q_template, lengths, turning, body, hv, hs,
                    hc, hr, count, margin, stop):
    """Write :func:`_candidates`' rows [r, end) into ``cand``, one value of the axes before at a time."""
    known = np.zeros(0, np.bool_)
    while r < end:
        p = r // rows_each
        stop_at = min(end, (p + 1) * rows_each)
        k = count[p]
        _fill_rows(cand, r, stop_at, shape, lower, step, planned, q_template, lengths, turning, body, hv[p],
                   hs[p, :k + 1], hc[p, :k], hr[p, :k], margin[p], False, known, ROW_EPS_RAD, stop)
        r = stop_at


@nb.njit(cache=True, nogil=True, parallel=True)
def _candidate_chunks(cand, rows, *args):
    """Run :func:`_candidate_rows` over ``rows`` rows in 64 chunks on numba's threads (each row on its own)."""
    chunks = 64
    size = (rows + chunks - 1) // chunks
    for ch in nb.prange(chunks):
        _candidate_rows(cand, ch * size, min(rows, (ch + 1) * size), *args)


def _candidates(shape, lower, step, axis, q_template, planned, lengths, checked, body, verts, starts, centres,
                radii, margin_m, stop, parallel: bool):
    """
    Return bool (nodes,): the nodes whose edge up ``axis`` may collide (see the module doc).

    The links from the axis's joint on come within ``margin_m`` + the largest sagitta of a hull
    of an obstacle (and, past the attitude, the body) with its copy turned by −step[axis] about
    the joint (:func:`_all_hulls`); the row kernel's rows, in 64 chunks on numba's threads where
    ``parallel`` (each row on its own: the same candidates either way).  shape, lower, step: the
    grid's (rad); ``planned`` int64: each axis's joint (the last axis the chain's last joint); the
    rest as ``motion.SegmentTest.arrays()``.  ``stop`` int64 (1,): the termination flag, polled
    by the row kernel (nonzero: returns part-way).
    """
    ndim = shape.size
    turning = np.ascontiguousarray(checked[checked >= planned[axis]])
    rows_each = int(np.prod(shape[axis:ndim - 1]))
    rows = rows_each * int(np.prod(shape[:axis]))
    hulls = _all_hulls(shape, lower, step, axis, q_template, planned, lengths, body, verts, starts, centres, radii,
                       margin_m)
    cand = np.zeros(rows * int(shape[ndim - 1]), np.bool_)
    args = (rows_each, shape, lower, step, planned, q_template, lengths, turning, body, *hulls, stop)
    if parallel:
        _candidate_chunks(cand, rows, *args)
    else:
        _candidate_rows(cand, 0, rows, *args)
    return cand


@nb.njit(**NO_REFCOUNT)
def _tested(cand, occ, shape, periodic, axis, lower, step, strides, q_template, planned, lengths, checked, body,
            verts, starts, centres, radii, threshold_m, seg_step_rad, reach_m, q_full, pts, body_w, qa, qb, clr,
            found, k, f0, f1):
    """
    Append to ``found`` (from row k) each candidate's edge up ``axis`` between free nodes whose motion collides.

    The candidates among the flat nodes [f0, f1).  The quick test at the scene's margin, as the
    sheet search tests an edge (``repair.edge_up``, ``repair.motion_up_free``); flat node pairs, the
    smaller first.  Returns the new row count.  Scratch: the test's (q_full, pts, body_w), qa, qb
    (ndim,), clr (2,).
    """
    ndim = shape.size
    for f in range(f0, f1):
        if not cand[f] or occ[f]:
            continue
        g = edge_up(f, axis, (f // strides[axis]) % shape[axis], shape, strides, periodic, occ)
        if g < 0:
            continue
        for a in range(ndim):
            qa[a] = lower[a] + ((f // strides[a]) % shape[a]) * step[a]
        clr[0] = np.nan
        if not motion_up_free(qa, qb, axis, step, q_template, planned, lengths, checked, body, verts, starts,
                              centres, radii, threshold_m, seg_step_rad, reach_m, q_full, pts, body_w, clr):
            found[k, 0] = min(f, g)
            found[k, 1] = max(f, g)
            k += 1
    return k


@nb.njit(cache=True, nogil=True)
def _tested_all(cand, occ, shape, periodic, axis, lower, step, strides, q_template, planned, lengths, checked,
                body, verts, starts, centres, radii, threshold_m, seg_step_rad, reach_m):
    """Return :func:`_tested`'s edges over every node in one thread, in node order."""
    found = np.empty((np.count_nonzero(cand), 2), np.int64)  # each candidate has at most one edge up the axis
    k = _tested(cand, occ, shape, periodic, axis, lower, step, strides, q_template, planned, lengths, checked,
                body, verts, starts, centres, radii, threshold_m, seg_step_rad, reach_m, q_template.copy(),
                np.empty((lengths.size + 1, 2)), np.empty_like(body), np.empty(shape.size), np.empty(shape.size),
                np.empty(2), found, 0, 0, cand.size)
    return found[:k].copy()


@nb.njit(cache=True, nogil=True, parallel=True)
def _tested_chunks(cand, occ, shape, periodic, axis, lower, step, strides, q_template, planned, lengths, checked,
                   body, verts, starts, centres, radii, threshold_m, seg_step_rad, reach_m):
    """Return :func:`_tested`'s edges over every node, in 64 chunks of nodes on numba's threads (the chunks' order)."""
    n = cand.size
    chunks = 64
    size = (n + chunks - 1) // chunks
    room = np.zeros(chunks + 1, np.int64)               # each candidate has at most one edge up the axis
    for ch in range(chunks):
        room[ch + 1] = room[ch] + np.count_nonzero(cand[ch * size:min(n, (ch + 1) * size)])
    found = np.empty((room[chunks], 2), np.int64)
    got = np.zeros(chunks, np.int64)
    for ch in nb.prange(chunks):
        q_full = q_template.copy()
        pts = np.empty((lengths.size + 1, 2))
        body_w = np.empty_like(body)
        got[ch] = _tested(cand, occ, shape, periodic, axis, lower, step, strides, q_template, planned, lengths,
                          checked, body, verts, starts, centres, radii, threshold_m, seg_step_rad, reach_m, q_full,
                          pts, body_w, np.empty(shape.size), np.empty(shape.size), np.empty(2), found, room[ch],
                          ch * size, min(n, (ch + 1) * size)) - room[ch]
    out = np.empty((got.sum(), 2), np.int64)
    k = 0
    for ch in range(chunks):
        out[k:k + got[ch]] = found[room[ch]:room[ch] + got[ch]]
        k += got[ch]
    return out


def applies(motions, ndim: int) -> bool:
    """
    Return whether :func:`swept_edges` finds anything on a grid of ``ndim`` axes for these motions.

    The grid's axes are the chain's joints in order, its last axis the chain's last joint (the
    row kernel's rows), and it has an axis before that one.
    """
    planned = np.asarray(motions.planned)
    return (ndim >= 2 and planned.size == ndim and int(planned[-1]) == motions.lengths.size - 1
            and bool(np.all(np.diff(planned) > 0)))


def swept_edges(occupied, periodic, lower_rad, step_rad, motions, token=None,
                parallel: bool | None = None) -> np.ndarray:
    """
    Return the colliding grid edges along every axis but the last: int64 (k, 2) flat node pairs (smaller first), sorted.

    occupied: bool grid (its free nodes are the edges' ends); periodic: one bool per axis;
    the nodes at ``lower_rad + index * step_rad``; motions: the scene's ``motion.SegmentTest``.
    Empty where :func:`applies` says no.  ``token``: the plan's termination token
    (``termination.Termination``; raises ``termination.Cancelled`` once it is set).
    ``parallel``: the kernels' form, on numba's threads or in this one (None: on the threads
    where this thread has more than one, ``cores.current_threads``).  The same edges either way.
    """
    token = Termination.of(token)
    occ = np.ascontiguousarray(occupied, dtype=np.bool_)
    if not applies(motions, occ.ndim):
        return np.zeros((0, 2), np.int64)
    shape = np.array(occ.shape, np.int64)
    lower = np.asarray(lower_rad, dtype=float)
    step = np.asarray(step_rad, dtype=float)
    per = np.array(periodic, np.bool_)
    arrays = motions.arrays()
    threshold_m = arrays[9]
    flat = occ.reshape(-1)
    strides = grid_strides(shape)
    if parallel is None:
        parallel = current_threads() > 1
    tested = _tested_chunks if parallel else _tested_all
    parts = []
    for axis in range(shape.size - 1):
        cand = _candidates(shape, lower, step, axis, *arrays[:9], threshold_m, token.flag, parallel)
        token.check()
        parts.append(tested(cand, flat, shape, per, axis, lower, step, strides, *arrays))
        token.check()
    edges = np.concatenate(parts)
    return in_row_order(edges)


def warm_up(robot, scene, grid) -> None:
    """
    Compile (or load from numba's cache) both forms of :func:`swept_edges`' kernels on ``grid`` (a coarse one).

    A plan's own grid reaches one form only (as the C-space's row kernel, ``cspace.warm_up``).
    """
    occ = build_cspace(robot, scene, grid).occupied
    motions = MotionValidator(CollisionChecker(robot, scene)).segment_test()
    for parallel in (False, True):
        swept_edges(occ, grid.periodic, grid.lower_rad, grid.step_rad, motions, parallel=parallel)
