"""The error budget's corruptions of the truth (leapnbv_perception.truth_corruption): sizes as asked, seeded."""
from __future__ import annotations

import numpy as np
import pytest

from leapnbv_common.procrustes import pa_mpvpe_mm
from leapnbv_perception.smplx_layer import SMPLXModel, SMPLXParams
from leapnbv_perception.truth_corruption import (
    BoxCorruption,
    corrupted_boxes,
    displaced_mesh,
    frame_rng,
    noisy_pose_and_shape,
)
from leapnbv_stand_ins.stand_in_body_model import build_stand_in_body_model

K = np.array([[615.0, 0.0, 320.0], [0.0, 615.0, 240.0], [0.0, 0.0, 1.0]])
BOX = np.array([250.0, 100.0, 370.0, 420.0, 0.9])


def _project(points):
    return (points[:, :2] / points[:, 2:3]) * np.diag(K)[:2] + K[:2, 2]


def _body():
    rng = np.random.default_rng(0)
    return rng.normal(0.0, 0.3, (500, 3)) * [0.25, 0.8, 0.15] + [0.1, 0.2, 3.0]


def test_the_same_stamp_and_seed_draw_the_same_and_another_stamp_or_seed_does_not():
    def first(seed, stamp):
        return frame_rng(seed, stamp, 1).random(4)

    np.testing.assert_array_equal(first(3, 10**18), first(3, 10**18))
    assert not np.array_equal(first(3, 10**18), first(3, 10**18 + 1))
    assert not np.array_equal(first(3, 10**18), first(4, 10**18))
    assert not np.array_equal(frame_rng(3, 5, 1).random(4), frame_rng(3, 5, 2).random(4))


def test_a_depth_error_keeps_the_projection_and_moves_the_body_along_the_line_of_sight():
    body = _body()
    for stamp in range(6):
        moved, translation = displaced_mesh(body, np.array([0.1, 0.2, 3.0]), BOX, K, 0.0, 0.3, frame_rng(0, stamp, 1))
        ratio = moved[:, 2].mean() / body[:, 2].mean()
        assert ratio == pytest.approx(1.3) or ratio == pytest.approx(0.7)
        np.testing.assert_allclose(_project(moved), _project(body), atol=1e-9)
        np.testing.assert_allclose(translation, np.array([0.1, 0.2, 3.0]) * ratio)


def test_a_placement_error_moves_the_projection_by_its_share_of_the_box():
    body = _body()
    width, height = BOX[2] - BOX[0], BOX[3] - BOX[1]
    angles = []
    for stamp in range(20):
        moved, translation = displaced_mesh(body, np.zeros(3), BOX, K, 0.2, 0.0, frame_rng(0, stamp, 1))
        centre = np.array([[0.0, 0.0, moved[:, 2].mean()]])
        # At the centroid's depth the pixel offset is the asked share of the box's width and height.
        offset = (_project(centre + translation) - _project(centre))[0]
        assert (offset[0] / width) ** 2 + (offset[1] / height) ** 2 == pytest.approx(0.04, rel=1e-9)
        np.testing.assert_allclose(moved - body, np.broadcast_to(translation, body.shape), atol=1e-12)
        assert translation[2] == 0.0
        angles.append(np.arctan2(offset[1] / height, offset[0] / width))
    assert np.ptp(angles) > 3.0  # every direction, not one


def test_pose_and_shape_noise_reaches_the_asked_pa_mpvpe():
    model = SMPLXModel(build_stand_in_body_model("small"), source="stand_in_small")
    zeros = np.zeros
    rng = np.random.default_rng(1)
    body_pose, betas = rng.normal(0, 0.1, 63), rng.normal(0, 0.5, 10)

    def vertices_of(pose, shape):
        return model.forward(SMPLXParams.from_axis_angle(zeros(3), pose, zeros(45), zeros(45), zeros(3), shape,
                                                         zeros(10))).vertices

    truth = vertices_of(body_pose, betas)
    for target in (25.0, 75.0, 150.0):
        pose, shape, reached = noisy_pose_and_shape(body_pose, betas, vertices_of, target, frame_rng(0, 7, 1))
        assert reached == pytest.approx(target, abs=1.0)
        assert pa_mpvpe_mm(vertices_of(pose, shape), truth) == pytest.approx(reached, abs=1e-6)
    pose, shape, reached = noisy_pose_and_shape(body_pose, betas, vertices_of, 0.0, frame_rng(0, 7, 1))
    assert reached == 0.0 and np.array_equal(pose, body_pose) and np.array_equal(shape, betas)


def test_boxes_grow_about_their_centre_and_a_truncated_box_loses_one_side():
    boxes = np.array([BOX, [20.0, 40.0, 80.0, 200.0, 0.5]], np.float32)
    grown = corrupted_boxes(boxes, (640, 480), BoxCorruption(grow=0.5), frame_rng(0, 1, 2))
    np.testing.assert_allclose(grown[0], [220.0, 20.0, 400.0, 500.0 - 20.0, 0.9], atol=1e-4)  # bottom at the image
    np.testing.assert_allclose(grown[1, :4], [5.0, 0.0, 95.0, 240.0], atol=1e-4)  # top clipped at 0
    np.testing.assert_allclose(grown[:, 4], boxes[:, 4])
    sides = set()
    for stamp in range(40):
        cut = corrupted_boxes(boxes[:1], (640, 480), BoxCorruption(truncate=0.25), frame_rng(0, stamp, 2))[0]
        moved = np.flatnonzero(np.abs(cut[:4] - BOX[:4]) > 1e-3)
        assert len(moved) == 1
        side = int(moved[0])
        size = (BOX[2] - BOX[0]) if side in (0, 2) else (BOX[3] - BOX[1])
        assert abs(cut[side] - BOX[side]) == pytest.approx(0.25 * size, rel=1e-5)
        sides.add(side)
    assert sides == {0, 1, 2, 3}


def test_jitter_moves_each_side_by_its_share_and_missed_frames_have_no_box():
    moves = []
    for stamp in range(400):
        out = corrupted_boxes(BOX[None], (640, 480), BoxCorruption(jitter=0.05), frame_rng(2, stamp, 2))
        moves.append((out[0, :4] - BOX[:4]) / [120.0, 320.0, 120.0, 320.0])
    spread = np.std(moves, axis=0)
    np.testing.assert_allclose(spread, 0.05, rtol=0.15)
    missed = [len(corrupted_boxes(BOX[None], (640, 480), BoxCorruption(miss_share=0.3), frame_rng(0, s, 2))) == 0
              for s in range(400)]
    assert np.mean(missed) == pytest.approx(0.3, abs=0.06)
    assert corrupted_boxes(BOX[None], (640, 480), BoxCorruption(miss_share=1.0), frame_rng(0, 0, 2)).shape == (0, 5)


def test_the_corruption_parameters_are_refused_for_a_real_engine():
    from leapnbv_common.params import params_from_values
    from leapnbv_perception.params import DetectorParams, HmrParams

    with pytest.raises(ValueError, match="ground_truth only"):
        params_from_values(HmrParams, {"backend": "onnxruntime", "truth_mesh_shift": 0.1})
    with pytest.raises(ValueError, match="ground_truth only"):
        params_from_values(DetectorParams, {"backend": "onnxruntime", "truth_miss_share": 0.5})
    assert params_from_values(HmrParams, {"backend": "ground_truth", "truth_mesh_shift": 0.1}).mesh_corruption().active
