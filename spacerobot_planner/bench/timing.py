"""What the benchmarks share to time a call."""

from __future__ import annotations

import contextlib
import subprocess
import sys
import time

import numpy as np

__all__ = ["busy_processes", "load_phrase", "call_times_s", "median_s", "tail_stats"]


@contextlib.contextmanager
def busy_processes(count: int):
    """Run ``count`` busy-loop processes (a loaded machine) while the block runs; stop them after."""
    hogs = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(max(0, int(count)))]
    try:
        yield hogs
    finally:
        for h in hogs:              # only the processes started here
            h.kill()
            h.wait()


def load_phrase(count: int) -> str:
    """Return "2 busy-loop processes beside" for ``--load 2`` (:func:`busy_processes`), "" for none."""
    return f"{count} busy-loop process{'es' if count != 1 else ''} beside" if count else ""


def call_times_s(fn, repeats: int) -> list:
    """Return the wall time of each of ``repeats`` calls of ``fn()``, seconds."""
    out = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        out.append(time.perf_counter() - t0)
    return out


def median_s(fn, repeats: int) -> float:
    """Return the median wall time of ``repeats`` calls of ``fn()``, seconds."""
    return float(np.median(call_times_s(fn, repeats)))


def tail_stats(values_s, median_key: str = "median_s", count_key: str = "runs") -> dict:
    """Return the median (``median_key``), ``p90_s``, ``min_s``, ``max_s`` and the count (``count_key``) of seconds."""
    v = np.asarray(values_s, dtype=float)
    return {median_key: float(np.median(v)), "p90_s": float(np.percentile(v, 90)), "min_s": float(v.min()),
            "max_s": float(v.max()), count_key: int(v.size)}
