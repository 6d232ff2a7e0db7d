"""
Shared helpers of the in-process node tests (test_node*.py, test_reliability_node.py, test_action.py, ...).

The ``graph`` fixture (conftest.py) makes them.  Each graph gets a private rclpy Context
and a NodeExecutor (what planner_node's main uses) spinning in a thread; no
launch_testing.

Rules these tests keep, each learnt from a failure on a loaded machine (CI runs three workers
on two cores):

- wait for the thing judged, in the channel it comes on: a message on /diagnostics is waited
  for by its content (a status still set is published again every period), not read right
  after a node's attribute changed;
- a node's log lines are read from /rosout (:meth:`Graph.log_text`, :meth:`Graph.wait_log`),
  never by polling pytest's ``capfd``: its ``readouterr()`` reads, then truncates the captured
  file, and a line another thread writes in between is lost;
- a state on a topic the planner hears best effort is sent until taken
  (:meth:`Graph.send_joint_state`, :meth:`Graph.publish_until`), and counts allow a copy taken twice;
- a "long" plan is long by injection (``planner.test_stall_s``), long enough that what must
  happen during it does on a slow machine; bounds are for hangs (tens of seconds), not speed.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import re
import threading
import time

import numpy as np
import rclpy
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from geometry_msgs.msg import PoseStamped
from rcl_interfaces.msg import Log
from rclpy.context import Context
from rclpy.qos import QoSProfile, qos_profile_rosout_default
from sensor_msgs.msg import JointState
from trajectory_msgs.msg import JointTrajectory
from visualization_msgs.msg import MarkerArray

import spacerobot_planner
from spacerobot_planner.collision import CollisionChecker
from spacerobot_planner.config import load_params_file, scenario_from_params
from spacerobot_planner.ros.executor import NodeExecutor
from spacerobot_planner.ros.mock_arm_node import MockArmNode
from spacerobot_planner.ros.parameters import MOCK_ARM_PARAMETERS
from spacerobot_planner.ros.planner_node import GRID_QOS, PlannerNode, params_to_overrides
from spacerobot_planner.worker import HybridBackend, ProcessBackend, make_backend

from planning_zygote import PlanningZygote

#: the log line of a plan ended by a shutdown: the session stops it ("the plan in progress is
#: cancelled"), or the deactivation that a shutdown from active starts with cancels it first
PLAN_CANCELLED_AT_SHUTDOWN = re.compile(r"shutdown: the plan in progress is cancelled"
                                        r"|plan #\d+ cancelled: the node is shutting down")
#: The node's promises about time (a cancel within 0.5 s, a shutdown within 1 s) are measured by
#: ``python -m spacerobot_planner.bench promptness``; a test checks only that the work ends far
#: sooner than the injected stall (30 s) would, a bound a loaded machine keeps.
PROMPT_BOUND_S = 10.0
#: s for a fresh planner_node process to come up (generous: a loaded 2-core machine imports rclpy and numba slowly)
START_TIMEOUT_S = 120.0
#: the graph's /rosout subscription: the nodes' own profile (reliable, transient local), a deeper queue (a flood's
#: lines while the graph's one executor thread is busy)
ROSOUT_QOS = QoSProfile(depth=10_000, reliability=qos_profile_rosout_default.reliability,
                        durability=qos_profile_rosout_default.durability)
#: rcl_interfaces/Log levels as rcutils' console lines name them
_LEVELS = {Log.DEBUG: "DEBUG", Log.INFO: "INFO", Log.WARN: "WARN", Log.ERROR: "ERROR", Log.FATAL: "FATAL"}
# s between a test's sends of one state on a topic the planner hears best effort (Graph.publish_until)
RESEND_S = 0.25
FAST = {"trajectory.max_velocity_deg_s": [90.0, 180.0, 180.0],
        "trajectory.max_acceleration_deg_s2": [360.0, 720.0, 720.0]}
_CONFIG = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "config")
SCENES = {"2dof": (os.path.join(_CONFIG, "paper_2dof.yaml"), [180, 180]),
          "3dof": (os.path.join(_CONFIG, "paper_3dof.yaml"), [36, 36, 36]),
          "servicer": (os.path.join(_CONFIG, "servicer_3dof.yaml"), [36, 36, 36]),
          "servicer4": (os.path.join(_CONFIG, "servicer_4joint.yaml"), [16, 16, 16, 16])}


class ZygoteBackend(ProcessBackend):
    """The node's ``worker.ProcessBackend``, its planning processes forked warm by this test process's zygote."""

    def start_process(self, fd: int):
        return ZYGOTE.fork(fd)


class ZygoteHybridBackend(HybridBackend):
    """The node's default ``worker.HybridBackend``, its planning processes forked warm by this test process's zygote."""

    start_process = ZygoteBackend.start_process


def planning_backend(scenario, separate_process, log=None, info=None, replans_here=True, **kw):
    """Make the node's own backend (a PlannerNode ``backend_factory``), its planning processes forked by the zygote."""
    if not separate_process:
        return make_backend(scenario, False, log=log, info=info, **kw)
    return (ZygoteHybridBackend if replans_here else ZygoteBackend)(scenario, log=log, info=info, **kw)


