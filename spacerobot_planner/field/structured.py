"""
The multigrid's fine level on a structured grid: the band's bounding box, red and black cells apart.

The node graph's fine level (:mod:`.multigrid`) reads every neighbour through a table of
indices.  On a box of grid cells the neighbours are at fixed offsets instead, so a sweep,
a matrix-vector product and the residual are plain vector loops; the price is the box's
cells that are not unknowns (walls, obstacles, known nodes, the ghost layer), which every
loop also visits.  It pays where the box has at most :data:`MAX_CELLS_PER_UNKNOWN` cells per
unknown (the big first band of a plan); :func:`fine_layout` holds the rule.

The layout.  The unknowns' bounding box (a periodic axis whole: it must be axis 0, of even
length) and one ghost layer on every side; axes 1.. padded to an odd length, so that every
C-order stride is odd and the colour of a cell (the parity of its coordinate sum) is the
parity of its flat index ``f`` (offset by ``base`` in {2, 3}, so that red, an even
coordinate sum, is an even ``f``: the graph's red).  A cell's values live at ``v[f % 2, f // 2]``
of a (2, H) array: a red cell k reads the black half at ``k + (s - 1) / 2`` and
``k - (s + 1) / 2`` for each stride s (a black cell: ``k + (s + 1) / 2`` and
``k - (s - 1) / 2``).  A float32 mask is 1 at the unknowns and 0 elsewhere: every loop
multiplies by it, so the other cells stay 0 and read as the graph's "no neighbour".  The
periodic axis 0 is three loop ranges (its first slab, the middle, its last slab); the end
slabs read across the seam, ``(N0 - 1)·S0`` away.  A cut edge (a face neighbour in the box
that is an unknown, where the graph says none: a wall between them) is a short list per
colour, taken back out after the vector loop.

The coarse levels are the graph's (:class:`.multigrid.Hierarchy`), linked to the cells by
each red cell's aggregate (the prolongation) and each level-1 node's red cells (the
restriction, a gather in the graph's row order: the same float32 sums as the graph's
scatter).  The black residuals are 0 after the V-cycle's black half-sweep, as on the graph.
Level 1 also goes on cells where it can (:func:`coarse_layout`, :class:`Coarse`: its own box,
laid out as the fine one, with the graph's weights per cell and direction, 0 where there is
no neighbour, so no cut list), linked to level 2 the same way; its sweeps compute the graph's
float32 values in the graph's order, so the V-cycle gives the same bits either way.  Level 1
on the graph cost about 75 us of a 180 us V-cycle on the paper's 2-D band (gathers through
its index table); on cells the paper bands' whole solves took 0.85x (2-D) and 0.92x (3-D),
random scenes' first bands 0.84x and 0.93x (medians).

On a large box (:data:`.multigrid.PARALLEL_MIN_CELLS`) the fine level's vector loops run on all of
numba's threads (the ``*_chunks`` kernels: each colour's ranges cut into chunks of
:data:`.multigrid.PARALLEL_CHUNK` cells, :func:`chunks_of`): every cell's value is computed as in one
thread, and a dot product is summed per chunk, then over the chunks in their order, so the solve
gives the same bits on any number of threads.

Editing this module: numba's cache keys the kernels of :mod:`.multigrid` that call these (and
link them in: ``_spcg``, ``_svcycle``) on multigrid.py's own time stamp, so after an edit here delete the
cached kernels (``field/__pycache__/*.nbi``, ``*.nbc``) or touch multigrid.py.
"""
from __future__ import annotations

import numba as nb
import numpy as np

from .graph import grid_strides, named_neighbours, put_at, strided_sum, take_at

#: The structured fine level is used where the box (ghosts and padding included) has at most
#: this many cells per unknown.  Whole solves (layout built, interleaved with the graph's route,
#: random 3-D bands; time on the cells / time on the graph): 0.82-0.95 at 1.5-1.63 cells per
#: unknown, 0.90-1.10 at 1.7-1.8; per CG iteration 0.71-0.83 at 1.15-1.5, 0.9 at 1.8, 1.33 at 3.3.
MAX_CELLS_PER_UNKNOWN = 1.6
#: ... and has at least this many unknowns: a smaller problem takes the graph's route without a
#: look at its box (the look costs 3 us, 5 % of a 200-node band's solve; every sampled band
#: under 6 000 unknowns had more than 2 cells per unknown).
MIN_UNKNOWNS = 1000
#: Level 1 goes on cells too (:func:`coarse_layout`) where its box has at most this many cells per
#: row (its ghost layer weighs more than the fine level's).
MAX_COARSE_CELLS_PER_UNKNOWN = 2.0
#: The grid dimensions with structured kernels (the degrees 4 and 6 are spelled out).
DIMENSIONS = (2, 3)


class Layout:
    """
    The structured fine level of one problem (see the module docstring).

    half: H, the length of each colour's half; ``cell`` int64 (n,): each fine row's index in
    a flattened (2, H) array; ``mask`` float32 (2, H); ``ranges`` int64 (2, 3, 2 + deg):
    per colour the loop ranges of half indices ``[k0, k1)`` and the other colour's offset per
    direction (``2a`` the − neighbour along axis a, ``2a + 1`` the +), ``nranges`` of them (1,
    or 3 with a periodic axis 0); ``cut_red`` / ``cut_black`` int64 (k, 2): a cut edge's cell
    and its neighbour (half indices); ``aggr`` uint32 (H,): each red cell's level-1 node
    (others: level 1's dummy row); ``gather`` int64 (level-1 nodes, 2^(ndim-1)): each level-1
    node's red cells in fine row order, padded with ``H - 1`` (a red cell outside every range:
    its residual stays 0).  ``cells``: the box's cells.  ``lo``, ``hi``, ``base``, ``strides`` and
    ``padded`` (int64 (ndim,) but base): :func:`_box`'s, so that a cell's flat index is
    ``base + Σ (c − lo + 1) · strides`` (its half index that over 2).
    """

    def __init__(self, cell, mask, ranges, nranges, cut_red, cut_black, aggr, gather, cells, lo, hi, base, strides,
                 padded):
        """Hold the arrays of :func:`_build` and :func:`_box`'s box."""
        self.cell, self.mask, self.ranges, self.nranges = cell, mask, ranges, int(nranges)
        self.cut_red, self.cut_black, self.aggr, self.gather = cut_red, cut_black, aggr, gather
        self.half = int(mask.shape[1])
        self.cells = int(cells)
        self.lo, self.hi, self.base, self.strides, self.padded = lo, hi, int(base), strides, padded

    def to_cells(self, values, rows=None):
        """Return float64 (2, H): ``values`` (n,) of the fine rows (or of the inputs at fine ``rows``) on the cells."""
        v = np.zeros((2, self.half))
        put_at(v.reshape(-1), self.cell if rows is None else self.cell[rows], np.ascontiguousarray(values, dtype=float))
        return v

    def from_cells(self, v, rows=None):
        """Return the fine rows' values (n,) of ``v`` (2, H) (or the inputs' values, fine ``rows`` of them)."""
        return take_at(v.reshape(-1), self.cell if rows is None else self.cell[rows])


