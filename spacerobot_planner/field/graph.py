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


#: Face codes (:func:`grid_codes`), per node and axis: no neighbour below / above (a wall or a
#: cut edge), the neighbour below / above is across the periodic seam.
_LOW_NONE, _LOW_WRAP, _HIGH_NONE, _HIGH_WRAP = 1, 2, 4, 8


@nb.njit(cache=True, nogil=True)
def grid_strides(shape):
    """C-order strides of the grid (in nodes), int64 (ndim,): the one definition (descent uses it too)."""
    ndim = shape.size
    strides = np.ones(ndim, np.int64)
    for a in range(ndim - 2, -1, -1):
        strides[a] = strides[a + 1] * shape[a + 1]
    return strides


@nb.njit(cache=True, nogil=True, inline="always")
def coord_sum(coords, i):
    """
    Return the sum of row ``i`` of ``coords`` (n, ndim) (its parity is the node's colour).

    Spelled out for 2 and 3 dimensions: a per-row loop over a dimension known only at run
    time is not unrolled by LLVM, which made the set-up's row loops 2-3x slower (the branch
    is the same for every row, so a loop around this call is compiled once per dimension).
    The kernels of :mod:`.multigrid` and :mod:`.structured` inline this and the two below:
    numba's cache keys them on their own module's time stamp, so after an edit here delete
    the cached kernels (``field/__pycache__/*.nbi``, ``*.nbc``).
    """
    nd = coords.shape[1]
    if nd == 3:
        return coords[i, 0] + coords[i, 1] + coords[i, 2]
    if nd == 2:
        return coords[i, 0] + coords[i, 1]
    s = 0
    for a in range(nd):
        s += coords[i, a]
    return s


@nb.njit(cache=True, nogil=True, inline="always")
def strided_sum(coords, i, strides, shift):
    """
    Return ``Σ_a (coords[i, a] >> shift) · strides[a]``: a flat index (``shift`` 1: of the node's block).

    coords (n, ndim) non-negative, strides int64 (ndim,).  Spelled out for 2 and 3 dimensions
    (see :func:`coord_sum`).
    """
    nd = coords.shape[1]
    if nd == 3:
        return ((coords[i, 0] >> shift) * strides[0] + (coords[i, 1] >> shift) * strides[1]
                + (coords[i, 2] >> shift) * strides[2])
    if nd == 2:
        return (coords[i, 0] >> shift) * strides[0] + (coords[i, 1] >> shift) * strides[1]
    f = 0
    for a in range(nd):
        f += (coords[i, a] >> shift) * strides[a]
    return f


@nb.njit(cache=True, nogil=True, inline="always")
def named_neighbours(nbr, i, none):
    """Return how many of row ``i``'s neighbours ``nbr`` (n, deg) are below ``none`` (spelled out for deg 4 and 6)."""
    deg = nbr.shape[1]
    if deg == 6:
        return ((nbr[i, 0] < none) + (nbr[i, 1] < none) + (nbr[i, 2] < none) + (nbr[i, 3] < none)
                + (nbr[i, 4] < none) + (nbr[i, 5] < none))
    if deg == 4:
        return (nbr[i, 0] < none) + (nbr[i, 1] < none) + (nbr[i, 2] < none) + (nbr[i, 3] < none)
    k = 0
    for d in range(deg):
        k += nbr[i, d] < none
    return k


@nb.njit(cache=True, nogil=True)
def put_at(out, at, vals):
    """out[at] = vals (at int64 (k,), vals float64 (k,)): NumPy's fancy assignment in one loop."""
    for k in range(at.size):
        out[at[k]] = vals[k]


@nb.njit(cache=True, nogil=True)
def take_at(v, at):
    """Return v[at] (float64 (k,), at int64 (k,)): NumPy's fancy indexing in one loop."""
    out = np.empty(at.size)
    for k in range(at.size):
        out[k] = v[at[k]]
    return out


