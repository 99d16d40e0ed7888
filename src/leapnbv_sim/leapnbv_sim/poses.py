"""Camera poses in the simulator's world (metres, z up, floor z = 0).

A camera pose is ``T_world_camera``: the rotation's columns are the optical axes (x right, y down,
z forward) in world coordinates and the position is the optical centre in the world.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Tuple

import numpy as np

from leapnbv_common.array_types import FloatArray


@dataclass
class CameraPose:
    """T_world_camera: rotation (3,3) whose columns are the optical axes in the world, position (3,)."""

    rotation: FloatArray
    position: FloatArray

    def as_matrix(self) -> FloatArray:
        """(4,4) homogeneous T_world_camera."""
        matrix = np.eye(4)
        matrix[:3, :3] = self.rotation
        matrix[:3, 3] = self.position
        return matrix

    @classmethod
    def from_matrix(cls, matrix: FloatArray) -> CameraPose:
        """Build from a (4,4) homogeneous T_world_camera."""
        matrix = np.asarray(matrix, dtype=np.float64)
        if matrix.shape != (4, 4):
            raise ValueError(f"T_world_camera must be (4,4), got {matrix.shape}")
        return cls(matrix[:3, :3].copy(), matrix[:3, 3].copy())

    def copy(self) -> CameraPose:
        """An independent copy (the arrays are copied)."""
        return CameraPose(self.rotation.copy(), self.position.copy())

    def world_to_camera(self, points_world: FloatArray) -> FloatArray:
        """(N,3) world points -> (N,3) camera optical frame: R^T (p - position)."""
        return (np.asarray(points_world, dtype=np.float64) - self.position) @ self.rotation


def yaw_matrix(angle: float) -> FloatArray:
    """(3,3) rotation by ``angle`` radians about world z."""
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def look_at_pose(
    position: FloatArray, target: FloatArray, up: Tuple[float, float, float] = (0.0, 0.0, 1.0)
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
    x_axis: FloatArray = np.cross(z_axis, np.asarray(up, dtype=np.float64))
    x_norm = np.linalg.norm(x_axis)
    if x_norm < 1e-9:
        raise ValueError("look_at_pose: viewing direction is parallel to up")
    x_axis /= x_norm
    y_axis = np.cross(z_axis, x_axis)
    return CameraPose(np.stack([x_axis, y_axis, z_axis], axis=1), position)


def pose_in_world(T_world_obscam: CameraPose, R_obs_new: FloatArray, p_obs_new: FloatArray) -> CameraPose:
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
    base_xy: FloatArray,
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


#: How the simulated robot reaches a goal: "base" drives its base and carries the camera at its
#: mounting height; "free" puts the camera at the goal's 6-DoF pose (no robot: the older evaluation).
ROBOT_MOTIONS: Tuple[str, ...] = ("base", "free")
#: The camera head: "pan_tilt" turns and tilts toward the goal's viewing direction; "fixed" turns with
#: the base only and keeps the mounting pitch.
HEAD_MODES: Tuple[str, ...] = ("pan_tilt", "fixed")


def camera_pitch(camera: CameraPose) -> float:
    """Downward pitch (rad) of a camera's optical axis below the horizon (world z up)."""
    forward = np.asarray(camera.rotation, dtype=np.float64)[:, 2]
    return float(np.arcsin(np.clip(-forward[2], -1.0, 1.0)))


def camera_heading(camera: CameraPose) -> float:
    """Heading (rad about world z) of a camera's optical axis; from its x axis when it looks straight down/up."""
    rotation = np.asarray(camera.rotation, dtype=np.float64)
    forward = rotation[:, 2]
    if np.hypot(forward[0], forward[1]) > 1e-6:
        return float(np.arctan2(forward[1], forward[0]))
    right = rotation[:, 0]  # forward is up x right, projected: heading = right turned +90 deg about z
    return float(np.arctan2(right[0], -right[1]))


def mounted_camera_pose(goal: CameraPose, camera_height: float, head: str = "pan_tilt",
                        pitch_rad: float = 0.0) -> CameraPose:
    """Where a wheeled robot's camera ends up when the robot is sent to a camera goal.

    The base drives to the goal's point on the floor (x, y of the goal's optical centre) and turns
    to the goal's heading; the camera sits ``camera_height`` above the floor with no roll. With a
    ``pan_tilt`` head it tilts to the goal's pitch; with a ``fixed`` head it keeps ``pitch_rad``
    (the mounting pitch). A goal the robot can reach exactly (at the mounting height, level x axis)
    gives the goal itself.

    Args:
        goal: The requested T_world_camera.
        camera_height: The camera's mounting height above the floor (m), > 0.
        head: One of HEAD_MODES.
        pitch_rad: Downward pitch of a fixed head (rad).

    Returns:
        The camera pose the robot reaches.

    Raises:
        ValueError: an unknown head or a non-positive height.
    """
    if head not in HEAD_MODES:
        raise ValueError(f"head must be one of {HEAD_MODES}, got {head!r}")
    if not camera_height > 0.0:
        raise ValueError(f"the camera's mounting height must be > 0, got {camera_height}")
    pitch = camera_pitch(goal) if head == "pan_tilt" else float(pitch_rad)
    return camera_pose_from_base_goal(np.asarray(goal.position, dtype=np.float64)[:2], camera_heading(goal),
                                      float(camera_height), pitch)


@dataclass
class RobotModel:
    """The simulated robot: how it moves to a camera goal (see ROBOT_MOTIONS, HEAD_MODES).

    Attributes:
        motion: "base" (default: the base drives, the camera stays at its mounting) or "free".
        head: "pan_tilt" (default) or "fixed".
        camera_height: Mounting height (m); 0 takes the height of the camera that observed the goal's frame.
    """

    motion: str = "base"
    head: str = "pan_tilt"
    camera_height: float = 0.0

    def __post_init__(self) -> None:
        if self.motion not in ROBOT_MOTIONS:
            raise ValueError(f"robot motion must be one of {ROBOT_MOTIONS}, got {self.motion!r}")
        if self.head not in HEAD_MODES:
            raise ValueError(f"robot head must be one of {HEAD_MODES}, got {self.head!r}")
        if not self.camera_height >= 0.0:
            raise ValueError(f"robot camera_height must be >= 0, got {self.camera_height}")

    def reach(self, observer: CameraPose, goal: CameraPose) -> CameraPose:
        """The camera pose after the robot, whose camera is at ``observer`` now, is sent to ``goal``.

        The mounting height (when 0) and a fixed head's pitch are the observer's: the same robot.
        """
        if self.motion == "free":
            return goal.copy()
        height = self.camera_height if self.camera_height > 0.0 else float(observer.position[2])
        return mounted_camera_pose(goal, height, self.head, camera_pitch(observer))