def fine_layout(h, shape, sweeps, max_cells_per_unknown=MAX_CELLS_PER_UNKNOWN, min_unknowns=MIN_UNKNOWNS,
                built=None):
    """
    Return the structured fine level of a problem (a :class:`Layout`), or None: the graph's route.

    The rule (one place): a structured fine level where the grid has 2 or 3 dimensions
    (:data:`DIMENSIONS`), the problem has coarse levels (more than one level), the V-cycle
    smooths (``sweeps`` ≥ 1), at most axis 0 is periodic (an edge crosses its seam) and then of
    even length (an odd one puts two cells of one colour side by side), and the problem has at
    least ``min_unknowns`` unknowns and its box at most ``max_cells_per_unknown`` cells per
    unknown.  h: the problem's :class:`.multigrid.Hierarchy` (its fine rows, coordinates and
    level 1); shape: the grid's.  The fine rows' neighbours follow the node graph's
    convention (``nb0[i, 2a + (0|1)]`` the −/+ face neighbour along axis a, or none), as
    :func:`.multigrid.solve` requires: a neighbour that is none where the box holds an unknown
    is a cut edge.
    ``built``: ``(laid_out(...),)`` of the same fine level, made while ``h`` coarsened
    (:func:`.multigrid.solve`: from the fine level's own level-1 aggregates, the same arrays), or
    None: laid out here.
    """
    nb0 = h.nb0
    n = nb0.shape[0]
    if not may_lay_out(n, h.coords.shape[1], sweeps, min_unknowns) or h.levels < 2 or h.rrows[0] != h.red[0]:
        return None
    if built is not None:
        return built[0]
    return laid_out(nb0, h.coords, shape, h.red0, h.agg[:n], int(h.sizes[1]), max_cells_per_unknown)


def may_lay_out(n: int, ndim: int, sweeps: int, min_unknowns: int = MIN_UNKNOWNS) -> bool:
    """Tell whether :func:`fine_layout`'s rule can hold for ``n`` unknowns (what it asks before the coarse levels)."""
    return n >= min_unknowns and ndim in DIMENSIONS and sweeps >= 1


def laid_out(nb0, coords, shape, red0: int, agg, coarse_nodes: int, max_cells_per_unknown,
             seamless: bool = False) -> "Layout | None":
    """
    Return the fine level on its box's cells (:func:`fine_layout`'s arrays), or None where they cannot hold it.

    nb0 uint32 (n, deg), coords (n, ndim), ``red0``: the fine level (:class:`.multigrid.Hierarchy`'s,
    red rows first); agg uint32 (n,): each row's level-1 row, of ``coarse_nodes`` (0: none); the box at most
    ``max_cells_per_unknown`` cells per unknown.  ``seamless``: None also where an edge crosses
    axis 0's seam (one loop range, as :mod:`.geometric`'s levels need), before the cells are built.
    """
    n = nb0.shape[0]
    shape = np.asarray(shape, np.int64)
    ok, lo, hi, padded, strides, base, periodic0 = _box(nb0, coords, shape)
    cells = int(padded[0] * strides[0])
    if not ok or cells > max_cells_per_unknown * n or (seamless and periodic0):
        return None
    ok, *arrays = _build(nb0, coords, shape, lo, padded, strides, base, periodic0, agg, int(red0),
                         int(coarse_nodes), True)
    return Layout(*arrays, cells, lo, hi, base, strides, padded) if ok else None


class Coarse:
    """
    Level 1 of the multigrid on the cells of its own box (see the module docstring): :func:`coarse_layout`.

    half: H, each colour's half; ``cell`` int64 (m,): each level-1 row's index in a flattened
    (2, H) array; ``wts`` float32 (deg, 2, H): each cell's weight towards its neighbour in
    each direction (0 where the graph's level has none: a wall, an obstacle, a cut, a cell
    that is no row); ``diag``, ``inv_diag`` float32 (2, H): the level's diagonal and its
    inverse, 0 off its rows (so their x stays 0); ``ranges``, ``nranges``: as
    :class:`Layout`'s; ``aggr`` uint32 (H,): each red cell's level-2 row (others: level 2's
    dummy row); ``gather`` int64 (level-2 rows, 2^(ndim-1)): each level-2 row's red cells in
    level 1's row order, padded with ``H - 1`` (a red cell outside every range).
    ``fine_aggr`` uint32 (the fine layout's H,): each fine red cell's level-1 cell (a flat
    index of level 1's (2, H) array; others: level 1's red cell ``H - 1``, which stays 0).  ``cells``: the
    box's cells.
    """

    def __init__(self, cell, wts, diag, inv_diag, ranges, nranges, aggr, gather, fine_aggr, cells):
        """Hold the arrays of :func:`coarse_layout`."""
        self.cell, self.wts, self.diag, self.inv_diag = cell, wts, diag, inv_diag
        self.ranges, self.nranges, self.aggr, self.gather = ranges, int(nranges), aggr, gather
        self.fine_aggr = fine_aggr
        self.half = int(diag.shape[1])
        self.cells = int(cells)


def coarse_layout(h, shape, layout, coarse_sweeps, max_cells_per_unknown=MAX_COARSE_CELLS_PER_UNKNOWN):
    """
    Return level 1 of hierarchy ``h`` on cells (a :class:`Coarse`), or None: it stays on the node graph.

    The rule (one place): the fine level is on cells (``layout``, a :class:`Layout`), the
    coarse levels are smoothed (``coarse_sweeps`` ≥ 1: the cells run the graph's red-black
    steps, which start with a sweep), level 1
    is not the coarsest (``h`` has at least 3 levels), no two of its rows of one colour are
    neighbours (an odd periodic axis 0 at level 1, whose rows the graph then sweeps one by
    one in order) and its box has at most ``max_cells_per_unknown`` cells per row.  Level 1's
    box is laid out as the fine one (:func:`_box`, :func:`_build`, on the level's own
    coordinates (``h.coords1``), on ``shape`` halved rounding up), its weights and
    diagonal copied from the graph's level 1, so a sweep over it computes the same float32
    values as the graph's sweep over its rows.
    """
    if layout is None or coarse_sweeps < 1 or h.levels < 3 or h.rrows[1] != h.red[1]:
        return None
    a, m = int(h.off[1]), int(h.sizes[1])
    shape1 = (np.asarray(shape, np.int64) + 1) // 2
    nb1 = h.nbr[a:a + m]
    coords1 = h.coords1
    ok, lo, _, padded, strides, base, periodic0 = _box(nb1, coords1, shape1)
    cells = int(padded[0] * strides[0])
    if not ok or cells > max_cells_per_unknown * m:
        return None
    ok, cell, mask, ranges, nranges, _, _, aggr, gather = _build(nb1, coords1, shape1, lo, padded, strides, base,
                                                                 periodic0, h.agg[a:a + m], int(h.red[1]),
                                                                 int(h.sizes[2]), False)
    if not ok:
        return None
    wts, diag, inv_diag, fine_aggr = _coarse_arrays(cell, h.wt[a:a + m], h.diag[a:a + m], h.inv_diag[a:a + m],
                                                    layout.aggr, mask.shape[1])
    return Coarse(cell, wts, diag, inv_diag, ranges, nranges, aggr, gather, fine_aggr, cells)


