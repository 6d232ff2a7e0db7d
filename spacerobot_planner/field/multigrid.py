"""
Aggregation multigrid for one Dirichlet problem of the harmonic field, on its node graph.

The linear problem: on n unknowns (graph nodes), ``deg·x_i − Σ_j x_j = b_i`` where the sum
runs over the unknown face neighbours of i (deg = 2·ndim) and ``b_i`` holds the known
neighbour values (the goal, or nodes solved before); walls, obstacles and unreachable
nodes are 0.  The matrix is symmetric positive definite (every unknown connects to a
known node).

Coarse levels aggregate the unknowns by index blocks: node (i, j, …) joins aggregate
(i // 2, j // 2, …) of the next level, in any dimension.  With piecewise constant
prolongation P the coarse operator Pᵀ A P is again a face-neighbour operator (a weight per
direction and a diagonal), so every level is stored like the fine one.  Blocks follow the
grid's periodic wrap, so the attitude seam needs nothing special.  The coarsest level (at
most ``COARSEST_NODES`` unknowns; a whole problem of at most ``DIRECT_NODES``) is solved by a
dense Cholesky factor.

One preconditioner application is a symmetric V-cycle (forward Gauss–Seidel before the
coarse correction, backward after: one sweep each on a 2-D grid's fine level, two on a 3-D
one's (:data:`SWEEPS`); the correction scaled by ``boost``, 1.8 on a 2-D grid and less in
more dimensions (:data:`BOOST`), as plain aggregation under-corrects) inside
conjugate gradients: about two iterations per decade of residual on the paper's scenes.
Each level is renumbered red nodes first, then black.
The V-cycle runs in float32 (its vectors and the coarse weights, which are small integers
and so exact) inside the float64 CG: half the bytes of every pass over the levels, which
bound the cost from about 100 000 unknowns; a preconditioner's precision does not change
what CG converges to, and it costs no iterations on the paper's grids.

On a big 3-D band (:func:`kcycle_of`: at least :data:`KCYCLE_MIN_UNKNOWNS` unknowns, level 1 on
its cells) level 1 is a K-cycle's (:func:`_level1_kcycle`): two CG steps there, each
preconditioned by the V-cycle from level 1, and the outer CG flexible (the preconditioner is
then not a fixed linear map): 120³'s first band 16 -> 11 iterations, its plans 0.82-0.91x the time.

Where the band is compact (:func:`.structured.fine_layout`'s rule: its bounding box has few
cells per unknown, at most axis 0 periodic and of even length) the fine level lives on the
box's cells instead (:mod:`.structured`): its sweeps, product and residual read neighbours at
fixed offsets, in vector loops (:func:`_spcg`, :func:`_svcycle`: the same CG and V-cycle,
the same iterations); the coarse levels are the same.  On a 2-D grid, where such a band has no
edge across a periodic seam, the coarse levels are :mod:`.geometric`'s instead (bilinear
prolongation, Galerkin 9-point levels: 9 CG iterations on the paper's first band instead of 17).

Levels are packed into flat arrays: level l owns rows ``off[l] .. off[l] + size[l]`` plus
one dummy row (value 0, weight 0) at ``off[l] + size[l]`` that stands for "no neighbour".
Neighbour tables and aggregate maps are unsigned (uint32): an index of a signed type makes
numba test it for a negative wrap-around at every load, which doubled the cost of a sweep.

Every kernel of the node graph's levels runs on one thread.  A two-thread fine level (from 100 000 unknowns) was
2–4× *slower* on the project's shared two-core machine under load (its threads wait for
each other at every colour of every sweep), and gains at most the second core when the
machine is quiet.  The fine level on cells runs its vector loops on all cores from
:data:`PARALLEL_MIN_CELLS` cells on, and a large problem's set-up builds its coarse levels on a
second thread while its fine level's cells are laid out (:data:`BESIDE_MIN_UNKNOWNS`).
"""
from __future__ import annotations

import threading

import numba as nb
import numpy as np

from . import geometric, structured
from .graph import coord_sum, grid_strides, strided_sum
from .krylov import _cholesky, _descend, _descend_in, _now, _subtract_max, _turn, _turn_in     # CG's steps, shared

#: Stop coarsening at this many unknowns and solve that level directly.  Its dense triangular
#: solves run in every cycle (m² multiply-adds, a dependent chain): at 100 they were a third of
#: a 200-node band's time (at 30 it takes 0.61 of the time) and nothing on the paper's first bands;
#: the extra levels cost next to nothing and the iterations hardly change (1 067 vs 1 062, 0.5 %
#: more, over 125 random 2-DOF bands; 1 134 vs 1 132 over 110 3-DOF bands).
COARSEST_NODES = 30
#: A problem of at most this many unknowns is not coarsened: its fine level is the coarsest,
#: solved directly in one iteration (the small bands of narrow passages).
DIRECT_NODES = 100
#: Gauss–Seidel sweeps before and after the coarse correction on the coarse levels.
COARSE_SWEEPS = 2
#: Gauss–Seidel sweeps before and after the coarse correction on the fine level, by grid
#: dimension (:func:`sweeps_of`; 4: and above).  3-D: 2 (random scenes' bands, 40 scenes: 946 ->
#: 690 iterations, the time of bands of at least 1 000 unknowns 0.95x, of smaller ones 0.92x;
#: the paper's 36³ 15 -> 12 iterations, 0.95x, 72³ 17 -> 14, 0.97x); 2-D: 1 (2 sweeps: 13 %
#: fewer iterations, 3 % more time, the fine level being the larger part of a 2-D V-cycle).
SWEEPS = {1: 1, 2: 1, 3: 2, 4: 1}
#: The scale of the coarse correction (plain aggregation under-corrects), by grid dimension
#: and fine sweeps (:func:`boost_of`): the fewest CG iterations on the bands of the paper's
#: scenes and of random ones (`bench scenes`' family).  2-D: 1.8 (1.6 costs 5 % more
#: iterations); 3-D with one sweep: 1.5 (11 % fewer than 1.8 on random scenes, 1 of 16 on the
#: paper's 36³, 1 of 18 at 72³), with two: 1.7 (random scenes: 1.3, 1.5, 1.9 took 7 %, 2 %
#: and 1 % more time); the 4-D servicer's 16⁴: 1.4 (15 iterations, 18 at 1.8), and above.
BOOST = {(1, 1): 1.8, (2, 1): 1.8, (3, 1): 1.5, (3, 2): 1.7, (4, 1): 1.4}
#: :func:`solve`'s routes for the fine level.
ROUTES = ("auto", "graph", "structured", "geometric")
#: Level 1 as a K-cycle's (:func:`_level1_kcycle`: two CG steps there, each preconditioned by
#: the V-cycle from level 1) on a 3-D grid whose fine level has at least this many unknowns,
#: where level 1 is on its cells (:func:`kcycle_of`, the rule).  Each iteration then costs
#: a second pass over level 1 and below, two level-1 products, five level-1 dot products and
#: one fine one more, and fewer iterations are needed.  The paper's 3-DOF scene, fresh plans,
#: K-cycle against V-cycle interleaved in one process (whole plan, medians): 120³ (first band 1.16 million unknowns,
#: 16 -> 11 iterations) 258 -> 234 ms, 100³ (668 000, 14 -> 10) 118 -> 112 ms, but 72³ (254 000,
#: 14 -> 10) 38.4 -> 37.5 and 44.4 -> 44.5 ms with a longer tail (p90 57 against 53 ms).  The
#: first band alone at 36³: 12 -> 10 iterations, 2.7 -> 3.0 ms.  On 2-D grids, where level 1 is
#: a quarter of the fine level, no gain: 720² 23 -> 15 iterations, 50.5-51.6 -> 56.2-57.0 ms.
KCYCLE_MIN_UNKNOWNS = 500_000
#: The fine level on cells runs its vector loops on all cores from this many cells on (numba's
#: threads, chunks of PARALLEL_CHUNK cells; the dot products per chunk, then over the chunks in
#: their order: the same bits on any number of threads).  The paper 3-DOF scene's first band on
#: 2 cores, one thread against two (median of 5, ms; the dot products still in one thread):
#: 36³ (43 k cells) 3.5 / 4.0, 48³ (99 k) 9.5 / 8.9, 60³ (184 k) 19.2 / 15.6, 72³ 39 / 28 (26 with
#: the dot products on both); 2-D 362² (101 k) 12.8 / 12.8.
PARALLEL_MIN_CELLS = 150_000
PARALLEL_CHUNK = 16_384
#: A problem of at least this many unknowns builds its coarse levels (:func:`_levels`) on a second
#: thread while its fine level's cells are laid out (:func:`.structured.laid_out`; :func:`beside_of`,
#: the rule).  The paper 3-DOF scene's first band alone, the two set-ups alternating (ratios of
#: medians of 41, 15 or 5; tails in docs/benchmarks.md, ninth sitting): 36³ (31 901 unknowns) 1.01x
#: the time, 48³ (76 752) 0.95-0.98x, 60³ (145 437) 1.03-1.05x, 72³ (254 460) 0.94-0.95x, 120³ (1.16 M)
#: 0.84x; with the fine level's loops in one thread, 60³ 0.96x and 72³ 0.92x: numba's threads, which
#: spin a while after a parallel loop, hold the second core then.  2-D 181²: 1.03-1.05x.
BESIDE_MIN_UNKNOWNS = 200_000


