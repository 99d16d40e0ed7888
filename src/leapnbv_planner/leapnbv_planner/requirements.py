"""What a score term reads beyond the candidate poses and the frame's clouds: named requirements.

A score term declares the requirements it may read (``@score_term(..., requires=(PATH_LENGTHS,))``).
Each requirement is computed by its provider the first time a term of the plan reads it
(:meth:`leapnbv_planner.score_terms.ScoringContext.need`), once per plan, and never when no chosen
term declares it: the target points' line of sight through the obstacle map is walked only for a
term that reads it. A term that reads a requirement it did not declare is refused, so the
declarations stay true.

A provider computes from the :class:`leapnbv_planner.score_terms.ScoringContext`: the scored
candidates' poses, the clouds, the parameters and, inside a plan, ``context.frame`` (a
:class:`PlanFrame`: the :class:`leapnbv_planner.inputs.PlanInputs` as the caller gave them and what
the plan made of them before scoring). It returns one value for the scored candidates, or None when
the frame does not have it (no obstacle map, no body mesh, no path search). A caller without a plan
(:func:`leapnbv_planner.scoring.score_candidates`) gives the values by name instead; the
requirement's ``check`` validates either.

The built-in requirements:

- ``body_mesh`` (:data:`BODY_MESH`): the person's metric body mesh as vertices and outward normals.
- ``path_lengths`` (:data:`PATH_LENGTHS`): metres of the robot's free path to each candidate.
- ``target_line_of_sight`` (:data:`TARGET_LINE_OF_SIGHT`) and ``mesh_line_of_sight``
  (:data:`MESH_LINE_OF_SIGHT`): the obstacle map's clear line-of-sight share of the target points,
  and of the body mesh's vertices, from each candidate.
- ``target_counts`` (:data:`TARGET_COUNTS`): the occlusion kernel's in-view and not-hidden counts of
  the target points (a term that declares it lets S_v take its counts from the same kernel call).

A new requirement is a provider registered with :func:`requirement` (in the module of the term that
reads it, or any module imported before planning); a new input it computes from is a field of
:class:`leapnbv_planner.inputs.PlanInputs`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Callable, Generic, Optional, Tuple, TypeVar

import numpy as np

from leapnbv_common.registry import Registry
from leapnbv_planner.arrays import Array
from leapnbv_planner.mesh_kernel import mesh_vertex_normals
from leapnbv_planner.obstacle_map import line_of_sight_clear_fraction

if TYPE_CHECKING:  # only for annotations: these modules import the score terms, which import this one
    from leapnbv_planner.candidates import CandidateSet
    from leapnbv_planner.inputs import PlanInputs
    from leapnbv_planner.score_terms.base import ScoringContext

T = TypeVar("T")

__all__ = ["BODY_MESH", "MESH_LINE_OF_SIGHT", "PATH_LENGTHS", "REQUIREMENTS", "TARGET_COUNTS",
           "TARGET_LINE_OF_SIGHT", "PlanFrame", "Requirement", "ScoringInputError", "SurfacePoints",
           "get_requirement", "register_requirement", "requirement"]


class ScoringInputError(ValueError):
    """Raised when an input of the scoring has the wrong shape or an invalid value."""


@dataclass(frozen=True)
class PlanFrame:
    """What a provider computes from inside a plan: the inputs as given, and what the plan made of them.

    Attributes:
        inputs: the plan's :class:`leapnbv_planner.inputs.PlanInputs`, passed through unchanged (a new
            input is a new field there).
        candidates: every candidate of the plan (the scored ones are ``candidates[picked]``).
        picked: (S,) int64 indices of the scored candidates, the rows of every requirement's value.
        target_points: (N, 3) float64 target points (the frame's, as the scoring reads them).
        path_lengths: (C,) metres of the free path to every candidate (0 for the current view, inf:
            none), None when reachability is off.
    """

    inputs: PlanInputs
    candidates: CandidateSet
    picked: Array
    target_points: Array
    path_lengths: Optional[Array] = None


@dataclass(frozen=True)
class SurfacePoints:
    """Points on a surface with their outward unit normals: (V, 3) float64 each, all finite."""

    points: Array
    normals: Array


@dataclass(frozen=True)
class Requirement(Generic[T]):
    """One named input of score terms and how it is computed.

    Attributes:
        name: What a term declares and a caller names in ``score_candidates(given=...)``.
        description: One line: what the value is.
        provide: context -> the value for the context's candidates, or None when the frame lacks it.
        check: (value, number of candidates) -> the value validated (and converted), raising
            :class:`ScoringInputError`; applied to provided and given values alike.
    """

    name: str
    description: str
    provide: Callable[[ScoringContext], Optional[T]]
    check: Optional[Callable[[Any, int], T]] = None

    def accept(self, value: object, num_candidates: int) -> Optional[T]:
        """``value`` checked for ``num_candidates`` candidates (None stays None: the frame lacks it).

        Raises:
            ScoringInputError: the value is invalid (the requirement's check).
        """
        if value is None:
            return None
        if self.check is None:
            return value  # type: ignore[return-value]  # unchecked requirement: the provider's own type
        return self.check(value, num_candidates)


def _check_requirement(entry: object) -> None:
    if not isinstance(entry, Requirement):
        raise TypeError(f"a score-term requirement must be a Requirement, got {entry!r}")
    if not entry.name.isidentifier():
        raise ValueError(f"requirement name {entry.name!r} must be an identifier")


REQUIREMENTS: Registry[Requirement[Any]] = Registry("score-term requirement", check=_check_requirement)


def register_requirement(entry: Requirement[T]) -> Requirement[T]:
    """Make a requirement declarable by its name; returns it.

    Raises:
        ValueError: the name is not an identifier, or already registered.
    """
    REQUIREMENTS.register(entry.name, entry)
    return entry


def requirement(name: str, description: str, check: Optional[Callable[[Any, int], T]] = None
                ) -> Callable[[Callable[[ScoringContext], Optional[T]]], Requirement[T]]:
    """Decorator that registers a provider as the requirement ``name`` and returns the Requirement."""

    def register(provide: Callable[[ScoringContext], Optional[T]]) -> Requirement[T]:
        return register_requirement(Requirement(name, description, provide, check))

    return register


def get_requirement(name: str) -> Requirement[Any]:
    """The registered requirement called ``name``.

    Raises:
        ValueError: an unknown name (the message lists the known ones).
    """
    return REQUIREMENTS.get(name)


def check_shares(value: object, num_candidates: int, name: str) -> Array:
    """(C,) float64 values in [0, 1], one per candidate."""
    shares = np.asarray(value, dtype=np.float64).reshape(-1)
    if shares.shape != (num_candidates,) or not np.all((shares >= 0.0) & (shares <= 1.0)):
        raise ScoringInputError(f"{name} must be {num_candidates} values in [0, 1], got shape {shares.shape}")
    return shares


def _check_path_lengths(value: object, num_candidates: int) -> Array:
    lengths = np.asarray(value, dtype=np.float64).reshape(-1)
    if lengths.shape != (num_candidates,) or np.any(np.isnan(lengths)) or np.any(lengths < 0.0):
        raise ScoringInputError(f"path_lengths must be {num_candidates} values >= 0, got shape {lengths.shape}")
    return lengths


def _check_surface(value: object, num_candidates: int) -> SurfacePoints:
    """Vertices and normals of one shape, contiguous float64; rows with a non-finite value dropped."""
    if not isinstance(value, SurfacePoints):
        raise ScoringInputError(f"body_mesh must be SurfacePoints (vertices, normals), got {type(value).__name__}")
    vertices = np.ascontiguousarray(value.points, dtype=np.float64)
    normals = np.ascontiguousarray(value.normals, dtype=np.float64)
    if vertices.ndim != 2 or vertices.shape[1] != 3 or normals.shape != vertices.shape:
        raise ScoringInputError(f"body_mesh vertices must be (V, 3) with normals of the same shape, got "
                                f"{vertices.shape} and {normals.shape}")
    if np.isfinite(vertices).all() and np.isfinite(normals).all():  # the usual case: no copies
        return SurfacePoints(vertices, normals)
    keep = np.all(np.isfinite(vertices), axis=1) & np.all(np.isfinite(normals), axis=1)
    return SurfacePoints(vertices[keep], normals[keep])


def _line_of_sight(context: ScoringContext, points: Array) -> Optional[Array]:
    """The map's clear line-of-sight share of ``points`` from each scored candidate; None without map and pose."""
    frame = context.frame
    if frame is None or frame.inputs.obstacle_map is None or frame.inputs.camera_pose is None:
        return None
    pose, params = frame.inputs.camera_pose, frame.inputs.params
    return line_of_sight_clear_fraction(frame.inputs.obstacle_map, np.asarray(pose.rotation, dtype=np.float64),
                                        np.asarray(pose.position, dtype=np.float64), context.positions, points,
                                        params.map_max_target_points, params.map_target_margin)


@requirement("body_mesh", "the person's metric body mesh: vertices and outward normals, observation frame",
             _check_surface)
def _body_mesh(context: ScoringContext) -> Optional[SurfacePoints]:
    if context.frame is None or context.frame.inputs.body_mesh is None:
        return None
    vertices, faces = context.frame.inputs.body_mesh
    vertices = np.asarray(vertices, dtype=np.float64)
    return SurfacePoints(vertices, mesh_vertex_normals(vertices, faces))


@requirement("path_lengths", "metres of the robot's free path to each candidate (inf: no path)",
             _check_path_lengths)
def _path_lengths(context: ScoringContext) -> Optional[Array]:
    if context.frame is None or context.frame.path_lengths is None:
        return None
    return context.frame.path_lengths[context.frame.picked]


@requirement("target_line_of_sight", "the obstacle map's clear line-of-sight share of the target points",
             lambda value, count: check_shares(value, count, "target_line_of_sight"))
def _target_line_of_sight(context: ScoringContext) -> Optional[Array]:
    if context.frame is None:
        return None
    return _line_of_sight(context, context.frame.target_points)


@requirement("mesh_line_of_sight", "the obstacle map's clear line-of-sight share of the body mesh's vertices",
             lambda value, count: check_shares(value, count, "mesh_line_of_sight"))
def _mesh_line_of_sight(context: ScoringContext) -> Optional[Array]:
    if context.frame is None or context.frame.inputs.body_mesh is None:
        return None
    # The mesh's vertices as given (the walk drops non-finite ones itself).
    return _line_of_sight(context, np.asarray(context.frame.inputs.body_mesh[0], dtype=np.float64))


def _target_counts(context: ScoringContext) -> Tuple[Array, Array]:
    return context.visible_counts()


BODY_MESH: Requirement[SurfacePoints] = _body_mesh
PATH_LENGTHS: Requirement[Array] = _path_lengths
TARGET_LINE_OF_SIGHT: Requirement[Array] = _target_line_of_sight
MESH_LINE_OF_SIGHT: Requirement[Array] = _mesh_line_of_sight
TARGET_COUNTS: Requirement[Tuple[Array, Array]] = register_requirement(Requirement(
    "target_counts", "(in_view, not_hidden) (C,) int64 counts of the target points (occlusion kernel)", _target_counts))