# --------------------------------------------------------------------------
# the layout, in O(n)
# --------------------------------------------------------------------------
@nb.njit(cache=True, nogil=True)
def _box(nb0, coords, shape):
    """
    Return the box of the unknowns: ``(ok, lo, hi, padded, strides, base, periodic0)``.

    nb0 uint32 (n, deg): the fine neighbours (n = none); coords (n, ndim); shape int64 (ndim,).
    lo, hi int64 (ndim,): the box's lowest and highest coordinates (the ghost layer beyond them); padded: the
    box's extent with its ghosts (axes 1.. odd); strides: its C-order strides (odd); base:
    the flat index's offset (its parity is the colour's); periodic0: an edge crosses axis
    0's seam (the box then spans the axis).  ``ok`` False: an edge crosses another axis'
    seam, or axis 0's of odd length (the graph's route).
    """
    n, ndim = coords.shape
    lo = np.empty(ndim, np.int64)
    hi = np.empty(ndim, np.int64)
    wraps = np.zeros(ndim, np.bool_)
    for a in range(ndim):
        col = coords[:, a]
        low = high = col[0]
        for i in range(n):
            low = min(low, col[i])
            high = max(high, col[i])
        lo[a] = low
        hi[a] = high
        end = shape[a] - 1
        if low == 0 or high == end:      # the neighbour below 0 (above the last) is across the seam
            below = nb0[:, 2 * a]
            above = nb0[:, 2 * a + 1]
            for i in range(n):
                if (col[i] == 0 and below[i] < n) or (col[i] == end and above[i] < n):
                    wraps[a] = True
                    break
    padded = np.empty(ndim, np.int64)
    ok = not (wraps[0] and shape[0] % 2 == 1)
    for a in range(1, ndim):
        ok = ok and not wraps[a]
    if wraps[0]:
        lo[0] = 0
        hi[0] = shape[0] - 1
    base = 2
    for a in range(ndim):
        padded[a] = hi[a] - lo[a] + 3
        if a > 0 and padded[a] % 2 == 0:
            padded[a] += 1
        base += lo[a]
    base = 2 + (base + ndim) % 2       # f = base + sum((c - lo + 1) * stride): f and sum(c) of one parity
    return ok, lo, hi, padded, grid_strides(padded), base, wraps[0]


@nb.njit(cache=True, nogil=True)
def _half_range(colour, f0, f1):
    """Return the half indices ``[k0, k1)`` of the cells of ``colour`` (0 red, 1 black) with flat index in [f0, f1)."""
    if colour == 0:
        return (f0 + 1) // 2, (f1 + 1) // 2
    return f0 // 2, f1 // 2


@nb.njit(cache=True, nogil=True)
def _half_offset(colour, step):
    """Return the half-index offset of the other colour's cell ``step`` (odd) flat cells away."""
    return (step - 1) // 2 if colour == 0 else (step + 1) // 2


@nb.njit(cache=True, nogil=True, inline="always")
def _neighbour(f, d, steps, periodic0, seam, c0, last0):
    """Return the flat index of the cell ``f``'s neighbour ``d`` (axis 0 coordinate c0, last0 its end: the seam)."""
    if periodic0 and d == 0 and c0 == 0:
        return f + seam
    if periodic0 and d == 1 and c0 == last0:
        return f - seam
    return f + steps[d]


