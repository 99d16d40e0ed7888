#!/usr/bin/env bash
# Device check: TensorRT FP32 and FP16 engines of the exported SMPLer-X s32 student and of YOLOv8s,
# compared with onnxruntime FP32, with per-engine latency; on a Jetson (power rails present), the
# whole graph's joules per frame on a sample bag. Minutes, and nothing but the repository and the models.
#
#   scripts/device/device_check.sh --s32 models/smplerx_student.onnx --yolo models/yolov8s.onnx \
#       [--plan models/smplerx_student.precision_plan.json] [--cache DIR] [--runs 50] \
#       [--body-model models/SMPLX_NEUTRAL.npz] [--bag bags/sample_a] [--seconds 30] [--json out.json] [--no-gpu]
#
# The same paths can come from the environment: LEAPNBV_S32_ONNX, LEAPNBV_YOLO_ONNX,
# LEAPNBV_PRECISION_PLAN, LEAPNBV_ENGINE_CACHE, LEAPNBV_BODY_MODEL. LEAPNBV_PYTHON picks the
# interpreter (default python3; inside the Jetson image, the ROS environment is sourced first).
#
# "No GPU" mode: without a GPU or without TensorRT (or with --no-gpu), it prints what it would run,
# with the tolerances, says which inputs are missing, and exits 0: there is nothing to fail here.
# Exit status otherwise: 0 when every engine is within tolerance and the graph step (when it ran)
# produced frames; 1 when a check failed; 2 for a usage error or a missing model.
set -euo pipefail
ROOT=$(cd "$(dirname "${BASH_SOURCE[0]}")/../.." && pwd)
log() { printf '[device-check] %s\n' "$*"; }

S32=${LEAPNBV_S32_ONNX:-}
YOLO=${LEAPNBV_YOLO_ONNX:-}
PLAN=${LEAPNBV_PRECISION_PLAN:-}
CACHE=${LEAPNBV_ENGINE_CACHE:-}
BODY=${LEAPNBV_BODY_MODEL:-}
BAG=$ROOT/bags/sample_a
RUNS=50
SECONDS_MEASURED=30
JSON=""
FORCE_NO_GPU=0
while [ $# -gt 0 ]; do
  case "$1" in
    --s32) S32=$2; shift 2 ;;
    --yolo) YOLO=$2; shift 2 ;;
    --plan) PLAN=$2; shift 2 ;;
    --cache) CACHE=$2; shift 2 ;;
    --body-model) BODY=$2; shift 2 ;;
    --bag) BAG=$2; shift 2 ;;
    --runs) RUNS=$2; shift 2 ;;
    --seconds) SECONDS_MEASURED=$2; shift 2 ;;
    --json) JSON=$2; shift 2 ;;
    --no-gpu) FORCE_NO_GPU=1; shift ;;
    -h|--help) sed -n '2,20p' "$0"; exit 0 ;;
    *) echo "[device-check] unknown argument: $1 (see --help)" >&2; exit 2 ;;
  esac
done
PYTHON=${LEAPNBV_PYTHON:-python3}
if [ -f /opt/ros/jazzy/setup.bash ] && [ -f /opt/leapnbv/install/setup.bash ]; then
  # inside the Jetson image
  set +u
  # shellcheck disable=SC1091
  . /opt/ros/jazzy/setup.bash
  # shellcheck disable=SC1091
  . /opt/leapnbv/install/setup.bash
  set -u
fi

# What is here: a GPU, TensorRT, the power rails, ROS 2 (for the graph step).
gpu=""
if [ -e /dev/nvhost-ctrl-gpu ] || [ -e /dev/nvgpu/igpu0/ctrl ]; then
  gpu="Jetson integrated GPU"
elif command -v nvidia-smi >/dev/null 2>&1 && nvidia-smi -L >/dev/null 2>&1; then
  gpu=$(nvidia-smi -L | head -1)
fi
trt=$("$PYTHON" -c 'import tensorrt; print(tensorrt.__version__)' 2>/dev/null || true)
rails=""
for device in /sys/bus/i2c/devices/*; do
  grep -qs ina3221 "$device/name" || continue
  for label in "$device"/hwmon/hwmon*/in*_label "$device"/iio:device*/rail_name_*; do
    [ -r "$label" ] || continue
    name=$(cat "$label" 2>/dev/null || true)
    case "$name" in ""|"sum of shunt voltages"|NC) continue ;; esac
    rails="${rails:+$rails, }$name"
  done
