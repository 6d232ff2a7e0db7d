"""
Parameters per node.

Each declares what it reads, with descriptors; both nodes take their parameters from one
--params-file (/** + their own section).

Oracles: the parameter services a `ros2 param` user calls, and the YAML file read
here directly.
"""

from __future__ import annotations

import os
import yaml
from rcl_interfaces.msg import ParameterType
from rcl_interfaces.srv import DescribeParameters, ListParameters, SetParameters
from rclpy.parameter import Parameter

from spacerobot_planner.field import SOLVERS

from node_helpers import scene_params
from conftest import CONFIG_DIR


def _call(g, node, srv_type, name, request):
    cli = g.drv.create_client(srv_type, f"/{node}/{name}")
    assert cli.wait_for_service(30.0), name
    fut = cli.call_async(request)
    g.wait(fut.done, 30, f"{name} response")
    g.drv.destroy_client(cli)
    return fut.result()


def _names(g, node):
    return set(_call(g, node, ListParameters, "list_parameters", ListParameters.Request()).result.names)


def _describe(g, node, names):
    res = _call(g, node, DescribeParameters, "describe_parameters", DescribeParameters.Request(names=names))
    return {d.name: d for d in res.descriptors}


def test_each_node_declares_only_what_it_reads(graph):
    g = graph(scene_params("3dof"))
    planner = _names(g, "spacerobot_planner") - {"use_sim_time", "start_type_description_service"}
    arm = _names(g, "mock_arm") - {"use_sim_time", "start_type_description_service"}
    assert not any(n.startswith(("scenario.", "mock_arm.")) for n in planner), planner
    assert {"robot.joint_names", "grid.cells", "planner.solver", "autostart", "grid_frame"} <= planner
    assert arm == {"robot.joint_names", "robot.link_lengths_m", "robot.lower_deg", "robot.upper_deg",
                   "robot.periodic", "robot.body_side_m", "robot.planned_joints", "robot.locked_positions_deg",
                   "scenario.start_deg", "controller.switch", "rate_hz", "allow_trajectory_replacement"}, arm
    assert "controller.switch" in planner          # both: when the arm's controller switches to a newer trajectory


def test_descriptors_carry_ranges_and_allowed_values(graph):
    g = graph(scene_params("3dof"), with_arm=False)
    d = _describe(g, "spacerobot_planner", ["safety_margin_m", "planner.solver", "grid.cells", "robot.link_lengths_m",
                                            "planner.max_grid_nodes", "acs.mode"])
    fr = d["safety_margin_m"].floating_point_range[0]
    assert (fr.from_value, fr.to_value) == (0.0, 1.0) and d["safety_margin_m"].type == ParameterType.PARAMETER_DOUBLE
    ir = d["planner.max_grid_nodes"].integer_range[0]
    assert (ir.from_value, ir.to_value) == (4, 200_000_000)
    allowed = d["planner.solver"].additional_constraints
    assert allowed.startswith("one of:") and all(s in allowed for s in SOLVERS)
    assert d["acs.mode"].additional_constraints == "one of: held, free_floating"     # as docs/reaction.md names them
    assert "Range [2, 4096]" in d["grid.cells"].additional_constraints
    assert d["robot.link_lengths_m"].read_only


def test_rejected_values_name_the_parameter(graph):
    g = graph(scene_params("3dof"), with_arm=False)
    res = g.planner.set_parameters([Parameter("planner.solver", value="bogus")])[0]
    assert not res.successful and "planner.solver: 'bogus' is not one of" in res.reason, res.reason
    assert all(s in res.reason for s in SOLVERS)
    # a wrong type through the service (`ros2 param set`): the node's reason, not rclpy's enum numbers
    req = SetParameters.Request(parameters=[Parameter("safety_margin_m", value="wide").to_parameter_msg()])
    r = _call(g, "spacerobot_planner", SetParameters, "set_parameters", req).results[0]
    assert not r.successful and r.reason == "safety_margin_m: expected a number, got 'wide' (str)", r.reason
    # the input status is ERROR already (planner.solver's refusal): it is this refusal's that is waited for
    g.wait(lambda: g.status("input") is not None
           and "safety_margin_m: expected a number, got 'wide'" in g.status("input").message, 30,
           lambda: f"the input status naming safety_margin_m: {g.status('input')}")
    assert g.level("input") == b"\x02"
    assert g.planner.get_parameter("safety_margin_m").value == 0.02
    # a frame RViz and tf2 could not use (an empty one was taken: a ROS user's audit)
    for frame in ("", " ", "/cspace"):
        req = SetParameters.Request(parameters=[Parameter("grid_frame", value=frame).to_parameter_msg()])
        r = _call(g, "spacerobot_planner", SetParameters, "set_parameters", req).results[0]
        assert not r.successful and r.reason.startswith("grid_frame: expected a frame id"), (frame, r.reason)
    assert g.planner.get_parameter("grid_frame").value == "cspace"


