"""hmr_node: image + PersonDetections (same stamp) -> HumanMesh of the target person.

Engine backends run the SMPLer-X-style encoder + heads and the FP32 SMPL-X tail; the
ground_truth backend poses the body model with the simulator's ground-truth parameters.

Parameters: :class:`leapnbv_perception.params.HmrParams`. The crop scale, the hand un-mirroring
and the target tracking change at runtime; the engine, the models and the cache are set at start-up.
"""
from __future__ import annotations

import os
import time
from typing import Optional, Set

import numpy as np
from rclpy.node import Node
from sensor_msgs.msg import CameraInfo, Image

from leapnbv_common.contracts import DuplicateStampGuard, check_same_frame, check_same_size, refused
from leapnbv_common.conversions import (
    HumanMeshArrays,
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
from leapnbv_common.qos import camera_input_qos, stage_input_qos, stage_output_qos
from leapnbv_common.stamp_cache import ExactStampPairer, StampCache
from leapnbv_common.topics import DETECTIONS, GROUND_TRUTH, HUMAN_MESH
from leapnbv_msgs.msg import HumanMesh, PersonDetections, SceneGroundTruth
from leapnbv_perception.nodes.engine_loading import RetryingLoader, create_engine_backend
from leapnbv_perception.params import HmrParams
from leapnbv_perception.target_selection import select_target


class HmrNode(Node):
    def __init__(self) -> None:
        super().__init__("hmr_node")
        self.params = NodeParams(self, HmrParams, self.on_params_change)
        p = self.params.value
        self.diagnostics = StageDiagnostics(self, hardware_id=p.backend)
        self.publisher = self.create_publisher(HumanMesh, HUMAN_MESH, stage_output_qos())
        self.ground_truth = p.backend == "ground_truth"
        self.previous_box: Optional[np.ndarray] = None
        self.camera_k: Optional[np.ndarray] = None
        self.camera_info: Optional[CameraInfo] = None
        self.stamps = DuplicateStampGuard()  # one content per stamp and input (contracts)
        self.engine = RetryingLoader(self, self.diagnostics, f"HMR engine {p.model_file_path!r} with body "
                                     f"model {p.body_model_path!r}", self.load_engine, p.model_retry_period_s)
        if self.ground_truth:
            self.pairer = ExactStampPairer(capacity=p.cache_size)
            self.create_subscription(SceneGroundTruth, GROUND_TRUTH, self.on_ground_truth, stage_input_qos(10))
            self.create_subscription(CameraInfo, "camera_info", self.on_camera_info, camera_input_qos(1))
        else:
            self.images: StampCache = StampCache(p.cache_size)
            self.create_subscription(Image, "image", self.on_image, camera_input_qos(p.cache_size))
        self.create_subscription(PersonDetections, DETECTIONS, self.on_detections, stage_input_qos(5))

    def load_engine(self):
        from leapnbv_perception.smplx_layer import SMPLXModel

        p = self.params.value
        if not p.body_model_path:
            raise FileNotFoundError("parameter body_model_path is empty: set it to SMPLX_NEUTRAL.npz")
        body_model = SMPLXModel.load(os.path.expanduser(p.body_model_path))
        if self.ground_truth:
            return body_model
        from leapnbv_perception.hmr import HumanMeshEstimator

        return HumanMeshEstimator(create_engine_backend(p), body_model, box_scale=p.box_scale,
                                  unmirror_left_hand=p.unmirror_left_hand)

    def on_params_change(self, params: HmrParams, changed: Set[str]) -> None:
        """The crop scale and the hand un-mirroring apply from the next frame; the tracking settings
        are read per frame."""
        if self.engine.value is not None and not self.ground_truth:
            self.engine.value.box_scale = params.box_scale
            self.engine.value.unmirror_left_hand = params.unmirror_left_hand

    @rejects_bad_input("bad_camera_info")
    def on_camera_info(self, msg: CameraInfo) -> None:
        self.camera_k = camera_info_to_k(msg)
        self.camera_info = msg

    def on_image(self, msg: Image) -> None:
        if refused(self.diagnostics, "bad_image", self.stamps.check, "image", msg):
            return
        self.images.put(stamp_to_ns(msg.header.stamp), msg)

    @rejects_bad_input("bad_ground_truth")
    def on_ground_truth(self, msg: SceneGroundTruth) -> None:
        # The contract: finite values, a box or none
        if refused(self.diagnostics, "bad_ground_truth", scene_ground_truth_to_arrays, msg) or \
                refused(self.diagnostics, "bad_ground_truth", self.stamps.check, "ground_truth", msg):
            return
        pair = self.pairer.add_second(stamp_to_ns(msg.header.stamp), msg)
        if pair is not None:
            self.estimate(*pair)

    @rejects_bad_input("bad_detections")
    def on_detections(self, msg: PersonDetections) -> None:
        self.diagnostics.frame_in()
        # The contract: finite boxes in the image, scores in [0, 1]
        if refused(self.diagnostics, "bad_detections", detections_to_boxes, msg) or \
                refused(self.diagnostics, "bad_detections", self.stamps.check, "detections", msg):
            return
        stamp = stamp_to_ns(msg.header.stamp)
        if self.ground_truth:
            pair = self.pairer.add_first(stamp, msg)
            if pair is not None:
                self.estimate(*pair)
            return
        image = self.images.pop(stamp)
        if image is None:
            self.diagnostics.reject("no_matching_image", f"no cached image with stamp {stamp} ns")
            return
        self.estimate(msg, image)

    @rejects_bad_input("bad_frame")
    def estimate(self, detections: PersonDetections, source) -> None:
        started = time.perf_counter()
        if self.engine.value is None:
            self.diagnostics.reject("engine_not_ready", self.diagnostics.engine_state)
            return
        # The frame's other input (its colour image, or the camera_info the ground truth is placed with)
        # names the same frame and has the size the detections were found in.
        other = self.camera_info if self.ground_truth else source
        if self.ground_truth and other is None:
            raise ValueError("no camera_info received yet (ground-truth meshes use the real intrinsics)")
        if refused(self.diagnostics, "bad_frame", check_same_frame, "detections", detections.header.frame_id,
                   type(other).__name__, other.header.frame_id) or \
                refused(self.diagnostics, "bad_frame", check_same_size, "the detections' image",
                        (detections.image_width, detections.image_height), type(other).__name__, image_size(other)):
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
            mesh = self.ground_truth_mesh(box, source, (detections.image_width, detections.image_height))
        else:
            mesh = self.engine_mesh(box, source)
        self.previous_box = box[:4]
        out = arrays_to_human_mesh(mesh, header=detections.header,
                                   compute_time_ms=(time.perf_counter() - started) * 1e3)
        self.publisher.publish(out)
        self.diagnostics.frame_out(detections.header.stamp, out.compute_time_ms)

    def engine_mesh(self, box: np.ndarray, image: Image) -> HumanMeshArrays:
        rgb = image_to_rgb(image)
        est = self.engine.value.estimate(rgb, box[:4])
        return HumanMeshArrays(
            vertices=est.vertices, faces=est.faces, virtual_intrinsics=(est.fx, est.fy, est.cx, est.cy),
            image_size=(rgb.shape[1], rgb.shape[0]), detection=box, processed_box=est.processed_box,
            root_pose=est.root, body_pose=est.body, left_hand_pose=est.left_hand,
            right_hand_pose=est.right_hand, jaw_pose=est.jaw, betas=est.betas,
            expression=est.expression, cam_translation=est.cam_translation,
            model_id=os.path.basename(self.params.value.model_file_path))

    def ground_truth_mesh(self, box: np.ndarray, truth: SceneGroundTruth, image_size) -> HumanMeshArrays:
        """The simulator's body, already metric in the camera frame: its 'virtual' camera is the real one."""
        from leapnbv_perception.hmr_crop import process_box, xyxy_to_xywh
        from leapnbv_perception.smplx_layer import SMPLXParams

        if self.camera_k is None:
            raise ValueError("no camera_info received yet (ground-truth meshes use the real intrinsics)")
        k = self.camera_k
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
    run_node(HmrNode, args)


if __name__ == "__main__":
    main()
