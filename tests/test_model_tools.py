"""The model tools (tools/leapnbv_model_tools: the SMPLer-X network in PyTorch, checkpoints, the ONNX
export) run in their own environment, which has torch and is never the robot's. This runs their tests
there when that environment exists, and skips with the command that sets it up otherwise."""

from __future__ import annotations

import os
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def tools_venv() -> Path:
    result = subprocess.run(["bash", str(ROOT / "tools" / "setup_tools_env.sh"), "--path"], capture_output=True,
                            text=True)
    if result.returncode != 0:
        pytest.skip("the tools environment (torch) is not set up: `bash tools/setup_tools_env.sh` (several GB from "
                    "PyPI, see tools/README.md); scripts/test.sh sets it up with LEAPNBV_TOOLS_ENV=1")
    return Path(result.stdout.strip())


@pytest.mark.slow
@pytest.mark.timeout(900)
def test_model_tools_in_their_environment() -> None:
    venv = tools_venv()
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(str(ROOT / p) for p in ("tools", "src/leapnbv_perception",
                                                                 "src/leapnbv_common", "src/leapnbv_stand_ins"))
    result = subprocess.run([str(venv / "bin" / "python"), "-m", "pytest", "-q", "-p", "no:cacheprovider",
                             "-c", str(ROOT / "tools" / "pytest.ini"), str(ROOT / "tools" / "tests")],
                            cwd=str(ROOT), env=env, capture_output=True, text=True, timeout=900)
    assert result.returncode == 0, result.stdout[-4000:] + result.stderr[-2000:]
