"""ground_node: depth + camera_info (minus the latest person mask) -> GroundPlane (RANSAC).

The camera's pose of the same stamp (T_fixed_cameraOptical in a floor-aligned fixed frame, from the
robot's localization / TF or the simulator, through the shared camera-pose source:
:mod:`leapnbv_common.camera_pose`, today the PoseStamped topic ``camera_pose``) checks RANSAC's
plane: one that disagrees with the pose's floor z = 0 beyond the tolerance is refused, and the
pose's floor is published instead, as when RANSAC finds none (``source = SOURCE_CAMERA_POSE``;
:func:`leapnbv_geometry.ground.fuse_floor`). A pose of the frame's stamp is waited for briefly (DDS
does not order topics); until a first pose has come, a RANSAC plane goes out at once. The first
frame of a scene (no recent person mask) leaves out its own person boxes (detections of the same
stamp, waited for briefly once detections flow).

Parameters: :class:`leapnbv_geometry.params.GroundParams`; all but the camera-pose source and
its switch change at runtime (``ros2 param set``).
"""
from __future__ import annotations

import collections
import dataclasses
import time
from typing import Dict, NamedTuple, Optional, Set, Tuple

import numpy as np
from diagnostic_msgs.msg import DiagnosticStatus, KeyValue
from rclpy.node import Node
from sensor_msgs.msg import CameraInfo, Image
from std_msgs.msg import Header

from leapnbv_common.camera_pose import StampedCameraPose, create_camera_pose_source
from leapnbv_common.contracts import DuplicateStampGuard, check_same_frame, check_same_size, refused
from leapnbv_common.conversions import (
    DEPTH_ENCODINGS,
    GroundPlaneArrays,
    arrays_to_ground_plane,
    camera_info_to_k,
    check_image,
    depth_to_metres,
    detections_to_boxes,
    image_size,
    image_to_numpy,
    stamp_to_ns,
)
from leapnbv_common.diagnostics import StageDiagnostics, rejects_bad_input
from leapnbv_common.node_params import NodeParams, run_node
from leapnbv_common.qos import camera_input_qos, stage_input_qos, stage_output_qos
from leapnbv_common.stamp_cache import CompanionWait
from leapnbv_common.topics import DETECTIONS, GROUND_PLANE, PERSON_MASK
from leapnbv_geometry.ground import (
    FLOOR_NONE,
    box_exclusion_mask,
    expected_up,
    fit_ground_plane,
    floor_plane_from_camera_pose,
    fuse_floor,
    ground_points_from_depth,
)
from leapnbv_geometry.params import GroundParams
from leapnbv_msgs.msg import GroundPlane, PersonDetections

POSE_CACHE = 30  # camera poses (and frames waiting for theirs) remembered by stamp: ~1 s at 30 Hz
FALLBACK_LOG_EVERY = 100  # log the camera-pose fallback on its first frame and every this many after


class FittedFrame(NamedTuple):
    """One depth frame's RANSAC result, as it waits to be published."""

    plane: GroundPlaneArrays
    header: Header
    compute_time_ms: float
    point_count: int  # the points RANSAC was fitted on
    ransac: object = None  # the GroundPlaneResult (fused with the pose's floor when it is published)


class GroundDiagnostics(StageDiagnostics):
    """StageDiagnostics plus which estimate the published planes were (``planes.ransac``,
    ``planes.camera_pose``, ``planes.none`` for invalid ones) and why (``floor.<decision>``: the
    FLOOR_* names of leapnbv_geometry.ground, e.g. ``floor.camera_pose_refused_ransac``): a floor
    taken from the camera pose is served, not rejected, so it is counted apart from the rejections
    (the status stays OK)."""

    def __init__(self, node) -> None:
        super().__init__(node)
        self.plane_sources: Dict[str, int] = collections.Counter()
        self.last_plane_source = ""
        self.last_floor_decision = ""

    def plane_out(self, source: str, decision: str = "") -> None:
        self.plane_sources[source] += 1
        self.last_plane_source = source
        if decision:
            self.plane_sources[f"floor.{decision}"] += 1
            self.last_floor_decision = decision

    def status(self) -> DiagnosticStatus:
        status = super().status()
        status.values.append(KeyValue(key="last_plane_source", value=self.last_plane_source))
        status.values.append(KeyValue(key="last_floor_decision", value=self.last_floor_decision))
        status.values.extend(KeyValue(key=k if k.startswith("floor.") else f"planes.{k}", value=str(v))
                             for k, v in sorted(self.plane_sources.items()))
        return status


