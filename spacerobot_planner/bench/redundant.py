"""
Redundant chains: the capture posture's cost, and the 4-joint grid resolution.

    python -m spacerobot_planner.bench redundant [--targets 12] [--cells 8 10 12 16 20 24]
        [--seed 0] [--repeats 3]

1. The grasp IK of ``config/servicer_4joint.yaml`` (one swept joint) and of a 5-joint
   variant (links 1.4 / 1.2 / 1.2 / 1.0 / 0.8 m: two swept joints) on the paper's target:
   median and largest time over ``--repeats`` after a warm-up, the manipulability chosen, and a
   brute-force sweep 4× denser per swept joint (no refinement) for comparison.
2. Plans of ``config/servicer_4joint.yaml`` at each ``--cells`` resolution, on the paper's
   target and ``--targets`` seeded random targets (centre 3.0–4.6 m from the spacecraft,
   any bearing and yaw; kept when the start is free and a collision-free grasp exists):
   plans that succeed, median and largest plan time, median path length, smallest
   clearance.  This is how the scenario's resolution was chosen (docs/redundant.md).

Prints a table, then one JSON object per line.
"""

from __future__ import annotations

import argparse
import json
import math
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from ..collision import CollisionChecker
from ..config import load_scenario
from ..ik import grasp_ik
from ..planner import Planner
from ..redundant import SWEEP_VALUES, redundant_grasp
from ..robot import PlanarArm
from ..scene import Target
from .timing import call_times_s, tail_stats

CONFIG = Path(__file__).resolve().parent.parent.parent / "config"


def five_joint(robot4: PlanarArm) -> PlanarArm:
    """Return the 5-joint variant of the 4-joint servicer: links 1.4 / 1.2 / 1.2 / 1.0 / 0.8 m, arm joints ±180°."""
    return PlanarArm(("attitude", "shoulder", "elbow", "wrist", "hand"), (1.4, 1.2, 1.2, 1.0, 0.8),
                     (-math.pi,) * 5, (math.pi,) * 5, (True, False, False, False, False), robot4.body_polygon_m,
                     checked_links=(1, 2, 3, 4))


def ik_rows(sc, repeats: int) -> list:
    """Part 1: the grasp IK's cost and quality for 4 and 5 joints."""
    rows = []
    t = sc.scene.target
    for label, robot in (("4 joints", sc.robot), ("5 joints", five_joint(sc.robot))):
        grasp_ik(robot, sc.scene)                                          # warm-up (numba)
        sols = grasp_ik(robot, sc.scene)
        times = call_times_s(lambda robot=robot: grasp_ik(robot, sc.scene), max(1, repeats))
        r = robot.dof - 3
        dense = 4 * SWEEP_VALUES[r]
        t0 = time.perf_counter()
        brute = redundant_grasp(robot, sc.scene, t.grasp_point_m, t.approach_angle_rad, sweep_values=dense)
        brute_s = time.perf_counter() - t0
        best = sols[0] if sols else None
        rows.append({"stage": "redundant_ik", "grid": label, **tail_stats(times, median_key="seconds"),
                     "manipulability_m2": None if best is None else best.manipulability,
                     "q_deg": None if best is None else np.degrees(best.q_full).round(3).tolist(),
                     "method": None if best is None else best.method,
                     "dense_sweep_values": dense, "dense_seconds": brute_s,
                     "dense_manipulability_m2": brute[0].manipulability if brute else None})
    return rows


def random_targets(sc, count: int, seed: int) -> list:
    """Seeded targets with a free start and a collision-free grasp (the paper's target first)."""
    rng = np.random.default_rng(seed)
    out = [sc.scene.target]
    tries = 0
    while len(out) < count + 1 and tries < 100 * (count + 1):
        tries += 1
        r, bearing, yaw = rng.uniform(3.0, 4.6), rng.uniform(-math.pi, math.pi), rng.uniform(-math.pi, math.pi)
        target = Target(center_m=(r * math.cos(bearing), r * math.sin(bearing)), yaw_rad=yaw)
        scene = sc.scene.with_target(target)
        if not CollisionChecker(sc.robot, scene).is_free(sc.start_rad):
            continue
        if grasp_ik(sc.robot, scene):
            out.append(target)
    return out


def resolution_rows(sc, cells_list, targets) -> list:
    """Part 2: plans at each resolution over the targets."""
    rows = []
    warm = Planner(replace(sc, grid=sc.grid_with_cells(6)))          # numba warm-up
    warm.plan(sc.start_rad)
    for cells in cells_list:
        times, lengths, clearances, codes = [], [], [], []
        for target in targets:
            s = replace(sc, grid=sc.grid_with_cells(cells)).with_scene(sc.scene.with_target(target))
            t0 = time.perf_counter()
            res = Planner(s).plan(s.start_rad)
            times.append(time.perf_counter() - t0)
            codes.append(str(res.code))
            if res.ok:
                lengths.append(res.path_length_rad)
                clearances.append(res.min_clearance_m)
        rows.append({"stage": "redundant_resolution", "grid": "x".join(map(str, sc.grid_with_cells(cells).shape)),
                     "cells": cells, "targets": len(targets), "ok": codes.count("ok"),
                     "codes": {c: codes.count(c) for c in sorted(set(codes))},
                     "seconds": float(np.median(times)), "max_seconds": float(np.max(times)),
                     "median_path_length_rad": float(np.median(lengths)) if lengths else None,
                     "min_clearance_m": float(np.min(clearances)) if clearances else None})
    return rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="bench redundant")
    ap.add_argument("--targets", type=int, default=12, help="random targets besides the paper's")
    ap.add_argument("--cells", type=int, nargs="+", default=[8, 10, 12, 16, 20, 24])
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args(argv)
    sc = load_scenario(CONFIG / "servicer_4joint.yaml")
    rows = ik_rows(sc, args.repeats)
    print(f"{'chain':10} {'IK [ms]':>8} {'max':>8} {'w [m²]':>8} {'dense w':>8} {'dense [ms]':>10}  method")
    for r in rows:
        print(f"{r['grid']:10} {1e3 * r['seconds']:8.1f} {1e3 * r['max_s']:8.1f} {r['manipulability_m2']:8.4f} "
              f"{r['dense_manipulability_m2']:8.4f} {1e3 * r['dense_seconds']:10.1f}  {r['method']}")
    targets = random_targets(sc, args.targets, args.seed)
    res_rows = resolution_rows(sc, args.cells, targets)
    print(f"{'grid':14} {'ok':>7} {'median s':>9} {'max s':>7} {'length':>7} {'clearance':>9}  codes")
    for r in res_rows:
        length = "n/a" if r["median_path_length_rad"] is None else f"{r['median_path_length_rad']:.3f}"
        clr = "n/a" if r["min_clearance_m"] is None else f"{r['min_clearance_m']:.4f}"
        print(f"{r['grid']:14} {r['ok']:3d}/{r['targets']:<3d} {r['seconds']:9.2f} {r['max_seconds']:7.2f} "
              f"{length:>7} {clr:>9}  {r['codes']}")
    for r in rows + res_rows:
        print(json.dumps(r))
    return 0
