"""The episode's rules without ROS (leapnbv_evaluation.closed_loop, .frame_outputs).

When a multi-move episode stops, what a failed scene records, the planner's terms, and what a
frame's outputs say.
"""
from __future__ import annotations

import dataclasses
from types import SimpleNamespace
from typing import Dict, List, Optional, Tuple

import numpy as np
import pytest

from leapnbv_common.conversions import ViewCandidatesArrays
from leapnbv_evaluation.closed_loop import (
    STOP_LOW_GAIN,
    STOP_NO_PLAN,
    ClosedLoopEpisodes,
    predicted_gain,
    stay_where_the_graph_failed,
    stop_reason,
)
from leapnbv_evaluation.episode import EvaluationError, candidate_world_pose, frame_stamp_ns
from leapnbv_evaluation.frame_outputs import END_TO_END, FrameOutputs, expected_outputs
from leapnbv_evaluation.options import EvaluationOptions
from leapnbv_evaluation.results import MethodResult, PoseRecord, ViewMetrics
from leapnbv_perception.smplx_layer import SMPLXModel
from leapnbv_planner.candidates import CandidateRingParams, generate_candidates
from leapnbv_sim.generation import SceneConfig, generate_scene
from leapnbv_sim.poses import CameraPose
from leapnbv_stand_ins.files import ensure_stand_in_body_model


def _candidates(score, chosen, includes_current_view=True, terms=("visibility", "area")) -> ViewCandidatesArrays:
    count = len(score)
    return ViewCandidatesArrays(
        rotations=np.tile(np.eye(3), (count, 1, 1)), positions=np.zeros((count, 3)), term_names=list(terms),
        term_weights=np.full(len(terms), 1.0 / len(terms)), term_scores=np.zeros((count, len(terms))),
        score=np.asarray(score, float), feasible=np.ones(count, bool), infeasible_reason=np.zeros(count, np.uint8),
        chosen_index=chosen, includes_current_view=includes_current_view, ring_center=np.zeros(3), ring_radius=1.0)


def test_predicted_gain_is_the_picks_score_above_the_current_views() -> None:
    assert predicted_gain(_candidates([0.25, 0.5, 0.75], chosen=2)) == pytest.approx(0.5)
    assert predicted_gain(_candidates([0.25, 0.5, 0.75], chosen=1)) == pytest.approx(0.25)
    # Without the current view among the candidates the gain is unknown: never a reason to stop.
    assert predicted_gain(_candidates([0.25, 0.5], chosen=1, includes_current_view=False)) == float("inf")


def test_stop_reason_of_a_multi_move_episode() -> None:
    assert stop_reason(None, 0.02) == STOP_NO_PLAN
    assert stop_reason(_candidates([0.1, 0.2], chosen=-1), 0.02) == STOP_NO_PLAN
    assert stop_reason(_candidates([0.3, 0.2], chosen=0), -1.0) == STOP_LOW_GAIN  # staying is no move
    assert stop_reason(_candidates([0.30, 0.31], chosen=1), 0.02) == STOP_LOW_GAIN
    assert stop_reason(_candidates([0.30, 0.33], chosen=1), 0.02) is None
    assert stop_reason(_candidates([0.30, 0.29], chosen=1), -1.0) is None  # a negative min_gain moves on
    assert stop_reason(_candidates([0.5, 0.1], chosen=1, includes_current_view=False), 0.02) is None


def _stay() -> MethodResult:
    metrics = ViewMetrics(surface_coverage=0.4, raw_coverage=0.5, area_px=90, person_pixels=100)
    return MethodResult(chosen_index=-1, pose=PoseRecord(position_m=[0.0, 0.0, 1.0], heading_deg=0.0, pitch_deg=0.0),
                        before=metrics, after=metrics, success=False, raw_success=False)


def test_a_failed_scene_stays_for_every_method_learned_later() -> None:
    failed = SimpleNamespace(graph_failure="no person detected", per_method={"leap_nbv": _stay()})
    planned = SimpleNamespace(graph_failure=None, per_method={"leap_nbv": dataclasses.replace(_stay(), chosen_index=3)})
    stay_where_the_graph_failed([failed, planned], ["leap_nbv", "random", "area_only"])
    assert list(failed.per_method) == ["leap_nbv", "random", "area_only"]
    assert all(result.chosen_index == -1 for result in failed.per_method.values())
    assert failed.per_method["random"] is not failed.per_method["area_only"]  # copies, not one shared record
    assert list(planned.per_method) == ["leap_nbv"]  # a planned scene keeps its own methods


