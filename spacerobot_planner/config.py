"""
Scenario files and parameters: one schema for the YAML loader, the CLI and the node.

The problem type itself (``Scenario``) lives in ``problem.py`` (no YAML there); it is
re-exported here.

Scenario files are ROS 2 parameter files (``--params-file``): a shared ``/**``
section (robot, scene, start: what more than one node reads) and a section per node
(``/**/spacerobot_planner``: grid, planner, trajectory, node settings;
``/**/mock_arm``), named with a wildcard namespace so that they apply to a node
started in any namespace (``-r __ns:=/robot2``; a plain ``spacerobot_planner`` section
applies to ``/spacerobot_planner`` only)::

    /**:
      ros__parameters:
        robot:
          joint_names: [attitude, shoulder, elbow]
          ...
    /**/spacerobot_planner:
      ros__parameters:
        grid:
          cells: [36, 36, 36]

Nested keys become dotted parameter names (``robot.joint_names``).  Angles are in
degrees in files (people read them), radians everywhere inside.  ``PARAMETERS``
lists every parameter with its type, default (the paper's 3-DOF scene), unit,
range and whether a change needs a restart; the node declares exactly these.
"""

from __future__ import annotations

import array
import difflib
import math
import re
from dataclasses import dataclass

import numpy as np
import yaml

from .cspace import grid_for_robot
from .spacecraft import ACS_MODES, AcsSettings, MassProperties
from .problem import Scenario
from .robot import PlanarArm, square_polygon
from .scene import Scene, Target
from .settings import JointLimits, PlannerSettings, SessionSettings

__all__ = ["ParamSpec", "PARAMETERS", "Scenario", "load_scenario", "load_params_file", "matching_sections",
           "section_regex", "flatten_params",
           "unknown_parameters", "ROS_PARAMETERS", "DECLARED_ALIASES",
           "scenario_from_params", "spec_default", "NODE_NAME", "settings_from_params", "joint_limits_from_params",
           "session_settings_from_params"]

NODE_NAME = "spacerobot_planner"


@dataclass(frozen=True)
class ParamSpec:
    """One parameter: dotted name, ROS type, default, description, unit, range."""

    name: str
    type: str                      # double, integer, string, bool, *_array
    default: object
    description: str
    read_only: bool = False        # a change needs a restart (robot geometry)
    min_value: float | None = None
    max_value: float | None = None
    required_in_file: bool = False  # a scenario file must state it


