"""
Running a sweep: the chunks on Dask (or in this process), rows to the store, a progress bar.

:func:`run_envelope` opens the sweep's folder (``store.EnvelopeStore``: what is done
already), splits the poses still to plan into chunks of consecutive ``pose_id``
(``sweep.chunks``) and hands each chunk to ``sweep.plan_chunk``:

- by default on a ``distributed.LocalCluster`` it starts on this machine: one worker
  process per core, one thread each (numba's kernels then run on one thread per process);
- with ``scheduler="tcp://host:8786"`` on a running Dask cluster (``dask scheduler`` and
  ``dask worker``, each worker with this package installed): the same tasks, the same table;
- with ``workers=0`` in this process, one chunk after the other, without Dask.

Chunks finish in any order; each one's rows go to disk as it finishes, so a killed sweep
resumes where it stopped.  A chunk whose task fails as a whole (its worker died, say)
becomes ``internal_error`` rows naming the failure, like a pose that raises.
"""

from __future__ import annotations

import logging
import math
import os
import signal
import sys
import threading
import time
from contextlib import ExitStack, contextmanager
from dataclasses import dataclass, field

from ..problem import Scenario
from ..results import Code
from .store import PARQUET_MIN_POSES, EnvelopeStore
from .sweep import PoseGrid, blank_row, chunks, plan_chunk

__all__ = ["run_envelope", "SweepReport", "Progress", "default_workers", "guided_size", "local_cluster",
           "LOCAL_CLUSTER_CONFIG"]

#: guided chunks: each default chunk takes 1/(GUIDED_SHARE · slots) of the poses not yet in a chunk
GUIDED_SHARE = 2
#: the smallest default chunk, poses (then extended to whole target poses: all their starts)
MIN_CHUNK = 2
#: the largest default chunk, poses
MAX_CHUNK = 64


def default_workers() -> int:
    """Return the cores this process may use (one local worker process each)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:              # not on Linux
        return os.cpu_count() or 1


def guided_size(slots: int):
    """
    Return the default chunk-size rule for ``slots`` worker slots: a function of the poses left.

    Guided self-scheduling: the next chunk takes ``1/(GUIDED_SHARE · slots)`` of the poses
    not yet in a chunk, between ``MIN_CHUNK`` and ``MAX_CHUNK``.  The first chunks are large
    (few tasks, rows on disk in large writes); the last are small, so the workers run out of
    work at nearly the same moment instead of one finishing a large last chunk while the
    others wait.  Chunks go to the workers in this order as they free up.
    """
    share = GUIDED_SHARE * max(1, int(slots))
    return lambda left: max(MIN_CHUNK, min(MAX_CHUNK, math.ceil(left / share)))


@dataclass
class SweepReport:
    """
    What one run of a sweep did.

    Attributes
    ----------
        n_poses: the sweep's poses.
        done_before: poses that had a row when the run started (resume).
        planned_ids: the ``pose_id`` of every pose this run planned, in the order written.
        complete: every pose has its row.
        seconds: the run's wall time, s (cluster start included).
        plan_seconds: from the first task handed out to the last row written, s.
        engine: "serial", "local cluster, N workers" or the scheduler's address.
        chunks: the chunks this run handed out.
        rows: the whole table sorted by ``pose_id`` when complete, else [].

    """

    n_poses: int
    done_before: int
    planned_ids: list = field(default_factory=list)
    complete: bool = False
    seconds: float = 0.0
    plan_seconds: float = 0.0
    engine: str = ""
    chunks: int = 0
    rows: list = field(default_factory=list)

    @property
    def planned(self) -> int:
        return len(self.planned_ids)


class Progress:
    """
    A one-line progress bar on a terminal: poses done, rate (poses/s) and ETA.

    Quiet when ``enabled`` is false or the stream is not a terminal.
    """

    WIDTH = 28

    def __init__(self, total: int, done: int, enabled: bool = True, stream=None):
        self.stream = stream if stream is not None else sys.stderr
        self.enabled = enabled and hasattr(self.stream, "isatty") and self.stream.isatty()
        self.total, self.done, self.new = total, done, 0
        self.t0 = time.perf_counter()
        self._draw()

    def line(self) -> str:
        """Return the bar's text (without the carriage return)."""
        frac = self.done / self.total if self.total else 1.0
        fill = int(round(self.WIDTH * frac))
        elapsed = max(time.perf_counter() - self.t0, 1e-9)
        rate = self.new / elapsed
        left = self.total - self.done
        eta = "--:--" if rate <= 0 else _clock(left / rate)
        return (f"envelope [{'#' * fill}{'-' * (self.WIDTH - fill)}] {self.done}/{self.total} poses "
                f"{rate:6.1f} poses/s  ETA {eta}")

    def update(self, n: int) -> None:
        self.done += n
        self.new += n
        self._draw()

    def _draw(self) -> None:
        if self.enabled:
            self.stream.write("\r" + self.line())
            self.stream.flush()

    def close(self) -> None:
        if self.enabled:
            self.stream.write("\n")
            self.stream.flush()


