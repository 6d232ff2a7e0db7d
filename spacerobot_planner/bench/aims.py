"""
Issue 19's speed aims, measured in one run: ``python -m spacerobot_planner.bench aims [--skip NAMES] [--quick]``.

Runs the benchmarks that the aims name, each as its own ``main`` in this process
(``coldstart`` starts processes of its own), reads the JSON rows each prints, and prints
every aim against its limit as measured in this run (a time: its median, with its p90 and
max beside it): ``met``, ``missed``, ``not measured``, or ``not run``
(its benchmark skipped with ``--skip``, or unavailable: OMPL's wheel for ``peers``, ROS 2's
for ``latency``; the reason is printed).  The machine's speed drifts between runs (the
project's VM swings by a fifth within minutes), so an aim's verdict is only ever taken from
figures of one run, and the paper's Gauss–Seidel times (``bench plan``'s baseline, in the
same run) are printed beside them as the run's yardstick.

The benchmarks, in order: ``plan`` (the paper scenes at 181², 36³, 72³ and 120³; their fresh
plans, cached replans and the field against the Gauss–Seidel baseline), ``peers`` (OMPL's
RRTConnect + simplify on the paper scenes), ``scenes`` (200 random scenes per DOF),
``latency`` (the node: joint state → trajectory) and ``coldstart`` (``spacerobot-plan`` in a
fresh process).  ``--quick`` runs each with fewer repeats (a smoke run: its verdicts are
rougher).  Each benchmark's own output is written to ``--log`` (default: not kept) and
its time is printed as it ends.  Prints a table, then one JSON object per aim::

    {"stage": "aim", "aim": "...", "bench": "plan", "value": 7.01, "p90": 8.27, "max": 10.14,
     "unit": "ms", "limit": 5.0, "at_most": true, "met": false}
"""
from __future__ import annotations

import argparse
import contextlib
import importlib
import io
import json
import math
import os
import sys
import tempfile
import time
import traceback
from dataclasses import dataclass

from ..cores import cpu_limit, limit_text
from .latency import JOINT_STATE_AIM_S
from .scenes import AIM_MAX_OVER_MEDIAN, AIM_MOST_S

#: the benchmarks the aims read, in the order they run
BENCHES = ("plan", "peers", "scenes", "latency", "coldstart")

#: each benchmark's arguments: (full run, --quick run)
ARGS = {
    "plan": (["--cases", "2dof:180,3dof:36,3dof:72,3dof:120", "--repeats", "15"],
             ["--cases", "2dof:180,3dof:36,3dof:72,3dof:120", "--repeats", "3"]),
    "peers": (["--runs", "20"], ["--runs", "5"]),
    "scenes": (["--dof", "2,3", "--count", "200", "--oracle", "0"], ["--dof", "2,3", "--count", "40", "--oracle", "0"]),
    "latency": (["--repeats", "30", "--no-moving"], ["--repeats", "8", "--no-moving"]),
    "coldstart": (["--runs", "5"], ["--runs", "2"]),
}


def _row(rows, **match) -> dict | None:
    """Return the first row whose items include ``match``, or None."""
    for r in rows:
        if all(r.get(k) == v for k, v in match.items()):
            return r
    return None


#: the tails a time's row holds beside its median (bench plan's, latency's and coldstart's rows)
_TAILS = ("p90_s", "max_s")


@dataclass(frozen=True)
class Read:
    """
    A figure of a benchmark's rows: ``row[key] * scale`` of the first row whose items include ``match``.

    match: (name, value) pairs; tails: the same row's keys of its p90 and max (in ``key``'s
    units: :data:`_TAILS` for a time whose median is ``key``), or () for a figure without tails.
    """

    key: str
    scale: float = 1.0
    match: tuple = ()
    tails: tuple = ()

    def _value(self, row, key: str) -> float | None:
        v = None if row is None else row.get(key)
        return None if v is None else float(v) * self.scale

    def __call__(self, rows) -> float | None:
        """Return the figure, or None: no such row or value."""
        return self._value(_row(rows, **dict(self.match)), self.key)

    def tail(self, rows) -> tuple:
        """Return the figure's (p90, max) from its row, each None where the row has none."""
        row = _row(rows, **dict(self.match))
        return tuple(self._value(row, k) for k in self.tails) if self.tails else (None, None)


