"""The PyTorch SMPL-X layer against the robot's numpy layer (stand-in body models, not SMPL-X)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from leapnbv_model_tools.torch_smplx import (
    TorchSMPLX,
    axis_angle_to_matrix,
    matrix_to_axis_angle,
    mesh_from_outputs,
    rot6d_to_matrix,
    vertex_loss,
)

from leapnbv_perception.hmr_tail import unmirror_left_hand
from leapnbv_perception.rotations import rot6d_to_matrix as np_rot6d_to_matrix
from leapnbv_perception.smplx_layer import SMPLXModel, SMPLXParams

torch.set_num_threads(1)


@pytest.fixture(scope="module")
def body_model(tmp_path_factory) -> SMPLXModel:
    from leapnbv_stand_ins.files import ensure_stand_in_body_model

    return SMPLXModel.load(ensure_stand_in_body_model("small", tmp_path_factory.mktemp("body")))


def test_rotation_conversions_round_trip() -> None:
    rng = np.random.default_rng(0)
    axis_angle = torch.from_numpy(rng.normal(size=(200, 3)) * 1.2)
    axis_angle[0] = 0.0
    axis_angle[1] = torch.tensor([3.1, 0.0, 0.0], dtype=torch.float64)  # near pi
    back = matrix_to_axis_angle(axis_angle_to_matrix(axis_angle))
    torch.testing.assert_close(axis_angle_to_matrix(back), axis_angle_to_matrix(axis_angle), atol=1e-9, rtol=0)
    six = rng.normal(size=(10, 6))
    torch.testing.assert_close(rot6d_to_matrix(torch.from_numpy(six)), torch.from_numpy(np_rot6d_to_matrix(six)))


def test_torch_layer_matches_the_numpy_layer_within_1e_5_m(body_model: SMPLXModel) -> None:
    rng = np.random.default_rng(3)
    layer = TorchSMPLX(body_model)
    outputs = {"root_pose": rng.normal(size=(2, 6)), "body_pose": rng.normal(size=(2, 126)),
               "lhand_pose": rng.normal(size=(2, 90)), "rhand_pose": rng.normal(size=(2, 90)),
               "jaw_pose": rng.normal(size=(2, 6)), "betas": rng.normal(size=(2, 10)),
               "expression": rng.normal(size=(2, 10))}
    got = mesh_from_outputs(layer, {k: torch.from_numpy(v).float() for k, v in outputs.items()}).numpy()
    for b in range(2):
        params = SMPLXParams(
            root_rotation=np_rot6d_to_matrix(outputs["root_pose"][b].reshape(1, 6))[0],
            body_rotations=np_rot6d_to_matrix(outputs["body_pose"][b].reshape(21, 6)),
            jaw_rotation=np_rot6d_to_matrix(outputs["jaw_pose"][b].reshape(1, 6))[0],
            left_hand_rotations=unmirror_left_hand(np_rot6d_to_matrix(outputs["lhand_pose"][b].reshape(15, 6))),
            right_hand_rotations=np_rot6d_to_matrix(outputs["rhand_pose"][b].reshape(15, 6)),
            betas=outputs["betas"][b], expression=outputs["expression"][b])
        expected = body_model.forward(params).vertices
        assert np.abs(got[b] - expected).max() <= 1e-5
    # The loss is centroid-relative: a translated copy costs nothing, a scaled one does.
    mesh = torch.from_numpy(got)
    assert float(vertex_loss(mesh + torch.tensor([1.0, -2.0, 3.0]), mesh).max()) < 1e-6
    assert float(vertex_loss(mesh * 1.1, mesh).min()) > 1e-3
