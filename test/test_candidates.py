"""The start/goal candidate nodes (``PlanRun.candidates``) against the rule written out in plain Python."""

import itertools
import math
import random

import numpy as np
import pytest

from spacerobot_planner.cspace import GridSpec
from spacerobot_planner.pipeline import PlanRun


def oracle_candidates(q, grid, occupied, max_count=8):
    """
    Return the candidates by the rule in plain Python floats and tuples.

    Nodes at index offsets -1 .. 2 from the floor cell of q on every axis, wrapped on
    periodic axes, dropped outside bounded ones; the distinct free ones in index order,
    sorted stably by the Euclidean norm of (node's joint values − q), wrapped to [-π, π)
    on periodic axes, the squares summed axis by axis in order; the first max_count.
    """
    cells, lo, up, per = grid.cells, grid.lower_rad, grid.upper_rad, grid.periodic
    shape = [c if p else c + 1 for c, p in zip(cells, per)]
    step = [(hi - low) / c for low, hi, c in zip(lo, up, cells)]
    base = [math.floor((float(q[i]) - lo[i]) / step[i]) for i in range(len(cells))]
    nodes = set()
    for off in itertools.product(range(-1, 3), repeat=len(cells)):
        node = []
        for i, o in enumerate(off):
            v = base[i] + o
            if per[i]:
                v %= shape[i]
            elif not 0 <= v < shape[i]:
                break
            node.append(v)
        else:
            nodes.add(tuple(node))
    free = [n for n in sorted(nodes) if not occupied[n]]

    def dist(n):
        s = 0.0
        for i, v in enumerate(n):
            d = (lo[i] + v * step[i]) - float(q[i])
            if per[i]:
                d = (d + math.pi) % (2.0 * math.pi) - math.pi
            s += d * d
        return math.sqrt(s)

    return sorted(free, key=dist)[:max_count]


def random_case(rng: random.Random):
    """Return a grid (small periodic axes repeat indices), an occupancy, a q on nodes, cell centres or anywhere."""
    ndim = rng.choice([1, 2, 2, 3, 3, 4])
    cells, lo, up, per = [], [], [], []
    for _ in range(ndim):
        p = rng.random() < 0.5
        c = rng.choice([2, 3, 4, 5, 8, 12, 36])
        if p and rng.random() < 0.7:
            lo.append(-math.pi)
            up.append(math.pi)
        else:
            a = rng.uniform(-3.0, 1.0)
            lo.append(a)
            up.append(a + rng.uniform(0.5, 4.0))
        cells.append(c)
        per.append(p)
    grid = GridSpec(tuple(cells), tuple(lo), tuple(up), tuple(per))
    fill = rng.choice([0.0, 0.3, 0.7, 1.0])
    occupied = np.random.default_rng(rng.randrange(1 << 30)).random(grid.shape) < fill
    q = []
    for i in range(ndim):
        step = (up[i] - lo[i]) / cells[i]
        kind = rng.random()
        if kind < 0.3:           # on a node: mirror neighbours tie
            q.append(lo[i] + rng.randrange(cells[i] + 1) * step)
        elif kind < 0.55:        # a cell centre: ties both sides
            q.append(lo[i] + (rng.randrange(cells[i]) + 0.5) * step)
        elif kind < 0.65:        # the bounds
            q.append(rng.choice([lo[i], up[i]]))
        else:
            q.append(rng.uniform(lo[i], up[i]))
    return np.array(q), grid, occupied


@pytest.mark.parametrize("seed", range(6))
def test_candidates_match_the_plain_rule(seed):
    rng = random.Random(seed)
    for _ in range(400):
        q, grid, occupied = random_case(rng)
        max_count = rng.choice([1, 4, 8, 8, 100])
        got = PlanRun.candidates(None, q, grid, occupied, max_count)
        want = oracle_candidates(q, grid, occupied, max_count)
        assert got.dtype == np.int64 and got.shape == (len(want), grid.ndim)
        assert [tuple(int(v) for v in n) for n in got] == want, (q.tolist(), grid, max_count)


def test_candidates_ties_keep_index_order():
    """With q on a node of a unit-step grid, its 4 axis neighbours tie exactly and come in index order."""
    grid = GridSpec((8, 8), (0.0, 0.0), (8.0, 8.0), (False, False))
    occupied = np.zeros(grid.shape, bool)
    q = np.array([4.0, 4.0])
    got = [tuple(int(v) for v in n) for n in PlanRun.candidates(None, q, grid, occupied, 5)]
    assert got == [(4, 4), (3, 4), (4, 3), (4, 5), (5, 4)]
    occupied[4, 4] = occupied[3, 4] = True
    got = [tuple(int(v) for v in n) for n in PlanRun.candidates(None, q, grid, occupied, 4)]
    assert got == [(4, 3), (4, 5), (5, 4), (3, 3)]
