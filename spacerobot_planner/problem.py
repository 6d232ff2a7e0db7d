"""
The planning problem: robot, scene, grid and typed settings (no file format here).

``config.py`` builds one from a parameter file (the only place that reads the dotted
parameter names); tests and tools build one directly.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from .cspace import GridSpec
from .spacecraft import AcsSettings, MassProperties
from .robot import PlanarArm
from .scene import Scene
from .settings import JointLimits, PlannerSettings

__all__ = ["Scenario"]


@dataclass(frozen=True, eq=False)
class Scenario:
    """
    Everything needed to plan: robot, scene, grid, and optionally start/goal.

    Attributes
    ----------
        robot: the arm (``robot.PlanarArm``).
        scene: target, debris and safety margin (``scene.Scene``).
        grid: the C-space grid over the planned joints (``cspace.GridSpec``).
        start_rad, goal_rad: (dof,) planned-joint postures, rad (None when not given).
        planning_frame: frame name of the scene's coordinates.
        params: the flat dotted parameter dict it was built from, for display only: the
            core never reads it (a copy with other values changes nothing; build a new
            scenario with ``config.scenario_from_params`` or replace the typed fields).
        masses: the spacecraft's mass properties (``dynamics.*``).
        acs: attitude-control settings (``acs.*``, ``grasp.position_tolerance_m``).
        joint_limits: the trajectory's joint limits (``trajectory.*``); None when the
            scenario states none: the planner then returns paths without trajectories.
        planner_settings: how the planner plans (``planner.*``,
            ``grasp.max_approach_error_deg``); ``Planner`` starts from them.

    """

    robot: PlanarArm
    scene: Scene
    grid: GridSpec
    start_rad: np.ndarray | None
    goal_rad: np.ndarray | None
    planning_frame: str = "world"
    params: dict = field(default_factory=dict)
    masses: MassProperties = field(default_factory=MassProperties)
    acs: AcsSettings = field(default_factory=AcsSettings)
    joint_limits: JointLimits | None = None
    planner_settings: PlannerSettings = field(default_factory=PlannerSettings)

    def __post_init__(self):
        if self.joint_limits is not None:
            self.joint_limits.check_robot(self.robot)

    def grid_with_cells(self, cells) -> GridSpec:
        """Return the same grid bounds with ``cells`` cells per planned joint."""
        return self.grid.with_cells(cells)

    def with_scene(self, scene: Scene) -> "Scenario":
        """Return a copy with another scene."""
        return replace(self, scene=scene)

    def with_grid(self, grid: GridSpec) -> "Scenario":
        """Return a copy with another grid."""
        return replace(self, grid=grid)
