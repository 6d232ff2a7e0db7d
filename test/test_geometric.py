"""
The geometric coarse levels of a 2-D band (field/geometric.py) against a direct solve and a product built here.

Each problem is ``test_structured``'s (built from the grid's definition: obstacles, a window of
unknowns, cut edges, the unknowns in a random order) or a maze's first band.  The solve on the
geometric levels must meet the residual it reports on the grid's own Laplacian, agree with
SciPy's direct solve, give the same bits twice, and stop where the other routes stop (a guess,
a deadline).  Level 1's operator must be Galerkin's product Pᵀ A P with the bilinear
prolongation P written here from its definition (SciPy's sparse product), and so must the
level below it.  The coarsest level's factor, with a null column, must solve every consistent
right-hand side.
"""

import itertools
import time

import numba
import numpy as np
import pytest
import scipy.sparse as sp

from spacerobot_planner.field import geometric, multigrid, structured
from test_structured import PROBLEMS, _box_cells, _meets_the_grid_problem, _problem
from test_termination import _first_band, _maze_problem

TWO_D = [name for name in PROBLEMS if name.startswith("2-D") and "periodic" not in name]


def _maze_band():
    """Return a 181² maze's first band ``(nbr, coords, shape, rhs, A)``, as ``harmonic.solve`` poses it (goal 1)."""
    sub, coords, shape, rhs = _first_band(_maze_problem())
    sub = sub.astype(np.int64)
    n = len(rhs)
    rows, cols = np.nonzero(sub < n)
    A = sp.csr_matrix((np.full(rows.size, -1.0), (rows, sub[rows, cols])), shape=(n, n)) + 4 * sp.identity(n)
    return sub, coords, shape, rhs, A.tocsr()


def _case(name):
    if name == "maze":
        return _maze_band()
    nbr, coords, rhs, A = _problem(**PROBLEMS[name])
    return nbr, coords, PROBLEMS[name]["shape"], rhs, A


@pytest.mark.parametrize("name", TWO_D + ["maze"])
def test_the_geometric_levels_solve_the_grid_problem(name):
    nbr, coords, shape, rhs, A = _case(name)
    h = multigrid.Hierarchy(nbr, coords, shape, coarsen=False)
    layout = structured.laid_out(h.nb0, h.coords, shape, h.red0, np.zeros(len(rhs), np.uint32), 0, np.inf)
    assert geometric.applies(2, layout), "the problem does not take the geometric levels"
    tol = 1e-10
    x, its, res = multigrid.solve(nbr, coords, shape, rhs, tol=tol, route="geometric")
    assert 0 < its and res < tol
    _meets_the_grid_problem(x, res, rhs, A, tol)
    again = multigrid.solve(nbr, coords, shape, rhs, tol=tol, route="geometric")
    assert np.array_equal(x, again[0]) and again[1] == its, "the same problem gave other bits"


def test_the_maze_takes_fewer_iterations_than_on_the_aggregation_levels():
    """What the route is for: bilinear prolongation, Galerkin levels, on a 181² maze's first band."""
    nbr, coords, shape, rhs, _ = _maze_band()
    its_geo = multigrid.solve(nbr, coords, shape, rhs, tol=1e-10, route="geometric")[1]
    its_agg = multigrid.solve(nbr, coords, shape, rhs, tol=1e-10, route="structured")[1]
    assert its_geo < its_agg, (its_geo, its_agg)


