"""SMPLest-X in the model tools: structure, strict loading, export to the engine contract, FP16 check, distillation.

The full-size network (smplest_x_h, 687 M parameters) is checked on the meta device (keys and shapes, no weights);
everything that runs uses the narrow members of the same architecture (smplest_x_t32, smplest_x_t128).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import onnx
import pytest
import torch
from leapnbv_model_tools import export as export_module
from leapnbv_model_tools.checkpoint import (
    CheckpointError,
    load_network,
    manifest,
    parameter_count,
    random_network,
    read_manifest,
    save_official,
)
from leapnbv_model_tools.export import OUTPUT_NAMES, TENSORRT_OPERATORS, operator_types, parity_report
from leapnbv_model_tools.smplest_x import TOKEN_RANGES, SMPLestX
from torch.nn import functional as F

torch.set_num_threads(1)
VARIANT = "smplest_x_t32"
# The authors' figure: SMPLest-X (arXiv 2501.09782) scales ViT backbones "from Small to Huge (32M to 687M
# parameters)"; 687 M is the Huge model's encoder + decoder (its code prints that sum at start-up).
AUTHORS_HUGE_PARAMETERS = 687e6


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory) -> str:
    return save_official(random_network(VARIANT, seed=3), str(tmp_path_factory.mktemp("sx") / "smplest_x_t32.pth.tar"))


@pytest.fixture(scope="module")
def exported(checkpoint: str) -> str:
    from leapnbv_model_tools.__main__ import main

    out = str(Path(checkpoint).with_suffix(".onnx"))
    assert main(["export-hmr", "--checkpoint", checkpoint, "--variant", VARIANT, "--out", out]) == 0
    return out


def test_the_full_size_structure_manifest_and_parameter_count() -> None:
    keys = manifest("smplest_x_h")  # meta device: nothing allocated
    assert {k: tuple(v) for k, v in keys.items()} == read_manifest("smplest_x_h")
    count = parameter_count("smplest_x_h")
    assert count == 687_223_152 and abs(count - AUTHORS_HUGE_PARAMETERS) / AUTHORS_HUGE_PARAMETERS < 1e-3
    data = json.loads((Path(export_module.__file__).parent / "manifests" / "smplest_x_h.json").read_text())
    assert data["parameters_and_buffers"] == count  # no buffers: no BatchNorm in SMPLest-X
    assert keys["encoder.task_tokens"] == [1, 80, 1280] and keys["encoder.pos_embed"] == [1, 193, 1280]
    assert keys["encoder.blocks.31.attn.qkv.bias"] == [3840] and "encoder.blocks.32.norm1.weight" not in keys
    decoder = "decoder.transformer.transformer.layers"
    assert keys[f"{decoder}.5.0.fn.to_qkv.weight"] == [1536, 1280] and f"{decoder}.6.0.norm.weight" not in keys
    assert keys[f"{decoder}.0.1.fn.to_kv.weight"] == [1024, 1280]
    assert keys[f"{decoder}.0.1.fn.to_q.weight"] == [512, 1280]
    assert keys[f"{decoder}.0.2.fn.net.3.weight"] == [1280, 1280] and f"{decoder}.0.0.fn.to_qkv.bias" not in keys
    assert keys["decoder.transformer.pos_embedding"] == [1, 1, 1280]
    assert keys["decoder.transformer.to_token_embedding.weight"] == [1280, 80]
    assert keys["decoder.token_conv.weight"] == [512, 1280]
    assert keys["decoder.dec_body_pose.weight"] == [126, 21 * 512]
    assert keys["decoder.dec_hand_pose.weight"] == [180, 30 * 512]
    assert keys["decoder.dec_body_shape.weight"] == [10, 10 * 512] and keys["decoder.dec_face_cam.weight"] == [3, 512]
    assert not any(k.startswith(("body_position_net", "box_net", "hand_roi_net")) for k in keys)  # no hand RoI branch
    assert 4 * count > export_module.EXTERNAL_DATA_ABOVE_BYTES  # its export writes external data, as h32's


def _reference_outputs(weights, image: torch.Tensor, heads: int, depth: int, decoder_heads: int) -> dict:
    """The reference's test-time forward restated with torch.nn.functional on the state dict (float64)."""
    w = {k: v.double() for k, v in weights.items()}
    x = F.conv2d(image[:, :, ::2, ::2], w["encoder.patch_embed.proj.weight"], w["encoder.patch_embed.proj.bias"],
                 stride=16, padding=2)
    batch, dim, grid_h, grid_w = x.shape
    x = x.flatten(2).transpose(1, 2) + w["encoder.pos_embed"][:, 1:] + w["encoder.pos_embed"][:, :1]
    x = torch.cat([w["encoder.task_tokens"].expand(batch, -1, -1), x], dim=1)

    def attention(q, k, v, count):
        split = [t.reshape(batch, t.shape[1], count, -1).permute(0, 2, 1, 3) for t in (q, k, v)]
        scale = split[0].shape[-1] ** -0.5
        out = torch.softmax(split[0] @ split[1].transpose(-1, -2) * scale, dim=-1) @ split[2]
        return out.permute(0, 2, 1, 3).reshape(batch, q.shape[1], -1)

    for i in range(depth):
        p = f"encoder.blocks.{i}."
        h = F.layer_norm(x, (dim,), w[p + "norm1.weight"], w[p + "norm1.bias"], eps=1e-6)
        q, k, v = F.linear(h, w[p + "attn.qkv.weight"], w[p + "attn.qkv.bias"]).chunk(3, dim=-1)
        x = x + F.linear(attention(q, k, v, heads), w[p + "attn.proj.weight"], w[p + "attn.proj.bias"])
        h = F.layer_norm(x, (dim,), w[p + "norm2.weight"], w[p + "norm2.bias"], eps=1e-6)
        x = x + F.linear(F.gelu(F.linear(h, w[p + "mlp.fc1.weight"], w[p + "mlp.fc1.bias"])), w[p + "mlp.fc2.weight"],
                         w[p + "mlp.fc2.bias"])
    x = F.layer_norm(x, (dim,), w["encoder.last_norm.weight"], w["encoder.last_norm.bias"], eps=1e-6)
    tokens, image_feature = x[:, :80], x[:, 80:]  # the reference's feature map, back to rows: the same rows
    rows = torch.cat([tokens, image_feature], dim=1) + w["decoder.transformer.pos_embedding"][:, :1]
    for i in range(len({k.split(".")[4] for k in w if k.startswith("decoder.transformer.transformer.layers.")})):
        p = f"decoder.transformer.transformer.layers.{i}."

        def norm(x, j, p=p):
            return F.layer_norm(x, (dim,), w[f"{p}{j}.norm.weight"], w[f"{p}{j}.norm.bias"])  # eps 1e-5

        q, k, v = F.linear(norm(rows, 0), w[p + "0.fn.to_qkv.weight"]).chunk(3, dim=-1)
        rows = rows + F.linear(attention(q, k, v, decoder_heads), w[p + "0.fn.to_out.0.weight"],
                               w[p + "0.fn.to_out.0.bias"])
        k, v = F.linear(image_feature, w[p + "1.fn.to_kv.weight"]).chunk(2, dim=-1)
        q = F.linear(norm(rows, 1), w[p + "1.fn.to_q.weight"])
        rows = rows + F.linear(attention(q, k, v, decoder_heads), w[p + "1.fn.to_out.0.weight"],
                               w[p + "1.fn.to_out.0.bias"])
        h = F.gelu(F.linear(norm(rows, 2), w[p + "2.fn.net.0.weight"], w[p + "2.fn.net.0.bias"]))
        rows = F.linear(h, w[p + "2.fn.net.3.weight"], w[p + "2.fn.net.3.bias"]) + rows
    read = F.linear(rows, w["decoder.token_conv.weight"], w["decoder.token_conv.bias"])[:, :80]

    def head(name):
        start, end = TOKEN_RANGES[name]
        return F.linear(read[:, start:end].reshape(batch, -1), w[f"decoder.{name}.weight"], w[f"decoder.{name}.bias"])

    hands = head("dec_hand_pose")
    return {"root_pose": head("dec_body_root_pose"), "body_pose": head("dec_body_pose"), "lhand_pose": hands[:, :90],
            "rhand_pose": hands[:, 90:], "jaw_pose": head("dec_face_jaw_pose"), "betas": head("dec_body_shape"),
            "expression": head("dec_face_expression"), "cam_param": head("dec_body_cam")}


