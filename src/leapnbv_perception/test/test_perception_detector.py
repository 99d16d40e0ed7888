"""Tests for YOLOv8 letterboxing and person-box decoding."""

from __future__ import annotations

import numpy as np
import pytest

from leapnbv_perception.detector import LetterboxTransform, decode_person_boxes, letterbox


@pytest.mark.parametrize(
    "height, width, scale, pad_x, pad_y",
    [(480, 640, 1.0, 0, 80), (720, 1280, 0.5, 0, 140), (640, 480, 1.0, 80, 0), (300, 300, 640 / 300, 0, 0)],
)
def test_letterbox_geometry(height: int, width: int, scale: float, pad_x: int, pad_y: int) -> None:
    rgb = np.full((height, width, 3), 255, dtype=np.uint8)
    tensor, transform = letterbox(rgb)
    assert tensor.shape == (1, 3, 640, 640) and tensor.dtype == np.float32
    assert transform.scale == pytest.approx(scale)
    assert (transform.pad_x, transform.pad_y) == (pad_x, pad_y)
    pad_value = 114.0 / 255.0
    if pad_y:
        assert tensor[0, 0, pad_y - 1, 320] == pytest.approx(pad_value)
        assert tensor[0, 0, pad_y, 320] == pytest.approx(1.0)
        assert tensor[0, 0, 640 - pad_y, 320] == pytest.approx(pad_value)
    if pad_x:
        assert tensor[0, 2, 320, pad_x - 1] == pytest.approx(pad_value)
        assert tensor[0, 2, 320, pad_x] == pytest.approx(1.0)


def test_letterbox_keeps_rgb_order() -> None:
    rgb = np.zeros((480, 640, 3), dtype=np.uint8)
    rgb[..., 0] = 255
    tensor, _ = letterbox(rgb)
    assert tensor[0, 0, 320, 320] == 1.0 and tensor[0, 1, 320, 320] == 0.0


def make_output(entries: list) -> np.ndarray:
    """entries: (anchor, cx, cy, w, h, class, score) in letterbox pixels."""
    output = np.zeros((1, 84, 8400), dtype=np.float32)
    output[0, :4] = 5.0  # harmless tiny boxes with zero scores everywhere else
    for anchor, cx, cy, w, h, klass, score in entries:
        output[0, :4, anchor] = (cx, cy, w, h)
        output[0, 4 + klass, anchor] = score
    return output


def to_letterbox(transform: LetterboxTransform, box: list) -> tuple:
    (x1, y1), (x2, y2) = transform.to_letterbox(np.array([box[:2], box[2:]]))
    return (x1 + x2) / 2, (y1 + y2) / 2, x2 - x1, y2 - y1


@pytest.mark.parametrize("height, width", [(480, 640), (720, 1280)])
def test_decode_person_boxes(height: int, width: int) -> None:
    _, transform = letterbox(np.zeros((height, width, 3), dtype=np.uint8))
    person_a = [100.0, 60.0, 220.0, 400.0]  # source pixels
    person_b = [400.0, 100.0, 520.0, 420.0]
    duplicate_a = [104.0, 64.0, 224.0, 404.0]  # IoU with a > 0.5, lower score
    entries = [
        (10, *to_letterbox(transform, person_a), 0, 0.9),
        (2000, *to_letterbox(transform, duplicate_a), 0, 0.8),
        (5000, *to_letterbox(transform, person_b), 0, 0.6),
        (7000, *to_letterbox(transform, [300.0, 300.0, 350.0, 350.0]), 5, 0.99),  # not a person
        (8000, *to_letterbox(transform, [10.0, 10.0, 50.0, 50.0]), 0, 0.2),  # below threshold
    ]
    boxes = decode_person_boxes(make_output(entries), transform, width, height)
    assert boxes.shape == (2, 5) and boxes.dtype == np.float32
    np.testing.assert_allclose(boxes[0], person_a + [0.9], atol=1e-3)
    np.testing.assert_allclose(boxes[1], person_b + [0.6], atol=1e-3)


def test_decode_clips_to_image_and_keeps_separate_people() -> None:
    _, transform = letterbox(np.zeros((480, 640, 3), dtype=np.uint8))
    # A box reaching into the top padding and past the right edge.
    entries = [(0, 620.0, 100.0, 80.0, 100.0, 0, 0.7), (1, 100.0, 300.0, 50.0, 50.0, 0, 0.5)]
    boxes = decode_person_boxes(make_output(entries), transform, 640, 480)
    np.testing.assert_allclose(boxes[0], [580.0, 0.0, 640.0, 70.0, 0.7], atol=1e-4)
    np.testing.assert_allclose(boxes[1], [75.0, 195.0, 125.0, 245.0, 0.5], atol=1e-4)


def test_decode_iou_threshold_and_max_detections() -> None:
    transform = LetterboxTransform(1.0, 0.0, 0.0)
    entries = [(i, 100.0 + 30.0 * i, 100.0, 100.0, 100.0, 0, 0.9 - 0.01 * i) for i in range(5)]
    output = make_output(entries)
    # Neighbours overlap with IoU 70/130 = 0.54: suppressed at 0.5, kept at 0.6.
    assert len(decode_person_boxes(output, transform, 640, 640, iou_threshold=0.5)) == 3
    assert len(decode_person_boxes(output, transform, 640, 640, iou_threshold=0.6)) == 5
    assert len(decode_person_boxes(output, transform, 640, 640, iou_threshold=0.6, max_detections=2)) == 2


def test_decode_empty() -> None:
    boxes = decode_person_boxes(np.zeros((1, 84, 8400), np.float32), LetterboxTransform(1.0, 0.0, 0.0), 640, 480)
    assert boxes.shape == (0, 5)
