"""DirectExecutor: rclpy's single-threaded executor with a short path from a message to its callback.

After every wait, rclpy's :class:`~rclpy.executors.SingleThreadedExecutor`
walks every entity of every node, releases the handles it held, and runs the
ready callback as a task (a coroutine driven by a guard condition).  In the
composed graph -- one subscription on the ping path beside 28 parameter
services and five timers -- that walk stands between the middleware receiving
a ping and its callback; called directly, the callback starts sooner and its
markers go out sooner (alternating runs; some of the time saved is spent again
warming the callback's own code after the idle time between pings).  rclcpp's
static executor exists for the same reason.

This executor waits on the same entities, and calls a ready subscription's
callback directly; anything else that is ready (timers, services, guard
conditions) is handed to rclpy's own executor code, unchanged.  It uses
rclpy's as long as any node has something this path does not run: a client, a
waitable (e.g. a QoS event handler), a coroutine callback, or a task still
pending.  Semantics are rclpy's single-threaded ones: one callback at a time,
in this thread; an exception from a callback leaves :meth:`spin_once`.

It reads rclpy internals (the wait set and the entities' handles), which
belong to the rclpy this package pins (``ros-kilted-rclpy``);
``test/test_executor.py`` runs every kind of entity through it.
"""

from __future__ import annotations

import inspect
import time
from contextlib import ExitStack

from rclpy.exceptions import InvalidHandle
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
from rclpy.subscription import Subscription
from rclpy.utilities import timeout_sec_to_nsec

SHUTDOWN_GRACE = 1.0
"""s: how long a failed take is given to turn out a shutdown (Ctrl-C) before it is raised."""


class DirectExecutor(SingleThreadedExecutor):
    """A :class:`~rclpy.executors.SingleThreadedExecutor` that calls subscription callbacks without a task."""

    def spin_once(self, timeout_sec: float | None = None) -> None:
        """Wait up to ``timeout_sec`` (None: forever) for work and do it: one wait, its ready callbacks.

        Unlike rclpy's, it also returns, without work done, when woken before
        the timeout (a node, an entity or a task added): :meth:`spin` and loops
        over ``spin_once`` do not tell the difference.  Raises
        :class:`~rclpy.executors.ExternalShutdownException` when the context was
        shut down from another thread or by a signal, also while a wait set was
        being made (rclpy's executor raises an ``RCLError`` there) or a message
        taken (rclpy 9 may fail to convert it then, before the context is down:
        a failed take waits up to :data:`SHUTDOWN_GRACE` for the shutdown).
        """
        try:
            self._spin_once(timeout_sec)
        except RuntimeError:  # rclpy's RCLError as the context went down
            if self._context.ok():
                raise
        if not self._context.ok():
            raise ExternalShutdownException()

    def _spin_once(self, timeout_sec: float | None) -> None:
        nodes = self.get_nodes()
        subscriptions = [subscription for node in nodes for subscription in node.subscriptions]
        if not self._direct(nodes, subscriptions):
            super().spin_once(timeout_sec)
            return
        timers = [timer for node in nodes for timer in node.timers]
        services = [service for node in nodes for service in node.services]
        node_guards = [guard for node in nodes for guard in node.guards]
        for guard in node_guards:
            if guard._executor_triggered:  # its callback is still due: wake at once, as rclpy does
                guard.trigger()
        executor_guards = [guard for guard in (self._guard, self._sigint_gc) if guard]
        # The handles are held until the callbacks are done: an entity destroyed meanwhile goes when released.
        with ExitStack() as held:
            subscriptions, timers, services, node_guards, executor_guards = (
                [entity for entity in entities if _held(held, entity)]
                for entities in (subscriptions, timers, services, node_guards, executor_guards))
            held.enter_context(self._context.handle)
            wait_set = self._wait(subscriptions, node_guards + executor_guards, timers, services, timeout_sec)
            if not self._context.ok():
                raise ExternalShutdownException()
            # A guard condition is reset by the wait that saw it: marked, rclpy's path runs its callback.
            triggered = wait_set.get_ready_entities("guard_condition")
            for guard in node_guards:
                if guard.handle.pointer in triggered:
                    guard._executor_triggered = True
            ready = wait_set.get_ready_entities("subscription")
            for subscription in subscriptions:
                if subscription.handle.pointer in ready:
                    _call(subscription, self._context)
            # Still ready if a callback raised: the next wait sees them again.
            handed_on = bool(wait_set.get_ready_entities("timer") or wait_set.get_ready_entities("service")
                             or any(guard._executor_triggered for guard in node_guards))
        if handed_on:
            self._cb_iter = None  # rclpy's ready list of an earlier wait may miss what this one saw: wait afresh
            super().spin_once(0)

    def _wait(self, subscriptions, guards, timers, services, timeout_sec):
        """The wait set of these entities after waiting up to ``timeout_sec`` for one of them."""
        wait_set = _rclpy.WaitSet(len(subscriptions), len(guards), len(timers), 0, len(services), 0,
                                  self._context.handle)
        wait_set.clear_entities()
        for subscription in subscriptions:
            wait_set.add_subscription(subscription.handle)
        for guard in guards:
            wait_set.add_guard_condition(guard.handle)
        for timer in timers:
            wait_set.add_timer(timer.handle)
        for service in services:
            wait_set.add_service(service.handle)
        wait_set.wait(timeout_sec_to_nsec(timeout_sec))
        return wait_set

    def _direct(self, nodes, subscriptions) -> bool:
        """Whether this wait can take the direct path: nothing of the nodes needs rclpy's tasks."""
        if self._is_shutdown or any(inspect.iscoroutinefunction(s.callback) for s in subscriptions):
            return False
        if any(next(node.clients, None) or next(node.waitables, None) for node in nodes):
            return False
        with self._tasks_lock:
            return all(task.done() for task, _, _ in self._tasks)


def _take(subscription: Subscription):
    """One message of ``subscription`` as rclpy takes it: ``(message, MessageInfo)``, or None."""
    return subscription.handle.take_message(subscription.msg_type, subscription.raw)


def _goes_down(context, within: float) -> bool:
    """Whether ``context`` is shut down now or within ``within`` seconds (polled every 10 ms)."""
    deadline = time.monotonic() + within
    while context.ok():
        if time.monotonic() >= deadline:
            return False
        time.sleep(0.01)
    return True


def _held(held: ExitStack, entity) -> bool:
    """Hold ``entity``'s handle in ``held``; False when it was destroyed (still listed by its node), and left out."""
    try:
        held.enter_context(entity.handle)
    except InvalidHandle:
        return False
    return True


def _call(subscription: Subscription, context) -> None:
    """Take one message of a ready subscription and call its callback (with its MessageInfo if it takes one).

    A subscription destroyed by an earlier callback of the same wait is skipped, as rclpy's executor does.
    A take that fails while ``context`` goes down within :data:`SHUTDOWN_GRACE` raises
    :class:`~rclpy.executors.ExternalShutdownException`.
    """
    try:
        with subscription.handle:
            taken = _take(subscription)
    except InvalidHandle:
        return
    except RuntimeError:
        # Ctrl-C: Python raises the KeyboardInterrupt inside rclpy's conversion of the message, which turns it
        # into this error, and rclpy's signal thread shuts the context down a moment later.
        if _goes_down(context, SHUTDOWN_GRACE):
            raise ExternalShutdownException() from None
        raise
    if taken is None:  # the middleware had nothing after all (e.g. a message it could not deserialize)
        return
    if subscription._callback_type is Subscription.CallbackType.MessageOnly:
        subscription.callback(taken[0])
    else:
        subscription.callback(*taken)