def sweeps_of(ndim: int) -> int:
    """Return the fine level's Gauss–Seidel sweeps for a grid of ``ndim`` dimensions (:data:`SWEEPS`)."""
    return SWEEPS[min(int(ndim), 4)]


def kcycle_of(n_unknowns: int, ndim: int, coarse) -> bool:
    """
    Return whether a problem runs level 1 as a K-cycle's (:data:`KCYCLE_MIN_UNKNOWNS`).

    n_unknowns: its fine level's; ndim: the grid's dimensions; coarse: its level 1 on
    cells (:func:`.structured.coarse_layout`), or None.
    """
    return coarse is not None and int(ndim) >= 3 and int(n_unknowns) >= KCYCLE_MIN_UNKNOWNS


def boost_of(ndim: int, sweeps: int | None = None) -> float:
    """
    Return the coarse correction's scale for a grid of ``ndim`` dimensions and ``sweeps`` fine sweeps (:data:`BOOST`).

    sweeps None: :func:`sweeps_of`; a number of sweeps not tuned for: the dimension's own.
    """
    d = min(int(ndim), 4)
    s = sweeps_of(d) if sweeps is None else int(sweeps)
    return BOOST.get((d, s), BOOST[(d, sweeps_of(d))])


# --------------------------------------------------------------------------
# set-up
# --------------------------------------------------------------------------
@nb.njit(cache=True, nogil=True)
def _by_parity(nbr, wt, diag, coords):
    """
    Renumber a level red nodes first, then black (parity of the coordinate sum), each in its previous order.

    A Gauss–Seidel sweep in that order has no chain of dependent updates (neighbours have the other
    colour, except across odd periodic seams, where the serial sweep is still a valid Gauss–Seidel
    order).

    Returns the renumbered arrays, ``new_of_old`` (n,) and the number of red nodes.
    """
    n, deg = nbr.shape
    ndim = coords.shape[1]
    red = 0
    for i in range(n):
        if coords[i].sum() % 2 == 0:
            red += 1
    new_of_old = np.empty(n + 1, np.int64)
    new_of_old[n] = n
    k_red = 0
    k_black = red
    for i in range(n):
        if coords[i].sum() % 2 == 0:
            new_of_old[i] = k_red
            k_red += 1
        else:
            new_of_old[i] = k_black
            k_black += 1
    nbr2 = np.empty_like(nbr)
    wt2 = np.empty_like(wt)
    diag2 = np.empty_like(diag)
    coords2 = np.empty_like(coords)
    for i in range(n):
        j = new_of_old[i]
        for d in range(deg):
            nbr2[j, d] = new_of_old[nbr[i, d]]
            wt2[j, d] = wt[i, d]
        diag2[j] = diag[i]
        for a in range(ndim):
            coords2[j, a] = coords[i, a]
    return nbr2, wt2, diag2, coords2, new_of_old[:n].copy(), red


@nb.njit(cache=True, nogil=True)
def _red_rows(coords):
    """Return ``(red, in_order)``: the number of red nodes (even coordinate sum) and whether they come first."""
    n = coords.shape[0]
    red = 0
    in_order = True
    for i in range(n):
        if coord_sum(coords, i) % 2 == 0:
            if red < i:
                in_order = False
            red += 1
    return red, in_order


@nb.njit(cache=True, nogil=True)
def _restrict_rows(nbr, n, red):
    """
    Return the rows of a level (``n`` rows, red rows first) whose residual a sweep leaves nonzero.

    ``red`` unless two black rows are neighbours (across an odd periodic seam; then all n).
    nbr (n, deg): the level's neighbours, n = none.
    """
    deg = nbr.shape[1]
    for i in range(red, n):
        for d in range(deg):
            j = nbr[i, d]
            if j >= red and j < n:
                return n
    return red


@nb.njit(cache=True, nogil=True)
def _aggregates(coords, shape, cell_id):
    """
    Aggregate one level by index blocks: node (i, j, …) joins cell (i // 2, j // 2, …).

    coords int32 or int64 (n, ndim) of a level on a grid of ``shape`` (the coarse grid's, each axis
    halved rounding up); cell_id int64 scratch, at least prod(shape) entries, all -1 on entry
    and on return.  The coarse nodes are numbered red first, then black (parity of their
    coordinate sum), each in the order of their first fine node.  Returns ``(agg uint32 (n,),
    ccoords (nc, ndim) of coords' type, red)``: each node's coarse node, the coarse coordinates and the
    number of red coarse nodes.
    """
    n, ndim = coords.shape
    first = np.empty(n, np.int64)           # a node of each cell, in the order the cells are met
    cell = np.empty(n, np.int64)            # each node's cell (a flat index on the coarse grid)
    strides = grid_strides(shape)
    nc = 0
    red = 0
    for i in range(n):
        f = strided_sum(coords, i, strides, 1)          # coordinates are >= 0: >> 1 is // 2
        cell[i] = f
        if cell_id[f] < 0:
            cell_id[f] = nc
            first[nc] = i
            nc += 1
            par = 0
            for a in range(ndim):
                par += coords[i, a] >> 1
            if par % 2 == 0:
                red += 1
    new = np.empty(nc, np.int64)            # met order -> red first, then black
    ccoords = np.empty((nc, ndim), coords.dtype)
    k_red = 0
    k_black = red
    for c in range(nc):
        par = 0
        for a in range(ndim):
            par += coords[first[c], a] >> 1
        if par % 2 == 0:
            k = k_red
            k_red += 1
        else:
            k = k_black
            k_black += 1
        new[c] = k
        for a in range(ndim):
            ccoords[k, a] = coords[first[c], a] >> 1
    agg = np.empty(n, np.uint32)
    for i in range(n):
        agg[i] = new[cell_id[cell[i]]]
    for c in range(nc):
        cell_id[cell[first[c]]] = -1
    return agg, ccoords, red


@nb.njit(cache=True, nogil=True)
def _galerkin(nbr, wt, diag, n, red, agg, cnbr, cwt, cdiag, nc, unit):
    """
    Fill the coarse level (cnbr, cwt, cdiag: its rows, nc of them) from the level below (n rows).

    nbr (n, deg) level-local (index >= n: none), wt / diag float64 (with ``unit``: the fine
    level, weight 1 to every neighbour, diagonal deg; wt and diag unused); agg (n,) each
    row's coarse row.  The coarse operator Pᵀ A P of piecewise constant P: a coarse row's
    diagonal sums its rows' diagonals less the weights between them, its weight towards a
    neighbouring aggregate sums the weights that cross; accumulated over the rows in order.
    Returns the level below's rows to restrict (:func:`_restrict_rows`, seen on the way:
    its first ``red`` rows are red).
    """
    deg = nbr.shape[1]
    for c in range(nc):
        cdiag[c] = 0.0
        for d in range(deg):
            cnbr[c, d] = nc
            cwt[c, d] = 0.0
    rrows = red
    for i in range(n):
        c = agg[i]
        s = deg if unit else diag[i]     # the row's diagonal less its weights inside the aggregate
        for d in range(deg):
            j = nbr[i, d]
            if j >= n:
                continue
            if i >= red and j >= red:
                rrows = n            # two black rows are neighbours (an odd periodic seam)
            cj = agg[j]
            w = 1.0 if unit else wt[i, d]
            if cj == c:
                s -= w
            else:
                cnbr[c, d] = cj
                cwt[c, d] += w
        cdiag[c] += s                # the weights are small integers: every sum exact, in any order
    return rrows


