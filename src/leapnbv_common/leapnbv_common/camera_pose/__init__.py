"""Where a node gets the camera's pose for a frame: one source shared by the nodes that need it.

The pose is the camera's optical frame in a fixed, floor-aligned frame (z up, floor z = 0: a
``map`` frame), looked up by the frame's stamp. Every source is a :class:`CameraPoseSource`, made by
``create_camera_pose_source(kind, node, capacity, on_pose)`` with ``kind`` the node's
``camera_pose_source`` parameter, a name in :data:`CAMERA_POSE_SOURCES`:

* ``topic`` (:class:`TopicCameraPoseSource`): a ``geometry_msgs/PoseStamped`` topic (relative name
  ``camera_pose``) stamped with each camera frame, as the simulator and a TF relay publish it;
* ``tf`` (:class:`leapnbv_common.camera_pose.tf_source.TfCameraPoseSource`): the robot's TF tree
  (``/tf`` + ``/tf_static``), ``fixed frame -> the image's optical frame`` at the image's stamp,
  interpolated; through ``tf2_ros.Buffer`` where tf2_ros is installed, else the project's own
  buffer (:mod:`leapnbv_common.tf_buffer`).

A source has three methods: ``pose_at(stamp_ns, camera_frame)`` answers for a frame now (None when it
cannot), ``expect(stamp_ns, camera_frame)`` says that a frame is waiting for its pose, which the
source hands to its ``on_pose`` callback when it has it, and ``destroy()`` releases what the source
made on its node (subscriptions, timers: a node's cleanup calls it, so that the next configure's
source does not sit beside the old one). Every pose passes one contract
(:func:`check_camera_pose`: unit quaternion, finite, camera above the floor) whatever its source.
Another source is one more module that registers its class with :func:`camera_pose_source`
(e.g. ``camera_pose/<name>.py``, named in :data:`CAMERA_POSE_SOURCES`'s built-in modules).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable, Optional, Protocol

import numpy as np
from geometry_msgs.msg import PoseStamped

from leapnbv_common.contracts import (
    QUATERNION_TOLERANCE,
    ContractError,
    DuplicateStampGuard,
    check_camera_pose,
    refused,
)
from leapnbv_common.conversions import ConversionError, pose_to_numpy, quaternion_to_rotation, stamp_to_ns
from leapnbv_common.diagnostics import rejects_bad_input
from leapnbv_common.qos import stage_input_qos
from leapnbv_common.registry import Registry
from leapnbv_common.stamp_cache import StampCache
from leapnbv_common.topics import CAMERA_POSE

__all__ = ["QUATERNION_TOLERANCE", "StampedCameraPose", "CameraPoseSource", "PoseCallback", "camera_pose_from_msg",
           "checked_camera_pose", "TopicCameraPoseSource", "CAMERA_POSE_SOURCES", "camera_pose_source",
           "create_camera_pose_source"]


@dataclass(frozen=True)
class StampedCameraPose:
    """The camera's optical frame in ``frame_id`` at ``stamp_ns``: p_fixed = rotation @ p_camera + position."""

    stamp_ns: int
    frame_id: str
    rotation: np.ndarray
    position: np.ndarray


PoseCallback = Callable[[StampedCameraPose], None]


class CameraPoseSource(Protocol):
    """What every camera-pose source offers the nodes (made as ``Source(node, capacity, on_pose)``).

    The node given at construction has a ``diagnostics`` (StageDiagnostics): a pose that breaks the
    contract is counted there as ``bad_camera_pose``. ``on_pose`` (may be None) is called with each
    pose the source has for a frame that ``expect`` named, and may be called with others (the topic
    source hands on every pose that arrives, the TF source every pose at the newest stamp of the tree).
    """

    def pose_at(self, stamp_ns: int, camera_frame: str = "") -> Optional[StampedCameraPose]:
        """The pose of ``camera_frame`` (the image's header.frame_id) at this stamp, or None when there is none now."""

    def expect(self, stamp_ns: int, camera_frame: str = "") -> None:
        """A frame of this stamp waits for its pose: hand it to on_pose once the source has it."""

    def destroy(self) -> None:
        """Release the subscriptions and timers the source made on its node (safe twice)."""


def checked_camera_pose(stamp_ns: int, frame_id: str, xyzw, position) -> StampedCameraPose:
    """A StampedCameraPose from a quaternion and a position that pass the camera-pose contract.

    Raises:
        ConversionError: a quaternion that is not unit length (or NaN: it is refused, never
            normalized), a non-finite position, or a camera not above the floor of the
            floor-aligned fixed frame (z <= 0): contracts.check_camera_pose.
    """
    try:
        check_camera_pose(xyzw, position)
    except ContractError as error:
        raise ConversionError(str(error)) from None
    return StampedCameraPose(int(stamp_ns), str(frame_id), quaternion_to_rotation(np.asarray(xyzw, dtype=np.float64)),
                             np.asarray(position, dtype=np.float64).reshape(3).copy())


