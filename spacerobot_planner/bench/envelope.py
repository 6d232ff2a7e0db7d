"""
Envelope sweep throughput: poses per second serial and on a local Dask cluster, overhead per pose.

    python -m spacerobot_planner.bench envelope [--scene 3dof] [--cells 36] [--nx 5] [--ny 5]
        [--starts 2] [--workers 2] [--chunk-size N] [--repeats 3]

The poses: a grid of ``--nx`` × ``--ny`` target centres around the paper's target
(x −3.5…−2.5 m, y −3.1…−2.1 m, yaw 0) from ``--starts`` start postures (the scenario's, then
others a few degrees away).  After a warm-up (the numba kernels loaded: the scenario's own
capture and every tenth pose planned), ``--repeats`` times in this order on the same poses
(the best of each kind is shown, with the speedup of each repeat):

1. **single plans**: each pose planned alone in this process, the way ``spacerobot-plan``
   plans one request (a fresh ``Planner``, ``offline.plan_offline``): the baseline;
2. **serial sweep**: ``run_envelope(workers=0)``, the chunks one after the other in this
   process, rows to a folder;
3. **local cluster**: ``run_envelope`` on the sweep's ``distributed.LocalCluster``
   (``envelope.engine.local_cluster``) of ``--workers`` processes (one thread each), its
   workers warmed up first (cluster start and warm-up are reported apart); poses/s over the
   time from the first task to the last row.

Overhead per pose: (worker-seconds per pose of the sweep) / (seconds per single plan) − 1,
the cluster's worker-seconds being its wall time × workers; and the same in CPU time (every
worker process's, plus this process's: the client and the local scheduler), which other work
on the machine does not inflate as it does wall times.  The tables must agree (every column
but the wall times).  Prints a table, then one JSON object per line.
"""

from __future__ import annotations

import argparse
import json
import math
import os
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
    ap.add_argument("--repeats", type=int, default=3, help="runs of each kind, interleaved; the best is shown")
    args = ap.parse_args(argv)
    from distributed import Client

    params = CONFIG / f"paper_{args.scene}.yaml"
    sc = load_scenario(params)
    sc = sc.with_grid(sc.grid_with_cells([args.cells] * sc.robot.dof))
    grid = PoseGrid(axis_values(-3.5, -2.5, args.nx, "x"), axis_values(-3.1, -2.1, args.ny, "y"), (0.0,),
                    tuple(tuple(s) for s in _starts(sc, args.starts)))
    spec = sweep_spec(params, sc.grid.cells, grid)
    n = grid.n_poses
    t0 = time.perf_counter()
    _warm_up(sc, grid)
    print(f"bench envelope: paper_{args.scene}, grid {sc.grid.label()}, {n} poses ({args.nx} x × {args.ny} y × "
          f"{len(grid.starts_rad)} starts), JIT warm-up {time.perf_counter() - t0:.1f} s", flush=True)
    singles, serials, dasks = [], [], []
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
    single_s, single_cpu = min(singles)
    serial_s, serial_cpu, serial = min(serials, key=lambda r: r[0])
    dask_s, dask_cpu, dask, client_cpu = min(dasks, key=lambda r: r[0])
    serial_rate, dask_rate = n / serial_s, n / dask_s
    single_per = single_s / n
    rows = [
        {"stage": "single_plans", "poses": n, "seconds": single_s, "poses_per_s": n / single_s,
         "seconds_per_pose": single_per, "cpu_seconds": single_cpu, "all_seconds": [r[0] for r in singles]},
        {"stage": "serial_sweep", "poses": n, "seconds": serial_s, "poses_per_s": serial_rate,
         "chunks": serial.chunks, "overhead": serial_s / n / single_per - 1.0,
         "cpu_seconds": serial_cpu, "cpu_overhead": serial_cpu / single_cpu - 1.0,
         "all_seconds": [r[0] for r in serials]},
        {"stage": "local_cluster", "poses": n, "workers": args.workers, "seconds": dask_s,
         "poses_per_s": dask_rate, "chunks": dask.chunks, "speedup_vs_serial": dask_rate / serial_rate,
         "speedups_per_repeat": [s[0] / d[0] for s, d in zip(serials, dasks)],
         "overhead": dask_s * args.workers / n / single_per - 1.0,
         "cpu_seconds": dask_cpu, "cpu_overhead": dask_cpu / single_cpu - 1.0,
         "client_and_scheduler_cpu_seconds": client_cpu, "all_seconds": [r[0] for r in dasks],
         "cluster_start_s": started_s, "worker_warm_up_s": warm_s,
         "rows_differing_from_serial": max(_differences(serial.rows, d[2].rows) for d in dasks)},
    ]
    load = os.getloadavg()
    codes = {}
    for r in serial.rows:
        codes[r["code"]] = codes.get(r["code"], 0) + 1
    print(f"codes: {', '.join(f'{c} {k}' for c, k in sorted(codes.items()))}")
    head = (f"{'run':<16}{'seconds':>9}{'poses/s':>9}{'chunks':>8}{'overhead':>10}{'CPU s':>8}"
            f"{'CPU overhead':>14}{'speedup':>9}")
    print(head + "\n" + "-" * len(head))
    print(f"{'single plans':<16}{single_s:>9.2f}{n / single_s:>9.2f}{'':>8}{'':>10}{single_cpu:>8.2f}{'':>14}{'':>9}")
    for name, r, rate in (("serial sweep", rows[1], serial_rate), ("local cluster", rows[2], dask_rate)):
        print(f"{name:<16}{r['seconds']:>9.2f}{rate:>9.2f}{r['chunks']:>8}{100 * r['overhead']:>9.1f}%"
              f"{r['cpu_seconds']:>8.2f}{100 * r['cpu_overhead']:>13.1f}%{rate / serial_rate:>9.2f}")
    print(f"best of {args.repeats} of each; speedup per repeat "
          f"{', '.join(f'{x:.2f}' for x in rows[2]['speedups_per_repeat'])}")
    print(f"local cluster: {args.workers} workers, started in {started_s:.1f} s, warmed up in {warm_s:.1f} s; "
          f"rows differing from the serial sweep: {rows[2]['rows_differing_from_serial']}; load average "
          f"{load[0]:.1f} {load[1]:.1f} {load[2]:.1f} at the end")
    for row in rows:
        print(json.dumps(row))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
