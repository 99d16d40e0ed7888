"""quantize-int8's recipe: U8S8 with per-channel weights after the pre-processing, per CPU, on small graphs."""

from __future__ import annotations

from pathlib import Path
from typing import Dict, List

import numpy as np
import onnx
import onnxruntime
import pytest
from onnx import TensorProto, helper, numpy_helper

from leapnbv_model_tools import int8_recipe, quantize_int8
from leapnbv_model_tools.int8_graph import (
    conv_transpose_to_conv,
    phase_conv_weights,
    quantized_tensor_types,
    weight_scales,
)

VNNI_FLAGS = ["fpu", "avx2", "avx512f", "avx512bw", "avx512_vnni"]


def _upsampling_model(path: Path, seed: int = 0, with_norm: bool = True, bias: bool = False) -> Path:
    """The input x (1, 8, 6, 5) -> Conv 3x3, Relu, ConvTranspose(k4, s2, p1) [, BatchNormalization], Relu, Conv 1x1."""
    rng = np.random.default_rng(seed)
    inits = [numpy_helper.from_array(rng.normal(0, 0.3, (16, 8, 3, 3)).astype(np.float32), "w0"),
             numpy_helper.from_array(rng.normal(0, 0.1, 16).astype(np.float32), "b0"),
             numpy_helper.from_array(rng.normal(0, 0.2, (16, 12, 4, 4)).astype(np.float32), "wt"),
             numpy_helper.from_array(rng.normal(0, 0.2, (4, 12, 1, 1)).astype(np.float32), "w2")]
    nodes = [helper.make_node("Conv", ["x", "w0", "b0"], ["c0"], name="/model/stem/Conv", pads=[1, 1, 1, 1]),
             helper.make_node("Relu", ["c0"], ["r0"], name="/model/stem/Relu")]
    up_inputs = ["r0", "wt"]
    if bias:
        inits.append(numpy_helper.from_array(rng.normal(0, 0.1, 12).astype(np.float32), "bt"))
        up_inputs.append("bt")
    nodes.append(helper.make_node("ConvTranspose", up_inputs, ["up"], name="/model/box_net/deconv/ConvTranspose",
                                  kernel_shape=[4, 4], strides=[2, 2], pads=[1, 1, 1, 1]))
    last = "up"
    if with_norm:
        for name, values in (("g", rng.uniform(0.5, 1.5, 12)), ("beta", rng.normal(0, 0.1, 12)),
                             ("mean", rng.normal(0, 0.1, 12)), ("var", rng.uniform(0.5, 2.0, 12))):
            inits.append(numpy_helper.from_array(values.astype(np.float32), name))
        nodes.append(helper.make_node("BatchNormalization", ["up", "g", "beta", "mean", "var"], ["bn"],
                                      name="/model/box_net/deconv/BatchNormalization", epsilon=1e-5))
        last = "bn"
    nodes += [helper.make_node("Relu", [last], ["r1"], name="/model/box_net/deconv/Relu"),
              helper.make_node("Conv", ["r1", "w2"], ["y"], name="/model/body_regressor/out/Conv")]
    graph = helper.make_graph(nodes, "up", [helper.make_tensor_value_info("x", TensorProto.FLOAT, [1, 8, 6, 5])],
                              [helper.make_tensor_value_info("y", TensorProto.FLOAT, [1, 4, 12, 10])], inits)
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    entry = model.metadata_props.add()
    entry.key, entry.value = "leapnbv.variant", "test"
    onnx.save(model, str(path))
    return path


def _run(path, x: np.ndarray) -> np.ndarray:
    session = onnxruntime.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    return session.run(None, {session.get_inputs()[0].name: x})[0]


def _feeds(count: int, seed: int = 1) -> List[Dict[str, np.ndarray]]:
    rng = np.random.default_rng(seed)
    return [{"x": rng.uniform(-1, 1, (1, 8, 6, 5)).astype(np.float32)} for _ in range(count)]


