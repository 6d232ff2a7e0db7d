"""
Peers on the paper's scenes: ``python -m spacerobot_planner.bench peers [--runs 20] [--seed 0]``.

OMPL's RRTConnect followed by ``PathSimplifier.simplify`` (what a MoveIt user runs), on
the same start, goal and exact geometry as this planner: OMPL's state validity is the
project's own (``motion.MotionValidator``: clearance above the scene's margin, bounded
joints within bounds; periodic joints are SO(2)), and its motion check is OMPL's discrete
one at the planner's certified step (``planner.verify_step_rad``, 0.5°): the exact
clearance at samples at most that far apart, run by the project's kernel
(``motion.segment_free``) in one call per motion.  Each
simplified path is then checked by the project's certified check
(``MotionValidator.check``: the whole segment, not only the samples): the paths that fail
it graze an obstacle between OMPL's samples and are counted.

Per scene, interleaved in the same run: this planner's whole plan (a fresh planner: C-space,
field, descent, smoothing, trajectory), its cached replan (same target, a new start) and
RRTConnect + simplify; median, p90 and max of ``--runs`` each, and the ratios of the medians.
OMPL (the ``ompl`` wheel, ``requirements-bench.txt``) is optional: without it the bench says
so and exits 0.  Prints a table, then one JSON object per line.
"""
from __future__ import annotations

import argparse
import json
import gc
import math
import sys
import time

import numpy as np

from ..joint_space import unwrap_path
from ..motion import MotionValidator, motion_scratch, segment_free
from ..planner import Planner
from .plan import _new_start, _scenario, warm_up

SCENES = (("2dof", 180), ("3dof", 36))


def _ompl():
    try:
        from ompl import base as ob, geometric as og, util as ou
    except ImportError:
        return None
    return ob, og, ou


class OmplProblem:
    """OMPL's set-up for one scenario: the joint space, validity from ``validator``, RRTConnect."""

    def __init__(self, validator: MotionValidator, step_rad: float):
        ob, og, ou = _ompl()
        ou.setLogLevel(ou.LOG_WARN)
        self.ob, self.og = ob, og
        self.v = validator
        self.periodic = validator.periodic
        self.dof = len(self.periodic)
        space = ob.CompoundStateSpace()
        for lo, hi, per in zip(validator.lower_rad, validator.upper_rad, self.periodic):
            if per:
                space.addSubspace(ob.SO2StateSpace(), 1.0)
            else:
                sub = ob.RealVectorStateSpace(1)
                b = ob.RealVectorBounds(1)
                b.setLow(float(lo))
                b.setHigh(float(hi))
                sub.setBounds(b)
                space.addSubspace(sub, 1.0)
        self.space = space
        self.ss = og.SimpleSetup(space)
        self.ss.setStateValidityChecker(self._valid)
        si = self.ss.getSpaceInformation()
        si.setStateValidityCheckingResolution(float(step_rad) / space.getMaximumExtent())
        self._test = validator.segment_test(float(step_rad)).arrays()
        self._scratch = motion_scratch(self._test[0], self._test[2], self._test[4])
        problem = self

        class Motions(ob.MotionValidator):
            def checkMotion(self, s1, s2):
                return problem.motion_ok(s1, s2)
        self._motions = Motions(si)          # kept alive: OMPL holds a raw reference
        si.setMotionValidator(self._motions)
        self.ss.setPlanner(og.RRTConnect(si))
        self.ss.setup()
        self.checks = 0

    def close(self) -> None:
        """
        Drop OMPL's objects, the set-up first (it holds this object's validity callback).

        The set-up and the callbacks form a cycle through C++ that Python's collector cannot
        see: without this nanobind reports every one of them as leaked at the interpreter's exit.
        """
        self.ss = None
        self._motions = self.space = None

    def to_q(self, state) -> np.ndarray:
        q = np.empty(self.dof)
        for a in range(self.dof):
            s = state[a]
            q[a] = s.value if self.periodic[a] else s[0]
        return q

    def _state(self, q):
        st = self.space.allocState()
        for a in range(self.dof):
            if self.periodic[a]:
                st[a].value = float(math.remainder(q[a], 2 * math.pi))
            else:
                st[a][0] = float(q[a])
        return st

    def _valid(self, state) -> bool:
        self.checks += 1
        q = self.to_q(state)
        return bool(self.v.within_bounds(q[None, :])[0]) and float(self.v.clearance_m(q)) > self.v.margin_m

    def motion_ok(self, s1, s2) -> bool:
        """Check the shortest segment s1 → s2 as OMPL's discrete motion check does, at the step."""
        q = unwrap_path(np.stack([self.to_q(s1), self.to_q(s2)]), self.periodic)
        if not self.v.within_bounds(q[1:])[0]:
            return False
        return bool(segment_free(q[0], q[1], *self._test, *self._scratch))

    def solve(self, start, goal, time_limit_s: float):
        """(path (k, dof) rad or None, seconds of solve + simplify)."""
        self.ss.clear()
        self.ss.setStartAndGoalStates(self._state(start), self._state(goal))
        t0 = time.perf_counter()
        status = self.ss.solve(time_limit_s)
        if not self.ss.haveExactSolutionPath():
            return None, time.perf_counter() - t0, str(status)
        path = self.ss.getSolutionPath()
        self.ss.getPathSimplifier().simplify(path, time_limit_s)
        sec = time.perf_counter() - t0
        return np.array([self.to_q(s) for s in path.getStates()]), sec, str(status)


