"""The episode's rules without ROS (leapnbv_evaluation.closed_loop, .frame_outputs).

When a multi-move episode stops, what a failed scene records, the planner's terms, and what a
frame's outputs say.
"""
from __future__ import annotations

import dataclasses
from types import SimpleNamespace

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
from leapnbv_evaluation.episode import EvaluationError
from leapnbv_evaluation.frame_outputs import END_TO_END, FrameOutputs, expected_outputs
from leapnbv_evaluation.options import EvaluationOptions
from leapnbv_evaluation.results import MethodResult, PoseRecord, ViewMetrics


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
    frame.messages["detections"] = SimpleNamespace(detections=[], compute_time_ms=4.0)
    assert frame.early_failure() == "no person detected"
    assert frame.latency_ms() == {"detector_node": 4.0, "raster_node": 2.5, "ground_node": 1.0}
    frame.received_ns["view_candidates"] = 31_000_000
    assert frame.latency_ms()[END_TO_END] == pytest.approx(30.0)
    assert not frame.complete(real_models=False)
    for topic in expected_outputs(real_models=False):
        frame.messages.setdefault(topic, SimpleNamespace(compute_time_ms=0.0))
    assert frame.complete(real_models=False)
    assert not frame.complete(real_models=True)  # the metric mesh is missing
    assert expected_outputs(True) - expected_outputs(False) == {"human_mesh_metric"}
