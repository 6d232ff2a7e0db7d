"""
A plan's parallel loops get no more threads than other work leaves cores (``cores``).

- the share of the machine's other work that falls on this process's cores, by hand;
- with as many busy-loop processes as this process has cores, every core counts busy and a
  large grid's stages get one thread; a small grid's keep the limit and count nothing;
- a plan on a large grid under that load reports one thread and plans the same path, bit for
  bit, as the same plan before the load (a plan is the same on any number of threads);
- the line the log and the CLI print.
"""

from __future__ import annotations

import os
import subprocess
import sys
import time

import numpy as np
import pytest

from spacerobot_planner import cores

#: the most busy processes a test starts (one per core of this process)
MOST_HOGS = 8


def _my_cores() -> int:
    return len(os.sched_getaffinity(0))


def _cpu_ticks(pid: int) -> int:
    """User + system clock ticks of process ``pid`` (``/proc/<pid>/stat`` fields 14 and 15)."""
    with open(f"/proc/{pid}/stat", "rb") as f:
        fields = f.read().rsplit(b")", 1)[1].split()
    return int(fields[11]) + int(fields[12])


@pytest.fixture
def every_core_busy():
    """One busy-loop process per core of this process, each seen running, stopped after the test."""
    n = _my_cores()
    if n > MOST_HOGS or not os.path.exists("/proc/loadavg"):
        pytest.skip(f"{n} cores (more than {MOST_HOGS}) or no /proc/loadavg")
    hogs = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(n)]
    try:
        t_end = time.monotonic() + 10.0
        while any(_cpu_ticks(h.pid) < 2 for h in hogs):       # each has had the CPU (its start-up done)
            assert time.monotonic() < t_end, "the busy processes did not start running"
            time.sleep(0.02)
        yield n
    finally:
        for h in hogs:
            h.kill()
            h.wait()


def test_busy_share_by_hand():
    # a machine of this process's cores only: each other runnable thread keeps one busy
    assert cores.busy_share(0, 2, 2) == 0
    assert cores.busy_share(1, 2, 2) == 1
    assert cores.busy_share(2, 2, 2) == 2
    assert cores.busy_share(7, 2, 2) == 2            # never more than its cores
    assert cores.busy_share(-1, 2, 2) == 0           # a reading between two changes
    # pinned to 2 of 64 CPUs: 10 others make 0.31 of a core here, 16 make 0.5 (half up), 48 make 1.5
    assert cores.busy_share(10, 2, 64) == 0
    assert cores.busy_share(16, 2, 64) == 1
    assert cores.busy_share(48, 2, 64) == 2
    assert cores.busy_share(3, 8, 16) == 2           # 1.5 rounds up


def test_every_core_busy_gives_one_thread(every_core_busy):
    import numba
    if numba.config.NUMBA_NUM_THREADS < 2:
        pytest.skip("numba runs one thread here")
    assert cores.busy_elsewhere() == every_core_busy
    fit = cores.fit_threads(0, cores.PARALLEL_MIN_NODES)
    assert (fit.threads, fit.busy) == (1, every_core_busy)
    assert numba.get_num_threads() == 1
    small = cores.fit_threads(0, cores.PARALLEL_MIN_NODES - 1)    # a small grid counts nothing
    assert (small.threads, small.busy) == (numba.config.NUMBA_NUM_THREADS, None)
    assert numba.get_num_threads() == numba.config.NUMBA_NUM_THREADS
    capped = cores.fit_threads(1, 10 * cores.PARALLEL_MIN_NODES)  # a limit of one: nothing to count
    assert (capped.threads, capped.limit, capped.busy) == (1, 1, None)
    cores.fit_threads(0, 0)


def test_large_plan_under_load_runs_one_thread_same_path(paper_scenario, request):
    import numba
    if numba.config.NUMBA_NUM_THREADS < 2:
        pytest.skip("numba runs one thread here")
    from spacerobot_planner.planner import Planner
    sc = paper_scenario(3)
    sc = sc.with_grid(sc.grid.with_cells(48))                    # 48 x 49 x 49: above PARALLEL_MIN_NODES
    assert sc.grid.n_nodes >= cores.PARALLEL_MIN_NODES

    def plan():
        return Planner(sc).plan(sc.start_rad, sc.goal_rad)

    before = plan()
    assert before.ok, before.reason
    assert before.solver_stats["threads_limit"] == numba.config.NUMBA_NUM_THREADS
    n = request.getfixturevalue("every_core_busy")
    loaded = plan()
    assert loaded.ok, loaded.reason
    assert (loaded.solver_stats["threads"], loaded.solver_stats["busy_cores"]) == (1, n)
    assert np.array_equal(loaded.path_rad, before.path_rad)
    assert np.array_equal(loaded.field.log_u, before.field.log_u, equal_nan=True)


def test_threads_text():
    assert cores.threads_text({}) == ""
    assert cores.threads_text({"threads": 2, "threads_limit": 2, "busy_cores": 0}) == ""
    assert cores.threads_text({"threads": 1, "threads_limit": 2, "busy_cores": 2}) == (
        "; parallel loops on 1 of 2 threads, 2 cores busy with other work")
