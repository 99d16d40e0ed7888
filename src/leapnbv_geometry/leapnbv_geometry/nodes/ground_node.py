"""ground_node: depth + camera_info (minus the previous frame's person mask) -> GroundPlane (RANSAC).

Which frames: with ``fit_detected_frames_only`` (the default) the depth frames of the camera frames
the detector published a person for (the frames the rest of the graph works on; the detections
subscription keeps the newest only, depth frames wait for them in a bounded cache), else every
depth frame (the newest only). A frame older than one already fitted is dropped; every drop is
counted on /diagnostics (``dropped.<reason>``). The plane carries the depth frame's header and
lists what it used (``inputs``): the depth frame, its camera_info, the detections, and the
previous frame's person mask (an exclusion hint of bounded age, ``mask_max_age_s``).

The camera's pose of the frame's stamp (T_fixed_cameraOptical in a floor-aligned fixed frame, from
:mod:`leapnbv_common.camera_pose`) checks RANSAC's plane: one that disagrees with the pose's floor
z = 0 beyond the tolerance is refused and the pose's floor published instead, as when RANSAC finds
none (``source = SOURCE_CAMERA_POSE``; :mod:`leapnbv_geometry.floor_fusion`). The pose is waited for
briefly (DDS does not order topics); until a first pose has come, a RANSAC plane goes out at once. A
frame with no recent person mask (the first of a scene) leaves out its own person boxes.

Parameters: :class:`leapnbv_geometry.params.GroundParams`; all but the camera-pose source and
its switch change at runtime (``ros2 param set``).
"""
from __future__ import annotations

import dataclasses
import time
from typing import List, Set

from sensor_msgs.msg import CameraInfo, Image
from std_msgs.msg import Header

from leapnbv_common.contracts import ContractError
from leapnbv_common.conversions import (
    GroundPlaneArrays,
    arrays_to_ground_plane,
    camera_info_to_k,
    depth_to_metres,
    detections_to_boxes,
    stamp_to_ns,
)
from leapnbv_common.managed_node import ManagedNode, managed_node_main
from leapnbv_common.qos import camera_input_qos, stage_input_qos, stage_output_qos
from leapnbv_common.stage import DROP, NEAREST, REJECT, SAME_OR_LATEST, Companion, Frame, KeyInput, Received, Stage
from leapnbv_common.stage_inputs import checked_camera_info, checked_depth_image
from leapnbv_common.topics import DETECTIONS, GROUND_PLANE
from leapnbv_geometry.floor_fusion import POSE_CACHE, fuse_with_pose_floor
from leapnbv_geometry.ground import (
    FLOOR_NONE,
    GroundPlaneResult,
    expected_up,
    fit_ground_plane,
    ground_points_from_depth,
)
from leapnbv_geometry.nodes.ground_inputs import (
    CameraPoseFloors,
    GroundDiagnostics,
    PreviousFrameMask,
    check_depth_against,
    depth_of,
)
from leapnbv_geometry.params import GroundParams
from leapnbv_msgs.msg import GroundPlane, InputStamp, PersonDetections


