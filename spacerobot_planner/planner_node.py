"""`planner_node`: the ROS 2 shell around the planning core.

Subscribes ``target_pose`` (PoseStamped), ``joint_states`` (JointState) and
``goal_joint_state`` (JointState); publishes ``joint_trajectory``,
``potential_grid`` / ``cspace_grid`` (OccupancyGrid, transient-local),
``planned_path_markers`` (MarkerArray) and ``/diagnostics``; serves ``~/replan``
(std_srvs/Trigger).  Parameters: ``config.PARAMETERS`` (load a scenario with
``--ros-args --params-file config/paper_3dof.yaml``).

Threads: callbacks only record requests and run in one SingleThreadedExecutor (they
share the node's mutually exclusive callback group, so a MultiThreadedExecutor adds
nothing but a busy loop: its idle threads spin on messages that wait for the group,
and under a 200 Hz target_pose flood that loop took a whole core and starved the
callbacks -- 6-21 % of the targets handled, joint_states gaps of 0.6-0.9 s).  ONE
worker thread plans, latest request wins (a new request cancels the one being
planned and replaces the queued one; results of superseded requests are dropped).
The worker drives the planning core in a child process by default
(``planner.separate_process``): numba kernels hold the GIL for the whole solve, so
in-thread planning would freeze the executor, and a process can be stopped at
shutdown even in the middle of a long solve.  The child keeps the C-space and field
caches between plans, so a replan from a new joint state costs milliseconds.

Faults: an exception inside the planning core or the backend is logged with its
traceback (formatted where it happened, in the child process too) and reported on
``/diagnostics`` as ``internal_error``; the worker goes on with the next request.  A
planning process that died (killed, crashed) is reported the same way and a fresh
one is started for the next request (its caches are lost).
"""

from __future__ import annotations

import array
import math
import threading
import time
import traceback
from dataclasses import dataclass, replace

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from geometry_msgs.msg import PoseStamped
from nav_msgs.msg import OccupancyGrid
from rcl_interfaces.msg import (FloatingPointRange, IntegerRange, ParameterDescriptor, ParameterType,
                                SetParametersResult)
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy, HistoryPolicy
from sensor_msgs.msg import JointState
from std_srvs.srv import Trigger
from trajectory_msgs.msg import JointTrajectory
from visualization_msgs.msg import MarkerArray

from . import node_main
from . import ros_conversions as conv
from .config import NODE_NAME, PARAMETERS, check_value, scenario_from_params
from .scene import Target
from .trajectory import time_parameterize

__all__ = ["PlannerNode", "main", "spin_until_shutdown", "params_to_overrides", "GRID_QOS"]

GRID_QOS = QoSProfile(depth=1, history=HistoryPolicy.KEEP_LAST,
                      durability=DurabilityPolicy.TRANSIENT_LOCAL,
                      reliability=ReliabilityPolicy.RELIABLE)

_PTYPE = {
    "double": ParameterType.PARAMETER_DOUBLE, "integer": ParameterType.PARAMETER_INTEGER,
    "string": ParameterType.PARAMETER_STRING, "bool": ParameterType.PARAMETER_BOOL,
    "double_array": ParameterType.PARAMETER_DOUBLE_ARRAY,
    "integer_array": ParameterType.PARAMETER_INTEGER_ARRAY,
    "string_array": ParameterType.PARAMETER_STRING_ARRAY,
    "bool_array": ParameterType.PARAMETER_BOOL_ARRAY,
}
_SPECS = {p.name: p for p in PARAMETERS}
# changes of these only affect publishing, not the plan
_NO_REPLAN = {"replan.target_tolerance_m", "replan.target_tolerance_deg", "diagnostics.period_s",
              "mock_arm.rate_hz", "potential_grid.use_current_attitude",
              "potential_grid.slice_attitude_deg"}


