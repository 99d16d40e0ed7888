"""detector_node: colour image -> PersonDetections (a detector engine, or the simulator's ground truth).

The detector is the graph's first stage, so it decides which camera frames the graph works on
(latest-frame scheduling, docs/ARCHITECTURE.md "Timing"): the image subscription keeps only the
newest frame (depth 1), a frame older than one already published is dropped, and once the planner
answers (``view_candidates``), at most ``max_frames_in_flight`` admitted frames are in the graph at
a time: while the graph is full the newest frame waits and goes in the moment an answer comes, and
the frames it replaces are dropped before any stage spends work on them. Every drop is counted on
/diagnostics (``dropped.<reason>``).

Parameters: :class:`leapnbv_perception.params.DetectorParams`. The thresholds and the admission
settings change at runtime (``ros2 param set``); the backend, the model and the detector family
are set at start-up.
"""
from __future__ import annotations

import dataclasses
import time
from typing import Optional, Sequence, Set, Tuple

import numpy as np
from sensor_msgs.msg import Image
from std_msgs.msg import Header

from leapnbv_common.camera_pose import create_camera_pose_source
from leapnbv_common.contracts import ContractError, check_same_frame, refused
from leapnbv_common.conversions import (
    COLOUR_ENCODINGS,
    HumanMeshArrays,
    SerializedImage,
    box_to_detection,
    human_mesh_to_arrays,
    image_to_rgb,
    input_stamp_msgs,
    serialized_header_stamp_ns,
    stamp_to_ns,
)
from leapnbv_common.diagnostics import rejects_bad_input
from leapnbv_common.managed_node import ManagedNode
from leapnbv_common.node_params import run_node
from leapnbv_common.process_tuning import tune_node_process
from leapnbv_common.pulled_input import PulledInput
from leapnbv_common.qos import camera_input_qos, stage_input_qos, stage_output_qos
from leapnbv_common.stage import Frame, KeyInput, Stage
from leapnbv_common.stage_inputs import checked_serialized_image
from leapnbv_common.topics import CAMERA_POSE, DETECTIONS, HUMAN_MESH_METRIC, VIEW_CANDIDATES
from leapnbv_msgs.msg import HumanMesh, InputStamp, PersonDetections, ViewCandidates
from leapnbv_perception.admission import Admission
from leapnbv_perception.backends.ground_truth import GROUND_TRUTH_BACKEND, ground_truth_boxes, truth_companion
from leapnbv_perception.box_tracking import DetectionSchedule, camera_motion, carry_box
from leapnbv_perception.nodes.engine_loading import create_engine_backend, load_in_configure
from leapnbv_perception.params import DetectorParams

WAITING_CHECK_PERIOD_S = 0.05  # how often a waiting frame checks whether an in-flight frame timed out
CARRY_POSE_CACHE = 90  # camera poses remembered for carrying boxes (3 s at 30 FPS)


