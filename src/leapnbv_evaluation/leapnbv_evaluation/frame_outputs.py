"""The graph's outputs of one published frame: what came, when, and what a frame's answer is.

The evaluation session (:mod:`leapnbv_evaluation.harness`) files each output message it receives
under the frame of its stamp; the episode (:mod:`leapnbv_evaluation.closed_loop`) reads the frame's
view candidates, latencies and energy from here. The messages are the graph's rclpy messages as
received (their fields are read, never written).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Dict, FrozenSet, Optional, Tuple

from leapnbv_common.conversions import ConversionError, ViewCandidatesArrays, view_candidates_to_arrays
from leapnbv_common.power_monitor import RAIL_TOTAL, PowerMonitor
from leapnbv_common.topics import (
    DETECTIONS,
    GROUND_PLANE,
    HUMAN_MESH,
    HUMAN_MESH_METRIC,
    PERSON_MASK,
    TARGET_GEOMETRY,
    TARGET_TRACK,
    VIEW_CANDIDATES,
)
from leapnbv_evaluation.episode import EvaluationError

# Graph node -> its output (short topic name) whose compute_time_ms is that stage's latency.
STAGE_TOPICS: Tuple[Tuple[str, str], ...] = (
    ("detector_node", DETECTIONS),
    ("hmr_node", HUMAN_MESH),
    ("raster_node", TARGET_GEOMETRY),
    ("ground_node", GROUND_PLANE),
    ("nbv_node", VIEW_CANDIDATES),
)
END_TO_END = "end_to_end"
#: Latency stages of the tables, in order.
STAGES: Tuple[str, ...] = tuple(stage for stage, _ in STAGE_TOPICS) + (END_TO_END,)


def expected_outputs(real_models: bool) -> FrozenSet[str]:
    """The outputs (short topic names) the graph publishes for a frame it plans for.

    Args:
        real_models: Real perception runs (the HMR node then also publishes the metric mesh).

    Returns:
        The stage outputs, the person mask and the target track (and the metric mesh with real models).
    """
    expected = {topic for _, topic in STAGE_TOPICS} | {PERSON_MASK, TARGET_TRACK}
    if real_models:
        expected.add(HUMAN_MESH_METRIC)
    return frozenset(expected)


@dataclass
class FrameOutputs:
    """The graph's outputs of one stamp, as received (rclpy messages), with receive times (ns, monotonic)."""

    stamp_ns: int
    published_ns: int
    messages: Dict[str, Any] = field(default_factory=dict)
    received_ns: Dict[str, int] = field(default_factory=dict)
    failure: Optional[str] = None

    @property
    def view_candidates(self) -> Any:
        """The view_candidates message, or None before (or without) it."""
        return self.messages.get(VIEW_CANDIDATES)

    def complete(self, real_models: bool) -> bool:
        """Whether every output of a planned frame came (:func:`expected_outputs`)."""
        return expected_outputs(real_models) <= set(self.messages)

    def failure_recorded(self) -> bool:
        """Whether a frame that ends early has its record: hmr_node's target track of every frame it decides.

        hmr_node decides a frame with no detections too; its target track may come after the empty detections.
        """
        return TARGET_TRACK in self.messages

    def early_failure(self) -> Optional[str]:
        """A reason the graph will publish no view_candidates for this frame, once it is certain."""
        detections = self.messages.get(DETECTIONS)
        if detections is not None and not detections.detections:
            return "no person detected"
        track = self.messages.get(TARGET_TRACK)
        if track is not None and track.detection_index < 0:
            # hmr_node gives no mesh to a frame whose target is not among its detections (hidden, out of view).
            return f"the target is not among the detections: {track.reason}"
        target = self.messages.get(TARGET_GEOMETRY)
        if target is not None and not target.valid:
            return "empty target (no person points survived the mask and depth clustering)"
        ground = self.messages.get(GROUND_PLANE)
        if ground is not None and not ground.valid:
            return f"no ground plane ({ground.inlier_count} inliers)"
        return None

    def latency_ms(self) -> Dict[str, float]:
        """compute_time_ms per stage, and end-to-end (view_candidates receive - publish), when present."""
        out: Dict[str, float] = {}
        for stage, topic in STAGE_TOPICS:
            msg = self.messages.get(topic)
            if msg is not None:
                out[stage] = float(msg.compute_time_ms)
        if VIEW_CANDIDATES in self.received_ns:
            out[END_TO_END] = (self.received_ns[VIEW_CANDIDATES] - self.published_ns) * 1e-6
        return out

    def energy_j(self, power: Optional[PowerMonitor]) -> Optional[float]:
        """Joules the board's input rail (VDD_IN) took from the frame's publication to its view candidates.

        The interval is on the monotonic clock. None without rails or without candidates.
        """
        if power is None or VIEW_CANDIDATES not in self.received_ns:
            return None
        frame = power.energy(self.published_ns * 1e-9, self.received_ns[VIEW_CANDIDATES] * 1e-9)
        return frame.energy_j.get(RAIL_TOTAL) if frame is not None else None

    def candidates(self) -> Optional[ViewCandidatesArrays]:
        """The view candidates as arrays, or None when the graph published none.

        Raises:
            EvaluationError: The message is malformed.
        """
        msg = self.view_candidates
        if msg is None:
            return None
        try:
            return view_candidates_to_arrays(msg)
        except ConversionError as error:
            raise EvaluationError(f"view_candidates: {error}") from error