def _get(key: str, scale: float = 1.0, tails: tuple = (), **match) -> Read:
    """Return the :class:`Read` of ``row[key] * scale`` in the first row that matches ``match``."""
    return Read(key, scale, tuple(match.items()), tuple(tails))


@dataclass(frozen=True)
class Aim:
    """
    One of issue 19's aims.

    name: what is measured, for people; bench: the benchmark whose rows hold it; pick: its
    figure from those rows (in ``unit``: a :class:`Read`), None when they do not hold it; limit
    and at_most: met when the figure is at most (else at least) the limit.
    """

    name: str
    bench: str
    pick: Read
    limit: float
    unit: str
    at_most: bool = True

    def verdict(self, value: float | None) -> bool | None:
        """Return whether ``value`` meets the aim (None: not measured)."""
        if value is None or not math.isfinite(value):
            return None
        return value <= self.limit if self.at_most else value >= self.limit


_G2, _G3, _G72, _G120 = "181x181", "36x37x37", "72x73x73", "120x121x121"

#: The aims, as issue 19 states them (one place).
AIMS = (
    Aim("paper 2-DOF 181², whole plan (median)", "plan", _get("seconds", 1e3, _TAILS, stage="total", grid=_G2),
        5.0, "ms"),
    Aim("paper 3-DOF 36³, whole plan (median)", "plan", _get("seconds", 1e3, _TAILS, stage="total", grid=_G3),
        10.0, "ms"),
    Aim("paper 2-DOF plan / RRTConnect + simplify (medians)", "peers",
        _get("plan_over_rrt", stage="peers", scene="paper_2dof"), 1.0, "×"),
    Aim("paper 3-DOF plan / RRTConnect + simplify (medians)", "peers",
        _get("plan_over_rrt", stage="peers", scene="paper_3dof"), 1.0, "×"),
    Aim("paper 2-DOF cached replan (median)", "plan", _get("seconds", 1e3, _TAILS, stage="replan_cached", grid=_G2),
        1.0, "ms"),
    Aim("paper 3-DOF cached replan (median)", "plan", _get("seconds", 1e3, _TAILS, stage="replan_cached", grid=_G3),
        1.0, "ms"),
    Aim("node: joint state → trajectory (median)", "latency",
        _get("seconds", 1e3, _TAILS, stage="latency_joint_state"), 1e3 * JOINT_STATE_AIM_S, "ms"),
    Aim("paper 3-DOF 72³, whole plan (median)", "plan", _get("seconds", 1e3, _TAILS, stage="total", grid=_G72),
        40.0, "ms"),
    Aim("paper 3-DOF 120³, whole plan (median)", "plan", _get("seconds", 1e3, _TAILS, stage="total", grid=_G120),
        300.0, "ms"),
    Aim("field against the paper's Gauss–Seidel, 181²", "plan", _get("ratio", stage="field", grid=_G2), 100.0,
        "×", at_most=False),
    Aim("field against the paper's Gauss–Seidel, 36³", "plan", _get("ratio", stage="field", grid=_G3), 20.0,
        "×", at_most=False),
    Aim("random 2-DOF scenes: max / median of the plans", "scenes", _get("max_over_median", stage="aims", dof=2),
        AIM_MAX_OVER_MEDIAN, "×"),
    Aim("random 3-DOF scenes: max / median of the plans", "scenes", _get("max_over_median", stage="aims", dof=3),
        AIM_MAX_OVER_MEDIAN, "×"),
    Aim(f"random 3-DOF scenes: plans above {1e3 * AIM_MOST_S:g} ms", "scenes",
        _get("plans_above", stage="aims", dof=3), 0.0, "plans"),
    Aim("cold start of spacerobot-plan, paper 3-DOF (median)", "coldstart",
        _get("median_s", 1.0, _TAILS, case="spacerobot-plan"), 0.5, "s"),
)


