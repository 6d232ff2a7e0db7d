"""
The planner's field: the harmonic potential to relative precision, by bands of scale.

See :mod:`spacerobot_planner.field` for what the field is and why it is solved this way;
this module holds the route's steps.  All arrays are over the node graph
(:class:`~spacerobot_planner.field.graph.NodeGraph`), so any grid dimension works.
"""
from __future__ import annotations

import math
import time

import numba as nb
import numpy as np

from ..termination import Termination
from . import multigrid
from .graph import NodeGraph, ascent_defects, put_at

#: Each band's linear solve stops at this largest residual (its known values are ≤ 1).
RESIDUAL_TOL = 1e-10
#: A band keeps the values at or above this (relative to its largest known value); the
#: nodes below it make up the next band, solved on their own scale.
BAND_FLOOR = 1e-6
#: Bands after the first solve a window of their nodes: those within this many face steps
#: of a known node at first (doubled while the window's outer layers are not negligible).
WINDOW_STEPS = 32
#: ... negligible: below BAND_FLOOR times this.
WINDOW_NEGLIGIBLE = 1e-4
#: A window of more than this fraction of the unknown nodes is not taken: the band solves them
#: all.  Such a window saves at most that fraction of the band's work, and where its outer layers
#: are not negligible the band is solved again on a window twice as wide (most often the whole
#: rest): on 200 random scenes per DOF (`bench scenes`' family) 731 -> 701 band solves and 3.7 %
#: fewer node-iterations at 3-DOF, 1 079 -> 945 and 7.4 % fewer at 2-DOF, the same paths bit for bit.
WINDOW_WHOLE_FRACTION = 0.5
#: The ascent repair lowers a node to this much (in log u) below the neighbour it follows.
REPAIR_STEP = 1e-9


@nb.njit(cache=True, nogil=True)
def _band_problem(nbr, active, known, log_u):
    """
    Return the Dirichlet problem on the ``active`` nodes, with the ``known`` ones fixed.

    Returns ``(sub_nbr uint32 (m, deg), rhs (m,), log_scale)``: neighbours in local indices
    (m = none), and the known neighbour values divided by the largest of them,
    ``exp(log_scale)``.
    """
    n, deg = nbr.shape
    m = active.size
    local = np.full(n + 1, m, np.int32)     # m: not in the band (known, outside the window, none)
    for k in range(m):
        local[active[k]] = k
    sub = np.empty((m, deg), np.uint32)     # the multigrid's fine level reads uint32
    edge_k = np.empty(m * deg, np.int64)    # the band's edges to known nodes, in row order
    edge_j = np.empty(m * deg, np.int64)
    edges = 0
    log_scale = -np.inf
    for k in range(m):
        i = active[k]
        for a in range(deg):
            j = nbr[i, a]
            sub[k, a] = local[j]
            if j < n and known[j]:
                edge_k[edges] = k
                edge_j[edges] = j
                edges += 1
                if log_u[j] > log_scale:
                    log_scale = log_u[j]
    rhs = np.zeros(m)
    for e in range(edges):
        rhs[edge_k[e]] += math.exp(log_u[edge_j[e]] - log_scale)
    return sub, rhs, log_scale


@nb.njit(cache=True, nogil=True)
def _steps_from_known(nbr, active, known, mark, max_steps):
    """
    Count the face steps from each ``active`` node to the nearest known node.

    Face steps through active nodes, int64 (m,): 1 next to a known node, up to
    ``max_steps`` (0 = no limit); ``max_steps + 1`` for the nodes farther away.
    ``mark`` int32 (N + 1,) scratch, all -1 on entry and on return: during the search it
    holds each active node's steps so far, by graph node (so a neighbour is one load, not a
    look-up of its position in ``active`` and then of its steps: 2.5x faster on windows of
    300 000-500 000 nodes, the same steps).
    """
    n, deg = nbr.shape
    m = active.size
    far = (1 << 40) if max_steps == 0 else max_steps + 1
    unseen = np.int32(min(far, 2 ** 31 - 1))
    for k in range(m):
        mark[active[k]] = unseen
    queue = np.empty(m, np.int64)
    tail = 0
    for k in range(m):
        g = active[k]
        for a in range(deg):
            j = nbr[g, a]
            if j < n and known[j]:
                mark[g] = 1
                queue[tail] = g
                tail += 1
                break
    head = 0
    while head < tail:
        g = queue[head]
        head += 1
        s = mark[g] + 1
        if s >= far:
            continue
        for a in range(deg):
            j = nbr[g, a]
            if mark[j] > s:          # -1 (not active, the dummy N): never
                mark[j] = s
                queue[tail] = j
                tail += 1
    steps = np.empty(m, np.int64)
    for k in range(m):
        g = active[k]
        v = mark[g]
        steps[k] = far if v == unseen else v
        mark[g] = -1
    return steps


