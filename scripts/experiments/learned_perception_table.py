"""The closed loop with learned perception beside ground-truth perception (scripts/experiments/learned_perception.sh).

Reads OUT/learned/run.json and OUT/truth/run.json and prints, for leap_nbv, random and oracle under each
perception: scenes, success (%), surface coverage before -> after (%), person area before -> after (k px)
and the graph mesh's PA-MPVPE before -> after (mm; learned perception only: the truth's mesh is exact).
Usage: scripts/env.sh python scripts/experiments/learned_perception_table.py OUT
Exit 0; 2 when a run is missing.
"""
from __future__ import annotations

import math
import os
import sys
from typing import Callable, List, Optional, Sequence

from leapnbv_evaluation.results import EvaluationRun
from leapnbv_evaluation.task_report import aggregate_task_results

METHODS = ("leap_nbv", "random", "oracle")


def _fmt(value: float, digits: int = 1) -> str:
    return "n/a" if value is None or not math.isfinite(value) else f"{value:.{digits}f}"


def print_table(out_dir: str, variants: Sequence[str], first_column: str, program: str,
                label: Callable[[str, EvaluationRun], str], missing_error: Optional[str] = "n/a") -> int:
    """Print the table of OUT_DIR/<variant>/run.json for each variant; returns the exit code (2: a run missing).

    label: the first column's text of a variant's rows; missing_error: the PA-MPVPE cell of a method without a
    graph mesh (None: its before -> after as they are).
    """
    lines = [f"| {first_column} | method | scenes | success (%) | coverage before -> after (%) | area before -> "
             "after (k px) | PA-MPVPE before -> after (mm) |", "|---|---|---:|---:|---:|---:|---:|"]
    failures = []
    for variant in variants:
        path = os.path.join(out_dir, variant, "run.json")
        if not os.path.exists(path):
            print(f"{program}: run not found: '{path}'", file=sys.stderr)
            return 2
        run = EvaluationRun.read(path)
        failures.append(f"{variant}: {sum(1 for s in run.scenes if s.graph_failure)} of {len(run.scenes)}")
        per_method = aggregate_task_results(run)["per_method"]
        for method in METHODS:
            if method not in per_method:
                continue
            row = per_method[method]
            error = (f"{_fmt(row['pa_mpvpe_before_mm'])} -> {_fmt(row['pa_mpvpe_mm'])}"
                     if missing_error is None or math.isfinite(row["pa_mpvpe_mm"]) else missing_error)
            lines.append(f"| {label(variant, run)} | {method} | {row['scenes']} | {_fmt(row['success_rate_pct'])} | "
                         f"{_fmt(row['coverage_before_pct'])} -> {_fmt(row['coverage_after_pct'])} | "
                         f"{_fmt(row['area_before_kpx'])} -> {_fmt(row['area_after_kpx'])} | {error} |")
    print("\n".join(lines))
    print(f"\ngraph failures: {'; '.join(failures)}")
    return 0


def main(argv: List[str]) -> int:
    """Print the table; returns the exit code."""
    if len(argv) != 1:
        print("usage: learned_perception_table.py OUT", file=sys.stderr)
        return 2
    return print_table(argv[0], ("truth", "learned"), "perception", "learned_perception_table",
                       lambda variant, run: run.perception)


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