#: this test process's zygote (planning_zygote.py): every Graph's planning process is forked there
ZYGOTE = PlanningZygote(os.path.dirname(os.path.dirname(os.path.abspath(spacerobot_planner.__file__))), _CONFIG)


def scene_params(name, cells=None, **extra):
    """
    Return the scene's parameter file with fast limits, ``cells`` and ``extra``.

    ``extra`` takes dotted names: pass them as ``**{"planner.separate_process": False}``.
    """
    path, default_cells = SCENES[name]
    flat = load_params_file(path)
    n = len(flat["robot.joint_names"])
    flat.update({k: v[:1] + v[1:2] * (n - 1) for k, v in FAST.items()})    # the attitude's, then the arm's
    flat["grid.cells"] = list(cells or default_cells)
    flat.update(extra)
    return flat


class Graph:
    """
    A private context with the planner, the mock arm (optional) and a driver node.

    The driver publishes inputs and records every output (with its arrival time).
    """

    def __init__(self, flat, with_arm=True, wait_subscribed=True):
        if not with_arm:
            # nothing follows the trajectories: a replan starts at the published joint state.
            # (The node cannot tell a still arm from one that follows a trajectory that has just
            # begun; it would join that trajectory, as for an arm following it.)
            flat = {"replan.horizon_s": 0.0, **flat}
        self.ctx = Context()
        rclpy.init(context=self.ctx)
        self.flat = flat
        self.scenario = scenario_from_params(flat)
        self.planner = PlannerNode(context=self.ctx, parameter_overrides=params_to_overrides(flat),
                                   backend_factory=planning_backend)
        self.planner_destroyed = False
        self.arm = None
        self.ex = NodeExecutor(context=self.ctx)     # as planner_node.main
        self.ex.add_node(self.planner)
        if with_arm:
            self.arm = MockArmNode(context=self.ctx,
                                   parameter_overrides=params_to_overrides(flat, MOCK_ARM_PARAMETERS))
            self.ex.add_node(self.arm)
        self.drv = rclpy.create_node("test_driver", context=self.ctx)
        self.ex.add_node(self.drv)
        self.lock = threading.Lock()
        self.trajs, self.states, self.diags, self.markers = [], [], [], []
        self.att_trajs = []
        self.logs = []            # (arrival time, rcl_interfaces Log) of every line on /rosout (log_text, wait_log)
        self.checked = []         # (topic, msg, ROS time received, latest joint_states positions by name)
        # violations a test expects (and says why); every other one fails the test at close()
        self.known_violations = set()
        self.drv.create_subscription(JointTrajectory, "joint_trajectory",
                                     self._rec_traj(self.trajs, "joint_trajectory"), 10)
        self.drv.create_subscription(JointTrajectory, "attitude_trajectory",
                                     self._rec_traj(self.att_trajs, "attitude_trajectory"), 10)
        self.drv.create_subscription(JointState, "joint_states", self._rec(self.states), 100)
        self.drv.create_subscription(DiagnosticArray, "/diagnostics", self._rec(self.diags), 50)
        # every node's log lines, as ``ros2 topic echo /rosout`` or rqt_console has them: reliable, and the
        # lines from before this subscription matched come too (transient local, kept 10 s).  Not pytest's
        # capfd while nodes log: its readouterr() reads, then truncates the captured file, and a line written
        # by another thread in between is lost (a CI run polled it and never saw a warning the node logged)
        self.drv.create_subscription(Log, "/rosout", self._rec(self.logs), ROSOUT_QOS)
        self.drv.create_subscription(MarkerArray, "planned_path_markers", self._rec(self.markers), GRID_QOS)
        self.pub_target = self.drv.create_publisher(PoseStamped, "target_pose", 10)
        self.pub_js = self.drv.create_publisher(JointState, "joint_states", 10)
        self.pub_goal = self.drv.create_publisher(JointState, "goal_joint_state", 10)
        self._action_client = None
        self.client_node = None               # the action client's node (action_client())
        self.spin_error = None                # what ended the spin thread, if anything did
        self._stop_spin = threading.Event()
        self.thread = threading.Thread(target=self._spin, daemon=True)
        self.thread.start()
        if wait_subscribed:
            self.wait_connected()

    def nodes(self):
        return [n for n in (None if self.planner_destroyed else self.planner, self.arm, self.drv) if n is not None]

    def unmatched(self):
        """
        List the endpoints of the graph's nodes not yet matched with all their peers in the graph.

        A publisher's matched-subscription count (and a subscription's matched-publisher count) is
        DDS's own: a message sent before its endpoints match is lost (volatile QoS), which is what
        a test that publishes or subscribes "at once" would otherwise race.
        """
        pubs = [p for n in self.nodes() for p in n.publishers]
        subs = [s for n in self.nodes() for s in n.subscriptions]
        out = []
        for p in pubs:
            want = sum(s.topic_name == p.topic_name for s in subs)
            if p.get_subscription_count() < want:
                out.append(f"publisher {p.topic_name} {p.get_subscription_count()}/{want}")
        for s in subs:
            want = sum(p.topic_name == s.topic_name for p in pubs)
            if s.get_publisher_count() < want:
                out.append(f"subscription {s.topic_name} {s.get_publisher_count()}/{want}")
        return out

    def wait_connected(self, timeout=60):
        """Wait until every publisher and subscription in the graph has matched its peers (DDS discovery)."""
        self.wait(lambda: not self.unmatched(), timeout, lambda: f"the graph connected: {self.unmatched()}")

    def _spin(self):
        # not ex.spin(): Executor.shutdown() from another thread destroys its guard
        # conditions while spin may still use them (InvalidHandle in this thread); so the
        # loop stops and is joined first, and close() shuts the executor down afterwards
        ctx = self.ctx
        try:
            while not self._stop_spin.is_set() and ctx.ok():
                self.ex.spin_once(timeout_sec=0.05)
        except BaseException as e:       # kept for wait(), which fails at once; then raised as before
            self.spin_error = e
            raise

    def stop_spinning(self):
        self._stop_spin.set()
        self.thread.join(5)

    def _rec_traj(self, store, topic):
        def cb(msg, info):
            # when DDS received it (what a controller's subscription sees; this executor may run later)
            now = info["received_timestamp"] * 1e-9 or self.drv.get_clock().now().nanoseconds * 1e-9
            with self.lock:
                store.append((time.monotonic(), msg))
                last = self.states[-1][1] if self.states else None
                self.checked.append((topic, msg, now, None if last is None else dict(zip(last.name, last.position))))
        return cb

    def state_at(self, names, ros_s):
        """
        Return the recorded joint_states positions of ``names`` at ROS time ``ros_s``.

        Interpolated between the two stamped messages around it: cubic (Hermite) from their
        positions and velocities when both have velocities (exact for a constant acceleration,
        so a gap in the record under load costs little), else linear; None when the record
        does not bracket it.
        """
        with self.lock:
            msgs = [m for _, m in self.states if m.header.stamp.sec or m.header.stamp.nanosec]
        ts = np.array([m.header.stamp.sec + 1e-9 * m.header.stamp.nanosec for m in msgs])
        if len(ts) < 2 or not ts[0] <= ros_s <= ts[-1] or any(n not in msgs[0].name for n in names):
            return None
        k = min(int(np.searchsorted(ts, ros_s, side="right")) - 1, len(ts) - 2)
        a, b = msgs[k], msgs[k + 1]
        qa = np.array([a.position[list(a.name).index(n)] for n in names])
        qb = np.array([b.position[list(b.name).index(n)] for n in names])
        dt = ts[k + 1] - ts[k]
        f = 0.0 if dt == 0.0 else (ros_s - ts[k]) / dt
        if len(a.velocity) != len(a.name) or len(b.velocity) != len(b.name):
            return qa + f * (qb - qa)
        va = np.array([a.velocity[list(a.name).index(n)] for n in names])
        vb = np.array([b.velocity[list(b.name).index(n)] for n in names])
        h00, h10 = 2 * f ** 3 - 3 * f ** 2 + 1, f ** 3 - 2 * f ** 2 + f
        h01, h11 = -2 * f ** 3 + 3 * f ** 2, f ** 3 - f ** 2
        return h00 * qa + h10 * dt * va + h01 * qb + h11 * dt * vb

    def controller_violations(self, current_tol_rad=np.radians(1.0)):
        """
        List the trajectories joint_trajectory_controller would refuse.

        [(topic, index, violations)] for every trajectory received (see
        controller_rule_violations).  "The current state" of a first point at time 0 is the
        mock arm's state just before the trajectory's stamp (its own motion, exact), without an
        arm the recorded joint_states interpolated at the stamp (at its arrival for a zero
        stamp, or when the record does not reach the stamp).  A trajectory that a newer one on its
        topic drops while it waits for its stamp (one that arrives before it and starts no later:
        the mock arm's and joint_trajectory_controller's replacement) never starts: it is not
        judged against the state at its stamp (a flood test's plan from the executing trajectory's
        end, replaced 0.4 s later by a join that started before that end).
        """
        known = set(self.scenario.robot.joint_names)
        out = []
        with self.lock:
            got = list(self.checked)
        at_arrival = self.arm is not None and self.arm.switch_at_arrival

        def switch_s(msg, now):
            stamp_s = msg.header.stamp.sec + 1e-9 * msg.header.stamp.nanosec
            return now if at_arrival or not stamp_s else max(stamp_s, now)
        dropped = {i for i, (topic, msg, now, _) in enumerate(got)
                   if any(t2 == topic and now2 < switch_s(msg, now) and switch_s(m2, now2) <= switch_s(msg, now)
                          for t2, m2, now2, _ in got[i + 1:])}
        for i, (topic, msg, now, state) in enumerate(got):
            current = None
            if msg.points and i in dropped:
                current = list(msg.points[0].positions)          # never starts: no current state to meet
            elif msg.points:
                names, first = list(msg.joint_names), list(msg.points[0].positions)
                stamp_s = msg.header.stamp.sec + 1e-9 * msg.header.stamp.nanosec
                q = None
                if stamp_s and self.arm is not None and all(n in self.arm.names for n in names):
                    # the mock arm's own motion just before the stamp (exact, also in a gap of its
                    # joint_states under load; at the stamp itself this trajectory takes over)
                    stamp_ns = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
                    q_arm = self.arm.history_state_at(stamp_ns - 1)[0]
                    q = [q_arm[self.arm.names.index(n)] for n in names]
                elif stamp_s:
                    q = self.state_at(names, stamp_s)
                if q is None and state is not None and all(n in state for n in names):
                    q = [state[n] for n in names]
                if q is not None and len(first) == len(q) and all(
                        abs(a - b) <= current_tol_rad for a, b in zip(first, q)):
                    current = first          # the trajectory starts at (about) the arm's state
            bad = [v for v in controller_rule_violations(msg, known, now, current)
                   if v not in self.known_violations]
            if bad:
                out.append((topic, i, bad))
        return out

    def _rec(self, store):
        def cb(msg):
            with self.lock:
                store.append((time.monotonic(), msg))
        return cb

    def wait(self, cond, timeout, what):
        """
        Poll ``cond`` until true; AssertionError after ``timeout`` s (``what``: a text, or a callable giving one).

        At once when the graph's spin thread has died (nothing would be delivered any more).
        """
        t0 = time.monotonic()
        while not cond():
            if self.spin_error is not None:
                raise AssertionError(f"the graph's executor stopped spinning ({self.spin_error!r}) while "
                                     f"waiting for: {what() if callable(what) else what}")
            if time.monotonic() - t0 > timeout:
                raise AssertionError(f"timed out after {timeout} s waiting for: {what() if callable(what) else what}")
            time.sleep(0.01)

    def publish_until(self, pub, msg, cond, timeout, what):
        """
        Publish ``msg`` on ``pub`` until ``cond()`` holds, again every RESEND_S; AssertionError as ``wait``.

        For the topics the planner hears best effort (joint_states and the attitude topic, as a
        driver's sensor data): a message may be dropped (a reader's queue full, another process's
        participant), and a test that sent one and waited for what it causes would wait for
        nothing.  A driver sends its state at its rate; so does a test.  ``cond`` must say that the
        planner took this message (or refused it), not only that an earlier one arrived; a copy
        may be taken twice (sent again while the first was still on its way).
        """
        pub.publish(msg)
        sent = [time.monotonic()]

        def taken():
            if cond():
                return True
            if time.monotonic() - sent[0] >= RESEND_S:
                pub.publish(msg)
                sent[0] = time.monotonic()
            return False
        self.wait(taken, timeout, what)

    def send_joint_state(self, msg, cond=None, timeout=30, what=None):
        """
        Publish ``msg`` on joint_states until the planner took it (``publish_until``).

        ``cond`` defaults to: the planner's joint state is ``msg``'s planned joints' positions and
        no refusal came after it (every planned joint in ``msg``); give one for a state it refuses
        or completes otherwise.
        """
        if cond is None:
            names = list(msg.name)
            want = np.array([msg.position[names.index(n)] for n in self.scenario.robot.planned_names])

            def cond():
                session = self.planner.session
                q = session.joint_q
                return q is not None and session.joint_refused is None and np.array_equal(np.asarray(q), want)
        self.publish_until(self.pub_js, msg, cond, timeout,
                           what or f"the joint state {dict(zip(msg.name, np.round(np.degrees(msg.position), 3)))}° "
                                   f"taken by the planner")

    def log_count(self) -> int:
        """Return how many log lines were received so far (a ``since`` for :meth:`log_text`)."""
        with self.lock:
            return len(self.logs)

    def log_text(self, since=0, name="spacerobot_planner") -> str:
        """
        Return the log lines received on /rosout from the ``since``-th on, of node ``name`` (None: every node).

        One line each, as rcutils' console format has them: ``[WARN] [spacerobot_planner]: text``.
        """
        with self.lock:
            msgs = [m for _, m in self.logs[since:]]
        return "".join(f"[{_LEVELS.get(m.level, m.level)}] [{m.name}]: {m.msg}\n" for m in msgs
                       if name is None or m.name == name)

    def wait_log(self, fragment, timeout=30, since=0, name="spacerobot_planner"):
        """Wait for a log line of ``name`` containing ``fragment`` (from the ``since``-th line on); return the text."""
        self.wait(lambda: fragment in self.log_text(since, name), timeout,
                  lambda: f"a log line with {fragment!r}; the lines:\n{self.log_text(since, name)[-3000:]}")
        return self.log_text(since, name)

    def send_target(self, x=-3.27, y=-2.60, yaw=0.0, frame="world", quat=None):
        m = PoseStamped()
        m.header.frame_id = frame
        m.pose.position.x, m.pose.position.y = float(x), float(y)
        q = quat or (0.0, 0.0, math.sin(yaw / 2), math.cos(yaw / 2))
        (m.pose.orientation.x, m.pose.orientation.y, m.pose.orientation.z, m.pose.orientation.w) = q
        self.pub_target.publish(m)

    def errors(self):
        """[(arrival time, message)] of every ERROR status received (planner or input)."""
        return [(t, st.message) for t, st in self.error_diags()]

    def error_diags(self):
        """[(arrival time, DiagnosticStatus)] of every ERROR status received."""
        with self.lock:
            return [(t, st) for t, d in self.diags for st in d.status if st.level == DiagnosticStatus.ERROR]

    def status(self, which, index=-1):
        """
        Return the ``which`` ("planner" or "input") DiagnosticStatus.

        Of the diagnostics message ``index`` (default: the latest).
        """
        with self.lock:
            if not self.diags:
                return None
            d = self.diags[index][1]
        return next(st for st in d.status if st.name.endswith(f": {which}"))

    def planner_values_for_goal(self, goal_rad, timeout=PROMPT_BOUND_S):
        """
        Return the key/values of the planner status that reported the plan to ``goal_rad`` (rad).

        The record is published before the trajectory, on another topic: it may arrive after it.
        """
        want = np.degrees(np.asarray(goal_rad, dtype=float))
        found = []

        def seen():
            with self.lock:
                diags = [d for _, d in self.diags]
            for d in reversed(diags):
                for st in d.status:
                    v = diag_values(st)
                    if st.name.endswith(": planner") and "goal_deg" in v and \
                            np.allclose(json.loads(v["goal_deg"]), want, atol=1e-2):
                        found.append(v)
                        return True
            return False
        self.wait(seen, timeout, f"the planner status of the plan to {np.round(want, 2).tolist()}°")
        return found[0]

    def level(self, which):
        """Return the latest level of the ``which`` status (None before any diagnostics)."""
        st = self.status(which)
        return None if st is None else st.level

    def all_ok(self):
        """Tell whether the latest diagnostics message has only OK statuses."""
        with self.lock:
            return bool(self.diags) and all(st.level == DiagnosticStatus.OK for st in self.diags[-1][1].status)

    # ---------------------------------------------------------------- action client
    def action_client(self):
        """
        Return the graph's plan_capture action client, made on first use, its server discovered.

        It lives on a node of its own that joins the spinning executor only once the client
        is built: rclpy's ActionClient registers with its node before it makes its lock, and
        an executor that meets it in between (from its own thread) raises AttributeError
        ("'ActionClient' object has no attribute '_lock'") and its spin thread ends; the goal
        response then never came (one fresh-clone run in three).
        """
        from rclpy.action import ActionClient
        from spacerobot_planner_interfaces.action import PlanCapture
        if self._action_client is None:
            self.client_node = rclpy.create_node("test_action_client", context=self.ctx)
            self._action_client = ActionClient(self.client_node, PlanCapture, "plan_capture")
            self.ex.add_node(self.client_node)
            self.wait(self._action_client.server_is_ready, 60, "the plan_capture action server discovered")
        return self._action_client

    def send_goal(self, goal, feedback=None):
        """Send a PlanCapture goal; returns the accepted ClientGoalHandle (asserts acceptance)."""
        fut = self.action_client().send_goal_async(goal, feedback_callback=feedback)
        self.wait(fut.done, 30, "the goal response")
        handle = fut.result()
        assert handle.accepted, "goal rejected"
        return handle

    def goal_result(self, handle, timeout=60):
        """(status, PlanCapture.Result, arrival monotonic time) of a goal."""
        fut = handle.get_result_async()
        got = {}
        fut.add_done_callback(lambda f: got.setdefault("t", time.monotonic()))
        self.wait(fut.done, timeout, "the goal result")
        r = fut.result()
        return r.status, r.result, got.get("t", time.monotonic())

    def n_trajs(self):
        with self.lock:
            return len(self.trajs)

    def destroy_planner(self):
        """
        Stop spinning and destroy the planner node (as a launch file's shutdown or planner_node's main do).

        Returns the seconds destroy_node took.

        Spinning stops first: destroying a node while an executor waits on its entities
        races in rclpy (InvalidHandle in the spinning thread).
        """
        self.stop_spinning()
        t0 = time.monotonic()
        self.planner.destroy_node()
        self.planner_destroyed = True
        return time.monotonic() - t0

    def _arm_past_the_stamps(self):
        """
        (spinning stopped) Advance the mock arm's motion past the latest stamp received, as its clock would.

        A test may end before a trajectory it was sent starts, or before one it waits behind does:
        the arm's record of its switches (``history_state_at``) holds only those made so far, and the
        controller check would judge a later trajectory against the arm as it was before them (a
        request answered while the first trajectory still waited its stamp: "not the current state").
        The arm starts the trajectories due by then in order of their switch times, as its ticks would.
        """
        if self.arm is None:
            return
        with self.lock:
            stamps = [m.header.stamp.sec * 1_000_000_000 + m.header.stamp.nanosec for _, m, _, _ in self.checked]
        now_ns = self.arm.get_clock().now().nanoseconds
        self.arm.state(max([now_ns] + [s + 1 for s in stamps]))

    def close(self):
        if self.ctx is None:
            return
        if not self.planner_destroyed:
            self.planner.shutdown_worker()
        self.stop_spinning()
        self._arm_past_the_stamps()
        bad = self.controller_violations()
        self.ex.shutdown()
        for n in (None if self.planner_destroyed else self.planner, self.arm, self.drv, self.client_node):
            if n is not None:
                n.destroy_node()
        rclpy.shutdown(context=self.ctx)
        self.ctx = None
        assert not bad, f"trajectories joint_trajectory_controller would refuse: {bad}"


