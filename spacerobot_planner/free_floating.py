"""
Free-floating planning: plan the arm so that, drifting, it still grasps the handle.

With attitude control off during the motion the spacecraft turns and translates under the
arm (``spacecraft.free_floating_response``): the attitude change depends on the arm's whole
path (the constraint is nonholonomic), the body's position only on the configuration (the
system's centre of mass stays put).

- :func:`plan_capture` (the planner's free-floating capture, ``acs.mode: free_floating``
  with a target): Papadopoulos' polynomial joint paths.  The capture postures are solved
  in the inertial frame (tip at the grasp point, link 3 along the handle's normal, the body
  where the centre of mass puts it: :func:`capture_postures`); each fixes the attitude change
  the arm's motion must make.  The arm follows a quintic from its start to the posture's arm
  joints plus free sine terms (two harmonics per joint) whose amplitude along a direction
  of the coefficient space is solved (Brent) so that the momentum balance turns the body
  by exactly that change; among the solutions within the joint bounds the shortest whose
  drifted motion is certified collision-free in the inertial frame
  (``reaction.check_drifted``) is the plan.  A change outside what the family's motions
  achieve is refused with both numbers.
- :func:`plan_free_floating` (``acs.compensate_drift``, the earlier strategy): predict the
  drift of a plan and plan again for the scene as the body will see it at the end, until the
  drifted tip reaches the grasp point.  It places the tip only: the approach angle follows
  from the drift (not a grasp in general).

No ROS imports.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import time
from dataclasses import replace

import numpy as np
from numba import njit
from scipy.optimize import brentq

from .collision import CollisionChecker
from .ik import approach_error_rad, grasp_ik
from .joint_space import wrap_angle_rad
from .reaction import DriftCheck, check_drifted
from .scene import Scene, Target
from .spacecraft import FreeFloatingResponse, MassProperties, free_floating_response, system_com_m

__all__ = ["CompensatedPlan", "plan_free_floating", "apparent_scene", "FreeFloatingCapture", "CapturePostureFF",
           "capture_postures", "attitude_changes_rad", "plan_capture", "SEARCH"]


@dataclass(frozen=True, eq=False)
class CompensatedPlan:
    """
    A plan whose free-floating execution reaches the grasp (see :func:`plan_free_floating`).

    Attributes
    ----------
        ok: the drifted tip ends within the tolerance of the grasp point and the drifted
            motion is certified collision-free in the inertial frame.
        reason: why not (None when ok).
        plan: the last ``PlanResult`` (planned in the apparent scene of that iteration).
        goal_rad: (dof,) its goal posture.
        response: FreeFloatingResponse of that plan in the real (inertial) scene.
        drift: DriftCheck of that plan in the real scene.
        history: per iteration (tip miss m, attitude change deg, drift certified).

    """

    ok: bool
    reason: str | None
    plan: object
    goal_rad: np.ndarray | None
    response: FreeFloatingResponse | None
    drift: DriftCheck | None
    history: tuple


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


def plan_free_floating(scenario, start_rad, goal_rad=None, *, masses: MassProperties | None = None,
                       position_tolerance_m: float | None = None, max_iterations: int = 12) -> CompensatedPlan:
    """
    Plan the arm so that, free floating, it still reaches the handle (the target's grasp).

    Plan once in the real scene; then, repeatedly, predict the drift of that plan
    (attitude change Δθ1 and body displacement b at its end), move the scene to where
    the body will see it at the end (turned by −Δθ1 about the body centre after the body
    moved by b: the *apparent* scene), take the grasp IK branch nearest the previous
    goal there and plan again (the planner certifies the path against the apparent
    scene).  Each plan is judged in the real inertial scene: its drifted tip against the
    grasp point and its drifted motion by :func:`check_drifted`.  It stops when the miss
    is below a tenth of the tolerance (or 1 mm) and the drifted motion is certified.

    Args:
        scenario: a ``config.Scenario`` with a target; the attitude (joint 1) must not be
            planned (free floating, nothing commands it).
        start_rad: (dof,) start posture.
        goal_rad: first goal (default: the target's IK).
        masses: default ``scenario.masses``; position_tolerance_m: default
            ``scenario.acs.position_tolerance_m``.

    Returns
    -------
        CompensatedPlan (``ok`` False with a reason when it did not converge).

    Raises
    ------
        ValueError: no target, or the attitude is a planned joint.

    """
    robot, scene = scenario.robot, scenario.scene
    if scene.target is None:
        raise ValueError("plan_free_floating: the scene has no target (nothing to reach)")
    if 0 in robot.planned_joints:
        raise ValueError("robot.planned_joints: free floating, the attitude is not commanded; plan the arm "
                         "joints only (lock the attitude at its start value)")
    masses = scenario.masses if masses is None else masses
    tol = scenario.acs.position_tolerance_m if position_tolerance_m is None else float(position_tolerance_m)
    grasp = scene.target.grasp_point_m
    from .planner import Planner           # the planner imports this module (free-floating capture)
    # geometry only: the core refuses free-floating trajectories on their reaction
    # (reaction_refused); the caller adds the trajectory to the compensated plan
    res = Planner(scenario, trajectory=False).plan(start_rad, goal_rad)
    history = []
    resp = drift = None
    for _ in range(max_iterations + 1):
        if not res.ok:
            return CompensatedPlan(False, f"planning failed ({res.code}): {res.reason}", res, res.goal_rad,
                                   resp, drift, tuple(history))
        goal = res.goal_rad
        resp = free_floating_response(robot, masses, res.path_rad, grasp)
        drift = check_drifted(robot, masses, scene, res.path_rad)
        history.append((resp.tip_miss_m, resp.attitude_change_deg, drift.ok))
        if drift.ok and resp.tip_miss_m <= min(0.1 * tol, 1e-3) or len(history) > max_iterations:
            break
        apparent = apparent_scene(scene, math.radians(resp.attitude_change_deg), resp.body_position_m[-1])
        sols = grasp_ik(robot, apparent)
        if not sols:
            return CompensatedPlan(False, "no collision-free grasp posture for the drifted target", res, goal,
                                   resp, drift, tuple(history))
        goal = min(sols, key=lambda sol: float(np.linalg.norm(sol.q - goal))).q
        res = Planner(scenario.with_scene(apparent), trajectory=False).plan(start_rad, goal)
    ok = drift.ok and resp.tip_miss_m <= tol
    reason = None if ok else (
        f"free floating, compensated: after {len(history)} plans the drifted tip misses the grasp by "
        f"{resp.tip_miss_m:.3f} m (tolerance {tol} m){'' if drift.ok else ' and the drifted arm collides'}")
    return CompensatedPlan(ok, reason, res, goal, resp, drift, tuple(history))


# ================================================================ free-floating capture
#: the path family and its search (see :func:`plan_capture`): samples of the coarse scan, the
#: sine harmonics per arm joint, the scanned amplitudes (rad), the scanned directions of the
#: coefficient space (seeded, so the plan is deterministic), the candidates certified at most
SEARCH = {"coarse_samples": 61, "harmonics": 2, "max_amplitude_rad": math.radians(180.0), "amplitudes": 31,
          "directions": 96, "seed": 0, "max_checks": 400}


@njit(cache=True, nogil=True)
def _attitude_profiles(paths, pair, inertia):
    """
    Attitude change (rad) at every row of each full-joint path of ``paths`` (B, K, n): (B, K).

    The paths are straight between rows.  The momentum row at q: g_k = Σ_j pair[j, k]
    cos(φ_k − φ_j) + inertia[k] is the angular momentum per unit rate of the absolute angle
    φ_k (about the system's centre of mass), and H_i = Σ_{k≥i} g_k; free floating
    dθ1 = −Σ_{i>0} H_i dθ_i / H_0, Simpson's rule per row step.
    """
    nb, nk, n = paths.shape
    out = np.zeros((nb, nk))
    phi = np.empty(n)
    g = np.empty(n)
    for b in range(nb):
        total = 0.0
        for k in range(nk - 1):
            step = 0.0
            for w_i in range(3):
                w = 0.5 * w_i
                acc = 0.0
                for j in range(n):
                    acc += paths[b, k, j] + w * (paths[b, k + 1, j] - paths[b, k, j])
                    phi[j] = acc
                for kk in range(n):
                    v = inertia[kk]
                    for j in range(n):
                        v += pair[j, kk] * math.cos(phi[kk] - phi[j])
                    g[kk] = v
                hsum = 0.0
                num = 0.0
                for i in range(n - 1, -1, -1):
                    hsum += g[i]
                    if i > 0:
                        num += hsum * (paths[b, k + 1, i] - paths[b, k, i])
                step += (4.0 if w_i == 1 else 1.0) * (-num / hsum)
            total += step / 6.0
            out[b, k + 1] = total
    return out


def _attitude_changes(paths, pair, inertia):
    """The attitude change over each path of ``paths`` (B, K, n): (B,) rad (see :func:`_attitude_profiles`)."""
    return _attitude_profiles(paths, pair, inertia)[:, -1]


def _pair_tables(robot, masses):
    """(pair (n, n), inertia per absolute angle (n,)) of the momentum row (see :func:`_attitude_changes`)."""
    masses.check_robot(robot)
    n = robot.n_joints
    lengths = np.asarray(robot.link_lengths_m, dtype=float)
    coef = (np.tril(np.ones((n, n)), -1) + 0.5 * np.eye(n)) * lengths[None, :]   # link centres
    a = np.vstack([np.zeros((1, n)), coef])                                       # body first
    m = np.concatenate([[masses.body_mass_kg], masses.link_masses_kg])
    ma = m @ a
    pair = a.T @ (m[:, None] * a) - np.outer(ma, ma) / m.sum()
    inertia = np.array(masses.link_inertias_kgm2, dtype=float)
    inertia[0] += masses.body_inertia_kgm2                                        # the body turns with θ1
    return np.ascontiguousarray(pair), inertia


def attitude_changes_rad(robot, masses: MassProperties, paths_full_rad) -> np.ndarray:
    """
    Free-floating attitude change of full-joint paths, rad: (K, n) → float, (B, K, n) → (B,).

    The arm joints (columns 1…) straight between rows; column 0 is ignored (it drifts).  The
    same quadrature as ``spacecraft.free_floating_response`` in a numba kernel.
    """
    p = np.asarray(paths_full_rad, dtype=float)
    pair, inertia = _pair_tables(robot, masses)
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

    """

    q_full: np.ndarray
    body_m: np.ndarray
    attitude_change_rad: float


def capture_postures(robot, masses: MassProperties, scene, start_full_rad) -> list:
    """
    Return the inertial capture postures of the scene's target from ``start_full_rad`` (n,).

    The grasp pose (``ik.grasp_ik`` with the attitude free: both branches) for the grasp point
    moved by the body's displacement b, and b = r̄(start) − r̄(q) from that posture, iterated
    to a fixed point (b is a few centimetres: it converges in a handful of steps).  Postures
    outside the joint bounds are dropped; collisions are not judged here (the inertial
    check of the whole motion does that).  3-joint chains (``grasp_ik``'s).
    """
    free_robot = replace(robot, planned_joints=tuple(range(robot.n_joints)))
    q0 = np.asarray(start_full_rad, dtype=float)
    com0 = system_com_m(robot, masses, q0)
    grasp = np.asarray(scene.target.grasp_point_m, dtype=float)
    out = []
    for branch in (0, 1):
        body = np.zeros(2)
        q = None
        for _ in range(50):
            sols = sorted(grasp_ik(free_robot, scene, grasp_point_m=grasp - body, free_only=False),
                          key=lambda s: s.q_full[-1])
            if len(sols) <= branch:
                q = None
                break
            q = sols[branch].q_full
            moved = com0 - system_com_m(robot, masses, q)
            done = float(np.linalg.norm(moved - body)) < 1e-12
            body = moved
            if done:
                break
        if q is not None:
            out.append(CapturePostureFF(q, body, float(wrap_angle_rad(q[0] - q0[0]))))
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
        needed_deg: per capture posture (or the goal), the attitude change it needs, degrees.
        achievable_deg: per capture posture, (lowest, highest) attitude change of the
            family's motions to its arm joints within the joint bounds, degrees.
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
    """The rest-to-rest quintic a0 → af: a function of s ∈ [0, 1] (K,) → (K, m)."""
    def at(s):
        sig = s ** 3 * (10.0 - 15.0 * s + 6.0 * s * s)
        return a0 + (af - a0) * sig[:, None]
    return at


def _along(path):
    """A path's rows as a function of its normalised joint-space arc length s ∈ [0, 1] (K,) → (K, m)."""
    p = np.asarray(path, dtype=float)
    u = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(p, axis=0), axis=1))])
    u = u / u[-1] if u[-1] > 0.0 else np.linspace(0.0, 1.0, len(p))

    def at(s):
        return np.stack([np.interp(s, u, p[:, j]) for j in range(p.shape[1])], axis=-1)
    return at


