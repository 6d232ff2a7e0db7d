"""
The chain after the path: what a planned path becomes before it is published.

MoveIt's planning adapters in one function, :func:`post_process`, which the capture
session (``session.py``: the node) and ``spacerobot-plan`` both run, so the CLI's JSON
carries the very trajectory the node publishes:

1. **time** -- the path in time under the scenario's joint limits, from rest
   (``timing.timed_motion``) or joined to the executing trajectory
   (``replanning.joined_motion``: from the join, through the horizon point; when the
   executing trajectory ends within the lead, or the session retries from its end, from
   rest at that end, stamped no earlier than it: :func:`starts_at_the_end`);
2. **reaction** -- the spacecraft's verdict on it (free floating, wheel limits); a refused
   trajectory stops the chain (``Processed.refused``);
3. **resample and certify** -- a subset of the dense points at most ``time_step_s``
   apart and within 0.1° of the dense path; the motion the controller makes of them (its
   quintics, sampled: ``published.controller_check``) certified on the exact geometry with
   the scene's ``motion.MotionValidator`` (``published.resample``); when that certification
   fails the dense trajectory is kept;
4. **the controller's motion** -- joint_trajectory_controller interpolates the published
   points (quintic segments), which overshoots the time-optimal profile's piecewise-constant
   accelerations by up to about a quarter (and, the attitude held, a wheel torque limit by up to
   about a third): that motion is sampled (:func:`segment_overshoots`,
   :func:`controller_overshoot`) and, where it exceeds a limit, steps 1 to 3 run again with
   that limit lowered by the overshoot along the stretch where it happened (the segment and its
   neighbours: ``trajectory.Lowering``; the rest of the path keeps its limits, and a joined arm
   keeps its speed), within the limits as the arm really moves; a joined plan's
   paths (the corner and its blends) are made once and the re-timings time the one the first
   round chose (the others only when it cannot be entered at the arm's speed); every path's
   spline model is made once for all rounds (``trajectory.shared_path_models``);
5. **split** -- the attitude joint (the robot's first, the spacecraft's) for the attitude
   control system, the arm joints for the arm's controller (:class:`TrajectoryPart`,
   None for a group that is not planned); both None when nothing moves more than
   ``AT_GOAL_TOL_RAD`` (at the goal: nothing to publish).  Free floating
   (``acs.mode: free_floating``) nothing commands the attitude: no attitude part, and
   ``Processed.predicted_drift`` holds the attitude as it will drift and the body's
   displacement at the published points' times (:func:`predicted_drift`).

No rclpy here; times are seconds from the trajectory's start, ROS times integer ns.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from .motion import MotionValidator
from .published import (BOUND_SLACK_RAD, Resampled, controller_check, past_bounds, resample, sample_points,
                        segment_peaks, segment_wheel_peaks)
from .reaction import DriftedValidator
from .replanning import START_LEAD_S, Executing, joined_paths, plan_start, rests_at, timed_join
from .settings import SessionSettings
from .spacecraft import free_floating_rates, free_floating_response
from .timing import reaction_matters, reaction_of, timed_motion
from .trajectory import Lowering, Trajectory, lowering_factors, shared_path_models

__all__ = ["TrajectoryPart", "Processed", "post_process", "split_parts", "predicted_drift", "starts_at_the_end",
           "switching_at_arrival", "AFTER_THE_END_S", "HOLD_S", "held", "certifying",
           "controller_overshoot", "controller_wheel_overshoot", "overshot_stretches", "segment_overshoots",
           "braking_allowance", "braking_text",
           "RESAMPLE_STEP_S", "AT_GOAL_TOL_RAD", "warm_up"]

#: published trajectories keep a point at least this often (plus where the path bends), s
RESAMPLE_STEP_S = 0.25
#: a plan whose joints all move less than this is at the goal: nothing is published, rad
AT_GOAL_TOL_RAD = 1e-4
#: a goal where the arm rests on the trajectory it follows, which then goes on, is held this long (:func:`held`), s
HOLD_S = 0.1
#: the controller's interpolation may exceed a limit by this fraction (sampling of its peak)
CONTROLLER_TOL = 1e-3
#: when the controller's motion overshoots, the first CONTROLLER_RETIMES - 1 re-timings lower the limits
#: along the stretches where it did ...
CONTROLLER_RETIMES = 4
#: ... and the next ones along the whole path, at most this many of them (with one, a from-rest chain
#: on 100 random 3-DOF scenes of `bench scenes`' family published up to 1.104 x a limit, 2 of them
#: over; 2-DOF 1.025 x, 5 over; with three, none: at most 1.0010 x after up to six re-timings)
WHOLE_PATH_RETIMES = 3
#: ... and for a stop on the executing path (``replanning.stopping_join``), this many: its first point has the
#: arm's acceleration, which no re-timing changes, and the quintic from there to the braking shrinks its
#: overshoot about by half a round (closed-loop audit replay, 3.55 s: 1.87, 1.28, 1.14, ... 1.016 x after 6)
STOP_WHOLE_PATH_RETIMES = 6
#: each re-timing lowers a limit a little more than its overshoot there (converges in 1-2)
CONTROLLER_SHRINK = 0.99
#: ... and tapers the lowering back to the full limit by this fraction of the limit per segment
LOWERING_TAPER = 0.0025


@dataclass(frozen=True, eq=False)
class TrajectoryPart:
    """
    The points sent to one controller: some joints of a published trajectory.

    Attributes
    ----------
        joint_names: the joints (columns), in the robot's order.
        times_s: (K,) from the trajectory's start (its stamp), s.
        positions_rad, velocities_rad_s, accelerations_rad_s2: (K, len(joint_names)).

    """

    joint_names: tuple
    times_s: np.ndarray
    positions_rad: np.ndarray
    velocities_rad_s: np.ndarray
    accelerations_rad_s2: np.ndarray

    @classmethod
    def of(cls, traj: Trajectory, joints) -> "TrajectoryPart | None":
        """Return the columns of ``traj`` named in ``joints`` (None when there are none)."""
        cols = [i for i, n in enumerate(traj.joint_names) if n in joints]
        if not cols:
            return None
        return cls(tuple(traj.joint_names[i] for i in cols), traj.times_s.copy(), traj.positions_rad[:, cols],
                   traj.velocities_rad_s[:, cols], traj.accelerations_rad_s2[:, cols])

    @property
    def duration_s(self) -> float:
        return float(self.times_s[-1])

    def to_json_dict(self) -> dict:
        return {"joint_names": list(self.joint_names), "times_s": self.times_s.tolist(),
                "positions_rad": self.positions_rad.tolist(), "velocities_rad_s": self.velocities_rad_s.tolist(),
                "accelerations_rad_s2": self.accelerations_rad_s2.tolist()}


def split_parts(traj: Trajectory, attitude_joint: str, hold: bool = False) -> tuple:
    """
    Return (arm part, attitude part) of a trajectory to publish: the at-goal rule and the split.

    Both None when no joint moves more than ``AT_GOAL_TOL_RAD`` from start to end (unless
    ``hold``: a trajectory that holds the arm, :func:`held`).  A group that does not move while
    the other does still gets its (holding) part, which replaces an older trajectory still
    running on its controller.
    """
    q = np.asarray(traj.positions_rad)
    if not hold and float(np.max(np.abs(q[-1] - q[0]))) <= AT_GOAL_TOL_RAD:
        return None, None
    others = [n for n in traj.joint_names if n != attitude_joint]
    return TrajectoryPart.of(traj, others), TrajectoryPart.of(traj, [attitude_joint])


def held(traj: Trajectory) -> Trajectory:
    """
    Return a trajectory that holds the arm at ``traj``'s first point, at rest: there, and again :data:`HOLD_S` later.

    For a goal where the arm comes to rest on the trajectory it follows, which then goes on (a
    stop it was sent with, or its first point, not begun): nothing moves, yet a message must
    replace that trajectory there, or the arm would follow it on.  Two points, so that every
    controller takes it as a trajectory (times increasing, the last after the stamp).
    """
    two = traj.subset([0, 0])
    zero = np.zeros_like(two.velocities_rad_s)
    return replace(two, times_s=np.array([0.0, HOLD_S]), velocities_rad_s=zero, accelerations_rad_s2=zero.copy())


@dataclass(frozen=True, eq=False)
class Processed:
    """
    What :func:`post_process` made of a path.

    Attributes
    ----------
        dense: the time-parameterised trajectory (every sample; its polyline is the path
            the collision checks certified).
        trajectory: the points to publish (``dense`` resampled; ``dense`` itself when the
            resampled polyline could not be certified, or when refused).
        indices: (K,) their indices in ``dense``.
        certified: the published polyline passed the exact-geometry check.
        min_clearance_m: its clearance, m: the least at the check's samples of the controller's motion
            (``published.controller_check``; where not certified, the check's up to where it failed;
            nan when not checked).
        reaction: ``reaction.ReactionReport`` or None (not reported for this scenario).
        arm, attitude: the :class:`TrajectoryPart` of each controller (see :func:`split_parts`).
        join_stamp_ns: ROS time of the trajectory's start when joined to an executing one
            (its stamp: the join), None from rest (stamped when published; for a plan
            given a join, from the executing trajectory's end, which it reaches first).
        continuation: the ``trajectory.Continuation`` of a join, else None.
        not_before_ns: from rest at the executing trajectory's end: ``AFTER_THE_END_S`` after that end
            (ROS time, ns), the earliest stamp (see :func:`starts_at_the_end`); else None.
        stamp_exact: from rest where the executing trajectory stops before its end (a stop an
            earlier plan sent, or its first point, not begun): the stamp is ``not_before_ns``
            exactly, as the arm leaves that point after it (later: plan again); False otherwise.
        predicted_drift: free floating: :func:`predicted_drift` at the published points (not
            published: nothing commands the attitude); else None.
        retimings: how many times the path was timed again because the controller's motion of
            the points overshot a limit (step 4; 0: the first timing was kept).

    """

    dense: Trajectory
    trajectory: Trajectory
    indices: np.ndarray
    certified: bool
    min_clearance_m: float
    reaction: object
    arm: TrajectoryPart | None
    attitude: TrajectoryPart | None
    join_stamp_ns: int | None = None
    continuation: object = None
    not_before_ns: int | None = None
    predicted_drift: TrajectoryPart | None = None
    stamp_exact: bool = False
    retimings: int = 0

    @property
    def refused(self) -> str | None:
        """Return the spacecraft's reason to refuse the trajectory, or None."""
        if self.reaction is not None and not self.reaction.ok:
            return self.reaction.reason
        return None

    @property
    def fixed_stamp_ns(self) -> int | None:
        """Return the stamp it must have, ROS ns: a join's, or a stop's (``stamp_exact``); None: when published."""
        if self.join_stamp_ns is not None:
            return int(self.join_stamp_ns)
        return int(self.not_before_ns) if self.stamp_exact else None

    @property
    def at_goal(self) -> bool:
        """Tell whether nothing moves (nothing to publish)."""
        return self.arm is None and self.attitude is None and self.refused is None

    def to_json_dict(self) -> dict:
        """
        Return the published trajectory as plain JSON.

        ``joint_trajectory`` (arm) and ``attitude_trajectory`` parts, as the node publishes them
        (null when not published), ``predicted_drift`` (free floating), ``at_goal``, ``certified``,
        ``min_clearance_m``, and the dense point count.
        """
        clr = self.min_clearance_m
        return {"joint_trajectory": None if self.arm is None else self.arm.to_json_dict(),
                "attitude_trajectory": None if self.attitude is None else self.attitude.to_json_dict(),
                "predicted_drift": (None if self.predicted_drift is None
                                    else self.predicted_drift.to_json_dict()),
                "at_goal": self.at_goal, "certified": bool(self.certified),
                "min_clearance_m": None if not np.isfinite(clr) else float(clr),
                "points": len(self.trajectory), "dense_points": len(self.dense)}


#: a plan from the executing trajectory's end starts this long after that end, s: its first point
#: and the old last one are both at rest but with their own accelerations (the time-optimal
#: profiles': braking into the end, speeding up out of it), and a controller that splices the
#: two messages (joint_trajectory_controller's blend after 6.9.0, ros2_controllers #2419, or the points in front for
#: one that switches at arrival) would otherwise give the old last segment the new acceleration
#: at its end (a re-run audit measured 1.045 × the elbow's limit there); over the gap the
#: controller's quintic between the two states stays within their accelerations
AFTER_THE_END_S = 1e-3


def starts_at_the_end(join, now_ns: int, lead_s: float, from_end_at_rest: bool = False) -> int | None:
    """
    Return when a plan starting where the executing trajectory comes to rest may start (ROS time, ns), else None.

    The plan starts at a point where the arm comes to rest on the trajectory it follows
    (``join.horizon_index``: its last point, or a stop an earlier plan sent there,
    ``replanning.rests_at``) and either that point is less than ``lead_s`` after ``now_ns`` (no
    join can be the lead ahead), or the join stops there before the trajectory's end
    (``join.stop``: the session's stop on the executing path, ``replanning.stopping_join``, which
    never brakes past such a point; a stop at the end is braked to it, and where that does not fit
    the limits the session retries from the end), or ``from_end_at_rest`` (the session's retry
    from the end, after a join missed its time).  The arm comes to rest there on the trajectory
    it follows, so the new one starts there from rest, stamped :data:`AFTER_THE_END_S` after it
    (at the trajectory's first point, not begun, at its very stamp: no segment of it comes
    before; at its end, no earlier than that and the lead after it is published): a stamp the
    chain's own time cannot overtake.  None: a join (through the horizon point without stopping,
    or braked to it).
    """
    ex, h = join.executing, join.horizon_index
    if not rests_at(ex, h):
        return None
    rest_ns = ex.start_ns + int(round(float(ex.trajectory.times_s[h]) * 1e9))
    stop_before_end = join.stop and h < len(ex.trajectory) - 1
    if from_end_at_rest or stop_before_end or rest_ns <= int(now_ns) + int(round(lead_s * 1e9)):
        # at its first point (not begun) no segment of it comes before the new one: its very stamp
        return rest_ns + (0 if h == 0 < len(ex.trajectory) - 1 else int(round(AFTER_THE_END_S * 1e9)))
    return None


def post_process(scenario, path_rad, *, start_rad=None, join=None, now_ns: int = 0, lead_s: float = START_LEAD_S,
                 motions: MotionValidator | None = None, time_step_s: float = RESAMPLE_STEP_S,
                 from_end_at_rest: bool = False) -> Processed:
    """
    Run the chain after the path (see the module docstring).

    Args:
        scenario: ``problem.Scenario`` (joint limits, spacecraft, scene).
        path_rad: (M, dof) the planned path.
        start_rad: (dof,) the arm's state from rest (periodic joints as measured: the path is
            shifted by whole turns to start there); ignored when joined.
        join: a ``replanning.Join`` (the plan started on the executing trajectory), or None.
        now_ns: ROS time now (for a join), ns.
        lead_s: a join is at least this far after ``now_ns``, s.
        motions: the scene's MotionValidator (made when None), for the certification, the
            corner blends of a join and the reaction's drift check.
        time_step_s: largest time between published points, s.
        from_end_at_rest: (joined at the executing trajectory's end) start there from rest,
            stamped no earlier than that end, instead of joining (:func:`starts_at_the_end`).

    Returns
    -------
        Processed.

    Raises
    ------
        trajectory.HorizonPassed: (joined) the arm is already past the horizon point.
        ValueError: no or bad joint limits; (joined) the new path cannot be entered at the
            arm's speed.

    """
    with shared_path_models():          # the re-timings time the same paths: each modelled once
        return _post_process(scenario, path_rad, start_rad, join, now_ns, lead_s, motions, time_step_s,
                             from_end_at_rest)


def warm_up(scenario) -> None:
    """
    Load the chain's kernels (numba's cache, else compiled) before a user's plan meets them: two chains.

    One from rest along a straight path through the middle of the joint ranges (and a refusal's
    text of the bounds on its trajectory), and one joined to it while the arm moves
    (``replanning.plan_start`` with the session's defaults, the arm on the trajectory; a new path
    from the join on to the first's end, a little off it): a joined replan's own kernels (the start
    tangent's spline, the joins' turns) otherwise loaded in the middle of the first joined replan
    (paper_3dof: 9.3 ms against 2.6 for the next, 3.2 after this warm-up).
    Raises ValueError when the scenario's limits refuse the first chain (every plan's chain would
    refuse too); the joined chain's own refusals are no matter here.
    """
    robot = scenario.robot
    lo, hi = robot.planned_lower_rad, robot.planned_upper_rad
    first = post_process(scenario, np.linspace(lo + 0.25 * (hi - lo), lo + 0.75 * (hi - lo), 8))
    _past_bounds_text(scenario, first.trajectory)      # a refusal's kernel (published.past_bounds)
    dense = first.dense
    if len(dense) < 2:
        return
    ex = Executing(dense, np.asarray(first.indices), 0)
    now = int(0.3e9 * dense.duration_s)
    q = ex.expected_at(now)
    s = SessionSettings()
    start, join, _ = plan_start(ex, now, q, now, s.horizon_s, s.follow_tolerance_rad, robot.planned_periodic)
    if join is None:
        return
    end = np.clip(dense.positions_rad[-1] + 0.02 * (hi - lo), lo, hi)
    try:
        post_process(scenario, np.linspace(start, end, 6), join=join, now_ns=now, lead_s=0.0)
    except ValueError:
        pass


def _post_process(scenario, path_rad, start_rad, join, now_ns, lead_s, motions, time_step_s,
                  from_end_at_rest) -> Processed:
    """:func:`post_process`'s chain (its arguments, in order)."""
    motions = motions or MotionValidator.for_scene(scenario.robot, scenario.scene)
    if len(motions.periodic) != np.shape(path_rad)[-1]:
        raise ValueError(f"motions: a validator of {len(motions.periodic)} planned joints for a path of "
                         f"{np.shape(path_rad)[-1]} (the scenario's own validator expected)")
    # a join's paths (the continuation, the corner and its certified blends) do not depend on the
    # limits: made once, the re-timings only time them (HorizonPassed: the arm is past the horizon)
    paths = None
    if join is not None and starts_at_the_end(join, now_ns, lead_s, from_end_at_rest) is None:
        paths = joined_paths(scenario, join, path_rad, now_ns, lead_s, motions)
    # the published points' motion certified in the frame the plan was (free floating: inertial)
    motions = certifying(scenario, motions)
    args = (path_rad, start_rad, join, now_ns, lead_s, motions, time_step_s, from_end_at_rest, paths)
    # the re-timing rounds need only the published points (the certification cannot change them
    # when it passes at once) and, from rest, not the reaction report (the same path; the verdict
    # is the accepted round's): certify and report the accepted round alone ...
    got, first, wheel_over = _retimed(scenario, args, certify=False)
    if got.refused is not None:
        return got
    done = _certified(scenario, got, args, wheel_over)
    if done is not None and done.refused is None:
        return done
    # a refusal of the first round is where the reported chain stops: that round, as it would
    # (the accepted round's refusal is the first round's when there was no re-timing)
    refused = done if first is got else _refusal(scenario, first, args) if done is not None else None
    if refused is not None:
        return refused
    # ... and where the certification added points back or failed (or only a re-timed round was
    # refused), run every round certified and reported (the points whose interpolation is
    # checked are then the ones published)
    return _retimed(scenario, args, certify=True)[0]


def _retimed(scenario, args, certify: bool) -> tuple:
    """
    Run steps 1 to 4 of the chain: time, react, resample (certified when ``certify``), re-time.

    The controller interpolates the published points (quintic segments): its motion is
    checked against the limits; where it overshoots, the chain runs again with the limits it
    exceeds lowered by the overshoot along the stretches where it did (:func:`overshot_stretches`),
    from the CONTROLLER_RETIMES-th re-timing on along the whole path (the scaling factors, as
    MoveIt's: a stretch's lowering that moved the overshoot on does not go on forever), at most
    WHOLE_PATH_RETIMES times (a stop on the executing path: STOP_WHOLE_PATH_RETIMES).
    A join's re-timings time the path the first round chose (``replanning.timed_join``).
    ``args``: :func:`_time_and_resample`'s arguments after the scenario.  Returns (the
    :class:`Processed` of the last round (its ``retimings`` counted), that of the first, the last
    round's :func:`controller_wheel_overshoot` when it was checked, else None).
    """
    limits, acs = scenario.joint_limits, scenario.acs
    got, chosen = _time_and_resample(scenario, *args, certify=certify)
    first, wheel_over, joined = got, None, args[8] is not None
    stop = joined and args[8].join.stop
    last = CONTROLLER_RETIMES - 1 + (STOP_WHOLE_PATH_RETIMES if stop else WHOLE_PATH_RETIMES)
    retimings = 0
    for round_ in range(last + 1):
        if got.refused is not None or limits is None:
            break
        per_segment = segment_overshoots(got.trajectory, scenario)
        over = controller_overshoot(per_segment)
        wheel_over = over[2:]
        if max(over) <= 1.0 + CONTROLLER_TOL:
            break
        if round_ == last:
            if joined:                # the session plans again (a longer horizon, the executing end)
                raise ValueError(f"{_overshoot_text(over)} after {last} re-timings")
            # from rest: the same points, slowed down until the controller's motion is within its limits
            got, wheel_over = _slowed(scenario, got, over, args, certify), None
            break
        wheel_over = None             # the round is timed again
        if round_ < CONTROLLER_RETIMES - 1:
            # only the limits that overshoot, only where (lowered everywhere, a joined path could not
            # be entered at the arm's speed: its start sits at the velocity bound)
            stretches = overshot_stretches(got.trajectory, scenario, per_segment=per_segment)
            limits = replace(limits, lowered=limits.lowered + stretches)
        else:                         # the whole path, as the stretches have not done it
            lowered = [_lowered(scale, peak) for scale, peak in zip(
                (limits.velocity_scaling, limits.acceleration_scaling, acs.wheel_momentum_scaling,
                 acs.wheel_torque_scaling), over)]
            limits = replace(limits, velocity_scaling=lowered[0], acceleration_scaling=lowered[1])
            acs = replace(acs, wheel_momentum_scaling=lowered[2], wheel_torque_scaling=lowered[3])
        try:
            got, chosen = _time_and_resample(replace(scenario, joint_limits=limits, acs=acs), *args,
                                             certify=certify, chosen=chosen)
        except ValueError as e:
            # (joined) the slower motion cannot enter the path at the arm's speed: never published
            # over the limits (the session plans again: a longer horizon, the executing end)
            raise ValueError(f"{_overshoot_text(over)}, and a slower motion cannot be entered at the "
                             f"arm's speed ({e})") from e
        retimings += 1
    return (replace(got, retimings=retimings) if retimings else got), first, wheel_over     # (first is got: none)


def _slowed(scenario, got: Processed, over, args, certify: bool) -> Processed:
    """
    Return a round from rest whose controller's motion still overshoots (``over``: :func:`_retimed`'s ratios), slowed.

    Its dense and published points, t → k·t (``Trajectory.slowed``), k the least that brings each
    ratio to 1: the velocity's and the wheel momentum's fall by k, the acceleration's and the wheel
    torque's by k² (the controller's quintics through the slowed points are the old ones, slower:
    the same curve, the same collision verdict).  The whole-path re-timings, whose switches move
    the overshoot on, had left a free-floating capture's elbow at 1.0059 × its acceleration limit
    after the last (a helper's audit: 1 of 130 plans; published as it was).  A certified and
    reported round (``certify``) is certified and reported again on its slowed points.
    """
    k = max(1.0, over[0], over[2], math.sqrt(over[1]), math.sqrt(over[3]))
    slowed = replace(got, dense=got.dense.slowed(k), trajectory=got.trajectory.slowed(k))
    if not certify:
        return slowed
    motions = args[5]
    if slowed.reaction is not None:
        slowed = replace(slowed, reaction=_reaction(scenario, slowed, args))
        if slowed.refused is not None:
            return _stopped(slowed)
    check, _ = controller_check(slowed.trajectory, motions)
    return _finished(scenario, slowed, Resampled(slowed.trajectory, slowed.indices, check, 0))


def _lowered(scaling: float, peak: float) -> float:
    """Return a scaling factor lowered by the controller's overshoot ``peak`` (a peak ratio; kept within the limit)."""
    return scaling / peak * CONTROLLER_SHRINK if peak > 1.0 + CONTROLLER_TOL else scaling


def _wheels_limited(scenario) -> bool:
    """Tell whether the wheels' load of the controller's motion is checked (the attitude held, a wheel limit set)."""
    return scenario.acs.mode == "held" and scenario.acs.has_wheel_limits


#: the quantities :func:`_retimed`'s overshoot ratios measure, in order
_OVERSHOOT_NAMES = ("joint velocity", "joint acceleration", "wheel momentum", "wheel torque")


def _overshoot_text(over) -> str:
    """Say which limit the controller's motion exceeds most, and by how much (``over``: the ratios of _retimed)."""
    k = int(np.argmax(over))
    return f"as the controller moves the arm, its {_OVERSHOOT_NAMES[k]} reaches {over[k]:.3f} times its limit"


def overshot_stretches(traj: Trajectory, scenario, samples_per_segment: int = 16, per_segment=None) -> tuple:
    """
    Return where the controller's motion of ``traj`` overshoots a limit, and by how much: ``trajectory.Lowering``s.

    A segment of ``traj``'s points (from a point to the next) whose controller's motion exceeds
    a limit by more than ``CONTROLLER_TOL`` (:func:`segment_overshoots`) has that limit lowered
    to CONTROLLER_SHRINK over the overshoot; the segments around it taper back to the full
    limit by ``LOWERING_TAPER`` per segment (a step in a limit is a step in the time-optimal
    acceleration, which the controller's quintics overshoot in turn: lowered on the segment
    alone, the overshoot moved to its neighbours, and took three to four re-timings where a
    lowering of the whole path took two).  One stretch per run of lowered segments; timed again
    within them (``JointLimits.lowered``), the rest of the path keeps its limits.
    ``per_segment``: :func:`segment_overshoots` of the same, when known.
    """
    over = segment_overshoots(traj, scenario, samples_per_segment) if per_segment is None else per_segment
    # where the acceleration is lowered, the velocity by CONTROLLER_SHRINK too (the new profile overshot
    # it by up to 0.4 % in the next segment: a second re-timing on 11 of 20 paper 3-DOF starts, now 5)
    f = lowering_factors(np.ascontiguousarray(over, dtype=np.float64), CONTROLLER_TOL, CONTROLLER_SHRINK,
                         LOWERING_TAPER)
    low = np.any(f < 1.0, axis=1)
    if not low.any():
        return ()
    # one stretch per run of lowered segments
    edges = np.flatnonzero(np.diff(np.concatenate([[False], low, [False]]).astype(np.int8)))
    q = traj.positions_rad
    return tuple(Lowering(q[a:b + 1].copy(), f[a:b].copy()) for a, b in zip(edges[::2], edges[1::2]))


def segment_overshoots(traj: Trajectory, scenario, samples_per_segment: int = 16) -> np.ndarray:
    """
    Return each segment's peak ratios of the controller's motion to the limits, (M - 1, 4).

    Columns: joint velocity, joint acceleration (the largest over the planned joints, over the
    limits times the scaling factors), wheel momentum, wheel torque (over the limits; 0 unless
    the attitude is held and the limit set); each over ``samples_per_segment`` samples of the
    segment's quintic and its end point (``published.segment_peaks`` for the joints, the
    acceleration exact; ``published.segment_wheel_peaks`` for the wheels, their peak between
    the samples searched: 16 samples alone miss it by up to 0.4 % of a limit, with the search
    by less than 0.004 %).
    """
    m = len(traj.times_s)
    if m < 2:
        return np.zeros((0, 4))
    s = samples_per_segment
    vmax, amax = scenario.joint_limits.planned(scenario.robot)
    vlim = vmax * scenario.joint_limits.velocity_scaling
    seg = np.zeros((m - 1, 4))
    # joints: one kernel, the acceleration exact (its peak near a point falls between the samples)
    seg[:, :2] = segment_peaks(traj, np.arange(s) / s, vlim, amax * scenario.joint_limits.acceleration_scaling)
    seg[:, 0] /= braking_allowance(traj, vlim)
    limits = _wheel_limits(scenario)
    if limits is not None:
        seg[:, 2:] = segment_wheel_peaks(scenario.robot, scenario.masses, traj, s) / limits
    return seg


def braking_allowance(traj: Trajectory, vlim) -> np.ndarray:
    """
    Return each segment's allowance on the velocity limits (M - 1,): ≥ 1 where the trajectory brakes down to them.

    A trajectory that starts above the velocity limits (lowered while the arm moves: timed with
    ``brake_to_limits``) brakes to them first: along the run of points from its first one whose
    velocity exceeds ``vlim`` (n,) by more than ``CONTROLLER_TOL``, a segment's motion is held to
    the speed of its first point (its largest ratio to the limits over the joints, which the
    time parameterisation's braking never lets rise), not to the limits, which it cannot meet yet;
    1 elsewhere (every trajectory that starts within them: its first point alone is looked at).
    """
    m = len(traj.times_s)
    allow = np.ones(max(m - 1, 0))
    if m < 2 or not np.max(np.abs(traj.velocities_rad_s[0]) / vlim) > 1.0 + CONTROLLER_TOL:
        return allow
    ratio = np.max(np.abs(traj.velocities_rad_s) / np.asarray(vlim, dtype=float), axis=1)
    run = _leading_run(ratio > 1.0 + CONTROLLER_TOL)       # the points above from the first one
    allow[:min(run, m - 1)] = ratio[:min(run, m - 1)]
    return allow


def _leading_run(mask) -> int:
    """Return how many of ``mask``'s (K,) first values are all True."""
    mask = np.asarray(mask, dtype=bool)
    return len(mask) if mask.all() else int(np.argmin(mask))


def braking_text(scenario, traj: Trajectory) -> str:
    """
    Say when a trajectory that starts above the velocity limits comes within them (for the log), or "".

    ``traj``: a published trajectory (``Processed.trajectory``); the limits are the scenario's
    (scaled).  E.g. "; within the velocity limits from 1.41 s on (the arm at 15.99 times them at its
    start)": the time of its first point within them (:func:`braking_allowance`'s run), whether it
    brakes there or follows the executing trajectory that far (to where that one rests).
    """
    if len(traj.times_s) < 2:
        return ""
    vmax, _ = scenario.joint_limits.planned(scenario.robot)
    allow = braking_allowance(traj, vmax * scenario.joint_limits.velocity_scaling)
    run = _leading_run(allow > 1.0)
    if run == 0:
        return ""
    return (f"; within the velocity limits from {traj.times_s[run]:.2f} s on (the arm at {allow[0]:.2f} times "
            f"them at its start)")


def _wheel_limits(scenario):
    """Return the wheel momentum and torque limits (2,) the controller's motion is held to (inf: none), or None."""
    if not _wheels_limited(scenario):
        return None
    acs = scenario.acs
    return np.array([x if x is not None and x > 0.0 else np.inf
                     for x in (acs.max_wheel_momentum_Nms, acs.max_wheel_torque_Nm)])


def controller_overshoot(per_segment) -> tuple:
    """
    Return the peaks (joint velocity, joint acceleration, wheel momentum, wheel torque) over their limits.

    From :func:`segment_overshoots`' rows (M - 1, 4): the largest of each column (0.0 without
    segments; NaN where a ratio is).
    """
    if not len(per_segment):
        return 0.0, 0.0, 0.0, 0.0
    return tuple(float(x) for x in np.max(per_segment, axis=0))


def controller_wheel_overshoot(traj: Trajectory, scenario, samples_per_segment: int = 16) -> tuple:
    """
    Return the peak (wheel momentum, wheel torque) over the scenario's wheel limits of the controller's motion.

    The wheels take the arm's reaction as the arm really moves: joint_trajectory_controller's
    interpolation of ``traj``'s points (``published.controller_motion``), sampled
    ``samples_per_segment`` times per segment and at the end, its peak between the samples
    searched (:func:`segment_overshoots`), not only the points the time parameterisation kept within the
    limits (the quintics between them overshoot a torque limit that binds by up to about a
    third).  The ratios are max |h_wheel| / ``acs.max_wheel_momentum_Nms`` and max |τ_wheel| /
    ``acs.max_wheel_torque_Nm`` (``spacecraft.wheel_load``; 1.0: at the limit); 0.0 for a limit
    not set, and both 0.0 unless the attitude is held.
    """
    if not _wheels_limited(scenario):
        return 0.0, 0.0
    return controller_overshoot(segment_overshoots(traj, scenario, samples_per_segment))[2:]


def _time_and_resample(scenario, path_rad, start_rad, join, now_ns, lead_s, motions, time_step_s,
                       from_end_at_rest, paths=None, certify: bool = True, chosen: int | None = None) -> tuple:
    """
    Run steps 1 to 3 and 5 of the chain (see the module docstring) under the scenario's limits.

    ``paths``: a join's ``replanning.JoinedPaths`` (None from rest or from the executing
    trajectory's end); ``chosen``: the candidate an earlier round timed (``replanning.timed_join``).
    ``certify`` False: the points are resampled but neither certified nor split, and from rest
    the reaction is not reported (a round whose points only the controller check reads;
    :func:`_certified` finishes the accepted one).  Returns (:class:`Processed`, the
    candidate timed or None).
    """
    stamp_ns = cont = not_before_ns = None
    exact = False
    if paths is None and join is None:
        dense, reaction = timed_motion(scenario, path_rad, start_rad, motions=motions, report=certify)
    elif paths is None:
        # from rest at the executing trajectory's end, stamped when published, not before that end
        not_before_ns = starts_at_the_end(join, now_ns, lead_s, from_end_at_rest)
        exact = join.horizon_index < len(join.executing.trajectory) - 1     # the arm leaves that point after it
        dense, reaction = timed_motion(scenario, path_rad, join.start_rad, motions=motions, report=certify)
    else:
        dense, reaction, chosen = timed_join(scenario, paths, motions, chosen)
        stamp_ns, cont = paths.stamp_ns, paths.continuation
        dense = _in_the_arms_state(dense, paths)
    on_bounds = _on_bounds(dense, scenario.robot)
    dense = _still_on_bounds(dense, on_bounds)
    keep = _bound_points(on_bounds)
    got = Processed(dense, dense, np.arange(len(dense)), False, float("nan"), reaction, None, None,
                    stamp_ns, cont, not_before_ns, stamp_exact=exact)
    if reaction is not None and not reaction.ok:
        return got, chosen
    if not certify:
        rs = resample(dense, None, time_step_s=time_step_s, keep=keep)
        return replace(got, trajectory=rs.trajectory, indices=rs.indices), chosen
    return _finished(scenario, got, resample(dense, motions, time_step_s=time_step_s, keep=keep)), chosen


def _still_on_bounds(dense: Trajectory, on_bounds) -> Trajectory:
    """
    Return ``dense`` with each bounded joint held on its bound at its points exactly on it.

    A path along a joint's bound (its samples snapped onto it) was timed on a spline through them whose
    slope there is small but not 0: the controller's quintic between two such points bulged past the
    bound (by up to 0.0055° in a helper's audit, where it runs along the elbow's -180°).  The timing's
    spline now has slope 0 there wherever it would pass the bound (``trajectory.time_parameterize``'s
    ``lower_rad``, ``upper_rad``); here every such point holds it, whatever the spline: that joint's
    velocity is set to 0, and its acceleration too where it points past the bound or where a
    neighbouring point lies on the same bound (along the bound).  Where the path touches the bound at
    one point, or leaves a run along it, the point's acceleration is then the least inward one that
    keeps the controller's quintic to the next point off the bound within it (:func:`_least_inward`:
    a long, slow segment next to it, where the speed changes fast, had its quintic pass the bound by
    up to 7.3e-4 rad in a helper's audit of the servicer scenes; the published points keep both
    neighbours, :func:`_bound_points`).  The first point keeps its state (a join's is the arm's).
    ``on_bounds``: :func:`_on_bounds` of ``dense``.  The same object where no point lies on a bound.
    """
    at_lo, at_hi = on_bounds
    if not (at_lo.any() or at_hi.any()):
        return dense
    vel, acc = dense.velocities_rad_s.copy(), dense.accelerations_rad_s2.copy()
    along_lo = at_lo & (np.roll(at_lo, 1, axis=0) | np.roll(at_lo, -1, axis=0))
    along_hi = at_hi & (np.roll(at_hi, 1, axis=0) | np.roll(at_hi, -1, axis=0))
    vel[at_lo | at_hi] = 0.0
    acc[along_lo | along_hi | (at_lo & (acc < 0.0)) | (at_hi & (acc > 0.0))] = 0.0
    t, q, m = dense.times_s, dense.positions_rad, len(dense.times_s)
    for at, inward in ((at_lo, 1.0), (at_hi, -1.0)):
        for k, c in zip(*np.nonzero(at)):
            need = inward * acc[k, c]
            for o in (k - 1, k + 1):
                if 0 <= o < m and not at[o, c]:
                    need = max(need, _least_inward(t, q[:, c], vel[:, c], acc[:, c], k, o, inward))
            acc[k, c] = inward * need
    return replace(dense, velocities_rad_s=vel, accelerations_rad_s2=acc)


#: samples of a segment's quintic for :func:`_least_inward`, and the margin on what they ask
_LIFT_SAMPLES, _LIFT_MARGIN = 128, 1.05


def _least_inward(t, q, v, a, k, o, inward: float) -> float:
    """
    Return the least inward acceleration at point k, on its joint's bound, that keeps the quintic to point o within it.

    t (M,), q, v, a (M,) one joint's column; ``inward`` +1 at a lower bound, -1 at an upper.  The
    quintic with k's acceleration A is Q + A·H (Q: with A = 0, ``published.sample_points``; H the
    quintic Hermite basis of that end's acceleration, ≥ 0 on the segment: τ²/2 (1 - τ/T)³ from its
    start, its mirror to its end), so one least A keeps it within at every sample
    (:data:`_LIFT_SAMPLES`, the value raised by :data:`_LIFT_MARGIN`); 0 where it is within already.
    """
    i, j = min(k, o), max(k, o)
    dur = t[j] - t[i]
    acc = np.array([a[i], a[j]], dtype=float)
    acc[0 if k == i else 1] = 0.0
    tau = dur * np.arange(1, _LIFT_SAMPLES) / _LIFT_SAMPLES
    quintic = sample_points(np.array([0.0, dur]), q[[i, j], None], v[[i, j], None], acc[:, None], tau)[0][:, 0]
    u = tau / dur
    basis = tau ** 2 / 2.0 * (1.0 - u) ** 3 if k == i else (dur - tau) ** 2 / 2.0 * u ** 3
    need = float(np.max(inward * (q[k] - quintic) / basis))
    return need * _LIFT_MARGIN if need > 0.0 else 0.0


def _on_bounds(dense: Trajectory, robot) -> tuple:
    """Return (at_lo, at_hi) (M, n) bool: the points where a bounded joint lies exactly on its bound (not the first)."""
    lo, hi = robot.planned_bounds_rad              # ±inf for a periodic joint: no position equals them
    names = robot.planned_names
    if tuple(dense.joint_names) != names:
        cols = [names.index(n) for n in dense.joint_names]
        lo, hi = lo[cols], hi[cols]
    q = dense.positions_rad
    at_lo, at_hi = q == lo, q == hi
    at_lo[0] = at_hi[0] = False
    return at_lo, at_hi


def _bound_points(on_bounds) -> np.ndarray:
    """
    Return the indices of the points the published trajectory keeps because a joint reaches its bound there.

    Each point where a bounded joint touches its bound, and the first and last of a run along it
    (within the run the controller holds the joint on the bound: :func:`_still_on_bounds`), and their
    neighbours (the quintics :func:`_still_on_bounds` keeps within the bound are to them); the
    resampling may drop them otherwise (0.1° of the path), and the quintic between the points left
    then passes the bound (a helper's audit: up to 8e-7 rad; the certification, exact on the bounds,
    would add points back round by round).  ``on_bounds``: :func:`_on_bounds` of the dense points.
    """
    at_lo, at_hi = on_bounds
    if len(at_lo) < 3 or not (at_lo.any() or at_hi.any()):
        return np.zeros(0, np.int64)
    out = np.zeros(len(at_lo), dtype=bool)
    for at in (at_lo, at_hi):
        inner = at[1:-1] & at[:-2] & at[2:]            # inside a run: both neighbours on the same bound
        out[1:-1] |= (at[1:-1] & ~inner).any(axis=1)
    kept = out.copy()
    out[:-1] |= kept[1:]
    out[1:] |= kept[:-1]
    return np.flatnonzero(out)


def _in_the_arms_state(dense: Trajectory, paths) -> Trajectory:
    """
    Return a joined trajectory whose first point has the executing trajectory's velocity and acceleration at the join.

    The time parameterisation starts along the arm's own direction (``replanning.start_tangent``:
    the joined path's spline clamped to it) at the arm's path speed, so the velocity is the
    arm's up to the speed's rounding; its acceleration is the time-optimal profile's, not the
    arm's (the executing trajectory may be braking where the new one speeds up).  The first
    point takes the state the arm is in, exactly; the controller's quintic from there to the
    second point is what the chain checks and certifies (the overshoot, the collisions), as
    every other segment.
    """
    ex, k = paths.join.executing.trajectory, paths.continuation.index
    vel, acc = dense.velocities_rad_s.copy(), dense.accelerations_rad_s2.copy()
    vel[0], acc[0] = ex.velocities_rad_s[k], ex.accelerations_rad_s2[k]
    return replace(dense, velocities_rad_s=vel, accelerations_rad_s2=acc)


def _certified(scenario, got: Processed, args, wheel_over=None) -> Processed | None:
    """
    Certify (and from rest report) an uncertified round (``_time_and_resample(certify=False)``).

    ``args``: :func:`_time_and_resample`'s arguments after the scenario; ``wheel_over``: the
    round's :func:`controller_wheel_overshoot` when known (None: computed).  Returns the finished
    :class:`Processed`; when the reaction refuses, the refused round as a reported round stops
    (the dense points, not split); None when the certification added points back or failed (the
    published points would not be the ones whose interpolation was checked).
    """
    motions = args[5]
    if got.join_stamp_ns is None and reaction_matters(scenario):
        got = replace(got, reaction=_reaction(scenario, got, args))
        if got.refused is not None:
            return _stopped(got)
    # the round's points are resample's selection of these dense points (time_step_s, the path
    # tolerance): resample(got.dense, motions) would select them again and certify the controller's
    # motion through them, keeping them when it passes at once, adding points back (or failing) otherwise
    check, _ = controller_check(got.trajectory, motions)
    if not check.ok:
        return None
    return _finished(scenario, got, Resampled(got.trajectory, got.indices, check, 0), wheel_over)


def _reaction(scenario, got: Processed, args):
    """Return the reaction report of an unreported round from rest (``reaction_of`` its dense points)."""
    path_rad, start_rad, join, motions = args[0], args[1], args[2], args[5]
    state = start_rad if got.not_before_ns is None else join.start_rad
    return reaction_of(scenario, path_rad, got.dense, state, motions=motions)


def _refusal(scenario, got: Processed, args) -> Processed | None:
    """Return an unreported round from rest, reported, when its reaction refuses (:func:`_stopped`), else None."""
    if got.join_stamp_ns is not None or not reaction_matters(scenario):
        return None
    got = replace(got, reaction=_reaction(scenario, got, args))
    return None if got.refused is None else _stopped(got)


def _stopped(got: Processed) -> Processed:
    """Return a refused round as ``_time_and_resample`` returns one: its dense points, not resampled, not split."""
    return replace(got, trajectory=got.dense, indices=np.arange(len(got.dense)))


def _finished(scenario, got: Processed, rs, wheel_over=None) -> Processed:
    """
    Return ``got`` with the resampled points ``rs`` (the dense ones when not certified), split.

    ``wheel_over``: :func:`controller_wheel_overshoot` of ``rs.trajectory`` when known (None: computed).
    """
    dense = got.dense
    traj, idx = (rs.trajectory, rs.indices) if rs.ok else (dense, np.arange(len(dense)))
    arm, att = split_parts(traj, scenario.robot.joint_names[0])
    if arm is None and att is None and got.stamp_exact:
        # the goal is where the arm rests on the trajectory it follows, which then goes on: held there
        dense = traj = held(traj)
        idx = np.arange(len(traj))
        arm, att = split_parts(traj, scenario.robot.joint_names[0], hold=True)
        got = replace(got, dense=dense)
    drift = None
    if scenario.acs.mode == "free_floating":
        att = None                  # nothing commands the attitude
        drift = None if arm is None else predicted_drift(scenario, dense, idx)
    clr = float(rs.check.min_clearance_m) if rs.check is not None else float("nan")
    return replace(got, trajectory=traj, indices=idx, certified=rs.ok, min_clearance_m=clr, arm=arm,
                   attitude=att, predicted_drift=drift,
                   reaction=_published_peaks(scenario, got.reaction, traj, wheel_over if rs.ok else None))


def switching_at_arrival(sent_stamp_ns: int, sent_parts, stamp_ns: int, parts, drift, now_ns: int) -> tuple:
    """
    Return (stamp_ns, parts, drift) of a trajectory from a moving arm for a controller that switches at arrival.

    Such a controller (``controller.switch: arrival``) installs a trajectory when it arrives and
    goes from its state then to the first point, reached at the stamp: a connecting stretch
    nobody checked.  So the message is stamped at the last point, at or before ``now_ns``, of the
    message last sent (``sent_stamp_ns``, ``sent_parts``: what the controller executes, whatever
    it was joined to before) and holds that message's points from there up to ``stamp_ns`` (the
    join, one of them; or after its end, at rest there), then ``parts`` shifted: arriving
    anywhere before the switch, the controller samples the segment it is in, the one it had.
    ``parts``: the (arm, attitude) ``TrajectoryPart`` objects from ``stamp_ns`` (None where a group is
    not sent); ``drift``: the reported free-floating drift, its times shifted alike.  As given
    when the two messages do not hold the same groups and joints, or no sent point lies before
    ``stamp_ns``.
    """
    same = [(a is None) == (b is None) and (a is None or a.joint_names == b.joint_names)
            for a, b in zip(sent_parts, parts)]
    ref = next((p for p in sent_parts if p is not None), None)
    if not all(same) or ref is None:
        return stamp_ns, tuple(parts), drift
    t_ns = sent_stamp_ns + np.round(1e9 * np.asarray(ref.times_s)).astype(np.int64)
    before = np.flatnonzero(t_ns < stamp_ns)
    if not len(before):
        return stamp_ns, tuple(parts), drift
    past = np.flatnonzero(t_ns[before] <= now_ns)
    first = int(before[past[-1]]) if len(past) else 0     # the last point the controller has passed (or its first)
    rows = np.arange(first, int(before[-1]) + 1)
    t0 = float(ref.times_s[first])
    anchor_ns = int(t_ns[first])
    shift = 1e-9 * (stamp_ns - anchor_ns)

    # after the sent message's end (a plan from there, at rest): held between, at rest, through points with no
    # acceleration AFTER_THE_END_S after that end and before the new start (a quintic from one state at rest to
    # another with their own accelerations over the whole wait would sway)
    gap = AFTER_THE_END_S
    end_s = float(ref.times_s[-1]) - t0
    holds = ([end_s + gap, shift - gap] if rows[-1] == len(ref.times_s) - 1 and shift - gap > end_s + gap + 1e-9
             else [])

    def prefixed(old, part):
        if part is None:
            return None
        rest = np.repeat(old.positions_rad[-1:], len(holds), axis=0)
        still = np.zeros_like(rest)
        return TrajectoryPart(part.joint_names, np.concatenate([old.times_s[rows] - t0, holds, part.times_s + shift]),
                              np.vstack([old.positions_rad[rows], rest, part.positions_rad]),
                              np.vstack([old.velocities_rad_s[rows], still, part.velocities_rad_s]),
                              np.vstack([old.accelerations_rad_s2[rows], still, part.accelerations_rad_s2]))
    if drift is not None:               # reported, not sent: its times on the message's clock
        drift = replace(drift, times_s=drift.times_s + shift)
    return anchor_ns, tuple(prefixed(old, part) for old, part in zip(sent_parts, parts)), drift


def certifying(scenario, motions: MotionValidator) -> MotionValidator:
    """
    Return the validator that certifies the controller's motion in ``scenario``: free floating, the inertial frame's.

    With ``acs.mode: free_floating`` nothing holds the attitude: the arm's motion turns and
    moves the spacecraft, so the motion through the published points is certified with the
    body drifting (``reaction.DriftedValidator``), as the plan's path was
    (``reaction.check_drifted``), not on a body held still (where a capture's last stretch,
    planned for the drifted body, may cross the target).  Else ``motions`` itself.
    """
    motions = MotionValidator.of(motions)
    if scenario.acs.mode != "free_floating" or isinstance(motions, DriftedValidator):
        return motions
    return DriftedValidator(motions, scenario.masses)


def uncertified_text(scenario, processed: Processed, motions) -> str:
    """
    Say where the controller's motion through ``processed``'s published points leaves the certified (a text).

    When it comes within the safety margin (``motions``: the scene's ``motion.MotionValidator``,
    :func:`certifying` in ``scenario``) and how close: for the log of a trajectory that is not
    certified (a start within the margin, or a joined one whose executing path a new scene put an
    obstacle on).
    """
    traj, motions = processed.trajectory, certifying(scenario, motions)
    check, seg_ok = controller_check(traj, motions)
    if check.ok:
        return f"the controller's motion is certified (clearance {check.min_clearance_m:.3f} m)"
    bad = np.flatnonzero(~seg_ok)
    when = f"{traj.times_s[bad[0]]:.2f} s after its start" if len(bad) else "at its points"
    said = []
    if not check.min_clearance_m > motions.margin_m:
        said.append(f"comes within the safety margin {motions.margin_m:g} m {when}: clearance "
                    f"{check.min_clearance_m:.3f} m")
    said += _past_bounds_text(scenario, traj)
    if not said:
        said.append(f"is not certified {when} (clearance {check.min_clearance_m:.3f} m)")
    return "the controller's motion " + "; it ".join(said)


def _past_bounds_text(scenario, traj: Trajectory) -> list:
    """
    Say where the controller's motion of ``traj`` passes a bounded joint's bound, joint by joint (texts; [] when none).

    The quintics' exact peaks (``published.past_bounds``) against the robot's planned bounds, where
    they pass them by more than the controller check's slack: e.g. "passes elbow's bound -180° by
    0.0055° 8.09 s after its start" (the points themselves lie within them: the path's samples do).
    """
    robot = scenario.robot
    names = list(robot.planned_names)
    lo, hi = robot.planned_bounds_rad               # ±inf for a periodic joint: never passed
    cols = [names.index(name) for name in traj.joint_names]
    excess, at, side = past_bounds(traj, lo[cols], hi[cols])
    out = []
    for c, name in enumerate(traj.joint_names):
        if excess[c] > BOUND_SLACK_RAD:
            bound = hi[cols[c]] if side[c] > 0 else lo[cols[c]]
            out.append(f"passes {name}'s bound {np.degrees(bound):g}° by {np.degrees(excess[c]):.2g}° "
                       f"{at[c]:.2f} s after its start")
    return out


def _published_peaks(scenario, reaction, traj: Trajectory, wheel_over=None):
    """
    Return ``reaction`` with its wheel peaks those of the motion the arm makes of the published points.

    The report's peaks are at the dense points, which a re-timing keeps below the lowered wheel
    limits; the arm, moved by the controller through the published points, comes up to the
    limits (:func:`controller_wheel_overshoot`, or ``wheel_over`` when it is known): the larger
    of the two is reported.  ``reaction`` as it is without wheel limits or a report.
    """
    if reaction is None or reaction.peak_wheel_torque_Nm is None:
        return reaction
    over_h, over_tau = controller_wheel_overshoot(traj, scenario) if wheel_over is None else wheel_over
    if over_h == 0.0 and over_tau == 0.0:
        return reaction
    acs = scenario.acs
    return replace(reaction, peak_wheel_momentum_Nms=max(reaction.peak_wheel_momentum_Nms,
                                                         over_h * acs.max_wheel_momentum_Nms),
                   peak_wheel_torque_Nm=max(reaction.peak_wheel_torque_Nm, over_tau * acs.max_wheel_torque_Nm))


def predicted_drift(scenario, dense: Trajectory, indices) -> TrajectoryPart:
    """
    Return the free-floating drift of a trajectory at some of its points.

    Columns: the attitude joint (rad, as it drifts: what an attitude sensor would read) and
    ``body_x``, ``body_y`` (the body centre's displacement from the start, inertial frame,
    metres), at ``dense``'s points ``indices`` (``spacecraft.free_floating_response`` along
    the dense points; velocities from the arm's, ``spacecraft.free_floating_rates``: 0 where the
    arm is at rest, which finite differences were not; accelerations 0).
    """
    robot = scenario.robot
    resp = free_floating_response(robot, scenario.masses, dense.positions_rad)
    q = np.column_stack([resp.q_full_rad[:, 0], resp.body_position_m])
    t = np.asarray(dense.times_s, dtype=float)
    att_rate, body_v = free_floating_rates(robot, scenario.masses, resp.q_full_rad, dense.velocities_rad_s)
    v = np.column_stack([att_rate, body_v])
    idx = np.asarray(indices)
    return TrajectoryPart((robot.joint_names[0], "body_x", "body_y"), t[idx].copy(), q[idx], v[idx],
                          np.zeros_like(q[idx]))
