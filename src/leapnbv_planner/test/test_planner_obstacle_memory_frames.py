"""A frame's background points for the obstacle memory (leapnbv_planner.obstacle_memory.frame_obstacle_points)."""
from __future__ import annotations

import numpy as np

from leapnbv_planner.obstacle_memory import ObstacleMemory, frame_obstacle_points

# The camera at (0, 0, 1.2) looking along the fixed frame's +x, level (optical z = x, x = -y, y = -z).
ROTATION = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
POSITION = np.array([0.0, 0.0, 1.2])


def optical(points_fixed: np.ndarray) -> np.ndarray:
    return (np.asarray(points_fixed, float) - POSITION) @ ROTATION  # R^T (p - t), row-wise


def column(x: float, y: float, n: int = 60) -> np.ndarray:
    """Points of an upright pole 0.1-1.8 m high at (x, y) of the fixed frame."""
    z = np.linspace(0.1, 1.8, n)
    return np.column_stack([np.full(n, x), np.full(n, y), z])


def test_background_goes_to_the_fixed_frame_and_the_persons_columns_are_left_out():
    person = column(3.0, 0.0)
    chair = column(2.0, 1.0)
    edge = column(3.05, 0.12)  # the mask's edge: the person's own pixels, left in the background
    behind = column(3.0, 0.6)  # 0.6 m to the person's side: an obstacle
    background = optical(np.concatenate([chair, edge, behind]))
    points, distances = frame_obstacle_points(background, optical(person), ROTATION, POSITION, 0.1)
    kept = {tuple(np.round(p[:2], 2)) for p in points}
    assert kept == {(2.0, 1.0), (3.0, 0.6)}
    np.testing.assert_allclose(distances, np.linalg.norm(optical(points), axis=1))
    np.testing.assert_allclose(points[points[:, 1] > 0.9], chair, atol=1e-9)
    # Without a person every background point stays; a margin of 0 leaves out the person's own column only
    # (the edge is in the next one).
    everything, _ = frame_obstacle_points(background, np.zeros((0, 3)), ROTATION, POSITION, 0.1)
    assert len(everything) == len(background)
    tight, _ = frame_obstacle_points(background, optical(person), ROTATION, POSITION, 0.1, margin_m=0.0)
    assert len(tight) == len(background)
    inside, _ = frame_obstacle_points(optical(column(3.02, 0.03)), optical(person), ROTATION, POSITION, 0.1,
                                      margin_m=0.0)
    assert len(inside) == 0


def test_a_chair_seen_once_stays_in_the_memory_when_the_next_frames_do_not_show_it():
    memory = ObstacleMemory()
    chair = optical(column(2.0, 1.0))
    person = optical(column(3.0, 0.0))
    points, distances = frame_obstacle_points(chair, person, ROTATION, POSITION, memory.params.resolution)
    memory.add_points(points, distances, 0, "map")
    for k in range(1, 6):  # 0.2 s frames that no longer show it
        points, distances = frame_obstacle_points(np.zeros((0, 3)), person, ROTATION, POSITION, 0.1)
        memory.add_points(points, distances, k * 200_000_000, "map")
    centres = memory.occupied_centres()
    assert len(centres) > 0
    assert np.all(np.abs(centres[:, 0] - 2.0) <= 0.1) and np.all(np.abs(centres[:, 1] - 1.0) <= 0.1)
