"""
Messages ↔ core types: the only module besides the nodes that imports ROS messages.

Every function is pure (no node, no graph) and raises ``ValueError`` with a reason
a person can act on when a message is unusable.

Decisions documented here (and in the README):
- Target poses: the frame must equal the planning frame; position z is ignored
  (the problem is planar); the orientation must be a rotation about +z (the target's
  z axis within 1° of the planning frame's); a quaternion whose norm is within 1 %
  of 1 is normalised (hand-typed values such as 0.707), any other norm (zero
  included) is rejected; NaN/inf anywhere is rejected.
- Joint states are matched by name: extra joints are ignored, a missing planned
  joint, a name/position length mismatch or a non-finite position is an error.
- Trajectories carry the planned joints only, with continuous (unwrapped) values
  for periodic joints.
- Grids: see :func:`potential_slice_values` and :func:`grid_slice_to_msg`.
"""

from __future__ import annotations

import array
import math
import struct
from types import SimpleNamespace

import numpy as np
from builtin_interfaces.msg import Duration, Time
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import Point, PoseStamped
from nav_msgs.msg import OccupancyGrid
from sensor_msgs.msg import JointState
from std_msgs.msg import ColorRGBA
from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint
from visualization_msgs.msg import Marker, MarkerArray

from ..scene import Target
from ..trajectory import MAX_DURATION_S, Trajectory

__all__ = [
    "pose_to_target", "quaternion_to_yaw", "yaw_to_quaternion", "target_to_pose",
    "joint_state_positions", "joint_state_msg", "trajectory_to_msg", "msg_to_trajectory_arrays",
    "duration_to_s", "s_to_duration", "ns_to_time", "time_to_ns", "potential_slice_values", "obstacle_slice_values",
    "grid_slice", "grid_slice_to_msg", "path_markers", "marker_strips", "markers_msg", "markers_cdr",
    "markers_payload", "diagnostic_array", "plan_result", "predicted_drift_msg",
    "split_trajectory_msg", "plan_visuals", "GridSlices", "slice_axes_and_point", "publication_msgs",
    "publication_payloads", "trajectory_cdr", "diagnostic_cdr", "diagnostic_payload",
    "OBSTACLE", "UNREACHABLE",
]

OBSTACLE = 100        # occupancy value of an obstacle node
UNREACHABLE = 99      # free node not connected to the goal (u = 0, φ = +inf)
_NORM_TOL = 0.01      # quaternion norms within 1 % of 1 are normalised
_TILT_TOL_RAD = math.radians(1.0)


# ------------------------------------------------------------------ time
def duration_to_s(d) -> float:
    return float(d.sec) + 1e-9 * float(d.nanosec)


def _sec_nanosec(t_s):
    """
    Return (sec, nanosec) of times in seconds (a float or an array): the nearest ns, ties to even.

    ValueError for a time that is not finite or beyond what builtin_interfaces/Duration holds
    (``trajectory.MAX_DURATION_S``: the time parameterisation refuses longer trajectories).
    """
    t = np.asarray(t_s, dtype=np.float64)
    if not np.all(np.isfinite(t)):
        raise ValueError(f"time_from_start: not finite ({t_s} s)")
    if np.any(np.abs(t) > MAX_DURATION_S):
        raise ValueError(f"time_from_start: {float(np.max(np.abs(t))):.4g} s is more than a message holds "
                         f"({MAX_DURATION_S:.0f} s)")
    return np.divmod(np.rint(t * 1e9).astype(np.int64), 1_000_000_000)


def s_to_duration(t_s: float) -> Duration:
    sec, nsec = _sec_nanosec(float(t_s))
    return Duration(sec=int(sec), nanosec=int(nsec))


def ns_to_time(ns: int) -> Time:
    """Convert a ROS time in integer nanoseconds → builtin_interfaces/Time (a header stamp)."""
    ns = int(ns)
    return Time(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)


def time_to_ns(stamp) -> int:
    """builtin_interfaces/Time → integer nanoseconds (0 for a zero stamp)."""
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


# ------------------------------------------------------------------ poses
def quaternion_to_yaw(x: float, y: float, z: float, w: float) -> float:
    """Yaw (rad) of a rotation about +z; ValueError for NaN, a bad norm or a tilt."""
    q = np.array([x, y, z, w], dtype=float)
    if not np.all(np.isfinite(q)):
        raise ValueError(f"orientation: quaternion has NaN or inf components ({x}, {y}, {z}, {w})")
    norm = float(np.linalg.norm(q))
    if abs(norm - 1.0) > _NORM_TOL:
        raise ValueError(f"orientation: not a unit quaternion (norm {norm:.4g}; "
                         f"accepted within {_NORM_TOL:.0%} of 1 and normalised)")
    x, y, z, w = q / norm
    # z axis of the rotated frame: its z component is 1 - 2(x² + y²)
    zz = 1.0 - 2.0 * (x * x + y * y)
    if math.acos(max(-1.0, min(1.0, zz))) > _TILT_TOL_RAD:
        raise ValueError("orientation: the target is tilted out of the plane (the pose must be "
                         "a rotation about +z of the planning frame)")
    return math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))


