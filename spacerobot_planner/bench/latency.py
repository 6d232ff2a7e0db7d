"""
Latency of planner_node: message in → joint_trajectory out, in one process.

- ``latency_target``: a new ``target_pose`` (each repeat a new pose, so the C-space and
  the field are rebuilt) → the ``joint_trajectory`` message (aim < 150 ms at 36³);
- ``latency_joint_state``: a new ``joint_states`` + ``~/replan`` (C-space and field
  cached) → the ``joint_trajectory`` message (aim ≤ 5 ms median: issue 19's, :data:`JOINT_STATE_AIM_S`);
- ``latency_moving``: with the mock arm moving on the node's trajectory (the file's
  limits), a new target (1 cm away) → the ``joint_trajectory`` message; the table also
  gives how many replans were joined to the moving arm and the largest velocity step
  the mock arm recorded at a switch (between two joint_states, deg/s, less what the
  acceleration limits allow in that time);
- ``js_*``: where ``latency_joint_state`` goes (the session's stamps, ``session.Outcome.stamps``):
  ``js_to_planning`` (the joint state and the ``~/replan`` call through the executor, the
  session's queue, the start on the executing trajectory; in two: ``js_to_request``, up to the
  session's request from the service callback, the bench's own wait for the node to hold the
  joint state included (woken by the session's ``joint_state``, :class:`_Held`), and
  ``js_request_to_planning``, the session's worker thread woken and the start decided),
  ``js_plan_round_trip`` (the job to
  its backend and its outcome back: a replan the node's worker thread plans itself, the default's
  (``worker.HybridBackend``), or the round trip to the planning process; ``js_plan_in_process``:
  the plan itself, its ``timings_s`` (the total less the chain, which the session counts as its
  trajectory stage); through the planning process, in three: ``js_job_to_process``, until the process
  has the job, ``js_job_in_process``, until its outcome is ready (the plan and the job around
  it), and ``js_answer_to_node``, until the node has the outcome), ``js_chain``
  (``adapters.post_process``), ``js_record_and_send`` (the record, the stamp, the messages, the
  trajectories published), ``js_sent_to_arrival`` (the driver's
  subscriber has its bytes: the visuals and the log line that follow in the worker thread hold the
  interpreter meanwhile), and ``js_after_sent`` (the publish hook's rest: the visuals);
- ``subscriber_deserialize``: what a Python subscriber then spends turning the bytes into a
  ``JointTrajectory`` (rclpy's message objects: about 0.6 ms for 100 points).  A trajectory
  "arrives" when its subscriber has the bytes (a raw subscription): a controller in C++ has
  its message microseconds later, and this conversion is no part of the planner's latency;
- ``message``: the chain after the path (``adapters.post_process``: time parameterisation,
  resample + certify, split) and the published messages for the last plan, and the
  messages of the dense trajectory for comparison;
- ``stamp_margin``: for every trajectory received in the run, its stamp minus its arrival
  (ROS time) and its stamp + duration minus its arrival: min, p10 and median, so the worst
  case of the node's ``trajectory.start_lead_s`` is measured (both must stay positive: a
  controller refuses a trajectory that ends before it arrives, and one arriving after its
  start begins with a velocity step);
- ``--load N`` runs N busy-loop processes meanwhile (a loaded machine);
- ``--replans-in-process``: every plan through the planning process (``planner.replans_in_node``
  false), the baseline of the default's replans in the worker thread; ``--in-process``: every plan
  in the worker thread (``planner.separate_process`` false);
- ``--pause-s S``: the pause after each joint-state replan's trajectory before the next joint
  state (default :data:`PAUSE_S`, the aim's: after it the machine has gone idle and runs slow for
  a while; shorter: a stream of replans at sensor rate).  Every row says it (``pause_s``).

The node is built as ``main()`` builds it (``freeze_start_up``: its start-up frozen out of the
garbage collector's reach once configured), so a full collection of this process's some 10⁵
start-up objects does not hold a trajectory back as it would not under ``ros2 run``.

Median, p90 and max of ``--repeats`` after one warm-up plan.  Prints a table and one JSON
object per line.  ``python -m spacerobot_planner.bench latency [--cells 36] [--repeats 7] [--load N]``
"""

from __future__ import annotations

import argparse
import json
import threading
import time
from pathlib import Path

import numpy as np

from .timing import busy_processes, load_phrase, tail_stats

