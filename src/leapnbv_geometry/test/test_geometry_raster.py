"""Tests of leapnbv_geometry.raster against ray casting and analytic geometry."""

from __future__ import annotations

import time

import numpy as np
import pytest
import trimesh

from leapnbv_geometry.raster import RasterError, rasterize_mesh, warm_up
from leapnbv_geometry.target_geometry import backproject

WIDTH, HEIGHT = 640, 480
K_REAL = np.array([[525.0, 0.0, 319.5], [0.0, 525.0, 239.5], [0.0, 0.0, 1.0]])


def primitive_person(z: float = 3.0) -> trimesh.Trimesh:
    """A closed stand-in figure: a box torso, capsule limbs and an icosphere head (not fused)."""
    parts = []
    torso = trimesh.creation.box(extents=(0.40, 0.60, 0.25))
    torso.apply_translation((0.0, -0.15, 0.0))
    parts.append(torso)
    head = trimesh.creation.icosphere(subdivisions=3, radius=0.12)
    head.apply_translation((0.0, -0.60, 0.0))
    parts.append(head)
    for side in (-1.0, 1.0):
        arm = trimesh.creation.capsule(height=0.55, radius=0.05, count=(24, 24))
        # Capsule axis is +z: tilt it into the image plane, hanging away from the torso.
        arm.apply_transform(trimesh.transformations.rotation_matrix(np.radians(90 - 15 * side), (1, 0, 0)))
        arm.apply_transform(trimesh.transformations.rotation_matrix(np.radians(15 * side), (0, 0, 1)))
        arm.apply_translation((side * 0.33, -0.10, 0.02))
        parts.append(arm)
        leg = trimesh.creation.capsule(height=0.75, radius=0.07, count=(24, 24))
        leg.apply_transform(trimesh.transformations.rotation_matrix(np.radians(90), (1, 0, 0)))
        leg.apply_translation((side * 0.11, 0.55, 0.0))
        parts.append(leg)
    person = trimesh.util.concatenate(parts)
    # A slight turn so that no face is exactly fronto-parallel or axis-aligned in the image.
    person.apply_transform(trimesh.transformations.rotation_matrix(np.radians(20), (0, 1, 0)))
    person.apply_transform(trimesh.transformations.rotation_matrix(np.radians(5), (1, 0, 0)))
    person.apply_translation((0.1, 0.05, z))
    return person


def raycast_depth(
    vertices: np.ndarray, faces: np.ndarray, K: np.ndarray, rows: np.ndarray, cols: np.ndarray
) -> np.ndarray:
    """Reference depth by trimesh ray casting, one ray per pixel centre (u, v) = (col, row).

    Returns:
        (N,) depth (camera z) of the nearest hit per pixel, NaN where the ray misses.
    """
    mesh = trimesh.Trimesh(vertices=vertices, faces=faces, process=False)
    intersector = trimesh.ray.ray_triangle.RayMeshIntersector(mesh)
    directions = np.stack(
        [(cols - K[0, 2]) / K[0, 0], (rows - K[1, 2]) / K[1, 1], np.ones(rows.shape[0])], axis=1
    )
    origins = np.zeros_like(directions)
    locations, index_ray, _ = intersector.intersects_location(origins, directions, multiple_hits=False)
    depth = np.full(rows.shape[0], np.nan)
    depth[index_ray] = locations[:, 2]
    return depth


def compare_with_raycast(
    vertices: np.ndarray, faces: np.ndarray, K: np.ndarray, width: int, height: int, step: int = 1
):
    """Rasterize (V, F) and ray-cast the pixel centres of its image bounding box (every
    ``step``-th row and column, one pixel of margin).

    Returns:
        (silhouette IoU, max |depth difference| where both hit, number of rays, whether the
        raster hit anything outside the ray-cast box).
    """
    result = rasterize_mesh(vertices, faces, K, width, height)
    hit_rows, hit_cols = np.nonzero(result.silhouette)
    row0, row1 = max(hit_rows.min() - 1, 0), min(hit_rows.max() + 2, height)
    col0, col1 = max(hit_cols.min() - 1, 0), min(hit_cols.max() + 2, width)
    grid_rows, grid_cols = np.mgrid[row0:row1:step, col0:col1:step]
    rows, cols = grid_rows.ravel(), grid_cols.ravel()
    reference = raycast_depth(vertices, faces, K, rows.astype(float), cols.astype(float))
    raster_hit = result.silhouette[rows, cols]
    reference_hit = np.isfinite(reference)
    iou = np.count_nonzero(raster_hit & reference_hit) / np.count_nonzero(raster_hit | reference_hit)
    both = raster_hit & reference_hit
    max_error = float(np.max(np.abs(result.depth[rows, cols][both] - reference[both])))
    return iou, max_error, rows.shape[0]


def test_rasterizer_matches_raycast_reference_on_primitive_person():
    person = primitive_person()
    iou, max_error, n_rays = compare_with_raycast(person.vertices, person.faces, K_REAL, WIDTH, HEIGHT)
    assert n_rays >= 20000
    assert iou >= 0.99
    assert max_error <= 1e-3


