"""
The harmonic potential on a C-space grid: the field that steepest descent follows.

What the field is
-----------------
The paper's Laplace potential on the grid of joint angles: on the free nodes connected to
the goal, each value is the mean of its 2n face neighbours (the discrete Laplace
equation); goal nodes are fixed, obstacles and the faces of bounded joints are walls,
periodic joints (the attitude) wrap.  We solve it in the flipped form the paper's Φ maps
to, u = 1 − Φ/Φ0: goal 1, walls 0, so 0 < u < 1 on every goal-connected node, and store
``log_u`` (0 at the goal, −inf at obstacles and unreachable nodes).  The published
potential is φ = −log u.  A harmonic u has no interior local maximum, so steepest ascent
of u (descent of φ) reaches the goal from every goal-connected node.

Why not the paper's Gauss–Seidel, and how this avoids the flat field
--------------------------------------------------------------------
u decays geometrically into narrow passages and pockets: 1e-30 is common, a maze reaches
1e-561.  In the paper's form Φ0 − Φ then falls below what a double holds next to Φ0 and
the field is exactly flat, so descent stalls; any solver that is accurate only to an
absolute tolerance (SOR, multigrid to 1e-12) stalls the same way one level deeper.  The
route here (``"log_harmonic"``, :mod:`.harmonic`) is accurate *relative* to each value,
band by band of scale:

1. Band 1: the whole Dirichlet problem (goal = 1) by conjugate gradients preconditioned
   by an aggregation-multigrid V-cycle (:mod:`.multigrid`; on a compact 2-D band,
   geometric coarse levels: :mod:`.geometric`), to a largest residual of 1e-10.  Values
   ≥ 1e-6 are then right to about 1e-4 relative (measured against a direct solve: 1e-5 at
   most on the paper's scenes) and are kept.
2. Band k + 1: the nodes still without a value, as a Dirichlet problem of their own whose
   known neighbours are the kept values, divided by the largest of them, so the band's
   values are again of order one; solved and kept the same way.  Every band keeps at
   least the neighbours of its largest known value (a harmonic value is ≥ 1/2n of its
   largest neighbour), so the bands end; a typical scene needs one to three, a maze one
   per six decades.  Its iterations start from the values the bands before it left
   below their floors (right to about 1e-4 of its scale), not from 0.
3. A check that every non-goal node has a strictly higher face neighbour.  Where rounding
   made two neighbours equal, a repair lowers the later one by 1e-9 in log u (in
   decreasing order of value from the goal, so every node ends strictly below the
   neighbour it follows); ``repaired_nodes`` counts them.

When it stops
-------------
When every node has a value (``converged``), or when the budget (``budget_s``, wall
time; the planner's ``planner.field_budget_s``) or a soft ``cancel`` ends the bands first.  Then
the nodes without a value are filled breadth-first from the solved ones, each 1/2n of
the node it was reached from (the subharmonic lower bound's rule), the check and repair
run as above, and the result is still a valid ascent field: descent reaches the goal
from every goal-connected node, on a less accurate field there.  ``converged`` is then
false and ``left`` says what is left.

The plan's termination token (``token``, :class:`~spacerobot_planner.termination.Termination`)
is another matter: a hard stop, polled inside the kernels' iterations (CG iterations,
Gauss–Seidel sweeps) as the deadline is, and between the steps.  Once it is set,
:func:`solve_field` raises :class:`~spacerobot_planner.termination.Cancelled` and returns
no field, so a cancelled solve leaves nothing behind to be cached.

Solvers (``solve_field(..., solver=NAME)``)
-------------------------------------------
``"log_harmonic"``  the planner's route above (default).
``"gauss_seidel"``  the paper's method, literally (:mod:`.paper`): reference and the
                    baseline of every benchmark ratio; ``tol`` is its largest change per
                    sweep (the paper's 1e-6).
Internal, not a planner choice: ``"oracle"`` (:mod:`.oracle`), a sparse direct solve
band by band, seconds at 36³: the slow reference of the tests and of ``bench scenes``.
"""
from __future__ import annotations

