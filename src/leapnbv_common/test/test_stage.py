"""The stage helper: matching, waits, what a frame is served with, and every drop and rejection counted.

The node is a stand-in that records subscriptions and timers and whose clock the test sets, so that
each rule is checked on exact stamps and times; the messages are real PointStamped messages.
"""
from __future__ import annotations

import collections
from typing import Any, Callable, Dict, List

import pytest

pytest.importorskip("rclpy")

from geometry_msgs.msg import PointStamped  # noqa: E402

from leapnbv_common.contracts import ContractError  # noqa: E402
from leapnbv_common.stage import (  # noqa: E402
    DROP,
    NEAREST,
    REJECT,
    SAME_OR_LATEST,
    STATIC_RELATION,
    Companion,
    KeyInput,
    Stage,
)

MS = 1_000_000


class FakeDiagnostics:
    def __init__(self) -> None:
        self.rejected: Dict[str, int] = collections.Counter()
        self.dropped: Dict[str, int] = collections.Counter()
        self.frames_in = 0

    def frame_in(self) -> None:
        self.frames_in += 1

    def input_seen(self, name: str, info: Any) -> None:
        pass

    def reject(self, reason: str, detail: str = "") -> None:
        self.rejected[reason] += 1

    def drop(self, reason: str, count: int = 1) -> None:
        self.dropped[reason] += count

    def drop_callback(self) -> Callable[[str, int], None]:
        return lambda reason, stamp: self.drop(reason)


class FakeTimer:
    def __init__(self) -> None:
        self.canceled = False

    def cancel(self) -> None:
        self.canceled = True

    def reset(self) -> None:
        self.canceled = False

    def is_canceled(self) -> bool:
        return self.canceled


class FakeNode:
    """Subscriptions by topic (their callbacks), timers, a clock the test moves."""

    def __init__(self) -> None:
        self.diagnostics = FakeDiagnostics()
        self.now = 0
        self.callbacks: Dict[str, Callable[..., None]] = {}
        self.timers: List[FakeTimer] = []

    def get_clock(self) -> Any:
        node = self

        class Clock:
            def now(self) -> Any:
                return type("Time", (), {"nanoseconds": node.now})()

        return Clock()

    def get_logger(self) -> Any:
        return type("Logger", (), {"error": lambda *a, **k: None})()

    def create_subscription(self, msg_type: Any, topic: str, callback: Callable[..., None], qos: Any,
                            raw: bool = False) -> str:
        self.callbacks[topic] = callback
        return topic

    def create_timer(self, period: float, callback: Callable[[], None]) -> FakeTimer:
        timer = FakeTimer()
        timer.callback = callback  # type: ignore[attr-defined]
        self.timers.append(timer)
        return timer

    def destroy_subscription(self, subscription: Any) -> None:
        self.callbacks.pop(subscription, None)

    def destroy_timer(self, timer: Any) -> None:
        pass

    def send(self, topic: str, stamp_ms: int, frame_id: str = "cam", x: float = 0.0) -> None:
        msg = PointStamped()
        msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(stamp_ms * MS, 1_000_000_000)
        msg.header.frame_id = frame_id
        msg.point.x = float(x)
        self.callbacks[topic](msg, None)

    def tick(self, to_ms: int) -> None:
        """Move the clock and run the wait timer (when it runs)."""
        self.now = to_ms * MS
        for timer in self.timers:
            if not timer.canceled:
                timer.callback()  # type: ignore[attr-defined]


def point(msg: PointStamped) -> float:
    if msg.point.x < 0:
        raise ContractError("a negative x breaks this input's contract")
    return msg.point.x


def make(companions: List[Companion]) -> Any:
    node = FakeNode()
    served: List[Any] = []
    stage = Stage(node, KeyInput("key", PointStamped, "key", point, None), companions, served.append)
    stage.start()
    return node, stage, served


def test_a_frame_takes_its_companion_of_the_same_stamp_whichever_comes_first() -> None:
    node, _, served = make([Companion("a", PointStamped, "a", point, wait_s=lambda f: 0.1)])
    node.send("a", 100, x=1.0)
    node.send("key", 100)
    node.send("key", 200)  # its companion comes after it
    assert len(served) == 1
    node.send("a", 150, x=9.0)  # another stamp: never paired
    assert len(served) == 1
    node.send("a", 200, x=2.0)
    assert [f["a"] for f in served] == [1.0, 2.0]
    assert served[1].inputs == [("key", 200 * MS, 0), ("a", 200 * MS, 0)]


def test_a_companion_that_never_comes_is_served_without_rejected_or_dropped_as_declared() -> None:
    node, _, served = make([Companion("a", PointStamped, "a", point, wait_s=lambda f: 0.05,
                                      missing_reason="a_late")])
    node.send("key", 100)
    node.tick(30)
    assert not served  # still within its wait
    node.tick(60)
    assert len(served) == 1 and served[0]["a"] is None and node.diagnostics.rejected["a_late"] == 1
    assert node.timers[-1].is_canceled()  # nothing waits: the wait timer stops

    node, _, served = make([Companion("a", PointStamped, "a", point, when_missing=REJECT, missing_reason="no_a")])
    node.send("key", 100)
    assert not served and node.diagnostics.rejected["no_a"] == 1
    node, _, served = make([Companion("a", PointStamped, "a", point, when_missing=DROP, missing_reason="no_a")])
    node.send("key", 100)
    assert not served and node.diagnostics.dropped["no_a"] == 1


