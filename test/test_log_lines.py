"""
``ros/log_lines.py``: a line logged through ``LogLines`` is the line rclpy's logger sends.

The oracle is rclpy's own logger called on the same source line (the same caller: function,
file, line): both lines are read back from /rosout, where rcutils puts every field it was given.
"""

import threading
import time

import pytest
import rclpy
from rcl_interfaces.msg import Log
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.logging import LoggingSeverity

from spacerobot_planner.ros.log_lines import LogLines


@pytest.fixture
def node():
    ctx = Context()
    rclpy.init(context=ctx)
    n = rclpy.create_node("log_lines_test", context=ctx)
    ex = SingleThreadedExecutor(context=ctx)
    ex.add_node(n)
    spin = threading.Thread(target=ex.spin, daemon=True)
    spin.start()
    try:
        yield n
    finally:
        ex.shutdown()
        spin.join(5.0)
        n.destroy_node()
        rclpy.shutdown(context=ctx)


def _lines_of(node, got, n, timeout_s=60.0):
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        mine = [m for m in list(got) if m.name == node.get_logger().name]
        if len(mine) >= n:
            return mine
        time.sleep(0.01)
    raise AssertionError(f"{len(mine)} of {n} lines on /rosout within {timeout_s} s")


def _fields(m: Log) -> tuple:
    return m.level, m.name, m.msg, m.file, m.function, m.line


def test_a_line_is_the_line_rclpys_logger_sends_from_the_same_call_site(node):
    got = []
    node.create_subscription(Log, "/rosout", got.append, 100)
    probe = node.get_logger().get_child("probe")     # its own name: its lines are never counted below
    end = time.monotonic() + 60.0
    while not any(m.name == probe.name for m in list(got)):     # until the subscription hears the node's rosout
        assert time.monotonic() < end, "no line of the node on /rosout within 60 s"
        probe.info("discovery")
        time.sleep(0.05)
    lines, logger = LogLines(node.get_logger()), node.get_logger()
    info, warn, error = LoggingSeverity.INFO, LoggingSeverity.WARN, LoggingSeverity.ERROR
    # each line of the pair on one source line: the same caller (rclpy's logger: one severity a call site)
    sent = [(lines.log(info, "plan #7 ok in 1.2 ms"), logger.log("plan #7 ok in 1.2 ms", info)),
            (lines.log(warn, "a warning"), logger.log("a warning", warn))]
    sent.append((lines.log(error, "an error: ünïcode ✓"), logger.log("an error: ünïcode ✓", error)))
    sent.append((lines.log(info, "second"), logger.log("second", info)))
    assert sent == [(True, True)] * 4
    mine = _lines_of(node, got, 8)
    assert len(mine) == 8
    for ours, theirs in zip(mine[0::2], mine[1::2]):
        assert _fields(ours) == _fields(theirs)
    assert [m.msg for m in mine[0::2]] == ["plan #7 ok in 1.2 ms", "a warning", "an error: ünïcode ✓", "second"]
    assert mine[0].function == "test_a_line_is_the_line_rclpys_logger_sends_from_the_same_call_site"
    assert mine[0].file == __file__


def test_a_severity_the_logger_is_not_enabled_for_is_not_logged(node):
    logger = node.get_logger()
    logger.set_level(LoggingSeverity.WARN)
    try:
        lines = LogLines(logger)
        assert (lines.log(LoggingSeverity.INFO, "quiet"), logger.log("quiet", LoggingSeverity.INFO)) == (False, False)
        assert lines.log(LoggingSeverity.WARN, "loud") is True
    finally:
        logger.set_level(LoggingSeverity.UNSET)


def test_without_rclpys_binding_each_severity_goes_through_the_loggers_own_method(node, monkeypatch):
    """The fallback: rclpy ties a call site to one severity, so lines of several severities must not share one."""
    from spacerobot_planner.ros import log_lines
    monkeypatch.setattr(log_lines, "_EMIT", None)
    lines = LogLines(node.get_logger())
    for severity in (LoggingSeverity.INFO, LoggingSeverity.WARN, LoggingSeverity.ERROR, LoggingSeverity.INFO):
        assert lines.log(severity, f"line at {severity.name}") is True