import ctypes
import math
import os
import sys
import time
from dataclasses import dataclass, field as dc_field

import numpy as np

from ..termination import Termination
from . import harmonic, multigrid, paper
from .graph import NodeGraph, bfs, bfs_distance, node_graph, validate_problem

__all__ = ["Field", "SOLVERS", "DEFAULT_SOLVER", "DEFAULT_BUDGET_S", "solve_field",
           "bfs_distance", "node_graph", "validate_problem", "NodeGraph", "warm_up", "warm_up_rare"]

SOLVERS = ("log_harmonic", "gauss_seidel")
DEFAULT_SOLVER = "log_harmonic"
INTERNAL_SOLVERS = ("oracle",)
#: Default wall-time budget of one field solve, seconds.
DEFAULT_BUDGET_S = 5.0


@dataclass(frozen=True, eq=False)
class Field:
    """
    A solved potential field on an occupancy grid.

    Attributes
    ----------
        log_u: float64, grid shape: log of the flipped potential u (0 at goal nodes,
            -inf at obstacles and nodes not connected to the goal; for the paper's
            solver also where Φ is flat at Φ0 in float64).
        occupied, periodic, goal_nodes: the problem it was solved for.
        solver: the solver's name.
        sweeps: relaxation sweeps (gauss_seidel) or CG iterations over all bands.
        residual: gauss_seidel: the last largest change per sweep; log_harmonic: the
            largest final residual of a band, relative to the band's scale.
        converged: the solve ran to its precision (see the package doc).
        seconds: wall time of the solve, graph set-up included.
        left: what is left when not converged ("" otherwise), for people.
        stats: solver details (log_harmonic: bands, unsolved_nodes, repaired_nodes).

    """

    log_u: np.ndarray
    occupied: np.ndarray
    periodic: tuple
    goal_nodes: np.ndarray
    solver: str
    sweeps: int
    residual: float
    converged: bool
    seconds: float
    left: str = ""
    stats: dict = dc_field(default_factory=dict)

    def potential(self) -> np.ndarray:
        """φ = −log u: 0 at the goal, +inf at obstacles (plot it on a log scale)."""
        return -self.log_u

    @property
    def reachable(self) -> np.ndarray:
        """Bool mask of the nodes with u > 0 (finite log u)."""
        return np.isfinite(self.log_u)

    @property
    def goal_mask(self) -> np.ndarray:
        """Bool mask of the goal nodes."""
        mask = np.zeros(self.occupied.shape, dtype=np.bool_)
        mask[tuple(self.goal_nodes.T)] = True
        return mask


def _paper(occ, per, goals, tol, max_sweeps, t0, token, cut_edges=None):
    tol = 1e-6 if tol is None else float(tol)
    max_sweeps = 200_000 if max_sweeps is None else int(max_sweeps)
    phi, sweeps, change = paper.gauss_seidel_phi(occ, per, goals, 1.0, tol, max_sweeps, stop=token.flag,
                                                 cut_edges=cut_edges)
    token.check()
    with np.errstate(divide="ignore"):
        log_u = np.log(np.clip(1.0 - phi, 0.0, None))
    log_u[occ] = -np.inf
    converged = change < tol
    left = "" if converged else f"stopped after {sweeps} sweeps at a change of {change:.2e} > {tol:g}"
    return Field(log_u, occ, per, goals, "gauss_seidel", sweeps, change, converged,
                 time.perf_counter() - t0, left)


