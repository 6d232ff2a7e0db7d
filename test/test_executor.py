"""
The executables' executor (``ros.executor.NodeExecutor``) against rclpy's SingleThreadedExecutor.

Its wakes are counted from outside (each pass of the executor asks for its nodes once), the
callbacks by what they record, the answers by a client on its own rclpy executor.
"""

import threading
import time

import pytest
import rclpy
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup, ReentrantCallbackGroup
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.task import Future
from std_msgs.msg import String
from std_srvs.srv import Trigger

from spacerobot_planner.ros import executor as executor_mod
from spacerobot_planner.ros.executor import NodeExecutor


@pytest.fixture
def ros():
    """Yield (context, served node, client node, client executor); the client's executor spins in a thread."""
    ctx = Context()
    rclpy.init(context=ctx)
    served = rclpy.create_node("executor_served", context=ctx)
    client = rclpy.create_node("executor_client", context=ctx, start_parameter_services=False)
    client_ex = SingleThreadedExecutor(context=ctx)
    client_ex.add_node(client)
    spin = threading.Thread(target=client_ex.spin, daemon=True)
    spin.start()
    try:
        yield ctx, served, client
    finally:
        client_ex.shutdown()
        spin.join(5.0)
        served.destroy_node()
        client.destroy_node()
        rclpy.shutdown(context=ctx)


def _spinning(ex, node):
    """Start spinning ``ex`` (with ``node``) in a thread; return (passes list, stop callable)."""
    passes = []
    get_nodes = ex.get_nodes

    def counted():
        passes.append(time.monotonic())
        return get_nodes()
    ex.get_nodes = counted
    ex.add_node(node)
    t = threading.Thread(target=ex.spin, daemon=True)
    t.start()

    def stop():
        ex.shutdown()
        t.join(5.0)
    return passes, stop


def _wait(pred, timeout_s=10.0):
    end = time.monotonic() + timeout_s
    while not pred():
        if time.monotonic() > end:
            return False
        time.sleep(0.005)
    return True


def _settled(passes, quiet_s=0.05, timeout_s=5.0):
    """Wait until the executor has made no pass for ``quiet_s`` (at most ``timeout_s``)."""
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        seen = len(passes)
        time.sleep(quiet_s)
        if len(passes) == seen:
            return


def _passes_per_message(ros, make_executor, count=20):
    """
    Return (messages taken, executor passes while they came).

    Each message is sent once the one before was taken and the executor has gone quiet (no pass
    for 50 ms): its wakes are its own.  (It had sent one every 30 ms: an executor thread that fell
    behind on a loaded machine took a message in the same wait as the wake after the one before,
    and rclpy's count fell below twice the messages: 20 passes for 20 messages, 2 runs in 16 under
    three busy loops.)
    """
    ctx, served, client = ros
    got = []
    served.create_subscription(String, "chatter", lambda m: got.append(m.data), 50)
    pub = client.create_publisher(String, "chatter", 50)
    ex = make_executor(ctx)
    passes, stop = _spinning(ex, served)
    try:
        assert _wait(lambda: pub.get_subscription_count() > 0)
        pub.publish(String(data="warm"))
        assert _wait(lambda: got)
        time.sleep(0.1)
        _settled(passes)
        before = len(passes)
        for i in range(count):
            n_got = len(got)
            pub.publish(String(data=str(i)))
            assert _wait(lambda: len(got) > n_got)
            _settled(passes)
        assert _wait(lambda: len(got) == count + 1)
        _settled(passes)
        return len(got) - 1, len(passes) - before
    finally:
        stop()


def test_one_wait_set_per_callback(ros):
    """After each callback NodeExecutor builds one wait set and sleeps in it; rclpy's builds two."""
    taken, passes = _passes_per_message(ros, lambda ctx: NodeExecutor(context=ctx))
    assert taken == 20
    assert passes <= taken + 2, (taken, passes)


def test_rclpy_wakes_twice_per_callback(ros):
    """The behaviour NodeExecutor removes (rclpy 9.1's handler triggers the executor's guard condition)."""
    taken, passes = _passes_per_message(ros, lambda ctx: SingleThreadedExecutor(context=ctx))
    assert taken == 20
    assert passes >= 2 * taken - 1, (taken, passes)


