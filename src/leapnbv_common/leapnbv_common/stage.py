"""The one way a stage node takes a camera frame in: a key input, its companions, the waits, the drops.

A stage node declares the input that starts its work (the **key**: hmr's detections, raster's mesh,
nbv's target) and, in order, the **companions** the frame needs (its depth image, its camera_info,
its ground plane, its camera pose, ...), each with how it is matched to the frame and how long the
frame may wait for it. :class:`Stage` then does what every node used to write for itself:

- converts each message **once**, on arrival (a message that breaks its contract is counted as
  ``rejected.bad_<input>`` and never kept), and checks one content per stamp (``duplicate_stamp``);
- refuses a key or companion stamped later than the node clock's now + ``max_stamp_ahead_s`` (the
  node's parameter, :class:`leapnbv_common.params.StageParams`; 0 = off; not applied while the clock
  reads 0, a sim-time node before its first /clock): ``rejected.stamp_in_future``. Such a frame would
  never age out (its age is negative) and, once served, would make every later frame "older than
  published";
- applies the stamp rules to the key: a frame not newer than the newest one served is dropped
  (``duplicate_stamp`` / ``older_than_published``), unless it is so much older that the stamps
  started over (a replay from its start, a simulator reset: ``STAMP_RESTART_NS``);
- keeps companions in bounded caches by stamp (``<input>_evicted`` when one falls out unused) and
  pulls the ones that arrive at camera rate only when a frame needs them
  (:mod:`leapnbv_common.pulled_input`);
- walks each frame through its companions in order: a companion that is here is taken; one that is
  not is waited for (a timer that runs only while a frame waits), then the frame is served without
  it, rejected or dropped, as the companion says, with the reason counted;
- serves frames in stamp order: when a frame is served, every older frame still waiting is dropped
  (``<key>_superseded``), and older companion frames the graph never worked on are dropped
  (``<input>_skipped``);
- calls the node's ``on_frame(frame)`` with the converted values and the ``inputs`` list each output
  carries; an exception there is counted (``bad_frame`` for a ValueError, ``internal_error`` else) and
  never kills the node.

Nothing here imports a message package: the node passes the message types and converters in.
"""
from __future__ import annotations

import dataclasses
import traceback
from typing import Any, Callable, Dict, List, Optional, Sequence, Tuple

from leapnbv_common.contracts import ContractError, DuplicateStampGuard, check_stamp_not_ahead
from leapnbv_common.pulled_input import HOUSEKEEPING_PERIOD_S, PulledInput
from leapnbv_common.stamp_cache import STAMP_RESTART_NS, StampCache

__all__ = ["SAME_STAMP", "NEAREST", "SAME_OR_LATEST", "SERVE_WITHOUT", "REJECT", "DROP", "Received", "KeyInput",
           "Companion", "Frame", "Stage", "WAIT_CHECK_PERIOD_S"]

#: How often waiting frames are checked (the timer runs only while one waits).
WAIT_CHECK_PERIOD_S = 0.02

# How a companion is matched to a frame.
SAME_STAMP = "same_stamp"  # exactly the frame's stamp
NEAREST = "nearest"  # the nearest stamp within the companion's slop (a depth frame of the colour frame)
SAME_OR_LATEST = "same_or_latest"  # the frame's own, else the latest received (calibration: recorded STATIC)

# What a frame does when its companion did not come within its wait.
SERVE_WITHOUT = "serve_without"  # served with None for it (counted as rejected.<missing_reason> if one is set)
REJECT = "reject"  # not served: rejected.<missing_reason>
DROP = "drop"  # not served: dropped.<missing_reason>

# InputStamp relations (leapnbv_msgs/InputStamp: SAME_FRAME 0, CARRIED 1, EXCLUSION_HINT 2, STATIC 3), by value:
# this module imports no message package.
SAME_FRAME_RELATION = 0
STATIC_RELATION = 3


def _never(frame: Frame) -> float:
    return 0.0


def _always(frame: Frame) -> bool:
    return True


