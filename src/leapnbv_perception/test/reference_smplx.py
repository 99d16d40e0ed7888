"""A straightforward SMPL-X LBS the fast layer is checked against (tests and the perception benchmark).

Joint regression from the shaped vertices (not the precomputed joint directions), float64
throughout, and skinning as a loop over the 55 joints, each step written as lbs.py writes it.
It uses the layer's step functions and arrays, so it checks how `SMPLXModel.forward` composes
and precomputes them; `test_perception_smplx_dense.py` checks the steps against the equations.
"""

from __future__ import annotations

import numpy as np

from leapnbv_perception.smplx_layer import (
    NUM_JOINTS,
    SMPLXModel,
    SMPLXOutput,
    SMPLXParams,
    batch_rigid_transform,
    blend_shapes,
    pose_blend,
    vertices2joints,
)


def forward_reference(model: SMPLXModel, params: SMPLXParams, add_hand_mean: bool = True) -> SMPLXOutput:
    """Pose and shape the body the slow way; the same result as `model.forward(params)`.

    Args:
        model: the loaded body model.
        params: pose (rotation matrices), betas and expression.
        add_hand_mean: add the hand mean pose (SMPLer-X: True).

    Returns:
        SMPLXOutput with vertices (V, 3) and joints (55, 3), float32, model frame.
    """
    rotations = model.full_pose_rotations(params, add_hand_mean)
    coefficients = model.shape_coefficients(params).astype(np.float64)
    shape_dirs = model.shape_dirs_flat.astype(np.float64)
    v_shaped = model.v_template.astype(np.float64) + blend_shapes(coefficients, shape_dirs)
    joints = vertices2joints(model.joint_regressor, v_shaped)
    v_posed = v_shaped + pose_blend(rotations, model.pose_dirs_flat.astype(np.float64))
    posed_joints, transforms = batch_rigid_transform(rotations, joints, model.parents)
    homogeneous = np.concatenate([v_posed, np.ones((v_posed.shape[0], 1))], axis=1)
    vertices = np.zeros_like(v_posed)
    for joint in range(NUM_JOINTS):
        moved = (homogeneous @ transforms[joint].T)[:, :3]
        vertices += model.weights[:, joint : joint + 1].astype(np.float64) * moved
    return SMPLXOutput(vertices=vertices.astype(np.float32), joints=posed_joints.astype(np.float32))
