"""
Field benchmark: ``python -m spacerobot_planner.bench field [options]``.

For each grid (2-D 181^2, 361^2, 721^2 of the paper's 2-DOF scene; 3-D
36x37x37, 72x73x73, 120x121x121 of the 3-DOF scene, axis 0 periodic) it builds
the C-space, then times every field solver after a JIT warm-up, with the
paper's Gauss-Seidel (Phi0 = 1, stop at change < 1e-6) measured in the same
run as the baseline.  Each solver runs ``--repeats`` times on grids up to 100 000
nodes, ``--large-repeats`` times above: the table gives the median, p90 and max of
its times, the ratio the baseline's median over the solver's.  On grids above
``--gs-cap-nodes`` nodes the baseline is capped at ``--gs-cap-sweeps`` sweeps
(said in the output: its time is then a lower bound and so is every ratio).
``descent_ok_fraction`` is the share of goal-connected free nodes from which
steepest descent reaches the goal.

Prints a table and one JSON object per line (times in seconds; ``seconds`` the median)::

    {"stage": "field", "grid": "181x181", "solver": ..., "seconds": ..., "p90_s": ...,
     "min_s": ..., "max_s": ..., "runs": ..., "baseline_seconds": ..., "ratio": ...,
     "sweeps": ..., "descent_ok_fraction": ...}
"""
from __future__ import annotations

import argparse
import json
import time

import numpy as np

from .. import field as F
from ..field.harmonic import BAND_FLOOR
from ..descent import descend, reaches_goal_mask
from .timing import tail_stats

GRIDS_2D = (180, 360, 720)           # cells; bounded axes give cells + 1 nodes
GRIDS_3D = (36, 72, 120)


def _nearest_free(occupied, node):
    """Return the free node nearest (in index steps) to ``node``: the node itself when free."""
    if not occupied[node]:
        return tuple(int(k) for k in node)
    free = np.argwhere(~occupied)
    return tuple(int(k) for k in free[np.argmin(np.abs(free - np.asarray(node)).sum(axis=1))])


def _scene_problem(scenario_path, cells):
    """
    (occupied, periodic, goal_node, start_node, source) for a paper scene.

    Where the scenario's goal or start falls on an obstacle node at this resolution
    (the goal at 120³, the 3-DOF start at 36³), the nearest free node stands in, as
    the planner's own choice of nearby nodes would.
    """
    from ..config import load_scenario
    from ..cspace import build_cspace
    sc = load_scenario(scenario_path)
    cs = build_cspace(sc.robot, sc.scene, sc.grid_with_cells(cells))
    goal = _nearest_free(cs.occupied, cs.grid.node_of(sc.goal_rad))
    start = _nearest_free(cs.occupied, cs.grid.node_of(sc.start_rad))
    return cs.occupied, tuple(cs.grid.periodic), goal, start, scenario_path


def _runs(args, n_nodes):
    """(label, solver, kwargs) per timed run: the paper's baseline first."""
    base = {"max_sweeps": args.gs_cap_sweeps} if n_nodes > args.gs_cap_nodes else {}
    return [("gauss_seidel", "gauss_seidel", base), ("log_harmonic", "log_harmonic", {}),
            (f"budget {args.small_budget_s:g}s", "log_harmonic", {"budget_s": args.small_budget_s})]


def _time_solver(occ, per, goal, solver, kwargs, repeats):
    """Return the first of ``repeats`` fields of a solver and the tails of their times (``tail_stats``)."""
    fields = [F.solve_field(occ, per, [goal], solver=solver, **kwargs) for _ in range(repeats)]
    return fields[0], tail_stats([f.seconds for f in fields], median_key="seconds")