def diag_values(status) -> dict:
    """
    Return a DiagnosticStatus's key/values as a dict of strings.

    None (``Graph.status`` before any /diagnostics message arrived) has none: a wait on a
    value keeps waiting instead of raising.
    """
    return {} if status is None else {kv.key: kv.value for kv in status.values}


def diag_list(status, key):
    """Parse a list-valued diagnostics entry (e.g. ``target_m``), or None."""
    v = diag_values(status).get(key)
    return None if v is None else json.loads(v)


def rss_mb(pid="self") -> float:
    """Resident set size of a process (VmRSS from /proc), MiB; nan once it is gone."""
    try:
        with open(f"/proc/{pid}/status") as f:
            for line in f:
                if line.startswith("VmRSS:"):
                    return int(line.split()[1]) / 1024.0
    except (FileNotFoundError, ProcessLookupError):
        pass
    return math.nan


def planning_pids() -> list:
    """
    Return the pids of this test process's planning processes that run (the graphs' nodes start them).

    Not every child: with the zygote this process is a child subreaper, so the orphaned
    planning process of a node run as a subprocess (and killed) also becomes its child for a while.
    """
    return ZYGOTE.running()


def child_pids(pid=None) -> list:
    """Direct children of a process (default: this one, less its planning zygote), from /proc/*/stat."""
    zygote = {ZYGOTE.pid} if pid is None else set()
    pid = os.getpid() if pid is None else pid
    out = []
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        try:
            with open(f"/proc/{entry}/stat") as f:
                stat = f.read()
        except OSError:
            continue
        fields = stat[stat.rfind(")") + 2:].split()       # after "(comm)": state, ppid, ...
        if int(fields[1]) == pid and int(entry) not in zygote:
            out.append(int(entry))
    return out


