"""
What the planner node accepts at start and as input (issue 17).

Start-up refusals (one line, no traceback), parameter files under a namespace,
unknown parameters, a goal sent before any joint_states, floods of bad input, targets
that overlap the spacecraft.  Oracles: the process's exit code and stderr, the
node's declared parameters, the action protocol, the log lines (/rosout, capfd where no node logs any more) and
/diagnostics.
"""

from __future__ import annotations

import math
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
import rclpy
from rclpy.context import Context
from rclpy.parameter import Parameter

from conftest import CONFIG_DIR
from node_helpers import START_TIMEOUT_S


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


@pytest.mark.parametrize("text", [
    "/**:\n  ros__parameters:\n    safety_margin_m: [0.02\n",
    "/**:\n  ros__parameters:\n    robot.upper_deg: [180, 180.0, 180.0]\n",
], ids=["yaml_syntax", "mixed_list"])
def test_a_params_file_rcl_cannot_parse_is_one_line_and_a_nonzero_exit(tmp_path, text):
    """A file that rcl refuses inside ``rclpy.init``: one line naming the file, not a traceback."""
    bad = tmp_path / "bad.yaml"
    bad.write_text(text)
    proc = _run_node("--params-file", str(bad))
    err = proc.stderr
    assert proc.returncode != 0, f"exit {proc.returncode}\n{err}"
    assert "Traceback" not in err, err
    ours = [line for line in err.splitlines() if line.startswith("planner_node: ")]     # after rcl's own [ERROR]
    assert len(ours) == 1 and str(bad) in ours[0] and "line" in ours[0], err


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
        assert node.param_handler.scenario.grid.shape == (181, 181)
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
@pytest.mark.parametrize("sim_time", [False, True], ids=["wall_time", "sim_time_without_clock"])
def test_goal_without_start_before_joint_states_says_so_then_aborts(graph, sim_time):
    """
    The wait ends after joint_states_timeout_s of wall time, also under use_sim_time with no /clock published.

    There the reason also says that no /clock came (a driver on ROS time, the mock arm too, publishes nothing
    before it: a ROS user's goal had said only "no joint_states").
    """
    from action_msgs.msg import GoalStatus
    from spacerobot_planner_interfaces.action import PlanCapture
    from node_helpers import scene_params
    extra = {"use_sim_time": True} if sim_time else {}
    g = graph(scene_params("3dof", joint_states_timeout_s=1.0, **extra), with_arm=False)   # no joint_states at all
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
    assert ("no /clock message has come yet" in res.reason) == sim_time, res.reason
    assert g.n_trajs() == 0


def _mock_arm_started_with(argv):
    """Start a mock arm in a context rcl initialised with ``argv``; return (not_taken's lines, rate_hz, start)."""
    from spacerobot_planner.ros.mock_arm_node import MockArmNode
    from spacerobot_planner.ros.node_main import not_taken
    ctx = Context()
    rclpy.init(args=argv, context=ctx)
    try:
        node = MockArmNode(context=ctx)
        lines = not_taken(node, argv)
        rate = node.get_parameter("rate_hz").value
        start = list(node.get_parameter("scenario.start_deg").value)
        node.destroy_node()
    finally:
        rclpy.shutdown(context=ctx)
    return lines, rate, start


def test_a_command_line_parameter_the_files_node_section_overrides_is_said(tmp_path):
    """
    ``--params-file paper_3dof.yaml -p rate_hz:=20.0``: rcl keeps the file's ``/**/mock_arm`` value; the start says so.

    rcl itself decides (the node in a context initialised with those arguments); a ``-p`` of a
    name the file sets only under ``/**`` is taken (applied in order), and so is one naming the node.
    """
    from spacerobot_planner.ros.node_main import parameter_sections
    config = os.path.join(CONFIG_DIR, "paper_3dof.yaml")
    for args, fragments in (
            (["-p", "rate_hz:=20.0", "-p", "scenario.start_deg:=[-80.0,130.0,90.0]"],
             ["-p rate_hz:=20.0 was not taken (rate_hz is 50.0)", "-p mock_arm:rate_hz:=20.0 after the parameter file",
              "ros2 param set /mock_arm rate_hz 20.0", "its section /**/mock_arm"]),
            (["-p", "mock_arm:rate_hz:=20.0"], [])):
        lines, rate, start = _mock_arm_started_with(["mock_arm_node", "--ros-args", "--params-file", config, *args])
        if fragments:
            assert rate == 50.0 and start == [-80.0, 130.0, 90.0]          # rcl's choice: the file's, the -p's
            assert len(lines) == 1 and all(f in lines[0] for f in fragments), lines
        else:
            assert rate == 20.0 and lines == []
    assert parameter_sections(["x", "-p", "a:=1", "--ros-args", "-p", "b:=2", "--param", "c:=[1, 2]",
                               "-p", "n:d:=3", "-p", "b:=4", "--", "-p", "e:=5"]) == [
        ("/**", {"b": ("-p", "b:=4"), "c": ("-p", "c:=[1, 2]")}), ("/n", {"d": ("-p", "n:d:=3")})]


