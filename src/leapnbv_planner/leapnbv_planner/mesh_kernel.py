"""A triangle mesh's outward vertex normals: compiled sums of the face normals per vertex, and their
normalization (mesh_vertex_normals)."""

from __future__ import annotations

from typing import Tuple

import numpy as np

from leapnbv_planner.arrays import Array
from leapnbv_planner.jit import njit


@njit(cache=True)
def face_normal_sums(vertices: Array, faces: Array) -> Array:
    """(V, 3) sum over the faces of each vertex of (b - a) x (c - a), the face's area-weighted normal.

    The arithmetic is numpy's: the cross product as np.cross computes it (each product rounded, then
    subtracted), and the sums in the order np.bincount takes them over faces.reshape(-1) (face by face,
    corner by corner), so the result is bit for bit the numpy one.

    Args:
        vertices: (V, 3) float64.
        faces: (F, 3) int64 indices in [0, V) (checked by the caller).
    """
    sums = np.zeros(vertices.shape)
    for f in range(faces.shape[0]):
        a, b, c = faces[f, 0], faces[f, 1], faces[f, 2]
        e0 = vertices[b, 0] - vertices[a, 0]
        e1 = vertices[b, 1] - vertices[a, 1]
        e2 = vertices[b, 2] - vertices[a, 2]
        g0 = vertices[c, 0] - vertices[a, 0]
        g1 = vertices[c, 1] - vertices[a, 1]
        g2 = vertices[c, 2] - vertices[a, 2]
        n0 = e1 * g2 - e2 * g1
        n1 = e2 * g0 - e0 * g2
        n2 = e0 * g1 - e1 * g0
        for corner in range(3):
            v = faces[f, corner]
            sums[v, 0] += n0
            sums[v, 1] += n1
            sums[v, 2] += n2
    return sums


@njit(cache=True)
def unit_normals(sums: Array, vertices: Array, centre: Array) -> Tuple[Array, float, float]:
    """(V, 3) sums / |sums| per row (0 for a zero row), with numpy's arithmetic for np.linalg.norm(axis=1) and
    ``np.where(length > 0, sums / np.maximum(length, 1e-300), 0)``; and the sum over the vertices of
    n . (v - centre) and of its terms' magnitudes (what decides, and bounds the rounding of, the outward sign).
    """
    count = sums.shape[0]
    normals = np.empty((count, 3))
    total = 0.0
    magnitude = 0.0
    for v in range(count):
        x, y, z = sums[v, 0], sums[v, 1], sums[v, 2]
        length = np.sqrt(x * x + y * y + z * z)
        if length > 0.0:
            divisor = max(length, 1e-300)
            normals[v, 0] = x / divisor
            normals[v, 1] = y / divisor
            normals[v, 2] = z / divisor
        else:
            normals[v, 0] = 0.0
            normals[v, 1] = 0.0
            normals[v, 2] = 0.0
        for a in range(3):
            term = normals[v, a] * (vertices[v, a] - centre[a])
            total += term
            magnitude += abs(term)
    return normals, total, magnitude


def mesh_vertex_normals(vertices: Array, faces: Array) -> Array:
    """(V, 3) unit outward vertex normals of a triangle mesh (area-weighted face normals summed per vertex).

    The faces' winding decides the sign; a closed body's normals are turned outward when they point, on
    the whole, toward its centre. A vertex in no face gets a zero normal (it never faces a camera).

    Raises:
        ValueError: vertices not (V, 3) or faces not (F, 3) indices into them.
    """
    vertices = np.asarray(vertices, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    if vertices.ndim != 2 or vertices.shape[1] != 3 or faces.ndim != 2 or faces.shape[1] != 3:
        raise ValueError(f"mesh: vertices must be (V, 3) and faces (F, 3), got {vertices.shape} and {faces.shape}")
    if faces.size and (faces.min() < 0 or faces.max() >= len(vertices)):
        raise ValueError(f"mesh: face indices must lie in [0, {len(vertices)})")
    vertices = np.ascontiguousarray(vertices)
    centre = vertices.mean(axis=0)
    normals, total, magnitude = unit_normals(face_normal_sums(vertices, np.ascontiguousarray(faces)), vertices,
                                             centre)
    # The sign of the sum decides; when it is too near 0 for the summation order not to matter (never for a body),
    # it is taken as numpy sums it.
    if abs(total) <= 1e-9 * magnitude:
        total = float(np.sum(normals * (vertices - centre)))
    if total < 0.0:
        normals = -normals
    return normals
