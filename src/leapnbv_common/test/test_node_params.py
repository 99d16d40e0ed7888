"""NodeParams: a params dataclass declared on a real rclpy node, and runtime changes applied or refused."""
from __future__ import annotations

from dataclasses import dataclass
from typing import List, Set

import pytest

rclpy = pytest.importorskip("rclpy")

from rclpy.parameter import Parameter  # noqa: E402

from leapnbv_common.node_params import NodeParams  # noqa: E402
from leapnbv_common.params import ParamsError, param  # noqa: E402

pytestmark = pytest.mark.ros


@dataclass
class StageParams:
    radius: float = param(2.5, "metres: ring radius", min=0.5, max=10.0)
    count: int = param(16, "candidates", min=1, max=64)
    backend: str = param("onnxruntime", "engine", choices=("onnxruntime", "tensorrt"), read_only=True)
    terms: List[str] = param(["a", "b"], "terms")


@pytest.fixture()
def node():
    rclpy.init()
    node = rclpy.create_node("node_params_test")
    yield node
    node.destroy_node()
    rclpy.shutdown()


def test_declared_with_descriptors_and_defaults(node):
    params = NodeParams(node, StageParams)
    assert params.value == StageParams()
    descriptor = node.describe_parameter("radius")
    assert descriptor.description == "metres: ring radius"
    assert (descriptor.floating_point_range[0].from_value, descriptor.floating_point_range[0].to_value) == (0.5, 10.0)
    assert node.describe_parameter("count").integer_range[0].to_value == 64
    assert node.describe_parameter("backend").read_only
    assert "one of: onnxruntime, tensorrt" in node.describe_parameter("backend").additional_constraints


def test_runtime_change_is_applied_after_the_node_rebuilds(node):
    seen: List[Set[str]] = []
    params = NodeParams(node, StageParams, on_change=lambda new, changed: seen.append(changed))
    result = node.set_parameters([Parameter("radius", value=2.0), Parameter("count", value=8)])
    assert all(r.successful for r in result)
    assert (params.value.radius, params.value.count) == (2.0, 8)
    assert seen == [{"radius"}, {"count"}]  # rclpy sets (and asks about) one parameter at a time


def test_invalid_or_refused_changes_keep_the_old_values(node):
    def refuse_big_counts(new: StageParams, changed: Set[str]) -> None:
        if new.count > 32:
            raise ValueError("count above 32 needs a restart")

    params = NodeParams(node, StageParams, on_change=refuse_big_counts)
    out_of_range = node.set_parameters([Parameter("radius", value=0.1)])[0]
    assert not out_of_range.successful and params.value.radius == 2.5
    refused = node.set_parameters([Parameter("count", value=40)])[0]
    assert not refused.successful and "needs a restart" in refused.reason and params.value.count == 16
    read_only = node.set_parameters([Parameter("backend", value="tensorrt")])[0]
    assert not read_only.successful and params.value.backend == "onnxruntime"
    assert node.get_parameter("count").value == 16


def test_invalid_start_value_stops_the_node_with_its_name():
    rclpy.init()
    try:
        node = rclpy.create_node("bad_params", parameter_overrides=[Parameter("terms", value=["a", "b", "c"]),
                                                                   Parameter("count", value=0)])
        with pytest.raises(Exception) as error:  # rclpy refuses the out-of-range override itself
            NodeParams(node, StageParams)
        assert "count" in str(error.value)
        node.destroy_node()
    finally:
        rclpy.shutdown()


def test_a_rule_between_fields_is_checked_at_start():
    @dataclass
    class Paired:
        names: List[str] = param(["a"], "names")
        weights: List[float] = param([1.0], "weights")

        def check(self) -> None:
            if len(self.names) != len(self.weights):
                raise ValueError("names and weights differ in length")

    rclpy.init()
    try:
        node = rclpy.create_node("paired", parameter_overrides=[Parameter("names", value=["a", "b"])])
        with pytest.raises(ParamsError, match="paired: names and weights differ in length"):
            NodeParams(node, Paired)
        node.destroy_node()
    finally:
        rclpy.shutdown()
