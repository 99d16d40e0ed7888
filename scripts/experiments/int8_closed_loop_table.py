"""The closed loop with the learned HMR engine in FP32 and INT8 (scripts/experiments/int8_closed_loop.sh).

Reads OUT/fp32/run.json and OUT/int8/run.json and prints, for leap_nbv, random and oracle with each engine:
scenes, success (%), surface coverage before -> after (%), person area before -> after (k px) and the graph
mesh's PA-MPVPE before -> after (mm), and the graph failures.
Usage: scripts/env.sh python scripts/experiments/int8_closed_loop_table.py OUT
Exit 0; 2 when a run is missing.
"""
from __future__ import annotations

import math
import os
import sys
from typing import List

from leapnbv_evaluation.results import EvaluationRun
from leapnbv_evaluation.task_report import aggregate_task_results

METHODS = ("leap_nbv", "random", "oracle")


def _fmt(value: float, digits: int = 1) -> str:
    return "n/a" if value is None or not math.isfinite(value) else f"{value:.{digits}f}"


def main(argv: List[str]) -> int:
    """Print the table; returns the exit code."""
    if len(argv) != 1:
        print("usage: int8_closed_loop_table.py OUT", file=sys.stderr)
        return 2
    lines = ["| HMR engine | method | scenes | success (%) | coverage before -> after (%) | area before -> after "
             "(k px) | PA-MPVPE before -> after (mm) |", "|---|---|---:|---:|---:|---:|---:|"]
    failures = []
    for variant in ("fp32", "int8"):
        path = os.path.join(argv[0], variant, "run.json")
        if not os.path.exists(path):
            print(f"int8_closed_loop_table: run not found: '{path}'", file=sys.stderr)
            return 2
        run = EvaluationRun.read(path)
        failures.append(f"{variant}: {sum(1 for s in run.scenes if s.graph_failure)} of {len(run.scenes)}")
        per_method = aggregate_task_results(run)["per_method"]
        for method in METHODS:
            if method not in per_method:
                continue
            row = per_method[method]
            lines.append(f"| {variant.upper()} | {method} | {row['scenes']} | {_fmt(row['success_rate_pct'])} | "
                         f"{_fmt(row['coverage_before_pct'])} -> {_fmt(row['coverage_after_pct'])} | "
                         f"{_fmt(row['area_before_kpx'])} -> {_fmt(row['area_after_kpx'])} | "
                         f"{_fmt(row['pa_mpvpe_before_mm'])} -> {_fmt(row['pa_mpvpe_mm'])} |")
    print("\n".join(lines))
    print(f"\ngraph failures: {'; '.join(failures)}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
