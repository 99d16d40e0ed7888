"""The robot's map of static obstacles as a voxel grid, and line-of-sight tests through it.

The start view sees only what lies in its field of view: furniture beside or behind the
person, outside that view, cannot lower S_o, and the planner then sends the robot behind a
shelf. A robot that maps its surroundings knows that furniture. This module takes such a map
as the centres of its occupied voxels (what an OctoMap server publishes as
``octomap_point_cloud_centers``), in a fixed frame ``map`` in which the camera pose of the
observation is known, and answers two questions:

- which target points a candidate camera sees through free map space (a 3D DDA walk,
  Amanatides & Woo 1987, along each camera-to-point segment): ``line_of_sight_clear_fraction``;
- where the map's obstacles lie in the observation frame (for the footprint test of the
  candidate feasibility): ``centres_in_observation``.

Voxel convention (OctoMap's): voxel (i, j, k) spans [i r, (i+1) r) x [j r, (j+1) r) x
[k r, (k+1) r) in the map frame, r the resolution, and its centre is ((i, j, k) + 0.5) r.
Space outside the map's voxels counts as free (unknown space is not an obstacle here).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Optional, Protocol, Tuple

import numpy as np

from leapnbv_planner.arrays import Array
from leapnbv_planner.jit import njit

#: Largest dense grid built from a map (cells); 20 m x 20 m x 3 m at 5 cm is 9.6 M.
MAX_GRID_CELLS = 64_000_000


class ObstacleMapError(ValueError):
    """The obstacle map or the camera pose cannot be used; the text says which value is at fault."""


class ObstacleMap(Protocol):
    """What the planner reads of an obstacle map (:class:`VoxelObstacleMap` is one): see there for each."""

    @property
    def occupied(self) -> Array:
        """(X, Y, Z) bool occupancy of the map's box of cells."""

    @property
    def lower_index(self) -> Array:
        """(3,) int64 voxel index of cell (0, 0, 0)."""

    @property
    def resolution(self) -> float:
        """Voxel edge (m)."""

    @property
    def centres(self) -> Array:
        """(N, 3) centres of the occupied voxels, map frame."""

    def occupied_prefix_sums(self) -> Array:
        """(X + 1, Y + 1, Z + 1) counts of occupied cells below each corner."""


@dataclass
class VoxelObstacleMap:
    """A dense occupancy grid over the bounding box of a map's occupied voxels.

    Attributes:
        occupied: (X, Y, Z) bool; cell (a, b, c) is the map voxel lower_index + (a, b, c).
        lower_index: (3,) int64 voxel index of cell (0, 0, 0).
        resolution: voxel edge r (m).
        centres: (N, 3) float64 centres of the occupied voxels, map frame.
    """

    occupied: Array
    lower_index: Array
    resolution: float
    centres: Array
    _prefix: Optional[Array] = field(default=None, repr=False, compare=False)

    @property
    def voxel_count(self) -> int:
        return int(self.centres.shape[0])

    def occupied_prefix_sums(self) -> Array:
        """(X + 1, Y + 1, Z + 1) int32 counts of occupied cells in [0, a) x [0, b) x [0, c), computed once per map
        (a box of cells is counted with eight look-ups)."""
        if self._prefix is None or self._prefix.shape != tuple(s + 1 for s in self.occupied.shape):
            prefix = np.zeros(tuple(s + 1 for s in self.occupied.shape), dtype=np.int32)
            prefix[1:, 1:, 1:] = self.occupied.astype(np.int32).cumsum(0).cumsum(1).cumsum(2)
            self._prefix = prefix
        return self._prefix


