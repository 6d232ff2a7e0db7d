"""
The planning worker: runs the planning core for the node, in a child process by default.

No rclpy here, and the planning process imports none of it: it is started as
``python -c "...; from spacerobot_planner.worker import child_main; child_main(fd)"``
(a plain subprocess, not multiprocessing's spawn, which would re-import the caller's
``__main__``), so it loads the planning core (numpy, numba, the pipeline) and nothing else.

Messages are small dataclasses, pickled over a socketpair:

- node → process: a :class:`PlanJob`, :class:`Cancel` (a job number), ``None`` (quit);
- process → node: :class:`ReplanSeed` (once, during the warm-up: a coarse plan the node plans
  again from its C-space and field, :class:`HybridBackend`), :class:`Ready` (once, after the JIT
  warm-up), :class:`Progress`
  (stage and fraction while a job runs, when the job asks for its stages) and one outcome per
  job: :class:`PlanDone`
  (a ``PlanResult``, ok or not), :class:`PlanError` (no plan was attempted: e.g. the
  target has no capture posture) or :class:`PlanCrash` (an exception, with its traceback).

The node's default backend, :class:`HybridBackend`, plans the replans the C-space and field the
process sent last answer in the calling thread itself, from those alone, and the rest here.

Cancel stops the work, not the process: the planning process holds one termination
token (``termination.Termination``, a flag array numba kernels read without the GIL);
its reader thread raises it when a Cancel for the running job arrives, and the core polls
it inside its long loops (C-space rows, the field's CG iterations and sweeps, descent
candidates, smoothing rounds).  The stage returns at its next poll, stores nothing
partial, and the job answers ``PlanDone`` with a ``cancelled`` result; the process and its
caches (every complete C-space and field) stay for the next job.

Crash path only: a stage that does not answer the token within ``CANCEL_GRACE_S``
(seconds: never reached by a stage that polls, even on a loaded machine) has its process
killed and replaced (caches lost), logged as such, and the job reports ``cancelled``.

Test aids: ``PlanJob.stall_s`` makes the plan spend that long in ``stall_stage``:
``"start"`` (before planning), ``"cspace"`` or ``"field"`` (inside the stage, before its
kernels, when not cached), ``"descent"`` or ``"smoothing"``; with ``stall_polls`` (the
default) the stall answers the token like the kernels do, without it the stall is a plain
sleep that no cancel shortens (a stage that does not poll: the crash path).
"""

from __future__ import annotations

import gc
import os
import pickle
import queue
import threading
import time
import traceback
import weakref
from dataclasses import dataclass, replace
from dataclasses import field as dc_field
from typing import Callable

import numpy as np

from .adapters import warm_up as warm_up_chain
from .config import load_scenario
from .cores import cpu_limit, limit_text, threading_layer
from .jit_cache import start_numba
from .offline import plan_offline
from .free_floating_capture import captures_free_floating
from .free_floating_capture import warm_up as free_floating_warm_up
from .contact import warm_up as contact_warm_up
from .smoothing import warm_up as smoothing_warm_up
from .pipeline import NotCached, grid_margins
from .planner import Planner, warm_up_unreached
from .field import reserve_heap, warm_up_rare as field_warm_up_rare
from .termination import Termination, stall

__all__ = ["PlanJob", "Cancel", "Ready", "ReplanSeed", "Progress", "PlanDone", "PlanError", "PlanCrash",
           "ProcessBackend", "HybridBackend", "ThreadBackend", "make_backend", "compile_package", "STAGE_ORDER"]

#: the folder holding the ``spacerobot_planner`` package this module belongs to
_PACKAGE_PARENT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

#: the stages reported as Progress, in order (the core's stage names, then the node's)
STAGE_ORDER = ("queued", "cspace", "field", "descent", "smoothing", "verify", "trajectory")


# ================================================================== messages
@dataclass(frozen=True, eq=False)
class PlanJob:
    """
    One request for the planning core (picklable).

    scene, grid: ``scene.Scene`` and ``cspace.GridSpec``; start_rad: (dof,) planned
    joints, rad; joint_goal: (dof,) rad or None (then the goal is the target's IK);
    stall_s, stall_stage, stall_polls: test aid (see the module docstring), seconds;
    stages: False reports only that the job began (:func:`began`, the backend's own), not
    each stage (no one follows them: each is a message the plan pays for, and a wake of the
    node's waiting thread in the middle of the plan); start_tangent: (dof,) the direction
    the arm moves in at the start, or None (``Planner.plan``); scenario_settings: the
    scenario's ``(planner_settings, acs, masses, joint_limits)`` (``Planner.set_settings``: a
    runtime change of ``planner.*``, ``grasp.*``, ``acs.*``, ``dynamics.*`` or ``trajectory.*``
    reaches the planning process with its next job), None: the planner's own kept.
    """

    gen: int
    scene: object
    grid: object
    solver: str
    field_tolerance: float
    max_grid_nodes: int
    start_rad: np.ndarray
    joint_goal: np.ndarray | None
    stall_s: float = 0.0
    field_budget_s: float = 5.0
    max_threads: int = 0
    threads_follow_load: bool = True
    stall_stage: str = "start"
    stall_polls: bool = True
    stages: bool = True
    start_tangent: np.ndarray | None = None
    scenario_settings: tuple | None = None

    @classmethod
    def for_scenario(cls, gen: int, scenario, start_rad, joint_goal=None, start_tangent=None, **test) -> "PlanJob":
        """
        Return the job of planning ``scenario`` from ``start_rad``.

        Its scene and grid, its solver, tolerance, budget, grid limit and threads
        (``Scenario.planner_settings``), and its settings as a whole (``scenario_settings``);
        ``test``: the stall fields.
        """
        s = scenario.planner_settings
        return cls(gen=gen, scene=scenario.scene, grid=scenario.grid, solver=s.solver,
                   field_tolerance=float(s.field_tolerance), max_grid_nodes=int(s.max_grid_nodes),
                   start_rad=np.asarray(start_rad, dtype=float), joint_goal=joint_goal,
                   field_budget_s=float(s.field_budget_s), max_threads=int(s.max_threads), start_tangent=start_tangent,
                   threads_follow_load=bool(s.threads_follow_load),
                   scenario_settings=(s, scenario.acs, scenario.masses, scenario.joint_limits),
                   **test)