PARAMETERS = (
    ParamSpec("planning_frame", "string", "world",
              "Frame of target poses and markers; a target_pose in another frame is rejected.", True),
    ParamSpec("robot.joint_names", "string_array", ["attitude", "shoulder", "elbow"],
              "Joint names, base first: the attitude (virtual joint at the spacecraft CoM), then the arm.",
              True, required_in_file=True),
    ParamSpec("robot.link_lengths_m", "double_array", [1.4, 2.0, 2.0],
              "Link lengths in metres (link 1: CoM to shoulder).", True, 1e-6, 100.0, True),
    ParamSpec("robot.lower_deg", "double_array", [-180.0, -180.0, -180.0],
              "Lower joint bounds, degrees.", True, -360.0, 360.0, True),
    ParamSpec("robot.upper_deg", "double_array", [180.0, 180.0, 180.0],
              "Upper joint bounds, degrees.", True, -360.0, 360.0, True),
    ParamSpec("robot.periodic", "bool_array", [True, False, False],
              "Per joint: wraps around (the attitude: -180 deg == +180 deg).", True, required_in_file=True),
    ParamSpec("robot.body_side_m", "double", 1.8,
              "Side of the square spacecraft body (link 1 points at a corner), metres.", True, 1e-3, 100.0, True),
    ParamSpec("robot.planned_joints", "string_array", ["attitude", "shoulder", "elbow"],
              "Joints the planner moves; the others stay at robot.locked_positions_deg.", True,
              required_in_file=True),
    ParamSpec("robot.locked_positions_deg", "double_array", [0.0, 0.0, 0.0],
              "Full-length joint vector, degrees; used for the joints not planned.", True),
    ParamSpec("target.center_m", "double_array", [-3.27, -2.60],
              "Target body centre (x, y) in the planning frame, metres (target_pose overrides it).",
              False, -1000.0, 1000.0),
    ParamSpec("target.yaw_deg", "double", 0.0, "Target yaw, degrees (handle on the local +y face).",
              False, -360.0, 360.0),
    ParamSpec("target.body_side_m", "double", 1.0, "Target body side, metres.", False, 1e-3, 100.0),
    ParamSpec("target.handle_side_m", "double", 0.1, "Grasp handle side, metres.", False, 1e-3, 10.0),
    ParamSpec("obstacles.polygons_m", "string", "[]",
              "Debris polygons in the planning frame as a list of [[x, y], ...] lists, metres "
              "(a string, like Nav2's footprint).", False),
    ParamSpec("safety_margin_m", "double", 0.02,
              "Minimum distance kept between the arm's links (link 2 on: 2-3 on the paper's chain) and any "
              "obstacle or the body, metres.",
              False, 0.0, 1.0),
    ParamSpec("grid.cells", "integer_array", [36, 36, 36],
              "C-space cells per planned joint (a bounded joint has one grid node more than its cells, a "
              "periodic one as many: [36, 36, 36] with the attitude periodic is the 36x37x37 grid).",
              False, 2, 4096, True),
    ParamSpec("scenario.start_deg", "double_array", [-90.0, 135.0, 90.0],
              "Start posture of the planned joints, degrees (CLI and mock arm: where it starts).", True),
    ParamSpec("scenario.goal_deg", "double_array", [160.7, 32.8, 76.5],
              "Goal posture of the planned joints, degrees (CLI; the node plans to the target).", False),
    # ---- planner (field, path)
    ParamSpec("planner.solver", "string", "log_harmonic",
              "Field solver: log_harmonic (default; relative precision, no flat field) or "
              "gauss_seidel (the paper's, for comparison).", False),
    ParamSpec("planner.field_tolerance", "double", 1e-6,
              "Stop of the gauss_seidel solver: largest change of the potential per sweep (the "
              "paper's 1e-6). The log_harmonic route's precision is fixed (see spacerobot_planner.field).",
              False, 1e-14, 1e-1),
    ParamSpec("planner.field_budget_s", "double", 5.0,
              "Wall-time budget of one field solve, seconds. When it ends first the field is still a "
              "valid ascent field, less accurate where unsolved, and the result says converged: false. "
              "It stops the bands' iterations: the set-up before them and the fill after them run to "
              "their end (tens of ms at 72^3 with the least budget).",
              False, 1e-3, 600.0),
    ParamSpec("planner.max_grid_nodes", "integer", 4_000_000,
              "Refuse grids with more nodes than this (memory budget), before allocating.",
              False, 4, 200_000_000),
    ParamSpec("planner.max_threads", "integer", 0,
              "Most threads a plan's parallel kernels use (the C-space rows; on large grids the field's "
              "loops and the node graph's table; 1 also keeps a large band's set-up in one thread); 0: "
              "numba's (one per core, or NUMBA_NUM_THREADS). No more than the process's CPU limit (a "
              "container's cgroup quota, rounded up), and on grids of 100 000 nodes and more, no more "
              "than the cores other work leaves (counted before the C-space and each field solve; before a "
              "first repair's swept edges, and a C-space built node by node, on every grid). A "
              "plan is the same bit for bit on any number.",
              False, 0, 4096),
    ParamSpec("planner.threads_follow_load", "bool", True,
              "Run the parallel loops on no more threads than the process's CPU limit (a container's cgroup "
              "quota, rounded up: a larger team spends the quota's period in a burst, then the process waits) "
              "and, on grids of 100 000 nodes and more (a first repair's swept edges: every grid), than the "
              "cores other work leaves (a team larger than "
              "the free cores waits at every loop's join: a 72³ plan took up to 20× longer beside two busy "
              "processes on 2 cores). false: always planner.max_threads (benchmarks and tests of the threaded "
              "loops)."),
    ParamSpec("planner.max_start_penetration_m", "double", 0.05,
              "A start posture whose links reach at most this deep into an obstacle (e.g. holding the "
              "grasp after the target moved) is first walked out along increasing clearance (reported, "
              "not certified); deeper: start_in_collision. 0: always start_in_collision, metres.",
              False, 0.0, 1.0),
    ParamSpec("grasp.max_approach_error_deg", "double", 5.0,
              "Largest angle between the last link and the handle's inward normal accepted for a goal from "
              "the target: the perpendicular grasp first, else the least tilt within it (whole degrees) "
              "where that one is out of reach or not clear; with the attitude locked (position-only IK) the "
              "angle the posture gives; above it goal_unreachable, degrees.",
              False, 0.0, 180.0),
    # ---- trajectory (time parameterisation), per joint in robot.joint_names
    ParamSpec("trajectory.max_velocity_deg_s", "double_array", [5.0, 15.0, 15.0],
              "Per-joint velocity limits, deg/s.", False, 1e-3, 1e4),
    ParamSpec("trajectory.max_acceleration_deg_s2", "double_array", [5.0, 20.0, 20.0],
              "Per-joint acceleration limits, deg/s^2.", False, 1e-3, 1e5),
    ParamSpec("trajectory.max_velocity_scaling_factor", "double", 1.0,
              "Factor in (0, 1] on every joint velocity limit (MoveIt's max_velocity_scaling_factor).",
              False, 1e-6, 1.0),
    ParamSpec("trajectory.max_acceleration_scaling_factor", "double", 1.0,
              "Factor in (0, 1] on every joint acceleration limit (MoveIt's "
              "max_acceleration_scaling_factor).", False, 1e-6, 1.0),
    ParamSpec("trajectory.start_lead_s", "double", 0.35,
              "Every published trajectory starts at least this long after it is published (its stamp: "
              "now + this from rest, the join's time when joined), checked just before publishing, so it "
              "reaches the controller first: joint_trajectory_controller refuses one that ends before it "
              "arrives, and one arriving after its start begins with a velocity step. 0.35 s: the worst "
              "stamp-to-arrival time measured on a loaded machine (load 5, in-process graphs) was 0.26 s "
              "(python -m spacerobot_planner.bench latency --load N reports the margin), seconds.",
              False, 0.0, 10.0),
    ParamSpec("controller.switch", "string", "auto",
              "When the arm's trajectory controller takes a newer trajectory over: stamp (at its header "
              "stamp, following the one it has until then: ros2_controllers' joint_trajectory_controller "
              "from 6.8 on with allow_trajectory_replacement true, and the mock arm by default) or arrival "
              "(when it arrives, going from its state then to the first point: joint_trajectory_controller "
              "before 6.8, as in Kilted and Jazzy, or with allow_trajectory_replacement false). With arrival "
              "a trajectory joined to the moving arm is stamped at the executing one's last published point "
              "before it is sent and holds its points up to the join. auto: the planner asks the nodes that "
              "subscribe joint_trajectory for their parameters (allow_trajectory_replacement; "
              "joint_trajectory_controller's joints and interpolation_method without it: before 6.8) and "
              "sends for the kind they are, stamp until one answers or while they disagree; the mock arm "
              "then models its own allow_trajectory_replacement. Read by both nodes.", True),
    # ---- the spacecraft's reaction (spacecraft.py, reaction.py)
    ParamSpec("dynamics.body_mass_kg", "double", 2000.0,
              "Spacecraft body mass (with the massless link 1), kg.", False, 1e-6, 1e12),
    ParamSpec("dynamics.body_inertia_kgm2", "double", 1080.0,
              "Spacecraft body inertia about its centre (the chain's origin), kg m^2.", False, 0.0, 1e15),
    ParamSpec("dynamics.link_masses_kg", "double_array", [0.0, 30.0, 30.0],
              "Per link (link 1 first; its mass belongs to the body: 0), kg; centre at mid-link. "
              "Default for other chains: 0 for link 1, 30 for the others.", False, 0.0, 1e9),
    ParamSpec("dynamics.link_inertias_kgm2", "double_array", [0.0, 10.0, 10.0],
              "Per link, about its centre, kg m^2. Default for other chains: 0 for link 1, 10 for "
              "the others.", False, 0.0, 1e12),
    ParamSpec("acs.mode", "string", "held",
              "Attitude control during the arm motion: held (reaction wheels hold or command the "
              "attitude) or free_floating (off: the spacecraft turns and moves; the plan is refused "
              "when the drifted arm collides or misses the grasp).", False),
    ParamSpec("acs.max_wheel_momentum_Nms", "double", 0.0,
              "Largest reaction-wheel momentum the trajectory may need, N m s (0: no limit).",
              False, 0.0, 1e9),
    ParamSpec("acs.max_wheel_torque_Nm", "double", 0.0,
              "Largest reaction-wheel torque the trajectory may need, N m (0: no limit).",
              False, 0.0, 1e9),
    ParamSpec("acs.compensate_drift", "bool", False,
              "Free floating, the CLI's strategy: plan the arm for the predicted drift (goal corrected and "
              "replanned until the drifted tip reaches the grasp; 2-DOF, attitude not planned). The node has "
              "no drift compensation: set, it does not run the free-floating capture search either, and its "
              "plans are judged by the drift they would cause.", False),
    ParamSpec("grasp.position_tolerance_m", "double", 0.02,
              "Free floating: largest acceptable distance of the drifted tip from the grasp point, m.",
              False, 0.0, 10.0),
    # ---- node
    ParamSpec("replan.target_tolerance_m", "double", 0.005,
              "A target_pose closer than this (and within target_tolerance_deg) to the current "
              "target does not trigger a replan, metres.", False, 0.0, 10.0),
    ParamSpec("replan.target_tolerance_deg", "double", 0.5,
              "Yaw tolerance for the same-target test, degrees.", False, 0.0, 180.0),
    ParamSpec("potential_grid.use_current_attitude", "bool", True,
              "With more than 2 planned joints, slice the published grids at the plan's start "
              "(current) value of the joints other than the last two; else at "
              "potential_grid.slice_attitude_deg.", False),
    ParamSpec("potential_grid.slice_attitude_deg", "double", 0.0,
              "Attitude of the published slice when use_current_attitude is false, degrees.",
              False, -360.0, 360.0),
    ParamSpec("diagnostics.period_s", "double", 1.0,
              "Period of the /diagnostics heartbeat (changes are published at once), seconds.",
              False, 0.01, 3600.0),
    ParamSpec("planner.separate_process", "bool", True,
              "Run the planning core in a child process driven by the worker thread: the plans' "
              "Python steps do not share the executor's interpreter lock, a stage that does not answer "
              "a cancel is killed without the node, and the process keeps its heap for large grids. "
              "false: in the worker thread (its kernels run without the interpreter lock). With "
              "planner.replans_in_node the replans run in the worker thread either way.", True),
    ParamSpec("planner.replans_in_node", "bool", True,
              "With planner.separate_process: a plan that the C-space and field the planning process sent "
              "last answer (a new start to the same target: the replans) runs in the worker thread, "
              "from those alone, without the round trip to the process (about 0.6 ms); anything else (a "
              "new target or grid, a repair, a finer grid) in the process. false: every plan in the process.",
              True),
    ParamSpec("mock_arm.rate_hz", "double", 50.0,
              "mock_arm_node: joint_states publishing rate, Hz (its parameter 'rate_hz').", False, 0.1, 1000.0),
    ParamSpec("mock_arm.allow_trajectory_replacement", "bool", True,
              "mock_arm_node (its parameter 'allow_trajectory_replacement', as joint_trajectory_controller's "
              "from 6.8 on): true, a newer trajectory takes over at its stamp; false, at its arrival. With "
              "controller.switch stamp or arrival it is that (its default then: true with stamp, false with arrival; "
              "a value that contradicts it is refused at start); with auto it is the model, and the planner "
              "reads it.", True),
    # ---- planner node (ROS side)
    ParamSpec("autostart", "bool", True,
              "Configure and activate the lifecycle node at start (off: wait for `ros2 lifecycle set`).",
              True),
    ParamSpec("grid_frame", "string", "cspace",
              "Frame of potential_grid / cspace_grid: joint space (x, y in radians), not the "
              "planning frame, so RViz does not lay them over the workspace.", False),
    ParamSpec("replan.min_publish_period_s", "double", 1.0,
              "Under a stream of targets (topics), a plan in progress is let finish and published "
              "instead of being superseded once no trajectory was published for this long, so a "
              "drifting target is followed; 0 = the latest request always wins, seconds.", False, 0.0, 3600.0),
    ParamSpec("replan.horizon_s", "double", 1.0,
              "A replan while the node's last trajectory is executing starts this far ahead along it "
              "and the new trajectory is joined to it there (same position and velocity at the switch; "
              "doubled for a retry when a plan takes longer); 0 = plan from the measured state at "
              "rest, seconds.", False, 0.0, 60.0),
    ParamSpec("replan.follow_tolerance_deg", "double", 2.0,
              "The join needs the arm to follow the executing trajectory: the measured joint_states "
              "within this of it (per joint), else the replan starts from the measured state at "
              "rest, degrees.", False, 0.0, 360.0),
    ParamSpec("attitude_topic", "string", "",
              "Topic of the spacecraft body's pose (geometry_msgs/PoseStamped in the planning frame; "
              "its yaw is the attitude joint, its position is ignored), for joint_states that lack the "
              "attitude joint (a real servicer's); empty: joint_states only.", True),
    ParamSpec("joint_states_timeout_s", "double", 10.0,
              "A plan_capture goal without its own start sent before any joint_states waits this long "
              "for them (feedback stage waiting_for_joint_states), then aborts with INVALID_INPUT; "
              "topic requests wait without limit, seconds.", False, 0.1, 3600.0),
    ParamSpec("planner.test_stall_s", "double", 0.0,
              "Testing aid: the planning process stalls this long before every plan (a long, "
              "uninterruptible stage without a large grid); 0 in normal use, seconds.", False, 0.0, 600.0),
)

