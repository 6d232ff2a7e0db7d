"""ros_conversions: messages ↔ core types, without a running graph."""

import os
import math

import numpy as np
import pytest
from diagnostic_msgs.msg import DiagnosticStatus
from geometry_msgs.msg import PoseStamped
from sensor_msgs.msg import JointState

from spacerobot_planner.ros import conversions as conv
from spacerobot_planner.config import load_scenario
from spacerobot_planner.cspace import GridSpec
from spacerobot_planner.scene import Target
from spacerobot_planner.trajectory import time_parameterize
from conftest import CONFIG_DIR


def _pose(x=-3.27, y=-2.6, yaw=0.0, frame="world", quat=None):
    m = PoseStamped()
    m.header.frame_id = frame
    m.pose.position.x, m.pose.position.y = x, y
    q = quat if quat is not None else conv.yaw_to_quaternion(yaw)
    (m.pose.orientation.x, m.pose.orientation.y, m.pose.orientation.z, m.pose.orientation.w) = q
    return m


def test_pose_to_target_roundtrip():
    t = conv.pose_to_target(_pose(1.0, 2.0, 0.7), "world", Target(body_side_m=2.0))
    assert t.center_m == (1.0, 2.0) and math.isclose(t.yaw_rad, 0.7)
    assert t.body_side_m == 2.0
    back = conv.target_to_pose(t, "world")
    assert math.isclose(conv.pose_to_target(back, "world").yaw_rad, 0.7)


def test_slightly_non_unit_quaternion_is_normalised():
    q = np.array(conv.yaw_to_quaternion(0.5)) * 1.005
    assert math.isclose(conv.pose_to_target(_pose(quat=q), "world").yaw_rad, 0.5)


@pytest.mark.parametrize("pose, match", [
    (_pose(frame="map"), "frame 'map'"),
    (_pose(x=math.nan), "NaN"),
    (_pose(y=math.inf), "NaN or inf"),
    (_pose(quat=(0.0, 0.0, 0.0, 0.0)), "unit quaternion"),
    (_pose(quat=(0.0, 0.0, 0.0, 2.0)), "unit quaternion"),
    (_pose(quat=(0.0, 0.0, math.nan, 1.0)), "NaN"),
    (_pose(quat=(math.sin(0.2), 0.0, 0.0, math.cos(0.2))), "tilted"),
])
def test_bad_poses_are_rejected_with_a_reason(pose, match):
    with pytest.raises(ValueError, match=match):
        conv.pose_to_target(pose, "world")


def _js(names, pos):
    m = JointState()
    m.name, m.position = list(names), [float(v) for v in pos]
    return m


def test_joint_state_matched_by_name_extra_ignored():
    q = conv.joint_state_positions(_js(["elbow", "x", "shoulder"], [1, 2, 3]), ("shoulder", "elbow"))
    np.testing.assert_array_equal(q, [3.0, 1.0])


@pytest.mark.parametrize("msg, match", [
    (_js(["shoulder"], [1.0]), "missing joint"),
    (_js(["shoulder", "elbow"], [1.0]), "2 names but 1 positions"),
    (_js(["shoulder", "elbow"], [1.0, math.nan]), "not finite"),
    (_js(["shoulder", "shoulder"], [1.0, 2.0]), "twice"),
])
def test_bad_joint_states(msg, match):
    with pytest.raises(ValueError, match=match):
        conv.joint_state_positions(msg, ("shoulder", "elbow"))


def test_trajectory_roundtrip():
    traj = time_parameterize(np.array([[0.0, 0.0], [0.3, -0.2]]), [1.0, 1.0], [2.0, 2.0], ("a", "b"))
    msg = conv.trajectory_to_msg(traj)
    assert msg.joint_names == ["a", "b"] and len(msg.points) == len(traj)
    names, t, q, v = conv.msg_to_trajectory_arrays(msg)
    assert names == ("a", "b")
    np.testing.assert_allclose(t, traj.times_s, atol=1e-9)
    np.testing.assert_array_equal(q, traj.positions_rad)
    np.testing.assert_array_equal(v, traj.velocities_rad_s)


