"""The error budget's table and plot (scripts/experiments/error_budget.sh).

Reads OUT/<corruption>/<level>/registration_<off|on>/run.json and prints, for leap_nbv, one row per corruption
and level: success (%) and surface coverage after the move (%) with the mesh registration off (the graph's
default) and on, and the graph failures; then, per corruption, the first level at which success drops below
95 % with each. Writes OUT/error_budget.png (success and coverage against each corruption's level).
Usage: scripts/env.sh python scripts/experiments/error_budget_table.py OUT
Exit 0; 2 when OUT holds no run.
"""
from __future__ import annotations

import math
import os
import sys
from typing import Dict, List, Optional, Tuple

from leapnbv_evaluation.results import EvaluationRun
from leapnbv_evaluation.task_report import aggregate_task_results

METHOD = "leap_nbv"
SUCCESS_FLOOR_PCT = 95.0
REGISTRATIONS = ("off", "on")
#: The order and the wording of the corruptions (error_budget.sh's names).
CORRUPTIONS = {
    "none": "none (ground truth)",
    "mesh_shift": "mesh 2-D placement (share of the box)",
    "mesh_depth": "mesh depth / scale (share of the distance)",
    "mesh_pa": "mesh pose and shape (PA-MPVPE, mm)",
    "box_jitter": "box jitter (std of each side, share of the box)",
    "box_grow": "box too large (grown by, share of the box)",
    "box_truncate": "box truncated (one side cut by, share of the box)",
    "second_person": "a second person in view (family)",
}

Cell = Tuple[float, float, int, int]  # success %, coverage after %, graph failures, scenes


def _cell(path: str) -> Optional[Cell]:
    if not os.path.exists(path):
        return None
    run = EvaluationRun.read(path)
    row = aggregate_task_results(run)["per_method"].get(METHOD)
    if row is None:
        return None
    failures = sum(1 for scene in run.scenes if scene.graph_failure)
    return float(row["success_rate_pct"]), float(row["coverage_after_pct"]), failures, int(row["scenes"])


def _level_key(level: str) -> Tuple[int, float, str]:
    try:
        return 0, float(level), level
    except ValueError:
        return 1, 0.0, level


def collect(out_dir: str) -> Dict[str, Dict[str, Dict[str, Cell]]]:
    """Every run found: corruption -> level -> registration -> cell."""
    found: Dict[str, Dict[str, Dict[str, Cell]]] = {}
    for corruption in CORRUPTIONS:
        folder = os.path.join(out_dir, corruption)
        if not os.path.isdir(folder):
            continue
        for level in sorted(os.listdir(folder), key=_level_key):
            for registration in REGISTRATIONS:
                cell = _cell(os.path.join(folder, level, f"registration_{registration}", "run.json"))
                if cell is not None:
                    found.setdefault(corruption, {}).setdefault(level, {})[registration] = cell
    return found


def _fmt(value: float) -> str:
    return "n/a" if not math.isfinite(value) else f"{value:.1f}"


def _pair(cells: Dict[str, Cell], index: int) -> str:
    return " / ".join(_fmt(cells[r][index]) if r in cells else "-" for r in REGISTRATIONS)


def table(found: Dict[str, Dict[str, Dict[str, Cell]]]) -> List[str]:
    """The markdown lines: one row per corruption and level, then the first level below the floor."""
    lines = ["| corruption | level | scenes | success (%) reg. off / on | coverage after (%) reg. off / on | "
             "graph failures off / on |", "|---|---:|---:|---:|---:|---:|"]
    for corruption, levels in found.items():
        for level, cells in levels.items():
            scenes = max(cell[3] for cell in cells.values())
            failures = " / ".join(str(cells[r][2]) if r in cells else "-" for r in REGISTRATIONS)
            lines.append(f"| {CORRUPTIONS[corruption]} | {level} | {scenes} | {_pair(cells, 0)} | "
                         f"{_pair(cells, 1)} | {failures} |")
    lines += ["", f"| corruption | first level with success < {SUCCESS_FLOOR_PCT:g} %, reg. off | reg. on |",
              "|---|---:|---:|"]
    for corruption, levels in found.items():
        if corruption in ("none", "second_person"):
            continue
        firsts = []
        for registration in REGISTRATIONS:
            below = [level for level, cells in levels.items()
                     if registration in cells and cells[registration][0] < SUCCESS_FLOOR_PCT]
            firsts.append(below[0] if below else f"none up to {list(levels)[-1]}")
        lines.append(f"| {CORRUPTIONS[corruption]} | {firsts[0]} | {firsts[1]} |")
    return lines


def plot(found: Dict[str, Dict[str, Dict[str, Cell]]], path: str) -> None:
    """Success and coverage against the level, one column per graded corruption, written to ``path``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    graded = [c for c in found if c not in ("none", "second_person")]
    if not graded:
        return
    baseline = found.get("none", {}).get("0", {})
    fig, axes = plt.subplots(2, len(graded), figsize=(2.6 * len(graded), 5.0), squeeze=False)
    for column, corruption in enumerate(graded):
        levels = found[corruption]
        for row, (index, label) in enumerate(((0, "success (%)"), (1, "coverage after (%)"))):
            axis = axes[row][column]
            for registration, style in zip(REGISTRATIONS, ("o-", "s--")):
                points = [(0.0, baseline[registration][index])] if registration in baseline else []
                points += [(float(level), cells[registration][index]) for level, cells in levels.items()
                           if registration in cells]
                if points:
                    axis.plot(*zip(*points), style, label=f"registration {registration}")
            if row == 0:
                axis.axhline(SUCCESS_FLOOR_PCT, color="grey", linewidth=0.8)
                axis.set_title(corruption.replace("_", " "), fontsize=9)
            else:
                axis.set_xlabel("level", fontsize=8)
            if column == 0:
                axis.set_ylabel(label)
            axis.tick_params(labelsize=7)
    axes[0][0].legend(fontsize=7)
    fig.tight_layout()
    tmp = path + ".tmp.png"
    fig.savefig(tmp, dpi=90)
    os.replace(tmp, path)  # a half-written plot never replaces a good one


def main(argv: List[str]) -> int:
    """Print the table and write the plot; returns the exit code."""
    if len(argv) != 1:
        print("usage: error_budget_table.py OUT", file=sys.stderr)
        return 2
    found = collect(argv[0])
    if not found:
        print(f"error_budget_table: no run found under '{argv[0]}'", file=sys.stderr)
        return 2
    print("\n".join(table(found)))
    plot(found, os.path.join(argv[0], "error_budget.png"))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
