"""The camera pose from the robot's TF tree (``camera_pose_source: tf``).

Every robot publishes its frames on ``/tf`` (dynamic links: ``map -> odom`` from localization,
``odom -> base_link`` from odometry, a pan-tilt head's joints) and ``/tf_static`` (fixed mounts:
``base_link -> camera_link -> camera_color_optical_frame``). :class:`TfCameraPoseSource` answers
``pose_at(stamp, camera_frame)`` with ``T_fixed_camera`` at the image's stamp (``camera_frame`` is the
image's ``header.frame_id``, the fixed frame the ``camera_pose_fixed_frame`` parameter), each dynamic
link interpolated between its two transforms around the stamp.

Where ``tf2_ros`` is installed (the robot) the transforms go into a ``tf2_ros.Buffer`` (tf2's C++
core); elsewhere (ROS 2 from PyPI wheels, which have no tf2) into the project's own
:class:`~leapnbv_common.tf_buffer.TransformBuffer`, which follows tf2's rules. Either way the source
subscribes to /tf and /tf_static itself, with tf2_ros's QoS (as ``tf2_ros.TransformListener`` does),
so that it knows when new transforms come:

* a frame that waits for its pose (``expect``) gets it through ``on_pose`` as soon as the tree has
  it (checked on each TF message, and by a short timer that runs only while something waits);
* as the newest stamp the whole chain ``fixed frame -> camera`` covers advances, the pose at that
  stamp is handed to ``on_pose`` too (a TF relay's PoseStamped, without the relay): a node that
  learns poses as they come (ground_node) sees them, and on the simulator, whose links are stamped
  with each camera frame, that is each frame's pose.

A lookup that fails says why (:class:`~leapnbv_common.tf_buffer.TransformError`: frames not
connected, or an extrapolation by how much): ``pose_at`` returns None and logs it (throttled),
``lookup`` raises it. A transform with a bad quaternion or a non-finite translation is counted as
``bad_transform`` and left out; a pose that breaks the camera-pose contract as ``bad_camera_pose``.
"""
from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass
from typing import Any, Callable, Dict, List, Optional, Set, Tuple
from typing import OrderedDict as OrderedDictType

from rclpy.duration import Duration
from rclpy.time import Time
from tf2_msgs.msg import TFMessage

from leapnbv_common.camera_pose import PoseCallback, StampedCameraPose, camera_pose_source, checked_camera_pose
from leapnbv_common.camera_pose.tf_messages import transform_from_msg
from leapnbv_common.conversions import ConversionError, stamp_to_ns
from leapnbv_common.diagnostics import rejects_bad_input
from leapnbv_common.node_params import NodeParams
from leapnbv_common.params import param, param_specs, params_from_values
from leapnbv_common.qos import tf_qos, tf_static_qos
from leapnbv_common.tf_buffer import (
    ExtrapolationError,
    MissingTransformError,
    Transform,
    TransformBuffer,
    TransformError,
)
from leapnbv_common.topics import TF_STATIC_TOPIC, TF_TOPIC

try:  # the robot's tf2 (ROS distro); ROS 2 from PyPI wheels has none
    import tf2_ros
except ImportError:
    tf2_ros = None

__all__ = ["TfCameraPoseParams", "TfCameraPoseSource", "TfListener", "tf2_available"]

#: How often the frames that wait for a pose are looked up again (only while one waits).
WAIT_CHECK_PERIOD_S = 0.01
#: How long (node clock) the source keeps looking for an expected pose; the node's own wait
#: (``camera_pose_wait_s``) is shorter and decides what happens to its frame.
EXPECT_LIFETIME_NS = 2_000_000_000
#: A failed lookup of one kind (missing, extrapolation) and camera frame is logged at most this often.
LOG_PERIOD_NS = 5_000_000_000
#: The authority tf2 records for the transforms the source inserts (tf2 logs it on conflicts).
AUTHORITY = "leapnbv_common.camera_pose.tf_source"


@dataclass
class TfCameraPoseParams:
    """Parameters the TF source declares on its node (read at start-up)."""

    camera_pose_fixed_frame: str = param("map", "the fixed, floor-aligned frame (z up, floor z = 0) the TF "
                                         "camera-pose source gives the camera's pose in", read_only=True)
    camera_pose_camera_frame: str = param("camera_color_optical_frame", "the camera's optical frame whose poses "
                                          "the TF source hands on as the tree's newest stamp advances (a frame's "
                                          "own lookups use the image's frame_id)", read_only=True)
    camera_pose_tf_cache_s: float = param(10.0, "s: how long each dynamic TF link's transforms are kept (tf2's "
                                          "cache time)", min=0.5, max=3600.0, read_only=True)


