"""End-to-end test of HumanMeshEstimator on the contract HMR model and the small stand-in."""

from __future__ import annotations

from typing import Dict

import numpy as np
import pytest

from leapnbv_perception.backends import create_backend
from leapnbv_perception.hmr import HMROutputError, HumanMeshEstimator
from leapnbv_perception.hmr_crop import InvalidBoxError
from leapnbv_perception.model_contracts import ModelContractError
from leapnbv_perception.smplx_layer import SMPLXModel
from leapnbv_stand_ins.contract_models import write_contract_detector, write_contract_hmr
from leapnbv_stand_ins.stand_in_body_model import write_stand_in_body_model


@pytest.fixture(scope="module")
def paths(tmp_path_factory: pytest.TempPathFactory) -> Dict[str, str]:
    folder = tmp_path_factory.mktemp("hmr")
    return {
        "hmr": write_contract_hmr(str(folder / "hmr.onnx")),
        "hmr256": write_contract_hmr(str(folder / "hmr256.onnx"), (256, 192)),
        "detector": write_contract_detector(str(folder / "det.onnx")),
        "body": write_stand_in_body_model(str(folder / "stand_in_small.npz"), "small"),
    }


@pytest.fixture(scope="module")
def body(paths: Dict[str, str]) -> SMPLXModel:
    return SMPLXModel.load(paths["body"])


def scene() -> np.ndarray:
    rng = np.random.default_rng(7)
    rgb = rng.integers(0, 255, size=(480, 640, 3), dtype=np.uint8)
    rgb[100:400, 250:330] = (200, 80, 60)
    return rgb


@pytest.mark.parametrize("key", ["hmr", "hmr256"])
def test_estimate_end_to_end(paths: Dict[str, str], body: SMPLXModel, key: str) -> None:
    estimator = HumanMeshEstimator(create_backend("onnxruntime", paths[key]), body)
    rgb = scene()
    estimate = estimator.estimate(rgb, [250.0, 100.0, 330.0, 400.0, 0.9])
    assert estimate.vertices.shape == (body.num_vertices, 3) and estimate.vertices.dtype == np.float32
    assert np.all(np.isfinite(estimate.vertices))
    assert estimate.faces.dtype == np.uint32 and estimate.faces.shape == (body.num_faces, 3)
    for name, size in [("root", 3), ("body", 63), ("left_hand", 45), ("right_hand", 45), ("jaw", 3),
                       ("betas", 10), ("expression", 10), ("cam_translation", 3)]:
        assert getattr(estimate, name).shape == (size,)
    # The body stands in front of the virtual camera at the contract's depth (k * sigmoid).
    assert 15.0 < estimate.cam_translation[2] < 40.0
    assert np.all(estimate.vertices[:, 2] > 0.0)
    # Projected with the virtual intrinsics, the mesh lands around the processed box.
    u = estimate.fx * estimate.vertices[:, 0] / estimate.vertices[:, 2] + estimate.cx
    v = estimate.fy * estimate.vertices[:, 1] / estimate.vertices[:, 2] + estimate.cy
    x, y, w, h = estimate.processed_box
    assert x - w < np.median(u) < x + 2 * w and y - h < np.median(v) < y + 2 * h
    # Root near 180 deg about x: upright in the image (head above the feet: smaller v).
    assert v[np.argmax(body.v_template[:, 1])] < v[np.argmin(body.v_template[:, 1])]


def test_moving_the_box_changes_the_mesh(paths: Dict[str, str], body: SMPLXModel) -> None:
    estimator = HumanMeshEstimator(create_backend("onnxruntime", paths["hmr"]), body)
    rgb = scene()
    first = estimator.estimate(rgb, [250.0, 100.0, 330.0, 400.0])
    second = estimator.estimate(rgb, [150.0, 60.0, 230.0, 360.0])
    assert not np.allclose(first.vertices, second.vertices, atol=1e-4)
    assert not np.allclose(first.body, second.body)
    assert second.cx < first.cx


def test_detector_model_is_not_an_hmr_model(paths: Dict[str, str], body: SMPLXModel) -> None:
    with pytest.raises(ModelContractError, match="root_pose"):
        HumanMeshEstimator(create_backend("onnxruntime", paths["detector"]), body)


def test_box_outside_image(paths: Dict[str, str], body: SMPLXModel) -> None:
    estimator = HumanMeshEstimator(create_backend("onnxruntime", paths["hmr"]), body)
    with pytest.raises(InvalidBoxError):
        estimator.estimate(scene(), [700.0, 10.0, 800.0, 100.0])


