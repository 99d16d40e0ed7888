#!/usr/bin/env python3
"""Load benchmark: a 640x480 RGB-D camera at 30 FPS through the ground-truth graph, the camera moving
between viewpoints (a script, not a test: it runs for minutes).

    scripts/env.sh python scripts/bench/bench_load.py [--duration 300] [--fps 30] [--out out/bench_load]
                                               [--profile-s 30 --py-spy /path/to/py-spy]

What it does: renders a simulated scene (stand-in body, ground-truth perception) from three
viewpoints at different heights and headings and the frames on the way between them (the camera
holds each viewpoint ``--hold-s``, then moves for ``--move-s``), starts the five nodes with the
graph runner, and publishes what a RealSense driver and the robot's localization would: colour,
aligned depth, both camera infos, the camera pose (and, once, the latched obstacle map), plus the
simulator's ground truth, at ``--fps`` with wall-clock stamps. Pre-rendered frames are published as
stored CDR bytes with the stamp patched, so the publisher costs little CPU.

It prints (and writes to OUT/bench_load.json):

* goal rate (next_best_view), and end-to-end latency (goal received - frame stamp) p50/p95 in the
  first and the last minute (and the whole run), with the per-stage breakdown: each stage's output
  time after the previous stage's, and the stage's own compute time (the rest is transport, message
  conversion, and waiting);
* RSS of each node over time;
* goals from mixed frames: for each goal, the recorded inputs (InputStamp) of its ViewCandidates,
  TargetGeometry, HumanMesh and GroundPlane (leapnbv_bringup.frame_chains.check_goal_chain, which the
  frame-timing tests use too): every SAME_FRAME input must carry the goal's stamp (a
  CARRIED ground plane must be younger than ground_max_age_s); and, independently, the base goal
  must lie on the floor of the viewpoint the frame was rendered from (a plane from another
  viewpoint puts it 0.1-0.5 m off);
* goals older than max_goal_age_s when received (must be 0), and the goal_status states seen;
* every node's dropped.* and rejected.* counters from /diagnostics.

With ``--profile-s N`` (and py-spy installed), each node is sampled with ``py-spy record`` for N
seconds in the middle of the run (flame graphs in OUT/profile_<node>.svg, and a per-node table of
where the samples went: rclpy/DDS machinery, message conversion, the stage's compute).
"""
from __future__ import annotations

import argparse
import collections
import json
import os
import shutil
import struct
import subprocess
import sys
import threading
import time
from typing import Any, Dict, List, Optional, Tuple

import numpy as np

NS = "/leapnbv"
WORLD = "sim_world"
FRAME_ID = "camera_color_optical_frame"


# ----------------------------------------------------------------------------- the camera path


