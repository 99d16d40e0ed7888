"""Evaluation metrics: body coverage, reconstructed area, the success rule and latency percentiles.

PA-MPVPE is in leapnbv_common.procrustes (the perception stand-ins use it too).
"""

from __future__ import annotations

from typing import Dict, Sequence

import numpy as np

from leapnbv_common.array_types import BoolArray, FloatArray, FloatingArray, IntArray
from leapnbv_sim.visibility import self_visible_vertex_mask, visible_vertex_mask

# Success rule of the task table: coverage rises by at least this many points (fraction) ...
SUCCESS_MIN_GAIN = 0.10
# ... or reaches at least this coverage after the move.
SUCCESS_MIN_COVERAGE = 0.90
# Coverages are fractions computed in floating point: 0.60 - 0.50 is 0.0999...98, which must count.
_SUCCESS_TOLERANCE = 1e-9


def is_success(coverage_before: float, coverage_after: float) -> bool:
    """The task's success rule: coverage rises by >= 10 points or reaches >= 90 % after one move.

    Computed once per method and scene, when the episode is scored; reports read the flag.

    Args:
        coverage_before: Body coverage before the move, fraction 0-1.
        coverage_after: Body coverage after the move, fraction 0-1.

    Returns:
        True for a success.
    """
    before, after = float(coverage_before), float(coverage_after)
    rises_enough = after - before >= SUCCESS_MIN_GAIN - _SUCCESS_TOLERANCE
    return rises_enough or after >= SUCCESS_MIN_COVERAGE - _SUCCESS_TOLERANCE


def body_coverage(
    gt_vertices_cam: FloatArray,
    scene_depth_m: FloatingArray,
    K: FloatArray,
    tolerance: float = 0.02,
) -> float:
    """Share of ground-truth body vertices visible in the view (docs/ALGORITHMS.md §8).

    Use the rendered scene depth WITHOUT noise; see :func:`visible_vertex_mask`.

    Args:
        gt_vertices_cam: (V,3) ground-truth body vertices in the camera optical frame, metres.
        scene_depth_m: (H,W) noise-free scene depth, metres, 0 = no return.
        K: (3,3) intrinsics.
        tolerance: Metres a vertex may lie behind the scene surface (default 2 cm).

    Returns:
        Fraction in [0, 1] (0 for an empty vertex set).
    """
    visible = visible_vertex_mask(gt_vertices_cam, scene_depth_m, K, tolerance)
    if visible.size == 0:
        return 0.0
    return float(np.count_nonzero(visible)) / float(visible.size)


def reconstructed_area(mask: BoolArray, depth: FloatArray) -> int:
    """Pixels of the person mask with valid depth (docs/ALGORITHMS.md §8).

    Args:
        mask: (H,W) bool person mask.
        depth: (H,W) depth, metres (float) or millimetres (uint16); valid = finite and > 0.

    Returns:
        The pixel count.

    Raises:
        ValueError: The shapes differ.
    """
    mask = np.asarray(mask, dtype=bool)
    depth = np.asarray(depth)
    if mask.shape != depth.shape:
        raise ValueError(f"mask {mask.shape} and depth {depth.shape} differ in shape")
    if np.issubdtype(depth.dtype, np.floating):
        valid = np.isfinite(depth) & (depth > 0)
    else:
        valid = depth > 0
    return int(np.count_nonzero(mask & valid))


def latency_summary(samples_ms: Sequence[float]) -> Dict[str, float]:
    """Percentiles of latency samples (linear interpolation, numpy's default).

    Args:
        samples_ms: Latencies in milliseconds.

    Returns:
        ``{"n", "mean", "p50", "p95", "p99", "max"}``; all NaN except n = 0 when empty.
    """
    samples = np.asarray(list(samples_ms), dtype=np.float64)
    if samples.size == 0:
        nan = float("nan")
        return {"n": 0, "mean": nan, "p50": nan, "p95": nan, "p99": nan, "max": nan}
    p50, p95, p99 = np.percentile(samples, [50, 95, 99])
    return {
        "n": int(samples.size),
        "mean": float(samples.mean()),
        "p50": float(p50),
        "p95": float(p95),
        "p99": float(p99),
        "max": float(samples.max()),
    }


def surface_coverage(
    gt_vertices_cam: FloatArray,
    body_faces: IntArray,
    scene_depth_m: FloatingArray,
    K: FloatArray,
    tolerance: float = 0.02,
) -> float:
    """Share of the body surface this viewpoint could show that it does show (in [0, 1]).

    :func:`body_coverage` divides by all vertices; its ceiling is about 50-55 % because the
    back of a body is always hidden by its front. Here the denominator is the set of vertices
    the body shows by itself from the camera's position (in front, not self-occluded, image
    bounds ignored: :func:`self_visible_vertex_mask`), and the numerator those of them that
    the real view sees (inside the image, in front, not behind the scene depth by more than
    ``tolerance``: :func:`visible_vertex_mask`). An unoccluded, fully framed body scores ~1;
    occluders and the image border lower it.

    Args:
        gt_vertices_cam: (V,3) ground-truth body vertices in the camera optical frame, metres.
        body_faces: (F,3) the body model's triangles.
        scene_depth_m: (H,W) noise-free depth of the whole scene from this camera, metres.
        K: (3,3) intrinsics.
        tolerance: Metres a vertex may lie behind a surface and still count (default 2 cm).

    Returns:
        Fraction in [0, 1]; 0 when the body shows no vertex from here (e.g. behind the camera).
    """
    self_visible = self_visible_vertex_mask(gt_vertices_cam, body_faces, K, tolerance)
    count = int(np.count_nonzero(self_visible))
    if count == 0:
        return 0.0
    seen = visible_vertex_mask(gt_vertices_cam, scene_depth_m, K, tolerance) & self_visible
    return float(np.count_nonzero(seen)) / float(count)
