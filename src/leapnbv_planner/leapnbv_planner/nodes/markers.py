"""RViz / Foxglove markers of a plan: the candidate ring coloured by score, the chosen view, the ring's centre."""
from __future__ import annotations

import numpy as np
from visualization_msgs.msg import Marker, MarkerArray

from leapnbv_common.conversions import point_msg, pose_msg
from leapnbv_msgs.msg import ViewCandidates
from leapnbv_planner.plan import Plan, base_goal_frame

__all__ = ["candidate_markers"]


def _score_colour(value: float, lo: float, hi: float):
    t = 0.0 if hi <= lo else (value - lo) / (hi - lo)
    return float(1.0 - t), float(t), 0.2  # red (low) -> green (high)


def candidate_markers(header, out: ViewCandidates, plan: Plan) -> MarkerArray:
    """Ring coloured by score, infeasible candidates as grey cubes, the chosen view as an arrow."""
    markers = MarkerArray()
    clear = Marker(header=header, ns="leapnbv_candidates", action=Marker.DELETEALL)
    markers.markers.append(clear)
    scores = np.asarray(out.score, dtype=np.float64)
    shown = scores[np.asarray(out.feasible, dtype=bool)]  # the colour scale of the candidates that were scored
    lo, hi = (float(shown.min()), float(shown.max())) if shown.size else (0.0, 1.0)
    for i, pose in enumerate(out.poses):
        m = Marker(header=header, ns="leapnbv_candidates", id=i, pose=pose)
        m.frame_locked = False
        if out.feasible[i]:
            m.type = Marker.SPHERE
            m.scale.x = m.scale.y = m.scale.z = 0.12
            m.color.r, m.color.g, m.color.b = _score_colour(float(scores[i]), lo, hi)
        else:
            m.type = Marker.CUBE
            m.scale.x = m.scale.y = m.scale.z = 0.1
            m.color.r = m.color.g = m.color.b = 0.5
        m.color.a = 1.0
        markers.markers.append(m)
    if out.chosen_index >= 0:
        # Arrow markers point along their x axis; the camera looks along its z axis.
        arrow = Marker(header=header, ns="leapnbv_chosen", id=0, type=Marker.ARROW)
        start = plan.candidates.positions[out.chosen_index]
        end = start + 0.5 * plan.candidates.rotations[out.chosen_index][:, 2]
        arrow.points = [point_msg(start), point_msg(end)]
        arrow.scale.x, arrow.scale.y, arrow.scale.z = 0.04, 0.08, 0.1
        arrow.color.g, arrow.color.b, arrow.color.a = 0.8, 1.0, 1.0
        markers.markers.append(arrow)
    centre = Marker(header=header, ns="leapnbv_ring_center", id=0, type=Marker.CYLINDER)
    # A flat disc on the ground: the cylinder's axis (its z) along the plane normal.
    centre.pose = pose_msg(*base_goal_frame(plan.candidates.ring_center, plan.candidates.positions[-1], plan.up))
    centre.scale.x = centre.scale.y = 2 * out.ring_radius
    centre.scale.z = 0.005
    centre.color.b, centre.color.a = 1.0, 0.15
    markers.markers.append(centre)
    return markers
