"""hmr_node: image + PersonDetections (same stamp) -> HumanMesh of the target person.

Engine backends run the SMPLer-X-style encoder + heads and the FP32 SMPL-X tail; the
ground_truth backend poses the body model with the simulator's ground-truth parameters.

One frame, one set of inputs: the detections are paired with the image (or the ground truth) of
exactly their stamp, and the mesh lists what it used (``inputs``). Latest-frame scheduling: the
detections subscription keeps the newest message only, a frame older than one already published
is dropped, and cached images / ground truth older than a published frame are dropped; every drop
is counted on /diagnostics (``dropped.<reason>``). Once the engine is loaded, /diagnostics says whether
it estimates the hands (``info.hands``: ``estimated``, or ``not_estimated`` for a body-only export,
whose meshes all have the SMPL-X hand mean pose; that is also logged once).

Parameters: :class:`leapnbv_perception.params.HmrParams`. The crop scale, the hand un-mirroring
and the target tracking change at runtime; the engine, the models and the cache are set at start-up.
"""
from __future__ import annotations

import os
import time
from typing import Optional, Set, Tuple

import numpy as np
from rclpy.node import Node
from sensor_msgs.msg import CameraInfo, Image

from leapnbv_common.contracts import DuplicateStampGuard, check_same_frame, check_same_size, refused
from leapnbv_common.conversions import (
    HumanMeshArrays,
    SerializedImage,
    arrays_to_human_mesh,
    camera_info_to_k,
    detections_to_boxes,
    image_size,
    image_to_rgb,
    scene_ground_truth_to_arrays,
    stamp_to_ns,
)
from leapnbv_common.diagnostics import StageDiagnostics, rejects_bad_input
from leapnbv_common.node_params import NodeParams, run_node
from leapnbv_common.process_tuning import tune_node_process
from leapnbv_common.pulled_input import HOUSEKEEPING_PERIOD_S, PulledInput
from leapnbv_common.qos import camera_input_qos, stage_input_qos, stage_output_qos
from leapnbv_common.stamp_cache import STAMP_RESTART_NS, ExactStampPairer, StampCache
from leapnbv_common.topics import DETECTIONS, GROUND_TRUTH, HUMAN_MESH
from leapnbv_msgs.msg import HumanMesh, InputStamp, PersonDetections, SceneGroundTruth
from leapnbv_perception.nodes.engine_loading import RetryingLoader, create_engine_backend
from leapnbv_perception.params import HmrParams
from leapnbv_perception.target_selection import select_target

CAMERA_INFO_WAIT_S = 0.2  # ground truth: how long a frame waits for the camera_info of its stamp
# How long detections wait for their colour image: DDS does not order topics, and a fast detector (the
# simulator's boxes, a carried box) can publish before this node has the image it was made from.
IMAGE_WAIT_S = 0.2