def tf_params(node) -> TfCameraPoseParams:
    """The TF source's parameters of a node, declared on first use (a second source on the node reads them)."""
    specs = param_specs(TfCameraPoseParams)
    if all(node.has_parameter(spec.name) for spec in specs):
        return params_from_values(TfCameraPoseParams, {spec.name: node.get_parameter(spec.name).value
                                                       for spec in specs})
    return NodeParams(node, TfCameraPoseParams).value


def tf2_available() -> bool:
    """Whether tf2_ros is installed here (then the source's transforms go into a tf2_ros.Buffer)."""
    return tf2_ros is not None


class _OwnStore:
    """Transforms in the project's TransformBuffer (no tf2 here)."""

    kind = "leapnbv_common.tf_buffer.TransformBuffer"

    def __init__(self, cache_time_ns: int) -> None:
        self.buffer = TransformBuffer(cache_time_ns)

    def add(self, msg, link, static: bool) -> None:
        self.buffer.set_transform(link, static)

    def lookup(self, target: str, source: str, stamp_ns: int) -> Transform:
        return self.buffer.lookup(target, source, stamp_ns)

    def latest_stamp(self, target: str, source: str) -> int:
        return self.buffer.latest_common_stamp(target, source)


class _Tf2Store:
    """Transforms in a tf2_ros.Buffer (the robot); tf2's exceptions become TransformErrors."""

    kind = "tf2_ros.Buffer"

    def __init__(self, cache_time_ns: int) -> None:
        # Without a node: Buffer(node=...) would offer a tf2_frames service from every node that has a source.
        self.buffer = tf2_ros.Buffer(cache_time=Duration(nanoseconds=int(cache_time_ns)))

    def add(self, msg, link, static: bool) -> None:
        if static:
            self.buffer.set_transform_static(msg, AUTHORITY)
        else:
            self.buffer.set_transform(msg, AUTHORITY)

    def _lookup(self, target: str, source: str, stamp_ns: int):
        try:
            return self.buffer.lookup_transform(target, source, Time(nanoseconds=int(stamp_ns)))
        except tf2_ros.ExtrapolationException as error:
            raise ExtrapolationError(str(error), stamp_ns=stamp_ns) from None
        except tf2_ros.TransformException as error:  # Lookup, Connectivity, InvalidArgument
            raise MissingTransformError(str(error)) from None

    def lookup(self, target: str, source: str, stamp_ns: int) -> Transform:
        return transform_from_msg(self._lookup(target, source, stamp_ns)).transform

    def latest_stamp(self, target: str, source: str) -> int:
        return stamp_to_ns(self._lookup(target, source, 0).header.stamp)


class TfListener:
    """Subscriptions to /tf and /tf_static that feed a store, as tf2_ros.TransformListener does.

    Args:
        node: The node (its ``diagnostics`` counts ``bad_transform``).
        store: Where the transforms go (``add(msg, link, static)``).
        on_links: Called after each message with the child frames it updated.
    """

    def __init__(self, node: Any, store: Any, on_links: Callable[[List[str]], None]) -> None:
        self.node = node
        self.diagnostics = node.diagnostics
        self.get_logger = node.get_logger  # rejects_bad_input logs through it
        self.store = store
        self.on_links = on_links
        self.parents: Dict[str, str] = {}  # child -> its newest parent
        self.messages = 0
        self.subscriptions: List[Any] = [
            node.create_subscription(TFMessage, TF_TOPIC, self._on_tf, tf_qos()),
            node.create_subscription(TFMessage, TF_STATIC_TOPIC, self._on_tf_static, tf_static_qos())]

    def destroy(self) -> None:
        """Destroy the /tf and /tf_static subscriptions (safe twice)."""
        subscriptions, self.subscriptions = self.subscriptions, []
        for subscription in subscriptions:
            self.node.destroy_subscription(subscription)

    @rejects_bad_input("bad_transform")
    def _on_tf(self, msg: TFMessage) -> None:
        self.add(msg, static=False)

    @rejects_bad_input("bad_transform")
    def _on_tf_static(self, msg: TFMessage) -> None:
        self.add(msg, static=True)

    def add(self, msg: TFMessage, static: bool) -> None:
        """Put every good transform of a message into the store (a bad one is counted and left out)."""
        self.messages += 1
        children = []
        for transform in msg.transforms:
            try:
                link = transform_from_msg(transform)
                self.store.add(transform, link, static)
            except ValueError as error:  # ConversionError, a link of a frame to itself
                self.diagnostics.reject("bad_transform", str(error))
                continue
            self.parents[link.child.lstrip("/")] = link.parent.lstrip("/")
            children.append(link.child.lstrip("/"))
        if children:
            self.on_links(children)

    def chain(self, frame: str, root: str) -> Set[str]:
        """The children whose links lie between ``frame`` and ``root`` (or its tree's top), as published so far."""
        children: Set[str] = set()
        while frame in self.parents and frame != root and frame not in children:
            children.add(frame)
            frame = self.parents[frame]
        return children


