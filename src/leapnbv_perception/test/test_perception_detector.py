"""Tests for the detector families: YOLOv8 letterboxing and person-box decoding, the family registry."""

from __future__ import annotations

import numpy as np
import pytest

from leapnbv_common.params import ParamsError, params_from_values
from leapnbv_perception import detector_families
from leapnbv_perception.backends.base import EngineBackend, TensorSpec
from leapnbv_perception.detector import PersonDetector
from leapnbv_perception.detector_families import DetectorFamily, nms
from leapnbv_perception.detector_families.yolov8 import LetterboxTransform, decode_person_boxes, letterbox
from leapnbv_perception.model_contracts import YOLOV8_CONTRACT, ModelContract, ModelContractError, TensorContract
from leapnbv_perception.params import DetectorParams


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


def test_decode_another_class_wins_is_no_person_unless_multi_label() -> None:
    transform = LetterboxTransform(1.0, 0.0, 0.0)
    output = make_output([(3, 200.0, 200.0, 100.0, 200.0, 0, 0.6), (9, 400.0, 200.0, 100.0, 200.0, 0, 0.5)])
    output[0, 4 + 16, 3] = 0.9  # anchor 3 is a dog more than a person
    boxes = decode_person_boxes(output, transform, 640, 640)
    np.testing.assert_allclose(boxes, [[350.0, 100.0, 450.0, 300.0, 0.5]], atol=1e-4)
    boxes = decode_person_boxes(output, transform, 640, 640, multi_label=True)
    np.testing.assert_allclose(boxes[:, 4], [0.6, 0.5], atol=1e-6)
    np.testing.assert_allclose(boxes[0, :4], [150.0, 100.0, 250.0, 300.0], atol=1e-4)


@pytest.mark.parametrize("multi_label", [False, True])
def test_decode_threshold_is_strict(multi_label: bool) -> None:
    transform = LetterboxTransform(1.0, 0.0, 0.0)
    output = make_output([(3, 200.0, 200.0, 100.0, 200.0, 0, 0.25), (9, 400.0, 200.0, 100.0, 200.0, 0, 0.2500001)])
    assert output[0, 4, 3] == np.float32(0.25)
    boxes = decode_person_boxes(output, transform, 640, 640, score_threshold=0.25, multi_label=multi_label)
    assert boxes.shape == (1, 5) and boxes[0, 0] == pytest.approx(350.0)


def test_letterbox_per_axis_gains_on_odd_size() -> None:
    # 641 x 481: r = 640 / 641; the image becomes 640 x 480 (round(480.25)), so the real vertical
    # factor is 480 / 481, not r.
    tensor, transform = letterbox(np.full((481, 641, 3), 255, dtype=np.uint8))
    assert (transform.pad_x, transform.pad_y) == (0.0, 80.0)
    assert transform.gain_x == pytest.approx(640 / 641) and transform.gain_y == pytest.approx(480 / 481)
    assert tensor[0, 0, 79, 320] != 1.0 and tensor[0, 0, 80, 320] == 1.0 and tensor[0, 0, 559, 320] == 1.0
    assert tensor[0, 0, 560, 320] != 1.0
    # A box from letterbox (100, 100) to (300, 540) goes back with each axis' own factor.
    boxes = decode_person_boxes(make_output([(0, 200.0, 320.0, 200.0, 440.0, 0, 0.9)]), transform, 641, 481)
    expected = [100 * 641 / 640, 20 * 481 / 480, 300 * 641 / 640, 460 * 481 / 480]
    np.testing.assert_allclose(boxes[0, :4], expected, atol=1e-3)
    single_gain_y2 = 460 / transform.scale
    assert abs(single_gain_y2 - expected[3]) > 0.2  # the old single-gain mapping was off by this


def test_detector_multi_label_needs_a_family_that_has_it() -> None:
    with pytest.raises(ValueError, match="no options"):
        detector_families.get_detector_family("yolov8").with_options(nms_free=True)
    assert detector_families.get_detector_family("yolov8").with_options(multi_label=True).multi_label
    with pytest.raises(ValueError, match="no options"):
        HalfScaleBoxesFamily().with_options(multi_label=True)


def test_decode_empty() -> None:
    boxes = decode_person_boxes(np.zeros((1, 84, 8400), np.float32), LetterboxTransform(1.0, 0.0, 0.0), 640, 480)
    assert boxes.shape == (0, 5)


# ----------------------------------------------------------------------------- detector families


@pytest.fixture
def registry(monkeypatch):
    """The family registry, emptied of runtime registrations for one test."""
    monkeypatch.setattr(detector_families, "DETECTOR_FAMILIES", detector_families.family_registry())
    return detector_families


class HalfScaleBoxesFamily(DetectorFamily):
    """A made-up output layout: ``boxes`` (1, 3, 5) = x0, y0, x1, y1, score in a half-size input image."""

    name = "test_half_scale_boxes"
    contract = ModelContract("half-scale test detector", inputs=(TensorContract("pixels", ((1, 3, 32, 40),)),),
                             outputs=(TensorContract("boxes", ((1, 3, 5),)),))

    def preprocess(self, rgb):
        half = rgb[::2, ::2].transpose(2, 0, 1)[None].astype(np.float32) / 255.0
        return {"pixels": half}, 2.0

    def decode(self, outputs, context, image_w, image_h, score_threshold, iou_threshold, max_detections):
        rows = np.asarray(outputs["boxes"], np.float64)[0]
        rows = rows[rows[:, 4] >= score_threshold]
        boxes = rows[:, :4] * context
        keep = nms(boxes, rows[:, 4], iou_threshold, max_detections)
        return np.concatenate([boxes[keep], rows[keep, 4:]], axis=1).astype(np.float32)


