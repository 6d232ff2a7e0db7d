"""
The chain after the path (adapters.post_process): the controller's motion stays within the limits.

Oracle: joint_trajectory_controller's interpolation of the published points rebuilt with
SciPy's ``BPoly.from_derivatives`` (a piecewise polynomial matching position, velocity and
acceleration at both ends of each segment: the controller's quintic), sampled densely, against
the scenario's limits; the wheels' load of that motion by the test's own momentum sum
(``oracles.wheel_load``).  No code of the package's sampler or momentum model is used.
"""
import os
import re

from dataclasses import replace

import numpy as np
import pytest

from oracles import controller_motion, controller_wheel_load
from spacerobot_planner.adapters import post_process
from spacerobot_planner.settings import JointLimits
from spacerobot_planner.timing import timed_motion


def _controller_peaks(traj):
    """(dof,) peak |velocity| and |acceleration| of the quintic through the points, per joint."""
    _, v, a = controller_motion(traj, 40 * len(traj.times_s))
    return np.max(np.abs(v), axis=0), np.max(np.abs(a), axis=0)


LIMITS = [([30.0, 60.0, 60.0], [60.0, 120.0, 120.0]), ([90.0, 180.0, 180.0], [360.0, 720.0, 720.0])]


@pytest.mark.parametrize("vmax_deg_s, amax_deg_s2", LIMITS, ids=["moderate", "fast"])
def test_the_controllers_interpolation_of_the_published_points_keeps_the_limits(
        paper_scenario, paper_path, vmax_deg_s, amax_deg_s2):
    sc = paper_scenario(3)
    limits = JointLimits(np.radians(vmax_deg_s), np.radians(amax_deg_s2))
    sc = replace(sc, joint_limits=limits)
    out = post_process(sc, paper_path(3), start_rad=sc.start_rad)
    traj = out.trajectory
    idx = list(sc.robot.planned_joints)
    vpk, apk = _controller_peaks(traj)
    v_ratio = vpk / np.radians(vmax_deg_s)[idx]
    a_ratio = apk / np.radians(amax_deg_s2)[idx]
    assert np.all(v_ratio <= 1.0 + 2e-3), f"velocity over the limits: {v_ratio}"
    assert np.all(a_ratio <= 1.0 + 2e-3), f"acceleration over the limits: {a_ratio}"
    # and it is not slowed for nothing: some joint comes within 15 % of a limit
    assert max(v_ratio.max(), a_ratio.max()) > 0.85, (v_ratio, a_ratio)
    np.testing.assert_allclose(traj.positions_rad[0], sc.start_rad, atol=1e-9)
    np.testing.assert_allclose(traj.positions_rad[-1], paper_path(3)[-1], atol=1e-9)


@pytest.mark.parametrize("vmax_deg_s, amax_deg_s2", LIMITS, ids=["moderate", "fast"])
@pytest.mark.parametrize("dof", [2, 3])
def test_the_retimings_count_says_why_the_first_timing_was_not_published(
        paper_scenario, paper_path, dof, vmax_deg_s, amax_deg_s2):
    """
    ``Processed.retimings`` counts the timings after the first, each for the controller's overshoot.

    The first timing's points (the time-optimal trajectory from rest, resampled as the chain does)
    moved by the controller (the test's quintics) overshoot a limit by more than the chain's
    tolerance exactly when the chain timed the path again; with none, the published points are
    that first timing's.
    """
    from spacerobot_planner.adapters import RESAMPLE_STEP_S
    from spacerobot_planner.published import resample
    sc = paper_scenario(dof)
    idx = list(sc.robot.planned_joints)
    n = sc.robot.n_joints
    vmax, amax = np.radians((vmax_deg_s * n)[:n]), np.radians((amax_deg_s2 * n)[:n])
    sc = replace(sc, joint_limits=JointLimits(vmax, amax))
    out = post_process(sc, paper_path(dof), start_rad=sc.start_rad)
    dense, _ = timed_motion(sc, paper_path(dof), sc.start_rad)
    first = resample(dense, None, time_step_s=RESAMPLE_STEP_S).trajectory
    vpk, apk = _controller_peaks(first)
    over = max(float(np.max(vpk / vmax[idx])), float(np.max(apk / amax[idx])))
    print(f"\n{dof}-DOF: the first timing's controller motion at {over:.4f} x a limit; "
          f"timed again {out.retimings} times")
    if out.retimings == 0:
        assert over <= 1.0 + 2e-3
        np.testing.assert_array_equal(out.trajectory.times_s, first.times_s)
        np.testing.assert_array_equal(out.trajectory.positions_rad, first.positions_rad)
    else:
        assert over > 1.0 + 1e-3
        assert out.trajectory.duration_s > first.duration_s


