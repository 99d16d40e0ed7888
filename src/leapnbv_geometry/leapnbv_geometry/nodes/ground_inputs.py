"""ground_node's inputs beside the depth frame (person mask, camera poses' floors) and its diagnostics.

:class:`PreviousFrameMask` is the ``person_mask`` companion: raster_node's mask of the previous
fitted frame, waited for briefly while masks flow (so that a fit does not depend on message timing
and replays repeat), and the pixels a fit leaves out (the mask when recent and of the same size, else
the frame's own person boxes). :class:`CameraPoseFloors` is the ``camera_pose`` companion: the floor of
each camera pose of the shared source (:mod:`leapnbv_common.camera_pose`), by stamp, that checks RANSAC's
plane (:mod:`leapnbv_geometry.floor_fusion`). :class:`GroundDiagnostics` adds the published planes' tally
(:class:`leapnbv_geometry.floor_fusion.FloorTally`) to the stage's /diagnostics.
"""
from __future__ import annotations

from typing import Any, Optional, Tuple

import numpy as np
from diagnostic_msgs.msg import DiagnosticStatus, KeyValue
from sensor_msgs.msg import CameraInfo, Image

from leapnbv_common.array_types import BoolArray
from leapnbv_common.camera_pose import CameraPoseSource, StampedCameraPose, create_camera_pose_source
from leapnbv_common.contracts import check_same_frame, check_same_size
from leapnbv_common.conversions import SerializedImage, check_image, image_size, image_to_numpy, stamp_to_ns
from leapnbv_common.diagnostics import StageDiagnostics
from leapnbv_common.pulled_input import PulledInput
from leapnbv_common.qos import stage_input_qos
from leapnbv_common.stage import Companion, Frame, Received
from leapnbv_common.topics import PERSON_MASK
from leapnbv_geometry.floor_fusion import POSE_CACHE, FloorTally, PoseFloors
from leapnbv_geometry.ground import box_exclusion_mask
from leapnbv_msgs.msg import InputStamp

__all__ = ["GroundDiagnostics", "PreviousFrameMask", "CameraPoseFloors", "depth_of", "check_depth_against"]


def depth_of(frame: Frame) -> SerializedImage:
    """The depth frame of a ground_node frame (its key, or its depth companion)."""
    depth: SerializedImage = frame.key.value if frame.key_name == "depth" else frame["depth"]
    return depth


def check_depth_against(depth: SerializedImage, info: CameraInfo) -> None:
    """Check that a depth frame has its camera_info's size and optical frame.

    Raises:
        ContractError: another size or optical frame than the camera_info's.
    """
    check_same_size("depth", image_size(depth), "depth camera_info", image_size(info))
    check_same_frame("depth", depth.header.frame_id, "depth camera_info", info.header.frame_id)


class GroundDiagnostics(StageDiagnostics):
    """StageDiagnostics plus the published planes' sources and floor decisions.

    The keys: ``planes.<source>``, ``floor.<decision>``, ``last_plane_source``, ``last_floor_decision``;
    the status stays OK for a floor taken from the camera pose.
    """

    def __init__(self, node: Any) -> None:
        super().__init__(node)
        self.planes = FloorTally()

    def status(self) -> DiagnosticStatus:
        status = super().status()
        status.values.extend(KeyValue(key=key, value=value) for key, value in self.planes.values())
        return status


