"""
Spacecraft physics, reaction verdict and free-floating planning against independent oracles.

The modules: spacecraft.py, reaction.py, free_floating.py; the oracles: test/oracles.py, and a
known answer.

Momentum sums from finite differences of the joint points (m r × v + I ω about the system CoM),
the wheel's momentum and torque the same way, a free-floating simulator of the test's own, a
two-body known answer, an inertial-frame point test of the drifted arm.
"""

import numpy as np
import pytest

from oracles import inside_target_or_margin, momentum_fd, simulate_free_floating, wheel_load
from paper_paths import joint_limits
from spacerobot_planner.reaction import check_drifted, reaction_report
from spacerobot_planner.spacecraft import MassProperties, WheelModel, free_floating_response
from spacerobot_planner.robot import PlanarArm, square_polygon
from spacerobot_planner.trajectory import time_parameterize

REF = MassProperties()                                   # the reference servicer
HEAVY = MassProperties(body_mass_kg=2.0e7, body_inertia_kgm2=1.08e7)
#: test_node.py imports the wheel's load oracle from here
_load_oracle = wheel_load


def _arm(planned=(1, 2), locked=(np.radians(160.7), 0.0, 0.0)):
    return PlanarArm(("attitude", "shoulder", "elbow"), (1.4, 2.0, 2.0), (-np.pi,) * 3, (np.pi,) * 3,
                     (True, False, False), square_polygon(1.8, corner_first=True),
                     planned_joints=planned, locked_rad=np.array(locked))


def _smooth_arm_path(k=4000):
    s = np.linspace(0.0, 1.0, k)
    return np.stack([2.3 - 1.7 * s + 0.3 * np.sin(3 * s), 1.6 - 0.3 * s + 0.4 * np.sin(5 * s)], axis=1)


@pytest.mark.parametrize("planned", [(1, 2), (0, 1, 2)])
def test_free_floating_motion_conserves_momentum_and_keeps_the_com(planned):
    robot = _arm(planned)
    arm = _smooth_arm_path()
    path = arm if len(planned) == 2 else np.column_stack([np.linspace(0.3, -1.0, len(arm)), arm])
    resp = free_floating_response(robot, REF, path)
    dt = 0.01                                     # any time law: h is linear in the rates
    h, scale, com = momentum_fd(robot, REF, resp.q_full_rad, resp.body_position_m, dt)
    assert np.max(np.abs(h) / scale) < 1e-6
    assert np.max(np.linalg.norm(com - com[0], axis=1)) < 1e-9
    assert abs(resp.attitude_change_deg) > 1.0    # it did turn
    # the oracle can fail: the planned motion (attitude held, body fixed) has momentum
    h_planned, scale_p, com_p = momentum_fd(robot, REF, resp.planned_q_full_rad,
                                            np.zeros_like(resp.body_position_m), dt)
    assert np.max(np.abs(h_planned) / scale_p) > 0.1
    assert np.max(np.linalg.norm(com_p - com_p[0], axis=1)) > 1e-3


def test_known_answer_a_rotor_on_a_rigid_body():
    """
    Link 3 massless with inertia I3 (a rotor) turns by Δ while the shoulder is locked.

    Body + link 2 form one rigid body A, and 0 = I_A θ̇1 + I3 (θ̇1 + θ̇3) about the common CoM, so
    Δθ1 = −I3 Δ / (I_A + I3) with I_A = I0 + I2 + m0 |c|² + m2 |r2 − c|².
    """
    m0, i0, m2, i2, i3 = 2000.0, 1080.0, 30.0, 10.0, 40.0
    mp = MassProperties(m0, i0, (0.0, m2, 0.0), (0.0, i2, i3))
    theta2 = np.radians(50.0)
    robot = _arm((1, 2), (0.2, 0.0, 0.0))
    d = 1.3
    path = np.column_stack([np.full(500, theta2), np.linspace(0.4, 0.4 + d, 500)])
    resp = free_floating_response(robot, mp, path)
    r2 = np.hypot(1.4 + 1.0 * np.cos(theta2), 1.0 * np.sin(theta2))   # |centre of link 2|
    c = m2 * r2 / (m0 + m2)
    i_a = i0 + i2 + m0 * c ** 2 + m2 * (r2 - c) ** 2
    expected = -i3 * d / (i_a + i3)
    assert np.isclose(np.radians(resp.attitude_change_deg), expected, rtol=1e-9)
    # the body moves on a circle: b = (m2/M)(r2(θ1_0) − r2(θ1))
    dth = np.radians(resp.attitude_change_deg)
    assert np.isclose(resp.body_displacement_m, m2 / (m0 + m2) * r2 * 2 * abs(np.sin(dth / 2)), rtol=1e-9)