def yaw_to_quaternion(yaw_rad: float):
    """(x, y, z, w) of a rotation by yaw about +z."""
    return 0.0, 0.0, math.sin(0.5 * yaw_rad), math.cos(0.5 * yaw_rad)


def pose_to_target(msg: PoseStamped, planning_frame: str, template: Target | None = None) -> Target:
    """
    Convert a PoseStamped (target body centre and yaw) → Target; sizes from ``template``.

    Raises ValueError: wrong frame, NaN/inf, non-unit quaternion, tilted pose.
    """
    frame = msg.header.frame_id
    if frame.lstrip("/") != planning_frame.lstrip("/"):
        raise ValueError(f"target_pose: frame '{frame}' is not the planning frame "
                         f"'{planning_frame}' (no TF lookup: publish it in '{planning_frame}')")
    p, o = msg.pose.position, msg.pose.orientation
    if not all(math.isfinite(v) for v in (p.x, p.y, p.z)):
        raise ValueError(f"target_pose: position has NaN or inf ({p.x}, {p.y}, {p.z})")
    try:
        yaw = quaternion_to_yaw(o.x, o.y, o.z, o.w)
    except ValueError as e:
        raise ValueError(f"target_pose: {e}") from None
    t = template if template is not None else Target()
    return Target(center_m=(float(p.x), float(p.y)), yaw_rad=yaw,
                  body_side_m=t.body_side_m, handle_side_m=t.handle_side_m)


def target_to_pose(target: Target, frame: str, stamp=None) -> PoseStamped:
    msg = PoseStamped()
    msg.header.frame_id = frame
    if stamp is not None:
        msg.header.stamp = stamp
    msg.pose.position.x, msg.pose.position.y = (float(v) for v in target.center_m)
    qx, qy, qz, qw = yaw_to_quaternion(target.yaw_rad)
    msg.pose.orientation.x, msg.pose.orientation.y = qx, qy
    msg.pose.orientation.z, msg.pose.orientation.w = qz, qw
    return msg


# ------------------------------------------------------------------ joints
def joint_state_positions(msg: JointState, names, what: str = "joint_states", fallback: dict | None = None
                          ) -> np.ndarray:
    """
    Positions (rad) of the joints ``names`` (in that order) from a JointState.

    Extra joints are ignored; a joint the message lacks takes its value from ``fallback``
    (name -> rad) when there.  Raises ValueError when the message's name and position
    lists differ in length, a joint is missing or listed twice, or a value is not finite.
    """
    if len(msg.name) != len(msg.position):
        raise ValueError(f"{what}: {len(msg.name)} names but {len(msg.position)} positions")
    index = {}
    for i, n in enumerate(msg.name):
        if n in index:
            raise ValueError(f"{what}: joint '{n}' is listed twice")
        index[n] = i
    fallback = fallback or {}
    missing = [n for n in names if n not in index and n not in fallback]
    if missing:
        raise ValueError(f"{what}: missing joint(s) {', '.join(missing)} "
                         f"(got {', '.join(msg.name) or 'none'})")
    q = np.array([msg.position[index[n]] if n in index else fallback[n] for n in names], dtype=float)
    bad = [n for n, v in zip(names, q) if not math.isfinite(v)]
    if bad:
        raise ValueError(f"{what}: joint(s) {', '.join(bad)} not finite")
    return q


def joint_state_msg(names, positions, velocities=None, stamp=None) -> JointState:
    msg = JointState()
    if stamp is not None:
        msg.header.stamp = stamp
    msg.name = [str(n) for n in names]
    msg.position = [float(v) for v in positions]
    if velocities is not None:
        msg.velocity = [float(v) for v in velocities]
    return msg


def _points_public(rows, secs, nsecs) -> list:
    """Return the points built by the messages' constructors (rows: (positions, velocities, accelerations) bytes)."""
    dbl = array.array
    return [JointTrajectoryPoint(positions=dbl("d", q), velocities=dbl("d", v), accelerations=dbl("d", a),
                                 time_from_start=Duration(sec=s, nanosec=n, check_fields=False), check_fields=False)
            for (q, v, a), s, n in zip(rows, secs, nsecs)]


def _points_direct(rows, secs, nsecs) -> list:
    """
    Return the points :func:`_points_public` builds, their fields set on the generated slots (7× faster).

    Used only when the message classes have the slots of rosidl's generated Python (checked
    once against :func:`_points_public`: see :data:`_POINTS`).
    """
    new_p, new_d, dbl = JointTrajectoryPoint.__new__, Duration.__new__, array.array
    out = []
    for (q, v, a), s, n in zip(rows, secs, nsecs):
        d = new_d(Duration)
        d._check_fields, d._sec, d._nanosec = False, s, n
        p = new_p(JointTrajectoryPoint)
        p._check_fields = False
        p._positions, p._velocities, p._accelerations = dbl("d", q), dbl("d", v), dbl("d", a)
        p._effort, p._time_from_start = dbl("d"), d
        out.append(p)
    return out


