"""
`mock_arm_node`: a kinematic arm that follows JointTrajectory messages.

Publishes ``joint_states`` (every joint in ``robot.joint_names``) at
``mock_arm.rate_hz``.  The initial posture is ``scenario.start_deg`` over the
planned joints and ``robot.locked_positions_deg`` for the rest.  A trajectory on
``joint_trajectory`` (the arm) or ``attitude_trajectory`` (the spacecraft's attitude, as
an attitude control system would) is followed by interpolating its points in time from
its header stamp (a zero stamp: from the moment it arrives).  A newer trajectory on the
same topic replaces the old one at its stamp: until then the arm goes on following the
old one (or holds still), as a controller does with a trajectory that starts in the
future.  When the arm is not exactly where the new trajectory is at that moment (it moved
while the planner worked), the difference is faded out linearly over ``blend_s`` (0.2 s),
so the arm starts from where it is without a jump.  The published velocities are the
trajectory's, interpolated in time like the positions.

Parameters: ``robot.*`` and ``scenario.start_deg`` (the shared ``/**`` section of a
scenario file) and ``rate_hz`` (its own ``mock_arm`` section).  Run it with the same
file as the planner::

    ros2 run spacerobot_planner mock_arm_node --ros-args --params-file config/paper_3dof.yaml
"""

from __future__ import annotations

import array
import math
import threading

import numpy as np
from rclpy.node import Node
from sensor_msgs.msg import JointState
from trajectory_msgs.msg import JointTrajectory

from ..config import scenario_from_params
from . import conversions as conv
from . import node_main
from .parameters import MOCK_ARM_PARAMETERS, SPECS, descriptor_for

__all__ = ["MockArmNode", "main"]


