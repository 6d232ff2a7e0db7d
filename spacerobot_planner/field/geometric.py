"""
Geometric multigrid for a 2-D band: bilinear prolongation and Galerkin coarse levels under the fine level's cells.

The aggregation hierarchy of :mod:`.multigrid` prolongs piecewise constant and scales its
correction up (its ``boost``): on the paper's 2-D first band CG takes 17 iterations for
the ten decades of its stop.  Here the coarse levels are the fine grid's halved, each node
of level l + 1 the fine node at twice its index (less one), and the prolongation is
bilinear: a fine node between two coarse ones takes half of each, one amid four a
quarter of each.  The coarse operators are Galerkin's (Pᵀ A P), so obstacles, walls,
windows and cut edges need nothing of their own: they are in A.  Each level below the fine
one is a 9-point stencil on its box of cells, smoothed by damped Jacobi (vector loops,
float32, its weight :data:`JACOBI_WEIGHT`, less on a row whose absolute sum asks it:
:func:`_levels`); the coarsest (at most :data:`COARSEST_UNKNOWNS` unknowns) is solved directly.
The fine level is :mod:`.structured`'s (its cells, red and black apart, and its kernels: the
same Gauss–Seidel half-sweeps, product and residual).
One V-cycle: a red and a black half-sweep, the red residuals restricted (the black ones are
0), the coarse cycle, its correction added to the red cells (the black ones are set, not
read, by the next half-sweep), a black and a red half-sweep: a symmetric preconditioner for
CG, with the same stop rule, deadline and termination flag as :func:`.multigrid._spcg`.
The red cells of a fine row are all on level-1 nodes (an odd row) or all amid four (an even
row), and consecutive in their half of the cells, so the restriction and the prolongation
are vector loops along the rows (:func:`_restrict_fine`, :func:`_prolong_fine`; through
index tables they took 18.1 and 14.4 of a V-cycle's 120.3 us at 181², medians; 8.9, 7.5 and 101.0 after).

Measured on the captured first bands of the paper's 2-DOF scene and of random ones (`bench
scenes`' family), against the aggregation route on cells in the same process (median / max of
21 solves, 5 at 360² and 720²): 9 iterations against 15-17, 0.73x the time at 181² (2.18 / 2.65
against 3.00 / 3.39 ms), 0.62x at 360² (10.09 / 10.80 against 16.26 / 17.17 ms), 0.96x at 720²
(63.35 / 64.49 against 65.97 / 68.01 ms, where the other route runs on both cores; since then this
route's loops run on numba's threads too on a large box, :func:`_gpcg`'s ``chunk``: 720² 71.4 -> 57.0
ms on 2 cores, median of 5 alternating, max 72.1 -> 57.5; and the transfers along the rows took the 181² band's solve
from 2.44 / 2.55 / 3.17 to 2.11 / 2.21 / 2.80 ms, median / p90 / max of 41).  Where it
applies: :func:`applies` (2-D, the cells route's box rule, no edge across a periodic seam) and
:func:`levels`; :func:`.multigrid.solve` takes this route there.

Coordinates.  A fine row's padded coordinates are ``q = c − lo + 1`` (``lo``: the unknowns'
lowest coordinates), axis 1 shifted by one more where ``lo0 + lo1`` is odd, so that a red row
(even coordinate sum) has ``q0 + q1`` even.  The parents of a padded index q: ``(q + 1) / 2``
(odd q, weight 1), ``q / 2`` and ``q / 2 + 1`` (even q, ½ each).  Level l's box has
``m = (m_above − 2) // 2 + 3`` cells per axis, its border (index 0 and m − 1) never an unknown.
Stencil slot k of a node is its neighbour at ``(k // 3 − 1, k % 3 − 1)``.

Editing :mod:`.structured`'s kernels or :mod:`.krylov`'s CG steps (``_descend``, ``_turn``):
numba's cache keys this module's kernels, which link them in, on this file's time stamp, so
delete them (``field/__pycache__/geometric*.nbi``, ``*.nbc``) or touch this file.
"""
from __future__ import annotations

import numba as nb
import numpy as np

from . import structured
from .krylov import _cholesky, _descend_in, _now, _subtract_max, _turn_in

#: The levels are halved until one has at most this many unknowns (a dense factor solves it) ...
COARSEST_UNKNOWNS = 64
#: ... or its box is 4 cells across (no halving shrinks it): a long thin band's coarsest level then holds
#: more, and above this many the band takes the aggregation levels instead (:func:`levels` says None).
COARSEST_MOST = 128
#: Damped Jacobi's weight on the coarse levels (0.7: one iteration more on 3 of 7 sampled bands) ...
JACOBI_WEIGHT = 0.8
#: ... or less, row by row: a row's step is at most this over its absolute sum, so that 2 M − S is
#: diagonally dominant and every sweep damps every mode (Galerkin's levels have positive entries beside
#: obstacles and cut edges: Gershgorin bounds on D⁻¹ S up to 2.7 were met, where 0.8 would amplify one;
#: a level's whole weight lowered to its worst row's doubled the iterations on the paper's 2-D band).
JACOBI_MOST = 1.9
#: Jacobi sweeps on each coarse level before the coarser correction (the first from 0) and after it.
PRE_SWEEPS = 2
POST_SWEEPS = 2


class Levels:
    """The coarse levels of one problem (:func:`levels`): the arrays :func:`_gpcg` reads."""

    def __init__(self, tr, st, inv, off, shp, idx, low):
        """Hold :func:`_links`' and :func:`_levels`' arrays."""
        self.tr, self.st, self.inv, self.off, self.shp, self.idx, self.low = tr, st, inv, off, shp, idx, low


def applies(ndim: int, layout) -> bool:
    """
    Return whether a problem may take this route (the rule, one place, with :func:`levels`).

    A 2-D grid whose fine level lies on cells (``layout``: :func:`.structured.laid_out`'s, or
    None: the box breaks the cells' rule, or, laid out ``seamless``, an edge crosses a periodic
    seam) in one loop range (no edge across the seam).
    The rule's second half is the caller's to check: :func:`levels` is not None (the coarsest
    level holds at most :data:`COARSEST_MOST` unknowns).
    """
    return int(ndim) == 2 and layout is not None and layout.nranges == 1


