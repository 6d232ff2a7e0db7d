"""Scaled harmonic relaxation: u_i = w_i · exp(s_i) on the graph of reachable nodes.

The iteration is SOR on the flipped harmonic potential u (goal 1, obstacles 0),
written for w with a per-node log scale s: the update of node i is

    w_i ← (1 − ω) w_i + ω Σ_a c_ia w_j(a),   c_ia = exp(s_j − s_i) / 2n,

a diagonal similarity transform of the SOR iteration on u, so it is the same
iteration, but nothing underflows (u reaches 1e−3000 in long corridors) and the
hot loop is multiply–adds.  The scales are refreshed (s += log w, w = 1,
recompute c) when some w drifts far from 1.  Nodes are swept colour class by
colour class (red–black, plus extra colours at odd periodic seams), each class in
parallel.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np

_RENORM_LOG = 300.0          # refresh the scales when |log w| exceeds this somewhere


@nb.njit(cache=True, nogil=True)
def colour_classes(nbr, n_goal, coords_parity):
    """Colour the non-goal nodes so that no two neighbours share a colour.

    Starts from the grid parity (red–black) and re-colours the few nodes where an
    odd periodic axis breaks it.  Returns (members, starts): class c is
    members[starts[c]:starts[c+1]], ascending node positions.
    """
    n = nbr.shape[0]
    deg = nbr.shape[1]
    colour = np.empty(n, np.int64)
    for i in range(n):
        colour[i] = coords_parity[i]
    used = np.zeros(deg + 3, np.bool_)
    for i in range(n):
        clash = False
        for a in range(deg):
            j = nbr[i, a]
            if j < n and j != i and colour[j] == colour[i]:
                clash = True
        if clash:
            used[:] = False
            for a in range(deg):
                j = nbr[i, a]
                if j < n and j != i:
                    used[colour[j]] = True
            c = 2
            while used[c]:
                c += 1
            colour[i] = c
    n_col = 0
    for i in range(n_goal, n):
        if colour[i] + 1 > n_col:
            n_col = colour[i] + 1
    counts = np.zeros(n_col + 1, np.int64)
    for i in range(n_goal, n):
        counts[colour[i] + 1] += 1
    starts = np.cumsum(counts)
    fill = starts[:-1].copy()
    members = np.empty(n - n_goal, np.int64)
    for i in range(n_goal, n):
        members[fill[colour[i]]] = i
        fill[colour[i]] += 1
    return members, starts


@nb.njit(cache=True, nogil=True, parallel=True)
def _refresh(w, s, coef, lbw, scale, nbr, lb_s, inv_deg):
    """s += log w, w = 1; recompute the coefficients, exp(s) and the lower bound in w units."""
    n = nbr.shape[0]
    deg = nbr.shape[1]
    for i in nb.prange(n):
        s[i] += math.log(w[i])
        w[i] = 1.0
        scale[i] = math.exp(s[i])
    for i in nb.prange(n):
        for a in range(deg):
            j = nbr[i, a]
            coef[i, a] = 0.0 if j >= n else math.exp(s[j] - s[i]) * inv_deg
        d = lb_s[i] - s[i]
        lbw[i] = math.exp(d) if d > -700.0 else 0.0


@nb.njit(cache=True, nogil=True, parallel=True)
def scaled_sweeps(w, s, coef, lbw, scale, nbr, lb_s, members, starts, omega, tol, absolute,
                  max_sweeps, n_chunks):
    """Red–black SOR sweeps until the largest change of u in a sweep is below tol.

    The change is relative (|Δu|/u, i.e. |Δ log u|) or, with ``absolute``, in u
    itself (as the linear solvers measure it).

    Arrays cover the n reachable nodes in BFS order (goal nodes first, held at
    u = 1); w has one more entry, the dummy node n (u = 0) that stands for walls
    and obstacles.  Values are kept ≥ the subharmonic lower bound exp(lb_s) and
    positive.  Returns (sweeps, change).
    """
    n = nbr.shape[0]
    deg = nbr.shape[1]
    inv_deg = 1.0 / deg
    n_cls = starts.shape[0] - 1
    cmax = np.zeros(n_chunks)
    amax = np.zeros(n_chunks)
    wmax = np.zeros(n_chunks)
    sweeps = 0
    change = np.inf
    achange = np.inf
    while sweeps < max_sweeps:
        cmax[:] = 0.0
        amax[:] = 0.0
        wmax[:] = 0.0
        for c in range(n_cls):
            lo = starts[c]
            hi = starts[c + 1]
            size = hi - lo
            step = (size + n_chunks - 1) // n_chunks
            for ch in nb.prange(n_chunks):
                mx = cmax[ch]
                ax = amax[ch]
                big = wmax[ch]
                for t in range(lo + ch * step, min(hi, lo + (ch + 1) * step)):
                    i = members[t]
                    acc = 0.0
                    for a in range(deg):
                        acc += coef[i, a] * w[nbr[i, a]]
                    old = w[i]
                    new = old + omega * (acc - old)
                    floor = lbw[i]
                    if old * 1e-8 > floor:
                        floor = old * 1e-8
                    if new < floor:
                        new = floor
                    w[i] = new
                    # only the measure this phase stops on; divide only when the max grows
                    d = abs(new - old)
                    if absolute:
                        d *= scale[i]
                        if d > ax:
                            ax = d
                    elif d > mx * new:
                        mx = d / new
                    if new > 1e100 or new < 1e-100:
                        lg = abs(math.log(new))
                        if lg > big:
                            big = lg
                cmax[ch] = mx
                amax[ch] = ax
                wmax[ch] = big
        sweeps += 1
        change = cmax.max() if not absolute else np.inf
        achange = amax.max() if absolute else np.inf
        if wmax.max() > _RENORM_LOG:
            _refresh(w, s, coef, lbw, scale, nbr, lb_s, inv_deg)
        if (achange if absolute else change) < tol:
            break
    return sweeps, change, achange


def prepare(nbr, n_goal, lb_s, parity, s0=None):
    """Initial state: s = s0 (default: the lower bound lb_s), w = 1; the
    coefficients; the colour classes.  ``s0`` must be >= ``lb_s``."""
    n = nbr.shape[0]
    deg = nbr.shape[1]
    s = np.empty(n + 1)
    s[:n] = lb_s if s0 is None else s0
    s[n] = 0.0
    w = np.ones(n + 1)
    w[n] = 0.0
    coef = np.empty((n, deg))
    lbw = np.empty(n)
    scale = np.empty(n + 1)
    lb_full = np.empty(n + 1)
    lb_full[:n] = lb_s
    lb_full[n] = 0.0
    _refresh(w, s, coef, lbw, scale, nbr, lb_full, 1.0 / deg)    # w = 1: sets coef, lbw, scale
    members, starts = colour_classes(nbr, n_goal, parity)
    return w, s, coef, lbw, scale, lb_full, members, starts


def restrict_classes(members, starts, keep):
    """The colour classes limited to the nodes where ``keep`` (bool, one per
    node) is True, in the same order: sweeping them relaxes only those nodes
    and holds every other node fixed.  Returns (members, starts)."""
    sel = keep[members]
    kept = members[sel]
    counts = np.array([np.count_nonzero(sel[starts[c]:starts[c + 1]]) for c in range(starts.size - 1)])
    new_starts = np.zeros(starts.size, np.int64)
    new_starts[1:] = np.cumsum(counts)
    return np.ascontiguousarray(kept), new_starts
