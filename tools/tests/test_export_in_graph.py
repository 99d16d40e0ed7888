"""The exported network in the robot's graph: a random-initialised SMPLer-X s32 checkpoint in the official
file structure -> export-hmr -> onnxruntime in hmr_node, with the dense SMPL-X-layout stand-in body, on
bags/sample_a, compared with its own regression golden (bags/sample_a.smpler_x_s32_random.golden.npz)."""

from __future__ import annotations

import os
import subprocess
from pathlib import Path

import numpy as np
import torch
from leapnbv_model_tools.checkpoint import random_smplerx, save_official
from leapnbv_model_tools.export import main as export_main

from leapnbv_stand_ins.files import ensure_stand_in_smplx_dense

ROOT = Path(__file__).resolve().parents[2]
GOLDEN = ROOT / "bags" / "sample_a.smpler_x_s32_random.golden.npz"
GROUND_TRUTH_GOLDEN = ROOT / "bags" / "sample_a.golden.npz"


def regression_command(model: Path, out: Path, *extra: str):
    return [str(ROOT / "scripts" / "env.sh"), "python", "-m", "leapnbv_bringup.regression", "bags/sample_a",
            "--golden", str(GOLDEN), "--set", "hmr_node.backend=onnxruntime", "--hmr-model", str(model),
            "--body-model", ensure_stand_in_smplx_dense(), "--out", str(out), *extra]


def test_exported_s32_in_the_graph_on_sample_a_matches_its_golden(tmp_path: Path) -> None:
    torch.manual_seed(0)
    checkpoint = save_official(random_smplerx("s32", 0), str(tmp_path / "smpler_x_s32.pth.tar"))
    model = tmp_path / "smpler_x_s32.onnx"
    assert export_main(["--checkpoint", checkpoint, "--variant", "s32", "--out", str(model)]) == 0
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}  # the robot's venv, not the tools'
    env.setdefault("ROS_DOMAIN_ID", "57")
    update = os.environ.get("LEAPNBV_UPDATE_EXPORT_GOLDEN") == "1"  # after a deliberate change
    result = subprocess.run(regression_command(model, tmp_path / "run", *(["--update-golden"] if update else [])),
                            cwd=str(ROOT), env=env, capture_output=True, text=True, timeout=600)
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-3000:]
    assert ("PASS: 0 problems over 10 frames" in result.stdout) or update, result.stdout[-3000:]
    # The network's meshes, not the ground truth's: the dense layout's 10,475 vertices, and other
    # goals than the ground-truth perception's run of the same bag.
    golden, truth = np.load(GOLDEN), np.load(GROUND_TRUTH_GOLDEN)
    meshes = [key for key in golden.files if key.startswith("human_mesh|") and key.endswith("|vertices")]
    assert len(meshes) == 10 and all(golden[key].shape == (10475, 3) for key in meshes)
    goals = [key for key in golden.files if key.startswith("next_best_view|")]
    assert goals and any(not np.allclose(golden[key], truth[key]) for key in goals if key in truth.files)
    log = (tmp_path / "run" / "logs" / "hmr_node.log").read_text()
    assert "Traceback" not in log
