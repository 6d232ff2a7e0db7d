"""
Free-floating capture: plan the arm so that, drifting, it still grasps the handle perpendicularly.

With attitude control off during the motion (``acs.mode: free_floating``) the spacecraft turns
and translates under the arm (``spacecraft.free_floating_response``): the attitude change
depends on the arm's whole path (the constraint is nonholonomic), the body's position only on
the configuration (the system's centre of mass stays put).  :func:`plan_capture` is
Papadopoulos' method with polynomial joint paths whose free parameters steer the final
attitude:

1. the capture postures, inertial frame (:func:`capture_postures`): tip at the grasp point,
   link 3 at the handle's normal turned by an offset within ``grasp.max_approach_error_deg``,
   the body where the centre of mass puts it; each fixes the attitude change the arm's motion
   must make;
2. the base paths from the start's arm joints to the posture's: the rest-to-rest quintic and,
   from the pipeline, the harmonic field's path in the scene as the drifted body sees it at
   the end (:func:`apparent_scene`);
3. the approach offset is a free parameter: where a base path's own attitude change equals
   the one its posture needs, that base needs no correction (found by Brent's method over
   the offset, the edge of reach bisected);
4. otherwise sine terms (``SEARCH["harmonics"]`` per joint) are added along seeded
   directions of their coefficient space, the amplitude solved (Brent) so that the
   momentum balance turns the body by exactly the needed change;
5. the families are taken least correction first, each one's candidates shortest first,
   each certified in the inertial frame (``reaction.check_drifted``: the body turned and
   moved, the target fixed); the first certified is the plan.

A change outside what the families' motions achieve is refused with both numbers.  The
attitude change of a path is integrated by a numba kernel (:func:`attitude_changes_rad`,
the same quadrature as ``spacecraft.free_floating_response``): most of a plan's time, the
scan of step 4 above all (96 × 31 coarse paths per family).  Each momentum row is evaluated
once per path row and midpoint, each cosine once per pair of links, and step 3's postures
and gaps once per approach offset (its bisection of the edge of reach needs the postures
only): in half the time (the capture scene's replans 145-170 -> 69-77 ms; refusals, which
scan every family, 0.9-1.2 -> 0.4-0.6 s), the same plans to the bit on the 14 scenes it was
measured on as the kernel that evaluated every Simpson point afresh.  A row's end point is
now the row itself, not the previous row plus the step: the same attitude changes on smooth
paths, within 4e-15 on rows drawn at random.  A batch of paths (a family's scan, step 3's gaps
at every approach offset, integrated together) runs on numba's threads from
:data:`PARALLEL_MIN_ROWS` path rows on, each path as in one thread (the same bits on any number of
threads); the pipeline gives the scans the cores other work leaves (``fit_threads``), and a family's
scan makes, checks and integrates each path's rows in one kernel (:func:`_family_changes`): on the
capture scene from its start and from 12 random targets and starts (docs/benchmarks.md, twenty-first
sitting) a grasp takes 26-28 ms instead of 67 and a refusal 129 instead of 714-737 (medians on two
cores, over two paired runs: 67 -> 37 and 714-737 -> 272 by the changes here, then -> 26-28 and 129 by
the momentum's row inlined in the kernels, ``spacecraft``).  No ROS imports.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np
from numba import njit, prange

from .collision import CollisionChecker
from .cores import current_threads
from .ik import _fit_to_bounds as fit_to_bounds  # noqa: PLC2701 - the IK module's own helpers
from .ik import _two_link as two_link  # noqa: PLC2701
from .ik import approach_error_rad
from .joint_space import wrap_angle_rad
from .reaction import DriftCheck, check_drifted
from .scene import Scene, Target
from .spacecraft import FreeFloatingResponse, MassProperties, free_floating_response, system_com_m
from .spacecraft import _momentum_map_row, _momentum_tables  # noqa: PLC2701 - the momentum's one rule

__all__ = ["apparent_scene", "captures_free_floating", "check_capture_scenario", "FreeFloatingCapture",
           "CapturePostureFF", "capture_postures", "attitude_changes_rad", "plan_capture", "SEARCH",
           "warm_up"]


def apparent_scene(scene, attitude_change_rad, body_position_m):
    """
    Return the inertial scene as the body sees it at the end of a free-floating motion.

    Turned by −Δθ1 about the body centre after the body moved by b.
    """
    c, s = math.cos(-attitude_change_rad), math.sin(-attitude_change_rad)
    rot = np.array([[c, -s], [s, c]])
    b = np.asarray(body_position_m, dtype=float)

    def move(p):
        return (np.asarray(p, dtype=float) - b) @ rot.T

    target = None
    if scene.target is not None:
        t = scene.target
        target = Target(center_m=tuple(move(t.center_m)), yaw_rad=t.yaw_rad - attitude_change_rad,
                        body_side_m=t.body_side_m, handle_side_m=t.handle_side_m)
    return Scene(target=target, debris_m=tuple(move(p) for p in scene.debris_m),
                 safety_margin_m=scene.safety_margin_m)


def circular_band_deg(angles_deg) -> tuple:
    """
    Return (lo, hi), degrees, lo ≤ hi: the shortest arc of the circle holding every angle.

    Where the angles straddle ±180° (+176.2 ... +180 and -180 ... -174.5) the arc is +176.2° to
    +185.5°, not -180° to +178.3°.  ``lo`` lies in [-180, 180); ``hi - lo`` < 360.
    """
    a = np.sort(np.mod(np.asarray(angles_deg, dtype=float) + 180.0, 360.0) - 180.0)
    gaps = np.diff(np.r_[a, a[0] + 360.0])               # the gap after each angle, round the circle
    k = int(np.argmax(gaps))                              # the arc is the circle less its largest gap
    lo = a[(k + 1) % len(a)]
    return float(lo), float(lo + 360.0 - gaps[k])


#: the path family and its search (see :func:`plan_capture`): samples of the coarse scan, the
#: sine harmonics per arm joint, the scanned amplitudes (rad), the scanned directions of the
#: coefficient space (seeded, so the plan is deterministic), the candidates certified at most, the
#: capture postures' approach offsets (fractions of grasp.max_approach_error_deg), and whether the
#: offset is solved for as a free parameter (step 3), whether the field's guide is used (step 2);
#: the bench turns those off to measure without them.  The offsets reach the tolerance's edge
#: (0.999: a grasp point at the edge of reach has capture postures only 4.5-5° off the normal,
#: and was refused as "out of the arm's reach")
SEARCH = {"coarse_samples": 61, "harmonics": 2, "max_amplitude_rad": math.radians(180.0), "amplitudes": 31,
          "directions": 96, "seed": 0, "max_checks": 400,
          "approach_fractions": (0.0, -0.5, 0.5, -0.9, 0.9, -0.999, 0.999),
          "approach_as_parameter": True, "field_guide": True}


@njit(cache=True, nogil=True, inline="always")
def _rate(h, q0, q1):
    """Return the attitude's rate per unit path step −Σ_{i>0} H_i (q1_i − q0_i) / H_0."""
    num = 0.0
    for i in range(h.shape[0] - 1, 0, -1):
        num += h[i] * (q1[i] - q0[i])
    return -num / h[0]


