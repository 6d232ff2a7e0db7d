"""
`planner_node`: the ROS 2 shell around the planning core, a lifecycle node.

Lifecycle (``rclpy.lifecycle``, as Nav2's planner server): ``configure`` starts the
planning process and waits for its JIT warm-up, creates the publishers and the worker
thread; ``activate`` creates the subscriptions, ``~/replan`` and the ``plan_capture``
action and enables the publishers; ``deactivate`` cancels what is being planned and
removes them; ``cleanup`` stops the worker and the planning process; ``shutdown`` does
what is needed from any state.  ``autostart`` (default true) configures and activates
at start, so ``ros2 run`` plans at once.  A transition that is not possible from the
current state is refused with a log line naming the state and the transitions it has.

Start: the values given (parameter file, ``-p``, ``parameter_overrides``) are checked
against the schema (``config.PARAMETERS``) before rclpy's descriptors; a refused one
ends the start with one line naming the parameter and why (``planner_node: safety_margin_m:
-1.0 is below the minimum 0.0``, exit code 1); an unknown one is named in a warning with
the closest known name.

Interfaces (when active):

- subscribes ``target_pose`` (PoseStamped), ``joint_states``, ``goal_joint_state`` (JointState),
  and ``attitude_topic`` when set (PoseStamped of the spacecraft body in the planning frame:
  its yaw stands for the attitude joint in joint_states that lack it, a real servicer's);
  a target whose body overlaps the spacecraft's body (at the locked attitude, or at any
  attitude within its bounds when the attitude is planned: ``overlap.py``) is invalid
  input, as a goal's or as the ``target.*`` parameters;
- the goal: the latest accepted request from any channel (a target_pose, a
  goal_joint_state, a plan_capture goal) is what a later ``~/replan`` or parameter change
  plans to; a plan_capture goal with its own ``start`` is planned and returned, not
  executed, and leaves the goal as it was;
- action ``plan_capture`` (spacerobot_planner_interfaces/action/PlanCapture), Nav2's
  ``ComputePathToPose`` pattern: a newer goal (or a topic request) aborts the older one
  with code SUPERSEDED and a reason; a cancel ends a plan within about 1 s; feedback
  carries the stage and a progress fraction (``waiting_for_joint_states`` while a goal
  without its own start waits for the first joint_states: it aborts with INVALID_INPUT
  after ``joint_states_timeout_s``; topic requests wait without limit); bad goals abort
  with INVALID_INPUT and the reason; every accepted goal ends with a result: deactivate,
  shutdown, cleanup, destroy_node and Ctrl-C abort the goals in flight with code
  CANCELLED and the reason before the action server goes (``pending.py``);
- publishes ``joint_trajectory``, ``potential_grid`` / ``cspace_grid`` (OccupancyGrid in
  frame ``grid_frame``, x/y in radians, transient-local), ``planned_path_markers`` and
  ``/diagnostics`` (two statuses: ``planner`` = state + outcome of the last finished
  request, ``input`` = the last rejected input and the count of all, OK again once a good
  request follows); a topic's rejected messages are logged rate-limited (the first
  whole, then at most one line per 5 s with the count and the latest reason:
  ``rejections.py``), a parameter's and a goal's each;
- serves ``~/replan`` (std_srvs/Trigger): plans to the current goal from the arm's state
  and answers once that plan has ended (the executor serves everything else meanwhile):
  ``success`` true when it was planned (and its trajectory published), else false with
  the planner's code and reason in ``message`` (e.g. ``replan #7: goal_unreachable: ...``;
  ``superseded`` when a newer request took over; ``cancelled`` when the node was
  deactivated).  Before the first joint_states it answers at once, success false, saying
  that the replan is queued until they arrive.

Threads: callbacks only record requests (one SingleThreadedExecutor; see the README on
why not a MultiThreadedExecutor).  ONE worker thread plans, latest request wins (a new
request cancels the one being planned; results of superseded requests are dropped),
through ``worker.ProcessBackend``: a child process that never imports rclpy.
"""

from __future__ import annotations

import array
import math
import sys
import threading
import time
import traceback
from dataclasses import dataclass, field
from typing import Callable

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from geometry_msgs.msg import PoseStamped
from lifecycle_msgs.msg import Transition
from nav_msgs.msg import OccupancyGrid
from rcl_interfaces.msg import SetParametersResult
from rclpy.action import ActionServer, CancelResponse, GoalResponse
from rclpy.callback_groups import ReentrantCallbackGroup
from rclpy.lifecycle import LifecycleNode, TransitionCallbackReturn
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.task import Future
from sensor_msgs.msg import JointState
from spacerobot_planner_interfaces.action import PlanCapture
from std_srvs.srv import Trigger
from trajectory_msgs.msg import JointTrajectory
from visualization_msgs.msg import MarkerArray

from ..config import NODE_NAME, check_value, scenario_from_params, unknown_parameters
from ..scene import Target
from ..collision import CollisionChecker
from ..overlap import target_overlap_reason
from ..pipeline import timed_motion
from ..replanning import START_LEAD_S, Executing, joined_motion, plan_start
from ..trajectory import HorizonPassed, resample, time_parameterize
from ..worker import PlanCrash, PlanDone, PlanError, PlanJob, Progress, make_backend
from . import conversions as conv
from . import node_main
from .pending import PendingAnswers
from .rejections import RejectionLog
from .parameters import PLANNER_PARAMETERS, SPECS, check_choice, declare_checked, params_to_overrides

__all__ = ["PlannerNode", "main", "spin_until_shutdown", "params_to_overrides", "GRID_QOS", "Outcome"]

GRID_QOS = QoSProfile(depth=1, history=HistoryPolicy.KEEP_LAST,
                      durability=DurabilityPolicy.TRANSIENT_LOCAL,
                      reliability=ReliabilityPolicy.RELIABLE)

# changes of these only affect publishing, not the plan
_NO_REPLAN = {"replan.target_tolerance_m", "replan.target_tolerance_deg", "diagnostics.period_s",
              "replan.min_publish_period_s", "replan.horizon_s", "replan.follow_tolerance_deg",
              "potential_grid.use_current_attitude", "potential_grid.slice_attitude_deg", "grid_frame",
              "planner.test_stall_s", "joint_states_timeout_s"}
WARM_UP_TIMEOUT_S = 300.0
#: inputs at sensor rate: their rejections are logged rate-limited
_RATE_LIMITED = ("joint_states", "target_pose", "goal_joint_state", "attitude")
#: a joint group that moves less than this is at the goal: no trajectory for it, rad
AT_GOAL_TOL_RAD = 1e-4
#: Published trajectories keep a point at least this often (plus where the path bends).
RESAMPLE_STEP_S = 0.25
#: the feedback stage of a goal that waits for the first joint_states
WAITING_STAGE = "waiting_for_joint_states"


