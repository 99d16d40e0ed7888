"""overflow-table: the final normalization's FP16 overflow against the ViT width, naive vs guarded.

    python -m leapnbv_model_tools overflow-table [--widths 384,768,1024,1280] [--rms 7.5] [--out DIR]

For each width D a small ViT built from the SMPLer-X blocks (``smplerx.Block``, the exported
LayerNorm pattern, ``last_norm``) on a 64 x 48 crop (12 patches + 4 task tokens, 2 blocks,
D / 64 heads). Its weights are random (seeded) except the last block's MLP output bias, set
to a zero-mean pattern of RMS ``--rms`` (7.5: peaks about +-13, plus the tokens' own
variation), so the final normalization's input reaches about +-14 while every earlier
normalization sees small values: activations that grow in the last block, as the large ViTs'
do. The final normalization's sum of squares is then about D x 7.5^2: 21.6 k (384), 43 k (768),
57.6 k (1,024), 72 k (1,280) against FP16's 65,504. (D x 14^2, the bound from the peak alone,
would exceed 65,504 already at D = 384: what matters is the sum, not the peak.)

Each model is exported (opset 16, the project's exporter settings), run through
``fp16-check`` on 8 random crops, and compared on 4 crops: FP32 (onnxruntime), naive FP16
(every node FP16) and the guarded FP16 model fp16-check wrote, both run by the FP16 emulator
(fp16.Fp16Emulator: FP16 storage, sequential FP16 accumulation in the reductions; see fp16.py).
"Diverges" means a relative output error above 5 % (or inf/NaN).
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path
from typing import Dict, List, Optional, Sequence

import numpy as np
import torch
from torch import nn

from leapnbv_model_tools.smplerx import LAYER_NORM_EPS, Block, LayerNorm

DIVERGES = 0.05
CROP_HW = (64, 48)


class OverflowViT(nn.Module):
    """A 2-block ViT of width ``dim`` whose last block drives the final normalization's input to +-(about 2 rms)."""

    def __init__(self, dim: int, rms: float = 7.5, depth: int = 2, tokens: int = 4, outputs: int = 32,
                 seed: int = 0) -> None:
        super().__init__()
        generator = torch.Generator().manual_seed(seed)
        patches = (CROP_HW[0] // 16) * (CROP_HW[1] // 16)
        self.patch_embed = nn.Conv2d(3, dim, kernel_size=16, stride=16)
        self.task_tokens = nn.Parameter(torch.randn(1, tokens, dim, generator=generator) * 0.02)
        self.pos_embed = nn.Parameter(torch.randn(1, patches, dim, generator=generator) * 0.02)
        self.blocks = nn.ModuleList([Block(dim, max(1, dim // 64)) for _ in range(depth)])
        self.last_norm = LayerNorm(dim, eps=LAYER_NORM_EPS)
        self.head = nn.Linear(dim, outputs)
        with torch.no_grad():
            for name, parameter in self.named_parameters():
                if name.endswith("weight") and parameter.dim() > 1:
                    parameter.copy_(torch.randn(parameter.shape, generator=generator) * 0.02)
                elif name.endswith("bias") and "norm" not in name:
                    parameter.zero_()
            pattern = torch.rand(dim, generator=generator) * 2.0 - 1.0
            pattern -= pattern.mean()
            self.blocks[-1].mlp.fc2.bias.copy_(pattern * (rms / pattern.pow(2).mean().sqrt()))

    def forward(self, image: torch.Tensor) -> torch.Tensor:
        patches = self.patch_embed(image).flatten(2).transpose(1, 2) + self.pos_embed
        x = torch.cat([self.task_tokens.expand(image.shape[0], -1, -1), patches], dim=1)
        for block in self.blocks:
            x = block(x)
        return self.head(self.last_norm(x))


def export_overflow_vit(model: OverflowViT, path: str) -> str:
    example = torch.zeros(1, 3, *CROP_HW)
    with torch.no_grad():
        torch.onnx.export(model.eval(), (example,), path, input_names=["img"], output_names=["out"],
                          opset_version=16, dynamo=False)
    return path


def table_row(width: int, rms: float, work: Path, calib: int = 8, verify: int = 4, seed: int = 0) -> Dict[str, object]:
    from leapnbv_model_tools.fp16 import fp16_check

    path = export_overflow_vit(OverflowViT(width, rms, seed=seed), str(work / f"overflow_vit_{width}.onnx"))
    crops = np.random.default_rng(seed).uniform(0.0, 1.0, size=(calib, 3) + CROP_HW).astype(np.float32)
    started = time.perf_counter()
    result = fp16_check(path, crops, str(work / f"check_{width}"), verify=True, verify_crops=verify)
    final = [n for n in result.norms if n.name.endswith("last_norm")][0]
    errors = result.verification or {}
    return {
        "width": width,
        "final_sum_squares": final.stats["max_sum_squares"],
        "final_peak": final.stats["max_abs_input"],
        "flagged": [n.name for n in result.norms if n.verdict != "ok"],
        "kept_nodes": len(result.kept_nodes),
        "fp32_emulator": errors.get("fp32 (emulator vs onnxruntime)", float("nan")),
        "naive": errors.get("naive fp16", float("nan")),
        "guarded": errors.get("guarded fp16", float("nan")),
        "seconds": time.perf_counter() - started,
    }


def format_table(rows: List[Dict[str, object]]) -> str:
    lines = ["| width D | final norm max sum of squares | / 65504 | final norm peak abs input | flagged | "
             "FP32 emulator vs onnxruntime | naive FP16 rel. error | guarded FP16 rel. error | naive | guarded |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for row in rows:
        def verdict(error: float) -> str:
            return "diverges" if not np.isfinite(error) or error > DIVERGES else "matches"

        lines.append(
            f"| {row['width']} | {row['final_sum_squares']:.0f} | {row['final_sum_squares'] / 65504.0:.2f} | "
            f"{row['final_peak']:.1f} | {', '.join(row['flagged']) or 'none'} ({row['kept_nodes']} nodes fp32) | "
            f"{row['fp32_emulator']:.1e} | {row['naive']:.3g} | {row['guarded']:.3g} | {verdict(row['naive'])} | "
            f"{verdict(row['guarded'])} |")
    return "\n".join(lines)


def main(argv: Optional[Sequence[str]] = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m leapnbv_model_tools overflow-table", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--widths", default="384,768,1024,1280")
    parser.add_argument("--rms", type=float, default=7.5)
    parser.add_argument("--out", default="", help="keep the models and reports here (default: a temporary folder)")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    try:
        widths = [int(w) for w in args.widths.split(",")]
    except ValueError:
        print(f"overflow-table: --widths '{args.widths}' is not a comma-separated list of integers", file=sys.stderr)
        return 2
    with tempfile.TemporaryDirectory() as temporary:
        work = Path(args.out or temporary)
        work.mkdir(parents=True, exist_ok=True)
        rows = []
        for width in widths:
            rows.append(table_row(width, args.rms, work))
            print(f"width {width}: done in {rows[-1]['seconds']:.1f} s", file=sys.stderr)
    print(format_table(rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
