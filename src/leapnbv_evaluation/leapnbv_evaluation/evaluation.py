"""Closed-loop evaluation: benchmark scenes through the running node graph, one next-best-view move each.

    python -m leapnbv_evaluation.evaluation --scenes 50 --out out/eval
    python -m leapnbv_evaluation.evaluation --scenes 10 --out out/eval_models --perception onnxruntime \
        --detector-model yolov8s.onnx --hmr-model smplerx.onnx --body-model SMPLX_NEUTRAL.npz \
        --scene-body-model SMPLX_NEUTRAL.npz

The five-node graph starts once (``leapnbv_bringup.graph_runner``, separate processes;
ground-truth perception with the small stand-in body by default). A
:class:`~leapnbv_sim.nodes.simulator_node.SimulatorNode` runs in this process with rate 0 and
publishes frames only when asked. Per benchmark scene:

1. the start view is published (stamp ``stamp_base + 10 s * scene + 0.1 s * frame``) and the
   graph's outputs of that stamp are awaited (each frame is processed before the next is
   published, so the run is deterministic frame by frame); per-stage compute times and the
   end-to-end latency (receive time of view_candidates minus the frame's publish time: in a
   live system the header stamp is the capture time, which the publish time stands for here)
   are recorded, and the graph's reconstructed area (target_geometry.mask_pixel_count);
2. every method picks one of the SAME scored candidates of that frame: ``leap_nbv`` (the
   graph's chosen_index, default weights), ``stay`` (candidate 0, the current view),
   ``random`` (a feasible ring candidate drawn with a per-scene seed; staying is not a random
   move), ``visibility_only`` / ``area_only`` / ``occlusion_only`` (arg-max of S_v / S_a /
   S_o over the feasible candidates: the planner's ``choose_best`` with one-hot weights);
3. the camera moves to each method's pick (``pose_in_world`` of the start camera and the
   candidate's pose in the observation frame), the scene is rendered there and scored:
   surface coverage (:func:`~leapnbv_evaluation.metrics.surface_coverage`, the headline), raw body
   coverage (:func:`~leapnbv_evaluation.metrics.body_coverage`, share of all vertices) and the
   ground-truth reconstructed area (person pixels with a depth return);
4. for ``leap_nbv`` the simulator node itself follows the graph's next-best-view goal over
   DDS (the closed loop), publishes the after-view through the graph, and the graph's area
   after the move is recorded (and PA-MPVPE of the graph's metric mesh when real models run).

Success is ``report.is_success`` on surface coverage (+10 points or >= 90 % after the move).
A scene whose start frame the graph cannot plan for (no detection, empty target, no ground
plane, timeout) is recorded as failed with the reason, and every method "stays" there (no
method can move without the graph's candidates), so the success rates stay comparable.

Outputs in ``--out``: results.md / results.json / plots (``report.write_task_table``),
chosen_views.json (per scene: stamps, candidates' scores, each method's pick, world pose and
metrics), evaluation.md (raw-coverage table, the graph's own areas, failures, wall time), and
logs/ (one log per node).
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
from dataclasses import dataclass, field
from typing import Any, Dict, List, Mapping, Optional, Sequence, Tuple

import numpy as np

from leapnbv_evaluation.metrics import body_coverage, pa_mpvpe_mm, surface_coverage
from leapnbv_evaluation.report import is_success, task_table_markdown, write_task_table
from leapnbv_sim.poses import CameraPose, pose_in_world
from leapnbv_sim.render import PERSON_ID, RenderedFrame
from leapnbv_sim.scene import Scene

METHODS: Tuple[str, ...] = ("leap_nbv", "stay", "random", "visibility_only", "area_only", "occlusion_only")
#: Upper bound (uses the ground truth): the feasible candidate with the best surface coverage.
ORACLE_METHOD = "oracle"
DEFAULT_METHOD = "leap_nbv"

# Graph output (short topic name) -> latency stage name in the tables.
STAGE_TOPICS: Tuple[Tuple[str, str], ...] = (
    ("detector_node", "detections"),
    ("hmr_node", "human_mesh"),
    ("raster_node", "target_geometry"),
    ("ground_node", "ground_plane"),
    ("nbv_node", "view_candidates"),
)
END_TO_END = "end_to_end"

#: Default first stamp: an arbitrary fixed sim time (2023-11-14), so stamps repeat run to run.
DEFAULT_STAMP_BASE_NS = 1_700_000_000_000_000_000
#: Stamps of consecutive scenes lie this far apart: farther than the ground node's
#: mask_max_age_s (1 s), so no scene's start frame ever uses another scene's person mask.
SCENE_STAMP_SPACING_NS = 10_000_000_000
#: Stamps of consecutive frames of one scene (start view, view after the move).
FRAME_STAMP_SPACING_NS = 100_000_000
#: The noise draw of every after-move render (the same for all methods: a fair comparison).
AFTER_FRAME_INDEX = 1
#: Mixed into the per-scene seed of the "random" method.
RANDOM_METHOD_SALT = 7919


class EvaluationError(RuntimeError):
    """The evaluation cannot run (graph did not start, bad arguments); the text says why."""


# ---------------------------------------------------------------------------------------------
# ROS-free core: candidates, method choices, view metrics
# ---------------------------------------------------------------------------------------------


@dataclass
class ScoredCandidates:
    """The candidates of one frame as the graph scored them (observation optical frame).

    Attributes:
        rotations: (C,3,3) candidate camera axes (columns) in the observation frame.
        positions: (C,3) candidate camera centres in the observation frame.
        score: (C,) w_v S_v + w_a S_a + w_o S_o with the graph's weights.
        s_visibility: (C,) S_v.
        s_area: (C,) S_a.
        s_occlusion: (C,) S_o.
        feasible: (C,) bool.
        chosen_index: The graph's choice, -1 when none was feasible.
        includes_current_view: Candidate 0 is the current view.
    """

    rotations: np.ndarray
    positions: np.ndarray
    score: np.ndarray
    s_visibility: np.ndarray
    s_area: np.ndarray
    s_occlusion: np.ndarray
    feasible: np.ndarray
    chosen_index: int
    includes_current_view: bool

    def __len__(self) -> int:
        return int(self.positions.shape[0])


def choose_method_views(candidates: ScoredCandidates, scene_seed: int) -> Dict[str, int]:
    """Each method's candidate index among the same scored candidates (-1: stays, nothing feasible).

    Args:
        candidates: The graph's scored candidates of the start frame.
        scene_seed: Seeds the "random" method (with RANDOM_METHOD_SALT): same scene, same draw.

    Returns:
        {method: index} for every method in METHODS.
    """
    from leapnbv_planner.scoring import choose_best

    here = np.zeros(3)
    feasible = np.asarray(candidates.feasible, dtype=bool)
    choices = {"leap_nbv": int(candidates.chosen_index)}
    choices["stay"] = 0 if candidates.includes_current_view and len(candidates) else -1
    ring = np.flatnonzero(feasible)
    if candidates.includes_current_view:
        ring = ring[ring > 0]
    rng = np.random.default_rng([int(scene_seed) & 0xFFFFFFFF, RANDOM_METHOD_SALT])
    choices["random"] = int(rng.choice(ring)) if ring.size else -1
    # One-hot weights: the score is the single term itself.
    for method, term in (("visibility_only", candidates.s_visibility), ("area_only", candidates.s_area),
                         ("occlusion_only", candidates.s_occlusion)):
        choices[method] = int(choose_best(np.asarray(term, dtype=np.float64), feasible, candidates.positions, here))
    return choices


@dataclass
class ViewMetrics:
    """What one rendered view shows of the person.

    Attributes:
        surface_coverage: Share of the self-visible body surface that this view sees, 0-1.
        raw_coverage: Share of all body vertices this view sees, 0-1 (ALGORITHMS.md 8).
        area_px: Person pixels with a depth return (ground-truth reconstructed area).
        person_pixels: Person pixels, with or without depth.
    """

    surface_coverage: float
    raw_coverage: float
    area_px: int
    person_pixels: int


def view_metrics(scene: Scene, frame: RenderedFrame) -> ViewMetrics:
    """Coverage and area of a rendered frame (noise-free depth for coverage, the sensor's for area).

    Args:
        scene: The scene the frame was rendered from (its body faces).
        frame: The rendered frame.

    Returns:
        The metrics.
    """
    vertices = frame.ground_truth.vertices_camera
    person = frame.object_id == PERSON_ID
    return ViewMetrics(
        surface_coverage=surface_coverage(vertices, scene.body_faces, frame.depth_clean_m, frame.K),
        raw_coverage=body_coverage(vertices, frame.depth_clean_m, frame.K),
        area_px=int(np.count_nonzero(person & (frame.depth_mm > 0))),
        person_pixels=int(np.count_nonzero(person)),
    )


def candidate_world_pose(observation: CameraPose, candidates: ScoredCandidates, index: int) -> CameraPose:
    """World pose of candidate ``index`` (the observation's own pose for -1: staying)."""
    if index < 0:
        return CameraPose(observation.rotation.copy(), observation.position.copy())
    return pose_in_world(observation, candidates.rotations[index], candidates.positions[index])


def frame_stamp_ns(stamp_base_ns: int, scene_index: int, frame: int) -> int:
    """Deterministic sim time of frame ``frame`` of scene ``scene_index`` in a run."""
    return int(stamp_base_ns) + int(scene_index) * SCENE_STAMP_SPACING_NS + int(frame) * FRAME_STAMP_SPACING_NS


def _pose_record(pose: CameraPose) -> Dict[str, Any]:
    forward = pose.rotation[:, 2]
    return {
        "position_m": [round(float(v), 6) for v in pose.position],
        "heading_deg": round(float(np.degrees(np.arctan2(forward[1], forward[0]))), 4),
        "pitch_deg": round(float(np.degrees(np.arcsin(np.clip(-forward[2], -1.0, 1.0)))), 4),
    }


def _graph_vs_truth(scene: Scene, outputs: Any) -> Dict[str, Any]:
    """The graph's target centroid and ground plane next to the truth (start camera's optical frame)."""
    camera = scene.start_camera
    body = camera.world_to_camera(scene.body_vertices_world)
    # The floor z = 0 in the camera frame: n_c = R^T e_z, offset = camera height.
    record: Dict[str, Any] = {
        "truth_body_centre_m": [round(float(v), 4) for v in 0.5 * (body.min(axis=0) + body.max(axis=0))],
        "truth_body_median_m": [round(float(v), 4) for v in np.median(body, axis=0)],
        "truth_ground_normal": [round(float(v), 5) for v in camera.rotation.T @ np.array([0.0, 0.0, 1.0])],
        "truth_ground_offset_m": round(float(camera.position[2]), 4),
    }
    target = outputs.messages.get("target_geometry")
    if target is not None:
        record.update({
            "target_valid": bool(target.valid),
            "target_centroid_m": [round(float(v), 4)
                                  for v in (target.centroid.x, target.centroid.y, target.centroid.z)],
            "target_depth_offset_m": round(float(target.depth_offset), 4),
            "target_visible_fraction": round(float(target.visible_fraction), 4),
        })
    ground = outputs.messages.get("ground_plane")
    if ground is not None:
        normal = np.array([ground.normal.x, ground.normal.y, ground.normal.z])
        record.update({
            "ground_valid": bool(ground.valid),
            "ground_normal": [round(float(v), 5) for v in normal],
            "ground_offset_m": round(float(ground.offset), 4),
            "ground_inlier_ratio": round(float(ground.inlier_ratio), 4),
            "ground_tilt_error_deg": round(float(np.degrees(np.arccos(np.clip(
                normal @ (camera.rotation.T @ np.array([0.0, 0.0, 1.0])) / max(np.linalg.norm(normal), 1e-12),
                -1.0, 1.0)))), 3),
        })
    candidates = outputs.messages.get("view_candidates")
    if candidates is not None:
        centre = candidates.ring_center
        record["ring_center_m"] = [round(float(v), 4) for v in (centre.x, centre.y, centre.z)]
    return record


def _candidate_record(candidates: ScoredCandidates) -> Dict[str, Any]:
    def rounded(values: np.ndarray) -> List[float]:
        return [round(float(v), 6) for v in values]

    return {
        "count": len(candidates),
        "chosen_index": int(candidates.chosen_index),
        "feasible": [bool(v) for v in candidates.feasible],
        "score": rounded(candidates.score),
        "s_visibility": rounded(candidates.s_visibility),
        "s_area": rounded(candidates.s_area),
        "s_occlusion": rounded(candidates.s_occlusion),
        "positions_obs_m": [[round(float(v), 6) for v in p] for p in candidates.positions],
    }


# ---------------------------------------------------------------------------------------------
# The ROS side: graph, simulator node, output collection
# ---------------------------------------------------------------------------------------------


@dataclass
class EvaluationOptions:
    """How the graph runs and how long frames may take.

    Attributes:
        perception: "ground_truth" (default) or "onnxruntime" / "tensorrt" (real models).
        detector_model: YOLOv8 ONNX file (real perception).
        hmr_model: SMPLer-X student ONNX file (real perception).
        body_model: SMPL-X .npz of the HMR node (default with ground truth: the small stand-in).
        scene_body_model: Body model of the scenes (default: the small stand-in, as the benchmark
            seeds were chosen for). PA-MPVPE needs it to share the vertex count of body_model.
        params_file: Graph parameter YAML (default: leapnbv_bringup/config/leapnbv.yaml).
        set_parameters: Extra "node.param=value" overrides.
        frame_timeout_s: Longest wait for a frame's view_candidates.
        ready_timeout_s: Longest wait for the graph's nodes to appear.
        stamp_base_ns: Sim time of the first scene's first frame.
        log_dir: Node logs folder (None: inherit the terminal).
        room: "furnished" (the benchmark: 2-4 pieces of furniture around the person) or "open"
            (only the occluders in front of the person and the walls).
        score_all_candidates: Render every candidate of every scene, log its coverage and add
            the "oracle" row (the best feasible candidate by ground-truth surface coverage: the
            ceiling of the candidate ring). About 0.3 s per scene.
        obstacle_map: The simulator publishes each scene's static obstacles as a voxel map (what
            a robot's mapping stack knows of the room) and the nbv node uses it, with the
            camera pose of every frame; False: the planner knows only what each frame shows.
    """

    perception: str = "ground_truth"
    detector_model: Optional[str] = None
    hmr_model: Optional[str] = None
    body_model: Optional[str] = None
    scene_body_model: Optional[str] = None
    params_file: Optional[str] = None
    set_parameters: List[str] = field(default_factory=list)
    frame_timeout_s: float = 15.0
    ready_timeout_s: float = 60.0
    stamp_base_ns: int = DEFAULT_STAMP_BASE_NS
    log_dir: Optional[str] = None
    score_all_candidates: bool = True
    room: str = "furnished"
    obstacle_map: bool = True

    @property
    def methods(self) -> List[str]:
        return list(METHODS) + ([ORACLE_METHOD] if self.score_all_candidates else [])

    @property
    def real_models(self) -> bool:
        return self.perception != "ground_truth"


@dataclass
class FrameOutputs:
    """The graph's outputs of one stamp, as received (rclpy messages), with receive times (ns, monotonic)."""

    stamp_ns: int
    published_ns: int
    messages: Dict[str, Any] = field(default_factory=dict)
    received_ns: Dict[str, int] = field(default_factory=dict)
    failure: Optional[str] = None

    @property
    def view_candidates(self) -> Any:
        return self.messages.get("view_candidates")

    def latency_ms(self) -> Dict[str, float]:
        """compute_time_ms per stage, and end-to-end (view_candidates receive - publish), when present."""
        out: Dict[str, float] = {}
        for stage, topic in STAGE_TOPICS:
            msg = self.messages.get(topic)
            if msg is not None:
                out[stage] = float(msg.compute_time_ms)
        if "view_candidates" in self.received_ns:
            out[END_TO_END] = (self.received_ns["view_candidates"] - self.published_ns) * 1e-6
        return out


def _scored_candidates(msg: Any) -> ScoredCandidates:
    from leapnbv_common.conversions import ConversionError, view_candidates_to_arrays

    try:
        views = view_candidates_to_arrays(msg)
    except ConversionError as error:
        raise EvaluationError(f"view_candidates: {error}") from error
    return ScoredCandidates(rotations=views.rotations, positions=views.positions, score=views.score,
                            s_visibility=views.term("visibility"), s_area=views.term("area"),
                            s_occlusion=views.term("occlusion"), feasible=views.feasible,
                            chosen_index=views.chosen_index, includes_current_view=views.includes_current_view)


class ClosedLoopEvaluator:
    """The graph (started once), the in-process simulator node and an output collector.

    Use as a context manager; :meth:`evaluate` may be called several times (each call's stamps
    continue after the previous call's, so no node ever sees a stamp twice).

    Args:
        options: Perception, models, timeouts.
    """

    def __init__(self, options: Optional[EvaluationOptions] = None) -> None:
        self.options = options or EvaluationOptions()
        self._next_stamp_ns = int(self.options.stamp_base_ns)
        self._started = False
        self._owns_rclpy = False
        self.runner = None
        self.sim = None
        self.collector = None
        self.executor = None
        self.frames: Dict[int, FrameOutputs] = {}
        self._scene_body_model = None
        self.ready_s = float("nan")

    # ------------------------------------------------------------------ lifecycle

    def __enter__(self) -> ClosedLoopEvaluator:
        self.start()
        return self

    def __exit__(self, *exc: Any) -> None:
        self.stop()

    def scene_body_model(self) -> Any:
        """The body model scenes are generated with (loaded once)."""
        if self._scene_body_model is None:
            from leapnbv_perception.smplx_layer import SMPLXModel
            from leapnbv_stand_ins.files import ensure_stand_in_body_model

            self._scene_body_model = SMPLXModel.load(self.options.scene_body_model
                                                     or ensure_stand_in_body_model("small"))
        return self._scene_body_model

    def _graph_overrides(self) -> Dict[str, Dict[str, str]]:
        from leapnbv_bringup.graph_runner import merge_overrides, parse_set_arguments, perception_overrides
        from leapnbv_stand_ins.files import ensure_stand_in_body_model

        o = self.options
        body = o.body_model or (ensure_stand_in_body_model("small") if not o.real_models else None)
        if o.real_models and not (o.detector_model and o.hmr_model and o.body_model):
            raise EvaluationError("real perception needs --detector-model, --hmr-model and --body-model")
        map_switch = [] if o.obstacle_map else ["nbv_node.use_obstacle_map=false"]
        return merge_overrides(perception_overrides(o.perception, o.detector_model, o.hmr_model, body),
                               parse_set_arguments(map_switch + list(o.set_parameters)))

    def start(self) -> None:
        """Start the graph's processes and the in-process nodes; wait until all are connected.

        Raises:
            EvaluationError: A node died or did not appear, or the topics did not connect.
        """
        import rclpy
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.node import Node

        from leapnbv_bringup.graph_runner import GraphError, GraphRunner
        from leapnbv_sim.nodes.simulator_node import SimulatorNode

        overrides = self._graph_overrides()
        if not rclpy.ok():
            rclpy.init()
            self._owns_rclpy = True
        first_scene = self._load_scene(0)
        self.collector = Node("leapnbv_evaluation")
        self.runner = GraphRunner(self.options.params_file, overrides, log_dir=self.options.log_dir)
        self._started = True
        try:
            self.runner.start()
            self.ready_s = self.runner.wait_ready(self.collector, timeout_s=self.options.ready_timeout_s)
        except GraphError as exc:
            raise EvaluationError(f"the graph did not start: {exc}") from exc
        self.sim = SimulatorNode(scene=first_scene, parameter_overrides=_sim_parameters(self.options.obstacle_map))
        self._subscribe_outputs()
        self.executor = SingleThreadedExecutor()
        self.executor.add_node(self.sim)
        self.executor.add_node(self.collector)
        self._wait_connected()
        # One throw-away frame: the first frame through fresh processes pays for imports and
        # caches; it must not count in the latency tables.
        stamp = self._take_stamps(1)
        self.sim.set_scene(first_scene)
        _, warm_up = self._run_frame(stamp)
        if warm_up.view_candidates is not None and warm_up.view_candidates.chosen_index >= 0:
            self._wait_goal(stamp)  # consumed here, not rejected as stale by the first scene

    def stop(self) -> None:
        """Stop the graph's processes and the in-process nodes (safe to call twice)."""
        import rclpy

        if self.runner is not None and self._started:
            self.runner.stop()
        self._started = False
        if self.executor is not None:
            self.executor.shutdown()
            self.executor = None
        for node in (self.sim, self.collector):
            if node is not None:
                node.destroy_node()
        self.sim = self.collector = None
        if self._owns_rclpy:
            rclpy.try_shutdown()
            self._owns_rclpy = False

    def _load_scene(self, seed: int) -> Scene:
        import dataclasses

        from leapnbv_evaluation.benchmark_set import BENCHMARK_CONFIG
        from leapnbv_sim.generation import generate_scene

        # The seeds qualify under both rooms: the furniture keeps off the start view.
        clutter = BENCHMARK_CONFIG.clutter_count_range if self.options.room == "furnished" else (0, 0)
        config = dataclasses.replace(BENCHMARK_CONFIG, seed=int(seed), clutter_count_range=clutter)
        return generate_scene(config, self.scene_body_model())

    def _subscribe_outputs(self) -> None:
        from rclpy.qos import QoSProfile, ReliabilityPolicy
        from sensor_msgs.msg import Image

        from leapnbv_bringup.graph import NAMESPACE
        from leapnbv_msgs.msg import GroundPlane, HumanMesh, PersonDetections, TargetGeometry, ViewCandidates

        topics = {"detections": PersonDetections, "human_mesh": HumanMesh, "target_geometry": TargetGeometry,
                  "ground_plane": GroundPlane, "view_candidates": ViewCandidates, "person_mask": Image}
        if self.options.real_models:
            topics["human_mesh_metric"] = HumanMesh
        qos = QoSProfile(depth=20, reliability=ReliabilityPolicy.RELIABLE)
        self._subscriptions = {}
        for name, msg_type in topics.items():
            self._subscriptions[name] = self.collector.create_subscription(
                msg_type, f"{NAMESPACE}/{name}", lambda msg, name=name: self._on_output(name, msg), qos)

    def _on_output(self, name: str, msg: Any) -> None:
        from leapnbv_common.conversions import stamp_to_ns

        frame = self.frames.get(stamp_to_ns(msg.header.stamp))
        if frame is None or name in frame.messages:
            return  # a stamp this evaluator did not publish, or a duplicate
        frame.messages[name] = msg
        frame.received_ns[name] = time.monotonic_ns()

    def _spin_until(self, done: Any, timeout_s: float) -> bool:
        deadline = time.monotonic() + timeout_s
        while not done():
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                return False
            self.executor.spin_once(timeout_sec=min(0.01, remaining))
        return True

    def _wait_connected(self, timeout_s: float = 20.0) -> None:
        """Every camera topic has the graph's subscribers and every output its publisher."""
        sim = self.sim

        def connected() -> bool:
            # The colour camera_info and the ground truth have readers only with ground-truth perception.
            publishers = (sim.image_pub, sim.depth_pub, sim.depth_info_pub)
            if not self.options.real_models:
                publishers += (sim.image_info_pub, sim.truth_pub)
            outputs = all(sub.get_publisher_count() > 0 for sub in self._subscriptions.values())
            goal = sim.count_publishers("/leapnbv/next_best_view") > 0
            return all(pub.get_subscription_count() > 0 for pub in publishers) and outputs and goal

        if not self._spin_until(connected, timeout_s):
            raise EvaluationError(f"the simulator and the graph did not connect within {timeout_s:.0f} s")
        self._spin_until(lambda: False, 0.5)  # let the matching settle on both sides

    def _take_stamps(self, scene_slots: int) -> int:
        first = self._next_stamp_ns
        self._next_stamp_ns += int(scene_slots) * SCENE_STAMP_SPACING_NS
        return first

    def _complete(self, frame: FrameOutputs) -> bool:
        expected = {topic for _, topic in STAGE_TOPICS} | {"person_mask"}
        if self.options.real_models:
            expected.add("human_mesh_metric")
        return expected <= set(frame.messages)

    def _early_failure(self, frame: FrameOutputs) -> Optional[str]:
        """A reason the graph will publish no view_candidates for this frame, once it is certain."""
        detections = frame.messages.get("detections")
        if detections is not None and not detections.detections:
            return "no person detected"
        target = frame.messages.get("target_geometry")
        if target is not None and not target.valid:
            return "empty target (no person points survived the mask and depth clustering)"
        ground = frame.messages.get("ground_plane")
        if ground is not None and not ground.valid:
            return f"no ground plane ({ground.inlier_count} inliers)"
        return None

    def _run_frame(self, stamp_ns: int) -> Tuple[RenderedFrame, FrameOutputs]:
        """Publish the simulator's current view at ``stamp_ns`` and collect the graph's outputs."""
        frame = FrameOutputs(stamp_ns=stamp_ns, published_ns=0)
        self.frames[stamp_ns] = frame
        frame.published_ns = time.monotonic_ns()
        _, rendered = self.sim.publish_frame(stamp_ns)
        timeout = self.options.frame_timeout_s
        failure_seen_at: List[float] = []

        def answered() -> bool:
            if frame.view_candidates is not None:
                return True
            if self._early_failure(frame) is not None:
                if not failure_seen_at:
                    failure_seen_at.append(time.monotonic())
                # nbv_node publishes nothing for such a frame; wait a moment for certainty.
                return time.monotonic() - failure_seen_at[0] > 0.5
            return False

        if not self._spin_until(answered, timeout):
            frame.failure = f"no view_candidates within {timeout:.0f} s (got {sorted(frame.messages)})"
        elif frame.view_candidates is None:
            frame.failure = self._early_failure(frame)
        else:
            # The remaining outputs of this stamp (person mask, metric mesh) are on their way.
            self._spin_until(lambda: self._complete(frame), 1.0)
        self.runner.check_alive()
        return rendered, frame

    def _wait_goal(self, stamp_ns: int, timeout_s: float = 5.0) -> bool:
        return self._spin_until(lambda: self.sim.last_goal_stamp_ns == stamp_ns, timeout_s)

    # ------------------------------------------------------------------ evaluation

    def evaluate(self, seeds: Sequence[int]) -> Dict[str, Any]:
        """Run every scene once through the graph and score every method.

        Args:
            seeds: Scene seeds (benchmark seeds for comparable numbers).

        Returns:
            The results dict of ``report.write_task_table`` ("methods", "default_method",
            "scenes" with per-method rows, "latency_ms") plus "scene_logs" (the chosen-view
            log) and "wall_s".
        """
        started = time.monotonic()
        stamp_base = self._take_stamps(len(seeds))
        scenes: List[Dict[str, Any]] = []
        logs: List[Dict[str, Any]] = []
        latency: Dict[str, List[float]] = {stage: [] for stage, _ in STAGE_TOPICS}
        latency[END_TO_END] = []
        for scene_index, seed in enumerate(seeds):
            scene = self._load_scene(seed)
            row, log, frames = self._evaluate_scene(scene, int(seed), scene_index, stamp_base)
            scenes.append(row)
            logs.append(log)
            for frame in frames:
                for stage, value in frame.latency_ms().items():
                    latency[stage].append(value)
        return {
            "methods": self.options.methods,
            "default_method": DEFAULT_METHOD,
            "scenes": scenes,
            "latency_ms": latency,
            "scene_logs": logs,
            "wall_s": time.monotonic() - started,
        }

    def _evaluate_scene(self, scene: Scene, seed: int, scene_index: int,
                        stamp_base: int) -> Tuple[Dict[str, Any], Dict[str, Any], List[FrameOutputs]]:
        self.sim.set_scene(scene)
        start_pose = scene.start_camera
        stamp0 = frame_stamp_ns(stamp_base, scene_index, 0)
        before_frame, outputs0 = self._run_frame(stamp0)
        frames = [outputs0]
        before = view_metrics(scene, before_frame)
        target0 = outputs0.messages.get("target_geometry")
        log: Dict[str, Any] = {
            "seed": seed,
            "stamp_ns": stamp0,
            "start_occlusion": float(scene.start_occluder_share),
            "start_pose": _pose_record(start_pose),
            "graph_failure": outputs0.failure,
            "graph_area_before_px": int(target0.mask_pixel_count) if target0 is not None else None,
            "before": vars(before),
            "pa_mpvpe_before_mm": self._pa_mpvpe(outputs0, before_frame),
            "graph_vs_truth": _graph_vs_truth(scene, outputs0),
        }
        methods = self.options.methods
        rendered: Dict[int, Tuple[RenderedFrame, ViewMetrics]] = {}
        if outputs0.failure is not None:
            choices = {method: -1 for method in methods}
            candidates = None
        else:
            candidates = _scored_candidates(outputs0.view_candidates)
            choices = choose_method_views(candidates, seed)
            log["candidates"] = _candidate_record(candidates)
            if self.options.score_all_candidates:
                from leapnbv_planner.scoring import choose_best

                for index in range(len(candidates)):
                    frame = scene.render(candidate_world_pose(start_pose, candidates, index),
                                         frame_index=AFTER_FRAME_INDEX)
                    rendered[index] = (frame, view_metrics(scene, frame))
                coverage = np.array([rendered[i][1].surface_coverage for i in range(len(candidates))])
                log["candidates"]["surface_coverage"] = [round(float(v), 6) for v in coverage]
                log["candidates"]["raw_coverage"] = [round(rendered[i][1].raw_coverage, 6)
                                                     for i in range(len(candidates))]
                choices[ORACLE_METHOD] = int(choose_best(coverage, candidates.feasible, candidates.positions,
                                                         np.zeros(3)))

        per_method: Dict[str, Dict[str, Any]] = {}
        method_logs: Dict[str, Dict[str, Any]] = {}
        for method in methods:
            index = choices[method]
            pose = candidate_world_pose(start_pose, candidates, index) if candidates is not None else start_pose
            if index not in rendered:
                frame = scene.render(pose, frame_index=AFTER_FRAME_INDEX)
                rendered[index] = (frame, view_metrics(scene, frame))
            _, after = rendered[index]
            per_method[method] = {
                "coverage_before": before.surface_coverage,
                "coverage_after": after.surface_coverage,
                "raw_coverage_before": before.raw_coverage,
                "raw_coverage_after": after.raw_coverage,
                "area_before": before.area_px,
                "area_after": after.area_px,
                "pa_mpvpe_mm": None,
                "chosen_index": index,
            }
            method_logs[method] = {"chosen_index": index, "pose": _pose_record(pose), "after": vars(after)}

        if candidates is not None and choices["leap_nbv"] >= 0:
            frames.append(self._closed_loop_after(scene, candidates, choices["leap_nbv"], stamp_base, scene_index,
                                                  rendered, per_method["leap_nbv"], method_logs["leap_nbv"]))
        for method in methods:
            row = per_method[method]
            row["success"] = is_success(row["coverage_before"], row["coverage_after"])
            method_logs[method]["success"] = row["success"]
        log["per_method"] = method_logs
        row = {"seed": seed, "start_occlusion": float(scene.start_occluder_share), "per_method": per_method,
               "graph_failure": outputs0.failure}
        return row, log, frames

    def _closed_loop_after(self, scene: Scene, candidates: ScoredCandidates, chosen: int, stamp_base: int,
                           scene_index: int, rendered: Mapping[int, Tuple[RenderedFrame, ViewMetrics]],
                           row: Dict[str, Any], log: Dict[str, Any]) -> FrameOutputs:
        """The robot follows the graph's goal over DDS and observes again through the graph."""
        stamp0 = frame_stamp_ns(stamp_base, scene_index, 0)
        log["goal_received"] = self._wait_goal(stamp0)
        if not log["goal_received"]:
            # The goal message did not arrive: move the robot from the candidates directly.
            self.sim.move_to(candidate_world_pose(scene.start_camera, candidates, chosen))
        expected = candidate_world_pose(scene.start_camera, candidates, chosen)
        log["goal_position_error_m"] = float(np.linalg.norm(self.sim.camera.position - expected.position))
        stamp1 = frame_stamp_ns(stamp_base, scene_index, 1)
        after_frame, outputs1 = self._run_frame(stamp1)
        target1 = outputs1.messages.get("target_geometry")
        row["graph_area_after"] = int(target1.mask_pixel_count) if target1 is not None else None
        row["pa_mpvpe_mm"] = self._pa_mpvpe(outputs1, after_frame)
        log["graph_area_after_px"] = row["graph_area_after"]
        log["after_stamp_ns"] = stamp1
        log["after_graph_failure"] = outputs1.failure
        log["after_graph_chosen_index"] = (int(outputs1.view_candidates.chosen_index)
                                           if outputs1.view_candidates is not None else None)
        # The node rendered the same view as the in-process render (same pose, same noise draw).
        log["closed_loop_matches_render"] = bool(np.array_equal(after_frame.depth_mm, rendered[chosen][0].depth_mm))
        if outputs1.view_candidates is not None and outputs1.view_candidates.chosen_index >= 0:
            self._wait_goal(stamp1)  # the next goal lands here, not as a stale goal in the next scene
        return outputs1

    def _pa_mpvpe(self, outputs: FrameOutputs, frame: RenderedFrame) -> Optional[float]:
        """PA-MPVPE of the graph's metric mesh against the ground truth (real models only)."""
        if not self.options.real_models:
            return None
        mesh = outputs.messages.get("human_mesh_metric")
        if mesh is None:
            return None
        predicted = np.frombuffer(mesh.vertices, dtype=np.float32).reshape(-1, 3).astype(np.float64)
        truth = frame.ground_truth.vertices_camera
        if predicted.shape != truth.shape:
            return None  # another body model than the scene's: no vertex correspondence
        return pa_mpvpe_mm(predicted, truth)


def _sim_parameters(publish_obstacle_map: bool = True) -> List[Any]:
    from rclpy.parameter import Parameter

    return [Parameter("rate_hz", value=0.0), Parameter("move_speed_m_s", value=0.0),
            Parameter("publish_obstacle_map", value=bool(publish_obstacle_map))]


# ---------------------------------------------------------------------------------------------
# Reports
# ---------------------------------------------------------------------------------------------


def raw_coverage_results(results: Mapping[str, Any]) -> Dict[str, Any]:
    """The same results with coverage_before/after replaced by the raw body coverage (for a second table)."""
    scenes = []
    for scene in results["scenes"]:
        per_method = {}
        for method, row in scene["per_method"].items():
            copy = dict(row)
            copy["coverage_before"] = row["raw_coverage_before"]
            copy["coverage_after"] = row["raw_coverage_after"]
            copy.pop("success", None)
            per_method[method] = copy
        scenes.append({"seed": scene.get("seed"), "start_occlusion": scene.get("start_occlusion"),
                       "per_method": per_method})
    return {"methods": list(results["methods"]), "scenes": scenes, "latency_ms": {}}


def evaluation_summary_markdown(results: Mapping[str, Any], options: EvaluationOptions, wall_s: float) -> str:
    """evaluation.md: what ran, the raw-coverage table, the graph's own areas, failures, wall time."""
    scenes = results["scenes"]
    failures = [(scene["seed"], scene["graph_failure"]) for scene in scenes if scene.get("graph_failure")]
    leap = [scene["per_method"][DEFAULT_METHOD] for scene in scenes]
    graph_before = [log["graph_area_before_px"] for log in results["scene_logs"]
                    if log.get("graph_area_before_px") is not None]
    graph_after = [row["graph_area_after"] for row in leap if row.get("graph_area_after") is not None]
    lines = [
        "# LEAP-NBV closed-loop evaluation",
        "",
        f"Scenes: {len(scenes)} (seeds {', '.join(str(scene['seed']) for scene in scenes)}); rooms: "
        f"{options.room}; obstacle map: {'used' if options.obstacle_map else 'not used'}; perception: "
        f"{options.perception}; wall time {wall_s:.1f} s (graph ready in {results.get('ready_s', float('nan')):.1f} s, "
        f"scenes {results.get('wall_s', float('nan')):.1f} s).",
        "",
        "Headline coverage (results.md) is the surface coverage: the share of the body surface the "
        "viewpoint could show (self-visible vertices, image bounds ignored) that the view does show. "
        "The raw body coverage below divides by all vertices (its ceiling is ~50-55 %: the back of "
        "a body is always hidden); success there uses the same rule, so read it with that in mind.",
        "",
        "## Raw body coverage (share of all vertices)",
        "",
        task_table_markdown(raw_coverage_results(results)),
        "## Reconstructed area measured by the graph (leap_nbv, mask pixels with depth)",
        "",
        f"before {np.mean(graph_before) / 1000.0:.1f} k px -> after {np.mean(graph_after) / 1000.0:.1f} k px "
        f"over {len(graph_after)} scenes" if graph_after and graph_before else "n/a",
        "",
        "## Graph failures",
        "",
    ]
    lines += [f"- seed {seed}: {reason}" for seed, reason in failures] or ["none"]
    lines.append("")
    return "\n".join(lines)


def write_outputs(out_dir: str, results: Dict[str, Any], options: EvaluationOptions, wall_s: float) -> str:
    """Write results.md/.json and plots (report.write_task_table), chosen_views.json and evaluation.md.

    Returns:
        Path of results.md.
    """
    os.makedirs(out_dir, exist_ok=True)
    path = write_task_table(out_dir, results)
    with open(os.path.join(out_dir, "chosen_views.json"), "w", encoding="utf-8") as stream:
        json.dump(_plain(results["scene_logs"]), stream, indent=1, allow_nan=False)
        stream.write("\n")
    with open(os.path.join(out_dir, "evaluation.md"), "w", encoding="utf-8") as stream:
        stream.write(evaluation_summary_markdown(results, options, wall_s))
    return path


def _plain(value: Any) -> Any:
    if isinstance(value, dict):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if isinstance(value, (np.floating, float)):
        return float(value) if np.isfinite(value) else None
    if isinstance(value, (np.integer,)):
        return int(value)
    if isinstance(value, np.bool_):
        return bool(value)
    return value


def benchmark_seeds(count: int, offset: int = 0) -> List[int]:
    """Benchmark seeds [offset, offset + count) of the committed set.

    Raises:
        EvaluationError: The slice runs past the committed seeds.
    """
    from leapnbv_evaluation.benchmark_set import BENCHMARK_SEEDS

    if count < 1 or offset < 0 or offset + count > len(BENCHMARK_SEEDS):
        raise EvaluationError(f"--scenes {count} --seed-offset {offset}: the benchmark set has "
                              f"{len(BENCHMARK_SEEDS)} seeds")
    return list(BENCHMARK_SEEDS[offset:offset + count])


def run_evaluation(seeds: Sequence[int], out_dir: str, options: Optional[EvaluationOptions] = None) -> Dict[str, Any]:
    """Start the graph, evaluate the scenes, write the outputs; returns the results dict."""
    options = options or EvaluationOptions()
    if options.log_dir is None:
        options.log_dir = os.path.join(out_dir, "logs")
    started = time.monotonic()
    with ClosedLoopEvaluator(options) as evaluator:
        results = evaluator.evaluate(seeds)
        results["ready_s"] = evaluator.ready_s
    wall_s = time.monotonic() - started
    results["total_wall_s"] = wall_s
    write_outputs(out_dir, results, options, wall_s)
    return results


def main(argv: Optional[List[str]] = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scenes", type=int, default=50, help="how many benchmark scenes (of 64)")
    parser.add_argument("--seed-offset", type=int, default=0, help="skip this many benchmark seeds first")
    parser.add_argument("--out", default=os.path.join("out", "evaluation"), help="output folder")
    parser.add_argument("--perception", choices=["ground_truth", "onnxruntime", "tensorrt"], default="ground_truth")
    parser.add_argument("--detector-model", default=None, help="YOLOv8 ONNX file (real perception)")
    parser.add_argument("--hmr-model", default=None, help="SMPLer-X student ONNX file (real perception)")
    parser.add_argument("--body-model", default=None,
                        help="SMPL-X .npz of the HMR node (ground truth default: the small stand-in)")
    parser.add_argument("--scene-body-model", default=None,
                        help="body model of the scenes (default: the small stand-in the seeds were chosen for)")
    parser.add_argument("--params", default=None, help="graph parameter YAML")
    parser.add_argument("--set", action="append", default=[], metavar="NODE.PARAM=VALUE",
                        help="override one graph parameter (repeatable)")
    parser.add_argument("--frame-timeout", type=float, default=15.0, help="seconds to wait for a frame's plan")
    parser.add_argument("--room", choices=["furnished", "open"], default="furnished",
                        help="benchmark rooms with furniture around the person (default) or without")
    parser.add_argument("--no-obstacle-map", action="store_true",
                        help="the planner gets no map of the room: it knows only what each frame shows")
    args = parser.parse_args(argv)

    options = EvaluationOptions(perception=args.perception, detector_model=args.detector_model,
                                hmr_model=args.hmr_model, body_model=args.body_model,
                                scene_body_model=args.scene_body_model, params_file=args.params,
                                set_parameters=list(args.set), frame_timeout_s=args.frame_timeout,
                                room=args.room, obstacle_map=not args.no_obstacle_map)
    try:
        seeds = benchmark_seeds(args.scenes, args.seed_offset)
        results = run_evaluation(seeds, args.out, options)
    except EvaluationError as exc:
        print(f"[evaluation] {exc}", file=sys.stderr)
        return 1
    print(task_table_markdown(results), end="")
    failures = sum(1 for scene in results["scenes"] if scene.get("graph_failure"))
    print(f"[evaluation] {len(seeds)} scenes ({failures} graph failures) in {results['total_wall_s']:.1f} s; "
          f"outputs in {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
