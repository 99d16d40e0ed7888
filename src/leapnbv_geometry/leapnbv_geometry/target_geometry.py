"""Target geometry: metric mesh placement, person mask, depth clustering and back-projection."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional, Sequence, Tuple

import numpy as np

from leapnbv_common.array_types import BoolArray, Float32Array, FloatArray, FloatingArray, IntArray

from .raster import RasterResult, rasterize_mesh

__all__ = [
    "TargetGeometryError",
    "TargetGeometryResult",
    "backproject",
    "compute_target_geometry",
    "pixels_to_points",
    "place_mesh_metric",
]


class TargetGeometryError(ValueError):
    """Invalid input to the target-geometry stage (names the argument and shape at fault)."""


@dataclass
class TargetGeometryResult:
    """Output of :func:`compute_target_geometry` (all geometry in the real camera optical frame).

    When no pixel survives (empty silhouette, box outside the image, no valid depth, everything
    occluded) ``valid`` is False, ``invalid_reason`` says why, point arrays are empty (0, 3),
    ``centroid`` / ``bbox_min`` / ``bbox_max`` are zeros (never NaN) and must not be used.

    Attributes:
        valid: True when at least one target point was found.
        invalid_reason: '' when valid, otherwise a short human-readable reason.
        target_points: (N, 3) float32 back-projected person pixels, metres (with ``target_stride`` s > 1
            those of every s-th row and column).
        centroid: (3,) float64 per-axis median of every person pixel's point.
        bbox_min: (3,) float64 per-axis minimum of every person pixel's point.
        bbox_max: (3,) float64 per-axis maximum of every person pixel's point.
        mask: (H, W) bool final person mask: silhouette ∩ dilated box ∩ valid depth ∩ depth
            agreement with the aligned mesh. ``target_points`` are exactly its pixels (stride 1).
        silhouette: (H, W) bool mesh silhouette under the real K (before the box and depth).
        box_mask: (H, W) bool silhouette ∩ dilated box (the paper's M, before depth).
        mask_pixel_count: pixels in ``mask`` (reconstructed area).
        silhouette_pixel_count: pixels in ``silhouette``.
        visible_fraction: mask_pixel_count / silhouette_pixel_count (0 when the silhouette is
            empty).
        depth_offset: metres added to the mesh depth to match the observed depth (median of
            D - D_mesh over the agreeing cluster, see :func:`compute_target_geometry`).
        background_points: (K, 3) float32 valid-depth pixels outside ``mask`` (strided), minus
            ground-plane inliers when a plane was given. Occluders in front of the person are
            background points.
        metric_vertices: (V, 3) float32 mesh after depth alignment (moved along the viewing
            ray through its centre by ``depth_offset`` in z).
        mesh_depth: (H, W) float32 rendered mesh depth before alignment (0 = no hit).
    """

    valid: bool
    invalid_reason: str
    target_points: Float32Array
    centroid: FloatArray
    bbox_min: FloatArray
    bbox_max: FloatArray
    mask: BoolArray
    silhouette: BoolArray
    box_mask: BoolArray
    mask_pixel_count: int
    silhouette_pixel_count: int
    visible_fraction: float
    depth_offset: float
    background_points: Float32Array
    metric_vertices: Float32Array
    mesh_depth: Float32Array


def _intrinsics(K: FloatArray, name: str = "K") -> Tuple[float, float, float, float, float]:
    """(fx, skew, cx, fy, cy) of a (3, 3) camera matrix, validated."""
    K = np.asarray(K, dtype=np.float64)
    if K.shape != (3, 3) or not np.all(np.isfinite(K)) or K[0, 0] == 0.0 or K[1, 1] == 0.0:
        raise TargetGeometryError(f"{name} must be a finite (3, 3) camera matrix with fx, fy != 0")
    return float(K[0, 0]), float(K[0, 1]), float(K[0, 2]), float(K[1, 1]), float(K[1, 2])


def pixels_to_points(rows: IntArray, cols: IntArray, z: FloatingArray, K: FloatArray) -> Float32Array:
    """Back-project pixels with known depth: the one inverse of the projection used here.

    Pixel (row i, column j) is the image point (u, v) = (j, i) (integer coordinates are pixel
    centres, as in ``raster.rasterize_mesh``), so with K = [[fx, s, cx], [0, fy, cy], [0, 0, 1]]
        y = (i - cy) z / fy,    x = (j - cx - s (i - cy) / fy) z / fx.

    Args:
        rows: (N,) pixel rows i.
        cols: (N,) pixel columns j.
        z: (N,) depth (camera-frame z) in metres.
        K: (3, 3) camera matrix.

    Returns:
        (N, 3) float32 points in the camera optical frame.
    """
    fx, skew, cx, fy, cy = _intrinsics(K)
    z = np.asarray(z, dtype=np.float32)
    y_norm = (np.asarray(rows, dtype=np.float32) - np.float32(cy)) * np.float32(1.0 / fy)
    x_norm = np.asarray(cols, dtype=np.float32) - np.float32(cx)
    if skew != 0.0:
        x_norm = x_norm - np.float32(skew) * y_norm
    x_norm *= np.float32(1.0 / fx)
    points = np.empty((z.shape[0], 3), dtype=np.float32)
    points[:, 0] = x_norm * z
    points[:, 1] = y_norm * z
    points[:, 2] = z
    return points


def backproject(
    depth: FloatingArray,
    K: FloatArray,
    mask: Optional[BoolArray] = None,
    stride: int = 1,
) -> Float32Array:
    """Back-project every valid depth pixel (finite, > 0), optionally masked and strided.

    Args:
        depth: (H, W) float depth in metres (0 = no return; leapnbv_common.conversions.depth_to_metres).
        K: (3, 3) camera matrix.
        mask: optional (H, W) bool; only True pixels are used.
        stride: keep every ``stride``-th row and column (rows 0, s, 2s, ...).

    Returns:
        (N, 3) float32 points in the camera optical frame, in row-major pixel order.

    Raises:
        TargetGeometryError: on a non 2-D depth, a mask of another shape, or stride < 1.
    """
    depth = np.asarray(depth)
    if depth.ndim != 2:
        raise TargetGeometryError(f"backproject: depth must be (H, W), got {depth.shape}")
    stride = int(stride)
    if stride < 1:
        raise TargetGeometryError(f"backproject: stride must be >= 1, got {stride}")
    sub = depth[::stride, ::stride]
    keep = sub > 0.0  # NaN compares False: dropped too
    if not np.issubdtype(sub.dtype, np.integer):
        keep &= np.isfinite(sub)
    if mask is not None:
        mask = np.asarray(mask, dtype=bool)
        if mask.shape != depth.shape:
            raise TargetGeometryError(
                f"backproject: mask shape {mask.shape} differs from depth shape {depth.shape}"
            )
        keep &= mask[::stride, ::stride]
    rows, cols = np.nonzero(keep)
    return pixels_to_points(rows * stride, cols * stride, sub[rows, cols], K)


def place_mesh_metric(
    vertices_virtual: FloatArray,
    virtual_K_params: Sequence[float],
    real_K: FloatArray,
    cam_translation: FloatArray,
    virtual_image_size: Optional[Tuple[int, int]] = None,
    real_image_size: Optional[Tuple[int, int]] = None,
) -> FloatArray:
    """Move a mesh from the HMR virtual camera into the real camera frame (weak perspective).

    The HMR mesh is ``vertices_virtual = body + t`` with t = ``cam_translation`` and is meant to
    be viewed by the virtual camera (fx_v, fy_v, cx_v, cy_v) in full-image pixels. We keep the
    body and replace t by t' such that its centre projects to the same pixel and its image
    scale is the same under the real camera (fx_r, fy_r, cx_r, cy_r):

        t'_z = t_z f_r / f_v                     with f = sqrt(fx fy) per camera,
        t'_x = t_x + (cx_v - cx_r) t_z / fx_v,
        t'_y = t_y + (cy_v - cy_r) t_z / fy_v,
        vertices_real = vertices_virtual + (t' - t).

    When the virtual K equals the real K, t' - t is exactly 0 and the vertices come back
    unchanged (a ground-truth mesh already metric passes through). The depth is still only as
    good as HMR's t_z: :func:`compute_target_geometry` aligns it to the observed depth.

    Both intrinsics must be in pixels of images of the same size (the depth aligned to colour):
    with another size the two K differ although the mesh may already be metric, and the formula
    would rescale it (a ground-truth mesh placed 1.4 m off). Given both sizes, a mismatch is refused.

    Args:
        vertices_virtual: (V, 3) vertices in the virtual camera frame (translation included).
        virtual_K_params: (fx, fy, cx, cy) of the virtual camera in full-image pixels.
        real_K: (3, 3) real camera matrix.
        cam_translation: (3,) the translation t already included in ``vertices_virtual``.
        virtual_image_size: (width, height) of the image the virtual intrinsics are in (HumanMesh
            image_width, image_height), or None.
        real_image_size: (width, height) of the real camera's image (the depth frame), or None.

    Returns:
        (V, 3) float64 vertices in the real camera optical frame.

    Raises:
        TargetGeometryError: on wrong shapes, a non-positive focal length, or image sizes that differ.
    """
    if virtual_image_size is not None and real_image_size is not None \
            and tuple(int(v) for v in virtual_image_size) != tuple(int(v) for v in real_image_size):
        raise TargetGeometryError(
            f"place_mesh_metric: the mesh's image is {tuple(int(v) for v in virtual_image_size)} but the "
            f"real camera's {tuple(int(v) for v in real_image_size)} (width, height): colour and depth must be "
            "aligned to one size")
    vertices_virtual = np.asarray(vertices_virtual, dtype=np.float64)
    if vertices_virtual.ndim != 2 or vertices_virtual.shape[1] != 3:
        raise TargetGeometryError(
            f"place_mesh_metric: vertices_virtual must be (V, 3), got {vertices_virtual.shape}"
        )
    params = np.asarray(virtual_K_params, dtype=np.float64).reshape(-1)
    if params.shape != (4,):
        raise TargetGeometryError(
            f"place_mesh_metric: virtual_K_params must be (fx, fy, cx, cy), got {params.shape}"
        )
    t = np.asarray(cam_translation, dtype=np.float64).reshape(-1)
    if t.shape != (3,):
        raise TargetGeometryError(f"place_mesh_metric: cam_translation must be (3,), got {t.shape}")
    fx_v, fy_v, cx_v, cy_v = (float(p) for p in params)
    fx_r, _, cx_r, fy_r, cy_r = _intrinsics(real_K, "place_mesh_metric: real_K")
    if min(fx_v, fy_v, fx_r, fy_r) <= 0.0:
        raise TargetGeometryError("place_mesh_metric: focal lengths must be positive")
    f_ratio = 1.0 if (fx_v, fy_v) == (fx_r, fy_r) else float(np.sqrt(fx_r * fy_r / (fx_v * fy_v)))
    t_new = np.array([
        t[0] + (cx_v - cx_r) * t[2] / fx_v,
        t[1] + (cy_v - cy_r) * t[2] / fy_v,
        t[2] * f_ratio,
    ])
    placed: FloatArray = vertices_virtual + (t_new - t)
    return placed


def _dilated_box(
    box_xyxy: Sequence[float], dilation_px: float, width: int, height: int
) -> Optional[Tuple[int, int, int, int]]:
    """Integer pixel ranges [row0, row1) x [col0, col1) of the dilated box, clipped; or None."""
    box = np.asarray(box_xyxy, dtype=np.float64).reshape(-1)
    if box.shape != (4,) or not np.all(np.isfinite(box)):
        raise TargetGeometryError(f"box_xyxy must be 4 finite numbers, got {box_xyxy!r}")
    x0, y0, x1, y1 = box
    # A pixel centre (j, i) is inside when x0 - d <= j <= x1 + d (and likewise rows).
    col0 = max(int(np.ceil(min(x0, x1) - dilation_px)), 0)
    col1 = min(int(np.floor(max(x0, x1) + dilation_px)) + 1, width)
    row0 = max(int(np.ceil(min(y0, y1) - dilation_px)), 0)
    row1 = min(int(np.floor(max(y0, y1) + dilation_px)) + 1, height)
    if col0 >= col1 or row0 >= row1:
        return None
    return row0, row1, col0, col1


MIN_CLUSTER_SHARE = 0.15


def _robust_depth_offset(offsets: FloatArray, tolerance: float, min_share: float = MIN_CLUSTER_SHARE) -> float:
    """Depth offset of the person's cluster of D - D_mesh values.

    The person's offsets are tightly clustered (the mesh models its surface, so D - D_mesh is
    nearly constant over it); occluders form clusters NEARER than the person, and background
    seen through gaps of an imperfect silhouette is farther but covers little of it. So we take
    the FARTHEST window of width ``tolerance`` (histogram bins of tolerance / 3, summed over 3
    neighbouring bins) that holds at least ``min_share`` of the offsets -- the densest window
    when none does -- then the median of the offsets within ``tolerance`` of its centre, twice.
    Neither a plain median nor the densest cluster works once an occluder covers more of the
    silhouette than the visible person does: both would align the mesh to the occluder.
    """
    bin_width = tolerance / 3.0
    lowest = float(offsets.min())
    bins = ((offsets - lowest) / bin_width).astype(np.int64)
    counts = np.bincount(bins)
    if counts.shape[0] >= 3:
        window = counts[:-2] + counts[1:-1] + counts[2:]
        supported = np.nonzero(window >= min_share * offsets.size)[0]
        chosen = int(supported[-1]) if supported.size else int(np.argmax(window))
        centre = lowest + (chosen + 1.5) * bin_width
    else:
        centre = lowest + 0.5 * counts.shape[0] * bin_width
    for _ in range(2):
        near_centre = offsets[np.abs(offsets - centre) <= tolerance]
        if near_centre.size == 0:
            break
        centre = float(np.median(near_centre))
    return float(centre)


def compute_target_geometry(
    vertices_metric: FloatArray,
    faces: IntArray,
    depth: FloatingArray,
    K: FloatArray,
    box_xyxy: Sequence[float],
    box_dilation_px: float = 10.0,
    depth_tolerance: float = 0.15,
    min_depth: float = 0.1,
    max_depth: float = 10.0,
    background_stride: int = 4,
    target_stride: int = 1,
    ground_plane: Optional[Tuple[FloatArray, float]] = None,
    ground_inlier_threshold: float = 0.03,
    depth_offset: Optional[float] = None,
    refused_reason: str = "",
    mesh_raster: Optional[RasterResult] = None,
) -> TargetGeometryResult:
    """Person mask, target points and background points of one frame (docs/ALGORITHMS.md §4).

    Steps:
      1. Rasterize the metric mesh with the real K: silhouette M_sil and mesh depth D_mesh.
      2. M = M_sil ∩ dilate(box) (the box grown by ``box_dilation_px`` on every side).
      3. Valid depth: finite and within [min_depth, max_depth]; other pixels are dropped.
      4. Depth alignment: offset = robust median of D - D_mesh over M with valid depth (the
         median of the dominant cluster, see ``_robust_depth_offset``; it ignores occluders
         and background as long as the person is the largest depth cluster in M).
      5. Depth clustering: keep pixels of M with |D - (D_mesh + offset)| <= depth_tolerance;
         much nearer pixels are occluders, much farther ones background seen through gaps.
      6. Target points = back-projection of the kept pixels with the real K; centroid = per
         axis median; axis-aligned bounds.
      7. Background points = valid pixels outside the final mask, on a grid of stride
         ``background_stride``, minus points with |n.x + d| <= ground_inlier_threshold when
         ``ground_plane`` = (n, d) is given.
      8. The mesh is aligned by moving it along the viewing ray through its vertex mean so that
         the mean's z changes by ``offset`` (its image position stays put).

    Args:
        vertices_metric: (V, 3) mesh in the real camera frame (see :func:`place_mesh_metric`).
        faces: (F, 3) int triangles.
        depth: (H, W) float depth in metres, 0 / NaN = no return (leapnbv_common.conversions.depth_to_metres).
        K: (3, 3) real camera matrix.
        box_xyxy: person box (x0, y0, x1, y1) in pixels.
        box_dilation_px: growth of the box on every side, pixels.
        depth_tolerance: metres of allowed disagreement between observed and aligned mesh depth.
        min_depth: nearest valid depth, metres.
        max_depth: farthest valid depth, metres.
        background_stride: pixel stride of the background points.
        target_stride: keep the target points of every n-th image row and column (1: every person pixel).
            What crosses a slow link to the planner (docs/TWO_HOSTS.md); the centroid, box, mask and
            visible fraction are of every person pixel whatever the stride.
        ground_plane: optional (n (3,), d) with n.x + d = 0 the ground.
        ground_inlier_threshold: metres from the plane within which background points are
            ground and left out.
        depth_offset: the depth offset to use instead of step 4's estimate (0.0 for a mesh already
            registered to the depth, ``mesh_registration``), or None to estimate it.
        refused_reason: when not empty, the mesh was refused before this stage: no target point
            (``valid`` False with this reason), every valid pixel is background.
        mesh_raster: the render of ``vertices_metric`` under K at the depth's size when already
            made (the registration's, scaled), or None to render it here.

    Returns:
        TargetGeometryResult; ``valid`` is False (with a reason) instead of raising when the
        frame holds no target point.

    Raises:
        TargetGeometryError: on malformed inputs (shapes, K, box, parameters).
        RasterError: on malformed faces (wrong shape, indices out of range).
    """
    depth = np.asarray(depth)
    if depth.ndim != 2:
        raise TargetGeometryError(f"depth must be (H, W), got {depth.shape}")
    if not np.issubdtype(depth.dtype, np.floating):
        raise TargetGeometryError(
            f"depth must be float metres, got dtype {depth.dtype}; convert with conversions.depth_to_metres"
        )
    vertices_metric = np.asarray(vertices_metric)
    if vertices_metric.ndim != 2 or vertices_metric.shape[1] != 3:
        raise TargetGeometryError(f"vertices_metric must be (V, 3), got {vertices_metric.shape}")
    if not depth_tolerance > 0.0:
        raise TargetGeometryError(f"depth_tolerance must be > 0, got {depth_tolerance}")
    if int(target_stride) < 1:
        raise TargetGeometryError(f"target_stride must be >= 1, got {target_stride}")
    if int(background_stride) < 1:
        raise TargetGeometryError(f"background_stride must be >= 1, got {background_stride}")
    _intrinsics(K)
    height, width = depth.shape

    raster = mesh_raster if mesh_raster is not None else rasterize_mesh(vertices_metric, faces, K, width, height)
    silhouette = raster.silhouette
    mesh_depth = raster.depth
    silhouette_pixel_count = int(np.count_nonzero(silhouette))
    mask = np.zeros((height, width), dtype=bool)
    box_mask = np.zeros((height, width), dtype=bool)

    def valid_depth(values: FloatingArray) -> BoolArray:
        # NaN and +-inf fail one of the comparisons: no separate isfinite pass needed.
        return (values >= min_depth) & (values <= max_depth)

    kept_rows = np.zeros(0, dtype=np.int64)
    kept_cols = np.zeros(0, dtype=np.int64)

    offset = 0.0
    reason = ""
    region = _dilated_box(box_xyxy, float(box_dilation_px), width, height)
    if refused_reason:
        reason = refused_reason
    elif silhouette_pixel_count == 0:
        reason = "mesh silhouette is empty (mesh behind the camera or outside the image)"
    elif region is None:
        reason = "person box lies outside the image"
    else:
        # Everything below works on the dilated box only: the mask cannot leave it.
        row0, row1, col0, col1 = region
        box_mask[row0:row1, col0:col1] = silhouette[row0:row1, col0:col1]
        roi_candidates = box_mask[row0:row1, col0:col1] & valid_depth(depth[row0:row1, col0:col1])
        rows, cols = np.nonzero(roi_candidates)
        if rows.size == 0:
            reason = "no valid depth inside the person silhouette"
        else:
            observed = depth[row0:row1, col0:col1][rows, cols].astype(np.float64)
            rendered = mesh_depth[row0:row1, col0:col1][rows, cols].astype(np.float64)
            differences = observed - rendered
            offset = _robust_depth_offset(differences, float(depth_tolerance)) if depth_offset is None \
                else float(depth_offset)
            agree = np.abs(differences - offset) <= depth_tolerance
            # Row-major within the box is row-major in the image: same order as np.nonzero(mask).
            kept_rows = rows[agree] + row0
            kept_cols = cols[agree] + col0
            mask[kept_rows, kept_cols] = True
            if not np.any(agree):
                reason = "no depth pixel agrees with the mesh depth"

    target_points = pixels_to_points(kept_rows, kept_cols, depth[kept_rows, kept_cols], K)
    mask_pixel_count = int(kept_rows.size)
    visible_fraction = (
        mask_pixel_count / silhouette_pixel_count if silhouette_pixel_count else 0.0
    )

    stride = int(background_stride)
    strided = depth[::stride, ::stride]
    bg_rows, bg_cols = np.nonzero(valid_depth(strided) & ~mask[::stride, ::stride])
    background_points = pixels_to_points(
        bg_rows * stride, bg_cols * stride, strided[bg_rows, bg_cols], K
    )
    if ground_plane is not None and background_points.shape[0]:
        normal = np.asarray(ground_plane[0], dtype=np.float32).reshape(3)
        plane_offset = np.float32(ground_plane[1])
        off_plane = np.abs(background_points @ normal + plane_offset) > ground_inlier_threshold
        background_points = background_points[off_plane]

    metric_vertices = np.asarray(vertices_metric, dtype=np.float32)
    if offset != 0.0 and vertices_metric.shape[0]:
        centre = vertices_metric.astype(np.float64).mean(axis=0)
        if centre[2] > 0.0:
            shift = centre / centre[2] * offset
        else:
            shift = np.array([0.0, 0.0, offset])
        metric_vertices = (vertices_metric + shift).astype(np.float32)
    else:
        metric_vertices = metric_vertices.copy()

    valid = mask_pixel_count > 0
    if valid:
        centroid = np.median(target_points, axis=0).astype(np.float64)
        bbox_min = target_points.min(axis=0).astype(np.float64)
        bbox_max = target_points.max(axis=0).astype(np.float64)
    else:
        centroid = np.zeros(3)
        bbox_min = np.zeros(3)
        bbox_max = np.zeros(3)
    if int(target_stride) > 1 and valid:
        on_grid = (kept_rows % int(target_stride) == 0) & (kept_cols % int(target_stride) == 0)
        if np.any(on_grid):  # a person smaller than the grid keeps its pixels: never a valid target without points
            target_points = target_points[on_grid]
    return TargetGeometryResult(
        valid=valid,
        invalid_reason=reason if not valid else "",
        target_points=target_points,
        centroid=centroid,
        bbox_min=bbox_min,
        bbox_max=bbox_max,
        mask=mask,
        silhouette=silhouette,
        box_mask=box_mask,
        mask_pixel_count=mask_pixel_count,
        silhouette_pixel_count=silhouette_pixel_count,
        visible_fraction=float(visible_fraction),
        depth_offset=float(offset),
        background_points=background_points,
        metric_vertices=metric_vertices,
        mesh_depth=mesh_depth,
    )
