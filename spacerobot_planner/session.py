"""
A capture session: requests from any channel in, what to publish out.  No rclpy.

The node (``ros/planner_node.py``) turns messages into calls of a :class:`CaptureSession`
and its answers into messages; everything between is here:

- **requests** from any channel (a topic target, a joint goal, an action goal, a replan,
  a parameter change): :meth:`CaptureSession.submit`.  The latest request wins: a newer
  one supersedes the one queued and cancels the one being planned (its result is dropped),
  except under a stream of topic targets, where a plan is let finish once nothing was
  published for ``min_publish_period_s``.  A request without its own start waits for the
  first joint state.  Requests with their own start (what-if queries, returned, not executed)
  are a stream of their own: the latest query supersedes an older query only, never a request
  the arm executes (nor the other way round); the worker takes the two queues' requests in the
  order they came.
- **the current goal**: the latest accepted request from any channel (its target or its
  joint goal) is what a replan or a parameter change plans to; a request with its own
  ``start_rad`` (an action goal's) is planned and returned, not executed, and changes
  nothing.  A joint goal is planned in the scene of the current target (the obstacle).
- **the start**: its own, or the arm's measured state at rest, or (the arm following the
  trajectory last published) the point ``horizon_s`` ahead on it
  (``replanning.plan_start``; a trajectory published but not started yet is joined like
  one running: joint_trajectory_controller keeps a waiting trajectory until a newer one's
  stamp, when that is later, as the mock arm does; where it starts beyond the horizon (a plan
  from the end of the running one), the running one is joined, and the new message, stamped
  first, drops the waiting ones).
- **ONE post-processing chain** (``adapters.post_process``: time, reaction, resampling
  certified with the scene's ``motion.MotionValidator``, arm/attitude split), the same
  as ``spacerobot-plan``'s.
- **retries**: when a joined plan cannot be published (it took longer than the horizon,
  the new path cannot be entered at the arm's speed, or the join is less than
  ``start_lead_s`` ahead when it would be published) it is planned again with twice the
  horizon, then stopping on the executing path as soon as the limits allow
  (``replanning.stopping_join``), then from the executing trajectory's end, then from the
  measured state at rest (:data:`RETRY`), this last only where the arm does not follow its
  trajectory or it has ended: else the request fails (:data:`JOIN_FAILED`, nothing sent; the arm
  finishes its trajectory), as a trajectory from rest would not start where the arm is.  A plan
  from a moving arm is judged on the whole motion it commits the arm to, in its own scene
  (:meth:`CaptureSession._exposure`: the executing path up to its switch, then its trajectory
  as the controller moves the arm): where a new target lies on the executing path it stops on
  it right after the join (not on to the end), and what cannot be avoided is published with a
  warning (``trajectory_certified: false``): where no stop fits the limits either, the plan from
  the executing trajectory's end (the arm goes there on it whatever is sent).
- **the stamp**: every published trajectory starts at least ``start_lead_s`` after it is
  published: a trajectory from rest is stamped now + the lead just before it is
  published; a joined one carries the join's time, checked then to be still at least the
  lead ahead (else the retry above).  A plan starting at the end of an executing
  trajectory that ends within the lead, and the retry from the end, start there at rest,
  stamped no earlier than that end (the arm comes to rest there on the trajectory it
  follows; ``adapters.starts_at_the_end``): a stamp the chain's time cannot overtake, so
  the retry from the measured state is left for an arm that does not follow.
- **the at-goal rule**: a plan along which nothing moves more than
  ``adapters.AT_GOAL_TOL_RAD`` publishes nothing and says so.

What to publish is plain data (:class:`Publication`: the stamp in ns, the arm's and the
attitude's :class:`adapters.TrajectoryPart`), handed with the request's
:class:`Outcome` (code, reason, the ``PlanResult``, diagnostics values) to the hooks
given to the session: ``publish`` (ok outcomes, in the worker thread, just after the stamp
was taken), ``record`` (every finished request but a superseded one), ``log``,
``changed`` (planning began) and ``now_ns`` (the ROS clock).  One worker thread plans
(:meth:`start`); tests may instead call :meth:`run_once`.
"""

from __future__ import annotations

import math
import threading
import time
import traceback
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from .adapters import (AT_GOAL_TOL_RAD, Processed, TrajectoryPart, braking_text, post_process, switching_at_arrival,
                       uncertified_text)
from .cores import threads_text
from .motion import MotionValidator
from .replanning import (MAX_STATE_AGE_S, STATE_WAIT_S, Executing, committed_path, join_direction, plan_start,
                         resting_join, stopping_join)
from .scene import Target
from .settings import SWITCH_UNTIL_FOUND, SessionSettings
from .trajectory import HorizonPassed
from .worker import STAGE_ORDER, PlanCrash, PlanDone, PlanError, PlanJob, Progress

__all__ = ["CaptureSession", "Request", "Outcome", "Publication", "RETRY", "JOIN_FAILED", "WAITING_STAGE",
           "CHAIN_ALLOWANCE_S",
           "stamp_for", "target_why"]

#: the feedback stage of a request that waits for the first joint state
WAITING_STAGE = "waiting_for_joint_states"
#: a join is chosen this much more than the lead ahead: the chain's own time after it is chosen
#: (time parameterisation with its corner blends, the controller check and re-timing, resampling
#: and certification, the record): tens of ms idle, up to 0.43 s measured on a loaded 2-core
#: machine (three test workers, a target flood), s
CHAIN_ALLOWANCE_S = 0.3
#: what a further attempt does after a join failed (index = the attempt)
RETRY = ("", "with twice the horizon", "stopping on the executing path as soon as the limits allow",
         "from the end of the executing trajectory", "from the measured state, at rest")
#: a flood of requests: at most FLOOD_LINES log lines of a kind (planning, superseded) in FLOOD_WINDOW_S
FLOOD_LINES, FLOOD_WINDOW_S = 5, 1.0
#: a request planned again this many times for ROS time jumping back fails (two /clock sources, a bag on a loop)
TIME_JUMPS_MOST = 3
#: the attempt from the measured state, at rest (RETRY); an outcome planned again from there at once
AT_REST = len(RETRY) - 1
RETRY_AT_REST = "retry_at_rest"
#: the code of a request whose every attempt to take over the moving arm failed (node only, like "superseded")
JOIN_FAILED = "join_failed"
#: the attempt that starts from the executing trajectory's end, at rest (RETRY)
FROM_THE_END = 3
#: the attempt that stops on the executing path (RETRY; right after the join when ``Request.stop_soonest``)
STOPPING = FROM_THE_END - 1


@dataclass(eq=False)
class Request:
    """
    One request, from any channel, as the session plans it.

    ``scenario`` is the session's at submission, its scene with the request's target (a
    target request) or the current target (a joint goal, a replan); ``settings`` likewise.
    """

    gen: int
    why: str
    scenario: object
    settings: SessionSettings
    joint_goal: np.ndarray | None
    t_request: float
    start_rad: np.ndarray | None = None          # its own start: planned, not executed
    on_done: Callable | None = None              # called once with the Outcome
    on_progress: Callable | None = None          # worker.Progress while planning
    cancelled: str | None = None                 # reason, once cancelled
    keep: bool = False                           # finish and publish although superseded (a stream)
    plan_cancelled: bool = False                 # its plan was cancelled in the backend (superseded)
    attempt: int = 0                             # planned again after a join failed (RETRY)
    stop_soonest: bool = False                   # its stop (RETRY's) right after the join: the path ahead is not clear
    stop_failed: str | None = None               # why its last stop on the executing path was not published
    stop_again: bool = False                     # its stop was planned again once after it came too late
    waiting: bool = False                        # waited for the first joint state
    job: int = 0                                 # the backend's job number (its cancels), given when it is taken
    time_jumps: int = 0                          # planned again after ROS time jumped (TIME_JUMPS_MOST)