@camera_pose_source("tf")
class TfCameraPoseSource:
    """The camera's optical frame in the fixed frame, from /tf and /tf_static (see the module docstring).

    Args:
        node: The node; it must have a ``diagnostics`` (StageDiagnostics). The source declares
            TfCameraPoseParams on it.
        capacity: How many poses (and waiting frames) are remembered.
        on_pose: Called with the pose of each expected frame once the tree has it, and with the pose at
            each newer stamp the whole chain covers.
        fixed_frame: The fixed frame (default: the ``camera_pose_fixed_frame`` parameter).
        camera_frame: The camera frame of a lookup that names none, and whose poses are handed on as the
            tree advances (default: the ``camera_pose_camera_frame`` parameter).
        use_tf2: Put the transforms in a tf2_ros.Buffer (default: where tf2_ros is installed).
    """

    def __init__(self, node, capacity: int, on_pose: Optional[PoseCallback] = None, fixed_frame: str = "",
                 camera_frame: str = "", use_tf2: Optional[bool] = None) -> None:
        params = tf_params(node)
        self.fixed_frame = (fixed_frame or params.camera_pose_fixed_frame).lstrip("/")
        self.camera_frame = (camera_frame or params.camera_pose_camera_frame).lstrip("/")
        self.diagnostics = node.diagnostics
        self.get_logger = node.get_logger  # rejects_bad_input logs through it
        self.clock = node.get_clock()
        self.on_pose = on_pose
        self.capacity = max(1, int(capacity))
        cache_ns = int(params.camera_pose_tf_cache_s * 1e9)
        if use_tf2 is None:
            use_tf2 = tf2_available()
        if use_tf2 and not tf2_available():
            raise ValueError("use_tf2: tf2_ros is not installed here")
        self.store = _Tf2Store(cache_ns) if use_tf2 else _OwnStore(cache_ns)
        self.poses: OrderedDictType[Tuple[str, int], Optional[StampedCameraPose]] = OrderedDict()  # None: refused pose
        self.waiting: OrderedDictType[Tuple[str, int], int] = OrderedDict()  # (frame, stamp) -> since (node clock ns)
        self.handed: OrderedDictType[Tuple[str, int], None] = OrderedDict()  # given to on_pose already
        self.frames: Set[str] = {self.camera_frame} if self.camera_frame else set()
        self.announced: Dict[str, int] = {}  # frame -> newest stamp handed on as the tree advanced
        self.last_error: Optional[TransformError] = None
        self.logged: Dict[Tuple[str, str], int] = {}  # (error kind, camera frame) -> when last logged
        self.listener = TfListener(node, self.store, self._on_links)
        self.node = node
        self.timer: Any = node.create_timer(WAIT_CHECK_PERIOD_S, self._check_waiting)
        self.timer.cancel()  # runs only while a frame waits
        node.get_logger().info(f"camera pose from TF: {self.fixed_frame!r} -> the image's optical frame, "
                               f"through {self.store.kind}")

    def destroy(self) -> None:
        """Destroy the /tf and /tf_static subscriptions and the wait timer; the frames waiting get no pose
        (safe twice)."""
        self.listener.destroy()
        self.waiting.clear()
        if self.timer is not None:
            self.node.destroy_timer(self.timer)
            self.timer = None

    # ------------------------------------------------------------------ lookups

    def _frame(self, camera_frame: str) -> str:
        frame = (camera_frame or self.camera_frame).lstrip("/")
        self.frames.add(frame)
        return frame

    def lookup(self, stamp_ns: int, camera_frame: str = "") -> StampedCameraPose:
        """The checked pose of ``camera_frame`` (default: the source's camera frame) at this stamp.

        Raises:
            TransformError: MissingTransformError (frames not connected, unknown frame) or
                ExtrapolationError (the stamp outside a dynamic link's buffered time, by how much).
            ConversionError: the pose breaks the camera-pose contract (e.g. the camera below the floor).
        """
        frame = self._frame(camera_frame)
        if not frame:
            raise MissingTransformError("no camera frame: the image names none and camera_pose_camera_frame is empty")
        transform = self.store.lookup(self.fixed_frame, frame, int(stamp_ns))
        return checked_camera_pose(int(stamp_ns), self.fixed_frame, transform.rotation, transform.translation)

    def _pose(self, key: Tuple[str, int]) -> Tuple[Optional[StampedCameraPose], Optional[TransformError]]:
        """(pose or None, the lookup's error); a pose refused by the contract is counted once and remembered."""
        if key in self.poses:
            return self.poses[key], None
        try:
            pose: Optional[StampedCameraPose] = self.lookup(key[1], key[0])
        except TransformError as error:
            return None, error
        except ConversionError as error:
            self.diagnostics.reject("bad_camera_pose", f"camera pose from TF at {key[1]} ns: {error}")
            pose = None
        self.poses[key] = pose
        while len(self.poses) > self.capacity:
            self.poses.popitem(last=False)
        return pose, None

    def _note(self, error: TransformError, key: Tuple[str, int]) -> None:
        """Keep the error and log it: a warning at most every LOG_PERIOD_NS per kind and frame, at debug
        level an extrapolation into the future (the transforms of the stamp are still on the way)."""
        self.last_error = error
        text = f"no camera pose of {key[0]!r} in {self.fixed_frame!r} from TF at {key[1]} ns: {error}"
        if isinstance(error, ExtrapolationError) and error.by_ns > 0:
            self.get_logger().debug(text)
            return
        now = self.clock.now().nanoseconds
        kind = (type(error).__name__, key[0])
        if now - self.logged.get(kind, -LOG_PERIOD_NS) >= LOG_PERIOD_NS:
            self.logged[kind] = now
            self.get_logger().warning(text)

    def pose_at(self, stamp_ns: int, camera_frame: str = "") -> Optional[StampedCameraPose]:
        """The pose of ``camera_frame`` (the image's frame_id) at this stamp, or None (``last_error`` says why)."""
        key = (self._frame(camera_frame), int(stamp_ns))
        pose, error = self._pose(key)
        if error is not None:
            self._note(error, key)
        return pose

    # ------------------------------------------------------------------ handing poses on

    def expect(self, stamp_ns: int, camera_frame: str = "") -> None:
        """A frame of this stamp waits: its pose goes to on_pose once the tree has it (for up to 2 s)."""
        key = (self._frame(camera_frame), int(stamp_ns))
        if key in self.waiting or key in self.handed:
            return
        self.waiting[key] = self.clock.now().nanoseconds
        while len(self.waiting) > self.capacity:
            self.waiting.popitem(last=False)
        if self.timer is not None and self.timer.is_canceled():  # (None: destroyed)
            self.timer.reset()

    def _hand(self, key: Tuple[str, int], pose: StampedCameraPose) -> None:
        self.handed[key] = None
        while len(self.handed) > self.capacity:
            self.handed.popitem(last=False)
        self.waiting.pop(key, None)
        if self.on_pose is None:
            return
        try:
            self.on_pose(pose)
        except ValueError as error:  # the node refuses it (e.g. its floor check): as the topic source counts it
            self.diagnostics.reject("bad_camera_pose", str(error))

    @rejects_bad_input("camera_pose_wait")
    def _check_waiting(self) -> None:
        now = self.clock.now().nanoseconds
        for key, since in list(self.waiting.items()):
            pose, error = self._pose(key)
            if pose is not None:
                self._hand(key, pose)
                continue
            gone_by = isinstance(error, ExtrapolationError) and error.by_ns < 0  # older than the buffer: never
            if error is None or gone_by or now - since > EXPECT_LIFETIME_NS:
                del self.waiting[key]  # refused by the contract (counted), or it will not come
                if error is not None:
                    self._note(error, key)
        if not self.waiting and self.timer is not None:
            self.timer.cancel()

    def _on_links(self, children: List[str]) -> None:
        """New transforms: hand on the poses of waiting frames, and of the newest stamp of each camera's chain."""
        if self.waiting:
            self._check_waiting()
        if self.on_pose is None:
            return
        for frame in sorted(self.frames):
            if not self.listener.chain(frame, self.fixed_frame).intersection(children):
                continue  # this message moved nothing between the camera and the fixed frame
            try:
                stamp = self.store.latest_stamp(self.fixed_frame, frame)
            except TransformError:
                continue  # not connected (yet)
            if stamp == 0 or stamp <= self.announced.get(frame, -1):
                continue  # only static links, or nothing newer
            self.announced[frame] = stamp
            key = (frame, stamp)
            pose, _ = self._pose(key)
            if pose is not None and key not in self.handed:
                self._hand(key, pose)
