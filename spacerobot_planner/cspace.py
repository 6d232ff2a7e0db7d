"""
The configuration-space grid and its occupancy.

A grid covers the planned joints.  Along a bounded axis with ``cells`` cells the
nodes sit at ``lower + k·step`` for k = 0…cells (both ends are nodes); along a
periodic axis there are ``cells`` nodes and the upper end *is* the lower one
(−180° ≡ +180° for the attitude).  ``step = (upper − lower) / cells``.

A node is an obstacle when, at that configuration, a checked link comes within the
safety margin of the spacecraft body or of an obstacle (the exact test of
``collision``).

Rows along the last axis.  When the grid's last axis is the chain's last joint, only
the last link moves along a row: it turns about the fixed elbow point E.  The absolute
link angles at which a segment of length L from E comes within the margin m of a
polygon are a union of intervals in closed form (for each edge: the two edges offset by
±m and the disks of radius m at its vertices), so the row is filled from intervals: a
node farther than ``ROW_EPS_RAD`` inside an interval is occupied, one farther outside
all of them is free of the last link, and the few nodes within ``ROW_EPS_RAD`` of an
interval's end get the exact segment test.  The links before it are tested once per
row.  Same occupancy as the node-by-node test, far fewer tests.

Cancel: the kernels poll the plan's termination token (``termination.Termination``,
its ``flag`` array) before every row (node by node: before every node) and return
early when it is set; :func:`build_cspace` then raises ``termination.Cancelled``, so a
partial occupancy never leaves this module.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
from numba import njit, prange

import math

from .collision import (NO_REFCOUNT, link_points, point_segment_dist2, rotate_body, links_hit_body,
                        links_hit_polygons, point_in_polygon, segment_hits_polygons,
                        segment_polygon_within)
from .scene import pack_polygons
from .termination import Termination

__all__ = ["GridSpec", "CSpace", "build_cspace", "body_occupancy", "grid_for_robot"]


@dataclass(frozen=True)
class GridSpec:
    """
    A regular grid over the planned joints.

    Attributes
    ----------
        cells: cells per axis (≥ 2 each).
        lower_rad, upper_rad: axis bounds, rad.
        periodic: per axis, whether the axis wraps.

    """

    cells: tuple
    lower_rad: tuple
    upper_rad: tuple
    periodic: tuple

    def __post_init__(self):
        n = len(self.cells)
        for name in ("lower_rad", "upper_rad", "periodic"):
            if len(getattr(self, name)) != n:
                raise ValueError(f"grid.{name}: expected {n} values, got {len(getattr(self, name))}")
        cells = []
        for i, c in enumerate(self.cells):
            if isinstance(c, (bool, np.bool_)) or int(c) != c or int(c) < 2:
                raise ValueError(f"grid.cells: axis {i} must be an integer ≥ 2, got {c!r}")
            cells.append(int(c))
        object.__setattr__(self, "cells", tuple(cells))
        object.__setattr__(self, "lower_rad", tuple(float(v) for v in self.lower_rad))
        object.__setattr__(self, "upper_rad", tuple(float(v) for v in self.upper_rad))
        object.__setattr__(self, "periodic", tuple(bool(p) for p in self.periodic))
        for i in range(n):
            if not self.upper_rad[i] > self.lower_rad[i]:
                raise ValueError(f"grid: axis {i} upper bound must exceed its lower bound")

    @property
    def ndim(self) -> int:
        return len(self.cells)

    @property
    def shape(self) -> tuple:
        """Nodes per axis: cells on periodic axes, cells + 1 on bounded ones."""
        return tuple(c if p else c + 1 for c, p in zip(self.cells, self.periodic))

    @property
    def n_nodes(self) -> int:
        return math.prod(self.shape)

    @property
    def step_rad(self) -> np.ndarray:
        """Node spacing per axis, rad, float64 (ndim,): a new array each call (computed once per grid)."""
        return self._arrays()[1].copy()

    def _arrays(self) -> tuple:
        """Return ``(lower_rad, step_rad)`` as float64 arrays, computed once per grid (never handed out)."""
        held = self.__dict__.get("_held_arrays")
        if held is None:
            lower = np.asarray(self.lower_rad, dtype=float)
            held = (lower, (np.asarray(self.upper_rad) - lower) / np.asarray(self.cells))
            object.__setattr__(self, "_held_arrays", held)
        return held

    def __getstate__(self):
        """Pickle the fields only, not the arrays held (a grid's bytes are the same whether it was used or not)."""
        return {k: v for k, v in self.__dict__.items() if k != "_held_arrays"}

    def axis_values_rad(self, axis: int) -> np.ndarray:
        """Joint values of the nodes along one axis, rad."""
        return self.lower_rad[axis] + np.arange(self.shape[axis]) * self.step_rad[axis]

    def config_of(self, node) -> np.ndarray:
        """Return the configuration(s) (rad) of node index/indices: (ndim,) → (ndim,), (N, ndim) → (N, ndim)."""
        lower, step = self._arrays()
        return lower + np.asarray(node) * step

    def node_of(self, q) -> tuple:
        """
        Nearest node to configuration ``q`` (rad), wrapping periodic axes.

        Raises ValueError when q is not finite or lies outside a bounded axis.
        """
        q = np.asarray(q, dtype=float)
        if q.shape != (self.ndim,):
            raise ValueError(f"configuration: expected {self.ndim} values, got shape {q.shape}")
        idx = []
        for i in range(self.ndim):
            if not np.isfinite(q[i]):
                raise ValueError(f"configuration: axis {i} is {q[i]}")
            k = int(np.round((q[i] - self.lower_rad[i]) / self.step_rad[i]))
            if self.periodic[i]:
                k %= self.cells[i]
            elif not 0 <= k <= self.cells[i]:
                raise ValueError(f"configuration: axis {i} = {np.degrees(q[i]):.3f}° is outside "
                                 f"[{np.degrees(self.lower_rad[i]):.1f}°, {np.degrees(self.upper_rad[i]):.1f}°]")
            idx.append(k)
        return tuple(idx)

    def with_cells(self, cells) -> "GridSpec":
        """Return the same grid with another resolution (an int for every axis, or one per axis)."""
        cells = (cells,) * self.ndim if np.isscalar(cells) else tuple(cells)
        return GridSpec(cells, self.lower_rad, self.upper_rad, self.periodic)

    def label(self) -> str:
        return "x".join(str(s) for s in self.shape)


def grid_for_robot(robot, cells) -> GridSpec:
    """Return the grid over a robot's planned joints and their bounds."""
    cells = (cells,) * robot.dof if np.isscalar(cells) else tuple(cells)
    if len(cells) != robot.dof:
        raise ValueError(f"grid.cells: expected {robot.dof} values (one per planned joint), got {len(cells)}")
    return GridSpec(cells, tuple(robot.planned_lower_rad), tuple(robot.planned_upper_rad),
                    robot.planned_periodic)


@dataclass(frozen=True, eq=False)
class CSpace:
    """
    Occupancy of every grid node.

    Attributes
    ----------
        grid: the grid.
        occupied: bool array of shape ``grid.shape``; True = obstacle.
        margin_m: the safety margin the occupancy was built with, metres.
        seconds: build time.

    """

    grid: GridSpec
    occupied: np.ndarray
    margin_m: float = 0.0
    seconds: float = 0.0

    @property
    def free_fraction(self) -> float:
        """Return the share of the grid's nodes that are free, 0..1 (a count: a replan's progress line says it)."""
        return 1.0 - np.count_nonzero(self.occupied) / self.occupied.size


@njit(parallel=True, cache=True, nogil=True)
def _occupancy_kernel(shape, lower, step, axis_joint, q_locked, lengths, checked, body,
                      obs_verts, obs_starts, obs_centres, obs_radii, margin_m, check_body,
                      known_hit, stop):
    """
    Occupancy (flat, C order) of every node.

    ``known_hit`` (size K, may be empty): nodes with ``known_hit[flat % K]`` are
    occupied without a test (the body table over the trailing axes).  ``stop`` int64
    (1,): the termination flag, polled before every node (nonzero: return, partial).
    """
    ndim = shape.shape[0]
    n_nodes = 1
    for d in range(ndim):
        n_nodes *= shape[d]
    n_known = known_hit.shape[0]
    occ = np.zeros(n_nodes, dtype=np.bool_)
    n_chunks = 64
    chunk = (n_nodes + n_chunks - 1) // n_chunks
    for c in prange(n_chunks):
        q_full = q_locked.copy()
        pts = np.empty((lengths.shape[0] + 1, 2))
        body_w = np.empty_like(body)
        for flat in range(c * chunk, min(n_nodes, (c + 1) * chunk)):
            if stop[0] != 0:
                break
            if n_known > 0 and known_hit[flat % n_known]:
                occ[flat] = True
                continue
            rem = flat
            for d in range(ndim - 1, -1, -1):
                k = rem % shape[d]
                rem //= shape[d]
                q_full[axis_joint[d]] = lower[d] + k * step[d]
            link_points(q_full, lengths, pts)
            if check_body:
                rotate_body(body, q_full[0], body_w)
                if links_hit_body(pts, checked, body_w, margin_m):
                    occ[flat] = True
                    continue
            occ[flat] = links_hit_polygons(pts, checked, obs_verts, obs_starts, obs_centres,
                                           obs_radii, margin_m)
    return occ


#: Nodes closer than this (rad) to the end of a collision interval get the exact test.
ROW_EPS_RAD = 1e-7
_TWO_PI = 2.0 * math.pi


@njit(cache=True, nogil=True, inline="always")
def _push(ivals, n, centre, half):
    ivals[n, 0] = centre
    ivals[n, 1] = half
    return n + 1


@njit(cache=True, nogil=True)
def _disk_interval(ex, ey, cx, cy, r, length, ivals, n):
    """
    Directions from E in which a segment of ``length`` meets the disk (C, r).

    Appended as (centre angle, half-width); the caller has checked that E lies outside the disk.
    """
    dx, dy = cx - ex, cy - ey
    d2 = dx * dx + dy * dy
    d = math.sqrt(d2)
    if d - r > length:
        return n
    if length * length >= d2 - r * r:
        half = math.asin(min(1.0, r / d))
    else:
        c = (d2 + length * length - r * r) / (2.0 * d * length)
        half = math.acos(max(-1.0, min(1.0, c)))
    return _push(ivals, n, math.atan2(dy, dx), half)


@njit(cache=True, nogil=True)
def _segment_interval(ex, ey, ax, ay, bx, by, length, ivals, n):
    """Directions from E in which a segment of ``length`` meets segment AB (E not on it)."""
    ux, uy = bx - ax, by - ay
    fx, fy = ax - ex, ay - ey
    a = ux * ux + uy * uy
    b = 2.0 * (fx * ux + fy * uy)
    c = fx * fx + fy * fy - length * length
    if a == 0.0:
        t0, t1 = 0.0, 0.0
        if c > 0.0:
            return n
    else:
        disc = b * b - 4.0 * a * c
        if disc < 0.0:
            return n
        sq = math.sqrt(disc)
        t0 = max(0.0, (-b - sq) / (2.0 * a))
        t1 = min(1.0, (-b + sq) / (2.0 * a))
        if t0 > t1:
            return n
    p0 = math.atan2(fy + t0 * uy, fx + t0 * ux)
    p1 = math.atan2(fy + t1 * uy, fx + t1 * ux)
    dlt = (p1 - p0 + math.pi) % _TWO_PI - math.pi
    return _push(ivals, n, p0 + 0.5 * dlt, 0.5 * abs(dlt))


@njit(cache=True, nogil=True)
def _polygon_intervals(ex, ey, length, verts, start, stop, margin_m, ivals, n):
    """
    Append the directions in which a segment from E comes near a polygon.

    Append the directions in which a segment of ``length`` from E comes within ``margin_m`` of
    polygon verts[start:stop]; -1 when E itself does (every direction).
    """
    m2 = margin_m * margin_m
    if point_in_polygon(ex, ey, verts, start, stop):
        return -1
    j = stop - 1
    for i in range(start, stop):
        if point_segment_dist2(ex, ey, verts[j, 0], verts[j, 1], verts[i, 0], verts[i, 1]) <= m2:
            return -1
        j = i
    j = stop - 1
    for i in range(start, stop):
        cx, cy, dx, dy = verts[j, 0], verts[j, 1], verts[i, 0], verts[i, 1]
        if margin_m > 0.0:
            ux, uy = dx - cx, dy - cy
            norm = math.sqrt(ux * ux + uy * uy)
            ox, oy = -uy / norm * margin_m, ux / norm * margin_m
            n = _segment_interval(ex, ey, cx + ox, cy + oy, dx + ox, dy + oy, length, ivals, n)
            n = _segment_interval(ex, ey, cx - ox, cy - oy, dx - ox, dy - oy, length, ivals, n)
            n = _disk_interval(ex, ey, cx, cy, margin_m, length, ivals, n)
        else:
            n = _segment_interval(ex, ey, cx, cy, dx, dy, length, ivals, n)
        j = i
    return n


@njit(cache=True, nogil=True)
def _link_hits(ax, ay, bx, by, verts, starts, centres, radii, body_w, check_body, margin_m):
    """Run the exact test of one link against the body (if ``check_body``) and the polygons."""
    if check_body and segment_polygon_within(ax, ay, bx, by, body_w, 0, body_w.shape[0], margin_m):
        return True
    return segment_hits_polygons(ax, ay, bx, by, verts, starts, centres, radii, margin_m)


@njit(cache=True, nogil=True)
def _fill_rows(occ, row_start, row_stop, shape, lower, step, axis_joint, q_locked, lengths, checked,
               body, obs_verts, obs_starts, obs_centres, obs_radii, margin_m, check_body,
               known_hit, eps_rad, stop):
    """
    Fill the occupancy of the rows ``row_start .. row_stop`` (flat, C order, into ``occ``).

    Along the last axis, which must be the chain's last joint (see the module doc).
    Arguments as for ``_occupancy_kernel``; ``stop`` is polled before every row.
    :func:`_fill_rows_into` with its scratch.
    """
    max_iv = 4 * (obs_verts.shape[0] + body.shape[0]) + 1
    _fill_rows_into(occ, row_start, row_stop, shape, lower, step, axis_joint, q_locked, lengths, checked, body,
                    obs_verts, obs_starts, obs_centres, obs_radii, margin_m, check_body, known_hit, eps_rad, stop,
                    q_locked.copy(), np.empty((lengths.shape[0] + 1, 2)), np.empty_like(body),
                    np.empty((max_iv, 2)), np.zeros(shape[shape.shape[0] - 1], np.bool_))


@njit(**NO_REFCOUNT)
def _fill_rows_into(occ, row_start, row_stop, shape, lower, step, axis_joint, q_locked, lengths, checked,
                    body, obs_verts, obs_starts, obs_centres, obs_radii, margin_m, check_body,
                    known_hit, eps_rad, stop, q_full, pts, body_w, ivals, unsure):
    """
    Run :func:`_fill_rows` with its scratch given.

    q_full (n_joints,) starting as ``q_locked``, pts (n_links + 1, 2), body_w like body, ivals
    (4 (obstacle vertices + body vertices) + 1, 2), unsure bool (row length,) all False.
    """
    ndim = shape.shape[0]
    row_len = shape[ndim - 1]
    n_rows = 1
    for d in range(ndim - 1):
        n_rows *= shape[d]
    n_known = known_hit.shape[0]
    last = lengths.shape[0] - 1
    last_checked = False
    for c in range(checked.shape[0]):
        if checked[c] == last:
            last_checked = True
    length = lengths[last]
    n_poly = obs_radii.shape[0]
    lo = lower[ndim - 1]
    st = step[ndim - 1]
    e = eps_rad / st
    if True:
        for row in range(row_start, row_stop):
            if stop[0] != 0:
                return
            base_flat = row * row_len
            kb0 = base_flat % n_known if n_known > 0 else 0     # known_hit[(base_flat + t) % n_known]
            full = n_known > 0                  # the body table occupies the whole row: no test
            kb = kb0
            for t in range(row_len if full else 0):
                if not known_hit[kb]:
                    full = False
                    break
                kb += 1
                if kb == n_known:
                    kb = 0
            if full:
                for t in range(row_len):
                    occ[base_flat + t] = True
                continue
            rem = row
            for d in range(ndim - 2, -1, -1):
                k = rem % shape[d]
                rem //= shape[d]
                q_full[axis_joint[d]] = lower[d] + k * step[d]
            q_full[last] = 0.0
            link_points(q_full, lengths, pts)
            rotate_body(body, q_full[0], body_w)
            hit = False
            for c in range(checked.shape[0]):
                k = checked[c]
                if k != last and _link_hits(pts[k, 0], pts[k, 1], pts[k + 1, 0], pts[k + 1, 1], obs_verts,
                                            obs_starts, obs_centres, obs_radii, body_w, check_body, margin_m):
                    hit = True
                    break
            if hit:
                for t in range(row_len):
                    occ[base_flat + t] = True
                continue
            if last_checked:
                ex, ey = pts[last, 0], pts[last, 1]
                n = 0
                if check_body:
                    n = _polygon_intervals(ex, ey, length, body_w, 0, body_w.shape[0], margin_m, ivals, n)
                for p in range(n_poly):
                    if n < 0:
                        break
                    r = obs_radii[p] + margin_m + length
                    dx, dy = obs_centres[p, 0] - ex, obs_centres[p, 1] - ey
                    if dx * dx + dy * dy > r * r:
                        continue
                    n = _polygon_intervals(ex, ey, length, obs_verts, obs_starts[p], obs_starts[p + 1],
                                           margin_m, ivals, n)
                if n < 0:
                    for t in range(row_len):
                        occ[base_flat + t] = True
                    continue
                base = 0.0
                for j in range(last):
                    base += q_full[j]
                for t in range(row_len):
                    unsure[t] = False
                for v in range(n):
                    half = ivals[v, 1]
                    a = (ivals[v, 0] - half - base - lo) % _TWO_PI       # interval start, rad from lo
                    for turn in range(2):
                        x0 = (a - turn * _TWO_PI) / st
                        x1 = x0 + 2.0 * half / st
                        k0 = max(0, int(math.ceil(x0 + e)))
                        k1 = min(row_len - 1, int(math.floor(x1 - e)))
                        for t in range(k0, k1 + 1):
                            occ[base_flat + t] = True
                        for x in (x0, x1):
                            for t in range(max(0, int(math.ceil(x - e))), min(row_len - 1, int(math.floor(x + e))) + 1):
                                unsure[t] = True
                for t in range(row_len):
                    if unsure[t] and not occ[base_flat + t]:
                        ang = base + lo + t * st
                        bx = ex + length * math.cos(ang)
                        by = ey + length * math.sin(ang)
                        occ[base_flat + t] = _link_hits(ex, ey, bx, by, obs_verts, obs_starts, obs_centres,
                                                        obs_radii, body_w, check_body, margin_m)
            if n_known > 0:
                kb = kb0
                for t in range(row_len):
                    if known_hit[kb]:
                        occ[base_flat + t] = True
                    kb += 1
                    if kb == n_known:
                        kb = 0


@njit(parallel=True, cache=True, nogil=True)
def _fill_rows_parallel(occ, n_rows, *args):
    n_chunks = 64
    chunk = (n_rows + n_chunks - 1) // n_chunks
    for ch in prange(n_chunks):
        _fill_rows(occ, ch * chunk, min(n_rows, (ch + 1) * chunk), *args)


#: Grids with fewer nodes are filled by one thread (a parallel launch costs more there).
ROWS_PARALLEL_NODES = 300_000


def _by_rows(axis_joint, n_joints: int) -> bool:
    """Tell whether the row kernel fills a grid: its last axis is the chain's last joint (else node by node)."""
    return int(axis_joint[-1]) == n_joints - 1


def loops_at_any_size(robot) -> bool:
    """
    Tell whether the C-space of ``robot``'s planned joints runs a parallel loop on every grid size.

    The node-by-node kernel (:func:`_occupancy_kernel`, where the last planned joint is not the
    chain's last) runs on numba's threads whatever the size; the row kernel from
    ``ROWS_PARALLEL_NODES`` nodes only.  The planner counts the busy cores before such a build
    on every grid (``cores.fit_threads(any_size=True)``).
    """
    return not _by_rows(robot.planned_joints, robot.n_joints)


def _occupancy(shape, lower, step, axis_joint, *rest, token=None, parallel=None):
    """
    Use the row kernel where the last axis is the chain's last joint, else node by node.

    ``token``: the termination token (None: never); raises Cancelled when it stopped the kernel.
    ``parallel``: the row kernel's form, parallel or one thread (None: parallel from
    ``ROWS_PARALLEL_NODES`` nodes).
    """
    token = Termination.of(token)
    stop = token.flag
    q_locked = rest[0]
    if not _by_rows(axis_joint, q_locked.shape[0]):
        occ = _occupancy_kernel(shape, lower, step, axis_joint, *rest, stop)
    else:
        n_nodes = int(np.prod(shape))
        occ = np.zeros(n_nodes, dtype=np.bool_)
        n_rows = n_nodes // int(shape[-1])
        args = (shape, lower, step, axis_joint, *rest, ROW_EPS_RAD, stop)
        if parallel is None:
            parallel = n_nodes >= ROWS_PARALLEL_NODES
        if parallel:
            _fill_rows_parallel(occ, n_rows, *args)
        else:
            _fill_rows(occ, 0, n_rows, *args)
    token.check()           # the kernel may have stopped part-way: never return that
    return occ


def body_occupancy(robot, grid: GridSpec, margin_m: float, token=None) -> np.ndarray | None:
    """
    Collisions with the spacecraft body over the grid's trailing axes, or None.

    The body turns with the attitude, so in the body frame its collisions depend on
    the arm joints only: when the attitude is the grid's first axis, one table over
    the other axes serves every attitude.  It does not depend on the target or the
    debris, so a caller may keep it across target moves.  Shape ``grid.shape[1:]``.
    ``token``: the termination token; raises ``termination.Cancelled`` when it stops the build.
    """
    if robot.planned_joints[0] != 0 or grid.ndim < 2:
        return None
    rest = GridSpec(grid.cells[1:], grid.lower_rad[1:], grid.upper_rad[1:], grid.periodic[1:])
    q_locked = np.array(robot.locked_rad, dtype=float)
    q_locked[0] = 0.0
    none = np.zeros((0, 2))
    occ = _occupancy(
        np.asarray(rest.shape, dtype=np.int64), np.asarray(rest.lower_rad), np.asarray(rest.step_rad),
        np.asarray(robot.planned_joints[1:], dtype=np.int64), q_locked,
        np.asarray(robot.link_lengths_m, dtype=float), np.asarray(robot.checked_links, dtype=np.int64),
        np.ascontiguousarray(robot.body_polygon_m), none, np.zeros(1, dtype=np.int64), none,
        np.zeros(0), float(margin_m), True, np.zeros(0, dtype=np.bool_), token=token)
    return occ.reshape(rest.shape)


def build_cspace(robot, scene, grid: GridSpec, extra_margin_m: float = 0.0,
                 body_table: np.ndarray | None = None, token=None, parallel: bool | None = None) -> CSpace:
    """
    Occupancy of every node of ``grid`` for ``robot`` among ``scene``'s obstacles.

    Parameters
    ----------
    grid, robot, scene
        The ``GridSpec``, the ``Robot`` and the ``Scene``.
    extra_margin_m
        Added to the scene's safety margin for the grid only (a conservative grid keeps
        grid paths farther from obstacles).
    body_table
        A ``body_occupancy`` result for the same robot, grid and total margin, to skip
        recomputing it (computed here when None).
    token
        The plan's termination token (``termination.Termination``; None: never set),
        polled by the kernels row by row.  Raises ``termination.Cancelled`` when it is
        set before the build ends: nothing partial is returned.
    parallel
        Fill the rows on all threads or on one (None: on all from ``ROWS_PARALLEL_NODES``
        nodes; :func:`warm_up` loads the parallel form on a small grid).

    """
    if grid.ndim != robot.dof:
        raise ValueError(f"grid has {grid.ndim} axes but the robot plans {robot.dof} joints")
    margin = float(scene.safety_margin_m + extra_margin_m)
    verts, starts, centres, radii = pack_polygons(scene.obstacle_polygons_m)
    t0 = time.perf_counter()
    if body_table is None:
        body_table = body_occupancy(robot, grid, margin, token=token)
    elif body_table.shape != grid.shape[1:]:
        raise ValueError(f"body_table: shape {body_table.shape} does not match grid {grid.shape}")
    known = (np.zeros(0, dtype=np.bool_) if body_table is None
             else np.ascontiguousarray(body_table).reshape(-1))
    occ = _occupancy(
        np.asarray(grid.shape, dtype=np.int64), np.asarray(grid.lower_rad, dtype=float),
        np.asarray(grid.step_rad, dtype=float), np.asarray(robot.planned_joints, dtype=np.int64),
        np.asarray(robot.locked_rad, dtype=float), np.asarray(robot.link_lengths_m, dtype=float),
        np.asarray(robot.checked_links, dtype=np.int64), np.ascontiguousarray(robot.body_polygon_m),
        verts, starts, centres, radii, margin, body_table is None, known, token=token, parallel=parallel)
    seconds = time.perf_counter() - t0
    return CSpace(grid=grid, occupied=occ.reshape(grid.shape), margin_m=margin, seconds=seconds)


def warm_up(robot, scene, grid: GridSpec) -> None:
    """
    Compile (or load from numba's cache) both forms of the row kernel on ``grid`` (a coarse one).

    A plan's own grid reaches one form only (the parallel one from ``ROWS_PARALLEL_NODES``
    nodes): a refinement to a finer grid would otherwise compile the other (seconds) inside
    the plan.
    """
    for parallel in (False, True):
        build_cspace(robot, scene, grid, parallel=parallel)
