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
from rclpy.node import Node
from sensor_msgs.msg import CameraInfo, Image
from std_msgs.msg import Header

from leapnbv_common.camera_pose import StampedCameraPose, create_camera_pose_source
from leapnbv_common.contracts import DuplicateStampGuard, check_same_frame, check_same_size, refused
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
from leapnbv_common.diagnostics import StageDiagnostics, rejects_bad_input
from leapnbv_common.node_params import NodeParams, run_node
from leapnbv_common.process_tuning import tune_node_process
from leapnbv_common.pulled_input import HOUSEKEEPING_PERIOD_S, PulledInput
from leapnbv_common.qos import camera_input_qos, stage_input_qos, stage_output_qos
from leapnbv_common.stamp_cache import STAMP_RESTART_NS, CompanionWait, StampCache
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
from leapnbv_msgs.msg import GroundPlane, InputStamp, PersonDetections

POSE_CACHE = 60  # camera poses (and frames waiting for theirs) remembered by stamp: ~2 s at 30 Hz
WAIT_CHECK_PERIOD_S = 0.02  # how often waiting frames are checked (the timer runs only while one waits)
FALLBACK_LOG_EVERY = 100  # log the camera-pose fallback on its first frame and every this many after


class FittedFrame(NamedTuple):
    """One depth frame's RANSAC result, as it waits to be published."""

    plane: GroundPlaneArrays
    header: Header
    compute_time_ms: float
    point_count: int  # the points RANSAC was fitted on
    inputs: list  # (name, stamp ns[, relation]) of what the fit used (GroundPlane.inputs)
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


class Pending(NamedTuple):
    """The newest frame to fit, waiting for its depth frame or for the previous frame's person mask."""

    key_stamp: int  # stamp of what started it: the detections (or the depth frame itself)
    since_ns: int  # node clock when it started waiting


