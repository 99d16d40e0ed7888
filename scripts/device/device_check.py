#!/usr/bin/env python3
"""The device check's work (scripts/device/device_check.sh runs it; Python 3.8: it runs inside the Jetson image).

    device_check.py engines --s32 S32.onnx --yolo YOLOV8S.onnx [--plan PLAN.json] [--cache DIR] [--runs N]
    device_check.py graph --bag DIR --s32 ... --yolo ... --body-model SMPLX_NEUTRAL.npz [--seconds S]

engines: for each model, FP32 and FP16 TensorRT engines (built through the project's backend, so
the engine cache and the FP16 precision plan are the graph's own), the same seeded inputs through
onnxruntime FP32 on the CPU as the reference, and per output the relative L2 error
||trt - ort|| / ||ort|| against TOLERANCES, the largest absolute difference, and the engine's
latency (median and p95 of --runs calls, host<->device copies included).

graph: on a board with power rails, the whole graph (ros2 launch) on a bag played in a loop
(ros2 bag play) for --seconds, with the rails integrated over that time: joules per frame =
energy / view_candidates published, for VDD_IN and the compute rail; the idle power before the
graph starts is reported beside it.

Exit status: 0 when every engine is within tolerance (and the graph step, if it ran, produced
frames), 1 otherwise.
"""
from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import tempfile
import time
from typing import Dict, List, Optional, Tuple

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

# Relative L2 error of each output against onnxruntime FP32, per engine precision. FP32 engines
# differ only by kernel choice and summation order; FP16 keeps ~3 significant digits per op, and a
# 12-block ViT accumulates that: 2e-2 is about ten times what a guarded FP16 build is expected to
# show and well under what an unguarded LayerNorm overflow gives (order 1).
TOLERANCES = {"fp32": 1e-3, "fp16": 2e-2}
WARMUP_RUNS = 10


def _import_project() -> None:
    """Use the installed packages (the image), else the repository's sources."""
    try:
        import leapnbv_perception  # noqa: F401
    except ImportError:
        for package in ("leapnbv_common", "leapnbv_perception"):
            sys.path.insert(0, os.path.join(ROOT, "src", package))


def seeded_inputs(specs, seed: int = 0) -> Dict[str, object]:
    """Uniform [0, 1) float inputs of the engine's static shapes (images in [0, 1] as both models take)."""
    import numpy as np

    rng = np.random.default_rng(seed)
    return {name: rng.random(spec.static_shape(), dtype=np.float32) for name, spec in specs.items()}


def compare(reference: Dict[str, object], outputs: Dict[str, object], tolerance: float) -> List[dict]:
    """Per output: relative L2 error, largest absolute difference, within tolerance or not."""
    import numpy as np

    rows = []
    for name, ref in reference.items():
        ref = np.asarray(ref, dtype=np.float64)
        got = np.asarray(outputs[name], dtype=np.float64).reshape(ref.shape)
        rel = float(np.linalg.norm(got - ref) / (np.linalg.norm(ref) + 1e-12))
        finite = bool(np.all(np.isfinite(got)))
        rows.append({"output": name, "rel_l2": rel, "max_abs": float(np.max(np.abs(got - ref))) if ref.size else 0.0,
                     "finite": finite, "ok": finite and rel <= tolerance})
    return rows


def time_runs(run, inputs, runs: int) -> Tuple[float, float]:
    import numpy as np

    for _ in range(WARMUP_RUNS):
        run(inputs)
    samples = []
    for _ in range(runs):
        start = time.perf_counter()
        run(inputs)
        samples.append((time.perf_counter() - start) * 1e3)
    return float(np.median(samples)), float(np.percentile(samples, 95))


def check_engines(models: Dict[str, str], plan: Optional[str], cache: Optional[str], runs: int) -> Tuple[bool, list]:
    _import_project()
    from leapnbv_perception.backends.onnxruntime_backend import OnnxRuntimeBackend
    from leapnbv_perception.backends.tensorrt_backend import TensorRTBackend

    results = []
    all_ok = True
    for label, path in models.items():
        reference_backend = OnnxRuntimeBackend(path)
        inputs = seeded_inputs(reference_backend.input_specs)
        reference = reference_backend.run(inputs)
        for precision in ("fp32", "fp16"):
            started = time.perf_counter()
            engine = TensorRTBackend(path, precision, cache, precision_plan_path=plan if precision == "fp16" else None)
            ready_s = time.perf_counter() - started
            rows = compare(reference, engine.run(inputs), TOLERANCES[precision])
            median_ms, p95_ms = time_runs(engine.run, inputs, runs)
            ok = all(row["ok"] for row in rows)
            all_ok &= ok
            results.append({"model": label, "onnx": path, "precision": precision, "ok": ok,
                            "engine": engine.engine_path, "built_now": engine.engine_was_built,
                            "ready_s": ready_s, "latency_ms_median": median_ms, "latency_ms_p95": p95_ms,
                            "kept_fp32_layers": len(engine.kept_fp32_layers or []), "outputs": rows})
            print("%-5s %-4s %s  latency %.2f ms median, %.2f ms p95  (%s in %.1f s)"
                  % (label, precision, "OK  " if ok else "FAIL", median_ms, p95_ms,
                     "built" if engine.engine_was_built else "loaded from cache", ready_s))
            for row in rows:
                print("        %-24s rel L2 %.2e (tolerance %.0e)  max |diff| %.3g%s"
                      % (row["output"], row["rel_l2"], TOLERANCES[precision], row["max_abs"],
                         "" if row["finite"] else "  NON-FINITE"))
            engine.close()
    return all_ok, results


