"""Candidate camera poses on a ring around the target, and their feasibility on the ground
(docs/ALGORITHMS.md §6).

The ring's parameters are :class:`leapnbv_planner.params.CandidateRingParams` (the nbv node's
parameters are an extension of it, so a node's params instance can be passed as they are).
"""

from __future__ import annotations

import enum
from dataclasses import dataclass
from typing import NamedTuple, Optional, Tuple

import numpy as np

from leapnbv_planner.arrays import Array
from leapnbv_planner.footprint_kernel import elevated_plane_points, footprints_blocked_in_plane
from leapnbv_planner.params import CandidateRingParams

# Everything here lives in the camera optical frame of the observation (x right, y down,
# z forward). The current camera sits at the origin with identity orientation. The ground is
# the plane n.x + d = 0 with unit n pointing up (toward the camera side), so the signed
# height of a point p above the ground is n.p + d, and the current camera's height is d.

_DEGENERATE_NORM = 1e-9


class CandidateGenerationError(ValueError):
    """Raised when the ring cannot be built from the given centroid, plane or parameters."""


class FeasibilityReason(enum.IntEnum):
    """Why a candidate is (in)feasible; one code per candidate.

    When a candidate fails both tests, OUT_OF_TRAVEL_RANGE is reported (it is checked first:
    it needs no scene data).
    """

    OK = 0
    OUT_OF_TRAVEL_RANGE = 1
    OBSTACLE = 2
    UNREACHABLE = 3  # no free path of at most max_path_length (leapnbv_planner.reachability)


@dataclass
class CandidateSet:
    """Candidate camera poses, all in the observation's camera optical frame.

    Attributes:
        rotations: (C, 3, 3) camera-to-observation rotations; columns are the candidate
            camera's x, y, z axes.
        positions: (C, 3) camera centres.
        foot_points: (C, 3) camera centres projected onto the ground plane.
        ring_center: (3,) target centroid projected onto the ground plane.
        camera_height: height (m) of the current camera above the plane; every ring candidate
            is placed at this height.
        is_current: (C,) bool, True for the current view.
    """

    rotations: Array
    positions: Array
    foot_points: Array
    ring_center: Array
    camera_height: float
    is_current: Array

    def __len__(self) -> int:
        return int(self.positions.shape[0])


class FeasibilityResult(NamedTuple):
    """Output of check_feasibility; unpacks as (feasible, reasons).

    Attributes:
        feasible: (C,) bool.
        reasons: (C,) int8 FeasibilityReason codes (0 = OK).
    """

    feasible: Array
    reasons: Array


def _as_vector3(value: object, name: str) -> Array:
    """Return value as a finite float64 (3,) array or raise CandidateGenerationError."""
    vector = np.asarray(value, dtype=np.float64)
    if vector.shape != (3,):
        raise CandidateGenerationError(f"{name} must have shape (3,), got {vector.shape}")
    if not np.all(np.isfinite(vector)):
        raise CandidateGenerationError(f"{name} must be finite, got {vector.tolist()}")
    return vector


def cross(a: Array, b: Array) -> Array:
    """np.cross over the last axis (3-vectors, or rows of them, broadcast), the same arithmetic (each component
    a_i b_j - a_j b_i, the products rounded first) without np.cross's per-call overhead (~0.1 ms)."""
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    out = np.empty(np.broadcast(a, b).shape)
    out[..., 0] = a[..., 1] * b[..., 2] - a[..., 2] * b[..., 1]
    out[..., 1] = a[..., 2] * b[..., 0] - a[..., 0] * b[..., 2]
    out[..., 2] = a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]
    return out


def norm3(v: Array) -> Array:
    """Euclidean length of 3-vectors over the last axis, as elementwise arithmetic: the same bits for one vector
    and for rows of them on every CPU (np.linalg.norm of one vector goes through BLAS, whose summation order
    depends on the CPU's vector width)."""
    v = np.asarray(v, dtype=np.float64)
    norms: Array = np.sqrt(v[..., 0] * v[..., 0] + v[..., 1] * v[..., 1] + v[..., 2] * v[..., 2])
    return norms


def normalize_plane(plane_normal: Array, plane_offset: float) -> Tuple[Array, float]:
    """Scale the plane n.x + d = 0 so that |n| = 1.

    Args:
        plane_normal: (3,) normal n, any non-zero length, pointing up.
        plane_offset: offset d.

    Returns:
        (unit normal (3,), offset) describing the same plane.

    Raises:
        CandidateGenerationError: the normal is not a finite non-zero (3,) vector.
    """
    normal = _as_vector3(plane_normal, "plane_normal")
    length = float(np.linalg.norm(normal))
    if length < _DEGENERATE_NORM:
        raise CandidateGenerationError("plane_normal has zero length")
    offset = float(plane_offset)
    if not np.isfinite(offset):
        raise CandidateGenerationError(f"plane_offset must be finite, got {plane_offset}")
    return normal / length, offset / length


