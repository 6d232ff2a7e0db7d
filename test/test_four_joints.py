"""
A 4-joint planar chain (attitude, shoulder, elbow, wrist) planned end to end on a 4-D grid.

C-space, field, descent, smoothing and the certified check are dimension-generic.

Checked with the independent geometry of ``test_collision`` (plain-Python segment and
polygon distances), not the planner's checker.
"""
import math

import numpy as np

from spacerobot_planner.collision import CollisionChecker
from spacerobot_planner.config import Scenario
from spacerobot_planner.cspace import grid_for_robot
from spacerobot_planner.planner import Planner
from spacerobot_planner.robot import PlanarArm, square_polygon
from spacerobot_planner.scene import Scene, Target
from test_collision import ref_clearance
from test_properties import dense_samples, wrap_diff

PI = math.pi


def _four_joint_scenario(cells=24):
    robot = PlanarArm(("attitude", "shoulder", "elbow", "wrist"), (1.4, 1.6, 1.4, 1.0), (-PI,) * 4,
                      (PI,) * 4, (True, False, False, False), square_polygon(1.8, corner_first=True),
                      checked_links=(1, 2, 3))
    scene = Scene(target=Target(center_m=(-3.0, -2.4), yaw_rad=0.3),
                  debris_m=(np.array([[1.5, 2.0], [2.3, 2.0], [2.1, 2.8]]),), safety_margin_m=0.02)
    return Scenario(robot=robot, scene=scene, grid=grid_for_robot(robot, [cells] * 4),
                    start_rad=None, goal_rad=None)


def test_four_joint_chain_plans_a_collision_free_path_end_to_end():
    sc = _four_joint_scenario()
    assert sc.grid.shape == (24, 25, 25, 25)
    chk = CollisionChecker(sc.robot, sc.scene)
    rng = np.random.default_rng(3)
    q = rng.uniform(-PI, PI, size=(400, 4))
    q = q[chk.is_free(q)]
    start, goal = q[0], q[1]
    # converged is asserted: no wall-clock budget that a loaded machine could cut it with
    res = Planner(sc, field_budget_s=300.0).plan(start, goal)
    assert res.ok, res.reason
    assert res.field.log_u.ndim == 4 and res.solver_stats["converged"]
    path = res.path_rad
    assert np.array_equal(path[0], start)                         # exact ends
    assert np.all(np.abs(wrap_diff(path[-1], goal)) < 1e-12)
    assert np.array_equal(path[-1, 1:], goal[1:])
    assert np.all(np.abs(path[:, 1:]) <= PI)                      # bounded joints stay inside
    dense = dense_samples(path)
    clearance = np.array([ref_clearance(sc.robot, sc.scene, qi) for qi in dense])
    assert clearance.min() > sc.scene.safety_margin_m
    # the planner's reported clearance is a minimum at its own (sparser) check samples
    assert res.min_clearance_m >= clearance.min() - 1e-9