def solve_field(occupied, periodic, goal_nodes, solver: str = DEFAULT_SOLVER, *, tol=None,
                max_sweeps=None, budget_s=None, cancel=None, cut_edges=None, token=None, guess=None) -> Field:
    """
    Solve the harmonic field (see the package doc).

    Parameters
    ----------
    occupied
        Bool array, any number of axes (each ≥ 2 nodes), True = obstacle.
    periodic
        One bool per axis.
    goal_nodes
        Int (k, ndim) goal node indices (free).
    solver
        ``"log_harmonic"`` (default) or ``"gauss_seidel"`` (``SOLVERS``).
    tol, max_sweeps
        gauss_seidel's stop (largest change per sweep, sweep cap).
    budget_s
        log_harmonic's wall-time budget, seconds (default ``DEFAULT_BUDGET_S``).
    cancel
        Optional callable; log_harmonic stops between bands once it returns true (a soft
        stop: the field is completed as when the budget ends).
    cut_edges
        Optional int (k, 2) flat index pairs of face-neighbour nodes whose edge is removed
        (a wall between them: the planner's repair of motions that collide).
    token
        The plan's termination token (``termination.Termination``; None: never set):
        polled inside the kernels.  Raises ``termination.Cancelled`` once it is set
        (no field: a partial one is never returned).
    guess
        Optional ``log_u`` of the grid's shape (no NaN): a field of the same grid and goal, e.g.
        the one before a repair cut a few edges.  log_harmonic starts its first band's
        iterations from it instead of from 0 (the later bands start from the bands before
        them, see :func:`.harmonic.solve`); the other solvers do not use it.  The field stops
        at the same residuals, so it is as precise; it is not bit for bit the field solved
        without a guess (equal to the solver's precision).

    Raises ValueError naming a malformed argument or an unknown solver.

    """
    if solver == "log_harmonic":
        _compile_once(np.ndim(occupied))     # the budget is the solve's: a first call's JIT compile is not
    t0 = time.perf_counter()
    if solver not in SOLVERS + INTERNAL_SOLVERS:
        raise ValueError(f"solver: unknown solver {solver!r}; expected one of {list(SOLVERS)}")
    occ, per, goals = validate_problem(occupied, periodic, goal_nodes)
    if guess is not None:
        guess = np.asarray(guess, dtype=float)
        if guess.shape != occ.shape:
            raise ValueError(f"guess: a log_u of the grid's shape {occ.shape} expected, got {guess.shape}")
        if np.isnan(guess).any():
            raise ValueError(f"guess: {int(np.isnan(guess).sum())} NaN value(s); a log_u holds numbers and -inf")
    token = Termination.of(token)
    token.check()
    if solver == "gauss_seidel":
        return _paper(occ, per, goals, tol, max_sweeps, t0, token, cut_edges)
    budget = DEFAULT_BUDGET_S if budget_s is None else float(budget_s)
    if not (math.isfinite(budget) and budget > 0.0):
        raise ValueError(f"budget_s: must be a positive number of seconds, got {budget_s!r}")
    graph = node_graph(occ, per, goals, cut_edges, token=token)
    if solver == "oracle":
        from . import oracle           # SciPy's sparse solver: the tests' and benches' reference only
        log_u = oracle.oracle_log_u(graph)
        token.check()
        stats = {"bands": 0}
        return Field(graph.scatter(log_u[:-1]), occ, per, goals, "oracle", 0, 0.0, True,
                     time.perf_counter() - t0, "", stats)
    if guess is not None:
        guess = np.append(guess.reshape(-1)[graph.order], -np.inf)     # the graph's nodes, the dummy last
    log_u, stats = harmonic.solve(graph, budget, cancel=cancel, token=token, guess=guess)
    left = stats.pop("left")
    return Field(graph.scatter(log_u[:-1]), occ, per, goals, "log_harmonic",
                 int(stats.pop("iterations")), float(stats.pop("residual")),
                 bool(stats.pop("converged")), time.perf_counter() - t0, left, stats)


#: What :func:`_compile_once` loaded in this process: "graph" (the node graph's route), 2, 3 (a dimension's cells)
_COMPILED: set = set()


