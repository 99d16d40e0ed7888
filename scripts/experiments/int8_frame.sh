#!/usr/bin/env bash
# The whole frame with the INT8 engines beside FP32, in one command (docs/INT8.md, "Speed").
# Usage: scripts/experiments/int8_frame.sh [MODELS (default ~/.cache/leapnbv/int8)] [OUT (default out/int8_frame)]
# Builds what is missing in MODELS (tools environment: the random-weight YOLOv8s and s32 full and body-only
# exports; robot environment: their INT8 files by quantize-int8 with its defaults for this CPU), then runs
# scripts/bench/bench_frame.py with the full-cost and the recommended configurations, FP32 and INT8, in turn for
# $ROUNDS rounds (default 2), $DURATION s each (default 40), and writes OUT/table.md (the CPU's instruction set,
# uptime before and after each configuration, p50 / p95, each INT8 row against its FP32 namesake of the same round).
set -euo pipefail
ROOT=$(cd "$(dirname "${BASH_SOURCE[0]}")/../.." && pwd)
cd "$ROOT"
MODELS=${1:-$HOME/.cache/leapnbv/int8}
OUT=${2:-out/int8_frame}
ROUNDS=${ROUNDS:-2}
DURATION=${DURATION:-40}
mkdir -p "$MODELS" "$OUT"
[ -f "$MODELS/yolov8s_random.onnx" ] || tools/run.sh python -m leapnbv_model_tools random-yolov8 --out "$MODELS/yolov8s_random.onnx"
[ -f "$MODELS/s32.pth.tar" ] || tools/run.sh python -m leapnbv_model_tools random-checkpoint --variant s32 --out "$MODELS/s32.pth.tar"
[ -f "$MODELS/s32.onnx" ] || tools/run.sh python -m leapnbv_model_tools export-hmr --checkpoint "$MODELS/s32.pth.tar" \
  --variant s32 --out "$MODELS/s32.onnx"
[ -f "$MODELS/s32_body_only.onnx" ] || tools/run.sh python -m leapnbv_model_tools export-hmr \
  --checkpoint "$MODELS/s32.pth.tar" --variant s32 --without-hands --out "$MODELS/s32_body_only.onnx"
for pair in "detector yolov8s_random" "hmr s32" "hmr s32_body_only"; do
  set -- $pair
  [ -f "$MODELS/$2.int8.onnx" ] || PYTHONPATH=tools scripts/env.sh python -m leapnbv_model_tools quantize-int8 "$1" \
    "$MODELS/$2.onnx" --out "$MODELS/$2.int8.onnx" 2>&1 | grep -v -i "warning" | tee "$OUT/quantize_$2.log"
done
FULL="1 thread each"
RECOMMENDED="body-only HMR 2 threads, detector 1 thread, detect every 5th frame"
scripts/env.sh python scripts/bench/bench_frame.py --detector "$MODELS/yolov8s_random.onnx" --hmr "$MODELS/s32.onnx" \
  --hmr-body-only "$MODELS/s32_body_only.onnx" --detector-int8 "$MODELS/yolov8s_random.int8.onnx" \
  --hmr-int8 "$MODELS/s32.int8.onnx" --hmr-body-only-int8 "$MODELS/s32_body_only.int8.onnx" \
  --duration "$DURATION" --rounds "$ROUNDS" --out "$OUT" \
  --only "$FULL" "INT8 engines, $FULL" "$RECOMMENDED" "INT8 engines, $RECOMMENDED" ${BENCH_ARGS:-} | tee "$OUT/bench_frame.log"
{ echo "uptime at the end: $(uptime)"; sed -n '/^== whole frame/,$p' "$OUT/bench_frame.log"; } > "$OUT/table.md"
cat "$OUT/table.md"
