"""Scenes with several people and a walking target (leapnbv_sim.people, generation, Scene.at_time, the ground truth)."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest

from leapnbv_common.conversions import header_with_stamp, scene_ground_truth_to_arrays, scene_people_to_arrays
from leapnbv_common.topics import SCENE_PEOPLE
from leapnbv_perception.smplx_layer import SMPLXModel
from leapnbv_sim.frame_messages import scene_ground_truth_msg, scene_people_msg
from leapnbv_sim.generation import SceneConfig, generate_scene
from leapnbv_sim.people import ROLE_BYSTANDER, ROLE_PASSER_BY, body_radius, pelvis_xy
from leapnbv_sim.poses import look_at_pose
from leapnbv_sim.render import PERSON_ID
from leapnbv_sim.scene import SceneError
from leapnbv_stand_ins.stand_in_body_model import build_stand_in_body_model

FURNISHED = SceneConfig(clutter_count_range=(2, 4))
TWO = dataclasses.replace(FURNISHED, bystanders=1)
THREE = dataclasses.replace(FURNISHED, bystanders=1, passers_by=1)
WALKING = dataclasses.replace(FURNISHED, target_motion="walk")
SEEDS = list(range(12))


@pytest.fixture(scope="module")
def body_model() -> SMPLXModel:
    return SMPLXModel(build_stand_in_body_model("small"), source="stand_in_small")


def _scene(config, seed, body_model):
    """The scene of a seed, or None when the config gives none there (a seed the family leaves out)."""
    try:
        return generate_scene(dataclasses.replace(config, seed=seed), body_model)
    except SceneError:
        return None


@pytest.fixture(scope="module")
def three_people(body_model):
    scenes = {seed: _scene(THREE, seed, body_model) for seed in SEEDS}
    return {seed: scene for seed, scene in scenes.items() if scene is not None}


@pytest.fixture(scope="module")
def walking(body_model):
    scenes = {seed: _scene(WALKING, seed, body_model) for seed in range(24)}
    return {seed: scene for seed, scene in scenes.items() if scene is not None}


def _person(scene, role):
    return next(person for person in scene.others if person.role == role)


def test_other_people_come_last_and_every_other_id_stays(three_people, body_model) -> None:
    # Where the occluders leave no free crossing the seed gives no scene (a family skips it); most do.
    assert len(three_people) >= 4
    for seed, scene in three_people.items():
        plain = generate_scene(dataclasses.replace(FURNISHED, seed=seed), body_model)
        count, faces = len(plain.vertices_world), len(plain.faces)
        # The one-person scene of the seed, untouched, then the people appended.
        assert np.array_equal(scene.vertices_world[:count], plain.vertices_world)
        assert np.array_equal(scene.faces[:faces], plain.faces)
        assert np.array_equal(scene.face_object_id[:faces], plain.face_object_id)
        assert np.array_equal(scene.face_rgb[:faces], plain.face_rgb)
        assert {k: v for k, v in scene.object_names.items() if k in plain.object_names} == plain.object_names
        last = max(plain.object_names)
        assert scene.object_names[last + 1] == "person_bystander"
        assert scene.object_names[last + 2] == "person_passer_by"
        assert [p.object_id for p in scene.others] == [last + 1, last + 2]
        assert scene.people[0].object_id == PERSON_ID and scene.object_names[PERSON_ID] == "person"
        # They keep off the start view's line of sight: the start view hides as much of the target.
        assert scene.start_occluder_share == plain.start_occluder_share
        assert scene.render().ground_truth.occluder_share == plain.render().ground_truth.occluder_share
        np.testing.assert_array_equal(scene.start_camera.as_matrix(), plain.start_camera.as_matrix())
        assert scene.moving_person_ids == [last + 2]


def test_the_bystander_is_an_obstacle_the_passer_by_is_not(three_people, body_model) -> None:
    seed, scene = next(iter(three_people.items()))
    plain = generate_scene(dataclasses.replace(FURNISHED, seed=seed), body_model)
    ours = {tuple(v) for v in np.round(scene.obstacle_voxel_centres(0.1), 6)}
    before = {tuple(v) for v in np.round(plain.obstacle_voxel_centres(0.1), 6)}
    added = np.array(sorted(ours - before))
    assert before <= ours and len(added) > 10
    bystander, passer_by = _person(scene, ROLE_BYSTANDER), _person(scene, ROLE_PASSER_BY)
    # Every added voxel is the bystander's (within a voxel of its body); none is where the passer-by walks.
    near = np.linalg.norm(added[:, :2] - pelvis_xy(bystander.body), axis=1)
    assert np.all(near <= body_radius(bystander.body) + 0.1)
    walk = np.array([passer_by.motion.at(t)[0] for t in np.linspace(0.0, passer_by.motion.duration_s, 50)])
    assert np.min(np.linalg.norm(added[:, None, :2] - walk[None], axis=2)) > 0.2
    # A scene at a later time has the same map.
    np.testing.assert_array_equal(scene.at_time(2.0).obstacle_voxel_centres(0.1), scene.obstacle_voxel_centres(0.1))


def test_the_bystander_stands_near_the_target_in_the_start_view(three_people) -> None:
    seen = 0
    for scene in three_people.values():
        bystander = _person(scene, ROLE_BYSTANDER)
        assert bystander.motion is None
        xy = pelvis_xy(bystander.body)
        assert 0.6 <= float(np.linalg.norm(xy)) <= 1.5
        to_camera = scene.start_camera.position[:2] / np.linalg.norm(scene.start_camera.position[:2])
        angle = math.degrees(math.acos(float(np.clip(xy @ to_camera / np.linalg.norm(xy), -1.0, 1.0))))
        assert 35.0 - 1e-6 <= angle <= 160.0 + 1e-6
        # On the floor, apart from the target.
        assert abs(float(bystander.body.vertices_world[:, 2].min())) < 1e-9
        frame = scene.render()
        truth = {other.object_id: other for other in frame.ground_truth.others}
        mine = truth[bystander.object_id]
        pixels = frame.object_id == bystander.object_id
        assert mine.pixel_count == int(np.count_nonzero(pixels))
        if mine.pixel_count:
            rows, columns = np.nonzero(pixels)
            assert mine.box_xyxy == (columns.min(), rows.min(), columns.max() + 1, rows.max() + 1)
            seen += 1
    assert seen >= len(three_people) - 1  # in the start view (hidden at most where furniture stands in front)


def test_the_passer_by_walks_across_the_line_of_sight(three_people) -> None:
    for scene in three_people.values():
        passer_by = _person(scene, ROLE_PASSER_BY)
        motion = passer_by.motion
        assert 0.5 <= motion.max_speed_m_s <= 1.0 and motion.max_turn_rate_rad_s == 0.0
        camera_xy = scene.start_camera.position[:2]
        normal = np.array([-camera_xy[1], camera_xy[0]]) / np.linalg.norm(camera_xy)
        times = np.arange(0.0, motion.duration_s + 1e-9, 0.02)
        side = np.array([motion.at(t)[0] @ normal for t in times])
        crossing = int(np.nonzero(np.sign(side[1:]) != np.sign(side[:-1]))[0][0]) + 1
        t_cross = float(times[crossing])
        assert 1.0 - 0.05 <= t_cross <= 3.0 + 0.05
        along = float(motion.at(t_cross)[0] @ camera_xy) / float(camera_xy @ camera_xy)
        assert 0.15 - 0.05 <= along <= 0.85 + 0.05  # between the target and the robot
        # Crossing, it hides more of the target from the start camera than at time 0.
        start = scene.render().ground_truth
        crossed = scene.at_time(t_cross).render().ground_truth
        assert crossed.occluder_share > start.occluder_share + 0.05
        assert crossed.person_pixel_count < start.person_pixel_count


def test_at_time_moves_the_people_rigidly_and_keeps_the_rest(three_people, body_model) -> None:
    scene = next(iter(three_people.values()))
    passer_by = _person(scene, ROLE_PASSER_BY)
    assert scene.at_time(0.0).vertices_world.tobytes() == scene.vertices_world.tobytes()
    later = scene.at_time(1.5)
    assert later.elapsed_s == 1.5 and scene.elapsed_s == 0.0
    moved = passer_by.vertex_slice
    still = np.ones(len(scene.vertices_world), bool)
    still[moved] = False
    np.testing.assert_array_equal(later.vertices_world[still], scene.vertices_world[still])
    offset = later.vertices_world[moved] - scene.vertices_world[moved]
    # A walk: one shift for every vertex, on the floor, 1.5 s at the passer-by's speed.
    np.testing.assert_allclose(offset, np.broadcast_to(offset[0], offset.shape), atol=1e-12)
    assert offset[0, 2] == 0.0
    assert float(np.linalg.norm(offset[0])) == pytest.approx(1.5 * passer_by.motion.max_speed_m_s, rel=1e-9)
    # From the scene's time 0, whichever scene of it is asked.
    np.testing.assert_array_equal(later.at_time(0.4).vertices_world, scene.at_time(0.4).vertices_world)
    # The ground truth places the moved person's body model where it was rendered.
    frame = later.render()
    other = next(o for o in frame.ground_truth.others if o.object_id == passer_by.object_id)
    vertices = body_model.forward(other.body_params_camera.to_smplx_params()).vertices + other.translation_camera
    np.testing.assert_allclose(vertices, frame.camera_pose.world_to_camera(later.vertices_world[moved]), atol=2e-5)
    assert frame.scene_time_s == 1.5


def test_a_standing_scene_is_itself_at_every_time(body_model) -> None:
    scene = generate_scene(dataclasses.replace(TWO, seed=3), body_model)
    assert scene.at_time(5.0) is scene and scene.moving_person_ids == []


def test_the_same_seed_gives_the_same_people(three_people, body_model) -> None:
    seed, scene = next(iter(three_people.items()))
    again = generate_scene(dataclasses.replace(THREE, seed=seed), body_model)
    assert again.vertices_world.tobytes() == scene.vertices_world.tobytes()
    assert again.at_time(2.0).render().rgb.tobytes() == scene.at_time(2.0).render().rgb.tobytes()
    other_seed, other = [(s, x) for s, x in three_people.items() if s != seed][0]
    assert not np.allclose(pelvis_xy(_person(other, ROLE_BYSTANDER).body),
                           pelvis_xy(_person(scene, ROLE_BYSTANDER).body))


def test_the_walking_target_walks_slowly_or_turns(walking) -> None:
    kinds = set()
    for scene in walking.values():
        motion = scene.target_motion
        assert motion is not None and scene.moving_person_ids == [PERSON_ID]
        assert motion.max_speed_m_s <= 0.5 + 1e-12 and motion.max_turn_rate_rad_s <= 1.0 + 1e-12
        times = np.arange(0.0, motion.duration_s + 0.5, 0.05)
        xy = np.array([motion.at(t)[0] for t in times])
        step = np.linalg.norm(np.diff(xy, axis=0), axis=1) / 0.05
        assert np.all(step <= 0.5 + 1e-9)
        walked = float(np.linalg.norm(xy[-1] - xy[0]))
        turned = abs(motion.heading_rad[-1] - motion.heading_rad[0])
        if walked > 0:
            kinds.add("walk")
            assert 0.8 - 1e-9 <= walked <= 2.0 + 1e-9
            # It faces the way it walks, and keeps clear of the robot's start.
            heading = motion.heading_rad[-1]
            facing = np.array([-math.cos(heading), -math.sin(heading)])
            assert facing @ (xy[-1] - xy[0]) / walked == pytest.approx(1.0, abs=1e-9)
            gap = np.min(np.linalg.norm(xy - scene.start_camera.position[:2], axis=1))
            assert gap >= 0.3 + body_radius(scene.people[0].start_body)
        else:
            kinds.add("turn")
            assert math.radians(60) - 1e-9 <= turned <= math.radians(150) + 1e-9
        end = scene.at_time(motion.duration_s + 1.0)
        # The target's fields are its body then: its centre followed its pelvis, and it still stands on the floor.
        np.testing.assert_allclose(end.body_centre_world[:2] - scene.body_centre_world[:2], xy[-1] - xy[0],
                                   atol=0.35)
        assert abs(float(end.body_vertices_world[:, 2].min())) < 1e-9
    assert kinds == {"walk", "turn"}


def test_a_turned_target_is_reshaded_and_its_truth_follows(walking, body_model) -> None:
    scene = next(s for s in walking.values() if s.target_motion.heading_rad[-1] != s.target_motion.heading_rad[0])
    end = scene.at_time(scene.target_motion.duration_s)
    target = scene.people[0]
    assert not np.array_equal(end.face_rgb[target.face_slice], scene.face_rgb[target.face_slice])
    camera = look_at_pose(np.array([-2.5, 0.5, 1.2]), end.body_centre_world)
    frame = end.render(camera)
    truth = frame.ground_truth
    vertices = body_model.forward(truth.body_params_camera.to_smplx_params()).vertices + truth.translation_camera
    np.testing.assert_allclose(vertices, truth.vertices_camera, atol=2e-5)
    np.testing.assert_allclose(truth.vertices_camera, camera.world_to_camera(end.body_vertices_world), atol=1e-12)


def test_one_person_scenes_have_no_others_in_their_truth(body_model) -> None:
    frame = generate_scene(dataclasses.replace(FURNISHED, seed=2), body_model).render()
    assert frame.ground_truth.others == [] and frame.scene_time_s == 0.0
    assert list(scene_people_msg(header_with_stamp(10, "cam"), frame).people) == []


def test_the_ground_truth_message_lists_every_other_person(three_people, body_model) -> None:
    from leapnbv_common.conversions import make_camera_info
    from leapnbv_msgs.msg import PersonDetections
    from leapnbv_perception.backends.ground_truth import GroundTruthMeshBackend, ground_truth_boxes

    for scene in three_people.values():
        passer_by = _person(scene, ROLE_PASSER_BY)
        frame = scene.at_time(1.0).render()
        both = [o for o in frame.ground_truth.others if o.box_xyxy is not None]
        if frame.ground_truth.person_box_xyxy is not None and len(both) == 2:
            break
    else:
        pytest.fail("no scene shows all three people at 1 s")
    header = header_with_stamp(1_000, "cam")
    truth = scene_ground_truth_to_arrays(scene_ground_truth_msg(header, frame, "stand_in_small"),
                                         scene_people_to_arrays(scene_people_msg(header, frame)))
    assert [p.object_id for p in truth.others] == [o.object_id for o in scene.others]
    for person, rendered in zip(truth.others, frame.ground_truth.others):
        np.testing.assert_array_equal(person.person_box, np.array(list(rendered.box_xyxy) + [1.0], np.float32))
        assert person.occlusion_share == pytest.approx(rendered.occlusion_share, abs=1e-6)
    # The detector backend: all three boxes, largest first.
    boxes = ground_truth_boxes(truth, (640, 480))
    assert len(boxes) == 3 and np.all(boxes[:, 4] == 1.0)
    areas = (boxes[:, 2] - boxes[:, 0]) * (boxes[:, 3] - boxes[:, 1])
    assert np.all(np.diff(areas) <= 0)
    # The mesh backend: the mesh of the person in the box it is given.

    class _Frame(dict):
        key = type("Key", (), {"message": PersonDetections(header=header, image_width=640, image_height=480)})

    stub = _Frame({"ground_truth": truth, SCENE_PEOPLE: truth.others,
                   "camera_info": make_camera_info(frame.K, 640, 480, header)})
    for person in [None] + list(scene.others):
        if person is None:
            box, vertices = frame.ground_truth.person_box_xyxy, frame.ground_truth.vertices_camera
        else:
            box = next(o.box_xyxy for o in frame.ground_truth.others if o.object_id == person.object_id)
            vertices = frame.camera_pose.world_to_camera(scene.at_time(1.0).vertices_world[person.vertex_slice])
        mesh = GroundTruthMeshBackend.mesh(body_model, stub, np.array(list(box) + [1.0], np.float32), 1.2)
        np.testing.assert_allclose(mesh.vertices, vertices, atol=1e-4)
    assert passer_by.object_id in [p.object_id for p in truth.others]


# The one-person scenes as they were before other people existed (furnished seed 3 and corridor seed 5,
# small stand-in body): world vertices in micrometres and the start view's render (object ids, depth in
# mm, colours), one_person_scenes.npz. The body's vertices follow the CPU's float32 BLAS kernel in their
# last bit (test_sim_scene: up to 1.2e-7 m), which may move a handful of edge pixels on another CPU; on the
# machine that stored them the render is byte-identical.
_ONE_PERSON = Path(__file__).with_name("one_person_scenes.npz")
_ONE_PERSON_CONFIGS = {"furnished_3": dataclasses.replace(FURNISHED, seed=3),
                       "corridor_5": SceneConfig(seed=5, room_layout="corridor")}


@pytest.mark.parametrize("name", sorted(_ONE_PERSON_CONFIGS))
def test_one_person_scenes_are_as_they_were(name, body_model) -> None:
    scene = generate_scene(_ONE_PERSON_CONFIGS[name], body_model)
    frame = scene.render()
    with np.load(_ONE_PERSON) as stored:
        vertices = stored[name + "_vertices_um"] / 1e6
        faces, ids = stored[name + "_faces"], stored[name + "_face_ids"]
        object_id, depth_mm, rgb = stored[name + "_object_id"], stored[name + "_depth_mm"], stored[name + "_rgb"]
        names = str(stored[name + "_names"])
        share = float(stored[name + "_share"])
    assert scene.vertices_world.shape == vertices.shape
    np.testing.assert_allclose(scene.vertices_world, vertices, rtol=0.0, atol=1e-6)
    np.testing.assert_array_equal(scene.faces, faces)
    np.testing.assert_array_equal(scene.face_object_id, ids)
    assert repr(sorted(scene.object_names.items())) == names
    assert scene.start_occluder_share == pytest.approx(share, abs=1e-12)
    assert int(np.count_nonzero(frame.object_id != object_id)) <= 20
    assert int(np.count_nonzero(np.abs(frame.depth_mm.astype(np.int32) - depth_mm) > 1)) <= 20
    assert int(np.count_nonzero(np.any(frame.rgb != rgb, axis=2))) <= 40
