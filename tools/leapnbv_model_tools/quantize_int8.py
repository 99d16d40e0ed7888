"""quantize-int8: static INT8 quantization (QDQ) of the CPU engines, built for the CPU it runs on.

Calibrated on frames the simulator renders, with its accuracy and speed cost against FP32 measured on
other frames.

Runs with the robot's environment (the simulator renders the frames with numba; onnxruntime's
quantizer is in its lock), the tools folder on the path:

    PYTHONPATH=tools scripts/env.sh python -m leapnbv_model_tools quantize-int8 hmr s32.onnx \
        --out s32.int8.onnx [--calib 32] [--eval 16]
    PYTHONPATH=tools scripts/env.sh python -m leapnbv_model_tools quantize-int8 detector yolov8s.onnx \
        --out yolov8s.int8.onnx

Calibration inputs are what the node would feed the engine: for ``hmr`` the SMPLer-X crop of the
person box of benchmark scenes (leapnbv_perception.hmr_crop), for ``detector`` the letterboxed frame
(at the model's input size). Evaluation uses other scenes than calibration. The quantized model is
onnxruntime's QDQ format, static (MinMax calibration), per-channel symmetric int8 weights, written
beside the target and moved into place when done. The recipe (leapnbv_model_tools.int8_recipe, docs/INT8.md):

- before quantizing, the transposed convolutions are rewritten as convolutions (onnxruntime has no
  integer ConvTranspose: int8_graph.conv_transpose_to_conv) and onnxruntime's pre-processing runs
  (quant_pre_process: symbolic shape inference, graph optimization, ONNX shape inference);
- ``--recipe auto`` (default) picks the integer format for the CPU (``--target-cpu``, default this
  machine's, from /proc/cpuinfo): **u8s8** (uint8 activations, int8 weights) on x86-64 with VNNI or
  AMX, u8s8-reduce-range (7-bit weights) on x86-64 with AVX2 / AVX-512 but no VNNI, s8s8 (symmetric
  int8 activations, what TensorRT takes) on ARM64; ``--recipe s8s8`` etc. asks for one;
- ``--op-set`` (default per engine: detector ``all``, hmr ``products``) and ``--keep-fp32`` (default
  per engine: hmr ``heads``, the encoder's last LayerNorm and the regression heads; detector ``none``)
  say what is quantized.

The choice is printed and written in the model's metadata (``leapnbv.int8.*``: recipe, activation
and weight types, why, the CPU, pre-processing, FP32 layers, calibration); the source model's
``leapnbv.*`` metadata (the export's) is kept.

Cost reported against the FP32 model on the evaluation frames:
- hmr: PA-MPVPE (mm) between the INT8 and the FP32 meshes through the same SMPL-X tail
  (leapnbv_evaluation.metrics.pa_mpvpe_mm), and the largest output difference;
- detector: IoU between the INT8 and FP32 decoded boxes of every anchor (all 80x80+40x40+20x20 at
  640), and the largest class-score difference; with trained weights, compare the detections too;
- both: engine median / p95 ms on one thread, FP32 and INT8 in the same process.

The engines run INT8 only on onnxruntime's CPU path: a QDQ model is a separate file and the node
runs it only when its model_file_path names it (never a silent default).

Exit codes (leapnbv_model_tools.exit_codes): 0 done; 2 a file missing or not an engine of that kind, or a
model the pre-processing refuses.
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
    """The HMR engine's feeds: the SMPLer-X crop of each frame's person box at input_hw."""
    from leapnbv_perception.hmr_crop import engine_input_for_box
    from leapnbv_perception.model_contracts import HMR_INPUT_NAME

    feeds = []
    for rgb, box in frames:
        feeds.append({HMR_INPUT_NAME: engine_input_for_box(rgb, box, input_hw)[0]})
    return feeds


def detector_inputs(frames, size: int) -> List[Dict[str, np.ndarray]]:
    """The detector's feeds: each frame letterboxed to size x size."""
    from leapnbv_perception.detector_families.yolov8 import letterbox
    from leapnbv_perception.model_contracts import YOLO_INPUT_NAME

    return [{YOLO_INPUT_NAME: letterbox(rgb, size)[0]} for rgb, _ in frames]


def engine_inputs(kind: str, shape: Sequence[object], frames) -> List[Dict[str, np.ndarray]]:
    """The engine's feeds for ``frames`` ((rgb, box) pairs): the HMR crop or the letterboxed frame at its input."""
    if kind == "hmr":
        return hmr_inputs(frames, (int(shape[2]), int(shape[3])))  # type: ignore[call-overload]
    return detector_inputs(frames, int(shape[2]))  # type: ignore[call-overload]


class FeedReader:
    """onnxruntime's CalibrationDataReader over a list of feeds (one pass)."""

    def __init__(self, feeds: Sequence[Dict[str, np.ndarray]]) -> None:
        self.feeds = iter(feeds)

    def get_next(self) -> Optional[Dict[str, np.ndarray]]:
        """The next feed, None after the last."""
        return next(self.feeds, None)

    def rewind(self) -> None:
        """Not supported: one pass (quantize_static reads it once)."""
        raise NotImplementedError


