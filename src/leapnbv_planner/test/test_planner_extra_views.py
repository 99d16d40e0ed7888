"""Tests of PlanInputs.extra_foot_points: views planned beside the ring, with its rules and terms, never chosen."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from test_planner_plan import CAMERA_HEIGHT, CAMERA_IN_MAP, UP, frame, obstacle_map

from leapnbv_planner.candidates import CandidateGenerationError, FeasibilityReason
from leapnbv_planner.inputs import PlanInputs
from leapnbv_planner.params import nbv_params_class
from leapnbv_planner.plan import Plan, plan_views


def _plan(extra=None, with_map=False, **params) -> Plan:
    target, ground = frame()
    grid, pose = (obstacle_map(), CAMERA_IN_MAP) if with_map else (None, None)
    return plan_views(PlanInputs(target, ground, nbv_params_class()(**params), grid,
                                 None if pose is None else _pose(pose), extra_foot_points=extra))


def _pose(pair):
    from leapnbv_planner.inputs import CameraInMap
    return CameraInMap(*pair)


def _assert_same_ring(a: Plan, b: Plan) -> None:
    np.testing.assert_array_equal(a.candidates.rotations, b.candidates.rotations)
    np.testing.assert_array_equal(a.candidates.positions, b.candidates.positions)
    np.testing.assert_array_equal(a.feasibility.reasons, b.feasibility.reasons)
    np.testing.assert_array_equal(a.scores.term_scores, b.scores.term_scores)
    np.testing.assert_array_equal(a.scores.score, b.scores.score)
    np.testing.assert_array_equal(a.path_lengths, b.path_lengths)
    assert a.chosen_index == b.chosen_index
    np.testing.assert_array_equal(a.base_goal[1], b.base_goal[1])
    np.testing.assert_array_equal(a.base_path, b.base_path)


@pytest.mark.parametrize("with_map", [False, True])
def test_a_view_at_a_ring_candidates_foot_point_scores_as_that_candidate(with_map):
    plain = _plan(with_map=with_map, min_radius=1.0)
    assert plain.extra is None
    feasible = np.flatnonzero(plain.feasibility.feasible & ~plain.candidates.is_current)
    picks = feasible[[0, len(feasible) // 2, -1]]
    planned = _plan(plain.candidates.foot_points[picks], with_map=with_map, min_radius=1.0)
    _assert_same_ring(plain, planned)  # the ring never sees the extra views
    extra = planned.extra
    assert extra is not None and len(extra) == 3
    np.testing.assert_array_equal(extra.feasibility.reasons, np.zeros(3))
    np.testing.assert_allclose(extra.candidates.positions, plain.candidates.positions[picks], atol=1e-12)
    np.testing.assert_allclose(extra.candidates.rotations, plain.candidates.rotations[picks], atol=1e-12)
    np.testing.assert_array_equal(extra.path_lengths, plain.path_lengths[picks])
    np.testing.assert_allclose(extra.scores.term_scores, plain.scores.term_scores[picks], atol=1e-12)
    np.testing.assert_allclose(extra.scores.score, plain.scores.score[picks], atol=1e-12)
    assert extra.scores.term_names == plain.scores.term_names
    rotation, position = extra.base_goal(1)
    np.testing.assert_allclose(position, plain.candidates.foot_points[picks[1]], atol=1e-12)
    np.testing.assert_allclose(rotation[:, 2], UP)
    # The path to it ends at its foot point and is the ring candidate's path.
    path = extra.base_paths[2]
    assert path is not None
    np.testing.assert_allclose(path[-1], plain.candidates.foot_points[picks[2]], atol=1e-12)
    np.testing.assert_array_equal(path, plain.reach.path_to(plain.candidates.foot_points[picks[2]]))
    assert len(path) > 2


def test_extra_views_are_infeasible_for_the_rings_reasons():
    # In the box before the person (z = 2, |x| <= 0.4); 7 m away (beyond max_travel); 5 m to the left, within the
    # travel range but off the floor grid, which spans the ring and 1 m more (no path known): unreachable.
    feet = np.array([[0.0, CAMERA_HEIGHT, 2.0], [0.0, CAMERA_HEIGHT, 7.0], [-5.0, CAMERA_HEIGHT, 0.5]])
    plan = _plan(feet, min_radius=1.0)
    extra = plan.extra
    assert extra is not None
    assert extra.feasibility.reasons.tolist() == [int(FeasibilityReason.OBSTACLE),
                                                   int(FeasibilityReason.OUT_OF_TRAVEL_RANGE),
                                                   int(FeasibilityReason.UNREACHABLE)]
    assert not extra.feasibility.feasible.any()
    np.testing.assert_array_equal(extra.scores.score, np.zeros(3))  # not scored, as the ring's infeasible ones
    assert extra.base_paths == [None, None, None]
    assert np.isinf(extra.path_lengths[2])
    every = _plan(feet, min_radius=1.0, score_infeasible=True).extra
    assert every is not None and every.scores.score[0] > 0.0  # scored on request, still infeasible
    # Without the path search the third is feasible (travel range and footprint only).
    no_paths = _plan(feet, min_radius=1.0, reachability=False).extra
    assert no_paths is not None and no_paths.path_lengths is None
    assert no_paths.feasibility.reasons.tolist() == [int(FeasibilityReason.OBSTACLE),
                                                      int(FeasibilityReason.OUT_OF_TRAVEL_RANGE), 0]
    assert no_paths.scores.score[2] > 0.0


def test_extra_views_stand_on_this_frames_floor():
    # A foot point 4 cm below the floor (planned on another frame's plane) is put on it, the camera at the height.
    feet = np.array([[1.5, CAMERA_HEIGHT + 0.04, 1.5]])
    extra = _plan(feet).extra
    assert extra is not None
    np.testing.assert_allclose(extra.candidates.foot_points[0], [1.5, CAMERA_HEIGHT, 1.5], atol=1e-12)
    np.testing.assert_allclose(extra.candidates.positions[0], [1.5, 0.0, 1.5], atol=1e-12)
    # Aimed at the centroid, level x (the ring's look_at).
    target, _ = frame()
    z_axis = extra.candidates.rotations[0][:, 2]
    aim = target.centroid - extra.candidates.positions[0]
    np.testing.assert_allclose(z_axis, aim / np.linalg.norm(aim), atol=1e-12)
    assert abs(extra.candidates.rotations[0][:, 0] @ UP) < 1e-12


def test_no_extra_views_and_bad_ones():
    empty = _plan(np.zeros((0, 3)))
    assert empty.extra is not None and len(empty.extra) == 0 and empty.extra.scores.score.shape == (0,)
    with pytest.raises(CandidateGenerationError, match="extra_foot_points"):
        _plan(np.array([[np.nan, 0.0, 1.0]]))
    with pytest.raises(CandidateGenerationError, match="extra_foot_points"):
        _plan(np.zeros((2, 2)))


def test_the_old_call_form_has_no_extra_views():
    target, ground = frame()
    assert plan_views(target, ground).extra is None
    assert dataclasses.fields(PlanInputs)[-1].name == "extra_foot_points"  # optional, last: positional calls hold


def _distance_to_plate(feet: np.ndarray) -> np.ndarray:
    """Metres in the floor plane from foot points to frame()'s box (a plate at z = 2, |x| <= 0.4)."""
    dx = np.maximum(np.abs(feet[:, 0]) - 0.4, 0.0)
    return np.hypot(dx, feet[:, 2] - 2.0)


