"""Camera poses in the simulator's world (metres, z up, floor z = 0).

A camera pose is ``T_world_camera``: the rotation's columns are the optical axes (x right, y down,
z forward) in world coordinates and the position is the optical centre in the world.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Tuple

import numpy as np


@dataclass
class CameraPose:
    """T_world_camera: rotation (3,3) whose columns are the optical axes in the world, position (3,)."""

    rotation: np.ndarray
    position: np.ndarray

    def as_matrix(self) -> np.ndarray:
        """(4,4) homogeneous T_world_camera."""
        matrix = np.eye(4)
        matrix[:3, :3] = self.rotation
        matrix[:3, 3] = self.position
        return matrix

    @classmethod
    def from_matrix(cls, matrix: np.ndarray) -> CameraPose:
        """Build from a (4,4) homogeneous T_world_camera."""
        matrix = np.asarray(matrix, dtype=np.float64)
        if matrix.shape != (4, 4):
            raise ValueError(f"T_world_camera must be (4,4), got {matrix.shape}")
        return cls(matrix[:3, :3].copy(), matrix[:3, 3].copy())

    def copy(self) -> CameraPose:
        """An independent copy (the arrays are copied)."""
        return CameraPose(self.rotation.copy(), self.position.copy())

    def world_to_camera(self, points_world: np.ndarray) -> np.ndarray:
        """(N,3) world points -> (N,3) camera optical frame: R^T (p - position)."""
        return (np.asarray(points_world, dtype=np.float64) - self.position) @ self.rotation


def yaw_matrix(angle: float) -> np.ndarray:
    """(3,3) rotation by ``angle`` radians about world z."""
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def look_at_pose(
    position: np.ndarray, target: np.ndarray, up: Tuple[float, float, float] = (0.0, 0.0, 1.0)
) -> CameraPose:
    """Camera at ``position`` with its optical z toward ``target`` and x parallel to the floor.

    z = normalize(target - position), x = normalize(z x up) (right), y = z x x (down).

    Args:
        position: (3,) camera centre in the world.
        target: (3,) point to look at.
        up: World up direction.

    Returns:
        T_world_camera.

    Raises:
        ValueError: target coincides with position or lies straight above/below it.
    """
    position = np.asarray(position, dtype=np.float64).reshape(3)
    forward = np.asarray(target, dtype=np.float64).reshape(3) - position
    norm = np.linalg.norm(forward)
    if norm < 1e-9:
        raise ValueError("look_at_pose: target coincides with position")
    z_axis = forward / norm
    x_axis = np.cross(z_axis, np.asarray(up, dtype=np.float64))
    x_norm = np.linalg.norm(x_axis)
    if x_norm < 1e-9:
        raise ValueError("look_at_pose: viewing direction is parallel to up")
    x_axis /= x_norm
    y_axis = np.cross(z_axis, x_axis)
    return CameraPose(np.stack([x_axis, y_axis, z_axis], axis=1), position)


def pose_in_world(T_world_obscam: CameraPose, R_obs_new: np.ndarray, p_obs_new: np.ndarray) -> CameraPose:
    """Move the camera to a pose given in an observation's optical frame.

    T_world_new = T_world_obs T_obs_new: R = R_wo R_on, p = R_wo p_on + p_wo.

    Args:
        T_world_obscam: Pose of the camera that made the observation.
        R_obs_new: (3,3) new camera axes in the observation's optical frame.
        p_obs_new: (3,) new camera centre in the observation's optical frame.

    Returns:
        T_world_newcam.
    """
    R_on = np.asarray(R_obs_new, dtype=np.float64).reshape(3, 3)
    p_on = np.asarray(p_obs_new, dtype=np.float64).reshape(3)
    return CameraPose(
        T_world_obscam.rotation @ R_on,
        T_world_obscam.rotation @ p_on + T_world_obscam.position,
    )


def camera_pose_from_base_goal(
    base_xy: np.ndarray,
    heading_rad: float,
    camera_height: float,
    pitch_rad: float = 0.0,
) -> CameraPose:
    """Camera pose of a robot whose base stands at ``base_xy`` (floor z = 0) facing ``heading_rad``.

    The camera sits straight above the base point at ``camera_height``; its optical axis points
    along the heading (angle from world +x about +z), pitched down by ``pitch_rad``.

    Args:
        base_xy: (2,) base position on the floor, world metres.
        heading_rad: Heading about world z.
        camera_height: Optical centre height above the floor (m).
        pitch_rad: Downward pitch of the optical axis (rad).

    Returns:
        T_world_camera.
    """
    base = np.asarray(base_xy, dtype=np.float64).reshape(2)
    direction = np.array(
        [np.cos(heading_rad) * np.cos(pitch_rad), np.sin(heading_rad) * np.cos(pitch_rad), -np.sin(pitch_rad)]
    )
    position = np.array([base[0], base[1], float(camera_height)])
    return look_at_pose(position, position + direction)