_PARAMS = Path(__file__).resolve().parent.parent.parent / "config" / "paper_3dof.yaml"
#: The aim of ``latency_joint_state``'s median, s (issue 19; ``bench aims`` reads it here).
JOINT_STATE_AIM_S = 0.005
#: the default pause after each joint-state replan's trajectory, s (the aim's figures)
PAUSE_S = 0.05


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.strip().splitlines()[0])
    ap.add_argument("--params-file", default=str(_PARAMS))
    ap.add_argument("--cells", type=int, default=36)
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--in-process", action="store_true",
                    help="plan in the worker thread instead of the child process (planner.separate_process false)")
    ap.add_argument("--replans-in-process", action="store_true",
                    help="plan the cached replans in the child process too (planner.replans_in_node false)")
    ap.add_argument("--no-moving", action="store_true", help="skip the latency_moving stage (mock arm)")
    ap.add_argument("--load", type=int, default=0, metavar="N", help="run N busy-loop processes meanwhile")
    ap.add_argument("--pause-s", type=float, default=PAUSE_S, metavar="S",
                    help=f"pause after each joint-state replan's trajectory, s (default {PAUSE_S:g}, the aim's)")
    args = ap.parse_args(argv)
    if not (args.pause_s >= 0.0 and np.isfinite(args.pause_s)):
        ap.error(f"--pause-s: expected a finite number of seconds >= 0, got {args.pause_s}")
    with busy_processes(args.load):
        return _run(args)


def _run(args) -> int:
    margins = []                    # (stamp - arrival, stamp + duration - arrival) of every trajectory, s

    import os
    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    import rclpy
    from geometry_msgs.msg import PoseStamped
    from rclpy.context import Context
    from sensor_msgs.msg import JointState
    from std_srvs.srv import Trigger
    from trajectory_msgs.msg import JointTrajectory

    from ..config import load_params_file, scenario_from_params
    from ..ros.executor import NodeExecutor
    from ..ros.planner_node import PlannerNode, params_to_overrides
    from ..ros.conversions import joint_state_msg

    flat = load_params_file(args.params_file)
    flat["grid.cells"] = [args.cells] * len(flat.get("robot.planned_joints", [0, 0, 0]))
    flat["planner.separate_process"] = not args.in_process
    flat["planner.replans_in_node"] = not args.replans_in_process
    sc = scenario_from_params(flat)
    robot = sc.robot
    ctx = Context()
    rclpy.init(context=ctx)
    # as ``ros2 run`` starts it (main()): what start-up made frozen out of the garbage collector's
    # reach (a full collection of this process walks some 10^5 objects: 60-110 ms, once in ~20 replans)
    node = PlannerNode(context=ctx, parameter_overrides=params_to_overrides(flat), freeze_start_up=True)
    # the driver shares the node's executor (as planner_node.main's has only the node): no parameter
    # services and no rosout, the fewest entities a driver needs in the executor's wait set
    drv = rclpy.create_node("latency_driver", context=ctx, start_parameter_services=False, enable_rosout=False)
    ex = NodeExecutor(context=ctx)     # as planner_node.main
    ex.add_node(node)
    ex.add_node(drv)
    got = _Arrivals(node, drv, margins)
    drv.create_subscription(JointTrajectory, "joint_trajectory", got, 10, raw=True)
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
        got.wait(1)
        lat_t = []
        for i in range(1, args.repeats + 1):
            n = len(got)
            t0 = time.perf_counter()
            pub_t.publish(target(i))
            lat_t.append(got.wait(n + 1) - t0)
            time.sleep(0.05)
        lat_j, parts = [], []
        rng = np.random.default_rng(0)
        held = _Held(node.session)
        for i in range(args.repeats):
            q = q_full.copy()
            q[list(robot.planned_joints)] += np.radians(rng.uniform(-1.0, 1.0, robot.dof))
            n = len(got)
            held.clear()
            t0 = time.perf_counter()
            pub_js.publish(joint_state_msg(robot.joint_names, q))
            held.wait_for(q[list(robot.planned_joints)])
            cli.call_async(Trigger.Request())
            arrival = got.wait(n + 1, ended=lambda: _sent_nothing(node, t0))
            if arrival is not None:          # else the replan sent nothing (e.g. at the goal): skipped
                lat_j.append(arrival - t0)
                parts.append(_parts(node, t0, arrival))
            time.sleep(args.pause_s)
        cached = node.last_result.cached
        grid = sc.grid.label()
        msg_s = _message_times(node, args.repeats)
        stages = [("latency_target", lat_t, 0.150), ("latency_joint_state", lat_j, JOINT_STATE_AIM_S),
                  ("subscriber_deserialize", got.deserialize_s, None),
                  ("message_published", msg_s[0], None), ("message_dense", msg_s[1], None)]
        parts = [p for p in parts if p is not None]
        stages[2:2] = [(name, [p[name] for p in parts if name in p], None) for name in _PARTS
                       if any(name in p for p in parts)]
        for stage, vals, aim in stages:
            rows.append({"stage": stage, "grid": grid, **_stats(vals), "aim_s": aim, "pause_s": args.pause_s,
                         "backend": _backend(args),
                         **({"cached": list(cached)} if stage == "latency_joint_state" else {})})
    finally:
        node.shutdown_worker()
        ex.shutdown()
        spin.join(5.0)
        node.destroy_node()
        drv.destroy_node()
        rclpy.shutdown(context=ctx)
    if not args.no_moving:
        rows.append(_moving(args, flat, margins))
    rows.append(_margin_row(margins, sc.grid.label(), args))
    print(f"bench latency: joint-state replans {1e3 * args.pause_s:g} ms after the last trajectory"
          + (" (the aim's pause)" if args.pause_s == PAUSE_S else "")
          + (f"; {load_phrase(args.load)}" if args.load else ""))
    print(f"{'stage':<24}{'grid':<12}{'median ms':>10}{'p90 ms':>9}{'max ms':>9}{'aim ms':>8}")
    for r in rows:
        if "seconds" not in r:
            continue
        aim = "" if r["aim_s"] is None else f"{1e3 * r['aim_s']:.0f}"
        print(f"{r['stage']:<24}{r['grid']:<12}{1e3 * r['seconds']:>10.1f}{1e3 * r['p90_s']:>9.1f}"
              f"{1e3 * r['max_s']:>9.1f}{aim:>8}")
    for r in rows:
        if r["stage"] == "stamp_margin":
            print(f"stamp_margin over {r['trajectories']} trajectories (load {args.load}): stamp - arrival min "
                  f"{1e3 * r['start_min_s']:.1f} ms, p10 {1e3 * r['start_p10_s']:.1f}, median "
                  f"{1e3 * r['start_median_s']:.1f}; stamp + duration - arrival min {1e3 * r['end_min_s']:.1f} ms, "
                  f"p10 {1e3 * r['end_p10_s']:.1f}, median {1e3 * r['end_median_s']:.1f}")
        if "joined" in r:
            print(f"latency_moving: {r['joined']} of {r['repeats']} replans joined to the moving arm; "
                  f"largest velocity step at a switch {r['velocity_step_deg_s']:.3f}°/s beyond the "
                  f"acceleration limits (arm at up to {r['arm_speed_deg_s']:.2f}°/s)")
    for r in rows:
        print(json.dumps(r))
    return 0


