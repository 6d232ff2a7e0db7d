"""
A rate-limited log of rejected inputs (no rclpy): one line per source, then counts.

A wrong input repeated at sensor rate (a joint_states publisher that sends NaN at 100
Hz) would otherwise log one line per message.  Per source: the first rejection after a
quiet period is logged whole; the ones after it are counted, and at most once per
``period_s`` a line says how many there were and the latest reason
(``joint_states: 99 more rejected in the last 5.0 s (latest: ...)``).  :meth:`flush`
(the node's diagnostics timer) writes the count of a flood that has stopped.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Callable

__all__ = ["RejectionLog", "REJECT_LOG_PERIOD_S"]

#: at most one line per source this often during a flood, seconds
REJECT_LOG_PERIOD_S = 5.0


@dataclass
class _Source:
    line_t: float          # when the last line of this source was written
    last_t: float          # when the last rejection came
    pending: int = 0       # rejections since that line
    latest: str = ""


class RejectionLog:
    """Decide which rejections are logged: see the module docstring."""

    def __init__(self, period_s: float = REJECT_LOG_PERIOD_S, clock: Callable[[], float] = time.monotonic):
        self.period_s = float(period_s)
        self._clock = clock
        self._sources: dict[str, _Source] = {}

    def reject(self, source: str, reason: str) -> str | None:
        """Record one rejection; return the line to log now, or None (counted for a later line)."""
        now = self._clock()
        st = self._sources.get(source)
        if st is None or (st.pending == 0 and now - st.last_t >= self.period_s):
            self._sources[source] = _Source(line_t=now, last_t=now, latest=reason)
            return f"{source}: {reason}"
        st.pending += 1
        st.latest = reason
        st.last_t = now
        return self._summary(source, st, now) if now - st.line_t >= self.period_s else None

    def flush(self) -> list:
        """Return the count lines of the sources whose period has passed with rejections not yet logged."""
        now = self._clock()
        return [self._summary(source, st, now) for source, st in self._sources.items()
                if st.pending and now - st.line_t >= self.period_s]

    @staticmethod
    def _summary(source, st, now) -> str:
        line = (f"{source}: {st.pending} more rejected in the last {now - st.line_t:.1f} s "
                f"(latest: {st.latest})")
        st.pending, st.line_t = 0, now
        return line