@pytest.mark.parametrize("with_norm,bias", [(True, False), (False, True)])
def test_the_transposed_convolution_rewrite_computes_the_same_function(tmp_path: Path, with_norm: bool,
                                                                       bias: bool) -> None:
    source = _upsampling_model(tmp_path / "m.onnx", with_norm=with_norm, bias=bias)
    model = onnx.load(str(source))
    assert conv_transpose_to_conv(model) == 1
    ops = [n.op_type for n in model.graph.node]
    assert "ConvTranspose" not in ops and "DepthToSpace" in ops
    assert ("BatchNormalization" in ops) is False  # folded into the phase convolution (or there was none)
    rewritten = tmp_path / "r.onnx"
    onnx.save(onnx.shape_inference.infer_shapes(model), str(rewritten))
    x = _feeds(1)[0]["x"]
    expected, got = _run(source, x), _run(rewritten, x)
    assert got.shape == expected.shape == (1, 4, 12, 10)
    np.testing.assert_allclose(got, expected, rtol=1e-5, atol=1e-5)


def test_phase_weights_place_each_kernel_tap_of_the_transposed_convolution() -> None:
    weight = np.arange(1 * 1 * 16, dtype=np.float32).reshape(1, 1, 4, 4)  # W[c, o, kh, kw] = 4 kh + kw
    phases, bias = phase_conv_weights(weight, np.array([2.0], np.float32))
    # phase (a, b) = (0, 0): rows i-1, i are kernel rows 3, 1; phase (1, 1): rows i, i+1 are kernel rows 2, 0
    np.testing.assert_array_equal(phases[0, 0], [[15, 13], [7, 5]])
    np.testing.assert_array_equal(phases[3, 0], [[10, 8], [2, 0]])
    np.testing.assert_array_equal(bias, [2, 2, 2, 2])


def _quantized(tmp_path: Path, name: str, keep_fp32: str = "none") -> onnx.ModelProto:
    source = _upsampling_model(tmp_path / "m.onnx")
    prepared = tmp_path / "prepared.onnx"
    assert int8_recipe.prepare(str(source), str(prepared)) == 1
    out = tmp_path / f"{name}.onnx"
    excluded = int8_recipe.excluded_nodes(onnx.load(str(prepared)), keep_fp32)
    int8_recipe.quantize(str(prepared), str(out), quantize_int8.FeedReader(_feeds(8)), int8_recipe.recipe(name),
                         nodes_to_exclude=excluded)
    return onnx.load(str(out))


def test_u8s8_writes_uint8_activations_and_per_channel_int8_weights_after_the_pre_processing(tmp_path: Path) -> None:
    model = _quantized(tmp_path, "u8s8")
    types = quantized_tensor_types(model)
    assert set(types["activations"]) == {"UINT8"} and types["activations"]["UINT8"] >= 3, types
    assert set(types["weights"]) == {"INT8"} and types["weights"]["INT8"] == 3, types  # stem, phase conv, head
    # one scale per output channel: 16 (stem), 4 x 12 (the phase convolution), 4 (the head)
    assert sorted(weight_scales(model).values()) == [(4,), (16,), (48,)]
    # the pre-processing ran (onnxruntime marks its output) and the rewrite left no float ConvTranspose
    assert "onnx.quant.pre_process" in {p.key for p in model.metadata_props}
    assert not any(n.op_type == "ConvTranspose" for n in model.graph.node)


def _output_error(tmp_path: Path, model: onnx.ModelProto) -> float:
    """The largest error of the quantized model on an input it was not calibrated on, as a share of the output."""
    x = _feeds(1, seed=9)[0]["x"]
    path = tmp_path / "check.onnx"
    onnx.save(model, str(path))
    reference = _run(tmp_path / "m.onnx", x)
    return float(np.abs(_run(path, x) - reference).max() / np.abs(reference).max())


def test_the_recipe_chosen_for_this_cpu_keeps_the_output(tmp_path: Path) -> None:
    # Plain U8S8 is exact only where the CPU has VNNI / AMX: AVX2 and AVX-512 without VNNI sum u8 x s8
    # pairs in int16 (VPMADDUBSW) and saturate (measured on an AVX2-only EPYC: 14 % error). The recipe the
    # tool picks for the running CPU must keep the output whatever the CPU is.
    chosen, why = int8_recipe.choose_recipe("auto", int8_recipe.this_cpu())
    assert _output_error(tmp_path, _quantized(tmp_path, chosen.name)) < 0.05, why


def test_reduce_range_keeps_the_output_on_every_cpu(tmp_path: Path) -> None:
    # 7-bit weights cannot saturate the int16 pair sums, so this recipe is safe on any x86 kernel
    assert _output_error(tmp_path, _quantized(tmp_path, "u8s8-reduce-range")) < 0.05


