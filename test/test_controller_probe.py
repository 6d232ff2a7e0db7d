"""
``controller.switch: auto``: the planner sends its joins for the kind of controller that subscribes its trajectories.

The oracle is ros2_controllers' joint_trajectory_controller as its sources and docs state it,
written here as a table: from 6.8 on it declares ``allow_trajectory_replacement`` (default
true: a newer trajectory takes over at its stamp (6.8.0 and 6.9.0 hold it until then; after 6.9.0,
ros2_controllers #2419, it is spliced in from its stamp on); false: the legacy install at arrival);
before 6.8 (Kilted's 5.x, Jazzy's 4.x) it declares ``joints`` and ``interpolation_method`` and
installs at arrival.  The fake controllers below are plain rclpy nodes that declare those
parameters and subscribe the topic, as a controller manager's controller node does; what the
planner says is read where a user reads it (``/diagnostics``, its log).
"""

from __future__ import annotations

import time

import pytest
from node_helpers import diag_values, scene_params

#: (parameters the node declares, when joint_trajectory_controller of that kind switches): the table above
CONTROLLERS = {
    "jtc_before_6_8": ({"joints": ["shoulder", "elbow"], "interpolation_method": "splines"}, "arrival"),
    "jtc_6_8": ({"joints": ["shoulder", "elbow"], "interpolation_method": "splines",
                 "allow_trajectory_replacement": True}, "stamp"),
    "jtc_6_8_legacy": ({"joints": ["shoulder", "elbow"], "interpolation_method": "splines",
                        "allow_trajectory_replacement": False}, "arrival"),
}


#: a controller manager's controller as far as the planner can see: a node in a process of its own that
#: declares a controller's parameters and subscribes the topic (argv: name, parameters as JSON, null: a node
#: without parameter services, as ros2cli's ``ros2 topic echo``; s before its parameter services start, 0: at once)
_FAKE = """
import json, sys
import rclpy
from rclpy.executors import ExternalShutdownException
from trajectory_msgs.msg import JointTrajectory
from rclpy.parameter_service import ParameterService
rclpy.init()
late_s = float(sys.argv[3])
node = rclpy.create_node(sys.argv[1], start_parameter_services=sys.argv[2] != "null" and not late_s)
for key, value in (json.loads(sys.argv[2]) or {}).items():
    node.declare_parameter(key, value)
if late_s and sys.argv[2] != "null":
    timer = None

    def serve():
        node.destroy_timer(timer)
        node._parameter_service = ParameterService(node)
    timer = node.create_timer(late_s, serve)
node.create_subscription(JointTrajectory, "joint_trajectory", lambda m: None, 10)
try:
    rclpy.spin(node)
except (KeyboardInterrupt, ExternalShutdownException):
    pass
"""


class _FakeController:
    """A fake controller (``_FAKE``) in a process of its own, in the test run's ROS domain (its stderr in ``log``)."""

    def __init__(self, name, parameters, log, services_after_s=0.0):
        import json
        import subprocess
        import sys
        self.name, self.log = name, log
        with open(log, "w") as err:
            self.proc = subprocess.Popen([sys.executable, "-c", _FAKE, name, json.dumps(parameters),
                                          str(float(services_after_s))],
                                         stdout=subprocess.DEVNULL, stderr=err)

    def close(self):
        import signal
        import subprocess
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGINT)
        try:
            self.proc.wait(30)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()


@pytest.fixture
def fakes(tmp_path):
    """
    Start fake controllers (name, parameters); every one is stopped at the test's end.

    A failed wait would otherwise leave a process spinning in the worker's ROS domain (a stray
    controller for the tests after it); the waits' messages carry the fakes' stderr.
    """
    made = []

    def start(name, parameters, services_after_s=0.0):
        fake = _FakeController(name, parameters, tmp_path / f"{name}-{len(made)}.err", services_after_s)
        made.append(fake)
        return fake
    yield start
    for fake in made:
        fake.close()


def _stderr(fakes_made):
    return "".join(f"\n{f.name}: {open(f.log).read()[-1000:]}" for f in fakes_made)


def _probe_state(g) -> str:
    """Say what the planner's probe saw and asked (a failed wait's message): the subscribers, each remote."""
    probe = getattr(g.planner, "_probe", None)
    if probe is None:
        return "\nno probe"
    try:
        infos = g.planner.get_subscriptions_info_by_topic(probe._topic)
        seen = ", ".join(f"{i.node_namespace.rstrip('/')}/{i.node_name}" for i in infos)
    except Exception as e:          # noqa: BLE001 - only for the message
        seen = f"(not read: {e!r})"
    now = time.monotonic()
    remotes = "; ".join(f"{r.node}: asking {r.asking}, names {r.names}, answer {r.answer}, "
                        f"{now - r.seen_at:.1f} s since seen, {len(r.asked)} questions, "
                        f"clients {'yes' if r.clients else 'no'}" for r in list(probe._remotes.values()))
    return f"\nthe planner saw on {probe._topic}: {seen}\nits probe: {remotes or 'no remotes'}"