def _pcts(v) -> dict:
    a = np.asarray(v, dtype=float)
    return {"p50_s": float(np.median(a)), "p90_s": float(np.percentile(a, 90)), "max_s": float(a.max())}


def bench_scene(scene: str, cells: int, runs: int, time_limit_s: float) -> list:
    sc = _scenario(scene, cells)
    step = Planner(sc).settings.verify_step_rad
    validator = MotionValidator.for_scene(sc.robot, sc.scene, step_rad=step)
    peer = OmplProblem(validator, step)
    try:
        return _bench_runs(scene, sc, validator, peer, runs, time_limit_s)
    finally:
        peer.close()
        gc.collect()


def _bench_runs(scene: str, sc, validator, peer, runs: int, time_limit_s: float) -> list:
    """:func:`bench_scene`'s runs: this planner's fresh plan and cached replan, and ``peer``'s, interleaved."""
    cached = Planner(sc)
    cached.plan(sc.start_rad, sc.goal_rad)
    new_start = _new_start(sc, cached)
    ours, replans, rrt, grazing, failed, lengths = [], [], [], 0, 0, []
    for _ in range(runs):
        res = Planner(sc).plan(sc.start_rad, sc.goal_rad)
        ours.append(res.timings_s["total"])
        rep = cached.plan(new_start, sc.goal_rad)
        replans.append(rep.timings_s["total"])
        path, sec, status = peer.solve(sc.start_rad, sc.goal_rad, time_limit_s)
        rrt.append(sec)
        if path is None:
            failed += 1
            continue
        path = unwrap_path(path, validator.periodic)
        lengths.append(float(np.sum(np.linalg.norm(np.diff(path, axis=0), axis=1))))
        if not validator.check(path).ok:
            grazing += 1
    label = sc.grid.label()
    o, r, p = _pcts(ours), _pcts(replans), _pcts(rrt)
    row = {"stage": "peers", "scene": f"paper_{scene}", "grid": label, "runs": runs,
           "plan": o, "replan_cached": r, "rrtconnect_simplify": p,
           "plan_over_rrt": o["p50_s"] / p["p50_s"], "replan_over_rrt": r["p50_s"] / p["p50_s"],
           "rrt_grazing_paths": grazing, "rrt_failed": failed,
           "rrt_length_rad_p50": float(np.median(lengths)) if lengths else None,
           "plan_length_rad": res.path_length_rad if res.ok else None}
    return [row]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="bench peers", description=__doc__.strip().split("\n\n")[0])
    ap.add_argument("--runs", type=int, default=20)
    ap.add_argument("--seed", type=int, default=1, help="OMPL's random seed (> 0; set once per process)")
    ap.add_argument("--time-limit", type=float, default=5.0, help="OMPL's solve and simplify limit, s")
    args = ap.parse_args(argv)
    if _ompl() is None:
        print("bench peers: skipped: the optional 'ompl' wheel is not installed "
              "(pip install -r requirements-bench.txt)")
        return 0
    if args.seed < 1:
        print("bench peers: --seed: must be a positive integer (OMPL ignores 0)", file=sys.stderr)
        return 1
    _ompl()[2].RNG.setSeed(args.seed)
    warm_up("log_harmonic")
    print(f"bench peers: {args.runs} runs per scene, interleaved; ms: p50 / p90 / max")
    head = (f"{'scene':<11}{'grid':>10}  {'this planner, whole plan':>26}  {'cached replan':>22}  "
            f"{'RRTConnect + simplify':>24}  {'plan/RRT':>8}  {'replan/RRT':>10}  grazing")
    print(head + "\n" + "-" * len(head))
    rows = []
    for scene, cells in SCENES:
        (row,) = bench_scene(scene, cells, args.runs, args.time_limit)
        rows.append(row)

        def fmt(d):
            return f"{1e3 * d['p50_s']:.1f} / {1e3 * d['p90_s']:.1f} / {1e3 * d['max_s']:.1f}"
        print(f"{row['scene']:<11}{row['grid']:>10}  {fmt(row['plan']):>26}  {fmt(row['replan_cached']):>22}  "
              f"{fmt(row['rrtconnect_simplify']):>24}  {row['plan_over_rrt']:>8.2f}  {row['replan_over_rrt']:>10.2f}"
              f"  {row['rrt_grazing_paths']} of {args.runs - row['rrt_failed']}", flush=True)
    print("grazing: simplified RRTConnect paths whose straight segments fail the project's certified "
          "check (MotionValidator.check) although every sample OMPL checked was valid")
    for r in rows:
        print(json.dumps(r))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
