"""The ROS 2 install layout: `make venv` lays it out in .venv; ament_install does the same anywhere."""

import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
PKG = "spacerobot_planner"


def _check_prefix(prefix: Path):
    assert (prefix / "share/ament_index/resource_index/packages" / PKG).is_file()
    assert (prefix / "share" / PKG / "package.xml").is_file()
    assert (prefix / "share" / PKG / "config/paper_3dof.yaml").is_file()
    for exe in ("planner_node", "mock_arm_node"):
        path = prefix / "lib" / PKG / exe
        assert path.is_file() and os.access(path, os.X_OK), f"{path} is not executable"


def test_venv_has_the_ament_layout():
    venv = ROOT / ".venv"
    if not (venv / ".installed").exists():
        pytest.skip("run `make venv` first")
    _check_prefix(venv)


def test_ament_install_into_a_temp_prefix(tmp_path):
    r = subprocess.run([sys.executable, "-m", "spacerobot_planner.tools.ament_install", "--prefix", str(tmp_path)],
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    _check_prefix(tmp_path)
    launcher = (tmp_path / "lib" / PKG / "planner_node").read_text()
    assert "spacerobot_planner.ros.planner_node" in launcher and "main" in launcher
