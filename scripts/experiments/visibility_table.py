"""S_v over the observed points against S_v over the body mesh (nbv_node ``visibility_points``), per run.

Success, coverage and how much of the body the chosen views cut off at the image border.

Each argument is LABEL=OUT, OUT an evaluation's output folder (``scripts/experiments/evaluate.sh --out OUT``, e.g.
with ``--set nbv_node.visibility_points=observed``). Per run: leap_nbv's success (%) and mean surface coverage
before -> after (%), then for leap_nbv's and the oracle's picks the mean *border cut*: the share of the body's
self-visible vertices from the view the robot reached (what the body shows by itself, image bounds ignored:
``leapnbv_sim.visibility.self_visible_vertex_mask``, the denominator of the coverage) that fall outside the image or
behind the camera, and the picks that cut more than 10 % of it. The view is re-made from the run's candidates and
the evaluation's robot (``leapnbv_evaluation.episode.candidate_world_pose``); its camera centre is checked against
the pose the run logged.

Usage: scripts/env.sh python scripts/experiments/visibility_table.py LABEL=OUT [LABEL=OUT ...]
Exit 0; 2 for a wrong argument or a folder without run.json (one line on stderr).
"""
from __future__ import annotations

import os
import sys
from typing import Dict, List, Optional, Tuple

import numpy as np

from leapnbv_evaluation.benchmark_set import benchmark_scene
from leapnbv_evaluation.episode import candidate_world_pose
from leapnbv_evaluation.results import EvaluationRun, SceneResult
from leapnbv_perception.smplx_layer import SMPLXModel
from leapnbv_sim.scene import Scene
from leapnbv_sim.visibility import project_points, self_visible_vertex_mask
from leapnbv_stand_ins.files import ensure_stand_in_body_model

#: A wrong argument (2 is a usage error in every table of leapnbv_common.exit_codes).
USAGE = 2
#: A pick cuts "much" of the body when more than this share of its self-visible vertices is off the image.
MUCH = 0.10
#: The run's logged camera centre (6 decimals) and the re-made one must agree to this (m).
POSE_TOLERANCE_M = 1e-4


def border_cut(scene: Scene, result: SceneResult, method: str) -> Optional[float]:
    """The share of the self-visible body the view of ``method``'s pick leaves outside the image (None: no pick)."""
    move = result.per_method.get(method)
    if move is None or result.candidates is None or move.chosen_index < 0:
        return None
    pose = candidate_world_pose(scene.start_camera, result.candidates, move.chosen_index)
    if np.max(np.abs(pose.position - np.asarray(move.pose.position_m))) > POSE_TOLERANCE_M:
        raise ValueError(f"seed {result.seed}: the re-made {method} camera {pose.position} is not the logged "
                         f"{move.pose.position_m}")
    vertices = pose.world_to_camera(scene.body_vertices_world)
    self_visible = self_visible_vertex_mask(vertices, scene.body_faces, scene.K)
    count = int(np.count_nonzero(self_visible))
    if count == 0:
        return 1.0
    in_front = vertices[:, 2] > 1e-6
    uv = project_points(np.where(in_front[:, None], vertices, 1.0), scene.K)
    columns, rows = np.rint(uv[:, 0]), np.rint(uv[:, 1])  # the pixel test of visible_vertex_mask
    width, height = scene.config.width, scene.config.height
    inside = in_front & (columns >= 0) & (columns < width) & (rows >= 0) & (rows < height)
    return 1.0 - float(np.count_nonzero(inside & self_visible)) / float(count)


def summary(run: EvaluationRun, body: SMPLXModel) -> Dict[str, object]:
    """One run's row: success, coverage before -> after, and the border cut of leap_nbv's and the oracle's picks."""
    scenes = run.scenes
    leap = [scene.per_method["leap_nbv"] for scene in scenes]
    cuts: Dict[str, List[float]] = {"leap_nbv": [], "oracle": []}
    for result in scenes:
        scene = benchmark_scene(result.seed, body, run.room)
        for method in cuts:
            cut = border_cut(scene, result, method)
            if cut is not None:
                cuts[method].append(cut)
    return {
        "room": run.room, "scenes": len(scenes),
        "success": 100.0 * np.mean([move.success for move in leap]),
        "before": 100.0 * np.mean([move.before.surface_coverage for move in leap]),
        "after": 100.0 * np.mean([move.after.surface_coverage for move in leap]),
        "cut": {method: (100.0 * float(np.mean(values)) if values else float("nan"),
                         int(np.count_nonzero(np.asarray(values) > MUCH)), len(values))
                for method, values in cuts.items()},
    }


def main(argv: List[str]) -> int:
    """Print the table of the LABEL=OUT runs; the exit code."""
    if not argv:
        print(__doc__.strip().splitlines()[-2], file=sys.stderr)
        return USAGE
    runs: List[Tuple[str, EvaluationRun]] = []
    for argument in argv:
        label, _, folder = argument.rpartition("=")
        path = os.path.join(folder, "run.json")
        if not label or not os.path.isfile(path):
            print(f"visibility_table: {argument!r}: give LABEL=OUT with OUT/run.json", file=sys.stderr)
            return USAGE
        runs.append((label, EvaluationRun.read(path)))
    body = SMPLXModel.load(ensure_stand_in_body_model("small"))
    print("| run | room | scenes | success (%) | coverage before -> after (%) | border cut of the picks, mean (%) |"
          " picks cutting > 10 % | oracle's border cut (%) |")
    print("|---|---|---:|---:|---|---:|---:|---:|")
    for label, run in runs:
        row = summary(run, body)
        cut = row["cut"]
        leap_mean, leap_much, leap_count = cut["leap_nbv"]  # type: ignore[index]
        oracle_mean = cut["oracle"][0]  # type: ignore[index]
        print(f"| {label} | {row['room']} | {row['scenes']} | {row['success']:.1f} | {row['before']:.1f} -> "
              f"{row['after']:.1f} | {leap_mean:.1f} | {leap_much} of {leap_count} | {oracle_mean:.1f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