class GroundNode(Node):
    def __init__(self) -> None:
        super().__init__("ground_node")
        self.params = NodeParams(self, GroundParams, self.on_params_change)
        p = self.params.value
        self.diagnostics = GroundDiagnostics(self)
        self.camera_info: Optional[CameraInfo] = None
        self.person_mask: Optional[Image] = None
        self.stamps = DuplicateStampGuard()  # one content per stamp and input (contracts)
        self.publisher = self.create_publisher(GroundPlane, GROUND_PLANE, stage_output_qos())
        self.create_subscription(CameraInfo, "depth/camera_info", self.on_camera_info, camera_input_qos(1))
        self.create_subscription(Image, PERSON_MASK, self.on_mask, stage_input_qos(1))
        self.create_subscription(Image, "depth", self.on_depth, camera_input_qos(5))
        # A frame with no recent mask (a scene's first) leaves out its own person boxes.
        self.detections: collections.OrderedDict[int, np.ndarray] = collections.OrderedDict()
        # None until known: the first frame waits for its detections (a graph without a detector pays that once)
        self.detections_flowing: Optional[bool] = None
        self.create_subscription(PersonDetections, DETECTIONS, self.on_detections, stage_input_qos(5))
        # The mask excluded from frame t is the previous frame's. Waiting briefly for it (when
        # masks are flowing) makes the fit independent of message timing, so replays repeat.
        self.previous_depth_stamp: Optional[int] = None
        self.masks_flowing = False
        self.pending: Optional[tuple] = None  # (depth message, arrival ns) waiting for its mask
        # Floors from the camera pose, by stamp; frames without a RANSAC floor wait here for theirs.
        self.pose_floors = CompanionWait(int(p.camera_pose_wait_s * 1e9), capacity=POSE_CACHE)
        self.fallback_count = 0
        self.camera_pose = None
        if p.use_camera_pose_fallback:
            self.camera_pose = create_camera_pose_source(p.camera_pose_source, self, POSE_CACHE, self.on_camera_pose)
        self.create_timer(0.02, self.expire_wait)

    def on_params_change(self, params: GroundParams, changed: Set[str]) -> None:
        """A new pose wait applies to the frames already waiting too; the fit reads its settings per frame."""
        self.pose_floors.wait_ns = int(params.camera_pose_wait_s * 1e9)

    @rejects_bad_input("bad_camera_info")
    def on_camera_info(self, msg: CameraInfo) -> None:
        camera_info_to_k(msg)
        self.camera_info = msg

    def on_camera_pose(self, pose: StampedCameraPose) -> None:
        """Keep the floor of this pose by stamp; a frame waiting for it is published now.

        Raises:
            GroundPlaneError: the camera is not above the floor (the source counts it as bad_camera_pose).
        """
        normal, offset = floor_plane_from_camera_pose(pose.rotation, pose.position)
        ready = self.pose_floors.add_companion(pose.stamp_ns, (pose.stamp_ns, normal, offset))
        if ready is not None:
            self.publish_plane(ready[0], ready[1])

    @rejects_bad_input("bad_person_mask")
    def on_mask(self, msg: Image) -> None:
        check_image(msg, ("mono8",), "person mask")
        if self.camera_info is not None and refused(self.diagnostics, "bad_person_mask", check_same_frame,
                                                    "person_mask", msg.header.frame_id, "depth camera_info",
                                                    self.camera_info.header.frame_id):
            return
        self.person_mask = msg
        self.masks_flowing = True
        waiting_for_mask = self.pending is not None and not self.pending[2]  # not a frame waiting for detections
        if waiting_for_mask and stamp_to_ns(msg.header.stamp) == self.previous_depth_stamp:
            depth, self.pending = self.pending[0], None
            self.fit(depth)

    @rejects_bad_input("bad_detections")
    def on_detections(self, msg: PersonDetections) -> None:
        stamp = stamp_to_ns(msg.header.stamp)
        self.detections[stamp] = detections_to_boxes(msg)
        while len(self.detections) > POSE_CACHE:
            self.detections.popitem(last=False)
        self.detections_flowing = True
        if self.pending is not None and self.pending[2] and stamp_to_ns(self.pending[0].header.stamp) == stamp:
            depth, self.pending = self.pending[0], None
            self.fit(depth)

    def needs_detections(self, msg: Image) -> bool:
        """A frame without a recent person mask waits for its own detections (unless the last wait found none:
        then not until detections come again). The first frame waits too, so whether a bag's first frame leaves
        its person out does not depend on which message arrived first."""
        p = self.params.value
        if not (p.exclude_detections and self.detections_flowing is not False and p.detections_wait_s > 0):
            return False
        if stamp_to_ns(msg.header.stamp) in self.detections:
            return False
        mask = self.person_mask
        return mask is None or abs(stamp_to_ns(msg.header.stamp) - stamp_to_ns(mask.header.stamp)) > \
            p.mask_max_age_s * 1e9

    @rejects_bad_input("bad_depth")
    def on_depth(self, msg: Image) -> None:
        self.diagnostics.frame_in()
        # The depth contract (a view, no conversion)
        if refused(self.diagnostics, "bad_depth", check_image, msg, DEPTH_ENCODINGS, "depth") or \
                refused(self.diagnostics, "bad_depth", self.stamps.check, "depth", msg):
            return
        if self.pending is not None:
            if stamp_to_ns(msg.header.stamp) == stamp_to_ns(self.pending[0].header.stamp):
                return  # the waiting frame sent once more: it keeps waiting
            depth, self.pending = self.pending[0], None  # a newer frame: the waiting one is served now
            self.fit(depth)
        mask_stamp = stamp_to_ns(self.person_mask.header.stamp) if self.person_mask is not None else None
        if (self.params.value.mask_wait_s > 0 and self.masks_flowing and self.previous_depth_stamp is not None
                and mask_stamp != self.previous_depth_stamp):
            self.pending = (msg, self.get_clock().now().nanoseconds, False)
            return
        if self.needs_detections(msg):
            self.pending = (msg, self.get_clock().now().nanoseconds, True)
            return
        self.fit(msg)

    def expire_wait(self) -> None:
        for plane, _ in self.pose_floors.expire(self.get_clock().now().nanoseconds):
            self.publish_plane(plane, None)  # no pose of its stamp came: the invalid plane, as before
        if self.pending is None:
            return
        p = self.params.value
        wait_s = p.detections_wait_s if self.pending[2] else p.mask_wait_s
        if self.get_clock().now().nanoseconds - self.pending[1] >= wait_s * 1e9:
            depth, for_detections, self.pending = self.pending[0], self.pending[2], None
            if for_detections:
                self.detections_flowing = False  # none for that frame: do not wait again until some come
            else:
                self.masks_flowing = False  # no mask for that frame: do not wait again until one comes
            self.fit(depth)

    def exclusion_mask(self, depth_msg: Image, shape) -> Optional[np.ndarray]:
        """The latest person mask, if recent and of the same size (the person is not floor)."""
        mask = self.person_mask
        if mask is None or (mask.height, mask.width) != shape:
            return self.detection_mask(depth_msg, shape)
        age = (depth_msg.header.stamp.sec - mask.header.stamp.sec) + \
              (depth_msg.header.stamp.nanosec - mask.header.stamp.nanosec) * 1e-9
        if abs(age) > self.params.value.mask_max_age_s:
            return self.detection_mask(depth_msg, shape)
        return image_to_numpy(mask) > 0

    def detection_mask(self, depth_msg: Image, shape) -> Optional[np.ndarray]:
        """The frame's own person boxes (no recent mask: the first frame of a scene), or None."""
        p = self.params.value
        boxes = self.detections.get(stamp_to_ns(depth_msg.header.stamp)) if p.exclude_detections else None
        if boxes is None or len(boxes) == 0:
            return None
        return box_exclusion_mask(shape, boxes, p.detection_grow_px, p.detection_top_share)

    @rejects_bad_input("bad_depth")
    def fit(self, msg: Image) -> None:
        started = time.perf_counter()
        self.previous_depth_stamp = stamp_to_ns(msg.header.stamp)
        if self.camera_info is None:
            raise ValueError("no depth camera_info received yet")
        p = self.params.value
        if refused(self.diagnostics, "bad_depth", check_same_size, "depth", image_size(msg), "depth camera_info",
                   image_size(self.camera_info)) or \
                refused(self.diagnostics, "bad_depth", check_same_frame, "depth", msg.header.frame_id,
                        "depth camera_info", self.camera_info.header.frame_id):
            return
        depth = depth_to_metres(msg)
        points = ground_points_from_depth(depth, camera_info_to_k(self.camera_info),
                                          exclude_mask=self.exclusion_mask(msg, depth.shape), stride=p.stride,
                                          min_depth=p.min_depth, max_depth=p.max_depth)
        result = fit_ground_plane(points, max_tilt_deg=p.max_tilt_deg, inlier_threshold=p.inlier_threshold,
                                  iterations=p.iterations, min_inliers=p.min_inliers,
                                  min_inlier_ratio=p.min_inlier_ratio, seed=p.seed, max_points=p.max_points,
                                  depth_noise_coeff=p.depth_noise_coeff, up=expected_up(p.camera_pitch_deg),
                                  camera_height_range=(p.min_camera_height, p.max_camera_height))
        plane = GroundPlaneArrays(normal=result.normal, offset=result.offset, valid=result.valid,
                                  source=GroundPlane.SOURCE_RANSAC, inlier_count=result.inlier_count,
                                  inlier_ratio=result.inlier_ratio)
        frame = FittedFrame(plane, msg.header, (time.perf_counter() - started) * 1e3, len(points), result)
        if not p.use_camera_pose_fallback or (result.valid and self.pose_floors.latest_companion is None):
            self.publish_plane(frame, None)  # no pose to check it against (none has come so far)
            return
        # The floor of this frame's camera pose checks RANSAC's, once it is here (or the wait ran out).
        stamp = stamp_to_ns(msg.header.stamp)
        ready = self.pose_floors.add_frame(stamp, frame, self.get_clock().now().nanoseconds)
        if ready is None:
            self.camera_pose.expect(stamp, msg.header.frame_id)
        else:
            self.publish_plane(ready[0], ready[1])

    def publish_plane(self, frame: FittedFrame, pose_floor: Optional[Tuple[int, np.ndarray, float]]) -> None:
        """Publish the frame's floor: RANSAC's, checked against the pose's floor when the pose has its stamp.

        Args:
            frame: the plane as RANSAC gave it, with its frame's header.
            pose_floor: (stamp ns, normal, offset) of a camera pose, or None.
        """
        p = self.params.value
        matching = pose_floor is not None and pose_floor[0] == stamp_to_ns(frame.header.stamp)
        floor = fuse_floor(frame.ransac, (pose_floor[1], pose_floor[2]) if matching else None,
                           max_angle_deg=p.pose_max_angle_deg, max_height_m=p.pose_max_height_m,
                           full_support_ratio=p.quality_full_support)
        plane = dataclasses.replace(frame.plane, quality=floor.quality)
        if floor.from_pose:
            plane = dataclasses.replace(plane, normal=floor.normal, offset=floor.offset, valid=True,
                                        source=GroundPlane.SOURCE_CAMERA_POSE)
            self.fallback_count += 1
            if (self.fallback_count - 1) % FALLBACK_LOG_EVERY == 0:
                self.get_logger().warning(
                    f"{floor.decision} ({plane.inlier_count} RANSAC inliers of {frame.point_count} points): "
                    f"published the floor of the camera pose (height {floor.offset:.3f} m); {self.fallback_count} "
                    "such frames so far")
        elif not plane.valid:
            detail = f"{plane.inlier_count} inliers of {frame.point_count} points"
            if p.use_camera_pose_fallback:
                detail += "; no camera pose of this stamp"
            self.diagnostics.reject("no_ground_plane", detail)
        if not plane.valid:
            self.diagnostics.plane_out("none", FLOOR_NONE)
        else:
            self.diagnostics.plane_out("camera_pose" if plane.source == GroundPlane.SOURCE_CAMERA_POSE else "ransac",
                                       floor.decision)
        self.publisher.publish(arrays_to_ground_plane(plane, frame.header, frame.compute_time_ms))
        self.diagnostics.frame_out(frame.header.stamp, frame.compute_time_ms)


def main(args=None) -> None:
    run_node(GroundNode, args)


if __name__ == "__main__":
    main()
