"""Scene generation, rendering and camera poses (leapnbv_sim.generation, render, poses) on the small stand-in body."""

from __future__ import annotations

import dataclasses
import hashlib
from pathlib import Path

import numpy as np
import pytest

from leapnbv_bags import bag_io
from leapnbv_common import topics
from leapnbv_perception.rotations import axis_angle_to_matrix
from leapnbv_perception.smplx_layer import SMPLXModel
from leapnbv_sim.generation import SceneConfig, generate_scene
from leapnbv_sim.poses import CameraPose, camera_pose_from_base_goal, look_at_pose, pose_in_world
from leapnbv_sim.render import FLOOR_ID, PERSON_ID
from leapnbv_sim.sample_bags import write_scene_bag
from leapnbv_sim.visibility import visible_vertex_mask
from leapnbv_stand_ins.stand_in_body_model import build_stand_in_body_model


@pytest.fixture(scope="module")
def body_model() -> SMPLXModel:
    return SMPLXModel(build_stand_in_body_model("small"), source="stand_in_small")


# A furnished room (the evaluation's benchmark rooms are these): occluders, walls, 2-4 pieces of furniture.
FURNISHED = SceneConfig(clutter_count_range=(2, 4))


@pytest.fixture(scope="module")
def scene(body_model: SMPLXModel):
    return generate_scene(SceneConfig(seed=0), body_model)


def test_same_seed_same_scene_and_frames(body_model: SMPLXModel) -> None:
    a = generate_scene(SceneConfig(seed=11), body_model)
    b = generate_scene(SceneConfig(seed=11), body_model)
    c = generate_scene(SceneConfig(seed=12), body_model)
    fa, fb, fc = a.render(), b.render(), c.render()
    assert fa.rgb.tobytes() == fb.rgb.tobytes()
    assert fa.depth_mm.tobytes() == fb.depth_mm.tobytes()
    assert fa.ground_truth.person_box_xyxy == fb.ground_truth.person_box_xyxy
    assert np.array_equal(fa.ground_truth.vertices_camera, fb.ground_truth.vertices_camera)
    assert np.array_equal(fa.ground_truth.body_params_camera.body_pose, fb.ground_truth.body_params_camera.body_pose)
    assert fa.rgb.tobytes() != fc.rgb.tobytes()
    assert fa.depth_mm.tobytes() != fc.depth_mm.tobytes()
    # The depth noise is drawn per frame index.
    assert a.render(frame_index=1).depth_mm.tobytes() != fa.depth_mm.tobytes()


def _clutter_boxes(scene) -> list:
    """(8,3) world vertices per clutter object of a scene."""
    boxes = []
    for object_id, name in sorted(scene.object_names.items()):
        if name.startswith("clutter"):
            faces = scene.faces[scene.face_object_id == object_id]
            boxes.append(scene.vertices_world[np.unique(faces)])
    return boxes


def _footprint_distance(box: np.ndarray, points_xy: np.ndarray) -> np.ndarray:
    """Horizontal distance of (N,2) points to a box's footprint (0 inside), from its (8,3) vertices."""
    corners = box[box[:, 2] < 1e-9][:, :2]  # the four floor corners
    centre = corners.mean(axis=0)
    order = np.argsort(np.arctan2(corners[:, 1] - centre[1], corners[:, 0] - centre[0]))
    polygon = corners[order]
    distances = np.full(len(points_xy), np.inf)
    inside = np.ones(len(points_xy), dtype=bool)
    for a, b in zip(polygon, np.roll(polygon, -1, axis=0)):
        edge = b - a
        t = np.clip(((points_xy - a) @ edge) / (edge @ edge), 0.0, 1.0)
        distances = np.minimum(distances, np.linalg.norm(points_xy - (a + t[:, None] * edge), axis=1))
        inside &= (edge[0] * (points_xy[:, 1] - a[1]) - edge[1] * (points_xy[:, 0] - a[0])) >= 0
    return np.where(inside, 0.0, distances)


