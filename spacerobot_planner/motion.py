"""
Motion validity: straight joint-space segments checked on the exact geometry.

OMPL splits validity in two: the state validity checker (``collision.CollisionChecker``:
is one configuration free, and by how much) and the motion validator (this module: is
every configuration on the straight segment between two configurations free).  Every
stage that accepts a motion (the joins to the exact start and goal, the grid path,
shortcuts, the spline, the trajectory's points) asks this module.

The certified check: along a segment, configurations are tested at most ``step`` apart
and, near obstacles, closer, so that consecutive clearance balls overlap (a bound on how
far a checked link moves along the segment, :func:`sweep_m`: per joint, so a motion of
the wrist alone steps by the wrist's reach, not the whole arm's): the *whole*
segment, not only the samples, keeps clearance above the threshold.  The quick test
(``certified=False``) samples at a fixed step only: for choosing among candidates,
never for what is returned.

One scene, one validator (OMPL's ``SpaceInformation`` with its ``MotionValidator``):
:class:`MotionValidator` is bound to a scene's collision checker and owns the planned
joints' bounds, their periodic axes and the certified step.  The stages (smoothing, the
pipeline's joins and grid paths, ``published.resample``, the replan's corner blends, the
exit from a contact) ask it instead of passing a checker, bounds and packed arrays around;
:func:`check_path` and :func:`first_bad_segment` are the same checks for a checker and
bounds given one by one.

All configurations are planned-joint vectors in radians; paths are (M, dof) arrays,
periodic joints unwrapped (continuous).
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np
from numba import njit

from .collision import NO_REFCOUNT, CollisionChecker, config_clearance
from .joint_space import row_within_bounds, unwrap_path, within_bounds

__all__ = ["PathCheck", "MotionValidator", "check_path", "first_bad_segment", "lipschitz_m_per_rad", "joint_reach_m",
           "certify_segments", "sweep_m", "SegmentTest", "DEFAULT_VERIFY_STEP_RAD", "QUICK_STEP_RAD", "quick_step_rad",
           "narrowest_obstacle_m"]

DEFAULT_VERIFY_STEP_RAD = float(np.radians(0.5))  # largest spacing of the certified checks
QUICK_STEP_RAD = float(np.radians(1.0))           # spacing of the quick test of candidates
#: ... at the finest (a scene with an obstacle narrower than a 1° sweep: :func:`quick_step_rad`)
QUICK_STEP_MIN_RAD = float(np.radians(0.1))
#: the quick test proves a sample free only this far beyond what the Lipschitz bound gives (m):
#: far above the rounding of a clearance (about 1e-15 m), as the clearance's own bounds
#: (``collision._pair_bound``)
ROUNDING_SLACK_M = 1e-9
#: interval certificates a validator keeps (``MotionValidator.check_kept``), oldest out first
KEPT_INTERVALS = 4096


@dataclass(frozen=True, eq=False)
class PathCheck:
    """
    Result of a dense check of a sampled path.

    Attributes
    ----------
        ok: every check sample is free and within bounds.
        interval_ok: (M-1,) bool, per interval between consecutive path samples
            (the whole straight interval, certified; see :func:`check_path`).
        min_clearance_m: smallest clearance over all check samples, metres.
        n_checked: number of configurations tested.
        interval_clearance_m: (M-1,) smallest clearance per interval, metres.
        vertex_clearance_m: (M,) clearance at each point where the check evaluated it
            (NaN elsewhere); give it to a later check of the same points to reuse.

    """

    ok: bool
    interval_ok: np.ndarray
    min_clearance_m: float
    n_checked: int
    interval_clearance_m: np.ndarray = None
    vertex_clearance_m: np.ndarray = None


@njit(cache=True, nogil=True, inline="always")
def sweep_m(qa, qb, reach_m):
    """
    Return the most a checked point moves along the straight segment qa → qb (planned joints, rad), m.

    D = Σ_j reach_m[j]·|Δq_j| (:func:`joint_reach_m`: no point of a checked link moves faster
    than reach_m[j] per radian of planned joint j, relative to the obstacles and the body).
    The one Lipschitz rule of every walk along a segment (:func:`certify_segments`,
    :func:`segment_free_from`, ``smoothing._quick_segment_kernel``): per unit of joint-space
    length it is at most :func:`lipschitz_m_per_rad` (Cauchy–Schwarz), and along a grid edge,
    where one joint moves, it is that joint's reach alone.
    """
    span = 0.0
    for j in range(reach_m.shape[0]):
        span += reach_m[j] * abs(qb[j] - qa[j])
    return span


@njit(**NO_REFCOUNT)
def certify_segments(points, q_template, planned, lengths, checked, body, verts, starts, centres, radii,
                     threshold_m, reach_m, max_step_rad, min_step_rad,
                     interval_ok, interval_clr, certified, vertex_clr, every_row, q_full, pts, body_w):
    """
    Walk each straight interval of ``points`` (M×dof planned joints) with certified steps.

    On an interval of joint-space length ℓ no point of a checked link moves faster than
    D/ℓ m per rad of it (D: :func:`sweep_m`, ``reach_m`` (dof,) :func:`joint_reach_m`), so
    from a sample with clearance c the interval is free for (c - threshold)·ℓ/D on either
    side, and the next sample goes at most that far (less 0.1 %, and at most max_step_rad).
    An interval fails where c ≤ threshold or the certified step falls below min_step_rad, and
    where a row at either end is not finite (unwalked, its clearance NaN).
    With ``certified`` false the samples go ``max_step_rad`` apart whatever the
    clearance (a quick test, not a proof).  Returns the number of clearance evaluations.

    ``vertex_clr`` (M,): the clearance at each point (NaN: not known yet), read where
    known and filled where evaluated, so a vertex is evaluated once (an interval's first
    and last samples are the points themselves) and a later check of the same points
    (the certified check after the quick one) reuses them.

    ``every_row`` false: one walk along the whole polyline instead, its certificate carried past
    the rows (a sample's ball covers the sweep after it, in whatever intervals: :func:`sweep_m`
    bounds each, and their sum bounds the polyline's); a row is evaluated where the walk's next
    sample falls on it or where its clearance is known, the samples still at most
    ``max_step_rad`` apart along the polyline.  For a dense polyline whose rows are samples of a
    curve themselves (the controller's motion, eight rows a segment): the same proof with fewer
    evaluations.  An interval no sample falls in has clearance ``inf`` in ``interval_clr`` (none
    measured; the walk's certificate covers it), and a failed interval ends the certificate
    (the next interval starts from its first row, as with ``every_row``).

    Scratch (:func:`motion_scratch`): q_full (n_joints,) starting as ``q_template``, pts
    (n_links + 1, 2), body_w like body.
    """
    dof = points.shape[1]
    n_eval = 0
    free_m = -1.0       # (carried) the sweep, m, the last sample proves free beyond the walk's place (< 0: none)
    room_rad = 0.0      # (carried) the length, rad, the walk may still go before its next sample
    for i in range(points.shape[0] - 1):
        seg_len = 0.0
        for a in range(dof):
            d = points[i + 1, a] - points[i, a]
            seg_len += d * d
        seg_len = np.sqrt(seg_len)
        if not seg_len < np.inf:
            # a row not finite (NaN, ±inf): the interval fails unwalked (a walk's place would never reach
            # its end; a clearance there is no clearance)
            interval_ok[i] = False
            interval_clr[i] = np.nan
            free_m = -1.0
            continue
        span = sweep_m(points[i], points[i + 1], reach_m)
        rad_per_m = seg_len / span if span > 0.0 else 0.0     # rad of the segment per m of motion (0: no length)
        t = 0.0
        ok = True
        best = np.inf
        if free_m >= 0.0 and np.isnan(vertex_clr[i]):
            # row i passed over: the walk goes on under the last sample's certificate
            go = room_rad if free_m == np.inf else min(free_m * rad_per_m, room_rad)
            if go >= seg_len:
                free_m -= span
                room_rad -= seg_len
                interval_ok[i] = True
                interval_clr[i] = np.inf
                continue
            t = go
        free_m = -1.0
        while True:
            v = i if t == 0.0 else (i + 1 if t >= seg_len else -1)     # a vertex: its index
            if v >= 0 and not np.isnan(vertex_clr[v]):
                c = vertex_clr[v]
            else:
                if v >= 0:
                    for a in range(dof):
                        q_full[planned[a]] = points[v, a]
                else:
                    f = t / seg_len
                    for a in range(dof):
                        q_full[planned[a]] = points[i, a] + f * (points[i + 1, a] - points[i, a])
                c = config_clearance(q_full, lengths, checked, body, verts, starts, centres, radii, pts, body_w)
                n_eval += 1
                if v >= 0:
                    vertex_clr[v] = c
            if c < best:
                best = c
            if not c > threshold_m:
                ok = False
                break
            if t >= seg_len:
                if not every_row:
                    free_m = 0.999 * (c - threshold_m) if certified else np.inf
                    room_rad = max_step_rad
                break
            step = 0.999 * (c - threshold_m) * rad_per_m if certified else max_step_rad
            if step < min_step_rad:
                ok = False
                break
            if not every_row and t + min(step, max_step_rad) >= seg_len:
                # the rest of the interval is proven free: the certificate goes on past row i + 1
                left = seg_len - t
                free_m = 0.999 * (c - threshold_m) - left / rad_per_m if certified else np.inf
                room_rad = max_step_rad - left
                break
            t = min(seg_len, t + min(step, max_step_rad))
        interval_ok[i] = ok
        interval_clr[i] = best
    return n_eval


def check_kernel(points, lower_rad, upper_rad, periodic, q_template, planned, lengths, checked, body, verts,
                 starts, centres, radii, threshold_m, reach_m, max_step_rad, min_step_rad, certified,
                 vertex_clr, every_row=True):
    """
    Run :meth:`MotionValidator.check` on M ≥ 2 rows: :func:`certify_segments` and the bounds, in one call.

    An interval fails also where a row at either end has a bounded joint outside
    [lower_rad, upper_rad] (``periodic`` (dof,) bool: unbounded).  Returns (ok, smallest
    interval clearance (NaN if one is NaN), evaluations, interval_ok (M-1,), interval
    clearances (M-1,)); ``vertex_clr`` and ``every_row`` as in :func:`certify_segments`.
    """
    m = points.shape[0] - 1
    interval_ok = np.empty(m, np.bool_)
    interval_clr = np.empty(m)
    ok, best, n = _check_rows(points, lower_rad, upper_rad, periodic, q_template, planned, lengths, checked, body,
                              verts, starts, centres, radii, threshold_m, reach_m, max_step_rad,
                              min_step_rad, certified, vertex_clr, bool(every_row), interval_ok, interval_clr,
                              *motion_scratch(q_template, lengths, body))
    return ok, best, n, interval_ok, interval_clr


@njit(**NO_REFCOUNT)
def _check_rows(points, lower_rad, upper_rad, periodic, q_template, planned, lengths, checked, body, verts, starts,
                centres, radii, threshold_m, reach_m, max_step_rad, min_step_rad, certified, vertex_clr,
                every_row, interval_ok, interval_clr, q_full, pts, body_w):
    """:func:`check_kernel` into interval_ok, interval_clr (M-1,), with the scratch given; (ok, best, n)."""
    m = points.shape[0] - 1
    n = certify_segments(points, q_template, planned, lengths, checked, body, verts, starts, centres, radii,
                         threshold_m, reach_m, max_step_rad, min_step_rad, interval_ok,
                         interval_clr, certified, vertex_clr, every_row, q_full, pts, body_w)
    ok = True
    best = np.inf
    before = True
    for r in range(m + 1):
        inside = row_within_bounds(points[r], lower_rad, upper_rad, periodic)
        if r > 0:
            if not (before and inside):
                interval_ok[r - 1] = False
            ok = ok and interval_ok[r - 1]
            c = interval_clr[r - 1]
            if np.isnan(c) or c < best:
                if not np.isnan(best):
                    best = c
        before = inside
    return ok, best, n


@functools.lru_cache(maxsize=64)
def lipschitz_m_per_rad(robot) -> float:
    """
    Return the Lipschitz bound L of the checked links, m per rad.

    Bound L on how fast any point of a checked link moves relative to the obstacles and the body per
    radian of planned-joint motion (Euclidean norm): sqrt(Σ r_j²), r_j the length of the chain
    beyond planned joint j.
    """
    return float(np.sqrt(np.sum(joint_reach_m(robot) ** 2)))


def narrowest_obstacle_m(checker) -> float:
    """
    Return the narrowest obstacle's width with the safety margin on both sides, m (inf: none).

    An obstacle's width: its convex hull's smallest extent across (the least, over the
    directions normal to a line through two of its vertices, of the spread of its vertices).
    """
    verts, starts = checker.verts, checker.starts
    narrowest = np.inf
    for p in range(len(starts) - 1):
        v = verts[starts[p]:starts[p + 1]]
        d = (v[None, :, :] - v[:, None, :]).reshape(-1, 2)          # every vertex pair's direction
        d = d[np.hypot(d[:, 0], d[:, 1]) > 0.0]
        if not len(d):
            continue
        normals = np.stack([-d[:, 1], d[:, 0]], axis=1) / np.hypot(d[:, 0], d[:, 1])[:, None]
        across = v @ normals.T                                        # (vertices, directions)
        narrowest = min(narrowest, float(np.min(across.max(axis=0) - across.min(axis=0))))
    return narrowest + 2.0 * float(checker.margin_m)


def quick_step_rad(checker) -> float:
    """
    Return the quick test's sample spacing on this scene, rad (:data:`QUICK_STEP_RAD` or finer).

    Between two samples Δq apart no point of the arm moves more than Σ_j r_j |Δq_j| ≤
    |r| |Δq| (:func:`joint_reach_m`); an obstacle narrower than that can pass between two
    samples unseen.  Its C-space image is then a sheet thinner than a grid step that no grid
    node marks (a small piece of debris): the descent, testing its steps this way, walks into
    it, and the certified check finds it edge by edge, one repair each.  So the step is made
    small enough that no point moves farther than :func:`narrowest_obstacle_m` between two
    samples, down to :data:`QUICK_STEP_MIN_RAD`.  The skipping of samples the Lipschitz bound
    proves free keeps a finer step cheap away from obstacles.
    """
    sweep = lipschitz_m_per_rad(checker.robot)
    if sweep <= 0.0:
        return QUICK_STEP_RAD
    return float(np.clip(narrowest_obstacle_m(checker) / sweep, QUICK_STEP_MIN_RAD, QUICK_STEP_RAD))


def joint_reach_m(robot) -> np.ndarray:
    """
    Return r_j per planned joint, m: the length of the chain beyond planned joint j.

    No point of a checked link moves faster than r_j per radian of joint j relative to the
    obstacles and the body, so over a joint-space step Δq no point moves more than
    Σ_j r_j |Δq_j| (:func:`sweep_m`, the rule of every walk along a segment; at most
    :func:`lipschitz_m_per_rad` times |Δq|).  float64 (dof,).
    """
    lengths = np.asarray(robot.link_lengths_m, dtype=float)
    return np.array([lengths[j:].sum() for j in robot.planned_joints], dtype=float)


def check_path(checker, path_rad, lower_rad, upper_rad, periodic,
               verify_step_rad: float = DEFAULT_VERIFY_STEP_RAD,
               required_clearance_m: float | None = None,
               min_step_rad: float = 1e-6, certified: bool = True) -> PathCheck:
    """
    Certified check of the piecewise-linear path through the rows of ``path_rad``.

    :meth:`MotionValidator.check` of the validator of ``checker`` with these bounds and step.
    """
    return MotionValidator(checker, lower_rad, upper_rad, periodic, verify_step_rad).check(
        path_rad, required_clearance_m=required_clearance_m, min_step_rad=min_step_rad, certified=certified)


def first_bad_segment(checker, points_rad, lower_rad, upper_rad, periodic,
                      verify_step_rad: float = DEFAULT_VERIFY_STEP_RAD) -> int:
    """Index i of the first straight segment points[i]→points[i+1] that fails, or -1."""
    return MotionValidator(checker, lower_rad, upper_rad, periodic, verify_step_rad).first_bad_segment(points_rad)


@njit(cache=True, nogil=True)
def motion_scratch(q_template, lengths, body):
    """
    Return the scratch arrays (q_full, pts, body_w).

    The scratch arrays of :func:`segment_free` and the clearance kernel (a full configuration from
    ``q_template``, the chain's points, the posed body).
    """
    return q_template.copy(), np.empty((lengths.shape[0] + 1, 2)), np.empty_like(body)


@njit(cache=True, nogil=True)
def segment_free(qa, qb, q_template, planned, lengths, checked, body, verts, starts, centres, radii,
                 threshold_m, step_rad, reach_m, q_full, pts, body_w):
    """
    Quick test of the straight segment qa → qb (planned joints, rad).

    Clearance above ``threshold_m`` at samples at most ``step_rad`` apart, both ends included
    (:func:`segment_free_from` with nothing known; ``reach_m``: :func:`joint_reach_m`).

    Scratch: q_full (n_joints,) starting as ``q_template``, pts (n_links + 1, 2), body_w
    like body.
    """
    return segment_free_from(qa, qb, q_template, planned, lengths, checked, body, verts, starts, centres, radii,
                             threshold_m, step_rad, reach_m, q_full, pts, body_w, np.full(2, np.nan))


@njit(cache=True, nogil=True)
def segment_free_from(qa, qb, q_template, planned, lengths, checked, body, verts, starts, centres, radii,
                      threshold_m, step_rad, reach_m, q_full, pts, body_w, clr_ends):
    """
    Quick test of qa → qb, as :func:`segment_free`, reusing a known clearance at qa.

    The verdict on the samples at qa + (k/n)·(qb − qa), k = 0 .. n (n = ⌈|qb − qa| / step_rad⌉),
    the last one qb itself: every one's clearance above ``threshold_m``.  A sample is measured
    unless a measured one before it proves it free: from clearance c at sample k, no point of
    a checked link comes nearer than c − D·(j − k)/n at sample j, D = Σ_a reach_m[a]·|qb_a − qa_a|
    (:func:`joint_reach_m`), so the samples with D·(j − k)/n ≤ 0.999 (c − threshold_m) −
    ``ROUNDING_SLACK_M`` are skipped (a margin, relative and absolute, that no rounding of a
    clearance or of a sample's position reaches: without the absolute part a segment an ulp
    long could pass on a clearance 10⁻¹⁵ m from the threshold).  The same verdict as measuring
    every sample, with fewer measurements away from obstacles; False where an end is not finite.
    ``clr_ends`` (2,), m:
    [0] the clearance at qa (NaN: measured, then stored there, so a walk trying several
    neighbours measures its node once); [1] set to the clearance at qb, NaN when qb was not
    measured (the test stopped before it, or skipped it): the next step's [0].
    """
    dof = qa.shape[0]
    d2 = 0.0
    for a in range(dof):
        d = qb[a] - qa[a]
        d2 += d * d
    clr_ends[1] = np.nan
    if not d2 < np.inf:
        return False                          # an end not finite: no motion (and no sample count)
    span_m = sweep_m(qa, qb, reach_m)      # D, m
    n = max(1, int(np.ceil(np.sqrt(d2) / step_rad)))
    k = 0
    while k <= n:
        if k == 0 and not np.isnan(clr_ends[0]):
            c = clr_ends[0]
        else:
            if k == n:
                for a in range(dof):
                    q_full[planned[a]] = qb[a]
            else:
                f = k / n
                for a in range(dof):
                    q_full[planned[a]] = qa[a] + f * (qb[a] - qa[a])
            c = config_clearance(q_full, lengths, checked, body, verts, starts, centres, radii, pts, body_w)
            if k == 0:
                clr_ends[0] = c
        if k == n:
            clr_ends[1] = c
        if not c > threshold_m:
            return False
        free = 0.999 * (c - threshold_m) - ROUNDING_SLACK_M     # the samples within it of k are free
        if free >= span_m:
            return True                           # every later sample (D ≥ the distance of any)
        k += 1 + (int(free * n / span_m) if free > 0.0 else 0)  # the first sample not proven free
    return True


@dataclass(frozen=True, eq=False)
class SegmentTest:
    """What a numba kernel needs to run :func:`segment_free` for one robot and scene."""

    q_template: np.ndarray
    planned: np.ndarray
    lengths: np.ndarray
    checked: np.ndarray
    body: np.ndarray
    verts: np.ndarray
    starts: np.ndarray
    centres: np.ndarray
    radii: np.ndarray
    threshold_m: float
    step_rad: float
    reach_m: np.ndarray

    @classmethod
    def of(cls, checker, step_rad: float = QUICK_STEP_RAD) -> "SegmentTest":
        robot = checker.robot
        return cls(np.asarray(robot.locked_rad, dtype=float), np.asarray(robot.planned_joints, dtype=np.int64),
                   checker.lengths, checker.checked, checker.body, checker.verts, checker.starts,
                   checker.centres, checker.radii, float(checker.margin_m), float(step_rad), joint_reach_m(robot))

    def arrays(self) -> tuple:
        return (self.q_template, self.planned, self.lengths, self.checked, self.body, self.verts,
                self.starts, self.centres, self.radii, self.threshold_m, self.step_rad, self.reach_m)


class MotionValidator:
    """
    The motion validator of one scene: its checker, the planned joints' bounds and axes, the step.

    OMPL's ``SpaceInformation`` and ``MotionValidator`` in one object: state validity comes
    from the scene's ``collision.CollisionChecker`` (clearance above its safety margin) and
    the bounds (bounded joints within them, periodic ones anywhere); motion validity from
    the certified walk along straight joint-space segments (:func:`certify_segments`,
    samples at most ``step_rad`` apart and closer near obstacles).

    Parameters
    ----------
        checker: the scene's CollisionChecker (robot, scene, margin).
        lower_rad, upper_rad, periodic: planned-joint bounds and periodic axes (default: the
            robot's, ``robot.planned_lower_rad`` ...).
        step_rad: largest spacing of the certified checks (``DEFAULT_VERIFY_STEP_RAD``).

    """

    def __init__(self, checker, lower_rad=None, upper_rad=None, periodic=None,
                 step_rad: float = DEFAULT_VERIFY_STEP_RAD):
        robot = checker.robot
        self.checker = checker
        self.lower_rad = np.asarray(robot.planned_lower_rad if lower_rad is None else lower_rad, dtype=float)
        self.upper_rad = np.asarray(robot.planned_upper_rad if upper_rad is None else upper_rad, dtype=float)
        self.periodic = tuple(bool(p) for p in (robot.planned_periodic if periodic is None else periodic))
        self.step_rad = float(step_rad)
        if not (np.isfinite(self.step_rad) and self.step_rad > 0.0):
            raise ValueError(f"step_rad: must be a positive number, got {step_rad!r}")
        self._periodic_mask = np.array(self.periodic, dtype=bool)
        #: (lower, upper) (dof,) rad with -inf and inf for a periodic joint (the controller check's quintics)
        self.bounds_rad = (np.where(self._periodic_mask, -np.inf, self.lower_rad),
                           np.where(self._periodic_mask, np.inf, self.upper_rad))
        self._with_step = {}          # the validators of other steps (with_step), made once
        self._kept = {}               # an interval's two rows (bytes) -> its certificate (check_kept)
        self._quick_step_rad = None   # the quick test's spacing on this scene (segment_test), made once
        #: what the certified walk (``certify_segments``) needs of the robot and the scene
        self.kernel_arrays = (np.asarray(robot.locked_rad, dtype=float),
                              np.asarray(robot.planned_joints, dtype=np.int64), checker.lengths,
                              checker.checked, checker.body, checker.verts, checker.starts, checker.centres,
                              checker.radii)
        #: r_j per planned joint, m (:func:`joint_reach_m`): the certified walk's Lipschitz rule (:func:`sweep_m`)
        self.reach_m = joint_reach_m(robot)

    @classmethod
    def for_scene(cls, robot, scene, step_rad: float = DEFAULT_VERIFY_STEP_RAD) -> "MotionValidator":
        """Return the validator of ``scene`` for ``robot`` (its bounds; a new CollisionChecker)."""
        return cls(CollisionChecker(robot, scene), step_rad=step_rad)

    @classmethod
    def of(cls, motions, step_rad: float | None = None) -> "MotionValidator":
        """Return ``motions`` itself (a MotionValidator) or the validator of a CollisionChecker."""
        if isinstance(motions, MotionValidator):
            return motions if step_rad is None else motions.with_step(step_rad)
        return cls(motions, step_rad=DEFAULT_VERIFY_STEP_RAD if step_rad is None else step_rad)

    def with_step(self, step_rad: float) -> "MotionValidator":
        """Return a validator of the same scene and bounds with another certified step."""
        if float(step_rad) == self.step_rad:
            return self
        other = self._with_step.get(float(step_rad))
        if other is None:
            other = MotionValidator(self.checker, self.lower_rad, self.upper_rad, self.periodic, step_rad)
            if len(self._with_step) >= 8:
                self._with_step.clear()
            self._with_step[float(step_rad)] = other
        return other

    @property
    def robot(self):
        return self.checker.robot

    @property
    def margin_m(self) -> float:
        return self.checker.margin_m

    # ----------------------------------------------------------------- states
    def clearance_m(self, q_rad):
        """Clearance of one configuration (float) or of each row of (N, dof) (array), metres."""
        return self.checker.clearance_m(q_rad)

    def within_bounds(self, q_rad, tol_rad: float = 0.0) -> np.ndarray:
        """Per row of q: every bounded joint within its bounds (± ``tol_rad``)."""
        return within_bounds(q_rad, self.lower_rad, self.upper_rad, self.periodic, tol_rad)

    # ---------------------------------------------------------------- motions
    def _rows(self, path_rad) -> np.ndarray:
        """
        Return ``path_rad`` as contiguous float64 rows (M, dof) of this validator's planned joints.

        ValueError for another shape: the kernels write each row into the robot's configuration
        by the planned joints' indices, unchecked (a path of another robot's joints would write
        past it).
        """
        p = np.ascontiguousarray(path_rad, dtype=float)
        if p.ndim != 2 or p.shape[1] != len(self.periodic) or len(p) == 0:
            raise ValueError(f"path_rad: rows of this validator's {len(self.periodic)} planned joints expected, "
                             f"got shape {p.shape}")
        return p

    def check(self, path_rad, *, step_rad: float | None = None, required_clearance_m: float | None = None,
              min_step_rad: float = 1e-6, certified: bool = True, vertex_clearance_m=None,
              every_row: bool = True) -> PathCheck:
        """
        Certified check of the piecewise-linear path through the rows of ``path_rad``.

        Along every interval, samples are at most ``step_rad`` (default the validator's)
        apart and close enough that their clearance balls overlap (:func:`sweep_m`'s bound
        of the interval), so the *whole* interval, not only the samples, keeps clearance above the
        safety margin (and at least ``required_clearance_m`` if given).  Bounded joints
        must stay within bounds at the rows (then also between them).  ``certified=False``:
        a quick test at samples ``step_rad`` apart only (for candidates; never for what
        is returned).  ``vertex_clearance_m``: (M,) the clearances at the rows from an
        earlier check of the *same* rows (``PathCheck.vertex_clearance_m``, NaN where not
        known), reused instead of evaluated again.  ``every_row=False``: one walk along the whole
        polyline, rows that a sample before them proves free passed over (for a dense polyline
        of samples of a curve, :func:`certify_segments`); an interval no sample falls in then has
        clearance ``inf`` in ``interval_clearance_m``, and ``min_clearance_m`` is the smallest over the samples taken
        and the first and last rows (the walk may pass over the last: a controller's motion's goal, where a grasp's
        clearance is least; a helper's audit found the servicer's reported up to 27 mm high on half its plans).
        """
        checker = self.checker
        step = self.step_rad if step_rad is None else float(step_rad)
        p = self._rows(path_rad)
        threshold = checker.margin_m if required_clearance_m is None else max(checker.margin_m,
                                                                              required_clearance_m)
        if len(p) == 1:
            c = float(checker.clearance_m(p[0]))
            return PathCheck(c > threshold and bool(self.within_bounds(p)[0]), np.zeros(0, dtype=bool), c, 1,
                             np.zeros(0))
        if vertex_clearance_m is None:
            vertex_clr = np.full(len(p), np.nan)
        else:
            vertex_clr = np.array(vertex_clearance_m, dtype=float)
            if vertex_clr.shape != (len(p),):
                raise ValueError(f"vertex_clearance_m: expected {len(p)} values (one per row), "
                                 f"got shape {vertex_clr.shape}")
        ok, best, n, interval_ok, interval_clr = check_kernel(
            p, self.lower_rad, self.upper_rad, self._periodic_mask, *self.kernel_arrays, float(threshold),
            self.reach_m, step, float(min_step_rad), bool(certified), vertex_clr, every_row)
        if not every_row:
            ends = vertex_clr[[0, -1]]
            ends = np.where(np.isnan(ends), checker.clearance_m(p[[0, -1]]), ends)
            best = min(float(best), float(ends.min()))
        return PathCheck(bool(ok), interval_ok, float(best), int(n), interval_clr, vertex_clr)

    def check_kept(self, path_rad) -> PathCheck:
        """
        Run :meth:`check` (certified, this validator's step and margin), keeping each interval's certificate.

        An interval's certificate (passed, its smallest clearance, the clearances at its two
        rows) is a pure function of its two rows, so the validator keeps it (``KEPT_INTERVALS``,
        keyed by the rows' bytes) and a later check of an interval with the same two rows bit
        for bit reuses it: the grid path of a replan shares every interval but its first with
        the plan before, and a start's join checked by :meth:`segment_ok` (``keep``) is the first interval
        of its grid path.  The intervals not kept are checked by :meth:`check`, one call per run
        of consecutive ones.  Returns what :meth:`check` returns, except ``n_checked``:
        the clearance evaluations this call made.
        """
        p = self._rows(path_rad)
        m = len(p) - 1
        if m < 1:
            return self.check(p)
        buf, row = p.tobytes(), p.shape[1] * 8
        keys = [buf[i * row:(i + 2) * row] for i in range(m)]      # an interval's two rows, contiguous
        kept = self._kept
        hits = [kept.get(key) for key in keys]
        ok_l, clr_l, vc_l = [False] * m, [0.0] * m, [math.nan] * (m + 1)     # Python lists: item by item
        todo = []
        for i, hit in enumerate(hits):
            if hit is None:
                todo.append(i)
                continue
            ok_l[i], clr_l[i], a, b = hit
            if a == a:                  # not NaN (a walk that failed early leaves its end unknown)
                vc_l[i] = a
            if b == b:
                vc_l[i + 1] = b
        interval_ok = np.array(ok_l, dtype=bool)
        interval_clr = np.array(clr_l, dtype=float)
        vertex_clr = np.array(vc_l, dtype=float)
        n = 0
        k = 0
        while k < len(todo):
            lo = todo[k]
            while k + 1 < len(todo) and todo[k + 1] == todo[k] + 1:
                k += 1
            hi = todo[k] + 1            # intervals lo .. hi - 1: rows lo .. hi
            k += 1
            run = self.check(p[lo:hi + 1], vertex_clearance_m=vertex_clr[lo:hi + 1])    # its own copy
            n += run.n_checked
            interval_ok[lo:hi] = run.interval_ok
            interval_clr[lo:hi] = run.interval_clearance_m
            vertex_clr[lo:hi + 1] = run.vertex_clearance_m
            oks, clrs, vcs = (run.interval_ok.tolist(), run.interval_clearance_m.tolist(),
                              run.vertex_clearance_m.tolist())
            for j in range(hi - lo):
                if len(kept) >= KEPT_INTERVALS:
                    kept.pop(next(iter(kept)))              # the oldest out
                kept[keys[lo + j]] = (oks[j], clrs[j], vcs[j], vcs[j + 1])
        # check_kernel's smallest interval clearance: NaN if one is NaN
        return PathCheck(bool(interval_ok.all()), interval_ok, float(interval_clr.min()), n, interval_clr,
                         vertex_clr)

    def first_bad_segment(self, points_rad, step_rad: float | None = None) -> int:
        """Index i of the first straight segment points[i]→points[i+1] that fails, or -1."""
        chk = self.check(points_rad, step_rad=step_rad)
        if chk.ok:
            return -1
        bad = np.flatnonzero(~chk.interval_ok)
        return int(bad[0]) if len(bad) else len(points_rad) - 2

    def segment_ok(self, a_rad, b_rad, step_rad: float | None = None, keep: bool = False) -> bool:
        """
        Certified check of the shortest straight segment a → b (periodic axes unwrapped).

        ``keep``: its certificate kept (:meth:`check_kept`, at this validator's step), for a
        later check of a path that starts with this segment (a start's join to its grid path).
        """
        seg = unwrap_path(np.vstack([a_rad, b_rad]), self.periodic)
        if keep and (step_rad is None or float(step_rad) == self.step_rad):
            return self.check_kept(seg).ok
        return self.check(seg, step_rad=step_rad).ok

    def segment_test(self, step_rad: float | None = None) -> SegmentTest:
        """
        Return what a numba kernel needs to run the quick :func:`segment_free` on this scene.

        ``step_rad``: its sample spacing; None: the scene's (:func:`quick_step_rad`).
        """
        if step_rad is None:
            if self._quick_step_rad is None:
                self._quick_step_rad = quick_step_rad(self.checker)
            step_rad = self._quick_step_rad
        return SegmentTest.of(self.checker, step_rad)
