"""
Free-floating capture (``free_floating.plan_capture`` through the planner, the CLI and the node's chain).

Judged by the test's own physics and geometry (test/oracles.py): the attitude and the body's
position from the test's free-floating simulator (``simulate_free_floating``: each step's attitude
increment solved so that the step's angular momentum about the centre of mass is zero, the body
moved so that the centre of mass stays put), the tip and link 3 from the test's complex-number
chain (``arm_points``, ``link3_and_normal_deg``), the inertial collision check by points along the
links against the target's square and by segment-polygon distances against the spacecraft body.
"""

import json
import math
import re
from dataclasses import replace

import numpy as np
import pytest

from oracles import (arm_points, body_polygon, inside_target_or_margin, link3_and_normal_deg, ref_seg_poly_distance,
                     simulate_free_floating, wrap_diff)
from spacerobot_planner.adapters import post_process
from spacerobot_planner.config import load_scenario
from spacerobot_planner.motion import MotionValidator
from spacerobot_planner.planner import Planner
from spacerobot_planner.ros import conversions as conv
from spacerobot_planner.scene import Scene, Target
from spacerobot_planner.session import Publication, result_values
from spacerobot_planner.tools.cli import main

FF = "config/free_floating_capture.yaml"
S3 = "config/servicer_3dof.yaml"


@pytest.fixture(scope="module")
def capture():
    sc = load_scenario(FF)
    return sc, Planner(sc).plan(sc.start_rad)


def _judge(sc, path_rad, sub=2):
    """Return the test's own drift along a planned path: (q_full (K, 3) with the drifted attitude, body (K, 2))."""
    return simulate_free_floating(sc.robot, sc.masses, path_rad, sub=sub)


def test_the_attitude_kernel_meets_the_simulator_on_coarse_paths():
    """
    The search's attitude change (``attitude_changes_rad``, Simpson per row step) against the simulator.

    Random arm paths of 9 rows (big steps, straight between rows, where the quadrature
    matters), each change within 2e-5 rad of the test's simulator on 64 substeps per row step.
    A trapezoid rule (or a wrong midpoint) misses by 1e-4 and more there.
    """
    from spacerobot_planner.free_floating_capture import attitude_changes_rad
    sc = load_scenario(FF)
    robot = sc.robot
    rng = np.random.default_rng(5)
    lo, hi = robot.planned_lower_rad, robot.planned_upper_rad
    paths = []
    for _ in range(6):
        a, b = rng.uniform(lo, hi), rng.uniform(lo, hi)
        s = np.linspace(0.0, 1.0, 9)[:, None]
        paths.append(np.clip(a + (b - a) * s + 0.4 * np.sin(np.pi * s) * rng.normal(size=len(lo)), lo, hi))
    got = attitude_changes_rad(robot, sc.masses, np.stack([robot.full(p) for p in paths]))
    for p, change in zip(paths, got):
        q, _ = simulate_free_floating(robot, sc.masses, p, sub=64)
        assert abs(change - (q[-1, 0] - q[0, 0])) < 2e-5, (change, q[-1, 0] - q[0, 0])
    assert np.max(np.abs(got)) > 0.05                      # the paths turn the body (the check is not vacuous)