_SPECS = {p.name: p for p in PARAMETERS}

#: parameters rclpy declares on every node (never the package's, never unknown)
ROS_PARAMETERS = ("use_sim_time", "start_type_description_service")
#: names a node of the package declares that differ from the schema's (mock_arm_node)
DECLARED_ALIASES = {"rate_hz": "mock_arm.rate_hz",
                    "allow_trajectory_replacement": "mock_arm.allow_trajectory_replacement"}


def unknown_parameters(names) -> list:
    """
    Return a line for each name that no node of the package knows (a typo in a file, a ``-p``).

    The line names it and the closest known name (difflib), e.g. ``unknown parameter
    'safety_margn_m' (ignored); did you mean 'safety_margin_m'?``.  Known: the schema
    (``PARAMETERS``: every node's), ``DECLARED_ALIASES``, rclpy's own (``ROS_PARAMETERS``,
    ``qos_overrides.*``).
    """
    known = sorted({*_SPECS, *DECLARED_ALIASES, *ROS_PARAMETERS})
    out = []
    for name in names:
        if name in known or name.startswith("qos_overrides."):
            continue
        close = difflib.get_close_matches(name, known, n=1, cutoff=0.6)
        out.append(f"unknown parameter '{name}' (ignored)" + (f"; did you mean '{close[0]}'?" if close else ""))
    return out


