"""
What the planner node accepts at start and as input (issue 17).

Start-up refusals (one line, no traceback), parameter files under a namespace,
unknown parameters, a goal sent before any joint_states, floods of bad input, targets
that overlap the spacecraft.  Oracles: the process's exit code and stderr, the
node's declared parameters, the action protocol, the log lines (capfd) and
/diagnostics.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys

import pytest
import rclpy
from rclpy.context import Context
from rclpy.parameter import Parameter

from conftest import CONFIG_DIR


#: generous: a loaded 2-core machine imports rclpy and numba slowly
START_TIMEOUT_S = 120


def _run_node(*ros_args):
    """Run planner_node until it exits (killed with its process group after START_TIMEOUT_S)."""
    cmd = [sys.executable, "-m", "spacerobot_planner.ros.planner_node", "--ros-args", *ros_args]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, stdin=subprocess.DEVNULL,
                            text=True, start_new_session=True)
    try:
        out, err = proc.communicate(timeout=START_TIMEOUT_S)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        out, err = proc.communicate()
        raise AssertionError(f"planner_node did not exit within {START_TIMEOUT_S} s\n{err[-3000:]}") from None
    return subprocess.CompletedProcess(cmd, proc.returncode, out, err)


# ================================================================== 1. start-up refusals
@pytest.mark.parametrize("ros_args, fragments", [
    (["-p", "safety_margin_m:=-1.0"], ["safety_margin_m", "-1.0 is below the minimum 0.0"]),
    (["-p", "planner.solver:=multigrid"], ["planner.solver", "'multigrid' is not one of"]),
    (["-p", "grid.cells:=[36,36]"], ["grid.cells", "expected 3 values"]),
    (["-p", "safety_margin_m:=wide"], ["safety_margin_m", "expected a number"]),
], ids=["below_range", "not_a_choice", "wrong_length", "wrong_type"])
def test_refused_start_value_is_one_line_and_a_nonzero_exit(ros_args, fragments):
    proc = _run_node(*ros_args)
    err = proc.stderr
    assert proc.returncode != 0, f"exit {proc.returncode}\n{err}"
    assert "Traceback" not in err and "AttributeError" not in err, err
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1, err
    for frag in fragments:
        assert frag in lines[0], lines[0]
    assert lines[0].startswith("planner_node: "), lines[0]


def test_refused_override_raises_value_error_and_the_context_shuts_down_cleanly():
    from spacerobot_planner.ros.planner_node import PlannerNode
    ctx = Context()
    rclpy.init(context=ctx)
    try:
        with pytest.raises(ValueError, match=r"safety_margin_m: -1.0 is below the minimum 0.0"):
            PlannerNode(context=ctx, parameter_overrides=[Parameter("safety_margin_m", value=-1.0)])
    finally:
        rclpy.shutdown(context=ctx)       # destroys the half-made node: no AttributeError


# ================================================================== 2. namespaces
@pytest.mark.parametrize("ns", ["/robot2", "/fleet/robot2"])
def test_shipped_file_configures_a_node_in_a_namespace(ns):
    """`--params-file config/paper_2dof.yaml -r __ns:=/robot2`: the file's node section applies."""
    from spacerobot_planner.ros.mock_arm_node import MockArmNode
    from spacerobot_planner.ros.planner_node import PlannerNode
    path = os.path.join(CONFIG_DIR, "paper_2dof.yaml")
    ctx = Context()
    rclpy.init(context=ctx, args=["planner_node", "--ros-args", "--params-file", path, "-r", f"__ns:={ns}",
                                  "-p", "autostart:=false"])
    try:
        node = PlannerNode(context=ctx)
        arm = MockArmNode(context=ctx)
        assert node.get_fully_qualified_name() == f"{ns}/spacerobot_planner"
        assert list(node.get_parameter("grid.cells").value) == [180, 180]      # its own section
        assert list(node.get_parameter("robot.planned_joints").value) == ["shoulder", "elbow"]   # /**
        assert node._scenario.grid.shape == (181, 181)
        assert list(arm.get_parameter("robot.planned_joints").value) == ["shoulder", "elbow"]
        node.destroy_node()
        arm.destroy_node()
    finally:
        rclpy.shutdown(context=ctx)


@pytest.mark.parametrize("name", ["paper_2dof", "paper_3dof", "servicer_3dof"])
def test_shipped_files_have_only_namespace_independent_sections(name):
    """Every section of a shipped file matches its node under any namespace."""
    import yaml
    from spacerobot_planner.config import load_params_file
    with open(os.path.join(CONFIG_DIR, f"{name}.yaml")) as f:
        doc = yaml.safe_load(f)
    assert all(key.startswith("/**") for key in doc), list(doc)
    flat = load_params_file(os.path.join(CONFIG_DIR, f"{name}.yaml"))
    assert "grid.cells" in flat and "robot.joint_names" in flat
    assert load_params_file(os.path.join(CONFIG_DIR, f"{name}.yaml"), node="mock_arm").get("rate_hz", 50.0) == 50.0


# ================================================================== 6. a goal before any joint_states
def test_goal_without_start_before_joint_states_says_so_then_aborts(graph):
    from action_msgs.msg import GoalStatus
    from spacerobot_planner_interfaces.action import PlanCapture
    from node_helpers import scene_params
    g = graph(scene_params("3dof", joint_states_timeout_s=1.0), with_arm=False)     # no joint_states at all
    desc = g.planner.describe_parameter("joint_states_timeout_s")
    assert desc.floating_point_range and "seconds" in desc.description
    goal = PlanCapture.Goal()
    goal.target_pose.header.frame_id = "world"
    goal.target_pose.pose.position.x, goal.target_pose.pose.position.y = -3.27, -2.60
    goal.target_pose.pose.orientation.w = 1.0
    feedback = []
    handle = g.send_goal(goal, feedback=lambda m: feedback.append(m.feedback.stage))
    status, res, _ = g.goal_result(handle, timeout=60)
    assert "waiting_for_joint_states" in feedback, feedback
    assert status == GoalStatus.STATUS_ABORTED and res.error_code == PlanCapture.Result.INVALID_INPUT
    assert "joint_states" in res.reason and "1 s" in res.reason, res.reason
    assert g.n_trajs() == 0


def test_goal_waiting_for_joint_states_plans_when_they_arrive(graph):
    from action_msgs.msg import GoalStatus
    from spacerobot_planner.ros.conversions import joint_state_msg
    from spacerobot_planner_interfaces.action import PlanCapture
    from node_helpers import scene_params
    g = graph(scene_params("3dof", joint_states_timeout_s=600.0), with_arm=False)
    goal = PlanCapture.Goal()
    goal.target_pose.header.frame_id = "world"
    goal.target_pose.pose.position.x, goal.target_pose.pose.position.y = -3.27, -2.60
    goal.target_pose.pose.orientation.w = 1.0
    feedback = []
    handle = g.send_goal(goal, feedback=lambda m: feedback.append(m.feedback.stage))
    g.wait(lambda: "waiting_for_joint_states" in feedback, 10, "the waiting feedback")
    robot = g.scenario.robot
    g.pub_js.publish(joint_state_msg(robot.joint_names, robot.full(g.scenario.start_rad)))
    status, res, _ = g.goal_result(handle, timeout=60)
    assert status == GoalStatus.STATUS_SUCCEEDED, res.reason
    assert feedback[0] == "waiting_for_joint_states" and "cspace" in feedback, feedback


def test_joint_states_timeout_default():
    from spacerobot_planner.config import spec_default
    assert spec_default("joint_states_timeout_s") == 10.0