class _Held:
    """
    Wakes the bench the moment the node's session takes a joint state (its ``joint_state`` wrapped).

    ``latency_joint_state`` calls ``~/replan`` once the node holds the new state (the two travel
    on different DDS entities, so the call could overtake it); waiting for that by polling every
    0.5 ms added the poll's own delay, about 0.3 ms on average, to ``js_to_request``.
    """

    def __init__(self, session):
        self._session = session
        self._event = threading.Event()
        take = session.joint_state

        def joint_state(q_rad, stamp_ns):
            take(q_rad, stamp_ns)
            self._event.set()
        session.joint_state = joint_state

    def clear(self) -> None:
        self._event.clear()

    def wait_for(self, q_rad, timeout_s: float = 10.0) -> None:
        """Return once the session holds ``q_rad`` (planned joints), or after ``timeout_s``."""
        t_end = time.monotonic() + timeout_s
        while time.monotonic() < t_end:
            q = self._session.joint_q
            if q is not None and np.allclose(q, q_rad):
                return
            self._event.wait(0.05)
            self._event.clear()


class _Arrivals:
    """
    A joint_trajectory subscriber's callback: arrival times (perf_counter, s).

    Given a message, or its bytes (a raw subscription: the arrival is taken before rclpy turns
    them into a message, which ``deserialize_s`` times).  With ``margins`` (a list) also each
    message's (stamp - arrival, stamp + duration - arrival) in ROS time (``clock_node``'s
    clock), s.
    """

    def __init__(self, node, clock_node=None, margins=None):
        self.node = node
        self.clock_node, self.margins = clock_node, margins
        self.times = []
        self.deserialize_s = []
        self.cond = threading.Condition()

    def __call__(self, msg):
        arrival = time.perf_counter()
        now_s = None if self.margins is None else 1e-9 * self.clock_node.get_clock().now().nanoseconds
        if isinstance(msg, bytes):
            from rclpy.serialization import deserialize_message
            from trajectory_msgs.msg import JointTrajectory
            t0 = time.perf_counter()
            msg = deserialize_message(msg, JointTrajectory)
            self.deserialize_s.append(time.perf_counter() - t0)
        if self.margins is not None and msg.points:
            stamp_s = msg.header.stamp.sec + 1e-9 * msg.header.stamp.nanosec
            end = msg.points[-1].time_from_start
            self.margins.append((stamp_s - now_s, stamp_s + end.sec + 1e-9 * end.nanosec - now_s))
        with self.cond:
            self.times.append(arrival)
            self.cond.notify_all()

    def __len__(self):
        with self.cond:
            return len(self.times)

    def wait(self, n, timeout=120.0, ended=None) -> float | None:
        """
        Return the arrival time of the n-th trajectory (waits for it).

        None when ``ended()`` (polled every 10 ms) says none is coming.
        """
        end = time.monotonic() + timeout
        with self.cond:
            while len(self.times) < n:
                if ended is not None and ended():
                    return None
                left = end - time.monotonic()
                if left <= 0.0:
                    raise RuntimeError(f"no trajectory within {timeout} s (state {self.node.state})")
                self.cond.wait(min(left, 0.01 if ended is not None else left))
            return self.times[n - 1]


