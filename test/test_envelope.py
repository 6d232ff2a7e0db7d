"""
Capture envelope maps (issue 21): ``spacerobot_planner.envelope`` and ``spacerobot-plan envelope``.

- a sweep on a ``distributed.LocalCluster`` the test starts equals the serial sweep row by
  row (every column but the wall times), and a few of its rows replanned one by one with a
  fresh plain ``Planner`` (and the node's chain) agree; the goals grasp the target where the
  test's own geometry puts the handle;
- a sweep killed (SIGKILL, in a subprocess) after some chunks resumes: the rerun plans only
  the poses without a row (counted from its own record and the manifest) and the final table
  equals the uninterrupted one;
- a pose whose planning raises becomes an ``internal_error`` row with the reason, and the
  sweep completes;
- the command: its files, Parquet equal to the CSV, bad input naming the flag;
- the default chunks shrink towards the end and never split a target's starts; the local
  cluster's workers start without the MALLOC_TRIM_THRESHOLD_ Dask sets.

Kept small: the paper's 2-DOF scene on a 31×31 grid, 2 x × 2 y × 1 yaw × 2 starts.
"""

import csv
import io
import json
import math
import os
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from oracles import arm_points
from spacerobot_planner.adapters import post_process
from spacerobot_planner.config import load_scenario
from spacerobot_planner.envelope import (TIMING_COLUMNS, PoseGrid, axis_values, read_rows, run_envelope,
                                         sweep_spec)
from spacerobot_planner.envelope.engine import MAX_CHUNK, Progress, guided_size, local_cluster
from spacerobot_planner.envelope.sweep import COLUMNS, chunks
from spacerobot_planner.motion import MotionValidator
from spacerobot_planner.planner import Planner
from spacerobot_planner.scene import Target
from spacerobot_planner.tools.cli import main as cli_main

ROOT = Path(__file__).resolve().parent.parent
P2 = ROOT / "config" / "paper_2dof.yaml"
CELLS = 30
#: the paper's target at (−3.27, −2.60) and a pose 0.25 m right of it (ok and goal_unreachable, see below)
X_M, Y_M, YAW_DEG = (-3.27, -3.02, 2), (-2.60, -2.45, 2), (0.0, 0.0, 1)
STARTS_DEG = ((135.0, 90.0), (120.0, 100.0))


def _scenario():
    sc = load_scenario(P2)
    return sc.with_grid(sc.grid_with_cells([CELLS, CELLS]))


def _grid(sc):
    return PoseGrid(axis_values(*X_M, "x"), axis_values(*Y_M, "y"), axis_values(*YAW_DEG, "yaw"),
                    tuple(tuple(np.radians(s)) for s in STARTS_DEG))


def _spec(sc, grid):
    return sweep_spec(P2, sc.grid.cells, grid)


def _same(a, b) -> bool:
    if isinstance(a, float) and isinstance(b, float) and math.isnan(a) and math.isnan(b):
        return True
    return a == b


def _differences(rows_a, rows_b) -> list:
    """Every (pose_id, column, a, b) where two tables differ, wall times aside."""
    assert [r["pose_id"] for r in rows_a] == [r["pose_id"] for r in rows_b]
    return [(ra["pose_id"], k, ra[k], rb[k]) for ra, rb in zip(rows_a, rows_b) for k in ra
            if k not in TIMING_COLUMNS and not _same(ra[k], rb[k])]


@pytest.fixture(scope="module")
def serial(tmp_path_factory):
    """Return the uninterrupted serial sweep (in this process, chunks of 3): (scenario, grid, report)."""
    sc = _scenario()
    grid = _grid(sc)
    report = run_envelope(sc, grid, tmp_path_factory.mktemp("serial"), _spec(sc, grid), workers=0, chunk_size=3,
                          quiet=True)
    return sc, grid, report


def test_poses_are_numbered_starts_fastest_then_x_y_yaw():
    grid = PoseGrid((1.0, 2.0, 3.0), (10.0, 20.0), (0.0, 45.0), ((0.0,), (1.0,)))
    assert grid.n_poses == 3 * 2 * 2 * 2
    poses = [grid.pose(i) for i in range(grid.n_poses)]
    expected = [(x, y, a, s) for a in (0.0, 45.0) for y in (10.0, 20.0) for x in (1.0, 2.0, 3.0) for s in (0, 1)]
    assert [(p.x_m, p.y_m, p.yaw_deg, p.start_index) for p in poses] == expected
    assert chunks([7, 0, 3, 1, 2], 2) == [[0, 1], [2, 3], [7]]


