"""The numpy SMPL-X layer on "stand_in_smplx_dense" (the SMPL-X npz layout in every key: 400 shape
columns with expression at 300:310, dense pose correctives) against an independent LBS written
here from the SMPL-X equations, not from the layer's code."""

from __future__ import annotations

from typing import Dict, Tuple

import numpy as np
import pytest
from reference_smplx import forward_reference

from leapnbv_perception.smplx_layer import SMPLXModel, SMPLXParams
from leapnbv_stand_ins.stand_in_smplx_dense import build_stand_in_smplx_dense

# SMPL-X's kinematic tree, written out here (not taken from the model or the layer).
PARENTS = (
    -1, 0, 0, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 9, 9, 12, 13, 14, 16, 17, 18, 19, 15, 15, 15,
    20, 25, 26, 20, 28, 29, 20, 31, 32, 20, 34, 35, 20, 37, 38,
    21, 40, 41, 21, 43, 44, 21, 46, 47, 21, 49, 50, 21, 52, 53,
)


@pytest.fixture(scope="module")
def arrays() -> Dict[str, np.ndarray]:
    return build_stand_in_smplx_dense()


@pytest.fixture(scope="module")
def model(arrays: Dict[str, np.ndarray]) -> SMPLXModel:
    return SMPLXModel(arrays, source="stand_in_smplx_dense")


def rodrigues(axis_angle: np.ndarray) -> np.ndarray:
    """R = I + sin(t) K + (1 - cos(t)) K^2, K the cross-product matrix of the unit axis."""
    angle = np.linalg.norm(axis_angle)
    if angle < 1e-12:
        return np.eye(3)
    x, y, z = axis_angle / angle
    k = np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])
    return np.eye(3) + np.sin(angle) * k + (1.0 - np.cos(angle)) * (k @ k)


def reference_lbs(
    arrays: Dict[str, np.ndarray], pose: np.ndarray, betas: np.ndarray, expression: np.ndarray,
    expression_offset: int = 300, transpose_pose_feature: bool = False,
) -> Tuple[np.ndarray, np.ndarray]:
    """SMPL-X from its equations, float64, one joint at a time.

    pose: (55, 3) axis-angles in SMPL-X joint order, hand mean already added.
    Returns (vertices (V, 3), posed joints (55, 3)).
    """
    shapedirs = arrays["shapedirs"].astype(np.float64)
    v_shaped = (
        arrays["v_template"]
        + np.einsum("vcs,s->vc", shapedirs[:, :, :10], betas)
        + np.einsum("vcs,s->vc", shapedirs[:, :, expression_offset:expression_offset + 10], expression)
    )
    joints = arrays["J_regressor"] @ v_shaped
    rotations = [rodrigues(p) for p in pose]
    feature = []
    for k in range(1, 55):
        difference = rotations[k] - np.eye(3)
        feature.append((difference.T if transpose_pose_feature else difference).reshape(9))
    v_posed = v_shaped + np.einsum("vcp,p->vc", arrays["posedirs"].astype(np.float64), np.concatenate(feature))
    world = []
    for k in range(55):
        local = np.eye(4)
        local[:3, :3] = rotations[k]
        local[:3, 3] = joints[k] - (joints[PARENTS[k]] if k else 0.0)
        world.append(local if k == 0 else world[PARENTS[k]] @ local)
    homogeneous = np.concatenate([v_posed, np.ones((len(v_posed), 1))], axis=1)
    vertices = np.zeros_like(v_posed)
    for k in range(55):
        skin = world[k].copy()
        skin[:3, 3] -= world[k][:3, :3] @ joints[k]
        vertices += arrays["weights"][:, k:k + 1] * (homogeneous @ skin.T)[:, :3]
    return vertices, np.array([g[:3, 3] for g in world])