class PreviousFrameMask:
    """The previous fitted frame's person mask, as ground_node's ``person_mask`` companion.

    Args:
        node: The ground node (its ``stage`` and ``params.value``: GroundParams).
    """

    def __init__(self, node: Any) -> None:
        self.node = node
        self.previous_fit_stamp: Optional[int] = None  # the mask excluded from frame t is the previous fit's
        self.gave_up_on: Optional[int] = -1  # stamp of the newest mask when a wait for one ran out

    def companion(self) -> Companion:
        return Companion("person_mask", Image, PERSON_MASK, self.checked, stage_input_qos(1), lookup=self.lookup,
                         needed=self.needed, wait_s=lambda f: self.node.params.value.mask_wait_s,
                         on_missing=self.stop_waiting, capacity=2, bad_reason="bad_person_mask")

    def _latest(self) -> Optional[Received]:
        latest: Optional[Received] = self.node.stage.latest.get("person_mask")
        return latest

    def checked(self, msg: Image) -> Image:
        """A mono8 mask in the depth camera's optical frame (once a depth camera_info came).

        Raises:
            ConversionError, ContractError: another encoding, or another frame than the depth camera's.
        """
        check_image(msg, ("mono8",), "person mask")
        info = self.node.stage.latest.get("depth/camera_info")
        if info is not None:
            check_same_frame("person_mask", msg.header.frame_id, "depth camera_info", info.frame_id)
        return msg

    def needed(self, frame: Frame) -> bool:
        """Wait for the previous fitted frame's mask while masks flow (one came since the last wait ran out)."""
        latest = self._latest()
        flowing = latest is not None and latest.stamp_ns != self.gave_up_on
        return bool(self.node.params.value.mask_wait_s > 0 and flowing and self.previous_fit_stamp is not None)

    def lookup(self, frame: Frame) -> Optional[Received]:
        """The latest person mask when it is the previous fitted frame's (within the slop), else None."""
        mask = self._latest()
        if mask is None or self.previous_fit_stamp is None or \
                abs(mask.stamp_ns - self.previous_fit_stamp) > self.node.params.value.slop_s * 1e9:
            return None
        return mask

    def stop_waiting(self, frame: Frame) -> None:
        """No mask for the previous frame came in time: do not wait again until a newer one comes."""
        latest = self._latest()
        self.gave_up_on = None if latest is None else latest.stamp_ns

    def exclusion(self, depth_msg: SerializedImage, shape: Tuple[int, int],
                  frame: Frame) -> Tuple[Optional[BoolArray], Optional[tuple]]:
        """The pixels a fit leaves out (the person is not floor), and the input entry of the mask.

        The latest person mask, if recent and of the same size; without one (the first frame of a scene),
        the frame's own person boxes (no entry: the detections are among the plane's inputs already).
        """
        latest = self._latest()
        if latest is None or (latest.value.height, latest.value.width) != shape:
            return self.detection_mask(shape, frame), None
        p = self.node.params.value
        age_ns = stamp_to_ns(depth_msg.header.stamp) - latest.stamp_ns
        if abs(age_ns) > p.mask_max_age_s * 1e9:
            return self.detection_mask(shape, frame), None
        relation = InputStamp.SAME_FRAME if abs(age_ns) <= p.slop_s * 1e9 else InputStamp.EXCLUSION_HINT
        return np.asarray(image_to_numpy(latest.value) > 0), ("person_mask", latest.stamp_ns, relation)

    def detection_mask(self, shape: Tuple[int, int], frame: Frame) -> Optional[BoolArray]:
        """The frame's own person boxes (its detections: already among the plane's inputs), or None."""
        p = self.node.params.value
        boxes = frame["detections"] if p.exclude_detections else None
        if boxes is None or len(boxes) == 0:
            return None
        return box_exclusion_mask(shape, boxes, p.detection_grow_px, p.detection_top_share)


class CameraPoseFloors:
    """The floors of the camera poses by stamp, as ground_node's ``camera_pose`` companion.

    Args:
        node: The ground node (its ``stage`` once made, ``params.value``: GroundParams).
    """

    def __init__(self, node: Any) -> None:
        self.node = node
        self.floors = PoseFloors(POSE_CACHE)  # until a first pose has come, a RANSAC plane goes out unchecked
        self.source: Optional[CameraPoseSource] = None

    def companion(self) -> Companion:
        return Companion("camera_pose", lookup=self.lookup, needed=lambda f: self.floors.seen,
                         wait_s=lambda f: self.node.params.value.camera_pose_wait_s, expect=self.expect)

    def attach(self) -> None:
        """Make the camera-pose source, after the stage (its poses wake frames waiting in it).

        It is released with the configure's entities on cleanup (ManagedNode.owned).
        """
        self.source = self.node.owned(create_camera_pose_source(self.node.params.value.camera_pose_source,
                                                                self.node, POSE_CACHE, self.on_pose))
        self.node.stage.add_pulled(PulledInput.adopt(self.node, self.source))  # None for a source without one

    def on_pose(self, pose: StampedCameraPose) -> None:
        """Keep the floor of this pose by stamp; a frame waiting for it goes on now.

        Raises:
            GroundPlaneError: the camera is not above the floor (the source counts it as bad_camera_pose).
        """
        self.floors.add(pose.stamp_ns, pose.rotation, pose.position)
        self.node.stage.companion_arrived("camera_pose")

    def lookup(self, frame: Frame) -> Optional[Received]:
        floor = self.floors.at(frame.stamp_ns)
        return None if floor is None else Received(frame.stamp_ns, frame.header, floor)

    def expect(self, frame: Frame) -> None:
        if self.source is not None:
            self.source.expect(frame.stamp_ns, depth_of(frame).header.frame_id)
