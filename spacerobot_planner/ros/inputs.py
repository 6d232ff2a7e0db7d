"""
The planner node's input topics: messages checked and turned into the session's requests and states.

- ``target_pose`` (PoseStamped): a new target (``conversions.pose_to_target``; a target
  whose body overlaps the spacecraft's, at the locked attitude or at any attitude within its
  bounds when the attitude is planned, is invalid input: ``overlap.py``); one within
  ``replan.target_tolerance_*`` of the current target is no new request;
- ``goal_joint_state`` (JointState): a joint goal of the planned joints;
- ``joint_states`` (JointState): the arm's state (``robot.validate_q``: a joint outside its bounds is
  rejected), stamped (its header, else the arrival; a
  header more than ``CLOCK_MISMATCH_S`` from this node's clock at arrival is another clock's,
  a driver on sim time and a planner not or the other way round: the arrival, and a warning
  at most every ``CLOCK_WARNING_PERIOD_S``);
- ``attitude_topic`` when set (PoseStamped of the spacecraft body in the planning frame):
  its yaw stands for the attitude joint in joint_states that lack it (a real servicer's).

A bad message is rejected through the node (log, rate-limited per topic, and /diagnostics).
"""

from __future__ import annotations

import math
import time

import numpy as np
from geometry_msgs.msg import PoseStamped
from rclpy.qos import QoSPolicyKind, QoSProfile, ReliabilityPolicy
from rclpy.qos_overriding_options import QoSOverridingOptions
from sensor_msgs.msg import JointState

from ..joint_space import wrap_angle_rad
from ..overlap import target_overlap_reason
from ..scene import Target
from ..session import target_why
from . import conversions as conv
from .time_jumps import no_clock_yet

__all__ = ["Inputs", "CLOCK_MISMATCH_S", "OVERRIDABLE", "unused_qos_overrides", "locked_mismatches",
           "LOCKED_TOL_RAD"]

#: a joint_states header stamped further than this from the node's clock at arrival, s, is on
#: another clock (wall time against sim time: 1.8e9 s); its stamp made a late state look
#: "1796299619.64 s old" and joins fail
CLOCK_MISMATCH_S = 60.0
#: a joint the planner does not plan that joint_states report this far from its
#: ``robot.locked_positions_deg`` (rad; a periodic one the shortest way) is said in a warning, at
#: most every LOCKED_WARNING_PERIOD_S: the plans hold it at the parameter (after a free-floating
#: capture the attitude has drifted from it)
LOCKED_TOL_RAD = math.radians(0.5)
LOCKED_WARNING_PERIOD_S = 30.0
#: the QoS policies of target_pose, joint_states and goal_joint_state that
#: ``qos_overrides.<topic>.subscription.<policy>`` may set (rclpy's defaults and the durability)
OVERRIDABLE = (QoSPolicyKind.HISTORY, QoSPolicyKind.DEPTH, QoSPolicyKind.RELIABILITY, QoSPolicyKind.DURABILITY)
#: ... said at most this often, s
CLOCK_WARNING_PERIOD_S = 30.0
#: two joint_states publishers whose states, received within DISAGREE_WINDOW_S of each other, put a
#: planned joint more than DISAGREE_TOL_RAD apart are not one arm (a mock arm left running beside a
#: driver or a simulator): said in a warning at most every DISAGREE_WARNING_PERIOD_S, naming them
DISAGREE_WINDOW_S = 0.1
DISAGREE_TOL_RAD = math.radians(2.0)
DISAGREE_WARNING_PERIOD_S = 30.0


def locked_mismatches(robot, names, positions, tol_rad: float = LOCKED_TOL_RAD) -> list:
    """
    Return (name, reported rad, locked rad) of each joint not planned that a joint state reports away from its lock.

    ``names``, ``positions``: the message's; a joint reported more than ``tol_rad`` from
    ``robot.locked_rad`` (a periodic one the shortest way round) is one.  Joints not in the
    message, or not finite there, are not.
    """
    out = []
    planned = set(robot.planned_joints)
    for j, name in enumerate(robot.joint_names):
        if j in planned or name not in names:
            continue
        i = list(names).index(name)
        if i >= len(positions):
            continue
        got, held = float(positions[i]), float(robot.locked_rad[j])
        off = float(wrap_angle_rad(got - held)) if robot.periodic[j] else got - held
        if math.isfinite(off) and abs(off) > tol_rad:
            out.append((name, got, held))
    return out


