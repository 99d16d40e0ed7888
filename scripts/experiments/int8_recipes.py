#!/usr/bin/env python3
"""The INT8 recipes side by side on this CPU: each variant's median / p95 ms on one thread beside FP32.

FP32 and each recipe are timed round-robin in the same process (a busy machine slows them alike),
with the machine's load and the CPU's integer flags.

    PYTHONPATH=tools scripts/env.sh python scripts/experiments/int8_recipes.py --kind detector yolov8s.onnx \
        [--calib 8] [--runs 10] [--out /tmp/int8_recipes] [--variants u8s8 s8s8 ...]

Variants (default: all): ``u8s8`` (the recipe quantize-int8 writes on a VNNI CPU: transposed convolutions
rewritten, onnxruntime's pre-processing, the engine's op set: int8_recipe.OP_SETS), ``u8s8-all-ops`` (the same
with every operator onnxruntime can quantize), ``u8s8-no-rewrite`` (without the ConvTranspose rewrite),
``u8s8-quantized-matmul-outputs`` (the MatMuls' outputs quantized too: int8_recipe.FLOAT_OUTPUTS),
``u8s8-no-softmax`` / ``u8s8-products`` (op sets: all but Softmax; the products only),
``u8s8-no-preprocess`` (neither rewrite nor pre-processing), ``u8s8-reduce-range`` (the AVX2 recipe),
``s8s8`` (symmetric int8 activations: the ARM / TensorRT recipe, and the old one), and ``fp32-rewritten``
(the FP32 model after the rewrite and pre-processing, not quantized). The models are written under --out.
Exit codes: 0 done; 2 the model is missing or not loadable.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time
from typing import Dict, List

import numpy as np

VARIANTS = ("u8s8", "u8s8-quantized-matmul-outputs", "u8s8-all-ops", "u8s8-no-softmax", "u8s8-products",
            "u8s8-no-rewrite", "u8s8-no-preprocess", "u8s8-reduce-range", "s8s8", "fp32-rewritten")


def main(argv=None) -> int:
    """Quantize the variants, time them; returns the exit code."""
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("model")
    parser.add_argument("--kind", choices=["hmr", "detector"], required=True)
    parser.add_argument("--calib", type=int, default=8)
    parser.add_argument("--runs", type=int, default=10)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--variants", nargs="*", default=list(VARIANTS), choices=VARIANTS)
    parser.add_argument("--out", default="/tmp/int8_recipes")
    args = parser.parse_args(argv)
    if not os.path.isfile(args.model):
        print(f"int8_recipes: model not found: {args.model}", file=sys.stderr)
        return 2
    import onnxruntime
    from onnxruntime.quantization.shape_inference import quant_pre_process

    from leapnbv_model_tools import int8_recipe
    from leapnbv_model_tools.quantize_int8 import FeedReader, engine_inputs, rendered_frames

    os.makedirs(args.out, exist_ok=True)
    cpu = int8_recipe.this_cpu()
    session = onnxruntime.InferenceSession(args.model, providers=["CPUExecutionProvider"])
    shape = tuple(session.get_inputs()[0].shape)
    feeds = engine_inputs(args.kind, shape, rendered_frames(args.calib + 1, offset=0))
    calibration, probe = feeds[:-1], feeds[-1]
    stem = os.path.join(args.out, os.path.splitext(os.path.basename(args.model))[0])
    prepared = f"{stem}.prepared.onnx"
    int8_recipe.prepare(args.model, prepared)
    plain = f"{stem}.preprocessed.onnx"
    if any(v == "u8s8-no-rewrite" for v in args.variants):
        quant_pre_process(args.model, plain)
    paths: Dict[str, str] = {"fp32": args.model}
    for variant in args.variants:
        path = f"{stem}.{variant}.onnx"
        if variant == "fp32-rewritten":
            paths[variant] = prepared
            continue
        name = "u8s8" if variant.startswith("u8s8") and variant != "u8s8-reduce-range" else variant
        source = {"u8s8-no-rewrite": plain, "u8s8-no-preprocess": args.model}.get(variant, prepared)
        op_set = {"u8s8-all-ops": "all", "u8s8-no-softmax": "no-softmax", "u8s8-products": "products"}.get(
            variant, int8_recipe.OP_SETS[args.kind])
        ops = int8_recipe.quantized_ops(op_set)
        float_outputs = () if variant == "u8s8-quantized-matmul-outputs" else int8_recipe.FLOAT_OUTPUTS[args.kind]
        started = time.perf_counter()
        int8_recipe.quantize(source, path, FeedReader(calibration), int8_recipe.recipe(name), op_types=ops,
                             float_outputs=float_outputs)
        print(f"[int8_recipes] {variant}: quantized in {time.perf_counter() - started:.0f} s", flush=True)
        paths[variant] = path
    options = onnxruntime.SessionOptions()
    options.intra_op_num_threads = args.threads
    sessions = {k: onnxruntime.InferenceSession(p, options, providers=["CPUExecutionProvider"])
                for k, p in paths.items()}
    samples: Dict[str, List[float]] = {k: [] for k in sessions}
    for s in sessions.values():
        s.run(None, probe)
    load_before = os.getloadavg()
    for _ in range(args.runs):
        for key, s in sessions.items():  # round-robin: load changes hit every variant alike
            start = time.perf_counter()
            s.run(None, probe)
            samples[key].append((time.perf_counter() - start) * 1e3)
    load_after = os.getloadavg()
    reference = float(np.median(samples["fp32"]))
    flags = subprocess.run(["uptime"], stdout=subprocess.PIPE, text=True).stdout.strip()
    print(f"\n== {os.path.basename(args.model)} ({args.kind}), {args.threads} thread(s), {args.runs} runs each "
          f"round-robin; CPU {cpu.describe()}; load {load_before[0]:.2f} -> {load_after[0]:.2f} ({flags})")
    print("| variant | median / p95 ms | FP32 / variant | size MB |")
    print("|---|---:|---:|---:|")
    for key, values in samples.items():
        median = float(np.median(values))
        print(f"| {key} | {median:.1f} / {np.percentile(values, 95):.1f} | {reference / median:.2f} | "
              f"{os.path.getsize(paths[key]) / 1e6:.0f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
