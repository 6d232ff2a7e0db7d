"""
The ament linters that ros2/examples packages run, over the package, the tests and setup.py.

- ament_flake8, line length: the project's 120 (ament's default is 99);
- ament_pep257, the ament convention (pydocstyle with D100-D107, D203, D212 and D404
  ignored): a summary line of its own on the docstring's second line, ending with a period,
  a blank line after it, and the closing quotes on a line of their own.

Every file is checked.
"""

import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
PATHS = [str(ROOT / p) for p in ("spacerobot_planner", "test", "setup.py")]


@pytest.mark.flake8
@pytest.mark.linter
def test_flake8():
    # in a process of its own: flake8 forks its workers, and a fork of this process after the
    # in-process rclpy tests (their threads) has crashed them (a segfault, then a hang)
    pytest.importorskip("ament_flake8.main")
    run = subprocess.run([sys.executable, "-c", "import sys; from ament_flake8.main import main; "
                          "sys.exit(main(sys.argv[1:]))", "--linelength", "120", *PATHS],
                         capture_output=True, text=True, timeout=600)
    assert run.returncode == 0, f"flake8 findings:\n{run.stdout}\n{run.stderr}"


@pytest.mark.linter
@pytest.mark.pep257
def test_pep257():
    ament_pep257 = pytest.importorskip("ament_pep257.main")
    rc = ament_pep257.main(argv=PATHS)
    assert rc == 0, "pep257 findings: see the captured output above"