def _choose_points():
    """Return :func:`_points_direct` when it builds what :func:`_points_public` builds, else the latter."""
    rows = [(np.array([0.5, -1.0]).tobytes(), np.array([0.25, 2.0]).tobytes(), np.array([-3.0, 0.0]).tobytes())]
    try:
        if _points_direct(rows, [3], [7]) == _points_public(rows, [3], [7]):
            return _points_direct
    except (AttributeError, TypeError):        # other generated classes: the public way
        pass
    return _points_public


_POINTS = _choose_points()


def trajectory_to_msg(traj: Trajectory, stamp=None, frame_id: str = "") -> JointTrajectory:
    """
    Trajectory → JointTrajectory (positions, velocities, accelerations, time_from_start).

    Each point's arrays are ``array.array('d')`` (as a received message's are; publishing
    copies them whole), built without the per-field checks (the values are float64 by
    construction).  The times as :func:`s_to_duration` rounds them (nearest ns, ties to even).
    """
    msg = JointTrajectory()
    if stamp is not None:
        msg.header.stamp = stamp
    msg.header.frame_id = frame_id
    msg.joint_names = list(traj.joint_names)
    q, v, a = (np.ascontiguousarray(x, dtype=np.float64)
               for x in (traj.positions_rad, traj.velocities_rad_s, traj.accelerations_rad_s2))
    sec, nsec = _sec_nanosec(traj.times_s)
    rows = [(qi.tobytes(), vi.tobytes(), ai.tobytes()) for qi, vi, ai in zip(q, v, a)]
    msg.points = _POINTS(rows, sec.tolist(), nsec.tolist())
    return msg


def split_trajectory_msg(msg: JointTrajectory, joints) -> tuple:
    """
    Return (the trajectory of ``joints``, the trajectory of the others).

    The same points and times, columns picked by name; either is None when it would have no joints.
    """
    names = list(msg.joint_names)

    def pick(cols):
        if not cols:
            return None
        out = JointTrajectory()
        out.header = msg.header
        out.joint_names = [names[c] for c in cols]
        pts = []
        for p in msg.points:
            q = JointTrajectoryPoint()
            q.positions = [p.positions[c] for c in cols]
            if len(p.velocities):
                q.velocities = [p.velocities[c] for c in cols]
            if len(p.accelerations):
                q.accelerations = [p.accelerations[c] for c in cols]
            q.time_from_start = p.time_from_start
            pts.append(q)
        out.points = pts
        return out

    inside = [i for i, n in enumerate(names) if n in joints]
    return pick(inside), pick([i for i in range(len(names)) if i not in inside])


def msg_to_trajectory_arrays(msg: JointTrajectory):
    """
    Convert a JointTrajectory → (names, times (M,), positions (M, n), velocities (M, n) or None).

    Raises ValueError for an empty trajectory, ragged points, NaN, or times that do not
    increase.
    """
    names = tuple(msg.joint_names)
    if not names:
        raise ValueError("joint_trajectory: no joint names")
    if not msg.points:
        raise ValueError("joint_trajectory: no points")
    n = len(names)
    t = np.array([duration_to_s(p.time_from_start) for p in msg.points])
    if any(len(p.positions) != n for p in msg.points):
        raise ValueError(f"joint_trajectory: every point needs {n} positions")
    q = np.array([list(p.positions) for p in msg.points], dtype=float)
    v = None
    if all(len(p.velocities) == n for p in msg.points):
        v = np.array([list(p.velocities) for p in msg.points], dtype=float)
    if not np.all(np.isfinite(q)) or not np.all(np.isfinite(t)):
        raise ValueError("joint_trajectory: NaN or inf in positions or times")
    if len(t) > 1 and np.any(np.diff(t) <= 0.0):
        raise ValueError("joint_trajectory: time_from_start must increase strictly")
    return names, t, q, v


# ------------------------------------------------------------------ grids
def _slice_index(grid, q_rad, slice_axes):
    """Index tuple selecting the 2-D slice over ``slice_axes`` through the node nearest q."""
    node = grid.node_of(np.asarray(q_rad, dtype=float))
    return tuple(slice(None) if d in slice_axes else node[d] for d in range(grid.ndim))


def grid_slice(grid, arr, q_rad, slice_axes=None):
    """
    Return the 2-D slice of an array over the grid (indexed [x, y]) through the node nearest ``q_rad``.

    ``slice_axes`` defaults to the last two planned axes.
    """
    axes = tuple(slice_axes) if slice_axes is not None else (grid.ndim - 2, grid.ndim - 1)
    out = np.asarray(arr)[_slice_index(grid, q_rad, axes)]
    return out if axes[0] < axes[1] else out.T


def potential_slice_values(log_u_slice, occupied_slice, phi_max: float) -> np.ndarray:
    """
    Occupancy values (int8, same shape) of a potential slice.

    Obstacles → 100; free nodes not connected to the goal (log u = -inf) → 99;
    connected free nodes → round(98 · log(1 + φ) / log(1 + φ_max)) with φ = -log u
    (goal 0, so the goal holds the minimum 0; φ_max = the largest finite φ of the
    whole field, so every slice uses the same scale).
    """
    log_u = np.asarray(log_u_slice, dtype=float)
    occ = np.asarray(occupied_slice, dtype=bool)
    phi = -log_u
    finite = np.isfinite(phi) & ~occ
    scale = math.log1p(phi_max) if phi_max > 0 else 1.0
    vals = np.full(log_u.shape, UNREACHABLE, dtype=np.int16)
    vals[finite] = np.clip(np.rint(98.0 * np.log1p(np.maximum(phi[finite], 0.0)) / scale), 0, 98)
    vals[occ] = OBSTACLE
    return vals.astype(np.int8)


