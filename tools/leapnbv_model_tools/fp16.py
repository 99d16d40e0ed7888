"""fp16-check: find the normalizations that overflow or lose precision in FP16, and guard them.

    python -m leapnbv_model_tools fp16-check model.onnx --calib CROPS --out DIR
        [--headroom 1.0] [--tolerance 0.02] [--max-error 0.02] [--no-verify]

1. Finds every normalization of the FP32 ONNX: LayerNormalization nodes, and the pattern the
   project's exporter writes LayerNorm as (``ReduceMean(x)``, ``Sub``, ``Mul(c, c)`` or
   ``Pow(c, 2)``, ``ReduceMean``, ``Add(eps)``, ``Sqrt``, ``Div``).
2. Runs the calibration crops through it with onnxruntime (FP32, CPU), every normalization's
   input exposed as an extra output, and records per normalization the largest sum of squares
   of the centred input over the normalized axis (what the variance's ReduceMean sums before
   it divides) and the largest absolute input.
3. Predicts, per normalization: ``overflow`` when the sum of squares times ``--headroom``, an
   input or a squared centred input exceeds FP16's largest finite value (65504), or the FP16
   emulation of the normalization on the calibration rows with the largest sums (below) gives
   inf/NaN; ``precision`` when that emulation differs from the float64 result by more than
   ``--tolerance`` (on the normalized output before the affine scale and shift, relative to
   its largest magnitude when that exceeds 1, else absolute);
   ``ok`` otherwise.
4. Writes into DIR:
   - ``<stem>.fp16.onnx``: the model in FP16 with the flagged normalizations' nodes (the
     reductions and what feeds them: mean, centring, square, variance, eps, sqrt, division)
     in FP32, Casts at the borders; graph inputs and outputs stay float32;
   - ``<stem>.precision_plan.json``: the TensorRT backend's precision plan (version 1, the
     format of leapnbv_perception.backends.precision_plan) naming those nodes, for an FP16
     engine built from the FP32 ONNX; its digest is part of the engine cache key;
   - ``<stem>.fp16_report.md`` and ``<stem>.fp16_ranges.png``: the ranges per normalization
     against the FP16 limit, the verdicts, and the verification below.
5. Verification (unless ``--no-verify``): the FP32 model (onnxruntime), the naive FP16 model
   (every node FP16) and the guarded FP16 model, run on the calibration crops by the FP16
   emulator below; the largest output difference to FP32 relative to the FP32 output's range.

FP16 emulation (onnxruntime's CPU provider has no FP16 kernels for most of these operators):
``onnx.reference.ReferenceEvaluator`` (numpy) runs the FP16 ONNX with float16 tensors, so
every tensor is stored in FP16 and every elementwise result (Add, Sub, Mul, Div, Sqrt, Pow,
Erf, Exp, ...) is rounded to FP16 after each operation (numpy's half arithmetic: computed in
float32, rounded to nearest even). ReduceMean / ReduceSum / ReduceSumSquare on float16 are
replaced by a sequential FP16 accumulation (each partial sum rounded to FP16, so a partial sum
above 65504 becomes inf), then the division by the count in FP16: the worst case of an FP16
reduction. MatMul / Gemm / Conv / ConvTranspose products are accumulated in float32 and rounded to FP16
once (numpy's half matmul, torch's float32 convolutions; what tensor-core GEMMs with FP32
accumulation do); Softmax's sum is
accumulated in float32 too. Nodes that the guarded model keeps in FP32 run in float32.

Exit codes: 0 files written (and the guarded model within ``--max-error`` of FP32 when
verified); 1 files written but the guarded FP16 model still differs from FP32 by more than
``--max-error`` on the calibration crops (the report says where); 2 bad input (missing or
unreadable model or crops, crops that do not fit the model's input, no normalization found).
Errors are one line on stderr.
"""

from __future__ import annotations

import argparse
import os
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Dict, Iterable, List, Optional, Sequence, Tuple

import numpy as np

from leapnbv_model_tools.file_hash import sha256_of

FP16_MAX = 65504.0
EMULATED_ROWS = 32  # calibration rows (largest sums of squares) each normalization is emulated on
TOOL = "leapnbv_model_tools fp16-check 1"


