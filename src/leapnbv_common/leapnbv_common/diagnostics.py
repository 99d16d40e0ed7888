"""Per-node health on /diagnostics: rate, latency, engine state, and why inputs were rejected."""
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
    `reject(reason, detail)` for an input it could not use, and `set_engine_state(state, ok)`.
    """

    def __init__(self, node, hardware_id: str = "", period_s: float = 1.0) -> None:
        self._node = node
        self._name = node.get_fully_qualified_name()
        self._hardware_id = hardware_id
        self._pub = node.create_publisher(DiagnosticArray, "/diagnostics", 10)
        self.frames_in = 0
        self.frames_out = 0
        self.rejected: Dict[str, int] = collections.Counter()
        self.last_reject_detail = ""
        self._last_reject_time = -1e9
        self.last_latency_ms = float("nan")
        self.last_compute_ms = float("nan")
        self.engine_state = "ready"
        self._engine_ok = True
        self._out_times: Deque[float] = collections.deque(maxlen=50)
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

    def set_engine_state(self, state: str, ok: bool) -> None:
        self.engine_state = state
        self._engine_ok = ok

    def rate_hz(self) -> float:
        if len(self._out_times) < 2:
            return 0.0
        span = self._out_times[-1] - self._out_times[0]
        return (len(self._out_times) - 1) / span if span > 0 else 0.0

    def status(self) -> DiagnosticStatus:
        if not self._engine_ok:
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
            "engine_state": self.engine_state,
            "rejected_total": sum(self.rejected.values()),
            "last_rejection": self.last_reject_detail,
        }
        values.update({f"rejected.{k}": v for k, v in sorted(self.rejected.items())})
        return DiagnosticStatus(
            level=level,
            name=self._name,
            message=message[:200],
            hardware_id=self._hardware_id,
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
