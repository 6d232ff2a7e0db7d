"""What the benchmarks share to time a call."""

from __future__ import annotations

import time

import numpy as np

__all__ = ["median_s"]


def median_s(fn, repeats: int) -> float:
    """Return the median wall time of ``repeats`` calls of ``fn()``, seconds."""
    out = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        out.append(time.perf_counter() - t0)
    return float(np.median(out))
