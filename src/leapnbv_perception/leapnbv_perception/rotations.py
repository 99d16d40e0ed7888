"""Rotation conversions (6D, matrix, axis-angle): defined once, in :mod:`leapnbv_common.rotations`.

The rotation math of every package lives in leapnbv_common (the lowest layer that needs it: the
pose messages' quaternions); this module keeps the perception code's import path to it.
"""

from __future__ import annotations

from leapnbv_common.rotations import (
    axis_angle_to_matrix,
    matrix_to_axis_angle,
    matrix_to_rot6d,
    rot6d_to_matrix,
)

__all__ = ["axis_angle_to_matrix", "matrix_to_axis_angle", "matrix_to_rot6d", "rot6d_to_matrix"]
