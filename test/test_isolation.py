"""
Each test run claims a ROS domain that no concurrent run on the machine holds (conftest.claim_ros_domain).

Oracle: separate processes, each claiming from the same lock folder.
"""

import os
import subprocess
import sys

from conftest import claim_ros_domain, domains_in_use

_CLAIM_AND_HOLD = r"""
import sys
from conftest import claim_ros_domain
domain, lock = claim_ros_domain(sys.argv[1], range(1, 4), in_use=())
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
    mine, lock = claim_ros_domain(str(tmp_path), range(1, 4), in_use=())
    assert len({dom_a, dom_b, mine}) == 3, (dom_a, dom_b, mine)
    a.communicate("\n", timeout=30)          # run a ends: its domain is free again
    c, dom_c = _claimer(tmp_path)
    assert dom_c == dom_a
    for p in (b, c):
        p.communicate("\n", timeout=30)
    lock.close()


def test_a_domain_another_process_uses_is_passed_over_while_another_is_free(tmp_path):
    """
    A UDP socket bound in domain d's DDS port range (as a node there binds): seen, and the claim takes d + 1, then d.

    Oracle: the socket this test binds (in a process of its own, as a node outside the test runs
    would be) and the RTPS port mapping written here, 7400 + 250 × domain.  d and d + 1: two
    domains nothing on the machine uses now.
    """
    import socket
    used = domains_in_use()
    d = next(d for d in range(1, 231) if d not in used and d + 1 not in used)
    port = 7400 + 250 * d + 17
    holder = subprocess.Popen([sys.executable, "-c", (
        "import socket, sys\n"
        "s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)\n"
        f"s.bind(('127.0.0.1', {port}))\n"
        "print('bound', flush=True)\n"
        "sys.stdin.readline()\n")], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "bound"
        assert d in domains_in_use()
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:     # the port is really taken
            try:
                probe.bind(("127.0.0.1", port))
            except OSError:
                pass
            else:
                raise AssertionError("the holder's port was free")
        # the claim passes over what the probe saw in use (d: seen above; d + 1 may meanwhile get a
        # node of another worker of this run, whose domain lock is in another folder: not this test's)
        used = domains_in_use() - {d + 1}
        assert d in used
        first, lock_a = claim_ros_domain(str(tmp_path), [d, d + 1], in_use=used)
        second, lock_b = claim_ros_domain(str(tmp_path), [d, d + 1], in_use=used)     # only d left: taken
        assert (first, second) == (d + 1, d)
        lock_a.close()
        lock_b.close()
    finally:
        holder.communicate("\n", timeout=30)


def test_this_run_holds_its_domain():
    held = int(os.environ["ROS_DOMAIN_ID"])
    from conftest import DOMAIN_LOCK_DIR
    try:
        claim_ros_domain(DOMAIN_LOCK_DIR, [held])
    except RuntimeError as e:
        assert "held by a test run" in str(e)
    else:
        raise AssertionError(f"domain {held} was free to claim while this run uses it")
