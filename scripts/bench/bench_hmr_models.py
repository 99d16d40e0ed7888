#!/usr/bin/env python3
"""Benchmark exported HMR models (export-hmr ONNX files) on this CPU with onnxruntime.

For each model: its variant and input size (from the export's metadata), file size (with its
external data, ``<model>.data``), session load time (for an export with external data: reading the
weights file too), the engine alone (encoder + heads) at each thread count, and the whole estimate (crop +
engine + SMPL-X tail with the given body model) at the largest thread count; median and p95 in ms
over --runs runs after --warmup, and each figure's ratio against the first model's at the same
thread count (timed in the same process, so a busy machine shifts both alike). The machine's load
average is printed with the figures. The paper's deployed figure is printed beside them: the
32 M student in FP16 on TensorRT 8.5, Jetson Xavier NX: 12 ms for the engine.

    tools/run.sh python -m leapnbv_model_tools export-hmr --checkpoint smpler_x_s32.pth.tar \\
        --variant s32 --out s32.onnx                     # (tools environment; smplest_x_h likewise)
    scripts/env.sh python scripts/bench/bench_hmr_models.py s32.onnx b32.onnx [--threads 1 2] [--runs 10]
        [--body-model models/stand_in/stand_in_smplx_dense.npz]

The cost of a body-only engine (``export-hmr ... --without-hands``): give a full export and the
body-only export of the same checkpoint with ``--hand-cost``,

    scripts/env.sh python scripts/bench/bench_hmr_models.py s32.onnx s32_body_only.onnx --hand-cost

and after the timings it prints (i) the largest difference of the body and face parameters between
the two engines' whole estimates on --crops crops (they should be equal), (ii) the mesh difference
that the flat (mean-pose) hands make there: mean and max vertex distance and PA-MPVPE over the
whole mesh, and the mean and max over the hand vertices (those whose dominant skinning joint is a
wrist or a finger joint), and (iii) the same figures for realistic hand poses computed with the
SMPL-X tail alone: --hand-samples poses whose 90 hand axis-angle components are drawn from
N(0, --hand-std rad) against the mean pose (random weights give arbitrary hand poses, so (ii) is
not a figure for a trained network).

Exit codes: 0 done; 2 a model or the body model could not be loaded, or --hand-cost without a full
and a body-only export (one line naming it).
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


def timed(function: Callable[[], object], runs: int, warmup: int) -> Tuple[float, float, float]:
    """Median and p95 wall time and median process CPU time (all threads), in ms.

    On a busy machine the wall time grows with the others' load; the CPU time much less."""
    for _ in range(warmup):
        function()
    samples: List[float] = []
    cpu: List[float] = []
    for _ in range(runs):
        start, start_cpu = time.perf_counter(), time.process_time()
        function()
        samples.append((time.perf_counter() - start) * 1e3)
        cpu.append((time.process_time() - start_cpu) * 1e3)
    return float(np.median(samples)), float(np.percentile(samples, 95)), float(np.median(cpu))


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("models", nargs="+", help="export-hmr ONNX files; the first is the reference")
    parser.add_argument("--threads", type=int, nargs="+", default=[1, 2])
    parser.add_argument("--runs", type=int, default=10)
    parser.add_argument("--warmup", type=int, default=2)
    parser.add_argument("--body-model", default=None,
                        help="SMPL-X .npz for the tail (default: the dense SMPL-X-layout stand-in, generated)")
    parser.add_argument("--hand-cost", action="store_true",
                        help="the mesh cost of a body-only export: needs a full and a body-only export (see above)")
    parser.add_argument("--crops", type=int, default=5, help="--hand-cost: crops through both engines")
    parser.add_argument("--hand-samples", type=int, default=200, help="--hand-cost: hand poses through the tail")
    parser.add_argument("--hand-std", type=float, default=0.3, help="--hand-cost: std of each hand component, rad")
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
          f"{' '.join(f'{v:.1f}' for v in os.getloadavg())}); median / p95 ms over {args.runs} runs, "
          "CPU: median process CPU time (all threads) ms")
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
            median, p95, cpu = timed(functools.partial(backend.run, feed), args.runs, args.warmup)
            key = ("engine", threads)
            if index == 0:
                reference[key] = median
            print(f"  engine, {threads} thread(s)         {median:8.1f} / {p95:8.1f}   "
                  f"x{median / reference[key]:5.2f} of the first model   CPU {cpu:6.1f}   "
                  f"(session load {load_s:.1f} s)")
            if threads == max(args.threads):
                # The tail's parameters the export was made for (SMPLest-X: box x 1.2, left hand not mirrored).
                unmirror = meta.get("leapnbv.unmirror_left_hand", "true") == "true"
                estimator = HumanMeshEstimator(backend, body, box_scale=float(meta.get("leapnbv.box_ratio", 1.25)),
                                               unmirror_left_hand=unmirror)
                median, p95, cpu = timed(functools.partial(estimator.estimate, frame, box), args.runs, args.warmup)
                key = ("estimate", threads)
                if index == 0:
                    reference[key] = median
                print(f"  whole estimate, {threads} thread(s) {median:8.1f} / {p95:8.1f}   "
                      f"x{median / reference[key]:5.2f} of the first model   CPU {cpu:6.1f}   "
                      "(crop + engine + SMPL-X tail)")
    print(f"load average now {' '.join(f'{v:.1f}' for v in os.getloadavg())}")
    print(f"\npaper: the 32 M student, FP16, TensorRT 8.5, Jetson Xavier NX: engine {PAPER_ENGINE_MS:.0f} ms")
    if args.hand_cost:
        return print_hand_cost(args, body)
    return 0


