"""Which camera frames the graph takes: latest-frame scheduling at its first stage (ROS-free).

The detector admits a frame only while fewer than ``max_frames_in_flight`` admitted frames are still
on their way to the planner's answer (``view_candidates``). While the graph is full, the newest frame
waits and goes in the moment an answer comes; the frame it replaces is dropped (``graph_busy``)
before any stage spends work on it. See docs/ARCHITECTURE.md, "Timing".
"""
from __future__ import annotations

from collections import OrderedDict
from typing import Callable, Dict, Optional, Tuple

__all__ = ["MIN_IN_FLIGHT_TIMEOUT_S", "FramesInFlight", "Admission"]

MIN_IN_FLIGHT_TIMEOUT_S = 0.05  # an admitted frame counts at least this long (see FramesInFlight)


class FramesInFlight:
    """The admitted frames whose final output (view candidates) has not come back, by stamp.

    A final output of stamp s completes every admitted frame stamped s or earlier (a stage never
    publishes an older frame after a newer one). A frame refused downstream (no person, a bad
    input, no ground plane) never comes back: it stops counting after twice the graph's recent
    time to answer (an average of the admitted frames that came back), at most ``timeout_s``, so a
    refused frame blocks the next one only briefly.
    """

    def __init__(self) -> None:
        self._admitted: Dict[int, float] = OrderedDict()  # stamp -> admitted at (monotonic s), oldest first
        self.planner_answered = False
        self.timed_out = 0
        self.answer_s: Optional[float] = None  # moving average of the time from admission to the answer

    def __len__(self) -> int:
        return len(self._admitted)

    def timeout(self, timeout_s: float) -> float:
        if self.answer_s is None:
            return timeout_s
        return min(timeout_s, max(MIN_IN_FLIGHT_TIMEOUT_S, 2.0 * self.answer_s))

    def expire(self, now_s: float, timeout_s: float) -> None:
        limit = self.timeout(timeout_s)
        for stamp, since in list(self._admitted.items()):
            if now_s - since >= limit:
                del self._admitted[stamp]
                self.timed_out += 1

    def full(self, limit: int, now_s: float, timeout_s: float) -> bool:
        """Whether no further frame may be admitted now (never before the planner answered once)."""
        if limit <= 0 or not self.planner_answered:
            return False
        self.expire(now_s, timeout_s)
        return len(self._admitted) >= limit

    def admit(self, stamp_ns: int, now_s: float) -> None:
        self._admitted[stamp_ns] = now_s

    def done(self, stamp_ns: int, now_s: float) -> None:
        self.planner_answered = True
        answered = self._admitted.get(stamp_ns)
        if answered is not None:
            took = now_s - answered
            self.answer_s = took if self.answer_s is None else 0.8 * self.answer_s + 0.2 * took
        for stamp in [s for s in self._admitted if s <= stamp_ns]:
            del self._admitted[stamp]


class Admission:
    """The frames in flight and the one newest frame held back while the graph is full.

    Args:
        drop: Called with a drop reason (``graph_busy``) for each frame that will never go in.
    """

    def __init__(self, drop: Callable[[str], None]) -> None:
        self.drop = drop
        self.in_flight = FramesInFlight()
        self.waiting: Optional[Tuple[int, Callable[[], None]]] = None  # (stamp, work) of the frame held back

    def reset(self) -> None:
        """The stamps started over (a replay, a reset): nothing is in flight any more."""
        self.in_flight = FramesInFlight()
        self.waiting = None

    def offer(self, stamp_ns: int, work: Callable[[], None], now_s: float, limit: int, timeout_s: float) -> bool:
        """Whether the graph takes this frame now; while it is full, the frame is held (``work`` runs it
        later, from :meth:`release`) and the frame it replaces is dropped. Frames come newest last."""
        if self.in_flight.full(limit, now_s, timeout_s):
            if self.waiting is not None:
                if self.waiting[0] >= stamp_ns:
                    self.drop("graph_busy")
                    return False
                self.drop("graph_busy")  # the frame that waited: this newer one takes its place
            self.waiting = (stamp_ns, work)
            return False
        if self.waiting is not None and self.waiting[0] <= stamp_ns:
            self.waiting = None  # a newer frame goes in: the one that waited is superseded
            self.drop("graph_busy")
        return True

    def release(self, now_s: float, limit: int, timeout_s: float) -> Optional[Callable[[], None]]:
        """The held frame's work once the graph has room (an answer came, or a frame timed out), else None."""
        if self.waiting is not None and not self.in_flight.full(limit, now_s, timeout_s):
            (_, work), self.waiting = self.waiting, None
            return work
        return None

    def admitted(self, stamp_ns: int, now_s: float) -> None:
        """A frame with a person went into the graph."""
        self.in_flight.admit(stamp_ns, now_s)

    def answered(self, stamp_ns: int, now_s: float) -> None:
        """The planner finished the frame of this stamp (and so every older one)."""
        self.in_flight.done(stamp_ns, now_s)
