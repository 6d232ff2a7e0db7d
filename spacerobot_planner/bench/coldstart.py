"""
Cold start of ``spacerobot-plan``: a fresh process, its caches filled, to the first plan.

The caches a second start of any install finds: numba's (the warm-up run below fills it) and
Python's bytecode of the package (``worker.compile_package`` first: an interpreter started with
``PYTHONDONTWRITEBYTECODE`` set, as on this project's VM (and a CI machine like it), would never write it, and every
start would compile the package's sources again, about 0.12 s).

Runs ``spacerobot-plan --params-file FILE --quiet`` (the console script's code,
``tools.entry.plan``) ``--runs`` times as a new process each, and in the same run, interleaved:

- ``interpreter``: ``python -c pass``, the floor;
- ``numpy + numba imports``: what every kernel module needs before it is defined;
- ``numba first cached kernel``: those imports plus one call of a one-line kernel loaded
  from numba's cache, as numba starts on its own (its target set-up happens at the first
  load, whatever the kernel, and imports SciPy's BLAS);
- ``spacerobot-plan, numba as numba starts``: the baseline, the same plan with numba's own
  import (with its coverage support's), its own loading of the cached kernels (their linking
  bitcode parsed), its own target set-up, and the interpreter's exit with its cycle collections
  (``tools.cli.main`` where the console script calls ``jit_cache.import_numba`` and
  ``tools.cli.run``): what those save, measured in the run.

Each CLI run also reports, from inside the process (``_probe``), where its time went:
importing the package, loading each kernel from numba's cache (count and seconds), and the
rest of the plan.  Figures are wall seconds: median, p90 and max over the runs.

``python -m spacerobot_planner.bench coldstart [--params-file F] [--runs N]``
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from .timing import tail_stats

_PKG = Path(__file__).resolve().parent.parent
_PARAMS = _PKG.parent / "config" / "paper_3dof.yaml"

#: Run inside the CLI's process: phases and numba cache loads, as one JSON line on stderr.
_PROBE = r"""
import json, sys, time
t0 = time.perf_counter()
if "--baseline" not in sys.argv:        # as the console script's entry (tools.entry.plan)
    from spacerobot_planner.jit_cache import import_numba
    import_numba()
import numba.core.caching as caching
loads = [0, 0.0]
_load = caching.Cache.load_overload
def load_overload(self, *a, **k):
    s = time.perf_counter()
    try:
        return _load(self, *a, **k)
    finally:
        loads[0] += 1
        loads[1] += time.perf_counter() - s
caching.Cache.load_overload = load_overload
t1 = time.perf_counter()
from spacerobot_planner.tools import cli
if "--baseline" in sys.argv:            # numba as numba starts, the interpreter's own exit
    sys.argv.remove("--baseline")
    cli.start_numba = lambda: None
    cli.run = cli.main
t2 = time.perf_counter()
rc = cli.run(sys.argv[1:])
t3 = time.perf_counter()
print(json.dumps({"numba_import_s": t1 - t0, "package_import_s": t2 - t1, "main_s": t3 - t2,
                  "kernel_loads": loads[0], "kernel_load_s": loads[1], "rc": rc}), file=sys.stderr)
"""

_KERNEL = "from numba import njit\n@njit(cache=True)\ndef one(x):\n    return x + 1.0\n"


def _wall(cmd, env=None, cwd=None) -> tuple:
    t0 = time.perf_counter()
    done = subprocess.run(cmd, capture_output=True, text=True, env=env, cwd=cwd)
    wall = time.perf_counter() - t0
    if done.returncode not in (0, 2):
        raise RuntimeError(f"{' '.join(cmd)} failed ({done.returncode}):\n{done.stderr[-2000:]}")
    return wall, done.stderr


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.strip().splitlines()[0])
    ap.add_argument("--params-file", default=str(_PARAMS))
    ap.add_argument("--runs", type=int, default=7)
    args = ap.parse_args(argv)
    py = sys.executable
    from ..worker import compile_package
    compile_package()
    with tempfile.TemporaryDirectory() as tmp:
        Path(tmp, "one_kernel.py").write_text(_KERNEL)
        kernel_env = dict(os.environ, PYTHONPATH=tmp + os.pathsep + os.environ.get("PYTHONPATH", ""))
        cases = {
            "interpreter": ([py, "-c", "pass"], None),
            "numpy + numba imports": ([py, "-c", "import numpy, numba"], None),
            "numba first cached kernel": ([py, "-c", "import one_kernel; one_kernel.one(1.0)"], kernel_env),
            "spacerobot-plan": ([py, "-c", _PROBE, "--params-file", args.params_file, "--quiet"], None),
            "spacerobot-plan, numba as numba starts": (
                [py, "-c", _PROBE, "--params-file", args.params_file, "--quiet", "--baseline"], None),
        }
        for cmd, env in cases.values():          # warm-up: numba's cache of the kernel, the OS file cache
            _wall(cmd, env)
        walls = {name: [] for name in cases}
        probes = {}
        for _ in range(args.runs):
            for name, (cmd, env) in cases.items():
                w, err = _wall(cmd, env)
                walls[name].append(w)
                if name.startswith("spacerobot-plan"):
                    probes.setdefault(name, []).append(json.loads(err.strip().splitlines()[-1]))
    rows = [{"bench": "coldstart", "case": name, **tail_stats(v)} for name, v in walls.items()]
    for name, runs in probes.items():
        for key in ("numba_import_s", "package_import_s", "kernel_load_s", "main_s"):
            rows.append({"bench": "coldstart", "case": f"{name}: {key[:-2]}", **tail_stats([p[key] for p in runs])})
    loads = sorted({p["kernel_loads"] for runs in probes.values() for p in runs})
    ratio = tail_stats(walls["spacerobot-plan"])["median_s"] / tail_stats(
        walls["spacerobot-plan, numba as numba starts"])["median_s"]
    print(f"bench coldstart: {Path(args.params_file).name}, {args.runs} runs each, interleaved; "
          f"wall seconds of a fresh process, numba's cache and the package's bytecode filled "
          f"(load {os.getloadavg()[0]:.1f})")
    print(f"{'case':<56}{'median':>9}{'p90':>9}{'max':>9}")
    for r in rows:
        print(f"{r['case']:<56}{r['median_s']:>9.3f}{r['p90_s']:>9.3f}{r['max_s']:>9.3f}")
    print(f"spacerobot-plan against numba as numba starts (medians): {ratio:.2f}×")
    print(f"kernels loaded from numba's cache per CLI run: {', '.join(map(str, loads))} (the first load "
          f"includes numba's target set-up; the package import includes numba's and numpy's)")
    for r in rows:
        print(json.dumps(r))
    return 0


if __name__ == "__main__":
    sys.exit(main())
