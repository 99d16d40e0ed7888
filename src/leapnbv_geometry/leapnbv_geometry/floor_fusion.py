"""ground_node's floor decision: RANSAC's plane checked against the camera pose's floor of its frame.

ROS-free: the camera poses' floors remembered by stamp (:class:`PoseFloors`), the fusion of a
frame's RANSAC result with the pose floor of exactly its stamp (:func:`fuse_with_pose_floor`,
around :func:`leapnbv_geometry.ground.fuse_floor`), and the tally of what the published planes
were (:class:`FloorTally`: ``planes.<source>`` and ``floor.<decision>`` on /diagnostics).
"""
from __future__ import annotations

import collections
from typing import Counter, List, Optional, Tuple

from leapnbv_common.array_types import FloatArray
from leapnbv_common.stamp_cache import StampCache
from leapnbv_geometry.ground import FloorEstimate, GroundPlaneResult, floor_plane_from_camera_pose, fuse_floor

__all__ = ["POSE_CACHE", "FALLBACK_LOG_EVERY", "PoseFloor", "PoseFloors", "fuse_with_pose_floor", "FloorTally"]

POSE_CACHE = 60  # camera poses (and frames waiting for theirs) remembered by stamp: ~2 s at 30 Hz
FALLBACK_LOG_EVERY = 100  # log the camera-pose fallback on its first frame and every this many after

#: (stamp ns, unit up normal (3,) in the camera frame, camera height above the floor m) of one camera pose.
PoseFloor = Tuple[int, FloatArray, float]


class PoseFloors:
    """The floors of the camera poses by stamp.

    ``seen`` once a first one came: until then a RANSAC plane goes out unchecked.

    Args:
        capacity: How many floors are remembered (the newest).
    """

    def __init__(self, capacity: int = POSE_CACHE) -> None:
        self.floors: StampCache[PoseFloor] = StampCache(capacity)
        self.seen = False

    def add(self, stamp_ns: int, rotation: FloatArray, position: FloatArray) -> None:
        """Keep the floor of a camera pose (camera -> floor-aligned fixed frame) under its stamp.

        Raises:
            GroundPlaneError: the camera is not above the floor, or the rotation is not one.
        """
        normal, offset = floor_plane_from_camera_pose(rotation, position)
        self.seen = True
        self.floors.put(stamp_ns, (stamp_ns, normal, offset))

    def at(self, stamp_ns: int) -> Optional[PoseFloor]:
        """The floor of the pose of exactly this stamp, or None."""
        return self.floors.get_exact(stamp_ns)


def fuse_with_pose_floor(ransac: GroundPlaneResult, stamp_ns: int, pose_floor: Optional[PoseFloor],
                         max_angle_deg: float, max_height_m: float,
                         full_support_ratio: float) -> Tuple[FloorEstimate, Optional[int]]:
    """A frame's floor: its RANSAC result checked against the pose floor of its own stamp.

    Args:
        ransac: The fit on the frame.
        stamp_ns: The frame's stamp; a pose floor of another stamp never checks it.
        pose_floor: The pose floor the frame was given, or None.
        max_angle_deg: Largest normal disagreement of an accepted RANSAC plane.
        max_height_m: Largest offset disagreement of an accepted RANSAC plane.
        full_support_ratio: Inlier ratio at which the quality's support figure saturates.

    Returns:
        (the FloorEstimate, the stamp of the pose it was checked against or None: an input of the plane).
    """
    if pose_floor is not None and pose_floor[0] != stamp_ns:
        pose_floor = None
    floor = fuse_floor(ransac, None if pose_floor is None else (pose_floor[1], pose_floor[2]),
                       max_angle_deg=max_angle_deg, max_height_m=max_height_m, full_support_ratio=full_support_ratio)
    return floor, None if pose_floor is None else pose_floor[0]


class FloorTally:
    """Which estimate the published planes were, and why.

    The sources are ``ransac``, ``camera_pose`` and ``none`` (an invalid plane); the decisions the FLOOR_*
    names of leapnbv_geometry.ground. A floor taken from the camera pose is served, not rejected, so it is
    counted apart from the rejections.
    """

    def __init__(self) -> None:
        self.counts: Counter[str] = collections.Counter()
        self.last_source = ""
        self.last_decision = ""
        self.fallbacks = 0  # planes taken from the camera pose

    def plane_out(self, source: str, decision: str = "") -> None:
        """Count one published plane of this source (and its decision, when there is one)."""
        self.counts[source] += 1
        self.last_source = source
        if decision:
            self.counts[f"floor.{decision}"] += 1
            self.last_decision = decision

    def fallback(self) -> bool:
        """Count a plane taken from the camera pose; True when it is one to log.

        The first is logged, then one in FALLBACK_LOG_EVERY.
        """
        self.fallbacks += 1
        return (self.fallbacks - 1) % FALLBACK_LOG_EVERY == 0

    def values(self) -> List[Tuple[str, str]]:
        """The /diagnostics key-value pairs: the last source and decision, then every count by name."""
        return [("last_plane_source", self.last_source), ("last_floor_decision", self.last_decision),
                *((k if k.startswith("floor.") else f"planes.{k}", str(v)) for k, v in sorted(self.counts.items()))]
