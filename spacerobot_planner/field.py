"""Harmonic (Laplace) potential fields on C-space occupancy grids.

Grid conventions
----------------
``occupied``   bool array of shape ``shape`` (2-D or 3-D), True = obstacle node.
``periodic``   tuple of bools, one per axis; a periodic axis wraps (index -1 is
               ``shape[a] - 1``), a bounded axis has walls beyond its ends.
``goal_nodes`` int array (k, ndim) of goal node indices.
Neighbours are the 2n face neighbours, always visited in the fixed order
``(axis 0, -1), (axis 0, +1), (axis 1, -1), ...``.

Solvers (``solve_field(..., solver=NAME)``)
-------------------------------------------
``"gauss_seidel"``  The paper's method, literally: potential Phi with obstacles
                    (and walls) at Phi0, goal at 0, free nodes start at Phi0,
                    lexicographic in-place sweeps, stop when the largest
                    absolute change in a sweep is below ``tol``.  Reference
                    solver and benchmark baseline.  In float64 the far field
                    becomes *exactly* Phi0 (flat), so descent stalls there.
``"sor"``           The same linear problem in the flipped form u = 1 - Phi/Phi0
                    (goal 1, obstacles 0, free nodes start at 0), red-black SOR
                    with omega = 2 / (1 + sin(pi / N)), absolute-change stop.
``"multigrid"``     The flipped linear form solved by conjugate gradients
                    preconditioned with an aggregation multigrid V-cycle
                    (``_multigrid``), stop on the residual.  Accurate to an
                    absolute tolerance only, like ``sor``.
``"log_harmonic"``  Planner default.  The same harmonic u without underflow:
                    u_i = w_i * exp(s_i) with a per-node log scale s
                    (``_scaled_field``), so SOR on u becomes multiply-adds with
                    per-edge coefficients exp(s_j - s_i) / 2n (a diagonal
                    similarity transform: the same iteration, no underflow),
                    never below the subharmonic lower bound u0 = (2n)**-d
                    (d = BFS distance from the goal).  Phase 1 settles the
                    bulk: on 2-D grids and 3-D grids from 100k nodes the
                    multigrid solve to a residual of 1e-12, on smaller 3-D
                    grids red-black SOR from u0 until the absolute change <
                    ``tol`` (the paper's rule); phase 2,
                    plain Gauss-Seidel until the *relative* change |d log u| <
                    ``rel_tol``, settles the tiny values of deep pockets (after
                    multigrid only the nodes with u < 1e-5 need it); then a
                    check that every reachable non-goal node has a strictly
                    higher neighbour (else it falls back to ``"log_gs"``).
``"log_gs"``        Plain symmetric Gauss-Seidel (forward / backward passes in
                    BFS order from the goal) on the same representation from
                    the same lower bound.  In exact arithmetic
                    every iterate is subharmonic, so steepest ascent reaches the
                    goal on *any* iterate ("anytime" field; ``max_sweeps=0``
                    gives the BFS field itself).

Every solver returns a :class:`Field` holding ``log_u`` (log of the flipped
potential u: 0 at the goal, -inf at obstacles and wherever u is 0 in float64).
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numba as nb
import numpy as np

from . import _multigrid as _mg
from . import _scaled_field as _sf

SOLVERS = ("log_harmonic", "log_gs", "multigrid", "sor", "gauss_seidel")
DEFAULT_SOLVER = "log_harmonic"

#: Default stopping tolerance per solver (absolute change of the potential
#: per sweep; for log_gs the change of log u; for multigrid the residual).
DEFAULT_TOL = {"gauss_seidel": 1e-6, "sor": 1e-6, "log_harmonic": 1e-6, "log_gs": 1e-4,
               "multigrid": 1e-12}
#: Default sweep cap per solver (one sweep = one pass over the grid; for
#: multigrid one CG iteration).
DEFAULT_MAX_SWEEPS = {"gauss_seidel": 200_000, "sor": 100_000, "log_harmonic": 100_000,
                      "log_gs": 1_000_000, "multigrid": 500}


@dataclass(frozen=True)
class Field:
    """A solved potential field on an occupancy grid.

    Attributes
    ----------
    log_u : float64 array, grid shape
        log of the flipped harmonic potential u (u = 1 at the goal, 0 at
        obstacles): 0 at goal nodes, -inf at obstacles and at free nodes where
        u is zero (not connected to the goal, or flat in the paper's form).
    occupied, periodic, goal_nodes : the problem the field was solved for.
    solver : name of the solver that produced it.
    sweeps : number of relaxation passes over the grid.
    residual : the solver's convergence measure at stop (absolute change of
        Phi or u per sweep for the linear forms, max |change of log u| for the
        log forms).
    converged : whether ``residual`` fell below the tolerance.
    seconds : wall time of the solve, set-up included.
    """

    log_u: np.ndarray
    occupied: np.ndarray
    periodic: tuple
    goal_nodes: np.ndarray
    solver: str
    sweeps: int
    residual: float
    converged: bool
    seconds: float

    def potential(self) -> np.ndarray:
        """phi = -log u: 0 at the goal, +inf at obstacles (plot on a log scale)."""
        return -self.log_u

    @property
    def reachable(self) -> np.ndarray:
        """Bool mask of nodes with u > 0 (finite log u)."""
        return np.isfinite(self.log_u)

    @property
    def goal_mask(self) -> np.ndarray:
        """Bool mask of the goal nodes."""
        mask = np.zeros(self.occupied.shape, dtype=np.bool_)
        mask[tuple(self.goal_nodes.T)] = True
        return mask


# --------------------------------------------------------------------------
# input checks
# --------------------------------------------------------------------------
def validate_problem(occupied, periodic, goal_nodes):
    """Check and normalise a field problem.

    Returns ``(occupied bool array, periodic tuple of bools, goal_nodes int64
    array (k, ndim))``.  Raises ValueError naming the offending argument.
    """
    occ = np.asarray(occupied)
    if occ.ndim not in (2, 3):
        raise ValueError(f"occupied: expected a 2-D or 3-D grid, got shape {occ.shape}")
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
    shape = np.array(occ.shape)
    if np.any(goals < 0) or np.any(goals >= shape):
        raise ValueError(f"goal_nodes: index out of the grid {occ.shape}: {goals.tolist()}")
    hit = occ[tuple(goals.T)]
    if np.any(hit):
        raise ValueError(f"goal_nodes: goal node {tuple(goals[np.argmax(hit)])} lies in an obstacle")
    goals = np.unique(goals, axis=0)
    return np.ascontiguousarray(occ), per, goals


# --------------------------------------------------------------------------
# the paper's Gauss-Seidel (reference)
# --------------------------------------------------------------------------
@nb.njit(cache=True, nogil=True)
def _gs_paper_2d(phi, fixed, per0, per1, phi0, tol, max_sweeps):
    n0, n1 = phi.shape
    change = np.inf
    sweeps = 0
    while sweeps < max_sweeps:
        change = 0.0
        for i in range(n0):
            for j in range(n1):
                if fixed[i, j]:
                    continue
                if i > 0:
                    a = phi[i - 1, j]
                elif per0:
                    a = phi[n0 - 1, j]
                else:
                    a = phi0
                if i < n0 - 1:
                    b = phi[i + 1, j]
                elif per0:
                    b = phi[0, j]
                else:
                    b = phi0
                if j > 0:
                    c = phi[i, j - 1]
                elif per1:
                    c = phi[i, n1 - 1]
                else:
                    c = phi0
                if j < n1 - 1:
                    d = phi[i, j + 1]
                elif per1:
                    d = phi[i, 0]
                else:
                    d = phi0
                new = (a + b + c + d) / 4.0
                delta = abs(new - phi[i, j])
                if delta > change:
                    change = delta
                phi[i, j] = new
        sweeps += 1
        if change < tol:
            break
    return sweeps, change


@nb.njit(cache=True, nogil=True)
def _gs_paper_3d(phi, fixed, per0, per1, per2, phi0, tol, max_sweeps):
    n0, n1, n2 = phi.shape
    change = np.inf
    sweeps = 0
    while sweeps < max_sweeps:
        change = 0.0
        for i in range(n0):
            for j in range(n1):
                for k in range(n2):
                    if fixed[i, j, k]:
                        continue
                    s = 0.0
                    if i > 0:
                        s += phi[i - 1, j, k]
                    elif per0:
                        s += phi[n0 - 1, j, k]
                    else:
                        s += phi0
                    if i < n0 - 1:
                        s += phi[i + 1, j, k]
                    elif per0:
                        s += phi[0, j, k]
                    else:
                        s += phi0
                    if j > 0:
                        s += phi[i, j - 1, k]
                    elif per1:
                        s += phi[i, n1 - 1, k]
                    else:
                        s += phi0
                    if j < n1 - 1:
                        s += phi[i, j + 1, k]
                    elif per1:
                        s += phi[i, 0, k]
                    else:
                        s += phi0
                    if k > 0:
                        s += phi[i, j, k - 1]
                    elif per2:
                        s += phi[i, j, n2 - 1]
                    else:
                        s += phi0
                    if k < n2 - 1:
                        s += phi[i, j, k + 1]
                    elif per2:
                        s += phi[i, j, 0]
                    else:
                        s += phi0
                    new = s / 6.0
                    delta = abs(new - phi[i, j, k])
                    if delta > change:
                        change = delta
                    phi[i, j, k] = new
        sweeps += 1
        if change < tol:
            break
    return sweeps, change


def gauss_seidel_phi(occupied, periodic, goal_nodes, phi0=1.0, tol=1e-6, max_sweeps=200_000):
    """The paper's Gauss-Seidel on the raw potential Phi.

    Obstacles (and the walls beyond bounded axes) are held at ``phi0``, goal
    nodes at 0, free nodes start at ``phi0``; lexicographic in-place sweeps
    set each free node to the mean of its 2n neighbours until the largest
    absolute change in one sweep is below ``tol``.

    Returns ``(phi, sweeps, change)``: phi float64 array of the grid shape,
    the number of sweeps done and the largest change in the last sweep.
    """
    occ, per, goals = validate_problem(occupied, periodic, goal_nodes)
    phi = np.full(occ.shape, float(phi0))
    phi[tuple(goals.T)] = 0.0
    fixed = occ.copy()
    fixed[tuple(goals.T)] = True
    if occ.ndim == 2:
        sweeps, change = _gs_paper_2d(phi, fixed, per[0], per[1], float(phi0), float(tol), int(max_sweeps))
    else:
        sweeps, change = _gs_paper_3d(phi, fixed, per[0], per[1], per[2], float(phi0), float(tol),
                                      int(max_sweeps))
    return phi, int(sweeps), float(change)


def gauss_seidel(occupied, periodic, goal_nodes, phi0=1.0, tol=1e-6, max_sweeps=200_000) -> Field:
    """The paper's Gauss-Seidel (see :func:`gauss_seidel_phi`) as a Field.

    ``log_u = log(1 - Phi / Phi0)``: -inf wherever Phi == Phi0 exactly, i.e.
    at obstacles and on the flat far field where float64 cannot tell Phi from
    Phi0 (the paper's descent stalls there).
    """
    t0 = time.perf_counter()
    occ, per, goals = validate_problem(occupied, periodic, goal_nodes)
    phi, sweeps, change = gauss_seidel_phi(occ, per, goals, phi0, tol, max_sweeps)
    return _linear_field(1.0 - phi / float(phi0), occ, per, goals, "gauss_seidel", sweeps, change,
                         change < tol, t0)


def _linear_field(u, occ, per, goals, solver, sweeps, residual, converged, t0) -> Field:
    """A Field from the flipped linear potential u (log u; -inf where u <= 0 and at obstacles)."""
    with np.errstate(divide="ignore"):
        log_u = np.log(np.maximum(u, 0.0))
    log_u[occ] = -np.inf
    return Field(log_u, occ, per, goals, solver, sweeps, residual, bool(converged), time.perf_counter() - t0)


# --------------------------------------------------------------------------
# red-black SOR on the flipped linear form u (goal 1, obstacles 0)
# --------------------------------------------------------------------------
@nb.njit(cache=True, parallel=True, nogil=True)
def _rb_sor_2d(u, active, per0, per1, omega, tol, max_sweeps):
    """Red-black SOR; ``active`` = free non-goal nodes, others keep their u.

    Rows are processed in parallel per colour.  If axis 0 is periodic with an
    odd length, its last row has the same colour as its neighbour row 0, so
    that row is relaxed on its own after the parallel part (deterministic).
    """
    n0, n1 = u.shape
    split = n0 - 1 if (per0 and n0 % 2 == 1) else n0
    rowmax = np.zeros(n0)
    change = np.inf
    sweeps = 0
    while sweeps < max_sweeps:
        for colour in range(2):
            for part in range(2):
                lo = 0 if part == 0 else split
                hi = split if part == 0 else n0
                for i in nb.prange(lo, hi):
                    if colour == 0:
                        rowmax[i] = 0.0
                    im = i - 1 if i > 0 else n0 - 1
                    ip = i + 1 if i < n0 - 1 else 0
                    has_im = i > 0 or per0
                    has_ip = i < n0 - 1 or per0
                    m = rowmax[i]
                    for j in range((i + colour) % 2, n1, 2):
                        if not active[i, j]:
                            continue
                        s = 0.0
                        if has_im:
                            s += u[im, j]
                        if has_ip:
                            s += u[ip, j]
                        if j > 0:
                            s += u[i, j - 1]
                        elif per1:
                            s += u[i, n1 - 1]
                        if j < n1 - 1:
                            s += u[i, j + 1]
                        elif per1:
                            s += u[i, 0]
                        old = u[i, j]
                        new = old + omega * (0.25 * s - old)
                        u[i, j] = new
                        d = abs(new - old)
                        if d > m:
                            m = d
                    rowmax[i] = m
        sweeps += 1
        change = rowmax.max()
        if change < tol:
            break
    return sweeps, change


@nb.njit(cache=True, parallel=True, nogil=True)
def _rb_sor_3d(u, active, per0, per1, per2, omega, tol, max_sweeps):
    """3-D red-black SOR, parallel over axis-0 slabs (see :func:`_rb_sor_2d`)."""
    n0, n1, n2 = u.shape
    split = n0 - 1 if (per0 and n0 % 2 == 1) else n0
    rowmax = np.zeros(n0)
    change = np.inf
    sweeps = 0
    inv6 = 1.0 / 6.0
    while sweeps < max_sweeps:
        for colour in range(2):
            for part in range(2):
                lo = 0 if part == 0 else split
                hi = split if part == 0 else n0
                for i in nb.prange(lo, hi):
                    if colour == 0:
                        rowmax[i] = 0.0
                    im = i - 1 if i > 0 else n0 - 1
                    ip = i + 1 if i < n0 - 1 else 0
                    has_im = i > 0 or per0
                    has_ip = i < n0 - 1 or per0
                    m = rowmax[i]
                    for j in range(n1):
                        jm = j - 1 if j > 0 else n1 - 1
                        jp = j + 1 if j < n1 - 1 else 0
                        has_jm = j > 0 or per1
                        has_jp = j < n1 - 1 or per1
                        for k in range((i + j + colour) % 2, n2, 2):
                            if not active[i, j, k]:
                                continue
                            s = 0.0
                            if has_im:
                                s += u[im, j, k]
                            if has_ip:
                                s += u[ip, j, k]
                            if has_jm:
                                s += u[i, jm, k]
                            if has_jp:
                                s += u[i, jp, k]
                            if k > 0:
                                s += u[i, j, k - 1]
                            elif per2:
                                s += u[i, j, n2 - 1]
                            if k < n2 - 1:
                                s += u[i, j, k + 1]
                            elif per2:
                                s += u[i, j, 0]
                            old = u[i, j, k]
                            new = old + omega * (s * inv6 - old)
                            u[i, j, k] = new
                            d = abs(new - old)
                            if d > m:
                                m = d
                    rowmax[i] = m
        sweeps += 1
        change = rowmax.max()
        if change < tol:
            break
    return sweeps, change


def sor_omega(shape) -> float:
    """Near-optimal SOR factor 2 / (1 + sin(pi / N)), N = largest axis length."""
    return 2.0 / (1.0 + math.sin(math.pi / max(shape)))


def sor_u(occupied, periodic, goal_nodes, tol=1e-6, max_sweeps=100_000, omega=None):
    """Red-black SOR on the flipped linear form.

    u = 1 at goal nodes, 0 at obstacles and walls, free nodes start at 0; stop
    when the largest absolute change of u in one sweep is below ``tol``.
    Returns ``(u, sweeps, change)``; u float64 array of the grid shape equals
    ``1 - Phi / Phi0`` of the paper's problem at convergence.
    """
    occ, per, goals = validate_problem(occupied, periodic, goal_nodes)
    if omega is None:
        omega = sor_omega(occ.shape)
    u = np.zeros(occ.shape)
    u[tuple(goals.T)] = 1.0
    active = ~occ
    active[tuple(goals.T)] = False
    if occ.ndim == 2:
        sweeps, change = _rb_sor_2d(u, active, per[0], per[1], float(omega), float(tol), int(max_sweeps))
    else:
        sweeps, change = _rb_sor_3d(u, active, per[0], per[1], per[2], float(omega), float(tol),
                                    int(max_sweeps))
    return u, int(sweeps), float(change)


def sor(occupied, periodic, goal_nodes, tol=1e-6, max_sweeps=100_000, omega=None) -> Field:
    """Red-black SOR on the flipped linear form (see :func:`sor_u`) as a Field."""
    t0 = time.perf_counter()
    occ, per, goals = validate_problem(occupied, periodic, goal_nodes)
    u, sweeps, change = sor_u(occ, per, goals, tol, max_sweeps, omega)
    return _linear_field(u, occ, per, goals, "sor", sweeps, change, change < tol, t0)


def multigrid_u(occupied, periodic, goal_nodes, tol=1e-12, max_iter=500):
    """The flipped linear form solved by multigrid-preconditioned CG (``_multigrid``).

    Same problem and result as :func:`sor_u` (u = 1 at goal nodes, 0 at
    obstacles, walls and nodes not connected to the goal); stops when the
    largest residual ``2n u_i - sum_j u_j`` is below ``tol``.  Returns ``(u,
    iterations, residual)``; u float64 array of the grid shape.
    """
    occ, per, goals = validate_problem(occupied, periodic, goal_nodes)
    order, nbr, coords, _ = _grid_ordered_graph(occ, per, goals)
    u_nodes, its, res = _mg.solve(nbr, len(goals), coords, occ.shape, tol=tol, max_iter=max_iter)
    u = np.zeros(occ.size)
    u[order] = u_nodes
    return u.reshape(occ.shape), int(its), float(res)


def multigrid(occupied, periodic, goal_nodes, tol=1e-12, max_sweeps=500) -> Field:
    """Multigrid-preconditioned CG on the flipped linear form (see
    :func:`multigrid_u`) as a Field; ``sweeps`` counts CG iterations.  Like
    ``sor`` it is exact to an absolute tolerance only: where u is below it
    (deep pockets on large grids) log u is noise."""
    t0 = time.perf_counter()
    occ, per, goals = validate_problem(occupied, periodic, goal_nodes)
    u, its, res = multigrid_u(occ, per, goals, tol, max_sweeps)
    return _linear_field(u, occ, per, goals, "multigrid", its, res, res < tol, t0)


# --------------------------------------------------------------------------
# breadth-first search and the node graph of the reachable nodes
# --------------------------------------------------------------------------
@nb.njit(cache=True, nogil=True)
def _grid_neighbours(shape, periodic):
    """Flat index of each node's 2n face neighbours, -1 beyond a wall.

    int64 (N, 2n), column 2a + (0|1) = the (-|+) neighbour along axis a, wrapping
    on periodic axes.  One odometer pass over the grid, no integer divisions.
    """
    ndim = shape.size
    n = 1
    for a in range(ndim):
        n *= shape[a]
    strides = np.ones(ndim, np.int64)
    for a in range(ndim - 2, -1, -1):
        strides[a] = strides[a + 1] * shape[a + 1]
    out = np.empty((n, 2 * ndim), np.int64)
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
        a = ndim - 1
        while a >= 0:
            coord[a] += 1
            if coord[a] < shape[a]:
                break
            coord[a] = 0
            a -= 1
    return out


@nb.njit(cache=True, nogil=True)
def _bfs(occ_flat, gnbr, goal_flat):
    """BFS through free nodes from the goal nodes over the grid neighbour table.

    Returns ``(dist, order)``: dist int64 per flat node (-1 = not reached),
    order = reached flat nodes in BFS order (goal nodes first).
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
def _neighbour_table(order, gnbr):
    """nbr[k, 2a + (0|1)] = position in ``order`` of the (-|+) neighbour of node
    ``order[k]`` along axis a, or ``len(order)`` (a dummy node with u = 0) for
    walls, obstacles and nodes not in ``order``."""
    n = order.size
    deg = gnbr.shape[1]
    pos = np.full(gnbr.shape[0], n, np.int32)
    for k in range(n):
        pos[order[k]] = k
    nbr = np.empty((n, deg), np.int32)
    for k in range(n):
        f = order[k]
        for a in range(deg):
            g = gnbr[f, a]
            nbr[k, a] = n if g < 0 else pos[g]
    return nbr


def _graph(occ, per, goals):
    """(dist, order, gnbr) of a validated problem: BFS from the goal nodes (which
    come first in ``order``; ``validate_problem`` made them distinct and free)."""
    gnbr = _grid_neighbours(np.array(occ.shape, np.int64), np.array(per, np.bool_))
    goal_flat = np.ravel_multi_index(tuple(goals.T), occ.shape).astype(np.int64)
    dist, order = _bfs(occ.ravel(), gnbr, goal_flat)
    return dist, order, gnbr


def _grid_ordered_graph(occ, per, goals):
    """The reachable nodes, goal nodes first, then the others in grid order (memory
    locality): ``(order, nbr, coords, dist)`` with ``nbr`` from :func:`_neighbour_table`,
    ``coords`` int (N, ndim) and ``dist`` the BFS distance of each, in that order."""
    dist, order, gnbr = _graph(occ, per, goals)
    n_goal = len(goals)
    order = np.concatenate([order[:n_goal], np.sort(order[n_goal:])])
    coords = np.stack(np.unravel_index(order, occ.shape), axis=1)
    return order, _neighbour_table(order, gnbr), coords, dist[order]


def bfs_distance(occupied, periodic, goal_nodes) -> np.ndarray:
    """Graph distance (in face steps through free nodes) from the goal; -1 at
    obstacles and at free nodes not connected to the goal.  int64, grid shape."""
    occ, per, goals = validate_problem(occupied, periodic, goal_nodes)
    return _graph(occ, per, goals)[0].reshape(occ.shape)


# --------------------------------------------------------------------------
# log-harmonic: u = mant * 2**expo per node, symmetric SOR in BFS order
# --------------------------------------------------------------------------
_P2_OFF = 1100
#: _P2[k + _P2_OFF] = 2.0**k for k in [-1100, 1100] (0 / inf at the ends).
with np.errstate(over="ignore"):
    _P2 = np.ldexp(1.0, np.arange(-_P2_OFF, _P2_OFF + 1))


@nb.njit(cache=True, nogil=True, inline="always")
def _p2(k, p2):
    if k < -_P2_OFF:
        k = -_P2_OFF
    elif k > 1000:
        k = 1000
    return p2[k + _P2_OFF]


@nb.njit(cache=True, nogil=True)
def _log_sgs(mant, expo, nbr, n_goal, lb_expo, tol, max_passes, p2):
    """Symmetric Gauss-Seidel on u_i = mant_i * 2**expo_i over the node graph.

    Nodes ``0..n_goal-1`` are goal nodes (u = 1, fixed), ``n_goal..n-1`` the
    other reachable nodes in BFS order, node ``n`` a dummy (u = 0) standing
    for walls and obstacles.  Passes alternate forward / backward.  Each
    update sets u to the mean of its neighbours, evaluated in the scale 2**E of the
    largest neighbour so nothing over- or underflows; the result is clipped
    from below by the subharmonic lower bound 2**lb_expo (which the solution
    satisfies) and stored normalised (mantissa in [0.5, 1)).

    Returns ``(passes, change)`` with change = max |new - old| / new over the
    last forward + backward pair (the relative change, = |d log u| to first
    order); stops after a backward pass once change < tol.
    """
    n = nbr.shape[0]
    deg = nbr.shape[1]
    inv_deg = 1.0 / deg
    change = np.inf
    passes = 0
    while passes < max_passes:
        forward = passes % 2 == 0
        if forward:
            change = 0.0
        for t in range(n_goal, n):
            i = t if forward else n - 1 + n_goal - t
            big = expo[nbr[i, 0]]
            for a in range(1, deg):
                ea = expo[nbr[i, a]]
                if ea > big:
                    big = ea
            s = 0.0
            for a in range(deg):
                j = nbr[i, a]
                s += mant[j] * _p2(expo[j] - big, p2)
            s *= inv_deg
            old = mant[i] * _p2(expo[i] - big, p2)
            new = s
            if new > 0.0 and new >= _p2(lb_expo[i] - big, p2):
                rel = abs(new - old) / new
                m, k = math.frexp(new)
                mant[i] = m
                expo[i] = big + k
            else:
                # rounding below the known lower bound: clip to it
                rel = 1.0
                mant[i] = 0.5
                expo[i] = lb_expo[i] + 1
            if rel > change:
                change = rel
        passes += 1
        if change < tol and not forward:
            break
    return passes, change


@nb.njit(cache=True, nogil=True)
def _scatter_log(mant, expo, order, n_flat):
    out = np.full(n_flat, -np.inf)
    ln2 = math.log(2.0)
    for k in range(order.size):
        out[order[k]] = math.log(mant[k]) + expo[k] * ln2
    return out


def _log_field(occ, per, goals, solver, tol, max_sweeps):
    """Symmetric Gauss-Seidel in BFS order on the node graph (log_gs)."""
    t0 = time.perf_counter()
    dist, order, gnbr = _graph(occ, per, goals)
    nbr = _neighbour_table(order, gnbr)
    n = order.size
    n_goal = len(goals)
    bits = int(math.ceil(math.log2(2 * occ.ndim)))       # 2**bits >= 2n
    lb_expo = np.empty(n + 1, np.int64)
    lb_expo[:n] = -bits * dist[order]
    lb_expo[n] = -(1 << 40)
    mant = np.ones(n + 1)
    mant[n] = 0.0
    expo = lb_expo.copy()
    passes, change = _log_sgs(mant, expo, nbr, n_goal, lb_expo, float(tol),
                               int(max_sweeps), _P2)
    converged = change < tol
    log_u = _scatter_log(mant, expo, order, occ.size).reshape(occ.shape)
    return Field(log_u, occ, per, goals, solver, int(passes), float(change), bool(converged),
                 time.perf_counter() - t0)


#: Linear solve of the multigrid phase: stop when the largest residual is below this.
MG_RESIDUAL_TOL = 1e-12
#: After the multigrid phase, nodes with u below this are settled in log space
#: (where the linear solve's absolute error is not small relative to u).
MG_SETTLE_BELOW = 1e-5
#: ... within this many sweeps per node of the longest grid axis, else the SOR route.
MG_SETTLE_SWEEPS_PER_NODE = 1
#: Multigrid values above this are taken as resolved; the others start from a
#: breadth-first extension of them (a factor 1/2n per step, never below the lower bound).
MG_RESOLVED_ABOVE = 1e-11
#: "auto" takes the multigrid route on every 2-D grid and on 3-D grids from this
#: many nodes (measured: SOR first at 36x37x37, multigrid first at 72x73x73).
MG_MIN_NODES_3D = 100_000
PHASE1_CHOICES = ("auto", "multigrid", "sor")


@nb.njit(cache=True, nogil=True)
def _extend_log_start(u, nbr, n_goal, lb_s, resolved_above, log_deg):
    """Initial log scales for the multigrid route, float64 (N,).

    Nodes with u > ``resolved_above`` start at log u; every other node at the
    value of its nearest resolved node (graph steps) less ``log_deg`` per step,
    but never below its lower bound ``lb_s``: a start on the scale of its
    neighbours, so the coefficients exp(s_j - s_i) stay moderate.
    """
    n = nbr.shape[0]
    deg = nbr.shape[1]
    s0 = np.empty(n)
    seen = np.zeros(n, np.bool_)
    queue = np.empty(n, np.int64)
    tail = 0
    for i in range(n):
        if i < n_goal or u[i] > resolved_above:
            s0[i] = 0.0 if i < n_goal else math.log(u[i])
            seen[i] = True
            queue[tail] = i
            tail += 1
    head = 0
    while head < tail:
        i = queue[head]
        head += 1
        for a in range(deg):
            j = nbr[i, a]
            if j >= n or seen[j]:
                continue
            seen[j] = True
            s0[j] = max(s0[i] - log_deg, lb_s[j])
            queue[tail] = j
            tail += 1
    for i in range(n):
        if not seen[i]:
            s0[i] = lb_s[i]
    return s0


def log_harmonic(occupied, periodic, goal_nodes, tol=1e-6, max_sweeps=100_000, omega=None,
                 rel_tol=1e-4, finish_sweeps=2, phase1="auto") -> Field:
    """Underflow-free harmonic field (planner default), see the module doc.

    u = w · exp(s) per node (``_scaled_field``), never below the BFS lower bound.
    Phase 1 settles the bulk of the field in the linear form, by one of

    * ``"multigrid"``: conjugate gradients preconditioned by an aggregation
      V-cycle (``_multigrid``) to a residual below ``MG_RESIDUAL_TOL`` (far below
      the paper's 1e-6 change), started at 0; the values become the initial
      scales s = log max(u, lower bound).  Phase 2 then relaxes only the nodes
      with u < ``MG_SETTLE_BELOW``, where that absolute accuracy is not a
      relative one, within ``MG_SETTLE_SWEEPS_PER_NODE`` sweeps per node of the
      longest axis.  Where that does not settle, or the result fails the ascent
      check (deep maze-like regions, whose values the linear solve cannot see),
      the SOR route runs from the start.
    * ``"sor"``: red–black SOR (``omega`` defaults to :func:`sor_omega`) from the
      lower bound until the largest change of u in a sweep is below ``tol`` (the
      paper's stopping rule, absolute); phase 2 relaxes every node.
    * ``"auto"`` (default): multigrid on 2-D grids and on 3-D grids of at least
      ``MG_MIN_NODES_3D`` nodes, SOR on smaller 3-D grids: the faster of the two
      on the paper's scenes (``python -m spacerobot_planner.bench field``).

    Phase 2: plain Gauss–Seidel sweeps until the largest relative change (|Δ log
    u|) is below ``rel_tol``: the linear phase gets the bulk of the field right
    but leaves tiny values in deep pockets wrong, plain sweeps fix them locally.
    Then ``finish_sweeps`` plain sweeps over every node and a check that every
    reachable non-goal node has a strictly higher neighbour; should any not (e.g.
    ``max_sweeps`` stopped it early), the result is replaced by ``log_gs`` with the
    same budget, valid by construction (``solver`` then reads
    ``"log_harmonic(fallback log_gs)"``).  ``sweeps`` counts the passes of all
    phases (a multigrid iteration counts as one); ``residual`` is the last
    relative change.
    """
    t0 = time.perf_counter()
    occ, per, goals = validate_problem(occupied, periodic, goal_nodes)
    if phase1 not in PHASE1_CHOICES:
        raise ValueError(f"phase1: expected one of {PHASE1_CHOICES}, got {phase1!r}")
    if omega is None:
        omega = sor_omega(occ.shape)
    if not 0.0 < omega < 2.0:
        raise ValueError(f"omega: must lie in (0, 2), got {omega}")
    use_mg = phase1 == "multigrid" or (phase1 == "auto" and (occ.ndim == 2 or occ.size >= MG_MIN_NODES_3D))
    order, nbr, coords, dist = _grid_ordered_graph(occ, per, goals)
    n_goal = len(goals)
    parity = (coords.sum(axis=1) % 2).astype(np.int64)
    lb_s = -dist * math.log(2 * occ.ndim)              # (2n)^-d, natural log
    chunks = 16
    goal_mask = np.zeros(occ.shape, np.bool_)
    goal_mask[tuple(goals.T)] = True

    def finish(state, change):
        """Finishing sweeps, log u on the grid, and whether it is a valid ascent field."""
        more, _, _ = _sf.scaled_sweeps(*state[:5], nbr, *state[5:], 1.0, 0.0, False, int(finish_sweeps),
                                       chunks)
        w, s_log = state[0], state[1]
        log_u = np.full(occ.size, -np.inf)
        log_u[order] = s_log[:-1] + np.log(w[:-1])
        log_u = log_u.reshape(occ.shape)
        valid = np.all(np.isfinite(log_u.ravel()[order])) and \
            ascent_defects(log_u, goal_mask, per).shape[0] == 0
        return log_u, more, valid

    sweeps = 0
    if use_mg:
        u, sweeps, _ = _mg.solve(nbr, n_goal, coords, occ.shape, tol=min(MG_RESIDUAL_TOL, tol),
                                    max_iter=max_sweeps)
        s0 = _extend_log_start(u, nbr, n_goal, lb_s, MG_RESOLVED_ABOVE, math.log(2 * occ.ndim))
        state = _sf.prepare(nbr, n_goal, lb_s, parity, s0=s0)
        members, starts = _sf.restrict_classes(state[6], state[7], u < MG_SETTLE_BELOW)
        # Pockets next to the solved bulk settle in a few sweeps; a deep region (a
        # maze: u down to 1e-8000, far below what the linear solve resolves) starts
        # from its lower bound and would take very long: past the budget, or if the
        # result is not a valid ascent field, take the SOR route from the start.
        budget = min(MG_SETTLE_SWEEPS_PER_NODE * max(occ.shape), max(0, int(max_sweeps) - sweeps))
        more, change, _ = _sf.scaled_sweeps(*state[:5], nbr, state[5], members, starts, 1.0,
                                            float(rel_tol), False, budget, chunks)
        sweeps += more
        if change < rel_tol:
            log_u, more, valid = finish(state, change)
            sweeps += more
            if valid:
                return Field(log_u, occ, per, goals, "log_harmonic", int(sweeps), float(change), True,
                             time.perf_counter() - t0)
    state = _sf.prepare(nbr, n_goal, lb_s, parity)
    more, _, _ = _sf.scaled_sweeps(*state[:5], nbr, *state[5:], float(omega), float(tol), True,
                                   max(0, int(max_sweeps) - sweeps), chunks)
    sweeps += more
    more, change, _ = _sf.scaled_sweeps(*state[:5], nbr, *state[5:], 1.0, float(rel_tol), False,
                                        max(0, int(max_sweeps) - sweeps), chunks)
    sweeps += more
    log_u, more, valid = finish(state, change)
    sweeps += more
    if not valid:
        fb = _log_field(occ, per, goals, "log_harmonic(fallback log_gs)", rel_tol, max_sweeps)
        return Field(fb.log_u, occ, per, goals, fb.solver, sweeps + fb.sweeps, fb.residual, fb.converged,
                     time.perf_counter() - t0)
    return Field(log_u, occ, per, goals, "log_harmonic", int(sweeps), float(change), bool(change < rel_tol),
                 time.perf_counter() - t0)


def log_gs(occupied, periodic, goal_nodes, tol=1e-4, max_sweeps=1_000_000) -> Field:
    """Plain symmetric Gauss-Seidel on the underflow-free u from the BFS lower
    bound: every iterate is a valid ascent field (anytime)."""
    occ, per, goals = validate_problem(occupied, periodic, goal_nodes)
    return _log_field(occ, per, goals, "log_gs", tol, max_sweeps)


# --------------------------------------------------------------------------
# ascent check
# --------------------------------------------------------------------------
@nb.njit(cache=True, nogil=True)
def _defects_2d(log_u, is_goal, per0, per1):
    n0, n1 = log_u.shape
    out = np.empty((0, 2), np.int64)
    bad = []
    for i in range(n0):
        for j in range(n1):
            v = log_u[i, j]
            if is_goal[i, j] or not v > -np.inf:
                continue
            up = False
            if i > 0 or per0:
                up |= log_u[(i - 1) % n0, j] > v
            if i < n0 - 1 or per0:
                up |= log_u[(i + 1) % n0, j] > v
            if j > 0 or per1:
                up |= log_u[i, (j - 1) % n1] > v
            if j < n1 - 1 or per1:
                up |= log_u[i, (j + 1) % n1] > v
            if not up:
                bad.append(i * n1 + j)
    if len(bad) == 0:
        return out
    out = np.empty((len(bad), 2), np.int64)
    for t in range(len(bad)):
        out[t, 0] = bad[t] // n1
        out[t, 1] = bad[t] % n1
    return out


@nb.njit(cache=True, nogil=True)
def _defects_3d(log_u, is_goal, per0, per1, per2):
    n0, n1, n2 = log_u.shape
    bad = []
    for i in range(n0):
        for j in range(n1):
            for k in range(n2):
                v = log_u[i, j, k]
                if is_goal[i, j, k] or not v > -np.inf:
                    continue
                up = False
                if i > 0 or per0:
                    up |= log_u[(i - 1) % n0, j, k] > v
                if i < n0 - 1 or per0:
                    up |= log_u[(i + 1) % n0, j, k] > v
                if j > 0 or per1:
                    up |= log_u[i, (j - 1) % n1, k] > v
                if j < n1 - 1 or per1:
                    up |= log_u[i, (j + 1) % n1, k] > v
                if k > 0 or per2:
                    up |= log_u[i, j, (k - 1) % n2] > v
                if k < n2 - 1 or per2:
                    up |= log_u[i, j, (k + 1) % n2] > v
                if not up:
                    bad.append((i * n1 + j) * n2 + k)
    out = np.empty((len(bad), 3), np.int64)
    for t in range(len(bad)):
        f = bad[t]
        out[t, 0] = f // (n1 * n2)
        out[t, 1] = (f // n2) % n1
        out[t, 2] = f % n2
    return out


def ascent_defects(log_u, goal_mask, periodic) -> np.ndarray:
    """Nodes with finite log u, not goal, and no strictly higher face
    neighbour (where steepest ascent would get stuck).  int64 array (m, ndim)."""
    log_u = np.ascontiguousarray(log_u, dtype=np.float64)
    goal_mask = np.ascontiguousarray(goal_mask, dtype=np.bool_)
    per = tuple(bool(p) for p in periodic)
    if log_u.ndim == 2:
        return _defects_2d(log_u, goal_mask, per[0], per[1])
    return _defects_3d(log_u, goal_mask, per[0], per[1], per[2])


# --------------------------------------------------------------------------
# JIT warm-up
# --------------------------------------------------------------------------
def warm_up() -> None:
    """Compile (or load from numba's cache) every solver kernel, 2-D and 3-D, on
    grids just large enough to build multigrid levels (a few hundred ms cold)."""
    occ2 = np.zeros((40, 41), dtype=bool)
    occ2[10:20, 5:30] = True
    occ3 = np.zeros((12, 13, 13), dtype=bool)
    occ3[3:6, 2:10, 2:10] = True
    for occ, per, goal in ((occ2, (False, False), (39, 40)), (occ3, (True, False, False), (11, 12, 12))):
        for solver in SOLVERS:
            solve_field(occ, per, [goal], solver=solver, max_sweeps=50)
        for phase1 in ("multigrid", "sor"):
            log_harmonic(occ, per, [goal], phase1=phase1)


# --------------------------------------------------------------------------
# dispatcher
# --------------------------------------------------------------------------
_SOLVER_FUNCS = {
    "gauss_seidel": gauss_seidel,
    "sor": sor,
    "log_harmonic": log_harmonic,
    "log_gs": log_gs,
    "multigrid": multigrid,
}


def solve_field(occupied, periodic, goal_nodes, solver=DEFAULT_SOLVER, tol=None, max_sweeps=None,
                **opts) -> Field:
    """Solve the harmonic field with the named solver (one of ``SOLVERS``).

    ``tol`` / ``max_sweeps`` default per solver (``DEFAULT_TOL``,
    ``DEFAULT_MAX_SWEEPS``); extra keyword options go to the solver
    (``phi0`` for gauss_seidel, ``omega`` for sor / log_harmonic).
    Raises ValueError for an unknown solver name or a malformed problem.
    """
    if solver not in _SOLVER_FUNCS:
        raise ValueError(f"solver: unknown solver {solver!r}; expected one of {SOLVERS}")
    tol = DEFAULT_TOL[solver] if tol is None else float(tol)
    max_sweeps = DEFAULT_MAX_SWEEPS[solver] if max_sweeps is None else int(max_sweeps)
    return _SOLVER_FUNCS[solver](occupied, periodic, goal_nodes, tol=tol, max_sweeps=max_sweeps, **opts)
