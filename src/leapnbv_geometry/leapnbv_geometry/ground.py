"""Ground plane by RANSAC with a tilt prior, refined by least squares (ALGORITHMS.md sec. 6)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional, Sequence

import numpy as np

from .target_geometry import backproject

__all__ = [
    "GroundPlaneError",
    "GroundPlaneResult",
    "fit_ground_plane",
    "ground_points_from_depth",
]

# Plane convention: n.x + d = 0 with |n| = 1 and n pointing up (n.up > 0; up is -y in the
# optical frame). Then n.x + d is the signed height of x above the plane and d is the height
# of the camera (the origin) above the ground: positive for a camera above the floor.


class GroundPlaneError(ValueError):
    """Invalid input to the ground-plane fit (names the argument and shape at fault)."""


@dataclass
class GroundPlaneResult:
    """Output of :func:`fit_ground_plane`.

    Attributes:
        valid: True when a plane within the tilt prior reached the minimum inliers and ratio.
        normal: (3,) unit normal pointing up (n.up > 0); zeros when no hypothesis survived.
        offset: d in n.x + d = 0, i.e. the camera height above the plane in metres.
        inlier_mask: (N,) bool, points within the inlier threshold of the refined plane.
        inlier_count: number of inliers.
        inlier_ratio: inlier_count / N (0 for no points).
        tilt_deg: angle between ``normal`` and ``up`` in degrees (NaN when no plane).
    """

    valid: bool
    normal: np.ndarray
    offset: float
    inlier_mask: np.ndarray
    inlier_count: int
    inlier_ratio: float
    tilt_deg: float


def _refine_plane(points: np.ndarray, up: np.ndarray):
    """Least-squares plane (unit normal oriented to ``up``, offset) through (K, 3) points.

    The normal is the direction of least variance: the eigenvector of the smallest eigenvalue
    of the 3x3 scatter matrix of the centred points (same as the last right-singular vector
    of the SVD, for a fraction of the cost).
    """
    centre = points.mean(axis=0)
    centred = points - centre
    scatter = centred.T @ centred
    _, vectors = np.linalg.eigh(scatter)
    normal = vectors[:, 0]
    if normal @ up < 0.0:
        normal = -normal
    return normal, float(-normal @ centre)


def fit_ground_plane(
    points: np.ndarray,
    max_tilt_deg: float = 30.0,
    inlier_threshold: float = 0.02,
    iterations: int = 128,
    min_inliers: int = 200,
    min_inlier_ratio: float = 0.1,
    seed: int = 0,
    up: Sequence[float] = (0.0, -1.0, 0.0),
    max_points: int = 2048,
    refine_iterations: int = 2,
) -> GroundPlaneResult:
    """Fit the ground plane n.x + d = 0 to background points.

    RANSAC, vectorized: ``iterations`` three-point hypotheses are drawn from a random
    subsample of at most ``max_points`` points and all are scored at once (one matrix
    product). Hypotheses whose normal is more than ``max_tilt_deg`` from ``up`` are rejected
    before scoring, so walls are never taken for the floor. The best hypothesis is refined by
    least squares on its inliers among all points (``refine_iterations`` rounds, inliers
    re-selected each round). Deterministic for a given ``seed``.

    Args:
        points: (N, 3) background points in the camera optical frame, metres.
        max_tilt_deg: largest allowed angle between the plane normal and ``up``.
        inlier_threshold: metres from the plane for a point to count as an inlier.
        iterations: number of RANSAC hypotheses.
        min_inliers: fewest inliers (over all points) of a valid plane.
        min_inlier_ratio: smallest inlier_count / N of a valid plane.
        seed: random seed.
        up: (3,) up direction in the camera frame (-y of the optical frame by default).
        max_points: size of the subsample used to score hypotheses.
        refine_iterations: least-squares rounds on the inliers.

    Returns:
        GroundPlaneResult (``valid`` False when no plane within the tilt prior reaches
        ``min_inliers`` and ``min_inlier_ratio``).

    Raises:
        GroundPlaneError: on points not (N, 3), a zero ``up`` or non-positive parameters.
    """
    points = np.asarray(points)
    if points.ndim != 2 or points.shape[1] != 3:
        raise GroundPlaneError(f"fit_ground_plane: points must be (N, 3), got {points.shape}")
    up_vec = np.asarray(up, dtype=np.float64).reshape(-1)
    if up_vec.shape != (3,) or not np.linalg.norm(up_vec) > 0.0:
        raise GroundPlaneError(f"fit_ground_plane: up must be a non-zero 3-vector, got {up!r}")
    if iterations < 1 or max_points < 3 or not inlier_threshold > 0.0:
        raise GroundPlaneError(
            "fit_ground_plane: iterations >= 1, max_points >= 3 and inlier_threshold > 0 required"
        )
    up_vec = up_vec / np.linalg.norm(up_vec)
    cos_max_tilt = float(np.cos(np.radians(max_tilt_deg)))
    # Non-finite points need no filtering: they give NaN hypotheses (rejected) and NaN
    # distances (never inliers).
    n_points = points.shape[0]
    invalid = GroundPlaneResult(
        valid=False,
        normal=np.zeros(3),
        offset=0.0,
        inlier_mask=np.zeros(n_points, dtype=bool),
        inlier_count=0,
        inlier_ratio=0.0,
        tilt_deg=float("nan"),
    )
    if n_points < 3:
        return invalid

    rng = np.random.default_rng(seed)
    # Sampling with replacement keeps this O(max_points); repeats are harmless.
    if n_points > max_points:
        sample = points[rng.integers(0, n_points, size=max_points)].astype(np.float64)
    else:
        sample = points.astype(np.float64)
    triplets = rng.integers(0, sample.shape[0], size=(int(iterations), 3))
    p0 = sample[triplets[:, 0]]
    normals = np.cross(sample[triplets[:, 1]] - p0, sample[triplets[:, 2]] - p0)
    lengths = np.linalg.norm(normals, axis=1)
    usable = lengths > 1e-12  # collinear or repeated points give no plane
    normals[usable] /= lengths[usable, None]
    normals[normals @ up_vec < 0.0] *= -1.0
    usable &= normals @ up_vec >= cos_max_tilt  # the tilt prior
    if not np.any(usable):
        return invalid
    normals = normals[usable]
    offsets = -np.einsum("ij,ij->i", normals, p0[usable])
    # All hypotheses scored at once: (S, 3) @ (3, H) distances.
    distances = np.abs(sample.astype(np.float32) @ normals.T.astype(np.float32)
                       + offsets.astype(np.float32))
    scores = np.count_nonzero(distances <= inlier_threshold, axis=0)
    best = int(np.argmax(scores))  # first best on ties: deterministic
    normal = normals[best]
    offset = float(offsets[best])

    points64 = points.astype(np.float64, copy=False)
    inliers = np.abs(points64 @ normal + offset) <= inlier_threshold
    for _ in range(int(refine_iterations)):
        if np.count_nonzero(inliers) < 3:
            break
        normal, offset = _refine_plane(points64[inliers], up_vec)
        inliers = np.abs(points64 @ normal + offset) <= inlier_threshold

    inlier_count = int(np.count_nonzero(inliers))
    cos_tilt = float(np.clip(normal @ up_vec, -1.0, 1.0))
    valid = (
        inlier_count >= min_inliers
        and inlier_count >= min_inlier_ratio * n_points
        and cos_tilt >= cos_max_tilt
    )
    return GroundPlaneResult(
        valid=bool(valid),
        normal=np.asarray(normal, dtype=np.float64),
        offset=float(offset),
        inlier_mask=inliers,
        inlier_count=inlier_count,
        inlier_ratio=inlier_count / n_points,
        tilt_deg=float(np.degrees(np.arccos(cos_tilt))),
    )


def ground_points_from_depth(
    depth: np.ndarray,
    K: np.ndarray,
    exclude_mask: Optional[np.ndarray] = None,
    stride: int = 4,
    min_depth: float = 0.1,
    max_depth: float = 10.0,
) -> np.ndarray:
    """Background points for the ground fit: valid depth pixels not in ``exclude_mask``.

    Args:
        depth: (H, W) float depth in metres (0 / NaN = no return).
        K: (3, 3) camera matrix.
        exclude_mask: optional (H, W) bool of pixels to leave out (the person mask).
        stride: keep every ``stride``-th row and column.
        min_depth: nearest valid depth, metres.
        max_depth: farthest valid depth, metres.

    Returns:
        (N, 3) float32 points in the camera optical frame.

    Raises:
        GroundPlaneError: if ``exclude_mask`` does not match the depth shape.
    """
    depth = np.asarray(depth)
    sub = depth[::stride, ::stride]
    keep = (sub >= min_depth) & (sub <= max_depth)
    if exclude_mask is not None:
        exclude_mask = np.asarray(exclude_mask, dtype=bool)
        if exclude_mask.shape != depth.shape:
            raise GroundPlaneError(
                f"ground_points_from_depth: exclude_mask shape {exclude_mask.shape} "
                f"differs from depth shape {depth.shape}"
            )
        keep &= ~exclude_mask[::stride, ::stride]
    full_keep = np.zeros(depth.shape, dtype=bool)
    full_keep[::stride, ::stride] = keep
    return backproject(depth, K, mask=full_keep, stride=stride)