class Fp16CheckError(ValueError):
    """Bad input to the FP16 check (one line, naming the file)."""


# ----------------------------------------------------------------------------------------
# Finding normalizations


@dataclass
class Normalization:
    """One normalization of the graph.

    Attributes:
        name: a readable name (the scope of its nodes, e.g. ``/encoder/last_norm``).
        input: the tensor it normalizes.
        axis: the normalized axis (negative: from the end).
        eps: the epsilon added to the variance.
        nodes: the nodes to keep in FP32 when it is guarded (reductions and what feeds them).
        kind: ``"LayerNormalization"`` or ``"primitive"``.
    """

    name: str
    input: str
    axis: int
    eps: float
    nodes: List[str]
    kind: str
    stats: Dict[str, float] = field(default_factory=dict)
    verdict: str = ""
    width: int = 0


def _attribute(node, name: str, default=None):
    import onnx

    for attribute in node.attribute:
        if attribute.name == name:
            return onnx.helper.get_attribute_value(attribute)
    return default


def _constant_values(model) -> Dict[str, np.ndarray]:
    """Initializers and Constant node outputs as numpy arrays."""
    from onnx import numpy_helper

    values = {init.name: numpy_helper.to_array(init) for init in model.graph.initializer}
    for node in model.graph.node:
        if node.op_type == "Constant" and node.attribute and node.attribute[0].name == "value":
            values[node.output[0]] = numpy_helper.to_array(node.attribute[0].t)
    return values


def _reduce_axes(node, constants: Dict[str, np.ndarray]) -> Optional[Tuple[int, ...]]:
    axes = _attribute(node, "axes")
    if axes is None and len(node.input) > 1 and node.input[1] in constants:
        axes = constants[node.input[1]].tolist()
    if axes is None:
        return None
    return tuple(int(a) for a in np.atleast_1d(axes))


def _scope(node_name: str) -> str:
    return node_name.rsplit("/", 1)[0] if "/" in node_name else node_name


def find_normalizations(model) -> List[Normalization]:
    """Every LayerNormalization node and every exported reduce/square/sqrt/div LayerNorm pattern."""
    producer = {out: node for node in model.graph.node for out in node.output}
    consumers: Dict[str, List] = {}
    for node in model.graph.node:
        for name in node.input:
            consumers.setdefault(name, []).append(node)
    constants = _constant_values(model)
    found: List[Normalization] = []
    for node in model.graph.node:
        if node.op_type == "LayerNormalization":
            found.append(Normalization(node.name, node.input[0], int(_attribute(node, "axis", -1)),
                                       float(_attribute(node, "epsilon", 1e-5)), [node.name], "LayerNormalization"))
            continue
        if node.op_type != "ReduceMean":
            continue
        square = producer.get(node.input[0])
        if square is None:
            continue
        if square.op_type == "Mul" and square.input[0] == square.input[1]:
            centred_name = square.input[0]
        elif square.op_type == "Pow" and float(np.asarray(constants.get(square.input[1], np.nan)).ravel()[0]) == 2.0:
            centred_name = square.input[0]
        else:
            continue
        sub = producer.get(centred_name)
        if sub is None or sub.op_type != "Sub":
            continue
        mean = producer.get(sub.input[1])
        if mean is None or mean.op_type != "ReduceMean" or mean.input[0] != sub.input[0]:
            continue
        axes = _reduce_axes(node, constants)
        if axes is None or len(axes) != 1 or _reduce_axes(mean, constants) != axes:
            continue
        nodes = [mean.name, sub.name, square.name, node.name]
        eps = 0.0
        current = node.output[0]
        following = consumers.get(current, [])
        if len(following) == 1 and following[0].op_type == "Add":
            add = following[0]
            other = add.input[1] if add.input[0] == current else add.input[0]
            eps = float(np.asarray(constants.get(other, 0.0)).ravel()[0])
            nodes.append(add.name)
            current = add.output[0]
            following = consumers.get(current, [])
        if len(following) == 1 and following[0].op_type == "Sqrt":
            nodes.append(following[0].name)
            current = following[0].output[0]
            following = consumers.get(current, [])
            if len(following) == 1 and following[0].op_type == "Div" and following[0].input[1] == current:
                nodes.append(following[0].name)
        for constant_node in model.graph.node:  # eps / exponent constants used only inside the pattern
            if constant_node.op_type == "Constant":
                users = consumers.get(constant_node.output[0], [])
                if users and all(user.name in nodes for user in users):
                    nodes.append(constant_node.name)
        found.append(Normalization(_scope(node.name), sub.input[0], axes[0], eps, nodes, "primitive"))
    return found


