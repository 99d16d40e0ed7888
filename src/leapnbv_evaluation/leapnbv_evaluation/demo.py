"""The demo: run the five-node graph on a sample bag and leave a report a person can read.

    python -m leapnbv_evaluation.demo [--bag bags/sample_a] [--out out/demo]
                                   [--perception onnxruntime --detector-model Y.onnx --hmr-model S.onnx
                                    --body-model SMPLX_NEUTRAL.npz]

Ground-truth perception (the simulator's boxes and body parameters, recorded in the bag) is
used unless real models are given. The report has, per frame, the chosen view and its scores,
the colour frame with the person box and mask, and a top-down map of the candidate ring.
"""
from __future__ import annotations

import argparse
import os
import sys
import time
from typing import Any, Dict, List, Mapping, Optional

import numpy as np
from sensor_msgs.msg import Image

from leapnbv_bags.bag_io import read_bag
from leapnbv_bringup.graph_runner import add_graph_arguments
from leapnbv_bringup.regression import overrides_for_bag_run, run_graph_on_bag
from leapnbv_common.conversions import (
    ground_plane_to_arrays,
    image_to_numpy,
    image_to_rgb,
    pointcloud2_to_xyz,
    stamp_to_ns,
    view_candidates_to_arrays,
)
from leapnbv_common.topics import (
    CAMERA_TOPICS,
    DETECTIONS,
    GROUND_PLANE,
    HUMAN_MESH,
    MARKERS,
    PERSON_MASK,
    TARGET_GEOMETRY,
    VIEW_CANDIDATES,
    short_topic,
)
from leapnbv_evaluation.demo_report import DemoFrame, chosen_view_scores, write_demo_report
from leapnbv_evaluation.metrics import latency_summary

#: The stages whose compute times the summary lists.
STAGE_OUTPUTS = (DETECTIONS, HUMAN_MESH, TARGET_GEOMETRY, GROUND_PLANE, VIEW_CANDIDATES)


def _frames_for_report(run: Mapping[str, Any], bag: str) -> List[DemoFrame]:
    """Join the bag's colour frames with the graph's outputs of the same stamp (``run``: run_graph_on_bag's)."""
    outputs: Dict[str, Dict[int, Any]] = {}  # rclpy messages
    received: Dict[int, int] = {}
    for topic, when, msg in run["decoded"]:
        name = short_topic(topic)
        if name == MARKERS:
            continue
        stamp = stamp_to_ns(msg.header.stamp)
        outputs.setdefault(name, {})[stamp] = msg
        if name == VIEW_CANDIDATES:
            received[stamp] = when
    published = run["replayer"].published_at
    rgb_by_stamp: Dict[int, Any] = {}
    colour_msg: Any  # the bag's own message class (rosbags), read by field
    for _, _, _, colour_msg in read_bag(bag, topics=[CAMERA_TOPICS["image"]]):
        rgb_by_stamp[stamp_to_ns(colour_msg.header.stamp)] = colour_msg
    frames = []
    for index, stamp in enumerate(run["input_stamps"]):
        colour = rgb_by_stamp[stamp]
        image = Image(height=colour.height, width=colour.width, encoding=colour.encoding,
                      is_bigendian=colour.is_bigendian, step=colour.step)
        image.data = bytes(colour.data)
        detections = outputs.get(DETECTIONS, {}).get(stamp)
        mask_msg = outputs.get(PERSON_MASK, {}).get(stamp)
        target = outputs.get(TARGET_GEOMETRY, {}).get(stamp)
        ground = outputs.get(GROUND_PLANE, {}).get(stamp)
        candidates = outputs.get(VIEW_CANDIDATES, {}).get(stamp)
        box, label = None, "no person"
        if detections is not None and detections.detections:
            d = detections.detections[0]
            box, label = [d.x_min, d.y_min, d.x_max, d.y_max], f"person {d.score:.2f}"
        latency = (received[stamp] - published[stamp]) * 1e-6 if stamp in received and stamp in published else None
        frames.append(DemoFrame(
            index=index, stamp_ns=stamp, rgb=image_to_rgb(image), box=box, label=label,
            mask=image_to_numpy(mask_msg) > 0 if mask_msg is not None else None,
            candidates=view_candidates_to_arrays(candidates) if candidates is not None else None,
            ground=ground_plane_to_arrays(ground) if ground is not None else None,
            target_points=pointcloud2_to_xyz(target.target_points) if target is not None else np.zeros((0, 3)),
            background_points=(pointcloud2_to_xyz(target.background_points) if target is not None
                               else np.zeros((0, 3))),
            latency_ms=latency,
        ))
    return frames


def stage_latency_summary(run: Mapping[str, Any]) -> Dict[str, str]:
    """p50 / p95 of each stage's compute time and of the end-to-end latency, as report rows."""
    per_stage: Dict[str, List[float]] = {}
    for topic, _, msg in run["decoded"]:
        name = short_topic(topic)
        if name in STAGE_OUTPUTS:
            per_stage.setdefault(name, []).append(float(msg.compute_time_ms))
    rows = {}
    for name, samples in per_stage.items():
        s = latency_summary(samples)
        rows[f"compute {name} (ms)"] = f"p50 {s['p50']:.1f}, p95 {s['p95']:.1f} (n={s['n']})"
    return rows


def main(argv: Optional[List[str]] = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--bag", default=os.path.join("bags", "sample_a"), help="input bag")
    parser.add_argument("--out", default=os.path.join("out", "demo"), help="report folder")
    add_graph_arguments(parser)
    args = parser.parse_args(argv)

    started = time.monotonic()
    try:
        perception, overrides = overrides_for_bag_run(args)
    except ValueError as exc:
        print(f"[demo] {exc}", file=sys.stderr)
        return 2
    print(f"[demo] graph on {args.bag} with {perception} perception ...", flush=True)
    run = run_graph_on_bag(args.bag, os.path.join(args.out, "graph_run"), overrides, args.params)
    frames = _frames_for_report(run, args.bag)
    latencies = [f.latency_ms for f in frames if f.latency_ms is not None]
    goals = sum(1 for f in frames if f.has_goal)
    summary = {"bag": args.bag, "perception": perception, "frames": len(frames),
               "frames with a goal": goals, "frames without an answer": len(run["timed_out"])}
    if latencies:
        s = latency_summary(latencies)
        summary["end-to-end latency (ms)"] = f"p50 {s['p50']:.1f}, p95 {s['p95']:.1f}, p99 {s['p99']:.1f}"
    summary.update(stage_latency_summary(run))
    report = write_demo_report(args.out, frames, summary)
    print(f"[demo] {len(frames)} frames, {goals} goals; report: {report}")
    for f in frames:
        c = f.candidates
        if c is None or c.chosen_index < 0:
            print(f"  frame {f.index}: no goal")
            continue
        i = c.chosen_index
        x, y, z = c.positions[i]
        scores = chosen_view_scores(c, i)
        terms = ", ".join(f"{name} {scores['s_' + name]:.2f}" for name in c.term_names)
        print(f"  frame {f.index}: view {i:2d} at ({x:+.2f}, {y:+.2f}, {z:+.2f}) m  score {scores['score']:.3f} "
              f"({terms}; stay {c.score[0]:.3f})")
    print(f"[demo] done in {time.monotonic() - started:.1f} s")
    return 0 if goals == len(frames) else 1


if __name__ == "__main__":
    sys.exit(main())