def test_a_view_on_the_edge_of_free_space_moves_into_it_within_the_same_goal_distance():
    # 0.15 m before the plate (the robot's radius is 0.3): the footprint holds it. Free space begins 0.15 m back,
    # within commit_same_goal_m (0.25): the view moves there, as the ring's candidates do, and is feasible.
    feet = np.array([[0.0, CAMERA_HEIGHT, 1.85], [0.0, CAMERA_HEIGHT, 2.0]])  # the second: on the plate, 0.3 deep
    plan = _plan(feet, min_radius=1.0)
    extra = plan.extra
    assert extra is not None and extra.nudged_m is not None
    assert extra.feasibility.reasons.tolist() == [int(FeasibilityReason.OK), int(FeasibilityReason.OBSTACLE)]
    moved = extra.candidates.foot_points[0]
    assert 0.15 <= extra.nudged_m[0] <= 0.25 + 1e-12 and extra.nudged_m[1] == 0.0
    assert np.linalg.norm(moved - feet[0]) == pytest.approx(extra.nudged_m[0], abs=1e-9)
    assert _distance_to_plate(moved[None])[0] >= 0.3 > _distance_to_plate(feet[:1])[0]
    assert moved[1] == pytest.approx(CAMERA_HEIGHT, abs=1e-12)  # on the floor
    np.testing.assert_array_equal(extra.candidates.foot_points[1], feet[1])  # nothing free within 0.25 m
    # It is scored and has a path to where it now stands, and its camera is the mounting rule's at that foot point.
    assert extra.scores.score[0] > 0.0 and extra.base_paths[0] is not None
    np.testing.assert_allclose(extra.base_paths[0][-1], moved, atol=1e-9)
    at_moved = _plan(moved[None], min_radius=1.0).extra
    assert at_moved is not None and at_moved.nudged_m is not None and at_moved.nudged_m[0] == 0.0
    np.testing.assert_allclose(extra.candidates.positions[0], at_moved.candidates.positions[0], atol=1e-12)
    np.testing.assert_allclose(extra.scores.score[0], at_moved.scores.score[0], atol=1e-12)


@pytest.mark.parametrize("params", [dict(fit_to_free_space=False), dict(commit_same_goal_m=0.0),
                                    dict(commit_same_goal_m=0.1)])
def test_a_blocked_view_stays_blocked_without_the_fit_or_beyond_the_same_goal_distance(params):
    feet = np.array([[0.0, CAMERA_HEIGHT, 1.85]])
    extra = _plan(feet, min_radius=1.0, **params).extra
    assert extra is not None and extra.nudged_m is not None
    assert extra.feasibility.reasons.tolist() == [int(FeasibilityReason.OBSTACLE)]
    assert extra.nudged_m.tolist() == [0.0]
    np.testing.assert_array_equal(extra.candidates.foot_points, feet)


def test_the_nudge_is_the_same_for_a_mirror_image():
    # The plate is symmetric about x = 0: a foot point at x and its mirror at -x move to mirror images.
    left = _plan(np.array([[-0.3, CAMERA_HEIGHT, 1.85]]), min_radius=1.0).extra
    right = _plan(np.array([[0.3, CAMERA_HEIGHT, 1.85]]), min_radius=1.0).extra
    assert left is not None and right is not None and left.nudged_m is not None and right.nudged_m is not None
    assert left.nudged_m[0] == pytest.approx(right.nudged_m[0], abs=1e-9) and left.nudged_m[0] > 0.0
    assert left.candidates.foot_points[0][2] == pytest.approx(right.candidates.foot_points[0][2], abs=1e-9)
