"""
The spacecraft's verdict on a planned motion: wheel load, free-floating drift, accept or refuse.

With the attitude held (reaction wheels on), the wheels' momentum and torque along the
trajectory against ``acs.max_wheel_*``.  Free floating (attitude control off), the
spacecraft turns and translates (``spacecraft.free_floating_response``) while the target
and the debris stay where they are: the arm is checked in the inertial frame
(:func:`check_drifted`) and the tip lands somewhere else than planned.
:func:`reaction_report` gathers both and says whether the plan is acceptable in the
scenario's ACS mode.  Physics: ``spacecraft.py``.  No ROS imports.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from .collision import CollisionChecker
from .ik import approach_error_rad
from .motion import MotionValidator, PathCheck
from .spacecraft import (ACS_MODES, MassProperties, WheelModel, free_floating_response, system_com_m,
                         wheel_load)

__all__ = ["DriftCheck", "DriftedValidator", "ReactionReport", "check_drifted", "reaction_report"]


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


def check_drifted(robot, masses: MassProperties, scene, path_rad, max_rounds: int = 12, motions=None,
                  response=None) -> DriftCheck:
    """
    Check the free-floating motion along ``path_rad`` against the inertially fixed scene.

    The spacecraft turns and translates (:func:`free_floating_response`), the target and
    debris do not; clearance is the exact segment–polygon distance of links 2… to the
    obstacles and to the (moving) body.  Between two samples every point of a checked
    link moves (relative to the obstacles and to the body) by at most
    δ = Σ_j |Δq_j| · reach_j + |Δb| (reach_j: chain length beyond joint j, b: body
    position), so an interval is certified when (c_a + c_b − δ)/2 > margin; otherwise
    it is split (the path is straight between its rows) and the drift recomputed.
    Stops at the first sample within the margin (:func:`_drift_walk`).

    ``motions``: the scene's ``motion.MotionValidator`` (its checker is used; one is made
    when None).  ``response``: :func:`free_floating_response` of ``path_rad`` when the caller
    has it (its first round; the grasp point does not enter the drift).
    """
    chk = CollisionChecker(robot, scene) if motions is None else motions.checker
    walk = _drift_walk(robot, masses, chk, np.atleast_2d(np.asarray(path_rad, dtype=float)), chk.margin_m,
                       max_rounds, response, stop_at_hit=True)
    return DriftCheck(walk.ok, walk.min_clearance_m, walk.first_hit_fraction, walk.n_checked)


@dataclass(frozen=True, eq=False)
class _DriftWalk:
    """:func:`_drift_walk`'s result: per interval of the given rows (M - 1,), per row (M,), overall."""

    ok: bool
    interval_ok: np.ndarray
    interval_clearance_m: np.ndarray
    vertex_clearance_m: np.ndarray
    min_clearance_m: float
    first_hit_fraction: float | None
    n_checked: int


