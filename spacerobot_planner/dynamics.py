"""
What the arm's motion does to the spacecraft: momentum map, wheel load, free floating.

The planar chain of ``robot.py`` (joint 1 = the spacecraft attitude θ1, link 1 a rigid,
massless offset fixed in the body, links 2… the arm) is given masses: the spacecraft
body (mass, inertia about its centre, which is the chain's origin) and each link (mass
and inertia about its centre, at mid-link).  Positions here are relative to the
spacecraft body centre with inertial axes (the absolute angles φ_k = θ1 + … + θk);
the planning frame is the body-centred frame at the start of the motion.  Numbers:
``shared/reference/free-floating.md``.

- **Momentum map.** With no external force the system centre of mass (CoM) stays put
  and the angular momentum about it, h = Σ m (r − r̄) × (ṙ − r̄̇) + Σ I φ̇, is linear in
  the joint rates: h = H(q) · q̇ (H depends on the arm joints only).
- **Attitude held or commanded** (reaction wheels on): the wheels take the rest,
  h_wheel = −H · q̇, and their torque is τ_wheel = dh_wheel/dt = −dh/dt.  Along a path
  q(s): h_wheel = −(H·q′) ṡ and τ_wheel = −(d(H·q′)/ds ṡ² + H·q′ s̈) — the terms
  :class:`WheelModel` hands to ``trajectory.time_parameterize``.
- **Free floating** (attitude control off during the motion): θ1 is not commanded,
  θ̇1 = −(Σ_{k>1} H_k θ̇k) / H_1, integrated along the arm's path (Simpson's rule per
  segment; H does not depend on θ1, so this is a quadrature), and the body translates
  so that the CoM stays fixed: b = r̄(q(0)) − r̄(q).  The target stays where it is, so
  the arm is checked in the inertial frame (:func:`check_drifted`) and the tip lands
  somewhere else than planned (:func:`free_floating_response`).

Units: kg, kg·m², m, rad, s; momentum N·m·s, torque N·m.  No ROS imports.
"""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass

import numpy as np
from numba import njit

from .collision import CollisionChecker, config_clearance

__all__ = ["MassProperties", "AcsSettings", "WheelModel", "FreeFloatingResponse", "DriftCheck", "ReactionReport",
           "ACS_MODES", "system_com_m", "angular_momentum_Nms", "momentum_rate_Nm", "momentum_map",
           "wheel_load", "free_floating_response", "check_drifted", "reaction_report", "Motion", "plan_motion",
           "scenario_joint_limits", "CompensatedPlan", "plan_free_floating"]

ACS_MODES = ("held", "free_floating")


@dataclass(frozen=True)
class MassProperties:
    """
    Masses and inertias of the spacecraft body and the links (planar, about the z axis).

    Attributes
    ----------
        body_mass_kg: spacecraft body (with the massless link 1), > 0.
        body_inertia_kgm2: its inertia about its centre (the chain's origin), ≥ 0.
        link_masses_kg: one per link (link 1 first, usually 0: it is part of the body), ≥ 0.
        link_inertias_kgm2: one per link, about the link's centre (mid-link), ≥ 0.
    Defaults: the reference servicer (2000 kg, 1080 kg·m²; links 2, 3: 30 kg, 10 kg·m²).

    """

    body_mass_kg: float = 2000.0
    body_inertia_kgm2: float = 1080.0
    link_masses_kg: tuple = (0.0, 30.0, 30.0)
    link_inertias_kgm2: tuple = (0.0, 10.0, 10.0)

    def __post_init__(self):
        def finite(name, v, positive=False):
            if isinstance(v, bool) or not isinstance(v, numbers.Real) or not math.isfinite(v):
                raise ValueError(f"dynamics.{name}: expected a finite number, got {v!r}")
            if (positive and v <= 0.0) or v < 0.0:
                raise ValueError(f"dynamics.{name}: must be {'> 0' if positive else '≥ 0'}, got {v}")
            return float(v)

        object.__setattr__(self, "body_mass_kg", finite("body_mass_kg", self.body_mass_kg, True))
        object.__setattr__(self, "body_inertia_kgm2", finite("body_inertia_kgm2", self.body_inertia_kgm2))
        for name in ("link_masses_kg", "link_inertias_kgm2"):
            vals = tuple(finite(f"{name}[{i}]", v) for i, v in enumerate(getattr(self, name)))
            object.__setattr__(self, name, vals)
        if len(self.link_masses_kg) != len(self.link_inertias_kgm2):
            raise ValueError(f"dynamics.link_inertias_kgm2: expected {len(self.link_masses_kg)} values "
                             f"(one per link, like dynamics.link_masses_kg), got {len(self.link_inertias_kgm2)}")

    def check_robot(self, robot) -> None:
        """Raise ValueError when the link tables do not match the robot's links."""
        if len(self.link_masses_kg) != robot.n_joints:
            raise ValueError(f"dynamics.link_masses_kg: expected {robot.n_joints} values (one per link "
                             f"of robot.joint_names), got {len(self.link_masses_kg)}")

    @property
    def total_mass_kg(self) -> float:
        return self.body_mass_kg + sum(self.link_masses_kg)