@dataclass(eq=False)
class _Request:
    gen: int
    why: str
    scenario: object            # config.Scenario (scene = with the current target)
    params: dict
    joint_goal: np.ndarray | None
    t_request: float
    start_rad: np.ndarray | None = None          # explicit start (an action goal's)
    on_done: Callable | None = None              # called once with the Outcome
    on_progress: Callable | None = None          # worker.Progress while planning
    cancelled: str | None = None                 # reason, once cancelled
    keep: bool = False                           # finish and publish although superseded (a stream)
    attempt: int = 0                             # planned again after a join failed (see _start_of)


@dataclass(eq=False)
class Outcome:
    """
    How a request ended.

    Code (a planner code or "superseded"), reason, and on success the PlanResult, the Trajectory and
    the published message.
    """

    code: str
    reason: str = ""
    result: object = None
    trajectory: object = None
    msg: JointTrajectory | None = None           # as published on joint_trajectory (arm joints)
    values: dict = field(default_factory=dict)
    attitude_msg: JointTrajectory | None = None  # as published on attitude_trajectory

    @property
    def ok(self) -> bool:
        return self.code == "ok"


class PlannerNode(LifecycleNode):
    """
    See the module docstring.

    ``parameter_overrides`` as for rclpy.Node (see :func:`params_to_overrides`
    for a flat dict from a scenario file).
    """

    #: every attribute exists (a refused start ends in ``__init__``; rclpy destroys the node later)
    _started = False

    def __init__(self, *, context=None, parameter_overrides=None, node_name: str = NODE_NAME, **kwargs):
        super().__init__(node_name, context=context, parameter_overrides=parameter_overrides,
                         automatically_declare_parameters_from_overrides=True, **kwargs)
        self._log_name = node_name
        others = declare_checked(self, PLANNER_PARAMETERS)      # ValueError: the parameter and why
        for line in unknown_parameters(others):                 # typos, named with the closest name
            self.get_logger().warning(line)
        params = {n: self.get_parameter(n).value for n in PLANNER_PARAMETERS}
        self._params = {k: (list(v) if isinstance(v, (tuple, np.ndarray, array.array)) else v)
                        for k, v in params.items()}
        self._scenario = scenario_from_params(self._params)        # raises on a bad file: fail at start
        self._check_runtime(self._params, self._scenario)
        self._robot = self._scenario.robot
        self._frame = self._scenario.planning_frame
        self._target: Target | None = self._scenario.scene.target
        self._joint_goal = None          # (dof,) rad when planning to a joint goal
        self._requested_target = None    # the target of the last target-mode request

        self._lock = threading.Condition()
        self._gen = 0
        self._pending: _Request | None = None
        self._waiting: _Request | None = None   # a request waiting for the first joint_states
        self._active: _Request | None = None
        self._latest: _Request | None = None
        self._stop = True                # no worker until configured
        self._closing = False            # shutdown_worker runs: no diagnostics, worker logs to stderr
        self._accepting = False          # requests are taken only while active
        self._joint_q = None             # latest planned-joint positions (raw, unwrapped), rad
        self._joint_ns = 0               # ROS time of that measurement (its stamp, else arrival), ns
        self._executing = None           # replanning.Executing: the trajectory last sent to the arm
        self._rejections = RejectionLog()     # topics' rejections: a line, then counts
        self._attitude = None            # rad: the latest yaw on attitude_topic (joint_states without it)
        self._waiting_timer = None       # ends a goal's wait for the first joint_states

        self.state = "unconfigured"
        self.last_result = None          # PlanResult of the last published plan
        self.last_trajectory = None      # trajectory.Trajectory
        self.last_outcome: Outcome | None = None     # the last finished request (not superseded)
        self._last_req = None
        self._rejected = None            # (source, code, reason, monotonic time) of the last bad input
        self._rejected_total = 0

        self._backend = None
        self._worker = None
        self._pubs = {}
        self.pub_diag = None
        self._diag_timer = None
        self._active_entities = []       # subscriptions, service (destroyed on deactivate)
        self._action = None
        self._pending_answers = PendingAnswers(self, self._log)    # goals and ~/replan calls in flight
        self._goals = self._pending_answers.goals                  # goal id bytes -> _Request of a goal
        self._wake = self.create_guard_condition(lambda: None)   # resumes awaiting goals
        self.add_pre_set_parameters_callback(self._pre_set_params)
        self.add_on_set_parameters_callback(self._on_set_params)
        self.add_post_set_parameters_callback(self._post_set_params)
        self._explain_refused_transitions()
        self._started = True
        if self._params["autostart"]:
            if self.trigger_configure() != TransitionCallbackReturn.SUCCESS:
                raise RuntimeError("autostart: configure failed (see the log)")
            if self.trigger_activate() != TransitionCallbackReturn.SUCCESS:
                raise RuntimeError("autostart: activate failed (see the log)")

    # ------------------------------------------------------------------ lifecycle
    def _explain_refused_transitions(self):
        """
        Explain refused lifecycle transitions in the log.

        rclpy refuses an impossible transition with transition and state numbers only: log which
        state the node is in and what it can do instead (the service reply has no text field).
        """
        for srv in self.services:
            if srv.srv_name.endswith("/change_state"):
                inner = srv.callback

                def callback(req, resp, inner=inner):
                    self.transition_refusal(req.transition.id, req.transition.label)
                    return inner(req, resp)
                srv.callback = callback

    def trigger_configure(self):
        self.transition_refusal(Transition.TRANSITION_CONFIGURE)
        return super().trigger_configure()

    def trigger_activate(self):
        self.transition_refusal(Transition.TRANSITION_ACTIVATE)
        return super().trigger_activate()

    def trigger_deactivate(self):
        self.transition_refusal(Transition.TRANSITION_DEACTIVATE)
        return super().trigger_deactivate()

    def trigger_cleanup(self):
        self.transition_refusal(Transition.TRANSITION_CLEANUP)
        return super().trigger_cleanup()

    def transition_refusal(self, transition_id: int = 0, label: str = "") -> str | None:
        """Return the reason a transition would be refused now (and log it), or None if possible."""
        current = self._state_machine.current_state
        available = {t[1]: t[0] for t in self._state_machine.available_transitions}
        names = {v: k for k, v in available.items()}
        if (label and label in available) or (not label and transition_id in names):
            return None
        want = label or {Transition.TRANSITION_CONFIGURE: "configure", Transition.TRANSITION_ACTIVATE: "activate",
                         Transition.TRANSITION_DEACTIVATE: "deactivate", Transition.TRANSITION_CLEANUP: "cleanup"}.get(
                             transition_id, f"transition {transition_id}")
        reason = (f"lifecycle: '{want}' refused: the node is '{current[1]}'; possible now: "
                  f"{', '.join(available) or 'none'}")
        self.get_logger().error(reason)
        return reason

    def on_configure(self, state):
        log = self.get_logger()
        t0 = time.perf_counter()
        try:
            self._backend = make_backend(self._scenario, self._params["planner.separate_process"],
                                         log=log.warning, info=log.info, solver=self._params["planner.solver"],
                                         field_tolerance=self._params["planner.field_tolerance"])
            self._warm_time_parameterization()     # this process's kernels, while the child warms up
            warm = self._backend.wait_ready(WARM_UP_TIMEOUT_S)
            if warm is None:
                raise RuntimeError(f"no warm-up within {WARM_UP_TIMEOUT_S} s")
        except Exception as e:      # noqa: BLE001 - a failed configure, with the reason
            log.error(f"configure failed: planning process: {type(e).__name__}: {e}")
            self._stop_backend()
            return TransitionCallbackReturn.FAILURE
        self._pubs = {
            "traj": self.create_lifecycle_publisher(JointTrajectory, "joint_trajectory", 10),
            "attitude": self.create_lifecycle_publisher(JointTrajectory, "attitude_trajectory", 10),
            "potential": self.create_lifecycle_publisher(OccupancyGrid, "potential_grid", GRID_QOS),
            "cspace": self.create_lifecycle_publisher(OccupancyGrid, "cspace_grid", GRID_QOS),
            "markers": self.create_lifecycle_publisher(MarkerArray, "planned_path_markers", GRID_QOS),
        }
        self.pub_diag = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
        self._action = ActionServer(self, PlanCapture, "plan_capture", execute_callback=self._execute_goal,
                                    goal_callback=self._on_goal_request, cancel_callback=self._cancel_goal,
                                    handle_accepted_callback=lambda h: h.execute())
        self._diag_timer = self.create_timer(float(self._params["diagnostics.period_s"]), self._diag_tick)
        with self._lock:
            self._stop = False
            self._closing = False
        self._worker = threading.Thread(target=self._worker_loop, name="spacerobot_planner-worker", daemon=True)
        self._worker.start()
        self.state = "inactive"
        where = "planning process" if self._params["planner.separate_process"] else "worker thread"
        log.info(f"configured in {time.perf_counter() - t0:.2f} s: planning "
                 f"{', '.join(self._robot.planned_names)} on a {self._scenario.grid.label()} grid in frame "
                 f"'{self._frame}' ({where}"
                 f" warmed up)")
        self._publish_diag()
        return TransitionCallbackReturn.SUCCESS

    def _warm_time_parameterization(self):
        """
        Compile (or load) the time parameterisation's kernels in this process.

        They run here, not in the planning process, on the first trajectory otherwise.
        """
        robot = self._robot
        lo, hi = robot.planned_lower_rad, robot.planned_upper_rad
        path = np.linspace(lo + 0.25 * (hi - lo), lo + 0.75 * (hi - lo), 8)
        vmax = np.radians(np.asarray(self._params["trajectory.max_velocity_deg_s"], dtype=float))
        amax = np.radians(np.asarray(self._params["trajectory.max_acceleration_deg_s2"], dtype=float))
        idx = list(robot.planned_joints)
        time_parameterize(path, vmax[idx], amax[idx], robot.planned_names)

    def on_activate(self, state):
        ret = super().on_activate(state)          # enables the lifecycle publishers
        self._active_entities = [
            self.create_subscription(PoseStamped, "target_pose", self._on_target, 10),
            self.create_subscription(JointState, "joint_states", self._on_joint_state, 10),
            self.create_subscription(JointState, "goal_joint_state", self._on_goal_joint_state, 10),
            # its own (reentrant) group: the node's default group is mutually exclusive, and an
            # awaiting callback would hold it (no other callback of the node) until it answers
            self.create_service(Trigger, "~/replan", self._on_replan, callback_group=ReentrantCallbackGroup()),
        ]
        topic = self._params["attitude_topic"]
        if topic:
            self._active_entities.append(self.create_subscription(PoseStamped, topic, self._on_attitude, 10))
        with self._lock:
            self._accepting = True
            self.state = "idle"
            self._last_publish_t = time.monotonic()
        self.get_logger().info("active: waiting for target_pose / goal_joint_state / plan_capture goals "
                               "and joint_states")
        self._publish_diag()
        return ret

    def on_deactivate(self, state):
        self._deactivate("the node was deactivated")
        self.get_logger().info("inactive")
        self._publish_diag()
        return super().on_deactivate(state)

    def _deactivate(self, why: str):
        with self._lock:
            self._accepting = False
            self.state = "inactive"
            self._drop_requests(why)
        for ent in self._active_entities:
            if hasattr(ent, "srv_name"):
                self._pending_answers.retire(lambda srv=ent: self.destroy_service(srv))   # after its answers
            else:
                self.destroy_subscription(ent)
        self._active_entities = []
        self._wake_goals()

    def on_cleanup(self, state):
        self._cleanup()
        self.get_logger().info("cleaned up: planning process stopped")
        return TransitionCallbackReturn.SUCCESS

    def _cleanup(self, finish_goals: bool = False):
        """
        Stop the worker and remove what configure made.

        In a transition (a callback of the executor) the goals in flight return their results
        after it, so their action server is destroyed later (``pending.PendingAnswers.retire``);
        ``finish_goals`` (not in a callback: destroy_node) lets them return their results first.
        """
        self.shutdown_worker(finish_goals=finish_goals)
        action, self._action = self._action, None
        if action is not None:
            self._pending_answers.retire(action.destroy)
        for pub in self._pubs.values():
            self.destroy_lifecycle_publisher(pub)
        self._pubs = {}
        if self._diag_timer is not None:
            self.destroy_timer(self._diag_timer)
            self._diag_timer = None
        if self.pub_diag is not None:
            self.destroy_publisher(self.pub_diag)
            self.pub_diag = None
        self.state = "unconfigured"

    def on_shutdown(self, state):
        self._shutdown_all("shutdown")
        return TransitionCallbackReturn.SUCCESS

    def on_error(self, state):
        self._shutdown_all("error")
        return TransitionCallbackReturn.SUCCESS

    def _shutdown_all(self, why):
        if self._accepting:
            self._deactivate(f"the node is shutting down ({why})")
        self._cleanup(finish_goals=why == "destroy_node")
        self.state = "finalized"
        self._log("info", f"{why}: finalized")

    # ------------------------------------------------------------------ params
    def _check_runtime(self, params, scenario):
        check_choice("planner.solver", params["planner.solver"])
        n = scenario.robot.n_joints
        for key in ("trajectory.max_velocity_deg_s", "trajectory.max_acceleration_deg_s2"):
            if len(params[key]) != n:
                raise ValueError(f"{key}: expected {n} values (one per joint in robot.joint_names), "
                                 f"got {len(params[key])}")
        overlap = target_overlap_reason(scenario.robot, scenario.scene.target)
        if overlap is not None:
            raise ValueError(f"target.center_m: {overlap}")
        nodes = scenario.grid.n_nodes
        if nodes > params["planner.max_grid_nodes"]:
            raise ValueError(f"grid.cells: {scenario.grid.label()} = {nodes} nodes exceeds "
                             f"planner.max_grid_nodes = {params['planner.max_grid_nodes']}")

    def _validate(self, parameters):
        """Merge the parameters and build the scenario: (merged params, scenario); ValueError names the field."""
        merged = dict(self._params)
        for p in parameters:
            if p.name not in self._params:
                continue
            if SPECS[p.name].read_only:
                raise ValueError(f"{p.name}: read-only (a change needs a restart)")
            merged[p.name] = check_value(p.name, p.value)
            check_choice(p.name, merged[p.name])       # the node's wording, before the scenario's
        scenario = scenario_from_params(merged)
        self._check_runtime(merged, scenario)
        return merged, scenario

    def _precheck(self, parameters) -> SetParametersResult | None:
        """
        Give the node's own reason for values it refuses (a wrong type included).

        It answers before rclpy's descriptor checks, which answer with enum numbers; None when
        the values pass.
        """
        try:
            self._validate(parameters)
        except ValueError as e:
            self._reject("parameters", "invalid_parameter", f"parameter rejected: {e}")
            return SetParametersResult(successful=False, reason=str(e))
        return None

    def set_parameters_atomically(self, parameter_list):
        """As rclpy's (the ``~/set_parameters`` service calls it), with :meth:`_precheck` first."""
        refused = self._precheck(parameter_list)
        return refused if refused is not None else super().set_parameters_atomically(parameter_list)

    def set_parameters(self, parameter_list):
        """As rclpy's, with :meth:`_precheck` first for each parameter."""
        out = []
        for p in parameter_list:
            refused = self._precheck([p])
            out.extend([refused] if refused is not None else super().set_parameters([p]))
        return out

    def _pre_set_params(self, parameters):
        # runs before rclpy's own descriptor checks (whose type errors are enum numbers):
        # the node's own reason goes to the log and /diagnostics
        try:
            self._validate(parameters)
        except ValueError as e:
            self._reject("parameters", "invalid_parameter", f"parameter rejected: {e}")
        return parameters

    def _on_set_params(self, parameters):
        try:
            self._validate(parameters)
        except ValueError as e:
            return SetParametersResult(successful=False, reason=str(e))
        return SetParametersResult(successful=True)

    def _post_set_params(self, parameters):
        merged, scenario = self._validate(parameters)
        names = [p.name for p in parameters if p.name in self._params]
        with self._lock:
            self._params = merged
            self._scenario = scenario
            if any(n.startswith("target.") for n in names):
                self._target = scenario.scene.target
        if "diagnostics.period_s" in names and self._diag_timer is not None:
            self.destroy_timer(self._diag_timer)
            self._diag_timer = self.create_timer(float(merged["diagnostics.period_s"]), self._diag_tick)
        if any(n not in _NO_REPLAN for n in names) and self._accepting:
            self.get_logger().info(f"parameters changed ({', '.join(names)}): replanning")
            self._submit(f"parameter change ({', '.join(names)})")

    # ------------------------------------------------------------------ inputs
    def _target_from_pose(self, msg: PoseStamped, what: str) -> Target:
        """Return the target of a pose; ValueError (named ``what``) when unusable or inside the spacecraft."""
        try:
            target = conv.pose_to_target(msg, self._frame, self._scenario.scene.target)
        except ValueError as e:
            raise ValueError(str(e).replace("target_pose:", f"{what}:", 1)) from None
        overlap = target_overlap_reason(self._robot, target)
        if overlap is not None:
            raise ValueError(f"{what}: {overlap}")
        return target

    def _on_target(self, msg: PoseStamped):
        try:
            target = self._target_from_pose(msg, "target_pose")
        except ValueError as e:
            self._reject("target_pose", "invalid_input", str(e))
            return
        prev = self._requested_target
        if prev is not None and self._joint_goal is None:
            dist = math.hypot(target.center_m[0] - prev.center_m[0], target.center_m[1] - prev.center_m[1])
            dyaw = abs(math.degrees(math.remainder(target.yaw_rad - prev.yaw_rad, 2 * math.pi)))
            if (dist <= self._params["replan.target_tolerance_m"]
                    and dyaw <= self._params["replan.target_tolerance_deg"]):
                self.get_logger().debug(f"target_pose within tolerance of the current target "
                                        f"({dist:.4f} m, {dyaw:.2f}°): no replan")
                return
        with self._lock:
            self._target = target
            self._joint_goal = None
        self._submit(_target_why(target))

    def _on_goal_joint_state(self, msg: JointState):
        try:
            q = self._joint_goal_from_msg(msg, "goal_joint_state")
        except ValueError as e:
            self._reject("goal_joint_state", "invalid_input", str(e))
            return
        with self._lock:
            self._joint_goal = q
        self._submit(f"joint goal {np.round(np.degrees(q), 2).tolist()}°")

    def _joint_goal_from_msg(self, msg: JointState, what: str) -> np.ndarray:
        q = conv.joint_state_positions(msg, self._robot.planned_names, what)
        return self._robot.validate_q(q, what)

    def _on_joint_state(self, msg: JointState):
        attitude = self._robot.joint_names[0]
        topic = self._params["attitude_topic"]
        fallback = None if self._attitude is None else {attitude: self._attitude}
        try:
            q = conv.joint_state_positions(msg, self._robot.planned_names, fallback=fallback)
        except ValueError as e:
            reason = str(e)
            if topic and fallback is None and attitude in self._robot.planned_names and attitude not in msg.name:
                reason += f"; no attitude received on '{topic}' yet"
            self._reject("joint_states", "invalid_input", reason)
            return
        stamp_ns = conv.time_to_ns(msg.header.stamp)
        with self._lock:
            self._joint_q = q
            self._joint_ns = stamp_ns or self.get_clock().now().nanoseconds
            waiting, self._waiting = self._waiting, None
            if waiting is not None:
                self._replace_pending(waiting)

    def _on_attitude(self, msg: PoseStamped):
        """
        Take the spacecraft body's pose (``attitude_topic``): its yaw is the attitude joint.

        Used for the joint_states that lack the attitude joint (a real servicer's); the
        position is ignored.
        """
        topic = self._params["attitude_topic"]
        if msg.header.frame_id.lstrip("/") != self._frame.lstrip("/"):
            self._reject("attitude", "invalid_input", f"{topic}: frame '{msg.header.frame_id}' is not the "
                         f"planning frame '{self._frame}'")
            return
        o = msg.pose.orientation
        try:
            yaw = conv.quaternion_to_yaw(o.x, o.y, o.z, o.w)
        except ValueError as e:
            self._reject("attitude", "invalid_input", f"{topic}: {e}")
            return
        self._attitude = yaw

    async def _on_replan(self, request, response):
        """~/replan: plan to the current goal now; answer with the plan's outcome (see the module docstring)."""
        self._pending_answers.running()
        if self._joint_q is None:
            gen = self._submit("~/replan")
            response.success = False
            response.message = (f"replan #{gen} queued: no joint_states received yet, it plans when the first "
                                "arrives (its outcome: /diagnostics)")
            return response
        done = Future()

        def on_done(outcome):
            done.set_result(outcome)
            self._wake_goals()

        with self._lock:
            req = self._make_request("~/replan", self._joint_goal,
                                     None if self._joint_goal is not None else self._target)
        req.on_done = on_done
        self._pending_answers.replans += 1
        try:
            gen = self._submit_request(req)
            outcome = await done
        finally:
            self._pending_answers.replans -= 1
        response.success = outcome.ok
        response.message = f"replan #{gen}: {outcome.code}" + (f": {outcome.reason}" if outcome.reason else "")
        return response

    # ------------------------------------------------------------------ action
    async def _execute_goal(self, goal_handle):
        """One plan_capture goal: validate, hand to the worker, await its outcome."""
        self._pending_answers.running()
        goal = goal_handle.request
        done = Future()
        try:
            req = self._request_from_goal(goal)
        except ValueError as e:
            self._reject("plan_capture", "invalid_input", str(e))
            goal_handle.abort()
            return conv.plan_result(PlanCapture.Result, "invalid_input", str(e))

        def on_done(outcome):
            done.set_result(outcome)
            self._wake_goals()

        def on_progress(p):
            fb = PlanCapture.Feedback(stage=p.stage, progress=float(p.fraction))
            try:
                goal_handle.publish_feedback(fb)
            except Exception:      # noqa: BLE001 - goal already finished / server gone
                pass

        req.on_done, req.on_progress = on_done, on_progress
        key = bytes(goal_handle.goal_id.uuid)
        self._goals[key] = req
        try:
            self._submit_request(req)
            outcome = await done
        finally:
            self._goals.pop(key, None)
        result = conv.plan_result(PlanCapture.Result, outcome.code, outcome.reason, outcome.msg, outcome.result,
                                  outcome.attitude_msg)
        try:
            if outcome.ok:
                goal_handle.succeed()
            elif outcome.code == "cancelled" and goal_handle.is_cancel_requested:
                goal_handle.canceled()
            else:
                goal_handle.abort()
        except Exception as e:     # noqa: BLE001 - the server went away (shutdown)
            self._log("warning", f"plan_capture: goal ended during shutdown: {e}")
        return result

    def _request_from_goal(self, goal) -> _Request:
        """Make the request of an action goal (not yet submitted); ValueError names the field."""
        start = None
        if len(goal.start.name) or len(goal.start.position):
            start = conv.joint_state_positions(goal.start, self._robot.planned_names, "goal.start")
            start = self._robot.validate_q(start, "goal.start")
        if goal.use_joint_goal:
            q = self._joint_goal_from_msg(goal.joint_goal, "goal.joint_goal")
            return self._make_request(f"plan_capture goal: joint goal {np.round(np.degrees(q), 2).tolist()}°",
                                      joint_goal=q, target=None, start=start)
        target = self._target_from_pose(goal.target_pose, "goal.target_pose")
        return self._make_request(f"plan_capture goal: {_target_why(target)}", joint_goal=None, target=target,
                                  start=start)

    def _on_goal_request(self, goal):
        if not self._accepting:
            self.get_logger().warning("plan_capture: goal rejected: the node is not active "
                                      f"(lifecycle state '{self._state_machine.current_state[1]}')")
            return GoalResponse.REJECT
        return GoalResponse.ACCEPT

    def _cancel_goal(self, goal_handle):
        req = self._goals.get(bytes(goal_handle.goal_id.uuid))
        if req is not None:
            self._cancel_request(req, "cancelled by the action client")
        return CancelResponse.ACCEPT

    def _wake_goals(self):
        try:
            self._wake.trigger()
        except Exception:          # noqa: BLE001 - context already shut down
            pass

    # ------------------------------------------------------------------ requests
    def _make_request(self, why, joint_goal, target, start=None) -> _Request:
        with self._lock:
            scenario = self._scenario
            if target is not None:
                scenario = scenario.with_scene(scenario.scene.with_target(target))
            return _Request(0, why, scenario, dict(self._params),
                            None if joint_goal is None else np.array(joint_goal, dtype=float),
                            time.perf_counter(), start_rad=start)

    def _submit(self, why: str) -> int:
        """Submit a request for the current target / joint goal (the topics', ~/replan's, a parameter change's)."""
        with self._lock:
            req = self._make_request(why, self._joint_goal, None if self._joint_goal is not None else self._target)
        return self._submit_request(req)

    def _make_current(self, req: _Request):
        """
        (lock held) The goal of an accepted request becomes the current goal.

        The latest request from any channel (target_pose, goal_joint_state, a plan_capture
        goal) is what a replan or a parameter change plans to; a goal with its own start is
        planned, not executed, and changes nothing.
        """
        if req.start_rad is not None:
            return
        if req.joint_goal is not None:
            self._joint_goal = req.joint_goal
        else:
            self._target = self._requested_target = req.scenario.scene.target
            self._joint_goal = None

    def _submit_request(self, req: _Request) -> int:
        with self._lock:
            if not self._accepting:
                self._finish(req, Outcome("cancelled", "the node is not active"))
                return 0
            self._gen += 1
            req.gen = self._gen
            self._make_current(req)
            self._rejected = None              # a good request: the input status is OK again
            if self._joint_q is None and req.start_rad is None:
                if self._waiting is not None:
                    self._finish(self._waiting, _superseded(req))
                self._waiting = req
                self.get_logger().info(f"request #{req.gen} ({req.why}): waiting for joint_states")
                self._wait_for_joint_states(req)
            else:
                self._replace_pending(req)
            self._latest = req
            active = self._active
            if active is not None:
                period = float(self._params["replan.min_publish_period_s"])
                starving = period > 0 and time.monotonic() - self._last_publish_t >= period
                if starving and active.on_done is None and req.on_done is None:
                    active.keep = True          # a stream of targets: let this one be published
                else:
                    self._backend.cancel(active.gen)   # supersede the plan in progress
            self._lock.notify_all()
            return req.gen

    def _wait_for_joint_states(self, req):
        """
        (lock held) ``req`` waits for the first joint_states: say so to its client, and bound the wait.

        A request a client awaits (a plan_capture goal) ends after ``joint_states_timeout_s``.
        """
        if req.on_progress is not None:
            req.on_progress(Progress(req.gen, WAITING_STAGE, 0.0))
        if req.on_done is None:
            return
        timeout_s = float(self._params["joint_states_timeout_s"])
        if self._waiting_timer is not None:
            self.destroy_timer(self._waiting_timer)
        self._waiting_timer = self.create_timer(timeout_s, lambda: self._joint_states_timeout(req, timeout_s))

    def _joint_states_timeout(self, req, timeout_s):
        """Timer: ``req`` waited too long for joint_states."""
        with self._lock:
            timer, self._waiting_timer = self._waiting_timer, None
            expired = self._waiting is req
            if expired:
                self._waiting = None
        if timer is not None:
            self.destroy_timer(timer)
        if not expired:
            return
        outcome = self._failure(req, "invalid_input", f"no joint_states within {timeout_s:g} s: the arm's state (the "
                                "plan's start) is unknown; publish joint_states or give the goal a start")
        self._record(req, outcome)
        with self._lock:
            self._finish(req, outcome)

    def _replace_pending(self, req):
        """(lock held) ``req`` becomes the next request; the one it replaces is superseded."""
        if self._pending is not None:
            self._finish(self._pending, _superseded(req))
        if self._waiting is not None and self._waiting is not req:
            self._finish(self._waiting, _superseded(req))
            self._waiting = None
        self._pending = req
        self._lock.notify_all()

    def _cancel_request(self, req, reason):
        with self._lock:
            if self._pending is req:
                self._pending = None
                self._finish(req, Outcome("cancelled", reason))
            elif self._waiting is req:
                self._waiting = None
                self._finish(req, Outcome("cancelled", reason))
            elif self._active is req:
                req.cancelled = reason
                self._backend.cancel(req.gen)

    def _drop_requests(self, why):
        """(lock held) cancel everything queued or running."""
        for attr in ("_pending", "_waiting"):
            req = getattr(self, attr)
            if req is not None:
                setattr(self, attr, None)
                self._finish(req, Outcome("cancelled", why))
        if self._active is not None:
            self._active.cancelled = why
            if self._backend is not None:
                self._backend.cancel(self._active.gen)

    def _finish(self, req, outcome: Outcome):
        """Every request ends here exactly once."""
        cb, req.on_done = req.on_done, None
        if cb is not None:
            cb(outcome)

    # ------------------------------------------------------------------ worker
    def _worker_loop(self):
        while True:
            with self._lock:
                while self._pending is None and not self._stop:
                    self._lock.wait()
                if self._stop:
                    return
                req, self._pending = self._pending, None
                self._active = req
            while True:
                try:
                    outcome = self._plan(req, *self._start_of(req))
                except Exception as e:      # noqa: BLE001 - never let the worker die
                    outcome = self._failure(req, "internal_error", f"planning crashed: {type(e).__name__}: "
                                            f"{e}", tb=traceback.format_exc())
                if outcome.code != "retry":
                    break
                req.attempt += 1
                self._log("warning", f"plan #{req.gen}: {outcome.reason}; planning again "
                          + _RETRY[min(req.attempt, len(_RETRY) - 1)])
            with self._lock:
                self._active = None
                if self.state == "planning" and self._pending is None:
                    self.state = "idle" if self._accepting else "inactive"
            if not outcome.ok and outcome.code != "superseded":
                self._record(req, outcome)
            with self._lock:
                self._finish(req, outcome)

    def _start_of(self, req: _Request):
        """
        (start_raw, replanning.Join or None) of a request.

        Its own start, or the arm's state, or (the arm moving on the node's last trajectory) the
        point ``replan.horizon_s`` ahead on it.

        When the join fails (``_plan``: the plan took longer than the horizon, or the
        new path cannot be entered at the arm's speed) the next attempt doubles the
        horizon, the one after starts at the executing trajectory's end (its goal, at
        rest: always joinable), the last at the measured state (_RETRY).
        """
        with self._lock:
            if req.start_rad is not None:
                return req.start_rad, None
            q, q_ns, ex = self._joint_q.copy(), self._joint_ns, self._executing
        horizon_s = float(req.params["replan.horizon_s"]) * (2.0 if req.attempt == 1 else 1.0)
        if req.attempt == 2 and ex is not None and horizon_s > 0.0:
            horizon_s = max(horizon_s, ex.trajectory.duration_s - ex.time_s(self.get_clock().now().nanoseconds))
        if req.attempt >= 3:
            horizon_s = 0.0
        start, join, why = plan_start(ex, self.get_clock().now().nanoseconds, q, q_ns, horizon_s,
                                      math.radians(float(req.params["replan.follow_tolerance_deg"])),
                                      self._robot.planned_periodic)
        if why is not None:
            self._log("warning", f"plan #{req.gen}: {why}")
        return start, join

    def _superseded_by(self, req) -> Outcome | None:
        with self._lock:
            if req.cancelled:
                return Outcome("cancelled", req.cancelled)
            if self._stop:
                return Outcome("cancelled", "the node is shutting down")
            if req.gen != self._gen and not req.keep:
                return _superseded(self._latest)
        return None

    def _plan(self, req: _Request, start_raw: np.ndarray, join=None) -> Outcome:
        if self.state != "planning":       # state changes at once; a flood is not echoed
            self.state = "planning"
            self._publish_diag()
        sc = req.scenario
        where = "" if join is None else f" ({join.horizon_s:g} s ahead on the executing trajectory)"
        self._log("info", f"planning #{req.gen} ({req.why}) from {np.round(np.degrees(start_raw), 2).tolist()}°"
                  f"{where} on {sc.grid.label()}")
        p = req.params
        job = PlanJob(gen=req.gen, scene=sc.scene, grid=sc.grid, solver=p["planner.solver"],
                      field_tolerance=float(p["planner.field_tolerance"]),
                      max_grid_nodes=int(p["planner.max_grid_nodes"]), start_rad=start_raw,
                      joint_goal=req.joint_goal, stall_s=float(p["planner.test_stall_s"]),
                      field_budget_s=float(p["planner.field_budget_s"]))
        out = self._backend.run(job, progress=req.on_progress)
        dropped = self._superseded_by(req)
        if out is None or dropped is not None:
            dropped = dropped or Outcome("cancelled", "the node is shutting down")
            if isinstance(out, PlanCrash):      # still worth a traceback
                self._log("error", f"plan #{req.gen} crashed: {out.what}\n{out.traceback.rstrip()}")
            self._log("info", f"plan #{req.gen} {dropped.code}: {dropped.reason}")
            return dropped
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
                self._log("info", f"plan #{req.gen} cancelled")
                return Outcome("cancelled", res.reason or "cancelled")
            return self._failure(req, res.code, res.reason or res.code, res, tb=res.traceback or None)
        if req.on_progress is not None:
            req.on_progress(_progress("trajectory"))
        stamp_ns, joined = None, "no (the arm at rest)"
        checker = CollisionChecker(sc.robot, sc.scene)
        try:
            if join is None:
                traj, reaction = timed_motion(req.scenario, res.path_rad, start_raw)
            else:
                traj, reaction, stamp_ns, c = joined_motion(req.scenario, join, res.path_rad,
                                                            self.get_clock().now().nanoseconds, checker=checker)
                joined = (f"yes, {c.join_time_s:.3f} s into the executing trajectory at "
                          f"{np.degrees(np.linalg.norm(c.start_velocity_rad_s)):.2f}°/s")
        except HorizonPassed:
            return Outcome("retry", f"the plan took longer than the {join.horizon_s:g} s horizon")
        except ValueError as e:
            if join is not None:
                return Outcome("retry", f"the new path cannot be joined at the arm's speed ({e})")
            return self._failure(req, "invalid_input", f"time parameterisation: {e}", res)
        if reaction is not None and not reaction.ok:
            return self._failure(req, "reaction_refused", reaction.reason, res)
        dense_points = len(traj)
        # fewer points, same guarantee: a subset of the points within 0.1° of the dense path
        # and at most RESAMPLE_STEP_S apart, its polyline certified on the exact geometry
        dense, published = traj, np.arange(len(traj))
        rs = resample(traj, checker, time_step_s=RESAMPLE_STEP_S)
        if rs.ok:
            traj, published = rs.trajectory, rs.indices
        dropped = self._superseded_by(req)
        if dropped is not None:
            self._log("info", f"plan #{req.gen} {dropped.code}: {dropped.reason}")
            return dropped
        # one stamp for both parts: the arm's and the attitude's controllers start together (a
        # zero stamp would mean "on arrival", each its own), a moment ahead so that it arrives
        # first: START_LEAD_S from now, or the join's time (the controller follows the
        # trajectory it has until then)
        if stamp_ns is None:      # from rest: the arm holds its state until then
            stamp_ns = self.get_clock().now().nanoseconds + int(START_LEAD_S * 1e9)
        stamp = conv.ns_to_time(stamp_ns)
        msg, att_msg = self._split(conv.trajectory_to_msg(traj, stamp), traj)
        latency = time.perf_counter() - req.t_request
        values = {
            "goal_deg": np.round(np.degrees(res.goal_rad), 3).tolist(),
            "min_clearance_m": f"{res.min_clearance_m:.4f}",
            "trajectory_duration_s": f"{traj.duration_s:.3f}",
            "trajectory_points": len(traj),
            "trajectory_dense_points": dense_points,
            "joined_moving_arm": joined,
            "cached": ",".join(res.cached) or "none",
            "solver": res.solver,
            "latency_s": f"{latency:.4f}",
            **_result_values(res, reaction),
        }
        at_goal = msg is None and att_msg is None
        if at_goal:
            values["at_goal"] = "true"
        outcome = Outcome("ok", "already at the goal: no trajectory published" if at_goal else "", res, traj,
                          msg, values, att_msg)
        with self._lock:           # the node's state first: whoever reacts to the trajectory sees it
            self.last_result = res
            self.last_trajectory = traj
            if self._pending is None:
                self.state = "idle"
        self._record(req, outcome)
        # a goal with its own start is planned, not executed: the controller's arm is elsewhere
        execute = req.start_rad is None
        if msg is not None and execute:
            self._pubs["traj"].publish(msg)
        if att_msg is not None and execute:
            self._pubs["attitude"].publish(att_msg)
        if not execute:
            self._log("info", f"plan #{req.gen}: planned from the goal's own start: returned, not published")
        elif not at_goal:
            with self._lock:
                self._last_publish_t = time.monotonic()
                self._executing = (Executing(dense, published, stamp_ns) if join is None
                                   else join.executing.joined_by(dense, published, stamp_ns))
        else:
            self._log("info", f"plan #{req.gen}: already at the goal (within {AT_GOAL_TOL_RAD:g} rad): "
                      "no trajectory published")
        t = res.timings_s
        self._log("info", f"plan #{req.gen} ok in {1e3 * t['total']:.1f} ms (cspace {1e3 * t['cspace']:.1f}, "
                  f"field {1e3 * t['field']:.1f}, descent {1e3 * t['descent']:.1f}, smoothing "
                  f"{1e3 * t['smoothing']:.1f}, verify {1e3 * t['verify']:.1f} ms; cached: "
                  f"{', '.join(res.cached) or 'none'}); clearance {res.min_clearance_m:.3f} m; "
                  f"trajectory {len(traj)} points, {traj.duration_s:.2f} s, joined to the moving arm: "
                  f"{joined}; request→trajectory "
                  f"{1e3 * latency:.1f} ms")
        self._publish_visuals(res, sc, start_raw, p)
        return outcome

    def _split(self, full: JointTrajectory, traj):
        """
        (arm joints' message, attitude's message).

        The attitude (the robot's first joint, the spacecraft's) goes to the attitude control
        system, the arm joints to the arm's controller (None for a group that is not planned).

        Both None when nothing moves more than AT_GOAL_TOL_RAD: at the goal.  A group that
        does not move while the other does still gets its (holding) trajectory, which
        replaces an older one still running.
        """
        attitude = self._robot.joint_names[0]
        att, arm = conv.split_trajectory_msg(full, [attitude])
        q = np.asarray(traj.positions_rad)
        if float(np.max(np.abs(q[-1] - q[0]))) <= AT_GOAL_TOL_RAD:
            return None, None
        return arm, att

    def _failure(self, req, code, reason, res=None, tb=None) -> Outcome:
        self._log("error", f"plan #{req.gen}: {code}: {reason}" + (f"\n{tb.rstrip()}" if tb else ""))
        values = {}
        if res is not None and res.goal_rad is not None:
            values["goal_deg"] = np.round(np.degrees(res.goal_rad), 3).tolist()
        return Outcome(code, reason, res, values=values)

    def slice_axes_and_point(self, res, start_raw, params):
        """(x axis, y axis, q at which to slice) for the published grids."""
        dof = self._robot.dof
        if dof < 2:
            return None
        q = np.array(res.start_rad, dtype=float)
        if dof > 2 and not params["potential_grid.use_current_attitude"]:
            q = q.copy()
            q[0] = math.radians(params["potential_grid.slice_attitude_deg"])
        q = self._robot.validate_q(q, "slice")
        return dof - 2, dof - 1, q

    def _publish_visuals(self, res, sc, start_raw, params):
        stamp = self.get_clock().now().to_msg()
        self._pubs["markers"].publish(conv.path_markers(self._robot, sc.scene, res.path_rad, self._frame, stamp))
        sl = self.slice_axes_and_point(res, start_raw, params)
        if sl is None or res.cspace is None:
            return
        ax, ay, q = sl
        grid = res.cspace.grid
        frame = params["grid_frame"]
        occ = conv.grid_slice(grid, res.cspace.occupied, q, (ax, ay))
        self._pubs["cspace"].publish(conv.grid_slice_to_msg(conv.obstacle_slice_values(occ), grid, (ax, ay),
                                                            frame, stamp))
        if res.field is not None:
            phi = res.field.potential()
            finite = np.isfinite(phi)
            phi_max = float(phi[finite].max()) if finite.any() else 0.0
            log_u = conv.grid_slice(grid, res.field.log_u, q, (ax, ay))
            focc = conv.grid_slice(grid, res.field.occupied, q, (ax, ay))
            vals = conv.potential_slice_values(log_u, focc, phi_max)
            self._pubs["potential"].publish(conv.grid_slice_to_msg(vals, grid, (ax, ay), frame, stamp))

    # ------------------------------------------------------------------ diagnostics
    @staticmethod
    def _request_values(req: _Request) -> dict:
        """Diagnostics values naming a request: its number and its goal (target or joints)."""
        out = {"request": f"#{req.gen}", "request_reason": req.why}
        if req.joint_goal is not None:
            out["joint_goal_deg"] = np.round(np.degrees(req.joint_goal), 3).tolist()
        elif req.scenario.scene.target is not None:
            t = req.scenario.scene.target
            out["target_m"] = [round(float(v), 4) for v in t.center_m]
            out["target_yaw_deg"] = round(math.degrees(t.yaw_rad), 3)
        return out

    def _record(self, req, outcome: Outcome):
        """Make the planner status describe this (finished) request from now on, and only it."""
        with self._lock:
            self.last_outcome = outcome
            self._last_req = req
        self._publish_diag()

    def _reject(self, source: str, code: str, reason: str):
        """
        Bad input (a message, a goal, a parameter): log it and raise the input status.

        A topic's rejections are rate-limited (:mod:`.rejections`: the first whole, then counts);
        a parameter's or a goal's (one per request of a person or a client) are all logged.
        /diagnostics counts them all and names the latest.
        """
        line = f"{source}: {code}: {reason}"
        if source in _RATE_LIMITED:
            line = self._rejections.reject(source, f"{code}: {reason}")
        if line is not None:
            self.get_logger().error(line)
        with self._lock:
            news = self._rejected is None or self._rejected[:3] != (source, code, reason)
            self._rejected = (source, code, reason, time.monotonic())
            self._rejected_total += 1
        if line is not None or news:          # else the heartbeat carries the count
            self._publish_diag()

    def _diag_tick(self):
        """Diagnostics timer: the heartbeat, and the count lines of floods of bad input."""
        for line in self._rejections.flush():
            self.get_logger().error(line)
        self._publish_diag()

    def diagnostic_statuses(self):
        """[(name, level, message, values)]: the planner status and the input status."""
        with self._lock:
            out, req, rej = self.last_outcome, self._last_req, self._rejected
            state, total = self.state, self._rejected_total
        name = self.get_name()
        values = {"state": state}
        if out is None:
            level, message = DiagnosticStatus.OK, f"{state}: no request finished yet"
        else:
            values.update(self._request_values(req))
            values["code"] = out.code
            if out.result is not None:
                values.update({f"time_{k}_ms": f"{1e3 * v:.2f}" for k, v in out.result.timings_s.items()})
            values.update(out.values)
            if out.ok:
                level, message = DiagnosticStatus.OK, f"{state}: request #{req.gen} planned"
            elif out.code == "cancelled":
                level, message = DiagnosticStatus.OK, f"{state}: request #{req.gen} cancelled: {out.reason}"
                values["reason"] = out.reason
            else:
                level, message = DiagnosticStatus.ERROR, f"failed: request #{req.gen}: {out.reason}"
                values["reason"] = out.reason
        statuses = [(f"{name}: planner", level, message, values)]
        ivalues = {"rejected_total": total}
        if rej is None:
            statuses.append((f"{name}: input", DiagnosticStatus.OK, "inputs ok", ivalues))
        else:
            source, code, reason, t = rej
            ivalues.update({"source": source, "code": code, "reason": reason,
                            "age_s": f"{time.monotonic() - t:.1f}"})
            statuses.append((f"{name}: input", DiagnosticStatus.ERROR, f"rejected {source}: {reason}", ivalues))
        return statuses

    def _publish_diag(self):
        pub = self.pub_diag
        if pub is None or self._closing:
            return
        try:
            pub.publish(conv.diagnostic_array(self.diagnostic_statuses(), self.get_clock().now().to_msg(),
                                              NODE_NAME))
        except Exception:              # noqa: BLE001 - context shutting down
            pass

    def _log(self, level: str, text: str):
        """
        Log through rosout while the context lives, else to stderr (no rcl error line).

        The worker thread never asks the context while the node shuts down: rclpy's
        context shutdown destroys the nodes holding the context's lock, which ``ok()``
        needs (the worker would wait for the thread that waits for it).
        """
        in_worker = threading.current_thread() is self._worker
        if not (in_worker and self._closing) and self.context.ok():
            log = self.get_logger()     # one call site per severity (rclpy requires it)
            if level == "error":
                log.error(text)
            elif level == "warning":
                log.warning(text)
            else:
                log.info(text)
        else:
            print(f"[{level.upper()}] [{self._log_name}]: {text}", file=sys.stderr)

    # ------------------------------------------------------------------ shutdown
    def destroy_node(self):
        if self._started and self._state_machine.current_state[1] != "finalized":
            self._shutdown_all("destroy_node")
        if self._started:
            self._pending_answers.drain()
            self._pending_answers.reap(now=True)
        return super().destroy_node()

    def shutdown_worker(self, timeout_s: float = 5.0, finish_goals: bool = False):
        """
        Stop the worker (cancelling a plan in progress) and the planning process.

        Every request ends (cancelled: the node is shutting down); ``finish_goals`` then lets
        the plan_capture goals and ~/replan calls in flight send their answers (see
        ``pending.PendingAnswers.drain``; not from a callback of the node's executor).
        """
        self._stop_worker(timeout_s)
        if finish_goals:
            self._pending_answers.drain()

    def _stop_worker(self, timeout_s):
        with self._lock:
            if self._stop and self._worker is None and self._backend is None:
                return
            self._closing = True
            was_planning = self._active is not None
            self._stop = True
            self._accepting = False
            self._drop_requests("the node is shutting down")
            self._lock.notify_all()
        if was_planning:
            self._log("info", "shutdown: the plan in progress is cancelled")
        self._stop_backend()
        if self._worker is not None:
            self._worker.join(timeout_s)
            self._worker = None
        self._wake_goals()

    def _stop_backend(self):
        if self._backend is not None:
            self._backend.close()
            self._backend = None