def _params_file(models: Dict[str, str], body_model: str, plan: Optional[str], cache: Optional[str]) -> str:
    """The deployed YAML with this check's model paths (and plan) in place of the robot's."""
    import yaml

    with open(os.path.join(ROOT, "src", "leapnbv_bringup", "config", "leapnbv.yaml"), encoding="utf-8") as stream:
        params = yaml.safe_load(stream)
    detector = params["/**/detector_node"]["ros__parameters"]
    hmr = params["/**/hmr_node"]["ros__parameters"]
    detector["model_file_path"], hmr["model_file_path"] = models["yolo"], models["s32"]
    hmr["body_model_path"] = body_model
    if plan:
        hmr["precision_plan_path"] = plan
    if cache:
        detector["engine_cache_dir"] = hmr["engine_cache_dir"] = cache
    handle, path = tempfile.mkstemp(prefix="leapnbv_device_check_", suffix=".yaml")
    with os.fdopen(handle, "w") as stream:
        yaml.safe_dump(params, stream)
    return path


def check_graph(bag: str, models: Dict[str, str], body_model: str, plan: Optional[str], cache: Optional[str],
                seconds: float, idle_s: float = 3.0) -> Tuple[bool, dict]:
    _import_project()
    from leapnbv_common.power_monitor import RAIL_TOTAL, PowerParams, start_power_monitor

    monitor, message = start_power_monitor(PowerParams())
    if monitor is None:
        print("graph: skipped, %s" % message)
        return True, {"skipped": message}
    print("graph: %s" % message)
    import rclpy

    from leapnbv_common.qos import stage_input_qos
    from leapnbv_msgs.msg import ViewCandidates

    time.sleep(idle_s)
    now = monitor.clock()
    idle = monitor.energy(now - idle_s + 0.2, now)
    params = _params_file(models, body_model, plan, cache)
    env = dict(os.environ, LEAPNBV_POWER_NODE="1")
    launch = subprocess.Popen(["ros2", "launch", "leapnbv_bringup", "leapnbv.launch.py", "params_file:=" + params],
                              env=env, start_new_session=True)
    rclpy.init()
    node = rclpy.create_node("device_check")
    frames = []
    node.create_subscription(ViewCandidates, "/leapnbv/view_candidates", frames.append, stage_input_qos(50))
    player = None
    try:
        deadline = time.monotonic() + 600.0  # engine builds on the first start take minutes
        print("graph: waiting for the first output (TensorRT engines build now if the cache is cold)")
        player = subprocess.Popen(["ros2", "bag", "play", bag, "--loop"], start_new_session=True,
                                  stdout=subprocess.DEVNULL)
        while not frames and time.monotonic() < deadline and launch.poll() is None:
            rclpy.spin_once(node, timeout_sec=0.1)
        if not frames:
            state = "exited" if launch.poll() is not None else "running"
            print("graph: FAIL, no view_candidates (the launch is %s)" % state)
            return False, {"frames": 0}
        count0, t0 = len(frames), monitor.clock()
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            rclpy.spin_once(node, timeout_sec=0.05)
        t1, count = monitor.clock(), len(frames) - count0
        time.sleep(0.05)
        energy = monitor.energy(t0, t1)
    finally:
        for process in (player, launch):
            if process is not None and process.poll() is None:
                os.killpg(process.pid, signal.SIGINT)
                try:
                    process.wait(timeout=15)
                except subprocess.TimeoutExpired:
                    os.killpg(process.pid, signal.SIGKILL)
        node.destroy_node()
        rclpy.shutdown()
        monitor.stop()
        os.remove(params)
    result = {"frames": count, "seconds": t1 - t0, "fps": count / (t1 - t0),
              "idle_power_w": idle.mean_power_w if idle else None,
              "mean_power_w": energy.mean_power_w, "energy_j_per_frame":
                  {rail: joules / count for rail, joules in energy.energy_j.items()} if count else None}
    print("graph: %d frames in %.1f s (%.2f FPS)" % (count, t1 - t0, result["fps"]))
    for rail in monitor.names:
        per_frame = energy.energy_j[rail] / count if count else float("nan")
        print("graph: %-15s %.3f J/frame, %.2f W while running (idle %.2f W)"
              % (rail, per_frame, energy.mean_power_w[rail], idle.mean_power_w[rail] if idle else float("nan")))
    print("graph: energy per frame (%s) = %.3f J" % (RAIL_TOTAL, result["energy_j_per_frame"][RAIL_TOTAL])
          if count and RAIL_TOTAL in energy.energy_j else "graph: no VDD_IN figure")
    return count > 0, result


def main(argv: Optional[List[str]] = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("step", choices=("engines", "graph"))
    parser.add_argument("--s32", required=True, help="exported SMPLer-X s32 student ONNX")
    parser.add_argument("--yolo", required=True, help="YOLOv8s ONNX")
    parser.add_argument("--plan", default=None, help="FP16 precision plan JSON of the s32 model")
    parser.add_argument("--cache", default=None, help="TensorRT engine cache folder")
    parser.add_argument("--runs", type=int, default=50, help="timed runs per engine")
    parser.add_argument("--bag", default=os.path.join(ROOT, "bags", "sample_a"))
    parser.add_argument("--body-model", default="", help="SMPLX_NEUTRAL.npz (graph step)")
    parser.add_argument("--seconds", type=float, default=30.0, help="graph step: seconds measured")
    parser.add_argument("--json", default="", help="write the results here")
    args = parser.parse_args(argv)
    models = {"s32": args.s32, "yolo": args.yolo}
    if args.step == "engines":
        ok, results = check_engines(models, args.plan, args.cache, args.runs)
    else:
        ok, results = check_graph(args.bag, models, args.body_model, args.plan, args.cache, args.seconds)
    if args.json:
        with open(args.json, "w", encoding="utf-8") as stream:
            json.dump(results, stream, indent=2)
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
