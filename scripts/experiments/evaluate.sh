#!/usr/bin/env bash
# Closed-loop evaluation of LEAP-NBV on the benchmark scenes (graph started once, simulator in process).
# Usage: scripts/experiments/evaluate.sh [--scenes 50] [--out out/evaluation] [--workers N] [--domain-base D]
#        [--perception onnxruntime --detector-model M --hmr-model M --body-model M] [--seed-offset K]
#        [--set node.param=value]
# Writes results.md / results.json / plots, chosen_views.json, evaluation.md and run.json to --out.
# --workers N: N processes with a graph each, each on its own ROS domain: D + k with --domain-base D
# (or $LEAPNBV_EVAL_DOMAIN_BASE=D), else N free domains in 1..101 claimed with lock files in
# $TMPDIR/leapnbv-ros-domains/ (as the test suite does) for the run. Their logs are in
# --out/workers/worker_<k>/. The tables and chosen views are the same as with one worker.
# One worker: domain D when given, else $ROS_DOMAIN_ID when set, else a free domain claimed the same way
# (printed), so a run never shares a domain with another graph on this machine.
set -euo pipefail
ROOT=$(cd "$(dirname "${BASH_SOURCE[0]}")/../.." && pwd)
cd "$ROOT"
exec scripts/env.sh python -m leapnbv_evaluation.cli "$@"
