"""Input/output names and shapes the detector and HMR engines must declare, and their check.

YOLOv8 person detector (ultralytics ONNX export, `yolov8s.onnx`):

    input  `images`  float32 (1, 3, 640, 640)  RGB / 255, NCHW, letterboxed
    output `output0` float32 (1, 84, 8400)     (cx, cy, w, h) in letterbox pixels + 80 class
                                                scores (sigmoid applied, no objectness)

SMPLer-X encoder + heads export (one engine, rotations in 6D):

    input  `img`        float32 (1, 3, 512, 384) or (1, 3, 256, 192)  RGB / 255, NCHW
    output `root_pose`  (1, 6)     global orientation, 6D
           `body_pose`  (1, 126)   21 body joints x 6D
           `lhand_pose` (1, 90)    15 left-hand joints x 6D (predicted on a mirrored crop)
           `rhand_pose` (1, 90)    15 right-hand joints x 6D
           `jaw_pose`   (1, 6)     jaw, 6D
           `betas`      (1, 10)    shape coefficients
           `expression` (1, 10)    expression coefficients
           `cam_param`  (1, 3)     (t_x, t_y, gamma logit of t_z)

Dimensions a backend declares as symbolic (None or a string, e.g. a dynamic batch) match any
expected size.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Dict, Mapping, Optional, Sequence, Tuple, Union

Dim = Union[int, str, None]
Shape = Tuple[Dim, ...]


class ModelContractError(ValueError):
    """A model's declared inputs/outputs do not match the contract its consumer expects."""


@dataclass(frozen=True)
class TensorContract:
    """One named tensor with the shapes it may have.

    Attributes:
        name: exact tensor name in the exported model.
        allowed_shapes: every accepted static shape (more than one for the HMR input).
        meaning: one line for error messages and documentation.
    """

    name: str
    allowed_shapes: Tuple[Tuple[int, ...], ...]
    meaning: str = ""


@dataclass(frozen=True)
class ModelContract:
    """Named inputs and outputs of one exported model.

    Attributes:
        model_name: what the model is (used in error messages).
        inputs: tensors the model must take.
        outputs: tensors the model must return (extra outputs are allowed).
    """

    model_name: str
    inputs: Tuple[TensorContract, ...]
    outputs: Tuple[TensorContract, ...]

    def output_names(self) -> Tuple[str, ...]:
        """Names of the required outputs, in contract order."""
        return tuple(tensor.name for tensor in self.outputs)


YOLO_INPUT_NAME = "images"
YOLO_OUTPUT_NAME = "output0"
YOLO_INPUT_SIZE = 640  # the ultralytics export's default; the node reads the model's own (yolo_input_size)
YOLO_NUM_CLASSES = 80
YOLO_NUM_ANCHORS = 8400  # at 640
# Square letterbox sides a YOLOv8 export may have here (ultralytics `imgsz`, multiples of the largest stride).
YOLO_INPUT_SIZES = (320, 384, 416, 480, 512, 576, 640, 768, 960, 1280)


