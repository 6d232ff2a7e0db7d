"""
The executables' executor: rclpy's SingleThreadedExecutor without the empty wakes after each callback.

rclpy's executor hands each ready entity to a handler, and that handler triggers the executor's
own guard condition twice: once the entity's data is taken, and again once its callback ends.
Those triggers are for an executor whose threads wait while another runs the callback: they make
the waiting thread's wait return, so that it builds its wait set again with the entity (and the
other entities of its callback group) back in it.  In a single-threaded executor the thread that
ran the callback is the one that waits next, and it builds that wait set anyway.  There each
trigger only made the next wait return at once, empty, and the wait set be built once more.

Building a wait set is Python work over every entity of the nodes (the planner node has about
forty: the parameter and lifecycle services, the action server, a QoS event handler for each
publisher and subscription): about 0.18 ms on the development VM.  That work holds the interpreter
right after each callback, while the thread the callback woke (the session's worker, after a
``~/replan`` call) waits for it.  :class:`NodeExecutor` is rclpy's executor with a handler that
does not trigger, so after a callback the executor builds one wait set and sleeps in it.

One trigger stays: at the end of a callback that awaited (a coroutine run again as a task, as a
``~/replan`` call that awaits its plan).  A wake begins by running the tasks in progress, then
waits; such a callback ends among those tasks, and a task that ran before it in that wake and
awaits what it did (a future it completed) runs again only at the next wake, which the trigger
makes at once.  A callback that ends in its first step ends before the next wake begins, so that
wake runs every task in progress after it.

Everything else is rclpy's: which entities are waited for, the order of the callbacks, the
callback groups, the tasks, shutdown.  A handler that its callback group refuses triggers (as
rclpy's).  Where the rclpy in use lacks what the handler needs (another rclpy than this package's,
9.1), the handlers are rclpy's.
"""
from __future__ import annotations

import inspect

from rclpy.exceptions import InvalidHandle
from rclpy.executors import Executor, SingleThreadedExecutor
from rclpy.task import Task

#: what the handler reads of rclpy's Executor (rclpy 9.1); without any of them it is rclpy's own
_NEEDS = ("_guard", "_is_shutdown", "_work_tracker", "_tasks", "_tasks_lock")
_SIGNATURE = ["self", "entity", "node", "take_from_wait_list"]


class _StepCounted(Task):
    """A task that counts its steps (calls: the first, and one per resumption)."""

    steps = 0

    def __call__(self) -> None:
        self.steps += 1
        super().__call__()


class NodeExecutor(SingleThreadedExecutor):
    """A SingleThreadedExecutor whose handlers do not wake it (see the module docstring)."""

    def __init__(self, *, context=None) -> None:
        super().__init__(context=context)
        #: whether the handlers are this module's (False: rclpy's, another rclpy)
        self.quiet_handlers = (all(hasattr(self, name) for name in _NEEDS)
                               and list(inspect.signature(Executor._make_handler).parameters) == _SIGNATURE)

    def _make_handler(self, entity, node, take_from_wait_list):
        """Return rclpy's handler of ``entity``, less its triggers of this executor's guard condition."""
        if not self.quiet_handlers:
            return super()._make_handler(entity, node, take_from_wait_list)
        entity._executor_event = True      # not waited for until its data is taken

        async def handler(entity, gc, is_shutdown, work_tracker):
            if is_shutdown or entity.callback_group is not None and \
                    not entity.callback_group.beginning_execution(entity):
                entity._executor_event = False     # refused: waited for again, at once (as rclpy)
                gc.trigger()
                return
            with work_tracker:
                call_coroutine = take_from_wait_list(entity)
                entity._executor_event = False
                try:
                    if call_coroutine is not None:
                        await call_coroutine()
                finally:
                    if entity.callback_group:
                        entity.callback_group.ending_execution(entity)
                    if task.steps > 1:          # it awaited: ends among the tasks (the module docstring)
                        try:
                            gc.trigger()
                        except InvalidHandle:   # the executor shut down from the callback (as rclpy)
                            pass

        task = _StepCounted(handler, (entity, self._guard, self._is_shutdown, self._work_tracker), executor=self)
        with self._tasks_lock:
            self._tasks.append((task, entity, node))
        return task
