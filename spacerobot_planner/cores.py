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
configured number holds and nothing is read (the loops there are a few, and short), but before a
plan's first repair's swept edges (``swept``), whose loops run on threads at every size and waited
a time slice each beside another session's busy process (a 36³ repair 137 ms instead of 14.6):
they are counted on every grid (``any_size``), as before a C-space built node by node (a last
planned joint that is not the chain's last: ``cspace.loops_at_any_size``).  Where ``/proc`` cannot
be read (not Linux), the configured number holds.

A process in a container often may run on all of the machine's CPUs but for a share of their time
only: a CPU limit (cgroup's ``cpu.max``, or ``cpu.cfs_quota_us`` over ``cpu.cfs_period_us`` in
cgroup v1; ``docker run --cpus``, a Kubernetes CPU limit).  numba starts a thread per CPU it may
run on, and a team of more threads than the limit spends the period's time in a burst, then the
whole process waits for the next period, its serial work too.  So the threads are also no more
than the limit, rounded up (:func:`cpu_limit`: the least limit of the process's cgroup and those
above it, read at most once a second), on every grid.  Measured on the 2-core development VM in a
cgroup of 1 CPU: the paper's 3-DOF scene at 72³ 94.5 / 98.2 / 99.3 ms on two threads against
71.8 / 74.9 / 78.3 on one (median / p90 / max of 7); of half a CPU, 287.7 / 296.5 / 304.3 against
224.2 / 272.2 / 275.3.

numba runs its parallel loops on one of three threading layers, the first of its priority that
loads: OpenMP needs the system's ``libgomp`` (absent from slim container images), TBB the ``tbb``
wheel (installed by ``requirements.txt`` on x86-64), and its own ``workqueue`` is always there but
took 2.4× OpenMP's time at 72³ here (119.0 / 128.4 / 129.2 against 50.8 / 54.7 / 57.1 ms, median /
p90 / max of 5, alternating) and ends the process where two threads launch parallel loops at
once.  numba's own priority is TBB first; TBB was 1.07× OpenMP at 72³ here (medians 49.1–50.8
against 45.8–47.3 ms, tails in docs/benchmarks.md; small grids equal), so the package prefers
OpenMP, then TBB, then the work queue (:func:`prefer_threading_layers`, on import; ``NUMBA_THREADING_LAYER`` or
``NUMBA_THREADING_LAYER_PRIORITY`` set by the user hold).

``/proc/loadavg`` counts the whole machine.  A process that may run on some of its CPUs only
takes the machine's other work as spread evenly over them (:func:`busy_share`); work pinned to
the same CPUs as the planner is then undercounted, and ``planner.max_threads`` caps the threads
by hand.  ``planner.threads_follow_load: false`` keeps ``planner.max_threads`` whatever the load
and the CPU limit.
"""

from __future__ import annotations

import math
import os
import re
import time
from dataclasses import dataclass

__all__ = ["Fit", "PARALLEL_MIN_NODES", "fit_threads", "current_threads", "busy_share", "busy_elsewhere",
           "threads_text", "own_thread_files", "cpu_limit", "cgroup_cpu_limit", "prefer_threading_layers",
           "LAYER_PRIORITY", "limit_phrase", "limit_text", "threading_layer"]

#: grids of at least this many nodes count the busy cores before a stage's parallel loops (the swept edges: every
#: grid, ``fit_threads(any_size=True)``); the
#: node graph's (``field.graph.PARALLEL_MIN_NODES``) and the fine level's (``multigrid.PARALLEL_MIN_CELLS``)
#: loops run on threads from about there on
PARALLEL_MIN_NODES = 100_000

#: a count of busy cores above zero is read again this many times, and the least count holds ...
CONFIRM_READINGS = 4
#: ... one every this many seconds (about a millisecond in all; longer on a loaded machine)
CONFIRM_STEP_S = 2.5e-4
#: the threading layers numba tries, in order (see the module docstring)
LAYER_PRIORITY = ("omp", "tbb", "workqueue")
#: ... and numba's own order (its config's default)
_NUMBAS_PRIORITY = ["tbb", "omp", "workqueue"]
#: the CPU limit is read again after this many seconds (a container's limit may be changed while it runs)
CPU_LIMIT_MAX_AGE_S = 1.0


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
        cpu_limit: the process's CPU limit rounded up (:func:`cpu_limit`) where it is below
            ``limit`` and was applied, else None.

    """

    threads: int
    limit: int
    busy: int | None
    cpu_limit: int | None = None


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


