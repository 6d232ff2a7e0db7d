"""
Start-up of planner_node as a user starts it: process start → ``active`` → the paper target's trajectory.

Starts ``planner_node --ros-args --params-file FILE`` as a subprocess, and, once it
subscribes, publishes the scene's start as ``joint_states`` (at 50 Hz, as a driver) and its target as
``target_pose``.  Figures: ``ready_s`` (process start → the node subscribes: configured
and active, planning process warmed up), ``first_plan_s`` (target sent → joint_trajectory
received) and ``start_to_trajectory_s``.  ``--cold`` deletes numba's cache of the package
first (a fresh install without ``make``'s cache step).  Prints a table and one JSON
object per line.  ``python -m spacerobot_planner.bench startup [--params-file F] [--cold]``
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

_PKG = Path(__file__).resolve().parent.parent
_PARAMS = _PKG.parent / "config" / "paper_3dof.yaml"


def clear_numba_cache(root: Path = _PKG) -> int:
    """Delete numba's cache files (*.nbi, *.nbc) under ``root``; return how many."""
    files = [p for ext in ("*.nbi", "*.nbc") for p in root.rglob(ext)]
    for p in files:
        p.unlink()
    return len(files)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.strip().splitlines()[0])
    ap.add_argument("--params-file", default=str(_PARAMS))
    ap.add_argument("--cold", action="store_true", help="delete numba's cache first")
    ap.add_argument("--timeout", type=float, default=120.0)
    args = ap.parse_args(argv)
    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    import rclpy
    from geometry_msgs.msg import PoseStamped
    from rclpy.context import Context
    from rclpy.executors import SingleThreadedExecutor
    from sensor_msgs.msg import JointState
    from trajectory_msgs.msg import JointTrajectory

    from ..config import load_params_file, scenario_from_params
    from ..ros.conversions import joint_state_msg, target_to_pose

    sc = scenario_from_params(load_params_file(args.params_file))
    removed = clear_numba_cache() if args.cold else 0
    ctx = Context()
    rclpy.init(context=ctx)
    drv = rclpy.create_node("startup_bench", context=ctx)
    got = []
    drv.create_subscription(JointTrajectory, "joint_trajectory", lambda m: got.append(time.perf_counter()), 10)
    pub_t = drv.create_publisher(PoseStamped, "target_pose", 10)
    pub_j = drv.create_publisher(JointState, "joint_states", 10)
    ex = SingleThreadedExecutor(context=ctx)
    ex.add_node(drv)
    cmd = [sys.executable, "-c", "import sys; from spacerobot_planner.ros.planner_node import main; sys.exit(main())",
           "--ros-args", "--params-file", args.params_file, "--log-level", os.environ.get("STARTUP_LOG", "warn")]
    t0 = time.perf_counter()
    log = None if "STARTUP_LOG" in os.environ else subprocess.DEVNULL    # STARTUP_LOG=info: the node's log
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=log)
    try:
        while pub_t.get_subscription_count() == 0 or pub_j.get_subscription_count() == 0:
            ex.spin_once(timeout_sec=0.01)
            if proc.poll() is not None or time.perf_counter() - t0 > args.timeout:
                print(f"startup: planner_node did not become active (exit {proc.poll()})", file=sys.stderr)
                return 1
        t_ready = time.perf_counter()
        # joint_states as a driver sends them, at 50 Hz: the node's subscription is best effort, and one
        # message sent while the node had not yet matched this publisher was lost ("no trajectory", the
        # node waiting for joint_states: 7 runs in 10 on a loaded machine)
        js = joint_state_msg(sc.robot.joint_names, sc.robot.full(sc.start_rad))
        pub_j.publish(js)
        drv.create_timer(0.02, lambda: pub_j.publish(js))
        t_sent = time.perf_counter()
        pub_t.publish(target_to_pose(sc.scene.target, sc.planning_frame))
        while not got:
            ex.spin_once(timeout_sec=0.01)
            if time.perf_counter() - t_sent > args.timeout:
                print(f"startup: no trajectory within {args.timeout:g} s of the target (STARTUP_LOG=info shows the "
                      f"node's log)", file=sys.stderr)
                return 1
    finally:
        proc.terminate()
        proc.wait(10)
        ex.shutdown()
        drv.destroy_node()
        rclpy.shutdown(context=ctx)
    row = {"bench": "startup", "params_file": args.params_file, "cold": args.cold, "numba_files_removed": removed,
           "ready_s": round(t_ready - t0, 3), "first_plan_s": round(got[0] - t_sent, 3),
           "start_to_trajectory_s": round(got[0] - t0, 3)}
    print(f"{'scenario':<28} {'cold':>5} {'ready s':>8} {'first plan s':>13} {'start→trajectory s':>19}")
    print(f"{Path(args.params_file).name:<28} {str(args.cold):>5} {row['ready_s']:>8.3f} {row['first_plan_s']:>13.3f} "
          f"{row['start_to_trajectory_s']:>19.3f}")
    print(json.dumps(row))
    return 0