@dataclass(frozen=True, eq=False)
class Publication:
    """
    What goes to the controllers: one stamp for both parts (they start together).

    ``arm``/``attitude``: ``adapters.TrajectoryPart`` or None; both None at the goal.
    ``execute``: False for a plan from a request's own start (returned, not sent).
    ``predicted_drift``: free floating, the attitude as it will drift and the body's
    displacement (``adapters.predicted_drift``): reported (the action's result), never sent.
    """

    stamp_ns: int
    arm: TrajectoryPart | None
    attitude: TrajectoryPart | None
    execute: bool = True
    predicted_drift: TrajectoryPart | None = None

    @property
    def at_goal(self) -> bool:
        return self.arm is None and self.attitude is None

    @property
    def sent(self) -> bool:
        """Tell whether the parts go to the controllers (executed and not at the goal)."""
        return self.execute and not self.at_goal


@dataclass(eq=False)
class Outcome:
    """
    How a request ended: code (a planner code, ``superseded``, ``cancelled``), reason.

    On success also the ``PlanResult``, the published ``Trajectory`` (all planned joints),
    the :class:`Publication`, the chain's ``adapters.Processed``, the plan's start and the
    diagnostics values.
    """

    code: str
    reason: str = ""
    result: object = None
    trajectory: object = None
    publication: Publication | None = None
    values: dict = field(default_factory=dict)
    processed: Processed | None = None
    start_rad: np.ndarray | None = None
    #: where the request's time went, ``time.perf_counter()`` s: "request" (made), "planning"
    #: (its attempt began: the start chosen), "received" (the backend's answer), "chain" (the
    #: chain after the path done), "published" (the publish hook returned; ok outcomes); from a
    #: planning process also "process_received" and "process_answered" (it had the job, its
    #: outcome was ready: ``worker.PlanDone.stats``)
    stamps: dict = field(default_factory=dict)

    @property
    def ok(self) -> bool:
        return self.code == "ok"


def stamp_for(processed: Processed, now_ns: int, lead_s: float) -> int | None:
    """
    Return the stamp of a trajectory published at ``now_ns``, or None when the join is too close.

    From rest: ``now_ns`` + the lead (from the executing trajectory's end: not before that
    end).  Joined, or from rest where the executing trajectory stops before its end
    (``Processed.stamp_exact``): the join's time (the stop's), when it is still at least the lead
    ahead (None otherwise: plan again).  Either way the trajectory also ends at least the lead
    after ``now_ns``.
    """
    lead_ns = int(round(lead_s * 1e9))
    stamp = processed.fixed_stamp_ns
    if stamp is None:        # from rest (at the executing trajectory's end: not before it)
        return max(int(now_ns) + lead_ns, int(processed.not_before_ns or 0))
    end = stamp + int(round(processed.trajectory.duration_s * 1e9))
    return stamp if stamp - int(now_ns) >= lead_ns and end - int(now_ns) >= lead_ns else None


def target_why(target: Target) -> str:
    """Describe a new target in a request's ``why``."""
    return (f"new target ({target.center_m[0]:.3f}, {target.center_m[1]:.3f}) m, "
            f"yaw {math.degrees(target.yaw_rad):.1f}°")


def _from_rest_on(join) -> str:
    """Say where on the executing trajectory a plan from rest starts (its end or start, a stop an earlier plan sent)."""
    ex, h = join.executing, join.horizon_index
    if h == len(ex.trajectory) - 1:
        return "no (from the end of the executing trajectory, at rest)"
    if h == 0:
        return "no (from the start of the executing trajectory, sent and not begun, at rest)"
    return f"no (from where the executing trajectory stops, {ex.trajectory.times_s[h]:.3f} s into it, at rest)"


def _ahead_s(join, now_ns: int) -> float:
    """Return how far ahead of ``now_ns`` the join's point is on the executing trajectory, s."""
    ex = join.executing
    return float(ex.trajectory.times_s[join.horizon_index]) - ex.time_s(now_ns)


def _late(reason: str) -> Outcome:
    """Return a retry because the plan came too late for its join (``values["late"]``; not the limits or the scene)."""
    return Outcome("retry", reason, values={"late": True})


def _superseded(newer: Request) -> Outcome:
    return Outcome("superseded", f"superseded by request #{newer.gen} ({newer.why})")


def _progress(stage):
    return Progress(0, stage, STAGE_ORDER.index(stage) / len(STAGE_ORDER))


def _quiet(level, text):
    pass


