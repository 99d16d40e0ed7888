"""Tests for the SMPL-X loader and LBS (run on the small stand-in body model)."""

from __future__ import annotations

import io
import pickle
import zipfile
from pathlib import Path
from typing import Dict

import numpy as np
import pytest
from reference_smplx import forward_reference

from leapnbv_perception.rotations import axis_angle_to_matrix
from leapnbv_perception.smplx_layer import (
    BodyModelNotFoundError,
    SMPLXModel,
    SMPLXModelError,
    SMPLXParams,
)
from leapnbv_stand_ins.stand_in_body_model import build_stand_in_body_model, write_stand_in_body_model

LEFT_ELBOW, LEFT_WRIST, LEFT_INDEX3, RIGHT_WRIST, HEAD = 18, 20, 27, 21, 15


@pytest.fixture(scope="module")
def arrays() -> Dict[str, np.ndarray]:
    return build_stand_in_body_model("small")


@pytest.fixture(scope="module")
def model(tmp_path_factory: pytest.TempPathFactory) -> SMPLXModel:
    path = tmp_path_factory.mktemp("body") / "stand_in_small.npz"
    write_stand_in_body_model(str(path), "small")
    return SMPLXModel.load(str(path))


def hand_weight(model: SMPLXModel) -> np.ndarray:
    return model.weights[:, 25:55].sum(axis=1)


def test_zero_pose_without_hand_mean_is_template(model: SMPLXModel) -> None:
    out = model.forward(SMPLXParams.zeros(), add_hand_mean=False)
    np.testing.assert_allclose(out.vertices, model.v_template, atol=1e-6)
    np.testing.assert_allclose(out.joints, model.joint_regressor @ model.v_template, atol=1e-6)


def test_hand_mean_moves_only_hand_vertices(model: SMPLXModel) -> None:
    out = model.forward(SMPLXParams.zeros())
    moved = np.linalg.norm(out.vertices - model.v_template, axis=1) > 1e-6
    no_hand = hand_weight(model) == 0.0
    assert not np.any(moved & no_hand)
    assert np.count_nonzero(moved) > 50
    np.testing.assert_allclose(out.vertices[no_hand], model.v_template[no_hand], atol=1e-6)


def test_global_rotation_rotates_about_root_joint(model: SMPLXModel) -> None:
    rotation = axis_angle_to_matrix(np.array([0.3, -1.1, 0.4]))
    rest = model.forward(SMPLXParams.zeros())
    params = SMPLXParams.zeros()
    params.root_rotation = rotation
    rotated = model.forward(params)
    root = rest.joints[0]
    expected = (rest.vertices - root) @ rotation.T + root
    np.testing.assert_allclose(rotated.vertices, expected, atol=1e-5)
    np.testing.assert_allclose(rotated.joints, (rest.joints - root) @ rotation.T + root, atol=1e-5)


def test_betas_follow_shapedirs_exactly(model: SMPLXModel, arrays: Dict[str, np.ndarray]) -> None:
    betas = np.array([1.0, -0.5, 0.3, 0.0, 0.7, -1.2, 0.4, 0.2, -0.3, 0.9])
    expression = np.linspace(-1.0, 1.0, 10)
    params = SMPLXParams(betas=betas, expression=expression)
    out = model.forward(params, add_hand_mean=False)
    shapedirs = arrays["shapedirs"]
    expected = arrays["v_template"] + shapedirs[:, :, :10] @ betas + shapedirs[:, :, 10:20] @ expression
    np.testing.assert_allclose(out.vertices, expected, atol=1e-5)
    np.testing.assert_allclose(out.joints, arrays["J_regressor"] @ expected, atol=1e-5)
    assert not np.allclose(out.joints, arrays["J_regressor"] @ arrays["v_template"], atol=1e-3)


def test_left_elbow_moves_only_its_chain(model: SMPLXModel) -> None:
    rest = model.forward(SMPLXParams.zeros())
    params = SMPLXParams.zeros()
    params.body_rotations = params.body_rotations.copy()
    params.body_rotations[LEFT_ELBOW - 1] = axis_angle_to_matrix(np.array([0.0, 0.0, 1.2]))
    bent = model.forward(params)
    moved = np.linalg.norm(bent.joints - rest.joints, axis=1) > 1e-6
    descendants = {LEFT_WRIST} | set(range(25, 40))
    assert set(np.nonzero(moved)[0]) == descendants
    # The wrist swings about the elbow: its distance to the elbow is unchanged.
    assert np.linalg.norm(bent.joints[LEFT_WRIST] - bent.joints[LEFT_ELBOW]) == pytest.approx(
        np.linalg.norm(rest.joints[LEFT_WRIST] - rest.joints[LEFT_ELBOW]), abs=1e-6
    )
    # Vertices with no weight on the left elbow chain do not move.
    chain_weight = model.weights[:, [LEFT_ELBOW, LEFT_WRIST] + list(range(25, 40))].sum(axis=1)
    still = chain_weight == 0.0
    np.testing.assert_allclose(bent.vertices[still], rest.vertices[still], atol=1e-6)
    assert np.all(np.linalg.norm(bent.vertices - rest.vertices, axis=1)[model.weights[:, LEFT_INDEX3] > 0.9] > 0.05)


def test_fast_forward_matches_reference(model: SMPLXModel) -> None:
    rng = np.random.default_rng(5)
    params = SMPLXParams.from_axis_angle(
        rng.normal(0, 0.5, 3), rng.normal(0, 0.4, 63), rng.normal(0, 0.3, 45), rng.normal(0, 0.3, 45),
        rng.normal(0, 0.2, 3), rng.normal(0, 1, 10), rng.normal(0, 1, 10),
    )
    fast = model.forward(params)
    reference = forward_reference(model, params)
    assert fast.vertices.dtype == np.float32 and fast.joints.shape == (55, 3)
    np.testing.assert_allclose(fast.vertices, reference.vertices, atol=1e-5)
    np.testing.assert_allclose(fast.joints, reference.joints, atol=1e-5)


