"""hmr_node: image + PersonDetections (same stamp) -> HumanMesh of the target person.

Engine backends run the SMPLer-X-style encoder + heads and the FP32 SMPL-X tail; the
ground_truth backend poses the body model with the simulator's ground-truth parameters.
"""
from __future__ import annotations

import os
import time
from typing import Optional

import numpy as np
from rclpy.node import Node
from sensor_msgs.msg import CameraInfo, Image

from leapnbv_common.conversions import (
    HumanMeshArrays,
    arrays_to_human_mesh,
    camera_info_to_k,
    detection_to_box,
    image_to_rgb,
    stamp_to_ns,
)
from leapnbv_common.diagnostics import StageDiagnostics, rejects_bad_input
from leapnbv_common.node_params import declare_parameters, run_node
from leapnbv_common.qos import camera_input_qos, stage_input_qos, stage_output_qos
from leapnbv_common.stamp_cache import ExactStampPairer, StampCache
from leapnbv_msgs.msg import HumanMesh, PersonDetections, SceneGroundTruth
from leapnbv_perception.nodes.engine_loading import RetryingLoader
from leapnbv_perception.target_selection import select_target

PARAMETERS = {
    "backend": ("onnxruntime", "onnxruntime (CPU), tensorrt (Jetson) or ground_truth (simulator body)"),
    "model_file_path": ("", "SMPLer-X student ONNX (encoder + heads; see README for the tensor names)"),
    "body_model_path": ("", "SMPL-X body model .npz (SMPLX_NEUTRAL.npz, or the stand-in model)"),
    "engine_cache_dir": ("", "TensorRT engine cache folder (default: beside the ONNX file)"),
    "precision": ("fp16", "TensorRT precision: fp16 or fp32; the SMPL-X tail is always FP32"),
    "providers": (["CPUExecutionProvider"], "onnxruntime execution providers, in order of preference"),
    "intra_op_threads": (1, "onnxruntime intra-op threads (0 = its default)"),
    "box_scale": (1.25, "crop box scale about its centre (SMPLer-X 1.25, SMPLest-X 1.2)"),
    "unmirror_left_hand": (True, "un-mirror the left hand (SMPLer-X: true, SMPLest-X: false)"),
    "track_previous_target": (True, "follow the person who overlaps the last target, else the best score"),
    "min_track_iou": (0.3, "overlap with the last target needed to keep following it"),
    "cache_size": (10, "images kept while waiting for their detections"),
    "model_retry_period_s": (5.0, "retry loading a missing or broken model this often (0 = never)"),
}


class HmrNode(Node):
    def __init__(self) -> None:
        super().__init__("hmr_node")
        p = self.params = declare_parameters(self, PARAMETERS)
        self.diagnostics = StageDiagnostics(self, hardware_id=p["backend"])
        self.publisher = self.create_publisher(HumanMesh, "human_mesh", stage_output_qos())
        self.ground_truth = p["backend"] == "ground_truth"
        self.previous_box: Optional[np.ndarray] = None
        self.camera_k: Optional[np.ndarray] = None
        self.engine = RetryingLoader(self, self.diagnostics, f"HMR engine {p['model_file_path']!r} with body "
                                     f"model {p['body_model_path']!r}", self.load_engine, p["model_retry_period_s"])
        if self.ground_truth:
            self.pairer = ExactStampPairer(capacity=p["cache_size"])
            self.create_subscription(SceneGroundTruth, "ground_truth", self.on_ground_truth, stage_input_qos(10))
            self.create_subscription(CameraInfo, "camera_info", self.on_camera_info, camera_input_qos(1))
        else:
            self.images: StampCache = StampCache(p["cache_size"])
            self.create_subscription(Image, "image", self.on_image, camera_input_qos(p["cache_size"]))
        self.create_subscription(PersonDetections, "detections", self.on_detections, stage_input_qos(5))

    def load_engine(self):
        from leapnbv_perception.smplx_layer import SMPLXModel

        p = self.params
        if not p["body_model_path"]:
            raise FileNotFoundError("parameter body_model_path is empty: set it to SMPLX_NEUTRAL.npz")
        body_model = SMPLXModel.load(os.path.expanduser(p["body_model_path"]))
        if self.ground_truth:
            return body_model
        from leapnbv_perception.backends import create_backend
        from leapnbv_perception.hmr import HumanMeshEstimator

        backend = create_backend(p["backend"], p["model_file_path"], precision=p["precision"],
                                 providers=list(p["providers"]), engine_cache_dir=p["engine_cache_dir"] or None,
                                 intra_op_threads=p["intra_op_threads"])
        return HumanMeshEstimator(backend, body_model, box_scale=p["box_scale"],
                                  unmirror_left_hand=p["unmirror_left_hand"])

    @rejects_bad_input("bad_camera_info")
    def on_camera_info(self, msg: CameraInfo) -> None:
        self.camera_k = camera_info_to_k(msg)

    def on_image(self, msg: Image) -> None:
        self.images.put(stamp_to_ns(msg.header.stamp), msg)

    @rejects_bad_input("bad_ground_truth")
    def on_ground_truth(self, msg: SceneGroundTruth) -> None:
        pair = self.pairer.add_second(stamp_to_ns(msg.header.stamp), msg)
        if pair is not None:
            self.estimate(*pair)

    @rejects_bad_input("bad_detections")
    def on_detections(self, msg: PersonDetections) -> None:
        self.diagnostics.frame_in()
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
        boxes = np.array([detection_to_box(d) for d in detections.detections], np.float32).reshape(-1, 5)
        previous = self.previous_box if self.params["track_previous_target"] else None
        index = select_target(boxes, previous, self.params["min_track_iou"])
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
            model_id=os.path.basename(self.params["model_file_path"]))

    def ground_truth_mesh(self, box: np.ndarray, truth: SceneGroundTruth, image_size) -> HumanMeshArrays:
        """The simulator's body, already metric in the camera frame: its 'virtual' camera is the real one."""
        from leapnbv_perception.hmr_crop import process_box, xyxy_to_xywh
        from leapnbv_perception.smplx_layer import SMPLXParams

        if self.camera_k is None:
            raise ValueError("no camera_info received yet (ground-truth meshes use the real intrinsics)")
        k = self.camera_k
        params = SMPLXParams.from_axis_angle(
            np.asarray(truth.root_pose), np.asarray(truth.body_pose), np.asarray(truth.left_hand_pose),
            np.asarray(truth.right_hand_pose), np.asarray(truth.jaw_pose), np.asarray(truth.betas),
            np.asarray(truth.expression))
        body = self.engine.value
        translation = np.asarray(truth.translation, dtype=np.float32)
        vertices = body.forward(params).vertices + translation
        return HumanMeshArrays(
            vertices=vertices, faces=body.faces, virtual_intrinsics=(k[0, 0], k[1, 1], k[0, 2], k[1, 2]),
            image_size=image_size, detection=box,
            processed_box=process_box(xyxy_to_xywh(box[:4]), image_size[0], image_size[1],
                                      scale=self.params["box_scale"]),
            root_pose=truth.root_pose, body_pose=truth.body_pose, left_hand_pose=truth.left_hand_pose,
            right_hand_pose=truth.right_hand_pose, jaw_pose=truth.jaw_pose, betas=truth.betas,
            expression=truth.expression, cam_translation=translation, model_id="ground_truth")


def main(args=None) -> None:
    run_node(HmrNode, args)


if __name__ == "__main__":
    main()