@nb.njit(cache=True, nogil=True)
def grid_codes(shape, periodic):
    """
    Each grid node's face code per axis: uint8 (prod(shape), ndim), bits ``_LOW_*`` / ``_HIGH_*``.

    shape int64 (ndim,), periodic bool (ndim,).  A node's face neighbours follow from its
    code and the grid's strides (:func:`_grid_nbr`): one byte per axis instead of a table of
    2n indices (a ninth of the memory in 3-D).  Only the two end slabs of each axis have a
    nonzero code: they are written, nothing else is visited.
    """
    ndim = shape.size
    n = 1
    for a in range(ndim):
        n *= shape[a]
    code = np.zeros((n, ndim), np.uint8)
    strides = grid_strides(shape)
    for a in range(ndim):
        low = _LOW_WRAP if periodic[a] else _LOW_NONE
        high = _HIGH_WRAP if periodic[a] else _HIGH_NONE
        s = strides[a]
        top = (shape[a] - 1) * s            # from coordinate 0 to shape[a] - 1 along axis a
        for base in range(0, n, s * shape[a]):
            for f in range(base, base + s):
                code[f, a] = low            # every axis has >= 2 nodes: the slabs are distinct
                code[f + top, a] = high
    return code


@nb.njit(cache=True, nogil=True, inline="always")
def _grid_nbr(code, f, d, shape, strides):
    """Flat index of grid node ``f``'s face neighbour ``d`` (2a + (0|1): −/+ along axis a), -1 for none."""
    a = d >> 1
    c = code[f, a]
    if d & 1 == 0:
        if c & _LOW_NONE:
            return -1
        if c & _LOW_WRAP:
            return f + (shape[a] - 1) * strides[a]
        return f - strides[a]
    if c & _HIGH_NONE:
        return -1
    if c & _HIGH_WRAP:
        return f - (shape[a] - 1) * strides[a]
    return f + strides[a]


def grid_neighbours(shape, periodic, cut_edges=None):
    """
    Flat index of each grid node's 2n face neighbours, -1 beyond a wall.

    shape int64 (ndim,), periodic bool (ndim,).  Returns int64 (prod(shape), 2 ndim):
    column 2a + (0|1) = the (-|+) neighbour along axis a, wrapping on periodic axes.
    ``cut_edges``: int (k, 2) flat node pairs of face neighbours with a wall between them
    (each end reads -1 there), or None.
    """
    shape = np.asarray(shape, np.int64)
    out = np.empty((int(np.prod(shape)), 2 * shape.size), np.int64)
    _neighbours_of(face_codes(shape, periodic, cut_edges), shape, out)
    return out


@nb.njit(cache=True, nogil=True)
def _neighbours_of(code, shape, out):
    """Fill ``out`` (prod(shape), 2 ndim) with each node's face neighbours by the face codes ``code`` (-1: none)."""
    strides = grid_strides(shape)
    for f in range(out.shape[0]):
        for d in range(out.shape[1]):
            out[f, d] = _grid_nbr(code, f, d, shape, strides)
    return out


@nb.njit(cache=True, nogil=True)
def _bfs(occ_flat, code, shape, goal_flat):
    """
    BFS through free nodes from the goal nodes.

    ``(dist, order)``, dist int64 per flat node (-1 = not reached), order = reached flat nodes in
    BFS order.  code: the grid's face codes (:func:`grid_codes`, cut edges marked).
    """
    n = occ_flat.size
    deg = 2 * shape.size
    strides = grid_strides(shape)
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
            g = _grid_nbr(code, f, a, shape, strides)
            if g < 0 or occ_flat[g] or dist[g] >= 0:
                continue
            dist[g] = dist[f] + 1
            order[tail] = g
            tail += 1
    return dist, order[:tail]


#: :func:`_node_tables`' marks in ``pos`` (above any position: a graph has < 2**32 - 3 nodes).
_UNSEEN = np.uint32(0xFFFFFFFF)
_BLOCKED = np.uint32(0xFFFFFFFE)
_REACHED = np.uint32(0xFFFFFFFD)


@nb.njit(cache=True, nogil=True, inline="always")
def _row_lead(r, shape):
    """Return the coordinates of grid row ``r`` (along the last axis) on the leading axes (the last one 0)."""
    ndim = shape.size
    lead = np.zeros(ndim, np.int64)
    for a in range(ndim - 2, -1, -1):
        lead[a] = r % shape[a]
        r //= shape[a]
    return lead