def prefer_threading_layers() -> None:
    """
    Make numba try :data:`LAYER_PRIORITY`'s threading layers in order, unless the user chose.

    The user chose where ``NUMBA_THREADING_LAYER`` or ``NUMBA_THREADING_LAYER_PRIORITY`` is set,
    or, numba already imported, its config's layer or order is not numba's default (set in
    code).  Before numba's import the order goes in the environment (numba reads it at import;
    the planning process and Dask workers inherit it); after, in numba's config only (a change
    to the environment makes numba read its whole config again at the next compile, and drop
    what the user set in code).  numba picks a layer when the first parallel loop runs.  Where
    the system's OpenMP runtime does not load, the ``tbb`` wheel's library is loaded first
    (:func:`_load_tbb`), whoever chose the order: a process started by one that imported the
    package (the planning process) finds the order in the environment.
    """
    import sys
    if "NUMBA_THREADING_LAYER" not in os.environ and "NUMBA_THREADING_LAYER_PRIORITY" not in os.environ:
        config = sys.modules.get("numba.core.config")
        if config is None:
            os.environ["NUMBA_THREADING_LAYER_PRIORITY"] = " ".join(LAYER_PRIORITY)
        elif config.THREADING_LAYER == "default" and list(config.THREADING_LAYER_PRIORITY) == _NUMBAS_PRIORITY:
            config.THREADING_LAYER_PRIORITY = list(LAYER_PRIORITY)
    # whoever set the order (the planning process inherits the node's): TBB loadable where OpenMP is not
    if not _loads("libgomp.so.1"):
        _load_tbb()


def _loads(library: str, mode: int | None = None) -> bool:
    """Tell whether the dynamic loader loads ``library`` (a name or a path)."""
    import ctypes
    try:
        ctypes.CDLL(library, mode=ctypes.DEFAULT_MODE if mode is None else mode)
    except OSError:
        return False
    return True


def _load_tbb() -> bool:
    """
    Load TBB's library for numba's TBB layer: by name, else from the ``tbb`` wheel's ``<prefix>/lib``.

    numba's TBB module finds ``libtbb.so.12`` by name only, and the wheel puts it in the
    install prefix's ``lib``, which the dynamic loader does not search (a virtualenv; a system
    prefix before ``ldconfig``).  Loaded by its path with global symbols, the name is then taken.
    Returns whether it is loaded.
    """
    import ctypes
    import site
    import sys
    name = "libtbb.so.12"
    if _loads(name, ctypes.RTLD_GLOBAL):
        return True
    prefixes = [sys.prefix, getattr(site, "USER_BASE", None) or ""]
    return any(p and _loads(os.path.join(p, "lib", name), ctypes.RTLD_GLOBAL) for p in prefixes)


def fit_threads(most: int, nodes: int, follow: bool = True, any_size: bool = False) -> Fit:
    """
    Set the calling thread's numba threads for a stage on a grid of ``nodes`` nodes; return the :class:`Fit`.

    ``most``: ``planner.max_threads`` (0: numba's number, ``NUMBA_NUM_THREADS``).  With
    ``follow`` (``planner.threads_follow_load``), no more than the process's CPU limit
    (:func:`cpu_limit`) on any grid, and from :data:`PARALLEL_MIN_NODES` nodes on (on any grid
    with ``any_size``: a stage whose loops run on threads at every size, the swept edges) and
    with a limit above one, no more than the cores that other work leaves
    (:func:`busy_elsewhere`), at least one; without, the limit itself.  The planner owns the count
    of the thread it plans in: a count set on numba there directly is replaced
    (``planner.max_threads`` is the setting).  numba's thread pool starts where a number is set
    or a parallel kernel is first loaded, so a thread of a process without a pool that keeps
    numba's number sets nothing (:func:`current_threads`).
    """
    import numba
    numba_limit = numba.config.NUMBA_NUM_THREADS
    limit = numba_limit if int(most) <= 0 else min(int(most), numba_limit)
    threads, busy, capped = limit, None, None
    if follow:
        cpus = cpu_limit()
        if cpus is not None and cpus < limit:
            threads = capped = cpus
        if threads > 1 and (nodes >= PARALLEL_MIN_NODES or any_size):
            busy = busy_elsewhere()
            if busy is not None:
                threads = max(1, min(threads, _cores() - busy))
    if threads != current_threads():
        numba.set_num_threads(threads)
    return Fit(threads, limit, busy, capped)


