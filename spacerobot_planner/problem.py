"""
The planning problem: robot, scene, grid and the spacecraft's settings (no file format here).

``config.py`` builds one from a parameter file; tests and tools build one directly.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from .cspace import GridSpec
from .dynamics import AcsSettings, MassProperties
from .robot import PlanarArm
from .scene import Scene

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
        params: the flat dotted parameter dict it was built from (``config.PARAMETERS``
            names; the trajectory limits and planner options are read from it).
        masses: the spacecraft's mass properties (``dynamics.*``).
        acs: attitude-control settings (``acs.*``, ``grasp.position_tolerance_m``).

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

    def grid_with_cells(self, cells) -> GridSpec:
        """Return the same grid bounds with ``cells`` cells per planned joint."""
        return self.grid.with_cells(cells)

    def with_scene(self, scene: Scene) -> "Scenario":
        """Return a copy with another scene."""
        return replace(self, scene=scene)

    def with_grid(self, grid: GridSpec) -> "Scenario":
        """Return a copy with another grid."""
        return replace(self, grid=grid)
