"""Score terms of the next-best-view score, one module each, registered by name.

Adding a term: a module here that registers it (``@score_term(name, default_weight, description,
requires=(...))`` on a function ``context -> (C,) values``, ``requires`` naming what it reads beyond
the candidate poses and the clouds: :mod:`leapnbv_planner.requirements`), its weight and its name in
``score_terms`` in the params file, and its test. Nothing else changes: this package imports every
module in it, the node declares ``weight_<name>`` from the registry
(:func:`leapnbv_planner.params.nbv_params_class`), ``plan_views`` computes the requirements the
chosen terms declare, and the score and the ViewCandidates message carry whichever terms
``score_terms`` lists. A term that needs a new input adds a requirement provider and a field of
:class:`leapnbv_planner.inputs.PlanInputs`.
"""

from __future__ import annotations

import importlib
import pkgutil

from leapnbv_planner.score_terms.base import (
    TERMS,
    ScoreTerm,
    ScoringContext,
    ScoringInputError,
    declared_requirements,
    get_term,
    missing_requirement_detail,
    register_term,
    registered_terms,
    score_term,
    unregister_term,
    weight_parameter,
)

# Every module of this package but base defines and registers one term.
for _module in pkgutil.iter_modules(__path__):
    if _module.name != "base":
        importlib.import_module(f"{__name__}.{_module.name}")

__all__ = [
    "TERMS",
    "ScoreTerm",
    "ScoringContext",
    "ScoringInputError",
    "declared_requirements",
    "get_term",
    "missing_requirement_detail",
    "register_term",
    "registered_terms",
    "score_term",
    "unregister_term",
    "weight_parameter",
]
