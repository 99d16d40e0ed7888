"""Rotation representations and the conversions between them, vectorized over leading dimensions.

ROS-free (numpy only). The one place for rotation math: quaternions (x, y, z, w: the order of
geometry_msgs/Quaternion) for the pose messages and the transform tree (products, rotating a vector,
slerp), axis-angle for the SMPL-X body parameters, and the 6D representation the HMR network
outputs. A rotation matrix's columns are the rotated frame's axes.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, Tuple

import numpy as np

if TYPE_CHECKING:
    import numpy.typing as npt

__all__ = [
    "axis_angle_to_matrix",
    "matrix_to_axis_angle",
    "matrix_to_rot6d",
    "quaternion_multiply",
    "quaternion_rotate",
    "quaternion_to_rotation",
    "rot6d_to_matrix",
    "rotations_to_quaternions",
    "slerp",
]

# Norms below this are treated as zero: the direction they would give is meaningless.
_DEGENERATE_NORM = 1e-8


# --------------------------------------------------------------------------- quaternions


def rotations_to_quaternions(rotations: npt.ArrayLike) -> npt.NDArray[np.float64]:
    """(N, 4) (x, y, z, w) unit quaternions of (N, 3, 3) rotation matrices (Shepperd's method, w >= 0).

    Per matrix the largest of trace, m00, m11, m22 picks the formula whose divisor is far from 0;
    every formula is evaluated on every row (a few vector operations instead of a Python loop per
    pose) and each row keeps its own.

    Args:
        rotations: (N, 3, 3) (or anything that reshapes to it) rotation matrices.

    Returns:
        (N, 4) float64 quaternions, x, y, z, w, with w >= 0.
    """
    m = np.asarray(rotations, dtype=np.float64).reshape(-1, 3, 3)
    m00, m01, m02 = m[:, 0, 0], m[:, 0, 1], m[:, 0, 2]
    m10, m11, m12 = m[:, 1, 0], m[:, 1, 1], m[:, 1, 2]
    m20, m21, m22 = m[:, 2, 0], m[:, 2, 1], m[:, 2, 2]
    trace = m00 + m11 + m22
    case = np.where(trace > 0, 0, np.where((m00 > m11) & (m00 > m22), 1, np.where(m11 > m22, 2, 3)))
    with np.errstate(invalid="ignore", divide="ignore"):  # the rows a formula is not picked for
        s = 2.0 * np.sqrt(np.stack([trace + 1.0, 1.0 + m00 - m11 - m22, 1.0 + m11 - m00 - m22,
                                    1.0 + m22 - m00 - m11]))
        formulas = np.stack([
            [(m21 - m12) / s[0], (m02 - m20) / s[0], (m10 - m01) / s[0], 0.25 * s[0]],
            [0.25 * s[1], (m01 + m10) / s[1], (m02 + m20) / s[1], (m21 - m12) / s[1]],
            [(m01 + m10) / s[2], 0.25 * s[2], (m12 + m21) / s[2], (m02 - m20) / s[2]],
            [(m02 + m20) / s[3], (m12 + m21) / s[3], 0.25 * s[3], (m10 - m01) / s[3]],
        ])  # (4 formulas, 4 components, N)
    q: npt.NDArray[np.float64] = formulas[case, :, np.arange(len(m))]
    q /= np.sqrt(np.sum(q * q, axis=1))[:, None]
    return np.where(q[:, 3:4] < 0, -q, q)


def quaternion_to_rotation(xyzw: npt.ArrayLike) -> npt.NDArray[np.float64]:
    """3x3 rotation matrix of a (x, y, z, w) quaternion (normalized first).

    Args:
        xyzw: 4 numbers, x, y, z, w.

    Returns:
        (3, 3) float64 rotation matrix.
    """
    x, y, z, w = np.asarray(xyzw, dtype=np.float64).reshape(4) / np.linalg.norm(xyzw)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


def quaternion_multiply(a: npt.NDArray[np.float64], b: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
    """Hamilton product a b of (x, y, z, w) quaternions: the rotation b, then a.

    Args:
        a: (4,) quaternion.
        b: (4,) quaternion.

    Returns:
        (4,) float64 quaternion a b (unit when both are).
    """
    ax, ay, az, aw = a
    bx, by, bz, bw = b
    return np.array([aw * bx + ax * bw + ay * bz - az * by,
                     aw * by - ax * bz + ay * bw + az * bx,
                     aw * bz + ax * by - ay * bx + az * bw,
                     aw * bw - ax * bx - ay * by - az * bz])


def quaternion_rotate(q: npt.NDArray[np.float64], v: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
    """R(q) v for a unit (x, y, z, w) quaternion: v + 2 w (u x v) + 2 u x (u x v), u = (x, y, z).

    Args:
        q: (4,) unit quaternion.
        v: (3,) vector.

    Returns:
        (3,) the rotated vector.
    """
    u, w = q[:3], q[3]
    uv = np.cross(u, v)
    rotated: npt.NDArray[np.float64] = v + 2.0 * w * uv + 2.0 * np.cross(u, uv)
    return rotated


def slerp(q0: npt.ArrayLike, q1: npt.ArrayLike, fraction: float) -> npt.NDArray[np.float64]:
    """The rotation ``fraction`` of the way from q0 to q1 on the shorter arc (unit (x, y, z, w) quaternions).

    q(f) = sin((1 - f) theta) / sin(theta) q0 + sin(f theta) / sin(theta) q1, cos(theta) = |q0 . q1|,
    with q1 negated first when q0 . q1 < 0 (q and -q are the same rotation); a straight line, normalized,
    when the two are nearly equal (sin(theta) ~ 0).

    Args:
        q0: (4,) unit quaternion at fraction 0.
        q1: (4,) unit quaternion at fraction 1.
        fraction: where between them, usually in [0, 1].

    Returns:
        (4,) float64 unit quaternion.
    """
    q0 = np.asarray(q0, dtype=np.float64)
    q1 = np.asarray(q1, dtype=np.float64)
    dot = float(q0 @ q1)
    if dot < 0.0:
        q1, dot = -q1, -dot
    if dot > 0.9995:
        q = q0 + fraction * (q1 - q0)
        line: npt.NDArray[np.float64] = q / np.sqrt(q @ q)
        return line
    theta = np.arccos(min(1.0, dot))
    arc: npt.NDArray[np.float64] = (np.sin((1.0 - fraction) * theta) * q0
                                    + np.sin(fraction * theta) * q1) / np.sin(theta)
    return arc


# --------------------------------------------------------------------------- 6D representation


def _safe_normalize(vectors: npt.NDArray[Any], fallback: npt.NDArray[Any]) -> Tuple[npt.NDArray[Any],
                                                                                     npt.NDArray[np.bool_]]:
    """Normalize vectors, replacing those with a near-zero norm by `fallback`.

    Args:
        vectors: (..., 3) vectors.
        fallback: (..., 3) unit vectors used where `vectors` has a near-zero norm.

    Returns:
        (unit (..., 3), degenerate (...) bool) where `degenerate` marks the replaced rows.
    """
    norms = np.linalg.norm(vectors, axis=-1, keepdims=True)
    degenerate = norms[..., 0] < _DEGENERATE_NORM
    safe_norms = np.where(norms < _DEGENERATE_NORM, 1.0, norms)
    unit = np.where(degenerate[..., None], fallback, vectors / safe_norms)
    return unit, degenerate


def _least_aligned_axis(unit: npt.NDArray[Any]) -> npt.NDArray[Any]:
    """Pick, per vector, the coordinate axis least aligned with it.

    Args:
        unit: (..., 3) unit vectors.

    Returns:
        (..., 3) coordinate axes; never parallel to the matching input vector.
    """
    axis_index = np.argmin(np.abs(unit), axis=-1)
    axes: npt.NDArray[Any] = np.eye(3, dtype=unit.dtype)[axis_index]
    return axes


def rot6d_to_matrix(rot6d: npt.ArrayLike) -> npt.NDArray[np.floating[Any]]:
    """Convert the 6D rotation representation to rotation matrices (Gram-Schmidt).

    The 6 numbers are read as a 3x2 matrix; its columns are a1 = x[0::2] and a2 = x[1::2]
    (the SMPLer-X / Zhou et al. convention). b1 = a1/|a1|, b2 = normalize(a2 - (b1.a2) b1),
    b3 = b1 x b2; R has columns (b1, b2, b3).

    Degenerate input (zero a1, a2 parallel to a1, NaN/inf) never yields NaN: a zero a1 falls
    back to the x axis, and an a2 without a component orthogonal to b1 falls back to the
    coordinate axis least aligned with b1, so the result is always a proper rotation.

    Args:
        rot6d: (..., 6) 6D rotations.

    Returns:
        (..., 3, 3) rotation matrices, same floating dtype as the input (float64 for ints).

    Raises:
        ValueError: the last dimension is not 6.
    """
    values = np.asarray(rot6d)
    if values.shape[-1:] != (6,):
        raise ValueError("rot6d_to_matrix expects (..., 6), got shape %s" % (values.shape,))
    dtype = values.dtype if np.issubdtype(values.dtype, np.floating) else np.float64
    values = np.nan_to_num(values.astype(dtype, copy=False), nan=0.0, posinf=0.0, neginf=0.0)
    pairs = values.reshape(values.shape[:-1] + (3, 2))
    a1 = pairs[..., 0]
    a2 = pairs[..., 1]
    x_axis = np.broadcast_to(np.array([1.0, 0.0, 0.0], dtype=dtype), a1.shape)
    b1, _ = _safe_normalize(a1, x_axis)
    # b2 = normalize(a2 - (b1 . a2) b1)
    a2_orthogonal = a2 - np.sum(b1 * a2, axis=-1, keepdims=True) * b1
    fallback_axis = _least_aligned_axis(b1)
    fallback = fallback_axis - np.sum(b1 * fallback_axis, axis=-1, keepdims=True) * b1
    fallback = fallback / np.linalg.norm(fallback, axis=-1, keepdims=True)
    b2, _ = _safe_normalize(a2_orthogonal, fallback)
    b3 = np.cross(b1, b2)
    return np.stack([b1, b2, b3], axis=-1)


def matrix_to_rot6d(matrices: npt.ArrayLike) -> npt.NDArray[Any]:
    """Convert rotation matrices to the 6D representation (first two columns, interleaved).

    Args:
        matrices: (..., 3, 3) rotation matrices.

    Returns:
        (..., 6) with x[0::2] = first column and x[1::2] = second column.

    Raises:
        ValueError: the last two dimensions are not 3 x 3.
    """
    matrices = np.asarray(matrices)
    if matrices.shape[-2:] != (3, 3):
        raise ValueError("matrix_to_rot6d expects (..., 3, 3), got shape %s" % (matrices.shape,))
    return matrices[..., :, :2].reshape(matrices.shape[:-2] + (6,))


# --------------------------------------------------------------------------- axis-angle


def _skew(vectors: npt.NDArray[Any]) -> npt.NDArray[Any]:
    """Cross-product matrices [v]x.

    Args:
        vectors: (..., 3).

    Returns:
        (..., 3, 3) with [v]x w = v x w.
    """
    x, y, z = vectors[..., 0], vectors[..., 1], vectors[..., 2]
    zeros = np.zeros_like(x)
    return np.stack(
        [
            np.stack([zeros, -z, y], axis=-1),
            np.stack([z, zeros, -x], axis=-1),
            np.stack([-y, x, zeros], axis=-1),
        ],
        axis=-2,
    )


def axis_angle_to_matrix(axis_angle: npt.ArrayLike) -> npt.NDArray[np.floating[Any]]:
    """Rodrigues' formula R = I + A [r]x + B [r]x^2, A = sin(t)/t, B = (1 - cos t)/t^2.

    Near t = 0 A and B use their Taylor series, so tiny rotations stay exact and finite.

    Args:
        axis_angle: (..., 3) rotation vectors (axis * angle, radians).

    Returns:
        (..., 3, 3) rotation matrices, same floating dtype as the input (float64 for ints).

    Raises:
        ValueError: the last dimension is not 3.
    """
    vectors = np.asarray(axis_angle)
    if vectors.shape[-1:] != (3,):
        raise ValueError("axis_angle_to_matrix expects (..., 3), got shape %s" % (vectors.shape,))
    dtype = vectors.dtype if np.issubdtype(vectors.dtype, np.floating) else np.float64
    vectors = vectors.astype(np.float64, copy=False)
    theta_sq = np.sum(vectors * vectors, axis=-1)
    theta = np.sqrt(theta_sq)
    small = theta < 1e-4
    safe_theta = np.where(small, 1.0, theta)
    sin_over_theta = np.where(small, 1.0 - theta_sq / 6.0, np.sin(safe_theta) / safe_theta)
    one_minus_cos_over_theta_sq = np.where(
        small, 0.5 - theta_sq / 24.0, (1.0 - np.cos(safe_theta)) / (safe_theta * safe_theta)
    )
    skew = _skew(vectors)
    identity = np.broadcast_to(np.eye(3), skew.shape)
    matrices = (
        identity
        + sin_over_theta[..., None, None] * skew
        + one_minus_cos_over_theta_sq[..., None, None] * (skew @ skew)
    )
    rotations: npt.NDArray[np.floating[Any]] = matrices.astype(dtype, copy=False)
    return rotations


def matrix_to_axis_angle(matrices: npt.ArrayLike) -> npt.NDArray[np.floating[Any]]:
    """Convert rotation matrices to rotation vectors, stable near 0 and near pi.

    The angle is atan2(|v|, (tr R - 1)/2) with v = vee(R - R^T)/2 = sin(t) * axis. Away from
    pi the axis comes from v; near pi (cos t < 0) from the symmetric part
    (R + R^T)/2 - cos(t) I = (1 - cos t) axis axis^T, with its sign taken from v.

    Args:
        matrices: (..., 3, 3) rotation matrices.

    Returns:
        (..., 3) rotation vectors with angle in [0, pi], same floating dtype as the input (float64 for ints).

    Raises:
        ValueError: the last two dimensions are not 3 x 3.
    """
    matrices = np.asarray(matrices)
    if matrices.shape[-2:] != (3, 3):
        raise ValueError("matrix_to_axis_angle expects (..., 3, 3), got shape %s" % (matrices.shape,))
    dtype = matrices.dtype if np.issubdtype(matrices.dtype, np.floating) else np.float64
    rot = matrices.astype(np.float64, copy=False)
    sin_axis = 0.5 * np.stack(
        [rot[..., 2, 1] - rot[..., 1, 2], rot[..., 0, 2] - rot[..., 2, 0], rot[..., 1, 0] - rot[..., 0, 1]],
        axis=-1,
    )
    sin_theta = np.linalg.norm(sin_axis, axis=-1)
    cos_theta = np.clip((np.trace(rot, axis1=-2, axis2=-1) - 1.0) * 0.5, -1.0, 1.0)
    theta = np.arctan2(sin_theta, cos_theta)

    # Branch 1 (cos >= 0): r = v * t / sin t, with t / sin t -> 1 + t^2 / 6 near zero.
    small = sin_theta < 1e-6
    factor = np.where(small, 1.0 + theta * theta / 6.0, theta / np.where(small, 1.0, sin_theta))
    from_skew = sin_axis * factor[..., None]

    # Branch 2 (cos < 0): axis from the largest diagonal of the symmetric part.
    symmetric = 0.5 * (rot + np.swapaxes(rot, -1, -2)) - cos_theta[..., None, None] * np.eye(3)
    one_minus_cos = np.maximum(1.0 - cos_theta, 1e-12)
    outer = symmetric / one_minus_cos[..., None, None]
    diagonal = np.diagonal(outer, axis1=-2, axis2=-1)
    best = np.argmax(diagonal, axis=-1)
    row = np.take_along_axis(outer, best[..., None, None], axis=-2)[..., 0, :]
    row_scale = np.sqrt(np.maximum(np.take_along_axis(diagonal, best[..., None], axis=-1), 1e-12))
    axis = row / row_scale
    axis = axis / np.maximum(np.linalg.norm(axis, axis=-1, keepdims=True), 1e-12)
    sign = np.where(np.sum(axis * sin_axis, axis=-1) < 0.0, -1.0, 1.0)
    from_symmetric = axis * (sign * theta)[..., None]

    result = np.where((cos_theta < 0.0)[..., None], from_symmetric, from_skew)
    vectors: npt.NDArray[np.floating[Any]] = result.astype(dtype, copy=False)
    return vectors