def render_path(args) -> Tuple[List, List[int], object]:
    """(distinct rendered frames, the frame index published at each tick of one cycle, the scene)."""
    from leapnbv_perception.smplx_layer import SMPLXModel
    from leapnbv_sim.generation import SceneConfig, generate_scene
    from leapnbv_sim.poses import CameraPose, look_at_pose, yaw_matrix
    from leapnbv_sim.simulator import interpolate_camera_pose
    from leapnbv_stand_ins.files import ensure_stand_in_body_model

    body = SMPLXModel.load(ensure_stand_in_body_model("small"))
    scene = generate_scene(SceneConfig(seed=args.seed, body_resolution="small", clutter_count_range=(0, 0)), body)
    start = scene.start_camera
    centre = scene.body_centre_world
    # Three viewpoints: the start view, and two around the person at other heights (floors 0.15-0.35 m
    # apart in camera height, so a plane from the wrong viewpoint shows in the base goal's height).
    viewpoints = [start]
    for yaw_deg, height in ((25.0, 1.35), (-25.0, 0.95)):
        offset = yaw_matrix(np.radians(yaw_deg)) @ (start.position - np.array([0.0, 0.0, start.position[2]]))
        position = np.array([offset[0], offset[1], height])
        viewpoints.append(look_at_pose(position, centre))
    frames, schedule = [], []
    hold = max(1, int(round(args.hold_s * args.fps)))
    move = max(0, int(round(args.move_s * args.fps)))
    for i, view in enumerate(viewpoints):
        nxt = viewpoints[(i + 1) % len(viewpoints)]
        frames.append(scene.render(CameraPose(view.rotation.copy(), view.position.copy()), frame_index=len(frames)))
        schedule += [len(frames) - 1] * hold
        renders = min(move, args.move_renders)
        for k in range(renders):
            pose = interpolate_camera_pose(view, nxt, (k + 1) / (renders + 1))
            frames.append(scene.render(pose, frame_index=len(frames)))
            schedule += [len(frames) - 1] * max(1, move // max(1, renders))
    visible = [f.ground_truth.person_pixel_count for f in frames]
    print(f"[bench] {len(frames)} distinct frames rendered (person pixels {min(visible)}-{max(visible)}), "
          f"a cycle of {len(schedule)} ticks ({len(schedule) / args.fps:.1f} s)", flush=True)
    return frames, schedule, scene


def frame_cdrs(frame, body_model_id: str, types: Dict[str, Any]) -> List[Tuple[str, bytes]]:
    """(topic, CDR bytes) of everything published for one rendered frame, stamp 0 (patched per tick).

    ``types`` gets each topic's message class (the publishers are made for what the frames carry)."""
    from geometry_msgs.msg import PoseStamped
    from rclpy.serialization import serialize_message
    from std_msgs.msg import Header

    from leapnbv_common.conversions import pose_msg
    from leapnbv_common.topics import CAMERA_POSE_TOPIC, COLOR_INFO_TOPIC, DEPTH_INFO_TOPIC
    from leapnbv_sim.frame_messages import camera_frame_messages

    messages = camera_frame_messages(frame, Header(frame_id=FRAME_ID), body_model_id)
    pose = PoseStamped(header=Header(frame_id=WORLD),
                       pose=pose_msg(frame.camera_pose.rotation, frame.camera_pose.position))
    ordered = [(COLOR_INFO_TOPIC, messages.pop(COLOR_INFO_TOPIC)), (DEPTH_INFO_TOPIC, messages.pop(DEPTH_INFO_TOPIC)),
               (CAMERA_POSE_TOPIC, pose)] + list(messages.items())  # then ground truth, people, colour, depth
    types.update((topic, type(msg)) for topic, msg in ordered)
    out = [(topic, serialize_message(msg)) for topic, msg in ordered]
    for _, cdr in out:
        assert cdr[1] == 1, "little-endian CDR expected"
    return out


def with_stamp(cdr: bytes, stamp_ns: int) -> bytes:
    """CDR of a message that starts with a std_msgs/Header, its stamp replaced."""
    return cdr[:4] + struct.pack("<iI", *divmod(stamp_ns, 1_000_000_000)) + cdr[12:]


class CameraPublisher(threading.Thread):
    """Publishes the schedule at a fixed rate with wall-clock stamps, from its own thread."""

    def __init__(self, node, cdrs: List[List[Tuple[str, bytes]]], types: Dict[str, Any], schedule: List[int],
                 fps: float, duration_s: float) -> None:
        super().__init__(daemon=True)
        from leapnbv_common.qos import camera_input_qos, stage_output_qos

        self.publishers = {topic: node.create_publisher(
            kind, topic, camera_input_qos(5) if topic.startswith("/camera/") else stage_output_qos(10))
            for topic, kind in types.items()}
        self.node, self.cdrs, self.schedule = node, cdrs, schedule
        self.period_s, self.duration_s = 1.0 / fps, duration_s
        self.published: Dict[int, Tuple[int, float]] = {}  # stamp -> (frame index, publish monotonic s)
        self.late_ticks = 0
        self.publish_delay_ms: List[float] = []
        self.started_wall_ns = 0
        self.stop_flag = threading.Event()
        self.error: Optional[Exception] = None

    def run(self) -> None:
        try:
            self._publish()
        except Exception as error:  # noqa: BLE001 - the main thread reports it and fails the run
            self.error = error

    def _publish(self) -> None:
        start = time.monotonic()
        self.started_wall_ns = time.time_ns()
        tick = 0
        while not self.stop_flag.is_set():
            due = start + tick * self.period_s
            if due - start >= self.duration_s:
                break
            delay = due - time.monotonic()
            if delay > 0:
                time.sleep(delay)
            elif delay < -self.period_s:
                self.late_ticks += 1
            index = self.schedule[tick % len(self.schedule)]
            # The camera's clock: exposure times 1/fps apart, even when a busy machine delivers them late.
            stamp = self.started_wall_ns + int(round(tick * self.period_s * 1e9))
            self.published[stamp] = (index, time.monotonic())
            for topic, cdr in self.cdrs[index]:
                self.publishers[topic].publish(with_stamp(cdr, stamp))
            self.publish_delay_ms.append((time.time_ns() - stamp) * 1e-6)  # this process's own lateness
            tick += 1


# ----------------------------------------------------------------------------- what the graph answers


class Monitor:
    """Subscribes to the graph's outputs and /diagnostics; records arrival times and recorded inputs."""

    def __init__(self, node) -> None:
        from diagnostic_msgs.msg import DiagnosticArray
        from geometry_msgs.msg import PoseStamped

        from leapnbv_common.qos import latched_goal_qos, stage_input_qos
        from leapnbv_msgs.msg import (
            GoalStatus,
            GroundPlane,
            HumanMesh,
            PersonDetections,
            TargetGeometry,
            ViewCandidates,
        )

        self.node = node
        self.arrivals: Dict[str, Dict[int, float]] = collections.defaultdict(dict)  # topic -> stamp -> wall s
        self.compute_ms: Dict[str, Dict[int, float]] = collections.defaultdict(dict)
        self.inputs: Dict[str, Dict[int, list]] = collections.defaultdict(dict)
        self.goals: List[Tuple[int, float]] = []  # (stamp, received wall ns)
        self.base_goals: Dict[int, np.ndarray] = {}
        self.cleared_goals = 0
        self.statuses: List[Tuple[float, int, str, float]] = []  # (monotonic s, state, reason, goal age s)
        self.diagnostics: Dict[str, Dict[str, str]] = {}
        qos = stage_input_qos(50)
        for name, kind in (("detections", PersonDetections), ("human_mesh", HumanMesh),
                           ("target_geometry", TargetGeometry), ("ground_plane", GroundPlane),
                           ("view_candidates", ViewCandidates)):
            node.create_subscription(kind, f"{NS}/{name}", lambda msg, n=name: self.on_output(n, msg), qos)
        node.create_subscription(PoseStamped, f"{NS}/next_best_view", self.on_goal, latched_goal_qos())
        node.create_subscription(PoseStamped, f"{NS}/base_goal", self.on_base_goal, latched_goal_qos())
        node.create_subscription(GoalStatus, f"{NS}/goal_status", self.on_status, latched_goal_qos())
        node.create_subscription(DiagnosticArray, "/diagnostics", self.on_diagnostics, stage_input_qos(50))

    def now_ns(self) -> int:
        return time.time_ns()

    def on_output(self, name: str, msg) -> None:
        from leapnbv_common.conversions import input_stamps, stamp_to_ns

        stamp = stamp_to_ns(msg.header.stamp)
        self.arrivals[name][stamp] = self.now_ns()
        self.compute_ms[name][stamp] = float(msg.compute_time_ms)
        if hasattr(msg, "inputs"):
            self.inputs[name][stamp] = input_stamps(msg)

    def on_goal(self, msg) -> None:
        from leapnbv_common.conversions import stamp_to_ns

        if not msg.header.frame_id:
            self.cleared_goals += 1
            return
        self.goals.append((stamp_to_ns(msg.header.stamp), self.now_ns()))

    def on_base_goal(self, msg) -> None:
        from leapnbv_common.conversions import stamp_to_ns

        if msg.header.frame_id:
            p = msg.pose.position
            self.base_goals[stamp_to_ns(msg.header.stamp)] = np.array([p.x, p.y, p.z])

    def on_status(self, msg) -> None:
        self.statuses.append((time.monotonic(), int(msg.state), str(msg.reason), float(msg.goal_age_s)))

    def on_diagnostics(self, msg) -> None:
        for status in msg.status:
            self.diagnostics[status.name] = {kv.key: kv.value for kv in status.values}


# ----------------------------------------------------------------------------- checks and figures


def percentile(values, q) -> float:
    return float(np.percentile(values, q)) if len(values) else float("nan")


def floor_error(monitor: Monitor, publisher: CameraPublisher, frames, stamp: int) -> Optional[float]:
    """|n.x + d| of the base goal of a frame on the true floor of that frame's viewpoint (metres)."""
    position = monitor.base_goals.get(stamp)
    if position is None or stamp not in publisher.published:
        return None
    camera = frames[publisher.published[stamp][0]].camera_pose
    normal = camera.rotation.T @ np.array([0.0, 0.0, 1.0])  # floor z = 0: n = R^T e_z, d = p_z
    return float(abs(normal @ position + camera.position[2]))


def window_latencies(goals: List[Tuple[int, float]], start_ns: int, end_ns: int) -> List[float]:
    return [(received - stamp) * 1e-6 for stamp, received in goals if start_ns <= stamp < end_ns]


def rss_mb(pid: int) -> float:
    try:
        with open(f"/proc/{pid}/status") as handle:
            for line in handle:
                if line.startswith("VmRSS:"):
                    return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    return float("nan")


def cpu_seconds(pid: int) -> Dict[str, float]:
    """CPU seconds (user + system) of a process so far, split: the main thread (the executor: takes,
    conversions, the stage's compute, publishes), the DDS threads (``dds.*``: sockets, shared memory,
    history), other threads (BLAS pools and the like)."""
    ticks = os.sysconf("SC_CLK_TCK")
    out = {"main": 0.0, "dds": 0.0, "other": 0.0}
    try:
        for tid in os.listdir(f"/proc/{pid}/task"):
            with open(f"/proc/{pid}/task/{tid}/stat") as handle:
                fields = handle.read().rpartition(")")[2].split()
            with open(f"/proc/{pid}/task/{tid}/comm") as handle:
                name = handle.read().strip()
            seconds = (int(fields[11]) + int(fields[12])) / ticks
            kind = "main" if int(tid) == pid else ("dds" if name.startswith("dds.") else "other")
            out[kind] += seconds
    except OSError:
        pass
    return out


def stage_breakdown(monitor: Monitor, publisher: CameraPublisher) -> Dict[str, Dict[str, float]]:
    """Median time from the previous stage's output (or the frame stamp) to each stage's output, and the
    stage's median compute time, over the frames that produced a goal."""
    goal_stamps = {stamp for stamp, _ in monitor.goals}
    hops = [("detections", None), ("human_mesh", "detections"), ("ground_plane", "detections"),
            ("target_geometry", "human_mesh"), ("view_candidates", "target_geometry")]
    out = {}
    for name, previous in hops:
        gaps, compute = [], []
        for stamp in goal_stamps:
            t = monitor.arrivals[name].get(stamp)
            t0 = stamp if previous is None else monitor.arrivals[previous].get(stamp)
            if t is None or t0 is None:
                continue
            gaps.append((t - t0) * 1e-6)
            compute.append(monitor.compute_ms[name].get(stamp, float("nan")))
        out[name] = {"after_ms_p50": percentile(gaps, 50), "after_ms_p95": percentile(gaps, 95),
                     "compute_ms_p50": percentile(compute, 50), "frames": len(gaps)}
    return out


def run_py_spy(py_spy: str, pids: Dict[str, int], seconds: int, out_dir: str) -> Dict[str, subprocess.Popen]:
    procs = {}
    for name, pid in pids.items():
        cmd = [py_spy, "record", "--pid", str(pid), "--duration", str(seconds), "--rate", "100", "--nonblocking",
               "--format", "raw", "--output", os.path.join(out_dir, f"profile_{name}.txt")]
        procs[name] = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.STDOUT)
    return procs


