"""Tests of leapnbv_evaluation.metrics and leapnbv_sim.depth_noise."""

from __future__ import annotations

import numpy as np
import pytest

from leapnbv_evaluation.metrics import (
    body_coverage,
    latency_summary,
    pa_mpvpe_mm,
    procrustes_align,
    reconstructed_area,
    visible_vertex_mask,
)
from leapnbv_perception.rotations import axis_angle_to_matrix
from leapnbv_sim.depth_noise import DepthNoiseConfig, apply_depth_noise, depth_edge_mask, depth_m_to_mm

K = np.array([[100.0, 0.0, 50.0], [0.0, 100.0, 40.0], [0.0, 0.0, 1.0]])


def test_pa_mpvpe_is_zero_for_similarity_copy() -> None:
    rng = np.random.default_rng(1)
    gt = rng.normal(size=(200, 3))
    R = axis_angle_to_matrix(np.array([0.3, -1.2, 2.0]))
    pred = 0.7 * gt @ R.T + np.array([1.0, -2.0, 0.5])
    assert pa_mpvpe_mm(pred, gt) == pytest.approx(0.0, abs=1e-9)


def test_pa_mpvpe_known_value_for_perturbed_vertex() -> None:
    # A symmetric set with one vertex pushed along an axis through the centroid cannot be
    # improved by rotation; Procrustes then only recentres and rescales.
    gt = np.array([[1.0, 0, 0], [-1.0, 0, 0], [0, 1.0, 0], [0, -1.0, 0], [0, 0, 1.0], [0, 0, -1.0]])
    pred = gt.copy()
    pred[0, 0] += 0.006  # metres
    # Closed form: centre shifts by 0.001 along x; best scale s = sum(x.y)/sum(x.x).
    Xc = pred - pred.mean(axis=0)
    s = float(np.sum(Xc * gt)) / float(np.sum(Xc * Xc))
    expected = np.mean(np.linalg.norm(s * Xc - gt, axis=1)) * 1000.0
    assert pa_mpvpe_mm(pred, gt) == pytest.approx(expected, rel=1e-9)
    assert 0.5 < expected < 2.0  # not trivially 0 nor the unaligned 1 mm mean


def test_procrustes_never_reflects() -> None:
    rng = np.random.default_rng(2)
    gt = rng.normal(size=(100, 3))
    mirrored = gt * np.array([-1.0, 1.0, 1.0])
    aligned = procrustes_align(mirrored, gt)
    # The best proper rotation of a mirror image cannot match exactly.
    assert np.mean(np.linalg.norm(aligned - gt, axis=1)) > 0.1
    # The aligned set keeps the handedness of the prediction.
    a = aligned - aligned.mean(axis=0)
    m = mirrored - mirrored.mean(axis=0)
    assert np.sign(np.linalg.det(a[:3])) == np.sign(np.linalg.det(m[:3]))


def test_body_coverage_counts_inside_front_and_unoccluded() -> None:
    depth = np.full((80, 100), 5.0, dtype=np.float32)
    depth[:, :50] = 2.0  # an occluder covers the left half
    vertices = np.array(
        [
            [0.5, 0.0, 3.0],  # right half, in front of the 5 m wall: visible
            [-0.5, 0.0, 3.0],  # left half, behind the 2 m occluder: hidden
            [-0.5, 0.0, 2.015],  # behind it by 1.5 cm: within tolerance, visible
            [0.0, 0.0, -1.0],  # behind the camera
            [10.0, 0.0, 1.0],  # outside the image
        ]
    )
    mask = visible_vertex_mask(vertices, depth, K)
    assert mask.tolist() == [True, False, True, False, False]
    assert body_coverage(vertices, depth, K) == pytest.approx(2 / 5)


def test_reconstructed_area_needs_mask_and_valid_depth() -> None:
    mask = np.zeros((4, 5), dtype=bool)
    mask[1:3, 1:4] = True
    depth = np.ones((4, 5), dtype=np.float32)
    depth[1, 1] = 0.0
    depth[2, 3] = np.nan
    assert reconstructed_area(mask, depth) == 4
    assert reconstructed_area(mask, np.full((4, 5), 1500, dtype=np.uint16)) == 6


def test_latency_summary_percentiles() -> None:
    summary = latency_summary(list(range(1, 101)))
    assert summary["n"] == 100
    assert summary["p50"] == pytest.approx(50.5)
    assert summary["p99"] == pytest.approx(99.01)
    assert summary["mean"] == pytest.approx(50.5)
    assert latency_summary([])["n"] == 0


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