@nb.njit(cache=True, nogil=True)
def _levels(nb0, red0, coords, shape, stop):
    """
    Aggregate the fine level (``nb0`` uint32 (n, deg), red rows first) down to the coarsest.

    coords int32 or int64 (n, ndim), shape int64 (ndim,): the fine grid.  First the aggregates of
    every level (from the coordinates alone), then the packed arrays, each coarse level
    written in place from the one below.  Returns ``(sizes, off, nbr, wt, inv_diag, diag,
    agg, red, rrows, coords1, chol, stopped)`` (see the module doc; the fine level's rows of nbr,
    wt, diag and inv_diag are left unset: its kernels read ``nb0`` and unit weights); ``coords1``: level 1's
    coordinates (its rows', of coords' type; no rows without a level 1); ``chol``: the
    coarsest level's Cholesky factor (:func:`_cholesky`); ``stopped``: the termination flag
    ``stop`` was seen set between levels (nothing else is valid).
    """
    n, deg = nb0.shape
    aggs = [np.zeros(0, np.uint32)]         # aggs[l]: the row on level l + 1 of each row of level l
    reds = [red0]
    size_list = [n]
    shape = shape.copy()
    stopped = False
    size = n
    ncell = 1
    for a in range(shape.size):
        ncell *= (shape[a] + 1) // 2
    cell_id = np.full(ncell, -1, np.int64)  # the first coarse grid is the largest
    coords1 = coords[:0].copy()
    while size > COARSEST_NODES and n > DIRECT_NODES and np.any(shape > 1):
        if stop[0] != 0:
            stopped = True
            break
        shape = (shape + 1) // 2
        agg, ccoords, red = _aggregates(coords, shape, cell_id)
        if ccoords.shape[0] == size:
            break
        if len(size_list) == 1:
            aggs[0] = agg
            coords1 = ccoords
        else:
            aggs.append(agg)
        reds.append(red)
        coords = ccoords
        size = ccoords.shape[0]
        size_list.append(size)
    levels = len(size_list)
    sizes = np.empty(levels, np.int64)
    off = np.zeros(levels + 1, np.int64)
    for lv in range(levels):
        sizes[lv] = size_list[lv]
        off[lv + 1] = off[lv] + sizes[lv] + 1
    total = off[levels]
    if stopped:                  # nothing more (above all no dense matrix of a fine level cut short)
        total = 0
    nbr = np.empty((total, deg), np.uint32)
    wt = np.empty((total, deg))
    diag = np.empty(total)       # the fine level's rows unset (its kernels read nb0), the rest 1: each
    inv_diag = np.empty(total)   # coarse level's rows are written below, its dummy row keeps diagonal 1
    diag[off[1] - 1:] = 1.0
    inv_diag[off[1] - 1:] = 1.0
    agg = np.zeros(total, np.uint32)
    red = np.empty(levels, np.int64)
    rrows = np.empty(levels, np.int64)
    if stopped:
        return sizes, off, nbr, wt, inv_diag, diag, agg, red, rrows, coords1, np.zeros((0, 0)), True
    for lv in range(levels):
        a, m = off[lv], sizes[lv]
        red[lv] = reds[lv]
        if lv + 1 < levels:
            agg[a:a + m] = aggs[lv]
        if lv == 0:
            continue             # the fine level reads nb0 (unit weights, diagonal deg)
        if stop[0] != 0:
            return sizes, off, nbr, wt, inv_diag, diag, agg, red, rrows, coords1, np.zeros((0, 0)), True
        b, mb = off[lv - 1], sizes[lv - 1]
        if lv == 1:
            rrows[0] = _galerkin(nb0, wt, diag, n, red0, aggs[0], nbr[a:a + m], wt[a:a + m], diag[a:a + m], m,
                                 True)
        else:
            rrows[lv - 1] = _galerkin(nbr[b:b + mb], wt[b:b + mb], diag[b:b + mb], mb, reds[lv - 1], aggs[lv - 1],
                                      nbr[a:a + m], wt[a:a + m], diag[a:a + m], m, False)
        for i in range(m):
            inv_diag[a + i] = 1.0 / diag[a + i]
        nbr[a + m] = m           # the dummy row: no neighbours, weight 0, diagonal 1
        wt[a + m] = 0.0
    if levels == 1:
        rrows[0] = _restrict_rows(nb0, n, red0)
    else:                        # the coarsest level's (no level above it to see them on the way)
        a, m = off[levels - 1], sizes[levels - 1]
        rrows[levels - 1] = _restrict_rows(nbr[a:a + m], m, reds[levels - 1])
    m = sizes[levels - 1]
    if levels == 1:              # the fine level is the coarsest: unit weights, diagonal deg
        dense = _coarsest_matrix(nb0, np.ones((m, deg)), np.full(m, float(deg)))
    else:
        a = off[levels - 1]
        dense = _coarsest_matrix(nbr[a:a + m], wt[a:a + m], diag[a:a + m])
    return sizes, off, nbr, wt, inv_diag, diag, agg, red, rrows, coords1, _cholesky(dense), stopped


@nb.njit(cache=True, nogil=True)
def _coarsest_matrix(cn, cw, cd):
    """Return the coarsest level's dense matrix: ``cd`` on the diagonal, ``-cw`` at each neighbour (cn >= m: none)."""
    m, deg = cn.shape
    dense = np.zeros((m, m))
    for i in range(m):
        dense[i, i] = cd[i]
    for i in range(m):
        for d in range(deg):
            j = cn[i, d]
            if j < m:
                dense[i, j] += -cw[i, d]
    return dense


class Stopped(Exception):
    """The set-up saw its termination flag set."""


class Hierarchy:
    """The packed levels of one problem (see the module docstring)."""

    def __init__(self, nbr, coords, shape, stop=None, coarsen=True):
        """
        Set up the levels from the fine grid.

        nbr int (n, deg): fine neighbours, index n = none (already mapped so that goal nodes,
        walls and obstacles all read n); coords int (n, ndim); shape: the fine grid shape.
        ``fine_of_input`` maps an input node to its row on the (renumbered) fine level;
        ``in_order``: it is the identity (the input came red rows first; ``fine_of_input`` is
        then None).
        ``stop``: a termination flag, polled between levels (raises :class:`Stopped`).
        ``coarsen`` False: the fine level alone (``nb0``, ``coords``, ``red0``); :meth:`coarsen`
        builds the rest (meanwhile another thread may start on the fine level: :func:`solve`),
        and takes the ``stop`` flag then (here it is not used).
        """
        n, deg = nbr.shape
        # the node graph's int32 (half the bytes to read) as it is, any other integer type as int64
        coords = np.asarray(coords)
        coords = np.ascontiguousarray(coords, dtype=None if coords.dtype == np.int32 else np.int64)
        red, in_order = _red_rows(coords)
        self.in_order = bool(in_order)
        if in_order:                            # already red rows first (the node graph's order)
            nb0 = np.ascontiguousarray(nbr, dtype=np.uint32)
            self.fine_of_input = None
        else:
            nb0, _, _, coords, self.fine_of_input, _ = _by_parity(
                np.ascontiguousarray(nbr, dtype=np.int64), np.zeros((n, deg)), np.zeros(n), coords)
            nb0 = nb0.astype(np.uint32)
        #: the fine level's coordinates, in its rows' order
        self.coords = coords
        # the fine level on its own: unit weights, diagonal deg, uint32 neighbours
        self.nb0 = nb0
        #: the fine level's red rows (its first ones)
        self.red0 = int(red)
        self.shape = np.asarray(shape, np.int64)
        if coarsen:
            self.coarsen(stop)

    def coarsen(self, stop=None):
        """Build the coarse levels (see :meth:`__init__`; ``stop``: raises :class:`Stopped`)."""
        # per level: red rows (first), and the rows to restrict: after a sweep (red rows, then
        # black) the black residuals are zero unless two black rows are neighbours (across an
        # odd periodic seam): the red ones only
        (self.sizes, self.off, self.nbr, self.wt, self.inv_diag, self.diag, self.agg, self.red, self.rrows,
         self.coords1, chol, stopped) = _levels(self.nb0, self.red0, self.coords, self.shape,
                                                np.zeros(1, np.int64) if stop is None else stop)
        if stopped:
            raise Stopped()
        # coords1: level 1's coordinates, in its rows' order (its cells: :func:`.structured.coarse_layout`)
        self.levels = int(self.sizes.size)
        # SPD: every unknown is connected to the goal, a Dirichlet node
        self.chol = chol


# --------------------------------------------------------------------------
# kernels
# --------------------------------------------------------------------------
@nb.njit(cache=True, nogil=True, inline="always")
def _row(nbr, wt, x, i, deg):
    """
    Return one row's neighbour sum on a coarse level: sum_d wt[i, d] * x[nbr[i, d]].

    nbr, wt, x: the level's own rows (views of the packed arrays); nbr unsigned, so that no
    index pays numba's negative-index wrap-around.  The usual degrees spelled out, as in
    :func:`_row0`.
    """
    if deg == 4:
        return (wt[i, 0] * x[nbr[i, 0]] + wt[i, 1] * x[nbr[i, 1]]
                + wt[i, 2] * x[nbr[i, 2]] + wt[i, 3] * x[nbr[i, 3]])
    if deg == 6:
        return (wt[i, 0] * x[nbr[i, 0]] + wt[i, 1] * x[nbr[i, 1]]
                + wt[i, 2] * x[nbr[i, 2]] + wt[i, 3] * x[nbr[i, 3]]
                + wt[i, 4] * x[nbr[i, 4]] + wt[i, 5] * x[nbr[i, 5]])
    s = 0.0
    for d in range(deg):
        s += wt[i, d] * x[nbr[i, d]]
    return s