def test_nearest_within_the_slop_and_the_latest_calibration_recorded_static() -> None:
    node, _, served = make([
        Companion("depth", PointStamped, "depth", point, match=NEAREST, slop_s=lambda f: 0.010, consume=True,
                  when_missing=REJECT, missing_reason="no_depth"),
        Companion("info", PointStamped, "info", point, match=SAME_OR_LATEST, stamp_from="depth",
                  when_missing=REJECT, missing_reason="no_info")])
    node.send("key", 100)  # no depth within the slop, no wait: refused before its calibration is looked at
    assert node.diagnostics.rejected == {"no_depth": 1} and not served
    node.send("info", 90, x=5.0)
    node.send("depth", 196, x=1.0)
    node.send("depth", 215, x=2.0)
    node.send("key", 200)  # 196 is 4 ms away, 215 is 15 ms: outside the slop
    assert served[-1]["depth"] == 1.0
    assert served[-1]["info"] == 5.0 and served[-1].inputs[-1] == ("info", 90 * MS, STATIC_RELATION)
    node.send("info", 215, x=6.0)
    node.send("key", 212)
    assert served[-1]["depth"] == 2.0 and served[-1].inputs[-1] == ("info", 215 * MS, 0)  # the depth frame's own


def test_stamp_rules_supersede_and_restart() -> None:
    node, stage, served = make([Companion("a", PointStamped, "a", point, wait_s=lambda f: 1.0)])
    node.send("key", 100)
    node.send("key", 200)
    node.send("a", 200)  # the newer frame is served: the older one still waiting is superseded
    assert [f.stamp_ns for f in served] == [200 * MS] and node.diagnostics.dropped["key_superseded"] == 1
    node.send("a", 100)
    node.send("key", 100)  # older than one served
    node.send("key", 200)  # the same stamp again
    assert node.diagnostics.dropped["older_than_published"] == 1 and node.diagnostics.dropped["duplicate_stamp"] == 1
    node.send("a", 20_300)
    node.send("key", 20_300)
    node.send("a", 50)
    node.send("key", 50)  # 20 s back: the stamps started over (a replay from its start): served
    assert [f.stamp_ns for f in served] == [200 * MS, 20_300 * MS, 50 * MS] and stage.restarts == 1


def test_a_message_that_breaks_its_contract_is_counted_and_never_kept() -> None:
    node, _, served = make([Companion("a", PointStamped, "a", point)])
    node.send("a", 100, x=-1.0)  # refused on arrival
    node.send("key", 100)
    assert node.diagnostics.rejected["bad_a"] == 1 and served[-1]["a"] is None
    node.send("key", 200, x=-1.0)
    assert node.diagnostics.rejected["bad_key"] == 1 and len(served) == 1
    node.send("a", 300, x=1.0)
    node.send("a", 300, x=2.0)  # another content under a stamp already here: the first one stays
    node.send("key", 300)
    assert node.diagnostics.rejected["duplicate_stamp"] == 1 and served[-1]["a"] == 1.0


def test_an_exception_in_on_frame_is_counted_and_the_stage_serves_the_next_frame() -> None:
    node = FakeNode()
    calls: List[int] = []

    def on_frame(frame: Any) -> None:
        calls.append(frame.stamp_ns)
        if len(calls) == 1:
            raise ValueError("a frame the core refuses")
        if len(calls) == 2:
            raise KeyError("a bug")

    Stage(node, KeyInput("key", PointStamped, "key", point, None), [], on_frame,
          frame_error_reason="bad_depth").start()
    for stamp in (100, 200, 300):
        node.send("key", stamp)
    assert calls == [100 * MS, 200 * MS, 300 * MS]
    assert node.diagnostics.rejected["bad_depth"] == 1 and node.diagnostics.rejected["internal_error"] == 1


def test_a_key_or_companion_stamped_ahead_of_the_clock_is_refused_before_its_stamp_is_remembered() -> None:
    from types import SimpleNamespace

    from leapnbv_common.params import StageParams

    node = FakeNode()
    node.params = SimpleNamespace(value=StageParams())  # type: ignore[attr-defined]  # the node's parameter: 0.5 s
    served: List[Any] = []
    stage = Stage(node, KeyInput("key", PointStamped, "key", point, None),
                  [Companion("a", PointStamped, "a", point, wait_s=lambda f: 0.1)], served.append)
    stage.start()
    node.now = 1000 * MS
    node.send("a", 1000 + 3_600_000, x=1.0)  # an hour ahead
    node.send("key", 1000 + 3_600_000)
    assert node.diagnostics.rejected["stamp_in_future"] == 2 and not served and not stage.waiting
    node.send("key", 1400)  # 0.4 s ahead: within the tolerance
    node.send("a", 1400, x=2.0)
    assert [f["a"] for f in served] == [2.0]
    node.now = 2000 * MS
    node.send("a", 2000, x=3.0)
    node.send("key", 2000)  # the future frame was never served: this one is not "older than published"
    assert [f["a"] for f in served] == [2.0, 3.0] and not node.diagnostics.dropped

    node, stage, served = make([])
    stage.max_stamp_ahead_s = lambda: 0.0  # 0: no limit
    node.now = 1000 * MS
    node.send("key", 1000 + 3_600_000)
    assert len(served) == 1 and not node.diagnostics.rejected