# --------------------------------------------------------------- type checking
def _check_scalar(name, kind, value):
    if kind == "double":
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ValueError(f"{name}: expected a number, got {value!r} ({type(value).__name__})")
        if not math.isfinite(float(value)):
            raise ValueError(f"{name}: expected a finite number, got {value!r}")
        return float(value)
    if kind == "integer":
        if isinstance(value, bool) or not isinstance(value, int):
            raise ValueError(f"{name}: expected an integer, got {value!r} ({type(value).__name__})")
        return int(value)
    if kind == "string":
        if not isinstance(value, str):
            raise ValueError(f"{name}: expected a string, got {value!r} ({type(value).__name__})")
        return value
    if kind == "bool":
        if not isinstance(value, bool):
            raise ValueError(f"{name}: expected true or false, got {value!r}")
        return value
    raise AssertionError(kind)


#: parameters that name a frame: a tf2 frame id, not empty, no leading "/" (tf2 refuses it)
FRAME_PARAMETERS = ("planning_frame", "grid_frame")


def _mixed_list_hint(value, kind: str) -> str:
    """
    Say why a list came as a string, where it reads as a list of numbers ("" otherwise).

    ``ros2 param set NODE NAME "[0.5, 2, 2]"`` sends a list that mixes integers and decimals as a
    string (no ROS parameter type holds both).  ``kind``: the parameter's element type ("double",
    "integer", ...): what to write instead.
    """
    if not isinstance(value, str):
        return ""
    try:
        parsed = yaml.safe_load(value)
    except yaml.YAMLError:
        return ""
    if not (isinstance(parsed, list) and parsed
            and all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in parsed)):
        return ""
    why = " (a string: a list that mixes integers and decimals arrives as one, no ROS parameter type holds both; "
    if kind == "integer":
        return why + "this one takes whole numbers only)"
    decimals = "[" + ", ".join(repr(float(v)) for v in parsed) + "]"
    return why + f"write every number with a decimal point, {decimals})"