def test_default_chunks_shrink_towards_the_end_and_keep_a_targets_starts_together():
    # 20 poses, 2 starts per target, 2 worker slots: each chunk a quarter of what is left
    # (at least 2), extended to the end of its target: 5 -> 6, 14/4 -> 4, 10/4 -> 3 -> 4, then 2s
    assert chunks(range(20), guided_size(2), group=2) == [
        list(range(0, 6)), list(range(6, 10)), list(range(10, 14)), [14, 15], [16, 17], [18, 19]]
    rng = np.random.default_rng(5)
    for slots, group in ((1, 1), (2, 2), (3, 3), (16, 2)):
        ids = sorted(rng.choice(2000, size=int(rng.integers(1, 1500)), replace=False).tolist())
        work = chunks(rng.permutation(ids), guided_size(slots), group=group)
        assert [i for c in work for i in c] == ids                  # every id once, in order
        for a, b in zip(work, work[1:]):
            assert a[-1] // group != b[0] // group                  # no target split between chunks
        assert all(1 <= len(c) <= MAX_CHUNK + group - 1 for c in work)
        # large first (a 1/(2·slots) share of all, at most MAX_CHUNK), small last
        assert len(work[0]) >= min(len(ids), MAX_CHUNK, math.ceil(len(ids) / (2 * slots)))
        assert len(work[-1]) <= 2 + group - 1 or len(work) == 1
    with pytest.raises(ValueError, match="≥ 1"):
        chunks([1, 2], lambda left: 0)


def test_the_local_clusters_workers_start_without_dasks_malloc_trim_threshold(monkeypatch):
    from distributed import Client

    # as a Dask cluster started before in this process leaves it in the environment
    monkeypatch.setenv("MALLOC_TRIM_THRESHOLD_", "65536")
    with local_cluster(1) as cluster, Client(cluster) as client:
        seen = client.run(lambda: (os.environ.get("MALLOC_TRIM_THRESHOLD_"), os.getpid()))
        assert os.environ.get("MALLOC_TRIM_THRESHOLD_") == "65536"          # this process's is back
    assert len(seen) == 1
    ((trim, pid),) = seen.values()
    assert pid != os.getpid() and trim is None


def test_the_local_clusters_workers_ignore_a_terminals_ctrl_c():
    """A terminal's Ctrl-C reaches every process of its group: the workers printed KeyboardInterrupt tracebacks."""
    import signal
    from distributed import Client
    before = signal.getsignal(signal.SIGINT)
    with local_cluster(1) as cluster, Client(cluster) as client:
        assert signal.getsignal(signal.SIGINT) is before                 # this process's is back
        seen = client.run(lambda: signal.getsignal(signal.SIGINT) == signal.SIG_IGN)
    assert list(seen.values()) == [True], seen


def test_the_serial_sweep_covers_the_grid_with_both_outcomes(serial):
    sc, grid, rep = serial
    assert rep.complete and rep.done_before == 0 and rep.planned == grid.n_poses == 8
    rows = rep.rows
    assert [r["pose_id"] for r in rows] == list(range(8))
    # the poses, from the test's own grid
    xs, ys = np.linspace(*X_M[:2], 2), np.linspace(*Y_M[:2], 2)
    assert {(r["x_m"], r["y_m"]) for r in rows} == {(x, y) for x in xs for y in ys}
    codes = {r["code"] for r in rows}
    assert "ok" in codes and codes - {"ok"}, codes          # the map has both sides of its boundary
    for r in rows:
        assert (r["code"] == "ok") == (r["reason"] == "")
        assert (r["code"] == "ok") == math.isfinite(r["path_length_rad"]) == math.isfinite(r["duration_s"])


