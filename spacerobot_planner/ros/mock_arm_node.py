"""
`mock_arm_node`: a kinematic arm that follows JointTrajectory messages.

Publishes ``joint_states`` (every joint in ``robot.joint_names``: positions and velocities) at
``mock_arm.rate_hz``.  The initial posture is ``scenario.start_deg`` over the planned joints
and ``robot.locked_positions_deg`` for the rest.  A trajectory on ``joint_trajectory`` (the
arm) or ``attitude_trajectory`` (the spacecraft's attitude, as an attitude control system
would) is followed as ros2_controllers' joint_trajectory_controller (JTC) follows one:

- its points are interpolated per segment by ``published.sample_points``: linear for
  positions only, a cubic Hermite with velocities, a quintic with velocities and
  accelerations; after the last point the arm holds it, at rest;
- its time base is its header stamp (a zero stamp: the moment it arrives); one that would
  end before it arrives (a non-zero stamp plus its duration in the past) is refused;
- it takes over at its stamp (at its arrival when that is later): until then the arm goes on
  following the trajectory it had on the same topic (or holds still), as JTC from
  ros2_controllers 6.8 on does with ``allow_trajectory_replacement`` (a newer waiting trajectory
  drops any waiting one that would start at or after it); with ``controller.switch: arrival`` (or
  ``auto`` and ``allow_trajectory_replacement: false``) it takes over when it arrives, as JTC before
  6.8 (Kilted, Jazzy);
- when it takes over before its first point's time, the arm moves from its state at that
  moment (position, velocity, acceleration) to the first point along the segment the first
  point's fields call for (JTC's "point before the trajectory"; a periodic joint's state is
  first wrapped to within half a turn of the point); a trajectory whose first point is at
  time 0 starts on it there.

The state is a function of the ROS time: ``state(now_ns)`` (positions, velocities,
accelerations of every joint) starts the trajectories due by then and samples them;
``joint_state_at(now_ns)`` is the message the timer publishes for that instant (the
accelerations are not in it: JointState has no field for them).  Times are kept in integer
nanoseconds, so a state is exact at its stamp.  Joints that no trajectory moves hold their
position.

Parameters: ``robot.*``, ``scenario.start_deg`` and ``controller.switch`` (the shared ``/**``
section of a scenario file; read-only), ``rate_hz`` (its own ``mock_arm`` section; a change takes effect
at once, a whole number too) and ``allow_trajectory_replacement`` (read-only: joint_trajectory_controller's
name for the model, which the planner's ``controller.switch: auto`` reads; it follows ``controller.switch``
unless that is ``auto``, default true).  Run it with the same file as the planner::

    ros2 run spacerobot_planner mock_arm_node --ros-args --params-file config/paper_3dof.yaml
"""

from __future__ import annotations

import array
import math
import threading
from dataclasses import dataclass, replace

import numpy as np
from rclpy.node import Node
from sensor_msgs.msg import JointState
from trajectory_msgs.msg import JointTrajectory

from ..config import scenario_from_params
from ..published import sample_points
from . import conversions as conv
from . import node_main
from .parameters import MOCK_ARM_PARAMETERS, SPECS, as_declared, check_choice, descriptor_for
from .time_jumps import on_time_jumps

__all__ = ["MockArmNode", "main"]


@dataclass(frozen=True, eq=False)
class _Motion:
    """
    A received trajectory.

    Attributes
    ----------
        cols: the joint_states columns of its joints.
        times: (M,) its points' times from ``start_ns``, s.
        q, v, a: (M, k) its positions, velocities (or None), accelerations (or None).
        start_ns: ROS time of its time 0 (its stamp, or its arrival for a zero stamp), ns.
        switch_ns: ROS time at which it takes over (its stamp, or its arrival when later), ns.

    """

    cols: tuple
    times: np.ndarray
    q: np.ndarray
    v: np.ndarray | None
    a: np.ndarray | None
    start_ns: int
    switch_ns: int

    def s_at(self, ns: int) -> float:
        """Return ROS time ``ns`` in the trajectory's time, s (from its time 0)."""
        return 1e-9 * (int(ns) - self.start_ns)