class GroundNode(Node):
    def __init__(self) -> None:
        super().__init__("ground_node")
        self.params = NodeParams(self, GroundParams, self.on_params_change)
        p = self.params.value
        self.diagnostics = GroundDiagnostics(self)
        drop = self.diagnostics.drop_callback()
        self.depth_frames: StampCache = StampCache(p.depth_cache_size, "depth_evicted", drop)
        self.camera_infos: StampCache = StampCache(p.depth_cache_size, "camera_info_evicted")
        self.latest_camera_info: Optional[CameraInfo] = None
        self.person_mask: Optional[Image] = None
        # A frame with no recent mask (a scene's first) leaves out its own person boxes: its detections.
        self.detection_boxes: StampCache = StampCache(POSE_CACHE)
        self.stamps = DuplicateStampGuard()  # one content per stamp and input (contracts)
        self.publisher = self.create_publisher(GroundPlane, GROUND_PLANE, stage_output_qos())
        # Camera infos, depth frames and camera poses are pulled when a frame is fitted (they do not wake
        # the node at 30 Hz: leapnbv_common.pulled_input); depth frames stay serialized until fitted.
        self.info_input = PulledInput.create(self, CameraInfo, "depth/camera_info", self.on_camera_info,
                                             camera_input_qos(p.depth_cache_size))
        self.create_subscription(Image, PERSON_MASK, self.on_mask, stage_input_qos(1))
        # Depth frames are kept serialized (raw): only the ones that are fitted are ever deserialized.
        if p.fit_detected_frames_only:
            # The detections start the work (the newest only); depth frames wait for them in the reader / cache.
            self.depth_input = PulledInput.create(self, Image, "depth", self.on_depth,
                                                  camera_input_qos(p.depth_cache_size), raw=True)
            self.create_subscription(PersonDetections, DETECTIONS, self.on_detections, stage_input_qos(1))
            self.diagnostics.await_publishers(DETECTIONS)  # ready once the detector is connected
        else:
            self.depth_input = None
            self.create_subscription(Image, "depth", self.on_depth, camera_input_qos(1), raw=True)
            # Only for the first frame's exclusion: the boxes that came before their depth frame.
            self.create_subscription(PersonDetections, DETECTIONS, self.keep_detection_boxes, stage_input_qos(5))
        # The mask excluded from frame t is the previous fitted frame's. Waiting briefly for it (when
        # masks are flowing) makes the fit independent of message timing, so replays repeat.
        self.previous_fit_stamp: Optional[int] = None
        self.masks_flowing = False
        self.pending: Optional[Pending] = None
        # Floors from the camera pose, by stamp; fitted frames without a RANSAC floor wait here for theirs.
        self.pose_floors = CompanionWait(int(p.camera_pose_wait_s * 1e9), capacity=POSE_CACHE, frame_name="plane",
                                         companion_name="camera_pose", on_drop=drop)
        self.fallback_count = 0
        self.poses_seen = False  # until a first camera pose has come, a RANSAC plane goes out unchecked
        self.camera_pose = None
        self.pose_input: Optional[PulledInput] = None
        if p.use_camera_pose_fallback:
            self.camera_pose = create_camera_pose_source(p.camera_pose_source, self, POSE_CACHE, self.on_camera_pose)
            self.pose_input = PulledInput.adopt(self, self.camera_pose)  # None for a source without a subscription
        # A bad depth frame, camera_info or pose is counted within HOUSEKEEPING_PERIOD_S even while no frame
        # is fitted.
        self.create_timer(HOUSEKEEPING_PERIOD_S, self.housekeeping)
        self.wait_timer = self.create_timer(WAIT_CHECK_PERIOD_S, self.expire_wait)
        self.wait_timer.cancel()  # runs only while something waits: an idle node does not wake up

    def on_params_change(self, params: GroundParams, changed: Set[str]) -> None:
        """A new pose wait applies to the frames already waiting too; the fit reads its settings per frame."""
        self.pose_floors.wait_ns = int(params.camera_pose_wait_s * 1e9)

    def now_ns(self) -> int:
        return self.get_clock().now().nanoseconds

    def start_wait_timer(self) -> None:
        if self.wait_timer.is_canceled():
            self.wait_timer.reset()

    @rejects_bad_input("bad_camera_info")
    def on_camera_info(self, msg: CameraInfo) -> None:
        camera_info_to_k(msg)
        self.camera_infos.put(stamp_to_ns(msg.header.stamp), msg)
        self.latest_camera_info = msg

    def on_camera_pose(self, pose: StampedCameraPose) -> None:
        """Keep the floor of this pose by stamp; a frame waiting for it is published now.

        Raises:
            GroundPlaneError: the camera is not above the floor (the source counts it as bad_camera_pose).
        """
        normal, offset = floor_plane_from_camera_pose(pose.rotation, pose.position)
        self.poses_seen = True
        ready = self.pose_floors.add_companion(pose.stamp_ns, (pose.stamp_ns, normal, offset))
        if ready is not None:
            self.publish_plane(ready[0], ready[1])

    def slop_ns(self) -> int:
        return int(self.params.value.slop_s * 1e9)

    @rejects_bad_input("bad_person_mask")
    def on_mask(self, msg: Image) -> None:
        check_image(msg, ("mono8",), "person mask")
        if self.latest_camera_info is not None and refused(
                self.diagnostics, "bad_person_mask", check_same_frame, "person_mask", msg.header.frame_id,
                "depth camera_info", self.latest_camera_info.header.frame_id):
            return
        self.person_mask = msg
        self.masks_flowing = True
        if self.pending is not None:
            self.try_fit()

    def pull_companions(self) -> None:
        """Take the camera infos and depth frames that arrived since the last pull."""
        self.info_input.drain()
        if self.depth_input is not None:
            self.depth_input.drain()

    def pull_poses(self) -> None:
        if self.pose_input is not None:
            self.pose_input.drain()

    def housekeeping(self) -> None:
        self.pull_companions()
        self.pull_poses()

    def on_detections(self, msg: PersonDetections, info) -> None:
        self.diagnostics.input_seen("detections", info)
        if not msg.detections:
            self.diagnostics.drop("no_person")  # nobody downstream works on this frame
            return
        if not self.keep_detection_boxes(msg):
            return
        self.pull_companions()
        self.start_frame(stamp_to_ns(msg.header.stamp))

    def keep_detection_boxes(self, msg: PersonDetections) -> bool:
        """Keep the frame's person boxes by stamp (a first frame leaves them out); False: refused as bad."""
        if refused(self.diagnostics, "bad_detections", detections_to_boxes, msg):
            return False
        self.detection_boxes.put(stamp_to_ns(msg.header.stamp), detections_to_boxes(msg))
        return True

    @rejects_bad_input("bad_depth")
    def on_depth(self, msg: bytes, info) -> None:
        """A depth frame, read in place from its serialized bytes: cached by stamp until it is fitted."""
        self.diagnostics.input_seen("depth", info)
        msg = SerializedImage(msg)  # a ConversionError counts as bad_depth
        # The depth contract (a view, no conversion)
        if refused(self.diagnostics, "bad_depth", check_image, msg, DEPTH_ENCODINGS, "depth") or \
                refused(self.diagnostics, "bad_depth", self.stamps.check, "depth", msg):
            return
        stamp = stamp_to_ns(msg.header.stamp)
        # Checked against its camera_info on arrival (not only when fitted): a depth frame that disagrees
        # with its own calibration is refused whether or not the graph works on its frame.
        info = self.camera_infos.get_exact(stamp)
        if info is not None and (
                refused(self.diagnostics, "bad_depth", check_same_size, "depth", image_size(msg), "depth camera_info",
                        image_size(info)) or
                refused(self.diagnostics, "bad_depth", check_same_frame, "depth", msg.header.frame_id,
                        "depth camera_info", info.header.frame_id)):
            return
        if self.previous_fit_stamp is not None and 0 < self.previous_fit_stamp - stamp < STAMP_RESTART_NS:
            self.diagnostics.drop("depth_older_than_published")
            return
        self.depth_frames.put(stamp, msg)
        if not self.params.value.fit_detected_frames_only:
            self.info_input.drain()
            self.start_frame(stamp)
        elif self.pending is not None:
            self.try_fit()

    def start_frame(self, stamp: int) -> None:
        """A frame to fit (the newest): an older one still waiting is served now or superseded."""
        self.diagnostics.frame_in()
        if self.previous_fit_stamp is not None and stamp <= self.previous_fit_stamp:
            if self.previous_fit_stamp - stamp < STAMP_RESTART_NS:
                self.diagnostics.drop("duplicate_stamp" if stamp == self.previous_fit_stamp else "older_than_published")
                return
            self.previous_fit_stamp = None  # the stamps started over (a replay from its start)
        if self.pending is not None:
            if self.pending.key_stamp >= stamp:
                self.diagnostics.drop("frame_superseded")
                return
            if self.depth_for(self.pending.key_stamp) is not None:
                self.try_fit(serve_now=True)  # it waits only for a mask: serve it, it is in flight downstream
            else:
                self.pending = None
                self.diagnostics.drop("frame_superseded")
        self.pending = Pending(stamp, self.now_ns())
        self.try_fit()

    def depth_for(self, stamp: int) -> Optional[SerializedImage]:
        match = self.depth_frames.find_nearest(stamp, self.slop_ns())
        return None if match is None else match[1]

    def mask_of(self, stamp: int) -> bool:
        """Whether the latest person mask belongs to the frame of this stamp (within the slop)."""
        mask = self.person_mask
        return mask is not None and abs(stamp_to_ns(mask.header.stamp) - stamp) <= self.slop_ns()

    def try_fit(self, serve_now: bool = False) -> None:
        """Fit the pending frame once its depth frame (and, while masks flow, the previous frame's mask) is here."""
        if self.pending is None:
            return
        p = self.params.value
        waited_ns = self.now_ns() - self.pending.since_ns
        depth = self.depth_for(self.pending.key_stamp)
        if depth is None:
            if waited_ns >= p.depth_wait_s * 1e9:
                self.diagnostics.drop("no_matching_depth")
                self.pending = None
            else:
                self.start_wait_timer()
            return
        needs_mask = (p.mask_wait_s > 0 and self.masks_flowing and self.previous_fit_stamp is not None
                      and not self.mask_of(self.previous_fit_stamp))
        if needs_mask and not serve_now:
            if waited_ns < p.mask_wait_s * 1e9:
                self.start_wait_timer()
                return
            self.masks_flowing = False  # no mask for that frame: do not wait again until one comes
        key = self.pending.key_stamp
        self.pending = None
        self.fit(depth, key)

    def expire_wait(self) -> None:
        if self.pose_floors.waiting():
            self.pull_poses()
        if self.pending is not None:
            self.pull_companions()
        for _, plane in self.pose_floors.expire(self.now_ns()):
            self.publish_plane(plane, None)  # no pose of its stamp came: the invalid plane, as before
        self.try_fit()
        if self.pending is None and not self.pose_floors.waiting():
            self.wait_timer.cancel()

    def exclusion_mask(self, depth_msg: Image, shape, key_stamp: int) -> Tuple[Optional[np.ndarray], Optional[tuple]]:
        """The latest person mask, if recent and of the same size (the person is not floor), and its input
        entry; without one (the first frame of a scene), the frame's own person boxes."""
        mask = self.person_mask
        if mask is None or (mask.height, mask.width) != shape:
            return self.detection_mask(shape, key_stamp), None
        age_ns = stamp_to_ns(depth_msg.header.stamp) - stamp_to_ns(mask.header.stamp)
        if abs(age_ns) > self.params.value.mask_max_age_s * 1e9:
            return self.detection_mask(shape, key_stamp), None
        relation = InputStamp.SAME_FRAME if abs(age_ns) <= self.slop_ns() else InputStamp.EXCLUSION_HINT
        return image_to_numpy(mask) > 0, ("person_mask", stamp_to_ns(mask.header.stamp), relation)

    def detection_mask(self, shape, key_stamp: int) -> Optional[np.ndarray]:
        """The frame's own person boxes (its detections: already among the plane's inputs), or None."""
        p = self.params.value
        boxes = self.detection_boxes.get_exact(key_stamp) if p.exclude_detections else None
        if boxes is None or len(boxes) == 0:
            return None
        return box_exclusion_mask(shape, boxes, p.detection_grow_px, p.detection_top_share)

    def frame_camera_info(self, stamp: int) -> Tuple[CameraInfo, tuple]:
        """The depth frame's own camera_info, else the latest one (calibration: recorded as STATIC)."""
        info = self.camera_infos.get_exact(stamp)
        if info is not None:
            return info, ("depth/camera_info", stamp, InputStamp.SAME_FRAME)
        if self.latest_camera_info is None:
            raise ValueError("no depth camera_info received yet")
        info = self.latest_camera_info
        return info, ("depth/camera_info", stamp_to_ns(info.header.stamp), InputStamp.STATIC)

    @rejects_bad_input("bad_depth")
    def fit(self, msg: SerializedImage, key_stamp: int) -> None:
        started = time.perf_counter()
        stamp = stamp_to_ns(msg.header.stamp)
        self.depth_frames.pop(stamp)
        self.previous_fit_stamp = stamp
        self.depth_frames.drop_older_than(stamp, "depth_skipped")  # frames the graph did not work on
        camera_info, info_input = self.frame_camera_info(stamp)
        p = self.params.value
        # A camera_info of another stamp (calibration) is checked here; the frame's own was checked on arrival.
        if info_input[2] == InputStamp.STATIC and (
                refused(self.diagnostics, "bad_depth", check_same_size, "depth", image_size(msg), "depth camera_info",
                        image_size(camera_info)) or
                refused(self.diagnostics, "bad_depth", check_same_frame, "depth", msg.header.frame_id,
                        "depth camera_info", camera_info.header.frame_id)):
            return
        depth = depth_to_metres(msg)
        exclude, mask_input = self.exclusion_mask(msg, depth.shape, key_stamp)
        inputs = [("depth", stamp), info_input]
        if p.fit_detected_frames_only:
            inputs.append(("detections", key_stamp))
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
        if p.fit_detected_frames_only:
            header.stamp.sec, header.stamp.nanosec = divmod(key_stamp, 1_000_000_000)
        frame_stamp = stamp_to_ns(header.stamp)
        frame = FittedFrame(plane, header, (time.perf_counter() - started) * 1e3, len(points), inputs, result)
        self.pull_poses()
        if not p.use_camera_pose_fallback or (result.valid and not self.poses_seen):
            self.publish_plane(frame, None)  # no pose to check it against (none has come so far)
            return
        # The floor of this frame's camera pose checks RANSAC's, once it is here (or the wait ran out).
        ready = self.pose_floors.add_frame(frame_stamp, frame, self.now_ns())
        if ready is None:
            self.camera_pose.expect(frame_stamp, msg.header.frame_id)
            self.start_wait_timer()
        else:
            self.publish_plane(ready[0], ready[1])

    def publish_plane(self, frame: FittedFrame, pose_floor: Optional[Tuple[int, np.ndarray, float]]) -> None:
        """Publish the frame's floor: RANSAC's, checked against the pose's floor when the pose has its stamp.

        Args:
            frame: the plane as RANSAC gave it, with its frame's header.
            pose_floor: (stamp ns, normal, offset) of a camera pose, or None.
        """
        p = self.params.value
        inputs = list(frame.inputs)
        matching = pose_floor is not None and pose_floor[0] == stamp_to_ns(frame.header.stamp)
        if matching:
            inputs.append(("camera_pose", pose_floor[0]))
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
        self.publisher.publish(arrays_to_ground_plane(plane, frame.header, frame.compute_time_ms, inputs=inputs))
        self.diagnostics.frame_out(frame.header.stamp, frame.compute_time_ms)


def main(args=None) -> None:
    tune_node_process()  # one BLAS thread, image buffers reused (leapnbv_common.process_tuning)
    run_node(GroundNode, args)


if __name__ == "__main__":
    main()
