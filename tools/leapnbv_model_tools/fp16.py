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

The FP16 results are emulated (onnxruntime's CPU provider has no FP16 kernels for most of these
operators): FP16 storage, elementwise results rounded to FP16, reductions accumulated sequentially
in FP16, products in float32; `fp16_emulation` says how.

The steps live in one module each: `fp16_normalizations` (1), `fp16_inputs` (the model and the
crops), `fp16_calibration` (2, 3), `fp16_cast` (the guarded FP16 model), `fp16_report` (the report
and the plot), `fp16_emulation` (FP16 arithmetic, the emulator); this module holds the check (4, 5:
the FP32 islands, the precision plan, the verification) and the command line, and re-exports
the names the other tools and the tests import.

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
from dataclasses import dataclass
from pathlib import Path
from typing import Dict, List, Optional, Sequence

import numpy as np

from leapnbv_model_tools.file_hash import sha256_of
from leapnbv_model_tools.fp16_calibration import EMULATED_ROWS, calibrate, cpu_session, judge
from leapnbv_model_tools.fp16_cast import convert_float16
from leapnbv_model_tools.fp16_emulation import (
    FP16_MAX,
    Fp16Emulator,
    normalize_fp16,
    normalize_reference,
    relative_error,
    sequential_sum_fp16,
)
from leapnbv_model_tools.fp16_inputs import Fp16CheckError, load_crops, load_model
from leapnbv_model_tools.fp16_normalizations import Normalization, find_normalizations
from leapnbv_model_tools.fp16_report import write_ranges_png, write_report

TOOL = "leapnbv_model_tools fp16-check 1"


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


def precision_plan_entries(model, flagged: List[Normalization]) -> List[str]:
    """The TensorRT precision plan's entries for the flagged normalizations' nodes.

    TensorRT names a layer after its ONNX node; a LayerNormalization node may become several layers
    ("<name>", "<name>_1", ...), hence its pattern "<name>*". Constant nodes become weights, not
    layers the plan could name, so they are left out.
    """
    constants = {node.name for node in model.graph.node if node.op_type == "Constant"}
    return [name + "*" if n.kind == "LayerNormalization" else name for n in flagged for name in n.nodes
            if name not in constants]


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
    plan_entries = precision_plan_entries(model, flagged)
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
    session = cpu_session(model.SerializeToString())
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

__all__ = [
    "EMULATED_ROWS",
    "FP16_MAX",
    "TOOL",
    "CheckResult",
    "Fp16CheckError",
    "Fp16Emulator",
    "Normalization",
    "calibrate",
    "convert_float16",
    "find_normalizations",
    "fp16_check",
    "judge",
    "load_crops",
    "load_model",
    "main",
    "normalize_fp16",
    "normalize_reference",
    "precision_plan_entries",
    "relative_error",
    "sequential_sum_fp16",
    "verify_models",
    "write_ranges_png",
    "write_report",
]
