"""
The planner node's parameter handler (Nav2's pattern): a change is validated once and applied once.

rclpy calls three hooks per change: the node's ``set_parameters*`` (here
:meth:`ParameterHandler.precheck`, before rclpy's descriptor checks, whose type errors are
enum numbers and whose undeclared-parameter error names none: the node's own reason goes to
the log and ``/diagnostics``; a whole number for a double is made a double before it,
``parameters.as_declared``), the
on-set callback (accept or refuse) and the post-set callback (apply).  The first
validation's result (the merged parameters and the scenario built from them, or the
reason) is kept for the same parameters and reused by the others; the post-set callback
hands it to ``apply`` once.

Validation: the schema's type and range (``config.check_value``), read-only parameters,
string choices, then the scenario (``config.scenario_from_params``: per-joint lengths
among others) and the node's own checks (:func:`check_runtime`: a target inside the
spacecraft, a grid over ``planner.max_grid_nodes``; a new size of the target's that would make
the current target, a ``target_pose``'s where it is, overlap the spacecraft: :func:`check_resized`).
"""

from __future__ import annotations

import difflib
import threading

from rcl_interfaces.msg import SetParametersResult

from ..config import check_value, scenario_from_params
from ..overlap import target_overlap_reason
from .parameters import SPECS, check_choice

__all__ = ["ParameterHandler", "check_runtime", "check_resized", "NO_REPLAN", "TARGET_POSE_PARAMETERS"]

#: the target.* parameters that place the target: a change makes the parameters' target current
#: (a target_pose's with it); target.body_side_m / handle_side_m alone resize the current one where it is
TARGET_POSE_PARAMETERS = ("target.center_m", "target.yaw_deg")

#: changes of these only affect publishing, not the plan: no replan
NO_REPLAN = {"replan.target_tolerance_m", "replan.target_tolerance_deg", "diagnostics.period_s",
             "replan.min_publish_period_s", "replan.horizon_s", "replan.follow_tolerance_deg",
             "potential_grid.use_current_attitude", "potential_grid.slice_attitude_deg", "grid_frame",
             "planner.test_stall_s", "joint_states_timeout_s", "trajectory.start_lead_s"}


def check_runtime(params: dict, scenario) -> None:
    """Raise ValueError (naming the parameter) for what the node refuses beyond the scenario."""
    check_choice("planner.solver", params["planner.solver"])
    overlap = target_overlap_reason(scenario.robot, scenario.scene.target)
    if overlap is not None:
        raise ValueError(f"target.center_m: {overlap}")
    nodes = scenario.grid.n_nodes
    if nodes > params["planner.max_grid_nodes"]:
        raise ValueError(f"grid.cells: {scenario.grid.label()} = {nodes} nodes exceeds "
                         f"planner.max_grid_nodes = {params['planner.max_grid_nodes']}")


def check_resized(names, scenario, current) -> None:
    """
    Raise ValueError (naming the parameter) where a change of the target's sizes alone overlaps the current target.

    ``names``: the changed parameters; ``scenario``: the one they make; ``current``: the
    session's current target (a ``target_pose``'s), which takes the new sizes where it is.
    """
    sized = [n for n in names if n.startswith("target.") and n not in TARGET_POSE_PARAMETERS]
    if current is None or not sized or any(n in TARGET_POSE_PARAMETERS for n in names):
        return
    overlap = target_overlap_reason(scenario.robot, current.sized_as(scenario.scene.target))
    if overlap is not None:
        raise ValueError(f"{sized[0]}: the current target at ({current.center_m[0]:.3f}, {current.center_m[1]:.3f}) m, "
                         f"resized: {overlap}")


def _key(parameters) -> tuple:
    return tuple((p.name, repr(p.value)) for p in parameters)


class ParameterHandler:
    """
    The node's parameters and scenario, changed through rclpy's parameter hooks.

    Parameters
    ----------
        node: the node (its on-set and post-set callbacks are added here; its
            ``set_parameters``/``set_parameters_atomically`` call :meth:`precheck`).
        params: the declared values (flat dotted dict); scenario: built from them.
        reject(reason): a refused change (log and /diagnostics).
        apply(params, scenario, names): an accepted change, once.
        current_target(): the session's current target (:func:`check_resized`), or None.

    """

    def __init__(self, node, params: dict, scenario, reject, apply, current_target=None):
        self.params, self.scenario = params, scenario
        self._reject, self._apply = reject, apply
        self._current_target = current_target
        self._lock = threading.Lock()
        self._checked = None        # (base params, key, (merged, scenario) or ValueError)
        self._declared = node.has_parameter
        node.add_on_set_parameters_callback(self._on_set)
        node.add_post_set_parameters_callback(self._post_set)

    def validate(self, parameters) -> tuple:
        """Return (merged params, scenario) of a change; ValueError names the field.  Once per change."""
        key = _key(parameters)
        with self._lock:
            checked, base = self._checked, self.params
        if checked is not None and checked[0] is base and checked[1] == key:
            got = checked[2]
        else:
            try:
                got = self._merge(base, parameters)
            except ValueError as e:
                got = e
            with self._lock:
                self._checked = (base, key, got)
        if isinstance(got, ValueError):
            raise got
        if self._current_target is not None:       # not kept with the rest: the current target moves
            check_resized([p.name for p in parameters], got[1], self._current_target())
        return got

    @staticmethod
    def _merge(base, parameters):
        merged = dict(base)
        for p in parameters:
            if p.name not in base:
                continue
            if SPECS[p.name].read_only:
                raise ValueError(f"{p.name}: read-only (a change needs a restart)")
            merged[p.name] = check_value(p.name, p.value)
            check_choice(p.name, merged[p.name])       # the node's wording, before the scenario's
        scenario = scenario_from_params(merged)
        check_runtime(merged, scenario)
        return merged, scenario

    def precheck(self, parameters) -> SetParametersResult | None:
        """Return the refusal of a change with the node's own reason, or None when it passes."""
        try:
            for p in parameters:
                if not self._declared(p.name):
                    close = difflib.get_close_matches(p.name, list(self.params), n=1, cutoff=0.6)
                    raise ValueError(f"'{p.name}': not a parameter of this node"
                                     + (f"; did you mean '{close[0]}'?" if close else "")
                                     + " (`ros2 param list` shows them)")
            self.validate(parameters)
        except ValueError as e:
            self._reject(f"parameter rejected: {e}")
            return SetParametersResult(successful=False, reason=str(e))
        return None

    def _on_set(self, parameters):
        try:
            self.validate(parameters)
        except ValueError as e:
            return SetParametersResult(successful=False, reason=str(e))
        return SetParametersResult(successful=True)

    def _post_set(self, parameters):
        merged, scenario = self.validate(parameters)
        names = [p.name for p in parameters if p.name in self.params]
        with self._lock:
            self.params, self.scenario = merged, scenario
            self._checked = None
        self._apply(merged, scenario, names)