# ----------------------------------------------------------------------------------------
# FP16 arithmetic


def sequential_sum_fp16(values: np.ndarray, axis: int, keepdims: bool = True) -> np.ndarray:
    """Sum along ``axis`` accumulated in FP16, one element at a time (each partial sum rounded)."""
    moved = np.moveaxis(np.asarray(values, dtype=np.float16), axis, 0)
    total = np.zeros(moved.shape[1:], dtype=np.float16)
    with np.errstate(over="ignore", invalid="ignore"):
        for index in range(moved.shape[0]):
            total = (total + moved[index]).astype(np.float16)
    if keepdims:
        total = np.expand_dims(total, axis)
    return total


def normalize_fp16(rows: np.ndarray, eps: float) -> np.ndarray:
    """The exported LayerNorm (without affine) on (N, D) rows, emulated in FP16."""
    with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
        x = rows.astype(np.float16)
        count = np.float16(x.shape[-1])
        mean = (sequential_sum_fp16(x, -1) / count).astype(np.float16)
        centred = (x - mean).astype(np.float16)
        variance = (sequential_sum_fp16(centred * centred, -1) / count).astype(np.float16)
        return (centred / np.sqrt(variance + np.float16(eps))).astype(np.float16)


def normalize_reference(rows: np.ndarray, eps: float) -> np.ndarray:
    x = rows.astype(np.float64)
    centred = x - x.mean(axis=-1, keepdims=True)
    return centred / np.sqrt((centred * centred).mean(axis=-1, keepdims=True) + eps)


# ----------------------------------------------------------------------------------------
# Calibration


def load_crops(path: str, input_shape: Sequence[int]) -> np.ndarray:
    """Calibration crops as (N, C, H, W) float32: a .npy/.npz array, or a folder of .npy/.png/.jpg files.

    Images are resized to the input size and scaled to RGB / 255 (the HMR input).
    """
    source = Path(path)
    if not source.exists():
        raise Fp16CheckError(f"calibration crops not found: '{path}'")
    arrays: List[np.ndarray] = []
    channels, height, width = (int(v) for v in input_shape[1:])
    files = sorted(p for p in source.iterdir() if p.is_file()) if source.is_dir() else [source]
    for file in files:
        suffix = file.suffix.lower()
        try:
            if suffix == ".npy":
                arrays.append(np.load(file))
            elif suffix == ".npz":
                with np.load(file) as archive:
                    arrays.extend(archive[key] for key in archive.files)
            elif suffix in (".png", ".jpg", ".jpeg"):
                from PIL import Image

                image = Image.open(file).convert("RGB").resize((width, height), Image.BILINEAR)
                arrays.append(np.asarray(image, dtype=np.float32).transpose(2, 0, 1) / 255.0)
        except (OSError, ValueError) as error:
            raise Fp16CheckError(f"calibration crops '{file}' unreadable: {error}") from error
    if not arrays:
        raise Fp16CheckError(f"calibration crops '{path}': no .npy/.npz/.png/.jpg crops found")
    crops = []
    for array in arrays:
        array = np.asarray(array, dtype=np.float32)
        array = array[None] if array.ndim == 3 else array
        if array.ndim != 4 or tuple(array.shape[1:]) != (channels, height, width):
            raise Fp16CheckError(f"calibration crops '{path}': shape {tuple(array.shape)} does not fit the model "
                                 f"input (N, {channels}, {height}, {width})")
        crops.append(array)
    return np.concatenate(crops)


def _ort_session(model_bytes: bytes, threads: int = 1):
    import onnxruntime

    options = onnxruntime.SessionOptions()
    options.intra_op_num_threads = threads
    options.inter_op_num_threads = 1
    return onnxruntime.InferenceSession(model_bytes, options, providers=["CPUExecutionProvider"])


