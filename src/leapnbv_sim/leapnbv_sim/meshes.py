"""Mesh building blocks of the scenes (boxes, quads) and the 2-D floor-plan geometry used to place them.

A box is ``box_mesh(centre, size, yaw)``: 8 corners (corner index 4 ix + 2 iy + iz), 12 triangles,
turned by ``yaw`` about world z. Its floor footprint is :func:`box_footprint`. Placement keeps
footprints apart with :func:`convex_polygons_apart` (and :func:`convex_hull_2d` for a region).
"""

from __future__ import annotations

from typing import List, Tuple

import numpy as np

from leapnbv_common.array_types import FloatArray, Int32Array


def box_mesh(centre: FloatArray, size: FloatArray, yaw: float) -> Tuple[FloatArray, Int32Array]:
    """Axis-aligned-in-yaw box: 8 vertices, 12 triangles (world frame)."""
    half = 0.5 * np.asarray(size, dtype=np.float64)
    corners = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], dtype=np.float64) * half
    c, s = np.cos(yaw), np.sin(yaw)
    rotation = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    vertices = corners @ rotation.T + centre
    # Corner index = 4*ix + 2*iy + iz.
    faces = np.array(
        [
            [0, 1, 3],
            [0, 3, 2],  # x-
            [4, 6, 7],
            [4, 7, 5],  # x+
            [0, 4, 5],
            [0, 5, 1],  # y-
            [2, 3, 7],
            [2, 7, 6],  # y+
            [0, 2, 6],
            [0, 6, 4],  # z-
            [1, 5, 7],
            [1, 7, 3],  # z+
        ],
        dtype=np.int32,
    )
    return vertices, faces


def quad_mesh(corners: FloatArray) -> Tuple[FloatArray, Int32Array]:
    """Planar quad from 4 corners in order: 4 vertices, 2 triangles."""
    return np.asarray(corners, dtype=np.float64), np.array([[0, 1, 2], [0, 2, 3]], dtype=np.int32)


def box_footprint(centre: FloatArray, size: FloatArray, yaw: float) -> FloatArray:
    """(4,2) floor footprint of a box of :func:`box_mesh`, counter-clockwise."""
    half = 0.5 * np.asarray(size, dtype=np.float64)[:2]
    corners = np.array([[-1.0, -1.0], [1.0, -1.0], [1.0, 1.0], [-1.0, 1.0]]) * half
    c, s = np.cos(yaw), np.sin(yaw)
    footprint: FloatArray = corners @ np.array([[c, s], [-s, c]]) + np.asarray(centre, dtype=np.float64)[:2]
    return footprint


def convex_hull_2d(points: FloatArray) -> FloatArray:
    """(K,2) convex hull, counter-clockwise (Andrew's monotone chain) of (N,2) points."""
    unique = sorted(set(map(tuple, np.asarray(points, dtype=np.float64).tolist())))
    if len(unique) < 3:
        return np.asarray(unique, dtype=np.float64)

    def cross(o: Tuple[float, float], a: Tuple[float, float], b: Tuple[float, float]) -> float:
        return (a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0])

    lower: List[Tuple[float, float]] = []
    for point in unique:
        while len(lower) >= 2 and cross(lower[-2], lower[-1], point) <= 0:
            lower.pop()
        lower.append(point)
    upper: List[Tuple[float, float]] = []
    for point in reversed(unique):
        while len(upper) >= 2 and cross(upper[-2], upper[-1], point) <= 0:
            upper.pop()
        upper.append(point)
    return np.asarray(lower[:-1] + upper[:-1], dtype=np.float64)


def convex_polygons_apart(a: FloatArray, b: FloatArray, gap: float) -> bool:
    """Whether two convex polygons (K,2) are at least ``gap`` apart along one of their edge normals.

    A separating axis with a gap of ``gap`` proves a distance of at least ``gap`` (conservative:
    polygons whose closest points are vertex to vertex may be refused a little early).
    """
    for polygon in (a, b):
        edges = np.roll(polygon, -1, axis=0) - polygon
        normals = np.stack([edges[:, 1], -edges[:, 0]], axis=1)
        normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)
        project_a = a @ normals.T
        project_b = b @ normals.T
        apart = (project_a.min(axis=0) - project_b.max(axis=0) >= gap) | (
            project_b.min(axis=0) - project_a.max(axis=0) >= gap
        )
        if np.any(apart):
            return True
    return False