def check_value(name: str, value):
    """Type- and range-check one parameter value; return it normalised (lists as lists)."""
    spec = _SPECS.get(name)
    if spec is None:
        raise ValueError(f"unknown parameter '{name}'")
    if name in FRAME_PARAMETERS:
        frame = _check_scalar(name, spec.type, value)
        if not frame.strip() or frame.startswith("/") or frame != frame.strip():
            raise ValueError(f"{name}: expected a frame id (not empty, no spaces around it, no leading '/', "
                             f"as tf2 asks), got {value!r}")
        return frame
    if spec.type.endswith("_array"):
        if isinstance(value, (tuple, np.ndarray, array.array)):    # array.array: from a ROS message
            value = list(value)
        if not isinstance(value, list) or not value:
            raise ValueError(f"{name}: expected a non-empty list, got {value!r}"
                             + _mixed_list_hint(value, spec.type[:-6]))
        kind = spec.type[:-6]
        out = [_check_scalar(f"{name}[{i}]", kind, v) for i, v in enumerate(value)]
    else:
        out = _check_scalar(name, spec.type, value)
    values = out if isinstance(out, list) else [out]
    for i, v in enumerate(values):
        if spec.min_value is not None and v < spec.min_value:
            raise ValueError(f"{name}: {v} is below the minimum {spec.min_value}")
        if spec.max_value is not None and v > spec.max_value:
            raise ValueError(f"{name}: {v} is above the maximum {spec.max_value}")
    return out