def test_from_rest_the_controllers_motion_keeps_the_limits_on_random_scenes():
    """
    From rest, the published points' controller motion keeps the joint limits on the random family's plans.

    30 plans of ``bench scenes``' 2-DOF family (seeded): where lowering the limits along stretches
    and then once along the whole path still left the controller's quintics over a limit, the chain
    published them as they were: one of these 30 at 1.0070 x the acceleration limit.  Oracle
    as above (SciPy's quintics, 40 samples per point, the scenario's limits and scaling factors).
    """
    from spacerobot_planner.bench.scenes import plan_problems
    problems = plan_problems(np.random.default_rng([5, 2]), 2)
    worst, planned = 0.0, 0
    while planned < 30:
        sc, start, planner, goal = next(problems)
        res = planner.plan(start, goal)
        if not res.ok:
            continue
        planned += 1
        traj = post_process(sc, res.path_rad, start_rad=start).trajectory
        jl = sc.joint_limits
        vmax = np.asarray(jl.max_velocity_rad_s, dtype=float)[list(sc.robot.planned_joints)] * jl.velocity_scaling
        amax = (np.asarray(jl.max_acceleration_rad_s2, dtype=float)[list(sc.robot.planned_joints)]
                * jl.acceleration_scaling)
        vpk, apk = _controller_peaks(traj)
        worst = max(worst, float(np.max(vpk / vmax)), float(np.max(apk / amax)))
    assert worst <= 1.0 + 2e-3, f"the controller's motion reaches {worst:.4f} x a limit"


@pytest.mark.parametrize("dof", [2, 3])
def test_a_refused_trajectory_is_the_first_timings_verdict_without_timing_again(paper_scenario, paper_path, dof,
                                                                                monkeypatch):
    """
    Free floating, the paper's scenes drift onto the obstacles or miss the grasp: refused.

    Oracle: the core's timing of the path from the start with its reaction report
    (``timing.timed_motion``, no chain): the chain answers that verdict with that round's dense
    points (what a reported round stops at), and times the path no more often than the same
    chain with the spacecraft held (whose reaction does not matter): the refusal does not run
    the chain again.
    """
    from spacerobot_planner import adapters, timing
    sc = paper_scenario(dof)
    ff = replace(sc, acs=replace(sc.acs, mode="free_floating"))
    held = replace(sc, acs=replace(sc.acs, mode="held", max_wheel_momentum_Nms=0.0, max_wheel_torque_Nm=0.0))
    path = paper_path(dof)
    dense, report = timing.timed_motion(ff, path, sc.start_rad)
    assert report is not None and not report.ok
    timings = []
    real = adapters.timed_motion

    def counted(*a, **k):
        timings.append(1)
        return real(*a, **k)

    monkeypatch.setattr(adapters, "timed_motion", counted)
    assert post_process(held, path, start_rad=sc.start_rad).refused is None
    n_held, timings[:] = len(timings), []
    out = post_process(ff, path, start_rad=sc.start_rad)
    assert out.refused == report.reason
    assert len(timings) == n_held, f"timed {len(timings)} times, {n_held} held"
    np.testing.assert_array_equal(out.dense.times_s, dense.times_s)
    np.testing.assert_array_equal(out.dense.positions_rad, dense.positions_rad)
    assert len(out.trajectory) == len(dense)
    assert out.arm is None and out.attitude is None and not out.certified


@pytest.mark.parametrize("offset_deg", [(0.0, 0.0, 0.0), (11.0, -18.0, -37.0), (-16.0, -6.0, -38.0)],
                         ids=["file_start", "start_b", "start_c"])
