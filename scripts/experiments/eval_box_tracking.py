#!/usr/bin/env python3
"""How well a person box carried from an earlier frame by the mesh's image motion
(leapnbv_perception.box_tracking) matches the box of the frame it is carried into, on the simulator's
benchmark scenes: the accuracy cost of running the detector only every N frames.

For each scene the camera moves from the start view 0.6 m sideways (and 0.2 m toward the person)
over 1 s at 30 FPS (a wheeled base at 0.6 m/s), keeping its heading (``--motion sideways``: the
person crosses the image) or turning to keep the person centred (``--motion turning``). For each
frame t and gap N, the visible-person box of frame t - N is carried into frame t with the body
mesh of frame t - N and both camera poses, and compared (IoU) with frame t's own visible-person
box (what a detector run on every frame gives, here without detector error). Two baselines: the
box of frame t - N kept unchanged, and carried without the camera poses.

What it does not measure: the person's own motion (the simulated person stands still), and the
HMR's mesh error (the simulator's mesh is used; the HMR's estimate is what the node carries).

    scripts/env.sh python scripts/experiments/eval_box_tracking.py [--scenes 10] [--gaps 1 2 3 5 10]
    scripts/env.sh python scripts/experiments/eval_box_tracking.py --bag bags/sample_a [--gaps 1 2 3]

``--bag``: the same on a recorded bag's frames, in order: each frame's box and mesh from its ground
truth (the body parameters and translation in the camera frame, through the body model the bag
names; the small stand-in for the sample bags) and its colour camera_info. A bag without camera
poses gives the carry without them only (the camera's motion between the frames is not known).
"""

from __future__ import annotations

import argparse
import sys
from typing import Dict, List

import numpy as np


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scenes", type=int, default=10)
    parser.add_argument("--gaps", type=int, nargs="+", default=[1, 2, 3, 5, 10])
    parser.add_argument("--fps", type=float, default=30.0)
    parser.add_argument("--min-confidence", type=float, default=0.8)
    parser.add_argument("--motion", choices=["turning", "sideways"], default="sideways",
                        help="turning: the camera keeps the person centred; sideways: its heading stays")
    parser.add_argument("--bag", default=None, help="measure on this bag's frames instead of the benchmark scenes")
    args = parser.parse_args(argv)
    if args.bag:
        return bag_main(args)

    from leapnbv_evaluation.benchmark_set import benchmark_scene, benchmark_seeds
    from leapnbv_perception.box_tracking import camera_motion, carry_box
    from leapnbv_perception.smplx_layer import SMPLXModel
    from leapnbv_perception.target_selection import box_iou
    from leapnbv_sim.poses import CameraPose, look_at_pose
    from leapnbv_stand_ins.files import ensure_stand_in_body_model

    body = SMPLXModel.load(ensure_stand_in_body_model("small"))
    frames_per_path = int(round(args.fps))  # 1 s
    results: Dict[str, Dict[int, List[float]]] = {"carried": {}, "without poses": {}, "kept": {}}
    untrusted: Dict[int, int] = {}
    for seed in benchmark_seeds(args.scenes, body_model=body):
        scene = benchmark_scene(seed, body)
        start, centre = scene.start_camera, scene.body_centre_world
        towards = centre[:2] - start.position[:2]
        towards /= max(np.linalg.norm(towards), 1e-9)
        side = np.array([-towards[1], towards[0]])
        frames = []
        for k in range(frames_per_path + 1):
            f = k / frames_per_path
            position = start.position + np.append(0.6 * f * side + 0.2 * f * towards, 0.0)
            pose = look_at_pose(position, centre) if args.motion == "turning" else \
                CameraPose(start.rotation.copy(), position)
            frames.append(scene.render(pose, frame_index=k))
        for t, frame in enumerate(frames):
            truth_b = frame.ground_truth.person_box_xyxy
            if truth_b is None:
                continue
            size = (frame.rgb.shape[1], frame.rgb.shape[0])
            for gap in args.gaps:
                if t - gap < 0 or frames[t - gap].ground_truth.person_box_xyxy is None:
                    continue
                earlier = frames[t - gap]
                box_a = np.asarray(earlier.ground_truth.person_box_xyxy, np.float64)
                poses = [(f.camera_pose.rotation, f.camera_pose.position) for f in (earlier, frame)]
                truth = np.asarray(truth_b, np.float64)[None]
                for name, motion in (("carried", camera_motion(*poses)), ("without poses", camera_motion(None, None))):
                    carried = carry_box(box_a, earlier.ground_truth.vertices_camera, earlier.K, frame.K, size, motion)
                    iou = 0.0 if carried is None else float(box_iou(carried.box, truth)[0])
                    results[name].setdefault(gap, []).append(iou)
                    if name == "carried" and (carried is None or carried.confidence < args.min_confidence):
                        untrusted[gap] = untrusted.get(gap, 0) + 1
                results["kept"].setdefault(gap, []).append(float(box_iou(box_a, truth)[0]))
    print(f"box carried over N frames vs the frame's own visible-person box: {args.scenes} benchmark scenes, "
          f"camera 0.6 m/s, {args.motion}, {args.fps:.0f} FPS (IoU p5 / p50 / mean; share >= 0.7)")
    for gap in args.gaps:
        row = []
        for name in ("carried", "without poses", "kept"):
            values = np.asarray(results[name].get(gap, [np.nan]))
            row.append(f"{name} {np.percentile(values, 5):.2f} / {np.median(values):.2f} / {values.mean():.2f}; "
                       f"{(values >= 0.7).mean():.0%}")
        n = len(results["carried"].get(gap, []))
        print(f"  N = {gap:2d} ({n} boxes): " + " | ".join(row) +
              f" | confidence < {args.min_confidence}: {untrusted.get(gap, 0)} of {n}")
    return 0