def test_a_large_batch_runs_on_numbas_threads_and_meets_the_simulator(monkeypatch):
    """
    A batch of many paths runs the attitude kernel's parallel form (``_profiles``' rule), and it meets the simulator.

    600 random coarse arm paths (5 400 path rows, above ``PARALLEL_MIN_ROWS``) on two of numba's
    threads: the parallel form ran (counted at its call), every fiftieth path's change is within
    2e-5 rad of the test's simulator, and every path's change is the one it has integrated alone
    (one path: the one-thread form), bit for bit: the plan is the same on any number of threads.
    """
    import numba
    from spacerobot_planner import free_floating_capture as ffc
    if numba.config.NUMBA_NUM_THREADS < 2:
        pytest.skip("numba runs one thread here")
    sc = load_scenario(FF)
    robot = sc.robot
    rng = np.random.default_rng(11)
    lo, hi = robot.planned_lower_rad, robot.planned_upper_rad
    s = np.linspace(0.0, 1.0, 9)[:, None]
    paths = []
    for _ in range(600):
        a, b = rng.uniform(lo, hi), rng.uniform(lo, hi)
        paths.append(robot.full(np.clip(a + (b - a) * s + 0.4 * np.sin(np.pi * s) * rng.normal(size=len(lo)), lo, hi)))
    paths = np.stack(paths)
    assert paths.shape[0] * paths.shape[1] >= ffc.PARALLEL_MIN_ROWS
    ran = []
    parallel = ffc._attitude_profiles_parallel
    monkeypatch.setattr(ffc, "_attitude_profiles_parallel", lambda *a: ran.append(len(a[0])) or parallel(*a))
    threads = numba.get_num_threads()
    numba.set_num_threads(2)
    try:
        got = ffc.attitude_changes_rad(robot, sc.masses, paths)
    finally:
        numba.set_num_threads(threads)
    assert ran == [600]
    alone = np.array([ffc.attitude_changes_rad(robot, sc.masses, p) for p in paths])
    assert ran == [600]                                    # one path at a time: the one-thread form
    assert np.array_equal(got, alone)
    for p, change in zip(paths[::50], got[::50]):
        q, _ = simulate_free_floating(robot, sc.masses, p[:, list(robot.planned_joints)], sub=64)
        assert abs(change - (q[-1, 0] - q[0, 0])) < 2e-5, (change, q[-1, 0] - q[0, 0])
    assert np.max(np.abs(got)) > 0.05


def test_a_familys_scan_keeps_its_paths_within_the_bounds_and_meets_the_simulator():
    """
    A family's scan (``_family_changes``, both forms) against the test's own rows, bounds and simulator.

    The test makes the family's paths itself: a rest-to-rest quintic between two arm postures plus
    Σ_h c_h sin((h + 1)π s) per joint, c = amplitude × direction (8 random directions, 6 amplitudes up
    to 120°), 61 rows.  A path is in the scan where each of its rows is within the joint bounds, and
    then its attitude change is within 2e-5 rad of the simulator's (10 of them judged); NaN where not;
    the parallel form (two of numba's threads) gives the one-thread form's values bit for bit.
    """
    import numba
    from spacerobot_planner import free_floating_capture as ffc
    from spacerobot_planner.spacecraft import _momentum_tables
    sc = load_scenario(FF)
    robot = sc.robot
    lo, hi = np.asarray(robot.planned_lower_rad), np.asarray(robot.planned_upper_rad)
    rng = np.random.default_rng(4)
    a0, af = rng.uniform(lo + 0.3, hi - 0.3), rng.uniform(lo + 0.3, hi - 0.3)
    s = np.linspace(0.0, 1.0, 61)
    base = a0 + (af - a0) * (s ** 3 * (10.0 - 15.0 * s + 6.0 * s * s))[:, None]           # (61, 2)
    basis = np.stack([np.sin(np.pi * s), np.sin(2.0 * np.pi * s)])                         # (2, 61)
    dirs = rng.normal(size=(8, 2, 2))
    dirs /= np.linalg.norm(dirs.reshape(8, -1), axis=1)[:, None, None]
    amps = np.radians(np.linspace(0.0, 120.0, 6))
    pair, inertia = _momentum_tables(robot, sc.masses)
    att0 = float(robot.full(a0)[0])
    args = (base, basis, dirs, amps, lo - 1e-9, hi + 1e-9, att0, pair, inertia)
    delta, inside = ffc._family_changes(*args)
    threads = numba.get_num_threads()
    numba.set_num_threads(min(2, numba.config.NUMBA_NUM_THREADS))
    try:
        delta_p, inside_p = ffc._family_changes_parallel(*args)
    finally:
        numba.set_num_threads(threads)
    assert np.array_equal(inside, inside_p) and np.array_equal(delta, delta_p, equal_nan=True)
    judged = 0
    for d in range(len(dirs)):
        for a in range(len(amps)):
            terms = [sum(amps[a] * dirs[d, j, h] * basis[h] for h in range(2)) for j in range(2)]
            rows = base + np.stack(terms, axis=1)
            ok = bool(np.all((rows >= lo - 1e-9) & (rows <= hi + 1e-9)))
            assert inside[d, a] == ok, (d, a)
            assert np.isnan(delta[d, a]) != ok
            if ok and judged < 10 and (d + a) % 2 == 0:
                q, _ = simulate_free_floating(robot, sc.masses, rows, sub=16)
                assert abs(delta[d, a] - (q[-1, 0] - q[0, 0])) < 2e-5, (d, a, delta[d, a], q[-1, 0] - q[0, 0])
                judged += 1
    assert judged == 10 and 0 < np.count_nonzero(inside) < inside.size     # both kinds of path (not vacuous)


