"""
``controller.switch: auto``: the planner sends its joins for the kind of controller that subscribes its trajectories.

The oracle is ros2_controllers' joint_trajectory_controller as its sources and docs state it,
written here as a table: from 6.8 on it declares ``allow_trajectory_replacement`` (default
true: a newer trajectory is spliced in at its stamp; false: the legacy install at arrival);
before 6.8 (Kilted's 5.x, Jazzy's 4.x) it declares ``joints`` and ``interpolation_method`` and
installs at arrival.  The fake controllers below are plain rclpy nodes that declare those
parameters and subscribe the topic, as a controller manager's controller node does; what the
planner says is read where a user reads it (``/diagnostics``, its log).
"""

from __future__ import annotations

import time

import pytest
from node_helpers import diag_values, scene_params

from spacerobot_planner.ros.controller_probe import PROBE_PERIOD_S

#: (parameters the node declares, when joint_trajectory_controller of that kind switches): the table above
CONTROLLERS = {
    "jtc_before_6_8": ({"joints": ["shoulder", "elbow"], "interpolation_method": "splines"}, "arrival"),
    "jtc_6_8": ({"joints": ["shoulder", "elbow"], "interpolation_method": "splines",
                 "allow_trajectory_replacement": True}, "stamp"),
    "jtc_6_8_legacy": ({"joints": ["shoulder", "elbow"], "interpolation_method": "splines",
                        "allow_trajectory_replacement": False}, "arrival"),
}


#: a controller manager's controller as far as the planner can see: a node in a process of its own that
#: declares a controller's parameters and subscribes the topic (argv: name, parameters as JSON; null: a node
#: without parameter services, as ros2cli's ``ros2 topic echo``)
_FAKE = """
import json, sys
import rclpy
from rclpy.executors import ExternalShutdownException
from trajectory_msgs.msg import JointTrajectory
rclpy.init()
node = rclpy.create_node(sys.argv[1], start_parameter_services=sys.argv[2] != "null")
for key, value in (json.loads(sys.argv[2]) or {}).items():
    node.declare_parameter(key, value)
node.create_subscription(JointTrajectory, "joint_trajectory", lambda m: None, 10)
try:
    rclpy.spin(node)
except (KeyboardInterrupt, ExternalShutdownException):
    pass
"""


class _FakeController:
    """A fake controller (``_FAKE``) in a process of its own, in the test run's ROS domain."""

    def __init__(self, g, name, parameters):
        import json
        import subprocess
        import sys
        self.name = name
        self.proc = subprocess.Popen([sys.executable, "-c", _FAKE, name, json.dumps(parameters)],
                                     stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)

    def close(self):
        import signal
        import subprocess
        self.proc.send_signal(signal.SIGINT)
        try:
            self.proc.wait(30)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()


def _switch(g):
    """Return the planner status's (controller_switch, controller_switch_source), as /diagnostics last said."""
    v = diag_values(g.status("planner"))
    return v.get("controller_switch"), v.get("controller_switch_source", "")


def _wait_switch(g, switch, source_has, timeout=30):
    g.wait(lambda: _switch(g)[0] == switch and source_has in _switch(g)[1], timeout,
           lambda: f"controller_switch {switch} ({source_has!r}); /diagnostics says {_switch(g)}")


@pytest.mark.parametrize("kind", sorted(CONTROLLERS))
def test_auto_sends_for_the_kind_of_joint_trajectory_controller_that_subscribes(graph, kind):
    parameters, switch = CONTROLLERS[kind]
    g = graph(scene_params("3dof"), with_arm=False)
    assert g.planner.get_parameter("controller.switch").value == "auto"          # the default
    _wait_switch(g, "stamp", "no trajectory controller")     # only the test's driver subscribes: not one
    fake = _FakeController(g, "joint_trajectory_controller", parameters)
    try:
        _wait_switch(g, switch, "/joint_trajectory_controller")
        assert g.planner.session.controller_switch == switch
    finally:
        fake.close()
    _wait_switch(g, "stamp", "no trajectory controller")     # gone: back to the assumption


def test_a_runtime_change_of_allow_trajectory_replacement_is_followed(graph):
    """``ros2 param set /arm_controller allow_trajectory_replacement false`` (the driver's parameter client)."""
    from rclpy.parameter import Parameter
    from rclpy.parameter_client import AsyncParameterClient
    g = graph(scene_params("3dof"), with_arm=False)
    fake = _FakeController(g, "arm_controller", CONTROLLERS["jtc_6_8"][0])
    try:
        _wait_switch(g, "stamp", "/arm_controller (allow_trajectory_replacement true)")
        client = AsyncParameterClient(g.drv, "/arm_controller")
        g.wait(lambda: client.services_are_ready(), 30, "/arm_controller's parameter services")
        for value, switch in ((False, "arrival"), (True, "stamp")):
            client.set_parameters([Parameter("allow_trajectory_replacement", Parameter.Type.BOOL, value)])
            _wait_switch(g, switch, f"/arm_controller (allow_trajectory_replacement {str(value).lower()})")
    finally:
        fake.close()