#: :func:`_keep` without window steps (the first band).
_NO_STEPS = np.zeros(0, np.int64)


@nb.njit(cache=True, nogil=True)
def _keep(x, floor, window, known, steps):
    """
    Return the band's values to keep: those at or above ``floor``.

    x float64 (m,) the band's solution on ``window`` int64 (m,) (graph nodes); marks them
    ``known``.  steps int64 (m,) each window node's face steps from a known node (counted up
    to the window's steps + 1: :func:`_steps_from_known`), or empty.  Returns ``(kept int64 (k,)
    graph nodes, their values float64 (k,), the most steps among them (0 without steps))``.
    """
    m = x.size
    kept = np.empty(m, np.int64)
    vals = np.empty(m)
    far = 0
    k = 0
    for i in range(m):
        if x[i] >= floor:
            kept[k] = window[i]
            vals[k] = x[i]
            known[window[i]] = True
            if steps.size and steps[i] > far:
                far = steps[i]
            k += 1
    return kept[:k], vals[:k], far


@nb.njit(cache=True, nogil=True)
def _unknown(active, known):
    """Return the ``active`` nodes (int64, graph nodes) not ``known``, in their order."""
    out = np.empty(active.size, np.int64)
    k = 0
    for i in active:
        if not known[i]:
            out[k] = i
            k += 1
    return out[:k]


@nb.njit(cache=True, nogil=True)
def _extend_below(log_u, known, nbr, n_goal, log_deg):
    """
    Values for the nodes no band reached (the budget ran out).

    Breadth-first from the known nodes, each ``log_deg`` (= log 2n) below the node it was reached
    from — the subharmonic lower bound's rule, so each has a strictly higher neighbour.
    """
    n, deg = nbr.shape
    queue = np.empty(n, np.int64)
    seen = known.copy()
    tail = 0
    for i in range(n):
        if known[i]:
            queue[tail] = i
            tail += 1
    head = 0
    while head < tail:
        i = queue[head]
        head += 1
        for a in range(deg):
            j = nbr[i, a]
            if j < n and not seen[j]:
                seen[j] = True
                log_u[j] = log_u[i] - log_deg
                queue[tail] = j
                tail += 1


@nb.njit(cache=True, nogil=True, inline="always")
def _sift_down(heap_k, heap_i, size, p):
    """Restore the min-heap (keys heap_k, items heap_i) below position p."""
    while True:
        c = 2 * p + 1
        if c >= size:
            break
        if c + 1 < size and heap_k[c + 1] < heap_k[c]:
            c += 1
        if heap_k[c] < heap_k[p]:
            heap_k[c], heap_k[p] = heap_k[p], heap_k[c]
            heap_i[c], heap_i[p] = heap_i[p], heap_i[c]
            p = c
        else:
            break


@nb.njit(cache=True, nogil=True, inline="always")
def _sift_up(heap_k, heap_i, c):
    """Restore the min-heap (keys heap_k, items heap_i) above position c."""
    while c > 0:
        p = (c - 1) // 2
        if heap_k[c] < heap_k[p]:
            heap_k[c], heap_k[p] = heap_k[p], heap_k[c]
            heap_i[c], heap_i[p] = heap_i[p], heap_i[c]
            c = p
        else:
            break


