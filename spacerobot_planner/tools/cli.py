"""
``spacerobot-plan``: plan one capture motion offline from a scenario file.

    spacerobot-plan --params-file config/paper_3dof.yaml [--start-deg A B C]
        [--goal-deg A B C] [--cells N] [--solver NAME] [--json PATH] [--plot PATH]
    spacerobot-plan envelope --params-file F --x-m X0 X1 NX --y-m Y0 Y1 NY
        --yaw-deg A0 A1 NA --out DIR [--scheduler ADDRESS]    (tools/envelope_cli.py)

The trajectory is made by the same chain as the node's (``adapters.post_process``: time
parameterisation, the spacecraft's reaction, resampling certified on the exact geometry,
the arm/attitude split): ``--json`` carries it as ``published_trajectory`` (the
``joint_trajectory`` and ``attitude_trajectory`` the node publishes for the same request
from rest, point for point) and the dense samples as ``dense_trajectory``.

Exit status: 0 a path was found, 2 there is none or the spacecraft's reaction refuses
it (``acs.mode: free_floating`` and the drifted arm collides or misses the grasp; the
reason is printed and in the JSON), 1 bad input (a message naming the field on stderr).
"""

from __future__ import annotations

import argparse
import functools
import gc
import json
import math
import sys

import numpy as np

from ..cores import threads_text
from ..field import SOLVERS
from ..jit_cache import start_numba
from ..offline import plan_offline
from ..planner import Planner
from ..timing import Motion
from .args import Parser, fail_input, load, option_value, output_file, parse, posture, with_cells

__all__ = ["main", "build_parser", "run"]


def build_parser() -> argparse.ArgumentParser:
    ap = Parser(prog="spacerobot-plan", description=__doc__.strip().split("\n\n")[0].replace("``", ""),
                formatter_class=argparse.RawDescriptionHelpFormatter,
                epilog="spacerobot-plan envelope --help: capture envelope maps over target poses "
                       "(docs/envelope.md)")
    ap.add_argument("--params-file", required=True, help="ROS 2 parameter file (config/paper_3dof.yaml)")
    ap.add_argument("--start-deg", type=float, nargs="+", metavar="DEG",
                    help="start posture of the planned joints, degrees (default: scenario.start_deg)")
    ap.add_argument("--goal-deg", type=float, nargs="+", metavar="DEG",
                    help="goal posture, degrees (default: scenario.goal_deg, else the target's IK)")
    ap.add_argument("--cells", type=int, nargs="+", metavar="N",
                    help="grid cells per planned joint (one value for all, or one per joint)")
    ap.add_argument("--solver", help=f"field solver: {', '.join(SOLVERS)}")
    ap.add_argument("--tolerance", type=float, help="gauss_seidel's tolerance (planner.field_tolerance)")
    ap.add_argument("--field-budget", type=float, help="field budget, seconds (planner.field_budget_s)")
    ap.add_argument("--json", metavar="PATH", help="write the result as JSON ('-' for stdout)")
    ap.add_argument("--plot", metavar="PATH", help="write a figure: C-space, potential, path, arm motion (its "
                    "format by the suffix, .png where none; the reaction's beside it, NAME_reaction)")
    ap.add_argument("--quiet", action="store_true", help="no stage lines")
    return ap


def _summary(res, scenario, chain_s: float = 0.0) -> list:
    deg = np.degrees
    lines = []
    t = res.timings_s
    stages = ", ".join(f"{k} {'cached' if k in res.cached else f'{1e3 * t[k]:.1f} ms'}"
                       for k in ("cspace", "field", "descent", "repair", "smoothing", "verify", "trajectory")
                       if k in t)
    if chain_s:
        stages += f" (of it the node's chain {1e3 * chain_s:.1f} ms)"
    lines.append(f"stages: {stages}; total {1e3 * t['total']:.1f} ms{threads_text(res.solver_stats)}")
    if res.ok:
        lines.append(f"path: {len(res.path_rad)} samples ({res.smoothing}), {len(res.grid_path_rad)} grid nodes, "
                     f"length {res.path_length_rad:.3f} rad ({deg(res.path_length_rad):.1f}°), "
                     f"min clearance {res.min_clearance_m:.4f} m "
                     f"(margin {scenario.scene.safety_margin_m} m)")
        lines.append(f"start {np.round(deg(res.path_rad[0]), 2).tolist()}° → "
                     f"goal {np.round(deg(res.goal_rad), 2).tolist()}°")
    else:
        lines.append(f"no path ({res.code}): {res.reason}")
    return lines