@dataclass(frozen=True)
class AcsSettings:
    """
    Attitude control during the arm motion (``acs.*``, ``grasp.position_tolerance_m``).

    Attributes
    ----------
        mode: "held" (reaction wheels hold or command the attitude) or "free_floating".
        max_wheel_momentum_Nms, max_wheel_torque_Nm: wheel limits, 0 = no limit.
        position_tolerance_m: free floating: largest acceptable tip miss, metres.
        compensate_drift: free floating: plan for the predicted drift (:func:`plan_free_floating`).

    """

    mode: str = "held"
    max_wheel_momentum_Nms: float = 0.0
    max_wheel_torque_Nm: float = 0.0
    position_tolerance_m: float = 0.02
    compensate_drift: bool = False

    @property
    def has_wheel_limits(self) -> bool:
        return self.max_wheel_momentum_Nms > 0.0 or self.max_wheel_torque_Nm > 0.0


# ------------------------------------------------------------------ kinematics
def _tables(robot, masses):
    masses.check_robot(robot)
    n = robot.n_joints
    lengths = np.asarray(robot.link_lengths_m, dtype=float)
    coef = np.tril(np.ones((n, n)), -1) + 0.5 * np.eye(n)      # link centre: Σ_{j<k} L_j e_j + L_k/2 e_k
    m = np.concatenate([[masses.body_mass_kg], masses.link_masses_kg])
    inertia = np.concatenate([[masses.body_inertia_kgm2], masses.link_inertias_kgm2])
    return coef * lengths[None, :], m, inertia


def _cross(a, b):
    return a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]


def _bodies(robot, masses, q_full, qd_full=None, qdd_full=None):
    """
    Return the centres, velocities and accelerations of the body and the links.

    Centres (..., n+1, 2) of the body (row 0, at the origin) and the links, their velocities and
    accelerations, and the bodies' absolute angles, rates, accelerations.
    """
    cl, m, inertia = _tables(robot, masses)
    q = np.asarray(q_full, dtype=float)
    phi = np.cumsum(q, axis=-1)
    e = np.stack([np.cos(phi), np.sin(phi)], axis=-1)
    e_perp = np.stack([-np.sin(phi), np.cos(phi)], axis=-1)
    zero = np.zeros(q.shape[:-1] + (1, 2))

    def with_body(links):
        return np.concatenate([zero, links], axis=-2)

    r = with_body(np.einsum("kj,...jd->...kd", cl, e))
    ang = np.concatenate([phi[..., :1], phi], axis=-1)
    out = {"r": r, "phi": ang, "m": m, "I": inertia}
    if qd_full is not None:
        phid = np.cumsum(np.asarray(qd_full, dtype=float), axis=-1)
        out["v"] = with_body(np.einsum("kj,...jd->...kd", cl, phid[..., None] * e_perp))
        out["phid"] = np.concatenate([phid[..., :1], phid], axis=-1)
        if qdd_full is not None:
            phidd = np.cumsum(np.asarray(qdd_full, dtype=float), axis=-1)
            acc = phidd[..., None] * e_perp - (phid ** 2)[..., None] * e
            out["a"] = with_body(np.einsum("kj,...jd->...kd", cl, acc))
            out["phidd"] = np.concatenate([phidd[..., :1], phidd], axis=-1)
    return out


