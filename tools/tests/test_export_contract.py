"""export-hmr's contract: the parity limit from the network's own FP32 noise (and what it still refuses),
the file at --out only after every check passed, and every unusable input one line with exit 2."""

from __future__ import annotations

import hashlib
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import onnx
import pytest
import torch
from leapnbv_model_tools.__main__ import main
from leapnbv_model_tools.checkpoint import CheckpointError, load_smplerx, random_smplerx, save_official
from leapnbv_model_tools.exit_codes import ModelToolExit
from leapnbv_model_tools.export import (
    OUTPUT_NAMES,
    PARITY_FLOOR,
    PARITY_NOISE_FACTOR,
    OutputParity,
    _Exported,
    export_metadata,
    export_onnx,
    parity_report,
)
from onnx import numpy_helper

VARIANT, INPUT, HW = "t32", "256x192", (256, 192)  # the narrow network: the checks are the same, the export fast


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory: pytest.TempPathFactory) -> str:
    folder = tmp_path_factory.mktemp("checkpoint")
    return save_official(random_smplerx(VARIANT, seed=1), str(folder / f"smpler_x_{VARIANT}.pth.tar"))


@pytest.fixture(scope="module")
def exported(checkpoint: str, tmp_path_factory: pytest.TempPathFactory) -> str:
    path = str(tmp_path_factory.mktemp("exported") / f"{VARIANT}.onnx")
    return export_onnx(load_smplerx(checkpoint, VARIANT), path, HW, export_metadata(VARIANT, "0" * 64, HW))


def crops(count: int = 2) -> np.ndarray:
    return np.random.default_rng(0).uniform(0.0, 1.0, size=(count, 3) + HW).astype(np.float32)


def export_args(checkpoint: str, out: str, *extra: str) -> list:
    return ["export-hmr", "--checkpoint", checkpoint, "--variant", VARIANT, "--input", INPUT, "--out", out,
            "--parity-crops", "1", *extra]


def sha256(path: str) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


# --- the parity limit --------------------------------------------------------------------------------------


def test_the_limit_is_the_outputs_fp32_noise_not_a_fixed_number() -> None:
    # The case a fixed 1e-4 refused: FP32 noise 1.2e-4 in a hand output, onnxruntime 1.5e-4 from PyTorch.
    hand = OutputParity("lhand_pose", difference=1.5e-4, noise=1.2e-4, scale=1.1)
    assert hand.ok and hand.limit == pytest.approx(PARITY_NOISE_FACTOR * 1.2e-4 + PARITY_FLOOR * 1.1)
    # Where FP32 rounds (nearly) exactly, the floor, relative to the output's scale.
    assert OutputParity("betas", difference=9e-6, noise=0.0, scale=0.5).ok
    assert not OutputParity("betas", difference=2e-5, noise=0.0, scale=0.5).ok
    assert OutputParity("betas", difference=4e-5, noise=0.0, scale=5.0).ok
    assert not OutputParity("cam_param", difference=1e-2, noise=1.2e-4, scale=1.0).ok
    assert not OutputParity("cam_param", difference=float("nan"), noise=1e-6, scale=1.0).ok


def test_parity_measures_the_noise_and_passes_a_correct_export(checkpoint: str, exported: str) -> None:
    model = load_smplerx(checkpoint, VARIANT)
    before = {k: v.clone() for k, v in model.state_dict().items()}
    report = parity_report(model, exported, crops())
    assert report.ok, "\n".join(report.lines())
    assert [o.name for o in report.outputs] == list(OUTPUT_NAMES)
    for output in report.outputs:
        # FP32 vs FP64 of this network: rounding, neither zero nor large; onnxruntime within a few times it.
        assert 1e-9 < output.noise < 1e-5, output
        assert output.difference < 1e-5 and 0.1 < output.scale < 10, output
    # The FP64 pass converts the network back exactly.
    for name, tensor in model.state_dict().items():
        assert tensor.dtype == before[name].dtype and torch.equal(tensor, before[name]), name