class DetectorNode(ManagedNode):
    def __init__(self) -> None:
        super().__init__("detector_node", DetectorParams)

    def configure_stage(self) -> None:
        """The detector engine is loaded here: a missing or broken model fails the configure with its path and the
        node stays unconfigured (retried: leapnbv_common.managed_node)."""
        p = self.params.value
        self.diagnostics.hardware_id = p.backend
        self.admission = Admission(self.diagnostics.drop)
        self.ground_truth = p.backend == GROUND_TRUTH_BACKEND
        self.detector = None
        if not self.ground_truth:
            self.detector = load_in_configure(self, "detector model " + repr(p.model_file_path),
                                                             self.load_detector)
        elif p.timing_stand_in:  # a benchmark: the real network's cost, the truth's boxes
            self.detector = load_in_configure(
                self, "timing stand-in detector model " + repr(p.model_file_path), self.load_timing_detector)
        self.publisher = self.create_lifecycle_publisher(PersonDetections, DETECTIONS, stage_output_qos())
        # Detect less often: the target's box carried by its mesh's image motion between detections.
        self.schedule = DetectionSchedule(p.detect_every_n_frames, p.carry_min_confidence)
        self.carrying = p.detect_every_n_frames > 1
        self.last_mesh: Optional[Tuple[int, str, HumanMeshArrays]] = None  # (stamp, frame_id, arrays)
        # The newest frame only (depth 1): frames that came while the node was busy are counted as not taken.
        # Read in place from its serialized bytes (SerializedImage): it is checked, never deserialized. With the
        # ground-truth backend, the simulator's truth of its stamp (pulled when the image comes).
        self.stage = Stage(self, KeyInput("image", Image, "image",
                                          lambda cdr: checked_serialized_image(cdr, COLOUR_ENCODINGS, "colour"),
                                          camera_input_qos(1), raw=True),
                           [truth_companion(10)] if self.ground_truth else [], self.on_frame,
                           frame_error_reason="bad_ground_truth" if self.ground_truth else "bad_image",
                           on_restart=self.admission.reset)

    def activate_stage(self) -> None:
        p = self.params.value
        if self.carrying:
            # Both pulled when a frame is decided: they do not wake the node.
            self.mesh_input = PulledInput.create(self, HumanMesh, HUMAN_MESH_METRIC, self.on_mesh, stage_input_qos(1))
            self.camera_poses = create_camera_pose_source(p.camera_pose_source, self, CARRY_POSE_CACHE)
            self.pose_input = PulledInput.adopt(self, self.camera_poses)
            self.get_logger().info(f"detecting one admitted frame in {p.detect_every_n_frames}; the target's box is "
                                   f"carried into the others (meshes up to {p.carry_max_age_s:g} s old)")
        self.stage.start()
        # The planner's answers free the graph: the newest frame that waited for it goes in at once.
        self.create_subscription(ViewCandidates, VIEW_CANDIDATES, self.on_final_output, stage_input_qos(10), raw=True)
        # An answer releases the waiting frame at once (on_final_output); this timer only catches an
        # in-flight frame that timed out (refused downstream), and runs only while a frame waits.
        self.waiting_timer = self.create_timer(WAITING_CHECK_PERIOD_S, self.admit_waiting)
        self.waiting_timer.cancel()

    def deactivate_stage(self) -> None:
        self.stage.stop()
        self.admission.reset()

    def cleanup_stage(self) -> None:
        self.detector = None  # the engine's memory goes with it

    def load_detector(self):
        from leapnbv_perception.detector import PersonDetector

        p = self.params.value
        return PersonDetector(create_engine_backend(p), p.score_threshold, p.iou_threshold, p.max_detections,
                              family=p.detector_family, multi_label=p.multi_label)

    def load_timing_detector(self):
        """The timing stand-in's engine: onnxruntime, whatever the (ground_truth) backend says."""
        from leapnbv_perception.detector import PersonDetector

        p = self.params.value
        return PersonDetector(create_engine_backend(dataclasses.replace(p, backend="onnxruntime")), p.score_threshold,
                              p.iou_threshold, p.max_detections, family=p.detector_family, multi_label=p.multi_label)

    def on_params_change(self, params: DetectorParams, changed: Set[str]) -> None:
        """The thresholds, the carrying limits and the admission settings apply from the next frame (the
        rest is read-only)."""
        self.schedule.min_confidence = params.carry_min_confidence
        detector = self.detector
        if detector is not None:
            detector.score_threshold = params.score_threshold
            detector.iou_threshold = params.iou_threshold
            detector.max_detections = params.max_detections

    @rejects_bad_input("bad_human_mesh")
    def on_mesh(self, msg: HumanMesh, info) -> None:
        """The newest metric mesh of the target (raster_node), kept to carry its box into later frames."""
        self.diagnostics.input_seen("human_mesh_metric", info)
        stamp = stamp_to_ns(msg.header.stamp)
        if self.last_mesh is None or stamp > self.last_mesh[0]:
            self.last_mesh = (stamp, msg.header.frame_id, human_mesh_to_arrays(msg))

    def carried_box(self, image: SerializedImage) -> Optional[Tuple[np.ndarray, list]]:
        """(boxes (1, 5), inputs) when this frame's target box is carried instead of detected; None: detect.

        Carried from the newest metric mesh of a frame at most carry_max_age_s older, by its image motion
        and the camera poses of both frames, while the schedule allows and the carried box is trusted."""
        if not self.carrying:
            return None
        self.mesh_input.drain()
        if self.pose_input is not None:
            self.pose_input.drain()
        stamp = stamp_to_ns(image.header.stamp)
        carried, refused_because = None, "no_mesh"
        if self.last_mesh is not None:
            mesh_stamp, mesh_frame, mesh = self.last_mesh
            pose_a = self.camera_poses.pose_at(mesh_stamp, mesh_frame)
            pose_b = self.camera_poses.pose_at(stamp, image.header.frame_id)
            if not 0 < stamp - mesh_stamp <= self.params.value.carry_max_age_s * 1e9:
                refused_because = "mesh_too_old"
            elif mesh_frame != image.header.frame_id or tuple(mesh.image_size) != (image.width, image.height):
                refused_because = "mesh_of_another_camera"
            elif pose_a is None or pose_b is None:
                refused_because = "no_camera_pose"
            else:
                fx, fy, cx, cy = mesh.virtual_intrinsics  # the metric mesh carries the camera's intrinsics
                K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
                motion = camera_motion((pose_a.rotation, pose_a.position), (pose_b.rotation, pose_b.position))
                carried = carry_box(mesh.detection[:4], mesh.vertices, K, K, (image.width, image.height), motion)
                refused_because = "mesh_not_in_view" if carried is None else "low_confidence"
        if carried is None or self.schedule.should_detect(carried):
            if not self.schedule.due():  # a frame that could have been carried: say why it was not
                self.diagnostics.count("detected_instead." + refused_because)
            self.schedule.record(True)
            return None
        self.schedule.record(False)
        self.diagnostics.count("boxes_carried")
        boxes = np.array([[*carried.box, mesh.detection[4]]], np.float32)
        inputs = [(HUMAN_MESH_METRIC, mesh_stamp, InputStamp.CARRIED), (CAMERA_POSE, stamp, InputStamp.SAME_FRAME),
                  (CAMERA_POSE, mesh_stamp, InputStamp.CARRIED)]
        return boxes, inputs

    def publish(self, header: Header, width: int, height: int, boxes: np.ndarray, started: float,
                inputs: Sequence[tuple] = ()) -> None:
        stamp = stamp_to_ns(header.stamp)
        out = PersonDetections(header=header, image_width=width, image_height=height, inputs=input_stamp_msgs(inputs))
        out.detections = [box_to_detection(b) for b in boxes]
        out.backend = self.params.value.backend
        out.compute_time_ms = (time.perf_counter() - started) * 1e3
        self.publisher.publish(out)
        if len(boxes):  # an empty frame ends here (hmr_node has no person to work on)
            self.admission.admitted(stamp, time.monotonic())
        self.diagnostics.frame_out(header.stamp, out.compute_time_ms)

    def on_final_output(self, cdr: bytes) -> None:
        """The planner finished a frame (view candidates of its stamp): it and older ones leave the graph."""
        self.admission.answered(serialized_header_stamp_ns(cdr), time.monotonic())
        self.admit_waiting()

    def admit_waiting(self) -> None:
        """The frame held back goes in once the graph has room (an answer came, or a frame timed out)."""
        p = self.params.value
        work = self.admission.release(time.monotonic(), p.max_frames_in_flight, p.in_flight_timeout_s)
        if work is not None:
            work()
        if self.admission.waiting is None:
            self.waiting_timer.cancel()

    def on_frame(self, frame: Frame) -> None:
        """A checked colour frame (with its truth, for the ground-truth backend): into the graph now, held back
        while the graph is full, or dropped (latest-frame scheduling: leapnbv_perception.admission)."""
        started = time.perf_counter()
        image: SerializedImage = frame["image"]
        if self.ground_truth:
            truth = frame.received("ground_truth")  # always there: a frame without its truth is dropped
            if truth is None or refused(self.diagnostics, "bad_ground_truth", check_same_frame, "image",
                                        image.header.frame_id, "ground truth", truth.frame_id):
                return
        p = self.params.value
        if self.admission.offer(frame.stamp_ns, lambda: self.guarded_detect(frame), time.monotonic(),
                                p.max_frames_in_flight, p.in_flight_timeout_s):
            self.detect(frame, started)
        elif self.admission.waiting is not None and self.waiting_timer.is_canceled():
            self.waiting_timer.reset()

    @rejects_bad_input("bad_image")
    def guarded_detect(self, frame: Frame) -> None:
        """A held-back frame, run from the admission timer or an answer's callback."""
        self.detect(frame)

    def detect(self, frame: Frame, started: Optional[float] = None) -> None:
        if started is None:
            started = time.perf_counter()
        image: SerializedImage = frame["image"]
        carried = self.carried_box(image)
        if carried is not None:
            self.publish(image.header, image.width, image.height, carried[0], started, carried[1])
            return
        if self.detector is not None:  # the engine's boxes (a timing stand-in: its cost, the truth's boxes)
            boxes = self.detector.detect(image_to_rgb(image))
        if self.ground_truth:
            # The truth gives the box: the image's pixels are not read (only checked on arrival).
            try:
                boxes = ground_truth_boxes(frame["ground_truth"], (image.width, image.height))
            except ContractError as error:
                self.diagnostics.reject("bad_ground_truth", error.detail)
                return
        self.publish(image.header, image.width, image.height, boxes, started)


def main(args=None) -> None:
    tune_node_process()  # one BLAS thread, image buffers reused (leapnbv_common.process_tuning)
    run_node(DetectorNode, args)


if __name__ == "__main__":
    main()