def _about_com(x, m):
    """Return x (..., nb, 2) minus its mass-weighted mean."""
    return x - np.einsum("b,...bd->...d", m, x)[..., None, :] / m.sum()


def system_com_m(robot, masses: MassProperties, q_full) -> np.ndarray:
    """
    System centre of mass relative to the spacecraft body centre, inertial axes.

    q_full: (n,) or (N, n) rad → (2,) or (N, 2) m.
    """
    b = _bodies(robot, masses, q_full)
    return np.einsum("b,...bd->...d", b["m"], b["r"]) / b["m"].sum()


def angular_momentum_Nms(robot, masses: MassProperties, q_full, qd_full) -> np.ndarray:
    """Return h = Σ m (r − r̄) × (ṙ − r̄̇) + Σ I φ̇ about the system CoM: (...,) N·m·s."""
    b = _bodies(robot, masses, q_full, qd_full)
    m = b["m"]
    return (np.einsum("b,...b->...", m, _cross(_about_com(b["r"], m), _about_com(b["v"], m)))
            + np.einsum("b,...b->...", b["I"], b["phid"]))


def momentum_rate_Nm(robot, masses: MassProperties, q_full, qd_full, qdd_full) -> np.ndarray:
    """dh/dt = Σ m (r − r̄) × (r̈ − r̄̈) + Σ I φ̈ (the cross term ṙ × ṙ vanishes): (...,) N·m."""
    b = _bodies(robot, masses, q_full, qd_full, qdd_full)
    m = b["m"]
    return (np.einsum("b,...b->...", m, _cross(_about_com(b["r"], m), _about_com(b["a"], m)))
            + np.einsum("b,...b->...", b["I"], b["phidd"]))


def momentum_map(robot, masses: MassProperties, q_full) -> np.ndarray:
    """Return the row H(q) with h = H · q̇: (n,) or (N, n), N·m·s per rad/s (kg·m²)."""
    q = np.asarray(q_full, dtype=float)
    n = q.shape[-1]
    eye = np.eye(n)
    qb = np.broadcast_to(q[..., None, :], q.shape[:-1] + (n, n))
    return angular_momentum_Nms(robot, masses, qb, np.broadcast_to(eye, qb.shape))


def _planned_rates(robot, d_planned):
    """Planned-joint rates (..., dof) → full-joint rates (..., n) (locked joints: 0)."""
    d = np.asarray(d_planned, dtype=float)
    out = np.zeros(d.shape[:-1] + (robot.n_joints,))
    out[..., list(robot.planned_joints)] = d
    return out


@dataclass(frozen=True, eq=False)
class WheelModel:
    """
    Reaction-wheel load of a trajectory, and the wheels' limits.

    Reaction-wheel load of a trajectory with the attitude held (locked joint) or commanded (planned
    joint), and the wheels' limits (None: no limit).

    ``trajectory.time_parameterize(..., wheel=WheelModel(...))`` uses :meth:`path_terms`.
    """

    robot: object
    masses: MassProperties
    max_momentum_Nms: float | None = None
    max_torque_Nm: float | None = None

    def __post_init__(self):
        self.masses.check_robot(self.robot)
        for name, key in (("max_momentum_Nms", "acs.max_wheel_momentum_Nms"),
                          ("max_torque_Nm", "acs.max_wheel_torque_Nm")):
            v = getattr(self, name)
            if v is not None and not (math.isfinite(v) and v >= 0.0):
                raise ValueError(f"{key}: must be a finite number ≥ 0 (0: no limit), got {v}")
            object.__setattr__(self, name, None if v is None or v == 0.0 else float(v))

    def path_terms(self, q_rad, dq_ds, d2q_ds2):
        """
        Return the wheel terms along a path q(s) of the planned joints ((G, dof) each).

        g = H·q′ (G,) and g′ = d(H·q′)/ds (G,), so h_wheel = −g ṡ and τ_wheel = −(g′ ṡ² + g s̈).
        """
        qf = self.robot.full(q_rad)
        d1 = _planned_rates(self.robot, dq_ds)
        d2 = _planned_rates(self.robot, d2q_ds2)
        g = angular_momentum_Nms(self.robot, self.masses, qf, d1)
        gp = momentum_rate_Nm(self.robot, self.masses, qf, d1, d2)
        return g, gp