@njit(cache=True, nogil=True, inline="always")
def _profile_into(path, pair, inertia, out, w, h_row, h_mid, h_next, mid):
    """Write a path's (K, n) attitude change at each row after its first into out (K,) (:func:`_attitude_profiles`)."""
    nk, n = path.shape
    total = 0.0
    _momentum_map_row(pair, inertia, path[0], w, h_row)
    for k in range(nk - 1):
        q0 = path[k]
        q1 = path[k + 1]
        for j in range(n):
            mid[j] = q0[j] + 0.5 * (q1[j] - q0[j])
        _momentum_map_row(pair, inertia, mid, w, h_mid)
        _momentum_map_row(pair, inertia, q1, w, h_next)
        step = _rate(h_row, q0, q1)
        step += 4.0 * _rate(h_mid, q0, q1)
        step += _rate(h_next, q0, q1)
        total += step / 6.0
        out[k + 1] = total
        h_row, h_next = h_next, h_row


@njit(cache=True, nogil=True)
def _attitude_profiles(paths, pair, inertia):
    """
    Attitude change (rad) at every row of each full-joint path of ``paths`` (B, K, n): (B, K).

    The paths are straight between rows.  The momentum row at q (``spacecraft._momentum_map_row``):
    g_k = Σ_j pair[j, k] cos(φ_k − φ_j) + inertia[k] is the angular momentum per unit rate of the
    absolute angle φ_k (about the system's centre of mass), and H_i = Σ_{k≥i} g_k; free floating
    dθ1 = −Σ_{i>0} H_i dθ_i / H_0, Simpson's rule per row step: H at the rows (each row's
    once, the end of one step and the start of the next) and at the steps' midpoints.
    """
    nb, nk, n = paths.shape
    out = np.zeros((nb, nk))
    w = np.empty((4, n))
    h_row, h_mid, h_next, mid = np.empty(n), np.empty(n), np.empty(n), np.empty(n)
    for b in range(nb):
        _profile_into(paths[b], pair, inertia, out[b], w, h_row, h_mid, h_next, mid)
    return out


@njit(cache=True, nogil=True, parallel=True)
def _attitude_profiles_parallel(paths, pair, inertia):
    """:func:`_attitude_profiles` with the paths in 64 chunks on numba's threads: each path as in one thread."""
    nb, nk, n = paths.shape
    out = np.zeros((nb, nk))
    chunks = 64
    size = (nb + chunks - 1) // chunks
    for ch in prange(chunks):
        w = np.empty((4, n))
        h_row, h_mid, h_next, mid = np.empty(n), np.empty(n), np.empty(n), np.empty(n)
        for b in range(ch * size, min(nb, (ch + 1) * size)):
            _profile_into(paths[b], pair, inertia, out[b], w, h_row, h_mid, h_next, mid)
    return out


#: A batch of at least this many path rows (paths × rows) runs on numba's threads where the calling
#: thread has more than one (:func:`_profiles`; ``cores.current_threads``, which the pipeline sets for
#: the cores other work leaves before the search).  Each path is integrated as in one thread: the same
#: bits either way.  Below it, the team's start and join cost more than the rows (a row about 0.3 us).
PARALLEL_MIN_ROWS = 4096


def _on_threads(paths: int, rows: int) -> bool:
    """Tell whether a batch of ``paths`` paths of ``rows`` rows each runs its kernel's parallel form (above)."""
    return paths > 1 and paths * rows >= PARALLEL_MIN_ROWS and current_threads() > 1


def _profiles(paths, pair, inertia):
    """Return :func:`_attitude_profiles` of ``paths`` (B, K, n), on numba's threads for a large batch (above)."""
    nb, nk = paths.shape[0], paths.shape[1]
    if nk == 0:
        return np.zeros((nb, 0))          # (the kernels read each path's first row)
    kernel = _attitude_profiles_parallel if _on_threads(nb, nk) else _attitude_profiles
    return kernel(paths, pair, inertia)


