"""Rotation representations (leapnbv_common.rotations): quaternions, axis-angle and matrices agree (ROS-free)."""
from __future__ import annotations

import numpy as np
import pytest

from leapnbv_common.rotations import (
    axis_angle_to_matrix,
    matrix_to_axis_angle,
    quaternion_to_rotation,
    rotations_to_quaternions,
)


def test_rotations_to_quaternions_takes_every_branch_and_inverts_quaternion_to_rotation():
    rng = np.random.default_rng(7)
    quaternions = rng.normal(size=(400, 4))
    quaternions /= np.linalg.norm(quaternions, axis=1)[:, None]
    # 180-degree turns about x, y, z and the identity: the four formulas (largest of trace, m00, m11, m22)
    specials = [np.diag([1.0, -1.0, -1.0]), np.diag([-1.0, 1.0, -1.0]), np.diag([-1.0, -1.0, 1.0]), np.eye(3)]
    rotations = np.concatenate([[quaternion_to_rotation(q) for q in quaternions], specials])
    diagonal = np.stack([np.trace(rotations, axis1=1, axis2=2), *np.diagonal(rotations, axis1=1, axis2=2).T[:3]])
    assert set(np.argmax(diagonal, axis=0)) == {0, 1, 2, 3}  # every formula is exercised
    out = rotations_to_quaternions(rotations)
    assert out.shape == (404, 4) and out.dtype == np.float64 and np.all(out[:, 3] >= 0.0)
    np.testing.assert_allclose(np.linalg.norm(out, axis=1), 1.0, atol=1e-15)
    np.testing.assert_allclose(np.abs(np.sum(out[:400] * quaternions, axis=1)), 1.0, atol=1e-12)  # q or -q
    np.testing.assert_allclose([quaternion_to_rotation(q) for q in out], rotations, atol=1e-12)
    assert rotations_to_quaternions(np.zeros((0, 3, 3))).shape == (0, 4)


def test_a_quaternion_is_normalized_before_it_becomes_a_matrix():
    q = np.array([0.1, -0.4, 0.3, 0.8])
    np.testing.assert_allclose(quaternion_to_rotation(3.0 * q), quaternion_to_rotation(q / np.linalg.norm(q)),
                               atol=1e-15)
    rotation = quaternion_to_rotation(3.0 * q)
    np.testing.assert_allclose(rotation @ rotation.T, np.eye(3), atol=1e-15)
    assert np.linalg.det(rotation) > 0.0


def test_quaternion_and_axis_angle_describe_the_same_rotation():
    # q = (sin(t/2) axis, cos(t/2)) and r = t axis: the two representations of one module agree.
    rng = np.random.default_rng(3)
    axes = rng.normal(size=(200, 3))
    axes /= np.linalg.norm(axes, axis=1)[:, None]
    angles = rng.uniform(0.0, np.pi, size=200)
    vectors = axes * angles[:, None]
    quaternions = np.concatenate([axes * np.sin(angles / 2)[:, None], np.cos(angles / 2)[:, None]], axis=1)
    matrices = axis_angle_to_matrix(vectors)
    np.testing.assert_allclose([quaternion_to_rotation(q) for q in quaternions], matrices, atol=1e-12)
    np.testing.assert_allclose(rotations_to_quaternions(matrices), quaternions, atol=1e-12)  # w >= 0 for t <= pi
    np.testing.assert_allclose(matrix_to_axis_angle(quaternion_to_rotation(quaternions[0])), vectors[0], atol=1e-9)


def test_perception_keeps_its_import_path_to_the_one_definition():
    perception_rotations = pytest.importorskip("leapnbv_perception.rotations")
    import leapnbv_common.rotations as rotations

    for name in ("axis_angle_to_matrix", "matrix_to_axis_angle", "matrix_to_rot6d", "rot6d_to_matrix"):
        assert getattr(perception_rotations, name) is getattr(rotations, name)