def _clock(seconds: float) -> str:
    s = int(round(seconds))
    return f"{s // 3600}:{s // 60 % 60:02d}:{s % 60:02d}" if s >= 3600 else f"{s // 60}:{s % 60:02d}"


#: how many times a chunk cancelled by a lost worker (the scenario's copies gone with it) is submitted again
LOST_RESUBMITS = 3


def _failed_chunk_rows(grid: PoseGrid, ids, error: BaseException) -> list:
    rows = []
    for i in ids:
        row = blank_row(grid, i)
        row.update(code=str(Code.INTERNAL_ERROR),
                   reason=" ".join(f"the task planning this pose's chunk failed: {type(error).__name__}: "
                                   f"{error}".split()))
        rows.append(row)
    return rows


def run_envelope(scenario: Scenario, grid: PoseGrid, out_dir, spec: dict, *, scheduler: str | None = None,
                 workers: int | None = None, client=None, chunk_size: int | None = None,
                 parquet: bool | None = None, quiet: bool = False, after_chunk=None) -> SweepReport:
    """
    Plan every pose of ``grid`` not yet in ``out_dir`` (see the module docstring).

    Args:
        scenario: the scenario (its target is moved to each pose).
        grid: the poses (``sweep.PoseGrid``).
        out_dir: the sweep's folder; spec: ``store.sweep_spec`` (a rerun must match it).
        scheduler: a Dask scheduler's address ("tcp://host:8786"), or None.
        workers: local worker processes when no scheduler or client is given (default: one per
            core); 0 plans in this process without Dask.
        client: a ``distributed.Client`` to use (the caller keeps it open), or None.
        chunk_size: poses per task (default: :func:`guided_size`, chunks of whole target poses).
        parquet: write ``envelope.parquet`` too (default: for ``PARQUET_MIN_POSES`` poses or more).
        quiet: no progress bar.
        after_chunk: called with each chunk's rows once they are on disk (a test's hook), or None.

    Returns
    -------
        SweepReport.

    Raises
    ------
        ValueError: ``out_dir`` holds another sweep or a damaged table; bad workers/chunk size.

    """
    t_start = time.perf_counter()
    if workers is not None and workers < 0:
        raise ValueError(f"--workers: must be ≥ 0, got {workers}")
    if chunk_size is not None and chunk_size < 1:
        raise ValueError(f"--chunk-size: must be ≥ 1, got {chunk_size}")
    if scenario.scene.target is None:
        raise ValueError("target: the scenario has no target; an envelope sweeps the target's pose")
    store = EnvelopeStore(out_dir, spec)
    done = store.open(grid)
    todo_ids = [i for i in range(grid.n_poses) if i not in done]
    report = SweepReport(n_poses=grid.n_poses, done_before=len(done))
    serial = client is None and scheduler is None and workers == 0
    bar = None
    try:
        with ExitStack() as stack:
            if serial:
                slots, report.engine = 1, "serial (this process)"
            else:
                client = client or _client(stack, scheduler, workers)
                if scheduler:
                    _wait_for_a_worker(client, scheduler)
                slots = max(1, sum(w.get("nthreads", 1) for w in client.scheduler_info()["workers"].values()))
                report.engine = (f"Dask at {scheduler}" if scheduler else f"Dask, {slots} worker slots")
            if chunk_size:
                work = chunks(todo_ids, chunk_size)
            else:
                work = chunks(todo_ids, guided_size(slots), group=len(grid.starts_rad))
            report.chunks = len(work)
            store.start_run(engine=report.engine, poses_to_plan=len(todo_ids), chunks=len(work),
                            chunk_size=chunk_size or "guided")
            bar = Progress(grid.n_poses, len(done), enabled=not quiet)
            t_plan = time.perf_counter()

            def take(rows):
                store.append(rows)
                report.planned_ids.extend(r["pose_id"] for r in rows)
                bar.update(len(rows))
                if after_chunk is not None:
                    after_chunk(rows)

            if serial:
                with _interrupt_between_poses() as interrupted:
                    for ids in work:
                        take(plan_chunk(scenario, grid, ids, stop=interrupted))
                        if interrupted:
                            raise KeyboardInterrupt
            elif work:
                _run_on_dask(client, scenario, grid, work, take)
            report.plan_seconds = time.perf_counter() - t_plan
        report.complete = len(done) + report.planned == grid.n_poses
    finally:
        if bar is not None:
            bar.close()
        store.close()
        report.seconds = time.perf_counter() - t_start
        if store.running:
            store.end_run(report.planned, report.complete, report.seconds)
        else:            # stopped before a run began (no --scheduler to connect to): leave no new folder behind
            store.discard_new()
    if report.complete:
        want_parquet = grid.n_poses >= PARQUET_MIN_POSES if parquet is None else parquet
        report.rows = store.finish(want_parquet)
    return report