@nb.njit(cache=True, nogil=True, inline="always")
def _count_rows(pos, shape, r0, r1):
    """Return ``(red, all)``: how many nodes marked ``_REACHED`` in ``pos`` on the grid's rows [r0, r1) are red, all."""
    ndim = shape.size
    last = shape[ndim - 1]
    lead = _row_lead(r0, shape)
    lead_shape = shape.copy()
    lead_shape[ndim - 1] = 1                 # the odometer turns the leading axes only
    n_red = 0
    n = 0
    for r in range(r0, r1):
        par = 0                              # the row's coordinate sum
        for a in range(ndim - 1):
            par += lead[a]
        f = r * last
        for j in range(last):
            hit = pos[f + j] == _REACHED
            n += hit
            n_red += hit and (par + j) & 1 == 0
        _next_coord(lead, lead_shape)
    return n_red, n


@nb.njit(cache=True, nogil=True, inline="always")
def _place_rows(pos, order, coords, shape, r0, r1, k_red, k_black):
    """
    Give the reached nodes on the grid's rows [r0, r1) their positions, from ``k_red`` (red) and ``k_black`` (black).

    In grid order: ``pos[f]`` the node's position, ``order`` and ``coords`` its entries (no
    divisions: a row's coordinate sum is counted once per row).
    """
    ndim = shape.size
    last = shape[ndim - 1]
    lead = _row_lead(r0, shape)
    lead_shape = shape.copy()
    lead_shape[ndim - 1] = 1
    for r in range(r0, r1):
        par = 0
        for a in range(ndim - 1):
            par += lead[a]
        f = r * last
        for j in range(last):
            if pos[f] == _REACHED:
                black = (par + j) & 1            # coordinates are >= 0: the parity, without a branch
                k = k_black if black else k_red
                k_red += 1 - black
                k_black += black
                pos[f] = k
                order[k] = f
                for a in range(ndim - 1):
                    coords[k, a] = lead[a]
                coords[k, ndim - 1] = j
            f += 1
        _next_coord(lead, lead_shape)