class FixedOutputBackend(EngineBackend):
    """An engine that answers every input with the same ``boxes``."""

    def __init__(self, boxes: np.ndarray) -> None:
        self.model_path = "half_scale.onnx"
        self._inputs = {"pixels": TensorSpec((1, 3, 32, 40))}
        self._outputs = {"boxes": TensorSpec((1, 3, 5))}
        self._precision = "fp32"
        self.boxes = boxes
        self.inputs = []

    def run(self, inputs):
        self.inputs.append(inputs["pixels"])
        return {"boxes": self.boxes[None]}


def test_a_family_registered_from_outside_runs_through_person_detector(registry) -> None:
    registry.register_detector_family(HalfScaleBoxesFamily())
    assert registry.detector_family_names() == ["test_half_scale_boxes", "yolov8"]
    backend = FixedOutputBackend(np.array([[1, 2, 11, 22, 0.4], [20, 5, 30, 25, 0.9], [0, 0, 1, 1, 0.1]], np.float32))
    detector = PersonDetector(backend, score_threshold=0.3, family="test_half_scale_boxes")
    boxes = detector.detect(np.full((64, 80, 3), 255, np.uint8))
    np.testing.assert_allclose(boxes, [[40, 10, 60, 50, 0.9], [2, 4, 22, 44, 0.4]], rtol=1e-6)
    assert boxes.dtype == np.float32 and backend.inputs[0].shape == (1, 3, 32, 40)
    detector.score_threshold = 0.5  # thresholds apply from the next frame
    assert len(detector.detect(np.zeros((64, 80, 3), np.uint8))) == 1
    # and the node's parameters accept it
    assert params_from_values(DetectorParams, {"detector_family": "test_half_scale_boxes"}).detector_family \
        == "test_half_scale_boxes"


def test_a_family_checks_its_contract_on_the_engine(registry) -> None:
    registry.register_detector_family(HalfScaleBoxesFamily())
    with pytest.raises(ModelContractError, match="missing input 'images'"):
        PersonDetector(FixedOutputBackend(np.zeros((3, 5), np.float32)), family="yolov8")


def test_an_unknown_family_names_the_known_ones(registry) -> None:
    with pytest.raises(ValueError, match=r"unknown detector family 'yolov9'; known: yolov8"):
        registry.get_detector_family("yolov9")
    with pytest.raises(ValueError, match=r"unknown detector family 'yolov9'; known: yolov8"):
        PersonDetector(FixedOutputBackend(np.zeros((3, 5), np.float32)), family="yolov9")
    with pytest.raises(ParamsError, match=r"detector_family = 'yolov9' is not one of \['yolov8'\]"):
        params_from_values(DetectorParams, {"detector_family": "yolov9"})
    with pytest.raises(TypeError):
        registry.register_detector_family("yolov9")


def test_yolov8_is_the_default_family() -> None:
    family = detector_families.get_detector_family(detector_families.DEFAULT_DETECTOR_FAMILY)
    assert family.name == "yolov8" and family.contract is YOLOV8_CONTRACT
    inputs, transform = family.preprocess(np.zeros((480, 640, 3), np.uint8))
    assert list(inputs) == ["images"] and inputs["images"].shape == (1, 3, 640, 640)
    assert (transform.scale, transform.pad_x, transform.pad_y) == (1.0, 0.0, 80.0)


def test_the_letterbox_side_is_the_models_and_its_anchors_must_fit(tmp_path) -> None:
    # A 320 export (a cheaper CPU detector): letterboxed to 320 and decoded with 2,100 anchors.
    import onnx
    from onnx import TensorProto, helper

    from leapnbv_perception.backends.onnxruntime_backend import OnnxRuntimeBackend
    from leapnbv_perception.detector import PersonDetector
    from leapnbv_perception.model_contracts import ModelContractError, yolo_anchor_count

    assert yolo_anchor_count(640) == 8400 and yolo_anchor_count(320) == 2100 and yolo_anchor_count(480) == 4725

    def model(size: int, anchors: int) -> str:
        # output0 = a constant: one person box of 100 x 200 letterbox pixels centred in the input, score 0.9
        values = np.zeros((1, 84, anchors), np.float32)
        values[0, :4, 0] = [size / 2, size / 2, 100.0, 200.0]
        values[0, 4, 0] = 0.9
        const = helper.make_tensor("const", TensorProto.FLOAT, values.shape, values.ravel())
        graph = helper.make_graph(
            [helper.make_node("ReduceSum", ["images"], ["total"], keepdims=0),
             helper.make_node("Mul", ["total", "zero"], ["nothing"]),
             helper.make_node("Add", ["const", "nothing"], ["output0"])], "g",
            [helper.make_tensor_value_info("images", TensorProto.FLOAT, [1, 3, size, size])],
            [helper.make_tensor_value_info("output0", TensorProto.FLOAT, [1, 84, anchors])],
            [const, helper.make_tensor("zero", TensorProto.FLOAT, [], [0.0])])
        path = str(tmp_path / f"yolo_{size}_{anchors}.onnx")
        onnx.save(helper.make_model(graph, opset_imports=[helper.make_opsetid("", 13)]), path)
        return path

    detector = PersonDetector(OnnxRuntimeBackend(model(320, 2100)))
    assert detector.family.input_size == 320
    boxes = detector.detect(np.zeros((480, 640, 3), np.uint8))  # gain 0.5, padded 40 px top and bottom
    np.testing.assert_allclose(boxes[0, :4], [220.0, 40.0, 420.0, 440.0], atol=1e-3)
    with pytest.raises(ModelContractError, match="a 320x320 input has 2100 anchors, but 'output0' has 8400"):
        PersonDetector(OnnxRuntimeBackend(model(320, 8400)))