@contextmanager
def _interrupt_between_poses():
    """
    Within it, a Ctrl-C (SIGINT) is taken between the serial sweep's poses: yields a list, not empty once one came.

    A KeyboardInterrupt raised inside a numba kernel comes out as a SystemError ("returned a
    result with an exception set"), which the plan turned into an ``internal_error`` row, and
    the sweep went on (an audit: exit 0, a row a rerun would not plan again).  The pose being
    planned is finished and written; the sweep then stops as interrupted.  Outside the main
    thread (no signals there) it changes nothing.
    """
    came = []
    if threading.current_thread() is not threading.main_thread():
        yield came
        return
    before = signal.signal(signal.SIGINT, lambda signum, frame: came.append(signum))
    try:
        yield came
    finally:
        signal.signal(signal.SIGINT, before)


#: glibc's variable that Dask sets in its workers' environment (see ``LOCAL_CLUSTER_CONFIG``)
MALLOC_TRIM = "MALLOC_TRIM_THRESHOLD_"
#: Dask settings of the local cluster: the workers' statistical profiler samples every thread's
#: stack every 10 ms (3 % of a core per idle worker on the 2-core development machine, 0.4 %
#: without it, and it competes with the plans for the GIL); the event-loop tick and the system
#: and memory monitors poll less often (the client and scheduler's idle CPU: 3.6 % → 1 %)
LOCAL_CLUSTER_CONFIG = {
    "distributed.worker.profile.enabled": False,
    "distributed.admin.tick.interval": "500ms",
    "distributed.admin.system-monitor.interval": "1s",
    "distributed.worker.memory.monitor-interval": "1s",
    # Dask spawns its workers with MALLOC_TRIM_THRESHOLD_=65536 (to hand memory back to the OS
    # between large dataframe tasks); any such setting also turns off glibc's adaptive mmap
    # threshold, so every array of 128 kB or more is mapped and unmapped at each plan: 3× the
    # page faults and 8-12 % more CPU per pose than the same plans in a plain process.  None
    # keeps the variable out of the workers' environment (``local_cluster`` also keeps this
    # process's own out of it while the workers spawn).
    f"distributed.nanny.pre-spawn-environ.{MALLOC_TRIM}": None,
}


def local_cluster(workers: int | None = None):
    """
    Return a ``distributed.LocalCluster`` for sweeps: ``workers`` processes (default one per core), one thread each.

    Use it as a context manager (it closes its processes).  No dashboard port is taken from
    the default 8787 (a free one is chosen); logs below ERROR are silenced; the workers get
    ``LOCAL_CLUSTER_CONFIG`` and start without ``MALLOC_TRIM_THRESHOLD_`` in their environment
    (whatever this process's says; a worker the nanny restarts later gets this process's), and
    ignoring SIGINT: a terminal's Ctrl-C reaches every process of its group, and each worker
    printed a KeyboardInterrupt traceback above the sweep's "interrupted; run the same command
    again to resume" (this process ends the cluster when it is interrupted).  Spawned with
    SIGINT ignored, their interpreters keep it so (Python installs its handler only over the
    default); meanwhile, a few seconds, a Ctrl-C here is not taken either.
    """
    import dask                                      # Dask: loaded only when a sweep runs on it
    from distributed import LocalCluster
    # a Dask cluster started before in this process leaves MALLOC_TRIM_THRESHOLD_ in its
    # environment (the nannies set it there before they spawn); out of it while ours spawn
    trim = os.environ.pop(MALLOC_TRIM, None)
    main = threading.current_thread() is threading.main_thread()     # (signals: the main thread's only)
    interrupt = signal.signal(signal.SIGINT, signal.SIG_IGN) if main else None
    try:
        with dask.config.set(LOCAL_CLUSTER_CONFIG):      # the nannies hand this config to their workers
            return LocalCluster(n_workers=workers or default_workers(), threads_per_worker=1, processes=True,
                                dashboard_address=":0", silence_logs=logging.ERROR)
    finally:
        if trim is not None:
            os.environ[MALLOC_TRIM] = trim
        if main:
            signal.signal(signal.SIGINT, interrupt)


