"""
Keep freed memory in the process heap, so that a solve does not page-fault its arrays in afresh.

Every solve allocates its arrays anew (the node graph, the band problems, the multigrid
levels, the conjugate-gradient vectors: megabytes at 181², a hundred at 72³).  glibc's
malloc serves a block above its mmap threshold by a fresh ``mmap`` and gives it back to
the system when it is freed, and trims the top of the heap once more than its trim
threshold is free there; either way the next solve touches new pages, each a page fault
with a zeroing (about 6 µs each on the project's virtual machine; 900 of them at 181²,
15 000 at 72³: 40 % of the field's time at 181² and 36³).

:func:`keep_heap` raises both thresholds, once per process: blocks up to
``MMAP_THRESHOLD_BYTES`` come from the heap, and freed memory stays there (up to
``TRIM_THRESHOLD_BYTES`` free at the top), to be reused by the next solve.  It is what
real-time ROS 2 nodes do for the same reason (there with the thresholds at their maximum
and the pages locked); the cost is a process that keeps the heap of its largest solve.
It is a process-wide setting of the C library: applied only on glibc, and not where the
user set glibc's own ``MALLOC_MMAP_THRESHOLD_`` / ``MALLOC_TRIM_THRESHOLD_``.
"""
from __future__ import annotations

import ctypes
import ctypes.util
import os
import sys

#: Blocks up to this many bytes come from the heap (glibc's default: 128 KiB, rising to 32 MiB).
MMAP_THRESHOLD_BYTES = 64 << 20
#: Free memory at the heap's top is given back to the system above this many bytes.
TRIM_THRESHOLD_BYTES = 256 << 20
_M_TRIM_THRESHOLD = -1          # glibc's mallopt parameters (malloc.h)
_M_MMAP_THRESHOLD = -3

_STATE = {"applied": None}


def keep_heap() -> bool:
    """
    Raise glibc's mmap and trim thresholds (see the module doc), once per process.

    Returns whether they are set (False off glibc, where the user set them by the
    environment, or where ``mallopt`` refused).
    """
    if _STATE["applied"] is None:
        _STATE["applied"] = _apply()
    return _STATE["applied"]


def _apply() -> bool:
    if not sys.platform.startswith("linux"):
        return False
    if "MALLOC_MMAP_THRESHOLD_" in os.environ or "MALLOC_TRIM_THRESHOLD_" in os.environ:
        return False
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        mallopt = libc.mallopt
        libc.gnu_get_libc_version        # glibc only (musl has no mallopt thresholds)
    except (OSError, AttributeError):
        return False
    mallopt.argtypes = (ctypes.c_int, ctypes.c_int)
    mallopt.restype = ctypes.c_int
    return bool(mallopt(_M_MMAP_THRESHOLD, MMAP_THRESHOLD_BYTES)) and bool(
        mallopt(_M_TRIM_THRESHOLD, TRIM_THRESHOLD_BYTES))