def wheel_load(robot, masses: MassProperties, positions_rad, velocities_rad_s, accelerations_rad_s2):
    """
    Return the wheel momentum and torque at the points of a trajectory.

    Wheel momentum h_wheel = −H·q̇ (M,) N·m·s and torque dh_wheel/dt (M,) N·m at the points of a
    trajectory over the planned joints ((M, dof) each; locked joints at rest).
    """
    qf = robot.full(positions_rad)
    qd = _planned_rates(robot, velocities_rad_s)
    qdd = _planned_rates(robot, accelerations_rad_s2)
    return (-angular_momentum_Nms(robot, masses, qf, qd),
            -momentum_rate_Nm(robot, masses, qf, qd, qdd))


# ----------------------------------------------------------------- free floating
@dataclass(frozen=True, eq=False)
class FreeFloatingResponse:
    """
    The spacecraft's free-floating response along a joint path.

    Attributes
    ----------
        q_full_rad: (K, n) the configurations that happen: arm joints as planned, the
            attitude (joint 1) drifting (its planned motion, if any, is not executed).
        planned_q_full_rad: (K, n) the configurations as planned.
        body_position_m: (K, 2) spacecraft body centre in the planning (inertial) frame
            (0 at the start).
        attitude_change_deg: final minus initial attitude, degrees.
        body_displacement_m: |body_position_m[-1]|, metres.
        tip_m: (2,) where the tip ends in the inertial frame; planned_tip_m: where the
            plan puts it (body fixed, attitude as planned).
        tip_miss_m: |tip_m − grasp point| when a grasp point was given, else
            |tip_m − planned_tip_m|, metres.

    """

    q_full_rad: np.ndarray
    planned_q_full_rad: np.ndarray
    body_position_m: np.ndarray
    attitude_change_deg: float
    body_displacement_m: float
    tip_m: np.ndarray
    planned_tip_m: np.ndarray
    tip_miss_m: float

    @property
    def attitude_drift_rad(self) -> np.ndarray:
        """(K,) attitude that happens minus the planned one, rad."""
        return self.q_full_rad[:, 0] - self.planned_q_full_rad[:, 0]


def _attitude_rate_integrand(robot, masses, q_full, dq_full):
    """dθ1 along a step dq (arm joints) at q: −(Σ_{k>1} H_k dq_k) / H_1, rows (N,)."""
    h = momentum_map(robot, masses, q_full)
    return -np.einsum("...k,...k->...", h[..., 1:], dq_full[..., 1:]) / h[..., 0]


def free_floating_response(robot, masses: MassProperties, path_rad, grasp_point_m=None) -> FreeFloatingResponse:
    """
    Integrate the free-floating attitude and body translation along a planned path.

    Args:
        robot: the PlanarArm (joint 1 = attitude).
        masses: MassProperties for its links.
        path_rad: (K, dof) planned joints, unwrapped, start first; straight between rows.
        grasp_point_m: optional (2,) inertial grasp point for ``tip_miss_m``.

    Returns
    -------
        FreeFloatingResponse.

    """
    masses.check_robot(robot)
    planned = robot.full(np.atleast_2d(np.asarray(path_rad, dtype=float)))
    q = planned.copy()
    if len(q) > 1:
        step = np.diff(planned, axis=0)
        f = [_attitude_rate_integrand(robot, masses, planned[:-1] + w * step, step) for w in (0.0, 0.5, 1.0)]
        dtheta = (f[0] + 4.0 * f[1] + f[2]) / 6.0             # Simpson per segment
        q[:, 0] = planned[0, 0] + np.concatenate([[0.0], np.cumsum(dtheta)])
    com = system_com_m(robot, masses, q)
    body = com[0] - com
    tip = body[-1] + robot.tip_position(q[-1])
    planned_tip = robot.tip_position(planned[-1])
    ref = planned_tip if grasp_point_m is None else np.asarray(grasp_point_m, dtype=float)
    return FreeFloatingResponse(q, planned, body, float(np.degrees(q[-1, 0] - q[0, 0])),
                                float(np.linalg.norm(body[-1])), tip, planned_tip,
                                float(np.linalg.norm(tip - ref)))