def test_a_parameter_file_that_does_not_state_the_robot_is_refused_and_one_for_no_node_is_said(tmp_path):
    """
    A file with ``robot.link_length_m`` (a typo) had started the nodes on the default arm; a file for no node: nothing.

    ``node_main.file_problems`` against rcl itself (the mock arm in a context initialised with the
    arguments): where it refuses, the node holds the default for every name it says is missing;
    the robot split over two files, or a file and a ``-p``, is stated; no file at all is the
    documented defaults.
    """
    from spacerobot_planner.ros.mock_arm_node import MockArmNode
    from spacerobot_planner.ros.node_main import file_problems
    import yaml
    paper = open(os.path.join(CONFIG_DIR, "paper_2dof.yaml")).read()
    typo, robot_only, rest, other = (tmp_path / f"{n}.yaml" for n in ("typo", "robot", "rest", "other"))
    typo.write_text(paper.replace("link_lengths_m", "link_length_m"))
    doc = yaml.safe_load(paper)                 # the robot in one file, the rest in another
    robot = doc["/**"]["ros__parameters"].pop("robot")
    robot_only.write_text(yaml.safe_dump({"/**": {"ros__parameters": {"robot": robot}}}))
    rest.write_text(yaml.safe_dump(doc))
    other.write_text("/**/planner:\n  ros__parameters:\n    rate_hz: 20.0\n")

    def problems(*args):
        """Start the node, checked where the executable checks it (its parameters declared, nothing begun)."""
        argv = ["mock_arm_node", "--ros-args", *map(str, args)]
        seen = {}

        def check(node):
            seen["said"] = file_problems(node, argv)
            seen["held"] = {n: list(node.get_parameter(n).value) for n in ("robot.link_lengths_m", "robot.joint_names")}
            raise ValueError("checked")       # the start stops here (the refusal's way)
        ctx = Context()
        rclpy.init(args=argv, context=ctx)
        try:
            with pytest.raises(ValueError, match="checked"):
                MockArmNode(context=ctx, start_check=check)
        finally:
            rclpy.shutdown(context=ctx)
        return (*seen["said"], seen["held"])
    refusal, warnings, held = problems("--params-file", typo)
    assert refusal is not None and refusal.startswith(f"the parameter file(s) {typo} state no robot.link_lengths_m "
                                                      f"for /mock_arm"), refusal
    assert held["robot.link_lengths_m"] == [1.4, 2.0, 2.0] and warnings == []     # rcl: the default, unset
    refusal, warnings, held = problems("--params-file", rest)
    assert refusal is not None and "robot.joint_names, robot.link_lengths_m" in refusal, refusal
    assert held["robot.joint_names"] == ["attitude", "shoulder", "elbow"]
    for args in (["--params-file", robot_only, "--params-file", rest],
                 ["--params-file", typo, "-p", "robot.link_lengths_m:=[1.4, 2.0, 2.0]"], ["-p", "rate_hz:=20.0"], []):
        refusal, warnings, _ = problems(*args)
        assert refusal is None and warnings == [], (args, refusal, warnings)
    refusal, warnings, _ = problems("--params-file", os.path.join(CONFIG_DIR, "paper_2dof.yaml"),
                                    "--params-file", other)
    assert refusal is None and len(warnings) == 1, warnings
    assert warnings[0].startswith(f"the parameter file {other} sets nothing for /mock_arm: none of its sections "
                                  f"(/**/planner) matches the node"), warnings


@pytest.mark.parametrize("exe", ["planner_node", "mock_arm_node"])
def test_the_executables_refuse_a_file_without_the_robot_and_arguments_outside_ros_args(tmp_path, exe):
    """One line and exit 1 before the node starts anything; a stray argument exit 2 naming it; --help the usage."""
    typo = tmp_path / "typo.yaml"
    paper = open(os.path.join(CONFIG_DIR, "paper_2dof.yaml")).read()
    typo.write_text(paper.replace("link_lengths_m", "link_length_m"))
    module = f"spacerobot_planner.ros.{exe}"

    def run(*args):
        proc = subprocess.run([sys.executable, "-m", module, *args], capture_output=True, text=True,
                              stdin=subprocess.DEVNULL, timeout=START_TIMEOUT_S)
        return proc.returncode, proc.stdout, proc.stderr
    rc, out, err = run("--ros-args", "--params-file", str(typo))
    ours = [line for line in err.splitlines() if line.startswith(f"{exe}: ")]
    assert rc == 1 and len(ours) == 1 and "state no robot.link_lengths_m" in ours[0], err
    assert "configured" not in err and "publishing" not in err, err          # nothing started
    if exe == "planner_node":      # renamed: the shipped file's /**/spacerobot_planner section (grid.cells) not its
        rc, out, err = run("--ros-args", "--params-file", os.path.join(CONFIG_DIR, "paper_3dof.yaml"),
                           "-r", "__node:=planner", "-r", "__ns:=/robot1")
        ours = [line for line in err.splitlines() if line.startswith(f"{exe}: ")]
        assert rc == 1 and len(ours) == 1 and "state no grid.cells for /robot1/planner: the section(s) " \
            "/**/spacerobot_planner set them, but not for this node's name" in ours[0], err
    rc, out, err = run("--params-file", os.path.join(CONFIG_DIR, "paper_2dof.yaml"))
    assert rc == 2 and err.startswith(f"{exe}: unrecognised argument(s) --params-file "), err
    assert "after --ros-args" in err, err
    rc, out, err = run("--help")
    assert rc == 0 and out.startswith(f"usage: {exe} [--ros-args") and "docs/parameters.md" in out, (out, err)