@dataclass(frozen=True)
class Cancel:
    gen: int                    # cancel this job (and every older one)


@dataclass(frozen=True)
class Ready:
    warm_up_s: float            # JIT warm-up (compile or cache load) of the process
    modules: tuple = ()         # top-level names in the process's sys.modules (what it loaded)
    #: the objects the garbage collector walks, and those it leaves alone (frozen), once ready
    gc_tracked: int = -1
    gc_frozen: int = -1
    #: numba's threading layer of the process ("" where no parallel loop ran yet), and its CPU
    #: limit in whole CPUs (None: none; ``cores.cpu_limit``)
    threading_layer: str = ""
    cpu_limit: int | None = None


@dataclass(frozen=True, eq=False)
class ReplanSeed:
    """
    A replan from the caches on a coarse copy of the scenario: what the node needs to plan it.

    Sent by the planning process once its warm-up's coarse plan succeeded, before its
    :class:`Ready`: the node loads its replans' kernels meanwhile (:meth:`HybridBackend.warm_up_here`).

    ``grid``: the copy's (``cspace.GridSpec``); ``cspace``, ``field``: (key,
    object) of the planning process's coarse plan (``Planner.cache_key_of``); ``start_rad``,
    ``goal_rad``: (dof,) a start on that plan's path and its goal, rad.
    """

    grid: object
    cspace: tuple
    field: tuple
    start_rad: np.ndarray
    goal_rad: np.ndarray


@dataclass(frozen=True)
class Progress:
    gen: int
    stage: str                  # one of STAGE_ORDER
    fraction: float             # 0..1, the share of the stages done
    note: str = ""              # "stall": a test stall (PlanJob.stall_s) has begun in this stage


@dataclass(frozen=True, eq=False)
class PlanDone:
    gen: int
    result: object              # planner.PlanResult (ok or a failure code)
    left_out: tuple = ()        # "cspace"/"field": the same objects as last sent (see _strip_sent)
    #: the planning process after the job: pid, jobs, cancelled (counts) and its cache
    #: sizes (cspaces, fields, body_tables); from the planning process also when it had the job
    #: and its outcome (``job_received_s``, ``job_answered_s``: ``time.perf_counter()`` s, the
    #: clock every process of the machine shares)
    stats: dict = dc_field(default_factory=dict)
    #: ("cspace"/"field", its key in the planning process's caches) of each one sent (not left
    #: out) that is cached there (``Planner.cache_key_of``): what a :class:`HybridBackend` holds
    keys: tuple = ()


@dataclass(frozen=True)
class PlanError:
    gen: int
    code: str                   # a planner code (planner.CODES)
    reason: str


@dataclass(frozen=True)
class PlanCrash:
    gen: int
    what: str                   # "ExceptionType: message"
    traceback: str              # formatted where it happened


# ================================================================== running one job
def _progress_of(text: str):
    """(stage now running, fraction) from one of the core's progress lines, or None."""
    done = {"goal": "cspace", "cspace": "field", "field": "descent", "smoothing": "verify"}
    for prefix, nxt in done.items():
        if text.startswith(prefix):
            return nxt, STAGE_ORDER.index(nxt) / len(STAGE_ORDER)
    return None


#: planner -> (the settings key of the last job applied to it, the planner's state after it: see
#: :func:`_state`)
_APPLIED: "weakref.WeakKeyDictionary" = weakref.WeakKeyDictionary()


def _apply_settings(planner, job: PlanJob) -> None:
    """
    Give ``planner`` the job's scene, grid, scenario settings, solver and limits.

    A job with the settings of the last one applied (a replan: the same bytes) changes
    nothing: the scene's checker and the target's goal (``Planner.capture_goal``) stay.
    """
    key = pickle.dumps((job.scene, job.grid, job.solver, job.field_tolerance, job.field_budget_s,
                        job.max_grid_nodes, job.max_threads, job.threads_follow_load, job.scenario_settings),
                       protocol=pickle.HIGHEST_PROTOCOL)
    held = _APPLIED.get(planner)
    if held is not None and held == (key, _state(planner)):
        return
    _APPLIED.pop(planner, None)
    if job.scenario_settings is not None:
        planner.set_settings(*job.scenario_settings)
    planner.set_scene(job.scene)
    if planner.scenario.grid != job.grid:
        planner.set_grid(job.grid)
    if (planner.solver, planner.field_tolerance, planner.settings.field_budget_s) != \
            (job.solver, job.field_tolerance, job.field_budget_s):
        planner.set_solver(job.solver, job.field_tolerance, job.field_budget_s)
    planner.configure(max_grid_nodes=job.max_grid_nodes, max_threads=job.max_threads,
                      threads_follow_load=job.threads_follow_load)
    _APPLIED[planner] = (key, _state(planner))


def _state(planner) -> tuple:
    """Return what a change of the planner outside a job changes: its scenario (by identity), solver, limits."""
    return (planner.scenario, planner.solver, planner.field_tolerance, planner.settings.field_budget_s,
            planner.max_grid_nodes, planner.settings.max_threads, planner.settings.threads_follow_load)


STALL_STAGES = ("start", "cspace", "field", "descent", "smoothing")


