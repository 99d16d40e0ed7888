"""What an episode does: one scene's start frame through the graph, the methods' picks, the graph's moves.

The graph and the simulator it observes are a :class:`GraphSession` (the ROS side,
:class:`leapnbv_evaluation.harness.ClosedLoopEvaluator`); this module decides what to publish,
when to move and when to stop. Per benchmark scene:

1. the start view is published (stamp ``stamp_base + 10 s * scene index + 0.1 s * frame``) and
   the graph's outputs of that stamp are awaited (each frame is processed before the next is
   published, so the run is deterministic frame by frame); per-stage compute times and the
   end-to-end latency (receive time of view_candidates minus the frame's publish time: in a
   live system the header stamp is the capture time, which the publish time stands for here)
   are recorded, and the graph's reconstructed area (target_geometry.mask_pixel_count);
2. every method picks among the same scored candidates and is scored
   (:func:`leapnbv_evaluation.episode.score_methods`);
3. for ``leap_nbv`` the simulator follows the graph's next-best-view goal (the closed loop),
   the after-view goes through the graph, and the graph's area after the move is recorded (and
   PA-MPVPE of the graph's metric mesh when real models run);
4. with ``max_moves`` > 1 the episode goes on from the view it reached, each move planned by the
   graph, until the graph plans nothing or its pick's predicted gain is below ``min_gain``.

A scene whose start frame the graph cannot plan for (no detection, empty target, no ground
plane, timeout) is recorded as failed with the reason, and every method "stays" there (no
method can move without the graph's candidates), so the success rates stay comparable.
"""
from __future__ import annotations

import dataclasses
from typing import Dict, List, Optional, Protocol, Sequence, Tuple

import numpy as np

from leapnbv_common.conversions import (
    ConversionError,
    ViewCandidatesArrays,
    ground_plane_to_arrays,
    target_geometry_to_arrays,
)
from leapnbv_common.power_monitor import PowerMonitor
from leapnbv_common.procrustes import pa_mpvpe_mm
from leapnbv_common.topics import GROUND_PLANE, HUMAN_MESH_METRIC, TARGET_GEOMETRY
from leapnbv_evaluation.episode import (
    DEFAULT_METHOD,
    EvaluationError,
    candidate_world_pose,
    frame_stamp_ns,
    graph_vs_truth,
    method_names,
    score_methods,
    view_metrics,
)
from leapnbv_evaluation.frame_outputs import END_TO_END, STAGES, FrameOutputs
from leapnbv_evaluation.options import EvaluationOptions
from leapnbv_evaluation.results import ClosedLoopResult, MethodResult, MoveStep, PoseRecord, SceneResult
from leapnbv_sim.poses import CameraPose
from leapnbv_sim.render import RenderedFrame
from leapnbv_sim.scene import Scene

STOP_MAX_MOVES = "max_moves"
STOP_NO_PLAN = "no plan"
STOP_LOW_GAIN = "predicted gain below min_gain"


class GraphSession(Protocol):
    """What an episode needs of the running graph and the simulator it observes.

    Attributes:
        power: The board's power rails while the graph runs (None without rails).
    """

    power: Optional[PowerMonitor]

    def set_scene(self, scene: Scene) -> None:
        """Put the simulator in a scene, its camera at the scene's start view."""

    def forget_last_scene(self) -> None:
        """Make the graph forget the last scene (its committed goal, its target and people followed)."""

    def run_frame(self, stamp_ns: int) -> Tuple[RenderedFrame, FrameOutputs]:
        """Publish the simulator's current view at ``stamp_ns``; the render and the graph's outputs of it."""

    def wait_goal(self, stamp_ns: int) -> bool:
        """Wait for the graph's goal planned on the frame of ``stamp_ns``; whether it came."""

    def move_to(self, pose: CameraPose) -> None:
        """Move the simulator's camera to ``pose`` (when the graph's goal did not arrive)."""

    def camera_pose(self) -> CameraPose:
        """The simulator's camera now."""

    def camera_pose_at(self, stamp_ns: int) -> Optional[CameraPose]:
        """Where the simulator's camera was when it rendered the frame of ``stamp_ns`` (None: unknown)."""


def predicted_gain(candidates: ViewCandidatesArrays) -> float:
    """The graph's pick's score minus the current view's (inf when the current view is not among the candidates)."""
    chosen = int(candidates.chosen_index)
    if not candidates.includes_current_view:
        return float("inf")
    return float(candidates.score[chosen] - candidates.score[0])


def stop_reason(candidates: Optional[ViewCandidatesArrays], min_gain: float) -> Optional[str]:
    """Why a multi-move episode stops before its next move, or None when the robot moves on.

    Args:
        candidates: The graph's candidates of the view the last move reached (None: it planned nothing).
        min_gain: The least predicted gain (:func:`predicted_gain`) worth a move.

    Returns:
        :data:`STOP_NO_PLAN`, :data:`STOP_LOW_GAIN` (also when the pick is the current view) or None.
    """
    if candidates is None or candidates.chosen_index < 0:
        return STOP_NO_PLAN
    if int(candidates.chosen_index) == 0 or predicted_gain(candidates) < min_gain:
        return STOP_LOW_GAIN
    return None


def stay_where_the_graph_failed(scenes: Sequence[SceneResult], methods: Sequence[str]) -> None:
    """Every method stays in a scene the graph could not plan for, methods learned after it ran too."""
    for scene in scenes:
        if scene.graph_failure is not None:
            staying = next(iter(scene.per_method.values()))
            scene.per_method = {method: scene.per_method.get(method) or dataclasses.replace(staying)
                                for method in methods}


