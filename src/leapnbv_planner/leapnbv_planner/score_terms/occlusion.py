"""S_o: the share of the framed target points that nothing hides (docs/ALGORITHMS.md §7: a square
pixel window, camera z as depth)."""

from __future__ import annotations

import numpy as np

from leapnbv_planner.score_terms.base import ScoringContext, score_term


@score_term("occlusion", 0.83, "S_o, share of in-view target points not hidden")
def occlusion(context: ScoringContext) -> np.ndarray:
    """S_o = (# in-view target points not hidden) / (# in-view target points), 0 when none is in view.

    With pixel (i, j) = (floor(u), floor(v)) and h = floor(delta_px), an in-view target point of
    depth z_t is hidden when some background point with z_b > 0 has its pixel within the square
    window |i_b - i| <= h, |j_b - j| <= h and z_b < z_t (depth is the optical-axis z, not the
    range). Background points outside the image still count inside the window. S_o is kept
    separate from S_v on purpose: S_v measures framing, S_o occlusion of what is framed.
    With the context's ``line_of_sight_clear`` (the share of target points each candidate sees
    through free space of the robot's obstacle map, see :mod:`leapnbv_planner.obstacle_map`) S_o
    is multiplied by it: the background only holds what the current view saw, the map also what
    it did not.
    """
    in_view, not_hidden = context.visible_counts()
    values = np.where(in_view > 0, not_hidden / np.maximum(in_view, 1), 0.0)
    if context.line_of_sight_clear is not None:
        values = values * context.line_of_sight_clear
    return np.asarray(values, dtype=np.float64)
