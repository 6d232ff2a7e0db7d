"""
The demo (``make demo``: ``python -m spacerobot_planner.tools.demo``) on what a newcomer tries beside the paper's scene.

Its closed loop to the goal is ``make demo``'s (test_docs_commands.py) and the node tests'; here
what it does with a target the planner refuses and an ``--out`` it cannot write in (a
newcomer audit: it waited its whole timeout, then said only "timed out"; it crashed mid-loop).
"""

import subprocess
import sys

#: generous: a loaded 2-core machine imports rclpy and numba slowly (the demo's own --timeout is larger)
RUN_TIMEOUT_S = 120


def _demo(*args, cwd):
    return subprocess.run([sys.executable, "-m", "spacerobot_planner.tools.demo", *args], capture_output=True,
                          text=True, stdin=subprocess.DEVNULL, timeout=RUN_TIMEOUT_S, cwd=cwd)


def test_a_target_the_planner_refuses_ends_the_demo_saying_why(tmp_path):
    """A target on the spacecraft: exit 1 with the planner's reason, not after its --timeout (an hour here)."""
    proc = _demo("--target", "0", "0", "--timeout", "3600", "--out", str(tmp_path / "out"), cwd=tmp_path)
    assert proc.returncode == 1, proc.stderr[-3000:]
    said = [line for line in proc.stderr.splitlines() if line.startswith("[demo] FAILED: ")]
    assert len(said) == 1 and "the planner refused the target (invalid_input)" in said[0], proc.stderr[-3000:]
    assert "overlaps the spacecraft body" in said[0], said


def test_an_out_that_is_a_file_is_refused_before_the_loop(tmp_path):
    (tmp_path / "taken").write_text("x")
    proc = _demo("--out", str(tmp_path / "taken" / "figs"), cwd=tmp_path)
    assert proc.returncode == 2 and f"--out: {tmp_path / 'taken' / 'figs'}: " in proc.stderr, proc.stderr[-3000:]
    assert "is a file, not a folder" in proc.stderr and "Traceback" not in proc.stderr, proc.stderr[-3000:]
    assert "[demo] planner up" not in proc.stdout, proc.stdout
