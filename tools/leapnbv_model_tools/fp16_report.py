"""fp16-check's report: the ranges per normalization against the FP16 limit (PNG) and the Markdown
table of ranges, verdicts, kept nodes and the verification."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Dict, List, Optional

import numpy as np

from leapnbv_model_tools.fp16_emulation import FP16_MAX
from leapnbv_model_tools.fp16_normalizations import Normalization


def write_ranges_png(norms: List[Normalization], path: str, title: str) -> str:
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib import pyplot as plt

    figure, axis = plt.subplots(figsize=(max(6.0, 0.35 * len(norms) + 2.0), 4.5))
    positions = np.arange(len(norms))
    sums = [max(n.stats["max_sum_squares"], 1e-3) for n in norms]
    peaks = [max(n.stats["max_abs_input"], 1e-3) for n in norms]
    colours = {"overflow": "tab:red", "precision": "tab:orange", "ok": "tab:blue"}
    axis.bar(positions, sums, color=[colours.get(n.verdict, "grey") for n in norms], label="max sum of squares")
    axis.plot(positions, peaks, "k.", label="max |input|")
    axis.axhline(FP16_MAX, color="tab:red", linestyle="--", label="FP16 max 65504")
    axis.set_yscale("log")
    axis.set_xticks(positions)
    axis.set_xticklabels([n.name for n in norms], rotation=90, fontsize=7)
    axis.set_ylabel("over the calibration crops")
    axis.set_title(title)
    axis.legend(fontsize=8)
    figure.tight_layout()
    figure.savefig(path, dpi=100)
    plt.close(figure)
    return path


def write_report(path: str, model_path: str, norms: List[Normalization], crops: int, headroom: float,
                 tolerance: float, kept: List[str], verification: Optional[Dict[str, float]],
                 png_name: str, outputs: Dict[str, str]) -> str:
    lines = [f"# FP16 check of `{os.path.basename(model_path)}`", "",
             f"{crops} calibration crop(s); FP16 limit {FP16_MAX:.0f}; headroom {headroom:g}; "
             f"tolerance {tolerance:g} (normalized output, relative to max(1, its largest magnitude)).", "",
             "| normalization | kind | width | max sum of squares | / 65504 | max abs input | FP16 emulation error "
             "| verdict |", "|---|---|---|---|---|---|---|---|"]
    for n in norms:
        s = n.stats
        lines.append(f"| `{n.name}` | {n.kind} | {n.width} | {s['max_sum_squares']:.1f} | "
                     f"{s['max_sum_squares'] / FP16_MAX:.3f} | {s['max_abs_input']:.2f} | {s['emulated_error']:.3g} "
                     f"| {n.verdict} |")
    lines += ["", f"Nodes kept in FP32 ({len(kept)}): " + (", ".join(f"`{k}`" for k in kept) or "none"), ""]
    if verification:
        lines += ["Verification on the calibration crops (largest |output - FP32| / largest |FP32 output|, "
                  "FP16 emulated):", "", "| model | relative error |", "|---|---|"]
        lines += [f"| {name} | {value:.3g} |" for name, value in verification.items()]
        lines.append("")
    lines += [f"![ranges]({png_name})", "", "Files: " + ", ".join(f"{k} `{v}`" for k, v in outputs.items()), ""]
    Path(path).write_text("\n".join(lines), encoding="utf-8")
    return path
