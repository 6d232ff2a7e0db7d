"""
Trajectory and spacecraft reaction on the paper's scenes, with the reference masses.

    python -m spacerobot_planner.bench reaction [--wheel 50 0.5] [--repeats 5]

Per scene (the planner's path, the config's joint limits): the time-optimal duration and,
when ``toppra`` is installed (a test dependency), TOPP-RA's on the same samples (grid 16×
finer); the wheel momentum and torque peaks with the attitude held; durations with the
momentum limit, the torque limit and both; the free-floating attitude change, body
displacement and tip miss; resampled point counts; the times (median, p90, max of ``--repeats`` calls) of
``time_parameterize`` and ``reaction_report``; and the largest joint acceleration (and
velocity) over the limit *between* the points when a controller interpolates them as
ros2_control's joint_trajectory_controller does (cubic from positions and velocities,
quintic with the accelerations too), for the dense trajectory and the one the node
publishes (resampled at 0.25 s).  Then a row for ``config/servicer_4joint.yaml`` (a redundant
arm, its own masses and wheels, attitude held): plan time, the attitude change, the tip's and
the approach's error at the end (the tip also in the inertial frame), the wheel peaks and the
free-floating drift.  Prints a table, then one JSON object per line.

Free floating (``config/free_floating_capture.yaml``, and the 3-DOF slew of
``config/servicer_3dof.yaml`` with ``acs.mode: free_floating``), one row per method: the
planner's capture (``free_floating_capture.plan_capture``: the field-guided and quintic
families with the approach offset as a free parameter), the same without the field's guide,
the same without the approach offset (exactly perpendicular postures, sine corrections only),
and the drift compensation (``free_floating.plan_free_floating``): plan time (a new planner,
then a replan from the same start), attitude change, body displacement, tip miss and approach
error in the inertial frame (the reaction report of the timed trajectory), path length,
duration.  Then ``--ff-starts`` cases of the capture scene with a random target (graspable
perpendicularly by a random posture whose attitude is within 20° of the start's, its centre at
least 2.2 m from the body's) and a random collision-free arm start: how often each method
ends in a grasp (tip within ``grasp.position_tolerance_m``, approach within
``grasp.max_approach_error_deg``, the drifted motion certified).
"""

from __future__ import annotations

import argparse
import json
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from .. import free_floating_capture as ffc
from ..collision import CollisionChecker
from ..config import load_scenario
from ..free_floating import plan_free_floating
from ..ik import grasp_ik
from ..planner import Planner, warm_up
from ..reaction import reaction_report
from ..spacecraft import MassProperties, WheelModel
from ..published import resample
from ..trajectory import time_parameterize
from .timing import call_times_s, tail_stats

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


def interpolated_ratios(traj, quintic: bool, samples: int = 40):
    """
    Return the largest acceleration and velocity ratios to the limits between the points.

    (largest |acceleration| / limit, largest |velocity| / limit) over the joints and over
    ``samples`` instants per interval, when the points are interpolated by cubic (positions,
    velocities) or quintic (…, accelerations) polynomials in time.
    """
    t, q, v, a = traj.times_s, traj.positions_rad, traj.velocities_rad_s, traj.accelerations_rad_s2
    T = np.diff(t)[:, None]
    p0, p1, v0, v1, a0, a1 = q[:-1], q[1:], v[:-1], v[1:], a[:-1], a[1:]
    if not quintic:
        a0 = a1 = np.zeros_like(p0)
    if quintic:
        c3 = (-20 * p0 + 20 * p1 - 3 * a0 * T ** 2 + a1 * T ** 2 - 12 * v0 * T - 8 * v1 * T) / (2 * T ** 3)
        c4 = (30 * p0 - 30 * p1 + 3 * a0 * T ** 2 - 2 * a1 * T ** 2 + 16 * v0 * T + 14 * v1 * T) / (2 * T ** 4)
        c5 = (-12 * p0 + 12 * p1 - a0 * T ** 2 + a1 * T ** 2 - 6 * v0 * T - 6 * v1 * T) / (2 * T ** 5)
        c2 = 0.5 * a0
    else:
        c2 = (-3 * p0 + 3 * p1 - 2 * v0 * T - v1 * T) / T ** 2
        c3 = (2 * p0 - 2 * p1 + v0 * T + v1 * T) / T ** 3
        c4 = c5 = np.zeros_like(p0)
    worst_a, worst_v = 0.0, 0.0
    for f in np.linspace(0.0, 1.0, samples):
        x = f * T
        acc = 2 * c2 + 6 * c3 * x + 12 * c4 * x ** 2 + 20 * c5 * x ** 3
        vel = v0 + 2 * c2 * x + 3 * c3 * x ** 2 + 4 * c4 * x ** 3 + 5 * c5 * x ** 4
        worst_a = max(worst_a, float(np.max(np.abs(acc) / traj.max_acceleration_rad_s2)))
        worst_v = max(worst_v, float(np.max(np.abs(vel) / traj.max_velocity_rad_s)))
    return worst_a, worst_v


