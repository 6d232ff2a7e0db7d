"""
The node graph of a field problem: the goal-connected free nodes of an occupancy grid.

Every kernel of the field works on this graph, whatever the grid's dimension: node ``k``
of the graph has ``2n`` face neighbours ``nbr[k, 2a + (0|1)]`` (the −/+ neighbour along
axis ``a``, wrapping on periodic axes); a neighbour that is a wall, an obstacle or a node
not connected to the goal reads ``N`` (one dummy node past the end, value 0).
"""
from __future__ import annotations

from dataclasses import dataclass

import numba as nb
import numpy as np

from ..termination import Termination


@nb.njit(cache=True, nogil=True, inline="always")
def _next_coord(coord, shape):
    """Advance the grid coordinate ``coord`` to the next node in C order (an odometer)."""
    a = coord.size - 1
    while a >= 0:
        coord[a] += 1
        if coord[a] < shape[a]:
            break
        coord[a] = 0
        a -= 1


@nb.njit(cache=True, nogil=True)
def grid_neighbours(shape, periodic):
    """
    Flat index of each grid node's 2n face neighbours, -1 beyond a wall.

    shape int64 (ndim,), periodic bool (ndim,).  Returns int64 (prod(shape), 2 ndim):
    column 2a + (0|1) = the (-|+) neighbour along axis a, wrapping on periodic axes.
    One odometer pass over the grid, no integer divisions.
    """
    n = 1
    for a in range(shape.size):
        n *= shape[a]
    out = np.empty((n, 2 * shape.size), np.int64)
    fill_grid_neighbours(shape, periodic, out)
    return out


@nb.njit(cache=True, nogil=True)
def fill_grid_neighbours(shape, periodic, out):
    """:func:`grid_neighbours` into ``out`` (prod(shape), 2 ndim), any integer type (the node graph's: int32)."""
    ndim = shape.size
    n = out.shape[0]
    strides = np.ones(ndim, np.int64)
    for a in range(ndim - 2, -1, -1):
        strides[a] = strides[a + 1] * shape[a + 1]
    coord = np.zeros(ndim, np.int64)
    for f in range(n):
        for a in range(ndim):
            c = coord[a]
            span = (shape[a] - 1) * strides[a]
            if c > 0:
                out[f, 2 * a] = f - strides[a]
            else:
                out[f, 2 * a] = f + span if periodic[a] else -1
            if c < shape[a] - 1:
                out[f, 2 * a + 1] = f + strides[a]
            else:
                out[f, 2 * a + 1] = f - span if periodic[a] else -1
        _next_coord(coord, shape)
    return out


@nb.njit(cache=True, nogil=True)
def _bfs(occ_flat, gnbr, goal_flat):
    """
    BFS through free nodes from the goal nodes.

    ``(dist, order)``, dist int64 per flat node (-1 = not reached), order = reached flat nodes in
    BFS order.
    """
    n = occ_flat.size
    deg = gnbr.shape[1]
    dist = np.full(n, -1, np.int64)
    order = np.empty(n, np.int64)
    head = 0
    tail = 0
    for g in goal_flat:
        if dist[g] < 0:
            dist[g] = 0
            order[tail] = g
            tail += 1
    while head < tail:
        f = order[head]
        head += 1
        for a in range(deg):
            g = gnbr[f, a]
            if g < 0 or occ_flat[g] or dist[g] >= 0:
                continue
            dist[g] = dist[f] + 1
            order[tail] = g
            tail += 1
    return dist, order[:tail]


