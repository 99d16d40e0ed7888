"""Compiled test of which candidate foot points have an obstacle point within the robot radius."""

from __future__ import annotations

from typing import Tuple

import numpy as np

from leapnbv_planner.arrays import Array
from leapnbv_planner.jit import njit


@njit(cache=True)
def _cells_near(foot_u: float, foot_v: float, u_lo: float, v_lo: float, size: float, reach: float, cols: int,
                rows: int) -> Tuple[int, int, int, int]:
    """(first col, last col, first row, last row) of the grid cells that come within reach of the foot."""
    col_a = max(0, int(np.floor((foot_u - reach - u_lo) / size)) - 1)
    col_b = min(cols - 1, int(np.floor((foot_u + reach - u_lo) / size)) + 1)
    row_a = max(0, int(np.floor((foot_v - reach - v_lo) / size)) - 1)
    row_b = min(rows - 1, int(np.floor((foot_v + reach - v_lo) / size)) + 1)
    return col_a, col_b, row_a, row_b


@njit(cache=True)
def elevated_plane_points(points: Array, unit_normal: Array, plane_offset: float, min_height: float,
                          plane_axis_u: Array, plane_axis_v: Array) -> Array:
    """(M, 2) plane coordinates (p.a_u, p.a_v) of the finite points higher than min_height above the plane
    (n.p + d > min_height), in input order: what the footprint test and the floor grid read of an obstacle cloud,
    made once for both.

    Args:
        points: (K, 3) float64 points.
        unit_normal: (3,) unit ground normal n.
        plane_offset: ground offset d.
        min_height: height above which a point is kept.
        plane_axis_u, plane_axis_v: (3,) orthonormal vectors spanning the plane.
    """
    out = np.empty((points.shape[0], 2))
    count = 0
    for k in range(points.shape[0]):
        x, y, z = points[k, 0], points[k, 1], points[k, 2]
        height = unit_normal[0] * x + unit_normal[1] * y + unit_normal[2] * z + plane_offset
        if not height > min_height:  # also drops NaN
            continue
        out[count, 0] = plane_axis_u[0] * x + plane_axis_u[1] * y + plane_axis_u[2] * z
        out[count, 1] = plane_axis_v[0] * x + plane_axis_v[1] * y + plane_axis_v[2] * z
        count += 1
    return out[:count]


def footprints_blocked(
    points: Array,
    unit_normal: Array,
    plane_offset: float,
    floor_clearance: float,
    plane_axis_u: Array,
    plane_axis_v: Array,
    feet_u: Array,
    feet_v: Array,
    robot_radius: float,
) -> Array:
    """For each foot point, whether an obstacle point lies within robot_radius of it.

    An obstacle point is a finite point p with height n.p + d > floor_clearance. Distances
    are measured in the plane: between (p.a_u, p.a_v) and the foot point's (u, v), where
    a_u, a_v span the plane; a distance equal to robot_radius counts as blocked.

    Args:
        points: (K, 3) float64 background points.
        unit_normal: (3,) unit ground normal n.
        plane_offset: ground offset d.
        floor_clearance: height above which a point is an obstacle.
        plane_axis_u, plane_axis_v: (3,) orthonormal vectors spanning the plane.
        feet_u, feet_v: (C,) plane coordinates of the candidate foot points.
        robot_radius: footprint radius.

    Returns:
        (C,) bool, True where the footprint holds an obstacle point.
    """
    return footprints_blocked_in_plane(
        elevated_plane_points(points, unit_normal, plane_offset, floor_clearance, plane_axis_u, plane_axis_v),
        feet_u, feet_v, robot_radius)


@njit(cache=True)
def footprints_blocked_in_plane(plane_points: Array, feet_u: Array, feet_v: Array,
                                robot_radius: float) -> Array:
    """footprints_blocked over the obstacle points' plane coordinates (from :func:`elevated_plane_points`).

    Returns:
        (C,) bool, True where some point lies within robot_radius of the foot point (a distance equal to it counts).
    """
    num_feet = feet_u.shape[0]
    blocked = np.zeros(num_feet, dtype=np.bool_)
    if num_feet == 0:
        return blocked
    radius_squared = robot_radius * robot_radius
    # Bounding square of all footprints: most points fail this cheap test.
    u_lo, u_hi = feet_u.min() - robot_radius, feet_u.max() + robot_radius
    v_lo, v_hi = feet_v.min() - robot_radius, feet_v.max() + robot_radius
    # A grid of square cells over the bounding square; each cell lists the feet within the radius of some point of
    # it (widened by far more than the rounding of a point's cell index, so no foot the distance test would block
    # is left out). A point is tested only against its cell's feet.
    size = max(robot_radius, (u_hi - u_lo) / 64.0, (v_hi - v_lo) / 64.0, 1e-9)
    cols = int((u_hi - u_lo) / size) + 1
    rows = int((v_hi - v_lo) / size) + 1
    reach = robot_radius * (1.0 + 1e-9) + size * 1e-9 + 1e-12
    counts = np.zeros(rows * cols + 1, dtype=np.int64)
    for c in range(num_feet):
        col_a, col_b, row_a, row_b = _cells_near(feet_u[c], feet_v[c], u_lo, v_lo, size, reach, cols, rows)
        for row in range(row_a, row_b + 1):
            for col in range(col_a, col_b + 1):
                counts[row * cols + col + 1] += 1
    for cell in range(rows * cols):
        counts[cell + 1] += counts[cell]
    fill = counts[:rows * cols].copy()
    listed = np.empty(counts[rows * cols], dtype=np.int64)
    for c in range(num_feet):
        col_a, col_b, row_a, row_b = _cells_near(feet_u[c], feet_v[c], u_lo, v_lo, size, reach, cols, rows)
        for row in range(row_a, row_b + 1):
            for col in range(col_a, col_b + 1):
                listed[fill[row * cols + col]] = c
                fill[row * cols + col] += 1
    for k in range(plane_points.shape[0]):
        u = plane_points[k, 0]
        v = plane_points[k, 1]
        if not (u >= u_lo and u <= u_hi and v >= v_lo and v <= v_hi):
            continue
        cell = min(int((v - v_lo) / size), rows - 1) * cols + min(int((u - u_lo) / size), cols - 1)
        for i in range(counts[cell], counts[cell + 1]):
            c = listed[i]
            du = u - feet_u[c]
            dv = v - feet_v[c]
            if du * du + dv * dv <= radius_squared:
                blocked[c] = True
    return blocked
