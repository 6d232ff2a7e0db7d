"""
`planner_node`: the ROS 2 shell around a capture session, a lifecycle node (docs/node.md).

The node is I/O: messages in become calls of a ``session.CaptureSession`` (which keeps
the current goal, chooses the start, plans through the one post-processing chain,
retries, stamps and applies the at-goal rule: no rclpy there), and what the session hands
back becomes messages.  Its parts: ``lifecycle.py`` (the lifecycle services, with the
reason of a refused transition), ``parameter_handler.py`` (a change validated once,
applied once), ``action.py`` (``plan_capture``), ``diagnostics.py`` (``/diagnostics``
from the session's outcomes), ``conversions.py`` (messages), ``pending.py`` (the answers
owed at shutdown), ``rejections.py`` (rate-limited logs of bad input), ``log_lines.py`` (the
session's log lines at rcutils' cost).

Lifecycle (as Nav2's planner server): ``configure`` starts the planning process and waits
for its JIT warm-up, creates the publishers, the action server and the session's worker;
``activate`` creates the subscriptions and ``~/replan`` and enables the publishers;
``deactivate`` cancels what is being planned and removes them; ``cleanup`` stops the worker
and the planning process; ``shutdown`` does what is needed from any state.  ``autostart``
(default true) configures and activates at start.  Start: the values given are checked
against the schema (``config.PARAMETERS``) first; a refused one ends the start with one
line naming the parameter and why (exit code 1); an unknown one is named in a warning.

Interfaces (when active): subscribes ``target_pose``, ``joint_states``,
``goal_joint_state`` and ``attitude_topic`` when set (its yaw stands for the attitude joint
in joint_states that lack it); publishes ``joint_trajectory`` (arm joints) and
``attitude_trajectory`` (one stamp, at least ``trajectory.start_lead_s`` after they are
published), ``potential_grid`` / ``cspace_grid`` (transient-local, frame ``grid_frame``),
``planned_path_markers``, ``/diagnostics``; serves ``~/replan`` (std_srvs/Trigger: plans
to the current goal and answers with that plan's outcome; before the first joint_states
at once, saying that it is queued) and the action ``plan_capture``.  The goal: the latest
accepted request from any channel is what a replan or a parameter change plans to; a goal
with its own ``start`` is planned and returned, not executed.

Threads: callbacks only record requests (one SingleThreadedExecutor, ``executor.NodeExecutor``).  The session's ONE
worker thread plans, latest request wins, through ``worker.HybridBackend``: a child
process that never imports rclpy, and the replans the C-space and field it sent last answer in
the worker thread itself (``planner.replans_in_node``).
"""

from __future__ import annotations

import array
import gc
import sys
import threading
import time

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray
from nav_msgs.msg import OccupancyGrid
from rclpy.callback_groups import ReentrantCallbackGroup
from rclpy.clock import Clock, ClockType
from rclpy.lifecycle import LifecycleNode, TransitionCallbackReturn
from rclpy.logging import LoggingSeverity
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.task import Future
from std_srvs.srv import Trigger
from trajectory_msgs.msg import JointTrajectory
from visualization_msgs.msg import MarkerArray

from ..adapters import warm_up as warm_up_chain
from ..config import NODE_NAME, scenario_from_params, session_settings_from_params, unknown_parameters
from ..jit_cache import start_numba
from ..session import CaptureSession, Outcome
from ..worker import make_backend
from . import conversions as conv
from . import node_main
from .action import PlanCaptureServer
from .controller_probe import ControllerProbe
from .diagnostics import NodeDiagnostics
from .inputs import Inputs
from .lifecycle import LifecycleInterface
from .log_lines import LogLines
from .parameter_handler import NO_REPLAN, TARGET_POSE_PARAMETERS, ParameterHandler, check_runtime
from .parameters import PLANNER_PARAMETERS, as_declared, declare_checked, params_to_overrides
from .pending import PendingAnswers
from .time_jumps import no_clock_yet, on_time_jumps