def test_s8s8_stays_available_with_symmetric_int8_activations(tmp_path: Path) -> None:
    model = _quantized(tmp_path, "s8s8")
    types = quantized_tensor_types(model)
    assert set(types["activations"]) == {"INT8"} and set(types["weights"]) == {"INT8"}, types
    initializers = {i.name: numpy_helper.to_array(i) for i in model.graph.initializer}
    zero_points = [initializers[n.input[2]] for n in model.graph.node if n.op_type == "QuantizeLinear"]
    assert zero_points and all(np.all(z == 0) for z in zero_points)  # what TensorRT accepts


def test_reduce_range_keeps_the_weights_in_seven_bits(tmp_path: Path) -> None:
    model = _quantized(tmp_path, "u8s8-reduce-range")
    initializers = {i.name: numpy_helper.to_array(i) for i in model.graph.initializer}
    weights = [initializers[n.input[0]] for n in model.graph.node
               if n.op_type == "DequantizeLinear" and n.input[0] in initializers
               and initializers[n.input[0]].dtype == np.int8]
    assert weights and max(int(np.abs(w.astype(np.int32)).max()) for w in weights) <= 64


def test_keep_fp32_heads_leaves_the_regression_heads_unquantized(tmp_path: Path) -> None:
    model = _quantized(tmp_path, "u8s8", keep_fp32="heads")
    weights = weight_scales(model)
    assert sorted(weights.values()) == [(16,), (48,)]  # the head's Conv (/model/body_regressor/) stays FP32
    head = next(n for n in model.graph.node if n.name == "/model/body_regressor/out/Conv")
    assert head.input[1] == "w2"


@pytest.mark.parametrize("machine,flags,kind,recipe", [
    ("x86_64", VNNI_FLAGS, "x86-vnni", "u8s8"),
    ("x86_64", ["avx2", "avx_vnni"], "x86-vnni", "u8s8"),
    ("x86_64", ["avx2", "amx_tile", "amx_int8"], "x86-vnni", "u8s8"),
    ("x86_64", ["avx2", "avx512f"], "x86-avx2", "u8s8-reduce-range"),
    ("x86_64", ["sse4_2"], "other", "u8s8"),
    ("aarch64", ["fp", "asimd", "asimddp"], "arm64", "s8s8"),
])
def test_the_auto_recipe_follows_the_cpu(machine: str, flags: List[str], kind: str, recipe: str) -> None:
    cpu = int8_recipe.classify_cpu(machine, flags, "test cpu")
    assert cpu.kind == kind
    chosen, why = int8_recipe.choose_recipe("auto", cpu)
    assert chosen.name == recipe and kind in why
    assert int8_recipe.choose_recipe("s8s8", cpu)[0].activation_type == "int8"


def test_read_cpuinfo_takes_the_flags_and_model_name(tmp_path: Path) -> None:
    info = tmp_path / "cpuinfo"
    info.write_text("processor\t: 0\nmodel\t\t: 207\nmodel name\t: Test Xeon\nflags\t\t: fpu avx2 avx512_vnni\n\n"
                    "processor\t: 1\nflags\t\t: fpu\n")
    assert int8_recipe.read_cpuinfo(str(info)) == (["fpu", "avx2", "avx512_vnni"], "Test Xeon")
    assert int8_recipe.read_cpuinfo(str(tmp_path / "absent")) == ([], "")


def _tiny_detector(path: Path) -> Path:
    """The input images (1, 3, 32, 32) -> Conv stride 8 -> (1, 84, 16): a YOLO-shaped output (4 box rows, 80 scores)."""
    rng = np.random.default_rng(3)
    inits = [numpy_helper.from_array(rng.normal(0, 0.2, (84, 3, 8, 8)).astype(np.float32), "w"),
             numpy_helper.from_array(np.full(84, 4.0, np.float32), "b"),
             numpy_helper.from_array(np.array([1, 84, 16], np.int64), "shape")]
    nodes = [helper.make_node("Conv", ["images", "w", "b"], ["c"], strides=[8, 8], name="/model/Conv"),
             helper.make_node("Relu", ["c"], ["r"], name="/model/Relu"),
             helper.make_node("Reshape", ["r", "shape"], ["output0"], name="/model/Reshape")]
    graph = helper.make_graph(nodes, "det", [helper.make_tensor_value_info("images", TensorProto.FLOAT,
                                                                            [1, 3, 32, 32])],
                              [helper.make_tensor_value_info("output0", TensorProto.FLOAT, [1, 84, 16])], inits)
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    entry = model.metadata_props.add()
    entry.key, entry.value = "leapnbv.producer", "test"
    onnx.save(model, str(path))
    return path


