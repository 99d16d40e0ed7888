"""The ROS side of the evaluation: the node graph (started once), an in-process simulator node, output collection.

The five-node graph runs as separate processes (``leapnbv_bringup.graph_runner``; ground-truth
perception with the small stand-in body by default). A
:class:`~leapnbv_sim.nodes.simulator_node.SimulatorNode` runs in this process with rate 0 and
publishes frames only when asked. Per benchmark scene:

1. the start view is published (stamp ``stamp_base + 10 s * scene index + 0.1 s * frame``) and
   the graph's outputs of that stamp are awaited (each frame is processed before the next is
   published, so the run is deterministic frame by frame); per-stage compute times and the
   end-to-end latency (receive time of view_candidates minus the frame's publish time: in a
   live system the header stamp is the capture time, which the publish time stands for here)
   are recorded, and the graph's reconstructed area (target_geometry.mask_pixel_count);
2. every method picks among the same scored candidates and is scored
   (:func:`leapnbv_evaluation.episode.score_methods`);
3. for ``leap_nbv`` the simulator node itself follows the graph's next-best-view goal over DDS
   (the closed loop), publishes the after-view through the graph, and the graph's area after the
   move is recorded (and PA-MPVPE of the graph's metric mesh when real models run).

A scene whose start frame the graph cannot plan for (no detection, empty target, no ground
plane, timeout) is recorded as failed with the reason, and every method "stays" there (no
method can move without the graph's candidates), so the success rates stay comparable.
"""
from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass, field
from typing import Any, Callable, Dict, List, Optional, Sequence, Tuple

import numpy as np
import rclpy
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import Image

from leapnbv_bringup.graph_runner import (
    GraphError,
    GraphRunner,
    merge_overrides,
    parse_set_arguments,
    perception_overrides,
)
from leapnbv_common.conversions import (
    ConversionError,
    ViewCandidatesArrays,
    ground_plane_to_arrays,
    stamp_to_ns,
    target_geometry_to_arrays,
    view_candidates_to_arrays,
)
from leapnbv_common.power_monitor import RAIL_TOTAL, PowerMonitor, start_power_monitor
from leapnbv_common.topics import (
    COLOR_INFO_TOPIC,
    DETECTIONS,
    GROUND_PLANE,
    GROUND_TRUTH_TOPIC,
    HUMAN_MESH,
    HUMAN_MESH_METRIC,
    NEXT_BEST_VIEW_TOPIC,
    PERSON_MASK,
    TARGET_GEOMETRY,
    VIEW_CANDIDATES,
    output_topic,
)
from leapnbv_evaluation.benchmark_set import FAMILY_GRAPH_PARAMETERS, benchmark_scene
from leapnbv_evaluation.episode import (
    DEFAULT_METHOD,
    DEFAULT_STAMP_BASE_NS,
    SCENE_STAMP_SPACING_NS,
    EvaluationError,
    candidate_world_pose,
    frame_stamp_ns,
    graph_vs_truth,
    method_names,
    score_methods,
    view_metrics,
)
from leapnbv_evaluation.metrics import pa_mpvpe_mm
from leapnbv_evaluation.results import (
    ClosedLoopResult,
    EvaluationRun,
    MethodResult,
    MoveStep,
    PoseRecord,
    SceneResult,
)
from leapnbv_msgs.msg import GroundPlane, HumanMesh, PersonDetections, TargetGeometry, ViewCandidates
from leapnbv_perception.smplx_layer import SMPLXModel
from leapnbv_sim.nodes.simulator_node import SimulatorNode
from leapnbv_sim.poses import RobotModel
from leapnbv_sim.render import RenderedFrame
from leapnbv_sim.scene import Scene
from leapnbv_stand_ins.files import ensure_stand_in_body_model