def _motion_summary(r, processed) -> list:
    traj = processed.dense
    labels, counts = np.unique(traj.active_limit, return_counts=True)
    active = ", ".join(f"{lab} {100 * c / len(traj):.0f} %" for lab, c in
                       sorted(zip(labels, counts), key=lambda lc: -lc[1]))
    lines = [f"published trajectory (the time-optimal one re-timed where the controller's interpolation of the "
             f"published points overshoots a limit): {traj.duration_s:.2f} s, {len(processed.trajectory)} points "
             f"published (of {len(traj)} dense samples; "
             f"{'certified' if processed.certified else 'NOT certified'}, clearance "
             f"{processed.min_clearance_m:.4f} m); active limits: {active}"]

    def lim(v, unit):
        return "no limit" if v is None else f"limit {v:g} {unit}"

    if r is None:
        return lines
    lines.append(f"reaction ({r.acs_mode}): wheel momentum peak {r.peak_wheel_momentum_Nms:.2f} N·m·s "
                 f"({lim(r.max_wheel_momentum_Nms, 'N·m·s')}), torque peak {r.peak_wheel_torque_Nm:.3f} N·m "
                 f"({lim(r.max_wheel_torque_Nm, 'N·m')}); free floating: attitude change "
                 f"{r.free_floating_attitude_change_deg:.2f}°, body displacement "
                 f"{r.free_floating_body_displacement_m:.3f} m, tip miss {r.free_floating_tip_miss_m:.3f} m"
                 f"{', drifted arm collides' if r.free_floating_collides else ''}")
    if r.acs_mode == "held" and r.held_tip_miss_m == r.held_tip_miss_m:
        beyond = (f" (beyond grasp.position_tolerance_m {r.position_tolerance_m:g} m)"
                  if r.held_tip_miss_m > r.position_tolerance_m else "")
        lines.append(f"held attitude: the body still translates {r.held_body_displacement_m:.3f} m (the centre of "
                     f"mass stays put), so the tip ends {r.held_tip_miss_m:.3f} m from the grasp point{beyond}")
    return lines