def _compile_once(ndim: int) -> None:
    """
    Compile (or load) the kernels of the routes a solve on ``ndim`` axes takes, once per process.

    Compile (or load from numba's cache), once per process, the node graph's route on a tiny
    grid and, for a 2-D or a 3-D solve, its dimension's cells route on a small grid of that
    dimension (:data:`_WARM_PROBLEMS`: the 2-D one :mod:`.geometric`'s levels, the 3-D one
    :mod:`.structured`'s aggregation levels), so that no budget pays for it; and keep freed
    memory in the heap (:func:`keep_heap`), so that no solve page-faults its arrays in afresh.
    Only the solve's own dimension: a process that plans in 3-D (the CLI's first plan, whose
    kernel loads are most of its time) does not load the 2-D levels' kernels (measured: 51 kernels
    and 0.67-0.70 s of loads in ``spacerobot-plan`` on the paper 3-DOF scene, ``_gpcg`` and the
    geometric ``_levels`` 58-66 ms of them).  The warm-ups (:func:`warm_up`) load every route.
    """
    if "busy" in _COMPILED:
        return                                   # a warm-up's own solve
    kind = ndim if ndim in (2, 3) else None
    if "graph" in _COMPILED and (kind is None or kind in _COMPILED):
        return
    _COMPILED.add("busy")
    try:
        if "graph" not in _COMPILED:
            keep_heap()
            occ = np.zeros((6, 7), dtype=bool)
            occ[2, 1:5] = True
            solve_field(occ, (True, False), [(5, 6)], budget_s=600.0)
            _COMPILED.add("graph")
        if kind is not None and kind not in _COMPILED:
            occ, per, goal = _WARM_PROBLEMS[kind - 2]     # its first band on cells
            solve_field(occ, per, [goal], budget_s=600.0)
            _COMPILED.add(kind)
    finally:
        _COMPILED.discard("busy")


def _warm_large_band_steps(graph, known, log_u) -> None:
    """
    Load (or compile) the steps of a 3-D first band that only large bands take, on a small 3-D warm problem.

    Level 1 on its cells (``structured.coarse_layout``'s rule: from a band of about 30³ on) and the coarse
    levels built beside the fine level's layout (``multigrid.BESIDE_MIN_UNKNOWNS``: from about 70³), each
    a kernel that the warm problems' sizes do not reach: forced here (``route="structured"``,
    ``beside=True``), so that the first 3-DOF plan of a process at 36³ or 72³ does not load them in
    its middle (level 1's layout of a first paper plan at 36³ took 3.99 ms against 0.13 ms later).
    graph: the problem's node graph; known, log_u: its goal nodes known at log u 0, as a first band's.
    """
    sub, rhs, _ = harmonic._band_problem(graph.nbr, np.arange(graph.n_goal, graph.size, dtype=np.int64), known,
                                         log_u)
    # the band's coordinates as harmonic.solve passes a first band's: the rows after the goal's
    multigrid.solve(sub, graph.coords[graph.n_goal:], graph.shape, rhs, tol=harmonic.RESIDUAL_TOL,
                    route="structured", beside=True)


def _warm_problem(shape, block):
    occ = np.zeros(shape, dtype=bool)
    occ[block] = True
    return occ


#: (occupancy, periodic, goal) of the warm-ups: a 2-D and a 3-D grid with an obstacle block, each first
#: band on cells (:func:`_compile_once`): the 2-D one's the geometric levels (1.3 cells per unknown),
#: the 3-D one's the aggregation levels (2 009 unknowns, 1.57 cells per unknown)
_WARM_PROBLEMS = ((_warm_problem((40, 41), np.s_[10:20, 5:30]), (False, False), (39, 40)),
                  (_warm_problem((12, 13, 13), np.s_[4:6, 5:8, 5:8]), (True, False, False), (11, 12, 12)))


def warm_up() -> None:
    """Compile (or load from numba's cache) the field kernels on small 2-D and 3-D grids."""
    for occ, per, goal in _WARM_PROBLEMS:
        solve_field(occ, per, [goal])
        solve_field(occ, per, [goal], solver="gauss_seidel", max_sweeps=5)
    warm_up_rare()