def test_capture_postures_grasp_where_the_centre_of_mass_puts_the_body():
    """
    Each capture posture, its body moved by ``body_m``, grasps the handle, and the system's centre of mass stays put.

    Random starts and approach offsets within the tolerance.  The test's own chain (``arm_points``,
    ``bodies_world``, ``mass_table``): the tip at the grasp point, link 3 at the offset from the
    handle's inward normal, the centre of mass where the start's was, the joints within their bounds,
    the attitude change the posture's attitude less the start's.
    """
    from spacerobot_planner.free_floating_capture import capture_postures
    from oracles import bodies_world, mass_table
    sc = load_scenario(FF)
    robot, target = sc.robot, sc.scene.target
    m, _ = mass_table(sc.masses)
    tol = math.radians(sc.planner_settings.max_approach_error_deg)
    rng = np.random.default_rng(8)

    def com(q_full, body):
        centres, _ = bodies_world(robot, np.asarray(q_full, dtype=float)[None], np.asarray(body, dtype=float)[None])
        return m @ centres[0] / m.sum()

    branches = set()
    for _ in range(40):
        q0 = robot.full(rng.uniform(robot.planned_lower_rad, robot.planned_upper_rad))
        q0[0] = rng.uniform(-0.3, 0.3)
        offset = rng.uniform(-tol, tol)
        for post in capture_postures(robot, sc.masses, sc.scene, q0, offset):
            branches.add(post.branch)
            tip = arm_points(robot, post.q_full)[-1] + post.body_m
            assert np.linalg.norm(tip - target.grasp_point_m) < 1e-9
            assert abs(link3_and_normal_deg(robot, target, post.q_full) - abs(math.degrees(offset))) < 1e-6
            assert np.linalg.norm(com(post.q_full, post.body_m) - com(q0, np.zeros(2))) < 1e-9
            assert np.all(post.q_full >= np.asarray(robot.lower_rad) - 1e-9)
            assert np.all(post.q_full <= np.asarray(robot.upper_rad) + 1e-9)
            assert abs(wrap_diff(post.attitude_change_rad, post.q_full[0] - q0[0])) < 1e-12
            assert 0.001 < np.linalg.norm(post.body_m) < 0.5          # the body moved (the check is not vacuous)
    assert branches == {0, 1}


def _tip_and_approach(sc, q_full, body):
    tip = arm_points(sc.robot, q_full)[-1] + body
    approach_deg = link3_and_normal_deg(sc.robot, sc.scene.target, q_full)
    return float(np.linalg.norm(tip - sc.scene.target.grasp_point_m)), approach_deg


def _body_clearance_m(sc, q_full):
    """Smallest distance of links 2 and 3 to the spacecraft's own body (a relative check: drift-free)."""
    best = math.inf
    for q in q_full:
        pts = arm_points(sc.robot, q).tolist()
        poly = body_polygon(sc.robot, q[0]).tolist()
        best = min(best, *(ref_seg_poly_distance(pts[k], pts[k + 1], poly) for k in (1, 2)))
    return best


def test_capture_grasps_perpendicularly_by_the_tests_own_momentum_integration(capture):
    sc, res = capture
    assert res.ok, res.reason
    assert res.smoothing == "free_floating_capture"
    assert np.max(np.abs(np.diff(res.path_rad, axis=0))) <= math.radians(0.5)        # the path's promise
    tol_m = sc.acs.position_tolerance_m
    tol_deg = sc.planner_settings.max_approach_error_deg
    # the held-attitude plan of the same scene would miss: the drift is real
    q, body = _judge(sc, res.path_rad)
    assert np.all(np.isclose(q[:, 1:], sc.robot.full(res.path_rad)[:, 1:]))       # the arm as planned
    change_deg = math.degrees(q[-1, 0] - q[0, 0])
    assert abs(change_deg) > 3.0 and np.linalg.norm(body[-1]) > 0.02
    # the attitude along the path: the package's prediction (the JSON's path_rad) against the test's
    doc = res.to_json_dict()
    assert doc["path_joint_names"] == ["attitude", "shoulder", "elbow"] and doc["joint_names"] == ["shoulder", "elbow"]
    predicted = np.asarray(doc["path_rad"])
    assert predicted.shape == (len(res.path_rad), 3)
    assert np.max(np.abs(wrap_diff(predicted[:, 0], q[:, 0]))) < math.radians(0.02)
    assert np.allclose(doc["free_floating"]["body_position_m"], body, atol=1e-3)
    assert doc["free_floating"]["body_displacement_m"] == pytest.approx(np.linalg.norm(body[-1]), abs=1e-3)
    # the end: at the handle, perpendicular, in the inertial frame
    miss_m, approach_deg = _tip_and_approach(sc, q[-1], body[-1])
    assert miss_m < 0.25 * tol_m and approach_deg < tol_deg
    # collision-free all along: drifted links vs the fixed target (points), links vs the own body
    assert not inside_target_or_margin(sc.robot, sc.scene, q, body).any()
    assert _body_clearance_m(sc, q) > sc.scene.safety_margin_m


