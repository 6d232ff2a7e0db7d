"""
Redundant chains grasp: the capture posture of 4- and 5-joint chains (spacerobot_planner.redundant).

The oracle is the test's own: its own forward kinematics (``oracles.arm_points``, complex
numbers), its own manipulability (Cauchy–Binet: det(J Jᵀ) = Σ over joint pairs of the squared
cross product of their levers to the tip), its own closed-form self-motion (the first r joints
swept on a grid far denser than the package's, the last three solved as wrist point + two-link
reach) and its own geometry (``oracles.ref_clearance`` over every arm link).  The package's
posture must grasp exactly, be within bounds and collision-free, and no posture of the
brute-force sweep that is within bounds and collision-free may be more than 2 % more
manipulable.
"""

import json
import math
from pathlib import Path

import numpy as np
import pytest

from spacerobot_planner.config import load_scenario
from spacerobot_planner.ik import capture_posture, grasp_ik
from spacerobot_planner.planner import Planner
from spacerobot_planner.robot import PlanarArm, square_polygon
from spacerobot_planner.scene import Scene, Target
from spacerobot_planner.tools.cli import main

from oracles import arm_points, dense_samples, ref_clearance, wrap_diff

ROOT = Path(__file__).resolve().parent.parent
S4 = str(ROOT / "config" / "servicer_4joint.yaml")
PI = math.pi
#: the brute-force sweep's samples per swept joint (the package sweeps 720 for one, 180² for two)
BRUTE = {1: 14_400, 2: 540}


def own_manipulability(robot, q_full) -> np.ndarray:
    """sqrt(det(J Jᵀ)) of the tip position Jacobian by Cauchy–Binet, (...,) m²."""
    pts = arm_points(robot, q_full)
    lever = pts[..., -1:, :] - pts[..., :-1, :]                   # joint k's pivot → tip
    n = lever.shape[-2]
    det = np.zeros(lever.shape[:-2])
    for i in range(n):
        for j in range(i + 1, n):
            cross = lever[..., i, 0] * lever[..., j, 1] - lever[..., i, 1] * lever[..., j, 0]
            det = det + cross ** 2
    return np.sqrt(det)


def own_self_motion(robot, grasp, psi, per_axis, axes=None):
    """
    Every posture of a chain (all joints planned, n = r + 3) grasping at ``grasp`` with the last link at ``psi``.

    The first r joints on a grid of ``per_axis`` values each over their range (or on the given
    ``axes``, one array of values per swept joint); the rest by the wrist point and a two-link
    reach.  Returns q_full (K, n) rad wrapped into (-π, π], and whether each is within the
    joint bounds (K,).
    """
    L = np.asarray(robot.link_lengths_m, dtype=float)
    n = len(L)
    r = n - 3
    if axes is None:
        axes = [np.linspace(robot.lower_rad[j], robot.upper_rad[j], per_axis, endpoint=not robot.periodic[j])
                for j in range(r)]
    s = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, r)
    phi = np.cumsum(s, axis=1)                                    # absolute angles of links 0..r-1
    base = np.sum(L[:r] * np.exp(1j * phi), axis=1)               # pivot of joint r
    wrist = complex(*grasp) - L[-1] * np.exp(1j * psi)
    d = wrist - base
    a, b = L[r], L[r + 1]
    c = (np.abs(d) ** 2 - a * a - b * b) / (2 * a * b)
    ok = np.abs(c) <= 1.0
    out = []
    for sign in (1.0, -1.0):
        e = sign * np.arccos(np.clip(c, -1.0, 1.0))
        first = np.angle(d) - np.arctan2(b * np.sin(e), a + b * np.cos(e))
        q = np.column_stack([s, first - phi[:, -1], e, psi - first - e])
        out.append(q[ok])
    q = np.angle(np.exp(1j * np.concatenate(out)))                # wrap into (-π, π]
    inb = np.ones(len(q), bool)
    for j in range(n):
        if not robot.periodic[j]:
            inb &= (q[:, j] >= robot.lower_rad[j] - 1e-12) & (q[:, j] <= robot.upper_rad[j] + 1e-12)
    return q, inb