def plane_basis(unit_normal: Array) -> Tuple[Array, Array]:
    """Two unit vectors spanning the plane orthogonal to unit_normal.

    Args:
        unit_normal: (3,) unit vector n.

    Returns:
        (e1, e2), each (3,), with (e1, e2, n) right-handed.
    """
    # Start from whichever optical axis is least aligned with n (for a level camera that is x).
    seed = np.eye(3)[int(np.argmin(np.abs(unit_normal)))]
    e1 = seed - float(seed @ unit_normal) * unit_normal
    e1 /= np.linalg.norm(e1)
    e2 = cross(unit_normal, e1)
    return e1, e2


def camera_look_at(position: Array, target: Array, up_normal: Array) -> Array:
    """Rotation of a camera at `position` whose optical axis points at `target`.

    z = normalize(target - position) (optical axis), x = normalize(z x up) (parallel to the
    ground, i.e. orthogonal to up), y = z x x. Then (x, y, z) is right-handed
    (x x y = z) and y.up = ((z.up)^2 - 1) / |z x up| <= 0: the image "down" axis points away
    from up, as for a level camera (z = (0,0,1), up = (0,-1,0) gives the identity).
    When z is parallel to up (looking straight down or up) x is undefined; then x is taken
    as the observation's x axis (or z axis if that is parallel too) made orthogonal to z.

    Args:
        position: (3,) camera centre.
        target: (3,) point to look at.
        up_normal: (3,) up direction (the ground normal n); need not be unit length.

    Returns:
        (3, 3) camera-to-observation rotation with columns x, y, z.

    Raises:
        CandidateGenerationError: position equals target, or up_normal is zero.
    """
    position = _as_vector3(position, "position")
    target = _as_vector3(target, "target")
    up = _as_vector3(up_normal, "up_normal")
    up_length = float(np.linalg.norm(up))
    if up_length < _DEGENERATE_NORM:
        raise CandidateGenerationError("up_normal has zero length")
    up = up / up_length
    view = target - position
    distance = float(norm3(view))
    if distance < _DEGENERATE_NORM:
        raise CandidateGenerationError("camera position coincides with the look-at target")
    z_axis = view / distance
    x_axis = cross(z_axis, up)
    x_length = float(norm3(x_axis))
    if x_length < _DEGENERATE_NORM:
        for fallback in (np.array([1.0, 0.0, 0.0]), np.array([0.0, 0.0, 1.0])):
            x_axis = fallback - float(fallback @ z_axis) * z_axis
            x_length = float(np.linalg.norm(x_axis))
            if x_length > 1e-3:
                break
    x_axis = x_axis / x_length
    y_axis = cross(z_axis, x_axis)
    return np.stack([x_axis, y_axis, z_axis], axis=1)


def _look_at_many(positions: Array, target: Array, unit_up: Array) -> Array:
    """camera_look_at for (C, 3) positions at once (the same arithmetic row by row); degenerate rows
    (looking along up, or at the target itself) go through camera_look_at."""
    positions = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
    unit_up = unit_up / float(np.linalg.norm(unit_up))  # as camera_look_at does, for the same bits
    targets = np.broadcast_to(np.asarray(target, dtype=np.float64), positions.shape)
    view = targets - positions
    distance = norm3(view)
    z_axis = view / np.where(distance > 0, distance, 1.0)[:, None]
    x_axis = cross(z_axis, unit_up[None, :])
    x_length = norm3(x_axis)
    x_axis = x_axis / np.where(x_length > 0, x_length, 1.0)[:, None]
    y_axis = cross(z_axis, x_axis)
    rotations: Array = np.stack([x_axis, y_axis, z_axis], axis=2)
    for index in np.flatnonzero((distance < _DEGENERATE_NORM) | (x_length < _DEGENERATE_NORM)):
        rotations[index] = camera_look_at(positions[index], targets[index], unit_up)
    return rotations