def descriptor_for(spec) -> ParameterDescriptor:
    """ParameterDescriptor of one ParamSpec: type, description, range, read-only."""
    rng = ""
    if spec.min_value is not None or spec.max_value is not None:
        rng = f" Range [{spec.min_value}, {spec.max_value}]" + (" per element." if spec.type.endswith("_array") else ".")
    d = ParameterDescriptor(name=spec.name, type=_PTYPE[spec.type], description=spec.description + rng,
                            read_only=spec.read_only)
    if spec.min_value is not None and spec.max_value is not None:
        if spec.type == "double":
            d.floating_point_range = [FloatingPointRange(from_value=float(spec.min_value),
                                                         to_value=float(spec.max_value), step=0.0)]
        elif spec.type == "integer":
            d.integer_range = [IntegerRange(from_value=int(spec.min_value), to_value=int(spec.max_value),
                                            step=0)]
    return d


def params_to_overrides(flat: dict) -> list:
    """A flat dotted dict (e.g. from ``config.load_params_file``) → rclpy Parameter list."""
    out = []
    for k, v in flat.items():
        spec = _SPECS.get(k)
        if spec is not None:
            v = check_value(k, v)
            if spec.type == "double_array":
                v = [float(x) for x in v]
            elif spec.type == "double":
                v = float(v)
        out.append(Parameter(k, value=v))
    return out


# ====================================================================== planning backend
def _apply_settings(planner, job):
    planner.set_scene(job.scene)
    if planner.scenario.grid != job.grid:
        planner.set_grid(job.grid)
    if (planner.solver, planner.field_tolerance) != (job.solver, job.field_tolerance):
        planner.set_solver(job.solver, job.field_tolerance)
    planner.max_grid_nodes = job.max_grid_nodes


def _run_job(planner, job, cancel):
    """(kind, payload): ("result", PlanResult) or ("error", (code, reason)) for a goal failure.

    The backends turn an exception into ("crash", (what, traceback text)).
    """
    _apply_settings(planner, job)
    goal = job.joint_goal
    if goal is None:
        try:
            goal = planner.goal_from_target()
        except ValueError as e:
            return "error", ("goal_unreachable", f"target: {e}")
    return "result", planner.plan(job.start_rad, goal, cancel=cancel)


def _strip_sent(res, sent: dict):
    """(result, names left out): drop the C-space and field the parent already holds.

    A replan from cache would otherwise pickle them again (~0.5 MB at 36³).  ``sent``
    keeps the objects last sent (references, so an id is never reused).
    """
    from dataclasses import replace
    left_out = []
    for name in ("cspace", "field"):
        obj = getattr(res, name)
        if obj is None:
            continue
        if sent.get(name) is obj:
            left_out.append(name)
        else:
            sent[name] = obj
    if left_out:
        res = replace(res, **{name: None for name in left_out})
    return res, tuple(left_out)


class _GenCancel:
    """Cancel flag of the child: job ``gen`` is cancelled once a cancel for it arrived."""

    def __init__(self):
        self.cancelled_upto = 0
        self.gen = 0

    def is_set(self) -> bool:
        return self.cancelled_upto >= self.gen


def _crash(e: BaseException):
    """("crash", (what, traceback text)) for an exception caught by a backend."""
    return "crash", (f"{type(e).__name__}: {e}", traceback.format_exc())