def test_the_controllers_motion_keeps_the_wheel_limits(offset_deg):
    """
    The wheels' load of the controller's motion, not only at the published points, within their limits.

    config/servicer_3dof.yaml: wheels of 50 N·m·s and 0.5 N·m, the attitude held.  Oracle: the
    quintic through the points (SciPy) and the test's own momentum sum; the torque limit binds
    (within 3 % of it somewhere: not slowed for nothing).  At the points alone the
    limits held before the chain checked the controller's motion; between them the torque
    reached up to a third above its limit (40 random starts: 39 above it).  The chain's
    reaction report gives the peaks of that motion (it gave those of the re-timed points).
    The re-timing lowers the limits only where the controller overshoots them: the published
    trajectory lasts at most 8 % longer than the time-optimal one (the limits lowered along the
    whole path, 13-17 % on these three starts).
    """
    from spacerobot_planner.config import load_scenario
    from spacerobot_planner.planner import Planner
    sc = load_scenario(os.path.join(os.path.dirname(__file__), "..", "config", "servicer_3dof.yaml"))
    start = sc.start_rad + np.radians(offset_deg)
    res = Planner(sc).plan(start, sc.goal_rad)
    assert res.ok, res.reason
    out = post_process(sc, res.path_rad, start_rad=start)
    assert out.refused is None and out.certified
    h, tau = controller_wheel_load(sc, out.trajectory, 40 * len(out.trajectory.times_s))
    h_ratio = np.max(np.abs(h)) / sc.acs.max_wheel_momentum_Nms
    tau_ratio = np.max(np.abs(tau)) / sc.acs.max_wheel_torque_Nm
    assert h_ratio <= 1.0 + 2e-3, f"wheel momentum over its limit: {h_ratio:.4f}"
    assert tau_ratio <= 1.0 + 2e-3, f"wheel torque over its limit: {tau_ratio:.4f}"
    assert tau_ratio >= 0.97, f"the torque limit does not bind: {tau_ratio:.4f}"
    optimal = timed_motion(sc, res.path_rad, start, report=False)[0]
    assert out.trajectory.duration_s <= 1.08 * optimal.duration_s, \
        f"{out.trajectory.duration_s:.1f} s published, {optimal.duration_s:.1f} s time-optimal"
    # the report (the node's /diagnostics) gives the peaks of that motion, not of the points
    np.testing.assert_allclose([out.reaction.peak_wheel_momentum_Nms, out.reaction.peak_wheel_torque_Nm],
                               [np.max(np.abs(h)), np.max(np.abs(tau))], rtol=2e-3)


def test_another_robots_validator_is_refused_by_name_not_run():
    """
    A validator of another robot's joints (``post_process(motions=...)``, ``MotionValidator.check``) is a ValueError.

    Its kernels write each row into that robot's configuration by its planned joints' indices,
    unchecked: a 3-joint path checked by a 4-joint validator read and wrote past its arrays (a heap
    corrupted, a crash later, seen in a bench harness).  Now the chain and the check name the
    mismatch and run nothing.
    """
    from pathlib import Path

    from spacerobot_planner.config import load_scenario
    from spacerobot_planner.motion import MotionValidator

    config = Path(__file__).resolve().parent.parent / "config"
    paper, other = load_scenario(config / "paper_3dof.yaml"), load_scenario(config / "servicer_4joint.yaml")
    assert len(paper.robot.planned_periodic) != len(other.robot.planned_periodic)
    lo, hi = paper.robot.planned_lower_rad, paper.robot.planned_upper_rad
    path = np.linspace(lo + 0.25 * (hi - lo), lo + 0.75 * (hi - lo), 8)
    validator = MotionValidator.for_scene(other.robot, other.scene)
    with pytest.raises(ValueError, match="motions: a validator of 4 planned joints for a path of 3"):
        post_process(paper, path, motions=validator)
    for rows in (path, path[:1], path[:, :2]):
        with pytest.raises(ValueError, match="rows of this validator's 4 planned joints"):
            validator.check(rows)
        with pytest.raises(ValueError, match="rows of this validator's 4 planned joints"):
            validator.check_kept(rows)
    assert post_process(paper, path).trajectory is not None       # its own validator: as ever


