"""Evaluation metrics: body coverage, reconstructed area, PA-MPVPE and latency percentiles."""

from __future__ import annotations

from typing import Dict, Sequence

import numpy as np


def project_points(points_cam: np.ndarray, K: np.ndarray) -> np.ndarray:
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
    vertices_cam: np.ndarray,
    scene_depth_m: np.ndarray,
    K: np.ndarray,
    tolerance: float = 0.02,
) -> np.ndarray:
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


def body_coverage(
    gt_vertices_cam: np.ndarray,
    scene_depth_m: np.ndarray,
    K: np.ndarray,
    tolerance: float = 0.02,
) -> float:
    """Share of ground-truth body vertices visible in the view (ALGORITHMS.md 8).

    Use the rendered scene depth WITHOUT noise; see :func:`visible_vertex_mask`.

    Args:
        gt_vertices_cam: (V,3) ground-truth body vertices in the camera optical frame, metres.
        scene_depth_m: (H,W) noise-free scene depth, metres, 0 = no return.
        K: (3,3) intrinsics.
        tolerance: Metres a vertex may lie behind the scene surface (default 2 cm).

    Returns:
        Fraction in [0, 1] (0 for an empty vertex set).
    """
    visible = visible_vertex_mask(gt_vertices_cam, scene_depth_m, K, tolerance)
    if visible.size == 0:
        return 0.0
    return float(np.count_nonzero(visible)) / float(visible.size)


def reconstructed_area(mask: np.ndarray, depth: np.ndarray) -> int:
    """Pixels of the person mask with valid depth (ALGORITHMS.md 8).

    Args:
        mask: (H,W) bool person mask.
        depth: (H,W) depth, metres (float) or millimetres (uint16); valid = finite and > 0.

    Returns:
        The pixel count.

    Raises:
        ValueError: The shapes differ.
    """
    mask = np.asarray(mask, dtype=bool)
    depth = np.asarray(depth)
    if mask.shape != depth.shape:
        raise ValueError(f"mask {mask.shape} and depth {depth.shape} differ in shape")
    if np.issubdtype(depth.dtype, np.floating):
        valid = np.isfinite(depth) & (depth > 0)
    else:
        valid = depth > 0
    return int(np.count_nonzero(mask & valid))


def procrustes_align(pred: np.ndarray, gt: np.ndarray) -> np.ndarray:
    """Similarity-align pred to gt: argmin over s, R, t of sum |s R pred_i + t - gt_i|^2.

    Umeyama's closed form: with centred X = pred - mean, Y = gt - mean and
    ``U S V^T = svd(X^T Y)``, ``R = V D U^T`` where ``D = diag(1, 1, sign(det(V U^T)))``
    keeps R a proper rotation (no reflection), ``s = trace(S D) / |X|^2`` and
    ``t = mean_gt - s R mean_pred``.

    Args:
        pred: (V,3) predicted vertices.
        gt: (V,3) ground-truth vertices (same order).

    Returns:
        (V,3) aligned prediction.

    Raises:
        ValueError: Shapes differ or are not (V,3), or pred is degenerate (all one point).
    """
    X = np.asarray(pred, dtype=np.float64)
    Y = np.asarray(gt, dtype=np.float64)
    if X.shape != Y.shape or X.ndim != 2 or X.shape[1] != 3:
        raise ValueError(f"pred {X.shape} and gt {Y.shape} must both be (V,3)")
    mean_x = X.mean(axis=0)
    mean_y = Y.mean(axis=0)
    Xc = X - mean_x
    Yc = Y - mean_y
    variance_x = float(np.sum(Xc * Xc))
    if variance_x <= 0.0:
        raise ValueError("pred is degenerate (all vertices coincide)")
    U, S, Vt = np.linalg.svd(Xc.T @ Yc)
    D = np.eye(3)
    D[2, 2] = np.sign(np.linalg.det(Vt.T @ U.T)) or 1.0
    R = Vt.T @ D @ U.T
    scale = float(np.sum(S * np.diag(D))) / variance_x
    t = mean_y - scale * (R @ mean_x)
    return scale * (X @ R.T) + t