def test_potential_values_and_grid_layout():
    grid = GridSpec((4, 3), (-1.0, -2.0), (1.0, 1.0), (False, False))   # shape (5, 4)
    log_u = -np.arange(20, dtype=float).reshape(5, 4)
    occ = np.zeros((5, 4), bool)
    occ[2, 1] = True
    log_u[2, 1] = -np.inf
    log_u[4, 3] = -np.inf                              # free but unreachable
    vals = conv.potential_slice_values(log_u, occ, phi_max=18.0)
    assert vals[0, 0] == 0 and vals.min() == 0
    assert vals[2, 1] == conv.OBSTACLE and vals[4, 3] == conv.UNREACHABLE
    assert np.all(vals[~occ & np.isfinite(log_u)] <= 98)
    msg = conv.grid_slice_to_msg(vals, grid, (0, 1), "world")
    assert (msg.info.width, msg.info.height) == (5, 4)
    assert math.isclose(msg.info.resolution, 0.5, rel_tol=1e-6)
    assert (msg.info.origin.position.x, msg.info.origin.position.y) == (-1.0, -2.0)
    data = np.array(msg.data).reshape(msg.info.height, msg.info.width)
    assert data[1, 2] == conv.OBSTACLE                   # row = y index, column = x index


def test_grid_slice_3d_takes_last_two_axes_at_the_nearest_node():
    grid = GridSpec((4, 4, 4), (-math.pi,) * 3, (math.pi,) * 3, (True, False, False))
    arr = np.arange(np.prod(grid.shape)).reshape(grid.shape)
    s = conv.grid_slice(grid, arr, np.array([-math.pi / 2, 0.0, 0.0]))
    np.testing.assert_array_equal(s, arr[1])


def test_markers_and_diagnostics():
    sc = load_scenario(os.path.join(CONFIG_DIR, "paper_3dof.yaml"))
    path = np.linspace(sc.start_rad, sc.goal_rad, 20)
    arr = conv.path_markers(sc.robot, sc.scene, path, "world", n_postures=5)
    ns = [m.ns for m in arr.markers[1:]]
    assert ns.count("arm") == 5 and "target" in ns and "handle" in ns and "spacecraft" in ns
    assert all(m.header.frame_id == "world" for m in arr.markers)
    long_reason = "x" * 5000
    d = conv.diagnostic_array([("p", DiagnosticStatus.ERROR, f"failed: {long_reason}", {"reason": long_reason}),
                               ("i", DiagnosticStatus.OK, "inputs ok", {})])
    assert [s.level for s in d.status] == [DiagnosticStatus.ERROR, DiagnosticStatus.OK]
    assert d.status[0].values[0].key == "reason"
    assert d.status[0].values[0].value == long_reason and d.status[0].message.endswith(long_reason)


def test_plan_result_codes_mirror_the_planner_codes():
    """Every planner code has its PlanCapture constant, and the values follow CODES' order."""
    from spacerobot_planner.planner import CODES
    from spacerobot_planner_interfaces.action import PlanCapture
    for i, code in enumerate(CODES):
        assert getattr(PlanCapture.Result, code.upper()) == i
        r = conv.plan_result(PlanCapture.Result, code, "why")
        assert r.error_code == i and r.error_name == code and r.reason == "why"
        assert len(r.trajectory.points) == 0 and math.isnan(r.min_clearance_m)
    assert conv.plan_result(PlanCapture.Result, "superseded").error_code == PlanCapture.Result.SUPERSEDED
    from spacerobot_planner.session import JOIN_FAILED
    assert conv.plan_result(PlanCapture.Result, JOIN_FAILED).error_code == PlanCapture.Result.JOIN_FAILED == 11
    with pytest.raises(ValueError, match="no PlanCapture result code"):
        conv.plan_result(PlanCapture.Result, "bogus")


