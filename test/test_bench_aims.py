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
    whole = out["paper 2-DOF 181², whole plan (median)"]
    assert whole["value"] == pytest.approx(1e3 * total["seconds"])
    assert (whole["p90"], whole["max"]) == pytest.approx((1e3 * total["p90_s"], 1e3 * total["max_s"]))
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
    start = out["cold start of spacerobot-plan, paper 3-DOF (median)"]
    assert (start["p90"], start["max"]) == pytest.approx((0.49, 0.5))       # the row's tails beside its median
    assert out["field against the paper's Gauss–Seidel, 181²"]["p90"] is None  # a ratio: no tails


def _fake_bench(monkeypatch, name, main):
    mod = types.ModuleType(f"spacerobot_planner.bench.{name}")
    mod.main = main
    monkeypatch.setitem(sys.modules, f"spacerobot_planner.bench.{name}", mod)


def test_a_benchmark_that_fails_leaves_the_others(monkeypatch, capsys, tmp_path):
    def broken(argv):
        print("half a table")
        raise RuntimeError("the machine caught fire")

    def refused(argv):
        import argparse
        argparse.ArgumentParser(prog="bench refused").parse_args(argv)     # an unknown option: exit 2

    def says_why(argv):
        raise SystemExit("bench says_why: --cases: expected items like 2dof:180")
    _fake_bench(monkeypatch, "broken", broken)
    _fake_bench(monkeypatch, "silent", lambda argv: print("bench silent: skipped: no wheel") or 0)
    _fake_bench(monkeypatch, "refused", refused)
    _fake_bench(monkeypatch, "says_why", says_why)
    with open(tmp_path / "log.txt", "w") as log:
        rows, why = aims.run_bench("broken", [], log)
        assert rows is None and why == "raised RuntimeError: the machine caught fire"
        rows, why = aims.run_bench("refused", ["--nonsense"], log)
        assert rows is None and why.startswith("exited with status 2") and "--nonsense" in why
        rows, why = aims.run_bench("says_why", [], log)
        assert rows is None and why == "exited with status 1: bench says_why: --cases: expected items like 2dof:180"
    rows, why = aims.run_bench("silent", [], None)
    assert rows is None and why == "bench silent: skipped: no wheel"
    rows, why = aims.run_bench("no_such_bench", [], None)
    assert rows is None and "not importable" in why
    captured = capsys.readouterr()
    assert captured.out == "" and "nonsense" not in captured.err     # captured, not printed
    logged = (tmp_path / "log.txt").read_text()
    assert "half a table" in logged and "Traceback" in logged and "unrecognized arguments: --nonsense" in logged


def test_skip_names_only_known_benchmarks(monkeypatch, capsys):
    def no_bench(name, argv, log):
        raise AssertionError(f"bench {name} ran")
    monkeypatch.setattr(aims, "run_bench", no_bench)
    with pytest.raises(SystemExit):
        aims.main(["--skip", "plan,nonsense"])
    assert "nonsense" in capsys.readouterr().err


def test_the_aims_name_what_the_benchmarks_print():
    """
    The grid labels, options and row names each aim and run relies on, from the benchmarks themselves.

    The paper scenes' grids at the aims' cells; every option in ``ARGS`` one its benchmark takes;
    the row names of the benchmarks that need a wheel or a node to run (peers, latency) and of
    coldstart, in their modules' own text.
    """
    import inspect
    from spacerobot_planner.bench import coldstart, latency, peers, plan
    from test_docs import _flags_of
    assert {plan._scenario(scene, cells).grid.label() for scene, cells in
            (("2dof", 180), ("3dof", 36), ("3dof", 72), ("3dof", 120))} == {aims._G2, aims._G3, aims._G72, aims._G120}
    for name, runs in aims.ARGS.items():
        takes = _flags_of(f"spacerobot_planner.bench.{name}")
        for argv in runs:
            assert {a for a in argv if a.startswith("--")} <= takes, (name, argv)
    assert '"latency_joint_state"' in inspect.getsource(latency)
    assert '"spacerobot-plan"' in inspect.getsource(coldstart)
    assert 'f"paper_{scene}"' in inspect.getsource(peers) and ("2dof", 180) in peers.SCENES


def test_an_aim_without_a_finite_figure_is_not_measured():
    plan = [{"stage": "field", "grid": "181x181", "ratio": float("nan")}]
    out = _by_name(aims.evaluate({"plan": plan}))
    r = out["field against the paper's Gauss–Seidel, 181²"]
    assert r["value"] is None and r["met"] is None


def test_bench_scenes_load_runs_its_busy_processes_and_says_so(capsys, monkeypatch):
    """``bench scenes --load 1``: its busy process runs while the scenes are planned, then stops; the output says so."""
    import contextlib
    import json

    from spacerobot_planner.bench import scenes
    started, running = [], []
    real = scenes.busy_processes

    @contextlib.contextmanager
    def watched(count):
        with real(count) as hogs:
            started.extend(hogs)
            yield hogs
            running.extend(h.poll() is None for h in hogs)     # still running once the scenes are planned

    monkeypatch.setattr(scenes, "busy_processes", watched)
    assert scenes.main(["--dof", "2", "--count", "2", "--oracle", "0", "--slowest", "0", "--load", "1"]) == 0
    out = capsys.readouterr().out
    assert "2 scenes (seed 0, 1 busy-loop process beside)" in out
    rows = [json.loads(line) for line in out.splitlines() if line.startswith("{")]
    assert rows and all(r["load"] == 1 for r in rows)
    assert len(started) == 1 and running == [True]
    assert started[0].poll() is not None                          # stopped after the run


def test_bench_latency_pauses_as_told_and_says_so(capsys, monkeypatch):
    """
    ``bench latency --pause-s``: the pause after each joint-state replan is the one given; every row says so.

    The bench's sleeps are recorded (the target replans keep their own 50 ms); a pause that is
    not a number of seconds >= 0 is refused naming the option.
    """
    import json
    import time as real_time

    from spacerobot_planner.bench import latency
    slept = []

    class _Time:
        def __getattr__(self, name):
            return getattr(real_time, name)

        @staticmethod
        def sleep(s):
            slept.append(s)
            real_time.sleep(s)
    monkeypatch.setattr(latency, "time", _Time())
    assert latency.main(["--repeats", "2", "--no-moving", "--pause-s", "0.0023"]) == 0
    out = capsys.readouterr().out
    assert "joint-state replans 2.3 ms after the last trajectory" in out
    rows = [json.loads(line) for line in out.splitlines() if line.startswith("{")]
    js = next(r for r in rows if r["stage"] == "latency_joint_state")
    assert js["repeats"] == 2 and all(r["pause_s"] == 0.0023 for r in rows if "seconds" in r)
    assert slept.count(0.0023) == 2 and slept.count(latency.PAUSE_S) == 2
    for bad in ("-1", "nan"):
        with pytest.raises(SystemExit):
            latency.main(["--pause-s", bad])
        assert "--pause-s" in capsys.readouterr().err
