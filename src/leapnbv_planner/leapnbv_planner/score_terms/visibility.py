"""S_v: the share of the target's points that a candidate view frames (docs/ALGORITHMS.md §7)."""

from __future__ import annotations

import numpy as np

from leapnbv_planner.arrays import Array
from leapnbv_planner.score_terms.base import ScoringContext, score_term


@score_term("visibility", 0.03, "S_v, share of target points in view")
def visibility(context: ScoringContext) -> Array:
    """S_v = (# target points with z > 0, 0 <= u < W, 0 <= v < H) / (# target points); 0 without target points."""
    in_view = context.in_view_counts()
    num_targets = context.num_targets
    values = in_view / float(num_targets) if num_targets else np.zeros(len(in_view))
    return np.asarray(values, dtype=np.float64)
