"""Compiled test of which candidate foot points have an obstacle point within the robot radius."""

from __future__ import annotations

import numpy as np

from leapnbv_planner.jit import njit


@njit(cache=True)
def footprints_blocked(
    points: np.ndarray,
    unit_normal: np.ndarray,
    plane_offset: float,
    floor_clearance: float,
    plane_axis_u: np.ndarray,
    plane_axis_v: np.ndarray,
    feet_u: np.ndarray,
    feet_v: np.ndarray,
    robot_radius: float,
) -> np.ndarray:
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
    num_feet = feet_u.shape[0]
    blocked = np.zeros(num_feet, dtype=np.bool_)
    if num_feet == 0:
        return blocked
    radius_squared = robot_radius * robot_radius
    # Bounding square of all footprints: most points fail this cheap test.
    u_lo, u_hi = feet_u.min() - robot_radius, feet_u.max() + robot_radius
    v_lo, v_hi = feet_v.min() - robot_radius, feet_v.max() + robot_radius
    # The feet sorted by u: a point is tested only against the feet whose u lies within the radius of its own
    # (widened by far more than the rounding, so no foot the distance test would block is left out).
    order = np.argsort(feet_u)
    sorted_u = feet_u[order]
    reach = robot_radius * (1.0 + 1e-9) + 1e-12
    for k in range(points.shape[0]):
        x, y, z = points[k, 0], points[k, 1], points[k, 2]
        height = unit_normal[0] * x + unit_normal[1] * y + unit_normal[2] * z + plane_offset
        if not height > floor_clearance:  # also drops NaN
            continue
        u = plane_axis_u[0] * x + plane_axis_u[1] * y + plane_axis_u[2] * z
        v = plane_axis_v[0] * x + plane_axis_v[1] * y + plane_axis_v[2] * z
        if not (u >= u_lo and u <= u_hi and v >= v_lo and v <= v_hi):
            continue
        first = np.searchsorted(sorted_u, u - reach)
        for i in range(first, num_feet):
            if sorted_u[i] > u + reach:
                break
            c = order[i]
            du = u - feet_u[c]
            dv = v - feet_v[c]
            if du * du + dv * dv <= radius_squared:
                blocked[c] = True
    return blocked
