"""Person detection on any engine backend, for any detector family (see detector_families)."""

from __future__ import annotations

from leapnbv_common.array_types import Float32Array, UInt8Array
from leapnbv_perception.backends.base import EngineBackend
from leapnbv_perception.detector_families import (
    DEFAULT_DETECTOR_FAMILY,
    DEFAULT_MAX_DETECTIONS,
    get_detector_family,
)
from leapnbv_perception.model_contracts import check_backend_contract


class PersonDetector:
    """A detector family's pre-processing, engine run and decoding, with the thresholds in force.

    Args:
        backend: engine loaded from an export of the family (or its contract model).
        score_threshold: a person's score must be above it (strictly, as ultralytics).
        iou_threshold: NMS IoU threshold.
        max_detections: most boxes per frame.
        family: the detector family's name (``detector_family`` parameter).
        multi_label: (yolov8) every anchor's person score counts, not only anchors whose best
            class is a person (the reference decoding, the default).

    Raises:
        ValueError: an unknown family (naming the known ones), or multi_label for a family
            without that option.
        ModelContractError: when the backend's model does not meet the family's contract
            (yolov8: `images` 1x3xSxS -> `output0` 1x84xA; S = 640 -> A = 8400).
    """

    def __init__(
        self,
        backend: EngineBackend,
        score_threshold: float = 0.25,
        iou_threshold: float = 0.5,
        max_detections: int = DEFAULT_MAX_DETECTIONS,
        family: str = DEFAULT_DETECTOR_FAMILY,
        multi_label: bool = False,
    ) -> None:
        self.family = get_detector_family(family)
        if multi_label:
            self.family = self.family.with_options(multi_label=True)
        check_backend_contract(backend, self.family.contract)
        self.family = self.family.for_backend(backend)
        self.backend = backend
        self.score_threshold = float(score_threshold)
        self.iou_threshold = float(iou_threshold)
        self.max_detections = int(max_detections)

    def detect(self, rgb: UInt8Array) -> Float32Array:
        """Detect people in one RGB image.

        Args:
            rgb: (H, W, 3) uint8 RGB.

        Returns:
            (K, 5) float32 [x_min, y_min, x_max, y_max, score] by descending score.

        Raises:
            ValueError: for a malformed image.
        """
        inputs, context = self.family.preprocess(rgb)
        outputs = self.backend.run(inputs)
        return self.family.decode(outputs, context, rgb.shape[1], rgb.shape[0], self.score_threshold,
                                  self.iou_threshold, self.max_detections)