def random_body(seed: int) -> Tuple[SMPLXParams, np.ndarray, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    root, body = rng.normal(0, 0.5, 3), rng.normal(0, 0.4, 63)
    left, right, jaw = rng.normal(0, 0.3, 45), rng.normal(0, 0.3, 45), rng.normal(0, 0.2, 3)
    betas, expression = rng.normal(0, 1, 10), rng.normal(0, 1.5, 10)
    params = SMPLXParams.from_axis_angle(root, body, left, right, jaw, betas, expression)
    pose = np.concatenate([root, body, jaw, np.zeros(6), left, right]).reshape(55, 3)
    return params, pose, betas, expression


def test_stand_in_has_every_key_smplx_create_reads(arrays: Dict[str, np.ndarray]) -> None:
    vertices = 10475
    expected = {
        "v_template": (vertices, 3), "f": (20908, 3), "shapedirs": (vertices, 3, 400),
        "posedirs": (vertices, 3, 486), "J_regressor": (55, vertices), "weights": (vertices, 55),
        "kintree_table": (2, 55), "hands_meanl": (45,), "hands_meanr": (45,),
        "hands_componentsl": (45, 45), "hands_componentsr": (45, 45),
        "lmk_faces_idx": (51,), "lmk_bary_coords": (51, 3),
        "dynamic_lmk_faces_idx": (79, 17), "dynamic_lmk_bary_coords": (79, 17, 3),
    }
    assert {key: arrays[key].shape for key in expected} == expected
    for key in ("lmk_faces_idx", "dynamic_lmk_faces_idx"):
        assert np.issubdtype(arrays[key].dtype, np.integer)
        assert 0 <= arrays[key].min() and arrays[key].max() < 20908
    for key in ("lmk_bary_coords", "dynamic_lmk_bary_coords"):
        np.testing.assert_allclose(arrays[key].sum(axis=-1), 1.0, atol=1e-12)
        assert arrays[key].min() > 0.0
    assert "not SMPL-X" in str(arrays["stand_in"])


def test_stand_in_is_dense_where_the_small_one_is_not(arrays: Dict[str, np.ndarray]) -> None:
    # Every one of the 486 pose-feature entries (all nine of R_k - I, joints 1..54) drives vertices.
    assert np.all(np.abs(arrays["posedirs"]).max(axis=(0, 1)) > 1e-4)
    # Off-diagonal entries of a joint differ from their transposes: a transposed feature shows.
    left_elbow = 9 * (18 - 1)
    assert np.abs(arrays["posedirs"][:, :, left_elbow + 1] - arrays["posedirs"][:, :, left_elbow + 3]).max() > 1e-3
    # All 400 shape columns are used, and expression (300:310) is not what 10:20 holds.
    assert np.all(np.abs(arrays["shapedirs"]).max(axis=(0, 1)) > 1e-4)
    assert np.abs(arrays["shapedirs"][:, :, 300:310] - arrays["shapedirs"][:, :, 10:20]).max() > 1e-3


@pytest.mark.parametrize("seed", [0, 1])
def test_layer_matches_independent_lbs_on_dense_model(
    arrays: Dict[str, np.ndarray], model: SMPLXModel, seed: int
) -> None:
    params, pose, betas, expression = random_body(seed)
    pose_with_mean = pose.copy()
    pose_with_mean[25:40] += arrays["hands_meanl"].reshape(15, 3)
    pose_with_mean[40:55] += arrays["hands_meanr"].reshape(15, 3)
    expected_vertices, expected_joints = reference_lbs(arrays, pose_with_mean, betas, expression)

    assert model.expression_start == 300
    out = model.forward(params)
    assert np.abs(out.vertices - expected_vertices).max() <= 1e-5
    assert np.abs(out.joints - expected_joints).max() <= 1e-5
    reference = forward_reference(model, params)
    assert np.abs(reference.vertices - expected_vertices).max() <= 1e-5

    # The comparison has teeth on this model: the two classic LBS mistakes move the mesh by far
    # more than the tolerance (on the small stand-in a transposed feature changes nothing).
    transposed, _ = reference_lbs(arrays, pose_with_mean, betas, expression, transpose_pose_feature=True)
    wrong_expression, _ = reference_lbs(arrays, pose_with_mean, betas, expression, expression_offset=10)
    assert np.abs(transposed - expected_vertices).max() > 5e-3
    assert np.abs(wrong_expression - expected_vertices).max() > 5e-3