# Where a sample goes, by the first matching frame from the leaf (file name parts).
SAMPLE_CLASSES = [
    ("message conversion", ("leapnbv_common/conversions.py", "rosidl", "_msg.py", "serialization",
                            "/msg/_", "sensor_msgs/msg", "leapnbv_msgs/msg", "geometry_msgs/msg")),
    ("rclpy / DDS machinery", ("rclpy/", "executors.py", "task.py", "_rclpy")),
]


def summarize_profile(path: str) -> Dict[str, float]:
    """Shares of samples: the stage's compute (leapnbv cores, numpy, numba), conversion, rclpy, idle."""
    counts: Dict[str, int] = collections.Counter()
    total = 0
    try:
        with open(path) as handle:
            for line in handle:
                stack, _, count = line.rstrip().rpartition(" ")
                if not stack:
                    continue
                n = int(count)
                total += n
                frames = stack.split(";")
                leaf_to_root = list(reversed(frames))
                kind = "stage compute"
                if any("wait" in f and ("rclpy" in f or "executors" in f) for f in leaf_to_root[:2]):
                    kind = "idle (waiting for messages)"
                else:
                    for label, marks in SAMPLE_CLASSES:
                        if any(any(m in f for m in marks) for f in leaf_to_root[:3]):
                            kind = label
                            break
                counts[kind] += n
    except OSError:
        return {}
    return {k: round(100.0 * v / total, 1) for k, v in counts.most_common()} if total else {}


