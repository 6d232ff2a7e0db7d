"""
`controller_probe`: which kind of controller takes the planner's ``joint_trajectory`` (``controller.switch: auto``).

ros2_controllers' joint_trajectory_controller takes a newer trajectory over at its header stamp
from 6.8 on with ``allow_trajectory_replacement`` true (its default), and at the trajectory's
arrival before 6.8 (Kilted's 5.x, Jazzy's 4.x) or with it false; a trajectory joined to the moving
arm is sent differently for each (``session.CaptureSession.controller_switch``, docs/node.md).
With ``controller.switch: auto`` the planner asks every node that subscribes its
``joint_trajectory`` for those parameters over the node's parameter services, as ``ros2 param``
does (``list_parameters`` of the names below, then ``get_parameters``):

- ``allow_trajectory_replacement`` true: it switches at the stamp; false: at the arrival
  (the mock arm declares it too);
- ``joints`` and ``interpolation_method`` without it: a joint_trajectory_controller before 6.8,
  at the arrival;
- neither: not a trajectory controller (``ros2 topic echo``, a recorder): left out.

The subscribers are looked at every ``PROBE_PERIOD_S`` (a controller started, gone, or started
again under its name: its subscription's gid; a question unanswered for ``ANSWER_TIMEOUT_S`` is
asked again; one that has not answered within ``GIVE_UP_S``, as a node without parameter services,
is left out, and asked again ``ASK_AGAIN_S`` later: a controller slow to answer on a loaded machine is
counted late, not never); a change of ``allow_trajectory_replacement`` at runtime comes on ``/parameter_events``.
What the controllers say together goes to the session
(``found``: one kind; None while there is none, or when they disagree, which is warned: the
session then keeps ``settings.SWITCH_UNTIL_FOUND``), and each change is logged once.  The
service clients live until the node answered.  Everything runs in the node's executor.
"""

from __future__ import annotations

import time
from typing import Callable

from rcl_interfaces.msg import ParameterEvent, ParameterType
from rcl_interfaces.srv import GetParameters, ListParameters
from rclpy.clock import Clock, ClockType
from rclpy.parameter import parameter_value_to_python
from rclpy.qos import qos_profile_parameter_events

from ..settings import SWITCH_UNTIL_FOUND

__all__ = ["ControllerProbe", "kind_of", "agreed", "REPLACEMENT", "JTC_PARAMETERS", "PROBE_PERIOD_S",
           "ANSWER_TIMEOUT_S", "GIVE_UP_S", "ASK_AGAIN_S"]

#: joint_trajectory_controller's parameter from ros2_controllers 6.8 on: true, a newer trajectory takes
#: over at its stamp (the mock arm's too)
REPLACEMENT = "allow_trajectory_replacement"
#: parameters every joint_trajectory_controller declares (Humble's on): without ``REPLACEMENT``, one before 6.8
JTC_PARAMETERS = ("joints", "interpolation_method")
#: a subscriber that has not answered this long after it was seen is not asked any more (its clients go), s
GIVE_UP_S = 30.0
#: a subscriber given up is asked again this long after, s (its answer, ``SILENT``, kept meanwhile): two
#: clients for up to ``GIVE_UP_S`` every minute for ``ros2 bag record``; a controller's answer found late
ASK_AGAIN_S = 30.0
#: what a subscriber given up is said to have done
SILENT = "did not answer"
#: the node name of a subscription discovered before its node's (rmw_dds_common's graph cache)
UNKNOWN_NAME = "_NODE_NAME_UNKNOWN_"
#: how often the subscribers of ``joint_trajectory`` are looked at, s (steady time)
PROBE_PERIOD_S = 1.0
#: a question unanswered this long is asked again, s (a service's response can be lost while the client's
#: side is being matched, although the service was ready)
ANSWER_TIMEOUT_S = 2.0


def kind_of(names, replacement=None) -> tuple:
    """
    Return (switch, what it is) of a node from the parameter names it has (of ``REPLACEMENT`` and ``JTC_PARAMETERS``).

    ``replacement``: the value of ``REPLACEMENT`` where it has it.  switch is "stamp", "arrival" or
    None (not a trajectory controller, or a value that says nothing); what it is, in words.
    """
    names = set(names)
    if REPLACEMENT in names:
        if isinstance(replacement, bool):
            return ("stamp" if replacement else "arrival"), f"{REPLACEMENT} {str(replacement).lower()}"
        return None, f"{REPLACEMENT} is {replacement!r}, not a bool"
    if all(n in names for n in JTC_PARAMETERS):
        return "arrival", (f"a joint_trajectory_controller without {REPLACEMENT}: before ros2_controllers 6.8, "
                           "as Kilted's and Jazzy's")
    return None, "not a trajectory controller (none of joint_trajectory_controller's parameters)"