def obstacle_slice_values(occupied_slice) -> np.ndarray:
    return np.where(np.asarray(occupied_slice, dtype=bool), OBSTACLE, 0).astype(np.int8)


def grid_slice_to_msg(values_xy, grid, slice_axes, frame_id: str, stamp=None) -> OccupancyGrid:
    """
    Convert a 2-D slice (indexed [x, y]) → OccupancyGrid.

    x = grid axis ``slice_axes[0]`` (columns), y = ``slice_axes[1]`` (rows);
    info.resolution = the x axis step (rad per cell); origin = (lower_x, lower_y) rad;
    width/height = nodes along x/y; data row-major from (lower_x, lower_y).
    """
    vals = np.asarray(values_xy)
    ax, ay = slice_axes
    msg = OccupancyGrid()
    msg.header.frame_id = frame_id
    if stamp is not None:
        msg.header.stamp = stamp
    msg.info.resolution = float(grid.step_rad[ax])
    msg.info.width = int(vals.shape[0])
    msg.info.height = int(vals.shape[1])
    msg.info.origin.position.x = float(grid.lower_rad[ax])
    msg.info.origin.position.y = float(grid.lower_rad[ay])
    msg.info.origin.orientation.w = 1.0
    msg.data = array.array("b", np.ascontiguousarray(vals.T, dtype=np.int8).tobytes())
    return msg


# ------------------------------------------------------------------ markers
def marker_strips(robot, scene, path_rad, n_postures: int = 8) -> list:
    """
    Return the LINE_STRIPs of a planned path and its scene: ``[(ns, id, points (k, 2) m, rgba, width m)]``.

    Arm postures along a path (start blue → goal green), the spacecraft body at the start and the
    goal, the target body and handle, debris; a polygon's strip closed (its first point again).
    """
    strips = []
    path = np.atleast_2d(np.asarray(path_rad, dtype=float))
    idx = np.unique(np.linspace(0, len(path) - 1, min(n_postures, len(path))).round().astype(int))
    pts = robot.forward_kinematics(robot.full(path[idx]))
    for i, (k, p) in enumerate(zip(idx, pts)):
        f = k / max(1, len(path) - 1)
        alpha = 0.4 + 0.6 * (i in (0, len(idx) - 1))
        strips.append(("arm", i, p, (0.1, 0.3 + 0.6 * f, 1.0 - 0.8 * f, alpha), 0.03))

    def closed(poly):
        poly = np.asarray(poly, dtype=float)
        return np.vstack([poly, poly[:1]])
    for i, k in enumerate((0, len(path) - 1)):
        att = robot.full(path[k])[0]
        strips.append(("spacecraft", i, closed(robot.body_polygon_world(att)), (0.7, 0.7, 0.7, 1.0), 0.04))
    if scene.target is not None:
        strips.append(("target", 0, closed(scene.target.body_polygon_m), (1.0, 0.5, 0.0, 1.0), 0.04))
        strips.append(("handle", 0, closed(scene.target.handle_polygon_m), (1.0, 0.1, 0.1, 1.0), 0.02))
    for i, poly in enumerate(scene.debris_m):
        strips.append(("debris", i, closed(poly), (0.8, 0.1, 0.1, 1.0), 0.04))
    return [(ns, i, np.asarray(p, dtype=float).reshape(-1, 2), rgba, w) for ns, i, p, rgba, w in strips]


def markers_msg(strips, frame: str, stamp=None) -> MarkerArray:
    """Return the MarkerArray of :func:`marker_strips`' strips: a DELETEALL, then one LINE_STRIP each."""
    arr = MarkerArray()
    clear = Marker()
    clear.header.frame_id = frame
    clear.action = Marker.DELETEALL
    arr.markers.append(clear)
    for ns, mid, pts, rgba, width in strips:
        m = Marker()
        m.header.frame_id = frame
        if stamp is not None:
            m.header.stamp = stamp
        m.ns, m.id, m.type, m.action = ns, mid, Marker.LINE_STRIP, Marker.ADD
        m.pose.orientation.w = 1.0
        m.scale.x = width
        m.color = ColorRGBA(r=float(rgba[0]), g=float(rgba[1]), b=float(rgba[2]), a=float(rgba[3]))
        m.points = [Point(x=float(x), y=float(y), z=0.0) for x, y in pts]
        arr.markers.append(m)
    return arr


def path_markers(robot, scene, path_rad, frame: str, stamp=None, n_postures: int = 8) -> MarkerArray:
    """Build the markers of a planned path and its scene (:func:`marker_strips`) as a MarkerArray."""
    return markers_msg(marker_strips(robot, scene, path_rad, n_postures), frame, stamp)


