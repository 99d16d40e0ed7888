"""Paths a wheeled robot needs on a scene's true floor map (the evaluation's measure of travel).

The grid is the planner's (leapnbv_planner.reachability) built from what the simulator knows: the
obstacles' voxel centres and the person's mesh, in the world frame (floor z = 0), every cell seen.
The planner plans on what the robot knew (its map, its view); this is the path the robot would
actually need, and whether one exists at all.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from leapnbv_common.array_types import FloatArray
from leapnbv_planner.reachability import build_occupancy_grid, reachability
from leapnbv_sim.scene import Scene

ROBOT_RADIUS_M = 0.3  # the planner's default robot_radius
GRID_CELL_M = 0.1
FLOOR_CLEARANCE_M = 0.05


def true_path_lengths(scene: Scene, start_xy: Sequence[float], goals_xy: FloatArray,
                      robot_radius: float = ROBOT_RADIUS_M, cell: float = GRID_CELL_M) -> FloatArray:
    """Shortest free path (m) from the start to each goal on the floor (inf: none; 0 for the start itself).

    Args:
        scene: a leapnbv_sim Scene (obstacle_voxel_centres, body_vertices_world).
        start_xy: (2,) the robot's foot point, world x, y.
        goals_xy: (G, 2) goal foot points.
        robot_radius: the obstacles and the person are grown by it.
        cell: grid cell edge.
    """
    goals = np.column_stack([np.asarray(goals_xy, np.float64).reshape(-1, 2), np.zeros(len(goals_xy))])
    start = np.array([float(start_xy[0]), float(start_xy[1]), 0.0])
    up = np.array([0.0, 0.0, 1.0])
    grid = build_occupancy_grid(scene.obstacle_voxel_centres(cell), scene.body_vertices_world, up, 0.0,
                                np.concatenate([start[None], goals]), cell, robot_radius, FLOOR_CLEARANCE_M)
    lengths: FloatArray = np.asarray(reachability(grid, start, goals, 1e6, robot_radius).path_lengths, np.float64)
    lengths[np.linalg.norm(goals[:, :2] - start[:2], axis=1) < 1e-6] = 0.0
    return lengths