def agreed(kinds: dict, topic: str) -> tuple:
    """
    Return (switch or None, level, text) of what the subscribers of ``topic`` say together.

    ``kinds``: node -> (switch or None, what it is) of the subscribers that answered (``kind_of``).
    One kind among the controllers: that; none, or controllers that disagree: None (the session keeps
    ``SWITCH_UNTIL_FOUND``), a warning when they disagree or when subscribers answered and none is a
    controller (a relay, a bridge, a driver of one's own: the planner is guessing).
    """
    controllers = {node: k for node, k in sorted(kinds.items()) if k[0] is not None}
    switches = {switch for switch, _ in controllers.values()}
    if len(switches) == 1:
        switch = switches.pop()
        who = "; ".join(f"{node} ({what})" for node, (_, what) in controllers.items())
        return switch, "info", (f"controller.switch auto: {who} on {topic} "
                                f"switch{'es' if len(controllers) == 1 else ''} to a newer trajectory at its "
                                f"{switch}: trajectories joined to the moving arm are sent for that")
    if switches:
        who = "; ".join(f"{node} at its {switch} ({what})" for node, (switch, what) in controllers.items())
        return None, "warning", (f"controller.switch auto: the controllers on {topic} disagree ({who}): sent as "
                                 f"for one that switches at its {SWITCH_UNTIL_FOUND} until they agree; set "
                                 "controller.switch to the one that moves the arm")
    tail = f"sent as for one that switches at its {SWITCH_UNTIL_FOUND} until one answers"
    if not kinds:
        return None, "info", f"controller.switch auto: no trajectory controller on {topic} has answered yet: {tail}"
    said = "; ".join(f"{node}: {what}" for node, (_, what) in sorted(kinds.items()))
    return None, "warning", (f"controller.switch auto: no trajectory controller on {topic} ({said}): {tail}; "
                             "set controller.switch if one of them moves the arm (a relay, a bridge, a driver)")


class _Remote:
    """A subscriber of the topic: its clients while a question is open, and its answer."""

    def __init__(self, node: str, gids: set):
        self.node = node               # its fully qualified name
        self.gids = gids               # its subscriptions' endpoint gids
        self.answer = None             # (switch or None, what it is) once it answered (kept while asked again)
        self.asking = True             # a question is due or open
        self.names = None              # the names it listed (of REPLACEMENT and JTC_PARAMETERS)
        self.clients = None            # (list_parameters, get_parameters) clients while asking
        self.future = None             # the question sent last
        self.asked = []                # every question of this round (a late reply is taken)
        self.asked_at = 0.0            # time.monotonic() of the question sent last
        self.seen_at = time.monotonic()   # when this round of questions began
        self.given_up_at = None        # time.monotonic() when it was given up (None: it answered, or is asked)

    def renew(self, now: float) -> None:
        """Ask again from the start (the answer there is, kept meanwhile)."""
        self.asking, self.names, self.future, self.seen_at, self.given_up_at = True, None, None, now, None