def flatten_params(d, prefix=""):
    """Return a nested ``ros__parameters`` mapping as a flat dotted dict."""
    out = {}
    for k, v in d.items():
        key = f"{prefix}{k}"
        if isinstance(v, dict):
            out.update(flatten_params(v, key + "."))
        else:
            out[key] = v
    return out


def _section_params(doc, key, path):
    """Return the flat ``ros__parameters`` of section ``key``."""
    section = doc[key]
    if not isinstance(section, dict) or not isinstance(section.get("ros__parameters"), dict):
        raise ValueError(f"params file: the '{key}' section in {path} has no 'ros__parameters' mapping")
    return flatten_params(section["ros__parameters"])


def section_regex(key: str) -> re.Pattern:
    """
    Return the regex of a section's node name, with rcl's wildcards.

    ``/**`` stands for any number of namespace tokens (none included), ``/*`` for one, as
    rcl matches a node's fully qualified name; a name without a leading slash gets one.
    """
    key = "/" + key.lstrip("/")
    out = []
    for token in key.split("/")[1:]:
        out.append("(/[^/]+)*" if token == "**" else "/[^/]+" if token == "*" else "/" + re.escape(token))
    return re.compile("".join(out))


def matching_sections(doc: dict, node: str, namespace: str = "/") -> list:
    """Return the keys of the sections of a parameter file that apply to ``namespace/node``, in file order."""
    fqn = namespace.rstrip("/") + "/" + node.strip("/")
    return [k for k in doc if isinstance(k, str) and section_regex(k).fullmatch(fqn)]


def load_params_file(path, node: str = NODE_NAME, namespace: str = "/") -> dict:
    """
    Read a ROS 2 parameter file; return one node's parameters as a flat dotted dict.

    As ``--params-file`` does for the node ``namespace/node``: every section whose name
    matches it (``/**``, ``/**/node``, ``node``, ``/node``, ``/ns/node``; rcl's wildcards),
    in file order, a later one on top.  A file with one section of another name is taken
    whole (older single-section files).  Unknown parameters are kept (the nodes ignore
    them; :func:`unknown_parameters` names them); known ones are type-checked.
    """
    try:
        with open(path, encoding="utf-8") as f:
            doc = yaml.safe_load(f)
    except OSError as e:
        raise ValueError(f"params file: cannot read {path}: {e.strerror}") from None
    except yaml.YAMLError as e:
        raise ValueError(f"params file: {path} is not valid YAML: {e}") from None
    if not isinstance(doc, dict) or not doc:
        raise ValueError(f"params file: {path} must map a node name to 'ros__parameters'")
    keys = matching_sections(doc, node, namespace)
    if not keys:
        if len(doc) != 1:
            raise ValueError(f"params file: no '/**/{node}', '{node}' or '/**' section in {path}")
        keys = [next(iter(doc))]
    flat = {}
    for key in keys:
        flat.update(_section_params(doc, key, path))
    if node == NODE_NAME:
        missing = [s.name for s in PARAMETERS if s.required_in_file and s.name not in flat]
        if missing:
            raise ValueError(f"params file {path}: missing required key(s): {', '.join(missing)}")
    return {k: (check_value(k, v) if k in _SPECS else v) for k, v in flat.items()}