def calibrate(model, norms: List[Normalization], crops: np.ndarray) -> None:
    """Fill each normalization's ``stats`` and ``width`` from the crops (FP32, onnxruntime)."""
    import copy

    import onnx

    probe = copy.deepcopy(model)
    existing = {out.name for out in probe.graph.output}
    for name in {norm.input for norm in norms} - existing:
        probe.graph.output.append(onnx.helper.make_tensor_value_info(name, onnx.TensorProto.FLOAT, None))
    session = _ort_session(probe.SerializeToString())
    input_name = session.get_inputs()[0].name
    names = [norm.input for norm in norms]
    worst_rows: Dict[str, np.ndarray] = {}
    for norm in norms:
        norm.stats = {"max_sum_squares": 0.0, "max_abs_input": 0.0, "max_abs_centred": 0.0}
    for crop in crops:
        values = dict(zip(names, session.run(names, {input_name: crop[None]})))
        for norm in norms:
            x = np.moveaxis(values[norm.input].astype(np.float64), norm.axis, -1)
            rows = x.reshape(-1, x.shape[-1])
            norm.width = rows.shape[1]
            centred = rows - rows.mean(axis=1, keepdims=True)
            sums = (centred * centred).sum(axis=1)
            norm.stats["max_sum_squares"] = max(norm.stats["max_sum_squares"], float(sums.max()))
            norm.stats["max_abs_input"] = max(norm.stats["max_abs_input"], float(np.abs(rows).max()))
            norm.stats["max_abs_centred"] = max(norm.stats["max_abs_centred"], float(np.abs(centred).max()))
            pool = rows if norm.name not in worst_rows else np.concatenate([worst_rows[norm.name], rows])
            pool_centred = pool - pool.mean(axis=1, keepdims=True)
            order = np.argsort(-(pool_centred * pool_centred).sum(axis=1))[:EMULATED_ROWS]
            worst_rows[norm.name] = pool[order]
    for norm in norms:
        rows = worst_rows[norm.name]
        emulated = normalize_fp16(rows, norm.eps).astype(np.float64)
        reference = normalize_reference(rows, norm.eps)
        finite = bool(np.isfinite(emulated).all())
        scale = max(1.0, float(np.abs(reference).max()))
        norm.stats["emulated_error"] = float(np.abs(emulated - reference).max()) / scale if finite else float("inf")


def judge(norms: List[Normalization], headroom: float, tolerance: float) -> None:
    for norm in norms:
        s = norm.stats
        overflow = (s["max_sum_squares"] * headroom > FP16_MAX or s["max_abs_input"] > FP16_MAX
                    or s["max_abs_centred"] ** 2 > FP16_MAX or not np.isfinite(s["emulated_error"]))
        norm.verdict = "overflow" if overflow else ("precision" if s["emulated_error"] > tolerance else "ok")


# ----------------------------------------------------------------------------------------
# FP16 conversion with FP32 islands

_FLOAT, _FLOAT16 = 1, 10
_FLOAT32_ONLY_INPUTS = {"Resize": {1, 2}, "Upsample": {1}}  # roi/scales stay float32


