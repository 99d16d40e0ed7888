"""Tests of leapnbv_sim.depth_noise: the structured-light depth noise of the rendered frames."""

from __future__ import annotations

import numpy as np
import pytest

from leapnbv_sim.depth_noise import DepthNoiseConfig, apply_depth_noise, depth_edge_mask, depth_m_to_mm


def test_depth_noise_is_seeded_and_depth_dependent() -> None:
    depth = np.zeros((60, 80), dtype=np.float32)
    depth[:, :40] = 1.0
    depth[:, 40:] = 4.0
    config = DepthNoiseConfig(random_dropout_probability=0.0, edge_dropout_probability=0.0)
    a = apply_depth_noise(depth, 7, config)
    assert np.array_equal(a, apply_depth_noise(depth, 7, config))
    assert not np.array_equal(a, apply_depth_noise(depth, 8, config))
    near = a[:, :38] - 1.0
    far = a[:, 42:] - 4.0
    # sigma(z) = 0.0026 z^2 + 0.0005: ~3.1 mm at 1 m, ~42 mm at 4 m.
    assert np.std(near) == pytest.approx(0.0031, rel=0.15)
    assert np.std(far) == pytest.approx(0.0421, rel=0.15)


def test_depth_noise_drops_edges() -> None:
    depth = np.full((20, 20), 2.0, dtype=np.float32)
    depth[:, 10:] = 3.0
    edges = depth_edge_mask(depth, 0.1)
    assert edges[:, 9].all() and edges[:, 10].all() and not edges[:, :9].any()
    config = DepthNoiseConfig(edge_dropout_probability=1.0, random_dropout_probability=0.0)
    noisy = apply_depth_noise(depth, 0, config)
    assert (noisy[:, 9:11] == 0).all()
    assert (noisy[:, :9] > 0).all()


def test_depth_m_to_mm_rounds_and_keeps_zero() -> None:
    out = depth_m_to_mm(np.array([[0.0, 1.2344, 1.2346, 70.0]]))
    assert out.dtype == np.uint16
    assert out.tolist() == [[0, 1234, 1235, 65535]]