def test_from_axis_angle_checks_sizes() -> None:
    with pytest.raises(ValueError, match="body"):
        SMPLXParams.from_axis_angle(np.zeros(3), np.zeros(60), np.zeros(45), np.zeros(45), np.zeros(3))


def test_loader_refuses_pickle(tmp_path: Path) -> None:
    path = tmp_path / "SMPLX_NEUTRAL.pkl"
    path.write_bytes(pickle.dumps({"v_template": np.zeros((3, 3))}))
    with pytest.raises(SMPLXModelError, match=r"(?s)pickle.*np\.savez"):
        SMPLXModel.load(str(path))


def test_loader_refuses_npz_needing_pickle(tmp_path: Path, arrays: Dict[str, np.ndarray]) -> None:
    path = tmp_path / "object.npz"
    broken = dict(arrays)
    broken["J_regressor"] = np.array([object()], dtype=object)
    np.savez(path, **broken)
    with pytest.raises(SMPLXModelError, match="J_regressor"):
        SMPLXModel.load(str(path))


def test_loader_names_missing_file(tmp_path: Path) -> None:
    path = tmp_path / "nowhere" / "SMPLX_NEUTRAL.npz"
    with pytest.raises(BodyModelNotFoundError, match="nowhere/SMPLX_NEUTRAL.npz"):
        SMPLXModel.load(str(path))
    assert issubclass(BodyModelNotFoundError, FileNotFoundError)


def test_loader_lists_missing_keys(tmp_path: Path, arrays: Dict[str, np.ndarray]) -> None:
    path = tmp_path / "partial.npz"
    partial = {k: v for k, v in arrays.items() if k not in ("posedirs", "hands_meanr")}
    np.savez(path, **partial)
    with pytest.raises(SMPLXModelError, match="posedirs, hands_meanr"):
        SMPLXModel.load(str(path))


@pytest.mark.parametrize("root_parent", [4294967295, -1])
def test_loader_accepts_both_root_parent_codes(tmp_path: Path, arrays: Dict[str, np.ndarray], root_parent: int) -> None:
    changed = dict(arrays)
    kintree = arrays["kintree_table"].astype(np.int64).copy()
    kintree[0, 0] = root_parent
    changed["kintree_table"] = kintree.astype(np.uint32) if root_parent > 0 else kintree
    path = tmp_path / "tree.npz"
    np.savez(path, **changed)
    model = SMPLXModel.load(str(path))
    assert model.parents[0] == -1 and model.parents[20] == 18 and model.parents[54] == 53


def test_loader_rejects_bad_shape(tmp_path: Path, arrays: Dict[str, np.ndarray]) -> None:
    changed = dict(arrays)
    changed["weights"] = arrays["weights"][:, :54]
    path = tmp_path / "bad.npz"
    np.savez(path, **changed)
    with pytest.raises(SMPLXModelError, match="weights"):
        SMPLXModel.load(str(path))


@pytest.mark.parametrize("damage", ["empty", "cut_at_1_percent", "cut_at_half", "cut_before_the_end",
                                    "flipped_byte", "garbled_member"])
def test_loader_names_a_truncated_or_corrupt_file(tmp_path: Path, arrays: Dict[str, np.ndarray], damage: str) -> None:
    path = tmp_path / "SMPLX_NEUTRAL.npz"
    np.savez(path, **arrays)
    data = bytearray(path.read_bytes())
    if damage == "empty":
        data = bytearray()  # np.load raises EOFError
    elif damage.startswith("cut"):
        fraction = {"cut_at_1_percent": 0.01, "cut_at_half": 0.5, "cut_before_the_end": 0.999}[damage]
        data = data[: int(len(data) * fraction)]  # BadZipFile: no central directory
    elif damage == "flipped_byte":
        data[len(data) // 2] ^= 0xFF  # BadZipFile: bad CRC-32 of the member holding that byte
    else:
        # A member whose .npy header promises more rows than it holds (the zip's CRC is right): numpy
        # raises ValueError, which is not a pickle problem.
        with zipfile.ZipFile(path, "w") as archive:
            for key, value in arrays.items():
                buffer = io.BytesIO()
                np.save(buffer, value)
                payload = buffer.getvalue()
                if key == "v_template":
                    rows = value.shape[0]
                    payload = payload.replace(b"'shape': (%d," % rows, b"'shape': (%d," % (rows + 9))
                archive.writestr(key + ".npy", payload)
        data = None
    if data is not None:
        path.write_bytes(bytes(data))
    with pytest.raises(SMPLXModelError, match=str(path)) as raised:
        SMPLXModel.load(str(path))
    assert "pickle" not in str(raised.value)


def test_expression_columns_of_full_layout(arrays: Dict[str, np.ndarray]) -> None:
    # A 400-column shapedirs takes expression from columns 300..309.
    wide = dict(arrays)
    shapedirs = np.zeros(arrays["shapedirs"].shape[:2] + (400,))
    shapedirs[:, :, :10] = arrays["shapedirs"][:, :, :10]
    shapedirs[:, :, 300:310] = arrays["shapedirs"][:, :, 10:20]
    wide["shapedirs"] = shapedirs
    model = SMPLXModel(wide)
    params = SMPLXParams(expression=np.ones(10))
    expected = arrays["v_template"] + arrays["shapedirs"][:, :, 10:20].sum(axis=2)
    np.testing.assert_allclose(model.forward(params, add_hand_mean=False).vertices, expected, atol=1e-5)