def convert_float16(model, keep_fp32: Iterable[str]):
    """A copy of ``model`` in FP16 except the named nodes; Casts where the two meet.

    Float initializers are stored in FP16 (and in FP32 too when a kept node reads them); Constant
    nodes and ``Cast(to=FLOAT)`` / ``ConstantOfShape`` outside the kept nodes produce FP16; graph
    inputs and outputs stay float32.
    """
    import copy

    import onnx
    from onnx import helper, numpy_helper

    keep = set(keep_fp32)
    model = copy.deepcopy(model)
    graph = model.graph
    inferred = onnx.shape_inference.infer_shapes(model)
    elem: Dict[str, int] = {}
    for info in list(inferred.graph.value_info) + list(inferred.graph.input) + list(inferred.graph.output):
        elem[info.name] = info.type.tensor_type.elem_type
    for init in graph.initializer:
        elem[init.name] = init.data_type
    float_inits = {init.name: init for init in graph.initializer if init.data_type == _FLOAT}
    precision: Dict[str, str] = {inp.name: "f32" for inp in graph.input if elem.get(inp.name) == _FLOAT}
    extra_inits = []
    made: Dict[Tuple[str, str], str] = {}
    nodes = []

    def as_precision(name: str, target: str) -> str:
        if name in float_inits:
            if target == "f32":
                return name
            key = (name, "f16")
            if key not in made:
                half = numpy_helper.from_array(numpy_helper.to_array(float_inits[name]).astype(np.float16),
                                               name + "__fp16")
                extra_inits.append(half)
                made[key] = half.name
            return made[key]
        if precision.get(name, target) == target:
            return name
        key = (name, target)
        if key not in made:
            out = f"{name}__to_{target}"
            nodes.append(helper.make_node("Cast", [name], [out], name=f"{name}__cast_{target}",
                                          to=_FLOAT if target == "f32" else _FLOAT16))
            made[key] = out
        return made[key]

    for node in graph.node:
        target = "f32" if node.name in keep else "f16"
        fixed = _FLOAT32_ONLY_INPUTS.get(node.op_type, set())
        for index, name in enumerate(node.input):
            if name and elem.get(name) == _FLOAT:
                node.input[index] = as_precision(name, "f32" if index in fixed else target)
        if target == "f16":
            for attribute in node.attribute:
                if node.op_type == "Cast" and attribute.name == "to" and attribute.i == _FLOAT:
                    attribute.i = _FLOAT16
                elif attribute.type == onnx.AttributeProto.TENSOR and attribute.t.data_type == _FLOAT:
                    half = numpy_helper.from_array(numpy_helper.to_array(attribute.t).astype(np.float16),
                                                   attribute.t.name)
                    attribute.t.CopyFrom(half)
        for name in node.output:
            if elem.get(name) == _FLOAT:
                precision[name] = target
        nodes.append(node)
    tail = []
    for output in graph.output:
        if elem.get(output.name) == _FLOAT and precision.get(output.name) == "f16":
            inner = output.name + "__fp16"
            for node in nodes:
                for index, name in enumerate(node.input):
                    if name == output.name:
                        node.input[index] = inner
                for index, name in enumerate(node.output):
                    if name == output.name:
                        node.output[index] = inner
            tail.append(helper.make_node("Cast", [inner], [output.name], name=output.name + "__cast_out", to=_FLOAT))
    used = {name for node in nodes + tail for name in node.input}
    kept_inits = [init for init in graph.initializer if init.name in used]
    del graph.node[:]
    graph.node.extend(nodes + tail)
    del graph.initializer[:]
    graph.initializer.extend(kept_inits + extra_inits)
    del graph.value_info[:]
    onnx.checker.check_model(model)
    onnx.shape_inference.infer_shapes(model, strict_mode=True)
    return model


# ----------------------------------------------------------------------------------------
# FP16 emulator


def _emulated_reduce(kind: str):
    from onnx.reference.op_run import OpRun

    def run(self, data, axes=None, keepdims=None, noop_with_empty_axes=None):
        if axes is None:
            axes = getattr(self, "axes", None)
        keepdims = 1 if keepdims is None else int(keepdims)
        axes_tuple = tuple(range(data.ndim)) if axes is None or len(np.atleast_1d(axes)) == 0 else \
            tuple(int(a) % data.ndim for a in np.atleast_1d(axes))
        if data.dtype != np.float16:
            x = data * data if kind == "ReduceSumSquare" else data
            result = x.sum(axis=axes_tuple, keepdims=True, dtype=np.float64)
            if kind == "ReduceMean":
                result = result / np.prod([data.shape[a] for a in axes_tuple])
            result = result.astype(data.dtype)
        else:
            with np.errstate(over="ignore", invalid="ignore"):
                result = (data * data).astype(np.float16) if kind == "ReduceSumSquare" else data
                count = 1
                for axis in axes_tuple:
                    result = sequential_sum_fp16(result, axis)
                    count *= data.shape[axis]
                if kind == "ReduceMean":
                    result = (result / np.float16(count)).astype(np.float16)
        if not keepdims:
            result = np.squeeze(result, axis=axes_tuple)
        return (result,)

    return type(kind, (OpRun,), {"op_domain": "", "_run": run})