def _oracle_points(times_s, q, v, a):
    """Build the points through the public setters, lists of floats; time by Python's round (ties to even)."""
    from builtin_interfaces.msg import Duration
    from trajectory_msgs.msg import JointTrajectoryPoint
    out = []
    for t, qi, vi, ai in zip(times_s, q, v, a):
        p = JointTrajectoryPoint()
        p.positions = [float(x) for x in qi]
        p.velocities = [float(x) for x in vi]
        p.accelerations = [float(x) for x in ai]
        ns = round(float(t) * 1e9)
        p.time_from_start = Duration(sec=ns // 10 ** 9, nanosec=ns % 10 ** 9)
        out.append(p)
    return out


def test_trajectory_msg_points_equal_a_plain_build_and_survive_serialization():
    """Both ways of building points (slots, constructors) give the points a plain build gives; they serialize."""
    from rclpy.serialization import deserialize_message, serialize_message
    from trajectory_msgs.msg import JointTrajectory
    from spacerobot_planner.adapters import TrajectoryPart
    rng = np.random.default_rng(7)
    k = 57
    t = np.concatenate([[0.0], np.cumsum(rng.uniform(1e-3, 0.4, k - 1))])
    t[3], t[4] = 1.0000000005, 2.0000000015           # half-ns ties
    q, v, a = rng.normal(size=(3, k, 3))
    part = TrajectoryPart(("j0", "j1", "j2"), t, q, v, a)
    oracle = _oracle_points(t, q, v, a)
    msg = conv.trajectory_to_msg(part, conv.ns_to_time(5 * 10 ** 9 + 3), "world")
    assert list(msg.points) == oracle and msg.joint_names == ["j0", "j1", "j2"]
    assert (msg.header.stamp.sec, msg.header.stamp.nanosec, msg.header.frame_id) == (5, 3, "world")
    rows = [(qi.tobytes(), vi.tobytes(), ai.tobytes()) for qi, vi, ai in zip(q, v, a)]
    ns = [round(float(x) * 1e9) for x in t]
    secs, nsecs = [n // 10 ** 9 for n in ns], [n % 10 ** 9 for n in ns]
    assert conv._points_public(rows, secs, nsecs) == oracle
    assert conv._points_direct(rows, secs, nsecs) == oracle
    back = deserialize_message(serialize_message(msg), JointTrajectory)
    assert list(back.points) == oracle and len(back.points[0].effort) == 0


@pytest.mark.parametrize("joints,k", [(("j0", "j1", "j2"), 57), (("shoulder", "elbow"), 1), (("attitude",), 12),
                                      (("attitude",), 0)])
def test_serialized_trajectory_is_the_message_a_subscriber_gets(joints, k):
    """The bytes the node publishes deserialize (as a subscriber does) into the message a plain build gives."""
    from rclpy.serialization import deserialize_message
    from trajectory_msgs.msg import JointTrajectory
    from spacerobot_planner.adapters import TrajectoryPart
    from spacerobot_planner.session import Publication
    rng = np.random.default_rng(11 + k)
    t = np.concatenate([[0.0], np.cumsum(rng.uniform(1e-3, 0.4, max(k - 1, 0)))])[:k]
    if k > 4:
        t[3], t[4] = 1.0000000005, 2.0000000015       # half-ns ties
    q, v, a = rng.normal(size=(3, k, len(joints)))
    part = TrajectoryPart(joints, t, q, v, a)
    raw = conv.trajectory_cdr(part, conv.ns_to_time(7 * 10 ** 9 + 5), "world")
    back = deserialize_message(raw, JointTrajectory)
    assert list(back.points) == _oracle_points(t, q, v, a) and back.joint_names == list(joints)
    assert (back.header.stamp.sec, back.header.stamp.nanosec, back.header.frame_id) == (7, 5, "world")
    assert all(len(p.effort) == 0 for p in back.points)
    # what the node publishes: these bytes (checked once at import: this machine's rmw), else the messages
    pub = Publication(9 * 10 ** 9, part, None)
    arm, att = conv.publication_payloads(pub)
    assert att is None and conv._TRAJECTORIES_SERIALIZED
    assert deserialize_message(arm, JointTrajectory) == conv.publication_msgs(pub)[0]


@pytest.mark.parametrize("config,n_postures,frame", [("paper_3dof", 5, "world"), ("paper_2dof", 8, "map"),
                                                     ("servicer_4joint", 1, "base_link_x")])
def test_serialized_markers_are_the_path_and_scene(config, n_postures, frame):
    """
    The markers' bytes the node publishes: the arm at postures along the path, the bodies, the target.

    Judged after rclpy deserializes them, against the test's own geometry (``oracles.arm_points``,
    ``oracles.body_polygon``) and against what a subscriber gets of the message build.
    """
    from rclpy.serialization import deserialize_message, serialize_message
    from builtin_interfaces.msg import Time
    from visualization_msgs.msg import Marker, MarkerArray
    from oracles import arm_points, body_polygon
    sc = load_scenario(os.path.join(CONFIG_DIR, f"{config}.yaml"))
    robot = sc.robot
    rng = np.random.default_rng(5)
    path = np.linspace(sc.start_rad, sc.start_rad + rng.uniform(-2.0, 2.0, robot.dof), 23)
    stamp = Time(sec=1_700_000_123, nanosec=456)
    strips = conv.marker_strips(robot, sc.scene, path, n_postures)
    got = deserialize_message(conv.markers_cdr(strips, frame, stamp), MarkerArray)
    assert got == deserialize_message(serialize_message(conv.markers_msg(strips, frame, stamp)), MarkerArray)
    assert conv._MARKERS_SERIALIZED             # so the node publishes these bytes
    clear, *strips_got = got.markers
    assert clear.action == Marker.DELETEALL and clear.header.frame_id == frame
    assert all(m.header.frame_id == frame and (m.header.stamp.sec, m.header.stamp.nanosec) == (1_700_000_123, 456)
               and m.type == Marker.LINE_STRIP and m.action == Marker.ADD and m.pose.orientation.w == 1.0
               for m in strips_got)

    def xyz(m):
        p = np.array([[q.x, q.y, q.z] for q in m.points])
        assert np.all(p[:, 2] == 0.0)
        return p[:, :2]
    arms = [m for m in strips_got if m.ns == "arm"]
    postures = sorted(set(int(round(x)) for x in np.linspace(0, len(path) - 1, n_postures)))
    assert [m.id for m in arms] == list(range(len(postures)))
    for m, k in zip(arms, postures):
        np.testing.assert_allclose(xyz(m), arm_points(robot, robot.full(path[k])), atol=1e-12)
    bodies = [m for m in strips_got if m.ns == "spacecraft"]
    for m, k in zip(bodies, (0, len(path) - 1)):
        outline = body_polygon(robot, robot.full(path[k])[0])
        np.testing.assert_allclose(xyz(m), np.vstack([outline, outline[:1]]), atol=1e-12)
    assert len(bodies) == 2
    target = [m for m in strips_got if m.ns == "target"]
    poly = np.asarray(sc.scene.target.body_polygon_m)
    np.testing.assert_array_equal(xyz(target[0]), np.vstack([poly, poly[:1]]))
    assert len([m for m in strips_got if m.ns == "debris"]) == len(sc.scene.debris_m)


@pytest.mark.parametrize("statuses,stamp,hw", [
    ([], None, ""),
    ([("p", DiagnosticStatus.ERROR, "failed: " + "x" * 5000, {"reason": "x" * 5000}),
      ("i", DiagnosticStatus.OK, "inputs ok", {})], (1_700_000_000, 999_999_999), "spacerobot_planner"),
    ([("node: planner", b"\x01", "ünïcode ✓ planned",
       {"goal_deg": [1.5, -2.25, 3.0], "repairs": 0, "a\0b": "c\0d", "empty": ""}),
      ("node: input", DiagnosticStatus.STALE, "", {"rejected_total": 7})], (0, 1), "h"),
])
def test_serialized_diagnostics_are_the_message_a_subscriber_gets(statuses, stamp, hw):
    """The bytes the node publishes on /diagnostics deserialize into what a subscriber gets of the plain build."""
    from diagnostic_msgs.msg import DiagnosticArray
    from rclpy.serialization import deserialize_message, serialize_message
    from builtin_interfaces.msg import Time
    stamp = None if stamp is None else Time(sec=stamp[0], nanosec=stamp[1])
    got = deserialize_message(conv.diagnostic_cdr(statuses, stamp, hw), DiagnosticArray)
    want = deserialize_message(serialize_message(conv.diagnostic_array(statuses, stamp, hw)), DiagnosticArray)
    assert got == want
    assert [st.name for st in got.status] == [name for name, *_ in statuses]
    assert [len(st.values) for st in got.status] == [len(v) for *_, v in statuses]
    assert conv._DIAGNOSTICS_SERIALIZED         # so the node publishes these bytes


def _fake_result(grid, rng, cspace=None, field=None):
    from types import SimpleNamespace
    occ = rng.uniform(size=grid.shape) < 0.2
    log_u = np.where(occ, -np.inf, -rng.uniform(0.0, 30.0, size=grid.shape))
    cspace = cspace or SimpleNamespace(grid=grid, occupied=occ)
    field = field or SimpleNamespace(occupied=occ, log_u=log_u, potential=lambda: -log_u)
    return SimpleNamespace(cspace=cspace, field=field, path_rad=np.zeros((3, 3)), start_rad=np.zeros(3))


def test_grid_slices_are_reused_only_for_the_same_cspace_field_and_slice():
    """A cached replan's grids are the last ones restamped; another C-space, field or slice node rebuilds them."""
    from types import SimpleNamespace
    sc = load_scenario(os.path.join(CONFIG_DIR, "paper_3dof.yaml"))
    robot = sc.robot
    grid = GridSpec((6, 5, 5), tuple(robot.planned_lower_rad), tuple(robot.planned_upper_rad),
                    tuple(robot.planned_periodic))
    rng = np.random.default_rng(3)
    res = _fake_result(grid, rng)
    res.path_rad = np.linspace(sc.start_rad, sc.goal_rad, 5)
    slices = conv.GridSlices()

    def both(r, stamp_ns, **kw):
        stamp = conv.ns_to_time(stamp_ns)
        fresh = conv.plan_visuals(robot, sc.scene, r, "w", "g", stamp, **kw)
        held = conv.plan_visuals(robot, sc.scene, r, "w", "g", stamp, slices=slices, **kw)
        for f, h in zip(fresh[1:], held[1:]):
            assert h == f                                         # what a fresh build gives, this stamp
        return held

    first = both(res, 10)
    again = both(SimpleNamespace(**{**vars(res), "path_rad": res.path_rad[::-1]}), 20)
    assert again[1] is first[1] and again[2] is first[2]           # same C-space, field, node: reused
    other = _fake_result(grid, rng)
    assert both(SimpleNamespace(**{**vars(res), "cspace": other.cspace}), 30)[1] is not first[1]
    assert both(SimpleNamespace(**{**vars(res), "field": other.field}), 40)[2] is not first[2]
    res2 = SimpleNamespace(**{**vars(res), "field": other.field})
    moved = SimpleNamespace(**{**vars(res2), "start_rad": np.array([1.0, 0.0, 0.0])})
    both(res2, 50)
    assert both(moved, 60)[2] is not both(res2, 70)[2]             # another node of the sliced-out axis
    assert both(res2, 80, slice_attitude_deg=90.0, use_current_attitude=False)[1] is not None
