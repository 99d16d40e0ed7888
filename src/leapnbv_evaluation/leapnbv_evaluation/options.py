"""How an evaluation runs: the graph's perception and models, its timeouts, the room and the episode's rules.

One options object serves both sides of the evaluation: the session that runs the graph
(:mod:`leapnbv_evaluation.harness`) and the episode that drives it (:mod:`leapnbv_evaluation.closed_loop`).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import List, Optional, Tuple

from leapnbv_evaluation.episode import DEFAULT_STAMP_BASE_NS
from leapnbv_sim.poses import RobotModel

#: The continuous episodes' clocks (EvaluationOptions.clock).
CLOCK_MODES: Tuple[str, ...] = ("lockstep", "real_time")


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
        continuous: Run continuous episodes (:mod:`leapnbv_evaluation.continuous`): the simulator's motion
            stack drives the robot while the graph plans from every frame, on sim time.
        clock: Continuous episodes' clock: "lockstep" (sim time advances one camera period once the graph
            answered the frame in flight: reproducible) or "real_time" (sim time follows the wall clock).
        camera_rate_hz: Continuous episodes' camera rate (frames per second of sim time).
        time_limit_s: A continuous episode ends at this sim time without arrival ...
        commit_hold_s: ... or on arrival at a goal committed at least this long ...
        no_plan_limit_s: ... or when no goal came within this time.
        obstacle_memory: Continuous, without the room's map: nbv_node plans with the map it builds on the way
            from the frames' background points (its ``obstacle_memory`` parameter; :mod:`leapnbv_planner.
            obstacle_memory`), forgotten at each new scene.
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
    continuous: bool = False
    clock: str = "lockstep"
    camera_rate_hz: float = 10.0
    time_limit_s: float = 30.0
    commit_hold_s: float = 1.0
    no_plan_limit_s: float = 3.0
    obstacle_memory: bool = False

    @property
    def robot(self) -> RobotModel:
        """The robot the picks are reached with (its motion and head)."""
        return RobotModel(motion=self.robot_motion, head=self.robot_head)

    @property
    def real_models(self) -> bool:
        """Real perception models run (not the simulator's ground truth)."""
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
