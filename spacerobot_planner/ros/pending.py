"""
What a node still owes its clients when it goes: every accepted call gets its answer.

A plan_capture goal and a ~/replan call are coroutines that the node's executor runs; the
answer goes out in a step of that coroutine (and, for a goal, in a task after it).  When
the node stops:

- in a lifecycle transition (a callback of the executor), the answers go out after the
  transition returns, so the servers they need are destroyed later (:meth:`retire`: a
  whole timer period after the last call was answered);
- after the spinning ended (planner_node's main after Ctrl-C, destroy_node),
  :meth:`drain` spins the node's executor until they are answered (or, when another
  thread still runs the calls, waits for it), for at most ``DRAIN_S``.
"""

from __future__ import annotations

import threading
import time
from typing import Callable

__all__ = ["PendingAnswers", "DRAIN_S", "FLUSH_S"]

#: at shutdown, the longest the calls in flight are given to send their answers, s
DRAIN_S = 2.0
#: the executor sends a goal's result in a task after the goal's own: spun this long more, s
FLUSH_S = 0.2


class PendingAnswers:
    """The plan_capture goals and ~/replan calls of a node not yet answered; see the module docstring."""

    def __init__(self, node, log: Callable[[str, str], None]):
        self._node = node
        self._log = log                  # log(level, text)
        self.goals = {}                  # goal id bytes -> the goal's request
        self.replans = 0                 # ~/replan calls awaiting their plans
        self.runner = None               # the thread that runs the calls' coroutines (the executor's)
        self._retired = []               # destroy callables of servers kept until the calls are answered
        self._timer = None
        self._idle = False

    def count(self) -> int:
        """Return how many calls are still to be answered."""
        return len(self.goals) + self.replans

    def running(self) -> None:
        """Note that this thread runs the calls (called from their coroutines)."""
        self.runner = threading.current_thread()

    def drain(self, timeout_s: float = DRAIN_S) -> None:
        """Let the calls in flight (their requests finished) send their answers; bounded by ``timeout_s``."""
        ex, runner = self._node.executor, self.runner
        if not self.count() or ex is None:          # (in no executor: nothing can run them)
            return
        spin = runner is None or runner is threading.current_thread() or not runner.is_alive()
        deadline = time.monotonic() + timeout_s
        flushed = None
        while self._node.context.ok():
            now = time.monotonic()
            if now >= deadline or (flushed is not None and now >= flushed):
                break
            if not self.count() and flushed is None:
                flushed = now + FLUSH_S
            if spin:
                try:
                    ex.spin_once(timeout_sec=0.02)
                except Exception:      # noqa: BLE001 - the executor or context is going away
                    break
            else:
                time.sleep(0.02)
        if self.count():
            self._log("warning", f"{self.count()} plan_capture goal(s) or ~/replan call(s) were not "
                      f"answered within {timeout_s:g} s")

    def retire(self, destroy: Callable[[], None]) -> None:
        """Call ``destroy`` (of a server) now, or once no call waits for an answer."""
        if not self.count():
            destroy()
            return
        self._retired.append(destroy)
        if self._timer is None:
            self._timer = self._node.create_timer(FLUSH_S, self.reap)

    def reap(self, now: bool = False) -> None:
        """Timer: destroy the retired servers a whole period after the last call was answered (or ``now``)."""
        idle, self._idle = self._idle, not self.count()
        if not now and not (idle and self._idle):
            return
        done, self._retired = self._retired, []
        for destroy in done:
            destroy()
        if self._timer is not None:
            self._node.destroy_timer(self._timer)
            self._timer = None