def check_grasp_against_brute_force(robot, scene, sol=None):
    """Check that the package's posture grasps exactly, is free, and no free dense-sweep posture beats it by 2 %."""
    target, margin = scene.target, scene.safety_margin_m
    links = range(1, robot.n_joints)
    if sol is None:
        sols = grasp_ik(robot, scene)
        assert sols, "no grasp found"
        sol = sols[0]
    q = sol.q_full
    tip = arm_points(robot, q)[-1]
    assert np.linalg.norm(tip - target.grasp_point_m) < 1e-9                    # tip exact
    assert abs(wrap_diff(np.sum(q), target.approach_angle_rad)) < 1e-9          # approach exact
    lo, hi = np.asarray(robot.lower_rad), np.asarray(robot.upper_rad)
    assert np.all((q >= lo - 1e-12) & (q <= hi + 1e-12))
    assert ref_clearance(robot, scene, q, links) > margin
    w = float(own_manipulability(robot, q))
    assert sol.manipulability == pytest.approx(w, rel=1e-9)
    every, inb = own_self_motion(robot, target.grasp_point_m, target.approach_angle_rad, BRUTE[robot.n_joints - 3])
    # a more manipulable posture must collide: the test's geometry checks each such posture
    better = every[inb & (own_manipulability(robot, every) > 1.02 * w)]
    free_better = [qb for qb in better if ref_clearance(robot, scene, qb, links) > margin]
    assert not free_better, (f"{len(free_better)} free postures more than 2 % more manipulable than "
                             f"{w:.4f} m², e.g. {np.degrees(free_better[0]).round(2)}°: "
                             f"{float(own_manipulability(robot, free_better[0])):.4f} m²")
    # and the sweep's best free posture is no better than the package's (a consistency check of the oracle)
    near = every[inb & (own_manipulability(robot, every) > w * (1 - 1e-3))]
    assert any(ref_clearance(robot, scene, qb, links) > margin for qb in near) or len(near) == 0
    return sol


def chain(lengths, lower_deg=None, upper_deg=None):
    n = len(lengths)
    lo = np.radians(lower_deg) if lower_deg is not None else (-PI,) * n
    hi = np.radians(upper_deg) if upper_deg is not None else (PI,) * n
    return PlanarArm(tuple(f"j{k}" for k in range(n)), tuple(lengths), tuple(lo), tuple(hi),
                     (True,) + (False,) * (n - 1), square_polygon(1.8, corner_first=True),
                     checked_links=tuple(range(1, n)))


def test_the_4_joint_scenario_grasps_with_the_most_manipulable_free_posture():
    sc = load_scenario(S4)
    robot = sc.robot
    assert robot.checked_links == (1, 2, 3)           # the wrist link is checked too
    sol = check_grasp_against_brute_force(robot, sc.scene)
    assert "swept 720 values of the attitude" in sol.method and "nested grid" in sol.method
    # the planner's goal from the target is that posture and says how it was chosen
    chosen = Planner(sc).capture_goal()
    np.testing.assert_array_equal(chosen.q_full, sol.q_full)
    assert chosen.manipulability == sol.manipulability


@pytest.mark.parametrize("seed", [3, 20])
def test_the_one_joint_refinement_reaches_the_local_optimum(seed):
    """
    The 4-joint grasp is the best collision-free posture near it, to 1e-7 (the refinement's job).

    The test's own self-motion on 4 001 values of the attitude within one sweep step (0.5°) of
    the chosen posture's, its own manipulability and clearance: none of those on the chosen
    branch that is within bounds and collision-free is more manipulable by more than 1e-7
    (relative).  With the refinement off it fails on both seeds, stopped at a 1e-4 rad bracket
    on one (where the 2 % brute-force check above passes).
    """
    sc = load_scenario(S4)
    robot = sc.robot
    links = range(1, robot.n_joints)
    for target in seeded_targets(4, seed=seed):
        scene = sc.scene.with_target(target)
        sols = grasp_ik(robot, scene)
        for sol in sols:
            q = sol.q_full
            w = float(own_manipulability(robot, q))
            near = q[0] + np.linspace(-1.0, 1.0, 4001) * np.radians(0.5)
            every, inb = own_self_motion(robot, target.grasp_point_m, target.approach_angle_rad, None, axes=[near])
            same = inb & (np.sign(every[:, 2]) == np.sign(q[2]))          # the chosen elbow branch
            cand = every[same]
            better = cand[own_manipulability(robot, cand) > w * (1 + 1e-7)]
            free_better = [qb for qb in better if ref_clearance(robot, scene, qb, links) > scene.safety_margin_m]
            assert not free_better, (f"{len(free_better)} free postures near {np.degrees(q).round(4)}° beat "
                                     f"{w:.9f} m²: {float(own_manipulability(robot, free_better[0])):.9f}")