@nb.njit(cache=True, nogil=True, inline="always")
def _row0(nb0, x, i, deg):
    """
    sum_d x[nb0[i, d]] on the fine level (unit weights).

    The usual degrees are spelled out (the same sum in the same order, 1.5x faster than
    the loop); nb0 is unsigned (uint32: no negative-index wrap-around, 2x faster).
    """
    if deg == 4:
        return x[nb0[i, 0]] + x[nb0[i, 1]] + x[nb0[i, 2]] + x[nb0[i, 3]]
    if deg == 6:
        return x[nb0[i, 0]] + x[nb0[i, 1]] + x[nb0[i, 2]] + x[nb0[i, 3]] + x[nb0[i, 4]] + x[nb0[i, 5]]
    if deg == 8:
        return (x[nb0[i, 0]] + x[nb0[i, 1]] + x[nb0[i, 2]] + x[nb0[i, 3]] + x[nb0[i, 4]]
                + x[nb0[i, 5]] + x[nb0[i, 6]] + x[nb0[i, 7]])
    s = 0.0
    for d in range(deg):
        s += x[nb0[i, d]]
    return s


# --------------------------------------------------------------------------
# the fine level: a range of rows, gathers through nb0
# --------------------------------------------------------------------------
@nb.njit(cache=True, nogil=True)
def _gs0(nb0, x, b, lo, hi, deg, inv_deg):
    """Gauss–Seidel over the fine rows lo .. hi - 1 (x float32: the V-cycle's; b float64: its right-hand side)."""
    for i in range(lo, hi):
        x[i] = (b[i] + _row0(nb0, x, i, deg)) * inv_deg


@nb.njit(cache=True, nogil=True)
def _gs0_dot(nb0, x, b, lo, hi, deg, inv_deg):
    """:func:`_gs0`, returning sum b[i] * x[i] over its rows (the new x, as stored; one pass, not two)."""
    s = 0.0
    for i in range(lo, hi):
        x[i] = (b[i] + _row0(nb0, x, i, deg)) * inv_deg
        s += b[i] * x[i]
    return s


@nb.njit(cache=True, nogil=True)
def _matvec0_dot(nb0, p, q, n, deg):
    """Compute q = A p on the fine level (float64); return p · q (summed in the same pass)."""
    fdeg = float(deg)
    s = 0.0
    for i in range(n):
        v = fdeg * p[i] - _row0(nb0, p, i, deg)
        q[i] = v
        s += p[i] * v
    return s


@nb.njit(cache=True, nogil=True)
def _dot(a, b, n):
    """Return sum_i a[i] * b[i] over the first n entries, in a fixed order (the same bits every run)."""
    s = 0.0
    for i in range(n):
        s += a[i] * b[i]
    return s


# --------------------------------------------------------------------------
# the cycle (single precision: the preconditioner of a double-precision CG)
# --------------------------------------------------------------------------
@nb.njit(cache=True, nogil=True)
def _coarse_cycle(red, rrows, nbr, wt, diag, inv_diag, agg, off, sizes, chol, chol_t, x, b, r, top, boost,
                  coarse_sweeps):
    """
    Compute x = M^-1 b on level ``top`` by a V-cycle over the levels from ``top`` down (packed vectors).

    Forward Gauss–Seidel sweeps (``coarse_sweeps``) before the coarse correction (scaled by
    ``boost``), backward ones after; the coarsest level by its Cholesky factor ``chol``
    and its transpose ``chol_t`` (float64, each read along its rows).  Each level's first
    ``red[l]`` rows are red; where no two rows of one colour are
    neighbours (``rrows[l] == red[l]``) the first sweep from 0 sets the red rows without
    reading their (zero) neighbours, and only the red rows' residuals (``rrows[l]``) are
    restricted: the black ones are zero after the sweep.
    x, b, r, wt, diag, inv_diag: float32 (:func:`_single_levels`); b of the levels below
    ``top`` and r are scratch.
    """
    deg = nbr.shape[1]
    nlev = sizes.size
    for lv in range(top, nlev - 1):
        lo, n, cb = off[lv], sizes[lv], off[lv + 1]
        xl, bl, nl, wl, dl, idl, al = (x[lo:cb], b[lo:cb], nbr[lo:cb], wt[lo:cb], diag[lo:cb], inv_diag[lo:cb],
                                       agg[lo:cb])
        bc = b[cb:off[lv + 2]]
        bc[:] = 0.0
        sweeps = coarse_sweeps
        clean = rrows[lv] == red[lv] and sweeps > 0
        if not clean:
            xl[:] = 0.0
        else:                        # the first sweep from 0: a red row sees only black zeros
            xl[n] = 0.0              # (and the black rows' old values are never read)
            for i in range(red[lv]):
                xl[i] = bl[i] * idl[i]
            for i in range(red[lv], n):
                xl[i] = (bl[i] + _row(nl, wl, xl, i, deg)) * idl[i]
            sweeps -= 1
        for _ in range(sweeps):
            for i in range(n):
                xl[i] = (bl[i] + _row(nl, wl, xl, i, deg)) * idl[i]
        for i in range(rrows[lv]):
            bc[al[i]] += bl[i] - dl[i] * xl[i] + _row(nl, wl, xl, i, deg)
    # coarsest: L L^T x = b
    base = off[nlev - 1]
    m = sizes[nlev - 1]
    for i in range(m):
        s = float(b[base + i])
        for k in range(i):
            s -= chol[i, k] * r[base + k]
        r[base + i] = s / chol[i, i]
    for i in range(m - 1, -1, -1):
        s = float(r[base + i])
        for k in range(i + 1, m):
            s -= chol_t[i, k] * x[base + k]
        x[base + i] = s / chol_t[i, i]
    x[base + m] = 0.0
    for lv in range(nlev - 2, top - 1, -1):
        lo, n, cb = off[lv], sizes[lv], off[lv + 1]
        xl, bl, nl, wl, idl, al = x[lo:cb], b[lo:cb], nbr[lo:cb], wt[lo:cb], inv_diag[lo:cb], agg[lo:cb]
        xc = x[cb:off[lv + 2]]
        # the backward sweep sets the black rows from red ones only: their correction is dead
        for i in range(red[lv] if rrows[lv] == red[lv] and coarse_sweeps > 0 else n):
            xl[i] += boost * xc[al[i]]
        for _ in range(coarse_sweeps):
            for i in range(n - 1, -1, -1):
                xl[i] = (bl[i] + _row(nl, wl, xl, i, deg)) * idl[i]


@nb.njit(cache=True, nogil=True)
def _vcycle(nb0, red, rrows, nbr, wt, diag, inv_diag, agg, off, sizes, chol, chol_t, rf, x, b, r, sweeps,
            boost, coarse_sweeps, stop):
    """
    Compute x = M^-1 rf on the finest level; return rf · x.

    rf float64 (n0 + 1,): the fine right-hand side (the CG residual; read only); x, b, r:
    float32 packed level vectors (b's fine part unused; b of the coarser levels and r are
    scratch); wt, diag, inv_diag: the float32 levels (:func:`_single_levels`).
    Symmetric: forward Gauss-Seidel sweeps before the coarse correction (scaled by
    ``boost``), backward ones after.  The fine level (unit weights, diagonal deg)
    reads ``nb0``; its first ``red[0]`` rows are red.  When ``rrows[0] == red[0]`` (no
    two rows of one colour are neighbours) a colour's rows are updated in any order,
    else one by one in order; the coarser levels by :func:`_coarse_cycle`.  The fine
    residual is restricted as it is computed (no residual vector), and rf · x summed in
    the last sweep.  The termination flag ``stop`` is polled after the fine level's
    pre-smoothing and before its post-smoothing (then x is garbage and 0 is returned: the
    caller discards both).
    """
    deg = nb0.shape[1]
    inv_deg = 1.0 / deg
    fdeg = float(deg)
    n0 = sizes[0]
    red0, restrict0 = red[0], rrows[0]
    if sizes.size == 1:          # the fine level is the coarsest
        for i in range(n0):
            b[i] = rf[i]
        _coarse_cycle(red, rrows, nbr, wt, diag, inv_diag, agg, off, sizes, chol, chol_t, x, b, r, 0, boost,
                      coarse_sweeps)
        return _dot(rf, x, n0)
    clean = restrict0 == red0 and sweeps > 0
    for i in range(n0 if clean else 0, n0 + 1):
        x[i] = 0.0
    if clean:            # first sweep from 0: a red row sees only black zeros (black rows are set, not read)
        for i in range(red0):
            x[i] = rf[i] * inv_deg
        _gs0(nb0, x, rf, red0, n0, deg, inv_deg)
        for _ in range(sweeps - 1):
            _gs0(nb0, x, rf, 0, red0, deg, inv_deg)
            _gs0(nb0, x, rf, red0, n0, deg, inv_deg)
    else:
        for _ in range(sweeps):
            _gs0(nb0, x, rf, 0, n0, deg, inv_deg)
    if stop[0] != 0:
        return 0.0
    cb = off[1]
    bc = b[cb:off[2]]
    bc[:] = 0.0
    for i in range(restrict0):          # the residual, restricted as it is computed
        bc[agg[i]] += rf[i] - fdeg * x[i] + _row0(nb0, x, i, deg)
    _coarse_cycle(red, rrows, nbr, wt, diag, inv_diag, agg, off, sizes, chol, chol_t, x, b, r, 1, boost,
                  coarse_sweeps)
    if stop[0] != 0:
        return 0.0
    xc = x[cb:off[2]]
    for i in range(red0 if clean else n0):     # clean: the black rows' correction is dead (set, not read)
        x[i] += boost * xc[agg[i]]
    if sweeps == 0:
        return _dot(rf, x, n0)
    for _ in range(sweeps - 1):
        if clean:        # black rows, then red (the backward order by colour)
            _gs0(nb0, x, rf, red0, n0, deg, inv_deg)
            _gs0(nb0, x, rf, 0, red0, deg, inv_deg)
        else:
            _gs0_back(nb0, x, rf, n0, deg, inv_deg)
    if clean:
        s_black = _gs0_dot(nb0, x, rf, red0, n0, deg, inv_deg)
        return _gs0_dot(nb0, x, rf, 0, red0, deg, inv_deg) + s_black
    return _gs0_back(nb0, x, rf, n0, deg, inv_deg)