def test_the_planner_terms_are_learned_once_and_may_not_change() -> None:
    episodes = ClosedLoopEpisodes(session=SimpleNamespace(), options=EvaluationOptions(score_all_candidates=False))
    base_methods = episodes.methods
    episodes.learn_terms(None)
    assert episodes.term_names is None
    episodes.learn_terms(_candidates([0.1, 0.2], chosen=1))
    assert episodes.term_names == ["visibility", "area"]
    assert set(episodes.methods) - set(base_methods) == {"visibility_only", "area_only"}
    episodes.learn_terms(_candidates([0.1, 0.2], chosen=1))  # the same terms again
    with pytest.raises(EvaluationError, match="score terms changed"):
        episodes.learn_terms(_candidates([0.1, 0.2], chosen=1, terms=("visibility",)))


def test_frame_outputs_early_failure_completeness_and_latency() -> None:
    frame = FrameOutputs(stamp_ns=7, published_ns=1_000_000)
    assert frame.early_failure() is None and frame.view_candidates is None and frame.candidates() is None
    frame.messages["detections"] = SimpleNamespace(detections=[object()], compute_time_ms=4.0)
    frame.messages["target_geometry"] = SimpleNamespace(valid=True, compute_time_ms=2.5)
    frame.messages["ground_plane"] = SimpleNamespace(valid=False, inlier_count=12, compute_time_ms=1.0)
    assert frame.early_failure() == "no ground plane (12 inliers)"
    # The target track: found (index 0) is no failure; not among the detections is one, with hmr_node's reason.
    frame.messages["ground_plane"] = SimpleNamespace(valid=True, inlier_count=900, compute_time_ms=1.0)
    assert not frame.failure_recorded()  # a frame that ends early waits for its target track
    frame.messages["target_track"] = SimpleNamespace(detection_index=0, reason="nearest")
    assert frame.early_failure() is None and frame.failure_recorded()
    frame.messages["target_track"] = SimpleNamespace(detection_index=-1, reason="hidden 0.4 s")
    assert frame.early_failure() == "the target is not among the detections: hidden 0.4 s"
    frame.messages["ground_plane"] = SimpleNamespace(valid=False, inlier_count=12, compute_time_ms=1.0)
    frame.messages["detections"] = SimpleNamespace(detections=[], compute_time_ms=4.0)
    assert frame.early_failure() == "no person detected"
    assert frame.latency_ms() == {"detector_node": 4.0, "raster_node": 2.5, "ground_node": 1.0}
    frame.received_ns["view_candidates"] = 31_000_000
    assert frame.latency_ms()[END_TO_END] == pytest.approx(30.0)
    assert not frame.complete(real_models=False)
    for topic in expected_outputs(real_models=False):
        frame.messages.setdefault(topic, SimpleNamespace(compute_time_ms=0.0))
    assert frame.complete(real_models=False)
    del frame.messages["target_track"]
    assert not frame.complete(real_models=False)  # a planned frame's record holds its target track
    frame.messages["target_track"] = SimpleNamespace(detection_index=0, reason="nearest")
    assert not frame.complete(real_models=True)  # the metric mesh is missing
    assert expected_outputs(True) - expected_outputs(False) == {"human_mesh_metric"}


# --------------------------------------------------------------------------- an episode through a fake session

@pytest.fixture(scope="module")
def scene():
    model = SMPLXModel.load(ensure_stand_in_body_model("small"))
    return generate_scene(dataclasses.replace(SceneConfig(), seed=3), model)


def _ring(scene, camera, chosen, score) -> ViewCandidatesArrays:
    """The candidate ring around the person as seen from ``camera`` (index 0: the current view)."""
    normal = camera.rotation.T @ np.array([0.0, 0.0, 1.0])
    centroid = camera.world_to_camera(scene.body_centre_world[None])[0]
    ring = generate_candidates(centroid, normal, float(camera.position[2]), CandidateRingParams(
        num_candidates=8, radius=2.0, num_rings=1))
    candidates = _candidates(score, chosen)
    return dataclasses.replace(candidates, rotations=ring.rotations, positions=ring.positions)


@dataclasses.dataclass
class _ScriptedFrame(FrameOutputs):
    """A frame whose candidates are given (the graph's answer without its messages)."""

    planned: Optional[ViewCandidatesArrays] = None

    @property
    def view_candidates(self):
        return None if self.planned is None else SimpleNamespace(chosen_index=self.planned.chosen_index)

    def candidates(self) -> Optional[ViewCandidatesArrays]:
        return self.planned


