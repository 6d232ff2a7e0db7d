"""
`make demo`: the closed loop on the paper's 3-DOF scene (or ``--params-file``'s), in one process.

planner_node + mock_arm_node + a small driver node that publishes the paper's target
pose (frame ``world``, (-3.27, -2.60), yaw 0) once the planner is up.  Prints the
progress (planning, stage timings, executing, reached), writes a figure of the plan
to ``--out`` (``demo_<scenario file's stem>.png``) and exits 0 once the arm is at the
goal (within 0.5°), 1 with a reason on timeout or failure.  ``--speedup`` scales the
velocity limits and the wheels' momentum limit by k, the acceleration limits and the
wheels' torque limit by k² (default 10: the motion takes a few seconds).
"""

from __future__ import annotations

import argparse
import math
import sys
import threading
import time
from pathlib import Path

import numpy as np

from ..collision import CollisionChecker
from ..config import load_params_file, load_scenario, scenario_from_params, spec_default
from ..cspace import build_cspace
from ..ik import capture_posture, grasp_ik
from ..joint_space import wrap_angle_rad
from .args import folder_to_write

_DEFAULT_PARAMS = Path(__file__).resolve().parents[2] / "config" / "paper_3dof.yaml"


def offline_facts(params_file) -> None:
    """Return what the old offline demo printed: robot, start clearance, IK, C-space."""
    sc = load_scenario(params_file)
    deg = np.degrees
    print(f"scene: {params_file}")
    print(f"robot: joints {sc.robot.joint_names}, planned {sc.robot.planned_names}, "
          f"links {sc.robot.link_lengths_m} m")
    chk = CollisionChecker(sc.robot, sc.scene)
    print(f"start {np.round(deg(sc.start_rad), 2)} deg: clearance {chk.clearance_m(sc.start_rad):.3f} m")
    cp = capture_posture(sc.robot, sc.scene.target)
    print(f"capture posture (max manipulability {cp.manipulability:.3f} m^2): "
          f"{np.round(deg(cp.q_full), 2)} deg, tip {np.round(cp.tip_m, 3)} m")
    for i, s in enumerate(grasp_ik(sc.robot, sc.scene)):
        print(f"IK branch {i}: {np.round(deg(s.q_full), 2)} deg, w={s.manipulability:.3f} m^2, "
              f"clearance {s.clearance_m:.3f} m ({s.method})")
    cs = build_cspace(sc.robot, sc.scene, sc.grid)
    print(f"C-space {cs.grid.label()}: {100 * cs.free_fraction:.1f} % free")


def _wrapped_err_deg(robot, q_full, goal):
    d = np.asarray(q_full)[list(robot.planned_joints)] - goal
    for k, p in enumerate(robot.planned_periodic):
        if p:
            d[k] = math.remainder(d[k], 2 * math.pi)
    return float(np.degrees(np.max(np.abs(d))))


