"""S_o: the share of the framed target points that nothing hides (docs/ALGORITHMS.md §7: a square
pixel window, camera z as depth)."""

from __future__ import annotations

from typing import Optional

import numpy as np

from leapnbv_planner.arrays import Array
from leapnbv_planner.requirements import TARGET_COUNTS, TARGET_LINE_OF_SIGHT
from leapnbv_planner.score_terms.base import ScoringContext, score_term


@score_term("occlusion", 0.83, "S_o, share of in-view target points not hidden",
            requires=(TARGET_COUNTS, TARGET_LINE_OF_SIGHT))
def occlusion(context: ScoringContext) -> Array:
    """S_o = (# in-view target points not hidden) / (# in-view target points), 0 when none is in view.

    With pixel (i, j) = (floor(u), floor(v)) and h = floor(delta_px), an in-view target point of
    depth z_t is hidden when some background point with z_b > 0 has its pixel within the square
    window |i_b - i| <= h, |j_b - j| <= h and z_b < z_t (depth is the optical-axis z, not the
    range). Background points outside the image still count inside the window. S_o is kept
    separate from S_v on purpose: S_v measures framing, S_o occlusion of what is framed.
    With the obstacle map (requirement ``target_line_of_sight``: the share of target points each
    candidate sees through free space of the robot's obstacle map, see
    :mod:`leapnbv_planner.obstacle_map`) S_o is multiplied by it: the background only holds what
    the current view saw, the map also what it did not.
    """
    in_view, not_hidden = context.visible_counts()
    return not_hidden_share(in_view, not_hidden, context.need(TARGET_LINE_OF_SIGHT))


def not_hidden_share(counted: Array, not_hidden: Array, clear: Optional[Array]) -> Array:
    """not_hidden / counted per candidate (0 where nothing is counted), times the clear share when given."""
    values = np.where(counted > 0, not_hidden / np.maximum(counted, 1), 0.0)
    if clear is not None:
        values = values * clear
    return np.asarray(values, dtype=np.float64)