@dataclasses.dataclass
class Received:
    """One input message as converted on arrival.

    Attributes:
        stamp_ns: Its header stamp.
        header: Its header (a std_msgs Header, or a SerializedImage's).
        value: What its converter returned (arrays, a checked view, a pose).
        message: The message itself (for the few fields a converter does not carry).
    """

    stamp_ns: int
    header: Any
    value: Any
    message: Any = None

    @property
    def frame_id(self) -> str:
        return str(self.header.frame_id)


@dataclasses.dataclass
class KeyInput:
    """The input that starts a stage's work: its subscription keeps the newest message only.

    Args:
        name: The input's name (diagnostics, ``inputs`` entries, reasons).
        msg_type: The message class.
        topic: The relative topic name.
        convert: message -> value (raises ContractError / ValueError for a message that breaks its contract).
        qos: The subscription's QoS (depth 1: the newest wins while the node is busy).
        raw: Take it serialized (``convert`` gets the bytes).
        bad_reason: What a message that does not convert is counted as (default ``bad_<name>``).
        accept: value -> a drop reason, or None to take the frame (e.g. detections without a person).
        frame_name: What the stage's frames are called in drop reasons (``<frame_name>_superseded``;
            default the name).
    """

    name: str
    msg_type: Any
    topic: str
    convert: Callable[[Any], Any]
    qos: Any
    raw: bool = False
    bad_reason: str = ""
    accept: Optional[Callable[[Received], Optional[str]]] = None
    frame_name: str = ""

    def __post_init__(self) -> None:
        self.bad_reason = self.bad_reason or f"bad_{self.name}"
        self.frame_name = self.frame_name or self.name


@dataclasses.dataclass
class Companion:
    """A message a frame needs besides its key, in the order the frame takes them.

    Args:
        name: The input's name (diagnostics, ``inputs`` entries, reasons).
        msg_type, topic, qos: Its subscription (topic None: the node supplies it through ``lookup``).
        convert: message -> value, run once on arrival (ContractError / ValueError: ``bad_reason``).
        match: SAME_STAMP, NEAREST (within ``slop_s``) or SAME_OR_LATEST.
        wait_s: frame -> how long (s) the frame waits for it now (read per frame: live parameters).
        when_missing: SERVE_WITHOUT, REJECT or DROP once the wait ran out.
        missing_reason: Counted when it never came (rejected.<reason>, or dropped.<reason> for DROP);
            empty with SERVE_WITHOUT: served without it silently.
        missing_detail: frame -> the detail logged with that reason.
        needed: frame -> whether this frame needs it at all (False: skipped, None in the frame).
        slop_s: frame -> the NEAREST match's tolerance (s).
        stamp_from: Match it on another companion's stamp instead of the frame's (the camera_info of the
            depth frame the frame was paired with).
        capacity: Messages kept by stamp.
        raw: Take it serialized.
        pulled: Read only when a frame needs it (it arrives at camera rate and must not wake the node).
        consume: Take it out of the cache when a frame uses it (a depth frame is used once).
        skip_older: Drop arrivals older than the newest frame served (``<name>_older_than_published``) and,
            when a frame is served, the cached ones older than the one it used (``<name>_skipped``).
        validate: Received -> None, raising ContractError for an arrival that disagrees with what the stage
            already has (a depth frame against its own camera_info).
        lookup: frame -> Received or None: where the node answers for this companion itself (a camera-pose
            source, the previous frame's mask); the cache is not used.
        expect: frame -> None, called once when a frame starts waiting for it (a camera-pose source that
            must be told which stamp is wanted).
        on_missing: frame -> None, called when the wait for it ran out (e.g. stop waiting for a stream
            that stopped).
        bad_reason: What a message that does not convert is counted as (default ``bad_<name>``).
        static_relation: The relation recorded for a SAME_OR_LATEST fallback (STATIC).
    """

    name: str
    msg_type: Any = None
    topic: Optional[str] = None
    convert: Callable[[Any], Any] = lambda msg: msg
    qos: Any = None
    match: str = SAME_STAMP
    wait_s: Callable[[Frame], float] = _never
    when_missing: str = SERVE_WITHOUT
    missing_reason: str = ""
    missing_detail: Callable[[Frame], str] = lambda frame: ""
    needed: Callable[[Frame], bool] = _always
    slop_s: Callable[[Frame], float] = _never
    stamp_from: Optional[str] = None
    capacity: int = 10
    raw: bool = False
    pulled: bool = False
    consume: bool = False
    skip_older: bool = False
    validate: Optional[Callable[[Received], None]] = None
    lookup: Optional[Callable[[Frame], Optional[Received]]] = None
    expect: Optional[Callable[[Frame], None]] = None
    on_missing: Optional[Callable[[Frame], None]] = None
    bad_reason: str = ""
    static_relation: int = STATIC_RELATION

    def __post_init__(self) -> None:
        self.bad_reason = self.bad_reason or f"bad_{self.name}"
        if self.match not in (SAME_STAMP, NEAREST, SAME_OR_LATEST):
            raise ValueError(f"companion {self.name!r}: unknown match {self.match!r}")
        if self.when_missing not in (SERVE_WITHOUT, REJECT, DROP):
            raise ValueError(f"companion {self.name!r}: unknown when_missing {self.when_missing!r}")