def test_a_wrong_weight_or_graph_still_fails(checkpoint: str, exported: str, tmp_path: Path) -> None:
    model = load_smplerx(checkpoint, VARIANT)
    # One bias element of the camera head off by 1e-3 (PyTorch has it, the exported graph not).
    with torch.no_grad():
        model.body_regressor.cam_out[0].bias[0] += 1e-3
    report = parity_report(model, exported, crops(1))
    assert [o.name for o in report.outputs if not o.ok] == ["cam_param"], "\n".join(report.lines())
    assert report.outputs[OUTPUT_NAMES.index("cam_param")].difference == pytest.approx(1e-3, rel=1e-3)
    # One whole weight 1 % off in the first encoder block: every output moves.
    model = load_smplerx(checkpoint, VARIANT)
    with torch.no_grad():
        model.encoder.blocks[0].attn.qkv.weight.mul_(1.01)
    assert not parity_report(model, exported, crops(1)).ok
    # The graph's LayerNorm eps 1e-6 -> 1e-3 (a wrong constant, the weights all right).
    graph = onnx.load(exported)
    changed = 0
    for node in graph.graph.node:
        if node.op_type == "Constant":
            value = numpy_helper.to_array(node.attribute[0].t)
            if value.size == 1 and abs(float(value.reshape(-1)[0]) - 1e-6) < 1e-12:
                node.attribute[0].t.CopyFrom(numpy_helper.from_array(np.full(value.shape, 1e-3, np.float32)))
                changed += 1
    assert changed > 0
    wrong = str(tmp_path / "eps.onnx")
    onnx.save(graph, wrong)
    report = parity_report(load_smplerx(checkpoint, VARIANT), wrong, crops(1))
    assert not report.ok and all(not o.ok for o in report.outputs if o.name in ("body_pose", "betas"))


# --- the file at --out only after every check passed -----------------------------------------------------


def test_a_failed_export_leaves_the_earlier_file_and_no_partial_one(checkpoint: str, tmp_path: Path,
                                                                     monkeypatch: pytest.MonkeyPatch,
                                                                     capsys: pytest.CaptureFixture) -> None:
    out = tmp_path / "model.onnx"
    assert main(export_args(checkpoint, str(out))) == ModelToolExit.OK
    good = sha256(str(out))
    assert {p.key: p.value for p in onnx.load(str(out)).metadata_props}["leapnbv.variant"] == f"smpler_x_{VARIANT}"
    capsys.readouterr()

    forward = _Exported.forward

    def wrong_graph(self, img):  # the traced graph's camera 1e-3 off what the network computes
        outputs = list(forward(self, img))
        outputs[OUTPUT_NAMES.index("cam_param")] = outputs[OUTPUT_NAMES.index("cam_param")] + 1e-3
        return tuple(outputs)

    monkeypatch.setattr(_Exported, "forward", wrong_graph)
    assert main(export_args(checkpoint, str(out))) == ModelToolExit.CHECK_FAILED
    captured = capsys.readouterr()
    assert "cam_param" in captured.out and "FAILED" in captured.out
    assert captured.err.strip().splitlines()[-1] == (
        f"export-hmr: parity onnxruntime vs PyTorch over the limit in cam_param; the earlier file there is "
        f"unchanged at '{out}'")
    assert sha256(str(out)) == good
    assert sorted(os.listdir(tmp_path)) == ["model.onnx"]  # no staged folder, no .data, no partial file
    # Without an earlier file: nothing at all.
    fresh = tmp_path / "fresh" / "model.onnx"
    fresh.parent.mkdir()
    assert main(export_args(checkpoint, str(fresh))) == ModelToolExit.CHECK_FAILED
    assert os.listdir(fresh.parent) == []


# --- every unusable input: one line naming the file, exit 2 ----------------------------------------------


def _tiny_onnx(path: Path) -> None:
    node = onnx.helper.make_node("Identity", ["x"], ["y"])
    graph = onnx.helper.make_graph([node], "g", [onnx.helper.make_tensor_value_info("x", onnx.TensorProto.FLOAT, [1])],
                                   [onnx.helper.make_tensor_value_info("y", onnx.TensorProto.FLOAT, [1])])
    onnx.save(onnx.helper.make_model(graph, producer_name="leapnbv"), str(path))


class _NotATensor:
    pass