def levels(nb0, coords, red0: int, layout) -> Levels:
    """
    Return the coarse levels of the fine rows ``nb0`` (uint32 (n, 4), red rows first), ``coords`` (n, 2).

    ``layout``: their cells (:func:`.structured.laid_out`, one loop range).  None where the
    coarsest level would hold more than :data:`COARSEST_MOST` unknowns (a long thin band: the
    rule's second half, see :func:`applies`).
    """
    lo0, lo1 = (int(v) for v in layout.lo)     # the unknowns' box (no seam: their lowest and highest coordinates)
    s1 = (lo0 + lo1) & 1
    m0 = int(layout.hi[0]) - lo0 + 3
    m1 = int(layout.hi[1]) - lo1 + 3 + s1
    ok, st, inv, off, shp, idx, low = _levels(nb0, coords, lo0, lo1, s1, m0, m1, COARSEST_MOST)
    if not ok:
        return None
    tr = np.array([layout.base, layout.strides[0], layout.padded[0], layout.padded[1], s1, shp[0, 0], shp[0, 1]],
                  np.int64)
    return Levels(tr, st, inv, off, shp, idx, low)


def pcg(layout, lv: Levels, rhs, u, tol: float, max_iter: int, deadline: float, stop, sweeps: int, chunk: int = 0):
    """
    Run CG preconditioned by this V-cycle on the cells: rhs, u float64 (2, H); return (iterations, max residual).

    u is updated in place; ``deadline`` (``time.perf_counter()`` s, 0: none) and the
    termination flag ``stop`` (int64 (1,)) as :func:`.multigrid.solve`'s; ``sweeps``: the fine
    level's red-black sweep pairs before and after the coarse correction; ``chunk`` > 0: the loops
    on numba's threads (:func:`_gpcg`).
    """
    return _gpcg(layout.mask, layout.ranges, layout.nranges, layout.cut_red, layout.cut_black, lv.tr, lv.st,
                 lv.inv, lv.off, lv.shp, lv.idx, lv.low, rhs, u, float(tol), int(max_iter), float(deadline), stop,
                 int(sweeps), int(chunk))


# --------------------------------------------------------------------------
# set-up
# --------------------------------------------------------------------------
@nb.njit(cache=True, nogil=True)
def _fine_edges(nb0, coords, lo0, lo1, s1, m0, m1):
    """
    Return the fine box's ``(e0, e1, deficit)``, float64 (m0 + 1, m1 + 1).

    e0, e1: 1 where a row's edge up axis 0 (axis 1) is in the graph; deficit: 4 less the
    row's edges (its Dirichlet part: walls, obstacles, known nodes and cut edges).
    """
    n = nb0.shape[0]
    e0 = np.zeros((m0 + 1, m1 + 1))
    e1 = np.zeros((m0 + 1, m1 + 1))
    dd = np.zeros((m0 + 1, m1 + 1))
    for i in range(n):
        p0 = coords[i, 0] - lo0 + 1
        p1 = coords[i, 1] - lo1 + 1 + s1
        links = 0
        for d in range(4):
            if nb0[i, d] < n:
                links += 1
        dd[p0, p1] = 4.0 - links
        if nb0[i, 1] < n:
            e0[p0, p1] = 1.0
        if nb0[i, 3] < n:
            e1[p0, p1] = 1.0
    return e0, e1, dd


@nb.njit(cache=True, nogil=True, inline="always")
def _element(centre_a, centre_b, out_a, out_b, ca, cb, w):
    """
    Add ``w (ca + cb)`` times edge elements: to both ends' centres, and taken from their entries to each other.

    Views along a row of level-1 edges (K, K + 1): ``centre_a`` / ``out_a`` at K, ``centre_b`` /
    ``out_b`` at K + 1.
    """
    for k in range(ca.size):
        c = w * (ca[k] + cb[k])
        centre_a[k] += c
        centre_b[k] += c
        out_a[k] -= c
        out_b[k] -= c


@nb.njit(cache=True, nogil=True, inline="always")
def _row_element(out, i0, nk, ca, cb, w):
    """Add ``w (ca + cb)`` times the edge element between level-1 columns K and K + 1 of row i0 (K = 1 .. nk)."""
    _element(out[4, i0, 1:1 + nk], out[4, i0, 2:2 + nk], out[5, i0, 1:1 + nk], out[3, i0, 2:2 + nk], ca, cb, w)


@nb.njit(cache=True, nogil=True, inline="always")
def _cross(p0, m0, m1, p1, p2, m2, m3, p3, ca, cb):
    """
    Add ``(ca + cb) / 16`` to the p views and take it from the m views (one fine edge pair's cross terms).

    An edge pair between level-1 nodes K and K + 1 in a fine row (column) amid two level-1 rows
    (columns): the entries between the two rows' (columns') nodes, ± as the element's.
    """
    for k in range(ca.size):
        c = 0.0625 * (ca[k] + cb[k])
        p0[k] += c
        m0[k] -= c
        m1[k] -= c
        p1[k] += c
        p2[k] += c
        m2[k] -= c
        m3[k] -= c
        p3[k] += c


@nb.njit(cache=True, nogil=True, inline="always")
def _add(dst, src, w):
    """Add w · src to dst (2-D views of one shape)."""
    for i in range(dst.shape[0]):
        for j in range(dst.shape[1]):
            dst[i, j] += w * src[i, j]