def _ff_row(sc, method, start):
    """Plan one free-floating scene with ``method``; the row's figures (see the module docstring)."""
    saved = dict(ffc.SEARCH)
    try:
        if method == "capture, no approach offset":
            ffc.SEARCH["approach_as_parameter"] = False
        if method == "capture, no field guide":
            ffc.SEARCH["field_guide"] = False
        t0 = time.perf_counter()
        if method == "drift compensation":
            # its goal: the position-only grasp (the attitude locked) of the best branch, if any
            goals = grasp_ik(sc.robot, sc.scene)
            cp = plan_free_floating(replace(sc, acs=replace(sc.acs, compensate_drift=True)), start,
                                    goals[0].q if goals else None)
            planner = Planner(sc)
            res = planner.add_trajectory(cp.plan, start) if cp.plan.ok else cp.plan
            if cp.plan.ok and res.ok is False and res.code != "reaction_refused":
                res = cp.plan
            replan_s = float("nan")
        else:
            planner = Planner(sc)
            res = planner.plan(start)
            t1 = time.perf_counter()
            planner.plan(start)
            replan_s = time.perf_counter() - t1
        plan_s = time.perf_counter() - t0 - (0.0 if replan_s != replan_s else replan_s)
    finally:
        ffc.SEARCH.clear()
        ffc.SEARCH.update(saved)
    row = {"stage": "reaction", "grid": sc.params.get("_name", ""), "method": method, "code": str(res.code),
           "plan_s": plan_s, "replan_s": replan_s}
    rep = res.reaction
    if rep is not None:
        row.update(ff_attitude_change_deg=rep.free_floating_attitude_change_deg,
                   ff_body_displacement_m=rep.free_floating_body_displacement_m,
                   ff_tip_miss_m=rep.free_floating_tip_miss_m,
                   ff_approach_error_deg=rep.free_floating_approach_error_deg,
                   ff_collides=rep.free_floating_collides, duration_s=res.trajectory.duration_s)
    if len(res.path_rad):
        row["path_length_deg"] = float(np.degrees(res.path_length_rad))
        row["grasp"] = bool(res.ok)
    else:
        row["grasp"] = False
    row["reason"] = res.reason
    return row


FF_METHODS = ("capture", "capture, no field guide", "capture, no approach offset", "drift compensation")


