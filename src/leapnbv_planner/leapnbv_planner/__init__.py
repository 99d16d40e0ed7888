"""Next-best-view candidate ring, S_v/S_a/S_o scoring and the nbv node."""

from __future__ import annotations

from leapnbv_planner.candidates import (
    CandidateGenerationError,
    CandidateRingParams,
    CandidateSet,
    FeasibilityReason,
    FeasibilityResult,
    camera_look_at,
    check_feasibility,
    generate_candidates,
)
from leapnbv_planner.scoring import (
    CandidateScores,
    ScoreWeights,
    ScoringInputError,
    bounding_box_area_fraction,
    choose_best,
    score_candidates,
    warm_up_scoring,
)

__all__ = [
    "CandidateGenerationError",
    "CandidateRingParams",
    "CandidateScores",
    "CandidateSet",
    "FeasibilityReason",
    "FeasibilityResult",
    "ScoreWeights",
    "ScoringInputError",
    "bounding_box_area_fraction",
    "camera_look_at",
    "check_feasibility",
    "choose_best",
    "generate_candidates",
    "score_candidates",
    "warm_up_scoring",
]
