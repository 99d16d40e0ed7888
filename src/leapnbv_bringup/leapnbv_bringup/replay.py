"""Replay a rosbag2 (MCAP) bag into the running graph, and record what the graph publishes.

Replay publishes each message's recorded CDR bytes as they are (no re-serialization), with
/clock from the bag's timeline for nodes that use sim time. Three pacings:
  * rate = 1.0: recorded timing; rate = k: k times faster or slower;
  * rate = None ("keep up"): one camera frame at a time, each published once the graph's
    final output for the previous frame arrived (or a timeout passed) -- the regression mode.

    python -m leapnbv_bringup.replay bags/sample_a [--rate 2.0 | --keep-up]

The bag is opened and checked (every MCAP chunk's CRC) before anything is published; a bag
whose MCAP summary/footer is missing but whose data section is complete is replayed (said on
stderr). Exit codes: 0 replayed, 2 usage, 3 unreadable bag (one line: the path and what is wrong).
"""
from __future__ import annotations

import argparse
import struct
import sys
import time
from dataclasses import dataclass, field
from typing import Any, Dict, Iterator, List, Optional, Set, Tuple, cast

from leapnbv_bags.bag_io import EXIT_OK, EXIT_UNREADABLE_BAG, BagError, check_bag
from leapnbv_bringup.graph import CAMERA_TOPICS, FINAL_OUTPUT_TOPIC, OUTPUT_TOPICS
from leapnbv_common.topics import MODEL_OUTPUT_TOPICS

COLOUR_TOPIC = CAMERA_TOPICS["image"]


@dataclass
class BagMessage:
    topic: str
    msgtype: str
    log_time_ns: int
    cdr: bytes


@dataclass
class CameraFrame:
    """The messages of one camera frame (same header stamp as the colour image)."""

    stamp_ns: int
    log_time_ns: int
    messages: List[BagMessage] = field(default_factory=list)


def header_stamp_ns(cdr: bytes) -> int:
    """The header stamp of a CDR-serialized message that starts with a std_msgs/Header.

    After the 4-byte encapsulation header come int32 sec and uint32 nanosec (little endian
    when the encapsulation says so, which every ROS 2 CDR writer does on x86 and ARM).
    """
    little = cdr[1] == 1
    sec, nanosec = struct.unpack_from("<iI" if little else ">iI", cdr, 4)
    return sec * 1_000_000_000 + nanosec


def read_bag_messages(path: str, topics: Optional[Set[str]] = None) -> Iterator[BagMessage]:
    """Every message of a bag in log-time order, as raw CDR bytes."""
    from leapnbv_bags.bag_io import read_bag

    for topic, msgtype, log_time, cdr in read_bag(path, topics=None if topics is None else sorted(topics), raw=True):
        yield BagMessage(topic, msgtype, log_time, bytes(cast(bytes, cdr)))  # raw=True: the CDR buffer


def load_camera_frames(bag_path: str) -> List[CameraFrame]:
    """Check a bag (leapnbv_bags.bag_io.check_bag) and read it into camera frames, before any graph starts.

    Raises:
        BagError: the bag is unreadable (missing metadata.yaml, truncated, corrupt, ...) or holds no
            colour frame; one line naming the path and what is wrong.
    """
    check_bag(bag_path)
    try:
        frames = group_camera_frames(list(read_bag_messages(bag_path)))
    except struct.error as error:  # a colour image too short to hold a header
        raise BagError(f"{bag_path}: a message on {COLOUR_TOPIC} is too short for a header: {error}") from None
    if not frames:
        raise BagError(f"{bag_path}: no colour frames on {COLOUR_TOPIC}")
    return frames


def group_camera_frames(messages: List[BagMessage]) -> List[CameraFrame]:
    """Group messages into camera frames by the header stamp of the colour image.

    Every message with a header whose stamp equals a colour image's stamp joins that frame;
    other messages (no header, or a stamp of no colour image) join the frame current at
    their log time, so nothing is left out. Within a frame the camera infos go first (calibration
    before the images, as a driver and the simulator publish them), the rest in the bag's order: the
    order of messages with one log time is the reader's (rosbags' seeking reader and a sequential
    read of a bag without its MCAP summary differ), and must not decide whether a node has its
    camera_info when the frame's first image arrives.
    """
    colour_stamps = {header_stamp_ns(m.cdr) for m in messages if m.topic == COLOUR_TOPIC}
    frames: Dict[int, CameraFrame] = {}
    current: Optional[CameraFrame] = None
    for message in messages:
        try:
            stamp = header_stamp_ns(message.cdr)
        except struct.error:
            stamp = None
        if stamp in colour_stamps:
            frame = frames.get(stamp)
            if frame is None:
                frame = frames[stamp] = CameraFrame(stamp, message.log_time_ns)
            current = frame
        elif current is None:
            continue  # before the first camera frame: nothing to attach it to
        else:
            frame = current
        frame.messages.append(message)
    for frame in frames.values():
        frame.messages.sort(key=lambda m: 0 if m.msgtype.endswith("/CameraInfo") else 1)  # stable
    return sorted(frames.values(), key=lambda f: f.log_time_ns)