def test_the_executed_trajectory_grasps_too(capture):
    """The dense trajectory (what the arm follows) judged the same way, and the reaction report agrees."""
    sc, res = capture
    traj = res.trajectory
    q, body = _judge(sc, traj.positions_rad, sub=1)
    miss_m, approach_deg = _tip_and_approach(sc, q[-1], body[-1])
    assert miss_m < 0.25 * sc.acs.position_tolerance_m and approach_deg < sc.planner_settings.max_approach_error_deg
    assert not inside_target_or_margin(sc.robot, sc.scene, q, body).any()
    rep = res.reaction
    assert rep.ok and rep.acs_mode == "free_floating" and not rep.free_floating_collides
    assert rep.free_floating_approach_error_deg == pytest.approx(approach_deg, abs=0.05)
    assert rep.free_floating_attitude_change_deg == pytest.approx(math.degrees(q[-1, 0] - q[0, 0]), abs=0.02)


def test_the_node_chain_publishes_the_arm_only_and_predicts_the_drift(capture):
    sc, res = capture
    processed = post_process(sc, res.path_rad, start_rad=sc.start_rad,
                             motions=MotionValidator.for_scene(sc.robot, sc.scene))
    assert processed.refused is None and processed.certified
    assert processed.attitude is None and processed.arm.joint_names == ("shoulder", "elbow")
    drift = processed.predicted_drift
    assert drift.joint_names == ("attitude", "body_x", "body_y")
    assert np.array_equal(drift.times_s, processed.arm.times_s)
    q, body = _judge(sc, processed.dense.positions_rad, sub=1)
    idx = processed.indices
    assert np.max(np.abs(wrap_diff(drift.positions_rad[:, 0], q[idx, 0]))) < math.radians(0.02)
    assert np.allclose(drift.positions_rad[:, 1:], body[idx], atol=1e-3)
    # what the node makes of it: the action result's attitude_trajectory, the diagnostics' values
    publication = Publication(123, processed.arm, processed.attitude, True, drift)
    arm_msg, att_msg = conv.publication_msgs(publication)
    assert arm_msg is not None and att_msg is None                                   # nothing commands the attitude
    msg = conv.predicted_drift_msg(publication)
    assert list(msg.joint_names) == ["attitude", "body_x", "body_y"] and len(msg.points) == len(drift.times_s)
    assert np.allclose(msg.points[-1].positions, drift.positions_rad[-1])
    values = result_values(res, processed.reaction)
    assert float(values["free_floating_body_displacement_m"]) == pytest.approx(np.linalg.norm(body[-1]), abs=1e-3)
    assert float(values["free_floating_approach_error_deg"]) < sc.planner_settings.max_approach_error_deg
    doc = processed.to_json_dict()
    assert doc["attitude_trajectory"] is None
    assert doc["predicted_drift"]["joint_names"] == ["attitude", "body_x", "body_y"]


