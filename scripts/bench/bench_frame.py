#!/usr/bin/env python3
"""A whole frame with the real network architectures through the real graph on this CPU, in several
onnxruntime configurations (a script, not a test: each configuration runs the graph for --duration s).

The networks are the real architectures with random weights, built in the tools environment:

    tools/run.sh python -m leapnbv_model_tools random-yolov8 --out yolov8s_random.onnx
    tools/run.sh python -m leapnbv_model_tools random-checkpoint --variant s32 --out s32.pth.tar
    tools/run.sh python -m leapnbv_model_tools export-hmr --checkpoint s32.pth.tar --variant s32 --out s32.onnx
    scripts/env.sh python scripts/bench/bench_frame.py --detector yolov8s_random.onnx --hmr s32.onnx [--duration 60]

The body-only configurations (names starting "body-only HMR") run a body-only export of the same
checkpoint (``export-hmr ... --without-hands --out s32_body_only.onnx``: no hand branch, the hands
at the SMPL-X hand mean pose), given with ``--hmr-body-only s32_body_only.onnx``; without it they
are skipped. ``--only NAME ...`` runs some configurations, e.g.

    scripts/env.sh python scripts/bench/bench_frame.py --detector yolov8s_random.onnx --hmr s32.onnx \
        --hmr-body-only s32_body_only.onnx --only "body-only HMR, 1 thread each"

The INT8 configurations (names starting "INT8 engines") run the same configurations as their FP32
namesakes with the INT8 engines that quantize-int8 writes (docs/INT8.md), given with
``--detector-int8``, ``--hmr-int8`` and ``--hmr-body-only-int8`` (each INT8 configuration is skipped
without the files it needs). ``--rounds N`` runs the chosen configurations N times in turn (A B A B:
an FP32 configuration and its INT8 namesake see the same load), and the table gives each INT8 row's
latency p50 against its FP32 namesake's of the same round. The header names the CPU's integer
instruction set (avx2, avx512_vnni, avx_vnni, amx_int8 from /proc/cpuinfo).

A random-weight detector finds nobody, so the detector runs as a timing stand-in
(``detector_node.timing_stand_in``): the network runs on every admitted frame and its boxes are
discarded; the simulator's boxes go on. The HMR network's (random) mesh goes through the rest of
the graph. The camera is scripts/bench/bench_load.py's (640x480 RGB-D, moving between viewpoints) at
--fps; the graph takes the newest frame it can finish. For each configuration: goals per second,
end-to-end latency (goal received - frame stamp) p50 / p95, each engine's compute p50, the CPU
time per goal of each node, and the machine's load before and after.

Exit codes: 0 done; 2 a model file is missing, --hmr-body-only is not a body-only export, or an
--only name is unknown; 3 a configuration's run failed (its bench_load exit code).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from typing import Dict, List, Tuple

HERE = os.path.dirname(os.path.abspath(__file__))

# The next frame is admitted once the previous one is planned: the mesh it carries a box from is
# one whole frame old, so the age limit must exceed the frame time. The random HMR network's mesh
# is no person (much of it outside the image): this timing run carries its box whatever the
# confidence (carry_min_confidence 0), to show the time a detection-free frame takes.
DETECT_EVERY_3RD = ["detector_node.detect_every_n_frames=3", "detector_node.carry_max_age_s=3.0",
                    "detector_node.carry_min_confidence=0.0"]
DETECT_EVERY_5TH = ["detector_node.detect_every_n_frames=5", "detector_node.carry_max_age_s=3.0",
                    "detector_node.carry_min_confidence=0.0"]

# name -> parameter overrides (node.param=value) on top of the engines' own settings
CONFIGURATIONS: Dict[str, List[str]] = {
    "1 thread each": ["detector_node.intra_op_threads=1", "hmr_node.intra_op_threads=1"],
    "2 threads each": ["detector_node.intra_op_threads=2", "hmr_node.intra_op_threads=2"],
    "1 thread each, basic graph optimization": ["detector_node.intra_op_threads=1", "hmr_node.intra_op_threads=1",
                                                "detector_node.graph_optimization=basic",
                                                "hmr_node.graph_optimization=basic"],
    "1 thread each, parallel execution (2 inter-op)": ["detector_node.intra_op_threads=1",
                                                       "hmr_node.intra_op_threads=1",
                                                       "detector_node.parallel_execution=true",
                                                       "hmr_node.parallel_execution=true",
                                                       "detector_node.inter_op_threads=2",
                                                       "hmr_node.inter_op_threads=2"],
    # One frame in three detected, the box carried by the mesh in between (DETECT_EVERY_3RD).
    "1 thread each, detect every 3rd frame": ["detector_node.intra_op_threads=1", "hmr_node.intra_op_threads=1",
                                              *DETECT_EVERY_3RD],
}

# The same graph with the body-only HMR engine (--hmr-body-only): the hand branch, about half of the s32
# engine's CPU time, is not run; the planner uses the body mesh, whose hands then have the mean pose.
BODY_ONLY_CONFIGURATIONS: Dict[str, List[str]] = {
    "body-only HMR, 1 thread each": ["detector_node.intra_op_threads=1", "hmr_node.intra_op_threads=1"],
    "body-only HMR, 2 threads each": ["detector_node.intra_op_threads=2", "hmr_node.intra_op_threads=2"],
    # The detector runs on one frame in 3 only, so the HMR engine, which runs on every frame, gets both cores.
    "body-only HMR 2 threads, detector 1 thread, detect every 3rd frame": [
        "detector_node.intra_op_threads=1", "hmr_node.intra_op_threads=2", *DETECT_EVERY_3RD],
    "body-only HMR 2 threads, detector 1 thread, detect every 5th frame": [
        "detector_node.intra_op_threads=1", "hmr_node.intra_op_threads=2", *DETECT_EVERY_5TH],
    # The same with the engines' idle threads asleep (thread_spinning false): raster and nbv run on the cores
    # the HMR engine's second thread would spin on between runs.
    "body-only HMR 2 threads, detector 1 thread, detect every 5th frame, threads sleep": [
        "detector_node.intra_op_threads=1", "hmr_node.intra_op_threads=2", *DETECT_EVERY_5TH,
        "detector_node.thread_spinning=false", "hmr_node.thread_spinning=false"],
}


#: INT8 configurations: "INT8 engines, " + the FP32 configuration's name, with the INT8 files
INT8_OF = ("1 thread each", "2 threads each", "1 thread each, detect every 3rd frame", "body-only HMR, 1 thread each",
           "body-only HMR 2 threads, detector 1 thread, detect every 5th frame")
INT8_PREFIX = "INT8 engines, "

#: the integer instruction-set flags the header names
INTEGER_FLAGS = ("avx2", "avx512f", "avx512_vnni", "avx_vnni", "amx_int8", "asimddp")


def instruction_set() -> str:
    """The CPU's model name and integer instruction-set flags, from /proc/cpuinfo."""
    flags: List[str] = []
    model = ""
    try:
        with open("/proc/cpuinfo") as handle:
            for line in handle:
                key, _, value = line.partition(":")
                key = key.strip().lower()
                if key in ("flags", "features") and not flags:
                    flags = value.split()
                elif key == "model name" and not model:
                    model = value.strip()
    except OSError:
        pass
    present = [f for f in INTEGER_FLAGS if f in flags]
    return f"{model or 'unknown CPU'}, {' '.join(present) if present else 'no AVX2 / VNNI / AMX'}"