def main(argv: Optional[List[str]] = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--duration", type=float, default=300.0, help="seconds of camera input (default 300)")
    parser.add_argument("--fps", type=float, default=30.0)
    parser.add_argument("--hold-s", type=float, default=2.0, help="seconds the camera holds each viewpoint")
    parser.add_argument("--move-s", type=float, default=1.0, help="seconds it takes to move to the next one")
    parser.add_argument("--move-renders", type=int, default=10, help="distinct frames rendered per move")
    parser.add_argument("--seed", type=int, default=3)
    parser.add_argument("--window-s", type=float, default=60.0, help="length of the first / last window")
    parser.add_argument("--out", default="out/bench_load")
    parser.add_argument("--set", action="append", default=[], metavar="NODE.PARAM=VALUE",
                        help="parameter override for the graph (repeatable)")
    parser.add_argument("--profile-s", type=int, default=0, help="sample every node with py-spy this long")
    parser.add_argument("--py-spy", default=shutil.which("py-spy") or "", help="py-spy executable")
    args = parser.parse_args(argv)
    os.makedirs(args.out, exist_ok=True)
    from leapnbv_evaluation.parallel import own_domain

    # A domain of its own ($ROS_DOMAIN_ID when set, else a free one): its camera topics must not reach another
    # graph on this machine, nor another graph's outputs its figures.
    with own_domain() as domain:
        print(f"[bench] ROS domain {domain}", flush=True)
        return measure(args)


def measure(args) -> int:
    """Render, start the graph, publish for args.duration, print and write the figures."""

    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node
    from sensor_msgs.msg import PointCloud2
    from std_msgs.msg import Header

    from leapnbv_bringup.frame_chains import check_goal_chain
    from leapnbv_bringup.graph_runner import GraphRunner, merge_overrides, parse_set_arguments, perception_overrides
    from leapnbv_common.conversions import xyz_to_pointcloud2
    from leapnbv_common.qos import latched_map_qos
    from leapnbv_common.topics import OBSTACLE_MAP_TOPIC
    from leapnbv_planner.params import default_nbv_params
    from leapnbv_stand_ins.files import ensure_stand_in_body_model

    frames, schedule, scene = render_path(args)
    types: Dict[str, Any] = {}
    cdrs = [frame_cdrs(f, scene.body_model_id, types) for f in frames]
    overrides = merge_overrides(perception_overrides("ground_truth", body_model=ensure_stand_in_body_model("small")),
                                parse_set_arguments(args.set))
    nbv_defaults = default_nbv_params()
    max_goal_age_s = float(overrides.get("nbv_node", {}).get("max_goal_age_s", nbv_defaults.max_goal_age_s))
    max_carry_ns = int(float(overrides.get("nbv_node", {}).get("ground_max_age_s", nbv_defaults.ground_max_age_s))
                       * 1e9)

    rclpy.init()
    node = Node("leapnbv_bench_load")
    runner = GraphRunner(overrides=overrides, log_dir=os.path.join(args.out, "logs"))
    report: Dict[str, object] = {"args": vars(args), "uptime_before": open("/proc/loadavg").read().strip()}
    try:
        runner.start()
        ready_s = runner.wait_ready(node, timeout_s=120.0)
        pids = {name: proc.pid for name, proc in runner.processes.items()}
        print(f"[bench] graph ready in {ready_s:.1f} s; load average {report['uptime_before']}", flush=True)
        monitor = Monitor(node)
        map_pub = node.create_publisher(PointCloud2, OBSTACLE_MAP_TOPIC, latched_map_qos())
        map_pub.publish(xyz_to_pointcloud2(scene.obstacle_voxel_centres(0.1), Header(frame_id=WORLD)))
        publisher = CameraPublisher(node, cdrs, types, schedule, args.fps, args.duration)
        executor = SingleThreadedExecutor()
        executor.add_node(node)
        deadline = time.monotonic() + 10.0
        while time.monotonic() < deadline and not all(p.get_subscription_count() > 0
                                                      for p in publisher.publishers.values()):
            executor.spin_once(timeout_sec=0.05)
        end = time.monotonic() + 1.0
        while time.monotonic() < end:
            executor.spin_once(timeout_sec=0.05)
        cpu_before = {name: cpu_seconds(pid) for name, pid in pids.items()}
        publisher.start()
        rss: Dict[str, List[Tuple[float, float]]] = {name: [] for name in pids}
        started = time.monotonic()
        next_rss = started
        profiling = None
        profile_at = started + max(0.0, args.duration / 2 - args.profile_s / 2)
        while publisher.is_alive():
            executor.spin_once(timeout_sec=0.05)
            now = time.monotonic()
            if now >= next_rss:
                for name, pid in pids.items():
                    rss[name].append((now - started, rss_mb(pid)))
                next_rss += 10.0
                runner.check_alive()
            if args.profile_s and args.py_spy and profiling is None and now >= profile_at:
                profiling = run_py_spy(args.py_spy, pids, args.profile_s, args.out)
                print(f"[bench] py-spy sampling every node for {args.profile_s} s", flush=True)
        end = time.monotonic() + max(2.0, max_goal_age_s + 0.5)  # trailing outputs, and the goal aging out
        while time.monotonic() < end:
            executor.spin_once(timeout_sec=0.05)
        for name, pid in pids.items():
            rss[name].append((time.monotonic() - started, rss_mb(pid)))
        cpu_after = {name: cpu_seconds(pid) for name, pid in pids.items()}
        wall_s = time.monotonic() - started
        runner.check_alive()
        if profiling:
            for proc in profiling.values():
                proc.wait(timeout=args.profile_s + 60)
    finally:
        codes = runner.stop()
        report["exit_codes"] = codes
        node.destroy_node()
        rclpy.try_shutdown()
    report["uptime_after"] = open("/proc/loadavg").read().strip()

    # ------------------------------------------------------------------ figures
    t0 = publisher.started_wall_ns
    duration_ns = int(args.duration * 1e9)
    window_ns = int(args.window_s * 1e9)
    goals = monitor.goals
    first = window_latencies(goals, t0, t0 + window_ns)
    last = window_latencies(goals, t0 + duration_ns - window_ns, t0 + duration_ns)
    whole = window_latencies(goals, t0, t0 + duration_ns)
    too_old = [lat for lat in whole if lat > max_goal_age_s * 1e3] if max_goal_age_s > 0 else []
    # The age nbv_node measured when it published each goal (GoalStatus CURRENT goes out with every goal).
    published_ages = [age for _, state, _, age in monitor.statuses if state == 1]
    too_old_at_publish = [a for a in published_ages if a > max_goal_age_s] if max_goal_age_s > 0 else []
    verifiable = mixed = 0
    mixed_details, carried = [], 0
    off_floor, floor_errors = [], []
    for stamp, _ in goals:
        verdict = check_goal_chain(monitor.inputs, stamp, max_carry_ns)
        verifiable += verdict.verifiable
        mixed += verdict.mixed
        carried += verdict.detail.startswith("carried")
        if verdict.mixed and len(mixed_details) < 10:
            mixed_details.append(verdict.detail)
        error = floor_error(monitor, publisher, frames, stamp)
        if error is not None:
            floor_errors.append(error)
            if error > 0.05:
                off_floor.append(error)
    stage_counts = {name: len(monitor.arrivals[name]) for name in
                    ("detections", "human_mesh", "ground_plane", "target_geometry", "view_candidates")}
    states = collections.Counter(state for _, state, _, _ in monitor.statuses)
    report.update({
        "frames_published": len(publisher.published), "publisher_late_ticks": publisher.late_ticks,
        "publisher_delay_ms": {"p50": percentile(publisher.publish_delay_ms, 50),
                               "p95": percentile(publisher.publish_delay_ms, 95)},
        "goals": len(goals), "goal_rate_hz": len(goals) / args.duration,
        "latency_ms": {
            "first_window": {"p50": percentile(first, 50), "p95": percentile(first, 95), "n": len(first)},
            "last_window": {"p50": percentile(last, 50), "p95": percentile(last, 95), "n": len(last)},
            "whole_run": {"p50": percentile(whole, 50), "p95": percentile(whole, 95),
                          "max": max(whole) if whole else float("nan"), "n": len(whole)}},
        "stage_outputs": stage_counts,
        "stage_breakdown": stage_breakdown(monitor, publisher),
        "mixed_frame_goals": mixed, "goals_verified": verifiable, "goals_with_carried_plane": carried,
        "mixed_frame_examples": mixed_details,
        "base_goal_floor_error_m": {"p50": percentile(floor_errors, 50), "max": max(floor_errors, default=0.0),
                                    "off_floor_over_5cm": len(off_floor), "n": len(floor_errors)},
        "goals_older_than_limit": len(too_old), "max_goal_age_s": max_goal_age_s,
        "goals_older_than_limit_at_publish": len(too_old_at_publish),
        "goal_age_at_publish_s": {"p50": percentile(published_ages, 50), "max": max(published_ages, default=0.0)},
        "goal_status_states": {str(k): v for k, v in sorted(states.items())}, "cleared_goals": monitor.cleared_goals,
        "rss_mb": {name: [(round(t, 1), round(v, 1)) for t, v in series] for name, series in rss.items()},
        "cpu_percent_of_one_core": {name: {kind: round(100.0 * (cpu_after[name][kind] - cpu_before[name][kind])
                                                       / wall_s, 1) for kind in ("main", "dds", "other")}
                                    for name in pids},
        "cpu_ms_per_goal": {name: round(1e3 * sum(cpu_after[name][k] - cpu_before[name][k] for k in cpu_after[name])
                                        / max(1, len(goals)), 1) for name in pids},
        "diagnostics": {name: {k: v for k, v in values.items()
                               if k.startswith(("dropped", "rejected", "counted", "frames_", "transport_ms",
                                                "last_compute"))}
                        for name, values in sorted(monitor.diagnostics.items())},
    })
    if args.profile_s:
        report["profile_shares_percent"] = {name: summarize_profile(os.path.join(args.out, f"profile_{name}.txt"))
                                            for name in pids}
    if publisher.error is not None:
        print(f"bench_load: the camera publisher failed: {publisher.error!r}", file=sys.stderr)
        return 1
    with open(os.path.join(args.out, "bench_load.json"), "w") as handle:
        json.dump(report, handle, indent=1, default=str)
    print_report(report)
    if not goals:
        print("bench_load: the graph published no goal", file=sys.stderr)
        return 1
    return 0


def print_report(r: Dict) -> None:
    lat = r["latency_ms"]
    print(f"\n== load benchmark: {r['args']['fps']:g} FPS 640x480 RGB-D for {r['args']['duration']:g} s")
    print(f"load average before: {r['uptime_before']}; after: {r['uptime_after']}")
    delay = r["publisher_delay_ms"]
    print(f"frames published {r['frames_published']} (late ticks {r['publisher_late_ticks']}; the publisher's own "
          f"delay after the stamp p50 {delay['p50']:.1f} ms, p95 {delay['p95']:.1f} ms, included in the latencies); "
          f"goals {r['goals']} = {r['goal_rate_hz']:.2f} Hz")
    for key in ("first_window", "last_window", "whole_run"):
        w = lat[key]
        extra = f", max {w['max']:.0f}" if "max" in w else ""
        print(f"end-to-end latency {key:12s}: p50 {w['p50']:.0f} ms, p95 {w['p95']:.0f} ms{extra} (n={w['n']})")
    print("stage outputs:", ", ".join(f"{k} {v}" for k, v in r["stage_outputs"].items()))
    print("per stage (goal frames): time after the previous stage's output p50/p95, own compute p50")
    for name, b in r["stage_breakdown"].items():
        print(f"  {name:16s} {b['after_ms_p50']:7.1f} / {b['after_ms_p95']:7.1f} ms   "
              f"compute {b['compute_ms_p50']:6.1f} ms")
    print(f"goals from mixed frames: {r['mixed_frame_goals']} of {r['goals_verified']} verified "
          f"({r['goals_with_carried_plane']} with a carried plane); base goal off the true floor by > 5 cm: "
          f"{r['base_goal_floor_error_m']['off_floor_over_5cm']} (max {r['base_goal_floor_error_m']['max']:.3f} m)")
    for example in r["mixed_frame_examples"]:
        print("   ", example)
    ages = r["goal_age_at_publish_s"]
    print(f"goals older than {r['max_goal_age_s']:g} s: {r['goals_older_than_limit_at_publish']} when published "
          f"(age at publish p50 {ages['p50']:.3f} s, max {ages['max']:.3f} s), "
          f"{r['goals_older_than_limit']} when received here")
    print(f"goal_status states seen {r['goal_status_states']} (0 NONE, 1 CURRENT, 2 STALE); goals withdrawn as stale "
          f"{r['cleared_goals']}")
    print("CPU per node, % of one core (main thread: executor, conversions, compute; dds: transport threads; "
          "other) and ms per goal:")
    for name, shares in r["cpu_percent_of_one_core"].items():
        print(f"  {name:14s} main {shares['main']:5.1f}  dds {shares['dds']:5.1f}  other {shares['other']:5.1f}   "
              f"{r['cpu_ms_per_goal'][name]:6.1f} ms/goal")
    transport = {name: {k[len("transport_ms."):]: v for k, v in values.items() if k.startswith("transport_ms.")}
                 for name, values in r["diagnostics"].items()}
    print("last transport time (publish -> receive) per input:",
          "; ".join(f"{n.rsplit('/', 1)[-1]}: " + ", ".join(f"{k} {v} ms" for k, v in t.items())
                    for n, t in transport.items() if t))
    print("RSS per node (MB) over time:")
    for name, series in r["rss_mb"].items():
        picks = [series[int(i)] for i in np.linspace(0, len(series) - 1, min(6, len(series)))]
        print(f"  {name:14s} " + "  ".join(f"{t:5.0f}s {v:6.1f}" for t, v in picks))
    print("drops, rejections and other counts by node:")
    for name, values in r["diagnostics"].items():
        counts = {k: v for k, v in values.items()
                  if k.startswith(("dropped.", "rejected.", "counted.")) and v not in ("0",)}
        print(f"  {name}: in {values.get('frames_in')}, out {values.get('frames_out')}; {counts}")
    if "profile_shares_percent" in r:
        print("py-spy samples by kind (% of each node's samples):")
        for name, shares in r["profile_shares_percent"].items():
            print(f"  {name:14s} {shares}")


if __name__ == "__main__":
    sys.exit(main())
