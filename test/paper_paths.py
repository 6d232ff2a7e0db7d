"""Joint limits of the paper's scenes (their paths: the ``paper_path`` fixture, conftest.py), and a new path."""

import numpy as np
from scipy.interpolate import CubicSpline


def joint_limits(sc):
    """Planned-joint (vmax rad/s, amax rad/s²) from the scenario file."""
    idx = list(sc.robot.planned_joints)
    return (np.radians(sc.params["trajectory.max_velocity_deg_s"])[idx],
            np.radians(sc.params["trajectory.max_acceleration_deg_s2"])[idx])


def turned(u, turn_deg):
    """Return the unit 3-vector ``turn_deg`` off ``u`` (3,), in the plane of ``u`` and ``u`` × z."""
    u = np.asarray(u, dtype=float) / np.linalg.norm(u)
    w = np.cross(u, [0.0, 0.0, 1.0])
    return np.cos(np.radians(turn_deg)) * u + np.sin(np.radians(turn_deg)) * w / np.linalg.norm(w)


def new_path_from(a, turn_deg=(20.0, -15.0, 10.0)):
    """Return a smooth 3-joint path from ``a`` (exactly) to ``a + turn_deg``, rad, 200 points: a replan's new path."""
    goal = a + np.radians(turn_deg)
    knots = np.vstack([a, a + 0.5 * (goal - a) + np.radians([5.0, 5.0, -5.0]), goal])
    new = CubicSpline([0.0, 0.5, 1.0], knots)(np.linspace(0.0, 1.0, 200))
    new[0] = a
    return new
