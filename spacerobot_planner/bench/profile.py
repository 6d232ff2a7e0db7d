"""
Per-step profile of plans: where a plan's time goes, step by step.

For ``bench plan --profile`` and ``bench scenes --profile``:
:class:`StepProfile` wraps named functions of the planning core (module attributes looked up
at call time by their Python callers, and a few methods) with wall-clock timers while it is
active, and restores them on exit; the core itself is not changed.  Steps nest (the field's
graph build is inside the field): each row is the step's own total, and its ``parent`` says
what it is part of.  Numba kernels are wrapped only where Python code calls them, so a
kernel's time is counted once, by its Python caller.

    with StepProfile() as prof:
        planner.plan(start, goal)
    prof.rows(plans=1)      # [{"step": ..., "parent": ..., "calls": ..., "ms_per_plan": ...}]
"""
from __future__ import annotations

import functools
import importlib
import time

#: (step, parent step or "", module, attribute[.method]): every step the profile times.
STEPS = (
    ("cspace", "", "spacerobot_planner.planner", "build_cspace"),
    ("goal nodes", "", "spacerobot_planner.pipeline", "PlanRun.goal_nodes"),
    ("field", "", "spacerobot_planner.planner", "Planner._solve"),
    ("graph build", "field", "spacerobot_planner.field", "node_graph"),
    ("graph: face codes", "graph build", "spacerobot_planner.field.graph", "grid_codes"),
    ("graph: nodes and neighbours", "graph build", "spacerobot_planner.field.graph", "_node_tables"),
    ("bands (harmonic.solve)", "field", "spacerobot_planner.field.harmonic", "solve"),
    ("band window", "bands (harmonic.solve)", "spacerobot_planner.field.harmonic", "_steps_from_known"),
    ("band problem", "bands (harmonic.solve)", "spacerobot_planner.field.harmonic", "_band_problem"),
    ("band solve (multigrid)", "bands (harmonic.solve)", "spacerobot_planner.field.multigrid", "solve"),
    ("hierarchy: fine level", "band solve (multigrid)", "spacerobot_planner.field.multigrid", "Hierarchy.__init__"),
    ("hierarchy: coarse levels", "band solve (multigrid)", "spacerobot_planner.field.multigrid",
     "Hierarchy.coarsen"),
    ("PCG iterations", "band solve (multigrid)", "spacerobot_planner.field.multigrid", "_pcg"),
    ("fine level on cells: layout", "band solve (multigrid)", "spacerobot_planner.field.structured", "laid_out"),
    ("level 1 on cells: layout", "band solve (multigrid)", "spacerobot_planner.field.structured", "coarse_layout"),
    ("PCG iterations on cells", "band solve (multigrid)", "spacerobot_planner.field.multigrid", "_spcg"),
    ("geometric levels: set-up", "band solve (multigrid)", "spacerobot_planner.field.geometric", "levels"),
    ("PCG iterations, geometric levels", "band solve (multigrid)", "spacerobot_planner.field.geometric", "pcg"),
    ("ascent check", "bands (harmonic.solve)", "spacerobot_planner.field.harmonic", "ascent_defects"),
    ("ascent repair", "bands (harmonic.solve)", "spacerobot_planner.field.harmonic", "_repair_ascent"),
    ("descent", "", "spacerobot_planner.planner", "descend"),
    ("repair: swept edges", "", "spacerobot_planner.swept", "swept_edges"),
    ("repair: colliding edges", "", "spacerobot_planner.pipeline", "sheet_edges"),
    ("repair: re-solve", "", "spacerobot_planner.pipeline", "PlanRun.resolve"),
    ("retried grid: joined check", "", "spacerobot_planner.pipeline", "PlanRun.check_joined"),
    ("no-path diagnosis", "", "spacerobot_planner.pipeline", "PlanRun.no_field_path_failure"),
    ("segment checks (ends)", "", "spacerobot_planner.pipeline", "PlanRun.segment_ok"),
    ("smoothing", "", "spacerobot_planner.pipeline", "smooth_path"),
    ("shortcut candidates", "smoothing", "spacerobot_planner.smoothing", "shortcut_indices"),
    ("spline + refinements", "smoothing", "spacerobot_planner.smoothing", "_refined_spline"),
    ("spline fit", "spline + refinements", "spacerobot_planner.smoothing", "spline_through"),
    ("motion checks", "", "spacerobot_planner.motion", "MotionValidator.check"),
    ("kept motion checks", "", "spacerobot_planner.motion", "MotionValidator.check_kept"),
    ("certify kernel", "motion checks", "spacerobot_planner.motion", "check_kernel"),
    ("trajectory", "", "spacerobot_planner.pipeline", "timed_motion"),
    ("time parameterisation", "trajectory", "spacerobot_planner.timing", "time_parameterize"),
    ("densify", "time parameterisation", "spacerobot_planner.trajectory", "densify_path"),
    ("spline model", "time parameterisation", "spacerobot_planner.trajectory", "_path_model"),
    ("constraint rows", "time parameterisation", "spacerobot_planner.trajectory", "_constraint_rows"),
    ("backward pass", "time parameterisation", "spacerobot_planner.trajectory", "_backward"),
    ("forward pass", "time parameterisation", "spacerobot_planner.trajectory", "_solve"),
    ("rounding margins", "time parameterisation", "spacerobot_planner.trajectory", "_rounding_margins"),
    ("sample states", "time parameterisation", "spacerobot_planner.trajectory", "_sample_states"),
    ("reaction report", "trajectory", "spacerobot_planner.timing", "reaction_report"),
)