def main(argv=None) -> int:
    start_numba()                   # a process of its own: cached kernels without their linking bitcode, no BLAS check
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv[:1] == ["envelope"]:
        from .envelope_cli import main as envelope_main     # Dask: loaded only for a sweep
        return envelope_main(argv[1:])
    args, rc = parse(build_parser(), argv)
    if args is None:
        return rc
    # ---- inputs (exit 1 on anything malformed, naming the field)
    try:
        scenario = load(args.params_file)
        robot = scenario.robot
        given = scenario.planner_settings           # the file's planner.* (defaults filled)
        if args.cells is not None:
            scenario = with_cells(scenario, args.cells)
        solver = args.solver if args.solver is not None else given.solver
        if solver not in SOLVERS:
            raise ValueError(f"--solver: unknown solver {solver!r}; expected one of {', '.join(SOLVERS)}")
        # the file's (checked when it was read), or the option's, checked here
        tol = (given.field_tolerance if args.tolerance is None else
               option_value("planner.field_tolerance", float(args.tolerance), "--tolerance"))
        field_budget = (given.field_budget_s if args.field_budget is None else
                        option_value("planner.field_budget_s", float(args.field_budget), "--field-budget"))
        # the outputs checked before the plan (it had run whole, then a traceback)
        json_path = None if args.json in (None, "-") else output_file(args.json, "--json", default_suffix=".json")
        plot_path = None if args.plot is None else output_file(args.plot, "--plot", _figure_formats(), ".png")

        if args.start_deg is not None:
            start = posture(robot, args.start_deg, "--start-deg")
        elif scenario.start_rad is not None:
            start = scenario.start_rad
        else:
            raise ValueError("--start-deg: no start given and the file has no scenario.start_deg")
        goal = posture(robot, args.goal_deg, "--goal-deg") if args.goal_deg is not None else scenario.goal_rad
        planner = Planner(scenario, solver=solver, field_tolerance=tol, field_budget_s=field_budget, reaction=True)
    except ValueError as e:
        return fail_input(str(e))
    # ---- plan (with --json -, stdout is the JSON alone: the lines for people go to stderr)
    say = functools.partial(print, file=sys.stderr if args.json == "-" else sys.stdout, flush=True)
    progress = None if args.quiet else (lambda line: say(f"  {line}"))
    if not args.quiet:
        say(f"planning {args.params_file}: joints {', '.join(robot.planned_names)}, "
            f"grid {scenario.grid.label()}, solver {solver}")
    try:
        done = plan_offline(planner, start, goal, progress=progress)
    except ValueError as e:            # the drift compensation refuses the scenario
        return fail_input(str(e))
    res, processed, comp = done.result, done.processed, done.compensated
    if res.code == "invalid_input":
        return fail_input(res.reason)
    if comp is not None:
        say(f"drift compensation: {len(comp.history)} plans, tip miss "
            f"{' → '.join(f'{h[0]:.4f}' for h in comp.history)} m; goal "
            f"{np.round(np.degrees(comp.goal_rad), 2).tolist()}°")
    for line in _summary(res, scenario, done.chain_s):
        say(line)
    if processed is not None:
        for line in _motion_summary(res.reaction, processed):
            say(line)
        if res.code == "reaction_refused":
            print(f"spacerobot-plan: refused: {res.reason}", file=sys.stderr)
    if args.json:
        doc = res.to_json_dict()
        if processed is not None:
            clr = processed.min_clearance_m
            doc["trajectory_resampled"] = dict(processed.trajectory.to_json_dict(), certified=processed.certified,
                                               min_clearance_m=float(clr) if math.isfinite(clr) else None)
            doc["published_trajectory"] = processed.to_json_dict()
            doc["dense_trajectory"] = processed.dense.to_json_dict()
        text = json.dumps(doc, indent=None, allow_nan=False)
        if json_path is None:
            print(text)
        else:
            try:
                json_path.parent.mkdir(parents=True, exist_ok=True)
                json_path.write_text(text + "\n", encoding="utf-8")
            except OSError as e:
                return fail_input(f"--json: cannot write {json_path}: {e.strerror or e}")
            say(f"wrote {json_path}")
    if plot_path is not None:
        from .plotting import plot_plan, plot_reaction     # matplotlib: loaded only when a plot is asked for
        written = [plot_path]
        if res.reaction is not None:        # the reaction's figure beside it, in the same format
            written.append(plot_path.with_name(plot_path.stem + "_reaction" + plot_path.suffix))
        try:
            plot_path.parent.mkdir(parents=True, exist_ok=True)
            plot_plan(res, scenario, plot_path)
            if res.reaction is not None:
                plot_reaction(Motion(res.trajectory, res.reaction), written[1])
        except OSError as e:
            return fail_input(f"--plot: cannot write {plot_path}: {e.strerror or e}")
        for path in written:
            say(f"wrote {path}")
    return 0 if res.ok else 2


def _figure_formats() -> set:
    """Return the file formats matplotlib writes (suffixes without the dot); imports matplotlib (``--plot`` only)."""
    from matplotlib.backend_bases import FigureCanvasBase
    return set(FigureCanvasBase.get_supported_filetypes())


def run(argv=None) -> int:
    """
    Run the console script ``spacerobot-plan`` (:func:`main`); return its status for an exit without cycle collections.

    The process ends right after (``sys.exit``).  The interpreter's exit collected cycles over
    the whole heap of numba's registries and the loaded kernels, several times (0.08 of the
    0.55 s of a cold start's paper 3-DOF plan; ``perf``: ``gc_collect_main``); frozen
    (``gc.freeze``), they are left to the process's end, as every object still referenced is.
    Whatever the run wrote is closed by then (files are written whole, stdout and stderr are
    flushed at exit as before; ``envelope``'s Dask cluster is closed before :func:`main`
    returns).  Not in :func:`main`, which tests and other code call in a process that goes on.
    (A Ctrl-C that :func:`main` does not take itself: ``tools.entry.plan``.)
    """
    rc = main(argv)
    gc.freeze()
    return rc


if __name__ == "__main__":
    sys.exit(run())