#: (the arguments after ``--ros-args``, the namespace, rcl's rate_hz, a fragment of the line said ("": none))
ORDER_CASES = {
    "scientific": (["-p", "rate_hz:=2e1"], "/", 20.0, ""),                      # rcl reads 2e1 as 20.0
    "wildcard_file": (["--params-file", "{wild}", "-p", "rate_hz:=2.5e1"], "/", 25.0, ""),
    "same_value": (["--params-file", "{paper}", "-p", "rate_hz:=50"], "/", 50.0, ""),
    "namespace": (["--params-file", "{paper}", "-p", "rate_hz:=20.0"], "/a", 50.0,
                  "ros2 param set /a/mock_arm rate_hz 20.0"),
    "wildcard_file_after": (["-p", "rate_hz:=2.5e1", "--params-file", "{wild}"], "/", 50.0, "its section /**"),
    "node_named_before": (["-p", "mock_arm:rate_hz:=20.0", "--params-file", "{paper}"], "/", 50.0,
                          "-p mock_arm:rate_hz:=20.0 was not taken"),
    "node_named_after": (["--params-file", "{paper}", "-p", "mock_arm:rate_hz:=20.0"], "/", 20.0, ""),
    # rcl matches a -p's node name in the root namespace only: in /a it applies to nothing (had been silent)
    "node_named_namespace": (["--params-file", "{paper}", "-p", "mock_arm:rate_hz:=20.0"], "/a", 50.0,
                             "it names the node /mock_arm in the root namespace, and this node is /a/mock_arm"),
    "own_section_first": (["--params-file", "{own}", "-p", "rate_hz:=25.0"], "/", 25.0, ""),
    "later_file": (["--params-file", "{wild}", "-p", "rate_hz:=25.0", "--params-file", "{w40}"], "/", 40.0,
                   "w40.yaml sets it in its section /**"),
    "repeated": (["-p", "rate_hz:=25.0", "--params-file", "{wild}", "-p", "rate_hz:=30.0"], "/", 30.0, ""),
    "root_star": (["-p", "rate_hz:=25.0", "--params-file", "{star}"], "/", 50.0, "its section /*"),
    "root_star_namespace": (["-p", "rate_hz:=25.0", "--params-file", "{star}"], "/a", 25.0, ""),
    "star_after_other": (["-p", "use_sim_time:=false", "--params-file", "{star}", "-p", "rate_hz:=25.0"], "/",
                         50.0, "its section /*"),
    "second_ros_args": (["-p", "rate_hz:=25.0", "--", "--ros-args", "--params-file", "{wild}"], "/", 50.0,
                        "its section /**"),
}


@pytest.mark.parametrize("case", list(ORDER_CASES))
def test_a_command_line_parameter_is_said_exactly_where_rcl_did_not_take_it(tmp_path, case):
    """
    A ``-p`` of ``rate_hz`` the node does not hold is named at its start; one it holds is not.

    rcl itself decides (the mock arm in a context initialised with the arguments): its value is
    the table's (rclpy applies the sections that match a node in the order their keys first
    appear: a ``-p`` that names no node joins ``/**``'s), and a line is said exactly where it
    differs from the last ``-p`` of it.  In a namespace no ``-p node:`` hint (rcl takes none there),
    and a ``-p node:`` is said not taken.
    """
    args, namespace, rcl_rate, fragment = ORDER_CASES[case]
    paper = os.path.join(CONFIG_DIR, "paper_3dof.yaml")
    files = {"paper": paper, "wild": tmp_path / "wild.yaml", "w40": tmp_path / "w40.yaml",
             "own": tmp_path / "own.yaml", "star": tmp_path / "star.yaml"}
    # the paper's /** section alone with rate_hz 50; /** with 40; the node's own section; /* (the root namespace's)
    files["wild"].write_text(open(paper).read().split("/**/spacerobot_planner:")[0].rstrip()
                             + "\n    rate_hz: 50.0\n")
    files["w40"].write_text("/**:\n  ros__parameters:\n    rate_hz: 40.0\n")
    files["own"].write_text("/**/mock_arm:\n  ros__parameters:\n    rate_hz: 50.0\n")
    files["star"].write_text("/*:\n  ros__parameters:\n    rate_hz: 50.0\n")
    lines, rate, _ = _mock_arm_started_with(["mock_arm_node", "--ros-args", "-r", f"__ns:={namespace}",
                                             *[a.format(**files) for a in args]])
    assert rate == rcl_rate
    given = [a for a in args if a.startswith(("rate_hz:=", "mock_arm:rate_hz:="))][-1]
    taken = rate == float(given.partition(":=")[2])
    assert len(lines) == (0 if taken else 1) and all(fragment in line for line in lines), lines
    assert bool(fragment) != taken
    assert all("give set" not in line and "ros2 param set " in line for line in lines), lines
    if namespace != "/":
        assert all("-p mock_arm:rate_hz:=20.0 after" not in line for line in lines), lines


def _clock_publisher(g):
    """Return tick(sec): the driver publishes /clock at ``sec`` s and the planner's ROS time follows (waited for)."""
    from rosgraph_msgs.msg import Clock
    pub = g.drv.create_publisher(Clock, "/clock", 10)

    def tick(sec):
        msg = Clock()
        msg.clock.sec = int(sec)
        g.wait(lambda: pub.publish(msg) or abs(g.planner.get_clock().now().nanoseconds - int(sec) * 10 ** 9) < 10 ** 6,
               30, f"the planner's ROS time at /clock {sec} s")
    return tick


def _stamp_s(msg):
    return msg.header.stamp.sec + 1e-9 * msg.header.stamp.nanosec