def _ring_start_direction(
    ring_center: Array, current_foot: Array, unit_normal: Array
) -> Array:
    """Unit in-plane direction from the ring centre toward the current camera's foot point.

    Falls back to the current camera's backward axis (-z) projected on the plane when the
    camera stands right above the ring centre, then to the projected x axis.
    """
    for direction in (
        current_foot - ring_center,
        np.array([0.0, 0.0, -1.0]),
        np.array([1.0, 0.0, 0.0]),
    ):
        in_plane = direction - float(direction @ unit_normal) * unit_normal
        length = float(np.linalg.norm(in_plane))
        if length > 1e-6:
            level: Array = in_plane / length
            return level
    raise CandidateGenerationError("cannot find an in-plane start direction for the ring")


def ring_radii(params: CandidateRingParams) -> Array:
    """The ring radii, innermost first: ``radius`` alone, or num_rings radii evenly from min_radius to radius."""
    rings = int(params.num_rings)
    if rings <= 1:
        return np.array([float(params.radius)])
    return np.linspace(float(params.min_radius), float(params.radius), rings)


def cameras_at_feet(feet: Array, centroid: Array, unit_normal: Array, camera_height: float,
                    params: CandidateRingParams) -> Tuple[Array, Array]:
    """(rotations (N, 3, 3), positions (N, 3)) of the robot's camera standing at (N, 3) foot points.

    The camera sits at the mounting height (``params.camera_height``, or ``camera_height``, the current
    camera's, when that is 0) above its foot point and looks at the centroid (``camera_tilt`` look_at), or
    turns toward it keeping the current camera's pitch (``fixed``).
    """
    mounting = float(params.camera_height)
    positions = feet + (mounting if mounting > 0.0 else camera_height) * unit_normal[None, :]
    aim = centroid
    if params.camera_tilt == "fixed":
        # A head without tilt: aim along the level bearing to the target, pitched as the current camera is
        # (sin(pitch) = -z.n for the current optical axis z = (0, 0, 1)).
        sin_pitch = float(np.clip(-unit_normal[2], -0.999, 0.999))
        level = centroid[None, :] - positions
        level -= (level @ unit_normal)[:, None] * unit_normal[None, :]
        level /= np.maximum(np.linalg.norm(level, axis=1), 1e-12)[:, None]
        aim = positions + np.sqrt(1.0 - sin_pitch ** 2) * level - sin_pitch * unit_normal[None, :]
    return _look_at_many(positions, aim, unit_normal), positions


def generate_candidates(
    centroid: Array,
    plane_normal: Array,
    plane_offset: float,
    params: CandidateRingParams,
) -> CandidateSet:
    """Candidate camera poses on a ring on the ground plane around the target.

    Ring centre c0 = centroid projected onto the plane. Camera height h = n.0 + d = d (the
    current camera's height above the plane). Ring candidate k (k = 0..N-1) stands at
    foot point f_k = c0 + r (cos(theta_k) u + sin(theta_k) (n x u)), theta_k = 2 pi k / N,
    with camera centre f_k + h n, and looks at the centroid (camera_look_at with up = n).
    u is the in-plane direction from c0 toward the current camera's foot point, so ring
    candidate 0 lies on the current camera's bearing from the target (at radius r, which
    is generally not the current distance); the ring then runs counter-clockwise seen from
    above (right-hand rule about n).
    With include_current the current view (identity rotation, origin) is prepended as
    index 0, so ring candidate k has index k + 1. With num_rings > 1 there are num_rings such
    rings (radii from :func:`ring_radii`, innermost first), N candidates each, the same angles.

    Args:
        centroid: (3,) target centroid.
        plane_normal: (3,) ground normal n pointing up (any non-zero length; normalized).
        plane_offset: ground offset d (scaled along with n).
        params: ring parameters.

    Returns:
        CandidateSet with C = N (+ 1 with include_current) candidates.

    Raises:
        CandidateGenerationError: non-finite or mis-shaped inputs, a camera that is not
            above the plane (d <= 0), or invalid parameters.
    """
    centroid = _as_vector3(centroid, "centroid")
    unit_normal, offset = normalize_plane(plane_normal, plane_offset)
    num_ring = int(params.num_candidates)
    if num_ring < 0:
        raise CandidateGenerationError(f"num_candidates must be >= 0, got {num_ring}")
    if num_ring > 0 and not params.radius > 0.0:
        raise CandidateGenerationError(f"radius must be > 0, got {params.radius}")
    camera_height = offset
    if camera_height <= 0.0:
        raise CandidateGenerationError(
            f"the current camera is not above the ground plane (height {camera_height:.3f} m);"
            " the plane normal must point toward the camera"
        )

    ring_center = centroid - (float(unit_normal @ centroid) + offset) * unit_normal
    current_foot = -offset * unit_normal
    start = _ring_start_direction(ring_center, current_foot, unit_normal)
    side = cross(unit_normal, start)
    angles = 2.0 * np.pi * np.arange(num_ring) / max(num_ring, 1)
    feet_per_ring = [
        ring_center[None, :]
        + float(radius) * np.cos(angles)[:, None] * start[None, :]
        + float(radius) * np.sin(angles)[:, None] * side[None, :]
        for radius in ring_radii(params)
    ]
    ring_feet = np.concatenate(feet_per_ring, axis=0) if feet_per_ring else np.zeros((0, 3))
    num_ring = ring_feet.shape[0]
    ring_rotations, ring_positions = cameras_at_feet(ring_feet, centroid, unit_normal, camera_height, params)

    if params.include_current:
        rotations = np.concatenate([np.eye(3)[None], ring_rotations], axis=0)
        positions = np.concatenate([np.zeros((1, 3)), ring_positions], axis=0)
        foot_points = np.concatenate([current_foot[None], ring_feet], axis=0)
        is_current = np.zeros(num_ring + 1, dtype=bool)
        is_current[0] = True
    else:
        rotations, positions, foot_points = ring_rotations, ring_positions, ring_feet
        is_current = np.zeros(num_ring, dtype=bool)
    return CandidateSet(
        rotations=rotations,
        positions=positions,
        foot_points=foot_points,
        ring_center=ring_center,
        camera_height=camera_height,
        is_current=is_current,
    )