def seeded_targets(count, seed=20):
    """Targets 3.0–4.4 m away at any bearing, the handle turned up to ±57° from facing the spacecraft."""
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(count):
        r, bearing, turn = rng.uniform(3.0, 4.4), rng.uniform(-PI, PI), rng.uniform(-1.0, 1.0)
        out.append(Target(center_m=(r * math.cos(bearing), r * math.sin(bearing)), yaw_rad=bearing + PI / 2 + turn))
    return out


@pytest.mark.parametrize("target", seeded_targets(5), ids=lambda t: f"{t.center_m[0]:.2f},{t.center_m[1]:.2f}")
def test_random_targets_4_joints(target):
    sc = load_scenario(S4)                            # its joint limits: elbow ±165°, wrist ±150°
    check_grasp_against_brute_force(sc.robot, sc.scene.with_target(target))


@pytest.mark.parametrize("target", [Target()] + seeded_targets(1, seed=5),
                         ids=lambda t: f"{t.center_m[0]:.2f},{t.center_m[1]:.2f}")
def test_five_joints(target):
    robot = chain((1.4, 1.2, 1.2, 1.0, 0.8))
    scene = Scene(target=target, safety_margin_m=0.02)
    sol = check_grasp_against_brute_force(robot, scene)
    assert "swept 180×180 values of (j0, j1)" in sol.method and "Nelder-Mead" in sol.method


def test_debris_pushes_the_choice_to_a_free_posture():
    """A debris block over the unconstrained optimum: the chosen posture moves off it and stays the best free one."""
    robot = chain((1.4, 1.6, 1.4, 1.0))
    free_scene = Scene(target=Target(), safety_margin_m=0.02)
    best = grasp_ik(robot, free_scene)[0]
    elbow = arm_points(robot, best.q_full)[2]
    block = np.array([[-0.25, -0.25], [0.25, -0.25], [0.25, 0.25], [-0.25, 0.25]]) + elbow
    scene = Scene(target=Target(), debris_m=(block,), safety_margin_m=0.02)
    sol = check_grasp_against_brute_force(robot, scene)
    assert sol.manipulability < best.manipulability


def test_no_redundancy_and_interleaved_locked_joints():
    # attitude locked: three planned joints for three constraints, two closed-form branches
    robot = PlanarArm(("attitude", "shoulder", "elbow", "wrist"), (1.4, 1.6, 1.4, 1.0), (-PI,) * 4, (PI,) * 4,
                      (True, False, False, False), square_polygon(1.8, corner_first=True),
                      planned_joints=(1, 2, 3), locked_rad=np.radians([160.0, 0, 0, 0]), checked_links=(1, 2, 3))
    scene = Scene(target=Target(), safety_margin_m=0.02)
    sols = grasp_ik(robot, scene, free_only=False)
    assert len(sols) == 2 and all("closed form" in s.method for s in sols)
    assert sols[0].manipulability >= sols[1].manipulability
    for s in sols:
        assert s.q_full[0] == pytest.approx(math.radians(160.0), abs=1e-12)
        assert np.linalg.norm(arm_points(robot, s.q_full)[-1] - scene.target.grasp_point_m) < 1e-9
        assert abs(wrap_diff(np.sum(s.q_full), scene.target.approach_angle_rad)) < 1e-9
        np.testing.assert_array_equal(s.q, s.q_full[1:])
    # a locked joint between planned ones (the elbow of a 5-joint chain at 30°): the rest still grasp exactly
    robot5 = PlanarArm(tuple("abcde"), (1.4, 1.2, 1.2, 1.0, 0.8), (-PI,) * 5, (PI,) * 5, (True,) + (False,) * 4,
                       square_polygon(1.8, corner_first=True), planned_joints=(0, 1, 3, 4),
                       locked_rad=np.radians([0, 0, 30.0, 0, 0]), checked_links=(1, 2, 3, 4))
    sols = grasp_ik(robot5, scene)
    assert sols and "swept 720 values of the a" in sols[0].method
    for s in sols:
        assert s.q_full[2] == pytest.approx(math.radians(30.0), abs=1e-12)
        assert np.linalg.norm(arm_points(robot5, s.q_full)[-1] - scene.target.grasp_point_m) < 1e-9
        assert abs(wrap_diff(np.sum(s.q_full), scene.target.approach_angle_rad)) < 1e-9
        assert ref_clearance(robot5, scene, s.q, range(1, 5)) > scene.safety_margin_m


