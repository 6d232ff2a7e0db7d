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


def _face_steps(nodes, shape, periodic) -> bool:
    """Return whether each node of a walk is a face neighbour of the one before (one index ±1, wrapped if periodic)."""
    d = np.diff(np.asarray(nodes), axis=0)
    for a, (n, per) in enumerate(zip(shape, periodic)):
        if per:
            d[:, a] = (d[:, a] + 1) % n - 1
    return bool(np.all(np.abs(d).sum(axis=1) == 1))


def _blocked_scene():
    """Return a random 3-DOF scene of ``bench scenes``' family whose plan repaired (walks on its first field block)."""
    from spacerobot_planner.bench.scenes import plan_problems
    for _, (sc, start, planner, goal) in zip(range(60), plan_problems(np.random.default_rng([0, 3]), 3)):
        res = planner.plan(start, goal)
        if res.ok and res.solver_stats.get("repairs"):
            return sc, res
    pytest.fail("no repairing scene among the first 60 of the family")


def test_walks_that_join_earlier_walks_are_the_walks_taken_alone():
    """
    A walk given the earlier walks on its field (``WalkJoins``) is the walk it takes alone, node for node.

    On the first field of a repairing random scene (the planner's grid C-space and goal nodes, no
    edge cut: walks there are blocked) with the planner's quick motion test, from every node of the
    box of three steps around the plan's first grid node, then from 60 random free nodes, in one
    ``WalkJoins``: each walk's nodes, end, reason and blocked flag against the same walk without it.
    Some walks must block, and later walks must stop on the nodes the first blocked walk stood on
    (those stay that walk's: a walk that went on past them would have taken them), or the joins
    were not exercised.
    """
    from spacerobot_planner.descent import WalkJoins
    from spacerobot_planner.motion import MotionValidator
    sc, res = _blocked_scene()
    grid = sc.grid
    f = F.solve_field(res.cspace.occupied, grid.periodic, res.field.goal_nodes)
    motions = MotionValidator.for_scene(sc.robot, sc.scene).segment_test()
    first = res.grid_path_rad[0]
    centre = np.rint((np.asarray(first) - grid.lower_rad) / grid.step_rad).astype(int) % np.array(grid.shape)
    box = np.stack(np.meshgrid(*[np.arange(-3, 4)] * 3, indexing="ij"), -1).reshape(-1, 3)
    starts = [tuple((centre + d) % np.array(grid.shape)) for d in box]
    free = np.argwhere(np.isfinite(f.log_u) & ~f.occupied)
    starts += [tuple(v) for v in free[np.random.default_rng(7).choice(len(free), 60, replace=False)]]
    starts = [s for s in starts if np.isfinite(f.log_u[s]) and not f.occupied[s]]
    joins = WalkJoins(f)
    walked = blocked = 0
    first_blocked = None
    for s in starts:
        alone = descend(f, s, motions, grid.lower_rad, grid.step_rad)
        joined = descend(f, s, motions, grid.lower_rad, grid.step_rad, joins=joins)
        assert np.array_equal(joined.nodes, alone.nodes), s
        assert _face_steps(joined.nodes, grid.shape, grid.periodic), s     # the joined path is one walk
        assert (joined.reached, joined.blocked, joined.reason, joined.steps) == \
            (alone.reached, alone.blocked, alone.reason, alone.steps), s
        walked += len(alone.nodes)
        blocked += alone.blocked
        if alone.blocked and first_blocked is None:
            first_blocked = (len(joins.walks) - 1, np.ravel_multi_index(tuple(alone.nodes.T), grid.shape))
    assert blocked >= 5, blocked
    w, nodes = first_blocked
    n = joins.owner.size
    assert np.mean(joins.owner[nodes] // n == w) > 0.9, "the first blocked walk's nodes were walked on again"
    with pytest.raises(ValueError, match="joins"):
        descend(F.solve_field(res.cspace.occupied, grid.periodic, res.field.goal_nodes), starts[0], motions,
                grid.lower_rad, grid.step_rad, joins=joins)


@pytest.mark.parametrize("cells", [2, 4])
def test_walks_that_join_on_a_tiny_grid_are_the_walks_taken_alone(cells):
    """
    On a grid of a few nodes a walk's room (its node count) is near every path: joined walks are the lone walks still.

    The paper 2-DOF scene on 3×3 and 5×5 nodes, the field towards each free node in turn, every free
    node's walk with one ``WalkJoins`` per field against the same walk alone (a joined path within a
    detour's box of the room is walked again alone, as a lone walk could have stopped there for room).
    """
    from dataclasses import replace as _replace
    from pathlib import Path
    from spacerobot_planner.config import load_scenario
    from spacerobot_planner.cspace import build_cspace
    from spacerobot_planner.descent import WalkJoins
    from spacerobot_planner.motion import MotionValidator
    sc = load_scenario(Path(__file__).resolve().parent.parent / "config" / "paper_2dof.yaml")
    sc = _replace(sc, grid=sc.grid_with_cells(cells))
    grid = sc.grid
    occ = build_cspace(sc.robot, sc.scene, grid).occupied
    motions = MotionValidator.for_scene(sc.robot, sc.scene).segment_test(step_rad=0.2)
    free = [tuple(v) for v in np.argwhere(~occ)]
    compared = 0
    for goal in free:
        f = F.solve_field(occ, grid.periodic, [goal])
        joins = WalkJoins(f)
        for s in free:
            if not np.isfinite(f.log_u[s]):
                continue
            alone = descend(f, s, motions, grid.lower_rad, grid.step_rad)
            joined = descend(f, s, motions, grid.lower_rad, grid.step_rad, joins=joins)
            assert np.array_equal(joined.nodes, alone.nodes) and joined.reason == alone.reason, (goal, s)
            assert _face_steps(joined.nodes, grid.shape, grid.periodic), (goal, s)
            compared += 1
    assert compared >= 9
