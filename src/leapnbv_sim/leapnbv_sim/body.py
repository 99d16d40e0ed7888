"""The scene's person: SMPL-X parameters, a random standing pose, and the body placed in the world.

The body stands with its pelvis above the world origin and its lowest vertex on the floor
(z = 0). Its parameters are kept in the world (``root_pose`` is the world orientation); a
camera's view of them is :func:`body_params_in_camera`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Tuple

import numpy as np

from leapnbv_common.array_types import FloatArray, IntArray
from leapnbv_perception.rotations import axis_angle_to_matrix, matrix_to_axis_angle
from leapnbv_perception.smplx_layer import SMPLXModel, SMPLXParams
from leapnbv_sim.poses import CameraPose, yaw_matrix

# SMPL-X joint indices (body_pose holds joints 1..21, three values each).
_LEFT_HIP, _RIGHT_HIP, _SPINE1, _LEFT_KNEE, _RIGHT_KNEE = 1, 2, 3, 4, 5
_SPINE2, _SPINE3, _NECK, _HEAD = 6, 9, 12, 15
_LEFT_SHOULDER, _RIGHT_SHOULDER, _LEFT_ELBOW, _RIGHT_ELBOW = 16, 17, 18, 19

# Body rest frame (y up, facing +z) -> world (z up) facing -x (toward a camera on the -x side):
# columns are the images of the body's x, y, z axes.
BODY_TO_WORLD_FACING_MINUS_X = np.array([[0.0, 0.0, -1.0], [-1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])


@dataclass
class BodyParams:
    """SMPL-X parameters, axis-angle (radians) per joint; shapes as in SceneGroundTruth.msg."""

    root_pose: FloatArray  # (3,)
    body_pose: FloatArray  # (63,)
    left_hand_pose: FloatArray  # (45,)
    right_hand_pose: FloatArray  # (45,)
    jaw_pose: FloatArray  # (3,)
    betas: FloatArray  # (10,)
    expression: FloatArray  # (10,)

    def to_smplx_params(self) -> SMPLXParams:
        """The same parameters as ``leapnbv_perception.smplx_layer.SMPLXParams``."""
        return SMPLXParams.from_axis_angle(
            self.root_pose,
            self.body_pose,
            self.left_hand_pose,
            self.right_hand_pose,
            self.jaw_pose,
            self.betas,
            self.expression,
        )

    def with_root(self, root_pose: FloatArray) -> BodyParams:
        """A copy with another root orientation."""
        return BodyParams(
            np.asarray(root_pose, dtype=np.float64).reshape(3),
            self.body_pose.copy(),
            self.left_hand_pose.copy(),
            self.right_hand_pose.copy(),
            self.jaw_pose.copy(),
            self.betas.copy(),
            self.expression.copy(),
        )


@dataclass
class PlacedBody:
    """A posed body standing in the world.

    Attributes:
        params_world: Parameters posed in the world: root_pose is the world orientation.
        forward_vertices: (V,3) ``model.forward(params_world).vertices``.
        root_joint: (3,) root joint of that forward pass (fixed under root rotation).
        translation_world: (3,) with vertices_world = forward_vertices + this.
        faces: (F,3) int32 the body model's triangles.
    """

    params_world: BodyParams
    forward_vertices: FloatArray
    root_joint: FloatArray
    translation_world: FloatArray
    faces: IntArray

    @property
    def vertices_world(self) -> FloatArray:
        """(V,3) body vertices in the world."""
        return self.forward_vertices + self.translation_world


def sample_body_pose(rng: np.random.Generator) -> Tuple[FloatArray, FloatArray]:
    """A mild standing pose and shape.

    Arms lowered from the T-pose by 55-80 degrees at the shoulders, elbows bent 0-40 degrees,
    small random bends (sigma 0.06 rad, clipped to 0.15) at every body joint, a slight knee
    flex, the head turned a little. Betas ~ N(0, 0.5) clipped to +-1.2.

    Args:
        rng: Random generator.

    Returns:
        (body_pose (63,), betas (10,)).
    """
    pose = np.clip(rng.normal(0.0, 0.06, size=(21, 3)), -0.15, 0.15)

    def add(joint: int, axis_angle: Tuple[float, float, float]) -> None:
        pose[joint - 1] += np.asarray(axis_angle)

    left_lower = rng.uniform(np.radians(55), np.radians(80))
    right_lower = rng.uniform(np.radians(55), np.radians(80))
    # The left arm points along +x in the rest frame; a negative turn about z lowers it.
    add(_LEFT_SHOULDER, (0.0, 0.0, -left_lower))
    add(_RIGHT_SHOULDER, (0.0, 0.0, right_lower))
    add(_LEFT_ELBOW, (0.0, -rng.uniform(0.0, np.radians(40)), 0.0))
    add(_RIGHT_ELBOW, (0.0, rng.uniform(0.0, np.radians(40)), 0.0))
    knee = rng.uniform(0.0, np.radians(15))
    add(_LEFT_KNEE, (knee, 0.0, 0.0))
    add(_RIGHT_KNEE, (knee, 0.0, 0.0))
    add(_HEAD, (0.0, rng.uniform(-0.3, 0.3), 0.0))
    betas = np.clip(rng.normal(0.0, 0.5, size=10), -1.2, 1.2)
    return pose.reshape(63), betas


def place_body(body_model: SMPLXModel, heading_rad: float, body_pose: FloatArray, betas: FloatArray) -> PlacedBody:
    """Pose the body and stand it on the floor, pelvis above the world origin.

    With heading 0 the body faces -x (toward a camera on the -x side); the heading turns it
    about world z. Hands, jaw and expression are neutral.

    Args:
        body_model: A loaded ``leapnbv_perception.smplx_layer.SMPLXModel``.
        heading_rad: Turn about world z from facing -x.
        body_pose: (63,) axis-angle of joints 1..21.
        betas: (10,) shape.

    Returns:
        The placed body.
    """
    R_root_world = yaw_matrix(heading_rad) @ BODY_TO_WORLD_FACING_MINUS_X
    params_world = BodyParams(
        root_pose=matrix_to_axis_angle(R_root_world),
        body_pose=body_pose,
        left_hand_pose=np.zeros(45),
        right_hand_pose=np.zeros(45),
        jaw_pose=np.zeros(3),
        betas=betas,
        expression=np.zeros(10),
    )
    output = body_model.forward(params_world.to_smplx_params())
    forward_vertices = np.asarray(output.vertices, dtype=np.float64)
    root_joint = np.asarray(output.joints, dtype=np.float64)[0]
    # Pelvis above the world origin, lowest vertex on the floor.
    translation_world = np.array([-root_joint[0], -root_joint[1], -forward_vertices[:, 2].min()])
    faces = np.asarray(body_model.faces, dtype=np.int32)
    return PlacedBody(params_world, forward_vertices, root_joint, translation_world, faces)


def body_params_in_camera(
    params_world: BodyParams, root_joint: FloatArray, translation_world: FloatArray, camera: CameraPose
) -> Tuple[BodyParams, FloatArray]:
    """Body parameters and translation in a camera's optical frame.

    With R_cw = R^T and J the root joint, the forward pass with root orientation
    R_cw R_root gives R_cw (v_f - J) + J, and the camera-frame vertices are
    R_cw (v_f + t_w - p). Their difference is the translation R_cw (t_w + J - p) - J.

    Args:
        params_world: Parameters posed in the world.
        root_joint: (3,) root joint of the world forward pass.
        translation_world: (3,) world translation of the forward pass.
        camera: T_world_camera.

    Returns:
        (params, translation (3,)) with forward(params).vertices + translation equal to the
        body vertices in the camera frame.
    """
    R_cw = camera.rotation.T
    R_root_world = axis_angle_to_matrix(params_world.root_pose)
    root_camera = matrix_to_axis_angle(R_cw @ R_root_world)
    translation = R_cw @ (translation_world + root_joint - camera.position) - root_joint
    return params_world.with_root(root_camera), translation


def body_model_id(body_model: SMPLXModel, body_resolution: str) -> str:
    """The model's own id, or "stand_in_<resolution>" for a model without one."""
    model_id = getattr(body_model, "model_id", None)
    return str(model_id) if model_id else "stand_in_" + body_resolution
