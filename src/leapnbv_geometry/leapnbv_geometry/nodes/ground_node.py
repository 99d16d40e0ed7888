"""ground_node: depth + camera_info (minus the previous frame's person mask) -> GroundPlane (RANSAC).

Which frames: with ``fit_detected_frames_only`` (the default) the depth frames of the camera frames
the detector published a person for (the frames the rest of the graph works on; the detections
subscription keeps the newest only, depth frames wait for them in a bounded cache), else every
depth frame (the newest only). A frame older than one already fitted is dropped; every drop is
counted on /diagnostics (``dropped.<reason>``). The plane carries the depth frame's header and
lists what it used (``inputs``): the depth frame, its camera_info, the detections, and the
previous frame's person mask (an exclusion hint of bounded age, ``mask_max_age_s``).

The camera's pose of the same stamp (T_fixed_cameraOptical in a floor-aligned fixed frame, from the
robot's localization / TF or the simulator, through the shared camera-pose source:
:mod:`leapnbv_common.camera_pose`, today the PoseStamped topic ``camera_pose``) checks RANSAC's
plane: one that disagrees with the pose's floor z = 0 beyond the tolerance is refused, and the
pose's floor is published instead, as when RANSAC finds none (``source = SOURCE_CAMERA_POSE``;
:func:`leapnbv_geometry.ground.fuse_floor`). A pose of the frame's stamp is waited for briefly (DDS
does not order topics); until a first pose has come, a RANSAC plane goes out at once. A frame with
no recent person mask (the first of a scene) leaves out its own person boxes (its detections).

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
from sensor_msgs.msg import CameraInfo, Image
from std_msgs.msg import Header

from leapnbv_common.camera_pose import StampedCameraPose, create_camera_pose_source
from leapnbv_common.contracts import ContractError, check_same_frame, check_same_size
from leapnbv_common.conversions import (
    DEPTH_ENCODINGS,
    GroundPlaneArrays,
    SerializedImage,
    arrays_to_ground_plane,
    camera_info_to_k,
    check_image,
    depth_to_metres,
    detections_to_boxes,
    image_size,
    image_to_numpy,
    stamp_to_ns,
)
from leapnbv_common.diagnostics import StageDiagnostics
from leapnbv_common.managed_node import ManagedNode
from leapnbv_common.node_params import run_node
from leapnbv_common.process_tuning import tune_node_process
from leapnbv_common.pulled_input import PulledInput
from leapnbv_common.qos import camera_input_qos, stage_input_qos, stage_output_qos
from leapnbv_common.stage import DROP, NEAREST, REJECT, SAME_OR_LATEST, Companion, Frame, KeyInput, Received, Stage
from leapnbv_common.stage_inputs import checked_camera_info, checked_serialized_image
from leapnbv_common.stamp_cache import StampCache
from leapnbv_common.topics import DETECTIONS, GROUND_PLANE, PERSON_MASK
from leapnbv_geometry.ground import (
    FLOOR_NONE,
    GroundPlaneResult,
    box_exclusion_mask,
    expected_up,
    fit_ground_plane,
    floor_plane_from_camera_pose,
    fuse_floor,
    ground_points_from_depth,
)
from leapnbv_geometry.params import GroundParams
from leapnbv_msgs.msg import GroundPlane, InputStamp, PersonDetections

POSE_CACHE = 60  # camera poses (and frames waiting for theirs) remembered by stamp: ~2 s at 30 Hz
FALLBACK_LOG_EVERY = 100  # log the camera-pose fallback on its first frame and every this many after


class FittedFrame(NamedTuple):
    """One depth frame's RANSAC result, as it waits to be published."""

    plane: GroundPlaneArrays
    header: Header
    compute_time_ms: float
    point_count: int  # the points RANSAC was fitted on
    inputs: list  # (name, stamp ns[, relation]) of what the fit used (GroundPlane.inputs)
    ransac: GroundPlaneResult  # RANSAC's result (fused with the pose's floor when it is published)


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