def test_a_tilted_grasp_within_the_tolerance_where_no_perpendicular_one_is_in_bounds():
    """
    The 4-joint servicer, a target whose perpendicular grasp leaves the joint bounds (a stress test's case).

    The planner tries the perpendicular grasp, then tilts within grasp.max_approach_error_deg (5°)
    in whole degrees.  Oracle: the test's own self-motion (3 600 attitudes) and clearance: no
    posture in bounds and clear of the 0.05 m margin grasps perpendicularly, one grasps at the
    tilt the planner chose; with a 1° tolerance the answer is goal_unreachable, saying what it tried
    (it had said "out of the arm's reach" with any tolerance).
    """
    sc = load_scenario(S4)
    scene = Scene(target=Target(center_m=(2.757826, 3.698642), yaw_rad=1.221912), safety_margin_m=0.05)
    sc = sc.with_scene(scene)
    robot, target = sc.robot, scene.target
    start = np.array([2.326925, 0.787949, 0.482547, -2.522416])

    def clear_postures(tilt_deg):
        q, inb = own_self_motion(robot, target.grasp_point_m, target.approach_angle_rad + math.radians(tilt_deg), 3600)
        return [row for row in q[inb] if ref_clearance(robot, scene, row[list(robot.planned_joints)]) > 0.05]

    res = Planner(sc).plan(start)
    assert res.ok, res.reason
    assert 0.5 < res.approach_error_deg <= 5.0, res.approach_error_deg
    assert not clear_postures(0.0)
    assert clear_postures(np.sign(wrap_diff(np.sum(robot.full(res.goal_rad)), target.approach_angle_rad))
                          * round(res.approach_error_deg))
    refused = Planner(sc, max_approach_error_deg=1.0).plan(start)
    assert refused.code == "goal_unreachable", refused.reason
    assert "at approach angles within ±1° of the handle's normal" in refused.reason, refused.reason


def test_a_goal_whose_nearest_grid_nodes_are_cut_off_joins_a_farther_one():
    """
    The 4-joint servicer's grid steps 22.5°: a goal near the target had none of its 8 nearest free nodes joinable.

    The answer was path_invalid ("no free grid node near the goal is joined to it"; the finer grid
    above planner.max_refined_nodes) where a path keeping 83 mm exists (a stress test's RRT, checked
    every 0.05°).  Now the rest of the goal's window of nodes is tried.  Oracle: the path sampled
    every 0.25°, the test's own clearance (``ref_clearance``) above the margin, the ends exact.
    """
    sc = load_scenario(S4)
    scene = Scene(target=Target(center_m=(-2.891514, 0.518069), yaw_rad=-1.793523),
                  safety_margin_m=0.05)
    sc = sc.with_scene(scene)
    start = np.array([-2.359939, 2.088851, -1.271815, -1.933338])
    res = Planner(sc).plan(start)
    assert res.ok, res.reason
    assert np.array_equal(res.path_rad[0], res.start_rad)
    assert np.allclose(wrap_diff(res.path_rad[-1], res.goal_rad), 0.0, atol=1e-12)
    clr = min(ref_clearance(sc.robot, scene, row) for row in dense_samples(res.path_rad, math.radians(0.25)))
    assert clr > 0.05, clr


