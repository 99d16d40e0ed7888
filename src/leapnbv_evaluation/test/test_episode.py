"""The evaluator core without ROS (leapnbv_evaluation.episode): surface coverage on scenes, candidate poses in the
world, method choices, scoring every method."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from leapnbv_common.conversions import ViewCandidatesArrays
from leapnbv_evaluation.episode import (
    AFTER_FRAME_INDEX,
    ORACLE_METHOD,
    candidate_world_pose,
    choose_method_views,
    frame_stamp_ns,
    method_names,
    score_methods,
    view_metrics,
)
from leapnbv_evaluation.metrics import body_coverage, is_success, surface_coverage
from leapnbv_perception.smplx_layer import SMPLXModel
from leapnbv_planner.candidates import CandidateRingParams, generate_candidates
from leapnbv_sim.generation import SceneConfig, generate_scene
from leapnbv_sim.poses import look_at_pose
from leapnbv_sim.render import PERSON_ID
from leapnbv_sim.visibility import self_visible_vertex_mask
from leapnbv_stand_ins.files import ensure_stand_in_body_model


@pytest.fixture(scope="module")
def scene():
    model = SMPLXModel.load(ensure_stand_in_body_model("small"))
    return generate_scene(dataclasses.replace(SceneConfig(), seed=3), model)


def _far_camera(scene, distance=4.5):
    """A camera on the person's -x side far enough to frame the whole body."""
    centre = scene.body_centre_world
    return look_at_pose(np.array([centre[0] - distance, centre[1], 1.2]), centre)


def test_surface_coverage_of_an_unoccluded_framed_body_is_one(scene):
    camera = _far_camera(scene)
    vertices = camera.world_to_camera(scene.body_vertices_world)
    body_depth, _ = scene.render_depth(camera, include=np.array([PERSON_ID]))
    coverage = surface_coverage(vertices, scene.body_faces, body_depth, scene.K)
    assert coverage > 0.98
    # The raw share of all vertices cannot come near 1: the back of the body is hidden.
    assert body_coverage(vertices, body_depth, scene.K) < 0.6


def test_surface_coverage_drops_with_the_occluder(scene):
    camera = scene.start_camera
    vertices = camera.world_to_camera(scene.body_vertices_world)
    scene_depth, _ = scene.render_depth(camera)
    body_depth, _ = scene.render_depth(camera, include=np.array([PERSON_ID]))
    occluded = surface_coverage(vertices, scene.body_faces, scene_depth, scene.K)
    free = surface_coverage(vertices, scene.body_faces, body_depth, scene.K)
    assert free > 0.95
    # The scene was generated so that occluders hide start_occluder_share of the body's
    # self-visible in-image vertices.
    assert occluded == pytest.approx(free * (1.0 - scene.start_occluder_share), abs=0.03)
    assert occluded < free - 0.15


def test_surface_coverage_counts_what_the_image_border_cuts_off(scene):
    camera = _far_camera(scene, distance=1.0)  # 42 degrees vertical FOV: the body does not fit
    vertices = camera.world_to_camera(scene.body_vertices_world)
    body_depth, _ = scene.render_depth(camera, include=np.array([PERSON_ID]))
    cropped = surface_coverage(vertices, scene.body_faces, body_depth, scene.K)
    assert 0.1 < cropped < 0.8
    # Self-visibility itself ignores the image bounds: about half the body faces the camera.
    share = self_visible_vertex_mask(vertices, scene.body_faces, scene.K).mean()
    assert 0.35 < share < 0.65