class GroundNode(ManagedNode):
    diagnostics: GroundDiagnostics
    def __init__(self) -> None:
        super().__init__("ground_node", GroundParams, diagnostics_class=GroundDiagnostics)

    def configure_stage(self) -> None:
        p = self.params.value
        self.publisher = self.create_lifecycle_publisher(GroundPlane, GROUND_PLANE, stage_output_qos())
        # The mask excluded from frame t is the previous fitted frame's. Waiting briefly for it (while masks
        # flow) makes the fit independent of message timing, so replays repeat.
        self.previous_fit_stamp: Optional[int] = None
        self.mask_gave_up_on: Optional[int] = -1  # stamp of the newest mask when a wait for one ran out
        # Floors of the camera poses by stamp; until a first pose has come, a RANSAC plane goes out unchecked.
        self.pose_floors: StampCache = StampCache(POSE_CACHE)
        self.poses_seen = False
        self.fallback_count = 0
        depth = Companion("depth", Image, "depth",
                          lambda cdr: checked_serialized_image(cdr, DEPTH_ENCODINGS, "depth"),
                          camera_input_qos(p.depth_cache_size), match=NEAREST,
                          slop_s=lambda f: self.params.value.slop_s,
                          wait_s=lambda f: self.params.value.depth_wait_s, when_missing=DROP,
                          missing_reason="no_matching_depth", capacity=p.depth_cache_size, raw=True, pulled=True,
                          consume=True, skip_older=True, validate=self.depth_agrees_with_its_camera_info)
        info = Companion("depth/camera_info", CameraInfo, "depth/camera_info", checked_camera_info,
                         camera_input_qos(p.depth_cache_size), match=SAME_OR_LATEST,
                         stamp_from=None if not p.fit_detected_frames_only else "depth", when_missing=REJECT,
                         missing_reason="bad_depth", missing_detail=lambda f: "no depth camera_info received yet",
                         capacity=p.depth_cache_size, pulled=True, bad_reason="bad_camera_info")
        mask = Companion("person_mask", Image, PERSON_MASK, self.checked_mask, stage_input_qos(1),
                         lookup=self.previous_frames_mask, needed=self.needs_mask,
                         wait_s=lambda f: self.params.value.mask_wait_s, on_missing=self.stop_waiting_for_masks,
                         capacity=2, bad_reason="bad_person_mask")
        pose = Companion("camera_pose", lookup=self.pose_floor, needed=lambda f: self.poses_seen,
                         wait_s=lambda f: self.params.value.camera_pose_wait_s,
                         expect=self.expect_pose)
        if p.fit_detected_frames_only:
            # The detections start the work (the newest only); depth frames wait for them in the reader / cache.
            key = KeyInput("detections", PersonDetections, DETECTIONS, detections_to_boxes, stage_input_qos(1),
                           frame_name="frame", accept=lambda d: None if len(d.value) else "no_person")
            companions = [depth, info, mask]
        else:
            # Every depth frame (the newest only); detections only for the first frame's exclusion.
            key = KeyInput("depth", Image, "depth", lambda cdr: checked_serialized_image(cdr, DEPTH_ENCODINGS, "depth"),
                           camera_input_qos(1), raw=True, frame_name="frame")
            companions = [info, Companion("detections", PersonDetections, DETECTIONS, detections_to_boxes,
                                          stage_input_qos(5), capacity=POSE_CACHE), mask]
        if p.use_camera_pose_fallback:
            companions.append(pose)
        self.stage = Stage(self, key, companions, self.fit, capacity=p.depth_cache_size, frame_error_reason="bad_depth")
        self.camera_pose = None
        if p.use_camera_pose_fallback:
            self.camera_pose = create_camera_pose_source(p.camera_pose_source, self, POSE_CACHE, self.on_camera_pose)
            self.stage.add_pulled(PulledInput.adopt(self, self.camera_pose))  # None for a source without one

    def activate_stage(self) -> None:
        self.stage.start()
        if self.params.value.fit_detected_frames_only:
            self.diagnostics.await_publishers(DETECTIONS)  # ready once the detector is connected

    def deactivate_stage(self) -> None:
        self.stage.stop()

    def on_params_change(self, params: GroundParams, changed: Set[str]) -> None:
        """Everything is read per frame (the waits too, for the frames already waiting)."""

    def expect_pose(self, frame: Frame) -> None:
        if self.camera_pose is not None:
            self.camera_pose.expect(frame.stamp_ns, self.depth_of(frame).header.frame_id)

    def depth_of(self, frame: Frame) -> SerializedImage:
        return frame.key.value if frame.key_name == "depth" else frame["depth"]

    def depth_agrees_with_its_camera_info(self, depth: Received) -> None:
        """Checked on arrival (not only when fitted): a depth frame that disagrees with its own calibration is
        refused whether or not the graph works on its frame.

        Raises:
            ContractError: another size or optical frame than its camera_info's.
        """
        info = self.stage.caches["depth/camera_info"].get_exact(depth.stamp_ns)
        if info is not None:
            self.check_depth_against(depth.value, info.value)

    @staticmethod
    def check_depth_against(depth: SerializedImage, info: CameraInfo) -> None:
        check_same_size("depth", image_size(depth), "depth camera_info", image_size(info))
        check_same_frame("depth", depth.header.frame_id, "depth camera_info", info.header.frame_id)

    def checked_mask(self, msg: Image) -> Image:
        check_image(msg, ("mono8",), "person mask")
        info = self.stage.latest.get("depth/camera_info")
        if info is not None:
            check_same_frame("person_mask", msg.header.frame_id, "depth camera_info", info.frame_id)
        return msg

    def needs_mask(self, frame: Frame) -> bool:
        """Wait for the previous fitted frame's mask while masks flow (one came since the last wait ran out)."""
        latest = self.stage.latest.get("person_mask")
        flowing = latest is not None and latest.stamp_ns != self.mask_gave_up_on
        return self.params.value.mask_wait_s > 0 and flowing and self.previous_fit_stamp is not None

    def previous_frames_mask(self, frame: Frame) -> Optional[Received]:
        """The latest person mask when it is the previous fitted frame's (within the slop), else None."""
        mask = self.stage.latest.get("person_mask")
        if mask is None or self.previous_fit_stamp is None or \
                abs(mask.stamp_ns - self.previous_fit_stamp) > self.params.value.slop_s * 1e9:
            return None
        return mask

    def stop_waiting_for_masks(self, frame: Frame) -> None:
        """No mask for the previous frame came in time: do not wait again until a newer one comes."""
        latest = self.stage.latest.get("person_mask")
        self.mask_gave_up_on = None if latest is None else latest.stamp_ns

    def on_camera_pose(self, pose: StampedCameraPose) -> None:
        """Keep the floor of this pose by stamp; a frame waiting for it goes on now.

        Raises:
            GroundPlaneError: the camera is not above the floor (the source counts it as bad_camera_pose).
        """
        normal, offset = floor_plane_from_camera_pose(pose.rotation, pose.position)
        self.poses_seen = True
        self.pose_floors.put(pose.stamp_ns, (pose.stamp_ns, normal, offset))
        self.stage.companion_arrived("camera_pose")

    def pose_floor(self, frame: Frame) -> Optional[Received]:
        floor = self.pose_floors.get_exact(frame.stamp_ns)
        return None if floor is None else Received(frame.stamp_ns, frame.header, floor)

    def exclusion_mask(self, depth_msg: SerializedImage, shape, frame: Frame) -> Tuple[Optional[np.ndarray],
                                                                                       Optional[tuple]]:
        """The latest person mask, if recent and of the same size (the person is not floor), and its input
        entry; without one (the first frame of a scene), the frame's own person boxes."""
        latest = self.stage.latest.get("person_mask")
        if latest is None or (latest.value.height, latest.value.width) != shape:
            return self.detection_mask(shape, frame), None
        mask = latest.value
        age_ns = stamp_to_ns(depth_msg.header.stamp) - latest.stamp_ns
        if abs(age_ns) > self.params.value.mask_max_age_s * 1e9:
            return self.detection_mask(shape, frame), None
        relation = InputStamp.SAME_FRAME if abs(age_ns) <= self.params.value.slop_s * 1e9 else InputStamp.EXCLUSION_HINT
        return image_to_numpy(mask) > 0, ("person_mask", latest.stamp_ns, relation)

    def detection_mask(self, shape, frame: Frame) -> Optional[np.ndarray]:
        """The frame's own person boxes (its detections: already among the plane's inputs), or None."""
        p = self.params.value
        boxes = frame["detections"] if p.exclude_detections else None
        if boxes is None or len(boxes) == 0:
            return None
        return box_exclusion_mask(shape, boxes, p.detection_grow_px, p.detection_top_share)

    def fit(self, frame: Frame) -> None:
        started = time.perf_counter()
        msg = self.depth_of(frame)
        stamp = stamp_to_ns(msg.header.stamp)
        self.previous_fit_stamp = stamp
        camera_info = frame["depth/camera_info"]  # always there: the frame is refused without one
        info_input = next(entry for entry in frame.inputs if entry[0] == "depth/camera_info")
        p = self.params.value
        # A camera_info of another stamp (calibration) is checked here; the frame's own was checked on arrival.
        if info_input[2] == InputStamp.STATIC or not p.fit_detected_frames_only:
            try:
                self.check_depth_against(msg, camera_info)
            except ContractError as error:
                self.diagnostics.reject(error.reason or "bad_depth", error.detail)
                return
        depth = depth_to_metres(msg)
        exclude, mask_input = self.exclusion_mask(msg, depth.shape, frame)
        inputs = [("depth", stamp), info_input]
        if p.fit_detected_frames_only:
            inputs.append(("detections", frame.stamp_ns))
        if mask_input is not None:
            inputs.append(mask_input)
        points = ground_points_from_depth(depth, camera_info_to_k(camera_info), exclude_mask=exclude,
                                          stride=p.stride, min_depth=p.min_depth, max_depth=p.max_depth)
        result = fit_ground_plane(points, max_tilt_deg=p.max_tilt_deg, inlier_threshold=p.inlier_threshold,
                                  iterations=p.iterations, min_inliers=p.min_inliers,
                                  min_inlier_ratio=p.min_inlier_ratio, seed=p.seed, max_points=p.max_points,
                                  depth_noise_coeff=p.depth_noise_coeff, up=expected_up(p.camera_pitch_deg),
                                  camera_height_range=(p.min_camera_height, p.max_camera_height))
        plane = GroundPlaneArrays(normal=result.normal, offset=result.offset, valid=result.valid,
                                  source=GroundPlane.SOURCE_RANSAC, inlier_count=result.inlier_count,
                                  inlier_ratio=result.inlier_ratio)
        # The plane carries the frame's stamp (the detections', i.e. the colour image's: what raster and nbv
        # pair it by) and the depth frame's optical frame; its inputs name the depth frame's own stamp.
        header = msg.header
        header.stamp = frame.header.stamp
        fitted = FittedFrame(plane, header, (time.perf_counter() - started) * 1e3, len(points), inputs, result)
        pose = frame.received("camera_pose")
        self.publish_plane(fitted, None if pose is None else pose.value)

    def publish_plane(self, frame: FittedFrame, pose_floor: Optional[Tuple[int, np.ndarray, float]]) -> None:
        """Publish the frame's floor: RANSAC's, checked against the pose's floor when the pose has its stamp.

        Args:
            frame: the plane as RANSAC gave it, with its frame's header.
            pose_floor: (stamp ns, normal, offset) of a camera pose, or None.
        """
        p = self.params.value
        inputs = list(frame.inputs)
        if pose_floor is not None and pose_floor[0] != stamp_to_ns(frame.header.stamp):
            pose_floor = None  # another frame's pose never checks this one
        if pose_floor is not None:
            inputs.append(("camera_pose", pose_floor[0]))
        floor = fuse_floor(frame.ransac, (pose_floor[1], pose_floor[2]) if pose_floor is not None else None,
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
        self.publisher.publish(arrays_to_ground_plane(plane, frame.header, frame.compute_time_ms, inputs=inputs))
        self.diagnostics.frame_out(frame.header.stamp, frame.compute_time_ms)


def main(args=None) -> None:
    tune_node_process()  # one BLAS thread, image buffers reused (leapnbv_common.process_tuning)
    run_node(GroundNode, args)


if __name__ == "__main__":
    main()
