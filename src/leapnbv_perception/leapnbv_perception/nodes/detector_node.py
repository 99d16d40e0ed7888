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
from collections import OrderedDict
from typing import Callable, Dict, Optional, Sequence, Set, Tuple

import numpy as np
from rclpy.node import Node
from sensor_msgs.msg import Image
from std_msgs.msg import Header

from leapnbv_common.camera_pose import create_camera_pose_source
from leapnbv_common.contracts import DuplicateStampGuard, check_boxes, check_same_frame, refused
from leapnbv_common.conversions import (
    COLOUR_ENCODINGS,
    HumanMeshArrays,
    SerializedImage,
    box_to_detection,
    check_image,
    human_mesh_to_arrays,
    image_to_rgb,
    input_stamp_msgs,
    scene_ground_truth_to_arrays,
    serialized_header_stamp_ns,
    stamp_to_ns,
)
from leapnbv_common.diagnostics import StageDiagnostics, rejects_bad_input
from leapnbv_common.node_params import NodeParams, run_node
from leapnbv_common.process_tuning import tune_node_process
from leapnbv_common.pulled_input import HOUSEKEEPING_PERIOD_S, PulledInput
from leapnbv_common.qos import camera_input_qos, stage_input_qos, stage_output_qos
from leapnbv_common.stamp_cache import STAMP_RESTART_NS, ExactStampPairer
from leapnbv_common.topics import CAMERA_POSE, DETECTIONS, GROUND_TRUTH, HUMAN_MESH_METRIC, VIEW_CANDIDATES
from leapnbv_msgs.msg import HumanMesh, InputStamp, PersonDetections, SceneGroundTruth, ViewCandidates
from leapnbv_perception.box_tracking import DetectionSchedule, camera_motion, carry_box
from leapnbv_perception.nodes.engine_loading import RetryingLoader, create_engine_backend
from leapnbv_perception.params import DetectorParams

MIN_IN_FLIGHT_TIMEOUT_S = 0.05  # an admitted frame counts at least this long (see FramesInFlight)
WAITING_CHECK_PERIOD_S = 0.05  # how often a waiting frame checks whether an in-flight frame timed out
CARRY_POSE_CACHE = 90  # camera poses remembered for carrying boxes (3 s at 30 FPS)
TRUTH_WAIT_S = 1.0  # ground truth: how long an image waits for the truth of its stamp (pulled every 20 ms)


class FramesInFlight:
    """The admitted frames whose final output (view candidates) has not come back, by stamp.

    A final output of stamp s completes every admitted frame stamped s or earlier (a stage never
    publishes an older frame after a newer one). A frame refused downstream (no person, a bad
    input, no ground plane) never comes back: it stops counting after twice the graph's recent
    time to answer (an average of the admitted frames that came back), at most ``timeout_s``, so a
    refused frame blocks the next one only briefly.
    """

    def __init__(self) -> None:
        self._admitted: Dict[int, float] = OrderedDict()  # stamp -> admitted at (monotonic s), oldest first
        self.planner_answered = False
        self.timed_out = 0
        self.answer_s: Optional[float] = None  # moving average of the time from admission to the answer

    def __len__(self) -> int:
        return len(self._admitted)

    def timeout(self, timeout_s: float) -> float:
        if self.answer_s is None:
            return timeout_s
        return min(timeout_s, max(MIN_IN_FLIGHT_TIMEOUT_S, 2.0 * self.answer_s))

    def expire(self, now_s: float, timeout_s: float) -> None:
        limit = self.timeout(timeout_s)
        for stamp, since in list(self._admitted.items()):
            if now_s - since >= limit:
                del self._admitted[stamp]
                self.timed_out += 1

    def full(self, limit: int, now_s: float, timeout_s: float) -> bool:
        """Whether no further frame may be admitted now (never before the planner answered once)."""
        if limit <= 0 or not self.planner_answered:
            return False
        self.expire(now_s, timeout_s)
        return len(self._admitted) >= limit

    def admit(self, stamp_ns: int, now_s: float) -> None:
        self._admitted[stamp_ns] = now_s

    def done(self, stamp_ns: int, now_s: float) -> None:
        self.planner_answered = True
        answered = self._admitted.get(stamp_ns)
        if answered is not None:
            took = now_s - answered
            self.answer_s = took if self.answer_s is None else 0.8 * self.answer_s + 0.2 * took
        for stamp in [s for s in self._admitted if s <= stamp_ns]:
            del self._admitted[stamp]