# Graph node -> its output (short topic name) whose compute_time_ms is that stage's latency.
STAGE_TOPICS: Tuple[Tuple[str, str], ...] = (
    ("detector_node", DETECTIONS),
    ("hmr_node", HUMAN_MESH),
    ("raster_node", TARGET_GEOMETRY),
    ("ground_node", GROUND_PLANE),
    ("nbv_node", VIEW_CANDIDATES),
)
END_TO_END = "end_to_end"
#: Latency stages of the tables, in order.
STAGES: Tuple[str, ...] = tuple(stage for stage, _ in STAGE_TOPICS) + (END_TO_END,)


@dataclass
class EvaluationOptions:
    """How the graph runs and how long frames may take.

    Attributes:
        perception: "ground_truth" (default) or "onnxruntime" / "tensorrt" (real models).
        detector_backend: The detector's backend when it differs from ``perception``: "ground_truth"
            runs a real HMR model on the simulator's person boxes (no detector model needed: a learned
            HMR with no trained detector). None: as ``perception``.
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
        score_all_candidates: Render every candidate of every scene, log its coverage and add
            the "oracle" row (the best feasible candidate by ground-truth surface coverage: the
            ceiling of the candidate ring). About 0.3 s per scene.
        room: "furnished" (the benchmark: 2-4 pieces of furniture around the person) or "open"
            (only the occluders in front of the person and the walls).
        obstacle_map: The simulator publishes each scene's static obstacles as a voxel map (what
            a robot's mapping stack knows of the room) and the nbv node uses it, with the
            camera pose of every frame; False: the planner knows only what each frame shows.
        robot_motion: "base" (default: the robot's base drives to a pick, its camera stays at the
            start camera's mounting height) or "free" (the camera jumps to the 6-DoF pick).
        robot_head: "pan_tilt" (default: the camera tilts to the pick's pitch) or "fixed".
        max_moves: leap_nbv's episode continues through the graph up to this many moves (1: one move, the
            table's), each planned on the view the previous one reached ...
        min_gain: ... while the graph's pick scores at least this much above staying (its predicted gain).
    """

    perception: str = "ground_truth"
    detector_backend: Optional[str] = None
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
    robot_motion: str = "base"
    robot_head: str = "pan_tilt"
    max_moves: int = 1
    min_gain: float = 0.02

    @property
    def robot(self) -> RobotModel:
        return RobotModel(motion=self.robot_motion, head=self.robot_head)

    @property
    def real_models(self) -> bool:
        return self.perception != "ground_truth"

    @property
    def detector_truth(self) -> bool:
        """The detector publishes the simulator's boxes while the HMR runs a model."""
        return self.real_models and self.detector_backend == "ground_truth"

    @property
    def perception_label(self) -> str:
        """The perception as the reports name it."""
        if self.detector_backend and self.detector_backend != self.perception:
            return f"{self.perception} (detector: {self.detector_backend})"
        return self.perception


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
        return self.messages.get(VIEW_CANDIDATES)

    def latency_ms(self) -> Dict[str, float]:
        """compute_time_ms per stage, and end-to-end (view_candidates receive - publish), when present."""
        out: Dict[str, float] = {}
        for stage, topic in STAGE_TOPICS:
            msg = self.messages.get(topic)
            if msg is not None:
                out[stage] = float(msg.compute_time_ms)
        if VIEW_CANDIDATES in self.received_ns:
            out[END_TO_END] = (self.received_ns[VIEW_CANDIDATES] - self.published_ns) * 1e-6
        return out

    def energy_j(self, power: Optional[PowerMonitor]) -> Optional[float]:
        """Joules the board's input rail (VDD_IN) took from the frame's publication to its view
        candidates (monotonic clock); None without rails or without candidates."""
        if power is None or VIEW_CANDIDATES not in self.received_ns:
            return None
        frame = power.energy(self.published_ns * 1e-9, self.received_ns[VIEW_CANDIDATES] * 1e-9)
        return frame.energy_j.get(RAIL_TOTAL) if frame is not None else None

    def candidates(self) -> Optional[ViewCandidatesArrays]:
        """The view candidates as arrays, or None when the graph published none.

        Raises:
            EvaluationError: The message is malformed.
        """
        msg = self.view_candidates
        if msg is None:
            return None
        try:
            return view_candidates_to_arrays(msg)
        except ConversionError as error:
            raise EvaluationError(f"view_candidates: {error}") from error


