"""S_a: how much of the image the target's projected 3D bounding box covers (docs/ALGORITHMS.md §7: the bounding
rectangle of the projected box, a deliberate deviation from the box's own image area)."""

from __future__ import annotations

import numpy as np

from leapnbv_planner.arrays import Array
from leapnbv_planner.occlusion_kernel import axis_aligned_bounds
from leapnbv_planner.score_terms.base import (
    Camera,
    ScoringContext,
    check_camera,
    check_poses,
    finite_points,
    score_term,
)

# Near plane for the bounding-box area: the box is clipped to z >= NEAR_PLANE_M before
# projecting, so a box reaching behind the camera extends to the image border on that side.
NEAR_PLANE_M = 1e-6

# Corner k of an axis-aligned box takes the max along axis a when bit a of k is set; box edges
# join corners differing in exactly one bit.
_CORNER_BITS = np.array([[(k >> axis) & 1 for axis in range(3)] for k in range(8)], dtype=bool)
_BOX_EDGES = np.array(
    [(k, k | (1 << axis)) for k in range(8) for axis in range(3) if not k & (1 << axis)]
)


@score_term("area", 0.14, "S_a, projected target box area over the image area")
def area(context: ScoringContext) -> Array:
    """S_a of every candidate: see bounding_box_area_fraction."""
    return box_area_fraction(context.targets, context.rotations, context.positions, context.camera)


def to_camera_frame(points: Array, rotations: Array, positions: Array) -> Array:
    """Express observation-frame points in each candidate camera's frame.

    Args:
        points: (M, 3) or (C, M, 3) points in the observation frame.
        rotations: (C, 3, 3) camera-to-observation rotations.
        positions: (C, 3) camera centres.

    Returns:
        (C, M, 3) camera coordinates R_c^T (p - t_c).
    """
    offsets = (points[None] if points.ndim == 2 else points) - positions[:, None, :]
    # Row vectors: (p - t)^T R = (R^T (p - t))^T.
    camera_points: Array = np.matmul(offsets, rotations)
    return camera_points


def bounding_box_area_fraction(
    target_points: Array,
    rotations: Array,
    positions: Array,
    K: Array,
    width: int,
    height: int,
) -> Array:
    """S_a: image area covered by the projected 3D bounding box of the target, over W*H.

    The box is the target's axis-aligned bounding box in the observation frame (8 corners).
    For each candidate the box is clipped to the near half-space z >= NEAR_PLANE_M (the
    vertices of the clipped box are the corners in front plus the crossings of the 12 box
    edges with the near plane), the vertices are projected, and their 2D bounding rectangle
    [u_min, u_max] x [v_min, v_max] is clipped to [0, W] x [0, H]. Because projection maps
    the convex clipped box to the convex hull of its projected vertices, this rectangle is
    the bounding rectangle of the box's image. A box reaching behind the camera therefore
    extends to the image border on the side that goes behind; a box wholly behind, or fewer
    than one target point, gives 0.

    Args:
        target_points: (N, 3) finite target points.
        rotations: (C, 3, 3) camera-to-observation rotations.
        positions: (C, 3) camera centres.
        K: (3, 3) intrinsics.
        width, height: image size in pixels.

    Returns:
        (C,) float64 fractions in [0, 1].
    """
    points = finite_points(target_points, "target_points")
    rotation_array, position_array = check_poses(rotations, positions)
    camera = check_camera(K, width, height)
    return box_area_fraction(points, rotation_array, position_array, camera)


def box_area_fraction(
    points: Array,
    rotation_array: Array,
    position_array: Array,
    camera: Camera,
) -> Array:
    """bounding_box_area_fraction on validated inputs (see there)."""
    fx, skew, cx, fy, cy, width, height = camera
    num_candidates = rotation_array.shape[0]
    if points.shape[0] == 0 or num_candidates == 0:
        return np.zeros(num_candidates)

    lower, upper = axis_aligned_bounds(points)
    corners = np.where(_CORNER_BITS, upper, lower)  # (8, 3)
    camera_corners = to_camera_frame(corners, rotation_array, position_array)  # (C, 8, 3)
    depth = camera_corners[..., 2]
    in_front = depth >= NEAR_PLANE_M

    # Crossings of the box edges with the near plane z = NEAR_PLANE_M.
    start = camera_corners[:, _BOX_EDGES[:, 0]]  # (C, 12, 3)
    end = camera_corners[:, _BOX_EDGES[:, 1]]
    crosses = in_front[:, _BOX_EDGES[:, 0]] != in_front[:, _BOX_EDGES[:, 1]]
    depth_step = np.where(crosses, end[..., 2] - start[..., 2], 1.0)
    fraction = np.where(crosses, (NEAR_PLANE_M - start[..., 2]) / depth_step, 0.0)
    crossings = start + fraction[..., None] * (end - start)
    crossings[..., 2] = NEAR_PLANE_M

    vertices = np.concatenate([camera_corners, crossings], axis=1)  # (C, 20, 3)
    valid = np.concatenate([in_front, crosses], axis=1)
    safe_depth = np.where(valid, vertices[..., 2], 1.0)
    x_norm = vertices[..., 0] / safe_depth
    y_norm = vertices[..., 1] / safe_depth
    u = fx * x_norm + skew * y_norm + cx
    v = fy * y_norm + cy
    any_valid = np.any(valid, axis=1)
    u_min = np.clip(np.where(valid, u, np.inf).min(axis=1), 0.0, width)
    u_max = np.clip(np.where(valid, u, -np.inf).max(axis=1), 0.0, width)
    v_min = np.clip(np.where(valid, v, np.inf).min(axis=1), 0.0, height)
    v_max = np.clip(np.where(valid, v, -np.inf).max(axis=1), 0.0, height)
    area = np.maximum(u_max - u_min, 0.0) * np.maximum(v_max - v_min, 0.0)
    return np.asarray(np.where(any_valid, area / float(width * height), 0.0), dtype=np.float64)
