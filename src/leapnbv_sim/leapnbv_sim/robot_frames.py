"""The simulated robot's frames, as a robot publishes them on TF: each camera pose split into base and head.

The simulator knows the world pose of the camera of every frame (``T_world_camera``, the optical
axes). A robot publishes that pose as a chain of frames (REP 105, REP 103):

    world (the map) -> odom -> base_link -> camera_link -> camera_color_optical_frame

* ``world -> odom``: the identity: the simulated odometry does not drift (dynamic, on /tf, as a
  localization publishes it);
* ``odom -> base_link``: the base on the floor (z = 0) under the camera's optical centre, facing the
  camera's heading (dynamic: it drives to each goal);
* ``base_link -> camera_link``: the pan-tilt head: the camera's height above the floor and its pitch
  (with ``robot_motion: free``, whatever roll and offset the 6-DoF goal had): dynamic, since the head
  tilts to each goal's pitch;
* ``camera_link -> optical frame``: x forward, y left, z up -> x right, y down, z forward (static, on
  /tf_static).

Composed, the chain is the camera's pose again (to rounding): :func:`dynamic_links` is exact for any
camera pose, :class:`RobotModel`'s or not.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import List

import numpy as np

from leapnbv_common.tf_buffer import StampedTransform, Transform
from leapnbv_sim.poses import CameraPose, camera_heading

__all__ = ["RobotFrameIds", "OPTICAL_IN_CAMERA_LINK", "static_links", "dynamic_links"]

#: camera_link -> optical frame (REP 103): the optical x is the link's -y, y its -z, z its x.
OPTICAL_IN_CAMERA_LINK = Transform(np.array([-0.5, 0.5, -0.5, 0.5]), np.zeros(3))


@dataclass(frozen=True)
class RobotFrameIds:
    """The names of the robot's frames, from the fixed frame down to the camera's optical frame."""

    world: str = "sim_world"
    odom: str = "odom"
    base: str = "base_link"
    head: str = "camera_link"
    camera: str = "camera_color_optical_frame"


def static_links(ids: RobotFrameIds) -> List[StampedTransform]:
    """The links that never move (/tf_static): the camera's optical frame on its link."""
    return [StampedTransform(ids.head, ids.camera, 0, OPTICAL_IN_CAMERA_LINK)]


def dynamic_links(camera: CameraPose, stamp_ns: int, ids: RobotFrameIds) -> List[StampedTransform]:
    """The moving links (/tf) at ``stamp_ns`` for a camera at ``camera`` (T_world_camera).

    T_base_head = T_world_base^-1 T_world_camera T_head_camera^-1, with the base under the camera
    facing its heading, so that world -> odom -> base -> head -> camera composes to the camera.
    """
    heading = camera_heading(camera)
    x, y = (float(v) for v in np.asarray(camera.position, dtype=np.float64)[:2])
    base = Transform(np.array([0.0, 0.0, np.sin(heading / 2.0), np.cos(heading / 2.0)]), np.array([x, y, 0.0]))
    head = base.inverse() @ Transform.from_matrix(camera.rotation, camera.position) @ OPTICAL_IN_CAMERA_LINK.inverse()
    if head.rotation[3] < 0.0:  # q and -q are one rotation: publish the one with w >= 0
        head = Transform(-head.rotation, head.translation)
    stamp = int(stamp_ns)
    return [StampedTransform(ids.world, ids.odom, stamp, Transform.identity()),
            StampedTransform(ids.odom, ids.base, stamp, base),
            StampedTransform(ids.base, ids.head, stamp, head)]
