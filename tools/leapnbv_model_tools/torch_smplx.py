"""SMPL-X in PyTorch (differentiable, batched), from the project's numpy layer's arrays.

Same math and conventions as ``leapnbv_perception.smplx_layer.SMPLXModel.forward`` (betas =
shape columns [:10], expression from the model's expression offset, no PCA hands, the hand
mean pose added in axis-angle, eyes at identity), so a mesh computed here for training equals
the one the robot's tail computes (tests: <= 1e-5 m). Also the network-output side of the tail:
6D rotations (Gram-Schmidt, the SMPLer-X convention) and the left hand's un-mirroring.
"""

from __future__ import annotations

from typing import Dict, Tuple

import torch
from torch import nn

NUM_JOINTS = 55
NUM_BODY_JOINTS = 21
NUM_HAND_JOINTS = 15
JAW_JOINT = 22
LEFT_HAND_FIRST_JOINT = 25
RIGHT_HAND_FIRST_JOINT = 40


def rot6d_to_matrix(rot6d: torch.Tensor) -> torch.Tensor:
    """(..., 6) -> (..., 3, 3): columns b1, b2, b3 from a1 = x[0::2], a2 = x[1::2] (leapnbv_perception.rotations)."""
    a1, a2 = rot6d[..., 0::2], rot6d[..., 1::2]
    b1 = a1 / a1.norm(dim=-1, keepdim=True).clamp(min=1e-8)
    a2 = a2 - (b1 * a2).sum(dim=-1, keepdim=True) * b1
    b2 = a2 / a2.norm(dim=-1, keepdim=True).clamp(min=1e-8)
    return torch.stack([b1, b2, torch.cross(b1, b2, dim=-1)], dim=-1)


def unmirror(rotations: torch.Tensor) -> torch.Tensor:
    """R_L = S R S, S = diag(-1, 1, 1) (leapnbv_perception.hmr_tail.unmirror_left_hand)."""
    sign = torch.tensor([-1.0, 1.0, 1.0], dtype=rotations.dtype, device=rotations.device)
    return rotations * sign[:, None] * sign[None, :]


def _sqrt_positive(x: torch.Tensor) -> torch.Tensor:
    return torch.where(x > 0, torch.sqrt(torch.clamp(x, min=1e-20)), torch.zeros_like(x))


def matrix_to_quaternion(matrix: torch.Tensor) -> torch.Tensor:
    """(..., 3, 3) -> (..., 4) (w, x, y, z), the best-conditioned of the four candidates."""
    m = matrix.reshape(matrix.shape[:-2] + (9,))
    m00, m01, m02, m10, m11, m12, m20, m21, m22 = m.unbind(-1)
    q_abs = _sqrt_positive(torch.stack([1.0 + m00 + m11 + m22, 1.0 + m00 - m11 - m22,
                                        1.0 - m00 + m11 - m22, 1.0 - m00 - m11 + m22], dim=-1))
    candidates = torch.stack([
        torch.stack([q_abs[..., 0] ** 2, m21 - m12, m02 - m20, m10 - m01], dim=-1),
        torch.stack([m21 - m12, q_abs[..., 1] ** 2, m10 + m01, m02 + m20], dim=-1),
        torch.stack([m02 - m20, m10 + m01, q_abs[..., 2] ** 2, m12 + m21], dim=-1),
        torch.stack([m10 - m01, m20 + m02, m21 + m12, q_abs[..., 3] ** 2], dim=-1),
    ], dim=-2)
    candidates = candidates / (2.0 * q_abs[..., None].clamp(min=0.1))
    best = torch.nn.functional.one_hot(q_abs.argmax(dim=-1), 4).to(matrix.dtype)
    quaternion = (candidates * best[..., None]).sum(dim=-2)
    return quaternion * torch.where(quaternion[..., :1] < 0, -1.0, 1.0)