@nb.njit(cache=True, nogil=True)
def _red_black_order(dist, goal_flat, shape):
    """
    Return (order, coords) of the reached nodes, red-black ordered.

    The goal nodes, then the reached nodes (dist ≥ 0) with an even coordinate sum, then the odd
    ones, each in grid order; coords int64 (N, ndim).
    """
    ndim = shape.size
    n_grid = dist.size
    n_goal = goal_flat.size
    is_goal = np.zeros(n_grid, np.bool_)
    for g in goal_flat:
        is_goal[g] = True
    n_red = 0
    n_all = n_goal
    coord = np.zeros(ndim, np.int64)
    parity = np.zeros(n_grid, np.int8)
    for f in range(n_grid):                  # odometer over the grid: coordinate sums
        par = 0
        for a in range(ndim):
            par += coord[a]
        parity[f] = par % 2
        if dist[f] >= 0 and not is_goal[f]:
            n_all += 1
            if par % 2 == 0:
                n_red += 1
        _next_coord(coord, shape)
    order = np.empty(n_all, np.int64)
    coords = np.empty((n_all, ndim), np.int64)
    order[:n_goal] = goal_flat
    strides = np.ones(ndim, np.int64)
    for a in range(ndim - 2, -1, -1):
        strides[a] = strides[a + 1] * shape[a + 1]
    for k in range(n_goal):
        for a in range(ndim):
            coords[k, a] = (order[k] // strides[a]) % shape[a]
    k_red = n_goal
    k_black = n_goal + n_red
    coord[:] = 0
    for f in range(n_grid):                  # the same odometer: the coordinates without divisions
        if dist[f] >= 0 and not is_goal[f]:
            if parity[f] == 0:
                k = k_red
                k_red += 1
            else:
                k = k_black
                k_black += 1
            order[k] = f
            for a in range(ndim):
                coords[k, a] = coord[a]
        _next_coord(coord, shape)
    return order, coords


@nb.njit(cache=True, nogil=True)
def _neighbour_table(order, gnbr):
    """
    Return nbr uint32 (N, 2n).

    Position in ``order`` of each node's face neighbours, N for walls, obstacles and nodes not in
    ``order``.
    """
    n = order.size
    deg = gnbr.shape[1]
    pos = np.full(gnbr.shape[0], n, np.int32)
    for k in range(n):
        pos[order[k]] = k
    nbr = np.empty((n, deg), np.uint32)     # unsigned: no negative-index wrap-around in the kernels
    for k in range(n):
        f = order[k]
        for a in range(deg):
            g = gnbr[f, a]
            nbr[k, a] = n if g < 0 else pos[g]
    return nbr


def validate_problem(occupied, periodic, goal_nodes):
    """
    Check and normalise a field problem.

    Returns ``(occupied bool array, periodic tuple of bools, goal_nodes int64 array
    (k, ndim), distinct)``.  Raises ValueError naming the offending argument.
    """
    occ = np.asarray(occupied)
    if occ.ndim < 1:
        raise ValueError(f"occupied: expected a grid with at least one axis, got shape {occ.shape}")
    if occ.dtype != np.bool_:
        raise ValueError(f"occupied: expected a bool array, got dtype {occ.dtype}")
    if min(occ.shape) < 2:
        raise ValueError(f"occupied: every axis needs at least 2 nodes, got shape {occ.shape}")
    per = tuple(bool(p) for p in periodic)
    if len(per) != occ.ndim:
        raise ValueError(f"periodic: expected {occ.ndim} flags for grid shape {occ.shape}, got {len(per)}")
    goals = np.asarray(goal_nodes)
    if goals.ndim == 1:
        goals = goals.reshape(1, -1)
    if goals.ndim != 2 or goals.shape[1] != occ.ndim or goals.shape[0] == 0:
        raise ValueError(f"goal_nodes: expected an int array (k, {occ.ndim}) with k >= 1, got shape {goals.shape}")
    if not np.issubdtype(goals.dtype, np.integer):
        if not np.all(goals == np.round(goals)):
            raise ValueError("goal_nodes: node indices must be integers")
    goals = goals.astype(np.int64)
    if np.any(goals < 0) or np.any(goals >= np.array(occ.shape)):
        raise ValueError(f"goal_nodes: index out of the grid {occ.shape}: {goals.tolist()}")
    hit = occ[tuple(goals.T)]
    if np.any(hit):
        raise ValueError(f"goal_nodes: goal node {tuple(goals[np.argmax(hit)])} lies in an obstacle")
    return np.ascontiguousarray(occ), per, np.unique(goals, axis=0)


@dataclass(frozen=True, eq=False)
class NodeGraph:
    """
    The goal-connected free nodes of a validated problem.

    order: int64 (N,) flat grid index of each graph node: the goal nodes first (``n_goal``
        of them), then the others with an even coordinate sum ("red"), then the odd ones
        ("black"), each in grid order (memory locality; the multigrid smoother's order).
    nbr: uint32 (N, 2 ndim) neighbour positions in ``order``; N = none (see module doc).
    coords: int64 (N, ndim) grid coordinates.
    dist: int64 (N,) BFS distance (face steps through free nodes) from the goal.
    shape, periodic: the grid's.
    """

    order: np.ndarray
    nbr: np.ndarray
    coords: np.ndarray
    dist: np.ndarray
    n_goal: int
    shape: tuple
    periodic: tuple

    @property
    def size(self) -> int:
        return int(self.order.size)

    def scatter(self, values, fill=-np.inf) -> np.ndarray:
        """Graph values (N,) onto the grid (``shape``), ``fill`` elsewhere."""
        out = np.full(int(np.prod(self.shape)), fill, dtype=float)
        out[self.order] = values
        return out.reshape(self.shape)


@nb.njit(cache=True, nogil=True)
def _cut_edges(gnbr, edges):
    """
    Remove the grid edges ``edges`` from the neighbour table.

    Remove the grid edges ``edges`` int64 (k, 2) (flat node pairs, face neighbours) from the
    neighbour table: each end then sees a wall there.
    """
    deg = gnbr.shape[1]
    for e in range(edges.shape[0]):
        a, b = edges[e, 0], edges[e, 1]
        for d in range(deg):
            if gnbr[a, d] == b:
                gnbr[a, d] = -1
            if gnbr[b, d] == a:
                gnbr[b, d] = -1


def bfs(occ, per, goals, cut_edges=None, token=None):
    """
    Return (dist, BFS order, grid neighbour table) of a validated problem.

    (dist int64 grid-flat, BFS order, grid neighbour table) of a validated problem, without the grid
    edges ``cut_edges`` (int (k, 2) flat node pairs) if given.  ``token``: a termination
    token checked between the passes (raises ``termination.Cancelled``).
    """
    gnbr = np.empty((occ.size, 2 * occ.ndim), np.int32 if occ.size < 2**31 else np.int64)
    fill_grid_neighbours(np.array(occ.shape, np.int64), np.array(per, np.bool_), gnbr)
    if token is not None:
        token.check()
    if cut_edges is not None and len(cut_edges):
        _cut_edges(gnbr, np.asarray(cut_edges, dtype=np.int64).reshape(-1, 2))
    goal_flat = np.ravel_multi_index(tuple(goals.T), occ.shape).astype(np.int64)
    dist, order = _bfs(occ.ravel(), gnbr, goal_flat)
    return dist, order, gnbr


def node_graph(occ, per, goals, cut_edges=None, token=None) -> NodeGraph:
    """
    Return the :class:`NodeGraph` of a validated problem.

    The :class:`NodeGraph` of a validated problem (``validate_problem``), without the grid edges
    ``cut_edges`` (int (k, 2) flat node pairs: a wall between the two).  ``token``: a
    termination token checked between the passes (raises ``termination.Cancelled``).
    """
    token = Termination.of(token)
    dist, order, gnbr = bfs(occ, per, goals, cut_edges, token)
    token.check()
    n_goal = len(goals)
    order, coords = _red_black_order(dist, order[:n_goal], np.array(occ.shape, np.int64))
    token.check()
    return NodeGraph(order, _neighbour_table(order, gnbr), coords, dist[order], n_goal,
                     tuple(occ.shape), tuple(per))


def bfs_distance(occupied, periodic, goal_nodes) -> np.ndarray:
    """
    Graph distance (face steps through free nodes) from the goal.

    -1 at obstacles and at free nodes not connected to the goal.

    int64, grid shape.
    """
    occ, per, goals = validate_problem(occupied, periodic, goal_nodes)
    return bfs(occ, per, goals)[0].reshape(occ.shape)


@nb.njit(cache=True, nogil=True)
def ascent_defects(log_u, nbr, n_goal):
    """
    Graph nodes (not goal) with no strictly higher face neighbour, int64 (m,).

    log_u float64 (N + 1,) with the dummy last (-inf).  Where steepest ascent would stop.
    """
    n, deg = nbr.shape
    bad = []
    for i in range(n_goal, n):
        v = log_u[i]
        up = False
        for a in range(deg):
            if log_u[nbr[i, a]] > v:
                up = True
                break
        if not up:
            bad.append(i)
    out = np.empty(len(bad), np.int64)
    for t in range(len(bad)):
        out[t] = bad[t]
    return out