def _bilinear(q, m_coarse):
    """Return P's rows for padded fine coordinates ``q`` (k, 2): (fine row, coarse flat index, weight) lists."""
    rows, cols, vals = [], [], []
    for r, (q0, q1) in enumerate(q):
        along = []
        for qa in (q0, q1):
            along.append([((qa + 1) // 2, 1.0)] if qa % 2 else [(qa // 2, 0.5), (qa // 2 + 1, 0.5)])
        for (i0, w0), (i1, w1) in itertools.product(*along):
            rows.append(r)
            cols.append(i0 * m_coarse[1] + i1)
            vals.append(w0 * w1)
    return rows, cols, vals


def _stencil_matrix(st, shape):
    """Return a level's 9-point stencils (9, c0 · c1) as a SciPy matrix over its cells."""
    c0, c1 = shape
    rows, cols, vals = [], [], []
    for k in range(9):
        d = (k // 3 - 1) * c1 + k % 3 - 1
        f = np.flatnonzero(st[k])
        rows.append(f)
        cols.append(f + d)
        vals.append(st[k][f])
    rows, cols, vals = np.concatenate(rows), np.concatenate(cols), np.concatenate(vals)
    return sp.csr_matrix((vals, (rows, cols)), shape=(c0 * c1,) * 2)


@pytest.mark.parametrize("name", ["2-D, cut edges", "2-D, a window", "maze"])
def test_the_coarse_levels_are_galerkins_product_with_bilinear_prolongation(name):
    """
    Level 1 = Pᵀ A P and level 2 = P₁ᵀ (level 1) P₁, P bilinear from the padded coordinates of the module's doc.

    The padded coordinates and P are computed here from the definition; the kernels' stencils
    must equal the SciPy product entry for entry (sums of multiples of 1/16: exact).
    """
    nbr, coords, shape, rhs, A = _case(name)
    h = multigrid.Hierarchy(nbr, coords, shape, coarsen=False)
    rows = np.arange(len(rhs)) if h.in_order else np.argsort(h.fine_of_input)   # fine row -> input
    c = h.coords
    lo = c.min(axis=0)
    q = c - lo + 1
    q[:, 1] += (lo[0] + lo[1]) % 2                       # a red row (even sum) has q0 + q1 even
    assert np.all((q.sum(axis=1) % 2 == 0) == (c.sum(axis=1) % 2 == 0))
    m = q.max(axis=0) + 2
    cshape = (m - 2) // 2 + 3
    pr, pc, pv = _bilinear(q, cshape)
    P = sp.csr_matrix((pv, (pr, pc)), shape=(len(rhs), int(np.prod(cshape))))
    A_rows = A[rows][:, rows]                             # A in the fine rows' order
    level1 = (P.T @ A_rows @ P).toarray()
    got1, c0, c1 = geometric._galerkin_fine(*geometric._fine_edges(h.nb0, h.coords, lo[0], lo[1],
                                                                   (lo[0] + lo[1]) % 2, m[0], m[1]), m[0], m[1])
    assert (c0, c1) == tuple(cshape)
    assert np.array_equal(_stencil_matrix(got1, (c0, c1)).toarray(), level1)
    # the level below, from level 1's stencils: its cells are its padded coordinates
    unknown = np.flatnonzero(np.diag(level1) > 0)
    q1 = np.array(np.unravel_index(unknown, (c0, c1))).T
    c2shape = (np.array([c0, c1]) - 2) // 2 + 3
    pr, pc, pv = _bilinear(q1, c2shape)
    P1 = sp.csr_matrix((pv, (pr, pc)), shape=(unknown.size, int(np.prod(c2shape))))
    level2 = (P1.T @ sp.csr_matrix(level1[np.ix_(unknown, unknown)]) @ P1).toarray()
    got2, d0, d1 = geometric._galerkin(got1, c0, c1)
    assert (d0, d1) == tuple(c2shape)
    assert np.array_equal(_stencil_matrix(got2, (d0, d1)).toarray(), level2)


def test_a_semidefinite_coarsest_factor_solves_every_consistent_right_hand_side():
    """A null column (equal columns of the prolongation) is left at 0: a x = b wherever b is in a's range."""
    rng = np.random.default_rng(7)
    for m in (6, 20, 45):
        b = rng.standard_normal((m, m - 3))
        a = b @ b.T                                       # rank m - 3: three null directions
        low = multigrid._cholesky(a, semidefinite=True)
        assert np.count_nonzero(np.diag(low) > 0) == m - 3
        rhs = a @ rng.standard_normal(m)                  # in the range
        x = np.zeros(m)
        y = np.zeros(m)
        geometric._coarsest(x, rhs.astype(np.float32), 0, np.arange(m), low, y)
        assert np.allclose(a @ x, rhs.astype(np.float32), rtol=1e-4, atol=1e-4 * np.max(np.abs(rhs)))
        with pytest.raises(ValueError, match="not positive definite"):
            multigrid._cholesky(a)


def test_a_guess_and_a_deadline_as_on_the_other_routes():
    """From the solution no iteration; from a wrong guess the same residual; a passed deadline stops at once."""
    nbr, coords, shape, rhs, A = _case("2-D, cut edges")
    tol = 1e-10
    x, its, _ = multigrid.solve(nbr, coords, shape, rhs, tol=tol, route="geometric")
    again, its0, res0 = multigrid.solve(nbr, coords, shape, rhs, tol=tol, x0=x, route="geometric")
    assert its0 == 0 and res0 < tol and np.array_equal(again, x)
    wrong = np.random.default_rng(5).random(len(rhs))
    y, its1, res1 = multigrid.solve(nbr, coords, shape, rhs, tol=tol, x0=wrong, route="geometric")
    assert its1 > 0 and res1 < tol and np.max(np.abs(rhs - A @ y)) < tol
    late, its_late, res_late = multigrid.solve(nbr, coords, shape, rhs, tol=tol, route="geometric",
                                               deadline=time.perf_counter())
    assert its > 0 and its_late == 0 and res_late > tol
    assert res_late == pytest.approx(np.max(np.abs(rhs - A @ late)))


@pytest.mark.parametrize("name, geometric_route", [
    ("2-D", True), ("2-D, cut edges", True),
    ("2-D, a window", False),                              # a diamond: its box has too many cells per unknown
    ("2-D, periodic axis 0", False),                       # its edges cross the seam
    ("3-D, periodic axis 0", False),
])
def test_the_rule_takes_the_geometric_levels_for_compact_2d_boxes_without_a_seam(name, geometric_route, monkeypatch):
    """``solve``'s "auto" builds the geometric levels where the cells' box rule holds on a 2-D grid, no seam edge."""
    nbr, coords, rhs, _ = _problem(**PROBLEMS[name])
    shape = PROBLEMS[name]["shape"]
    n = len(rhs)
    wraps = PROBLEMS[name]["periodic"][0] and np.any(nbr[coords[:, 0] == 0, 0] < n)
    compact = _box_cells(coords, shape, wraps) <= structured.MAX_CELLS_PER_UNKNOWN * n
    assert (len(shape) == 2 and not wraps and compact and n >= structured.MIN_UNKNOWNS) == geometric_route, \
        "the case does not test what it says"
    if wraps:                                             # refused before its cells are built
        h = multigrid.Hierarchy(nbr, coords, shape, coarsen=False)
        args = (h.nb0, h.coords, shape, h.red0, np.zeros(n, np.uint32), 0, np.inf)
        assert structured.laid_out(*args) is not None and structured.laid_out(*args, seamless=True) is None
    built = []
    real = geometric.levels

    def counted(*a):
        built.append(1)
        return real(*a)
    monkeypatch.setattr(geometric, "levels", counted)
    auto = multigrid.solve(nbr, coords, shape, rhs, tol=1e-10)
    assert bool(built) == geometric_route
    if geometric_route:
        geo = multigrid.solve(nbr, coords, shape, rhs, tol=1e-10, route="geometric")
        assert np.array_equal(auto[0], geo[0]) and auto[1] == geo[1]


def test_a_long_thin_band_takes_the_aggregation_levels():
    """
    A band 4 nodes across takes the aggregation levels on cells (their bits).

    Halving stops at a box 4 cells across, where the coarsest level would hold hundreds of
    unknowns (above ``COARSEST_MOST``): ``levels`` says None.
    """
    shape = (4, 2000)
    nbr, coords, rhs, A = _problem(shape, (False, False), 31, obstacles=0.0)
    n = len(rhs)
    assert _box_cells(coords, shape, False) <= structured.MAX_CELLS_PER_UNKNOWN * n, "not compact: tests nothing"
    h = multigrid.Hierarchy(nbr, coords, shape, coarsen=False)
    layout = structured.laid_out(h.nb0, h.coords, shape, h.red0, np.zeros(n, np.uint32), 0, np.inf)
    assert geometric.applies(2, layout) and geometric.levels(h.nb0, h.coords, h.red0, layout) is None
    auto = multigrid.solve(nbr, coords, shape, rhs, tol=1e-10)
    agg = multigrid.solve(nbr, coords, shape, rhs, tol=1e-10, route="structured")
    assert np.array_equal(auto[0], agg[0]) and auto[1] == agg[1]
    assert np.max(np.abs(rhs - A @ auto[0])) < 1e-10


@pytest.mark.parametrize("name", ["2-D, cut edges", "2-D, a window", "maze"])
def test_the_fine_transfers_are_the_bilinear_prolongation_and_its_transpose(name):
    """
    Restrict by Pᵀ and prolong by P on the red cells, P bilinear.

    Restriction: level 1's right-hand side = Pᵀ r, r the fine residual b − A x on the red rows (the black ones
    are 0 after a black half-sweep); prolongation: each red unknown gains (P x₁) at its row, no other cell changes.
    P is written here from the padded coordinates' definition, the residual by SciPy's product.
    """
    nbr, coords, shape, rhs, A = _case(name)
    h = multigrid.Hierarchy(nbr, coords, shape, coarsen=False)
    n = len(rhs)
    rows = np.arange(n) if h.in_order else np.argsort(h.fine_of_input)   # fine row -> input
    layout = structured.laid_out(h.nb0, h.coords, shape, h.red0, np.zeros(n, np.uint32), 0, np.inf, True)
    lv = geometric.levels(h.nb0, h.coords, h.red0, layout)
    c = h.coords
    lo = c.min(axis=0)
    q = c - lo + 1
    q[:, 1] += (lo[0] + lo[1]) % 2
    c0, c1 = (int(v) for v in lv.shp[0])
    pr, pc, pv = _bilinear(q, (c0, c1))
    P = sp.csr_matrix((pv, (pr, pc)), shape=(n, c0 * c1))
    rng = np.random.default_rng(5)
    x = rng.standard_normal(n).astype(np.float32)
    b = rng.standard_normal(n)
    xf = layout.to_cells(x).astype(np.float32)
    bf = layout.to_cells(b)
    r = b - A[rows][:, rows] @ x.astype(np.float64)
    r[h.red0:] = 0.0
    res = np.zeros(layout.half + int(lv.tr[1]) + 2)
    bc = np.zeros(lv.off[-1], np.float32)
    geometric._restrict_fine(bf, xf, layout.mask, res, bc, layout.ranges, layout.cut_red, lv.tr)
    want = P.T @ r
    assert np.allclose(bc[:c0 * c1], want, rtol=1e-6, atol=1e-6 * np.max(np.abs(want)))
    xc = np.zeros(lv.off[-1], np.float32)
    xc[:c0 * c1] = rng.standard_normal(c0 * c1)
    before = xf.copy()
    geometric._prolong_fine(xf, xc, layout.mask, lv.tr)
    red = layout.cell[:h.red0]
    gained = (P @ xc[:c0 * c1].astype(np.float64))[:h.red0]
    assert np.allclose(xf.reshape(-1)[red] - before.reshape(-1)[red], gained, rtol=1e-5, atol=1e-5)
    others = np.ones(xf.size, bool)
    others[red] = False
    assert np.array_equal(xf.reshape(-1)[others], before.reshape(-1)[others]), "a cell other than a red unknown moved"


@pytest.mark.parametrize("name", TWO_D + ["maze"])
def test_the_loops_on_all_threads_give_the_same_bits_on_any_number_of_them(name):
    """
    ``chunk_cells`` (a large box's route): every loop in chunks on numba's threads.

    Chunks of 37 cells (boundaries inside every row and level): the same bits and iterations
    with one thread and with numba's threads; the one-thread route's solution within 1e-9 (the
    dot products are summed per chunk), the residual met on the grid's own Laplacian, SciPy's
    direct solve.  Each transfer and the coarse cycle alone: the same values as in one loop.
    """
    nbr, coords, shape, rhs, A = _case(name)
    tol = 1e-10
    one = multigrid.solve(nbr, coords, shape, rhs, tol=tol, route="geometric", chunk_cells=0)
    threads = numba.get_num_threads()
    runs = []
    for n_threads in sorted({1, threads, 2}):
        numba.set_num_threads(min(n_threads, numba.config.NUMBA_NUM_THREADS))
        try:
            runs.append(multigrid.solve(nbr, coords, shape, rhs, tol=tol, route="geometric", chunk_cells=37))
        finally:
            numba.set_num_threads(threads)
    for x, its, res in runs[1:]:
        assert np.array_equal(x, runs[0][0]) and its == runs[0][1] and res == runs[0][2]
    x, its, res = runs[0]
    assert res < tol and abs(its - one[1]) <= 1, (its, one[1])
    assert np.max(np.abs(x - one[0])) <= 1e-9 * np.max(np.abs(one[0]))
    _meets_the_grid_problem(x, res, rhs, A, tol)
    # the kernels alone: chunked and in one loop, the same values
    h = multigrid.Hierarchy(nbr, coords, shape, coarsen=False)
    layout = structured.laid_out(h.nb0, h.coords, shape, h.red0, np.zeros(len(rhs), np.uint32), 0, np.inf, True)
    lv = geometric.levels(h.nb0, h.coords, h.red0, layout)
    rng = np.random.default_rng(3)
    xf = (rng.standard_normal((2, layout.half)) * layout.mask).astype(np.float32)
    bf = rng.standard_normal((2, layout.half)) * layout.mask
    outs = []
    for chunk in (0, 37):
        res_ = np.zeros(layout.half + int(lv.tr[1]) + 2)
        bc = np.zeros(lv.off[-1], np.float32)
        geometric._restrict_fine(bf, xf, layout.mask, res_, bc, layout.ranges, layout.cut_red, lv.tr, chunk)
        xc = np.zeros(lv.off[-1], np.float32)
        big = int(lv.shp[0, 0] * lv.shp[0, 1] + 2 * lv.shp[0, 1] + 2)
        geometric._coarse_cycle(lv.st, lv.inv, lv.off, lv.shp, lv.idx, lv.low, xc, bc.copy(),
                                np.zeros(big, np.float32), np.zeros(lv.idx.size), np.zeros(big, np.float32), chunk // 4)
        xp = xf.copy()
        geometric._prolong_fine(xp, xc, layout.mask, lv.tr, chunk)
        outs.append((bc, xc, xp))
    for a, b in zip(*outs):
        assert np.array_equal(a, b)


def _coarse_operator(lv):
    """Return the coarse cycle as a dense matrix over level 1's unknowns (its columns: the cycle of unit vectors)."""
    m = int(lv.shp[0, 0] * lv.shp[0, 1])
    unknown = np.flatnonzero(lv.inv[:m] > 0)
    big = m + 2 * int(lv.shp[0, 1]) + 2
    out = np.zeros((unknown.size, unknown.size))
    for j, u in enumerate(unknown):
        x = np.zeros(lv.off[-1], np.float32)
        b = np.zeros(lv.off[-1], np.float32)
        b[u] = 1.0
        geometric._coarse_cycle(lv.st, lv.inv, lv.off, lv.shp, lv.idx, lv.low, x, b, np.zeros(big, np.float32),
                                np.zeros(lv.idx.size), np.zeros(big, np.float32))
        out[:, j] = x[unknown]
    return out


def _levels_of(shape, seed, **kw):
    nbr, coords, rhs, _ = _problem(shape, (False, False), seed, **kw)
    h = multigrid.Hierarchy(nbr, coords, shape, coarsen=False)
    layout = structured.laid_out(h.nb0, h.coords, shape, h.red0, np.zeros(len(rhs), np.uint32), 0, np.inf)
    return geometric.levels(h.nb0, h.coords, h.red0, layout)


@pytest.mark.parametrize("shape, seed, kw", [
    ((90, 90), 1, dict(obstacles=0.0)),                  # level 2 even both ways: its restriction's last read
    ((64, 63), 13, dict(obstacles=0.35, cuts=0.02)),
])
def test_the_coarse_cycle_is_symmetric(shape, seed, kw):
    """CG needs a symmetric preconditioner: the coarse cycle's matrix, built column by column, equals its transpose."""
    lv = _levels_of(shape, seed, **kw)
    assert lv is not None and lv.shp.shape[0] >= 3
    b = _coarse_operator(lv)
    assert np.max(np.abs(b - b.T)) <= 1e-5 * np.max(np.abs(b))
    assert np.min(np.linalg.eigvalsh((b + b.T) / 2)) > -1e-6 * np.max(np.abs(b))


@pytest.mark.parametrize("shape, seed, kw", [
    ((64, 63), 13, dict(obstacles=0.35, cuts=0.02)),     # positive entries beside obstacles and cut edges
    ((68, 61), 55, dict(obstacles=0.25, cuts=0.2)),
    ((80, 70), 4, dict(obstacles=0.15)),
])
def test_every_coarse_jacobi_sweep_damps_every_mode(shape, seed, kw):
    """Each coarse level's Jacobi step M (1 / inv) makes 2 M − S positive definite (NumPy's eigenvalues)."""
    lv = _levels_of(shape, seed, **kw)
    for level in range(lv.shp.shape[0] - 1):                # the coarsest is solved, not smoothed
        c0, c1 = (int(v) for v in lv.shp[level])
        o = int(lv.off[level])
        st = lv.st[:, o:o + c0 * c1].astype(float)
        unknown = np.flatnonzero(lv.inv[o:o + c0 * c1] > 0)
        s = _stencil_matrix(st, (c0, c1)).toarray()[np.ix_(unknown, unknown)]
        m = 1.0 / lv.inv[o + unknown].astype(float)
        assert np.min(np.linalg.eigvalsh(2 * np.diag(m) - s)) > 0, f"level {level + 1}"