def test_candidate_pose_in_world_matches_the_ring_geometry(scene):
    start = scene.start_camera
    # The floor z = 0 seen from the start camera: n_c = R^T e_z, offset = camera height.
    normal = start.rotation.T @ np.array([0.0, 0.0, 1.0])
    offset = float(start.position[2])
    centroid_world = scene.body_centre_world
    centroid = start.world_to_camera(centroid_world[None])[0]
    params = CandidateRingParams(num_candidates=8, radius=2.0, num_rings=1)
    ring = generate_candidates(centroid, normal, offset, params)
    candidates = _arrays(ring.rotations, ring.positions, {"visibility": np.zeros(9)}, np.ones(9, bool), chosen=-1)
    stay = candidate_world_pose(start, candidates, 0)
    np.testing.assert_allclose(stay.as_matrix(), start.as_matrix(), atol=1e-12)
    for index in range(1, 9):
        pose = candidate_world_pose(start, candidates, index)
        # Same height as the start camera, on the ring around the centroid's foot point ...
        assert pose.position[2] == pytest.approx(start.position[2], abs=1e-9)
        assert np.linalg.norm(pose.position[:2] - centroid_world[:2]) == pytest.approx(2.0, abs=1e-9)
        # ... looking at the centroid, x axis level (no roll): the world look-at pose.
        expected = look_at_pose(pose.position, centroid_world)
        np.testing.assert_allclose(pose.rotation, expected.rotation, atol=1e-9)
    # Ring candidate 0 (index 1) lies on the start camera's bearing from the target.
    first = candidate_world_pose(start, candidates, 1).position[:2] - centroid_world[:2]
    bearing = start.position[:2] - centroid_world[:2]
    assert np.dot(first, bearing) / (np.linalg.norm(first) * np.linalg.norm(bearing)) == pytest.approx(1.0)


def _arrays(rotations, positions, terms, feasible, chosen):
    """ViewCandidatesArrays with the given score terms (name -> (C,) values), total score 0."""
    count = len(positions)
    names = list(terms)
    return ViewCandidatesArrays(
        rotations=np.asarray(rotations, float), positions=np.asarray(positions, float), term_names=names,
        term_weights=np.full(len(names), 1.0 / len(names)),
        term_scores=np.stack([np.asarray(terms[name], float) for name in names], axis=1),
        score=np.zeros(count), feasible=np.asarray(feasible, bool), infeasible_reason=np.zeros(count, np.uint8),
        chosen_index=chosen, includes_current_view=True, ring_center=np.zeros(3), ring_radius=1.0)


def _candidates(s_v, s_a, s_o, feasible, chosen=1):
    count = len(s_v)
    positions = np.array([[float(i), 0.0, 0.0] for i in range(count)])
    return _arrays(np.repeat(np.eye(3)[None], count, axis=0), positions,
                   {"visibility": s_v, "area": s_a, "occlusion": s_o}, feasible, chosen)


def test_methods_choose_among_the_same_feasible_candidates():
    c = _candidates(s_v=[1.0, 1.0, 1.0, 0.5, 1.0], s_a=[0.1, 0.2, 0.9, 0.3, 0.4],
                    s_o=[0.5, 0.6, 0.7, 0.99, 0.8], feasible=[True, True, False, True, True], chosen=4)
    choices = choose_method_views(c, scene_seed=11)
    assert choices["leap_nbv"] == 4
    assert choices["stay"] == 0
    assert choices["area_only"] == 4  # 2 has the largest S_a but is infeasible
    assert choices["occlusion_only"] == 3
    assert choices["visibility_only"] == 0  # S_v ties at 1.0: the nearest (the current view) wins
    assert choices["random"] in (1, 3, 4)
    # Seeded per scene: the same scene draws the same candidate, and the draws vary over scenes.
    assert choose_method_views(c, scene_seed=11)["random"] == choices["random"]
    draws = {choose_method_views(c, scene_seed=seed)["random"] for seed in range(40)}
    assert draws == {1, 3, 4}


def test_term_only_baselines_follow_the_planners_terms():
    c = _arrays(np.repeat(np.eye(3)[None], 3, axis=0), np.eye(3), {"area": [0.1, 0.9, 0.2], "novelty": [0.3, 0.1, 0.8]},
                [True, True, True], chosen=1)
    choices = choose_method_views(c, scene_seed=0)
    assert list(choices) == ["leap_nbv", "stay", "random", "area_only", "novelty_only"]
    assert choices["area_only"] == 1 and choices["novelty_only"] == 2
    assert method_names(c.term_names, oracle=True) == list(choices) + [ORACLE_METHOD]
    assert method_names(["visibility", "area", "occlusion"], oracle=False) == [
        "leap_nbv", "stay", "random", "visibility_only", "area_only", "occlusion_only"]


