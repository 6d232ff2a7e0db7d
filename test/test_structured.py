"""
The multigrid's fine level on the grid's cells (field/structured.py) against its fine level on the node graph.

Each problem is built here from the grid's definition (``oracles.face_neighbours``): the
unknowns (a window of free nodes, not always the whole grid), their known neighbours' values,
periodic axes and cut edges; the Laplacian as a SciPy matrix from the same definition.  The
two routes of ``multigrid.solve`` must give the same solution (1e-9 relative), within one
CG iteration of each other, meet the residual they report on the grid's own Laplacian and
agree with SciPy's direct solve.  The rule that picks the route is checked against the box
of cells counted here.  Level 1 as a K-cycle's (``kcycle``) must give the V-cycle's solution
and SciPy's as well, and run where its rule says (3-D problems of ``KCYCLE_MIN_UNKNOWNS`` or more).
"""

import numba
import numpy as np
import pytest
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from oracles import face_neighbours
from spacerobot_planner.field import multigrid, structured


def _problem(shape, periodic, seed, obstacles=0.15, window=None, cuts=0.0):
    """
    Return ``(nbr, coords, rhs, A)``: a Dirichlet problem on a grid, in multigrid.solve's form.

    Free nodes (``obstacles`` of them blocked at random) inside ``window`` (a bool grid; None:
    all) are the unknowns, the free nodes outside it are known (random values in [0.5, 1]),
    a corner node is a known 1; a fraction ``cuts`` of the face edges is cut.  Only the
    unknowns joined to a known node are kept (the solve's precondition), in a random order.
    A: the Laplacian on them (2 ndim on the diagonal, -1 per face edge between unknowns).
    """
    rng = np.random.default_rng(seed)
    shape = tuple(shape)
    deg = 2 * len(shape)
    free = rng.random(shape) >= obstacles
    free[(0,) * len(shape)] = True
    unknown = free & (np.ones(shape, bool) if window is None else window)
    unknown[(0,) * len(shape)] = False
    known_value = np.where(free & ~unknown, rng.uniform(0.5, 1.0, shape), 0.0).ravel()
    known_value[0] = 1.0
    flat_nbr = face_neighbours(shape, periodic).reshape(deg, -1)
    if cuts:
        edges = [(p, q) for p in range(flat_nbr.shape[1]) for q in flat_nbr[1::2, p] if q >= 0]
        chosen = rng.random(len(edges)) < cuts
        flat_nbr = face_neighbours(shape, periodic, np.array(edges, np.int64)[chosen]).reshape(deg, -1)
    cells = np.flatnonzero(unknown.ravel())
    index = np.full(flat_nbr.shape[1], -1)
    index[cells] = np.arange(cells.size)
    rows, cols, rhs = [], [], np.zeros(cells.size)
    for d in range(deg):
        j = flat_nbr[d, cells]
        inner = (j >= 0) & (index[np.maximum(j, 0)] >= 0)
        rows.append(np.flatnonzero(inner))
        cols.append(index[j[inner]])
        rhs += np.where(j >= 0, known_value[np.maximum(j, 0)], 0.0)
    rows, cols = np.concatenate(rows), np.concatenate(cols)
    lap = sp.csr_matrix((np.full(rows.size, -1.0), (rows, cols)), shape=(cells.size,) * 2) + deg * sp.identity(
        cells.size, format="csr")
    # only the unknowns joined to a known node
    _, labels = sp.csgraph.connected_components(lap, directed=False)
    keep = np.isin(labels, np.unique(labels[rhs > 0]))
    order = rng.permutation(np.flatnonzero(keep))
    local = np.full(cells.size, order.size)
    local[order] = np.arange(order.size)
    nbr = np.full((order.size, deg), order.size, np.int64)
    for d in range(deg):
        j = flat_nbr[d, cells[order]]
        ok = (j >= 0) & (index[np.maximum(j, 0)] >= 0)
        nbr[ok, d] = local[index[j[ok]]]
    coords = np.array(np.unravel_index(cells[order], shape), np.int64).T
    return nbr, coords, rhs[order], lap[order][:, order]


