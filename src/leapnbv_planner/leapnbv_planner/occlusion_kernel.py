"""Compiled per-candidate count of target points in view and not hidden by the background."""

from __future__ import annotations

import math
from typing import List, Tuple

import numpy as np

from leapnbv_planner.arrays import Array
from leapnbv_planner.jit import njit


@njit(cache=True)
def _row_window_minima(depth: Array, region_height: int, region_width: int, window: int, half_window: int,
                       first_occupied: Array, last_occupied: Array, prefix_min: Array,
                       suffix_min: Array, row_min: Array, valid_lo: Array,
                       valid_hi: Array) -> None:
    """Running min along each row over ``window`` columns (van Herk / Gil-Werman):
    row_min[rr, a + half_window] = min(depth[rr, a : a + window]), computed only for the window starts a
    that reach an occupied column (valid_lo..valid_hi per row; outside them the row min is +inf)."""
    for rr in range(region_height):
        if last_occupied[rr] < 0:
            valid_lo[rr] = 1
            valid_hi[rr] = 0
            continue
        start_lo = max(0, first_occupied[rr] - 2 * half_window)
        start_hi = min(last_occupied[rr], region_width - window)
        block_lo = (start_lo // window) * window
        block_hi = ((start_hi + 2 * half_window) // window + 1) * window
        for block in range(block_lo, block_hi, window):
            prefix_min[block] = depth[rr, block]
            for cc in range(block + 1, block + window):
                prefix_min[cc] = min(prefix_min[cc - 1], depth[rr, cc])
            last = block + window - 1
            suffix_min[last] = depth[rr, last]
            for cc in range(last - 1, block - 1, -1):
                suffix_min[cc] = min(suffix_min[cc + 1], depth[rr, cc])
        for a in range(start_lo, start_hi + 1):
            row_min[rr, a + half_window] = min(suffix_min[a], prefix_min[a + window - 1])
        valid_lo[rr] = start_lo + half_window
        valid_hi[rr] = start_hi + half_window


@njit(cache=True)
def axis_aligned_bounds(points: Array) -> Tuple[Array, Array]:
    """Per-axis min and max of a non-empty (N, 3) array in one pass.

    numpy's min(axis=0) on an (N, 3) array walks it with a stride and costs about 1 ms for
    20k points; one loop costs a few microseconds.

    Args:
        points: (N, 3) float64, N >= 1.

    Returns:
        (lower (3,), upper (3,)).
    """
    lower = points[0].copy()
    upper = points[0].copy()
    for n in range(1, points.shape[0]):
        for axis in range(3):
            value = points[n, axis]
            if value < lower[axis]:
                lower[axis] = value
            if value > upper[axis]:
                upper[axis] = value
    return lower, upper


@njit(cache=True)
def points_in_box(points: Array, lower: Array, upper: Array) -> Array:
    """The rows of (N, 3) ``points`` inside the closed box [lower, upper], in their order (a copy)."""
    out = np.empty_like(points)
    kept = 0
    for n in range(points.shape[0]):
        if lower[0] <= points[n, 0] <= upper[0] and lower[1] <= points[n, 1] <= upper[1] \
                and lower[2] <= points[n, 2] <= upper[2]:
            for a in range(3):
                out[kept, a] = points[n, a]
            kept += 1
    return out[:kept]


def possible_occluders(background: Array, positions: Array, targets: List[Array], fx: float, skew: float,
                       fy: float, half_window: int) -> Array:
    """The background points that can hide some target point from some candidate camera; the others are left out
    (in order), so that the counts of count_visible_targets are the same without them.

    A background point b hides target t from camera c only when b's pixel is within the window of t's
    (|floor(u_b) - floor(u_t)| <= half_window, the same for v) and 0 < z_b < z_t. Then |u_b - u_t| and
    |v_b - v_t| are below h = half_window + 1 pixels, so b's normalized image coordinates differ from t's by at
    most h / fy in y and h / fx + |skew| h / (fx fy) in x, and b lies within z_b (h / fx + |skew| h / (fx fy) +
    h / fy) of the point of the segment c-t at its own depth z_b < z_t <= |t - c|. Every camera and target is in
    their bounding box, so is the segment, and |t - c| is at most the box's diagonal D: b is in the box grown by
    D (h / fx + |skew| h / (fx fy) + h / fy) on every side (and a little more for rounding).

    Args:
        background: (K, 3) float64 points.
        positions: (C, 3) candidate camera centres.
        targets: (N_i, 3) float64 arrays of every point whose visibility is counted (target points, mesh vertices).
        fx, skew, fy: the intrinsics the candidates project with (fx, fy > 0).
        half_window: the window's half-width in pixels (>= 0).

    Returns:
        (K', 3) float64, the points that may hide something (all of them when there is nothing to bound).
    """
    clouds = [np.asarray(positions, dtype=np.float64).reshape(-1, 3)] + \
        [np.ascontiguousarray(cloud, dtype=np.float64) for cloud in targets if len(cloud)]
    if len(clouds) < 2 or len(clouds[0]) == 0 or len(background) == 0:
        return background
    bounds = [axis_aligned_bounds(cloud) for cloud in clouds]
    lower = np.min([low for low, _ in bounds], axis=0)
    upper = np.max([high for _, high in bounds], axis=0)
    diagonal = float(np.sqrt(np.sum(np.square(upper - lower))))
    reach = half_window + 1.0
    margin = diagonal * reach * (1.0 / fx + abs(skew) / (fx * fy) + 1.0 / fy)
    slack = 1e-6 * (1.0 + diagonal + float(np.max(np.abs(np.concatenate([lower, upper])))))
    return points_in_box(np.ascontiguousarray(background, dtype=np.float64), lower - margin - slack,
                         upper + margin + slack)


# ---------------------------------------------------------------------------------------------
# The same counts over points bucketed into boxes: whole boxes that cannot matter to a candidate
# are skipped, whole boxes that are surely in view are counted without projecting their points.
# The points that are projected go through exactly the per-point arithmetic of
# count_visible_targets, and every count is order-free (a count, a min), so the results are the
# same; the box tests only decide which points need that arithmetic, with margins far larger than
# the rounding of either side (see _PIXEL_MARGIN, _NEAR_Z, _Z_MARGIN).

#: Boxes are tested against the candidate's pixel rectangle grown (or, for "surely inside", shrunk) by this
#: many pixels; the per-point rounding of u and v is many orders of magnitude smaller.
_PIXEL_MARGIN = 1.0
#: The pixel-rectangle side tests are used only on boxes at least this far (m) in front of the camera plane, where
#: the division by z is well conditioned; boxes nearer the camera plane are tested point by point.
_NEAR_Z = 1e-3
#: A box is behind the camera (or beyond the farthest target) only when it is this far (m) past the plane.
_Z_MARGIN = 1e-9
#: Points per grid cell the bucketing aims at, and the most points in a run (the finer boxes inside a cell).
POINTS_PER_BOX = 64
RUN_LENGTH = 16


@njit(cache=True)
def _box_from_bounds(low: Array, high: Array, out: Array) -> None:
    """out (6,) = centre and half extents of [low, high], the half extents grown by far more than the rounding of
    the centre, so that the box surely holds everything in [low, high]."""
    for a in range(3):
        centre = 0.5 * (low[a] + high[a])
        out[a] = centre
        out[3 + a] = 0.5 * (high[a] - low[a]) * (1.0 + 1e-12) + 1e-12 * (abs(centre) + 1.0)


@njit(cache=True)
def bucket_points(points: Array, companions: Array, points_per_box: int, run_length: int
                  ) -> Tuple[Array, Array, Array, Array, Array, Array]:
    """Sort (N, 3) points into the cells of a regular grid over their bounds (a stable counting sort), and each
    cell's points into runs of at most run_length consecutive points (in the input's order within the cell: a depth
    image's raster order keeps a run compact).

    Args:
        points: (N, 3) float64, finite.
        companions: (N, 3) float64 rows that travel with the points (normals), or (0, 3).
        points_per_box: the grid has about N / points_per_box cells (at least 1, at most 64 per axis).
        run_length: the most points in one run (>= 1).

    Returns:
        (sorted points (N, 3), sorted companions (N or 0, 3), cell_runs (B + 1,) int64: the runs of non-empty cell
        b are cell_runs[b] to cell_runs[b + 1], cell_boxes (B, 6), run_starts (S + 1,) int64: run r holds the
        sorted points run_starts[r] to run_starts[r + 1], run_boxes (S, 6)); a box is (centre, half extents)
        of a bounding box of its points.
    """
    num = points.shape[0]
    run_length = max(1, run_length)
    with_companions = companions.shape[0] == num and num > 0
    low = np.empty(3)
    high = np.empty(3)
    for a in range(3):
        low[a] = np.inf
        high[a] = -np.inf
    for n in range(num):
        for a in range(3):
            value = points[n, a]
            if value < low[a]:
                low[a] = value
            if value > high[a]:
                high[a] = value
    cells_per_axis = 1
    if num > 0:
        cells_per_axis = int(max(1.0, min(64.0, np.floor((num / max(1, points_per_box)) ** (1.0 / 3.0) + 0.5))))
    scale = np.empty(3)
    for a in range(3):
        extent = high[a] - low[a] if num > 0 else 0.0
        scale[a] = cells_per_axis / extent if extent > 0.0 else 0.0
    total = cells_per_axis * cells_per_axis * cells_per_axis
    cell_of = np.empty(num, dtype=np.int64)
    counts = np.zeros(total + 1, dtype=np.int64)
    for n in range(num):
        key = 0
        for a in range(3):
            index = int((points[n, a] - low[a]) * scale[a])
            if index >= cells_per_axis:
                index = cells_per_axis - 1
            if index < 0:
                index = 0
            key = key * cells_per_axis + index
        cell_of[n] = key
        counts[key + 1] += 1
    num_cells = 0
    num_runs = 0
    for key in range(total):
        size = counts[key + 1]
        if size > 0:
            num_cells += 1
            num_runs += (size + run_length - 1) // run_length
        counts[key + 1] += counts[key]
    fill = counts[:total].copy()
    sorted_points = np.empty((num, 3))
    sorted_companions = np.empty((num if with_companions else 0, 3))
    for n in range(num):
        slot = fill[cell_of[n]]
        fill[cell_of[n]] += 1
        for a in range(3):
            sorted_points[slot, a] = points[n, a]
            if with_companions:
                sorted_companions[slot, a] = companions[n, a]
    cell_runs = np.empty(num_cells + 1, dtype=np.int64)
    cell_boxes = np.empty((num_cells, 6))
    run_starts = np.empty(num_runs + 1, dtype=np.int64)
    run_boxes = np.empty((num_runs, 6))
    cell = 0
    run = 0
    run_low = np.empty(3)
    run_high = np.empty(3)
    cell_low = np.empty(3)
    cell_high = np.empty(3)
    for key in range(total):
        begin, end = counts[key], counts[key + 1]
        if end == begin:
            continue
        cell_runs[cell] = run
        for a in range(3):
            cell_low[a] = np.inf
            cell_high[a] = -np.inf
        for first in range(begin, end, run_length):
            run_starts[run] = first
            for a in range(3):
                run_low[a] = sorted_points[first, a]
                run_high[a] = sorted_points[first, a]
            for n in range(first + 1, min(first + run_length, end)):
                for a in range(3):
                    value = sorted_points[n, a]
                    if value < run_low[a]:
                        run_low[a] = value
                    if value > run_high[a]:
                        run_high[a] = value
            _box_from_bounds(run_low, run_high, run_boxes[run])
            for a in range(3):
                cell_low[a] = min(cell_low[a], run_low[a])
                cell_high[a] = max(cell_high[a], run_high[a])
            run += 1
        _box_from_bounds(cell_low, cell_high, cell_boxes[cell])
        cell += 1
    cell_runs[num_cells] = num_runs
    run_starts[num_runs] = num
    return sorted_points, sorted_companions, cell_runs, cell_boxes, run_starts, run_boxes


@njit(cache=True)
def run_facing_bounds(points: Array, normals: Array, run_starts: Array) -> Array:
    """(S, 7) per run of bucketed points with normals: min of n . p over the run, then the lower and upper
    corners of its normals' bounding box (what tells that a whole run faces away from a camera)."""
    num_runs = run_starts.shape[0] - 1
    bounds = np.empty((num_runs, 7))
    for run in range(num_runs):
        lowest = np.inf
        for a in range(3):
            bounds[run, 1 + a] = np.inf
            bounds[run, 4 + a] = -np.inf
        for n in range(run_starts[run], run_starts[run + 1]):
            value = normals[n, 0] * points[n, 0] + normals[n, 1] * points[n, 1] + normals[n, 2] * points[n, 2]
            lowest = min(lowest, value)
            for a in range(3):
                bounds[run, 1 + a] = min(bounds[run, 1 + a], normals[n, a])
                bounds[run, 4 + a] = max(bounds[run, 4 + a], normals[n, a])
        bounds[run, 0] = lowest
    return bounds


@njit(cache=True)
def _run_faces_away(bounds: Array, run: int, tx: float, ty: float, tz: float) -> bool:
    """Every point of the run surely has n . (p - t) > 0 (the far side from camera centre t): n . p - n . t is at
    least min(n . p) - max over the normals' box of n . t, with a margin far above the rounding of either form."""
    most = (max(bounds[run, 1] * tx, bounds[run, 4] * tx) + max(bounds[run, 2] * ty, bounds[run, 5] * ty)
            + max(bounds[run, 3] * tz, bounds[run, 6] * tz))
    scale = abs(bounds[run, 0]) + abs(most) + 1.0
    return bounds[run, 0] - most > 1e-9 * scale  # type: ignore[no-any-return]  # numpy scalar compare


@njit(cache=True)
def _form_range(forms: Array, k: int, box: Array) -> Tuple[float, float]:
    """(min, max) over a box (centre, half extents) of the linear form forms[k, :3] . p + forms[k, 3]."""
    value = forms[k, 0] * box[0] + forms[k, 1] * box[1] + forms[k, 2] * box[2] + forms[k, 3]
    extent = abs(forms[k, 0]) * box[3] + abs(forms[k, 1]) * box[4] + abs(forms[k, 2]) * box[5]
    return value - extent, value + extent


@njit(cache=True)
def _frustum_forms(forms: Array, rotation: Array, position: Array, fx: float, skew: float, cx: float,
                   fy: float, cy: float, u_lo: float, u_hi: float, v_lo: float, v_hi: float, z_far: float) -> None:
    """Fill forms (6, 4) with observation-frame linear forms f(p) = a . p + b of a candidate camera:
    0: z, 1: z_far - z, 2: fx x + skew y - (u_lo - cx) z (>= 0: u >= u_lo), 3: (u_hi - cx) z - fx x - skew y
    (>= 0: u <= u_hi), 4: fy y - (v_lo - cy) z, 5: (v_hi - cy) z - fy y, with (x, y, z) = R^T (p - t)."""
    coefficients = np.zeros((6, 3))
    coefficients[0, 2] = 1.0
    coefficients[1, 2] = -1.0
    coefficients[2, 0], coefficients[2, 1], coefficients[2, 2] = fx, skew, cx - u_lo
    coefficients[3, 0], coefficients[3, 1], coefficients[3, 2] = -fx, -skew, u_hi - cx
    coefficients[4, 1], coefficients[4, 2] = fy, cy - v_lo
    coefficients[5, 1], coefficients[5, 2] = -fy, v_hi - cy
    for k in range(6):
        for a in range(3):  # a = R (alpha, beta, gamma): camera x, y, z are R^T (p - t)
            forms[k, a] = (rotation[a, 0] * coefficients[k, 0] + rotation[a, 1] * coefficients[k, 1]
                           + rotation[a, 2] * coefficients[k, 2])
        forms[k, 3] = -(forms[k, 0] * position[0] + forms[k, 1] * position[1] + forms[k, 2] * position[2])
    forms[1, 3] += z_far


@njit(cache=True)
def _box_outside(forms: Array, box: Array, far_test: bool) -> bool:
    """The box surely holds no point that the per-point test keeps (behind the camera, beyond z_far, or off the
    pixel rectangle; the forms carry the pixel margin)."""
    z_min, z_max = _form_range(forms, 0, box)
    if z_max < -_Z_MARGIN:
        return True
    if far_test:
        _, far_max = _form_range(forms, 1, box)
        if far_max < -_Z_MARGIN:
            return True
    if z_min < _NEAR_Z:
        return False
    for k in range(2, 6):
        _, side_max = _form_range(forms, k, box)
        if side_max < 0.0:
            return True
    return False


@njit(cache=True)
def _box_inside(forms: Array, box: Array) -> bool:
    """Every point of the box is surely in view (the forms carry the inner pixel margin)."""
    z_min, _ = _form_range(forms, 0, box)
    if not z_min >= _NEAR_Z:
        return False
    for k in range(2, 6):
        side_min, _ = _form_range(forms, k, box)
        if not side_min > 0.0:
            return False
    return True


@njit(cache=True)
def _live_runs(forms: Array, cell_runs: Array, cell_boxes: Array, run_boxes: Array,
               far_test: bool, out: Array) -> int:
    """Write to out the runs that _box_outside cannot rule out (their cell's box first, then their own); return
    how many."""
    count = 0
    for cell in range(cell_runs.shape[0] - 1):
        if _box_outside(forms, cell_boxes[cell], far_test):
            continue
        for run in range(cell_runs[cell], cell_runs[cell + 1]):
            if not _box_outside(forms, run_boxes[run], far_test):
                out[count] = run
                count += 1
    return count


@njit(cache=True)
def count_visible_targets_bucketed(
    target_points: Array,
    target_normals: Array,
    target_cell_runs: Array,
    target_cell_boxes: Array,
    target_run_starts: Array,
    target_run_boxes: Array,
    target_run_facing: Array,
    background_points: Array,
    background_cell_runs: Array,
    background_cell_boxes: Array,
    background_run_starts: Array,
    background_run_boxes: Array,
    rotations: Array,
    positions: Array,
    fx: float,
    skew: float,
    cx: float,
    fy: float,
    cy: float,
    width: int,
    height: int,
    half_window: int,
) -> Tuple[Array, Array]:
    """count_visible_targets (the per-point reference kernel, in the planner's tests:
    test/reference_planner_kernels.py) over bucketed clouds (from :func:`bucket_points`): the same counts, faster.

    Per candidate, a target cell or run wholly off the image is skipped, and, when nothing can hide anything (no
    background, no normals), a target run wholly in the image is counted without projecting its points. A
    background cell or run that lies wholly behind the camera, beyond the farthest in-view target point, or off
    the target pixels' rectangle grown by the window is skipped. Every other point goes through the per-point
    arithmetic of count_visible_targets (a point surely off the rectangle is left out before its division); counts
    and minima do not depend on the order of the points.

    Args:
        target_points, target_normals, target_cell_runs, target_cell_boxes, target_run_starts, target_run_boxes:
            the bucketed targets (normals (N, 3) or (0, 3), as in count_visible_targets).
        target_run_facing: with normals, run_facing_bounds of the targets' runs (a run that faces away from a
            candidate is skipped); (0, 7) otherwise.
        background_points, background_cell_runs, background_cell_boxes, background_run_starts,
            background_run_boxes: the bucketed background (may hold 0 points).
        rotations, positions, fx, skew, cx, fy, cy, width, height, half_window: as in count_visible_targets.

    Returns:
        (in_view (C,) int64, not_hidden (C,) int64) counts, equal to count_visible_targets's.
    """
    num_candidates = rotations.shape[0]
    num_targets = target_points.shape[0]
    num_background = background_points.shape[0]
    facing = target_normals.shape[0] == num_targets and num_targets > 0
    window = 2 * half_window + 1
    in_view = np.zeros(num_candidates, dtype=np.int64)
    not_hidden = np.zeros(num_candidates, dtype=np.int64)
    wholesale = num_background == 0 and not facing  # only the in-view count is needed

    live_runs = np.empty(max(target_run_starts.shape[0], background_run_starts.shape[0]), dtype=np.int64)
    padded_width = width + 2 * half_window
    row_capacity = ((padded_width + window - 1) // window) * window
    depth = np.empty((height + 2 * half_window, row_capacity))
    row_min = np.empty((height + 2 * half_window, padded_width))
    prefix_min = np.empty(row_capacity)
    suffix_min = np.empty(row_capacity)
    target_col = np.empty(num_targets, dtype=np.int64)
    target_row = np.empty(num_targets, dtype=np.int64)
    target_depth = np.empty(num_targets)
    first_occupied = np.empty(height + 2 * half_window, dtype=np.int64)
    last_occupied = np.empty(height + 2 * half_window, dtype=np.int64)
    valid_lo = np.empty(height + 2 * half_window, dtype=np.int64)
    valid_hi = np.empty(height + 2 * half_window, dtype=np.int64)
    near_block = np.empty(((height + 2 * half_window) // window + 1, (width + 2 * half_window) // window + 1),
                          dtype=np.bool_)
    holds_point = np.empty_like(near_block)
    near_targets = np.empty(num_targets, dtype=np.int64)
    outer_forms = np.empty((6, 4))
    inner_forms = np.empty((6, 4))
    region_forms = np.empty((6, 4))

    for c in range(num_candidates):
        rotation = rotations[c]
        position = positions[c]
        r00, r01, r02 = rotations[c, 0, 0], rotations[c, 0, 1], rotations[c, 0, 2]
        r10, r11, r12 = rotations[c, 1, 0], rotations[c, 1, 1], rotations[c, 1, 2]
        r20, r21, r22 = rotations[c, 2, 0], rotations[c, 2, 1], rotations[c, 2, 2]
        tx, ty, tz = positions[c, 0], positions[c, 1], positions[c, 2]
        _frustum_forms(outer_forms, rotation, position, fx, skew, cx, fy, cy, -_PIXEL_MARGIN,
                       width + _PIXEL_MARGIN, -_PIXEL_MARGIN, height + _PIXEL_MARGIN, 0.0)
        if wholesale:
            _frustum_forms(inner_forms, rotation, position, fx, skew, cx, fy, cy, _PIXEL_MARGIN,
                           width - _PIXEL_MARGIN, _PIXEL_MARGIN, height - _PIXEL_MARGIN, 0.0)

        count = 0
        col_min, col_max, row_min_t, row_max_t = width, -1, height, -1
        farthest_target = 0.0
        if wholesale:  # whole cells, then whole runs, surely in the image are counted without their points
            num_live = 0
            for cell in range(target_cell_runs.shape[0] - 1):
                if _box_outside(outer_forms, target_cell_boxes[cell], False):
                    continue
                first_run, end_run = target_cell_runs[cell], target_cell_runs[cell + 1]
                if _box_inside(inner_forms, target_cell_boxes[cell]):
                    count += target_run_starts[end_run] - target_run_starts[first_run]
                    continue
                for run in range(first_run, end_run):
                    if _box_outside(outer_forms, target_run_boxes[run], False):
                        continue
                    if _box_inside(inner_forms, target_run_boxes[run]):
                        count += target_run_starts[run + 1] - target_run_starts[run]
                        continue
                    live_runs[num_live] = run
                    num_live += 1
        else:
            num_live = _live_runs(outer_forms, target_cell_runs, target_cell_boxes, target_run_boxes, False,
                                  live_runs)
        run_bounds = facing and target_run_facing.shape[0] == target_run_starts.shape[0] - 1
        for live in range(num_live):
            run = live_runs[live]
            if run_bounds and _run_faces_away(target_run_facing, run, tx, ty, tz):
                continue
            for n in range(target_run_starts[run], target_run_starts[run + 1]):
                dx = target_points[n, 0] - tx
                dy = target_points[n, 1] - ty
                dz = target_points[n, 2] - tz
                if facing and not (target_normals[n, 0] * dx + target_normals[n, 1] * dy
                                   + target_normals[n, 2] * dz) < 0.0:
                    continue
                z = r02 * dx + r12 * dy + r22 * dz
                if not z > 0.0:
                    continue
                xn = (r00 * dx + r10 * dy + r20 * dz) / z
                yn = (r01 * dx + r11 * dy + r21 * dz) / z
                u = fx * xn + skew * yn + cx
                v = fy * yn + cy
                if not (u >= 0.0 and u < width and v >= 0.0 and v < height):
                    continue
                if wholesale:
                    count += 1
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
        if num_background == 0:
            not_hidden[c] = count
            continue

        col_lo = col_min - half_window
        row_lo = row_min_t - half_window
        region_width = col_max - col_min + 1 + 2 * half_window
        region_height = row_max_t - row_min_t + 1 + 2 * half_window
        region_row_len = ((region_width + window - 1) // window) * window
        col_hi_excl = float(col_lo + region_width)
        row_hi_excl = float(row_lo + region_height)
        for rr in range(region_height):  # a row's depths are set to +inf when its first point comes
            first_occupied[rr] = region_width
            last_occupied[rr] = -1
        any_occupied = False
        # Blocks of window x window pixels that hold a point (then grown by a block: 3 x 3 blocks hold any window
        # around a pixel of the middle one, so a target pixel in an unmarked block has nothing in its window).
        block_rows = (region_height + window - 1) // window
        block_cols = (region_width + window - 1) // window
        for br in range(block_rows):
            for bc in range(block_cols):
                holds_point[br, bc] = False
        u_off_lo, u_off_hi = col_lo - _PIXEL_MARGIN, col_hi_excl + _PIXEL_MARGIN
        v_off_lo, v_off_hi = row_lo - _PIXEL_MARGIN, row_hi_excl + _PIXEL_MARGIN
        _frustum_forms(region_forms, rotation, position, fx, skew, cx, fy, cy, col_lo - _PIXEL_MARGIN,
                       col_hi_excl + _PIXEL_MARGIN, row_lo - _PIXEL_MARGIN, row_hi_excl + _PIXEL_MARGIN,
                       farthest_target)

        num_live = _live_runs(region_forms, background_cell_runs, background_cell_boxes, background_run_boxes, True,
                              live_runs)
        for live in range(num_live):
            run = live_runs[live]
            for k in range(background_run_starts[run], background_run_starts[run + 1]):
                dx = background_points[k, 0] - tx
                dy = background_points[k, 1] - ty
                dz = background_points[k, 2] - tz
                z = r02 * dx + r12 * dy + r22 * dz
                if not (z > 0.0 and z < farthest_target):
                    continue
                x = r00 * dx + r10 * dy + r20 * dz
                y = r01 * dx + r11 * dy + r21 * dz
                if z >= _NEAR_Z:  # surely off the rectangle (by a pixel): no division needed
                    horizontal = fx * x + skew * y
                    if (horizontal < (u_off_lo - cx) * z or horizontal > (u_off_hi - cx) * z
                            or fy * y < (v_off_lo - cy) * z or fy * y > (v_off_hi - cy) * z):
                        continue
                xn = x / z
                yn = y / z
                u = fx * xn + skew * yn + cx
                v = fy * yn + cy
                if not (u >= col_lo and u < col_hi_excl and v >= row_lo and v < row_hi_excl):
                    continue
                cc = int(math.floor(u)) - col_lo
                rr = int(math.floor(v)) - row_lo
                if last_occupied[rr] < 0:
                    for cell in range(region_row_len):
                        depth[rr, cell] = np.inf
                    any_occupied = True
                if z < depth[rr, cc]:
                    depth[rr, cc] = z
                first_occupied[rr] = min(first_occupied[rr], cc)
                last_occupied[rr] = max(last_occupied[rr], cc)
                holds_point[rr // window, cc // window] = True
        if not any_occupied:  # nothing in front of the target pixels: every in-view point is seen
            not_hidden[c] = count
            continue

        for br in range(block_rows):
            for bc in range(block_cols):
                near_block[br, bc] = False
        for br in range(block_rows):
            for bc in range(block_cols):
                if holds_point[br, bc]:
                    for neighbour_row in range(max(0, br - 1), min(block_rows, br + 2)):
                        for neighbour_col in range(max(0, bc - 1), min(block_cols, bc + 2)):
                            near_block[neighbour_row, neighbour_col] = True
        # The targets whose window may hold a point; the others are seen.
        visible = 0
        num_near = 0
        for n in range(count):
            if near_block[(target_row[n] - row_lo) // window, (target_col[n] - col_lo) // window]:
                near_targets[num_near] = n
                num_near += 1
            else:
                visible += 1
        # Their window minima: read straight from the min-depth image (window x window reads each), or, when that
        # costs more, from running row minima (van Herk / Gil-Werman over the occupied span of each row, then
        # window reads each); both give the exact minimum.
        row_work = 0
        for rr in range(region_height):
            if last_occupied[rr] >= 0:
                row_work += 3 * (last_occupied[rr] - first_occupied[rr] + 3 * window)
        direct = num_near * window * window <= row_work + num_near * window
        if not direct:
            _row_window_minima(depth, region_height, region_width, window, half_window, first_occupied,
                               last_occupied, prefix_min, suffix_min, row_min, valid_lo, valid_hi)
        for near in range(num_near):
            n = near_targets[near]
            cc = target_col[n] - col_lo
            rr0 = target_row[n] - row_lo - half_window
            nearest = np.inf
            if direct:
                for rr in range(rr0, rr0 + window):
                    if last_occupied[rr] < 0 or cc + half_window < first_occupied[rr] \
                            or cc - half_window > last_occupied[rr]:
                        continue
                    for column in range(cc - half_window, cc + half_window + 1):
                        if depth[rr, column] < nearest:
                            nearest = depth[rr, column]
            else:
                for rr in range(rr0, rr0 + window):
                    if valid_lo[rr] <= cc and cc <= valid_hi[rr] and row_min[rr, cc] < nearest:
                        nearest = row_min[rr, cc]
            if target_depth[n] <= nearest:
                visible += 1
        not_hidden[c] = visible
    return in_view, not_hidden


@njit(cache=True)
def count_framed_bucketed(
    points: Array,
    cell_runs: Array,
    cell_boxes: Array,
    run_starts: Array,
    run_boxes: Array,
    rotations: Array,
    positions: Array,
    fx: float,
    skew: float,
    cx: float,
    fy: float,
    cy: float,
    width: int,
    height: int,
    near: float,
    far: float,
) -> Array:
    """(C,) int64 per candidate: the bucketed points (from :func:`bucket_points`) inside its image and depth range.

    A point is framed when, with (x, y, z) = R^T (p - t), z > 0 and near <= z <= far, and u = fx x/z + skew y/z +
    cx, v = fy y/z + cy satisfy 0 <= u < width, 0 <= v < height: the in-view test of count_visible_targets (the
    same arithmetic, point by point) with the depth range added. A cell or run wholly off the image or out of the
    range is skipped, one wholly a pixel inside the image and well inside the range is counted without projecting
    its points; every other point is tested. The count does not depend on the order of the points.
    """
    num_candidates = rotations.shape[0]
    framed = np.zeros(num_candidates, dtype=np.int64)
    outer_forms = np.empty((6, 4))
    inner_forms = np.empty((6, 4))
    live_runs = np.empty(run_starts.shape[0], dtype=np.int64)
    for c in range(num_candidates):
        rotation = rotations[c]
        position = positions[c]
        r00, r01, r02 = rotations[c, 0, 0], rotations[c, 0, 1], rotations[c, 0, 2]
        r10, r11, r12 = rotations[c, 1, 0], rotations[c, 1, 1], rotations[c, 1, 2]
        r20, r21, r22 = rotations[c, 2, 0], rotations[c, 2, 1], rotations[c, 2, 2]
        tx, ty, tz = positions[c, 0], positions[c, 1], positions[c, 2]
        _frustum_forms(outer_forms, rotation, position, fx, skew, cx, fy, cy, -_PIXEL_MARGIN,
                       width + _PIXEL_MARGIN, -_PIXEL_MARGIN, height + _PIXEL_MARGIN, far)
        _frustum_forms(inner_forms, rotation, position, fx, skew, cx, fy, cy, _PIXEL_MARGIN,
                       width - _PIXEL_MARGIN, _PIXEL_MARGIN, height - _PIXEL_MARGIN, far)
        count = 0
        num_live = 0
        for cell in range(cell_runs.shape[0] - 1):
            box = cell_boxes[cell]
            _, nearest_max = _form_range(outer_forms, 0, box)
            if nearest_max < near - _Z_MARGIN or _box_outside(outer_forms, box, True):
                continue
            first_run, end_run = cell_runs[cell], cell_runs[cell + 1]
            if _box_framed(inner_forms, box, near):
                count += run_starts[end_run] - run_starts[first_run]
                continue
            for run in range(first_run, end_run):
                box = run_boxes[run]
                _, nearest_max = _form_range(outer_forms, 0, box)
                if nearest_max < near - _Z_MARGIN or _box_outside(outer_forms, box, True):
                    continue
                if _box_framed(inner_forms, box, near):
                    count += run_starts[run + 1] - run_starts[run]
                    continue
                live_runs[num_live] = run
                num_live += 1
        for live in range(num_live):
            run = live_runs[live]
            for n in range(run_starts[run], run_starts[run + 1]):
                dx = points[n, 0] - tx
                dy = points[n, 1] - ty
                dz = points[n, 2] - tz
                z = r02 * dx + r12 * dy + r22 * dz
                if not (z > 0.0 and z >= near and z <= far):
                    continue
                xn = (r00 * dx + r10 * dy + r20 * dz) / z
                yn = (r01 * dx + r11 * dy + r21 * dz) / z
                u = fx * xn + skew * yn + cx
                v = fy * yn + cy
                if u >= 0.0 and u < width and v >= 0.0 and v < height:
                    count += 1
        framed[c] = count
    return framed


@njit(cache=True)
def _box_framed(forms: Array, box: Array, near: float) -> bool:
    """Every point of the box is surely framed: a pixel inside the image (the forms carry the inner margin) and
    within [near, far] by far more than the rounding of z (forms 0 and 1: z and far - z)."""
    nearest, _ = _form_range(forms, 0, box)
    if not nearest > near + _Z_MARGIN:
        return False
    farthest_margin, _ = _form_range(forms, 1, box)
    if not farthest_margin > _Z_MARGIN:
        return False
    return _box_inside(forms, box)