def _attitude_changes(paths, pair, inertia):
    """Return the attitude change over each path of ``paths`` (B, K, n): (B,) rad (see :func:`_attitude_profiles`)."""
    return _profiles(paths, pair, inertia)[:, -1]


@njit(cache=True, nogil=True, inline="always")
def _rows_into(base, coef, basis, out, col):
    """
    Write a family's path into out[:, col:col + m]: row k, joint j is base[k, j] + Σ_h coef[j, h] basis[h, k].

    base (K, m) the base's rows, coef (m, H) the sine terms' coefficients, rad; basis (H, K) (:func:`_basis`).
    The one rule of the family's rows (:func:`_family`, :func:`_family_span`).
    """
    nk, m = base.shape
    for k in range(nk):
        for j in range(m):
            acc = 0.0
            for h in range(basis.shape[0]):
                acc += coef[j, h] * basis[h, k]
            out[k, col + j] = base[k, j] + acc


@njit(cache=True, nogil=True)
def _family_rows(base, coef, basis):
    """Return a family's path (K, m) (:func:`_rows_into`)."""
    out = np.empty(base.shape)
    _rows_into(base, coef, basis, out, 0)
    return out


@njit(cache=True, nogil=True, inline="always")
def _family_span(i0, stride, base, basis, dirs, amps, lo, hi, att0, pair, inertia, delta, inside):
    """
    Integrate a family's paths i0, i0 + stride, ... (flat (direction, amplitude) indices) that stay within the bounds.

    Path (d, a): coefficients dirs[d] amps[a] (:func:`_rows_into`), the attitude ``att0`` (it drifts);
    within [lo, hi] at every row (NaN is not): ``inside[d, a]`` and ``delta[d, a]`` its attitude change
    (:func:`_profile_into`), else left as they are.
    """
    nk, m = base.shape
    n_amp = amps.shape[0]
    row = np.empty((nk, m + 1))
    coef = np.empty((m, basis.shape[0]))
    prof = np.zeros(nk)
    w = np.empty((4, m + 1))
    h_row, h_mid, h_next, mid = np.empty(m + 1), np.empty(m + 1), np.empty(m + 1), np.empty(m + 1)
    for i in range(i0, delta.size, stride):
        d, a = i // n_amp, i % n_amp
        for j in range(m):
            for h in range(coef.shape[1]):
                coef[j, h] = dirs[d, j, h] * amps[a]
        _rows_into(base, coef, basis, row, 1)
        within = True
        for k in range(nk):
            row[k, 0] = att0
            for j in range(m):
                v = row[k, j + 1]
                if not (v >= lo[j] and v <= hi[j]):
                    within = False
                    break
            if not within:
                break                   # not integrated: the rest of its rows unread
        if within:
            inside[d, a] = True
            _profile_into(row, pair, inertia, prof, w, h_row, h_mid, h_next, mid)
            delta[d, a] = prof[nk - 1]


@njit(cache=True, nogil=True)
def _family_changes(base, basis, dirs, amps, lo, hi, att0, pair, inertia):
    """
    Return a family's scan: (attitude change float64 (D, A), NaN outside the bounds; within the bounds bool (D, A)).

    base (K, m) the family's base at the scan's rows, basis (H, K) its sine terms (:func:`_basis`), dirs
    (D, m, H) the directions, amps (A,) the amplitudes, rad; lo, hi (m,) the arm joints' bounds, rad;
    att0 the start's attitude, rad.  Without the family's (D, A, K, m) array of rows: each path's rows
    made, checked and integrated in turn (:func:`_family_span`).
    """
    delta = np.full((dirs.shape[0], amps.shape[0]), np.nan)
    inside = np.zeros((dirs.shape[0], amps.shape[0]), np.bool_)
    _family_span(0, 1, base, basis, dirs, amps, lo, hi, att0, pair, inertia, delta, inside)
    return delta, inside


@njit(cache=True, nogil=True, parallel=True)
def _family_changes_parallel(base, basis, dirs, amps, lo, hi, att0, pair, inertia):
    """
    :func:`_family_changes` on numba's threads: each path as in one thread.

    64 strands, strand c the paths c, c + 64, ...: the paths out of bounds cost next to nothing and cluster
    by direction, and 64 contiguous chunks ran 2.5-4 % longer (four capture cases' scans, alternating).
    """
    delta = np.full((dirs.shape[0], amps.shape[0]), np.nan)
    inside = np.zeros((dirs.shape[0], amps.shape[0]), np.bool_)
    strands = 64
    for c in prange(strands):
        _family_span(c, strands, base, basis, dirs, amps, lo, hi, att0, pair, inertia, delta, inside)
    return delta, inside


def _family_scan(base, basis, dirs, amps, lo, hi, att0, pair, inertia):
    """Return :func:`_family_changes`, on numba's threads for a large scan (:data:`PARALLEL_MIN_ROWS`)."""
    if base.shape[0] == 0:
        raise ValueError("a family's scan needs rows (SEARCH['coarse_samples'] >= 1)")
    kernel = _family_changes_parallel if _on_threads(dirs.shape[0] * amps.shape[0], base.shape[0]) else _family_changes
    return kernel(np.ascontiguousarray(base, dtype=float), np.ascontiguousarray(basis, dtype=float),
                  np.ascontiguousarray(dirs, dtype=float), np.ascontiguousarray(amps, dtype=float),
                  np.ascontiguousarray(lo, dtype=float), np.ascontiguousarray(hi, dtype=float), float(att0), pair,
                  inertia)