def test_an_uncertified_motion_past_a_joint_bound_is_said_to_pass_it_not_to_come_within_the_margin():
    """
    The log's text for a controller's motion that leaves the elbow's bound names the bound, not the safety margin.

    An audit found a plan along the elbow's -180° bound whose quintics passed it by 0.0055° while the
    text said "comes within the safety margin 0.05 m ...: clearance 0.055 m".  Here two points on
    the bound with the elbow moving outwards at both: the quintic between them bulges past it.
    Oracle: SciPy's quintic (``oracles.controller_interpolation``) for the excess, the reference
    geometry (``oracles.ref_clearance``) for the clearance along it.
    """
    from types import SimpleNamespace
    from oracles import controller_interpolation, ref_clearance
    from spacerobot_planner.adapters import uncertified_text
    from spacerobot_planner.config import load_scenario
    from spacerobot_planner.motion import MotionValidator
    from spacerobot_planner.trajectory import Trajectory
    sc = load_scenario(os.path.join(os.path.dirname(__file__), "..", "config", "paper_2dof.yaml"))
    robot = sc.robot
    names = robot.planned_names
    elbow = names.index("elbow")
    lo = robot.planned_lower_rad[elbow]
    q = np.zeros((2, 2))
    q[:, 1 - elbow] = np.radians([60.0, 62.0])
    q[:, elbow] = lo
    v = np.zeros((2, 2))
    v[:, 1 - elbow] = np.radians(2.0)
    v[:, elbow] = -1e-3                                   # outwards, past the bound
    t = np.array([0.0, 1.0])
    traj = Trajectory(tuple(names), t, q, v, np.zeros((2, 2)), np.ones(2), np.ones(2))
    ts = np.linspace(0.0, 1.0, 2001)
    qs = controller_interpolation(t, q, v, np.zeros((2, 2)))(ts)[0]
    excess = float(np.max(lo - qs[:, elbow]))
    assert excess > 1e-5                                  # the test's premise
    clearance = min(ref_clearance(robot, sc.scene, row) for row in qs[::50])
    text = uncertified_text(sc, SimpleNamespace(trajectory=traj), MotionValidator.for_scene(robot, sc.scene))
    said = re.search(rf"passes elbow's bound {np.degrees(lo):g}° by ([0-9.e+-]+)°", text)
    assert said and abs(float(said.group(1)) - np.degrees(excess)) <= 0.06 * np.degrees(excess), (text, excess)
    assert clearance > sc.scene.safety_margin_m + 1e-3, clearance         # the posture is free: ...
    assert "safety margin" not in text, (text, clearance)                  # ... the margin is not the cause


def _touching_paths(sc, rng, count):
    """Yield V paths of the paper 2-DOF arm, its elbow on its ±180° bound at one sample, clear of the target."""
    from oracles import ref_clearance
    robot = sc.robot
    e, s = list(robot.planned_names).index("elbow"), list(robot.planned_names).index("shoulder")
    while count:
        depth = np.radians([rng.uniform(0.2, 2.0), rng.uniform(5.0, 30.0)])[rng.permutation(2)]   # one side shallow
        travel = np.radians(rng.uniform(10.0, 40.0, 2))
        side = int(rng.integers(2))                         # 0: the lower bound, 1: the upper
        bound = (robot.planned_lower_rad, robot.planned_upper_rad)[side][e]
        inward = 1.0 if side == 0 else -1.0
        path = np.zeros((3, 2))
        path[:, s] = np.radians(40.0) + np.concatenate([[0.0], np.cumsum(travel)])
        path[:, e] = bound + inward * np.array([depth[0], 0.0, depth[1]])
        path[1, e] = bound                                  # on the bound itself
        rows = np.concatenate([np.linspace(path[0], path[1], 15), np.linspace(path[1], path[2], 15)])
        if min(ref_clearance(robot, sc.scene, row) for row in rows) > sc.scene.safety_margin_m + 0.05:
            count -= 1
            yield path, e, bound, inward


