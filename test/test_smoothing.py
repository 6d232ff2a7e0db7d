"""Smoothing stage: unwrap, densify, dense check, shortcut, spline refinement, fallbacks."""

import numpy as np
import pytest

from oracles import shortest_grid_path
from spacerobot_planner.collision import CollisionChecker
from spacerobot_planner.motion import MotionValidator, check_path
from spacerobot_planner.smoothing import (DEFAULT_MAX_STEP_RAD, _median, _stretch_knots, densify_polyline,
                                          path_length_rad, shortcut_indices, smooth_path,
                                          spline_through)
from spacerobot_planner.joint_space import unwrap_path


@pytest.fixture(scope="module")
def sc2(paper_scenario):
    return paper_scenario(2)


@pytest.fixture(scope="module")
def chk2(sc2):
    return CollisionChecker(sc2.robot, sc2.scene)


def bounds(sc):
    r = sc.robot
    return r.planned_lower_rad, r.planned_upper_rad, r.planned_periodic


def test_unwrap_path_crosses_seam_continuously():
    q = np.radians([[170.0, 10.0], [178.0, 12.0], [-176.0, 14.0], [-170.0, 16.0]])
    u = unwrap_path(q, (True, False))
    assert np.array_equal(u[0], q[0])
    assert np.allclose(np.degrees(u[:, 0]), [170.0, 178.0, 184.0, 190.0])
    assert np.array_equal(u[:, 1], q[:, 1])
    # a bounded joint is never unwrapped, whatever its jumps
    jump = np.radians([[0.0, 170.0], [0.0, -170.0]])
    assert np.array_equal(unwrap_path(jump, (True, False)), jump)


def test_densify_keeps_vertices_and_step():
    pts = np.radians([[0.0, 0.0], [10.0, 0.0], [10.0, 3.3], [-20.0, 7.0]])
    d = densify_polyline(pts, DEFAULT_MAX_STEP_RAD)
    assert np.max(np.linalg.norm(np.diff(d, axis=0), axis=1)) <= DEFAULT_MAX_STEP_RAD + 1e-15
    for v in pts:
        assert np.any(np.all(d == v, axis=1))
    assert np.isclose(path_length_rad(d), path_length_rad(pts))


def test_spline_reproduces_end_knots_exactly():
    k = np.radians([[0.0, 0.0], [20.0, 10.0], [40.0, 5.0], [55.5, -3.3]])
    q, s_knots, s_samples = spline_through(k)
    assert np.array_equal(q[0], k[0]) and np.array_equal(q[-1], k[-1])
    assert np.max(np.linalg.norm(np.diff(q, axis=0), axis=1)) <= DEFAULT_MAX_STEP_RAD
    assert len(s_knots) == len(k) and s_samples[-1] == s_knots[-1]


def _free_pair_with_colliding_middle(sc, chk):
    """
    Return two free configurations whose straight segment collides.

    Two free configurations whose straight segment collides in between (through the obstacle in the
    2-DOF C-space).
    """
    a = np.radians([96.0, 0.0])
    b = np.radians([30.0, 0.0])
    mid = np.radians([76.0, 0.0])
    assert chk.is_free(a) and chk.is_free(b) and not chk.is_free(mid)
    return a, b


def test_check_path_finds_collision_between_free_ends(sc2, chk2):
    a, b = _free_pair_with_colliding_middle(sc2, chk2)
    res = check_path(chk2, np.vstack([a, b]), *bounds(sc2))
    # the certified walk stops where it can no longer prove clearance above the margin
    assert not res.ok and not res.interval_ok[0] and res.min_clearance_m < sc2.scene.safety_margin_m + 1e-3
    # dense samples along a free stretch pass
    c = np.radians([96.0, 40.0])
    ok = check_path(chk2, densify_polyline(np.vstack([a, c]), DEFAULT_MAX_STEP_RAD), *bounds(sc2))
    assert ok.ok and ok.interval_ok.all() and ok.min_clearance_m > sc2.scene.safety_margin_m