def pa_mpvpe_mm(pred: np.ndarray, gt: np.ndarray) -> float:
    """PA-MPVPE: mean per-vertex distance after Procrustes alignment (scale, rotation, translation).

    Args:
        pred: (V,3) predicted vertices, metres.
        gt: (V,3) ground-truth vertices, metres, same vertex order.

    Returns:
        Millimetres.
    """
    aligned = procrustes_align(pred, gt)
    return float(np.mean(np.linalg.norm(aligned - np.asarray(gt, dtype=np.float64), axis=1)) * 1000.0)


def latency_summary(samples_ms: Sequence[float]) -> Dict[str, float]:
    """Percentiles of latency samples (linear interpolation, numpy's default).

    Args:
        samples_ms: Latencies in milliseconds.

    Returns:
        ``{"n", "mean", "p50", "p95", "p99", "max"}``; all NaN except n = 0 when empty.
    """
    samples = np.asarray(list(samples_ms), dtype=np.float64)
    if samples.size == 0:
        nan = float("nan")
        return {"n": 0, "mean": nan, "p50": nan, "p95": nan, "p99": nan, "max": nan}
    p50, p95, p99 = np.percentile(samples, [50, 95, 99])
    return {
        "n": int(samples.size),
        "mean": float(samples.mean()),
        "p50": float(p50),
        "p95": float(p95),
        "p99": float(p99),
        "max": float(samples.max()),
    }


# Largest side (pixels) of the body-only render that decides self-visibility; beyond it the
# focal length is scaled down (coarser, but the whole body still fits).
MAX_SELF_VISIBILITY_IMAGE_PX = 4096


def self_visible_vertex_mask(
    vertices_cam: np.ndarray,
    faces: np.ndarray,
    K: np.ndarray,
    tolerance: float = 0.02,
    max_image_px: int = MAX_SELF_VISIBILITY_IMAGE_PX,
) -> np.ndarray:
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
    from leapnbv_geometry.raster import rasterize_mesh

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


def surface_coverage(
    gt_vertices_cam: np.ndarray,
    body_faces: np.ndarray,
    scene_depth_m: np.ndarray,
    K: np.ndarray,
    tolerance: float = 0.02,
) -> float:
    """Share of the body surface this viewpoint could show that it does show (in [0, 1]).

    :func:`body_coverage` divides by all vertices; its ceiling is about 50-55 % because the
    back of a body is always hidden by its front. Here the denominator is the set of vertices
    the body shows by itself from the camera's position (in front, not self-occluded, image
    bounds ignored: :func:`self_visible_vertex_mask`), and the numerator those of them that
    the real view sees (inside the image, in front, not behind the scene depth by more than
    ``tolerance``: :func:`visible_vertex_mask`). An unoccluded, fully framed body scores ~1;
    occluders and the image border lower it.

    Args:
        gt_vertices_cam: (V,3) ground-truth body vertices in the camera optical frame, metres.
        body_faces: (F,3) the body model's triangles.
        scene_depth_m: (H,W) noise-free depth of the whole scene from this camera, metres.
        K: (3,3) intrinsics.
        tolerance: Metres a vertex may lie behind a surface and still count (default 2 cm).

    Returns:
        Fraction in [0, 1]; 0 when the body shows no vertex from here (e.g. behind the camera).
    """
    self_visible = self_visible_vertex_mask(gt_vertices_cam, body_faces, K, tolerance)
    count = int(np.count_nonzero(self_visible))
    if count == 0:
        return 0.0
    seen = visible_vertex_mask(gt_vertices_cam, scene_depth_m, K, tolerance) & self_visible
    return float(np.count_nonzero(seen)) / float(count)
