"""The table per benchmark family, from the runs scripts/family_benchmark.sh wrote.

Reads OUT/<family>/paper/run.json and OUT/<family>/mesh/run.json and prints, per family: leap_nbv
with the paper's S_o, leap_nbv with the mesh S_o, random and oracle (both from the paper run: the
same candidates): scenes, success (%), mean surface coverage before -> after (%), mean travel of the
camera's foot point (straight distance on the floor, m; the planner's path is at least this), and the
start views whose published floor was wrong (> 2 deg or > 5 cm from the truth). Then the same over
all families.
Usage: scripts/env.sh python scripts/family_table.py OUT
Exit 0; 2 when OUT holds no run.
"""
from __future__ import annotations

import math
import os
import sys
from typing import Dict, List, Tuple

from leapnbv_evaluation.results import EvaluationRun

ROWS: Tuple[Tuple[str, str, str], ...] = (
    ("leap_nbv (paper S_o)", "paper", "leap_nbv"),
    ("leap_nbv (mesh S_o)", "mesh", "leap_nbv"),
    ("random", "paper", "random"),
    ("oracle", "paper", "oracle"),
)


def wrong_floor(scene) -> bool:
    truth = scene.graph_vs_truth
    if truth.ground_valid is None or not truth.ground_valid:
        return True
    return truth.ground_tilt_error_deg > 2.0 or abs(truth.ground_offset_m - truth.truth_ground_offset_m) > 0.05


def stats(run: EvaluationRun, method: str) -> Dict[str, float]:
    scenes = [s for s in run.scenes if method in s.per_method]
    results = [s.per_method[method] for s in scenes]
    travel = [math.dist(r.pose.position_m[:2], s.start_pose.position_m[:2]) for s, r in zip(scenes, results)]
    return {"n": len(results), "success": 100.0 * sum(r.success for r in results) / max(1, len(results)),
            "before": 100.0 * sum(r.before.surface_coverage for r in results) / max(1, len(results)),
            "after": 100.0 * sum(r.after.surface_coverage for r in results) / max(1, len(results)),
            "travel": sum(travel) / max(1, len(travel))}


def main(argv: List[str]) -> int:
    if len(argv) != 1 or not os.path.isdir(argv[0]):
        print("usage: family_table.py OUT (the folder scripts/family_benchmark.sh wrote)", file=sys.stderr)
        return 2
    out = argv[0]
    lines = ["| family | method | scenes | success (%) | coverage before -> after (%) | travel (m) |",
             "|---|---|---:|---:|---:|---:|"]
    totals: Dict[str, List[Dict[str, float]]] = {label: [] for label, _, _ in ROWS}
    floors = [0, 0]
    failures = 0
    for family in sorted(os.listdir(out)):
        runs = {}
        for variant in ("paper", "mesh"):
            path = os.path.join(out, family, variant, "run.json")
            if os.path.exists(path):
                runs[variant] = EvaluationRun.read(path)
        if not runs:
            continue
        if "paper" in runs:
            floors[0] += sum(wrong_floor(s) for s in runs["paper"].scenes)
            floors[1] += len(runs["paper"].scenes)
            failures += sum(1 for s in runs["paper"].scenes if s.graph_failure)
        for label, variant, method in ROWS:
            if variant not in runs or method not in runs[variant].methods:
                continue
            row = stats(runs[variant], method)
            totals[label].append(row)
            lines.append(f"| {family} | {label} | {row['n']} | {row['success']:.1f} | {row['before']:.1f} -> "
                         f"{row['after']:.1f} | {row['travel']:.2f} |")
    if not floors[1]:
        print(f"family_table: no run.json under {out}", file=sys.stderr)
        return 2
    for label, rows in totals.items():
        n = sum(r["n"] for r in rows)
        if not n:
            continue
        mean = {key: sum(r[key] * r["n"] for r in rows) / n for key in ("success", "before", "after", "travel")}
        lines.append(f"| all | {label} | {n} | {mean['success']:.1f} | {mean['before']:.1f} -> {mean['after']:.1f} | "
                     f"{mean['travel']:.2f} |")
    print("\n".join(lines))
    print(f"\nwrong floor on the start view (> 2 deg or > 5 cm, graph's plane vs truth): {floors[0]} of {floors[1]}; "
          f"graph failures: {failures}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