def test_ok_goals_grasp_the_pose_target_in_the_tests_own_geometry(serial):
    sc, grid, rep = serial
    robot, tgt = sc.robot, sc.scene.target
    tol = sc.acs.position_tolerance_m
    oks = [r for r in rep.rows if r["code"] == "ok"]
    assert oks
    for r in oks:
        q_full = robot.full(np.radians([float(v) for v in r["goal_deg"].split()]))
        tip = arm_points(robot, q_full)[-1]
        yaw = math.radians(r["yaw_deg"])
        d = 0.5 * tgt.body_side_m + tgt.handle_side_m
        grasp = np.array([r["x_m"] - d * math.sin(yaw), r["y_m"] + d * math.cos(yaw)])
        assert np.linalg.norm(tip - grasp) <= tol + 1e-6, (r["pose_id"], tip, grasp)


def test_a_sweep_on_a_local_cluster_equals_the_serial_sweep_row_by_row(serial, tmp_path):
    from distributed import Client, get_task_stream

    sc, grid, ser = serial
    with local_cluster(2) as cluster, Client(cluster) as client, get_task_stream(client) as stream:
        # as `--scheduler ADDRESS` does: the sweep opens its own client on the running cluster
        rep = run_envelope(sc, grid, tmp_path, _spec(sc, grid), scheduler=cluster.scheduler_address, chunk_size=1,
                           quiet=True)
        workers = len(client.scheduler_info()["workers"])
    assert workers == 2
    assert rep.complete and rep.planned == grid.n_poses and rep.chunks == grid.n_poses
    tasks = [t for t in stream.data if "plan_chunk" in str(t.get("key"))]
    assert len(tasks) == grid.n_poses, stream.data                  # the chunks ran on the cluster
    assert _differences(ser.rows, rep.rows) == []
    # what the folder holds is the table the run returned
    assert _differences(rep.rows, read_rows(tmp_path / "envelope.csv")) == []


def test_chunks_cancelled_with_a_lost_worker_are_planned_again_not_written_as_failures(serial, tmp_path):
    """
    The scenario's scattered copy lost (as with the only worker holding it killed) once the first chunk is submitted.

    Dask then cancels the chunks that need it ("already forgotten"): they had been written as
    ``internal_error`` rows, the run ending "complete" and a rerun planning nothing (an audit's
    remote worker, killed mid-sweep).  Now the scenario is scattered again and those chunks
    planned again: the table equals the serial sweep's.  Lost before any chunk can run, so the
    first chunk is cancelled whatever the machine's speed.
    """
    from distributed import Client

    sc, grid, ser = serial
    scattered, submitted = [], []
    with local_cluster(2) as cluster, Client(cluster) as client:
        real_scatter, real_submit = client.scatter, client.submit

        def scatter(*a, **k):
            scattered.append(real_scatter(*a, **k))
            return scattered[-1]

        def submit(*a, **k):
            submitted.append(real_submit(*a, **k))
            if len(submitted) == 1:
                client.cancel(scattered[0])         # its copies gone: the chunk submitted on it is cancelled
            return submitted[-1]

        client.scatter, client.submit = scatter, submit
        rep = run_envelope(sc, grid, tmp_path, _spec(sc, grid), client=client, chunk_size=1, quiet=True)
    assert len(scattered) >= 2 and len(submitted) > grid.n_poses        # scattered again, a chunk submitted again
    assert rep.complete and rep.planned == grid.n_poses
    assert [r["pose_id"] for r in rep.rows if r["code"] == "internal_error"] == []
    assert _differences(ser.rows, rep.rows) == []


@pytest.mark.parametrize("pose_id", [0, 1, 3, 6])
def test_rows_replanned_one_by_one_with_the_plain_planner_agree(serial, pose_id):
    sc, grid, rep = serial
    row = rep.rows[pose_id]
    p = grid.pose(pose_id)
    base = sc.scene.target
    scene = sc.scene.with_target(Target((p.x_m, p.y_m), math.radians(p.yaw_deg), base.body_side_m,
                                        base.handle_side_m))
    one = sc.with_scene(scene)
    start = np.radians(STARTS_DEG[p.start_index])
    res = Planner(one, reaction=True).plan(start)
    assert row["code"] == str(res.code)
    assert _same(row["path_length_rad"], res.path_length_rad if len(res.path_rad) else math.nan)
    assert _same(row["min_clearance_m"], res.min_clearance_m)
    if res.trajectory is not None:
        dense = post_process(one, res.path_rad, start_rad=start,
                             motions=MotionValidator.for_scene(one.robot, one.scene)).dense
        assert row["duration_s"] == dense.duration_s
    if res.goal_rad is not None:
        assert np.allclose(np.radians([float(v) for v in row["goal_deg"].split()]), res.goal_rad, atol=1e-7)