def _warm_up():
    F.warm_up()
    occ = np.zeros((9, 10), dtype=bool)
    occ[3:5, 3:6] = True
    f = F.solve_field(occ, (False, False), [(8, 9)])
    reaches_goal_mask(f)
    descend(f, (0, 0))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m spacerobot_planner.bench field", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--grids", default="all", help="'all', '2d', '3d', 'small' (181^2 and 36x37x37) "
                    "or a comma list of cells, e.g. '180,36'")
    ap.add_argument("--repeats", type=int, default=5, help="timed runs per solver on grids up to 100k nodes")
    ap.add_argument("--large-repeats", type=int, default=3, help="timed runs per solver on larger grids")
    ap.add_argument("--gs-cap-nodes", type=int, default=400_000,
                    help="cap the paper baseline on grids with more nodes than this")
    ap.add_argument("--gs-cap-sweeps", type=int, default=3000, help="baseline sweep cap on those grids")
    ap.add_argument("--small-budget-s", type=float, default=1e-3,
                    help="budget of the extra log_harmonic run that stops early (a valid, unconverged field)")
    args = ap.parse_args(argv)

    choice = args.grids
    if choice == "all":
        cases = [("2d", c) for c in GRIDS_2D] + [("3d", c) for c in GRIDS_3D]
    elif choice == "2d":
        cases = [("2d", c) for c in GRIDS_2D]
    elif choice == "3d":
        cases = [("3d", c) for c in GRIDS_3D]
    elif choice == "small":
        cases = [("2d", 180), ("3d", 36)]
    else:
        cases = [("2d" if int(c) in GRIDS_2D else "3d", int(c)) for c in choice.split(",")]

    t0 = time.perf_counter()
    _warm_up()
    print(f"# JIT warm-up {time.perf_counter() - t0:.1f} s")
    header = (f"{'grid':>12} {'solver':>14} {'ms':>10} {'p90 ms':>10} {'max ms':>10} {'base ms':>10} {'ratio':>8} "
              f"{'sweeps':>7} {'conv':>5} {'residual':>9} {'descent ok':>10}  note")
    print(header)
    records = []
    for kind, cells in cases:
        path = "config/paper_2dof.yaml" if kind == "2d" else "config/paper_3dof.yaml"
        occ, per, goal, start, source = _scene_problem(path, cells)
        grid = "x".join(str(n) for n in occ.shape)
        connected = F.bfs_distance(occ, per, [goal]) >= 0
        repeats = max(1, args.repeats if occ.size <= 100_000 else args.large_repeats)
        baseline = None
        for label, solver, kwargs in _runs(args, occ.size):
            f, times = _time_solver(occ, per, goal, solver, kwargs, repeats)
            ok = reaches_goal_mask(f)[connected].mean()
            notes = []
            if solver == "gauss_seidel":
                baseline = times
                if "max_sweeps" in kwargs and not f.converged:
                    notes.append(f"CAPPED at {kwargs['max_sweeps']} sweeps: baseline time and ratios are "
                                 "lower bounds")
            if not f.converged and solver != "gauss_seidel":
                notes.append(f"not converged: {f.left}")
            walk = descend(f, start)
            if not walk.reached:
                notes.append(f"descent from the scenario start {tuple(int(x) for x in start)} fails: "
                             f"{walk.reason}")
            rec = {"stage": "field", "grid": grid, "solver": label, **times,
                   "baseline_seconds": baseline["seconds"], "ratio": baseline["seconds"] / times["seconds"],
                   "sweeps": f.sweeps, "converged": bool(f.converged), "residual": f.residual,
                   "descent_ok_fraction": float(ok),
                   # share of goal-connected nodes with u below the first band's floor
                   "tiny_u_fraction": float((f.log_u[connected] < np.log(BAND_FLOOR)).mean()),
                   "bands": f.stats.get("bands"), "scene": source}
            if notes:
                rec["note"] = "; ".join(notes)
            records.append(rec)
            print(f"{grid:>12} {label:>14} {1e3 * times['seconds']:10.2f} {1e3 * times['p90_s']:10.2f} "
                  f"{1e3 * times['max_s']:10.2f} {1e3 * baseline['seconds']:10.1f} "
                  f"{rec['ratio']:8.1f} {f.sweeps:7d} {str(f.converged):>5} {f.residual:9.1e} "
                  f"{ok:10.4f}  {'; '.join(notes)}", flush=True)
    for rec in records:
        print(json.dumps(rec))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
