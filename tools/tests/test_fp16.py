"""fp16-check and the overflow table on tiny ViTs (widths 64 and 256, seconds)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import onnx
import pytest
import torch
from leapnbv_model_tools.fp16 import (
    convert_float16,
    find_normalizations,
    normalize_fp16,
    normalize_reference,
    sequential_sum_fp16,
)
from leapnbv_model_tools.overflow_table import OverflowViT, export_overflow_vit, table_row

torch.set_num_threads(1)


def test_sequential_fp16_sum_rounds_and_overflows_like_fp16() -> None:
    # 2048 + 1 is 2048 in FP16 (spacing 2 there): one element at a time, each partial sum rounded.
    assert float(sequential_sum_fp16(np.array([[2048.0, 1.0, 1.0]]), -1)[0, 0]) == 2048.0
    # 2000 x 40 = 80000 > 65504: inf, where numpy's own half sum (float32 accumulator) does not overflow.
    values = np.full((1, 2000), 40.0, dtype=np.float16)
    assert np.isinf(sequential_sum_fp16(values, -1)).all()
    assert np.isfinite(values.sum(dtype=np.float32))
    rows = np.random.default_rng(0).normal(size=(4, 64)) * 3.0
    np.testing.assert_allclose(normalize_fp16(rows, 1e-6), normalize_reference(rows, 1e-6), atol=5e-3)
    big = np.random.default_rng(0).uniform(-13, 13, size=(2, 1280))  # sum of squares about 72 000
    assert not np.any(normalize_fp16(big, 1e-6))  # the variance is inf: every normalized feature collapses to 0


def test_find_normalizations_and_conversion(tmp_path: Path) -> None:
    path = export_overflow_vit(OverflowViT(64, depth=1), str(tmp_path / "vit.onnx"))
    model = onnx.load(path)
    norms = find_normalizations(model)
    assert [n.name for n in norms] == ["/blocks.0/norm1", "/blocks.0/norm2", "/last_norm"]
    names = {node.name: node.op_type for node in model.graph.node}
    for norm in norms:
        assert norm.kind == "primitive" and norm.axis == -1 and norm.eps == pytest.approx(1e-6)
        ops = sorted(names[n] for n in norm.nodes if names[n] != "Constant")
        assert ops == ["Add", "Div", "Mul", "ReduceMean", "ReduceMean", "Sqrt", "Sub"]
    kept = norms[-1].nodes
    half = convert_float16(model, kept)
    kinds = {node.name: node for node in half.graph.node}
    assert all(init.data_type == onnx.TensorProto.FLOAT16 for init in half.graph.initializer)
    assert half.graph.input[0].type.tensor_type.elem_type == onnx.TensorProto.FLOAT
    assert half.graph.output[0].type.tensor_type.elem_type == onnx.TensorProto.FLOAT
    casts = [node for node in half.graph.node if node.op_type == "Cast"]
    # into FP16 after the input, into FP32 before the kept norm's mean and centring, back to FP16 after
    # its division, and the output back to FP32.
    assert len(casts) == 4
    inferred = onnx.shape_inference.infer_shapes(half)
    types = {v.name: v.type.tensor_type.elem_type for v in inferred.graph.value_info}
    assert types[kinds["/last_norm/ReduceMean_1"].output[0]] == onnx.TensorProto.FLOAT
    assert types[kinds["/blocks.0/norm1/ReduceMean_1"].output[0]] == onnx.TensorProto.FLOAT16


def test_guard_keeps_the_overflowing_final_norm_only_where_it_overflows(tmp_path: Path) -> None:
    """RMS 20: sum of squares 64 x 400 = 25.6 k (fits FP16) and 256 x 400 = 102 k (does not)."""
    from leapnbv_perception.backends.precision_plan import load_precision_plan

    narrow = table_row(64, 20.0, tmp_path, calib=4, verify=2)
    wide = table_row(256, 20.0, tmp_path, calib=4, verify=2)
    assert narrow["final_sum_squares"] == pytest.approx(64 * 400, rel=0.1)
    assert wide["final_sum_squares"] == pytest.approx(256 * 400, rel=0.1)
    assert "/last_norm" not in narrow["flagged"] and "/last_norm" in wide["flagged"]
    assert narrow["naive"] < 0.01 and narrow["guarded"] < 0.01
    assert not wide["naive"] < 0.5  # the overflowed variance zeroes the normalized features (or inf/NaN)
    assert wide["guarded"] < 0.01
    assert narrow["fp32_emulator"] < 1e-5 and wide["fp32_emulator"] < 1e-5
    check = tmp_path / "check_256"
    plan = load_precision_plan(str(check / "overflow_vit_256.precision_plan.json"))
    fp32_nodes = [node.name for node in onnx.load(str(tmp_path / "overflow_vit_256.onnx")).graph.node]
    selected, unmatched = plan.select(fp32_nodes)  # TensorRT names each layer after its ONNX node
    assert not unmatched and {"/last_norm/ReduceMean_1", "/last_norm/Sqrt", "/last_norm/Div"} <= set(selected)
    assert (check / "overflow_vit_256.fp16_ranges.png").stat().st_size > 1000
    report = (check / "overflow_vit_256.fp16_report.md").read_text()
    assert "| `/last_norm` | primitive | 256 |" in report and "overflow" in report


def test_cli_errors_are_one_line_with_exit_2(tmp_path: Path, capsys) -> None:
    from leapnbv_model_tools.__main__ import main

    assert main(["fp16-check", str(tmp_path / "absent.onnx"), "--calib", str(tmp_path), "--out", str(tmp_path)]) == 2
    assert capsys.readouterr().err.strip().count("\n") == 0
    path = export_overflow_vit(OverflowViT(64, depth=1), str(tmp_path / "vit.onnx"))
    np.save(tmp_path / "crops.npy", np.zeros((2, 3, 32, 32), np.float32))
    assert main(["fp16-check", path, "--calib", str(tmp_path / "crops.npy"), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert "does not fit the model input (N, 3, 64, 48)" in err and err.strip().count("\n") == 0
    np.save(tmp_path / "crops.npy", np.random.default_rng(0).uniform(size=(2, 3, 64, 48)).astype(np.float32))
    assert main(["fp16-check", path, "--calib", str(tmp_path / "crops.npy"), "--out", str(tmp_path / "o")]) == 0


def test_an_unusable_model_file_is_one_line_with_exit_2(tmp_path: Path, capsys) -> None:
    """An empty file (protobuf reads it as an empty model), a checkpoint and a truncated ONNX as the model."""
    from leapnbv_model_tools.__main__ import main
    from leapnbv_model_tools.checkpoint import random_smplerx, save_official

    path = export_overflow_vit(OverflowViT(64, depth=1), str(tmp_path / "vit.onnx"))
    np.save(tmp_path / "crops.npy", np.zeros((2, 3, 64, 48), np.float32))
    (tmp_path / "empty.onnx").write_bytes(b"")
    (tmp_path / "truncated.onnx").write_bytes(Path(path).read_bytes()[:2000])
    checkpoint = save_official(random_smplerx("t32"), str(tmp_path / "smpler_x_t32.pth.tar"))
    for model, message in ((tmp_path / "empty.onnx", "is not an ONNX model: no graph inputs, outputs or nodes"),
                           (tmp_path / "truncated.onnx", "is not a readable ONNX file"),
                           (checkpoint, "is not a readable ONNX file")):
        out = str(tmp_path / "o")
        assert main(["fp16-check", str(model), "--calib", str(tmp_path / "crops.npy"), "--out", out]) == 2
        err = capsys.readouterr().err
        assert err.startswith(f"fp16-check: model '{model}' {message}") and err.count("\n") == 1, err
        assert not (tmp_path / "o").exists()
