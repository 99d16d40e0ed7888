#!/usr/bin/env bash
# The main job: set up (idempotent), then run the five-node graph on a sample bag and one
# closed-loop episode, leaving reports in out/demo/. Extra arguments go to the bag demo
# (e.g. --perception onnxruntime --detector-model yolov8s.onnx --hmr-model student.onnx --body-model SMPLX_NEUTRAL.npz).
set -euo pipefail
ROOT=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
cd "$ROOT"
bash scripts/setup.sh
# Own DDS domain, so a demo never talks to another graph on this machine.
export ROS_DOMAIN_ID=${ROS_DOMAIN_ID:-$(( 100 + $$ % 50 ))}
started=$(date +%s)
scripts/env.sh python -m leapnbv_evaluation.demo --out out/demo "$@"
echo "[demo] one closed-loop episode (the robot moves to the chosen view and looks again)"
scripts/env.sh python -m leapnbv_evaluation.cli --scenes 1 --out out/demo/closed_loop
echo "[demo] finished in $(( $(date +%s) - started )) s; open out/demo/report.md and out/demo/closed_loop/results.md"