class HmrNode(Node):
    def __init__(self) -> None:
        super().__init__("hmr_node")
        self.params = NodeParams(self, HmrParams, self.on_params_change)
        p = self.params.value
        self.diagnostics = StageDiagnostics(self, hardware_id=p.backend)
        self.publisher = self.create_publisher(HumanMesh, HUMAN_MESH, stage_output_qos())
        self.ground_truth = p.backend == "ground_truth"
        self.previous_box: Optional[np.ndarray] = None
        self.last_published: Optional[int] = None
        self.stamps = DuplicateStampGuard()  # one content per stamp and input (contracts)
        drop = self.diagnostics.drop_callback()
        # Colour camera infos by stamp (ground truth: the mesh is metric in the real camera).
        self.camera_infos: StampCache = StampCache(p.cache_size, "camera_info_evicted")
        self.latest_camera_info: Optional[CameraInfo] = None
        self.info_wait: Optional[tuple] = None  # (stamp, (detections, truth), since): waits for its camera_info
        self.truth_wait: Optional[tuple] = None  # (stamp, since): detections waiting for their ground truth
        self.image_wait: Optional[tuple] = None  # (stamp, detections, since): detections waiting for their image
        self.wait_timer = self.create_timer(0.02, self.expire_waits)
        self.wait_timer.cancel()  # runs only while a frame waits
        self.engine = RetryingLoader(self, self.diagnostics, f"HMR engine {p.model_file_path!r} with body "
                                     f"model {p.body_model_path!r}", self.load_engine, p.model_retry_period_s)
        if self.ground_truth:
            self.pairer = ExactStampPairer(capacity=p.cache_size, first_name="detections",
                                           second_name="ground_truth", on_drop=drop)
            # The truth and the camera infos come at camera rate: they are pulled when detections come
            # (leapnbv_common.pulled_input), so they do not wake the node for frames it never works on.
            self.companions = [
                PulledInput.create(self, CameraInfo, "camera_info", self.on_camera_info,
                                   camera_input_qos(p.cache_size)),
                PulledInput.create(self, SceneGroundTruth, GROUND_TRUTH, self.on_ground_truth,
                                   stage_input_qos(p.cache_size))]
        else:
            # Images wait for their detections (the detector takes a while) in the reader and in this cache,
            # serialized: pulled when detections come, deserialized only for the frame worked on.
            self.images: StampCache = StampCache(p.cache_size, "image_evicted", drop)
            self.companions = [PulledInput.create(self, Image, "image", self.on_image, camera_input_qos(p.cache_size),
                                                  raw=True)]
        # The stream that starts the work: the newest message only.
        self.create_subscription(PersonDetections, DETECTIONS, self.on_detections, stage_input_qos(1))
        self.diagnostics.await_publishers(DETECTIONS)  # ready once the detector is connected
        # A bad companion is counted within HOUSEKEEPING_PERIOD_S even while no detections come.
        self.create_timer(HOUSEKEEPING_PERIOD_S, self.pull_companions)

    def load_engine(self):
        from leapnbv_perception.smplx_layer import SMPLXModel

        p = self.params.value
        if not p.body_model_path:
            raise FileNotFoundError("parameter body_model_path is empty: set it to SMPLX_NEUTRAL.npz")
        body_model = SMPLXModel.load(os.path.expanduser(p.body_model_path))
        if self.ground_truth:
            return body_model
        from leapnbv_perception.hmr import HANDS_ESTIMATED, HANDS_NOT_ESTIMATED, HumanMeshEstimator

        estimator = HumanMeshEstimator(create_engine_backend(p), body_model, box_scale=p.box_scale,
                                       unmirror_left_hand=p.unmirror_left_hand)
        # Said once, when the engine loads: a body-only engine's meshes all have the hand mean pose.
        self.diagnostics.set_info("hands", HANDS_ESTIMATED if estimator.hands_estimated else HANDS_NOT_ESTIMATED)
        if not estimator.hands_estimated:
            self.get_logger().info(
                f"HMR engine {p.model_file_path!r} is body-only (export metadata leapnbv.hands=not_estimated): "
                "the hand poses are not estimated, every mesh has the SMPL-X hand mean pose")
        return estimator

    def on_params_change(self, params: HmrParams, changed: Set[str]) -> None:
        """The crop scale and the hand un-mirroring apply from the next frame; the tracking settings
        are read per frame."""
        if self.engine.value is not None and not self.ground_truth:
            self.engine.value.box_scale = params.box_scale
            self.engine.value.unmirror_left_hand = params.unmirror_left_hand

    def pull_companions(self) -> None:
        for companion in self.companions:
            companion.drain()

    @rejects_bad_input("bad_camera_info")
    def on_camera_info(self, msg: CameraInfo) -> None:
        camera_info_to_k(msg)  # the contract, before it is kept
        stamp = stamp_to_ns(msg.header.stamp)
        self.camera_infos.put(stamp, msg)
        self.latest_camera_info = msg
        if self.info_wait is not None and self.info_wait[0] == stamp:
            _, pair, _ = self.info_wait
            self.info_wait = None
            self.estimate(*pair)

    def camera_info_for(self, stamp_ns: int) -> Tuple[CameraInfo, tuple]:
        """(camera_info, input stamp) of the frame: its own, else the latest (calibration: STATIC).

        Raises:
            ValueError: no camera_info received yet.
        """
        info = self.camera_infos.get_exact(stamp_ns)
        if info is not None:
            return info, ("camera_info", stamp_ns, InputStamp.SAME_FRAME)
        if self.latest_camera_info is None:
            raise ValueError("no camera_info received yet (ground-truth meshes use the real intrinsics)")
        info = self.latest_camera_info
        return info, ("camera_info", stamp_to_ns(info.header.stamp), InputStamp.STATIC)

    def is_stale(self, stamp_ns: int) -> bool:
        """A frame not newer than the last published one (counted); stamps far behind mean they started over."""
        if self.last_published is None or stamp_ns > self.last_published:
            return False
        if self.last_published - stamp_ns >= STAMP_RESTART_NS:
            self.last_published = None
            return False
        self.diagnostics.drop("duplicate_stamp" if stamp_ns == self.last_published else "older_than_published")
        return True

    @rejects_bad_input("bad_image")
    def on_image(self, msg: bytes, info) -> None:
        self.diagnostics.input_seen("image", info)
        image = SerializedImage(msg)  # read in place: pixels are converted only for the frame worked on
        if refused(self.diagnostics, "bad_image", self.stamps.check, "image", image):
            return
        stamp = stamp_to_ns(image.header.stamp)
        if self.image_wait is not None and self.image_wait[0] == stamp:
            detections = self.image_wait[1]
            self.image_wait = None
            self.estimate(detections, image)
            return
        self.images.put(stamp, image)

    @rejects_bad_input("bad_ground_truth")
    def on_ground_truth(self, msg: SceneGroundTruth, info) -> None:
        self.diagnostics.input_seen("ground_truth", info)
        # The contract: finite values, a box or none
        if refused(self.diagnostics, "bad_ground_truth", scene_ground_truth_to_arrays, msg) or \
                refused(self.diagnostics, "bad_ground_truth", self.stamps.check, "ground_truth", msg):
            return
        stamp = stamp_to_ns(msg.header.stamp)
        pair = self.pairer.add_second(stamp, msg)
        if pair is not None:
            if self.truth_wait is not None and self.truth_wait[0] == stamp:
                self.truth_wait = None
            self.estimate_with_camera_info(pair)

    def estimate_with_camera_info(self, pair: tuple) -> None:
        """Ground truth: estimate once the frame's camera_info is here (DDS does not order topics), waiting
        at most CAMERA_INFO_WAIT_S; then with the latest calibration, if any."""
        stamp = stamp_to_ns(pair[0].header.stamp)
        if self.camera_infos.get_exact(stamp) is not None:
            self.info_wait = None
            self.estimate(*pair)
            return
        if self.info_wait is not None:
            self.diagnostics.drop("detections_superseded")  # an older frame still waiting for its camera_info
        self.info_wait = (stamp, pair, time.monotonic())
        self.start_wait_timer()

    def start_wait_timer(self) -> None:
        if self.wait_timer.is_canceled():
            self.wait_timer.reset()

    def expire_waits(self) -> None:
        if self.waiting():
            self.pull_companions()
        if self.image_wait is not None and time.monotonic() - self.image_wait[2] >= IMAGE_WAIT_S:
            stamp = self.image_wait[0]
            self.image_wait = None
            self.diagnostics.reject("no_matching_image", f"no image with stamp {stamp} ns within {IMAGE_WAIT_S} s")
        if self.truth_wait is not None and time.monotonic() - self.truth_wait[1] >= CAMERA_INFO_WAIT_S:
            self.truth_wait = None  # its detections stay in the pairer until evicted (detections_unpaired)
        if self.info_wait is not None and time.monotonic() - self.info_wait[2] >= CAMERA_INFO_WAIT_S:
            _, pair, _ = self.info_wait
            self.info_wait = None
            self.estimate(*pair)  # with the latest camera_info (recorded as STATIC), or refused without one
        if not self.waiting():
            self.wait_timer.cancel()

    @rejects_bad_input("bad_detections")
    def on_detections(self, msg: PersonDetections, info) -> None:
        self.diagnostics.frame_in()
        self.diagnostics.input_seen("detections", info)
        # The contract: finite boxes in the image, scores in [0, 1]
        if refused(self.diagnostics, "bad_detections", detections_to_boxes, msg) or \
                refused(self.diagnostics, "bad_detections", self.stamps.check, "detections", msg):
            return
        stamp = stamp_to_ns(msg.header.stamp)
        if self.is_stale(stamp):
            return
        self.pull_companions()
        if self.ground_truth:
            pair = self.pairer.add_first(stamp, msg)
            if pair is not None:
                self.estimate_with_camera_info(pair)
            else:  # its truth may still be on the way (DDS does not order topics): pulled again shortly
                self.truth_wait = (stamp, time.monotonic())
                self.start_wait_timer()
            return
        if self.image_wait is not None and self.image_wait[0] == stamp:
            self.diagnostics.drop("duplicate_stamp")  # the frame's first detections wait for its image
            return
        image = self.images.pop(stamp)
        self.images.drop_older_than(stamp, "image_superseded")
        if self.image_wait is not None:
            self.image_wait = None
            self.diagnostics.drop("detections_superseded")  # an older frame still waiting for its image
        if image is None:  # its image may still be on the way: pulled again shortly (IMAGE_WAIT_S)
            self.image_wait = (stamp, msg, time.monotonic())
            self.start_wait_timer()
            return
        self.estimate(msg, image)

    def waiting(self) -> bool:
        """A frame waits for a companion message (its camera_info, ground truth or image)."""
        return self.info_wait is not None or self.truth_wait is not None or self.image_wait is not None

    @rejects_bad_input("bad_frame")
    def estimate(self, detections: PersonDetections, source) -> None:
        started = time.perf_counter()
        if self.engine.value is None:
            self.diagnostics.reject("engine_not_ready", self.diagnostics.engine_state)
            return
        stamp = stamp_to_ns(detections.header.stamp)
        # The frame's other input (its colour image, or the camera_info the ground truth is placed with)
        # names the same frame and has the size the detections were found in.
        if self.ground_truth:
            self.pairer.drop_older_than(stamp)
            other, info_input = self.camera_info_for(stamp)
            other_name = "camera_info"
        else:
            other, other_name = source, "image"
        if refused(self.diagnostics, "bad_frame", check_same_frame, "detections", detections.header.frame_id,
                   other_name, other.header.frame_id) or \
                refused(self.diagnostics, "bad_frame", check_same_size, "the detections' image",
                        (detections.image_width, detections.image_height), other_name, image_size(other)):
            return
        boxes = detections_to_boxes(detections)
        p = self.params.value
        previous = self.previous_box if p.track_previous_target else None
        index = select_target(boxes, previous, p.min_track_iou)
        if index < 0:
            self.diagnostics.reject("no_person", "no detection in this frame")
            return
        box = boxes[index]
        if self.ground_truth:
            mesh = self.ground_truth_mesh(box, source, (detections.image_width, detections.image_height),
                                          camera_info_to_k(other))
            inputs = [("detections", stamp), ("ground_truth", stamp_to_ns(source.header.stamp)), info_input]
        else:
            mesh = self.engine_mesh(box, source)
            inputs = [("detections", stamp), ("image", stamp_to_ns(source.header.stamp))]
        self.previous_box = box[:4]
        out = arrays_to_human_mesh(mesh, header=detections.header,
                                   compute_time_ms=(time.perf_counter() - started) * 1e3, inputs=inputs)
        self.publisher.publish(out)
        self.last_published = stamp
        self.diagnostics.frame_out(detections.header.stamp, out.compute_time_ms)

    def engine_mesh(self, box: np.ndarray, image: SerializedImage) -> HumanMeshArrays:
        rgb = image_to_rgb(image)
        est = self.engine.value.estimate(rgb, box[:4])
        return HumanMeshArrays(
            vertices=est.vertices, faces=est.faces, virtual_intrinsics=(est.fx, est.fy, est.cx, est.cy),
            image_size=(rgb.shape[1], rgb.shape[0]), detection=box, processed_box=est.processed_box,
            root_pose=est.root, body_pose=est.body, left_hand_pose=est.left_hand,
            right_hand_pose=est.right_hand, jaw_pose=est.jaw, betas=est.betas,
            expression=est.expression, cam_translation=est.cam_translation,
            model_id=os.path.basename(self.params.value.model_file_path))

    def ground_truth_mesh(self, box: np.ndarray, truth: SceneGroundTruth, image_size, k: np.ndarray) -> HumanMeshArrays:
        """The simulator's body, already metric in the camera frame: its 'virtual' camera is the real one (K)."""
        from leapnbv_perception.hmr_crop import process_box, xyxy_to_xywh
        from leapnbv_perception.smplx_layer import SMPLXParams

        gt = scene_ground_truth_to_arrays(truth)
        params = SMPLXParams.from_axis_angle(gt.root_pose, gt.body_pose, gt.left_hand_pose, gt.right_hand_pose,
                                             gt.jaw_pose, gt.betas, gt.expression)
        body = self.engine.value
        vertices = body.forward(params).vertices + gt.translation
        return HumanMeshArrays(
            vertices=vertices, faces=body.faces, virtual_intrinsics=(k[0, 0], k[1, 1], k[0, 2], k[1, 2]),
            image_size=image_size, detection=box,
            processed_box=process_box(xyxy_to_xywh(box[:4]), image_size[0], image_size[1],
                                      scale=self.params.value.box_scale),
            root_pose=gt.root_pose, body_pose=gt.body_pose, left_hand_pose=gt.left_hand_pose,
            right_hand_pose=gt.right_hand_pose, jaw_pose=gt.jaw_pose, betas=gt.betas,
            expression=gt.expression, cam_translation=gt.translation, model_id="ground_truth")


def main(args=None) -> None:
    tune_node_process()  # one BLAS thread, image buffers reused (leapnbv_common.process_tuning)
    run_node(HmrNode, args)


if __name__ == "__main__":
    main()
