"""Tests for 6D / matrix / axis-angle conversions."""

from __future__ import annotations

import numpy as np
import pytest

from leapnbv_perception.rotations import (
    axis_angle_to_matrix,
    matrix_to_axis_angle,
    matrix_to_rot6d,
    rot6d_to_matrix,
)


def random_rotations(count: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    quaternions = rng.normal(size=(count, 4))
    quaternions /= np.linalg.norm(quaternions, axis=1, keepdims=True)
    w, x, y, z = quaternions.T
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], axis=-1),
            np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], axis=-1),
            np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], axis=-1),
        ],
        axis=-2,
    )


def assert_rotation(matrices: np.ndarray) -> None:
    assert np.all(np.isfinite(matrices))
    identity = np.broadcast_to(np.eye(3), matrices.shape)
    np.testing.assert_allclose(matrices @ np.swapaxes(matrices, -1, -2), identity, atol=1e-9)
    np.testing.assert_allclose(np.linalg.det(matrices), 1.0, atol=1e-9)


def test_rot6d_round_trip() -> None:
    rotations = random_rotations(500)
    np.testing.assert_allclose(rot6d_to_matrix(matrix_to_rot6d(rotations)), rotations, atol=1e-6)


def test_rot6d_layout_is_interleaved_columns() -> None:
    # x.reshape(3, 2): a1 = x[0::2] is the first column, a2 = x[1::2] the second.
    x = np.array([0.0, 1.0, 1.0, 0.0, 0.0, 0.0])
    expected = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
    np.testing.assert_allclose(rot6d_to_matrix(x), expected, atol=1e-12)
    np.testing.assert_allclose(matrix_to_rot6d(expected), x, atol=1e-12)


def test_rot6d_gram_schmidt_of_unnormalized_input() -> None:
    x = np.array([2.0, 3.0, 0.0, 1.0, 0.0, 0.0])  # a1 = (2, 0, 0), a2 = (3, 1, 0)
    np.testing.assert_allclose(rot6d_to_matrix(x), np.eye(3), atol=1e-12)


@pytest.mark.parametrize(
    "degenerate",
    [
        np.zeros(6),
        np.array([1.0, 2.0, 0.0, 0.0, 0.0, 0.0]),  # parallel columns
        np.array([0.0, 0.0, 1.0, -3.0, 0.0, 0.0]),  # anti-parallel columns
        np.array([0.0, 1.0, 0.0, 0.0, 0.0, 0.0]),  # zero first column
        np.array([1e-12, 0.0, 0.0, 0.0, 0.0, 0.0]),
        np.array([np.nan, 1.0, np.inf, 0.0, 0.0, 1.0]),
    ],
)
def test_rot6d_degenerate_gives_rotation(degenerate: np.ndarray) -> None:
    assert_rotation(rot6d_to_matrix(degenerate))


def test_rot6d_batched_shapes() -> None:
    x = np.random.default_rng(1).normal(size=(4, 21, 6))
    result = rot6d_to_matrix(x)
    assert result.shape == (4, 21, 3, 3)
    assert_rotation(result)


def test_axis_angle_round_trip_random() -> None:
    rotations = random_rotations(500, seed=2)
    np.testing.assert_allclose(axis_angle_to_matrix(matrix_to_axis_angle(rotations)), rotations, atol=1e-9)


@pytest.mark.parametrize("angle", [0.0, 1e-10, 1e-6, 1e-3, 0.5, np.pi / 2, np.pi - 1e-3, np.pi - 1e-7, np.pi])
def test_axis_angle_round_trip_special_angles(angle: float) -> None:
    axes = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [1.0, -2.0, 0.5], [-0.3, 0.2, -0.9]])
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    vectors = axes * angle
    matrices = axis_angle_to_matrix(vectors)
    assert_rotation(matrices)
    recovered = matrix_to_axis_angle(matrices)
    # Same rotation either way; at exactly pi the sign of the axis is ambiguous.
    np.testing.assert_allclose(axis_angle_to_matrix(recovered), matrices, atol=1e-9)
    if angle < np.pi - 1e-3:
        np.testing.assert_allclose(recovered, vectors, atol=1e-9)
    np.testing.assert_allclose(np.linalg.norm(recovered, axis=1), angle, atol=1e-6)


def test_axis_angle_known_matrix() -> None:
    matrix = axis_angle_to_matrix(np.array([0.0, 0.0, np.pi / 2]))
    np.testing.assert_allclose(matrix @ np.array([1.0, 0.0, 0.0]), [0.0, 1.0, 0.0], atol=1e-12)
