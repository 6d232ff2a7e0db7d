"""
The paper's Gauss–Seidel, literally: the reference solver and every benchmark's baseline.

Potential Φ with obstacles and the walls beyond bounded axes at Φ0, the goal at 0, free
nodes starting at Φ0; lexicographic in-place sweeps of Φ_i = mean of the 2n face
neighbours; stop when the largest absolute change in a sweep is below ``tol``.  In float64
the far field becomes *exactly* Φ0 (flat), so steepest descent stalls there: this is what
the planner's own route (:mod:`.harmonic`) avoids.  Any grid dimension.
"""
from __future__ import annotations

import numba as nb
import numpy as np

from .graph import grid_neighbours


@nb.njit(cache=True, nogil=True)
def _sweeps(phi, fixed, gnbr, phi0, tol, max_sweeps, stop):
    """Sweep until the largest change is below ``tol``, ``max_sweeps``, or ``stop[0]`` (polled per sweep)."""
    n, deg = gnbr.shape
    inv = 1.0 / deg
    change = np.inf
    sweeps = 0
    while sweeps < max_sweeps:
        if stop[0] != 0:
            break
        change = 0.0
        for f in range(n):
            if fixed[f]:
                continue
            s = 0.0
            for a in range(deg):
                g = gnbr[f, a]
                s += phi0 if g < 0 else phi[g]
            new = s * inv
            d = abs(new - phi[f])
            if d > change:
                change = d
            phi[f] = new
        sweeps += 1
        if change < tol:
            break
    return sweeps, change


def gauss_seidel_phi(occ, per, goals, phi0: float = 1.0, tol: float = 1e-6, max_sweeps: int = 200_000,
                     stop=None, cut_edges=None):
    """
    (Φ on the grid, sweeps, last largest change) for a validated problem.

    ``stop``: a termination flag (int64 (1,), None = never), polled before every sweep;
    when it stopped the sweeps the result is partial (the caller checks its token).
    ``cut_edges``: int (k, 2) flat node pairs of face neighbours with a wall between them (a
    repair's: each end reads Φ0 there, as beyond a bounded axis), or None.
    """
    gnbr = grid_neighbours(np.array(occ.shape, np.int64), np.array(per, np.bool_), cut_edges)
    phi = np.full(occ.size, float(phi0))
    fixed = occ.ravel().copy()
    goal_flat = np.ravel_multi_index(tuple(goals.T), occ.shape)
    phi[goal_flat] = 0.0
    fixed[goal_flat] = True
    if stop is None:
        stop = np.zeros(1, np.int64)
    sweeps, change = _sweeps(phi, fixed, gnbr, float(phi0), float(tol), int(max_sweeps), stop)
    return phi.reshape(occ.shape), int(sweeps), float(change)