def _switches_at_arrival(switch: str, allow_replacement: bool) -> bool:
    """
    Return whether the mock arm takes a newer trajectory over at its arrival (else at its stamp).

    ``controller.switch`` (the shared section) decides when it is ``stamp`` or ``arrival``; with
    ``auto`` the arm's own ``allow_trajectory_replacement`` does, as joint_trajectory_controller's
    from 6.8 on (the planner's ``controller.switch: auto`` reads it there).  ValueError naming both
    when they contradict each other.
    """
    check_choice("controller.switch", switch)
    if switch == "auto":
        return not allow_replacement
    if allow_replacement != (switch == "stamp"):
        raise ValueError(f"allow_trajectory_replacement: {str(allow_replacement).lower()} contradicts "
                         f"controller.switch: {switch} (a controller that switches at its "
                         f"{'stamp' if allow_replacement else 'arrival'}); set controller.switch: auto, or leave "
                         "allow_trajectory_replacement out")
    return switch == "arrival"


class MockArmNode(Node):
    def __init__(self, *, context=None, parameter_overrides=None, node_name: str = "mock_arm", start_check=None,
                 **kwargs):
        super().__init__(node_name, context=context, parameter_overrides=parameter_overrides, **kwargs)
        params = {}
        for name, schema in MOCK_ARM_PARAMETERS.items():
            spec = SPECS[schema]
            default = spec.default
            if name == "allow_trajectory_replacement":      # what controller.switch (declared before) says
                default = params["controller.switch"] != "arrival"
            value = self.declare_parameter(name, default, descriptor_for(spec, name)).value
            params[schema] = list(value) if isinstance(value, (tuple, np.ndarray, array.array)) else value
        if start_check is not None:     # the executable's: its parameter files state the robot (ValueError)
            start_check(self)
        params["grid.cells"] = [2] * len(params["robot.planned_joints"])   # unused here
        sc = scenario_from_params(params)
        self.robot = sc.robot
        q_full = self.robot.full(sc.start_rad if sc.start_rad is not None else self.robot.locked_rad[
            list(self.robot.planned_joints)])
        self.names = tuple(self.robot.joint_names)
        # when a newer trajectory takes over: at its stamp (joint_trajectory_controller from 6.8 on) or at its
        # arrival, from the state then to its first point (before 6.8: Kilted, Jazzy)
        self.switch_at_arrival = _switches_at_arrival(params["controller.switch"],
                                                      params["mock_arm.allow_trajectory_replacement"])
        self.periodic = tuple(bool(p) for p in self.robot.periodic)
        self._lock = threading.Lock()
        self._hold = np.array(q_full, dtype=float)     # where joints no trajectory moves are
        self._q = self._hold.copy()                    # the latest state computed (positions)
        self._v = np.zeros_like(self._q)
        self._a = np.zeros_like(self._q)
        self._active = {}            # topic -> _Motion followed now (its point before prepended)
        self._waiting = {}           # topic -> [_Motion] not started yet, by switch time
        # (switch time ns, what is followed from then: active motions, hold): the motion is a
        # function of time, so the state at any past instant is exact (history_state_at)
        self._history = [(-1, {}, self._hold.copy())]
        self.trajectories_received = 0
        self.executing = False
        self.pub = self.create_publisher(JointState, "joint_states", 10)
        for topic in ("joint_trajectory", "attitude_trajectory"):      # the arm's and the attitude's
            self.create_subscription(JointTrajectory, topic, lambda m, t=topic: self._on_trajectory(m, t), 10)
        self._timer = self.create_timer(1.0 / float(params["mock_arm.rate_hz"]), self._tick)
        self.add_post_set_parameters_callback(self._post_set)
        self._time_jumps = on_time_jumps(self, self.time_jumped)      # the handle keeps the callback
        self.get_logger().info(f"mock arm at {np.round(np.degrees(self._q), 2).tolist()}°, "
                               f"publishing {', '.join(self.names)} at {params['mock_arm.rate_hz']} Hz; a newer "
                               f"trajectory takes over at its {'arrival' if self.switch_at_arrival else 'stamp'}")

    # ------------------------------------------------------------------ parameters
    def set_parameters_atomically(self, parameter_list):
        """As rclpy's (the ``~/set_parameters`` service calls it), a whole number given for a double as a double."""
        return super().set_parameters_atomically(as_declared(parameter_list, MOCK_ARM_PARAMETERS))

    def set_parameters(self, parameter_list):
        """As rclpy's, a whole number given for a double as a double (``ros2 param set /mock_arm rate_hz 100``)."""
        return super().set_parameters(as_declared(parameter_list, MOCK_ARM_PARAMETERS))

    def _post_set(self, parameters) -> None:
        """Apply a new ``rate_hz`` (the others it declares are read-only): the timer at the new rate."""
        for p in parameters:
            if p.name == "rate_hz":
                self.destroy_timer(self._timer)
                self._timer = self.create_timer(1.0 / float(p.value), self._tick)
                self.get_logger().info(f"publishing joint_states at {p.value} Hz")

    @property
    def positions(self) -> np.ndarray:
        """Return the positions of the latest state (the last ``state`` call's: the last published), (n,) rad."""
        with self._lock:
            return self._q.copy()

    def time_jumped(self, what: str) -> None:
        """
        Stop where the arm is: ROS time jumped back or changed source (``what``, for the log; ``ros.time_jumps``).

        The state is a function of the time, and the trajectories' stamps belong to the time
        before: followed on, the arm would go back to where it was at the new time (its start
        posture after a bag played again).  The latest state's positions are held, the
        trajectories dropped, the history begun again.
        """
        with self._lock:
            self._hold = self._q.copy()
            self._v[:] = 0.0
            self._a[:] = 0.0
            self._active, self._waiting = {}, {}
            self._history = [(-1, {}, self._hold.copy())]
            self.executing = False
            here = np.round(np.degrees(self._hold), 2).tolist()
        self.get_logger().warning(f"ROS time {what}: stopped at {here}°, its trajectories dropped")

    def _on_trajectory(self, msg: JointTrajectory, topic: str = "joint_trajectory"):
        self.receive(msg, topic, self.get_clock().now().nanoseconds)

    def receive(self, msg: JointTrajectory, topic: str, now_ns: int) -> bool:
        """
        Take a trajectory arriving on ``topic`` at ROS time ``now_ns`` (ns).

        What the subscriptions do (with the clock's time).  Returns False, logging why, for
        one that is refused (unknown joints, malformed, ending in the past).
        """
        try:
            names, t, q, v = conv.msg_to_trajectory_arrays(msg)
            unknown = [n for n in names if n not in self.names]
            if unknown:
                raise ValueError(f"{topic}: unknown joint(s) {', '.join(unknown)}")
        except ValueError as e:
            self.get_logger().error(str(e))
            return False
        a = None
        if v is not None and all(len(p.accelerations) == len(names) for p in msg.points):
            a = np.array([list(p.accelerations) for p in msg.points], dtype=float)
            if not np.all(np.isfinite(a)):
                a = None
        now_ns = int(now_ns)
        start_ns = conv.time_to_ns(msg.header.stamp) or now_ns
        switch_ns = now_ns if self.switch_at_arrival else max(start_ns, now_ns)
        m = _Motion(tuple(self.names.index(n) for n in names), t, q, v, a, start_ns, switch_ns)
        if m.s_at(now_ns) > t[-1]:
            self.get_logger().error(f"{topic}: refused a trajectory that ends in the past (stamp + duration "
                                    f"{m.s_at(now_ns) - t[-1]:.3f} s before now)")
            return False
        with self._lock:
            self._waiting[topic] = [w for w in self._waiting.get(topic, []) if w.switch_ns < m.switch_ns] + [m]
            self.trajectories_received += 1
            self.executing = True
        ahead = -m.s_at(now_ns)
        kind = "quintic" if a is not None else "cubic" if v is not None else "linear"
        self.get_logger().info(f"received a trajectory of {len(t)} points ({kind}), {t[-1]:.2f} s, on {topic}, "
                               "starting " + (f"in {ahead:.3f} s" if ahead > 0 else f"{-ahead:.3f} s ago"))
        return True

    def state(self, now_ns: int):
        """
        Return the arm's state at ROS time ``now_ns`` (ns): (positions, velocities, accelerations), each (n,).

        The node's clock is the time base of the motion and of the stamps.  Starts the
        trajectories due by ``now_ns`` first (in the order of their switch times, each from the
        state at its own switch time), so the result does not depend on when it is asked,
        provided the times asked do not go back past a switch already made.
        """
        now_ns = int(now_ns)
        with self._lock:
            due = []
            for topic, waiting in self._waiting.items():
                due += [(m.switch_ns, topic, m) for m in waiting if m.switch_ns <= now_ns]
                self._waiting[topic] = [m for m in waiting if m.switch_ns > now_ns]
            for _, topic, m in sorted(due, key=lambda d: d[0]):
                self._start(topic, m)
            self._waiting = {k: w for k, w in self._waiting.items() if w}
            q, v, a = self._evaluate(now_ns)
            self._q, self._v, self._a = q, v, a
            self.executing = bool(self._waiting) or any(m.s_at(now_ns) < m.times[-1] for m in self._active.values())
            return q.copy(), v.copy(), a.copy()

    def _start(self, topic: str, m: _Motion):
        """(lock held) ``m`` takes over ``topic`` at its switch time, from the arm's state then."""
        q_s, v_s, a_s = self._evaluate(m.switch_ns)
        self._hold = q_s.copy()            # the joints it leaves (a replaced trajectory's) stay there
        s0 = m.s_at(m.switch_ns)
        if s0 < m.times[0]:                # JTC's point before the trajectory, at the switch
            cols = list(m.cols)
            before = q_s[cols]
            for k, c in enumerate(cols):
                if self.periodic[c]:
                    before[k] = m.q[0, k] - _shortest_angle(before[k], m.q[0, k])
            m = replace(m, times=np.concatenate([[s0], m.times]), q=np.vstack([before, m.q]),
                        v=None if m.v is None else np.vstack([v_s[cols], m.v]),
                        a=None if m.a is None else np.vstack([a_s[cols], m.a]))
        self._active[topic] = m
        self._history.append((int(m.switch_ns), dict(self._active), self._hold.copy()))

    def history_state_at(self, ros_ns: int):
        """
        Return the arm's (positions, velocities, accelerations) at a past ROS time ``ros_ns`` (ns).

        Exact whenever the node published or not (a test's view of where the arm was at a
        trajectory's stamp, even in a gap of its joint_states under load); the switches made so
        far only (times after the latest state computed are not known yet).
        """
        with self._lock:
            k = max(i for i, (t, _, _) in enumerate(self._history) if t <= int(ros_ns))
            _, active, hold = self._history[k]
            return self._evaluate(int(ros_ns), active, hold)

    def _evaluate(self, now_ns: int, active=None, hold=None):
        """(lock held) the state at ``now_ns`` on the trajectories followed now (or ``active`` from ``hold``)."""
        active = self._active if active is None else active
        q = (self._hold if hold is None else hold).copy()
        v, a = np.zeros_like(q), np.zeros_like(q)
        for m in active.values():
            cols = list(m.cols)
            q[cols], v[cols], a[cols] = sample_points(m.times, m.q, m.v, m.a, m.s_at(now_ns))
        return q, v, a

    def joint_state_at(self, now_ns: int) -> JointState:
        """Return the joint_states message of the state at ROS time ``now_ns`` (ns), stamped with it."""
        q, v, _ = self.state(now_ns)
        return conv.joint_state_msg(self.names, q, v, conv.ns_to_time(now_ns))

    def _tick(self):
        # one instant for the state and its stamp (the state is computed at the stamp's time)
        self.pub.publish(self.joint_state_at(self.get_clock().now().nanoseconds))


def _shortest_angle(from_rad: float, to_rad: float) -> float:
    """Return the shortest signed angle from ``from_rad`` to ``to_rad`` (a half turn: toward the larger value)."""
    d = math.remainder(to_rad - from_rad, 2 * math.pi)
    if abs(abs(d) - math.pi) < 1e-9:
        d = abs(d) if to_rad > from_rad else -abs(d)
    return d


def main(args=None) -> int:
    """Entry point: ``ros2 run spacerobot_planner mock_arm_node``."""
    return node_main.run_node(lambda check: MockArmNode(start_check=check), "mock_arm_node", args)


if __name__ == "__main__":
    raise SystemExit(main())