def test_paths_that_touch_the_elbows_bound_at_one_sample_are_published_within_it():
    """
    A path that touches the elbow's bound at one sample and turns back: the controller's motion stays within it.

    The spline the time parameterisation fits through the samples rang at the corner and passed the
    bound between the samples (a path with one side shallow: the elbow approaching the bound by 1°
    while the shoulder turns 30°), so the controller's quintics passed it too (9 of these 24 paths
    before, up to 9.0e-5 rad, all published uncertified; 71 of 200 of the family, up to 2.2e-4 rad;
    2.8e-5 rad in a helper's audit of planned paths).  Oracle: SciPy's quintic through the published points
    (``oracles.controller_interpolation``), 256 samples a segment, against the bound.
    """
    from oracles import controller_interpolation
    from spacerobot_planner.config import load_scenario
    sc = load_scenario(os.path.join(os.path.dirname(__file__), "..", "config", "paper_2dof.yaml"))
    rng = np.random.default_rng(20261207)
    for path, e, bound, inward in _touching_paths(sc, rng, 24):
        out = post_process(sc, path)
        tr = out.trajectory
        f = controller_interpolation(tr.times_s, tr.positions_rad, tr.velocities_rad_s, tr.accelerations_rad_s2)
        ts = np.concatenate([np.linspace(a, b, 256, endpoint=False) for a, b in zip(tr.times_s[:-1], tr.times_s[1:])])
        excess = float(np.max(inward * (bound - f(ts)[0][:, e])))
        assert excess <= 1e-12, (np.degrees(path).round(3).tolist(), excess)
        assert out.certified, np.degrees(path).round(3).tolist()


#: plans of helpers' audits whose published quintics passed a joint's bound (start, goal rad; debris polygons, m;
#: the scene's configuration): paper 3-DOF (elbow), then servicer 3-DOF (elbow, wheel-limited) and 4-joint (wrist)
_AUDITED = [
    ([0.6206051596657169, -0.9309960453718302, -np.pi], [-1.8568973375480478, 1.5472109965953402, np.pi], []),
    ([1.4038058482168836, -2.0766362455735017, -3.0957013520059236],
     [-2.5323015914154325, 0.9917158016116003, 3.1180578602374838], []),
    ([1.9575845398501137, 1.2214404146062163, 3.1240436135664584],
     [-0.1982480962106834, -1.8163662767130224, -3.1301408955741],
     [[[4.18506790365893, 1.439098645532412], [4.416840053411597, 0.3856207197216852],
       [4.601692444604066, 0.502415691533155], [4.6904483177013905, 0.613387515697535]]]),
    ([-0.4952364349810252, 2.1115976400381324, np.pi], [-1.7551606341168855, 2.1480702958325555, -3.117269069664197],
     [[[5.353536758877566, 1.7998093972619682], [5.095861309337421, 1.943175519657909],
       [4.65453737921121, 1.6393101128131544]]]),
    ([1.5599577624495495, -1.9298303126199137, 2.8416794482208796],
     [-2.374749775244918, -2.250348356888216, 3.0529447826307137],
     [[[-1.3111096758502798, 0.9447576755648737], [-1.7101718225107823, 0.9489938270605904],
       [-1.9000933603290817, 0.5853225759431299], [-1.7333892639728876, 0.29618058057470276],
       [-1.5378170762304635, 0.2288398441379597], [-1.3992685135967649, 0.24556037416493592]]]),
    ([-2.9253372212439235, 1.3555122122642436, 3.0927736167717885],
     [2.3731648997812362, -2.080054976229631, 3.131884431232807],
     [[[-1.4648480246550182, 2.4794231267565205], [-1.4874035695796934, 2.477819378382993],
       [-1.4650630475864321, 2.265617448459524], [-1.371334691541324, 2.327978092323189]]], "servicer_3dof"),
    ([1.195581987093612, 1.42823631804736, 3.091413624421937],
     [-1.4323584625834744, -1.8131888134381584, 2.9501630376982453], [], "servicer_3dof"),
    ([2.16427900774523, -0.926299728328039, -2.663297602504987, 2.579404266282889],
     [1.0672376269341832, 2.222871517310402, -2.8593143483654746, 2.5837948103630115],
     [[[-0.06652260689816808, 3.4348673808528485], [0.05941127811289576, 3.2480686851993235],
       [-0.17773819840121424, 3.274434124947546], [0.016763404849532426, 2.8772593181615655],
       [0.0325997845071998, 2.5372243314142002], [0.705975043308293, 2.937157752163229]]], "servicer_4joint"),
]


