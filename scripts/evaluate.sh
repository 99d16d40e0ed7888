#!/usr/bin/env bash
# Closed-loop evaluation of LEAP-NBV on the benchmark scenes (graph started once, simulator in process).
# Usage: scripts/evaluate.sh [--scenes 50] [--out out/evaluation] [--perception onnxruntime
#        --detector-model M --hmr-model M --body-model M] [--seed-offset K] [--set node.param=value]
# Writes results.md / results.json / plots, chosen_views.json and evaluation.md to --out.
set -euo pipefail
ROOT=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
cd "$ROOT"
exec scripts/env.sh python -m leapnbv_evaluation.evaluation "$@"