class CaptureSession:
    """
    See the module docstring.

    Parameters
    ----------
        scenario: ``problem.Scenario`` (the parameters' scene: its target is the first current target).
        settings: ``settings.SessionSettings``.
        now_ns: the clock of the stamps and the joint states (ROS time), ns.
        log(level, text): "info", "warning" or "error".
        publish(request, outcome): an ok outcome, to publish (``outcome.publication``).
        record(request, outcome): a finished request (ok or failed; not a superseded one).
        changed(): the session began planning (``activity`` is "planning").
        clock_problem(): why ``now_ns`` cannot stamp a trajectory now (ROS time under
            ``use_sim_time`` before the first ``/clock``), else None: a request planned then fails
            with it (``invalid_input``).

    """

    def __init__(self, scenario, settings: SessionSettings | None = None, *, now_ns: Callable[[], int] = time.time_ns,
                 log: Callable = _quiet, publish: Callable | None = None, record: Callable | None = None,
                 changed: Callable | None = None, clock_problem: Callable[[], str | None] | None = None):
        self.lock = threading.Condition()
        self.scenario = scenario
        self.settings = settings or SessionSettings()
        self.now_ns = now_ns
        self._clock_problem = clock_problem or (lambda: None)
        self.time_epoch = 0              # time_jumped's count: a plan begun before a jump is planned again
        self._flood = {}                 # _log_flood: kind -> (window start, said, left out, the last left out)
        self.log = log
        self._publish = publish or (lambda req, out: None)
        self._record = record or (lambda req, out: None)
        self._changed = changed or (lambda: None)
        self.target: Target | None = scenario.scene.target      # the current target
        self.joint_goal = None           # (dof,) rad when the current goal is a joint goal
        self.requested_target = None     # the target of the last target request that became current
        self.gen = 0
        self._jobs = 0                   # the backend's job numbers, in the order the requests are taken
        self._pending: Request | None = None      # the next request the arm executes
        self._query: Request | None = None        # the next request with its own start (returned, not executed)
        self._waiting: Request | None = None      # waits for the first joint state
        self._active: Request | None = None
        self._latest: Request | None = None       # the latest request the arm executes
        self._latest_query: Request | None = None  # the latest request with its own start
        self.accepting = False           # requests are taken (the node is active)
        self._stop = True                # no worker until started
        self.closing = False             # stop() runs
        self.joint_q = None              # latest planned-joint positions (raw, unwrapped), rad
        self.joint_ns = 0                # its ROS time, ns
        self.joint_prev_ns = 0           # the ROS time of the joint state before it, ns (0: none)
        self.joint_refused = None        # why the joint states after it were refused (None: none were)
        self._state_wanted = False       # the worker waits for a recent joint state (_arm_state)
        self.executing: Executing | None = None      # the trajectory last sent to the arm
        self.last_sent: Publication | None = None    # ... as it was sent (controller.switch: arrival)
        self.controller_switch_found = None          # the controller's kind the node found (controller_found)
        self.activity = "idle"           # "idle" or "planning"
        self.last_result = None          # PlanResult of the last ok plan
        self.last_trajectory = None      # its published Trajectory
        self.last_publish_t = time.monotonic()
        self.backend = None
        self.worker: threading.Thread | None = None
        self._motions = (None, None)     # (scene, its MotionValidator)
        self._with_target = (None, None, None)   # (scenario, target, the scenario with the target)

    # ------------------------------------------------------------------ set-up
    def controller_found(self, switch: str | None) -> None:
        """
        Take the kind of the arm's controller as the node found it ("stamp", "arrival"; None: not known).

        Only ``controller.switch: auto`` reads it (:attr:`controller_switch`); a trajectory is sent for
        the kind known when it is sent.
        """
        self.controller_switch_found = switch

    @property
    def controller_switch(self) -> str:
        """Return when the arm's controller is taken to switch to a newer trajectory: "stamp" or "arrival"."""
        switch = self.settings.controller_switch
        if switch == "auto":
            return self.controller_switch_found or SWITCH_UNTIL_FOUND
        return switch

    def configure(self, scenario, settings: SessionSettings, target_changed: bool = False,
                  target_resized: bool = False) -> None:
        """
        Take new parameters (a validated change).

        ``target_changed``: the scenario's target becomes current (its pose changed); else
        ``target_resized``: the current target (a ``target_pose``'s too) takes the scenario's
        target's sizes, where it is.
        """
        with self.lock:
            self.scenario, self.settings = scenario, settings
            new = scenario.scene.target
            if target_changed:
                self.target = new
            elif target_resized and new is not None:
                if self.target is not None:
                    self.target = self.target.sized_as(new)
                if self.requested_target is not None:
                    self.requested_target = self.requested_target.sized_as(new)

    def start(self, backend, thread: bool = True) -> None:
        """Plan with ``backend`` (``worker.ProcessBackend`` or ``ThreadBackend``), in the worker thread (``thread``)."""
        with self.lock:
            self.backend = backend
            self._stop = False
            self.closing = False
        if thread:
            self.worker = threading.Thread(target=self._worker_loop, name="spacerobot_planner-worker", daemon=True)
            self.worker.start()

    def accept(self, on: bool, why: str = "") -> None:
        """Take requests (activate) or not (deactivate: what is queued or planned is cancelled with ``why``)."""
        with self.lock:
            self.accepting = on
            if on:
                self.activity = "idle"
                self.last_publish_t = time.monotonic()
            else:
                self.drop(why)

    def stop(self, timeout_s: float = 5.0) -> bool:
        """
        Stop the worker (a plan in progress is cancelled) and close the backend.

        Every request ends (cancelled: the node is shutting down).  False when nothing was running.
        """
        with self.lock:
            if self._stop and self.worker is None and self.backend is None:
                return False
            self.closing = True
            was_planning = self._active is not None
            self._stop = True
            self.accepting = False
            self.drop("the node is shutting down")
            self.lock.notify_all()
        if was_planning:
            self.log("info", "shutdown: the plan in progress is cancelled")
        backend, self.backend = self.backend, None
        if backend is not None:
            backend.close()
        if self.worker is not None:
            self.worker.join(timeout_s)
            self.worker = None
        return True

    # ------------------------------------------------------------------ inputs
    def joint_state(self, q_rad, stamp_ns: int) -> None:
        """Take the arm's measured planned-joint positions (rad) at ROS time ``stamp_ns``."""
        with self.lock:
            self.joint_q = np.asarray(q_rad, dtype=float)
            self.joint_prev_ns, self.joint_ns = self.joint_ns, int(stamp_ns)
            self.joint_refused = None
            if self._state_wanted:
                self.lock.notify_all()
            waiting, self._waiting = self._waiting, None
            if waiting is not None:
                self._replace_pending(waiting)

    def joint_state_refused(self, reason: str) -> None:
        """
        Take notice that the arm's latest joint state was refused (``reason``).

        A plan from the arm's state waits for one to be taken, up to ``STATE_WAIT_S``, then fails
        (``invalid_input``, saying why): the last one taken is a state the arm has left.
        """
        with self.lock:
            self.joint_refused = reason

    def time_jumping(self) -> None:
        """
        Take notice that ROS time is about to jump (rclpy's pre-jump callback; :meth:`time_jumped` follows).

        Under the lock, before the time changes: a plan that stamps its trajectory meanwhile
        does so wholly in the time before, and sees the jump at its next check.
        """
        with self.lock:
            self.time_epoch += 1

    def time_jumped(self, what: str) -> None:
        """
        Take a jump of ROS time back, or a change of its source (``what``: for the log line).

        The trajectory last sent and the joint states' stamps belong to the time before: the
        trajectory is forgotten (the next plan starts from the arm's measured state, at rest,
        stamped in the new time; a join on it would be stamped where the old time was: seconds
        or minutes ahead, the arm parked meanwhile), the last measured state is kept, stamped now
        (the next joint_states replace it).  A plan begun before the jump is planned again when
        it ends, from rest (its start and stamps were taken in the old time).
        """
        with self.lock:
            forgot = self.executing is not None
            self.executing = self.last_sent = None
            self.time_epoch += 1
            if self.joint_q is not None:
                self.joint_ns, self.joint_prev_ns = int(self.now_ns()), 0
            planning = self._active is not None
        self.log("warning", f"ROS time {what}: "
                 + ("the trajectory last sent is forgotten, " if forgot else "")
                 + "the next plan starts from the arm's measured state, at rest"
                 + ("; the plan under way is planned again" if planning else ""))

    def same_target(self, target: Target) -> str | None:
        """Say why a topic target is not a new request (within tolerance of the current one), else None."""
        s = self.settings
        with self.lock:
            prev, joint_goal = self.requested_target, self.joint_goal
        if prev is None or joint_goal is not None:
            return None
        dist = math.hypot(target.center_m[0] - prev.center_m[0], target.center_m[1] - prev.center_m[1])
        dyaw = abs(math.degrees(math.remainder(target.yaw_rad - prev.yaw_rad, 2 * math.pi)))
        if dist <= s.target_tolerance_m and dyaw <= s.target_tolerance_deg:
            return f"target_pose within tolerance of the current target ({dist:.4f} m, {dyaw:.2f}°): no replan"
        return None

    def request(self, why: str, *, target: Target | None = None, joint_goal=None, start_rad=None,
                on_done: Callable | None = None, on_progress: Callable | None = None) -> Request:
        """Make a request, not yet submitted: to ``target``, to ``joint_goal``, or (neither) to the current goal."""
        with self.lock:
            if target is None and joint_goal is None:
                joint_goal = self.joint_goal
                target = None if joint_goal is not None else self.target
            scene_target = target if target is not None else self.target
            scenario = self._scenario_with(scene_target)
            return Request(0, why, scenario, self.settings,
                           None if joint_goal is None else np.array(joint_goal, dtype=float),
                           time.perf_counter(), start_rad=None if start_rad is None else np.asarray(start_rad),
                           on_done=on_done, on_progress=on_progress)

    def _scenario_with(self, target: Target | None):
        """
        Return the session's scenario with ``target`` in its scene (lock held).

        The same object for the same scenario and target (a replan): its scene keeps its one
        ``MotionValidator`` (:meth:`motions`).
        """
        if target is None:
            return self.scenario
        base, held, scenario = self._with_target
        if base is not self.scenario or held is not target:
            scenario = self.scenario.with_scene(self.scenario.scene.with_target(target))
            self._with_target = (self.scenario, target, scenario)
        return scenario

    def submit(self, req: Request | str, **kw) -> Request:
        """
        Submit a request (or make one from ``why`` and the keywords of :meth:`request`).

        Its ``gen`` is 0 when refused (not accepting: it ends cancelled at once); ``waiting``
        when it waits for the first joint state.
        """
        if isinstance(req, str):
            req = self.request(req, **kw)
        with self.lock:
            if not self.accepting:
                self._finish(req, Outcome("cancelled", "the node is not active"))
                return req
            self.gen += 1
            req.gen = self.gen
            self._make_current(req)
            if req.start_rad is not None:       # a query: its own stream (supersedes an older query only)
                if self._query is not None:
                    self._finish(self._query, _superseded(req))
                self._query = self._latest_query = req
                active = self._active
                if active is not None and active.start_rad is not None:
                    active.plan_cancelled = True
                    self._cancel_job(active)
                self.lock.notify_all()
                return req
            if self.joint_q is None:
                if self._waiting is not None:
                    self._finish(self._waiting, _superseded(req))
                self._waiting = req
                req.waiting = True
                self.log("info", f"request #{req.gen} ({req.why}): waiting for joint_states")
                if req.on_progress is not None:
                    req.on_progress(Progress(req.gen, WAITING_STAGE, 0.0))
            else:
                self._replace_pending(req)
            self._latest = req
            active = self._active
            if active is not None and active.start_rad is None:
                period = float(req.settings.min_publish_period_s)
                starving = period > 0 and time.monotonic() - self.last_publish_t >= period
                if starving and active.on_done is None and req.on_done is None and not active.plan_cancelled:
                    active.keep = True          # a stream of targets: let this one be published
                elif self.backend is not None:
                    # supersede the plan in progress, kept or not (a goal after a stream's target had
                    # cancelled a kept plan, which then ended as an outcome "cancelled" with no reason)
                    active.keep = False
                    active.plan_cancelled = True
                    self._cancel_job(active)
            self.lock.notify_all()
            return req

    def expire_waiting(self, req: Request, why: str) -> bool:
        """End ``req`` with ``invalid_input`` (``why``) if it still waits for the first joint state."""
        with self.lock:
            expired = self._waiting is req
            if expired:
                self._waiting = None
        if expired:
            outcome = self._failure(req, "invalid_input", why)
            self._record(req, outcome)
            with self.lock:
                self._finish(req, outcome)
        return expired

    def cancel(self, req: Request, reason: str) -> None:
        """Cancel one request (queued, waiting or being planned)."""
        with self.lock:
            if self._pending is req:
                self._pending = None
                self._finish(req, Outcome("cancelled", reason))
            elif self._query is req:
                self._query = None
                self._finish(req, Outcome("cancelled", reason))
            elif self._waiting is req:
                self._waiting = None
                self._finish(req, Outcome("cancelled", reason))
            elif self._active is req:
                req.cancelled = reason
                self._cancel_job(req)
                self.lock.notify_all()          # a wait for a joint state ends (_arm_state)

    def drop(self, why: str) -> None:
        """Cancel everything queued or being planned."""
        with self.lock:
            for attr in ("_pending", "_query", "_waiting"):
                req = getattr(self, attr)
                if req is not None:
                    setattr(self, attr, None)
                    self._finish(req, Outcome("cancelled", why))
            if self._active is not None:
                self._active.cancelled = why
                self._cancel_job(self._active)
                self.lock.notify_all()          # a wait for a joint state ends (_arm_state)

    @property
    def planning(self) -> bool:
        """Tell whether a request is being planned."""
        return self._active is not None

    # ------------------------------------------------------------------ bookkeeping (lock held)
    def _cancel_job(self, req: Request) -> None:
        """Cancel the backend's job of the request being planned (``req``)."""
        if self.backend is not None:
            self.backend.cancel(req.job)

    def _next(self) -> Request | None:
        """
        Take the next request to plan: the older of the two queues' (the arm's, the queries'); None when none.

        It gets the next job number.  The backends cancel every job up to a number
        (``worker._GenCancel``), so the numbers follow the order the requests are taken in, not
        the requests' own (a request of the arm's that waited for the first joint state is taken
        after a query submitted later: cancelling that query must not cancel it).
        """
        queued = [r for r in (self._pending, self._query) if r is not None]
        if not queued:
            return None
        req = min(queued, key=lambda r: r.gen)
        if req is self._pending:
            self._pending = None
        else:
            self._query = None
        self._jobs += 1
        req.job = self._jobs
        return req

    def _make_current(self, req: Request) -> None:
        """Make the goal of an accepted request the current goal (not that of one with its own start)."""
        if req.start_rad is not None:
            return
        if req.joint_goal is not None:
            self.joint_goal = req.joint_goal
        else:
            self.target = self.requested_target = req.scenario.scene.target
            self.joint_goal = None

    def _replace_pending(self, req: Request) -> None:
        """``req`` becomes the next request; the one it replaces is superseded."""
        if self._pending is not None:
            self._finish(self._pending, _superseded(req))
        if self._waiting is not None and self._waiting is not req:
            self._finish(self._waiting, _superseded(req))
            self._waiting = None
        self._pending = req
        self.lock.notify_all()

    @staticmethod
    def _finish(req: Request, outcome: Outcome) -> None:
        """Every request ends here exactly once."""
        cb, req.on_done = req.on_done, None
        if cb is not None:
            cb(outcome)

    # ------------------------------------------------------------------ planning
    def _worker_loop(self):
        while True:
            with self.lock:
                while self._pending is None and self._query is None and not self._stop:
                    self.lock.wait()
                if self._stop:
                    return
                req = self._next()
                self._active = req
            self._run(req)

    def run_once(self) -> Outcome | None:
        """Plan the queued request in this thread (instead of the worker); None when there is none."""
        with self.lock:
            req = self._next()
            if req is None:
                return None
            self._active = req
        return self._run(req)

    def _run(self, req: Request) -> Outcome:
        outcome, tried = None, []          # the attempts made (RETRY's indices)
        while outcome is None:
            executes = req.start_rad is None           # a goal with its own start is returned, not stamped
            problem = self._clock_problem() if executes else None
            if problem is not None:
                outcome = self._failure(req, "invalid_input", problem)
                break
            outcome = self._refused_state(req) if executes else None
            if outcome is not None:
                break
            tried.append(req.attempt)
            try:
                epoch = self.time_epoch if executes else None
                outcome = self._plan(req, *self._start_of(req), epoch=epoch)
            except Exception as e:      # noqa: BLE001 - never let the worker die
                outcome = self._failure(req, "internal_error", f"planning crashed: {type(e).__name__}: {e}",
                                        tb=traceback.format_exc())
            if outcome.code == RETRY_AT_REST:
                req.time_jumps += 1
                if req.time_jumps >= TIME_JUMPS_MOST:
                    outcome = self._failure(req, "invalid_input", f"ROS time jumped back {req.time_jumps} times "
                                            "while this request was planned (two /clock publishers? a bag played "
                                            "on a short loop?)")
                    break
            if outcome.code == "retry" and req.attempt == STOPPING:
                req.stop_failed = outcome.reason
                if outcome.values.get("late") and not req.stop_again:      # a stop came late: once more, from now
                    req.stop_again = True
                    self.log("warning", f"plan #{req.gen}: {outcome.reason}; planning again " + RETRY[STOPPING])
                    outcome = None
                    continue
            if outcome.code in ("retry", RETRY_AT_REST):
                req.attempt = AT_REST if outcome.code == RETRY_AT_REST else req.attempt + 1
                if req.attempt >= AT_REST and outcome.code == "retry":
                    try:
                        moving = self._still_moving(req)
                    except Exception as e:      # noqa: BLE001 - never let the worker die
                        outcome = self._failure(req, "internal_error", f"the arm's state: {type(e).__name__}: {e}",
                                                tb=traceback.format_exc())
                        break
                    if moving is not None:      # a trajectory from rest would not start where the arm is
                        ways = ", ".join(RETRY[a] or "joined to it" for a in sorted(set(tried)))
                        outcome = self._failure(req, JOIN_FAILED, f"{moving} and no new trajectory can take over "
                                                f"from it (tried: {ways}; the last: {outcome.reason}); nothing was "
                                                "sent: the arm finishes the trajectory it follows")
                        break
                self.log("warning", f"plan #{req.gen}: {outcome.reason}; planning again "
                         + RETRY[min(req.attempt, len(RETRY) - 1)])
                outcome = None
        with self.lock:
            self._active = None
            idle = self._pending is None and self._query is None
            if idle:
                self.activity = "idle"
        if idle:
            self._flush_flood()
        if not outcome.ok and outcome.code != "superseded":
            self._record(req, outcome)
        with self.lock:
            self._finish(req, outcome)
        return outcome

    def _still_moving(self, req: Request) -> str | None:
        """
        Say how the arm follows the trajectory last sent, running or waiting for its start; else None.

        Then a trajectory from the measured state at rest would not start where the arm is at its
        stamp (a controller refuses a first point at time 0 that is not its state, or jumps): the
        arm is on that trajectory then, or at its end, or (one waiting) about to leave for it; a
        stamp estimated ahead could not tell which (the plan and the chain take what they take).
        None where the arm does not follow it (a stalled arm, one pushed away: the retry from rest
        is for it) or it has ended.
        """
        with self.lock:
            q, q_ns, ex = self.joint_q, self.joint_ns, self.executing
        if ex is None or q is None:
            return None
        s = req.settings
        now = self.now_ns()
        # plan_start's rule of following (any horizon above 0: only whether it joins is asked)
        _, join, _ = plan_start(ex, now, q, q_ns, max(float(s.horizon_s), 1e-3), float(s.follow_tolerance_rad),
                                req.scenario.robot.planned_periodic)
        if join is None:
            return None
        left_s = ex.trajectory.duration_s - ex.time_s(now)
        return f"the arm follows its trajectory ({left_s:.2f} s from its end)"

    def _refused_state(self, req: Request) -> Outcome | None:
        """
        Wait while the arm's latest joint state is a refused one; return None once one is taken.

        Up to ``STATE_WAIT_S`` (a driver's next state ends a glitch); then ``req``'s failure
        (``invalid_input``, the refusal's reason): no plan starts from an older state the arm has
        left.  Its supersession when a newer request came meanwhile.
        """
        deadline = time.monotonic() + STATE_WAIT_S
        with self.lock:
            while self.joint_refused is not None:
                gone = self._superseded_by(req)
                if gone is not None:
                    return gone
                left = deadline - time.monotonic()
                if left <= 0.0:
                    break
                self._state_wanted = True
                self.lock.wait(min(left, 0.1))
            self._state_wanted = False
            refused = self.joint_refused
        if refused is None:
            return None
        return self._failure(req, "invalid_input", f"the arm's latest joint_states was refused ({refused}) and "
                             f"none was taken within {STATE_WAIT_S:g} s: no plan starts from an older state the "
                             f"arm has left")

    def _start_of(self, req: Request):
        """
        Return (start_raw, replanning.Join or None) of a request's attempt.

        Its own start, or the arm's state, or (the arm moving on the last trajectory) the point
        ``horizon_s`` ahead on it; attempts after a failed join: :data:`RETRY`.
        """
        if req.start_rad is not None:
            return req.start_rad, None
        q, q_ns, ex = self._arm_state(req)
        s = req.settings
        horizon_s = float(s.horizon_s) * (2.0 if req.attempt == 1 else 1.0)
        now = self.now_ns()
        if req.attempt == FROM_THE_END and ex is not None and horizon_s > 0.0:
            # the end of the trajectory that runs at the horizon, not of the newest one waiting after it (a
            # plan from there, stamped first, drops the waiting ones; after them, they had piled up: an audit)
            run = ex.link_at(now + int(round(1e9 * horizon_s)), now)
            horizon_s = max(horizon_s, run.trajectory.duration_s - run.time_s(now))
        if req.attempt > FROM_THE_END:
            horizon_s = 0.0
        start, join, why = plan_start(ex, now, q, q_ns, horizon_s, float(s.follow_tolerance_rad),
                                      req.scenario.robot.planned_periodic)
        if join is not None and req.attempt == STOPPING:     # stop on the executing path, then go
            join = stopping_join(req.scenario, join, now, float(s.start_lead_s) + CHAIN_ALLOWANCE_S,
                                 soonest=req.stop_soonest)
            start = join.start_rad
        elif join is not None and req.attempt < STOPPING:    # the arm at rest at the join: from there
            join = resting_join(join, now, float(s.start_lead_s) + CHAIN_ALLOWANCE_S)
            start = join.start_rad
        if why is not None:
            self.log("warning", f"plan #{req.gen}: {why}")
        elif join is None and now - q_ns > MAX_STATE_AGE_S * 1e9:     # a driver gone, or a state sent once
            self.log("info", f"plan #{req.gen}: from the last joint_states, {1e-9 * (now - q_ns):.1f} s old "
                     "(none newer came)")
        return start, join

    def _arm_state(self, req: Request):
        """
        Return (q_rad (n,), its stamp ns, the executing trajectory or None) for a plan's start.

        While a trajectory executes and the joint states come as a stream (the last two at most
        ``replanning.MAX_STATE_AGE_S`` apart) but the last is late (older than that, and at most
        ``MAX_STATE_AGE_S + STATE_WAIT_S`` old: an older one is a stream that stopped), the worker
        thread first waits up to ``replanning.STATE_WAIT_S`` for a newer one: an executor loaded
        by a stream of requests delivers them late, while the controller goes on.  (A state
        published once, ``ros2 topic pub --once``, is no stream: nothing is waited for.)  A
        newer request, a cancel or a stop ends the wait; so does the trajectory's end.
        """
        recent_ns = int(MAX_STATE_AGE_S * 1e9)
        late_ns = int((MAX_STATE_AGE_S + STATE_WAIT_S) * 1e9)
        waited_from = time.monotonic()
        waited, why = False, ""
        with self.lock:
            first_ns = self.joint_ns
            while True:
                q_ns, ex, now = self.joint_ns, self.executing, self.now_ns()
                if q_ns > first_ns:
                    why = "got one"
                    break
                stream = self.joint_prev_ns > 0 and 0 < q_ns - self.joint_prev_ns <= recent_ns
                if not (ex is not None and ex.running_at(now) and stream and recent_ns < now - q_ns
                        and threading.current_thread() is self.worker):
                    why = "the trajectory ended meanwhile" if ex is not None and not ex.running_at(now) else \
                        "none came"
                    break
                left = waited_from + STATE_WAIT_S - time.monotonic()
                if left <= 0.0 or now - q_ns > late_ns:
                    why = "none came"
                    break
                if self._superseded_by(req) is not None:      # (the lock is re-entrant)
                    why = "the request ended meanwhile"
                    break
                waited = self._state_wanted = True
                self.lock.wait(min(left, 0.1))
            self._state_wanted = False
            q = self.joint_q.copy()
        if waited:
            self.log("info", f"plan #{req.gen}: waited {time.monotonic() - waited_from:.2f} s for a newer "
                     f"joint_states ({why})")
        return q, q_ns, ex

    def _superseded_by(self, req: Request) -> Outcome | None:
        with self.lock:
            if req.cancelled:
                return Outcome("cancelled", req.cancelled)
            if self._stop:
                return Outcome("cancelled", "the node is shutting down")
            latest = self._latest if req.start_rad is None else self._latest_query
            if latest is not req and not req.keep:
                return _superseded(latest)
        return None

    def _log_flood(self, kind: str, text: str) -> None:
        """
        Log an info line of a kind a flood of requests repeats (planning began, superseded, cancelled).

        At most :data:`FLOOD_LINES` of a kind in :data:`FLOOD_WINDOW_S`; the first line of the kind
        after a window with lines left out says how many (a target published at 100 Hz, each a new
        one: two lines per request, 400 a second, before).
        """
        now = time.monotonic()
        with self.lock:
            start, said, left, _ = self._flood.get(kind, (-math.inf, 0, 0, None))
            if now - start >= FLOOD_WINDOW_S:
                start, said, before, left = now, 0, left, 0
            else:
                before = 0
            if said >= FLOOD_LINES:
                self._flood[kind] = (start, said, left + 1, text)
                return
            self._flood[kind] = (start, said + 1, left, None)
        self.log("info", text + (f" ({before} more such lines left out before this one)" if before else ""))

    def _flush_flood(self) -> None:
        """Log the last line of each kind :meth:`_log_flood` left out (the worker went idle): the latest request's."""
        with self.lock:
            last = [(kind, left, text) for kind, (_, _, left, text) in self._flood.items() if left]
            self._flood = {}
        for _, left, text in last:
            self.log("info", text + (f" ({left - 1} more such lines left out before this one)" if left > 1 else ""))

    def motions(self, scene) -> MotionValidator:
        """Return the scene's one MotionValidator (kept while the scene is the same object)."""
        held, motions = self._motions
        if held is not scene:
            motions = MotionValidator.for_scene(self.scenario.robot, scene)
            self._motions = (scene, motions)
        return motions

    def _plan(self, req: Request, start_raw: np.ndarray, join=None, epoch: int | None = None) -> Outcome:
        stamps = {"request": req.t_request, "planning": time.perf_counter()}
        changed = self.activity != "planning"
        if changed:                           # the state changes at once; a flood is not echoed
            self.activity = "planning"
        sc = req.scenario
        job = PlanJob.for_scenario(req.job, sc, start_raw, req.joint_goal, start_tangent=join_direction(join),
                                   stall_s=float(req.settings.test_stall_s), stages=req.on_progress is not None)
        announced = []

        def announce():
            """Say that the planning began: the ``changed`` hook and the log line, once (while the job is planned)."""
            if announced:
                return
            announced.append(True)
            if changed:
                self._changed()
            where = "" if join is None else (
                f" (where the executing trajectory rests, {_ahead_s(join, self.now_ns()):.2f} s ahead)"
                if join.stop and join.rests
                else f" (stopping on the executing trajectory {_ahead_s(join, self.now_ns()):.2f} s ahead)" if join.stop
                else f" ({join.horizon_s:g} s ahead on the executing trajectory)")
            self._log_flood("planning", f"planning #{req.gen} ({req.why}) from "
                            f"{np.round(np.degrees(start_raw), 2).tolist()}°{where} on {sc.grid.label()}")

        def progress(p):
            announce()
            if req.on_progress is not None:
                req.on_progress(p)

        # the job goes first: the announcement is made at its first progress (the backend's, once
        # the job is handed over: in parallel with the plan), or else once the backend answered
        out = self.backend.run(job, progress=progress) if self.backend is not None else None
        stamps["received"] = time.perf_counter()
        if isinstance(out, PlanDone):
            for name in ("received", "answered"):
                if f"job_{name}_s" in out.stats:
                    stamps[f"process_{name}"] = out.stats[f"job_{name}_s"]
        announce()
        dropped = self._superseded_by(req)
        if out is None or dropped is not None:
            dropped = dropped or Outcome("cancelled", "the node is shutting down")
            if isinstance(out, PlanCrash):      # still worth a traceback
                self.log("error", f"plan #{req.gen} crashed: {out.what}\n{out.traceback.rstrip()}")
            self._log_flood(dropped.code, f"plan #{req.gen} {dropped.code}: {dropped.reason}")
            return dropped
        # the lines a flood held back (this plan's "planning" among them) before its own result's: at the
        # worker's idle they came after "plan #N ok", and the log seemed to end on a plan never finished
        self._flush_flood()
        if isinstance(out, PlanCrash):
            return self._failure(req, "internal_error", f"planning crashed: {out.what}", tb=out.traceback)
        if isinstance(out, PlanError):
            if out.code == "cancelled":
                return Outcome("cancelled", out.reason)
            return self._failure(req, out.code, out.reason)
        assert isinstance(out, PlanDone)
        res = out.result
        if not res.ok:
            if res.code == "cancelled":
                self.log("info", f"plan #{req.gen} cancelled")
                return Outcome("cancelled", res.reason or "cancelled")
            return self._failure(req, res.code, res.reason or res.code, res, tb=res.traceback or None)
        if req.on_progress is not None:
            req.on_progress(_progress("trajectory"))
        try:
            processed = post_process(sc, res.path_rad, start_rad=start_raw, join=join, now_ns=self.now_ns(),
                                     lead_s=float(req.settings.start_lead_s) + CHAIN_ALLOWANCE_S,
                                     motions=self.motions(sc.scene), from_end_at_rest=req.attempt == FROM_THE_END)
        except HorizonPassed:
            return _late(f"the plan took longer than the {join.horizon_s:g} s horizon")
        except ValueError as e:
            if join is not None:
                return Outcome("retry", f"the new path cannot be joined at the arm's speed ({e})")
            return self._failure(req, "invalid_input", f"time parameterisation: {e}", res)
        if processed.refused is not None:
            return self._failure(req, "reaction_refused", processed.refused, res)
        exposure, avoidable = (None, False) if join is None else self._exposure(req, join, processed,
                                                                                self.motions(sc.scene))
        if exposure is not None and avoidable and not req.stop_soonest:
            # the executing path it follows (to the horizon point, or to its end) comes within the margin of this
            # plan's scene (a target moved onto it): stop on it as soon as the limits allow instead
            req.stop_soonest, req.attempt = True, STOPPING - 1
            return Outcome("retry", f"the motion it commits the arm to is not collision-free in this plan's scene "
                           f"({exposure})")
        stamps["chain"] = time.perf_counter()
        if "received" in stamps:        # the node's trajectory stage is the chain: in the result's stages and total
            res = res.with_chain(stamps["chain"] - stamps["received"])
        dropped = self._superseded_by(req)
        if dropped is not None:
            self._log_flood(dropped.code, f"plan #{req.gen} {dropped.code}: {dropped.reason}")
            return dropped
        return self._publish_plan(req, res, processed, start_raw, join, stamps, epoch,
                                  planned_in=out.stats.get("planned_in", ""), exposure=exposure)

    def _exposure(self, req: Request, join, processed: Processed, motions) -> tuple:
        """
        Return where the motion a plan from a moving arm commits it to is not collision-free in the plan's scene.

        That motion is the executing path from the earliest a new message can take over (now +
        ``start_lead_s``) to the plan's switch (its join; from the executing trajectory's end, that
        end: ``replanning.committed_path``), then the published trajectory as the controller moves
        the arm (``processed.certified``): the executing path was certified in the scene it was
        planned in, not in this one (a target moved onto it).  Returns (text or None when clear,
        whether another plan may avoid it: not the stretch up to the earliest join any plan can
        have, now + the lead + ``CHAIN_ALLOWANCE_S`` or its own join, which the arm follows whatever
        is published).
        """
        ex = join.executing
        lead_ns = self.now_ns() + int(1e9 * float(req.settings.start_lead_s))
        earliest_ns = lead_ns + int(1e9 * CHAIN_ALLOWANCE_S)
        switch_ns = processed.join_stamp_ns
        if switch_ns is None:              # from where the executing trajectory stops (its end), at rest
            switch_ns = (processed.not_before_ns if processed.not_before_ns is not None
                         else ex.start_ns + int(round(1e9 * ex.trajectory.duration_s)))
        else:
            earliest_ns = max(earliest_ns, switch_ns)
        said = None
        for a_ns, b_ns, avoidable in ((earliest_ns, switch_ns, True), (lead_ns, min(earliest_ns, switch_ns), False)):
            path = committed_path(join, a_ns, b_ns)
            check = motions.check(path) if len(path) else None
            if check is not None and not check.ok:
                said = (f"the arm follows the executing path {1e-9 * (b_ns - lead_ns):.2f} s more after the lead, "
                        f"which comes within the safety margin {motions.margin_m:g} m: clearance "
                        f"{check.min_clearance_m:.3f} m" + ("" if avoidable else " (before any plan can take over)"))
                if avoidable:
                    return said, True
                break
        if not processed.certified:
            return uncertified_text(req.scenario, processed, motions), True
        return said, False

    def _publish_plan(self, req: Request, res, processed: Processed, start_raw, join, stamps=None,
                      epoch: int | None = None, planned_in: str = "", exposure: str | None = None) -> Outcome:
        """
        Record an ok plan, stamp it just before it is published, publish it (the hooks).

        ``epoch``: :attr:`time_epoch` when its start was taken (None: not checked); where ROS time
        jumped since (:meth:`time_jumped`), nothing is published: planned again, from rest.
        ``planned_in``: where the backend planned it, when it says (``worker.PlanDone.stats``).
        ``exposure``: where the motion it commits a moving arm to is not collision-free (:meth:`_exposure`).
        """
        jumped = Outcome(RETRY_AT_REST, "ROS time jumped while it planned")
        if epoch is not None and epoch != self.time_epoch:
            return jumped
        lead_s = float(req.settings.start_lead_s)
        if processed.fixed_stamp_ns is not None and stamp_for(processed, self.now_ns(), lead_s) is None:
            ahead = 1e-9 * (processed.fixed_stamp_ns - self.now_ns())
            return _late(f"the {'join' if processed.join_stamp_ns is not None else 'stop it starts from'} is "
                         f"{ahead:.3f} s ahead, less than trajectory.start_lead_s ({lead_s:g} s): it "
                         "would reach the controller after it")
        traj = processed.trajectory
        c = processed.continuation
        joined = (_from_rest_on(join) if c is None and join is not None
                  else "no (the arm at rest)") if c is None else (
            (f"yes, {c.join_time_s:.3f} s into the executing trajectory at " if c.join_time_s >= 0.0005 else
             "yes, at the start of the executing trajectory (sent, not begun: its first point) at ")
            + f"{np.degrees(np.linalg.norm(c.start_velocity_rad_s)):.2f}°/s"
            + (f", stopping on its path {c.prefix_rad.shape[0] - 1} points on" if join.stop else ""))
        latency = time.perf_counter() - req.t_request
        values = {
            "goal_deg": np.round(np.degrees(res.goal_rad), 3).tolist(),
            "min_clearance_m": f"{res.min_clearance_m:.4f}",
            # the published motion's, as the controller moves the arm through its points (a joined one: from
            # the join, on the executing path first): below the margin where not certified
            "trajectory_clearance_m": f"{processed.min_clearance_m:.4f}",
            "trajectory_certified": str(bool(processed.certified and exposure is None)).lower(),
            "trajectory_duration_s": f"{traj.duration_s:.3f}",
            "trajectory_points": len(traj),
            "trajectory_dense_points": len(processed.dense),
            "trajectory_retimings": processed.retimings,
            "joined_moving_arm": joined,
            "cached": ",".join(res.cached) or "none",
            "solver": res.solver,
            "latency_s": f"{latency:.4f}",
            **result_values(res, processed.reaction),
        }
        at_goal = processed.at_goal
        if at_goal:                   # nothing is published: no points, no duration (the arm holds where it is)
            values.update(at_goal="true", trajectory_points=0, trajectory_duration_s="0.000",
                          trajectory_dense_points=0, trajectory_retimings=0)
        # the last rung from the moving arm, and the trajectory it follows ends at the goal: no new motion, and the
        # arm goes on as sent, whatever made the request (limits lowered as it moves, say): said, not "at the goal"
        kept = (f"no new trajectory could take over from the moving arm ({req.stop_failed or 'no join fitted'}); "
                "the trajectory it follows ends at this goal: it finishes it as it was sent"
                if at_goal and join is not None and req.attempt == FROM_THE_END and req.start_rad is None else None)
        if kept:                      # not at the goal: on the way there as sent; no new motion, no reaction of one
            values.update(at_goal="false", finishes_executing="true",
                          joined_moving_arm="no (nothing sent: the arm finishes the trajectory it follows)")
            for key in [k for k in values if k.startswith(("peak_wheel_", "free_floating_", "held_"))]:
                del values[key]
        outcome = Outcome("ok", kept or ("already at the goal: no trajectory published" if at_goal else ""), res, traj,
                          None, values, processed, np.asarray(start_raw), dict(stamps or {}))
        with self.lock:           # the session's state first: whoever reacts to the trajectory sees it
            if epoch is not None and epoch != self.time_epoch:
                return jumped
            self.last_result = res
            self.last_trajectory = traj
            if self._pending is None and self._query is None:
                self.activity = "idle"
        self._record(req, outcome)
        execute = req.start_rad is None      # a goal with its own start: the arm is elsewhere
        with self.lock:           # the stamp and the trajectory held in one step: a jump comes before or after
            if epoch is not None and epoch != self.time_epoch:
                return jumped
            now = self.now_ns()
            stamp = stamp_for(processed, now, lead_s)
            if stamp is None:     # the record took the join's margin (a stalled machine): publish nothing
                return _late("the join came within trajectory.start_lead_s while the plan was recorded")
            sent_stamp, parts, drift = stamp, (processed.arm, processed.attitude), processed.predicted_drift
            last = self.last_sent
            if join is not None and execute and last is not None and self.controller_switch == "arrival":
                # a controller that switches when the message arrives: the points it has, up to the switch, in front
                sent_stamp, parts, drift = switching_at_arrival(last.stamp_ns, (last.arm, last.attitude), stamp,
                                                                parts, drift, now)
            outcome.publication = Publication(sent_stamp, parts[0], parts[1], execute, drift)
            if outcome.publication.sent:
                self.last_sent = outcome.publication
            if outcome.publication.sent:
                dense, idx = processed.dense, processed.indices
                self.last_publish_t = time.monotonic()
                self.executing = (Executing(dense, idx, stamp) if join is None
                                  else join.executing.joined_by(dense, idx, stamp, now))
        self._publish(req, outcome)
        if outcome.publication.sent and epoch is not None and epoch != self.time_epoch:
            # the time jumped as it went out: stamped in the time before; one from rest replaces it at once
            return Outcome(RETRY_AT_REST, "ROS time jumped as its trajectory was published")
        outcome.stamps["published"] = time.perf_counter()
        if not execute:
            self.log("info", f"plan #{req.gen}: planned from the goal's own start: returned, not published")
        elif kept:
            self.log("warning", f"plan #{req.gen}: {kept}; no trajectory published")
        elif at_goal:
            self.log("info", f"plan #{req.gen}: already at the goal (within {AT_GOAL_TOL_RAD:g} rad): "
                     "no trajectory published")
        if outcome.publication.sent and (exposure is not None or not processed.certified):
            motions = self.motions(req.scenario.scene)
            walks_out = join is None and not motions.clearance_m(processed.trajectory.positions_rad[0]) > \
                motions.margin_m
            self.log("warning", f"plan #{req.gen}: its motion is published although not collision-free: "
                     + (exposure or uncertified_text(req.scenario, processed, motions))
                     + ("" if join is None else "; the least exposed motion found from the moving arm"
                        + (" (it goes on to where the executing trajectory rests, and from there)"
                           if join.stop and join.rests else
                           " (it stops on the executing path as soon as the limits allow, and goes from there)"
                           if join.stop else f" (no stop on the executing path could be sent: {req.stop_failed}; "
                           "from its end, which the arm reaches whatever is sent)"
                           if req.stop_failed and processed.join_stamp_ns is None else ""))
                     + ("" if join is not None else "; it starts within the margin and walks out" if walks_out
                        else "; the path is certified, the controller's interpolation of every one of its points "
                        "is not"))
        t = res.timings_s
        self.log("info", f"plan #{req.gen} ok in {1e3 * t['total']:.1f} ms (cspace {1e3 * t['cspace']:.1f}, "
                 f"field {1e3 * t['field']:.1f}, descent {1e3 * t['descent']:.1f}, smoothing "
                 f"{1e3 * t['smoothing']:.1f}, verify {1e3 * t['verify']:.1f}, trajectory "
                 f"{1e3 * t.get('trajectory', 0.0):.1f} ms; cached: "
                 f"{', '.join(res.cached) or 'none'}{threads_text(res.solver_stats)}"
                 + (f"; planned in the {planned_in}" if planned_in else "") + "); clearance "
                 f"{res.min_clearance_m:.3f} m; "
                 + (f"trajectory {len(traj)} points, {traj.duration_s:.2f} s{_chain_text(processed)}, "
                    f"joined to the moving arm: {joined}; stamped {1e-9 * (stamp - now):.3f} s ahead"
                    + _prefix_text(outcome.publication, processed, now)
                    + braking_text(req.scenario, processed.trajectory)
                    if outcome.publication.sent else "no trajectory published")
                 + f"; request→trajectory {1e3 * latency:.1f} ms")
        return outcome

    def _failure(self, req: Request, code: str, reason: str, res=None, tb=None) -> Outcome:
        self.log("error", f"plan #{req.gen}: {code}: {reason}" + (f"\n{tb.rstrip()}" if tb else ""))
        values = {}
        if res is not None and res.goal_rad is not None:
            values["goal_deg"] = np.round(np.degrees(res.goal_rad), 3).tolist()
        return Outcome(code, reason, res, values=values)


