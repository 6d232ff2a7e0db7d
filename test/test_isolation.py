"""
Each test run claims a ROS domain that no concurrent run on the machine holds (conftest.claim_ros_domain).

Oracle: separate processes, each claiming from the same lock folder.
"""

import os
import subprocess
import sys

from conftest import claim_ros_domain

_CLAIM_AND_HOLD = r"""
import sys
from conftest import claim_ros_domain
domain, lock = claim_ros_domain(sys.argv[1], range(1, 4))
print(domain, flush=True)
sys.stdin.readline()            # hold the claim until told to go
"""


def _claimer(lock_dir):
    here = os.path.dirname(os.path.abspath(__file__))
    # `python -c` imports from its working directory: test/, for conftest
    p = subprocess.Popen([sys.executable, "-c", _CLAIM_AND_HOLD, str(lock_dir)], cwd=here,
                         stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    return p, int(p.stdout.readline())


def test_concurrent_runs_get_different_domains_and_a_finished_run_frees_its_own(tmp_path):
    a, dom_a = _claimer(tmp_path)
    b, dom_b = _claimer(tmp_path)
    mine, lock = claim_ros_domain(str(tmp_path), range(1, 4))
    assert len({dom_a, dom_b, mine}) == 3, (dom_a, dom_b, mine)
    a.communicate("\n", timeout=30)          # run a ends: its domain is free again
    c, dom_c = _claimer(tmp_path)
    assert dom_c == dom_a
    for p in (b, c):
        p.communicate("\n", timeout=30)
    lock.close()


def test_this_run_holds_its_domain():
    held = int(os.environ["ROS_DOMAIN_ID"])
    from conftest import DOMAIN_LOCK_DIR
    try:
        claim_ros_domain(DOMAIN_LOCK_DIR, [held])
    except RuntimeError as e:
        assert "held by a test run" in str(e)
    else:
        raise AssertionError(f"domain {held} was free to claim while this run uses it")