class BagReplayer:
    """Publishes a bag's camera frames into the graph from an rclpy node."""

    def __init__(self, node, bag_path: str, rate: Optional[float] = 1.0, frame_timeout_s: float = 10.0,
                 publish_clock: bool = True, wait_topic: str = FINAL_OUTPUT_TOPIC,
                 frames: Optional[List[CameraFrame]] = None) -> None:
        """Publishers for every topic of the bag's frames (``frames`` when already read: load_camera_frames)."""
        from rclpy.qos import QoSProfile, ReliabilityPolicy
        from rosgraph_msgs.msg import Clock

        from leapnbv_common.qos import camera_input_qos

        self.node = node
        self.rate = rate
        self.frame_timeout_s = frame_timeout_s
        self.resent: List[int] = []  # stamps of frames sent a second time (keep-up mode)
        self.frames = frames if frames is not None else load_camera_frames(bag_path)
        self.publishers: Dict[str, Any] = {}
        for frame in self.frames:
            for m in frame.messages:
                if m.topic not in self.publishers:
                    msg_class = _message_class(m.msgtype)
                    # Camera topics as a driver publishes them; everything else reliable.
                    qos = camera_input_qos(5) if m.topic.startswith("/camera/") else \
                        QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
                    self.publishers[m.topic] = node.create_publisher(msg_class, m.topic, qos)
        self.clock_pub = node.create_publisher(Clock, "/clock", 10) if publish_clock else None
        self._clock_class = Clock
        self.completed: Set[int] = set()
        self.published_at: Dict[int, int] = {}  # frame stamp -> wall time it was published (ns)
        node.create_subscription(_message_class(OUTPUT_TOPICS[wait_topic]), wait_topic, self._on_final, 10,
                                 raw=True)

    def _on_final(self, cdr: bytes) -> None:
        self.completed.add(header_stamp_ns(cdr))

    def wait_for_subscribers(self, timeout_s: float = 10.0) -> None:
        """Give DDS discovery time to match every publisher with the graph's subscriptions.

        A camera topic has several subscribers (depth: raster and ground): each publisher waits
        until it is matched with every subscription the graph cache knows on its topic, so that the
        first frame reaches all of them, not only the first one matched.
        """
        import rclpy

        def matched(topic: str, publisher) -> bool:
            known = len(self.node.get_subscriptions_info_by_topic(topic))
            return known > 0 and publisher.get_subscription_count() >= known

        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if all(matched(t, p) for t, p in self.publishers.items() if t.startswith("/camera/")):
                break
            rclpy.spin_once(self.node, timeout_sec=0.05)
        # Let the subscriptions' matching settle on both sides before the first frame.
        end = time.monotonic() + 0.5
        while time.monotonic() < end:
            rclpy.spin_once(self.node, timeout_sec=0.05)

    def publish_frame(self, frame: CameraFrame) -> None:
        if self.clock_pub is not None:
            clock = self._clock_class()
            clock.clock.sec, clock.clock.nanosec = divmod(frame.log_time_ns, 1_000_000_000)
            self.clock_pub.publish(clock)
        self.published_at[frame.stamp_ns] = self.node.get_clock().now().nanoseconds
        for m in frame.messages:
            self.publishers[m.topic].publish(m.cdr)

    def run(self) -> Tuple[int, List[int]]:
        """Replay every frame; returns (frames published, stamps whose final output never came)."""
        import rclpy

        self.wait_for_subscribers()
        timed_out = []
        start_wall = time.monotonic()
        start_log = self.frames[0].log_time_ns
        for frame in self.frames:
            if self.rate:
                due = start_wall + (frame.log_time_ns - start_log) * 1e-9 / self.rate
                while time.monotonic() < due:
                    rclpy.spin_once(self.node, timeout_sec=max(0.0, min(0.01, due - time.monotonic())))
            self.publish_frame(frame)
            if self.rate is None:
                # Camera topics are best effort: a frame whose messages were lost on the way is sent
                # once more, unchanged, half-way through its wait (the nodes accept an identical resend).
                for attempt in range(2):
                    deadline = time.monotonic() + 0.5 * self.frame_timeout_s
                    while frame.stamp_ns not in self.completed and time.monotonic() < deadline:
                        rclpy.spin_once(self.node, timeout_sec=0.01)
                    if frame.stamp_ns in self.completed or attempt == 1:
                        break
                    self.resent.append(frame.stamp_ns)
                    self.publish_frame(frame)
                if frame.stamp_ns not in self.completed:
                    timed_out.append(frame.stamp_ns)
        return len(self.frames), timed_out