@pytest.mark.parametrize("case", range(len(_AUDITED)))
def test_planned_paths_along_and_onto_a_joints_bound_are_published_within_it(case):
    """
    Plans from helpers' audits, a joint starting, running or ending on its bound: the published motion within it.

    The published quintics had passed the bound: the resampling dropped the sample where the path
    touches it or leaves a run along it (up to 8.0e-7 rad), or a start on the bound held at rest on
    the path started as t⁴ (2.9e-9 rad), and were certified (8 samples a segment); on the servicer
    scenes (wheel-limited) the quintic of a long, slow segment next to a touch (up to 7.3e-4 rad).
    Oracle: SciPy's quintic through the published points (``scipy.interpolate.BPoly``) and its exact
    extrema (the roots of its derivative), against the bounds of every bounded joint.
    """
    from scipy.interpolate import BPoly, PPoly
    from spacerobot_planner.config import load_scenario
    from spacerobot_planner.planner import Planner
    from spacerobot_planner.scene import Scene
    start, goal, debris, config = (_AUDITED[case] + ("paper_3dof",))[:4]
    base = load_scenario(os.path.join(os.path.dirname(__file__), "..", "config", f"{config}.yaml"))
    sc = base.with_scene(Scene(target=base.scene.target, debris_m=tuple(np.array(p) for p in debris),
                               safety_margin_m=base.scene.safety_margin_m))
    res = Planner(sc).plan(np.array(start), np.array(goal))
    assert res.ok, res.reason
    out = post_process(sc, res.path_rad)
    tr = out.trajectory
    robot = sc.robot
    on = 0
    for e in np.flatnonzero(~np.asarray(robot.planned_periodic)):
        lo, hi = robot.planned_lower_rad[e], robot.planned_upper_rad[e]
        on += int(np.isin(np.asarray(res.path_rad)[:, e], [lo, hi]).sum())
        bp = BPoly.from_derivatives(tr.times_s, np.stack([tr.positions_rad[:, e], tr.velocities_rad_s[:, e],
                                                          tr.accelerations_rad_s2[:, e]], axis=1))
        roots = PPoly.from_bernstein_basis(bp).derivative().roots(extrapolate=False)
        y = bp(np.concatenate([tr.times_s, roots[np.isfinite(roots)]]))
        assert max(lo - y.min(), y.max() - hi) <= 1e-12, (robot.planned_names[e], lo - y.min(), y.max() - hi)
    assert on                                                                       # premise: on a bound
    assert out.certified


def test_a_path_along_the_elbows_bound_is_published_without_passing_it():
    """
    A path that runs along the elbow's -180° bound: the controller's motion stays on it, and is certified.

    The path's samples there lie on the bound; the spline the time parameterisation fits through
    them leaves small velocities at them, and the controller's quintics between such points bulged
    past the bound (0.022° here; 0.0055° in a helper's audit), so the chain published its dense
    points uncertified.  Oracle: SciPy's quintic through the published points
    (``oracles.controller_interpolation``), 64 samples a segment, against the bound; the reference
    geometry for the path's clearance (the test's premise).
    """
    from oracles import controller_interpolation, ref_clearance
    from spacerobot_planner.config import load_scenario
    sc = load_scenario(os.path.join(os.path.dirname(__file__), "..", "config", "paper_2dof.yaml"))
    robot = sc.robot
    names = list(robot.planned_names)
    e, s = names.index("elbow"), names.index("shoulder")
    lo = robot.planned_lower_rad[e]
    path = np.tile(np.asarray(sc.start_rad, dtype=float), (61, 1))
    path[:, s] = np.radians(np.linspace(40.0, 100.0, 61))
    path[:, e] = np.radians(np.concatenate([np.linspace(-170.0, -180.0, 15), np.full(31, -180.0),
                                            np.linspace(-180.0, -170.0, 15)]))
    path[15:46, e] = lo                                          # on the bound itself
    assert min(ref_clearance(robot, sc.scene, row) for row in path) > sc.scene.safety_margin_m + 0.05
    out = post_process(sc, path)
    tr = out.trajectory
    f = controller_interpolation(tr.times_s, tr.positions_rad, tr.velocities_rad_s, tr.accelerations_rad_s2)
    ts = np.concatenate([np.linspace(a, b, 64, endpoint=False) for a, b in zip(tr.times_s[:-1], tr.times_s[1:])])
    q = f(ts)[0]
    assert float(np.max(lo - q[:, e])) <= 1e-12, np.degrees(np.max(lo - q[:, e]))
    assert out.certified


