"""
The repair stage's search: the colliding grid edges around a node where the descent was blocked.

A grid decides nothing about what lies between two nodes: two free face neighbours can be
joined by a straight motion that collides (an obstacle thinner than a grid step, in
C-space).  Such edges make up "sheets": an obstacle's thin part crosses the grid edges next
to each other.  The descent stops at the first of them; a repair (``pipeline.PlanRun``)
cuts them from the field's graph and re-solves the field.  Cutting only those within a few
steps of the node left the rest of the sheet, and the next descent, sliding along it, was
blocked a few nodes farther (one field solve per few nodes of sheet).

:func:`sheet_edges` follows the sheet: every edge within ``radius`` steps of the node is
tested, then every edge within one step of a colliding one, until no colliding edge is
found or ``max_tests`` edges were tested beyond the box (a count, so the same input gives the same
edges).
A sheet ends where the obstacle is thick enough to occupy grid nodes (edges to them are not
graph edges) or where it ends.
"""
from __future__ import annotations

import numba as nb
import numpy as np

from .descent import _along
from .field import solve_field
from .field.graph import grid_strides
from .collision import NO_REFCOUNT
from .motion import motion_scratch, segment_free_from

#: The most edge motions one repair tests beyond the box around the blocked node (a few ms;
#: a repair round at 36³ costs about 10 to 20 ms: on the repairing scenes of ``bench scenes``
#: 1000 to 2000 took the least CPU time, 12 % less than the box alone, 4000 more).
MAX_TESTS = 2_000


