"""
Input validation without ROS: whether a target's body overlaps the spacecraft's body.

Two bodies cannot be in one place: such a target is a wrong input (a pose in another
frame, a sign error), not something to plan for.  The spacecraft body turns with the
attitude joint: when the planner moves the attitude, every attitude within its bounds
counts (the body sweeps them during a plan); when it is locked, its locked value.
Attitudes are sampled every ``STEP_DEG`` (a square body of 1.8 m errs by < 0.1 mm).
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["target_overlap_reason", "overlap_attitude", "polygons_overlap", "STEP_DEG"]

#: attitude sampling step, degrees
STEP_DEG = 0.5


def _segments_cross(a0, a1, b0, b1) -> bool:
    """Tell whether any segment a0[i]→a1[i] meets any b0[j]→b1[j] (touching included)."""
    def orient(p, q, r):
        return (q[..., 0] - p[..., 0]) * (r[..., 1] - p[..., 1]) - (q[..., 1] - p[..., 1]) * (r[..., 0] - p[..., 0])
    p, q = a0[:, None, :], a1[:, None, :]
    r, s = b0[None, :, :], b1[None, :, :]
    d1, d2 = orient(r, s, p), orient(r, s, q)
    d3, d4 = orient(p, q, r), orient(p, q, s)
    proper = (d1 * d2 <= 0.0) & (d3 * d4 <= 0.0)
    # collinear pairs pass the test above even when apart: check that their boxes meet
    lo_a, hi_a = np.minimum(p, q), np.maximum(p, q)
    lo_b, hi_b = np.minimum(r, s), np.maximum(r, s)
    boxes = np.all((lo_a <= hi_b) & (lo_b <= hi_a), axis=-1)
    return bool(np.any(proper & boxes))


def _inside(points, poly) -> np.ndarray:
    """Even-odd rule: which of the (m×2) points lie inside the polygon (k×2)."""
    x, y = points[:, 0][:, None], points[:, 1][:, None]
    x0, y0 = poly[:, 0][None, :], poly[:, 1][None, :]
    x1, y1 = np.roll(poly[:, 0], -1)[None, :], np.roll(poly[:, 1], -1)[None, :]
    straddles = (y0 > y) != (y1 > y)
    with np.errstate(divide="ignore", invalid="ignore"):
        x_cross = x0 + (y - y0) * (x1 - x0) / (y1 - y0)
    return np.count_nonzero(straddles & (x < x_cross), axis=1) % 2 == 1


def polygons_overlap(a, b) -> bool:
    """Tell whether two simple polygons (k×2) share any point (edges crossing or one inside the other)."""
    a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    if _segments_cross(a, np.roll(a, -1, axis=0), b, np.roll(b, -1, axis=0)):
        return True
    return bool(_inside(a[:1], b)[0] or _inside(b[:1], a)[0])


def overlap_attitude(robot, target) -> float | None:
    """Return an attitude (rad) at which the target's body overlaps the spacecraft's, or None."""
    body = np.asarray(target.body_polygon_m, dtype=float)
    reach = float(np.max(np.linalg.norm(robot.body_polygon_m, axis=1)))
    if not _segments_near(body, reach) and not _inside(np.zeros((1, 2)), body)[0]:
        return None                       # beyond the circle the spacecraft's body sweeps
    if 0 in robot.planned_joints:
        lo, hi = float(robot.lower_rad[0]), float(robot.upper_rad[0])
        n = max(2, int(math.ceil(math.degrees(hi - lo) / STEP_DEG)) + 1)
        attitudes = np.linspace(lo, hi, n)
    else:
        attitudes = np.array([float(robot.locked_rad[0])])
    for a in attitudes:
        if polygons_overlap(robot.body_polygon_world(a), body):
            return float(a)
    return None


def _segments_near(poly, radius) -> bool:
    """Tell whether an edge of the polygon comes within ``radius`` of the origin."""
    a, b = poly, np.roll(poly, -1, axis=0)
    d = b - a
    t = np.clip(-np.einsum("ij,ij->i", a, d) / np.maximum(np.einsum("ij,ij->i", d, d), 1e-300), 0.0, 1.0)
    return bool(np.min(np.linalg.norm(a + t[:, None] * d, axis=1)) <= radius)


def target_overlap_reason(robot, target) -> str | None:
    """Return why the target is refused (its body overlaps the spacecraft's), or None."""
    a = overlap_attitude(robot, target)
    if a is None:
        return None
    cx, cy = target.center_m
    where = (f"at attitude {math.degrees(a):.1f}° (the attitude is planned: every attitude within its bounds "
             "counts)" if 0 in robot.planned_joints else f"at the locked attitude {math.degrees(a):.1f}°")
    return (f"the target body (centre ({cx:.3f}, {cy:.3f}) m, side {target.body_side_m:g} m) overlaps the "
            f"spacecraft body {where}")
