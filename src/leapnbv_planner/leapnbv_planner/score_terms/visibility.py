"""S_v: the share of the person that a candidate view frames (docs/ALGORITHMS.md §7).

Of the whole metric body mesh (``visibility_points: body_mesh``), or of the target points the current view saw
(``observed``, the paper's).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Tuple

import numpy as np

from leapnbv_planner.arrays import Array
from leapnbv_planner.requirements import BODY_MESH
from leapnbv_planner.score_terms.base import ScoringContext, score_term

if TYPE_CHECKING:  # params imports the score terms (their weights are its fields)
    from leapnbv_planner.params import PlannerParams

#: ``visibility_points``: what S_v counts (leapnbv_planner.params holds the default).
VISIBILITY_POINTS = ("observed", "body_mesh")


def _reads(params: PlannerParams) -> Tuple[str, ...]:
    """The requirements S_v reads with these parameters: the body mesh only when it counts the mesh."""
    return (BODY_MESH.name,) if params.visibility_points == "body_mesh" else ()


@score_term("visibility", 0.03, "S_v, share of the person in view (visibility_points: the metric body mesh's "
            "vertices, or the observed target points)", requires=(BODY_MESH,), requires_for=_reads,
            without={BODY_MESH.name: "S_v of the observed points"})
def visibility(context: ScoringContext) -> Array:
    """S_v of every candidate.

    ``body_mesh``: (# vertices of the person's metric body mesh with visibility_min_depth <= z <=
    visibility_max_depth, 0 <= u < W, 0 <= v < H) / (# vertices): the share of the whole predicted body, the parts
    the current view does not see included, that the candidate's image holds (hidden or not: S_o judges that), so a
    near view that cuts the legs off at the border scores what it keeps. Without a mesh in the frame it falls back
    to the observed points. ``observed`` (the paper's): (# target points with z > 0, 0 <= u < W, 0 <= v < H) /
    (# target points), 0 without target points; it counts only what the current view saw, which a view that
    frames those points but cuts the rest of the body off still scores 1.
    """
    if context.params.visibility_points == "body_mesh":
        mesh = context.need(BODY_MESH)
        if mesh is not None and len(mesh.points):
            return np.asarray(context.mesh_framed_counts() / float(len(mesh.points)), dtype=np.float64)
    in_view = context.in_view_counts()
    num_targets = context.num_targets
    values = in_view / float(num_targets) if num_targets else np.zeros(len(in_view))
    return np.asarray(values, dtype=np.float64)
