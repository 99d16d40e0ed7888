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
