"""Tests of leapnbv_model_tools (run in the tools environment: tools/run.sh python -m pytest tools/tests)."""

from __future__ import annotations

import math
import os
from pathlib import Path

import numpy as np
import onnx
import pytest
import torch
from leapnbv_model_tools.checkpoint import (
    CheckpointError,
    load_smplerx,
    manifest,
    random_smplerx,
    read_manifest,
    save_official,
)
from leapnbv_model_tools.smplerx import roi_align, sample_points
from torch.nn import functional as F


def reference_roi_align(feature: np.ndarray, roi: np.ndarray, out_h: int, out_w: int) -> np.ndarray:
    """RoIAlign (avg, aligned=False, sampling_ratio=0) as mmcv/torchvision compute it, one loop per sample."""
    channels, height, width = feature.shape
    x1, y1, x2, y2 = roi
    roi_w, roi_h = max(x2 - x1, 1.0), max(y2 - y1, 1.0)
    bin_w, bin_h = roi_w / out_w, roi_h / out_h
    grid_w, grid_h = math.ceil(roi_w / out_w), math.ceil(roi_h / out_h)
    out = np.zeros((channels, out_h, out_w))
    for ph in range(out_h):
        for pw in range(out_w):
            total = np.zeros(channels)
            for iy in range(grid_h):
                y = y1 + ph * bin_h + (iy + 0.5) * bin_h / grid_h
                for ix in range(grid_w):
                    x = x1 + pw * bin_w + (ix + 0.5) * bin_w / grid_w
                    if y < -1.0 or y > height or x < -1.0 or x > width:
                        continue
                    yy, xx = max(y, 0.0), max(x, 0.0)
                    y_low, x_low = int(yy), int(xx)
                    if y_low >= height - 1:
                        y_low = y_high = height - 1
                        yy = float(y_low)
                    else:
                        y_high = y_low + 1
                    if x_low >= width - 1:
                        x_low = x_high = width - 1
                        xx = float(x_low)
                    else:
                        x_high = x_low + 1
                    ly, lx = yy - y_low, xx - x_low
                    total += ((1 - ly) * (1 - lx) * feature[:, y_low, x_low] + (1 - ly) * lx * feature[:, y_low, x_high]
                              + ly * (1 - lx) * feature[:, y_high, x_low] + ly * lx * feature[:, y_high, x_high])
            out[:, ph, pw] = total / max(grid_h * grid_w, 1)
    return out


@pytest.mark.parametrize("roi", [[3.2, 5.7, 14.9, 20.1], [-4.0, -2.5, 9.0, 6.0], [40.0, 50.0, 47.5, 63.9],
                                 [10.0, 10.0, 10.3, 10.2], [0.0, 0.0, 48.0, 64.0]])
def test_roi_align_matches_the_reference_loops(roi) -> None:
    rng = np.random.default_rng(1)
    feature = rng.normal(size=(1, 5, 64, 48)).astype(np.float64)
    got = roi_align(torch.from_numpy(feature), torch.tensor([roi], dtype=torch.float64), (16, 16))[0].numpy()
    np.testing.assert_allclose(got, reference_roi_align(feature[0], np.array(roi), 16, 16), atol=1e-10)


def test_sample_points_matches_grid_sample() -> None:
    torch.manual_seed(0)
    feature = torch.randn(2, 4, 16, 12, dtype=torch.float64)
    points = torch.rand(2, 7, 2, dtype=torch.float64) * torch.tensor([11.0, 15.0], dtype=torch.float64)
    points[0, 0] = torch.tensor([11.0, 15.0])  # the far corner exactly
    grid = torch.stack([points[..., 0] / 11 * 2 - 1, points[..., 1] / 15 * 2 - 1], dim=2)[:, :, None]
    expected = F.grid_sample(feature, grid, align_corners=True)[:, :, :, 0].permute(0, 2, 1)
    torch.testing.assert_close(sample_points(feature, points), expected, atol=1e-12, rtol=0)


def test_manifest_in_the_repository_is_the_network() -> None:
    for variant in ("s32", "b32", "l32", "h32"):
        assert read_manifest(variant) == {k: tuple(v) for k, v in manifest(variant).items()}


