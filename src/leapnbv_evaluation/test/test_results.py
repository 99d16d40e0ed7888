"""Typed evaluation results (leapnbv_evaluation.results): JSON round trip, merging workers' runs."""

from __future__ import annotations

import json

import numpy as np
import pytest

from leapnbv_common.conversions import ViewCandidatesArrays
from leapnbv_evaluation.results import (
    ClosedLoopResult,
    EvaluationRun,
    GraphVsTruth,
    MethodResult,
    MoveStep,
    PoseRecord,
    ResultsError,
    SceneResult,
    ViewMetrics,
    candidates_from_json,
    candidates_to_json,
)
from leapnbv_sim.poses import look_at_pose

METHODS = ["leap_nbv", "stay", "visibility_only", "area_only"]
STAGES = ["detector_node", "nbv_node", "end_to_end"]


def _candidates(rng: np.random.Generator, count: int = 5) -> ViewCandidatesArrays:
    return ViewCandidatesArrays(
        rotations=rng.normal(size=(count, 3, 3)), positions=rng.normal(size=(count, 3)),
        term_names=["visibility", "area"], term_weights=np.array([0.3, 0.7]),
        # float32 values, as the message carries them
        term_scores=rng.random((count, 2)).astype(np.float32).astype(np.float64),
        score=rng.random(count), feasible=rng.random(count) > 0.3,
        infeasible_reason=rng.integers(0, 4, count).astype(np.uint8), chosen_index=2, includes_current_view=True,
        ring_center=rng.normal(size=3), ring_radius=2.5)


def _view(rng: np.random.Generator) -> ViewMetrics:
    return ViewMetrics(float(rng.random()), float(rng.random()) / 2.0, int(rng.integers(1000, 30000)),
                       int(rng.integers(30000, 40000)))


def _scene(seed: int, index: int, failed: bool = False) -> SceneResult:
    rng = np.random.default_rng(seed)
    before = _view(rng)
    pose = PoseRecord.of(look_at_pose(rng.normal(size=3), np.array([0.0, 0.0, 1.0])))
    per_method = {}
    for method in METHODS:
        after = before if failed else _view(rng)
        per_method[method] = MethodResult(chosen_index=-1 if failed else int(rng.integers(0, 5)), pose=pose,
                                          before=before, after=after, success=bool(rng.random() > 0.5),
                                          raw_success=bool(rng.random() > 0.5))
    if not failed:
        per_method["leap_nbv"].pa_mpvpe_mm = 43.21
        per_method["leap_nbv"].closed_loop = ClosedLoopResult(
            goal_received=True, goal_position_error_m=0.0, graph_area_after_px=21000, after_stamp_ns=10**18 + 7,
            after_graph_failure=None, after_graph_chosen_index=4, closed_loop_matches_render=True,
            steps=[MoveStep(move=2, stamp_ns=10**18 + 2 * 10**8, planned_from_stamp_ns=10**18 + 10**8, chosen_index=3,
                            predicted_gain=0.125, travel_m=1.75, surface_coverage=0.93, end_to_end_ms=None)],
            stop_reason="predicted gain below min_gain")
    truth = GraphVsTruth([0.1, 0.2, 2.3], [0.0, -0.2, 2.4], [0.0, -0.98963, -0.14365], 1.2548)
    if not failed:
        truth.target_valid, truth.target_centroid_m, truth.ring_center_m = True, [0.03, -0.45, 2.25], [0.0, 0.9, 2.4]
    return SceneResult(
        seed=seed, scene_index=index, stamp_ns=10**18 + index * 10**10, start_occlusion=float(rng.random()),
        start_pose=pose, graph_failure="no ground plane (12 inliers)" if failed else None,
        graph_area_before_px=None if failed else 12345, before=before, pa_mpvpe_before_mm=None,
        graph_vs_truth=truth, candidates=None if failed else _candidates(rng),
        candidate_views=None if failed else [_view(rng) for _ in range(5)], per_method=per_method,
        latency_ms={stage: [] if failed else list(rng.random(2) * 100.0) for stage in STAGES})


def _run(seeds=(3, 4, 5), first_index: int = 0, failed=(4,)) -> EvaluationRun:
    scenes = [_scene(seed, first_index + i, seed in failed) for i, seed in enumerate(seeds)]
    return EvaluationRun(methods=list(METHODS), default_method="leap_nbv", stages=list(STAGES), scenes=scenes,
                         ready_s=4.25, scenes_wall_s=12.5, total_wall_s=20.0)


def test_a_run_written_and_read_back_compares_equal(tmp_path) -> None:
    run = _run()
    path = run.write(str(tmp_path / "run.json"))
    again = EvaluationRun.read(path)
    assert again == run
    assert again.to_json() == run.to_json()
    # Plain JSON (no NaN), and every typed piece came back as its type.
    json.loads((tmp_path / "run.json").read_text())
    scene = again.scenes[0]
    assert isinstance(scene.per_method["leap_nbv"].closed_loop, ClosedLoopResult)
    assert isinstance(scene.candidates, ViewCandidatesArrays) and scene.candidates.feasible.dtype == bool
    np.testing.assert_array_equal(scene.candidates.term("area"), run.scenes[0].candidates.term("area"))
    assert again.scenes[1].candidates is None and again.scenes[1].graph_failure.startswith("no ground plane")
    # A difference anywhere is seen.
    again.scenes[2].per_method["stay"].after.area_px += 1
    assert again != run


def test_candidates_round_trip_exactly() -> None:
    views = _candidates(np.random.default_rng(0))
    back = candidates_from_json(json.loads(json.dumps(candidates_to_json(views))))
    for name in ("rotations", "positions", "term_weights", "term_scores", "score", "feasible", "infeasible_reason",
                 "ring_center"):
        original, copy = getattr(views, name), getattr(back, name)
        assert copy.dtype == original.dtype and np.array_equal(copy, original), name
    assert (back.term_names, back.chosen_index, back.ring_radius) == (views.term_names, 2, 2.5)


def test_latencies_merge_in_scene_order() -> None:
    run = _run()
    merged = run.latency_ms()
    assert list(merged) == STAGES
    assert merged["nbv_node"] == run.scenes[0].latency_ms["nbv_node"] + run.scenes[2].latency_ms["nbv_node"]


def test_workers_runs_merge_into_the_one_process_run() -> None:
    whole = _run(seeds=(3, 4, 5, 6, 7))
    parts = [_run(seeds=(3, 4, 5), first_index=0), _run(seeds=(6, 7), first_index=3)]
    parts[1].ready_s, parts[1].scenes_wall_s = 5.5, 9.0
    merged = EvaluationRun.merge(parts)
    assert merged.scenes == whole.scenes and merged.seeds == [3, 4, 5, 6, 7]
    assert merged.workers == 2 and merged.ready_s == 5.5 and merged.scenes_wall_s == 12.5
    assert merged.latency_ms() == whole.latency_ms()
    other = _run(seeds=(8,))
    other.methods = METHODS[:2]
    with pytest.raises(ResultsError, match="methods"):
        EvaluationRun.merge([parts[0], other])
    with pytest.raises(ResultsError, match="nothing"):
        EvaluationRun.merge([])


def test_a_foreign_format_is_refused() -> None:
    data = _run().to_json()
    data["format"] = 99
    with pytest.raises(ResultsError, match="format"):
        EvaluationRun.from_json(data)
    data = _run().to_json()
    del data["scenes"][0]["per_method"]["stay"]["pose"]
    with pytest.raises(ResultsError, match="malformed"):
        EvaluationRun.from_json(data)
