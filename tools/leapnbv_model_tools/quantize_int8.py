"""quantize-int8: static INT8 quantization (QDQ) of the CPU engines, calibrated on frames the simulator
renders, with its accuracy and speed cost against FP32 measured on other frames.

Runs with the robot's environment (the simulator renders the frames with numba; onnxruntime's
quantizer is in its lock), the tools folder on the path:

    PYTHONPATH=tools scripts/env.sh python -m leapnbv_model_tools quantize-int8 hmr s32.onnx \
        --out s32.int8.onnx [--calib 32] [--eval 16]
    PYTHONPATH=tools scripts/env.sh python -m leapnbv_model_tools quantize-int8 detector yolov8s.onnx \
        --out yolov8s.int8.onnx

Calibration inputs are what the node would feed the engine: for ``hmr`` the SMPLer-X crop of the
person box of benchmark scenes (leapnbv_perception.hmr_crop), for ``detector`` the letterboxed frame
(at the model's input size). Evaluation uses other scenes than calibration. The quantized model is
onnxruntime's QDQ format (per-channel weights, MinMax calibration; activations and weights int8),
written beside the target and moved into place when done.

Cost reported against the FP32 model on the evaluation frames:
- hmr: PA-MPVPE (mm) between the INT8 and the FP32 meshes through the same SMPL-X tail
  (leapnbv_evaluation.metrics.pa_mpvpe_mm), and the largest output difference;
- detector: IoU between the INT8 and FP32 decoded boxes of every anchor (all 80x80+40x40+20x20 at
  640), and the largest class-score difference; with trained weights, compare the detections too;
- both: engine median / p95 ms on one thread, FP32 and INT8 in the same process.

The engines run INT8 only on onnxruntime's CPU path: a QDQ model is a separate file and the node
runs it only when its model_file_path names it (never a silent default).

Exit codes: 0 done; 2 a file missing or not an engine of that kind.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from typing import Callable, Dict, List, Optional, Sequence

import numpy as np


def rendered_frames(count: int, offset: int):
    """(rgb, visible-person box) of benchmark scenes seeds[offset:offset+count] (start views)."""
    from leapnbv_evaluation.benchmark_set import benchmark_scene, benchmark_seeds
    from leapnbv_perception.smplx_layer import SMPLXModel
    from leapnbv_stand_ins.files import ensure_stand_in_body_model

    body = SMPLXModel.load(ensure_stand_in_body_model("small"))
    frames = []
    for seed in benchmark_seeds(count, offset=offset, body_model=body):
        frame = benchmark_scene(seed, body).render(benchmark_scene(seed, body).start_camera)
        frames.append((frame.rgb, np.asarray(frame.ground_truth.person_box_xyxy, np.float64)))
    return frames


def hmr_inputs(frames, input_hw) -> List[Dict[str, np.ndarray]]:
    from leapnbv_perception.hmr_crop import engine_input_for_box
    from leapnbv_perception.model_contracts import HMR_INPUT_NAME

    feeds = []
    for rgb, box in frames:
        feeds.append({HMR_INPUT_NAME: engine_input_for_box(rgb, box, input_hw)[0]})
    return feeds


def detector_inputs(frames, size: int) -> List[Dict[str, np.ndarray]]:
    from leapnbv_perception.detector_families.yolov8 import letterbox
    from leapnbv_perception.model_contracts import YOLO_INPUT_NAME

    return [{YOLO_INPUT_NAME: letterbox(rgb, size)[0]} for rgb, _ in frames]


def timed(function: Callable[[], object], runs: int = 10) -> tuple:
    function()
    samples = []
    for _ in range(runs):
        start = time.perf_counter()
        function()
        samples.append((time.perf_counter() - start) * 1e3)
    return float(np.median(samples)), float(np.percentile(samples, 95))


def anchor_box_iou(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """IoU per anchor of two (4, A) cx, cy, w, h arrays."""
    ax0, ay0, ax1, ay1 = a[0] - a[2] / 2, a[1] - a[3] / 2, a[0] + a[2] / 2, a[1] + a[3] / 2
    bx0, by0, bx1, by1 = b[0] - b[2] / 2, b[1] - b[3] / 2, b[0] + b[2] / 2, b[1] + b[3] / 2
    inter = np.clip(np.minimum(ax1, bx1) - np.maximum(ax0, bx0), 0, None) * \
        np.clip(np.minimum(ay1, by1) - np.maximum(ay0, by0), 0, None)
    union = a[2] * a[3] + b[2] * b[3] - inter
    return np.where(union > 0, inter / np.maximum(union, 1e-12), 1.0)


def main(argv: Optional[Sequence[str]] = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m leapnbv_model_tools quantize-int8", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("kind", choices=["hmr", "detector"])
    parser.add_argument("model")
    parser.add_argument("--out", required=True)
    parser.add_argument("--calib", type=int, default=32, help="calibration frames")
    parser.add_argument("--eval", type=int, default=16, help="evaluation frames (other scenes)")
    args = parser.parse_args(argv)

    from onnxruntime.quantization import CalibrationDataReader, QuantFormat, QuantType, quantize_static

    from leapnbv_perception.backends import BackendError, ModelFileNotFoundError
    from leapnbv_perception.backends.onnxruntime_backend import OnnxRuntimeBackend

    try:
        fp32 = OnnxRuntimeBackend(args.model, intra_op_threads=1)
    except (ModelFileNotFoundError, BackendError) as error:
        line = "; ".join(part.strip() for part in str(error).splitlines() if part.strip())  # one line
        print(f"quantize-int8: {line}", file=sys.stderr)
        return 2
    specs = dict(fp32.input_specs)
    name = next(iter(specs))
    shape = specs[name].shape
    if args.kind == "hmr":
        make_inputs = lambda frames: hmr_inputs(frames, (int(shape[2]), int(shape[3])))  # noqa: E731
    else:
        make_inputs = lambda frames: detector_inputs(frames, int(shape[2]))  # noqa: E731
    started = time.perf_counter()
    calibration = make_inputs(rendered_frames(args.calib, offset=0))
    evaluation = make_inputs(rendered_frames(args.eval, offset=args.calib))

    class Reader(CalibrationDataReader):
        def __init__(self, feeds):
            self.feeds = iter(feeds)

        def get_next(self):
            return next(self.feeds, None)

    final = os.path.abspath(args.out)
    with tempfile.TemporaryDirectory(dir=os.path.dirname(final), prefix=".quantize-") as work:
        staged = os.path.join(work, os.path.basename(final))
        quantize_static(args.model, staged, Reader(calibration), quant_format=QuantFormat.QDQ, per_channel=True,
                        activation_type=QuantType.QInt8, weight_type=QuantType.QInt8)
        os.replace(staged, final)
    print(f"{final}: INT8 QDQ, calibrated on {len(calibration)} rendered frames in "
          f"{time.perf_counter() - started:.0f} s")
    int8 = OnnxRuntimeBackend(final, intra_op_threads=1)
    sizes = [os.path.getsize(p) / 1e6 for p in (args.model, final)]
    if args.kind == "hmr":
        from leapnbv_evaluation.metrics import pa_mpvpe_mm
        from leapnbv_perception.hmr import HumanMeshEstimator
        from leapnbv_perception.smplx_layer import SMPLXModel
        from leapnbv_stand_ins.files import ensure_stand_in_smplx_dense

        body = SMPLXModel.load(ensure_stand_in_smplx_dense())
        errors, worst = [], 0.0
        for feed in evaluation:
            a, b = fp32.run(feed), int8.run(feed)
            worst = max(worst, max(float(np.abs(a[k] - b[k]).max()) for k in a))
        estimators = [HumanMeshEstimator(engine, body) for engine in (fp32, int8)]
        for rgb, box in rendered_frames(args.eval, offset=args.calib):
            meshes = [e.estimate(rgb, box).vertices for e in estimators]
            errors.append(pa_mpvpe_mm(meshes[1], meshes[0]))
        print(f"accuracy cost on {len(errors)} other frames: PA-MPVPE INT8 vs FP32 mesh mean {np.mean(errors):.1f} "
              f"mm, max {np.max(errors):.1f} mm; largest output difference {worst:.3g}")
    else:
        ious, worst = [], 0.0
        for feed in evaluation:
            a, b = fp32.run(feed), int8.run(feed)
            out_a, out_b = next(iter(a.values()))[0], next(iter(b.values()))[0]
            ious.append(anchor_box_iou(out_a[:4], out_b[:4]))
            worst = max(worst, float(np.abs(out_a[4:] - out_b[4:]).max()))
        ious = np.concatenate(ious)
        print(f"accuracy cost on {len(evaluation)} other frames: IoU of every anchor's INT8 vs FP32 box p5 "
              f"{np.percentile(ious, 5):.3f}, median {np.median(ious):.3f}; largest class score difference "
              f"{worst:.3g}")
    feed = evaluation[0]
    (m32, p32), (m8, p8) = timed(lambda: fp32.run(feed)), timed(lambda: int8.run(feed))
    print(f"engine on one thread (median / p95 ms): FP32 {m32:.1f} / {p32:.1f}, INT8 {m8:.1f} / {p8:.1f} "
          f"(x{m32 / m8:.2f}); size {sizes[0]:.0f} -> {sizes[1]:.0f} MB; load average "
          f"{' '.join(f'{v:.1f}' for v in os.getloadavg())}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