@nb.njit(cache=True, nogil=True)
def _repair_ascent(log_u, nbr, n_goal, step):
    """
    Make every non-goal node strictly lower than some neighbour, changing only nodes that are not already.

    Nodes are settled in decreasing order of value from the goal (a max-heap): a node is
    reached from its highest settled neighbour and keeps its value if that is lower by at
    least ``step``, else takes that neighbour's value less ``step``.  Returns the number of
    nodes changed.  log_u (N + 1,) float64, updated in place (dummy last).
    """
    n, deg = nbr.shape
    key = np.full(n, -np.inf)
    queued = np.zeros(n, np.bool_)
    heap_k = np.empty(n + 1)
    heap_i = np.empty(n + 1, np.int64)
    size = 0
    for g in range(n_goal):
        key[g] = log_u[g]
        heap_k[size] = -key[g]
        heap_i[size] = g
        size += 1
        queued[g] = True
    # heapify (min-heap on -key)
    for s in range(size // 2 - 1, -1, -1):
        _sift_down(heap_k, heap_i, size, s)
    changed = 0
    while size > 0:
        i = heap_i[0]
        size -= 1
        heap_k[0] = heap_k[size]
        heap_i[0] = heap_i[size]
        _sift_down(heap_k, heap_i, size, 0)
        if key[i] != log_u[i]:
            log_u[i] = key[i]
            changed += 1
        for a in range(deg):
            j = nbr[i, a]
            if j >= n or queued[j]:
                continue
            queued[j] = True              # pushed once: popped once, keyed by its first settler
            key[j] = min(log_u[j], log_u[i] - step)
            heap_k[size] = -key[j]
            heap_i[size] = j
            _sift_up(heap_k, heap_i, size)
            size += 1
    return changed


def _initial(prior, window, log_scale):
    """
    Return a band's initial guess from ``prior`` (log u over the graph, float64 (N + 1,)) on its ``window``.

    On the band's scale (divided by ``exp(log_scale)``) and at most 1, the band's largest
    value (its known values are at most 1 on that scale): float64 (m,), 0 where the prior is -inf;
    None (start from 0) for a band without a known value.
    """
    if not math.isfinite(log_scale):
        return None
    return np.exp(np.minimum(prior[window] - log_scale, 0.0))


@nb.njit(cache=True, nogil=True)
def _note(prior, window, x, log_scale, below):
    """
    Keep a band's solution as the next bands' guess: prior[window] = log x + log_scale, -inf where x ≤ 0.

    prior float64 (N + 1,) log u over the graph; window int64 (m,) graph nodes; x float64 (m,)
    the band's solution on its scale ``exp(log_scale)``; only where x < ``below`` (the band
    keeps the others: no later band solves them).  Where x ≤ 0 (CG's iterate below its
    precision) the guess is 0: what an earlier band or the caller's guess held there is
    coarser still (on 200 random scenes per DOF, keeping it cost 1 % more iterations, 7 % more
    in repairs).
    """
    for k in range(window.size):
        if x[k] < below:
            prior[window[k]] = math.log(x[k]) + log_scale if x[k] > 0.0 else -np.inf


def solve(graph: NodeGraph, budget_s: float, residual_tol: float = RESIDUAL_TOL,
          band_floor: float = BAND_FLOOR, cancel=None, token=None, guess=None):
    """
    Return log u over the graph, float64 (N + 1,) with the dummy last (-inf), and the stats.

    Band after band (see the package doc) until every node has a value, the budget
    (seconds of wall time from the call) ends, or ``cancel()`` returns true; then the
    ascent check and, where it fails, the repair.  Returns ``(log_u, stats)`` with stats
    a dict: ``bands``, ``iterations`` (CG iterations, all bands), ``residual`` (the
    largest final residual of a band, relative to its scale), ``converged``,
    ``unsolved_nodes`` (left to the breadth-first extension when the budget or a cancel
    stopped the bands), ``repaired_nodes``, ``left`` (what is left, for people; "" when
    converged).

    ``cancel()`` is a soft stop: the field is completed as when the budget ends.
    ``token`` (``termination.Termination``) is the plan's hard stop: polled inside the
    CG iterations as the deadline is, and between the steps; once it is set this raises
    ``termination.Cancelled`` and returns nothing.

    Each band's CG starts from the values the bands before it left below their floor (band 1
    solves every node: its values there are right to its residual, about 1e-4 of the next
    band's scale), not from 0: about 4 of the 10 decades of its stop are already there.
    ``guess``: float64 (N + 1,), a log u near this one (a field of the same grid before a few
    edges were cut): the first band starts from it (it covers every node, so the later bands
    start from the bands before them).  Every band still stops at the same largest residual,
    so the field has the same precision whatever the guesses; they only save iterations.
    """
    t0 = time.perf_counter()
    deadline = t0 + float(budget_s)
    token = Termination.of(token)
    n, n_goal = graph.size, graph.n_goal
    nbr = graph.nbr
    log_u = np.full(n + 1, -np.inf)
    log_u[:n_goal] = 0.0
    known = np.zeros(n, np.bool_)
    known[:n_goal] = True
    active = np.arange(n_goal, n, dtype=np.int64)
    bands = iterations = 0
    worst = 0.0
    converged = True
    left = ""
    window_steps = 0                 # 0: the whole band (the first one)
    scratch = None                   # _steps_from_known's, from the second band on
    # log u as the solves so far left it (every node a band solved: below the floors too), the guesses
    prior = np.full(n + 1, -np.inf) if guess is None else np.array(guess, dtype=float)
    while active.size:
        token.check()
        if time.perf_counter() > deadline or (cancel is not None and cancel()):
            converged = False
            left = (f"the field budget of {budget_s:g} s ended after {bands} band(s) with "
                    f"{active.size} of {n - n_goal} nodes unsolved")
            break
        if window_steps == 0:        # the first band: every node
            whole, steps = True, None
        else:
            if scratch is None:
                scratch = np.full(n + 1, -1, np.int32)
            steps = _steps_from_known(nbr, active, known, scratch, window_steps)
            inside = steps <= window_steps
            # every active node within the window's steps, or most of them: the band takes them all
            whole = np.count_nonzero(inside) > WINDOW_WHOLE_FRACTION * active.size
        inside = None if whole else inside
        # (np.compress and np.take: a boolean mask or an index array in brackets took 3-5x as long here)
        window = active if whole else np.compress(inside, active)
        steps_w = _NO_STEPS if steps is None else steps if whole else np.compress(inside, steps)    # the window's
        sub, rhs, log_scale = _band_problem(nbr, window, known, log_u)
        token.check()
        # every node but the goal's (the first band): a view of their coordinates, not a copy
        coords = graph.coords[n_goal:] if window.size == n - n_goal else np.take(graph.coords, window, axis=0)
        x0 = None if guess is None and bands == 0 else _initial(prior, window, log_scale)
        x, its, res = multigrid.solve(sub, coords, graph.shape, rhs, tol=residual_tol, deadline=deadline,
                                      stop=token.flag, x0=x0)
        token.check()               # the iterations stopped part-way: keep nothing
        bands += 1
        iterations += its
        worst = max(worst, res)
        if not whole and np.max(np.compress(steps_w >= window_steps - 1, x)) > band_floor * WINDOW_NEGLIGIBLE:
            _note(prior, window, x, log_scale, np.inf)      # the wider window's guess, every node
            window_steps *= 2        # the cut is felt: a wider window
            continue
        floor = band_floor
        if res > residual_tol:       # stopped by the deadline: keep what is already sure
            converged = False
            floor = max(floor, 1e6 * res)
        _note(prior, window, x, log_scale, floor)           # the nodes left to the next bands
        kept, vals, far = _keep(x, floor, window, known, steps_w)
        if not kept.size:
            continue                 # only when the deadline stopped the band: caught above
        np.log(vals, out=vals)       # NumPy's log, as ever (math.log differs in the last bit)
        vals += log_scale
        put_at(log_u, kept, vals)
        window_steps = WINDOW_STEPS if steps is None else max(WINDOW_STEPS, 2 * int(far))
        active = _unknown(active, known)
    unsolved = int(active.size)
    if unsolved:
        _extend_below(log_u, known, nbr, n_goal, math.log(2 * graph.coords.shape[1]))
    token.check()
    repaired = 0
    if ascent_defects(log_u, nbr, n_goal).size:
        token.check()
        repaired = int(_repair_ascent(log_u, nbr, n_goal, REPAIR_STEP))
    token.check()
    return log_u, {"bands": bands, "iterations": iterations, "residual": worst,
                   "converged": converged, "unsolved_nodes": unsolved,
                   "repaired_nodes": repaired, "left": left}
