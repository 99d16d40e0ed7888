"""The geometry nodes' parameters: valid defaults (the robot's), ranges and the rules between fields."""
from __future__ import annotations

import pytest

from leapnbv_common.params import ParamsError, param_specs, replace_params, validate_params
from leapnbv_geometry.params import GroundParams, RasterParams


@pytest.mark.parametrize("cls", [RasterParams, GroundParams])
def test_defaults_are_valid_and_described(cls) -> None:
    validate_params(cls())
    assert all(spec.description for spec in param_specs(cls))


def test_ground_defaults_are_the_robot_mounting_priors() -> None:
    params = GroundParams()
    assert (params.max_tilt_deg, params.min_camera_height, params.max_camera_height) == (25.0, 0.8, 1.6)
    assert params.camera_pose_source == "topic" and params.use_camera_pose_fallback


@pytest.mark.parametrize("cls", [RasterParams, GroundParams])
def test_depth_range_must_be_a_range_above_no_return(cls) -> None:
    with pytest.raises(ParamsError, match=r"min_depth \(5.0\) must be below max_depth \(5.0\)"):
        replace_params(cls(), {"min_depth": 5.0, "max_depth": 5.0})
    with pytest.raises(ParamsError, match="min_depth = 0.0 is below its minimum"):  # 0 is "no return"
        replace_params(cls(), {"min_depth": 0.0})


def test_ground_camera_height_range_and_read_only_settings() -> None:
    with pytest.raises(ParamsError, match="min_camera_height .* must not exceed max_camera_height"):
        replace_params(GroundParams(), {"min_camera_height": 2.0})
    assert replace_params(GroundParams(), {"seed": 7, "camera_pose_wait_s": 0.0}).seed == 7
    for name in ("use_camera_pose_fallback", "camera_pose_source"):
        with pytest.raises(ParamsError, match=f"{name} is read-only"):
            replace_params(GroundParams(), {name: GroundParams().__dict__[name]})
    with pytest.raises(ParamsError, match="depth_cache_size is read-only"):
        replace_params(RasterParams(), {"depth_cache_size": 3})
