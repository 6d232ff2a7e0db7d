"""
The space robot: a planar serial chain whose first joint is the spacecraft attitude.

Conventions (the project's notes on the paper's scenes, kept outside this repository): planar world (x, y) in
metres with the origin at the spacecraft centre of mass; joint angles in radians,
counter-clockwise from +x; joint k's angle is relative to link k-1, so link k points
at the cumulative sum θ1 + … + θk.  Joint 1 is the "virtual" attitude joint at the
origin; link 1 runs from the origin to the shoulder, fixed in the spacecraft body.

A configuration over *all* joints is ``q_full`` (length ``n_joints``); a configuration
over the *planned* joints only is ``q`` (length ``dof``).  Locked joints (the attitude
in the paper's 2-DOF case) keep the value in ``locked_rad``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .joint_space import TWO_PI, wrap_rad

__all__ = ["PlanarArm", "square_polygon", "validate_polygon", "BOUND_TOL_RAD", "MAX_TURNS_RAD"]

#: a bounded joint reported this far past a bound is taken as at the bound (rounding: a bound of
#: 180° in a file, the joint state's π in radians), rad; farther is refused
BOUND_TOL_RAD = 1e-9
#: the largest magnitude a periodic joint's value may have, rad (about 159 000 turns): a plan's
#: motion is published shifted by the whole turns of the joint state it starts from, and float64
#: resolves 1.2e-10 rad there (at 1e17 rad a step is 16 rad: the attitude could not move at all)
MAX_TURNS_RAD = 1e6


def _plain(value):
    """Return ``value`` with NumPy arrays and scalars as Python lists and numbers (for a reason's text)."""
    if isinstance(value, np.ndarray):
        value = value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    return value


def square_polygon(side_m: float, center_m=(0.0, 0.0), yaw_rad: float = 0.0,
                   corner_first: bool = False) -> np.ndarray:
    """
    Vertices (4×2, metres, counter-clockwise) of a square.

    With ``corner_first`` the first vertex lies on the local +x axis (the square is
    turned 45°), which is how the spacecraft body sits: link 1 points at a corner.
    """
    h = 0.5 * side_m
    if corner_first:
        r = h * np.sqrt(2.0)
        local = np.array([[r, 0.0], [0.0, r], [-r, 0.0], [0.0, -r]])
    else:
        local = np.array([[h, -h], [h, h], [-h, h], [-h, -h]])
    c, s = np.cos(yaw_rad), np.sin(yaw_rad)
    rot = np.array([[c, -s], [s, c]])
    return local @ rot.T + np.asarray(center_m, dtype=float)


@dataclass(frozen=True, eq=False)
class PlanarArm:
    """
    A planar serial arm mounted on a spacecraft body that turns with joint 1.

    Attributes
    ----------
        joint_names: one name per joint, e.g. ``("attitude", "shoulder", "elbow")``.
        link_lengths_m: length of each link (> 0), link 1 first.
        lower_rad, upper_rad: joint bounds (``upper > lower``); a periodic joint
            spans exactly one turn, ``upper - lower == 2π``.
        periodic: per joint, whether it wraps (−π ≡ +π for the attitude).
        body_polygon_m: (k×2) spacecraft body outline in the body frame (turns with
            joint 1), metres.
        planned_joints: indices of the joints the planner moves (its C-space axes).
        locked_rad: full-length vector; entries of joints not planned are held there.
        checked_links: indices of the links tested for collision (links 2 and 3:
            ``(1, 2)``); link 1 is inside the spacecraft structure.

    """

    joint_names: tuple
    link_lengths_m: tuple
    lower_rad: tuple
    upper_rad: tuple
    periodic: tuple
    body_polygon_m: np.ndarray
    planned_joints: tuple = None
    locked_rad: np.ndarray = None
    checked_links: tuple = (1, 2)

    def __post_init__(self):
        n = len(self.joint_names)
        if n < 2:
            raise ValueError("joint_names: a planar arm needs at least 2 joints")
        if len(set(self.joint_names)) != n:
            raise ValueError(f"joint_names: names must be unique, got {list(self.joint_names)}")
        for name in ("link_lengths_m", "lower_rad", "upper_rad", "periodic"):
            if len(getattr(self, name)) != n:
                raise ValueError(f"{name}: expected {n} values (one per joint), "
                                 f"got {len(getattr(self, name))}")
        lengths = np.asarray(self.link_lengths_m, dtype=float)
        if not np.all(np.isfinite(lengths)) or np.any(lengths <= 0.0):
            raise ValueError(f"link_lengths_m: every link length must be > 0, got {list(lengths)}")
        lo = np.asarray(self.lower_rad, dtype=float)
        hi = np.asarray(self.upper_rad, dtype=float)
        if not (np.all(np.isfinite(lo)) and np.all(np.isfinite(hi))):
            raise ValueError("lower/upper joint bounds must be finite")
        if np.any(hi <= lo):
            raise ValueError("joint bounds: every upper bound must exceed its lower bound")
        for i, p in enumerate(self.periodic):
            if p and not np.isclose(hi[i] - lo[i], TWO_PI):
                raise ValueError(f"periodic: joint '{self.joint_names[i]}' is periodic, so its "
                                 f"bounds must span exactly 360°")
        body = np.asarray(self.body_polygon_m, dtype=float)
        validate_polygon(body, "body_polygon_m")
        object.__setattr__(self, "body_polygon_m", body)
        planned = tuple(range(n)) if self.planned_joints is None else tuple(self.planned_joints)
        if not planned or len(set(planned)) != len(planned) or any(not 0 <= j < n for j in planned):
            raise ValueError(f"planned_joints: need distinct joint indices in 0..{n - 1}, got {planned}")
        object.__setattr__(self, "planned_joints", tuple(sorted(planned)))
        locked = np.zeros(n) if self.locked_rad is None else np.asarray(self.locked_rad, dtype=float)
        if locked.shape != (n,) or not np.all(np.isfinite(locked)):
            raise ValueError(f"locked_rad: expected {n} finite values")
        for j in range(n):
            if j not in planned and not (lo[j] <= locked[j] <= hi[j]):
                raise ValueError(f"locked position of joint '{self.joint_names[j]}' is outside its bounds")
        object.__setattr__(self, "locked_rad", locked)
        if any(not 0 <= k < n for k in self.checked_links):
            raise ValueError("checked_links: link indices out of range")
        # the planned joints' bounds and flags, made once and never written (the properties hand out copies)
        for attr, values, dtype in (("_planned_lower", lo, float), ("_planned_upper", hi, float),
                                    ("_planned_periodic", self.periodic, bool)):
            object.__setattr__(self, attr, np.array([values[j] for j in planned], dtype=dtype))
        bounds = (np.where(self._planned_periodic, -np.inf, self._planned_lower),
                  np.where(self._planned_periodic, np.inf, self._planned_upper))
        for b in bounds:
            b.setflags(write=False)
        object.__setattr__(self, "_planned_bounds", bounds)

    # ------------------------------------------------------------------ joints
    @property
    def n_joints(self) -> int:
        return len(self.joint_names)

    @property
    def dof(self) -> int:
        """Return the number of planned joints (the C-space dimension)."""
        return len(self.planned_joints)

    @property
    def planned_names(self) -> tuple:
        return tuple(self.joint_names[j] for j in self.planned_joints)

    @property
    def planned_lower_rad(self) -> np.ndarray:
        return self._planned_lower.copy()

    @property
    def planned_upper_rad(self) -> np.ndarray:
        return self._planned_upper.copy()

    @property
    def planned_periodic(self) -> tuple:
        return tuple(bool(self.periodic[j]) for j in self.planned_joints)

    @property
    def planned_bounds_rad(self) -> tuple:
        """(lower (dof,), upper (dof,)) rad, read-only: the planned joints' bounds, ±inf for a periodic joint."""
        return self._planned_bounds

    def full(self, q) -> np.ndarray:
        """Planned configuration(s) ``q`` (dof or N×dof) → full ones (n_joints or N×n_joints)."""
        q = np.asarray(q, dtype=float)
        out = np.empty(q.shape[:-1] + (self.n_joints,))
        out[...] = self.locked_rad
        out[..., list(self.planned_joints)] = q
        return out

    def validate_q(self, q, name: str = "configuration") -> np.ndarray:
        """
        Check a planned configuration: right length, finite, within bounds.

        Periodic joints are wrapped into their range (that is the same posture, not a
        clamp), where their value is within ``MAX_TURNS_RAD``; a bounded joint within
        ``BOUND_TOL_RAD`` past a bound is set to the bound (the motion validator accepts no posture
        outside, so every motion from or to it was refused as colliding).  Any other violation raises
        ``ValueError`` naming ``name`` and the joint (values that are not numbers: ``name`` and what
        was given).
        """
        try:
            q = np.asarray(q, dtype=float)
        except (ValueError, TypeError, OverflowError):
            text = repr(_plain(q))
            raise ValueError(f"{name}: expected {self.dof} joint values ({', '.join(self.planned_names)}) as "
                             f"numbers, rad; got {text if len(text) <= 60 else text[:57] + '...'}") from None
        if q.shape != (self.dof,):
            raise ValueError(f"{name}: expected {self.dof} joint values "
                             f"({', '.join(self.planned_names)}), got shape {q.shape}")
        lo, hi = self._planned_lower, self._planned_upper
        for k, (j, x, low, high) in enumerate(zip(self.planned_joints, q.tolist(), lo.tolist(), hi.tolist())):
            jn = self.joint_names[j]
            if not math.isfinite(x):
                raise ValueError(f"{name}: joint '{jn}' is {q[k]} (not a finite number)")
            if self.periodic[j] and abs(x) > MAX_TURNS_RAD:
                raise ValueError(f"{name}: joint '{jn}' = {x:.6g} rad is more turns than a plan can carry: at most "
                                 f"±{MAX_TURNS_RAD:g} rad (about {MAX_TURNS_RAD / TWO_PI:,.0f} turns; float64 "
                                 f"resolves {math.ulp(MAX_TURNS_RAD):.1g} rad there); report it wrapped, e.g. "
                                 f"into [-π, π)")
            if not self.periodic[j] and not (low - BOUND_TOL_RAD <= x <= high + BOUND_TOL_RAD):
                past_deg = math.degrees(max(low - x, x - high))
                # the digits that tell it from the bound (165.0000001°, not 165.000°)
                digits = min(12, max(3, 1 - math.floor(math.log10(past_deg))))
                raise ValueError(f"{name}: joint '{jn}' = {np.degrees(q[k]):.{digits}f}° is outside its "
                                 f"bounds [{np.degrees(lo[k]):.1f}°, {np.degrees(hi[k]):.1f}°] by {past_deg:.2g}°")
        q = wrap_rad(q, self._planned_periodic, lo)
        bounded = ~self._planned_periodic
        q[bounded] = np.clip(q[bounded], lo[bounded], hi[bounded])
        return q

    # -------------------------------------------------------------- kinematics
    def forward_kinematics(self, q_full) -> np.ndarray:
        """
        Joint positions for full configuration(s).

        Args:
            q_full: (n_joints,) or (N, n_joints) joint angles, rad.

        Returns
        -------
            (n_joints+1, 2) or (N, n_joints+1, 2) points, metres: the origin, then
            the end of each link (the last one is the end-effector tip).

        """
        q_full = np.asarray(q_full, dtype=float)
        abs_angles = np.cumsum(q_full, axis=-1)
        lengths = np.asarray(self.link_lengths_m, dtype=float)
        steps = np.stack([np.cos(abs_angles), np.sin(abs_angles)], axis=-1) * lengths[:, None]
        zero = np.zeros(q_full.shape[:-1] + (1, 2))
        return np.concatenate([zero, np.cumsum(steps, axis=-2)], axis=-2)

    def tip_position(self, q_full) -> np.ndarray:
        """End-effector tip, (2,) or (N, 2) metres."""
        return self.forward_kinematics(q_full)[..., -1, :]

    def body_polygon_world(self, attitude_rad: float) -> np.ndarray:
        """Spacecraft body outline (k×2, metres) at the given joint-1 angle."""
        c, s = np.cos(attitude_rad), np.sin(attitude_rad)
        return self.body_polygon_m @ np.array([[c, s], [-s, c]])

    def jacobian(self, q_full) -> np.ndarray:
        """Position Jacobian of the tip w.r.t. all joints: (2, n) or (N, 2, n), m/rad."""
        pts = self.forward_kinematics(q_full)
        tip = pts[..., -1:, :]
        lever = tip - pts[..., :-1, :]          # from each joint to the tip
        return np.stack([-lever[..., 1], lever[..., 0]], axis=-2)

    def manipulability(self, q_full) -> np.ndarray:
        """Yoshikawa's measure sqrt(det(J Jᵀ)) of the tip position Jacobian, m²."""
        jac = self.jacobian(q_full)
        jjt = jac @ np.swapaxes(jac, -1, -2)
        det = jjt[..., 0, 0] * jjt[..., 1, 1] - jjt[..., 0, 1] * jjt[..., 1, 0]
        return np.sqrt(np.maximum(det, 0.0))


def validate_polygon(poly, name: str) -> np.ndarray:
    """Check a polygon: (k×2) with k ≥ 3 finite vertices and non-zero area."""
    poly = np.asarray(poly, dtype=float)
    if poly.ndim != 2 or poly.shape[1] != 2:
        raise ValueError(f"{name}: a polygon is a list of [x, y] vertices, got shape {poly.shape}")
    if poly.shape[0] < 3:
        raise ValueError(f"{name}: a polygon needs at least 3 vertices, got {poly.shape[0]}")
    if not np.all(np.isfinite(poly)):
        raise ValueError(f"{name}: polygon vertices must be finite numbers (found NaN or inf)")
    x, y = poly[:, 0], poly[:, 1]
    area = 0.5 * abs(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1)))
    if area <= 1e-12:
        raise ValueError(f"{name}: polygon has zero area (degenerate vertices)")
    return poly
