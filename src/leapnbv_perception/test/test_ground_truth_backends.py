"""The ground-truth backends with several people: every visible person's box, the mesh of the person in the box."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

pytest.importorskip("rclpy")  # the backends read ROS messages: not among the ROS-free cores

from leapnbv_common.contracts import ContractError  # noqa: E402
from leapnbv_common.conversions import (  # noqa: E402
    SceneGroundTruthArrays,
    ScenePersonArrays,
    arrays_to_scene_ground_truth,
    arrays_to_scene_people,
    header_with_stamp,
    make_camera_info,
    scene_ground_truth_to_arrays,
    scene_people_to_arrays,
)
from leapnbv_common.conversions.base import ConversionError  # noqa: E402
from leapnbv_common.procrustes import pa_mpvpe_mm  # noqa: E402
from leapnbv_common.topics import SCENE_PEOPLE  # noqa: E402
from leapnbv_msgs.msg import PersonDetections  # noqa: E402
from leapnbv_perception.backends.ground_truth import (  # noqa: E402
    GroundTruthMeshBackend,
    ground_truth_boxes,
    matched_person,
)
from leapnbv_perception.smplx_layer import SMPLXModel, SMPLXParams  # noqa: E402
from leapnbv_perception.truth_corruption import MeshCorruption  # noqa: E402
from leapnbv_stand_ins.stand_in_body_model import build_stand_in_body_model  # noqa: E402

rng = np.random.default_rng(3)
K = np.array([[615.0, 0.0, 320.0], [0.0, 615.0, 240.0], [0.0, 0.0, 1.0]])
HEADER = header_with_stamp(1_700_000_000_000_000_000, "camera_color_optical_frame")


def _other(object_id, box, z):
    return ScenePersonArrays(object_id=object_id, person_box=np.array(box, np.float64),
                             root_pose=np.array([np.pi, 0.0, 0.0]) + rng.normal(0, 0.1, 3),
                             body_pose=rng.normal(0, 0.05, 63), betas=rng.normal(0, 0.5, 10),
                             translation=np.array([rng.normal(0, 0.3), 0.3, z]), occlusion_share=0.25)


def _truth(target_box, others):
    return SceneGroundTruthArrays(
        person_box=np.array(target_box, np.float64), root_pose=np.array([np.pi, 0.0, 0.0]),
        body_pose=rng.normal(0, 0.05, 63), left_hand_pose=rng.normal(0, 0.1, 45),
        right_hand_pose=rng.normal(0, 0.1, 45), jaw_pose=np.zeros(3), betas=rng.normal(0, 0.5, 10),
        expression=np.zeros(10), translation=np.array([0.0, 0.3, 3.0]), occlusion_share=0.4,
        body_model_id="stand_in_small", others=others)


def _through_the_message(truth):
    """The truth as the backends get it: the target on SceneGroundTruth, the others on ScenePeople."""
    people = scene_people_to_arrays(arrays_to_scene_people(truth.others, HEADER))
    return scene_ground_truth_to_arrays(arrays_to_scene_ground_truth(truth, HEADER), people)


def test_every_visible_person_is_a_box_largest_first():
    # Target 100x200 (area 20000); a bigger bystander 150x200 to its right; a small one left; one out of view.
    truth = _through_the_message(_truth([200, 100, 300, 300, 1], [
        _other(7, [400, 80, 550, 280, 1], 2.5), _other(8, [10, 150, 60, 250, 1], 4.0),
        _other(9, [0, 0, 0, 0, 0], 5.0)]))
    boxes = ground_truth_boxes(truth, (640, 480))
    np.testing.assert_array_equal(boxes, np.array([[400, 80, 550, 280, 1], [200, 100, 300, 300, 1],
                                                   [10, 150, 60, 250, 1]], np.float32))
    # Equal areas: the leftmost first, whoever the target is.
    tie = _through_the_message(_truth([300, 100, 400, 300, 1], [_other(4, [100, 100, 200, 300, 1], 3.0)]))
    assert ground_truth_boxes(tie, (640, 480))[:, 0].tolist() == [100.0, 300.0]
    # Nobody in view: no box; only another person in view: its box.
    assert ground_truth_boxes(_truth([0, 0, 0, 0, 0], []), (640, 480)).shape == (0, 5)
    only = ground_truth_boxes(_truth([0, 0, 0, 0, 0], [_other(3, [5, 6, 50, 60, 1], 3.0)]), (640, 480))
    np.testing.assert_array_equal(only, [[5, 6, 50, 60, 1]])
    # A box outside this image is a truth of another image.
    with pytest.raises(ContractError, match="outside"):
        ground_truth_boxes(_truth([200, 100, 300, 300, 1], [_other(3, [700, 6, 750, 60, 1], 3.0)]), (640, 480))


def test_the_matched_person_is_the_one_whose_box_overlaps_most():
    bystander, passer_by = _other(7, [400, 80, 550, 280, 1], 2.5), _other(8, [250, 90, 330, 300, 1], 2.0)
    truth = _truth([200, 100, 300, 300, 1], [bystander, passer_by])
    assert matched_person(truth, np.array([205, 100, 300, 295, 1.0])) is None  # the target
    assert matched_person(truth, np.array([405, 85, 545, 280, 1.0])) is bystander
    assert matched_person(truth, np.array([260, 90, 335, 300, 1.0])) is passer_by
    # Overlapping nobody: the nearest box centre (a box between them, nearer the bystander's).
    assert matched_person(truth, np.array([560, 300, 600, 400, 1.0])) is bystander
    # Nobody visible: the target (no mesh is right then).
    assert matched_person(_truth([0, 0, 0, 0, 0], []), np.array([1, 1, 9, 9, 1.0])) is None


class _Frame(dict):
    """The stage frame the mesh backend reads: the truth, the camera_info and the detections (its key)."""

    def __init__(self, truth):
        super().__init__({"ground_truth": dataclasses.replace(truth, others=[]), SCENE_PEOPLE: truth.others,
                          "camera_info": make_camera_info(K, 640, 480, HEADER)})
        self.key = type("Key", (), {"message": PersonDetections(header=HEADER, image_width=640, image_height=480)})
        self.stamp_ns = 1_700_000_000_000_000_000


def test_the_mesh_is_the_matched_persons():
    model = SMPLXModel(build_stand_in_body_model("small"), source="stand_in_small")
    bystander = _other(7, [400, 80, 550, 280, 1], 2.5)
    truth = _through_the_message(_truth([200, 100, 300, 300, 1], [bystander]))
    frame = _Frame(truth)
    on_bystander = GroundTruthMeshBackend.mesh(model, frame, np.array([400, 80, 550, 280, 1], np.float32), 1.2)
    person = truth.others[0]
    zeros = np.zeros
    expected = model.forward(SMPLXParams.from_axis_angle(person.root_pose, person.body_pose, zeros(45), zeros(45),
                                                         zeros(3), person.betas, zeros(10))).vertices
    np.testing.assert_allclose(on_bystander.vertices, expected + person.translation, atol=1e-6)
    np.testing.assert_array_equal(on_bystander.cam_translation, person.translation)
    assert not np.any(on_bystander.left_hand_pose) and on_bystander.model_id == "ground_truth"
    on_target = GroundTruthMeshBackend.mesh(model, frame, np.array([200, 100, 300, 300, 1], np.float32), 1.2)
    np.testing.assert_array_equal(on_target.left_hand_pose, truth.left_hand_pose)
    np.testing.assert_array_equal(on_target.cam_translation, truth.translation)
    assert float(np.linalg.norm(on_target.vertices.mean(axis=0) - on_bystander.vertices.mean(axis=0))) > 0.3


def test_the_others_round_trip_and_are_checked():
    truth = _truth([200, 100, 300, 300, 1], [_other(7, [400, 80, 550, 280, 1], 2.5), _other(9, [0, 0, 0, 0, 0], 5.0)])
    back = _through_the_message(truth)
    assert [p.object_id for p in back.others] == [7, 9]
    for mine, theirs in zip(back.others, truth.others):
        for name in ("person_box", "root_pose", "body_pose", "betas", "translation"):
            np.testing.assert_allclose(getattr(mine, name), np.asarray(getattr(theirs, name), np.float32))
        assert mine.occlusion_share == pytest.approx(0.25)
    assert _through_the_message(_truth([200, 100, 300, 300, 1], [])).others == []
    # The target's message carries no one else (its layout is the one recorded bags have).
    assert "others" not in arrays_to_scene_ground_truth(truth, HEADER).get_fields_and_field_types()
    assert scene_ground_truth_to_arrays(arrays_to_scene_ground_truth(truth, HEADER)).others == []
    for bad, message in ((dict(object_id=1), "the target's"), (dict(object_id=-2), "negative"),
                         (dict(occlusion_share=1.5), "outside"), (dict(person_box=np.array([9, 9, 5, 5, 1.0])),
                                                                 "inverted")):
        person = _other(7, [400, 80, 550, 280, 1], 2.5)
        for name, value in bad.items():
            setattr(person, name, value)
        with pytest.raises(ConversionError, match=message):
            _through_the_message(_truth([200, 100, 300, 300, 1], [person]))
    twice = _truth([200, 100, 300, 300, 1], [_other(7, [400, 80, 550, 280, 1], 2.5), _other(7, [9, 9, 50, 50, 1], 3)])
    with pytest.raises(ConversionError, match="twice"):
        _through_the_message(twice)
    nan = _other(7, [400, 80, 550, 280, 1], 2.5)
    nan.translation = np.array([0.0, np.nan, 2.0])
    with pytest.raises(ConversionError, match="non-finite"):
        _through_the_message(_truth([200, 100, 300, 300, 1], [nan]))


def test_a_corrupted_truth_mesh_is_as_far_off_as_asked_and_the_same_in_every_run():
    """The error budget's mesh: PA-MPVPE, depth and placement errors of the asked size, seeded by the stamp."""
    model = SMPLXModel(build_stand_in_body_model("small"), source="stand_in_small")
    truth = _through_the_message(_truth([200, 100, 300, 300, 1], []))
    frame = _Frame(truth)
    box = np.array([200, 100, 300, 300, 1], np.float32)
    clean = GroundTruthMeshBackend.mesh(model, frame, box, 1.2)
    asked = MeshCorruption(shift=0.2, depth=0.25, pa_mpvpe_mm=60.0, seed=4)
    worse = GroundTruthMeshBackend.mesh(model, frame, box, 1.2, asked)
    assert pa_mpvpe_mm(worse.vertices, clean.vertices) == pytest.approx(60.0, abs=1.5)
    assert np.any(worse.body_pose != clean.body_pose) and np.any(worse.betas != clean.betas)
    depth_ratio = float(worse.vertices[:, 2].mean() / clean.vertices[:, 2].mean())
    assert depth_ratio == pytest.approx(1.25, abs=0.01) or depth_ratio == pytest.approx(0.75, abs=0.01)
    again = GroundTruthMeshBackend.mesh(model, frame, box, 1.2, asked)
    np.testing.assert_array_equal(again.vertices, worse.vertices)
    frame.stamp_ns += 1  # another frame: other draws
    assert not np.array_equal(GroundTruthMeshBackend.mesh(model, frame, box, 1.2, asked).vertices, worse.vertices)