def test_controllers_that_disagree_are_warned_and_the_assumption_kept(graph, capfd):
    g = graph(scene_params("3dof"), with_arm=False)
    capfd.readouterr()
    new = _FakeController(g, "new_controller", CONTROLLERS["jtc_6_8"][0])
    old = _FakeController(g, "old_controller", CONTROLLERS["jtc_before_6_8"][0])
    seen = []

    def warned():
        seen.append(capfd.readouterr().err)
        return "disagree" in "".join(seen)
    try:
        g.wait(warned, 30, lambda: "the warning; the node said:\n" + "".join(seen)[-3000:])
        line = next(x for x in "".join(seen).splitlines() if "disagree" in x)
        assert "WARN" in line, line
        assert "/new_controller at its stamp" in line and "/old_controller at its arrival" in line, line
        assert g.planner.session.controller_switch == "stamp"
        _wait_switch(g, "stamp", "disagree")
    finally:
        old.close()
    _wait_switch(g, "stamp", "/new_controller (allow_trajectory_replacement true)")
    new.close()


def test_a_stated_controller_switch_is_not_probed(graph):
    g = graph(scene_params("3dof", **{"controller.switch": "arrival"}), with_arm=False)
    fake = _FakeController(g, "joint_trajectory_controller", CONTROLLERS["jtc_6_8"][0])
    try:
        _wait_switch(g, "arrival", "parameter controller.switch")
        assert g.planner._probe is None
    finally:
        fake.close()


def test_the_mock_arm_says_its_model_as_joint_trajectory_controller_does(graph):
    """The mock arm's ``allow_trajectory_replacement`` (false: a controller before 6.8) reaches the planner."""
    g = graph(scene_params("3dof", **{"mock_arm.allow_trajectory_replacement": False}))
    assert g.arm.switch_at_arrival
    _wait_switch(g, "arrival", "/mock_arm (allow_trajectory_replacement false)")


@pytest.mark.parametrize("switch, replacement, ok", [("stamp", True, True), ("arrival", False, True),
                                                     ("auto", False, True), ("auto", True, True),
                                                     ("stamp", False, False), ("arrival", True, False)])
def test_the_mock_arms_model_and_a_contradiction_refused(switch, replacement, ok):
    from spacerobot_planner.ros.mock_arm_node import _switches_at_arrival
    if ok:
        assert _switches_at_arrival(switch, replacement) is (not replacement)
    else:
        with pytest.raises(ValueError, match="contradicts controller.switch"):
            _switches_at_arrival(switch, replacement)


def test_a_controller_loaded_again_under_its_name_is_asked_again(graph):
    """``ros2 control unload_controller`` then ``load_controller`` of the same name with the other kind."""
    g = graph(scene_params("3dof"), with_arm=False)
    fake = _FakeController(g, "arm_controller", CONTROLLERS["jtc_6_8"][0])
    _wait_switch(g, "stamp", "/arm_controller (allow_trajectory_replacement true)")
    fake.close()
    fake = _FakeController(g, "arm_controller", CONTROLLERS["jtc_before_6_8"][0])
    try:
        _wait_switch(g, "arrival", "/arm_controller (a joint_trajectory_controller without")
    finally:
        fake.close()


def test_a_subscriber_without_parameter_services_is_given_up_and_a_controller_still_found(graph, monkeypatch):
    """``ros2 topic echo /joint_trajectory`` (no parameter services): its clients go after ``GIVE_UP_S``."""
    from spacerobot_planner.ros import controller_probe
    monkeypatch.setattr(controller_probe, "GIVE_UP_S", 3.0)
    g = graph(scene_params("3dof"), with_arm=False)
    echo = _FakeController(g, "echo", None)
    fake = None
    try:
        remotes = g.planner._probe._remotes
        g.wait(lambda: "/echo" in remotes and remotes["/echo"].answer is not None, 30, "/echo given up")
        assert remotes["/echo"].clients is None and "did not answer within 3 s" in remotes["/echo"].answer[1]
        _wait_switch(g, "stamp", "/echo: did not answer within 3 s")
        fake = _FakeController(g, "joint_trajectory_controller", CONTROLLERS["jtc_before_6_8"][0])
        _wait_switch(g, "arrival", "/joint_trajectory_controller")
    finally:
        echo.close()
        if fake is not None:
            fake.close()


def test_a_controller_started_again_beside_itself_keeps_its_kind_throughout(graph):
    """A respawn: the new process up before the old one is gone; the answer is kept while it is asked again."""
    g = graph(scene_params("3dof"), with_arm=False)
    old = _FakeController(g, "arm_controller", CONTROLLERS["jtc_before_6_8"][0])
    new = None
    try:
        _wait_switch(g, "arrival", "/arm_controller")
        with g.lock:
            since = len(g.diags)
        new = _FakeController(g, "arm_controller", CONTROLLERS["jtc_before_6_8"][0])
        infos = g.planner.get_subscriptions_info_by_topic("/joint_trajectory")
        g.wait(lambda: sum(i.node_name == "arm_controller" for i in g.planner.get_subscriptions_info_by_topic(
            "/joint_trajectory")) == 2, 30, f"the second /arm_controller's subscription ({infos})")
        old.close()
        g.wait(lambda: sum(i.node_name == "arm_controller" for i in g.planner.get_subscriptions_info_by_topic(
            "/joint_trajectory")) == 1, 30, "the first /arm_controller gone")
        time.sleep(2 * PROBE_PERIOD_S)        # ticks on the graph with the new one alone
        _wait_switch(g, "arrival", "/arm_controller")
        with g.lock:
            said = [diag_values(next(st for st in d.status if st.name.endswith(": planner"))).get("controller_switch")
                    for _, d in g.diags[since:]]
        assert said and set(said) == {"arrival"}, said
    finally:
        old.close()
        if new is not None:
            new.close()
