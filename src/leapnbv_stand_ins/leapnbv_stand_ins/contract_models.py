"""CONTRACT ONNX models: the exact input/output names and shapes of the YOLOv8 and SMPLer-X
exports, computed by small fixed graphs from the input pixels.

They are test doubles with no accuracy whatsoever: they exist so that the real loading,
pre-processing, inference and post-processing code runs end to end without the licensed
weights. Their outputs depend on the pixels (a wrong crop or letterbox changes them):

- Contract detector: "a person" is saturated red. The 640x640 image is average-pooled into
  the three YOLOv8 grids (80x80, 40x40, 20x20 cells of 8, 16, 32 px = 8400 anchors); per
  cell the person logit is 12 r - 6 g - 6 b - 3 (grey, black and the 114-grey padding stay
  negative). Anchor 0 carries the box enclosing every 8-px cell with a positive logit and
  the highest person score; every other anchor carries a box and scores from a fixed linear
  map of its cell's mean colour, with the person score scaled by 0.2 so it stays below the
  default 0.25 threshold. So one red figure gives one person box around it.
- Contract HMR: the crop is average-pooled to an 8x6 grid of mean colours (144 numbers),
  passed through a fixed seeded tanh layer and one linear head per output. Rotation heads
  are bounded offsets around a fixed pose (root: 180 deg about x, i.e. upright and facing
  the camera; other joints: identity), betas in [-1, 1], expression in [-0.5, 0.5], cam_param
  t_xy in [-0.2, 0.2] and gamma in [-0.5, 0.5].
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Dict, List, Tuple

import numpy as np

from leapnbv_common.array_types import Float32Array
from leapnbv_common.atomic_files import write_file_atomically
from leapnbv_perception.model_contracts import (
    HMR_INPUT_NAME,
    HMR_OUTPUT_SIZES,
    YOLO_INPUT_NAME,
    YOLO_NUM_ANCHORS,
    YOLO_NUM_CLASSES,
    YOLO_OUTPUT_NAME,
)

if TYPE_CHECKING:  # onnx is imported where a model is written (the stand-ins load without it)
    from onnx import ModelProto, ValueInfoProto

# Opset 13: accepted by onnxruntime 1.20 and by TensorRT 8.5's ONNX parser.
OPSET = 13
IR_VERSION = 8
YOLO_STRIDES = (8, 16, 32)
HMR_POOL_GRID = (8, 6)
HMR_HIDDEN = 64
HMR_SEED = 20240611
YOLO_SEED = 20240612

# 6D of the fixed pose around which the rotation heads vary (x[0::2] = col 1, x[1::2] = col 2).
_IDENTITY_6D = np.array([1.0, 0.0, 0.0, 1.0, 0.0, 0.0], dtype=np.float32)
_FLIP_X_6D = np.array([1.0, 0.0, 0.0, -1.0, 0.0, 0.0], dtype=np.float32)  # diag(1, -1, -1)


def _save_atomically(model: ModelProto, path: str) -> None:
    """Check the model and write it via a temporary file in the same folder."""
    import onnx

    onnx.checker.check_model(model)
    write_file_atomically(path, lambda temporary: onnx.save(model, temporary))


def _yolo_anchor_constants() -> Tuple[Float32Array, Float32Array]:
    """Anchor centres (1, 2, 8400) and strides (1, 1, 8400) in letterbox pixels."""
    centres = []
    strides = []
    for stride in YOLO_STRIDES:
        cells = 640 // stride
        ys, xs = np.meshgrid(np.arange(cells), np.arange(cells), indexing="ij")
        centres.append(np.stack([(xs.reshape(-1) + 0.5) * stride, (ys.reshape(-1) + 0.5) * stride]))
        strides.append(np.full(cells * cells, float(stride)))
    return (
        np.concatenate(centres, axis=1)[None].astype(np.float32),
        np.concatenate(strides)[None, None].astype(np.float32),
    )


def build_contract_detector() -> ModelProto:
    """The contract YOLOv8 model: `images` (1,3,640,640) -> `output0` (1,84,8400).

    Returns:
        onnx.ModelProto.
    """
    import onnx
    from onnx import TensorProto, helper, numpy_helper

    rng = np.random.default_rng(YOLO_SEED)
    centres, strides = _yolo_anchor_constants()
    weights = np.zeros((4 + YOLO_NUM_CLASSES, 3), dtype=np.float32)
    bias = np.zeros((4 + YOLO_NUM_CLASSES, 1), dtype=np.float32)
    weights[0:2] = rng.normal(0.0, 0.5, size=(2, 3))  # centre offsets (tanh, in strides)
    weights[2:4] = np.array([[2.0, -1.0, -1.0], [2.0, -1.0, -1.0]])  # redder cells: bigger boxes
    weights[4] = np.array([12.0, -6.0, -6.0])  # person: red
    bias[4] = -3.0
    weights[5:] = rng.normal(0.0, 2.0, size=(YOLO_NUM_CLASSES - 1, 3))
    bias[5:] = -4.0

    initializers = [
        numpy_helper.from_array(weights, "head_weight"),
        numpy_helper.from_array(bias, "head_bias"),
        numpy_helper.from_array(centres, "anchor_centres"),
        numpy_helper.from_array(strides, "anchor_strides"),
        numpy_helper.from_array(np.array([1, 3, -1], dtype=np.int64), "pooled_shape"),
        numpy_helper.from_array(np.array([4.0], dtype=np.float32), "size_gain"),
        numpy_helper.from_array(np.array([1.0], dtype=np.float32), "one"),
    ]
    for name, (start, end) in {"xy": (0, 2), "wh": (2, 4), "cls": (4, 4 + YOLO_NUM_CLASSES)}.items():
        initializers.append(numpy_helper.from_array(np.array([start], dtype=np.int64), "%s_start" % name))
        initializers.append(numpy_helper.from_array(np.array([end], dtype=np.int64), "%s_end" % name))
    initializers.append(numpy_helper.from_array(np.array([1], dtype=np.int64), "axis_1"))
    fine_cells = 640 // YOLO_STRIDES[0]
    ys, xs = np.meshgrid(np.arange(fine_cells), np.arange(fine_cells), indexing="ij")
    cell_x = (xs.reshape(1, 1, -1) * YOLO_STRIDES[0]).astype(np.float32)
    cell_y = (ys.reshape(1, 1, -1) * YOLO_STRIDES[0]).astype(np.float32)
    class_gain = np.ones((1, YOLO_NUM_CLASSES, 1), dtype=np.float32)
    class_gain[0, 0, 0] = 0.2
    initializers += [
        numpy_helper.from_array(weights[4:5], "person_weight"),
        numpy_helper.from_array(bias[4:5], "person_bias"),
        numpy_helper.from_array(class_gain, "class_gain"),
        numpy_helper.from_array(np.array([0.0], dtype=np.float32), "zero"),
        numpy_helper.from_array(np.array([0.5], dtype=np.float32), "half"),
        numpy_helper.from_array(np.array([1e6], dtype=np.float32), "far"),
        numpy_helper.from_array(np.array([-1e6], dtype=np.float32), "near"),
        numpy_helper.from_array(cell_x, "cell_x_min"),
        numpy_helper.from_array(cell_y, "cell_y_min"),
        numpy_helper.from_array(cell_x + YOLO_STRIDES[0], "cell_x_max"),
        numpy_helper.from_array(cell_y + YOLO_STRIDES[0], "cell_y_max"),
        numpy_helper.from_array(np.array([5], dtype=np.int64), "other_start"),
        numpy_helper.from_array(np.array([4 + YOLO_NUM_CLASSES], dtype=np.int64), "other_end"),
        numpy_helper.from_array(np.array([0], dtype=np.int64), "zero_index"),
        numpy_helper.from_array(np.array([1], dtype=np.int64), "one_index"),
        numpy_helper.from_array(np.array([YOLO_NUM_ANCHORS], dtype=np.int64), "end_index"),
        numpy_helper.from_array(np.array([2], dtype=np.int64), "axis_2"),
    ]

    nodes = []
    pooled_names = []
    for stride in YOLO_STRIDES:
        pooled = "pooled_%d" % stride
        nodes.append(
            helper.make_node(
                "AveragePool", [YOLO_INPUT_NAME], [pooled], kernel_shape=[stride, stride], strides=[stride, stride]
            )
        )
        nodes.append(helper.make_node("Reshape", [pooled, "pooled_shape"], [pooled + "_flat"]))
        pooled_names.append(pooled + "_flat")
    nodes += [
        helper.make_node("Concat", pooled_names, ["cell_colours"], axis=2),  # (1, 3, 8400)
        helper.make_node("MatMul", ["head_weight", "cell_colours"], ["head_linear"]),  # (1, 84, 8400)
        helper.make_node("Add", ["head_linear", "head_bias"], ["head_raw"]),
        helper.make_node("Slice", ["head_raw", "xy_start", "xy_end", "axis_1"], ["xy_raw"]),
        helper.make_node("Slice", ["head_raw", "wh_start", "wh_end", "axis_1"], ["wh_raw"]),
        helper.make_node("Slice", ["head_raw", "cls_start", "cls_end", "axis_1"], ["cls_raw"]),
        # cx, cy = anchor centre + stride * tanh(.)
        helper.make_node("Tanh", ["xy_raw"], ["xy_unit"]),
        helper.make_node("Mul", ["xy_unit", "anchor_strides"], ["xy_offset"]),
        helper.make_node("Add", ["anchor_centres", "xy_offset"], ["xy"]),
        # w, h = stride * 4 * (1 + sigmoid(.))
        helper.make_node("Sigmoid", ["wh_raw"], ["wh_unit"]),
        helper.make_node("Add", ["wh_unit", "one"], ["wh_factor"]),
        helper.make_node("Mul", ["wh_factor", "anchor_strides"], ["wh_strided"]),
        helper.make_node("Mul", ["wh_strided", "size_gain"], ["wh"]),
        helper.make_node("Sigmoid", ["cls_raw"], ["scores_raw"]),
        helper.make_node("Mul", ["scores_raw", "class_gain"], ["scores"]),
        helper.make_node("Concat", ["xy", "wh", "scores"], ["dense"], axis=1),
        # Anchor 0: the box around all positive 8-px cells, scored by the best cell.
        helper.make_node("MatMul", ["person_weight", "pooled_8_flat"], ["cell_person_linear"]),
        helper.make_node("Add", ["cell_person_linear", "person_bias"], ["cell_person_logit"]),
        helper.make_node("Greater", ["cell_person_logit", "zero"], ["cell_is_person"]),
        helper.make_node("Where", ["cell_is_person", "cell_x_min", "far"], ["masked_x_min"]),
        helper.make_node("Where", ["cell_is_person", "cell_y_min", "far"], ["masked_y_min"]),
        helper.make_node("Where", ["cell_is_person", "cell_x_max", "near"], ["masked_x_max"]),
        helper.make_node("Where", ["cell_is_person", "cell_y_max", "near"], ["masked_y_max"]),
        helper.make_node("ReduceMin", ["masked_x_min"], ["x_min"], axes=[2], keepdims=1),
        helper.make_node("ReduceMin", ["masked_y_min"], ["y_min"], axes=[2], keepdims=1),
        helper.make_node("ReduceMax", ["masked_x_max"], ["x_max"], axes=[2], keepdims=1),
        helper.make_node("ReduceMax", ["masked_y_max"], ["y_max"], axes=[2], keepdims=1),
        helper.make_node("Add", ["x_min", "x_max"], ["x_sum"]),
        helper.make_node("Add", ["y_min", "y_max"], ["y_sum"]),
        helper.make_node("Mul", ["x_sum", "half"], ["box_cx"]),
        helper.make_node("Mul", ["y_sum", "half"], ["box_cy"]),
        helper.make_node("Sub", ["x_max", "x_min"], ["box_w"]),
        helper.make_node("Sub", ["y_max", "y_min"], ["box_h"]),
        helper.make_node("Sigmoid", ["cell_person_logit"], ["cell_person_score"]),
        helper.make_node("ReduceMax", ["cell_person_score"], ["best_person_score"], axes=[2], keepdims=1),
        helper.make_node("Slice", ["dense", "other_start", "other_end", "axis_1"], ["other_rows"]),
        helper.make_node("Slice", ["other_rows", "zero_index", "one_index", "axis_2"], ["other_anchor0"]),
        helper.make_node(
            "Concat", ["box_cx", "box_cy", "box_w", "box_h", "best_person_score", "other_anchor0"], ["anchor0"], axis=1
        ),
        helper.make_node("Slice", ["dense", "one_index", "end_index", "axis_2"], ["dense_rest"]),
        helper.make_node("Concat", ["anchor0", "dense_rest"], [YOLO_OUTPUT_NAME], axis=2),
    ]
    graph = helper.make_graph(
        nodes,
        "contract_yolov8_person_detector",
        [helper.make_tensor_value_info(YOLO_INPUT_NAME, TensorProto.FLOAT, [1, 3, 640, 640])],
        [helper.make_tensor_value_info(YOLO_OUTPUT_NAME, TensorProto.FLOAT, [1, 4 + YOLO_NUM_CLASSES, 8400])],
        initializers,
    )
    model = helper.make_model(
        graph,
        opset_imports=[helper.make_opsetid("", OPSET)],
        producer_name="leapnbv_stand_ins.contract_models",
        doc_string="CONTRACT model with the YOLOv8 export's names and shapes; no accuracy.",
    )
    model.ir_version = IR_VERSION
    return onnx.shape_inference.infer_shapes(model)


def _hmr_head_layout() -> Dict[str, Tuple[float, Float32Array]]:
    """Per output: (tanh scale, offset vector) around which it varies."""
    layout: Dict[str, Tuple[float, Float32Array]] = {}
    for name, size in HMR_OUTPUT_SIZES.items():
        if name == "root_pose":
            layout[name] = (0.3, _FLIP_X_6D)
        elif name.endswith("_pose"):
            layout[name] = (0.25, np.tile(_IDENTITY_6D, size // 6))
        elif name == "betas":
            layout[name] = (1.0, np.zeros(size, dtype=np.float32))
        elif name == "expression":
            layout[name] = (0.5, np.zeros(size, dtype=np.float32))
        else:  # cam_param: t_x, t_y, gamma
            layout[name] = (1.0, np.zeros(size, dtype=np.float32))
    return layout


def build_contract_hmr(input_hw: Tuple[int, int] = (512, 384)) -> ModelProto:
    """The contract SMPLer-X encoder + heads: `img` (1,3,H,W) -> the eight named heads.

    Args:
        input_hw: (512, 384) or (256, 192).

    Returns:
        onnx.ModelProto.

    Raises:
        ValueError: for another input size.
    """
    import onnx
    from onnx import TensorProto, helper, numpy_helper

    height, width = int(input_hw[0]), int(input_hw[1])
    if (height, width) not in ((512, 384), (256, 192)):
        raise ValueError("contract HMR input must be 512x384 or 256x192, got %dx%d" % (height, width))
    rng = np.random.default_rng(HMR_SEED)
    grid_h, grid_w = HMR_POOL_GRID
    num_features = 3 * grid_h * grid_w
    hidden_weight = rng.normal(0.0, 4.0 / np.sqrt(num_features), size=(num_features, HMR_HIDDEN)).astype(np.float32)
    hidden_bias = rng.normal(0.0, 0.1, size=(HMR_HIDDEN,)).astype(np.float32)

    initializers = [
        numpy_helper.from_array(np.array([1, num_features], dtype=np.int64), "features_shape"),
        numpy_helper.from_array(np.array([0.5], dtype=np.float32), "grey"),
        numpy_helper.from_array(hidden_weight, "hidden_weight"),
        numpy_helper.from_array(hidden_bias, "hidden_bias"),
    ]
    nodes = [
        helper.make_node(
            "AveragePool",
            [HMR_INPUT_NAME],
            ["pooled"],
            kernel_shape=[height // grid_h, width // grid_w],
            strides=[height // grid_h, width // grid_w],
        ),
        helper.make_node("Reshape", ["pooled", "features_shape"], ["features_raw"]),
        helper.make_node("Sub", ["features_raw", "grey"], ["features"]),
        helper.make_node("MatMul", ["features", "hidden_weight"], ["hidden_linear"]),
        helper.make_node("Add", ["hidden_linear", "hidden_bias"], ["hidden_raw"]),
        helper.make_node("Tanh", ["hidden_raw"], ["hidden"]),
    ]
    outputs: List[ValueInfoProto] = []
    for name, (scale, offset) in _hmr_head_layout().items():
        size = HMR_OUTPUT_SIZES[name]
        weight = rng.normal(0.0, 1.0 / np.sqrt(HMR_HIDDEN), size=(HMR_HIDDEN, size)).astype(np.float32)
        initializers += [
            numpy_helper.from_array(weight, name + "_weight"),
            numpy_helper.from_array(np.full((size,), scale, dtype=np.float32), name + "_scale"),
            numpy_helper.from_array(offset.astype(np.float32).reshape(size), name + "_offset"),
        ]
        nodes += [
            helper.make_node("MatMul", ["hidden", name + "_weight"], [name + "_linear"]),
            helper.make_node("Tanh", [name + "_linear"], [name + "_unit"]),
            helper.make_node("Mul", [name + "_unit", name + "_scale"], [name + "_scaled"]),
            helper.make_node("Add", [name + "_scaled", name + "_offset"], [name]),
        ]
        outputs.append(helper.make_tensor_value_info(name, TensorProto.FLOAT, [1, size]))
    graph = helper.make_graph(
        nodes,
        "contract_smplerx_encoder_heads",
        [helper.make_tensor_value_info(HMR_INPUT_NAME, TensorProto.FLOAT, [1, 3, height, width])],
        outputs,
        initializers,
    )
    model = helper.make_model(
        graph,
        opset_imports=[helper.make_opsetid("", OPSET)],
        producer_name="leapnbv_stand_ins.contract_models",
        doc_string="CONTRACT model with the SMPLer-X encoder+heads export's names and shapes; no accuracy.",
    )
    model.ir_version = IR_VERSION
    return onnx.shape_inference.infer_shapes(model)


def write_contract_detector(path: str) -> str:
    """Write the contract YOLOv8 model (atomic). Returns the path."""
    _save_atomically(build_contract_detector(), path)
    return path


def write_contract_hmr(path: str, input_hw: Tuple[int, int] = (512, 384)) -> str:
    """Write the contract SMPLer-X model for `input_hw` (atomic). Returns the path."""
    _save_atomically(build_contract_hmr(input_hw), path)
    return path