@pytest.mark.parametrize("seed", [0, 5, 101, 202])
def test_clutter_keeps_clear_of_person_camera_and_each_other(body_model: SMPLXModel, seed: int) -> None:
    config = dataclasses.replace(FURNISHED, seed=seed, clutter_count_range=(4, 4))
    scene = generate_scene(config, body_model)
    boxes = _clutter_boxes(scene)
    assert 1 <= len(boxes) <= 4
    clearance = config.clutter_clearance - 1e-9
    body_xy = scene.body_vertices_world[:, :2]
    camera_xy = scene.start_camera.position[None, :2]
    for index, box in enumerate(boxes):
        # Standing on the floor, furniture-sized, around the person.
        assert box[:, 2].min() == pytest.approx(0.0, abs=1e-12)
        assert config.clutter_height_range[0] <= box[:, 2].max() <= config.clutter_height_range[1]
        centre_distance = np.linalg.norm(box[:, :2].mean(axis=0))
        assert config.clutter_distance_range[0] <= centre_distance <= config.clutter_distance_range[1]
        assert _footprint_distance(box, body_xy).min() >= clearance
        assert _footprint_distance(box, camera_xy)[0] >= 0.3 + clearance  # robot radius + gap
        for other in boxes[index + 1:]:
            assert _footprint_distance(box, other[:, :2]).min() >= clearance
            assert _footprint_distance(other, box[:, :2]).min() >= clearance
    # Clutter ids come after the walls; the clutter changes nothing of the start view's occlusion.
    plain = generate_scene(dataclasses.replace(config, clutter_count_range=(0, 0)), body_model)
    assert max(plain.object_names) < min(i for i, n in scene.object_names.items() if n.startswith("clutter"))
    assert scene.start_occluder_share == plain.start_occluder_share
    frame = scene.render()
    assert frame.ground_truth.occluder_share == plain.render().ground_truth.occluder_share


def test_clutter_comes_from_its_own_stream_after_everything_else(body_model: SMPLXModel) -> None:
    plain = generate_scene(SceneConfig(seed=7), body_model)
    furnished = generate_scene(SceneConfig(seed=7, clutter_count_range=(2, 4)), body_model)
    # The same body, camera, occluders and walls, then the clutter appended.
    count = len(plain.vertices_world)
    assert np.array_equal(furnished.vertices_world[:count], plain.vertices_world)
    assert np.array_equal(furnished.faces[: len(plain.faces)], plain.faces)
    assert np.array_equal(furnished.face_rgb[: len(plain.faces)], plain.face_rgb)
    assert {k: v for k, v in furnished.object_names.items() if k in plain.object_names} == plain.object_names
    assert len(furnished.vertices_world) - count == 8 * len(_clutter_boxes(furnished)) >= 16
    np.testing.assert_array_equal(furnished.start_camera.as_matrix(), plain.start_camera.as_matrix())
    # The clutter draw depends on the seed.
    other = generate_scene(SceneConfig(seed=8, clutter_count_range=(2, 4)), body_model)
    assert not np.array_equal(_clutter_boxes(other)[0], _clutter_boxes(furnished)[0])


def _scene_digest(scene, vertices_world: np.ndarray) -> str:
    """Digest of given world vertices with a scene's faces, object ids, names and start occluder share."""
    digest = hashlib.sha256()
    digest.update(np.asarray(vertices_world, dtype=np.float64).tobytes())
    digest.update(scene.faces.astype(np.int32).tobytes())
    digest.update(scene.face_object_id.astype(np.int32).tobytes())
    digest.update(repr(sorted(scene.object_names.items())).encode())
    digest.update(("%.6f" % scene.start_occluder_share).encode())
    return digest.hexdigest()


# The scenes generated before clutter existed (default SceneConfig, small stand-in body): their world
# vertices in whole micrometres (clutter_free_scenes.npz, key seed_<seed>_vertices_um) and digests of
# those vertices (in metres) with the faces, object ids, names and start occluder share. A change here
# means every clutter-free scene, sample bag and golden file changed too (or the stand-in body model /
# rasterizer did).
_CLUTTER_FREE_VERTICES = Path(__file__).with_name("clutter_free_scenes.npz")
_CLUTTER_FREE_DIGESTS = {
    3: "b1fee2af2dd1e7b011664582b503a5b2fda618b42617117e85e5c84bd02d0047",
    11: "6196a9e762c51e95df61e233846bc8639c920f3728675f240c00f4654632dec4",
}
# The body's vertices come out of float32 matrix products whose last bit follows the CPU's BLAS kernel
# (up to 1.2e-7 m apart between kernels), so rounding them to the micrometre flips some near a half
# (a hash of the rounded values is CPU-dependent). The stored micrometres are within 5e-7 m of the
# values; 1e-6 m holds both and still fails any vertex that really moved.
_VERTEX_TOLERANCE_M = 1e-6