def evaluate(rows_by_bench: dict, aims=AIMS) -> list:
    """
    Return one JSON row per aim from the benchmarks' rows.

    rows_by_bench: benchmark name → its JSON rows (a benchmark not run: absent).  Each row:
    ``stage`` "aim", the aim's ``name`` (as ``aim``), ``bench``, ``value`` (None: not
    measured: its benchmark not run, or no finite figure in its rows), ``p90`` and ``max`` (a
    time's tails in the same run, None for a figure without), ``unit``, ``limit``, ``at_most``
    and ``met`` (None: not measured).
    """
    out = []
    for a in aims:
        rows = rows_by_bench.get(a.bench)
        value = None if rows is None else a.pick(rows)
        p90, most = (None, None) if rows is None else a.pick.tail(rows)
        # not finite: not measured (and strict JSON)
        value, p90, most = (v if v is not None and math.isfinite(v) else None for v in (value, p90, most))
        out.append({"stage": "aim", "aim": a.name, "bench": a.bench, "value": value, "p90": p90, "max": most,
                    "unit": a.unit, "limit": a.limit, "at_most": a.at_most, "met": a.verdict(value)})
    return out


def _json_rows(text: str) -> list:
    """Return the JSON objects among the lines of ``text``."""
    rows = []
    for line in text.splitlines():
        line = line.strip()
        if line.startswith("{"):
            try:
                obj = json.loads(line)
            except ValueError:
                continue
            if isinstance(obj, dict):
                rows.append(obj)
    return rows


@contextlib.contextmanager
def _captured_stderr():
    """
    Send the process's stderr to a temporary file; yield a reader of what was written.

    File descriptor 2 (the C libraries' writes: ROS 2's logging) and Python's ``sys.stderr`` alike.
    """
    if sys.stderr is not None:
        sys.stderr.flush()
    saved = os.dup(2)
    try:
        with tempfile.TemporaryFile() as tmp, io.StringIO() as py_err:
            os.dup2(tmp.fileno(), 2)

            def read() -> str:
                """Return what was written to stderr so far (the C libraries' first, then Python's)."""
                tmp.flush()
                tmp.seek(0)
                return tmp.read().decode(errors="replace") + py_err.getvalue()
            with contextlib.redirect_stderr(py_err):
                yield read
    finally:
        os.dup2(saved, 2)
        os.close(saved)


def run_bench(name: str, argv: list, log) -> tuple:
    """
    Run benchmark ``name``'s ``main(argv)`` with its output captured; return ``(rows, why not)``.

    rows: its JSON rows, or None when it did not run (then ``why not`` says why: not importable,
    a non-zero status, an exception it raised, or the line it printed instead of rows, e.g. a
    skip).  Its standard output and its stderr (the C libraries' too: the node's ROS 2 log), and
    the traceback of an exception, go to ``log`` (a text file, or None: not kept).
    """
    try:
        mod = importlib.import_module(f"spacerobot_planner.bench.{name}")
    except ImportError as e:
        return None, f"not importable here: {e}"
    buf = io.StringIO()
    said, raised, tb = "", "", ""      # a SystemExit's message; an exception; its traceback
    with _captured_stderr() as err:
        try:
            with contextlib.redirect_stdout(buf):
                rc = mod.main(list(argv))
        except SystemExit as e:           # argparse's errors, a bench's own exit
            rc = e.code if isinstance(e.code, int) else (0 if e.code is None else 1)
            said = "" if isinstance(e.code, int) or e.code is None else str(e.code)
        except Exception as e:            # one benchmark's failure leaves the others' verdicts
            rc, raised, tb = 1, f"raised {type(e).__name__}: {e}", traceback.format_exc()
        err_text = err()
    out_text = buf.getvalue()
    if log is not None:
        log.write(f"===== bench {name} {' '.join(argv)}\n{out_text}\n----- stderr\n{err_text}{tb}\n")
        log.flush()
    if raised:
        return None, raised
    if rc:
        last = said or next((ln for ln in reversed((out_text + err_text).splitlines()) if ln.strip()), "")
        return None, f"exited with status {rc}" + (f": {last.strip()}" if last else "")
    rows = _json_rows(out_text)
    if not rows:
        first = next((ln for ln in out_text.splitlines() if ln.strip()), "no output")
        return None, first.strip()
    return rows, ""