def _result_values(res, reaction) -> dict:
    """
    /diagnostics keys of a plan beyond the basics.

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
        for key in ("acs_mode", "peak_wheel_momentum_Nms", "peak_wheel_torque_Nm",
                    "free_floating_attitude_change_deg", "free_floating_tip_miss_m"):
            value = getattr(reaction, key, None)
            if value is not None:
                out[key] = f"{value:.4f}" if isinstance(value, float) else str(value)
    return out


#: what a further attempt does after a join failed (index = the attempt)
_RETRY = ("", "with twice the horizon", "from the end of the executing trajectory", "from the measured state, at rest")


def _superseded(newer: _Request) -> Outcome:
    return Outcome("superseded", f"superseded by request #{newer.gen} ({newer.why})")


def _progress(stage):
    from ..worker import STAGE_ORDER, Progress
    return Progress(0, stage, STAGE_ORDER.index(stage) / len(STAGE_ORDER))


def _target_why(target: Target) -> str:
    return (f"new target ({target.center_m[0]:.3f}, {target.center_m[1]:.3f}) m, "
            f"yaw {math.degrees(target.yaw_rad):.1f}°")


def spin_until_shutdown(node: PlannerNode, executor) -> None:
    """
    Spin ``node`` until Ctrl-C or its context shuts down.

    Then stop the worker and the planning process (a plan in progress is cancelled) and
    destroy the node.
    """
    node_main.spin_until_shutdown(node, executor, lambda: node.shutdown_worker(finish_goals=True))


def main(args=None) -> int:
    """Entry point: ``ros2 run spacerobot_planner planner_node --ros-args --params-file ...``."""
    return node_main.run_node(PlannerNode, "planner_node", args, lambda node: node.shutdown_worker(finish_goals=True))


if __name__ == "__main__":
    raise SystemExit(main())
