"""Compiled shortest paths on a 2-D occupancy grid (Dijkstra, 8-connected)."""

from __future__ import annotations

import heapq
from typing import Tuple

import numpy as np

from leapnbv_planner.arrays import Array
from leapnbv_planner.jit import njit

_SQRT2 = float(np.sqrt(2.0))


@njit(cache=True)
def grid_distances(free: Array, start_row: int, start_col: int, cell: float) -> Tuple[Array, Array]:
    """Path length from the start cell to every cell over free cells (8-connected, diagonals sqrt(2) cells).

    A diagonal step needs both cells it cuts past to be free too (no corner cutting through an obstacle).

    Args:
        free: (R, C) bool, True where the robot's centre may be.
        start_row, start_col: the start cell (it is taken as free).
        cell: cell edge in metres.

    Returns:
        (distances (R, C) float64 metres, inf where unreachable; parents (R, C) int64 flat index of the
        previous cell on the shortest path, -1 for the start and unreachable cells).
    """
    rows, cols = free.shape
    distances = np.full((rows, cols), np.inf)
    parents = np.full((rows, cols), -1, dtype=np.int64)
    distances[start_row, start_col] = 0.0
    heap = [(0.0, start_row * cols + start_col)]
    d_rows = (-1, -1, -1, 0, 0, 1, 1, 1)
    d_cols = (-1, 0, 1, -1, 1, -1, 0, 1)
    while len(heap) > 0:
        distance, index = heapq.heappop(heap)
        r = index // cols
        c = index - r * cols
        if distance > distances[r, c]:
            continue
        for k in range(8):
            nr = r + d_rows[k]
            nc = c + d_cols[k]
            if nr < 0 or nr >= rows or nc < 0 or nc >= cols or not free[nr, nc]:
                continue
            diagonal = d_rows[k] != 0 and d_cols[k] != 0
            if diagonal and not (free[r, nc] and free[nr, c]):
                continue
            step = cell * (1.4142135623730951 if diagonal else 1.0)
            candidate = distance + step
            if candidate < distances[nr, nc]:
                distances[nr, nc] = candidate
                parents[nr, nc] = index
                heapq.heappush(heap, (candidate, nr * cols + nc))
    return distances, parents


@njit(cache=True)
def mark_occupied_in_plane(plane_points: Array, origin: Array, cell: float, occupied: Array) -> None:
    """Mark the grid cell of every point (in place), given as plane coordinates (p.e1, p.e2) of the points already
    kept by height (footprint_kernel.elevated_plane_points): cell (floor((v - o_v) / cell), floor((u - o_u) / cell));
    points off the grid are skipped."""
    rows, cols = occupied.shape
    for k in range(plane_points.shape[0]):
        u = (plane_points[k, 0] - origin[0]) / cell
        v = (plane_points[k, 1] - origin[1]) / cell
        if not (u >= 0.0 and v >= 0.0 and u < cols and v < rows):
            continue
        occupied[int(v), int(u)] = True