@njit(cache=True, nogil=True)
def _drifted_clearance(q_full, body_pos, lengths, checked, body, verts, starts):
    """
    Return the clearance of each configuration in the drifted scene, (K,) m.

    Clearance of each configuration with the obstacles shifted by −body position (the inertial scene
    seen from the translated spacecraft body), (K,) m.
    """
    k_n = q_full.shape[0]
    out = np.empty(k_n)
    pts = np.empty((lengths.shape[0] + 1, 2))
    body_w = np.empty_like(body)
    shifted = np.empty_like(verts)
    for k in range(k_n):
        for v in range(verts.shape[0]):
            shifted[v, 0] = verts[v, 0] - body_pos[k, 0]
            shifted[v, 1] = verts[v, 1] - body_pos[k, 1]
        out[k] = config_clearance(q_full[k], lengths, checked, body, shifted, starts, pts, body_w)
    return out


@dataclass(frozen=True, eq=False)
class DriftCheck:
    """
    Inertial-frame check of the free-floating arm motion.

    Attributes
    ----------
        ok: the whole drifted motion keeps clearance > the scene's margin (certified
            between samples, see :func:`check_drifted`).
        min_clearance_m: smallest clearance at the samples, metres.
        first_collision_fraction: path fraction (0…1, by sample) of the first sample
            within the margin, None when none is.
        n_checked: configurations evaluated.

    """

    ok: bool
    min_clearance_m: float
    first_collision_fraction: float | None
    n_checked: int


def check_drifted(robot, masses: MassProperties, scene, path_rad, max_rounds: int = 12) -> DriftCheck:
    """
    Check the free-floating motion along ``path_rad`` against the inertially fixed scene.

    The spacecraft turns and translates (:func:`free_floating_response`), the target and
    debris do not; clearance is the exact segment–polygon distance of links 2… to the
    obstacles and to the (moving) body.  Between two samples every point of a checked
    link moves (relative to the obstacles and to the body) by at most
    δ = Σ_j |Δq_j| · reach_j + |Δb| (reach_j: chain length beyond joint j, b: body
    position), so an interval is certified when (c_a + c_b − δ)/2 > margin; otherwise
    it is split (the path is straight between its rows) and the drift recomputed.
    """
    chk = CollisionChecker(robot, scene)
    lengths = chk.lengths
    reach = np.cumsum(lengths[::-1])[::-1]
    p = np.atleast_2d(np.asarray(path_rad, dtype=float))
    margin = chk.margin_m
    n_eval = 0
    for _ in range(max_rounds + 1):
        resp = free_floating_response(robot, masses, p)
        c = _drifted_clearance(np.ascontiguousarray(resp.q_full_rad), np.ascontiguousarray(resp.body_position_m),
                               lengths, chk.checked, chk.body, chk.verts, chk.starts)
        n_eval += len(c)
        hit = np.flatnonzero(~(c > margin))
        if len(hit):
            return DriftCheck(False, float(c.min()), float(hit[0] / max(1, len(c) - 1)), n_eval)
        if len(p) < 2:
            return DriftCheck(True, float(c.min()), None, n_eval)
        delta = (np.abs(np.diff(resp.q_full_rad, axis=0)) @ reach
                 + np.linalg.norm(np.diff(resp.body_position_m, axis=0), axis=1))
        bad = np.flatnonzero(~(0.5 * (c[:-1] + c[1:] - delta) > margin))
        if not len(bad):
            return DriftCheck(True, float(c.min()), None, n_eval)
        mids = 0.5 * (p[bad] + p[bad + 1])
        p = np.insert(p, bad + 1, mids, axis=0)
    return DriftCheck(False, float(c.min()), None, n_eval)


