#!/usr/bin/env bash
# Run a command in the tools environment with leapnbv_model_tools and the ROS-free perception core
# importable: tools/run.sh python -m leapnbv_model_tools export-hmr ...   (sets the env up if absent)
set -euo pipefail
ROOT=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
VENV=$(bash "$ROOT/tools/setup_tools_env.sh")
export PYTHONPATH=$ROOT/tools:$ROOT/src/leapnbv_perception:$ROOT/src/leapnbv_common:$ROOT/src/leapnbv_stand_ins${PYTHONPATH:+:$PYTHONPATH}
exec "$VENV/bin/$1" "${@:2}"