class GroundNode(ManagedNode):
    diagnostics: GroundDiagnostics

    def __init__(self) -> None:
        super().__init__("ground_node", GroundParams, diagnostics_class=GroundDiagnostics)

    def configure_stage(self) -> None:
        p = self.params.value
        self.publisher = self.create_lifecycle_publisher(GroundPlane, GROUND_PLANE, stage_output_qos())
        self.mask = PreviousFrameMask(self)
        self.pose_floors = CameraPoseFloors(self) if p.use_camera_pose_fallback else None
        depth = Companion("depth", Image, "depth", checked_depth_image, camera_input_qos(p.depth_cache_size),
                          match=NEAREST, slop_s=lambda f: self.params.value.slop_s,
                          wait_s=lambda f: self.params.value.depth_wait_s, when_missing=DROP,
                          missing_reason="no_matching_depth", capacity=p.depth_cache_size, raw=True, pulled=True,
                          consume=True, skip_older=True, validate=self.depth_agrees_with_its_camera_info)
        info = Companion("depth/camera_info", CameraInfo, "depth/camera_info", checked_camera_info,
                         camera_input_qos(p.depth_cache_size), match=SAME_OR_LATEST,
                         stamp_from=None if not p.fit_detected_frames_only else "depth", when_missing=REJECT,
                         missing_reason="bad_depth", missing_detail=lambda f: "no depth camera_info received yet",
                         capacity=p.depth_cache_size, pulled=True, bad_reason="bad_camera_info")
        if p.fit_detected_frames_only:
            # The detections start the work (the newest only); depth frames wait for them in the reader / cache.
            key = KeyInput("detections", PersonDetections, DETECTIONS, detections_to_boxes, stage_input_qos(1),
                           frame_name="frame", accept=lambda d: None if len(d.value) else "no_person")
            companions = [depth, info, self.mask.companion()]
        else:
            # Every depth frame (the newest only); detections only for the first frame's exclusion.
            key = KeyInput("depth", Image, "depth", checked_depth_image, camera_input_qos(1), raw=True,
                           frame_name="frame")
            companions = [info, Companion("detections", PersonDetections, DETECTIONS, detections_to_boxes,
                                          stage_input_qos(5), capacity=POSE_CACHE), self.mask.companion()]
        if self.pose_floors is not None:
            companions.append(self.pose_floors.companion())
        self.stage = Stage(self, key, companions, self.fit, capacity=p.depth_cache_size, frame_error_reason="bad_depth")
        if self.pose_floors is not None:
            self.pose_floors.attach()

    def activate_stage(self) -> None:
        self.stage.start()
        if self.params.value.fit_detected_frames_only:
            self.diagnostics.await_publishers(DETECTIONS)  # ready once the detector is connected

    def deactivate_stage(self) -> None:
        self.stage.stop()

    def on_params_change(self, params: GroundParams, changed: Set[str]) -> None:
        """Everything is read per frame (the waits too, for the frames already waiting)."""

    def depth_agrees_with_its_camera_info(self, depth: Received) -> None:
        """Checked on arrival, not only when fitted: a depth frame that disagrees with its own calibration is
        refused (ContractError) whether or not the graph works on its frame."""
        info = self.stage.caches["depth/camera_info"].get_exact(depth.stamp_ns)
        if info is not None:
            check_depth_against(depth.value, info.value)

    def fit(self, frame: Frame) -> None:
        started = time.perf_counter()
        msg = depth_of(frame)
        stamp = stamp_to_ns(msg.header.stamp)
        self.mask.previous_fit_stamp = stamp
        camera_info = frame["depth/camera_info"]  # always there: the frame is refused without one
        info_input = next(entry for entry in frame.inputs if entry[0] == "depth/camera_info")
        p = self.params.value
        # A camera_info of another stamp (calibration) is checked here; the frame's own was checked on arrival.
        if info_input[2] == InputStamp.STATIC or not p.fit_detected_frames_only:
            try:
                check_depth_against(msg, camera_info)
            except ContractError as error:
                self.diagnostics.reject(error.reason or "bad_depth", error.detail)
                return
        depth = depth_to_metres(msg)
        exclude, mask_input = self.mask.exclusion(msg, (depth.shape[0], depth.shape[1]), frame)
        inputs: List[tuple] = [("depth", stamp), info_input]
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
        pose = frame.received("camera_pose")
        self.publish_plane(plane, result, header, (time.perf_counter() - started) * 1e3, len(points), inputs,
                           None if pose is None else pose.value)

    def publish_plane(self, plane: GroundPlaneArrays, ransac: GroundPlaneResult, header: Header,
                      compute_time_ms: float, point_count: int, inputs: List[tuple], pose_floor) -> None:
        """Publish the frame's floor: RANSAC's, checked against the pose floor (a PoseFloor) of its stamp."""
        p = self.params.value
        floor, pose_stamp = fuse_with_pose_floor(ransac, stamp_to_ns(header.stamp), pose_floor,
                                                 p.pose_max_angle_deg, p.pose_max_height_m, p.quality_full_support)
        if pose_stamp is not None:
            inputs = [*inputs, ("camera_pose", pose_stamp)]
        plane = dataclasses.replace(plane, quality=floor.quality)
        tally = self.diagnostics.planes
        if floor.from_pose:
            plane = dataclasses.replace(plane, normal=floor.normal, offset=floor.offset, valid=True,
                                        source=GroundPlane.SOURCE_CAMERA_POSE)
            if tally.fallback():
                self.get_logger().warning(f"{floor.decision} ({plane.inlier_count} RANSAC inliers of {point_count}"
                                          f" points): published the floor of the camera pose (height"
                                          f" {floor.offset:.3f} m); {tally.fallbacks} such frames so far")
        elif not plane.valid:
            detail = f"{plane.inlier_count} inliers of {point_count} points"
            if p.use_camera_pose_fallback:
                detail += "; no camera pose of this stamp"
            self.diagnostics.reject("no_ground_plane", detail)
        if not plane.valid:
            tally.plane_out("none", FLOOR_NONE)
        else:
            tally.plane_out("camera_pose" if plane.source == GroundPlane.SOURCE_CAMERA_POSE else "ransac",
                            floor.decision)
        self.publisher.publish(arrays_to_ground_plane(plane, header, compute_time_ms, inputs=inputs))
        self.diagnostics.frame_out(header.stamp, compute_time_ms)


main = managed_node_main(GroundNode)  # the console script (leapnbv_common.managed_node: the process tuned, then run)


if __name__ == "__main__":
    main()