def _torch_conv(transpose: bool):
    """Conv / ConvTranspose through torch (float32 accumulation), the result rounded to the input's dtype.

    onnx.reference's own convolutions are Python loops (minutes per SMPLer-X crop).
    """
    from onnx.reference.op_run import OpRun

    def run(self, x, w, b=None, auto_pad=None, dilations=None, group=None, kernel_shape=None, pads=None,
            strides=None, output_padding=None, output_shape=None):
        import torch
        from torch.nn import functional as F

        if auto_pad not in (None, "NOTSET", b"NOTSET") or output_shape is not None:
            raise NotImplementedError("fp16 emulator: Conv auto_pad / output_shape")
        dims = x.ndim - 2
        dilations = list(dilations or [1] * dims)
        strides = list(strides or [1] * dims)
        pads = list(pads or [0] * (2 * dims))
        if pads[:dims] != pads[dims:]:
            raise NotImplementedError("fp16 emulator: asymmetric Conv pads")
        group = int(group or 1)
        tx, tw = torch.from_numpy(x.astype(np.float32)), torch.from_numpy(w.astype(np.float32))
        tb = None if b is None else torch.from_numpy(b.astype(np.float32))
        with torch.no_grad():
            if transpose:
                fn = {1: F.conv_transpose1d, 2: F.conv_transpose2d, 3: F.conv_transpose3d}[dims]
                y = fn(tx, tw, tb, stride=strides, padding=pads[:dims],
                       output_padding=list(output_padding or [0] * dims), groups=group, dilation=dilations)
            else:
                fn = {1: F.conv1d, 2: F.conv2d, 3: F.conv3d}[dims]
                y = fn(tx, tw, tb, stride=strides, padding=pads[:dims], dilation=dilations, groups=group)
        return (y.numpy().astype(x.dtype),)

    return type("ConvTranspose" if transpose else "Conv", (OpRun,), {"op_domain": "", "_run": run})


class Fp16Emulator:
    """Runs an ONNX (FP16, FP32 or mixed) with the FP16 arithmetic described in the module docstring."""

    def __init__(self, model) -> None:
        from onnx.reference import ReferenceEvaluator

        ops = [_emulated_reduce(kind) for kind in ("ReduceMean", "ReduceSum", "ReduceSumSquare")]
        ops += [_torch_conv(False), _torch_conv(True)]
        self.evaluator = ReferenceEvaluator(model, new_ops=ops)
        self.input_name = model.graph.input[0].name
        self.output_names = [out.name for out in model.graph.output]

    def run(self, crop: np.ndarray) -> List[np.ndarray]:
        with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
            return [np.asarray(v, dtype=np.float64) for v in self.evaluator.run(None, {self.input_name: crop})]


def relative_error(got: Sequence[np.ndarray], expected: Sequence[np.ndarray]) -> float:
    """Largest |got - expected| over the outputs, relative to each FP32 output's largest magnitude (inf: non-finite)."""
    worst = 0.0
    for a, b in zip(got, expected):
        if not np.isfinite(a).all():
            return float("inf")
        scale = max(float(np.abs(b).max()), 1e-12)
        worst = max(worst, float(np.abs(a - b).max()) / scale)
    return worst


# ----------------------------------------------------------------------------------------
# Report


def write_ranges_png(norms: List[Normalization], path: str, title: str) -> str:
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib import pyplot as plt

    figure, axis = plt.subplots(figsize=(max(6.0, 0.35 * len(norms) + 2.0), 4.5))
    positions = np.arange(len(norms))
    sums = [max(n.stats["max_sum_squares"], 1e-3) for n in norms]
    peaks = [max(n.stats["max_abs_input"], 1e-3) for n in norms]
    colours = {"overflow": "tab:red", "precision": "tab:orange", "ok": "tab:blue"}
    axis.bar(positions, sums, color=[colours.get(n.verdict, "grey") for n in norms], label="max sum of squares")
    axis.plot(positions, peaks, "k.", label="max |input|")
    axis.axhline(FP16_MAX, color="tab:red", linestyle="--", label="FP16 max 65504")
    axis.set_yscale("log")
    axis.set_xticks(positions)
    axis.set_xticklabels([n.name for n in norms], rotation=90, fontsize=7)
    axis.set_ylabel("over the calibration crops")
    axis.set_title(title)
    axis.legend(fontsize=8)
    figure.tight_layout()
    figure.savefig(path, dpi=100)
    plt.close(figure)
    return path