class StepProfile:
    """Time the :data:`STEPS` while active (a context manager); ``rows`` reports them."""

    def __init__(self, steps=STEPS):
        self.steps = steps
        self.seconds = {s[0]: 0.0 for s in steps}
        self.calls = {s[0]: 0 for s in steps}
        self._saved = []

    def _wrap(self, name, fn):
        sec, calls = self.seconds, self.calls

        @functools.wraps(fn)
        def timed(*a, **k):
            t = time.perf_counter()
            try:
                return fn(*a, **k)
            finally:
                sec[name] += time.perf_counter() - t
                calls[name] += 1
        return timed

    def __enter__(self):
        for name, _, mod_name, attr in self.steps:
            owner = importlib.import_module(mod_name)
            *path, last = attr.split(".")
            for p in path:
                owner = getattr(owner, p)
            if not hasattr(owner, last):
                raise AttributeError(f"bench profile: step {name!r}: {mod_name}.{attr} does not exist "
                                     "(the core changed: update bench/profile.py STEPS)")
            fn = owner.__dict__[last] if isinstance(owner, type) else getattr(owner, last)
            self._saved.append((owner, last, fn))
            setattr(owner, last, self._wrap(name, fn))
        return self

    def __exit__(self, *exc):
        for owner, last, fn in reversed(self._saved):
            setattr(owner, last, fn)
        self._saved.clear()
        return False

    def rows(self, plans: int) -> list:
        """One dict per step that ran: step, parent, calls per plan, ms per plan."""
        out = []
        for name, parent, _, _ in self.steps:
            if self.calls[name]:
                out.append({"step": name, "parent": parent, "calls_per_plan": self.calls[name] / plans,
                            "ms_per_plan": 1e3 * self.seconds[name] / plans})
        return out


def print_rows(title: str, rows: list) -> None:
    """Print a profile as an indented table (children under their parents)."""
    depth = {}
    for r in rows:
        depth[r["step"]] = depth.get(r["parent"], -1) + 1 if r["parent"] else 0
    print(f"  profile: {title}")
    for r in rows:
        label = "  " * depth[r["step"]] + r["step"]
        print(f"    {label:<40}{r['ms_per_plan']:>9.3f} ms{r['calls_per_plan']:>8.1f} calls")