def test_check_path_rejects_out_of_bounds(sc2, chk2):
    p = np.radians([[0.0, 170.0], [0.0, 181.0]])
    dense = densify_polyline(p, np.radians(0.1))
    assert chk2.is_free(dense).all()          # free everywhere, but the elbow leaves its bounds
    assert check_path(chk2, p[:1], *bounds(sc2)).ok
    assert not check_path(chk2, p, *bounds(sc2)).ok


def test_check_reuses_vertex_clearances_and_answers_the_same(sc2, chk2):
    # a path that leaves the free space in its middle and one that stays free
    a, b = _free_pair_with_colliding_middle(sc2, chk2)
    c = np.radians([96.0, 40.0])
    v = MotionValidator(chk2)
    for path in (densify_polyline(np.vstack([a, b]), DEFAULT_MAX_STEP_RAD),
                 densify_polyline(np.vstack([a, c, b + np.radians([0.0, 60.0])]), DEFAULT_MAX_STEP_RAD)):
        fresh = v.check(path)
        quick = v.check(path, certified=False)
        known = quick.vertex_clearance_m
        evaluated = np.isfinite(known)
        # the vertex clearances are the clearances of the rows themselves
        assert np.array_equal(known[evaluated], chk2.clearance_m(path[evaluated]))
        again = v.check(path, vertex_clearance_m=known)
        assert again.ok == fresh.ok
        assert np.array_equal(again.interval_ok, fresh.interval_ok)
        assert np.array_equal(again.interval_clearance_m, fresh.interval_clearance_m)
        assert again.n_checked < fresh.n_checked
    with pytest.raises(ValueError, match="vertex_clearance_m"):
        v.check(path, vertex_clearance_m=np.zeros(3))


def test_smooth_path_refuses_a_colliding_polyline(sc2, chk2):
    a, b = _free_pair_with_colliding_middle(sc2, chk2)
    assert smooth_path(chk2, np.vstack([a, b]), *bounds(sc2)) is None


def _detour(sc2):
    """Return a free staircase polyline around the obstacle tip (grid-like, 2° steps)."""
    a = np.radians([96.0, 0.0])
    b = np.radians([30.0, 0.0])
    up = np.radians(np.column_stack([np.full(46, 96.0), np.arange(0, 92, 2.0)]))
    over = np.radians(np.column_stack([np.arange(94, 28, -2.0), np.full(33, 90.0)]))
    down = np.radians(np.column_stack([np.full(45, 30.0), np.arange(88, -2, -2.0)]))
    w = np.vstack([up, over, down])
    assert np.array_equal(w[0], a) and np.array_equal(w[-1], b)
    return w


@pytest.mark.parametrize("shortcut", [True, False])
def test_smooth_path_is_verified_and_exact(sc2, chk2, shortcut):
    w = _detour(sc2)
    assert check_path(chk2, w, *bounds(sc2)).ok
    sp = smooth_path(chk2, w, *bounds(sc2), shortcut=shortcut)
    assert sp is not None
    assert np.array_equal(sp.path_rad[0], w[0]) and np.array_equal(sp.path_rad[-1], w[-1])
    assert np.max(np.linalg.norm(np.diff(sp.path_rad, axis=0), axis=1)) <= DEFAULT_MAX_STEP_RAD + 1e-12
    fine = check_path(chk2, sp.path_rad, *bounds(sc2), verify_step_rad=np.radians(0.05))
    assert fine.ok
    assert sp.length_rad < path_length_rad(w)          # smoother is shorter than the staircase
    assert sp.method == ("shortcut_spline" if shortcut else "spline")


