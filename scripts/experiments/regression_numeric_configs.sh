#!/usr/bin/env bash
# The regression on bags/sample_a, bags/sample_b and the exported-s32 golden in several numeric configurations,
# and with a changed weight (which must fail). CI runs one configuration per golden (tests/test_graph_regression.py,
# tools/tests/test_export_in_graph.py); this runs all of them and prints one line per run.
#
#   bash scripts/experiments/regression_numeric_configs.sh [OUT]     (needs the tools environment for the s32 runs)
#
# The ground-truth bags run no engine (their perception is the simulator's truth): there the numeric configurations
# are numpy's (OpenBLAS threads, and its AVX2 kernels where the CPU has AVX2); the engine settings are set anyway.
# Exit 1 if a configuration fails or the changed weight passes.
set -uo pipefail
ROOT=$(cd "$(dirname "${BASH_SOURCE[0]}")/../.." && pwd)
OUT=${1:-$ROOT/out/regression_numeric_configs}
export ROS_DOMAIN_ID=${ROS_DOMAIN_ID:-61}
mkdir -p "$OUT"
cd "$ROOT" || exit 2
status=0

run() {  # name expected_rc env-assignments... -- regression args...
  local name=$1 expected=$2; shift 2
  local envs=()
  while [ "$1" != "--" ]; do envs+=("$1"); shift; done; shift
  local started=$SECONDS
  env "${envs[@]}" scripts/env.sh python -m leapnbv_bringup.regression "$@" --out "$OUT/$name" >"$OUT/$name.log" 2>&1
  local rc=$?
  local verdict=ok; [ "$rc" = "$expected" ] || { verdict=UNEXPECTED; status=1; }
  printf '%-44s rc=%s (want %s) %-10s %4ss  %s\n' "$name" "$rc" "$expected" "$verdict" $((SECONDS - started)) \
    "$(grep '^\[regression\] \(PASS\|FAIL\)' "$OUT/$name.log" | tail -1)"
}

ENGINE_CONFIGS=(
  "threads_2:--set hmr_node.intra_op_threads=2 --set detector_node.intra_op_threads=2"
  "threads_4_parallel:--set hmr_node.intra_op_threads=4 --set hmr_node.parallel_execution=true --set hmr_node.inter_op_threads=2"
  "optimization_disable:--set hmr_node.graph_optimization=disable"
  "optimization_basic:--set hmr_node.graph_optimization=basic"
  "optimization_extended:--set hmr_node.graph_optimization=extended"
  "last_bit_nudged:--set hmr_node.backend=onnxruntime_last_bit_nudged"
)

for bag in sample_a sample_b; do
  run "${bag}_default" 0 LEAPNBV_NOTHING=1 -- "bags/$bag"
  run "${bag}_openblas_1_thread" 0 OPENBLAS_NUM_THREADS=1 -- "bags/$bag"
  run "${bag}_openblas_2_threads" 0 OPENBLAS_NUM_THREADS=2 -- "bags/$bag"
  if grep -qw avx2 /proc/cpuinfo 2>/dev/null; then
    run "${bag}_openblas_haswell_kernels" 0 OPENBLAS_CORETYPE=Haswell -- "bags/$bag"
  fi
  run "${bag}_changed_weight" 1 LEAPNBV_NOTHING=1 -- "bags/$bag" --set nbv_node.weight_area=0.15
done

if VENV=$(bash tools/setup_tools_env.sh --path 2>/dev/null); then
  MODEL=$OUT/smpler_x_s32.onnx
  BODY=$(scripts/env.sh python -c "from leapnbv_stand_ins.files import ensure_stand_in_smplx_dense as e; print(e())")
  PYTHONPATH=$ROOT/tools:$ROOT/src/leapnbv_perception:$ROOT/src/leapnbv_common:$ROOT/src/leapnbv_stand_ins \
    "$VENV/bin/python" - "$OUT" <<'EOF' || exit 2
import sys, numpy as np, onnx, torch
from onnx import numpy_helper
from leapnbv_model_tools.checkpoint import random_smplerx, save_official
from leapnbv_model_tools.export import main as export_main
out = sys.argv[1]
torch.manual_seed(0)  # the checkpoint tools/tests/test_export_in_graph.py makes
checkpoint = save_official(random_smplerx("s32", 0), f"{out}/smpler_x_s32.pth.tar")
assert export_main(["--checkpoint", checkpoint, "--variant", "s32", "--out", f"{out}/smpler_x_s32.onnx"]) == 0
graph = onnx.load(f"{out}/smpler_x_s32.onnx")
# The body pose head's weights with noise of 5 % of their spread, as tools/tests/test_export_in_graph.py changes them.
weights = next(t for t in graph.graph.initializer if t.name == "model.body_regressor.body_pose_out.0.weight")
values = numpy_helper.to_array(weights)
noise = np.random.default_rng(0).normal(0.0, 0.05 * float(values.std()), values.shape).astype(np.float32)
weights.CopyFrom(numpy_helper.from_array(values + noise, weights.name))
onnx.save(graph, f"{out}/smpler_x_s32_changed.onnx")
EOF
  S32=(bags/sample_a --golden bags/sample_a.smpler_x_s32_random.golden.npz --set hmr_node.backend=onnxruntime
       --body-model "$BODY")
  run "s32_default" 0 LEAPNBV_NOTHING=1 -- "${S32[@]}" --hmr-model "$MODEL"
  for config in "${ENGINE_CONFIGS[@]}"; do
    # shellcheck disable=SC2086 # the --set list splits into words on purpose
    run "s32_${config%%:*}" 0 LEAPNBV_NOTHING=1 -- "${S32[@]}" --hmr-model "$MODEL" ${config#*:}
  done
  run "s32_changed_weight" 1 LEAPNBV_NOTHING=1 -- "${S32[@]}" --hmr-model "$OUT/smpler_x_s32_changed.onnx"
else
  echo "no tools environment (bash tools/setup_tools_env.sh): the s32 runs are skipped"
fi
exit $status