def warm_up(scenario) -> None:
    """
    Load (or compile) the capture's kernels where ``scenario`` plans free-floating captures (else nothing).

    The attitude kernels' two forms (one thread, numba's threads: paths, a family's scan) and a
    family's rows.  No warm-up plan reaches them (:func:`captures_free_floating` plans have no goal).
    """
    if not captures_free_floating(scenario, False):
        return
    robot = scenario.robot
    pair, inertia = _momentum_tables(robot, scenario.masses)
    n = robot.n_joints
    paths = np.zeros((2, 2, n))
    _attitude_profiles(paths, pair, inertia)
    _attitude_profiles_parallel(paths, pair, inertia)
    scan = (np.zeros((2, n - 1)), np.zeros((1, 2)), np.zeros((2, n - 1, 1)), np.zeros(2), np.full(n - 1, -1.0),
            np.ones(n - 1), 0.0, pair, inertia)
    _family_changes(*scan)
    _family_changes_parallel(*scan)
    _family_rows(scan[0], np.zeros((n - 1, 1)), scan[1])      # base (K, m), coefficients (m, H), basis (H, K)


def _com_coefficients(robot, masses):
    """(n,) c with the system's centre of mass r̄ = Σ_k c_k (cos φ_k, sin φ_k) from the body centre."""
    masses.check_robot(robot)
    n = robot.n_joints
    lengths = np.asarray(robot.link_lengths_m, dtype=float)
    coef = (np.tril(np.ones((n, n)), -1) + 0.5 * np.eye(n)) * lengths[None, :]
    return np.asarray(masses.link_masses_kg, dtype=float) @ coef / masses.total_mass_kg


def attitude_changes_rad(robot, masses: MassProperties, paths_full_rad) -> np.ndarray:
    """
    Free-floating attitude change of full-joint paths, rad: (K, n) → float, (B, K, n) → (B,).

    The arm joints (columns 1…) straight between rows; column 0 is ignored (it drifts).  The
    same quadrature as ``spacecraft.free_floating_response`` in a numba kernel.
    """
    p = np.asarray(paths_full_rad, dtype=float)
    pair, inertia = _momentum_tables(robot, masses)
    out = _attitude_changes(np.ascontiguousarray(np.atleast_3d(p) if p.ndim == 3 else p[None]), pair, inertia)
    return out if p.ndim == 3 else float(out[0])


@dataclass(frozen=True)
class CapturePostureFF:
    """
    A capture posture of the free-floating spacecraft, inertial frame.

    Attributes
    ----------
        q_full: (n,) rad: tip at the grasp point and link 3 along the handle's inward normal
            with the body at ``body_m``.
        body_m: (2,) where the body centre is then (the start's centre of mass kept), metres.
        attitude_change_rad: the attitude change from the start that this posture needs,
            wrapped into [−π, π).
        branch: 0 or 1, the inverse-kinematics branch (elbow one way or the other); None for
            a goal posture.

    """

    q_full: np.ndarray
    body_m: np.ndarray
    attitude_change_rad: float
    branch: int | None = None


def capture_postures(robot, masses: MassProperties, scene, start_full_rad, approach_offset_rad: float = 0.0) -> list:
    """
    Return the inertial capture postures of the scene's target from ``start_full_rad`` (n,).

    The grasp pose (the full-pose inverse kinematics of ``ik.grasp_ik`` with the attitude free:
    both branches; link 3 at the handle's inward normal turned by ``approach_offset_rad``) for
    the grasp point moved by the body's displacement b, and b = r̄(start) − r̄(q) from that
    posture, iterated to a fixed point (b is a few centimetres: a handful of steps).  Postures outside
    the joint bounds are dropped; collisions are not judged here (the inertial check of the
    whole motion does that).  3-joint chains (``grasp_ik``'s).
    """
    q0 = np.asarray(start_full_rad, dtype=float)
    coef = [float(c) for c in _com_coefficients(robot, masses)]

    def com(q):
        """r̄(q) from the body centre, (x, y) m: scalar arithmetic (the fixed point runs it a dozen times a posture)."""
        phi = x = y = 0.0
        for c, a in zip(coef, q):
            phi += a
            x += c * math.cos(phi)
            y += c * math.sin(phi)
        return x, y

    com0_x, com0_y = com(q0)
    gx, gy = (float(v) for v in scene.target.grasp_point_m)
    psi = scene.target.approach_angle_rad + float(approach_offset_rad)
    l1, l2, l3 = (float(v) for v in robot.link_lengths_m)
    ex, ey = gx - l3 * math.cos(psi), gy - l3 * math.sin(psi)        # the elbow point, body at rest
    out = []
    for branch in (0, 1):
        bx = by = 0.0                                                # the body's displacement b, m
        q = None
        for _ in range(50):
            sols = two_link((0.0, 0.0), (ex - bx, ey - by), l1, l2)  # (θ1, θ2) with the elbow point reached
            if len(sols) <= branch:
                q = None
                break
            th1, th2 = sorted(sols, key=lambda s: -s[1])[branch]
            q = (th1, th2, psi - th1 - th2)
            cx, cy = com(q)
            mx, my = com0_x - cx, com0_y - cy
            done = math.sqrt((mx - bx) ** 2 + (my - by) ** 2) < 1e-12
            bx, by = mx, my
            if done:
                break
        if q is not None:
            q = fit_to_bounds(robot, wrap_angle_rad(np.array(q)))
        if q is not None:
            out.append(CapturePostureFF(q, np.array([bx, by]), float(wrap_angle_rad(q[0] - q0[0])), branch))
    return out


