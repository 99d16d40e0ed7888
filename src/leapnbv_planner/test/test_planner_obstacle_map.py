"""Tests of the voxel obstacle map: grid building, the line-of-sight walk, and its use in S_o."""

from __future__ import annotations

import numpy as np
import pytest
from reference_planner_kernels import segments_clear

from leapnbv_planner.obstacle_map import (
    ObstacleMapError,
    centres_in_observation,
    line_of_sight_clear_fraction,
    voxel_map_from_centres,
)
from leapnbv_planner.scoring import score_candidates as _score_candidates

RES = 0.1



# The paper's three terms, which these tests check (the deployed default scores body_occlusion instead of occlusion).
PAPER_TERMS = [("visibility", 0.03), ("area", 0.14), ("occlusion", 0.83)]


def score_candidates(*args, **kwargs):
    kwargs.setdefault("terms", PAPER_TERMS)
    return _score_candidates(*args, **kwargs)

def box_centres(lower, upper, res=RES):
    """Centres of the voxels of the box [lower, upper) (corners on voxel boundaries)."""
    index = [np.arange(int(round(lo / res)), int(round(hi / res))) for lo, hi in zip(lower, upper)]
    grid = np.stack(np.meshgrid(*index, indexing="ij"), axis=-1).reshape(-1, 3)
    return (grid + 0.5) * res


def cells_by_sampling(occupied, lower_index, res, origin, target, margin, samples=200_000):
    """Reference: is any occupied cell hit by densely sampled points of the shortened segment?"""
    length = np.linalg.norm(target - origin)
    t = np.linspace(0.0, 1.0 - margin / length, samples)
    points = origin[None, :] + t[:, None] * (target - origin)[None, :]
    cells = np.floor(points / res).astype(np.int64) - lower_index
    inside = np.all((cells >= 0) & (cells < np.array(occupied.shape)), axis=1)
    cells = cells[inside]
    return not occupied[cells[:, 0], cells[:, 1], cells[:, 2]].any()


def test_grid_marks_exactly_the_given_voxels():
    centres = box_centres((0.0, -0.2, 0.0), (0.3, 0.2, 0.5))
    grid = voxel_map_from_centres(centres, RES)
    assert grid.occupied.shape == (3, 4, 5)
    assert grid.occupied.all()
    assert grid.lower_index.tolist() == [0, -2, 0]
    assert grid.voxel_count == 60
    np.testing.assert_allclose(np.sort(grid.centres, axis=0), np.sort(centres, axis=0), atol=1e-12)


def test_grid_rejects_bad_input_by_name():
    with pytest.raises(ObstacleMapError, match="resolution"):
        voxel_map_from_centres(np.zeros((1, 3)), 0.0)
    with pytest.raises(ObstacleMapError, match=r"\(N, 3\)"):
        voxel_map_from_centres(np.zeros((4, 2)), RES)
    with pytest.raises(ObstacleMapError, match="cells"):
        voxel_map_from_centres(np.array([[0.0, 0.0, 0.0], [1e4, 1e4, 10.0]]), RES)
    empty = voxel_map_from_centres(np.zeros((0, 3)), RES)
    assert empty.voxel_count == 0 and not empty.occupied.any()


def test_walk_matches_dense_sampling_on_random_segments():
    rng = np.random.default_rng(3)
    occupied = rng.random((12, 10, 8)) < 0.08
    lower = np.array([-6, -5, 0])
    origins = rng.uniform([-0.8, -0.7, -0.2], [0.8, 0.7, 1.0], (6, 3))
    targets = rng.uniform([-0.8, -0.7, -0.2], [0.8, 0.7, 1.0], (40, 3))
    clear = segments_clear(occupied, lower.astype(np.float64), RES, origins, targets, 0.05)
    expected = np.array([[cells_by_sampling(occupied, lower, RES, o, q, 0.05) for q in targets] for o in origins])
    assert 0.1 < expected.mean() < 0.9  # both outcomes are exercised
    np.testing.assert_array_equal(clear, expected)


