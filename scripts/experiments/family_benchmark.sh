#!/usr/bin/env bash
# The benchmark families at the robot's mounting height, leap_nbv with the paper's S_o and with the mesh S_o.
# Usage: scripts/experiments/family_benchmark.sh [SCENES (default 40: every committed seed)] [OUT (default out/families)] [FAMILIES...]
# Each family runs twice through scripts/experiments/evaluate.sh (several rings, reachability on): OUT/<family>/paper
# (score_terms [visibility, area, occlusion, travel]: the paper's S_o over the observed points) and
# OUT/<family>/mesh (the default terms [visibility, area, body_occlusion, travel]); then scripts/experiments/family_table.py OUT prints the
# table (success, coverage before -> after, travel) per family and method. Pass extra evaluate.sh arguments in
# $FAMILY_EVAL_ARGS (e.g. "--workers 2").
set -euo pipefail
ROOT=$(cd "$(dirname "${BASH_SOURCE[0]}")/../.." && pwd)
cd "$ROOT"
SCENES=${1:-40}
OUT=${2:-out/families}
shift $(( $# > 2 ? 2 : $# ))
FAMILIES=("$@")
if [ ${#FAMILIES[@]} -eq 0 ]; then
  FAMILIES=(furnished open corner corridor near_wall heavy_occlusion far camera_0.6 camera_1.8 noise_3x)
fi
COMMON=(--set nbv_node.reachability=true --set nbv_node.num_rings=3)
for family in "${FAMILIES[@]}"; do
  scripts/experiments/evaluate.sh --scenes "$SCENES" --room "$family" --out "$OUT/$family/paper" "${COMMON[@]}" \
    --set "nbv_node.score_terms=[visibility,area,occlusion,travel]" \
    ${FAMILY_EVAL_ARGS:-} > "$OUT.$family.paper.log" 2>&1 || echo "[families] $family paper failed (see $OUT.$family.paper.log)"
  scripts/experiments/evaluate.sh --scenes "$SCENES" --room "$family" --out "$OUT/$family/mesh" "${COMMON[@]}" \
    ${FAMILY_EVAL_ARGS:-} > "$OUT.$family.mesh.log" 2>&1 || echo "[families] $family mesh failed (see $OUT.$family.mesh.log)"
  echo "[families] $family done"
done
scripts/env.sh python scripts/experiments/family_table.py "$OUT"