def test_ros_time_going_back_forgets_the_trajectory_sent_and_stamps_the_next_in_the_new_time(graph):
    """
    A bag played again under use_sim_time: /clock at 1000 s, a plan, then /clock back at 500 s.

    The next plan is stamped the lead after 500 s, from the arm's state; before, the node joined it
    to the trajectory sent before the jump and stamped it at that one's start, 500 s ahead.
    """
    from spacerobot_planner.ros.conversions import joint_state_msg
    from node_helpers import scene_params
    g = graph(scene_params("3dof", use_sim_time=True), with_arm=False)
    tick = _clock_publisher(g)
    robot = g.scenario.robot
    msg = joint_state_msg(robot.joint_names, robot.full(g.scenario.start_rad))
    tick(1000)
    msg.header.stamp.sec = 1000
    g.send_joint_state(msg)
    g.send_target()
    # the plan done (the worker publishes its visuals after the trajectory: a jump meanwhile plans again)
    g.wait(lambda: g.n_trajs() >= 1 and not g.planner.session.planning, 60, "the first trajectory, the plan done")
    with g.lock:
        first = g.trajs[0][1]
    assert 1000.0 < _stamp_s(first) < 1001.0
    tick(500)
    g.wait(lambda: g.planner.session.executing is None, 30, "the trajectory sent forgotten")
    msg.header.stamp.sec = 500
    g.send_joint_state(msg, lambda: g.planner.session.joint_ns == 500 * 10**9, what="the state stamped 500 s taken")
    g.send_target(x=-3.22, y=-2.65)
    g.wait(lambda: g.n_trajs() >= 2, 60, "the plan after the jump")
    with g.lock:
        second = g.trajs[1][1]
        g.checked.clear()             # their stamps are /clock's; the driver's controller check reads wall time
    assert 500.0 < _stamp_s(second) < 501.0, _stamp_s(second)
    assert not any(second.points[0].velocities), list(second.points[0].velocities)     # from rest
    err = g.wait_log("ROS time jumped back 500.000 s", 10)
    assert "forgotten" in err, err[-3000:]


def test_under_sim_time_before_the_first_clock_a_plan_fails_saying_so(graph):
    """ROS time 0 (no /clock yet): no trajectory stamped in the past, the reason named; no joint states called ahead."""
    from spacerobot_planner.ros.conversions import joint_state_msg
    from node_helpers import scene_params
    g = graph(scene_params("3dof", use_sim_time=True), with_arm=False)
    robot = g.scenario.robot
    msg = joint_state_msg(robot.joint_names, robot.full(g.scenario.start_rad))
    msg.header.stamp.sec = 1000                      # the driver's own sim time
    g.send_joint_state(msg)
    g.send_target()
    g.wait(lambda: any("/clock" in m for _, m in g.errors()), 60, "the plan's failure on /diagnostics")
    reason = next(m for _, m in g.errors() if "/clock" in m)
    assert "use_sim_time" in reason and "ROS time is 0" in reason, reason
    assert g.n_trajs() == 0
    assert "joint_states are stamped" not in g.log_text()


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
    g.send_joint_state(joint_state_msg(robot.joint_names, robot.full(g.scenario.start_rad)))
    status, res, _ = g.goal_result(handle, timeout=60)
    assert status == GoalStatus.STATUS_SUCCEEDED, res.reason
    # feedback and result travel apart: a feedback sent before the result may arrive after it
    g.wait(lambda: "cspace" in feedback, 5, "the cspace stage's feedback")
    assert feedback[0] == "waiting_for_joint_states" and "cspace" in feedback, feedback


def test_a_best_effort_joint_states_driver_is_heard(graph):
    """A driver publishing joint_states with the sensor-data QoS (best effort), as many do: heard and planned from."""
    from rclpy.qos import qos_profile_sensor_data
    from sensor_msgs.msg import JointState
    from spacerobot_planner.ros.conversions import joint_state_msg
    from node_helpers import scene_params
    g = graph(scene_params("3dof"), with_arm=False)
    pub = g.drv.create_publisher(JointState, "joint_states", qos_profile_sensor_data)
    g.wait(lambda: pub.get_subscription_count() >= 1, 30, "the planner's joint_states subscription matching "
           "a best-effort publisher")
    robot = g.scenario.robot
    start = robot.full(g.scenario.start_rad)
    msg = joint_state_msg(robot.joint_names, start)
    with g.lock:                 # the graph's reliable recorder does not hear it: the arm's state, for its checks
        g.states.append((time.monotonic(), msg))
    g.wait(lambda: pub.publish(msg) or g.planner.session.joint_q is not None, 30, "the best-effort joint state taken")
    g.send_target()
    g.wait(lambda: g.n_trajs() >= 1, 60, "a trajectory")
    with g.lock:
        first = g.trajs[0][1]
    want = [start[list(robot.joint_names).index(n)] for n in first.joint_names]    # it starts where the arm is
    assert np.allclose(first.points[0].positions, want, atol=1e-9), (list(first.points[0].positions), want)


