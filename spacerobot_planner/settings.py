"""
Typed settings: how the planner plans, the arm's joint limits, how a capture session replans.

``config.py`` is the only reader of the dotted parameter names (``config.PARAMETERS``:
names, defaults, ranges): it parses a parameter file once into these dataclasses, which
the core reads as attributes.  They validate themselves (so do the spacecraft's,
``spacecraft.MassProperties`` and ``spacecraft.AcsSettings``), for the scenarios that
tests and tools build directly.  Their defaults are the schema's (the paper's scenes).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .field import DEFAULT_BUDGET_S, DEFAULT_SOLVER, INTERNAL_SOLVERS, SOLVERS
from .motion import DEFAULT_VERIFY_STEP_RAD
from .smoothing import DEFAULT_MAX_STEP_RAD

__all__ = ["PlannerSettings", "JointLimits", "SessionSettings", "CONTROLLER_SWITCHES", "SWITCH_UNTIL_FOUND"]


def _positive(name, value, allow_zero=False) -> float:
    v = float(value)
    if not (math.isfinite(v) and (v >= 0.0 if allow_zero else v > 0.0)):
        raise ValueError(f"{name}: must be a {'non-negative' if allow_zero else 'positive'} number, "
                         f"got {value!r}")
    return v


@dataclass(frozen=True)
class PlannerSettings:
    """
    How the planner plans (immutable; ``Planner.configure`` makes a new one).

    From the parameters (``config.settings_from_params``): ``planner.solver``,
    ``planner.field_tolerance``, ``planner.field_budget_s``, ``planner.max_grid_nodes``,
    ``planner.max_start_penetration_m``, ``grasp.max_approach_error_deg``; the others are
    the planner's own.

    Attributes
    ----------
        solver: field solver name (``field.SOLVERS``).
        field_tolerance: gauss_seidel's stopping tolerance (largest change per sweep).
        field_budget_s: wall-time budget of one field solve (log_harmonic), seconds.
        max_grid_nodes: refuse larger grids (before allocating).
        max_threads: the most threads a plan's parallel kernels use; 0: numba's own number (one per
            core, or ``NUMBA_NUM_THREADS``).  No more than the process's CPU limit, and on large
            grids (and a first repair's swept edges on any) fewer while other work keeps the cores
            busy (``cores.fit_threads``).
        threads_follow_load: whether the stages take no more threads than the CPU limit and, on
            large grids (a first repair's swept edges: any), fewer while other work keeps cores busy
            (False: always ``max_threads``).
        grid_extra_margin_m: added to the safety margin for the grid only, metres (the
            planner retries at 0 before answering ``disconnected``).
        shortcut: try a shortcut spline before the paper's every-second-node spline.
        shortcut_keep_clearance_m: shortcuts keep at least margin + this (or the
            clearance of the stretch they replace, if smaller), metres.
        max_step_rad: spacing of the returned samples (≤ 0.5°).
        verify_step_rad: largest spacing of the certified collision checks along the path.
        max_repairs: edge-cutting / node-blocking re-solves allowed on one grid.
        max_refinements: how many times a plan may refine the grid (twice the cells per
            joint, or as many more as the node limits allow, at least 1.25 times:
            ``pipeline.refined``) where a grid does not join start and goal or gives no
            verified path (0: never).
        refine_after_repairs: on a grid that a finer one may follow, refine after this many
            repairs instead of repairing further.
        max_refined_nodes: a refined grid is tried only up to this many nodes (72³ is
            389 017; a 4-joint grid of 16 cells per joint is refined to 25, 439 400 nodes,
            not doubled, 1.15 million).
        max_start_penetration_m: a start whose links reach at most this deep into an
            obstacle is walked out of the contact first (0: refuse as start_in_collision).
        max_approach_error_deg: largest angle between link 3 and the handle's inward
            normal accepted for a goal from the target's IK.
        trajectory: run the trajectory stage when the scenario states joint limits.
        reaction: report the spacecraft's reaction with the trajectory (None: when the
            scenario has ACS or wheel settings).

    """

    solver: str = DEFAULT_SOLVER
    field_tolerance: float = 1e-6
    field_budget_s: float = DEFAULT_BUDGET_S
    max_grid_nodes: int = 4_000_000
    max_threads: int = 0
    threads_follow_load: bool = True
    grid_extra_margin_m: float = 0.02
    shortcut: bool = True
    shortcut_keep_clearance_m: float = 0.05
    max_step_rad: float = DEFAULT_MAX_STEP_RAD
    verify_step_rad: float = DEFAULT_VERIFY_STEP_RAD
    max_repairs: int = 30
    max_refinements: int = 1
    refine_after_repairs: int = 8
    max_refined_nodes: int = 500_000
    max_start_penetration_m: float = 0.05
    max_approach_error_deg: float = 5.0
    trajectory: bool = True
    reaction: bool | None = None

    def __post_init__(self):
        if self.solver not in SOLVERS + INTERNAL_SOLVERS:
            raise ValueError(f"planner.solver: unknown solver {self.solver!r}; expected one of {list(SOLVERS)}")
        set_ = object.__setattr__
        set_(self, "field_tolerance", _positive("planner.field_tolerance", self.field_tolerance))
        set_(self, "field_budget_s", _positive("planner.field_budget_s", self.field_budget_s))
        if isinstance(self.max_grid_nodes, bool) or int(self.max_grid_nodes) != self.max_grid_nodes \
                or self.max_grid_nodes < 1:
            raise ValueError(f"planner.max_grid_nodes: must be a positive integer, got {self.max_grid_nodes!r}")
        set_(self, "max_grid_nodes", int(self.max_grid_nodes))
        for name in ("grid_extra_margin_m", "shortcut_keep_clearance_m", "max_start_penetration_m",
                     "max_approach_error_deg"):
            set_(self, name, _positive(name, getattr(self, name), allow_zero=True))
        for name in ("max_step_rad", "verify_step_rad"):
            set_(self, name, _positive(name, getattr(self, name)))
        for name in ("max_repairs", "max_refinements", "refine_after_repairs", "max_refined_nodes", "max_threads"):
            v = getattr(self, name)
            if isinstance(v, bool) or int(v) != v or v < 0:
                raise ValueError(f"{name}: must be an integer ≥ 0, got {v!r}")
            set_(self, name, int(v))


@dataclass(frozen=True)
class JointLimits:
    """
    The trajectory's joint limits (``trajectory.*``), one per joint of ``robot.joint_names``.

    Attributes
    ----------
        max_velocity_rad_s: (n,) velocity limit per joint, rad/s, > 0.
        max_acceleration_rad_s2: (n,) acceleration limit per joint, rad/s², > 0.
        velocity_scaling, acceleration_scaling: factors in (0, 1] on every limit
            (MoveIt's max_velocity_scaling_factor, max_acceleration_scaling_factor).
        lowered: ``trajectory.Lowering`` stretches of the path where the limits (the joints'
            and the wheels') are lower still: the chain's re-timings, where the controller's
            interpolation overshot them (``adapters``); not a parameter, () from a file.
        A scenario without them (``Scenario.joint_limits`` None) plans paths, not trajectories.

    """

    max_velocity_rad_s: tuple
    max_acceleration_rad_s2: tuple
    velocity_scaling: float = 1.0
    acceleration_scaling: float = 1.0
    lowered: tuple = ()

    def __post_init__(self):
        set_ = object.__setattr__
        for name, key in (("max_velocity_rad_s", "trajectory.max_velocity_deg_s"),
                          ("max_acceleration_rad_s2", "trajectory.max_acceleration_deg_s2")):
            vals = tuple(float(v) for v in np.atleast_1d(np.asarray(getattr(self, name), dtype=float)))
            if not vals or not all(math.isfinite(v) and v > 0.0 for v in vals):
                raise ValueError(f"{key}: expected positive finite limits, got {list(vals)}")
            set_(self, name, vals)
        if len(self.max_velocity_rad_s) != len(self.max_acceleration_rad_s2):
            raise ValueError(f"trajectory.max_acceleration_deg_s2: expected {len(self.max_velocity_rad_s)} values "
                             f"(like trajectory.max_velocity_deg_s), got {len(self.max_acceleration_rad_s2)}")
        for name, key in (("velocity_scaling", "trajectory.max_velocity_scaling_factor"),
                          ("acceleration_scaling", "trajectory.max_acceleration_scaling_factor")):
            v = float(getattr(self, name))
            if not (math.isfinite(v) and 0.0 < v <= 1.0):
                raise ValueError(f"{key}: must be in (0, 1], got {v}")
            set_(self, name, v)

    def check_robot(self, robot) -> None:
        """Raise ValueError when there is not one limit per joint of the robot."""
        for key, vals in (("trajectory.max_velocity_deg_s", self.max_velocity_rad_s),
                          ("trajectory.max_acceleration_deg_s2", self.max_acceleration_rad_s2)):
            if len(vals) != robot.n_joints:
                raise ValueError(f"{key}: expected {robot.n_joints} values (one per joint in robot.joint_names), "
                                 f"got {len(vals)}")

    def planned(self, robot) -> tuple:
        """Return (max velocity (dof,) rad/s, max acceleration (dof,) rad/s²) of the planned joints, unscaled."""
        self.check_robot(robot)
        idx = list(robot.planned_joints)
        return (np.asarray(self.max_velocity_rad_s)[idx], np.asarray(self.max_acceleration_rad_s2)[idx])


#: ``controller.switch``: when the arm's trajectory controller takes a newer trajectory over: at its stamp
#: (ros2_controllers' joint_trajectory_controller from 6.8 on, ``allow_trajectory_replacement``; the mock
#: arm's default) or at its arrival, going from its state then to the first point (before 6.8: Kilted, Jazzy);
#: ``auto``: as the subscribers of ``joint_trajectory`` say (``ros.controller_probe``), ``SWITCH_UNTIL_FOUND``
#: until one does
CONTROLLER_SWITCHES = ("auto", "stamp", "arrival")
#: what ``controller.switch: auto`` assumes while no subscriber has said which kind it is (the mock arm's
#: default, and the one whose mistake on the other kind is a connecting stretch, not a step back)
SWITCH_UNTIL_FOUND = "stamp"


@dataclass(frozen=True)
class SessionSettings:
    """
    How a capture session (``session.py``) replans a moving arm and stamps what it publishes.

    From the parameters (``config.session_settings_from_params``): ``replan.*``,
    ``trajectory.start_lead_s``, ``planner.test_stall_s``, ``controller.switch``.

    Attributes
    ----------
        horizon_s: a replan while a trajectory executes starts this far ahead on it, s (0: never join).
        follow_tolerance_rad: largest per-joint distance of the measured state from the executing
            trajectory for the arm to count as following it, rad.
        min_publish_period_s: under a stream of topic requests, a plan in progress is let finish
            (not superseded) once nothing was published for this long, s (0: latest always wins).
        start_lead_s: every published trajectory starts (its stamp) at least this long after it is
            published, s.
        target_tolerance_m, target_tolerance_deg: a topic target this close to the current one
            is not a new request (metres, degrees).
        test_stall_s: testing aid, the planning process stalls this long before each plan, s.
        controller_switch: when the arm's controller takes a newer trajectory over, "stamp",
            "arrival" (``adapters.switching_at_arrival``) or "auto" (as the node finds the controller:
            ``CaptureSession.controller_found``) (:data:`CONTROLLER_SWITCHES`).

    """

    horizon_s: float = 1.0
    follow_tolerance_rad: float = math.radians(2.0)
    min_publish_period_s: float = 1.0
    start_lead_s: float = 0.35
    target_tolerance_m: float = 0.005
    target_tolerance_deg: float = 0.5
    test_stall_s: float = 0.0
    controller_switch: str = "auto"

    def __post_init__(self):
        for name in ("horizon_s", "follow_tolerance_rad", "min_publish_period_s", "start_lead_s",
                     "target_tolerance_m", "target_tolerance_deg", "test_stall_s"):
            object.__setattr__(self, name, _positive(name, getattr(self, name), allow_zero=True))
        if self.controller_switch not in CONTROLLER_SWITCHES:
            raise ValueError(f"controller.switch: expected one of {', '.join(CONTROLLER_SWITCHES)}, got "
                             f"{self.controller_switch!r}")
