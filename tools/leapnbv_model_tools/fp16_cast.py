"""The guarded cast: a model in FP16 with named nodes kept in FP32 and Casts where the two meet
(graph inputs and outputs stay float32)."""

from __future__ import annotations

from typing import Dict, Iterable, Tuple

import numpy as np

_FLOAT, _FLOAT16 = 1, 10
_FLOAT32_ONLY_INPUTS = {"Resize": {1, 2}, "Upsample": {1}}  # roi/scales stay float32


def convert_float16(model, keep_fp32: Iterable[str]):
    """A copy of ``model`` in FP16 except the named nodes; Casts where the two meet.

    Float initializers are stored in FP16 (and in FP32 too when a kept node reads them); Constant
    nodes and ``Cast(to=FLOAT)`` / ``ConstantOfShape`` outside the kept nodes produce FP16; graph
    inputs and outputs stay float32.
    """
    import copy

    import onnx
    from onnx import helper, numpy_helper

    keep = set(keep_fp32)
    model = copy.deepcopy(model)
    graph = model.graph
    inferred = onnx.shape_inference.infer_shapes(model)
    elem: Dict[str, int] = {}
    for info in list(inferred.graph.value_info) + list(inferred.graph.input) + list(inferred.graph.output):
        elem[info.name] = info.type.tensor_type.elem_type
    for init in graph.initializer:
        elem[init.name] = init.data_type
    float_inits = {init.name: init for init in graph.initializer if init.data_type == _FLOAT}
    precision: Dict[str, str] = {inp.name: "f32" for inp in graph.input if elem.get(inp.name) == _FLOAT}
    extra_inits = []
    made: Dict[Tuple[str, str], str] = {}
    nodes = []

    def as_precision(name: str, target: str) -> str:
        if name in float_inits:
            if target == "f32":
                return name
            key = (name, "f16")
            if key not in made:
                half = numpy_helper.from_array(numpy_helper.to_array(float_inits[name]).astype(np.float16),
                                               name + "__fp16")
                extra_inits.append(half)
                made[key] = half.name
            return made[key]
        if precision.get(name, target) == target:
            return name
        key = (name, target)
        if key not in made:
            out = f"{name}__to_{target}"
            nodes.append(helper.make_node("Cast", [name], [out], name=f"{name}__cast_{target}",
                                          to=_FLOAT if target == "f32" else _FLOAT16))
            made[key] = out
        return made[key]

    for node in graph.node:
        target = "f32" if node.name in keep else "f16"
        fixed = _FLOAT32_ONLY_INPUTS.get(node.op_type, set())
        for index, name in enumerate(node.input):
            if name and elem.get(name) == _FLOAT:
                node.input[index] = as_precision(name, "f32" if index in fixed else target)
        if target == "f16":
            for attribute in node.attribute:
                if node.op_type == "Cast" and attribute.name == "to" and attribute.i == _FLOAT:
                    attribute.i = _FLOAT16
                elif attribute.type == onnx.AttributeProto.TENSOR and attribute.t.data_type == _FLOAT:
                    half = numpy_helper.from_array(numpy_helper.to_array(attribute.t).astype(np.float16),
                                                   attribute.t.name)
                    attribute.t.CopyFrom(half)
        for name in node.output:
            if elem.get(name) == _FLOAT:
                precision[name] = target
        nodes.append(node)
    tail = []
    for output in graph.output:
        if elem.get(output.name) == _FLOAT and precision.get(output.name) == "f16":
            inner = output.name + "__fp16"
            for node in nodes:
                for index, name in enumerate(node.input):
                    if name == output.name:
                        node.input[index] = inner
                for index, name in enumerate(node.output):
                    if name == output.name:
                        node.output[index] = inner
            tail.append(helper.make_node("Cast", [inner], [output.name], name=output.name + "__cast_out", to=_FLOAT))
    used = {name for node in nodes + tail for name in node.input}
    kept_inits = [init for init in graph.initializer if init.name in used]
    del graph.node[:]
    graph.node.extend(nodes + tail)
    del graph.initializer[:]
    graph.initializer.extend(kept_inits + extra_inits)
    del graph.value_info[:]
    onnx.checker.check_model(model)
    onnx.shape_inference.infer_shapes(model, strict_mode=True)
    return model