@pytest.mark.parametrize("variant", ["smplest_x_t32", "smplest_x_t128"])
def test_the_network_is_the_reference_forward(variant: str) -> None:
    model = random_network(variant, seed=1).double()
    image = torch.rand(2, 3, 512, 384, dtype=torch.float64)
    with torch.no_grad():
        got = model(image)
        expected = _reference_outputs(model.state_dict(), image, model.variant.num_heads, model.variant.depth,
                                      model.variant.decoder_heads)
    for name in OUTPUT_NAMES:
        assert got[name].shape == expected[name].shape, name
        torch.testing.assert_close(got[name], expected[name], rtol=1e-9, atol=1e-10, msg=name)
    # the readout is not symmetric in the hands: swapping them changes the outputs
    assert not torch.allclose(got["lhand_pose"], got["rhand_pose"])


def test_round_trip_and_the_wrong_family_in_one_line(checkpoint: str, tmp_path: Path, capsys) -> None:
    from leapnbv_model_tools.__main__ import main

    loaded = load_network(checkpoint, VARIANT)
    assert isinstance(loaded, SMPLestX) and not loaded.training
    original = random_network(VARIANT, seed=3).state_dict()
    assert all(torch.equal(original[k], v) for k, v in loaded.state_dict().items())
    with pytest.raises(CheckpointError) as refused:
        load_network(checkpoint, "t32")
    assert refused.value.one_line().startswith(f"checkpoint '{checkpoint}' is a SMPLest-X checkpoint, not SMPLer-X")
    smpler = save_official(random_network("t32", seed=0), str(tmp_path / "smpler_x_t32.pth.tar"))
    out = str(tmp_path / "wrong.onnx")
    assert main(["export-hmr", "--checkpoint", smpler, "--variant", VARIANT, "--out", out]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"export-hmr: checkpoint '{smpler}' is a SMPLer-X checkpoint, not SMPLest-X (its modules: "
                          "body_position_net, body_regressor, box_net, encoder, face_regressor, hand_position_net, "
                          "hand_regressor, hand_roi_net); it does not fit SMPLest-X smplest_x_t32")
    assert err.strip().count("\n") == 0 and not Path(out).exists()
    # Missing, unexpected and misshaped keys of its own family: counted and the first of each named.
    network = torch.load(checkpoint, weights_only=True)["network"]
    network.pop("module.decoder.dec_face_cam.bias")
    network["module.decoder.extra.weight"] = torch.zeros(1)
    network["module.decoder.token_conv.weight"] = torch.zeros(3, 3)
    torch.save({"network": network}, str(tmp_path / "broken.pth.tar"))
    broken = str(tmp_path / "broken.pth.tar")
    assert main(["export-hmr", "--checkpoint", broken, "--variant", VARIANT, "--out", out]) == 2
    err = capsys.readouterr().err
    assert ("does not fit SMPLest-X smplest_x_t32 (embed 32, depth 1): 1 missing, 1 unexpected, 1 of the wrong shape; "
            "first missing decoder.dec_face_cam.bias; first unexpected decoder.extra.weight; first wrong shape "
            "decoder.token_conv.weight: checkpoint (3, 3), network (16, 32)") in err
    assert err.strip().count("\n") == 0 and "is a SMPLer-X" not in err
    assert main(["export-hmr", "--checkpoint", checkpoint, "--variant", VARIANT, "--out", out, "--without-hands"]) == 2
    assert "no separate hand branch" in capsys.readouterr().err