class Frame:
    """One camera frame on its way through a stage: the key and the companions taken so far.

    ``frame["depth"]`` is a companion's converted value (None when the frame was served without it),
    ``frame.received("depth")`` its :class:`Received`, ``frame.inputs`` the (name, stamp, relation)
    entries an output lists (leapnbv_msgs/InputStamp), in the order they were taken.
    """

    def __init__(self, key_name: str, key: Received, now_ns: int) -> None:
        self.key_name = key_name
        self.key = key
        self.stamp_ns = key.stamp_ns
        self.header = key.header
        self.arrived_ns = now_ns
        self.inputs: List[Tuple[str, int, int]] = [(key_name, key.stamp_ns, SAME_FRAME_RELATION)]
        self._received: Dict[str, Optional[Received]] = {key_name: key}
        self.next_companion = 0
        self.waiting_since_ns = now_ns  # when it began to wait for its current companion
        self.expected = False  # the current companion's expect() was called

    def __getitem__(self, name: str) -> Any:
        received = self._received.get(name)
        return None if received is None else received.value

    def received(self, name: str) -> Optional[Received]:
        return self._received.get(name)

    def has(self, name: str) -> bool:
        return self._received.get(name) is not None

    def take(self, name: str, received: Optional[Received], relation: int = SAME_FRAME_RELATION) -> None:
        self._received[name] = received
        if received is not None:
            self.inputs.append((name, received.stamp_ns, relation))


