"""ladder: the compression ladder on synthetic data, end to end, on the CPU.

    python -m leapnbv_model_tools ladder --out DIR [--size tiny|full]

1. Data: scenes of the simulator (leapnbv_sim.generation) with ``stand_in_smplx_dense`` (a
   procedural humanoid in SMPL-X's layout: a stand-in, not SMPL-X) in varied poses, shapes,
   headings, distances (1.5-4 m) and occluder shares (5-45 %), rendered from the start camera;
   the person box and the body parameters in the camera frame are the simulator's ground truth.
   Train / validation / test manifests (``distill``'s format) under DIR/data.
2. A wider teacher (``--teacher-variant``, default t128) trained on the ground-truth meshes
   (``distill --targets gt``). Several, comma-separated, side by side: ``t128,smplest_x_t128`` puts
   a SMPLest-X teacher beside the SMPLer-X one (each trained the same way, each distilled into its
   own copy of the student; the folders then carry the teacher's variant).
3. A narrower student (``--student-variant``, default t32) distilled from the teacher's meshes.
4. The same student trained on the ground truth with the same budget (epochs, batch, lr).
5. Each in FP32 (the exported ONNX, onnxruntime) and FP16 (fp16-check's guarded ONNX, run by the
   FP16 emulator for accuracy; latency from onnxruntime's CPU provider on the same FP16 graph):
   PA-MPVPE to the ground truth on the test split, CPU latency (1 thread, median of 10), size.
   DIR/ladder.md (table), DIR/ladder.png (Pareto plot: PA-MPVPE against latency, marker area
   from the size), DIR/ladder.json, and the wall time of the whole run.

Sizes: ``tiny`` (8 train, 4 val, 4 test crops, 1 epoch: the pieces, in minutes) and ``full``
(sized for <= 60 min on 2 cores: 160 train, 16 val, 32 test crops, teacher 3 epochs, students
3 epochs, batch 4). The synthetic-domain student is DIR/student_distilled/student.onnx.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path
from typing import Dict, List, Optional, Sequence

import numpy as np
import torch

SIZES = {
    "tiny": {"train": 8, "val": 4, "test": 4, "teacher_epochs": 1, "student_epochs": 1, "batch": 2},
    "full": {"train": 160, "val": 16, "test": 32, "teacher_epochs": 3, "student_epochs": 3, "batch": 4},
}


def make_dataset(folder: Path, counts: Dict[str, int], body_path: str, seed: int = 1000) -> Dict[str, str]:
    """Render the scenes with the robot's environment (.venv: the simulator needs numba, not torch)."""
    root = Path(__file__).resolve().parents[2]
    python = root / ".venv" / "bin" / "python"
    paths = [root / "tools"] + [root / "src" / p for p in ("leapnbv_perception", "leapnbv_common", "leapnbv_stand_ins",
                                                           "leapnbv_sim", "leapnbv_geometry")]
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(str(p) for p in paths))
    command = [str(python), "-m", "leapnbv_model_tools.ladder_data", "--out", str(folder), "--body", body_path,
               "--seed", str(seed)] + [f"--{k}={counts[k]}" for k in ("train", "val", "test")]
    subprocess.run(command, env=env, check=True)
    return {split: str(folder / f"{split}.jsonl") for split in ("train", "val", "test")}


def latency_ms(path: str, input_hw, runs: int = 10) -> float:
    import onnxruntime

    options = onnxruntime.SessionOptions()
    options.intra_op_num_threads = 1
    session = onnxruntime.InferenceSession(path, options, providers=["CPUExecutionProvider"])
    crop = np.random.default_rng(0).uniform(size=(1, 3) + tuple(input_hw)).astype(np.float32)
    session.run(None, {"img": crop})
    times = []
    for _ in range(runs):
        started = time.perf_counter()
        session.run(None, {"img": crop})
        times.append(time.perf_counter() - started)
    return float(np.median(times) * 1000.0)


