"""
The repair's search for colliding grid edges (``repair.sheet_edges``), against the tests' oracles.

A thin wall (1 cm) that a 20° grid of the paper's 3-DOF arm misses: its nodes are free on
both sides, and the grid edges across it collide (a "sheet" of edges).  Each edge's motion
is judged by the plain-Python distances of test/oracles.py at dense samples; an edge counts
as surely colliding (or surely free) when the dense clearance is below (above) the margin
by more than the arm can move between the kernel's samples and the oracle's.  Face
neighbours come from the oracle's own grid (``face_neighbours``).
"""

import math
import pickle
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from oracles import edge_clearance, face_neighbours
from spacerobot_planner.collision import CollisionChecker
from spacerobot_planner.config import load_scenario
from spacerobot_planner.cspace import build_cspace
from spacerobot_planner.motion import QUICK_STEP_RAD, MotionValidator
from spacerobot_planner.repair import CutEdges, sheet_edges
from spacerobot_planner.scene import Scene

CONFIG = Path(__file__).resolve().parent.parent / "config"
MARGIN_M = 0.05
#: the oracle's samples along an edge, rad apart at most
ORACLE_STEP_RAD = math.radians(0.25)
#: how far a point of links 2-3 moves per radian of one joint at most (the reach, 1.4 + 2 + 2 m)
REACH_M = 5.4
#: clearances within this of the margin decide nothing (the kernel's and the oracle's samples)
TOL_M = REACH_M * (QUICK_STEP_RAD + ORACLE_STEP_RAD) / 2 + 1e-3


@pytest.fixture(scope="module")
def wall():
    """(scenario, C-space, segment test) of the 3-DOF arm at 18 cells with a 1 cm wall of 0.32 m."""
    base = load_scenario(CONFIG / "paper_3dof.yaml")
    c, ang, length = np.array([3.28, -0.91]), 1.73, 0.32
    d, n = np.array([math.cos(ang), math.sin(ang)]), np.array([-math.sin(ang), math.cos(ang)])
    poly = np.array([c - length / 2 * d - 0.005 * n, c + length / 2 * d - 0.005 * n,
                     c + length / 2 * d + 0.005 * n, c - length / 2 * d + 0.005 * n])
    scene = Scene(target=None, debris_m=(poly,), safety_margin_m=MARGIN_M)
    sc = replace(base.with_scene(scene), grid=base.grid_with_cells(18))
    cs = build_cspace(sc.robot, scene, sc.grid)
    motions = MotionValidator(CollisionChecker(sc.robot, scene)).segment_test()
    return sc, cs, motions


def _box(flat, shape, periodic, radius):
    """Flat indices of the grid nodes within ``radius`` steps per axis of node ``flat`` (oracle grid)."""
    c = np.array(np.unravel_index(flat, shape))
    offs = np.stack(np.meshgrid(*[np.arange(-radius, radius + 1)] * len(shape), indexing="ij"), -1)
    nodes = c + offs.reshape(-1, len(shape))
    per = np.asarray(periodic)
    nodes[:, per] %= np.asarray(shape)[per]
    nodes = nodes[((nodes >= 0) & (nodes < np.asarray(shape))).all(axis=1)]
    return set(np.ravel_multi_index(nodes.T, shape).tolist())


