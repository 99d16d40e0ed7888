"""The scene's static obstacles as a voxel map (Scene.obstacle_voxel_centres); the simulator's map and pose topics."""

from __future__ import annotations

import dataclasses
import os
import re
import time

import numpy as np
import pytest

from leapnbv_perception.smplx_layer import SMPLXModel
from leapnbv_sim.generation import SceneConfig, generate_scene
from leapnbv_sim.render import FLOOR_ID, PERSON_ID
from leapnbv_sim.scene import SceneError
from leapnbv_stand_ins.stand_in_body_model import build_stand_in_body_model

RES = 0.1
# A furnished room (the evaluation's benchmark rooms are these): occluders, walls, 2-4 pieces of furniture.
FURNISHED = SceneConfig(clutter_count_range=(2, 4))


@pytest.fixture(scope="module")
def body_model() -> SMPLXModel:
    return SMPLXModel(build_stand_in_body_model("small"), source="stand_in_small")


@pytest.fixture(scope="module")
def scene(body_model: SMPLXModel):
    """A furnished room: occluders, a back wall and clutter."""
    return generate_scene(dataclasses.replace(FURNISHED, seed=0), body_model)


@pytest.fixture(scope="module")
def side_wall_scene(body_model: SMPLXModel):
    """A furnished room with both walls (the first seed that has a side wall)."""
    for seed in range(64):
        candidate = generate_scene(dataclasses.replace(FURNISHED, seed=seed), body_model)
        if "wall_side" in candidate.object_names.values():
            return candidate
    pytest.fail("no seed below 64 has a side wall")


def _obstacles(scene) -> list:
    """(name, (K,3) world vertices) of every object but the floor and the person."""
    found = []
    for object_id, name in sorted(scene.object_names.items()):
        if object_id in (FLOOR_ID, PERSON_ID):
            continue
        faces = scene.faces[scene.face_object_id == object_id]
        found.append((name, scene.vertices_world[np.unique(faces)]))
    return found


