"""The "yolov8" detector family: ultralytics YOLOv8 ONNX exports (COCO classes, person = class 0).

Decoded as the ultralytics predictor does (docs/ALGORITHMS.md §1), multi-label as an option.

Input ``images`` (1, 3, S, S) float32 RGB / 255, letterboxed (aspect kept, padded with 114,
centred as ultralytics does); S is the export's (640 by default; 320 or 480 are cheaper on a CPU);
output ``output0`` (1, 84, A) with A = (S/8)^2 + (S/16)^2 + (S/32)^2 (8,400 at 640): cx, cy, w, h in
letterbox pixels and 80 sigmoid class scores per anchor, no objectness (model_contracts.YOLOV8_CONTRACT).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Dict, Mapping, Optional, Tuple

import cv2
import numpy as np

from leapnbv_common.array_types import Float32Array, FloatArray, FloatingArray, UInt8Array
from leapnbv_perception.detector_families.base import DEFAULT_MAX_DETECTIONS, DetectorFamily, nms
from leapnbv_perception.model_contracts import (
    YOLO_INPUT_NAME,
    YOLO_INPUT_SIZE,
    YOLO_OUTPUT_NAME,
    YOLOV8_CONTRACT,
    ModelContractError,
    yolo_anchor_count,
)

PAD_VALUE = 114
PERSON_CLASS = 0


@dataclass(frozen=True)
class LetterboxTransform:
    """Maps source pixels to letterbox pixels: letterbox = source * gain + pad, per axis.

    Attributes:
        scale: r = min(size / h, size / w), the resize factor asked for.
        pad_x: left padding in letterbox pixels (an integer: where the image is placed).
        pad_y: top padding in letterbox pixels.
        gain_x: the horizontal factor the image really got, round(w r) / w; None means r.
        gain_y: the vertical factor, round(h r) / h; None means r. (On odd sizes the two differ
            from r by up to half a letterbox pixel over the image; ultralytics maps boxes back
            with these per-axis gains.)
    """

    scale: float
    pad_x: float
    pad_y: float
    gain_x: Optional[float] = None
    gain_y: Optional[float] = None

    def gains(self) -> FloatArray:
        """(gain_x, gain_y)."""
        return np.array([self.scale if self.gain_x is None else self.gain_x,
                         self.scale if self.gain_y is None else self.gain_y], dtype=np.float64)

    def to_source(self, points_xy: FloatArray) -> FloatArray:
        """Letterbox (..., 2) x, y -> source image x, y: (xy - pad) / gain."""
        offset = np.array([self.pad_x, self.pad_y], dtype=np.float64)
        return (np.asarray(points_xy, dtype=np.float64) - offset) / self.gains()

    def to_letterbox(self, points_xy: FloatArray) -> FloatArray:
        """Source (..., 2) x, y -> letterbox x, y."""
        offset = np.array([self.pad_x, self.pad_y], dtype=np.float64)
        return np.asarray(points_xy, dtype=np.float64) * self.gains() + offset


def letterbox(rgb: UInt8Array, size: int = YOLO_INPUT_SIZE) -> Tuple[Float32Array, LetterboxTransform]:
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
        canvas[top : top + new_h, left : left + new_w] = cv2.resize(rgb, (new_w, new_h), interpolation=cv2.INTER_LINEAR)
    else:
        canvas[top : top + new_h, left : left + new_w] = rgb
    # HWC uint8 -> NCHW float32 / 255
    tensor = canvas.transpose(2, 0, 1)[None].astype(np.float32) * np.float32(1.0 / 255.0)
    transform = LetterboxTransform(float(scale), float(left), float(top), new_w / width, new_h / height)
    return np.ascontiguousarray(tensor), transform


def decode_person_boxes(
    output0: FloatingArray,
    transform: LetterboxTransform,
    image_w: int,
    image_h: int,
    score_threshold: float = 0.25,
    iou_threshold: float = 0.5,
    max_detections: int = DEFAULT_MAX_DETECTIONS,
    multi_label: bool = False,
) -> Float32Array:
    """Decode YOLOv8 output into person boxes in source-image pixels (docs/ALGORITHMS.md §1).

    As the ultralytics predictor with ``classes=[0]``: each anchor takes its best class and is a
    person only when that class is 0 with a score strictly above ``score_threshold``. With
    ``multi_label`` every anchor whose person score is above the threshold is a person, whatever
    its other classes score (ultralytics' ``multi_label=True``).

    Args:
        output0: (1, 84, N) raw output: cx, cy, w, h (letterbox px) + 80 class scores.
        transform: the letterbox used for this frame (boxes go back with its per-axis gains).
        image_w: source image width (boxes are clipped to [0, image_w]).
        image_h: source image height.
        score_threshold: a person's score must be above this (strictly).
        iou_threshold: NMS IoU above which the lower-scored box is dropped.
        max_detections: most boxes returned.
        multi_label: threshold the person score of every anchor instead of its best class.

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
    class_scores = predictions[4:]
    person_scores = class_scores[PERSON_CLASS]
    is_person = person_scores > score_threshold
    if not multi_label:
        # np.argmax takes the first of equal scores: a tie with another class stays a person.
        is_person &= np.argmax(class_scores, axis=0) == PERSON_CLASS
    candidates = np.nonzero(is_person)[0]
    if candidates.size == 0:
        return np.zeros((0, 5), dtype=np.float32)
    boxes_cxcywh = predictions[:4, candidates].T.astype(np.float64)
    scores = person_scores[candidates].astype(np.float64)
    half = boxes_cxcywh[:, 2:4] * 0.5
    boxes = np.concatenate([boxes_cxcywh[:, :2] - half, boxes_cxcywh[:, :2] + half], axis=1)
    # NMS in letterbox pixels, as ultralytics does.
    keep = nms(boxes, scores, iou_threshold, max_detections)
    boxes = boxes[keep]
    gain_x, gain_y = transform.gains()
    boxes[:, [0, 2]] = (boxes[:, [0, 2]] - transform.pad_x) / gain_x
    boxes[:, [1, 3]] = (boxes[:, [1, 3]] - transform.pad_y) / gain_y
    boxes[:, [0, 2]] = np.clip(boxes[:, [0, 2]], 0.0, float(image_w))
    boxes[:, [1, 3]] = np.clip(boxes[:, [1, 3]], 0.0, float(image_h))
    result: Float32Array = np.concatenate([boxes, scores[keep, None]], axis=1).astype(np.float32)
    return result


class YoloV8Family(DetectorFamily):
    """Letterbox in, class-0 boxes out (NMS in letterbox pixels, then back to source pixels).

    Args:
        multi_label: decode every anchor's person score instead of its best class (an option;
            the default is the reference predictor's best-class decoding).
    """

    name = "yolov8"
    contract = YOLOV8_CONTRACT
    input_size = YOLO_INPUT_SIZE

    def __init__(self, multi_label: bool = False, input_size: int = YOLO_INPUT_SIZE) -> None:
        self.multi_label = bool(multi_label)
        self.input_size = int(input_size)

    def with_options(self, **options: Any) -> YoloV8Family:
        unknown = sorted(set(options) - {"multi_label"})
        if unknown:
            raise ValueError(f"detector family 'yolov8' has no options {unknown}; it has ['multi_label']")
        return YoloV8Family(multi_label=options.get("multi_label", self.multi_label), input_size=self.input_size)

    def for_backend(self, backend: Any) -> YoloV8Family:
        """This family for a backend's model: the letterbox side is the model's input side.

        An export at 320, 480, 640, ...; its output must have that size's anchor count.
        """
        size = int(backend.input_specs[YOLO_INPUT_NAME].shape[2])
        anchors = int(backend.output_specs[YOLO_OUTPUT_NAME].shape[2])
        if anchors != yolo_anchor_count(size):
            raise ModelContractError(f"{getattr(backend, 'model_path', 'the detector model')}: a {size}x{size} "
                                     f"input has {yolo_anchor_count(size)} anchors, but '{YOLO_OUTPUT_NAME}' has "
                                     f"{anchors}")
        return YoloV8Family(multi_label=self.multi_label, input_size=size)

    def preprocess(self, rgb: UInt8Array) -> Tuple[Dict[str, Float32Array], LetterboxTransform]:
        tensor, transform = letterbox(rgb, self.input_size)
        return {YOLO_INPUT_NAME: tensor}, transform

    def decode(self, outputs: Mapping[str, FloatingArray], context: Any, image_w: int, image_h: int,
               score_threshold: float, iou_threshold: float, max_detections: int) -> Float32Array:
        return decode_person_boxes(outputs[YOLO_OUTPUT_NAME], context, image_w, image_h, score_threshold,
                                   iou_threshold, max_detections, self.multi_label)


FAMILY = YoloV8Family()