# ------------------------------------------------------------------ diagnostics
def _level_byte(level) -> bytes:
    """Return a status level (DiagnosticStatus.OK/WARN/ERROR/STALE: one byte, or its int) as the one byte sent."""
    b = level if isinstance(level, bytes) else bytes([int(level)])
    if len(b) != 1:
        raise ValueError(f"level: expected one byte, got {level!r}")
    return b


def diagnostic_array(statuses, stamp=None, hardware_id: str = "") -> DiagnosticArray:
    """
    Build a DiagnosticArray of ``[(name, level, message, values dict)]``; ``level`` is DiagnosticStatus.OK/WARN/ERROR.

    Messages and values are sent whole (never cut).
    """
    arr = DiagnosticArray()
    if stamp is not None:
        arr.header.stamp = stamp
    for name, level, message, values in statuses:
        st = DiagnosticStatus()
        st.level = _level_byte(level)
        st.name = name
        st.message = message
        st.hardware_id = hardware_id
        st.values = [KeyValue(key=str(k), value=str(v)) for k, v in values.items()]
        arr.status.append(st)
    return arr


# ------------------------------------------------------------------ action
def plan_result(result_type, code: str, reason: str = "", trajectory=None, plan=None, attitude_trajectory=None):
    """
    Build a PlanCapture.Result.

    ``code`` (a planner code or "superseded") → its constant, the trajectory message (empty unless
    ok), the stage times and the clearance of ``plan`` (a PlanResult) when there is one.
    """
    res = result_type()
    const = code.upper()
    if not hasattr(result_type, const):
        raise ValueError(f"no PlanCapture result code for {code!r}")
    res.error_code = int(getattr(result_type, const))
    res.error_name = code
    res.reason = reason or ""
    if trajectory is not None:
        res.trajectory = trajectory
    if attitude_trajectory is not None:
        res.attitude_trajectory = attitude_trajectory
    res.min_clearance_m = math.nan
    if plan is not None:
        res.stage_names = [str(k) for k in plan.timings_s]
        res.stage_times_s = [float(v) for v in plan.timings_s.values()]
        if plan.min_clearance_m is not None and math.isfinite(plan.min_clearance_m):
            res.min_clearance_m = float(plan.min_clearance_m)
    return res


def slice_axes_and_point(robot, start_rad, use_current_attitude: bool = True, slice_attitude_deg: float = 0.0):
    """
    Return (x axis, y axis, q at which to slice) of the published grids, or None (under 2 planned joints).

    The last two planned joints; the others at the plan's start, or (``use_current_attitude``
    false, more than 2 joints) the first at ``slice_attitude_deg``.
    """
    dof = robot.dof
    if dof < 2:
        return None
    q = np.array(start_rad, dtype=float)
    if dof > 2 and not use_current_attitude:
        q[0] = math.radians(slice_attitude_deg)
    q = robot.validate_q(q, "slice")
    return dof - 2, dof - 1, q


class GridSlices:
    """
    The C-space and potential grid messages of the last plan (see :func:`plan_visuals`).

    A replan from the cached C-space and field slices the same arrays through the same
    node: its messages are the last ones, restamped, not sliced and converted again.
    Holds the C-space and field it sliced (compared by identity: cached objects).
    """

    def __init__(self):
        self._key = None
        self._msgs = (None, None)

    def get(self, key, stamp):
        """Return the held (cspace, potential) messages restamped when ``key`` is the held key, else None."""
        if self._key is None or len(key) != len(self._key) or not all(
                a is b if i < 2 else a == b for i, (a, b) in enumerate(zip(key, self._key))):
            return None
        for msg in self._msgs:
            if msg is not None and stamp is not None:
                msg.header.stamp = stamp
        return self._msgs

    def put(self, key, msgs) -> None:
        self._key, self._msgs = key, msgs


def plan_visuals(robot, scene, res, frame: str, grid_frame: str, stamp=None, use_current_attitude: bool = True,
                 slice_attitude_deg: float = 0.0, slices: GridSlices | None = None) -> tuple:
    """
    Return the visual messages of an ok plan (a ``PlanResult``): (markers, cspace grid, potential grid).

    The markers in the planning ``frame`` (serialized where that was checked:
    :func:`markers_payload`); the grids (None without a C-space or field, or under 2 planned
    joints) sliced by :func:`slice_axes_and_point` in ``grid_frame``.
    ``slices``: the last plan's grids (:class:`GridSlices`), reused (restamped) when this plan
    has the same C-space and field objects and the slice passes through the same node.
    """
    markers = markers_payload(marker_strips(robot, scene, res.path_rad), frame, stamp)
    sl = slice_axes_and_point(robot, res.start_rad, use_current_attitude, slice_attitude_deg)
    if sl is None or res.cspace is None:
        return markers, None, None
    ax, ay, q = sl
    grid = res.cspace.grid
    key = (res.cspace, res.field, grid_frame, (ax, ay), _slice_index(grid, q, (ax, ay)))
    held = None if slices is None else slices.get(key, stamp)
    if held is not None:
        return (markers, *held)
    occ = grid_slice(grid, res.cspace.occupied, q, (ax, ay))
    cspace = grid_slice_to_msg(obstacle_slice_values(occ), grid, (ax, ay), grid_frame, stamp)
    potential = None
    if res.field is not None:
        phi = res.field.potential()
        finite = np.isfinite(phi)
        phi_max = float(phi[finite].max()) if finite.any() else 0.0
        log_u = grid_slice(grid, res.field.log_u, q, (ax, ay))
        focc = grid_slice(grid, res.field.occupied, q, (ax, ay))
        potential = grid_slice_to_msg(potential_slice_values(log_u, focc, phi_max), grid, (ax, ay), grid_frame,
                                      stamp)
    if slices is not None:
        slices.put(key, (cspace, potential))
    return markers, cspace, potential