@pytest.mark.parametrize("shortcut", [True, False])
def test_repeated_waypoints_are_passed_over_and_the_goal_kept_exact(sc2, chk2, shortcut):
    """
    Waypoints repeated exactly or within 1e-13 rad answer as the waypoints without them.

    (A grid node where the exact start or goal sits on it.)  The same path, ends exact (the goal
    too where it is a hair past the row before it), every step moving, the dense check clear.
    """
    w = _detour(sc2)
    k = len(w) // 2
    repeated = np.vstack([w[:1], w[:k], w[k - 1:k] + 1e-13, w[k:-1], w[-1:] + 1e-13, w[-1:]])
    sp = smooth_path(chk2, repeated, *bounds(sc2), shortcut=shortcut)
    plain = smooth_path(chk2, w, *bounds(sc2), shortcut=shortcut)
    assert sp is not None and sp.method == plain.method
    np.testing.assert_array_equal(sp.path_rad, plain.path_rad)
    assert np.array_equal(sp.path_rad[0], w[0]) and np.array_equal(sp.path_rad[-1], w[-1])
    assert np.min(np.linalg.norm(np.diff(sp.path_rad, axis=0), axis=1)) > 0.0
    assert check_path(chk2, sp.path_rad, *bounds(sc2), verify_step_rad=np.radians(0.05)).ok


def test_shortcut_keeps_clearance(sc2, chk2):
    w = _detour(sc2)
    margin = sc2.scene.safety_margin_m
    keep = shortcut_indices(chk2, w, *bounds(sc2), keep_clearance_m=0.05)
    assert keep[0] == 0 and keep[-1] == len(w) - 1 and np.all(np.diff(keep) > 0)
    assert len(keep) < len(w) // 4
    poly = check_path(chk2, w, *bounds(sc2)).interval_clearance_m
    for i, j in zip(keep[:-1], keep[1:]):
        seg = check_path(chk2, w[[i, j]], *bounds(sc2))
        need = min(poly[i:j].min(), margin + 0.05)
        assert seg.ok and seg.min_clearance_m >= need - 1e-12
    # without the clearance rule the shortcut trades distance from obstacles for length:
    # no longer, but closer to the margin (here 0.023 m against 0.073 m)
    greedy = shortcut_indices(chk2, w, *bounds(sc2), keep_clearance_m=0.0)
    assert path_length_rad(w[greedy]) <= path_length_rad(w[keep]) + 1e-12
    kept_clr = check_path(chk2, w[keep], *bounds(sc2)).min_clearance_m
    greedy_clr = check_path(chk2, w[greedy], *bounds(sc2)).min_clearance_m
    assert kept_clr >= margin + 0.05 - 1e-12 > greedy_clr


def _hugging_path(sc2):
    """
    Shortest face-step grid path (2° grid, test/oracles.py) from (96°, 0) to (30°, 0).

    It hugs the obstacle, so coarse splines through it cut corners.
    """
    from spacerobot_planner.cspace import build_cspace
    cs = build_cspace(sc2.robot, sc2.scene, sc2.grid, extra_margin_m=0.04)
    start, goal = sc2.grid.node_of(np.radians([96.0, 0.0])), sc2.grid.node_of(np.radians([30.0, 0.0]))
    return sc2.grid.config_of(shortest_grid_path(cs.occupied, sc2.grid.periodic, start, goal))


def test_spline_refines_where_it_cuts_a_corner(sc2, chk2):
    """
    Through sparse knots the spline cuts the obstacle's corner.

    Refinement adds knots there until the dense check passes.
    """
    w = _hugging_path(sc2)
    assert check_path(chk2, w, *bounds(sc2)).ok
    for stride in (8, 12, 16, 24, 32):
        idx = np.unique(np.concatenate([np.arange(0, len(w), stride), [len(w) - 1]]))
        coarse, _, _ = spline_through(w[idx])
        if not check_path(chk2, coarse, *bounds(sc2)).ok:
            break
    else:
        pytest.fail("no coarse spline cuts the corner: the test scene lost its point")
    sp = smooth_path(chk2, w, *bounds(sc2), shortcut=False, knot_stride=stride)
    assert sp is not None and sp.method == "spline" and sp.refinements >= 1
    assert len(sp.knots_rad) > len(idx)
    assert check_path(chk2, sp.path_rad, *bounds(sc2), verify_step_rad=np.radians(0.05)).ok


