"""
Trajectory and spacecraft reaction on the paper's scenes, with the reference masses.

    python -m spacerobot_planner.bench reaction [--wheel 50 0.5] [--repeats 5]

Per scene (the planner's path, the config's joint limits): the time-optimal duration and,
when ``toppra`` is installed (a test dependency), TOPP-RA's on the same samples (grid 16×
finer); the wheel momentum and torque peaks with the attitude held; durations with the
momentum limit, the torque limit and both; the free-floating attitude change, body
displacement and tip miss; resampled point counts; the median time of
``time_parameterize`` and ``reaction_report``.  Prints a table, then one JSON object per line.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from ..collision import CollisionChecker
from ..config import load_scenario
from ..dynamics import MassProperties, WheelModel, reaction_report, scenario_joint_limits
from ..planner import Planner
from ..trajectory import resample, time_parameterize

CONFIG = Path(__file__).resolve().parent.parent.parent / "config"


def _toppra_s(path, vmax, amax):
    try:
        import toppra
        import toppra.algorithm
        import toppra.constraint
    except ImportError:
        return None
    toppra.setup_logging("WARNING")
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(path, axis=0), axis=1))])
    cons = [toppra.constraint.JointVelocityConstraint(np.stack([-vmax, vmax], axis=1)),
            toppra.constraint.JointAccelerationConstraint(
                np.stack([-amax, amax], axis=1),
                discretization_scheme=toppra.constraint.DiscretizationType.Interpolation)]
    algo = toppra.algorithm.TOPPRA(cons, toppra.SplineInterpolator(s, path),
                                   gridpoints=np.linspace(0.0, s[-1], 16 * len(path) + 1),
                                   parametrizer="ParametrizeConstAccel")
    return float(algo.compute_trajectory(0.0, 0.0).duration)


def _median_s(fn, repeats):
    out = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        out.append(time.perf_counter() - t0)
    return float(np.median(out))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="bench reaction")
    ap.add_argument("--wheel", type=float, nargs=2, default=(50.0, 0.5), metavar=("NMS", "NM"),
                    help="wheel momentum and torque limits (default: the reference page's 50 0.5)")
    ap.add_argument("--repeats", type=int, default=5)
    args = ap.parse_args(argv)
    masses = MassProperties()
    rows = []
    for name in ("paper_2dof", "paper_3dof"):
        sc = load_scenario(CONFIG / f"{name}.yaml")
        res = Planner(sc).plan(sc.start_rad, sc.goal_rad)
        if not res.ok:
            print(f"{name}: no path ({res.code})")
            return 1
        robot, path = sc.robot, res.path_rad
        vmax, amax, _, _ = scenario_joint_limits(sc)
        traj = time_parameterize(path, vmax, amax, robot.planned_names)
        rep = reaction_report(robot, masses, sc.scene, path, traj)
        row = {"stage": "reaction", "grid": name, "points": len(traj), "duration_s": traj.duration_s,
               "toppra_s": _toppra_s(path, vmax, amax),
               "peak_wheel_momentum_Nms": rep.peak_wheel_momentum_Nms,
               "peak_wheel_torque_Nm": rep.peak_wheel_torque_Nm}
        for label, lim in (("momentum", (args.wheel[0], None)), ("torque", (None, args.wheel[1])),
                           ("both", tuple(args.wheel))):
            row[f"duration_{label}_limit_s"] = time_parameterize(
                path, vmax, amax, wheel=WheelModel(robot, masses, *lim)).duration_s
        row.update(ff_attitude_change_deg=rep.free_floating_attitude_change_deg,
                   ff_body_displacement_m=rep.free_floating_body_displacement_m,
                   ff_tip_miss_m=rep.free_floating_tip_miss_m, ff_collides=rep.free_floating_collides,
                   held_tip_miss_m=rep.held_tip_miss_m)
        checker = CollisionChecker(robot, sc.scene)
        row["resampled_points"] = len(resample(traj, checker).trajectory)
        row["seconds"] = _median_s(lambda: time_parameterize(path, vmax, amax), args.repeats)
        row["seconds_with_wheel"] = _median_s(
            lambda: time_parameterize(path, vmax, amax, wheel=WheelModel(robot, masses, *args.wheel)), args.repeats)
        row["seconds_reaction_report"] = _median_s(
            lambda: reaction_report(robot, masses, sc.scene, path, traj), args.repeats)
        rows.append(row)
    print(f"{'scene':12} {'T [s]':>8} {'TOPP-RA':>8} {'h peak':>7} {'τ peak':>7} {'T h/τ/both [s]':>22} "
          f"{'ff Δθ1':>7} {'ff miss':>8} {'pts':>9} {'tp ms':>6}")
    for r in rows:
        tp = f"{r['toppra_s']:.3f}" if r["toppra_s"] is not None else "n/a"
        print(f"{r['grid']:12} {r['duration_s']:8.3f} {tp:>8} {r['peak_wheel_momentum_Nms']:7.1f} "
              f"{r['peak_wheel_torque_Nm']:7.1f} {r['duration_momentum_limit_s']:7.2f}/"
              f"{r['duration_torque_limit_s']:.2f}/{r['duration_both_limit_s']:.2f} "
              f"{r['ff_attitude_change_deg']:6.2f}° {r['ff_tip_miss_m']:7.3f}m "
              f"{r['points']:4d}→{r['resampled_points']:<4d} {1e3 * r['seconds']:6.1f}")
    for r in rows:
        print(json.dumps(r))
    return 0
