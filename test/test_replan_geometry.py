"""
The cached replan's geometry kernels against independent oracles.

The spline kernel against scipy's ``CubicSpline`` (not-a-knot); the quick shortcut test
(ends first, bisection, clearance balls) against evaluating every sample of the quick test
with ``CollisionChecker.clearance_m`` (itself checked against shapely in test_collision.py);
the shortcut pass given the polyline's certified check against the pass that checks it
itself; the walk's and the repair's segment test (samples proven free skipped) against
evaluating every one of its samples.
"""

import itertools

import numpy as np
import pytest
from scipy.interpolate import CubicSpline

from spacerobot_planner.collision import CollisionChecker
from spacerobot_planner.motion import QUICK_STEP_RAD, MotionValidator, motion_scratch, segment_free_from
from spacerobot_planner.scene import Scene
from spacerobot_planner.smoothing import (DEFAULT_MAX_STEP_RAD, _quick_segment_ok, _spline_samples,
                                          shortcut_indices, spline_through)

DEBRIS = (
    [[-1.0, 2.2], [0.0, 2.0], [0.2, 2.8], [-0.8, 3.0]],
    [[2.0, -1.0], [3.2, -1.0], [3.2, 0.2], [2.6, -0.4], [2.0, 0.2]],
    [[-4.5, 0.5], [-3.9, 0.5], [-4.2, 1.2]],
)


@pytest.fixture(scope="module", params=[2, 3])
def scenario(request, paper_scenario):
    sc = paper_scenario(request.param)
    scene = Scene(target=sc.scene.target, debris_m=tuple(np.array(p) for p in DEBRIS), safety_margin_m=0.05)
    return sc.with_scene(scene)


def _chord_param(k):
    return np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(k, axis=0), axis=1))])


@pytest.mark.parametrize("n_knots", [3, 4, 5, 9, 30])
def test_spline_is_scipys_not_a_knot_spline_sampled_within_the_step(n_knots):
    """
    The samples are SciPy's not-a-knot spline, within the step, each knot interval on its own.

    Every knot is a sample; inside each knot interval the samples are at equal parameter steps,
    no more of them than the interval's own fastest stretch needs (its largest |dq/ds| by
    SciPy's derivative, with the kernel's 5 % and one more): a spline that runs faster than its
    chord parameter in one interval is not sampled finer everywhere (equal steps over the whole
    parameter put 2.2 times the samples on the paper 3-DOF path).
    """
    rng = np.random.default_rng(n_knots)
    for dof in (2, 3):
        k = np.cumsum(rng.normal(scale=0.2, size=(n_knots, dof)), axis=0)
        q, s_knots, s_samples = spline_through(k)
        ref = CubicSpline(_chord_param(k), k, axis=0, bc_type="not-a-knot")
        assert np.allclose(s_knots, _chord_param(k), rtol=0, atol=1e-15)
        assert np.allclose(q, ref(s_samples), rtol=0, atol=1e-10)
        assert np.array_equal(q[0], k[0]) and np.array_equal(q[-1], k[-1])
        assert s_samples[0] == 0.0 and s_samples[-1] == s_knots[-1] and np.all(np.diff(s_samples) > 0)
        steps = np.linalg.norm(np.diff(q, axis=0), axis=1)
        assert steps.max() <= DEFAULT_MAX_STEP_RAD
        at_knot = np.searchsorted(s_samples, s_knots)
        assert np.array_equal(s_samples[at_knot], s_knots) and np.array_equal(q[at_knot], k)
        for i in range(n_knots - 1):
            u = s_samples[at_knot[i]:at_knot[i + 1] + 1]
            assert np.allclose(np.diff(u), (s_knots[i + 1] - s_knots[i]) / (len(u) - 1), rtol=1e-9, atol=0)
            # the interval's fastest |dq/ds| (SciPy's derivative, 201 points, 1 % for between them)
            fastest = 1.01 * np.linalg.norm(ref(np.linspace(s_knots[i], s_knots[i + 1], 201), 1), axis=1).max()
            h = s_knots[i + 1] - s_knots[i]
            assert len(u) - 1 <= np.ceil(1.05 * fastest * h / DEFAULT_MAX_STEP_RAD) + 1


