"""
The trajectory stage of a scenario: the path in time, and the spacecraft's verdict on it.

:func:`timed_motion` (the pipeline's last stage, the node's replan joins and the CLI)
time-parameterises a planned path with the scenario's joint limits
(``Scenario.joint_limits``) and, with the attitude held and wheel limits set, the wheel
momentum and torque (``spacecraft.WheelModel``); where the ACS settings make the reaction
matter (free floating, wheel limits) it also reports it (``reaction.reaction_report``):
:func:`plan_motion`.  No ROS imports.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .joint_space import align_to_state
from .reaction import ReactionReport, reaction_report
from .spacecraft import WheelModel
from .trajectory import time_parameterize

__all__ = ["Motion", "plan_motion", "timed_motion", "reaction_of", "reaction_matters", "scenario_joint_limits",
           "trajectory_limits_known"]


@dataclass(frozen=True, eq=False)
class Motion:
    """
    A planned path in time and the spacecraft's reaction to it.

    Attributes
    ----------
        trajectory: ``trajectory.Trajectory`` over the planned joints.
        reaction: ReactionReport (``reaction.ok`` False: refuse the plan, ``reaction.reason``).

    """

    trajectory: object
    reaction: ReactionReport

    def to_json_dict(self) -> dict:
        return {"trajectory": self.trajectory.to_json_dict(), "reaction": self.reaction.to_json_dict()}


def scenario_joint_limits(scenario):
    """
    Return the planned joints' limits and scalings (``Scenario.joint_limits``).

    (max velocity (dof,) rad/s, max acceleration (dof,) rad/s², velocity scaling, acceleration
    scaling); ValueError when the scenario states no joint limits.
    """
    limits = scenario.joint_limits
    if limits is None:
        raise ValueError("trajectory.max_velocity_deg_s, trajectory.max_acceleration_deg_s2: the scenario "
                         "states no joint limits (no trajectory)")
    vmax, amax = limits.planned(scenario.robot)
    return vmax, amax, limits.velocity_scaling, limits.acceleration_scaling


def plan_motion(scenario, path_rad, *, start_velocity_rad_s=None, start_path_speed=None, start_tangent=None,
                motions=None, brake_to_limits: bool = False) -> Motion:
    """
    Time-parameterise a planned path with the scenario's limits and report the reaction.

    The joint limits and scaling factors are ``Scenario.joint_limits``; with ``acs.mode``
    held and a wheel limit set (``acs.max_wheel_*``), the wheel momentum and torque
    enter the time-optimal parameterisation.  The reaction report then says whether
    the plan is acceptable (free floating: the drifted arm is checked against the
    inertial scene, the tip miss against ``grasp.position_tolerance_m`` and, at the grasp
    point, the approach against ``grasp.max_approach_error_deg``).

    Args:
        scenario: ``problem.Scenario`` (robot, scene, masses, acs, joint_limits).
        path_rad: (M, dof) the planned path (unwrapped, exact ends).
        start_velocity_rad_s, start_path_speed, start_tangent: a moving start (see
            ``trajectory.time_parameterize``); default at rest.
        motions: the scene's ``motion.MotionValidator``, for the drift check (made when None).
        brake_to_limits: a moving start above the velocity limits brakes to them
            (``trajectory.time_parameterize``).

    Returns
    -------
        Motion(trajectory, reaction).

    Raises
    ------
        ValueError: bad limits or a start velocity the path cannot be followed with.

    """
    traj = _wheel_timed(scenario, path_rad, start_velocity_rad_s, start_path_speed, start_tangent, brake_to_limits)
    return Motion(traj, _report(scenario, path_rad, traj, motions))


def _wheel_timed(scenario, path_rad, start_velocity_rad_s=None, start_path_speed=None, start_tangent=None,
                 brake_to_limits: bool = False):
    """:func:`plan_motion`'s trajectory (the wheel limits in the time-optimal parameterisation)."""
    robot, acs = scenario.robot, scenario.acs
    vmax, amax, vs, as_ = scenario_joint_limits(scenario)
    wheel = WheelModel(robot, scenario.masses, *acs.timed_wheel_limits)
    lo, hi = robot.planned_bounds_rad
    return time_parameterize(path_rad, vmax, amax, robot.planned_names, velocity_scaling=vs,
                             acceleration_scaling=as_, start_velocity_rad_s=start_velocity_rad_s,
                             start_path_speed=start_path_speed, start_tangent=start_tangent, wheel=wheel,
                             lowered=scenario.joint_limits.lowered, brake_to_limits=brake_to_limits,
                             lower_rad=lo, upper_rad=hi)