@pytest.mark.parametrize("seed", sorted(_CLUTTER_FREE_DIGESTS))
def test_clutter_free_config_reproduces_the_scenes_from_before_clutter(body_model: SMPLXModel, seed: int) -> None:
    assert SceneConfig().clutter_count_range == (0, 0)
    with np.load(_CLUTTER_FREE_VERTICES) as stored:
        reference = stored["seed_%d_vertices_um" % seed] / 1e6
    for config in (SceneConfig(seed=seed), SceneConfig(seed=seed, clutter_count_range=(0, 0))):
        scene = generate_scene(config, body_model)
        assert not any(name.startswith("clutter") for name in scene.object_names.values())
        # Faces, ids, names and share exactly; the stored vertices are those of the digest.
        assert _scene_digest(scene, reference) == _CLUTTER_FREE_DIGESTS[seed]
        assert scene.vertices_world.shape == reference.shape
        np.testing.assert_allclose(scene.vertices_world, reference, rtol=0.0, atol=_VERTEX_TOLERANCE_M)


def test_ground_truth_translation_reproduces_camera_vertices(scene, body_model: SMPLXModel) -> None:
    moved = pose_in_world(
        scene.start_camera, axis_angle_to_matrix(np.array([0.0, 0.6, 0.0])), np.array([1.0, 0.0, 0.5])
    )
    for camera in (scene.start_camera, moved):
        truth = scene.render(camera).ground_truth
        output = body_model.forward(truth.body_params_camera.to_smplx_params())
        reproduced = np.asarray(output.vertices, dtype=np.float64) + truth.translation_camera
        np.testing.assert_allclose(reproduced, truth.vertices_camera, atol=1e-5)
        # And those are the world vertices seen from this camera.
        expected = (scene.body_vertices_world - camera.position) @ camera.rotation
        np.testing.assert_allclose(truth.vertices_camera, expected, atol=1e-9)


def test_body_stands_on_floor_in_front_of_camera(scene) -> None:
    body = scene.body_vertices_world
    assert body[:, 2].min() == pytest.approx(0.0, abs=1e-6)
    assert 1.0 < body[:, 2].max() < 2.2
    in_camera = scene.start_camera.world_to_camera(body)
    assert (in_camera[:, 2] > 1.5).all()
    # No roll: the camera's x axis is horizontal.
    assert abs(scene.start_camera.rotation[2, 0]) < 1e-12


def test_floor_depth_matches_the_plane(body_model: SMPLXModel) -> None:
    config = SceneConfig(seed=1, depth_noise=False)
    scene = generate_scene(config, body_model)
    frame = scene.render()
    rows, columns = np.nonzero(frame.object_id == FLOOR_ID)
    assert rows.size > 10_000
    rays = np.linalg.solve(frame.K, np.stack([columns, rows, np.ones_like(rows)]).astype(np.float64))
    rays_world = scene.start_camera.rotation @ rays  # camera-z = 1 per ray
    depth_plane = -scene.start_camera.position[2] / rays_world[2]
    np.testing.assert_allclose(frame.depth_m[rows, columns], depth_plane, atol=1e-3)
    np.testing.assert_allclose(frame.depth_clean_m[rows, columns], depth_plane, rtol=1e-5)
    assert np.array_equal(frame.depth_mm, np.rint(frame.depth_clean_m.astype(np.float64) * 1000).astype(np.uint16))


def test_noise_keeps_depth_close(scene) -> None:
    frame = scene.render()
    both = (frame.depth_m > 0) & (frame.depth_clean_m > 0)
    error = frame.depth_m[both] - frame.depth_clean_m[both]
    assert 0.0 < np.std(error) < 0.05
    assert np.count_nonzero(frame.depth_m == 0) > np.count_nonzero(frame.depth_clean_m == 0)


def test_person_box_contains_visible_person_pixels(scene) -> None:
    frame = scene.render()
    x0, y0, x1, y1 = frame.ground_truth.person_box_xyxy
    rows, columns = np.nonzero(frame.object_id == PERSON_ID)
    assert rows.size == frame.ground_truth.person_pixel_count > 0
    assert columns.min() == x0 and columns.max() == x1 - 1
    assert rows.min() == y0 and rows.max() == y1 - 1
    # Looking away: no person, no box.
    away = look_at_pose(scene.start_camera.position, scene.start_camera.position + np.array([-1.0, 0.0, 0.0]))
    assert scene.render(away).ground_truth.person_box_xyxy is None


def test_visible_share_of_the_body_drops_when_occluded(scene) -> None:
    camera = scene.start_camera
    truth = scene.render(camera).ground_truth
    unoccluded_depth, _ = scene.render_depth(camera, include=np.array([FLOOR_ID, PERSON_ID]))
    occluded_depth, _ = scene.render_depth(camera)
    clear = visible_vertex_mask(truth.vertices_camera, unoccluded_depth, scene.K).mean()
    hidden = visible_vertex_mask(truth.vertices_camera, occluded_depth, scene.K).mean()
    # A body sees roughly its front half; the occluders then hide start_occluder_share of it.
    assert clear > 0.35
    assert hidden == pytest.approx(clear * (1.0 - scene.start_occluder_share), abs=0.02)
    assert hidden < clear - 0.05
    assert truth.occlusion_share == pytest.approx(1.0 - hidden)