@pytest.mark.parametrize("dof", [2, 3], ids=["paper_2dof", "paper_3dof"])
def test_wheel_limits_hold_on_the_trajectory(dof, paper_scenario, paper_path):
    sc, path = paper_scenario(dof), paper_path(dof)
    robot = sc.robot
    vmax, amax = joint_limits(sc)
    h_max, tau_max = 50.0, 0.5
    traj = time_parameterize(path, vmax, amax, robot.planned_names,
                             wheel=WheelModel(robot, REF, h_max, tau_max))
    q, qd, qdd = (robot.full(traj.positions_rad), np.zeros((len(traj), 3)), np.zeros((len(traj), 3)))
    idx = list(robot.planned_joints)
    qd[:, idx], qdd[:, idx] = traj.velocities_rad_s, traj.accelerations_rad_s2
    h, tau = wheel_load(robot, REF, q, qd, qdd)
    assert np.max(np.abs(h)) <= h_max * (1 + 1e-6)
    assert np.max(np.abs(tau)) <= tau_max * (1 + 1e-6)
    assert np.max(np.abs(tau)) >= 0.99 * tau_max            # the torque limit binds
    np.testing.assert_allclose(traj.wheel_torque_Nm, tau, atol=1e-6 * tau_max)   # the module's own series
    assert "wheel_torque" in set(traj.active_limit)
    # the joint-limited trajectory breaks them (so the check above can fail)
    free = time_parameterize(path, vmax, amax, robot.planned_names)
    qd[:, idx], qdd[:, idx] = free.velocities_rad_s, free.accelerations_rad_s2
    h_f, tau_f = wheel_load(robot, REF, robot.full(free.positions_rad), qd, qdd)
    assert np.max(np.abs(tau_f)) > 10 * tau_max and free.duration_s < traj.duration_s


def test_a_wheel_momentum_limit_near_zero_is_refused_by_name(paper_scenario, paper_path):
    """
    The wheel's momentum limit makes the motion last more than a trajectory message holds.

    Oracle: the momentum h = H(q) q̇ integrates over time to the path integral of H(q) dq, the
    same whatever the timing (the test's own wheel load, summed on the joint-limited
    trajectory); with |h| ≤ h_max the motion lasts at least that integral / h_max.
    """
    sc, path = paper_scenario(3), paper_path(3)
    robot = sc.robot
    vmax, amax = joint_limits(sc)
    free = time_parameterize(path, vmax, amax, robot.planned_names)
    qd = np.zeros((len(free), 3))
    qd[:, list(robot.planned_joints)] = free.velocities_rad_s
    h, _ = wheel_load(robot, REF, robot.full(free.positions_rad), qd, np.zeros_like(qd))
    impulse = float(np.sum(0.5 * (np.abs(h[1:]) + np.abs(h[:-1])) * np.diff(free.times_s)))    # N·m·s·s
    h_max = impulse / (4.0 * (2.0 ** 31 - 1))        # at least four times what a message holds
    with pytest.raises(ValueError, match="longer than a trajectory message can hold .*the wheel momentum limit"):
        time_parameterize(path, vmax, amax, robot.planned_names, wheel=WheelModel(robot, REF, h_max, None))


