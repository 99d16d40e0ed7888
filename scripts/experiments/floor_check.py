"""How often the start view's floor is wrong (> 2 deg or > 5 cm from the truth), before and after the fusion.

Runs the ground core (no ROS) on the start view of benchmark scenes, per family of camera
mounting: the committed scenes (camera 1.0-1.4 m), the camera at 0.6 m and at 1.8 m, and 3x depth
noise. Three ways of fitting each view:

* ``before``: as the ground node fitted a scene's first frame until now: no person left out (no
  previous mask yet), the simulator-set priors (0.8-1.6 m, tilt from -y), the camera pose's floor
  only when RANSAC finds none;
* ``before_excluded``: ``before`` with the upper part of the person's detection box left out (detection_top_share);
* ``ransac_after``: the upper part of the person's detection box left out and the priors from the robot's
  mounting height (+- ``--height-tolerance``), no camera pose;
* ``fused``: the same, checked against the camera pose's floor (``fuse_floor``): what the node
  publishes now.

Usage: scripts/env.sh python scripts/experiments/floor_check.py [--scenes 50] [--families committed,cam06,cam18,noise3]
Prints one line per family and way: wrong / invalid counts. Exit 0; 2 on a bad argument.
"""
from __future__ import annotations

import argparse
import dataclasses
import sys
from typing import Dict, List, Tuple

import numpy as np

from leapnbv_evaluation.benchmark_set import benchmark_config, benchmark_seeds
from leapnbv_geometry.ground import (
    box_exclusion_mask,
    expected_up,
    fit_ground_plane,
    floor_plane_from_camera_pose,
    fuse_floor,
    ground_points_from_depth,
)
from leapnbv_geometry.params import GroundParams
from leapnbv_perception.smplx_layer import SMPLXModel
from leapnbv_sim.generation import generate_scene
from leapnbv_sim.render import PERSON_ID
from leapnbv_sim.scene import SceneError
from leapnbv_stand_ins.files import ensure_stand_in_body_model

FAMILIES = {
    # name: (camera height range, depth-noise factor)
    "committed": ((1.0, 1.4), 1.0),
    "cam06": ((0.6, 0.6), 1.0),
    "cam18": ((1.8, 1.8), 1.0),
    "noise3": ((1.0, 1.4), 3.0),
}
WRONG_DEG, WRONG_M = 2.0, 0.05


def fit(points, params: GroundParams, height_range: Tuple[float, float], up) -> object:
    return fit_ground_plane(points, max_tilt_deg=params.max_tilt_deg, inlier_threshold=params.inlier_threshold,
                            iterations=params.iterations, min_inliers=params.min_inliers,
                            min_inlier_ratio=params.min_inlier_ratio, seed=params.seed,
                            max_points=params.max_points, depth_noise_coeff=params.depth_noise_coeff, up=up,
                            camera_height_range=height_range)


def error(normal, offset, truth_normal, truth_offset) -> Tuple[float, float]:
    cosine = float(np.clip(np.asarray(normal) @ truth_normal, -1.0, 1.0))
    return float(np.degrees(np.arccos(cosine))), abs(float(offset) - truth_offset)


def main(argv: List[str]) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", type=int, default=50)
    parser.add_argument("--families", default=",".join(FAMILIES))
    parser.add_argument("--height-tolerance", type=float, default=0.3,
                        help="metres: the mounting-height prior is the mounting height +- this")
    args = parser.parse_args(argv)
    families = [f for f in args.families.split(",") if f]
    unknown = [f for f in families if f not in FAMILIES]
    if unknown or args.scenes < 1:
        print(f"floor_check: unknown family {unknown} (known: {list(FAMILIES)}) or --scenes < 1", file=sys.stderr)
        return 2
    body = SMPLXModel.load(ensure_stand_in_body_model("small"))
    params = GroundParams()
    seeds = benchmark_seeds(args.scenes)
    for family in families:
        heights, noise_factor = FAMILIES[family]
        counts: Dict[str, List[int]] = {way: [0, 0] for way in ("before", "before_excluded", "ransac_after",
                                                                "fused")}
        decisions: Dict[str, int] = {}
        done = 0
        for seed in seeds:
            config = benchmark_config(seed)
            noise = dataclasses.replace(config.noise, sigma_quadratic_per_m=config.noise.sigma_quadratic_per_m
                                        * noise_factor, sigma_constant_m=config.noise.sigma_constant_m * noise_factor)
            config = dataclasses.replace(config, camera_height_range=heights, noise=noise)
            try:
                scene = generate_scene(config, body)
            except SceneError:
                continue
            done += 1
            frame = scene.render(scene.start_camera, frame_index=0)
            camera = scene.start_camera
            truth_normal = camera.rotation.T @ np.array([0.0, 0.0, 1.0])
            truth_offset = float(camera.position[2])
            pose_floor = floor_plane_from_camera_pose(camera.rotation, camera.position)
            depth = frame.depth_m
            rows, cols = np.nonzero(frame.object_id == PERSON_ID)
            boxes = np.array([[cols.min(), rows.min(), cols.max() + 1, rows.max() + 1]]) if rows.size else \
                np.zeros((0, 4))
            plain = ground_points_from_depth(depth, frame.K, stride=params.stride)
            excluded = ground_points_from_depth(depth, frame.K, exclude_mask=box_exclusion_mask(
                depth.shape, boxes, params.detection_grow_px, params.detection_top_share), stride=params.stride)
            # before: sim-set priors, no exclusion, pose only when RANSAC finds none
            result = fit(plain, params, (params.min_camera_height, params.max_camera_height), (0.0, -1.0, 0.0))
            normal, offset = (result.normal, result.offset) if result.valid else pose_floor
            angle, height = error(normal, offset, truth_normal, truth_offset)
            counts["before"][0] += int(angle > WRONG_DEG or height > WRONG_M)
            # the same with the person box left out (the first-frame exclusion alone)
            result = fit(excluded, params, (params.min_camera_height, params.max_camera_height), (0.0, -1.0, 0.0))
            normal, offset = (result.normal, result.offset) if result.valid else pose_floor
            angle, height = error(normal, offset, truth_normal, truth_offset)
            counts["before_excluded"][0] += int(angle > WRONG_DEG or height > WRONG_M)
            # after: the robot's mounting priors (height of this family's robot), the person box left out
            mount = float(np.mean(heights))
            prior = (max(0.0, mount - args.height_tolerance - 0.5 * (heights[1] - heights[0])),
                     mount + args.height_tolerance + 0.5 * (heights[1] - heights[0]))
            result = fit(excluded, params, prior, expected_up(params.camera_pitch_deg))
            if result.valid:
                angle, height = error(result.normal, result.offset, truth_normal, truth_offset)
                counts["ransac_after"][0] += int(angle > WRONG_DEG or height > WRONG_M)
            else:
                counts["ransac_after"][1] += 1
            floor = fuse_floor(result, pose_floor, params.pose_max_angle_deg, params.pose_max_height_m)
            decisions[floor.decision] = decisions.get(floor.decision, 0) + 1
            if floor.valid:
                angle, height = error(floor.normal, floor.offset, truth_normal, truth_offset)
                counts["fused"][0] += int(angle > WRONG_DEG or height > WRONG_M)
            else:
                counts["fused"][1] += 1
        for way, (wrong, invalid) in counts.items():
            print(f"{family:10s} {way:13s} wrong {wrong:3d} / {done}  invalid {invalid:3d}")
        print(f"{family:10s} fused decisions: {dict(sorted(decisions.items()))}")
        sys.stdout.flush()
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