@nb.njit(cache=True, nogil=True)
def _build(nb0, coords, shape, lo, padded, strides, base, periodic0, agg, red, coarse_nodes, find_cuts):
    """
    Build the layout of :func:`_box`'s box: ``(ok, cell, mask, ranges, nranges, cut_red, cut_black, aggr, gather)``.

    nb0 uint32 (n, deg), coords (n, ndim): the fine rows, the first ``red`` of them red; agg
    uint32 (n,): each row's level-1 node, ``coarse_nodes`` of them (0: no aggregates, ``aggr`` and
    ``gather`` then unused, as under :mod:`.geometric`'s levels).  See :class:`Layout` for
    the arrays; ``find_cuts`` False: no cut edges looked for (none returned: level 1's cells
    carry their weights instead).  ``ok`` False: two rows on one cell, a red row on a black cell, or a level-1
    node with more red cells than a block holds (the graph's route).
    """
    n, deg = nb0.shape
    ndim = coords.shape[1]
    total = base + padded[0] * strides[0] + 4
    total += total % 2
    half = total // 2
    flat = np.empty(n, np.int64)
    cell = np.empty(n, np.int64)
    mask = np.zeros((2, half), np.float32)
    mflat = mask.reshape(-1)
    ranges = np.zeros((2, 3, 2 + deg), np.int64)
    aggr = np.full(half, coarse_nodes, np.uint32)
    width = 1 << (ndim - 1)
    gather = np.full((coarse_nodes, width), half - 1, np.int64)
    none = np.empty((0, 2), np.int64)
    failed = (False, flat, mask, ranges, 0, none, none, aggr, gather)
    f_origin = base                          # the flat index of coordinates 0 (off the box where lo > 1)
    for a in range(ndim):
        f_origin += (1 - lo[a]) * strides[a]
    for i in range(n):
        f = f_origin + strided_sum(coords, i, strides, 0)
        flat[i] = f
        cell[i] = (f & 1) * half + (f >> 1)
        if mflat[cell[i]] != 0.0 or (i < red) != (f & 1 == 0):
            return failed
        mflat[cell[i]] = 1.0
    seam = (padded[0] - 3) * strides[0]      # axis 0's seam: slab 1 to slab N0
    steps = np.empty(deg, np.int64)
    for d in range(deg):
        steps[d] = strides[d // 2] if d % 2 == 1 else -strides[d // 2]
    first = base + strides[0]                # the first interior slab's flat index ...
    last = base + (padded[0] - 1) * strides[0]   # ... and the end of the last one
    nranges = 3 if periodic0 else 1
    for colour in range(2):
        for r in range(nranges):
            f0, f1 = first, last
            if periodic0:
                f0 = first if r == 0 else first + strides[0] if r == 1 else last - strides[0]
                f1 = first + strides[0] if r == 0 else last - strides[0] if r == 1 else last
            k0, k1 = _half_range(colour, f0, f1)
            ranges[colour, r, 0] = k0
            ranges[colour, r, 1] = max(k0, k1)
            for d in range(deg):
                step = steps[d]
                if periodic0 and d == 0 and r == 0:
                    step = seam
                elif periodic0 and d == 1 and r == 2:
                    step = -seam
                ranges[colour, r, 2 + d] = _half_offset(colour, step)
    # the cut edges, i · deg + d: only rows with fewer graph neighbours than unknown cells around them
    around = _neighbour_counts(mask, ranges, nranges, deg) if find_cuts else mflat     # (unread without cuts)
    cut_at = np.empty(n * deg, np.int64)     # (written only where met)
    ncut = 0
    for i in range(n if find_cuts else 0):
        if named_neighbours(nb0, i, n) == around[cell[i]]:
            continue
        f = flat[i]
        for d in range(deg):
            if nb0[i, d] < n:
                continue                     # the face neighbour it names (the graph's convention)
            g = _neighbour(f, d, steps, periodic0, seam, coords[i, 0], shape[0] - 1)
            if mflat[(g & 1) * half + (g >> 1)] != 0.0:     # an unknown on the other side of a wall
                cut_at[ncut] = i * deg + d
                ncut += 1
    counts = np.zeros(2, np.int64)
    for e in range(ncut):
        counts[flat[cut_at[e] // deg] & 1] += 1
    cut_red = np.empty((counts[0], 2), np.int64)
    cut_black = np.empty((counts[1], 2), np.int64)
    counts[:] = 0
    for e in range(ncut):
        i, d = cut_at[e] // deg, cut_at[e] % deg
        f = flat[i]
        g = _neighbour(f, d, steps, periodic0, seam, coords[i, 0], shape[0] - 1)
        cuts = cut_red if f & 1 == 0 else cut_black
        cuts[counts[f & 1], 0] = f >> 1
        cuts[counts[f & 1], 1] = g >> 1
        counts[f & 1] += 1
    filled = np.zeros(coarse_nodes, np.int64)
    for i in range(red if coarse_nodes > 0 else 0):     # in row order: the graph's restriction adds them so
        c = agg[i]
        if filled[c] == width:
            return failed
        aggr[flat[i] >> 1] = c
        gather[c, filled[c]] = flat[i] >> 1
        filled[c] += 1
    return True, cell, mask, ranges, nranges, cut_red, cut_black, aggr, gather


@nb.njit(cache=True, nogil=True)
def _neighbour_counts(mask, ranges, nranges, deg):
    """
    Return float32 (2 H,): each cell's unknown face neighbours in the box (the other colour's mask at its offsets).

    Over the layout's ranges (so across axis 0's seam where it is periodic), flattened as
    the cells' ``v[f % 2, f // 2]``; 0 outside the ranges.
    """
    out = np.zeros(mask.shape, np.float32)
    for colour in range(2):
        ms = mask[1 - colour]
        for r in range(nranges):
            k0, k1 = ranges[colour, r, 0], ranges[colour, r, 1]
            s0, s1, s2, s3, s4, s5 = _neighbour_views(ms, k0, k1, ranges[colour, r, 2:], deg)
            t = out[colour, k0:k1]
            if deg == 4:
                for i in range(k1 - k0):
                    t[i] = s0[i] + s1[i] + s2[i] + s3[i]
            else:
                for i in range(k1 - k0):
                    t[i] = s0[i] + s1[i] + s2[i] + s3[i] + s4[i] + s5[i]
    return out.reshape(-1)


@nb.njit(cache=True, nogil=True)
def _coarse_arrays(cell, wt, diag, inv_diag, fine_aggr_rows, half):
    """
    Return level 1's ``(wts, diag, inv_diag, fine_aggr)`` on its cells (see :class:`Coarse`).

    cell int64 (m,): each row's cell, from :func:`_build`; wt float64 (m, deg), diag, inv_diag
    float64 (m,): the graph's level-1 rows; fine_aggr_rows uint32: the fine layout's map of
    its red cells to level-1 rows (m: none); half: the level's H.
    """
    m, deg = wt.shape
    wts = np.zeros((deg, 2, half), np.float32)
    dg = np.zeros((2, half), np.float32)
    idg = np.zeros((2, half), np.float32)
    wflat = wts.reshape(deg, -1)
    dflat = dg.reshape(-1)
    iflat = idg.reshape(-1)
    for i in range(m):
        c = cell[i]
        for d in range(deg):
            wflat[d, c] = wt[i, d]
        dflat[c] = diag[i]
        iflat[c] = inv_diag[i]
    fine = np.empty(fine_aggr_rows.size, np.uint32)
    for k in range(fine_aggr_rows.size):
        r = fine_aggr_rows[k]
        fine[k] = cell[r] if r < m else half - 1
    return wts, dg, idg, fine


# --------------------------------------------------------------------------
# kernels: one colour's cells, range by range (vector loops at fixed offsets)
# --------------------------------------------------------------------------
@nb.njit(cache=True, nogil=True, inline="always")
def _views(a, b, c, xs, k0, k1, o, deg):
    """
    Return views of the cells [k0, k1): of ``a``, ``b`` and ``c``, and of their neighbours in ``xs``.

    The neighbours: :func:`_neighbour_views`.
    """
    s0, s1, s2, s3, s4, s5 = _neighbour_views(xs, k0, k1, o, deg)
    return a[k0:k1], b[k0:k1], c[k0:k1], s0, s1, s2, s3, s4, s5


@nb.njit(cache=True, nogil=True, inline="always")
def _neighbour_views(xs, k0, k1, o, deg):
    """Return the neighbours in ``xs`` of the cells [k0, k1), a view per direction (offsets ``o``; deg 4: 2 unused)."""
    s0 = xs[k0 + o[0]:k1 + o[0]]
    s1 = xs[k0 + o[1]:k1 + o[1]]
    s2 = xs[k0 + o[2]:k1 + o[2]]
    s3 = xs[k0 + o[3]:k1 + o[3]]
    s4 = s0 if deg == 4 else xs[k0 + o[4]:k1 + o[4]]
    s5 = s1 if deg == 4 else xs[k0 + o[5]:k1 + o[5]]
    return s0, s1, s2, s3, s4, s5


@nb.njit(cache=True, nogil=True, inline="always")
def _sweep_range(xt, xs, b, m, k0, k1, o, deg, inv_deg):
    """xt[k] = (b[k] + the other colour's neighbours xs) · inv_deg · m[k] for k in [k0, k1)."""
    t, bb, mm, s0, s1, s2, s3, s4, s5 = _views(xt, b, m, xs, k0, k1, o, deg)
    if deg == 4:
        for i in range(k1 - k0):
            t[i] = (bb[i] + (s0[i] + s1[i] + s2[i] + s3[i])) * inv_deg * mm[i]
    else:
        for i in range(k1 - k0):
            t[i] = (bb[i] + (s0[i] + s1[i] + s2[i] + s3[i] + s4[i] + s5[i])) * inv_deg * mm[i]


@nb.njit(cache=True, nogil=True, inline="always")
def _product_range(pt, ps, qt, m, k0, k1, o, deg, fdeg):
    """qt[k] = (deg · pt[k] − the other colour's neighbours ps) · m[k] for k in [k0, k1)."""
    p, q, mm, s0, s1, s2, s3, s4, s5 = _views(pt, qt, m, ps, k0, k1, o, deg)
    if deg == 4:
        for i in range(k1 - k0):
            q[i] = (fdeg * p[i] - (s0[i] + s1[i] + s2[i] + s3[i])) * mm[i]
    else:
        for i in range(k1 - k0):
            q[i] = (fdeg * p[i] - (s0[i] + s1[i] + s2[i] + s3[i] + s4[i] + s5[i])) * mm[i]


@nb.njit(cache=True, nogil=True, inline="always")
def _residual_range(bt, xt, xs, rt, k0, k1, o, deg, fdeg):
    """rt[k] = bt[k] − deg · xt[k] + the other colour's neighbours xs, for k in [k0, k1)."""
    t, bb, out, s0, s1, s2, s3, s4, s5 = _views(xt, bt, rt, xs, k0, k1, o, deg)
    if deg == 4:
        for i in range(k1 - k0):
            out[i] = bb[i] - fdeg * t[i] + (s0[i] + s1[i] + s2[i] + s3[i])
    else:
        for i in range(k1 - k0):
            out[i] = bb[i] - fdeg * t[i] + (s0[i] + s1[i] + s2[i] + s3[i] + s4[i] + s5[i])


@nb.njit(cache=True, nogil=True, inline="always")
def _dot_range(a, b, k0, k1):
    """
    Return sum a[k] · b[k] over k in [k0, k1), in 8 accumulators (a fixed order: the same bits every run).

    Each product in float64 (two float32 values would otherwise multiply in float32, which
    overflows from about 1e19 each and underflows below about 1e-19).
    """
    x = a[k0:k1]
    y = b[k0:k1]
    n = k1 - k0
    main = n - n % 8
    a0 = a1 = a2 = a3 = a4 = a5 = a6 = a7 = 0.0
    for i in range(0, main, 8):
        a0 += np.float64(x[i]) * np.float64(y[i])
        a1 += np.float64(x[i + 1]) * np.float64(y[i + 1])
        a2 += np.float64(x[i + 2]) * np.float64(y[i + 2])
        a3 += np.float64(x[i + 3]) * np.float64(y[i + 3])
        a4 += np.float64(x[i + 4]) * np.float64(y[i + 4])
        a5 += np.float64(x[i + 5]) * np.float64(y[i + 5])
        a6 += np.float64(x[i + 6]) * np.float64(y[i + 6])
        a7 += np.float64(x[i + 7]) * np.float64(y[i + 7])
    for i in range(main, n):
        a0 += np.float64(x[i]) * np.float64(y[i])
    return ((a0 + a1) + (a2 + a3)) + ((a4 + a5) + (a6 + a7))


@nb.njit(cache=True, nogil=True, inline="always")
def _first_red_range(x, b, m, k0, k1, inv_deg):
    """x[0, k] = b[0, k] · inv_deg · m[0, k] for k in [k0, k1)."""
    t = x[0, k0:k1]
    bb = b[0, k0:k1]
    mm = m[0, k0:k1]
    for i in range(k1 - k0):
        t[i] = bb[i] * inv_deg * mm[i]


@nb.njit(cache=True, nogil=True)
def first_red(x, b, m, ranges, nranges, inv_deg):
    """Run the red half-sweep from x = 0 (its neighbours are black zeros): x[0] = b[0] · inv_deg · m[0]."""
    for r in range(nranges):
        _first_red_range(x, b, m, ranges[0, r, 0], ranges[0, r, 1], inv_deg)


@nb.njit(cache=True, nogil=True)
def half_sweep(x, b, m, ranges, nranges, cut, colour, deg, inv_deg):
    """
    One colour's Gauss–Seidel half-sweep: x[colour] from b and the other colour's x.

    x float32 (2, H): the V-cycle's; b float64 (2, H): its right-hand side; m: the mask;
    cut: the colour's cut edges (their neighbour is taken back out after the vector loop).
    """
    xt = x[colour]
    xs = x[1 - colour]
    for r in range(nranges):
        _sweep_range(xt, xs, b[colour], m[colour], ranges[colour, r, 0], ranges[colour, r, 1],
                     ranges[colour, r, 2:], deg, inv_deg)
    for e in range(cut.shape[0]):
        k = cut[e, 0]
        xt[k] = xt[k] - xs[cut[e, 1]] * inv_deg


@nb.njit(cache=True, nogil=True)
def half_sweep_dot(x, b, m, ranges, nranges, cut, colour, deg, inv_deg):
    """:func:`half_sweep`; return sum b · x over the colour's cells (the new x, in 8 accumulators)."""
    half_sweep(x, b, m, ranges, nranges, cut, colour, deg, inv_deg)
    s = 0.0
    for r in range(nranges):
        s += _dot_range(b[colour], x[colour], ranges[colour, r, 0], ranges[colour, r, 1])
    return s


@nb.njit(cache=True, nogil=True)
def product_dot(p, q, m, ranges, nranges, cut_red, cut_black, deg):
    """Compute q = A p on the cells (float64 (2, H) each); return p · q (8 accumulators per range)."""
    fdeg = float(deg)
    s = 0.0
    for colour in range(2):
        pt = p[colour]
        qt = q[colour]
        ps = p[1 - colour]
        for r in range(nranges):
            _product_range(pt, ps, qt, m[colour], ranges[colour, r, 0], ranges[colour, r, 1], ranges[colour, r, 2:],
                           deg, fdeg)
        cut = cut_red if colour == 0 else cut_black
        for e in range(cut.shape[0]):
            qt[cut[e, 0]] += ps[cut[e, 1]]
        for r in range(nranges):
            s += _dot_range(pt, qt, ranges[colour, r, 0], ranges[colour, r, 1])
    return s


@nb.njit(cache=True, nogil=True, inline="always")
def cut_residuals(res, xs, cut):
    """Take the cut edges back out of the red residuals: res[k] −= xs[j] for each (k, j) of ``cut`` (both routes')."""
    for e in range(cut.shape[0]):
        res[cut[e, 0]] -= xs[cut[e, 1]]


@nb.njit(cache=True, nogil=True)
def restrict_red(b, x, res, gather, at, bc, ranges, nranges, cut_red, deg):
    """
    Restrict the red cells' residual to level 1: bc[at[c]] = the residuals of level-1 node c's red cells.

    b float64 (2, H), x float32 (2, H): the fine right-hand side and iterate (after the
    black half-sweep: the black residuals are 0); res float64 (H,): scratch, 0 outside the
    ranges; bc float32: level 1's right-hand side, node c's at ``at[c]`` (its row on the
    graph, or its cell: :class:`Coarse`), summed in the graph's row order (:class:`Layout`'s
    gather), rounded to float32 at each step as the graph's restriction is.
    """
    fdeg = float(deg)
    for r in range(nranges):
        _residual_range(b[0], x[0], x[1], res, ranges[0, r, 0], ranges[0, r, 1], ranges[0, r, 2:], deg, fdeg)
    cut_residuals(res, x[1], cut_red)
    for c in range(gather.shape[0]):
        bc[at[c]] = _gathered(res, gather, c)


@nb.njit(cache=True, nogil=True, inline="always")
def _gathered(res, gather, c):
    """Return row c's restricted residual: its cells' ``res`` in ``gather[c]``'s order, rounded to float32 each step."""
    t = np.float32(0.0)
    for j in range(gather.shape[1]):
        t = np.float32(np.float64(t) + res[gather[c, j]])
    return t


@nb.njit(cache=True, nogil=True, inline="always")
def _prolong_range(x, xc, aggr, k0, k1, boost):
    """x[0, k] += boost · xc[aggr[k]] for k in [k0, k1)."""
    t = x[0, k0:k1]
    ag = aggr[k0:k1]
    for i in range(k1 - k0):
        t[i] += boost * xc[ag[i]]


@nb.njit(cache=True, nogil=True)
def prolong_red(x, xc, aggr, ranges, nranges, boost):
    """Add ``boost`` times level 1's correction xc to the red cells (x float32 (2, H); others read xc's dummy 0)."""
    for r in range(nranges):
        _prolong_range(x, xc, aggr, ranges[0, r, 0], ranges[0, r, 1], boost)


# --------------------------------------------------------------------------
# level 1 on cells (:class:`Coarse`): weighted rows, float32 throughout
# --------------------------------------------------------------------------
@nb.njit(cache=True, nogil=True, inline="always")
def _weighted_sum(w, colour, k0, k1, xs, o, deg):
    """
    Return the views ``(s, w)`` of one colour's cells [k0, k1): their neighbours in ``xs`` and weights, per direction.

    As :func:`_views`, with deg 4 the last two unused.
    """
    s0, s1, s2, s3, s4, s5 = _neighbour_views(xs, k0, k1, o, deg)
    w0 = w[0, colour, k0:k1]
    w1 = w[1, colour, k0:k1]
    w2 = w[2, colour, k0:k1]
    w3 = w[3, colour, k0:k1]
    w4 = w0 if deg == 4 else w[4, colour, k0:k1]
    w5 = w1 if deg == 4 else w[5, colour, k0:k1]
    return s0, s1, s2, s3, s4, s5, w0, w1, w2, w3, w4, w5


@nb.njit(cache=True, nogil=True, inline="always")
def _weighted_first_red_range(x, b, inv_diag, k0, k1):
    """x[0, k] = b[0, k] · inv_diag[0, k] for k in [k0, k1)."""
    t = x[0, k0:k1]
    bb = b[0, k0:k1]
    ig = inv_diag[0, k0:k1]
    for i in range(k1 - k0):
        t[i] = bb[i] * ig[i]


@nb.njit(cache=True, nogil=True)
def weighted_first_red(x, b, inv_diag, ranges, nranges):
    """Run level 1's red half-sweep from x = 0 (its neighbours are black zeros): x[0] = b[0] · inv_diag[0]."""
    for r in range(nranges):
        _weighted_first_red_range(x, b, inv_diag, ranges[0, r, 0], ranges[0, r, 1])


@nb.njit(cache=True, nogil=True)
def weighted_half_sweep(x, b, w, inv_diag, ranges, nranges, colour, deg):
    """
    One colour's Gauss–Seidel half-sweep on level 1's cells: x[colour] = (b + Σ_d w_d x_d) · inv_diag.

    x, b, inv_diag float32 (2, H), w float32 (deg, 2, H) (:class:`Coarse`); the neighbour sum
    in float32 in the order of the directions, the rest in float64, as the graph's row
    (``multigrid._row``, whose value numba widens to float64), so each cell gets the graph's
    float32 value.
    """
    for r in range(nranges):
        _weighted_sweep_range(x, b, w, inv_diag, colour, ranges[colour, r, 0], ranges[colour, r, 1],
                              ranges[colour, r, 2:], deg)


@nb.njit(cache=True, nogil=True, inline="always")
def _weighted_sweep_range(x, b, w, inv_diag, colour, k0, k1, o, deg):
    """:func:`weighted_half_sweep` over the cells [k0, k1) of ``colour`` (offsets ``o``)."""
    s0, s1, s2, s3, s4, s5, w0, w1, w2, w3, w4, w5 = _weighted_sum(w, colour, k0, k1, x[1 - colour], o, deg)
    t = x[colour, k0:k1]
    bb = b[colour, k0:k1]
    ig = inv_diag[colour, k0:k1]
    if deg == 4:
        for i in range(k1 - k0):
            t[i] = (bb[i] + np.float64(w0[i] * s0[i] + w1[i] * s1[i] + w2[i] * s2[i] + w3[i] * s3[i])) * ig[i]
    else:
        for i in range(k1 - k0):
            t[i] = (bb[i] + np.float64(w0[i] * s0[i] + w1[i] * s1[i] + w2[i] * s2[i] + w3[i] * s3[i]
                                       + w4[i] * s4[i] + w5[i] * s5[i])) * ig[i]


@nb.njit(cache=True, nogil=True)
def weighted_restrict_red(b, x, w, diag, res, gather, bc, ranges, nranges, deg):
    """
    Restrict level 1's red residuals to level 2: bc[c] = the residuals of level-2 row c's red cells.

    b, x, diag float32 (2, H), w float32 (deg, 2, H) (after the black half-sweep: the black
    residuals are 0); res float64 (H,): scratch, 0 outside the ranges; bc float32 (level-2
    rows + 1, the dummy last: not written): summed in level 1's row order (:class:`Coarse`'s
    gather), rounded to float32 at each step, as the graph's restriction adds them.
    """
    for r in range(nranges):
        _weighted_residual_range(b, x, w, diag, res, ranges[0, r, 0], ranges[0, r, 1], ranges[0, r, 2:], deg)
    for c in range(gather.shape[0]):
        bc[c] = _gathered(res, gather, c)


@nb.njit(cache=True, nogil=True, inline="always")
def _weighted_residual_range(b, x, w, diag, res, k0, k1, o, deg):
    """Put level 1's red residuals of the cells [k0, k1) into ``res`` (:func:`weighted_restrict_red`'s first loop)."""
    s0, s1, s2, s3, s4, s5, w0, w1, w2, w3, w4, w5 = _weighted_sum(w, 0, k0, k1, x[1], o, deg)
    out = res[k0:k1]
    bb = b[0, k0:k1]
    t = x[0, k0:k1]
    dg = diag[0, k0:k1]
    if deg == 4:
        for i in range(k1 - k0):
            out[i] = (bb[i] - dg[i] * t[i]) + np.float64(w0[i] * s0[i] + w1[i] * s1[i] + w2[i] * s2[i]
                                                         + w3[i] * s3[i])
    else:
        for i in range(k1 - k0):
            out[i] = (bb[i] - dg[i] * t[i]) + np.float64(w0[i] * s0[i] + w1[i] * s1[i] + w2[i] * s2[i]
                                                         + w3[i] * s3[i] + w4[i] * s4[i] + w5[i] * s5[i])


@nb.njit(cache=True, nogil=True)
def weighted_product_dot(p, q, w, diag, ranges, nranges, deg):
    """
    Compute q = A₁ p on level 1's cells (diag · p − Σ_d w_d p_d); return p · q.

    p, q, diag float32 (2, H), w float32 (deg, 2, H) (:class:`Coarse`; q written over the
    ranges, 0 off the level's rows, where diag and the weights are 0).  The neighbour sum in
    float32 as :func:`weighted_half_sweep` takes it; p · q in 8 accumulators per range.
    """
    s = 0.0
    for colour in range(2):
        ps = p[1 - colour]
        for r in range(nranges):
            k0, k1 = ranges[colour, r, 0], ranges[colour, r, 1]
            s0, s1, s2, s3, s4, s5, w0, w1, w2, w3, w4, w5 = _weighted_sum(w, colour, k0, k1, ps,
                                                                           ranges[colour, r, 2:], deg)
            t = q[colour, k0:k1]
            pp = p[colour, k0:k1]
            dg = diag[colour, k0:k1]
            if deg == 4:
                for i in range(k1 - k0):
                    t[i] = dg[i] * pp[i] - (w0[i] * s0[i] + w1[i] * s1[i] + w2[i] * s2[i] + w3[i] * s3[i])
            else:
                for i in range(k1 - k0):
                    t[i] = dg[i] * pp[i] - (w0[i] * s0[i] + w1[i] * s1[i] + w2[i] * s2[i] + w3[i] * s3[i]
                                            + w4[i] * s4[i] + w5[i] * s5[i])
            s += _dot_range(p[colour], q[colour], k0, k1)
    return s


@nb.njit(cache=True, nogil=True)
def dot_all(a, b):
    """Return sum a · b over two flat arrays of one length, in 8 accumulators (:func:`_dot_range`'s order)."""
    return _dot_range(a, b, 0, a.size)


# --------------------------------------------------------------------------
# the fine level's vector loops on all cores (large boxes): the same values, split in chunks
# --------------------------------------------------------------------------
@nb.njit(cache=True, nogil=True)
def chunks_of(ranges, nranges, chunk):
    """
    Return each colour's loop ranges split into chunks of at most ``chunk`` cells: int64 (2, k, 3) (range, k0, k1).

    Colours with fewer chunks are padded with empty ones (k0 = k1).
    """
    most = 0
    for colour in range(2):
        count = 0
        for r in range(nranges):
            count += (ranges[colour, r, 1] - ranges[colour, r, 0] + chunk - 1) // chunk
        most = max(most, count)
    out = np.zeros((2, most, 3), np.int64)
    for colour in range(2):
        j = 0
        for r in range(nranges):
            k0, k1 = ranges[colour, r, 0], ranges[colour, r, 1]
            while k0 < k1:
                out[colour, j, 0] = r
                out[colour, j, 1] = k0
                out[colour, j, 2] = min(k1, k0 + chunk)
                k0 += chunk
                j += 1
    return out


@nb.njit(cache=True, nogil=True, parallel=True)
def half_sweep_chunks(x, b, m, ranges, chunks, cut, colour, deg, inv_deg):
    """:func:`half_sweep` over ``chunks[colour]`` (:func:`chunks_of`), the chunks in parallel: the same values."""
    xt = x[colour]
    xs = x[1 - colour]
    bt = b[colour]
    mt = m[colour]
    ch = chunks[colour]
    for j in nb.prange(ch.shape[0]):
        r = ch[j, 0]
        _sweep_range(xt, xs, bt, mt, ch[j, 1], ch[j, 2], ranges[colour, r, 2:], deg, inv_deg)
    for e in range(cut.shape[0]):
        k = cut[e, 0]
        xt[k] = xt[k] - xs[cut[e, 1]] * inv_deg


@nb.njit(cache=True, nogil=True, parallel=True)
def _product_chunks(p, q, m, ranges, chunks, colour, deg, fdeg):
    """One colour of q = A p over its chunks, in parallel (cut edges not taken out)."""
    pt = p[colour]
    qt = q[colour]
    ps = p[1 - colour]
    mt = m[colour]
    ch = chunks[colour]
    for j in nb.prange(ch.shape[0]):
        r = ch[j, 0]
        _product_range(pt, ps, qt, mt, ch[j, 1], ch[j, 2], ranges[colour, r, 2:], deg, fdeg)


@nb.njit(cache=True, nogil=True, parallel=True)
def _dot_chunks(a, b, ch):
    """Return sum a · b over the cells of chunks ``ch`` (k, 3): per chunk in parallel, then in the chunks' order."""
    part = np.zeros(ch.shape[0])
    for j in nb.prange(ch.shape[0]):
        part[j] = _dot_range(a, b, ch[j, 1], ch[j, 2])
    s = 0.0
    for j in range(ch.shape[0]):
        s += part[j]
    return s


@nb.njit(cache=True, nogil=True)
def dot_all_chunks(a, b, chunk):
    """Return sum a · b over two flat arrays of one length, in chunks of ``chunk`` (:func:`_dot_chunks`' order)."""
    count = (a.size + chunk - 1) // chunk
    ch = np.zeros((count, 3), np.int64)
    for j in range(count):
        ch[j, 1] = j * chunk
        ch[j, 2] = min(a.size, (j + 1) * chunk)
    return _dot_chunks(a, b, ch)


@nb.njit(cache=True, nogil=True)
def product_dot_chunks(p, q, m, ranges, chunks, cut_red, cut_black, deg):
    """:func:`product_dot` with its loops over chunks in parallel: the same q; p · q summed per chunk, then in order."""
    fdeg = float(deg)
    s = 0.0
    for colour in range(2):
        _product_chunks(p, q, m, ranges, chunks, colour, deg, fdeg)
        qt = q[colour]
        ps = p[1 - colour]
        cut = cut_red if colour == 0 else cut_black
        for e in range(cut.shape[0]):
            qt[cut[e, 0]] += ps[cut[e, 1]]
        s += _dot_chunks(p[colour], qt, chunks[colour])
    return s


@nb.njit(cache=True, nogil=True)
def half_sweep_dot_chunks(x, b, m, ranges, chunks, cut, colour, deg, inv_deg):
    """:func:`half_sweep_dot` over chunks in parallel: the same x; b · x summed per chunk, then in order."""
    half_sweep_chunks(x, b, m, ranges, chunks, cut, colour, deg, inv_deg)
    return _dot_chunks(b[colour], x[colour], chunks[colour])


@nb.njit(cache=True, nogil=True, parallel=True)
def first_red_chunks(x, b, m, chunks, inv_deg):
    """:func:`first_red` over the red chunks, in parallel: the same values."""
    ch = chunks[0]
    for j in nb.prange(ch.shape[0]):
        _first_red_range(x, b, m, ch[j, 1], ch[j, 2], inv_deg)


@nb.njit(cache=True, nogil=True, parallel=True)
def _residual_chunks(b, x, res, ranges, chunks, deg):
    """Put the red cells' residual into ``res`` over the red chunks, in parallel (cut edges not taken out)."""
    fdeg = float(deg)
    ch = chunks[0]
    for j in nb.prange(ch.shape[0]):
        r = ch[j, 0]
        _residual_range(b[0], x[0], x[1], res, ch[j, 1], ch[j, 2], ranges[0, r, 2:], deg, fdeg)


@nb.njit(cache=True, nogil=True, parallel=True)
def _gather_all(res, gather, at, bc):
    """bc[at[c]] = :func:`_gathered` for every level-1 row c, in parallel (each row its own sum, in its order)."""
    for c in nb.prange(gather.shape[0]):
        bc[at[c]] = _gathered(res, gather, c)


@nb.njit(cache=True, nogil=True)
def restrict_red_chunks(b, x, res, gather, at, bc, ranges, chunks, cut_red, deg):
    """:func:`restrict_red` with its loops in parallel: the same values."""
    _residual_chunks(b, x, res, ranges, chunks, deg)
    cut_residuals(res, x[1], cut_red)
    _gather_all(res, gather, at, bc)


@nb.njit(cache=True, nogil=True, parallel=True)
def prolong_red_chunks(x, xc, aggr, chunks, boost):
    """:func:`prolong_red` over the red chunks, in parallel: the same values."""
    ch = chunks[0]
    for j in nb.prange(ch.shape[0]):
        _prolong_range(x, xc, aggr, ch[j, 1], ch[j, 2], boost)


@nb.njit(cache=True, nogil=True, parallel=True)
def weighted_first_red_chunks(x, b, inv_diag, chunks):
    """:func:`weighted_first_red` over the red chunks, in parallel: the same values."""
    ch = chunks[0]
    for j in nb.prange(ch.shape[0]):
        _weighted_first_red_range(x, b, inv_diag, ch[j, 1], ch[j, 2])


@nb.njit(cache=True, nogil=True, parallel=True)
def weighted_half_sweep_chunks(x, b, w, inv_diag, ranges, chunks, colour, deg):
    """:func:`weighted_half_sweep` over the colour's chunks, in parallel: the same values."""
    ch = chunks[colour]
    for j in nb.prange(ch.shape[0]):
        _weighted_sweep_range(x, b, w, inv_diag, colour, ch[j, 1], ch[j, 2], ranges[colour, ch[j, 0], 2:], deg)


@nb.njit(cache=True, nogil=True, parallel=True)
def _weighted_residual_chunks(b, x, w, diag, res, ranges, chunks, deg):
    """Put level 1's red residuals into ``res`` over the red chunks, in parallel."""
    ch = chunks[0]
    for j in nb.prange(ch.shape[0]):
        _weighted_residual_range(b, x, w, diag, res, ch[j, 1], ch[j, 2], ranges[0, ch[j, 0], 2:], deg)


@nb.njit(cache=True, nogil=True)
def weighted_restrict_red_chunks(b, x, w, diag, res, gather, bc, ranges, chunks, deg):
    """:func:`weighted_restrict_red` with its loops in parallel: the same values."""
    _weighted_residual_chunks(b, x, w, diag, res, ranges, chunks, deg)
    _gather_all(res, gather, np.arange(gather.shape[0]), bc)


# --------------------------------------------------------------------------
# one loop or chunks: the fine level's kernels as both cells routes call them
# --------------------------------------------------------------------------
@nb.njit(cache=True, nogil=True, inline="always")
def first_red_in(x, b, m, ranges, nranges, chunks, inv_deg):
    """:func:`first_red`, over ``chunks`` (:func:`chunks_of`) on numba's threads where there are any."""
    if chunks.shape[1] > 0:
        first_red_chunks(x, b, m, chunks, inv_deg)
    else:
        first_red(x, b, m, ranges, nranges, inv_deg)


@nb.njit(cache=True, nogil=True, inline="always")
def half_sweep_in(x, b, m, ranges, nranges, chunks, cut, colour, deg, inv_deg):
    """:func:`half_sweep`, over ``chunks`` on numba's threads where there are any: the same values."""
    if chunks.shape[1] > 0:
        half_sweep_chunks(x, b, m, ranges, chunks, cut, colour, deg, inv_deg)
    else:
        half_sweep(x, b, m, ranges, nranges, cut, colour, deg, inv_deg)


@nb.njit(cache=True, nogil=True, inline="always")
def half_sweep_dot_in(x, b, m, ranges, nranges, chunks, cut, colour, deg, inv_deg):
    """:func:`half_sweep_dot`, over ``chunks`` where there are any (the dot product summed per chunk, then in order)."""
    if chunks.shape[1] > 0:
        return half_sweep_dot_chunks(x, b, m, ranges, chunks, cut, colour, deg, inv_deg)
    return half_sweep_dot(x, b, m, ranges, nranges, cut, colour, deg, inv_deg)


@nb.njit(cache=True, nogil=True, inline="always")
def product_dot_in(p, q, m, ranges, nranges, chunks, cut_red, cut_black, deg):
    """:func:`product_dot`, over ``chunks`` where there are any (the dot product summed per chunk, then in order)."""
    if chunks.shape[1] > 0:
        return product_dot_chunks(p, q, m, ranges, chunks, cut_red, cut_black, deg)
    return product_dot(p, q, m, ranges, nranges, cut_red, cut_black, deg)