def unused_qos_overrides(names, topics) -> list:
    """
    Return the ``qos_overrides.*`` parameter names among ``names`` that no subscription takes.

    ``topics``: the fully qualified topics of the overridable subscriptions; each takes
    ``qos_overrides.<topic>.subscription.<policy>`` for the policies of :data:`OVERRIDABLE`.
    """
    taken = {f"qos_overrides.{t}.subscription.{kind.name.lower()}" for t in topics for kind in OVERRIDABLE}
    return sorted(n for n in names if n.startswith("qos_overrides.") and n not in taken)


class Inputs:
    """The input subscriptions of ``node`` (a ``planner_node.PlannerNode``) and what they hold (the attitude)."""

    def __init__(self, node):
        self.node = node
        self.attitude = None        # rad: the latest yaw on attitude_topic (joint_states without it)
        self._clock_warned = -float("inf")     # monotonic s of the last clock-mismatch warning
        self._locked_warned = -float("inf")    # ... and of the last locked-joint warning
        self._disagree_warned = -float("inf")  # ... and of the last two-publishers warning
        self._by_publisher = {}     # publisher gid (bytes) -> (monotonic s, planned-joint rad) of its last state
        self._states_sub = None

    def subscribe(self) -> list:
        """Create the subscriptions (activate); return them."""
        node = self.node
        # states: best effort matches both reliable and best-effort (sensor-data) drivers; the
        # latest state is all that counts.  qos_overrides.<topic>.subscription.* may change it.
        states_qos = QoSProfile(depth=10, reliability=ReliabilityPolicy.BEST_EFFORT)
        overridable = QoSOverridingOptions(OVERRIDABLE)
        subs = [node.create_subscription(PoseStamped, "target_pose", self.on_target, 10,
                                         qos_overriding_options=overridable),
                node.create_subscription(JointState, "joint_states", self.on_joint_state, states_qos,
                                         qos_overriding_options=overridable),
                node.create_subscription(JointState, "goal_joint_state", self.on_goal_joint_state, 10,
                                         qos_overriding_options=overridable)]
        self._states_sub, self._by_publisher = subs[1], {}
        unused = unused_qos_overrides(node.list_parameters(["qos_overrides"], 0).names,
                                      [sub.topic_name for sub in subs])
        if unused:
            node.get_logger().warning(
                f"{', '.join(unused)}: not applied (the QoS overrides taken are "
                f"{', '.join(kind.name.lower() for kind in OVERRIDABLE)} of the subscriptions "
                f"{', '.join(sub.topic_name for sub in subs)})")
        topic = node.param_handler.params["attitude_topic"]
        if topic:
            subs.append(node.create_subscription(PoseStamped, topic, self.on_attitude, states_qos))
        return subs

    def target_from_pose(self, msg: PoseStamped, what: str) -> Target:
        """Return the target of a pose; ValueError (named ``what``) when unusable or inside the spacecraft."""
        node = self.node
        try:
            target = conv.pose_to_target(msg, node.planning_frame, node.param_handler.scenario.scene.target)
        except ValueError as e:
            raise ValueError(str(e).replace("target_pose:", f"{what}:", 1)) from None
        overlap = target_overlap_reason(node.robot, target)
        if overlap is not None:
            raise ValueError(f"{what}: {overlap}")
        return target

    def joint_goal_from_msg(self, msg: JointState, what: str) -> np.ndarray:
        """
        Return the planned joints' goal of a JointState; ValueError (named ``what``) when unusable.

        A joint the plans hold (not planned) asked to be away from where they hold it is refused: the
        goal would be planned without it, silently.  Joints the robot does not have are ignored (a
        JointState of a whole arm, its gripper's joints with it), as on ``joint_states``.
        """
        robot = self.node.robot
        q = robot.validate_q(conv.joint_state_positions(msg, robot.planned_names, what), what)
        off = locked_mismatches(robot, msg.name, msg.position)
        if off:
            said = ", ".join(f"{name} at {math.degrees(got):.1f}° (held at {math.degrees(held):.1f}°)"
                             for name, got, held in off)
            raise ValueError(f"{what}: {said}: not a planned joint, so no plan moves it (robot.planned_joints: "
                             f"{', '.join(robot.planned_names)}); leave it out of the goal or plan that joint")
        return q

    def on_target(self, msg: PoseStamped):
        node = self.node
        try:
            target = self.target_from_pose(msg, "target_pose")
        except ValueError as e:
            node._reject("target_pose", "invalid_input", str(e))
            return
        same = node.session.same_target(target)
        if same is not None:
            node.get_logger().debug(same)
            return
        node._submit(target_why(target), target=target)

    def on_goal_joint_state(self, msg: JointState):
        try:
            q = self.joint_goal_from_msg(msg, "goal_joint_state")
        except ValueError as e:
            self.node._reject("goal_joint_state", "invalid_input", str(e))
            return
        self.node._submit(f"joint goal {np.round(np.degrees(q), 2).tolist()}°", joint_goal=q)

    def on_joint_state(self, msg: JointState, info: dict):
        """Take the arm's state (``info``: rclpy's MessageInfo, its publisher's gid: two that disagree are said)."""
        node, robot = self.node, self.node.robot
        attitude = robot.joint_names[0]
        topic = node.param_handler.params["attitude_topic"]
        fallback = None if self.attitude is None else {attitude: self.attitude}
        try:
            q = conv.joint_state_positions(msg, robot.planned_names, fallback=fallback)
            # outside a joint's bounds no plan can start (every motion from there is refused): said here, where
            # the message came, not by each plan.  Checked only: the state is kept as reported (a periodic
            # joint unwrapped, as the controller has it; the plans wrap their starts themselves)
            robot.validate_q(q, "joint_states")
        except ValueError as e:
            reason = str(e)
            if topic and fallback is None and attitude in robot.planned_names and attitude not in msg.name:
                reason += f"; no attitude received on '{topic}' yet"
            node.session.joint_state_refused(reason)
            node._reject("joint_states", "invalid_input", reason)
            return
        now_ns, stamp_ns = node.get_clock().now().nanoseconds, conv.time_to_ns(msg.header.stamp)
        if now_ns == 0 and no_clock_yet(node.get_clock()):
            pass                  # use_sim_time before the first /clock: the stamp as it is, no time to compare
        elif stamp_ns and abs(now_ns - stamp_ns) > CLOCK_MISMATCH_S * 1e9:
            self._clock_mismatch(now_ns, stamp_ns)
            stamp_ns = 0
        node.session.joint_state(q, stamp_ns or now_ns)
        if len(msg.name) > len(robot.planned_names):       # a joint the planner holds may be in it
            self._check_locked(msg)
        gid = info.get("publisher_gid") or {}
        if gid.get("data") is not None:
            self._check_publishers(bytes(gid["data"]), q)

    def _check_publishers(self, gid: bytes, q) -> None:
        """
        Warn (at most every DISAGREE_WARNING_PERIOD_S) where two publishers' joint states are not one arm's.

        ``gid``: the publisher of ``q`` (planned-joint rad).  States of another publisher received
        within DISAGREE_WINDOW_S that put a planned joint more than DISAGREE_TOL_RAD away (a periodic
        one the shortest way) are another arm's: each plan would start from whichever came last.
        """
        t = time.monotonic()
        others = [(g, q_o, t - t_o) for g, (t_o, q_o) in self._by_publisher.items()
                  if g != gid and t - t_o <= DISAGREE_WINDOW_S]
        self._by_publisher = {g: v for g, v in self._by_publisher.items() if t - v[0] <= DISAGREE_WINDOW_S}
        self._by_publisher[gid] = (t, q)
        if not others or t < self._disagree_warned + DISAGREE_WARNING_PERIOD_S:
            return
        robot = self.node.robot
        periodic = np.asarray(robot.planned_periodic, dtype=bool)
        for g, q_o, ago_s in others:
            off = np.where(periodic, wrap_angle_rad(q - q_o), q - q_o)
            k = int(np.argmax(np.abs(off)))
            if not abs(off[k]) > DISAGREE_TOL_RAD:
                continue
            self._disagree_warned = t
            name = robot.planned_names[k]
            who = self._publisher_names()
            self.node.get_logger().warning(
                f"joint_states: two publishers disagree: {who.get(g, 'one')} has {name} at "
                f"{math.degrees(q_o[k]):.1f}°, {who.get(gid, 'another')} at {math.degrees(q[k]):.1f}° "
                f"({ago_s:.3f} s later): each plan starts from whichever came last. Is a mock arm running beside "
                f"the arm's driver or a simulator? (ros2 topic info -v {self._states_sub.topic_name})")
            return

    def _publisher_names(self) -> dict:
        """Return publisher gid (bytes) -> its node's name ("/ns/node"; "publisher 2 of /ns/node" beside another)."""
        try:
            infos = self.node.get_publishers_info_by_topic(self._states_sub.topic_name)
        except Exception:           # noqa: BLE001 - a name for a warning only
            return {}
        full = [f"{i.node_namespace.rstrip('/')}/{i.node_name}" for i in infos]
        out = {}
        for i, info in enumerate(infos):
            same = [k for k, f in enumerate(full) if f == full[i]]
            out[bytes(info.endpoint_gid)] = (full[i] if len(same) == 1
                                             else f"publisher {same.index(i) + 1} of {full[i]}")
        return out

    def _check_locked(self, msg: JointState) -> None:
        """Warn (at most every LOCKED_WARNING_PERIOD_S) where a joint the plans hold is reported elsewhere."""
        t = time.monotonic()
        if t < self._locked_warned + LOCKED_WARNING_PERIOD_S:
            return
        off = locked_mismatches(self.node.robot, msg.name, msg.position)
        if not off:
            return
        self._locked_warned = t
        said = ", ".join(f"{name} at {math.degrees(got):.1f}° where robot.locked_positions_deg holds it at "
                         f"{math.degrees(held):.1f}°" for name, got, held in off)
        self.node.get_logger().warning(
            f"joint_states: {said}: not a planned joint, so the plans hold it at the parameter (after a "
            f"free-floating capture the attitude has drifted): set robot.locked_positions_deg and restart the "
            f"node, or plan that joint")

    def _clock_mismatch(self, now_ns: int, stamp_ns: int) -> None:
        """Warn (at most every CLOCK_WARNING_PERIOD_S of wall time) that joint_states are stamped on another clock."""
        t = time.monotonic()
        if t < self._clock_warned + CLOCK_WARNING_PERIOD_S:
            return
        self._clock_warned = t
        node = self.node
        off = 1e-9 * (stamp_ns - now_ns)
        sim = node.get_parameter("use_sim_time").value
        node.get_logger().warning(
            f"joint_states are stamped {abs(off):.2f} s {'ahead of' if off > 0 else 'behind'} this node's clock "
            f"(use_sim_time: {str(bool(sim)).lower()}): do the driver and the planner use the same clock? Their "
            f"stamps are ignored (the arrival time is used), and a controller on the other clock will not run "
            f"the trajectories, stamped on this one")

    def on_attitude(self, msg: PoseStamped):
        """Take the spacecraft body's pose (``attitude_topic``): its yaw is the attitude joint (position ignored)."""
        node = self.node
        topic, frame = node.param_handler.params["attitude_topic"], node.planning_frame
        if msg.header.frame_id.lstrip("/") != frame.lstrip("/"):
            node._reject("attitude", "invalid_input", f"{topic}: frame '{msg.header.frame_id}' is not the "
                         f"planning frame '{frame}'")
            return
        o = msg.pose.orientation
        try:
            self.attitude = conv.quaternion_to_yaw(o.x, o.y, o.z, o.w)
        except ValueError as e:
            node._reject("attitude", "invalid_input", f"{topic}: {e}")