def test_export_contract_metadata_parity_and_operators(checkpoint: str, exported: str) -> None:
    metadata = {p.key: p.value for p in onnx.load(exported, load_external_data=False).metadata_props}
    assert metadata["leapnbv.variant"] == VARIANT and metadata["leapnbv.input_size"] == "512x384"
    assert metadata["leapnbv.unmirror_left_hand"] == "false" and metadata["leapnbv.box_ratio"] == "1.2"
    assert metadata["leapnbv.hands"] == "estimated"
    operators = set(operator_types(exported))
    assert operators <= TENSORRT_OPERATORS and "LayerNormalization" not in operators
    graph = onnx.load(exported, load_external_data=False).graph
    assert [o.name for o in graph.output] == list(OUTPUT_NAMES)
    shapes = {o.name: [d.dim_value for d in o.type.tensor_type.shape.dim] for o in graph.output}
    assert shapes == {"root_pose": [1, 6], "body_pose": [1, 126], "lhand_pose": [1, 90], "rhand_pose": [1, 90],
                      "jaw_pose": [1, 6], "betas": [1, 10], "expression": [1, 10], "cam_param": [1, 3]}
    # The training-only heads and the unused token embedding are not in the graph.
    names = {t.name for t in graph.initializer}
    assert not any("dec_face_cam" in n or "to_token_embedding" in n or "dec_hand_root_pose" in n for n in names)
    crops = np.random.default_rng(4).uniform(0.0, 1.0, size=(2, 3, 512, 384)).astype(np.float32)
    report = parity_report(load_network(checkpoint, VARIANT), exported, crops)
    assert report.ok
    for output in report.outputs:
        assert output.difference / max(1.0, output.scale) <= 1e-4, output