def free_floating_rows(n_starts: int, seed: int = 0) -> list:
    """Return the free-floating rows (see the module docstring): per scene and method, then the random starts."""
    rows = []
    cap = load_scenario(CONFIG / "free_floating_capture.yaml")
    cap = replace(cap, params=dict(cap.params, _name="free_floating_capture"))
    slew = load_scenario(CONFIG / "servicer_3dof.yaml")
    slew = replace(slew, acs=replace(slew.acs, mode="free_floating"),
                   params=dict(slew.params, _name="servicer_3dof free floating"))
    warm_up(cap)                 # every kernel the rows meet (the capture's search among them): no JIT in a row
    for method in FF_METHODS:
        rows.append(_ff_row(cap, method, cap.start_rad))
    t0 = time.perf_counter()
    res = Planner(slew).plan(slew.start_rad, slew.goal_rad)
    rows.append({"stage": "reaction", "grid": "servicer_3dof free floating", "method": "capture",
                 "code": str(res.code), "plan_s": time.perf_counter() - t0, "grasp": bool(res.ok),
                 "reason": res.reason})
    rng = np.random.default_rng(seed)
    lo, hi = cap.robot.planned_lower_rad, cap.robot.planned_upper_rad
    cases = []                   # (scenario with a random target, a random free start)
    t0_ = cap.scene.target
    handle = np.asarray(t0_.grasp_point_m) - np.asarray(t0_.center_m)         # at yaw 0
    while len(cases) < n_starts:
        # a target graspable perpendicularly by a posture whose attitude is within 20° of the start's
        # (the arm's motions turn the body by tens of degrees at most)
        q_grasp = np.array([cap.robot.locked_rad[0] + rng.uniform(-1.0, 1.0) * np.radians(20.0),
                            rng.uniform(-np.pi, np.pi), rng.uniform(np.radians(20.0), np.radians(160.0))])
        grasp = cap.robot.tip_position(q_grasp)
        yaw = float(np.sum(q_grasp)) - 1.5 * np.pi
        rot = np.array([[np.cos(yaw), -np.sin(yaw)], [np.sin(yaw), np.cos(yaw)]])
        centre = grasp - rot @ handle
        if np.linalg.norm(centre) < 2.2:
            continue
        target = replace(t0_, center_m=(float(centre[0]), float(centre[1])), yaw_rad=float(yaw))
        sc = cap.with_scene(replace(cap.scene, target=target))
        checker = CollisionChecker(sc.robot, sc.scene)
        for _ in range(50):
            q = rng.uniform(lo, hi)
            if checker.clearance_m(q) > 0.1:
                cases.append((sc, q))
                break
    for method in FF_METHODS:
        got = [_ff_row(sc, method, q) for sc, q in cases]
        ok = [r for r in got if r["grasp"]]
        rows.append({"stage": "reaction", "grid": f"free_floating_capture, {n_starts} random targets and starts",
                     "method": method, "grasps": len(ok), "starts": n_starts,
                     "refused_out_of_range": sum("no arm motion tried turns" in (r["reason"] or "") for r in got),
                     "refused_collisions": sum("come within the safety margin" in (r["reason"] or "") for r in got),
                     "median_plan_s": float(np.median([r["plan_s"] for r in got])),
                     "p90_plan_s": float(np.percentile([r["plan_s"] for r in got], 90)),
                     "max_plan_s": float(max(r["plan_s"] for r in got)),
                     "median_duration_s": float(np.median([r["duration_s"] for r in ok])) if ok else None,
                     "median_path_length_deg": float(np.median([r["path_length_deg"] for r in ok])) if ok else None})
    return rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="bench reaction")
    ap.add_argument("--wheel", type=float, nargs=2, default=(50.0, 0.5), metavar=("NMS", "NM"),
                    help="wheel momentum and torque limits (default: the reference page's 50 0.5)")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--ff-starts", type=int, default=12, help="random starts of the free-floating capture scene")
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
        vmax, amax = sc.joint_limits.planned(robot)
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
        published = resample(traj, checker, time_step_s=0.25).trajectory
        for label, tr in (("dense", traj), ("published", published)):
            for kind in ("cubic", "quintic"):
                ra, rv = interpolated_ratios(tr, kind == "quintic")
                row[f"{kind}_{label}_max_acc_ratio"], row[f"{kind}_{label}_max_vel_ratio"] = ra, rv
        wheel = WheelModel(robot, masses, *args.wheel)
        for key, fn in (("seconds", lambda: time_parameterize(path, vmax, amax)),
                        ("seconds_with_wheel", lambda: time_parameterize(path, vmax, amax, wheel=wheel)),
                        ("seconds_reaction_report", lambda: reaction_report(robot, masses, sc.scene, path, traj))):
            st = tail_stats(call_times_s(fn, args.repeats), median_key=key, count_key=f"{key}_runs")
            row.update({key: st[key], **{f"{key}_{k[:-2]}": st[k] for k in ("p90_s", "min_s", "max_s")},
                        f"{key}_runs": st[f"{key}_runs"]})
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
    print(f"times, ms (median / p90 / max of {args.repeats}): time_parameterize, with the wheel limits, "
          "reaction_report")
    for r in rows:
        print(f"  {r['grid']:12} " + "; ".join(
            f"{1e3 * r[key]:.2f} / {1e3 * r[f'{key}_p90']:.2f} / {1e3 * r[f'{key}_max']:.2f}"
            for key in ("seconds", "seconds_with_wheel", "seconds_reaction_report")))
    print("between the points, interpolated as joint_trajectory_controller does (largest |a| / limit, "
          "|v| / limit):")
    for r in rows:
        print(f"  {r['grid']:12} " + "; ".join(
            f"{kind} {label} {r[f'{kind}_{label}_max_acc_ratio']:.3f} / {r[f'{kind}_{label}_max_vel_ratio']:.3f}"
            for label in ("dense", "published") for kind in ("cubic", "quintic")))
    red = redundant_row(args.repeats)
    print(f"servicer_4joint (held): plan {1e3 * red['plan_seconds']:.0f} ms (p90 {1e3 * red['p90_s']:.0f}, "
          f"max {1e3 * red['max_s']:.0f} of {red['plans']}), attitude change "
          f"{red['attitude_change_deg']:.1f}°, tip error {1e3 * red['tip_error_m']:.3f} mm planned / "
          f"{1e3 * red['held_tip_miss_m']:.1f} mm inertial, approach error {red['approach_error_deg']:.2e}°, "
          f"trajectory {red['duration_s']:.1f} s (wheel peaks {red['peak_wheel_momentum_Nms']:.1f} N·m·s, "
          f"{red['peak_wheel_torque_Nm']:.3f} N·m); free floating it would turn "
          f"{red['ff_attitude_change_deg']:.2f}° and miss by {red['ff_tip_miss_m']:.3f} m")
    ff = free_floating_rows(args.ff_starts)
    print("free floating (inertial frame; plan = new planner, replan = same start again):")
    print(f"  {'scene':32} {'method':28} {'code':17} {'plan ms':>8} {'replan':>7} {'Δθ1 °':>7} {'body m':>7} "
          f"{'tip m':>9} {'appr °':>7} {'path °':>7} {'T s':>6}")
    for r in ff:
        if "starts" in r:
            continue

        def f(key, fmt, scale=1.0):
            v = r.get(key)
            return format(scale * v, fmt) if isinstance(v, float) and v == v else "-"
        print(f"  {r['grid']:32} {r['method']:28} {r['code']:17} {f('plan_s', '8.1f', 1e3):>8} "
              f"{f('replan_s', '7.1f', 1e3):>7} "
              f"{f('ff_attitude_change_deg', '7.2f')} {f('ff_body_displacement_m', '7.3f')} "
              f"{f('ff_tip_miss_m', '9.2e')} {f('ff_approach_error_deg', '7.2f')} {f('path_length_deg', '7.1f')} "
              f"{f('duration_s', '6.2f')}")
    for r in ff:
        if "starts" in r:
            print(f"  {r['grid']}: {r['method']}: {r['grasps']}/{r['starts']} grasps (refused: "
                  f"{r['refused_out_of_range']} out of the motions' attitude range, {r['refused_collisions']} "
                  f"collide), plans {1e3 * r['median_plan_s']:.1f} / {1e3 * r['p90_plan_s']:.1f} / "
                  f"{1e3 * r['max_plan_s']:.1f} ms (median / p90 / max); of the grasps, median duration "
                  f"{r['median_duration_s'] or float('nan'):.2f} s, median path "
                  f"{r['median_path_length_deg'] or float('nan'):.1f}°")
    for r in rows + [red] + ff:
        print(json.dumps(r))
    return 0