def began(job: PlanJob) -> Progress:
    """
    Return the Progress saying that ``job`` has started: stage "cspace".

    The backend reports it itself once the job is handed over (sent to the planning process,
    or started in the thread), before any of :func:`run_job`'s own: the planning process sends
    nothing for a job without ``stages`` until its outcome (a message from it in the middle of
    a 1 ms replan woke the node's waiting thread only to be told so: ``bench latency``'s round
    trip 3.0 -> 2.5 ms median).
    """
    return Progress(job.gen, "cspace", STAGE_ORDER.index("cspace") / len(STAGE_ORDER))


def run_job(planner, job: PlanJob, cancel, progress: Callable[[Progress], None] | None = None,
            cached_only: bool = False):
    """
    Return PlanDone or PlanError for one job (exceptions propagate: the backends catch them).

    ``cancel``: the job's termination token (``termination.Termination``, or anything
    with ``is_set()``).  ``progress`` gets the stages as they begin (``job.stages``) and a test
    stall's start, not that the job began (:func:`began`: the backend's).  ``cached_only``: the
    plan from the planner's caches alone (``Planner.plan``; ``pipeline.NotCached`` propagates).
    """
    def say(text):
        p = _progress_of(text)
        if p is not None and progress is not None and job.stages:
            progress(Progress(job.gen, *p))

    def stalling(stage):
        if progress is not None:
            stage = "cspace" if stage == "start" else stage
            progress(Progress(job.gen, stage, STAGE_ORDER.index(stage) / len(STAGE_ORDER), "stall"))

    token = Termination.of(cancel)
    if job.stall_stage not in STALL_STAGES:
        raise ValueError(f"stall_stage: expected one of {STALL_STAGES}, got {job.stall_stage!r}")
    if job.stall_stage == "start" and job.stall_s > 0:
        stalling("start")
        stall(token, job.stall_s, job.stall_polls)
    _apply_settings(planner, job)
    goal = job.joint_goal
    if goal is None and not captures_free_floating(planner.scenario, False):   # free floating: the pipeline's
        try:
            goal = planner.goal_from_target()
        except ValueError as e:
            return PlanError(job.gen, "goal_unreachable", f"target: {e}")
    if job.stall_stage != "start" and job.stall_s > 0:
        planner.test_stall = (job.stall_stage, float(job.stall_s), bool(job.stall_polls), stalling)
    try:
        return PlanDone(job.gen, planner.plan(job.start_rad, goal, cancel=token, progress=say,
                                              start_tangent=job.start_tangent, cached_only=cached_only))
    finally:
        planner.test_stall = None


def _crash(gen: int, e: BaseException) -> PlanCrash:
    return PlanCrash(gen, f"{type(e).__name__}: {e}", traceback.format_exc())


def _strip_sent(done: PlanDone, sent: dict, planner=None) -> PlanDone:
    """
    Leave out the C-space and field the node already holds (the objects last sent); name the keys of the others.

    A replan from cache would otherwise pickle them again (~0.5 MB at 36³).  ``planner``: whose
    caches name the keys of those sent (``PlanDone.keys``).
    """
    res = done.result
    left_out, keys = [], []
    for name in ("cspace", "field"):
        obj = getattr(res, name, None)
        if obj is None:
            continue
        if sent.get(name) is obj:
            left_out.append(name)
        else:
            sent[name] = obj
            key = None if planner is None else planner.cache_key_of(obj)
            if key is not None:
                keys.append((name, key))
    if not left_out and not keys:
        return done
    return PlanDone(done.gen, replace(res, **{n: None for n in left_out}), tuple(left_out), done.stats, tuple(keys))


class _GenCancel(Termination):
    """
    The planning process's termination token: set while the running job is cancelled.

    Job ``gen`` is cancelled once a Cancel for it (or a newer job) arrived, before or
    while it runs.  The main thread calls :meth:`start` for each job, the reader thread
    :meth:`cancel_upto`; a lock keeps a late Cancel of a finished job off the next one.
    """

    def __init__(self):
        super().__init__()
        self._gen_lock = threading.Lock()
        self.cancelled_upto = 0
        self.gen = 0

    def start(self, gen: int) -> None:
        with self._gen_lock:
            self.gen = gen
            self.clear()
            if self.cancelled_upto >= gen:
                self.set()

    def cancel_upto(self, gen: int) -> None:
        with self._gen_lock:
            self.cancelled_upto = max(self.cancelled_upto, gen)
            if self.cancelled_upto >= self.gen:
                self.set()

    def forget(self) -> None:
        """Drop the cancels so far (a new numbering of jobs: another session's)."""
        with self._gen_lock:
            self.cancelled_upto = 0


# ================================================================== warm-up
#: the warm-up also plans the configured target on the configured grid up to this size
WARM_FULL_GRID_MAX_NODES = 250_000
WARM_CELLS = 6


def warm_up(planner, cells: int = WARM_CELLS, full_grid_max_nodes: int = WARM_FULL_GRID_MAX_NODES,
            coarse_done: Callable | None = None) -> dict:
    """
    Compile (or load from numba's cache) the kernels of the default route only.

    Plans on a ``cells``-per-joint copy of the planner's scenario with its solver (from
    seeded random postures until one plan succeeds), then, when the configured grid has
    at most ``full_grid_max_nodes`` nodes, plans the configured target once on it with
    ``planner`` itself: the route a grid of that size takes (e.g. multigrid in 2-D) is
    compiled, and its C-space and field stay in ``planner``'s caches.  Kernels of other
    solvers are compiled when first used.  The heap a plan on the configured grid fills is
    faulted in either way (``field.reserve_heap``).  Returns seconds per phase.
    ``coarse_done(coarse planner, its plan)`` is called once a coarse plan succeeded.
    """
    t0 = time.perf_counter()
    sc = planner.scenario
    coarse, first = _coarse_plan(planner, cells)
    if coarse_done is not None and first is not None:
        coarse_done(coarse, first)
    warm_up_unreached(coarse.scenario)
    field_warm_up_rare()        # nor does a coarse plan need a breadth-first search or a second band
    free_floating_warm_up(sc)   # a free-floating capture's kernels, where the scenario plans one (no plan here does)
    reserve_heap(sc.grid.n_nodes, planner.settings.max_grid_nodes)    # the heap a plan on the grid fills
    out = {"coarse_s": time.perf_counter() - t0}
    if first is not None and sc.grid.n_nodes <= full_grid_max_nodes and sc.scene.target is not None:
        t1 = time.perf_counter()
        try:
            planner.plan(first.start_rad, planner.goal_from_target())
        except ValueError:          # no capture posture for the configured target: nothing to warm
            pass
        out["full_grid_s"] = time.perf_counter() - t1
    out["total_s"] = time.perf_counter() - t0
    return out


