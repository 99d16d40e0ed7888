#!/usr/bin/env bash
# The tools environment (torch, onnx, onnxruntime for tools/leapnbv_model_tools): a venv OUTSIDE the
# repository, keyed by the lock's hash, so the robot's .venv and image never see torch.
#   bash tools/setup_tools_env.sh          # install if absent (idempotent), print the venv path
#   bash tools/setup_tools_env.sh --path   # only print where it is / would be (exit 1 if absent)
# Location: ${LEAPNBV_TOOLS_CACHE:-~/.cache/leapnbv}/tools-venv-<first 16 hex of sha256(lock + python)>.
# Size and time: PyPI's Linux torch wheel imports only with its NVIDIA CUDA packages present (it
# preloads libcublasLt etc. even on CPU), so the install is several GB; see tools/README.md.
set -euo pipefail
ROOT=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
LOCK=$ROOT/tools/requirements.lock
PYTHON=${LEAPNBV_TOOLS_PYTHON:-$(command -v python3.11 || command -v python3)}
PIP_VERSION=24.3.1
key=$( (sha256sum "$LOCK" | cut -d' ' -f1; "$PYTHON" -c 'import sys; print(sys.version_info[:2])'; echo "pip $PIP_VERSION") \
  | sha256sum | cut -c1-16)
VENV=${LEAPNBV_TOOLS_CACHE:-$HOME/.cache/leapnbv}/tools-venv-$key
if [ "${1:-}" = "--path" ]; then
  echo "$VENV"
  [ -f "$VENV/.complete" ]
  exit
fi
if [ -f "$VENV/.complete" ]; then
  echo "$VENV"
  exit 0
fi
log() { printf '[tools-env] %s\n' "$*" >&2; }
start=$(date +%s)
rm -rf "$VENV.partial"
log "creating $VENV ($(grep -c '==' "$LOCK") pinned distributions)"
"$PYTHON" -m venv "$VENV.partial"
"$VENV.partial/bin/python" -m pip install -q --disable-pip-version-check "pip==$PIP_VERSION"
"$VENV.partial/bin/python" -m pip install -q --disable-pip-version-check --no-deps -r "$LOCK"
"$VENV.partial/bin/python" -m pip check >&2
"$VENV.partial/bin/python" -c 'import torch, onnx, onnxruntime; torch.zeros(1) + 1' >&2
rm -rf "$VENV"
mv "$VENV.partial" "$VENV"
# venvs are not relocatable: rewrite the scripts' shebangs and pyvenv.cfg for the final path.
grep -rlI --null "$VENV.partial" "$VENV/bin" "$VENV/pyvenv.cfg" 2>/dev/null | xargs -0 -r sed -i "s|$VENV.partial|$VENV|g"
touch "$VENV/.complete"
log "done in $(( $(date +%s) - start )) s"
echo "$VENV"
