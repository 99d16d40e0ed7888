"""Tests of leapnbv_geometry.ground: RANSAC floor with a tilt prior."""

from __future__ import annotations

import numpy as np
import pytest

from leapnbv_geometry.ground import GroundPlaneError, fit_ground_plane, ground_points_from_depth
from leapnbv_geometry.raster import rasterize_mesh

K_REAL = np.array([[525.0, 0.0, 319.5], [0.0, 525.0, 239.5], [0.0, 0.0, 1.0]])


def tilted_floor(tilt_deg: float = 10.0):
    """Normal of a floor tilted about the x axis, pointing up (-y)."""
    angle = np.radians(tilt_deg)
    return np.array([0.0, -np.cos(angle), np.sin(angle)])


def floor_scene(rng, n_floor=4000, n_wall=4500, n_random=1500):
    normal = tilted_floor(10.0)
    offset = 1.2
    # Floor points: sample x, z and solve the plane for y (exactly on it, plus noise).
    x = rng.uniform(-3.0, 3.0, n_floor)
    z = rng.uniform(1.0, 8.0, n_floor)
    y = -(offset + normal[0] * x + normal[2] * z) / normal[1]
    floor = np.stack([x, y, z], axis=1) + rng.normal(0, 0.004, (n_floor, 1)) * normal
    wall = np.stack([
        rng.uniform(-3.0, 3.0, n_wall), rng.uniform(-2.0, 1.0, n_wall), np.full(n_wall, 6.0)
    ], axis=1) + rng.normal(0, 0.004, (n_wall, 3))
    clutter = np.stack([
        rng.uniform(-3.0, 3.0, n_random), rng.uniform(-2.0, 1.0, n_random), rng.uniform(1.0, 8.0, n_random)
    ], axis=1)
    points = np.vstack([floor, wall, clutter])
    return points[rng.permutation(points.shape[0])], normal, offset


def test_recovers_floor_with_60_percent_outliers_and_a_bigger_wall():
    rng = np.random.default_rng(7)
    points, normal, offset = floor_scene(rng)
    result = fit_ground_plane(points, seed=3)
    assert result.valid
    angle = np.degrees(np.arccos(np.clip(result.normal @ normal, -1.0, 1.0)))
    assert angle < 1.0
    assert abs(result.offset - offset) < 0.01
    assert result.normal @ np.array([0.0, -1.0, 0.0]) > 0.0  # points up
    assert result.offset > 0.0  # camera above the floor
    assert result.inlier_count == np.count_nonzero(result.inlier_mask)
    assert 0.38 <= result.inlier_ratio <= 0.45  # 40 % floor plus the clutter lying on it
    assert result.tilt_deg == pytest.approx(10.0, abs=1.0)


def test_only_a_wall_in_view_is_invalid():
    rng = np.random.default_rng(1)
    wall = np.stack([rng.uniform(-3, 3, 5000), rng.uniform(-2, 1, 5000), np.full(5000, 4.0)], axis=1)
    wall += rng.normal(0, 0.003, wall.shape)
    result = fit_ground_plane(wall)
    assert not result.valid
    # A wall leaning 45 degrees is still beyond the 30 degree prior.
    leaning = wall.copy()
    leaning[:, 2] = 4.0 + leaning[:, 1]
    assert not fit_ground_plane(leaning).valid


def test_deterministic_for_a_seed():
    rng = np.random.default_rng(11)
    points, _, _ = floor_scene(rng)
    first = fit_ground_plane(points, seed=5)
    second = fit_ground_plane(points, seed=5)
    np.testing.assert_array_equal(first.normal, second.normal)
    assert first.offset == second.offset
    np.testing.assert_array_equal(first.inlier_mask, second.inlier_mask)
    other = fit_ground_plane(points, seed=6)
    assert abs(other.offset - first.offset) < 0.01


def test_too_few_inliers_is_invalid():
    rng = np.random.default_rng(2)
    points, _, _ = floor_scene(rng, n_floor=150, n_wall=0, n_random=0)
    assert not fit_ground_plane(points, min_inliers=200).valid
    assert fit_ground_plane(points, min_inliers=100).valid
    assert not fit_ground_plane(np.zeros((0, 3))).valid
    with pytest.raises(GroundPlaneError, match="points"):
        fit_ground_plane(np.zeros((10, 2)))


def test_floor_from_rendered_depth():
    floor = np.array([[-20, 1.1, -5.0], [20, 1.1, -5.0], [20, 1.1, 30.0], [-20, 1.1, 30.0]])
    box = np.array([[-0.5, -0.5, 3.0], [0.5, -0.5, 3.0], [0.5, 1.1, 3.0], [-0.5, 1.1, 3.0]])
    vertices = np.vstack([floor, box])
    faces = np.array([[0, 1, 2], [0, 2, 3], [4, 5, 6], [4, 6, 7]])
    render = rasterize_mesh(vertices, faces, K_REAL, 640, 480)
    person_mask = render.face_index >= 2
    points = ground_points_from_depth(render.depth, K_REAL, exclude_mask=person_mask, stride=4)
    assert points.shape[0] > 3000
    assert np.all(points[:, 2] <= 10.0)
    result = fit_ground_plane(points)
    assert result.valid
    np.testing.assert_allclose(result.normal, [0.0, -1.0, 0.0], atol=1e-4)
    assert result.offset == pytest.approx(1.1, abs=1e-3)
    assert result.inlier_ratio == pytest.approx(1.0)


def test_floor_wins_over_a_larger_box_top_above_it():
    """A table or box top can hold more points than the visible floor; the floor is the lowest."""
    rng = np.random.default_rng(4)
    floor = np.column_stack([rng.uniform(-2, 2, 3000), np.full(3000, 1.2), rng.uniform(2, 6, 3000)])
    top = np.column_stack([rng.uniform(-0.8, 0.8, 4500), np.full(4500, 0.5), rng.uniform(2, 3, 4500)])
    clutter = rng.uniform([-2, -1, 1], [2, 1.2, 6], size=(1500, 3))
    points = np.concatenate([floor, top, clutter]) + rng.normal(0, 0.004, size=(9000, 3))
    result = fit_ground_plane(points, seed=1, local_sampling=False)
    assert result.valid
    assert result.offset == pytest.approx(1.2, abs=0.01)
    assert np.degrees(np.arccos(abs(result.normal @ np.array([0.0, -1.0, 0.0])))) < 1.0
    # With only the best-supported plane allowed, the box top would win: the preference matters.
    assert fit_ground_plane(points, seed=1, local_sampling=False, lowest_plane_share=1.0).offset == \
        pytest.approx(0.5, abs=0.01)