def pid_alive(pid: int) -> bool:
    """Tell whether the process exists and is not a zombie."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            stat = f.read()
    except OSError:
        return False
    return stat[stat.rfind(")") + 2] != "Z"


def planned_positions(robot, msgs, index=-1):
    """
    Return the (dof,) planned-joint positions of point ``index``.

    Merged by name from the given JointTrajectory messages (joint_trajectory and
    attitude_trajectory of one plan).
    """
    got = {}
    for m in msgs:
        if m is not None:
            got.update(zip(m.joint_names, m.points[index].positions))
    return np.array([got[n] for n in robot.planned_names])


def angle_err_deg(robot, q_full, goal_planned):
    idx = list(robot.planned_joints)
    d = np.asarray(q_full)[idx] - goal_planned
    for k, p in enumerate(robot.planned_periodic):
        if p:
            d[k] = math.remainder(d[k], 2 * math.pi)
    return float(np.degrees(np.max(np.abs(d))))


def wait_at_goal(g, timeout=30):
    robot = g.scenario.robot
    g.wait(lambda: g.planner.last_result is not None, timeout, "a plan")
    goal = g.planner.last_result.goal_rad
    g.wait(lambda: not g.arm.executing and g.arm.trajectories_received > 0
           and angle_err_deg(robot, g.arm.positions, g.planner.last_result.goal_rad) < 0.5,
           timeout, "the arm at the goal")
    return goal


def joint_states_free(g, since=0.0):
    robot = g.scenario.robot
    scene = g.scenario.scene.with_target(g.planner._target)      # the current target
    checker = CollisionChecker(robot, scene)
    with g.lock:
        msgs = [m for t, m in g.states if t >= since]
    q = np.array([[m.position[list(m.name).index(n)] for n in robot.planned_names] for m in msgs])
    return len(q), checker.is_free(q)


# ---------------------------------------------------------------- controller rules
def controller_rule_violations(msg, known_joints, received_at_ros_s=None, current_state=None):
    """
    List what ros2_control's joint_trajectory_controller would refuse in a JointTrajectory.

    Its rules, written here from its documentation, sharing no code with the node:

    - joint names non-empty, known to the controller and unique;
    - every point has one position per joint; velocities / accelerations empty or one per joint;
    - time_from_start strictly increasing; the first > 0 unless that point is the current state;
    - a header stamp of zero means "start now"; a non-zero stamp plus the last
      time_from_start must not lie in the past (``received_at_ros_s``: the ROS time it arrived);
    - the last point has zero velocities (the arm stops there).

    Returns a list of sentences (empty when the trajectory is accepted).
    """
    out = []
    names = list(msg.joint_names)
    if not names:
        out.append("no joint names")
    unknown = [n for n in names if n not in known_joints]
    if unknown:
        out.append(f"unknown joints {unknown}")
    if len(set(names)) != len(names):
        out.append(f"duplicate joint names {names}")
    pts = list(msg.points)
    if not pts:
        out.append("no points")
        return out
    n = len(names)
    times = []
    for i, p in enumerate(pts):
        if len(p.positions) != n:
            out.append(f"point {i}: {len(p.positions)} positions for {n} joints")
        for field in ("velocities", "accelerations"):
            k = len(getattr(p, field))
            if k not in (0, n):
                out.append(f"point {i}: {k} {field} for {n} joints")
        times.append(p.time_from_start.sec + 1e-9 * p.time_from_start.nanosec)
    if any(b <= a for a, b in zip(times, times[1:])):
        out.append("time_from_start does not increase strictly")
    if times[0] <= 0.0:
        at_current = current_state is not None and len(current_state) == n and all(
            abs(a - b) < 1e-9 for a, b in zip(pts[0].positions, current_state))
        if not at_current:
            out.append("the first point is at time 0 but is not the current state")
    stamp_s = msg.header.stamp.sec + 1e-9 * msg.header.stamp.nanosec
    if stamp_s != 0.0 and received_at_ros_s is not None and stamp_s + times[-1] < received_at_ros_s:
        out.append(f"ends in the past (stamp + duration {stamp_s + times[-1]:.3f} < now {received_at_ros_s:.3f})")
    if len(pts[-1].velocities) == n and any(abs(v) > 1e-9 for v in pts[-1].velocities):
        out.append(f"non-zero velocities at the end {list(pts[-1].velocities)}")
    return out


def next_plan(g, n_traj, n_att=0, timeout=30):
    """
    Wait for the first plan published after the driver had ``n_traj`` joint and ``n_att`` attitude trajectories.

    Returns its (dof,) planned-joint end (rad) and its first point (rad).  One publisher's
    messages arrive in order, so this is the plan published next, whatever came before it:
    a test that sends a good request after a bad one checks with it that nothing went out for the
    bad one (the good one's plan comes first), with no sleep.
    """
    robot = g.scenario.robot
    has_att = "attitude" in robot.planned_names

    def arrived():
        with g.lock:
            return len(g.trajs) > n_traj and (not has_att or len(g.att_trajs) > n_att)
    g.wait(arrived, timeout, f"a trajectory after the first {n_traj}")
    with g.lock:
        msgs = [g.trajs[n_traj][1], g.att_trajs[n_att][1] if has_att else None]
    return planned_positions(robot, msgs, -1), planned_positions(robot, msgs, 0)


def assert_next_plan_grasps(g, n_traj, n_att, x_m, y_m, yaw_rad=0.0, timeout=30, tol_m=1e-3):
    """Assert the next plan published (see next_plan) ends with the tip at the grasp point of the target (x, y, yaw)."""
    end, _ = next_plan(g, n_traj, n_att, timeout)
    robot = g.scenario.robot
    tip = robot.tip_position(robot.full(end))
    grasp = dataclasses.replace(g.scenario.scene.target, center_m=(x_m, y_m), yaw_rad=yaw_rad).grasp_point_m
    miss = float(np.linalg.norm(tip - grasp))
    assert miss < tol_m, (f"the next trajectory ends {miss:.4f} m from the grasp of ({x_m}, {y_m}): "
                          "another plan went out first")
