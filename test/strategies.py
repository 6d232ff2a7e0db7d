"""
Hypothesis strategies for random planning scenes (issue: reliability).

Scenes: 0–6 debris polygons (convex and star-shaped non-convex, 0.1–1.5 m across)
scattered around the robot, a target satellite at a random pose within reach, a random
safety margin, random start postures; 2-DOF (attitude locked) and 3-DOF; grids from
coarse to fine.
"""

import os

from conftest import CONFIG_DIR
import math

import numpy as np
from hypothesis import strategies as st

from spacerobot_planner.config import load_scenario
from spacerobot_planner.scene import Scene, Target

PAPER = {dof: load_scenario(os.path.join(CONFIG_DIR, f"paper_{dof}dof.yaml")) for dof in (2, 3)}
CELLS = {2: (60, 90, 120, 180), 3: (18, 24, 36)}


@st.composite
def polygons(draw):
    """One debris polygon (k×2, metres): convex, or star-shaped and non-convex."""
    size = draw(st.floats(0.1, 1.5))
    k = draw(st.integers(3, 8))
    convex = draw(st.booleans()) or k < 5
    angles = np.sort(np.array(draw(st.lists(st.floats(0.0, 2 * math.pi), min_size=k, max_size=k,
                                            unique=True))))
    if np.min(np.diff(np.r_[angles, angles[0] + 2 * math.pi])) < 0.05:
        angles = np.linspace(0.0, 2 * math.pi, k, endpoint=False) + angles[0]
    radius = 0.5 * size * (np.ones(k) if convex
                           else np.where(np.arange(k) % 2 == 0, 1.0, draw(st.floats(0.3, 0.7))))
    # keep the centre outside the spacecraft body; debris anywhere the arm can reach
    r_c = draw(st.floats(1.6, 6.0))
    a_c = draw(st.floats(-math.pi, math.pi))
    centre = r_c * np.array([math.cos(a_c), math.sin(a_c)])
    return centre + np.stack([radius * np.cos(angles), radius * np.sin(angles)], axis=1)


@st.composite
def targets(draw):
    r = draw(st.floats(2.5, 5.2))
    a = draw(st.floats(-math.pi, math.pi))
    yaw = draw(st.floats(-math.pi, math.pi))
    return Target(center_m=(r * math.cos(a), r * math.sin(a)), yaw_rad=yaw)


@st.composite
def scenarios(draw, dof=None):
    """(scenario, start_rad): a random scene on the paper's robot, and a start posture."""
    dof = draw(st.sampled_from((2, 3))) if dof is None else dof
    base = PAPER[dof]
    debris = tuple(draw(st.lists(polygons(), min_size=0, max_size=6)))
    scene = Scene(target=draw(targets()), debris_m=debris,
                  safety_margin_m=draw(st.sampled_from((0.0, 0.01, 0.02, 0.05))))
    cells = draw(st.sampled_from(CELLS[dof]))
    sc = base.with_scene(scene)
    from dataclasses import replace
    sc = replace(sc, grid=sc.grid_with_cells(cells))
    # mostly collision-free starts (the interesting case), sometimes any posture
    start = random_configuration(sc, draw(st.integers(0, 2**31 - 1)),
                                 free=draw(st.sampled_from((True, True, True, False))))
    return sc, start


def random_configuration(sc, seed: int, free: bool = True, tries: int = 200) -> np.ndarray:
    """
    Return a uniform random planned configuration (rad).

    With ``free``, the first of ``tries`` samples that is collision-free (else the last sample).
    """
    from spacerobot_planner.collision import CollisionChecker
    rng = np.random.default_rng(seed)
    lo, hi = sc.robot.planned_lower_rad, sc.robot.planned_upper_rad
    q = rng.uniform(lo, hi, size=(tries, len(lo)))
    if not free:
        return q[0]
    ok = CollisionChecker(sc.robot, sc.scene).is_free(q)
    return q[int(np.argmax(ok))] if ok.any() else q[-1]