def test_a_ctrl_c_in_a_serial_sweep_finishes_the_pose_then_stops_and_resumes(serial, tmp_path, monkeypatch):
    """
    A SIGINT while a pose is planned in this process (``--workers 0``): that pose is written, the sweep stops.

    A KeyboardInterrupt inside a numba kernel had come out as a SystemError, an
    ``internal_error`` row, and the sweep went on to exit 0 (an audit, 2 of 4 tries).  The
    signal is raised here as pose 4's plan begins; poses 0-4 are in the table, none an
    ``internal_error``, and the rerun plans the rest: the serial sweep's table.
    """
    from spacerobot_planner.envelope import sweep
    sc, grid, ser = serial
    real = sweep.plan_pose

    def interrupted(planner, scenario, grid_, i):
        if i == 4:
            signal.raise_signal(signal.SIGINT)
        return real(planner, scenario, grid_, i)

    monkeypatch.setattr(sweep, "plan_pose", interrupted)
    with pytest.raises(KeyboardInterrupt):
        run_envelope(sc, grid, tmp_path, _spec(sc, grid), workers=0, chunk_size=3, quiet=True)
    first = read_rows(tmp_path / "envelope.csv")
    assert sorted(r["pose_id"] for r in first) == [0, 1, 2, 3, 4]
    assert all(r["code"] != "internal_error" for r in first)
    monkeypatch.setattr(sweep, "plan_pose", real)
    rep = run_envelope(sc, grid, tmp_path, _spec(sc, grid), workers=0, quiet=True)
    assert rep.done_before == 5 and rep.complete and _differences(ser.rows, rep.rows) == []


def test_a_pose_that_raises_becomes_an_internal_error_row(serial, tmp_path, monkeypatch):
    sc, grid, ser = serial
    bad = grid.pose(2)
    plan = Planner.plan

    def failing(self, start_rad, goal_rad=None, cancel=None, progress=None):
        if self.scenario.scene.target.center_m == (bad.x_m, bad.y_m):
            raise RuntimeError("injected failure in the planner")
        return plan(self, start_rad, goal_rad, cancel, progress)

    monkeypatch.setattr(Planner, "plan", failing)
    rep = run_envelope(sc, grid, tmp_path, _spec(sc, grid), workers=0, chunk_size=4, quiet=True)
    assert rep.complete and len(rep.rows) == grid.n_poses
    hit = [r for r in rep.rows if (r["x_m"], r["y_m"]) == (bad.x_m, bad.y_m)]
    assert len(hit) == 2                                           # both starts of that target
    for r in hit:
        assert r["code"] == "internal_error"
        assert "RuntimeError: injected failure in the planner" in r["reason"]
        assert math.isnan(r["path_length_rad"])
    rest = [r for r in rep.rows if r not in hit]
    assert _differences([r for r in ser.rows if r["pose_id"] in {x["pose_id"] for x in rest}], rest) == []


KILLED_RUN = """
import os, signal, sys
import numpy as np
sys.path.insert(0, {test_dir!r})
import test_envelope as t
from spacerobot_planner.envelope import run_envelope
sc = t._scenario(); grid = t._grid(sc); seen = []

def after_chunk(rows):
    seen.append(rows)
    if len(seen) == {kill_after}:
        os.kill(os.getpid(), signal.SIGKILL)       # killed between two chunks

run_envelope(sc, grid, {out!r}, t._spec(sc, grid), workers=0, chunk_size=1, quiet=True, after_chunk=after_chunk)
"""


