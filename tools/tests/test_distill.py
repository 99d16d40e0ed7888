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


def test_init_mean_starts_the_student_at_the_mean_body(setup) -> None:
    """After --init-mean every crop gives (about) the mesh of the manifest's mean parameters."""
    from leapnbv_model_tools.distill import init_from_mean, make_crop, read_manifest
    from leapnbv_model_tools.torch_smplx import TorchSMPLX, mesh_from_axis_angle, mesh_from_outputs

    from leapnbv_perception.smplx_layer import SMPLXModel

    root, _, body = setup
    samples = read_manifest(str(root / "val.jsonl"))
    with pytest.raises(DistillError, match="ground-truth params"):
        init_from_mean(random_smplerx("t32", seed=3), read_manifest(str(root / "train.jsonl")))
    student = random_smplerx("t32", seed=3)
    layer = TorchSMPLX(SMPLXModel.load(body))
    crops = torch.from_numpy(np.stack([make_crop(s, (256, 192)) for s in samples]))
    mean_params = {k: torch.from_numpy(np.mean([s.params[k] for s in samples], axis=0)[None]).float()
                   for k in ("root", "body", "lhand", "rhand", "jaw", "betas", "expression")}
    with torch.no_grad():
        mean_mesh = mesh_from_axis_angle(layer, mean_params)[0].numpy()
        before = [mesh_from_outputs(layer, student(crops[i:i + 1]))[0].numpy() for i in range(len(samples))]
        init_from_mean(student, samples)
        after = [mesh_from_outputs(layer, student(crops[i:i + 1]))[0].numpy() for i in range(len(samples))]
    # Hands: one head serves both, so each starts at the average of the two means (small hand poses here).
    for mesh in after:
        assert np.abs(mesh - mean_mesh).max() < 0.02
    assert min(np.abs(mesh - mean_mesh).max() for mesh in before) > 0.05


def test_student_projection_is_the_hmr_tails_placement() -> None:
    """The projection the camera head is trained with equals the graph's: vertices + camera_translation
    through virtual_intrinsics(processed box), in units of the box."""
    from leapnbv_model_tools.distill import box_projection, student_box_projection

    from leapnbv_perception.hmr_tail import camera_translation, virtual_intrinsics

    rng = np.random.default_rng(4)
    vertices = rng.normal(scale=0.4, size=(2, 50, 3))
    cam = np.array([[0.05, -0.1, 0.3], [-0.02, 0.08, -0.5]])
    boxes = np.array([[100.0, 40.0, 150.0, 200.0], [300.0, 10.0, 90.0, 120.0]])
    got = student_box_projection(torch.from_numpy(vertices).float(), torch.from_numpy(cam).float()).numpy()
    for b in range(2):
        placed = vertices[b] + camera_translation(cam[b])
        fx, fy, cx, cy = virtual_intrinsics(boxes[b])
        u, v = fx * placed[:, 0] / placed[:, 2] + cx, fy * placed[:, 1] / placed[:, 2] + cy
        expected = np.stack([(u - boxes[b, 0]) / boxes[b, 2], (v - boxes[b, 1]) / boxes[b, 3]], axis=1)
        np.testing.assert_allclose(got[b], expected, atol=1e-5)
        # The same points through box_projection with the virtual camera's K give the same units.
        again = box_projection(torch.from_numpy(placed[None]).float(), torch.tensor([[fx, fy, cx, cy]]).float(),
                               torch.from_numpy(boxes[b:b + 1]).float()).numpy()[0]
        np.testing.assert_allclose(again, expected, atol=1e-5)