def _report(scenario, path_rad, traj, motions=None) -> ReactionReport:
    """:func:`plan_motion`'s reaction report of ``traj`` along ``path_rad``."""
    acs = scenario.acs
    return reaction_report(scenario.robot, scenario.masses, scenario.scene, path_rad, traj, acs_mode=acs.mode,
                           max_wheel_momentum_Nms=acs.max_wheel_momentum_Nms,
                           max_wheel_torque_Nm=acs.max_wheel_torque_Nm,
                           position_tolerance_m=acs.position_tolerance_m,
                           max_approach_error_deg=scenario.planner_settings.max_approach_error_deg,
                           motions=motions)


def reaction_matters(scenario) -> bool:
    """Tell whether the scenario's ACS settings make the reaction matter (free floating, wheel limits)."""
    return scenario.acs.mode != "held" or scenario.acs.has_wheel_limits


def reaction_of(scenario, path_rad, traj, state_rad=None, motions=None) -> ReactionReport:
    """
    Return the reaction report :func:`timed_motion` gives with ``traj`` (its trajectory of ``path_rad``).

    For a trajectory from ``timed_motion(..., report=False)`` with the same path, state and a
    scenario that differs at most in its scaling factors, the joints' or the wheels', and its
    lowered stretches (``JointLimits.lowered``; the report does not read them: it judges the
    limits themselves).
    """
    path = np.asarray(path_rad, dtype=float)
    if state_rad is not None:
        path = align_to_state(path, state_rad, scenario.robot.planned_periodic)
    return _report(scenario, path, traj, motions)


def trajectory_limits_known(scenario) -> bool:
    """Tell whether the scenario states joint velocity and acceleration limits (``trajectory.*``)."""
    return scenario.joint_limits is not None


def timed_motion(scenario, path_rad, state_rad=None, reaction: bool | None = None, start_path_speed: float = 0.0,
                 motions=None, report: bool = True, start_tangent=None, brake_to_limits: bool = False):
    """
    Run the last core stage: the path in time (MoveIt's adapter order), for the CLI and the node.

    Args:
        scenario: ``problem.Scenario`` (its joint_limits, masses and ACS settings).
        path_rad: (M, dof) the planned path (unwrapped, exact ends).
        state_rad: (dof,) the arm's current joint positions (any number of turns on
            periodic joints); the path is first shifted by whole turns to start there
            (``joint_space.align_to_state``).  Default: the path's first row.
        reaction: also report the spacecraft's reaction (``plan_motion``);
            None: when the scenario has ACS or wheel settings (free floating, wheel
            limits), where the reaction shapes or refuses the trajectory.
        start_path_speed: the arm's speed along the path at its start (rad/s of joint-space
            chord length; a replan joined to a moving arm, see ``trajectory.continuation``).
        motions: the scene's ``motion.MotionValidator`` (the reaction's drift check; made
            when None and needed).
        report: False: the same trajectory, the report left out (None; :func:`reaction_of`
            makes it later, e.g. for the one of several re-timings that is kept).
        start_tangent: (dof,) the direction the path leaves its start along (the arm's
            velocity over ``start_path_speed``; ``trajectory.time_parameterize``), or None.
        brake_to_limits: a start speed above the velocity limits brakes to them instead of
            being refused (``trajectory.time_parameterize``: limits lowered while the arm moves).

    Returns
    -------
        (trajectory.Trajectory, reaction.ReactionReport or None).

    Raises
    ------
        ValueError: no joint limits or bad ones (naming the parameter), or a start speed the
            path cannot be followed with (``trajectory.time_parameterize``).

    """
    robot = scenario.robot
    path = np.asarray(path_rad, dtype=float)
    if state_rad is not None:
        path = align_to_state(path, state_rad, robot.planned_periodic)
    if reaction is None:
        reaction = reaction_matters(scenario)
    if reaction and not report:
        return _wheel_timed(scenario, path, start_path_speed=start_path_speed, start_tangent=start_tangent,
                            brake_to_limits=brake_to_limits), None
    if reaction:
        motion = plan_motion(scenario, path, start_path_speed=start_path_speed, start_tangent=start_tangent,
                             motions=motions, brake_to_limits=brake_to_limits)
        return motion.trajectory, motion.reaction
    vmax, amax, vs, as_ = scenario_joint_limits(scenario)
    lo, hi = robot.planned_bounds_rad
    return time_parameterize(path, vmax, amax, robot.planned_names, velocity_scaling=vs,
                             acceleration_scaling=as_, start_path_speed=start_path_speed,
                             start_tangent=start_tangent, lowered=scenario.joint_limits.lowered,
                             brake_to_limits=brake_to_limits, lower_rad=lo, upper_rad=hi), None