def test_kept_interval_checks_equal_a_fresh_check_bit_for_bit(sc2, chk2):
    """
    ``MotionValidator.check_kept`` reuses each interval's certificate kept from earlier checks.

    Polylines that share some intervals with earlier ones (free, colliding and out-of-bounds
    intervals among them) get what a fresh validator's ``check`` gives, bit for bit, except
    the evaluation count: none for intervals all kept.
    """
    lo, hi, per = bounds(sc2)
    rng = np.random.default_rng(7)
    kept = MotionValidator(chk2, lo, hi, per)
    base = rng.uniform(lo - 0.05, hi, size=(12, 2))        # some rows just below a bound
    paths = [base, base[3:9], np.vstack([rng.uniform(lo, hi, size=(2, 2)), base[4:10]]), base[::-1].copy(),
             np.vstack([base[:5], rng.uniform(lo, hi, size=(3, 2)), base[7:]])]
    outcomes = set()
    for path in paths:
        fresh = MotionValidator(chk2, lo, hi, per).check(path)
        got = kept.check_kept(path)
        assert got.ok == fresh.ok
        assert np.array_equal(got.interval_ok, fresh.interval_ok)
        assert np.array_equal(got.interval_clearance_m, fresh.interval_clearance_m)
        assert got.min_clearance_m == fresh.min_clearance_m
        known = ~np.isnan(got.vertex_clearance_m)
        assert np.array_equal(got.vertex_clearance_m[known], chk2.clearance_m(path[known]))
        assert kept.check_kept(path).n_checked == 0               # every interval kept now
        outcomes.update(fresh.interval_ok.tolist())
    assert outcomes == {True, False}                               # both kinds of interval seen


@pytest.mark.parametrize("seed", range(6))
def test_shortcut_knots_are_numpys_linspaces(seed):
    # the shortcut spline's knots: per stretch of the shortcut polyline, NumPy's linspace about
    # knot_stride times the median waypoint step apart, concatenated (the rule as it was written)
    rng = np.random.default_rng(seed)
    for k in range(300):
        steps = rng.uniform(1e-6, 1.0, int(rng.integers(2, 30))) * 10.0 ** rng.uniform(-3, 1)
        if k % 5 == 0:
            steps[-1] = steps[0]                                 # ties in the median
        t = np.concatenate([[0.0], np.cumsum(rng.uniform(1e-6, 2.0, int(rng.integers(1, 12))))])
        stride = int(rng.integers(1, 4))
        spacing = stride * np.median(steps)
        assert stride * _median(steps) == spacing
        ref = np.concatenate([np.linspace(a, b, max(2, int(np.ceil((b - a) / max(spacing, 1e-9))) + 1))
                              for a, b in zip(t[:-1], t[1:])])
        np.testing.assert_array_equal(_stretch_knots(t, stride * _median(steps)), ref)


