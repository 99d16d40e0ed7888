"""Calibration and verdicts: the calibration crops through the FP32 model (onnxruntime, CPU) with every
normalization's input exposed, the ranges recorded per normalization, its FP16 emulation on the rows
with the largest sums of squares, and the verdict (``overflow``, ``precision`` or ``ok``)."""

from __future__ import annotations

from typing import Dict, List

import numpy as np

from leapnbv_model_tools.fp16_emulation import FP16_MAX, normalize_fp16, normalize_reference
from leapnbv_model_tools.fp16_normalizations import Normalization

EMULATED_ROWS = 32  # calibration rows (largest sums of squares) each normalization is emulated on


def cpu_session(model_bytes: bytes, threads: int = 1):
    """An onnxruntime CPU session of the model (``threads`` intra-op threads, one inter-op)."""
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
    session = cpu_session(probe.SerializeToString())
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
