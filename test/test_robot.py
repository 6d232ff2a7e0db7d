"""Kinematics of the paper's robot: FK (against complex numbers, test/oracles.py), Jacobian, manipulability, IK."""

import numpy as np
import pytest

from oracles import arm_points, body_polygon
from spacerobot_planner.ik import capture_posture, grasp_ik

D = np.radians


@pytest.fixture(scope="module")
def sc3(paper_scenario):
    return paper_scenario(3)


@pytest.fixture(scope="module")
def sc2(paper_scenario):
    return paper_scenario(2)


def test_fk_of_paper_goal_reaches_grasp_point(sc3):
    tip = sc3.robot.tip_position(D([160.7, 32.8, 76.5]))
    assert np.linalg.norm(tip - np.array([-3.27, -2.00])) < 0.02


def test_fk_is_vectorised_and_link_lengths_hold(sc3):
    rng = np.random.default_rng(0)
    q = rng.uniform(-np.pi, np.pi, size=(50, 3))
    pts = sc3.robot.forward_kinematics(q)
    assert pts.shape == (50, 4, 2)
    assert np.allclose(pts[:, 0], 0.0)
    seg = np.linalg.norm(np.diff(pts, axis=1), axis=-1)
    assert np.allclose(seg, [1.4, 2.0, 2.0])
    single = sc3.robot.forward_kinematics(q[7])
    assert np.allclose(single, pts[7])
    assert np.allclose(pts, arm_points(sc3.robot, q), rtol=0.0, atol=1e-12)
    for att in q[:5, 0]:
        assert np.allclose(sc3.robot.body_polygon_world(att), body_polygon(sc3.robot, att), rtol=0.0, atol=1e-12)


def test_jacobian_matches_finite_differences(sc3):
    q = D([20.0, -40.0, 75.0])
    jac = sc3.robot.jacobian(q)
    eps = 1e-6
    fd = np.stack([(sc3.robot.tip_position(q + eps * e) - sc3.robot.tip_position(q - eps * e)) / (2 * eps)
                   for e in np.eye(3)], axis=1)
    assert np.allclose(jac, fd, atol=1e-6)


def test_manipulability_optimum_is_the_papers(sc3):
    cp = capture_posture(sc3.robot, sc3.scene.target)
    th2, th3 = np.degrees(cp.q_full[1:])
    assert abs(th2 - 32.7) < 0.3 and abs(th3 - 76.4) < 0.3
    assert cp.manipulability == pytest.approx(8.666, abs=2e-3)
    # the target must sit where its grasp point meets the tip: the paper's (-3.27, -2.00)
    assert np.allclose(cp.tip_m, [-3.267, -2.012], atol=2e-3)
    assert np.allclose(cp.target_center_m - cp.tip_m, [0.0, -0.6], atol=1e-9)


def test_manipulability_does_not_depend_on_attitude(sc3):
    q = D([0.0, 30.0, 70.0])
    w0 = sc3.robot.manipulability(q)
    for att in (-170.0, -45.0, 99.0):
        assert sc3.robot.manipulability(D([att, 30.0, 70.0])) == pytest.approx(w0, rel=1e-12)


def test_ik_of_default_target_reproduces_paper_goal(sc3):
    sols = grasp_ik(sc3.robot, sc3.scene)
    assert len(sols) == 2
    best = np.degrees(sols[0].q_full)
    assert np.all(np.abs(best - [160.7, 32.8, 76.5]) < 0.5)
    assert np.all(np.abs(np.degrees(sols[1].q_full) - [-160.9, -32.3, 103.2]) < 0.1)
    assert sols[0].manipulability > sols[1].manipulability
    for s in sols:   # every branch puts the tip on the grasp point, link 3 pointing into the target
        tip = sc3.robot.tip_position(s.q_full)
        assert np.allclose(tip, [-3.27, -2.00], atol=1e-9)
        assert np.isclose(np.cos(np.sum(s.q_full)), 0.0, atol=1e-9) and np.sin(np.sum(s.q_full)) < 0


def test_position_only_ik_with_locked_attitude(sc2):
    sols = grasp_ik(sc2.robot, sc2.scene)
    assert sols, "the paper's 2-DOF goal must be reachable"
    for s in sols:
        assert s.q_full[0] == pytest.approx(D(160.7))
        assert np.allclose(sc2.robot.tip_position(s.q_full), [-3.27, -2.00], atol=1e-9)
    assert np.all(np.abs(np.degrees(sols[0].q) - [32.8, 76.5]) < 0.5)


def test_ik_out_of_reach_gives_no_branch(sc3):
    assert grasp_ik(sc3.robot, sc3.scene, grasp_point_m=[20.0, 0.0], approach_angle_rad=0.0) == []


@pytest.mark.parametrize("q, field", [
    ([0.1, 0.2], "expected 3 joint values"),
    ([0.1, np.nan, 0.2], "'shoulder' is nan"),
    ([0.1, 0.2, np.radians(190.0)], "'elbow' = 190.000° is outside"),
])
def test_validate_q_names_the_problem(sc3, q, field):
    with pytest.raises(ValueError, match=field):
        sc3.robot.validate_q(np.asarray(q, dtype=float), "start")


def test_validate_q_takes_a_rounding_past_a_bound_as_the_bound(sc3):
    """The paper 3-DOF elbow's bounds are ±180° (config/paper_3dof.yaml): π + 1e-10 is π, π + 1e-8 is refused."""
    for past in (1e-10, 1e-9, 4.5e-16):
        assert sc3.robot.validate_q(np.array([0.1, 0.2, D(180.0) + past]))[2] == D(180.0)
        assert sc3.robot.validate_q(np.array([0.1, 0.2, -D(180.0) - past]))[2] == -D(180.0)
    # the value shown to the digits that tell it from the bound, and by how much it is past
    with pytest.raises(ValueError, match=r"'elbow' = 180\.00000057° is outside .* by 5\.7e-07°"):
        sc3.robot.validate_q(np.array([0.1, 0.2, D(180.0) + 1e-8]), "start")


@pytest.mark.parametrize("turns", [1e300, 1e17, 1e9, -2e6])
def test_validate_q_refuses_an_attitude_of_more_turns_than_a_plan_can_carry(sc3, turns):
    with pytest.raises(ValueError, match=r"start: joint 'attitude' = \S+ rad is more turns than a plan can carry"):
        sc3.robot.validate_q(np.array([turns, 0.2, 0.3]), "start")


def test_validate_q_wraps_the_periodic_attitude(sc3):
    q = sc3.robot.validate_q(D([190.0, 10.0, 10.0]))
    assert np.degrees(q[0]) == pytest.approx(-170.0)