def _controller_ratios(sc, tr):
    """Return the largest velocity and acceleration of SciPy's quintics through ``tr``'s points over the limits."""
    from oracles import controller_interpolation, quintic_acceleration_peaks
    cols = [list(sc.robot.joint_names).index(n) for n in tr.joint_names]
    amax = np.asarray(sc.joint_limits.max_acceleration_rad_s2)[cols]
    vmax = np.asarray(sc.joint_limits.max_velocity_rad_s)[cols]
    acc = quintic_acceleration_peaks(tr.times_s, tr.positions_rad, tr.velocities_rad_s, tr.accelerations_rad_s2)
    f = controller_interpolation(tr.times_s, tr.positions_rad, tr.velocities_rad_s, tr.accelerations_rad_s2)
    vel = np.max(np.abs(f(np.linspace(0.0, tr.times_s[-1], 20001))[1]), axis=0)
    return float(np.max(vel / vmax)), float(np.max(acc / amax))


@pytest.mark.parametrize("case", ["audited", "no_retiming_left"])
def test_a_chain_from_rest_that_overshoots_after_its_last_re_timing_is_published_slowed_within_the_limits(
        case, monkeypatch):
    """
    A chain from rest whose controller's motion still overshoots after its last re-timing: its points slowed.

    A helper's audit (1 of 130 free-floating plans): after the last re-timing the controller's
    quintics through the published points reached 1.0059 × the elbow's acceleration limit, and
    the chain published them as they were, certified.  "audited": that plan; "no_retiming_left":
    the paper 3-DOF plan with no re-timing allowed (its first round overshoots: the premise, with
    the slowing taken out).  Oracle: SciPy's quintics through the published points, their exact
    acceleration peaks (``oracles.quintic_acceleration_peaks``) and velocities at 20 001 times,
    against the scenario's limits with the chain's tolerance; the published points are dense ones.
    """
    from spacerobot_planner import adapters
    from spacerobot_planner.adapters import CONTROLLER_TOL
    from spacerobot_planner.config import load_scenario
    from spacerobot_planner.planner import Planner
    name = "free_floating_capture" if case == "audited" else "paper_3dof"
    sc = load_scenario(os.path.join(os.path.dirname(__file__), "..", "config", f"{name}.yaml"))
    if case == "audited":
        res = Planner(sc).plan(np.array([-0.33600434591624095, 1.8975952542528]))
    else:
        res = Planner(sc).plan(sc.start_rad, sc.goal_rad)
        monkeypatch.setattr(adapters, "CONTROLLER_RETIMES", 1)
        monkeypatch.setattr(adapters, "WHOLE_PATH_RETIMES", 0)
        with monkeypatch.context() as m:
            m.setattr(adapters, "_slowed", lambda scenario, got, *a: got)
            before = _controller_ratios(sc, post_process(sc, res.path_rad).trajectory)
        assert max(before) > 1.0 + 10 * CONTROLLER_TOL, before                        # the premise
    assert res.ok, res.reason
    out = post_process(sc, res.path_rad)
    assert out.certified
    tr = out.trajectory
    vel, acc = _controller_ratios(sc, tr)
    assert vel <= 1.0 + CONTROLLER_TOL and acc <= 1.0 + CONTROLLER_TOL, (vel, acc)
    assert np.array_equal(tr.positions_rad, out.dense.positions_rad[out.indices])
    assert np.array_equal(tr.times_s, out.dense.times_s[out.indices])


