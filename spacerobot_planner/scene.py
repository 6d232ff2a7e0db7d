"""
The world around the arm: the target satellite, debris, and the safety margin.

All positions are in the planning frame (metres, origin at the spacecraft centre of
mass); angles in radians.  The spacecraft body belongs to the robot (it turns with
the attitude joint), everything here is inertially fixed.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from .robot import square_polygon, validate_polygon

__all__ = ["Target", "Scene", "pack_polygons"]


@dataclass(frozen=True)
class Target:
    """
    The target satellite: a square body with a square grasp handle on one face.

    In the target's own frame the body is centred at the origin and the handle sits
    at the centre of the +y face, outside the body.  The grasp point is the centre
    of the handle's outer face; the end-effector approaches it along −y (into the
    target), so the capture posture has absolute link-3 angle ``yaw + 270°``.

    Attributes
    ----------
        center_m: (x, y) of the body centre, metres.
        yaw_rad: rotation of the target frame, rad.
        body_side_m: side of the square body (paper: 1.0 m).
        handle_side_m: side of the square handle (paper: 0.1 m).

    """

    center_m: tuple = (-3.27, -2.60)
    yaw_rad: float = 0.0
    body_side_m: float = 1.0
    handle_side_m: float = 0.1

    def __post_init__(self):
        c = np.asarray(self.center_m, dtype=float)
        if c.shape != (2,) or not np.all(np.isfinite(c)):
            raise ValueError(f"target.center_m: expected two finite numbers, got {self.center_m!r}")
        if not np.isfinite(self.yaw_rad):
            raise ValueError(f"target.yaw: not a finite number ({self.yaw_rad})")
        for name in ("body_side_m", "handle_side_m"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v > 0.0):
                raise ValueError(f"target.{name}: must be > 0, got {v}")
        object.__setattr__(self, "center_m", (float(c[0]), float(c[1])))

    def sized_as(self, other: "Target") -> "Target":
        """Return this target where it is with ``other``'s body and handle sides (a runtime change of the sizes)."""
        return replace(self, body_side_m=other.body_side_m, handle_side_m=other.handle_side_m)

    def _to_world(self, local_xy) -> np.ndarray:
        c, s = np.cos(self.yaw_rad), np.sin(self.yaw_rad)
        return np.asarray(local_xy, dtype=float) @ np.array([[c, s], [-s, c]]) + np.asarray(self.center_m)

    @property
    def body_polygon_m(self) -> np.ndarray:
        """Body outline (4×2, metres, counter-clockwise) in the planning frame."""
        return square_polygon(self.body_side_m, self.center_m, self.yaw_rad)

    @property
    def handle_polygon_m(self) -> np.ndarray:
        """Handle outline (4×2, metres): the goal, not an obstacle."""
        h, b = self.handle_side_m, 0.5 * self.body_side_m
        local = np.array([[h / 2, b], [h / 2, b + h], [-h / 2, b + h], [-h / 2, b]])
        return self._to_world(local)

    @property
    def grasp_point_m(self) -> np.ndarray:
        """Centre of the handle's outer face, (2,) metres."""
        return self._to_world([0.0, 0.5 * self.body_side_m + self.handle_side_m])

    @property
    def approach_angle_rad(self) -> float:
        """Absolute end-effector (last link) angle at capture: perpendicular, into the target."""
        return float(self.yaw_rad + 1.5 * np.pi)


@dataclass(frozen=True, eq=False)
class Scene:
    """
    What the arm must not touch, besides its own spacecraft body.

    Attributes
    ----------
        target: the target satellite, or None (joint-space goals only).
        debris_m: extra obstacles, a tuple of (k×2) polygons in metres (convex or not).
        safety_margin_m: minimum allowed distance from a checked link to any
            obstacle, metres (≥ 0); a configuration is free when its clearance is
            strictly greater than this margin.

    """

    target: Target | None = Target()
    debris_m: tuple = ()
    safety_margin_m: float = 0.0

    def __post_init__(self):
        if not (np.isfinite(self.safety_margin_m) and self.safety_margin_m >= 0.0):
            raise ValueError(f"safety_margin_m: must be a finite number ≥ 0, got {self.safety_margin_m}")
        # the scene's own copies: a caller's array changed later does not change the scene (nor its geometry key)
        polys = tuple(np.array(validate_polygon(p, f"obstacles[{i}]")) for i, p in enumerate(self.debris_m))
        object.__setattr__(self, "debris_m", polys)

    def geometry_key(self) -> tuple:
        """
        Return what the C-space depends on, as a hashable key: the obstacles' vertex bytes and the margin.

        Computed once per scene (a scene never changes: its polygons are its own copies, its
        target's outline follows from numbers), not on every plan.
        """
        key = self.__dict__.get("_geometry_key")
        if key is None:
            key = (tuple(np.asarray(p, dtype=float).tobytes() for p in self.obstacle_polygons_m),
                   float(self.safety_margin_m))
            object.__setattr__(self, "_geometry_key", key)
        return key

    def __getstate__(self):
        """Pickle the fields only, not the key held (a scene's bytes are the same whether it was planned on or not)."""
        return {k: v for k, v in self.__dict__.items() if k != "_geometry_key"}

    @property
    def obstacle_polygons_m(self) -> list:
        """Every inertially fixed obstacle: the target body (if any), then the debris."""
        polys = [self.target.body_polygon_m] if self.target is not None else []
        return polys + list(self.debris_m)

    def with_target(self, target: Target | None) -> "Scene":
        return Scene(target=target, debris_m=self.debris_m, safety_margin_m=self.safety_margin_m)

    def with_margin(self, safety_margin_m: float) -> "Scene":
        return Scene(target=self.target, debris_m=self.debris_m, safety_margin_m=safety_margin_m)


def pack_polygons(polygons) -> tuple:
    """
    Flatten polygons for the numba kernels.

    Returns
    -------
        (verts, starts, centres, radii): verts (V×2) all vertices; starts (P+1,)
        offsets so polygon p is verts[starts[p]:starts[p+1]]; centres (P×2) and
        radii (P,) of a bounding circle of each polygon (for cheap culling).

    """
    polygons = [np.asarray(p, dtype=float) for p in polygons]
    starts = np.zeros(len(polygons) + 1, dtype=np.int64)
    for i, p in enumerate(polygons):
        starts[i + 1] = starts[i] + len(p)
    verts = np.concatenate(polygons) if polygons else np.zeros((0, 2))
    centres = np.array([p.mean(axis=0) for p in polygons]).reshape(-1, 2)
    radii = np.array([np.max(np.hypot(*(p - c).T)) for p, c in zip(polygons, centres)])
    return (np.ascontiguousarray(verts), starts, np.ascontiguousarray(centres),
            radii.astype(float).reshape(-1))
