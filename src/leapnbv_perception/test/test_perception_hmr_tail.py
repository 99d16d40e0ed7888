"""Tests for the camera translation, virtual intrinsics and left-hand un-mirroring."""

from __future__ import annotations

import numpy as np

from leapnbv_perception.hmr_tail import camera_translation, depth_scale, unmirror_left_hand, virtual_intrinsics
from leapnbv_perception.rotations import axis_angle_to_matrix, matrix_to_axis_angle


def test_depth_scale_matches_smplerx() -> None:
    assert abs(depth_scale() - 56.38) < 0.01


def test_camera_translation_reference_value() -> None:
    np.testing.assert_allclose(camera_translation([0.1, -0.2, 0.0]), [0.1, -0.2, 28.19], atol=0.01)


def test_camera_translation_sigmoid() -> None:
    k = depth_scale()
    assert abs(camera_translation([0.0, 0.0, 2.0])[2] - k / (1.0 + np.exp(-2.0))) < 1e-9
    assert abs(camera_translation([0.0, 0.0, -800.0])[2]) < 1e-9  # no overflow


def test_virtual_intrinsics_project_crop_camera_into_image() -> None:
    box = np.array([100.0, 50.0, 150.0, 200.0])
    fx, fy, cx, cy = virtual_intrinsics(box)
    assert abs(fx - 5000.0 / 192.0 * 150.0) < 1e-9
    assert abs(fy - 5000.0 / 256.0 * 200.0) < 1e-9
    assert (cx, cy) == (175.0, 150.0)
    # A point projecting to body-crop pixel (u, v) with K=(5000, 5000, 96, 128) lands at the
    # matching place of the box: box corner + (u/192 w, v/256 h).
    point = np.array([0.3, -0.4, 25.0])
    u = 5000.0 * point[0] / point[2] + 96.0
    v = 5000.0 * point[1] / point[2] + 128.0
    assert abs(fx * point[0] / point[2] + cx - (box[0] + u / 192.0 * box[2])) < 1e-9
    assert abs(fy * point[1] / point[2] + cy - (box[1] + v / 256.0 * box[3])) < 1e-9


def test_unmirror_left_hand_negates_axis_angle_y_z() -> None:
    vectors = np.random.default_rng(3).normal(scale=0.5, size=(15, 3))
    result = unmirror_left_hand(axis_angle_to_matrix(vectors))
    np.testing.assert_allclose(matrix_to_axis_angle(result), vectors * [1.0, -1.0, -1.0], atol=1e-9)
    np.testing.assert_allclose(np.linalg.det(result), 1.0, atol=1e-12)