def bag_frames(path: str):
    """(box xyxy, vertices in the camera frame, K, (width, height)) of each frame of the bag with a person."""
    from leapnbv_bags.bag_io import read_bag
    from leapnbv_perception.smplx_layer import SMPLXModel, SMPLXParams
    from leapnbv_stand_ins.files import ensure_stand_in_body_model

    infos, truths = {}, {}
    for topic, _, _, msg in read_bag(path):
        stamp = int(msg.header.stamp.sec) * 1_000_000_000 + int(msg.header.stamp.nanosec)
        if topic.endswith("color/camera_info"):
            infos[stamp] = msg
        elif topic.endswith("ground_truth"):
            truths[stamp] = msg
    models = {}
    frames = []
    for stamp in sorted(truths):
        truth, info = truths[stamp], infos.get(stamp)
        box = truth.person_box
        if info is None or not box.x_max > box.x_min:
            continue
        name = truth.body_model_id or "small"
        if name not in models:  # the stand-ins by their ids; another id is a file path
            models[name] = SMPLXModel.load(ensure_stand_in_body_model("small") if "small" in name else name)
        params = SMPLXParams.from_axis_angle(truth.root_pose, truth.body_pose, truth.left_hand_pose,
                                             truth.right_hand_pose, truth.jaw_pose, truth.betas, truth.expression)
        vertices = models[name].forward(params, add_hand_mean=True).vertices + np.asarray(truth.translation)
        frames.append((np.array([box.x_min, box.y_min, box.x_max, box.y_max], np.float64), vertices,
                       np.asarray(info.k, np.float64).reshape(3, 3), (int(info.width), int(info.height))))
    return frames


def bag_main(args) -> int:
    from leapnbv_perception.box_tracking import camera_motion, carry_box
    from leapnbv_perception.target_selection import box_iou

    frames = bag_frames(args.bag)
    print(f"box carried over N frames vs the frame's own ground-truth box: {args.bag}, {len(frames)} frames "
          "with a person, no camera poses (IoU p5 / p50 / mean; share >= 0.7)")
    for gap in args.gaps:
        carried_iou, kept_iou = [], []
        for t in range(gap, len(frames)):
            box_a, vertices_a, k_a, _ = frames[t - gap]
            box_t, _, k_t, size = frames[t]
            carried = carry_box(box_a, vertices_a, k_a, k_t, size, camera_motion(None, None))
            carried_iou.append(0.0 if carried is None else float(box_iou(carried.box, box_t[None])[0]))
            kept_iou.append(float(box_iou(box_a, box_t[None])[0]))
        row = []
        for name, values in (("carried", carried_iou), ("kept", kept_iou)):
            values = np.asarray(values or [np.nan])
            row.append(f"{name} {np.percentile(values, 5):.2f} / {np.median(values):.2f} / {values.mean():.2f}; "
                       f"{(values >= 0.7).mean():.0%}")
        print(f"  N = {gap:2d} ({len(carried_iou)} boxes): " + " | ".join(row))
    return 0


if __name__ == "__main__":
    sys.exit(main())
