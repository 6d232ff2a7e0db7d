"""
The spacecraft's physics: mass properties, momentum map, wheel load, free-floating drift.

The planar chain of ``robot.py`` (joint 1 = the spacecraft attitude θ1, link 1 a rigid,
massless offset fixed in the body, links 2… the arm) is given masses: the spacecraft
body (mass, inertia about its centre, which is the chain's origin) and each link (mass
and inertia about its centre, at mid-link).  Positions here are relative to the
spacecraft body centre with inertial axes (the absolute angles φ_k = θ1 + … + θk);
the planning frame is the body-centred frame at the start of the motion.  Numbers: the
project's notes on the free-floating servicer (kept outside this repository; every number is
in ``config/servicer_3dof.yaml``).

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
  so that the CoM stays fixed: b = r̄(q(0)) − r̄(q) (:func:`free_floating_response`).

What the reaction means for a plan (the inertial-frame check of the drifted arm, the
verdict) is ``reaction.py``; planning for the drift is ``free_floating.py``.

Units: kg, kg·m², m, rad, s; momentum N·m·s, torque N·m.  NumPy, and numba for the momentum sums
(:func:`angular_momentum_Nms`, :func:`momentum_rate_Nm`, :func:`momentum_map`: one pass per sample
instead of stacked (N, n+1, 2) arrays; ``worker --warm-cache`` fills their cache: it runs the chain
with the reaction on); no geometry, no ROS.
"""

from __future__ import annotations

import functools
import math
import numbers
from dataclasses import dataclass

import numpy as np
from numba import njit

