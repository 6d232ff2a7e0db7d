"""
C-space build time on the paper's scenes: 180², 360², 720² (2-DOF) and 36³, 72³, 120³ (3-DOF).

``--repeats`` builds after a warm-up on grids up to 500 000 nodes, ``--large-repeats`` above; the
table gives the best, median, p90 and max, each JSON row ``seconds`` (the median), ``min_s``,
``p90_s``, ``max_s`` and ``runs``.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numba

from ..config import load_scenario
from ..cspace import build_cspace
from .timing import tail_stats

CONFIG = Path(__file__).resolve().parent.parent.parent / "config"
CASES = (("paper_2dof", 180), ("paper_2dof", 360), ("paper_2dof", 720),
         ("paper_3dof", 36), ("paper_3dof", 72), ("paper_3dof", 120))


def time_build(scenario, cells, repeats: int) -> tuple:
    """Return the grid, the C-space and the tails of ``repeats`` builds' times after a warm-up (``tail_stats``, s)."""
    grid = scenario.grid_with_cells(cells)
    build_cspace(scenario.robot, scenario.scene, grid)   # JIT + caches
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        cs = build_cspace(scenario.robot, scenario.scene, grid)
        times.append(time.perf_counter() - t0)
    return grid, cs, tail_stats(times, median_key="seconds")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="bench cspace", description=__doc__)
    ap.add_argument("--repeats", type=int, default=5, help="builds per grid up to 500 000 nodes")
    ap.add_argument("--large-repeats", type=int, default=3, help="builds per larger grid")
    args = ap.parse_args(argv)
    print(f"C-space build (numba, {numba.get_num_threads()} threads), ms over {args.repeats} builds "
          f"({args.large_repeats} above 500 000 nodes)")
    print(f"{'scene':<12}{'grid':>14}{'nodes':>11}{'free %':>8}{'best':>10}{'median':>10}{'p90':>10}{'max':>10}")
    rows = []
    for name, cells in CASES:
        sc = load_scenario(CONFIG / f"{name}.yaml")
        repeats = max(1, args.repeats if grid_small(sc, cells) else args.large_repeats)
        grid, cs, times = time_build(sc, cells, repeats)
        print(f"{name:<12}{grid.label():>14}{grid.n_nodes:>11}{100 * cs.free_fraction:>8.1f}"
              + "".join(f"{1e3 * times[k]:>10.2f}" for k in ("min_s", "seconds", "p90_s", "max_s")))
        rows.append({"stage": "cspace", "grid": grid.label(), "scene": name, "solver": None, **times,
                     "nodes": grid.n_nodes, "baseline_seconds": None, "ratio": None})
    for r in rows:
        print(json.dumps(r))
    return 0


def grid_small(scenario, cells) -> bool:
    return scenario.grid_with_cells(cells).n_nodes <= 500_000


if __name__ == "__main__":
    raise SystemExit(main())
