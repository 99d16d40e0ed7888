"""Reference kernels of the planner's tests: the plain forms its fast kernels must equal, count for count.

``count_visible_targets`` projects every target point and tests every background point (what
:func:`leapnbv_planner.occlusion_kernel.count_visible_targets_bucketed` computes over boxes of
points); ``segments_clear`` walks every segment cell by cell (what
:func:`leapnbv_planner.obstacle_map.segments_clear_skipping_empty` computes while leaving out the
walk where its answer is sure). Neither runs on the robot: the tests and ``scripts/bench/bench_planner.py``
compare the fast kernels with them (this folder's conftest puts it on sys.path).
"""

from __future__ import annotations

import math
from typing import Tuple

import numpy as np

from leapnbv_planner.jit import njit
from leapnbv_planner.occlusion_kernel import _row_window_minima


@njit(cache=True)
def count_visible_targets(
    target_points: np.ndarray,
    background_points: np.ndarray,
    rotations: np.ndarray,
    positions: np.ndarray,
    fx: float,
    skew: float,
    cx: float,
    fy: float,
    cy: float,
    width: int,
    height: int,
    half_window: int,
    target_normals: np.ndarray,
) -> Tuple[np.ndarray, np.ndarray]:
    """Count, per candidate, the target points in view and those not hidden.

    With ``target_normals`` of N rows (outward surface normals, e.g. a body mesh's vertex normals),
    a target point whose normal faces away from the candidate camera (n . (t_c - p) <= 0: the body's
    far side) is neither in view nor counted; with 0 rows every point counts.

    For candidate c a point p has camera coordinates (x, y, z) = R_c^T (p - t_c) and,
    when z > 0, image coordinates u = fx (x/z) + skew (y/z) + cx, v = fy (y/z) + cy and
    pixel (floor(u), floor(v)).
    In view: z > 0 and 0 <= u < width and 0 <= v < height.
    Not hidden: an in-view target point at pixel (i, j) with depth z_t is not hidden when
    z_t <= min z_b over the background points with z_b > 0 whose pixel (i_b, j_b) satisfies
    |i_b - i| <= half_window and |j_b - j| <= half_window (a square window on the pixel
    grid), or when there is no such point. Background points need not be inside the image.

    How: per candidate, a min-depth image of the background is built only over the target
    pixels' bounding rectangle grown by half_window, from the background points nearer than
    the farthest in-view target point (no other can hide anything); a running min along
    rows (van Herk / Gil-Werman, three comparisons per pixel whatever the window, only over
    the occupied span of each row) is followed by a min over the 2*half_window+1 rows
    around each target pixel.

    Args:
        target_points: (N, 3) float64, finite.
        background_points: (K, 3) float64, finite.
        rotations: (C, 3, 3) float64 camera-to-observation rotations.
        positions: (C, 3) float64 camera centres.
        fx, skew, cx, fy, cy: intrinsics (K[0,0], K[0,1], K[0,2], K[1,1], K[1,2]).
        width, height: image size in pixels.
        half_window: neighbourhood half-width in pixels (>= 0).
        target_normals: (N, 3) float64 outward normals, or (0, 3) for none.

    Returns:
        (in_view (C,) int64, not_hidden (C,) int64) counts.
    """
    num_candidates = rotations.shape[0]
    num_targets = target_points.shape[0]
    num_background = background_points.shape[0]
    facing = target_normals.shape[0] == num_targets and num_targets > 0
    window = 2 * half_window + 1
    in_view = np.zeros(num_candidates, dtype=np.int64)
    not_hidden = np.zeros(num_candidates, dtype=np.int64)

    padded_width = width + 2 * half_window
    row_capacity = ((padded_width + window - 1) // window) * window
    depth = np.empty((height + 2 * half_window, row_capacity))
    row_min = np.empty((height + 2 * half_window, padded_width))
    prefix_min = np.empty(row_capacity)
    suffix_min = np.empty(row_capacity)
    target_col = np.empty(num_targets, dtype=np.int64)
    target_row = np.empty(num_targets, dtype=np.int64)
    target_depth = np.empty(num_targets)

    # Per region row: first/last occupied column of the min-depth image, and the columns
    # where row_min holds a value (outside them the row min is +inf).
    first_occupied = np.empty(height + 2 * half_window, dtype=np.int64)
    last_occupied = np.empty(height + 2 * half_window, dtype=np.int64)
    valid_lo = np.empty(height + 2 * half_window, dtype=np.int64)
    valid_hi = np.empty(height + 2 * half_window, dtype=np.int64)

    for c in range(num_candidates):
        r00, r01, r02 = rotations[c, 0, 0], rotations[c, 0, 1], rotations[c, 0, 2]
        r10, r11, r12 = rotations[c, 1, 0], rotations[c, 1, 1], rotations[c, 1, 2]
        r20, r21, r22 = rotations[c, 2, 0], rotations[c, 2, 1], rotations[c, 2, 2]
        tx, ty, tz = positions[c, 0], positions[c, 1], positions[c, 2]

        # Project the target; keep pixels of the points in view and their bounding rectangle.
        count = 0
        col_min, col_max, row_min_t, row_max_t = width, -1, height, -1
        farthest_target = 0.0
        for n in range(num_targets):
            dx = target_points[n, 0] - tx
            dy = target_points[n, 1] - ty
            dz = target_points[n, 2] - tz
            if facing and not (target_normals[n, 0] * dx + target_normals[n, 1] * dy
                               + target_normals[n, 2] * dz) < 0.0:
                continue  # the far side of the surface
            z = r02 * dx + r12 * dy + r22 * dz
            if not z > 0.0:
                continue
            xn = (r00 * dx + r10 * dy + r20 * dz) / z
            yn = (r01 * dx + r11 * dy + r21 * dz) / z
            u = fx * xn + skew * yn + cx
            v = fy * yn + cy
            if not (u >= 0.0 and u < width and v >= 0.0 and v < height):
                continue
            col = int(math.floor(u))
            row = int(math.floor(v))
            target_col[count] = col
            target_row[count] = row
            target_depth[count] = z
            count += 1
            col_min = min(col_min, col)
            col_max = max(col_max, col)
            row_min_t = min(row_min_t, row)
            row_max_t = max(row_max_t, row)
            farthest_target = max(farthest_target, z)
        in_view[c] = count
        if count == 0:
            continue
        if num_background == 0:  # nothing can hide anything (S_v's projection-only call)
            not_hidden[c] = count
            continue

        # Region of the min-depth image that can influence a target pixel.
        col_lo = col_min - half_window
        row_lo = row_min_t - half_window
        region_width = col_max - col_min + 1 + 2 * half_window
        region_height = row_max_t - row_min_t + 1 + 2 * half_window
        region_row_len = ((region_width + window - 1) // window) * window
        col_hi_excl = float(col_lo + region_width)
        row_hi_excl = float(row_lo + region_height)
        for rr in range(region_height):
            first_occupied[rr] = region_width
            last_occupied[rr] = -1
            for cc in range(region_row_len):
                depth[rr, cc] = np.inf

        # Min-depth image of the background over the region. A background point at least as
        # deep as the farthest in-view target point can hide nothing: skip it early.
        for k in range(num_background):
            dx = background_points[k, 0] - tx
            dy = background_points[k, 1] - ty
            dz = background_points[k, 2] - tz
            z = r02 * dx + r12 * dy + r22 * dz
            if not (z > 0.0 and z < farthest_target):
                continue
            xn = (r00 * dx + r10 * dy + r20 * dz) / z
            yn = (r01 * dx + r11 * dy + r21 * dz) / z
            u = fx * xn + skew * yn + cx
            v = fy * yn + cy
            # Compare as floats first: far-off points must not overflow the int cast.
            if not (u >= col_lo and u < col_hi_excl and v >= row_lo and v < row_hi_excl):
                continue
            cc = int(math.floor(u)) - col_lo
            rr = int(math.floor(v)) - row_lo
            if z < depth[rr, cc]:
                depth[rr, cc] = z
            first_occupied[rr] = min(first_occupied[rr], cc)
            last_occupied[rr] = max(last_occupied[rr], cc)

        _row_window_minima(depth, region_height, region_width, window, half_window, first_occupied, last_occupied,
                           prefix_min, suffix_min, row_min, valid_lo, valid_hi)

        # Min over the window's rows at each target pixel, then the depth test.
        visible = 0
        for n in range(count):
            cc = target_col[n] - col_lo
            rr0 = target_row[n] - row_lo - half_window
            nearest = np.inf
            for rr in range(rr0, rr0 + window):
                if valid_lo[rr] <= cc and cc <= valid_hi[rr] and row_min[rr, cc] < nearest:
                    nearest = row_min[rr, cc]
            if target_depth[n] <= nearest:
                visible += 1
        not_hidden[c] = visible
    return in_view, not_hidden


@njit(cache=True)
def segments_clear(
    occupied: np.ndarray,
    lower_index: np.ndarray,
    resolution: float,
    origins: np.ndarray,
    targets: np.ndarray,
    target_margin: float,
) -> np.ndarray:
    """(C, M) bool: segment origins[c] -> targets[m] (shortened by target_margin) is free.

    Amanatides-Woo traversal in grid coordinates g = x / r - lower_index: the walk starts in
    the cell holding the origin and steps, one cell at a time, across whichever cell
    boundary the segment meets first, until it passes the shortened end. Cells outside the
    grid are free.
    """
    num_origins = origins.shape[0]
    num_targets = targets.shape[0]
    size_x, size_y, size_z = occupied.shape[0], occupied.shape[1], occupied.shape[2]
    clear = np.ones((num_origins, num_targets), dtype=np.bool_)
    start = np.empty(3)
    delta = np.empty(3)
    cell = np.empty(3, dtype=np.int64)
    step = np.empty(3, dtype=np.int64)
    t_max = np.empty(3)
    t_delta = np.empty(3)
    for c in range(num_origins):
        for m in range(num_targets):
            length = 0.0
            for a in range(3):
                delta[a] = targets[m, a] - origins[c, a]
                length += delta[a] * delta[a]
            length = np.sqrt(length)
            if length <= target_margin:
                continue  # nothing left to check
            t_end = 1.0 - target_margin / length
            for a in range(3):
                start[a] = origins[c, a] / resolution - lower_index[a]
                delta[a] = delta[a] / resolution
                cell[a] = np.int64(np.floor(start[a]))
                if delta[a] > 0.0:
                    step[a] = 1
                    t_delta[a] = 1.0 / delta[a]
                    t_max[a] = (cell[a] + 1.0 - start[a]) / delta[a]
                elif delta[a] < 0.0:
                    step[a] = -1
                    t_delta[a] = -1.0 / delta[a]
                    t_max[a] = (start[a] - cell[a]) / -delta[a]
                else:
                    step[a] = 0
                    t_delta[a] = np.inf
                    t_max[a] = np.inf
            t = 0.0
            while t <= t_end:
                if (0 <= cell[0] < size_x and 0 <= cell[1] < size_y and 0 <= cell[2] < size_z
                        and occupied[cell[0], cell[1], cell[2]]):
                    clear[c, m] = False
                    break
                axis = 0
                if t_max[1] < t_max[axis]:
                    axis = 1
                if t_max[2] < t_max[axis]:
                    axis = 2
                t = t_max[axis]
                cell[axis] += step[axis]
                t_max[axis] += t_delta[axis]
    return clear


def count_framed(points: np.ndarray, rotations: np.ndarray, positions: np.ndarray, fx: float, skew: float, cx: float,
                 fy: float, cy: float, width: int, height: int, near: float, far: float) -> np.ndarray:
    """(C,) int64 per candidate: the points with z > 0, near <= z <= far, 0 <= u < width, 0 <= v < height.

    Every point projected (vectorised numpy, the arithmetic of ``count_visible_targets`` term by term): what
    :func:`leapnbv_planner.occlusion_kernel.count_framed_bucketed` counts over boxes of points.
    """
    counts = np.zeros(len(rotations), dtype=np.int64)
    for c, (rotation, position) in enumerate(zip(rotations, positions)):
        dx, dy, dz = (points[:, a] - position[a] for a in range(3))
        z = rotation[0, 2] * dx + rotation[1, 2] * dy + rotation[2, 2] * dz
        ok = (z > 0.0) & (z >= near) & (z <= far)
        safe = np.where(ok, z, 1.0)
        xn = (rotation[0, 0] * dx + rotation[1, 0] * dy + rotation[2, 0] * dz) / safe
        yn = (rotation[0, 1] * dx + rotation[1, 1] * dy + rotation[2, 1] * dz) / safe
        u = fx * xn + skew * yn + cx
        v = fy * yn + cy
        counts[c] = np.count_nonzero(ok & (u >= 0.0) & (u < width) & (v >= 0.0) & (v < height))
    return counts