__all__ = ["MassProperties", "AcsSettings", "WheelModel", "FreeFloatingResponse", "ACS_MODES", "system_com_m",
           "angular_momentum_Nms", "momentum_rate_Nm", "momentum_map", "wheel_load", "free_floating_response",
           "free_floating_rates"]

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
        wheel_momentum_scaling, wheel_torque_scaling: the fractions of the wheel limits the time
            parameterisation keeps to along the whole path (not parameters: the chain after the
            path lowers them, with the joint limits' scaling factors, from its fourth re-timing on
            (up to three times) when lowered stretches (``JointLimits.lowered``) have not brought
            the controller's motion within the limits, and ``replanning.stopping_join`` for room to
            brake); the reaction's verdict judges the limits themselves.

    """

    mode: str = "held"
    max_wheel_momentum_Nms: float = 0.0
    max_wheel_torque_Nm: float = 0.0
    position_tolerance_m: float = 0.02
    compensate_drift: bool = False
    wheel_momentum_scaling: float = 1.0
    wheel_torque_scaling: float = 1.0

    @property
    def timed_wheel_limits(self) -> tuple:
        """(momentum N·m·s, torque N·m) the time parameterisation keeps to: None, None unless the attitude is held."""
        if self.mode != "held":
            return None, None
        return (self.max_wheel_momentum_Nms * self.wheel_momentum_scaling,
                self.max_wheel_torque_Nm * self.wheel_torque_scaling)

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


def _bodies(robot, masses, q_full):
    """
    Return the centres of the body and the links, and the masses.

    Centres (..., n+1, 2) of the body (row 0, at the origin) and the links (``"r"``), the
    masses (``"m"``, (n+1,)).
    """
    cl, m, _ = _tables(robot, masses)
    q = np.asarray(q_full, dtype=float)
    phi = np.cumsum(q, axis=-1)
    e = np.stack([np.cos(phi), np.sin(phi)], axis=-1)
    links = np.einsum("kj,...jd->...kd", cl, e)
    return {"r": np.concatenate([np.zeros(q.shape[:-1] + (1, 2)), links], axis=-2), "m": m}


def system_com_m(robot, masses: MassProperties, q_full) -> np.ndarray:
    """
    System centre of mass relative to the spacecraft body centre, inertial axes.

    q_full: (n,) or (N, n) rad → (2,) or (N, 2) m.
    """
    b = _bodies(robot, masses, q_full)
    return np.einsum("b,...bd->...d", b["m"], b["r"]) / b["m"].sum()


@functools.lru_cache(maxsize=32)
def _momentum_tables(robot, masses):
    """
    Return (pair (n, n), inertia (n,)): the angular momentum's coefficients, the one rule of it.

    With φ the absolute angles (the joint angles' running sums), e_k = (cos φ_k, sin φ_k) and the
    link centres r_b = Σ_k a[b, k] e_k (``_tables``; the body's centre, row 0, at the origin):
    h = Σ_b m_b (r_b − r̄) × (ṙ_b − r̄̇) + Σ I φ̇ = Σ_ij pair[i, j] cos(φ_i − φ_j) φ̇_j + Σ_j inertia[j] φ̇_j,
    pair = aᵀ diag(m) a − (aᵀm)(aᵀm)ᵀ / Σm (symmetric) and inertia the links' with the body's
    on the first (the body turns with φ_1).  Kept per robot and masses (every timing and check of a
    chain asks): read them, never write them.
    """
    cl, m, inertia_b = _tables(robot, masses)
    a = np.vstack([np.zeros((1, cl.shape[1])), cl])
    ma = m @ a
    pair = a.T @ (m[:, None] * a) - np.outer(ma, ma) / m.sum()
    inertia = inertia_b[1:].copy()
    inertia[0] += inertia_b[0]
    return np.ascontiguousarray(pair), inertia


@njit(cache=True, nogil=True, inline="always")
def _momentum_coefficients(pair, inertia, q, w):
    """
    Fill w (4, n) at the sample q (n,) full joints: w[0], w[1] cos, sin of φ − φ_1; w[2] A; w[3] B.

    A_j = inertia[j] + Σ_i pair[i, j] C_ij and B_j = Σ_i pair[i, j] S_ij with C_ij = cos(φ_i − φ_j),
    S_ij = sin(φ_i − φ_j) (:func:`_momentum_tables`): h = Σ_j A_j φ̇_j and dh/dt = Σ_j (A_j φ̈_j + B_j φ̇_j²)
    (the terms in φ̇_i φ̇_j, i ≠ j, cancel: S is antisymmetric, pair symmetric).  Each pair i < j once.
    Inlined where it is called, as the two rows below (a compiled call passed array views and their
    reference counts at every sample: the capture's scans took 2.6 times as long, the same bits).
    """
    n = q.shape[0]
    psi = 0.0                       # φ_j − φ_1: the differences alone matter (no sine of the attitude)
    for j in range(n):
        if j > 0:
            psi += q[j]
        w[0, j] = np.cos(psi) if j > 0 else 1.0
        w[1, j] = np.sin(psi) if j > 0 else 0.0
        w[2, j] = inertia[j] + pair[j, j]
        w[3, j] = 0.0
    for j in range(1, n):
        cj, sj = w[0, j], w[1, j]
        for i in range(j):
            p = pair[i, j]
            pc = p * (w[0, i] * cj + w[1, i] * sj)
            ps = p * (w[1, i] * cj - w[0, i] * sj)
            w[2, j] += pc
            w[2, i] += pc
            w[3, j] += ps
            w[3, i] -= ps


@njit(cache=True, nogil=True, inline="always")
def _sample_momentum(pair, inertia, q, qd, qdd, w):
    """
    (h, dh/dt) of one sample: q, qd, qdd (n,) full joints (qdd None: no rate, 0.0); w (4, n) scratch.

    :func:`_momentum_coefficients` and the absolute rates φ̇, φ̈ (the joint rates' running sums).
    """
    _momentum_coefficients(pair, inertia, q, w)
    h = rate = 0.0
    pd = pdd = 0.0
    for j in range(q.shape[0]):
        pd += qd[j]
        h += w[2, j] * pd
        if qdd is not None:
            pdd += qdd[j]
            rate += w[2, j] * pdd + w[3, j] * pd * pd
    return h, rate


@njit(cache=True, nogil=True)
def _momentum_rows(pair, inertia, q, qd, qdd, with_rate):
    """(h (N,), dh/dt (N,)) of the rows of q, qd, qdd (N, n); dh/dt zeros unless ``with_rate``."""
    w = np.empty((4, q.shape[1]))
    h = np.empty(q.shape[0])
    rate = np.zeros(q.shape[0])
    for i in range(q.shape[0]):
        if with_rate:
            h[i], rate[i] = _sample_momentum(pair, inertia, q[i], qd[i], qdd[i], w)
        else:
            h[i], _ = _sample_momentum(pair, inertia, q[i], qd[i], None, w)
    return h, rate


@njit(cache=True, nogil=True, inline="always")
def _momentum_map_row(pair, inertia, q, w, h):
    """Fill h (n,) with the momentum map's row at q (n,) full joints: H_k = Σ_{j ≥ k} A_j (w (4, n) scratch)."""
    _momentum_coefficients(pair, inertia, q, w)
    acc = 0.0
    for k in range(q.shape[0] - 1, -1, -1):
        acc += w[2, k]
        h[k] = acc


@njit(cache=True, nogil=True)
def _momentum_map_rows(pair, inertia, q):
    """H (N, n) of the rows of q (N, n): row i, column k is h at q[i] with unit rate of joint k."""
    nq, n = q.shape
    w = np.empty((4, n))
    out = np.empty((nq, n))
    for i in range(nq):
        _momentum_map_row(pair, inertia, q[i], w, out[i])
    return out


def _rows(*arrays):
    """Broadcast (..., n) arrays together; return their leading shape and (N, n) contiguous rows."""
    b = np.broadcast_arrays(*[np.asarray(x, dtype=float) for x in arrays])
    shape = b[0].shape[:-1]
    return shape, [np.ascontiguousarray(x.reshape(-1, x.shape[-1])) for x in b]


def _shaped(x, shape):
    """Rows (N,) back to the leading shape (a NumPy scalar for a single sample)."""
    return x.reshape(shape) if shape else x[0]


def angular_momentum_Nms(robot, masses: MassProperties, q_full, qd_full) -> np.ndarray:
    """Return h = Σ m (r − r̄) × (ṙ − r̄̇) + Σ I φ̇ about the system CoM: (...,) N·m·s."""
    pair, inertia = _momentum_tables(robot, masses)
    shape, (q, qd) = _rows(q_full, qd_full)
    h, _ = _momentum_rows(pair, inertia, q, qd, qd, False)
    return _shaped(h, shape)


def momentum_rate_Nm(robot, masses: MassProperties, q_full, qd_full, qdd_full) -> np.ndarray:
    """dh/dt = Σ m (r − r̄) × (r̈ − r̄̈) + Σ I φ̈ (the cross term ṙ × ṙ vanishes): (...,) N·m."""
    pair, inertia = _momentum_tables(robot, masses)
    shape, (q, qd, qdd) = _rows(q_full, qd_full, qdd_full)
    _, rate = _momentum_rows(pair, inertia, q, qd, qdd, True)
    return _shaped(rate, shape)


def momentum_map(robot, masses: MassProperties, q_full) -> np.ndarray:
    """Return the row H(q) with h = H · q̇: (n,) or (N, n), N·m·s per rad/s (kg·m²)."""
    pair, inertia = _momentum_tables(robot, masses)
    q = np.asarray(q_full, dtype=float)
    rows = _momentum_map_rows(pair, inertia, np.ascontiguousarray(q.reshape(-1, q.shape[-1])))
    return rows.reshape(q.shape)


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
        pair, inertia = _momentum_tables(self.robot, self.masses)
        shape, (qf, d1, d2) = _rows(self.robot.full(q_rad), _planned_rates(self.robot, dq_ds),
                                    _planned_rates(self.robot, d2q_ds2))
        g, gp = _momentum_rows(pair, inertia, qf, d1, d2, True)        # both in one pass
        return _shaped(g, shape), _shaped(gp, shape)


def wheel_load(robot, masses: MassProperties, positions_rad, velocities_rad_s, accelerations_rad_s2):
    """
    Return the wheel momentum and torque at the points of a trajectory.

    Wheel momentum h_wheel = −H·q̇ (M,) N·m·s and torque dh_wheel/dt (M,) N·m at the points of a
    trajectory over the planned joints ((M, dof) each; locked joints at rest).
    """
    pair, inertia = _momentum_tables(robot, masses)
    shape, (qf, qd, qdd) = _rows(robot.full(positions_rad), _planned_rates(robot, velocities_rad_s),
                                 _planned_rates(robot, accelerations_rad_s2))
    h, rate = _momentum_rows(pair, inertia, qf, qd, qdd, True)        # both in one pass
    return -_shaped(h, shape), -_shaped(rate, shape)


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
        joint_names: the robot's joints (the columns of ``q_full_rad``).

    """

    q_full_rad: np.ndarray
    planned_q_full_rad: np.ndarray
    body_position_m: np.ndarray
    attitude_change_deg: float
    body_displacement_m: float
    tip_m: np.ndarray
    planned_tip_m: np.ndarray
    tip_miss_m: float
    joint_names: tuple = ()

    @property
    def attitude_drift_rad(self) -> np.ndarray:
        """(K,) attitude that happens minus the planned one, rad."""
        return self.q_full_rad[:, 0] - self.planned_q_full_rad[:, 0]


def free_floating_rates(robot, masses: MassProperties, q_full, qd_planned) -> tuple:
    """
    Return the free-floating attitude rate and body velocity where the arm moves at ``qd_planned``.

    q_full: (K, n) the configurations that happen (the attitude as it drifts); qd_planned: (K, dof)
    the planned joints' rates (the attitude's own, where it is planned, is not executed: not read;
    locked joints do not move).  θ̇1 = −(Σ_{k>1} H_k q̇_k) / H_1; the body centre moves opposite
    the system centre of mass relative to it (which stays put): −d/dt :func:`system_com_m`.
    Returns ((K,) rad/s, (K, 2) m/s); 0 where the arm is at rest.
    """
    q = np.asarray(q_full, dtype=float)
    qd = _planned_rates(robot, qd_planned)
    qd[..., 0] = _attitude_rate_integrand(robot, masses, q, qd)
    cl, m, _ = _tables(robot, masses)
    phi = np.cumsum(q, axis=-1)
    phid = np.cumsum(qd, axis=-1)
    e_perp = np.stack([-np.sin(phi), np.cos(phi)], axis=-1) * phid[..., None]      # d e_j / dt
    com_rate = np.einsum("k,kj,...jd->...d", m[1:], cl, e_perp) / m.sum()        # the body's centre: 0 in it
    return qd[..., 0], -com_rate


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
                                float(np.linalg.norm(tip - ref)), tuple(robot.joint_names))
