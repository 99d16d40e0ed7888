"""The table per benchmark family, from the runs scripts/experiments/family_benchmark.sh wrote.

Reads OUT/<family>/paper/run.json and OUT/<family>/mesh/run.json and prints, per family: leap_nbv
with the paper's S_o, leap_nbv with the mesh S_o, random and oracle (both from the paper run: the
same candidates): scenes, success (%), mean surface coverage before -> after (%), the mean path length
the robot drives to its pick (m: the shortest free path on the scene's true floor map, the obstacles'
voxels and the person grown by the robot's 0.3 m radius, 0.1 m cells; the planner's own map is what
the robot knew) beside the straight distance, the picks with no such path, and the start views whose
published floor was wrong (> 2 deg or > 5 cm from the truth). Then the same over all families.
Usage: scripts/env.sh python scripts/experiments/family_table.py OUT
Exit 0; 2 when OUT holds no run.
"""
from __future__ import annotations

import math
import os
import sys
from typing import Dict, List, Tuple

import numpy as np

from leapnbv_evaluation.results import EvaluationRun

_SCENES: Dict[Tuple[str, int], object] = {}

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


def true_path_length(room: str, seed: int, start_xy, goal_xy) -> float:
    """Shortest free path (m) from start to goal on the scene's true floor map; inf when there is none."""
    from leapnbv_evaluation.benchmark_set import benchmark_scene
    from leapnbv_evaluation.truth_paths import true_path_lengths
    from leapnbv_perception.smplx_layer import SMPLXModel
    from leapnbv_stand_ins.files import ensure_stand_in_body_model

    key = (room, int(seed))
    if key not in _SCENES:
        _SCENES[key] = benchmark_scene(int(seed), SMPLXModel.load(ensure_stand_in_body_model("small")), room)
    return float(true_path_lengths(_SCENES[key], start_xy, np.asarray([goal_xy]))[0])


def stats(run: EvaluationRun, method: str) -> Dict[str, float]:
    scenes = [s for s in run.scenes if method in s.per_method]
    results = [s.per_method[method] for s in scenes]
    travel = [math.dist(r.pose.position_m[:2], s.start_pose.position_m[:2]) for s, r in zip(scenes, results)]
    paths = [true_path_length(run.room, s.seed, s.start_pose.position_m[:2], r.pose.position_m[:2])
             for s, r in zip(scenes, results)]
    driven = [p for p in paths if math.isfinite(p)]
    return {"n": len(results), "success": 100.0 * sum(r.success for r in results) / max(1, len(results)),
            "before": 100.0 * sum(r.before.surface_coverage for r in results) / max(1, len(results)),
            "after": 100.0 * sum(r.after.surface_coverage for r in results) / max(1, len(results)),
            "travel": sum(travel) / max(1, len(travel)), "path": sum(driven) / max(1, len(driven)),
            "no_path": len(paths) - len(driven)}


def main(argv: List[str]) -> int:
    if len(argv) != 1 or not os.path.isdir(argv[0]):
        print("usage: family_table.py OUT (the folder scripts/experiments/family_benchmark.sh wrote)", file=sys.stderr)
        return 2
    out = argv[0]
    lines = ["| family | method | scenes | success (%) | coverage before -> after (%) | path (m) | straight (m) "
             "| no path |", "|---|---|---:|---:|---:|---:|---:|---:|"]
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
                         f"{row['after']:.1f} | {row['path']:.2f} | {row['travel']:.2f} | {row['no_path']} |")
    if not floors[1]:
        print(f"family_table: no run.json under {out}", file=sys.stderr)
        return 2
    for label, rows in totals.items():
        n = sum(r["n"] for r in rows)
        if not n:
            continue
        mean = {key: sum(r[key] * r["n"] for r in rows) / n for key in ("success", "before", "after", "travel")}
        driven = sum(r["n"] - r["no_path"] for r in rows)
        mean["path"] = sum(r["path"] * (r["n"] - r["no_path"]) for r in rows) / max(1, driven)
        lines.append(f"| all | {label} | {n} | {mean['success']:.1f} | {mean['before']:.1f} -> {mean['after']:.1f} | "
                     f"{mean['path']:.2f} | {mean['travel']:.2f} | {sum(r['no_path'] for r in rows)} |")
    print("\n".join(lines))
    print(f"\nwrong floor on the start view (> 2 deg or > 5 cm, graph's plane vs truth): {floors[0]} of {floors[1]}; "
          f"graph failures: {failures}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