def redundant_row(repeats: int) -> dict:
    """
    Return the row of ``config/servicer_4joint.yaml`` (attitude held, its wheels and masses).

    The plan to the target's capture posture (the median time of ``repeats`` fresh planners
    after a warm-up: grasp IK, C-space, field, descent, smoothing, check, trajectory with the
    spacecraft's reaction), the attitude change it commands, the tip's error at the end (as
    planned, and in the inertial frame: the body translates so that the centre of mass stays),
    the approach error, and what the same motion would do free floating.
    """
    sc = load_scenario(CONFIG / "servicer_4joint.yaml")
    Planner(sc, reaction=True).plan(sc.start_rad)                      # warm-up (numba)
    plans = []
    for _ in range(max(1, repeats)):
        t0 = time.perf_counter()
        res = Planner(sc, reaction=True).plan(sc.start_rad)
        plans.append((time.perf_counter() - t0, res))
    times = tail_stats([t for t, _ in plans], median_key="plan_seconds", count_key="plans")
    res = plans[-1][1]
    if not res.ok:
        raise RuntimeError(f"servicer_4joint: no plan ({res.code}): {res.reason}")
    robot, path, rep = sc.robot, res.path_rad, res.reaction
    tip = robot.tip_position(robot.full(path[-1]))
    return {"stage": "reaction", "grid": "servicer_4joint", "cells": list(sc.grid.cells), **times,
            "timings_s": {k: float(v) for k, v in res.timings_s.items()},
            "attitude_change_deg": float(np.degrees(path[-1, 0] - path[0, 0])),
            "tip_error_m": float(np.linalg.norm(tip - sc.scene.target.grasp_point_m)),
            "held_tip_miss_m": rep.held_tip_miss_m, "held_body_displacement_m": rep.held_body_displacement_m,
            "approach_error_deg": res.approach_error_deg, "duration_s": res.trajectory.duration_s,
            "peak_wheel_momentum_Nms": rep.peak_wheel_momentum_Nms, "peak_wheel_torque_Nm": rep.peak_wheel_torque_Nm,
            "ff_attitude_change_deg": rep.free_floating_attitude_change_deg,
            "ff_tip_miss_m": rep.free_floating_tip_miss_m, "min_clearance_m": res.min_clearance_m}