class MockArmNode(Node):
    def __init__(self, *, context=None, parameter_overrides=None, node_name: str = "mock_arm",
                 blend_s: float = 0.2, **kwargs):
        super().__init__(node_name, context=context, parameter_overrides=parameter_overrides, **kwargs)
        params = {}
        for name, schema in MOCK_ARM_PARAMETERS.items():
            spec = SPECS[schema]
            value = self.declare_parameter(name, spec.default, descriptor_for(spec, name)).value
            params[schema] = list(value) if isinstance(value, (tuple, np.ndarray, array.array)) else value
        params["grid.cells"] = [2] * len(params["robot.planned_joints"])   # unused here
        sc = scenario_from_params(params)
        self.robot = sc.robot
        q_full = self.robot.full(sc.start_rad if sc.start_rad is not None else self.robot.locked_rad[
            list(self.robot.planned_joints)])
        self.names = tuple(self.robot.joint_names)
        self.periodic = tuple(bool(p) for p in self.robot.periodic)
        self._q = np.array(q_full, dtype=float)
        self._v = np.zeros_like(self._q)
        self._lock = threading.Lock()
        self._trajs = {}             # topic -> (column indices, times, positions, velocities, t0, offset, s_switch)
        self._next = {}              # topic -> (column indices, times, positions, velocities, t0): not started
        self.blend_s = float(blend_s)
        self.trajectories_received = 0
        self.executing = False
        self.pub = self.create_publisher(JointState, "joint_states", 10)
        for topic in ("joint_trajectory", "attitude_trajectory"):      # the arm's and the attitude's
            self.create_subscription(JointTrajectory, topic, lambda m, t=topic: self._on_trajectory(m, t), 10)
        self._timer = self.create_timer(1.0 / float(params["mock_arm.rate_hz"]), self._tick)
        self.get_logger().info(f"mock arm at {np.round(np.degrees(self._q), 2).tolist()}°, "
                               f"publishing {', '.join(self.names)} at {params['mock_arm.rate_hz']} Hz")

    @property
    def positions(self) -> np.ndarray:
        with self._lock:
            return self._q.copy()

    def _on_trajectory(self, msg: JointTrajectory, topic: str = "joint_trajectory"):
        try:
            names, t, q, v = conv.msg_to_trajectory_arrays(msg)
            unknown = [n for n in names if n not in self.names]
            if unknown:
                raise ValueError(f"joint_trajectory: unknown joint(s) {', '.join(unknown)}")
        except ValueError as e:
            self.get_logger().error(str(e))
            return
        cols = [self.names.index(n) for n in names]
        t0 = self._start_time(msg)
        with self._lock:
            self._next[topic] = (cols, t, q, v, t0)
            self.trajectories_received += 1
            self.executing = True
        ahead = t0 - self._now_s()
        self.get_logger().info(f"received a trajectory of {len(t)} points, {t[-1]:.2f} s, starting "
                               + (f"in {ahead:.3f} s" if ahead > 0 else f"{-ahead:.3f} s ago"))

    def _now_s(self) -> float:
        """Return the node's clock (ROS time), s: the time base of the motion and of the stamps."""
        return 1e-9 * self.get_clock().now().nanoseconds

    def _start_time(self, msg) -> float:
        """
        Return the ROS time (s) at which ``msg`` starts.

        Its header stamp (as a controller reads it: the arm's and the attitude's parts of one plan
        start together), or now for a zero stamp.
        """
        stamp_ns = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
        return self._now_s() if stamp_ns == 0 else 1e-9 * stamp_ns

    def _advance(self, now):
        with self._lock:
            self._v[:] = 0.0
            for topic in list(self._trajs):
                self._advance_one(topic, now)
            for topic in list(self._next):
                if now >= self._next[topic][4]:
                    self._switch(topic, now)
                    self._advance_one(topic, now)
            self.executing = bool(self._trajs or self._next)

    def _switch(self, topic, now):
        """
        (lock held) the waiting trajectory of ``topic`` takes over at ``now``.

        The arm's offset from it there is faded out over blend_s.
        """
        cols, t, q, v, t0 = self._next.pop(topic)
        s = now - t0
        pos, _ = _interpolate(t, q, v, s)
        off = self._q[cols] - pos
        for k, c in enumerate(cols):
            if self.periodic[c]:
                off[k] = math.remainder(off[k], 2 * math.pi)
        self._trajs[topic] = (cols, t, q, v, t0, off, s)

    def _advance_one(self, topic, now):
        """(lock held) one topic's trajectory at time ``now``."""
        cols, t, q, v, t0, off, s_switch = self._trajs[topic]
        s = now - t0
        since = s - s_switch
        if s >= t[-1] and since >= self.blend_s:
            self._q[cols] = q[-1]
            self._v[cols] = 0.0
            del self._trajs[topic]
            return
        pos, vel = _interpolate(t, q, v, s)
        fade = max(0.0, 1.0 - since / self.blend_s) if self.blend_s > 0 else 0.0
        self._q[cols] = pos + fade * off
        self._v[cols] = vel

    def _tick(self):
        # one instant for the state and its stamp (the state is computed at the stamp's time)
        now_ns = self.get_clock().now().nanoseconds
        self._advance(1e-9 * now_ns)
        with self._lock:
            q, v = self._q.copy(), self._v.copy()
        self.pub.publish(conv.joint_state_msg(self.names, q, v, conv.ns_to_time(now_ns)))


def _interpolate(t, q, v, s):
    """
    Interpolate a trajectory's points at time ``s``: (positions, velocities).

    The points: times ``t`` (M,), positions ``q`` (M, n), velocities ``v`` (M, n) or None;
    linear in time, clamped to its ends (at rest after the last point).
    """
    if s <= t[0]:
        return q[0].copy(), (np.zeros(q.shape[1]) if v is None or len(t) == 1 else v[0].copy())
    k = int(np.searchsorted(t, s, side="right") - 1)
    if k >= len(t) - 1:
        return q[-1].copy(), np.zeros(q.shape[1])
    f = (s - t[k]) / (t[k + 1] - t[k])
    pos = q[k] + f * (q[k + 1] - q[k])
    vel = (q[k + 1] - q[k]) / (t[k + 1] - t[k]) if v is None else v[k] + f * (v[k + 1] - v[k])
    return pos, vel


def main(args=None) -> int:
    """Entry point: ``ros2 run spacerobot_planner mock_arm_node``."""
    return node_main.run_node(MockArmNode, "mock_arm_node", args)


if __name__ == "__main__":
    raise SystemExit(main())
