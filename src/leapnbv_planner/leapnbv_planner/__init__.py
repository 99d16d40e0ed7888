"""Next-best-view planning: candidate ring, feasibility, named score terms, one-call plan_views, nbv node."""

from __future__ import annotations

from leapnbv_planner.candidates import (
    CandidateGenerationError,
    CandidateSet,
    FeasibilityReason,
    FeasibilityResult,
    camera_look_at,
    check_feasibility,
    generate_candidates,
)
from leapnbv_planner.params import (
    DEFAULT_SCORE_TERMS,
    CandidateRingParams,
    PlannerParams,
    default_nbv_params,
    nbv_params_class,
)
from leapnbv_planner.plan import Plan, PlanInputError, base_goal_frame, plan_views
from leapnbv_planner.score_terms import (
    ScoreTerm,
    ScoringContext,
    ScoringInputError,
    get_term,
    register_term,
    registered_terms,
    score_term,
    unregister_term,
)
from leapnbv_planner.score_terms.area import bounding_box_area_fraction
from leapnbv_planner.scoring import CandidateScores, choose_best, score_candidates, warm_up_scoring

__all__ = [
    "DEFAULT_SCORE_TERMS",
    "CandidateGenerationError",
    "CandidateRingParams",
    "CandidateScores",
    "CandidateSet",
    "FeasibilityReason",
    "FeasibilityResult",
    "Plan",
    "PlanInputError",
    "PlannerParams",
    "ScoreTerm",
    "ScoringContext",
    "ScoringInputError",
    "base_goal_frame",
    "bounding_box_area_fraction",
    "camera_look_at",
    "check_feasibility",
    "choose_best",
    "default_nbv_params",
    "generate_candidates",
    "get_term",
    "nbv_params_class",
    "plan_views",
    "register_term",
    "registered_terms",
    "score_candidates",
    "score_term",
    "unregister_term",
    "warm_up_scoring",
]
