"""
Envelope sweep throughput: poses per second serial and on a local Dask cluster, overhead per pose.

    python -m spacerobot_planner.bench envelope [--scene 3dof] [--cells 36] [--nx 5] [--ny 5]
        [--starts 2] [--workers 2] [--chunk-size N] [--repeats 3]

The poses: a grid of ``--nx`` × ``--ny`` target centres around the paper's target
(x −3.5…−2.5 m, y −3.1…−2.1 m, yaw 0) from ``--starts`` start postures (the scenario's, then
others a few degrees away).  After a warm-up (the numba kernels loaded: the scenario's own
capture and every tenth pose planned), ``--repeats`` times in this order on the same poses
(medians shown, with the spread and the speedup of each repeat):

1. **single plans**: each pose planned alone in this process, the way ``spacerobot-plan``
   plans one request (a fresh ``Planner``, ``offline.plan_offline``): the baseline;
2. **serial sweep**: ``run_envelope(workers=0)``, the chunks one after the other in this
   process, rows to a folder;
3. **local cluster**: ``run_envelope`` on the sweep's ``distributed.LocalCluster``
   (``envelope.engine.local_cluster``) of ``--workers`` processes (one thread each), its
   workers warmed up first; poses/s over the time from the first task to the last row.

Start-up is reported apart and then added: "with start-up" is what a user waits for, a fresh
process that imports the package and runs the warm-up (timed from outside) plus the serial
sweep's plans, against the cluster's start, its workers' warm-up (the same) and its plans.

Overhead per pose: (worker-seconds per pose of the sweep) / (seconds per single plan) − 1,
the cluster's worker-seconds being its wall time × workers; and the same in CPU time (every
worker process's, plus this process's: the client and the local scheduler), which other work
on the machine does not inflate as it does wall times.  On a shared machine the wall-time
speedup measures the share of the cores the cluster got; "with the cores to itself" is the
speedup the CPU times allow (workers × serial CPU / cluster CPU), and "busy" the cluster's CPU
over workers × its wall time.  The tables must agree (every column but the wall times).
Prints a table, then one JSON object per line.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from ..collision import CollisionChecker
from ..config import load_scenario
from ..envelope import TIMING_COLUMNS, PoseGrid, axis_values, run_envelope, sweep_spec
from ..envelope.engine import local_cluster
from ..envelope.sweep import plan_chunk
from ..offline import plan_offline
from ..planner import Planner
from ..scene import Target

CONFIG = Path(__file__).resolve().parent.parent.parent / "config"


def _starts(sc, n: int) -> list:
    """Return ``n`` free start postures: the scenario's, then a few degrees away."""
    chk = CollisionChecker(sc.robot, sc.scene)
    out = [sc.start_rad]
    for off in ([6.0, -4.0, 3.0], [-6.0, 4.0, -3.0], [10.0, 3.0, -5.0], [3.0, -8.0, 5.0], [-9.0, -3.0, 4.0]):
        q = sc.start_rad + np.radians(off[:sc.robot.dof])
        if len(out) < n and chk.is_free(q):
            out.append(q)
    return out[:n]


def _single_plans(sc, grid) -> float:
    """Plan every pose alone (fresh planner, the CLI's pipeline); return the seconds."""
    t0 = time.perf_counter()
    for i in range(grid.n_poses):
        p = grid.pose(i)
        tg = sc.scene.target
        one = sc.with_scene(sc.scene.with_target(Target((p.x_m, p.y_m), math.radians(p.yaw_deg), tg.body_side_m,
                                                        tg.handle_side_m)))
        plan_offline(Planner(one, reaction=True), np.asarray(grid.starts_rad[p.start_index]))
    return time.perf_counter() - t0


def _warm_up(scenario, grid, numba_threads=None):
    """
    Load the numba kernels in this process (a worker: one thread).

    The scenario's own capture, then every tenth pose of the grid (their failures too).
    """
    plan_offline(Planner(scenario, reaction=True), scenario.start_rad)
    return len(plan_chunk(scenario, grid, range(0, grid.n_poses, 10), numba_threads))


def _cpu_s() -> float:
    """Return this process's CPU time (user + system, every thread), s."""
    t = os.times()
    return t.user + t.system