def _meets_the_grid_problem(x, res, rhs, A, tol):
    """Assert that x meets ``tol`` on the grid's own Laplacian A (SciPy's product) and agrees with SciPy's solve."""
    true_res = np.max(np.abs(rhs - A @ x))
    assert true_res < tol, f"true residual {true_res:.3g}, reported {res:.3g}"
    direct = spla.spsolve(A.tocsc(), rhs)
    assert np.max(np.abs(x - direct)) < 1e-6 * np.max(np.abs(direct))


def _diamond(shape, centre, radius):
    """Return the grid nodes within ``radius`` face steps of ``centre`` (no wrap), bool of the grid's shape."""
    return sum(np.abs(g - c) for g, c in zip(np.indices(shape), centre)) <= radius


PROBLEMS = {
    "2-D": dict(shape=(61, 47), periodic=(False, False), seed=1),
    "2-D, periodic axis 0": dict(shape=(40, 37), periodic=(True, False), seed=2),
    "2-D, cut edges": dict(shape=(52, 45), periodic=(False, False), seed=3, cuts=0.05),
    "2-D, a window": dict(shape=(80, 70), periodic=(False, False), seed=4, window=_diamond((80, 70), (45, 30), 24)),
    "3-D, periodic axis 0": dict(shape=(16, 13, 12), periodic=(True, False, False), seed=5),
    "3-D, periodic axis 0, cut edges": dict(shape=(14, 12, 11), periodic=(True, False, False), seed=6, cuts=0.04),
    "3-D, a window across the seam": dict(shape=(18, 15, 14), periodic=(True, False, False), seed=7,
                                          window=np.roll(_diamond((18, 15, 14), (9, 7, 7), 9), 9, axis=0)),
    # level 1 on cells too (an even periodic axis at level 1): cut edges, a window across the seam
    "3-D, periodic axis 0 of 16, cut edges": dict(shape=(16, 12, 11), periodic=(True, False, False), seed=8,
                                                  cuts=0.04),
    "3-D, a window across the seam, 20": dict(shape=(20, 15, 14), periodic=(True, False, False), seed=9,
                                              window=np.roll(_diamond((20, 15, 14), (10, 7, 7), 9), 10, axis=0)),
}


@pytest.mark.parametrize("name", list(PROBLEMS))
def test_the_cells_route_gives_the_graph_routes_solution(name):
    nbr, coords, rhs, A = _problem(**PROBLEMS[name])
    shape = PROBLEMS[name]["shape"]
    h = multigrid.Hierarchy(nbr, coords, shape)
    assert structured.fine_layout(h, shape, 1, max_cells_per_unknown=np.inf, min_unknowns=0) is not None
    tol = 1e-10
    xs, its_s, res_s = multigrid.solve(nbr, coords, shape, rhs, tol=tol, route="structured")
    xg, its_g, res_g = multigrid.solve(nbr, coords, shape, rhs, tol=tol, route="graph")
    assert res_s < tol and res_g < tol
    assert abs(its_s - its_g) <= 1, (its_s, its_g)
    assert np.max(np.abs(xs - xg)) <= 1e-9 * np.max(np.abs(xg))
    _meets_the_grid_problem(xs, res_s, rhs, A, tol)
    again = multigrid.solve(nbr, coords, shape, rhs, tol=tol, route="structured")
    assert np.array_equal(xs, again[0]) and again[1] == its_s, "the same problem gave other bits"


@pytest.mark.parametrize("name", ["2-D, cut edges", "3-D, periodic axis 0, cut edges",
                                  "3-D, periodic axis 0 of 16, cut edges"])