@nb.njit(cache=True, nogil=True)
def _gs0_back(nb0, x, b, n, deg, inv_deg):
    """Backward Gauss–Seidel over the fine rows n - 1 .. 0; returns sum b[i] * x[i] (the new x)."""
    s = 0.0
    for i in range(n - 1, -1, -1):
        x[i] = (b[i] + _row0(nb0, x, i, deg)) * inv_deg
        s += b[i] * x[i]
    return s


@nb.njit(cache=True, nogil=True)
def _single_levels(off, wt, diag, inv_diag, chol):
    """
    Return the V-cycle's arrays ``(wt, diag, inv_diag, chol_t)`` from a hierarchy's packed levels.

    wt, diag, inv_diag: float32 copies of the coarse levels (rows from ``off[1]``; the
    coarse weights and diagonals are sums of unit weights, small integers: exact in
    float32); the fine level's rows are never read (its kernels read ``nb0``) and left
    unset.  chol_t: the coarsest factor's transpose, row-major (float64).
    """
    a = off[1] if off.size > 2 else off[-1]
    total, deg = wt.shape
    wt32 = np.empty((total, deg), np.float32)
    diag32 = np.empty(total, np.float32)
    inv_diag32 = np.empty(total, np.float32)
    for i in range(a, total):
        for d in range(deg):
            wt32[i, d] = wt[i, d]
        diag32[i] = diag[i]
        inv_diag32[i] = inv_diag[i]
    m = chol.shape[0]
    chol_t = np.empty((m, m))
    for i in range(m):
        for k in range(m):
            chol_t[i, k] = chol[k, i]
    return wt32, diag32, inv_diag32, chol_t


@nb.njit(cache=True, nogil=True)
def _pcg(nb0, red, rrows, nbr, wt64, diag64, inv_diag64, agg, off, sizes, chol, rhs, u, tol, max_iter,
         sweeps, boost, coarse_sweeps, deadline, stop):
    """
    Preconditioned CG on the finest level, from the initial guess ``u``.

    rhs, u float64 (n + 1,) (last entry the dummy, kept 0); the levels as the hierarchy
    holds them (float64).  CG runs in float64; its preconditioner, one V-cycle, in float32
    (the levels' copies: :func:`_single_levels`): half the bytes per pass, and the
    precision of the preconditioner does not change what CG converges to (each application
    is exact to float32's relative 6e-8 of the current residual: the same iterations on
    the paper's scenes at 181², 36³ and 72³, one more at 120³ and on 3 of 300 band problems
    of random scenes).  Stops when the largest residual |b - A u| falls below ``tol``, at
    ``deadline``, or when the termination flag ``stop`` (int64 (1,)) is nonzero (polled
    before every iteration, like the deadline, and inside it: after the update and within
    the V-cycle; u is then partial).  Returns (iterations, final max residual); u is
    updated in place.
    """
    deg = nb0.shape[1]
    n = sizes[0]
    total = off[-1]
    wt, diag, inv_diag, chol_t = _single_levels(off, wt64, diag64, inv_diag64, chol)
    xs = np.zeros(total, np.float32)
    bs = np.zeros(total, np.float32)
    ws = np.zeros(total, np.float32)
    r = np.zeros(n + 1)
    p = np.zeros(n + 1)
    q = np.zeros(n + 1)
    u[n] = 0.0
    res = 0.0
    fdeg = float(deg)
    for i in range(n):
        r[i] = rhs[i] - fdeg * u[i] + _row0(nb0, u, i, deg)
        if abs(r[i]) > res:
            res = abs(r[i])
    if res < tol:
        return 0, res
    rz = _vcycle(nb0, red, rrows, nbr, wt, diag, inv_diag, agg, off, sizes, chol, chol_t, r, xs, bs, ws,
                 sweeps, boost, coarse_sweeps, stop)
    for i in range(n):
        p[i] = xs[i]
    it = 0
    while it < max_iter:
        if stop[0] != 0 or (deadline > 0.0 and _now() > deadline):      # polled before every iteration
            break
        it += 1
        pq = _matvec0_dot(nb0, p, q, n, deg)
        if not pq > 0.0:
            break
        alpha, res, done = _descend(r, q, u, p, rz, pq, tol, n, stop)
        if done:
            break
        rz_new = _vcycle(nb0, red, rrows, nbr, wt, diag, inv_diag, agg, off, sizes, chol, chol_t, r, xs, bs, ws,
                         sweeps, boost, coarse_sweeps, stop)
        rz = _turn(u, p, xs, alpha, rz, rz_new, n)
    return it, res


# --------------------------------------------------------------------------
# the structured fine level (:mod:`.structured`): the same V-cycle and CG on cells
# --------------------------------------------------------------------------
@nb.njit(cache=True, nogil=True)
def _level1_cells(c_wts, c_diag, c_idg, c_ranges, c_nranges, c_aggr, c_gather, x1, b1, r1, red, rrows, nbr, wt,
                  diag, inv_diag, agg, off, sizes, chol, chol_t, x, b, r, boost, coarse_sweeps, deg, c_chunks):
    """
    :func:`_coarse_cycle` from level 1 with level 1 on its cells (:class:`.structured.Coarse`): x1 = M1^-1 b1.

    x1, b1 float32 (2, H1): level 1's iterate and right-hand side on its cells; r1 float64
    (H1,): scratch, 0 outside the ranges; the rest as :func:`_coarse_cycle`'s (level 2 and
    below on the graph).  The same steps as the graph's clean red-black level: the red
    half-sweep from 0, the black one, ``coarse_sweeps - 1`` more pairs; the red residuals
    restricted; after the coarse correction (red cells) ``coarse_sweeps`` pairs black then red.
    ``c_chunks``: level 1's cells in chunks (:func:`.structured.chunks_of`), its loops then in
    parallel (the same values); none (shape (2, 0, 3)): in one thread.
    """
    par = c_chunks.shape[1] > 0
    if par:
        structured.weighted_first_red_chunks(x1, b1, c_idg, c_chunks)
    else:
        structured.weighted_first_red(x1, b1, c_idg, c_ranges, c_nranges)
    _weighted_half_sweep(x1, b1, c_wts, c_idg, c_ranges, c_nranges, c_chunks, par, 1, deg)
    for _ in range(coarse_sweeps - 1):
        _weighted_half_sweep(x1, b1, c_wts, c_idg, c_ranges, c_nranges, c_chunks, par, 0, deg)
        _weighted_half_sweep(x1, b1, c_wts, c_idg, c_ranges, c_nranges, c_chunks, par, 1, deg)
    c2 = off[2]
    bc = b[c2:off[3]]
    if par:
        structured.weighted_restrict_red_chunks(b1, x1, c_wts, c_diag, r1, c_gather, bc, c_ranges, c_chunks, deg)
    else:
        structured.weighted_restrict_red(b1, x1, c_wts, c_diag, r1, c_gather, bc, c_ranges, c_nranges, deg)
    bc[sizes[2]] = 0.0
    _coarse_cycle(red, rrows, nbr, wt, diag, inv_diag, agg, off, sizes, chol, chol_t, x, b, r, 2, boost,
                  coarse_sweeps)
    if par:
        structured.prolong_red_chunks(x1, x[c2:off[3]], c_aggr, c_chunks, boost)
    else:
        structured.prolong_red(x1, x[c2:off[3]], c_aggr, c_ranges, c_nranges, boost)
    for _ in range(coarse_sweeps):
        _weighted_half_sweep(x1, b1, c_wts, c_idg, c_ranges, c_nranges, c_chunks, par, 1, deg)
        _weighted_half_sweep(x1, b1, c_wts, c_idg, c_ranges, c_nranges, c_chunks, par, 0, deg)


