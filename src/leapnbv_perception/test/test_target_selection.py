"""The HMR stage follows the previous target, else the best-scoring person."""
from __future__ import annotations

import numpy as np

from leapnbv_perception.target_selection import box_iou, select_target


def test_best_score_without_history_and_tracking_with_it():
    boxes = np.array([[0, 0, 10, 10, 0.6], [100, 100, 120, 130, 0.9]], np.float32)
    assert select_target(boxes) == 1
    assert select_target(boxes, previous_box=np.array([1, 1, 11, 11])) == 0
    assert select_target(boxes, previous_box=np.array([50, 50, 60, 60])) == 1
    assert select_target(np.zeros((0, 5))) == -1


def test_box_iou_known_values():
    np.testing.assert_allclose(box_iou(np.array([0, 0, 10, 10]), np.array([[5, 0, 15, 10], [20, 20, 30, 30]])),
                               [50 / 150, 0.0])


def test_a_nan_score_or_box_never_wins():
    nan = float("nan")
    boxes = np.array([[0, 0, 10, 10, nan], [100, 100, 120, 130, 0.9], [5, 5, 50, 50, 1.5]], np.float32)
    assert select_target(boxes) == 1  # np.argmax alone picks the NaN row 0
    assert select_target(boxes, previous_box=np.array([0, 0, 10, 10])) == 1  # nor does tracking follow it
    nan_box = np.array([[nan, 0, 10, 10, 0.95], [100, 100, 120, 130, 0.5]], np.float32)
    assert select_target(nan_box) == 1
    assert select_target(nan_box, previous_box=np.array([nan, 0, 10, 10])) == 1
    inverted = np.array([[10, 10, 0, 0, 0.99], [100, 100, 120, 130, 0.2]], np.float32)
    assert select_target(inverted) == 1
    assert select_target(np.array([[0, 0, 10, 10, nan]], np.float32)) == -1