class Stage:
    """A stage's intake (see the module docstring).

    Args:
        node: The rclpy node; it must have ``diagnostics`` (StageDiagnostics) and ``get_logger``.
        key: The input that starts the work.
        companions: What each frame takes, in order.
        on_frame: Called with each frame that is served.
        capacity: Frames waiting at once (the oldest falls out: ``<key>_evicted``).
        stamp_guard: The node's DuplicateStampGuard (one content per stamp and input), if it has other
            inputs that share it.
        frame_error_reason: What a ValueError raised by ``on_frame`` is counted as.
        on_restart: Called when the stamps started over (the node forgets what it keeps by stamp itself).
        max_stamp_ahead_s: () -> how far (s) a stamp may be ahead of the node clock (0: no limit); default the
            node's ``max_stamp_ahead_s`` parameter (StageParams), read per message (live parameters).
    """

    def __init__(self, node: Any, key: KeyInput, companions: Sequence[Companion], on_frame: Callable[[Frame], None],
                 capacity: int = 10, stamp_guard: Optional[DuplicateStampGuard] = None,
                 frame_error_reason: str = "bad_frame", on_restart: Optional[Callable[[], None]] = None,
                 max_stamp_ahead_s: Optional[Callable[[], float]] = None) -> None:
        self.node = node
        self.max_stamp_ahead_s = max_stamp_ahead_s or self._stamp_ahead_parameter
        self.diagnostics = node.diagnostics
        self.key = key
        self.companions = list(companions)
        self.on_frame = on_frame
        self.frame_error_reason = frame_error_reason
        self.on_restart = on_restart
        self.capacity = max(1, int(capacity))
        self.stamps = stamp_guard or DuplicateStampGuard()
        drop = self.diagnostics.drop_callback()
        self.caches: Dict[str, StampCache[Received]] = {
            c.name: StampCache(c.capacity, c.name + "_evicted", drop) for c in self.companions if c.topic}
        self.latest: Dict[str, Received] = {}
        self.waiting: List[Frame] = []  # oldest first
        self.served_stamp: Optional[int] = None
        self.restarts = 0
        self._pulled: List[PulledInput] = []
        self._extra_pulled: List[PulledInput] = []
        self._subscriptions: List[Any] = []
        self._timers: List[Any] = []
        self._wait_timer: Any = None

    # ------------------------------------------------------------------ life cycle

    def start(self) -> None:
        """Create the subscriptions and timers (a lifecycle node's activate)."""
        node = self.node
        # Calibration (SAME_OR_LATEST) is pulled before the frames: a frame taken in the same pull is checked
        # against its own camera_info.
        for companion in sorted(self.companions, key=lambda c: c.match != SAME_OR_LATEST):
            if companion.topic is None:
                continue
            callback = self._companion_callback(companion)
            if companion.pulled:
                pulled = PulledInput.create(node, companion.msg_type, companion.topic, callback, companion.qos,
                                            raw=companion.raw)
                self._pulled.append(pulled)
                self._subscriptions.append(pulled.subscription)
            else:
                self._subscriptions.append(node.create_subscription(
                    companion.msg_type, companion.topic, callback, companion.qos, raw=companion.raw))
        self._subscriptions.append(node.create_subscription(
            self.key.msg_type, self.key.topic, self._on_key, self.key.qos, raw=self.key.raw))
        # A bad companion is counted within HOUSEKEEPING_PERIOD_S even while no frame comes.
        if self._pulled or self._extra_pulled:
            self._timers.append(node.create_timer(HOUSEKEEPING_PERIOD_S, self.pull))
        self._wait_timer = node.create_timer(WAIT_CHECK_PERIOD_S, self._check_waits)
        self._wait_timer.cancel()  # runs only while a frame waits: an idle node does not wake up
        self._timers.append(self._wait_timer)

    def stop(self) -> None:
        """Destroy the subscriptions and timers and forget the waiting frames (a lifecycle node's deactivate)."""
        for subscription in self._subscriptions:
            self.node.destroy_subscription(subscription)
        for timer in self._timers:
            self.node.destroy_timer(timer)
        self._subscriptions, self._timers, self._pulled, self._wait_timer = [], [], [], None
        self.waiting = []

    def add_pulled(self, pulled: Optional[PulledInput]) -> None:
        """Drain this pulled input with the stage's own (e.g. a camera-pose source's subscription)."""
        if pulled is not None:
            self._extra_pulled.append(pulled)

    def pull(self) -> None:
        """Take what the pulled companions received since the last pull."""
        for pulled in self._pulled + self._extra_pulled:
            pulled.drain()

    def now_ns(self) -> int:
        return int(self.node.get_clock().now().nanoseconds)

    def _stamp_ahead_parameter(self) -> float:
        params = getattr(getattr(self.node, "params", None), "value", None)
        return float(getattr(params, "max_stamp_ahead_s", 0.0))

    # ------------------------------------------------------------------ arrivals

    def _convert(self, name: str, convert: Callable[[Any], Any], bad_reason: str, msg: Any) -> Optional[Received]:
        """The converted arrival, or None when it broke its contract (counted)."""
        try:
            value = convert(msg)
            header = getattr(value, "header", None) or msg.header
            stamp = int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)
            # Before the stamp is remembered: a frame from the future must not make its stamp "seen".
            check_stamp_not_ahead(name, stamp, self.now_ns(), self.max_stamp_ahead_s())
            self.stamps.check(name, value if hasattr(value, "header") and not hasattr(msg, "header") else msg)
        except ContractError as error:
            self.diagnostics.reject(error.reason or bad_reason, error.detail)
            return None
        except ValueError as error:
            self.diagnostics.reject(bad_reason, str(error))
            return None
        return Received(stamp, header, value, msg)

    def _guarded(self, reason: str, call: Callable[[], None]) -> None:
        """Run ``call``; an exception is counted (``reason`` for a ValueError), never raised."""
        try:
            call()
        except ValueError as error:
            self.diagnostics.reject(reason, str(error))
        except Exception as error:  # noqa: BLE001 - a node must survive any bad frame
            self.diagnostics.reject("internal_error", f"{type(error).__name__}: {error}")
            self.node.get_logger().error(traceback.format_exc(), throttle_duration_sec=5.0)

    def _on_key(self, msg: Any, info: Any) -> None:  # two arguments: rclpy passes the MessageInfo
        self.diagnostics.frame_in()
        self.diagnostics.input_seen(self.key.name, info)
        self._guarded(self.key.bad_reason, lambda: self._take_key(msg))

    def _take_key(self, msg: Any) -> None:
        received = self._convert(self.key.name, self.key.convert, self.key.bad_reason, msg)
        if received is None:
            return
        stamp = received.stamp_ns
        if self.served_stamp is not None and stamp <= self.served_stamp:
            if self.served_stamp - stamp < STAMP_RESTART_NS:
                self.diagnostics.drop("duplicate_stamp" if stamp == self.served_stamp else "older_than_published")
                return
            self.restart()
        if any(frame.stamp_ns == stamp for frame in self.waiting):
            self.diagnostics.drop("duplicate_stamp")  # the frame's first key message waits already
            return
        if self.key.accept is not None:
            reason = self.key.accept(received)
            if reason:
                self.diagnostics.drop(reason)
                return
        self.pull()
        frame = Frame(self.key.name, received, self.now_ns())
        self.waiting.append(frame)
        self.waiting.sort(key=lambda f: f.stamp_ns)
        while len(self.waiting) > self.capacity:
            self.waiting.pop(0)
            self.diagnostics.drop(self.key.frame_name + "_evicted")
        self._advance(frame)

    def restart(self) -> None:
        """The stamps started over: forget the frames waiting and the newest served (companions stay: the new
        run's first ones may have come before its first frame)."""
        if self.waiting:
            self.diagnostics.drop(self.key.frame_name + "_reset", len(self.waiting))
        self.waiting = []
        self.served_stamp = None
        self.restarts += 1
        if self.on_restart is not None:
            self.on_restart()

    def _companion_callback(self, companion: Companion) -> Callable[..., None]:
        def on_message(msg: Any, info: Any) -> None:
            self.diagnostics.input_seen(companion.name, info)
            self._guarded(companion.bad_reason, lambda: self._take_companion(companion, msg))
        return on_message

    def _take_companion(self, companion: Companion, msg: Any) -> None:
        received = self._convert(companion.name, companion.convert, companion.bad_reason, msg)
        if received is None:
            return
        if companion.validate is not None:
            try:
                companion.validate(received)
            except ContractError as error:
                self.diagnostics.reject(error.reason or companion.bad_reason, error.detail)
                return
        stamp = received.stamp_ns
        if companion.skip_older and self.served_stamp is not None and \
                0 < self.served_stamp - stamp < STAMP_RESTART_NS:
            self.diagnostics.drop(companion.name + "_older_than_published")
            return
        self.caches[companion.name].put(stamp, received)
        self.latest[companion.name] = received
        self.companion_arrived(companion.name)

    def companion_arrived(self, name: str) -> None:
        """A companion called ``name`` may now answer for waiting frames (a source the node owns calls this)."""
        for frame in list(self.waiting):
            if frame in self.waiting and frame.next_companion < len(self.companions) and \
                    self.companions[frame.next_companion].name == name:
                self._advance(frame)

    # ------------------------------------------------------------------ matching, waiting, serving

    def _match_stamp(self, companion: Companion, frame: Frame) -> Optional[int]:
        if companion.stamp_from is None:
            return frame.stamp_ns
        other = frame.received(companion.stamp_from)
        return None if other is None else other.stamp_ns

    def find(self, companion: Companion, frame: Frame) -> Tuple[Optional[Received], int]:
        """(what answers for ``companion`` in ``frame`` now, or None; the relation to record)."""
        if companion.lookup is not None:
            return companion.lookup(frame), SAME_FRAME_RELATION
        cache = self.caches[companion.name]
        stamp = self._match_stamp(companion, frame)
        if companion.match == NEAREST:
            if stamp is None:
                return None, SAME_FRAME_RELATION
            found = cache.find_nearest(stamp, int(companion.slop_s(frame) * 1e9))
            return (None if found is None else found[1]), SAME_FRAME_RELATION
        exact = None if stamp is None else cache.get_exact(stamp)
        if exact is not None or companion.match == SAME_STAMP:
            return exact, SAME_FRAME_RELATION
        return None, companion.static_relation  # SAME_OR_LATEST: the fallback is decided when the wait ran out

    def _advance(self, frame: Frame) -> None:
        """Take the frame's companions in order; it waits at the first one missing, or is served."""
        while frame.next_companion < len(self.companions):
            companion = self.companions[frame.next_companion]
            if not companion.needed(frame):
                frame.take(companion.name, None)
                self._next(frame)
                continue
            found, relation = self.find(companion, frame)
            if found is not None:
                frame.take(companion.name, found, relation)
                if companion.consume:
                    self.caches[companion.name].pop(found.stamp_ns)
                self._next(frame)
                continue
            now = self.now_ns()
            if now - frame.waiting_since_ns < companion.wait_s(frame) * 1e9:
                if companion.expect is not None and not frame.expected:
                    frame.expected = True
                    companion.expect(frame)
                self._start_wait_timer()
                return
            if not self._missing(companion, frame):
                self._remove(frame)
                return
            self._next(frame)
        self._serve(frame)

    def _next(self, frame: Frame) -> None:
        frame.next_companion += 1
        frame.waiting_since_ns = self.now_ns()
        frame.expected = False

    def _missing(self, companion: Companion, frame: Frame) -> bool:
        """The wait for ``companion`` ran out: whether the frame goes on without it (counted as it says)."""
        if companion.on_missing is not None:
            companion.on_missing(frame)
        if companion.match == SAME_OR_LATEST and companion.lookup is None and companion.name in self.latest:
            frame.take(companion.name, self.latest[companion.name], companion.static_relation)
            return True
        reason = companion.missing_reason
        if companion.when_missing == DROP:
            self.diagnostics.drop(reason or companion.name + "_missing")
            return False
        if companion.when_missing == REJECT:
            self.diagnostics.reject(reason or "no_" + companion.name, companion.missing_detail(frame))
            return False
        if reason:
            self.diagnostics.reject(reason, companion.missing_detail(frame))
        frame.take(companion.name, None)
        return True

    def _remove(self, frame: Frame) -> None:
        if frame in self.waiting:
            self.waiting.remove(frame)

    def _serve(self, frame: Frame) -> None:
        self._remove(frame)
        if self.served_stamp is not None and frame.stamp_ns <= self.served_stamp:
            self.diagnostics.drop("older_than_published")
            return
        self.served_stamp = frame.stamp_ns
        # Older frames still waiting can no longer be the newest result.
        older = [f for f in self.waiting if f.stamp_ns < frame.stamp_ns]
        for stale in older:
            self.waiting.remove(stale)
        if older:
            self.diagnostics.drop(self.key.frame_name + "_superseded", len(older))
        for companion in self.companions:
            used = frame.received(companion.name)
            if companion.skip_older and used is not None and companion.name in self.caches:
                self.caches[companion.name].drop_older_than(used.stamp_ns, companion.name + "_skipped")
        self._guarded(self.frame_error_reason, lambda: self.on_frame(frame))

    def _start_wait_timer(self) -> None:
        if self._wait_timer is not None and self._wait_timer.is_canceled():
            self._wait_timer.reset()

    def _check_waits(self) -> None:
        """The wait timer: pull, then move every waiting frame on (its companion came, or its wait ran out)."""
        self.pull()
        for frame in list(self.waiting):
            if frame in self.waiting:
                self._guarded("bad_frame", lambda: self._advance(frame))  # noqa: B023 - called at once
        if not self.waiting and self._wait_timer is not None:
            self._wait_timer.cancel()