def test_a_killed_sweep_resumes_planning_only_what_is_missing(serial, tmp_path):
    sc, grid, ser = serial
    out = tmp_path / "sweep"
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]))
    script = KILLED_RUN.format(test_dir=str(Path(__file__).parent), kill_after=3, out=str(out))
    r = subprocess.run([sys.executable, "-c", script], env=env, capture_output=True, text=True, timeout=300)
    assert r.returncode == -signal.SIGKILL, r.stderr[-3000:]
    first = read_rows(out / "envelope.csv")
    assert len(first) == 3
    manifest = json.loads((out / "envelope.json").read_text())
    assert [run["complete"] for run in manifest["runs"]] == [False]     # the killed run never ended
    # a kill in the middle of a write leaves a torn line: that pose is planned again
    torn = next(row for row in ser.rows if row["pose_id"] not in {x["pose_id"] for x in first})
    with open(out / "envelope.csv", "a") as f:
        f.write(f"{torn['pose_id']},{torn['x_m']},{torn['y_m']},0.0,0,ok,1.2")
    rep = run_envelope(sc, grid, out, _spec(sc, grid), workers=0, quiet=True)
    missing = sorted(set(range(grid.n_poses)) - {x["pose_id"] for x in first})
    assert rep.done_before == 3
    assert sorted(rep.planned_ids) == missing and len(rep.planned_ids) == len(set(rep.planned_ids))
    runs = json.loads((out / "envelope.json").read_text())["runs"]
    assert runs[-1]["planned"] == len(missing) and runs[-1]["complete"] and runs[-1]["poses_to_plan"] == len(missing)
    assert rep.complete and _differences(ser.rows, rep.rows) == []
    assert _differences(ser.rows, read_rows(out / "envelope.csv")) == []
    # a third run has nothing left to plan
    again = run_envelope(sc, grid, out, _spec(sc, grid), workers=0, quiet=True)
    assert again.planned == 0 and again.complete


def test_a_folder_of_another_sweep_is_refused(serial, tmp_path):
    """A folder of another sweep is refused, naming what differs and the values of both (the folder's, this one's)."""
    sc, grid, _ = serial
    small = PoseGrid(grid.x_m[:1], grid.y_m[:1], grid.yaw_deg, grid.starts_rad[:1])
    run_envelope(sc, small, tmp_path, _spec(sc, small), workers=0, quiet=True)
    with pytest.raises(ValueError, match="another sweep.*poses") as e:
        run_envelope(sc, grid, tmp_path, _spec(sc, grid), workers=0, quiet=True)
    said = str(e.value)
    assert f"x_m [{grid.x_m[0]:g}] there, " in said and f"y_m [{grid.y_m[0]:g}] there, " in said, said
    assert "yaw_deg" not in said, said                  # the same in both
    for values in (grid.x_m, grid.y_m):
        here = f"[{', '.join(f'{v:g}' for v in values)}] here" if len(values) <= 4 else f"{len(values)} values"
        assert here in said, (here, said)
    # values that read the same in short: the first that differs, in full
    nudged = PoseGrid(grid.x_m[:1], (grid.y_m[0] + 1e-7,), grid.yaw_deg, grid.starts_rad[:1])
    with pytest.raises(ValueError, match="another sweep") as e:
        run_envelope(sc, nudged, tmp_path, _spec(sc, nudged), workers=0, quiet=True)
    assert f"y_m[0] {float(grid.y_m[0])!r} there, {float(grid.y_m[0] + 1e-7)!r} here" in str(e.value), str(e.value)


def test_a_table_of_another_sweep_without_its_manifest_is_refused(serial, tmp_path):
    """
    ``envelope.csv`` left without ``envelope.json``: rows of another grid are refused, naming the line.

    Before, their ids were taken as done (a 4-pose sweep over 4 foreign rows planned nothing and
    exited 0; over 300 it said "-296 poses not planned" at every rerun).  Oracle: the rows the test
    wrote, changed by hand from the serial sweep's.
    """
    sc, grid, ser = serial
    out = tmp_path / "stale"
    out.mkdir()
    names = [n for n, _ in COLUMNS]

    def write(rows):
        buf = io.StringIO()
        w = csv.writer(buf, lineterminator="\n")
        w.writerow(names)
        w.writerows([[repr(r[n]) if isinstance(r[n], float) else r[n] for n in names] for r in rows])
        (out / "envelope.csv").write_text(buf.getvalue())
    rows = [dict(r) for r in ser.rows[:4]]
    rows[2]["x_m"] += 0.5                                  # one row of another grid
    write(rows)
    with pytest.raises(ValueError, match=r"line 4 is another sweep's pose \(pose 2: .*no envelope.json"):
        run_envelope(sc, grid, out, _spec(sc, grid), workers=0, quiet=True)
    rows[2]["x_m"] -= 0.5                                  # this sweep's own rows, manifest lost: resumed
    rows[3]["pose_id"] = grid.n_poses + 7                  # ... but an id beyond its poses is not
    write(rows)
    with pytest.raises(ValueError, match=f"line 5 is another sweep's pose .*this sweep has {grid.n_poses} poses"):
        run_envelope(sc, grid, out, _spec(sc, grid), workers=0, quiet=True)
    write(rows[:3])
    rep = run_envelope(sc, grid, out, _spec(sc, grid), workers=0, quiet=True)
    assert rep.done_before == 3 and rep.complete and _differences(ser.rows, rep.rows) == []