def _drift_walk(robot, masses, chk, path, threshold_m: float, max_rounds: int, response=None,
                stop_at_hit: bool = False) -> _DriftWalk:
    """
    Certify the drifted motion through the rows of ``path`` (M, dof), interval by interval.

    :func:`check_drifted`'s rule, per interval of the given rows.
    Each round integrates the drift along the rows so far (:func:`free_floating_response`),
    evaluates their inertial clearance, fails the intervals with a row at or below
    ``threshold_m`` and splits those whose two ends' clearance balls do not overlap (the
    motion between them bounded by δ, above) at their middles; after ``max_rounds`` splits an
    interval still open fails.  ``stop_at_hit``: return at the first round with a row within
    the threshold (``first_hit_fraction``: that row's place among the rows then, 0…1).
    ``interval_clearance_m``: the least clearance at the rows in each interval (its two ends
    included), ``vertex_clearance_m`` the clearance at the given rows, both from the last round.
    """
    lengths = np.asarray(robot.link_lengths_m, dtype=float)
    reach = np.cumsum(lengths[::-1])[::-1]
    p, m = path, len(path)
    owner = np.arange(m)                  # each row's interval of the given rows (the last row: m - 1, none)
    given = np.arange(m)                  # where the given rows are among the rows
    failed = np.zeros(max(m - 1, 0), dtype=bool)
    n_eval, c, hit_fraction = 0, np.zeros(m), None
    for r in range(max_rounds + 1):
        resp = response if r == 0 and response is not None else free_floating_response(robot, masses, p)
        c = chk.clearance_shifted_m(resp.q_full_rad, resp.body_position_m)
        n_eval += len(c)
        hit = np.flatnonzero(~(c > threshold_m))
        if len(hit):
            hit_fraction = float(hit[0] / max(1, len(c) - 1)) if hit_fraction is None else hit_fraction
            if stop_at_hit:
                break
            # a row within the threshold fails its interval (a given row: both of its intervals)
            failed[owner[hit][owner[hit] < m - 1]] = True
            at_given = np.searchsorted(given, hit)
            on_given = (at_given < m) & (given[np.minimum(at_given, m - 1)] == hit)
            before = at_given[on_given] - 1
            failed[before[before >= 0]] = True
        if len(p) < 2:
            break
        delta = (np.abs(np.diff(resp.q_full_rad, axis=0)) @ reach
                 + np.linalg.norm(np.diff(resp.body_position_m, axis=0), axis=1))
        bad = np.flatnonzero(~(0.5 * (c[:-1] + c[1:] - delta) > threshold_m) & ~failed[owner[:-1]])
        if not len(bad):
            break
        if r == max_rounds:
            failed[owner[bad]] = True
            break
        mids = 0.5 * (p[bad] + p[bad + 1])
        p = np.insert(p, bad + 1, mids, axis=0)
        owner = np.insert(owner, bad + 1, owner[bad])
        given = given + np.searchsorted(bad, given, side="left")
    iv_clr = np.full(max(m - 1, 0), np.inf)
    if m > 1:
        rows = np.flatnonzero(owner < m - 1)
        np.minimum.at(iv_clr, owner[rows], c[rows])
        np.minimum(iv_clr, c[given[1:]], out=iv_clr)
    ok = hit_fraction is None and not failed.any()
    return _DriftWalk(bool(ok), ~failed, iv_clr, c[given].copy(), float(c.min()), hit_fraction, n_eval)