@nb.njit(cache=True, nogil=True)
def _galerkin_fine(e0, e1, dd, m0, m1):
    """
    Return level 1's operator Pᵀ A P, float64 (9, c0 · c1), and (c0, c1), from the fine edges (:func:`_fine_edges`).

    A = Σ over edges (e_p − e_q)(e_p − e_q)ᵀ + Σ_p deficit_p e_p e_pᵀ.  An edge along axis 1 has
    P_p − P_q = u ⊗ ½ (e_K − e_K+1) (u: its row's parents along axis 0), so the two fine edges
    of a row over one level-1 edge add ¼ u uᵀ times that edge's element; likewise along axis 0;
    the deficits add their rows' P_p P_pᵀ, class by class.  Every sum is of multiples of 1/16:
    the same values as the product computed entry by entry (:func:`_galerkin`).
    """
    c0 = (m0 - 2) // 2 + 3
    c1 = (m1 - 2) // 2 + 3
    out = np.zeros((9, c0, c1))
    nk = (m1 - 2) // 2                  # level-1 edges K = 1 .. nk along axis 1 (fine edges from 2K - 1 and 2K)
    for q0 in range(1, m0 - 1):
        ca = e1[q0, 1:1 + 2 * nk:2]
        cb = e1[q0, 2:2 + 2 * nk:2]
        if q0 & 1:
            _row_element(out, (q0 + 1) >> 1, nk, ca, cb, 0.25)
            continue
        a = q0 >> 1
        _row_element(out, a, nk, ca, cb, 0.0625)
        _row_element(out, a + 1, nk, ca, cb, 0.0625)
        _cross(out[7, a, 1:1 + nk], out[8, a, 1:1 + nk], out[6, a, 2:2 + nk], out[7, a, 2:2 + nk],
               out[1, a + 1, 1:1 + nk], out[2, a + 1, 1:1 + nk], out[0, a + 1, 2:2 + nk], out[1, a + 1, 2:2 + nk],
               ca, cb)
    nk0 = (m0 - 2) // 2                 # level-1 edges K0 = 1 .. nk0 along axis 0
    no = (m1 - 1) // 2                  # odd columns q1 = 2 I1 - 1
    ne = (m1 - 2) // 2                  # even columns q1 = 2 b
    for k0 in range(1, nk0 + 1):
        ra = e0[2 * k0 - 1]
        rb = e0[2 * k0]
        _element(out[4, k0, 1:1 + no], out[4, k0 + 1, 1:1 + no], out[7, k0, 1:1 + no], out[1, k0 + 1, 1:1 + no],
                 ra[1:1 + 2 * no:2], rb[1:1 + 2 * no:2], 0.25)
        ea = ra[2:2 + 2 * ne:2]
        eb = rb[2:2 + 2 * ne:2]
        for side in range(2):
            j = 1 + side
            _element(out[4, k0, j:j + ne], out[4, k0 + 1, j:j + ne], out[7, k0, j:j + ne], out[1, k0 + 1, j:j + ne],
                     ea, eb, 0.0625)
        _cross(out[5, k0, 1:1 + ne], out[8, k0, 1:1 + ne], out[2, k0 + 1, 1:1 + ne], out[5, k0 + 1, 1:1 + ne],
               out[3, k0, 2:2 + ne], out[6, k0, 2:2 + ne], out[0, k0 + 1, 2:2 + ne], out[3, k0 + 1, 2:2 + ne],
               ea, eb)
    n0o, n0e, n1o, n1e = (m0 - 1) // 2, (m0 - 2) // 2, (m1 - 1) // 2, (m1 - 2) // 2
    _add(out[4, 1:1 + n0o, 1:1 + n1o], dd[1:1 + 2 * n0o:2, 1:1 + 2 * n1o:2], 1.0)
    oe = dd[1:1 + 2 * n0o:2, 2:2 + 2 * n1e:2]              # parents (I0, b), (I0, b + 1)
    _add(out[4, 1:1 + n0o, 1:1 + n1e], oe, 0.25)
    _add(out[4, 1:1 + n0o, 2:2 + n1e], oe, 0.25)
    _add(out[5, 1:1 + n0o, 1:1 + n1e], oe, 0.25)
    _add(out[3, 1:1 + n0o, 2:2 + n1e], oe, 0.25)
    eo = dd[2:2 + 2 * n0e:2, 1:1 + 2 * n1o:2]              # parents (a, I1), (a + 1, I1)
    _add(out[4, 1:1 + n0e, 1:1 + n1o], eo, 0.25)
    _add(out[4, 2:2 + n0e, 1:1 + n1o], eo, 0.25)
    _add(out[7, 1:1 + n0e, 1:1 + n1o], eo, 0.25)
    _add(out[1, 2:2 + n0e, 1:1 + n1o], eo, 0.25)
    ee = dd[2:2 + 2 * n0e:2, 2:2 + 2 * n1e:2]              # four parents: each pair 1/16
    for u0 in range(2):
        for u1 in range(2):
            for t0 in range(2):
                for t1 in range(2):
                    _add(out[(t0 - u0 + 1) * 3 + t1 - u1 + 1, 1 + u0:1 + u0 + n0e, 1 + u1:1 + u1 + n1e], ee, 0.0625)
    return out.reshape(9, c0 * c1), c0, c1


@nb.njit(cache=True, nogil=True, inline="always")
def _axis_terms(par, u, d, t):
    """
    Return ``(I − j, J − I, weight)`` along one axis of a Galerkin product's term (weight 0: no such term).

    A fine index of parity ``par`` (1: odd, 2j − 1; 0: even, 2j), its parent choice ``u``, its
    neighbour at ``d`` (−1, 0, 1) and that neighbour's parent choice ``t``.
    """
    if par:
        if u > 0:
            return 0, 0, 0.0
        if d == 0:
            return 0, 0, (1.0 if t == 0 else 0.0)
        return 0, (t - 1 if d == -1 else t), 0.5
    if d == 0:
        return u, t - u, 0.25
    if t > 0:
        return 0, 0, 0.0
    return u, (-u if d == -1 else 1 - u), 0.5


