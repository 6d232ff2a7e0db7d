"""
Goal configurations from the target: inverse kinematics of the grasp pose.

For the 3-joint chain (attitude, shoulder, elbow) the grasp pose fixes the tip
position and the absolute angle of the last link, so the elbow point is known and
the first two joints solve a two-link problem: two branches.  With locked joints
(the 2-DOF case) only the tip position can be met: position-only IK of the two
joints nearest the tip, again two branches.  Longer chains (redundant: more planned
joints than the grasp's three constraints) take the most manipulable collision-free
posture of their self-motion (``redundant.py``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from .collision import CollisionChecker
from .joint_space import TWO_PI, wrap_angle_rad, wrap_rad
from .redundant import most_manipulable_arm, redundant_grasp

__all__ = ["IKSolution", "grasp_ik", "meets_approach_angle", "capture_posture", "CapturePosture", "approach_error_rad",
           "perpendicular_attitudes"]


@dataclass(frozen=True)
class IKSolution:
    """
    One inverse-kinematics branch.

    Attributes
    ----------
        q: planned joints (rad), wrapped into the joint ranges.
        q_full: all joints (rad).
        manipulability: sqrt(det(J Jᵀ)), m².
        clearance_m: exact clearance of the posture.
        free: clearance > safety margin.
        method: how the posture was chosen, for people.

    """

    q: np.ndarray
    q_full: np.ndarray
    manipulability: float
    clearance_m: float
    free: bool
    method: str = "closed form, 2 branches"


def _two_link(base, target, l_a, l_b):
    """Both solutions (absolute angle of link a, relative angle of link b) of a 2-link reach (floats, rad)."""
    dx = float(target[0]) - float(base[0])
    dy = float(target[1]) - float(base[1])
    r2 = dx * dx + dy * dy
    cos_b = (r2 - l_a * l_a - l_b * l_b) / (2.0 * l_a * l_b)
    if cos_b > 1.0 + 1e-12 or cos_b < -1.0 - 1e-12:
        return []
    cos_b = min(1.0, max(-1.0, cos_b))
    sols = []
    for sign in (1.0, -1.0):
        rel_b = sign * math.acos(cos_b)
        abs_a = math.atan2(dy, dx) - math.atan2(l_b * math.sin(rel_b), l_a + l_b * math.cos(rel_b))
        sols.append((abs_a, rel_b))
        if cos_b in (1.0, -1.0):
            break
    return sols


def _fit_to_bounds(robot, q_full):
    """Shift each joint by whole turns into [lower, upper]; None when one cannot fit."""
    out = wrap_rad(q_full, robot.periodic, robot.lower_rad)
    for j in range(robot.n_joints):
        lo, hi = robot.lower_rad[j], robot.upper_rad[j]
        if robot.periodic[j]:
            continue
        fits = [v for v in out[j] + TWO_PI * np.arange(-2, 3) if lo - 1e-9 <= v <= hi + 1e-9]
        if not fits:
            return None
        out[j] = min(fits, key=abs)
    return out


def meets_approach_angle(robot) -> bool:
    """
    Tell whether :func:`grasp_ik` meets a given approach angle.

    Every chain but the 3-joint one with its attitude locked, whose IK is position-only: the
    posture then gives its own angle.
    """
    return robot.n_joints != 3 or 0 in robot.planned_joints


def grasp_ik(robot, scene, grasp_point_m=None, approach_angle_rad=None, free_only: bool = True):
    """
    All IK branches reaching the grasp pose, best manipulability first.

    Args:
        grasp_point_m: (2,) tip position; defaults to the scene target's grasp point.
        approach_angle_rad: absolute angle of the last link; defaults to the target's
            perpendicular approach.  Ignored (position-only IK) when the attitude is
            locked.
        free_only: drop branches whose posture collides (clearance ≤ margin).

    Other chains than the 3-joint one: per branch of the self-motion, the most manipulable
    collision-free posture within the bounds (``redundant.redundant_grasp``; its ``method``
    says how it was found); ``approach_angle_rad`` is always met.

    Returns
    -------
        list of IKSolution (possibly empty: the grasp pose is out of reach).

    """
    if grasp_point_m is None or approach_angle_rad is None:
        if scene.target is None:
            raise ValueError("grasp_ik: the scene has no target and no grasp pose was given")
        grasp_point_m = scene.target.grasp_point_m if grasp_point_m is None else grasp_point_m
        if approach_angle_rad is None:
            approach_angle_rad = scene.target.approach_angle_rad
    p = np.asarray(grasp_point_m, dtype=float)
    if p.shape != (2,) or not np.all(np.isfinite(p)):
        raise ValueError(f"grasp point: expected two finite numbers, got {grasp_point_m!r}")
    if robot.n_joints != 3:
        return [IKSolution(q=sol.q_full[list(robot.planned_joints)], q_full=sol.q_full,
                           manipulability=sol.manipulability, clearance_m=sol.clearance_m, free=sol.free,
                           method=sol.method)
                for sol in redundant_grasp(robot, scene, p, float(approach_angle_rad), free_only=free_only)]
    l1, l2, l3 = (float(v) for v in robot.link_lengths_m)
    candidates = []
    if meets_approach_angle(robot):
        # full pose: the elbow point follows from the approach angle
        psi = float(approach_angle_rad)
        elbow = p - l3 * np.array([np.cos(psi), np.sin(psi)])
        for th1, th2 in _two_link((0.0, 0.0), elbow, l1, l2):
            candidates.append(np.array([th1, th2, psi - th1 - th2]))
    else:
        th1 = float(robot.locked_rad[0])
        shoulder = l1 * np.array([np.cos(th1), np.sin(th1)])
        for abs2, th3 in _two_link(shoulder, p, l2, l3):
            candidates.append(np.array([th1, abs2 - th1, th3]))
    checker = CollisionChecker(robot, scene)
    sols = []
    for q_full in candidates:
        q_full = _fit_to_bounds(robot, wrap_angle_rad(q_full))
        if q_full is None:
            continue
        q = q_full[list(robot.planned_joints)]
        clr = float(checker.clearance_m(q))
        sol = IKSolution(q=q, q_full=q_full, manipulability=float(robot.manipulability(q_full)),
                         clearance_m=clr, free=clr > scene.safety_margin_m)
        if sol.free or not free_only:
            sols.append(sol)
    sols.sort(key=lambda s: -s.manipulability)
    return sols


def approach_error_rad(robot, target, q_full) -> float:
    """
    Return the approach error at full configuration ``q_full``, rad in [0, π].

    Angle between the last link and the handle's inward normal (the perpendicular approach
    ``target.approach_angle_rad``) at full configuration ``q_full``, in [0, π].
    """
    last = float(np.sum(np.asarray(q_full, dtype=float)))
    return abs(float(wrap_angle_rad(last - target.approach_angle_rad)))


def perpendicular_attitudes(robot, scene) -> list:
    """
    Attitudes (joint 1, rad) at which the arm grasps the scene's target perpendicularly.

    The full-pose IK of the 3-joint chain with the attitude free.

    Returns [(attitude_rad, free)] per branch, collision-free branches first; empty when
    the grasp pose is out of reach.
    """
    free_robot = replace(robot, planned_joints=tuple(range(robot.n_joints)))
    sols = grasp_ik(free_robot, scene, free_only=False)
    return sorted(((float(s.q_full[0]), bool(s.free)) for s in sols), key=lambda a: not a[1])


@dataclass(frozen=True)
class CapturePosture:
    """
    The paper's advice: the most manipulable capture posture and where the target must sit.

    Attributes
    ----------
        q_full: (θ1, θ2, θ3) rad, with θ1 chosen so the last link meets the approach angle.
        manipulability: m².
        tip_m: end-effector tip position, metres.
        target_center_m: where the target's body centre must be for its grasp point to
            coincide with the tip (for the given target yaw and size).
        method: how the posture was found, for people.

    """

    q_full: np.ndarray
    manipulability: float
    tip_m: np.ndarray
    target_center_m: np.ndarray
    method: str = "scanned (θ2, θ3 > 0) every 3°, refined by Nelder-Mead"


def capture_posture(robot, target) -> CapturePosture:
    """
    Maximise manipulability over (θ2, θ3 > 0), then orient the chain for the target's approach.

    The mirror posture (−θ2, −θ3) is as manipulable; the paper's branch is returned.  Longer
    chains: every arm joint within its bounds (``redundant.most_manipulable_arm``).
    """
    offset = target.grasp_point_m - np.asarray(target.center_m)
    if robot.n_joints != 3:
        q_full, w, method = most_manipulable_arm(robot, target.approach_angle_rad)
        tip = robot.tip_position(q_full)
        return CapturePosture(q_full=q_full, manipulability=w, tip_m=tip, target_center_m=tip - offset,
                              method=method)

    def neg_w(x):
        return -float(robot.manipulability(np.array([0.0, x[0], x[1]])))

    # w(θ2, θ3) = w(−θ2, −θ3): scan the paper's branch (elbow angle θ3 > 0) coarsely,
    # then polish locally
    g2 = np.radians(np.arange(-179.0, 180.0, 3.0))
    g3 = np.radians(np.arange(1.0, 180.0, 3.0))
    t2, t3 = np.meshgrid(g2, g3, indexing="ij")
    w = robot.manipulability(np.stack([np.zeros_like(t2), t2, t3], axis=-1))
    i, j = np.unravel_index(np.argmax(w), w.shape)
    from scipy.optimize import minimize     # SciPy loaded only here: off the plan's route
    res = minimize(neg_w, x0=[t2[i, j], t3[i, j]], method="Nelder-Mead",
                   options={"xatol": 1e-9, "fatol": 1e-12, "maxiter": 2000})
    th2, th3 = res.x
    th1 = float(wrap_angle_rad(target.approach_angle_rad - th2 - th3))
    q_full = np.array([th1, float(wrap_angle_rad(th2)), float(wrap_angle_rad(th3))])
    tip = robot.tip_position(q_full)
    return CapturePosture(q_full=q_full, manipulability=-float(res.fun), tip_m=tip,
                          target_center_m=tip - offset)
