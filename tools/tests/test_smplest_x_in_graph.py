"""A SMPLest-X export in the robot's graph: hmr_node on bags/sample_a with the FP32 SMPL-X tail.

A random-initialised smplest_x_t32 checkpoint (the architecture of SMPLest-X-H at width 32) in the official file
structure -> export-hmr -> onnxruntime in hmr_node with the dense SMPL-X-layout stand-in body and the node's
SMPLest-X parameters (box_scale 1.2, unmirror_left_hand false, which the export's metadata requires). The run's
outputs are recorded as a golden in a temporary folder (none is kept in the repository for random weights) and
checked: a finite mesh of the body model's size for every frame, the contract met (the node loads it).
"""

from __future__ import annotations

import os
import subprocess
from pathlib import Path

import numpy as np
import torch
from leapnbv_model_tools.checkpoint import random_network, save_official
from leapnbv_model_tools.export import main as export_main
from leapnbv_stand_ins.files import ensure_stand_in_smplx_dense

ROOT = Path(__file__).resolve().parents[2]


def run_graph(model: Path, out: Path, *settings: str) -> subprocess.CompletedProcess:
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}  # the robot's venv, not the tools'
    env.setdefault("ROS_DOMAIN_ID", "62")
    command = [str(ROOT / "scripts" / "env.sh"), "python", "-m", "leapnbv_bringup.regression", "bags/sample_a",
               "--update-golden", "--golden", str(out / "run.golden.npz"), "--set", "hmr_node.backend=onnxruntime",
               "--hmr-model", str(model), "--body-model", ensure_stand_in_smplx_dense(), "--out", str(out / "run"),
               *settings]
    return subprocess.run(command, cwd=str(ROOT), env=env, capture_output=True, text=True, timeout=600)


def test_exported_smplest_x_in_the_graph_on_sample_a(tmp_path: Path) -> None:
    torch.manual_seed(0)
    checkpoint = save_official(random_network("smplest_x_t32", 0), str(tmp_path / "smplest_x_t32.pth.tar"))
    model = tmp_path / "smplest_x_t32.onnx"
    assert export_main(["--checkpoint", checkpoint, "--variant", "smplest_x_t32", "--out", str(model)]) == 0
    result = run_graph(model, tmp_path, "--set", "hmr_node.box_scale=1.2", "--set", "hmr_node.unmirror_left_hand=false")
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-3000:]
    golden = np.load(tmp_path / "run.golden.npz")
    meshes = [key for key in golden.files if key.startswith("human_mesh|") and key.endswith("|vertices")]
    assert len(meshes) == 10, golden.files[:20]
    for key in meshes:
        vertices = golden[key]
        assert vertices.shape == (10475, 3) and np.all(np.isfinite(vertices)), key
        assert np.ptp(vertices, axis=0).max() > 0.1  # a body, not a point
    log = (tmp_path / "run" / "logs" / "hmr_node.log").read_text()
    assert "Traceback" not in log and "ExportMetadataError" not in log
