"""Next-best-view planning: candidate ring, feasibility, named score terms, one-call plan_views, nbv node.

The entry points: :func:`plan_views` plans one frame without ROS; :class:`PlannerParams` (with the
term weights: :func:`default_nbv_params`) holds every setting; :func:`score_term` registers a term.
"""

from __future__ import annotations

from leapnbv_planner.params import PlannerParams, default_nbv_params
from leapnbv_planner.plan import Plan, plan_views
from leapnbv_planner.score_terms import score_term

__all__ = ["Plan", "PlannerParams", "default_nbv_params", "plan_views", "score_term"]
