"""The perception nodes' parameters: valid defaults, ranges, choices and what is fixed at start-up."""
from __future__ import annotations

import pytest

from leapnbv_common.params import ParamsError, param_specs, params_from_values, replace_params, validate_params
from leapnbv_perception.params import DetectorParams, HmrParams

ENGINE_SETTINGS = {"backend", "model_file_path", "engine_cache_dir", "precision", "providers", "intra_op_threads"}


@pytest.mark.parametrize("cls", [DetectorParams, HmrParams])
def test_defaults_are_valid_and_the_engine_is_fixed_at_start_up(cls) -> None:
    validate_params(cls())
    read_only = {spec.name for spec in param_specs(cls) if spec.read_only}
    assert ENGINE_SETTINGS <= read_only
    assert all(spec.description for spec in param_specs(cls))


def test_detector_thresholds_change_at_runtime_within_their_ranges() -> None:
    params = replace_params(DetectorParams(), {"score_threshold": 0.6, "max_detections": 3})
    assert (params.score_threshold, params.max_detections) == (0.6, 3)
    with pytest.raises(ParamsError, match="score_threshold = 1.5 is above its maximum 1.0"):
        replace_params(params, {"score_threshold": 1.5})
    with pytest.raises(ParamsError, match="max_detections = 0 is below its minimum 1"):
        replace_params(params, {"max_detections": 0})
    with pytest.raises(ParamsError, match="backend is read-only"):
        replace_params(params, {"backend": "tensorrt"})
    assert {spec.name for spec in param_specs(DetectorParams) if not spec.read_only} == {
        "score_threshold", "iou_threshold", "max_detections", "max_frames_in_flight", "in_flight_timeout_s",
        "carry_min_confidence", "carry_max_age_s", "max_stamp_ahead_s"}


def test_engine_choices() -> None:
    with pytest.raises(ParamsError, match=r"backend = 'openvino' is not one of \['onnxruntime', 'tensorrt'"):
        params_from_values(HmrParams, {"backend": "openvino"})
    with pytest.raises(ParamsError, match="precision = 'int8'"):
        params_from_values(DetectorParams, {"precision": "int8"})
    assert params_from_values(HmrParams, {"backend": "ground_truth", "precision": "fp32"}).backend == "ground_truth"


def test_hmr_runtime_settings() -> None:
    runtime = {spec.name for spec in param_specs(HmrParams) if not spec.read_only}
    assert runtime == {"box_scale", "unmirror_left_hand", "track_previous_target", "min_track_iou", "max_stamp_ahead_s",
                       "inline_mesh_faces", "track_in_fixed_frame", "target_gate_m", "target_gate_growth_m_s",
                       "target_lost_after_s", "target_depth_share", "target_ambiguity_m", "target_reacquire_window_s",
                       "target_reacquire_radius_m", "target_max_person_extent_m", "target_coast_s",
                       "target_input_wait_s", "depth_slop_s"}
    with pytest.raises(ParamsError, match="box_scale = 0.5 is below its minimum 1.0"):
        replace_params(HmrParams(), {"box_scale": 0.5})


def test_timing_stand_in_needs_the_ground_truth_backend_and_a_model() -> None:
    timed = params_from_values(DetectorParams, {"backend": "ground_truth", "timing_stand_in": True,
                                                "model_file_path": "/models/yolov8s_random.onnx"})
    assert timed.timing_stand_in
    for values, needle in [({"backend": "onnxruntime", "model_file_path": "/m.onnx"}, "backend 'onnxruntime'"),
                           ({"backend": "ground_truth"}, "model_file_path ''")]:
        with pytest.raises((ParamsError, ValueError), match="timing_stand_in needs backend ground_truth") as error:
            params_from_values(DetectorParams, {**values, "timing_stand_in": True})
        assert needle in str(error.value)