def _unusable(kind: str, folder: Path, checkpoint: str) -> Path:
    path = folder / f"{kind}.pth.tar"
    data = Path(checkpoint).read_bytes()
    if kind == "missing":
        return path
    if kind == "folder":
        path.mkdir()
    elif kind == "empty":
        path.write_bytes(b"")
    elif kind == "truncated":
        path.write_bytes(data[: len(data) // 2])
    elif kind == "truncated_head":
        path.write_bytes(data[:100])
    elif kind == "text":
        path.write_text("not a checkpoint\n")
    elif kind == "onnx":
        path = folder / "model.onnx"
        _tiny_onnx(path)
    elif kind == "pickle_with_a_class":
        torch.save({"network": _NotATensor()}, str(path))
    elif kind == "no_network":
        torch.save({"state_dict": {}}, str(path))
    elif kind == "network_not_tensors":
        torch.save({"network": {"module.encoder.cls_token": 1.0}}, str(path))
    elif kind == "another_network":  # the official structure, another family's keys
        torch.save({"network": {"module.backbone.conv1.weight": torch.zeros(64, 3, 7, 7)}}, str(path))
    return path


UNUSABLE = {
    "missing": "checkpoint not found: '{path}'",
    "folder": "checkpoint '{path}' is a folder, not a file",
    "empty": "checkpoint '{path}' is empty",
    "truncated": "checkpoint '{path}' is truncated or damaged (torch.load: failed finding central directory)",
    "truncated_head": "checkpoint '{path}' is truncated or damaged",
    "text": "checkpoint '{path}' is not a PyTorch checkpoint, or truncated",
    "onnx": "checkpoint '{path}' is not a PyTorch checkpoint (it looks like an ONNX model)",
    "pickle_with_a_class": "checkpoint '{path}' is not a plain-tensor checkpoint",
    "no_network": "checkpoint '{path}' is not a SMPLer-X checkpoint: no 'network' entry (found ['state_dict'])",
    "network_not_tensors": "checkpoint '{path}' is not a SMPLer-X checkpoint: 'network' entry",
    "another_network": f"checkpoint '{{path}}' does not fit SMPLer-X {VARIANT}",
}


@pytest.mark.parametrize("kind", sorted(UNUSABLE))
def test_an_unusable_checkpoint_is_one_line_and_exit_2(kind: str, checkpoint: str, tmp_path: Path,
                                                      capsys: pytest.CaptureFixture) -> None:
    path = _unusable(kind, tmp_path, checkpoint)
    out = tmp_path / "out.onnx"
    assert main(export_args(str(path), str(out))) == ModelToolExit.BAD_INPUT
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1, err
    assert err.startswith("export-hmr: " + UNUSABLE[kind].format(path=path)), err
    assert not out.exists()
    with pytest.raises(CheckpointError):
        load_smplerx(str(path), VARIANT)


def test_another_variant_and_bad_out_are_one_line_exit_2(checkpoint: str, tmp_path: Path,
                                                         capsys: pytest.CaptureFixture) -> None:
    s32 = save_official(random_smplerx("s32", seed=0), str(tmp_path / "smpler_x_s32.pth.tar"))
    out = str(tmp_path / "out.onnx")
    assert main(["export-hmr", "--checkpoint", s32, "--variant", "b32", "--out", out]) == ModelToolExit.BAD_INPUT
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1
    assert err.startswith(f"export-hmr: checkpoint '{s32}' does not fit SMPLer-X b32 (embed 768, depth 12): 0 missing, "
                          "0 unexpected, 171 of the wrong shape (its keys and shapes are those of s32); first wrong "
                          "shape "), err
    for bad_out, message in ((str(tmp_path / "absent" / "m.onnx"), f"folder '{tmp_path / 'absent'}' does not exist"),
                             (str(tmp_path), "is a folder")):
        assert main(export_args(checkpoint, bad_out)) == ModelToolExit.BAD_INPUT
        err = capsys.readouterr().err
        assert len(err.strip().splitlines()) == 1 and message in err, err


def test_the_command_line_prints_one_line_and_no_traceback(tmp_path: Path) -> None:
    """Through the real entry point (python -m), as a user runs it: an ONNX file passed as the checkpoint."""
    model = tmp_path / "model.onnx"
    _tiny_onnx(model)
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(sys.path))
    command = [sys.executable, "-m", "leapnbv_model_tools", *export_args(str(model), str(tmp_path / "o"))]
    result = subprocess.run(command, capture_output=True, text=True, env=env, timeout=300)
    assert result.returncode == 2
    assert result.stderr.strip() == (f"export-hmr: checkpoint '{model}' is not a PyTorch checkpoint (it looks like an "
                                     "ONNX model)")


def test_quantize_int8_refuses_an_unusable_model_in_one_line(checkpoint: str, tmp_path: Path,
                                                             capsys: pytest.CaptureFixture) -> None:
    """quantize-int8's model (read before any frame is rendered): missing, empty, a checkpoint."""
    (tmp_path / "empty.onnx").write_bytes(b"")
    for model, message in ((tmp_path / "absent.onnx", "model file not found"),
                           (tmp_path / "empty.onnx", "onnxruntime could not load"),
                           (Path(checkpoint), "onnxruntime could not load")):
        assert main(["quantize-int8", "hmr", str(model), "--out", str(tmp_path / "q.onnx")]) == 2
        err = capsys.readouterr().err
        assert err.startswith(f"quantize-int8: {message}") and str(model) in err, err
        assert err.count("\n") == 1 and err.endswith("\n"), err
        assert not (tmp_path / "q.onnx").exists()