def voxel_map_from_centres(centres: Array, resolution: float) -> VoxelObstacleMap:
    """Build the dense grid from occupied voxel centres.

    Args:
        centres: (N, 3) voxel centres in the map frame (N may be 0); non-finite rows are
            dropped. A point that is not exactly a centre marks the voxel it falls in.
        resolution: voxel edge r (m), as the map was built with.

    Returns:
        The VoxelObstacleMap.

    Raises:
        ObstacleMapError: resolution <= 0 or not finite, centres not (N, 3), or a grid larger
            than MAX_GRID_CELLS (a map far larger than the room, or a wrong resolution).
    """
    if not (np.isfinite(resolution) and resolution > 0.0):
        raise ObstacleMapError(f"obstacle map resolution must be a finite number > 0, got {resolution}")
    points = np.asarray(centres, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ObstacleMapError(f"obstacle map centres must have shape (N, 3), got {points.shape}")
    points = points[np.all(np.isfinite(points), axis=1)]
    if points.shape[0] == 0:
        return VoxelObstacleMap(np.zeros((1, 1, 1), dtype=bool), np.zeros(3, dtype=np.int64),
                                float(resolution), np.zeros((0, 3)))
    index = np.floor(points / resolution).astype(np.int64)
    lower = index.min(axis=0)
    shape = index.max(axis=0) - lower + 1
    cells = int(np.prod(shape))
    if cells > MAX_GRID_CELLS:
        raise ObstacleMapError(
            f"obstacle map spans {shape.tolist()} voxels of {resolution} m ({cells} cells, more than"
            f" {MAX_GRID_CELLS}): wrong resolution, or points far outside the mapped area")
    occupied = np.zeros(tuple(int(s) for s in shape), dtype=bool)
    local = index - lower
    occupied[local[:, 0], local[:, 1], local[:, 2]] = True
    unique_index = np.argwhere(occupied) + lower
    return VoxelObstacleMap(occupied, lower, float(resolution), (unique_index + 0.5) * resolution)


def _check_pose(rotation: Array, position: Array) -> Tuple[Array, Array]:
    rotation = np.asarray(rotation, dtype=np.float64)
    position = np.asarray(position, dtype=np.float64).reshape(-1)
    if rotation.shape != (3, 3) or position.shape != (3,):
        raise ObstacleMapError(f"camera pose must be a (3, 3) rotation and a (3,) position, got"
                               f" {rotation.shape} and {position.shape}")
    if not (np.all(np.isfinite(rotation)) and np.all(np.isfinite(position))):
        raise ObstacleMapError("camera pose is not finite")
    if not np.allclose(rotation.T @ rotation, np.eye(3), atol=1e-3) or np.linalg.det(rotation) < 0.0:
        raise ObstacleMapError("camera pose rotation is not a rotation matrix")
    return rotation, position


def centres_in_observation(obstacle_map: ObstacleMap, rotation: Array,
                           position: Array) -> Array:
    """The occupied voxel centres in the observation's camera frame.

    Args:
        obstacle_map: the map.
        rotation, position: T_map_observation, the observation camera's pose in the map
            (rotation columns = its optical axes in the map, position = its optical centre).

    Returns:
        (N, 3) R^T (c - t) for every centre c.
    """
    rotation, position = _check_pose(rotation, position)
    centres: Array = (obstacle_map.centres - position[None, :]) @ rotation
    return centres


def line_of_sight_clear_fraction(
    obstacle_map: ObstacleMap,
    rotation: Array,
    position: Array,
    camera_positions: Array,
    target_points: Array,
    max_targets: int = 1500,
    target_margin: float = 0.1,
) -> Array:
    """Per candidate camera, the share of target points whose line of sight crosses no occupied voxel.

    The segment from a camera centre o to a target point q is walked voxel by voxel up to
    ``target_margin`` metres before q (the target's own surface may touch a voxel of a wall
    it stands at); it is blocked when any voxel it enters is occupied, including the one o
    lies in (a camera inside furniture sees nothing).

    Args:
        obstacle_map: the map.
        rotation, position: T_map_observation (see centres_in_observation).
        camera_positions: (C, 3) candidate camera centres, observation frame.
        target_points: (M, 3) target points, observation frame (non-finite rows dropped).
        max_targets: at most this many target points are walked (an even stride through
            them: the points come in raster order, so a stride keeps the body's extent).
        target_margin: metres of each segment, at the target end, that are not checked.

    Returns:
        (C,) float64 in [0, 1]; 1 for every candidate when there are no target points.
    """
    rotation, position = _check_pose(rotation, position)
    cameras = np.asarray(camera_positions, dtype=np.float64).reshape(-1, 3)
    targets = np.asarray(target_points, dtype=np.float64).reshape(-1, 3)
    targets = targets[np.all(np.isfinite(targets), axis=1)]
    if targets.shape[0] == 0 or cameras.shape[0] == 0:
        return np.ones(cameras.shape[0])
    stride = max(1, int(np.ceil(targets.shape[0] / max(1, int(max_targets)))))
    targets = targets[::stride]
    # Observation frame -> map frame: x_map = R x + t.
    cameras_map = cameras @ rotation.T + position[None, :]
    targets_map = targets @ rotation.T + position[None, :]
    clear = segments_clear_skipping_empty(
        obstacle_map.occupied, obstacle_map.occupied_prefix_sums(), obstacle_map.lower_index.astype(np.float64),
        obstacle_map.resolution, np.ascontiguousarray(cameras_map), np.ascontiguousarray(targets_map),
        float(target_margin))
    shares: Array = clear.mean(axis=1)
    return shares


#: A segment's checked part is halved this many times at most for the empty-box test of
#: segments_clear_skipping_empty (pieces of 1/16 of it at the finest).
_MAX_HALVINGS = 4
#: Consecutive targets tested together, as a fan from the origin, before their segments one by one.
_FAN_RUN = 16
#: Cells by which a piece's bounding box is grown: the walk's cells stray from the segment's own by the rounding
#: of its crossing parameters (about 1e-13 cell over a walk of a few hundred cells), far less than this.
_BOX_GROWTH = 1e-6


@njit(cache=True)
def _box_count(prefix: Array, lo0: int, hi0: int, lo1: int, hi1: int, lo2: int, hi2: int) -> int:
    """Occupied voxels in the index box [lo, hi] per axis, from the inclusive 3-D prefix sums."""
    count: int = (prefix[hi0 + 1, hi1 + 1, hi2 + 1] - prefix[lo0, hi1 + 1, hi2 + 1] - prefix[hi0 + 1, lo1, hi2 + 1]
                  - prefix[hi0 + 1, hi1 + 1, lo2] + prefix[lo0, lo1, hi2 + 1] + prefix[lo0, hi1 + 1, lo2]
                  + prefix[hi0 + 1, lo1, lo2] - prefix[lo0, lo1, lo2])
    return count


@njit(cache=True)
def _piece_may_be_blocked(prefix: Array, sizes: Array, start: Array, delta: Array, t_a: float,
                          t_b: float) -> bool:
    """Whether the cells of the bounding box of g([t_a, t_b]) (g(t) = start + t delta, grid coordinates), grown
    by _BOX_GROWTH, hold an occupied cell (prefix sums: eight look-ups)."""
    lo0 = lo1 = lo2 = hi0 = hi1 = hi2 = 0
    for a in range(3):
        g_a = start[a] + t_a * delta[a]
        g_b = start[a] + t_b * delta[a]
        low = max(int(np.floor(min(g_a, g_b) - _BOX_GROWTH)), 0)
        high = min(int(np.floor(max(g_a, g_b) + _BOX_GROWTH)), sizes[a] - 1)
        if low > high:
            return False  # wholly off the grid: free
        if a == 0:
            lo0, hi0 = low, high
        elif a == 1:
            lo1, hi1 = low, high
        else:
            lo2, hi2 = low, high
    return _box_count(prefix, lo0, hi0, lo1, hi1, lo2, hi2) > 0


@njit(cache=True)
def _walk_axis(start: float, delta: float, cell: int) -> Tuple[int, float, float]:
    """(step, t_delta, first t_max) of one axis of the walk, with segments_clear's arithmetic."""
    if delta > 0.0:
        return 1, 1.0 / delta, (cell + 1.0 - start) / delta
    if delta < 0.0:
        return -1, -1.0 / delta, (start - cell) / -delta
    return 0, np.inf, np.inf


@njit(cache=True)
def segments_clear_skipping_empty(
    occupied: Array,
    prefix: Array,
    lower_index: Array,
    resolution: float,
    origins: Array,
    targets: Array,
    target_margin: float,
) -> Array:
    """segments_clear (the plain cell-by-cell walk, the reference kernel in the planner's tests:
    test/reference_planner_kernels.py), with the walk left out where its answer is sure without it.

    First, per origin, runs of _FAN_RUN consecutive targets are tested together: the fan of their segments is
    tested as a whole, then by halves, quarters, ... (at most _MAX_HALVINGS times, only the pieces whose box is
    not empty); when every piece at some level has a bounding box whose cells, grown by _BOX_GROWTH cells on each
    side (far more than the walk's rounding can stray), hold no occupied cell, all its segments are clear. The
    segments of other runs get the same test one by one; a segment still not sure is blocked when a point of its
    last non-empty piece lies well inside an occupied cell, and is otherwise walked as segments_clear walks it
    (the same arithmetic), up to the end of that piece. The answer is segments_clear's.

    Args:
        occupied, lower_index, resolution, origins, targets, target_margin: as in segments_clear.
        prefix: the map's occupied_prefix_sums().
    """
    num_origins = origins.shape[0]
    num_targets = targets.shape[0]
    size_x, size_y, size_z = occupied.shape[0], occupied.shape[1], occupied.shape[2]
    sizes = np.array([size_x, size_y, size_z], dtype=np.int64)
    clear = np.ones((num_origins, num_targets), dtype=np.bool_)
    start = np.empty(3)
    delta = np.empty(3)
    stack_a = np.empty(2 * _MAX_HALVINGS + 2)
    stack_b = np.empty(2 * _MAX_HALVINGS + 2)
    stack_level = np.empty(2 * _MAX_HALVINGS + 2, dtype=np.int64)
    # Runs of _FAN_RUN consecutive targets (in the given order: a raster order keeps them together), as boxes in
    # grid coordinates.
    num_runs = (num_targets + _FAN_RUN - 1) // _FAN_RUN
    run_box = np.empty((num_runs, 6))
    for run in range(num_runs):
        for a in range(3):
            run_box[run, a] = np.inf
            run_box[run, 3 + a] = -np.inf
        for m in range(run * _FAN_RUN, min(num_targets, (run + 1) * _FAN_RUN)):
            for a in range(3):
                value = targets[m, a] / resolution - lower_index[a]
                run_box[run, a] = min(run_box[run, a], value)
                run_box[run, 3 + a] = max(run_box[run, 3 + a], value)
    for c in range(num_origins):
        for a in range(3):
            start[a] = origins[c, a] / resolution - lower_index[a]
        for run in range(num_runs):
            if _fan_clear(prefix, sizes, start, run_box[run], resolution, target_margin, stack_a, stack_b,
                          stack_level):
                continue  # every segment of the run is clear
            for m in range(run * _FAN_RUN, min(num_targets, (run + 1) * _FAN_RUN)):
                _walk_one(occupied, prefix, sizes, lower_index, resolution, origins, targets, target_margin, c, m,
                          start, delta, stack_a, stack_b, stack_level, clear)
    return clear


@njit(cache=True)
def _fan_clear(prefix: Array, sizes: Array, start: Array, box: Array, resolution: float,
               target_margin: float, stack_a: Array, stack_b: Array, stack_level: Array) -> bool:
    """Whether every segment from the origin (grid coordinates start) to a point of the box (lower, upper corners in
    grid coordinates), up to where its check ends, surely crosses no occupied cell: the fan's pieces t in [t_a, t_b]
    lie in the bounding box of start + t (q - start) over the piece's ends and the box's corners (the map is
    bilinear in t and q), tested, then halved, like a segment's."""
    # The check of a segment ends at t_end = 1 - margin / length <= 1 - margin / (the farthest corner's distance).
    farthest = 0.0
    for corner in range(8):
        squared = 0.0
        for a in range(3):
            q = box[a] if (corner >> a) & 1 == 0 else box[3 + a]
            squared += ((q - start[a]) * resolution) ** 2
        farthest = max(farthest, squared)
    farthest = np.sqrt(farthest) * (1.0 + 1e-9) + 1e-9
    if farthest <= target_margin:
        return False
    t_end = 1.0 - target_margin / farthest + 1e-9
    stack_a[0], stack_b[0], stack_level[0] = 0.0, t_end, 0
    depth = 1
    while depth > 0:
        depth -= 1
        t_a, t_b, level = stack_a[depth], stack_b[depth], stack_level[depth]
        if not _fan_piece_may_be_blocked(prefix, sizes, start, box, t_a, t_b):
            continue
        if level == _MAX_HALVINGS:
            return False
        t_mid = 0.5 * (t_a + t_b)
        stack_a[depth], stack_b[depth], stack_level[depth] = t_a, t_mid, level + 1
        stack_a[depth + 1], stack_b[depth + 1], stack_level[depth + 1] = t_mid, t_b, level + 1
        depth += 2
    return True


@njit(cache=True)
def _fan_piece_may_be_blocked(prefix: Array, sizes: Array, start: Array, box: Array, t_a: float,
                              t_b: float) -> bool:
    """_piece_may_be_blocked for the points start + t (q - start), t in [t_a, t_b], q in the box."""
    lo0 = lo1 = lo2 = hi0 = hi1 = hi2 = 0
    for a in range(3):
        low_value = np.inf
        high_value = -np.inf
        for t in (t_a, t_b):
            for q in (box[a], box[3 + a]):
                value = start[a] + t * (q - start[a])
                low_value = min(low_value, value)
                high_value = max(high_value, value)
        low = max(int(np.floor(low_value - _BOX_GROWTH)), 0)
        high = min(int(np.floor(high_value + _BOX_GROWTH)), sizes[a] - 1)
        if low > high:
            return False
        if a == 0:
            lo0, hi0 = low, high
        elif a == 1:
            lo1, hi1 = low, high
        else:
            lo2, hi2 = low, high
    return _box_count(prefix, lo0, hi0, lo1, hi1, lo2, hi2) > 0


@njit(cache=True)
def _walk_one(occupied: Array, prefix: Array, sizes: Array, lower_index: Array,
              resolution: float, origins: Array, targets: Array, target_margin: float, c: int, m: int,
              start: Array, delta: Array, stack_a: Array, stack_b: Array,
              stack_level: Array, clear: Array) -> None:
    """One segment of segments_clear_skipping_empty: its own piece test, then (when needed) the walk."""
    size_x, size_y, size_z = occupied.shape[0], occupied.shape[1], occupied.shape[2]
    length = 0.0
    for a in range(3):
        delta[a] = targets[m, a] - origins[c, a]
        length += delta[a] * delta[a]
    length = np.sqrt(length)
    if length <= target_margin:
        return  # nothing left to check
    t_end = 1.0 - target_margin / length
    for a in range(3):
        start[a] = origins[c, a] / resolution - lower_index[a]
        delta[a] = delta[a] / resolution

    # The empty-box test: a piece whose box holds an occupied cell is halved, down to _MAX_HALVINGS; the
    # walk is needed only when a piece of the finest level holds one, and only up to the last such piece.
    walk_until = -1.0
    last_piece_start = 0.0
    stack_a[0], stack_b[0], stack_level[0] = 0.0, t_end, 0
    depth = 1
    while depth > 0:
        depth -= 1
        t_a, t_b, level = stack_a[depth], stack_b[depth], stack_level[depth]
        if t_b <= walk_until or not _piece_may_be_blocked(prefix, sizes, start, delta, t_a, t_b):
            continue
        if level == _MAX_HALVINGS:
            walk_until = t_b
            last_piece_start = t_a
            continue
        t_mid = 0.5 * (t_a + t_b)
        # The later half first: the first finest piece found then is the last one along the segment.
        stack_a[depth], stack_b[depth], stack_level[depth] = t_a, t_mid, level + 1
        stack_a[depth + 1], stack_b[depth + 1], stack_level[depth + 1] = t_mid, t_b, level + 1
        depth += 2
    if walk_until < 0.0:
        return
    # Points of the last such piece, a few per cell: one well inside an occupied cell (farther than _BOX_GROWTH
    # from its faces, before the check ends) is a cell the walk surely enters: the segment is blocked.
    longest = max(abs(delta[0]), abs(delta[1]), abs(delta[2]))
    samples = int(min(64.0, (walk_until - last_piece_start) * longest * 4.0)) + 2
    for k in range(samples):
        t = last_piece_start + (walk_until - last_piece_start) * k / (samples - 1)
        if t > t_end - 1e-9:
            break
        inside = True
        index_x = index_y = index_z = 0
        for a in range(3):
            g = start[a] + t * delta[a]
            index = np.floor(g)
            if not (g - index > _BOX_GROWTH and index + 1.0 - g > _BOX_GROWTH and 0.0 <= index < sizes[a]):
                inside = False
                break
            if a == 0:
                index_x = int(index)
            elif a == 1:
                index_y = int(index)
            else:
                index_z = int(index)
        if inside and occupied[index_x, index_y, index_z]:
            clear[c, m] = False
            return
    # Past walk_until (with a margin far above the rounding of the crossing parameters) every cell the walk
    # enters lies in an empty piece's box: the segment is clear from there on.
    walk_until += 1e-9

    # The walk of segments_clear, its arithmetic unchanged (scalars instead of 3-arrays).
    start_x, start_y, start_z = start[0], start[1], start[2]
    delta_x, delta_y, delta_z = delta[0], delta[1], delta[2]
    cell_x = int(np.floor(start_x))
    cell_y = int(np.floor(start_y))
    cell_z = int(np.floor(start_z))
    step_x, t_delta_x, t_max_x = _walk_axis(start_x, delta_x, cell_x)
    step_y, t_delta_y, t_max_y = _walk_axis(start_y, delta_y, cell_y)
    step_z, t_delta_z, t_max_z = _walk_axis(start_z, delta_z, cell_z)
    t = 0.0
    while t <= t_end:
        if t > walk_until:
            break
        if (0 <= cell_x < size_x and 0 <= cell_y < size_y and 0 <= cell_z < size_z
                and occupied[cell_x, cell_y, cell_z]):
            clear[c, m] = False
            break
        if t_max_y < t_max_x:
            if t_max_z < t_max_y:
                t = t_max_z
                cell_z += step_z
                t_max_z += t_delta_z
            else:
                t = t_max_y
                cell_y += step_y
                t_max_y += t_delta_y
        elif t_max_z < t_max_x:
            t = t_max_z
            cell_z += step_z
            t_max_z += t_delta_z
        else:
            t = t_max_x
            cell_x += step_x
            t_max_x += t_delta_x


def warm_up_obstacle_map() -> None:
    """Compile the traversal kernel now (a node calls this at start-up, not on frame one)."""
    grid = voxel_map_from_centres(np.array([[0.05, 0.05, 0.05]]), 0.1)
    line_of_sight_clear_fraction(grid, np.eye(3), np.zeros(3), np.array([[0.05, 0.05, -1.0]]),
                                 np.array([[0.05, 0.05, 1.0]]))