def test_the_layouts_cut_edges_are_the_graphs_missing_face_neighbours(name):
    """
    The layout's cut edges: every pair of unknowns that are face neighbours on the grid where the graph names none.

    Counted here from the rows' coordinates (a periodic axis wraps); the mask is 1 on the rows' cells alone.
    """
    nbr, coords, rhs, _ = _problem(**PROBLEMS[name])
    shape, periodic = PROBLEMS[name]["shape"], PROBLEMS[name]["periodic"]
    h = multigrid.Hierarchy(nbr, coords, shape)
    one = structured.fine_layout(h, shape, 1, max_cells_per_unknown=np.inf, min_unknowns=0)
    n, deg = h.nb0.shape
    row_at = {tuple(c): i for i, c in enumerate(h.coords.tolist())}
    expected = set()
    for i, c in enumerate(h.coords.tolist()):
        for d in range(deg):
            if h.nb0[i, d] < n:
                continue
            other = list(c)
            other[d // 2] += 1 if d % 2 else -1
            if periodic[d // 2]:
                other[d // 2] %= shape[d // 2]
            j = row_at.get(tuple(other))
            if j is not None:
                expected.add((int(one.cell[i]), int(one.cell[j])))
    assert expected, "the problem has no cut edge between unknowns"
    half = one.half
    got = {(int(k), half + int(j)) for k, j in one.cut_red} | {(half + int(k), int(j)) for k, j in one.cut_black}
    assert got == expected
    assert np.array_equal(np.flatnonzero(one.mask.reshape(-1)), np.sort(one.cell))


@pytest.mark.parametrize("name", ["2-D, cut edges", "3-D, periodic axis 0"])
def test_more_sweeps_on_the_cells_give_the_graph_routes_solution(name):
    sweeps = multigrid.sweeps_of(len(PROBLEMS[name]["shape"])) + 1      # more than the grid's own
    nbr, coords, rhs, A = _problem(**PROBLEMS[name])
    shape = PROBLEMS[name]["shape"]
    h = multigrid.Hierarchy(nbr, coords, shape)
    assert structured.fine_layout(h, shape, sweeps, max_cells_per_unknown=np.inf, min_unknowns=0) is not None
    xs, its_s, res_s = multigrid.solve(nbr, coords, shape, rhs, tol=1e-10, sweeps=sweeps, route="structured")
    xg, its_g, _ = multigrid.solve(nbr, coords, shape, rhs, tol=1e-10, sweeps=sweeps, route="graph")
    assert res_s < 1e-10 and abs(its_s - its_g) <= 1, (its_s, its_g)
    assert np.max(np.abs(xs - xg)) <= 1e-9 * np.max(np.abs(xg))
    assert np.max(np.abs(rhs - A @ xs)) < 1e-10


def _box_cells(coords, shape, periodic_axis0):
    """Count the cells of the structured box: the unknowns' extent + 2 ghosts per axis, axes 1.. rounded up to odd."""
    lo, hi = coords.min(axis=0), coords.max(axis=0)
    if periodic_axis0:
        lo[0], hi[0] = 0, shape[0] - 1
    extent = hi - lo + 3
    extent[1:] += 1 - extent[1:] % 2
    return int(np.prod(extent))


def _thin_band(shape):
    """Return the nodes within two steps of the grid's diagonal: a band whose box is mostly empty."""
    i, j = np.indices(shape)
    return np.abs(i - j) <= 2


RULE_CASES = [
    # (problem, expected: the cells route)
    (dict(shape=(61, 47), periodic=(False, False), seed=11), True),
    (dict(shape=(26, 23, 21), periodic=(True, False, False), seed=12, obstacles=0.1), True),
    (dict(shape=(300, 300), periodic=(False, False), seed=13, obstacles=0.0, window=_thin_band((300, 300))), False),
    (dict(shape=(20, 20), periodic=(False, False), seed=14), False),                  # too few unknowns
    (dict(shape=(40, 38), periodic=(False, True), seed=15, obstacles=0.05), False),    # periodic axis 1
    (dict(shape=(39, 40), periodic=(True, False), seed=16, obstacles=0.05), False),    # odd periodic axis 0
    (dict(shape=(7, 7, 6, 6), periodic=(False,) * 4, seed=17, obstacles=0.05), False),  # 4-D
]


@pytest.mark.parametrize("case, expected", RULE_CASES)
def test_the_rule_picks_the_cells_route_where_the_box_is_compact(case, expected):
    nbr, coords, rhs, _ = _problem(**case)
    shape = case["shape"]
    n = len(rhs)
    wraps = case["periodic"][0] and np.any(nbr[coords[:, 0] == 0, 0] < n)
    compact = _box_cells(coords, shape, wraps) <= structured.MAX_CELLS_PER_UNKNOWN * n
    supported = (len(shape) in (2, 3) and n >= structured.MIN_UNKNOWNS and not any(case["periodic"][1:])
                 and not (case["periodic"][0] and shape[0] % 2))
    assert (supported and compact) == expected, "the case does not test what it says"
    h = multigrid.Hierarchy(nbr, coords, shape)
    layout = structured.fine_layout(h, shape, 1)
    assert (layout is not None) == expected
    if layout is not None:
        assert layout.cells == _box_cells(coords, shape, wraps)
    # solve's "auto" route is the rule's: the same bits as the route it picks (a 2-D box whose edges
    # do not cross a periodic seam: the geometric levels under the cells)
    pick = ("geometric" if len(shape) == 2 and not wraps else "structured") if expected else "graph"
    x_auto, its_auto, _ = multigrid.solve(nbr, coords, shape, rhs, tol=1e-10)
    x_pick, its_pick, _ = multigrid.solve(nbr, coords, shape, rhs, tol=1e-10, route=pick)
    assert np.array_equal(x_auto, x_pick) and its_auto == its_pick


def test_an_unknown_route_is_refused():
    with pytest.raises(ValueError, match="route"):
        multigrid.solve(np.zeros((0, 4), np.int64), np.zeros((0, 2), np.int64), (3, 3), np.zeros(0), route="cells")


@pytest.mark.parametrize("route", ["structured", "graph"])
def test_a_right_hand_side_of_another_length_is_refused(route):
    nbr, coords, rhs, _ = _problem(**PROBLEMS["2-D"])
    with pytest.raises(ValueError, match="rhs"):
        multigrid.solve(nbr, coords, PROBLEMS["2-D"]["shape"], rhs[:-5], route=route)


def test_the_warm_up_problems_take_the_cells_routes(monkeypatch):
    """
    ``field._compile_once`` compiles the cells' kernels only if its problems' first bands take those routes.

    The 2-D one the geometric levels under the cells (:mod:`.geometric`), the 3-D one the
    aggregation levels on them (``multigrid._spcg``).
    """
    from spacerobot_planner import field as F
    from spacerobot_planner.field import geometric
    calls = []
    for module, name in ((multigrid, "_spcg"), (geometric, "_gpcg")):
        real = getattr(module, name)

        def counted(*args, _real=real, _name=name):
            calls.append(_name)
            return _real(*args)
        monkeypatch.setattr(module, name, counted)
    for occ, per, goal in F._WARM_PROBLEMS:
        F.solve_field(occ, per, [goal], budget_s=600.0)
    assert "_spcg" in calls, "no warm-up band took the aggregation levels on cells"
    assert "_gpcg" in calls, "no warm-up band took the geometric levels"


def _level1_coords(coords):
    """Return level 1's nodes: the distinct fine coordinates halved (the multigrid's 2^d blocks), (m, ndim)."""
    return np.unique(np.asarray(coords) // 2, axis=0)


@pytest.mark.parametrize("name", list(PROBLEMS))
def test_level_1_on_its_cells_computes_the_graph_levels_values(name):
    """Level 1 on cells is a layout of the same float32 arithmetic: the same bits as level 1 on the node graph."""
    nbr, coords, rhs, A = _problem(**PROBLEMS[name])
    shape = PROBLEMS[name]["shape"]
    h = multigrid.Hierarchy(nbr, coords, shape)
    layout = structured.fine_layout(h, shape, 1, max_cells_per_unknown=np.inf, min_unknowns=0)
    coarse = structured.coarse_layout(h, shape, layout, multigrid.COARSE_SWEEPS, max_cells_per_unknown=np.inf)
    assert structured.coarse_layout(h, shape, layout, 0, max_cells_per_unknown=np.inf) is None, \
        "level 1 on cells without coarse sweeps (the cells' steps start with one)"
    n = len(rhs)
    wraps = PROBLEMS[name]["periodic"][0] and np.any(nbr[coords[:, 0] == 0, 0] < n)
    # level 1 on cells where its rows of one colour are never neighbours: no odd periodic axis 0 at level 1
    assert (coarse is not None) == (not wraps or (shape[0] // 2) % 2 == 0)
    if coarse is not None:
        assert coarse.cell.size == len(_level1_coords(coords))
    x_cells, its_cells, res_cells = multigrid.solve(nbr, coords, shape, rhs, tol=1e-10, route="structured")
    x_graph, its_graph, res_graph = multigrid.solve(nbr, coords, shape, rhs, tol=1e-10, route="structured",
                                                    coarse_cells=False)
    assert np.array_equal(x_cells, x_graph) and its_cells == its_graph and res_cells == res_graph
    assert np.max(np.abs(rhs - A @ x_cells)) < 1e-10


@pytest.mark.parametrize("case, expected", [
    (dict(shape=(61, 47), periodic=(False, False), seed=11), True),
    (dict(shape=(40, 37), periodic=(True, False), seed=18, obstacles=0.05), True),                  # level 1: 20
    (dict(shape=(28, 23, 21), periodic=(True, False, False), seed=12, obstacles=0.1), True),        # level 1: 14
    (dict(shape=(26, 23, 21), periodic=(True, False, False), seed=12, obstacles=0.1), False),       # level 1: 13
    (dict(shape=(300, 300), periodic=(False, False), seed=13, obstacles=0.0, window=_thin_band((300, 300))), False),
])
def test_the_rule_puts_level_1_on_cells_where_its_colours_alternate_and_its_box_is_compact(case, expected):
    nbr, coords, rhs, _ = _problem(**case)
    shape = case["shape"]
    n = len(rhs)
    h = multigrid.Hierarchy(nbr, coords, shape)
    layout = structured.fine_layout(h, shape, 1, max_cells_per_unknown=np.inf, min_unknowns=0)
    assert layout is not None
    wraps = case["periodic"][0] and np.any(nbr[coords[:, 0] == 0, 0] < n)
    shape1 = tuple((s + 1) // 2 for s in shape)
    level1 = _level1_coords(coords)
    compact = _box_cells(level1, shape1, wraps) <= structured.MAX_COARSE_CELLS_PER_UNKNOWN * len(level1)
    alternate = not wraps or shape1[0] % 2 == 0
    assert (compact and alternate) == expected, "the case does not test what it says"
    coarse = structured.coarse_layout(h, shape, layout, multigrid.COARSE_SWEEPS)
    assert (coarse is not None) == expected
    if coarse is not None:
        assert coarse.cells == _box_cells(level1, shape1, wraps)


@pytest.mark.parametrize("name", ["2-D", "2-D, cut edges", "3-D, periodic axis 0 of 16, cut edges",
                                  "3-D, a window across the seam, 20"])
def test_the_k_cycle_gives_the_v_cycles_solution(name):
    """
    Level 1 as a K-cycle's (two CG steps there, flexible CG outside).

    The V-cycle's solution (other bits), SciPy's, the residual it reports, the same bits again.
    """
    nbr, coords, rhs, A = _problem(**PROBLEMS[name])
    shape = PROBLEMS[name]["shape"]
    h = multigrid.Hierarchy(nbr, coords, shape)
    layout = structured.fine_layout(h, shape, multigrid.sweeps_of(len(shape)), max_cells_per_unknown=np.inf,
                                    min_unknowns=0)
    assert structured.coarse_layout(h, shape, layout, multigrid.COARSE_SWEEPS, max_cells_per_unknown=np.inf) \
        is not None, "level 1 is not on cells: the K-cycle would not run"
    tol = 1e-10
    xk, its_k, res_k = multigrid.solve(nbr, coords, shape, rhs, tol=tol, route="structured", kcycle=True)
    xv, its_v, res_v = multigrid.solve(nbr, coords, shape, rhs, tol=tol, route="structured", kcycle=False)
    assert res_k < tol and res_v < tol
    assert not np.array_equal(xk, xv), "the K-cycle did not run (the V-cycle's bits)"
    # the K-cycle is there to save iterations: never more than the V-cycle's on these problems
    # (CG's flexible beta with the wrong sign takes 2-9 more than the V-cycle here)
    assert its_k <= its_v, (its_k, its_v)
    assert np.max(np.abs(xk - xv)) <= 1e-9 * np.max(np.abs(xv))
    _meets_the_grid_problem(xk, res_k, rhs, A, tol)
    again = multigrid.solve(nbr, coords, shape, rhs, tol=tol, route="structured", kcycle=True)
    assert np.array_equal(xk, again[0]) and again[1] == its_k, "the same problem gave other bits"


@pytest.mark.parametrize("case, k_cycle", [
    (dict(shape=(52, 52, 52), periodic=(False, False, False), seed=21), True),      # 3-D, ~119 000 unknowns
    (dict(shape=(40, 40, 40), periodic=(False, False, False), seed=22), False),     # 3-D, ~54 000
    (dict(shape=(380, 380), periodic=(False, False), seed=23), False),              # 2-D, ~123 000
])
def test_the_rule_runs_the_k_cycle_on_big_3d_problems(case, k_cycle, monkeypatch):
    """
    ``solve``'s own choice: the K-cycle's bits on a 3-D problem of ``KCYCLE_MIN_UNKNOWNS`` or more, else the V's.

    The threshold is lowered to 100 000 unknowns here (the module's is larger), so the
    problems stay small; the rule reads it at every solve.
    """
    monkeypatch.setattr(multigrid, "KCYCLE_MIN_UNKNOWNS", 100_000)
    nbr, coords, rhs, A = _problem(**case)
    shape = case["shape"]
    assert (len(rhs) >= 100_000) == (len(shape) == 2 or k_cycle), "the case's size"
    # the aggregation levels on cells (a 2-D problem's "auto" takes the geometric levels, which have no K-cycle)
    x, its, res = multigrid.solve(nbr, coords, shape, rhs, tol=1e-10, route="structured")
    chosen = multigrid.solve(nbr, coords, shape, rhs, tol=1e-10, kcycle=k_cycle, route="structured")
    other = multigrid.solve(nbr, coords, shape, rhs, tol=1e-10, kcycle=not k_cycle, route="structured")
    assert np.array_equal(x, chosen[0]) and its == chosen[1]
    assert not np.array_equal(x, other[0]), "both cycles gave the same bits: the case tests nothing"
    assert np.max(np.abs(rhs - A @ x)) < 1e-10


def _level1_operator(h):
    """Return level 1's matrix as SciPy's, from the hierarchy's graph rows (float64 weights and diagonal)."""
    a, m = int(h.off[1]), int(h.sizes[1])
    nb, w = h.nbr[a:a + m], h.wt[a:a + m]
    rows, cols = np.nonzero(nb < m)
    return sp.csr_matrix((-w[rows, cols], (rows, nb[rows, cols])), shape=(m, m)) + sp.diags(h.diag[a:a + m])


@pytest.mark.parametrize("name", ["2-D", "3-D, periodic axis 0 of 16, cut edges", "3-D, a window across the seam, 20"])
def test_the_k_cycles_level_1_is_the_best_combination_of_its_two_v_cycles(name):
    """
    ``_level1_kcycle``'s x1 against a Galerkin projection computed here.

    c = V₁ b and d = V₁ r̃ (the V-cycle from level 1, ``_level1_cells``), r̃ = b − (c·b / c·A₁c) A₁c,
    and x = the A₁-orthogonal projection of A₁⁻¹ b on span{c, d}: a 2 × 2 system in float64,
    with A₁ the graph's level-1 rows as a SciPy matrix (not the cells' product).  Level 1's loops
    over chunks of 5 cells on numba's threads (large grids) give the same V-cycle bit for bit.
    """
    nbr, coords, rhs, _ = _problem(**PROBLEMS[name])
    shape = PROBLEMS[name]["shape"]
    h = multigrid.Hierarchy(nbr, coords, shape)
    layout = structured.fine_layout(h, shape, multigrid.sweeps_of(len(shape)), max_cells_per_unknown=np.inf,
                                    min_unknowns=0)
    coarse = structured.coarse_layout(h, shape, layout, multigrid.COARSE_SWEEPS, max_cells_per_unknown=np.inf)
    assert coarse is not None and h.levels >= 3
    wt, diag, inv_diag, chol_t = multigrid._single_levels(h.off, h.wt, h.diag, h.inv_diag, h.chol)
    total = int(h.off[-1])
    c_args = multigrid._coarse_args(coarse, h)[2:9]          # c_wts .. c_gather
    deg = h.nbr.shape[1]
    boost = multigrid.boost_of(len(shape))
    A1 = _level1_operator(h)
    cell = coarse.cell
    rng = np.random.default_rng(5)

    def on_cells(v):
        out = np.zeros(coarse.diag.shape, np.float32)
        out.reshape(-1)[cell] = v
        return out

    one_thread = np.zeros((2, 0, 3), np.int64)
    chunked = structured.chunks_of(coarse.ranges, coarse.nranges, 5)

    def v_cycle(b, chunks=one_thread):
        x1 = np.zeros(coarse.diag.shape, np.float32)
        multigrid._level1_cells(*c_args, x1, on_cells(b), np.zeros(coarse.half), h.red, h.rrows, h.nbr, wt, diag,
                                inv_diag, h.agg, h.off, h.sizes, h.chol, chol_t, np.zeros(total, np.float32),
                                np.zeros(total, np.float32), np.zeros(total, np.float32), boost,
                                multigrid.COARSE_SWEEPS, deg, chunks)
        return x1.reshape(-1)[cell].astype(float)

    for trial in range(3):
        b = rng.standard_normal(A1.shape[0]).astype(np.float32).astype(float)
        c = v_cycle(b)
        assert np.array_equal(v_cycle(b, chunked), c)
        r_t = b - (c @ b) / (c @ (A1 @ c)) * (A1 @ c)
        d = v_cycle(r_t.astype(np.float32).astype(float))
        basis = np.stack([c, d], axis=1)
        coef = np.linalg.solve(basis.T @ (A1 @ basis), basis.T @ b)
        expected = basis @ coef
        x1 = np.zeros(coarse.diag.shape, np.float32)
        scratch = [np.zeros(coarse.diag.shape, np.float32) for _ in range(3)]
        multigrid._level1_kcycle(*c_args, x1, on_cells(b), np.zeros(coarse.half), *scratch, h.red, h.rrows, h.nbr,
                                 wt, diag, inv_diag, h.agg, h.off, h.sizes, h.chol, chol_t,
                                 np.zeros(total, np.float32), np.zeros(total, np.float32),
                                 np.zeros(total, np.float32), boost, multigrid.COARSE_SWEEPS, deg, one_thread)
        got = x1.reshape(-1)[cell].astype(float)
        assert np.max(np.abs(got - expected)) <= 1e-5 * np.max(np.abs(expected)), (name, trial)
        off_rows = np.ones(x1.size, bool)
        off_rows[cell] = False
        assert not np.any(x1.reshape(-1)[off_rows]), "a value off level 1's rows"


@pytest.mark.parametrize("name", ["2-D", "3-D, periodic axis 0 of 16, cut edges"])
@pytest.mark.parametrize("scale", [1e-25, 1e25, 1e30])
def test_the_k_cycle_solves_problems_far_from_unit_scale(name, scale):
    """
    A right-hand side of 1e25 (or 1e-25, 1e30) solves as one of 1: its dot products multiply in float64.

    In float32 the level-1 products of values about 1e25 overflow: the 2-D problem then
    stopped after one iteration with its residual unchanged, the 3-D one at 1e30 above
    its tolerance.
    """
    nbr, coords, rhs, A = _problem(**PROBLEMS[name])
    shape = PROBLEMS[name]["shape"]
    unit = multigrid.solve(nbr, coords, shape, rhs, tol=1e-10, route="structured", kcycle=True)
    tol = 1e-10 * scale
    x, its, res = multigrid.solve(nbr, coords, shape, rhs * scale, tol=tol, route="structured", kcycle=True)
    assert np.all(np.isfinite(x)) and res < tol
    assert np.max(np.abs(rhs * scale - A @ x)) < tol
    assert its <= unit[1] + 1, (its, unit[1])


@pytest.mark.parametrize("name", list(PROBLEMS))
def test_the_cells_loops_on_all_threads_give_the_same_bits_on_any_number_of_them(name):
    """
    The fine level's vector loops over chunks on numba's threads (``chunk_cells``, large grids).

    Chunks of 37 cells (boundaries inside every loop range, across the seam): the same bits and
    iterations with numba's threads as they are and with one; the one-thread route's solution
    (1e-9 relative: the dot products are summed per chunk), the residual met on the grid's own
    Laplacian, SciPy's direct solve; with level 1 as a K-cycle's too where it is on its cells
    (the flexible CG's other update and dot product).
    """
    nbr, coords, rhs, A = _problem(**PROBLEMS[name])
    shape = PROBLEMS[name]["shape"]
    tol = 1e-10
    direct = spla.spsolve(A.tocsc(), rhs)
    threads = numba.get_num_threads()
    for kcycle in (False, True):
        one = multigrid.solve(nbr, coords, shape, rhs, tol=tol, route="structured", kcycle=kcycle, chunk_cells=0)
        runs = []
        for n_threads in sorted({1, threads, 2}):
            numba.set_num_threads(min(n_threads, numba.config.NUMBA_NUM_THREADS))
            try:
                runs.append(multigrid.solve(nbr, coords, shape, rhs, tol=tol, route="structured", kcycle=kcycle,
                                            chunk_cells=37))
            finally:
                numba.set_num_threads(threads)
        for x, its, res in runs[1:]:
            assert np.array_equal(x, runs[0][0]) and its == runs[0][1] and res == runs[0][2], kcycle
        x, its, res = runs[0]
        assert res < tol and abs(its - one[1]) <= 1, (its, one[1])
        assert np.max(np.abs(x - one[0])) <= 1e-9 * np.max(np.abs(one[0]))
        assert np.max(np.abs(rhs - A @ x)) < tol
        assert np.max(np.abs(x - direct)) < 1e-6 * np.max(np.abs(direct))


@pytest.mark.parametrize("name", list(PROBLEMS))
def test_the_coarse_levels_built_beside_the_layout_give_the_same_bits(name):
    """
    A large problem's coarse levels are built on a second thread while its fine level's cells are laid out.

    ``beside=True`` forces it on these small problems: the same bits, iterations and residual as
    the set-up in one thread (route "structured", and "auto", which leaves the problems under
    ``structured.MIN_UNKNOWNS`` on the node graph either way), and the residual met on the grid's
    own Laplacian, with the rows in a random order and red first; the layout made without the
    coarse levels is the one made with them, array for array.
    """
    nbr, coords, rhs, A = _problem(**PROBLEMS[name])
    shape = PROBLEMS[name]["shape"]
    tol = 1e-10
    # the rows in a random order (the set-up renumbers them red first) and red first already (the node graph's)
    red_first = np.argsort(coords.sum(axis=1) % 2, kind="stable")
    row_of = np.append(np.argsort(red_first), len(red_first))       # old row -> new row; "none" stays
    for nbr_, coords_, rhs_, A_ in ((nbr, coords, rhs, A),
                                    (row_of[nbr[red_first]], coords[red_first], rhs[red_first],
                                     A[red_first][:, red_first])):
        for route in ("structured", "auto"):
            one = multigrid.solve(nbr_, coords_, shape, rhs_, tol=tol, route=route, beside=False)
            two = multigrid.solve(nbr_, coords_, shape, rhs_, tol=tol, route=route, beside=True)
            assert np.array_equal(one[0], two[0]) and one[1:] == two[1:], route
            assert np.max(np.abs(rhs_ - A_ @ two[0])) < tol
        h = multigrid.Hierarchy(nbr_, coords_, shape)
        alone = multigrid._fine_layout_alone(h.nb0, h.coords, h.shape, h.red0, np.inf)
        rule = dict(max_cells_per_unknown=np.inf, min_unknowns=0)
        split = structured.fine_layout(h, shape, 1, built=(alone,), **rule)
        serial = structured.fine_layout(h, shape, 1, **rule)
        assert (split is None) == (serial is None)
        if serial is not None:
            for key, value in vars(serial).items():
                assert np.array_equal(getattr(split, key), value), key


def test_the_rule_builds_the_coarse_levels_beside_on_large_problems_with_threads_allowed(monkeypatch):
    monkeypatch.setattr(multigrid, "BESIDE_MIN_UNKNOWNS", 500)
    threads = numba.get_num_threads()
    assert not multigrid.beside_of(499)
    assert multigrid.beside_of(500) == (threads > 1)
    numba.set_num_threads(1)            # planner.max_threads 1: one thread
    try:
        assert not multigrid.beside_of(10**9)
    finally:
        numba.set_num_threads(threads)
    # the rule's choice is what runs: a second thread is started exactly where it says so
    nbr, coords, rhs, _ = _problem(**PROBLEMS["2-D"])
    started = []
    real = multigrid._Beside.__init__

    def spy(self, fn, *args):
        started.append(fn)
        real(self, fn, *args)
    monkeypatch.setattr(multigrid._Beside, "__init__", spy)
    multigrid.solve(nbr, coords, PROBLEMS["2-D"]["shape"], rhs, route="structured")
    assert len(started) == int(multigrid.beside_of(len(nbr)))