def test_external_data_export(checkpoint: str, tmp_path: Path, monkeypatch) -> None:
    """The path the 2.8 GB smplest_x_h takes (weights beside the graph in <out>.data), on the tiny variant."""
    from leapnbv_model_tools.__main__ import main

    from leapnbv_perception.backends.onnxruntime_backend import OnnxRuntimeBackend

    monkeypatch.setattr(export_module, "EXTERNAL_DATA_ABOVE_BYTES", 0)
    out = tmp_path / "external.onnx"
    assert main(["export-hmr", "--checkpoint", checkpoint, "--variant", VARIANT, "--out", str(out),
                 "--input", "256x192", "--parity-crops", "1"]) == 0
    data = tmp_path / "external.onnx.data"
    assert data.stat().st_size > 0.9 * 4 * sum(p.numel() for p in SMPLestX(VARIANT).encoder.parameters())
    assert out.stat().st_size < data.stat().st_size
    backend = OnnxRuntimeBackend(str(out))
    outputs = backend.run({"img": np.zeros((1, 3, 256, 192), np.float32)})
    assert all(np.all(np.isfinite(outputs[name])) for name in OUTPUT_NAMES)


def test_the_runtime_estimator_takes_it_with_its_parameters(exported: str) -> None:
    """The HMR node's engine path (OnnxRuntimeBackend + HumanMeshEstimator + the FP32 SMPL-X tail)."""
    from leapnbv_perception.backends.onnxruntime_backend import OnnxRuntimeBackend
    from leapnbv_perception.hmr import ExportMetadataError, HumanMeshEstimator
    from leapnbv_perception.rotations import matrix_to_axis_angle, rot6d_to_matrix
    from leapnbv_perception.smplx_layer import SMPLXModel
    from leapnbv_stand_ins.files import ensure_stand_in_body_model

    body = SMPLXModel.load(ensure_stand_in_body_model())
    with pytest.raises(ExportMetadataError, match="unmirror_left_hand=false.*box ratio 1.2"):
        HumanMeshEstimator(OnnxRuntimeBackend(exported), body)  # the SMPLer-X defaults: refused
    backend = OnnxRuntimeBackend(exported)
    estimator = HumanMeshEstimator(backend, body, box_scale=1.2, unmirror_left_hand=False)
    image = np.random.default_rng(0).integers(0, 255, size=(480, 640, 3), dtype=np.uint8)
    estimate = estimator.estimate(image, [200.0, 60.0, 420.0, 460.0])
    assert estimator.hands_estimated
    assert estimate.vertices.shape == (body.v_template.shape[0], 3) and np.all(np.isfinite(estimate.vertices))
    assert np.all(np.isfinite(estimate.joints)) and estimate.cam_translation[2] > 0
    # The left hand is the engine's, not mirrored: the axis-angle of its 6D output as it is.
    from leapnbv_perception.hmr_crop import engine_input_for_box

    engine_input, _, _ = engine_input_for_box(image, [200.0, 60.0, 420.0, 460.0], (512, 384), 1.2)
    raw = backend.run({"img": engine_input})
    left = matrix_to_axis_angle(rot6d_to_matrix(np.asarray(raw["lhand_pose"], np.float64).reshape(15, 6))).reshape(-1)
    np.testing.assert_allclose(estimate.left_hand, left, atol=1e-5)


def test_fp16_check_finds_the_decoders_normalizations(exported: str, tmp_path: Path) -> None:
    from leapnbv_model_tools.fp16 import fp16_check
    from leapnbv_model_tools.fp16_normalizations import find_normalizations

    norms = find_normalizations(onnx.load(exported))
    encoder = [n for n in norms if "/encoder/" in n.name]
    decoder = [n for n in norms if "/decoder/" in n.name]
    assert len(encoder) == 2 * 1 + 1 and len(decoder) == 3 * 1 and len(norms) == 6  # t32: 1 block, 1 decoder layer
    assert all(abs(n.eps - 1e-6) < 1e-9 for n in encoder) and all(abs(n.eps - 1e-5) < 1e-8 for n in decoder)
    crops = np.random.default_rng(0).uniform(0.0, 1.0, size=(2, 3, 512, 384)).astype(np.float32)
    result = fp16_check(exported, crops, str(tmp_path / "fp16"), verify=False)
    assert {n.name for n in result.norms} == {n.name for n in norms}
    assert all(n.stats["max_sum_squares"] > 0 for n in result.norms)