# SMPL-X joints: 20 / 21 the wrists, 25-39 the left hand's fingers, 40-54 the right hand's.
HAND_JOINTS = np.array([20, 21] + list(range(25, 55)))


def hand_vertices(body) -> np.ndarray:
    """Indices of the vertices whose largest skinning weight is on a wrist or a finger joint."""
    return np.flatnonzero(np.isin(np.argmax(body.weights, axis=1), HAND_JOINTS))


def mesh_difference(reference: np.ndarray, other: np.ndarray, hands: np.ndarray) -> Dict[str, float]:
    """mm: mean / max vertex distance (no alignment) and PA-MPVPE over the whole mesh; mean / max over the hand
    vertices, without alignment and (``hand_pa_mean``) after the whole mesh's Procrustes alignment."""
    from leapnbv_common.procrustes import procrustes_align

    distance = np.linalg.norm(np.asarray(other, np.float64) - np.asarray(reference, np.float64), axis=1) * 1e3
    aligned = np.linalg.norm(procrustes_align(other, reference) - np.asarray(reference, np.float64), axis=1) * 1e3
    return {"mean": float(distance.mean()), "max": float(distance.max()), "pa_mpvpe": float(aligned.mean()),
            "hand_mean": float(distance[hands].mean()), "hand_max": float(distance[hands].max()),
            "hand_pa_mean": float(aligned[hands].mean())}


def print_differences(title: str, rows: List[Dict[str, float]]) -> None:
    print(title)
    print("  | figure (mm) | median | max |\n  |---|---|---|")
    labels = {"mean": "whole mesh, mean vertex distance", "max": "whole mesh, max vertex distance",
              "pa_mpvpe": "whole mesh, PA-MPVPE", "hand_mean": "hand vertices, mean distance",
              "hand_max": "hand vertices, max distance",
              "hand_pa_mean": "hand vertices, mean distance after the whole mesh's PA alignment"}
    for key, label in labels.items():
        values = [row[key] for row in rows]
        print(f"  | {label} | {np.median(values):.1f} | {np.max(values):.1f} |")


