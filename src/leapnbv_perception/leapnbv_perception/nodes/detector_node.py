"""detector_node: colour image -> PersonDetections (a detector engine, or the simulator's ground truth).

Parameters: :class:`leapnbv_perception.params.DetectorParams`. The thresholds change at runtime
(``ros2 param set``); the backend, the model and the detector family are set at start-up.
"""
from __future__ import annotations

import time
from typing import Set

import numpy as np
from rclpy.node import Node
from sensor_msgs.msg import Image

from leapnbv_common.contracts import DuplicateStampGuard, check_boxes, check_same_frame, refused
from leapnbv_common.conversions import (
    COLOUR_ENCODINGS,
    box_to_detection,
    check_image,
    image_to_rgb,
    scene_ground_truth_to_arrays,
    stamp_to_ns,
)
from leapnbv_common.diagnostics import StageDiagnostics, rejects_bad_input
from leapnbv_common.node_params import NodeParams, run_node
from leapnbv_common.qos import camera_input_qos, stage_input_qos, stage_output_qos
from leapnbv_common.stamp_cache import ExactStampPairer
from leapnbv_common.topics import DETECTIONS, GROUND_TRUTH
from leapnbv_msgs.msg import PersonDetections, SceneGroundTruth
from leapnbv_perception.nodes.engine_loading import RetryingLoader, create_engine_backend
from leapnbv_perception.params import DetectorParams


class DetectorNode(Node):
    def __init__(self) -> None:
        super().__init__("detector_node")
        self.params = NodeParams(self, DetectorParams, self.on_params_change)
        p = self.params.value
        self.diagnostics = StageDiagnostics(self, hardware_id=p.backend)
        self.publisher = self.create_publisher(PersonDetections, DETECTIONS, stage_output_qos())
        self.ground_truth = p.backend == "ground_truth"
        self.stamps = DuplicateStampGuard()  # one content per stamp and input (contracts)
        if self.ground_truth:
            self.detector = None
            self.pairer = ExactStampPairer(capacity=10)
            self.create_subscription(SceneGroundTruth, GROUND_TRUTH, self.on_ground_truth, stage_input_qos(10))
        else:
            self.detector = RetryingLoader(self, self.diagnostics, "detector model " + repr(p.model_file_path),
                                           self.load_detector, p.model_retry_period_s)
        # Ground truth must see every frame it pairs with; an engine takes the latest frame only.
        self.create_subscription(Image, "image", self.on_image, camera_input_qos(5 if self.ground_truth else 1))

    def load_detector(self):
        from leapnbv_perception.detector import PersonDetector

        p = self.params.value
        return PersonDetector(create_engine_backend(p), p.score_threshold, p.iou_threshold, p.max_detections,
                              family=p.detector_family, multi_label=p.multi_label)

    def on_params_change(self, params: DetectorParams, changed: Set[str]) -> None:
        """The thresholds apply from the next frame (the rest is read-only)."""
        detector = self.detector.value if self.detector is not None else None
        if detector is not None:
            detector.score_threshold = params.score_threshold
            detector.iou_threshold = params.iou_threshold
            detector.max_detections = params.max_detections

    def publish(self, image: Image, boxes: np.ndarray, started: float) -> None:
        out = PersonDetections(header=image.header, image_width=image.width, image_height=image.height)
        out.detections = [box_to_detection(b) for b in boxes]
        out.backend = self.params.value.backend
        out.compute_time_ms = (time.perf_counter() - started) * 1e3
        self.publisher.publish(out)
        self.diagnostics.frame_out(image.header.stamp, out.compute_time_ms)

    @rejects_bad_input("bad_image")
    def on_image(self, msg: Image) -> None:
        self.diagnostics.frame_in()
        started = time.perf_counter()
        # The colour contract (a view, no copy), ground truth too
        if refused(self.diagnostics, "bad_image", check_image, msg, COLOUR_ENCODINGS, "colour") or \
                refused(self.diagnostics, "bad_image", self.stamps.check, "image", msg):
            return
        if self.ground_truth:
            pair = self.pairer.add_first(stamp_to_ns(msg.header.stamp), msg)
            if pair is not None:
                self.publish_ground_truth(*pair)
            return
        if self.detector.value is None:
            self.diagnostics.reject("engine_not_ready", self.diagnostics.engine_state)
            return
        rgb = image_to_rgb(msg)
        self.publish(msg, self.detector.value.detect(rgb), started)

    @rejects_bad_input("bad_ground_truth")
    def on_ground_truth(self, msg: SceneGroundTruth) -> None:
        # The contract: finite values, a box or none
        if refused(self.diagnostics, "bad_ground_truth", scene_ground_truth_to_arrays, msg) or \
                refused(self.diagnostics, "bad_ground_truth", self.stamps.check, "ground_truth", msg):
            return
        pair = self.pairer.add_second(stamp_to_ns(msg.header.stamp), msg)
        if pair is not None:
            self.publish_ground_truth(*pair)

    def publish_ground_truth(self, image: Image, truth: SceneGroundTruth) -> None:
        started = time.perf_counter()
        if refused(self.diagnostics, "bad_ground_truth", check_same_frame, "image", image.header.frame_id,
                   "ground truth", truth.header.frame_id):
            return
        box = scene_ground_truth_to_arrays(truth).person_box  # all zero when no person is visible
        visible = box[2] > box[0] and box[3] > box[1]
        if visible and refused(self.diagnostics, "bad_ground_truth", check_boxes, box, (image.width, image.height),
                               "ground-truth person box"):
            return
        boxes = np.array([[box[0], box[1], box[2], box[3], 1.0]], np.float32)
        self.publish(image, boxes if visible else np.zeros((0, 5), np.float32), started)


def main(args=None) -> None:
    run_node(DetectorNode, args)


if __name__ == "__main__":
    main()