def test_a_clamped_spline_is_scipys_with_that_start_derivative():
    """With a start tangent the samples are SciPy's spline clamped to it at the start (not-a-knot at the end)."""
    rng = np.random.default_rng(11)
    for n_knots in (3, 4, 7):
        for dof in (2, 3):
            k = np.cumsum(rng.normal(scale=0.2, size=(n_knots, dof)), axis=0)
            d = k[1] - k[0] + rng.normal(scale=0.05, size=dof)
            t = d / np.linalg.norm(d)
            q, s_knots, s_samples = spline_through(k, start_tangent=t)
            ref = CubicSpline(_chord_param(k), k, axis=0, bc_type=((1, t), "not-a-knot"))
            assert np.allclose(q, ref(s_samples), rtol=0, atol=1e-10)
            assert np.allclose(ref(0.0, 1), t, rtol=0, atol=1e-12)
            assert np.linalg.norm(np.diff(q, axis=0), axis=1).max() <= DEFAULT_MAX_STEP_RAD


def test_each_step_is_within_the_step_where_a_short_interval_runs_fast():
    """
    Knots with a short interval between long ones (the spline runs fastest near its ends there).

    Every step within the step, the one into each knot included (where the spline runs into a
    short interval the last step before it is the largest), the values SciPy's.
    """
    for short, turn_deg, long in itertools.product((0.005, 0.01, 0.05), (60.0, 90.0, 120.0), (0.05, 0.3)):
        c, sn = np.cos(np.radians(turn_deg)), np.sin(np.radians(turn_deg))
        k = np.array([[0.0, 0.0], [long, 0.0], [long + short, 0.0], [long + short + long * c, long * sn],
                      [2 * long + short, long * sn + 0.4]])
        q, s_knots, s_samples = spline_through(k)
        steps = np.linalg.norm(np.diff(q, axis=0), axis=1)
        assert steps.max() <= DEFAULT_MAX_STEP_RAD
        ref = CubicSpline(_chord_param(k), k, axis=0, bc_type="not-a-knot")
        assert np.allclose(q, ref(s_samples), rtol=0, atol=1e-10)


def test_knots_a_hair_apart_do_not_swing_the_spline_out():
    """
    Knots closer than MIN_KNOT_CHORD_RAD to the one before are dropped, never the ends.

    A knot 5.6e-12 rad from its predecessor (in an arbitrary direction) made the not-a-knot
    spline swing millions of radians out (SciPy's spline through them does too): the samples
    stay about as many as the polyline's length needs, the first and last knot exact.
    """
    from spacerobot_planner.smoothing import MIN_KNOT_CHORD_RAD
    k = np.array([[0.5109625645468612, 0.4252309099879812, 0.10855601724430916],
                  [1.1194324751558924, -0.9486896934986888, 0.0724153937343155],
                  [1.1194324751593911, -0.9486896934996678, 0.0724153937385492],
                  [0.22331450741596715, -1.5922916344829066, 0.6829139555622208]])
    assert np.linalg.norm(k[2] - k[1]) < MIN_KNOT_CHORD_RAD
    length = np.linalg.norm(np.diff(k, axis=0), axis=1).sum()
    for ends in (k, k[::-1], np.vstack([k[:3], k[2] + 1e-9])):     # also the goal a hair past a knot
        q, s_knots, _ = spline_through(ends)
        assert len(q) <= 3 * length / DEFAULT_MAX_STEP_RAD + 10
        assert np.array_equal(q[0], ends[0]) and np.array_equal(q[-1], ends[-1])
        assert np.linalg.norm(np.diff(q, axis=0), axis=1).max() <= DEFAULT_MAX_STEP_RAD


def test_spline_sample_intervals_name_their_knot_interval():
    k = np.radians([[0.0, 0.0], [20.0, 10.0], [40.0, 5.0], [55.5, -3.3], [60.0, 10.0]])
    q, s_knots, s_samples, iv = _spline_samples(k, DEFAULT_MAX_STEP_RAD)
    assert len(iv) == len(q)
    want = np.clip(np.searchsorted(s_knots, s_samples, side="right") - 1, 0, len(s_knots) - 2)
    assert np.array_equal(iv, want)