def timed_pair(first: Callable[[], object], second: Callable[[], object], runs: int = 10) -> tuple:
    """((median, p95) of first, (median, p95) of second) in ms, the two run alternately (the same load)."""
    first()
    second()
    samples: tuple = ([], [])
    for _ in range(runs):
        for function, into in ((first, samples[0]), (second, samples[1])):
            start = time.perf_counter()
            function()
            into.append((time.perf_counter() - start) * 1e3)
    return tuple((float(np.median(s)), float(np.percentile(s, 95))) for s in samples)


def anchor_box_iou(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """IoU per anchor of two (4, A) cx, cy, w, h arrays."""
    ax0, ay0, ax1, ay1 = a[0] - a[2] / 2, a[1] - a[3] / 2, a[0] + a[2] / 2, a[1] + a[3] / 2
    bx0, by0, bx1, by1 = b[0] - b[2] / 2, b[1] - b[3] / 2, b[0] + b[2] / 2, b[1] + b[3] / 2
    inter = np.clip(np.minimum(ax1, bx1) - np.maximum(ax0, bx0), 0, None) * \
        np.clip(np.minimum(ay1, by1) - np.maximum(ay0, by0), 0, None)
    union = a[2] * a[3] + b[2] * b[3] - inter
    return np.where(union > 0, inter / np.maximum(union, 1e-12), 1.0)




def _one_line(error: BaseException) -> str:
    return "; ".join(part.strip() for part in str(error).splitlines() if part.strip())


def main(argv: Optional[Sequence[str]] = None) -> int:
    """quantize-int8's command line (the module docstring); returns the exit code."""
    from leapnbv_model_tools import int8_recipe
    from leapnbv_model_tools.exit_codes import ModelToolExit

    parser = argparse.ArgumentParser(prog="python -m leapnbv_model_tools quantize-int8", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("kind", choices=["hmr", "detector"])
    parser.add_argument("model")
    parser.add_argument("--out", required=True)
    parser.add_argument("--calib", type=int, default=32, help="calibration frames")
    parser.add_argument("--eval", type=int, default=16, help="evaluation frames (other scenes)")
    parser.add_argument("--recipe", default="auto", choices=("auto",) + int8_recipe.RECIPES,
                        help="integer format: auto (by --target-cpu), u8s8, u8s8-reduce-range or s8s8")
    parser.add_argument("--target-cpu", default="this", choices=("this",) + int8_recipe.CPU_KINDS,
                        help="the CPU kind the model is for (auto recipe): this machine's, or another's")
    parser.add_argument("--keep-fp32", default="auto", choices=("auto", "none", "heads"),
                        help="layers left in FP32: auto (hmr: heads, detector: none), none, or heads (the HMR "
                             "engine's final LayerNorm and regression heads)")
    parser.add_argument("--op-set", default="auto", choices=("auto", "all", "no-softmax", "products"),
                        help="operators quantized: auto (detector: all, hmr: products), all that onnxruntime can, "
                             "all but Softmax, or only the products (Conv, MatMul, Gemm) and the data movement")
    args = parser.parse_args(argv)

    from leapnbv_perception.backends import BackendError, ModelFileNotFoundError
    from leapnbv_perception.backends.onnxruntime_backend import OnnxRuntimeBackend

    try:
        fp32 = OnnxRuntimeBackend(args.model, intra_op_threads=1)
    except (ModelFileNotFoundError, BackendError) as error:
        print(f"quantize-int8: {_one_line(error)}", file=sys.stderr)
        return int(ModelToolExit.BAD_INPUT)
    cpu = int8_recipe.this_cpu()
    target = cpu if args.target_cpu == "this" else int8_recipe.CpuInfo(args.target_cpu, "named with --target-cpu")
    chosen, why = int8_recipe.choose_recipe(args.recipe, target)
    keep_fp32 = args.keep_fp32 if args.keep_fp32 != "auto" else KEEP_FP32_DEFAULT[args.kind]
    op_set = args.op_set if args.op_set != "auto" else int8_recipe.OP_SETS[args.kind]
    float_outputs = int8_recipe.FLOAT_OUTPUTS[args.kind]
    print(f"quantize-int8: recipe {chosen.name} (activations {chosen.activation_type}, weights {chosen.weight_type} "
          f"per-channel{', reduce-range' if chosen.reduce_range else ''}; {why}); this CPU: {cpu.describe()}; "
          f"FP32 layers: {keep_fp32}; operators quantized: {op_set}", flush=True)
    shape = next(iter(fp32.input_specs.values())).shape
    started = time.perf_counter()
    calibration = engine_inputs(args.kind, shape, rendered_frames(args.calib, offset=0))
    evaluation_frames = rendered_frames(args.eval, offset=args.calib)
    evaluation = engine_inputs(args.kind, shape, evaluation_frames)

    import onnx

    final = os.path.abspath(args.out)
    with tempfile.TemporaryDirectory(dir=os.path.dirname(final), prefix=".quantize-") as work:
        prepared = os.path.join(work, "prepared.onnx")
        try:
            rewritten = int8_recipe.prepare(args.model, prepared)
        except Exception as error:  # noqa: BLE001 - onnx / onnxruntime raise their own untyped errors
            print(f"quantize-int8: could not prepare '{args.model}': {_one_line(error)}", file=sys.stderr)
            return int(ModelToolExit.BAD_INPUT)
        excluded = int8_recipe.excluded_nodes(onnx.load(prepared, load_external_data=False), keep_fp32)
        staged = os.path.join(work, os.path.basename(final))
        int8_recipe.quantize(prepared, staged, FeedReader(calibration), chosen, nodes_to_exclude=excluded,
                             op_types=int8_recipe.quantized_ops(op_set), float_outputs=float_outputs)
        int8_recipe.write_metadata(staged, int8_recipe.metadata(chosen, why, target, rewritten, len(excluded),
                                                                keep_fp32, len(calibration), op_set, float_outputs),
                                   keep_from=args.model)
        os.replace(staged, final)
    print(f"{final}: INT8 QDQ {chosen.name}, {rewritten} transposed convolutions rewritten, {len(excluded)} nodes "
          f"kept FP32, calibrated on {len(calibration)} rendered frames in {time.perf_counter() - started:.0f} s")
    int8 = OnnxRuntimeBackend(final, intra_op_threads=1)
    sizes = [os.path.getsize(p) / 1e6 for p in (args.model, final)]
    if args.kind == "hmr":
        print(hmr_accuracy(fp32, int8, evaluation, evaluation_frames))
    else:
        print(detector_accuracy(fp32, int8, evaluation))
    feed = evaluation[0]
    (m32, p32), (m8, p8) = timed_pair(lambda: fp32.run(feed), lambda: int8.run(feed))
    print(f"engine on one thread (median / p95 ms, run alternately): FP32 {m32:.1f} / {p32:.1f}, INT8 {m8:.1f} / "
          f"{p8:.1f} (x{m32 / m8:.2f}); size {sizes[0]:.0f} -> {sizes[1]:.0f} MB; load average "
          f"{' '.join(f'{v:.1f}' for v in os.getloadavg())}")
    return int(ModelToolExit.OK)


#: the layers --keep-fp32 auto leaves in FP32 per engine (docs/INT8.md: measured on the learned student)
KEEP_FP32_DEFAULT = {"hmr": "heads", "detector": "none"}


def hmr_accuracy(fp32, int8, evaluation, frames) -> str:
    """PA-MPVPE between the INT8 and FP32 meshes through the same SMPL-X tail, and the largest output difference."""
    from leapnbv_common.procrustes import pa_mpvpe_mm
    from leapnbv_perception.hmr import HumanMeshEstimator
    from leapnbv_perception.smplx_layer import SMPLXModel
    from leapnbv_stand_ins.files import ensure_stand_in_smplx_dense

    body = SMPLXModel.load(ensure_stand_in_smplx_dense())
    worst = 0.0
    for feed in evaluation:
        a, b = fp32.run(feed), int8.run(feed)
        worst = max(worst, max(float(np.abs(a[k] - b[k]).max()) for k in a))
    estimators = [HumanMeshEstimator(engine, body) for engine in (fp32, int8)]
    errors = []
    for rgb, box in frames:
        meshes = [e.estimate(rgb, box).vertices for e in estimators]
        errors.append(pa_mpvpe_mm(meshes[1], meshes[0]))
    return (f"accuracy cost on {len(errors)} other frames: PA-MPVPE INT8 vs FP32 mesh mean {np.mean(errors):.1f} "
            f"mm, max {np.max(errors):.1f} mm; largest output difference {worst:.3g}")


def detector_accuracy(fp32, int8, evaluation) -> str:
    """IoU of every anchor's INT8 and FP32 decoded boxes, and the largest class-score difference."""
    ious, worst = [], 0.0
    for feed in evaluation:
        a, b = fp32.run(feed), int8.run(feed)
        out_a, out_b = next(iter(a.values()))[0], next(iter(b.values()))[0]
        ious.append(anchor_box_iou(out_a[:4], out_b[:4]))
        worst = max(worst, float(np.abs(out_a[4:] - out_b[4:]).max()))
    every = np.concatenate(ious)
    return (f"accuracy cost on {len(evaluation)} other frames: IoU of every anchor's INT8 vs FP32 box p5 "
            f"{np.percentile(every, 5):.3f}, median {np.median(every):.3f}; largest class score difference "
            f"{worst:.3g}")


if __name__ == "__main__":
    sys.exit(main())
