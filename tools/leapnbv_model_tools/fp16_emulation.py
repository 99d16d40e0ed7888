"""FP16 arithmetic in numpy and an FP16 emulator for whole ONNX graphs (what fp16-check measures with).

onnxruntime's CPU provider has no FP16 kernels for most of the operators a normalization uses,
so the FP16 results are emulated: ``onnx.reference.ReferenceEvaluator`` (numpy) runs the FP16
ONNX with float16 tensors, so every tensor is stored in FP16 and every elementwise result (Add,
Sub, Mul, Div, Sqrt, Pow, Erf, Exp, ...) is rounded to FP16 after each operation (numpy's half
arithmetic: computed in float32, rounded to nearest even). ReduceMean / ReduceSum /
ReduceSumSquare on float16 are replaced by a sequential FP16 accumulation (each partial sum
rounded to FP16, so a partial sum above 65504 becomes inf), then the division by the count in
FP16: the worst case of an FP16 reduction. MatMul / Gemm / Conv / ConvTranspose products are
accumulated in float32 and rounded to FP16 once (numpy's half matmul, torch's float32
convolutions; what tensor-core GEMMs with FP32 accumulation do); Softmax's sum is accumulated in
float32 too. Nodes that a guarded model keeps in FP32 run in float32.
"""

from __future__ import annotations

from typing import List, Sequence

import numpy as np

FP16_MAX = 65504.0


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
