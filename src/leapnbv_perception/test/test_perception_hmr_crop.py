"""Tests for the SMPLer-X box processing and crop."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from leapnbv_perception.hmr_crop import (
    InvalidBoxError,
    crop_for_hmr,
    fit_to_engine_input,
    process_box,
)


def apply(affine: np.ndarray, points: np.ndarray) -> np.ndarray:
    return points @ affine[:, :2].T + affine[:, 2]


@pytest.mark.parametrize("box", [[100.0, 80.0, 60.0, 200.0], [10.0, 40.0, 300.0, 100.0], [200.0, 100.0, 90.0, 120.0]])
def test_process_box_aspect_and_scale(box: list) -> None:
    processed = process_box(box, 640, 480)
    assert processed[2] / processed[3] == pytest.approx(0.75, abs=1e-12)
    centre = np.array([box[0] + box[2] / 2, box[1] + box[3] / 2])
    np.testing.assert_allclose(processed[:2] + processed[2:] / 2, centre, atol=1e-9)
    # The long side (relative to 3:4) is kept and scaled by 1.25.
    if box[2] / box[3] < 0.75:
        assert processed[3] == pytest.approx(1.25 * box[3])
    else:
        assert processed[2] == pytest.approx(1.25 * box[2])


def test_process_box_sanitizes_to_image() -> None:
    processed = process_box([-50.0, -20.0, 150.0, 220.0], 640, 480, scale=1.0)
    # Clipped to x in [0, 100], y in [0, 200] before the aspect fix: centre (50, 100).
    np.testing.assert_allclose(processed[:2] + processed[2:] / 2, [50.0, 100.0])
    assert processed[3] == pytest.approx(200.0)


def test_process_box_outside_image_raises() -> None:
    with pytest.raises(InvalidBoxError, match="no area"):
        process_box([700.0, 10.0, 50.0, 50.0], 640, 480)


def test_crop_corners_map_to_crop_corners_and_back() -> None:
    rgb = np.zeros((480, 640, 3), dtype=np.uint8)
    processed = process_box([250.0, 90.0, 80.0, 260.0], 640, 480)
    _, affine, inverse = crop_for_hmr(rgb, processed)
    x, y, w, h = processed
    corners = np.array([[x, y], [x + w, y], [x + w, y + h], [x, y + h]])
    crop_corners = np.array([[0.0, 0.0], [384.0, 0.0], [384.0, 512.0], [0.0, 512.0]])
    np.testing.assert_allclose(apply(affine, corners), crop_corners, atol=1e-3)
    np.testing.assert_allclose(apply(inverse, crop_corners), corners, atol=1e-3)


def test_crop_content_and_black_border() -> None:
    rgb = np.zeros((480, 640, 3), dtype=np.uint8)
    rgb[:, :, 0] = 200
    cv2.rectangle(rgb, (300, 200), (340, 280), (0, 255, 0), -1)
    processed = process_box([280.0, 180.0, 80.0, 120.0], 640, 480)
    tensor, affine, _ = crop_for_hmr(rgb, processed)
    assert tensor.shape == (1, 3, 512, 384) and tensor.dtype == np.float32
    centre = apply(affine, np.array([[320.0, 240.0]]))[0].astype(int)
    np.testing.assert_allclose(tensor[0, :, centre[1], centre[0]], [0.0, 1.0, 0.0], atol=1e-6)  # green, RGB/255
    # A box hanging over the top edge: the crop above the image is black.
    tensor, affine, _ = crop_for_hmr(rgb, process_box([300.0, 0.0, 60.0, 100.0], 640, 480))
    assert np.all(tensor[0, :, 0, :] == 0.0)
    assert tensor[0, 0].max() == pytest.approx(200.0 / 255.0)


def test_fit_to_engine_input_takes_every_other_pixel() -> None:
    tensor = np.random.default_rng(0).random((1, 3, 512, 384)).astype(np.float32)
    small = fit_to_engine_input(tensor, (256, 192))
    assert small.shape == (1, 3, 256, 192)
    assert small[0, 1, 10, 20] == tensor[0, 1, 20, 40]
    assert fit_to_engine_input(tensor, (512, 384)) is tensor
    with pytest.raises(ValueError, match="300x200"):
        fit_to_engine_input(tensor, (300, 200))
