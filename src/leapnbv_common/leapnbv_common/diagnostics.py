"""Per-node health on /diagnostics.

Rate, latency, engine state, lifecycle state, why inputs were rejected, and why frames were dropped.
"""
from __future__ import annotations

import collections
import functools
import time
import traceback
from typing import Callable, Deque, Dict, Optional

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue

from leapnbv_common.conversions import stamp_to_ns

WARN_WINDOW_S = 5.0  # a rejection in the last few seconds turns the status to WARN


class StageDiagnostics:
    """Counts what a stage node did and publishes it on /diagnostics once a second.

    A node calls `frame_in()` per input, `frame_out(header_stamp, compute_ms)` per output,
    `reject(reason, detail)` for an input it could not use, `drop(reason)` for an input it chose not
    to use (latest-frame scheduling: a newer frame superseded it, it was older than a frame already
    published, it fell out of a bounded cache unused), and `set_engine_state(state, ok)`.

    Rejections (``rejected.<reason>``) mean something was wrong and turn the status to WARN for a
    few seconds; drops (``dropped.<reason>``) are the normal cost of keeping up with the camera
    and leave the status OK. `input_seen(name, info)` (from a subscription callback that takes the
    message info) counts the messages of an input that the node never took (a newer one replaced
    them in the subscription's queue while the node was busy, or best-effort transport lost them)
    as ``dropped.<name>_not_taken``, from the publisher's sequence numbers, and keeps the input's
    last transport time (publish to receive) as ``transport_ms.<name>``.

    A managed node (:class:`leapnbv_common.managed_node.ManagedNode`) also reports its lifecycle
    state (``lifecycle_state``: unconfigured, inactive, active, ...), why its last transition failed
    (``lifecycle_reason``, empty once one succeeds) and its process (``process``: host:pid, so that a
    lifecycle manager sees a restarted node), in every state. ``awaiting_publishers`` lists the inputs
    named by `await_publishers` that have no publisher yet (empty when connected).
    """

    def __init__(self, node, hardware_id: str = "", period_s: float = 1.0) -> None:
        self._node = node
        self._name = node.get_fully_qualified_name()
        self.hardware_id = hardware_id
        self._pub = node.create_publisher(DiagnosticArray, "/diagnostics", 10)
        self.frames_in = 0
        self.frames_out = 0
        self.rejected: Dict[str, int] = collections.Counter()
        self.dropped: Dict[str, int] = collections.Counter()
        self.counted: Dict[str, int] = collections.Counter()  # other per-frame events (count)
        self._last_sequence: Dict[str, int] = {}
        self.transport_ms: Dict[str, float] = {}
        self.last_reject_detail = ""
        self._last_reject_time = -1e9
        self.last_latency_ms = float("nan")
        self.last_compute_ms = float("nan")
        self.engine_state = "ready"
        self._engine_ok = True
        self._out_times: Deque[float] = collections.deque(maxlen=50)
        self._awaited_publishers: Dict[str, str] = {}  # input name -> resolved topic, until one is discovered
        self.info: Dict[str, str] = {}  # what the node is configured as (``info.<key>``), e.g. the engine's kind
        self.lifecycle_state: Optional[str] = None  # None: not a managed node (no lifecycle keys)
        self.lifecycle_reason = ""
        self.process = ""
        self._timer = node.create_timer(period_s, self.publish)

    def frame_in(self) -> None:
        self.frames_in += 1

    def frame_out(self, header_stamp, compute_ms: float) -> None:
        """Record an output computed from the frame stamped header_stamp."""
        self.frames_out += 1
        now_ns = self._node.get_clock().now().nanoseconds
        self.last_latency_ms = (now_ns - stamp_to_ns(header_stamp)) * 1e-6
        self.last_compute_ms = float(compute_ms)
        self._out_times.append(time.monotonic())

    def reject(self, reason: str, detail: str = "") -> None:
        """Count an input that could not be used, and log why (throttled per reason)."""
        self.rejected[reason] += 1
        self.last_reject_detail = f"{reason}: {detail}" if detail else reason
        self._last_reject_time = time.monotonic()
        self._node.get_logger().warning(
            f"rejected input ({reason}): {detail}", throttle_duration_sec=2.0
        )

    def drop(self, reason: str, count: int = 1) -> None:
        """Count an input not used by choice (no log, no WARN): ``dropped.<reason>``."""
        if count > 0:
            self.dropped[reason] += count

    def count(self, name: str, count: int = 1) -> None:
        """Count a per-frame event that is neither a rejection nor a drop (``counted.<name>``)."""
        self.counted[name] += count

    def drop_callback(self) -> Callable[[str, int], None]:
        """An ``on_drop(reason, stamp_ns)`` for the stamp caches (leapnbv_common.stamp_cache)."""
        return lambda reason, stamp_ns: self.drop(reason)

    def input_seen(self, name: str, info) -> None:
        """Account one message of input ``name`` from its rclpy MessageInfo (a dict; None is ignored).

        A jump in the publisher's sequence number counts the messages in between as
        ``dropped.<name>_not_taken``; a number that goes back (another publisher, or it restarted)
        only resets the count.
        """
        if not info:
            return
        sequence = info.get("publication_sequence_number")
        if sequence:
            last = self._last_sequence.get(name)
            if last is not None and sequence > last + 1:
                self.dropped[name + "_not_taken"] += sequence - last - 1
            self._last_sequence[name] = sequence
        sent, received = info.get("source_timestamp"), info.get("received_timestamp")
        if sent and received:
            self.transport_ms[name] = (received - sent) * 1e-6

    def await_publishers(self, *inputs: str) -> None:
        """Report "waiting for a publisher of <inputs>" until each of these inputs has a publisher.

        ``engine_state`` says it (status OK) until each of these stage inputs (relative topic names)
        has a publisher in the graph, then the state set by the node; a managed node also lists the
        inputs still without one as ``awaiting_publishers``.

        A graph runner that waits for every engine to be "ready" then sends the first frame only once
        the stages are connected: a reliable, volatile stage output published before its subscriber
        was discovered is lost, and with it the frame.
        """
        for name in inputs:
            self._awaited_publishers[name] = self._node.resolve_topic_name(name)

    def _still_awaited(self) -> list:
        for name, topic in list(self._awaited_publishers.items()):
            if self._node.count_publishers(topic) > 0:
                del self._awaited_publishers[name]
        return sorted(self._awaited_publishers)

    def set_info(self, key: str, value: str) -> None:
        """Report a fixed fact about the node (what its engine is) as ``info.<key>`` in every status."""
        self.info[key] = str(value)

    def set_engine_state(self, state: str, ok: bool) -> None:
        self.engine_state = state
        self._engine_ok = ok

    def set_lifecycle_state(self, state: str, reason: str = "", process: str = "") -> None:
        """Report a managed node's lifecycle state, and why its last transition failed ("" if it did not)."""
        self.lifecycle_state = state
        self.lifecycle_reason = reason
        if process:
            self.process = process

    def rate_hz(self) -> float:
        if len(self._out_times) < 2:
            return 0.0
        span = self._out_times[-1] - self._out_times[0]
        return (len(self._out_times) - 1) / span if span > 0 else 0.0

    def status(self) -> DiagnosticStatus:
        engine_state = self.engine_state
        awaited = self._still_awaited() if self._awaited_publishers else []
        if self._engine_ok and engine_state == "ready" and awaited:
            engine_state = "waiting for a publisher of " + ", ".join(awaited)
        if self.lifecycle_reason:  # a managed node's transition failed: it says why
            level, message = DiagnosticStatus.ERROR, self.lifecycle_reason
        elif not self._engine_ok:
            level, message = DiagnosticStatus.ERROR, self.engine_state
        elif time.monotonic() - self._last_reject_time < WARN_WINDOW_S:
            level, message = DiagnosticStatus.WARN, self.last_reject_detail
        else:
            level, message = DiagnosticStatus.OK, "ok"
        values = {
            "frames_in": self.frames_in,
            "frames_out": self.frames_out,
            "rate_hz": f"{self.rate_hz():.2f}",
            "last_latency_ms": f"{self.last_latency_ms:.2f}",
            "last_compute_ms": f"{self.last_compute_ms:.2f}",
            "engine_state": engine_state,
            "rejected_total": sum(self.rejected.values()),
            "last_rejection": self.last_reject_detail,
            "dropped_total": sum(self.dropped.values()),
        }
        if self.lifecycle_state is not None:
            values.update({"lifecycle_state": self.lifecycle_state, "lifecycle_reason": self.lifecycle_reason,
                           "process": self.process, "awaiting_publishers": ", ".join(awaited)})
        values.update({f"rejected.{k}": v for k, v in sorted(self.rejected.items())})
        values.update({f"dropped.{k}": v for k, v in sorted(self.dropped.items())})
        values.update({f"counted.{k}": v for k, v in sorted(self.counted.items())})
        values.update({f"transport_ms.{k}": f"{v:.2f}" for k, v in sorted(self.transport_ms.items())})
        values.update({f"info.{k}": v for k, v in sorted(self.info.items())})
        return DiagnosticStatus(
            level=level,
            name=self._name,
            message=message[:200],
            hardware_id=self.hardware_id,
            values=[KeyValue(key=k, value=str(v)) for k, v in values.items()],
        )

    def publish(self) -> None:
        msg = DiagnosticArray()
        msg.header.stamp = self._node.get_clock().now().to_msg()
        msg.status = [self.status()]
        self._pub.publish(msg)


def rejects_bad_input(reason: str = "bad_input") -> Callable:
    """Decorate a node's callback method so that no exception ever kills the node.

    The node must have a `diagnostics` attribute (StageDiagnostics). A ValueError (conversion
    or contract failure) counts as `reason`; anything else counts as "internal_error" and logs
    the traceback. Either way the node serves the next message.
    """

    def wrap(method: Callable) -> Callable:
        @functools.wraps(method)
        def guarded(self, *args, **kwargs) -> Optional[object]:
            try:
                return method(self, *args, **kwargs)
            except ValueError as exc:
                self.diagnostics.reject(reason, str(exc))
            except Exception as exc:  # noqa: BLE001 - a node must survive any bad frame
                self.diagnostics.reject("internal_error", f"{type(exc).__name__}: {exc}")
                self.get_logger().error(traceback.format_exc(), throttle_duration_sec=5.0)
            return None

        return guarded

    return wrap
