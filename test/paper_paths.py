"""The paper's two scenes and their planned paths, planned once per test process."""

from functools import lru_cache
from pathlib import Path

import numpy as np

CONFIG = Path(__file__).resolve().parent.parent / "config"


@lru_cache(maxsize=None)
def scene(name):
    """(Scenario, path_rad) for "paper_2dof" or "paper_3dof" (the existing planner's path)."""
    from spacerobot_planner.config import load_scenario
    from spacerobot_planner.planner import Planner
    sc = load_scenario(CONFIG / f"{name}.yaml")
    res = Planner(sc).plan(sc.start_rad, sc.goal_rad)
    assert res.ok, res.reason
    path = np.array(res.path_rad)
    path.setflags(write=False)
    return sc, path


def joint_limits(sc):
    """Planned-joint (vmax rad/s, amax rad/s²) from the scenario file."""
    idx = list(sc.robot.planned_joints)
    return (np.radians(sc.params["trajectory.max_velocity_deg_s"])[idx],
            np.radians(sc.params["trajectory.max_acceleration_deg_s2"])[idx])
