"""
Compatibility names: ``dynamics.py`` was split (issue 17); import from the new modules.

- ``spacecraft.py``: the spacecraft's physics (``MassProperties``, ``AcsSettings``,
  ``ACS_MODES``, the momentum map, ``WheelModel``, ``wheel_load``,
  ``free_floating_response``);
- ``reaction.py``: the verdict on a planned motion (``check_drifted``, ``DriftCheck``,
  ``ReactionReport``, ``reaction_report``);
- ``timing.py``: the trajectory stage of a scenario (``Motion``, ``plan_motion``,
  ``scenario_joint_limits``, ``timed_motion``);
- ``free_floating.py``: planning for the drift (``CompensatedPlan``, ``plan_free_floating``).

Only for code outside the core (``test/test_node.py``, ``tools/gendocs.py``); no module of
the core imports this one (``test/test_core_imports.py``).
"""

from .free_floating import CompensatedPlan, plan_free_floating
from .reaction import DriftCheck, ReactionReport, check_drifted, reaction_report
from .spacecraft import (ACS_MODES, AcsSettings, FreeFloatingResponse, MassProperties, WheelModel,
                         angular_momentum_Nms, free_floating_response, momentum_map, momentum_rate_Nm,
                         system_com_m, wheel_load)
from .timing import Motion, plan_motion, scenario_joint_limits

__all__ = ["MassProperties", "AcsSettings", "WheelModel", "FreeFloatingResponse", "DriftCheck", "ReactionReport",
           "ACS_MODES", "system_com_m", "angular_momentum_Nms", "momentum_rate_Nm", "momentum_map",
           "wheel_load", "free_floating_response", "check_drifted", "reaction_report", "Motion", "plan_motion",
           "scenario_joint_limits", "CompensatedPlan", "plan_free_floating"]
