"""Finding the normalizations of an ONNX graph: LayerNormalization nodes and the pattern the project's
exporter writes LayerNorm as (``ReduceMean(x)``, ``Sub``, ``Mul(c, c)`` or ``Pow(c, 2)``, ``ReduceMean``,
``Add(eps)``, ``Sqrt``, ``Div``), each with the nodes a guarded FP16 model keeps in FP32."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Dict, List, Optional, Tuple

import numpy as np


@dataclass
class Normalization:
    """One normalization of the graph.

    Attributes:
        name: a readable name (the scope of its nodes, e.g. ``/encoder/last_norm``).
        input: the tensor it normalizes.
        axis: the normalized axis (negative: from the end).
        eps: the epsilon added to the variance.
        nodes: the nodes to keep in FP32 when it is guarded (reductions and what feeds them).
        kind: ``"LayerNormalization"`` or ``"primitive"``.
    """

    name: str
    input: str
    axis: int
    eps: float
    nodes: List[str]
    kind: str
    stats: Dict[str, float] = field(default_factory=dict)
    verdict: str = ""
    width: int = 0


def _attribute(node, name: str, default=None):
    import onnx

    for attribute in node.attribute:
        if attribute.name == name:
            return onnx.helper.get_attribute_value(attribute)
    return default


def _constant_values(model) -> Dict[str, np.ndarray]:
    """Initializers and Constant node outputs as numpy arrays."""
    from onnx import numpy_helper

    values = {init.name: numpy_helper.to_array(init) for init in model.graph.initializer}
    for node in model.graph.node:
        if node.op_type == "Constant" and node.attribute and node.attribute[0].name == "value":
            values[node.output[0]] = numpy_helper.to_array(node.attribute[0].t)
    return values


def _reduce_axes(node, constants: Dict[str, np.ndarray]) -> Optional[Tuple[int, ...]]:
    axes = _attribute(node, "axes")
    if axes is None and len(node.input) > 1 and node.input[1] in constants:
        axes = constants[node.input[1]].tolist()
    if axes is None:
        return None
    return tuple(int(a) for a in np.atleast_1d(axes))


def _scope(node_name: str) -> str:
    return node_name.rsplit("/", 1)[0] if "/" in node_name else node_name


def find_normalizations(model) -> List[Normalization]:
    """Every LayerNormalization node and every exported reduce/square/sqrt/div LayerNorm pattern."""
    producer = {out: node for node in model.graph.node for out in node.output}
    consumers: Dict[str, List] = {}
    for node in model.graph.node:
        for name in node.input:
            consumers.setdefault(name, []).append(node)
    constants = _constant_values(model)
    found: List[Normalization] = []
    for node in model.graph.node:
        if node.op_type == "LayerNormalization":
            found.append(Normalization(node.name, node.input[0], int(_attribute(node, "axis", -1)),
                                       float(_attribute(node, "epsilon", 1e-5)), [node.name], "LayerNormalization"))
            continue
        if node.op_type != "ReduceMean":
            continue
        square = producer.get(node.input[0])
        if square is None:
            continue
        if square.op_type == "Mul" and square.input[0] == square.input[1]:
            centred_name = square.input[0]
        elif square.op_type == "Pow" and float(np.asarray(constants.get(square.input[1], np.nan)).ravel()[0]) == 2.0:
            centred_name = square.input[0]
        else:
            continue
        sub = producer.get(centred_name)
        if sub is None or sub.op_type != "Sub":
            continue
        mean = producer.get(sub.input[1])
        if mean is None or mean.op_type != "ReduceMean" or mean.input[0] != sub.input[0]:
            continue
        axes = _reduce_axes(node, constants)
        if axes is None or len(axes) != 1 or _reduce_axes(mean, constants) != axes:
            continue
        nodes = [mean.name, sub.name, square.name, node.name]
        eps = 0.0
        current = node.output[0]
        following = consumers.get(current, [])
        if len(following) == 1 and following[0].op_type == "Add":
            add = following[0]
            other = add.input[1] if add.input[0] == current else add.input[0]
            eps = float(np.asarray(constants.get(other, 0.0)).ravel()[0])
            nodes.append(add.name)
            current = add.output[0]
            following = consumers.get(current, [])
        if len(following) == 1 and following[0].op_type == "Sqrt":
            nodes.append(following[0].name)
            current = following[0].output[0]
            following = consumers.get(current, [])
            if len(following) == 1 and following[0].op_type == "Div" and following[0].input[1] == current:
                nodes.append(following[0].name)
        for constant_node in model.graph.node:  # eps / exponent constants used only inside the pattern
            if constant_node.op_type == "Constant":
                users = consumers.get(constant_node.output[0], [])
                if users and all(user.name in nodes for user in users):
                    nodes.append(constant_node.name)
        found.append(Normalization(_scope(node.name), sub.input[0], axes[0], eps, nodes, "primitive"))
    return found