def _switch(g):
    """Return the planner status's (controller_switch, controller_switch_source), as /diagnostics last said."""
    v = diag_values(g.status("planner"))
    return v.get("controller_switch"), v.get("controller_switch_source", "")


#: a wait that includes starting or ending a Python process with rclpy, DDS discovery and a service round
#: trip, on a loaded 2-core machine (a fake killed at exit: Fast DDS's lease, about 20 s, before it is gone)
WAIT_S = 60


def _wait_switch(g, switch, source_has, timeout=WAIT_S, also=None):
    """Wait for /diagnostics to say ``switch`` with ``source_has`` in its source; ``also()`` runs at each poll."""
    def said():
        if also is not None:
            also()
        return _switch(g)[0] == switch and source_has in _switch(g)[1]
    g.wait(said, timeout, lambda: f"controller_switch {switch} ({source_has!r}); /diagnostics says {_switch(g)}")


def test_what_joint_trajectory_controllers_declare_tells_when_they_switch():
    """The table, node by node, and what the subscribers say together (no ROS: the pure rules)."""
    from spacerobot_planner.ros.controller_probe import agreed, kind_of
    for parameters, switch in CONTROLLERS.values():
        assert kind_of(set(parameters), parameters.get("allow_trajectory_replacement"))[0] == switch
    assert kind_of({"allow_trajectory_replacement"}, "yes")[0] is None          # a value that says nothing
    assert kind_of({"joints"})[0] is None and kind_of(set())[0] is None          # not a controller
    pre, new, other = ("arrival", "old"), ("stamp", "new"), (None, "not one")
    assert agreed({}, "/t")[:2] == (None, "info")                                 # nobody answered yet
    assert agreed({"/a": pre, "/b": pre, "/x": other}, "/t")[:2] == ("arrival", "info")
    assert agreed({"/a": pre, "/b": new}, "/t")[:2] == (None, "warning")        # disagree
    assert agreed({"/x": other}, "/t")[:2] == (None, "warning")                  # only non-controllers: guessing


@pytest.mark.parametrize("kind", sorted(CONTROLLERS))
def test_auto_sends_for_the_kind_of_joint_trajectory_controller_that_subscribes(graph, fakes, kind):
    parameters, switch = CONTROLLERS[kind]
    g = graph(scene_params("3dof"), with_arm=False)
    assert g.planner.get_parameter("controller.switch").value == "auto"          # the default
    _wait_switch(g, "stamp", "no trajectory controller")     # only the test's driver subscribes: not one
    fake = fakes("joint_trajectory_controller", parameters)
    _wait_switch(g, switch, "/joint_trajectory_controller")
    assert g.planner.session.controller_switch == switch
    fake.close()
    _wait_switch(g, "stamp", "no trajectory controller")     # gone: back to the assumption


def test_a_runtime_change_of_allow_trajectory_replacement_is_followed(graph, fakes):
    """``ros2 param set /arm_controller allow_trajectory_replacement false`` (the driver's parameter client)."""
    from rclpy.parameter import Parameter
    from rclpy.parameter_client import AsyncParameterClient
    g = graph(scene_params("3dof"), with_arm=False)
    fakes("arm_controller", CONTROLLERS["jtc_6_8"][0])
    _wait_switch(g, "stamp", "/arm_controller (allow_trajectory_replacement true)")
    client = AsyncParameterClient(g.drv, "/arm_controller")
    g.wait(lambda: client.services_are_ready(), WAIT_S, "/arm_controller's parameter services")
    for value, switch in ((False, "arrival"), (True, "stamp")):
        sent = []

        def set_value(value=value):       # again every 2 s: a request or its event lost while matching
            if not sent or time.monotonic() - sent[-1] > 2.0:
                sent.append(time.monotonic())
                client.set_parameters([Parameter("allow_trajectory_replacement", Parameter.Type.BOOL, value)])
        _wait_switch(g, switch, f"/arm_controller (allow_trajectory_replacement {str(value).lower()})", also=set_value)


def test_controllers_that_disagree_are_warned_and_the_assumption_kept(graph, fakes):
    g = graph(scene_params("3dof"), with_arm=False)
    new = fakes("new_controller", CONTROLLERS["jtc_6_8"][0])
    old = fakes("old_controller", CONTROLLERS["jtc_before_6_8"][0])
    g.wait(lambda: "disagree" in g.log_text(), WAIT_S,
           lambda: "the warning; the node said:\n" + g.log_text()[-3000:] + _stderr([new, old]) + _probe_state(g))
    line = next(x for x in g.log_text().splitlines() if "disagree" in x)
    assert "WARN" in line, line
    assert "/new_controller at its stamp" in line and "/old_controller at its arrival" in line, line
    assert g.planner.session.controller_switch == "stamp"
    _wait_switch(g, "stamp", "disagree")
    old.close()
    _wait_switch(g, "stamp", "/new_controller (allow_trajectory_replacement true)")


def test_a_stated_controller_switch_is_not_probed(graph, fakes):
    g = graph(scene_params("3dof", **{"controller.switch": "arrival"}), with_arm=False)
    fakes("joint_trajectory_controller", CONTROLLERS["jtc_6_8"][0])
    _wait_switch(g, "arrival", "parameter controller.switch")
    assert g.planner._probe is None


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


