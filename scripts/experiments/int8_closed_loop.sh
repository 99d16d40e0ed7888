#!/usr/bin/env bash
# The closed loop with the learned HMR engine in FP32 and in INT8, on the same benchmark scenes (docs/INT8.md).
# Usage: scripts/experiments/int8_closed_loop.sh [SCENES (default 20)] [OUT (default out/int8_closed_loop)] [INT8_ONNX]
# As scripts/experiments/learned_perception.sh: the synthetic student (tools/results/synthetic_student/) run by
# onnxruntime in hmr_node, the simulator's person boxes, the dense stand-in body; its INT8 file is written by
# quantize-int8 (its defaults for this CPU) into OUT when not given. Runs OUT/fp32 and OUT/int8, then
# scripts/experiments/int8_closed_loop_table.py OUT prints success, coverage, area and PA-MPVPE for both.
set -euo pipefail
ROOT=$(cd "$(dirname "${BASH_SOURCE[0]}")/../.." && pwd)
cd "$ROOT"
SCENES=${1:-20}
OUT=${2:-out/int8_closed_loop}
FP32=tools/results/synthetic_student/smpler_x_t32_synthetic_student.onnx
INT8=${3:-$OUT/smpler_x_t32_synthetic_student.int8.onnx}
mkdir -p "$OUT"
if [ ! -f "$INT8" ]; then
  PYTHONPATH=tools scripts/env.sh python -m leapnbv_model_tools quantize-int8 hmr "$FP32" --out "$INT8" 2>&1 \
    | grep -v -i warning | tee "$OUT/quantize.log"
fi
BODY=$(scripts/env.sh python -c "from leapnbv_stand_ins.files import ensure_stand_in_smplx_dense as e; print(e())")
for variant in int8 fp32; do
  MODEL=$FP32
  [ "$variant" = int8 ] && MODEL=$INT8
  scripts/experiments/evaluate.sh --scenes "$SCENES" --out "$OUT/$variant" --perception onnxruntime \
    --detector-backend ground_truth --hmr-model "$MODEL" --body-model "$BODY" --scene-body-model "$BODY" ${EVAL_ARGS:-}
done
scripts/env.sh python scripts/experiments/int8_closed_loop_table.py "$OUT"