def test_the_published_points_motion_is_certified_with_the_body_drifting():
    """
    The chain certifies the controller's motion of a free-floating capture in the inertial frame.

    From the arm's posture at the end of the file's capture (a ROS user's ``~/replan`` there,
    the attitude as the file states it): the capture's last stretch is planned for the drifted
    body, and on a body held still it crosses the target.  The chain had certified the
    published points on the body held still: 'NOT certified, clearance 0.000 m', every dense
    point published, and the node published it with a warning that the arm "starts within the
    margin" (it starts 0.13 m clear).  Oracle: the test's quintics through the published points
    (``controller_motion``, 40 samples a segment), the test's free-floating simulator, the
    target's square by points along the links, the body by segment-polygon distances.
    """
    from oracles import controller_motion
    from spacerobot_planner.offline import plan_offline
    sc = load_scenario(FF)
    start = np.radians([2.91, 90.35])
    done = plan_offline(Planner(sc, reaction=True), start)
    assert done.result.ok, done.result.reason
    processed = done.processed
    assert processed.certified and processed.min_clearance_m > sc.scene.safety_margin_m
    assert len(processed.trajectory) < len(processed.dense)          # not every dense point sent back
    traj = processed.trajectory
    arm = controller_motion(traj, 40 * (len(traj) - 1) + 1)[0]
    q, body = simulate_free_floating(sc.robot, sc.masses, arm, sub=2)
    assert not inside_target_or_margin(sc.robot, sc.scene, q, body).any()
    assert _body_clearance_m(sc, q[::8]) > sc.scene.safety_margin_m
    # not vacuous: held still, the same motion comes within the margin of the target
    held = sc.robot.full(arm)
    assert inside_target_or_margin(sc.robot, sc.scene, held, np.zeros((len(held), 2))).any()


def test_the_predicted_drifts_rates_are_the_drifts_own_zero_at_rest(capture):
    """
    The predicted drift's velocities: 0 where the arm is at rest, the oracle's drift's time derivative elsewhere.

    They had been finite differences of the positions: 0.002 rad/s of attitude and 0.9 mm/s of
    body at the start, where nothing moves (an audit with its own momentum balance).  Oracle: the
    test's simulator on the dense trajectory, differentiated at the published points (central
    differences over the dense points around each).
    """
    sc, res = capture
    processed = post_process(sc, res.path_rad, start_rad=sc.start_rad,
                             motions=MotionValidator.for_scene(sc.robot, sc.scene))
    drift, dense, idx = processed.predicted_drift, processed.dense, processed.indices
    at_rest = np.all(dense.velocities_rad_s[idx] == 0.0, axis=1)
    assert at_rest[0] and at_rest[-1]
    assert np.all(drift.velocities_rad_s[at_rest] == 0.0), drift.velocities_rad_s[at_rest]
    q, body = _judge(sc, dense.positions_rad, sub=8)
    oracle = np.gradient(np.column_stack([q[:, 0], body]), dense.times_s, axis=0)[idx]
    inner = slice(1, -1)
    scale = np.max(np.abs(oracle), axis=0)
    assert np.all(scale > 1e-4)                              # the body turns and moves (not vacuous)
    assert np.all(np.abs(drift.velocities_rad_s[inner] - oracle[inner]) < 0.005 * scale), \
        np.max(np.abs(drift.velocities_rad_s[inner] - oracle[inner]) / scale, axis=0)


def test_the_cli_json_holds_every_joint_and_the_bodys_displacement(tmp_path, capsys):
    js = tmp_path / "ff.json"
    rc = main(["--params-file", FF, "--json", str(js), "--quiet"])
    out = capsys.readouterr()
    assert rc == 0, out.err
    d = json.loads(js.read_text())
    assert d["ok"] and d["path_joint_names"] == ["attitude", "shoulder", "elbow"]
    path = np.asarray(d["path_rad"])
    assert path.shape[1] == 3 and path[0, 0] == pytest.approx(math.radians(160.7))
    assert d["free_floating"]["body_displacement_m"] > 0.02
    assert d["published_trajectory"]["attitude_trajectory"] is None
    assert d["reaction"]["free_floating_approach_error_deg"] < 5.0


