"""
A node's log lines at rcutils' cost: rclpy's logger less its look-up of the caller on every line.

rclpy's ``RcutilsLogger.log`` finds the frame that called it on every line
(``rcutils_logger``'s caller search: ``inspect.getframeinfo`` and ``os.path.realpath`` for
each frame it walks, and a ``CallerId``, which stat and read the source files): 0.3-0.5 ms a
line measured with Kilted's rclpy 9 in the planner node's worker thread, where a cached
replan's whole record and send takes 0.5 ms.
rcutils itself (the console line and /rosout) takes a few microseconds.  :class:`LogLines`
hands rcutils the very arguments rclpy's logger hands it (severity, the logger's name, the
text, the calling frame's ``CallerId``: function, file, line), the ``CallerId`` of each
call site found once.  No filters (once, throttle, skip_first): a line is logged when the
logger is enabled for its severity, as rclpy's logger without filters does.  Where rclpy
has no such binding (another rclpy), the logger's own methods log the line.
"""

from __future__ import annotations

import sys

from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
from rclpy.impl.rcutils_logger import CallerId
from rclpy.logging import LoggingSeverity

__all__ = ["LogLines"]

#: rcutils' log call and its severity check, as ``RcutilsLogger.log`` makes them (None: use the logger)
_EMIT = getattr(_rclpy, "rclpy_logging_rcutils_log", None)
_ENABLED = getattr(_rclpy, "rclpy_logging_logger_is_enabled_for", None)


class LogLines:
    """The lines of one rclpy logger (``node.get_logger()``), from call sites whose caller is found once."""

    def __init__(self, logger):
        self.logger = logger
        self._callers = {}            # (code object, line) of a call site -> its CallerId

    def log(self, severity: LoggingSeverity, text: str) -> bool:
        """
        Log ``text`` at ``severity`` as the logger's ``log`` method called on the calling line would.

        Returns whether it was logged (the logger is enabled for the severity).
        """
        if _EMIT is None or _ENABLED is None:
            return self._by_the_logger(severity, text)
        name = self.logger.name
        if not _ENABLED(name, severity):
            return False
        frame = sys._getframe(1)
        site = (frame.f_code, frame.f_lineno)
        caller = self._callers.get(site)
        if caller is None:
            caller = self._callers[site] = CallerId(frame)
        _EMIT(severity, name, text, caller.function_name, caller.file_path, caller.line_number)
        return True

    def _by_the_logger(self, severity: LoggingSeverity, text: str) -> bool:
        """Log through the logger's own method of the severity (rclpy ties a call site to one severity)."""
        log = self.logger
        if severity >= LoggingSeverity.FATAL:
            return log.fatal(text)
        if severity >= LoggingSeverity.ERROR:
            return log.error(text)
        if severity >= LoggingSeverity.WARN:
            return log.warning(text)
        if severity >= LoggingSeverity.INFO:
            return log.info(text)
        return log.debug(text)
