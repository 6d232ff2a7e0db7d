"""
A plan's parallel loops get no more threads than other work leaves cores (``cores``).

- the share of the machine's other work that falls on this process's cores, by hand;
- a reading: the machine's runnable threads less this process's own, scaled, from scripted
  readings; a count above zero read again and the least one kept;
- this process's running threads, with threads of known state started by the test;
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


def _skip_without_proc():
    if not os.path.exists("/proc/loadavg") or not os.path.exists("/proc/self/task"):
        pytest.skip("no /proc/loadavg or /proc/self/task (not Linux)")


@pytest.fixture
def every_core_busy():
    """One busy-loop process per core of this process, each seen running, stopped after the test."""
    _skip_without_proc()
    n = _my_cores()
    if n > MOST_HOGS or n < (os.cpu_count() or 1):
        pytest.skip(f"{n} cores (more than {MOST_HOGS}), or fewer than the machine's {os.cpu_count()} "
                    "(the machine's other work is scaled to them)")
    hogs = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(n)]
    try:
        t_end = time.monotonic() + 60.0
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


def test_a_reading_counts_the_others_on_this_process_cores(monkeypatch):
    readings = {"machine": 5, "here": 2, "cores": 2, "online": 2}
    monkeypatch.setattr(cores, "_runnable_on_machine", lambda: readings["machine"])
    monkeypatch.setattr(cores, "_running_here", lambda: readings["here"])
    monkeypatch.setattr(cores, "_cores", lambda: readings["cores"])
    monkeypatch.setattr(cores.os, "cpu_count", lambda: readings["online"])
    # 5 runnable on the machine, 2 of them this process's: 3 others, on 2 cores of 2: both busy
    assert cores._busy_now() == 2
    readings.update(machine=3)                      # 1 other: one core busy
    assert cores._busy_now() == 1
    readings.update(machine=2)                      # only this process's threads run
    assert cores._busy_now() == 0
    readings.update(machine=12, here=2, cores=4, online=16)     # 10 others spread over 16 CPUs: 2.5 of 4
    assert cores._busy_now() == 3
    readings.update(machine=None)
    assert cores._busy_now() is None


def test_a_busy_reading_is_read_again_and_the_least_kept(monkeypatch):
    def scripted(values):
        it = iter(values)
        calls = []

        def reading():
            calls.append(1)
            return next(it)
        monkeypatch.setattr(cores, "_busy_now", reading)
        return calls

    scripted([0])
    assert cores.busy_elsewhere() == 0
    calls = scripted([2, 1, 1, 1, 1] + [1] * 20)      # a busy core all along: 1 holds, read 4 times more
    assert cores.busy_elsewhere() == 1
    assert len(calls) == 1 + cores.CONFIRM_READINGS
    scripted([1, 2, 0] + [2] * 20)                    # a burst: gone at the second reading after
    assert cores.busy_elsewhere() == 0
    scripted([2, None, 1] + [1] * 20)                 # an unreadable reading again changes nothing
    assert cores.busy_elsewhere() == 1
    scripted([None])
    assert cores.busy_elsewhere() is None


def test_running_here_counts_this_process_running_threads():
    """Threads that sort (numpy lets the interpreter go) run beside the reading one; sleeping ones do not count."""
    import threading
    _skip_without_proc()
    stop = threading.Event()
    data = np.random.default_rng(0).random(1_000_000)

    def sort_until_stopped():
        while not stop.is_set():
            np.sort(data)

    sleepers = [threading.Thread(target=stop.wait) for _ in range(3)]
    for t in sleepers:
        t.start()
    time.sleep(0.2)                    # numba's team, should a test before have run a loop, stops spinning
    quiet = min(cores._running_here() for _ in range(20))     # the reader and no sorter
    sorters = [threading.Thread(target=sort_until_stopped) for _ in range(2)]
    try:
        for t in sorters:
            t.start()
        time.sleep(0.05)
        busy = max(cores._running_here() for _ in range(50))
    finally:
        stop.set()
        for t in sorters + sleepers:
            t.join()
    assert quiet >= 1
    assert busy >= quiet + 2 >= 3, (quiet, busy)


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
    _skip_without_proc()
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
    assert cores.threads_text({"threads": 3, "threads_limit": 4, "busy_cores": 1}) == (
        "; parallel loops on 3 of 4 threads, 1 core busy with other work")