def test_the_command_prints_the_choice_and_writes_it_in_the_metadata(tmp_path: Path, monkeypatch,
                                                                     capsys: pytest.CaptureFixture) -> None:
    rng = np.random.default_rng(0)
    frames = [(rng.integers(0, 255, (48, 64, 3), dtype=np.uint8), np.array([4.0, 4.0, 40.0, 40.0]))
              for _ in range(4)]
    monkeypatch.setattr(quantize_int8, "rendered_frames", lambda count, offset: frames[:count])
    monkeypatch.setattr(int8_recipe, "read_cpuinfo", lambda path="/proc/cpuinfo": (VNNI_FLAGS, "Test Xeon"))
    monkeypatch.setattr(int8_recipe.platform, "machine", lambda: "x86_64")
    source = _tiny_detector(tmp_path / "det.onnx")
    out = tmp_path / "det.int8.onnx"
    assert quantize_int8.main(["detector", str(source), "--out", str(out), "--calib", "3", "--eval", "1"]) == 0
    printed = capsys.readouterr().out
    assert "recipe u8s8 (activations uint8, weights int8 per-channel; auto for x86-vnni)" in printed
    assert "avx512_vnni" in printed and "IoU of every anchor" in printed
    metadata = {p.key: p.value for p in onnx.load(str(out)).metadata_props}
    assert metadata["leapnbv.int8.recipe"] == "u8s8"
    assert metadata["leapnbv.int8.activations"] == "uint8 asymmetric"
    assert metadata["leapnbv.int8.chosen"] == "auto for x86-vnni"
    assert metadata["leapnbv.producer"] == "test"  # the export's own metadata is kept
    assert set(quantized_tensor_types(onnx.load(str(out)))["activations"]) == {"UINT8"}
    # another CPU named: the ARM recipe, written as asked
    arm = tmp_path / "det.arm.onnx"
    assert quantize_int8.main(["detector", str(source), "--out", str(arm), "--calib", "3", "--eval", "1",
                               "--target-cpu", "arm64"]) == 0
    assert int8_recipe.read_int8_metadata(str(arm))["leapnbv.int8.recipe"] == "s8s8"


def test_float_matmul_outputs_leave_the_attention_scores_unquantized(tmp_path: Path) -> None:
    """The HMR engine's MatMul outputs stay float (no QLinearSoftmax fusion); its inputs are still uint8."""
    rng = np.random.default_rng(5)
    inits = [numpy_helper.from_array(rng.normal(0, 0.3, (8, 8)).astype(np.float32), "wq"),
             numpy_helper.from_array(rng.normal(0, 0.3, (8, 8)).astype(np.float32), "wv")]
    nodes = [helper.make_node("MatMul", ["x", "wq"], ["q"], name="/model/encoder/attn/MatMul"),
             helper.make_node("Softmax", ["q"], ["p"], name="/model/encoder/attn/Softmax", axis=-1),
             helper.make_node("MatMul", ["p", "wv"], ["y"], name="/model/encoder/attn/MatMul_1")]
    graph = helper.make_graph(nodes, "attn", [helper.make_tensor_value_info("x", TensorProto.FLOAT, [1, 4, 8])],
                              [helper.make_tensor_value_info("y", TensorProto.FLOAT, [1, 4, 8])], inits)
    source = tmp_path / "attn.onnx"
    onnx.save(helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)]), str(source))
    feeds = [{"x": rng.normal(0, 1, (1, 4, 8)).astype(np.float32)} for _ in range(4)]
    outputs = {}
    for label, float_outputs in (("float", int8_recipe.FLOAT_OUTPUTS["hmr"]), ("quantized", ())):
        out = tmp_path / f"{label}.onnx"
        int8_recipe.quantize(str(source), str(out), quantize_int8.FeedReader(feeds), int8_recipe.recipe("u8s8"),
                             op_types=int8_recipe.quantized_ops(int8_recipe.OP_SETS["hmr"]),
                             float_outputs=float_outputs)
        model = onnx.load(str(out))
        outputs[label] = {n.input[0] for n in model.graph.node if n.op_type == "QuantizeLinear"}
        assert set(quantized_tensor_types(model)["activations"]) == {"UINT8"}
    assert "q" not in outputs["float"] and "p" in outputs["float"] and "x" in outputs["float"]
    assert "q" in outputs["quantized"]