def _coarse_plan(planner, cells: int):
    """
    Plan once on a ``cells``-per-joint copy of ``planner``'s scenario (its solver), from seeded random postures.

    Returns (the coarse planner, its first plan that succeeded (None: none of 32 did)).
    """
    sc = planner.scenario
    coarse = Planner(replace(sc, grid=sc.grid.with_cells(cells)), solver=planner.solver,
                     field_tolerance=planner.field_tolerance)
    rng = np.random.default_rng(0)
    lo, hi = sc.robot.planned_lower_rad, sc.robot.planned_upper_rad
    for _ in range(32):
        a, b = rng.uniform(lo, hi, size=(2, sc.robot.dof))
        res = coarse.plan(a, b)
        if res.ok:
            return coarse, res
    return coarse, None


def replan_seed(coarse, first) -> ReplanSeed | None:
    """
    Return the :class:`ReplanSeed` of the coarse planner ``coarse``'s ok plan ``first``.

    Its grid, C-space and field, a start in the middle of its path, its goal.  None where the
    planner no longer caches them.
    """
    entries = [(coarse.cache_key_of(obj), obj) for obj in (first.cspace, first.field)]
    if any(key is None for key, _ in entries):
        return None
    return ReplanSeed(coarse.scenario.grid, *entries, first.path_rad[len(first.path_rad) // 2], first.goal_rad)


def warm_up_replans(planner, seed: ReplanSeed | None):
    """
    Load the kernels of a replan from the caches in this process: the planning process's ``seed``, a start in contact.

    The smoothing's own warm-up as well: the seed's path may need no spline (the first joined
    replan in the node loaded its kernel, about 11 ms, before).

    For :class:`HybridBackend`'s planner ``planner`` (its scenario, solver and tolerance), in
    the node's process, from the C-space and field of the seed: none is built here (no C-space or
    field kernel loaded, no numba thread pool started in the node's process).  Returns the
    seed's plan (None: no seed; a ``PlanResult``, or the ``pipeline.NotCached`` raised).
    """
    sc = planner.scenario
    contact_warm_up(sc.robot, sc.scene)
    smoothing_warm_up()         # the spline's kernels: a coarse seed's path may need none (two knots)
    if seed is None:
        return None
    coarse = Planner(replace(sc, grid=seed.grid), solver=planner.solver,
                     field_tolerance=planner.field_tolerance, trajectory=False)
    coarse.hold_only(seed.cspace, seed.field)
    try:
        return coarse.plan(seed.start_rad, seed.goal_rad, cached_only=True)
    except NotCached as e:      # (a seed of another scene or solver: the kernels up to there are loaded)
        return e


# ================================================================== the planning process
def child_main(fd: int) -> None:
    """
    Run the planning process: one Planner (caches kept between jobs), jobs over a socket.

    The main thread plans, and reads the socket itself while no job runs, so a job begins in the
    thread that received it (:class:`_Listener`: a handover to a reader thread cost each job a
    thread's wake, about 0.3 ms after an idle while); while a job runs, a reader thread takes the
    cancels (and queues what else comes) until the main thread wants the socket back.
    """
    import signal
    from multiprocessing.connection import Connection

    signal.signal(signal.SIGINT, signal.SIG_IGN)        # the node decides when to stop
    start_numba()                   # a process of its own: cached kernels without their linking bitcode, no BLAS check
    conn = Connection(fd)
    scenario, solver, field_tolerance = conn.recv()
    planner = Planner(scenario, solver=solver, field_tolerance=field_tolerance, trajectory=False)

    def send_seed(coarse, first):
        seed = replan_seed(coarse, first)
        if seed is not None:
            conn.send(seed)

    # compile / load the kernels before saying "ready"; the coarse plan's seed at once (the node
    # loads its replans' kernels meanwhile)
    t_warm = warm_up(planner, coarse_done=send_seed)["total_s"]
    # what start-up made (modules, kernels, the warm-up's objects) lives as long as the process:
    # out of the collector's reach, a full collection in the middle of a plan walks only what
    # the plans made since (about 70 ms -> under 1 ms at the 3-DOF grid; the node's own
    # process does the same in its configure).  This process hosts nothing else.
    gc.collect()                  # garbage is freed first, not frozen with the rest
    gc.freeze()
    cancel = _GenCancel()
    send_lock = threading.Lock()

    def send(msg) -> bool:
        try:
            with send_lock:
                conn.send(msg)
            return True
        except (OSError, ValueError):
            return False

    listener = _Listener(conn, cancel)
    sent: dict = {}
    import sys
    send(Ready(t_warm, tuple(sorted({m.split(".")[0] for m in sys.modules})), len(gc.get_objects()),
               gc.get_freeze_count(), threading_layer(), cpu_limit()))
    counts = {"jobs": 0, "cancelled": 0}
    while True:
        job = listener.next_job()
        got_s = time.perf_counter()
        if job is None:
            return
        cancel.start(job.gen)
        listener.listen()
        try:
            out = run_job(planner, job, cancel, send)
        except Exception as e:     # noqa: BLE001 - report to the node, keep serving
            out = _crash(job.gen, e)
        done_s = time.perf_counter()
        counts["jobs"] += 1
        if isinstance(out, PlanDone):
            counts["cancelled"] += out.result.code == "cancelled"
            out = replace(out, stats={**_process_stats(planner, counts), "job_received_s": got_s,
                                      "job_answered_s": done_s})
            out = _strip_sent(out, sent, planner)
        ok = send(out)
        listener.stop_listening()
        if not ok:
            return


class _Listener:
    """
    Who reads the planning process's socket: the main thread while it waits for a job, a reader thread during one.

    :meth:`next_job` returns the next job (None: quit): one the reader queued during the last
    job, else one read by the calling thread, the cancels before it applied.  Each job is one
    turn of the reader's: :meth:`listen` starts it (the reader takes the messages while the job
    runs: a Cancel cancels at once, anything else is queued), :meth:`stop_listening` ends it once
    the job's outcome is sent (one byte on a pipe wakes the reader out of its wait; the reader
    then says it is out of the socket).  Both hand-overs are counted (semaphores, one byte a
    turn), so a turn that starts and ends before the reader thread runs is still taken in
    order, and no wake is lost or left over.  The end of the socket (end of file, a failure,
    a message that cannot be read) counts as ``None``; after it the reader only answers its
    turns.
    """

    def __init__(self, conn, cancel: _GenCancel):
        self.conn, self.cancel = conn, cancel
        self.queued: queue.SimpleQueue = queue.SimpleQueue()
        self._turns = threading.Semaphore(0)        # one release per job: the reader's turn begins
        self._out = threading.Semaphore(0)          # one release per turn: the reader is out of the socket
        self._wake_r, self._wake_w = os.pipe()      # one byte per turn: it ends
        threading.Thread(target=self._reader, daemon=True, name="planning-reader").start()

    def _take(self):
        """Read one message; None at the end of the socket (or when a message cannot be read)."""
        try:
            return self.conn.recv()
        except Exception:       # noqa: BLE001 - EOFError, OSError, a message that cannot be unpickled
            return None

    def _apply(self, msg) -> bool:
        """Apply at once what a message says of the jobs (a Cancel; the end: all cancelled); tell if it is a Cancel."""
        if isinstance(msg, Cancel):
            self.cancel.cancel_upto(msg.gen)
            return True
        if msg is None:
            self.cancel.cancel_upto(1 << 62)
        return False

    def next_job(self):
        while True:
            try:
                msg = self.queued.get_nowait()
            except queue.Empty:
                msg = self._take()
            if not self._apply(msg):         # (a queued one again: the same cancels)
                return msg

    def listen(self) -> None:
        self._turns.release()

    def stop_listening(self) -> None:
        os.write(self._wake_w, b"x")
        self._out.acquire()

    def _reader(self):
        from multiprocessing.connection import wait
        ended = False
        while True:
            self._turns.acquire()
            while True:
                ready = wait([self._wake_r] if ended else [self.conn, self._wake_r])
                if not ended and self.conn in ready:
                    msg = self._take()
                    if not self._apply(msg):      # anything but a Cancel waits for the job's end
                        self.queued.put(msg)
                        ended = msg is None
                if self._wake_r in ready:
                    os.read(self._wake_r, 1)
                    break
            self._out.release()


def _process_stats(planner, counts: dict) -> dict:
    return {"pid": os.getpid(), **counts, **planner.cache_sizes()}


# ================================================================== backends (node side)
class ThreadBackend:
    """
    Plans in the calling (worker) thread: no process (``planner.separate_process:=false``).

    A cancel of job ``gen`` sets the plan's termination token for that job and every older one,
    before or while it runs (:class:`_GenCancel`, the planning process's): the stage stops at its
    next poll.  (A plain token cleared when a job began lost a cancel that came between the
    session taking the request and the job starting: a superseded plan then ran to its end.)  A job
    numbered below the one before starts a new numbering (the backend handed to another session,
    whose jobs count from 1 again): the cancels before it are forgotten.
    """

    def __init__(self, scenario, log=None, info=None, solver: str | None = None,
                 field_tolerance: float | None = None):
        self.planner = Planner(scenario, solver=solver, field_tolerance=field_tolerance, trajectory=False)
        self._cancel = _GenCancel()
        self._last_gen = 0
        self.pid = None
        self._counts = {"jobs": 0, "cancelled": 0}

    def wait_ready(self, timeout_s: float | None = None) -> float | None:
        return 0.0

    def warm_up_here(self, timeout_s: float | None = None):
        """Load this process's kernels before the first plan (none: the first plan loads them)."""
        return None

    def run(self, job: PlanJob, progress=None):
        if job.gen < self._last_gen:
            self._cancel.forget()
        self._last_gen = job.gen
        self._cancel.start(job.gen)
        try:
            if progress is not None:
                progress(began(job))
            out = run_job(self.planner, job, self._cancel, progress)
        except Exception as e:     # noqa: BLE001 - report to the node, keep serving
            return _crash(job.gen, e)
        self._counts["jobs"] += 1
        if isinstance(out, PlanDone):
            self._counts["cancelled"] += out.result.code == "cancelled"
            out = replace(out, stats=_process_stats(self.planner, self._counts))
        return out

    def cancel(self, gen: int) -> None:
        self._cancel.cancel_upto(gen)

    def close(self) -> None:
        self._cancel.cancel_upto(1 << 62)


class ProcessBackend:
    """
    Plans in a child process; the calling thread waits on a socket (GIL free).

    A cancel reaches the child's termination token: the stage stops at its next poll,
    the job answers a ``cancelled`` PlanDone and the process keeps its caches.  A child
    that died is replaced by a fresh one at the next :meth:`run`; one that does not
    answer a cancel within ``cancel_grace_s`` (the crash path: a stage that does not poll)
    is killed and replaced, with a warning.
    """

    CLOSE_GRACE_S = 0.2         # close(): an idle child exits by itself within this
    #: cancel(): a child whose stage has not answered within this is killed and replaced.
    #: Polling stages answer within a kernel step (milliseconds, see ``bench cancel``); this
    #: is only for one that does not, so it is long enough never to fire on a loaded machine.
    CANCEL_GRACE_S = 5.0

    def __init__(self, scenario, log=None, info=None, solver: str | None = None,
                 field_tolerance: float | None = None):
        """
        Start the planning process for ``scenario`` (it warms up meanwhile: see :meth:`wait_ready`).

        log: callable for warnings (a child that died); info: for progress (warm-up); solver,
        field_tolerance: what the warm-up compiles (None: the scenario's, ``Scenario.planner_settings``).
        """
        self._scenario = scenario
        self._solver = (solver, None if field_tolerance is None else float(field_tolerance))
        self._log = log
        self._info = info
        self._send_lock = threading.Lock()
        self._proc_lock = threading.Lock()
        self._closed = False
        self._cancel_at = {}        # gen -> monotonic time of its cancel
        self.cancel_grace_s = self.CANCEL_GRACE_S
        self._spawn()

    @property
    def pid(self) -> int:
        return self.proc.pid

    def warm_up_here(self, timeout_s: float | None = None):
        """Load the kernels this (the node's) process plans with (none: the planning process plans)."""
        return None

    def attach_logs(self, log=None, info=None) -> None:
        """Send this backend's warnings to ``log``, its progress to ``info`` from now on (a process started ahead)."""
        self._log, self._info = log, info

    @property
    def ready(self) -> Ready | None:
        """Return the current process's Ready message (None before its warm-up ended)."""
        return self._ready

    def start_process(self, fd: int):
        """
        Start a planning process that runs :func:`child_main` on socket ``fd``; return its handle.

        The handle has ``subprocess.Popen``'s ``pid``, ``returncode``, ``poll``, ``wait``,
        ``terminate`` and ``kill``.  A fresh interpreter; a subclass may start it otherwise.
        """
        import subprocess
        import sys
        # the child imports this very copy of the package (first on its sys.path), not one
        # that `python -c` would find in the working directory (e.g. a source tree)
        return subprocess.Popen(
            [sys.executable, "-c", f"import sys; sys.path.insert(0, {_PACKAGE_PARENT!r}); "
             "from spacerobot_planner.jit_cache import import_numba; import_numba(); "
             "from spacerobot_planner.worker import child_main; child_main(int(sys.argv[1]))", str(fd)],
            pass_fds=(fd,), stdin=subprocess.DEVNULL)

    def _spawn(self):
        import socket
        from multiprocessing.connection import Connection
        parent, child = socket.socketpair()
        self.conn = Connection(parent.detach())
        self.proc = self.start_process(child.fileno())
        child.close()
        self.conn.send((self._scenario, *self._solver))
        self._ready = None          # Ready once received
        self._seed = None           # its ReplanSeed once received (before Ready)
        self._held = {}             # C-space / field this child sent last

    def _respawn(self, why: str | None):
        with self._proc_lock:
            if self._closed:
                return
            if why is not None and self._log is not None:
                self._log(f"planning process {self.proc.pid} {why}: starting a new one")
            if self.proc.poll() is None:
                self.proc.kill()
                self.proc.wait()
            self.conn.close()
            self._spawn()

    def _recv(self, gen: int | None = None):
        """
        Return the next message; None when closed; raises RuntimeError if the child died.

        With ``gen``: returns PlanDone(cancelled) once its cancel is overdue.
        """
        while not self._closed:
            if self.conn.poll(0.02):
                return self.conn.recv()
            if self.proc.poll() is not None:
                raise RuntimeError(f"planning process exited (code {self.proc.returncode})")
            t = self._cancel_at.get(gen)
            if t is not None and time.monotonic() - t > self.cancel_grace_s:
                self._respawn(f"did not answer a cancel within {self.cancel_grace_s:g} s (its stage does not "
                              "poll the termination token): killing it, its C-space and field caches are lost")
                return _Overdue()
        return None

    def wait_ready(self, timeout_s: float | None = None) -> float | None:
        """Block until the child has warmed up; the warm-up seconds (None: closed or timeout)."""
        self._start_up(timeout_s)
        return None if self._ready is None else self._ready.warm_up_s

    def _start_up(self, timeout_s: float | None, seed: bool = False) -> None:
        """Read the child's warm-up messages until its Ready (``seed``: or its ReplanSeed), closed or ``timeout_s``."""
        t0 = time.monotonic()
        while not self._closed and self._ready is None and not (seed and self._seed is not None):
            if self.conn.poll(0.05):
                msg = self.conn.recv()
                if isinstance(msg, ReplanSeed):
                    self._seed = msg
                if isinstance(msg, Ready):
                    self._ready = msg
                    if self._info is not None:
                        self._info(f"planning process {self.proc.pid} ready: JIT warm-up {msg.warm_up_s:.2f} s"
                                   + (f", threading layer {msg.threading_layer}" if msg.threading_layer else "")
                                   + limit_text(msg.cpu_limit))
                continue
            if self.proc.poll() is not None:
                raise RuntimeError(f"planning process exited during warm-up (code {self.proc.returncode})")
            if timeout_s is not None and time.monotonic() - t0 > timeout_s:
                return

    def _unpack(self, done: PlanDone) -> PlanDone:
        res = done.result
        if done.left_out:
            res = replace(res, **{name: self._held[name] for name in done.left_out})
        for name in ("cspace", "field"):
            if getattr(res, name, None) is not None:
                self._held[name] = getattr(res, name)
        return PlanDone(done.gen, res, (), done.stats, done.keys)

    def run(self, job: PlanJob, progress=None):
        """
        Return the outcome of ``job`` (PlanDone/PlanError/PlanCrash), or None when closed.

        ``progress`` gets the child's Progress messages for this job.
        """
        with self._proc_lock:
            dead = not self._closed and self.proc.poll() is not None
        if dead:
            self._respawn(f"had exited (code {self.proc.returncode})")
        try:
            if self._ready is None and self.wait_ready() is None:
                return None
            with self._send_lock:
                self.conn.send(job)
            if progress is not None:
                progress(began(job))      # while the process plans
            while True:
                msg = self._recv(job.gen)
                if msg is None:
                    return None
                if isinstance(msg, _Overdue):
                    return _cancelled_done(job, self.cancel_grace_s)
                if isinstance(msg, Progress):
                    if msg.gen == job.gen and progress is not None:
                        progress(msg)
                    continue
                if isinstance(msg, PlanDone):
                    msg = self._unpack(msg)
                if getattr(msg, "gen", None) == job.gen:
                    return msg
        except (EOFError, OSError, RuntimeError) as e:
            if self._closed:
                return None
            try:       # a dead child closes the socket just before its exit status exists
                code = self.proc.wait(0.5)
            except Exception:      # noqa: BLE001 - alive: the socket itself failed
                code = None
            what = f"planning process failed: {type(e).__name__}: {e}"
            if code is not None and str(code) not in what:
                what += f" (exit code {code})"
            return PlanError(job.gen, "internal_error", what)
        finally:
            self._cancel_at.pop(job.gen, None)

    def cancel(self, gen: int) -> None:
        self._cancel_at.setdefault(gen, time.monotonic())
        try:
            with self._send_lock:
                self.conn.send(Cancel(gen))
        except (OSError, ValueError):
            pass

    def close(self) -> None:
        """
        Stop the child.

        It exits at once when idle; in a stage it is terminated after ``CLOSE_GRACE_S`` (a numba
        kernel cannot be interrupted otherwise).
        """
        with self._proc_lock:
            if self._closed:
                return
            self._closed = True
        try:
            with self._send_lock:
                self.conn.send(None)
        except (OSError, ValueError):
            pass
        try:
            self.proc.wait(self.CLOSE_GRACE_S)
        except Exception:          # noqa: BLE001 - in a stage: stop it
            self.proc.terminate()
            try:
                self.proc.wait(2.0)
            except Exception:      # noqa: BLE001
                self.proc.kill()
                self.proc.wait()
        self.conn.close()


class HybridBackend(ProcessBackend):
    """
    The planning process for what its caches alone hold, the calling (worker) thread for a replan the node holds.

    The node holds the C-space and field the planning process sent last (each new one comes with
    its plan, for the grids the node publishes; ``PlanDone.keys`` names their keys in the process's
    caches).  A job on that C-space's scene and grid runs first in the calling thread, on a
    planner that holds just those two (:attr:`here`, ``Planner.hold_only``) and plans from its
    caches alone (``Planner.plan(cached_only=True)``): a new start to the same target, the
    node's replans, without the process's round trip (two processes' wakes: about 0.6 ms of
    ``bench latency``'s 5).  Where that plan meets a stage the caches do not hold
    (``pipeline.NotCached``: another grid margin or a finer grid, a repair, a free-floating
    capture's search, a goal whose field is not held) the job goes to the process, as does every
    job before the first C-space and field arrive, and every test stall (``PlanJob.stall_s``).
    The result is the process's bit for bit: the same objects, the same pipeline; its kernels
    run serially, its stages poll the cancel as the process's do.
    """

    def __init__(self, scenario, log=None, info=None, solver: str | None = None,
                 field_tolerance: float | None = None):
        #: the planner of the jobs planned here (its caches: what the process sent last)
        self.here = Planner(scenario, solver=solver, field_tolerance=field_tolerance, trajectory=False)
        self._here_cancel = _GenCancel()
        #: ((key, C-space), (key, field)) the process sent last, which ``here`` holds (None: not sent,
        #: not cached there, or a repaired field: no plan from the caches alone reads one)
        self._hold = (None, None)
        #: the goals of the process's jobs whose plans read the field held (None: the target's; at
        #: most HELD_GOALS, the latest), each a joint goal (dof,) rad
        self._held_goals = []
        self.jobs_here = 0              # jobs answered here (a cancelled one included)
        super().__init__(scenario, log=log, info=info, solver=solver, field_tolerance=field_tolerance)

    def warm_up_here(self, timeout_s: float | None = None):
        """
        Load the kernels of the jobs planned here (:func:`warm_up_replans`): from the process's seed, while it warms up.

        Waits for the process's :class:`ReplanSeed` (at most ``timeout_s``; None where the process
        is ready without one, closed, or out of time: then only the start in contact).  Returns
        the seed's plan (see :func:`warm_up_replans`).
        """
        self._start_up(timeout_s, seed=True)
        return warm_up_replans(self.here, self._seed)

    def _unpack(self, done: PlanDone) -> PlanDone:
        out = super()._unpack(done)
        keys = dict(done.keys)
        hold = dict(zip(("cspace", "field"), self._hold))
        sent = False
        for name in ("cspace", "field"):
            obj = getattr(done.result, name, None)
            if obj is not None:             # sent anew: held with its key, or not at all
                sent = True
                usable = name in keys and not (name == "field" and Planner.repaired_key(keys[name]))
                hold[name] = (keys[name], obj) if usable else None
        if hold["field"] is not None and (hold["cspace"] is None or hold["field"][0][0] != hold["cspace"][0]):
            hold["field"] = None            # a field of another C-space than the one held: none would answer
        if sent:                            # (at once: no older pair kept beside the node's own)
            self._hold = (hold["cspace"], hold["field"])
            self.here.hold_only(*self._hold)
        if done.result.field is not None:   # a field sent anew: the goals that read it begin anew
            self._held_goals = []
        return out

    def _answers_here(self, job: PlanJob) -> bool:
        """
        Tell whether ``job`` may be planned here: a C-space and field held, of the job's scene, grid and goal; no stall.

        The goal: one of the process's jobs whose plans read the field held (the target, or a joint
        goal: a new joint goal needs a field of its own, and is not tried here only to fail at it);
        the C-space: of the grid margin a plan tries first.
        """
        cs, fld = self._hold
        if job.stall_s > 0 or cs is None or fld is None:
            return False
        if not self._goal_held(job.joint_goal):
            return False
        geometry, grid, extra_m = cs[0]
        # the grid margin a plan tries first: a C-space of the second (0, where the first left no
        # path) would not answer
        settings = self.here.settings if job.scenario_settings is None else job.scenario_settings[0]
        return grid == job.grid and extra_m == grid_margins(settings)[0] and geometry == job.scene.geometry_key()

    def run(self, job: PlanJob, progress=None):
        """Return the outcome of ``job`` (see the class): planned here where the caches held answer it, else there."""
        if self._closed:
            return None
        if self._answers_here(job):
            out = self._run_here(job, progress)
            if out is not None:
                return out
        out = super().run(job, progress)
        fld = self._hold[1]
        if isinstance(out, PlanDone) and fld is not None and out.result.field is fld[1] and \
                not self._goal_held(job.joint_goal):
            goal = None if job.joint_goal is None else np.array(job.joint_goal, dtype=float)
            self._held_goals = (self._held_goals + [goal])[-HELD_GOALS:]
        return out

    def _goal_held(self, joint_goal) -> bool:
        """Tell whether a process's plan to ``joint_goal`` (None: the target) read the field held."""
        return any((joint_goal is None and g is None) or (joint_goal is not None and g is not None
                                                          and np.array_equal(joint_goal, g)) for g in self._held_goals)

    def _run_here(self, job: PlanJob, progress):
        """Plan ``job`` here from the caches alone; None where they do not answer it (nothing reported then)."""
        said = []
        self._here_cancel.start(job.gen)
        try:
            out = run_job(self.here, job, self._here_cancel, said.append, cached_only=True)
        except NotCached:
            return None         # (a cancel meanwhile also went to the process: its job is cancelled there)
        except Exception as e:     # noqa: BLE001 - report to the node, keep serving
            out = _crash(job.gen, e)
        self._cancel_at.pop(job.gen, None)
        self.jobs_here += 1
        if progress is not None:        # (the stages of a plan of a millisecond or so, told once it is done)
            for p in [began(job)] + said:
                progress(p)
        if isinstance(out, PlanDone):
            out = replace(out, stats={"planned_in": "worker thread", "jobs_here": self.jobs_here,
                                      **self.here.cache_sizes()})
        return out

    def cancel(self, gen: int) -> None:
        self._here_cancel.cancel_upto(gen)
        super().cancel(gen)

    def close(self) -> None:
        self._here_cancel.cancel_upto(1 << 62)
        super().close()


#: :class:`HybridBackend` tries a job here only for one of the last this many goals whose plans read the field held
HELD_GOALS = 4


class _Overdue:
    """Internal: the running job's cancel is overdue and its process was replaced."""


def _cancelled_done(job: PlanJob, grace_s: float) -> PlanError:
    return PlanError(job.gen, "cancelled",
                     f"planning was cancelled (the planning process was replaced: the running "
                     f"stage did not answer the cancel within {grace_s:g} s)")


def make_backend(scenario, separate_process: bool, log=None, info=None, solver=None, field_tolerance=None,
                 replans_here: bool = True):
    """Make a HybridBackend (default), a ProcessBackend (``replans_here`` false) or a ThreadBackend (no process)."""
    kind = ThreadBackend if not separate_process else HybridBackend if replans_here else ProcessBackend
    return kind(scenario, log=log, info=info, solver=solver, field_tolerance=field_tolerance)


def compile_package() -> None:
    """
    Write Python's bytecode cache of this package (``__pycache__/*.pyc``, as an import would).

    An interpreter started with ``PYTHONDONTWRITEBYTECODE`` set (this project's development VM's,
    and a CI machine's like it) reads a module's cached bytecode but never writes it: without this every
    process compiles the package from source again (about 0.12 s of ``spacerobot-plan``'s start,
    and of every planning process's).  A module edited since is compiled in memory as before.
    """
    import compileall
    compileall.compile_dir(os.path.dirname(os.path.abspath(__file__)), quiet=1)


def main(argv=None) -> int:
    """
    Fill numba's cache with the default route of each scenario file, and the package's bytecode cache.

    ``python -m spacerobot_planner.worker --warm-cache FILE...`` (``make`` runs it after
    installing; so does ``setup.py install``, in the installed tree).  The bytecode first
    (:func:`compile_package`).
    """
    import argparse
    ap = argparse.ArgumentParser(description=main.__doc__.strip().splitlines()[0])
    ap.add_argument("--warm-cache", nargs="+", metavar="FILE", required=True)
    args = ap.parse_args(argv)
    compile_package()
    for path in args.warm_cache:
        scenario = load_scenario(path)
        planner = Planner(scenario, reaction=True)    # the file's solver and tolerance; as the CLI
        t = warm_up(planner, full_grid_max_nodes=10 ** 9)
        # the chain after the plan (timing, resampling, certification, reaction; the node runs it in
        # its own process, from rest and joined to a moving arm): the node's first trajectory, its
        # first joined replan and the CLI load its kernels, not compile them
        t0 = time.perf_counter()
        if scenario.start_rad is not None and scenario.scene.target is not None:
            plan_offline(planner, scenario.start_rad)
        try:
            warm_up_chain(scenario)
        except ValueError:          # limits no motion keeps to: the plans say so
            pass
        t["chain_s"] = time.perf_counter() - t0
        print(f"warm-cache {path}: " + ", ".join(f"{k} {v:.2f} s" for k, v in t.items()))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
