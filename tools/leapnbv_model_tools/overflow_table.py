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

``--decoder-widths`` (default 1280) adds rows of the same ViT followed by SMPLest-X's decoder
(``smplest_x.TransformerCrossAttn``: its pre-normed self-attention, cross-attention to the patch
features and feed-forward, 8 heads of 64, LayerNorm eps 1e-5; ``--decoder-depth`` layers, default
2 of the real 6), the learned row vector added before it and ``token_conv`` (D -> 512) on the
tokens after it: SMPLest-X-H's shape (width 1,280 and its decoder) in the table's construction,
where fp16-check sees the decoder's normalizations beside the encoder's.
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
from leapnbv_model_tools.smplest_x import SmplestVariant, TransformerCrossAttn

DIVERGES = 0.05
CROP_HW = (64, 48)


class OverflowViT(nn.Module):
    """A 2-block ViT of width ``dim`` whose last block drives the final normalization's input to +-(about 2 rms)."""

    def __init__(self, dim: int, rms: float = 7.5, depth: int = 2, tokens: int = 4, outputs: int = 32,
                 seed: int = 0, decoder_depth: int = 0) -> None:
        super().__init__()
        self.tokens = tokens
        generator = torch.Generator().manual_seed(seed)
        patches = (CROP_HW[0] // 16) * (CROP_HW[1] // 16)
        self.patch_embed = nn.Conv2d(3, dim, kernel_size=16, stride=16)
        self.task_tokens = nn.Parameter(torch.randn(1, tokens, dim, generator=generator) * 0.02)
        self.pos_embed = nn.Parameter(torch.randn(1, patches, dim, generator=generator) * 0.02)
        self.blocks = nn.ModuleList([Block(dim, max(1, dim // 64)) for _ in range(depth)])
        self.last_norm = LayerNorm(dim, eps=LAYER_NORM_EPS)
        self.decoder = None
        if decoder_depth:  # SMPLest-X's decoder after the encoder (its heads' sizes, this width)
            self.decoder = TransformerCrossAttn(SmplestVariant("overflow", dim, depth, max(1, dim // 64),
                                                               decoder_depth=decoder_depth))
            self.pos_embedding = nn.Parameter(torch.randn(1, 1, dim, generator=generator))
            self.token_conv = nn.Linear(dim, 512)
        self.head = nn.Linear(512 if decoder_depth else dim, outputs)
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
        x = self.last_norm(x)
        if self.decoder is None:
            return self.head(x)
        context = x[:, self.tokens:]
        rows = self.decoder(x + self.pos_embedding, context)
        return self.head(self.token_conv(rows[:, :self.tokens]))


def export_overflow_vit(model: OverflowViT, path: str) -> str:
    example = torch.zeros(1, 3, *CROP_HW)
    with torch.no_grad():
        torch.onnx.export(model.eval(), (example,), path, input_names=["img"], output_names=["out"],
                          opset_version=16, dynamo=False)
    return path


def table_row(width: int, rms: float, work: Path, calib: int = 8, verify: int = 4, seed: int = 0,
              decoder_depth: int = 0) -> Dict[str, object]:
    """One row; ``decoder_depth`` > 0: the ViT followed by that many SMPLest-X decoder layers."""
    from leapnbv_model_tools.fp16 import fp16_check

    stem = f"overflow_vit_{width}" + (f"_decoder{decoder_depth}" if decoder_depth else "")
    model = OverflowViT(width, rms, seed=seed, decoder_depth=decoder_depth)
    path = export_overflow_vit(model, str(work / f"{stem}.onnx"))
    crops = np.random.default_rng(seed).uniform(0.0, 1.0, size=(calib, 3) + CROP_HW).astype(np.float32)
    started = time.perf_counter()
    result = fp16_check(path, crops, str(work / f"check_{stem[len('overflow_vit_'):]}"), verify=True,
                        verify_crops=verify)
    final = [n for n in result.norms if n.name.endswith("last_norm")][0]
    decoder_norms = [n for n in result.norms if "/decoder/" in n.name]
    errors = result.verification or {}
    return {
        "width": width,
        "model": f"ViT + SMPLest-X decoder ({decoder_depth} layers)" if decoder_depth else "ViT",
        "norms": len(result.norms),
        "decoder_norms": len(decoder_norms),
        "decoder_max_sum_squares": max((n.stats["max_sum_squares"] for n in decoder_norms), default=0.0),
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
    notes = []
    for row in rows:
        def verdict(error: float) -> str:
            return "diverges" if not np.isfinite(error) or error > DIVERGES else "matches"

        label = f"{row['width']}" + (" + decoder" if row.get("decoder_norms") else "")
        if row.get("decoder_norms"):
            notes.append(f"{label}: {row['model']}, {row['norms']} normalizations found ({row['decoder_norms']} in the "
                         f"decoder, largest decoder sum of squares {row['decoder_max_sum_squares']:.0f})")
        lines.append(
            f"| {label} | {row['final_sum_squares']:.0f} | {row['final_sum_squares'] / 65504.0:.2f} | "
            f"{row['final_peak']:.1f} | {', '.join(row['flagged']) or 'none'} ({row['kept_nodes']} nodes fp32) | "
            f"{row['fp32_emulator']:.1e} | {row['naive']:.3g} | {row['guarded']:.3g} | {verdict(row['naive'])} | "
            f"{verdict(row['guarded'])} |")
    return "\n".join(lines + ([""] + notes if notes else []))


def main(argv: Optional[Sequence[str]] = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m leapnbv_model_tools overflow-table", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--widths", default="384,768,1024,1280")
    parser.add_argument("--rms", type=float, default=7.5)
    parser.add_argument("--decoder-widths", default="1280",
                        help="widths also built with SMPLest-X's decoder after the ViT ('' for none)")
    parser.add_argument("--decoder-depth", type=int, default=2)
    parser.add_argument("--out", default="", help="keep the models and reports here (default: a temporary folder)")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    try:
        widths = [int(w) for w in args.widths.split(",") if w]
        decoder_widths = [int(w) for w in args.decoder_widths.split(",") if w]
    except ValueError:
        print(f"overflow-table: --widths '{args.widths}' / --decoder-widths '{args.decoder_widths}' is not a "
              "comma-separated list of integers", file=sys.stderr)
        return 2
    if args.decoder_depth < 1:
        print(f"overflow-table: --decoder-depth {args.decoder_depth}: at least 1", file=sys.stderr)
        return 2
    with tempfile.TemporaryDirectory() as temporary:
        work = Path(args.out or temporary)
        work.mkdir(parents=True, exist_ok=True)
        rows = []
        for width, decoder_depth in [(w, 0) for w in widths] + [(w, args.decoder_depth) for w in decoder_widths]:
            rows.append(table_row(width, args.rms, work, decoder_depth=decoder_depth))
            print(f"width {width} ({rows[-1]['model']}): done in {rows[-1]['seconds']:.1f} s", file=sys.stderr)
    print(format_table(rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
