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
- the line the log and the CLI print;
- the process's CPU limit (a container's cgroup quota): read from cgroup trees the test writes
  (v1 and v2, nested, a container's own view, none), rounded up, kept for a second; under a
  limit of one CPU a plan's parallel loops get one thread, it says so, and it plans the same path;
  and, where this test may make a cgroup (root, cgroup v1's ``cpu`` controller), the limit a
  process placed in one reads;
- numba's threading layer in a fresh process that imports the package: OpenMP where the system
  has it, else TBB (installed on x86-64), never the work queue; a user's choice holds.
"""

from __future__ import annotations

import os
import subprocess
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from spacerobot_planner import cores

#: the most busy processes a test starts (one per core of this process)
MOST_HOGS = 8


@pytest.fixture(autouse=True)
def no_cpu_limit(request, monkeypatch):
    """Run the load tests as on a machine with no CPU limit (a CI runner's quota would cap their threads first)."""
    if "cpu_limit" not in request.node.name:
        monkeypatch.setattr(cores, "cpu_limit", lambda: None)


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
    swept = cores.fit_threads(0, 10, any_size=True)              # ... but a stage on threads at any size does
    assert (swept.threads, swept.busy) == (1, every_core_busy)
    assert numba.get_num_threads() == cores.current_threads() == 1
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


_REPAIR_PROBE = """
import hashlib
import numpy as np
from spacerobot_planner import swept
from spacerobot_planner.bench.scenes import random_scenario
from spacerobot_planner.planner import Planner
rng = np.random.default_rng(0)
for _ in range({draws}):
    sc, start = random_scenario(rng, 3)
    if start is not None:
        res = Planner(sc).plan(start)
print(res.code, res.solver_stats.get("repairs"), sc.grid.n_nodes, hashlib.sha256(res.path_rad.tobytes()).hexdigest(),
      len(swept._candidate_chunks.signatures) + len(swept._tested_chunks.signatures),
      len(swept._candidate_rows.signatures) + len(swept._tested_all.signatures))
"""


def test_small_repair_under_load_runs_one_thread_same_path(request):
    """
    A plan's first repair on a small grid counts the busy cores: its swept edges in one thread, the same path.

    On a team of two threads, with another session's process holding a core, each of the swept
    edges' four parallel loops waited a time slice for the member that lost its core (a 36³
    repair 137 ms instead of 14.6).  The repairing scene: the first of ``bench scenes``' 3-DOF
    family (seed 0) whose plan repairs, planned in a fresh process (numba's dispatchers then say
    which kernels ran) once idle and once beside one busy process per core.
    """
    import numba
    _skip_without_proc()
    n = _my_cores()
    if numba.config.NUMBA_NUM_THREADS < 2 or n > MOST_HOGS or n < (os.cpu_count() or 1):
        pytest.skip("numba runs one thread here, or the busy processes cannot hold every core")
    from spacerobot_planner.bench.scenes import random_scenario
    from spacerobot_planner.planner import Planner
    rng = np.random.default_rng(0)
    for draws in range(1, 61):
        sc, start = random_scenario(rng, 3)
        if start is not None and Planner(sc).plan(start).solver_stats.get("repairs", 0) >= 1:
            break
    else:
        pytest.fail("no repairing scene among the family's first 60 draws")

    def judged(fields):
        code, repairs, nodes = fields[:3]
        return code == "ok" and int(repairs) >= 1 and int(nodes) < cores.PARALLEL_MIN_NODES

    _idle_then_loaded(request, _REPAIR_PROBE.format(draws=draws), judged, kernels=2)


def _idle_then_loaded(request, script, judged, kernels):
    """
    Run a probe ``script`` in a fresh process idle, then beside one busy process per core: compare.

    Its last line: fields that ``judged`` accepts, then the path's digest, how many parallel and how
    many one-thread kernels ran (numba's dispatchers' signatures).  Beside the busy processes only the
    ``kernels`` one-thread kernels ran, and the path is the idle one's.
    """
    def probe():
        out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=600,
                             cwd=Path(__file__).parent.parent)
        assert out.returncode == 0, out.stderr[-3000:]
        *fields, digest, parallel, one = out.stdout.split()
        assert judged(fields), out.stdout
        return digest, int(parallel), int(one)

    idle = probe()
    request.getfixturevalue("every_core_busy")
    loaded = probe()
    assert loaded[1:] == (0, kernels), loaded          # beside busy processes: the one-thread kernels only
    assert loaded[0] == idle[0]                        # the same path
    assert kernels in idle[1:]                         # (idle: whichever form the machine's load gave)


_CAPTURE_PROBE = """
import hashlib
from spacerobot_planner import free_floating_capture as ffc
from spacerobot_planner.config import load_scenario
from spacerobot_planner.planner import Planner
sc = load_scenario("config/free_floating_capture.yaml")
res = Planner(sc).plan(sc.start_rad)
ran = lambda *kernels: sum(len(k.signatures) > 0 for k in kernels)
print(res.code, hashlib.sha256(res.path_rad.tobytes()).hexdigest(),
      ran(ffc._attitude_profiles_parallel, ffc._family_changes_parallel),
      ran(ffc._attitude_profiles, ffc._family_changes))
"""


def test_free_floating_capture_under_load_runs_one_thread_same_path(request):
    """
    A free-floating capture counts the busy cores before its scans: beside busy processes, the one-thread kernel.

    The capture's search integrates batches of paths on numba's threads (``free_floating_capture._profiles``,
    ``_family_scan``);
    the pipeline gives the scans the cores other work leaves, as a repair's swept edges.  The capture
    scene planned in a fresh process (numba's dispatchers then say which kernels ran), idle and beside
    one busy process per core: the same path, and beside them the parallel form never ran.
    """
    import numba
    _skip_without_proc()
    n = _my_cores()
    if numba.config.NUMBA_NUM_THREADS < 2 or n > MOST_HOGS or n < (os.cpu_count() or 1):
        pytest.skip("numba runs one thread here, or the busy processes cannot hold every core")

    _idle_then_loaded(request, _CAPTURE_PROBE, lambda fields: fields == ["ok"], kernels=2)


def test_node_by_node_cspace_counts_the_busy_cores_on_a_small_grid(paper_scenario, request, monkeypatch):
    """
    A C-space whose last planned joint is not the chain's last (node by node, a parallel loop at any size) counts.

    The paper 3-DOF arm with its elbow (the last joint) locked: its C-space over the attitude and
    the shoulder runs ``cspace._occupancy_kernel`` on numba's threads on every grid, so beside one
    busy process per core the planner gives it one thread: numba's count as each call of the
    kernel starts (the body table's and the C-space's), and the plan says so; the paper arm
    planning its last joint counts nothing on a small grid.
    """
    import numba
    from spacerobot_planner import cspace
    from spacerobot_planner.cspace import grid_for_robot, loops_at_any_size
    from spacerobot_planner.planner import Planner
    _skip_without_proc()
    n = _my_cores()
    if numba.config.NUMBA_NUM_THREADS < 2 or n > MOST_HOGS or n < (os.cpu_count() or 1):
        pytest.skip("numba runs one thread here, or the busy processes cannot hold every core")
    sc = paper_scenario(3)
    locked = np.array(sc.robot.locked_rad, dtype=float)
    locked[2] = sc.start_rad[2]
    robot = replace(sc.robot, planned_joints=(0, 1), locked_rad=locked)
    assert loops_at_any_size(robot) and not loops_at_any_size(sc.robot)
    two = replace(sc, robot=robot, grid=grid_for_robot(robot, [36, 36]), start_rad=sc.start_rad[:2],
                  goal_rad=sc.goal_rad[:2])
    assert two.grid.n_nodes < cores.PARALLEL_MIN_NODES
    request.getfixturevalue("every_core_busy")
    kernel, counts = cspace._occupancy_kernel, []

    def counted(*args):
        counts.append(numba.get_num_threads())
        return kernel(*args)
    monkeypatch.setattr(cspace, "_occupancy_kernel", counted)
    busy = Planner(two)
    busy.plan(two.start_rad, two.goal_rad)
    assert counts == [1, 1], counts                               # the body table, then the C-space
    note = busy.threads_note()
    assert note["threads"] == 1 and note["busy_cores"] >= 1, note
    rows = Planner(sc)
    rows.plan(sc.start_rad, sc.goal_rad)
    assert "busy_cores" not in rows.threads_note()            # the row kernel's small grid: nothing counted


def test_threads_text():
    assert cores.threads_text({}) == ""
    assert cores.threads_text({"threads": 2, "threads_limit": 2, "busy_cores": 0}) == ""
    assert cores.threads_text({"threads": 1, "threads_limit": 2, "busy_cores": 2}) == (
        "; parallel loops on 1 of 2 threads, 2 cores busy with other work")
    assert cores.threads_text({"threads": 3, "threads_limit": 4, "busy_cores": 1}) == (
        "; parallel loops on 3 of 4 threads, 1 core busy with other work")


def test_threads_text_names_a_cpu_limit():
    assert cores.threads_text({"threads": 1, "threads_limit": 2, "busy_cores": 0, "cpu_limit": 1}) == (
        "; parallel loops on 1 of 2 threads, a CPU limit of 1")
    assert cores.threads_text({"threads": 1, "threads_limit": 8, "busy_cores": 1, "cpu_limit": 2}) == (
        "; parallel loops on 1 of 8 threads, a CPU limit of 2 and 1 core busy with other work")


# ---- the CPU limit: cgroup trees written here, each file's limit by hand ----

def _mount(point, fstype, options="rw", root="/", optional=("shared:9",)) -> str:
    """One /proc/self/mountinfo line of a cgroup mount (spaces in the point escaped as the kernel does)."""
    return (f"41 31 0:38 {root} {str(point).replace(' ', chr(92) + '040')} rw,relatime "
            + "".join(f"{o} " for o in optional) + f"- {fstype} {fstype} {options}")


def _write(directory, **files):
    directory.mkdir(parents=True, exist_ok=True)
    for name, text in files.items():
        (directory / name.replace("__", ".")).write_text(text + "\n")


def test_cpu_limit_of_a_v2_cgroup_is_the_least_up_to_the_mount(tmp_path):
    top = tmp_path / "unified"
    _write(top / "a", cpu__max="150000 100000")          # 1.5 CPUs
    _write(top / "a" / "b", cpu__max="max 100000")        # none of its own
    mounts = _mount(top, "cgroup2")
    assert cores.cgroup_cpu_limit("0::/a/b\n", mounts) == pytest.approx(1.5)
    _write(top / "a" / "b", cpu__max="400000 200000")     # 2 CPUs below 1.5: 1.5 holds
    assert cores.cgroup_cpu_limit("0::/a/b\n", mounts) == pytest.approx(1.5)
    _write(top / "a" / "b", cpu__max="25000 100000")      # a quarter
    assert cores.cgroup_cpu_limit("0::/a/b\n", mounts) == pytest.approx(0.25)
    assert cores.cgroup_cpu_limit("0::/\n", mounts) is None          # the root: no cpu.max
    assert cores.cgroup_cpu_limit("0::/elsewhere\n", mounts) is None  # no such directory


def test_cpu_limit_in_a_container_reads_its_own_cgroup_at_the_mount(tmp_path):
    # inside a container, the cgroup namespace shows "/" and the mount's root is its own cgroup
    point = tmp_path / "sys fs cgroup"
    _write(point, cpu__max="200000 100000")
    assert cores.cgroup_cpu_limit("0::/\n", _mount(point, "cgroup2")) == pytest.approx(2.0)
    # a host's view of a bind mount of a sub-cgroup: the path below the mount's root
    _write(point / "pod", cpu__max="50000 100000")
    mounts = _mount(point, "cgroup2", root="/kubepods/burst")
    assert cores.cgroup_cpu_limit("0::/kubepods/burst/pod\n", mounts) == pytest.approx(0.5)
    assert cores.cgroup_cpu_limit("0::/kubepods/burst\n", mounts) == pytest.approx(2.0)


@pytest.mark.parametrize("optional", [(), ("shared:9",), ("shared:9", "master:2", "propagate_from:4")])
def test_cpu_limit_whatever_the_mount_lines_optional_fields(tmp_path, optional):
    top = tmp_path / "unified"
    _write(top / "a", cpu__max="300000 100000")
    assert cores.cgroup_cpu_limit("0::/a\n", _mount(top, "cgroup2", optional=optional)) == pytest.approx(3.0)


def test_a_cgroup_not_below_the_mount_is_not_read(tmp_path):
    point = tmp_path / "cg"
    _write(point, cpu__max="50000 100000")                # the mount's root: another cgroup's limit
    _write(tmp_path, cpu__max="10000 100000")             # above the mount point
    assert cores.cgroup_cpu_limit("0::/a\n", _mount(point, "cgroup2", root="/b")) is None
    assert cores.cgroup_cpu_limit("0::/../x\n", _mount(point, "cgroup2")) is None     # outside its namespace


def test_odd_bytes_and_names_limit_nothing_and_raise_nothing(tmp_path):
    top = tmp_path / "unified"
    _write(top / "a", cpu__max="150000 100000")
    odd = os.fsdecode(b"44 31 0:40 / /media/stick\xff rw - vfat /dev/sdb1 rw")     # as cpu_limit decodes mountinfo
    mounts = odd + "\n" + _mount(top, "cgroup2") + "\n" + _mount(tmp_path / "n\\000ul", "cgroup2")
    assert cores.cgroup_cpu_limit("0::/a\n", mounts) == pytest.approx(1.5)
    assert cores.cgroup_cpu_limit("0::/a\x00b\n", mounts) is None


def test_cpu_limit_of_a_v1_cpu_controller_and_both_hierarchies(tmp_path):
    cpu = tmp_path / "cpu,cpuacct"
    _write(cpu / "k8s", cpu__cfs_quota_us="-1", cpu__cfs_period_us="100000")
    _write(cpu / "k8s" / "pod", cpu__cfs_quota_us="250000", cpu__cfs_period_us="100000")
    other = tmp_path / "memory"
    _write(other / "k8s" / "pod", cpu__cfs_quota_us="10000", cpu__cfs_period_us="100000")   # not the cpu controller
    mounts = "\n".join([_mount(cpu, "cgroup", "rw,cpu,cpuacct"), _mount(other, "cgroup", "rw,memory")])
    groups = "6:cpuset:/elsewhere\n5:memory:/k8s/pod\n4:cpu,cpuacct:/k8s/pod\n3:cpuacct:/elsewhere\n0::/\n"
    assert cores.cgroup_cpu_limit(groups, mounts) == pytest.approx(2.5)
    _write(cpu / "k8s" / "pod", cpu__cfs_quota_us="-1", cpu__cfs_period_us="100000")
    assert cores.cgroup_cpu_limit(groups, mounts) is None
    # a hybrid machine: the v2 hierarchy limits too, the least holds
    unified = tmp_path / "unified"
    _write(unified / "k8s" / "pod", cpu__max="120000 100000")
    both = mounts + "\n" + _mount(unified, "cgroup2")
    assert cores.cgroup_cpu_limit(groups.replace("0::/", "0::/k8s/pod"), both) == pytest.approx(1.2)
    _write(cpu / "k8s" / "pod", cpu__cfs_quota_us="100000", cpu__cfs_period_us="100000")
    assert cores.cgroup_cpu_limit(groups.replace("0::/", "0::/k8s/pod"), both) == pytest.approx(1.0)


@pytest.mark.parametrize("text", ["", "garbage", "max", "100000", "0 100000", "-5 100000", "100000 0"])
def test_a_cpu_max_not_understood_limits_nothing(tmp_path, text):
    top = tmp_path / "unified"
    _write(top / "a", cpu__max=text)
    assert cores.cgroup_cpu_limit("0::/a\n", _mount(top, "cgroup2")) is None


def test_cpu_limit_rounds_up_and_is_read_at_most_once_a_second(monkeypatch):
    reads = []
    limit = [1.5]

    def scripted(cgroups, mounts):
        reads.append(1)
        return limit[0]
    clock = [100.0]
    monkeypatch.setattr(cores, "cgroup_cpu_limit", scripted)
    monkeypatch.setattr(cores.time, "monotonic", lambda: clock[0])
    monkeypatch.setattr(cores, "_limit_read", [-float("inf"), None])
    assert cores.cpu_limit() == 2
    limit[0] = 0.2
    clock[0] += 0.99 * cores.CPU_LIMIT_MAX_AGE_S
    assert cores.cpu_limit() == 2 and len(reads) == 1            # kept: read again only after a second
    for value, whole in ((0.2, 1), (2.0, 2), (2.00001, 3), (None, None)):
        limit[0] = value
        clock[0] += cores.CPU_LIMIT_MAX_AGE_S
        assert cores.cpu_limit() == whole, value
    assert len(reads) == 5


def test_a_plan_under_a_cpu_limit_of_one_runs_one_thread_and_plans_the_same(paper_scenario, monkeypatch):
    import numba
    if numba.config.NUMBA_NUM_THREADS < 2:
        pytest.skip("numba runs one thread here")
    from spacerobot_planner.planner import Planner
    sc = paper_scenario(3)
    monkeypatch.setattr(cores, "cpu_limit", lambda: None)
    free = Planner(sc).plan(sc.start_rad, sc.goal_rad)
    assert free.ok, free.reason
    assert "cpu_limit" not in free.solver_stats and numba.get_num_threads() == numba.config.NUMBA_NUM_THREADS
    monkeypatch.setattr(cores, "cpu_limit", lambda: 1)
    try:
        planner = Planner(sc)
        limited = planner.plan(sc.start_rad, sc.goal_rad)
        assert limited.ok, limited.reason
        assert numba.get_num_threads() == 1                          # the planning thread's kernels
        assert (limited.solver_stats["threads"], limited.solver_stats["cpu_limit"]) == (1, 1)
        assert "a CPU limit of 1" in cores.threads_text(limited.solver_stats)
        assert np.array_equal(limited.path_rad, free.path_rad)
        replan = planner.plan(sc.start_rad + 0.01, sc.goal_rad)       # cached: no stage ran loops, nothing noted
        assert replan.ok and "field" in replan.cached and "cpu_limit" not in replan.solver_stats
        # threads_follow_load false keeps the configured number, the limit notwithstanding
        kept = Planner(sc, settings=replace(sc.planner_settings, threads_follow_load=False)).plan(
            sc.start_rad, sc.goal_rad)
        assert "cpu_limit" not in kept.solver_stats and numba.get_num_threads() == numba.config.NUMBA_NUM_THREADS
    finally:
        monkeypatch.setattr(cores, "cpu_limit", lambda: None)
        cores.fit_threads(0, 0)


def _own_v1_cpu_cgroup():
    """Return this process's cgroup v1 ``cpu`` directory where it is writable here, else None."""
    base = "/sys/fs/cgroup/cpu"
    try:
        with open("/proc/self/cgroup") as f:
            line = next(ln for ln in f.read().splitlines() if "cpu" in ln.split(":")[1].split(","))
    except (OSError, StopIteration, IndexError):
        return None
    d = os.path.join(base, line.split(":", 2)[2].lstrip("/"))
    ok = os.path.exists(os.path.join(d, "cpu.cfs_quota_us")) and os.access(d, os.W_OK)
    return d if ok else None


def test_a_process_in_a_cgroup_of_a_cpu_and_a_half_reads_two():
    d = _own_v1_cpu_cgroup()
    if d is None:
        pytest.skip("no writable cgroup v1 cpu controller here (not root, or cgroup v2 only)")
    child = os.path.join(d, f"spacerobot_test_{os.getpid()}")
    try:
        os.mkdir(child)
        with open(os.path.join(child, "cpu.cfs_period_us"), "w") as f:
            f.write("100000")
        with open(os.path.join(child, "cpu.cfs_quota_us"), "w") as f:
            f.write("150000")
    except OSError as e:
        if os.path.isdir(child):
            os.rmdir(child)
        pytest.skip(f"cannot make a cgroup here: {e}")
    try:
        code = (f"import os; open({os.path.join(child, 'cgroup.procs')!r}, 'w').write(str(os.getpid())); "
                "from spacerobot_planner import cores; print(cores.cpu_limit())")
        out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
        assert out.returncode == 0, out.stderr
        assert out.stdout.split() == ["2"]
    finally:
        os.rmdir(child)


_LAYER_RUN = """
import sys
{before}
import spacerobot_planner
import numba
import numpy as np

@numba.njit(parallel=True)
def total(a):
    s = 0.0
    for i in numba.prange(a.size):
        s += a[i]
    return s

assert total(np.ones(1000)) == 1000.0
print(numba.threading_layer())
"""


def _layer(before: str = "", plain_venv: bool = False, **env) -> str:
    """
    Return the threading layer a fresh process's first parallel loop runs on (the package imported first).

    ``plain_venv``: without the library path this project's virtualenv sets (its ROS wheels'
    bootstrap), as a plain virtualenv or a system prefix before ``ldconfig`` runs.
    """
    clean = {k: v for k, v in os.environ.items() if not k.startswith("NUMBA_THREADING_LAYER")}
    if plain_venv:
        clean.update(_ROS_WHEELS_BOOTSTRAP_COMPLETE="1", LD_LIBRARY_PATH="")
    out = subprocess.run([sys.executable, "-c", _LAYER_RUN.format(before=before)], capture_output=True, text=True,
                         timeout=300, env=dict(clean, **env))
    assert out.returncode == 0, out.stderr
    return out.stdout.split()[-1]


#: run before the package's import: as on a machine without the system's OpenMP runtime
_NO_OPENMP = """
import ctypes
_cdll = ctypes.CDLL
class _NoGomp(_cdll):
    def __init__(self, name, *args, **kwargs):
        if name and "gomp" in str(name):
            raise OSError("no libgomp here")
        super().__init__(name, *args, **kwargs)
ctypes.CDLL = _NoGomp
sys.modules["numba.np.ufunc.omppool"] = None
"""


def _loads(name: str) -> bool:
    import ctypes
    try:
        ctypes.CDLL(name)
    except OSError:
        return False
    return True


def _tbb_wheel() -> bool:
    return os.path.exists(os.path.join(sys.prefix, "lib", "libtbb.so.12"))


def test_parallel_loops_run_on_openmp_where_it_loads_and_never_on_the_work_queue_beside_tbb():
    layer = _layer()
    if _loads("libgomp.so.1"):
        assert layer == "omp", layer
    elif _tbb_wheel() or _loads("libtbb.so.12"):
        assert layer == "tbb", layer
    else:
        pytest.skip(f"neither OpenMP nor TBB here (numba runs on {layer})")


def test_without_openmp_the_loops_run_on_the_tbb_wheel_even_off_the_loaders_path():
    if not _tbb_wheel():
        pytest.skip("no tbb wheel in this prefix (installed on x86-64 only)")
    assert _layer(_NO_OPENMP) == "tbb"
    assert _layer(_NO_OPENMP, plain_venv=True) == "tbb"
    # a process started by one that imported the package (the planning process) inherits the order
    assert _layer(_NO_OPENMP, plain_venv=True, NUMBA_THREADING_LAYER_PRIORITY="omp tbb workqueue") == "tbb"


def test_a_users_threading_layer_choice_holds():
    assert _layer(NUMBA_THREADING_LAYER_PRIORITY="workqueue omp tbb") == "workqueue"
    assert _layer(NUMBA_THREADING_LAYER="workqueue") == "workqueue"
    # chosen in code before the package's import: kept (numba's config is not read again)
    assert _layer("import numba; numba.config.THREADING_LAYER = 'workqueue'") == "workqueue"