def _family(base_at_s, coef, s, harmonics):
    """Arm paths (..., K, m): the base's rows at s plus Σ_h coef[..., j, h] sin((h+1)π s) on joint j."""
    return base_at_s + np.einsum("...jh,hk->...kj", coef, _basis(s, harmonics))


def _directions(m, harmonics, count, seed):
    """Unit directions of the (m × harmonics) coefficient space: the axes (both signs), then seeded ones."""
    dim = m * harmonics
    eye = np.eye(dim)
    rnd = np.random.default_rng(seed).normal(size=(max(0, count - 2 * dim), dim))
    d = np.vstack([eye, -eye, rnd / np.linalg.norm(rnd, axis=1, keepdims=True)])
    return d.reshape(-1, m, harmonics)


def _full(q0, arm_paths):
    """Full-joint paths: column 0 at the start's attitude (it drifts), the arm columns."""
    att = np.full(arm_paths.shape[:-1] + (1,), q0[0])
    return np.concatenate([att, arm_paths], axis=-1)


def plan_capture(scenario, start_rad, goal_rad=None, *, masses: MassProperties | None = None,
                 base_path=None, check=None) -> FreeFloatingCapture:
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

    Raises
    ------
        ValueError: no target, a locked arm joint, or a chain other than 3 joints.

    """
    robot, scene = scenario.robot, scenario.scene
    masses = scenario.masses if masses is None else masses
    if scene.target is None:
        raise ValueError("free-floating capture: the scene has no target")
    if robot.n_joints != 3:
        raise ValueError("free-floating capture: implemented for the 3-joint chain (attitude, shoulder, elbow)")
    arm = list(range(1, robot.n_joints))
    if any(j not in robot.planned_joints for j in arm):
        raise ValueError("robot.planned_joints: free-floating capture plans every arm joint (only the attitude "
                         "may be locked)")
    t0 = time.perf_counter()
    start_full = robot.full(np.asarray(start_rad, dtype=float))
    if goal_rad is None:
        postures = capture_postures(robot, masses, scene, start_full)
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
    pair, inertia = _pair_tables(robot, masses)
    candidates, needed, achievable = [], [], []
    for i_post, post in enumerate(postures):
        af = post.q_full[arm]
        af = np.where(np.asarray(robot.periodic)[arm], a0 + wrap_angle_rad(af - a0), af)
        need = post.attitude_change_rad
        needed.append(math.degrees(need))
        lo_hi = [math.inf, -math.inf]
        bases = [("quintic", _quintic(a0, af))]
        if base_path is not None:
            guide = base_path(post)
            if guide is not None:
                bases.insert(0, ("field", _along(guide)))
        for kind, base in bases:
            coef = dirs[:, None] * amps[None, :, None, None]                   # (D, A, m, H)
            paths = _family(base(s_coarse), coef, s_coarse, harm)             # (D, A, K, m)
            inside = np.all((paths >= lo) & (paths <= hi), axis=(-1, -2))      # (D, A)
            flat = paths.reshape(-1, len(s_coarse), len(arm))
            delta = _attitude_changes(np.ascontiguousarray(_full(start_full, flat)), pair, inertia)
            delta = delta.reshape(inside.shape)
            if not inside.any():
                continue
            lo_hi = [min(lo_hi[0], float(delta[inside].min())), max(lo_hi[1], float(delta[inside].max()))]
            # the final paths: no joint moves more than about 0.4° between rows
            step = float(np.max(np.abs(np.diff(paths[inside], axis=-2)))) * (len(s_coarse) - 1)
            s_fine = np.linspace(0.0, 1.0, int(max(241, math.ceil(step / math.radians(0.4)) + 1)))
            base_fine = base(s_fine)
            for d_i, d in enumerate(dirs):
                f = delta[d_i] - need
                for a_i in range(len(amps) - 1):
                    if not (inside[d_i, a_i] and inside[d_i, a_i + 1]) or f[a_i] * f[a_i + 1] > 0.0:
                        continue

                    def miss(alpha, d=d):
                        p = _family(base_fine, alpha * d, s_fine, harm)
                        return _attitude_changes(_full(start_full, p)[None], pair, inertia)[0] - need

                    try:
                        alpha = brentq(miss, amps[a_i], amps[a_i + 1], xtol=1e-12, rtol=1e-12)
                    except ValueError:     # the fine path's sign differs from the coarse one's
                        continue
                    p = _family(base_fine, alpha * d, s_fine, harm)
                    if np.all((p >= lo) & (p <= hi)):
                        length = float(np.sum(np.linalg.norm(np.diff(p, axis=0), axis=1)))
                        candidates.append((length, p, post, kind))
                    break                  # the smallest amplitude along this direction
        achievable.append((math.degrees(lo_hi[0]), math.degrees(lo_hi[1])) if lo_hi[0] <= lo_hi[1]
                          else (math.nan, math.nan))
    search_s = time.perf_counter() - t0
    candidates.sort(key=lambda c: c[0])
    t1 = time.perf_counter()
    n_checked = 0
    best_clear = -math.inf
    dof_cols = list(robot.planned_joints)
    checker = CollisionChecker(robot, scene)
    for length, p, post, kind in candidates[:SEARCH["max_checks"]]:
        if check is not None:
            check()
        n_checked += 1
        full = _full(start_full, p)
        # a quick look at the rows first (the kernel's drift, the body where the CoM puts it)
        moved = full.copy()
        moved[:, 0] += _attitude_profiles(full[None], pair, inertia)[0]
        com = system_com_m(robot, masses, moved)
        clr = checker.clearance_shifted_m(moved, com[0] - com)
        best_clear = max(best_clear, float(clr.min()))
        if not np.all(clr > scene.safety_margin_m):
            continue
        planned = full[:, dof_cols]
        drift = check_drifted(robot, masses, scene, planned, motions=None)
        best_clear = max(best_clear, drift.min_clearance_m)
        if not drift.ok:
            continue
        resp = free_floating_response(robot, masses, planned, scene.target.grasp_point_m)
        if 0 in robot.planned_joints:                  # the attitude column: as it drifts
            planned = planned.copy()
            planned[:, dof_cols.index(0)] = resp.q_full_rad[:, 0]
        approach = math.degrees(approach_error_rad(robot, scene.target, resp.q_full_rad[-1]))
        verify_s = time.perf_counter() - t1
        return FreeFloatingCapture(True, None, planned, planned[-1].copy(), post, tuple(needed),
                                   tuple(achievable), resp, drift, resp.tip_miss_m, approach,
                                   len(candidates), n_checked, search_s, verify_s, kind)
    verify_s = time.perf_counter() - t1
    names = ("elbow one way", "elbow the other way") if goal_rad is None else ("the goal",)
    what = "; ".join(f"{n}: needs {nd:+.1f}° (or {nd - math.copysign(360.0, nd):+.1f}° the other way round), "
                     f"the arm's motions achieve {a[0]:+.1f}° to {a[1]:+.1f}°"
                     for n, nd, a in zip(names, needed, achievable))
    if not postures:
        reason = (f"free floating: the grasp pose at {np.round(scene.target.grasp_point_m, 3).tolist()} m is "
                  "out of the arm's reach (no capture posture)")
    elif not candidates:
        reason = (f"free floating: no arm motion turns the spacecraft by the attitude change the capture needs "
                  f"({what}; single motions of the family: quintic plus {harm} sine terms per joint, "
                  f"within the joint bounds)")
    else:
        reason = (f"free floating: {len(candidates)} arm motions turn the spacecraft by the needed attitude change "
                  f"({what}), but the {n_checked} certified come within the safety margin in the inertial "
                  f"frame (best clearance {best_clear:.3f} m, margin {scene.safety_margin_m} m)")
    return FreeFloatingCapture(False, reason, np.zeros((0, robot.dof)), None, None, tuple(needed),
                               tuple(achievable), None, None, math.nan, math.nan, len(candidates), n_checked,
                               search_s, verify_s)
