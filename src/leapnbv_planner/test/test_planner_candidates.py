"""Tests of the candidate ring (geometry of each pose) and of the feasibility test."""

from __future__ import annotations

import numpy as np
import pytest

from leapnbv_planner.candidates import (
    CandidateGenerationError,
    CandidateRingParams,
    FeasibilityReason,
    camera_look_at,
    check_feasibility,
    generate_candidates,
)

LEVEL_NORMAL = np.array([0.0, -1.0, 0.0])
LEVEL_OFFSET = 1.2  # floor at y = 1.2: the camera is 1.2 m above it



def single_ring(**values) -> CandidateRingParams:
    """One ring, no path search: the geometry these tests check by hand (the robot's defaults add rings and
    reachability, tested in test_planner_reachability)."""
    return CandidateRingParams(**{"num_rings": 1, "reachability": False, **values})

def tilted_plane():
    """A floor seen by a camera pitched down ~12 deg and rolled ~5 deg, 1.35 m above it."""
    normal = np.array([0.08, -0.97, -0.21])
    normal /= np.linalg.norm(normal)
    return normal, 1.35


def test_candidate_zero_is_the_current_pose():
    candidates = generate_candidates(
        np.array([0.3, 0.2, 3.0]), LEVEL_NORMAL, LEVEL_OFFSET, single_ring()
    )
    assert len(candidates) == 17
    np.testing.assert_array_equal(candidates.rotations[0], np.eye(3))
    np.testing.assert_array_equal(candidates.positions[0], np.zeros(3))
    np.testing.assert_allclose(candidates.foot_points[0], [0.0, 1.2, 0.0])
    assert candidates.is_current.tolist() == [True] + [False] * 16
    assert candidates.camera_height == pytest.approx(1.2)


def test_without_current_view_only_the_ring():
    params = single_ring(num_candidates=8, include_current=False)
    candidates = generate_candidates(np.array([0.0, 0.2, 3.0]), LEVEL_NORMAL, 1.2, params)
    assert len(candidates) == 8
    assert not candidates.is_current.any()


@pytest.mark.parametrize("plane", ["level", "tilted"])
def test_ring_poses_look_at_the_centroid_at_camera_height(plane):
    normal, offset = (LEVEL_NORMAL, LEVEL_OFFSET) if plane == "level" else tilted_plane()
    centroid = np.array([0.4, 0.25, 2.7])
    params = single_ring(num_candidates=16, radius=1.5)
    candidates = generate_candidates(centroid, normal, offset, params)
    ring_center = centroid - (normal @ centroid + offset) * normal
    np.testing.assert_allclose(candidates.ring_center, ring_center, atol=1e-12)
    assert abs(normal @ candidates.ring_center + offset) < 1e-12

    for index in range(1, len(candidates)):
        rotation = candidates.rotations[index]
        position = candidates.positions[index]
        x_axis, y_axis, z_axis = rotation[:, 0], rotation[:, 1], rotation[:, 2]
        # Optical axis passes within 1 cm of the centroid, in front of the camera.
        to_centroid = centroid - position
        assert to_centroid @ z_axis > 0
        miss = np.linalg.norm(to_centroid - (to_centroid @ z_axis) * z_axis)
        assert miss < 0.01
        # Height above the plane equals the current camera's.
        assert abs(normal @ position + offset - offset) < 1e-3
        # x parallel to the ground, y pointing down, right-handed orthonormal frame.
        assert abs(x_axis @ normal) < 1e-6
        assert y_axis @ normal < 0
        np.testing.assert_allclose(rotation.T @ rotation, np.eye(3), atol=1e-12)
        assert np.linalg.det(rotation) == pytest.approx(1.0, abs=1e-12)
        np.testing.assert_allclose(np.cross(x_axis, y_axis), z_axis, atol=1e-12)
        # Foot point on the plane at radius r from the ring centre.
        foot = candidates.foot_points[index]
        assert abs(normal @ foot + offset) < 1e-9
        assert np.linalg.norm(foot - ring_center) == pytest.approx(1.5, abs=1e-9)
        np.testing.assert_allclose(position - foot, offset * normal, atol=1e-9)


def test_first_ring_candidate_is_on_the_current_bearing_and_ring_turns_counterclockwise():
    centroid = np.array([1.0, 0.3, 3.0])
    candidates = generate_candidates(centroid, LEVEL_NORMAL, LEVEL_OFFSET, single_ring())
    center = candidates.ring_center
    current_bearing = candidates.foot_points[0] - center
    first = candidates.foot_points[1] - center
    cosine = current_bearing @ first / np.linalg.norm(current_bearing) / np.linalg.norm(first)
    assert cosine == pytest.approx(1.0, abs=1e-12)
    # Counter-clockwise seen from above = positive turn about the up normal.
    second = candidates.foot_points[2] - center
    assert np.cross(first, second) @ LEVEL_NORMAL > 0
    # Angles are evenly spaced by 360/16 degrees.
    angle = np.arccos(first @ second / np.linalg.norm(first) / np.linalg.norm(second))
    assert angle == pytest.approx(2 * np.pi / 16, abs=1e-9)


