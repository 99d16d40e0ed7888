"""Tests of leapnbv_evaluation.metrics and leapnbv_common.procrustes.

PA-MPVPE, coverage, area, latency percentiles, the success rule.
"""

from __future__ import annotations

import numpy as np
import pytest

from leapnbv_common.procrustes import pa_mpvpe_mm, procrustes_align
from leapnbv_evaluation.metrics import (
    body_coverage,
    is_success,
    latency_summary,
    reconstructed_area,
)
from leapnbv_perception.rotations import axis_angle_to_matrix
from leapnbv_sim.visibility import visible_vertex_mask

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


@pytest.mark.parametrize(
    "before, after, expected",
    [
        (0.50, 0.59, False),
        (0.50, 0.60, True),
        (0.85, 0.90, True),
        (0.85, 0.89, False),
        (0.95, 0.92, True),
        (0.30, 0.25, False),
        (0.70, 0.80, True),
    ],
)
def test_is_success_rule(before, after, expected):
    assert is_success(before, after) is expected
