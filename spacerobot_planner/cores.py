"""
The threads a plan's parallel kernels use: numba's number, fewer while other work keeps the cores busy.

numba's parallel loops fork a team of threads and join them at the loop's end.  Where other
processes keep the cores busy, the kernel scheduler takes team members off their cores, and the
members that are left wait at the join until the missing one gets a time slice back: every loop
of a solve pays a slice.  On the 2-core development VM, with two busy processes beside it, the
paper's 3-DOF scene at 72³ planned in 445 / 2 113 / 3 012 ms (median / p90 / max of 5) on numba's
two threads against 133 / 138 / 140 ms on one thread (61 and 78 ms on an idle machine); with one
busy process, 90–97 / 205–230 / 233–250 ms against 82–83 / 86–89 / 90–98 ms.

So where a plan's parallel loops run (a grid of :data:`PARALLEL_MIN_NODES` nodes or more), the
planner counts, before its C-space build and before each field solve, the threads that are
runnable on the machine outside this process (Linux's ``/proc/loadavg`` now, less this process's
own running threads: numba's team spins a while after each loop; a count above zero confirmed over
a millisecond, so that a system thread's burst is not a busy core) and gives its kernels no more
threads than cores are left (:func:`fit_threads`).  The field's values are the same bits on any
number of threads (``field.multigrid``), so the count changes only the time.  Below that size the
configured number holds and nothing is read (the loops there are a few, and short).  Where
``/proc`` cannot be read (not Linux), the configured number holds.

``/proc/loadavg`` counts the whole machine.  A process that may run on some of its CPUs only
takes the machine's other work as spread evenly over them (:func:`busy_share`); work pinned to
the same CPUs as the planner is then undercounted, and ``planner.max_threads`` caps the threads
by hand.  ``planner.threads_follow_load: false`` keeps ``planner.max_threads`` whatever the load.
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass

__all__ = ["Fit", "PARALLEL_MIN_NODES", "fit_threads", "busy_share", "busy_elsewhere", "threads_text",
           "own_thread_files"]

#: grids of at least this many nodes count the busy cores before a stage's parallel loops; the
#: node graph's (``field.graph.PARALLEL_MIN_NODES``) and the fine level's (``multigrid.PARALLEL_MIN_CELLS``)
#: loops run on threads from about there on
PARALLEL_MIN_NODES = 100_000

#: a count of busy cores above zero is read again this many times, and the least count holds ...
CONFIRM_READINGS = 4
#: ... one every this many seconds (about a millisecond in all; longer on a loaded machine)
CONFIRM_STEP_S = 2.5e-4


@dataclass(frozen=True)
class Fit:
    """
    One choice of :func:`fit_threads`.

    Attributes
    ----------
        threads: the threads the calling thread's parallel kernels now use.
        limit: the most they may use (``planner.max_threads``, or numba's number).
        busy: the cores counted busy with other work (scaled to this process's cores);
            None where nothing was counted (a small grid, a limit of one, no ``/proc``).

    """

    threads: int
    limit: int
    busy: int | None


def _runnable_on_machine() -> int | None:
    """Return the threads runnable on the machine now (``/proc/loadavg``'s fourth field, this one included), or None."""
    try:
        with open("/proc/loadavg", "rb") as f:
            return int(f.read().split()[3].split(b"/")[0])
    except (OSError, ValueError, IndexError):
        return None


def own_thread_files(name: str) -> list:
    """Return the bytes of ``/proc/self/task/<tid>/<name>`` for each of this process's threads ([] without /proc)."""
    try:
        tids = os.listdir("/proc/self/task")
    except OSError:
        return []
    out = []
    for tid in tids:
        try:
            with open(f"/proc/self/task/{tid}/{name}", "rb") as f:
                out.append(f.read())
        except OSError:               # the thread ended meanwhile
            continue
    return out


def _running_here() -> int:
    """Return this process's threads in state R (running or runnable), from ``/proc/self/task/*/stat``."""
    n = 0
    for s in own_thread_files("stat"):
        end = s.rfind(b")")           # the state follows the command name, which may hold anything
        if end >= 0 and s[end + 2:end + 3] == b"R":
            n += 1
    return max(n, 1)                  # the reading thread runs


def busy_elsewhere() -> int | None:
    """
    Return how many of this process's cores other work keeps busy now, or None where it cannot be read.

    The threads runnable on the machine less this process's own (:func:`busy_share`), this
    process's counted first: a thread of its own that stops between the two readings then
    counts as its own, not as other work (numba's team stops spinning a while after a loop).
    A count above zero is read again :data:`CONFIRM_READINGS` times, every :data:`CONFIRM_STEP_S`
    (a millisecond), and the least count holds: on the idle development VM 2.5–2.6 % of single readings met a
    system thread's burst, 0.43–0.6 % of readings confirmed over 1 ms (3 000–4 000 readings).
    """
    busy = _busy_now()
    for _ in range(CONFIRM_READINGS):
        if not busy:
            break
        time.sleep(CONFIRM_STEP_S)
        again = _busy_now()
        busy = busy if again is None else min(busy, again)
    return busy


def _busy_now() -> int | None:
    """:func:`busy_elsewhere`'s single reading."""
    own = _running_here()
    runnable = _runnable_on_machine()
    if runnable is None:
        return None
    return busy_share(runnable - own, _cores(), os.cpu_count() or 1)


def busy_share(others: int, cores: int, online: int) -> int:
    """
    Return the cores of ``cores`` that ``others`` threads runnable outside this process keep busy.

    The machine's ``online`` CPUs share its other work evenly: a process that may run on 2 of
    64 CPUs meets about 2/64 of it there.  Rounded half up, at most ``cores``.
    """
    cores, online, others = max(1, int(cores)), max(1, int(online)), max(0, int(others))
    return min(cores, (2 * others * cores + online) // (2 * online))


def fit_threads(most: int, nodes: int) -> Fit:
    """
    Set the calling thread's numba threads for a stage on a grid of ``nodes`` nodes; return the :class:`Fit`.

    ``most``: ``planner.max_threads`` (0: numba's number, ``NUMBA_NUM_THREADS``).  From
    :data:`PARALLEL_MIN_NODES` nodes on and with a limit above one, no more than the cores
    that other work leaves (:func:`busy_elsewhere`), at least one; below (and with ``nodes``
    0), the limit itself.  The planner owns the count of the thread it plans in: a count set
    on numba there directly is replaced (``planner.max_threads`` is the setting).  numba's
    thread pool starts where a number is set or a parallel kernel first runs, so a thread of
    a process without a pool that keeps numba's number sets nothing (a plan on a small grid
    starts no pool).
    """
    import numba
    from numba.np.ufunc import parallel as pool
    numba_limit = numba.config.NUMBA_NUM_THREADS
    limit = numba_limit if int(most) <= 0 else min(int(most), numba_limit)
    threads, busy = limit, None
    if limit > 1 and nodes >= PARALLEL_MIN_NODES:
        busy = busy_elsewhere()
        if busy is not None:
            threads = max(1, min(limit, _cores() - busy))
    now = numba.get_num_threads() if pool._is_initialized else numba_limit
    if threads != now:
        numba.set_num_threads(threads)
    return Fit(threads, limit, busy)


def threads_text(stats: dict) -> str:
    """
    Return '; parallel loops on 1 of 2 threads, 2 cores busy with other work', or '' where a plan ran on all.

    ``stats``: a plan's ``solver_stats`` (``Planner.threads_note``'s entries).
    """
    if stats.get("threads", 0) >= stats.get("threads_limit", 0):
        return ""
    busy = stats["busy_cores"]
    return (f"; parallel loops on {stats['threads']} of {stats['threads_limit']} threads, "
            f"{busy} {'core' if busy == 1 else 'cores'} busy with other work")


def _cores() -> int:
    """Return the CPUs this process may run on."""
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        return os.cpu_count() or 1