@pytest.mark.parametrize("dof", [2, 3])
def test_the_certified_walks_bound_holds_every_checked_point_and_is_exact_for_the_last_joint(paper_scenario, dof):
    """
    ``motion.sweep_m``, the bound the certified walk steps by, holds how far a checked point travels.

    Judged by the test's own kinematics (``oracles.arm_points``): the path length of 41 points along
    each checked link over 4001 samples of the segment.  One, two or every planned joint moving, by
    0.5-60°.  Where only the last joint moves, its link's tip travels the bound exactly (the bound
    is not loose there); everywhere it is at most the whole arm's Lipschitz bound times the
    joint-space length (the rule it replaced).
    """
    from oracles import arm_points
    from spacerobot_planner.motion import joint_reach_m, lipschitz_m_per_rad, sweep_m
    sc = paper_scenario(dof)
    robot = sc.robot
    reach = joint_reach_m(robot)
    lo, hi, _ = bounds(sc)
    rng = np.random.default_rng(5 + dof)
    along = np.linspace(0.0, 1.0, 41)[None, :, None]
    for trial in range(40):
        moving = np.zeros(dof, bool)
        moving[rng.integers(dof) if trial % 3 else dof - 1] = True
        if trial % 2:
            moving |= rng.random(dof) < 0.5
        direction = np.where(moving, rng.normal(size=dof), 0.0)
        a = rng.uniform(lo, hi)
        b = a + np.radians(rng.uniform(0.5, 60.0)) * direction / np.linalg.norm(direction)
        bound = sweep_m(a, b, reach)
        q = a + np.linspace(0.0, 1.0, 4001)[:, None] * (b - a)
        pts = arm_points(robot, robot.full(q))                  # (4001, n_joints + 1, 2)
        travel = max(np.linalg.norm(np.diff(pts[:, k, None] + along * (pts[:, k + 1, None] - pts[:, k, None]),
                                            axis=0), axis=-1).sum(axis=0).max() for k in robot.checked_links)
        assert travel <= bound * (1 + 1e-9), (trial, travel, bound)
        if moving.sum() == 1 and moving[-1] and robot.planned_joints[-1] == robot.n_joints - 1:
            assert travel >= bound * (1 - 1e-6), (trial, travel, bound)
        assert bound <= lipschitz_m_per_rad(robot) * np.linalg.norm(b - a) * (1 + 1e-12)


@pytest.mark.parametrize("dof", [2, 3])
def test_the_walk_past_rows_proves_what_the_geometry_says(paper_scenario, dof):
    """
    ``MotionValidator.check(every_row=False)`` (the controller's motion: eight rows a segment) against the geometry.

    Curved paths (cubic Béziers, rows 0.1° apart on average, as the controller's samples are)
    that come nearest an obstacle in their middle, checked at a required clearance near that
    least clearance, judged by the test's own geometry (``oracles.ref_clearance``) at samples
    0.02° apart: where the walk passes an interval, no sample of it is within the required
    clearance; every interval with a sample more than 0.1 mm inside it fails; the verdict is the
    every-row walk's (5 mm below the least clearance: passed; 2 and 0.3 mm above: failed); the rows it
    measured are the geometry's clearances.  Samples up to 6° apart, so the certificate carried
    past the rows alone bounds them.  At the scene's margin and the validator's own step it
    evaluates fewer than half the rows.
    """
    from oracles import dense_samples, ref_clearance
    sc = paper_scenario(dof)
    v = MotionValidator.for_scene(sc.robot, sc.scene)
    wide = v.with_step(np.radians(6.0))          # samples as far apart as the certificate alone allows
    margin = sc.scene.safety_margin_m
    lo, hi, _ = bounds(sc)
    rng = np.random.default_rng(40 + dof)
    trials = draws = 0
    while trials < 6:
        draws += 1
        assert draws < 1_000_000, f"only {trials} curves near an obstacle in 1 000 000 draws"
        mid = rng.uniform(lo, hi)
        if not margin + 0.01 < v.clearance_m(mid) < 0.08:
            continue
        d = rng.normal(size=dof)
        d *= rng.uniform(0.2, 0.5) / np.linalg.norm(d)
        ctrl = np.array([mid - d, mid - d / 3 + rng.normal(0.0, 0.05, dof),
                         mid + d / 3 + rng.normal(0.0, 0.05, dof), mid + d])
        fine = np.linspace(0.0, 1.0, 2001)[:, None]

        def curve(u):
            return ((1 - u) ** 3 * ctrl[0] + 3 * u * (1 - u) ** 2 * ctrl[1] + 3 * u ** 2 * (1 - u) * ctrl[2]
                    + u ** 3 * ctrl[3])
        length_deg = np.degrees(np.linalg.norm(np.diff(curve(fine), axis=0), axis=1).sum())
        u = np.sort(np.concatenate([[0.0, 1.0], rng.uniform(0.0, 1.0, int(length_deg / 0.1))]))[:, None]
        rows = curve(u)
        quick = v.clearance_m(curve(fine))          # the selection only (the verdicts are judged below)
        if not (v.within_bounds(rows).all() and quick.min() > margin + 0.006
                and min(quick[0], quick[-1]) > quick.min() + 0.01):
            continue
        dense, owner = [], []
        for i in range(len(rows) - 1):
            piece = dense_samples(rows[i:i + 2], np.radians(0.02))
            dense.append(piece)
            owner += [i] * len(piece)
        dense, owner = np.concatenate(dense), np.array(owner)
        truth = np.array([ref_clearance(sc.robot, sc.scene, q) for q in dense])
        least = truth.min()
        if not (least > margin + 0.006 and min(truth[0], truth[-1]) > least + 0.01):
            continue                     # nearest the obstacle in its middle, with room for both verdicts
        trials += 1
        for need in (least - 5e-3, least + 2e-3, least + 3e-4):
            got = wide.check(rows, required_clearance_m=need, every_row=False)
            every = wide.check(rows, required_clearance_m=need)
            for i in np.flatnonzero(got.interval_ok):
                assert truth[owner == i].min() > need - 1e-9, (trials, i)
            inside = np.unique(owner[truth < need - 1e-4])
            assert not got.interval_ok[inside].any(), (trials, inside)
            assert got.ok == (need < least) == every.ok, (trials, need, least)
            known = np.isfinite(got.vertex_clearance_m)
            np.testing.assert_allclose(got.vertex_clearance_m[known],
                                       [ref_clearance(sc.robot, sc.scene, q) for q in rows[known]], rtol=0, atol=1e-9)
            # the least of the samples the walk took: on the path (within the oracle's spacing), rows among them
            assert truth.min() - 5e-4 <= got.min_clearance_m <= got.vertex_clearance_m[known].min()
        got, every = v.check(rows, every_row=False), v.check(rows)
        assert got.ok and every.ok and got.n_checked < len(rows) // 2 < every.n_checked, trials