def _differences(a, b) -> int:
    def same(x, y):
        return x == y or (isinstance(x, float) and isinstance(y, float) and math.isnan(x) and math.isnan(y))
    return sum(1 for ra, rb in zip(a, b) for k in ra if k not in TIMING_COLUMNS and not same(ra[k], rb[k]))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="bench envelope", description=__doc__.strip().split("\n\n")[0])
    ap.add_argument("--scene", choices=("2dof", "3dof"), default="3dof")
    ap.add_argument("--cells", type=int, default=36)
    ap.add_argument("--nx", type=int, default=5)
    ap.add_argument("--ny", type=int, default=5)
    ap.add_argument("--starts", type=int, default=2)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--chunk-size", type=int)
    ap.add_argument("--repeats", type=int, default=3, help="runs of each kind, interleaved; medians shown")
    ap.add_argument("--warm-up-only", action="store_true", help=argparse.SUPPRESS)   # the cold start's process
    args = ap.parse_args(argv)

    params = CONFIG / f"paper_{args.scene}.yaml"
    sc = load_scenario(params)
    sc = sc.with_grid(sc.grid_with_cells([args.cells] * sc.robot.dof))
    grid = PoseGrid(axis_values(-3.5, -2.5, args.nx, "x"), axis_values(-3.1, -2.1, args.ny, "y"), (0.0,),
                    tuple(tuple(s) for s in _starts(sc, args.starts)))
    spec = sweep_spec(params, sc.grid.cells, grid)
    n = grid.n_poses
    t0 = time.perf_counter()
    _warm_up(sc, grid)
    warm0_s = time.perf_counter() - t0
    if args.warm_up_only:
        return 0
    from distributed import Client
    # a serial sweep's start-up: a fresh process imports the package and loads the kernels
    # (the same warm-up), as a worker of the cluster does
    cold = [a for a in (argv if argv is not None else sys.argv[2:]) if a != "--warm-up-only"]
    t0 = time.perf_counter()
    subprocess.run([sys.executable, "-m", "spacerobot_planner.bench", "envelope", "--warm-up-only", *cold], check=True,
                   stdout=subprocess.DEVNULL)
    cold_s = time.perf_counter() - t0
    print(f"bench envelope: paper_{args.scene}, grid {sc.grid.label()}, {n} poses ({args.nx} x × {args.ny} y × "
          f"{len(grid.starts_rad)} starts), JIT warm-up {warm0_s:.1f} s", flush=True)
    singles, serials, dasks = [], [], []
    load0 = os.getloadavg()
    with tempfile.TemporaryDirectory() as tmp:
        t1 = time.perf_counter()
        with local_cluster(args.workers) as cluster, Client(cluster) as client:
            started_s = time.perf_counter() - t1
            t2 = time.perf_counter()
            client.run(_warm_up, sc, grid, 1)
            warm_s = time.perf_counter() - t2
            for k in range(args.repeats):       # interleaved, so a burst of other work hits every kind alike
                c0 = _cpu_s()
                seconds = _single_plans(sc, grid)
                singles.append((seconds, _cpu_s() - c0))
                c0 = _cpu_s()
                rep = run_envelope(sc, grid, Path(tmp) / f"serial{k}", spec, workers=0, chunk_size=args.chunk_size,
                                   quiet=True)
                serials.append((rep.plan_seconds, _cpu_s() - c0, rep))
                w0, c0 = client.run(_cpu_s), _cpu_s()
                rep = run_envelope(sc, grid, Path(tmp) / f"dask{k}", spec, client=client,
                                   chunk_size=args.chunk_size, quiet=True)
                w1, c1 = client.run(_cpu_s), _cpu_s()
                # the workers' CPU and this process's (client and scheduler)
                dasks.append((rep.plan_seconds, sum(w1[w] - w0[w] for w in w1) + c1 - c0, rep, c1 - c0))
    load1 = os.getloadavg()
    med = statistics.median
    single_s, single_cpu = med(r[0] for r in singles), med(r[1] for r in singles)
    serial_s, serial_cpu = med(r[0] for r in serials), med(r[1] for r in serials)
    dask_s, dask_cpu = med(r[0] for r in dasks), med(r[1] for r in dasks)
    serial, dask = serials[0][2], dasks[0][2]
    speedups = [s[0] / d[0] for s, d in zip(serials, dasks)]
    # what the cluster would reach with its cores to itself: the serial sweep's CPU over the cluster's
    # CPU per worker (its wall time if the cores were busy only with its work, perfectly balanced)
    cpu_bound = [args.workers * s[1] / d[1] for s, d in zip(serials, dasks)]
    busy = [d[1] / (args.workers * d[0]) for d in dasks]
    single_per = single_s / n
    # what a user waits for: a serial sweep loads the kernels in its process, a cluster starts and
    # its workers load them; both then plan (the warm-ups plan the same poses)
    serial_e2e_s, dask_e2e_s = cold_s + serial_s, started_s + warm_s + dask_s
    rows = [
        {"stage": "single_plans", "poses": n, "seconds": single_s, "poses_per_s": n / single_s,
         "seconds_per_pose": single_per, "cpu_seconds": single_cpu, "all_seconds": [r[0] for r in singles]},
        {"stage": "serial_sweep", "poses": n, "seconds": serial_s, "poses_per_s": n / serial_s,
         "chunks": serial.chunks, "overhead": serial_s / n / single_per - 1.0,
         "cpu_seconds": serial_cpu, "cpu_overhead": serial_cpu / single_cpu - 1.0,
         "all_seconds": [r[0] for r in serials], "all_cpu_seconds": [r[1] for r in serials],
         "start_up_s": cold_s, "with_start_up_s": serial_e2e_s},
        {"stage": "local_cluster", "poses": n, "workers": args.workers, "seconds": dask_s,
         "poses_per_s": n / dask_s, "chunks": dask.chunks, "speedup_vs_serial": med(speedups),
         "speedups_per_repeat": speedups, "cpu_bound_speedups": cpu_bound, "busy_fraction": busy,
         "overhead": dask_s * args.workers / n / single_per - 1.0,
         "cpu_seconds": dask_cpu, "cpu_overhead": dask_cpu / single_cpu - 1.0,
         "cpu_vs_serial": dask_cpu / serial_cpu - 1.0,
         "client_and_scheduler_cpu_seconds": med(r[3] for r in dasks), "all_seconds": [r[0] for r in dasks],
         "all_cpu_seconds": [r[1] for r in dasks], "cluster_start_s": started_s, "worker_warm_up_s": warm_s,
         "with_start_up_s": dask_e2e_s, "speedup_with_start_up": serial_e2e_s / dask_e2e_s,
         "rows_differing_from_serial": max(_differences(serial.rows, d[2].rows) for d in dasks),
         "load_average_start_end": [load0[0], load1[0]]},
    ]
    codes = {}
    for r in serial.rows:
        codes[r["code"]] = codes.get(r["code"], 0) + 1
    print(f"codes: {', '.join(f'{c} {k}' for c, k in sorted(codes.items()))}")
    head = (f"{'run':<16}{'seconds':>9}{'(min-max)':>14}{'poses/s':>9}{'chunks':>8}{'overhead':>10}{'CPU s':>8}"
            f"{'CPU overhead':>14}{'speedup':>9}")
    print(head + "\n" + "-" * len(head))

    def spread(xs):
        return f"({min(xs):.2f}-{max(xs):.2f})"
    print(f"{'single plans':<16}{single_s:>9.2f}{spread([r[0] for r in singles]):>14}{n / single_s:>9.2f}{'':>8}"
          f"{'':>10}{single_cpu:>8.2f}{'':>14}{'':>9}")
    for name, r, runs in (("serial sweep", rows[1], serials), ("local cluster", rows[2], dasks)):
        print(f"{name:<16}{r['seconds']:>9.2f}{spread([x[0] for x in runs]):>14}{r['poses_per_s']:>9.2f}"
              f"{r['chunks']:>8}{100 * r['overhead']:>9.1f}%{r['cpu_seconds']:>8.2f}{100 * r['cpu_overhead']:>13.1f}%"
              f"{r['seconds'] and serial_s / r['seconds']:>9.2f}")
    print(f"medians of {args.repeats} interleaved repeats; cluster speedup per repeat "
          f"{', '.join(f'{x:.2f}' for x in speedups)} (median {med(speedups):.2f}); with the cores to itself "
          f"(serial CPU / cluster CPU per worker) {', '.join(f'{x:.2f}' for x in cpu_bound)}; the cluster's "
          f"workers busy {', '.join(f'{100 * x:.0f}' for x in busy)} % of their wall time")
    print(f"local cluster: {args.workers} workers, started in {started_s:.1f} s, warmed up in {warm_s:.1f} s; "
          f"with start-up {serial_e2e_s:.1f} s serial (a fresh process warmed up in {cold_s:.1f} s) vs "
          f"{dask_e2e_s:.1f} s, speedup {serial_e2e_s / dask_e2e_s:.2f}; rows differing from the serial sweep: "
          f"{rows[2]['rows_differing_from_serial']}; load average {load0[0]:.1f} at the start, "
          f"{load1[0]:.1f} at the end")
    for row in rows:
        print(json.dumps(row))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