@nb.njit(cache=True, nogil=True)
def _galerkin(s, m0, m1):
    """
    Return ``(Pᵀ S P float64 (9, c0 · c1), c0, c1)`` of a 9-point operator s (9, m0 · m1).

    Its border rows and columns are no unknowns.  P is bilinear, the product of its two axes'
    linear prolongations, so the product is taken one axis at a time: along axis 1 (every
    row: a 9-point operator on m0 × c1), then along axis 0.  Each term, one stencil slot and
    one parity class of the fine nodes along the axis, is a 2-D strided view update.  Every
    entry is a sum of dyadic fractions, exact in float64: the same values as the product
    taken over both axes at once (which cost 1.6x the time: 0.205 against 0.128 ms below the
    paper's 2-D band's level 1).
    """
    c0 = (m0 - 2) // 2 + 3
    c1 = (m1 - 2) // 2 + 3
    half = np.zeros((9, m0, c1))          # along axis 1: slot (d0, J1 − I1) of row i0, column I1
    for k in range(9):
        if not np.any(s[k] != 0.0):
            continue
        src_all = s[k].reshape(m0, m1)
        d0 = k // 3 - 1
        d1 = k % 3 - 1
        for par1 in range(2):
            n1 = (m1 - 1) // 2 if par1 else (m1 - 2) // 2       # columns 2j - 1 (odd) or 2j (even), up to m1 - 2
            f1 = 1 if par1 else 2
            src = src_all[:, f1:f1 + 2 * n1:2]
            for u1 in range(2):
                for t1 in range(2):
                    a1, dl1, w1 = _axis_terms(par1, u1, d1, t1)
                    if w1 != 0.0:
                        _add(half[(d0 + 1) * 3 + dl1 + 1, :, 1 + a1:1 + a1 + n1], src, w1)
    out = np.zeros((9, c0, c1))
    for k in range(9):
        d0 = k // 3 - 1
        src_all = half[k]
        for par0 in range(2):
            n0 = (m0 - 1) // 2 if par0 else (m0 - 2) // 2       # rows 2j - 1 (odd) or 2j (even), up to m0 - 2
            f0 = 1 if par0 else 2
            src = src_all[f0:f0 + 2 * n0:2, :]
            for u0 in range(2):
                for t0 in range(2):
                    a0, dl0, w0 = _axis_terms(par0, u0, d0, t0)
                    if w0 != 0.0:
                        _add(out[(dl0 + 1) * 3 + k % 3, 1 + a0:1 + a0 + n0, :], src, w0)
    return out.reshape(9, c0 * c1), c0, c1


@nb.njit(cache=True, nogil=True)
def _count(s):
    """Return the unknowns of a level (its stencils' centres above 0)."""
    return np.count_nonzero(s[4] > 0.0)


