"""Tests of plan_views: the whole plan of a frame equals the pipeline assembled step by step."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from leapnbv_planner.candidates import check_feasibility, generate_candidates
from leapnbv_planner.inputs import CameraInMap, PlanFloor, PlanInputs, PlanTarget
from leapnbv_planner.obstacle_map import centres_in_observation, line_of_sight_clear_fraction, voxel_map_from_centres
from leapnbv_planner.params import nbv_params_class
from leapnbv_planner.plan import PlanInputError, base_goal_frame, plan_views
from leapnbv_planner.scoring import choose_best, score_candidates

K = np.array([[615.0, 0.0, 320.0], [0.0, 615.0, 240.0], [0.0, 0.0, 1.0]])
CAMERA_HEIGHT = 1.2
UP = np.array([0.0, -1.0, 0.0])
# The camera in the map: at (0, 0, 1.2) looking along map +x, level.
CAMERA_IN_MAP = (np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]]), np.array([0.0, 0.0, CAMERA_HEIGHT]))


def frame(seed=7):
    """A person ~3 m ahead, a low box in front of their legs, floor and a far wall."""
    rng = np.random.default_rng(seed)
    n = 3000
    person = np.column_stack([rng.uniform(-0.25, 0.25, n), rng.uniform(-0.5, 1.15, n), rng.uniform(2.85, 3.15, n)])
    floor = np.column_stack([rng.uniform(-3, 3, 400), np.full(400, CAMERA_HEIGHT), rng.uniform(0.5, 6, 400)])
    box = np.column_stack([rng.uniform(-0.4, 0.4, 300), rng.uniform(0.2, CAMERA_HEIGHT, 300), np.full(300, 2.0)])
    wall = np.column_stack([rng.uniform(-3, 3, 400), rng.uniform(-1.0, CAMERA_HEIGHT, 400), np.full(400, 6.0)])
    target = PlanTarget(target_points=person.astype(np.float32),
                        background_points=np.concatenate([floor, box, wall]).astype(np.float32),
                        centroid=np.median(person.astype(np.float32), axis=0).astype(np.float64),
                        k=K, width=640, height=480)
    return target, PlanFloor(normal=UP, offset=CAMERA_HEIGHT)


def obstacle_map():
    """A screen 0.5 m behind the person (map x 3.6-3.9 m) and a pillar 1.5 m to their left: map-frame voxels."""
    def box(lo, hi):
        index = np.stack(np.meshgrid(*[np.arange(a, b) for a, b in zip(lo, hi)], indexing="ij"), -1).reshape(-1, 3)
        return (index + 0.5) * 0.1
    return voxel_map_from_centres(np.concatenate([box((36, -10, 0), (39, 10, 20)), box((29, 14, 0), (32, 17, 20))]),
                                  0.1)


@pytest.mark.parametrize("with_map", [False, True])
@pytest.mark.parametrize("radius", [1.5, 2.5])
def test_plan_views_is_the_step_by_step_pipeline(with_map, radius):
    target, ground = frame()
    # The paper's steps: no path search, every candidate scored.
    params = nbv_params_class()(radius=radius, min_radius=1.0, reachability=False, score_infeasible=True)
    grid = obstacle_map() if with_map else None
    plan = plan_views(target, ground, params, grid, CAMERA_IN_MAP if with_map else None)

    candidates = generate_candidates(target.centroid, UP, CAMERA_HEIGHT, params)
    obstacles, clear = target.background_points, None
    if with_map:
        obstacles = np.concatenate([obstacles, centres_in_observation(grid, *CAMERA_IN_MAP)])
        clear = line_of_sight_clear_fraction(grid, *CAMERA_IN_MAP, candidates.positions, target.target_points,
                                             1500, 0.1)
    feasibility = check_feasibility(candidates, obstacles, UP, CAMERA_HEIGHT, params)
    scores = score_candidates(target.target_points, target.background_points, candidates.rotations,
                              candidates.positions, K, 640, 480, given={"target_line_of_sight": clear})
    chosen = choose_best(scores.score, feasibility.feasible, candidates.positions, np.zeros(3))

    np.testing.assert_array_equal(plan.candidates.rotations, candidates.rotations)
    np.testing.assert_array_equal(plan.candidates.positions, candidates.positions)
    np.testing.assert_array_equal(plan.feasibility.reasons, feasibility.reasons)
    np.testing.assert_array_equal(plan.scores.term_scores, scores.term_scores)
    np.testing.assert_array_equal(plan.scores.score, scores.score)
    assert plan.chosen_index == chosen >= 1
    assert plan.used_obstacle_map == with_map
    if with_map:
        np.testing.assert_array_equal(plan.line_of_sight_clear, clear)
        assert clear.min() < 0.5  # the map matters in this scene
    rotation, position = plan.base_goal
    expected_rotation, expected_position = base_goal_frame(candidates.foot_points[chosen], candidates.ring_center, UP)
    np.testing.assert_array_equal(rotation, expected_rotation)
    np.testing.assert_array_equal(position, candidates.foot_points[chosen])
    np.testing.assert_allclose(rotation[:, 2], UP)
    np.testing.assert_array_equal(plan.chosen_pose()[1], candidates.positions[chosen])


@pytest.mark.parametrize("with_map", [False, True])
def test_only_feasible_candidates_are_scored_by_default(with_map):
    target, ground = frame()
    grid, pose = (obstacle_map(), CAMERA_IN_MAP) if with_map else (None, None)
    params = nbv_params_class()(min_radius=1.0)
    plan = plan_views(target, ground, params, grid, pose)
    every = plan_views(target, ground, dataclasses.replace(params, score_infeasible=True), grid, pose)
    scored = plan.feasibility.feasible
    assert 0 < scored.sum() < len(scored)  # the scene has infeasible candidates
    np.testing.assert_array_equal(plan.feasibility.reasons, every.feasibility.reasons)
    np.testing.assert_array_equal(plan.scores.term_scores[scored], every.scores.term_scores[scored])
    np.testing.assert_array_equal(plan.scores.score[scored], every.scores.score[scored])
    assert np.all(plan.scores.term_scores[~scored] == 0.0) and np.all(plan.scores.score[~scored] == 0.0)
    assert np.any(every.scores.score[~scored] > 0.0)
    assert plan.chosen_index == every.chosen_index >= 1
    if with_map:
        np.testing.assert_array_equal(plan.line_of_sight_clear[scored], every.line_of_sight_clear[scored])
        assert np.all(np.isnan(plan.line_of_sight_clear[~scored]))


def test_camera_pose_as_an_object_or_a_pair_and_map_only_with_a_pose():
    target, ground = frame()
    grid = obstacle_map()
    pose = CameraInMap(rotation=CAMERA_IN_MAP[0], position=CAMERA_IN_MAP[1])
    by_object = plan_views(target, ground, None, grid, pose)
    by_pair = plan_views(target, ground, None, grid, CAMERA_IN_MAP)
    np.testing.assert_array_equal(by_object.scores.score, by_pair.scores.score)
    without_pose = plan_views(target, ground, None, grid, None)
    assert not without_pose.used_obstacle_map
    np.testing.assert_array_equal(without_pose.scores.score, plan_views(target, ground).scores.score)


def test_invalid_target_or_ground_is_refused():
    target, ground = frame()
    with pytest.raises(PlanInputError, match="target"):
        plan_views(dataclasses.replace(target, valid=False), ground)
    with pytest.raises(PlanInputError, match="ground"):
        plan_views(PlanInputs(target, PlanFloor(normal=UP, offset=CAMERA_HEIGHT, valid=False)))


def test_nothing_feasible_gives_no_goal():
    target, ground = frame()
    plan = plan_views(target, ground, nbv_params_class()(include_current=False, max_travel=0.0))
    assert plan.chosen_index == -1 and plan.base_goal is None and plan.chosen_pose() is None


@pytest.mark.ros
def test_plan_converts_to_the_view_candidates_arrays():
    conversions = pytest.importorskip("leapnbv_common.conversions")
    target, ground = frame()
    plan = plan_views(target, ground)
    views = plan.to_arrays()
    assert isinstance(views, conversions.ViewCandidatesArrays)
    assert views.term_names == ["visibility", "area", "body_occlusion", "travel"]
    assert views.chosen_index == plan.chosen_index
    np.testing.assert_array_equal(views.term("body_occlusion"), plan.scores.term("body_occlusion"))
    np.testing.assert_array_equal(views.infeasible_reason, plan.feasibility.reasons.astype(np.uint8))
    assert views.ring_radius == 2.5 and views.includes_current_view
    back = conversions.view_candidates_to_arrays(conversions.arrays_to_view_candidates(views))
    np.testing.assert_allclose(back.term_scores, views.term_scores, atol=1e-7)
    assert back.term_names == views.term_names