def write_report(path: str, model_path: str, norms: List[Normalization], crops: int, headroom: float,
                 tolerance: float, kept: List[str], verification: Optional[Dict[str, float]],
                 png_name: str, outputs: Dict[str, str]) -> str:
    lines = [f"# FP16 check of `{os.path.basename(model_path)}`", "",
             f"{crops} calibration crop(s); FP16 limit {FP16_MAX:.0f}; headroom {headroom:g}; "
             f"tolerance {tolerance:g} (normalized output, relative to max(1, its largest magnitude)).", "",
             "| normalization | kind | width | max sum of squares | / 65504 | max abs input | FP16 emulation error "
             "| verdict |", "|---|---|---|---|---|---|---|---|"]
    for n in norms:
        s = n.stats
        lines.append(f"| `{n.name}` | {n.kind} | {n.width} | {s['max_sum_squares']:.1f} | "
                     f"{s['max_sum_squares'] / FP16_MAX:.3f} | {s['max_abs_input']:.2f} | {s['emulated_error']:.3g} "
                     f"| {n.verdict} |")
    lines += ["", f"Nodes kept in FP32 ({len(kept)}): " + (", ".join(f"`{k}`" for k in kept) or "none"), ""]
    if verification:
        lines += ["Verification on the calibration crops (largest |output - FP32| / largest |FP32 output|, "
                  "FP16 emulated):", "", "| model | relative error |", "|---|---|"]
        lines += [f"| {name} | {value:.3g} |" for name, value in verification.items()]
        lines.append("")
    lines += [f"![ranges]({png_name})", "", "Files: " + ", ".join(f"{k} `{v}`" for k, v in outputs.items()), ""]
    Path(path).write_text("\n".join(lines), encoding="utf-8")
    return path


# ----------------------------------------------------------------------------------------
# The check


@dataclass
class CheckResult:
    norms: List[Normalization]
    kept_nodes: List[str]
    plan_entries: List[str]
    fp16_path: str
    plan_path: str
    report_path: str
    png_path: str
    verification: Optional[Dict[str, float]]


def load_model(path: str):
    import onnx

    if not os.path.isfile(path):
        raise Fp16CheckError(f"model not found: '{path}'")
    try:
        return onnx.load(path)
    except Exception as error:  # noqa: BLE001 - protobuf raises several kinds
        raise Fp16CheckError(f"model '{path}' is not a readable ONNX file: {error}") from error


def fp16_check(model_path: str, crops: np.ndarray, out_dir: str, headroom: float = 1.0, tolerance: float = 0.02,
               verify: bool = True, verify_crops: int = 4) -> CheckResult:
    import onnx

    from leapnbv_perception.backends.precision_plan import write_precision_plan

    model = load_model(model_path)
    norms = find_normalizations(model)
    if not norms:
        raise Fp16CheckError(f"model '{model_path}': no normalization (LayerNormalization or the "
                             "ReduceMean/Sub/Mul/ReduceMean/Sqrt/Div pattern) found")
    calibrate(model, norms, crops)
    judge(norms, headroom, tolerance)
    flagged = [n for n in norms if n.verdict != "ok"]
    kept = [name for n in flagged for name in n.nodes]
    constants = {node.name for node in model.graph.node if node.op_type == "Constant"}
    # TensorRT names a layer after its ONNX node; a LayerNormalization node may become several layers
    # ("<name>", "<name>_1", ...). Constant nodes become weights, not layers the plan could name.
    plan_entries = [name + "*" if n.kind == "LayerNormalization" else name for n in flagged for name in n.nodes
                    if name not in constants]
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    stem = Path(model_path).stem
    fp16_model = convert_float16(model, kept)
    meta = fp16_model.metadata_props.add()
    meta.key, meta.value = "leapnbv.precision", f"fp16, {len(kept)} node(s) kept in fp32 by fp16-check"
    fp16_path = str(out / f"{stem}.fp16.onnx")
    onnx.save(fp16_model, fp16_path)
    plan_path = write_precision_plan(
        str(out / f"{stem}.precision_plan.json"), plan_entries, sha256_of(model_path), tool=TOOL,
        notes="normalizations predicted to overflow or lose precision in FP16: "
              + (", ".join(f"{n.name} ({n.verdict})" for n in flagged) or "none"))
    verification = None
    if verify:
        verification = verify_models(model, fp16_model, crops[:verify_crops])
    png_path = write_ranges_png(norms, str(out / f"{stem}.fp16_ranges.png"), f"{stem}: normalization ranges")
    report_path = write_report(str(out / f"{stem}.fp16_report.md"), model_path, norms, len(crops), headroom,
                               tolerance, kept, verification, os.path.basename(png_path),
                               {"fp16 onnx": os.path.basename(fp16_path),
                                "precision plan": os.path.basename(plan_path)})
    return CheckResult(norms, kept, plan_entries, fp16_path, plan_path, report_path, png_path, verification)