done
ros2_cli=$(command -v ros2 || true)

describe_plan() {
  log "engines, for each model in {s32: ${S32:-<not given>}, yolov8s: ${YOLO:-<not given>}}:"
  log "  1. onnxruntime FP32 (CPU) on seeded uniform [0,1) inputs: the reference"
  log "  2. TensorRT FP32 engine (engine cache: ${CACHE:-\$LEAPNBV_ENGINE_CACHE or ~/.cache/leapnbv/tensorrt}), outputs vs reference:"
  log "     relative L2 error <= 1e-3 per output"
  log "  3. TensorRT FP16 engine$( [ -n "$PLAN" ] && printf ' with the precision plan %s (s32)' "$PLAN" ), outputs vs reference:"
  log "     relative L2 error <= 2e-2 per output (and every value finite)"
  log "  4. latency of each engine: median and p95 of $RUNS runs after 10 warm-up runs (copies included)"
  log "graph, only where the board's INA3221 rails exist (a Jetson): ros2 launch of the graph (power_node on)"
  log "  with these models (body model: ${BODY:-<not given>}), ros2 bag play --loop ${BAG}, ${SECONDS_MEASURED} s measured:"
  log "  joules per frame = energy of VDD_IN (and VDD_CPU_GPU_CV) / view_candidates published; idle power beside it"
}

missing=()
for pair in "s32:$S32" "yolov8s:$YOLO"; do
  name=${pair%%:*}; path=${pair#*:}
  if [ -z "$path" ]; then missing+=("$name ONNX not given (--${name/yolov8s/yolo} or env)"); elif [ ! -f "$path" ]; then missing+=("$name ONNX not found: $path"); fi
done
[ -z "$PLAN" ] || [ -f "$PLAN" ] || missing+=("precision plan not found: $PLAN")

if [ "$FORCE_NO_GPU" = 1 ] || [ -z "$gpu" ] || [ -z "$trt" ]; then
  why=()
  [ "$FORCE_NO_GPU" = 1 ] && why+=("--no-gpu given")
  [ -z "$gpu" ] && why+=("no GPU found (no /dev/nvhost-ctrl-gpu, no nvidia-smi device)")
  [ -z "$trt" ] && why+=("TensorRT's Python package is not importable by $PYTHON")
  log "no-GPU mode: $(IFS=';'; echo "${why[*]}")"
  log "on a machine with a GPU and TensorRT this check would run:"
  describe_plan
  log "power rails here: ${rails:-none} -> the graph step would $( [ -n "$rails" ] && echo run || echo be skipped )"
  for item in "${missing[@]}"; do log "note: $item"; done
  log "nothing was run; exit 0"
  exit 0
fi

if [ ${#missing[@]} -gt 0 ]; then
  for item in "${missing[@]}"; do echo "[device-check] ERROR: $item" >&2; done
  exit 2
fi
log "GPU: $gpu; TensorRT $trt; Python $("$PYTHON" -c 'import sys; print(sys.version.split()[0])'); rails: ${rails:-none}"
args=(--s32 "$S32" --yolo "$YOLO" --runs "$RUNS")
[ -n "$PLAN" ] && args+=(--plan "$PLAN")
[ -n "$CACHE" ] && args+=(--cache "$CACHE")
status=0
"$PYTHON" "$ROOT/scripts/device/device_check.py" engines "${args[@]}" ${JSON:+--json "${JSON%.json}.engines.json"} || status=1
if [ -z "$rails" ]; then
  log "graph: skipped (no power rails: not a Jetson, or /sys not visible in this container)"
elif [ -z "$ros2_cli" ]; then
  log "graph: skipped (no ros2 command: run this inside the Jetson image, docker/jetson/README.md)"
elif [ -z "$BODY" ] || [ ! -f "$BODY" ]; then
  log "graph: skipped (the hmr node needs the SMPL-X body model: --body-model or LEAPNBV_BODY_MODEL)"
else
  "$PYTHON" "$ROOT/scripts/device/device_check.py" graph "${args[@]}" --bag "$BAG" --body-model "$BODY" \
    --seconds "$SECONDS_MEASURED" ${JSON:+--json "${JSON%.json}.graph.json"} || status=1
fi
log "done: $( [ $status = 0 ] && echo 'all checks passed' || echo 'a check FAILED' )"
exit $status
