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
    sanitize_box,
)


def apply(affine: np.ndarray, points: np.ndarray) -> np.ndarray:
    return points @ affine[:, :2].T + affine[:, 2]


def smplerx_process_bbox(box: list, width: int, height: int, ratio: float = 1.25):
    """SMPLer-X's sanitize_bbox + process_bbox (common/utils/preprocessing.py), restated step by
    step for 384 x 512 (aspect 0.75); None where it rejects the box."""
    x, y, w, h = box
    x1, y1 = max(0.0, x), max(0.0, y)
    x2 = min(width - 1.0, x1 + max(0.0, w - 1.0))
    y2 = min(height - 1.0, y1 + max(0.0, h - 1.0))
    if not (w * h > 0 and x2 > x1 and y2 > y1):
        return None
    w, h = x2 - x1, y2 - y1
    c_x, c_y = x1 + w / 2.0, y1 + h / 2.0
    if w > 0.75 * h:
        h = w / 0.75
    elif w < 0.75 * h:
        w = h * 0.75
    return np.array([c_x - w * ratio / 2.0, c_y - h * ratio / 2.0, w * ratio, h * ratio])


@pytest.mark.parametrize("box", [[100.0, 80.0, 60.0, 200.0], [10.0, 40.0, 300.0, 100.0], [200.0, 100.0, 90.0, 120.0]])
def test_process_box_aspect_and_scale(box: list) -> None:
    processed = process_box(box, 640, 480)
    assert processed[2] / processed[3] == pytest.approx(0.75, abs=1e-12)
    # Pixel-index convention: the box covers pixels x .. x + w - 1, so its centre is x + (w - 1) / 2.
    centre = np.array([box[0] + (box[2] - 1) / 2, box[1] + (box[3] - 1) / 2])
    np.testing.assert_allclose(processed[:2] + processed[2:] / 2, centre, atol=1e-9)
    # The long side (relative to 3:4), less one pixel, is kept and scaled by 1.25.
    if (box[2] - 1) / (box[3] - 1) < 0.75:
        assert processed[3] == pytest.approx(1.25 * (box[3] - 1))
    else:
        assert processed[2] == pytest.approx(1.25 * (box[2] - 1))
    np.testing.assert_allclose(processed, smplerx_process_bbox(box, 640, 480), atol=1e-9)


@pytest.mark.parametrize(
    "box, expected_xywh",
    [
        ([-50.0, -20.0, 150.0, 220.0], [0.0, 0.0, 149.0, 219.0]),  # starts outside: shifted in, size kept
        ([600.0, 400.0, 100.0, 200.0], [600.0, 400.0, 39.0, 79.0]),  # past the far edges: clipped at W-1, H-1
        ([0.0, 0.0, 640.0, 480.0], [0.0, 0.0, 639.0, 479.0]),  # the whole image
        ([10.0, 10.0, 1.5, 30.0], [10.0, 10.0, 0.5, 29.0]),  # just over one pixel: kept
        ([-300.0, 50.0, 100.0, 100.0], [0.0, 50.0, 99.0, 99.0]),  # wholly left of the image: shifted in (as SMPLer-X)
    ],
)
def test_sanitize_box_as_smplerx(box: list, expected_xywh: list) -> None:
    np.testing.assert_allclose(sanitize_box(box, 640, 480), expected_xywh, atol=1e-12)
    np.testing.assert_allclose(process_box(box, 640, 480), smplerx_process_bbox(box, 640, 480), atol=1e-9)


@pytest.mark.parametrize(
    "box",
    [
        [700.0, 10.0, 50.0, 50.0],  # right of the image
        [10.0, 479.0, 50.0, 50.0],  # starts on the last row: nothing below it
        [10.0, 10.0, 1.0, 50.0],  # one pixel wide
        [10.0, 10.0, 50.0, 0.5],  # under a pixel high
        [10.0, 10.0, -5.0, -5.0],  # negative size (w h > 0, but no extent)
        [float("nan"), 10.0, 50.0, 50.0],
    ],
)
def test_process_box_rejects_as_smplerx(box: list) -> None:
    if all(np.isfinite(box)):
        assert smplerx_process_bbox(box, 640, 480) is None
    with pytest.raises(InvalidBoxError):
        process_box(box, 640, 480)


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