def _prefix_text(publication: Publication, processed: Processed, now_ns: int) -> str:
    """Say what a message for a controller that switches at arrival holds in front of the trajectory (else "")."""
    part, own = ((publication.arm, processed.arm) if publication.arm is not None
                 else (publication.attitude, processed.attitude))
    if part is None or own is None or len(part.times_s) == len(own.times_s):
        return ""
    k = len(part.times_s) - len(own.times_s)
    return (f" (sent for a controller that switches at arrival: {k} points of the message before in front, "
            f"{len(part.times_s)} points, {part.times_s[-1]:.2f} s, stamped "
            f"{1e-9 * (now_ns - publication.stamp_ns):.3f} s ago)")


def _chain_text(processed: Processed) -> str:
    """Return the log's ' (timed again twice for the controller's overshoot)', or '' (the chain's time: its stages)."""
    n = processed.retimings
    if not n:
        return ""
    return " (timed again " + {1: "once", 2: "twice"}.get(n, f"{n} times") + " for the controller's overshoot)"


def result_values(res, reaction) -> dict:
    """
    Diagnostics values of a plan beyond the basics.

    The field's convergence and repairs, the grasp's approach error, the spacecraft's reaction.
    """
    st = res.solver_stats
    out = {"field_converged": str(bool(st.get("converged", True))).lower(),
           "field_bands": st.get("bands", ""), "repairs": st.get("repairs", 0)}
    if st.get("left"):
        out["field_left"] = st["left"]
    approach = getattr(res, "approach_error_deg", float("nan"))
    if approach == approach:
        out["approach_error_deg"] = f"{approach:.2f}"
    if reaction is not None:
        keys = ["acs_mode", "peak_wheel_momentum_Nms", "peak_wheel_torque_Nm",
                "free_floating_attitude_change_deg", "free_floating_tip_miss_m"]
        if getattr(reaction, "acs_mode", None) == "free_floating":
            keys += ["free_floating_body_displacement_m", "free_floating_approach_error_deg"]
        else:                # the attitude held, the body still translates: where the tip then is
            keys += ["held_body_displacement_m", "held_tip_miss_m"]
        for key in keys:
            value = getattr(reaction, key, None)
            if value is not None:
                out[key] = f"{value:.4f}" if isinstance(value, float) else str(value)
    return out