def predicted_drift_msg(publication):
    """
    Return the free-floating drift of a ``session.Publication`` as a JointTrajectory, or None.

    Joints: the attitude (rad, as it will drift), ``body_x`` and ``body_y`` (the body centre's
    displacement, inertial frame, m); the publication's stamp.  Reported in the action's
    result (its ``attitude_trajectory``), never published: nothing commands the attitude.
    """
    if publication is None or publication.predicted_drift is None:
        return None
    return trajectory_to_msg(publication.predicted_drift, ns_to_time(publication.stamp_ns))


def publication_msgs(publication) -> tuple:
    """
    Return (arm message, attitude message) of a ``session.Publication`` (None: no publication, or a part not planned).

    One stamp for both (the controllers start them together); the points as the session made them.
    """
    if publication is None:
        return None, None
    stamp = ns_to_time(publication.stamp_ns)
    return tuple(None if part is None else trajectory_to_msg(part, stamp)
                 for part in (publication.arm, publication.attitude))


# ------------------------------------------------------------------ trajectories as serialized bytes
#: a trajectory's per-point columns, in a point's order
_ROWS = ("positions_rad", "velocities_rad_s", "accelerations_rad_s2")
#: CDR's encapsulation header: plain CDR, little endian (what rmw_fastrtps and rmw_cyclonedds write)
_CDR_LE = b"\x00\x01\x00\x00"


def _cdr_point_layout(start: int, n: int) -> tuple:
    """
    Return (offsets, size) of one JointTrajectoryPoint of ``n`` joints serialized at payload offset ``start``.

    ``offsets``: byte offsets from the point's start of the positions', velocities' and
    accelerations' (count, first value), then of effort's count (empty), sec and nanosec
    (CDR: each primitive aligned to its size from the payload's start; no values, no padding).
    """
    o, offs = start, []
    for _ in range(3):
        o += -o % 4
        count = o
        o += 4
        if n:
            o += -o % 8
        offs.append((count - start, o - start))
        o += 8 * n
    o += -o % 4
    offs.append(o - start)                   # effort: count 0
    offs.append(o + 4 - start)               # time_from_start.sec
    offs.append(o + 8 - start)               # time_from_start.nanosec
    return tuple(offs), o + 12 - start


#: a CDR count or length: uint32, little endian
_CDR_U32 = struct.Struct("<I").pack


def _cdr_align(out: bytearray, size: int) -> None:
    """Append the zero bytes that align the next primitive of ``size`` bytes (from the payload's start)."""
    out += b"\0" * (-(len(out) - 4) % size)


def _cdr_count(out: bytearray, n: int) -> None:
    """Append a sequence's element count (uint32, aligned to 4 from the payload's start)."""
    _cdr_align(out, 4)
    out += _CDR_U32(n)


def _cdr_string(out: bytearray, text: str) -> None:
    """
    Append a CDR string (aligned count with the NUL, the bytes, the NUL).

    Up to its first NUL character, as rclpy converts a message's string (a C string).
    """
    raw = text.encode().partition(b"\0")[0]
    _cdr_count(out, len(raw) + 1)
    out += raw
    out += b"\0"


def trajectory_cdr(traj, stamp=None, frame_id: str = "") -> bytes:
    """
    Return :func:`trajectory_to_msg`'s message serialized (CDR, as a publisher sends it), made from the arrays.

    ``traj``: a Trajectory or ``adapters.TrajectoryPart`` (joint_names, times_s (K,), positions,
    velocities, accelerations (K, n)); ``stamp``: builtin_interfaces/Time or None (zero).  A
    publisher sends these bytes as they are (``Publisher.publish(bytes)``): no message objects,
    no per-point conversion.  Checked once: rclpy deserializes it into that message
    (:data:`_TRAJECTORIES_SERIALIZED`).
    """
    out = _cdr_header(stamp, frame_id)
    names = list(traj.joint_names)
    _cdr_count(out, len(names))
    for name in names:
        _cdr_string(out, name)
    rows = [np.ascontiguousarray(getattr(traj, f), dtype="<f8").reshape(len(traj.times_s), len(names))
            for f in _ROWS]
    k, n = rows[0].shape
    _cdr_count(out, k)
    sec, nsec = _sec_nanosec(traj.times_s)
    start = len(out) - 4
    # every point after the first starts at the same offset modulo 8: one layout for all of them
    first, first_size = _cdr_point_layout(start, n)
    rest, size = _cdr_point_layout(start + first_size, n)
    buf = np.zeros(first_size + (k - 1) * size if k else 0, np.uint8)
    for lo, hi, layout, width in ((0, min(k, 1), first, first_size), (1, k, rest, size)):
        if hi <= lo:
            continue
        pts = buf[(0 if lo == 0 else first_size):][:(hi - lo) * width].reshape(hi - lo, width)
        for (count, values), x in zip(layout[:3], rows):
            pts[:, count:count + 4] = np.frombuffer(np.uint32(n).tobytes(), np.uint8)
            pts[:, values:values + 8 * n] = x[lo:hi].view(np.uint8).reshape(hi - lo, 8 * n)
        pts[:, layout[4]:layout[4] + 4] = sec[lo:hi].astype("<i4")[:, None].view(np.uint8)
        pts[:, layout[5]:layout[5] + 4] = nsec[lo:hi].astype("<u4")[:, None].view(np.uint8)
    return bytes(out) + buf.tobytes()