def test_rasterizer_matches_raycast_for_a_mesh_crossing_the_image_border():
    person = primitive_person(z=2.0)
    person.apply_translation((0.9, -0.3, 0.0))  # cut by the right and top image borders
    iou, max_error, n_rays = compare_with_raycast(
        person.vertices, person.faces, K_REAL, WIDTH, HEIGHT, step=2
    )
    assert n_rays >= 5000
    assert iou >= 0.99
    assert max_error <= 1e-3


def floor_quad(height_below_camera: float, near_z: float, far_z: float, half_width: float):
    """Two triangles of the plane y = h (below the camera), spanning z in [near_z, far_z]."""
    vertices = np.array([
        [-half_width, height_below_camera, near_z],
        [half_width, height_below_camera, near_z],
        [half_width, height_below_camera, far_z],
        [-half_width, height_below_camera, far_z],
    ])
    faces = np.array([[0, 1, 2], [0, 2, 3]])
    return vertices, faces


def test_floor_extending_behind_camera_renders_analytic_depth_everywhere():
    h, far_z, half_width = 1.2, 20.0, 30.0
    vertices, faces = floor_quad(h, -10.0, far_z, half_width)
    result = rasterize_mesh(vertices, faces, K_REAL, WIDTH, HEIGHT)
    rows, cols = np.mgrid[0:HEIGHT, 0:WIDTH].astype(float)
    y_norm = (rows - K_REAL[1, 2]) / K_REAL[1, 1]
    x_norm = (cols - K_REAL[0, 2]) / K_REAL[0, 0]
    with np.errstate(divide="ignore"):
        analytic = np.where(y_norm > 0, h / y_norm, np.inf)
    # Pixels whose ray meets the quad with a margin from its far and side edges.
    inside = (analytic < far_z * 0.98) & (np.abs(x_norm * analytic) < half_width * 0.98)
    outside = ~((analytic < far_z * 1.02) & (np.abs(x_norm * analytic) < half_width * 1.02))
    assert np.count_nonzero(inside) > 0.4 * WIDTH * HEIGHT
    assert np.all(result.silhouette[inside])
    assert not np.any(result.silhouette[outside])
    relative = np.abs(result.depth[inside] - analytic[inside]) / analytic[inside]
    assert relative.max() < 1e-5


def test_triangle_straddling_near_plane_is_clipped_not_dropped():
    # One vertex behind the camera, two in front: a wedge of the floor near the camera.
    vertices = np.array([[0.0, 0.5, -1.0], [-2.0, 0.5, 3.0], [2.0, 0.5, 3.0]])
    result = rasterize_mesh(vertices, np.array([[0, 1, 2]]), K_REAL, WIDTH, HEIGHT, near=0.05)
    assert np.count_nonzero(result.silhouette) > 10000
    rows, cols = np.nonzero(result.silhouette)
    analytic = 0.5 / ((rows - K_REAL[1, 2]) / K_REAL[1, 1])
    np.testing.assert_allclose(result.depth[rows, cols], analytic, rtol=1e-5)
    # Entirely behind the near plane: nothing.
    behind = vertices.copy()
    behind[:, 2] = np.array([-1.0, -3.0, 0.04])
    assert not np.any(rasterize_mesh(behind, np.array([[0, 1, 2]]), K_REAL, WIDTH, HEIGHT, near=0.05).silhouette)


def test_back_faces_are_rendered_like_front_faces():
    vertices = np.array([[-0.5, -0.4, 2.0], [0.6, -0.3, 2.5], [0.0, 0.5, 3.0]])
    front = rasterize_mesh(vertices, np.array([[0, 1, 2]]), K_REAL, WIDTH, HEIGHT)
    back = rasterize_mesh(vertices, np.array([[0, 2, 1]]), K_REAL, WIDTH, HEIGHT)
    assert np.count_nonzero(front.silhouette) > 1000
    np.testing.assert_array_equal(front.silhouette, back.silhouette)
    np.testing.assert_array_equal(front.depth, back.depth)


def test_degenerate_triangles_are_skipped():
    person = primitive_person()
    clean = rasterize_mesh(person.vertices, person.faces, K_REAL, WIDTH, HEIGHT)
    n = person.vertices.shape[0]
    extra_vertices = np.array([[0.0, 0.0, 2.0], [0.1, 0.1, 2.0], [0.2, 0.2, 2.0], [np.nan, 0.0, 2.0]])
    vertices = np.vstack([person.vertices, extra_vertices])
    degenerate = np.array([
        [n, n, n + 1],          # repeated index
        [n, n + 1, n + 2],      # collinear
        [n, n + 1, n + 3],      # non-finite vertex
    ])
    faces = np.vstack([person.faces, degenerate])
    dirty = rasterize_mesh(vertices, faces, K_REAL, WIDTH, HEIGHT)
    np.testing.assert_array_equal(clean.face_index, dirty.face_index)
    np.testing.assert_array_equal(clean.depth, dirty.depth)


