"""
The multigrid solve against a direct sparse solve of the same grid problem, built here from the grid.

The solve's V-cycle runs in float32 inside a float64 CG: what it returns must still meet the
residual tolerance it reports, measured on the grid's own Laplacian, and agree with
SciPy's direct solve.  The problems: random obstacles on a 2-D grid and on a 3-D grid with
an odd periodic axis (two black rows are neighbours across its seam), the unknowns in a
random order, and one small enough to be its own coarsest level.
"""

import itertools
import time

import numpy as np
import pytest
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from spacerobot_planner.field import multigrid


def _grid_problem(shape, periodic, seed, obstacle_fraction=0.2):
    """
    Return ``(nbr, coords, rhs, A)``: a Dirichlet Laplace problem, goal 1 at one corner.

    nbr / coords / rhs in multigrid.solve's form (unknowns in a random order); A: the
    same operator as a SciPy matrix, built from the grid's face neighbours.
    """
    rng = np.random.default_rng(seed)
    free = rng.random(shape) >= obstacle_fraction
    goal = (0,) * len(shape)
    free[goal] = True
    cells = [c for c in itertools.product(*(range(s) for s in shape)) if free[c] and c != goal]
    rng.shuffle(cells)
    index = {c: k for k, c in enumerate(cells)}
    n, deg = len(cells), 2 * len(shape)
    nbr = np.full((n, deg), n, np.int64)
    rhs = np.zeros(n)
    rows, cols, vals = [], [], []
    for k, c in enumerate(cells):
        rows.append(k)
        cols.append(k)
        vals.append(float(deg))
        for a in range(len(shape)):
            for d, step in enumerate((-1, 1)):
                m = list(c)
                m[a] += step
                if periodic[a]:
                    m[a] %= shape[a]
                elif not 0 <= m[a] < shape[a]:
                    continue
                m = tuple(m)
                if m == goal:
                    rhs[k] += 1.0
                elif m in index:
                    nbr[k, 2 * a + d] = index[m]
                    rows.append(k)
                    cols.append(index[m])
                    vals.append(-1.0)
    A = sp.csr_matrix((vals, (rows, cols)), shape=(n, n))
    return nbr, np.array(cells, np.int64), rhs, A


@pytest.mark.parametrize("shape, periodic, seed", [
    ((61, 47), (False, False), 1),
    ((15, 12, 14), (True, False, False), 2),   # even periodic count
    ((13, 12, 10), (True, False, False), 3),   # odd periodic count: black rows meet across the seam
    ((7, 9), (False, True), 4),                # its own coarsest level
])
def test_the_solve_meets_its_residual_and_matches_a_direct_solve(shape, periodic, seed):
    nbr, coords, rhs, A = _grid_problem(shape, periodic, seed)
    # only the unknowns joined to the goal (the solve's precondition: SPD)
    _, labels = sp.csgraph.connected_components(A, directed=False)
    touching = np.unique(labels[rhs > 0])
    keep = np.isin(labels, touching)
    new = np.full(len(rhs) + 1, keep.sum())
    new[np.flatnonzero(keep)] = np.arange(keep.sum())
    nbr = new[nbr[keep]]
    coords, rhs, A = coords[keep], rhs[keep], A[keep][:, keep]
    tol = 1e-10
    x, its, res = multigrid.solve(nbr, coords, shape, rhs, tol=tol)
    true_res = np.max(np.abs(rhs - A @ x))
    assert res < tol and its > 0
    assert true_res < tol, f"true residual {true_res:.3g}, reported {res:.3g}"
    direct = spla.spsolve(A.tocsc(), rhs)
    assert np.max(np.abs(x - direct)) < 1e-6 * np.max(np.abs(direct))
    again = multigrid.solve(nbr, coords, shape, rhs, tol=tol)[0]
    assert np.array_equal(x, again), "the same problem gave other bits"


@pytest.mark.parametrize("route", ["graph", "structured"])
def test_a_guess_is_only_where_the_iterations_start(route):
    """
    The initial guess ``x0`` changes where the iterations start, not where they stop.

    From the solution itself the solve takes no iteration; from a wrong guess it meets the same
    residual on the grid's own Laplacian; a guess of another length is refused.
    """
    shape = (16, 12, 14)
    nbr, coords, rhs, A = _grid_problem(shape, (True, False, False), 2, obstacle_fraction=0.0)
    tol = 1e-10
    x, its, _ = multigrid.solve(nbr, coords, shape, rhs, tol=tol, route=route)
    again, its0, res0 = multigrid.solve(nbr, coords, shape, rhs, tol=tol, x0=x, route=route)
    assert its0 == 0 and res0 < tol and np.array_equal(again, x)
    wrong = np.random.default_rng(5).random(len(rhs))
    y, its1, res1 = multigrid.solve(nbr, coords, shape, rhs, tol=tol, x0=wrong, route=route)
    assert its1 > 0 and res1 < tol and np.max(np.abs(rhs - A @ y)) < tol
    near = x + 1e-6 * wrong
    assert 0 < multigrid.solve(nbr, coords, shape, rhs, tol=tol, x0=near, route=route)[1] < its
    with pytest.raises(ValueError, match="x0"):
        multigrid.solve(nbr, coords, shape, rhs, x0=x[1:], route=route)


@pytest.mark.parametrize("m", [1, 2, 3, 5, 15, 30, 68, 100])
def test_the_coarsest_factor_is_lapacks_cholesky(m):
    """The coarsest level's factor (``_cholesky``, in the set-up kernel) against NumPy's LAPACK on SPD matrices."""
    rng = np.random.default_rng(m)
    for _ in range(5):
        b = rng.standard_normal((m, m))
        a = b @ b.T + m * np.eye(m)                  # symmetric positive definite, well conditioned
        low = multigrid._cholesky(a)
        ref = np.linalg.cholesky(a)
        assert np.array_equal(low, np.tril(low))
        assert np.allclose(low, ref, rtol=1e-12, atol=1e-12)
        assert np.allclose(low @ low.T, a, rtol=1e-12, atol=1e-12 * m)


def test_a_matrix_that_is_not_positive_definite_is_refused():
    """A pivot at or below zero is an error, not a NaN factor."""
    with pytest.raises(ValueError, match="not positive definite"):
        multigrid._cholesky(np.array([[1.0, 2.0], [2.0, 1.0]]))


@pytest.mark.parametrize("route", ["graph", "structured"])
def test_a_deadline_stops_the_iterations_on_pythons_clock(route):
    """
    ``deadline`` is a ``time.perf_counter()`` instant, read inside the solve's kernels.

    One already passed stops the solve before its first iteration, with the residual it
    started from (what it returns is still the grid's own Laplacian applied to its iterate);
    one an hour ahead lets it finish, with the same bits as no deadline.
    """
    shape = (16, 12, 14)
    nbr, coords, rhs, A = _grid_problem(shape, (True, False, False), 2, obstacle_fraction=0.0)
    tol = 1e-10
    x, its, res = multigrid.solve(nbr, coords, shape, rhs, tol=tol, route=route)
    late, its_late, res_late = multigrid.solve(nbr, coords, shape, rhs, tol=tol, route=route,
                                               deadline=time.perf_counter())
    assert its > 0 and its_late == 0 and res_late > tol
    assert res_late == pytest.approx(np.max(np.abs(rhs - A @ late)))
    ahead = multigrid.solve(nbr, coords, shape, rhs, tol=tol, route=route, deadline=time.perf_counter() + 3600.0)
    assert ahead[1] == its and np.array_equal(ahead[0], x)
