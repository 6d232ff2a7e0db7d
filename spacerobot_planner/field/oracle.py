"""
A slow reference field for tests and benchmarks (not a planner choice).

The same Dirichlet problem as the planner's route, solved by a sparse direct
factorisation (SciPy's SuperLU, diagonal pivots: on this M-matrix the elimination adds
no cancelling terms to the solution, so small values keep their relative precision),
band by band like the planner but with its own code and a floor of 1e-200, so only
values that would underflow a double take a second band.  Seconds at 36³.
"""
from __future__ import annotations

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

FLOOR = 1e-200


def oracle_log_u(graph) -> np.ndarray:
    """Return log u over ``graph`` (N + 1,), dummy last, by direct solves."""
    n, n_goal = graph.size, graph.n_goal
    nbr = graph.nbr.astype(np.int64)
    deg = nbr.shape[1]
    log_u = np.full(n + 1, -np.inf)
    log_u[:n_goal] = 0.0
    known = np.zeros(n + 1, bool)
    known[:n_goal] = True
    active = np.arange(n_goal, n)
    while active.size:
        local = np.full(n + 1, -1)
        local[active] = np.arange(active.size)
        nb_act = nbr[active]                                  # (m, deg)
        is_known = known[nb_act] & (nb_act < n)
        scale = np.max(np.where(is_known, log_u[nb_act], -np.inf))
        rhs = np.where(is_known, np.exp(log_u[nb_act] - scale), 0.0).sum(axis=1)
        rows, cols = np.nonzero(local[nb_act] >= 0)
        m = active.size
        a = sp.csc_matrix((np.full(rows.size, -1.0), (rows, local[nb_act[rows, cols]])), shape=(m, m))
        a = a + sp.identity(m, format="csc") * deg
        lu = spla.splu(a, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0,
                       options={"SymmetricMode": True})
        x = lu.solve(rhs)
        keep = x >= FLOOR
        if not keep.any():
            raise RuntimeError("oracle: no value above the floor in a band")
        log_u[active[keep]] = np.log(x[keep]) + scale
        known[active[keep]] = True
        active = active[~keep]
    return log_u