def test_methods_stay_when_nothing_is_feasible():
    c = _candidates([1.0, 1.0], [0.2, 0.3], [0.5, 0.9], feasible=[False, False], chosen=-1)
    choices = choose_method_views(c, scene_seed=0)
    assert choices["random"] == -1 and choices["area_only"] == -1 and choices["occlusion_only"] == -1


def test_view_metrics_of_the_start_view(scene):
    frame = scene.render(scene.start_camera, frame_index=0)
    metrics = view_metrics(scene, frame)
    person = frame.object_id == PERSON_ID
    assert metrics.person_pixels == int(person.sum())
    assert metrics.area_px == int(np.count_nonzero(person & (frame.depth_mm > 0)))
    assert 0 < metrics.area_px <= metrics.person_pixels
    assert metrics.raw_coverage == pytest.approx(frame.ground_truth.visible_vertices.mean())
    assert metrics.raw_coverage < metrics.surface_coverage < 1.0


def test_frame_stamps_are_deterministic_and_ordered():
    base = 1_700_000_000_000_000_000
    assert frame_stamp_ns(base, 0, 0) == base
    assert frame_stamp_ns(base, 2, 1) == base + 20_000_000_000 + 100_000_000
    assert frame_stamp_ns(base, 1, 0) > frame_stamp_ns(base, 0, 1)


def test_score_methods_renders_each_pick_and_decides_success_once(scene):
    start = scene.start_camera
    normal = start.rotation.T @ np.array([0.0, 0.0, 1.0])
    centroid = start.world_to_camera(scene.body_centre_world[None])[0]
    ring = generate_candidates(centroid, normal, float(start.position[2]), CandidateRingParams(num_candidates=8,
                                                                                              radius=2.0, num_rings=1))
    feasible = np.ones(9, bool)
    feasible[4] = False
    candidates = _arrays(ring.rotations, ring.positions, {"visibility": np.linspace(1.0, 0.2, 9),
                                                          "area": np.linspace(0.0, 0.8, 9)}, feasible, chosen=3)
    before = view_metrics(scene, scene.render(start, frame_index=0))
    views = score_methods(scene, before, candidates, seed=3, score_all_candidates=True, methods_when_staying=[])
    assert list(views.per_method) == ["leap_nbv", "stay", "random", "visibility_only", "area_only", "oracle"]
    assert len(views.candidate_views) == 9
    coverage = [view.surface_coverage for view in views.candidate_views]
    oracle = views.per_method["oracle"]
    assert feasible[oracle.chosen_index]
    assert coverage[oracle.chosen_index] == max(c for c, f in zip(coverage, feasible) if f)
    for method, result in views.per_method.items():
        pose = candidate_world_pose(start, candidates, result.chosen_index)
        frame = scene.render(pose, frame_index=AFTER_FRAME_INDEX)
        assert result.after == view_metrics(scene, frame), method
        assert result.before == before
        assert result.success == is_success(before.surface_coverage, result.after.surface_coverage)
        assert result.raw_success == is_success(before.raw_coverage, result.after.raw_coverage)
    assert views.per_method["leap_nbv"].chosen_index == 3 and views.per_method["stay"].chosen_index == 0
    # Without candidates (a graph failure) every method stays where it is.
    staying = score_methods(scene, before, None, seed=3, score_all_candidates=True,
                            methods_when_staying=["leap_nbv", "stay", "oracle"])
    assert list(staying.per_method) == ["leap_nbv", "stay", "oracle"] and staying.candidate_views is None
    for result in staying.per_method.values():
        assert result.chosen_index == -1
        np.testing.assert_allclose(result.pose.position_m, np.round(start.position, 6))
        assert result.after.surface_coverage == pytest.approx(before.surface_coverage)