@pytest.mark.parametrize("dof", [2, 3], ids=["paper_2dof", "paper_3dof"])
def test_without_wheel_limits_the_trajectory_is_the_joint_limited_one(dof, paper_scenario, paper_path):
    sc, path = paper_scenario(dof), paper_path(dof)
    vmax, amax = joint_limits(sc)
    plain = time_parameterize(path, vmax, amax)
    for wheel in (WheelModel(sc.robot, REF), WheelModel(sc.robot, REF, 0.0, 0.0)):
        t = time_parameterize(path, vmax, amax, wheel=wheel)
        np.testing.assert_array_equal(t.times_s, plain.times_s)
        np.testing.assert_array_equal(t.velocities_rad_s, plain.velocities_rad_s)
        np.testing.assert_array_equal(t.accelerations_rad_s2, plain.accelerations_rad_s2)
        assert t.wheel_momentum_Nms is not None
    loose = time_parameterize(path, vmax, amax, wheel=WheelModel(sc.robot, REF, 1e7, 1e7))
    np.testing.assert_allclose(loose.times_s, plain.times_s, rtol=1e-12, atol=1e-12)


def test_free_floating_refuses_the_paper_2dof_motion_and_accepts_a_heavy_spacecraft(paper_scenario, paper_path):
    sc, path = paper_scenario(2), paper_path(2)
    robot = sc.robot
    vmax, amax = joint_limits(sc)
    traj = time_parameterize(path, vmax, amax, robot.planned_names)
    rep = reaction_report(robot, REF, sc.scene, path, traj, acs_mode="free_floating",
                          position_tolerance_m=0.02)
    assert not rep.ok
    assert rep.free_floating_tip_miss_m > 0.1
    assert f"{rep.free_floating_tip_miss_m:.3f} m" in rep.reason
    assert 5.0 < abs(rep.free_floating_attitude_change_deg) < 30.0
    # the oracle agrees that the drifted arm hits the target
    resp = free_floating_response(robot, REF, traj.positions_rad, sc.scene.target.grasp_point_m)
    assert rep.free_floating_collides
    assert inside_target_or_margin(robot, sc.scene, resp.q_full_rad, resp.body_position_m).any()
    grasp = sc.scene.target.grasp_point_m
    assert np.isclose(np.linalg.norm(resp.tip_m - grasp), rep.free_floating_tip_miss_m)
    # a very heavy spacecraft barely moves: accepted
    heavy = reaction_report(robot, HEAVY, sc.scene, path, traj, acs_mode="free_floating",
                            position_tolerance_m=0.02)
    assert heavy.ok, heavy.reason
    assert heavy.free_floating_tip_miss_m < 0.02 and not heavy.free_floating_collides
    resp_h = free_floating_response(robot, HEAVY, traj.positions_rad)
    assert not inside_target_or_margin(robot, sc.scene, resp_h.q_full_rad, resp_h.body_position_m).any()
    # held mode never refuses without wheel limits, and reports the same free-floating figures
    held = reaction_report(robot, REF, sc.scene, path, traj)
    assert held.ok and held.free_floating_tip_miss_m == rep.free_floating_tip_miss_m
    assert held.peak_wheel_momentum_Nms > 50.0


def test_drift_check_certifies_a_clear_motion(paper_scenario, paper_path):
    sc, path = paper_scenario(3), paper_path(3)
    chk = check_drifted(sc.robot, HEAVY, sc.scene, path)
    assert chk.ok and chk.min_clearance_m > sc.scene.safety_margin_m


