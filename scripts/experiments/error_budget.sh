#!/usr/bin/env bash
# The error budget: the closed loop with ground-truth perception made worse by a known amount, per corruption
# and level, with the mesh registration off (the graph's default) and on.
# Usage: scripts/experiments/error_budget.sh [SCENES (default 40)] [OUT (default out/error_budget)] [CORRUPTIONS...]
# A corruption is one of: mesh_shift mesh_depth mesh_pa box_jitter box_grow box_truncate second_person
# (default: all); its levels are in LEVELS below. Each (corruption, level, registration) is one
# scripts/experiments/evaluate.sh run into OUT/<corruption>/<level>/<registration_off|registration_on> on the
# first SCENES furnished scenes (second_person: the two_people and three_people families, no corruption).
# The corruptions are the ground-truth backends' truth_* parameters (leapnbv_perception.truth_corruption),
# seeded by each frame's stamp, so a rerun corrupts every frame the same way. Then
# scripts/experiments/error_budget_table.py OUT prints the table and writes OUT/error_budget.png.
# Missed detections are not in this one-shot budget: the one frame a scene plans from either has its box or
# not (a miss is a scene without a plan); they belong to the continuous loop (detector_node.truth_miss_share).
set -euo pipefail
ROOT=$(cd "$(dirname "${BASH_SOURCE[0]}")/../.." && pwd)
cd "$ROOT"
SCENES=${1:-40}
OUT=${2:-out/error_budget}
shift $(( $# > 2 ? 2 : $# ))
CORRUPTIONS=("$@")
if [ ${#CORRUPTIONS[@]} -eq 0 ]; then
  CORRUPTIONS=(none mesh_shift mesh_depth mesh_pa box_jitter box_grow box_truncate second_person)
fi
declare -A PARAM=([mesh_shift]=hmr_node.truth_mesh_shift [mesh_depth]=hmr_node.truth_mesh_depth_error
  [mesh_pa]=hmr_node.truth_mesh_pa_mpvpe_mm [box_jitter]=detector_node.truth_box_jitter
  [box_grow]=detector_node.truth_box_grow [box_truncate]=detector_node.truth_box_truncate)
declare -A LEVELS=([none]=0 [mesh_shift]="0.05 0.1 0.2 0.3" [mesh_depth]="0.1 0.2 0.4" [mesh_pa]="50.0 100.0 150.0"
  [box_jitter]="0.05 0.1 0.2" [box_grow]="0.25 0.5" [box_truncate]="0.2 0.4" [second_person]="two_people three_people")
for corruption in "${CORRUPTIONS[@]}"; do
  [ -n "${LEVELS[$corruption]:-}" ] || { echo "[error_budget] unknown corruption $corruption" >&2; exit 2; }
done
for corruption in "${CORRUPTIONS[@]}"; do
  for level in ${LEVELS[$corruption]}; do
    for registration in off on; do
      dir=$OUT/$corruption/$level/registration_$registration
      mkdir -p "$(dirname "$dir")"
      args=(--scenes "$SCENES" --out "$dir" --set "raster_node.registration_enabled=$([ $registration = on ] && echo true || echo false)")
      if [ "$corruption" = second_person ]; then
        args+=(--room "$level")
      elif [ "$corruption" != none ]; then
        args+=(--set "${PARAM[$corruption]}=$level")
      fi
      scripts/experiments/evaluate.sh "${args[@]}" > "$dir.log" 2>&1 \
        || echo "[error_budget] $corruption $level registration $registration failed (see $dir.log)"
      echo "[error_budget] $corruption $level registration $registration: $(tail -1 "$dir.log")"
    done
  done
done
scripts/env.sh python scripts/experiments/error_budget_table.py "$OUT"