class NaNBackend:
    """Declares the HMR contract but returns NaN for one head."""

    def __init__(self, real: object) -> None:
        self.real = real
        self.input_specs = real.input_specs
        self.output_specs = real.output_specs
        self.precision = "fp16"
        self.model_path = "nan.onnx"

    def run(self, inputs: dict) -> dict:
        outputs = self.real.run(inputs)
        outputs["betas"] = outputs["betas"] * np.nan
        return outputs


def test_non_finite_engine_output_is_rejected(paths: Dict[str, str], body: SMPLXModel) -> None:
    estimator = HumanMeshEstimator(NaNBackend(create_backend("onnxruntime", paths["hmr"])), body)
    with pytest.raises(HMROutputError, match="betas"):
        estimator.estimate(scene(), [250.0, 100.0, 330.0, 400.0])


def with_metadata(source: str, target: str, metadata: Dict[str, str]) -> str:
    import onnx

    proto = onnx.load(source)
    for key, value in metadata.items():
        entry = proto.metadata_props.add()
        entry.key, entry.value = key, value
    onnx.save(proto, target)
    return target


EXPORT_METADATA = {
    "leapnbv.producer": "leapnbv_model_tools export-hmr", "leapnbv.variant": "smpler_x_s32",
    "leapnbv.checkpoint_sha256": "ab" * 32, "leapnbv.input_size": "512x384",
    "leapnbv.unmirror_left_hand": "true", "leapnbv.box_ratio": "1.25",
}


def test_export_metadata_round_trip_and_mismatch(paths: Dict[str, str], body: SMPLXModel, tmp_path) -> None:
    from leapnbv_perception.hmr import ExportMetadataError, read_export_metadata

    exported = with_metadata(paths["hmr"], str(tmp_path / "exported.onnx"), EXPORT_METADATA)
    assert read_export_metadata(exported) == EXPORT_METADATA
    assert read_export_metadata(paths["hmr"]) == {}  # a contract model carries none: nothing to check
    estimator = HumanMeshEstimator(create_backend("onnxruntime", exported), body)
    assert estimator.export_metadata["leapnbv.variant"] == "smpler_x_s32"
    with pytest.raises(ExportMetadataError, match=r"box ratio 1.25 but box_scale is 1.2"):
        HumanMeshEstimator(create_backend("onnxruntime", exported), body, box_scale=1.2)
    with pytest.raises(ExportMetadataError, match="unmirror_left_hand=true but the parameter is false"):
        HumanMeshEstimator(create_backend("onnxruntime", exported), body, unmirror_left_hand=False)
    wrong_size = with_metadata(paths["hmr256"], str(tmp_path / "wrong_size.onnx"), EXPORT_METADATA)
    with pytest.raises(ExportMetadataError, match="input_size 512x384 but the graph's input is 256x192"):
        HumanMeshEstimator(create_backend("onnxruntime", wrong_size), body)


def test_export_metadata_says_whether_the_engine_estimates_the_hands(paths: Dict[str, str], body: SMPLXModel,
                                                                     tmp_path) -> None:
    from leapnbv_perception.hmr import ExportMetadataError

    # An export without the key (older exports, contract models) and a full export estimate the hands.
    assert HumanMeshEstimator(create_backend("onnxruntime", paths["hmr"]), body).hands_estimated is True
    full = with_metadata(paths["hmr"], str(tmp_path / "full.onnx"),
                         dict(EXPORT_METADATA, **{"leapnbv.hands": "estimated"}))
    assert HumanMeshEstimator(create_backend("onnxruntime", full), body).hands_estimated is True
    body_only = with_metadata(paths["hmr"], str(tmp_path / "body_only.onnx"),
                              dict(EXPORT_METADATA, **{"leapnbv.hands": "not_estimated"}))
    assert HumanMeshEstimator(create_backend("onnxruntime", body_only), body).hands_estimated is False
    unknown = with_metadata(paths["hmr"], str(tmp_path / "unknown.onnx"),
                            dict(EXPORT_METADATA, **{"leapnbv.hands": "left"}))
    with pytest.raises(ExportMetadataError, match="metadata hands 'left' is neither 'estimated' nor 'not_estimated'"):
        HumanMeshEstimator(create_backend("onnxruntime", unknown), body)