def test_the_drifted_validator_fails_every_interval_the_drifted_arm_hits_in(paper_scenario, paper_path):
    """
    ``reaction.DriftedValidator`` (the chain's certification, free floating): per interval, sound.

    The paper's 2-DOF path with the reference spacecraft free: the drifted arm reaches the
    target.  Oracle: the test's simulator over 16 substeps a row interval and the target's
    square by points along the links; every interval where it finds the arm within the margin
    is failed, the intervals before the first such are passed, and a held check of the same
    rows (the scene's ``MotionValidator``) passes them all (the frame is what differs).
    """
    from spacerobot_planner.motion import MotionValidator
    from spacerobot_planner.reaction import DriftedValidator
    sc, path = paper_scenario(2), paper_path(2)
    rows = path[::6]
    motions = MotionValidator.for_scene(sc.robot, sc.scene)
    got = DriftedValidator(motions, REF).check(rows)
    assert not got.ok and got.interval_ok.shape == (len(rows) - 1,)
    assert motions.check(rows).ok
    sub = 16
    hit = np.zeros(len(rows) - 1, bool)
    q, body = simulate_free_floating(sc.robot, REF, np.vstack(
        [np.linspace(a, b, sub, endpoint=False) for a, b in zip(rows[:-1], rows[1:])] + [rows[-1:]]), sub=4)
    inside = inside_target_or_margin(sc.robot, sc.scene, q, body)
    for k in range(len(rows) - 1):
        hit[k] = inside[k * sub:(k + 1) * sub + 1].any()
    assert hit.any() and not hit[0]
    assert not got.interval_ok[hit].any(), np.flatnonzero(hit & got.interval_ok)
    first = int(np.flatnonzero(hit)[0])
    assert got.interval_ok[:max(0, first - 2)].all()


def test_bad_masses_and_modes_name_the_field(paper_scenario, paper_path):
    with pytest.raises(ValueError, match="dynamics.body_mass_kg"):
        MassProperties(body_mass_kg=0.0)
    with pytest.raises(ValueError, match=r"dynamics.link_masses_kg\[1\]"):
        MassProperties(link_masses_kg=(0.0, -1.0, 30.0))
    with pytest.raises(ValueError, match="dynamics.link_masses_kg"):
        WheelModel(_arm(), MassProperties(link_masses_kg=(0.0, 30.0), link_inertias_kgm2=(0.0, 1.0)))
    with pytest.raises(ValueError, match="acs.max_wheel_torque_Nm"):
        WheelModel(_arm(), REF, 10.0, -1.0)
    sc, path = paper_scenario(3), paper_path(3)
    with pytest.raises(ValueError, match="acs.mode"):
        reaction_report(sc.robot, REF, sc.scene, path, acs_mode="off")


def test_compensated_free_floating_plan_reaches_the_handle(paper_scenario, paper_path):
    """
    Stretch goal: a drift-compensated plan reaches the handle.

    The goal is corrected for the predicted drift and replanned until the free-floating arm reaches
    the grasp; checked with the test's own simulator.
    """
    from spacerobot_planner.free_floating import plan_free_floating
    sc, path = paper_scenario(2), paper_path(2)
    robot, grasp = sc.robot, sc.scene.target.grasp_point_m
    # the oracle first agrees that the uncompensated plan misses
    q0, b0 = simulate_free_floating(robot, REF, path)
    tip0 = robot.tip_position(q0[-1]) + b0[-1]
    assert np.linalg.norm(tip0 - grasp) > 0.5
    assert np.isclose(np.degrees(q0[-1, 0] - q0[0, 0]), free_floating_response(robot, REF, path).attitude_change_deg,
                      atol=0.02)
    cp = plan_free_floating(sc, sc.start_rad, sc.goal_rad, masses=REF, position_tolerance_m=0.02)
    assert cp.ok, cp.reason
    assert len(cp.history) > 2 and cp.history[0][0] > 0.5
    q, b = simulate_free_floating(robot, REF, cp.plan.path_rad)
    tip = robot.tip_position(q[-1]) + b[-1]
    assert np.linalg.norm(tip - grasp) < 0.02
    assert not inside_target_or_margin(robot, sc.scene, q, b).any()
    rep = reaction_report(robot, REF, sc.scene, cp.plan.path_rad, acs_mode="free_floating")
    assert rep.ok and not rep.free_floating_collides
    with pytest.raises(ValueError, match="robot.planned_joints"):
        plan_free_floating(paper_scenario(3), paper_scenario(3).start_rad)
