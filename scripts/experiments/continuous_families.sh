#!/usr/bin/env bash
# Continuous closed-loop episodes per family: the robot drives while the graph plans from every frame, on sim time.
# Usage: scripts/experiments/continuous_families.sh [SCENES (default 40)] [OUT (default out/continuous)] [RUNS...]
# A run is a family name (furnished, corridor, two_people, three_people, walking, ... : any --room of
# leapnbv_evaluation.cli, with the obstacle map) or <family>:nomap (the planner knows only what the frames show);
# default: furnished furnished:nomap corridor. An unknown family fails before any run starts. Each run is one
# `python -m leapnbv_evaluation.cli --continuous` (lockstep clock) into OUT/<run> (continuous.md, continuous.json,
# logs/); then scripts/experiments/continuous_table.py OUT prints the table of all runs. Extra CLI arguments in
# $CONTINUOUS_ARGS (e.g. "--camera-rate 10 --time-limit 30"); default camera 5 Hz, limit 30 s (CPU: about
# 0.7 s of wall time per frame on two shared cores).
set -euo pipefail
ROOT=$(cd "$(dirname "${BASH_SOURCE[0]}")/../.." && pwd)
cd "$ROOT"
SCENES=${1:-40}
OUT=${2:-out/continuous}
shift $(( $# > 2 ? 2 : $# ))
RUNS=("$@")
if [ ${#RUNS[@]} -eq 0 ]; then
  RUNS=(furnished furnished:nomap corridor)
fi
ROOMS=$(scripts/env.sh python -c "from leapnbv_evaluation.benchmark_set import ROOMS; print(' '.join(ROOMS))")
for run in "${RUNS[@]}"; do
  case " $ROOMS " in
    *" ${run%%:*} "*) ;;
    *) echo "[continuous] unknown family ${run%%:*} (known: $ROOMS)" >&2; exit 2 ;;
  esac
  if [ "$run" != "${run%%:*}" ] && [ "${run#*:}" != nomap ]; then
    echo "[continuous] unknown run $run (a family, or <family>:nomap)" >&2; exit 2
  fi
done
mkdir -p "$OUT"
for run in "${RUNS[@]}"; do
  family=${run%%:*}
  extra=()
  name=$family
  if [ "$run" != "$family" ]; then
    extra=(--no-obstacle-map)
    name="${family}_nomap"
  fi
  # shellcheck disable=SC2086
  scripts/env.sh python -m leapnbv_evaluation.cli --continuous --room "$family" --scenes "$SCENES" \
    --out "$OUT/$name" "${extra[@]}" ${CONTINUOUS_ARGS:---camera-rate 5 --time-limit 30} \
    > "$OUT/$name.log" 2>&1 || echo "[continuous] $name failed (see $OUT/$name.log)"
  echo "[continuous] $name done"
done
scripts/env.sh python scripts/experiments/continuous_table.py "$OUT"
