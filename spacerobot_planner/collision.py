"""
Exact collision tests and clearance between the arm's links and polygons.

Links are line segments (zero width).  A link collides with a polygon when it
crosses an edge or lies inside it; with a safety margin, when its distance to the
polygon is at most the margin.  The clearance of a configuration is the smallest
distance from any checked link to the spacecraft body or any obstacle (0 when they
touch or overlap).

The numba kernels work on packed polygons (see ``scene.pack_polygons``) and are
shared with the C-space builder.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from .scene import pack_polygons

#: numba's options for a kernel that allocates nothing (its outputs and scratch come from its
#: caller, Python): compiled without the runtime's reference counting (NRT).  With it, each call
#: with array arguments inside a loop (a clearance per sample, a constraint test per grid point)
#: increments and decrements every array's count atomically, which numba's pruning does not
#: remove across loops: half of the trajectory's backward pass.  The same arithmetic, bit for
#: bit.  Such a kernel is called from Python, from another such kernel, or once from a kernel
#: that allocates its scratch (``cspace._fill_rows``).  Its helpers without options of their own
#: (``config_clearance``, ``motion.segment_free_from``) take their caller's; numba keeps one
#: compiled version per signature, in the process and in its cache, so a helper compiled first
#: for a loop with NRT keeps its counting for every caller: every loop over such a helper is one
#: of these kernels (``_clearances_into``: the warm-up's first clearance compiles
#: ``config_clearance``).
NO_REFCOUNT = {"cache": True, "nogil": True, "_nrt": False}

__all__ = ["CollisionChecker"]


# ----------------------------------------------------------------- primitives
@njit(cache=True, nogil=True, inline="always")
def _orient(ax, ay, bx, by, cx, cy):
    return (bx - ax) * (cy - ay) - (by - ay) * (cx - ax)


@njit(cache=True, nogil=True, inline="always")
def _on_segment(ax, ay, bx, by, px, py):
    return min(ax, bx) <= px <= max(ax, bx) and min(ay, by) <= py <= max(ay, by)


@njit(cache=True, nogil=True)
def segments_intersect(ax, ay, bx, by, cx, cy, dx, dy):
    """Return True when segment AB and segment CD share at least one point."""
    d1 = _orient(cx, cy, dx, dy, ax, ay)
    d2 = _orient(cx, cy, dx, dy, bx, by)
    d3 = _orient(ax, ay, bx, by, cx, cy)
    d4 = _orient(ax, ay, bx, by, dx, dy)
    if ((d1 > 0 and d2 < 0) or (d1 < 0 and d2 > 0)) and ((d3 > 0 and d4 < 0) or (d3 < 0 and d4 > 0)):
        return True
    if d1 == 0 and _on_segment(cx, cy, dx, dy, ax, ay):
        return True
    if d2 == 0 and _on_segment(cx, cy, dx, dy, bx, by):
        return True
    if d3 == 0 and _on_segment(ax, ay, bx, by, cx, cy):
        return True
    if d4 == 0 and _on_segment(ax, ay, bx, by, dx, dy):
        return True
    return False


@njit(cache=True, nogil=True, inline="always")
def point_segment_dist2(px, py, ax, ay, bx, by):
    """Squared distance from point P to segment AB."""
    ux, uy = bx - ax, by - ay
    den = ux * ux + uy * uy
    t = 0.0
    if den > 0.0:
        t = min(1.0, max(0.0, ((px - ax) * ux + (py - ay) * uy) / den))
    ex, ey = ax + t * ux - px, ay + t * uy - py
    return ex * ex + ey * ey


@njit(cache=True, nogil=True)
def point_in_polygon(px, py, verts, start, stop):
    """Even–odd ray test: True when P lies strictly inside polygon verts[start:stop]."""
    inside = False
    j = stop - 1
    for i in range(start, stop):
        xi, yi = verts[i, 0], verts[i, 1]
        xj, yj = verts[j, 0], verts[j, 1]
        if (yi > py) != (yj > py):
            x_cross = xi + (py - yi) * (xj - xi) / (yj - yi)
            if px < x_cross:
                inside = not inside
        j = i
    return inside


@njit(cache=True, nogil=True)
def segment_polygon_distance(ax, ay, bx, by, verts, start, stop):
    """
    Distance from segment AB to polygon verts[start:stop] (0 if touching or inside).

    The smallest segment-to-edge distance over the edges (0 where AB crosses one), by squared distances
    and one square root (a correctly rounded square root is monotone: the same value); each
    vertex's squared distance to AB is computed once, for both of its edges.
    """
    if point_in_polygon(ax, ay, verts, start, stop):
        return 0.0
    best = np.inf
    cx, cy = verts[stop - 1, 0], verts[stop - 1, 1]
    dc = point_segment_dist2(cx, cy, ax, ay, bx, by)
    for i in range(start, stop):
        dx, dy = verts[i, 0], verts[i, 1]
        if segments_intersect(ax, ay, bx, by, cx, cy, dx, dy):
            return 0.0
        dd = point_segment_dist2(dx, dy, ax, ay, bx, by)
        d = min(min(point_segment_dist2(ax, ay, cx, cy, dx, dy), point_segment_dist2(bx, by, cx, cy, dx, dy)),
                min(dc, dd))
        if d < best:
            best = d
        cx, cy, dc = dx, dy, dd
    return np.sqrt(best)


@njit(cache=True, nogil=True)
def segment_polygon_within(ax, ay, bx, by, verts, start, stop, margin_m):
    """
    Return True when segment AB comes within ``margin_m`` of the polygon (early exit).

    Compares squared distances (no square roots); touching counts at margin 0.
    """
    if point_in_polygon(ax, ay, verts, start, stop):
        return True
    m2 = margin_m * margin_m
    j = stop - 1
    for i in range(start, stop):
        cx, cy, dx, dy = verts[j, 0], verts[j, 1], verts[i, 0], verts[i, 1]
        if segments_intersect(ax, ay, bx, by, cx, cy, dx, dy):
            return True
        if margin_m > 0.0 and (point_segment_dist2(ax, ay, cx, cy, dx, dy) <= m2
                               or point_segment_dist2(bx, by, cx, cy, dx, dy) <= m2
                               or point_segment_dist2(cx, cy, ax, ay, bx, by) <= m2
                               or point_segment_dist2(dx, dy, ax, ay, bx, by) <= m2):
            return True
        j = i
    return False


# ------------------------------------------------------- per-configuration core
@njit(cache=True, nogil=True)
def link_points(q_full, lengths, out):
    """
    Fill out (n+1, 2) with the chain's joint points for one configuration.

    Returns the cosine and sine of the first link's angle (0.0 + q_full[0]).
    """
    ang = 0.0
    out[0, 0] = 0.0
    out[0, 1] = 0.0
    c0 = s0 = 0.0
    for k in range(q_full.shape[0]):
        ang += q_full[k]
        c, s = np.cos(ang), np.sin(ang)
        if k == 0:
            c0, s0 = c, s
        out[k + 1, 0] = out[k, 0] + lengths[k] * c
        out[k + 1, 1] = out[k, 1] + lengths[k] * s
    return c0, s0


@njit(cache=True, nogil=True, inline="always")
def _rotate_body_cs(body, c, s, out):
    """Fill out like body, turned by the angle whose cosine and sine are c and s."""
    for i in range(body.shape[0]):
        out[i, 0] = c * body[i, 0] - s * body[i, 1]
        out[i, 1] = s * body[i, 0] + c * body[i, 1]


@njit(cache=True, nogil=True)
def rotate_body(body, attitude, out):
    _rotate_body_cs(body, np.cos(attitude), np.sin(attitude), out)


@njit(cache=True, nogil=True)
def segment_hits_polygons(ax, ay, bx, by, verts, starts, centres, radii, margin_m):
    """Return True when segment AB comes within margin_m of one of the packed polygons."""
    for p in range(radii.shape[0]):
        # bounding-circle cull: the segment is farther than radius + margin from the centre
        r = radii[p] + margin_m
        if point_segment_dist2(centres[p, 0], centres[p, 1], ax, ay, bx, by) > r * r:
            continue
        if segment_polygon_within(ax, ay, bx, by, verts, starts[p], starts[p + 1], margin_m):
            return True
    return False


@njit(cache=True, nogil=True)
def links_hit_polygons(pts, checked, verts, starts, centres, radii, margin_m):
    """Return True when a checked link (pts: chain points) comes within margin_m of a polygon."""
    for c in range(checked.shape[0]):
        k = checked[c]
        if segment_hits_polygons(pts[k, 0], pts[k, 1], pts[k + 1, 0], pts[k + 1, 1], verts, starts,
                                 centres, radii, margin_m):
            return True
    return False


@njit(cache=True, nogil=True)
def links_hit_body(pts, checked, body_w, margin_m):
    """Return True when a checked link comes within margin_m of the (posed) spacecraft body."""
    nb = body_w.shape[0]
    for c in range(checked.shape[0]):
        k = checked[c]
        if segment_polygon_within(pts[k, 0], pts[k, 1], pts[k + 1, 0], pts[k + 1, 1],
                                  body_w, 0, nb, margin_m):
            return True
    return False


@njit(cache=True, nogil=True, inline="always")
def _pair_bound(pts, k, p, obs_centres, obs_radii, body_r):
    """
    Lower bound on the distance of link k to polygon p (0: the body, p ≥ 1: obstacle p - 1).

    The link's distance to the polygon's bounding circle (``obs_centres``, ``obs_radii`` of
    ``scene.pack_polygons``; for the body, the circle of radius ``body_r`` about the origin),
    less 1e-9 m for rounding.
    """
    ax, ay, bx, by = pts[k, 0], pts[k, 1], pts[k + 1, 0], pts[k + 1, 1]
    if p == 0:
        return np.sqrt(point_segment_dist2(0.0, 0.0, ax, ay, bx, by)) - body_r - 1e-9
    return (np.sqrt(point_segment_dist2(obs_centres[p - 1, 0], obs_centres[p - 1, 1], ax, ay, bx, by))
            - obs_radii[p - 1] - 1e-9)


@njit(cache=True, nogil=True, inline="always")
def _pair_distance(pts, k, p, body_w, obs_verts, obs_starts):
    """Distance of link k to polygon p (0: the posed body ``body_w``, p ≥ 1: obstacle p - 1)."""
    ax, ay, bx, by = pts[k, 0], pts[k, 1], pts[k + 1, 0], pts[k + 1, 1]
    if p == 0:
        return segment_polygon_distance(ax, ay, bx, by, body_w, 0, body_w.shape[0])
    return segment_polygon_distance(ax, ay, bx, by, obs_verts, obs_starts[p - 1], obs_starts[p])


@njit(cache=True, nogil=True)
def config_clearance(q_full, lengths, checked, body, obs_verts, obs_starts, obs_centres, obs_radii, pts, body_w):
    """
    Smallest distance (m) from a checked link to the body or any obstacle.

    Each (link, polygon) pair has a lower bound on its distance (:func:`_pair_bound`).  The
    pair of the smallest bound is measured first, then every other pair whose bound is below
    the smallest distance found so far: the minimum is the same as over every pair (a pair
    skipped is at least as far).  No allocation; ``pts`` and ``body_w`` are scratch (the
    chain's points, the posed body), the body turned by the attitude with the first link's
    cosine and sine (:func:`link_points`).
    """
    c0, s0 = link_points(q_full, lengths, pts)
    # the attitude's own sine: sin(0.0 + q) is sin(q) but for q = -0.0 (sin(±0) = ±0)
    _rotate_body_cs(body, c0, q_full[0] if q_full[0] == 0.0 else s0, body_w)
    body_r2 = 0.0
    for i in range(body.shape[0]):
        body_r2 = max(body_r2, body[i, 0] * body[i, 0] + body[i, 1] * body[i, 1])
    body_r = np.sqrt(body_r2)
    n_poly = obs_starts.shape[0]          # the body, then the obstacles
    n_pair = checked.shape[0] * n_poly
    first, low = 0, np.inf
    for pair in range(n_pair):
        b = _pair_bound(pts, checked[pair // n_poly], pair % n_poly, obs_centres, obs_radii, body_r)
        if b < low:
            first, low = pair, b
    best = _pair_distance(pts, checked[first // n_poly], first % n_poly, body_w, obs_verts, obs_starts)
    for pair in range(n_pair):
        if pair != first:
            k = checked[pair // n_poly]
            p = pair % n_poly
            if _pair_bound(pts, k, p, obs_centres, obs_radii, body_r) < best:
                best = min(best, _pair_distance(pts, k, p, body_w, obs_verts, obs_starts))
    return best


@njit(cache=True, nogil=True)
def _batch_clearance(q_full, lengths, checked, body, obs_verts, obs_starts, obs_centres, obs_radii):
    """Clearance of each full configuration q_full[i], (N,) m (:func:`_clearances_into` with its scratch)."""
    out = np.empty(q_full.shape[0])
    _clearances_into(out, q_full, lengths, checked, body, obs_verts, obs_starts, obs_centres, obs_radii,
                     np.empty((lengths.shape[0] + 1, 2)), np.empty_like(body))
    return out


@njit(**NO_REFCOUNT)
def _clearances_into(out, q_full, lengths, checked, body, obs_verts, obs_starts, obs_centres, obs_radii, pts,
                     body_w):
    """:func:`_batch_clearance` into out (N,); scratch pts (n_links + 1, 2), body_w like body."""
    for i in range(q_full.shape[0]):
        out[i] = config_clearance(q_full[i], lengths, checked, body, obs_verts, obs_starts, obs_centres,
                                  obs_radii, pts, body_w)


@njit(cache=True, nogil=True)
def _batch_clearance_shifted(q_full, shift, lengths, checked, body, verts, starts, centres, radii):
    """Clearance of each configuration q_full[k] with the obstacles shifted by −shift[k], (K,) m."""
    out = np.empty(q_full.shape[0])
    _shifted_clearances_into(out, q_full, shift, lengths, checked, body, verts, starts, centres, radii,
                             np.empty((lengths.shape[0] + 1, 2)), np.empty_like(body), np.empty_like(verts),
                             np.empty_like(centres))
    return out


@njit(**NO_REFCOUNT)
def _shifted_clearances_into(out, q_full, shift, lengths, checked, body, verts, starts, centres, radii, pts, body_w,
                             shifted, shifted_centres):
    """:func:`_batch_clearance_shifted` into out (K,); scratch pts, body_w, shifted like verts and centres."""
    for k in range(q_full.shape[0]):
        for v in range(verts.shape[0]):
            shifted[v, 0] = verts[v, 0] - shift[k, 0]
            shifted[v, 1] = verts[v, 1] - shift[k, 1]
        for p in range(centres.shape[0]):
            shifted_centres[p, 0] = centres[p, 0] - shift[k, 0]
            shifted_centres[p, 1] = centres[p, 1] - shift[k, 1]
        out[k] = config_clearance(q_full[k], lengths, checked, body, shifted, starts, shifted_centres, radii,
                                  pts, body_w)


# ------------------------------------------------------------------ public API
class CollisionChecker:
    """
    The validity checker: exact tests of planned configurations against a scene.

    Build it once per (robot, scene); it packs the geometry for the kernels.
    """

    def __init__(self, robot, scene):
        self.robot = robot
        self.scene = scene
        self.lengths = np.asarray(robot.link_lengths_m, dtype=float)
        self.checked = np.asarray(robot.checked_links, dtype=np.int64)
        self.body = np.ascontiguousarray(robot.body_polygon_m, dtype=float)
        self.verts, self.starts, self.centres, self.radii = pack_polygons(scene.obstacle_polygons_m)
        self.margin_m = float(scene.safety_margin_m)

    def clearance_m(self, q) -> np.ndarray | float:
        """Clearance (m) of planned configuration(s) q: (dof,) → float, (N, dof) → (N,)."""
        q = np.asarray(q, dtype=float)
        single = q.ndim == 1
        q_full = np.ascontiguousarray(self.robot.full(np.atleast_2d(q)))
        out = _batch_clearance(q_full, self.lengths, self.checked, self.body, self.verts, self.starts,
                               self.centres, self.radii)
        return float(out[0]) if single else out

    def clearance_shifted_m(self, q_full, shift_m) -> np.ndarray:
        """
        Clearance (m) of full configurations (K, n) with the obstacles moved by −shift_m (K, 2).

        The scene seen from a spacecraft body that translated by ``shift_m`` (the obstacles
        stay where they are in the inertial frame): one value per row.
        """
        return _batch_clearance_shifted(np.ascontiguousarray(q_full, dtype=float),
                                        np.ascontiguousarray(shift_m, dtype=float), self.lengths, self.checked,
                                        self.body, self.verts, self.starts, self.centres, self.radii)

    def is_free(self, q) -> np.ndarray | bool:
        """Return True where clearance > safety margin: (dof,) → bool, (N, dof) → (N,) bool."""
        c = self.clearance_m(q)
        return bool(c > self.margin_m) if np.ndim(c) == 0 else c > self.margin_m