@pytest.mark.parametrize("every_row", [True, False])
@pytest.mark.parametrize("certified", [True, False])
def test_a_row_that_is_not_finite_fails_its_intervals_at_once(sc2, chk2, paper_scenario, certified, every_row):
    """
    A NaN or infinite row (a periodic joint's or a bounded one's) fails the two intervals it ends, and only those.

    The quick test of a segment to it (``segment_free``) and the certified one say it is not free.

    The walk's place never reached such a row's interval end (a NaN attitude hung the kernel; an
    infinite attitude passed, its clearance an infinity or a number of no posture).  Each check
    must return within 60 s, judged in a thread.
    """
    import threading

    from spacerobot_planner.motion import motion_scratch, segment_free
    for sc in (sc2, paper_scenario(3)):
        v = MotionValidator.for_scene(sc.robot, sc.scene)
        lo, hi, _ = bounds(sc)
        base = np.linspace(lo + 0.45 * (hi - lo), lo + 0.55 * (hi - lo), 9)
        assert v.check(base, certified=certified, every_row=every_row).ok
        for bad in (np.nan, np.inf, -np.inf):
            for joint in range(sc.robot.dof):              # joint 0 is the periodic attitude's
                path = base.copy()
                path[4, joint] = bad
                out = {}
                th = threading.Thread(target=lambda: out.setdefault(
                    "chk", v.check(path, certified=certified, every_row=every_row)), daemon=True)
                th.start()
                th.join(60.0)
                assert not th.is_alive(), (bad, joint, "the check did not return")
                chk = out["chk"]
                assert not chk.ok
                assert list(np.flatnonzero(~chk.interval_ok)) == [3, 4], (bad, joint, chk.interval_ok)
                assert np.isnan(chk.interval_clearance_m[3:5]).all() and np.isnan(chk.min_clearance_m)
                # the quick test and the certified segment test of the same motion: not free
                if certified and every_row:
                    t = v.segment_test()
                    assert not segment_free(path[3], path[4], *t.arrays(),
                                            *motion_scratch(t.q_template, t.lengths, t.body))
                    assert not v.segment_ok(path[3], path[4])