@nb.njit(cache=True, nogil=True, inline="always")
def _weighted_half_sweep(x1, b1, c_wts, c_idg, c_ranges, c_nranges, c_chunks, par, colour, deg):
    """One colour's half-sweep on level 1's cells: over ``c_chunks`` in parallel when ``par`` (the same values)."""
    if par:
        structured.weighted_half_sweep_chunks(x1, b1, c_wts, c_idg, c_ranges, c_chunks, colour, deg)
    else:
        structured.weighted_half_sweep(x1, b1, c_wts, c_idg, c_ranges, c_nranges, colour, deg)


@nb.njit(cache=True, nogil=True)
def _level1_kcycle(c_wts, c_diag, c_idg, c_ranges, c_nranges, c_aggr, c_gather, x1, b1, r1, kc, kv, kw, red, rrows,
                   nbr, wt, diag, inv_diag, agg, off, sizes, chol, chol_t, x, b, r, boost, coarse_sweeps, deg,
                   c_chunks):
    """
    Level 1 of a K-cycle on its cells: two CG steps on A₁ x1 = b1, each preconditioned by :func:`_level1_cells`.

    Notay's K-cycle at level 1 only (see :data:`KCYCLE_MIN_UNKNOWNS`): c = M₁⁻¹ b1, v = A₁ c,
    then d = M₁⁻¹ (b1 − (c·b1 / c·v) v), w = A₁ d, and x1 = the combination of c and d that
    minimises the A₁-norm of the error over the two (Notay and Vassilevski, "Recursive
    Krylov-based multigrid cycles", 2008: two inner iterations, no skip test).  The V-cycle
    below level 1 is unchanged.  x1, b1 float32 (2, H1) as :func:`_level1_cells`' (b1 is
    overwritten with the residual after the first step); kc, kv, kw float32 (2, H1): scratch
    (c, v, w; c is the first V-cycle's own output array).  Every vector is 0 off level 1's rows (their
    diagonal, weights and right-hand side are 0), so the dot products run over the whole arrays,
    in 8 float64 accumulators (:func:`.structured.dot_all`).
    """
    _level1_cells(c_wts, c_diag, c_idg, c_ranges, c_nranges, c_aggr, c_gather, kc, b1, r1, red, rrows, nbr, wt,
                  diag, inv_diag, agg, off, sizes, chol, chol_t, x, b, r, boost, coarse_sweeps, deg, c_chunks)
    xf, bf, cf, vf = x1.reshape(-1), b1.reshape(-1), kc.reshape(-1), kv.reshape(-1)
    rho1 = structured.weighted_product_dot(kc, kv, c_wts, c_diag, c_ranges, c_nranges, deg)
    if not rho1 > 0.0:           # c is 0 (b1 is): x1 = c
        xf[:] = cf
        return
    a1 = structured.dot_all(cf, bf) / rho1
    for i in range(bf.size):
        bf[i] = bf[i] - a1 * vf[i]
    _level1_cells(c_wts, c_diag, c_idg, c_ranges, c_nranges, c_aggr, c_gather, x1, b1, r1, red, rrows, nbr, wt,
                  diag, inv_diag, agg, off, sizes, chol, chol_t, x, b, r, boost, coarse_sweeps, deg, c_chunks)
    beta = structured.weighted_product_dot(x1, kw, c_wts, c_diag, c_ranges, c_nranges, deg)
    gamma = structured.dot_all(xf, vf)
    a2 = structured.dot_all(xf, bf)
    rho2 = beta - gamma * gamma / rho1
    if not rho2 > 0.0:           # d adds nothing A₁-independent of c (in float32): x1 = the first step's
        for i in range(xf.size):
            xf[i] = a1 * cf[i]
        return
    sc = a1 - gamma * a2 / (rho1 * rho2)
    sd = a2 / rho2
    for i in range(xf.size):
        xf[i] = sc * cf[i] + sd * xf[i]


@nb.njit(cache=True, nogil=True)
def _svcycle(mask, ranges, nranges, cut_red, cut_black, aggr, gather, red, rrows, nbr, wt, diag, inv_diag, agg, off,
             sizes, chol, chol_t, rf, xf, res, x, b, r, sweeps, boost, coarse_sweeps, stop, c_on, c_at, c_wts,
             c_diag, c_idg, c_ranges, c_nranges, c_aggr, c_gather, c_fine_aggr, x1, b1, r1, kcyc, kc, kv, kw, chunks,
             c_chunks):
    """
    :func:`_vcycle` with the fine level on cells (:mod:`.structured`): compute xf = M^-1 rf; return rf · xf.

    rf float64 (2, H): the CG residual on the cells (read only); xf float32 (2, H); res float64
    (H,): scratch, 0 outside the layout's ranges; the rest as :func:`_vcycle`'s (x, b, r: the
    packed coarse levels', from level 1).  Only the clean red-black case (:func:`.structured.fine_layout`):
    the red half-sweep from 0 and the black one, ``sweeps - 1`` more pairs, the red residuals
    restricted, and after the coarse correction (red cells: the black ones are set, not read)
    ``sweeps`` pairs black then red.  ``stop`` is polled where :func:`_vcycle` polls it.
    ``c_on``: level 1 is on its cells too (``c_*``: a :class:`.structured.Coarse`'s arrays, x1,
    b1, r1 its scratch, :func:`_level1_cells`), else on the graph; ``c_at``: level 1's index of
    each level-1 row (its cell, or its row in the packed vectors' level 1).  ``kcyc`` (with ``c_on``):
    level 1 by :func:`_level1_kcycle` (kc, kv, kw its scratch).  ``chunks``, ``c_chunks``: the fine
    level's and level 1's cells in chunks (:func:`.structured.chunks_of`), their loops then on
    numba's threads; none (shape (2, 0, 3)): in one thread.
    """
    deg = ranges.shape[2] - 2
    inv_deg = 1.0 / deg
    par = chunks.shape[1] > 0
    structured.first_red_in(xf, rf, mask, ranges, nranges, chunks, inv_deg)
    structured.half_sweep_in(xf, rf, mask, ranges, nranges, chunks, cut_black, 1, deg, inv_deg)
    for _ in range(sweeps - 1):
        structured.half_sweep_in(xf, rf, mask, ranges, nranges, chunks, cut_red, 0, deg, inv_deg)
        structured.half_sweep_in(xf, rf, mask, ranges, nranges, chunks, cut_black, 1, deg, inv_deg)
    if stop[0] != 0:
        return 0.0
    cb = off[1]
    if c_on:
        if par:
            structured.restrict_red_chunks(rf, xf, res, gather, c_at, b1.reshape(-1), ranges, chunks, cut_red, deg)
        else:
            structured.restrict_red(rf, xf, res, gather, c_at, b1.reshape(-1), ranges, nranges, cut_red, deg)
        if kcyc:
            _level1_kcycle(c_wts, c_diag, c_idg, c_ranges, c_nranges, c_aggr, c_gather, x1, b1, r1, kc, kv, kw, red,
                           rrows, nbr, wt, diag, inv_diag, agg, off, sizes, chol, chol_t, x, b, r, boost,
                           coarse_sweeps, deg, c_chunks)
        else:
            _level1_cells(c_wts, c_diag, c_idg, c_ranges, c_nranges, c_aggr, c_gather, x1, b1, r1, red, rrows, nbr,
                          wt, diag, inv_diag, agg, off, sizes, chol, chol_t, x, b, r, boost, coarse_sweeps, deg,
                          c_chunks)
    else:
        bc = b[cb:off[2]]
        if par:
            structured.restrict_red_chunks(rf, xf, res, gather, c_at, bc, ranges, chunks, cut_red, deg)
        else:
            structured.restrict_red(rf, xf, res, gather, c_at, bc, ranges, nranges, cut_red, deg)
        bc[sizes[1]] = 0.0
        _coarse_cycle(red, rrows, nbr, wt, diag, inv_diag, agg, off, sizes, chol, chol_t, x, b, r, 1, boost,
                      coarse_sweeps)
    if stop[0] != 0:
        return 0.0
    xc, pa = (x1.reshape(-1), c_fine_aggr) if c_on else (x[cb:off[2]], aggr)
    if par:
        structured.prolong_red_chunks(xf, xc, pa, chunks, boost)
    else:
        structured.prolong_red(xf, xc, pa, ranges, nranges, boost)
    for _ in range(sweeps - 1):
        structured.half_sweep_in(xf, rf, mask, ranges, nranges, chunks, cut_black, 1, deg, inv_deg)
        structured.half_sweep_in(xf, rf, mask, ranges, nranges, chunks, cut_red, 0, deg, inv_deg)
    s_black = structured.half_sweep_dot_in(xf, rf, mask, ranges, nranges, chunks, cut_black, 1, deg, inv_deg)
    return structured.half_sweep_dot_in(xf, rf, mask, ranges, nranges, chunks, cut_red, 0, deg, inv_deg) + s_black