def warm_up_rare() -> None:
    """
    Compile (or load) the field kernels that only some plans reach, on small 2-D and 3-D grids.

    The breadth-first search of the disconnected diagnosis and of a retried grid (with cut
    edges), a later band's window (a solve of one band does not reach it), the fill and the
    ascent repair of a field whose budget ran out, and a large 3-D band's steps
    (:func:`_warm_large_band_steps`): without this, the first plan that needs one loads or
    compiles it (a plan already late, for the budget's).
    """
    for occ, per, goal in _WARM_PROBLEMS:
        problem = validate_problem(occ, per, [goal])
        bfs(*problem)
        bfs(*problem, cut_edges=np.array([[0, 1]], dtype=np.int64))
        graph = node_graph(*problem)
        known = np.zeros(graph.size, np.bool_)
        known[:graph.n_goal] = True
        harmonic._steps_from_known(graph.nbr, np.arange(graph.n_goal, graph.size, dtype=np.int64), known,
                                   np.full(graph.size + 1, -1, np.int32), harmonic.WINDOW_STEPS)
        log_u = np.full(graph.size + 1, -np.inf)
        log_u[:graph.n_goal] = 0.0
        if len(occ.shape) == 3:
            _warm_large_band_steps(graph, known, log_u)
        # a field whose budget ran out (a loaded machine, a large grid): the rest filled below the known
        # nodes, then its ascent repaired
        harmonic._extend_below(log_u, known, graph.nbr, graph.n_goal, math.log(2 * graph.coords.shape[1]))
        harmonic._repair_ascent(log_u, graph.nbr, graph.n_goal, harmonic.REPAIR_STEP)


# --------------------------------------------------------------------------
# the heap
# --------------------------------------------------------------------------
#: :func:`keep_heap`: every block comes from the heap (glibc's ``mmap`` of blocks off: its
#: automatic threshold stops at 32 MiB, some releases refuse a higher one, and a 120³ solve has
#: blocks above it), and free memory at the heap's top is given back to the system only above
#: this many bytes (glibc's default: 128 KiB; mallopt takes a C int, so this is the most it
#: accepts): a 120³ solve frees about 400 MiB there, one on 4 million nodes (the default
#: ``planner.max_grid_nodes``) above 1 GiB.
TRIM_THRESHOLD_BYTES = 2**31 - 1
_M_TRIM_THRESHOLD = -1          # glibc's mallopt parameters (malloc.h)
_M_MMAP_MAX = -4
_GLIBC_HEAP_VARIABLES = ("MALLOC_MMAP_MAX_", "MALLOC_MMAP_THRESHOLD_", "MALLOC_TRIM_THRESHOLD_")
#: ... and their names in ``GLIBC_TUNABLES`` (``glibc.malloc.<name>=...``)
_GLIBC_HEAP_TUNABLES = ("glibc.malloc.mmap_max", "glibc.malloc.mmap_threshold", "glibc.malloc.trim_threshold")
_HEAP = {"kept": None}