# ---------------------------------------------------------------------- report
@dataclass(frozen=True, eq=False)
class ReactionReport:
    """
    The spacecraft's reaction to a planned motion (the CLI's ``reaction`` object).

    Attributes
    ----------
        acs_mode: "held" (wheels hold/command the attitude) or "free_floating".
        ok: False when the plan must be refused (free floating: the drifted arm
            collides or the tip misses by more than the tolerance; held: the wheel load
            exceeds a limit); reason says why.
        peak_wheel_momentum_Nms, peak_wheel_torque_Nm: largest |h_wheel|, |τ_wheel| over
            the trajectory (attitude held/commanded); None without a trajectory.
        max_wheel_momentum_Nms, max_wheel_torque_Nm: the limits (None: none).
        free_floating_attitude_change_deg, free_floating_body_displacement_m,
        free_floating_tip_miss_m: the free-floating response (see FreeFloatingResponse).
        free_floating_min_clearance_m, free_floating_collides: the inertial-frame check.
        held_body_displacement_m: how far the body translates with the attitude held
            (the CoM stays put either way), and held_tip_miss_m: the tip's miss that causes
            (vs the grasp point, else vs the planned tip).
        position_tolerance_m: grasp.position_tolerance_m.
        times_s, wheel_momentum_Nms, wheel_torque_Nm, free_floating_attitude_rad,
        planned_attitude_rad: (M,) series for plots (None without a trajectory; the
            attitudes per sample of the trajectory, else of the path).

    """

    acs_mode: str
    ok: bool
    reason: str | None
    peak_wheel_momentum_Nms: float | None
    peak_wheel_torque_Nm: float | None
    max_wheel_momentum_Nms: float | None
    max_wheel_torque_Nm: float | None
    free_floating_attitude_change_deg: float
    free_floating_body_displacement_m: float
    free_floating_tip_miss_m: float
    free_floating_min_clearance_m: float
    free_floating_collides: bool
    held_body_displacement_m: float
    held_tip_miss_m: float
    position_tolerance_m: float
    times_s: np.ndarray | None = None
    wheel_momentum_Nms: np.ndarray | None = None
    wheel_torque_Nm: np.ndarray | None = None
    free_floating_attitude_rad: np.ndarray | None = None
    planned_attitude_rad: np.ndarray | None = None

    def to_json_dict(self) -> dict:
        """Scalars only (plain JSON; None where not known)."""
        keys = ("acs_mode", "ok", "reason", "peak_wheel_momentum_Nms", "peak_wheel_torque_Nm",
                "max_wheel_momentum_Nms", "max_wheel_torque_Nm", "free_floating_attitude_change_deg",
                "free_floating_body_displacement_m", "free_floating_tip_miss_m",
                "free_floating_min_clearance_m", "free_floating_collides", "held_body_displacement_m",
                "held_tip_miss_m", "position_tolerance_m")
        out = {}
        for k in keys:
            v = getattr(self, k)
            if isinstance(v, float) and not math.isfinite(v):
                v = None
            out[k] = v
        return out