def _sent_nothing(node, t0: float) -> bool:
    """Tell whether a plan begun after ``t0`` (perf_counter s) ended ok without sending a trajectory (at the goal)."""
    out = node.last_outcome
    st = {} if out is None else out.stamps
    return out is not None and out.ok and st.get("planning", 0.0) >= t0 and "published" in st and "sent" not in st


def _margin_row(margins, grid, args) -> dict:
    """Return the stamp_margin row: min, p10, median of stamp - arrival and of stamp + duration - arrival, s."""
    m = np.asarray(margins, dtype=float).reshape(-1, 2)
    out = {"stage": "stamp_margin", "grid": grid, "trajectories": int(len(m)), "load": args.load,
           "backend": _backend(args)}
    for k, name in enumerate(("start", "end")):
        v = m[:, k] if len(m) else np.array([np.nan])
        out.update({f"{name}_min_s": float(v.min()), f"{name}_p10_s": float(np.percentile(v, 10)),
                    f"{name}_median_s": float(np.median(v))})
    return out


def _backend(args) -> str:
    """Return where the bench's node plans: "thread", "process" (every plan), "hybrid" (replans in the thread)."""
    return "thread" if args.in_process else "process" if args.replans_in_process else "hybrid"


def _stats(vals) -> dict:
    return tail_stats(vals, median_key="seconds", count_key="repeats")


#: the parts of latency_joint_state (see the module docstring), in order
_PARTS = ("js_to_planning", "js_to_request", "js_request_to_planning",
          "js_plan_round_trip", "js_job_to_process", "js_job_in_process", "js_answer_to_node",
          "js_plan_in_process", "js_chain", "js_record_and_send", "js_sent_to_arrival", "js_after_sent")


def _parts(node, t0: float, arrival: float, timeout_s: float = 5.0) -> dict | None:
    """
    Return the parts of one joint state → trajectory (s, see :data:`_PARTS`), or None.

    From the last outcome's stamps (``session.Outcome.stamps``, perf_counter s) once its
    publish hook returned; ``t0``: the joint state published, ``arrival``: the trajectory received.
    """
    end = time.perf_counter() + timeout_s
    while True:
        out = node.last_outcome
        st = {} if out is None else out.stamps
        if out is not None and out.ok and "published" in st and st.get("planning", 0.0) >= t0:
            if "sent" not in st:    # nothing sent (already at the goal): no trajectory to split
                return None
            break
        if time.perf_counter() > end:
            return None
        time.sleep(0.001)
    got = {"js_to_planning": st["planning"] - t0, "js_to_request": st["request"] - t0,
           "js_request_to_planning": st["planning"] - st["request"],
           "js_plan_round_trip": st["received"] - st["planning"],
           # the result's total holds the chain (the node's trajectory stage): the plan alone without it
           "js_plan_in_process": float(out.result.timings_s["total"]) - (st["chain"] - st["received"]),
           "js_chain": st["chain"] - st["received"],
           "js_record_and_send": st["sent"] - st["chain"], "js_sent_to_arrival": arrival - st["sent"],
           "js_after_sent": st["published"] - st["sent"]}
    if "process_received" in st and "process_answered" in st:      # the planning process's own stamps
        got.update(js_job_to_process=st["process_received"] - st["planning"],
                   js_job_in_process=st["process_answered"] - st["process_received"],
                   js_answer_to_node=st["received"] - st["process_answered"])
    return got


