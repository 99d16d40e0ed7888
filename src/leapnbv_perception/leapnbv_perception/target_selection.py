"""Which detected person the HMR stage follows from frame to frame."""
from __future__ import annotations

from typing import Optional

import numpy as np

from leapnbv_common.array_types import BoolArray, FloatArray


def box_iou(box: FloatArray, boxes: FloatArray) -> FloatArray:
    """IoU of one [x0, y0, x1, y1] box with each row of boxes (N, >=4)."""
    boxes = np.asarray(boxes, dtype=np.float64).reshape(-1, boxes.shape[-1] if np.ndim(boxes) > 1 else 4)
    x0 = np.maximum(box[0], boxes[:, 0])
    y0 = np.maximum(box[1], boxes[:, 1])
    x1 = np.minimum(box[2], boxes[:, 2])
    y1 = np.minimum(box[3], boxes[:, 3])
    inter = np.clip(x1 - x0, 0, None) * np.clip(y1 - y0, 0, None)
    area = (box[2] - box[0]) * (box[3] - box[1])
    areas = (boxes[:, 2] - boxes[:, 0]) * (boxes[:, 3] - boxes[:, 1])
    union = area + areas - inter
    return np.where(union > 0, inter / np.maximum(union, 1e-12), 0.0)


def usable_boxes(boxes: FloatArray) -> BoolArray:
    """(N,) bool: rows that are finite, have x_max > x_min, y_max > y_min and a score in [0, 1]."""
    boxes = np.asarray(boxes, dtype=np.float64).reshape(-1, 5)
    with np.errstate(invalid="ignore"):
        usable: BoolArray = (np.all(np.isfinite(boxes), axis=1) & (boxes[:, 2] > boxes[:, 0])
                             & (boxes[:, 3] > boxes[:, 1]) & (boxes[:, 4] >= 0.0) & (boxes[:, 4] <= 1.0))
    return usable


def select_target(boxes: FloatArray, previous_box: Optional[FloatArray] = None, min_track_iou: float = 0.3) -> int:
    """Index of the person to reconstruct, or -1 when there is none.

    The best-scoring box, unless a box overlaps the previous frame's target by at least
    min_track_iou: then the one overlapping most, so that a second, briefly more confident
    person does not steal the target. A row that is not a usable box (NaN or inf anywhere, an
    empty or inverted box, a score outside [0, 1]) is never chosen: np.argmax would pick a NaN.

    Args:
        boxes: (N, 5) [x_min, y_min, x_max, y_max, score], sorted by score or not.
        previous_box: [x_min, y_min, x_max, y_max] of the last target, or None.
        min_track_iou: overlap needed to keep following the previous target.
    """
    boxes = np.asarray(boxes, dtype=np.float64).reshape(-1, 5)
    usable = usable_boxes(boxes)
    if not np.any(usable):
        return -1
    if previous_box is not None and np.all(np.isfinite(previous_box)):
        overlaps = np.where(usable, box_iou(np.asarray(previous_box, dtype=np.float64), boxes), -1.0)
        best = int(np.argmax(overlaps))
        if overlaps[best] >= min_track_iou:
            return best
    return int(np.argmax(np.where(usable, boxes[:, 4], -1.0)))
