"""
The plan's termination token: one flag that every long-running loop polls.

OMPL's PlannerTerminationCondition, for this planner: :class:`Termination` is a
``threading.Event`` whose state also lives in a one-element int64 numpy array,
``token.flag``.  Python code polls ``token.is_set()`` (or :meth:`Termination.check`, which
raises :class:`Cancelled`); a numba kernel gets ``token.flag`` as an argument and reads
``flag[0] != 0`` between its units of work (a C-space row, a CG iteration, a sweep) with
no GIL, as the field's kernels read their deadline.  A kernel that sees the flag returns
early with a partial result; its Python caller then raises :class:`Cancelled`, so no
partial C-space or field is ever returned or cached.

Why a flag array is safe here: numba gives no ``volatile``, but a kernel loop that stores
into any array cannot have the flag's load hoisted out of it (numba emits no alias
information), so each poll reads memory.  The polling loops all store.

A plain object with ``is_set()`` (a ``threading.Event``, or None for never) still works
where a token is taken: :meth:`Termination.of` wraps it, and then Python-level polls see it
(and raise the flag for the kernels from then on), but a kernel already running does not.
"""

from __future__ import annotations

import threading
import time

import numpy as np

__all__ = ["Termination", "Cancelled", "stall"]


class Cancelled(Exception):
    """A stage stopped because its termination token was set; nothing it built is kept."""


class Termination(threading.Event):
    """
    A plan's termination token (see the module doc).

    ``set()`` raises the kernels' flag and wakes :meth:`wait`; ``clear()`` lowers both.
    """

    def __init__(self):
        super().__init__()
        self.flag = np.zeros(1, dtype=np.int64)     # read by kernels: flag[0] != 0 = stop

    def set(self) -> None:
        self.flag[0] = 1
        super().set()

    def clear(self) -> None:
        self.flag[0] = 0
        super().clear()

    def is_set(self) -> bool:
        return bool(self.flag[0])

    def check(self) -> None:
        """Raise :class:`Cancelled` when set."""
        if self.is_set():
            raise Cancelled()

    @staticmethod
    def of(cancel) -> "Termination":
        """Return ``cancel`` as a token: itself, a never-set token for None, else a wrapper."""
        if isinstance(cancel, Termination):
            return cancel
        if cancel is None:
            return Termination()
        return _Linked(cancel)


class _Linked(Termination):
    """A token over a foreign ``is_set()`` object, seen at Python-level polls."""

    def __init__(self, other):
        super().__init__()
        self._other = other
        if other.is_set():
            self.set()

    def is_set(self) -> bool:
        if not self.flag[0] and self._other.is_set():
            self.set()
        return bool(self.flag[0])

    def wait(self, timeout=None) -> bool:
        end = None if timeout is None else time.monotonic() + timeout
        while not self.is_set():
            left = 0.05 if end is None else min(0.05, end - time.monotonic())
            if left <= 0:
                return False
            super().wait(left)
        return True


def stall(token, seconds: float, polls: bool = True) -> None:
    """
    Test aid: spend ``seconds`` in the current stage.

    ``polls``: as a stage that polls the token (returns at once when it is set);
    else as one that does not (a plain sleep, which no cancel shortens).
    """
    if seconds <= 0:
        return
    if polls and token is not None:
        Termination.of(token).wait(seconds)
    else:
        time.sleep(seconds)