@nb.njit(cache=True, nogil=True)
def _spcg(mask, ranges, nranges, cut_red, cut_black, aggr, gather, red, rrows, nbr, wt64, diag64, inv_diag64, agg,
          off, sizes, chol, rhs, u, tol, max_iter, sweeps, boost, coarse_sweeps, deadline, stop, c_on, c_at, c_wts,
          c_diag, c_idg, c_ranges, c_nranges, c_aggr, c_gather, c_fine_aggr, kcyc, chunk):
    """
    :func:`_pcg` with the fine level on cells (:mod:`.structured`; rhs, u float64 (2, H), 0 off the unknowns).

    The same iteration, stop rule (the largest residual below ``tol``), deadline and
    termination flag as :func:`_pcg`, on vectors of the layout's cells (the other cells stay
    0); its dot products in 8 accumulators.  ``c_on``, ``c_*``: level 1 on its cells too
    (:func:`_svcycle`).  ``kcyc`` (with ``c_on``): level 1 as a K-cycle's (:func:`_level1_kcycle`),
    a preconditioner that is not a fixed linear map, so CG's new
    direction is the flexible one (β = z·(r − r_old) / rz_old = −α z·q / rz_old, q = A p;
    Notay 2000); else the usual β = z·r / rz_old.  ``chunk`` > 0: the loops over the cells in
    chunks of that many on numba's threads (:func:`solve`'s ``chunk_cells``).  Returns (iterations,
    final max residual); u is updated in place.
    """
    half = mask.shape[1]
    cells = 2 * half
    total = off[-1]
    wt, diag, inv_diag, chol_t = _single_levels(off, wt64, diag64, inv_diag64, chol)
    xs = np.empty(total, np.float32)        # the coarse levels' rows (the fine level is on the cells)
    bs = np.empty(total, np.float32)
    ws = np.empty(total, np.float32)
    xs[off[1]:] = 0.0
    bs[off[1]:] = 0.0
    ws[off[1]:] = 0.0
    xf = np.zeros((2, half), np.float32)
    res_red = np.zeros(half)
    r = np.zeros((2, half))
    p = np.zeros((2, half))
    q = np.zeros((2, half))
    x1 = np.zeros(c_diag.shape, np.float32)
    b1 = np.zeros(c_diag.shape, np.float32)
    r1 = np.zeros(c_diag.shape[1])
    kcyc = kcyc and c_on
    kshape = c_diag.shape if kcyc else (2, 1)
    kc = np.zeros(kshape, np.float32)
    kv = np.zeros(kshape, np.float32)
    kw = np.zeros(kshape, np.float32)
    rl, pl, ql, ul, xl = r.reshape(-1), p.reshape(-1), q.reshape(-1), u.reshape(-1), xf.reshape(-1)
    deg = ranges.shape[2] - 2
    # chunk > 0: the fine level's vector loops over chunks of that many cells, on all cores
    chunks = structured.chunks_of(ranges, nranges, chunk) if chunk > 0 else np.zeros((2, 0, 3), np.int64)
    par = chunks.shape[1] > 0
    # level 1 on its cells: its loops in chunks of an eighth as many (its box is about an eighth)
    c_chunks = structured.chunks_of(c_ranges, c_nranges, max(1, chunk // 8)) if par and c_on else \
        np.zeros((2, 0, 3), np.int64)
    structured.product_dot_in(u, q, mask, ranges, nranges, chunks, cut_red, cut_black, deg)
    rl[:] = rhs.reshape(-1)
    res = _subtract_max(rl, ql, 1.0, cells)
    if res < tol:
        return 0, res
    rz = _svcycle(mask, ranges, nranges, cut_red, cut_black, aggr, gather, red, rrows, nbr, wt, diag, inv_diag, agg,
                  off, sizes, chol, chol_t, r, xf, res_red, xs, bs, ws, sweeps, boost, coarse_sweeps, stop, c_on, c_at,
                  c_wts, c_diag, c_idg, c_ranges, c_nranges, c_aggr, c_gather, c_fine_aggr, x1, b1, r1, kcyc, kc, kv,
                  kw, chunks, c_chunks)
    pl[:] = xl
    it = 0
    while it < max_iter:
        if stop[0] != 0 or (deadline > 0.0 and _now() > deadline):      # polled before every iteration
            break
        it += 1
        pq = structured.product_dot_in(p, q, mask, ranges, nranges, chunks, cut_red, cut_black, deg)
        if not pq > 0.0:
            break
        alpha, res, done = _descend_in(rl, ql, ul, pl, rz, pq, tol, cells, stop, chunk if par else 0)
        if done:
            break
        rz_new = _svcycle(mask, ranges, nranges, cut_red, cut_black, aggr, gather, red, rrows, nbr, wt, diag,
                          inv_diag, agg, off, sizes, chol, chol_t, r, xf, res_red, xs, bs, ws, sweeps, boost,
                          coarse_sweeps, stop, c_on, c_at, c_wts, c_diag, c_idg, c_ranges, c_nranges, c_aggr,
                          c_gather, c_fine_aggr, x1, b1, r1, kcyc, kc, kv, kw, chunks, c_chunks)
        # beta's numerator: z · r, or the flexible z · (r − r_old) = −alpha z · q (r_old = r + alpha q)
        num = rz_new
        if kcyc:
            num = -alpha * (structured.dot_all_chunks(xl, ql, chunk) if par else structured.dot_all(xl, ql))
        _turn_in(ul, pl, xl, alpha, rz, num, cells, chunk if par else 0)
        rz = rz_new
    return it, res


def _coarse_args(coarse, h):
    """Return :func:`_spcg`'s level-1 arguments (``c_on`` .. ``c_fine_aggr``): ``coarse``'s, or the graph's level 1."""
    if coarse is not None:
        return (True, coarse.cell, coarse.wts, coarse.diag, coarse.inv_diag, coarse.ranges, coarse.nranges,
                coarse.aggr, coarse.gather, coarse.fine_aggr)
    deg = h.nbr.shape[1]
    none32 = np.zeros((2, 1), np.float32)
    return (False, np.arange(int(h.sizes[1]), dtype=np.int64), np.zeros((deg, 2, 1), np.float32), none32, none32,
            np.zeros((2, 3, 2 + deg), np.int64), 0, np.zeros(1, np.uint32), np.zeros((1, 1), np.int64),
            np.zeros(1, np.uint32))


def beside_of(n_unknowns: int) -> bool:
    """
    Return whether a problem builds its coarse levels on a second thread while its fine level's cells are laid out.

    The rule (:data:`BESIDE_MIN_UNKNOWNS`): a problem of that many unknowns, and numba allowed
    more than one thread (``planner.max_threads``: :func:`numba.get_num_threads` in this thread).
    """
    return int(n_unknowns) >= BESIDE_MIN_UNKNOWNS and nb.get_num_threads() > 1


class _Beside:
    """Run ``fn(*args)`` on a thread of its own; :meth:`result` waits for it: its result, or raises its exception."""

    def __init__(self, fn, *args):
        self._out = None
        self._error = None

        def run():
            try:
                self._out = fn(*args)
            except BaseException as e:     # noqa: BLE001 - raised in result(), in the solve's thread
                self._error = e
        self._thread = threading.Thread(target=run, name="field-beside", daemon=True)
        self._thread.start()

    def join(self) -> None:
        """Wait for the thread to end."""
        self._thread.join()

    def result(self):
        self.join()
        if self._error is not None:
            raise self._error
        return self._out


def _fine_layout_alone(nb0, coords, shape, red0, max_cells_per_unknown):
    """
    Return :func:`.structured.laid_out` of a fine level from its own level-1 aggregates, without its coarse levels.

    The aggregates :func:`_levels` makes first (:func:`_aggregates` of the same coordinates on
    the same halved grid: the same arrays), so that the layout runs while :func:`_levels`
    builds the coarse levels on another thread.
    """
    half = (shape + 1) // 2
    agg, ccoords, _ = _aggregates(coords, half, np.full(int(np.prod(half)), -1, np.int64))
    return structured.laid_out(nb0, coords, shape, red0, agg, ccoords.shape[0], max_cells_per_unknown)


def _chunk_of(layout, chunk_cells):
    """Return the chunk of a fine level on cells: ``chunk_cells``, or (None) :data:`PARALLEL_CHUNK` on a large box."""
    if chunk_cells is not None:
        return int(chunk_cells)
    return PARALLEL_CHUNK if 2 * layout.half >= PARALLEL_MIN_CELLS else 0


def _solve_geometric(h, layout, lv, rhs, x0, tol, max_iter, deadline, stop, sweeps, chunk):
    """
    Return :func:`solve`'s ``(x, iterations, largest residual)`` by :mod:`.geometric`'s levels ``lv`` under ``layout``.

    h: the problem's fine level (:class:`Hierarchy`, not coarsened); ``chunk``: :func:`.geometric.pcg`'s.
    """
    rows = None if h.in_order else h.fine_of_input     # each input's fine row
    u = np.zeros((2, layout.half)) if x0 is None else layout.to_cells(x0, rows)
    if stop is None:
        stop = np.zeros(1, np.int64)
    elif stop[0] != 0:
        return np.zeros(h.nb0.shape[0]), 0, np.inf
    it, res = geometric.pcg(layout, lv, layout.to_cells(rhs, rows), u, tol, max_iter, deadline, stop, sweeps, chunk)
    return layout.from_cells(u, rows), int(it), float(res)


def solve(nbr, coords, shape, rhs, tol=1e-12, max_iter=500, deadline=0.0, sweeps=None, boost=None, stop=None,
          coarse_sweeps=COARSE_SWEEPS, route="auto", x0=None, coarse_cells=True, kcycle=None, chunk_cells=None,
          beside=None):
    """
    Solve ``A x = rhs`` on n unknowns (see the module doc) by multigrid-preconditioned CG.

    nbr int (n, deg): each unknown's face neighbours among the unknowns, n = none (a wall,
    an obstacle or a known node, whose value is in ``rhs``); coords int (n, ndim) grid
    coordinates; shape: the grid shape; rhs float (n,).  Stops when the largest residual
    is below ``tol``, after ``max_iter`` iterations or at ``deadline``
    (``time.perf_counter()`` seconds, 0 = none), or when the termination flag ``stop``
    (``termination.Termination.flag``, int64 (1,); None = never) is set: then the
    result is partial and the caller must not keep it.  ``sweeps``: the fine level's
    Gauss–Seidel sweeps before and after the coarse correction (None: :func:`sweeps_of` the
    grid's dimension); ``boost``: the coarse correction's scale (None: :func:`boost_of` the
    grid's dimension and the sweeps).  ``route``: "auto", on a
    2-D grid :mod:`.geometric`'s levels under the fine level's cells where :func:`.geometric.applies`
    says so, else the fine level on the grid's cells where :func:`.structured.fine_layout`'s rule
    says so (else on the node graph); "graph", on the node graph always; "structured", on the
    cells wherever they can hold it, whatever its size, with the aggregation levels; "geometric",
    the geometric levels wherever they apply, whatever the size (else as "structured"; the tests').
    The geometric levels read ``sweeps`` (the fine level's) and ``chunk_cells`` (their coarse levels'
    loops in chunks of a quarter as many cells), and none of ``boost``, ``coarse_sweeps``,
    ``coarse_cells``, ``kcycle`` and ``beside``.
    ``coarse_cells``: with the fine level on cells, level 1 on its cells too where
    :func:`.structured.coarse_layout`'s rule says so (with route "structured": wherever they can
    hold it); False: on the node graph (the tests').  The same
    values either way: level 1's cells compute its rows' float32 values in the graph's order.
    ``kcycle``: level 1 as a K-cycle's (:func:`_level1_kcycle`); None: where :func:`kcycle_of`
    says so; True: wherever level 1 is on its cells (the tests'); False: never.
    ``x0``: float (n,), the initial guess (None: 0); the
    stop rule is the same from any guess, so a guess near the solution saves iterations only.
    ``chunk_cells``: with the fine level on cells, its vector loops (sweeps, products, the
    residual, the restriction, the prolongation, CG's updates and dot products) over chunks of
    that many cells on all of numba's threads, 0 in one thread; the dot products are summed per
    chunk and then over the chunks in order, so a chunk size gives the same bits on any number
    of threads (and other bits than one thread's order).  None: :data:`PARALLEL_CHUNK` from
    :data:`PARALLEL_MIN_CELLS` cells on (the tests' other values).
    ``beside``: build the coarse levels on a second thread while the fine level's cells are
    laid out (the same arrays); None: where :func:`beside_of` says so; True / False: always /
    never (the tests').

    Returns ``(x float64 (n,), iterations, largest residual)``.
    """
    if route not in ROUTES:
        raise ValueError(f"route: expected one of {ROUTES}, got {route!r}")
    nbr = np.asarray(nbr)
    n = nbr.shape[0]
    if n == 0:
        return np.zeros(0), 0, 0.0
    rhs = np.asarray(rhs, dtype=float)
    if rhs.shape != (n,):
        raise ValueError(f"rhs: expected shape ({n},), got {rhs.shape}")
    if x0 is not None:
        x0 = np.asarray(x0, dtype=float)
        if x0.shape != (n,):
            raise ValueError(f"x0: expected shape ({n},), got {x0.shape}")
    if sweeps is None:
        sweeps = sweeps_of(len(shape))
    if boost is None:
        boost = boost_of(len(shape), sweeps)
    max_cells, min_unknowns = ((structured.MAX_CELLS_PER_UNKNOWN, structured.MIN_UNKNOWNS) if route == "auto"
                               else (np.inf, 0))
    if stop is not None and stop[0] != 0:
        return np.zeros(n), 0, np.inf           # as the set-up would stop at its first level
    h = Hierarchy(nbr, coords, shape, coarsen=False)
    if route in ("auto", "geometric") and len(shape) == 2 and structured.may_lay_out(n, 2, sweeps, min_unknowns):
        layout = structured.laid_out(h.nb0, h.coords, shape, h.red0, np.zeros(n, np.uint32), 0, max_cells, True)
        lv = geometric.levels(h.nb0, h.coords, h.red0, layout) if geometric.applies(len(shape), layout) else None
        if lv is not None:
            return _solve_geometric(h, layout, lv, rhs, x0, tol, max_iter, deadline, stop, sweeps,
                                    _chunk_of(layout, chunk_cells))
    built = None
    try:
        if route != "graph" and structured.may_lay_out(n, len(shape), sweeps, min_unknowns) and (
                beside_of(n) if beside is None else bool(beside)):
            coarsening = _Beside(h.coarsen, stop)         # the coarse levels on a second thread, meanwhile
            try:
                built = (_fine_layout_alone(h.nb0, h.coords, h.shape, h.red0, max_cells),)  # the fine cells
            finally:
                coarsening.join()                         # (no thread left running, whatever happened here)
            coarsening.result()
        else:
            h.coarsen(stop)
    except Stopped:
        return np.zeros(n), 0, np.inf
    if stop is None:
        stop = np.zeros(1, np.int64)
    layout = None
    if route != "graph":
        layout = structured.fine_layout(h, shape, sweeps, max_cells, min_unknowns, built=built)
    if layout is not None:
        rows = None if h.in_order else h.fine_of_input     # each input's fine row
        u = np.zeros((2, layout.half)) if x0 is None else layout.to_cells(x0, rows)
        coarse = None
        if coarse_cells:
            coarse = structured.coarse_layout(h, shape, layout, coarse_sweeps, **(
                {} if route == "auto" else {"max_cells_per_unknown": np.inf}))
        it, res = _spcg(layout.mask, layout.ranges, layout.nranges, layout.cut_red, layout.cut_black, layout.aggr,
                        layout.gather, h.red, h.rrows, h.nbr, h.wt, h.diag, h.inv_diag, h.agg, h.off, h.sizes,
                        h.chol, layout.to_cells(rhs, rows), u, float(tol), int(max_iter), int(sweeps),
                        float(boost), int(coarse_sweeps), float(deadline), stop, *_coarse_args(coarse, h),
                        kcycle_of(n, len(shape), coarse) if kcycle is None else bool(kcycle),
                        _chunk_of(layout, chunk_cells))
        return layout.from_cells(u, rows), int(it), float(res)
    rows = slice(0, n) if h.in_order else h.fine_of_input     # each input's fine row (in order: no renumbering)
    b = np.zeros(n + 1)
    b[rows] = rhs
    x = np.zeros(n + 1)
    if x0 is not None:
        x[rows] = x0
    it, res = _pcg(h.nb0, h.red, h.rrows, h.nbr, h.wt, h.diag, h.inv_diag, h.agg, h.off, h.sizes,
                   h.chol, b, x, float(tol), int(max_iter), int(sweeps),
                   float(boost), int(coarse_sweeps), float(deadline), stop)
    return x[rows], int(it), float(res)