def test_joint_states_on_another_clock_are_said_so_and_taken_at_their_arrival(graph):
    """A driver on sim time (stamps near 100 s) and a planner on wall time: a warning naming the clocks, a plan."""
    from spacerobot_planner.ros.conversions import joint_state_msg
    from node_helpers import scene_params
    g = graph(scene_params("3dof"), with_arm=False)
    robot = g.scenario.robot
    start = robot.full(g.scenario.start_rad)
    msg = joint_state_msg(robot.joint_names, start)
    msg.header.stamp.sec = 100
    with g.lock:                 # the arm's state, for the graph's checks of what a controller sees
        g.states.append((time.monotonic(), msg))
    g.send_joint_state(msg, lambda: "joint_states are stamped" in g.log_text(),
                       what=lambda: "the clocks' warning; the node said:\n" + g.log_text()[-2000:])
    err = g.log_text()
    line = next(x for x in err.splitlines() if "joint_states are stamped" in x)
    assert "s behind this node's clock" in line and "use_sim_time: false" in line and "same clock" in line, line
    off = float(line.split("stamped ")[1].split(" s ")[0])
    assert abs(off - (time.time() - 100.0)) < 60.0, line            # the test's own clock difference
    g.send_target()
    g.wait(lambda: g.n_trajs() >= 1, 60, "a trajectory from the state")


def test_a_plan_from_an_old_joint_state_says_how_old(graph):
    """One joint state, then silence (a driver gone, or `ros2 topic pub --once`): the plan says the state's age."""
    from spacerobot_planner.ros.conversions import joint_state_msg
    from node_helpers import scene_params
    g = graph(scene_params("3dof"), with_arm=False)
    robot = g.scenario.robot
    t_sent = time.monotonic()
    g.send_joint_state(joint_state_msg(robot.joint_names, robot.full(g.scenario.start_rad)))
    time.sleep(1.5)
    since = g.log_count()
    g.send_target()
    g.wait(lambda: g.n_trajs() >= 1, 60, "a trajectory")
    t_plan = time.monotonic()
    err = g.wait_log("from the last joint_states, ", 10, since=since)
    line = next((x for x in err.splitlines() if "from the last joint_states, " in x), None)
    assert line is not None, err[-2000:]
    age = float(line.split("from the last joint_states, ")[1].split(" s old")[0])
    # the test's own clock: 1.5 s of silence (less a copy of the state sent again, at most 0.25 s later)
    assert 1.2 <= age <= t_plan - t_sent + 0.1, (line, t_plan - t_sent)


def test_joint_states_timeout_default():
    from spacerobot_planner.config import spec_default
    assert spec_default("joint_states_timeout_s") == 10.0


# ================================================================== 7. a flood of bad input
def test_rejection_log_first_line_then_counts():
    from spacerobot_planner.ros.rejections import RejectionLog
    t = [0.0]
    log = RejectionLog(period_s=5.0, clock=lambda: t[0])
    lines = []
    for i in range(100):                  # 100 Hz for 1 s
        t[0] = 0.01 * i
        lines.append(log.reject("joint_states", f"bad {i}"))
    assert [x for x in lines if x] == ["joint_states: bad 0"]
    assert log.flush() == []              # within the period
    t[0] = 5.0
    assert log.flush() == ["joint_states: 99 more rejected in the last 5.0 s (latest: bad 99)"]
    assert log.flush() == []
    t[0] = 5.5                            # not quiet long enough: counted
    assert log.reject("joint_states", "bad") is None
    assert log.reject("target_pose", "other source") == "target_pose: other source"
    t[0] = 20.0                           # quiet for a period: whole again
    assert log.flush() == ["joint_states: 1 more rejected in the last 15.0 s (latest: bad)"]
    assert log.reject("joint_states", "again") == "joint_states: again"
    for i in range(1000):                 # a long flood: one count line per period
        t[0] = 20.0 + 0.01 * (i + 1)
        line = log.reject("joint_states", "x")
        assert line is None or (i + 1) % 500 == 0, (i, line)


def test_a_flood_of_bad_joint_states_logs_a_line_then_counts(graph):
    import math
    import time
    from spacerobot_planner.ros.conversions import joint_state_msg
    from spacerobot_planner.ros.rejections import REJECT_LOG_PERIOD_S
    from node_helpers import diag_values, scene_params
    g = graph(scene_params("3dof"), with_arm=False)
    names = g.scenario.robot.joint_names
    since = g.log_count()
    sent = []

    class Counted:              # one lost is sent again (joint_states are heard best effort): every send counted
        def publish(self, msg):
            sent.append(msg)
            g.pub_js.publish(msg)
    t0 = time.monotonic()
    for i in range(100):                  # a NaN in a different joint each time: the reasons differ
        q = [0.1, 0.2, 0.3]
        q[i % 3] = math.nan
        n0 = g.planner._rejected_total
        g.publish_until(Counted(), joint_state_msg(names, q), lambda: g.planner._rejected_total > n0, 10,
                        f"bad joint_states {i} rejected")
    elapsed = time.monotonic() - t0
    latest = f"joint(s) {names[99 % 3]} not finite"

    def counted():
        got = diag_values(g.status("input")).get("rejected_total")
        return got is not None and 100 <= int(got) <= len(sent) and int(got) == g.planner._rejected_total
    g.wait(counted, 10, lambda: f"the count (100 to {len(sent)} sent) in /diagnostics")
    iv = diag_values(g.status("input"))
    assert iv["source"] == "joint_states" and latest in iv["reason"], iv
    # the count line of the flood, at the latest a period after it
    err = g.wait_log("more rejected", REJECT_LOG_PERIOD_S + 15, since=since)
    lines = [line for line in err.splitlines() if "]: joint_states: " in line]      # the input's own lines
    assert "not finite" in lines[0], lines
    assert len(lines) <= 2 + elapsed / REJECT_LOG_PERIOD_S, lines
    total = 1 + sum(int(line.split("joint_states: ")[1].split(" more")[0]) for line in lines[1:])
    assert total == int(iv["rejected_total"]), (lines, iv)     # the log and /diagnostics agree
    assert latest in lines[-1], lines


