"""
Test isolation, hypothesis profiles and the paper's scenarios and paths.

Each run gets its own DDS domain and discovery stays on this host, and the DDS participants a
test's nodes leave to the garbage collector are finalized before the next test starts (a
participant finalized while another sends it discovery data can hang Fast DDS for good).  Property tests
run a few dozen cases by default; ``pytest --hypothesis-profile=long`` (or
``make test-long``) runs thousands.  The ``graph`` fixture: in-process node graphs
(test/node_helpers.py).
"""

import fcntl
import gc
import os
import tempfile

import pytest
from hypothesis import HealthCheck, settings

#: the ROS domains a test run may claim: 233 and up fail with "port number is too high"
ROS_DOMAINS = range(1, 233)
#: one lock file per domain; a run holds its domain's lock until its process ends
DOMAIN_LOCK_DIR = os.path.join(tempfile.gettempdir(), "spacerobot_planner-test-ros-domains")


#: Fast DDS's (and the RTPS standard's) ports: domain d's participants bind UDP ports in
#: [PORT_BASE + DOMAIN_GAIN * d, PORT_BASE + DOMAIN_GAIN * (d + 1))
PORT_BASE, DOMAIN_GAIN = 7400, 250


def domains_in_use(tables=("/proc/net/udp", "/proc/net/udp6")) -> set:
    """
    Return the ROS domains whose DDS ports some process on this machine has bound (a node running there).

    From the kernel's UDP socket tables (the local port of each socket): a process outside the
    test runs' locks (a node someone started, a benchmark, another tool's run in a domain it
    chose) is seen too.  A socket in that range that is not DDS's only makes a domain look taken.
    """
    used = set()
    for table in tables:
        try:
            with open(table, encoding="ascii") as f:
                rows = f.read().splitlines()[1:]
        except OSError:
            continue
        for row in rows:
            fields = row.split()
            if len(fields) > 1 and ":" in fields[1]:
                port = int(fields[1].rsplit(":", 1)[1], 16)
                if port >= PORT_BASE:
                    used.add((port - PORT_BASE) // DOMAIN_GAIN)
    return used


def claim_ros_domain(lock_dir: str = DOMAIN_LOCK_DIR, domains=ROS_DOMAINS, in_use=None):
    """
    Claim a ROS domain that no concurrent test run on this machine holds and no other process uses.

    Each domain has a lock file in ``lock_dir``; the first domain whose lock this process
    gets (``flock``, non-blocking) is claimed and held until the returned file is closed or
    the process ends (the kernel drops the lock then, so a crashed run never leaks one).
    Domains ``in_use`` (None: :func:`domains_in_use`, the machine's bound DDS ports) are passed
    over while any other is free: a node outside the test runs in the same domain (a benchmark,
    someone's ``ros2 run``) had sent a test its own ``joint_states``.  The search starts at a
    point derived from the process id, so concurrent runs rarely contend for the same file.
    Returns (domain id, open lock file).
    """
    os.makedirs(lock_dir, exist_ok=True)
    domains = list(domains)
    used = domains_in_use() if in_use is None else set(in_use)
    first = os.getpid() % len(domains)
    order = [domains[(first + k) % len(domains)] for k in range(len(domains))]
    for domain in [d for d in order if d not in used] + [d for d in order if d in used]:
        f = open(os.path.join(lock_dir, f"{domain}.lock"), "w")
        try:
            fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            f.close()
            continue
        f.write(f"{os.getpid()}\n")
        f.flush()
        return domain, f
    raise RuntimeError(f"every ROS domain in {domains[0]}..{domains[-1]} is held by a test run ({lock_dir})")


# before rclpy is imported anywhere; the processes the tests start inherit it.  Claimed once
# per process (the key names the process that holds the lock).
_CLAIMED_BY = "SPACEROBOT_PLANNER_TEST_DOMAIN_PID"
if os.environ.get(_CLAIMED_BY) != str(os.getpid()):
    _domain, _DOMAIN_LOCK = claim_ros_domain()
    os.environ["ROS_DOMAIN_ID"], os.environ[_CLAIMED_BY] = str(_domain), str(os.getpid())
os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"

_common = dict(deadline=None, suppress_health_check=[HealthCheck.too_slow], derandomize=False)
settings.register_profile("default", max_examples=30, **_common)
settings.register_profile("ci", max_examples=30, derandomize=True, deadline=None,
                          suppress_health_check=[HealthCheck.too_slow])
settings.register_profile("long", max_examples=3000, **_common)
settings.load_profile("ci" if os.environ.get("CI") else "default")


def pytest_collection_modifyitems(config, items):
    """
    Run the ``slow`` tests first.

    They are the long poles of a run in several workers (``make test``: pytest-xdist hands the
    tests out in collection order), so they start while the short ones fill the other workers.
    """
    items.sort(key=lambda item: item.get_closest_marker("slow") is None)      # stable: order kept otherwise


def dds_participants() -> int:
    """Return the DDS participants alive in this process: Fast DDS's event threads (``dds.ev.<n>``, one each)."""
    from spacerobot_planner.cores import own_thread_files      # no rclpy, no numba
    return sum(comm.startswith(b"dds.ev") for comm in own_thread_files("comm"))


@pytest.hookimpl(trylast=True)
def pytest_runtest_logfinish(nodeid, location):
    """
    Finalize the DDS participants of the test that ended, where its nodes left any, before the next test.

    A node's rcl handle, and with the context's last node its DDS participant, is finalized when
    its Python objects go: the ``graph`` fixture's nodes are destroyed and their contexts shut
    down, but pytest holds the test's fixture values until after its teardown, and the nodes sit in
    reference cycles (callbacks, threads), so before this the garbage collector finalized them at
    some allocation of a later test, often while that test's own participants were discovering
    each other.  A fresh clone's ``make test`` hung there once for good (2026-12-05): Fast DDS
    destroying a participant (``DomainParticipant::set_listener``) while another participant of
    the process delivered it an endpoint's discovery (nine participants alive in that worker).
    Here every one of them goes in a collection with no test running (about 20 ms, only where a
    participant is alive).
    """
    if dds_participants():
        gc.collect()


#: the wall-clock budget of a field solved with the default budget (``field.DEFAULT_BUDGET_S``,
#: 5 s) in the tests: at load 10 on 2 cores the 4-D maze took longer.  What a test checks of a
#: field is its values; the budget's own tests pass theirs.
TEST_FIELD_BUDGET_S = 300.0


@pytest.fixture(autouse=True)
def _field_budget_unhurried(monkeypatch):
    import spacerobot_planner.field as field
    monkeypatch.setattr(field, "DEFAULT_BUDGET_S", TEST_FIELD_BUDGET_S)


@pytest.fixture
def graph():
    """
    Make in-process node graphs, closed after the test.

    ``graph(flat, with_arm=True)`` → a node_helpers.Graph (planner, mock arm, driver in a
    private context).
    """
    from node_helpers import Graph          # imports rclpy: after ROS_DOMAIN_ID is set
    made = []

    def make(flat, with_arm=True, **kw):
        g = Graph(flat, with_arm, **kw)
        made.append(g)
        return g

    yield make
    for g in made:
        g.close()


#: The repository's config/ folder (tests never depend on the working directory).
CONFIG_DIR = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "config")


@pytest.fixture(scope="session")
def paper_scenario():
    """
    Load the paper's scenarios.

    ``paper_scenario(dof)`` → the paper's 2-DOF or 3-DOF ``Scenario`` (config/paper_<dof>dof.yaml).
    """
    from spacerobot_planner.config import load_scenario

    def get(dof: int):
        return load_scenario(os.path.join(CONFIG_DIR, f"paper_{dof}dof.yaml"))

    return get


@pytest.fixture(scope="session")
def paper_path(paper_scenario):
    """
    Plan the paper's paths, once per test session.

    ``paper_path(dof)`` → the planner's path for the paper's 2-DOF or 3-DOF scene, (M, dof) rad,
    read-only (from ``paper_scenario(dof)``'s start to its goal).
    """
    import numpy as np
    from spacerobot_planner.planner import Planner
    planned = {}

    def get(dof: int):
        if dof not in planned:
            sc = paper_scenario(dof)
            res = Planner(sc).plan(sc.start_rad, sc.goal_rad)
            assert res.ok, res.reason
            path = np.array(res.path_rad)
            path.setflags(write=False)
            planned[dof] = path
        return planned[dof]

    return get