def _every_sample_ok(checker, a, b, threshold_m, step_rad):
    """Answer the quick test from every one of its samples (arc lengths k·step below the length, the end)."""
    length = float(np.linalg.norm(b - a))
    n_last = max(1, int(np.ceil(length / step_rad)))
    t = np.minimum(np.arange(n_last) * step_rad, length) / length
    q = np.vstack([a + t[:, None] * (b - a), b])
    return bool(np.all(checker.clearance_m(q) > threshold_m))


def test_quick_shortcut_test_answers_as_every_sample(scenario):
    chk = CollisionChecker(scenario.robot, scenario.scene)
    v = MotionValidator(chk)
    rng = np.random.default_rng(7)
    lo, hi = scenario.robot.planned_lower_rad, scenario.robot.planned_upper_rad
    scratch = motion_scratch(v.kernel_arrays[0], chk.lengths, chk.body)
    answers = []
    for _ in range(400):
        a = rng.uniform(lo, hi)
        b = a + rng.normal(scale=rng.choice([0.05, 0.3, 1.0]), size=scenario.robot.dof)
        b = np.clip(b, lo, hi)
        if np.linalg.norm(b - a) < 1e-6:
            continue
        threshold = chk.margin_m + rng.choice([0.0, 0.02, 0.05])
        pts = np.ascontiguousarray(np.vstack([a, b]))
        known = np.full(2, np.nan)
        if rng.random() < 0.5:                  # an end's clearance already known
            known[0] = chk.clearance_m(a)
        got = _quick_segment_ok(pts, 0, 1, known, *v.kernel_arrays, threshold, v.reach_m,
                                QUICK_STEP_RAD, *scratch)
        want = _every_sample_ok(chk, a, b, threshold, QUICK_STEP_RAD)
        assert got == want, (a, b, threshold)
        for e, q in ((0, a), (1, b)):       # what it wrote for the ends is their clearance
            if np.isfinite(known[e]):
                assert known[e] == chk.clearance_m(q)
        answers.append(got)
    assert 50 < sum(answers) < len(answers) - 50          # both answers exercised


def test_segment_test_answers_as_every_sample(scenario):
    """
    motion.segment_free_from skips the samples a measured one proves free: the verdict of measuring them all.

    Random segments, grid edges (one joint moving 10°, the walk's and the repair's) and
    segments an ulp long, near the debris and away from them, with the start's clearance known
    or not; thresholds at the margin and above it, and at a sample's own clearance and the
    floats next to it (where a sample proven free without its margin would flip the verdict).
    The oracle measures every sample k/n of the segment with CollisionChecker.clearance_m
    (checked against shapely in test_collision.py).  The clearances it hands on are those of
    the ends.
    """
    chk = CollisionChecker(scenario.robot, scenario.scene)
    arrays = MotionValidator(chk).segment_test().arrays()
    scratch = motion_scratch(arrays[0], chk.lengths, chk.body)
    rng = np.random.default_rng(11)
    lo, hi = scenario.robot.planned_lower_rad, scenario.robot.planned_upper_rad
    dof = scenario.robot.dof
    answers = []
    for i in range(900):
        a = rng.uniform(lo, hi)
        b = a.copy()
        if i % 3 == 0:
            b[rng.integers(dof)] += rng.choice([-1.0, 1.0]) * np.radians(10.0)
        elif i % 3 == 1:
            b = a + rng.normal(scale=rng.choice([0.05, 0.3, 1.0]), size=dof)
        else:
            j = rng.integers(dof)
            b[j] = np.nextafter(b[j], rng.choice([-np.inf, np.inf]))
        b = np.clip(b, lo, hi)
        n = max(1, int(np.ceil(np.linalg.norm(b - a) / QUICK_STEP_RAD)))
        q = np.vstack([a + (k / n) * (b - a) for k in range(n)] + [b])
        clr = chk.clearance_m(q)
        if rng.random() < 0.5:
            threshold = chk.margin_m + rng.choice([0.0, 0.02, 0.05])
        else:                                   # at a sample's clearance, or the float next to it
            threshold = np.nextafter(clr[rng.integers(len(clr))], rng.choice([-np.inf, np.inf, 0.0]))
        ends = np.full(2, np.nan)
        if rng.random() < 0.5:
            ends[0] = chk.clearance_m(a)
        got = segment_free_from(a, b, *arrays[:9], threshold, QUICK_STEP_RAD, arrays[11], *scratch, ends)
        want = bool(np.all(clr > threshold))
        assert got == want, (a, b, threshold)
        assert ends[0] == chk.clearance_m(a)
        assert np.isnan(ends[1]) or ends[1] == chk.clearance_m(b)
        answers.append(got)
    assert 150 < sum(answers) < len(answers) - 150          # both answers exercised


