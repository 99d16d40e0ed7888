"""Next-best-view scores S_v, S_a, S_o of candidate camera poses, and the choice among them."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional, Tuple

import numpy as np

from leapnbv_planner.occlusion_kernel import axis_aligned_bounds, count_visible_targets

# Camera coordinates: (x, y, z) = R^T (p - t) for a candidate with rotation R (columns = the
# candidate's axes in the observation frame) and centre t. Projection of a point with z > 0:
# u = fx (x/z) + skew (y/z) + cx, v = fy (y/z) + cy, pixel (floor(u), floor(v)).

# Near plane for the bounding-box area: the box is clipped to z >= NEAR_PLANE_M before
# projecting, so a box reaching behind the camera extends to the image border on that side.
NEAR_PLANE_M = 1e-6

# Two scores within this of each other are a tie (broken by distance to the current pose).
SCORE_TIE_TOLERANCE = 1e-9

# Corner k of an axis-aligned box takes the max along axis a when bit a of k is set; box edges
# join corners differing in exactly one bit.
_CORNER_BITS = np.array([[(k >> axis) & 1 for axis in range(3)] for k in range(8)], dtype=bool)
_BOX_EDGES = np.array(
    [(k, k | (1 << axis)) for k in range(8) for axis in range(3) if not k & (1 << axis)]
)


class ScoringInputError(ValueError):
    """Raised when an input of the scoring has the wrong shape or an invalid value."""


@dataclass
class ScoreWeights:
    """Weights of score = w_v S_v + w_a S_a + w_o S_o (paper defaults)."""

    visibility: float = 0.03
    area: float = 0.14
    occlusion: float = 0.83


@dataclass
class CandidateScores:
    """Scores of C candidate views, each a (C,) float64 array.

    Attributes:
        s_visibility: S_v, fraction of target points in view.
        s_area: S_a, clipped image area of the target's projected 3D bounding box over W*H.
        s_occlusion: S_o, fraction of the in-view target points not hidden by background.
        score: w_v S_v + w_a S_a + w_o S_o.
    """

    s_visibility: np.ndarray
    s_area: np.ndarray
    s_occlusion: np.ndarray
    score: np.ndarray


def _finite_points(points: object, name: str) -> np.ndarray:
    """Return the finite rows of an (M, 3) array as contiguous float64."""
    array = np.asarray(points, dtype=np.float64)
    if array.ndim != 2 or array.shape[1] != 3:
        raise ScoringInputError(f"{name} must have shape (M, 3), got {array.shape}")
    finite = np.isfinite(array)
    if finite.all():  # the usual case: skip the row mask and the copy it would need
        return np.ascontiguousarray(array)
    return np.ascontiguousarray(array[np.all(finite, axis=1)])


def _check_poses(rotations: object, positions: object) -> Tuple[np.ndarray, np.ndarray]:
    """Validate candidate poses; return contiguous float64 (C,3,3) and (C,3) arrays."""
    rotation_array = np.ascontiguousarray(rotations, dtype=np.float64)
    position_array = np.ascontiguousarray(positions, dtype=np.float64)
    if rotation_array.ndim != 3 or rotation_array.shape[1:] != (3, 3):
        raise ScoringInputError(f"rotations must have shape (C, 3, 3), got {rotation_array.shape}")
    if position_array.shape != (rotation_array.shape[0], 3):
        raise ScoringInputError(
            f"positions must have shape ({rotation_array.shape[0]}, 3) to match rotations,"
            f" got {position_array.shape}"
        )
    if not (np.all(np.isfinite(rotation_array)) and np.all(np.isfinite(position_array))):
        raise ScoringInputError("rotations and positions must be finite")
    return rotation_array, position_array


def _check_camera(
    intrinsics: object, width: int, height: int
) -> Tuple[float, float, float, float, float, int, int]:
    """Validate K and the image size; return (fx, skew, cx, fy, cy, width, height)."""
    matrix = np.asarray(intrinsics, dtype=np.float64)
    if matrix.shape != (3, 3) or not np.all(np.isfinite(matrix)):
        raise ScoringInputError(f"K must be a finite (3, 3) matrix, got shape {matrix.shape}")
    if not (matrix[0, 0] > 0.0 and matrix[1, 1] > 0.0):
        raise ScoringInputError(f"K must have positive focal lengths, got {matrix[0, 0]}, {matrix[1, 1]}")
    if int(width) <= 0 or int(height) <= 0:
        raise ScoringInputError(f"image size must be positive, got {width} x {height}")
    return (
        float(matrix[0, 0]),
        float(matrix[0, 1]),
        float(matrix[0, 2]),
        float(matrix[1, 1]),
        float(matrix[1, 2]),
        int(width),
        int(height),
    )


def to_camera_frame(points: np.ndarray, rotations: np.ndarray, positions: np.ndarray) -> np.ndarray:
    """Express observation-frame points in each candidate camera's frame.

    Args:
        points: (M, 3) or (C, M, 3) points in the observation frame.
        rotations: (C, 3, 3) camera-to-observation rotations.
        positions: (C, 3) camera centres.

    Returns:
        (C, M, 3) camera coordinates R_c^T (p - t_c).
    """
    offsets = (points[None] if points.ndim == 2 else points) - positions[:, None, :]
    # Row vectors: (p - t)^T R = (R^T (p - t))^T.
    return np.matmul(offsets, rotations)


def bounding_box_area_fraction(
    target_points: np.ndarray,
    rotations: np.ndarray,
    positions: np.ndarray,
    K: np.ndarray,
    width: int,
    height: int,
) -> np.ndarray:
    """S_a: image area covered by the projected 3D bounding box of the target, over W*H.

    The box is the target's axis-aligned bounding box in the observation frame (8 corners).
    For each candidate the box is clipped to the near half-space z >= NEAR_PLANE_M (the
    vertices of the clipped box are the corners in front plus the crossings of the 12 box
    edges with the near plane), the vertices are projected, and their 2D bounding rectangle
    [u_min, u_max] x [v_min, v_max] is clipped to [0, W] x [0, H]. Because projection maps
    the convex clipped box to the convex hull of its projected vertices, this rectangle is
    the bounding rectangle of the box's image. A box reaching behind the camera therefore
    extends to the image border on the side that goes behind; a box wholly behind, or fewer
    than one target point, gives 0.

    Args:
        target_points: (N, 3) finite target points.
        rotations: (C, 3, 3) camera-to-observation rotations.
        positions: (C, 3) camera centres.
        K: (3, 3) intrinsics.
        width, height: image size in pixels.

    Returns:
        (C,) float64 fractions in [0, 1].
    """
    points = _finite_points(target_points, "target_points")
    rotation_array, position_array = _check_poses(rotations, positions)
    camera = _check_camera(K, width, height)
    return _box_area_fraction(points, rotation_array, position_array, camera)


def _box_area_fraction(
    points: np.ndarray,
    rotation_array: np.ndarray,
    position_array: np.ndarray,
    camera: Tuple[float, float, float, float, float, int, int],
) -> np.ndarray:
    """bounding_box_area_fraction on validated inputs (see there)."""
    fx, skew, cx, fy, cy, width, height = camera
    num_candidates = rotation_array.shape[0]
    if points.shape[0] == 0 or num_candidates == 0:
        return np.zeros(num_candidates)

    lower, upper = axis_aligned_bounds(points)
    corners = np.where(_CORNER_BITS, upper, lower)  # (8, 3)
    camera_corners = to_camera_frame(corners, rotation_array, position_array)  # (C, 8, 3)
    depth = camera_corners[..., 2]
    in_front = depth >= NEAR_PLANE_M

    # Crossings of the box edges with the near plane z = NEAR_PLANE_M.
    start = camera_corners[:, _BOX_EDGES[:, 0]]  # (C, 12, 3)
    end = camera_corners[:, _BOX_EDGES[:, 1]]
    crosses = in_front[:, _BOX_EDGES[:, 0]] != in_front[:, _BOX_EDGES[:, 1]]
    depth_step = np.where(crosses, end[..., 2] - start[..., 2], 1.0)
    fraction = np.where(crosses, (NEAR_PLANE_M - start[..., 2]) / depth_step, 0.0)
    crossings = start + fraction[..., None] * (end - start)
    crossings[..., 2] = NEAR_PLANE_M

    vertices = np.concatenate([camera_corners, crossings], axis=1)  # (C, 20, 3)
    valid = np.concatenate([in_front, crosses], axis=1)
    safe_depth = np.where(valid, vertices[..., 2], 1.0)
    x_norm = vertices[..., 0] / safe_depth
    y_norm = vertices[..., 1] / safe_depth
    u = fx * x_norm + skew * y_norm + cx
    v = fy * y_norm + cy
    any_valid = np.any(valid, axis=1)
    u_min = np.clip(np.where(valid, u, np.inf).min(axis=1), 0.0, width)
    u_max = np.clip(np.where(valid, u, -np.inf).max(axis=1), 0.0, width)
    v_min = np.clip(np.where(valid, v, np.inf).min(axis=1), 0.0, height)
    v_max = np.clip(np.where(valid, v, -np.inf).max(axis=1), 0.0, height)
    area = np.maximum(u_max - u_min, 0.0) * np.maximum(v_max - v_min, 0.0)
    return np.where(any_valid, area / float(width * height), 0.0)


def score_candidates(
    target_points: np.ndarray,
    background_points: np.ndarray,
    rotations: np.ndarray,
    positions: np.ndarray,
    K: np.ndarray,
    width: int,
    height: int,
    weights: Optional[ScoreWeights] = None,
    delta_px: float = 4.0,
    line_of_sight_clear: Optional[np.ndarray] = None,
) -> CandidateScores:
    """Score C candidate views of the target.

    With (x, y, z) = R^T (p - t), u = fx x/z + skew y/z + cx, v = fy y/z + cy:
      - S_v = (# target points with z > 0, 0 <= u < W, 0 <= v < H) / (# target points).
      - S_a = bounding_box_area_fraction (projected 3D box clipped to the image, over W*H).
      - S_o = (# in-view target points not hidden) / (# in-view target points), 0 when no
        target point is in view. With pixel (i, j) = (floor(u), floor(v)) and
        h = floor(delta_px), an in-view target point of depth z_t is hidden when some
        background point with z_b > 0 has its pixel within the square window
        |i_b - i| <= h, |j_b - j| <= h and z_b < z_t (depth is the optical-axis z, not
        the range). Background points outside the image still count inside the window.
        S_o is kept separate from S_v on purpose: S_v measures framing, S_o occlusion of
        what is framed. With ``line_of_sight_clear`` (the share of target points that each
        candidate sees through free space of the robot's obstacle map, see
        :mod:`leapnbv_planner.obstacle_map`) S_o is multiplied by it: the background only
        holds what the current view saw, the map also what it did not.
      - score = w_v S_v + w_a S_a + w_o S_o.
    Rows with a non-finite coordinate are dropped from both clouds before anything is
    counted. The first call compiles the occlusion kernel (see warm_up_scoring).

    Args:
        target_points: (N, 3) target (person) points, observation frame.
        background_points: (K, 3) other scene points (K may be 0).
        rotations: (C, 3, 3) candidate camera-to-observation rotations.
        positions: (C, 3) candidate camera centres.
        K: (3, 3) intrinsics of the candidate views.
        width, height: image size in pixels.
        weights: score weights; ScoreWeights() when None.
        delta_px: occlusion neighbourhood half-width in pixels (floored to an integer).
        line_of_sight_clear: optional (C,) factors in [0, 1] applied to S_o.

    Returns:
        CandidateScores with (C,) arrays.

    Raises:
        ScoringInputError: a shape, intrinsic, image size or delta_px is invalid.
    """
    weights = ScoreWeights() if weights is None else weights
    targets = _finite_points(target_points, "target_points")
    background = _finite_points(background_points, "background_points")
    rotation_array, position_array = _check_poses(rotations, positions)
    camera = _check_camera(K, width, height)
    fx, skew, cx, fy, cy, width, height = camera
    if not (np.isfinite(delta_px) and delta_px >= 0.0):
        raise ScoringInputError(f"delta_px must be a finite number >= 0, got {delta_px}")
    half_window = int(np.floor(delta_px))

    in_view, not_hidden = count_visible_targets(
        targets, background, rotation_array, position_array,
        fx, skew, cx, fy, cy, width, height, half_window,
    )
    num_targets = targets.shape[0]
    s_visibility = in_view / float(num_targets) if num_targets else np.zeros(len(in_view))
    s_occlusion = np.where(in_view > 0, not_hidden / np.maximum(in_view, 1), 0.0)
    if line_of_sight_clear is not None:
        clear = np.asarray(line_of_sight_clear, dtype=np.float64).reshape(-1)
        if clear.shape != s_occlusion.shape or not np.all((clear >= 0.0) & (clear <= 1.0)):
            raise ScoringInputError(
                f"line_of_sight_clear must be {s_occlusion.shape[0]} values in [0, 1], got shape {clear.shape}")
        s_occlusion = s_occlusion * clear
    s_area = _box_area_fraction(targets, rotation_array, position_array, camera)
    score = (
        weights.visibility * s_visibility
        + weights.area * s_area
        + weights.occlusion * s_occlusion
    )
    return CandidateScores(
        s_visibility=np.asarray(s_visibility, dtype=np.float64),
        s_area=np.asarray(s_area, dtype=np.float64),
        s_occlusion=np.asarray(s_occlusion, dtype=np.float64),
        score=np.asarray(score, dtype=np.float64),
    )


def choose_best(
    scores: np.ndarray,
    feasible: np.ndarray,
    positions: np.ndarray,
    current_position: np.ndarray,
) -> int:
    """Index of the best feasible candidate, or -1 when none is feasible.

    Among feasible candidates with a finite score, those within SCORE_TIE_TOLERANCE of the
    best score tie; the tie goes to the one whose position is nearest current_position, then
    to the lowest index. Infeasible candidates and NaN scores are never chosen.

    Args:
        scores: (C,) scores.
        feasible: (C,) bool.
        positions: (C, 3) candidate camera centres.
        current_position: (3,) current camera centre.

    Returns:
        Chosen index in [0, C) or -1.

    Raises:
        ScoringInputError: the array lengths disagree.
    """
    score_array = np.asarray(scores, dtype=np.float64).reshape(-1)
    feasible_array = np.asarray(feasible, dtype=bool).reshape(-1)
    position_array = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
    if not (score_array.shape[0] == feasible_array.shape[0] == position_array.shape[0]):
        raise ScoringInputError(
            f"scores ({score_array.shape[0]}), feasible ({feasible_array.shape[0]}) and"
            f" positions ({position_array.shape[0]}) must have the same length"
        )
    eligible = feasible_array & np.isfinite(score_array)
    if not np.any(eligible):
        return -1
    best = float(np.max(score_array[eligible]))
    tied = np.flatnonzero(eligible & (score_array >= best - SCORE_TIE_TOLERANCE))
    distances = np.linalg.norm(
        position_array[tied] - np.asarray(current_position, dtype=np.float64)[None, :], axis=1
    )
    # argmin returns the first minimum, i.e. the lowest index among equal distances.
    return int(tied[int(np.argmin(distances))])


def warm_up_scoring() -> None:
    """Compile the occlusion kernel now (a node calls this at start-up, not on frame one)."""
    score_candidates(
        np.array([[0.0, 0.0, 2.0]]),
        np.array([[0.0, 0.0, 1.0]]),
        np.eye(3)[None],
        np.zeros((1, 3)),
        np.array([[100.0, 0.0, 50.0], [0.0, 100.0, 50.0], [0.0, 0.0, 1.0]]),
        100,
        100,
    )
