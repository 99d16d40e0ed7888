"""The continuous runs' table: one row per run folder (OUT/<run>/continuous.json), as continuous_families.sh writes.

Usage: ``scripts/env.sh python scripts/experiments/continuous_table.py out/continuous``
"""
from __future__ import annotations

import json
import os
import sys
from typing import List

from leapnbv_evaluation.continuous_results import ContinuousRun, aggregate_continuous


def _fmt(value: float, digits: int) -> str:
    return "-" if value != value else f"{value:.{digits}f}"  # NaN: no episode it applies to


def main(argv: List[str]) -> int:
    """Print the table of the runs under argv[0]; exit code 2 on a wrong argument."""
    if len(argv) != 1 or not os.path.isdir(argv[0]):
        print("usage: continuous_table.py OUT (a folder of <run>/continuous.json)", file=sys.stderr)
        return 2
    rows = ["| run | episodes | success | arrived | coverage start -> end (best) | time to arrival s median / p95 | "
            "distance / first path median | goal switches median / p95 / max | reversals (% eps) | target swaps |",
            "|---|---|---|---|---|---|---|---|---|---|"]
    for name in sorted(os.listdir(argv[0])):
        path = os.path.join(argv[0], name, "continuous.json")
        if not os.path.isfile(path):
            continue
        with open(path, encoding="utf-8") as handle:
            run = ContinuousRun.from_json(json.load(handle))
        a = aggregate_continuous(run)
        rows.append(f"| {name} | {int(a['episodes'])} | {_fmt(a['success_pct'], 1)} % | "
                    f"{_fmt(a['arrived_pct'], 1)} % | "
                    f"{_fmt(a['coverage_start'], 3)} -> {_fmt(a['coverage_end'], 3)} ({_fmt(a['coverage_best'], 3)}) | "
                    f"{_fmt(a['time_to_arrival_median_s'], 1)} / {_fmt(a['time_to_arrival_p95_s'], 1)} | "
                    f"{_fmt(a['path_ratio_median'], 2)} | {_fmt(a['goal_switches_median'], 0)} / "
                    f"{_fmt(a['goal_switches_p95'], 1)} / {_fmt(a['goal_switches_max'], 0)} | "
                    f"{int(a['reversals_total'])} ({_fmt(a['episodes_with_reversal_pct'], 1)} %) | "
                    f"{int(a['target_swaps_total'])} |")
    print("\n".join(rows))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