def parse_polygons(text: str, name: str = "obstacles.polygons_m") -> tuple:
    """Parse ``"[[[x, y], ...], ...]"`` into a tuple of (k×2) arrays (metres)."""
    try:
        data = yaml.safe_load(text) if isinstance(text, str) else text
    except yaml.YAMLError as e:
        raise ValueError(f"{name}: not a list of polygons: {e}") from None
    if data is None:
        return ()
    if not isinstance(data, list):
        raise ValueError(f"{name}: expected a list of polygons, got {type(data).__name__}")
    polys = []
    for i, p in enumerate(data):
        try:
            arr = np.asarray(p, dtype=float)
        except (TypeError, ValueError):
            raise ValueError(f"{name}[{i}]: vertices must be [x, y] number pairs") from None
        polys.append(arr)   # shape, count, NaN and area are checked by Scene
    return tuple(polys)


def spec_default(name: str):
    """Return the default of a parameter in ``PARAMETERS`` (a copy for lists)."""
    d = _SPECS[name].default
    return list(d) if isinstance(d, list) else d


def _get(params, name):
    if name in params:
        return check_value(name, params[name])
    return _SPECS[name].default


def scenario_from_params(params: dict) -> Scenario:
    """Build a Scenario from a flat dotted parameter dict (defaults fill the gaps)."""
    names = _get(params, "robot.joint_names")
    n = len(names)

    def per_joint(key):
        v = _get(params, key)
        if len(v) != n:
            raise ValueError(f"{key}: expected {n} values (one per joint in robot.joint_names), got {len(v)}")
        return v

    lengths = per_joint("robot.link_lengths_m")
    lower = np.radians(per_joint("robot.lower_deg"))
    upper = np.radians(per_joint("robot.upper_deg"))
    periodic = per_joint("robot.periodic")
    locked = np.radians(per_joint("robot.locked_positions_deg"))
    planned_names = _get(params, "robot.planned_joints")
    unknown = [j for j in planned_names if j not in names]
    if unknown:
        raise ValueError(f"robot.planned_joints: {unknown} not in robot.joint_names {list(names)}")
    planned = tuple(names.index(j) for j in planned_names)
    robot = PlanarArm(tuple(names), tuple(lengths), tuple(lower), tuple(upper), tuple(periodic),
                      square_polygon(_get(params, "robot.body_side_m"), corner_first=True),
                      planned_joints=planned, locked_rad=locked, checked_links=tuple(range(1, n)))
    center = _get(params, "target.center_m")
    if len(center) != 2:
        raise ValueError(f"target.center_m: expected [x, y], got {len(center)} values")
    target = Target(center_m=tuple(center), yaw_rad=math.radians(_get(params, "target.yaw_deg")),
                    body_side_m=_get(params, "target.body_side_m"),
                    handle_side_m=_get(params, "target.handle_side_m"))
    scene = Scene(target=target, debris_m=parse_polygons(_get(params, "obstacles.polygons_m")),
                  safety_margin_m=_get(params, "safety_margin_m"))
    grid = grid_for_robot(robot, _get(params, "grid.cells"))

    def posture(key):
        if key not in params:
            return None
        v = check_value(key, params[key])
        return robot.validate_q(np.radians(v), key)

    def per_link(key, default_other):
        if key not in params:
            return [0.0] + [default_other] * (n - 1)
        return per_joint(key)

    masses = MassProperties(_get(params, "dynamics.body_mass_kg"), _get(params, "dynamics.body_inertia_kgm2"),
                            tuple(per_link("dynamics.link_masses_kg", 30.0)),
                            tuple(per_link("dynamics.link_inertias_kgm2", 10.0)))
    mode = _get(params, "acs.mode")
    if mode not in ACS_MODES:
        raise ValueError(f"acs.mode: expected one of {', '.join(ACS_MODES)}, got {mode!r}")
    acs = AcsSettings(mode, _get(params, "acs.max_wheel_momentum_Nms"), _get(params, "acs.max_wheel_torque_Nm"),
                      _get(params, "grasp.position_tolerance_m"), _get(params, "acs.compensate_drift"))
    return Scenario(robot=robot, scene=scene, grid=grid, start_rad=posture("scenario.start_deg"),
                    goal_rad=posture("scenario.goal_deg"),
                    planning_frame=_get(params, "planning_frame"), params=dict(params),
                    masses=masses, acs=acs, joint_limits=joint_limits_from_params(params, robot),
                    planner_settings=settings_from_params(params))