def quaternion_to_axis_angle(quaternion: torch.Tensor) -> torch.Tensor:
    norms = quaternion[..., 1:].norm(dim=-1, keepdim=True)
    half = torch.atan2(norms, quaternion[..., :1])
    angles = 2.0 * half
    small = angles.abs() < 1e-6
    safe = torch.where(small, torch.ones_like(angles), angles)
    factor = torch.where(small, 0.5 - angles * angles / 48.0, torch.sin(half) / safe)
    return quaternion[..., 1:] / factor


def axis_angle_to_matrix(axis_angle: torch.Tensor) -> torch.Tensor:
    angles = axis_angle.norm(dim=-1, keepdim=True)
    half = 0.5 * angles
    small = angles.abs() < 1e-6
    safe = torch.where(small, torch.ones_like(angles), angles)
    factor = torch.where(small, 0.5 - angles * angles / 48.0, torch.sin(half) / safe)
    w = torch.cos(half)[..., 0]
    x, y, z = (axis_angle * factor).unbind(-1)
    two = 2.0
    return torch.stack([
        1 - two * (y * y + z * z), two * (x * y - z * w), two * (x * z + y * w),
        two * (x * y + z * w), 1 - two * (x * x + z * z), two * (y * z - x * w),
        two * (x * z - y * w), two * (y * z + x * w), 1 - two * (x * x + y * y),
    ], dim=-1).reshape(axis_angle.shape[:-1] + (3, 3))


def matrix_to_axis_angle(matrix: torch.Tensor) -> torch.Tensor:
    return quaternion_to_axis_angle(matrix_to_quaternion(matrix))


class TorchSMPLX(nn.Module):
    """Batched SMPL-X LBS with the arrays of a loaded ``SMPLXModel`` (buffers, no parameters)."""

    def __init__(self, model, dtype: torch.dtype = torch.float32) -> None:
        super().__init__()

        def buffer(name: str, array) -> None:
            self.register_buffer(name, torch.as_tensor(array).to(dtype).clone(), persistent=False)

        buffer("v_template", model.v_template)
        buffer("shape_dirs", model.shape_dirs_flat)  # (V*3, 20)
        buffer("pose_dirs", model.pose_dirs_flat)  # (486, V*3)
        buffer("joint_template", model.joint_template)  # (55, 3)
        buffer("joint_shape_dirs", model.joint_shape_dirs)  # (165, 20)
        buffer("weights", model.weights)  # (V, 55)
        buffer("left_hand_mean", model.left_hand_mean)
        buffer("right_hand_mean", model.right_hand_mean)
        self.parents = [int(p) for p in model.parents]
        self.faces = model.faces

    def forward(self, root: torch.Tensor, body: torch.Tensor, left_hand: torch.Tensor, right_hand: torch.Tensor,
                jaw: torch.Tensor, betas: torch.Tensor, expression: torch.Tensor,
                add_hand_mean: bool = True) -> Tuple[torch.Tensor, torch.Tensor]:
        """Rotation matrices (B, 3, 3) / (B, 21, 3, 3) / (B, 15, 3, 3) x2 / (B, 3, 3), betas and expression (B, 10).

        Returns:
            (vertices (B, V, 3), joints (B, 55, 3)) in the model frame.
        """
        batch = root.shape[0]
        dtype = self.v_template.dtype
        if add_hand_mean:
            left_hand = axis_angle_to_matrix(matrix_to_axis_angle(left_hand) + self.left_hand_mean)
            right_hand = axis_angle_to_matrix(matrix_to_axis_angle(right_hand) + self.right_hand_mean)
        eye = torch.eye(3, dtype=dtype).expand(batch, 1, 3, 3)
        rotations = torch.cat([root[:, None], body, jaw[:, None], eye, eye, left_hand, right_hand], dim=1).to(dtype)
        coefficients = torch.cat([betas, expression], dim=1).to(dtype)
        v_shaped = self.v_template + (coefficients @ self.shape_dirs.T).reshape(batch, -1, 3)
        joints = self.joint_template + (coefficients @ self.joint_shape_dirs.T).reshape(batch, NUM_JOINTS, 3)
        pose_feature = (rotations[:, 1:] - torch.eye(3, dtype=dtype)).reshape(batch, -1)
        v_posed = v_shaped + (pose_feature @ self.pose_dirs).reshape(batch, -1, 3)
        relative = joints.clone()
        relative[:, 1:] = joints[:, 1:] - joints[:, self.parents[1:]]
        local = torch.cat([torch.cat([rotations, relative[..., None]], dim=3),
                           torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=dtype).expand(batch, NUM_JOINTS, 1, 4)], dim=2)
        world = [local[:, 0]]
        for joint in range(1, NUM_JOINTS):
            world.append(world[self.parents[joint]] @ local[:, joint])
        world_t = torch.stack(world, dim=1)  # (B, 55, 4, 4)
        posed_joints = world_t[:, :, :3, 3]
        translation = posed_joints - (world_t[:, :, :3, :3] @ joints[..., None])[..., 0]
        top = torch.cat([world_t[:, :, :3, :3], translation[..., None]], dim=3).reshape(batch, NUM_JOINTS, 12)
        blended = (self.weights @ top).reshape(batch, -1, 3, 4)
        vertices = (blended[..., :3] @ v_posed[..., None])[..., 0] + blended[..., 3]
        return vertices, posed_joints