def _cdr_header(stamp, frame_id: str) -> bytearray:
    """Return a payload's encapsulation header and its std_msgs/Header (``stamp``: Time or None: zero)."""
    out = bytearray(_CDR_LE)
    out += struct.pack("<iI", 0 if stamp is None else stamp.sec, 0 if stamp is None else stamp.nanosec)
    _cdr_string(out, frame_id)
    return out


def diagnostic_cdr(statuses, stamp=None, hardware_id: str = "") -> bytes:
    """
    Return :func:`diagnostic_array`'s message serialized (CDR, as a publisher sends it), made from the statuses.

    ``statuses``, ``stamp``, ``hardware_id``: as for :func:`diagnostic_array`.  No message objects
    (a KeyValue each); checked once: rclpy deserializes it into that message (:data:`_DIAGNOSTICS_SERIALIZED`).
    """
    out = _cdr_header(stamp, "")
    _cdr_count(out, len(statuses))
    for name, level, message, values in statuses:
        out += _level_byte(level)
        _cdr_string(out, name)
        _cdr_string(out, message)
        _cdr_string(out, hardware_id)
        _cdr_count(out, len(values))
        for key, value in values.items():
            _cdr_string(out, str(key))
            _cdr_string(out, str(value))
    return bytes(out)


def markers_cdr(strips, frame: str, stamp=None) -> bytes:
    """
    Return :func:`markers_msg`'s message serialized (CDR, as a publisher sends it), made from the strips.

    ``strips``: :func:`marker_strips`' list; ``stamp``: builtin_interfaces/Time or None (zero).  No
    message objects: about a fifth of the time of building and serializing the MarkerArray.
    Checked once: rclpy deserializes it into that message (:data:`_MARKERS_SERIALIZED`).
    """
    sec, nsec = (0, 0) if stamp is None else (stamp.sec, stamp.nanosec)
    out = bytearray(_CDR_LE)
    _cdr_count(out, len(strips) + 1)
    # the DELETEALL first: every field at its default (no stamp, no width, no colour, no points)
    for k, (ns, mid, xy, rgba, width) in enumerate([("", 0, np.zeros((0, 2)), (0.0,) * 4, 0.0)] + list(strips)):
        kind, action, stamp_k = ((0, Marker.DELETEALL, (0, 0)) if k == 0
                                 else (Marker.LINE_STRIP, Marker.ADD, (sec, nsec)))
        _cdr_align(out, 4)
        out += struct.pack("<iI", *stamp_k)
        _cdr_string(out, frame)
        _cdr_string(out, ns)
        _cdr_align(out, 4)
        out += struct.pack("<iii", mid, kind, action)
        _cdr_align(out, 8)                        # pose (orientation w 1), scale (x the width), colour, lifetime 0
        out += struct.pack("<7d3d4fiI?", 0, 0, 0, 0, 0, 0, 1.0, width, 0, 0, *map(float, rgba), 0, 0, False)
        pts = np.column_stack([xy, np.zeros(len(xy))])
        _cdr_count(out, len(pts))
        if len(pts):
            _cdr_align(out, 8)
            out += np.ascontiguousarray(pts, dtype="<f8").tobytes()
        _cdr_count(out, 0)                        # colors
        _cdr_string(out, "")                      # texture_resource
        _cdr_align(out, 4)
        out += struct.pack("<iI", 0, 0)           # texture: its header's stamp
        _cdr_string(out, "")                      # its frame_id
        _cdr_string(out, "")                      # its format
        _cdr_count(out, 0)                        # its data
        _cdr_count(out, 0)                        # uv_coordinates
        _cdr_string(out, "")                      # text
        _cdr_string(out, "")                      # mesh_resource
        _cdr_string(out, "")                      # mesh_file: filename
        _cdr_count(out, 0)                        # its data
        out += b"\0"                              # mesh_use_embedded_materials
    return bytes(out)


def _same_as_rclpy(cdr, build, msg_type, cases) -> bool:
    """
    Tell whether ``cdr(*case)`` deserializes into what rclpy's round trip of ``build(*case)`` gives, in every case.

    rclpy deserializes them as a subscriber does; its own serialization leaves its padding bytes
    uninitialised, so the bytes themselves are not compared.  False where rclpy cannot say, or
    raises (any doubt: the messages are published).
    """
    try:
        from rclpy.serialization import deserialize_message, serialize_message
    except ImportError:          # no rclpy serialization: messages are published
        return False
    for case in cases:
        try:
            if deserialize_message(cdr(*case), msg_type) != \
                    deserialize_message(serialize_message(build(*case)), msg_type):
                return False
        except Exception:        # noqa: BLE001 - any doubt: messages
            return False
    return True


