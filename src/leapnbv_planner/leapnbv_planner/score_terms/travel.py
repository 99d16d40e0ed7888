"""S_t (travel): how little the robot drives to a candidate (docs/ALGORITHMS.md §7)."""

from __future__ import annotations

import numpy as np

from leapnbv_planner.score_terms.base import ScoringContext, score_term


@score_term("travel", 0.05, "S_t, 1 - path length / travel scale (shorter drives score higher)")
def travel(context: ScoringContext) -> np.ndarray:
    """1 - min(1, L_c / travel_scale): L_c the path length on the floor grid when reachability ran, else the
    straight distance between the current and the candidate camera centres; no path scores 0."""
    if context.path_lengths is not None:
        lengths = context.path_lengths
    else:
        lengths = np.linalg.norm(context.positions, axis=1)
    values = 1.0 - np.minimum(1.0, lengths / context.travel_scale)
    return np.where(np.isfinite(values), values, 0.0)
