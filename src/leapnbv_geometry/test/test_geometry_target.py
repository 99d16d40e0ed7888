"""Tests of leapnbv_geometry.target_geometry on scenes rendered with the rasterizer."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from leapnbv_geometry.raster import rasterize_mesh
from leapnbv_geometry.target_geometry import (
    TargetGeometryError,
    backproject,
    compute_target_geometry,
    pixels_to_points,
    place_mesh_metric,
)

WIDTH, HEIGHT = 640, 480
K_REAL = np.array([[525.0, 0.0, 319.5], [0.0, 525.0, 239.5], [0.0, 0.0, 1.0]])
PERSON, WALL, OCCLUDER, FLOOR = 0, 1, 2, 3


def box_mesh(centre, extents) -> trimesh.Trimesh:
    """Axis-aligned closed box."""
    box = trimesh.creation.box(extents=extents)
    box.apply_translation(centre)
    return box


def person_mesh(z: float, arm_width: float) -> trimesh.Trimesh:
    """Torso, head, two legs and a right arm hanging ``0.26 - arm_width/2 - 0.2`` m from it."""
    parts = [
        box_mesh((0.0, -0.2, z), (0.40, 0.60, 0.24)),      # torso x in [-0.2, 0.2]
        box_mesh((0.0, -0.62, z), (0.18, 0.22, 0.18)),     # head
        box_mesh((-0.1, 0.5, z), (0.14, 0.78, 0.14)),      # legs
        box_mesh((0.1, 0.5, z), (0.14, 0.78, 0.14)),
        box_mesh((-0.27, -0.15, z), (0.10, 0.60, 0.10)),   # left arm against the torso
        box_mesh((0.31 - (arm_width - 0.08) / 2, -0.15, z), (arm_width, 0.60, 0.10)),  # right arm
    ]
    return trimesh.util.concatenate(parts)


def render_scene(z_person: float = 3.0):
    """The true person (right arm 0.07 m from the torso), a wall 1.5 m behind, an occluder
    box 0.7 m in front of the torso and a floor 1 m below the camera.

    Returns:
        (depth (H, W) float32, object id image (H, W), true person mesh).
    """
    person = person_mesh(z_person, arm_width=0.08)  # right arm x in [0.27, 0.35]: gap 0.07
    wall = box_mesh((0.0, 0.0, z_person + 1.5), (8.0, 4.0, 0.05))
    occluder = box_mesh((-0.12, -0.05, z_person - 0.7), (0.25, 0.35, 0.05))
    floor_vertices = np.array([[-20, 1.0, -5.0], [20, 1.0, -5.0], [20, 1.0, 30.0], [-20, 1.0, 30.0]])
    floor = trimesh.Trimesh(floor_vertices, [[0, 1, 2], [0, 2, 3]], process=False)
    meshes = [person, wall, occluder, floor]
    ids = np.concatenate([np.full(len(m.faces), i, dtype=np.int32) for i, m in enumerate(meshes)])
    scene = trimesh.util.concatenate(meshes)
    result = rasterize_mesh(scene.vertices, scene.faces, K_REAL, WIDTH, HEIGHT, face_object_id=ids)
    return result.depth, result.object_id, person


def silhouette_box(silhouette: np.ndarray):
    rows, cols = np.nonzero(silhouette)
    return (cols.min(), rows.min(), cols.max(), rows.max())


def test_occluder_and_background_through_gap_are_excluded():
    depth, object_id, true_person = render_scene()
    true_alone = rasterize_mesh(true_person.vertices, true_person.faces, K_REAL, WIDTH, HEIGHT)
    # The estimated mesh: right arm too wide (covers the gap), and 10 % too large and too far
    # (scaling about the camera keeps its image but shifts its depth by about -0.3 m).
    estimate = person_mesh(3.0, arm_width=0.16)
    estimate_vertices = estimate.vertices * 1.1
    box = silhouette_box(true_alone.silhouette)

    result = compute_target_geometry(estimate_vertices, estimate.faces, depth, K_REAL, box)

    assert result.valid
    # Preconditions: the scene really has wall pixels in the estimated silhouette (the gap)
    # and occluder pixels in front of the person.
    gap_pixels = result.silhouette & (object_id == WALL)
    occluded_pixels = true_alone.silhouette & (object_id == OCCLUDER)
    assert np.count_nonzero(gap_pixels) > 500
    assert np.count_nonzero(occluded_pixels) > 2000
    # The mask is exactly the visible pixels of the true person.
    visible_person = object_id == PERSON
    np.testing.assert_array_equal(result.mask, visible_person)
    np.testing.assert_array_equal(result.mask, true_alone.silhouette & ~occluded_pixels)
    assert result.mask_pixel_count == np.count_nonzero(visible_person)
    assert result.visible_fraction == pytest.approx(
        np.count_nonzero(visible_person) / np.count_nonzero(result.silhouette)
    )
    # Depth alignment recovers the 10 % scale error: offset = -0.1 * depth of the person.
    median_person_depth = np.median(depth[visible_person])
    assert result.depth_offset == pytest.approx(-0.1 * median_person_depth, abs=0.02)
    # Target points are the back-projected person pixels.
    expected_points = backproject(depth, K_REAL, mask=visible_person)
    np.testing.assert_allclose(result.target_points, expected_points)
    np.testing.assert_allclose(result.centroid, np.median(expected_points, axis=0))
    assert result.target_points.shape == (result.mask_pixel_count, 3)
    assert np.all(result.bbox_min <= result.centroid) and np.all(result.centroid <= result.bbox_max)
    # The aligned mesh now sits on the observed depth.
    aligned = rasterize_mesh(result.metric_vertices, estimate.faces, K_REAL, WIDTH, HEIGHT)
    assert np.median(np.abs(aligned.depth[visible_person] - depth[visible_person])) < 0.02


def test_target_stride_keeps_the_grid_pixels_and_every_pixels_summary():
    depth, object_id, true_person = render_scene()
    true_alone = rasterize_mesh(true_person.vertices, true_person.faces, K_REAL, WIDTH, HEIGHT)
    box = silhouette_box(true_alone.silhouette)
    full = compute_target_geometry(true_person.vertices, true_person.faces, depth, K_REAL, box)
    strided = compute_target_geometry(true_person.vertices, true_person.faces, depth, K_REAL, box, target_stride=2)
    # The points of the person pixels on the even rows and columns, in the same order.
    grid = np.zeros_like(full.mask)
    grid[::2, ::2] = True
    np.testing.assert_allclose(strided.target_points, backproject(depth, K_REAL, mask=full.mask & grid))
    assert 0.2 < strided.target_points.shape[0] / full.target_points.shape[0] < 0.3
    # Mask, counts and the summaries are of every person pixel, as without the stride.
    np.testing.assert_array_equal(strided.mask, full.mask)
    assert strided.mask_pixel_count == full.mask_pixel_count and strided.visible_fraction == full.visible_fraction
    np.testing.assert_array_equal(strided.centroid, full.centroid)
    np.testing.assert_array_equal(strided.bbox_min, full.bbox_min)
    with pytest.raises(TargetGeometryError, match="target_stride must be >= 1"):
        compute_target_geometry(true_person.vertices, true_person.faces, depth, K_REAL, box, target_stride=0)


def test_background_points_hold_occluder_and_wall_minus_ground():
    depth, object_id, true_person = render_scene()
    true_alone = rasterize_mesh(true_person.vertices, true_person.faces, K_REAL, WIDTH, HEIGHT)
    box = silhouette_box(true_alone.silhouette)
    floor_plane = (np.array([0.0, -1.0, 0.0]), 1.0)  # -y + 1 = 0: the floor y = 1
    without_plane = compute_target_geometry(
        true_person.vertices, true_person.faces, depth, K_REAL, box, background_stride=4
    )
    with_plane = compute_target_geometry(
        true_person.vertices, true_person.faces, depth, K_REAL, box, background_stride=4,
        ground_plane=floor_plane, ground_inlier_threshold=0.03,
    )
    stride_grid = np.zeros_like(without_plane.mask)
    stride_grid[::4, ::4] = True
    expected_count = np.count_nonzero(stride_grid & (depth > 0) & ~without_plane.mask)
    assert without_plane.background_points.shape == (expected_count, 3)
    floor_count = np.count_nonzero(stride_grid & (object_id == FLOOR))
    all_heights = without_plane.background_points @ floor_plane[0] + floor_plane[1]
    off_floor = np.abs(all_heights) > 0.03
    # Every floor pixel (and the strip of wall just above it) is removed, nothing else.
    assert np.count_nonzero(~off_floor) >= floor_count
    np.testing.assert_array_equal(with_plane.background_points, without_plane.background_points[off_floor])
    # The occluder is background (it matters for occlusion scoring).
    occluder_z = 3.0 - 0.7 - 0.025
    assert np.any(np.abs(with_plane.background_points[:, 2] - occluder_z) < 0.01)
    # A ground-truth metric mesh needs (almost) no alignment.
    assert abs(without_plane.depth_offset) < 0.01


def test_box_limits_the_mask():
    depth, object_id, true_person = render_scene()
    full = rasterize_mesh(true_person.vertices, true_person.faces, K_REAL, WIDTH, HEIGHT).silhouette
    x0, y0, x1, y1 = silhouette_box(full)
    upper_half = (x0, y0, x1, (y0 + y1) / 2)
    result = compute_target_geometry(
        true_person.vertices, true_person.faces, depth, K_REAL, upper_half, box_dilation_px=0
    )
    rows, _ = np.nonzero(result.mask)
    assert rows.max() <= (y0 + y1) / 2
    assert result.mask_pixel_count == np.count_nonzero((object_id == PERSON)[: int((y0 + y1) / 2) + 1])


def test_empty_and_invalid_inputs_give_invalid_result():
    depth, _, true_person = render_scene()
    box = (200, 50, 440, 450)
    no_depth = compute_target_geometry(
        true_person.vertices, true_person.faces, np.zeros_like(depth), K_REAL, box
    )
    assert not no_depth.valid and "depth" in no_depth.invalid_reason
    assert no_depth.visible_fraction == 0.0 and no_depth.mask_pixel_count == 0
    assert no_depth.target_points.shape == (0, 3)
    assert np.all(np.isfinite(no_depth.centroid))
    nan_depth = np.full_like(depth, np.nan)
    assert not compute_target_geometry(true_person.vertices, true_person.faces, nan_depth, K_REAL, box).valid
    behind = true_person.vertices * np.array([1.0, 1.0, -1.0])
    result = compute_target_geometry(behind, true_person.faces, depth, K_REAL, box)
    assert not result.valid and "silhouette" in result.invalid_reason
    outside = compute_target_geometry(true_person.vertices, true_person.faces, depth, K_REAL, (900, 900, 990, 990))
    assert not outside.valid and "box" in outside.invalid_reason
    with pytest.raises(TargetGeometryError, match="depth"):
        compute_target_geometry(true_person.vertices, true_person.faces, depth[0], K_REAL, box)
    with pytest.raises(TargetGeometryError, match="depth_to_metres"):
        compute_target_geometry(true_person.vertices, true_person.faces, (depth * 1000).astype(np.uint16), K_REAL, box)


def test_place_mesh_metric_identity_when_cameras_match():
    rng = np.random.default_rng(1)
    vertices = rng.normal(size=(100, 3)) + np.array([0.1, 0.2, 5.0])
    params = (K_REAL[0, 0], K_REAL[1, 1], K_REAL[0, 2], K_REAL[1, 2])
    placed = place_mesh_metric(vertices, params, K_REAL, np.array([0.1, 0.2, 5.0]))
    np.testing.assert_array_equal(placed, vertices)


def test_place_mesh_metric_hand_computed_case():
    # Virtual camera f = 1000, c = (300, 200); real f = 500, c = (320, 240); t = (0.1, -0.2, 10).
    # t'_z = 10 * 500 / 1000 = 5; t'_x = 0.1 + (300 - 320) * 10 / 1000 = -0.1;
    # t'_y = -0.2 + (200 - 240) * 10 / 1000 = -0.6.
    t = np.array([0.1, -0.2, 10.0])
    body = np.array([[0.0, 0.0, 0.0], [0.3, -0.8, 0.1]])
    real_K = np.array([[500.0, 0.0, 320.0], [0.0, 500.0, 240.0], [0.0, 0.0, 1.0]])
    placed = place_mesh_metric(body + t, (1000.0, 1000.0, 300.0, 200.0), real_K, t)
    np.testing.assert_allclose(placed, body + np.array([-0.1, -0.6, 5.0]), atol=1e-12)
    # The mesh centre projects to the same pixel under both cameras: (310, 180).
    centre = placed[0]
    assert 500.0 * centre[0] / centre[2] + 320.0 == pytest.approx(1000.0 * t[0] / t[2] + 300.0)
    assert 500.0 * centre[1] / centre[2] + 240.0 == pytest.approx(1000.0 * t[1] / t[2] + 200.0)
    with pytest.raises(TargetGeometryError, match="cam_translation"):
        place_mesh_metric(body, (1.0, 1.0, 0.0, 0.0), real_K, np.zeros(2))


def test_place_mesh_metric_refuses_images_of_different_sizes():
    # A metric (ground-truth) mesh whose virtual K is the colour camera's, and a depth image of half
    # the size with its own K: the formula would move the mesh to half its distance. Refused instead.
    vertices = np.array([[0.0, 0.0, 3.0], [0.2, -0.5, 3.1]])
    colour_k = (615.0, 615.0, 320.0, 240.0)
    depth_k = np.array([[307.5, 0.0, 160.0], [0.0, 307.5, 120.0], [0.0, 0.0, 1.0]])
    with pytest.raises(TargetGeometryError, match=r"\(640, 480\) but the real camera's \(320, 240\)"):
        place_mesh_metric(vertices, colour_k, depth_k, np.array([0.0, 0.0, 3.0]), (640, 480), (320, 240))
    colour_matrix = np.array([[615.0, 0.0, 320.0], [0.0, 615.0, 240.0], [0.0, 0.0, 1.0]])
    same = place_mesh_metric(vertices, colour_k, colour_matrix, np.array([0.0, 0.0, 3.0]), (640, 480), (640, 480))
    np.testing.assert_array_equal(same, vertices)


def test_backproject_inverts_projection_and_skips_invalid():
    K = np.array([[500.0, 2.0, 310.0], [0.0, 480.0, 250.0], [0.0, 0.0, 1.0]])
    rng = np.random.default_rng(0)
    rows = rng.integers(0, 480, 50)
    cols = rng.integers(0, 640, 50)
    z = rng.uniform(0.5, 5.0, 50)
    points = pixels_to_points(rows, cols, z, K).astype(np.float64)
    projected = points @ K.T
    np.testing.assert_allclose(projected[:, 0] / projected[:, 2], cols, atol=1e-3)
    np.testing.assert_allclose(projected[:, 1] / projected[:, 2], rows, atol=1e-3)
    depth = np.zeros((4, 6), dtype=np.float32)
    depth[1, 2] = 2.0
    depth[2, 3] = np.nan
    depth[3, 4] = -1.0
    depth[2, 4] = 3.0
    out = backproject(depth, K)
    np.testing.assert_allclose(out[:, 2], [2.0, 3.0])
    mask = np.zeros((4, 6), dtype=bool)
    mask[2, 4] = True
    np.testing.assert_allclose(backproject(depth, K, mask=mask)[:, 2], [3.0])
    assert backproject(depth, K, stride=2).shape == (1, 3)  # only (2, 4) is on the grid


def test_depth_alignment_stays_on_the_person_when_an_occluder_covers_most_of_it():
    """An occluder hiding ~70 % of the silhouette must not become the target (it is nearer)."""
    z = 3.0
    person = person_mesh(z, arm_width=0.08)
    big_occluder = box_mesh((-0.1, 0.25, z - 0.8), (0.45, 0.9, 0.05))
    wall = box_mesh((0.0, 0.0, z + 1.5), (8.0, 4.0, 0.05))
    meshes = [person, wall, big_occluder]
    ids = np.concatenate([np.full(len(m.faces), i, dtype=np.int32) for i, m in enumerate(meshes)])
    scene = trimesh.util.concatenate(meshes)
    rendered = rasterize_mesh(scene.vertices, scene.faces, K_REAL, WIDTH, HEIGHT, face_object_id=ids)
    alone = rasterize_mesh(person.vertices, person.faces, K_REAL, WIDTH, HEIGHT)
    hidden = np.count_nonzero(alone.silhouette & (rendered.object_id == 2)) / np.count_nonzero(alone.silhouette)
    assert 0.6 < hidden < 0.8, hidden  # precondition: the occluder covers most of the person

    # The estimate is 0.3 m too far: the alignment must bring it back onto the person, not the box.
    estimate = person.vertices * (z + 0.3) / z
    result = compute_target_geometry(estimate, person.faces, rendered.depth, K_REAL,
                                     silhouette_box(alone.silhouette))
    assert result.valid
    assert result.depth_offset == pytest.approx(-0.3, abs=0.03)
    kept_ids = rendered.object_id[result.mask]
    assert np.all(kept_ids == PERSON)
    visible_person = alone.silhouette & (rendered.object_id == PERSON)
    assert result.mask_pixel_count >= 0.95 * np.count_nonzero(visible_person)