@pytest.mark.parametrize("seed", range(3))
def test_a_slowed_trajectory_is_the_controllers_motion_at_a_slower_time(seed):
    """
    ``Trajectory.slowed(k)``: the quintics through its points are the old ones at t / k.

    Oracle: SciPy's quintics (``oracles.controller_interpolation``) through both, at 500 times:
    positions equal, velocities ÷ k, accelerations ÷ k²; a factor below 1 is refused.
    """
    from oracles import controller_interpolation
    from spacerobot_planner.trajectory import Trajectory
    rng = np.random.default_rng(seed)
    m, n = 7, 3
    t = np.concatenate([[0.0], np.cumsum(rng.uniform(0.1, 1.0, m - 1))])
    q, v, a = rng.normal(size=(m, n)), rng.normal(size=(m, n)), rng.normal(size=(m, n))
    tr = Trajectory(("a", "b", "c"), t, q, v, a, np.ones(n), np.ones(n), path_speed=rng.uniform(0, 1, m),
                    active_limit=np.array(["velocity:a", "acceleration:b", "wheel_torque", "wheel_momentum",
                                           "velocity:c", "acceleration:a", "velocity:b"]),
                    limit_ratio=np.full(m, 0.9), wheel_momentum_Nms=rng.normal(size=m),
                    wheel_torque_Nm=rng.normal(size=m))
    k = rng.uniform(1.0, 3.0)
    slow = tr.slowed(k)
    ts = np.linspace(0.0, t[-1], 500)
    old, new = controller_interpolation(t, q, v, a)(ts), controller_interpolation(
        slow.times_s, slow.positions_rad, slow.velocities_rad_s, slow.accelerations_rad_s2)(k * ts)
    np.testing.assert_allclose(new[0], old[0], atol=1e-12)
    np.testing.assert_allclose(new[1], old[1] / k, atol=1e-12)
    np.testing.assert_allclose(new[2], old[2] / k ** 2, atol=1e-11)
    np.testing.assert_allclose(slow.wheel_torque_Nm, tr.wheel_torque_Nm / k ** 2)
    np.testing.assert_allclose(slow.wheel_momentum_Nms, tr.wheel_momentum_Nms / k)
    np.testing.assert_allclose(slow.limit_ratio, 0.9 / np.array([k, k * k, k * k, k, k, k * k, k]))
    with pytest.raises(ValueError, match="factor"):
        tr.slowed(0.99)


def test_the_clearance_reported_for_the_published_motion_is_no_more_than_at_its_goal():
    """
    The servicer 4-joint arm grasping a moved target: the reported clearance is at most the goal posture's.

    The certification's walk passes over samples its certificates cover, the last point among
    them: a helper's audit (149 of 297 servicer plans) found the reported clearance up to 27 mm
    above the least along the motion, always at the goal, where the wrist link grasps 0.100 m from
    the target (this plan: 0.1272 m reported).  Oracle: the test's own geometry
    (``oracles.ref_clearance``) at the first and last published points.
    """
    from oracles import ref_clearance
    from spacerobot_planner.config import load_scenario
    from spacerobot_planner.planner import Planner
    base = load_scenario(os.path.join(os.path.dirname(__file__), "..", "config", "servicer_4joint.yaml"))
    target = replace(base.scene.target, center_m=(-2.9327579199404923, -2.7572330263388487),
                     yaw_rad=np.radians(9.672616950900988))
    sc = base.with_scene(replace(base.scene, target=target))
    res = Planner(sc).plan(np.radians([67.08062209990837, -66.96970926931176, 81.76392293632722, 33.0339328712796]))
    assert res.ok, res.reason
    out = post_process(sc, res.path_rad)
    tr = out.trajectory
    ends = min(ref_clearance(sc.robot, sc.scene, tr.positions_rad[i]) for i in (0, -1))
    assert out.certified and out.min_clearance_m <= ends + 1e-9, (out.min_clearance_m, ends)
