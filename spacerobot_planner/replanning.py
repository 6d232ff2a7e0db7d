"""
Replanning from a moving arm: where a new plan starts, and how its trajectory joins.

A new target (or a replan) while the node's last trajectory executes must not start the
arm from rest where it happens to be: the velocity would jump at the switch.  Instead
(MoveIt's hybrid planning and Nav2's controller do the same in spirit):

1. When the plan begins (:func:`plan_start`), the new plan starts at the executing
   trajectory's point ``horizon_s`` ahead (the *horizon point*): the arm will get there
   on the trajectory it already follows while the plan is computed.  This needs the arm
   to follow that trajectory: the last measured joint state must lie within
   ``follow_tolerance_rad`` of where the trajectory (or the one it joined, before its
   start) had the arm at the measurement's time, interpolated as a spline (the dense
   trajectory) or linearly between the published points.  A state taken before the
   trajectory started counts when it is at its first point (the controller holds the
   start until the stamp; under load the first joint_states after a start arrive late)
   and is at most ``MAX_STATE_AGE_S`` old: an older one shows nothing moving.  An older
   state taken while the trajectory moved is the last sign there is, and it joins (when
   the states come as a stream, the node's session first waits a moment for a newer one,
   ``STATE_WAIT_S``: a loaded executor delivers states late, while the controller goes
   on).  Otherwise (a controller that stopped, an arm pushed away) the plan starts from
   the measured state, at rest, as for an arm standing still.  (A still arm is told from
   a following one only once the trajectory has moved by more than the tolerance: just
   after it started, it joins.)
2. When the plan is done (:func:`joined_motion`), the published trajectory starts at the
   executing one's next published point (the *join*: an exact state of the executing
   trajectory, position and velocity, that the controller has been sent) and follows
   its certified path to the horizon point, then the new path; the time-optimal
   parameterisation starts at the join's path speed, so position and velocity are
   continuous at the switch and the limits hold throughout.  Its stamp is the join's
   time: the controller keeps following the old trajectory until then.  A plan that took
   longer than the horizon (the join would be past the horizon point) raises
   ``trajectory.HorizonPassed``: plan again with a longer horizon.  The new path is
   planned from a point, not a state: it may leave the horizon point in another
   direction than the arm's, a corner the arm would have to slow down for.  So the
   corner is also replaced by cubic (Hermite) blends, tangent to both paths, over
   ``BLEND_SAMPLES`` samples on either side; each blend is certified on the exact
   geometry (the scene's ``motion.MotionValidator``) and the fastest certified candidate (the corner
   itself included) is published (:func:`joined_paths` makes the candidates,
   :func:`timed_join` times them: a re-timing under lowered scaling factors times the one
   chosen).  Where none can be entered at the arm's speed (the
   re-fitted spline through a sharp corner asks for a slower arm than the join's) it
   raises ``ValueError``; with the horizon at the executing trajectory's end (its goal,
   at rest) the published trajectory is then that trajectory's own remainder followed
   by the new one from rest (``Trajectory.then``), which is always possible.

Times are ROS times in integer nanoseconds (the stamps of the messages); no rclpy here.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from .joint_space import align_to_state, difference_rad
from .motion import MotionValidator
from .timing import timed_motion
from .trajectory import Trajectory, check_start_tangent, chord_lengths_rad, continuation, horizon_index, sample

__all__ = ["Executing", "Join", "JoinedPaths", "plan_start", "joined_paths", "joined_motion", "timed_join",
           "stopping_join", "resting_join", "committed_path", "rests_at", "next_rest",
           "MAX_STATE_AGE_S", "STATE_WAIT_S", "BLEND_SAMPLES", "START_LEAD_S"]

#: the default of :func:`joined_motion`'s ``lead_s``: the join at least this far ahead (the messages'
#: transit: a controller that gets one after its start catches up with a velocity step); the node's
#: is the parameter ``trajectory.start_lead_s`` (``session.py``), s
START_LEAD_S = 0.1
#: half-widths (path samples on either side of the horizon point) of the corner blends tried
BLEND_SAMPLES = (8, 24)
#: a turn at the horizon point smaller than this (rad) is left as it is
MIN_CORNER_RAD = float(np.radians(1.0))
#: :func:`stopping_join` gives the arm 1 / STOP_ROOM of the path the limits need to stop: a braking at this
#: fraction of their deceleration
STOP_ROOM = 0.5

#: a joint state older than this (s) is late: taken before the trajectory's start, it does not show
#: that the arm follows it; the node's session first waits up to ``STATE_WAIT_S`` for a newer one
MAX_STATE_AGE_S = 0.5
#: how long (s) the node's session waits for a newer joint state than a late one from a stream before
#: a plan starts while a trajectory executes (MoveIt's wait for the current state is 1 s)
STATE_WAIT_S = 1.0


@dataclass(frozen=True, eq=False)
class Executing:
    """
    A trajectory the controller was sent.

    Attributes
    ----------
        trajectory: the dense trajectory (planned joints, unwrapped, rad), whose polyline
            was certified collision-free.
        published: (K,) indices of the points sent (``published.resample``'s), 0 and the
            last included.
        start_ns: the ROS time of its time 0 (the message's stamp), ns.
        previous: the trajectory it was joined to (what the arm follows before
            ``start_ns``), or None.

    """

    trajectory: Trajectory
    published: np.ndarray
    start_ns: int
    previous: "Executing | None" = None

    def time_s(self, ros_ns: int) -> float:
        """Seconds into the trajectory at ROS time ``ros_ns``."""
        return 1e-9 * (int(ros_ns) - self.start_ns)

    def running_at(self, ros_ns: int) -> bool:
        """Tell whether the arm is still moving on it at ``ros_ns``."""
        return self.time_s(ros_ns) < self.trajectory.duration_s

    def first_start_ns(self) -> int:
        """Return the start of the oldest trajectory kept in the chain (ROS time, ns)."""
        return self.start_ns if self.previous is None else self.previous.first_start_ns()

    def expected_at(self, ros_ns: int, published_only: bool = False) -> np.ndarray:
        """
        (n,) where the arm following it is at ROS time ``ros_ns``, rad.

        On the previous trajectory before this one starts (at this one's start with none).

        A controller interpolating the published points with their velocities (splines,
        as joint_trajectory_controller) follows the dense trajectory; one interpolating
        the positions linearly in time (``published_only``) runs ahead of it between
        points where the arm speeds up (up to a few degrees at high accelerations).
        """
        if ros_ns < self.start_ns and self.previous is not None:
            return self.previous.expected_at(ros_ns, published_only)
        return sample(self.trajectory, self.time_s(ros_ns), self.published if published_only else None)[0]

    def link_at(self, ros_ns: int, now_ns: int) -> "Executing":
        """
        Return the link of the chain the arm is on at ROS time ``ros_ns`` (seen at ``now_ns``).

        The newest whose start is before ``ros_ns``: a trajectory sent to start later (a plan from
        the end of the one that runs, stamped seconds or minutes ahead) waits for its stamp, and a
        newer message stamped before it drops it (the controller's rule, and the mock arm's), so
        a plan that takes over at ``ros_ns`` joins the one running then.  Only links whose
        predecessor still runs at ``now_ns`` are stepped back over.
        """
        link = self
        while link.previous is not None and link.start_ns >= int(ros_ns) and link.previous.running_at(now_ns):
            link = link.previous
        return link

    def joined_by(self, trajectory: Trajectory, published, start_ns: int, now_ns: int | None = None) -> "Executing":
        """
        Record a trajectory joined to this one at ``start_ns``, published at ROS time ``now_ns``.

        The chain of the trajectories it replaced is kept back to the one on which a late
        joint state was taken (``MAX_STATE_AGE_S + STATE_WAIT_S``, and a join is at most a
        published points' spacing ahead): links whose successor started over 2 s before the
        earlier of ``start_ns`` and ``now_ns`` are cut, and an older state reads as one from
        before the trajectory started.  (A plan from the end of a trajectory that has not begun
        is stamped far ahead: the trajectory the arm follows now stays in the chain.)
        """
        keep, link = [], self
        horizon_ns = min(int(start_ns), int(start_ns) if now_ns is None else int(now_ns)) - 2 * 1_000_000_000
        successor_start = int(start_ns)
        while link is not None and successor_start >= horizon_ns:
            keep.append(link)
            successor_start, link = link.start_ns, link.previous
        prev = None
        for e in reversed(keep):
            prev = Executing(e.trajectory, e.published, e.start_ns, prev)
        return Executing(trajectory, np.asarray(published), int(start_ns), prev)


@dataclass(frozen=True, eq=False)
class Join:
    """
    A plan that starts on an executing trajectory (see :func:`plan_start`).

    Attributes
    ----------
        executing: the trajectory the arm follows.
        horizon_index: its point where the new plan starts.
        horizon_s: the horizon it was chosen with, s.
        stop: the arm stops there on the executing path (:func:`stopping_join`) and the new path
            starts from rest, instead of going through it at speed.

    """

    executing: Executing
    horizon_index: int
    horizon_s: float
    stop: bool = False

    @property
    def start_rad(self) -> np.ndarray:
        """(n,) the new plan's start (unwrapped as on the executing trajectory), rad."""
        return self.executing.trajectory.positions_rad[self.horizon_index].copy()

    @property
    def rests(self) -> bool:
        """Tell whether the arm comes to rest at the horizon point on the executing trajectory (:func:`rests_at`)."""
        return rests_at(self.executing, self.horizon_index)


def join_direction(join: Join | None) -> np.ndarray | None:
    """
    Return the direction a plan starting at ``join``'s horizon point leaves it along: the arm's there (unit), or None.

    The executing trajectory's velocity at the horizon point: the new path leaves it as the arm
    arrives (``Planner.plan(start_tangent=...)``), so the joined path has no corner there for
    the arm to slow down for.  None without a join, for a join that stops there
    (:func:`stopping_join`) and where the arm passes the point at rest.
    """
    if join is None or join.stop:
        return None
    v = join.executing.trajectory.velocities_rad_s[join.horizon_index]
    speed = float(np.linalg.norm(v))
    return v / speed if speed > 0.0 else None


def plan_start(executing: Executing | None, now_ns: int, measured_rad, measured_ns: int, horizon_s: float,
               follow_tolerance_rad: float, periodic):
    """
    Where a plan beginning at ``now_ns`` starts.

    Args:
        executing: the trajectory the controller was last sent, or None.
        now_ns: ROS time now, ns.
        measured_rad: (n,) the arm's latest measured joint positions, rad.
        measured_ns: the ROS time of that measurement (its message's stamp), ns.
        horizon_s: how far ahead along the executing trajectory the plan starts, s
            (0: never join).
        follow_tolerance_rad: largest per-joint difference between the measurement and
            the executing trajectory at the measurement's time for the arm to count as
            following it, rad.
        periodic: (n,) flags of the periodic joints.

    Returns
    -------
        (start_rad (n,), Join or None, why): ``why`` says in words why the plan does not
        join, or what a join on a state older than ``MAX_STATE_AGE_S`` assumes (None when
        it joins on a recent state, or when there is nothing to join).

    """
    q = np.asarray(measured_rad, dtype=float).copy()
    if executing is None or horizon_s <= 0.0 or not executing.running_at(now_ns):
        return q, None, None
    traj = executing.trajectory
    age_s = 1e-9 * (int(now_ns) - int(measured_ns))
    stale = age_s > MAX_STATE_AGE_S
    # before the (oldest kept) trajectory's start the controller holds its first point (a
    # controller holds the start until the stamp): a state there is consistent with following
    before_start = measured_ns < executing.first_start_ns()
    if stale and before_start:
        return q, None, (f"the last joint_states is {age_s:.2f} s old and from before the trajectory started (no "
                         "sign that the arm follows it): planned from it, at rest")
    off = min((np.abs(difference_rad(q, executing.expected_at(measured_ns, lin), periodic)) for lin in (False, True)),
              key=lambda d: float(d.max()))
    if float(off.max()) > follow_tolerance_rad:
        j = int(np.argmax(off))
        if before_start:
            return q, None, (f"no joint_states since the trajectory started, and the last one is not at its start "
                             f"({traj.joint_names[j]} {np.degrees(off[j]):.2f}° from it; no sign that the arm "
                             "follows it): planned from the last one, at rest")
        return q, None, (f"the arm does not follow its trajectory ({traj.joint_names[j]} "
                         f"{np.degrees(off[j]):.2f}° from it): planned from the measured state, at rest")
    # the link the arm is on at the horizon: the plan takes over from the trajectory that runs then,
    # not after the ones waiting for later stamps (Executing.link_at)
    link = executing.link_at(int(now_ns) + int(round(1e9 * float(horizon_s))), now_ns)
    h = horizon_index(link.trajectory, link.time_s(now_ns), horizon_s)
    join = Join(link, h, float(horizon_s))
    # a late state taken on the moving trajectory is the last sign there is: the arm followed it
    # then (a controller keeps following; under load the states arrive late)
    why = (f"the last joint_states is {age_s:.2f} s old; it had the arm on its trajectory: planned from the "
           "trajectory, assuming the arm still follows it") if stale else None
    return join.start_rad, join, why


def _turn_rad(path, i):
    """Angle between the path's directions into and out of row ``i``, rad."""
    d0, d1 = path[i] - path[i - 1], path[i + 1] - path[i]
    n = np.linalg.norm(d0) * np.linalg.norm(d1)
    return 0.0 if n <= 0.0 else float(np.arccos(np.clip(d0 @ d1 / n, -1.0, 1.0)))


def _turn_refusal(c, path) -> str | None:
    """
    Return why a join at the horizon point itself may not leave it along the new path's own tangent, or None.

    A timing along its own tangent (``_fastest``'s second choice) starts along the path's first
    direction at the arm's path speed: with executing path before the horizon point that
    direction is the arm's and the corner is blended after it; with none (the executing
    trajectory's points are sparse, or the lead reaches the horizon) it is the new path's, and
    the arm's velocity would step (reverse, for a path back) at the switch.  ``c``: the
    ``trajectory.Continuation``; ``path`` (M, n): ``c.join(new)``.  The reason where the first
    step turns more than :data:`MIN_CORNER_RAD`; None for an arm at rest, which turns freely.
    """
    v = np.asarray(c.start_velocity_rad_s, dtype=float)
    d = path[1] - path[0] if len(path) > 1 else np.zeros_like(v)
    nv, nd = float(np.linalg.norm(v)), float(np.linalg.norm(d))
    if nv <= 1e-9 or nd <= 0.0:
        return None
    turn = float(np.arccos(np.clip(v @ d / (nv * nd), -1.0, 1.0)))
    if turn > MIN_CORNER_RAD:
        return (f"the join is the horizon point itself and the new path leaves it {np.degrees(turn):.1f}° off "
                f"the arm's direction: no executing path before the turn to blend it in (the arm's velocity "
                f"would step)")
    return None


def _corner_blends(path, corner, first, step_rad):
    """
    Candidate paths.

    Rows ``a = corner - m`` to ``b = corner + m`` of ``path`` (M, n) replaced by a cubic Hermite
    curve with the path's directions at a and b (tangents scaled to the chord), samples ≤
    ``step_rad`` apart; rows before ``first`` are kept.

    Yields (a, b, candidate path).
    """
    for m in BLEND_SAMPLES:
        a, b = max(first, corner - m), min(len(path) - 2, corner + m)
        if a >= corner or b <= corner or a < 1:
            continue
        p0, p1 = path[a], path[b]
        d0, d1 = path[a] - path[a - 1], path[b + 1] - path[b]
        n0, n1, chord = np.linalg.norm(d0), np.linalg.norm(d1), np.linalg.norm(p1 - p0)
        if n0 <= 1e-12 or n1 <= 1e-12 or chord <= 1e-12:
            continue
        t0, t1 = d0 * (chord / n0), d1 * (chord / n1)
        k = max(2, int(np.ceil(1.5 * chord / step_rad)))
        u = np.linspace(0.0, 1.0, k + 1)[:, None]
        curve = ((2 * u ** 3 - 3 * u ** 2 + 1) * p0 + (u ** 3 - 2 * u ** 2 + u) * t0
                 + (-2 * u ** 3 + 3 * u ** 2) * p1 + (u ** 3 - u ** 2) * t1)
        curve[0], curve[-1] = p0, p1
        yield a, b, np.vstack([path[:a], curve, path[b + 1:]])


@dataclass(frozen=True, eq=False)
class JoinedPaths:
    """
    The paths a joined plan may take (:func:`joined_paths`): what every timing of it shares.

    Attributes
    ----------
        join: the ``Join`` it starts on.
        continuation: the ``trajectory.Continuation`` (the join, the prefix to the horizon point).
        new_rad: (M, n) the new plan's path, aligned to the horizon point (unwrapped).
        stamp_ns: ROS time of the join (the trajectory's stamp), ns.
        candidates: the joined path with its corner at the horizon point first, then its
            certified corner blends (each (K, n), rad).
        turn_refusal: why the candidates may only leave the join along the arm's direction (a
            join at the horizon point itself, where the new path turns off it: :func:`_turn_refusal`),
            or None.

    """

    join: Join
    continuation: object
    new_rad: np.ndarray
    stamp_ns: int
    candidates: tuple
    turn_refusal: str | None = None


def joined_paths(scenario, join: Join, path_rad, now_ns: int, lead_s: float = START_LEAD_S,
                 checker=None) -> JoinedPaths:
    """
    Return the paths of a plan that started at ``join.start_rad`` (see :func:`joined_motion`).

    The continuation from the join (at least ``lead_s`` after ``now_ns``) to the horizon
    point, the new path aligned to it, and the candidates through the corner (the corner
    itself and its certified blends, :data:`BLEND_SAMPLES`): nothing here depends on the
    joint limits, so re-timings under lowered scaling factors (``adapters``) share it.

    Raises
    ------
        trajectory.HorizonPassed: the arm is already past the horizon point.

    """
    motions = None if checker is None else MotionValidator.of(checker)
    ex = join.executing
    c = continuation(ex.trajectory, ex.time_s(now_ns) + lead_s, horizon_at=join.horizon_index,
                     join_indices=ex.published)
    new = align_to_state(np.asarray(path_rad, dtype=float), c.prefix_rad[-1], scenario.robot.planned_periodic)
    stamp_ns = ex.start_ns + int(round(1e9 * c.join_time_s))
    path = c.join(new)                      # the prefix's rows, then the new path's
    corner = len(c.prefix_rad) - 1          # the horizon point's row
    if join.stop:                           # no corner: the arm stops there (timed_join)
        return JoinedPaths(join, c, new, stamp_ns, (path,))
    turn = _turn_refusal(c, path) if corner == 0 else None
    candidates = [path]
    if 0 < corner < len(path) - 1 and _turn_rad(path, corner) > MIN_CORNER_RAD:
        motions = motions or MotionValidator.for_scene(scenario.robot, scenario.scene)
        for a, b, cand in _corner_blends(path, corner, 1, np.radians(0.5)):
            piece = cand[a - 1:len(cand) - (len(path) - b) + 2]
            if motions.check(piece).ok:
                candidates.append(cand)
    return JoinedPaths(join, c, new, stamp_ns, tuple(candidates), turn)


def joined_motion(scenario, join: Join, path_rad, now_ns: int, lead_s: float = START_LEAD_S, checker=None):
    """
    Build the trajectory to publish for a plan that started at ``join.start_rad``.

    Args:
        scenario: ``problem.Scenario`` (limits, reaction settings).
        join: from :func:`plan_start`.
        path_rad: (M, n) the new plan's path, from the horizon point.
        now_ns: ROS time now, ns.
        lead_s: the join is at least this far in the future, s: the message must reach the
            controller before it (a controller that gets it late switches there with the
            difference of the two accelerations times the delay as a velocity step).
        checker: the scene's ``motion.MotionValidator`` (or its ``collision.CollisionChecker``;
            made when None), to certify the corner blends.

    Returns
    -------
        (trajectory.Trajectory, reaction.ReactionReport or None, stamp_ns, Continuation):
        the trajectory from the join (time 0) through the horizon point to the new goal,
        to be stamped ``stamp_ns``.  (For a remainder followed by a new motion from rest,
        the reaction report covers the new motion: the remainder's was reported before.)

    Raises
    ------
        trajectory.HorizonPassed: the arm is already past the horizon point.
        ValueError: the new path cannot be entered at the arm's speed.

    """
    paths = joined_paths(scenario, join, path_rad, now_ns, lead_s, checker)
    traj, reaction, _ = timed_join(scenario, paths, checker)
    return traj, reaction, paths.stamp_ns, paths.continuation


def timed_join(scenario, paths: JoinedPaths, checker=None, chosen: int | None = None):
    """
    Time a joined plan's paths (:func:`joined_paths`) under the scenario's limits.

    The fastest of ``paths.candidates`` that can be entered at the join's speed (leaving the
    join along the arm's direction, else along their own tangents: :func:`_fastest`); with
    ``chosen`` (a timing's index, the one an earlier timing picked) that timing alone, the
    others only when it cannot be entered.  When none can and the horizon point is the
    executing trajectory's end (its goal, at rest): that trajectory's remainder, then the
    new path from rest.

    Returns
    -------
        (trajectory.Trajectory, reaction.ReactionReport or None, the timing's index (:func:`_fastest`)
        or None for the remainder and the new motion).

    Raises
    ------
        ValueError: the new path cannot be entered at the arm's speed.

    """
    motions = None if checker is None else MotionValidator.of(checker)
    c, ex = paths.continuation, paths.join.executing
    if paths.join.stop:
        after, reaction = timed_motion(scenario, paths.new_rad, motions=motions)
        return _stop_at_horizon(scenario, c).then(after), reaction, None
    try:
        return _fastest(scenario, paths, motions, chosen)
    except ValueError:
        h = paths.join.horizon_index
        if not rests_at(ex, h):
            raise
        after, reaction = timed_motion(scenario, paths.new_rad, motions=motions)
        return _remainder(ex.trajectory, c.index, h).then(after), reaction, None


def _rest_points(ex: Executing) -> np.ndarray:
    """
    Return the executing trajectory's points where the arm comes to rest, increasing: the one rule of rest.

    Its published points (``ex.published``) whose velocities are all exactly 0 (its first point
    from rest, a stop an earlier plan sent: ``Trajectory.then``), where the controller's motion
    rests too, and its last point.
    """
    pub = np.asarray(ex.published, dtype=np.int64)
    still = pub[np.all(ex.trajectory.velocities_rad_s[pub] == 0.0, axis=1)]
    return np.union1d(still, [len(ex.trajectory) - 1])


def rests_at(ex: Executing, index: int) -> bool:
    """Tell whether the arm comes to rest at the executing trajectory's point ``index`` (:func:`_rest_points`)."""
    return bool(np.any(_rest_points(ex) == int(index)))


def next_rest(ex: Executing, index: int) -> int:
    """Return the executing trajectory's first point after ``index`` where the arm rests (:func:`_rest_points`)."""
    rest = _rest_points(ex)
    return int(rest[np.searchsorted(rest, int(index), side="right")]) if index < rest[-1] else int(rest[-1])


def _joins_ahead(ex: Executing, now_ns: int, lead_s: float) -> list:
    """Return the executing trajectory's published points at least ``lead_s`` after ``now_ns``: the join and on."""
    pub = np.asarray(ex.published)
    return [int(j) for j in pub[ex.trajectory.times_s[pub] >= ex.time_s(now_ns) + lead_s]]


def _remainder(traj: Trajectory, first: int, last: int) -> Trajectory:
    """Return ``traj``'s points ``first`` to ``last`` as sent, timed from 0 (the arm follows them)."""
    rest = traj.subset(np.arange(first, last + 1))
    return replace(rest, times_s=rest.times_s - rest.times_s[0])


def _stop_at_horizon(scenario, c):
    """
    Return the arm brought to rest at the horizon point along the executing path, from the join's speed.

    ``c``: the join's ``trajectory.Continuation``; its prefix (the executing path from the join
    to the horizon point) timed from ``c.start_path_speed`` to rest under the scenario's limits
    (the wheels' too): the same path and speed at the join, a new timing that brakes.
    ValueError when the prefix is a single point or too short to stop on.
    """
    if len(c.prefix_rad) < 2:
        raise ValueError("the join is the stopping point itself: no executing path to stop on")
    return _braked(scenario, c.prefix_rad, c.start_path_speed, start_tangent(c))


def _braked(scenario, path_rad, path_speed: float, tangent=None):
    """
    Return ``path_rad`` timed from ``path_speed`` (rad/s along it) to rest; ValueError when too short to stop on.

    ``tangent``: the arm's direction at the start (its velocity over its path speed), or None
    (at rest): the spline re-fitted through the executing rows leaves the start along it, as the
    arm does (with its own end tangent, its curvature there, and the speed the limits allow, were
    off the arm's: a slow arm at a bend of its path could not be stopped on it at all).  A tangent
    the path cannot take (``trajectory.check_start_tangent``: where the executing path nearly turns
    back, the arm's velocity over its path speed is far from unit length) is left out, as a join's
    timings do (``_fastest``'s second choice).  A speed above the velocity limits (lowered while the
    arm moves) is braked to them on the way (``trajectory.time_parameterize(brake_to_limits=True)``).
    """
    if tangent is not None:
        try:
            check_start_tangent(np.asarray(tangent, dtype=float), path_rad)
        except ValueError:
            tangent = None
    return timed_motion(scenario, path_rad, start_path_speed=path_speed, report=False, start_tangent=tangent,
                        brake_to_limits=True)[0]


def resting_join(join: Join, now_ns: int, lead_s: float) -> Join:
    """
    Return where a plan takes over from an arm at rest there: the join, when it is a point where the arm rests.

    The join is the executing trajectory's first published point at least ``lead_s`` after
    ``now_ns`` (:func:`continuation`'s).  Where the arm is at rest there (:func:`rests_at`: the first
    point of a trajectory sent and not begun, the controller holding it until its stamp; or a stop
    an earlier plan sent) before the horizon point, the new plan starts there, from rest, stamped
    when the arm is there (``Join.stop``; ``adapters.starts_at_the_end``), instead of following the
    executing path on to the horizon point and turning there: a target moved again before the arm
    set off goes to the new target from where the arm is.  Else ``join`` as given.
    """
    ex = join.executing
    joins = [] if join.stop else _joins_ahead(ex, now_ns, lead_s)
    if joins and joins[0] < join.horizon_index and rests_at(ex, joins[0]):
        return Join(ex, joins[0], join.horizon_s, stop=True)
    return join


def stopping_join(scenario, join: Join, now_ns: int, lead_s: float, soonest: bool = False) -> Join:
    """
    Return a join where the arm stops on the executing path as soon as the limits allow, with room.

    From the executing trajectory's first published point at least ``lead_s`` after ``now_ns``
    (where the join will be) and from the next (where it will be when the plan runs late): the
    nearest point the arm can stop at along the executing path from its speed and direction
    there under the scenario's limits (found in doubling steps, then by bisection), and then
    the path to it stretched to 1 / ``STOP_ROOM`` of its length (braking from the same speed
    over that much more path needs ``STOP_ROOM`` of the deceleration: room for the chain, which
    re-times the stop with the limits lowered by the controller's overshoot); the farther of
    the two joins' stops, at or after ``join.horizon_index`` (``soonest``: after the join, for an
    executing path that comes within the safety margin of a new scene before the horizon
    point; the plan then has until the join); where the executing trajectory itself comes to rest
    before that, at a stop an earlier plan sent, there, from rest, the arm following it as sent
    until then (``adapters.starts_at_the_end``: re-timed from a re-fitted spline, its braking could
    need a few per cent more path than it has, and a stop searched past it braked through it to
    the end: minutes on a slow servicer); its end when none before it.  (The room as lowered
    limits along the stop, or as scaling factors, did not hold: the timing lets a moving start
    keep the full limits where the arm's speed needs them to enter the path, which took the room
    back; as factors, a start at the arm's speed on a bend could not enter at all.)  The new plan
    starts there from rest (``Join.stop``): for a new path that cannot be entered at speed (it
    turns back, or the arm, slowed by weak wheels, cannot brake within the horizon), sooner than
    waiting for the executing trajectory's end.
    """
    ex = join.executing
    traj = ex.trajectory
    last = len(traj) - 1
    along = np.concatenate([[0.0], np.cumsum(chord_lengths_rad(traj.positions_rad))])   # path length, rad

    def stop_from(j: int) -> int:
        """Return the stop with room from executing point ``j`` (the trajectory's next rest when none before)."""
        rest = next_rest(ex, j)                 # it stops there as sent (adapters.starts_at_the_end): no braking past
        speed = float(traj.path_speed[j])
        tangent = _arm_direction(traj.velocities_rad_s[j], speed)

        def brakes(stop: int) -> bool:
            try:
                _braked(scenario, traj.positions_rad[j:stop + 1], speed, tangent)
            except ValueError:
                return False
            return True

        lo, hi, step = j, j + 1, 1              # lo: too near (the join itself), hi: the next to try
        while hi < rest and not brakes(hi):
            lo, hi, step = hi, min(rest, hi + step), 2 * step
        if hi >= rest:
            return rest
        while hi - lo > 1:                      # the nearest stop at the full limits
            mid = (lo + hi) // 2
            lo, hi = (lo, mid) if brakes(mid) else (mid, hi)
        stop = max(hi, int(np.searchsorted(along, along[j] + (along[hi] - along[j]) / STOP_ROOM)))
        step = 1
        while stop < rest and not brakes(stop):
            stop, step = min(rest, stop + step), 2 * step
        return min(stop, rest)

    joins = _joins_ahead(ex, now_ns, lead_s)[:2]
    if not joins or rests_at(ex, joins[0]):     # the arm comes to rest at the join: from there
        return Join(ex, joins[0] if joins else last, join.horizon_s, stop=True)
    # never past the executing trajectory's own next rest (the horizon point may be beyond it)
    rest = next_rest(ex, joins[0])
    stop = 0 if soonest else min(join.horizon_index, rest)
    for j in joins:                             # the join, or the next point when the plan runs late
        stop = max(stop, stop_from(j) if j < rest else rest)
    return Join(ex, min(stop, rest), join.horizon_s, stop=True)


def committed_path(join: Join, from_ns: int, to_ns: int) -> np.ndarray:
    """
    Return the executing path the arm follows from ROS time ``from_ns`` to ``to_ns``: (K, n) rows, rad.

    Along the chain of trajectories it follows (``Executing.previous`` before each one's start:
    a trajectory joined to one that had not started yet is reached on the one before), each
    one's dense rows in the stretch and the positions at the stretch's ends and at the switches
    (K = 0 when ``to_ns`` is not after ``from_ns``; before the oldest one's start, at its first
    point; after the newest one's end, at its last).  A plan that switches at ``to_ns`` leaves
    the arm on it until then: what it must keep clear in the plan's scene from the earliest a new
    message can take over (``from_ns``: now + the lead).
    """
    chain, link = [], join.executing
    while link is not None:
        chain.append(link)
        link = link.previous
    chain.reverse()                                   # the oldest first
    n = chain[-1].trajectory.positions_rad.shape[1]
    if to_ns <= from_ns:
        return np.zeros((0, n))
    rows = []
    for i, link in enumerate(chain):
        traj = link.trajectory
        a_ns = from_ns if i == 0 else max(from_ns, link.start_ns)
        b_ns = to_ns if i + 1 == len(chain) else min(to_ns, chain[i + 1].start_ns)
        if b_ns < a_ns or (rows and b_ns == a_ns):
            continue
        ta = min(max(0.0, link.time_s(a_ns)), traj.duration_s)
        tb = min(max(0.0, link.time_s(b_ns)), traj.duration_s)
        t = traj.times_s
        rows += [sample(traj, ta)[0], *traj.positions_rad[(t > ta) & (t < tb)], sample(traj, tb)[0]]
    return np.array(rows).reshape(-1, n)


def start_tangent(c) -> np.ndarray | None:
    """
    Return the direction a joined path leaves the join along: the arm's velocity over its path speed, (n,).

    ``c``: the ``trajectory.Continuation``.  The executing trajectory's own path tangent at the
    join (its velocity is that tangent times its path speed, over the same rows), so the joined
    timing starts with the arm's velocity, not the tangent a spline re-fitted through a few rows
    of executing path and the new path's corner gives (up to 7 % off it on the paper's 3-DOF
    scene).  None at rest (nothing to keep: the path's own tangent).
    """
    return _arm_direction(c.start_velocity_rad_s, c.start_path_speed)


def _arm_direction(velocity_rad_s, path_speed: float) -> np.ndarray | None:
    """Return the arm's direction along its path, its velocity (n,) over its path speed; None at rest."""
    if not path_speed > 0.0:
        return None
    return np.asarray(velocity_rad_s, dtype=float) / float(path_speed)


def _fastest(scenario, paths: JoinedPaths, motions, chosen: int | None = None):
    """
    (trajectory, reaction, index) of the fastest timing of ``paths``' candidates (``chosen`` alone when it times).

    Timing i < K (the candidates' count) leaves the join along the arm's own direction
    (:func:`start_tangent`); only where none of those can be entered at the arm's speed, timing
    K + i leaves it along candidate i's re-fitted tangent (a path turning just after the join,
    which the arm's direction would take too sharply at its speed; the published first point
    still has the arm's velocity: ``adapters._in_the_arms_state``, the controller's quintic from
    it checked as every other).  A join's speed above the velocity limits (lowered while the arm
    moves) is braked to them first (``brake_to_limits``).  ValueError when none can be entered at
    the join's speed.
    """
    k = len(paths.candidates)
    speed, tangent = paths.continuation.start_path_speed, start_tangent(paths.continuation)

    def timing(j):
        return timed_motion(scenario, paths.candidates[j % k], start_path_speed=speed,
                            start_tangent=tangent if j < k else None, motions=motions, brake_to_limits=True)

    err = None
    if chosen is not None:
        try:
            return (*timing(chosen), chosen)
        except ValueError as e:
            err = e
    own = paths.turn_refusal is None            # the own tangents may be taken (the velocity does not step)
    groups = [range(k)] if tangent is None or not own else [range(k), range(k, 2 * k)]
    for group in groups:
        best = None
        for j in group:
            if j == chosen:
                continue
            try:
                got = timing(j)
            except ValueError as e:
                err = err or e
                continue
            if best is None or got[0].duration_s < best[0][0].duration_s:
                best = (got, j)
        if best is not None:
            return (*best[0], best[1])
    if not own:
        raise ValueError(f"{paths.turn_refusal}; leaving along the arm's direction: {err}")
    raise err
