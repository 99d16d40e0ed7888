"""The "yolov8" detector family: ultralytics YOLOv8 ONNX exports (COCO classes, person = class 0);
docs/ALGORITHMS.md §1 lists where the decoding differs from the reference predictor.

Input ``images`` (1, 3, 640, 640) float32 RGB / 255, letterboxed (aspect kept, padded with 114,
centred as ultralytics does); output ``output0`` (1, 84, 8400): cx, cy, w, h in letterbox pixels
and 80 sigmoid class scores per anchor, no objectness (see model_contracts.YOLOV8_CONTRACT).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Dict, Mapping, Tuple

import cv2
import numpy as np

from leapnbv_perception.detector_families.base import DEFAULT_MAX_DETECTIONS, DetectorFamily, nms
from leapnbv_perception.model_contracts import YOLO_INPUT_NAME, YOLO_INPUT_SIZE, YOLO_OUTPUT_NAME, YOLOV8_CONTRACT

PAD_VALUE = 114
PERSON_CLASS = 0


@dataclass(frozen=True)
class LetterboxTransform:
    """Maps source pixels to letterbox pixels: letterbox = source * scale + pad.

    Attributes:
        scale: r = min(size / h, size / w).
        pad_x: left padding in letterbox pixels (may be fractional; the image is placed at
            its rounded value, which is what the arithmetic here uses too).
        pad_y: top padding in letterbox pixels.
    """

    scale: float
    pad_x: float
    pad_y: float

    def to_source(self, points_xy: np.ndarray) -> np.ndarray:
        """Letterbox (..., 2) x, y -> source image x, y: (xy - pad) / r."""
        offset = np.array([self.pad_x, self.pad_y], dtype=np.float64)
        return (np.asarray(points_xy, dtype=np.float64) - offset) / self.scale

    def to_letterbox(self, points_xy: np.ndarray) -> np.ndarray:
        """Source (..., 2) x, y -> letterbox x, y."""
        offset = np.array([self.pad_x, self.pad_y], dtype=np.float64)
        return np.asarray(points_xy, dtype=np.float64) * self.scale + offset


def letterbox(rgb: np.ndarray, size: int = YOLO_INPUT_SIZE) -> Tuple[np.ndarray, LetterboxTransform]:
    """Resize keeping the aspect ratio and pad (value 114, centred) to size x size.

    Args:
        rgb: (H, W, 3) uint8 RGB image.
        size: letterbox side in pixels (640 for the YOLOv8 export).

    Returns:
        (tensor (1, 3, size, size) float32 RGB / 255 NCHW, LetterboxTransform).

    Raises:
        ValueError: for an image that is not (H, W, 3) uint8 with H, W > 0.
    """
    if rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.dtype != np.uint8 or rgb.shape[0] == 0 or rgb.shape[1] == 0:
        raise ValueError("letterbox expects an (H, W, 3) uint8 image, got %s %s" % (rgb.shape, rgb.dtype))
    height, width = rgb.shape[:2]
    scale = min(size / height, size / width)
    new_w = int(round(width * scale))
    new_h = int(round(height * scale))
    # Centred padding as ultralytics does: split the remainder, left/top get the rounded half.
    pad_w = (size - new_w) / 2.0
    pad_h = (size - new_h) / 2.0
    left = int(round(pad_w - 0.1))
    top = int(round(pad_h - 0.1))
    canvas = np.full((size, size, 3), PAD_VALUE, dtype=np.uint8)
    if (new_w, new_h) != (width, height):
        resized = cv2.resize(rgb, (new_w, new_h), interpolation=cv2.INTER_LINEAR)
    else:
        resized = rgb
    canvas[top : top + new_h, left : left + new_w] = resized
    # HWC uint8 -> NCHW float32 / 255
    tensor = canvas.transpose(2, 0, 1)[None].astype(np.float32) * np.float32(1.0 / 255.0)
    return np.ascontiguousarray(tensor), LetterboxTransform(float(scale), float(left), float(top))


def decode_person_boxes(
    output0: np.ndarray,
    transform: LetterboxTransform,
    image_w: int,
    image_h: int,
    score_threshold: float = 0.25,
    iou_threshold: float = 0.5,
    max_detections: int = DEFAULT_MAX_DETECTIONS,
) -> np.ndarray:
    """Decode YOLOv8 output into person boxes in source-image pixels.

    Args:
        output0: (1, 84, N) raw output: cx, cy, w, h (letterbox px) + 80 class scores.
        transform: the letterbox used for this frame.
        image_w: source image width (boxes are clipped to [0, image_w]).
        image_h: source image height.
        score_threshold: minimum person score.
        iou_threshold: NMS IoU above which the lower-scored box is dropped.
        max_detections: most boxes returned.

    Returns:
        (K, 5) float32 [x_min, y_min, x_max, y_max, score], by descending score.

    Raises:
        ValueError: when output0 is not (1, 84, N) / (84, N).
    """
    predictions = np.asarray(output0)
    if predictions.ndim == 3 and predictions.shape[0] == 1:
        predictions = predictions[0]
    if predictions.ndim != 2 or predictions.shape[0] < 5:
        raise ValueError("output0 must be (1, 84, N), got %s" % (np.shape(output0),))
    person_scores = predictions[4 + PERSON_CLASS]
    candidates = np.nonzero(person_scores >= score_threshold)[0]
    if candidates.size == 0:
        return np.zeros((0, 5), dtype=np.float32)
    boxes_cxcywh = predictions[:4, candidates].T.astype(np.float64)
    scores = person_scores[candidates].astype(np.float64)
    half = boxes_cxcywh[:, 2:4] * 0.5
    boxes = np.concatenate([boxes_cxcywh[:, :2] - half, boxes_cxcywh[:, :2] + half], axis=1)
    # NMS in letterbox pixels, as ultralytics does (the letterbox is a uniform scale + shift).
    keep = nms(boxes, scores, iou_threshold, max_detections)
    boxes = boxes[keep]
    scale = transform.scale
    boxes[:, [0, 2]] = (boxes[:, [0, 2]] - transform.pad_x) / scale
    boxes[:, [1, 3]] = (boxes[:, [1, 3]] - transform.pad_y) / scale
    boxes[:, [0, 2]] = np.clip(boxes[:, [0, 2]], 0.0, float(image_w))
    boxes[:, [1, 3]] = np.clip(boxes[:, [1, 3]], 0.0, float(image_h))
    result = np.concatenate([boxes, scores[keep, None]], axis=1).astype(np.float32)
    return result


class YoloV8Family(DetectorFamily):
    """Letterbox in, class-0 boxes out (NMS in letterbox pixels, then back to source pixels)."""

    name = "yolov8"
    contract = YOLOV8_CONTRACT
    input_size = YOLO_INPUT_SIZE

    def preprocess(self, rgb: np.ndarray) -> Tuple[Dict[str, np.ndarray], LetterboxTransform]:
        tensor, transform = letterbox(rgb, self.input_size)
        return {YOLO_INPUT_NAME: tensor}, transform

    def decode(self, outputs: Mapping[str, np.ndarray], context: Any, image_w: int, image_h: int,
               score_threshold: float, iou_threshold: float, max_detections: int) -> np.ndarray:
        return decode_person_boxes(outputs[YOLO_OUTPUT_NAME], context, image_w, image_h, score_threshold,
                                   iou_threshold, max_detections)


FAMILY = YoloV8Family()
