"""S_o over the whole body: the share of the body mesh's near side that a candidate sees unhidden
(docs/ALGORITHMS.md §7)."""

from __future__ import annotations

import numpy as np

from leapnbv_planner.score_terms.base import ScoringContext, score_term
from leapnbv_planner.score_terms.occlusion import occlusion


@score_term("body_occlusion", 0.83, "S_o over the metric body mesh: share of the body's near side in view and "
            "not hidden")
def body_occlusion(context: ScoringContext) -> np.ndarray:
    """(# facing mesh vertices in view and not hidden) / (# facing mesh vertices), 0 when none faces.

    The mesh is the person's metric HMR mesh: the whole body, the parts hidden now included, so a view
    that reveals the hidden side scores higher (the paper's S_o only knows the points the current view
    shows). A vertex faces a candidate when its outward normal points toward the camera (the far side
    of the body is never counted); hidden is the same square-window test against the background
    points as S_o's. With the obstacle map the value is multiplied by the mesh vertices' clear line-of-
    sight share. Without a mesh in the context it is the paper's S_o (``occlusion``).
    """
    if context.mesh_vertices is None or len(context.mesh_vertices) == 0:
        return occlusion(context)
    facing, not_hidden = context.mesh_counts()
    values = np.where(facing > 0, not_hidden / np.maximum(facing, 1), 0.0)
    if context.mesh_line_of_sight_clear is not None:
        values = values * context.mesh_line_of_sight_clear
    return np.asarray(values, dtype=np.float64)