@nb.njit(cache=True, nogil=True)
def _levels(nb0, coords, lo0, lo1, s1, m0, m1, most):
    """
    Return the coarse levels, packed: ``(ok, st, inv, off, shp, idx, low)``.

    ok False: no factor, the coarsest level has more than ``most`` unknowns.

    st float32 (9, total): each level's stencils from ``off[l]`` (its c0 · c1 cells, then a
    zero); inv float32 (total,): each row's Jacobi step, :data:`JACOBI_WEIGHT` over its centre or
    :data:`JACOBI_MOST` over its absolute sum, whichever is less (0 off the unknowns); shp (L, 2):
    the levels' boxes; idx (k,): the
    coarsest level's unknowns (flat), low (k, k): their matrix's factor (semidefinite:
    :func:`.krylov._cholesky`).
    """
    e0, e1, dd = _fine_edges(nb0, coords, lo0, lo1, s1, m0, m1)
    s, c0, c1 = _galerkin_fine(e0, e1, dd, m0, m1)
    ss = [s]
    dims = [(c0, c1)]
    while _count(ss[-1]) > COARSEST_UNKNOWNS and min(dims[-1]) > 4:
        t, d0, d1 = _galerkin(ss[-1], dims[-1][0], dims[-1][1])
        ss.append(t)
        dims.append((d0, d1))
    nl = len(ss)
    off = np.zeros(nl + 1, np.int64)
    shp = np.zeros((nl, 2), np.int64)
    for lv in range(nl):
        shp[lv, 0], shp[lv, 1] = dims[lv]
        off[lv + 1] = off[lv] + dims[lv][0] * dims[lv][1] + 1
    st = np.zeros((9, off[nl]), np.float32)
    inv = np.zeros(off[nl], np.float32)
    for lv in range(nl):
        m = shp[lv, 0] * shp[lv, 1]
        for k in range(9):
            st[k, off[lv]:off[lv] + m] = ss[lv][k]
        centre = ss[lv][4]
        for f in range(m):
            if centre[f] > 0.0:
                row = 0.0              # the row's absolute sum: 2 M − S diagonally dominant where M ≥ it / 1.9
                for q in range(9):
                    row += abs(ss[lv][q, f])
                inv[off[lv] + f] = np.float32(1.0 / max(centre[f] / JACOBI_WEIGHT, row / JACOBI_MOST))
    last = ss[nl - 1]
    w1 = shp[nl - 1, 1]
    idx = np.flatnonzero(last[4] > 0.0)
    k = idx.size
    if k > most:
        return False, st, inv, off, shp, idx, np.zeros((0, 0))
    pos = np.full(last.shape[1], -1, np.int64)
    pos[idx] = np.arange(k)
    a = np.zeros((k, k))
    for r in range(k):
        f = idx[r]
        for q in range(9):
            v = last[q, f]
            if v != 0.0:
                a[r, pos[f + (q // 3 - 1) * w1 + q % 3 - 1]] += v
    return True, st, inv, off, shp, idx, _cholesky(a, True)


# --------------------------------------------------------------------------
# the coarse levels' kernels (float32, vector loops over each level's box)
# --------------------------------------------------------------------------
@nb.njit(cache=True, nogil=True, inline="always")
def _span(mode, st, inv, x, b, t, o0, m1, a, c):
    """
    One vector loop over a level's flat cells [a, c) (from ``o0``, rows of m1): the coarse kernels' one place.

    mode 0: t = b − S x (its residual); 1: x = inv b (a Jacobi sweep from 0); 2: x += inv t (a
    sweep's update from the residual in t).
    """
    n = c - a
    g = o0 + a
    if mode == 1:
        xx, iv, bb = x[g:g + n], inv[g:g + n], b[g:g + n]
        for i in range(n):
            xx[i] = iv[i] * bb[i]
        return
    if mode == 2:
        xx, iv, tt = x[g:g + n], inv[g:g + n], t[a:c]
        for i in range(n):
            xx[i] += iv[i] * tt[i]
        return
    bb = b[g:g + n]
    tt = t[a:c]
    a0, a1, a2 = st[0, g:g + n], st[1, g:g + n], st[2, g:g + n]
    a3, a4, a5 = st[3, g:g + n], st[4, g:g + n], st[5, g:g + n]
    a6, a7, a8 = st[6, g:g + n], st[7, g:g + n], st[8, g:g + n]
    x0, x1, x2 = x[g - m1 - 1:g - m1 - 1 + n], x[g - m1:g - m1 + n], x[g - m1 + 1:g - m1 + 1 + n]
    x3, x4, x5 = x[g - 1:g - 1 + n], x[g:g + n], x[g + 1:g + 1 + n]
    x6, x7, x8 = x[g + m1 - 1:g + m1 - 1 + n], x[g + m1:g + m1 + n], x[g + m1 + 1:g + m1 + 1 + n]
    for i in range(n):
        tt[i] = bb[i] - ((((a0[i] * x0[i] + a1[i] * x1[i]) + (a2[i] * x2[i] + a3[i] * x3[i]))
                          + ((a5[i] * x5[i] + a6[i] * x6[i]) + (a7[i] * x7[i] + a8[i] * x8[i]))) + a4[i] * x4[i])


@nb.njit(cache=True, nogil=True, parallel=True)
def _spans(mode, st, inv, x, b, t, o0, m1, lo, hi, chunk):
    """:func:`_span` over [lo, hi) in chunks of ``chunk`` cells on numba's threads: the same values."""
    for j in nb.prange((hi - lo + chunk - 1) // chunk):
        a = lo + j * chunk
        _span(mode, st, inv, x, b, t, o0, m1, a, min(hi, a + chunk))


@nb.njit(cache=True, nogil=True)
def _level_loop(mode, st, inv, x, b, t, o0, m0, m1, chunk):
    """:func:`_span` over a level's rows between its border rows, in chunks on numba's threads where ``chunk`` > 0."""
    lo = m1 + 1
    hi = (m0 - 1) * m1 - 1
    if chunk > 0 and hi - lo > chunk:
        _spans(mode, st, inv, x, b, t, o0, m1, lo, hi, chunk)
    else:
        _span(mode, st, inv, x, b, t, o0, m1, lo, hi)


@nb.njit(cache=True, nogil=True)
def _residual(st, x, b, t, o0, m0, m1, chunk=0):
    """
    Write t = b − S x over a level's cells (from ``o0``, m0 × m1), 0 on its border rows, the row after and one more.

    (:func:`_restrict` reads up to ``t[(m0 + 1) m1]`` where m0 and m1 are even.)

    The rows between hold border columns too: their stencils and right-hand sides are 0.
    ``chunk``: see :func:`_level_loop`.
    """
    _level_loop(0, st, st[4], x, b, t, o0, m0, m1, chunk)
    t[:m1 + 1] = 0.0
    t[(m0 - 1) * m1 - 1:(m0 + 1) * m1 + 1] = 0.0


@nb.njit(cache=True, nogil=True)
def _jacobi(st, inv, x, b, t, o0, m0, m1, first, chunk=0):
    """One damped Jacobi sweep on a level: x = inv b (``first``: from 0), else x += inv (b − S x) (inv: weighted)."""
    if first:
        _level_loop(1, st, inv, x, b, t, o0, m0, m1, chunk)
        return
    _residual(st, x, b, t, o0, m0, m1, chunk)
    _level_loop(2, st, inv, x, b, t, o0, m0, m1, chunk)


@nb.njit(cache=True, nogil=True, inline="always")
def _restrict_rows(t, b, o1, m1, c1, h, r0, r1, j0, j1):
    """
    :func:`_restrict`'s rows: the fine rows [r0, r1) weighted along axis 1 into h, or (r0 = r1) level rows [j0, j1).

    Each row on its own: a loop over either kind of row may run in any order.
    """
    half = np.float32(0.5)
    nj = c1 - 2
    for r in range(r0, r1):
        hr = h[r * c1 + 1:r * c1 + 1 + nj]
        mid = t[r * m1 + 1:r * m1 + 1 + 2 * nj:2]           # fine column 2 J1 - 1
        left = t[r * m1:r * m1 + 2 * nj:2]                   # 2 J1 - 2
        right = t[r * m1 + 2:r * m1 + 2 + 2 * nj:2]          # 2 J1
        for j in range(nj):
            hr[j] = mid[j] + half * (left[j] + right[j])
    for row in range(j0, j1):
        out = b[o1 + row * c1 + 1:o1 + row * c1 + 1 + nj]
        above = h[(2 * row - 2) * c1 + 1:(2 * row - 2) * c1 + 1 + nj]
        mid = h[(2 * row - 1) * c1 + 1:(2 * row - 1) * c1 + 1 + nj]
        below = h[(2 * row) * c1 + 1:(2 * row) * c1 + 1 + nj]
        for j in range(nj):
            out[j] = mid[j] + half * (above[j] + below[j])


@nb.njit(cache=True, nogil=True, parallel=True)
def _restrict_par(t, b, o1, m0, m1, c0, c1, h, rows):
    """:func:`_restrict` with its rows in blocks of ``rows`` on numba's threads: the same values."""
    for k in nb.prange((m0 + rows) // rows):
        _restrict_rows(t, b, o1, m1, c1, h, k * rows, min(m0 + 1, (k + 1) * rows), 0, 0)
    for k in nb.prange((c0 - 2 + rows - 1) // rows):
        _restrict_rows(t, b, o1, m1, c1, h, 0, 0, 1 + k * rows, min(c0 - 1, 1 + (k + 1) * rows))


@nb.njit(cache=True, nogil=True)
def _restrict(t, b, o1, m0, m1, c0, c1, h, chunk=0):
    """
    Write b (the level below, from ``o1``, c0 × c1) = Pᵀ t: the residual t (m0 × m1) weighted fully.

    h: scratch of (m0 + 1) × c1, each fine row weighted along axis 1 first, then the rows.
    ``chunk`` > 0: rows in blocks of about that many cells on numba's threads where there are two blocks or more.
    """
    rows = max(1, chunk // m1) if chunk > 0 else m0 + 1
    if rows < m0:
        _restrict_par(t, b, o1, m0, m1, c0, c1, h, rows)
        return
    _restrict_rows(t, b, o1, m1, c1, h, 0, m0 + 1, 0, 0)
    _restrict_rows(t, b, o1, m1, c1, h, 0, 0, 1, c0 - 1)


@nb.njit(cache=True, nogil=True, inline="always")
def _prolong_rows(x, o0, m1, o1, c1, p0, p1):
    """:func:`_prolong`'s fine rows [p0, p1), each on its own."""
    half = np.float32(0.5)
    quarter = np.float32(0.25)
    n_odd = (m1 - 1) // 2                 # columns 2 J1 - 1 up to m1 - 2
    n_even = (m1 - 2) // 2                # columns 2 J1
    for q0 in range(p0, p1):
        row = o0 + q0 * m1
        xo = x[row + 1:row + 1 + 2 * n_odd:2]
        xe = x[row + 2:row + 2 + 2 * n_even:2]
        if q0 & 1:
            j0 = (q0 + 1) >> 1
            c = x[o1 + j0 * c1 + 1:o1 + j0 * c1 + 2 + n_odd]
            for j in range(n_odd):
                xo[j] += c[j]
            for j in range(n_even):
                xe[j] += half * (c[j] + c[j + 1])
        else:
            a0 = q0 >> 1
            c = x[o1 + a0 * c1 + 1:o1 + a0 * c1 + 2 + n_odd]
            d = x[o1 + (a0 + 1) * c1 + 1:o1 + (a0 + 1) * c1 + 2 + n_odd]
            for j in range(n_odd):
                xo[j] += half * (c[j] + d[j])
            for j in range(n_even):
                xe[j] += quarter * ((c[j] + c[j + 1]) + (d[j] + d[j + 1]))


@nb.njit(cache=True, nogil=True, parallel=True)
def _prolong_par(x, o0, m0, m1, o1, c1, rows):
    """:func:`_prolong` with its rows in blocks of ``rows`` on numba's threads: the same values."""
    for k in nb.prange((m0 - 2 + rows - 1) // rows):
        _prolong_rows(x, o0, m1, o1, c1, 1 + k * rows, min(m0 - 1, 1 + (k + 1) * rows))


@nb.njit(cache=True, nogil=True)
def _prolong(x, o0, m0, m1, o1, c1, chunk=0):
    """
    Add P x_below (from ``o1``, rows of c1) to a level's x (from ``o0``, m0 × m1), one parity class at a time.

    Cells off the unknowns take values too: no stencil reads them (their weights are 0) and
    the next cycle starts them from 0 again.  ``chunk``: as :func:`_restrict`'s.
    """
    rows = max(1, chunk // m1) if chunk > 0 else m0
    if rows < m0 - 2:
        _prolong_par(x, o0, m0, m1, o1, c1, rows)
    else:
        _prolong_rows(x, o0, m1, o1, c1, 1, m0 - 1)


@nb.njit(cache=True, nogil=True)
def _coarsest(x, b, o, idx, low, y):
    """
    Solve the coarsest level (from ``o``) with its factor: x_K = A_KK⁻¹ b_K, x_N = 0.

    K: its unknowns whose pivots are not null, N: those whose are (:func:`.krylov._cholesky`'s
    semidefinite factor): a symmetric semidefinite generalized inverse of A.
    """
    k = idx.size
    for i in range(k):
        acc = np.float64(b[o + idx[i]])
        for j in range(i):
            acc -= low[i, j] * y[j]
        y[i] = acc / low[i, i] if low[i, i] > 0.0 else 0.0
    for i in range(k - 1, -1, -1):
        acc = y[i]
        for j in range(i + 1, k):
            acc -= low[j, i] * y[j]
        y[i] = acc / low[i, i] if low[i, i] > 0.0 else 0.0
    for i in range(k):
        x[o + idx[i]] = y[i]


@nb.njit(cache=True, nogil=True)
def _coarse_cycle(st, inv, off, shp, idx, low, x, b, t, y, h, chunk=0):
    """
    Compute x = M⁻¹ b from level 1 down (x, b float32 packed by ``off``): a V-cycle of damped Jacobi.

    t, h: scratch of the largest level (:func:`_restrict`'s); y: the coarsest's (float64).
    ``chunk`` > 0: each level's loops in chunks of that many cells on numba's threads (a level
    of one chunk in this thread): the same values.
    """
    nl = shp.shape[0]
    for lv in range(nl - 1):
        o0, m0, m1 = off[lv], shp[lv, 0], shp[lv, 1]
        _jacobi(st, inv, x, b, t, o0, m0, m1, True, chunk)
        for _ in range(PRE_SWEEPS - 1):
            _jacobi(st, inv, x, b, t, o0, m0, m1, False, chunk)
        _residual(st, x, b, t, o0, m0, m1, chunk)
        _restrict(t, b, off[lv + 1], m0, m1, shp[lv + 1, 0], shp[lv + 1, 1], h, chunk)
    o = off[nl - 1]
    x[o:off[nl]] = 0.0
    _coarsest(x, b, o, idx, low, y)
    for lv in range(nl - 2, -1, -1):
        o0, m0, m1 = off[lv], shp[lv, 0], shp[lv, 1]
        _prolong(x, o0, m0, m1, off[lv + 1], shp[lv + 1, 1], chunk)
        for _ in range(POST_SWEEPS):
            _jacobi(st, inv, x, b, t, o0, m0, m1, False, chunk)


# --------------------------------------------------------------------------
# the fine level (:mod:`.structured`'s cells) and CG
# --------------------------------------------------------------------------
@nb.njit(cache=True, nogil=True, inline="always")
def _red_residual(b, x, mask, res, k0, k1, o):
    """res[k] = the red cell k's residual b − 4 x + its black neighbours (``o``: their offsets), 0 off the unknowns."""
    n = k1 - k0
    bb, xt, mm, out = b[0, k0:k1], x[0, k0:k1], mask[0, k0:k1], res[k0:k1]
    xs = x[1]
    n0, n1, n2, n3 = xs[k0 + o[0]:k1 + o[0]], xs[k0 + o[1]:k1 + o[1]], xs[k0 + o[2]:k1 + o[2]], xs[k0 + o[3]:k1 + o[3]]
    for i in range(n):
        v = bb[i] - 4.0 * xt[i] + (n0[i] + n1[i] + n2[i] + n3[i])
        out[i] = v if mm[i] != 0.0 else 0.0


@nb.njit(cache=True, nogil=True, inline="always")
def _gather_rows(res, bc, tr, j0, j1):
    """Level-1 rows [j0, j1) of :func:`_restrict_fine`: five vector reads a row, each row on its own."""
    base, s0, s1, c1 = tr[0], tr[1], tr[4], tr[6]
    nj = c1 - 2
    for row in range(j0, j1):
        kc = (base + (2 * row - 1) * s0 + 1 - s1) >> 1      # node (row, 1)'s coincident cell (red: f even)
        ka = (base + (2 * row - 2) * s0 - s1) >> 1          # its corner cells below and above along axis 1 ...
        kb = (base + 2 * row * s0 - s1) >> 1                # ... in the fine rows on either side
        mid = res[kc:kc + nj]
        a_lo, a_hi = res[ka:ka + nj], res[ka + 1:ka + 1 + nj]
        b_lo, b_hi = res[kb:kb + nj], res[kb + 1:kb + 1 + nj]
        dst = bc[row * c1 + 1:row * c1 + 1 + nj]
        for j in range(nj):
            dst[j] = np.float32(mid[j] + 0.25 * ((a_lo[j] + a_hi[j]) + (b_lo[j] + b_hi[j])))


@nb.njit(cache=True, nogil=True, parallel=True)
def _restrict_fine_par(b, x, mask, res, bc, ranges, cut_red, tr, chunk):
    """:func:`_restrict_fine` with its loops in chunks of ``chunk`` cells (rows) on numba's threads: the same values."""
    k0, k1 = ranges[0, 0, 0], ranges[0, 0, 1]
    o = ranges[0, 0, 2:]
    for j in nb.prange((k1 - k0 + chunk - 1) // chunk):
        a = k0 + j * chunk
        _red_residual(b, x, mask, res, a, min(k1, a + chunk), o)
    structured.cut_residuals(res, x[1], cut_red)
    c0 = tr[5]
    rows = max(1, chunk // tr[6])
    for k in nb.prange((c0 - 2 + rows - 1) // rows):
        _gather_rows(res, bc, tr, 1 + k * rows, min(c0 - 1, 1 + (k + 1) * rows))


@nb.njit(cache=True, nogil=True)
def _restrict_fine(b, x, mask, res, bc, ranges, cut_red, tr, chunk=0):
    """
    Write level 1's right-hand side bc = Pᵀ r from the red cells' residuals (the black ones are 0 after a sweep).

    b float64 (2, H), x float32 (2, H): the fine level's right-hand side and iterate; res
    float64 (H + S0 + 2,): scratch, 0 outside the range (its residuals, 0 off the unknowns);
    tr: :func:`levels`' links ``(base, S0, rows, columns, s1, c0, c1)``.  A level-1 node
    (J0, J1) takes its coincident red cell's residual and a quarter of the four red cells at
    its corners (padded coordinates ``(2 J0 − 1, 2 J1 − 1)`` and ``(2 J0 − 1 ± 1, 2 J1 − 1 ± 1)``):
    along a row of level-1 nodes each of the five is the next red cell of its fine row, so a
    row is five vector reads.  A cell off the box reads the scratch's zeros.  ``chunk`` > 0: on
    numba's threads (:func:`_restrict_fine_par`).
    """
    if chunk > 0:
        _restrict_fine_par(b, x, mask, res, bc, ranges, cut_red, tr, chunk)
        return
    _red_residual(b, x, mask, res, ranges[0, 0, 0], ranges[0, 0, 1], ranges[0, 0, 2:])
    structured.cut_residuals(res, x[1], cut_red)
    _gather_rows(res, bc, tr, 1, tr[5] - 1)


@nb.njit(cache=True, nogil=True, inline="always")
def _prolong_fine_rows(x, xc, mask, tr, r0, r1):
    """Fine rows [r0, r1) of :func:`_prolong_fine`, each on its own."""
    base, s0, cols, s1, c1 = tr[0], tr[1], tr[3], tr[4], tr[6]
    quarter = np.float32(0.25)
    t = x[0]
    m = mask[0]
    for p0 in range(r0, r1):
        f0 = base + p0 * s0                       # the row's first cell (padded coordinate q1 = s1)
        k0 = (f0 + 1) >> 1                        # its first red cell ...
        k1 = (f0 + cols + 1) >> 1                 # ... and the end of its red cells
        n = k1 - k0
        q1 = 2 * k0 - f0 + s1                     # the first red cell's padded coordinate along axis 1
        xt = t[k0:k1]
        mm = m[k0:k1]
        if p0 & 1:                                # q1 odd: the node (q0 + 1) / 2, (q1 + 1) / 2
            row = ((p0 + 1) >> 1) * c1 + ((q1 + 1) >> 1)
            c = xc[row:row + n]
            for i in range(n):
                if mm[i] != 0.0:
                    xt[i] += c[i]
        else:                                     # q1 even: amid (q0 / 2, q1 / 2) and the next three
            row = (p0 >> 1) * c1 + (q1 >> 1)
            u = xc[row:row + n + 1]
            v = xc[row + c1:row + c1 + n + 1]
            for i in range(n):
                if mm[i] != 0.0:
                    xt[i] += quarter * ((u[i] + u[i + 1]) + (v[i] + v[i + 1]))


@nb.njit(cache=True, nogil=True, parallel=True)
def _prolong_fine_par(x, xc, mask, tr, rows):
    """:func:`_prolong_fine` with its rows in blocks of ``rows`` on numba's threads: the same values."""
    last = tr[2] - 1
    for k in nb.prange((last - 1 + rows - 1) // rows):
        _prolong_fine_rows(x, xc, mask, tr, 1 + k * rows, min(last, 1 + (k + 1) * rows))


@nb.njit(cache=True, nogil=True)
def _prolong_fine(x, xc, mask, tr, chunk=0):
    """
    Add level 1's correction xc (float32, c0 · c1) to the red unknowns of x (float32 (2, H)), a fine row at a time.

    tr: :func:`levels`' links.  A red cell in an odd fine row (padded coordinate q0) sits on a
    level-1 node, one in an even row amid four; along the row they are the next level-1 nodes
    (pairs) one after the other.  Cells off the unknowns keep their 0.  ``chunk`` > 0: rows
    in blocks of about that many cells on numba's threads.
    """
    if chunk > 0:
        _prolong_fine_par(x, xc, mask, tr, max(1, 2 * chunk // tr[3]))
    else:
        _prolong_fine_rows(x, xc, mask, tr, 1, tr[2] - 1)


@nb.njit(cache=True, nogil=True)
def _gvcycle(mask, ranges, nranges, cut_red, cut_black, tr, st, inv, off, shp, idx, low, rf, xf, res, xc, bc, t, y,
             h, sweeps, stop, chunks, chunk):
    """
    Compute xf = M⁻¹ rf (one V-cycle, see the module doc); return rf · xf.

    rf float64 (2, H): CG's residual on the cells; xf float32 (2, H); ``sweeps`` red-black pairs
    before and after the coarse correction; ``stop`` polled before it.  ``chunks``
    (:func:`.structured.chunks_of`, none: shape (2, 0, 3)) and ``chunk`` (0: none): the loops on
    numba's threads, the fine level's over those chunks, the others' in chunks of that many cells.
    """
    inv_deg = 0.25
    structured.first_red_in(xf, rf, mask, ranges, nranges, chunks, inv_deg)
    structured.half_sweep_in(xf, rf, mask, ranges, nranges, chunks, cut_black, 1, 4, inv_deg)
    for _ in range(sweeps - 1):
        structured.half_sweep_in(xf, rf, mask, ranges, nranges, chunks, cut_red, 0, 4, inv_deg)
        structured.half_sweep_in(xf, rf, mask, ranges, nranges, chunks, cut_black, 1, 4, inv_deg)
    if stop[0] != 0:
        return 0.0
    _restrict_fine(rf, xf, mask, res, bc, ranges, cut_red, tr, chunk)
    _coarse_cycle(st, inv, off, shp, idx, low, xc, bc, t, y, h, chunk // 4)
    _prolong_fine(xf, xc, mask, tr, chunk)
    for _ in range(sweeps - 1):
        structured.half_sweep_in(xf, rf, mask, ranges, nranges, chunks, cut_black, 1, 4, inv_deg)
        structured.half_sweep_in(xf, rf, mask, ranges, nranges, chunks, cut_red, 0, 4, inv_deg)
    s_black = structured.half_sweep_dot_in(xf, rf, mask, ranges, nranges, chunks, cut_black, 1, 4, inv_deg)
    return structured.half_sweep_dot_in(xf, rf, mask, ranges, nranges, chunks, cut_red, 0, 4, inv_deg) + s_black


@nb.njit(cache=True, nogil=True)
def _gpcg(mask, ranges, nranges, cut_red, cut_black, tr, st, inv, off, shp, idx, low, rhs, u, tol, max_iter, deadline,
          stop, sweeps, chunk):
    """
    CG on the cells preconditioned by :func:`_gvcycle`, from u: the stop rule of :func:`.multigrid._spcg`.

    rhs, u float64 (2, H) (0 off the unknowns); stops when the largest residual is below
    ``tol``, after ``max_iter`` iterations, at ``deadline`` or when ``stop[0]`` is set (polled
    before every iteration, after the update and within the V-cycle).  Returns (iterations,
    final max residual); u is updated in place.  ``chunk`` > 0: every vector loop in chunks of
    that many cells on numba's threads (each value as in one thread; the dot products summed per
    chunk, then in order: the same bits on any number of threads, other bits than ``chunk`` 0's).
    """
    half = mask.shape[1]
    cells = 2 * half
    xf = np.zeros((2, half), np.float32)
    res = np.zeros(half + tr[1] + 2)
    r = np.zeros((2, half))
    p = np.zeros((2, half))
    q = np.zeros((2, half))
    total = off[-1]
    xc = np.zeros(total, np.float32)
    bc = np.zeros(total, np.float32)
    big = shp[0, 0] * shp[0, 1] + 2 * shp[0, 1] + 2
    t = np.zeros(big, np.float32)
    h = np.zeros(big, np.float32)
    y = np.zeros(idx.size)
    rl, pl, ql, ul, xl = r.reshape(-1), p.reshape(-1), q.reshape(-1), u.reshape(-1), xf.reshape(-1)
    chunks = structured.chunks_of(ranges, nranges, chunk) if chunk > 0 else np.zeros((2, 0, 3), np.int64)
    structured.product_dot_in(u, q, mask, ranges, nranges, chunks, cut_red, cut_black, 4)
    rl[:] = rhs.reshape(-1)
    worst = _subtract_max(rl, ql, 1.0, cells)
    if worst < tol:
        return 0, worst
    rz = _gvcycle(mask, ranges, nranges, cut_red, cut_black, tr, st, inv, off, shp, idx, low, r, xf, res, xc, bc,
                  t, y, h, sweeps, stop, chunks, chunk)
    pl[:] = xl
    it = 0
    while it < max_iter:
        if stop[0] != 0 or (deadline > 0.0 and _now() > deadline):      # polled before every iteration
            break
        it += 1
        pq = structured.product_dot_in(p, q, mask, ranges, nranges, chunks, cut_red, cut_black, 4)
        if not pq > 0.0:
            break
        alpha, worst, done = _descend_in(rl, ql, ul, pl, rz, pq, tol, cells, stop, chunk)
        if done:
            break
        rz_new = _gvcycle(mask, ranges, nranges, cut_red, cut_black, tr, st, inv, off, shp, idx, low, r, xf, res, xc,
                          bc, t, y, h, sweeps, stop, chunks, chunk)
        _turn_in(ul, pl, xl, alpha, rz, rz_new, cells, chunk)
        rz = rz_new
    return it, worst
