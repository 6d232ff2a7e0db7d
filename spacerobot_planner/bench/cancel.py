"""
Cancel latency of the planning process, caches kept (issue 17).

One ``worker.ProcessBackend`` (the node's default) on a scenario with a grid large enough
that a plan takes about a second or more.  Each of ``--repeats`` trials plans for a target
moved by a few millimetres (a new C-space and a new field) and cancels it at a random
moment within the plan's measured time; the latency is from ``ProcessBackend.cancel()``
to ``run()`` returning the cancelled result.  The same plan then runs again, uncancelled,
in the same process: what it found cached shows what the cancel kept.

Prints the latency's p50, p90 and max, the stage each cancel hit, the planning process's
replacements (0: no cancel took the crash path), the load average (the figures grow with
it), and one JSON object per line.
``python -m spacerobot_planner.bench cancel [--cells 120] [--repeats 10] [--seed 0]``
"""

from __future__ import annotations

import argparse
import json
import os
import threading
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

_PARAMS = Path(__file__).resolve().parent.parent.parent / "config" / "paper_3dof.yaml"


def _percentile(values, q) -> float:
    return float(np.percentile(np.asarray(values, dtype=float), q)) if values else float("nan")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="bench cancel", description=__doc__.strip().splitlines()[0])
    ap.add_argument("--params-file", default=str(_PARAMS))
    ap.add_argument("--cells", type=int, default=120)
    ap.add_argument("--repeats", type=int, default=10)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)

    from ..config import load_scenario
    from ..worker import PlanDone, PlanJob, ProcessBackend

    sc = load_scenario(args.params_file)
    sc = sc.with_grid(sc.grid.with_cells(args.cells))
    rng = np.random.default_rng(args.seed)
    logs: list = []
    b = ProcessBackend(sc, log=logs.append)
    gen = [0]

    def job(dx_m, dy_m):
        gen[0] += 1
        t = sc.scene.target
        scene = sc.scene.with_target(replace(t, center_m=(t.center_m[0] + dx_m, t.center_m[1] + dy_m)))
        return PlanJob(gen=gen[0], scene=scene, grid=sc.grid, solver="log_harmonic", field_tolerance=1e-6,
                       max_grid_nodes=100_000_000, start_rad=sc.start_rad, joint_goal=None)

    def offset():
        return tuple(rng.uniform(-0.005, 0.005, size=2))

    rows = []
    try:
        t0 = time.perf_counter()
        if b.wait_ready(600) is None:
            print("bench cancel: the planning process did not start")
            return 1
        print(f"planning process {b.pid} ready after {time.perf_counter() - t0:.1f} s; grid {sc.grid.label()} "
              f"({sc.grid.n_nodes:,} nodes)")
        b.run(job(*offset()))                              # the JIT of this grid's route
        full = []
        for _ in range(2):
            t1 = time.perf_counter()
            out = b.run(job(*offset()))
            full.append(time.perf_counter() - t1)
            assert isinstance(out, PlanDone), out
        plan_s = min(full)
        timings = {k: round(v, 3) for k, v in out.result.timings_s.items() if v}
        print(f"an uncancelled plan of a new target: {plan_s:.3f} s {timings}")
        pid0 = b.pid
        latencies = []
        print(f"{'#':>3}{'cancel at s':>13}{'stage':>11}{'latency ms':>12}{'outcome':>11}"
              f"{'then: cached':>22}{'plan s':>9}")
        for k in range(args.repeats):
            j = job(*offset())
            at = rng.uniform(0.02, 0.9) * plan_s
            stage = ["queued"]
            got = {}

            def progress(p, stage=stage):
                stage[0] = p.stage

            def run(j=j, got=got, progress=progress):
                got["out"] = b.run(j, progress=progress)
                got["t"] = time.perf_counter()

            th = threading.Thread(target=run)
            t_start = time.perf_counter()
            th.start()
            time.sleep(max(0.0, t_start + at - time.perf_counter()))
            hit = stage[0]
            t_cancel = time.perf_counter()
            b.cancel(j.gen)
            th.join()
            latency = got["t"] - t_cancel
            out = got["out"]
            code = out.result.code if isinstance(out, PlanDone) else out.code
            t2 = time.perf_counter()
            again = b.run(replace(j, gen=j.gen + 1000000))
            again_s = time.perf_counter() - t2
            cached = ",".join(again.result.cached) if isinstance(again, PlanDone) else "-"
            if code == "cancelled":
                latencies.append(latency)
            shown = f"{1e3 * latency:.1f}" if code == "cancelled" else "-"   # it ended before the cancel
            print(f"{k:>3}{at:>13.3f}{hit:>11}{shown:>12}{code:>11}{cached or 'none':>22}{again_s:>9.3f}")
            rows.append({"stage": "cancel", "grid": sc.grid.label(), "solver": "log_harmonic",
                         "cancel_at_s": round(at, 4), "stage_hit": hit, "seconds": latency, "outcome": code,
                         "next_plan_cached": list(again.result.cached) if isinstance(again, PlanDone) else None,
                         "next_plan_s": again_s, "same_process": b.pid == pid0})
        respawns = sum("does not poll" in m for m in logs)
        load = os.getloadavg()[0]
        print(f"load average {load:.1f} on {os.cpu_count()} CPUs; cancel latency over {len(latencies)} cancels "
              f"(caches kept): p50 {1e3 * _percentile(latencies, 50):.1f} ms, "
              f"p90 {1e3 * _percentile(latencies, 90):.1f} ms, max {1e3 * max(latencies, default=np.nan):.1f} ms; "
              f"planning process replaced {respawns} times (pid {pid0} -> {b.pid})")
        rows.append({"stage": "cancel_summary", "grid": sc.grid.label(), "solver": "log_harmonic",
                     "cancels": len(latencies), "p50_s": _percentile(latencies, 50),
                     "p90_s": _percentile(latencies, 90), "max_s": max(latencies, default=None),
                     "plan_s": plan_s, "respawns": respawns, "same_process": b.pid == pid0, "load_avg": load})
        for r in rows:
            print(json.dumps(r))
    finally:
        b.close()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