@pytest.mark.parametrize("center, yaw, debris, start", [
    ((-2.057189, 1.934301), -2.121767,
     (((1.968334, 2.783663), (1.868493, 2.929086), (1.726568, 2.998248), (1.587617, 2.997777)),
      ((2.261165, -0.389963), (1.939623, -0.178445), (1.757713, -0.590655)),
      ((-0.288245, 2.856874), (-0.081226, 2.484904), (0.09307, 2.56833)),
      ((2.01342, -4.070797), (1.744693, -3.97656), (1.375741, -4.228994), (1.426691, -4.628736))),
     (-2.224866, 1.334314, -0.141314, -1.928366)),
    ((-4.195112, 0.719948), -1.366596,
     (((-0.766936, 1.911286), (-1.237595, 1.764887), (-1.180299, 1.617974), (-0.926475, 1.531711)),
      ((0.089443, -3.046157), (0.026241, -3.572199), (0.186471, -3.442758)),
      ((3.642957, 0.094332), (2.819386, 0.131234), (2.723614, -0.196944), (3.644985, -0.417745))),
     (0.35144, -1.130418, 2.459799, -2.173989)),
])
def test_the_most_manipulable_capture_posture_keeps_room_to_be_reached(center, yaw, debris, start):
    """
    The redundant arm's most manipulable grasp lay on the safety margin (1e-9 m above it): no certified motion left it.

    Two of a stress test's random 4-joint scenes (margin 0.05 m) where the self-motion's
    manipulability rises towards an obstacle: the search ran up to the clearance boundary and
    the plan answered path_invalid on both grids ("no free grid node near the goal is joined to
    it").  Oracle: the test's own geometry (``ref_clearance`` every 0.25°, ``arm_points``): a
    path clear of the margin from the exact start to a goal that grasps the handle within
    grasp.max_approach_error_deg and clears the margin by a millimetre.
    """
    sc = load_scenario(S4)
    scene = Scene(target=Target(center_m=center, yaw_rad=yaw), debris_m=tuple(np.array(d) for d in debris),
                  safety_margin_m=0.05)
    sc = sc.with_scene(scene)
    res = Planner(sc).plan(np.array(start))
    assert res.ok, res.reason
    assert np.array_equal(res.path_rad[0], res.start_rad)
    assert np.allclose(wrap_diff(res.start_rad, np.array(start)), 0.0, atol=1e-12)
    assert np.allclose(wrap_diff(res.path_rad[-1], res.goal_rad), 0.0, atol=1e-12)
    assert np.linalg.norm(arm_points(sc.robot, res.goal_rad)[-1] - scene.target.grasp_point_m) < 1e-9
    approach = abs(wrap_diff(np.sum(sc.robot.full(res.goal_rad)), scene.target.approach_angle_rad))
    assert math.degrees(approach) <= sc.planner_settings.max_approach_error_deg + 1e-9
    assert ref_clearance(sc.robot, scene, res.goal_rad) > 0.05 + 0.999e-3
    clr = min(ref_clearance(sc.robot, scene, row) for row in dense_samples(res.path_rad, math.radians(0.25)))
    assert clr > 0.05, clr


def test_out_of_reach_and_too_few_planned_joints():
    robot = chain((1.4, 1.6, 1.4, 1.0))
    far = Scene(target=Target(center_m=(9.0, 0.0)), safety_margin_m=0.02)
    assert grasp_ik(robot, far) == [] and grasp_ik(robot, far, free_only=False) == []
    two = PlanarArm(("attitude", "shoulder", "elbow", "wrist"), (1.4, 1.6, 1.4, 1.0), (-PI,) * 4, (PI,) * 4,
                    (True, False, False, False), square_polygon(1.8, corner_first=True), planned_joints=(2, 3))
    with pytest.raises(ValueError, match="at least 3 planned joints.*elbow, wrist"):
        grasp_ik(two, Scene(target=Target()))