class DriftedValidator(MotionValidator):
    """
    A scene's motion validator for a free-floating spacecraft: :meth:`check` certifies in the inertial frame.

    The arm's joints move as the rows say and the spacecraft turns and translates as the
    momentum balance makes it (:func:`free_floating_response`, from the first row), while the
    target and the debris stay put (:func:`_drift_walk`, :func:`check_drifted`'s rule, per
    interval): what the chain's certification of the controller's motion must judge when
    nothing holds the attitude (``acs.mode: free_floating``), not the arm on a body held still.
    The segment tests the planning stages use (``segment_ok``, ``check_kept``, ...) would restart
    the drift at each segment: they raise here; the planning stages use the scene's own validator.
    """

    def __init__(self, motions: MotionValidator, masses: MassProperties, max_rounds: int = 12):
        super().__init__(motions.checker, motions.lower_rad, motions.upper_rad, motions.periodic, motions.step_rad)
        self.masses, self.max_rounds = masses, int(max_rounds)

    def check(self, path_rad, *, required_clearance_m: float | None = None, **_) -> PathCheck:
        """
        Certified check of the drifted motion through the rows of ``path_rad`` (M, planned joints), rad.

        ``motion.PathCheck`` per interval between the rows (every row checked: the drift
        integrates along all of them); bounded joints within their bounds at the rows.
        ``required_clearance_m``: a larger threshold than the margin.  The other arguments of
        ``MotionValidator.check`` (the walk's step, reused clearances, one walk past the rows)
        have no meaning here and are ignored.
        """
        p = self._rows(path_rad)
        threshold = self.margin_m if required_clearance_m is None else max(self.margin_m, required_clearance_m)
        walk = _drift_walk(self.robot, self.masses, self.checker, p, threshold, self.max_rounds)
        inside = self.within_bounds(p)
        interval_ok = walk.interval_ok & inside[:-1] & inside[1:]       # a row out of bounds fails its intervals
        ok = walk.ok and bool(inside.all())
        return PathCheck(ok, interval_ok, walk.min_clearance_m, walk.n_checked, walk.interval_clearance_m,
                         walk.vertex_clearance_m)

    def with_step(self, step_rad: float) -> "DriftedValidator":
        """Return itself: :meth:`check` evaluates every row (the drift integrates along all of them), no step."""
        return self

    def _planning_frame_only(self, *_, **__):
        raise NotImplementedError("DriftedValidator certifies whole paths from their first row (check); its segment "
                                  "tests would restart the drift at each segment: use the scene's MotionValidator")

    check_kept = segment_ok = first_bad_segment = segment_test = _planning_frame_only


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
        free_floating_approach_error_deg: at the end, the angle between link 3 (attitude
            drifted) and the handle's inward normal, degrees (nan without a target).
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
    free_floating_approach_error_deg: float = math.nan
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
                "held_tip_miss_m", "position_tolerance_m", "free_floating_approach_error_deg")
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
                    position_tolerance_m: float = 0.02, max_approach_error_deg: float | None = None,
                    motions=None) -> ReactionReport:
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
        max_approach_error_deg: free floating with a target: a tip within the tolerance must
            also meet the handle within this angle of its normal (a grasp), degrees; None:
            not judged.
        motions: the scene's ``motion.MotionValidator`` for the drift check (made when None).

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
    drift = check_drifted(robot, masses, scene, along, motions=motions, response=resp)
    com = system_com_m(robot, masses, robot.full(along))
    held_disp = float(np.linalg.norm(com[-1] - com[0]))
    held_tip = com[0] - com[-1] + robot.tip_position(robot.full(along[-1]))
    held_miss = float(np.linalg.norm(held_tip - (resp.planned_tip_m if grasp_point_m is None
                                                 else np.asarray(grasp_point_m, dtype=float))))
    approach = (math.degrees(approach_error_rad(robot, scene.target, resp.q_full_rad[-1]))
                if scene.target is not None else math.nan)
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
        elif max_approach_error_deg is not None and approach > max_approach_error_deg:
            reason = (f"free floating: the tip reaches the grasp point (miss {resp.tip_miss_m:.3f} m) but link 3 "
                      f"meets the handle {approach:.1f}° off its normal > grasp.max_approach_error_deg "
                      f"{max_approach_error_deg:g}° (attitude change {resp.attitude_change_deg:.2f}°): not a grasp")
    elif peak_h is not None:
        tol = 1.0 + 1e-6
        if wheel.max_momentum_Nms is not None and peak_h > wheel.max_momentum_Nms * tol:
            reason = f"wheel momentum peak {peak_h:.2f} N·m·s > acs.max_wheel_momentum_Nms {wheel.max_momentum_Nms}"
        elif wheel.max_torque_Nm is not None and peak_tau > wheel.max_torque_Nm * tol:
            reason = f"wheel torque peak {peak_tau:.3f} N·m > acs.max_wheel_torque_Nm {wheel.max_torque_Nm}"
    return ReactionReport(acs_mode, reason is None, reason, peak_h, peak_tau, wheel.max_momentum_Nms,
                          wheel.max_torque_Nm, resp.attitude_change_deg, resp.body_displacement_m,
                          resp.tip_miss_m, drift.min_clearance_m, not drift.ok, held_disp, held_miss,
                          float(position_tolerance_m), approach, times, h_w, tau_w, resp.q_full_rad[:, 0],
                          resp.planned_q_full_rad[:, 0])