class ClosedLoopEpisodes:
    """The episodes of an evaluation, one per scene, through one graph session.

    Args:
        session: The running graph and its simulator.
        options: The run's options (read at every scene: ``max_moves`` and ``min_gain`` may change between scenes).
    """

    def __init__(self, session: GraphSession, options: EvaluationOptions) -> None:
        self.session = session
        self.options = options
        #: The planner's score terms, from the first view candidates seen (the methods follow them).
        self.term_names: Optional[List[str]] = None

    @property
    def methods(self) -> List[str]:
        """The methods of this run (the "<term>_only" baselines once the planner's terms are known)."""
        return method_names(self.term_names or [], self.options.score_all_candidates)

    def learn_terms(self, candidates: Optional[ViewCandidatesArrays]) -> None:
        """Take the planner's score terms from its candidates (the first seen); they may not change.

        Raises:
            EvaluationError: The terms differ from those seen before.
        """
        if candidates is None:
            return
        if self.term_names is None:
            self.term_names = list(candidates.term_names)
        elif list(candidates.term_names) != self.term_names:
            raise EvaluationError(f"the planner's score terms changed from {self.term_names} to "
                                  f"{list(candidates.term_names)} during the run")

    def run(self, scene: Scene, seed: int, scene_index: int, stamp_base: int) -> SceneResult:
        """One scene's episode: its start frame, every method's pick, and leap_nbv's moves through the graph.

        Args:
            scene: The scene.
            seed: Its seed.
            scene_index: Its place in the run (its stamps, :func:`~leapnbv_evaluation.episode.frame_stamp_ns`).
            stamp_base: Sim time of the run's first scene's first frame.

        Returns:
            The scene's result.

        Raises:
            EvaluationError: The graph's target geometry or view candidates are malformed.
        """
        session = self.session
        session.set_scene(scene)
        # Every scene puts its person at the same fixed-frame place: the last scene's target (its
        # re-acquisition window) and committed goal must not decide this one's.
        session.forget_last_scene()
        stamp0 = frame_stamp_ns(stamp_base, scene_index, 0)
        before_frame, outputs0 = session.run_frame(stamp0)
        frames = [outputs0]
        before = view_metrics(scene, before_frame)
        candidates = outputs0.candidates() if outputs0.failure is None else None
        self.learn_terms(candidates)
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
        energy = (frame.energy_j(session.power) for frame in frames)
        return SceneResult(
            seed=seed, scene_index=scene_index, stamp_ns=stamp0, start_occlusion=float(scene.start_occluder_share),
            start_pose=PoseRecord.of(scene.start_camera), graph_failure=outputs0.failure,
            graph_area_before_px=int(target.mask_pixel_count) if target is not None else None, before=before,
            pa_mpvpe_before_mm=self._pa_mpvpe(outputs0, before_frame),
            graph_vs_truth=graph_vs_truth(scene, target, ground, candidates if outputs0.failure is None else None),
            candidates=candidates, candidate_views=views.candidate_views, per_method=views.per_method,
            latency_ms=latency, energy_j=[joules for joules in energy if joules is not None])

    def _closed_loop_after(self, scene: Scene, candidates: ViewCandidatesArrays, stamp_base: int, scene_index: int,
                           render: RenderedFrame, result: MethodResult) -> FrameOutputs:
        """The robot follows the graph's goal and observes again through the graph."""
        session = self.session
        chosen = result.chosen_index
        stamp0 = frame_stamp_ns(stamp_base, scene_index, 0)
        goal_received = session.wait_goal(stamp0)
        expected = candidate_world_pose(scene.start_camera, candidates, chosen, self.options.robot)
        if not goal_received:
            # The goal message did not arrive: move the robot from the candidates directly.
            session.move_to(expected)
        error_m = float(np.linalg.norm(session.camera_pose().position - expected.position))
        stamp1 = frame_stamp_ns(stamp_base, scene_index, 1)
        after_frame, outputs1 = session.run_frame(stamp1)
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
            session.wait_goal(stamp1)  # the next goal lands here, not as a stale goal in the next scene
        if self.options.max_moves > 1:
            self._further_moves(scene, stamp_base, scene_index, outputs1, result.closed_loop)
        return outputs1

    def _further_moves(self, scene: Scene, stamp_base: int, scene_index: int, outputs: FrameOutputs,
                       record: ClosedLoopResult) -> None:
        """Moves 2..max_moves, each planned by the graph on the view the previous move reached.

        The simulator already follows that view's goal; the episode stops at :func:`stop_reason`.
        """
        session = self.session
        record.stop_reason = STOP_MAX_MOVES
        for move in range(2, int(self.options.max_moves) + 1):
            candidates = outputs.candidates() if outputs.failure is None else None
            reason = stop_reason(candidates, self.options.min_gain)
            if reason is not None or candidates is None:
                record.stop_reason = reason or STOP_NO_PLAN
                return
            # Where the planned-on view was taken (the simulator already follows that view's goal).
            before = session.camera_pose_at(outputs.stamp_ns) or session.camera_pose().copy()
            stamp = frame_stamp_ns(stamp_base, scene_index, move)
            rendered, outputs_next = session.run_frame(stamp)
            after = session.camera_pose()
            record.steps.append(MoveStep(
                move=move, stamp_ns=stamp, planned_from_stamp_ns=outputs.stamp_ns,
                chosen_index=int(candidates.chosen_index), predicted_gain=round(predicted_gain(candidates), 6),
                travel_m=round(float(np.linalg.norm(after.position[:2] - before.position[:2])), 4),
                surface_coverage=view_metrics(scene, rendered).surface_coverage,
                end_to_end_ms=outputs_next.latency_ms().get(END_TO_END)))
            next_candidates = outputs_next.view_candidates
            if next_candidates is not None and next_candidates.chosen_index >= 0:
                session.wait_goal(stamp)
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