def evaluate(onnx_path: str, fp16: bool, test_manifest: str, body_path: str, input_hw,
             unmirror_left: bool = True) -> float:
    """Mean PA-MPVPE (mm) to the ground truth over the test split (``unmirror_left``: the network's family's)."""
    import onnx
    import onnxruntime

    from leapnbv_model_tools.distill import PARAM_SIZES, make_crop, pa_mpvpe_mm, read_manifest
    from leapnbv_model_tools.export import OUTPUT_NAMES
    from leapnbv_model_tools.fp16 import Fp16Emulator
    from leapnbv_model_tools.torch_smplx import TorchSMPLX, mesh_from_axis_angle, mesh_from_outputs
    from leapnbv_perception.smplx_layer import SMPLXModel

    layer = TorchSMPLX(SMPLXModel.load(body_path))
    samples = read_manifest(test_manifest)
    if fp16:
        emulator = Fp16Emulator(onnx.load(onnx_path))
        names = emulator.output_names

        def run(crop):
            return dict(zip(names, emulator.run(crop)))
    else:
        session = onnxruntime.InferenceSession(onnx_path, providers=["CPUExecutionProvider"])

        def run(crop):
            return dict(zip(OUTPUT_NAMES, session.run(list(OUTPUT_NAMES), {"img": crop})))
    errors = []
    for sample in samples:
        outputs = run(make_crop(sample, input_hw)[None])
        with torch.no_grad():
            values = {k: torch.from_numpy(np.asarray(v, np.float32)) for k, v in outputs.items()}
            mesh = mesh_from_outputs(layer, values, unmirror_left)
            truth = mesh_from_axis_angle(layer, {k: torch.from_numpy(sample.params[k][None]).float()
                                                 for k in PARAM_SIZES})
        errors.append(pa_mpvpe_mm(mesh[0].numpy(), truth[0].numpy()))
    return float(np.mean(errors))


def run_ladder(out: Path, size: str, teacher_variant: str, student_variant: str, lr: float) -> Dict[str, object]:
    """``teacher_variant``: one variant, or several comma-separated (each its own teacher and distilled student)."""
    from leapnbv_model_tools.checkpoint import unmirrors_left_hand
    from leapnbv_model_tools.distill import DistillConfig, distill, make_crop, read_manifest
    from leapnbv_model_tools.fp16 import fp16_check
    from leapnbv_stand_ins.files import ensure_stand_in_smplx_dense

    started = time.perf_counter()
    plan = SIZES[size]
    input_hw = (256, 192)
    body = ensure_stand_in_smplx_dense(out / "models")
    manifests = make_dataset(out / "data", plan, body)
    timings = {"data_s": time.perf_counter() - started}

    def train(name: str, variant: str, epochs: int, targets: str, teacher: str = "",
              teacher_variant: str = "") -> Dict[str, object]:
        begun = time.perf_counter()
        result = distill(DistillConfig(
            train=manifests["train"], val=manifests["val"], teacher=teacher, teacher_variant=teacher_variant,
            student_variant=variant, body_model=body, out=str(out / name), epochs=epochs, batch_size=plan["batch"],
            lr=lr, targets=targets))
        timings[f"{name}_s"] = time.perf_counter() - begun
        return result

    teachers = [v for v in teacher_variant.split(",") if v]
    several = len(teachers) > 1
    runs = []  # (row name, variant, distill result)
    for variant in teachers:
        suffix = f"_{variant}" if several else ""
        label = f" from {variant}" if several else ""
        teacher = train(f"teacher_gt{suffix}", variant, plan["teacher_epochs"], "gt")
        distilled = train(f"student_distilled{suffix}", student_variant, plan["student_epochs"], "teacher",
                          str(teacher["checkpoint"]), variant)
        runs += [(f"teacher (GT){' ' + variant if several else ''}", variant, teacher),
                 (f"student distilled{label}", student_variant, distilled)]
    first_distilled = runs[1][2]
    baseline = train("student_gt", student_variant, plan["student_epochs"], "gt")
    runs.append(("student (GT, same budget)", student_variant, baseline))
    calib = np.stack([make_crop(s, input_hw) for s in read_manifest(manifests["val"])])
    rows = []
    for name, variant, result in runs:
        fp32_path = str(result["onnx"])
        check = fp16_check(fp32_path, calib, str(Path(fp32_path).parent / "fp16"), verify=False)
        params = sum(p.numel() for p in torch.load(str(result["checkpoint"]), map_location="cpu",
                                                    weights_only=True)["network"].values())
        for precision, path in (("fp32", fp32_path), ("fp16", check.fp16_path)):
            rows.append({"model": name, "variant": variant, "precision": precision, "parameters": int(params),
                         "size_mb": Path(path).stat().st_size / 1e6,
                         "latency_ms": latency_ms(path, input_hw),
                         "pa_mpvpe_mm": evaluate(path, precision == "fp16", manifests["test"], body, input_hw,
                                                 unmirrors_left_hand(variant)),
                         "fp32_kept_nodes": len(check.kept_nodes) if precision == "fp16" else 0})
    timings["total_s"] = time.perf_counter() - started
    summary = {"size": size, "counts": plan, "rows": rows, "timings": timings,
               "student_onnx": str(first_distilled["onnx"])}
    (out / "ladder.json").write_text(json.dumps(summary, indent=1) + "\n")
    (out / "ladder.md").write_text(format_table(summary) + "\n")
    plot(rows, str(out / "ladder.png"))
    return summary


