"""Where a node gets the camera's pose for a frame: one source shared by the nodes that need it.

The pose is the camera's optical frame in a fixed, floor-aligned frame (z up, floor z = 0: a
``map`` frame), looked up by the frame's stamp. Today it comes from a ``geometry_msgs/PoseStamped``
topic (relative name ``camera_pose``) stamped with each camera frame, as the simulator and a TF
relay publish it.

A source has two methods: ``pose_at(stamp_ns, camera_frame)`` answers for a frame now (None when it
cannot), and ``expect(stamp_ns, camera_frame)`` says that a frame is waiting for its pose, which the
source hands to its ``on_pose`` callback when it has it. Another source (a TF lookup of
``map -> camera optical frame``, which would poll its buffer for the expected stamps) is one more
class here with those two methods, and one more entry in :data:`CAMERA_POSE_SOURCES`.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Dict, Optional

import numpy as np
from geometry_msgs.msg import PoseStamped

from leapnbv_common.contracts import (
    QUATERNION_TOLERANCE,
    ContractError,
    DuplicateStampGuard,
    check_camera_pose,
    refused,
)
from leapnbv_common.conversions import ConversionError, pose_to_numpy, stamp_to_ns
from leapnbv_common.diagnostics import rejects_bad_input
from leapnbv_common.qos import stage_input_qos
from leapnbv_common.stamp_cache import StampCache
from leapnbv_common.topics import CAMERA_POSE

__all__ = ["QUATERNION_TOLERANCE", "StampedCameraPose", "camera_pose_from_msg", "TopicCameraPoseSource",
           "CAMERA_POSE_SOURCES", "create_camera_pose_source"]


@dataclass(frozen=True)
class StampedCameraPose:
    """The camera's optical frame in ``frame_id`` at ``stamp_ns``: p_fixed = rotation @ p_camera + position."""

    stamp_ns: int
    frame_id: str
    rotation: np.ndarray
    position: np.ndarray


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

    def __init__(self, node, capacity: int, on_pose: Optional[Callable[[StampedCameraPose], None]] = None,
                 topic: str = CAMERA_POSE) -> None:
        self.diagnostics = node.diagnostics
        self.get_logger = node.get_logger  # rejects_bad_input logs through it
        self.poses: StampCache = StampCache(max(1, int(capacity)))
        self.on_pose = on_pose
        self.stamps = DuplicateStampGuard()
        node.create_subscription(PoseStamped, topic, self._on_message, stage_input_qos(max(10, int(capacity))))

    @rejects_bad_input("bad_camera_pose")
    def _on_message(self, msg: PoseStamped) -> None:
        pose = camera_pose_from_msg(msg)
        if refused(self.diagnostics, "bad_camera_pose", self.stamps.check, "camera_pose", msg):
            return  # another pose with the stamp of one already here: the first one stays
        self.poses.put(pose.stamp_ns, pose)
        if self.on_pose is not None:
            self.on_pose(pose)

    def pose_at(self, stamp_ns: int, camera_frame: str = "") -> Optional[StampedCameraPose]:
        """The pose with exactly this stamp, if it arrived and is still remembered (the topic names the frame)."""
        return self.poses.get_exact(int(stamp_ns))

    def expect(self, stamp_ns: int, camera_frame: str = "") -> None:
        """A frame of this stamp waits for its pose: topic poses are handed to on_pose as they arrive anyway."""


# camera_pose_source parameter value -> class.
CAMERA_POSE_SOURCES: Dict[str, type] = {"topic": TopicCameraPoseSource}


def create_camera_pose_source(kind: str, node, capacity: int,
                              on_pose: Optional[Callable[[StampedCameraPose], None]] = None):
    """The camera-pose source named ``kind`` (a key of CAMERA_POSE_SOURCES).

    Raises:
        ValueError: an unknown kind.
    """
    if kind not in CAMERA_POSE_SOURCES:
        raise ValueError(f"unknown camera pose source {kind!r}; known: {sorted(CAMERA_POSE_SOURCES)}")
    return CAMERA_POSE_SOURCES[kind](node, capacity, on_pose)