def current_threads() -> int:
    """
    Return the calling thread's numba thread count, without starting numba's thread pool.

    numba's count (``numba.get_num_threads``) starts the pool; before it has started the count is
    numba's number, ``NUMBA_NUM_THREADS``.
    """
    import numba
    from numba.np.ufunc import parallel as pool
    return numba.get_num_threads() if pool._is_initialized else numba.config.NUMBA_NUM_THREADS


def limit_phrase(cpus: int | None) -> str:
    """Return 'a CPU limit of 2' for a CPU limit of 2 (whole CPUs), '' for None: how every line names it."""
    return "" if cpus is None else f"a CPU limit of {cpus}"


def limit_text(cpus: int | None) -> str:
    """Return ', a CPU limit of 2' (:func:`limit_phrase` after a comma), '' for None."""
    return "" if cpus is None else f", {limit_phrase(cpus)}"


def threading_layer() -> str:
    """Return numba's threading layer in this process, or "" where no parallel loop has run yet."""
    import numba
    try:
        return str(numba.threading_layer())
    except ValueError:
        return ""


def threads_text(stats: dict) -> str:
    """
    Return '; parallel loops on 1 of 2 threads, 2 cores busy with other work', or '' where a plan ran on all.

    ``stats``: a plan's ``solver_stats`` (``Planner.threads_note``'s entries): the busy cores
    (``busy_cores``) and the CPU limit (``cpu_limit``) where each took threads.
    """
    if stats.get("threads", 0) >= stats.get("threads_limit", 0):
        return ""
    busy = stats.get("busy_cores") or 0
    why = [w for w in (limit_phrase(stats.get("cpu_limit")),
                       f"{busy} {'core' if busy == 1 else 'cores'} busy with other work" if busy else "") if w]
    return f"; parallel loops on {stats['threads']} of {stats['threads_limit']} threads" + (
        ", " + " and ".join(why) if why else "")


def _cores() -> int:
    """Return the CPUs this process may run on."""
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        return os.cpu_count() or 1


_limit_read = [-math.inf, None]          # [when (monotonic s), the limit read then]


def cpu_limit() -> int | None:
    """
    Return this process's CPU limit in whole CPUs (rounded up, at least 1), or None where it has none.

    Read from ``/proc/self/cgroup`` and ``/proc/self/mountinfo`` (:func:`cgroup_cpu_limit`) at
    most once every :data:`CPU_LIMIT_MAX_AGE_S`; None too where they cannot be read (not Linux).
    """
    now = time.monotonic()
    if now - _limit_read[0] >= CPU_LIMIT_MAX_AGE_S:
        cpus = None
        try:
            with open("/proc/self/cgroup", "rb") as f:
                cgroups = os.fsdecode(f.read())
            with open("/proc/self/mountinfo", "rb") as f:
                mounts = os.fsdecode(f.read())     # a mount point's name may be any bytes
            cpus = cgroup_cpu_limit(cgroups, mounts)
        except (OSError, ValueError):
            cpus = None
        _limit_read[:] = [now, None if cpus is None else max(1, math.ceil(cpus))]
    return _limit_read[1]