def test_a_sweep_that_cannot_reach_its_scheduler_leaves_no_new_folder_and_an_old_one_as_it_was(
        serial, tmp_path, monkeypatch):
    """``--scheduler`` that does not answer (Dask's own 30 s, here at once): no folder made for nothing (audit)."""
    from spacerobot_planner.envelope import engine
    sc, grid, ser = serial

    def unreachable(stack, scheduler, workers):
        raise ValueError(f"--scheduler {scheduler}: cannot connect: timed out")
    monkeypatch.setattr(engine, "_client", unreachable)
    new = tmp_path / "a" / "new"
    with pytest.raises(ValueError, match="cannot connect"):
        run_envelope(sc, grid, new, _spec(sc, grid), scheduler="tcp://127.0.0.1:9", quiet=True)
    assert not new.exists() and (tmp_path / "a").exists()       # its parent made on the way stays
    old = tmp_path / "old"
    run_envelope(sc, grid, old, _spec(sc, grid), workers=0, quiet=True)
    before = {p.name: p.read_bytes() for p in old.iterdir()}
    with pytest.raises(ValueError, match="cannot connect"):
        run_envelope(sc, grid, old, _spec(sc, grid), scheduler="tcp://127.0.0.1:9", quiet=True)
    assert {p.name: p.read_bytes() for p in old.iterdir()} == before


def test_a_scheduler_without_workers_is_named_and_leaves_no_folder(serial, tmp_path, monkeypatch):
    """
    A scheduler no worker has joined: waited for a while, then refused naming ``--scheduler``, no folder left.

    It had waited silently, or said "--out ...: No valid workers found" after 30 s and left the
    folder's files behind (an audit).  Here a local scheduler without workers, a 1 s wait.
    """
    from distributed import LocalCluster
    from spacerobot_planner.envelope import engine
    sc, grid, _ = serial
    monkeypatch.setattr(engine, "WORKER_WAIT_S", 1.0)
    out = tmp_path / "sweep"
    with LocalCluster(n_workers=0, processes=False, dashboard_address=":0") as cluster:
        with pytest.raises(ValueError, match=r"--scheduler .*: no worker joined it in 1 s \(start one: dask worker"):
            run_envelope(sc, grid, out, _spec(sc, grid), scheduler=cluster.scheduler_address, quiet=True)
    assert not out.exists()


def test_the_maps_show_a_range_given_from_its_larger_end_and_name_close_yaws_apart():
    """
    A reversed range's cells are all in the panel, the scenario's target too; close yaws get their own files.

    The panel had shown one corner; yaws 0.0004° apart, rounded to 0.001°, had shared a name and
    one map overwrote the other (an audit).
    """
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from spacerobot_planner.envelope.plots import _edges, _panel_limits, figure_name
    sc = _scenario()
    xs, ys = np.linspace(-2.6, -3.6, 3), np.linspace(-2.2, -3.0, 3)         # as given: larger end first
    fig, ax = plt.subplots()
    body = np.array([[-0.9, -0.9], [0.9, -0.9], [0.9, 0.9], [-0.9, 0.9]])
    target = np.asarray(sc.scene.target.body_polygon_m)
    _panel_limits(ax, _edges(xs), _edges(ys), body, target)
    (x0, x1), (y0, y1) = ax.get_xlim(), ax.get_ylim()
    plt.close(fig)
    for lo, hi, values in ((x0, x1, np.r_[xs, target[:, 0]]), (y0, y1, np.r_[ys, target[:, 1]])):
        assert lo < values.min() and values.max() < hi, (lo, hi, values)
    names = [figure_name(0, yaw, 1) for yaw in (-0.0004, 0.0, 0.0004, -1e-9)]
    assert len(set(names[:3])) == 3 and names[3] == names[1] == "envelope_yaw0deg.png", names