def closed_loop(params_file, out: Path, speedup: float, timeout_s: float, target_xy, yaw_deg) -> int:
    # ROS (rclpy, the messages, the nodes) only here: offline_facts runs without it
    import rclpy
    from geometry_msgs.msg import PoseStamped
    from rclpy.executors import ExternalShutdownException
    from trajectory_msgs.msg import JointTrajectory

    from ..ros.executor import NodeExecutor
    from ..ros.mock_arm_node import MockArmNode
    from ..ros.parameters import MOCK_ARM_PARAMETERS
    from ..ros.planner_node import PlannerNode, params_to_overrides

    flat = load_params_file(params_file)
    for key, power in (("trajectory.max_velocity_deg_s", 1), ("trajectory.max_acceleration_deg_s2", 2)):
        flat[key] = [float(v) * speedup ** power for v in flat.get(key, spec_default(key))]
    # the wheels' momentum goes with the joint rates, their torque with the accelerations (0: no limit)
    for key, power in (("acs.max_wheel_momentum_Nms", 1), ("acs.max_wheel_torque_Nm", 2)):
        if key in flat:
            flat[key] = float(flat[key]) * speedup ** power
    scenario = scenario_from_params(flat)
    robot = scenario.robot
    t_start = time.monotonic()
    rc, reason = 1, f"timed out after {timeout_s:.0f} s"
    try:
        with rclpy.init():
            planner = PlannerNode(parameter_overrides=params_to_overrides(flat))
            arm = MockArmNode(parameter_overrides=params_to_overrides(
                {**load_params_file(params_file, node="mock_arm"), **flat}, MOCK_ARM_PARAMETERS))
            driver = rclpy.create_node("demo_driver")
            executor = NodeExecutor()    # as the executables' (see planner_node: no busy loop)
            for n in (planner, arm, driver):
                executor.add_node(n)
            got = []
            driver.create_subscription(JointTrajectory, "joint_trajectory", lambda m: got.append(m), 10)
            pub = driver.create_publisher(PoseStamped, "target_pose", 10)
            spin = threading.Thread(target=executor.spin, daemon=True)
            spin.start()
            try:
                while pub.get_subscription_count() == 0:
                    time.sleep(0.02)
                msg = PoseStamped()
                msg.header.frame_id = scenario.planning_frame
                msg.pose.position.x, msg.pose.position.y = target_xy
                msg.pose.orientation.z = math.sin(math.radians(yaw_deg) / 2)
                msg.pose.orientation.w = math.cos(math.radians(yaw_deg) / 2)
                print(f"[demo] planner up after {time.monotonic() - t_start:.1f} s; target_pose "
                      f"({target_xy[0]}, {target_xy[1]}) m, yaw {yaw_deg}° in '{msg.header.frame_id}'")
                pub.publish(msg)
                print("[demo] planning ...")
                phase = "planning"
                t_start = time.monotonic()      # the timeout is the loop's: the start-up (a first JIT) is not in it
                while time.monotonic() - t_start < timeout_s:
                    time.sleep(0.05)
                    refused = planner.diagnostics.last_rejection
                    if refused is not None and refused[0] == "target_pose":     # no plan follows
                        reason = f"the planner refused the target ({refused[1]}): {refused[2]}"
                        break
                    last = planner.last_outcome
                    if last is not None and not last.ok and last.code != "cancelled":
                        reason = f"planning failed ({last.code}): {last.reason}"
                        break
                    res = planner.last_result
                    if phase == "planning" and res is not None and got:
                        t = res.timings_s
                        print("[demo] plan ok: " + ", ".join(f"{k} {1e3 * v:.1f} ms" for k, v in t.items())
                              + f"; min clearance {res.min_clearance_m:.3f} m; goal "
                              f"{np.round(np.degrees(res.goal_rad), 2).tolist()}°")
                        traj = planner.last_trajectory
                        print(f"[demo] executing: {len(traj)} points, {traj.duration_s:.2f} s "
                              f"(limits × {speedup:g})")
                        phase = "executing"
                        _plot(res, scenario, out / f"demo_{Path(params_file).stem}.png")
                    if phase == "executing" and not arm.executing:
                        err = _wrapped_err_deg(robot, arm.positions, res.goal_rad)
                        if err < 0.5:
                            shown = np.where(robot.periodic, wrap_angle_rad(arm.positions), arm.positions)
                            print(f"[demo] reached the goal: {np.round(np.degrees(shown), 2).tolist()}° "
                                  f"(error {err:.3f}°) after {time.monotonic() - t_start:.1f} s")
                            rc, reason = 0, None
                            break
            finally:
                planner.shutdown_worker()
                executor.shutdown()
                spin.join(5.0)
                for n in (planner, arm, driver):
                    n.destroy_node()
    except (KeyboardInterrupt, ExternalShutdownException):
        reason = "interrupted"
    if reason:
        print(f"[demo] FAILED: {reason}", file=sys.stderr)
    return rc


def _plot(res, scenario, path: Path) -> None:
    try:
        from .plotting import plot_plan       # matplotlib: optional here
    except ImportError:
        print("[demo] spacerobot_planner.tools.plotting not available: no figure")
        return
    sc = scenario.with_scene(scenario.scene)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        plot_plan(res, sc, path)
        print(f"[demo] figure: {path}")
    except Exception as e:        # noqa: BLE001 - a figure must not fail the demo
        print(f"[demo] figure not written: {e}")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.strip().splitlines()[0])
    ap.add_argument("--params-file", default=str(_DEFAULT_PARAMS))
    ap.add_argument("--out", default="out", help="folder for figures")
    ap.add_argument("--speedup", type=float, default=10.0,
                    help="velocity limits × k, acceleration limits × k² (default 10)")
    ap.add_argument("--timeout", type=float, default=60.0,
                    help="seconds from the target's publication (the nodes' start and a first JIT not counted) "
                         "to the arm at the goal before giving up")
    ap.add_argument("--target", type=float, nargs=2, default=(-3.27, -2.60), metavar=("X", "Y"))
    ap.add_argument("--yaw-deg", type=float, default=0.0)
    ap.add_argument("--offline-only", action="store_true", help="print the offline facts and stop")
    args = ap.parse_args(argv)
    if not args.speedup > 0:
        ap.error("--speedup must be > 0")
    try:                              # a folder, or one that can be made (the figure comes mid-loop)
        folder_to_write(args.out, "--out")
    except ValueError as e:
        ap.error(str(e))
    try:
        offline_facts(args.params_file)
    except ValueError as e:
        print(f"demo: {e}", file=sys.stderr)
        return 1
    if args.offline_only:
        return 0
    return closed_loop(args.params_file, Path(args.out), args.speedup, args.timeout,
                       tuple(args.target), args.yaw_deg)


if __name__ == "__main__":
    sys.exit(main())
