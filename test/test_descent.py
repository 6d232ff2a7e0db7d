"""Tests of spacerobot_planner.descent (steepest descent over grid nodes)."""
import os
import sys

import numpy as np
import pytest

sys.path.insert(0, os.path.dirname(__file__))
import mazes  # noqa: E402

from spacerobot_planner import field as F  # noqa: E402
from spacerobot_planner.descent import GridPath, descend, reaches_goal_mask  # noqa: E402


@pytest.fixture(scope="module")
def blocks():
    occ, start, goal = mazes.blocks_2d(181)
    return F.solve_field(occ, (False, False), [goal]), start, goal


def test_path_is_strictly_ascending_face_walk(blocks):
    f, start, goal = blocks
    p = descend(f, start)
    assert isinstance(p, GridPath) and p.reached and p.reason is None
    assert tuple(p.nodes[0]) == tuple(start) and tuple(p.nodes[-1]) == tuple(goal)
    assert p.steps == len(p.nodes) - 1
    assert np.all(np.abs(np.diff(p.nodes, axis=0)).sum(axis=1) == 1)
    vals = f.log_u[tuple(p.nodes.T)]
    assert np.all(np.diff(vals) > 0)
    assert not f.occupied[tuple(p.nodes.T)].any()
    q = descend(f, np.array(start))
    assert np.array_equal(p.nodes, q.nodes)


def test_start_in_obstacle(blocks):
    f, start, goal = blocks
    p = descend(f, (90, 90))
    assert not p.reached and p.reason == "start node is an obstacle" and p.steps == 0


def test_start_disconnected(blocks):
    f, start, goal = blocks
    p = descend(f, (160, 160))                 # inside the closed ring
    assert not f.occupied[160, 160]
    assert not p.reached and p.reason == "start node not connected to the goal"


def test_start_at_goal(blocks):
    f, start, goal = blocks
    p = descend(f, goal)
    assert p.reached and p.steps == 0 and len(p.nodes) == 1


def test_bad_start_raises(blocks):
    f, start, goal = blocks
    with pytest.raises(ValueError, match="start_node"):
        descend(f, (181, 0))
    with pytest.raises(ValueError, match="start_node"):
        descend(f, (1, 2, 3))


def test_stuck_reason_on_a_local_maximum():
    occ = np.zeros((5, 7), dtype=bool)
    log_u = np.full((5, 7), -5.0)
    log_u[0, 0] = 0.0
    log_u[2, 3] = -1.0                          # isolated bump: a local maximum
    f = F.Field(log_u, occ, (False, False), np.array([[0, 0]]), "test", 0, 0.0, True, 0.0)
    p = descend(f, (2, 4))
    assert not p.reached and p.reason == "stuck at node (2, 3): no strictly higher neighbour"
    assert p.steps == 1
    mask = reaches_goal_mask(f)
    assert mask[0, 0] and not mask[2, 4] and not mask[4, 6]


def test_reaches_goal_mask_matches_walks(blocks):
    f, start, goal = blocks
    paper = F.solve_field(f.occupied, f.periodic, f.goal_nodes, solver="gauss_seidel", max_sweeps=60)
    rng = np.random.default_rng(1)
    free = np.argwhere(~f.occupied)
    sample = free[rng.choice(len(free), 300, replace=False)]
    for fld in (f, paper):
        mask = reaches_goal_mask(fld)
        for node in sample:
            assert descend(fld, node).reached == mask[tuple(node)]
    assert not reaches_goal_mask(paper)[f.reachable].all()   # early paper sweeps: flat