@nb.njit(**NO_REFCOUNT)
def _push_box(f, radius, shape, strides, periodic, seen, queue, tail, c0, off):
    """Append the unseen nodes within ``radius`` index steps of flat node ``f`` to ``queue``; returns the new tail."""
    ndim = shape.size
    for a in range(ndim):
        c0[a] = (f // strides[a]) % shape[a]
    side = 2 * radius + 1
    total = 1
    for a in range(ndim):
        total *= side
    for t in range(total):
        rem = t
        for a in range(ndim - 1, -1, -1):
            off[a] = rem % side - radius
            rem //= side
        g = 0
        for a in range(ndim):
            k = _along(c0[a], off[a], shape[a], periodic[a])
            if k < 0:
                g = -1
                break
            g += k * strides[a]
        if g >= 0 and not seen[g]:
            seen[g] = True
            queue[tail] = g
            tail += 1
    return tail


@nb.njit(**NO_REFCOUNT, inline="always")
def edge_up(f, a, c_a, shape, strides, periodic, occ_flat):
    """Return the free node one step up axis ``a`` from flat node ``f`` (coordinate ``c_a`` on it), else -1."""
    k = _along(c_a, 1, shape[a], periodic[a])
    if k < 0:
        return -1
    g = f + (k - c_a) * strides[a]
    return -1 if occ_flat[g] else g


@nb.njit(**NO_REFCOUNT, inline="always")
def motion_up_free(qa, qb, a, step, q_template, planned, lengths, checked, body, verts, starts, centres, radii,
                   threshold_m, seg_step_rad, reach_m, q_full, pts, body_w, clr_ends):
    """
    Return the quick test's verdict on the motion from ``qa`` one step up axis ``a`` (``motion.segment_free_from``).

    The grid edge's motion (across a periodic seam too: the motion itself); qb: scratch, set to its end.
    """
    for b in range(qa.shape[0]):
        qb[b] = qa[b]
    qb[a] += step[a]
    return segment_free_from(qa, qb, q_template, planned, lengths, checked, body, verts, starts, centres, radii,
                             threshold_m, seg_step_rad, reach_m, q_full, pts, body_w, clr_ends)


def _sheet_edges(occ_flat, shape, periodic, centre, radius, max_tests, lower, step, q_template, planned,
                 lengths, checked, body, verts, starts, obs_centres, obs_radii, threshold_m, seg_step_rad, reach_m):
    """
    Return (colliding edges int64 (k, 2) flat node pairs (smaller first), edges tested).

    Breadth-first over nodes: those within ``radius`` of flat node ``centre`` first; each
    node's edges to its free + neighbours are tested (``motion.segment_free``), and the nodes
    within one step of both ends of a colliding edge are queued.  Beyond the box around
    ``centre``, no node is taken once ``max_tests`` edges were tested.
    """
    ndim = shape.size
    n = occ_flat.size
    # every node taken tests at most ndim edges; beyond the box, none is taken after max_tests
    most = ndim * ((2 * radius + 1) ** ndim + max_tests + 1)
    found = np.empty((most, 2), np.int64)
    k, tests = _sheet_search(occ_flat, shape, periodic, centre, radius, max_tests, lower, step, q_template, planned,
                             lengths, checked, body, verts, starts, obs_centres, obs_radii, threshold_m, seg_step_rad,
                             reach_m, grid_strides(shape), *motion_scratch(q_template, lengths, body), np.empty(ndim),
                             np.empty(ndim), np.empty((3, ndim), np.int64), np.zeros(n, np.bool_),
                             np.empty(n, np.int64), np.empty(2), found)
    return found[:k].copy(), tests


@nb.njit(**NO_REFCOUNT)
def _sheet_search(occ_flat, shape, periodic, centre, radius, max_tests, lower, step, q_template, planned,
                  lengths, checked, body, verts, starts, obs_centres, obs_radii, threshold_m, seg_step_rad, reach_m,
                  strides, q_full, pts, body_w, qa, qb, coords, seen, queue, clr_ends, found):
    """
    :func:`_sheet_edges` into ``found`` (large enough); returns (edges found, edges tested).

    A node's edges start at the same coordinates: its clearance, measured by the first of its
    tests, starts the others (``motion.segment_free_from``), the same value.

    Scratch: the motion test's (``motion.motion_scratch``), qa and qb (ndim,), coords int64 (3, ndim),
    seen bool (nodes,) all False, queue int64 (nodes,), clr_ends (2,).
    """
    ndim = shape.size
    c = coords[0]
    c0 = coords[1]
    off = coords[2]
    seeds = tail = _push_box(centre, radius, shape, strides, periodic, seen, queue, 0, c0, off)
    head = 0
    tests = 0
    k_found = 0
    while head < tail and (head < seeds or tests < max_tests):    # the box around the centre: all
        f = queue[head]
        head += 1
        if occ_flat[f]:
            continue
        for a in range(ndim):
            c[a] = (f // strides[a]) % shape[a]
            qa[a] = lower[a] + c[a] * step[a]
        clr_ends[0] = np.nan                    # the clearance at qa: measured by the node's first test
        for a in range(ndim):
            g = edge_up(f, a, c[a], shape, strides, periodic, occ_flat)
            if g < 0:
                continue
            tests += 1
            if not motion_up_free(qa, qb, a, step, q_template, planned, lengths, checked, body, verts, starts,
                                  obs_centres, obs_radii, threshold_m, seg_step_rad, reach_m, q_full, pts, body_w,
                                  clr_ends):
                found[k_found, 0] = min(f, g)
                found[k_found, 1] = max(f, g)
                k_found += 1
                tail = _push_box(f, 1, shape, strides, periodic, seen, queue, tail, c0, off)
                tail = _push_box(g, 1, shape, strides, periodic, seen, queue, tail, c0, off)
    return k_found, tests


def sheet_edges(occupied, periodic, node, motions, lower_rad, step_rad, radius: int = 2,
                max_tests: int | None = None) -> np.ndarray:
    """
    Return the colliding grid edges near ``node`` and those joined to them (see the module doc).

    occupied: bool grid; periodic: one bool per axis; node: the grid index where the descent
    was blocked; motions: a ``motion.SegmentTest``; nodes at ``lower_rad + index * step_rad``.
    Returns int64 (k, 2) flat node pairs (smaller first), in the order found; every edge
    within ``radius`` index steps of ``node`` that collides is among them.  ``max_tests``:
    None for :data:`MAX_TESTS`.
    """
    occ = np.ascontiguousarray(occupied)
    limit = MAX_TESTS if max_tests is None else max_tests
    edges, _ = _sheet_edges(occ.ravel(), np.array(occ.shape, np.int64), np.array(periodic, np.bool_),
                            int(np.ravel_multi_index(tuple(node), occ.shape)), int(radius), int(limit),
                            np.asarray(lower_rad, dtype=float), np.asarray(step_rad, dtype=float),
                            *motions.arrays())
    return edges


def in_row_order(edges: np.ndarray) -> np.ndarray:
    """Return grid edges int (k, 2) with their rows in ``sorted``'s order of the pairs (first node, then second)."""
    return edges[np.lexsort((edges[:, 1], edges[:, 0]))]


class CutEdges:
    """
    The grid edges a plan's repairs have cut: int64 (k, 2) flat node pairs, distinct, in row order.

    Immutable and hashable, a part of the repaired fields' and their walks' cache keys
    (``pipeline.PlanRun``): two are equal when they hold the same edges.  ``array`` (read-only,
    the rows sorted as ``sorted`` sorts their pairs) is what the field solve and the grid's
    search take.  Made from arrays, never from Python tuples: a first repair cuts hundreds to
    thousands of edges (every colliding one off the last axis), and a frozenset of tuples of
    them cost about 2 us an edge to build plus a sort at every key made of it (each walk's,
    each field's): milliseconds per repairing plan.
    """

    __slots__ = ("array", "_bytes")

    def __init__(self, edges=()):
        """Hold ``edges`` (anything of k pairs of flat node indices; repeats taken once)."""
        a = np.array(edges, dtype=np.int64).reshape(-1, 2)
        if len(a) > 1:
            a = in_row_order(a)
            a = a[np.concatenate(([True], np.any(a[1:] != a[:-1], axis=1)))]
        a = np.ascontiguousarray(a)
        a.flags.writeable = False
        self.array = a
        self._bytes = a.tobytes()

    def with_edges(self, edges) -> tuple:
        """Return ``(these edges and ``edges``, how many of ``edges`` were not cut yet)`` (distinct ones)."""
        grown = CutEdges(np.concatenate((self.array, np.asarray(edges, dtype=np.int64).reshape(-1, 2))))
        return grown, len(grown) - len(self)

    def __len__(self) -> int:
        return int(self.array.shape[0])

    def __eq__(self, other) -> bool:
        return isinstance(other, CutEdges) and self._bytes == other._bytes

    def __hash__(self) -> int:
        return hash(self._bytes)

    def __reduce__(self):
        return CutEdges, (np.array(self.array),)

    def __repr__(self) -> str:
        return f"CutEdges({len(self)} edges)"


def warm_up() -> None:
    """
    Compile (or load from numba's cache) what a repair runs: the search, a field with cut edges.

    The search on a made-up arm and one square obstacle, with a plan's argument types.
    """
    square = np.array([[1.0, 0.0], [0.0, 1.0], [-1.0, 0.0], [0.0, -1.0]])
    arrays = (np.zeros(3), np.array([1, 2], dtype=np.int64), np.array([1.4, 2.0, 2.0]),
              np.array([1, 2], dtype=np.int64), square.copy(), square + 3.0, np.array([0, 4], dtype=np.int64),
              np.array([[3.0, 3.0]]), np.array([1.0]), 0.02, 0.05, np.array([4.0, 2.0]))
    occ = np.zeros((6, 6), np.bool_)
    _sheet_edges(occ.ravel(), np.array(occ.shape, np.int64), np.array([True, False]), 14, 1, 100,
                 np.radians([-180.0, -150.0]), np.radians([60.0, 60.0]), *arrays)
    solve_field(occ, (True, False), [(5, 5)], cut_edges=np.array([[14, 15]]))
