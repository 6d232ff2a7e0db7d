"""
Latency of planner_node: message in → joint_trajectory out, in one process.

- ``latency_target``: a new ``target_pose`` (each repeat a new pose, so the C-space and
  the field are rebuilt) → the ``joint_trajectory`` message (aim < 150 ms at 36³);
- ``latency_joint_state``: a new ``joint_states`` + ``~/replan`` (C-space and field
  cached) → the ``joint_trajectory`` message (aim < 20 ms).

Median of ``--repeats`` after one warm-up plan.  Prints a table and one JSON object
per line.  ``python -m spacerobot_planner.bench latency [--cells 36] [--repeats 7]``
"""

from __future__ import annotations

import argparse
import json
import statistics
import threading
import time
from pathlib import Path

import numpy as np

_PARAMS = Path(__file__).resolve().parent.parent.parent / "config" / "paper_3dof.yaml"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.strip().splitlines()[0])
    ap.add_argument("--params-file", default=str(_PARAMS))
    ap.add_argument("--cells", type=int, default=36)
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--in-process", action="store_true",
                    help="plan in the worker thread instead of the child process")
    args = ap.parse_args(argv)

    import os
    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    import rclpy
    from geometry_msgs.msg import PoseStamped
    from rclpy.context import Context
    from rclpy.executors import SingleThreadedExecutor
    from sensor_msgs.msg import JointState
    from std_srvs.srv import Trigger
    from trajectory_msgs.msg import JointTrajectory

    from ..config import load_params_file, scenario_from_params
    from ..ros.planner_node import PlannerNode, params_to_overrides
    from ..ros.conversions import joint_state_msg

    flat = load_params_file(args.params_file)
    flat["grid.cells"] = [args.cells] * len(flat.get("robot.planned_joints", [0, 0, 0]))
    flat["planner.separate_process"] = not args.in_process
    sc = scenario_from_params(flat)
    robot = sc.robot
    ctx = Context()
    rclpy.init(context=ctx)
    node = PlannerNode(context=ctx, parameter_overrides=params_to_overrides(flat))
    drv = rclpy.create_node("latency_driver", context=ctx)
    ex = SingleThreadedExecutor(context=ctx)     # as planner_node.main
    ex.add_node(node)
    ex.add_node(drv)
    got = []
    cond = threading.Condition()

    def on_traj(msg):
        with cond:
            got.append(time.perf_counter())
            cond.notify_all()

    drv.create_subscription(JointTrajectory, "joint_trajectory", on_traj, 10)
    pub_t = drv.create_publisher(PoseStamped, "target_pose", 10)
    pub_js = drv.create_publisher(JointState, "joint_states", 10)
    cli = drv.create_client(Trigger, "/spacerobot_planner/replan")
    spin = threading.Thread(target=ex.spin, daemon=True)
    spin.start()
    rows = []
    try:
        while pub_t.get_subscription_count() == 0 or pub_js.get_subscription_count() == 0:
            time.sleep(0.02)
        cli.wait_for_service(10.0)

        def wait_traj(n, timeout=120.0):
            with cond:
                ok = cond.wait_for(lambda: len(got) >= n, timeout)
            if not ok:
                raise RuntimeError(f"no trajectory within {timeout} s (state {node.state}, "
                                   f"error {node.last_error})")
            return got[n - 1]

        q_full = robot.full(sc.start_rad)
        pub_js.publish(joint_state_msg(robot.joint_names, q_full))
        time.sleep(0.3)

        def target(i):
            m = PoseStamped()
            m.header.frame_id = sc.planning_frame
            m.pose.position.x, m.pose.position.y = -3.27 + 0.01 * (i % 5), -2.60 + 0.01 * (i // 5)
            m.pose.orientation.w = 1.0
            return m

        pub_t.publish(target(0))                                  # warm-up (process start, JIT cache)
        wait_traj(1)
        lat_t = []
        for i in range(1, args.repeats + 1):
            n = len(got)
            t0 = time.perf_counter()
            pub_t.publish(target(i))
            lat_t.append(wait_traj(n + 1) - t0)
            time.sleep(0.05)
        lat_j = []
        rng = np.random.default_rng(0)
        for i in range(args.repeats):
            q = q_full.copy()
            q[list(robot.planned_joints)] += np.radians(rng.uniform(-1.0, 1.0, robot.dof))
            n = len(got)
            t0 = time.perf_counter()
            pub_js.publish(joint_state_msg(robot.joint_names, q))
            time.sleep(0.0)
            while node._joint_q is None or not np.allclose(node._joint_q, q[list(robot.planned_joints)]):
                time.sleep(0.0005)
            cli.call_async(Trigger.Request())
            lat_j.append(wait_traj(n + 1) - t0)
            time.sleep(0.05)
        cached = node.last_result.cached
        grid = sc.grid.label()
        for stage, vals, aim in (("latency_target", lat_t, 0.150), ("latency_joint_state", lat_j, 0.020)):
            rows.append({"stage": stage, "grid": grid, "seconds": statistics.median(vals),
                         "min_s": min(vals), "max_s": max(vals), "repeats": len(vals), "aim_s": aim,
                         "backend": "thread" if args.in_process else "process",
                         **({"cached": list(cached)} if stage == "latency_joint_state" else {})})
    finally:
        node.shutdown_worker()
        ex.shutdown()
        spin.join(5.0)
        node.destroy_node()
        drv.destroy_node()
        rclpy.shutdown(context=ctx)
    print(f"{'stage':<22}{'grid':<12}{'median ms':>10}{'min ms':>9}{'max ms':>9}{'aim ms':>8}")
    for r in rows:
        print(f"{r['stage']:<22}{r['grid']:<12}{1e3 * r['seconds']:>10.1f}{1e3 * r['min_s']:>9.1f}"
              f"{1e3 * r['max_s']:>9.1f}{1e3 * r['aim_s']:>8.0f}")
    for r in rows:
        print(json.dumps(r))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