def reaction_report(robot, masses: MassProperties, scene, path_rad, trajectory=None, *,
                    acs_mode: str = "held", max_wheel_momentum_Nms: float | None = None,
                    max_wheel_torque_Nm: float | None = None, grasp_point_m=None,
                    position_tolerance_m: float = 0.02) -> ReactionReport:
    """
    Report the wheel load and free-floating response of a planned motion.

    Wheel load (attitude held) and free-floating response of a planned motion, and whether it is
    acceptable in the given ACS mode.

    Args:
        robot, masses, scene: the PlanarArm, its MassProperties, the Scene planned in.
        path_rad: (K, dof) the planned path (unwrapped).
        trajectory: optional ``trajectory.Trajectory`` over the planned joints: the wheel
            series and peaks come from it, and the free-floating response is taken
            along its positions (so the attitude series matches its times).
        acs_mode: "held" or "free_floating".
        max_wheel_momentum_Nms, max_wheel_torque_Nm: wheel limits (None or 0: none).
        grasp_point_m: (2,) the inertial grasp point (default: the scene target's, if any).
        position_tolerance_m: largest acceptable free-floating tip miss, metres.

    Returns
    -------
        ReactionReport.

    Raises
    ------
        ValueError: an unknown ``acs_mode`` (named ``acs.mode``), bad limits or masses.

    """
    if acs_mode not in ACS_MODES:
        raise ValueError(f"acs.mode: expected one of {', '.join(ACS_MODES)}, got {acs_mode!r}")
    if not (math.isfinite(position_tolerance_m) and position_tolerance_m >= 0.0):
        raise ValueError(f"grasp.position_tolerance_m: must be a finite number ≥ 0, got {position_tolerance_m}")
    wheel = WheelModel(robot, masses, max_wheel_momentum_Nms, max_wheel_torque_Nm)
    if grasp_point_m is None and scene.target is not None:
        grasp_point_m = scene.target.grasp_point_m
    along = trajectory.positions_rad if trajectory is not None else np.asarray(path_rad, dtype=float)
    resp = free_floating_response(robot, masses, along, grasp_point_m)
    drift = check_drifted(robot, masses, scene, along)
    com = system_com_m(robot, masses, robot.full(along))
    held_disp = float(np.linalg.norm(com[-1] - com[0]))
    held_tip = com[0] - com[-1] + robot.tip_position(robot.full(along[-1]))
    held_miss = float(np.linalg.norm(held_tip - (resp.planned_tip_m if grasp_point_m is None
                                                 else np.asarray(grasp_point_m, dtype=float))))
    times = h_w = tau_w = None
    peak_h = peak_tau = None
    if trajectory is not None:
        times = trajectory.times_s
        h_w, tau_w = wheel_load(robot, masses, trajectory.positions_rad, trajectory.velocities_rad_s,
                                trajectory.accelerations_rad_s2)
        peak_h, peak_tau = float(np.max(np.abs(h_w))), float(np.max(np.abs(tau_w)))
    reason = None
    if acs_mode == "free_floating":
        if not drift.ok:
            where = ("" if drift.first_collision_fraction is None
                     else f" at {100 * drift.first_collision_fraction:.0f} % of the path")
            reason = (f"free floating: the drifted arm comes within the safety margin of an obstacle or the "
                      f"body{where} (clearance {drift.min_clearance_m:.3f} m, margin {scene.safety_margin_m} m; "
                      f"attitude change {resp.attitude_change_deg:.2f}°, the tip would miss the grasp by "
                      f"{resp.tip_miss_m:.3f} m)")
        elif resp.tip_miss_m > position_tolerance_m:
            reason = (f"free floating: the tip misses the grasp by {resp.tip_miss_m:.3f} m > "
                      f"grasp.position_tolerance_m {position_tolerance_m} m (attitude change "
                      f"{resp.attitude_change_deg:.2f}°, body displacement {resp.body_displacement_m:.3f} m)")
    elif peak_h is not None:
        tol = 1.0 + 1e-6
        if wheel.max_momentum_Nms is not None and peak_h > wheel.max_momentum_Nms * tol:
            reason = f"wheel momentum peak {peak_h:.2f} N·m·s > acs.max_wheel_momentum_Nms {wheel.max_momentum_Nms}"
        elif wheel.max_torque_Nm is not None and peak_tau > wheel.max_torque_Nm * tol:
            reason = f"wheel torque peak {peak_tau:.3f} N·m > acs.max_wheel_torque_Nm {wheel.max_torque_Nm}"
    return ReactionReport(acs_mode, reason is None, reason, peak_h, peak_tau, wheel.max_momentum_Nms,
                          wheel.max_torque_Nm, resp.attitude_change_deg, resp.body_displacement_m,
                          resp.tip_miss_m, drift.min_clearance_m, not drift.ok, held_disp, held_miss,
                          float(position_tolerance_m), times, h_w, tau_w, resp.q_full_rad[:, 0],
                          resp.planned_q_full_rad[:, 0])