def _diagnostics_match() -> bool:
    """
    Tell whether :func:`diagnostic_cdr`'s bytes are the message they stand for.

    What a subscriber gets of :func:`diagnostic_array`'s message (a string up to a NUL), on a few
    shapes (:func:`_same_as_rclpy`).
    """
    cases = (([], None, ""), ([("n", DiagnosticStatus.WARN, "m", {})], Time(sec=3, nanosec=4), "h"),
             ([("node: planner", b"\x02", "failed: ü ✓", {"a": 1, "bb": "x\0y", "ccc": ""}),
               ("node: input", DiagnosticStatus.OK, "", {"k": [1.5, "z"]})],
              Time(sec=1_700_000_000, nanosec=999_999_999), "hw"))
    return _same_as_rclpy(diagnostic_cdr, diagnostic_array, DiagnosticArray, cases)


def _markers_match() -> bool:
    """
    Tell whether :func:`markers_cdr`'s bytes are the message they stand for.

    What a subscriber gets of :func:`markers_msg`'s message (the colours as float32), on a few
    shapes (:func:`_same_as_rclpy`): no strip, strips of 0, 1 and several points, namespaces and
    frames of every length modulo 4, a zero and a set stamp.
    """
    rng = np.random.default_rng(0)
    shapes = ([], [("a", 0, np.zeros((0, 2)), (0.1, 0.2, 0.3, 0.4), 0.03)],
              [(ns, i, rng.normal(size=(k, 2)), tuple(rng.uniform(size=4)), float(rng.uniform()))
               for i, (ns, k) in enumerate((("arm", 1), ("ab", 5), ("abc", 2), ("abcd", 0), ("spacecraft", 7)))])
    stamps = (None, Time(sec=3, nanosec=4), Time(sec=1_700_000_000, nanosec=999_999_999))
    return _same_as_rclpy(markers_cdr, markers_msg, MarkerArray, zip(shapes, ("", "map", "world"), stamps))


def _trajectories_match() -> bool:
    """
    Tell whether :func:`trajectory_cdr`'s bytes are the messages they stand for.

    What a subscriber gets of :func:`trajectory_to_msg`'s messages, on a few shapes
    (:func:`_same_as_rclpy`).
    """
    rng = np.random.default_rng(0)
    cases = []
    for k, names, frame in ((3, ("a",), ""), (2, ("shoulder", "elbow"), "world"), (0, ("j0", "j1", "j2"), "ab"),
                            (5, ("x1", "y22", "z333"), ""), (1, ("attitude",), "map")):
        t = SimpleNamespace(joint_names=tuple(names), times_s=np.cumsum(rng.uniform(0.1, 1.0, k)),
                            **{f: rng.normal(size=(k, len(names))) for f in _ROWS})
        cases.append((t, Time(sec=1_700_000_000 + k, nanosec=123_456_789), frame))
    return _same_as_rclpy(trajectory_cdr, trajectory_to_msg, JointTrajectory, cases)


#: the node publishes :func:`trajectory_cdr`'s bytes (:func:`_trajectories_match`), else :func:`trajectory_to_msg`'s
_TRAJECTORIES_SERIALIZED = _trajectories_match()
#: the node publishes :func:`diagnostic_cdr`'s bytes (:func:`_diagnostics_match`), else :func:`diagnostic_array`'s
_DIAGNOSTICS_SERIALIZED = _diagnostics_match()
#: the node publishes :func:`markers_cdr`'s bytes (:func:`_markers_match`), else :func:`markers_msg`'s
_MARKERS_SERIALIZED = _markers_match()


def markers_payload(strips, frame: str, stamp=None):
    """Return what a publisher sends for :func:`markers_msg`: its bytes (:func:`markers_cdr`) or the message."""
    return (markers_cdr if _MARKERS_SERIALIZED else markers_msg)(strips, frame, stamp)


def diagnostic_payload(statuses, stamp=None, hardware_id: str = ""):
    """Return what a publisher sends for :func:`diagnostic_array`: its bytes (:func:`diagnostic_cdr`) or the message."""
    return (diagnostic_cdr if _DIAGNOSTICS_SERIALIZED else diagnostic_array)(statuses, stamp, hardware_id)


def publication_payloads(publication) -> tuple:
    """
    Return what a publisher sends for :func:`publication_msgs`: (arm, attitude), each the serialized message (bytes).

    The same messages, serialized from the arrays (:func:`trajectory_cdr`) where that was checked
    to match rclpy's serialization, else the messages themselves; None as there.
    """
    if not _TRAJECTORIES_SERIALIZED:
        return publication_msgs(publication)
    if publication is None:
        return None, None
    stamp = ns_to_time(publication.stamp_ns)
    return tuple(None if part is None else trajectory_cdr(part, stamp)
                 for part in (publication.arm, publication.attitude))