class _FakeSession:
    """The simulator and a graph that answers frame k with plans[k]; goals are followed at once."""

    def __init__(self, plans) -> None:
        self.plans = list(plans)  # callables (scene, camera) -> candidates or None
        self.power = None
        self.stamps: List[int] = []
        self.waited: List[int] = []
        self.moved_directly: List[CameraPose] = []
        self._frames: Dict[int, Tuple[CameraPose, Optional[ViewCandidatesArrays]]] = {}

    def set_scene(self, scene) -> None:
        self.scene, self.camera = scene, scene.start_camera.copy()
        self.forgotten = getattr(self, "forgotten", 0)

    def forget_last_scene(self) -> None:
        self.forgotten += 1

    def run_frame(self, stamp_ns):
        plan = self.plans[len(self.stamps)](self.scene, self.camera)
        self.stamps.append(stamp_ns)
        self._frames[stamp_ns] = (self.camera.copy(), plan)
        return self.scene.render(self.camera, frame_index=1), _ScriptedFrame(stamp_ns=stamp_ns, published_ns=0,
                                                                             planned=plan)

    def wait_goal(self, stamp_ns) -> bool:
        self.waited.append(stamp_ns)
        pose, plan = self._frames[stamp_ns]
        if plan is not None and plan.chosen_index >= 0:
            self.camera = candidate_world_pose(pose, plan, plan.chosen_index)
        return True

    def move_to(self, pose) -> None:
        self.moved_directly.append(pose)
        self.camera = pose.copy()

    def camera_pose(self):
        return self.camera

    def camera_pose_at(self, stamp_ns):
        return self._frames[stamp_ns][0].copy() if stamp_ns in self._frames else None


def _plan(chosen, score):
    return lambda scene, camera: _ring(scene, camera, chosen, score)


def test_an_episode_moves_while_the_predicted_gain_holds_then_stops(scene) -> None:
    nine = np.linspace(0.1, 0.5, 9)
    session = _FakeSession([_plan(2, nine), _plan(5, np.r_[0.3, np.full(8, 0.1)] + np.eye(9)[5] * 0.25),
                            _plan(4, np.r_[0.4, np.full(8, 0.41)])])
    options = EvaluationOptions(score_all_candidates=False, max_moves=4, min_gain=0.02)
    episodes = ClosedLoopEpisodes(session, options)
    result = episodes.run(scene, seed=3, scene_index=2, stamp_base=1_000_000_000_000)
    stamps = [frame_stamp_ns(1_000_000_000_000, 2, frame) for frame in range(3)]
    assert session.stamps == stamps and session.waited == stamps  # every planned frame's goal is consumed
    assert session.forgotten == 1  # the graph forgot the last scene's target and goal before this one's frames
    assert result.graph_failure is None and result.stamp_ns == stamps[0]
    leap = result.per_method["leap_nbv"]
    assert leap.chosen_index == 2
    loop = leap.closed_loop
    assert loop.goal_received and loop.goal_position_error_m == pytest.approx(0.0, abs=1e-9)
    assert loop.after_stamp_ns == stamps[1] and loop.after_graph_chosen_index == 5
    # Move 2 (gain 0.35 - 0.3 = 0.05 >= 0.02) was made; the view it reached predicts 0.01: stop.
    assert [step.move for step in loop.steps] == [2]
    step = loop.steps[0]
    assert step.planned_from_stamp_ns == stamps[1] and step.stamp_ns == stamps[2] and step.chosen_index == 5
    assert step.predicted_gain == pytest.approx(0.05)
    after_move_1 = candidate_world_pose(scene.start_camera, _ring(scene, scene.start_camera, 2, nine), 2)
    travel = np.linalg.norm(session.camera_pose_at(stamps[2]).position[:2] - after_move_1.position[:2])
    assert step.travel_m == pytest.approx(travel, abs=1e-4) and step.travel_m > 0.5
    assert loop.stop_reason == STOP_LOW_GAIN
    assert session.moved_directly == []
    assert episodes.term_names == ["visibility", "area"]


def test_an_episode_stops_when_the_graph_plans_nothing_and_a_one_move_episode_has_no_rule(scene) -> None:
    session = _FakeSession([_plan(3, np.linspace(0.1, 0.5, 9)), lambda scene, camera: None])
    result = ClosedLoopEpisodes(session, EvaluationOptions(score_all_candidates=False, max_moves=3)).run(
        scene, seed=3, scene_index=0, stamp_base=0)
    loop = result.per_method["leap_nbv"].closed_loop
    assert loop.steps == [] and loop.stop_reason == STOP_NO_PLAN and loop.after_graph_chosen_index is None
    assert len(session.stamps) == 2 and session.waited == session.stamps[:1]  # no goal for the unplanned frame
    session = _FakeSession([_plan(3, np.linspace(0.1, 0.5, 9)), _plan(4, np.linspace(0.1, 0.9, 9))])
    loop = ClosedLoopEpisodes(session, EvaluationOptions(score_all_candidates=False, max_moves=1)).run(
        scene, seed=3, scene_index=0, stamp_base=0).per_method["leap_nbv"].closed_loop
    assert loop.steps == [] and loop.stop_reason == "" and len(session.stamps) == 2