def _child_main(fd: int) -> None:
    """The planning process: one Planner (caches kept between jobs), jobs over a socket.

    A reader thread takes ("job", gen, job), ("cancel", gen) and None (quit); the main
    thread plans.  Started by :class:`_ProcessBackend` with ``python -c``.
    """
    import queue
    import signal
    from multiprocessing.connection import Connection

    from .planner import Planner, warm_up
    signal.signal(signal.SIGINT, signal.SIG_IGN)        # the parent decides when to stop
    conn = Connection(fd)
    scenario = conn.recv()
    t_warm = time.perf_counter()
    warm_up(scenario)          # compile / load the kernels before saying "ready"
    t_warm = time.perf_counter() - t_warm
    planner = Planner(scenario)
    jobs: queue.Queue = queue.Queue()
    cancel = _GenCancel()

    def reader():
        while True:
            try:
                msg = conn.recv()
            except (EOFError, OSError):
                msg = None
            if msg is None:
                cancel.cancelled_upto = 1 << 62
                jobs.put(None)
                return
            if msg[0] == "cancel":
                cancel.cancelled_upto = max(cancel.cancelled_upto, msg[1])
            else:
                jobs.put(msg)

    threading.Thread(target=reader, daemon=True).start()
    sent = {}                  # ids of the C-space / field the node already holds
    conn.send(("ready", t_warm, None))
    while True:
        msg = jobs.get()
        if msg is None:
            return
        _, gen, job = msg
        cancel.gen = gen
        try:
            out = _run_job(planner, job, cancel)
        except Exception as e:     # noqa: BLE001 - report to the node, keep serving
            out = _crash(e)
        if out[0] == "result":
            out = ("packed", _strip_sent(out[1], sent))
        try:
            conn.send((out[0], gen, out[1]))
        except (OSError, ValueError):
            return


class _ThreadBackend:
    """Plans in the calling (worker) thread."""

    def __init__(self, scenario):
        from .planner import Planner
        self.planner = Planner(scenario)
        self._cancel = threading.Event()

    def run(self, gen, job):
        self._cancel.clear()
        try:
            return _run_job(self.planner, job, self._cancel)
        except Exception as e:     # noqa: BLE001 - report to the node, keep serving
            return _crash(e)

    def cancel(self, gen):
        self._cancel.set()

    def close(self):
        self._cancel.set()


class _ProcessBackend:
    """Plans in a child Python process; the worker thread waits on a socket (GIL free).

    A plain subprocess (not multiprocessing's spawn, which re-imports the caller's
    ``__main__``) connected by a socketpair carrying pickled jobs and results.  A child
    that died is replaced by a fresh one at the next :meth:`run`.
    """

    #: seconds ``close`` lets an idle child exit on its own before terminating it
    CLOSE_GRACE_S = 0.2

    def __init__(self, scenario, log=None, info=None):
        """log: callable for warnings (a child that died); info: for progress (warm-up)."""
        self._scenario = scenario
        self._log = log
        self._info = info
        self._send_lock = threading.Lock()
        self._proc_lock = threading.Lock()     # spawn vs close
        self._closed = False
        self._spawn()

    def _spawn(self):
        import socket
        import subprocess
        import sys
        from multiprocessing.connection import Connection
        parent, child = socket.socketpair()
        self.conn = Connection(parent.detach())
        fd = child.fileno()
        self.proc = subprocess.Popen(
            [sys.executable, "-c",
             "import sys; from spacerobot_planner.planner_node import _child_main; "
             "_child_main(int(sys.argv[1]))", str(fd)],
            pass_fds=(fd,), stdin=subprocess.DEVNULL)
        child.close()
        self.conn.send(self._scenario)
        self._ready = False
        self._held = {}          # C-space / field this child sent last (see _unpack)

    def _respawn_if_dead(self):
        with self._proc_lock:
            if self._closed or self.proc.poll() is None:
                return
            code = self.proc.returncode
            if self._log is not None:
                self._log(f"planning process {self.proc.pid} had exited (code {code}): starting a new one")
            self.conn.close()
            self._spawn()

    def _recv(self):
        while not self._closed:
            if self.conn.poll(0.05):
                return self.conn.recv()
            if self.proc.poll() is not None:
                raise RuntimeError(f"planning process exited (code {self.proc.returncode})")
        return None

    def _unpack(self, res, left_out):
        """Put back the C-space / field the child left out (the ones it sent before)."""
        from dataclasses import replace
        if left_out:
            res = replace(res, **{name: self._held[name] for name in left_out})
        for name in ("cspace", "field"):
            if getattr(res, name) is not None:
                self._held[name] = getattr(res, name)
        return res

    def run(self, gen, job):
        self._respawn_if_dead()
        try:
            if not self._ready:
                t_wait = time.perf_counter()
                ready = self._recv()
                if ready is None:
                    return None
                self._ready = True
                if self._info is not None:
                    self._info(f"planning process {self.proc.pid} ready: JIT warm-up {ready[1]:.2f} s "
                               f"(this request waited {time.perf_counter() - t_wait:.2f} s for it)")
            with self._send_lock:
                self.conn.send(("job", gen, job))
            while True:
                msg = self._recv()
                if msg is None:
                    return None
                kind, g, payload = msg
                if kind == "packed":            # see _strip_sent
                    kind, payload = "result", self._unpack(*payload)
                if g == gen:
                    return kind, payload
        except (EOFError, OSError, RuntimeError) as e:
            if self._closed:
                return None
            try:       # a dead child closes the socket just before its exit status exists
                code = self.proc.wait(0.5)
            except Exception:      # noqa: BLE001 - alive: the socket itself failed
                code = None
            what = f"planning process failed: {type(e).__name__}: {e}"
            if code is not None and str(code) not in what:
                what += f" (exit code {code})"
            return "error", ("internal_error", what)

    def cancel(self, gen):
        try:
            with self._send_lock:
                self.conn.send(("cancel", gen))
        except (OSError, ValueError):
            pass

    def close(self):
        """Stop the child: it exits at once when idle; in a solve it is terminated
        (a numba kernel cannot be interrupted otherwise) after ``CLOSE_GRACE_S``."""
        with self._proc_lock:
            self._closed = True
        try:
            with self._send_lock:
                self.conn.send(None)
        except (OSError, ValueError):
            pass
        try:
            self.proc.wait(self.CLOSE_GRACE_S)
        except Exception:          # noqa: BLE001 - a long solve: stop it
            self.proc.terminate()
            try:
                self.proc.wait(2.0)
            except Exception:      # noqa: BLE001
                self.proc.kill()
                self.proc.wait()
        self.conn.close()