@nb.njit(cache=True, nogil=True, parallel=True)
def _place_chunks(pos, order, coords, shape, n_goal):
    """
    :func:`_count_rows` and :func:`_place_rows` over every grid row, in chunks of about 8 192 nodes on numba's threads.

    Each chunk's red and black nodes are counted, then the chunks' first positions summed in
    order (the goal nodes first, then every red node, then the black ones), then each chunk
    placed: the positions of one thread's pass.
    """
    length = shape[shape.size - 1]
    rows = (pos.size - 1) // length
    per = max(1, 8192 // length)
    chunks = (rows + per - 1) // per
    red = np.empty(chunks, np.int64)
    reached = np.empty(chunks, np.int64)
    for j in nb.prange(chunks):
        red[j], reached[j] = _count_rows(pos, shape, j * per, min(rows, (j + 1) * per))
    k_red = np.empty(chunks, np.int64)
    k_black = np.empty(chunks, np.int64)
    n_red = 0
    for j in range(chunks):
        n_red += red[j]
    kr, kb = n_goal, n_goal + n_red
    for j in range(chunks):
        k_red[j] = kr
        k_black[j] = kb
        kr += red[j]
        kb += reached[j] - red[j]
    for j in nb.prange(chunks):
        _place_rows(pos, order, coords, shape, j * per, min(rows, (j + 1) * per), k_red[j], k_black[j])


@nb.njit(cache=True, nogil=True)
def _node_tables(occ_flat, code, shape, goal_flat, cuts):
    """
    Return ``(order, coords, nbr)`` of the goal-connected free nodes, in one kernel.

    occ_flat bool (prod(shape),), code: the grid's face codes (:func:`grid_codes`, cut edges
    marked; ``cuts``: whether any is), goal_flat int64 (k,) distinct free flat nodes.  order int64 (N,): the goal nodes,
    then the reached nodes with an even coordinate sum ("red"), then the odd ones, each in
    grid order; coords int32 (N, ndim); nbr uint32 (N, 2 ndim): position in ``order`` of
    each node's face neighbours, N for walls, obstacles and nodes not reached.

    One grid-sized table (``pos``, uint32: obstacles marked as it is filled) and four passes: the
    goal's components by runs (marks: :func:`_reach`), the grid in C order by rows of the last
    axis twice (the red nodes counted, then positions and coordinates: :func:`_count_rows`,
    :func:`_place_rows`), the neighbour table.  The last three on numba's threads from
    :data:`PARALLEL_MIN_NODES` nodes on (in chunks of rows: the same tables).
    """
    n_grid = occ_flat.size
    ndim = shape.size
    deg = 2 * ndim
    strides = grid_strides(shape)
    pos = np.empty(n_grid + 1, np.uint32)   # the last entry: what a wall reads (:func:`_uncut_rows`)
    for f in range(n_grid):
        pos[f] = _BLOCKED if occ_flat[f] else _UNSEEN
    pos[n_grid] = _BLOCKED
    order = np.empty(n_grid, np.int64)       # the goal nodes, then the order
    n_goal = 0
    for g in goal_flat:
        if pos[g] == _UNSEEN:
            pos[g] = n_goal
            order[n_goal] = g
            n_goal += 1
    n = n_goal + _reach(pos, occ_flat, code, shape, order[:n_goal], cuts)
    order = order[:n]
    coords = np.empty((n, ndim), np.int32)   # int32: half the bytes to write, and for the multigrid to read
    for k in range(n_goal):
        for a in range(ndim):
            coords[k, a] = (order[k] // strides[a]) % shape[a]
    rows = n_grid // shape[ndim - 1]
    if n >= PARALLEL_MIN_NODES:
        _place_chunks(pos, order, coords, shape, n_goal)
    else:
        n_red = _count_rows(pos, shape, 0, rows)[0]
        _place_rows(pos, order, coords, shape, 0, rows, n_goal, n_goal + n_red)
    nbr = np.empty((n, deg), np.uint32)     # unsigned: no negative-index wrap-around in the kernels
    if cuts and n >= PARALLEL_MIN_NODES:
        _neighbour_rows_chunks(nbr, order, pos, code, shape, strides)
    elif cuts:
        _neighbour_rows(nbr, order, pos, code, shape, strides, 0, n)
    elif n >= PARALLEL_MIN_NODES:
        _uncut_rows_chunks(nbr, pos, code, shape, strides)
    else:
        _uncut_rows(nbr, pos, code, shape, strides, 0, rows)
    return order, coords, nbr


@nb.njit(cache=True, nogil=True, inline="always")
def _root(parent, r):
    """Return run ``r``'s root in the union-find forest ``parent`` (int64), halving the path on the way."""
    while parent[r] != r:
        parent[r] = parent[parent[r]]
        r = parent[r]
    return r


@nb.njit(cache=True, nogil=True, inline="always")
def _join(parent, r, s):
    """Put runs ``r`` and ``s`` in one set (the lower root the root)."""
    r = _root(parent, r)
    s = _root(parent, s)
    if r < s:
        parent[s] = r
    elif s < r:
        parent[r] = s


@nb.njit(cache=True, nogil=True)
def _reach(pos, occ_flat, code, shape, goals, cuts):
    """
    Mark ``_REACHED`` in ``pos`` every free node joined to the goal nodes; return how many (the goals not counted).

    pos uint32 (prod(shape),): ``_UNSEEN`` at the free nodes, ``_BLOCKED`` at obstacles, the goal
    nodes (``goals`` int64 (k,), flat) marked with their positions (below k); occ_flat bool
    (prod(shape),); code uint8 (prod(shape), ndim): the grid's face codes (:func:`grid_codes`, cut
    edges marked); ``cuts``: whether any edge is cut (False: only the end slabs have codes).

    The components of the free nodes by runs: a run is a stretch of a row (the last axis, stride
    1) joined node to node.  The runs are found in one pass over the grid, then joined in a
    union-find forest: a run that wraps across a periodic last axis to the row's first one, and
    each pair of overlapping runs of two neighbouring rows (along every other axis, across a
    periodic seam too) that an uncut edge joins.  Without cuts one edge joins the whole overlap
    (the rows' codes are the same along it); with cuts the overlap's nodes are read until one of
    them is joined.  The goals' runs' sets are reached: their runs' nodes are marked.  About one
    read of the occupancy and one of ``pos`` a node, and a few operations a run; the scanline
    flood it replaces read each node's neighbouring rows and codes (9 ns a node at 36³).
    """
    ndim = shape.size
    last = ndim - 1
    length = shape[last]                    # a row's nodes
    n_grid = occ_flat.size
    rows = n_grid // length
    cf = code.reshape(code.size)            # node f's code along axis a at f · ndim + a
    lo = np.empty(n_grid, np.int64)         # each run's first node and one past its last (flat)
    hi = np.empty(n_grid, np.int64)
    first = np.empty(rows + 1, np.int64)    # row r's runs: first[r] .. first[r + 1]
    runs = 0
    for r in range(rows):
        first[r] = runs
        f = r * length
        end = f + length
        while f < end:
            if occ_flat[f]:
                f += 1
                continue
            lo[runs] = f
            while f + 1 < end and not occ_flat[f + 1] and (not cuts or not cf[f * ndim + last] & _HIGH_NONE):
                f += 1
            f += 1
            hi[runs] = f
            runs += 1
    first[rows] = runs
    parent = np.arange(runs)
    for r in range(rows):                   # a periodic last axis: the row's last run and its first
        a0, a1 = first[r], first[r + 1]
        if a1 - a0 > 1 and lo[a0] == r * length and hi[a1 - 1] == (r + 1) * length:
            c = cf[(hi[a1 - 1] - 1) * ndim + last]
            if c & _HIGH_WRAP and not c & _HIGH_NONE:
                _join(parent, a0, a1 - 1)
    strides = grid_strides(shape)
    for a in range(last):                   # every other axis: each row and the next one along it
        step = strides[a] // length         # in rows
        n_a = shape[a]
        for r in range(rows):
            a0, a1 = first[r], first[r + 1]
            if a0 == a1:
                continue
            c = cf[r * length * ndim + a]   # the row's code along a (cuts aside: the same along the row)
            if c & _HIGH_NONE and not cuts:
                continue                    # a wall above the row
            if (r // step) % n_a == n_a - 1:
                if not c & _HIGH_WRAP:
                    continue
                q = r - (n_a - 1) * step    # across the seam
            else:
                q = r + step
            b0, b1 = first[q], first[q + 1]
            shift = (q - r) * length        # from a node of row r to its neighbour in row q
            i, j = a0, b0
            while i < a1 and j < b1:        # the overlapping runs, in row order
                s = max(lo[i], lo[j] - shift)
                e = min(hi[i], hi[j] - shift)
                if s < e:
                    joined = True
                    if cuts:                # an uncut edge in the overlap
                        joined = False
                        for g in range(s, e):
                            if not cf[g * ndim + a] & _HIGH_NONE:
                                joined = True
                                break
                    if joined:
                        _join(parent, i, j)
                if hi[i] <= hi[j] - shift:
                    i += 1
                else:
                    j += 1
    reached_set = np.zeros(runs, np.bool_)
    for g in goals:                         # the goals' runs (a binary search in the row's runs)
        r = g // length
        i0, i1 = first[r], first[r + 1] - 1
        while i0 < i1:
            mid = (i0 + i1 + 1) // 2
            if lo[mid] <= g:
                i0 = mid
            else:
                i1 = mid - 1
        reached_set[_root(parent, i0)] = True
    reached = -goals.size                   # every goal node is in a reached run
    for i in range(runs):
        if not reached_set[_root(parent, i)]:
            continue
        for f in range(lo[i], hi[i]):
            v = pos[f]
            pos[f] = _REACHED if v == _UNSEEN else v        # (a goal node keeps its position)
        reached += hi[i] - lo[i]
    return reached


#: :func:`_node_tables` fills its neighbour table on all of numba's threads from this many nodes on
#: (each node's entries on their own: the same table; numba reads the value when it compiles the kernel).
#: The paper 3-DOF scene's table, one thread against two (the kernel alone, median of 7): 72³ 1.8 / 1.2 ms,
#: 120³ 9.3 / 5.2 ms.
PARALLEL_MIN_NODES = 100_000


@nb.njit(cache=True, nogil=True, inline="always")
def _neighbour_rows(nbr, order, pos, code, shape, strides, k0, k1):
    """Fill rows [k0, k1) of the neighbour table: each node's face neighbours' positions, N for none."""
    none = np.uint32(nbr.shape[0])
    for k in range(k0, k1):
        f = order[k]
        for d in range(nbr.shape[1]):
            g = _grid_nbr(code, f, d, shape, strides)
            nbr[k, d] = none if g < 0 else min(pos[g], none)     # the marks are above every position


@nb.njit(cache=True, nogil=True, parallel=True)
def _neighbour_rows_chunks(nbr, order, pos, code, shape, strides):
    """:func:`_neighbour_rows` for every node, in chunks of 8 192 on numba's threads."""
    n = nbr.shape[0]
    for j in nb.prange((n + 8191) // 8192):
        _neighbour_rows(nbr, order, pos, code, shape, strides, j * 8192, min(n, (j + 1) * 8192))


@nb.njit(cache=True, nogil=True, inline="always")
def _uncut_rows(nbr, pos, code, shape, strides, r0, r1):
    """
    Fill the neighbour table's rows of the nodes on the grid's rows [r0, r1) (along the last axis), no edge cut.

    pos uint32 (prod(shape) + 1,): each node's position in the graph, a mark above every position
    elsewhere, the last entry one too (what a wall reads).  With no edge cut, every node of a grid
    row has its row's codes along the other axes, so each row's offsets are decoded once, and along
    the row only its two ends read theirs: the table :func:`_neighbour_rows` fills, at 0.65x its
    time (36³: 0.19 against 0.29 ms, medians of 40).
    """
    none = np.uint32(nbr.shape[0])
    ndim = shape.size
    last = ndim - 1
    length = shape[last]
    cf = code.reshape(code.size)
    wall = pos.size - 1
    off = np.empty(2 * last, np.int64)      # the row's neighbour offsets along the other axes ...
    walled = np.empty(2 * last, np.bool_)   # ... and where a wall stands instead
    for r in range(r0, r1):
        f0 = r * length
        for a in range(last):
            c = cf[f0 * ndim + a]
            span = (shape[a] - 1) * strides[a]
            off[2 * a] = span if c & _LOW_WRAP else -strides[a]
            walled[2 * a] = c & _LOW_NONE != 0
            off[2 * a + 1] = -span if c & _HIGH_WRAP else strides[a]
            walled[2 * a + 1] = c & _HIGH_NONE != 0
        below0 = wall if cf[f0 * ndim + last] & _LOW_NONE else f0 + length - 1         # the row's ends
        above1 = wall if cf[(f0 + length - 1) * ndim + last] & _HIGH_NONE else f0
        for j in range(length):
            f = f0 + j
            k = pos[f]
            if k >= none:
                continue
            for d in range(2 * last):
                nbr[k, d] = min(pos[wall if walled[d] else f + off[d]], none)
            nbr[k, 2 * last] = min(pos[f - 1 if j > 0 else below0], none)
            nbr[k, 2 * last + 1] = min(pos[f + 1 if j < length - 1 else above1], none)


@nb.njit(cache=True, nogil=True, parallel=True)
def _uncut_rows_chunks(nbr, pos, code, shape, strides):
    """:func:`_uncut_rows` for every grid row, in chunks of about 8 192 nodes on numba's threads."""
    length = shape[shape.size - 1]
    rows = (pos.size - 1) // length
    per = max(1, 8192 // length)
    for j in nb.prange((rows + per - 1) // per):
        _uncut_rows(nbr, pos, code, shape, strides, j * per, min(rows, (j + 1) * per))


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
    # distinct, in index order (a row-major flat index sorts as the index tuples do; what
    # np.unique(goals, axis=0) returns, at a third of its cost)
    flat = np.unique(np.ravel_multi_index(tuple(goals.T), occ.shape))
    return np.ascontiguousarray(occ), per, np.stack(np.unravel_index(flat, occ.shape), axis=1).astype(np.int64)


@dataclass(frozen=True, eq=False)
class NodeGraph:
    """
    The goal-connected free nodes of a validated problem.

    order: int64 (N,) flat grid index of each graph node: the goal nodes first (``n_goal``
        of them), then the others with an even coordinate sum ("red"), then the odd ones
        ("black"), each in grid order (memory locality; the multigrid smoother's order).
    nbr: uint32 (N, 2 ndim) neighbour positions in ``order``; N = none (see module doc).
    coords: int32 (N, ndim) grid coordinates.
    shape, periodic: the grid's.
    """

    order: np.ndarray
    nbr: np.ndarray
    coords: np.ndarray
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
def _cut_edges(code, shape, edges):
    """
    Remove the grid edges ``edges`` int64 (k, 2) (flat node pairs, face neighbours) from the face codes.

    Each end then sees a wall there (every direction in which it reaches the other: both on a
    periodic axis of two nodes).
    """
    deg = 2 * shape.size
    strides = grid_strides(shape)
    for e in range(edges.shape[0]):
        p, q = edges[e, 0], edges[e, 1]
        for d in range(deg):         # test both ends before either is cut
            p_to_q = _grid_nbr(code, p, d, shape, strides) == q
            q_to_p = _grid_nbr(code, q, d, shape, strides) == p
            if p_to_q:
                code[p, d >> 1] |= _LOW_NONE if d & 1 == 0 else _HIGH_NONE
            if q_to_p:
                code[q, d >> 1] |= _LOW_NONE if d & 1 == 0 else _HIGH_NONE


def face_codes(shape, periodic, cut_edges=None, token=None) -> np.ndarray:
    """
    Return the grid's face codes (:func:`grid_codes`) with the grid edges ``cut_edges`` walled off.

    shape int64 (ndim,); periodic: one bool per axis; cut_edges: int (k, 2) flat node pairs of
    face neighbours (a wall between the two), or None.  ``token``: a termination token checked
    after the codes (raises ``termination.Cancelled``), or None.
    """
    code = grid_codes(shape, np.array(periodic, np.bool_))
    if token is not None:
        token.check()
    if cut_edges is not None and len(cut_edges):
        # a writable copy: the kernel's one signature (a read-only array, repair.CutEdges', would compile another)
        _cut_edges(code, shape, np.array(cut_edges, dtype=np.int64).reshape(-1, 2))
    return code


def bfs(occ, per, goals, cut_edges=None, token=None):
    """
    Return (dist, BFS order, face codes) of a validated problem.

    (dist int64 grid-flat, BFS order, the grid's face codes uint8 (prod(shape), ndim), see
    :func:`grid_codes`) of a validated problem, without the grid edges ``cut_edges``
    (int (k, 2) flat node pairs) if given.  ``token``: a termination token checked between
    the passes (raises ``termination.Cancelled``).
    """
    shape = np.array(occ.shape, np.int64)
    code = face_codes(shape, per, cut_edges, token)
    goal_flat = np.ravel_multi_index(tuple(goals.T), occ.shape).astype(np.int64)
    dist, order = _bfs(occ.ravel(), code, shape, goal_flat)
    return dist, order, code


def node_graph(occ, per, goals, cut_edges=None, token=None) -> NodeGraph:
    """
    Return the :class:`NodeGraph` of a validated problem.

    The :class:`NodeGraph` of a validated problem (``validate_problem``), without the grid edges
    ``cut_edges`` (int (k, 2) flat node pairs: a wall between the two).  ``token``: a
    termination token checked between the passes (raises ``termination.Cancelled``).
    """
    token = Termination.of(token)
    shape = np.array(occ.shape, np.int64)
    code = face_codes(shape, per, cut_edges, token)
    goal_flat = np.ravel_multi_index(tuple(goals.T), occ.shape).astype(np.int64)
    order, coords, nbr = _node_tables(occ.ravel(), code, shape, goal_flat,
                                      cut_edges is not None and len(cut_edges) > 0)
    token.check()
    return NodeGraph(order, nbr, coords, len(goals), tuple(occ.shape), tuple(per))


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
