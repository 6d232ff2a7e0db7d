"""
What the planner node accepts at start and as input (issue 17).

Start-up refusals (one line, no traceback), parameter files under a namespace,
unknown parameters, a goal sent before any joint_states, floods of bad input, targets
that overlap the spacecraft.  Oracles: the process's exit code and stderr, the
node's declared parameters, the action protocol, the log lines (capfd) and
/diagnostics.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys

import pytest
import rclpy
from rclpy.context import Context
from rclpy.parameter import Parameter


#: generous: a loaded 2-core machine imports rclpy and numba slowly
START_TIMEOUT_S = 120


def _run_node(*ros_args):
    """Run planner_node until it exits (killed with its process group after START_TIMEOUT_S)."""
    cmd = [sys.executable, "-m", "spacerobot_planner.ros.planner_node", "--ros-args", *ros_args]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, stdin=subprocess.DEVNULL,
                            text=True, start_new_session=True)
    try:
        out, err = proc.communicate(timeout=START_TIMEOUT_S)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        out, err = proc.communicate()
        raise AssertionError(f"planner_node did not exit within {START_TIMEOUT_S} s\n{err[-3000:]}") from None
    return subprocess.CompletedProcess(cmd, proc.returncode, out, err)


# ================================================================== 1. start-up refusals
@pytest.mark.parametrize("ros_args, fragments", [
    (["-p", "safety_margin_m:=-1.0"], ["safety_margin_m", "-1.0 is below the minimum 0.0"]),
    (["-p", "planner.solver:=multigrid"], ["planner.solver", "'multigrid' is not one of"]),
    (["-p", "grid.cells:=[36,36]"], ["grid.cells", "expected 3 values"]),
    (["-p", "safety_margin_m:=wide"], ["safety_margin_m", "expected a number"]),
], ids=["below_range", "not_a_choice", "wrong_length", "wrong_type"])
def test_refused_start_value_is_one_line_and_a_nonzero_exit(ros_args, fragments):
    proc = _run_node(*ros_args)
    err = proc.stderr
    assert proc.returncode != 0, f"exit {proc.returncode}\n{err}"
    assert "Traceback" not in err and "AttributeError" not in err, err
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1, err
    for frag in fragments:
        assert frag in lines[0], lines[0]
    assert lines[0].startswith("planner_node: "), lines[0]


def test_refused_override_raises_value_error_and_the_context_shuts_down_cleanly():
    from spacerobot_planner.ros.planner_node import PlannerNode
    ctx = Context()
    rclpy.init(context=ctx)
    try:
        with pytest.raises(ValueError, match=r"safety_margin_m: -1.0 is below the minimum 0.0"):
            PlannerNode(context=ctx, parameter_overrides=[Parameter("safety_margin_m", value=-1.0)])
    finally:
        rclpy.shutdown(context=ctx)       # destroys the half-made node: no AttributeError