def test_pose_in_world_composes_transforms(scene) -> None:
    start = scene.start_camera
    same = pose_in_world(start, np.eye(3), np.zeros(3))
    np.testing.assert_allclose(same.as_matrix(), start.as_matrix())
    R_on = axis_angle_to_matrix(np.array([0.1, -0.4, 0.2]))
    p_on = np.array([0.3, -0.2, 1.0])
    moved = pose_in_world(start, R_on, p_on)
    np.testing.assert_allclose(moved.as_matrix(), start.as_matrix() @ CameraPose(R_on, p_on).as_matrix())
    # A point fixed in the world maps consistently through both frames.
    point = np.array([[0.2, 0.1, 1.0]])
    in_start = start.world_to_camera(point)[0]
    np.testing.assert_allclose(moved.world_to_camera(point)[0], R_on.T @ (in_start - p_on), atol=1e-12)


def test_camera_pose_from_base_goal_is_level_above_base() -> None:
    pose = camera_pose_from_base_goal(np.array([1.0, 2.0]), np.pi / 2, 1.2)
    np.testing.assert_allclose(pose.position, [1.0, 2.0, 1.2])
    np.testing.assert_allclose(pose.rotation[:, 2], [0.0, 1.0, 0.0], atol=1e-12)  # forward = +y
    np.testing.assert_allclose(pose.rotation[:, 1], [0.0, 0.0, -1.0], atol=1e-12)  # down


def test_rendered_frames_round_trip_through_a_bag(scene, tmp_path: Path) -> None:
    frames = [scene.render(frame_index=i) for i in range(2)]
    path = tmp_path / "scene"
    write_scene_bag(path, frames, body_model_id=scene.body_model_id)
    truths = [m for t, _, _, m in bag_io.read_bag(path, topics=[topics.GROUND_TRUTH_TOPIC])]
    depths = [m for t, _, _, m in bag_io.read_bag(path, topics=[topics.DEPTH_IMAGE_TOPIC])]
    assert len(truths) == 2
    expected = frames[0].ground_truth
    np.testing.assert_allclose(truths[0].root_pose, expected.body_params_camera.root_pose, atol=1e-6)
    np.testing.assert_allclose(truths[0].translation, expected.translation_camera, atol=1e-6)
    assert truths[0].person_box.x_min == expected.person_box_xyxy[0]
    assert bytes(depths[1].data) == frames[1].depth_mm.tobytes()
    assert bag_io.validate_bag_crcs(path)[topics.GROUND_TRUTH_TOPIC] == 2


def test_configs_are_plain_dataclasses() -> None:
    config = dataclasses.replace(SceneConfig(), seed=5, walls=False)
    assert config.seed == 5 and not config.walls
    np.testing.assert_allclose(config.K, [[615.0, 0, 320.0], [0, 615.0, 240.0], [0, 0, 1]])


@pytest.mark.parametrize("layout, walls", [("corridor", {"wall_side", "wall_side_2"}),
                                           ("corner", {"wall_back", "wall_side"}), ("near_wall", {"wall_back"})])
def test_room_layouts_put_their_walls_round_the_person_and_keep_the_rest(layout, walls, body_model):
    config = SceneConfig(seed=4)
    default = generate_scene(config, body_model)
    scene = generate_scene(dataclasses.replace(config, room_layout=layout), body_model)
    names = set(scene.object_names.values())
    assert walls <= names and not ({"wall_back", "wall_side", "wall_side_2"} - walls) & names
    # The rest of the scene (camera, body) is the default layout's.
    np.testing.assert_array_equal(scene.start_camera.position, default.start_camera.position)
    np.testing.assert_array_equal(scene.body_vertices_world, default.body_vertices_world)
    camera_xy = scene.start_camera.position[:2]
    ids = {name: object_id for object_id, name in scene.object_names.items()}
    for name in walls:
        vertices = scene.vertices_world[np.unique(scene.faces[scene.face_object_id == ids[name]])]
        x, y = vertices[:, 0], vertices[:, 1]  # noqa: F841
        if np.ptp(y) < 1e-9:  # a wall along x at this y: the person (y = 0) and the camera are on one side
            assert np.sign(y[0]) == np.sign(y[0] - camera_xy[1]) and 0.6 <= abs(y[0]) <= 1.5, name
        else:  # a back wall at this x, behind the person (x = 0)
            assert 0.4 <= x[0] <= 1.0, name
