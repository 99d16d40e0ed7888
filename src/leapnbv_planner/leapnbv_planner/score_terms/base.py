"""What a score term is, the scoring context every term computes from, and the registry of terms by name.

A score term maps C candidate views to C numbers in [0, 1]; the planner's score is the weighted sum
of the terms named by the ``score_terms`` parameter, in that order (see
:func:`leapnbv_planner.scoring.score_candidates`). A term is registered once, by the module that
defines it (one module per term in this package; the package imports them all). The context
validates the inputs once and shares the expensive per-candidate counts between terms: the
occlusion kernel gives both the in-view and the not-hidden counts in one call, made at most once
per context, whichever term asks first.

Camera coordinates: (x, y, z) = R^T (p - t) for a candidate with rotation R (columns = the
candidate's axes in the observation frame) and centre t. Projection of a point with z > 0:
u = fx (x/z) + skew (y/z) + cx, v = fy (y/z) + cy, pixel (floor(u), floor(v)).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Dict, List, Optional, Tuple

import numpy as np

from leapnbv_planner.occlusion_kernel import (
    POINTS_PER_BOX,
    RUN_LENGTH,
    bucket_points,
    count_visible_targets_bucketed,
    possible_occluders,
    run_facing_bounds,
)

# (fx, skew, cx, fy, cy, width, height) of validated intrinsics and image size.
Camera = Tuple[float, float, float, float, float, int, int]
# A cloud sorted into boxes by leapnbv_planner.occlusion_kernel.bucket_points: (points, companions, cell_runs,
# cell_boxes, run_starts, run_boxes).
Buckets = Tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]
_NO_ROWS = np.zeros((0, 3))


class ScoringInputError(ValueError):
    """Raised when an input of the scoring has the wrong shape or an invalid value."""


def finite_points(points: object, name: str) -> np.ndarray:
    """Return the finite rows of an (M, 3) array as contiguous float64."""
    array = np.asarray(points, dtype=np.float64)
    if array.ndim != 2 or array.shape[1] != 3:
        raise ScoringInputError(f"{name} must have shape (M, 3), got {array.shape}")
    finite = np.isfinite(array)
    if finite.all():  # the usual case: skip the row mask and the copy it would need
        return np.ascontiguousarray(array)
    return np.ascontiguousarray(array[np.all(finite, axis=1)])


def check_poses(rotations: object, positions: object) -> Tuple[np.ndarray, np.ndarray]:
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


def check_camera(intrinsics: object, width: int, height: int) -> Camera:
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


class ScoringContext:
    """The validated inputs of one scoring call, and the results terms share.

    Rows with a non-finite coordinate are dropped from both clouds before anything is counted.

    Args:
        target_points: (N, 3) target (person) points, observation frame.
        background_points: (K, 3) other scene points (K may be 0).
        rotations: (C, 3, 3) candidate camera-to-observation rotations.
        positions: (C, 3) candidate camera centres.
        K: (3, 3) intrinsics of the candidate views.
        width, height: image size in pixels.
        delta_px: occlusion neighbourhood half-width in pixels (floored to an integer).
        line_of_sight_clear: optional (C,) factors in [0, 1]: the share of target points each
            candidate sees through free space of the robot's obstacle map (the occlusion term
            multiplies by it).
        path_lengths: optional (C,) metres the robot drives to each candidate (inf: no path); None:
            the straight distance between the camera centres.
        travel_scale: metres of travel that cost the whole travel term.
        mesh_vertices: optional (V, 3) vertices of the person's metric body mesh (the whole body, the hidden
            parts included), observation frame; with mesh_normals (V, 3) outward vertex normals.
        mesh_line_of_sight_clear: optional (C,) obstacle-map clear share of the mesh vertices per candidate.

    Raises:
        ScoringInputError: a shape, intrinsic, image size, delta_px or line_of_sight_clear is invalid.
    """

    def __init__(self, target_points: np.ndarray, background_points: np.ndarray, rotations: np.ndarray,
                 positions: np.ndarray, K: np.ndarray, width: int, height: int, delta_px: float = 4.0,
                 line_of_sight_clear: Optional[np.ndarray] = None, path_lengths: Optional[np.ndarray] = None,
                 travel_scale: float = 6.0, mesh_vertices: Optional[np.ndarray] = None,
                 mesh_normals: Optional[np.ndarray] = None,
                 mesh_line_of_sight_clear: Optional[np.ndarray] = None) -> None:
        self.targets = finite_points(target_points, "target_points")
        self.background = finite_points(background_points, "background_points")
        self.rotations, self.positions = check_poses(rotations, positions)
        self.camera: Camera = check_camera(K, width, height)
        if not (np.isfinite(delta_px) and delta_px >= 0.0):
            raise ScoringInputError(f"delta_px must be a finite number >= 0, got {delta_px}")
        self.half_window = int(np.floor(delta_px))
        self.line_of_sight_clear: Optional[np.ndarray] = None
        if line_of_sight_clear is not None:
            clear = np.asarray(line_of_sight_clear, dtype=np.float64).reshape(-1)
            if clear.shape != (self.num_candidates,) or not np.all((clear >= 0.0) & (clear <= 1.0)):
                raise ScoringInputError(f"line_of_sight_clear must be {self.num_candidates} values in [0, 1],"
                                        f" got shape {clear.shape}")
            self.line_of_sight_clear = clear
        self.path_lengths: Optional[np.ndarray] = None
        if path_lengths is not None:
            lengths = np.asarray(path_lengths, dtype=np.float64).reshape(-1)
            if lengths.shape != (self.num_candidates,) or np.any(np.isnan(lengths)) or np.any(lengths < 0.0):
                raise ScoringInputError(f"path_lengths must be {self.num_candidates} values >= 0, got shape "
                                        f"{lengths.shape}")
            self.path_lengths = lengths
        if not (np.isfinite(travel_scale) and travel_scale > 0.0):
            raise ScoringInputError(f"travel_scale must be a finite number > 0, got {travel_scale}")
        self.travel_scale = float(travel_scale)
        self.mesh_vertices: Optional[np.ndarray] = None
        self.mesh_normals: Optional[np.ndarray] = None
        self.mesh_line_of_sight_clear: Optional[np.ndarray] = None
        if mesh_vertices is not None:
            vertices = np.ascontiguousarray(mesh_vertices, dtype=np.float64)
            normals = np.ascontiguousarray(mesh_normals, dtype=np.float64) if mesh_normals is not None else None
            if vertices.ndim != 2 or vertices.shape[1] != 3 or normals is None or normals.shape != vertices.shape:
                raise ScoringInputError(f"mesh_vertices must be (V, 3) with mesh_normals of the same shape, got "
                                        f"{vertices.shape} and {None if normals is None else normals.shape}")
            if np.isfinite(vertices).all() and np.isfinite(normals).all():  # the usual case: no copies
                self.mesh_vertices, self.mesh_normals = vertices, normals
            else:
                keep = np.all(np.isfinite(vertices), axis=1) & np.all(np.isfinite(normals), axis=1)
                self.mesh_vertices, self.mesh_normals = vertices[keep], normals[keep]
            if mesh_line_of_sight_clear is not None:
                clear = np.asarray(mesh_line_of_sight_clear, dtype=np.float64).reshape(-1)
                if clear.shape != (self.num_candidates,) or not np.all((clear >= 0.0) & (clear <= 1.0)):
                    raise ScoringInputError(f"mesh_line_of_sight_clear must be {self.num_candidates} values in "
                                            f"[0, 1], got shape {clear.shape}")
                self.mesh_line_of_sight_clear = clear
        self._buckets: Dict[str, Buckets] = {}
        self._mesh_counts: Optional[Tuple[np.ndarray, np.ndarray]] = None
        self._in_view: Optional[np.ndarray] = None
        self._counts: Optional[Tuple[np.ndarray, np.ndarray]] = None
        self.kernel_calls = 0

    @property
    def num_candidates(self) -> int:
        return int(self.rotations.shape[0])

    @property
    def num_targets(self) -> int:
        return int(self.targets.shape[0])

    def buckets(self, name: str) -> Buckets:
        """The cloud ``name`` ("targets", "background", "mesh" with its normals, "none": no points) sorted into
        boxes once per context (the kernels skip or count whole boxes per candidate). The background keeps only
        the points that can hide a target point or mesh vertex from a candidate (``possible_occluders``: the
        counts are the same)."""
        if name not in self._buckets:
            if name == "mesh" and self.mesh_vertices is not None:
                points, companions = self.mesh_vertices, self.mesh_normals
            elif name == "background":  # only the points that can hide a target or mesh point from a candidate
                fx, skew, _, fy, _, _, _ = self.camera
                points = possible_occluders(self.background, self.positions, [self.targets] + (
                    [self.mesh_vertices] if self.mesh_vertices is not None else []), fx, skew, fy, self.half_window)
                companions = _NO_ROWS
            else:
                points = {"targets": self.targets}.get(name, _NO_ROWS)
                companions = _NO_ROWS
            self._buckets[name] = bucket_points(np.ascontiguousarray(points), np.ascontiguousarray(companions),
                                                POINTS_PER_BOX, RUN_LENGTH)
        return self._buckets[name]

    def _kernel_counts(self, targets: str, background: str) -> Tuple[np.ndarray, np.ndarray]:
        """(in_view, not_hidden) of :func:`leapnbv_planner.occlusion_kernel.count_visible_targets_bucketed`."""
        fx, skew, cx, fy, cy, width, height = self.camera
        target_points, target_normals, *target_boxes = self.buckets(targets)
        background_points, _, *background_boxes = self.buckets(background)
        facing = (run_facing_bounds(target_points, target_normals, target_boxes[2]) if len(target_normals)
                  else np.zeros((0, 7)))
        self.kernel_calls += 1
        return count_visible_targets_bucketed(
            target_points, target_normals, *target_boxes, facing, background_points, *background_boxes,
            self.rotations, self.positions, fx, skew, cx, fy, cy, width, height, self.half_window)

    def visible_counts(self) -> Tuple[np.ndarray, np.ndarray]:
        """(in_view (C,) int64, not_hidden (C,) int64), from one occlusion-kernel call per context.

        In view: z > 0 and 0 <= u < W and 0 <= v < H. Not hidden: with pixel (i, j) and
        h = floor(delta_px), no background point with z_b > 0 has its pixel within the window
        |i_b - i| <= h, |j_b - j| <= h and z_b < z_t (see
        :func:`leapnbv_planner.occlusion_kernel.count_visible_targets`, here its bucketed form).
        """
        if self._counts is None:
            self._counts = self._kernel_counts("targets", "background")
        return self._counts

    def in_view_counts(self) -> np.ndarray:
        """(C,) int64 target points in view: from visible_counts when it ran, else from a kernel call without
        the background (projection only, no occlusion test: what S_v needs when S_o is not scored)."""
        if self._counts is not None:
            return self._counts[0]
        if self._in_view is None:
            self._in_view, _ = self._kernel_counts("targets", "none")
        return self._in_view

    def mesh_counts(self) -> Tuple[np.ndarray, np.ndarray]:
        """(facing (C,) int64, not_hidden (C,) int64) over the body mesh's vertices, once per context.

        Facing: vertices whose outward normal faces the candidate camera (n . (t_c - p) > 0), in view or
        not (the body's near side from there). Not hidden: facing vertices in view and not hidden by the
        background (the same window test as S_o's, :func:`count_visible_targets`).

        Raises:
            ScoringInputError: the context has no mesh.
        """
        if self.mesh_vertices is None:
            raise ScoringInputError("no body mesh in the scoring context")
        if self._mesh_counts is None:
            _, not_hidden = self._kernel_counts("mesh", "background")
            # n . (t_c - v) > 0  <=>  n . t_c > n . v: one (C, 3) x (3, V) product.
            facing = np.count_nonzero(self.positions @ self.mesh_normals.T
                                      > np.einsum("vk,vk->v", self.mesh_normals, self.mesh_vertices), axis=1)
            self._mesh_counts = (facing.astype(np.int64), not_hidden)
        return self._mesh_counts


@dataclass(frozen=True)
class ScoreTerm:
    """One named score term.

    Attributes:
        name: The name in the ``score_terms`` parameter, in ViewCandidates.term_names and the
            regression goldens (key ``s_<name>``); its weight is the parameter ``weight_<name>``.
        default_weight: The weight when the parameter is not set.
        description: One line: what the term measures (ends up in the weight's description).
        compute: context -> (C,) float64 values in [0, 1], higher is better.
    """

    name: str
    default_weight: float
    description: str
    compute: Callable[[ScoringContext], np.ndarray]


_REGISTRY: Dict[str, ScoreTerm] = {}


def register_term(term: ScoreTerm) -> ScoreTerm:
    """Add a term to the registry; returns it.

    Raises:
        ValueError: the name is empty, not an identifier (it becomes part of a parameter name), or taken.
    """
    if not term.name.isidentifier():
        raise ValueError(f"score term name {term.name!r} must be an identifier (it names weight_{term.name})")
    if term.name in _REGISTRY:
        raise ValueError(f"score term {term.name!r} is already registered")
    _REGISTRY[term.name] = term
    return term


def score_term(name: str, default_weight: float, description: str) -> Callable:
    """Decorator form of register_term for a compute function: ``@score_term("area", 0.14, "...")``."""

    def register(compute: Callable[[ScoringContext], np.ndarray]) -> Callable[[ScoringContext], np.ndarray]:
        register_term(ScoreTerm(name, float(default_weight), description, compute))
        return compute

    return register


def unregister_term(name: str) -> None:
    """Remove a term (tests that register a throwaway term clean up with it)."""
    _REGISTRY.pop(name, None)


def get_term(name: str) -> ScoreTerm:
    """The registered term of that name.

    Raises:
        KeyError: no such term (the message lists the registered ones).
    """
    if name not in _REGISTRY:
        raise KeyError(f"unknown score term {name!r}; registered: {sorted(_REGISTRY)}")
    return _REGISTRY[name]


def registered_terms() -> List[ScoreTerm]:
    """Every registered term, by name."""
    return [_REGISTRY[name] for name in sorted(_REGISTRY)]


def weight_parameter(name: str) -> str:
    """The parameter holding a term's weight: ``weight_<name>``."""
    return "weight_" + name
