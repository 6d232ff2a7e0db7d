"""
The colliding grid edges of a whole grid from swept obstacles (``swept.swept_edges``), against an exhaustive search.

The exhaustive search tests every grid edge of the grid with the repair's own edge test
(``repair.sheet_edges`` with a box over the whole grid): what ``swept_edges`` must find on
every axis but the last, by another route (the candidates from hulls of the swept obstacles,
then the same test).  The scenes: two 1 cm slats a coarse grid misses, and random scenes of
``bench scenes``' family (convex and non-convex debris, the margins 0, 2 and 5 cm), 2- and
3-joint, on coarse grids.  The exhaustive search shares the edge test with what it checks, so
the oracle of test/oracles.py (plain-Python distances at dense samples) judges samples of both
sides: edges found come within the margin, edges left out near an obstacle stay clear of it.
"""

import math
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from oracles import edge_clearance, ref_clearance
from spacerobot_planner.bench.scenes import random_scenario
from spacerobot_planner.collision import CollisionChecker
from spacerobot_planner.config import load_scenario
from spacerobot_planner.cspace import build_cspace
from spacerobot_planner.motion import QUICK_STEP_RAD, MotionValidator
from spacerobot_planner.repair import sheet_edges
from spacerobot_planner.scene import Scene
from spacerobot_planner.swept import applies, swept_edges

CONFIG = Path(__file__).resolve().parent.parent / "config"
#: the oracle's samples along an edge, rad apart at most
ORACLE_STEP_RAD = math.radians(0.25)
#: how far a point of the links moves per radian of one joint at most (the reach, 1.4 + 2 + 2 m)
REACH_M = 5.4
#: the kernel's samples and the oracle's: a clearance within this of the margin decides nothing
TOL_M = REACH_M * (QUICK_STEP_RAD + ORACLE_STEP_RAD) / 2 + 1e-3


def _slats():
    """Return the paper's 3-DOF arm at 18 cells among two 1 cm slats (0.3 and 0.4 m long) that its grid misses."""
    base = load_scenario(CONFIG / "paper_3dof.yaml")
    slats = []
    for (x, y), ang, length in (((3.1, 1.2), 0.4, 0.3), ((-2.2, -2.6), 2.0, 0.4)):
        d = 0.5 * np.array([math.cos(ang), math.sin(ang)])
        n = 0.005 * np.array([-math.sin(ang), math.cos(ang)])
        c = np.array([x, y])
        slats.append(np.array([c - length * d - n, c + length * d - n, c + length * d + n, c - length * d + n]))
    scene = Scene(target=None, debris_m=tuple(slats), safety_margin_m=0.05)
    return replace(base.with_scene(scene), grid=base.grid_with_cells(18))


def _body_only(name, cells):
    """Return the scenario ``name`` with neither target nor debris: the spacecraft body its only obstacle."""
    base = load_scenario(CONFIG / f"{name}.yaml")
    return replace(base.with_scene(Scene(target=None, debris_m=(), safety_margin_m=0.05)),
                   grid=base.grid_with_cells(cells))


def _random(dof, seed, cells, min_debris=3):
    rng = np.random.default_rng([seed, dof, 7])
    while True:
        sc, _ = random_scenario(rng, dof)
        if len(sc.scene.debris_m) >= min_debris:
            return replace(sc, grid=sc.grid_with_cells(cells))


SCENES = {"two 1 cm slats, 3-DOF at 18 cells": _slats,
          # edges whose motion only comes near the body while a joint after the attitude turns
          "the 4-joint servicer and its body alone at 8 cells": lambda: _body_only("servicer_4joint", 8),
          # edges only the arcs' bulge beyond the hulls' chords finds (a 22.5° and a 30° step)
          **{f"random 3-DOF scene {s} at 16 cells": (lambda s=s: _random(3, s, 16)) for s in range(3)},
          **{f"random 3-DOF scene {s} at 12 cells": (lambda s=s: _random(3, s, 12, 0)) for s in (34, 37)},
          **{f"random 2-DOF scene {s} at 60 cells": (lambda s=s: _random(2, s, 60)) for s in range(3)}}


def _every_colliding_edge(occ, grid, motions):
    """Every grid edge between free nodes whose motion the repair's test finds colliding: the whole grid as its box."""
    return sheet_edges(occ, grid.periodic, (0,) * occ.ndim, motions, grid.lower_rad, grid.step_rad,
                       radius=max(occ.shape), max_tests=0)