def test_what_ros2_param_set_sends_is_taken_or_refused_by_name(graph):
    """
    `ros2 param set` sends `1` as an integer and `[90, 180, 180]` as an integer array.

    Oracle: the parameter services a `ros2 param` user calls (set, then get through the node).
    A whole number for a double is that double; an undeclared name is refused naming it (rclpy
    says "Invalid access to undeclared parameter(s): []"), and the closest declared name.
    """
    g = graph(scene_params("3dof"), with_arm=False)

    def set_one(name, value):
        req = SetParameters.Request(parameters=[Parameter(name, value=value).to_parameter_msg()])
        return _call(g, "spacerobot_planner", SetParameters, "set_parameters", req).results[0]

    r = set_one("planner.field_budget_s", 7)
    assert r.successful, r.reason
    got = g.planner.get_parameter("planner.field_budget_s")
    assert got.type_ == Parameter.Type.DOUBLE and got.value == 7.0
    r = set_one("trajectory.max_velocity_deg_s", [90, 180, 180])
    assert r.successful, r.reason
    got = g.planner.get_parameter("trajectory.max_velocity_deg_s")
    assert got.type_ == Parameter.Type.DOUBLE_ARRAY and list(got.value) == [90.0, 180.0, 180.0]
    assert g.planner.session.scenario.joint_limits is not None
    # the range still holds for a whole number (the node's reason, not rclpy's)
    r = set_one("safety_margin_m", 3)
    assert not r.successful and r.reason == "safety_margin_m: 3.0 is above the maximum 1.0", r.reason
    # an integer parameter given a fraction is still refused by name
    r = set_one("planner.max_grid_nodes", 1.5)
    assert not r.successful and r.reason.startswith("planner.max_grid_nodes: expected an integer"), r.reason
    r = set_one("safety_margn_m", 0.05)
    assert not r.successful and r.reason == ("'safety_margn_m': not a parameter of this node; did you mean "
                                             "'safety_margin_m'? (`ros2 param list` shows them)"), r.reason
    g.wait(lambda: g.status("input") is not None and "safety_margn_m" in g.status("input").message, 30,
           "the input status names it")
    assert g.planner.get_parameter("safety_margin_m").value == 0.02


def test_the_mock_arms_rate_takes_effect_and_its_start_is_read_only(graph):
    """
    ``ros2 param set /mock_arm rate_hz 25`` (an integer) sets the joint_states timer; ``scenario.start_deg`` is refused.

    Oracle: the parameter service a ``ros2 param`` user calls and the node's timers (rclpy's
    view). Both had been taken and never applied (a ROS user's audit), and a whole number for
    the rate was refused with rclpy's type numbers.
    """
    g = graph(scene_params("3dof"))

    def set_one(name, value):
        req = SetParameters.Request(parameters=[Parameter(name, value=value).to_parameter_msg()])
        return _call(g, "mock_arm", SetParameters, "set_parameters", req).results[0]

    assert [t.timer_period_ns for t in g.arm.timers] == [20_000_000]          # the file's 50 Hz
    r = set_one("rate_hz", 25)
    assert r.successful, r.reason
    assert g.arm.get_parameter("rate_hz").value == 25.0
    assert [t.timer_period_ns for t in g.arm.timers] == [40_000_000]
    r = set_one("scenario.start_deg", [0.0, 90.0, 90.0])
    assert not r.successful and "read-only" in r.reason, r.reason


def test_a_target_size_that_would_overlap_the_current_target_is_refused(graph):
    """
    A new ``target.body_side_m`` resizes the current target (a target_pose's) where it is: refused where that overlaps.

    The parameters' own target at (-3.27, -2.60) m stays clear of the spacecraft with a 2 m body;
    a target_pose at (-2.0, -1.2) m does not (a review of the resize's mend found nothing refused it).
    Oracle: the parameter service's answer and the session's target, as a ``ros2 param`` user sees them.
    """
    from spacerobot_planner.ros.conversions import joint_state_msg
    g = graph(scene_params("3dof"), with_arm=False)
    robot = g.scenario.robot
    g.send_joint_state(joint_state_msg(robot.joint_names, robot.full(g.scenario.start_rad)))
    g.send_target(-2.0, -1.2)
    g.wait(lambda: g.planner.session.target.center_m == (-2.0, -1.2), 15, "the topic's target current")

    def set_one(name, value):
        req = SetParameters.Request(parameters=[Parameter(name, value=value).to_parameter_msg()])
        return _call(g, "spacerobot_planner", SetParameters, "set_parameters", req).results[0]

    r = set_one("target.body_side_m", 2.0)
    assert not r.successful and r.reason.startswith("target.body_side_m: the current target at (-2.000, -1.200) m"), \
        r.reason
    assert "overlap" in r.reason and g.planner.session.target.body_side_m == 1.0
    r = set_one("target.body_side_m", 1.1)
    assert r.successful, r.reason
    assert g.planner.session.target.center_m == (-2.0, -1.2) and g.planner.session.target.body_side_m == 1.1