def test_wall_between_camera_and_person_blocks_every_line_of_sight():
    # A wall 2 m wide, 2 m tall, at x in [1.0, 1.1); the person stands at x = 2.
    grid = voxel_map_from_centres(box_centres((1.0, -1.0, 0.0), (1.1, 1.0, 2.0)), RES)
    person = np.column_stack([np.full(50, 2.0), np.linspace(-0.2, 0.2, 50), np.linspace(0.1, 1.7, 50)])
    cameras = np.array([[0.0, 0.0, 1.2], [3.5, 0.0, 1.2], [2.0, -2.5, 1.2]])  # behind the wall, beyond, beside
    fraction = line_of_sight_clear_fraction(grid, np.eye(3), np.zeros(3), cameras, person)
    np.testing.assert_allclose(fraction, [0.0, 1.0, 1.0])


def test_low_cabinet_hides_only_the_legs():
    # A cabinet 0.9 m tall between the camera (at 1.2 m) and a vertical line of target points.
    grid = voxel_map_from_centres(box_centres((1.0, -0.5, 0.0), (1.5, 0.5, 0.9)), RES)
    heights = np.linspace(0.05, 1.75, 69)
    person = np.column_stack([np.full(69, 2.5), np.zeros(69), heights])
    camera = np.array([[0.0, 0.0, 1.2]])
    fraction = float(line_of_sight_clear_fraction(grid, np.eye(3), np.zeros(3), camera, person)[0])
    # The segment to height h leaves the cabinet's far top edge (x = 1.5, z = 0.9) clear when
    # it is above 0.9 there: 1.2 + (h - 1.2) * 1.5 / 2.5 >= 0.9  <=>  h >= 0.7.
    assert fraction == pytest.approx(np.mean(heights >= 0.7), abs=1.0 / 69)


def test_map_frame_is_applied_to_cameras_targets_and_centres():
    # The observation camera looks along map +x from (0, 0, 1.2): optical z = map x, x = -map y, y = -map z.
    rotation = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
    position = np.array([0.0, 0.0, 1.2])
    grid = voxel_map_from_centres(box_centres((1.0, -1.0, 0.0), (1.1, 1.0, 2.0)), RES)
    in_camera = centres_in_observation(grid, rotation, position)
    np.testing.assert_allclose(in_camera[:, 2].min(), 1.05, atol=1e-9)  # the wall lies 1.05 m ahead
    np.testing.assert_allclose(in_camera[:, 1].max(), 1.15, atol=1e-9)  # its foot, 1.15 m below the camera
    target = np.array([[0.0, 0.0, 2.0]])  # 2 m ahead of the camera: beyond the wall
    cameras = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 3.0]])
    np.testing.assert_allclose(line_of_sight_clear_fraction(grid, rotation, position, cameras, target), [0.0, 1.0])
    with pytest.raises(ObstacleMapError, match="rotation"):
        line_of_sight_clear_fraction(grid, 2.0 * rotation, position, cameras, target)


def test_clear_fraction_scales_s_o_only():
    rng = np.random.default_rng(0)
    target = rng.uniform([-0.2, -0.8, 2.8], [0.2, 0.8, 3.2], (500, 3))
    poses = (np.stack([np.eye(3)] * 2), np.zeros((2, 3)))
    k = np.array([[300.0, 0.0, 160.0], [0.0, 300.0, 120.0], [0.0, 0.0, 1.0]])
    plain = score_candidates(target, np.zeros((0, 3)), *poses, k, 320, 240)
    scaled = score_candidates(target, np.zeros((0, 3)), *poses, k, 320, 240,
                              given={"target_line_of_sight": [0.25, 1.0]})
    np.testing.assert_allclose(scaled.term("occlusion"), plain.term("occlusion") * [0.25, 1.0])
    np.testing.assert_allclose(scaled.term("area"), plain.term("area"))
    np.testing.assert_allclose(plain.score - scaled.score, 0.83 * 0.75 * plain.term("occlusion") * [1.0, 0.0])
    with pytest.raises(ValueError, match="target_line_of_sight"):
        score_candidates(target, np.zeros((0, 3)), *poses, k, 320, 240, given={"target_line_of_sight": [1.5, 1.0]})