def test_look_at_straight_ahead_on_level_ground_is_identity():
    rotation = camera_look_at(np.zeros(3), np.array([0.0, 0.0, 4.0]), LEVEL_NORMAL)
    np.testing.assert_allclose(rotation, np.eye(3), atol=1e-15)


def test_look_at_straight_down_still_gives_a_rotation():
    rotation = camera_look_at(np.zeros(3), np.array([0.0, 2.0, 0.0]), LEVEL_NORMAL)
    np.testing.assert_allclose(rotation[:, 2], [0.0, 1.0, 0.0])
    assert np.linalg.det(rotation) == pytest.approx(1.0)


def test_camera_below_the_plane_is_rejected():
    with pytest.raises(CandidateGenerationError, match="not above the ground plane"):
        generate_candidates(np.array([0.0, 0.0, 3.0]), LEVEL_NORMAL, -1.2, single_ring())


def test_obstacle_at_a_foot_point_makes_it_infeasible():
    params = single_ring(num_candidates=8, radius=1.5, robot_radius=0.3,
                                 floor_clearance=0.05, max_travel=10.0)
    candidates = generate_candidates(np.array([0.0, 0.3, 3.0]), LEVEL_NORMAL, 1.2, params)
    blocked_index, floor_index, near_miss_index = 3, 5, 7
    up = LEVEL_NORMAL  # n points up
    background = np.array([
        # 0.5 m high, 0.2 m (horizontally) from candidate 3's foot point: an obstacle.
        candidates.foot_points[blocked_index] + 0.5 * up + np.array([0.2, 0.0, 0.0]),
        # On candidate 5's foot point but only 0.03 m high: floor, not an obstacle.
        candidates.foot_points[floor_index] + 0.03 * up,
        # 1 m high but 0.35 m away from candidate 7's foot point: outside the footprint.
        candidates.foot_points[near_miss_index] + 1.0 * up + np.array([0.0, 0.0, 0.35]),
        # Right at the current camera's foot point: the current view stays feasible.
        candidates.foot_points[0] + 0.5 * up,
    ])
    feasible, reasons = check_feasibility(candidates, background, LEVEL_NORMAL, 1.2, params)
    expected = np.ones(len(candidates), dtype=bool)
    expected[blocked_index] = False
    np.testing.assert_array_equal(feasible, expected)
    assert reasons[blocked_index] == FeasibilityReason.OBSTACLE
    assert reasons[0] == FeasibilityReason.OK
    assert (reasons[expected] == FeasibilityReason.OK).all()


def test_candidates_beyond_travel_range_are_infeasible():
    # Target 3 m ahead: the current foot point is 3 m from the ring centre, ring foot points
    # are between 1.5 and 4.5 m away from it.
    params = single_ring(num_candidates=16, radius=1.5, max_travel=3.0)
    candidates = generate_candidates(np.array([0.0, 0.3, 3.0]), LEVEL_NORMAL, 1.2, params)
    travel = np.linalg.norm(candidates.foot_points - candidates.foot_points[0], axis=1)
    feasible, reasons = check_feasibility(candidates, np.zeros((0, 3)), LEVEL_NORMAL, 1.2, params)
    np.testing.assert_array_equal(feasible, travel <= 3.0)
    assert (~feasible).sum() >= 5
    assert (reasons[~feasible] == FeasibilityReason.OUT_OF_TRAVEL_RANGE).all()


def test_feasibility_on_a_tilted_plane_uses_plane_distances():
    normal, offset = tilted_plane()
    params = single_ring(num_candidates=6, radius=1.5, robot_radius=0.3, max_travel=10.0)
    candidates = generate_candidates(np.array([0.2, 0.3, 3.0]), normal, offset, params)
    e1 = np.cross(normal, [1.0, 0.0, 0.0])
    e1 /= np.linalg.norm(e1)
    # 2 m above candidate 2's foot point along n and 0.29 m aside in the plane: blocked.
    # Same for candidate 4 but 0.31 m aside: free.
    background = np.array([
        candidates.foot_points[2] + 2.0 * normal + 0.29 * e1,
        candidates.foot_points[4] + 2.0 * normal + 0.31 * e1,
    ])
    feasible, _ = check_feasibility(candidates, background, normal, offset, params)
    assert feasible.tolist() == [True, True, False, True, True, True, True]
