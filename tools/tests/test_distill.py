"""distill on a tiny network (t32) and the small stand-in body model: cache, resume, 2 processes."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import onnx
import pytest
import torch
from leapnbv_model_tools.checkpoint import random_smplerx, save_official
from leapnbv_model_tools.distill import DistillConfig, DistillError, distill, pa_mpvpe_mm
from leapnbv_model_tools.fp16 import convert_float16

torch.set_num_threads(1)


def _params(rng: np.random.Generator) -> dict:
    return {"root": (rng.normal(size=3) * 0.3).tolist(), "body": (rng.normal(size=63) * 0.2).tolist(),
            "lhand": (rng.normal(size=45) * 0.1).tolist(), "rhand": (rng.normal(size=45) * 0.1).tolist(),
            "jaw": [0.1, 0.0, 0.0], "betas": rng.normal(size=10).tolist(), "expression": [0.0] * 10}


@pytest.fixture(scope="module")
def setup(tmp_path_factory):
    import cv2

    from leapnbv_stand_ins.files import ensure_stand_in_body_model

    root = tmp_path_factory.mktemp("distill")
    rng = np.random.default_rng(0)
    for split, count in (("train", 4), ("val", 2)):
        lines = []
        for index in range(count):
            image = rng.integers(0, 255, size=(96, 80, 3), dtype=np.uint8)
            cv2.imwrite(str(root / f"{split}{index}.png"), image)
            lines.append(json.dumps({"image": f"{split}{index}.png", "box": [10, 8, 60, 90],
                                     "params": _params(rng) if split == "val" else None}))
        (root / f"{split}.jsonl").write_text("\n".join(lines) + "\n")
    teacher = save_official(random_smplerx("t32", seed=1), str(root / "teacher.pth.tar"))
    body = ensure_stand_in_body_model("small", root / "body")
    return root, teacher, body


def _config(setup, out: str, **changes) -> DistillConfig:
    root, teacher, body = setup
    values = dict(train=str(root / "train.jsonl"), val=str(root / "val.jsonl"), teacher=teacher, teacher_variant="t32",
                  student_variant="t32", body_model=body, out=out, epochs=2, batch_size=2, lr=1e-3,
                  cache=str(root / "cache"), export=False)
    values.update(changes)
    return DistillConfig(**values)


def test_procrustes_metric_ignores_similarity_transforms() -> None:
    rng = np.random.default_rng(0)
    mesh = rng.normal(size=(50, 3))
    angle = 0.7
    rotation = np.array([[np.cos(angle), -np.sin(angle), 0], [np.sin(angle), np.cos(angle), 0], [0, 0, 1]])
    assert pa_mpvpe_mm(2.0 * mesh @ rotation.T + 1.0, mesh) < 1e-9
    assert pa_mpvpe_mm(mesh + rng.normal(size=mesh.shape) * 0.01, mesh) > 1.0


def test_teacher_cache_resume_and_export(setup, tmp_path: Path) -> None:
    whole = distill(_config(setup, str(tmp_path / "whole"), export=True))
    assert whole["teacher_computed"] == 6 and whole["step"] == 4
    losses = [loss for _, loss in whole["history"]["loss"]]
    assert len(losses) == 4 and all(np.isfinite(losses))
    assert len(whole["history"]["val"]) == 2 and whole["history"]["val"][0]["val_gt"] > 0
    assert whole["parity_ok"] and Path(whole["onnx"]).stat().st_size > 0
    assert (tmp_path / "whole" / "curves.png").stat().st_size > 1000
    # The ladder's evaluation of the exported ONNX (onnxruntime; FP16 emulated) gives the PA-MPVPE that
    # validation computed in PyTorch for the same student and crops.
    from leapnbv_model_tools.ladder import evaluate

    root, _, body = setup
    val_gt = whole["history"]["val"][-1]["val_gt"]
    assert evaluate(str(whole["onnx"]), False, str(root / "val.jsonl"), body, (256, 192)) == pytest.approx(val_gt,
                                                                                                           abs=0.05)
    half = convert_float16(onnx.load(str(whole["onnx"])), [])
    onnx.save(half, str(tmp_path / "half.onnx"))
    assert evaluate(str(tmp_path / "half.onnx"), True, str(root / "val.jsonl"), body, (256, 192)) == pytest.approx(
        val_gt, abs=5.0)
    # Stopped after step 1, then resumed: the same losses as the run that never stopped.
    first = distill(_config(setup, str(tmp_path / "resumed"), max_steps=1))
    assert first["step"] == 1 and first["teacher_computed"] == 0 and first["teacher_reused"] == 6
    resumed = distill(_config(setup, str(tmp_path / "resumed")))
    assert resumed["step"] == 4
    np.testing.assert_allclose([loss for _, loss in resumed["history"]["loss"]], losses, rtol=1e-5)
    with pytest.raises(DistillError, match="another configuration"):
        distill(_config(setup, str(tmp_path / "resumed"), lr=5e-4))


def test_teacher_cache_keys(setup, tmp_path: Path) -> None:
    """A changed crop is recomputed; another teacher (or body model) gets another folder."""
    from leapnbv_model_tools.distill import TeacherCache, crop_sha256
    from leapnbv_model_tools.torch_smplx import TorchSMPLX

    from leapnbv_perception.smplx_layer import SMPLXModel

    root, teacher_path, body = setup
    teacher = random_smplerx("t32", seed=1)
    layer = TorchSMPLX(SMPLXModel.load(body))
    crops = np.random.default_rng(0).uniform(size=(2, 3, 256, 192)).astype(np.float32)
    hashes = [crop_sha256(c) for c in crops]
    cache = TeacherCache(str(tmp_path), "a" * 64, "t32", "b" * 64, (256, 192))
    cache.fill(teacher, layer, crops, hashes)
    assert (cache.computed, cache.reused) == (2, 0)
    crops[1, 0, 0, 0] += 0.01
    hashes = [crop_sha256(c) for c in crops]
    again = TeacherCache(str(tmp_path), "a" * 64, "t32", "b" * 64, (256, 192))
    again.fill(teacher, layer, crops, hashes)
    assert (again.computed, again.reused) == (1, 1) and again.folder == cache.folder
    meshes = again.load(hashes)
    assert meshes.shape == (2, layer.v_template.shape[0], 3) and np.abs(meshes.mean(axis=1)).max() < 1e-5
    for other in (TeacherCache(str(tmp_path), "c" * 64, "t32", "b" * 64, (256, 192)),
                  TeacherCache(str(tmp_path), "a" * 64, "t32", "d" * 64, (256, 192)),
                  TeacherCache(str(tmp_path), "a" * 64, "t64", "b" * 64, (256, 192))):
        assert other.folder != cache.folder


def test_two_processes_give_the_loss_curve_of_one(setup, tmp_path: Path) -> None:
    single = distill(_config(setup, str(tmp_path / "one"), max_steps=2))
    root, teacher, body = setup
    env = dict(os.environ, OMP_NUM_THREADS="1")
    command = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node", "2",
               "-m", "leapnbv_model_tools", "distill", "--train", str(root / "train.jsonl"), "--val",
               str(root / "val.jsonl"), "--teacher", teacher, "--teacher-variant", "t32", "--student-variant", "t32",
               "--body-model", body, "--out", str(tmp_path / "two"), "--epochs", "2", "--batch-size", "2",
               "--lr", "1e-3", "--cache", str(tmp_path / "cache2"), "--max-steps", "2", "--no-export"]
    result = subprocess.run(command, env=env, capture_output=True, text=True, timeout=600)
    assert result.returncode == 0, result.stderr[-3000:]
    history = json.loads((tmp_path / "two" / "history.json").read_text())
    np.testing.assert_allclose([loss for _, loss in history["loss"]],
                               [loss for _, loss in single["history"]["loss"]], rtol=1e-4)


def test_ground_truth_targets(setup, tmp_path: Path) -> None:
    root = setup[0]
    with pytest.raises(DistillError, match="samples without params"):
        distill(_config(setup, str(tmp_path / "a"), targets="gt", teacher=""))
    result = distill(_config(setup, str(tmp_path / "b"), train=str(root / "val.jsonl"), targets="gt", teacher="",
                             epochs=1))
    assert result["step"] == 1 and result["teacher_computed"] == 0
    assert np.isfinite(result["history"]["loss"][0][1]) and "val_teacher" not in result["history"]["val"][0]
    assert result["history"]["val"][0]["val_gt"] > 0