def test_shared_edge_through_pixel_centres_is_drawn_exactly_once():
    # A square at z = 1 with corners on pixel centres; its diagonal and sides pass exactly
    # through pixel centres, where the fill rule decides.
    K = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
    vertices = np.array([[2.0, 2.0, 1.0], [12.0, 2.0, 1.0], [12.0, 12.0, 1.0], [2.0, 12.0, 1.0]])
    first = rasterize_mesh(vertices, np.array([[0, 1, 2]]), K, 16, 16).silhouette
    second = rasterize_mesh(vertices, np.array([[0, 2, 3]]), K, 16, 16).silhouette
    both = rasterize_mesh(vertices, np.array([[0, 1, 2], [0, 2, 3]]), K, 16, 16).silhouette
    assert not np.any(first & second)  # no double draw on the diagonal
    np.testing.assert_array_equal(first | second, both)
    # No hole: every pixel centre strictly inside the square is covered, and a neighbouring
    # square sharing its right edge tiles the plane with it (top-left rule: 10 x 10 each).
    assert np.all(both[3:12, 3:12])
    right = vertices + np.array([10.0, 0.0, 0.0])
    neighbour = rasterize_mesh(right, np.array([[0, 1, 2], [0, 2, 3]]), K, 32, 16).silhouette
    wide = rasterize_mesh(vertices, np.array([[0, 1, 2], [0, 2, 3]]), K, 32, 16).silhouette
    assert not np.any(neighbour & wide)
    assert np.count_nonzero(wide) == 100 and np.count_nonzero(neighbour) == 100


def test_rendered_plane_backprojects_onto_the_plane():
    normal = np.array([0.2, -0.9, -0.3])
    normal /= np.linalg.norm(normal)
    offset = 2.0  # n.x + d = 0
    # Four far-apart points on the plane around the point where the optical axis meets it.
    u_axis = np.cross(normal, [0.0, 0.0, 1.0])
    u_axis /= np.linalg.norm(u_axis)
    v_axis = np.cross(normal, u_axis)
    centre = np.array([0.0, 0.0, -offset / normal[2]])
    corners = np.array([centre + a * u_axis + b * v_axis for a, b in [(-5, -5), (5, -5), (5, 5), (-5, 5)]])
    result = rasterize_mesh(corners, np.array([[0, 1, 2], [0, 2, 3]]), K_REAL, WIDTH, HEIGHT)
    points = backproject(result.depth, K_REAL)
    assert points.shape[0] > 10000
    residual = np.abs(points.astype(np.float64) @ normal + offset)
    assert residual.max() < 1e-3


def test_object_id_image_maps_faces_to_objects():
    person = primitive_person()
    ids = np.arange(person.faces.shape[0], dtype=np.int32) % 7
    result = rasterize_mesh(person.vertices, person.faces, K_REAL, WIDTH, HEIGHT, face_object_id=ids)
    expected = np.where(result.face_index >= 0, ids[np.maximum(result.face_index, 0)], -1)
    np.testing.assert_array_equal(result.object_id, expected)


def test_rejects_malformed_inputs():
    vertices = np.zeros((3, 3))
    with pytest.raises(RasterError, match="face indices"):
        rasterize_mesh(vertices, np.array([[0, 1, 3]]), K_REAL, WIDTH, HEIGHT)
    with pytest.raises(RasterError, match="vertices"):
        rasterize_mesh(np.zeros((3, 2)), np.array([[0, 1, 2]]), K_REAL, WIDTH, HEIGHT)
    with pytest.raises(RasterError, match="K"):
        rasterize_mesh(vertices, np.array([[0, 1, 2]]), np.eye(2), WIDTH, HEIGHT)


def test_warm_up_reports_compile_time():
    start = time.perf_counter()
    seconds = warm_up()
    assert 0.0 <= seconds <= time.perf_counter() - start + 1e-6


@pytest.mark.slow
def test_rasterizer_matches_raycast_reference_on_posed_stand_in_body():
    """The issue's check: a posed stand-in body at 640x480 against independent ray casting."""
    from leapnbv_perception.smplx_layer import SMPLXModel, SMPLXParams
    from leapnbv_stand_ins.stand_in_body_model import build_stand_in_body_model

    model = SMPLXModel(build_stand_in_body_model("small"))
    body = np.zeros(63)
    body[15 * 3 + 2] = -1.1  # left shoulder down  (joint 16 -> body index 15)
    body[16 * 3 + 2] = 1.1   # right shoulder down
    body[17 * 3 + 1] = -1.2  # left elbow bent
    body[3 * 3] = 0.6        # left knee bent (joint 4 -> body index 3)
    params = SMPLXParams.from_axis_angle(np.array([np.pi, 0.3, 0.0]), body, np.zeros(45), np.zeros(45),
                                         np.zeros(3))
    # Upside-down root (y up -> optical y down), turned a little, 3 m ahead of the camera.
    vertices = model.forward(params).vertices.astype(np.float64) + np.array([0.1, 0.1, 3.0])
    iou, max_error, n_rays = compare_with_raycast(vertices, model.faces, K_REAL, WIDTH, HEIGHT)
    assert n_rays >= 20000
    assert iou >= 0.99, iou
    assert max_error <= 1e-3, max_error
