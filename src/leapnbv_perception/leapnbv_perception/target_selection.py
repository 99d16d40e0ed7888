"""Which detected person the HMR stage follows, by the image alone: box overlap and the acquisition rule.

The fixed-frame tracking (:mod:`leapnbv_perception.target_tracking`) uses these for the frames it follows in
the image only (no camera pose or no depth) and to take a target when it has none.
"""
from __future__ import annotations

from typing import Optional, Tuple

import numpy as np

from leapnbv_common.array_types import BoolArray, FloatArray

#: Scores closer than this are a tie for the acquisition rule (a detector's score is no finer than this).
SCORE_TIE = 1e-3
#: Box centres whose distances to the image centre differ by less than this (pixels) are a tie.
CENTRE_TIE_PX = 0.5


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


def acquisition_index(boxes: FloatArray, candidates: BoolArray, image_size: Optional[Tuple[int, int]]) -> int:
    """The box the acquisition rule takes among the candidate rows, or -1 when there is none.

    The rule: the highest score; scores within :data:`SCORE_TIE` of it tie, and then the box whose centre is
    nearest the image centre wins (distances within :data:`CENTRE_TIE_PX` tie); then the lowest index. The
    tolerances make the choice independent of the last bit of a score or a coordinate.

    Args:
        boxes: (N, 5) [x_min, y_min, x_max, y_max, score].
        candidates: (N,) bool, the rows that may be taken (usable boxes).
        image_size: (width, height) of the image; None: no centre rule (the lowest index among the tied).
    """
    boxes = np.asarray(boxes, dtype=np.float64).reshape(-1, 5)
    rows = np.flatnonzero(np.asarray(candidates, dtype=bool))
    if rows.size == 0:
        return -1
    scores = boxes[rows, 4]
    rows = rows[scores >= scores.max() - SCORE_TIE]
    if rows.size > 1 and image_size is not None:
        centre = np.array([image_size[0] / 2.0, image_size[1] / 2.0])
        centres = np.stack([(boxes[rows, 0] + boxes[rows, 2]) / 2.0, (boxes[rows, 1] + boxes[rows, 3]) / 2.0], 1)
        distances = np.hypot(*(centres - centre).T)
        rows = rows[distances <= distances.min() + CENTRE_TIE_PX]
    return int(rows.min())


def select_target(boxes: FloatArray, previous_box: Optional[FloatArray] = None, min_track_iou: float = 0.3,
                  image_size: Optional[Tuple[int, int]] = None) -> int:
    """Index of the person to reconstruct by the image alone, or -1 when there is none.

    The box overlapping the previous frame's target most, when it overlaps by at least min_track_iou
    (so that a second, briefly more confident person does not steal the target); else the acquisition
    rule's box (:func:`acquisition_index`: the best score, ties to the image centre). A row that is not a
    usable box (NaN or inf anywhere, an empty or inverted box, a score outside [0, 1]) is never chosen.

    Args:
        boxes: (N, 5) [x_min, y_min, x_max, y_max, score], sorted by score or not.
        previous_box: [x_min, y_min, x_max, y_max] of the last target, or None.
        min_track_iou: overlap needed to keep following the previous target.
        image_size: (width, height), for the acquisition rule's tie-break.
    """
    index, _ = overlapping_index(boxes, previous_box, min_track_iou)
    if index >= 0:
        return index
    boxes = np.asarray(boxes, dtype=np.float64).reshape(-1, 5)
    return acquisition_index(boxes, usable_boxes(boxes), image_size)


def overlapping_index(boxes: FloatArray, previous_box: Optional[FloatArray], min_track_iou: float,
                      candidates: Optional[BoolArray] = None) -> Tuple[int, float]:
    """(the candidate box overlapping previous_box most, its IoU), or (-1, the best IoU or 0) below min_track_iou.

    Candidates default to the usable boxes; IoUs within 1e-9 tie to the lowest index.
    """
    boxes = np.asarray(boxes, dtype=np.float64).reshape(-1, 5)
    usable = usable_boxes(boxes) if candidates is None else np.asarray(candidates, dtype=bool) & usable_boxes(boxes)
    if previous_box is None or not np.any(usable) or not np.all(np.isfinite(previous_box)):
        return -1, 0.0
    overlaps = np.where(usable, box_iou(np.asarray(previous_box, dtype=np.float64), boxes), -1.0)
    best = float(overlaps.max())
    index = int(np.flatnonzero(overlaps >= best - 1e-9).min())
    if best >= min_track_iou and best > 0.0:
        return index, best
    return -1, max(best, 0.0)
