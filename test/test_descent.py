"""
Tests of spacerobot_planner.descent (steepest descent over grid nodes).

The walks are checked against the test's own steepest-ascent rule (test/oracles.py): every
node's steepest strictly higher face neighbour from its own neighbour table, ties to the
first in the documented order, and where following them ends.
"""
import numpy as np
import pytest

import mazes
from oracles import ascent_reaches_goal, ascent_walk, steepest_successors
from spacerobot_planner import field as F
from spacerobot_planner.descent import GridPath, descend, reaches_goal_mask


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
    assert np.array_equal(p.nodes, ascent_walk(steepest_successors(f.log_u, f.periodic), f.goal_mask, start))


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


def test_ties_go_to_the_first_neighbour_in_the_fixed_order():
    """
    Equal higher neighbours along one axis and across axes: the walk takes the first in the order.

    The order (axis 0, -1), (axis 0, +1), (axis 1, -1), (axis 1, +1); one walk crosses the seam.
    """
    occ = np.zeros((6, 5), dtype=bool)
    rows = np.array([0, 1, 2, 3, 2, 1])                       # steps to row 0, the seam included
    log_u = -(np.abs(np.arange(5) - 2)[None, :] + rows[:, None]).astype(float)
    f = F.Field(log_u, occ, (True, False), np.array([[0, 2]]), "test", 0, 0.0, True, 0.0)
    succ = steepest_successors(log_u, f.periodic)
    first_steps = {(3, 2): (2, 2), (1, 0): (0, 0), (1, 4): (0, 4), (5, 3): (0, 3)}
    for start, step in first_steps.items():
        p = descend(f, start)
        assert p.reached and tuple(p.nodes[1]) == step
        assert np.array_equal(p.nodes, ascent_walk(succ, f.goal_mask, start))
    assert np.array_equal(reaches_goal_mask(f), ascent_reaches_goal(succ, f.goal_mask))


def test_reaches_goal_mask_matches_walks(blocks):
    f, start, goal = blocks
    paper = F.solve_field(f.occupied, f.periodic, f.goal_nodes, solver="gauss_seidel", max_sweeps=60)
    rng = np.random.default_rng(1)
    free = np.argwhere(~f.occupied)
    sample = free[rng.choice(len(free), 300, replace=False)]
    for fld in (f, paper):
        succ = steepest_successors(fld.log_u, fld.periodic)
        mask = reaches_goal_mask(fld)
        assert np.array_equal(mask, ascent_reaches_goal(succ, fld.goal_mask) & ~fld.occupied)
        for node in sample:
            p = descend(fld, node)
            assert p.reached == mask[tuple(node)]
            assert np.array_equal(p.nodes, ascent_walk(succ, fld.goal_mask, node))
    assert not reaches_goal_mask(paper)[f.reachable].all()   # early paper sweeps: flat