def test_the_3dof_slew_is_refused_with_the_attitude_change_it_needs():
    """
    Free floating, the paper's 3-DOF slew (attitude −90° → 160.7°) cannot be made by the arm.

    The refusal names the attitude change (the test's own: 250.7°, or −109.3° the other way) and the
    range the arm's motions achieve, which must hold a motion the test integrates itself (the
    straight joint motion) and be far from the change needed.
    """
    sc = load_scenario(S3)
    sc = replace(sc, acs=replace(sc.acs, mode="free_floating"))
    res = Planner(sc).plan(sc.start_rad, sc.goal_rad)
    assert res.code == "reaction_refused" and not res.ok
    need = math.degrees(sc.goal_rad[0] - sc.start_rad[0])                           # 250.7
    m = re.search(r"needs ([-+][\d.]+)° \(or ([-+][\d.]+)° the other way round\), the arm's motions achieve "
                  r"([-+][\d.]+)° to ([-+][\d.]+)°", res.reason)
    assert m, res.reason
    needs = sorted(float(v) for v in m.group(1, 2))
    assert needs == pytest.approx(sorted([need, need - 360.0]), abs=0.05)
    lo, hi = float(m.group(3)), float(m.group(4))
    straight = np.linspace(sc.start_rad, sc.goal_rad, 400)
    straight[:, 0] = sc.start_rad[0]                                                  # the attitude is not driven
    q, _ = simulate_free_floating(sc.robot, sc.masses, straight, sub=1)
    own = math.degrees(q[-1, 0] - q[0, 0])
    assert lo - 0.1 <= own <= hi + 0.1
    assert min(abs(n) for n in needs) > 3.0 * max(abs(lo), abs(hi))


def test_the_node_publishes_the_arm_only_and_returns_the_predicted_drift(graph):
    """The planner node on the capture scene: the action's result and /diagnostics carry the drift."""
    from action_msgs.msg import GoalStatus
    from spacerobot_planner_interfaces.action import PlanCapture

    from node_helpers import FAST, load_params_file

    flat = load_params_file(FF)
    flat.update({k: v[:1] + v[1:2] * 2 for k, v in FAST.items()})
    g = graph(flat, with_arm=False)
    robot = g.scenario.robot
    g.send_joint_state(conv.joint_state_msg(robot.joint_names, robot.full(g.scenario.start_rad)))
    goal = PlanCapture.Goal()
    goal.target_pose.header.frame_id = "world"
    goal.target_pose.pose.position.x, goal.target_pose.pose.position.y = -3.27, -2.60
    goal.target_pose.pose.orientation.w = 1.0
    status, res, _ = g.goal_result(g.send_goal(goal))
    assert status == GoalStatus.STATUS_SUCCEEDED, res.reason
    g.wait(lambda: g.n_trajs() == 1, 5, "the arm's trajectory on joint_trajectory")
    assert list(res.trajectory.joint_names) == ["shoulder", "elbow"]
    drift = res.attitude_trajectory                       # the prediction, never published
    assert list(drift.joint_names) == ["attitude", "body_x", "body_y"]
    assert len(drift.points) == len(res.trajectory.points)
    assert g.att_trajs == []
    # the predicted end grasps: the test's own chain at the drifted attitude, the body moved
    q_end = np.array([drift.points[-1].positions[0], *res.trajectory.points[-1].positions])
    body = np.array(drift.points[-1].positions[1:])
    miss_m, approach_deg = _tip_and_approach(g.scenario, q_end, body)
    assert miss_m < g.scenario.acs.position_tolerance_m and approach_deg < 5.0
    values = g.planner_values_for_goal(res.trajectory.points[-1].positions)
    assert values["acs_mode"] == "free_floating"
    assert float(values["free_floating_body_displacement_m"]) == pytest.approx(np.linalg.norm(body), abs=1e-3)
    assert float(values["free_floating_attitude_change_deg"]) == pytest.approx(
        math.degrees(q_end[0] - drift.points[0].positions[0]), abs=1e-3)


