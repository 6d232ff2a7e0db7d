"""C-space build time on the paper's scenes: 180², 360², 720² (2-DOF) and 36³, 72³, 120³ (3-DOF)."""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numba

from ..config import load_scenario
from ..cspace import build_cspace

CONFIG = Path(__file__).resolve().parent.parent.parent / "config"
CASES = (("paper_2dof", 180), ("paper_2dof", 360), ("paper_2dof", 720),
         ("paper_3dof", 36), ("paper_3dof", 72), ("paper_3dof", 120))


def time_build(scenario, cells, repeats: int) -> tuple:
    """Best and median build time (s) over ``repeats`` builds after a warm-up."""
    grid = scenario.grid_with_cells(cells)
    build_cspace(scenario.robot, scenario.scene, grid)   # JIT + caches
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        cs = build_cspace(scenario.robot, scenario.scene, grid)
        times.append(time.perf_counter() - t0)
    times.sort()
    return grid, cs, times[0], times[len(times) // 2]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="bench cspace", description=__doc__)
    ap.add_argument("--repeats", type=int, default=5)
    args = ap.parse_args(argv)
    print(f"C-space build (numba, {numba.get_num_threads()} threads), best / median of {args.repeats}")
    print(f"{'scene':<12}{'grid':>14}{'nodes':>11}{'free %':>8}{'best ms':>10}{'median ms':>11}")
    rows = []
    for name, cells in CASES:
        sc = load_scenario(CONFIG / f"{name}.yaml")
        grid, cs, best, med = time_build(sc, cells, args.repeats if grid_small(sc, cells) else 2)
        print(f"{name:<12}{grid.label():>14}{grid.n_nodes:>11}{100 * cs.free_fraction:>8.1f}"
              f"{1e3 * best:>10.2f}{1e3 * med:>11.2f}")
        rows.append({"stage": "cspace", "grid": grid.label(), "scene": name, "solver": None,
                     "seconds": best, "median_seconds": med, "nodes": grid.n_nodes,
                     "baseline_seconds": None, "ratio": None})
    for r in rows:
        print(json.dumps(r))
    return 0


def grid_small(scenario, cells) -> bool:
    return scenario.grid_with_cells(cells).n_nodes <= 500_000


if __name__ == "__main__":
    raise SystemExit(main())