def test_projection_weight_needs_the_camera_and_trains_the_camera_head(setup, tmp_path: Path) -> None:
    root = setup[0]
    with pytest.raises(DistillError, match="without params or camera"):
        distill(_config(setup, str(tmp_path / "a"), train=str(root / "val.jsonl"), targets="gt", teacher="",
                        projection_weight=1.0))
    lines = [json.loads(line) for line in (root / "val.jsonl").read_text().splitlines()]
    for line in lines:
        line["camera"] = {"K": [500.0, 500.0, 40.0, 48.0], "translation": [0.0, 0.2, 3.0]}
    (root / "val_camera.jsonl").write_text("\n".join(json.dumps(line) for line in lines) + "\n")
    plain = distill(_config(setup, str(tmp_path / "b"), train=str(root / "val_camera.jsonl"), targets="gt",
                            teacher="", epochs=1))
    with_projection = distill(_config(setup, str(tmp_path / "c"), train=str(root / "val_camera.jsonl"), targets="gt",
                                      teacher="", epochs=1, projection_weight=1.0))
    # Same weights and batch: the step's loss is the vertex loss plus the projection term (> 0).
    assert with_projection["history"]["loss"][0][1] > plain["history"]["loss"][0][1] + 1e-3


def test_unusable_checkpoints_and_resume_state_are_one_line(setup, tmp_path: Path, capsys) -> None:
    """A truncated teacher, an ONNX file as the student checkpoint, a teacher of another variant and a damaged
    resume state: DistillError (the CLI: exit 2) in one line naming the file, before any training."""
    from leapnbv_model_tools.__main__ import main

    root, teacher, _ = setup
    truncated = tmp_path / "truncated.pth.tar"
    truncated.write_bytes(Path(teacher).read_bytes()[:5000])
    onnx_file = tmp_path / "student.onnx"
    onnx.save(onnx.helper.make_model(onnx.helper.make_graph([], "g", [], [])), str(onnx_file))
    cases = [(dict(teacher=str(truncated)), f"checkpoint '{truncated}' is truncated or damaged"),
             (dict(student_checkpoint=str(onnx_file)), f"checkpoint '{onnx_file}' is not a PyTorch checkpoint"),
             (dict(teacher_variant="t64"), f"checkpoint '{teacher}' does not fit SMPLer-X t64")]
    for changes, message in cases:
        with pytest.raises(DistillError) as raised:
            distill(_config(setup, str(tmp_path / "run"), **changes))
        assert str(raised.value).startswith(message) and "\n" not in str(raised.value), raised.value
    (tmp_path / "damaged").mkdir()
    (tmp_path / "damaged" / "checkpoint.pt").write_bytes(b"PK\x03\x04 not a whole archive")
    with pytest.raises(DistillError, match=r"checkpoint\.pt' \(the run's resume state\) is unreadable"):
        distill(_config(setup, str(tmp_path / "damaged")))
    assert main(["distill", "--train", str(root / "train.jsonl"), "--teacher", str(truncated), "--teacher-variant",
                 "t32", "--student-variant", "t32", "--body-model", setup[2], "--out", str(tmp_path / "cli")]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"distill: checkpoint '{truncated}' is truncated") and err.count("\n") == 1, err


def test_a_student_whose_export_fails_parity_leaves_no_engine(setup, tmp_path: Path, monkeypatch, capsys) -> None:
    """distill exports through export-hmr's checks: a parity failure keeps student.onnx from being written (the
    checkpoint stays), the result says so and the CLI's exit is 1; a good student.onnx from an earlier run stays."""
    from leapnbv_model_tools import export

    out = tmp_path / "run"
    out.mkdir()
    (out / "student.onnx").write_bytes(b"an earlier run's good engine")
    real = export.parity_report

    def off_by_far(*args, **kwargs):
        report = real(*args, **kwargs)
        first = report.outputs[0]
        return export.ParityReport((export.OutputParity(first.name, 1.0, first.noise, first.scale),)
                                   + report.outputs[1:])

    monkeypatch.setattr(export, "parity_report", off_by_far)
    result = distill(_config(setup, str(out), export=True, epochs=1))
    assert not result["parity_ok"] and result["onnx"] is None and result["parity"] == 1.0
    assert (out / "student.onnx").read_bytes() == b"an earlier run's good engine"
    assert Path(result["checkpoint"]).stat().st_size > 0
    assert not [p.name for p in out.iterdir() if p.name.startswith(".export-hmr-")]  # no staged leftovers
    assert "student.onnx not written: parity onnxruntime vs PyTorch over the limit in" in capsys.readouterr().err