def print_hand_cost(args, body) -> int:
    from leapnbv_perception.backends.onnxruntime_backend import OnnxRuntimeBackend
    from leapnbv_perception.hmr import HumanMeshEstimator, hands_estimated, read_export_metadata
    from leapnbv_perception.smplx_layer import NUM_HAND_JOINTS, SMPLXParams

    metadata = [read_export_metadata(path) for path in args.models]
    full = [path for path, meta in zip(args.models, metadata) if meta and hands_estimated(meta)]
    body_only = [path for path, meta in zip(args.models, metadata) if meta and not hands_estimated(meta)]
    if not full or not body_only:
        print("bench_hmr_models: --hand-cost needs a full export and a body-only export (export-hmr --without-hands) "
              f"among the models; got full {full}, body-only {body_only}", file=sys.stderr)
        return 2
    sha = {path: meta.get("leapnbv.checkpoint_sha256") for path, meta in zip(args.models, metadata)}
    if sha[full[0]] != sha[body_only[0]]:
        print(f"bench_hmr_models: {full[0]} and {body_only[0]} come from different checkpoints "
              f"({sha[full[0]][:12]} / {sha[body_only[0]][:12]})", file=sys.stderr)
        return 2
    hands = hand_vertices(body)
    print(f"\n== the cost of the body-only engine: {full[0]} against {body_only[0]} "
          f"(same checkpoint {sha[full[0]][:12]})")
    print(f"hand vertices: {hands.size} of {body.num_vertices} (dominant skinning joint a wrist or a finger)")
    estimators = [HumanMeshEstimator(OnnxRuntimeBackend(path, intra_op_threads=max(args.threads)), body)
                  for path in (full[0], body_only[0])]
    rng = np.random.default_rng(1)
    rows, parameter_difference, body_only_hands = [], 0.0, 0.0
    for _ in range(args.crops):
        frame = rng.integers(0, 255, size=(480, 640, 3), dtype=np.uint8)
        x, y = rng.uniform(100, 400), rng.uniform(20, 120)
        box = [x, y, x + rng.uniform(120, 220), y + rng.uniform(250, 350), 0.9]
        with_hands, without = (estimator.estimate(frame, box) for estimator in estimators)
        for name in ("root", "body", "jaw", "betas", "expression", "cam_translation"):
            parameter_difference = max(parameter_difference,
                                       float(np.abs(getattr(with_hands, name) - getattr(without, name)).max()))
        hand_poses = np.concatenate([without.left_hand, without.right_hand])
        body_only_hands = max(body_only_hands, float(np.abs(hand_poses).max()))
        rows.append(mesh_difference(with_hands.vertices, without.vertices, hands))
    print(f"body and face parameters (root, body, jaw, betas, expression, camera translation): largest difference "
          f"{parameter_difference:.2g} over {args.crops} crops; the body-only hand poses' largest |axis-angle| "
          f"{body_only_hands:.2g} rad (0: the SMPL-X hand mean pose)")
    print_differences(f"(ii) whole estimates on {args.crops} random crops (random weights: arbitrary full-engine "
                      "hand poses; the body-only mesh against the full mesh):", rows)
    rows = []
    rest = body.forward(SMPLXParams.zeros(), add_hand_mean=True).vertices
    for _ in range(args.hand_samples):
        poses = rng.normal(0.0, args.hand_std, size=(2, NUM_HAND_JOINTS, 3))
        params = SMPLXParams.from_axis_angle(np.zeros(3), np.zeros(63), poses[0], poses[1], np.zeros(3))
        rows.append(mesh_difference(body.forward(params, add_hand_mean=True).vertices, rest, hands))
    print_differences(f"(iii) realistic hand poses, SMPL-X tail alone: {args.hand_samples} poses with every hand "
                      f"component ~ N(0, {args.hand_std} rad) about the mean pose, against the mean pose "
                      "(rest body, zero shape):", rows)
    return 0


if __name__ == "__main__":
    sys.exit(main())
