"""Next-best-view planning: candidate ring, feasibility, named score terms, one-call plan_views, nbv node.

The entry points: :func:`plan_views` plans one frame without ROS from one :class:`PlanInputs`;
:class:`PlannerParams` (with the term weights: :func:`default_nbv_params`) holds every setting;
:func:`score_term` registers a term and :func:`requirement` what a term reads beyond the candidate
poses and the clouds (:mod:`leapnbv_planner.requirements`).
"""

from __future__ import annotations

from leapnbv_planner.inputs import CameraInMap, PlanFloor, PlanInputs, PlanTarget
from leapnbv_planner.params import PlannerParams, default_nbv_params
from leapnbv_planner.plan import Plan, plan_views
from leapnbv_planner.requirements import requirement
from leapnbv_planner.score_terms import score_term

__all__ = ["CameraInMap", "Plan", "PlanFloor", "PlanInputs", "PlanTarget", "PlannerParams", "default_nbv_params",
           "plan_views", "requirement", "score_term"]