def simulator_parameters(publish_obstacle_map: bool = True, robot: Optional[RobotModel] = None) -> List[Parameter]:
    """The in-process simulator's parameters: frames only when asked, goals reached at once, the robot's motion."""
    robot = robot or RobotModel()
    return [Parameter("rate_hz", value=0.0), Parameter("move_speed_m_s", value=0.0),
            Parameter("publish_obstacle_map", value=bool(publish_obstacle_map)),
            Parameter("robot_motion", value=robot.motion), Parameter("robot_head", value=robot.head),
            Parameter("robot_camera_height", value=float(robot.camera_height))]


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
        self.runner: Optional[GraphRunner] = None
        self.sim: Optional[SimulatorNode] = None
        self.collector: Optional[Node] = None
        self.executor: Optional[SingleThreadedExecutor] = None
        self.frames: Dict[int, FrameOutputs] = {}
        self._scene_body_model: Optional[SMPLXModel] = None
        self._subscriptions: Dict[str, Any] = {}
        #: The planner's score terms, from the first view candidates seen (the methods follow them).
        self.term_names: Optional[List[str]] = None
        self.ready_s: Optional[float] = None
        #: The board's power rails, sampled while the graph runs (None without rails: no J/frame then).
        self.power: Optional[PowerMonitor] = None

    @property
    def methods(self) -> List[str]:
        """The methods of this run (the "<term>_only" baselines once the planner's terms are known)."""
        return method_names(self.term_names or [], self.options.score_all_candidates)

    # ------------------------------------------------------------------ lifecycle

    def __enter__(self) -> ClosedLoopEvaluator:
        self.start()
        return self

    def __exit__(self, *exc: Any) -> None:
        self.stop()

    def scene_body_model(self) -> SMPLXModel:
        """The body model scenes are generated with (loaded once)."""
        if self._scene_body_model is None:
            path = self.options.scene_body_model or ensure_stand_in_body_model("small")
            self._scene_body_model = SMPLXModel.load(path)
        return self._scene_body_model

    def _graph_overrides(self) -> Dict[str, Dict[str, str]]:
        o = self.options
        body = o.body_model or (ensure_stand_in_body_model("small") if not o.real_models else None)
        if o.detector_backend not in (None, o.perception, "ground_truth"):
            raise EvaluationError(f"--detector-backend {o.detector_backend!r}: the perception's "
                                  f"({o.perception!r}) or ground_truth")
        needs_detector = o.real_models and not o.detector_truth
        if o.real_models and not ((o.detector_model or not needs_detector) and o.hmr_model and o.body_model):
            raise EvaluationError("real perception needs --detector-model (unless --detector-backend ground_truth), "
                                  "--hmr-model and --body-model")
        map_switch = [] if o.obstacle_map else ["nbv_node.use_obstacle_map=false"]
        map_switch.append("nbv_node.max_goal_age_s=0.0")  # simulated stamps, not the clock's: no goal age limit
        robot = FAMILY_GRAPH_PARAMETERS.get(o.room, [])  # the family's robot (camera mounting), before --set
        detector = {"detector_node": {"backend": o.detector_backend}} if o.detector_backend else {}
        return merge_overrides(perception_overrides(o.perception, o.detector_model, o.hmr_model, body), detector,
                               parse_set_arguments(map_switch + robot + list(o.set_parameters)))

    def start(self) -> None:
        """Start the graph's processes and the in-process nodes; wait until all are connected.

        Raises:
            EvaluationError: A node died or did not appear, or the topics did not connect.
        """
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
        self.sim = SimulatorNode(scene=first_scene, parameter_overrides=simulator_parameters(self.options.obstacle_map,
                                                                                    self.options.robot))
        self._subscribe_outputs()
        self.executor = SingleThreadedExecutor()
        self.executor.add_node(self.sim)
        self.executor.add_node(self.collector)
        self._wait_connected()
        self.power, _ = start_power_monitor(clock=time.monotonic)
        # One throw-away frame: the first frame through fresh processes pays for imports and
        # caches; it must not count in the latency tables. Its candidates name the planner's terms.
        stamp = self._take_stamps(1)
        self.sim.set_scene(first_scene)
        _, warm_up = self._run_frame(stamp)
        self._learn_terms(warm_up.candidates())
        if warm_up.view_candidates is not None and warm_up.view_candidates.chosen_index >= 0:
            self._wait_goal(stamp)  # consumed here, not rejected as stale by the first scene

    def stop(self) -> None:
        """Stop the graph's processes and the in-process nodes (safe to call twice)."""
        if self.power is not None:
            self.power.stop()
            self.power = None
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
        return benchmark_scene(seed, self.scene_body_model(), self.options.room)

    def _learn_terms(self, candidates: Optional[ViewCandidatesArrays]) -> None:
        if candidates is None:
            return
        if self.term_names is None:
            self.term_names = list(candidates.term_names)
        elif list(candidates.term_names) != self.term_names:
            raise EvaluationError(f"the planner's score terms changed from {self.term_names} to "
                                  f"{list(candidates.term_names)} during the run")

    def _subscribe_outputs(self) -> None:
        topics = {DETECTIONS: PersonDetections, HUMAN_MESH: HumanMesh, TARGET_GEOMETRY: TargetGeometry,
                  GROUND_PLANE: GroundPlane, VIEW_CANDIDATES: ViewCandidates, PERSON_MASK: Image}
        if self.options.real_models:
            topics[HUMAN_MESH_METRIC] = HumanMesh
        qos = QoSProfile(depth=20, reliability=ReliabilityPolicy.RELIABLE)
        for name, msg_type in topics.items():
            self._subscriptions[name] = self.collector.create_subscription(
                msg_type, output_topic(name), lambda msg, name=name: self._on_output(name, msg), qos)

    def _on_output(self, name: str, msg: Any) -> None:
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
        # The colour camera_info and the ground truth have readers only with ground-truth perception.
        unread = (COLOR_INFO_TOPIC, GROUND_TRUTH_TOPIC) if self.options.real_models else ()
        publishers = [pub for topic, pub in sim.frame_pubs.items() if topic not in unread]

        def connected() -> bool:
            outputs = all(sub.get_publisher_count() > 0 for sub in self._subscriptions.values())
            goal = sim.count_publishers(NEXT_BEST_VIEW_TOPIC) > 0
            return all(pub.get_subscription_count() > 0 for pub in publishers) and outputs and goal

        if not self._spin_until(connected, timeout_s):
            raise EvaluationError(f"the simulator and the graph did not connect within {timeout_s:.0f} s")
        self._spin_until(lambda: False, 0.5)  # let the matching settle on both sides

    def _take_stamps(self, scene_slots: int) -> int:
        first = self._next_stamp_ns
        self._next_stamp_ns += int(scene_slots) * SCENE_STAMP_SPACING_NS
        return first

    def _complete(self, frame: FrameOutputs) -> bool:
        expected = {topic for _, topic in STAGE_TOPICS} | {PERSON_MASK}
        if self.options.real_models:
            expected.add(HUMAN_MESH_METRIC)
        return expected <= set(frame.messages)

    def _early_failure(self, frame: FrameOutputs) -> Optional[str]:
        """A reason the graph will publish no view_candidates for this frame, once it is certain."""
        detections = frame.messages.get(DETECTIONS)
        if detections is not None and not detections.detections:
            return "no person detected"
        target = frame.messages.get(TARGET_GEOMETRY)
        if target is not None and not target.valid:
            return "empty target (no person points survived the mask and depth clustering)"
        ground = frame.messages.get(GROUND_PLANE)
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

    def evaluate(self, seeds: Sequence[int], first_index: int = 0,
                 on_scene: Optional[Callable[[SceneResult], None]] = None) -> EvaluationRun:
        """Run every scene once through the graph and score every method.

        Args:
            seeds: Scene seeds (benchmark seeds for comparable numbers).
            first_index: Scene index of the first seed: the scenes get the stamps they would get
                at these places of a longer run (a worker of a parallel run gives its share's
                place, so its stamps are those of a one-process run).
            on_scene: Called with each scene's result as it is done (progress).

        Returns:
            The run (methods, one result per scene in seed order, wall time of the scenes).
        """
        started = time.monotonic()
        stamp_base = self._take_stamps(int(first_index) + len(seeds))
        scenes = []
        for offset, seed in enumerate(seeds):
            scenes.append(self._evaluate_scene(self._load_scene(seed), int(seed), int(first_index) + offset,
                                               stamp_base))
            if on_scene is not None:
                on_scene(scenes[-1])
        methods = self.methods
        for scene in scenes:
            if scene.graph_failure is not None:
                # Every method stays; methods learned after the scene ran stay the same way.
                staying = next(iter(scene.per_method.values()))
                scene.per_method = {method: scene.per_method.get(method) or dataclasses.replace(staying)
                                    for method in methods}
        o = self.options
        return EvaluationRun(methods=methods, default_method=DEFAULT_METHOD, stages=list(STAGES), scenes=scenes,
                             perception=o.perception_label, room=o.room, obstacle_map=o.obstacle_map, workers=1,
                             ready_s=self.ready_s, scenes_wall_s=time.monotonic() - started)

    def _evaluate_scene(self, scene: Scene, seed: int, scene_index: int, stamp_base: int) -> SceneResult:
        self.sim.set_scene(scene)
        stamp0 = frame_stamp_ns(stamp_base, scene_index, 0)
        before_frame, outputs0 = self._run_frame(stamp0)
        frames = [outputs0]
        before = view_metrics(scene, before_frame)
        candidates = outputs0.candidates() if outputs0.failure is None else None
        self._learn_terms(candidates)
        target_msg = outputs0.messages.get(TARGET_GEOMETRY)
        ground_msg = outputs0.messages.get(GROUND_PLANE)
        try:
            target = target_geometry_to_arrays(target_msg) if target_msg is not None else None
        except ConversionError as error:
            raise EvaluationError(f"target_geometry of seed {seed}: {error}") from error
        ground = ground_plane_to_arrays(ground_msg) if ground_msg is not None else None
        views = score_methods(scene, before, candidates, seed, self.options.score_all_candidates, self.methods,
                              self.options.robot)
        leap = views.per_method.get(DEFAULT_METHOD)
        if candidates is not None and leap is not None and leap.chosen_index >= 0:
            frames.append(self._closed_loop_after(scene, candidates, stamp_base, scene_index,
                                                  views.rendered[leap.chosen_index][0], leap))
        latency: Dict[str, List[float]] = {stage: [] for stage in STAGES}
        for frame in frames:
            for stage, value in frame.latency_ms().items():
                latency[stage].append(value)
        return SceneResult(
            seed=seed, scene_index=scene_index, stamp_ns=stamp0, start_occlusion=float(scene.start_occluder_share),
            start_pose=PoseRecord.of(scene.start_camera), graph_failure=outputs0.failure,
            graph_area_before_px=int(target.mask_pixel_count) if target is not None else None, before=before,
            pa_mpvpe_before_mm=self._pa_mpvpe(outputs0, before_frame),
            graph_vs_truth=graph_vs_truth(scene, target, ground, candidates if outputs0.failure is None else None),
            candidates=candidates, candidate_views=views.candidate_views, per_method=views.per_method,
            latency_ms=latency,
            energy_j=[joules for joules in (frame.energy_j(self.power) for frame in frames) if joules is not None])

    def _closed_loop_after(self, scene: Scene, candidates: ViewCandidatesArrays, stamp_base: int, scene_index: int,
                           render: RenderedFrame, result: MethodResult) -> FrameOutputs:
        """The robot follows the graph's goal over DDS and observes again through the graph."""
        chosen = result.chosen_index
        stamp0 = frame_stamp_ns(stamp_base, scene_index, 0)
        goal_received = self._wait_goal(stamp0)
        expected = candidate_world_pose(scene.start_camera, candidates, chosen, self.options.robot)
        if not goal_received:
            # The goal message did not arrive: move the robot from the candidates directly.
            self.sim.move_to(expected)
        error_m = float(np.linalg.norm(self.sim.camera.position - expected.position))
        stamp1 = frame_stamp_ns(stamp_base, scene_index, 1)
        after_frame, outputs1 = self._run_frame(stamp1)
        target1 = outputs1.messages.get(TARGET_GEOMETRY)
        after_candidates = outputs1.view_candidates
        result.pa_mpvpe_mm = self._pa_mpvpe(outputs1, after_frame)
        result.closed_loop = ClosedLoopResult(
            goal_received=goal_received, goal_position_error_m=error_m,
            graph_area_after_px=int(target1.mask_pixel_count) if target1 is not None else None,
            after_stamp_ns=stamp1, after_graph_failure=outputs1.failure,
            after_graph_chosen_index=int(after_candidates.chosen_index) if after_candidates is not None else None,
            # The node rendered the same view as the in-process render (same pose, same noise draw).
            closed_loop_matches_render=bool(np.array_equal(after_frame.depth_mm, render.depth_mm)))
        if after_candidates is not None and after_candidates.chosen_index >= 0:
            self._wait_goal(stamp1)  # the next goal lands here, not as a stale goal in the next scene
        if self.options.max_moves > 1:
            self._further_moves(scene, stamp_base, scene_index, outputs1, result.closed_loop)
        return outputs1

    def _further_moves(self, scene: Scene, stamp_base: int, scene_index: int, outputs: FrameOutputs,
                       record: ClosedLoopResult) -> None:
        """Moves 2..max_moves: each planned by the graph on the view the previous move reached (the simulator
        already follows that view's goal); the episode stops when the graph plans nothing or its pick's
        predicted gain (score minus the current view's) is below min_gain."""
        record.stop_reason = "max_moves"
        for move in range(2, int(self.options.max_moves) + 1):
            candidates = outputs.candidates() if outputs.failure is None else None
            if candidates is None or candidates.chosen_index < 0:
                record.stop_reason = "no plan"
                return
            chosen = int(candidates.chosen_index)
            gain = float(candidates.score[chosen] - candidates.score[0]) if candidates.includes_current_view \
                else float("inf")
            if chosen == 0 or gain < self.options.min_gain:
                record.stop_reason = "predicted gain below min_gain"
                return
            # Where the planned-on view was taken (the simulator already follows that view's goal).
            before = self.sim.camera_pose_at(outputs.stamp_ns) or self.sim.camera.copy()
            stamp = frame_stamp_ns(stamp_base, scene_index, move)
            rendered, outputs_next = self._run_frame(stamp)
            after = self.sim.camera
            record.steps.append(MoveStep(
                move=move, stamp_ns=stamp, planned_from_stamp_ns=outputs.stamp_ns, chosen_index=chosen,
                predicted_gain=round(gain, 6), travel_m=round(float(np.linalg.norm(after.position[:2]
                                                                                  - before.position[:2])), 4),
                surface_coverage=view_metrics(scene, rendered).surface_coverage,
                end_to_end_ms=outputs_next.latency_ms().get(END_TO_END)))
            next_candidates = outputs_next.view_candidates
            if next_candidates is not None and next_candidates.chosen_index >= 0:
                self._wait_goal(stamp)
            outputs = outputs_next

    def _pa_mpvpe(self, outputs: FrameOutputs, frame: RenderedFrame) -> Optional[float]:
        """PA-MPVPE of the graph's metric mesh against the ground truth (real models only)."""
        if not self.options.real_models:
            return None
        mesh = outputs.messages.get(HUMAN_MESH_METRIC)
        if mesh is None:
            return None
        predicted = np.frombuffer(mesh.vertices, dtype=np.float32).reshape(-1, 3).astype(np.float64)
        truth = frame.ground_truth.vertices_camera
        if predicted.shape != truth.shape:
            return None  # another body model than the scene's: no vertex correspondence
        return pa_mpvpe_mm(predicted, truth)