# ------------------------------------------------------------- scenario level
@dataclass(frozen=True, eq=False)
class Motion:
    """
    A planned path in time and the spacecraft's reaction to it.

    Attributes
    ----------
        trajectory: ``trajectory.Trajectory`` over the planned joints.
        reaction: ReactionReport (``reaction.ok`` False: refuse the plan, ``reaction.reason``).

    """

    trajectory: object
    reaction: ReactionReport

    def to_json_dict(self) -> dict:
        return {"trajectory": self.trajectory.to_json_dict(), "reaction": self.reaction.to_json_dict()}


def scenario_joint_limits(scenario):
    """
    Return the planned joints' limits and scalings (``Scenario.joint_limits``).

    (max velocity (dof,) rad/s, max acceleration (dof,) rad/s², velocity scaling, acceleration
    scaling); ValueError when the scenario states no joint limits.
    """
    limits = scenario.joint_limits
    if limits is None:
        raise ValueError("trajectory.max_velocity_deg_s, trajectory.max_acceleration_deg_s2: the scenario "
                         "states no joint limits (no trajectory)")
    vmax, amax = limits.planned(scenario.robot)
    return vmax, amax, limits.velocity_scaling, limits.acceleration_scaling


def plan_motion(scenario, path_rad, *, start_velocity_rad_s=None, start_path_speed=None) -> Motion:
    """
    Time-parameterise a planned path with the scenario's limits and report the reaction.

    The joint limits and scaling factors come from ``trajectory.*``; with ``acs.mode``
    held and a wheel limit set (``acs.max_wheel_*``), the wheel momentum and torque
    enter the time-optimal parameterisation.  The reaction report then says whether
    the plan is acceptable (free floating: the drifted arm is checked against the
    inertial scene and the tip miss against ``grasp.position_tolerance_m``).

    Args:
        scenario: ``config.Scenario`` (robot, scene, masses, acs, params).
        path_rad: (M, dof) the planned path (unwrapped, exact ends).
        start_velocity_rad_s, start_path_speed: a moving start (see
            ``trajectory.time_parameterize``); default at rest.

    Returns
    -------
        Motion(trajectory, reaction).

    Raises
    ------
        ValueError: bad limits or a start velocity the path cannot be followed with.

    """
    from .trajectory import time_parameterize
    robot, acs = scenario.robot, scenario.acs
    vmax, amax, vs, as_ = scenario_joint_limits(scenario)
    limits = (acs.max_wheel_momentum_Nms, acs.max_wheel_torque_Nm) if acs.mode == "held" else (None, None)
    wheel = WheelModel(robot, scenario.masses, *limits)
    traj = time_parameterize(path_rad, vmax, amax, robot.planned_names, velocity_scaling=vs,
                             acceleration_scaling=as_, start_velocity_rad_s=start_velocity_rad_s,
                             start_path_speed=start_path_speed, wheel=wheel)
    report = reaction_report(robot, scenario.masses, scenario.scene, path_rad, traj, acs_mode=acs.mode,
                             max_wheel_momentum_Nms=acs.max_wheel_momentum_Nms,
                             max_wheel_torque_Nm=acs.max_wheel_torque_Nm,
                             position_tolerance_m=acs.position_tolerance_m)
    return Motion(traj, report)


# ------------------------------------------------ free floating, compensated (stretch)
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


def _apparent_scene(scene, attitude_change_rad, body_position_m):
    """
    Return the inertial scene as the body sees it at the end of a free-floating motion.

    Turned by −Δθ1 about the body centre after the body moved by b.
    """
    from .scene import Scene, Target
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
    from .ik import grasp_ik
    from .planner import Planner
    robot, scene = scenario.robot, scenario.scene
    if scene.target is None:
        raise ValueError("plan_free_floating: the scene has no target (nothing to reach)")
    if 0 in robot.planned_joints:
        raise ValueError("robot.planned_joints: free floating, the attitude is not commanded; plan the arm "
                         "joints only (lock the attitude at its start value)")
    masses = scenario.masses if masses is None else masses
    tol = scenario.acs.position_tolerance_m if position_tolerance_m is None else float(position_tolerance_m)
    grasp = scene.target.grasp_point_m
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
        apparent = _apparent_scene(scene, math.radians(resp.attitude_change_deg), resp.body_position_m[-1])
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
