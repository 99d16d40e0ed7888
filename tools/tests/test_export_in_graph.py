"""The exported network in the robot's graph, on bags/sample_a, against its own regression golden.

A random-initialised SMPLer-X s32 checkpoint in the official file structure -> export-hmr -> onnxruntime in hmr_node,
with the dense SMPL-X-layout stand-in body, compared with bags/sample_a.smpler_x_s32_random.golden.npz: as the
regression runs it, in another numeric configuration of the engine (threads, optimization level, every output
nudged by one ulp), and with one weight of the network changed (which must fail).
"""

from __future__ import annotations

import os
import subprocess
from pathlib import Path

import numpy as np
import onnx
import torch
from onnx import numpy_helper

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


# Another numeric configuration of the engine than the regression's pinned one (leapnbv_bringup.regression
# REPLAY_ENGINE_SETTINGS): two threads, basic graph optimizations, and every output nudged by one ulp.
OTHER_NUMERIC_CONFIGURATION = ("--set", "hmr_node.backend=onnxruntime_last_bit_nudged",
                               "--set", "hmr_node.intra_op_threads=2", "--set", "hmr_node.graph_optimization=basic")


def run_regression(model: Path, out: Path, *extra: str) -> subprocess.CompletedProcess:
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}  # the robot's venv, not the tools'
    env.setdefault("ROS_DOMAIN_ID", "57")
    return subprocess.run(regression_command(model, out, *extra), cwd=str(ROOT), env=env, capture_output=True,
                          text=True, timeout=600)


# The body pose head's weights: every body vertex depends on them (the largest tensor, the box
# network's deconvolution, moves only the hand and face boxes, which this replay does not use).
CHANGED_WEIGHT = "model.body_regressor.body_pose_out.0.weight"


def with_one_weight_changed(model: Path, out: Path) -> Path:
    """The network with CHANGED_WEIGHT changed by noise of 5 % of its spread (a fine-tuning step's size).

    Noise, not a uniform scale, which a normalization after the layer could take out again.
    """
    graph = onnx.load(str(model))
    weights = next(t for t in graph.graph.initializer if t.name == CHANGED_WEIGHT)
    values = numpy_helper.to_array(weights)
    noise = np.random.default_rng(0).normal(0.0, 0.05 * float(values.std()), values.shape).astype(np.float32)
    weights.CopyFrom(numpy_helper.from_array(values + noise, weights.name))
    onnx.save(graph, str(out))
    return out


def test_exported_s32_in_the_graph_on_sample_a_matches_its_golden(tmp_path: Path) -> None:
    torch.manual_seed(0)
    checkpoint = save_official(random_smplerx("s32", 0), str(tmp_path / "smpler_x_s32.pth.tar"))
    model = tmp_path / "smpler_x_s32.onnx"
    assert export_main(["--checkpoint", checkpoint, "--variant", "s32", "--out", str(model)]) == 0
    update = os.environ.get("LEAPNBV_UPDATE_EXPORT_GOLDEN") == "1"  # after a deliberate change
    result = run_regression(model, tmp_path / "run", *(["--update-golden"] if update else []))
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-3000:]
    assert ("PASS: 0 problems over 10 frames" in result.stdout) or update, result.stdout[-3000:]
    if not update:
        other = run_regression(model, tmp_path / "other", *OTHER_NUMERIC_CONFIGURATION)
        assert other.returncode == 0, other.stdout[-3000:] + other.stderr[-3000:]
        assert "PASS: 0 problems over 10 frames" in other.stdout, other.stdout[-3000:]
        changed = run_regression(with_one_weight_changed(model, tmp_path / "changed.onnx"), tmp_path / "changed")
        assert changed.returncode == 1, changed.stdout[-3000:] + changed.stderr[-3000:]
        assert "FAIL human_mesh:" in changed.stdout and "FAIL view_candidates:" in changed.stdout, changed.stdout
    # The network's meshes, not the ground truth's: the dense layout's 10,475 vertices, and other
    # goals than the ground-truth perception's run of the same bag.
    golden, truth = np.load(GOLDEN), np.load(GROUND_TRUTH_GOLDEN)
    meshes = [key for key in golden.files if key.startswith("human_mesh|") and key.endswith("|vertices")]
    assert len(meshes) == 10 and all(golden[key].shape == (10475, 3) for key in meshes)
    goals = [key for key in golden.files if key.startswith("next_best_view|")]
    assert goals and any(not np.allclose(golden[key], truth[key]) for key in goals if key in truth.files)
    log = (tmp_path / "run" / "logs" / "hmr_node.log").read_text()
    assert "Traceback" not in log