def test_joint_states_outside_a_joints_bounds_are_refused_and_no_plan_starts_from_an_older_state(graph):
    """
    A driver reporting the shoulder at 250° (bounds ±180°): refused, naming it; no plan until a state is taken.

    Before, the state was taken (the input status OK) and each plan failed on its start.  Oracle:
    the bounds in the scenario file and the values the test sent; the attitude at 370° is the same
    posture as 10° (periodic), taken.
    """
    from action_msgs.msg import GoalStatus
    from spacerobot_planner.ros.conversions import joint_state_msg
    from spacerobot_planner_interfaces.action import PlanCapture
    from node_helpers import diag_values, scene_params
    g = graph(scene_params("3dof"), with_arm=False)
    robot = g.scenario.robot
    start = robot.full(g.scenario.start_rad)                         # attitude -90°, shoulder 135°, elbow 90°
    g.send_joint_state(joint_state_msg(robot.joint_names, start))
    away = start.copy()
    away[1] = math.radians(250.0)
    n0 = g.planner._rejected_total
    g.send_joint_state(joint_state_msg(robot.joint_names, away), lambda: g.planner._rejected_total > n0,
                       what="the out-of-bounds joint state refused")
    # the refusal reaches /diagnostics after the node counted it (two fresh clones' suites side by side
    # read the status before it, twice): waited for, then judged

    def refused():
        iv = diag_values(g.status("input"))
        return iv.get("source") == "joint_states" and "'shoulder' = 250.000°" in iv.get("reason", "")
    g.wait(refused, 10, "the refusal, naming the shoulder at 250°, in /diagnostics' input status")
    iv = diag_values(g.status("input"))
    assert "bounds [-180.0°, 180.0°]" in iv["reason"], iv
    np.testing.assert_array_equal(g.planner.session.joint_q, start)   # the last state taken, untouched
    goal = PlanCapture.Goal()
    goal.target_pose.header.frame_id = "world"
    goal.target_pose.pose.position.x, goal.target_pose.pose.position.y = -3.27, -2.60
    goal.target_pose.pose.orientation.w = 1.0
    status, res, _ = g.goal_result(g.send_goal(goal), timeout=60)
    assert status == GoalStatus.STATUS_ABORTED and "'shoulder' = 250.000°" in res.reason, (status, res.reason)
    assert g.n_trajs() == 0
    turned = start.copy()
    turned[0] += 2 * math.pi                                         # the attitude a turn on: the same posture
    g.send_joint_state(joint_state_msg(robot.joint_names, turned))                 # the attitude a turn on taken
    status, res, _ = g.goal_result(g.send_goal(goal), timeout=60)
    assert status == GoalStatus.STATUS_SUCCEEDED, res.reason


# ================================================================== 8. a target inside the spacecraft
def _unit_target(r, deg, side=0.2):
    from spacerobot_planner.scene import Target
    a = math.radians(deg)
    return Target(center_m=(r * math.cos(a), r * math.sin(a)), body_side_m=side)


def test_overlap_with_the_spacecraft_body(paper_scenario):
    from spacerobot_planner.overlap import polygons_overlap, target_overlap_reason
    from spacerobot_planner.robot import square_polygon
    assert polygons_overlap(square_polygon(1.0), square_polygon(0.2, (0.45, 0.0)))
    assert polygons_overlap(square_polygon(1.0), square_polygon(0.2))            # inside
    assert polygons_overlap(square_polygon(0.2), square_polygon(1.0))
    assert not polygons_overlap(square_polygon(1.0), square_polygon(0.2, (0.61, 0.0)))
    r2, r3 = paper_scenario(2).robot, paper_scenario(3).robot   # 1.8 m body, link 1 points at a corner
    assert target_overlap_reason(r3, paper_scenario(3).scene.target) is None   # the paper's target
    assert "overlaps the spacecraft body" in target_overlap_reason(r3, _unit_target(1.0, 180.0, 1.0))
    # 1.2 m out: inside the corner's reach (1.27 m), outside the edges' (0.9 m)
    locked = 160.7                                                  # the 2-DOF scene's attitude
    assert "locked attitude 160.7°" in target_overlap_reason(r2, _unit_target(1.2, locked))
    assert target_overlap_reason(r2, _unit_target(1.2, locked + 45.0)) is None
    assert "attitude is planned" in target_overlap_reason(r3, _unit_target(1.2, locked + 45.0))
    assert target_overlap_reason(r3, _unit_target(1.4, 0.0)) is None            # beyond the reach
    assert target_overlap_reason(r3, _unit_target(0.0, 0.0, 50.0)) is not None  # around the spacecraft


