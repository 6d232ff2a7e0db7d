"""
Test isolation, hypothesis profiles and the paper's scenarios and paths.

Each run gets its own DDS domain and discovery stays on this host.  Property tests
run a few dozen cases by default; ``pytest --hypothesis-profile=long`` (or
``make test-long``) runs thousands.  The ``graph`` fixture: in-process node graphs
(test/node_helpers.py).
"""

import os
import random

import pytest
from hypothesis import HealthCheck, settings

# before rclpy is imported anywhere: 233 and up fail here with "port number is too high"
os.environ["ROS_DOMAIN_ID"] = str(random.SystemRandom().randint(1, 232))
os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"

_common = dict(deadline=None, suppress_health_check=[HealthCheck.too_slow], derandomize=False)
settings.register_profile("default", max_examples=30, **_common)
settings.register_profile("ci", max_examples=30, derandomize=True, deadline=None,
                          suppress_health_check=[HealthCheck.too_slow])
settings.register_profile("long", max_examples=3000, **_common)
settings.load_profile("ci" if os.environ.get("CI") else "default")


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
