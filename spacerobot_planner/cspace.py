"""The configuration-space grid and its occupancy.

A grid covers the planned joints.  Along a bounded axis with ``cells`` cells the
nodes sit at ``lower + k·step`` for k = 0…cells (both ends are nodes); along a
periodic axis there are ``cells`` nodes and the upper end *is* the lower one
(−180° ≡ +180° for the attitude).  ``step = (upper − lower) / cells``.

A node is an obstacle when, at that configuration, a checked link comes within the
safety margin of the spacecraft body or of an obstacle (the exact test of
``collision``).
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
from numba import njit, prange

from .collision import _link_points, _rotate_body, links_hit_body, links_hit_polygons
from .scene import pack_polygons

__all__ = ["GridSpec", "CSpace", "build_cspace", "body_occupancy", "grid_for_robot"]


@dataclass(frozen=True)
class GridSpec:
    """A regular grid over the planned joints.

    Attributes:
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
        return int(np.prod(self.shape))

    @property
    def step_rad(self) -> np.ndarray:
        return (np.asarray(self.upper_rad) - np.asarray(self.lower_rad)) / np.asarray(self.cells)

    def axis_values_rad(self, axis: int) -> np.ndarray:
        """Joint values of the nodes along one axis, rad."""
        return self.lower_rad[axis] + np.arange(self.shape[axis]) * self.step_rad[axis]

    def config_of(self, node) -> np.ndarray:
        """Configuration(s) (rad) of node index/indices: (ndim,) → (ndim,), (N, ndim) → (N, ndim)."""
        node = np.asarray(node)
        return np.asarray(self.lower_rad) + node * self.step_rad

    def node_of(self, q) -> tuple:
        """Nearest node to configuration ``q`` (rad), wrapping periodic axes.

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
        """The same grid with another resolution (an int for every axis, or one per axis)."""
        cells = (cells,) * self.ndim if np.isscalar(cells) else tuple(cells)
        return GridSpec(cells, self.lower_rad, self.upper_rad, self.periodic)

    def label(self) -> str:
        return "x".join(str(s) for s in self.shape)


def grid_for_robot(robot, cells) -> GridSpec:
    """The grid over a robot's planned joints and their bounds."""
    cells = (cells,) * robot.dof if np.isscalar(cells) else tuple(cells)
    if len(cells) != robot.dof:
        raise ValueError(f"grid.cells: expected {robot.dof} values (one per planned joint), got {len(cells)}")
    return GridSpec(cells, tuple(robot.planned_lower_rad), tuple(robot.planned_upper_rad),
                    robot.planned_periodic)


@dataclass(frozen=True, eq=False)
class CSpace:
    """Occupancy of every grid node.

    Attributes:
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
        return float(1.0 - self.occupied.mean())


@njit(parallel=True, cache=True, nogil=True)
def _occupancy_kernel(shape, lower, step, axis_joint, q_locked, lengths, checked, body,
                      obs_verts, obs_starts, obs_centres, obs_radii, margin_m, check_body,
                      known_hit):
    """Occupancy (flat, C order) of every node.

    ``known_hit`` (size K, may be empty): nodes with ``known_hit[flat % K]`` are
    occupied without a test (the body table over the trailing axes).
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
            if n_known > 0 and known_hit[flat % n_known]:
                occ[flat] = True
                continue
            rem = flat
            for d in range(ndim - 1, -1, -1):
                k = rem % shape[d]
                rem //= shape[d]
                q_full[axis_joint[d]] = lower[d] + k * step[d]
            _link_points(q_full, lengths, pts)
            if check_body:
                _rotate_body(body, q_full[0], body_w)
                if links_hit_body(pts, checked, body_w, margin_m):
                    occ[flat] = True
                    continue
            occ[flat] = links_hit_polygons(pts, checked, obs_verts, obs_starts, obs_centres,
                                           obs_radii, margin_m)
    return occ


def body_occupancy(robot, grid: GridSpec, margin_m: float) -> np.ndarray | None:
    """Collisions with the spacecraft body over the grid's trailing axes, or None.

    The body turns with the attitude, so in the body frame its collisions depend on
    the arm joints only: when the attitude is the grid's first axis, one table over
    the other axes serves every attitude.  It does not depend on the target or the
    debris, so a caller may keep it across target moves.  Shape ``grid.shape[1:]``.
    """
    if robot.planned_joints[0] != 0 or grid.ndim < 2:
        return None
    rest = GridSpec(grid.cells[1:], grid.lower_rad[1:], grid.upper_rad[1:], grid.periodic[1:])
    q_locked = np.array(robot.locked_rad, dtype=float)
    q_locked[0] = 0.0
    none = np.zeros((0, 2))
    occ = _occupancy_kernel(
        np.asarray(rest.shape, dtype=np.int64), np.asarray(rest.lower_rad), np.asarray(rest.step_rad),
        np.asarray(robot.planned_joints[1:], dtype=np.int64), q_locked,
        np.asarray(robot.link_lengths_m, dtype=float), np.asarray(robot.checked_links, dtype=np.int64),
        np.ascontiguousarray(robot.body_polygon_m), none, np.zeros(1, dtype=np.int64), none,
        np.zeros(0), float(margin_m), True, np.zeros(0, dtype=np.bool_))
    return occ.reshape(rest.shape)


def build_cspace(robot, scene, grid: GridSpec, extra_margin_m: float = 0.0,
                 body_table: np.ndarray | None = None) -> CSpace:
    """Occupancy of every node of ``grid`` for ``robot`` among ``scene``'s obstacles.

    Args:
        extra_margin_m: added to the scene's safety margin for the grid only (a
            conservative grid keeps grid paths farther from obstacles).
        body_table: a ``body_occupancy`` result for the same robot, grid and total
            margin, to skip recomputing it (computed here when None).
    """
    if grid.ndim != robot.dof:
        raise ValueError(f"grid has {grid.ndim} axes but the robot plans {robot.dof} joints")
    margin = float(scene.safety_margin_m + extra_margin_m)
    verts, starts, centres, radii = pack_polygons(scene.obstacle_polygons_m)
    t0 = time.perf_counter()
    if body_table is None:
        body_table = body_occupancy(robot, grid, margin)
    elif body_table.shape != grid.shape[1:]:
        raise ValueError(f"body_table: shape {body_table.shape} does not match grid {grid.shape}")
    known = (np.zeros(0, dtype=np.bool_) if body_table is None
             else np.ascontiguousarray(body_table).reshape(-1))
    occ = _occupancy_kernel(
        np.asarray(grid.shape, dtype=np.int64), np.asarray(grid.lower_rad, dtype=float),
        np.asarray(grid.step_rad, dtype=float), np.asarray(robot.planned_joints, dtype=np.int64),
        np.asarray(robot.locked_rad, dtype=float), np.asarray(robot.link_lengths_m, dtype=float),
        np.asarray(robot.checked_links, dtype=np.int64), np.ascontiguousarray(robot.body_polygon_m),
        verts, starts, centres, radii, margin, body_table is None, known)
    seconds = time.perf_counter() - t0
    return CSpace(grid=grid, occupied=occ.reshape(grid.shape), margin_m=margin, seconds=seconds)