def test_the_progress_bar_shows_rate_and_eta_on_a_terminal_only():
    class Tty(io.StringIO):
        def isatty(self):
            return True

    tty, pipe = Tty(), io.StringIO()
    for stream in (tty, pipe):
        bar = Progress(10, 2, stream=stream)
        bar.update(3)
        bar.close()
    assert pipe.getvalue() == ""
    last = tty.getvalue().split("\r")[-1]
    assert "5/10 poses" in last and "poses/s" in last and "ETA" in last


def test_the_command_writes_the_table_parquet_and_maps(tmp_path, capsys):
    out = tmp_path / "env"
    argv = ["envelope", "--params-file", str(P2), "--x-m", "-3.27", "-3.02", "2", "--y-m", "-2.6", "-2.6", "1",
            "--cells", str(CELLS), "--out", str(out), "--workers", "0", "--parquet", "yes"]
    assert cli_main(argv) == 0, capsys.readouterr().err
    text = capsys.readouterr().out
    assert "codes:" in text and "wrote" in text
    rows = read_rows(out / "envelope.csv")
    assert [r["pose_id"] for r in rows] == [0, 1]
    header = next(csv.reader(io.StringIO((out / "envelope.csv").read_text())))
    assert header[:6] == ["pose_id", "x_m", "y_m", "yaw_deg", "start_index", "code"]
    import pyarrow.parquet as pq
    table = pq.read_table(out / "envelope.parquet").to_pylist()
    assert _differences(rows, table) == [] and [r["plan_s"] for r in rows] == [r["plan_s"] for r in table]
    pngs = sorted(out.glob("*.png"))
    assert [p.name for p in pngs] == ["envelope_yaw0deg.png"]
    assert pngs[0].read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


@pytest.mark.parametrize("extra, named", [
    (["--x-m", "-3", "-2", "0"], "--x-m"),
    (["--x-m", "-3", "-2", "1"], "--x-m"),
    (["--starts-deg", "1", "2", "3"], "--starts-deg"),
    (["--workers", "2", "--scheduler", "tcp://127.0.0.1:1"], "--workers"),
    (["--cells", "0"], "--cells: 0 is below the minimum 2"),
    (["--x-m", "-3.27", "-3.27", "3"], "--x-m: 3 values asked for between equal ends"),
    (["--x-m", "-3", "-2", "100000", "--y-m", "-3", "-2", "1000"], "more than one sweep holds"),
    (["--yaw-deg", "400", "400", "1"], "--yaw-deg: target.yaw_deg: 400.0 is above the maximum 360"),
    # an audit's: tracebacks, a flag not named, 3 GB before the refusal; and a --scheduler Dask would not take
    (["--x-m", "-3", "-2", "inf"], "--x-m: the count must be an integer, got inf"),
    (["--y-m", "-3", "-2", "nan"], "--y-m: the count must be an integer, got nan"),
    (["--x-m", "-3", "-2", "1e20"], "--x-m: 100000000000000000000 values, more than one sweep holds"),
    (["--x-m", "-3", "-2", "1e5", "--y-m", "-3", "-2", "1e4"], "more than one sweep holds"),
    (["--scheduler", "foo"], "--scheduler: 'foo' is not a Dask scheduler's address"),
    (["--scheduler", "http://127.0.0.1:8786"], "--scheduler: 'http://127.0.0.1:8786' is not a Dask"),
    (["--scheduler", ""], "--scheduler: an empty address"),
    (["--x-m", "1e300", "1e300", "1"], "--x-m: target.center_m: 1e+300 is above the maximum 1000"),
    (["--y-m", "-3", "-2000", "2"], "--y-m: target.center_m: -2000.0 is below the minimum -1000"),
])
def test_bad_input_exits_1_naming_the_flag(extra, named, tmp_path, capsys):
    argv = ["envelope", "--params-file", str(P2), "--x-m", "-3.27", "-3.02", "2", "--y-m", "-2.6", "-2.6", "1",
            "--out", str(tmp_path / "env"), "--workers", "0"]
    flags = {a for a in extra if a.startswith("--")}
    for flag in flags:              # the test's value replaces the default one
        if flag in argv:
            k = argv.index(flag)
            n = 4 if flag in ("--x-m", "--y-m") else 2
            del argv[k:k + n]
    assert cli_main(argv + extra) == 1
    assert named in capsys.readouterr().err
