"""S_t (travel): how little the robot drives to a candidate (docs/ALGORITHMS.md §7)."""

from __future__ import annotations

import numpy as np

from leapnbv_planner.arrays import Array
from leapnbv_planner.requirements import PATH_LENGTHS
from leapnbv_planner.score_terms.base import ScoringContext, score_term


@score_term("travel", 0.05, "S_t, 1 - path length / travel scale (shorter drives score higher)",
            requires=(PATH_LENGTHS,))
def travel(context: ScoringContext) -> Array:
    """1 - min(1, L_c / max_path_length): L_c the path length on the floor grid when reachability ran, else the
    straight distance between the current and the candidate camera centres; no path scores 0."""
    lengths = context.need(PATH_LENGTHS)
    if lengths is None:
        lengths = np.linalg.norm(context.positions, axis=1)
    values = 1.0 - np.minimum(1.0, lengths / float(context.params.max_path_length))
    return np.asarray(np.where(np.isfinite(values), values, 0.0), dtype=np.float64)
