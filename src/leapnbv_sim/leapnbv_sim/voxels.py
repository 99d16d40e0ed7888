"""Voxel maps of the scene's static obstacles, the ground truth of a robot's mapping stack (e.g. OctoMap).

Voxels follow OctoMap's convention: voxel (i, j, k) spans [i r, (i+1) r) on each axis (r = the
resolution) and its centre is ((i, j, k) + 0.5) r. A voxel is occupied when an obstacle's solid
reaches into it; a box that only touches a voxel's face does not occupy it. A wall (a rectangle
of zero thickness) occupies every voxel it passes through, so it is one voxel thick unless its
plane lies exactly on a voxel boundary (then both layers). Voxels entirely below the floor
(k < 0) are left out. Boxes (:func:`leapnbv_sim.meshes.box_mesh`) and rectangles
(:func:`leapnbv_sim.meshes.quad_mesh`) are voxelized exactly (separating-axis test of each
candidate voxel against the oriented box); an object of another shape is voxelized from samples
of its triangles at r/4 spacing.
"""

from __future__ import annotations

from typing import Iterable, Optional, Tuple

import numpy as np

from leapnbv_common.array_types import FloatArray, Int64Array, IntArray

# Half thickness (m) given to a flat obstacle (a wall quad) so that it occupies the voxels its
# plane passes through, and the slack of the separating-axis test against round-off.
_FLAT_HALF_THICKNESS = 1e-6
_SEPARATION_SLACK = 1e-9


def occupied_voxel_centres(
    vertices: FloatArray,
    faces: IntArray,
    face_object_id: IntArray,
    object_ids: Iterable[int],
    resolution: float,
) -> FloatArray:
    """World-frame centres of the voxels that the given objects of a mesh occupy.

    Args:
        vertices: (N,3) mesh vertices, world frame.
        faces: (M,3) triangles into ``vertices``.
        face_object_id: (M,) object id per face.
        object_ids: The objects to voxelize (each a box, a rectangle or any triangle set).
        resolution: Voxel edge length in metres, finite and > 0 (the caller checks).

    Returns:
        (K,3) float64 voxel centres, sorted by (i, j, k), each voxel once.
    """
    res = float(resolution)
    blocks = [np.zeros((0, 3), dtype=np.int64)]
    for object_id in object_ids:
        object_faces = faces[face_object_id == object_id]
        if len(object_faces) == 0:
            continue
        used = np.unique(object_faces)
        object_vertices = vertices[used]
        box = oriented_box_of(object_vertices, len(object_faces))
        if box is not None:
            blocks.append(oriented_box_voxels(box[0], box[1], box[2], res))
        else:
            blocks.append(triangle_voxels(object_vertices, np.searchsorted(used, object_faces), res))
    indices = np.concatenate(blocks, axis=0)
    indices = indices[indices[:, 2] >= 0]
    indices = np.unique(indices, axis=0) if len(indices) else indices
    return (indices.astype(np.float64) + 0.5) * res


def oriented_box_of(vertices: FloatArray, face_count: int) -> Optional[Tuple[FloatArray, FloatArray, FloatArray]]:
    """(centre (3,), axes (3,3) unit rows, half extents (3,)) of a box mesh or quad mesh object.

    A box has 8 vertices (corner index 4 ix + 2 iy + iz) and 12 faces; a quad has 4 corners in
    order and 2 faces (a flat box: half extent 0 along its normal). Returns None when the
    vertices do not form a rectangular box or rectangle in that order.
    """
    vertices = np.asarray(vertices, dtype=np.float64)
    if len(vertices) == 8 and face_count == 12:
        origin = vertices[0]
        edges = np.stack([vertices[4] - origin, vertices[2] - origin, vertices[1] - origin])
        signs = np.array([[sx, sy, sz] for sx in (0, 1) for sy in (0, 1) for sz in (0, 1)], dtype=np.float64)
        rebuilt = origin + signs @ edges
    elif len(vertices) == 4 and face_count == 2:
        origin = vertices[0]
        u, v = vertices[1] - origin, vertices[3] - origin
        edges = np.stack([u, v, np.cross(u, v)])
        rebuilt = np.stack([origin, origin + u, origin + u + v, origin + v])
    else:
        return None
    lengths = np.linalg.norm(edges, axis=1)
    if np.any(lengths < 1e-12):
        return None
    axes = edges / lengths[:, None]
    scale = max(1.0, float(np.abs(vertices).max()))
    if np.abs(axes @ axes.T - np.eye(3)).max() > 1e-6 or np.abs(rebuilt - vertices).max() > 1e-9 * scale:
        return None
    half = 0.5 * lengths
    if len(vertices) == 4:
        half[2] = 0.0
    return vertices.mean(axis=0), axes, half


def oriented_box_voxels(centre: FloatArray, axes: FloatArray, half: FloatArray, res: float) -> Int64Array:
    """(N,3) int64 indices of the voxels (edge ``res``, OctoMap convention) an oriented box reaches into.

    Separating-axis test of every voxel of the box's bounding range: the 3 world axes, the 3
    box axes and their 9 cross products; a voxel is kept when no axis separates it from the
    box (touching counts as separated). Flat boxes get ``_FLAT_HALF_THICKNESS``.
    """
    half = np.maximum(np.asarray(half, dtype=np.float64), _FLAT_HALF_THICKNESS)
    extent = np.abs(axes).T @ half  # world-axis half extents of the box
    low = np.floor((centre - extent) / res).astype(np.int64)
    high = np.floor((centre + extent) / res).astype(np.int64)
    low[2] = max(low[2], 0)  # nothing entirely below the floor
    if np.any(high < low):
        return np.zeros((0, 3), dtype=np.int64)
    grids = np.meshgrid(*[np.arange(low[i], high[i] + 1) for i in range(3)], indexing="ij")
    indices = np.stack([grid.reshape(-1) for grid in grids], axis=1)
    offsets = (indices + 0.5) * res - centre
    test_axes = [np.eye(3)[i] for i in range(3)] + [axes[j] for j in range(3)]
    test_axes += [np.cross(np.eye(3)[i], axes[j]) for i in range(3) for j in range(3)]
    keep = np.ones(len(indices), dtype=bool)
    for axis in test_axes:
        norm = np.linalg.norm(axis)
        if norm < 1e-9:  # parallel edges: no axis
            continue
        axis = axis / norm
        reach = 0.5 * res * np.abs(axis).sum() + np.abs(axes @ axis) @ half
        keep &= np.abs(offsets @ axis) < reach - _SEPARATION_SLACK
    kept: Int64Array = indices[keep]
    return kept


def triangle_voxels(vertices: FloatArray, faces: IntArray, res: float) -> Int64Array:
    """(N,3) int64 indices of the voxels (edge ``res``) holding samples of triangles at <= res/4 spacing."""
    blocks = [np.zeros((0, 3), dtype=np.int64)]
    for a, b, c in np.asarray(vertices, dtype=np.float64)[np.asarray(faces)]:
        longest = max(np.linalg.norm(b - a), np.linalg.norm(c - b), np.linalg.norm(a - c))
        steps = max(1, int(np.ceil(longest / (0.25 * res))))
        i, j = np.meshgrid(np.arange(steps + 1), np.arange(steps + 1), indexing="ij")
        inside = i + j <= steps
        u, v = i[inside] / steps, j[inside] / steps
        points = a + u[:, None] * (b - a) + v[:, None] * (c - a)
        blocks.append(np.floor(points / res).astype(np.int64))
    return np.concatenate(blocks, axis=0)
