#!/usr/bin/env bash
# Set up (idempotent) and run every check: ruff, mypy, the Python 3.8 syntax check of src/ (the robot
# runs JetPack 5), the ROS-free cores under Python 3.8 + numpy 1.24 when that interpreter exists,
# and the whole pytest suite (unit + integration) on an isolated ROS domain.
# Extra arguments go to pytest (e.g. scripts/test.sh -k raster).
set -euo pipefail
ROOT=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
cd "$ROOT"
log() { printf '[test] %s\n' "$*"; }

bash scripts/setup.sh

# The tools environment (torch for tools/leapnbv_model_tools; never the robot's .venv or image): set up
# once per tools/requirements.lock (a venv in ~/.cache/leapnbv keyed by the lock's hash; about 8 min and
# 5.5 GB the first time, 0.2 s after), so tests/test_model_tools.py runs the tools' tests in it.
# LEAPNBV_TOOLS_ENV=0 leaves it out for a quick local run: that test then skips, saying so.
export LEAPNBV_TOOLS_ENV=${LEAPNBV_TOOLS_ENV:-1}
if [ "$LEAPNBV_TOOLS_ENV" != 0 ]; then
  log "tools environment (LEAPNBV_TOOLS_ENV=0 leaves it and the tools' tests out)"
  tools_start=$(date +%s)
  bash tools/setup_tools_env.sh >/dev/null
  log "tools environment ready in $(( $(date +%s) - tools_start )) s"
fi

log "ruff"
.venv/bin/ruff check src tests scripts

log "mypy (mypy.ini: strict on the ROS-free cores)"
.venv/bin/mypy

log "vermin: src/ must run on Python 3.8"
.venv/bin/vermin -q -t=3.8- --no-tips --violations --eval-annotations --backport dataclasses \
  --exclude-regex '/(build|install|log)/' src

log "hadolint: the Dockerfiles (docker/.hadolint.yaml)"
.venv/bin/hadolint --config docker/.hadolint.yaml docker/*/Dockerfile

if [ -x scripts/test_py38.sh ]; then
  bash scripts/test_py38.sh
fi

# One ROS_DOMAIN_ID per run, held by a lock, so parallel runs on one machine do not hear each other.
lock_dir=${TMPDIR:-/tmp}/leapnbv-ros-domains
mkdir -p "$lock_dir"
for offset in $(seq 0 89); do
  domain=$(( 1 + ($$ + offset) % 90 ))
  exec 9>"$lock_dir/$domain.lock"
  if flock -n 9; then break; fi
  exec 9>&-
  domain=""
done
[ -n "${domain:-}" ] || { echo "[test] no free ROS_DOMAIN_ID" >&2; exit 1; }
export ROS_DOMAIN_ID=$domain LEAPNBV_ROS_DOMAIN_CLAIMED=1
log "pytest on ROS_DOMAIN_ID=$ROS_DOMAIN_ID"
set +e
scripts/env.sh python -m pytest -p no:cacheprovider "$@"
status=$?
set -e
if [ $status -eq 5 ]; then
  echo "[test] pytest collected no tests: that is a failure here" >&2
  exit 1
fi
exit $status