def cgroup_cpu_limit(cgroups: str, mountinfo: str) -> float | None:
    """
    Return the CPU limit (CPUs, a fraction) of the process whose cgroups and mounts are given, or None.

    ``cgroups``: the text of its ``/proc/<pid>/cgroup``; ``mountinfo``: of its
    ``/proc/<pid>/mountinfo``.  The cgroup v2 hierarchy (``cpu.max``: "quota period", or "max
    period") and the v1 ``cpu`` controller's (``cpu.cfs_quota_us`` over ``cpu.cfs_period_us``;
    -1: none) are read from the process's cgroup up to the hierarchy's mount point, each where
    it is mounted (a container sees its own cgroup as the mount's root); the least limit holds,
    since a cgroup's own limit and every one above it apply.  Files that are not there or not
    understood limit nothing.
    """
    v2_path = v1_path = None
    for line in cgroups.splitlines():
        parts = line.split(":", 2)
        if len(parts) != 3:
            continue
        if parts[0] == "0" and parts[1] == "":
            v2_path = parts[2]
        elif "cpu" in parts[1].split(","):
            v1_path = parts[2]
    least = None
    for fstype, options, root, point in _cgroup_mounts(mountinfo):
        if fstype == "cgroup2" and v2_path is not None:
            path, read = v2_path, _v2_limit
        elif fstype == "cgroup" and v1_path is not None and "cpu" in options:
            path, read = v1_path, _v1_limit
        else:
            continue
        rel = _below(path, root)
        if rel is None:               # the cgroup is not under this mount: it cannot be read here
            continue
        cpus = _least_limit(point, rel, read)
        if cpus is not None and (least is None or cpus < least):
            least = cpus
    return least


def _cgroup_mounts(mountinfo: str):
    """Yield (fstype, super options (a set), the mount's root in its hierarchy, its point) of each cgroup mount."""
    for line in mountinfo.splitlines():
        fields = line.split()
        if "-" not in fields:
            continue
        dash = fields.index("-")
        if dash < 5 or len(fields) < dash + 4 or fields[dash + 1] not in ("cgroup", "cgroup2"):
            continue
        yield (fields[dash + 1], set(fields[dash + 3].split(",")), _unescaped(fields[3]),
               _unescaped(fields[4]))


def _unescaped(field: str) -> str:
    """Return a mountinfo path field with its octal escapes (a space written as backslash 040) undone."""
    return re.sub(r"\\([0-7]{3})", lambda m: chr(int(m.group(1), 8)), field)


def _below(path: str, root: str) -> str | None:
    """
    Return ``path`` relative to a mount's ``root`` ('' where it is the root), or None where it is not below it.

    None also for a path with a ``..`` part (a process outside its cgroup namespace's root).
    """
    path, root = path.rstrip("/"), root.rstrip("/")
    if ".." in path.split("/"):
        return None
    if path == root:
        return ""
    if not path.startswith(root + "/"):
        return None
    return path[len(root) + 1:]


def _least_limit(point: str, rel: str, read) -> float | None:
    """Return the least of ``read(directory)`` from the mount point + ``rel`` up to the mount point, or None."""
    least = None
    parts = [p for p in rel.split("/") if p]
    for depth in range(len(parts), -1, -1):
        cpus = read(os.path.join(point, *parts[:depth]))
        if cpus is not None and (least is None or cpus < least):
            least = cpus
    return least


def _read_text(path: str) -> str | None:
    """Return a file's text, or None where it cannot be read (or its path or bytes are not understood)."""
    try:
        with open(path) as f:
            return f.read()
    except (OSError, ValueError):
        return None


def _v2_limit(directory: str) -> float | None:
    """Return a cgroup v2 directory's ``cpu.max`` quota over its period (CPUs), or None (no limit, no file)."""
    text = _read_text(os.path.join(directory, "cpu.max"))
    try:
        quota, period = text.split()
        return None if quota == "max" else _ratio(float(quota), float(period))
    except (AttributeError, ValueError):
        return None


def _v1_limit(directory: str) -> float | None:
    """Return a cgroup v1 ``cpu`` directory's ``cpu.cfs_quota_us`` over ``cpu.cfs_period_us`` (CPUs), or None."""
    quota, period = (_read_text(os.path.join(directory, f"cpu.cfs_{name}_us")) for name in ("quota", "period"))
    try:
        return _ratio(float(quota), float(period))
    except (TypeError, ValueError):
        return None


def _ratio(quota: float, period: float) -> float | None:
    """Return quota / period, or None where either is not a positive number (-1: no quota)."""
    return quota / period if quota > 0 and period > 0 else None