def _message_class(msgtype: str):
    """The rclpy message class of 'pkg/msg/Type' (or 'pkg/Type')."""
    import importlib

    parts = msgtype.split("/")
    if len(parts) not in (2, 3) or (len(parts) == 3 and parts[1] != "msg"):
        raise ValueError(f"not a message type name: {msgtype!r}")
    module = importlib.import_module(parts[0] + ".msg")
    try:
        return getattr(module, parts[-1])
    except AttributeError:
        raise ValueError(f"unknown message type {msgtype!r}") from None


class OutputRecorder:
    """Subscribes to every output topic of the graph and keeps the raw messages in arrival order.

    The default topics are every frame's outputs and those sent once per model (the mesh triangles the
    meshes name), so that a bag written from the recording is complete.
    """

    def __init__(self, node, topics: Optional[Dict[str, str]] = None) -> None:
        from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

        self.topics = dict(topics or {**OUTPUT_TOPICS, **MODEL_OUTPUT_TOPICS})
        self.messages: List[Tuple[str, int, bytes]] = []
        for topic, msgtype in self.topics.items():
            durable = topic.endswith(("next_best_view", "base_goal")) or topic in MODEL_OUTPUT_TOPICS
            qos = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE,
                             durability=DurabilityPolicy.TRANSIENT_LOCAL if durable else DurabilityPolicy.VOLATILE)
            node.create_subscription(_message_class(msgtype), topic,
                                     lambda cdr, t=topic: self._on_message(t, cdr), qos, raw=True)
        self._node = node

    def _on_message(self, topic: str, cdr: bytes) -> None:
        self.messages.append((topic, self._node.get_clock().now().nanoseconds, bytes(cdr)))

    def decoded(self) -> List[Tuple[str, int, object]]:
        """(topic, receive time ns, rclpy message) for everything recorded."""
        from rclpy.serialization import deserialize_message

        classes = {t: _message_class(m) for t, m in self.topics.items()}
        return [(t, when, deserialize_message(cdr, classes[t])) for t, when, cdr in self.messages]

    def write_bag(self, path: str, overwrite: bool = True) -> None:
        """Write what was recorded as a rosbag2 MCAP bag (atomically: complete or not at all)."""
        from leapnbv_bags.bag_io import BagWriter

        with BagWriter(path, overwrite=overwrite) as bag:
            for topic in sorted({t for t, _, _ in self.messages}):
                bag.add_topic(topic, self.topics[topic])
            for topic, when, cdr in self.messages:
                bag.write(topic, when, cdr)


def main(argv: Optional[List[str]] = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("bag", help="rosbag2 directory (MCAP)")
    pacing = parser.add_mutually_exclusive_group()
    pacing.add_argument("--rate", type=float, default=1.0, help="time factor (1 = recorded timing)")
    pacing.add_argument("--keep-up", action="store_true",
                        help="publish each frame once the graph answered the previous one")
    parser.add_argument("--frame-timeout", type=float, default=10.0)
    parser.add_argument("--no-clock", action="store_true", help="do not publish /clock")
    args = parser.parse_args(argv)
    try:
        frames = load_camera_frames(args.bag)  # before ROS starts: an unreadable bag ends here
    except BagError as error:
        print(f"[replay] unreadable bag: {error}", file=sys.stderr)
        return EXIT_UNREADABLE_BAG

    import rclpy
    from rclpy.node import Node

    rclpy.init()
    node = Node("leapnbv_replay")
    try:
        replayer = BagReplayer(node, args.bag, rate=None if args.keep_up else args.rate,
                               frame_timeout_s=args.frame_timeout, publish_clock=not args.no_clock, frames=frames)
        count, missing = replayer.run()
        print(f"[replay] published {count} frames from {args.bag}"
              + (f"; no final output for {len(missing)}" if args.keep_up and missing else ""))
    except KeyboardInterrupt:
        pass
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
    return EXIT_OK


if __name__ == "__main__":
    sys.exit(main())