def test_limits_too_low_for_a_trajectory_message_are_refused_by_name(graph):
    """
    Velocity limits near 0 (a slip of `ros2 param set`): the plan answers invalid_input, nothing is published.

    0.001°/s scaled by 1e-6 on the paper's 3-DOF path would take about 1e11 s (its attitude alone
    turns by more than 200°: at least 200 / 1e-9 s), more than a trajectory message's int32 seconds
    hold; published, its times wrapped around to negative values.  Then the limits are raised and the
    node plans and publishes again, times that start at 0 and increase.
    """
    from node_helpers import diag_values
    from spacerobot_planner.ros.conversions import joint_state_msg
    g = graph(scene_params("3dof", **{"trajectory.max_velocity_deg_s": [0.001] * 3,
                                      "trajectory.max_velocity_scaling_factor": 1e-6}), with_arm=False)
    robot = g.scenario.robot
    g.send_joint_state(joint_state_msg(robot.joint_names, robot.full(g.scenario.start_rad)))
    g.send_target()

    def code():
        st = g.status("planner")
        return None if st is None else diag_values(st).get("code")
    g.wait(lambda: code() == "invalid_input", 60, "the planner status invalid_input")
    reason = diag_values(g.status("planner"))["reason"]
    assert "longer than a trajectory message can hold" in reason and "velocity limit of joint" in reason, reason
    assert g.n_trajs() == 0
    assert g.planner.set_parameters([Parameter("trajectory.max_velocity_scaling_factor", value=1.0)])[0].successful
    g.wait(lambda: g.n_trajs() >= 1, 60, "a trajectory once the limits are raised")
    with g.lock:
        msg = g.trajs[-1][1]
    t = [p.time_from_start.sec + 1e-9 * p.time_from_start.nanosec for p in msg.points]
    assert t[0] >= 0.0 and all(b > a for a, b in zip(t, t[1:])), t[:5]


def test_a_change_is_validated_once_and_applied_once(graph, monkeypatch):
    """
    Nav2's parameter handler: one scenario built per change, one application (through the service too).

    The oracle: a counting wrapper around the scenario builder the handler uses, and one around the
    session's configure.
    """
    import spacerobot_planner.ros.parameter_handler as handler
    g = graph(scene_params("3dof"), with_arm=False)
    built, applied = [], []
    real_build, real_configure = handler.scenario_from_params, g.planner.session.configure
    monkeypatch.setattr(handler, "scenario_from_params", lambda params: built.append(1) or real_build(params))
    monkeypatch.setattr(g.planner.session, "configure", lambda *a, **k: applied.append(a) or real_configure(*a, **k))
    assert g.planner.set_parameters([Parameter("replan.horizon_s", value=0.5)])[0].successful
    assert (len(built), len(applied)) == (1, 1) and applied[0][1].horizon_s == 0.5
    req = SetParameters.Request(parameters=[Parameter("replan.horizon_s", value=0.75).to_parameter_msg()])
    assert _call(g, "spacerobot_planner", SetParameters, "set_parameters", req).results[0].successful
    assert (len(built), len(applied)) == (2, 2) and g.planner.session.settings.horizon_s == 0.75
    # a refused change: validated once, applied never
    assert not g.planner.set_parameters([Parameter("safety_margin_m", value=-1.0)])[0].successful
    assert (len(built), len(applied)) == (2, 2)


def test_both_nodes_from_one_params_file(tmp_path):
    """
    `--params-file` with /** + a section per node.

    Each node gets /** and its own section, nothing of the other's (as rcl resolves it).
    """
    import rclpy
    from rclpy.context import Context

    from spacerobot_planner.ros.mock_arm_node import MockArmNode
    with open(os.path.join(CONFIG_DIR, "paper_2dof.yaml")) as f:
        doc = yaml.safe_load(f)
    doc["/**/mock_arm"]["ros__parameters"]["rate_hz"] = 20.0
    doc["/**/spacerobot_planner"]["ros__parameters"]["autostart"] = False
    path = tmp_path / "two.yaml"
    path.write_text(yaml.safe_dump(doc))
    ctx = Context()
    rclpy.init(context=ctx, args=["--ros-args", "--params-file", str(path)])
    try:
        from spacerobot_planner.ros.planner_node import PlannerNode
        arm = MockArmNode(context=ctx)
        planner = PlannerNode(context=ctx)
        shared = doc["/**"]["ros__parameters"]
        assert arm.get_parameter("rate_hz").value == 20.0
        assert list(arm.get_parameter("scenario.start_deg").value) == shared["scenario"]["start_deg"]
        assert list(arm.get_parameter("robot.planned_joints").value) == shared["robot"]["planned_joints"]
        own = doc["/**/spacerobot_planner"]["ros__parameters"]
        assert list(planner.get_parameter("grid.cells").value) == own["grid"]["cells"]
        assert list(planner.get_parameter("robot.planned_joints").value) == ["shoulder", "elbow"]
        assert planner.state == "unconfigured"                  # autostart: false from its section
        planner.destroy_node()
        arm.destroy_node()
    finally:
        rclpy.shutdown(context=ctx)
