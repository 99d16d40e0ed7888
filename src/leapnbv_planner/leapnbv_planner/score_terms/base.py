"""What a score term is, the scoring context every term computes from, and the registry of terms by name.

A score term maps C candidate views to C numbers in [0, 1]; the planner's score is the weighted sum
of the terms named by the ``score_terms`` parameter, in that order (see
:func:`leapnbv_planner.scoring.score_candidates`). A term is registered once, by the module that
defines it (one module per term in this package; the package imports them all), with the
requirements it reads beyond the candidate poses and the clouds (:mod:`leapnbv_planner.requirements`).
The context validates the inputs once, computes each requirement the first time a term reads it,
and shares the expensive per-candidate counts between terms: the occlusion kernel gives both the
in-view and the not-hidden counts in one call, made at most once per context, whichever term asks first.

Camera coordinates: (x, y, z) = R^T (p - t) for a candidate with rotation R (columns = the
candidate's axes in the observation frame) and centre t. Projection of a point with z > 0:
u = fx (x/z) + skew (y/z) + cx, v = fy (y/z) + cy, pixel (floor(u), floor(v)).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import (
    TYPE_CHECKING,
    AbstractSet,
    Any,
    Callable,
    Dict,
    FrozenSet,
    Iterable,
    List,
    Mapping,
    Optional,
    Sequence,
    Tuple,
    TypeVar,
    Union,
    cast,
)

import numpy as np

from leapnbv_common.registry import Registry
from leapnbv_planner.arrays import Array
from leapnbv_planner.occlusion_kernel import (
    POINTS_PER_BOX,
    RUN_LENGTH,
    bucket_points,
    count_framed_bucketed,
    count_visible_targets_bucketed,
    possible_occluders,
    run_facing_bounds,
)
from leapnbv_planner.requirements import (
    BODY_MESH,
    TARGET_COUNTS,
    PlanFrame,
    Requirement,
    ScoringInputError,
    get_requirement,
)

if TYPE_CHECKING:  # params imports this package (the term weights are its fields)
    from leapnbv_planner.params import PlannerParams

T = TypeVar("T")
# (fx, skew, cx, fy, cy, width, height) of validated intrinsics and image size.
Camera = Tuple[float, float, float, float, float, int, int]
# A cloud sorted into boxes by leapnbv_planner.occlusion_kernel.bucket_points: (points, companions, cell_runs,
# cell_boxes, run_starts, run_boxes).
Buckets = Tuple[Array, Array, Array, Array, Array, Array]
_NO_ROWS = np.zeros((0, 3))

__all__ = ["Camera", "ScoreTerm", "ScoringContext", "ScoringInputError", "check_camera", "check_poses",
           "declared_requirements", "finite_points", "get_term", "missing_requirement_detail", "register_term",
           "registered_terms", "score_term", "unregister_term", "weight_parameter"]


def finite_points(points: object, name: str) -> Array:
    """Return the finite rows of an (M, 3) array as contiguous float64."""
    array = np.asarray(points, dtype=np.float64)
    if array.ndim != 2 or array.shape[1] != 3:
        raise ScoringInputError(f"{name} must have shape (M, 3), got {array.shape}")
    finite = np.isfinite(array)
    if finite.all():  # the usual case: skip the row mask and the copy it would need
        return np.ascontiguousarray(array)
    return np.ascontiguousarray(array[np.all(finite, axis=1)])


def check_poses(rotations: object, positions: object) -> Tuple[Array, Array]:
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
    """The validated inputs of one scoring call, the requirements terms read, and the results terms share.

    Rows with a non-finite coordinate are dropped from both clouds before anything is counted.

    Args:
        target_points: (N, 3) target (person) points, observation frame.
        background_points: (K, 3) other scene points (K may be 0).
        rotations: (C, 3, 3) candidate camera-to-observation rotations.
        positions: (C, 3) candidate camera centres.
        K: (3, 3) intrinsics of the candidate views.
        width, height: image size in pixels.
        delta_px: occlusion neighbourhood half-width in pixels (floored to an integer).
        params: the planner's parameters (what a term reads of them, e.g. the travel term's scale
            max_path_length); the robot's defaults when None.
        given: requirement values by name, for these candidates (a caller without a plan); each is
            checked by its requirement.
        frame: inside a plan, what the requirements are computed from (its inputs and candidates).
        declared: the requirements the chosen terms declare; reading another one raises. None (a context
            built by hand): any requirement may be read.

    Raises:
        ScoringInputError: a shape, intrinsic, image size, delta_px or given value is invalid.
        ValueError: a given value names no registered requirement.
    """

    def __init__(self, target_points: Array, background_points: Array, rotations: Array, positions: Array,
                 K: Array, width: int, height: int, delta_px: float = 4.0, params: Optional[PlannerParams] = None,
                 given: Optional[Mapping[str, object]] = None, frame: Optional[PlanFrame] = None,
                 declared: Optional[AbstractSet[str]] = None) -> None:
        self.targets = finite_points(target_points, "target_points")
        self.background = finite_points(background_points, "background_points")
        self.rotations, self.positions = check_poses(rotations, positions)
        self.camera: Camera = check_camera(K, width, height)
        if not (np.isfinite(delta_px) and delta_px >= 0.0):
            raise ScoringInputError(f"delta_px must be a finite number >= 0, got {delta_px}")
        self.half_window = int(np.floor(delta_px))
        if params is None:
            from leapnbv_planner.params import default_nbv_params  # at call time: params imports this module

            params = default_nbv_params()
        self.params: PlannerParams = params
        self.frame = frame
        self.declared: Optional[FrozenSet[str]] = None if declared is None else frozenset(declared)
        self._values: Dict[str, object] = {}
        for name, value in (given or {}).items():
            self._values[name] = get_requirement(name).accept(value, self.num_candidates)
        self._buckets: Dict[str, Buckets] = {}
        self._mesh_counts: Optional[Tuple[Array, Array]] = None
        self._in_view: Optional[Array] = None
        self._mesh_framed: Optional[Array] = None
        self._counts: Optional[Tuple[Array, Array]] = None
        self.kernel_calls = 0

    @property
    def num_candidates(self) -> int:
        return int(self.rotations.shape[0])

    @property
    def num_targets(self) -> int:
        return int(self.targets.shape[0])

    def need(self, requirement: Requirement[T]) -> Optional[T]:
        """The requirement's value for these candidates (computed on the first read), None when the frame
        lacks it (no obstacle map, no body mesh, no path search).

        Raises:
            ScoringInputError: no chosen term declares it, or its provider gave an invalid value.
        """
        name = requirement.name
        if self.declared is not None and name not in self.declared:
            raise ScoringInputError(f"requirement {name!r} was read, but no chosen score term declares it "
                                    f"(declared: {sorted(self.declared)})")
        if name not in self._values:
            self._values[name] = requirement.accept(requirement.provide(self), self.num_candidates)
        return cast(Optional[T], self._values[name])

    def declares(self, requirement: Requirement[Any]) -> bool:
        """A chosen term may read the requirement (or its value was given)."""
        return requirement.name in self._values or (self.declared is not None and requirement.name in self.declared)

    def computed(self) -> Dict[str, object]:
        """The requirement values given or computed so far, by name (None: the frame lacks it)."""
        return dict(self._values)

    def buckets(self, name: str) -> Buckets:
        """The cloud ``name`` ("targets", "background", "mesh" with its normals, "none": no points) sorted into
        boxes once per context (the kernels skip or count whole boxes per candidate). The background keeps only
        the points that can hide a target point or mesh vertex from a candidate (``possible_occluders``: the
        counts are the same)."""
        if name not in self._buckets:
            mesh = self.need(BODY_MESH) if name in ("mesh", "background") and self.declares(BODY_MESH) else None
            if name == "mesh" and mesh is not None:
                points, companions = mesh.points, mesh.normals
            elif name == "background":  # only the points that can hide a target or mesh point from a candidate
                fx, skew, _, fy, _, _, _ = self.camera
                points = possible_occluders(self.background, self.positions, [self.targets] + (
                    [mesh.points] if mesh is not None else []), fx, skew, fy, self.half_window)
                companions = _NO_ROWS
            else:
                points = {"targets": self.targets}.get(name, _NO_ROWS)
                companions = _NO_ROWS
            self._buckets[name] = bucket_points(np.ascontiguousarray(points), np.ascontiguousarray(companions),
                                                POINTS_PER_BOX, RUN_LENGTH)
        return self._buckets[name]

    def _kernel_counts(self, targets: str, background: str) -> Tuple[Array, Array]:
        """(in_view, not_hidden) of :func:`leapnbv_planner.occlusion_kernel.count_visible_targets_bucketed`."""
        fx, skew, cx, fy, cy, width, height = self.camera
        target_points, target_normals, target_cell_runs, target_cell_boxes, target_run_starts, target_run_boxes = \
            self.buckets(targets)
        background_points, _, *background_boxes = self.buckets(background)
        facing = (run_facing_bounds(target_points, target_normals, target_run_starts) if len(target_normals)
                  else np.zeros((0, 7)))
        self.kernel_calls += 1
        cell_runs, cell_boxes, run_starts, run_boxes = background_boxes
        return count_visible_targets_bucketed(
            target_points, target_normals, target_cell_runs, target_cell_boxes, target_run_starts, target_run_boxes,
            facing, background_points, cell_runs, cell_boxes, run_starts, run_boxes, self.rotations, self.positions,
            fx, skew, cx, fy, cy, width, height, self.half_window)

    def visible_counts(self) -> Tuple[Array, Array]:
        """(in_view (C,) int64, not_hidden (C,) int64), from one occlusion-kernel call per context.

        In view: z > 0 and 0 <= u < W and 0 <= v < H. Not hidden: with pixel (i, j) and
        h = floor(delta_px), no background point with z_b > 0 has its pixel within the window
        |i_b - i| <= h, |j_b - j| <= h and z_b < z_t (see the reference kernel
        ``count_visible_targets`` in the planner's tests; here its bucketed form).
        """
        if self._counts is None:
            self._counts = self._kernel_counts("targets", "background")
        return self._counts

    def in_view_counts(self) -> Array:
        """(C,) int64 target points in view: from visible_counts when it ran or a chosen term declares
        ``target_counts`` (it will run: one kernel call for both), else from a kernel call without the
        background (projection only, no occlusion test: what S_v needs when S_o is not scored)."""
        if self._counts is not None or self.declares(TARGET_COUNTS):
            return self.visible_counts()[0]
        if self._in_view is None:
            self._in_view, _ = self._kernel_counts("targets", "none")
        return self._in_view

    def mesh_framed_counts(self) -> Array:
        """(C,) int64 body mesh vertices each candidate frames: in its image and its depth range, hidden or not,
        facing it or not (:func:`leapnbv_planner.occlusion_kernel.count_framed_bucketed`), once per context.

        In view as for :meth:`in_view_counts` (z > 0, 0 <= u < W, 0 <= v < H), and
        ``visibility_min_depth <= z <= visibility_max_depth``.

        Raises:
            ScoringInputError: the context has no mesh.
        """
        mesh = self.need(BODY_MESH)
        if mesh is None:
            raise ScoringInputError("no body mesh in the scoring context")
        if self._mesh_framed is None:
            fx, skew, cx, fy, cy, width, height = self.camera
            points, _, cell_runs, cell_boxes, run_starts, run_boxes = self.buckets("mesh")
            self._mesh_framed = count_framed_bucketed(
                points, cell_runs, cell_boxes, run_starts, run_boxes, self.rotations, self.positions, fx, skew, cx,
                fy, cy, width, height, float(self.params.visibility_min_depth),
                float(self.params.visibility_max_depth))
        return self._mesh_framed

    def mesh_counts(self) -> Tuple[Array, Array]:
        """(facing (C,) int64, not_hidden (C,) int64) over the body mesh's vertices, once per context.

        Facing: vertices whose outward normal faces the candidate camera (n . (t_c - p) > 0), in view or
        not (the body's near side from there). Not hidden: facing vertices in view and not hidden by the
        background (the same window test as S_o's).

        Raises:
            ScoringInputError: the context has no mesh.
        """
        mesh = self.need(BODY_MESH)
        if mesh is None:
            raise ScoringInputError("no body mesh in the scoring context")
        if self._mesh_counts is None:
            _, not_hidden = self._kernel_counts("mesh", "background")
            # n . (t_c - v) > 0  <=>  n . t_c > n . v: one (C, 3) x (3, V) product.
            facing = np.count_nonzero(self.positions @ mesh.normals.T
                                      > np.einsum("vk,vk->v", mesh.normals, mesh.points), axis=1)
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
        requires: Names of the requirements (:mod:`leapnbv_planner.requirements`) the term may read
            with ``context.need``; only these are computed for it.
        requires_for: params -> the names of ``requires`` the term reads with those parameters (a term whose
            parameters choose what it reads, e.g. S_v's ``visibility_points``); None: all of ``requires``.
        without: What the term scores when a requirement it reads is missing from the frame, by requirement
            name (one phrase, e.g. "S_v of the observed points"): the text of ``planned_without``.
    """

    name: str
    default_weight: float
    description: str
    compute: Callable[[ScoringContext], Array]
    requires: FrozenSet[str] = field(default_factory=frozenset)
    requires_for: Optional[Callable[[PlannerParams], Iterable[str]]] = None
    without: Mapping[str, str] = field(default_factory=dict)

    def requirements(self, params: Optional[PlannerParams] = None) -> FrozenSet[str]:
        """The requirements the term reads with ``params``: all it may read (``requires``) without them.

        Raises:
            ValueError: ``requires_for`` named a requirement the term does not declare in ``requires``.
        """
        if params is None or self.requires_for is None:
            return self.requires
        names = frozenset(self.requires_for(params))
        if not names <= self.requires:
            raise ValueError(f"score term {self.name!r} reads {sorted(names - self.requires)} with these parameters, "
                             f"which it does not declare (requires: {sorted(self.requires)})")
        return names


def _check_term(term: object) -> None:
    if not isinstance(term, ScoreTerm):
        raise TypeError(f"a score term must be a ScoreTerm, got {term!r}")
    if not term.name.isidentifier():
        raise ValueError(f"score term name {term.name!r} must be an identifier (it names weight_{term.name})")


TERMS: Registry[ScoreTerm] = Registry("score term", check=_check_term)


def register_term(term: ScoreTerm) -> ScoreTerm:
    """Add a term to the registry; returns it.

    Raises:
        ValueError: the name is empty, not an identifier (it becomes part of a parameter name), or taken.
    """
    return TERMS.register(term.name, term)


def score_term(name: str, default_weight: float, description: str,
               requires: Iterable[Union[str, Requirement[Any]]] = (),
               requires_for: Optional[Callable[[PlannerParams], Iterable[str]]] = None,
               without: Optional[Mapping[str, str]] = None,
               ) -> Callable[[Callable[[ScoringContext], Array]], Callable[[ScoringContext], Array]]:
    """Decorator form of register_term for a compute function: ``@score_term("area", 0.14, "...")``;
    ``requires``: the requirements it may read (Requirement objects or their names); ``requires_for`` and
    ``without``: see :class:`ScoreTerm`."""
    names = frozenset(entry if isinstance(entry, str) else entry.name for entry in requires)

    def register(compute: Callable[[ScoringContext], Array]) -> Callable[[ScoringContext], Array]:
        register_term(ScoreTerm(name, float(default_weight), description, compute, names, requires_for,
                                dict(without or {})))
        return compute

    return register


def unregister_term(name: str) -> None:
    """Remove a term (tests that register a throwaway term clean up with it)."""
    TERMS.unregister(name)


def get_term(name: str) -> ScoreTerm:
    """The registered term of that name.

    Raises:
        KeyError: no such term (the message lists the registered ones).
    """
    if name not in TERMS:
        raise KeyError(f"unknown score term {name!r}; registered: {TERMS.names()}")
    return TERMS.get(name)


def registered_terms() -> List[ScoreTerm]:
    """Every registered term, by name."""
    return [TERMS.get(name) for name in TERMS.names()]


def declared_requirements(terms: Sequence[ScoreTerm], params: Optional[PlannerParams] = None) -> FrozenSet[str]:
    """The requirements the terms read with ``params`` (:meth:`ScoreTerm.requirements`; without params all they
    may read), each checked to be registered.

    Raises:
        ValueError: a term declares a requirement nobody registered (the message lists the known ones).
    """
    names = frozenset(name for term in terms for name in term.requirements(params))
    for name in names:
        get_requirement(name)
    return names


def missing_requirement_detail(requirement: Requirement[Any], params: PlannerParams) -> str:
    """What the chosen terms (``params.score_terms``) that read ``requirement`` score without it, joined: the
    ``planned_without`` text of a frame that lacks it, e.g. "S_v of the observed points; S_o of the observed
    points" ("" when no chosen term reads it)."""
    phrases = []
    for name in params.score_terms:
        term = get_term(name)
        if requirement.name in term.requirements(params):
            phrases.append(term.without.get(requirement.name, f"{name} without {requirement.name}"))
    return "; ".join(phrases)


def weight_parameter(name: str) -> str:
    """The parameter holding a term's weight: ``weight_<name>``."""
    return "weight_" + name
