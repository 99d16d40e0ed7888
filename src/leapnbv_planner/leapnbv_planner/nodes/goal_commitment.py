"""nbv_node's goal commitment: the committed goal between plans, in the fixed frame of the frame's camera pose.

The rules are the core's (:mod:`leapnbv_planner.commitment`, docs/ALGORITHMS.md §10); this module gives it
the node's inputs: the frame's camera pose (the ``camera_pose`` companion, fetched while ``commit_goals``
is on; its ``frame_id``, e.g. ``map``, is the fixed frame), the committed goal's foot point for the plan
to re-score, and the decision the node publishes in place of the plan's own choice. Without a camera
pose each plan's choice is the goal (NO_FIXED_FRAME). Deactivating the node forgets the committed goal,
and so does a change of what the scores are made of (a term's weight, ``score_terms``): a score of
the committed goal from before is not comparable any more.
"""
from __future__ import annotations

import dataclasses
from typing import Any, Iterable, Optional, Tuple

from leapnbv_common.camera_pose import StampedCameraPose
from leapnbv_common.stage import Frame, Received
from leapnbv_planner.arrays import Array
from leapnbv_planner.commitment import GoalCommitment, GoalDecision
from leapnbv_planner.plan import Plan
from leapnbv_planner.score_terms import weight_parameter

__all__ = ["NodeCommitment", "decision_path_frames", "scores_changed"]


def scores_changed(changed: Iterable[str]) -> bool:
    """Whether a parameter change alters what the scores are made of (the terms or a term's weight)."""
    return any(name == "score_terms" or name.startswith(weight_parameter("")) for name in changed)


class NodeCommitment:
    """The node's :class:`GoalCommitment` and the inputs of each frame to it.

    Args:
        node: The nbv node (its ``params.value``).
    """

    def __init__(self, node: Any) -> None:
        self.node = node
        self.core = GoalCommitment()
        self.poses_seen = False  # a camera pose has come for a frame (some node publishes them)

    def clear(self) -> None:
        """Forget the committed goal (deactivate, a change of the scores' terms or weights)."""
        self.core.clear()

    def needs_pose(self, map_in_use: bool) -> bool:
        """Whether a frame looks its camera pose up: for the obstacle map in use or for the commitment."""
        return map_in_use or bool(self.node.params.value.commit_goals)

    def pose_wait_s(self, map_in_use: bool) -> float:
        """How long a frame waits for its camera pose (the pose is looked up once in any case).

        camera_pose_wait_s while the map is in use, or while commitment is on and camera poses have come;
        else none: a graph without camera poses is not slowed by the commitment (its frames plan without one).
        """
        p = self.node.params.value
        return float(p.camera_pose_wait_s) if map_in_use or (p.commit_goals and self.poses_seen) else 0.0

    def seen(self, received: Received) -> Received:
        """A frame's camera pose was found (returned as it is): from now on frames wait for theirs."""
        self.poses_seen = True
        return received

    def camera_pose(self, frame: Frame) -> Optional[StampedCameraPose]:
        """The frame's camera pose in its fixed frame while commitment is on (None: no fixed frame)."""
        if not self.node.params.value.commit_goals:
            return None
        pose: Optional[StampedCameraPose] = frame["camera_pose"]
        return pose

    def extra_foot_points(self, pose: Optional[StampedCameraPose]) -> Optional[Array]:
        """The committed goal's foot point in the frame's optical frame, for ``PlanInputs.extra_foot_points``."""
        return self.core.extra_foot_points(self.node.params.value, pose, pose.frame_id if pose is not None else "")

    def update(self, plan: Plan, pose: Optional[StampedCameraPose], stamp_ns: int) -> GoalDecision:
        """The goal of this plan (kept or replaced), and the commitment it leaves."""
        return self.core.update(self.node.params.value, plan, pose, pose.frame_id if pose is not None else "",
                                stamp_ns)


def decision_path_frames(plan: Plan, decision: GoalDecision) -> Optional[Tuple[Array, Array]]:
    """Poses along the decision's base path (the plan's ``base_path_frames`` of the goal published)."""
    if decision.base_path is None or decision.base_goal is None:
        return None
    return dataclasses.replace(plan, base_path=decision.base_path, base_goal=decision.base_goal).base_path_frames()
