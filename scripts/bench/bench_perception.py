#!/usr/bin/env python3
"""Benchmark the perception cores on one CPU core: detector post-processing, crop, SMPL-X tail.

Prints median and p95 (ms) over many runs, and the ratio of the SMPL-X tail against a
straightforward reference (joint regression from vertices, float64, per-joint skinning loop)
timed in the same process. Uses the full-size STAND-IN body model (10,475 vertices, the
real SMPL-X size; not SMPL-X) built in memory.

Usage: scripts/bench/bench_perception.py [--runs N]
"""

from __future__ import annotations

import os

# One core: set before numpy is imported.
for _variable in ("NUMBA_NUM_THREADS", "OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_variable] = "1"

import argparse  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from typing import Callable, List, Tuple  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402

_PERCEPTION = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "..", "src", "leapnbv_perception")
sys.path.insert(0, _PERCEPTION)
sys.path.insert(0, os.path.join(_PERCEPTION, "test"))  # reference_smplx: the tests' slow LBS

from reference_smplx import forward_reference  # noqa: E402

from leapnbv_perception.detector_families.yolov8 import decode_person_boxes, letterbox  # noqa: E402
from leapnbv_perception.hmr_crop import crop_for_hmr, fit_to_engine_input, process_box  # noqa: E402
from leapnbv_perception.hmr_tail import camera_translation, unmirror_left_hand  # noqa: E402
from leapnbv_perception.rotations import matrix_to_axis_angle, rot6d_to_matrix  # noqa: E402
from leapnbv_perception.smplx_layer import SMPLXModel, SMPLXParams  # noqa: E402
from leapnbv_stand_ins.stand_in_body_model import build_stand_in_body_model  # noqa: E402


def timed(function: Callable[[], object], runs: int, warmup: int = 30) -> Tuple[float, float]:
    """Median and p95 wall time in ms."""
    for _ in range(warmup):
        function()
    samples: List[float] = []
    for _ in range(runs):
        start = time.perf_counter()
        function()
        samples.append((time.perf_counter() - start) * 1e3)
    return float(np.median(samples)), float(np.percentile(samples, 95))


def realistic_yolo_output(rng: np.random.Generator) -> np.ndarray:
    """1x84x8400 like a real frame: low scores everywhere, a few people with many anchors each."""
    output = np.zeros((1, 84, 8400), dtype=np.float32)
    output[0, 0:2] = rng.uniform(0, 640, size=(2, 8400))
    output[0, 2:4] = rng.uniform(8, 200, size=(2, 8400))
    output[0, 4:] = rng.beta(0.3, 30.0, size=(80, 8400))  # mostly ~0.01
    for centre in ((200.0, 300.0), (420.0, 320.0), (320.0, 250.0)):
        anchors = rng.choice(8400, size=60, replace=False)
        output[0, 0, anchors] = centre[0] + rng.normal(0, 4, 60)
        output[0, 1, anchors] = centre[1] + rng.normal(0, 6, 60)
        output[0, 2, anchors] = 90 + rng.normal(0, 5, 60)
        output[0, 3, anchors] = 260 + rng.normal(0, 8, 60)
        output[0, 4, anchors] = rng.uniform(0.3, 0.95, 60)
    return output


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=300)
    args = parser.parse_args()
    if hasattr(os, "sched_setaffinity"):
        os.sched_setaffinity(0, {0})
    cv2.setNumThreads(1)
    rng = np.random.default_rng(0)
    rgb = rng.integers(0, 255, size=(720, 1280, 3), dtype=np.uint8)

    print("perception cores, one core, %d runs (median / p95 ms)" % args.runs)
    output0 = realistic_yolo_output(rng)
    _, transform = letterbox(rgb)
    median, p95 = timed(lambda: decode_person_boxes(output0, transform, 1280, 720), args.runs)
    print("  decode + NMS (1x84x8400, %3d cand.)    %7.3f / %7.3f"
          % (int((output0[0, 4] >= 0.25).sum()), median, p95))

    def detector_post() -> object:
        _, lb = letterbox(rgb)
        return decode_person_boxes(output0, lb, 1280, 720)

    median, p95 = timed(detector_post, args.runs)
    print("  letterbox + decode + NMS               %7.3f / %7.3f" % (median, p95))
    median, p95 = timed(lambda: letterbox(rgb), args.runs)
    print("  letterbox 1280x720 -> 640x640 alone    %7.3f / %7.3f" % (median, p95))

    box = process_box([500.0, 150.0, 200.0, 450.0], 1280, 720)
    median, p95 = timed(lambda: fit_to_engine_input(crop_for_hmr(rgb, box)[0], (256, 192)), args.runs)
    print("  HMR crop 512x384 (+ 256x192 subsample) %7.3f / %7.3f" % (median, p95))

    arrays = build_stand_in_body_model("full")
    model = SMPLXModel(arrays, source="stand-in full (in memory)")
    heads = {
        "root_pose": rng.normal(0, 1, 6), "body_pose": rng.normal(0, 1, 126), "lhand_pose": rng.normal(0, 1, 90),
        "rhand_pose": rng.normal(0, 1, 90), "jaw_pose": rng.normal(0, 1, 6), "betas": rng.normal(0, 1, 10),
        "expression": rng.normal(0, 1, 10), "cam_param": np.array([0.1, -0.2, 0.0]),
    }

    def tail(reference: bool = False) -> object:
        left = unmirror_left_hand(rot6d_to_matrix(heads["lhand_pose"].reshape(15, 6)))
        params = SMPLXParams(
            root_rotation=rot6d_to_matrix(heads["root_pose"]),
            body_rotations=rot6d_to_matrix(heads["body_pose"].reshape(21, 6)),
            jaw_rotation=rot6d_to_matrix(heads["jaw_pose"]),
            left_hand_rotations=left,
            right_hand_rotations=rot6d_to_matrix(heads["rhand_pose"].reshape(15, 6)),
            betas=heads["betas"],
            expression=heads["expression"],
        )
        posed = forward_reference(model, params) if reference else model.forward(params)
        matrix_to_axis_angle(params.body_rotations)
        return posed.vertices + camera_translation(heads["cam_param"]).astype(np.float32)

    median, p95 = timed(tail, args.runs)
    reference_runs = max(args.runs // 10, 10)
    reference_median, reference_p95 = timed(lambda: tail(True), reference_runs, warmup=2)
    np.testing.assert_allclose(tail(), tail(True), atol=1e-4)
    print("  SMPL-X tail, %d vertices (6D, cam, LBS) %7.3f / %7.3f   goal < 5 ms" % (model.num_vertices, median, p95))
    print("  reference tail (per-joint loop, f64)    %7.3f / %7.3f   (%d runs)"
          % (reference_median, reference_p95, reference_runs))
    print("  speed-up vs reference                   %7.1fx" % (reference_median / median))
    return 0


if __name__ == "__main__":
    sys.exit(main())