def test_rclpy_handlers_where_its_needs_are_missing(ros, monkeypatch):
    """Without what its handler reads of rclpy's executor, NodeExecutor's handlers are rclpy's (and work)."""
    monkeypatch.setattr(executor_mod, "_NEEDS", executor_mod._NEEDS + ("_not_in_this_rclpy",))
    made = []

    def make(ctx):
        made.append(NodeExecutor(context=ctx))
        return made[-1]
    taken, passes = _passes_per_message(ros, make)
    assert not made[0].quiet_handlers
    assert taken == 20
    assert passes >= 2 * taken - 1, (taken, passes)


def _call(client, name):
    cli = client.create_client(Trigger, name)
    assert cli.wait_for_service(10.0)
    return cli.call_async(Trigger.Request())


def test_a_task_awaiting_what_another_finished_runs_again(ros):
    """
    An awaiting callback that completes a future another awaits wakes the executor at its end.

    ``first`` awaits ``done_by_second``; ``second`` awaits ``go`` (set from another thread, which
    then triggers a guard condition of the node, as the planner node resumes its goals), then
    completes ``done_by_second`` and ends.  Both end within one wake's tasks, ``first`` before
    ``second`` in the list: without the wake at ``second``'s end nothing would run ``first`` again.
    """
    ctx, served, client = ros
    go, done_by_second = Future(), Future()
    group = ReentrantCallbackGroup()
    order = []

    async def first(req, resp):
        await done_by_second
        order.append("first")
        resp.success = True
        return resp

    async def second(req, resp):
        await go
        done_by_second.set_result(True)
        order.append("second")
        resp.success = True
        return resp
    served.create_service(Trigger, "first", first, callback_group=group)
    served.create_service(Trigger, "second", second, callback_group=group)
    wake = served.create_guard_condition(lambda: None)
    ex = NodeExecutor(context=ctx)
    _passes, stop = _spinning(ex, served)
    try:
        f1 = _call(client, "first")
        assert _wait(lambda: len(ex._tasks) >= 1)
        f2 = _call(client, "second")
        assert _wait(lambda: len(ex._tasks) >= 2)
        time.sleep(0.1)
        go.set_result(True)
        wake.trigger()
        assert _wait(lambda: f1.done() and f2.done(), 5.0), order
        assert f1.result().success and f2.result().success
        assert order == ["second", "first"]
    finally:
        stop()


def test_mutually_exclusive_group_waits_for_an_awaiting_callback(ros):
    """
    A message to a callback group whose awaiting callback runs is taken after it ends, never beside it.

    A second subscription of the topic, in a reentrant group, says when the message has reached the
    node.  The node has no timer: nothing but the callback's end wakes the executor for the message.
    """
    ctx, served, client = ros
    group = MutuallyExclusiveCallbackGroup()
    go = Future()
    events, witnessed = [], []

    async def slow(req, resp):
        events.append("slow begins")
        await go
        events.append("slow ends")
        resp.success = True
        return resp
    served.create_service(Trigger, "slow", slow, callback_group=group)
    served.create_subscription(String, "chatter", lambda m: events.append("message"), 10, callback_group=group)
    served.create_subscription(String, "chatter", witnessed.append, 10, callback_group=ReentrantCallbackGroup())
    wake = served.create_guard_condition(lambda: None)
    pub = client.create_publisher(String, "chatter", 10)
    ex = NodeExecutor(context=ctx)
    _passes, stop = _spinning(ex, served)
    try:
        assert _wait(lambda: pub.get_subscription_count() == 2)
        f = _call(client, "slow")
        assert _wait(lambda: events)
        pub.publish(String(data="while slow awaits"))
        assert _wait(lambda: witnessed)                            # the message is at the node
        assert events == ["slow begins"]                           # not beside it
        go.set_result(True)
        wake.trigger()
        assert _wait(lambda: f.done() and len(events) == 3, 5.0), events
        assert events == ["slow begins", "slow ends", "message"]
    finally:
        stop()