def _up_edges(nodes, occ_flat, nbr):
    """Return the edges (smaller flat index first) from each free node of ``nodes`` to its free upper neighbours."""
    out = set()
    for f in nodes:
        if occ_flat[f]:
            continue
        for a in range(nbr.shape[0] // 2):
            g = int(nbr[2 * a + 1, f])
            if g >= 0 and g != f and not occ_flat[g]:
                out.add((min(f, g), max(f, g)))
    return out


def test_sheet_edges_collide_and_follow_the_sheet(wall):
    sc, cs, motions = wall
    grid, occ = sc.grid, cs.occupied
    occ_flat = occ.ravel()
    nbr = face_neighbours(grid.shape, grid.periodic).reshape(2 * grid.ndim, -1)
    # a node next to the wall: an end of a colliding edge of the whole grid's search (which
    # node is not what is checked)
    every = sheet_edges(occ, grid.periodic, (0, 0, 0), motions, grid.lower_rad, grid.step_rad,
                        radius=max(grid.shape), max_tests=0)             # every edge of the grid
    assert len(every) > 50, "the wall should cross many grid edges"
    seed = int(every[len(every) // 2][0])
    assert edge_clearance(sc, *map(int, every[len(every) // 2])) < MARGIN_M + TOL_M    # the seed, by the oracle
    node = tuple(int(v) for v in np.unravel_index(seed, grid.shape))
    found = sheet_edges(occ, grid.periodic, node, motions, grid.lower_rad, grid.step_rad, radius=1,
                        max_tests=10 ** 6)
    got = {(int(a), int(b)) for a, b in found}
    assert len(got) == len(found)
    # every edge found joins free face neighbours and collides (within the tolerance)
    for a, b in got:
        assert not occ_flat[a] and not occ_flat[b] and b in nbr[:, a]
        assert edge_clearance(sc, a, b) < MARGIN_M + TOL_M
    # the search followed the sheet beyond the box around the node
    box2 = _box(seed, grid.shape, grid.periodic, 2)
    assert any(a not in box2 or b not in box2 for a, b in got)
    # closed: every surely colliding edge within a step of a found edge (or of the node) was found
    near = _box(seed, grid.shape, grid.periodic, 1)
    for a, b in sorted(got):
        near |= _box(a, grid.shape, grid.periodic, 1) | _box(b, grid.shape, grid.periodic, 1)
    candidates = sorted(_up_edges(near, occ_flat, nbr) - got)
    rng = np.random.default_rng(0)
    for i in rng.choice(len(candidates), size=min(120, len(candidates)), replace=False):
        a, b = candidates[i]
        assert edge_clearance(sc, a, b) > MARGIN_M - TOL_M, f"edge {a}-{b} collides but was not found"


def test_the_box_around_the_node_is_searched_whatever_the_count(wall):
    sc, cs, motions = wall
    grid, occ = sc.grid, cs.occupied
    every = sheet_edges(occ, grid.periodic, (0, 0, 0), motions, grid.lower_rad, grid.step_rad,
                        radius=max(grid.shape), max_tests=0)
    assert edge_clearance(sc, *map(int, every[0])) < MARGIN_M + TOL_M          # the seed, by the oracle
    node = tuple(int(v) for v in np.unravel_index(int(every[0][0]), grid.shape))
    few = sheet_edges(occ, grid.periodic, node, motions, grid.lower_rad, grid.step_rad, radius=2, max_tests=0)
    more = sheet_edges(occ, grid.periodic, node, motions, grid.lower_rad, grid.step_rad, radius=2)
    assert {tuple(e) for e in few.tolist()} <= {tuple(e) for e in more.tolist()}
    nbr = face_neighbours(grid.shape, grid.periodic).reshape(2 * grid.ndim, -1)
    flat = int(np.ravel_multi_index(node, grid.shape))
    box = _up_edges(_box(flat, grid.shape, grid.periodic, 2), occ.ravel(), nbr)
    few_set = {tuple(e) for e in few.tolist()}
    for a, b in sorted(box - few_set):
        assert edge_clearance(sc, a, b) > MARGIN_M - TOL_M, f"edge {a}-{b} near the node collides, not found"
    # the same input, the same edges in the same order
    again = sheet_edges(occ, grid.periodic, node, motions, grid.lower_rad, grid.step_rad, radius=2)
    np.testing.assert_array_equal(again, more)


@pytest.mark.parametrize("seed", range(5))
def test_cut_edges_hold_the_set_of_pairs_in_sorted_order(seed):
    """Compare ``CutEdges`` with a set of pairs: its edges in sorted order, the new ones counted, equal as sets."""
    rng = np.random.default_rng(seed)
    pairs = rng.integers(0, 30, size=(int(rng.integers(0, 60)), 2))
    cut = CutEdges(pairs)
    held = {(int(a), int(b)) for a, b in pairs}
    assert cut.array.tolist() == [list(p) for p in sorted(held)]
    assert len(cut) == len(held) and not cut.array.flags.writeable
    more = rng.integers(0, 30, size=(int(rng.integers(0, 20)), 2))
    grown, new = cut.with_edges(more)
    assert new == len({(int(a), int(b)) for a, b in more} - held)
    assert grown.array.tolist() == [list(p) for p in sorted(held | {(int(a), int(b)) for a, b in more})]
    shuffled = CutEdges(rng.permutation(np.vstack([pairs, more, pairs]).reshape(-1, 2)))
    assert shuffled == grown and hash(shuffled) == hash(grown) and {grown: 1}[shuffled] == 1
    assert pickle.loads(pickle.dumps(grown)) == grown
    assert (grown == cut) == (new == 0)
