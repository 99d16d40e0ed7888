#!/usr/bin/env python3
"""Benchmark exported HMR models (export-hmr ONNX files) on this CPU with onnxruntime.

For each model: its variant and input size (from the export's metadata), file size, session load
time, the engine alone (encoder + heads) at each thread count, and the whole estimate (crop +
engine + SMPL-X tail with the given body model) at the largest thread count; median and p95 in ms
over --runs runs after --warmup, and each figure's ratio against the first model's at the same
thread count (timed in the same process, so a busy machine shifts both alike). The machine's load
average is printed with the figures. The paper's deployed figure is printed beside them: the
32 M student in FP16 on TensorRT 8.5, Jetson Xavier NX: 12 ms for the engine.

    tools/run.sh python -m leapnbv_model_tools export-hmr --checkpoint smpler_x_s32.pth.tar \\
        --variant s32 --out s32.onnx                     # (tools environment)
    scripts/env.sh python scripts/bench_hmr_models.py s32.onnx b32.onnx [--threads 1 2] [--runs 10]
        [--body-model models/stand_in/stand_in_smplx_dense.npz]

Exit codes: 0 done; 2 a model or the body model could not be loaded (one line naming it).
"""

from __future__ import annotations

import argparse
import functools
import os
import sys
import time
from typing import Callable, Dict, List, Tuple

import numpy as np

PAPER_ENGINE_MS = 12.0  # the student, FP16, TensorRT 8.5 on the Xavier NX (the paper's figure)


def timed(function: Callable[[], object], runs: int, warmup: int) -> Tuple[float, float]:
    """Median and p95 wall time in ms."""
    for _ in range(warmup):
        function()
    samples: List[float] = []
    for _ in range(runs):
        start = time.perf_counter()
        function()
        samples.append((time.perf_counter() - start) * 1e3)
    return float(np.median(samples)), float(np.percentile(samples, 95))


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("models", nargs="+", help="export-hmr ONNX files; the first is the reference")
    parser.add_argument("--threads", type=int, nargs="+", default=[1, 2])
    parser.add_argument("--runs", type=int, default=10)
    parser.add_argument("--warmup", type=int, default=2)
    parser.add_argument("--body-model", default=None,
                        help="SMPL-X .npz for the tail (default: the dense SMPL-X-layout stand-in, generated)")
    args = parser.parse_args(argv)

    from leapnbv_perception.backends import BackendError, ModelFileNotFoundError
    from leapnbv_perception.backends.onnxruntime_backend import OnnxRuntimeBackend
    from leapnbv_perception.hmr import HumanMeshEstimator, read_export_metadata
    from leapnbv_perception.smplx_layer import SMPLXModel
    from leapnbv_stand_ins.files import ensure_stand_in_smplx_dense

    body_path = args.body_model or ensure_stand_in_smplx_dense()
    try:
        body = SMPLXModel.load(body_path)
    except (OSError, ValueError) as error:
        print(f"bench_hmr_models: body model {body_path}: {error}", file=sys.stderr)
        return 2
    rng = np.random.default_rng(0)
    frame = rng.integers(0, 255, size=(480, 640, 3), dtype=np.uint8)
    box = [220.0, 60.0, 420.0, 460.0, 0.9]
    print(f"HMR engines on this CPU (onnxruntime, {os.cpu_count()} cores, load average "
          f"{' '.join(f'{v:.1f}' for v in os.getloadavg())}); median / p95 ms over {args.runs} runs")
    print(f"body model for the tail: {body_path} ({body.num_vertices} vertices)")
    reference: Dict[Tuple[str, int], float] = {}
    for index, path in enumerate(args.models):
        meta = read_export_metadata(path)
        variant = meta.get("leapnbv.variant", "?")
        size_mb = sum(os.path.getsize(p) for p in (path, path + ".data") if os.path.isfile(p)) / 1e6
        print(f"\n{path}: {variant}, input {meta.get('leapnbv.input_size', '?')}, {size_mb:.0f} MB")
        for threads in args.threads:
            started = time.perf_counter()
            try:
                backend = OnnxRuntimeBackend(path, intra_op_threads=threads)
            except (ModelFileNotFoundError, BackendError) as error:
                print(f"bench_hmr_models: {error}", file=sys.stderr)
                return 2
            load_s = time.perf_counter() - started
            feed = {name: np.zeros(spec.shape, dtype=spec.dtype) for name, spec in backend.input_specs.items()}
            median, p95 = timed(functools.partial(backend.run, feed), args.runs, args.warmup)
            key = ("engine", threads)
            if index == 0:
                reference[key] = median
            print(f"  engine, {threads} thread(s)         {median:8.1f} / {p95:8.1f}   "
                  f"x{median / reference[key]:5.2f} of the first model   (session load {load_s:.1f} s)")
            if threads == max(args.threads):
                estimator = HumanMeshEstimator(backend, body)
                median, p95 = timed(functools.partial(estimator.estimate, frame, box), args.runs, args.warmup)
                key = ("estimate", threads)
                if index == 0:
                    reference[key] = median
                print(f"  whole estimate, {threads} thread(s) {median:8.1f} / {p95:8.1f}   "
                      f"x{median / reference[key]:5.2f} of the first model   (crop + engine + SMPL-X tail)")
    print(f"\npaper: the 32 M student, FP16, TensorRT 8.5, Jetson Xavier NX: engine {PAPER_ENGINE_MS:.0f} ms")
    return 0


if __name__ == "__main__":
    sys.exit(main())