class DetectorNode(Node):
    def __init__(self) -> None:
        super().__init__("detector_node")
        self.params = NodeParams(self, DetectorParams, self.on_params_change)
        p = self.params.value
        self.diagnostics = StageDiagnostics(self, hardware_id=p.backend)
        self.publisher = self.create_publisher(PersonDetections, DETECTIONS, stage_output_qos())
        self.in_flight = FramesInFlight()
        self.last_published: Optional[int] = None
        self.ground_truth = p.backend == "ground_truth"
        self.stamps = DuplicateStampGuard()  # one content per stamp and input (contracts)
        if self.ground_truth:
            self.detector = None
            self.pairer = ExactStampPairer(capacity=10, first_name="image", second_name="ground_truth",
                                           on_drop=self.diagnostics.drop_callback())
            # The truth comes at camera rate before its image: pulled when the image comes
            # (leapnbv_common.pulled_input), so it does not wake the node a second time per frame.
            self.truth_input = PulledInput.create(self, SceneGroundTruth, GROUND_TRUTH, self.on_ground_truth,
                                                  stage_input_qos(10))
            self.truth_wait_since: Optional[float] = None  # an image waits for its truth (DDS does not order topics)
            self.truth_timer = self.create_timer(0.02, self.pull_late_truth)
            self.truth_timer.cancel()  # runs only while an image waits
            # A bad truth is counted within HOUSEKEEPING_PERIOD_S even while no image comes.
            self.create_timer(HOUSEKEEPING_PERIOD_S, self.truth_input.drain)
            if p.timing_stand_in:  # a benchmark: the real network's cost, the truth's boxes
                self.detector = RetryingLoader(self, self.diagnostics, "timing stand-in detector model "
                                               + repr(p.model_file_path), self.load_timing_detector,
                                               p.model_retry_period_s)
        else:
            self.detector = RetryingLoader(self, self.diagnostics, "detector model " + repr(p.model_file_path),
                                           self.load_detector, p.model_retry_period_s)
        # Detect less often: the target's box carried by its mesh's image motion between detections.
        self.schedule = DetectionSchedule(p.detect_every_n_frames, p.carry_min_confidence)
        self.carrying = p.detect_every_n_frames > 1
        self.last_mesh: Optional[Tuple[int, str, HumanMeshArrays]] = None  # (stamp, frame_id, arrays)
        if self.carrying:
            # Both pulled when a frame is decided: they do not wake the node.
            self.mesh_input = PulledInput.create(self, HumanMesh, HUMAN_MESH_METRIC, self.on_mesh, stage_input_qos(1))
            self.camera_poses = create_camera_pose_source(p.camera_pose_source, self, CARRY_POSE_CACHE)
            self.pose_input = PulledInput.adopt(self, self.camera_poses)
            self.get_logger().info(f"detecting one admitted frame in {p.detect_every_n_frames}; the target's box is "
                                   f"carried into the others (meshes up to {p.carry_max_age_s:g} s old)")
        # The newest frame only (depth 1): frames that came while the node was busy are counted as not taken.
        # Read in place from its serialized bytes (SerializedImage): it is checked, never deserialized.
        self.create_subscription(Image, "image", self.on_image, camera_input_qos(1), raw=True)
        # The planner's answers free the graph: the newest frame that waited for it goes in at once.
        self.create_subscription(ViewCandidates, VIEW_CANDIDATES, self.on_final_output, stage_input_qos(10), raw=True)
        self.waiting: Optional[Tuple[int, Callable[[], None]]] = None  # (stamp, work) of the newest frame held back
        # An answer releases the waiting frame at once (on_final_output); this timer only catches an
        # in-flight frame that timed out (refused downstream), and runs only while a frame waits.
        self.waiting_timer = self.create_timer(WAITING_CHECK_PERIOD_S, self.admit_waiting)
        self.waiting_timer.cancel()

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
        detector = self.detector.value if self.detector is not None else None
        if detector is not None:
            detector.score_threshold = params.score_threshold
            detector.iou_threshold = params.iou_threshold
            detector.max_detections = params.max_detections

    def on_final_output(self, cdr: bytes) -> None:
        """The planner finished a frame (view candidates of its stamp): it and older ones leave the graph."""
        self.in_flight.done(serialized_header_stamp_ns(cdr), time.monotonic())
        self.admit_waiting()

    def admit_waiting(self) -> None:
        """The frame held back goes in once the graph has room (an answer came, or a frame timed out)."""
        if self.waiting is not None:
            p = self.params.value
            if not self.in_flight.full(p.max_frames_in_flight, time.monotonic(), p.in_flight_timeout_s):
                (_, work), self.waiting = self.waiting, None
                work()
        if self.waiting is None:
            self.waiting_timer.cancel()

    def admit(self, stamp_ns: int, work: Callable[[], None]) -> bool:
        """Whether the graph takes this frame now. A frame older than one published is dropped; while
        the graph is full, the newest frame waits (``work`` runs it when there is room) and the one
        it replaces is dropped; both counted by reason."""
        if self.last_published is not None and stamp_ns <= self.last_published:
            if self.last_published - stamp_ns >= STAMP_RESTART_NS:  # the stamps started over (a replay, a reset)
                self.last_published = None
                self.in_flight = FramesInFlight()
            else:
                self.diagnostics.drop("duplicate_stamp" if stamp_ns == self.last_published else "older_than_published")
                return False
        p = self.params.value
        if self.in_flight.full(p.max_frames_in_flight, time.monotonic(), p.in_flight_timeout_s):
            if self.waiting is not None:
                if self.waiting[0] >= stamp_ns:
                    self.diagnostics.drop("graph_busy")
                    return False
                self.diagnostics.drop("graph_busy")  # the frame that waited: this newer one takes its place
            self.waiting = (stamp_ns, work)
            if self.waiting_timer.is_canceled():
                self.waiting_timer.reset()
            return False
        if self.waiting is not None and self.waiting[0] <= stamp_ns:
            self.waiting = None  # a newer frame goes in: the one that waited is superseded
            self.diagnostics.drop("graph_busy")
        return True

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
            pose_a, pose_b = self.camera_poses.pose_at(mesh_stamp), self.camera_poses.pose_at(stamp)
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
        if self.schedule.should_detect(carried):
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
        self.last_published = stamp
        if len(boxes):  # an empty frame ends here (hmr_node has no person to work on)
            self.in_flight.admit(stamp, time.monotonic())
        self.diagnostics.frame_out(header.stamp, out.compute_time_ms)

    @rejects_bad_input("bad_image")
    def on_image(self, cdr: bytes, info) -> None:
        self.diagnostics.frame_in()
        self.diagnostics.input_seen("image", info)
        started = time.perf_counter()
        image = SerializedImage(cdr)  # a ConversionError counts as bad_image
        # The colour contract (a view, no copy), ground truth too
        if refused(self.diagnostics, "bad_image", check_image, image, COLOUR_ENCODINGS, "colour") or \
                refused(self.diagnostics, "bad_image", self.stamps.check, "image", image):
            return
        stamp = stamp_to_ns(image.header.stamp)
        if self.ground_truth:
            self.truth_input.drain()
            pair = self.pairer.add_first(stamp, image)
            if pair is not None:
                self.publish_ground_truth(*pair)
            else:
                self.truth_wait_since = time.monotonic()
                if self.truth_timer.is_canceled():
                    self.truth_timer.reset()
            return
        if self.detector.value is None:
            self.diagnostics.reject("engine_not_ready", self.diagnostics.engine_state)
            return
        if self.admit(stamp, lambda: self.detect(image)):
            self.detect(image, started)

    @rejects_bad_input("bad_image")
    def detect(self, image: SerializedImage, started: Optional[float] = None) -> None:
        if started is None:
            started = time.perf_counter()
        carried = self.carried_box(image)
        if carried is not None:
            self.publish(image.header, image.width, image.height, carried[0], started, carried[1])
            return
        rgb = image_to_rgb(image)
        self.publish(image.header, image.width, image.height, self.detector.value.detect(rgb), started)

    def pull_late_truth(self) -> None:
        """While an image waits for its truth: pull again (for TRUTH_WAIT_S at most)."""
        self.truth_input.drain()
        if self.truth_wait_since is None or time.monotonic() - self.truth_wait_since >= TRUTH_WAIT_S:
            self.truth_wait_since = None
            self.truth_timer.cancel()

    @rejects_bad_input("bad_ground_truth")
    def on_ground_truth(self, msg: SceneGroundTruth, info) -> None:
        self.diagnostics.input_seen("ground_truth", info)
        # The contract: finite values, a box or none
        if refused(self.diagnostics, "bad_ground_truth", scene_ground_truth_to_arrays, msg) or \
                refused(self.diagnostics, "bad_ground_truth", self.stamps.check, "ground_truth", msg):
            return
        pair = self.pairer.add_second(stamp_to_ns(msg.header.stamp), msg)
        if pair is not None:
            self.truth_wait_since = None
            self.publish_ground_truth(*pair)

    @rejects_bad_input("bad_ground_truth")
    def publish_ground_truth(self, image: SerializedImage, truth: SceneGroundTruth) -> None:
        started = time.perf_counter()
        stamp = stamp_to_ns(image.header.stamp)
        self.pairer.drop_older_than(stamp)  # frames older than this pair can no longer be the newest
        if refused(self.diagnostics, "bad_ground_truth", check_same_frame, "image", image.header.frame_id,
                   "ground truth", truth.header.frame_id):
            return
        if not self.admit(stamp, lambda: self.publish_ground_truth(image, truth)):
            return
        carried = self.carried_box(image)
        if carried is not None:
            self.publish(image.header, image.width, image.height, carried[0], started, carried[1])
            return
        if self.detector is not None:  # timing stand-in: pay the network's cost, keep the truth's boxes
            if self.detector.value is None:
                self.diagnostics.reject("engine_not_ready", self.diagnostics.engine_state)
                return
            self.detector.value.detect(image_to_rgb(image))
        # The truth gives the box: the image's pixels are not read (only checked, in on_image).
        box = scene_ground_truth_to_arrays(truth).person_box  # all zero when no person is visible
        visible = box[2] > box[0] and box[3] > box[1]
        if visible and refused(self.diagnostics, "bad_ground_truth", check_boxes, box, (image.width, image.height),
                               "ground-truth person box"):
            return
        boxes = np.array([[box[0], box[1], box[2], box[3], 1.0]], np.float32)
        self.publish(image.header, image.width, image.height, boxes if visible else np.zeros((0, 5), np.float32),
                     started)


def main(args=None) -> None:
    tune_node_process()  # one BLAS thread, image buffers reused (leapnbv_common.process_tuning)
    run_node(DetectorNode, args)


if __name__ == "__main__":
    main()
