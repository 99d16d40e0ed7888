#!/usr/bin/env bash
# The closed loop with learned perception beside ground-truth perception, on the same benchmark scenes.
# Usage: scripts/experiments/learned_perception.sh [SCENES (default 20)] [OUT (default out/learned_perception)] [HMR_ONNX]
# The HMR engine is the synthetic-domain student (default tools/results/synthetic_student/, trained on
# renders of the dense stand-in body: a stand-in, not a model for real images) run by onnxruntime in
# hmr_node; the detector publishes the simulator's person boxes (no trained detector here); the scenes and
# the HMR tail use the dense stand-in body (stand_in_smplx_dense), so PA-MPVPE has vertex correspondence.
# Runs the evaluation twice (OUT/learned, OUT/truth), then scripts/experiments/learned_perception_table.py OUT prints
# coverage, area and PA-MPVPE before -> after and success for both. Extra evaluate.sh arguments: $EVAL_ARGS.
set -euo pipefail
ROOT=$(cd "$(dirname "${BASH_SOURCE[0]}")/../.." && pwd)
cd "$ROOT"
SCENES=${1:-20}
OUT=${2:-out/learned_perception}
MODEL=${3:-tools/results/synthetic_student/smpler_x_t32_synthetic_student.onnx}
if [ ! -f "$MODEL" ]; then
  echo "[learned_perception] HMR model not found: $MODEL" >&2
  exit 2
fi
BODY=$(scripts/env.sh python -c "from leapnbv_stand_ins.files import ensure_stand_in_smplx_dense as e; print(e())")
scripts/experiments/evaluate.sh --scenes "$SCENES" --out "$OUT/learned" --perception onnxruntime --detector-backend ground_truth \
  --hmr-model "$MODEL" --body-model "$BODY" --scene-body-model "$BODY" ${EVAL_ARGS:-}
scripts/experiments/evaluate.sh --scenes "$SCENES" --out "$OUT/truth" --body-model "$BODY" --scene-body-model "$BODY" ${EVAL_ARGS:-}
scripts/env.sh python scripts/experiments/learned_perception_table.py "$OUT"
