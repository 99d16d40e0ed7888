#!/usr/bin/env python3
"""The best view a wheeled robot could reach in a benchmark scene: is success possible at all?

For each scene, base positions on a 0.25 m grid within 5 m of the person; a position counts when the
robot's shortest free path to it on the scene's true floor map (leapnbv_evaluation.truth_paths:
obstacles and the person grown by 0.3 m) is at most 6 m (the planner's max_path_length). The camera
stays at the start camera's mounting height and looks at the body's centre (a pan-tilt head). Prints
the start view's surface coverage, the best reachable view's, the best of all positions (reachable or
not), and whether success (+10 points or >= 90 %) is possible for the robot.

    scripts/env.sh python scripts/experiments/reachable_ceiling.py corridor 3 11 25
Exit 0; 2 on a bad room.
"""

from __future__ import annotations

import argparse
import sys

import numpy as np


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("room")
    parser.add_argument("seeds", type=int, nargs="+")
    parser.add_argument("--step", type=float, default=0.25, help="grid step, metres")
    parser.add_argument("--max-path", type=float, default=6.0)
    args = parser.parse_args(argv)

    from leapnbv_evaluation.benchmark_set import ROOMS, benchmark_scene
    from leapnbv_evaluation.episode import view_metrics
    from leapnbv_evaluation.metrics import is_success
    from leapnbv_evaluation.truth_paths import true_path_lengths
    from leapnbv_perception.smplx_layer import SMPLXModel
    from leapnbv_sim.poses import look_at_pose
    from leapnbv_stand_ins.files import ensure_stand_in_body_model

    if args.room not in ROOMS:
        print(f"reachable_ceiling: room must be one of {ROOMS}", file=sys.stderr)
        return 2
    body = SMPLXModel.load(ensure_stand_in_body_model("small"))
    print("| seed | before (%) | best reachable (%) | its path (m) | its distance to the person (m) | start's "
          "distance (m) | best anywhere (%) | success possible |")
    print("|---:|---:|---:|---:|---:|---:|---:|---|")
    for seed in args.seeds:
        scene = benchmark_scene(seed, body, args.room)
        start = scene.start_camera
        height = float(start.position[2])
        centre = scene.body_vertices_world.mean(axis=0)
        before = view_metrics(scene, scene.render(start)).surface_coverage
        offsets = np.arange(-5.0, 5.0 + 1e-9, args.step)
        grid = np.array([[centre[0] + dx, centre[1] + dy] for dx in offsets for dy in offsets
                         if 1.0 <= np.hypot(dx, dy) <= 5.0])
        paths = true_path_lengths(scene, start.position[:2], grid)
        best_reach, best_path, best_any, best_xy = 0.0, float("nan"), 0.0, centre[:2]
        for xy, path in zip(grid, paths):
            coverage = view_metrics(scene, scene.render(look_at_pose(np.array([xy[0], xy[1], height]), centre))) \
                .surface_coverage
            best_any = max(best_any, coverage)
            if path <= args.max_path and coverage > best_reach:
                best_reach, best_path, best_xy = coverage, float(path), xy
        possible = is_success(before, best_reach)
        distance = float(np.hypot(*(best_xy - centre[:2])))
        start_distance = float(np.hypot(*(start.position[:2] - centre[:2])))
        print(f"| {seed} | {100 * before:.1f} | {100 * best_reach:.1f} | {best_path:.2f} | {distance:.2f} | "
              f"{start_distance:.2f} | {100 * best_any:.1f} | {'yes' if possible else 'no'} |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
