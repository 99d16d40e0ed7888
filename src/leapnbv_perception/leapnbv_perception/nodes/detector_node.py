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

import time
from typing import Optional, Sequence, Set

import numpy as np
from sensor_msgs.msg import Image
from std_msgs.msg import Header

from leapnbv_common.contracts import ContractError, check_same_frame, refused
from leapnbv_common.conversions import (
    SerializedImage,
    box_to_detection,
    image_to_rgb,
    input_stamp_msgs,
    serialized_header_stamp_ns,
    stamp_to_ns,
)
from leapnbv_common.diagnostics import rejects_bad_input
from leapnbv_common.managed_node import ManagedNode, managed_node_main
from leapnbv_common.qos import camera_input_qos, stage_input_qos, stage_output_qos
from leapnbv_common.stage import Frame, KeyInput, Stage
from leapnbv_common.stage_inputs import checked_colour_image
from leapnbv_common.topics import DETECTIONS, VIEW_CANDIDATES
from leapnbv_msgs.msg import PersonDetections, ViewCandidates
from leapnbv_perception.admission import Admission
from leapnbv_perception.backends.ground_truth import (
    GROUND_TRUTH_BACKEND,
    frame_truth,
    ground_truth_boxes,
    people_published_on,
    truth_companions,
)
from leapnbv_perception.nodes.box_carrying import BoxCarrier
from leapnbv_perception.nodes.engine_loading import load_in_configure, load_person_detector
from leapnbv_perception.params import DetectorParams
from leapnbv_perception.truth_corruption import BOX_STREAM, corrupted_boxes, frame_rng

WAITING_CHECK_PERIOD_S = 0.05  # how often a waiting frame checks whether an in-flight frame timed out


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
        if self.ground_truth:  # the error budget's corrupted truth says so in every status
            self.diagnostics.set_info("truth_corruption", p.box_corruption().describe())
        self.detector = None
        if not self.ground_truth:
            self.detector = load_in_configure(self, "detector model " + repr(p.model_file_path),
                                              lambda: load_person_detector(p))
        elif p.timing_stand_in:  # a benchmark: the real network's cost (onnxruntime), the truth's boxes
            self.detector = load_in_configure(self, "timing stand-in detector model " + repr(p.model_file_path),
                                              lambda: load_person_detector(p, backend="onnxruntime"))
        self.publisher = self.create_lifecycle_publisher(PersonDetections, DETECTIONS, stage_output_qos())
        # Detect less often: the target's box carried by its mesh's image motion between detections.
        self.carrier = BoxCarrier(self) if p.detect_every_n_frames > 1 else None
        # The newest frame only (depth 1): frames that came while the node was busy are counted as not taken.
        # Read in place from its serialized bytes (SerializedImage): it is checked, never deserialized. With the
        # ground-truth backend, the simulator's truth of its stamp and its other people (pulled when the image comes).
        self.stage = Stage(self, KeyInput("image", Image, "image", checked_colour_image, camera_input_qos(1), raw=True),
                           truth_companions(10, people_published_on(self)) if self.ground_truth else [], self.on_frame,
                           frame_error_reason="bad_ground_truth" if self.ground_truth else "bad_image",
                           on_restart=self.admission.reset)

    def activate_stage(self) -> None:
        if self.carrier is not None:
            self.carrier.start()
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

    def on_params_change(self, params: DetectorParams, changed: Set[str]) -> None:
        """The thresholds, the carrying limits and the admission settings apply from the next frame (the
        rest is read-only)."""
        if self.carrier is not None:
            self.carrier.schedule.min_confidence = params.carry_min_confidence
        detector = self.detector
        if detector is not None:
            detector.score_threshold = params.score_threshold
            detector.iou_threshold = params.iou_threshold
            detector.max_detections = params.max_detections

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
        carried = None if self.carrier is None else self.carrier.carried_box(image)
        if carried is not None:
            self.publish(image.header, image.width, image.height, carried[0], started, carried[1])
            return
        if self.detector is not None:  # the engine's boxes (a timing stand-in: its cost, the truth's boxes)
            boxes = self.detector.detect(image_to_rgb(image))
        if self.ground_truth:
            # The truth gives the box: the image's pixels are not read (only checked on arrival).
            try:
                boxes = ground_truth_boxes(frame_truth(frame), (image.width, image.height))
            except ContractError as error:
                self.diagnostics.reject("bad_ground_truth", error.detail)
                return
            corruption = self.params.value.box_corruption()
            if corruption.active:  # the error budget: a worse detector's boxes
                boxes = corrupted_boxes(boxes, (image.width, image.height), corruption,
                                        frame_rng(corruption.seed, frame.stamp_ns, BOX_STREAM))
        self.publish(image.header, image.width, image.height, boxes, started)


main = managed_node_main(DetectorNode)  # the console script (leapnbv_common.managed_node: the process tuned, then run)


if __name__ == "__main__":
    main()
