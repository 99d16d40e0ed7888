"""Graph work for quantize-int8: the transposed convolutions rewritten as convolutions, and what a QDQ graph holds.

onnxruntime's CPU provider has no integer kernel for ConvTranspose: in a QDQ model it stays a float
operator behind a DequantizeLinear of its weights (run every inference). In the SMPLer-X engines the
box net's and the hand RoI net's transposed convolutions (kernel 4, stride 2, padding 1, each followed
by BatchNormalization) are about half of the s32 engine's CPU time. ``conv_transpose_to_conv`` writes
each one as the same arithmetic in operators the quantizer does make integer: a 2x2 convolution
(padding 1) that computes the four output phases of the stride-2 upsampling as 4 x O channels, with
the BatchNormalization folded into its weights and bias, four Slices (one phase each), a Concat and
a DepthToSpace that interleaves the phases. In FP32 it is the same function up to summation order.

The inspection functions read what the quantizer wrote (the tests use them): the activations' and
weights' zero-point types and the per-channel weight scales.
"""

from __future__ import annotations

from typing import Any, Dict, List, Optional, Tuple

import numpy as np

# For kernel 4, stride 2, padding 1: output row 2i + a is made of input rows i - 1 + a + t (t = 0, 1), which
# are the kernel rows KERNEL_TAP[a][t] of the transposed convolution.
KERNEL_TAP = ((3, 1), (2, 0))


def _attributes(node) -> Dict[str, Any]:
    from onnx import helper

    return {a.name: helper.get_attribute_value(a) for a in node.attribute}


def _rewritable(node, attributes: Dict[str, Any], initializers: Dict[str, np.ndarray]) -> bool:
    """A ConvTranspose of the SMPLer-X upsampling form: 2-D, kernel 4, stride 2, padding 1, one group."""
    if node.op_type != "ConvTranspose" or len(node.input) < 2 or node.input[1] not in initializers:
        return False
    if len(node.input) > 2 and node.input[2] and node.input[2] not in initializers:
        return False
    weight = initializers[node.input[1]]
    return (weight.ndim == 4 and tuple(weight.shape[2:]) == (4, 4)
            and list(attributes.get("strides", [1, 1])) == [2, 2]
            and list(attributes.get("pads", [0, 0, 0, 0])) == [1, 1, 1, 1]
            and list(attributes.get("dilations", [1, 1])) == [1, 1]
            and int(attributes.get("group", 1)) == 1
            and not any(attributes.get("output_padding", [0, 0]))
            and not attributes.get("output_shape")
            and attributes.get("auto_pad", b"NOTSET") in (b"NOTSET", "NOTSET"))


def phase_conv_weights(weight: np.ndarray, bias: Optional[np.ndarray] = None) -> Tuple[np.ndarray, np.ndarray]:
    """The (4 O, C, 2, 2) convolution weights and (4 O,) bias of a (C, O, 4, 4) stride-2 transposed convolution.

    Output channel (2 a + b) O + o is output channel o at the phase (row 2i + a, column 2j + b).
    """
    channels_in, channels_out = weight.shape[:2]
    out = np.empty((4 * channels_out, channels_in, 2, 2), dtype=weight.dtype)
    for a in (0, 1):
        for b in (0, 1):
            phase = 2 * a + b
            for t in (0, 1):
                for r in (0, 1):
                    out[phase * channels_out:(phase + 1) * channels_out, :, t, r] = \
                        weight[:, :, KERNEL_TAP[a][t], KERNEL_TAP[b][r]].T
    bias = np.zeros(channels_out, weight.dtype) if bias is None else bias.astype(weight.dtype)
    return out, np.tile(bias, 4)


