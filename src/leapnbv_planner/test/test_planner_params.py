"""Tests of the nbv node's parameters: one dataclass, the robot's defaults, ranges and rules enforced."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from leapnbv_common.params import ParamsError, param_specs, params_from_values, replace_params, validate_params
from leapnbv_planner.candidates import check_feasibility, generate_candidates
from leapnbv_planner.params import CandidateRingParams, PlannerParams, default_nbv_params, nbv_params_class

# Every parameter the node had before its params became a dataclass: names do not change.
NODE_PARAMETER_NAMES = {
    "num_candidates", "radius", "include_current", "max_travel", "robot_radius", "floor_clearance",
    "weight_visibility", "weight_area", "weight_occlusion", "delta_px", "ground_wait_s", "ground_max_age_s",
    "use_obstacle_map", "obstacle_map_resolution", "map_max_target_points", "map_target_margin", "camera_pose_cache",
}

# The robot's values (src/leapnbv_bringup/config/leapnbv.yaml when the params became a dataclass).
ROBOT_VALUES = {
    "num_candidates": 16, "radius": 2.5, "include_current": True, "max_travel": 6.0, "robot_radius": 0.3,
    "floor_clearance": 0.05, "weight_visibility": 0.03, "weight_area": 0.14, "weight_occlusion": 0.83,
    "delta_px": 4.0, "ground_wait_s": 0.5, "ground_max_age_s": 0.5, "use_obstacle_map": True,
    "obstacle_map_resolution": 0.1, "map_max_target_points": 1500, "map_target_margin": 0.1, "camera_pose_cache": 150,
    "max_goal_age_s": 1.0, "camera_pose_wait_s": 0.1, "num_rings": 3, "min_radius": 1.5, "reachability": True,
    "weight_body_occlusion": 0.83, "max_stamp_ahead_s": 0.5, "max_obstacle_voxels": 200_000,
    "commit_goals": True, "commit_margin": 0.02, "commit_margin_without_map": 0.05, "commit_person_moved_m": 0.5,
    "commit_same_goal_m": 0.25,
    "commit_blocked_s": 0.6, "commit_dropped_s": 5.0, "commit_dropped_radius_m": 1.0,
    "obstacle_memory": False, "obstacle_memory_half_life_s": 20.0, "obstacle_memory_max_voxels": 50_000,
}
# One frame per output and no stale goal: the frame's own plane is waited for 0.5 s, an older
# plane is carried (by the camera-pose delta) from at most 0.5 s back, goals are at most 1 s old, and the pose
# cache covers 5 s at 30 Hz.


def test_defaults_are_the_robot_values_and_valid():
    params = default_nbv_params()
    validate_params(params)
    names = {spec.name for spec in param_specs(type(params))}
    assert NODE_PARAMETER_NAMES <= names
    assert names - NODE_PARAMETER_NAMES == {
        "score_terms", "camera_pose_source", "max_goal_age_s", "hidden_target_goal_hold_s", "camera_pose_wait_s",
        "body_mesh_wait_s",
        "weight_travel", "weight_body_occlusion", "num_rings", "min_radius", "reachability", "max_path_length",
        "grid_resolution", "unknown_space", "camera_height", "camera_tilt", "score_infeasible", "fit_to_free_space",
        "min_free_radius", "max_stamp_ahead_s", "max_obstacle_voxels", "commit_goals", "commit_margin",
        "commit_margin_without_map", "commit_person_moved_m", "commit_same_goal_m", "commit_blocked_s",
        "commit_dropped_s",
        "commit_dropped_radius_m", "visibility_points", "visibility_min_depth",
        "visibility_max_depth", "obstacle_memory", "obstacle_memory_half_life_s", "obstacle_memory_max_voxels"}
    for name, value in ROBOT_VALUES.items():
        assert getattr(params, name) == value, name
    assert params.score_terms == ["visibility", "area", "body_occlusion", "travel"]
    assert params.camera_pose_source == "topic"
    for spec in param_specs(type(params)):
        assert spec.description, spec.name


def test_ring_code_takes_its_defaults_from_the_node_params():
    ring, node = CandidateRingParams(), default_nbv_params()
    assert isinstance(node, CandidateRingParams) and isinstance(node, PlannerParams)
    for f in dataclasses.fields(CandidateRingParams):
        assert getattr(ring, f.name) == getattr(node, f.name), f.name
    # The node's params instance drives the ring and the feasibility test as they are.
    centroid, up = np.array([0.0, 0.3, 3.0]), np.array([0.0, -1.0, 0.0])
    candidates = generate_candidates(centroid, up, 1.2, node)
    assert len(candidates) == 1 + 3 * 16  # the current view and three rings: 1.5, 2.0, 2.5 m
    radii = np.linalg.norm(candidates.foot_points[1:] - candidates.ring_center, axis=1)
    np.testing.assert_allclose(radii, np.repeat([1.5, 2.0, 2.5], 16))
    feasible, _ = check_feasibility(candidates, np.zeros((0, 3)), up, 1.2, node)
    travel = np.linalg.norm(candidates.foot_points - candidates.foot_points[0], axis=1)
    np.testing.assert_array_equal(feasible, travel <= 6.0)


@pytest.mark.parametrize("name, value, message", [
    ("radius", -1.0, "radius = -1.0 is below its minimum"),
    ("radius", 0.0, "below its minimum"),
    ("num_candidates", 0, "num_candidates"),
    ("num_candidates", 2.5, "must be a int"),
    ("max_travel", float("nan"), "NaN"),
    ("weight_area", -0.1, "weight_area"),
    ("delta_px", -1.0, "delta_px"),
    ("score_terms", ["visibility", "sharpness"], "unknown score term 'sharpness'"),
    ("score_terms", ["area", "occlusion", "area"], "more than once"),
    ("score_terms", [], "at least one"),
])
def test_invalid_values_are_refused_with_the_name(name, value, message):
    with pytest.raises(ParamsError, match=message):
        params_from_values(nbv_params_class(), {name: value})
    with pytest.raises(ParamsError, match=message):
        replace_params(default_nbv_params(), {name: value})


def test_read_only_parameters_are_those_that_make_subscriptions():
    read_only = {spec.name for spec in param_specs(nbv_params_class()) if spec.read_only}
    assert read_only == {"use_obstacle_map", "camera_pose_source", "camera_pose_cache"}
    with pytest.raises(ParamsError, match="read-only"):
        replace_params(default_nbv_params(), {"use_obstacle_map": False})
    changed = replace_params(default_nbv_params(), {"radius": 2.0, "score_terms": ["occlusion"]})
    assert changed.radius == 2.0 and changed.term_weights() == [("occlusion", 0.83)]


def test_the_params_class_is_made_once_per_set_of_terms():
    assert nbv_params_class() is nbv_params_class()
    assert nbv_params_class().__name__ == "NbvParams"
