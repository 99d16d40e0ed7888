"""detector_node: colour image -> PersonDetections (YOLOv8 engine, or the simulator's ground truth)."""
from __future__ import annotations

import time

import numpy as np
from rclpy.node import Node
from sensor_msgs.msg import Image

from leapnbv_common.conversions import box_to_detection, image_to_rgb, stamp_to_ns
from leapnbv_common.diagnostics import StageDiagnostics, rejects_bad_input
from leapnbv_common.node_params import declare_parameters, run_node
from leapnbv_common.qos import camera_input_qos, stage_input_qos, stage_output_qos
from leapnbv_common.stamp_cache import ExactStampPairer
from leapnbv_msgs.msg import PersonDetections, SceneGroundTruth
from leapnbv_perception.nodes.engine_loading import RetryingLoader

PARAMETERS = {
    "backend": ("onnxruntime", "onnxruntime (CPU), tensorrt (Jetson) or ground_truth (simulator boxes)"),
    "model_file_path": ("", "YOLOv8 ONNX export (input 'images' 1x3x640x640, output 'output0' 1x84x8400)"),
    "engine_cache_dir": ("", "TensorRT engine cache folder (default: beside the ONNX file)"),
    "precision": ("fp16", "TensorRT precision: fp16 or fp32 (onnxruntime runs the model as exported)"),
    "providers": (["CPUExecutionProvider"], "onnxruntime execution providers, in order of preference"),
    "intra_op_threads": (1, "onnxruntime intra-op threads (0 = its default)"),
    "score_threshold": (0.25, "minimum person score"),
    "iou_threshold": (0.5, "NMS IoU threshold (ultralytics uses 0.7; 0.5 suits people)"),
    "max_detections": (20, "most person boxes per frame"),
    "model_retry_period_s": (5.0, "retry loading a missing or broken model this often (0 = never)"),
}


class DetectorNode(Node):
    def __init__(self) -> None:
        super().__init__("detector_node")
        self.params = declare_parameters(self, PARAMETERS)
        self.diagnostics = StageDiagnostics(self, hardware_id=self.params["backend"])
        self.publisher = self.create_publisher(PersonDetections, "detections", stage_output_qos())
        self.ground_truth = self.params["backend"] == "ground_truth"
        if self.ground_truth:
            self.detector = None
            self.pairer = ExactStampPairer(capacity=10)
            self.create_subscription(SceneGroundTruth, "ground_truth", self.on_ground_truth, stage_input_qos(10))
        else:
            self.detector = RetryingLoader(self, self.diagnostics, "detector model " + repr(
                self.params["model_file_path"]), self.load_detector, self.params["model_retry_period_s"])
        # Ground truth must see every frame it pairs with; an engine takes the latest frame only.
        self.create_subscription(Image, "image", self.on_image, camera_input_qos(5 if self.ground_truth else 1))

    def load_detector(self):
        from leapnbv_perception.backends import create_backend
        from leapnbv_perception.detector import PersonDetector

        p = self.params
        backend = create_backend(p["backend"], p["model_file_path"], precision=p["precision"],
                                 providers=list(p["providers"]), engine_cache_dir=p["engine_cache_dir"] or None,
                                 intra_op_threads=p["intra_op_threads"])
        return PersonDetector(backend, p["score_threshold"], p["iou_threshold"], p["max_detections"])

    def publish(self, image: Image, boxes: np.ndarray, started: float) -> None:
        out = PersonDetections(header=image.header, image_width=image.width, image_height=image.height)
        out.detections = [box_to_detection(b) for b in boxes]
        out.backend = self.params["backend"]
        out.compute_time_ms = (time.perf_counter() - started) * 1e3
        self.publisher.publish(out)
        self.diagnostics.frame_out(image.header.stamp, out.compute_time_ms)

    @rejects_bad_input("bad_image")
    def on_image(self, msg: Image) -> None:
        self.diagnostics.frame_in()
        started = time.perf_counter()
        if self.ground_truth:
            if msg.width == 0 or msg.height == 0:
                raise ValueError(f"empty image {msg.width}x{msg.height}")
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
        pair = self.pairer.add_second(stamp_to_ns(msg.header.stamp), msg)
        if pair is not None:
            self.publish_ground_truth(*pair)

    def publish_ground_truth(self, image: Image, truth: SceneGroundTruth) -> None:
        started = time.perf_counter()
        box = truth.person_box
        visible = box.x_max > box.x_min and box.y_max > box.y_min
        boxes = np.array([[box.x_min, box.y_min, box.x_max, box.y_max, 1.0]], np.float32)
        self.publish(image, boxes if visible else np.zeros((0, 5), np.float32), started)


def main(args=None) -> None:
    run_node(DetectorNode, args)


if __name__ == "__main__":
    main()