def test_target_overlapping_the_spacecraft_is_invalid_input(graph):
    from action_msgs.msg import GoalStatus
    from rclpy.parameter import Parameter
    from spacerobot_planner.ros.conversions import joint_state_msg
    from spacerobot_planner_interfaces.action import PlanCapture
    from node_helpers import diag_values, scene_params
    g = graph(scene_params("3dof"), with_arm=False)
    robot = g.scenario.robot
    g.send_joint_state(joint_state_msg(robot.joint_names, robot.full(g.scenario.start_rad)))
    g.send_target(-1.0, 0.0)
    g.wait(lambda: g.level("input") == b"\x02", 15, "the input status ERROR")
    iv = diag_values(g.status("input"))
    assert iv["code"] == "invalid_input" and "overlaps the spacecraft body" in iv["reason"], iv
    goal = PlanCapture.Goal()
    goal.target_pose.header.frame_id = "world"
    goal.target_pose.pose.position.x = -1.0
    goal.target_pose.pose.orientation.w = 1.0
    status, res, _ = g.goal_result(g.send_goal(goal))
    assert status == GoalStatus.STATUS_ABORTED and res.error_code == PlanCapture.Result.INVALID_INPUT
    assert "goal.target_pose" in res.reason and "overlaps the spacecraft body" in res.reason, res.reason
    refused = g.planner.set_parameters([Parameter("target.center_m", value=[-1.0, 0.0])])[0]
    assert not refused.successful and "target.center_m" in refused.reason and "overlaps" in refused.reason
    assert g.planner._gen == 0 and g.n_trajs() == 0                 # nothing was planned


# ================================================================== 9. unknown parameters
def test_unknown_parameters_name_the_closest_known_one():
    from spacerobot_planner.config import unknown_parameters
    lines = unknown_parameters(["safety_margn_m", "grid.cells", "rate_hz", "use_sim_time", "planner.solvr",
                                "qos_overrides./x.publisher.depth", "zzzzzz"])
    assert lines == ["unknown parameter 'safety_margn_m' (ignored); did you mean 'safety_margin_m'?",
                     "unknown parameter 'planner.solvr' (ignored); did you mean 'planner.solver'?",
                     "unknown parameter 'zzzzzz' (ignored)"], lines


def _typo_file(tmp_path):
    import yaml
    with open(os.path.join(CONFIG_DIR, "paper_2dof.yaml")) as f:
        doc = yaml.safe_load(f)
    doc["/**/spacerobot_planner"]["ros__parameters"]["safety_margn_m"] = 0.05
    doc["/**/spacerobot_planner"]["ros__parameters"]["grid"]["cells"] = [60, 60]
    path = tmp_path / "typo.yaml"
    path.write_text(yaml.safe_dump(doc))
    return str(path)


def test_unknown_parameter_in_a_file_is_reported_by_the_cli(tmp_path, capsys):
    from spacerobot_planner.tools.cli import main
    rc = main(["--params-file", _typo_file(tmp_path), "--quiet"])
    err = capsys.readouterr().err
    assert rc == 0, err
    assert "unknown parameter 'safety_margn_m' (ignored); did you mean 'safety_margin_m'?" in err, err


def test_unknown_parameter_in_a_file_is_reported_by_the_node(tmp_path, capfd):
    from spacerobot_planner.ros.planner_node import PlannerNode
    ctx = Context()
    rclpy.init(context=ctx, args=["--ros-args", "--params-file", _typo_file(tmp_path), "-p", "autostart:=false"])
    try:
        node = PlannerNode(context=ctx)
        assert not node.has_parameter("safety_margn_m")
        node.destroy_node()
    finally:
        rclpy.shutdown(context=ctx)
    err = capfd.readouterr().err
    lines = [line for line in err.splitlines() if "safety_margn_m" in line]
    assert len(lines) == 1 and "WARN" in lines[0], err
    assert "unknown parameter 'safety_margn_m' (ignored); did you mean 'safety_margin_m'?" in lines[0]


def test_an_inputs_durability_override_is_applied_and_one_not_taken_is_said(graph):
    """
    ``qos_overrides.<topic>.subscription.durability`` sets an input's QoS; one no input takes is named in a warning.

    Oracle: the ROS graph's view of the planner's own subscription (what ``ros2 topic info -v``
    prints).  rclpy's default overridable policies leave durability out: it was declared and
    reported by ``ros2 param get`` but not applied (a ROS user's audit).
    """
    from rclpy.qos import DurabilityPolicy
    from node_helpers import scene_params
    g = graph(scene_params("3dof", **{"qos_overrides./target_pose.subscription.durability": "transient_local",
                                      "qos_overrides./target_pose.subscription.lifespan": 5}),
              with_arm=False, wait_subscribed=False)

    def planner_endpoint():
        ends = g.drv.get_subscriptions_info_by_topic("/target_pose")
        return next((e for e in ends if e.node_name == "spacerobot_planner"), None)
    g.wait(lambda: planner_endpoint() is not None, 30, "the planner's target_pose subscription seen")
    assert planner_endpoint().qos_profile.durability == DurabilityPolicy.TRANSIENT_LOCAL
    g.wait_log("qos_overrides./target_pose.subscription.lifespan", 10)       # the override not taken, named


def test_a_held_joint_reported_away_from_its_lock_is_said_in_a_warning(graph):
    """
    joint_states with the attitude of the paper 2-DOF scene (not planned, held at 160.7°) 10° off: a warning names it.

    The plans hold a joint that is not planned at ``robot.locked_positions_deg``; after a
    free-floating capture the real attitude has drifted from it, and a user would plan with
    the wrong body pose unaware.  Oracle: the node's log (/rosout), the values the test sent.
    """
    from spacerobot_planner.ros.conversions import joint_state_msg
    from node_helpers import scene_params
    g = graph(scene_params("2dof"), with_arm=False)
    robot = g.scenario.robot
    q = robot.full(g.scenario.start_rad)
    assert robot.planned_joints == (1, 2) and abs(np.degrees(q[0]) - 160.7) < 1e-9
    g.send_joint_state(joint_state_msg(robot.joint_names, q))          # at its lock: nothing said
    off = q.copy()
    off[0] += np.radians(10.0)
    # sent until said (joint_states are heard best effort); one warning in 30 s however many came
    g.send_joint_state(joint_state_msg(robot.joint_names, off),
                       lambda: "attitude at 170.7° where robot.locked_positions_deg holds it at 160.7°" in g.log_text(),
                       what=lambda: "the held attitude's warning; the node said:\n" + g.log_text()[-3000:])
    assert g.log_text().count("robot.locked_positions_deg holds it") == 1, g.log_text()[-3000:]