def conv_transpose_to_conv(model) -> int:
    """Rewrite, in place, every ConvTranspose of the upsampling form (``_rewritable``) as Conv + DepthToSpace.

    A BatchNormalization (inference mode) that is the transposed convolution's only consumer is folded
    into the convolution. Returns how many were rewritten.
    """
    from onnx import helper, numpy_helper

    graph = model.graph
    initializers = {i.name: numpy_helper.to_array(i) for i in graph.initializer}
    consumers: Dict[str, List] = {}
    for node in graph.node:
        for name in node.input:
            consumers.setdefault(name, []).append(node)
    graph_outputs = {o.name for o in graph.output}
    new_initializers = []
    nodes = []
    removed = set()
    rewritten = 0
    for node in graph.node:
        if id(node) in removed:
            continue
        attributes = _attributes(node)
        if not _rewritable(node, attributes, initializers):
            nodes.append(node)
            continue
        weight = initializers[node.input[1]].astype(np.float32)
        bias = initializers[node.input[2]] if len(node.input) > 2 and node.input[2] else None
        out_name = node.output[0]
        users = consumers.get(out_name, [])
        if len(users) == 1 and users[0].op_type == "BatchNormalization" and out_name not in graph_outputs \
                and all(n in initializers for n in users[0].input[1:5]) \
                and not _attributes(users[0]).get("training_mode", 0):
            norm = users[0]
            gamma, beta, mean, var = (initializers[n].astype(np.float64) for n in norm.input[1:5])
            scale = gamma / np.sqrt(var + float(_attributes(norm).get("epsilon", 1e-5)))
            base_bias = np.zeros(weight.shape[1]) if bias is None else bias.astype(np.float64)
            weight = (weight * scale[None, :, None, None]).astype(np.float32)
            bias = ((base_bias - mean) * scale + beta).astype(np.float32)
            out_name = norm.output[0]
            removed.add(id(norm))
        conv_weight, conv_bias = phase_conv_weights(weight, bias)
        stem = (node.name or out_name).replace("ConvTranspose", "PhaseConv")
        w_name, b_name = f"{stem}/weight", f"{stem}/bias"
        new_initializers += [numpy_helper.from_array(conv_weight, w_name), numpy_helper.from_array(conv_bias, b_name)]
        phases_out = f"{stem}/phases"
        nodes.append(helper.make_node("Conv", [node.input[0], w_name, b_name], [phases_out], name=f"{stem}/Conv",
                                      kernel_shape=[2, 2], pads=[1, 1, 1, 1], strides=[1, 1]))
        channels = weight.shape[1]
        pieces = []
        for a in (0, 1):
            for b in (0, 1):
                phase = 2 * a + b
                # rows a .. a + H of the H + 1 the padded 2x2 convolution gives (the same for columns)
                starts = [phase * channels, a, b]
                ends = [(phase + 1) * channels, -1 if a == 0 else 2 ** 62, -1 if b == 0 else 2 ** 62]
                names = [f"{stem}/slice{phase}_{k}" for k in ("starts", "ends", "axes")]
                for value, name in zip((starts, ends, [1, 2, 3]), names):
                    new_initializers.append(numpy_helper.from_array(np.asarray(value, np.int64), name))
                piece = f"{stem}/phase{phase}"
                nodes.append(helper.make_node("Slice", [phases_out] + names, [piece], name=f"{stem}/Slice{phase}"))
                pieces.append(piece)
        nodes.append(helper.make_node("Concat", pieces, [f"{stem}/phases_ordered"], name=f"{stem}/Concat", axis=1))
        nodes.append(helper.make_node("DepthToSpace", [f"{stem}/phases_ordered"], [out_name],
                                      name=f"{stem}/DepthToSpace", blocksize=2, mode="DCR"))
        rewritten += 1
    if not rewritten:
        return 0
    del graph.node[:]
    graph.node.extend(nodes)
    graph.initializer.extend(new_initializers)
    used = {name for node in graph.node for name in node.input}
    kept = [i for i in graph.initializer if i.name in used or i.name in graph_outputs]
    del graph.initializer[:]
    graph.initializer.extend(kept)
    # the intermediate values' shapes are no longer right: shape inference runs again afterwards
    del graph.value_info[:]
    return rewritten


def quantized_tensor_types(model) -> Dict[str, Dict[str, int]]:
    """Per QuantizeLinear / weight DequantizeLinear: zero-point type counts, {"activations": ..., "weights": ...}.

    Activations are the QuantizeLinear nodes whose input is computed (not an initializer); weights the
    DequantizeLinear nodes whose quantized input is an initializer. Values: ``onnx.TensorProto`` type names.
    """
    from onnx import TensorProto

    initializers = {i.name: i for i in model.graph.initializer}
    counts: Dict[str, Dict[str, int]] = {"activations": {}, "weights": {}}
    for node in model.graph.node:
        if len(node.input) < 3 or node.input[2] not in initializers:
            continue
        zero_point = initializers[node.input[2]]
        type_name = TensorProto.DataType.Name(zero_point.data_type)
        if node.op_type == "QuantizeLinear" and node.input[0] not in initializers:
            counts["activations"][type_name] = counts["activations"].get(type_name, 0) + 1
        elif node.op_type == "DequantizeLinear" and node.input[0] in initializers:
            weight = initializers[node.input[0]]
            if TensorProto.DataType.Name(weight.data_type) in ("INT8", "UINT8"):
                counts["weights"][type_name] = counts["weights"].get(type_name, 0) + 1
    return counts


def weight_scales(model) -> Dict[str, Tuple[int, ...]]:
    """Each 8-bit weight DequantizeLinear's name -> the shape of its scale (per-channel: one per output channel)."""
    from onnx import TensorProto

    initializers = {i.name: i for i in model.graph.initializer}
    scales = {}
    for node in model.graph.node:
        if node.op_type == "DequantizeLinear" and node.input[0] in initializers and node.input[1] in initializers:
            weight = initializers[node.input[0]]
            if TensorProto.DataType.Name(weight.data_type) in ("INT8", "UINT8"):
                scales[node.name or node.output[0]] = tuple(initializers[node.input[1]].dims)
    return scales
