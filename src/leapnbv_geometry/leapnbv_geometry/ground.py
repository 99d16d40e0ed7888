"""Ground plane by RANSAC with a tilt prior, refined by least squares (docs/ALGORITHMS.md §5).

Also the floor given by the camera's pose in a floor-aligned frame, for views where RANSAC
finds none (:func:`floor_plane_from_camera_pose`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import List, Optional, Sequence, Tuple, Union

import numpy as np

from leapnbv_common.array_types import BoolArray, Float32Array, FloatArray, FloatingArray, IntArray

from .target_geometry import backproject

__all__ = [
    "FloorEstimate",
    "GroundPlaneError",
    "GroundPlaneResult",
    "box_exclusion_mask",
    "expected_up",
    "fit_ground_plane",
    "floor_plane_from_camera_pose",
    "fuse_floor",
    "ground_points_from_depth",
    "mounting_priors",
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
    normal: FloatArray
    offset: float
    inlier_mask: BoolArray
    inlier_count: int
    inlier_ratio: float
    tilt_deg: float


def _refine_plane(points: FloatArray, up: FloatArray) -> Tuple[FloatArray, float]:
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


MAX_NOISE_THRESHOLD_M = 0.08
DISTINCT_COS = float(np.cos(np.radians(5.0)))  # hypotheses closer than this are the same plane
LOCAL_RADIUS_M = 1.0  # NAPSAC neighbourhood
LOCAL_POOL = 384  # companions are drawn from this many sample points (bounds the distance matrix)
LOCAL_MIN_GAP_M = 0.15  # closer companions make the normal noise-dominated
PARALLEL_COS = float(np.cos(np.radians(2.0)))  # a box top is level with the floor, a slice through it is not
LEVEL_SEPARATION_M = 0.15  # a surface this far below the best-supported one is another level
LOW_PLANE_SCORE_SHARE = 0.3  # low hypotheses with at least this share of the best score are refined too


def fit_ground_plane(
    points: FloatingArray,
    max_tilt_deg: float = 30.0,
    inlier_threshold: float = 0.02,
    iterations: int = 128,
    min_inliers: int = 200,
    min_inlier_ratio: float = 0.1,
    seed: int = 0,
    up: Union[Sequence[float], FloatingArray] = (0.0, -1.0, 0.0),
    max_points: int = 2048,
    refine_iterations: int = 2,
    depth_noise_coeff: float = 0.0,
    local_sampling: bool = True,
    local_refinements: int = 6,
    lowest_plane_share: float = 0.5,
    camera_height_range: Sequence[float] = (0.0, float("inf")),
) -> GroundPlaneResult:
    """Fit the ground plane n.x + d = 0 to background points.

    RANSAC, vectorized: ``iterations`` three-point hypotheses are drawn from a random
    subsample of at most ``max_points`` points and all are scored at once (one matrix
    product). Hypotheses whose normal is more than ``max_tilt_deg`` from ``up`` are rejected
    before scoring, so walls are never taken for the floor. The best hypothesis is refined by
    least squares on its inliers among all points (``refine_iterations`` rounds, inliers
    re-selected each round). Deterministic for a given ``seed``.

    Hypothesis sampling: when the floor is a small share f of the view (a far floor behind
    walls and occluders), uniform triplets are all-floor with probability f^3 only. With
    ``local_sampling`` half of the triplets are drawn NAPSAC-style: a uniform first point and
    two companions among the subsample points 0.15 to 1 m from it, which lie on the same
    surface far more often. The other half stays uniform.

    Depth cameras' noise grows with z^2, so a point is an inlier within
    ``inlier_threshold + depth_noise_coeff * z^2`` of the plane (0 keeps a fixed threshold).

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
        depth_noise_coeff: metres per metre^2 added to the threshold at depth z (RealSense ~0.003).
        local_sampling: draw half of the hypotheses from neighbouring points (NAPSAC).
        local_refinements: how many of the best-scoring hypotheses are refined before choosing.
        camera_height_range: (min, max) height of the camera above the floor, i.e. of d; planes
            outside it are refused like tilted ones. A robot knows its camera's mounting height:
            this prior keeps box and table tops (and the ceiling) out.
        lowest_plane_share: among refined planes with at least this share of the best one's
            inliers, the lowest (largest offset) wins; 1.0 keeps the most-supported plane.

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
    points64 = points.astype(np.float64, copy=False)
    # Capped, so that a far wall does not become a thick slab that any level plane cuts through.
    thresholds = np.minimum(inlier_threshold + depth_noise_coeff * np.square(points64[:, 2]),
                            max(inlier_threshold, MAX_NOISE_THRESHOLD_M))
    # Sampling with replacement keeps this O(max_points); repeats are harmless.
    if n_points > max_points:
        chosen = rng.integers(0, n_points, size=max_points)
        sample, sample_thresholds = points64[chosen], thresholds[chosen]
    else:
        sample, sample_thresholds = points64, thresholds
    hypotheses = np.empty((int(iterations), 3, 3))
    uniform = rng.integers(0, sample.shape[0], size=(int(iterations), 3))
    hypotheses[:] = sample[uniform]
    if local_sampling and sample.shape[0] > 3:
        # NAPSAC: companions drawn among the sample points within LOCAL_RADIUS_M of a uniform
        # first point lie on the same surface far more often than uniform draws do.
        half = int(iterations) // 2
        first = rng.integers(0, sample.shape[0], size=half)
        pool = sample[rng.integers(0, sample.shape[0], size=min(LOCAL_POOL, sample.shape[0]))]
        gaps = np.sqrt(np.square(sample[first][:, None, :] - pool[None, :, :]).sum(axis=2))
        keys = rng.random(gaps.shape)
        keys[(gaps < LOCAL_MIN_GAP_M) | (gaps > LOCAL_RADIUS_M)] = -1.0
        companions = np.argpartition(-keys, 1, axis=1)[:, :2]
        has_two = np.take_along_axis(keys, companions, axis=1).min(axis=1) >= 0.0
        local = hypotheses[:half]
        local[has_two, 0] = sample[first[has_two]]
        local[has_two, 1] = pool[companions[has_two, 0]]
        local[has_two, 2] = pool[companions[has_two, 1]]
    p0 = hypotheses[:, 0]
    normals = np.cross(hypotheses[:, 1] - p0, hypotheses[:, 2] - p0)
    lengths = np.linalg.norm(normals, axis=1)
    usable = lengths > 1e-12  # collinear or repeated points give no plane
    normals[usable] /= lengths[usable, None]
    normals[normals @ up_vec < 0.0] *= -1.0
    usable &= normals @ up_vec >= cos_max_tilt  # the tilt prior
    if not np.any(usable):
        return invalid
    offsets = -np.einsum("ij,ij->i", normals, p0)
    min_height, max_height = (float(v) for v in camera_height_range)
    usable &= (offsets >= min_height) & (offsets <= max_height)  # the height prior
    if not np.any(usable):
        return invalid
    normals = normals[usable]
    offsets = offsets[usable]
    # All hypotheses scored at once: (S, 3) @ (3, H) distances.
    distances = np.abs(sample.astype(np.float32) @ normals.T.astype(np.float32)
                       + offsets.astype(np.float32))
    scores = np.count_nonzero(distances <= sample_thresholds[:, None].astype(np.float32), axis=0)
    # LO-RANSAC: a hypothesis from three noisy points scores poorly even when it lies on the
    # floor, so the few best are each refined by least squares before the winner is chosen.
    # The best few DISTINCT hypotheses (a plane is found many times over; refining copies
    # of the winner would crowd out the runner-up, e.g. the floor behind a larger box top),
    # and the lowest few among those with a fair share of the best score (the floor is the
    # lowest surface, however little of it is in view).
    def distinct(candidates: IntArray, chosen: List[int], limit: int) -> None:
        for h in candidates:
            if len(chosen) >= limit:
                return
            if all(abs(offsets[h] - offsets[k]) > 2 * inlier_threshold or normals[h] @ normals[k] < DISTINCT_COS
                   for k in chosen):
                chosen.append(int(h))

    order: List[int] = []
    limit = max(1, int(local_refinements))
    distinct(np.argsort(-scores, kind="stable"), order, limit)
    fair = np.nonzero(scores >= LOW_PLANE_SCORE_SHARE * scores.max())[0]
    distinct(fair[np.argsort(-offsets[fair], kind="stable")], order, 2 * limit)
    order = order or [int(np.argmax(scores))]
    refined = []
    for h in order:
        candidate_normal, candidate_offset = normals[h], float(offsets[h])
        candidate_inliers = np.abs(points64 @ candidate_normal + candidate_offset) <= thresholds
        for _ in range(int(refine_iterations)):
            if np.count_nonzero(candidate_inliers) < 3:
                break
            candidate_normal, candidate_offset = _refine_plane(points64[candidate_inliers], up_vec)
            candidate_inliers = np.abs(points64 @ candidate_normal + candidate_offset) <= thresholds
        count = int(np.count_nonzero(candidate_inliers))
        refined.append((count, candidate_normal, candidate_offset, candidate_inliers))
    # The floor is the lowest level surface: a box or table top may hold as many points, but
    # never lies below it. A well-supported plane PARALLEL to the best-supported one and clearly
    # below it (not the same noisy surface fitted twice) is the floor; else the best one is.
    best = max(refined, key=lambda r: r[0])
    lower = [r for r in refined
             if r[0] >= lowest_plane_share * best[0] and r[1] @ best[1] >= PARALLEL_COS
             and r[2] > best[2] + LEVEL_SEPARATION_M]
    _, normal, offset, inliers = max(lower, key=lambda r: r[2]) if lower else best

    inlier_count = int(np.count_nonzero(inliers))
    cos_tilt = float(np.clip(normal @ up_vec, -1.0, 1.0))
    valid = (
        min_height <= offset <= max_height
        and inlier_count >= min_inliers
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


ROTATION_TOLERANCE = 1e-3  # largest |R^T R - I| entry of an accepted rotation matrix


def floor_plane_from_camera_pose(rotation: FloatArray, position: FloatArray) -> Tuple[FloatArray, float]:
    """The floor z = 0 of a floor-aligned fixed frame, in the camera optical frame.

    The pose T_fixed_camera maps a camera point x to R x + p in the fixed frame (z up, floor at
    z = 0; e.g. ``map`` from the robot's localization). x is on the floor when the z of its
    image is 0::

        e_z . (R x + p) = 0   <=>   (R^T e_z) . x + p_z = 0   <=>   n . x + d = 0,
        n = R^T e_z  (the fixed frame's up in camera coordinates, a unit vector),  d = p_z

    which is the GroundPlane convention: n points up (toward the camera side) and d is the
    camera's height above the floor, positive for a camera above it. For an R that is a rotation
    only to within the tolerance, n is normalized and d divided by the same norm, so the plane
    is exactly {x : e_z . (R x + p) = 0}.

    Args:
        rotation: (3, 3) R of T_fixed_camera; its columns are the optical axes (x right, y down,
            z forward) in the fixed frame. Orthonormal within 1e-3 with det +1.
        position: (3,) p, the optical centre in the fixed frame, metres.

    Returns:
        (normal (3,), offset): unit n and d of n.x + d = 0 in the camera optical frame.

    Raises:
        GroundPlaneError: on wrong shapes, non-finite values, an R that is not a rotation, or a
            camera not above the floor (p_z <= 0).
    """
    rotation = np.asarray(rotation, dtype=np.float64)
    position = np.asarray(position, dtype=np.float64)
    if rotation.shape != (3, 3) or position.shape != (3,):
        raise GroundPlaneError(f"floor_plane_from_camera_pose: rotation must be (3, 3) and position (3,), "
                               f"got {rotation.shape} and {position.shape}")
    if not (np.all(np.isfinite(rotation)) and np.all(np.isfinite(position))):
        raise GroundPlaneError("floor_plane_from_camera_pose: the camera pose is not finite")
    error = float(np.max(np.abs(rotation.T @ rotation - np.eye(3))))
    if error > ROTATION_TOLERANCE or np.linalg.det(rotation) <= 0.0:
        raise GroundPlaneError(f"floor_plane_from_camera_pose: rotation is not a rotation matrix "
                               f"(max |R^T R - I| = {error:.2e}, det = {np.linalg.det(rotation):.4f})")
    if not position[2] > 0.0:
        raise GroundPlaneError(f"floor_plane_from_camera_pose: the camera is not above the floor "
                               f"(height p_z = {position[2]:.4f} m)")
    normal = rotation[2, :].copy()  # R^T e_z: the third row of R
    scale = float(np.linalg.norm(normal))
    return normal / scale, float(position[2]) / scale


def ground_points_from_depth(
    depth: FloatingArray,
    K: FloatArray,
    exclude_mask: Optional[BoolArray] = None,
    stride: int = 4,
    min_depth: float = 0.1,
    max_depth: float = 10.0,
) -> Float32Array:
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


# --------------------------------------------------------------------------- priors and fusion


def expected_up(pitch_deg: float) -> FloatArray:
    """The floor's up in the optical frame of a camera pitched down by ``pitch_deg`` (no roll).

    A camera whose optical axis points ``pitch_deg`` below the horizon sees the world's up as
    (0, -cos p, -sin p): up leans back toward the camera as the camera looks down.
    """
    pitch = np.radians(float(pitch_deg))
    return np.array([0.0, -np.cos(pitch), -np.sin(pitch)])


def mounting_priors(camera_height: float, height_tolerance: float) -> Tuple[float, float]:
    """(min, max) camera height above the floor from the robot's mounting height and its tolerance."""
    return max(0.0, float(camera_height) - float(height_tolerance)), float(camera_height) + float(height_tolerance)


def box_exclusion_mask(shape: Tuple[int, int], boxes: FloatArray, grow_px: float = 10.0,
                       top_share: float = 1.0) -> BoolArray:
    """Pixels inside any person box (x1, y1, x2, y2[, score]) grown by ``grow_px``: the person is not floor.

    Used on a frame for which no person mask exists yet (the first frame of a scene), so that the
    fit does not take the person's own points for floor. With ``top_share`` < 1 only the upper
    share of each box is left out: the floor round the feet, often the only floor an occluder
    leaves in view, stays in the fit.

    Args:
        shape: (H, W) of the depth image.
        boxes: (N, 4+) boxes in image pixels (corners first; extra columns ignored).
        grow_px: pixels added on every side (at the bottom only when the whole box is left out).
        top_share: share (0..1] of each box's height, from its top, that is left out.

    Returns:
        (H, W) bool mask.

    Raises:
        GroundPlaneError: ``boxes`` is not (N, >= 4).
    """
    height, width = int(shape[0]), int(shape[1])
    boxes = np.asarray(boxes, dtype=np.float64)
    if boxes.size == 0:
        return np.zeros((height, width), dtype=bool)
    if boxes.ndim != 2 or boxes.shape[1] < 4:
        raise GroundPlaneError(f"box_exclusion_mask: boxes must be (N, >= 4), got {boxes.shape}")
    mask = np.zeros((height, width), dtype=bool)
    for x1, y1, x2, y2 in boxes[:, :4]:
        if not np.all(np.isfinite([x1, y1, x2, y2])):
            continue
        bottom = y2 + grow_px if top_share >= 1.0 else y1 + float(top_share) * (y2 - y1)
        c0, c1 = int(max(0, np.floor(x1 - grow_px))), int(min(width, np.ceil(x2 + grow_px)))
        r0, r1 = int(max(0, np.floor(y1 - grow_px))), int(min(height, np.ceil(bottom)))
        mask[r0:r1, c0:c1] = True
    return mask


#: Where a published floor came from, and how it relates to the camera pose (FloorEstimate.decision).
FLOOR_RANSAC = "ransac"  # RANSAC, no camera pose to check it against
FLOOR_RANSAC_CONFIRMED = "ransac_confirmed"  # RANSAC, within the tolerance of the camera-pose floor
FLOOR_POSE_REFUSED_RANSAC = "camera_pose_refused_ransac"  # RANSAC disagreed with the pose: the pose's floor
FLOOR_POSE_NO_RANSAC = "camera_pose_no_ransac"  # RANSAC found none: the pose's floor
FLOOR_NONE = "none"  # neither


@dataclass
class FloorEstimate:
    """The floor a frame is given: RANSAC's, the camera pose's, or none, with its quality.

    Attributes:
        valid: a floor was found.
        normal: (3,) unit up normal (zeros when not valid).
        offset: camera height above it, metres.
        from_pose: True when normal/offset are the camera pose's floor.
        decision: one of the FLOOR_* names (for diagnostics).
        quality: 0..1, how far the floor can be trusted (:func:`floor_quality`).
        angle_to_pose_deg: angle between RANSAC's and the pose's normals (NaN without both).
        height_to_pose_m: |d_ransac - d_pose| (NaN without both).
    """

    valid: bool
    normal: FloatArray
    offset: float
    from_pose: bool
    decision: str
    quality: float
    angle_to_pose_deg: float = float("nan")
    height_to_pose_m: float = float("nan")


def floor_quality(decision: str, inlier_ratio: float, full_support_ratio: float = 0.2) -> float:
    """A 0..1 trust figure of a floor (the GroundPlane ``quality`` field).

    s = min(1, inlier_ratio / full_support_ratio) is how much of the view supports the RANSAC
    plane. A RANSAC plane no pose could check scores 0.5 s (at most 0.5: one source only); the
    camera pose's floor alone scores 0.5 (the robot's localization, not seen in this view); a
    RANSAC plane confirmed by the pose scores 0.5 + 0.5 s (two sources agree: above 0.5). No
    floor scores 0.
    """
    support = float(np.clip(inlier_ratio / max(full_support_ratio, 1e-9), 0.0, 1.0)) if inlier_ratio > 0 else 0.0
    if decision == FLOOR_RANSAC:
        return 0.5 * support
    if decision == FLOOR_RANSAC_CONFIRMED:
        return 0.5 + 0.5 * support
    if decision in (FLOOR_POSE_REFUSED_RANSAC, FLOOR_POSE_NO_RANSAC):
        return 0.5
    return 0.0


def fuse_floor(
    ransac: GroundPlaneResult,
    pose_floor: Optional[Tuple[FloatArray, float]],
    max_angle_deg: float = 2.0,
    max_height_m: float = 0.05,
    full_support_ratio: float = 0.2,
) -> FloorEstimate:
    """RANSAC's floor checked against the camera pose's floor (docs/ALGORITHMS.md §5).

    With a pose, a valid RANSAC plane is kept only when its normal is within ``max_angle_deg``
    of the pose floor's and its offset within ``max_height_m``; otherwise it is refused and the
    pose's floor is used. A wrong RANSAC plane (an occluder's top, a wall's bottom, a slice
    through furniture when little floor is in view) is what this catches; a RANSAC plane that
    agrees measures the floor actually in view (small localization errors of the pose stay out).
    Without a pose, RANSAC's plane is used as it is.

    Args:
        ransac: the fit on this frame.
        pose_floor: (normal, offset) of the camera pose of this frame's stamp, or None.
        max_angle_deg: largest normal disagreement of an accepted RANSAC plane.
        max_height_m: largest offset disagreement of an accepted RANSAC plane.
        full_support_ratio: inlier ratio at which the quality's support figure saturates.

    Returns:
        The FloorEstimate.
    """
    angle = height = float("nan")
    if pose_floor is None:
        decision = FLOOR_RANSAC if ransac.valid else FLOOR_NONE
    else:
        pose_normal = np.asarray(pose_floor[0], dtype=np.float64)
        pose_offset = float(pose_floor[1])
        if ransac.valid:
            cosine = float(np.clip(np.asarray(ransac.normal) @ pose_normal, -1.0, 1.0))
            angle = float(np.degrees(np.arccos(cosine)))
            height = abs(float(ransac.offset) - pose_offset)
            agrees = angle <= max_angle_deg and height <= max_height_m
            decision = FLOOR_RANSAC_CONFIRMED if agrees else FLOOR_POSE_REFUSED_RANSAC
        else:
            decision = FLOOR_POSE_NO_RANSAC
    quality = floor_quality(decision, ransac.inlier_ratio, full_support_ratio)
    if decision in (FLOOR_RANSAC, FLOOR_RANSAC_CONFIRMED):
        return FloorEstimate(True, np.asarray(ransac.normal, dtype=np.float64), float(ransac.offset), False,
                             decision, quality, angle, height)
    if decision == FLOOR_NONE:
        return FloorEstimate(False, np.zeros(3), 0.0, False, decision, 0.0, angle, height)
    return FloorEstimate(True, pose_normal, pose_offset, True, decision, quality, angle, height)
