#!/usr/bin/env bash
# The code that runs on the robot (JetPack 5: Python 3.8, numpy 1.24) is tested under that Python:
# the ROS-free cores' unit tests run in .venv38 (pinned by scripts/requirements-py38.lock).
# Uses python3.8 from PATH or pyenv; where neither exists it says so and stops (vermin still checks syntax).
set -euo pipefail
ROOT=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
cd "$ROOT"
VENV=$ROOT/.venv38
LOCK=$ROOT/scripts/requirements-py38.lock
PY38=${LEAPNBV_PYTHON38:-}
if [ -z "$PY38" ]; then
  if command -v python3.8 >/dev/null && python3.8 -c 'import sys; sys.exit(sys.version_info[:2] != (3, 8))' 2>/dev/null; then
    PY38=$(command -v python3.8)
  elif command -v pyenv >/dev/null; then
    version=$(pyenv versions --bare 2>/dev/null | grep -E '^3\.8(\.|$)' | tail -1 || true)
    [ -n "$version" ] && PY38=$(PYENV_VERSION=$version pyenv which python)
  fi
fi
if [ -z "$PY38" ]; then
  echo "[py38] WARNING: no Python 3.8 here; the cores were only syntax-checked for 3.8 (vermin)" >&2
  exit 0
fi
stamp=$VENV/.leapnbv-lock.sha256
want=$(sha256sum "$LOCK" | cut -d' ' -f1)
if [ ! -x "$VENV/bin/python" ] || [ "$(cat "$stamp" 2>/dev/null)" != "$want" ]; then
  echo "[py38] creating $VENV with $PY38"
  rm -rf "$VENV"
  "$PY38" -m venv "$VENV"
  "$VENV/bin/python" -m pip install -q --disable-pip-version-check --no-deps -r "$LOCK"
  "$VENV/bin/python" -m pip check
  echo "$want" >"$stamp"
fi
echo "[py38] ROS-free cores on $("$VENV/bin/python" -c 'import sys, numpy, numba; print("Python", sys.version.split()[0], "numpy", numpy.__version__, "numba", numba.__version__)')"
"$VENV/bin/python" -m pytest -p no:cacheprovider -q -m "not ros" \
  src/leapnbv_common/test src/leapnbv_perception/test src/leapnbv_geometry/test src/leapnbv_planner/test
