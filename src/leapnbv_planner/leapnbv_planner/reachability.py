"""Which candidate foot points the robot can drive to, and how far: shortest paths on a floor grid
(docs/ALGORITHMS.md §6).

The floor around the robot and the candidates is cut into square cells in the plane. A cell is
occupied when an obstacle point (background or obstacle-map point higher than ``floor_clearance``
above the floor, or a person point: the robot does not drive through the person) falls in it; the
occupied cells are inflated by the robot's radius, so a free cell is one the robot's centre may
take. Cells outside the current view's field of view are unknown: free or occupied by the
``unknown_space`` parameter (not inflated: nothing is known to be there). The field of view is the
wedge of the image's columns on the floor: the floor just below the image, in front of the robot,
counts as seen. The path length from the robot's current foot point to each candidate's is a
Dijkstra shortest path over free cells (8-connected, no corner cutting); a candidate is reachable
when its cell is free and the path is at most ``max_path_length``.

Everything is in the observation's camera optical frame; the plane coordinates are
(p . e1, p . e2) with (e1, e2) = ``plane_basis(n)``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional, Tuple

import numpy as np

from leapnbv_planner.arrays import Array
from leapnbv_planner.candidates import plane_basis
from leapnbv_planner.footprint_kernel import elevated_plane_points
from leapnbv_planner.path_kernel import grid_distances, mark_occupied_in_plane

UNKNOWN_SPACE_CHOICES = ("free", "occupied")
GRID_MARGIN_M = 1.0  # the grid reaches this far beyond the outermost candidate and the robot
MAX_GRID_CELLS = 400  # per side: a plan never builds a grid larger than this (coarser cells instead)
NEAR_M = 0.1  # a floor cell nearer than this to the camera plane counts as unseen


class ReachabilityError(ValueError):
    """An input of the reachability test has the wrong shape or value."""


@dataclass
class OccupancyGrid:
    """A 2-D grid on the floor plane.

    Attributes:
        unit_normal, offset: the floor n.x + d = 0 (unit n up).
        axes: (2, 3) e1, e2 spanning the plane.
        origin: (2,) plane coordinates of the corner of cell (0, 0).
        cell: cell edge, metres.
        occupied: (R, C) bool, a cell holding an obstacle point.
        seen: (R, C) bool, a cell the current view sees (inside its field of view).
        free: (R, C) bool, where the robot's centre may be (not within the robot radius of an
            occupied cell; unknown cells by ``unknown_space``).
    """

    unit_normal: Array
    offset: float
    axes: Array
    origin: Array
    cell: float
    occupied: Array
    seen: Array
    free: Array

    def plane_coordinates(self, points: Array) -> Array:
        """(N, 2) plane coordinates of (N, 3) observation-frame points."""
        return np.asarray(points, dtype=np.float64) @ self.axes.T

    def cells_of(self, points: Array) -> Tuple[Array, Array, Array]:
        """(rows, cols, inside) of (N, 3) points (rows/cols clipped; inside False off the grid)."""
        uv = (self.plane_coordinates(points) - self.origin) / self.cell
        cols, rows = np.floor(uv[:, 0]).astype(np.int64), np.floor(uv[:, 1]).astype(np.int64)
        inside = (rows >= 0) & (rows < self.free.shape[0]) & (cols >= 0) & (cols < self.free.shape[1])
        return np.clip(rows, 0, self.free.shape[0] - 1), np.clip(cols, 0, self.free.shape[1] - 1), inside

    def cell_centres(self, rows: Array, cols: Array) -> Array:
        """(N, 3) observation-frame floor points at the centres of the given cells."""
        u = self.origin[0] + (np.asarray(cols, dtype=np.float64) + 0.5) * self.cell
        v = self.origin[1] + (np.asarray(rows, dtype=np.float64) + 0.5) * self.cell
        centres: Array = u[:, None] * self.axes[0] + v[:, None] * self.axes[1] - self.offset * self.unit_normal
        return centres


@dataclass
class Reachability:
    """Path lengths from the robot to every candidate foot point.

    Attributes:
        path_lengths: (C,) metres along the shortest free path; inf where there is none.
        reachable: (C,) bool: a free path of at most max_path_length.
        grid: the grid the paths were found on.
        parents: (R, C) flat index of each cell's predecessor on its shortest path (-1: none).
        start_cell: (row, col) of the robot's foot point.
        distances: (R, C) metres of the shortest free path to each cell's centre (inf: none).
    """

    path_lengths: Array
    reachable: Array
    grid: OccupancyGrid
    parents: Array
    start_cell: Tuple[int, int]
    distances: Optional[Array] = None

    def path_lengths_at(self, foot_points: Array) -> Array:
        """(N,) path lengths to (N, 3) floor points (their cells'; inf off the grid or without a path).

        Raises:
            ReachabilityError: the Reachability was made without its grid distances.
        """
        if self.distances is None:
            raise ReachabilityError("path_lengths_at needs the grid distances (Reachability.distances is None)")
        return _lengths_at(self.grid, self.distances, foot_points)

    def path_to(self, foot_point: Array) -> Optional[Array]:
        """(P, 3) floor points (cell centres) from the robot to ``foot_point`` (its exact point last); None
        when unreachable."""
        rows, cols, inside = self.grid.cells_of(np.asarray(foot_point, dtype=np.float64).reshape(1, 3))
        if not inside[0]:
            return None
        columns = self.free_columns()
        index = int(rows[0]) * columns + int(cols[0])
        start = self.start_cell[0] * columns + self.start_cell[1]
        if index != start and self.parents.reshape(-1)[index] < 0:
            return None
        chain = [index]
        while chain[-1] != start:
            chain.append(int(self.parents.reshape(-1)[chain[-1]]))
            if chain[-1] < 0 or len(chain) > self.parents.size:
                return None
        chain.reverse()
        flat = np.asarray(chain, dtype=np.int64)
        points = self.grid.cell_centres(flat // columns, flat % columns)
        points[-1] = np.asarray(foot_point, dtype=np.float64)
        return points

    def free_columns(self) -> int:
        return int(self.grid.free.shape[1])


def _inflate(occupied: Array, radius_cells: float) -> Array:
    """Occupied cells grown by a disc of ``radius_cells`` (cell centres within the radius)."""
    reach = int(np.floor(radius_cells))
    grown = occupied.copy()
    rows, cols = occupied.shape
    for dr in range(-reach, reach + 1):
        for dc in range(-reach, reach + 1):
            if (dr == 0 and dc == 0) or dr * dr + dc * dc > radius_cells * radius_cells:
                continue
            target = grown[max(0, dr):rows + min(0, dr), max(0, dc):cols + min(0, dc)]
            target |= occupied[max(0, -dr):rows + min(0, -dr), max(0, -dc):cols + min(0, -dc)]
    return grown


def build_occupancy_grid(
    obstacle_points: Array,
    person_points: Array,
    unit_normal: Array,
    offset: float,
    cover_points: Array,
    cell: float,
    robot_radius: float,
    floor_clearance: float,
    unknown_space: str = "free",
    camera: Optional[Tuple[Array, int, int]] = None,
    obstacle_plane_points: Optional[Array] = None,
) -> OccupancyGrid:
    """The floor grid around ``cover_points`` (the robot's and the candidates' foot points).

    Args:
        obstacle_points: (K, 3) background (and map) points; those higher than floor_clearance occupy their cell.
        person_points: (N, 3) target points; all occupy their cell.
        unit_normal, offset: the floor (unit n up).
        cover_points: (M, 3) points the grid must hold (with GRID_MARGIN_M around them).
        cell: cell edge, metres (coarsened so that no side exceeds MAX_GRID_CELLS).
        robot_radius: inflation radius, metres.
        floor_clearance: metres above the floor below which a point is floor, not obstacle.
        unknown_space: "free" or "occupied": cells outside the current view's field of view.
        camera: (K, width, height) of the current view; None counts every cell as seen (the height is unused:
            see the module's note on the field of view).
        obstacle_plane_points: the obstacle points higher than floor_clearance as (M, 2) plane coordinates (p.e1,
            p.e2), when the caller made them already (footprint_kernel.elevated_plane_points, the same basis); then
            obstacle_points is not read.

    Returns:
        The grid.

    Raises:
        ReachabilityError: a bad unknown_space, cell or shape.
    """
    if unknown_space not in UNKNOWN_SPACE_CHOICES:
        raise ReachabilityError(f"unknown_space must be one of {UNKNOWN_SPACE_CHOICES}, got {unknown_space!r}")
    if not cell > 0.0:
        raise ReachabilityError(f"grid cell must be > 0, got {cell}")
    e1, e2 = plane_basis(unit_normal)
    axes = np.stack([e1, e2])
    cover = np.asarray(cover_points, dtype=np.float64).reshape(-1, 3) @ axes.T
    low = cover.min(axis=0) - GRID_MARGIN_M - robot_radius
    high = cover.max(axis=0) + GRID_MARGIN_M + robot_radius
    cell = max(float(cell), float(np.max(high - low)) / (MAX_GRID_CELLS - 1))  # the origin below adds a cell
    # Cell edges at odd multiples of half a cell in plane coordinates: the robot's own foot point (plane
    # coordinates 0, 0) is a cell centre, and no foot point sits on an edge by construction (an origin at the
    # lowest foot point less a whole number of cells put that point on an edge, where the last bit of
    # rounding, which differs between CPUs, chose its cell).
    origin = (np.floor(low / cell - 0.5) + 0.5) * cell
    shape = (int(np.ceil((high[1] - origin[1]) / cell)), int(np.ceil((high[0] - origin[0]) / cell)))
    grid = OccupancyGrid(unit_normal=np.asarray(unit_normal, dtype=np.float64), offset=float(offset), axes=axes,
                         origin=origin, cell=cell, occupied=np.zeros(shape, dtype=bool),
                         seen=np.ones(shape, dtype=bool), free=np.ones(shape, dtype=bool))

    def in_plane(cloud: Array, min_height: float) -> Array:
        return elevated_plane_points(np.ascontiguousarray(np.asarray(cloud, dtype=np.float64).reshape(-1, 3)),
                                     grid.unit_normal, float(offset), min_height, e1, e2)

    if obstacle_plane_points is None:
        obstacle_plane_points = in_plane(obstacle_points, float(floor_clearance))
    for plane_points in (obstacle_plane_points, in_plane(person_points, -np.inf)):  # the person: every point
        mark_occupied_in_plane(np.ascontiguousarray(plane_points, dtype=np.float64), origin,
                               float(cell), grid.occupied)
    if camera is not None:
        k, width, height = camera
        all_rows, all_cols = np.indices(shape)
        centres = grid.cell_centres(all_rows.reshape(-1), all_cols.reshape(-1))
        z = centres[:, 2]
        # The wedge the camera looks into: its horizontal field of view. The floor just in front of the robot is
        # below the image but is the floor the robot stands on and looks over, so the rows are not tested.
        with np.errstate(divide="ignore", invalid="ignore"):
            u = k[0, 0] * centres[:, 0] / z + k[0, 1] * centres[:, 1] / z + k[0, 2]
        grid.seen = ((z > NEAR_M) & (u >= 0) & (u < width)).reshape(shape)
    # Obstacles are grown by the robot's radius; unknown cells (when they count as occupied) only keep the
    # robot's centre out: nothing is known to be there.
    grid.free = ~_inflate(grid.occupied, robot_radius / cell)
    if unknown_space == "occupied":
        grid.free &= grid.seen
    return grid


def reachability(grid: OccupancyGrid, start_foot: Array, feet: Array, max_path_length: float,
                 robot_radius: float) -> Reachability:
    """Shortest free paths from the robot's foot point to every candidate's.

    The robot stands where it stands: the cells within its radius of the start are free for it.

    Args:
        grid: the floor grid.
        start_foot: (3,) the robot's current foot point.
        feet: (C, 3) candidate foot points.
        max_path_length: longest path of a reachable candidate, metres.
        robot_radius: metres (the cleared disc round the start).

    Returns:
        The path lengths, the reachable flags and what is needed to read a path back.
    """
    free = grid.free.copy()
    rows, cols, inside = grid.cells_of(np.asarray(start_foot, dtype=np.float64).reshape(1, 3))
    start = (int(rows[0]), int(cols[0]))
    all_rows, all_cols = np.indices(free.shape)
    near_start = np.square(all_rows - start[0]) + np.square(all_cols - start[1]) <= \
        np.square(robot_radius / grid.cell + 0.5)
    free |= near_start & ~grid.occupied
    free[start] = True
    distances, parents = grid_distances(free, start[0], start[1], grid.cell)
    lengths = _lengths_at(grid, distances, feet)
    return Reachability(path_lengths=lengths, reachable=np.isfinite(lengths) & (lengths <= float(max_path_length)),
                        grid=grid, parents=parents, start_cell=start, distances=distances)


def _lengths_at(grid: OccupancyGrid, distances: Array, foot_points: Array) -> Array:
    """(N,) path lengths to (N, 3) floor points: their cells' distances; inf off the grid or without a path."""
    rows, cols, inside = grid.cells_of(np.asarray(foot_points, dtype=np.float64).reshape(-1, 3))
    return np.where(inside, distances[rows, cols], np.inf)