def keep_heap() -> bool:
    """
    Keep freed memory in the process heap, so that a solve does not page-fault its arrays in afresh.

    Every solve allocates its arrays anew (the node graph, the band problems, the multigrid
    levels, the conjugate-gradient vectors: megabytes at 181², a hundred at 72³, several
    hundred at 120³).  glibc's malloc serves a block above its mmap threshold by a fresh
    ``mmap`` and gives it back to the system when it is freed, and trims the top of the heap
    once more than its trim threshold is free there; either way the next solve touches new
    pages, each a page fault with a zeroing (about 6 µs each on the project's virtual machine;
    ~900 a solve at 181², ~15 000 at 72³: a fifth to a third of the field's time).

    This serves every block from the heap (``mmap`` off for blocks: glibc's automatic mmap
    threshold stops at 32 MiB, and a 120³ solve has blocks above it, which faulted ~50 000
    pages a solve, a quarter of its time) and raises the trim threshold
    (``TRIM_THRESHOLD_BYTES``), once per process (the first log_harmonic solve does): freed
    memory stays in the heap for the next solve.  It is what real-time ROS 2 nodes do for the
    same reason; the cost is a process that keeps the heap of its largest solve (the threshold
    caps only what is freed at the heap's top; memory freed below a block still in use stays
    in the process however large).

    It serves the solves of the process's main thread (the node's planning process, the CLI,
    the benchmarks).  glibc gives every other thread that allocates an arena of its own, built
    of 64 MiB heaps that it maps and gives back whole, and maps a block above 64 MiB there
    whatever the setting: a solve on such a thread (``planner.separate_process: false``, a
    Dask worker's task) still faults its largest blocks afresh.

    A process-wide setting of the C library: applied only on glibc, and not where the user
    set glibc's own ``MALLOC_MMAP_MAX_``, ``MALLOC_MMAP_THRESHOLD_`` or
    ``MALLOC_TRIM_THRESHOLD_``, or their tunables in ``GLIBC_TUNABLES``.  Returns whether it
    is applied.
    """
    if _HEAP["kept"] is None:
        _HEAP["kept"] = _mallopt_thresholds()
    return _HEAP["kept"]


#: :func:`reserve_heap`'s bytes per grid node: what a process's first plan grew its kept heap by
#: (the paper scenes, ``planner.warm_up`` before: 104 at 181², 154 at 36³, 137 at 72³), with room.
HEAP_BYTES_PER_NODE = 192
#: :func:`reserve_heap` writes one byte in every block of this many bytes (a page: each one faulted in).
_PAGE_BYTES = 4096


def reserve_heap(n_nodes: int, max_nodes: int) -> int:
    """
    Grow the kept heap (:func:`keep_heap`) now by what a plan on ``n_nodes`` grid nodes allocates; return the bytes.

    A process's first plan on a grid allocates its arrays from a heap that has never held them:
    every page is faulted in and zeroed on its first write (about 2 µs each on the project's
    virtual machine: 3.9 ms of the first paper 3-DOF plan at 36³, 12.8 against 8.9 ms; 18 ms at
    72³). A block of ``HEAP_BYTES_PER_NODE`` bytes a node, written once a page and freed, stays
    in the heap (the trim threshold), so that plan finds its pages in place: what a warm-up is
    for. 0 (nothing done) for a grid above ``max_nodes`` (``planner.max_grid_nodes``: its plans are
    refused before they allocate), where the heap is not kept (:func:`keep_heap` not applied by a solve
    before: another C library, a user's own malloc settings, no log_harmonic solve yet) or the
    block would be above half the trim threshold (about 5.6 million nodes: freed on top of what
    the heap's top already holds free, it could pass the threshold and go back to the system).
    """
    nbytes = HEAP_BYTES_PER_NODE * int(n_nodes)
    if _HEAP["kept"] is not True or nbytes <= 0 or n_nodes > max_nodes or nbytes > TRIM_THRESHOLD_BYTES // 2:
        return 0
    block = np.empty(nbytes, np.uint8)
    block[::_PAGE_BYTES] = 0
    del block
    return nbytes


def _mallopt_thresholds() -> bool:
    if not sys.platform.startswith("linux"):
        return False
    if any(name in os.environ for name in _GLIBC_HEAP_VARIABLES):
        return False
    tunables = os.environ.get("GLIBC_TUNABLES", "")
    if any(name in tunables for name in _GLIBC_HEAP_TUNABLES):
        return False
    try:
        libc = ctypes.CDLL(None)           # the process's own symbols: the C library it runs on
        mallopt = libc.mallopt
        libc.gnu_get_libc_version          # glibc only
    except (OSError, AttributeError):
        return False
    mallopt.argtypes = (ctypes.c_int, ctypes.c_int)
    mallopt.restype = ctypes.c_int
    return bool(mallopt(_M_MMAP_MAX, 0)) and bool(mallopt(_M_TRIM_THRESHOLD, TRIM_THRESHOLD_BYTES))