@dataclass(frozen=True, eq=False)
class _Job:
    """What the worker sends to the planning core (picklable)."""

    scene: object
    grid: object
    solver: str
    field_tolerance: float
    max_grid_nodes: int
    start_rad: np.ndarray
    joint_goal: np.ndarray | None


@dataclass(frozen=True, eq=False)
class _Request:
    gen: int
    why: str
    scenario: object            # config.Scenario (scene = with the current target)
    params: dict
    joint_goal: np.ndarray | None
    t_request: float


# ====================================================================== the node
class PlannerNode(Node):
    """See the module docstring.  ``parameter_overrides`` as for rclpy.Node (see
    :func:`params_to_overrides` for a flat dict from a scenario file)."""

    def __init__(self, *, context=None, parameter_overrides=None, node_name: str = NODE_NAME, **kwargs):
        super().__init__(node_name, context=context, parameter_overrides=parameter_overrides, **kwargs)
        for spec in PARAMETERS:
            self.declare_parameter(spec.name, spec.default, descriptor_for(spec))
        self._params = {s.name: self.get_parameter(s.name).value for s in PARAMETERS}
        self._params = {k: (list(v) if isinstance(v, (tuple, np.ndarray, array.array)) else v) for k, v in self._params.items()}
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
        self._active_gen = None
        self._stop = False
        self._joint_q = None             # latest planned-joint positions (raw, unwrapped), rad
        self._joint_full = None          # latest full positions (dict name → rad)
        self._joint_stamp = None
        self._bad_joint_reason = None

        self.state = "idle"
        self.last_result = None          # PlanResult of the last published plan
        self.last_trajectory = None      # trajectory.Trajectory
        self.last_error = None           # (code, reason)
        self._last_timings = {}
        self._diag_values = {}

        # publishers
        self.pub_traj = self.create_publisher(JointTrajectory, "joint_trajectory", 10)
        self.pub_potential = self.create_publisher(OccupancyGrid, "potential_grid", GRID_QOS)
        self.pub_cspace = self.create_publisher(OccupancyGrid, "cspace_grid", GRID_QOS)
        self.pub_markers = self.create_publisher(MarkerArray, "planned_path_markers", GRID_QOS)
        self.pub_diag = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
        # subscriptions
        self.create_subscription(PoseStamped, "target_pose", self._on_target, 10)
        self.create_subscription(JointState, "joint_states", self._on_joint_state, 10)
        self.create_subscription(JointState, "goal_joint_state", self._on_goal_joint_state, 10)
        self.create_service(Trigger, "~/replan", self._on_replan)
        self.add_pre_set_parameters_callback(self._pre_set_params)
        self.add_on_set_parameters_callback(self._on_set_params)
        self.add_post_set_parameters_callback(self._post_set_params)
        self._diag_timer = self.create_timer(float(self._params["diagnostics.period_s"]), self._publish_diag)

        if self._params["planner.separate_process"]:
            self._backend = _ProcessBackend(self._scenario, log=self.get_logger().warning,
                                            info=self.get_logger().info)
        else:
            self._backend = _ThreadBackend(self._scenario)
        self._worker = threading.Thread(target=self._worker_loop, name="spacerobot_planner-worker",
                                        daemon=True)
        self._worker.start()
        self.get_logger().info(
            f"ready: planning {', '.join(self._robot.planned_names)} on a "
            f"{self._scenario.grid.label()} grid in frame '{self._frame}' "
            f"({'child process, warming up' if self._params['planner.separate_process'] else 'worker thread'}); "
            f"waiting for target_pose / goal_joint_state and joint_states")
        self._publish_diag()

    # ------------------------------------------------------------------ params
    def _check_runtime(self, params, scenario):
        from .field import SOLVERS
        if params["planner.solver"] not in SOLVERS:
            raise ValueError(f"planner.solver: unknown solver {params['planner.solver']!r}; "
                             f"expected one of {list(SOLVERS)}")
        n = scenario.robot.n_joints
        for key in ("trajectory.max_velocity_deg_s", "trajectory.max_acceleration_deg_s2"):
            if len(params[key]) != n:
                raise ValueError(f"{key}: expected {n} values (one per joint in robot.joint_names), "
                                 f"got {len(params[key])}")
        nodes = scenario.grid.n_nodes
        if nodes > params["planner.max_grid_nodes"]:
            raise ValueError(f"grid.cells: {scenario.grid.label()} = {nodes} nodes exceeds "
                             f"planner.max_grid_nodes = {params['planner.max_grid_nodes']}")

    def _validate(self, parameters):
        """(merged params, scenario) or raise ValueError naming the field."""
        merged = dict(self._params)
        for p in parameters:
            if p.name not in _SPECS:
                continue
            if _SPECS[p.name].read_only:
                raise ValueError(f"{p.name}: read-only (a change needs a restart)")
            merged[p.name] = check_value(p.name, p.value)
        scenario = scenario_from_params(merged)
        self._check_runtime(merged, scenario)
        return merged, scenario

    def _pre_set_params(self, parameters):
        # runs before rclpy's own descriptor checks: report every rejection on /diagnostics
        try:
            self._validate(parameters)
        except ValueError as e:
            self._fail("invalid_parameter", f"parameter rejected: {e}")
        return parameters

    def _on_set_params(self, parameters):
        try:
            self._validate(parameters)
        except ValueError as e:
            return SetParametersResult(successful=False, reason=str(e))
        return SetParametersResult(successful=True)

    def _post_set_params(self, parameters):
        merged, scenario = self._validate(parameters)
        names = [p.name for p in parameters if p.name in _SPECS]
        with self._lock:
            self._params = merged
            self._scenario = scenario
            if any(n.startswith("target.") for n in names):
                self._target = scenario.scene.target
        if "diagnostics.period_s" in names:
            self._diag_timer.cancel()
            self._diag_timer = self.create_timer(float(merged["diagnostics.period_s"]), self._publish_diag)
        if any(n not in _NO_REPLAN for n in names):
            self.get_logger().info(f"parameters changed ({', '.join(names)}): replanning")
            self._submit(f"parameter change ({', '.join(names)})")

    # ------------------------------------------------------------------ inputs
    def _on_target(self, msg: PoseStamped):
        try:
            target = conv.pose_to_target(msg, self._frame, self._scenario.scene.target)
        except ValueError as e:
            self._fail("invalid_input", str(e))
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
        self._submit(f"new target ({target.center_m[0]:.3f}, {target.center_m[1]:.3f}) m, "
                     f"yaw {math.degrees(target.yaw_rad):.1f}°")

    def _on_goal_joint_state(self, msg: JointState):
        try:
            q = conv.joint_state_positions(msg, self._robot.planned_names, "goal_joint_state")
            q = self._robot.validate_q(q, "goal_joint_state")
        except ValueError as e:
            self._fail("invalid_input", str(e))
            return
        with self._lock:
            self._joint_goal = q
        self._submit(f"joint goal {np.round(np.degrees(q), 2).tolist()}°")

    def _on_joint_state(self, msg: JointState):
        try:
            q = conv.joint_state_positions(msg, self._robot.planned_names)
        except ValueError as e:
            if self._bad_joint_reason != str(e):
                self._bad_joint_reason = str(e)
                self._fail("invalid_input", str(e))
            return
        self._bad_joint_reason = None
        with self._lock:
            self._joint_q = q
            self._joint_stamp = time.monotonic()
            waiting, self._waiting = self._waiting, None
            if waiting is not None and self._pending is None:
                self._pending = waiting
                self._lock.notify_all()

    def _on_replan(self, request, response):
        if self._joint_q is None:
            response.success = False
            response.message = "no joint_states received yet: will plan when the first arrives"
            self._submit("~/replan")
            return response
        gen = self._submit("~/replan")
        response.success = True
        response.message = f"replan #{gen} queued"
        return response

    # ------------------------------------------------------------------ worker
    def _submit(self, why: str) -> int:
        with self._lock:
            self._gen += 1
            scenario = self._scenario
            if self._target is not None:
                scenario = scenario.with_scene(scenario.scene.with_target(self._target))
            req = _Request(self._gen, why, scenario, dict(self._params),
                           None if self._joint_goal is None else self._joint_goal.copy(), time.perf_counter())
            if self._joint_goal is None:
                self._requested_target = self._target
            if self._joint_q is None:
                self._waiting = req
                self.get_logger().info(f"request #{req.gen} ({why}): waiting for joint_states")
            else:
                self._pending = req
                self._waiting = None
            if self._active_gen is not None:
                self._backend.cancel(self._active_gen)   # supersede the plan in progress
            self._lock.notify_all()
            return req.gen

    def _worker_loop(self):
        while True:
            with self._lock:
                while self._pending is None and not self._stop:
                    self._lock.wait()
                if self._stop:
                    return
                req, self._pending = self._pending, None
                self._active_gen = req.gen
                start = self._joint_q.copy()
            try:
                self._plan(req, start)
            except Exception as e:      # noqa: BLE001 - never let the worker die
                self._fail("internal_error", f"planning crashed: {type(e).__name__}: {e}", req,
                           tb=traceback.format_exc())
            finally:
                with self._lock:
                    self._active_gen = None

    def _superseded(self, req) -> bool:
        with self._lock:
            return self._stop or req.gen != self._gen

    def _plan(self, req: _Request, start_raw: np.ndarray):
        log = self.get_logger()
        if self.state != "planning":       # state changes at once; a flood is not echoed
            self.state = "planning"
            self._publish_diag()
        sc = req.scenario
        log.info(f"planning #{req.gen} ({req.why}) from {np.round(np.degrees(start_raw), 2).tolist()}° "
                 f"on {sc.grid.label()}")
        p = req.params
        job = _Job(scene=sc.scene, grid=sc.grid, solver=p["planner.solver"],
                   field_tolerance=float(p["planner.field_tolerance"]),
                   max_grid_nodes=int(p["planner.max_grid_nodes"]), start_rad=start_raw,
                   joint_goal=req.joint_goal)
        out = self._backend.run(req.gen, job)
        if out is None or self._superseded(req):
            if out is not None and out[0] == "crash":      # still worth a traceback
                log.error(f"plan #{req.gen} crashed: {out[1][0]}\n{out[1][1].rstrip()}")
            log.info(f"plan #{req.gen} superseded: result dropped")
            return
        kind, payload = out
        if kind == "crash":
            what, tb = payload
            self._fail("internal_error", f"planning crashed: {what}", req, tb=tb)
            return
        if kind == "error":
            code, reason = payload
            self._fail(code, reason, req)
            return
        res = payload
        if not res.ok:
            if res.code == "cancelled":
                log.info(f"plan #{req.gen} cancelled")
                return
            self._fail(res.code, res.reason or res.code, req, res, tb=res.traceback or None)
            return
        traj = self._time_parameterize(res, start_raw, p)
        if self._superseded(req):
            log.info(f"plan #{req.gen} superseded: result dropped")
            return
        msg = conv.trajectory_to_msg(traj, self.get_clock().now().to_msg())
        latency = time.perf_counter() - req.t_request
        # the node's state first: whoever reacts to the trajectory sees this plan
        with self._lock:
            self.last_result = res
            self.last_trajectory = traj
            self.last_error = None
            self._last_timings = dict(res.timings_s)
            self._diag_values = {
                **self._request_values(req),
                "goal_deg": np.round(np.degrees(res.goal_rad), 3).tolist(),
                "min_clearance_m": f"{res.min_clearance_m:.4f}",
                "trajectory_duration_s": f"{traj.duration_s:.3f}",
                "trajectory_points": len(traj),
                "cached": ",".join(res.cached) or "none",
                "solver": res.solver,
                "latency_s": f"{latency:.4f}",
            }
            self.state = "idle"
        self.pub_traj.publish(msg)
        t = res.timings_s
        log.info(f"plan #{req.gen} ok in {1e3 * t['total']:.1f} ms (cspace {1e3 * t['cspace']:.1f}, "
                 f"field {1e3 * t['field']:.1f}, descent {1e3 * t['descent']:.1f}, smoothing "
                 f"{1e3 * t['smoothing']:.1f}, verify {1e3 * t['verify']:.1f} ms; cached: "
                 f"{', '.join(res.cached) or 'none'}); clearance {res.min_clearance_m:.3f} m; "
                 f"trajectory {len(traj)} points, {traj.duration_s:.2f} s; request→trajectory "
                 f"{1e3 * latency:.1f} ms")
        self._publish_visuals(res, sc, start_raw, p)
        self._publish_diag()

    def _time_parameterize(self, res, start_raw, p):
        robot = self._robot
        idx = list(robot.planned_joints)
        path = np.array(res.path_rad, dtype=float)
        # continuous values from where the arm is: shift periodic columns by whole turns so
        # the first point equals the joint_states value
        for k, periodic in enumerate(robot.planned_periodic):
            if periodic:
                path[:, k] += 2 * math.pi * round((start_raw[k] - path[0, k]) / (2 * math.pi))
        path[0] = start_raw
        vmax = np.radians(np.asarray(p["trajectory.max_velocity_deg_s"], dtype=float))[idx]
        amax = np.radians(np.asarray(p["trajectory.max_acceleration_deg_s2"], dtype=float))[idx]
        return time_parameterize(path, vmax, amax, robot.planned_names)

    # ------------------------------------------------------------------ outputs
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
        self.pub_markers.publish(conv.path_markers(self._robot, sc.scene, res.path_rad, self._frame, stamp))
        sl = self.slice_axes_and_point(res, start_raw, params)
        if sl is None or res.cspace is None:
            return
        ax, ay, q = sl
        grid = res.cspace.grid
        occ = conv.grid_slice(grid, res.cspace.occupied, q, (ax, ay))
        self.pub_cspace.publish(conv.grid_slice_to_msg(conv.obstacle_slice_values(occ), grid, (ax, ay),
                                                       self._frame, stamp))
        if res.field is not None:
            phi = res.field.potential()
            finite = np.isfinite(phi)
            phi_max = float(phi[finite].max()) if finite.any() else 0.0
            log_u = conv.grid_slice(grid, res.field.log_u, q, (ax, ay))
            focc = conv.grid_slice(grid, res.field.occupied, q, (ax, ay))
            vals = conv.potential_slice_values(log_u, focc, phi_max)
            self.pub_potential.publish(conv.grid_slice_to_msg(vals, grid, (ax, ay), self._frame, stamp))

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

    def _fail(self, code: str, reason: str, req: _Request | None = None, res=None, tb: str | None = None):
        """Report a failure: log (with the traceback if any) and an ERROR on /diagnostics.

        With ``req`` (a planning outcome) the diagnostics values describe that request
        (the previous plan's goal, clearance and timings are dropped); without (bad
        input, a rejected parameter) they keep describing the last plan.
        """
        log = self.get_logger()
        where = f"plan #{req.gen}: " if req is not None else ""
        log.error(f"{where}{code}: {reason}" + (f"\n{tb.rstrip()}" if tb else ""))
        with self._lock:
            self.last_error = (code, reason)
            self.state = "failed"
            if req is not None:
                values = self._request_values(req)
                if res is not None and res.goal_rad is not None:
                    values["goal_deg"] = np.round(np.degrees(res.goal_rad), 3).tolist()
                self._diag_values = values
                self._last_timings = dict(res.timings_s) if res is not None else {}
        self._publish_diag()

    def _publish_diag(self):
        with self._lock:
            state = self.state
            err = self.last_error
            values = {"state": state}
            values.update({f"time_{k}_ms": f"{1e3 * v:.2f}" for k, v in self._last_timings.items()})
            values.update(self._diag_values)
            if err is not None:
                values["code"], values["reason"] = err
        if err is not None and state == "failed":
            level, msg = DiagnosticStatus.ERROR, f"failed: {err[1]}"
        else:
            level, msg = DiagnosticStatus.OK, state
        try:
            self.pub_diag.publish(conv.diagnostic_array(f"{self.get_name()}: planner", level, msg, values,
                                                        self.get_clock().now().to_msg(), NODE_NAME))
        except Exception:              # noqa: BLE001 - context shutting down
            pass

    # ------------------------------------------------------------------ lifecycle
    def destroy_node(self):
        self.shutdown_worker()
        return super().destroy_node()

    def shutdown_worker(self, timeout_s: float = 5.0):
        """Stop the worker (cancelling a plan in progress) and the planning process."""
        with self._lock:
            if self._stop:
                return
            self._stop = True
            self._lock.notify_all()
        self._backend.close()
        self._worker.join(timeout_s)


def spin_until_shutdown(node: PlannerNode, executor) -> None:
    """Spin ``node`` until Ctrl-C or its context shuts down, then stop the worker and
    the planning process (a plan in progress is abandoned) and destroy the node.

    ``main``'s own shutdown path, in a function of its own so tests can run it.
    """
    node_main.spin_until_shutdown(node, executor, node.shutdown_worker)


def main(args=None) -> int:
    """Entry point: ``ros2 run spacerobot_planner planner_node --ros-args --params-file ...``."""
    return node_main.run_node(PlannerNode, "planner_node", args, PlannerNode.shutdown_worker)


if __name__ == "__main__":
    raise SystemExit(main())