def test_a_controller_loaded_again_under_its_name_is_asked_again(graph, fakes):
    """``ros2 control unload_controller`` then ``load_controller`` of the same name with the other kind."""
    g = graph(scene_params("3dof"), with_arm=False)
    fake = fakes("arm_controller", CONTROLLERS["jtc_6_8"][0])
    _wait_switch(g, "stamp", "/arm_controller (allow_trajectory_replacement true)")
    fake.close()
    fakes("arm_controller", CONTROLLERS["jtc_before_6_8"][0])
    _wait_switch(g, "arrival", "/arm_controller (a joint_trajectory_controller without")


def test_a_subscriber_without_parameter_services_is_given_up_and_a_controller_still_found(graph, fakes, monkeypatch):
    """A node with no parameter services on the topic: its clients go after ``GIVE_UP_S``, with a warning."""
    from spacerobot_planner.ros import controller_probe
    monkeypatch.setattr(controller_probe, "GIVE_UP_S", 3.0)
    g = graph(scene_params("3dof"), with_arm=False)
    fakes("silent", None)
    remotes = g.planner._probe._remotes
    g.wait(lambda: "/silent" in remotes and remotes["/silent"].answer is not None, WAIT_S, "/silent given up")
    assert remotes["/silent"].clients is None and "did not answer within 3 s" in remotes["/silent"].answer[1]
    _wait_switch(g, "stamp", "/silent: did not answer within 3 s")
    fakes("joint_trajectory_controller", CONTROLLERS["jtc_before_6_8"][0])
    _wait_switch(g, "arrival", "/joint_trajectory_controller")


def test_a_controller_that_answers_only_after_it_was_given_up_is_asked_again_and_found(graph, fakes, monkeypatch):
    """
    A controller whose parameter services come up late (a loaded machine): given up, asked again, its kind used.

    Before, a subscriber given up after ``GIVE_UP_S`` was never asked again until its
    subscriptions changed: a controller slow to answer was never counted.
    """
    from spacerobot_planner.ros import controller_probe
    monkeypatch.setattr(controller_probe, "GIVE_UP_S", 3.0)
    monkeypatch.setattr(controller_probe, "ASK_AGAIN_S", 2.0)
    g = graph(scene_params("3dof"), with_arm=False)
    made = [fakes("slow_controller", CONTROLLERS["jtc_before_6_8"][0], services_after_s=12.0)]
    _wait_switch(g, "stamp", "/slow_controller: did not answer within 3 s",
                 also=lambda: None if made[0].proc.poll() is None else pytest.fail(_stderr(made)))
    # still silent then (its services start 12 s after its process, the first give-up came at least 3 s after
    # its subscription was seen): then asked again until it answers
    _wait_switch(g, "arrival", "/slow_controller (a joint_trajectory_controller without")
    assert g.planner._probe._remotes["/slow_controller"].clients is None       # its clients gone once answered


@pytest.mark.parametrize("old_kind, new_kind", [("jtc_before_6_8", "jtc_before_6_8"), ("jtc_6_8", "jtc_before_6_8")])
def test_a_controller_started_again_beside_itself_is_asked_again_and_keeps_a_kind_throughout(
        graph, fakes, old_kind, new_kind):
    """
    A respawn: the new process up before the old one is gone.

    The answer is kept while the node is asked again (no flap to the assumption: every
    /diagnostics source names the controller), and once the old one is gone the new one's kind
    is the one used (the old process may have answered the question asked while both were up).
    """
    g = graph(scene_params("3dof"), with_arm=False)
    old = fakes("arm_controller", CONTROLLERS[old_kind][0])
    _wait_switch(g, CONTROLLERS[old_kind][1], "/arm_controller")
    with g.lock:
        since = len(g.diags)

    def subscriptions():
        return sum(i.node_name == "arm_controller" for i in g.planner.get_subscriptions_info_by_topic(
            "/joint_trajectory"))
    fakes("arm_controller", CONTROLLERS[new_kind][0])
    g.wait(lambda: subscriptions() == 2, WAIT_S, "the second /arm_controller's subscription")
    old.close()
    g.wait(lambda: subscriptions() == 1, WAIT_S, "the first /arm_controller gone")
    remotes = g.planner._probe._remotes
    g.wait(lambda: "/arm_controller" in remotes and len(remotes["/arm_controller"].gids) == 1
           and not remotes["/arm_controller"].asking, WAIT_S, "/arm_controller asked again, alone")
    _wait_switch(g, CONTROLLERS[new_kind][1], "/arm_controller")
    with g.lock:
        until = len(g.diags)
    g.wait(lambda: len(g.diags) > until, WAIT_S, "a /diagnostics heartbeat after it")   # none need come between
    with g.lock:
        sources = [diag_values(next(st for st in d.status if st.name.endswith(": planner"))).get(
            "controller_switch_source", "") for _, d in g.diags[since:]]
    assert all("/arm_controller (" in s for s in sources), sources
