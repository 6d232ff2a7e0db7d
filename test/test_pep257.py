"""
ament_pep257 over the package, the tests and setup.py, as ros2/examples packages run it.

The ament convention (pydocstyle with D100-D107, D203, D212 and D404 ignored): a summary line
of its own on the docstring's second line, ending with a period, a blank line after it, and
the closing quotes on a line of their own.  Every file is checked.
"""

from pathlib import Path

import pytest

ament_pep257 = pytest.importorskip("ament_pep257.main")

ROOT = Path(__file__).resolve().parent.parent


@pytest.mark.linter
@pytest.mark.pep257
def test_pep257():
    paths = [str(ROOT / p) for p in ("spacerobot_planner", "test", "setup.py")]
    rc = ament_pep257.main(argv=paths)
    assert rc == 0, "pep257 findings: see the captured output above"