#: parameters (``PARAMETERS``) → ``settings.PlannerSettings`` fields
_PLANNER_SETTINGS = {"planner.solver": "solver", "planner.field_tolerance": "field_tolerance",
                     "planner.field_budget_s": "field_budget_s", "planner.max_grid_nodes": "max_grid_nodes",
                     "planner.max_threads": "max_threads", "planner.threads_follow_load": "threads_follow_load",
                     "planner.max_start_penetration_m": "max_start_penetration_m",
                     "grasp.max_approach_error_deg": "max_approach_error_deg"}


def settings_from_params(params: dict, **overrides) -> PlannerSettings:
    """Return the PlannerSettings of a flat dotted parameter dict (the schema's defaults for what is absent)."""
    kw = {f: _get(params, k) for k, f in _PLANNER_SETTINGS.items()}
    kw.update(overrides)
    return PlannerSettings(**kw)


def session_settings_from_params(params: dict) -> SessionSettings:
    """Return the SessionSettings of a flat dotted parameter dict (``replan.*``, ``trajectory.start_lead_s``)."""
    return SessionSettings(horizon_s=_get(params, "replan.horizon_s"),
                           follow_tolerance_rad=math.radians(_get(params, "replan.follow_tolerance_deg")),
                           min_publish_period_s=_get(params, "replan.min_publish_period_s"),
                           start_lead_s=_get(params, "trajectory.start_lead_s"),
                           target_tolerance_m=_get(params, "replan.target_tolerance_m"),
                           target_tolerance_deg=_get(params, "replan.target_tolerance_deg"),
                           test_stall_s=_get(params, "planner.test_stall_s"),
                           controller_switch=_get(params, "controller.switch"))


def joint_limits_from_params(params: dict, robot: PlanarArm) -> JointLimits | None:
    """
    Return the JointLimits of a flat dotted parameter dict (``trajectory.*``), rad.

    None unless it states both ``trajectory.max_velocity_deg_s`` and
    ``trajectory.max_acceleration_deg_s2`` (a scenario without limits plans paths only);
    the scaling factors default to the schema's.  ValueError (naming the parameter) for a
    bad value or not one value per joint of ``robot``.
    """
    keys = ("trajectory.max_velocity_deg_s", "trajectory.max_acceleration_deg_s2")
    given = {k: _get(params, k) for k in keys if k in params}
    for key, v in given.items():
        if len(v) != robot.n_joints:
            raise ValueError(f"{key}: expected {robot.n_joints} values (one per joint in robot.joint_names), "
                             f"got {len(v)}")
    if len(given) < len(keys):
        return None
    return JointLimits(tuple(np.radians(np.asarray(given[keys[0]], dtype=float))),
                       tuple(np.radians(np.asarray(given[keys[1]], dtype=float))),
                       _get(params, "trajectory.max_velocity_scaling_factor"),
                       _get(params, "trajectory.max_acceleration_scaling_factor"))


def load_scenario(path, warn=None) -> Scenario:
    """
    Load a scenario from a ROS 2 parameter file (see ``config/paper_3dof.yaml``).

    ``warn(line)``, when given, is told each unknown parameter of the file (see
    :func:`unknown_parameters`).
    """
    params = load_params_file(path)
    if warn is not None:
        for line in unknown_parameters(params):
            warn(f"{path}: {line}")
    try:
        return scenario_from_params(params)
    except ValueError as e:
        raise ValueError(f"{path}: {e}") from None
