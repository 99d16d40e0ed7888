"""The parameters of detector_node and hmr_node: one source of each default, description and range.

The defaults are the deployed robot's, except where the engine lives: the model paths, the
backend and the precision are the robot's own (its params file names them). Parameters the node
builds its engine or its subscriptions from are read-only: set at start-up.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import List

from leapnbv_common.params import StageParams, param
from leapnbv_perception.backends.onnxruntime_backend import GRAPH_OPTIMIZATIONS
from leapnbv_perception.detector_families import DEFAULT_DETECTOR_FAMILY, detector_family_names
from leapnbv_perception.truth_corruption import BoxCorruption, MeshCorruption

# onnxruntime_last_bit_nudged: tests only, onnxruntime with every output moved by one ulp (the regression's
# numeric-configuration test; leapnbv_perception.backends.LAST_BIT_NUDGED_BACKEND).
ENGINE_BACKENDS = ("onnxruntime", "tensorrt", "ground_truth", "onnxruntime_last_bit_nudged")
PRECISIONS = ("fp16", "fp32")
THREADS_MAX = 256
GRAPH_OPTIMIZATION_LEVELS = tuple(GRAPH_OPTIMIZATIONS)


@dataclass
class EngineParams(StageParams):
    """What every engine-running node takes: the backend and how it runs (all fixed at start-up)."""

    backend: str = param("onnxruntime", "onnxruntime (CPU), tensorrt (Jetson) or ground_truth (the simulator's "
                         "truth instead of an engine)", choices=ENGINE_BACKENDS, read_only=True)
    model_file_path: str = param("", "the engine's ONNX model", read_only=True)
    engine_cache_dir: str = param("", "TensorRT engine cache folder (default: beside the ONNX file)", read_only=True)
    precision: str = param("fp16", "TensorRT precision (onnxruntime runs the model as exported)",
                           choices=PRECISIONS, read_only=True)
    precision_plan_path: str = param("", "TensorRT FP16 precision plan JSON: the layers kept in FP32 (written by the "
                                     "FP16 check; empty = none)", read_only=True)
    providers: List[str] = param(["CPUExecutionProvider"], "onnxruntime execution providers, in order of preference",
                                 read_only=True)
    intra_op_threads: int = param(1, "onnxruntime intra-op threads (0 = its default)", min=0, max=THREADS_MAX,
                                  read_only=True)
    graph_optimization: str = param("all", "onnxruntime graph optimization level", choices=GRAPH_OPTIMIZATION_LEVELS,
                                    read_only=True)
    parallel_execution: bool = param(False, "onnxruntime: run independent branches of the graph in parallel "
                                     "(inter_op_threads) instead of operator after operator", read_only=True)
    inter_op_threads: int = param(1, "onnxruntime inter-op threads for parallel_execution (0 = its default)", min=0,
                                  max=THREADS_MAX, read_only=True)
    thread_spinning: bool = param(True, "onnxruntime: idle intra-op threads spin for work (faster hand-over inside "
                                  "one run); off: they sleep, leaving the cores to the other nodes between runs",
                                  read_only=True)


@dataclass
class DetectorParams(EngineParams):
    """detector_node: colour image -> PersonDetections."""

    model_file_path: str = param("", "detector ONNX export (yolov8: input 'images' 1x3xSxS, S = 640 or another "
                                 "multiple of 32 the export was made at, e.g. 320 on a CPU; output 'output0' "
                                 "1x84xA, 8400 anchors at 640)", read_only=True)
    detector_family: str = param(DEFAULT_DETECTOR_FAMILY, "output layout of the exported detector: one of "
                                 + ", ".join(detector_family_names()) + " (leapnbv_perception.detector_families)",
                                 read_only=True)
    score_threshold: float = param(0.25, "a person's score must be above this (strictly)", min=0.0, max=1.0)
    iou_threshold: float = param(0.5, "NMS IoU threshold (ultralytics uses 0.7; 0.5 suits people)", min=0.0, max=1.0)
    max_detections: int = param(20, "most person boxes per frame", min=1, max=1000)
    multi_label: bool = param(False, "yolov8: a person is any anchor whose person score passes the threshold (false: "
                              "only anchors whose best class is person, as the ultralytics predictor)",
                              read_only=True)
    # Latest-frame scheduling: the detector is the graph's first stage, so it is where a frame the graph
    # cannot finish is dropped before any stage works on it (docs/ARCHITECTURE.md, "Timing").
    # 1: measured on the 2-core machine at 30 FPS (scripts/bench/bench_load.py, 40 s each, same load): 2 in flight
    # gave 14.6 goals/s at p50 160 ms / p95 220 ms, 1 gave 11.8 goals/s at p50 112 ms / p95 152 ms (the stages
    # share the cores: a second frame in flight slows the first).
    max_frames_in_flight: int = param(1, "camera frames admitted into the graph whose view candidates have not "
                                      "come back yet: while this many are in flight, the newest frame waits and "
                                      "the older ones are dropped before any work (dropped.graph_busy); 0 = no "
                                      "limit. Applies once the planner has answered", min=0, max=100)
    in_flight_timeout_s: float = param(0.5, "s: an admitted frame without view candidates after twice the graph's "
                                       "recent answer time, at most this long, was dropped downstream and stops "
                                       "counting as in flight", min=0.01, max=10.0)

    # Detect less often (leapnbv_perception.box_tracking): between detections the target's box is carried
    # by the image motion of its metric mesh (human_mesh_metric) and the camera poses. Off by default: the
    # person's own motion is not compensated (docs/ALGORITHMS.md, "Detect less often").
    detect_every_n_frames: int = param(1, "run the detector on one admitted frame in N and carry the target's box "
                                       "into the others (1 = every frame). Needs camera poses (camera_pose topic): "
                                       "a frame without its pose, or the pose of the mesh's frame, is detected",
                                       min=1, max=30, read_only=True)
    carry_min_confidence: float = param(0.8, "a carried box whose mesh is less than this share in the image (times "
                                        "the share of the box inside) is detected instead", min=0.0, max=1.0)
    camera_pose_source: str = param("topic", "with detect_every_n_frames > 1: where the camera poses come from (a "
                                    "key of leapnbv_common.camera_pose.CAMERA_POSE_SOURCES)", read_only=True)
    carry_max_age_s: float = param(0.5, "s: a mesh older than this (its frame before the current one) is not "
                                   "carried", min=0.0, max=5.0)
    timing_stand_in: bool = param(False, "benchmarks only, with backend ground_truth: also run the onnxruntime engine "
                                  "of model_file_path on every admitted frame and discard its boxes (the truth's "
                                  "are published), so that a whole-frame benchmark pays a real detector's cost "
                                  "with a network that has no weights (scripts/bench/bench_load.py)", read_only=True)

    # The error budget (leapnbv_perception.truth_corruption): the truth's boxes made worse by a known amount.
    truth_box_jitter: float = param(0.0, "error budget, backend ground_truth only: each box side moved by Gaussian "
                                    "noise of this share of the box's width or height", min=0.0, max=1.0,
                                    read_only=True)
    truth_box_grow: float = param(0.0, "error budget, backend ground_truth only: each box grown about its centre "
                                  "by this share of its width and height (a box too large)", min=0.0, max=2.0,
                                  read_only=True)
    truth_box_truncate: float = param(0.0, "error budget, backend ground_truth only: each box cut by this share of "
                                      "its size on one random side (a box truncated)", min=0.0, max=0.9, read_only=True)
    truth_miss_share: float = param(0.0, "error budget, backend ground_truth only: the share of frames with no "
                                    "detection at all (missed)", min=0.0, max=1.0, read_only=True)
    truth_corruption_seed: int = param(0, "error budget: the seed of the boxes' corruption (with each frame's "
                                       "stamp: the same frames are corrupted the same way in every run)", min=0,
                                       max=2**31 - 1, read_only=True)

    def box_corruption(self) -> BoxCorruption:
        return BoxCorruption(jitter=self.truth_box_jitter, grow=self.truth_box_grow,
                             truncate=self.truth_box_truncate, miss_share=self.truth_miss_share,
                             seed=self.truth_corruption_seed)

    def check(self) -> None:
        _check_truth_corruption(self.backend, self.box_corruption().active)
        if self.timing_stand_in and (self.backend != "ground_truth" or not self.model_file_path):
            raise ValueError("timing_stand_in needs backend ground_truth and a model_file_path (the network whose "
                             f"cost is paid); got backend {self.backend!r}, model_file_path {self.model_file_path!r}")
        if self.detector_family not in detector_family_names():
            raise ValueError(f"detector_family = {self.detector_family!r} is not one of {detector_family_names()}")


@dataclass
class HmrParams(EngineParams):
    """hmr_node: image + PersonDetections -> HumanMesh of the target person (the SMPL-X tail always runs FP32)."""

    model_file_path: str = param("", "SMPLer-X student ONNX (encoder + heads; see README for the tensor names)",
                                 read_only=True)
    body_model_path: str = param("", "SMPL-X body model .npz (SMPLX_NEUTRAL.npz, or the stand-in model)",
                                 read_only=True)
    box_scale: float = param(1.25, "crop box scale about its centre (SMPLer-X 1.25, SMPLest-X 1.2)", min=1.0, max=3.0)
    unmirror_left_hand: bool = param(True, "un-mirror the left hand (SMPLer-X: true, SMPLest-X: false)")
    # Keeping the same person (leapnbv_perception.target_tracking; docs/ALGORITHMS.md, "Keeping the same person").
    track_previous_target: bool = param(True, "follow the target from frame to frame (false: every frame takes the "
                                        "acquisition rule's box, a new track each frame)")
    min_track_iou: float = param(0.3, "frames decided in the image only: the overlap with the last target box that "
                                 "continues the target; boxes measured at one place in the gate: the overlap with "
                                 "the target's expected box one of them needs to be the target", min=0.0, max=1.0)
    track_in_fixed_frame: bool = param(True, "decide which detection is the target by its place in the camera pose's "
                                       "fixed frame (the box's depth and the frame's camera pose); false, or a frame "
                                       "without its pose or depth: by box overlap in the image only")
    target_gate_m: float = param(0.6, "m: a detection is the target only within this horizontal distance of its "
                                 "predicted place (in a frame right after one that saw it)", min=0.05, max=10.0)
    target_gate_growth_m_s: float = param(0.5, "m/s: how fast the gate grows with the time since the target's last "
                                          "measured place (a person walks about 0.5 m/s)", min=0.0, max=5.0)
    target_lost_after_s: float = param(3.0, "s: a target not among the detections for longer than this is lost: a "
                                       "frame with a detection then takes a new target by the acquisition rule",
                                       min=0.1, max=600.0)
    target_ambiguity_m: float = param(0.3, "m: boxes measured this near one another in the target's gate are one "
                                      "place (a box mostly covered by another person measures that person's "
                                      "depth): the one overlapping the last target box is the target, and the "
                                      "place moves no track", min=0.0, max=2.0)
    target_reacquire_window_s: float = param(10.0, "s: after the target is lost (with a place in the fixed frame), "
                                             "only a detection near that place may become the target for this "
                                             "long (the lost person found again, not a bystander in view); 0: the "
                                             "acquisition rule takes anyone at once", min=0.0, max=600.0)
    target_reacquire_radius_m: float = param(1.5, "m: how near the lost target's place a detection must be in the "
                                             "re-acquisition window", min=0.1, max=20.0)
    target_max_person_extent_m: float = param(2.4, "m: the largest height or width a person's box can measure at "
                                              "its place; a depth at which the box would be larger is not where "
                                              "its person stands (a hidden person behind them)", min=0.5, max=10.0)
    target_coast_s: float = param(1.5, "s: how long the target's last velocity carries its predicted place while it "
                                  "is not seen; then the prediction stands where it got to (a hidden person mostly "
                                  "stops: carried on, the place drifts about 2 m in 3 s and the gate misses them)",
                                  min=0.0, max=60.0)
    target_depth_share: float = param(0.5, "share of a box's width and height, about its centre, whose median depth "
                                      "is the person's place", min=0.1, max=1.0)
    target_input_wait_s: float = param(0.05, "s: how long detections wait for their depth frame and camera pose, once "
                                       "such inputs have come (DDS does not order topics); then decided without",
                                       min=0.0, max=2.0)
    depth_slop_s: float = param(0.005, "s: largest stamp difference between detections and their depth frame",
                                min=0.0, max=1.0)
    camera_pose_source: str = param("topic", "where the camera poses come from (a key of "
                                    "leapnbv_common.camera_pose.CAMERA_POSE_SOURCES)", read_only=True)
    # SMPL-X's triangles are 251 KB of its 377 KB mesh and the same in every frame (docs/TWO_HOSTS.md).
    inline_mesh_faces: bool = param(False, "send the triangles in every HumanMesh instead of once per model on "
                                           "mesh_faces (for a consumer that does not read mesh_faces)")
    # A detector on a CPU takes 0.3-0.6 s a frame (docs/ARCHITECTURE.md, "Timing"): with 10 images at
    # 30 FPS, every frame's image was gone when its detections came (rejected.no_matching_image).
    cache_size: int = param(45, "images kept while waiting for their detections (45: 1.5 s of a 30 FPS camera)",
                            min=1, max=1000, read_only=True)
    # The error budget (leapnbv_perception.truth_corruption): the truth's mesh made worse by a known amount.
    truth_mesh_shift: float = param(0.0, "error budget, backend ground_truth only: the mesh moved across the image "
                                    "by this share of the box's width and height, in a random direction",
                                    min=0.0, max=1.0, read_only=True)
    truth_mesh_depth_error: float = param(0.0, "error budget, backend ground_truth only: the mesh scaled about the "
                                          "camera centre by 1 +- this (nearer or farther, the same projection)",
                                          min=0.0, max=0.9, read_only=True)
    truth_mesh_pa_mpvpe_mm: float = param(0.0, "mm, error budget, backend ground_truth only: pose and shape noise "
                                          "that puts the mesh this far from the truth after Procrustes alignment",
                                          min=0.0, max=500.0, read_only=True)
    truth_corruption_seed: int = param(0, "error budget: the seed of the mesh's corruption (with each frame's "
                                       "stamp: the same frames are corrupted the same way in every run)", min=0,
                                       max=2**31 - 1, read_only=True)

    def mesh_corruption(self) -> MeshCorruption:
        return MeshCorruption(shift=self.truth_mesh_shift, depth=self.truth_mesh_depth_error,
                              pa_mpvpe_mm=self.truth_mesh_pa_mpvpe_mm, seed=self.truth_corruption_seed)

    def check(self) -> None:
        _check_truth_corruption(self.backend, self.mesh_corruption().active)


def _check_truth_corruption(backend: str, active: bool) -> None:
    if active and backend != "ground_truth":
        raise ValueError(f"the truth_* corruption parameters apply to backend ground_truth only (the error budget); "
                         f"backend is {backend!r}")