@pytest.mark.parametrize("name", list(SCENES))
def test_swept_edges_are_every_colliding_edge_along_the_axes_but_the_last(name):
    sc = SCENES[name]()
    grid = sc.grid
    occ = build_cspace(sc.robot, sc.scene, grid, extra_margin_m=0.02).occupied
    motions = MotionValidator(CollisionChecker(sc.robot, sc.scene)).segment_test()
    assert applies(motions, grid.ndim)
    every = _every_colliding_edge(occ, grid, motions)
    along_last = np.isin(every[:, 1] - every[:, 0], (1, grid.shape[-1] - 1))       # the last axis' stride is 1
    expected = {tuple(e) for e in every[~along_last].tolist()}
    for parallel in (False, True):          # the kernels in one thread and on numba's threads
        found = swept_edges(occ, grid.periodic, grid.lower_rad, grid.step_rad, motions, parallel=parallel)
        assert {tuple(e) for e in found.tolist()} == expected, parallel
        assert len(found) == len(expected)
        assert found.dtype == np.int64 and np.all(found[:, 0] < found[:, 1])
    rng = np.random.default_rng(0)
    for a, b in found[rng.permutation(len(found))[:12]]:      # a sample judged by the oracle
        assert edge_clearance(sc, int(a), int(b)) < sc.scene.safety_margin_m + TOL_M
    # and edges it left out, off the last axis, whose ends are near an obstacle: clear by the oracle
    free = np.flatnonzero(~occ.reshape(-1))
    judged = 0
    for f in rng.permutation(free):
        if judged == 8:
            break
        coord = np.array(np.unravel_index(f, grid.shape))
        axis = int(rng.integers(0, grid.ndim - 1))
        up = coord.copy()
        up[axis] += 1
        if grid.periodic[axis]:
            up[axis] %= grid.shape[axis]
        elif up[axis] >= grid.shape[axis]:
            continue
        g = int(np.ravel_multi_index(tuple(up), grid.shape))
        edge = (min(int(f), g), max(int(f), g))
        if occ.reshape(-1)[g] or edge in expected:
            continue
        if min(ref_clearance(sc.robot, sc.scene, grid.config_of(c)) for c in (coord, up)) > 0.6:
            continue                        # far from every obstacle at both ends: not worth the dense samples
        assert edge_clearance(sc, *edge) > sc.scene.safety_margin_m - TOL_M, f"edge {edge} collides, not found"
        judged += 1
    assert judged == 8


def test_the_wall_and_random_scenes_have_edges_to_find():
    """The cases above are not empty: each kind has colliding edges off the last axis."""
    counts = []
    for name in ("two 1 cm slats, 3-DOF at 18 cells", "the 4-joint servicer and its body alone at 8 cells",
                 "random 3-DOF scene 0 at 16 cells", "random 2-DOF scene 0 at 60 cells"):
        sc = SCENES[name]()
        occ = build_cspace(sc.robot, sc.scene, sc.grid, extra_margin_m=0.02).occupied
        motions = MotionValidator(CollisionChecker(sc.robot, sc.scene)).segment_test()
        counts.append(len(swept_edges(occ, sc.grid.periodic, sc.grid.lower_rad, sc.grid.step_rad, motions)))
    assert min(counts) > 0, counts


_FORM_PROBE = """
import sys
import numba
sys.path.insert(0, {test_dir!r})
from test_swept import _slats
from spacerobot_planner import swept
from spacerobot_planner.collision import CollisionChecker
from spacerobot_planner.cspace import build_cspace
from spacerobot_planner.motion import MotionValidator
sc = _slats()
grid = sc.grid_with_cells(36)
occ = build_cspace(sc.robot, sc.scene, grid).occupied
motions = MotionValidator(CollisionChecker(sc.robot, sc.scene)).segment_test()
loaded = lambda: [len(k.signatures) > 0 for k in (swept._candidate_chunks, swept._tested_chunks,
                                                  swept._candidate_rows, swept._tested_all)]
numba.set_num_threads(1)
edges = swept.swept_edges(occ, grid.periodic, grid.lower_rad, grid.step_rad, motions)
print(len(edges), *loaded())
numba.set_num_threads(2)
swept.swept_edges(occ, grid.periodic, grid.lower_rad, grid.step_rad, motions)
print(*loaded())
"""


def test_one_thread_runs_no_parallel_loop():
    """
    With one numba thread, the swept edges run their one-thread kernels only; with two, the parallel ones.

    The planner gives the stage the cores other work leaves (``cores.fit_threads(any_size=True)``):
    a parallel loop on a machine where other work holds a core waits a time slice for the team
    member that lost it (a 36³ repair took 137 ms instead of 14.6 on the 2-core VM).  In a fresh
    process, numba's own dispatchers say which kernels ran (a kernel that never ran has no
    signature).
    """
    import numba
    if numba.config.NUMBA_NUM_THREADS < 2:
        pytest.skip("numba runs one thread here")
    out = subprocess.run([sys.executable, "-c", _FORM_PROBE.format(test_dir=str(Path(__file__).parent))],
                         capture_output=True, text=True, timeout=600, cwd=Path(__file__).parent.parent)
    assert out.returncode == 0, out.stderr[-3000:]
    first, second = out.stdout.split("\n")[-3:-1]
    count, *one = first.split()
    assert int(count) > 0 and one == ["False", "False", "True", "True"], out.stdout
    assert second.split()[:2] == ["True", "True"], out.stdout
