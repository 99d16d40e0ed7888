"""Which body vertices a camera sees: projection, the depth test against a scene, and self-visibility."""

from __future__ import annotations

import numpy as np

from leapnbv_common.array_types import BoolArray, FloatArray, FloatingArray, IntArray
from leapnbv_geometry.raster import rasterize_mesh


def project_points(points_cam: FloatArray, K: FloatArray) -> FloatArray:
    """Pinhole projection u = fx x/z + cx, v = fy y/z + cy (pixel centres at integer u, v).

    Args:
        points_cam: (N,3) points in the camera optical frame (z > 0 expected).
        K: (3,3) intrinsics.

    Returns:
        (N,2) pixel coordinates (u, v); NaN/inf where z <= 0.
    """
    points = np.asarray(points_cam, dtype=np.float64)
    K = np.asarray(K, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        u = K[0, 0] * points[:, 0] / points[:, 2] + K[0, 2]
        v = K[1, 1] * points[:, 1] / points[:, 2] + K[1, 2]
    return np.stack([u, v], axis=1)


def visible_vertex_mask(
    vertices_cam: FloatArray,
    scene_depth_m: FloatingArray,
    K: FloatArray,
    tolerance: float = 0.02,
) -> BoolArray:
    """Which vertices the camera sees: inside the image, in front, not behind the scene depth.

    A vertex projects to pixel (round(v), round(u)); it is visible when that pixel lies in the
    image, z > 0, and z <= scene_depth + tolerance there. A pixel without a return (0) hides
    nothing, so a vertex there counts as visible.

    Args:
        vertices_cam: (V,3) vertices in the camera optical frame, metres.
        scene_depth_m: (H,W) noise-free rendered depth of the whole scene, metres, 0 = none.
        K: (3,3) intrinsics.
        tolerance: How far behind the scene surface a vertex may lie and still count (m).

    Returns:
        (V,) bool.

    Raises:
        ValueError: Bad shapes.
    """
    vertices = np.asarray(vertices_cam, dtype=np.float64)
    depth = np.asarray(scene_depth_m)
    if vertices.ndim != 2 or vertices.shape[1] != 3:
        raise ValueError(f"vertices_cam must be (V,3), got {vertices.shape}")
    if depth.ndim != 2:
        raise ValueError(f"scene_depth_m must be (H,W), got {depth.shape}")
    height, width = depth.shape
    in_front = vertices[:, 2] > 1e-6
    uv = project_points(np.where(in_front[:, None], vertices, 1.0), K)
    columns = np.rint(uv[:, 0])
    rows = np.rint(uv[:, 1])
    inside = in_front & (columns >= 0) & (columns < width) & (rows >= 0) & (rows < height)
    visible = np.zeros(vertices.shape[0], dtype=bool)
    index = np.nonzero(inside)[0]
    surface = depth[rows[index].astype(np.int64), columns[index].astype(np.int64)].astype(np.float64)
    visible[index] = (surface <= 0) | (vertices[index, 2] <= surface + tolerance)
    return visible

# Largest side (pixels) of the body-only render that decides self-visibility; beyond it the
# focal length is scaled down (coarser, but the whole body still fits).
MAX_SELF_VISIBILITY_IMAGE_PX = 4096


def self_visible_vertex_mask(
    vertices_cam: FloatArray,
    faces: IntArray,
    K: FloatArray,
    tolerance: float = 0.02,
    max_image_px: int = MAX_SELF_VISIBILITY_IMAGE_PX,
) -> BoolArray:
    """Which vertices the body shows by itself from this viewpoint, image bounds ignored.

    The body alone is rendered with a virtual camera at the same pose, with the same focal
    length and a principal point shifted by whole pixels so that every vertex in front of
    the camera lands inside a virtual image just large enough for them (the pixel grid stays
    the one of the real camera, so the test below matches :func:`visible_vertex_mask` on the
    real image pixel for pixel). A vertex is self-visible when it is in front (z > 0) and not
    more than ``tolerance`` behind that body-only depth (see :func:`visible_vertex_mask`).
    When the virtual image would exceed ``max_image_px`` on a side, the focal length is scaled
    down to fit (coarser pixels; only for bodies very near the camera).

    Args:
        vertices_cam: (V,3) body vertices in the camera optical frame, metres.
        faces: (F,3) int triangles into vertices_cam.
        K: (3,3) intrinsics of the real camera.
        tolerance: Metres a vertex may lie behind the body surface and still count.
        max_image_px: Largest side of the virtual image.

    Returns:
        (V,) bool.

    Raises:
        ValueError: Bad shapes.
    """
    vertices = np.asarray(vertices_cam, dtype=np.float64)
    if vertices.ndim != 2 or vertices.shape[1] != 3:
        raise ValueError(f"vertices_cam must be (V,3), got {vertices.shape}")
    faces = np.asarray(faces)
    if faces.ndim != 2 or faces.shape[1] != 3:
        raise ValueError(f"faces must be (F,3), got {faces.shape}")
    K = np.asarray(K, dtype=np.float64)
    # Only vertices clearly in front matter: the rasterizer clips at z = 1 cm anyway.
    in_front = vertices[:, 2] > 0.01
    if not np.any(in_front):
        return np.zeros(vertices.shape[0], dtype=bool)
    uv = project_points(vertices[in_front], K)
    u_min, v_min = np.floor(uv.min(axis=0)) - 2.0
    u_max, v_max = np.ceil(uv.max(axis=0)) + 2.0
    scale = min(1.0, float(max_image_px) / max(u_max - u_min + 1.0, v_max - v_min + 1.0))
    virtual_K = K.copy()
    if scale < 1.0:
        # Scale about the principal point, then shift: pixels grow by 1/scale.
        virtual_K[0, 0] *= scale
        virtual_K[1, 1] *= scale
        virtual_K[0, 1] *= scale
        uv = project_points(vertices[in_front], virtual_K)
        u_min, v_min = np.floor(uv.min(axis=0)) - 2.0
        u_max, v_max = np.ceil(uv.max(axis=0)) + 2.0
    virtual_K[0, 2] -= u_min
    virtual_K[1, 2] -= v_min
    width = int(u_max - u_min) + 1
    height = int(v_max - v_min) + 1
    body_depth = rasterize_mesh(vertices, faces, virtual_K, width, height).depth
    return visible_vertex_mask(vertices, body_depth, virtual_K, tolerance)