class ControllerProbe:
    """
    Ask the subscribers of ``topic`` which kind of controller they are (see the module docstring).

    ``found(switch)``: the session's ``controller_found``; ``log(level, text)``: the node's log.
    """

    def __init__(self, node, topic: str, found: Callable, log: Callable):
        self._node = node
        self._topic = topic
        self._found = found
        self._log = log
        self._own = node.get_fully_qualified_name()
        self._remotes: dict[str, _Remote] = {}
        self._said = None                    # the last (switch, level, text) told
        self.text = "no answer yet"          # what the subscribers said, for /diagnostics
        self._timer = node.create_timer(PROBE_PERIOD_S, self._tick, clock=Clock(clock_type=ClockType.STEADY_TIME))
        self._events = node.create_subscription(ParameterEvent, "/parameter_events", self._on_event,
                                                qos_profile_parameter_events)

    def start(self) -> None:
        """Look at the subscribers now (the timer does every ``PROBE_PERIOD_S`` from then)."""
        self._tick()

    def destroy(self) -> None:
        """Remove the timer, the subscription and any open question's clients."""
        for remote in list(self._remotes.values()):
            self._close(remote)
        self._remotes.clear()
        self._node.destroy_timer(self._timer)
        self._node.destroy_subscription(self._events)

    # ------------------------------------------------------------------ the subscribers
    def _tick(self) -> None:
        try:
            infos = self._node.get_subscriptions_info_by_topic(self._topic)
        except Exception:           # noqa: BLE001 - the context is shutting down
            return
        nodes = {}                  # node -> its subscriptions' gids (a node started again under its name: new ones)
        for i in infos:
            # a name not known yet (discovered before its node's: asked once it comes); a hidden node
            # (``_ros2cli_...``: ``ros2 topic echo``) is no controller
            if i.node_name != UNKNOWN_NAME and not i.node_name.startswith("_"):
                nodes.setdefault(_fqn(i.node_namespace, i.node_name), set()).add(bytes(i.endpoint_gid))
        nodes.pop(self._own, None)
        now = time.monotonic()
        for node, remote in list(self._remotes.items()):
            gids = nodes.get(node)
            if gids is None:
                self._close(self._remotes.pop(node))
            elif gids != remote.gids:         # started again under its name (both for a while): asked again with
                self._close(remote)           # new clients whenever its subscriptions change, its answer kept
                remote.renew(now)             # until the new one (the old node may have answered the question)
                remote.gids = gids
        for node in set(nodes) - set(self._remotes):
            self._remotes[node] = _Remote(node, nodes[node])
        for remote in self._remotes.values():
            if not remote.asking:
                if remote.given_up_at is None or now - remote.given_up_at < ASK_AGAIN_S:
                    continue
                remote.renew(now)                    # given up a while ago: asked again (slow under load?)
            if now - remote.seen_at > GIVE_UP_S:     # no parameter services (ros2 topic echo's node has none)
                self._answered(remote, (None, f"{SILENT} within {GIVE_UP_S:g} s (no parameter services?)"))
                remote.given_up_at = now
                continue
            if remote.future is None or now - remote.asked_at >= ANSWER_TIMEOUT_S:
                self._ask(remote, now)        # (again: a response sent before it could match is lost; a late
        self._decide()                        # one to the question before is taken too)

    def _ask(self, remote: _Remote, now: float) -> None:
        """Send the next question: the names it has (``list_parameters``), then ``REPLACEMENT``'s value."""
        if remote.clients is None:
            remote.clients = (self._node.create_client(ListParameters, f"{remote.node}/list_parameters"),
                              self._node.create_client(GetParameters, f"{remote.node}/get_parameters"))
        listing = remote.names is None
        client = remote.clients[0 if listing else 1]
        if not client.service_is_ready():      # not discovered yet (or no parameter services): the next tick
            return
        remote.asked_at = now
        if listing:
            remote.future = client.call_async(ListParameters.Request(
                prefixes=[REPLACEMENT, *JTC_PARAMETERS], depth=ListParameters.Request.DEPTH_RECURSIVE))
            remote.future.add_done_callback(lambda f, r=remote: self._listed(r, f))
        else:
            remote.future = client.call_async(GetParameters.Request(names=[REPLACEMENT]))
            remote.future.add_done_callback(lambda f, r=remote: self._got(r, f))
        remote.asked.append(remote.future)

    def _current(self, remote: _Remote, future) -> bool:
        """Whether a reply is still wanted: to this node's open questions (a late one too), with a result."""
        return (self._remotes.get(remote.node) is remote and remote.asking and future in remote.asked
                and not future.cancelled() and future.result() is not None)

    def _listed(self, remote: _Remote, future) -> None:
        if not self._current(remote, future) or remote.names is not None:
            return
        remote.names = set(future.result().result.names)
        remote.future = None
        if REPLACEMENT not in remote.names:
            self._answered(remote, kind_of(remote.names))
        else:
            self._ask(remote, time.monotonic())

    def _got(self, remote: _Remote, future) -> None:
        if not self._current(remote, future):
            return
        values = future.result().values
        value = values[0] if values else None
        self._answered(remote, kind_of({REPLACEMENT}, _python(value)))

    def _answered(self, remote: _Remote, answer: tuple) -> None:
        self._close(remote)
        remote.asking, remote.given_up_at = False, None
        if self._remotes.get(remote.node) is remote:
            remote.answer = answer
            self._decide()

    def _close(self, remote: _Remote) -> None:
        """Forget the open questions and remove the clients."""
        asked, remote.asked, remote.future = remote.asked, [], None
        clients, remote.clients = remote.clients, None
        for client in clients or ():
            for future in asked:
                client.remove_pending_request(future)
            self._node.destroy_client(client)

    def _on_event(self, event: ParameterEvent) -> None:
        """``/parameter_events``: a subscriber's ``allow_trajectory_replacement`` set or removed."""
        remote = self._remotes.get(event.node)
        if remote is None:
            return
        for p in (*event.new_parameters, *event.changed_parameters):
            if p.name == REPLACEMENT:
                self._answered(remote, kind_of({REPLACEMENT}, _python(p.value)))
        if any(p.name == REPLACEMENT for p in event.deleted_parameters):
            self._close(remote)
            remote.answer = None
            remote.renew(time.monotonic())          # asked again
            self._decide()

    def _decide(self) -> None:
        kinds = {node: r.answer for node, r in self._remotes.items() if r.answer is not None}
        said = agreed(kinds, self._topic)
        if said == self._said:
            return
        self._said = said
        switch, level, text = said
        self.text = text.split(": ", 1)[1]
        self._found(switch)
        self._log(level, text)


def _fqn(namespace: str, name: str) -> str:
    return f"{namespace.rstrip('/')}/{name}"


def _python(value):
    """Return a ParameterValue message's value (None for none, or one not set)."""
    if value is None or value.type == ParameterType.PARAMETER_NOT_SET:
        return None
    return parameter_value_to_python(value)