def _message_times(node, repeats):
    """
    Time the chain after the path and the messages for the node's last plan.

    (seconds of ``adapters.post_process`` + the published messages, seconds to build the dense
    trajectory's messages), ``repeats`` each.
    """
    from ..adapters import post_process, split_parts
    from ..ros import conversions as conv
    sc = node.param_handler.scenario
    sc = sc.with_scene(sc.scene.with_target(node.session.target))
    path = node.last_result.path_rad
    motions = node.session.motions(sc.scene)
    pub, full = [], []
    for _ in range(repeats):
        t0 = time.perf_counter()
        p = post_process(sc, path, motions=motions)
        [conv.trajectory_to_msg(part) for part in (p.arm, p.attitude) if part is not None]
        pub.append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        [conv.trajectory_to_msg(part) for part in split_parts(p.dense, sc.robot.joint_names[0]) if part is not None]
        full.append(time.perf_counter() - t0)
    return pub, full


def _moving(args, flat, margins) -> dict:
    """Measure the latency_moving row: planner + mock arm; the arm moving, new targets."""
    import rclpy
    from geometry_msgs.msg import PoseStamped
    from rclpy.context import Context
    from sensor_msgs.msg import JointState
    from trajectory_msgs.msg import JointTrajectory

    from ..config import scenario_from_params
    from ..ros.executor import NodeExecutor
    from ..ros.mock_arm_node import MockArmNode
    from ..ros.parameters import MOCK_ARM_PARAMETERS
    from ..ros.planner_node import PlannerNode, params_to_overrides

    sc = scenario_from_params(flat)
    ctx = Context()
    rclpy.init(context=ctx)
    node = PlannerNode(context=ctx, parameter_overrides=params_to_overrides(flat), freeze_start_up=True)
    # the planned joints' limits, as the node holds them (the file's, or the defaults where it has none)
    amax = node.param_handler.scenario.joint_limits.planned(sc.robot)[1]
    arm = MockArmNode(context=ctx, parameter_overrides=params_to_overrides(flat, MOCK_ARM_PARAMETERS))
    drv = rclpy.create_node("latency_moving_driver", context=ctx, start_parameter_services=False, enable_rosout=False)
    ex = NodeExecutor(context=ctx)
    for n in (node, arm, drv):
        ex.add_node(n)
    got, states = _Arrivals(node, drv, margins), []
    drv.create_subscription(JointTrajectory, "joint_trajectory", got, 10, raw=True)
    drv.create_subscription(JointState, "joint_states", states.append, 100)
    pub_t = drv.create_publisher(PoseStamped, "target_pose", 10)
    spin = threading.Thread(target=ex.spin, daemon=True)
    spin.start()

    def target(dx):
        m = PoseStamped()
        m.header.frame_id = sc.planning_frame
        m.pose.position.x, m.pose.position.y = -3.27 + dx, -2.60
        m.pose.orientation.w = 1.0
        return m

    lat, joined = [], 0
    try:
        while pub_t.get_subscription_count() == 0:
            time.sleep(0.02)
        pub_t.publish(target(0.0))
        got.wait(1)
        time.sleep(2.0)                          # the arm under way
        for i in range(args.repeats):
            n = len(got)
            t0 = time.perf_counter()
            pub_t.publish(target(0.01 * ((i % 2) + 1)))
            lat.append(got.wait(n + 1) - t0)
            time.sleep(0.05)
            if str(node.last_outcome.values.get("joined_moving_arm", "no")).startswith("yes"):
                joined += 1
            time.sleep(1.2)                      # the switch happens, the arm goes on
        msgs = [m for m in states if len(m.velocity) == len(m.name)]
    finally:
        node.shutdown_worker()
        ex.shutdown()
        spin.join(5.0)
        for n in (node, arm, drv):
            n.destroy_node()
        rclpy.shutdown(context=ctx)
    idx = [list(msgs[0].name).index(j) for j in sc.robot.planned_names]
    t = np.array([m.header.stamp.sec + 1e-9 * m.header.stamp.nanosec for m in msgs])
    v = np.array([[m.velocity[i] for i in idx] for m in msgs])
    dt = np.diff(t)
    step = np.abs(np.diff(v, axis=0)) - amax[None, :] * dt[:, None]
    return {"stage": "latency_moving", "grid": sc.grid.label(), **_stats(lat), "aim_s": None,
            "joined": joined, "velocity_step_deg_s": float(np.degrees(max(0.0, step.max()))),
            "arm_speed_deg_s": float(np.degrees(np.abs(v).max())),
            "backend": _backend(args)}


if __name__ == "__main__":
    raise SystemExit(main())
