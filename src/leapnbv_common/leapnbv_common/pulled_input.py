"""Inputs a node reads when it needs them, instead of being woken up for every message.

rclpy's executor wakes a node for every message of every subscription and spends about half a
millisecond of Python per wake-up (building the wait set, taking, dispatching), whatever the
message. A stage that works on a few frames a second but subscribes to 30 Hz companions (depth
frames, camera infos, camera poses, the simulator's truth) paid that 60-90 times a second for
messages it mostly drops (measured: docs/ARCHITECTURE.md, "Timing").

A *pulled* subscription is left out of the executor's wait set (its callback group never says it
can execute): its messages wait in the DDS reader's history (KEEP_LAST depth of its QoS) until the
node calls :meth:`PulledInput.drain`, which takes them all at once and hands each to the callback,
in arrival order. A node drains its companions when the message that starts its work arrives (and
from its wait timer while a frame waits for one). Messages that the history overwrote before a
drain are the ones ``StageDiagnostics.input_seen`` counts as ``<input>_not_taken``.
"""
from __future__ import annotations

import inspect
from typing import Any, Callable, Optional

from rclpy.callback_groups import CallbackGroup

#: A node drains its pulled inputs at least this often (a slow timer), so that a bad message is counted
#: on /diagnostics within this time even while no frame comes to start the work.
HOUSEKEEPING_PERIOD_S = 0.25


class _NeverReady(CallbackGroup):
    """A callback group whose entities the executor never waits for nor runs."""

    def can_execute(self, entity) -> bool:
        return False

    def beginning_execution(self, entity) -> bool:
        return False

    def ending_execution(self, entity) -> None:
        pass


def _takes_info(callback: Callable) -> bool:
    """Whether the callback takes (message, message_info), as rclpy decides it."""
    try:
        inspect.signature(callback).bind(object(), object())
        return True
    except TypeError:
        return False


class PulledInput:
    """A subscription read only by :meth:`drain` (see the module docstring).

    Args:
        subscription: An rclpy Subscription; it is moved into a callback group the executor
            never runs (so it no longer wakes the node).
    """

    def __init__(self, subscription) -> None:
        self.subscription = subscription
        group = _NeverReady()
        # The subscription and its QoS event handlers both leave the wait set: an unread reader whose
        # history overwrites samples reports them as lost, and a ready event nobody handles would make
        # the executor spin.
        for entity in [subscription, *getattr(subscription, "event_handlers", [])]:
            group.add_entity(entity)
            entity.callback_group = group
        self._with_info = _takes_info(subscription.callback)
        self.taken = 0

    @classmethod
    def create(cls, node, msg_type, topic: str, callback: Callable, qos, raw: bool = False) -> PulledInput:
        """A new pulled subscription (same arguments as ``Node.create_subscription``)."""
        return cls(node.create_subscription(msg_type, topic, callback, qos, raw=raw))

    @classmethod
    def adopt(cls, node, owner: Any) -> Optional[PulledInput]:
        """Pull the existing subscription of ``node`` whose callback is a method of ``owner`` (e.g. the
        camera-pose source made by leapnbv_common.camera_pose, whatever its topic is remapped to);
        None when there is none (a source without a subscription)."""
        for subscription in node.subscriptions:
            if getattr(subscription.callback, "__self__", None) is owner:
                return cls(subscription)
        return None

    def drain(self, limit: int = 1000) -> int:
        """Take every message waiting in the reader and hand each to the callback; returns how many."""
        sub = self.subscription
        count = 0
        while count < limit:
            with sub.handle:
                taken: Any = sub.handle.take_message(sub.msg_type, sub.raw)
            if taken is None:
                break
            count += 1
            if self._with_info:
                sub.callback(taken[0], taken[1])
            else:
                sub.callback(taken[0])
        self.taken += count
        return count
