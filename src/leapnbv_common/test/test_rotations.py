"""Rotation representations (leapnbv_common.rotations): quaternions, axis-angle and matrices agree (ROS-free)."""
from __future__ import annotations

import numpy as np
import pytest

from leapnbv_common.rotations import (
    axis_angle_to_matrix,
    matrix_to_axis_angle,
    quaternion_multiply,
    quaternion_rotate,
    quaternion_to_rotation,
    rotations_to_quaternions,
    slerp,
)


def _unit_quaternions(count: int, seed: int) -> np.ndarray:
    q = np.random.default_rng(seed).normal(size=(count, 4))
    return q / np.linalg.norm(q, axis=1)[:, None]


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


def test_the_quaternion_product_and_rotation_are_the_matrix_product_and_rotation():
    qa, qb = _unit_quaternions(50, 1), _unit_quaternions(50, 2)
    vectors = np.random.default_rng(3).normal(size=(50, 3))
    for a, b, v in zip(qa, qb, vectors):
        ab = quaternion_multiply(a, b)  # b first, then a
        np.testing.assert_allclose(quaternion_to_rotation(ab), quaternion_to_rotation(a) @ quaternion_to_rotation(b),
                                   atol=1e-14)
        np.testing.assert_allclose(quaternion_rotate(a, v), quaternion_to_rotation(a) @ v, atol=1e-14)
    identity = np.array([0.0, 0.0, 0.0, 1.0])
    np.testing.assert_array_equal(quaternion_multiply(identity, qa[0]), qa[0])


def test_slerp_follows_the_shorter_arc_at_constant_speed():
    axis = np.array([0.0, 0.6, 0.8])
    for angle in (0.5, 2.0, 3.0):  # the second and third: past 90 degrees, still the arc (not the line)
        q0 = np.array([0.0, 0.0, 0.0, 1.0])
        q1 = np.concatenate([axis * np.sin(angle / 2), [np.cos(angle / 2)]])
        for fraction in (0.0, 0.25, 0.5, 1.0):
            q = slerp(q0, q1, fraction)
            np.testing.assert_allclose(np.linalg.norm(q), 1.0, atol=1e-15)
            np.testing.assert_allclose(quaternion_to_rotation(q), axis_angle_to_matrix(axis * angle * fraction),
                                       atol=1e-12)
        # -q1 is the same rotation: slerp takes the same (shorter) way to it
        np.testing.assert_allclose(slerp(q0, -q1, 0.5), slerp(q0, q1, 0.5), atol=1e-15)
    # nearly equal quaternions: the normalized straight line, no division by sin(theta) ~ 0
    q0, q1 = np.array([0.0, 0.0, 0.0, 1.0]), np.array([1e-9, 0.0, 0.0, 1.0]) / np.hypot(1e-9, 1.0)
    q = slerp(q0, q1, 0.5)
    assert np.all(np.isfinite(q)) and abs(np.linalg.norm(q) - 1.0) < 1e-15
