"""power_node: energy and mean power of each frame from the board's INA3221 rails, on /diagnostics.

A frame's window runs from its camera stamp to the moment its `view_candidates` (the last stage's
output, which carries the frame's header) arrives here. The rails are sampled in a thread by
:class:`leapnbv_common.power_monitor.PowerMonitor` on the wall clock; the window is placed on that
clock as [receipt - latency, receipt] with the latency measured on the node's ROS clock, so it
is right with sim time too. A window is integrated once the samples cover its end.

Without rails (a workstation, a container without /sys, unreadable files) the node says so at
OK level ("no power rails: ...") and only counts frames; the rest of the graph never depends on
it. Parameters: :class:`leapnbv_common.power_monitor.PowerParams` (all read at start-up).

Diagnostics values (rail = VDD_IN, VDD_CPU_GPU_CV): ``energy_j.<rail>`` and
``mean_power_w.<rail>`` of the last frame, ``energy_j_per_frame.<rail>`` (mean over the frames
measured), ``window_ms`` (last frame's window), ``frames_measured``, ``windows_incomplete``,
``sample_rate_hz``, ``rail_read_errors``.
"""
from __future__ import annotations

import collections
import math
import time
from typing import Deque, Dict, Optional, Tuple

from diagnostic_msgs.msg import DiagnosticStatus, KeyValue
from rclpy.node import Node

from leapnbv_common.conversions import stamp_to_ns
from leapnbv_common.diagnostics import StageDiagnostics
from leapnbv_common.node_params import NodeParams, run_node
from leapnbv_common.power_monitor import FrameEnergy, PowerMonitor, PowerParams, start_power_monitor
from leapnbv_common.qos import stage_input_qos
from leapnbv_common.topics import VIEW_CANDIDATES
from leapnbv_msgs.msg import ViewCandidates

PROCESS_PERIOD_S = 0.05
GIVE_UP_S = 1.0  # a window whose end the samples have not reached after this is integrated as it is


class PowerDiagnostics(StageDiagnostics):
    """StageDiagnostics plus the per-frame energy figures; with no rails the status stays OK."""

    def __init__(self, node, monitor: Optional[PowerMonitor], rails_message: str) -> None:
        super().__init__(node)
        self.monitor = monitor
        self.rails_message = rails_message
        self.last: Optional[FrameEnergy] = None
        self.totals: Dict[str, float] = collections.defaultdict(float)
        self.frames_measured = 0
        self.windows_incomplete = 0
        self.windows_outside = 0
        self._errors_seen = 0

    def measured(self, frame: FrameEnergy) -> None:
        self.last = frame
        self.frames_measured += 1
        self.windows_incomplete += 0 if frame.complete else 1
        for rail, joules in frame.energy_j.items():
            self.totals[rail] += joules

    def status(self) -> DiagnosticStatus:
        status = super().status()
        values = []
        if self.monitor is None:
            status.message = self.rails_message[:200]
        else:
            errors = self.monitor.read_errors
            if errors > self._errors_seen:
                status.level = DiagnosticStatus.WARN
                status.message = ("rail read failed %d times: %s" % (errors - self._errors_seen,
                                                                      self.monitor.last_error))[:200]
                self._errors_seen = errors
            elif status.level == DiagnosticStatus.OK and self.last is not None:
                total = self.monitor.names[0]
                status.message = "%s %.3f J/frame, %.2f W (%d frames)" % (
                    total, self.totals[total] / self.frames_measured, self.last.mean_power_w[total],
                    self.frames_measured)
            values += [("rails", ", ".join(self.monitor.names)),
                       ("sample_rate_hz", "%.1f" % self.monitor.achieved_rate_hz()),
                       ("rail_read_errors", str(errors))]
            if self.last is not None:
                values.append(("window_ms", "%.1f" % (self.last.window_s * 1e3)))
                for rail in self.monitor.names:
                    values += [("energy_j.%s" % rail, "%.4f" % self.last.energy_j[rail]),
                               ("mean_power_w.%s" % rail, "%.3f" % self.last.mean_power_w[rail]),
                               ("energy_j_per_frame.%s" % rail, "%.4f" % (self.totals[rail] / self.frames_measured))]
        values += [("frames_measured", str(self.frames_measured)),
                   ("windows_incomplete", str(self.windows_incomplete)),
                   ("windows_outside_history", str(self.windows_outside)),
                   ("power_rails", self.rails_message)]
        status.values.extend(KeyValue(key=k, value=v) for k, v in values)
        return status


class PowerNode(Node):
    def __init__(self) -> None:
        super().__init__("power_node")
        self.params = NodeParams(self, PowerParams)
        self.monitor, message = start_power_monitor(self.params.value)
        if self.monitor is None:
            self.get_logger().info(f"{message}; frames are counted, no energy is reported")
        else:
            self.get_logger().info(message)
        self.diagnostics = PowerDiagnostics(self, self.monitor, message)
        self.diagnostics.set_engine_state("ready" if self.monitor is not None else message, ok=True)
        # (window start, window end) on the monitor's clock, when it was queued (monotonic), the frame's stamp
        self.pending: Deque[Tuple[float, float, float, object]] = collections.deque(maxlen=1000)
        self.create_subscription(ViewCandidates, VIEW_CANDIDATES, self.on_candidates, stage_input_qos(10))
        self.create_timer(PROCESS_PERIOD_S, self.process)

    def on_candidates(self, msg: ViewCandidates) -> None:
        self.diagnostics.frame_in()
        if self.monitor is None:
            return
        latency_s = (self.get_clock().now().nanoseconds - stamp_to_ns(msg.header.stamp)) * 1e-9
        received = self.monitor.clock()
        if not math.isfinite(latency_s) or latency_s < 0 or latency_s > self.monitor.history_s:
            self.diagnostics.windows_outside += 1
            return
        self.pending.append((received - latency_s, received, time.monotonic(), msg.header.stamp))

    def process(self) -> None:
        if self.monitor is None:
            return
        latest = self.monitor.latest_time()
        while self.pending:
            t0, t1, queued, stamp = self.pending[0]
            if latest < t1 and time.monotonic() - queued < GIVE_UP_S:
                return  # the samples have not reached this window's end yet
            self.pending.popleft()
            started = time.perf_counter()
            frame = self.monitor.energy(t0, t1)
            if frame is None:
                self.diagnostics.windows_outside += 1
                continue
            self.diagnostics.measured(frame)
            self.diagnostics.frame_out(stamp, (time.perf_counter() - started) * 1e3)

    def destroy_node(self) -> None:
        if self.monitor is not None:
            self.monitor.stop()
        super().destroy_node()


def main(args=None) -> None:
    run_node(PowerNode, args)


if __name__ == "__main__":
    main()
