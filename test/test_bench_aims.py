"""
``bench aims``: issue 19's aims read from the benchmarks' own rows, and judged against their limits.

The figures are never judged here (speed is not a test assertion): what is checked is that
each aim reads the row its benchmark really prints (two benchmarks run for it, on their
smallest settings), that a verdict follows the aim's limit and direction, and that a
benchmark that fails or is not run leaves the other aims measured.
"""
import sys
import types

import pytest

from spacerobot_planner.bench import aims
from spacerobot_planner.bench.timing import tail_stats


def _by_name(rows):
    return {r["aim"]: r for r in rows}


def test_the_aims_read_the_rows_bench_plan_and_bench_scenes_print():
    plan, why = aims.run_bench("plan", ["--cases", "2dof:180", "--repeats", "1"], None)
    assert plan is not None, why
    scenes, why = aims.run_bench("scenes", ["--dof", "2", "--count", "3", "--oracle", "0", "--slowest", "0"], None)
    assert scenes is not None, why
    out = _by_name(aims.evaluate({"plan": plan, "scenes": scenes}))
    total = next(r for r in plan if r["stage"] == "total" and r["grid"] == "181x181")
    field = next(r for r in plan if r["stage"] == "field" and r["grid"] == "181x181")
    replan = next(r for r in plan if r["stage"] == "replan_cached" and r["grid"] == "181x181")
    family = next(r for r in scenes if r["stage"] == "aims" and r["dof"] == 2)
    assert out["paper 2-DOF 181², whole plan (median)"]["value"] == pytest.approx(1e3 * total["seconds"])
    assert out["paper 2-DOF cached replan (median)"]["value"] == pytest.approx(1e3 * replan["seconds"])
    assert out["field against the paper's Gauss–Seidel, 181²"]["value"] == pytest.approx(
        field["baseline_seconds"] / field["seconds"])
    assert out["random 2-DOF scenes: max / median of the plans"]["value"] == pytest.approx(family["max_over_median"])
    for name in ("paper 2-DOF 181², whole plan (median)", "paper 2-DOF cached replan (median)",
                 "field against the paper's Gauss–Seidel, 181²", "random 2-DOF scenes: max / median of the plans"):
        assert out[name]["met"] in (True, False), name
    # the cases and benchmarks that did not run: not measured, not judged
    for name in ("paper 3-DOF 36³, whole plan (median)", "paper 3-DOF 120³, whole plan (median)",
                 "random 3-DOF scenes: plans above 30 ms", "node: joint state → trajectory (median)",
                 "paper 2-DOF plan / RRTConnect + simplify (medians)",
                 "cold start of spacerobot-plan, paper 3-DOF (median)"):
        assert out[name]["value"] is None and out[name]["met"] is None, name


def test_a_verdict_follows_the_limit_and_its_direction():
    plan = [{"stage": "total", "grid": "181x181", "seconds": 0.005},            # at the limit: met
            {"stage": "total", "grid": "36x37x37", "seconds": 0.0101},          # above it: missed
            {"stage": "field", "grid": "181x181", "ratio": 99.9},               # at least 100: missed
            {"stage": "field", "grid": "36x37x37", "ratio": 20.0}]              # met
    scenes = [{"stage": "aims", "dof": 3, "max_over_median": 2.5, "plans_above": 1},
              {"stage": "aims", "dof": 2, "max_over_median": 3.5, "plans_above": 0}]
    cold = [{"bench": "coldstart", "case": "spacerobot-plan", **tail_stats([0.4, 0.45, 0.5])}]
    out = _by_name(aims.evaluate({"plan": plan, "scenes": scenes, "coldstart": cold}))
    expected = {"paper 2-DOF 181², whole plan (median)": (5.0, True),
                "paper 3-DOF 36³, whole plan (median)": (10.1, False),
                "field against the paper's Gauss–Seidel, 181²": (99.9, False),
                "field against the paper's Gauss–Seidel, 36³": (20.0, True),
                "random 3-DOF scenes: max / median of the plans": (2.5, True),
                "random 3-DOF scenes: plans above 30 ms": (1.0, False),
                "random 2-DOF scenes: max / median of the plans": (3.5, False),
                "cold start of spacerobot-plan, paper 3-DOF (median)": (0.45, True)}
    for name, (value, met) in expected.items():
        assert out[name]["value"] == pytest.approx(value), name
        assert out[name]["met"] is met, name
    assert out["paper 2-DOF cached replan (median)"]["met"] is None       # no such row: not measured


def test_a_benchmark_that_fails_leaves_the_others(monkeypatch, capsys):
    broken = types.ModuleType("spacerobot_planner.bench.broken")

    def main(argv):
        print("half a table")
        raise RuntimeError("the machine caught fire")
    broken.main = main
    silent = types.ModuleType("spacerobot_planner.bench.silent")
    silent.main = lambda argv: print("bench silent: skipped: no wheel") or 0
    monkeypatch.setitem(sys.modules, "spacerobot_planner.bench.broken", broken)
    monkeypatch.setitem(sys.modules, "spacerobot_planner.bench.silent", silent)
    rows, why = aims.run_bench("broken", [], None)
    assert rows is None and "RuntimeError: the machine caught fire" in why
    rows, why = aims.run_bench("silent", [], None)
    assert rows is None and why == "bench silent: skipped: no wheel"
    rows, why = aims.run_bench("no_such_bench", [], None)
    assert rows is None and "not importable" in why
    assert capsys.readouterr().out == ""          # the benchmarks' own output is captured, not printed


def test_skip_names_only_known_benchmarks(capsys):
    with pytest.raises(SystemExit):
        aims.main(["--skip", "plan,nonsense"])
    assert "nonsense" in capsys.readouterr().err