def test_a_grasp_reached_only_near_the_approach_tolerance_is_not_called_out_of_reach():
    """
    Capture postures exist only 4.7-5° off the handle's normal: the refusal said "out of the arm's reach".

    A stress test's scene (margin 0.02 m).  Oracle: the test's own capture postures (two-link IK of
    the attitude link and the shoulder, the body moved so that the system's CoM stays where the
    start puts it, ``bodies_world`` and ``mass_table``): some exist within the tolerance, so the
    answer may refuse the motion but not the reach.
    """
    from oracles import bodies_world, mass_table
    sc = load_scenario(FF)
    debris = ([[0.646105, 1.754086], [0.678661, 1.488955], [1.399894, 1.355318], [1.525359, 1.59161]],
              [[-2.341996, -0.05209], [-2.349971, -0.005431], [-3.030182, 0.103235], [-2.939286, -0.38699]],
              [[-1.117485, -3.084818], [-1.638841, -2.663033], [-1.942772, -2.800012], [-2.056511, -2.970519],
               [-1.215191, -3.449622]])
    scene = Scene(target=Target(center_m=(1.186416, 2.930793), yaw_rad=1.448424),
                  debris_m=tuple(np.array(d) for d in debris), safety_margin_m=0.02)
    sc = sc.with_scene(scene)
    start = np.array([-1.286675, -0.960622])
    m, _ = mass_table(sc.masses)

    def com(q_full, body):
        c, _ = bodies_world(sc.robot, q_full[None, :], np.asarray(body, dtype=float)[None, :])
        return m @ c[0] / m.sum()

    c0 = com(sc.robot.full(start), (0.0, 0.0))
    l0, l1, l2 = sc.robot.link_lengths_m
    tol = sc.planner_settings.max_approach_error_deg
    found = []
    for off in np.arange(-tol + 1e-3, tol, 0.01):
        psi = scene.target.approach_angle_rad + math.radians(off)
        wrist = np.asarray(scene.target.grasp_point_m) - l2 * np.array([math.cos(psi), math.sin(psi)])
        for bend in (1.0, -1.0):
            body = np.zeros(2)
            for _ in range(60):                 # the body where the CoM stays put, the IK from it
                w = wrist - body
                c = (w @ w - l0 ** 2 - l1 ** 2) / (2 * l0 * l1)
                if abs(c) > 1.0:
                    break
                t1 = bend * math.acos(c)
                t0 = math.atan2(w[1], w[0]) - math.atan2(l1 * math.sin(t1), l0 + l1 * math.cos(t1))
                q = np.array([t0, t1, psi - t0 - t1])
                body = body + (c0 - com(q, body))
            else:
                tip = arm_points(sc.robot, q)[-1] + body
                assert np.linalg.norm(tip - scene.target.grasp_point_m) < 1e-9
                found.append(off)
    assert found and min(abs(f) for f in found) > 0.9 * tol, found     # only near the tolerance's edge
    res = Planner(sc).plan(start)
    assert not res.ok and "out of the arm's reach" not in res.reason, res.reason


def test_the_attitude_change_a_refusal_names_is_the_shortest_arc_holding_every_need():
    """Needs straddling ±180° make one short arc (+176.2° to +185.5°), not -180° to +178.3°; oracle: brute force."""
    from spacerobot_planner.free_floating_capture import circular_band_deg
    rng = np.random.default_rng(3)
    cases = [[-180.0, 178.3, 176.2, -174.5], [250.7], [10.0, 20.0, 350.0], [-90.0, 90.0]]
    cases += [list(rng.uniform(-180.0, 180.0, int(rng.integers(1, 6))) + rng.uniform(-30, 30)) for _ in range(200)]
    for angles in cases:
        lo, hi = circular_band_deg(angles)
        # the test's own: for each angle as the arc's start, the arc reaching every other one anticlockwise
        a = np.asarray(angles, dtype=float)
        spans = [max((b - s) % 360.0 for b in a) for s in a]
        assert hi - lo == pytest.approx(min(spans), abs=1e-9), (angles, lo, hi)
        assert -180.0 <= lo < 180.0
        assert all((x - lo) % 360.0 <= hi - lo + 1e-9 or (x - lo) % 360.0 > 360.0 - 1e-9 for x in a), (angles, lo, hi)


def test_a_grasp_out_of_the_arms_reach_answers_goal_unreachable_as_on_a_held_spacecraft():
    """
    Free floating, the target 7.5 m from the body's centre: ``goal_unreachable`` (it had answered ``reaction_refused``).

    Oracle: the test's own reach: the grasp point is farther from the body's centre than the
    arm's links end to end (its first link from the centre, then the rest) plus a body drift of a
    metre: no posture of the arm reaches it, wherever the body floats.
    """
    base = load_scenario(FF)
    target = replace(base.scene.target, center_m=(-7.0, -2.6))
    sc = base.with_scene(replace(base.scene, target=target))
    grasp = np.asarray(target.grasp_point_m, dtype=float)
    assert np.linalg.norm(grasp) > sum(base.robot.link_lengths_m) + 1.0        # the premise: out of reach
    res = Planner(sc).plan(base.start_rad)
    assert res.code == "goal_unreachable", (res.code, res.reason)
    assert "out of the arm's reach" in res.reason
