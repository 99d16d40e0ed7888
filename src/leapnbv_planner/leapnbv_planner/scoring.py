"""The next-best-view score of candidate camera poses (a weighted sum of named terms), and the choice among them."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import List, Mapping, Optional, Sequence, Tuple

import numpy as np

from leapnbv_planner.arrays import Array
from leapnbv_planner.params import PlannerParams, nbv_params_class
from leapnbv_planner.requirements import BODY_MESH, SurfacePoints
from leapnbv_planner.score_terms import (
    ScoringContext,
    ScoringInputError,
    declared_requirements,
    get_term,
    registered_terms,
)

# Two scores within this of each other are a tie (broken by distance to the current pose).
SCORE_TIE_TOLERANCE = 1e-9

__all__ = ["SCORE_TIE_TOLERANCE", "CandidateScores", "ScoringInputError", "choose_best", "score_candidates",
           "score_context", "warm_up_scoring"]


@dataclass
class CandidateScores:
    """Scores of C candidate views under T named terms.

    Attributes:
        term_names: the T terms, in the order they were summed.
        term_weights: (T,) float64 weights.
        term_scores: (C, T) float64 term values (column t: term_names[t]).
        score: (C,) float64 sum over t of term_weights[t] * term_scores[:, t], summed in term order.
    """

    term_names: List[str]
    term_weights: Array
    term_scores: Array
    score: Array

    def term(self, name: str) -> Array:
        """(C,) values of one term.

        Raises:
            KeyError: no term of that name was scored.
        """
        if name not in self.term_names:
            raise KeyError(f"no score term {name!r}; terms are {self.term_names}")
        return self.term_scores[:, self.term_names.index(name)]


def default_terms() -> List[Tuple[str, float]]:
    """(name, weight) of the deployed terms: the defaults of the nbv node's parameters."""
    return nbv_params_class()().term_weights()


def score_candidates(
    target_points: Array,
    background_points: Array,
    rotations: Array,
    positions: Array,
    K: Array,
    width: int,
    height: int,
    terms: Optional[Sequence[Tuple[str, float]]] = None,
    delta_px: float = 4.0,
    given: Optional[Mapping[str, object]] = None,
    params: Optional[PlannerParams] = None,
) -> CandidateScores:
    """Score C candidate views of the target.

    score = sum over the terms, in their order, of weight * term value (with the deployed terms
    w_v S_v + w_a S_a + w_o S_o, summed left to right). The terms are those of
    :mod:`leapnbv_planner.score_terms` (S_v visibility, S_a area, S_o occlusion, see each module
    for its definition); they share one :class:`ScoringContext`, so the occlusion kernel runs at
    most once whatever the terms. The first call compiles the kernels (see warm_up_scoring).
    :func:`leapnbv_planner.plan.plan_views` scores through :func:`score_context` with the
    requirements computed from its inputs; here the caller gives them.

    Args:
        target_points: (N, 3) target (person) points, observation frame.
        background_points: (K, 3) other scene points (K may be 0).
        rotations: (C, 3, 3) candidate camera-to-observation rotations.
        positions: (C, 3) candidate camera centres.
        K: (3, 3) intrinsics of the candidate views.
        width, height: image size in pixels.
        terms: (name, weight) pairs in summation order; the deployed terms and weights when None.
        delta_px: occlusion neighbourhood half-width in pixels (floored to an integer).
        given: requirement values by name (:mod:`leapnbv_planner.requirements`), e.g.
            ``{"target_line_of_sight": (C,) shares, "path_lengths": (C,) metres, "body_mesh":
            SurfacePoints(vertices, normals)}``; a requirement not given is absent (None) for the terms.
        params: what the terms read of the planner's parameters (the travel term's max_path_length, S_v's
            visibility_points); the robot's defaults when None.

    Returns:
        CandidateScores with (C,) score and (C, T) term values.

    Raises:
        ScoringInputError: a shape, intrinsic, image size, delta_px or given value is invalid.
        KeyError: an unknown term name.
        ValueError: a given value or a term's requirement names no registered requirement.
    """
    terms = default_terms() if terms is None else list(terms)
    if params is None:
        params = nbv_params_class()()
    declared = declared_requirements([get_term(name) for name, _ in terms], params) | frozenset(given or {})
    context = ScoringContext(target_points, background_points, rotations, positions, K, width, height,
                             delta_px=delta_px, params=params, given=given, declared=declared)
    return score_context(context, terms)


def score_context(context: ScoringContext, terms: Sequence[Tuple[str, float]]) -> CandidateScores:
    """The weighted sum of the terms, in their order, over one context's candidates.

    Raises:
        KeyError: an unknown term name.
        ScoringInputError: a term gave values of the wrong shape, or read a requirement it did not declare.
    """
    computes = [get_term(name).compute for name, _ in terms]
    columns = []
    score = np.zeros(context.num_candidates)
    for index, ((_, weight), compute) in enumerate(zip(terms, computes)):
        values = np.asarray(compute(context), dtype=np.float64).reshape(-1)
        if values.shape != (context.num_candidates,):
            raise ScoringInputError(f"score term {terms[index][0]!r} gave shape {values.shape},"
                                    f" not ({context.num_candidates},)")
        columns.append(values)
        # The first term starts the sum, so the float arithmetic is ((w0 t0 + w1 t1) + w2 t2).
        score = weight * values if index == 0 else score + weight * values
    return CandidateScores(
        term_names=[name for name, _ in terms],
        term_weights=np.array([float(weight) for _, weight in terms], dtype=np.float64),
        term_scores=np.column_stack(columns) if columns else np.zeros((context.num_candidates, 0)),
        score=np.asarray(score, dtype=np.float64),
    )


def choose_best(
    scores: Array,
    feasible: Array,
    positions: Array,
    current_position: Array,
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
    """Compile the kernels of every registered term now (a node calls this at start-up, not on frame one).

    Once without a body mesh, once with one (the mesh kernels: S_v's framing, the mesh S_o).
    """
    for given in (None, {BODY_MESH.name: SurfacePoints(np.array([[0.0, 0.0, 2.0]]), np.array([[0.0, 0.0, -1.0]]))}):
        score_candidates(
            np.array([[0.0, 0.0, 2.0]]),
            np.array([[0.0, 0.0, 1.0]]),
            np.eye(3)[None],
            np.zeros((1, 3)),
            np.array([[100.0, 0.0, 50.0], [0.0, 100.0, 50.0], [0.0, 0.0, 1.0]]),
            100,
            100,
            terms=[(term.name, 1.0) for term in registered_terms()],
            given=given,
            params=dataclasses.replace(nbv_params_class()(), visibility_points="body_mesh"),
        )