def check_feasibility(
    candidates: CandidateSet,
    background_points: Array,
    plane_normal: Array,
    plane_offset: float,
    params: CandidateRingParams,
    obstacle_plane_points: Optional[Array] = None,
) -> FeasibilityResult:
    """Which candidates the robot can stand at.

    A candidate is infeasible when
      - OUT_OF_TRAVEL_RANGE: its foot point is farther than max_travel from the current
        camera's foot point (-d n), or
      - OBSTACLE: some background point higher than floor_clearance above the plane
        (n.p + d > floor_clearance) lies within robot_radius of its foot point, measured
        in the plane (the distance between the two points projected onto the plane;
        exactly robot_radius counts as inside).
    The current view (is_current) is feasible by definition: the robot already stands
    there, so anything near it (its own body, the person's support) cannot block it.
    Non-finite background points are ignored.

    Args:
        candidates: the candidate set (C candidates).
        background_points: (K, 3) scene points that are not the target (K may be 0).
        plane_normal: (3,) ground normal n pointing up.
        plane_offset: ground offset d.
        params: robot_radius, floor_clearance and max_travel are used.
        obstacle_plane_points: the background points higher than floor_clearance as (M, 2) plane coordinates
            (footprint_kernel.elevated_plane_points with plane_basis of the unit normal), when the caller made them
            already; then background_points is only checked for its shape.

    Returns:
        FeasibilityResult(feasible (C,) bool, reasons (C,) int8 FeasibilityReason codes).

    Raises:
        CandidateGenerationError: background_points is not (K, 3), or the plane is invalid.
    """
    unit_normal, offset = normalize_plane(plane_normal, plane_offset)
    points = np.asarray(background_points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise CandidateGenerationError(
            f"background_points must have shape (K, 3), got {points.shape}"
        )
    foot_points = np.asarray(candidates.foot_points, dtype=np.float64)
    num_candidates = foot_points.shape[0]
    reasons = np.full(num_candidates, int(FeasibilityReason.OK), dtype=np.int8)

    # Travel range: distance between foot points (both lie on the plane).
    current_foot = -offset * unit_normal
    travel = np.linalg.norm(foot_points - current_foot[None, :], axis=1)
    out_of_range = travel > float(params.max_travel)

    # Obstacles: points above the floor clearance within the robot radius, in the plane.
    e1, e2 = plane_basis(unit_normal)
    if obstacle_plane_points is None:
        obstacle_plane_points = elevated_plane_points(np.ascontiguousarray(points), unit_normal, offset,
                                                      float(params.floor_clearance), e1, e2)
    blocked = footprints_blocked_in_plane(
        np.ascontiguousarray(obstacle_plane_points, dtype=np.float64), np.ascontiguousarray(foot_points @ e1),
        np.ascontiguousarray(foot_points @ e2), float(params.robot_radius))

    reasons[blocked] = int(FeasibilityReason.OBSTACLE)
    reasons[out_of_range] = int(FeasibilityReason.OUT_OF_TRAVEL_RANGE)
    is_current = np.asarray(candidates.is_current, dtype=bool)
    reasons[is_current] = int(FeasibilityReason.OK)
    feasible = reasons == int(FeasibilityReason.OK)
    return FeasibilityResult(feasible=feasible, reasons=reasons)