def camera_pose_from_msg(msg: PoseStamped) -> StampedCameraPose:
    """A checked StampedCameraPose from a PoseStamped (the contract every node applies to a camera pose).

    Raises:
        ConversionError: a quaternion that is not unit length (or NaN: it is refused, never
            normalized), a non-finite position, or a camera not above the floor of the
            floor-aligned fixed frame (z <= 0): contracts.check_camera_pose.
    """
    q = msg.pose.orientation
    p = msg.pose.position
    try:
        check_camera_pose([q.x, q.y, q.z, q.w], [p.x, p.y, p.z])
    except ContractError as error:
        raise ConversionError(str(error)) from None
    rotation, position = pose_to_numpy(msg.pose)
    return StampedCameraPose(stamp_to_ns(msg.header.stamp), str(msg.header.frame_id), rotation, position)


def _check_source_class(entry: object) -> None:
    missing = [name for name in ("pose_at", "expect", "destroy") if not callable(getattr(entry, name, None))]
    if not callable(entry) or missing:
        raise TypeError(f"a camera pose source is a class with pose_at, expect and destroy; {entry!r} lacks "
                        f"{', '.join(missing) or 'a constructor'}")


#: camera_pose_source parameter value -> the source's class, called as ``Source(node, capacity, on_pose)``.
CAMERA_POSE_SOURCES: Registry[Callable[..., Any]] = Registry(
    "camera pose source", modules={"tf": "leapnbv_common.camera_pose.tf_source"}, check=_check_source_class)


def camera_pose_source(name: str) -> Callable[[type], type]:
    """Class decorator: make a CameraPoseSource selectable as ``camera_pose_source: <name>``."""

    def register(cls: type) -> type:
        CAMERA_POSE_SOURCES.register(name, cls)
        return cls

    return register


@camera_pose_source("topic")
class TopicCameraPoseSource:
    """Camera poses from a PoseStamped topic, remembered by stamp (the newest ``capacity``).

    Args:
        node: The node; it must have a ``diagnostics`` (StageDiagnostics): a pose that breaks the
            contract (camera_pose_from_msg) is counted there as ``bad_camera_pose`` and dropped, a
            second, different pose of a stamp already here as ``duplicate_stamp``.
        capacity: How many poses are remembered.
        on_pose: Called with each accepted pose as it arrives (a node waiting for a frame's pose).
        topic: The relative topic name (remapped by the launch file / runner).
    """

    def __init__(self, node: Any, capacity: int, on_pose: Optional[PoseCallback] = None,
                 topic: str = CAMERA_POSE) -> None:
        self.node = node
        self.diagnostics = node.diagnostics
        self.get_logger = node.get_logger  # rejects_bad_input logs through it
        self.poses: StampCache = StampCache(max(1, int(capacity)))
        self.refusals: StampCache = StampCache(max(1, int(capacity)))  # stamp -> why its pose was refused
        self.on_pose = on_pose
        self.stamps = DuplicateStampGuard()
        self.subscription: Any = node.create_subscription(PoseStamped, topic, self._on_message,
                                                          stage_input_qos(max(10, int(capacity))))

    @rejects_bad_input("bad_camera_pose")
    def _on_message(self, msg: PoseStamped) -> None:
        try:
            pose = camera_pose_from_msg(msg)
        except ConversionError as error:  # counted by the decorator; remembered to say why a frame went without
            self.refusals.put(stamp_to_ns(msg.header.stamp), str(error))
            raise
        if refused(self.diagnostics, "bad_camera_pose", self.stamps.check, "camera_pose", msg):
            return  # another pose with the stamp of one already here: the first one stays
        self.poses.put(pose.stamp_ns, pose)
        if self.on_pose is not None:
            self.on_pose(pose)

    def pose_at(self, stamp_ns: int, camera_frame: str = "") -> Optional[StampedCameraPose]:
        """The pose with exactly this stamp, if it arrived and is still remembered (the topic names the frame)."""
        return self.poses.get_exact(int(stamp_ns))

    def refusal_at(self, stamp_ns: int) -> Optional[str]:
        """Why the pose of this stamp was refused (the contract it broke), or None when none was."""
        refusal: Optional[str] = self.refusals.get_exact(int(stamp_ns))
        return refusal

    def expect(self, stamp_ns: int, camera_frame: str = "") -> None:
        """A frame of this stamp waits for its pose: topic poses are handed to on_pose as they arrive anyway."""

    def destroy(self) -> None:
        """Destroy the subscription (safe twice; the node may have destroyed it already)."""
        if self.subscription is not None:
            self.node.destroy_subscription(self.subscription)
            self.subscription = None


def create_camera_pose_source(kind: str, node: Any, capacity: int,
                              on_pose: Optional[PoseCallback] = None) -> CameraPoseSource:
    """The camera-pose source named ``kind`` (a name of CAMERA_POSE_SOURCES).

    Raises:
        ValueError: an unknown kind (the message lists the known ones).
    """
    return CAMERA_POSE_SOURCES.get(kind)(node, capacity, on_pose)