def yolo_anchor_count(size: int) -> int:
    """Anchor points of a YOLOv8 head at strides 8, 16 and 32 for a size x size input (8,400 at 640)."""
    return sum((size // stride) ** 2 for stride in (8, 16, 32))


YOLOV8_CONTRACT = ModelContract(
    model_name="YOLOv8 detector (ultralytics ONNX export)",
    inputs=(TensorContract(YOLO_INPUT_NAME, tuple((1, 3, s, s) for s in YOLO_INPUT_SIZES),
                           "RGB/255 NCHW letterboxed image, square, a multiple of 32 (640 by default)"),),
    outputs=(
        TensorContract(
            YOLO_OUTPUT_NAME,
            tuple((1, 4 + YOLO_NUM_CLASSES, yolo_anchor_count(s)) for s in YOLO_INPUT_SIZES),
            "cx, cy, w, h (letterbox pixels) + 80 sigmoid class scores per anchor",
        ),
    ),
)

HMR_INPUT_NAME = "img"
HMR_INPUT_SHAPES = ((1, 3, 512, 384), (1, 3, 256, 192))

# Output name -> length per batch item (6D rotations are joints x 6).
HMR_OUTPUT_SIZES: Dict[str, int] = {
    "root_pose": 6,
    "body_pose": 21 * 6,
    "lhand_pose": 15 * 6,
    "rhand_pose": 15 * 6,
    "jaw_pose": 6,
    "betas": 10,
    "expression": 10,
    "cam_param": 3,
}

SMPLERX_CONTRACT = ModelContract(
    model_name="SMPLer-X encoder + heads export",
    inputs=(TensorContract(HMR_INPUT_NAME, HMR_INPUT_SHAPES, "RGB/255 NCHW body crop"),),
    outputs=tuple(TensorContract(name, ((1, size),)) for name, size in HMR_OUTPUT_SIZES.items()),
)


def _shape_matches(declared: Sequence[Dim], expected: Sequence[int]) -> bool:
    """True when `declared` equals `expected`, symbolic dimensions matching anything."""
    if len(declared) != len(expected):
        return False
    for declared_dim, expected_dim in zip(declared, expected):
        if isinstance(declared_dim, int) and declared_dim != expected_dim:
            return False
    return True


def _describe(specs: Mapping[str, Sequence[Dim]]) -> str:
    return ", ".join("%s%s" % (name, tuple(shape)) for name, shape in specs.items()) or "(none)"


def _describe_contract(tensors: Sequence[TensorContract]) -> str:
    parts = []
    for tensor in tensors:
        shapes = " or ".join(str(shape) for shape in tensor.allowed_shapes)
        parts.append("%s%s" % (tensor.name, shapes))
    return ", ".join(parts)


def check_specs(
    contract: ModelContract,
    input_shapes: Mapping[str, Sequence[Dim]],
    output_shapes: Mapping[str, Sequence[Dim]],
    source: str = "",
) -> None:
    """Check declared input/output shapes against a contract.

    Args:
        contract: what the consumer expects.
        input_shapes: name -> declared shape of every model input.
        output_shapes: name -> declared shape of every model output.
        source: model file (or other origin) named in the error message.

    Raises:
        ModelContractError: listing every problem, the expected tensors and the found ones.
    """
    problems = []
    for kind, tensors, declared in (
        ("input", contract.inputs, input_shapes),
        ("output", contract.outputs, output_shapes),
    ):
        for tensor in tensors:
            if tensor.name not in declared:
                problems.append("missing %s '%s'" % (kind, tensor.name))
                continue
            shape = tuple(declared[tensor.name])
            if not any(_shape_matches(shape, allowed) for allowed in tensor.allowed_shapes):
                problems.append(
                    "%s '%s' has shape %s, expected %s"
                    % (kind, tensor.name, shape, " or ".join(str(s) for s in tensor.allowed_shapes))
                )
    if problems:
        where = " in %s" % source if source else ""
        raise ModelContractError(
            "%s contract not met%s: %s.\n  expected inputs: %s\n  expected outputs: %s\n"
            "  found inputs: %s\n  found outputs: %s"
            % (
                contract.model_name,
                where,
                "; ".join(problems),
                _describe_contract(contract.inputs),
                _describe_contract(contract.outputs),
                _describe(input_shapes),
                _describe(output_shapes),
            )
        )


def check_backend_contract(backend: object, contract: ModelContract, source: Optional[str] = None) -> None:
    """Check an EngineBackend's declared inputs/outputs against a contract.

    Args:
        backend: an EngineBackend (anything with `input_specs`, `output_specs` mappings of
            name -> TensorSpec, and optionally `model_path`).
        contract: what the consumer expects.
        source: model file named in the error; defaults to `backend.model_path`.

    Raises:
        ModelContractError: when a required tensor is missing or has the wrong shape.
    """
    if source is None:
        source = str(getattr(backend, "model_path", ""))
    inputs = {name: spec.shape for name, spec in backend.input_specs.items()}  # type: ignore[attr-defined]
    outputs = {name: spec.shape for name, spec in backend.output_specs.items()}  # type: ignore[attr-defined]
    check_specs(contract, inputs, outputs, source)
