"""int8_student: the accuracy cost of INT8 HMR engines on trained weights, on a distill-format test split.

For the FP32 engine and each INT8 engine (quantize-int8 outputs of it): PA-MPVPE (mm) of the mesh to
the ground truth, and of each INT8 mesh to the FP32 mesh, over the test crops (the inference crop,
``distill.make_crop``), through the same SMPL-X layer (torch_smplx, as ``ladder.evaluate``); the
mean, median and max, the largest output difference, and onnxruntime's median ms on one thread
(FP32 and INT8 alternately). Runs in the tools environment:

    tools/run.sh python -m leapnbv_model_tools.int8_student --fp32 student.onnx --int8 a.onnx b.onnx \
        --test data/test.jsonl --body-model stand_in_smplx_dense.npz [--json out.json]

Exit codes (leapnbv_model_tools.exit_codes): 0 done; 2 a model or the manifest is missing.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from typing import Dict, List, Optional, Sequence

import numpy as np


def _session(path: str):
    import onnxruntime

    options = onnxruntime.SessionOptions()
    options.intra_op_num_threads = 1
    return onnxruntime.InferenceSession(path, options, providers=["CPUExecutionProvider"])


def evaluate(fp32_path: str, int8_paths: Sequence[str], test_manifest: str, body_path: str,
             runs: int = 10) -> List[Dict[str, object]]:
    """One row per engine (the FP32 first): PA-MPVPE to the ground truth and to the FP32 mesh, timing."""
    import torch

    from leapnbv_model_tools.distill import PARAM_SIZES, make_crop, pa_mpvpe_mm, read_manifest
    from leapnbv_model_tools.export import OUTPUT_NAMES
    from leapnbv_model_tools.int8_recipe import read_int8_metadata
    from leapnbv_model_tools.torch_smplx import TorchSMPLX, mesh_from_axis_angle, mesh_from_outputs
    from leapnbv_perception.smplx_layer import SMPLXModel

    layer = TorchSMPLX(SMPLXModel.load(body_path))
    samples = read_manifest(test_manifest)
    sessions = [_session(p) for p in [fp32_path, *int8_paths]]
    shape = sessions[0].get_inputs()[0].shape
    input_hw = (int(shape[2]), int(shape[3]))
    crops = [make_crop(s, input_hw)[None] for s in samples]
    truths = []
    with torch.no_grad():
        for sample in samples:
            truths.append(mesh_from_axis_angle(layer, {k: torch.from_numpy(sample.params[k][None]).float()
                                                       for k in PARAM_SIZES})[0].numpy())
    outputs = [[dict(zip(OUTPUT_NAMES, s.run(list(OUTPUT_NAMES), {"img": c}))) for c in crops] for s in sessions]
    meshes = []
    with torch.no_grad():
        for per_engine in outputs:
            meshes.append([mesh_from_outputs(layer, {k: torch.from_numpy(np.asarray(v, np.float32))
                                                     for k, v in o.items()})[0].numpy() for o in per_engine])
    rows = []
    for index, path in enumerate([fp32_path, *int8_paths]):
        to_truth = [pa_mpvpe_mm(m, t) for m, t in zip(meshes[index], truths)]
        to_fp32 = [pa_mpvpe_mm(m, f) for m, f in zip(meshes[index], meshes[0])]
        worst = max(float(np.abs(o[k] - f[k]).max()) for o, f in zip(outputs[index], outputs[0]) for k in o)
        fp32_ms, own_ms = [], []
        for _ in range(runs):  # alternately, so that the machine's load hits both alike
            for session, into in ((sessions[0], fp32_ms), (sessions[index], own_ms)):
                start = time.perf_counter()
                session.run(None, {"img": crops[0]})
                into.append((time.perf_counter() - start) * 1e3)
        info = read_int8_metadata(path) if index else {}
        rows.append({"model": os.path.basename(path), "recipe": info.get("leapnbv.int8.recipe", "fp32"),
                     "op_set": info.get("leapnbv.int8.quantized_ops", ""),
                     "keep_fp32": info.get("leapnbv.int8.keep_fp32", ""),
                     "crops": len(samples), "pa_mpvpe_gt_mm": float(np.mean(to_truth)),
                     "pa_mpvpe_gt_median_mm": float(np.median(to_truth)),
                     "pa_mpvpe_fp32_mm": float(np.mean(to_fp32)), "pa_mpvpe_fp32_max_mm": float(np.max(to_fp32)),
                     "largest_output_difference": worst, "ms_fp32": float(np.median(fp32_ms)),
                     "ms": float(np.median(own_ms)), "size_mb": os.path.getsize(path) / 1e6,
                     "load": os.getloadavg()[0]})
    return rows


def format_rows(rows: List[Dict[str, object]]) -> str:
    """The rows as a markdown table."""
    lines = ["| engine | recipe | operators | FP32 layers | PA-MPVPE to GT mean / median mm | to the FP32 mesh mean / "
             "max mm | largest output diff | ms 1 thread (FP32 alongside) | MB | load |",
             "|---|---|---|---|---:|---:|---:|---:|---:|---:|"]
    for r in rows:
        lines.append(f"| {r['model']} | {r['recipe']} | {r['op_set'] or '-'} | {r['keep_fp32'] or '-'} | "
                     f"{r['pa_mpvpe_gt_mm']:.1f} / {r['pa_mpvpe_gt_median_mm']:.1f} | "
                     f"{r['pa_mpvpe_fp32_mm']:.2f} / {r['pa_mpvpe_fp32_max_mm']:.2f} | "
                     f"{r['largest_output_difference']:.3g} | {r['ms']:.1f} ({r['ms_fp32']:.1f}) | "
                     f"{r['size_mb']:.0f} | {r['load']:.1f} |")
    return "\n".join(lines)


def main(argv: Optional[Sequence[str]] = None) -> int:
    """The command line (the module docstring); returns the exit code."""
    from leapnbv_model_tools.exit_codes import ModelToolExit

    parser = argparse.ArgumentParser(prog="python -m leapnbv_model_tools.int8_student", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--fp32", required=True)
    parser.add_argument("--int8", nargs="+", required=True)
    parser.add_argument("--test", required=True, help="distill-format test manifest (ladder_data)")
    parser.add_argument("--body-model", required=True)
    parser.add_argument("--json", default=None)
    args = parser.parse_args(argv)
    for path in [args.fp32, *args.int8, args.test, args.body_model]:
        if not os.path.isfile(path):
            print(f"int8_student: file not found: '{path}'", file=sys.stderr)
            return int(ModelToolExit.BAD_INPUT)
    rows = evaluate(args.fp32, args.int8, args.test, args.body_model)
    print(format_rows(rows))
    if args.json:
        with open(args.json, "w") as handle:
            json.dump(rows, handle, indent=1)
    return int(ModelToolExit.OK)


if __name__ == "__main__":
    sys.exit(main())
