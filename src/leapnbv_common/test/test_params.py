"""Params dataclasses: one declaration gives defaults, ranges, choices and read-only flags (no ROS needed)."""
from __future__ import annotations

from dataclasses import dataclass
from typing import List

import pytest

from leapnbv_common.params import (
    ParamsError,
    param,
    param_specs,
    params_as_dict,
    params_from_values,
    replace_params,
    validate_params,
)


@dataclass
class RingParams:
    radius: float = param(2.5, "metres: ring radius", min=0.5, max=10.0)
    count: int = param(16, "candidates on the ring", min=1, max=256)
    backend: str = param("onnxruntime", "engine backend", choices=("onnxruntime", "tensorrt"), read_only=True)
    terms: List[str] = param(["visibility", "area"], "score terms in order", choices=("visibility", "area", "x"))
    weights: List[float] = param([0.5, 0.5], "weight of each term", min=0.0, max=1.0)
    enabled: bool = param(True, "use it")

    def check(self) -> None:
        if len(self.terms) != len(self.weights):
            raise ValueError(f"terms ({len(self.terms)}) and weights ({len(self.weights)}) differ in length")


def test_specs_carry_every_declared_fact():
    specs = {spec.name: spec for spec in param_specs(RingParams)}
    assert list(specs) == ["radius", "count", "backend", "terms", "weights", "enabled"]
    assert (specs["radius"].default, specs["radius"].min, specs["radius"].max) == (2.5, 0.5, 10.0)
    assert specs["backend"].read_only and not specs["radius"].read_only
    assert specs["terms"].kind is list and specs["count"].kind is int and specs["enabled"].kind is bool
    assert specs["radius"].description.startswith("metres")


def test_defaults_are_valid_and_lists_are_not_shared():
    a, b = RingParams(), RingParams()
    validate_params(a)
    a.terms.append("x")
    assert b.terms == ["visibility", "area"]


@pytest.mark.parametrize("values, message", [
    ({"radius": 0.1}, "radius = 0.1 is below its minimum 0.5"),
    ({"radius": float("nan")}, "radius must be a number"),
    ({"count": 2.5}, "count must be a int"),
    ({"enabled": 1}, "enabled must be a bool"),
    ({"count": True}, "count must be a int"),
    ({"backend": "cuda"}, "backend = 'cuda' is not one of"),
    ({"terms": ["visibility", "height"], "weights": [0.5, 0.5]}, "'height' is not one of"),
    ({"weights": [0.5, 1.5]}, "weights = 1.5 is above its maximum 1.0"),
    ({"weights": [1.0]}, "terms (2) and weights (1) differ in length"),
    ({"ring": 1}, "unknown parameter(s) of RingParams: ring"),
])
def test_invalid_values_are_refused_by_name(values, message):
    with pytest.raises(ParamsError) as error:
        params_from_values(RingParams, values)
    assert message in str(error.value)


def test_ints_are_accepted_for_floats_and_replace_validates():
    params = params_from_values(RingParams, {"radius": 3})
    assert params.radius == 3.0 and isinstance(params.radius, float)
    changed = replace_params(params, {"count": 8})
    assert (changed.count, params.count) == (8, 16)
    with pytest.raises(ParamsError, match="backend is read-only"):
        replace_params(params, {"backend": "tensorrt"})
    assert replace_params(params, {"backend": "tensorrt"}, allow_read_only=True).backend == "tensorrt"
    assert params_as_dict(changed)["count"] == 8


def test_a_field_without_param_is_a_programming_error():
    @dataclass
    class Broken:
        radius: float = 1.0

    with pytest.raises(TypeError, match="Broken.radius is not declared with param"):
        param_specs(Broken)
