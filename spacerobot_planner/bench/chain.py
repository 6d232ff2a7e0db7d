"""
The chain after the path on replans joined to a moving arm: ``python -m spacerobot_planner.bench chain``.

What a node's replan costs after its plan, and how often it cannot be joined, without the
node's threads and processes around it (deterministic: the same figures on any machine but
the times).  Per scene (``--scenes``, config files): the scene's plan is published from rest
as the node does (``adapters.post_process``: the executing trajectory, its published points);
then, at ``--starts`` instants spread over it, for each plan time in ``--took`` (s, of the
1 s horizon), the arm following it: the replan starts at the horizon point
(``replanning.plan_start``), its path to the same goal is planned with the scene's cached
C-space and field, leaving the horizon point along the arm's direction
(``replanning.join_direction``), and the chain joins it to the moving arm (``post_process(join=...)``, the
session's lead: ``trajectory.start_lead_s`` + ``session.CHAIN_ALLOWANCE_S``).

Printed per scene: the joined chains (published on the first try, refused: the session would
plan again, with its reasons), the re-timings for the controller's overshoot per published
chain, the chain's time (median, p90, max of the median of ``--repeats`` calls each) and, as
the baseline measured in the same run, one time-optimal timing of the same joined path
(``replanning.joined_motion``) with the ratio of the medians; the same new paths' chains from
rest at the horizon point, for comparison.  Then one JSON object per line.
"""
from __future__ import annotations

import argparse
import json
import re
from collections import Counter
from pathlib import Path

import numpy as np

from ..adapters import post_process
from ..config import load_scenario
from ..motion import MotionValidator
from ..planner import Planner
from ..replanning import Executing, join_direction, joined_motion, plan_start
from ..session import CHAIN_ALLOWANCE_S
from ..settings import SessionSettings
from ..trajectory import HorizonPassed
from .timing import median_s, tail_stats

CONFIG = Path(__file__).resolve().parent.parent.parent / "config"
S = 1_000_000_000            # ns per s


def _median_s(fn, repeats: int):
    """Return (``timing.median_s`` of ``fn``, s; the last call's result, or the refusal it raised)."""
    out = []

    def call():
        try:
            out.append(fn())
        except (ValueError, HorizonPassed) as e:
            out.append(e)
    return median_s(call, repeats), out[-1]


def _reason(e: Exception) -> str:
    """Return a refusal's reason without its numbers (to count them)."""
    return re.sub(r"[-+]?\d[\d.e+-]*", "N", str(e))[:90]


def bench_scene(name: str, starts: int, took_s, repeats: int) -> dict:
    sc = load_scenario(CONFIG / f"{name}.yaml")
    settings = SessionSettings()
    lead_s = settings.start_lead_s + CHAIN_ALLOWANCE_S
    planner = Planner(sc)
    motions = MotionValidator.for_scene(sc.robot, sc.scene)      # the session's
    first = planner.plan(sc.start_rad, sc.goal_rad)
    if not first.ok:
        raise RuntimeError(f"{name}: the scene's own plan failed ({first.code}: {first.reason})")
    published = post_process(sc, first.path_rad, start_rad=sc.start_rad, motions=motions)
    ex = Executing(published.dense, published.indices, 100 * S)
    duration = published.dense.duration_s
    periodic = sc.robot.planned_periodic
    joined, rest, base, refused, retimings, errors = [], [], [], Counter(), Counter(), 0
    for frac in np.linspace(0.05, 0.85, starts):
        now = ex.start_ns + int(frac * duration * S)
        q_now = published.dense.positions_rad[int(np.searchsorted(published.dense.times_s, frac * duration))]
        start, join, _ = plan_start(ex, now, q_now, now, settings.horizon_s, settings.follow_tolerance_rad, periodic)
        if join is None:
            continue
        res = planner.plan(start, sc.goal_rad, start_tangent=join_direction(join))     # as the session plans it
        if not res.ok:
            errors += 1
            continue
        for took in took_s:
            later = now + int(took * S)
            t, out = _median_s(lambda: post_process(sc, res.path_rad, join=join, now_ns=later, lead_s=lead_s,
                                                    motions=motions), repeats)
            if isinstance(out, Exception):
                refused[_reason(out)] += 1
                continue
            joined.append(t)
            retimings[out.retimings] += 1
            tb, _ = _median_s(lambda: joined_motion(sc, join, res.path_rad, later, lead_s=lead_s,
                                                    checker=motions), repeats)
            base.append(tb)
        t, out = _median_s(lambda: post_process(sc, res.path_rad, start_rad=start, motions=motions),
                           repeats)
        if not isinstance(out, Exception):
            rest.append(t)
    return {"stage": "chain", "scene": name, "grid": sc.grid.label(), "joined": len(joined),
            "refused": sum(refused.values()), "refusals": dict(refused), "plan_errors": errors,
            "retimings": {str(k): v for k, v in sorted(retimings.items())},
            **({"chain": tail_stats(joined), "timing": tail_stats(base),
                "ratio": float(np.median(joined) / np.median(base))} if joined else {}),
            **({"from_rest": tail_stats(rest)} if rest else {})}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.strip().splitlines()[0])
    ap.add_argument("--scenes", default="paper_3dof,paper_2dof,servicer_3dof",
                    help="config files (without .yaml), comma-separated")
    ap.add_argument("--starts", type=int, default=12, help="instants on the executing trajectory per scene")
    ap.add_argument("--took", default="0.01,0.1,0.25",
                    help="plan times, s, comma-separated (the join is the lead after: within the 1 s horizon)")
    ap.add_argument("--repeats", type=int, default=3, help="calls per chain (their median)")
    args = ap.parse_args(argv)
    took = [float(x) for x in args.took.split(",")]
    rows = [bench_scene(name, args.starts, took, args.repeats) for name in args.scenes.split(",")]

    def tail(st):
        return f"{1e3 * st['median_s']:.2f} / {1e3 * st['p90_s']:.2f} / {1e3 * st['max_s']:.2f}"

    print("bench chain: replans joined to a moving arm; ms: median / p90 / max")
    print(f"{'scene':<15}{'grid':<12}{'joined':>7}{'refused':>8}  {'re-timings (count: chains)':<28}"
          f"{'chain':>22}{'one timing':>22}{'ratio':>7}{'from rest':>22}")
    for r in rows:
        rt = ", ".join(f"{k}: {v}" for k, v in r["retimings"].items())
        chain = tail(r["chain"]) if "chain" in r else "-"
        timing = tail(r["timing"]) if "timing" in r else "-"
        ratio = f"{r['ratio']:.2f}" if "ratio" in r else "-"
        from_rest = tail(r["from_rest"]) if "from_rest" in r else "-"
        print(f"{r['scene']:<15}{r['grid']:<12}{r['joined']:>7}{r['refused']:>8}  {rt:<28}{chain:>22}"
              f"{timing:>22}{ratio:>7}{from_rest:>22}")
    for r in rows:
        for why, n in sorted(r["refusals"].items(), key=lambda kv: -kv[1]):
            print(f"  {r['scene']}: refused {n}x: {why}")
    for r in rows:
        print(json.dumps(r))
    return 0