def test_capture_posture_of_4_joints_is_the_most_manipulable_arm():
    """The target-free advice: no arm posture on a 10° grid is more manipulable; the grasp meets the tip."""
    robot = chain((1.4, 1.6, 1.4, 1.0))
    target = Target()
    cp = capture_posture(robot, target)
    g = np.radians(np.arange(-180.0, 180.1, 10.0))
    arm = np.stack(np.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3)
    w_grid = own_manipulability(robot, np.column_stack([np.zeros(len(arm)), arm]))
    assert cp.manipulability >= w_grid.max() - 1e-9
    assert cp.manipulability == pytest.approx(float(own_manipulability(robot, cp.q_full)), rel=1e-9)
    assert abs(wrap_diff(np.sum(cp.q_full), target.approach_angle_rad)) < 1e-9
    placed = Target(center_m=tuple(cp.target_center_m), yaw_rad=target.yaw_rad)
    np.testing.assert_allclose(arm_points(robot, cp.q_full)[-1], placed.grasp_point_m, atol=1e-9)
    assert "Nelder-Mead" in cp.method


def test_cli_plans_the_4_joint_scenario_end_to_end(tmp_path, capsys):
    js = tmp_path / "s4.json"
    rc = main(["--params-file", S4, "--cells", "10", "--json", str(js), "--quiet"])
    out = capsys.readouterr()
    assert rc == 0, out.err
    d = json.loads(js.read_text())
    sc = load_scenario(S4)
    robot, scene = sc.robot, sc.scene
    assert d["ok"] and d["joint_names"] == ["attitude", "shoulder", "elbow", "wrist"]
    path, goal = np.array(d["path_rad"]), np.array(d["goal_rad"])
    np.testing.assert_array_equal(path[0], sc.start_rad)
    assert np.all(np.abs(wrap_diff(path[-1], goal)) < 1e-12)
    assert np.linalg.norm(arm_points(robot, goal)[-1] - scene.target.grasp_point_m) < 1e-9
    assert abs(wrap_diff(np.sum(goal), scene.target.approach_angle_rad)) < 1e-9
    assert d["approach_error_deg"] == pytest.approx(0.0, abs=1e-6)
    clr = min(ref_clearance(robot, scene, q, range(1, 4)) for q in dense_samples(path))
    assert clr > scene.safety_margin_m
    assert d["trajectory_resampled"]["certified"] is True
    assert d["published_trajectory"]["joint_trajectory"]["joint_names"] == ["shoulder", "elbow", "wrist"]
    re = d["reaction"]
    assert re["acs_mode"] == "held" and re["peak_wheel_torque_Nm"] <= 0.5 * (1 + 1e-6)
    assert re["peak_wheel_momentum_Nms"] <= 50.0 * (1 + 1e-6)


def test_the_node_plans_the_4_joint_scenario(graph):
    """planner_node with config/servicer_4joint.yaml: a target_pose gives a trajectory that grasps, collision-free."""
    from spacerobot_planner.ros.conversions import joint_state_msg
    from node_helpers import scene_params
    g = graph(scene_params("servicer4", cells=[10] * 4), with_arm=False)
    robot, scene = g.scenario.robot, g.scenario.scene
    assert robot.checked_links == (1, 2, 3)
    g.send_joint_state(joint_state_msg(robot.joint_names, robot.full(g.scenario.start_rad)))
    g.send_target()                                   # the paper's target
    # the message as a controller gets it (published, then delivered: later on a loaded machine)
    g.wait(lambda: g.n_trajs() > 0, 60, "a joint_trajectory message")
    traj = g.planner.last_trajectory
    q = robot.full(traj.positions_rad)
    np.testing.assert_allclose(q[0], g.scenario.start_rad, atol=1e-9)
    assert np.linalg.norm(arm_points(robot, q[-1])[-1] - scene.target.grasp_point_m) < 1e-6
    assert abs(wrap_diff(np.sum(q[-1]), scene.target.approach_angle_rad)) < 1e-6
    assert min(ref_clearance(robot, scene, qi, range(1, 4)) for qi in dense_samples(q)) > scene.safety_margin_m
    with g.lock:
        assert g.trajs and g.trajs[-1][1].joint_names == ["shoulder", "elbow", "wrist"]