@dataclass(frozen=True, eq=False)
class FreeFloatingCapture:
    """
    What :func:`plan_capture` found (or why not).

    Attributes
    ----------
        ok: a path whose free-floating motion ends in the grasp and is certified
            collision-free in the inertial frame.
        reason: why not (None when ok): the numbers (attitude change needed, the range the
            family's motions achieve, or the best clearance).
        path_rad: (K, dof) planned joints, samples ≤ 0.5° apart; a planned attitude column
            holds the attitude as it drifts.  (0, dof) when not ok.
        goal_rad: (dof,) the last row (None when not ok).
        posture: the chosen :class:`CapturePostureFF` (or the goal's), None when none.
        needed_deg: ((branch, degrees), …): the attitude change each capture posture (or the
            goal, branch None) needs.
        achievable_deg: ((branch, lowest, highest), …): the attitude changes of the families'
            motions that were searched, within the joint bounds, per branch, degrees.
        response: ``FreeFloatingResponse`` of ``path_rad`` (inertial), None when not ok.
        drift: the inertial ``DriftCheck`` of ``path_rad``, None when not ok.
        tip_miss_m, approach_error_deg: at the end, inertial frame (nan when not ok).
        candidates: paths with the needed attitude change within the bounds; checked: how many
            were certified before one passed.
        search_s, verify_s: seconds in the search and in the inertial certification.
        family: the base of the chosen path: "field" (the harmonic field's path, see
            ``base_path``) or "quintic" ("" when not ok).

    """

    ok: bool
    reason: str | None
    path_rad: np.ndarray
    goal_rad: np.ndarray | None
    posture: CapturePostureFF | None
    needed_deg: tuple
    achievable_deg: tuple
    response: FreeFloatingResponse | None
    drift: DriftCheck | None
    tip_miss_m: float
    approach_error_deg: float
    candidates: int
    checked: int
    search_s: float
    verify_s: float
    family: str = ""


def _basis(s, harmonics):
    """(H, K): sin(hπs), h = 1…H: zero at both ends (the base's ends kept)."""
    return np.stack([np.sin((h + 1) * np.pi * s) for h in range(harmonics)])


def _quintic(a0, af):
    """Return the rest-to-rest quintic a0 → af: a function of s ∈ [0, 1] (K,) → (K, m)."""
    def at(s):
        sig = s ** 3 * (10.0 - 15.0 * s + 6.0 * s * s)
        return a0 + (af - a0) * sig[:, None]
    return at


def _along(path):
    """Return a path's rows as a function of its normalised joint-space arc length s ∈ [0, 1] (K,) → (K, m)."""
    p = np.asarray(path, dtype=float)
    u = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(p, axis=0), axis=1))])
    u = u / u[-1] if u[-1] > 0.0 else np.linspace(0.0, 1.0, len(p))

    def at(s):
        return np.stack([np.interp(s, u, p[:, j]) for j in range(p.shape[1])], axis=-1)
    return at


def _family(base_at_s, coef, s, harmonics):
    """Arm path (K, m): the base's rows at s plus Σ_h coef[j, h] sin((h+1)π s) on joint j (:func:`_rows_into`)."""
    return _family_rows(np.ascontiguousarray(base_at_s, dtype=float), np.ascontiguousarray(coef, dtype=float),
                        _basis(s, harmonics))


def _directions(m, harmonics, count, seed):
    """Return unit directions of the (m × harmonics) coefficient space: the axes (both signs), then seeded ones."""
    dim = m * harmonics
    eye = np.eye(dim)
    rnd = np.random.default_rng(seed).normal(size=(max(0, count - 2 * dim), dim))
    d = np.vstack([eye, -eye, rnd / np.linalg.norm(rnd, axis=1, keepdims=True)])
    return d.reshape(-1, m, harmonics)


def _full(q0, arm_paths):
    """Full-joint paths: column 0 at the start's attitude (it drifts), the arm columns."""
    att = np.full(arm_paths.shape[:-1] + (1,), q0[0])
    return np.concatenate([att, arm_paths], axis=-1)


def captures_free_floating(scenario, goal_given: bool) -> bool:
    """
    Tell whether a plan of ``scenario`` is a free-floating capture (the pipeline runs :func:`plan_capture`).

    ``acs.mode: free_floating`` (not ``acs.compensate_drift``, the CLI's earlier strategy), a
    target, and either no goal (capture the target: callers leave the goal to the pipeline)
    or the attitude a planned joint (its motion must come from the arm's).
    """
    acs = scenario.acs
    return (acs.mode == "free_floating" and not acs.compensate_drift and scenario.scene.target is not None
            and (not goal_given or 0 in scenario.robot.planned_joints))


def check_capture_scenario(scenario) -> None:
    """Raise ValueError (naming what) when :func:`plan_capture` cannot plan for the scenario."""
    robot = scenario.robot
    if scenario.scene.target is None:
        raise ValueError("free-floating capture: the scene has no target")
    if robot.n_joints != 3:
        raise ValueError("free-floating capture: implemented for the 3-joint chain (attitude, shoulder, elbow)")
    if any(j not in robot.planned_joints for j in range(1, robot.n_joints)):
        raise ValueError("robot.planned_joints: free-floating capture plans every arm joint (only the attitude "
                         "may be locked)")


