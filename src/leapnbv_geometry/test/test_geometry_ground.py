"""Tests of leapnbv_geometry.ground: RANSAC floor with a tilt prior."""

from __future__ import annotations

import numpy as np
import pytest

from leapnbv_geometry.ground import (
    GroundPlaneError,
    fit_ground_plane,
    floor_plane_from_camera_pose,
    ground_points_from_depth,
)
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


# ----------------------------------------------------------------------------- floor from the camera pose


def camera_rotation(yaw_deg: float, pitch_down_deg: float) -> np.ndarray:
    """T_world_cameraOptical rotation (columns: optical x right, y down, z forward in a z-up world)
    of a camera looking along the world heading ``yaw_deg``, pitched down by ``pitch_down_deg``."""
    yaw, pitch = np.radians(yaw_deg), np.radians(pitch_down_deg)
    heading = np.array([np.cos(yaw), np.sin(yaw), 0.0])
    left = np.array([-np.sin(yaw), np.cos(yaw), 0.0])
    forward = np.cos(pitch) * heading - np.sin(pitch) * np.array([0.0, 0.0, 1.0])
    down = -np.sin(pitch) * heading - np.cos(pitch) * np.array([0.0, 0.0, 1.0])
    return np.column_stack([-left, down, forward])


def test_floor_from_a_camera_1_2_m_high_pitched_down_10_degrees():
    rotation = camera_rotation(0.0, 10.0)
    assert np.allclose(rotation.T @ rotation, np.eye(3)) and np.linalg.det(rotation) == pytest.approx(1.0)
    normal, offset = floor_plane_from_camera_pose(rotation, np.array([0.3, -0.7, 1.2]))
    angle = np.radians(10.0)
    # Up is -y of a level optical frame; pitched down, the world's up leans back (toward -z), and
    # the optical axis meets the floor 1.2 / sin(10 deg) ahead.
    np.testing.assert_allclose(normal, [0.0, -np.cos(angle), -np.sin(angle)], atol=1e-12)
    assert offset == pytest.approx(1.2, abs=1e-12)
    assert normal @ np.array([0.0, 0.0, 1.2 / np.sin(angle)]) + offset == pytest.approx(0.0, abs=1e-9)
    assert normal @ np.array([0.0, -1.0, 0.0]) > 0.0  # n points up, like RANSAC's planes


@pytest.mark.parametrize("yaw_deg,pitch_deg,position", [
    (0.0, 10.0, (0.0, 0.0, 1.2)),
    (37.0, 25.0, (4.0, -2.5, 0.9)),
    (-120.0, -5.0, (-1.0, 3.0, 2.0)),   # pitched up
    (200.0, 80.0, (0.5, 0.5, 0.4)),     # looking almost straight down
])
def test_world_floor_points_lie_on_the_plane_in_the_camera_frame(yaw_deg, pitch_deg, position):
    rotation, position = camera_rotation(yaw_deg, pitch_deg), np.array(position)
    normal, offset = floor_plane_from_camera_pose(rotation, position)
    assert np.linalg.norm(normal) == pytest.approx(1.0, abs=1e-12)
    rng = np.random.default_rng(3)
    floor_world = np.column_stack([rng.uniform(-10, 10, (500, 2)), np.zeros(500)])
    floor_camera = (floor_world - position) @ rotation  # x_c = R^T (x_w - p), row-wise
    np.testing.assert_allclose(floor_camera @ normal + offset, 0.0, atol=1e-9)
    # Off the floor, n.x + d is the height above it; the camera itself is at the offset.
    above_world = floor_world + np.array([0.0, 0.0, 0.75])
    np.testing.assert_allclose((above_world - position) @ rotation @ normal + offset, 0.75, atol=1e-9)
    assert offset == pytest.approx(position[2], abs=1e-12)


def test_floor_agrees_with_ransac_on_the_rendered_floor():
    # The same floor seen two ways: RANSAC on rendered floor points and the camera pose.
    rotation, position = camera_rotation(15.0, 12.0), np.array([1.0, 2.0, 1.3])
    normal, offset = floor_plane_from_camera_pose(rotation, position)
    rng = np.random.default_rng(5)
    world = np.column_stack([rng.uniform(-8, 8, (6000, 2)) + position[:2], np.zeros(6000)])
    camera = (world - position) @ rotation
    in_front = camera[(camera[:, 2] > 0.5) & (camera[:, 2] < 8.0)]
    result = fit_ground_plane(in_front, seed=1)
    assert result.valid
    np.testing.assert_allclose(result.normal, normal, atol=1e-6)
    assert result.offset == pytest.approx(offset, abs=1e-6)


def test_a_nearly_orthonormal_rotation_gives_the_exact_plane_of_that_matrix():
    rotation = camera_rotation(30.0, 10.0) * (1.0 + 4e-4)  # within the 1e-3 tolerance
    position = np.array([0.0, 0.0, 1.1])
    normal, offset = floor_plane_from_camera_pose(rotation, position)
    assert np.linalg.norm(normal) == pytest.approx(1.0, abs=1e-12)
    points_world = np.array([[1.0, 2.0, 0.0], [-3.0, 0.5, 0.0], [2.0, -1.0, 0.0]])
    points_camera = np.linalg.solve(rotation, (points_world - position).T).T  # R x + p = x_w
    np.testing.assert_allclose(points_camera @ normal + offset, 0.0, atol=1e-9)


@pytest.mark.parametrize("height", [0.0, -0.5])
def test_a_camera_not_above_the_floor_is_refused(height):
    with pytest.raises(GroundPlaneError, match="not above the floor"):
        floor_plane_from_camera_pose(camera_rotation(0.0, 10.0), np.array([0.0, 0.0, height]))


@pytest.mark.parametrize("where", ["rotation_nan", "rotation_inf", "position_nan", "position_inf"])
def test_a_non_finite_pose_is_refused(where):
    rotation, position = camera_rotation(0.0, 10.0), np.array([0.0, 0.0, 1.2])
    bad = np.nan if where.endswith("nan") else np.inf
    if where.startswith("rotation"):
        rotation[1, 2] = bad
    else:
        position[0] = bad
    with pytest.raises(GroundPlaneError, match="not finite"):
        floor_plane_from_camera_pose(rotation, position)


@pytest.mark.parametrize("kind", ["scaled", "sheared", "reflection", "zero"])
def test_a_matrix_that_is_not_a_rotation_is_refused(kind):
    rotation = camera_rotation(20.0, 10.0)
    if kind == "scaled":
        rotation = rotation * 1.01
    elif kind == "sheared":
        rotation = rotation @ np.array([[1.0, 0.05, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
    elif kind == "reflection":
        rotation = rotation @ np.diag([1.0, 1.0, -1.0])  # orthonormal, det -1
    else:
        rotation = np.zeros((3, 3))
    with pytest.raises(GroundPlaneError, match="not a rotation"):
        floor_plane_from_camera_pose(rotation, np.array([0.0, 0.0, 1.2]))


def test_wrong_shapes_are_refused():
    with pytest.raises(GroundPlaneError, match="must be"):
        floor_plane_from_camera_pose(np.eye(4), np.array([0.0, 0.0, 1.0]))
    with pytest.raises(GroundPlaneError, match="must be"):
        floor_plane_from_camera_pose(camera_rotation(0.0, 0.0), np.array([0.0, 1.0]))
