"""A floor plane of one camera frame moved into another by the camera poses of both (nbv_node's carried plane).

ROS-free. When a frame's own ground plane never came, nbv_node plans it on the newest valid plane of
an older frame, carried by the camera-pose delta between the two stamps.
"""
from __future__ import annotations

from typing import Tuple

import numpy as np

from leapnbv_common.array_types import FloatArray
from leapnbv_planner.inputs import CameraPose

__all__ = ["carry_plane"]


def carry_plane(normal: FloatArray, offset: float, pose_from: CameraPose,
                pose_to: CameraPose) -> Tuple[FloatArray, float]:
    """The plane n.x + d = 0 of camera frame ``pose_from`` expressed in camera frame ``pose_to``.

    Both poses are camera -> fixed frame (p_fixed = R p_camera + t). A point x_to of the new frame is
    R_from^T (R_to x_to + t_to - t_from) in the old one, so n_to = R_to^T R_from n and
    d_to = d + n . R_from^T (t_to - t_from).

    Args:
        normal: (3,) the plane's unit normal in the old camera frame.
        offset: d of the old camera frame.
        pose_from: the old frame's camera pose.
        pose_to: the new frame's camera pose (in the same fixed frame).

    Returns:
        (normal (3,), offset) in the new camera frame.
    """
    n = np.asarray(normal, dtype=np.float64)
    r_from = np.asarray(pose_from.rotation, dtype=np.float64)
    r_to = np.asarray(pose_to.rotation, dtype=np.float64)
    delta = np.asarray(pose_to.position, dtype=np.float64) - np.asarray(pose_from.position, dtype=np.float64)
    n_to: FloatArray = r_to.T @ (r_from @ n)
    d_to = float(offset) + float(n @ (r_from.T @ delta))
    return n_to, d_to
