"""The planner's obstacle memory: evidence, decay, bounds; what it holds after a simulated view of a furnished room."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from leapnbv_perception.smplx_layer import SMPLXModel
from leapnbv_planner.obstacle_map import voxel_map_from_centres
from leapnbv_planner.obstacle_memory import ObstacleMemory, ObstacleMemoryParams, depth_points_in_fixed_frame
from leapnbv_sim.generation import SceneConfig, generate_scene
from leapnbv_sim.render import PERSON_ID
from leapnbv_stand_ins.stand_in_body_model import build_stand_in_body_model

S = 1_000_000_000


def _blob(centre, count=5):
    """``count`` points in the voxel of ``centre`` (0.1 m voxels), 1 m from the camera."""
    return np.repeat(np.asarray(centre, dtype=np.float64)[None], count, axis=0), np.ones(count)


def test_evidence_needs_points_above_the_floor_and_in_range() -> None:
    memory = ObstacleMemory()
    points = np.vstack([_blob([1.05, 2.05, 0.55])[0], _blob([3.05, 0.05, 0.02])[0],  # a box; the floor
                        _blob([0.05, 0.05, 1.05], count=2)[0], _blob([6.05, 0.05, 0.55])[0]])  # too few; too far
    distances = np.concatenate([np.ones(12), np.full(5, 6.0)])
    assert memory.add_points(points, distances, 10 * S, "map") == 1
    np.testing.assert_allclose(memory.occupied_centres(), [[1.05, 2.05, 0.55]])
    assert memory.weight([1.01, 2.09, 0.51]) == pytest.approx(1.0)
    assert memory.weight([3.05, 0.05, 0.02]) == 0.0


def test_weight_halves_every_half_life_and_fades_out() -> None:
    memory = ObstacleMemory(ObstacleMemoryParams(half_life_s=20.0))
    memory.add_points(*_blob([0.55, 0.55, 0.55]), 10 * S, "map")
    assert memory.weight([0.55, 0.55, 0.55], 30 * S) == pytest.approx(0.5)
    assert len(memory.occupied_centres(30 * S)) == 1  # seen within the last half-life: an obstacle ...
    assert len(memory.occupied_centres(31 * S)) == 0  # ... and no longer (0.5 ** 1.05 = 0.48)
    memory.add_points(*_blob([0.55, 0.55, 0.55]), 30 * S, "map")  # seen again: 0.5 + 1
    assert memory.weight([0.55, 0.55, 0.55]) == pytest.approx(1.5)
    # Not seen for 3 half-lives (1.5 -> 0.19 < forget_weight 0.2): dropped at the next frame.
    memory.add_points(*_blob([5.05, 0.05, 0.55]), 90 * S, "map")
    assert len(memory) == 1 and memory.weight([0.55, 0.55, 0.55]) == 0.0


def test_weight_is_capped_and_one_frame_counts_once() -> None:
    memory = ObstacleMemory(ObstacleMemoryParams(max_weight=3.0))
    memory.add_points(*_blob([0.55, 0.55, 0.55], count=500), S, "map")
    assert memory.weight([0.55, 0.55, 0.55]) == pytest.approx(1.0)
    for k in range(10):
        memory.add_points(*_blob([0.55, 0.55, 0.55]), S + k, "map")
    assert memory.weight([0.55, 0.55, 0.55]) == pytest.approx(3.0, abs=1e-6)


def test_bounded_the_weakest_then_the_oldest_go_first() -> None:
    memory = ObstacleMemory(ObstacleMemoryParams(max_voxels=3, half_life_s=10.0))
    memory.add_points(*_blob([0.05, 0.05, 0.55]), 1 * S, "map")
    memory.add_points(*_blob([0.05, 0.05, 0.55]), 1 * S, "map")  # weight 2: the strongest
    for x, stamp in ((1.05, 2), (2.05, 3), (3.05, 4)):
        memory.add_points(*_blob([x, 0.05, 0.55]), stamp * S, "map")
    assert len(memory) == 3
    kept = {x for x in (0.05, 1.05, 2.05, 3.05) if memory.weight([x, 0.05, 0.55]) > 0.0}
    assert kept == {0.05, 2.05, 3.05}  # x = 1.05 (weight 1 at 2 s, 0.87 at 4 s) was the weakest
    assert memory.weight([0.05, 0.05, 0.55]) == pytest.approx(2.0 * 0.5 ** 0.3)


def test_stamps_run_forward_and_another_fixed_frame_starts_over() -> None:
    memory = ObstacleMemory()
    memory.add_points(*_blob([0.55, 0.55, 0.55]), 5 * S, "map")
    with pytest.raises(ValueError, match="older"):
        memory.add_points(*_blob([0.55, 0.55, 0.55]), 4 * S, "map")
    memory.add_points(*_blob([1.55, 0.55, 0.55]), 1 * S, "odom")  # another frame: cleared, its own stamps
    assert memory.frame_id == "odom" and len(memory) == 1 and memory.frames == 1
    with pytest.raises(ValueError, match="resolution"):
        ObstacleMemoryParams(resolution=0.0)


@pytest.fixture(scope="module")
def furnished_scene():
    body = SMPLXModel(build_stand_in_body_model("small"), source="stand_in_small")
    return generate_scene(dataclasses.replace(SceneConfig(clutter_count_range=(2, 4)), seed=3), body)


def test_a_view_of_a_furnished_room_fills_the_memory_with_its_obstacles(furnished_scene) -> None:
    scene = furnished_scene
    frame = scene.render()
    camera = frame.camera_pose
    points, distances = depth_points_in_fixed_frame(frame.depth_clean_m, frame.K, camera.rotation, camera.position,
                                                    stride=2, exclude=frame.object_id == PERSON_ID)
    memory = ObstacleMemory()
    assert memory.add_points(points, distances, 3 * S, "sim_world") > 0
    remembered = memory.occupied_centres()
    truth = scene.obstacle_voxel_centres(0.1)
    truth_cells = {tuple(c) for c in np.floor(truth / 0.1).astype(int)}
    cells = np.floor(remembered / 0.1).astype(int)
    # Every remembered voxel is an obstacle voxel of the scene, or touches one (a surface point on a voxel's face).
    near = [any((c[0] + i, c[1] + j, c[2] + k) in truth_cells for i in (-1, 0, 1) for j in (-1, 0, 1)
                for k in (-1, 0, 1)) for c in cells]
    assert np.mean(near) >= 0.99
    # Nothing of the person (its pixels were left out) and nothing on the floor.
    body = scene.body_vertices_world
    lo, hi = body.min(axis=0) - 0.05, body.max(axis=0) + 0.05
    inside_body = np.all((remembered > lo) & (remembered < hi), axis=1)
    assert not inside_body.any()
    assert remembered[:, 2].min() >= 0.1
    # The plan takes it as it takes the robot's map.
    as_map = voxel_map_from_centres(remembered, 0.1)
    assert int(as_map.occupied.sum()) == len(remembered)