def verify_models(model, guarded, crops: np.ndarray) -> Dict[str, float]:
    """Relative output error of FP32 (onnxruntime vs the emulator), naive and guarded FP16 (emulated)."""
    session = _ort_session(model.SerializeToString())
    input_name = session.get_inputs()[0].name
    naive = Fp16Emulator(convert_float16(model, []))
    guarded_run = Fp16Emulator(guarded)
    fp32_emulator = Fp16Emulator(model)
    errors = {"fp32 (emulator vs onnxruntime)": 0.0, "naive fp16": 0.0, "guarded fp16": 0.0}
    for crop in crops:
        expected = [np.asarray(v, dtype=np.float64) for v in session.run(None, {input_name: crop[None]})]
        for key, runner in (("fp32 (emulator vs onnxruntime)", fp32_emulator), ("naive fp16", naive),
                            ("guarded fp16", guarded_run)):
            errors[key] = max(errors[key], relative_error(runner.run(crop[None]), expected))
    return errors


def main(argv: Optional[Sequence[str]] = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m leapnbv_model_tools fp16-check",
                                     description="FP16 overflow check and guard (exit 0 ok, 1 guarded model "
                                                 "still off, 2 bad input)")
    parser.add_argument("model", help="the FP32 ONNX (export-hmr's output)")
    parser.add_argument("--calib", required=True, help=".npy/.npz (N, C, H, W) or a folder of .npy/.png/.jpg crops")
    parser.add_argument("--out", required=True, help="folder for the FP16 ONNX, the precision plan and the report")
    parser.add_argument("--headroom", type=float, default=1.0,
                        help="flag a normalization when its largest sum of squares times this exceeds 65504")
    parser.add_argument("--tolerance", type=float, default=0.02,
                        help="flag when the emulated FP16 normalization differs by more (relative, see above)")
    parser.add_argument("--max-error", type=float, default=0.02,
                        help="exit 1 when the guarded FP16 model's relative output error exceeds this")
    parser.add_argument("--no-verify", action="store_true", help="skip the emulated whole-model comparison")
    parser.add_argument("--verify-crops", type=int, default=4)
    args = parser.parse_args(argv)
    try:
        model = load_model(args.model)
        crops = load_crops(args.calib, [d.dim_value for d in model.graph.input[0].type.tensor_type.shape.dim])
        del model
        result = fp16_check(args.model, crops, args.out, args.headroom, args.tolerance, not args.no_verify,
                            args.verify_crops)
    except Fp16CheckError as error:
        print(f"fp16-check: {error}", file=sys.stderr)
        return 2
    for norm in result.norms:
        print(f"{norm.name}: width {norm.width}, max sum of squares {norm.stats['max_sum_squares']:.1f}, "
              f"max |input| {norm.stats['max_abs_input']:.2f}: {norm.verdict}")
    print(f"kept in fp32: {len(result.kept_nodes)} node(s); wrote {result.fp16_path}, {result.plan_path}, "
          f"{result.report_path}, {result.png_path}")
    if result.verification:
        print("verification: " + ", ".join(f"{k} {v:.3g}" for k, v in result.verification.items()))
        if result.verification["guarded fp16"] > args.max_error:
            print(f"fp16-check: the guarded FP16 model differs from FP32 by {result.verification['guarded fp16']:.3g} "
                  f"(> --max-error {args.max_error:g}); see {result.report_path}", file=sys.stderr)
            return 1
    return 0

