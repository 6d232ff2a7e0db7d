"""
ROS time that jumps back or changes its source, and ROS time before the first ``/clock``.

Under ``use_sim_time`` a node's ROS time is what ``/clock`` says: a bag played again
(``ros2 bag play --clock`` restarted) or a simulator reset sends it back, and switching
``use_sim_time`` at runtime changes its source.  Every stamp taken before (the trajectory last
sent, the joint states') then belongs to another time: the planner forgets the trajectory it sent
(``session.CaptureSession.time_jumped``: else it joins the next plan to it, stamped where the old
time was, minutes ahead, while the arm waits), and the mock arm stops where it is.  Before the
first ``/clock`` message ROS time reads 0: a trajectory stamped then starts in the past of
every clock that runs.
"""

from __future__ import annotations

from rclpy.clock import ClockChange, JumpThreshold
from rclpy.duration import Duration

__all__ = ["CLOCK_JUMP_BACK_S", "on_time_jumps", "jump_text", "no_clock_yet"]

#: a jump of ROS time back by more than this, s, is a new time (smaller ones: jitter between clock sources)
CLOCK_JUMP_BACK_S = 0.1


def jump_text(jump) -> str:
    """Say what a ``rclpy.clock.TimeJump`` was: 'jumped back 508.2 s ...' or the change of source."""
    if jump.clock_change == ClockChange.ROS_TIME_ACTIVATED:
        return "now follows /clock (use_sim_time true)"
    if jump.clock_change == ClockChange.ROS_TIME_DEACTIVATED:
        return "now follows the system clock (use_sim_time false)"
    return (f"jumped back {-1e-9 * jump.delta.nanoseconds:.3f} s (/clock started again: a bag played "
            "again, a simulator reset?)")


def on_time_jumps(node, callback, before=None):
    """
    Call ``callback(text)`` when ``node``'s ROS time jumps back (more than :data:`CLOCK_JUMP_BACK_S`) or changes source.

    ``text``: :func:`jump_text`; ``before()`` (optional) is called first, before the time changes.
    Returns the jump handle: keep it (rclpy drops the callbacks with it); called in the thread
    that sets the time (the executor's, ``/clock``'s callback).
    """
    threshold = JumpThreshold(min_forward=None, min_backward=Duration(nanoseconds=-int(CLOCK_JUMP_BACK_S * 1e9)),
                              on_clock_change=True)
    return node.get_clock().create_jump_callback(threshold, pre_callback=before,
                                                 post_callback=lambda jump: callback(jump_text(jump)))


def no_clock_yet(clock) -> bool:
    """Tell whether ``clock`` follows ``/clock`` (use_sim_time) and none has come yet (its time reads 0)."""
    return bool(clock.ros_time_is_active) and clock.now().nanoseconds == 0