def run_configuration(name: str, settings: List[str], args, out: str, hmr: str,
                      detector: str) -> Tuple[int, Dict]:
    """Run bench_load with one configuration; (exit code, its report)."""
    base = ["detector_node.timing_stand_in=true", f"detector_node.model_file_path={os.path.abspath(detector)}",
            "hmr_node.backend=onnxruntime", f"hmr_node.model_file_path={os.path.abspath(hmr)}",
            f"hmr_node.body_model_path={os.path.abspath(args.body_model)}",
            # a whole frame takes longer than the ground-truth graph's 1 s goal age limit on this CPU
            f"nbv_node.max_goal_age_s={args.max_goal_age_s}"]
    cmd = [sys.executable, os.path.join(HERE, "bench_load.py"), "--duration", str(args.duration), "--fps",
           str(args.fps), "--out", out, "--window-s", str(args.duration / 2)]
    for item in base + settings:
        cmd += ["--set", item]
    print(f"[bench_frame] {name} ({os.path.basename(detector)}, {os.path.basename(hmr)}): {' '.join(settings)}; "
          f"load {open('/proc/loadavg').read().split()[0]}", flush=True)
    result = subprocess.run(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    with open(os.path.join(out, "bench_load.log"), "w") as log:
        log.write(result.stdout)
    path = os.path.join(out, "bench_load.json")
    if result.returncode != 0 or not os.path.isfile(path):
        return result.returncode or 1, {}
    with open(path) as handle:
        return 0, json.load(handle)


def main(argv=None) -> int:
    """Run the configurations and print the table; returns the exit code."""
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--detector", required=True, help="YOLOv8-architecture ONNX (random-yolov8)")
    parser.add_argument("--hmr", required=True, help="exported SMPLer-X ONNX (export-hmr)")
    parser.add_argument("--hmr-body-only", default=None,
                        help="body-only export of the same checkpoint (export-hmr --without-hands), for the "
                             "'body-only HMR' configurations (skipped without it)")
    parser.add_argument("--detector-int8", default=None, help="the detector's INT8 file (quantize-int8 detector)")
    parser.add_argument("--hmr-int8", default=None, help="--hmr's INT8 file (quantize-int8 hmr)")
    parser.add_argument("--hmr-body-only-int8", default=None, help="--hmr-body-only's INT8 file")
    parser.add_argument("--rounds", type=int, default=1, help="run the chosen configurations this many times in turn")
    parser.add_argument("--body-model", default=None, help="SMPL-X .npz (default: the dense stand-in)")
    parser.add_argument("--duration", type=float, default=60.0)
    parser.add_argument("--fps", type=float, default=30.0)
    parser.add_argument("--max-goal-age-s", type=float, default=5.0)
    parser.add_argument("--only", nargs="*", default=None, help="run only these configurations (names)")
    parser.add_argument("--out", default="out/bench_frame")
    args = parser.parse_args(argv)
    if args.body_model is None:
        from leapnbv_stand_ins.files import ensure_stand_in_smplx_dense

        args.body_model = ensure_stand_in_smplx_dense()
    optional = tuple(p for p in (args.hmr_body_only, args.detector_int8, args.hmr_int8, args.hmr_body_only_int8) if p)
    for path in (args.detector, args.hmr, args.body_model) + optional:
        if not os.path.isfile(path):
            print(f"bench_frame: model file not found: {path}", file=sys.stderr)
            return 2
    from leapnbv_perception.hmr import hands_estimated, read_export_metadata

    for flag, path in (("--hmr-body-only", args.hmr_body_only), ("--hmr-body-only-int8", args.hmr_body_only_int8)):
        if path and hands_estimated(read_export_metadata(path)):
            print(f"bench_frame: {flag} {path} is not a body-only export (its metadata has "
                  "no leapnbv.hands=not_estimated; export it with export-hmr --without-hands)", file=sys.stderr)
            return 2
    known = list(CONFIGURATIONS) + list(BODY_ONLY_CONFIGURATIONS) + [INT8_PREFIX + n for n in INT8_OF]
    unknown = [name for name in args.only or () if name not in known]
    if unknown:
        print(f"bench_frame: unknown configuration(s) {unknown}; known: {known}", file=sys.stderr)
        return 2
    everything = [(name, settings, args.hmr, args.detector) for name, settings in CONFIGURATIONS.items()]
    everything += [(name, settings, args.hmr_body_only, args.detector)
                   for name, settings in BODY_ONLY_CONFIGURATIONS.items()]
    for name in INT8_OF:
        settings = CONFIGURATIONS.get(name) or BODY_ONLY_CONFIGURATIONS[name]
        hmr_int8 = args.hmr_int8 if name in CONFIGURATIONS else args.hmr_body_only_int8
        everything.append((INT8_PREFIX + name, settings, hmr_int8 if args.detector_int8 else None, args.detector_int8))
    chosen = [item for item in everything if not args.only or item[0] in args.only]
    rows = []
    for round_index in range(max(1, args.rounds)):
        for name, settings, hmr, detector in chosen:
            if hmr is None:
                if round_index == 0:
                    print(f"[bench_frame] {name}: skipped (its model files were not given)", flush=True)
                continue
            index = [item[0] for item in everything].index(name)
            folder = os.path.join(args.out, f"config_{index}" + (f"_round{round_index}" if args.rounds > 1 else ""))
            code, r = run_configuration(name, settings, args, folder, hmr, detector)
            if code:
                print(f"bench_frame: '{name}' failed (bench_load exit {code}); log in {folder}", file=sys.stderr)
                return 3
            stages = r["stage_breakdown"]
            rows.append((name, round_index, r["goal_rate_hz"], r["latency_ms"]["whole_run"],
                         stages["detections"]["compute_ms_p50"], stages["human_mesh"]["compute_ms_p50"],
                         r["cpu_ms_per_goal"], r["uptime_before"], r["uptime_after"]))
    fp32_p50 = {(name, k): latency["p50"] for name, k, _, latency, *_ in rows}
    print(f"\n== whole frame, real architectures (random weights), {args.fps:.0f} FPS camera, {args.duration:.0f} s "
          f"per configuration, {os.cpu_count()} cores; CPU: {instruction_set()}")
    print("| configuration | round | goals/s | latency p50 / p95 ms | INT8 p50 / FP32 namesake's p50 | "
          "detector compute p50 ms | HMR compute p50 ms | CPU ms per goal (det / hmr / raster / ground / nbv) | "
          "load before -> after |")
    print("|---|---|---|---|---|---|---|---|---|")
    for name, k, rate, latency, det, hmr, cpu, before, after in rows:
        cpu_text = " / ".join(f"{cpu.get(n, float('nan')):.0f}" for n in
                              ("detector_node", "hmr_node", "raster_node", "ground_node", "nbv_node"))
        namesake = fp32_p50.get((name[len(INT8_PREFIX):], k)) if name.startswith(INT8_PREFIX) else None
        ratio = f"{latency['p50'] / namesake:.2f}" if namesake else ""
        print(f"| {name} | {k + 1} | {rate:.2f} | {latency['p50']:.0f} / {latency['p95']:.0f} | {ratio} | {det:.0f} | "
              f"{hmr:.0f} | {cpu_text} | {before.split()[0]} -> {after.split()[0]} |")
    print("paper (Jetson Xavier NX, TensorRT FP16): 276 ms per frame, HMR 12 ms")
    return 0


if __name__ == "__main__":
    sys.exit(main())