def _prism_distance(vertices: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Euclidean distance of (N,3) points to a vertical prism (a box turned about z, or a vertical
    wall rectangle) given by its vertices; 0 inside. Independent of the vertex order."""
    z_low, z_high = vertices[:, 2].min(), vertices[:, 2].max()
    bottom = vertices[np.abs(vertices[:, 2] - z_low) < 1e-9][:, :2]
    top = vertices[np.abs(vertices[:, 2] - z_high) < 1e-9][:, :2]
    # A vertical prism: the top outline is the bottom one.
    assert len(bottom) == len(top) and np.abs(np.sort(bottom, axis=0) - np.sort(top, axis=0)).max() < 1e-9
    xy = points[:, :2]
    centre = bottom.mean(axis=0)
    polygon = bottom[np.argsort(np.arctan2(bottom[:, 1] - centre[1], bottom[:, 0] - centre[0]))]
    horizontal = np.full(len(points), np.inf)
    inside = np.full(len(points), len(polygon) >= 3)
    edges = zip(polygon, np.roll(polygon, -1, axis=0)) if len(polygon) >= 3 else [(polygon[0], polygon[1])]
    for a, b in edges:
        edge = b - a
        t = np.clip(((xy - a) @ edge) / (edge @ edge), 0.0, 1.0)
        horizontal = np.minimum(horizontal, np.linalg.norm(xy - (a + t[:, None] * edge), axis=1))
        inside &= (edge[0] * (xy[:, 1] - a[1]) - edge[1] * (xy[:, 0] - a[0])) >= 0
    horizontal = np.where(inside, 0.0, horizontal)
    vertical = np.maximum(0.0, np.maximum(z_low - points[:, 2], points[:, 2] - z_high))
    return np.hypot(horizontal, vertical)


def _distance_to_obstacles(scene, points: np.ndarray) -> np.ndarray:
    return np.min([_prism_distance(vertices, points) for _, vertices in _obstacles(scene)], axis=0)


def _occupied(centres: np.ndarray, res: float) -> set:
    return set(map(tuple, np.floor(centres / res).astype(np.int64).tolist()))


def _voxel_of(points: np.ndarray, res: float) -> list:
    return list(map(tuple, np.floor(points / res).astype(np.int64).tolist()))


@pytest.mark.parametrize("res", [0.1, 0.25])
def test_every_voxel_touches_an_obstacle_and_lies_on_the_grid(scene, res: float) -> None:
    centres = scene.obstacle_voxel_centres(res)
    assert centres.dtype == np.float64 and centres.ndim == 2 and centres.shape[1] == 3 and len(centres) > 100
    # Centres sit at (index + 0.5) * res, each voxel once.
    indices = centres / res - 0.5
    np.testing.assert_allclose(indices, np.rint(indices), atol=1e-9)
    assert len(np.unique(np.rint(indices), axis=0)) == len(centres)
    # Nothing under the floor; the boxes stand on it, so the lowest layer is k = 0.
    assert centres[:, 2].min() == pytest.approx(0.5 * res)
    # A voxel reaches into an obstacle only if its centre is within half its diagonal of one.
    assert _distance_to_obstacles(scene, centres).max() <= res * np.sqrt(3.0) / 2.0 + 1e-9


def test_points_inside_every_obstacle_fall_in_occupied_voxels(scene, side_wall_scene) -> None:
    rng = np.random.default_rng(0)
    for a_scene in (scene, side_wall_scene):
        occupied = _occupied(a_scene.obstacle_voxel_centres(RES), RES)
        names = [name for name, _ in _obstacles(a_scene)]
        assert any(n.startswith("occluder") for n in names) and any(n.startswith("clutter") for n in names)
        assert "wall_back" in names
        for name, vertices in _obstacles(a_scene):
            # Random convex combinations of the corners (inside a box, on a wall), and the
            # corners themselves pulled a micrometre inward (a sampler with gaps misses these).
            weights = rng.dirichlet(np.full(len(vertices), 0.3), size=3000)
            centroid = vertices.mean(axis=0)
            corners = vertices + 1e-6 * (centroid - vertices) / np.linalg.norm(centroid - vertices, axis=1)[:, None]
            points = np.concatenate([weights @ vertices, corners])
            missing = [v for v in _voxel_of(points, RES) if v not in occupied]
            assert not missing, f"{name}: {len(missing)} voxels inside it are not in the map, e.g. {missing[:3]}"


def test_walls_are_one_complete_voxel_layer(scene, side_wall_scene) -> None:
    for a_scene in (scene, side_wall_scene):
        centres = a_scene.obstacle_voxel_centres(RES)
        walls = dict((name, v) for name, v in _obstacles(a_scene) if name.startswith("wall"))
        back = walls["wall_back"][0, 0]
        assert abs(back / RES - round(back / RES)) > 1e-6  # not on a voxel boundary: one layer
        layer = int(np.floor(back / RES))
        in_layer = {(j, k) for i, j, k in _occupied(centres, RES) if i == layer}
        expected = {(j, k) for j in range(round(-8.0 / RES), round(8.0 / RES)) for k in range(round(3.0 / RES))}
        assert expected <= in_layer
        # The wall is the far end of the room: nothing behind it (it is thinner than a voxel, and
        # the map holds exactly the voxel layer its plane passes through).
        assert centres[:, 0].max() == pytest.approx((layer + 0.5) * RES)
        # Nothing above the walls' 3 m (the top edge only touches the layer above).
        assert centres[:, 2].max() == pytest.approx(3.0 - 0.5 * RES)
    side = dict((name, v) for name, v in _obstacles(side_wall_scene))["wall_side"][0, 1]
    side_layer = int(np.floor(side / RES))
    side_voxels = [v for v in _occupied(side_wall_scene.obstacle_voxel_centres(RES), RES) if v[1] == side_layer]
    assert len(side_voxels) >= round(10.0 / RES) * round(3.0 / RES)  # the side wall is >= 10 m long


def test_the_person_and_the_floor_are_not_obstacles(scene) -> None:
    centres = scene.obstacle_voxel_centres(RES)
    # The pelvis column above the world origin is free.
    column = (np.abs(centres[:, 0]) < 0.15) & (np.abs(centres[:, 1]) < 0.15) & (centres[:, 2] > 0.2)
    assert not np.any(column & (centres[:, 2] < 1.5))
    # No body vertex lies in an occupied voxel unless an obstacle is that close.
    occupied = _occupied(centres, RES)
    body = scene.body_vertices_world
    in_map = np.array([v in occupied for v in _voxel_of(body, RES)])
    near_obstacle = _distance_to_obstacles(scene, body) < RES * np.sqrt(3.0)
    assert not np.any(in_map & ~near_obstacle)
    # The 60 m floor would fill the k = 0 layer far from everything: the distance test above
    # rules it out; here, the bottom layer is no larger than the obstacles' footprints allow.
    bottom = centres[centres[:, 2] < RES]
    assert len(bottom) < 0.2 * len(centres)


def test_count_grows_with_finer_resolution_and_results_are_cached(scene, body_model: SMPLXModel) -> None:
    coarse = scene.obstacle_voxel_centres(RES)
    fine = scene.obstacle_voxel_centres(RES / 2)
    # Walls are surfaces (x4), boxes solids (x8, less at their borders).
    assert 3.5 < len(fine) / len(coarse) < 8.5
    boxes_only = generate_scene(dataclasses.replace(FURNISHED, seed=1, walls=False), body_model)
    ratio = len(boxes_only.obstacle_voxel_centres(RES / 2)) / len(boxes_only.obstacle_voxel_centres(RES))
    assert 4.5 < ratio < 8.5
    # Cached per resolution; callers get copies.
    started = time.perf_counter()
    again = scene.obstacle_voxel_centres(RES)
    assert time.perf_counter() - started < 0.01
    np.testing.assert_array_equal(again, coarse)
    again[:] = 0.0
    np.testing.assert_array_equal(scene.obstacle_voxel_centres(RES), coarse)


def test_a_furnished_room_is_voxelized_quickly(body_model: SMPLXModel) -> None:
    fresh = generate_scene(dataclasses.replace(FURNISHED, seed=2), body_model)
    started = time.perf_counter()
    centres = fresh.obstacle_voxel_centres(0.1)
    assert time.perf_counter() - started < 0.2
    assert len(centres) > 4800  # at least the 16 m x 3 m back wall


@pytest.mark.parametrize("bad", [0.0, -0.1, float("nan"), float("inf"), "coarse", None])
def test_bad_resolution_raises_naming_it(scene, bad) -> None:
    with pytest.raises(SceneError, match=re.escape(repr(bad))):
        scene.obstacle_voxel_centres(bad)


def test_an_obstacle_of_another_shape_is_voxelized_from_its_triangles(scene) -> None:
    # A triangle standing in the plane x = -0.45 (a voxel-centre plane at 0.1 m), on the person's -x side.
    triangle = np.array([[-0.45, 1.02, 0.0], [-0.45, 1.58, 0.0], [-0.45, 1.3, 0.88]])
    new_id = max(scene.object_names) + 1
    extended = dataclasses.replace(
        scene,
        vertices_world=np.concatenate([scene.vertices_world, triangle]),
        faces=np.concatenate([scene.faces, np.array([[0, 1, 2]], dtype=np.int32) + len(scene.vertices_world)]),
        face_object_id=np.concatenate([scene.face_object_id, np.array([new_id], dtype=np.int32)]),
        face_rgb=np.concatenate([scene.face_rgb, np.zeros((1, 3), dtype=np.uint8)]),
        object_names={**scene.object_names, new_id: "triangle"},
    )
    before = _occupied(scene.obstacle_voxel_centres(RES), RES)
    after = _occupied(extended.obstacle_voxel_centres(RES), RES)
    assert before <= after
    added = after - before
    assert added and {i for i, _, _ in added} == {-5}
    for point in _voxel_of(np.concatenate([triangle, triangle.mean(axis=0, keepdims=True)]), RES):
        assert point in after
    # Every added voxel holds part of the triangle: within its y-z outline (bounding box here).
    assert all(10 <= j <= 15 and 0 <= k <= 8 for _, j, k in added)


# ----------------------------------------------------------------------------- the simulator node


def _spin_until(executor, done, timeout_s: float) -> bool:
    deadline = time.monotonic() + timeout_s
    while not done() and time.monotonic() < deadline:
        executor.spin_once(timeout_sec=0.05)
    return done()


@pytest.mark.ros
def test_simulator_node_latches_each_scenes_map_and_publishes_the_frame_pose(scene, side_wall_scene) -> None:
    rclpy = pytest.importorskip("rclpy")
    from geometry_msgs.msg import PoseStamped
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.parameter import Parameter
    from sensor_msgs.msg import PointCloud2

    from leapnbv_common.conversions import pointcloud2_to_xyz, pose_to_numpy, stamp_to_ns
    from leapnbv_common.qos import latched_map_qos, stage_input_qos
    from leapnbv_common.topics import CAMERA_POSE_TOPIC, OBSTACLE_MAP_TOPIC
    from leapnbv_sim.nodes.simulator_node import SimulatorNode

    assert (CAMERA_POSE_TOPIC, OBSTACLE_MAP_TOPIC) == ("/leapnbv/camera_pose", "/leapnbv/obstacle_map")
    # A frame id of this test alone: messages of other simulators on the same ROS domain are ignored.
    world = "obstacle_map_test_%d" % os.getpid()
    context = rclpy.Context()
    rclpy.init(context=context)
    executor = SingleThreadedExecutor(context=context)
    nodes = []
    try:
        sim = SimulatorNode(
            scene=scene,
            context=context,
            parameter_overrides=[Parameter("rate_hz", value=0.0), Parameter("world_frame_id", value=world),
                                 Parameter("obstacle_map_resolution", value=0.2)],
        )
        nodes.append(sim)
        executor.add_node(sim)

        def listener(name: str) -> tuple:
            node = rclpy.create_node(name, context=context)
            nodes.append(node)
            executor.add_node(node)
            maps, poses = [], []
            node.create_subscription(PointCloud2, OBSTACLE_MAP_TOPIC,
                                     lambda m: maps.append(m) if m.header.frame_id == world else None,
                                     latched_map_qos())
            node.create_subscription(PoseStamped, CAMERA_POSE_TOPIC,
                                     lambda m: poses.append(m) if m.header.frame_id == world else None,
                                     stage_input_qos(10))
            return maps, poses

        # Subscribed after the node published the first scene's map: transient-local delivers it.
        early_maps, poses = listener("obstacle_map_test_early")
        assert _spin_until(executor, lambda: len(early_maps) >= 1, 20.0), "the latched map did not arrive"
        expected = scene.obstacle_voxel_centres(0.2)
        assert early_maps[0].width * early_maps[0].height == len(expected)
        np.testing.assert_allclose(pointcloud2_to_xyz(early_maps[0]), expected, atol=1e-6)

        # A published frame's camera pose: world frame, the frame's stamp, T_world_camera.
        stamp_ns, frame = sim.publish_frame(stamp_ns=5_000_000_000)
        assert _spin_until(executor, lambda: len(poses) >= 1, 20.0), "no camera pose arrived"
        assert stamp_to_ns(poses[0].header.stamp) == stamp_ns
        rotation, position = pose_to_numpy(poses[0].pose)
        np.testing.assert_allclose(rotation, frame.camera_pose.rotation, atol=1e-6)
        np.testing.assert_allclose(position, scene.start_camera.position, atol=1e-9)

        # A new scene publishes its own map once; a late subscriber gets only that latest one.
        sim.set_scene(side_wall_scene)
        assert _spin_until(executor, lambda: len(early_maps) >= 2, 20.0), "the second scene's map did not arrive"
        late_maps, _ = listener("obstacle_map_test_late")
        assert _spin_until(executor, lambda: len(late_maps) >= 1, 20.0), "the late subscriber got no map"
        executor.spin_once(timeout_sec=0.3)
        assert len(late_maps) == 1 and len(early_maps) == 2
        assert late_maps[0].width == len(side_wall_scene.obstacle_voxel_centres(0.2)) != len(expected)

        # Parameters (leapnbv_sim.simulator.SimulatorParams): a new map resolution at runtime publishes
        # the map again; the scene's parameters are read-only; values out of range are refused.
        assert sim.params.obstacle_map_resolution == 0.2 and sim.params.rate_hz == 0.0
        assert sim.set_parameters([Parameter("obstacle_map_resolution", value=0.25)])[0].successful
        assert _spin_until(executor, lambda: len(late_maps) >= 2, 20.0), "no map after the resolution change"
        assert late_maps[-1].width == len(side_wall_scene.obstacle_voxel_centres(0.25))
        assert sim.params.obstacle_map_resolution == 0.25
        assert not sim.set_parameters([Parameter("scene_seed", value=5)])[0].successful
        assert not sim.set_parameters([Parameter("obstacle_map_resolution", value=0.0)])[0].successful
        assert sim.params.scene_seed == 0 and sim.params.obstacle_map_resolution == 0.25
    finally:
        for node in nodes:
            executor.remove_node(node)
            node.destroy_node()
        executor.shutdown()
        rclpy.try_shutdown(context=context)