def test_overflow_table_row_with_the_decoder(tmp_path: Path) -> None:
    """The table's construction followed by SMPLest-X's decoder (width 256, RMS 20: 256 x 400 = 102 k > 65,504)."""
    from leapnbv_model_tools.overflow_table import format_table, table_row

    row = table_row(256, 20.0, tmp_path, calib=4, verify=2, decoder_depth=1)
    assert row["decoder_norms"] == 3 and row["norms"] == 2 * 2 + 1 + 3
    assert row["final_sum_squares"] == pytest.approx(256 * 400, rel=0.1)
    assert row["flagged"] == ["/last_norm"]  # the decoder's inputs are last_norm's outputs: O(1) per feature
    assert row["decoder_max_sum_squares"] < 65504 / 10
    assert not row["naive"] < 0.5 and row["guarded"] < 0.01
    table = format_table([row])
    assert "| 256 + decoder | " in table and "3 in the decoder" in table


def test_distill_takes_it_as_teacher(tmp_path: Path, checkpoint: str) -> None:
    """A SMPLest-X teacher beside a SMPLer-X one: its own cache folder, its meshes without the un-mirroring."""
    import cv2

    from leapnbv_model_tools.distill import DistillConfig, TeacherCache, crop_sha256, distill
    from leapnbv_model_tools.torch_smplx import TorchSMPLX, centroid_relative, mesh_from_outputs

    from leapnbv_perception.smplx_layer import SMPLXModel
    from leapnbv_stand_ins.files import ensure_stand_in_body_model

    rng = np.random.default_rng(0)
    lines = []
    for index in range(2):
        cv2.imwrite(str(tmp_path / f"t{index}.png"), rng.integers(0, 255, size=(96, 80, 3), dtype=np.uint8))
        lines.append(json.dumps({"image": f"t{index}.png", "box": [10, 8, 60, 90]}))
    (tmp_path / "train.jsonl").write_text("\n".join(lines) + "\n")
    body = ensure_stand_in_body_model("small", tmp_path / "body")
    result = distill(DistillConfig(train=str(tmp_path / "train.jsonl"), val="", teacher=checkpoint,
                                   teacher_variant=VARIANT, student_variant="t32", body_model=body,
                                   out=str(tmp_path / "run"), epochs=1, batch_size=2, lr=1e-3,
                                   cache=str(tmp_path / "cache"), export=False))
    assert result["step"] == 1 and np.isfinite(result["history"]["loss"][-1][1])
    assert (result["teacher_computed"], result["teacher_reused"]) == (2, 0)
    folders = [p for p in (tmp_path / "cache").iterdir() if p.is_dir()]
    assert len(folders) == 1
    identity = json.loads((folders[0] / "teacher.json").read_text())
    assert identity["teacher_variant"] == VARIANT and "not mirrored" in identity["mesh"]
    # The cached mesh is the teacher's own forward through the layer without un-mirroring.
    layer = TorchSMPLX(SMPLXModel.load(body))
    cache = TeacherCache(str(tmp_path / "cache"), identity["teacher_sha256"], VARIANT, identity["body_model_sha256"],
                         (256, 192), unmirror_left=False)
    assert cache.folder == folders[0]
    cached = sorted(folders[0].glob("*.npy"))
    assert len(cached) == 2
    teacher = load_network(checkpoint, VARIANT)
    from leapnbv_model_tools.distill import crop_and_box, read_manifest

    crop, _ = crop_and_box(read_manifest(str(tmp_path / "train.jsonl"))[0], (256, 192))
    with torch.no_grad():
        outputs = teacher(torch.from_numpy(crop[None]))
        mine = centroid_relative(mesh_from_outputs(layer, outputs, False))[0].numpy()
        mirrored = centroid_relative(mesh_from_outputs(layer, outputs, True))[0].numpy()
    np.testing.assert_allclose(np.load(cache.path(crop_sha256(crop))), mine, atol=1e-6)
    assert np.abs(mine - mirrored).max() > 1e-4  # the flag matters: the left hand moves
    smpler = TeacherCache(str(tmp_path / "cache"), identity["teacher_sha256"], "t32", identity["body_model_sha256"],
                          (256, 192))
    assert smpler.folder != cache.folder