#: how long a sweep waits for a worker to join a scheduler that has none, s
WORKER_WAIT_S = 30.0


def _wait_for_a_worker(client, scheduler: str) -> None:
    """Wait up to ``WORKER_WAIT_S`` for the scheduler to have a worker; ValueError naming ``--scheduler`` if none."""
    if client.scheduler_info()["workers"]:
        return
    print(f"spacerobot-plan envelope: the scheduler at {scheduler} has no workers yet; waiting up to "
          f"{WORKER_WAIT_S:g} s for one (dask worker {scheduler})", file=sys.stderr, flush=True)
    try:
        client.wait_for_workers(1, timeout=WORKER_WAIT_S)
    except (TimeoutError, OSError):
        raise ValueError(f"--scheduler {scheduler}: no worker joined it in {WORKER_WAIT_S:g} s (start one: "
                         f"dask worker {scheduler})") from None


def _client(stack: ExitStack, scheduler: str | None, workers: int | None):
    """Open a Client on ``scheduler``, or on a :func:`local_cluster` of ``workers`` (closed with the stack)."""
    from distributed import Client
    if scheduler:
        try:
            return stack.enter_context(Client(scheduler, timeout="30s"))
        except OSError as e:           # not the output folder's: said as the option's (envelope_cli)
            raise ValueError(f"--scheduler {scheduler}: cannot connect: {e}") from None
    cluster = stack.enter_context(local_cluster(workers))
    return stack.enter_context(Client(cluster))


def _run_on_dask(client, scenario, grid, work, take) -> None:
    """
    Submit one task per chunk; hand each chunk's rows to ``take`` as it finishes.

    The chunks' priorities follow their order (the scheduler hands the first ones out first).
    The scenario goes to the workers once (scattered); a worker lost with every copy of it
    cancels the chunks not yet planned (Dask's ``FutureCancelledError``: "already forgotten"):
    the scenario is scattered again and those chunks submitted again, up to ``LOST_RESUBMITS``
    times each, then left unplanned (the run ends incomplete; the same command resumes it).
    Only a chunk whose own task failed (it raised, or its workers died planning it: Dask's
    ``KilledWorker``) becomes rows naming the failure.
    """
    from distributed import as_completed
    from distributed.client import FutureCancelledError
    # a key of its own each time (not the data's hash): a copy scattered again must not meet the
    # scheduler still forgetting the lost one under the same key
    shared = [client.scatter(scenario, broadcast=True, hash=False)]
    futures, resubmits = {}, {}

    def submit(k, ids):
        if shared[0].status != "finished":          # its copies lost with their workers
            shared[0] = client.scatter(scenario, broadcast=True, hash=False)
        f = client.submit(plan_chunk, shared[0], grid, ids, 1, pure=False, priority=len(work) - k)
        futures[f.key] = (f, k, ids)
        return f

    finished = as_completed([submit(k, ids) for k, ids in enumerate(work)])
    for f in finished:
        _, k, ids = futures.pop(f.key)
        try:
            rows = f.result()
        except FutureCancelledError:
            f.release()
            resubmits[k] = resubmits.get(k, 0) + 1
            if resubmits[k] <= LOST_RESUBMITS:
                finished.add(submit(k, ids))
            continue
        except Exception as e:  # noqa: BLE001 -- a failed task is rows naming the failure, not the end of the run
            rows = _failed_chunk_rows(grid, ids, e)
        f.release()
        take(rows)