def test_random_checkpoint_round_trip_and_wrong_variant(tmp_path: Path) -> None:
    model = random_smplerx("s32", seed=3)
    path = save_official(model, str(tmp_path / "smpler_x_s32.pth.tar"))
    raw = torch.load(path, map_location="cpu", weights_only=True)
    assert set(raw) == {"epoch", "network"} and all(k.startswith("module.") for k in raw["network"])
    loaded = load_smplerx(path, "s32")
    image = torch.rand(1, 3, 512, 384)
    with torch.no_grad():
        first, second = model(image), loaded(image)
    for name in first:
        torch.testing.assert_close(first[name], second[name], atol=0, rtol=0)
    with pytest.raises(CheckpointError, match=r"(?s)does not fit SMPLer-X b32.*171 of the wrong shape "
                       r"\(its keys and shapes are those of s32\).*encoder\.blocks\.0\.attn"):
        load_smplerx(path, "b32")
    # The reference's older key names load too (backbone -> encoder, ...).
    renamed = {k.replace("module.encoder.", "module.backbone."): v for k, v in raw["network"].items()}
    torch.save({"network": renamed}, str(tmp_path / "old_names.pth.tar"))
    load_smplerx(str(tmp_path / "old_names.pth.tar"), "s32")
    del renamed["module.face_regressor.expr_out.0.bias"]
    renamed["module.extra.weight"] = torch.zeros(1)
    torch.save({"network": renamed}, str(tmp_path / "broken.pth.tar"))
    with pytest.raises(CheckpointError, match=r"(?s)missing \(1\): face_regressor.expr_out.0.bias.*unexpected \(1\)"):
        load_smplerx(str(tmp_path / "broken.pth.tar"), "s32")


def test_export_parity_contract_metadata_and_the_body_only_export(tmp_path: Path) -> None:
    """s32 exported in full and body-only (--without-hands) from the same weights: the body-only engine's
    root/body/betas/cam/jaw/expression are the full engine's, its hands the identity rotation."""
    import onnxruntime
    from leapnbv_model_tools.__main__ import main
    from leapnbv_model_tools.export import OUTPUT_NAMES

    from leapnbv_perception.backends.onnxruntime_backend import OnnxRuntimeBackend
    from leapnbv_perception.hmr import HumanMeshEstimator
    from leapnbv_perception.smplx_layer import SMPLXModel
    from leapnbv_stand_ins.files import ensure_stand_in_body_model

    checkpoint = save_official(random_smplerx("s32", seed=5), str(tmp_path / "smpler_x_s32.pth.tar"))
    full, body_only = str(tmp_path / "s32.onnx"), str(tmp_path / "s32_body_only.onnx")
    assert main(["export-hmr", "--checkpoint", checkpoint, "--variant", "s32", "--out", full]) == 0
    metadata = {p.key: p.value for p in onnx.load(full, load_external_data=False).metadata_props}
    assert metadata["leapnbv.variant"] == "smpler_x_s32" and metadata["leapnbv.input_size"] == "512x384"
    assert metadata["leapnbv.hands"] == "estimated"
    assert main(["export-hmr", "--checkpoint", checkpoint, "--variant", "b32", "--out", full + ".b32"]) == 2
    assert main(["export-hmr", "--checkpoint", checkpoint, "--variant", "s32", "--out", body_only,
                 "--without-hands", "--parity-crops", "1"]) == 0
    body_model = onnx.load(body_only)
    assert {p.key: p.value for p in body_model.metadata_props}["leapnbv.hands"] == "not_estimated"
    assert "ConvTranspose" not in {node.op_type for node in body_model.graph.node}  # no box net, no hand RoI
    assert os.path.getsize(body_only) < 0.8 * os.path.getsize(full)  # nor their weights

    sessions = [onnxruntime.InferenceSession(path, providers=["CPUExecutionProvider"]) for path in (full, body_only)]
    crops = np.random.default_rng(2).uniform(0.0, 1.0, size=(2, 1, 3, 512, 384)).astype(np.float32)
    identity = np.tile(np.array([1.0, 0.0, 0.0, 1.0, 0.0, 0.0], dtype=np.float32), 15)[None]
    for crop in crops:
        got_full, got_body = (dict(zip(OUTPUT_NAMES, s.run(list(OUTPUT_NAMES), {"img": crop}))) for s in sessions)
        for name in ("root_pose", "body_pose", "jaw_pose", "betas", "expression", "cam_param"):
            np.testing.assert_allclose(got_body[name], got_full[name], rtol=0, atol=1e-5, err_msg=name)
        for name in ("lhand_pose", "rhand_pose"):
            assert got_body[name].shape == got_full[name].shape == (1, 90)
            np.testing.assert_array_equal(got_body[name], identity)
            assert np.abs(got_full[name] - identity).max() > 1e-2  # the full engine's hands are its own
    # Through the project's estimator: the hands decode to axis-angle 0 (the SMPL-X hand mean pose), and the
    # estimator says that the engine does not estimate them.
    estimator = HumanMeshEstimator(OnnxRuntimeBackend(body_only), SMPLXModel.load(ensure_stand_in_body_model()))
    assert estimator.hands_estimated is False
    estimate = estimator.estimate(np.full((480, 640, 3), 128, dtype=np.uint8), [200.0, 60.0, 420.0, 460.0])
    np.testing.assert_array_equal(estimate.left_hand, np.zeros(45))
    np.testing.assert_array_equal(estimate.right_hand, np.zeros(45))
    assert HumanMeshEstimator(OnnxRuntimeBackend(full), estimator.body_model).hands_estimated is True