def mesh_from_outputs(layer: TorchSMPLX, outputs: Dict[str, torch.Tensor], unmirror_left: bool = True) -> torch.Tensor:
    """Vertices (B, V, 3) in the model frame from the HMR contract outputs (B, n) each."""
    batch = outputs["root_pose"].shape[0]
    left = rot6d_to_matrix(outputs["lhand_pose"].reshape(batch, NUM_HAND_JOINTS, 6))
    if unmirror_left:
        left = unmirror(left)
    vertices, _ = layer(
        rot6d_to_matrix(outputs["root_pose"].reshape(batch, 6)),
        rot6d_to_matrix(outputs["body_pose"].reshape(batch, NUM_BODY_JOINTS, 6)),
        left,
        rot6d_to_matrix(outputs["rhand_pose"].reshape(batch, NUM_HAND_JOINTS, 6)),
        rot6d_to_matrix(outputs["jaw_pose"].reshape(batch, 6)),
        outputs["betas"].reshape(batch, -1), outputs["expression"].reshape(batch, -1))
    return vertices


def mesh_from_axis_angle(layer: TorchSMPLX, params: Dict[str, torch.Tensor]) -> torch.Tensor:
    """Vertices (B, V, 3) from axis-angle ground truth: root (B, 3), body (B, 63), lhand/rhand (B, 45), jaw (B, 3)."""
    batch = params["root"].shape[0]
    vertices, _ = layer(
        axis_angle_to_matrix(params["root"].reshape(batch, 3)),
        axis_angle_to_matrix(params["body"].reshape(batch, NUM_BODY_JOINTS, 3)),
        axis_angle_to_matrix(params["lhand"].reshape(batch, NUM_HAND_JOINTS, 3)),
        axis_angle_to_matrix(params["rhand"].reshape(batch, NUM_HAND_JOINTS, 3)),
        axis_angle_to_matrix(params["jaw"].reshape(batch, 3)),
        params["betas"].reshape(batch, -1), params["expression"].reshape(batch, -1))
    return vertices


def centroid_relative(vertices: torch.Tensor) -> torch.Tensor:
    return vertices - vertices.mean(dim=-2, keepdim=True)


def vertex_loss(student: torch.Tensor, teacher: torch.Tensor) -> torch.Tensor:
    """Mean per-vertex distance (m) between centroid-relative meshes, per sample: (B,)."""
    return (centroid_relative(student) - centroid_relative(teacher)).norm(dim=-1).mean(dim=-1)
