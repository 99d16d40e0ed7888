"""The FP32 tail after the HMR engine.

Camera translation, virtual intrinsics, hand un-mirroring (docs/ALGORITHMS.md §3).
"""

from __future__ import annotations

import math
from typing import Sequence, Tuple, Union

import numpy as np

from leapnbv_common.array_types import FloatArray, FloatingArray

# SMPLer-X's virtual camera for the 256x192 body crop.
VIRTUAL_FOCAL = (5000.0, 5000.0)
BODY_INPUT_SHAPE = (256, 192)  # (H, W) of the ViT input
CAMERA_3D_SIZE = 2.5  # metres of the body box the depth prior assumes

# Reflection across the x = 0 plane (the mirrored left-hand crop).
_MIRROR = np.diag([-1.0, 1.0, 1.0])


def _sigmoid(value: float) -> float:
    """Numerically stable logistic function."""
    if value >= 0.0:
        return 1.0 / (1.0 + math.exp(-value))
    exp_value = math.exp(value)
    return exp_value / (1.0 + exp_value)


def depth_scale(
    focal: Sequence[float] = VIRTUAL_FOCAL, input_body_shape: Sequence[int] = BODY_INPUT_SHAPE
) -> float:
    """The depth factor k = sqrt(fx fy 2.5^2 / (H W)) = 56.38 for SMPLer-X's defaults."""
    return math.sqrt(
        float(focal[0]) * float(focal[1]) * CAMERA_3D_SIZE * CAMERA_3D_SIZE
        / (float(input_body_shape[0]) * float(input_body_shape[1]))
    )


def camera_translation(
    cam_param: Union[Sequence[float], FloatingArray],
    focal: Sequence[float] = VIRTUAL_FOCAL,
    input_body_shape: Sequence[int] = BODY_INPUT_SHAPE,
) -> FloatArray:
    """Translation of the body in the virtual crop camera.

    t_xy = cam_param[:2]; t_z = k * sigmoid(cam_param[2]), k = sqrt(fx fy 2.5^2 / (H W)).

    Args:
        cam_param: (3,) engine output (t_x, t_y, gamma).
        focal: virtual focal (fx, fy) in body-crop pixels.
        input_body_shape: (H, W) of the body crop.

    Returns:
        (3,) float64 translation in metres. Non-finite inputs give a non-finite result;
        the caller rejects it.
    """
    values = np.asarray(cam_param, dtype=np.float64).reshape(-1)
    if values.size != 3:
        raise ValueError("cam_param must have 3 values, got %d" % values.size)
    gamma = float(values[2])
    t_z = depth_scale(focal, input_body_shape) * (_sigmoid(gamma) if math.isfinite(gamma) else float("nan"))
    return np.array([values[0], values[1], t_z], dtype=np.float64)


def virtual_intrinsics(processed_box: Union[Sequence[float], FloatArray]) -> Tuple[float, float, float, float]:
    """Intrinsics that project the crop-camera mesh onto the person in the source image.

    focal = (5000/192 * w, 5000/256 * h), principal = (96/192 * w + x, 128/256 * h + y)
    for the processed box (x, y, w, h).

    Args:
        processed_box: [x, y, w, h] from `process_box`.

    Returns:
        (fx, fy, cx, cy) in source-image pixels.
    """
    x, y, w, h = (float(v) for v in processed_box[:4])
    body_h, body_w = BODY_INPUT_SHAPE
    fx = VIRTUAL_FOCAL[0] / body_w * w
    fy = VIRTUAL_FOCAL[1] / body_h * h
    cx = (body_w / 2.0) / body_w * w + x
    cy = (body_h / 2.0) / body_h * h + y
    return fx, fy, cx, cy


def unmirror_left_hand(rotations: FloatArray) -> FloatArray:
    """Undo the mirrored left-hand crop: R_L = S R S, S = diag(-1, 1, 1).

    In axis-angle terms this negates the y and z components, as SMPLer-X does.

    Args:
        rotations: (..., 3, 3) rotation matrices predicted on the mirrored crop.

    Returns:
        (..., 3, 3) rotations for the real left hand (still proper rotations).
    """
    unmirrored: FloatArray = _MIRROR @ np.asarray(rotations) @ _MIRROR
    return unmirrored
