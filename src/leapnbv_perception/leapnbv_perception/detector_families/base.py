"""What a detector family is: how one kind of exported detector is fed and how its output is read.

A family names the engine's input/output contract (checked when the engine loads), turns an RGB
image into the engine's inputs, and decodes the engine's outputs into person boxes in the source
image's pixels. :class:`leapnbv_perception.detector.PersonDetector` runs any family on any engine
backend; the registry (:mod:`leapnbv_perception.detector_families`) maps the ``detector_family``
parameter to one.
"""
from __future__ import annotations

import abc
from typing import Any, Dict, List, Mapping, Tuple

import numpy as np

from leapnbv_common.array_types import Float32Array, FloatArray, FloatingArray, Int64Array, UInt8Array
from leapnbv_perception.model_contracts import ModelContract

DEFAULT_MAX_DETECTIONS = 100  # most boxes a decode returns when the caller does not say


class DetectorFamily(abc.ABC):
    """One detector output layout.

    Attributes:
        name: the ``detector_family`` parameter value that selects it.
        contract: the inputs and outputs the engine must declare.
    """

    name: str = ""
    contract: ModelContract

    def with_options(self, **options: Any) -> DetectorFamily:
        """This family with decoding options set (e.g. yolov8's ``multi_label``).

        Raises:
            ValueError: an option this family does not have.
        """
        if options:
            raise ValueError(f"detector family {self.name!r} has no options {sorted(options)}")
        return self

    def for_backend(self, backend: Any) -> DetectorFamily:
        """This family set up for the engine's model (e.g. its input size), once the contract is checked.

        Raises:
            ModelContractError: shapes the contract allows one by one but that do not fit together.
        """
        return self

    @abc.abstractmethod
    def preprocess(self, rgb: UInt8Array) -> Tuple[Dict[str, Float32Array], Any]:
        """The engine inputs for one image, and what :meth:`decode` needs to map boxes back.

        Args:
            rgb: (H, W, 3) uint8 RGB.

        Raises:
            ValueError: for an image of another shape or dtype.
        """

    @abc.abstractmethod
    def decode(self, outputs: Mapping[str, FloatingArray], context: Any, image_w: int, image_h: int,
               score_threshold: float, iou_threshold: float, max_detections: int) -> Float32Array:
        """Person boxes from the engine outputs of one image.

        Args:
            outputs: name -> array, as the backend returned them.
            context: the second value :meth:`preprocess` returned for this image.
            image_w: source image width (boxes are clipped to it).
            image_h: source image height.
            score_threshold: minimum person score.
            iou_threshold: NMS IoU above which the lower-scored box is dropped.
            max_detections: most boxes returned.

        Returns:
            (K, 5) float32 [x_min, y_min, x_max, y_max, score] in source-image pixels, by
            descending score.

        Raises:
            ValueError: outputs that do not have the family's layout.
        """


def nms(boxes_xyxy: FloatArray, scores: FloatArray, iou_threshold: float, max_detections: int) -> Int64Array:
    """Greedy non-maximum suppression, vectorized per kept box.

    Args:
        boxes_xyxy: (N, 4) float boxes.
        scores: (N,) scores.
        iou_threshold: a box overlapping a kept one by more than this is dropped.
        max_detections: stop after this many kept boxes.

    Returns:
        (K,) indices of kept boxes, by descending score.
    """
    order = np.argsort(-scores, kind="stable")
    x1, y1, x2, y2 = boxes_xyxy[:, 0], boxes_xyxy[:, 1], boxes_xyxy[:, 2], boxes_xyxy[:, 3]
    areas = np.maximum(x2 - x1, 0.0) * np.maximum(y2 - y1, 0.0)
    keep: List[int] = []
    while order.size > 0 and len(keep) < max_detections:
        best = order[0]
        keep.append(best)
        rest = order[1:]
        inter_w = np.maximum(np.minimum(x2[best], x2[rest]) - np.maximum(x1[best], x1[rest]), 0.0)
        inter_h = np.maximum(np.minimum(y2[best], y2[rest]) - np.maximum(y1[best], y1[rest]), 0.0)
        intersection = inter_w * inter_h
        union = areas[best] + areas[rest] - intersection
        iou = np.where(union > 0.0, intersection / np.maximum(union, 1e-12), 0.0)
        order = rest[iou <= iou_threshold]
    return np.asarray(keep, dtype=np.int64)
