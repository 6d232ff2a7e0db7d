"""Joint limits of the paper's scenes (their paths: the ``paper_path`` fixture, conftest.py)."""

import numpy as np


def joint_limits(sc):
    """Planned-joint (vmax rad/s, amax rad/s²) from the scenario file."""
    idx = list(sc.robot.planned_joints)
    return (np.radians(sc.params["trajectory.max_velocity_deg_s"])[idx],
            np.radians(sc.params["trajectory.max_acceleration_deg_s2"])[idx])
