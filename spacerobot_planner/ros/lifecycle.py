"""
The planner node's lifecycle interface, on rclpy's public API only.

The node is a ``rclpy.lifecycle.LifecycleNode`` made with
``enable_communication_interface=False``: it serves the lifecycle services itself
(``~/change_state``, ``~/get_state``, ``~/get_available_states``,
``~/get_available_transitions``, ``~/get_transition_graph``; rcl still publishes
``~/transition_event``), as ``ros2 lifecycle`` expects them, so that a transition that is
not possible from the current state is refused with a log line naming the state and the
transitions it has (rclpy's own service answers with numbers only).  Transitions run
through the node's public ``trigger_*`` methods; the current state is tracked here from
what they return (the node's ``on_error`` always succeeds: an error ends unconfigured).
"""

from __future__ import annotations

from lifecycle_msgs.msg import State, Transition, TransitionDescription
from lifecycle_msgs.srv import ChangeState, GetAvailableStates, GetAvailableTransitions, GetState
from rclpy.lifecycle import TransitionCallbackReturn

__all__ = ["LifecycleInterface", "TRANSITIONS", "STATES"]

#: every state of the standard machine: id -> label
STATES = {State.PRIMARY_STATE_UNKNOWN: "unknown", State.PRIMARY_STATE_UNCONFIGURED: "unconfigured",
          State.PRIMARY_STATE_INACTIVE: "inactive", State.PRIMARY_STATE_ACTIVE: "active",
          State.PRIMARY_STATE_FINALIZED: "finalized", State.TRANSITION_STATE_CONFIGURING: "configuring",
          State.TRANSITION_STATE_CLEANINGUP: "cleaningup", State.TRANSITION_STATE_SHUTTINGDOWN: "shuttingdown",
          State.TRANSITION_STATE_ACTIVATING: "activating", State.TRANSITION_STATE_DEACTIVATING: "deactivating",
          State.TRANSITION_STATE_ERRORPROCESSING: "errorprocessing"}
_U, _I, _A, _F = (State.PRIMARY_STATE_UNCONFIGURED, State.PRIMARY_STATE_INACTIVE, State.PRIMARY_STATE_ACTIVE,
                  State.PRIMARY_STATE_FINALIZED)
#: the primary transitions, in rcl_lifecycle's order: (id, label, start, transition state, goal on success)
TRANSITIONS = (
    (Transition.TRANSITION_CONFIGURE, "configure", _U, State.TRANSITION_STATE_CONFIGURING, _I),
    (Transition.TRANSITION_UNCONFIGURED_SHUTDOWN, "shutdown", _U, State.TRANSITION_STATE_SHUTTINGDOWN, _F),
    (Transition.TRANSITION_CLEANUP, "cleanup", _I, State.TRANSITION_STATE_CLEANINGUP, _U),
    (Transition.TRANSITION_ACTIVATE, "activate", _I, State.TRANSITION_STATE_ACTIVATING, _A),
    (Transition.TRANSITION_INACTIVE_SHUTDOWN, "shutdown", _I, State.TRANSITION_STATE_SHUTTINGDOWN, _F),
    (Transition.TRANSITION_DEACTIVATE, "deactivate", _A, State.TRANSITION_STATE_DEACTIVATING, _I),
    (Transition.TRANSITION_ACTIVE_SHUTDOWN, "shutdown", _A, State.TRANSITION_STATE_SHUTTINGDOWN, _F),
)
_NAMES = {t[0]: t[1] for t in TRANSITIONS}


def _state(state_id: int) -> State:
    return State(id=state_id, label=STATES[state_id])


class LifecycleInterface:
    """
    The lifecycle services of ``node`` and its current state.

    ``node``: a LifecycleNode made with ``enable_communication_interface=False`` whose
    ``trigger_*`` methods call :meth:`run`.
    """

    def __init__(self, node):
        self.node = node
        self.state_id = _U
        node.create_service(ChangeState, "~/change_state", self._on_change_state)
        node.create_service(GetState, "~/get_state", self._on_get_state)
        node.create_service(GetAvailableStates, "~/get_available_states", self._on_get_available_states)
        node.create_service(GetAvailableTransitions, "~/get_available_transitions",
                            self._on_get_available_transitions)
        node.create_service(GetAvailableTransitions, "~/get_transition_graph", self._on_get_transition_graph)

    @property
    def state(self) -> str:
        """Return the current state's label."""
        return STATES[self.state_id]

    def available(self) -> list:
        """Return the transitions possible now: [(id, label, start, transition state, goal)]."""
        return [t for t in TRANSITIONS if t[2] == self.state_id]

    def refusal(self, label: str = "", transition_id: int = 0) -> str | None:
        """Return (and log) why a transition is not possible now, or None when it is."""
        names = [t[1] for t in self.available()]
        if (label and label in names) or (not label and any(t[0] == transition_id for t in self.available())):
            return None
        known = {t[0]: t for t in TRANSITIONS}.get(transition_id)
        if label:
            want = f"'{label}'"
        elif known is None:
            want = f"transition id {transition_id}"
        else:                    # by id alone: which one (three ids are 'shutdown', each from its own state)
            want = f"'{known[1]}' (id {transition_id}, from {STATES[known[2]]})"
        possible = ", ".join(f"{t[1]} (id {t[0]})" for t in self.available())
        reason = f"lifecycle: {want} refused: the node is '{self.state}'; possible now: {possible or 'none'}"
        self.node.get_logger().error(reason)
        return reason

    def run(self, label: str, trigger) -> TransitionCallbackReturn:
        """Run one transition through ``trigger`` (rclpy's ``trigger_<label>``) when possible now."""
        if self.refusal(label) is not None:
            return TransitionCallbackReturn.ERROR
        goal = next(t for t in self.available() if t[1] == label)[4]
        ret = trigger()
        if ret == TransitionCallbackReturn.SUCCESS:
            self.state_id = goal
        elif ret == TransitionCallbackReturn.ERROR:      # errorprocessing -> on_error (succeeds)
            self.state_id = _U
        elif label == "shutdown":
            self.state_id = _F
        return ret

    # ------------------------------------------------------------------ services
    def _on_change_state(self, req, resp):
        label, tid = req.transition.label, req.transition.id
        if self.refusal(label, tid) is not None:
            resp.success = False
            return resp
        label = label or _NAMES[tid]
        trigger = {"configure": self.node.trigger_configure, "cleanup": self.node.trigger_cleanup,
                   "activate": self.node.trigger_activate, "deactivate": self.node.trigger_deactivate,
                   "shutdown": self.node.trigger_shutdown}[label]
        resp.success = trigger() == TransitionCallbackReturn.SUCCESS
        return resp

    def _on_get_state(self, req, resp):
        resp.current_state = _state(self.state_id)
        return resp

    def _on_get_available_states(self, req, resp):
        resp.available_states = [_state(i) for i in STATES if i != State.PRIMARY_STATE_UNKNOWN]
        return resp

    @staticmethod
    def _descriptions(transitions) -> list:
        return [TransitionDescription(transition=Transition(id=t[0], label=t[1]), start_state=_state(t[2]),
                                      goal_state=_state(t[3])) for t in transitions]

    def _on_get_available_transitions(self, req, resp):
        resp.available_transitions = self._descriptions(self.available())
        return resp

    def _on_get_transition_graph(self, req, resp):
        resp.available_transitions = self._descriptions(TRANSITIONS)
        return resp