__all__ = ["PlannerNode", "main", "spin_until_shutdown", "params_to_overrides", "GRID_QOS", "Outcome"]

GRID_QOS = QoSProfile(depth=1, history=HistoryPolicy.KEEP_LAST,
                      durability=DurabilityPolicy.TRANSIENT_LOCAL,
                      reliability=ReliabilityPolicy.RELIABLE)
WARM_UP_TIMEOUT_S = 300.0
#: after publishing a trajectory the worker lets go of the interpreter this long before the
#: visuals (~2 ms of Python): a subscriber in this process (a test's, the latency bench's, a
#: controller's) takes it meanwhile instead of waiting for them.  Measured with
#: ``bench latency`` (load 9, 2 cores): send -> arrival 2.7 -> 2.0 ms median, p90 7.6 -> 2.5 ms, s
YIELD_AFTER_SEND_S = 0.0003
#: the worker thread's log lines wait at most this long for the rclpy context's lock, s
#: (:meth:`PlannerNode._context_ok_soon`)
CONTEXT_WAIT_S = 0.05
#: the severities of ``_log``'s levels (any other level: info), and rcutils' name of each in its lines
_SEVERITY = {"error": LoggingSeverity.ERROR, "warning": LoggingSeverity.WARN}
_RCUTILS_NAME = {LoggingSeverity.ERROR: "ERROR", LoggingSeverity.WARN: "WARN", LoggingSeverity.INFO: "INFO"}