def _fmt(value, unit: str) -> str:
    """Return a figure for the table: ``-`` when not measured."""
    if value is None:
        return "-"
    if unit == "plans":
        return f"{value:.0f}"
    return f"{value:.2f} {unit}" if unit != "×" else f"{value:.2f}×"


def print_table(aims_rows: list, why_not: dict, yardstick: str) -> None:
    """Print the aims: measured (a time: its median, p90 and max), limit, verdict (and why an aim was not measured)."""
    print(f"\nbench aims: issue 19's aims, each measured in this run{yardstick}")
    head = f"{'aim':<54}{'measured':>12}{'p90':>11}{'max':>11}{'limit':>12}  verdict"
    print(head + "\n" + "-" * len(head))
    for r in aims_rows:
        limit = ("≤ " if r["at_most"] else "≥ ") + _fmt(r["limit"], r["unit"])
        if r["met"] is None:
            verdict = (f"not run (bench {r['bench']}: {why_not[r['bench']]})" if r["bench"] in why_not
                       else f"not measured (no figure in bench {r['bench']}'s rows)")
        else:
            verdict = "met" if r["met"] else "missed"
        print(f"{r['aim']:<54}{_fmt(r['value'], r['unit']):>12}{_fmt(r['p90'], r['unit']):>11}"
              f"{_fmt(r['max'], r['unit']):>11}{limit:>12}  {verdict}")
    met = sum(r["met"] is True for r in aims_rows)
    measured = sum(r["met"] is not None for r in aims_rows)
    not_run = sum(r["met"] is None and r["bench"] in why_not for r in aims_rows)
    print(f"{met} of {measured} measured aims met ({not_run} not run, {len(aims_rows) - measured - not_run} "
          "not measured)")


def _yardstick(rows_by_bench: dict) -> str:
    """Return ' (the paper's Gauss–Seidel: ... ms at 181², ... at 36³)' from bench plan's rows, or ''."""
    rows = rows_by_bench.get("plan") or []
    parts = []
    for grid, label in ((_G2, "181²"), (_G3, "36³")):
        r = _row(rows, stage="field", grid=grid)
        if r is not None and r.get("baseline_seconds"):
            parts.append(f"{1e3 * r['baseline_seconds']:.0f} ms at {label}")
    return f" (the paper's Gauss–Seidel, the run's yardstick: {', '.join(parts)})" if parts else ""


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="bench aims", description=__doc__.strip().split("\n\n")[0])
    ap.add_argument("--skip", default="", help=f"comma list of benchmarks not to run ({', '.join(BENCHES)})")
    ap.add_argument("--quick", action="store_true", help="fewer repeats: a smoke run, rougher verdicts")
    ap.add_argument("--log", default=None, help="write each benchmark's own output to this file")
    args = ap.parse_args(argv)
    skip = {s.strip() for s in args.skip.split(",") if s.strip()}
    unknown = skip - set(BENCHES)
    if unknown:
        ap.error(f"--skip: unknown benchmark(s) {', '.join(sorted(unknown))}; choose from {', '.join(BENCHES)}")
    rows_by_bench, why_not = {}, {}
    log = open(args.log, "w", encoding="utf-8") if args.log else None
    try:
        print(f"bench aims: {', '.join(b for b in BENCHES if b not in skip)}"
              f"{' (--quick)' if args.quick else ''} on {os.cpu_count()} cores (load {os.getloadavg()[0]:.1f}"
              f"{limit_text(cpu_limit())})", flush=True)
        for name in BENCHES:
            if name in skip:
                why_not[name] = "skipped (--skip)"
                continue
            t0 = time.perf_counter()
            rows, why = run_bench(name, ARGS[name][1 if args.quick else 0], log)
            spent_s = time.perf_counter() - t0
            if rows is None:
                why_not[name] = why
                print(f"  bench {name}: not run ({why}), {spent_s:.1f} s", flush=True)
            else:
                rows_by_bench[name] = rows
                print(f"  bench {name}: {len(rows)} rows in {spent_s:.1f} s", flush=True)
    finally:
        if log is not None:
            log.close()
    out = evaluate(rows_by_bench)
    print_table(out, why_not, _yardstick(rows_by_bench))
    for r in out:
        print(json.dumps(r))
    return 0


if __name__ == "__main__":
    sys.exit(main())