def plan_capture(scenario, start_rad, goal_rad=None, *, masses: MassProperties | None = None,
                 base_path=None, check=None, fit_threads=None) -> FreeFloatingCapture:
    """
    Plan the arm so that the free-floating spacecraft ends grasping the handle perpendicularly.

    Papadopoulos' method: the end posture is fixed (:func:`capture_postures`, or the given
    goal with the attitude as a planned joint), so is the attitude change Δ the arm's motion
    must cause.  The arm joints follow a(s) = base(s) + Σ_h c_h sin(hπs) (s ∈ [0, 1],
    ``SEARCH["harmonics"]`` terms per joint), the base being the rest-to-rest quintic
    a0 + (af − a0) σ(s) and, when ``base_path`` gives one, a guide path by arc length.  The
    attitude change of the free-floating motion is a function of the coefficients c; along
    each of ``SEARCH["directions"]`` directions c = α d the amplitude α is scanned
    (``SEARCH["amplitudes"]`` values up to ``max_amplitude_rad``, coarse paths) and every
    bracket of Δ refined by Brent's method on the final path.  Candidates (within the joint
    bounds) are certified shortest first (``reaction.check_drifted``: the body turned and
    moved, the target fixed).  No candidate: ``ok`` False with the numbers.

    Args:
        scenario: a ``config.Scenario`` with a target and ``acs.mode`` free floating; every
            arm joint planned (the attitude may be planned: its column is the drift).
        start_rad: (dof,) planned joints; goal_rad: (dof,) a goal posture to reach instead of
            a capture posture (its attitude is reached by the drift).
        masses: default ``scenario.masses``.
        base_path: optional callable(posture) → (K, m) arm path from the start's arm joints to the
            posture's (or None): a second family on that path (by arc length) besides the
            quintic — the harmonic field's path in the scene as the body sees it at the end
            (``pipeline``).
        check: callable polled between candidates (a cancel check that raises).
        fit_threads: callable run once before the scans, after the guides' plans (which set the
            thread's numba threads for their own stages): the pipeline gives the scans' parallel
            kernel the cores other work leaves (``cores.fit_threads(any_size=True)``); None: the
            thread's count as it is.

    Raises
    ------
        ValueError: no target, a locked arm joint, or a chain other than 3 joints.

    """
    check_capture_scenario(scenario)
    robot, scene = scenario.robot, scenario.scene
    masses = scenario.masses if masses is None else masses
    arm = list(range(1, robot.n_joints))
    t0 = time.perf_counter()
    start_full = robot.full(np.asarray(start_rad, dtype=float))
    tol = math.radians(scenario.planner_settings.max_approach_error_deg)
    if goal_rad is None:
        postures = [p for f in SEARCH["approach_fractions"]
                    for p in capture_postures(robot, masses, scene, start_full, f * tol)]
    else:
        goal_full = robot.full(np.asarray(goal_rad, dtype=float))
        postures = [CapturePostureFF(goal_full, np.zeros(2), float(wrap_angle_rad(goal_full[0] - start_full[0])))]
    lo = np.asarray(robot.lower_rad)[arm] - 1e-9
    hi = np.asarray(robot.upper_rad)[arm] + 1e-9
    a0 = start_full[arm]
    harm = SEARCH["harmonics"]
    dirs = _directions(len(arm), harm, SEARCH["directions"], SEARCH["seed"])
    amps = np.linspace(0.0, SEARCH["max_amplitude_rad"], SEARCH["amplitudes"])
    s_coarse = np.linspace(0.0, 1.0, SEARCH["coarse_samples"])
    basis_coarse = _basis(s_coarse, harm)
    pair, inertia = _momentum_tables(robot, masses)
    periodic = np.asarray(robot.periodic)[arm]

    def arm_end(post):
        af = post.q_full[arm]
        return np.where(periodic, a0 + wrap_angle_rad(af - a0), af)

    # the families: (posture, name, base); the base's own attitude change (amplitude 0) orders them
    guides = {}

    def make_base(post, kind):
        af = arm_end(post)
        if kind == "quintic":
            return _quintic(a0, af)
        if post.branch not in guides:
            first = next(p for p in postures if p.branch == post.branch)        # approach offset 0
            g = base_path(first)
            guides[post.branch] = None if g is None else (_along(g), arm_end(first))
        if guides[post.branch] is None:
            return None
        along, af0 = guides[post.branch]
        ramp = _quintic(np.zeros_like(af), af - af0)                             # to this posture's end
        return lambda s: along(s) + ramp(s)

    guided = base_path is not None and goal_rad is None and SEARCH["field_guide"]
    kinds = ("field", "quintic") if guided else ("quintic",)
    families = [(post, kind, base) for post in postures for kind in kinds
                if (base := make_base(post, kind)) is not None]
    if fit_threads is not None:          # every guide is made: no plan of its own runs from here on
        fit_threads()
    if goal_rad is None and SEARCH["approach_as_parameter"]:
        # the approach tolerance as a free parameter: the end posture whose attitude change the
        # base path itself makes (no correction needed), where one exists within the tolerance
        s_mid = np.linspace(0.0, 1.0, 801)
        fracs = np.linspace(-0.999, 0.999, 20)       # up to the tolerance's edge, as SEARCH's
        front = []
        at_offset = {}            # approach fraction -> its capture postures (both branches; pure)
        gaps = {}                 # (fraction, branch, kind) -> gap (pure: each computed once)

        def based(frac, branch, kind):
            """Return (the family's base, its posture) at an approach fraction, or (None, None) beyond reach."""
            if frac not in at_offset:
                at_offset[frac] = capture_postures(robot, masses, scene, start_full, frac * tol)
            posts = [p for p in at_offset[frac] if p.branch == branch]
            base = make_base(posts[0], kind) if posts else None
            return (None, None) if base is None else (base, posts[0])

        def prefill(branches):
            """Fill ``gaps`` at every fraction of ``fracs``, branch and kind: their paths integrated in one batch."""
            todo, paths = [], []
            for branch in branches:
                for kind in kinds:
                    for frac in fracs:
                        key = (float(frac), branch, kind)
                        base, post = based(frac, branch, kind)
                        if base is None:
                            gaps[key] = math.nan, None
                        else:
                            todo.append((key, post))
                            paths.append(_full(start_full, base(s_mid)))
            if paths:        # each path as gap would integrate it alone: the same values
                own_d = _attitude_changes(np.ascontiguousarray(np.stack(paths)), pair, inertia)
                for (key, post), d in zip(todo, own_d):
                    gaps[key] = d - post.attitude_change_rad, post

        prefill(sorted({p.branch for p in postures}))
        for branch in sorted({p.branch for p in postures}):
            for kind in kinds:
                def gap(frac, branch=branch, kind=kind):
                    key = (float(frac), branch, kind)
                    if key not in gaps:
                        base, post = based(frac, branch, kind)
                        if base is None:
                            gaps[key] = math.nan, None
                        else:
                            own_d = _attitude_changes(np.ascontiguousarray(_full(start_full, base(s_mid))[None]),
                                                      pair, inertia)[0]
                            gaps[key] = own_d - post.attitude_change_rad, post
                    return gaps[key]

                vals = [gap(f)[0] for f in fracs]
                for i in range(len(fracs) - 1):
                    a_f, b_f, b_v = fracs[i], fracs[i + 1], vals[i + 1]
                    if math.isnan(vals[i]) != math.isnan(b_v):   # the edge of reach: bisect it
                        inner, outer = (a_f, b_f) if math.isnan(b_v) else (b_f, a_f)
                        for _ in range(24):      # reach only: the posture, not its attitude change
                            mid = 0.5 * (inner + outer)
                            inner, outer = (inner, mid) if based(mid, branch, kind)[0] is None else (mid, outer)
                        a_f, b_f = (a_f, inner) if math.isnan(b_v) else (inner, b_f)
                        a_v, b_v = gap(a_f)[0], gap(b_f)[0]
                    else:
                        a_v = vals[i]
                    if not (a_v * b_v <= 0.0):                     # no sign change
                        continue
                    try:
                        from scipy.optimize import brentq    # SciPy loaded only where it is used (start-up)
                        f_star = brentq(lambda f: gap(f)[0], a_f, b_f, xtol=1e-12)
                    except ValueError:
                        continue
                    post = gap(f_star)[1]
                    if post is not None:
                        front.append((post, kind, make_base(post, kind)))
                        postures.append(post)
        families = front + families
    base_paths = np.stack([base(s_coarse) for _, _, base in families]) if families else np.zeros((0, 1, len(arm)))
    own = _attitude_changes(np.ascontiguousarray(_full(start_full, base_paths)), pair, inertia)
    # least correction first (to 1e-3 rad: the tolerance-matched postures first, the field's first)
    order = sorted(range(len(families)), key=lambda i: (round(abs(own[i] - families[i][0].attitude_change_rad), 3), i))
    checker = CollisionChecker(robot, scene)
    dof_cols = list(robot.planned_joints)
    n_candidates = n_checked = 0
    best_clear = -math.inf
    search_s = verify_s = 0.0
    reach = {}                    # branch (or the goal) -> (lowest, highest) attitude change, rad
    found = None
    for f_i in order:
        post, kind, base = families[f_i]
        need = post.attitude_change_rad
        t_s = time.perf_counter()
        base_coarse = base(s_coarse)                                          # (K, m)
        # the attitude change of the paths within the joint bounds only (the others are no
        # candidates and no part of the reach): nan elsewhere; (D, A) each
        delta, inside = _family_scan(base_coarse, basis_coarse, dirs, amps, lo, hi, start_full[0], pair, inertia)
        if not inside.any():
            continue
        r = reach.get(post.branch, (math.inf, -math.inf))
        reach[post.branch] = (min(r[0], float(delta[inside].min())), max(r[1], float(delta[inside].max())))
        # the brackets (the smallest amplitude along each direction), the coarse path's length at
        # the interpolated root; refined on the final path only when certified, shortest first
        candidates = []
        f_all = delta - need
        bracket = inside[:, :-1] & inside[:, 1:] & ~(f_all[:, :-1] * f_all[:, 1:] > 0.0)    # (D, A - 1)
        firsts = bracket.argmax(axis=1)                          # each direction's first bracket
        for d_i in np.flatnonzero(bracket.any(axis=1)):
            d, f, a_i = dirs[d_i], f_all[d_i], int(firsts[d_i])
            w = f[a_i] / (f[a_i] - f[a_i + 1]) if f[a_i] != f[a_i + 1] else 0.0
            approx = _family(base_coarse, (amps[a_i] + w * (amps[a_i + 1] - amps[a_i])) * d, s_coarse, harm)
            candidates.append((float(np.sum(np.linalg.norm(np.diff(approx, axis=0), axis=1))), int(d_i), a_i))
        candidates.sort()
        n_candidates += len(candidates)
        search_s += time.perf_counter() - t_s
        t_v = time.perf_counter()
        for _, d_i, a_i in candidates[:SEARCH["max_checks"]]:
            if check is not None:
                check()
            d = dirs[d_i]
            # the final path: no joint moves more than about 0.4° between rows (at the bracket's end)
            bracket_end = _family(base_coarse, d * amps[a_i + 1], s_coarse, harm)
            step = float(np.max(np.abs(np.diff(bracket_end, axis=0)))) * (len(s_coarse) - 1)
            s_fine = np.linspace(0.0, 1.0, int(max(241, math.ceil(step / math.radians(0.4)) + 1)))
            base_fine = base(s_fine)

            def miss(alpha, d=d, s_fine=s_fine, base_fine=base_fine):
                p = _family(base_fine, alpha * d, s_fine, harm)
                return _attitude_changes(_full(start_full, p)[None], pair, inertia)[0] - need

            try:
                from scipy.optimize import brentq    # SciPy loaded only where it is used (start-up)
                alpha = brentq(miss, amps[a_i], amps[a_i + 1], xtol=1e-10, rtol=1e-12)
            except ValueError:             # the final path's sign differs from the coarse one's
                continue
            p = _family(base_fine, alpha * d, s_fine, harm)
            if not np.all((p >= lo) & (p <= hi)):
                continue
            n_checked += 1
            full = _full(start_full, p)
            # a quick look at the rows first (the kernel's drift, the body where the CoM puts it)
            moved = full.copy()
            moved[:, 0] += _profiles(full[None], pair, inertia)[0]
            com = system_com_m(robot, masses, moved)
            clr = checker.clearance_shifted_m(moved, com[0] - com)
            best_clear = max(best_clear, float(clr.min()))
            if not np.all(clr > scene.safety_margin_m):
                continue
            drift = check_drifted(robot, masses, scene, full[:, dof_cols])
            if drift.ok:
                found = (p, post, kind, drift)
                break
        verify_s += time.perf_counter() - t_v
        if found is not None:
            break
    search_s = time.perf_counter() - t0 - verify_s     # with the postures and the guides
    needed = tuple(sorted({(p.branch, round(math.degrees(p.attitude_change_rad), 9)) for p in postures}))
    achievable = tuple((b, math.degrees(r[0]), math.degrees(r[1]))
                       for b, r in sorted(reach.items(), key=lambda kv: str(kv[0])))
    if found is not None:
        p, post, kind, drift = found
        planned = _full(start_full, p)[:, dof_cols]
        resp = free_floating_response(robot, masses, planned, scene.target.grasp_point_m)
        if 0 in robot.planned_joints:                  # the attitude column: as it drifts
            planned[:, dof_cols.index(0)] = resp.q_full_rad[:, 0]
        approach = math.degrees(approach_error_rad(robot, scene.target, resp.q_full_rad[-1]))
        return FreeFloatingCapture(True, None, planned, planned[-1].copy(), post, needed, achievable, resp, drift,
                                   resp.tip_miss_m, approach, n_candidates, n_checked, search_s, verify_s, kind)
    names = {0: "elbow one way", 1: "elbow the other way", None: "the goal"}
    parts = []
    for b in sorted({p.branch for p in postures}, key=str):
        nd = [v for bb, v in needed if bb == b]
        ach = [(lo_, hi_) for bb, lo_, hi_ in achievable if bb == b]
        lo_n, hi_n = circular_band_deg(nd)
        turn = -math.copysign(360.0, lo_n + hi_n)         # the same changes the other way round

        def band(a, b):
            return f"{a:+.1f}°" if round(a, 1) == round(b, 1) else f"{a:+.1f}° to {b:+.1f}°"
        ach_text = (f"{ach[0][0]:+.1f}° to {ach[0][1]:+.1f}°" if ach else "none within the joint bounds")
        parts.append(f"{names[b]}: needs {band(lo_n, hi_n)} (or {band(lo_n + turn, hi_n + turn)} the other way "
                     f"round), the arm's motions achieve {ach_text}")
    what = "; ".join(parts)
    if not postures:
        reason = (f"free floating: the grasp pose at {np.round(scene.target.grasp_point_m, 3).tolist()} m is "
                  "out of the arm's reach (no capture posture)")
    elif not n_candidates:
        reason = (f"free floating: no arm motion tried turns the spacecraft by the attitude change the capture "
                  f"needs ({what}; tried: single motions, quintic or the field's path plus {harm} sine terms per "
                  f"joint, within the joint bounds; motions that loop to turn the spacecraft further are not)")
    else:
        skipped = n_candidates - n_checked
        motions = "1 arm motion turns" if n_candidates == 1 else f"{n_candidates} arm motions turn"
        none = ("the one checked in the inertial frame does not stay clear of the safety margin and grasp"
                if n_checked == 1 else f"none of the {n_checked} checked in the inertial frame stays clear of the "
                "safety margin and grasps")
        reason = (f"free floating: {motions} the spacecraft by the needed attitude change ({what}), but {none} "
                  f"(best clearance {best_clear:.3f} m, margin {scene.safety_margin_m} m)"
                  + (f"; {skipped} not checked (beyond the {SEARCH['max_checks']} shortest of a family, or off "
                     f"the joint bounds or the attitude change once refined to the final path)" if skipped else ""))
    return FreeFloatingCapture(False, reason, np.zeros((0, robot.dof)), None, None, needed, achievable, None, None,
                               math.nan, math.nan, n_candidates, n_checked, search_s, verify_s)
