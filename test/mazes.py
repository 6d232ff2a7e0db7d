"""
Deterministic synthetic occupancy grids for the field / descent tests.

``maze(shape, pitch, seed)``: a perfect maze (randomised depth-first search,
seeded) carved into an all-obstacle grid: corridors ``pitch - 1`` nodes wide,
walls 1 node thick, one route between any two cells, so the route from the
start corner to the goal corner winds through a large part of the grid.
``blocks_2d(n)``: a big central block and a side block (paper-like 2-DOF
scene).  ``seam_scene_2d`` / ``seam_scene_3d``: the only route from start to
goal crosses the seam of the periodic axis 0.
"""
from __future__ import annotations

import numpy as np


def maze(shape, pitch=4, seed=0):
    """
    Maze occupancy of 2-D ``shape`` (bounded axes).

    Cells sit at nodes ``1 + pitch * c`` .. ``pitch * (c + 1) - 1`` on each axis
    (``pitch - 1`` nodes wide); the outermost nodes and any remainder beyond
    the last full cell stay obstacles.  Returns ``(occupied, start, goal)``:
    bool array of ``shape``, and the start node (first cell, corner) and goal
    node (last cell, opposite corner) as int tuples.
    """
    n0, n1 = shape
    c0, c1 = (n0 - 1) // pitch, (n1 - 1) // pitch
    rng = np.random.default_rng(seed)
    occ = np.ones(shape, dtype=bool)
    w = pitch - 1

    def carve_cell(a, b):
        occ[1 + pitch * a: 1 + pitch * a + w, 1 + pitch * b: 1 + pitch * b + w] = False

    def carve_wall(a, b, da, db):
        if da:  # wall between (a, b) and (a + 1, b): row pitch * (a + 1)
            r = pitch * (a + 1)
            occ[r, 1 + pitch * b: 1 + pitch * b + w] = False
        else:
            col = pitch * (b + 1)
            occ[1 + pitch * a: 1 + pitch * a + w, col] = False

    seen = np.zeros((c0, c1), dtype=bool)
    stack = [(0, 0)]
    seen[0, 0] = True
    carve_cell(0, 0)
    while stack:
        a, b = stack[-1]
        options = [(a + da, b + db) for da, db in ((-1, 0), (1, 0), (0, -1), (0, 1))
                   if 0 <= a + da < c0 and 0 <= b + db < c1 and not seen[a + da, b + db]]
        if not options:
            stack.pop()
            continue
        na, nb = options[rng.integers(len(options))]
        seen[na, nb] = True
        carve_cell(na, nb)
        carve_wall(min(a, na), min(b, nb), na != a, nb != b)
        stack.append((na, nb))
    start = (1, 1)
    goal = (pitch * (c0 - 1) + 1, pitch * (c1 - 1) + 1)
    return occ, start, goal


def blocks_2d(n=181):
    """
    Paper-like 2-DOF scene on an n x n bounded grid.

    A big central block, a side block and a small disconnected pocket.

    Returns ``(occupied, start, goal)``.
    """
    occ = np.zeros((n, n), dtype=bool)
    f = n / 181.0
    occ[int(50 * f):int(130 * f), int(60 * f):int(125 * f)] = True   # central body
    occ[int(10 * f):int(75 * f), int(15 * f):int(30 * f)] = True     # side block
    # a closed ring: the nodes inside are free but not connected to the goal
    occ[int(150 * f):int(170 * f), int(150 * f):int(170 * f)] = True
    occ[int(155 * f):int(165 * f), int(155 * f):int(165 * f)] = False
    start = (int(20 * f), int(5 * f))
    goal = (int(160 * f), int(90 * f))
    return occ, start, goal


def seam_scene_2d(n0=36, n1=37):
    """
    Axis 0 periodic (n0 nodes), axis 1 bounded.

    A wall across axis 0 at rows n0/2 - 1 .. n0/2 + 1 (full width) separates
    start and goal inside the grid, so the only route crosses the seam row n0 -
    1 <-> 0.  Returns ``(occupied, periodic, start, goal)``.
    """
    occ = np.zeros((n0, n1), dtype=bool)
    mid = n0 // 2
    occ[mid - 1: mid + 2, :] = True
    start = (mid - 4, n1 // 2)
    goal = (mid + 4, n1 // 2)
    return occ, (True, False), start, goal


def seam_scene_3d(n0=36, n1=21, n2=21):
    """3-D version of :func:`seam_scene_2d` (axis 0 periodic), plus a pillar so the field is not trivially symmetric."""
    occ = np.zeros((n0, n1, n2), dtype=bool)
    mid = n0 // 2
    occ[mid - 1: mid + 2, :, :] = True
    occ[2:6, 5:12, 3:15] = True
    start = (mid - 4, n1 // 2, n2 // 2)
    goal = (mid + 4, 3, n2 // 2)
    return occ, (True, False, False), start, goal


def blocks_3d(shape=(36, 37, 37)):
    """
    Paper-like 3-DOF scene: axis 0 periodic; a slab-shaped body with a gap and a central block.

    Returns ``(occupied, periodic, start, goal)``.
    """
    n0, n1, n2 = shape
    occ = np.zeros(shape, dtype=bool)
    f0, f1, f2 = n0 / 36.0, n1 / 37.0, n2 / 37.0
    occ[int(8 * f0):int(20 * f0), int(10 * f1):int(27 * f1), int(10 * f2):int(27 * f2)] = True
    occ[:, int(30 * f1):int(33 * f1), :int(28 * f2)] = True
    start = (int(2 * f0), int(35 * f1), int(3 * f2))
    goal = (int(26 * f0), int(18 * f1), int(18 * f2))
    return occ, (True, False, False), start, goal