def test_segments_an_ulp_long_are_not_passed_on_rounding(paper_scenario):
    """
    A segment an ulp long whose end's clearance is rounded below the bound is measured, not passed.

    Where the clearances of two configurations an ulp apart differ by more than the bound on the
    motion between them (rounding, about 1e-15 m), the end is measured, not proven free: with the
    threshold at the end's own clearance the segment fails, as every sample measured says.
    """
    sc = paper_scenario(3)
    chk = CollisionChecker(sc.robot, sc.scene)
    arrays = MotionValidator(chk).segment_test().arrays()
    rng = np.random.default_rng(3)
    m = 40_000
    a = rng.uniform(sc.robot.planned_lower_rad, sc.robot.planned_upper_rad, size=(m, sc.robot.dof))
    axis = rng.integers(sc.robot.dof, size=m)
    b = a.copy()
    b[np.arange(m), axis] = np.nextafter(a[np.arange(m), axis], np.where(rng.random(m) < 0.5, -np.inf, np.inf))
    ca, cb = chk.clearance_m(a), chk.clearance_m(b)
    bound = np.abs(b - a) @ np.array([sum(sc.robot.link_lengths_m[j:]) for j in sc.robot.planned_joints])
    hits = np.flatnonzero((ca - cb) * 0.999 > bound)       # beyond the Lipschitz bound: rounding
    if not len(hits):
        pytest.skip("no pair whose clearances differ by more than the bound on this machine's rounding")
    scratch = motion_scratch(arrays[0], chk.lengths, chk.body)
    for i in hits[:20]:
        ends = np.full(2, np.nan)
        got = segment_free_from(a[i], b[i], *arrays[:9], float(cb[i]), QUICK_STEP_RAD, arrays[11], *scratch, ends)
        assert not got and ends[1] == cb[i], (a[i], b[i])


def _staircase():
    """Return a free 2-DOF grid-like polyline around the paper's target (2° steps)."""
    up = np.radians(np.column_stack([np.full(46, 96.0), np.arange(0, 92, 2.0)]))
    over = np.radians(np.column_stack([np.arange(94, 28, -2.0), np.full(33, 90.0)]))
    down = np.radians(np.column_stack([np.full(45, 30.0), np.arange(88, -2, -2.0)]))
    return np.vstack([up, over, down])


@pytest.mark.parametrize("certified", [True, False])
def test_shortcut_given_the_polylines_certified_check(paper_scenario, certified):
    sc = paper_scenario(2)
    v = MotionValidator(CollisionChecker(sc.robot, sc.scene))
    w = _staircase()
    poly = v.check(w)
    assert poly.ok
    given = shortcut_indices(v, w, certified=certified, polyline_check=poly)
    if certified:       # its own check is the same certified check
        assert np.array_equal(given, shortcut_indices(v, w, certified=True))
    assert given[0] == 0 and given[-1] == len(w) - 1 and np.all(np.diff(given) > 0) and len(given) < len(w) // 4
    # each kept segment keeps the clearance of what it replaced (or margin + 0.05 m), at the
    # quick test's samples
    chk = v.checker
    for i, j in zip(given[:-1], given[1:]):
        if j > i + 1:
            need = max(chk.margin_m, min(poly.interval_clearance_m[i:j].min(), chk.margin_m + 0.05))
            step = v.step_rad if certified else QUICK_STEP_RAD
            assert _every_sample_ok(chk, w[i], w[j], need, step)
    with pytest.raises(ValueError, match="polyline_check"):
        shortcut_indices(v, w[:-1], polyline_check=poly)