def test_two_joint_states_publishers_that_disagree_are_said_in_a_warning_naming_them(graph):
    """
    A mock arm left running beside a driver: two publishers, 20° apart on the shoulder; a warning names both nodes.

    Before, nothing was said and each plan started from whichever state came last.  Two
    publishers that agree come first: a warning for them would be the one said (one at most in
    30 s), so the check of its values is also the check that agreeing ones are not said.
    Oracle: the node names the test gave and the values it sent.
    """
    import rclpy
    from sensor_msgs.msg import JointState
    from spacerobot_planner.ros.conversions import joint_state_msg
    from node_helpers import scene_params
    g = graph(scene_params("3dof"), with_arm=False)
    robot = g.scenario.robot
    start = robot.full(g.scenario.start_rad)                     # shoulder 135°
    other = rclpy.create_node("second_driver", context=g.ctx)
    try:
        _two_publishers(g, robot, start, [g.pub_js, other.create_publisher(JointState, "joint_states", 10)],
                        joint_state_msg)
    finally:
        other.destroy_node()


def _two_publishers(g, robot, start, pubs, joint_state_msg):
    g.wait(lambda: all(p.get_subscription_count() >= 2 for p in pubs), 30, "both publishers matched")
    since = g.log_count()

    def said(text):
        return lambda: text in g.log_text(since)
    same = start.copy()
    same[0] += 2 * math.pi                                       # the attitude a turn on: the same posture
    for i in range(20):                                          # agreeing, as two drivers of one arm
        for pub, q in zip(pubs, (start, same)):
            pub.publish(joint_state_msg(robot.joint_names, q))
    g.wait(lambda: len(g.planner.inputs._by_publisher) == 2 or any(
        p.publish(joint_state_msg(robot.joint_names, start)) for p in pubs), 10, "states of both taken")
    away = start.copy()
    away[1] -= math.radians(20.0)                                # shoulder 115°
    g.wait(lambda: any(p.publish(joint_state_msg(robot.joint_names, q)) for p, q in zip(pubs, (start, away)))
           or said("two publishers disagree")(), 30,
           lambda: "the warning; the node said:\n" + g.log_text(since)[-3000:])
    text = g.log_text(since)
    line = next(x for x in text.splitlines() if "two publishers disagree" in x)
    ours, theirs = f"/{g.drv.get_name()}", "/second_driver"       # which came first: as the two arrived
    assert (f"{ours} has shoulder at 135.0°, {theirs} at 115.0°" in line
            or f"{theirs} has shoulder at 115.0°, {ours} at 135.0°" in line), line
    assert text.count("two publishers disagree") == 1, text[-3000:]


# ================================================================== 10. the attitude from its own topic
def test_attitude_from_its_own_topic_when_joint_states_lack_it(graph):
    from geometry_msgs.msg import PoseStamped
    from spacerobot_planner.ros.conversions import joint_state_msg
    from node_helpers import diag_values, planned_positions, scene_params
    g = graph(scene_params("3dof", attitude_topic="spacecraft_pose"), with_arm=False)
    robot = g.scenario.robot
    assert g.planner.get_parameter("attitude_topic").value == "spacecraft_pose"
    start = robot.full(g.scenario.start_rad)                  # attitude -90°, shoulder 135°, elbow 90°
    arm_only = joint_state_msg(robot.joint_names[1:], start[1:])  # a real servicer's joint_states
    g.send_joint_state(arm_only, lambda: g.level("input") == b"\x02",   # no attitude yet: refused, saying where from
                       what="joint_states without the attitude refused")
    reason = diag_values(g.status("input"))["reason"]
    assert "attitude" in reason and "spacecraft_pose" in reason, reason
    pub = g.drv.create_publisher(PoseStamped, "spacecraft_pose", 10)
    g.wait(lambda: pub.get_subscription_count() > 0, 10, "the planner subscribed to spacecraft_pose")
    pose = PoseStamped()
    pose.header.frame_id = "world"
    yaw = start[0]
    pose.pose.orientation.z, pose.pose.orientation.w = math.sin(yaw / 2), math.cos(yaw / 2)
    g.publish_until(pub, pose, lambda: g.planner._attitude is not None, 30, "the attitude received")
    g.send_joint_state(arm_only, lambda: g.planner._joint_q is not None, what="joint_states with the topic's attitude")
    # the graph's controller check reads the recorded joint_states, which lack the attitude here: it
    # cannot see the attitude's current state (checked against the topic's yaw below instead)
    g.known_violations.add("the first point is at time 0 but is not the current state")
    g.send_target()
    g.wait(lambda: g.n_trajs() == 1 and len(g.att_trajs) == 1, 30, "a trajectory")
    first = planned_positions(robot, [g.trajs[0][1], g.att_trajs[0][1]], 0)
    assert abs(math.remainder(first[0] - yaw, 2 * math.pi)) < 1e-6, np.degrees(first)
    np.testing.assert_allclose(first[1:], start[1:], atol=1e-9)
