"""true_path_lengths: the robot's path on a known floor map (open floor, around a wall, walled in)."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from leapnbv_evaluation.truth_paths import true_path_lengths


def _scene(obstacles: np.ndarray) -> SimpleNamespace:
    person = np.array([[5.0, 5.0, 1.0]])  # far from the paths below
    return SimpleNamespace(obstacle_voxel_centres=lambda cell: obstacles, body_vertices_world=person)


def _wall(x: float, y_from: float, y_to: float) -> np.ndarray:
    ys = np.arange(y_from, y_to, 0.05)
    return np.array([[x, y, z] for y in ys for z in (0.25, 0.75)])


def test_open_floor_is_about_the_straight_line():
    lengths = true_path_lengths(_scene(np.zeros((0, 3))), (0.0, 0.0), np.array([[3.0, 0.0], [0.0, 0.0]]))
    assert abs(lengths[0] - 3.0) <= 0.1 + 1e-9 and lengths[1] == 0.0  # cell centre to cell centre


def test_a_wall_in_the_way_is_walked_around_and_a_closed_room_has_no_path():
    wall = _wall(1.5, -1.0, 1.0)  # 2 m long across the straight line
    length = true_path_lengths(_scene(wall), (0.0, 0.0), np.array([[3.0, 0.0]]))[0]
    # Around an end of the wall, grown by the 0.3 m robot radius: at least 2 x hypot(1.5, 1.3).
    assert 2 * np.hypot(1.5, 1.3) - 0.1 <= length <= 5.0
    box = np.concatenate([_wall(-1.0, -1.0, 1.0), _wall(1.0, -1.0, 1.0),
                          np.array([[x, y, 0.5] for x in np.arange(-1.0, 1.0, 0.05) for y in (-1.0, 1.0)])])
    assert np.isinf(true_path_lengths(_scene(box), (0.0, 0.0), np.array([[3.0, 0.0]]))[0])
