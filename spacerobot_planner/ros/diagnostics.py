"""
The planner node's ``/diagnostics``: two statuses built from the session's outcomes and the rejected inputs.

- ``<node>: planner``: the node's state and the outcome of the last finished request
  (a superseded one is not an outcome): OK when planned (or cancelled), ERROR with the
  reason when it failed; its values name the request (number, reason, goal), the code,
  the stage times and the session's values (``session.Outcome.values``);
- ``<node>: input``: the last rejected input (topic message, goal, parameter) and the
  count of all, OK again once a good request follows.

A topic's rejections are logged rate-limited (``rejections.RejectionLog``: the first
whole, then counts); a parameter's or a goal's (one per request of a person or a
client) all.  No publishing here: the node publishes :meth:`NodeDiagnostics.statuses`.
"""

from __future__ import annotations

import math
import threading
import time

import numpy as np
from diagnostic_msgs.msg import DiagnosticStatus

from .rejections import RejectionLog

__all__ = ["NodeDiagnostics", "RATE_LIMITED", "request_values"]

#: inputs at sensor rate: their rejections are logged rate-limited
RATE_LIMITED = ("joint_states", "target_pose", "goal_joint_state", "attitude")


def request_values(req) -> dict:
    """Diagnostics values naming a request (``session.Request``): its number and its goal (target or joints)."""
    out = {"request": f"#{req.gen}", "request_reason": req.why}
    if req.joint_goal is not None:
        out["joint_goal_deg"] = np.round(np.degrees(req.joint_goal), 3).tolist()
    elif req.scenario.scene.target is not None:
        t = req.scenario.scene.target
        out["target_m"] = [round(float(v), 4) for v in t.center_m]
        out["target_yaw_deg"] = round(math.degrees(t.yaw_rad), 3)
    return out


class NodeDiagnostics:
    """The last finished request and the rejected inputs, as diagnostic statuses."""

    def __init__(self):
        self._lock = threading.Lock()
        self.last_outcome = None         # session.Outcome of the last finished request (not superseded)
        self._last_req = None
        self._rejected = None            # (source, code, reason, monotonic time) of the last bad input
        self.rejected_total = 0
        self.rejections = RejectionLog()

    def record(self, req, outcome) -> None:
        """Make the planner status describe this finished request from now on, and only it."""
        with self._lock:
            self.last_outcome, self._last_req = outcome, req

    def accepted(self) -> None:
        """Note a good request: the input status is OK again."""
        with self._lock:
            self._rejected = None

    @property
    def last_rejection(self) -> tuple | None:
        """(source, code, reason) of the last bad input (a topic's message, a goal, a parameter), or None."""
        with self._lock:
            return None if self._rejected is None else self._rejected[:3]

    def reject(self, source: str, code: str, reason: str) -> tuple:
        """
        Count a bad input; return (the line to log or None, whether the status changed).

        Topics' lines are rate-limited (None while a flood goes on: the counts follow in
        :meth:`flush`).
        """
        line = f"{source}: {code}: {reason}"
        if source in RATE_LIMITED:
            line = self.rejections.reject(source, f"{code}: {reason}")
        with self._lock:
            news = self._rejected is None or self._rejected[:3] != (source, code, reason)
            self._rejected = (source, code, reason, time.monotonic())
            self.rejected_total += 1
        return line, news

    def flush(self) -> list:
        """Return the count lines of floods of bad input due now."""
        return self.rejections.flush()

    def statuses(self, name: str, state: str, node_values: dict | None = None) -> list:
        """
        [(name, level, message, values)]: the planner status and the input status of node ``name``.

        ``node_values``: the planner status's values that are the node's, not a request's (the controller's kind).
        """
        with self._lock:
            out, req, rej, total = self.last_outcome, self._last_req, self._rejected, self.rejected_total
        values = {"state": state, **(node_values or {})}
        if out is None:
            level, message = DiagnosticStatus.OK, f"{state}: no request finished yet"
        else:
            values.update(request_values(req))
            values["code"] = out.code
            if out.result is not None:
                values.update({f"time_{k}_ms": f"{1e3 * v:.2f}" for k, v in out.result.timings_s.items()})
            values.update(out.values)
            if out.ok and out.values.get("finishes_executing") == "true":     # nothing new could take over
                level, message = DiagnosticStatus.WARN, f"{state}: request #{req.gen}: {out.reason}"
                values["reason"] = out.reason
            elif out.ok:
                level, message = DiagnosticStatus.OK, f"{state}: request #{req.gen} planned"
            elif out.code == "cancelled":
                level, message = DiagnosticStatus.OK, f"{state}: request #{req.gen} cancelled: {out.reason}"
                values["reason"] = out.reason
            else:
                level, message = DiagnosticStatus.ERROR, f"failed: request #{req.gen}: {out.reason}"
                values["reason"] = out.reason
        statuses = [(f"{name}: planner", level, message, values)]
        ivalues = {"rejected_total": total}
        if rej is None:
            statuses.append((f"{name}: input", DiagnosticStatus.OK, "inputs ok", ivalues))
        else:
            source, code, reason, t = rej
            ivalues.update({"source": source, "code": code, "reason": reason,
                            "age_s": f"{time.monotonic() - t:.1f}"})
            statuses.append((f"{name}: input", DiagnosticStatus.ERROR, f"rejected {source}: {reason}", ivalues))
        return statuses
