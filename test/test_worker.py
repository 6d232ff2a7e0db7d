"""
The planning worker without ROS.

The process loads no rclpy, plans, and a cancel ends even an uninterruptible stage (an injected
stall) by replacing the process.
"""

from __future__ import annotations

import os
import time

import numpy as np
import pytest

from spacerobot_planner.config import load_scenario
from spacerobot_planner.worker import PlanDone, PlanError, PlanJob, ProcessBackend, ThreadBackend
from conftest import CONFIG_DIR

CANCEL_BOUND_S = 1.0          # the bound for a cancel


def _job(sc, gen, **kw):
    return PlanJob(gen=gen, scene=sc.scene, grid=sc.grid, solver="log_harmonic", field_tolerance=1e-6,
                   max_grid_nodes=4_000_000, start_rad=sc.start_rad, joint_goal=kw.pop("joint_goal", None), **kw)


def _mapped_libraries(pid):
    with open(f"/proc/{pid}/maps") as f:
        return {line.split()[-1] for line in f if "/" in line}


@pytest.fixture(scope="module")
def backend():
    sc = load_scenario(os.path.join(CONFIG_DIR, "paper_3dof.yaml"))
    b = ProcessBackend(sc)
    assert b.wait_ready(300) is not None
    yield sc, b
    b.close()


def test_planning_process_never_imports_rclpy_or_messages(backend):
    sc, b = backend
    mods = set(b.ready.modules)
    assert "numpy" in mods and "spacerobot_planner" in mods     # the report is real
    ros = sorted(m for m in mods if m.startswith(("rclpy", "rcl", "rosidl")) or m.endswith("_msgs")
                 or m.endswith("_interfaces"))
    assert ros == [], f"the planning process imported {ros}"
    # a second oracle, from outside the process: no ROS shared library is mapped
    libs = [p for p in _mapped_libraries(b.pid) if "/librcl" in p or "rclpy" in p or "rosidl" in p
            or "_msgs" in p]
    assert libs == [], libs


def test_process_plans_and_reports_progress(backend):
    sc, b = backend
    stages = []
    out = b.run(_job(sc, 1), progress=lambda p: stages.append((p.stage, p.fraction)))
    assert isinstance(out, PlanDone) and out.result.ok, out
    # the path ends at the target's capture posture, checked on the robot's own kinematics
    tip = sc.robot.tip_position(sc.robot.full(out.result.path_rad[-1]))
    assert np.linalg.norm(tip - sc.scene.target.grasp_point_m) < 1e-6
    names = [s for s, _ in stages]
    assert names[0] == "cspace" and "field" in names and "verify" in names
    fractions = [f for _, f in stages]
    assert fractions == sorted(fractions) and 0.0 <= fractions[0] and fractions[-1] < 1.0


def test_unreachable_target_is_a_plan_error(backend):
    sc, b = backend
    far = sc.scene.with_target(sc.scene.target.__class__(center_m=(9.0, 9.0)))
    job = PlanJob(gen=2, scene=far, grid=sc.grid, solver="log_harmonic", field_tolerance=1e-6,
                  max_grid_nodes=4_000_000, start_rad=sc.start_rad, joint_goal=None)
    out = b.run(job)
    assert isinstance(out, PlanError) and out.code == "goal_unreachable" and "out of the arm's reach" in out.reason


def test_cancel_ends_an_uninterruptible_stage_and_a_fresh_process_plans(backend, record_property):
    import threading
    sc, b = backend
    old = b.pid
    result = {}

    def run():
        result["out"] = b.run(_job(sc, 3, stall_s=60.0))
        result["t"] = time.monotonic()

    t = threading.Thread(target=run)
    t.start()
    time.sleep(0.5)                     # inside the stall
    t_cancel = time.monotonic()
    b.cancel(3)
    t.join(10)
    dt = result["t"] - t_cancel
    print(f"\ncancel during a stalled stage: {dt:.3f} s")
    record_property("cancel_stalled_stage_s", round(dt, 3))
    out = result["out"]
    assert isinstance(out, PlanError) and out.code == "cancelled", out
    assert dt < CANCEL_BOUND_S
    assert b.pid != old                 # replaced
    out = b.run(_job(sc, 4))
    assert isinstance(out, PlanDone) and out.result.ok


def test_thread_backend_plans_the_same_job():
    sc = load_scenario(os.path.join(CONFIG_DIR, "paper_2dof.yaml"))
    out = ThreadBackend(sc).run(_job(sc, 1, joint_goal=sc.goal_rad))
    assert isinstance(out, PlanDone) and out.result.ok
    np.testing.assert_allclose(out.result.path_rad[-1], sc.goal_rad, atol=1e-9)


def test_planning_process_imports_the_callers_package_not_the_working_directorys(tmp_path, monkeypatch):
    """
    The planning process imports the node's copy of the package.

    Started from a folder holding another ``spacerobot_planner`` (a source tree next to an install),
    the planning process still imports the node's copy.
    """
    decoy = tmp_path / "spacerobot_planner"
    decoy.mkdir()
    (decoy / "__init__.py").write_text('raise ImportError("the decoy package in the working directory")\n')
    monkeypatch.chdir(tmp_path)
    sc = load_scenario(os.path.join(CONFIG_DIR, "paper_2dof.yaml"))
    b = ProcessBackend(sc)
    try:
        assert b.wait_ready(300) is not None
        out = b.run(_job(sc, 1, joint_goal=sc.goal_rad))
        assert isinstance(out, PlanDone) and out.result.ok
    finally:
        b.close()