def format_table(summary: Dict[str, object]) -> str:
    lines = [f"Synthetic ladder ({summary['size']}: {summary['counts']}); "
             f"wall {summary['timings']['total_s']:.0f} s", "",
             "| model | variant | precision | parameters | ONNX MB | CPU latency ms (1 thread) | PA-MPVPE to GT mm "
             "| FP32 nodes kept |", "|---|---|---|---|---|---|---|---|"]
    for row in summary["rows"]:
        lines.append(f"| {row['model']} | {row['variant']} | {row['precision']} | {row['parameters'] / 1e6:.1f} M | "
                     f"{row['size_mb']:.1f} | {row['latency_ms']:.0f} | {row['pa_mpvpe_mm']:.1f} | "
                     f"{row['fp32_kept_nodes']} |")
    return "\n".join(lines)


def plot(rows: List[Dict[str, object]], path: str) -> str:
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib import pyplot as plt

    figure, axis = plt.subplots(figsize=(7, 5))
    for row in rows:
        marker = "o" if row["precision"] == "fp32" else "s"
        axis.scatter(row["latency_ms"], row["pa_mpvpe_mm"], s=20 + 4 * float(row["size_mb"]), marker=marker,
                     alpha=0.7, label=f"{row['model']} {row['precision']}")
    axis.set_xlabel("CPU latency, ms (onnxruntime, 1 thread)")
    axis.set_ylabel("PA-MPVPE to ground truth, mm (synthetic test split)")
    axis.legend(fontsize=7)
    figure.tight_layout()
    figure.savefig(path, dpi=100)
    plt.close(figure)
    return path


def main(argv: Optional[Sequence[str]] = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m leapnbv_model_tools ladder", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", required=True)
    parser.add_argument("--size", default="tiny", choices=sorted(SIZES))
    parser.add_argument("--teacher-variant", default="t128",
                        help="the teacher's variant, or several comma-separated side by side (t128,smplest_x_t128)")
    parser.add_argument("--student-variant", default="t32")
    parser.add_argument("--lr", type=float, default=3e-4)
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    summary = run_ladder(out, args.size, args.teacher_variant, args.student_variant, args.lr)
    print(format_table(summary))
    return 0


if __name__ == "__main__":
    sys.exit(main())
