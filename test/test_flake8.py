"""
ament_flake8 over the package, the tests and setup.py, as ros2/examples packages run it.

Line length: the project's 120 (ament's default is 99).  Every file is checked.
"""

from pathlib import Path

import pytest

ament_flake8 = pytest.importorskip("ament_flake8.main")

ROOT = Path(__file__).resolve().parent.parent


@pytest.mark.flake8
@pytest.mark.linter
def test_flake8():
    paths = [str(ROOT / p) for p in ("spacerobot_planner", "test", "setup.py")]
    rc, errors = ament_flake8.main_with_errors(argv=["--linelength", "120", "--", *paths])
    assert rc == 0, f"{len(errors)} flake8 finding(s):\n" + "\n".join(errors)