class PlannerNode(LifecycleNode):
    """
    See the module docstring.

    ``parameter_overrides`` as for rclpy.Node (see :func:`params_to_overrides`
    for a flat dict from a scenario file).
    """

    #: every attribute exists (a refused start ends in ``__init__``; rclpy destroys the node later)
    _started = False

    def __init__(self, *, context=None, parameter_overrides=None, node_name: str = NODE_NAME, backend_factory=None,
                 freeze_start_up: bool = False, start_check=None, **kwargs):
        # backend_factory(scenario, separate_process, log=, info=, replans_here=) -> a worker backend: how configure
        # gets its planning process (default worker.make_backend: a new one, warmed up then)
        self._make_backend = backend_factory or make_backend
        # freeze_start_up: configure moves what start-up made out of the garbage collector's reach
        # (gc.freeze, a process-wide setting): only where the node owns its process (main());
        # in a process that hosts other nodes or tests, frozen garbage (an old rclpy context and
        # its DDS participant) would never be freed
        self._freeze_start_up = bool(freeze_start_up)
        super().__init__(node_name, context=context, parameter_overrides=parameter_overrides,
                         automatically_declare_parameters_from_overrides=True,
                         enable_communication_interface=False, **kwargs)
        self._log_name = self.get_logger().name       # the remapped name and namespace (robot1.other_name)
        self._steady_clock = Clock(clock_type=ClockType.STEADY_TIME)
        self._log_lines = LogLines(self.get_logger())     # _log's lines (rclpy's logger: ~0.4 ms a line)
        others = declare_checked(self, PLANNER_PARAMETERS)      # ValueError: the parameter and why
        for line in unknown_parameters(others):                 # typos, named with the closest name
            self.get_logger().warning(line)
        if start_check is not None:     # the executable's: its parameter files state the robot (ValueError)
            start_check(self)
        params = {n: self.get_parameter(n).value for n in PLANNER_PARAMETERS}
        params = {k: (list(v) if isinstance(v, (tuple, np.ndarray, array.array)) else v) for k, v in params.items()}
        scenario = scenario_from_params(params)        # raises on a bad file: fail at start
        check_runtime(params, scenario)
        self.robot = scenario.robot
        self.planning_frame = scenario.planning_frame
        self._phase = "unconfigured"     # the lifecycle's view: unconfigured, inactive, active, finalized
        self.session = CaptureSession(scenario, session_settings_from_params(params), now_ns=self._now_ns,
                                      log=self._log, publish=self._publish_outcome, record=self._record,
                                      changed=self._publish_diag, clock_problem=self._clock_problem)
        self._time_jumps = on_time_jumps(self, self.session.time_jumped,     # the handle keeps the callbacks
                                         before=self.session.time_jumping)
        self.diagnostics = NodeDiagnostics()
        self.inputs = Inputs(self)       # the input topics
        self._waiting_timer = None       # ends a goal's wait for the first joint_states
        self._pubs = {}
        self._grid_slices = conv.GridSlices()     # the last plan's grid messages (reused by a cached replan)
        self.pub_diag = None
        self._diag_timer = None
        self._active_entities = []       # subscriptions, service (destroyed on deactivate)
        self._probe = None               # controller.switch auto: asks joint_trajectory's subscribers (configure)
        self._action = None
        self._pending_answers = PendingAnswers(self, self._log)    # goals and ~/replan calls in flight
        self._goals = self._pending_answers.goals                  # goal id bytes -> the goal's request
        self._wake = self.create_guard_condition(lambda: None)   # resumes awaiting goals
        self.param_handler = ParameterHandler(
            self, params, scenario, apply=self._apply_params,
            reject=lambda reason: self._reject("parameters", "invalid_parameter", reason),
            current_target=lambda: self.session.target)
        self._lifecycle = LifecycleInterface(self)
        self._started = True
        if params["autostart"]:
            if self.trigger_configure() != TransitionCallbackReturn.SUCCESS:
                raise RuntimeError("autostart: configure failed (see the log)")
            if self.trigger_activate() != TransitionCallbackReturn.SUCCESS:
                raise RuntimeError("autostart: activate failed (see the log)")

    # ------------------------------------------------------------------ what tests and tools read
    @property
    def _params(self) -> dict:
        return self.param_handler.params

    @property
    def state(self) -> str:
        """Return unconfigured, inactive, idle, planning or finalized."""
        return self.session.activity if self._phase == "active" else self._phase

    @property
    def last_result(self):
        return self.session.last_result

    @property
    def last_trajectory(self):
        return self.session.last_trajectory

    @property
    def last_outcome(self) -> Outcome | None:
        return self.diagnostics.last_outcome

    _joint_q = property(lambda self: self.session.joint_q)
    _gen = property(lambda self: self.session.gen)
    _target = property(lambda self: self.session.target)
    _requested_target = property(lambda self: self.session.requested_target)
    _backend = property(lambda self: self.session.backend)
    _worker = property(lambda self: self.session.worker)
    _rejected_total = property(lambda self: self.diagnostics.rejected_total)
    _attitude = property(lambda self: self.inputs.attitude)

    @property
    def lifecycle_state(self) -> str:
        """Return the lifecycle state's label (unconfigured, inactive, active, finalized)."""
        return self._lifecycle.state

    def _now_ns(self) -> int:
        return self.get_clock().now().nanoseconds

    def _clock_problem(self) -> str | None:
        """Why ROS time cannot stamp a trajectory now (see ``ros.time_jumps``), else None."""
        if no_clock_yet(self.get_clock()):
            return ("ROS time is 0: use_sim_time is true and no /clock message has come yet, so a trajectory "
                    "would start in the past (publish /clock: the simulator, or `ros2 bag play --clock`)")
        return None

    # ------------------------------------------------------------------ lifecycle
    def trigger_configure(self):
        return self._lifecycle.run("configure", super().trigger_configure)

    def trigger_activate(self):
        return self._lifecycle.run("activate", super().trigger_activate)

    def trigger_deactivate(self):
        return self._lifecycle.run("deactivate", super().trigger_deactivate)

    def trigger_cleanup(self):
        return self._lifecycle.run("cleanup", super().trigger_cleanup)

    def trigger_shutdown(self):
        return self._lifecycle.run("shutdown", super().trigger_shutdown)

    def on_configure(self, state):
        log = self.get_logger()
        t0 = time.perf_counter()
        scenario = self.param_handler.scenario
        backend = None
        try:
            backend = self._make_backend(scenario, self._params["planner.separate_process"], log=log.warning,
                                         info=log.info, replans_here=self._params["planner.replans_in_node"])
            # this process's kernels (the chain from rest and joined to a moving arm), while the child warms up
            try:
                warm_up_chain(scenario)
            except ValueError as e:     # limits no motion can keep to: every plan says so too
                log.warning(f"configure: the trajectory warm-up was refused ({e}); plans will be too")
            # the replans it plans itself (worker.HybridBackend): from the child's seed, while it warms up
            until = time.monotonic() + WARM_UP_TIMEOUT_S
            backend.warm_up_here(WARM_UP_TIMEOUT_S)
            if backend.wait_ready(max(0.0, until - time.monotonic())) is None:
                raise RuntimeError(f"no warm-up within {WARM_UP_TIMEOUT_S} s")
        except Exception as e:      # noqa: BLE001 - a failed configure, with the reason
            log.error(f"configure failed: planning process: {type(e).__name__}: {e}")
            if backend is not None:
                backend.close()
            return TransitionCallbackReturn.FAILURE
        self._pubs = {
            "traj": self.create_lifecycle_publisher(JointTrajectory, "joint_trajectory", 10),
            "attitude": self.create_lifecycle_publisher(JointTrajectory, "attitude_trajectory", 10),
            "potential": self.create_lifecycle_publisher(OccupancyGrid, "potential_grid", GRID_QOS),
            "cspace": self.create_lifecycle_publisher(OccupancyGrid, "cspace_grid", GRID_QOS),
            "markers": self.create_lifecycle_publisher(MarkerArray, "planned_path_markers", GRID_QOS),
        }
        self.pub_diag = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
        self._action = PlanCaptureServer(self)
        self._diag_timer = self.create_timer(float(self._params["diagnostics.period_s"]), self._diag_tick)
        if self._params["controller.switch"] == "auto":
            self._probe = ControllerProbe(self, self._pubs["traj"].topic_name, self._controller_found, self._log)
            self._probe.start()
        self.session.start(backend)
        self._phase = "inactive"
        # what start-up made (modules, kernels, the warm-up's objects) lives as long as the process:
        # out of the collector's reach, a full collection in the worker thread (under a trajectory's
        # way out) walks only what the plans made since (100+ ms -> a few ms at the 3-DOF grid)
        if self._freeze_start_up:
            gc.collect()                 # garbage is freed first, not frozen with the rest
            gc.freeze()
        where = ("worker thread" if not self._params["planner.separate_process"] else "planning process"
                 if not self._params["planner.replans_in_node"] else "planning process and replans' kernels")
        log.info(f"configured in {time.perf_counter() - t0:.2f} s: planning "
                 f"{', '.join(self.robot.planned_names)} on a {scenario.grid.label()} grid in frame "
                 f"'{self.planning_frame}' ({where} warmed up)")
        self._publish_diag()
        return TransitionCallbackReturn.SUCCESS

    def on_activate(self, state):
        ret = super().on_activate(state)          # enables the lifecycle publishers
        self._active_entities = self.inputs.subscribe() + [
            # its own (reentrant) group: the node's default group is mutually exclusive, and an
            # awaiting callback would hold it (no other callback of the node) until it answers
            self.create_service(Trigger, "~/replan", self._on_replan, callback_group=ReentrantCallbackGroup()),
        ]
        self.session.accept(True)
        self._phase = "active"
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
        self.session.accept(False, why)
        self._phase = "inactive"
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
        Stop the worker and remove what configure made (the objects frozen then go back to the collector).

        In a transition (a callback of the executor) the goals in flight return their results
        after it, so their action server is destroyed later (``pending.PendingAnswers.retire``);
        ``finish_goals`` (not in a callback: destroy_node) lets them return their results first.
        """
        self.shutdown_worker(finish_goals=finish_goals)
        action, self._action = self._action, None
        if action is not None:
            self._pending_answers.retire(action.destroy)
        probe, self._probe = self._probe, None
        if probe is not None:
            probe.destroy()
            self.session.controller_found(None)
        for pub in self._pubs.values():
            self.destroy_lifecycle_publisher(pub)
        self._pubs = {}
        if self._diag_timer is not None:
            self.destroy_timer(self._diag_timer)
            self._diag_timer = None
        if self.pub_diag is not None:
            self.destroy_publisher(self.pub_diag)
            self.pub_diag = None
        if self._freeze_start_up:
            gc.unfreeze()
        self._phase = "unconfigured"

    def on_shutdown(self, state):
        self._shutdown_all("shutdown")
        return TransitionCallbackReturn.SUCCESS

    def on_error(self, state):
        self._shutdown_all("error")
        return TransitionCallbackReturn.SUCCESS

    def _shutdown_all(self, why):
        if self.session.accepting:
            self._deactivate(f"the node is shutting down ({why})")
        self._cleanup(finish_goals=why == "destroy_node")
        self._phase = "finalized"
        self._log("info", f"{why}: finalized")

    # ------------------------------------------------------------------ parameters
    def set_parameters_atomically(self, parameter_list):
        """As rclpy's (the ``~/set_parameters`` service calls it): whole numbers as doubles, then the precheck."""
        parameter_list = as_declared(parameter_list)
        refused = self.param_handler.precheck(parameter_list)
        return refused if refused is not None else super().set_parameters_atomically(parameter_list)

    def set_parameters(self, parameter_list):
        """As rclpy's, whole numbers as doubles, the handler's precheck first for each parameter."""
        out = []
        for p in as_declared(parameter_list):
            refused = self.param_handler.precheck([p])
            out.extend([refused] if refused is not None else super().set_parameters([p]))
        return out

    def _apply_params(self, params, scenario, names):
        """Apply an accepted change (once): the session's scenario and settings, the timer, a replan."""
        moved = any(n in TARGET_POSE_PARAMETERS for n in names)     # else only its sizes, where it is
        self.session.configure(scenario, session_settings_from_params(params), target_changed=moved,
                               target_resized=not moved and any(n.startswith("target.") for n in names))
        if "diagnostics.period_s" in names and self._diag_timer is not None:
            self.destroy_timer(self._diag_timer)
            self._diag_timer = self.create_timer(float(params["diagnostics.period_s"]), self._diag_tick)
        if any(n not in NO_REPLAN for n in names) and self.session.accepting:
            self.get_logger().info(f"parameters changed ({', '.join(names)}): replanning")
            self._submit(f"parameter change ({', '.join(names)})")

    # ------------------------------------------------------------------ requests
    async def _on_replan(self, request, response):
        """~/replan: plan to the current goal now; answer with the plan's outcome (see the module docstring)."""
        self._pending_answers.running()
        if self.session.joint_q is None:
            req = self._submit("~/replan")
            response.success = False
            response.message = (f"replan #{req.gen} queued: no joint_states received yet, it plans when the first "
                                "arrives (its outcome: /diagnostics)")
            return response
        done = Future()

        def on_done(outcome):
            done.set_result(outcome)
            self._wake_goals()

        self._pending_answers.replans += 1
        try:
            req = self._submit("~/replan", on_done=on_done)
            outcome = await done
        finally:
            self._pending_answers.replans -= 1
        response.success = outcome.ok
        response.message = f"replan #{req.gen}: {outcome.code}" + (f": {outcome.reason}" if outcome.reason else "")
        return response

    def _submit(self, req, **kw):
        """Submit a request to the session (see ``CaptureSession.submit``); bound a client's wait for joint_states."""
        req = self.session.submit(req, **kw)
        if req.gen:
            self.diagnostics.accepted()         # a good request: the input status is OK again
        if req.waiting and req.on_done is not None:
            timeout_s = float(self._params["joint_states_timeout_s"])
            if self._waiting_timer is not None:
                self.destroy_timer(self._waiting_timer)
            # a client's wait: wall time (a ROS-time timer never fires under use_sim_time without /clock)
            self._waiting_timer = self.create_timer(timeout_s, lambda: self._joint_states_timeout(req, timeout_s),
                                                    clock=self._steady_clock)
        return req

    def _joint_states_timeout(self, req, timeout_s):
        """Timer: ``req`` (a goal) waited too long for joint_states."""
        timer, self._waiting_timer = self._waiting_timer, None
        if timer is not None:
            self.destroy_timer(timer)
        clock = self._clock_problem()       # a driver (the mock arm too) on ROS time waits for /clock to publish
        self.session.expire_waiting(req, f"no joint_states within {timeout_s:g} s: the arm's state (the plan's "
                                    "start) is unknown; publish joint_states or give the goal a start"
                                    + ("" if clock is None else f"; and {clock}"))

    def _wake_goals(self):
        try:
            self._wake.trigger()
        except Exception:          # noqa: BLE001 - context already shut down
            pass

    # ------------------------------------------------------------------ outputs (the session's hooks)
    def _publish_outcome(self, req, outcome):
        """Publish an ok outcome (the worker thread, just after it was stamped): trajectories, then visuals."""
        if outcome.publication.sent:
            arm, att = conv.publication_payloads(outcome.publication)     # serialized: no message objects
            if arm is not None:
                self._pubs["traj"].publish(arm)
            if att is not None:
                self._pubs["attitude"].publish(att)
            outcome.stamps["sent"] = time.perf_counter()      # the trajectories (bench latency's breakdown)
            time.sleep(YIELD_AFTER_SEND_S)                    # their subscribers in this process first
        p = self._params
        markers, cspace, potential = conv.plan_visuals(
            self.robot, req.scenario.scene, outcome.result, self.planning_frame, p["grid_frame"],
            self.get_clock().now().to_msg(), p["potential_grid.use_current_attitude"],
            p["potential_grid.slice_attitude_deg"], slices=self._grid_slices)
        for key, msg in (("markers", markers), ("cspace", cspace), ("potential", potential)):
            if msg is not None:
                self._pubs[key].publish(msg)

    def _record(self, req, outcome):
        """Make the planner status describe this finished request from now on, and only it."""
        self.diagnostics.record(req, outcome)
        self._publish_diag()

    def _reject(self, source: str, code: str, reason: str):
        """Log bad input (a message, a goal, a parameter; rate-limited for topics) and raise the input status."""
        line, news = self.diagnostics.reject(source, code, reason)
        if line is not None:
            self.get_logger().error(line)
        if line is not None or news:          # else the heartbeat carries the count
            self._publish_diag()

    def _diag_tick(self):
        """Diagnostics timer: the heartbeat, and the count lines of floods of bad input."""
        for line in self.diagnostics.flush():
            self.get_logger().error(line)
        self._publish_diag()

    def _publish_diag(self):
        pub = self.pub_diag
        if pub is None or self.session.closing:
            return
        try:
            # the namespace too (robot1.spacerobot_planner; no '/': rqt_robot_monitor and the aggregator
            # split names on it): two robots' planners share /diagnostics
            name = self._log_name
            pub.publish(conv.diagnostic_payload(self.diagnostics.statuses(name, self.state, self._controller_values()),
                                                self.get_clock().now().to_msg(), name))
        except Exception:              # noqa: BLE001 - context shutting down
            pass

    def _controller_found(self, switch):
        """Take the probe's news (controller.switch auto): the session sends for that kind from now on; said at once."""
        self.session.controller_found(switch)
        self._publish_diag()

    def _controller_values(self) -> dict:
        """/diagnostics: when the arm's controller is taken to switch to a newer trajectory, and who says so."""
        probe = self._probe
        source = ("parameter controller.switch" if self._params["controller.switch"] != "auto"
                  else f"auto: {probe.text}" if probe is not None else "auto: not configured")
        return {"controller_switch": self.session.controller_switch, "controller_switch_source": source}

    def _log(self, level: str, text: str):
        """
        Log through rosout while the context lives, else to stderr (no rcl error line).

        The worker thread never asks the context while the node shuts down: rclpy's
        context shutdown destroys the nodes holding the context's lock, which ``ok()``
        needs (the worker would wait for the thread that waits for it).
        """
        in_worker = threading.current_thread() is self.session.worker
        severity = _SEVERITY.get(level, LoggingSeverity.INFO)
        if (self.context.ok() if not in_worker else not self.session.closing and self._context_ok_soon()):
            self._log_lines.log(severity, text)
        else:
            # as rcutils writes a line (its default format): the level (the one rosout gets), the time in
            # seconds, the name
            t_ns = time.time_ns()
            print(f"[{_RCUTILS_NAME[severity]}] [{t_ns // 10**9}.{t_ns % 10**9:09d}] "
                  f"[{self._log_name}]: {text}", file=sys.stderr)

    def _context_ok_soon(self) -> bool:
        """
        Return ``context.ok()`` for the worker thread, false when its lock is not free within ``CONTEXT_WAIT_S``.

        The shutdown may take the context's lock after the worker saw the session open: rclpy's
        context shutdown destroys the nodes holding it, and the node's destroy waits for the worker
        (up to 5 s, and the worker then outlived the node: seen under load, a Ctrl-C during a plan).
        Other holders (the executor's ``ok()`` each spin) hold it for microseconds.
        """
        lock = getattr(self.context, "_lock", None)        # rclpy's Context: an RLock
        if lock is None:
            return self.context.ok()
        if not lock.acquire(timeout=CONTEXT_WAIT_S):
            return False
        try:
            return self.context.ok()
        finally:
            lock.release()

    # ------------------------------------------------------------------ shutdown
    def destroy_node(self):
        if self._started and self._lifecycle.state != "finalized" and self._phase != "finalized":
            self._shutdown_all("destroy_node")
        if self._started:
            self._pending_answers.drain()
            self._pending_answers.reap(now=True)
        super().destroy_node()
        # rclpy's LifecycleNode leaves its state machine, which holds the rcl node, to the garbage
        # collector: the node, and with its context's last node the DDS participant, lived on
        # until the Python object went (a process that hosts other nodes met it at a random
        # allocation later, while its other participants discovered each other)
        machine = getattr(self, "_state_machine", None)
        if machine is not None:
            machine.destroy_when_not_in_use()

    def shutdown_worker(self, timeout_s: float = 5.0, finish_goals: bool = False):
        """
        Stop the session's worker (cancelling a plan in progress) and the planning process.

        Every request ends (cancelled: the node is shutting down); ``finish_goals`` then lets
        the plan_capture goals and ~/replan calls in flight send their answers (see
        ``pending.PendingAnswers.drain``; not from a callback of the node's executor).
        """
        if self.session.stop(timeout_s):
            self._wake_goals()
        if finish_goals:
            self._pending_answers.drain()


def spin_until_shutdown(node: PlannerNode, executor) -> None:
    """
    Spin ``node`` until Ctrl-C or its context shuts down.

    Then stop the worker and the planning process (a plan in progress is cancelled) and
    destroy the node.
    """
    node_main.spin_until_shutdown(node, executor, lambda: node.shutdown_worker(finish_goals=True))


def main(args=None) -> int:
    """Entry point: ``ros2 run spacerobot_planner planner_node --ros-args --params-file ...``."""
    start_numba()                   # a process of its own: cached kernels without their linking bitcode, no BLAS check
    return node_main.run_node(lambda check: PlannerNode(freeze_start_up=True, start_check=check), "planner_node", args,
                              lambda node: node.shutdown_worker(finish_goals=True))


if __name__ == "__main__":
    raise SystemExit(main())
