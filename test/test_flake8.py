"""ament_flake8 over the package and the tests, as ros2/examples packages run it.

Line length: the project's 120 (ament's default is 99).  Every file is checked.
"""

import pytest

ament_flake8 = pytest.importorskip("ament_flake8.main")


@pytest.mark.flake8
@pytest.mark.linter
def test_flake8():
    rc, errors = ament_flake8.main_with_errors(argv=["--linelength", "120", "--",
                                                     "spacerobot_planner", "test"])
    assert rc == 0, f"{len(errors)} flake8 finding(s):\n" + "\n".join(errors)
