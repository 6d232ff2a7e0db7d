"""
Leaving a contact: from a start that touches an obstacle to the nearest free posture.

After a capture the arm holds the handle; when the target then moves a little, the
current posture overlaps it and no certified motion starts there.  This stage walks out
along increasing *signed distance* (the clearance outside the obstacles, minus the
penetration depth inside them) in small joint steps until the posture is free with a
little room to spare; the planner certifies everything after that.  The walk itself is
not certified (it starts in collision): it is bounded (``max_length_rad``), reported
apart, and only allowed when the start is inside by at most ``max_penetration_m``.

Configurations are planned-joint vectors (rad); lengths in metres.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass

import numpy as np

from .joint_space import deg_text

__all__ = ["penetration_depth_m", "signed_distance_m", "Exit", "leave_contact"]

_SAMPLE_M = 0.002      # spacing of the link samples of the penetration depth (error ≤ 1 mm)


def _inside(points, poly) -> np.ndarray:
    """Even–odd test of (N, 2) points against a (k, 2) polygon: (N,) bool."""
    x, y = points[:, 0:1], points[:, 1:2]
    xi, yi = poly[:, 0], poly[:, 1]
    xj, yj = np.roll(xi, 1), np.roll(yi, 1)
    crosses = (yi > y) != (yj > y)
    with np.errstate(divide="ignore", invalid="ignore"):
        x_cross = xi + (y - yi) * (xj - xi) / (yj - yi)
    return np.count_nonzero(crosses & (x < x_cross), axis=1) % 2 == 1


def _boundary_distance(points, poly) -> np.ndarray:
    """Distance of (N, 2) points to the edges of a (k, 2) polygon: (N,)."""
    a = poly[None, :, :]
    b = np.roll(poly, -1, axis=0)[None, :, :]
    p = points[:, None, :]
    ab = b - a
    t = np.clip(np.sum((p - a) * ab, axis=2) / np.maximum(np.sum(ab * ab, axis=2), 1e-300), 0.0, 1.0)
    return np.min(np.linalg.norm(a + t[..., None] * ab - p, axis=2), axis=1)


def penetration_depth_m(checker, q) -> float:
    """
    Return how deep the checked links of ``q`` reach into the body or an obstacle, metres.

    How deep the checked links of planned configuration ``q`` (dof,) reach into the spacecraft body
    or an obstacle: the largest distance from a link point inside a polygon to that polygon's
    boundary, metres (0 when no link point is inside).

    Links are sampled every 2 mm, so the depth is exact to within 1 mm.
    """
    robot = checker.robot
    q_full = robot.full(np.asarray(q, dtype=float))
    pts = robot.forward_kinematics(q_full)
    polys = [robot.body_polygon_world(q_full[0])]
    polys += [np.asarray(p, dtype=float) for p in checker.scene.obstacle_polygons_m]
    depth = 0.0
    for k in robot.checked_links:
        a, b = pts[k], pts[k + 1]
        n = max(2, int(math.ceil(np.linalg.norm(b - a) / _SAMPLE_M)) + 1)
        samples = a + np.linspace(0.0, 1.0, n)[:, None] * (b - a)
        for poly in polys:
            lo, hi = poly.min(axis=0), poly.max(axis=0)
            near = np.all((samples >= lo) & (samples <= hi), axis=1)
            if not near.any():
                continue
            cand = samples[near]
            inside = _inside(cand, poly)
            if inside.any():
                depth = max(depth, float(_boundary_distance(cand[inside], poly).max()))
    return depth


def signed_distance_m(checker, q) -> float:
    """Clearance of ``q`` when the links touch nothing, else minus the penetration depth, m."""
    c = float(checker.clearance_m(q))
    return c if c > 0.0 else -penetration_depth_m(checker, q)


@dataclass(frozen=True, eq=False)
class Exit:
    """
    The way out of a contact.

    Attributes
    ----------
        ok: a free posture was reached within the bounds.
        path_rad: (K, dof) from the start (first row, exact) to the free posture (last
            row), consecutive rows ``step_rad`` apart, signed distance increasing.
        start_penetration_m: the start's penetration depth, metres.
        signed_distance_m: (K,) signed distance along ``path_rad``.
        reason: why not (None when ok).

    """

    ok: bool
    path_rad: np.ndarray
    start_penetration_m: float
    signed_distance_m: np.ndarray
    reason: str | None = None


def leave_contact(motions, start_rad, *, max_penetration_m: float,
                  room_m: float = 0.01, step_rad: float = math.radians(0.25),
                  max_length_rad: float = math.radians(30.0)) -> Exit:
    """
    Walk from a colliding ``start_rad`` to a posture with clearance ≥ margin + ``room_m``.

    ``motions``: the scene's ``motion.MotionValidator`` (its checker and joint bounds).

    Each step moves ``step_rad`` (joint-space norm) towards the neighbour, among the
    3^dof − 1 directions of the joint-space grid, with the largest signed distance, and
    must increase it; joint bounds are kept.  Refused (``ok`` False) when the start is
    deeper than ``max_penetration_m``, when no direction increases the signed distance,
    or after ``max_length_rad``.
    """
    checker = motions.checker
    q = np.asarray(start_rad, dtype=float)
    dof = len(q)
    margin = checker.margin_m
    sd0 = signed_distance_m(checker, q)
    depth = max(0.0, -sd0)
    dirs = np.array([d for d in itertools.product((-1.0, 0.0, 1.0), repeat=dof) if any(d)])
    dirs = step_rad * dirs / np.linalg.norm(dirs, axis=1, keepdims=True)
    path, sds = [q.copy()], [sd0]
    if depth > max_penetration_m:
        return Exit(False, np.array(path), depth, np.array(sds),
                    f"the links reach {depth:.3f} m into an obstacle, more than "
                    f"planner.max_start_penetration_m = {max_penetration_m} m")
    n_steps = int(math.ceil(max_length_rad / step_rad))
    for _ in range(n_steps):
        if sds[-1] >= margin + room_m:
            return Exit(True, np.array(path), depth, np.array(sds))
        cand = path[-1] + dirs
        cand = cand[motions.within_bounds(cand)]
        if not len(cand):
            break
        clr = np.asarray(checker.clearance_m(cand), dtype=float)
        sd = np.where(clr > 0.0, clr, 0.0)
        touching = np.flatnonzero(clr <= 0.0)
        for i in touching:
            sd[i] = -penetration_depth_m(checker, cand[i])
        best = int(np.argmax(sd))
        if not sd[best] > sds[-1]:
            return Exit(False, np.array(path), depth, np.array(sds),
                        f"no joint motion increases the clearance from {deg_text(path[-1])}")
        path.append(cand[best])
        sds.append(float(sd[best]))
    if sds[-1] >= margin + room_m:
        return Exit(True, np.array(path), depth, np.array(sds))
    return Exit(False, np.array(path), depth, np.array(sds),
                f"no free posture within {math.degrees(max_length_rad):.0f}° of joint motion "
                f"(clearance {max(sds[-1], 0.0):.3f} m after it)")
