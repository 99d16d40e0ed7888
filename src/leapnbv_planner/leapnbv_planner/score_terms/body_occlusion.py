"""S_o over the whole body: the share of the body mesh's near side that a candidate sees unhidden
(docs/ALGORITHMS.md §7)."""

from __future__ import annotations

from leapnbv_planner.arrays import Array
from leapnbv_planner.requirements import BODY_MESH, MESH_LINE_OF_SIGHT, TARGET_LINE_OF_SIGHT
from leapnbv_planner.score_terms.base import ScoringContext, score_term
from leapnbv_planner.score_terms.occlusion import not_hidden_share


@score_term("body_occlusion", 0.83, "S_o over the metric body mesh: share of the body's near side in view and "
            "not hidden", requires=(BODY_MESH, MESH_LINE_OF_SIGHT, TARGET_LINE_OF_SIGHT),
            without={BODY_MESH.name: "S_o of the observed points"})
def body_occlusion(context: ScoringContext) -> Array:
    """(# facing mesh vertices in view and not hidden) / (# facing mesh vertices), 0 when none faces.

    The mesh is the person's metric HMR mesh: the whole body, the parts hidden now included, so a view
    that reveals the hidden side scores higher (the paper's S_o only knows the points the current view
    shows). A vertex faces a candidate when its outward normal points toward the camera (the far side
    of the body is never counted); hidden is the same square-window test against the background
    points as S_o's. With the obstacle map the value is multiplied by the mesh vertices' clear line-of-
    sight share. Without a mesh in the frame it is the paper's S_o (``occlusion``): only then is the
    target points' line of sight walked.
    """
    mesh = context.need(BODY_MESH)
    if mesh is None or len(mesh.points) == 0:
        in_view, not_hidden = context.visible_counts()
        return not_hidden_share(in_view, not_hidden, context.need(TARGET_LINE_OF_SIGHT))
    facing, not_hidden = context.mesh_counts()
    return not_hidden_share(facing, not_hidden, context.need(MESH_LINE_OF_SIGHT))
