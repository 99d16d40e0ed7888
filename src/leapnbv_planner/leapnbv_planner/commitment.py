"""Goal commitment: the published goal stays until a plan gives a reason to change it (docs/ALGORITHMS.md §10).

Every frame is planned from a new view, and two views of nearly the same score trade places from one
frame to the next (bags/sample_a: candidates 34 and 35, 0.95 m apart, within 0.005 of each other,
5 changes in 10 frames). A motion stack that follows the latest goal would oscillate between them.
Here the goal is committed: it is kept in the fixed frame of the camera pose (the map), every plan
re-scores it from the current view with the ring's rules and terms
(``PlanInputs.extra_foot_points``, ``Plan.extra``), and :func:`decide` replaces it only

- when another view beats it by more than the margin (BEATEN_BY_MARGIN: ``commit_margin``, or
  ``commit_margin_without_map`` for a plan made without an obstacle map, whose scores move more as the
  drive shows furniture: :func:`margin_in_force`), unless that view is
  within ``commit_dropped_radius_m`` of a goal dropped as blocked in the last ``commit_dropped_s``
  (the way to it flickers: taking it back would send the robot to and fro),
- when it became infeasible or unreachable (INFEASIBLE, UNREACHABLE) and no foot point within
  ``commit_same_goal_m`` of its own is free and reachable (with ``fit_to_free_space``, the plan moves
  a blocked goal there: ``ExtraViews.nudged_m``; the edge of free space moves by a fraction of a cell
  between frames, and a goal on it would flip) and it has stayed so for ``commit_blocked_s``
  (until then KEPT_BLOCKED: it is kept on its last path, from the robot on; a narrow passage to it
  closes for a frame as the robot moves),
- when the person moved more than ``commit_person_moved_m`` from where they stood at the commit
  (PERSON_MOVED), or
- when staying is as good: the current view scores within the margin of the committed goal and of
  the plan's best, so no drive is worth it (STAYING_AS_GOOD: the goal becomes the current view).

Views whose foot points are within ``commit_same_goal_m`` of the committed goal's are the same goal and
never replace it. The comparisons leave SCORE_TIE_TOLERANCE (and 1e-9 m) on the side of keeping, so
that scores and distances at a threshold to the last bit (e.g. a difference of exactly the margin)
decide the same on every CPU.

:class:`GoalCommitment` holds the committed goal between plans; the node calls
:meth:`GoalCommitment.extra_foot_points` before planning and :meth:`GoalCommitment.update` after,
and publishes the :class:`GoalDecision`'s goal. Without a camera pose there is no fixed frame to keep
a goal in: each plan's choice is the goal (NO_FIXED_FRAME), as with commitment off (DISABLED).
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass, replace
from typing import List, Optional, Tuple

import numpy as np

from leapnbv_planner.arrays import Array
from leapnbv_planner.candidates import FeasibilityReason
from leapnbv_planner.inputs import CameraPose
from leapnbv_planner.params import CommitmentParams  # defined beside the other node parameters (no import cycle)
from leapnbv_planner.plan import Frame, Plan, base_goal_frame
from leapnbv_planner.scoring import SCORE_TIE_TOLERANCE

__all__ = ["DISTANCE_TOLERANCE_M", "CommitReason", "CommitmentParams", "CommittedGoal", "GoalCommitment",
           "GoalDecision", "HeldView", "Verdict", "decide", "margin_in_force"]

# Metres: distances within this of a threshold are on the side of keeping the goal (as SCORE_TIE_TOLERANCE for
# scores): far above the rounding of a transform, far below anything a robot can tell apart.
DISTANCE_TOLERANCE_M = 1e-9
# Seconds, the same for commit_blocked_s: stamps are whole nanoseconds, so a gate at exactly a frame's time keeps.
TIME_TOLERANCE_S = 1e-9


class CommitReason(enum.IntEnum):
    """Why the goal of a plan is what it is (goal_status carries it)."""

    KEPT = 0  # the committed goal stands: nothing beat it by the margin
    FIRST_GOAL = 1  # nothing was committed: the plan's choice is committed
    BEATEN_BY_MARGIN = 2  # another view scores more than the margin above the committed goal
    INFEASIBLE = 3  # the committed goal's footprint holds an obstacle or it is out of the travel range
    UNREACHABLE = 4  # no free path of at most max_path_length to the committed goal
    PERSON_MOVED = 5  # the person moved more than commit_person_moved_m since the commit
    STAYING_AS_GOOD = 6  # the current view scores within the margin of the committed goal and the best view
    NO_FIXED_FRAME = 7  # the frame has no camera pose: the plan's choice, nothing committed
    FIXED_FRAME_CHANGED = 8  # the camera pose is in another frame than the committed goal: committed anew
    DISABLED = 9  # commit_goals is off: the plan's choice
    NO_GOAL = 10  # nothing committed and no feasible view
    KEPT_BLOCKED = 11  # infeasible or unreachable in this plan, for less than commit_blocked_s: kept on its last path

    @property
    def replaces(self) -> bool:
        """A reason that replaces (or drops) a committed goal."""
        return self in _REPLACING

    @property
    def keeps(self) -> bool:
        """A reason that keeps the committed goal (KEPT, KEPT_BLOCKED)."""
        return self in (CommitReason.KEPT, CommitReason.KEPT_BLOCKED)


_REPLACING = frozenset({CommitReason.BEATEN_BY_MARGIN, CommitReason.INFEASIBLE, CommitReason.UNREACHABLE,
                        CommitReason.PERSON_MOVED, CommitReason.STAYING_AS_GOOD, CommitReason.NO_FIXED_FRAME,
                        CommitReason.FIXED_FRAME_CHANGED})


@dataclass(frozen=True)
class HeldView:
    """The committed goal as one plan sees it (what :func:`decide` weighs).

    Attributes:
        score: its score re-computed from the current view (the ring's terms and weights).
        reason: its FeasibilityReason code now (0 = feasible).
        person_moved_m: metres between the person's floor position now and at the commit.
        best_distance_m: metres between the plan's best view's foot point and the committed goal's (inf: no best).
        current_distance_m: metres between the robot's foot point and the committed goal's.
        blocked_s: seconds since the first plan of the run of plans (this one included) that found it infeasible or
            unreachable; 0 when it is feasible now or was not before this plan.
        best_near_dropped: the plan's best view is within commit_dropped_radius_m of a goal dropped as infeasible
            or unreachable less than commit_dropped_s ago: it may not beat the committed goal by the margin.
    """

    score: float
    reason: int
    person_moved_m: float
    best_distance_m: float = math.inf
    current_distance_m: float = math.inf
    blocked_s: float = 0.0
    best_near_dropped: bool = False

    @property
    def blocked(self) -> bool:
        """Infeasible or unreachable in this plan (or without a score)."""
        return self.reason != int(FeasibilityReason.OK) or not math.isfinite(self.score)


@dataclass(frozen=True)
class Verdict:
    """What :func:`decide` says: why, and which of the plan's candidates becomes the goal.

    Attributes:
        reason: why.
        index: the plan's candidate that becomes the goal (0: the current view); -1 when the committed goal is
            kept (KEPT) or there is no goal.
    """

    reason: CommitReason
    index: int

    @property
    def keep(self) -> bool:
        """The committed goal stays the goal."""
        return self.reason == CommitReason.KEPT


def margin_in_force(params: CommitmentParams, used_obstacle_map: bool = True) -> float:
    """The commit margin of a plan: ``commit_margin``, or ``commit_margin_without_map`` for a plan without a map."""
    return float(params.commit_margin if used_obstacle_map else params.commit_margin_without_map)


def decide(params: CommitmentParams, best_index: int, best_score: float, held: Optional[HeldView],
           current_score: Optional[float] = None, used_obstacle_map: bool = True) -> Verdict:
    """Keep the committed goal or take another (pure: the same inputs give the same verdict).

    In this order: commitment off -> the plan's best (DISABLED); nothing committed -> the plan's best
    (FIRST_GOAL, or NO_GOAL without one); the person moved past ``commit_person_moved_m`` -> PERSON_MOVED;
    the committed goal unreachable -> UNREACHABLE, otherwise infeasible (or not scored) -> INFEASIBLE
    (these three take the plan's best, or no goal when the plan has none); the current view farther
    than ``commit_same_goal_m`` from the committed goal and scoring at least max(committed, best) -
    margin -> the current view (STAYING_AS_GOOD); the best view farther than ``commit_same_goal_m`` and
    scoring more than committed + margin -> it (BEATEN_BY_MARGIN); else KEPT. Thresholds are widened by
    SCORE_TIE_TOLERANCE / DISTANCE_TOLERANCE_M toward keeping.

    Args:
        params: the thresholds.
        best_index: the plan's choice among its candidates (-1: none feasible).
        best_score: its score (ignored without a choice).
        held: the committed goal as this plan sees it; None when nothing is committed.
        current_score: the plan's candidate 0 (the current view, ``include_current``), None without it.
        used_obstacle_map: the plan was made with an obstacle map (``Plan.used_obstacle_map``): the margin is
            :func:`margin_in_force`'s.

    Returns:
        The verdict.
    """
    if not params.commit_goals:
        return Verdict(CommitReason.DISABLED, best_index)
    if held is None:
        return Verdict(CommitReason.FIRST_GOAL if best_index >= 0 else CommitReason.NO_GOAL, best_index)
    if held.person_moved_m > float(params.commit_person_moved_m) + DISTANCE_TOLERANCE_M:
        return Verdict(CommitReason.PERSON_MOVED, best_index)
    if held.blocked and held.blocked_s < float(params.commit_blocked_s) - TIME_TOLERANCE_S:
        return Verdict(CommitReason.KEPT_BLOCKED, -1)
    if held.reason == int(FeasibilityReason.UNREACHABLE):
        return Verdict(CommitReason.UNREACHABLE, best_index)
    if held.reason != int(FeasibilityReason.OK) or not math.isfinite(held.score):
        return Verdict(CommitReason.INFEASIBLE, best_index)
    margin = margin_in_force(params, used_obstacle_map)
    same_goal = float(params.commit_same_goal_m) + DISTANCE_TOLERANCE_M
    best = float(best_score) if best_index >= 0 else -math.inf
    if current_score is not None and held.current_distance_m > same_goal \
            and float(current_score) >= max(held.score, best) - margin - SCORE_TIE_TOLERANCE:
        return Verdict(CommitReason.STAYING_AS_GOOD, 0)
    if best_index >= 0 and held.best_distance_m > same_goal and best > held.score + margin + SCORE_TIE_TOLERANCE \
            and not held.best_near_dropped:
        return Verdict(CommitReason.BEATEN_BY_MARGIN, best_index)
    return Verdict(CommitReason.KEPT, -1)


@dataclass(frozen=True)
class CommittedGoal:
    """The committed goal, in the fixed frame of the camera pose (p_fixed = R p_optical + t).

    Attributes:
        fixed_frame: the frame's name (the camera pose's frame_id, e.g. "map").
        foot_point: (3,) where the robot is to stand (the base goal's position).
        base_rotation: (3, 3) the base goal's orientation at the commit (x toward the person, z up).
        camera_rotation: (3, 3) the camera's orientation of the view at the commit.
        camera_position: (3,) the camera's centre of the view at the commit.
        person_position: (3,) the person's floor position (the ring centre) at the commit.
        stamp_ns: the stamp of the frame it was committed on.
        score: its score on that frame.
        index: its candidate index in that frame's plan.
        path: (P, 3) the last base path published to it, in the fixed frame (None: none was, reachability off);
            a plan that finds it blocked keeps the robot on it (KEPT_BLOCKED).
        blocked_since_ns: the stamp of the first plan of the current run of plans that found it blocked; -1: none.
    """

    fixed_frame: str
    foot_point: Array
    base_rotation: Array
    camera_rotation: Array
    camera_position: Array
    person_position: Array
    stamp_ns: int
    score: float
    index: int
    path: Optional[Array] = None
    blocked_since_ns: int = -1


@dataclass(frozen=True)
class GoalDecision:
    """The goal of one plan, in the plan's optical frame, and why (what the node publishes and goal_status says).

    Attributes:
        reason: why the goal is what it is.
        changed: a committed goal was replaced or dropped by this plan (a goal switch).
        goal: (rotation, position) of the camera view to publish (next_best_view); None: no goal.
        base_goal: (rotation, position) of the robot base there (base_goal); None with no goal.
        base_path: (P, 3) floor points of the path there (base_path); None without reachability or goal.
        score: the goal's score in this plan (NaN without a goal).
        index: the plan's candidate that is the goal; -1 when it is the committed goal (kept) or there is none.
        committed: the committed goal after this plan (None: nothing committed).
        held_score: the committed goal's re-computed score before the decision (NaN: none was re-scored).
        best_index: the plan's own choice (-1: none), its rival.
        best_score: its score (NaN without one).
        person_moved_m: the person's displacement since the commit (NaN: none was re-scored).
        margin: the margin in force (:func:`margin_in_force`).
        nudged_m: metres the kept goal's foot point moved to free space in this plan (``ExtraViews.nudged_m``: its
            own foot point was blocked or had no path, one within commit_same_goal_m had); 0 when it did not.
        blocked_s: KEPT_BLOCKED: seconds the committed goal has been blocked (``HeldView.blocked_s``); 0 otherwise.
        best_near_dropped: the plan's best is near a goal dropped as blocked lately (``HeldView.best_near_dropped``).
    """

    reason: CommitReason
    changed: bool
    goal: Optional[Frame]
    base_goal: Optional[Frame]
    base_path: Optional[Array]
    score: float
    index: int
    committed: Optional[CommittedGoal]
    held_score: float = math.nan
    best_index: int = -1
    best_score: float = math.nan
    person_moved_m: float = math.nan
    margin: float = math.nan
    nudged_m: float = 0.0
    blocked_s: float = 0.0
    best_near_dropped: bool = False

    def describe(self) -> str:
        """One line for goal_status.reason."""
        best = f"view {self.best_index} ({self.best_score:.4f})" if self.best_index >= 0 else "no feasible view"
        held = f"the committed goal scores {self.held_score:.4f}"
        if self.reason == CommitReason.KEPT:
            nudge = f" ({self.nudged_m:.2f} m from its foot point, in free space)" if self.nudged_m > 0.0 else ""
            dropped = " (near a goal dropped as blocked within commit_dropped_s)" if self.best_near_dropped else ""
            return f"goal kept{nudge}: {held}, the plan's best is {best}{dropped}, margin {self.margin:g}"
        if self.reason == CommitReason.KEPT_BLOCKED:
            return f"goal kept on its last path: infeasible or unreachable in this plan for {self.blocked_s:.2f} s," \
                   f" less than commit_blocked_s; the plan's best is {best}"
        if self.reason == CommitReason.BEATEN_BY_MARGIN:
            return f"goal changed: {best} beats it by more than {self.margin:g} ({held})"
        if self.reason == CommitReason.STAYING_AS_GOOD:
            return f"goal changed to the current view ({self.score:.4f}): within {self.margin:g} of the best ({held}," \
                   f" {best})"
        if self.reason == CommitReason.PERSON_MOVED:
            return f"goal changed: the person moved {self.person_moved_m:.2f} m since the commit; now {best}"
        if self.reason in (CommitReason.INFEASIBLE, CommitReason.UNREACHABLE):
            why = "is unreachable" if self.reason == CommitReason.UNREACHABLE else "became infeasible"
            return f"goal changed: the committed goal {why}; now {best}"
        if self.reason == CommitReason.FIRST_GOAL:
            return f"goal committed: {best}"
        if self.reason == CommitReason.NO_FIXED_FRAME:
            return f"no camera pose: the plan's choice, nothing committed ({best})"
        if self.reason == CommitReason.FIXED_FRAME_CHANGED:
            return f"the camera pose's frame changed: committed anew ({best})"
        if self.reason == CommitReason.DISABLED:
            return f"commitment off: the plan's choice ({best})"
        return "no feasible view, nothing committed"


def _to_fixed(pose: CameraPose, points: Array) -> Array:
    """Optical-frame points (..., 3) in the fixed frame."""
    rotation = np.asarray(pose.rotation, dtype=np.float64)
    return np.asarray(points, dtype=np.float64) @ rotation.T + np.asarray(pose.position, dtype=np.float64)


def _to_optical(pose: CameraPose, points: Array) -> Array:
    """Fixed-frame points (..., 3) in the frame's optical frame."""
    rotation = np.asarray(pose.rotation, dtype=np.float64)
    return (np.asarray(points, dtype=np.float64) - np.asarray(pose.position, dtype=np.float64)) @ rotation


def _path_in_fixed(pose: CameraPose, path: Optional[Array]) -> Optional[Array]:
    """A base path of the frame's optical frame in the fixed frame (None stays None)."""
    return None if path is None else _to_fixed(pose, np.asarray(path, dtype=np.float64).reshape(-1, 3))


def _path_on(pose: CameraPose, path_fixed: Array, up: Array) -> Array:
    """The last path (fixed frame) in this frame's optical frame, from the robot on.

    Its point nearest the robot's foot point (seen from above) is replaced by that foot point and the points before
    it are left out, so that a motion stack that follows it goes on and never drives back to where the path began.
    """
    points = _to_optical(pose, path_fixed)
    normal = np.asarray(up, dtype=np.float64).reshape(3)
    normal = normal / max(float(np.linalg.norm(normal)), 1e-12)
    heights = points @ normal
    across = np.linalg.norm(points - heights[:, None] * normal[None, :], axis=1)  # from the camera's vertical
    nearest = int(np.argmin(across))
    foot = heights[nearest] * normal  # below the camera, on the path's floor
    rest = points[nearest + 1:] if nearest + 1 < len(points) else points[-1:]
    return np.vstack([foot[None, :], rest])


def _distance(a: Array, b: Array) -> float:
    difference = np.asarray(a, dtype=np.float64) - np.asarray(b, dtype=np.float64)
    return float(math.sqrt(float(difference @ difference)))


class GoalCommitment:
    """The committed goal between plans, and the decision of each plan (no ROS: the node holds one).

    Per frame: ``feet = commitment.extra_foot_points(params, pose, frame_id)``, plan with
    ``PlanInputs(..., extra_foot_points=feet)``, then ``decision = commitment.update(params, plan, pose,
    frame_id, stamp_ns)`` and publish ``decision.goal`` / ``base_goal`` / ``base_path``. The committed goal's
    view is the first row of the extra views (a caller that adds views of its own appends them after it).
    """

    def __init__(self) -> None:
        self.goal: Optional[CommittedGoal] = None
        # (fixed frame, foot point, stamp) of goals dropped as infeasible or unreachable (commit_dropped_s).
        self.dropped: List[Tuple[str, Array, int]] = []

    def clear(self) -> None:
        """Forget the committed goal and the dropped ones (the next plan's choice is committed anew)."""
        self.goal = None
        self.dropped = []

    def _near_dropped(self, params: CommitmentParams, foot_fixed: Array, fixed_frame: str, stamp_ns: int) -> bool:
        """A floor point within commit_dropped_radius_m of a goal dropped less than commit_dropped_s ago."""
        window_ns = float(params.commit_dropped_s) * 1e9
        # Entries from the future (a replay, a simulator reset) and past the window go.
        self.dropped = [d for d in self.dropped if 0 <= int(stamp_ns) - d[2] < window_ns]
        radius = float(params.commit_dropped_radius_m) + DISTANCE_TOLERANCE_M
        return any(frame == fixed_frame and _distance(foot, foot_fixed) <= radius for frame, foot, _ in self.dropped)

    def extra_foot_points(self, params: CommitmentParams, camera_pose: Optional[CameraPose],
                          fixed_frame: str) -> Optional[Array]:
        """The committed goal's foot point in this frame, to re-score: PlanInputs.extra_foot_points.

        Returns:
            (1, 3) the foot point in the frame's optical frame, or None when there is nothing to re-score:
            commitment off, nothing committed, no camera pose, or a pose in another fixed frame.
        """
        if not self._comparable(params, camera_pose, fixed_frame) or camera_pose is None or self.goal is None:
            return None
        return _to_optical(camera_pose, self.goal.foot_point).reshape(1, 3)

    def _comparable(self, params: CommitmentParams, camera_pose: Optional[CameraPose], fixed_frame: str) -> bool:
        return bool(params.commit_goals) and camera_pose is not None and self.goal is not None \
            and self.goal.fixed_frame == fixed_frame

    def update(self, params: CommitmentParams, plan: Plan, camera_pose: Optional[CameraPose], fixed_frame: str,
               stamp_ns: int) -> GoalDecision:
        """Decide the goal of a plan and keep the commitment it leaves.

        Args:
            params: the thresholds (a node's params instance, which has these fields).
            plan: the frame's plan, made with :meth:`extra_foot_points`' foot point when it gave one.
            camera_pose: the frame's camera in the fixed frame, None when the frame has none.
            fixed_frame: that frame's name.
            stamp_ns: the frame's stamp.

        Returns:
            The decision.

        Raises:
            ValueError: a goal is committed and comparable, but the plan has no extra view to re-score it (the plan
                was made without :meth:`extra_foot_points`).
        """
        had_goal = self.goal is not None
        best = int(plan.chosen_index)
        best_score = float(plan.scores.score[best]) if best >= 0 else math.nan
        margin = margin_in_force(params, plan.used_obstacle_map)
        if not params.commit_goals or camera_pose is None:
            self.goal = None
            reason = CommitReason.DISABLED if not params.commit_goals else CommitReason.NO_FIXED_FRAME
            return self._plan_choice(plan, Verdict(reason, best), changed=had_goal, committed=None,
                                     best_score=best_score, margin=margin)
        if self.goal is not None and self.goal.fixed_frame != fixed_frame:
            self.goal = None
            verdict = Verdict(CommitReason.FIXED_FRAME_CHANGED, best)
            committed = self._commit(plan, best, camera_pose, fixed_frame, stamp_ns)
            return self._plan_choice(plan, verdict, changed=True, committed=committed, best_score=best_score,
                                     margin=margin)
        held: Optional[HeldView] = None
        if self.goal is not None:
            held = self._held_view(plan, camera_pose)
            if held.blocked:
                if self.goal.blocked_since_ns < 0:
                    self.goal = replace(self.goal, blocked_since_ns=int(stamp_ns))
                held = replace(held, blocked_s=(int(stamp_ns) - self.goal.blocked_since_ns) * 1e-9)
            if best >= 0 and self.dropped:
                best_foot = _to_fixed(camera_pose, plan.candidates.foot_points[best])
                held = replace(held, best_near_dropped=self._near_dropped(params, best_foot, fixed_frame, stamp_ns))
        current_score = float(plan.scores.score[0]) if plan.includes_current_view else None
        verdict = decide(params, best, best_score, held, current_score, plan.used_obstacle_map)
        held_score = held.score if held is not None else math.nan
        moved = held.person_moved_m if held is not None else math.nan
        if verdict.reason == CommitReason.KEPT_BLOCKED and self.goal is not None and plan.extra is not None \
                and held is not None:
            extra = plan.extra
            path = None if self.goal.path is None else _path_on(camera_pose, self.goal.path, plan.up)
            return GoalDecision(reason=verdict.reason, changed=False, goal=extra.pose(0), base_goal=extra.base_goal(0),
                                base_path=path, score=held_score, index=-1, committed=self.goal,
                                held_score=held_score, best_index=best, best_score=best_score, person_moved_m=moved,
                                margin=margin, blocked_s=held.blocked_s)
        if verdict.keep and self.goal is not None and plan.extra is not None:
            extra = plan.extra
            self.goal = replace(self.goal, blocked_since_ns=-1, path=_path_in_fixed(camera_pose, extra.base_paths[0]))
            return GoalDecision(reason=verdict.reason, changed=False, goal=extra.pose(0), base_goal=extra.base_goal(0),
                                base_path=extra.base_paths[0], score=held_score, index=-1, committed=self.goal,
                                held_score=held_score, best_index=best, best_score=best_score, person_moved_m=moved,
                                margin=margin,
                                nudged_m=float(extra.nudged_m[0]) if extra.nudged_m is not None else 0.0,
                                best_near_dropped=held is not None and held.best_near_dropped)
        if verdict.reason in (CommitReason.INFEASIBLE, CommitReason.UNREACHABLE) and self.goal is not None:
            self.dropped.append((self.goal.fixed_frame, self.goal.foot_point, int(stamp_ns)))
        committed = self._commit(plan, verdict.index, camera_pose, fixed_frame, stamp_ns)
        return self._plan_choice(plan, verdict, changed=had_goal and verdict.reason.replaces, committed=committed,
                                 held_score=held_score, best_score=best_score, person_moved_m=moved, margin=margin)

    def _held_view(self, plan: Plan, camera_pose: CameraPose) -> HeldView:
        """The committed goal in this plan: its re-computed score and feasibility, the distances decide weighs."""
        goal = self.goal
        assert goal is not None
        extra = plan.extra
        if extra is None or len(extra) == 0:
            raise ValueError("a goal is committed but the plan has no extra view to re-score it: plan with"
                             " PlanInputs(extra_foot_points=GoalCommitment.extra_foot_points(...))")
        foot = extra.candidates.foot_points[0]
        candidates = plan.candidates
        best = int(plan.chosen_index)
        return HeldView(
            score=float(extra.scores.score[0]), reason=int(extra.feasibility.reasons[0]),
            person_moved_m=_distance(_to_fixed(camera_pose, candidates.ring_center), goal.person_position),
            best_distance_m=_distance(candidates.foot_points[best], foot) if best >= 0 else math.inf,
            current_distance_m=_distance(candidates.foot_points[0], foot) if plan.includes_current_view
            else math.inf)

    def _commit(self, plan: Plan, index: int, camera_pose: CameraPose, fixed_frame: str,
                stamp_ns: int) -> Optional[CommittedGoal]:
        """Commit the plan's candidate ``index`` (-1: nothing) in the fixed frame."""
        if index < 0:
            self.goal = None
            return None
        candidates = plan.candidates
        base_rotation, foot = base_goal_frame(candidates.foot_points[index], candidates.ring_center, plan.up)
        rotation = np.asarray(camera_pose.rotation, dtype=np.float64)
        self.goal = CommittedGoal(
            fixed_frame=fixed_frame, foot_point=_to_fixed(camera_pose, foot), base_rotation=rotation @ base_rotation,
            camera_rotation=rotation @ candidates.rotations[index],
            camera_position=_to_fixed(camera_pose, candidates.positions[index]),
            person_position=_to_fixed(camera_pose, candidates.ring_center), stamp_ns=int(stamp_ns),
            score=float(plan.scores.score[index]), index=int(index),
            path=_path_in_fixed(camera_pose, _candidate_goal(plan, index)[2]))
        return self.goal

    @staticmethod
    def _plan_choice(plan: Plan, verdict: Verdict, changed: bool, committed: Optional[CommittedGoal],
                     best_score: float, margin: float, held_score: float = math.nan,
                     person_moved_m: float = math.nan) -> GoalDecision:
        """The decision whose goal is the plan's candidate ``verdict.index`` (-1: no goal)."""
        index = verdict.index
        goal, base_goal, base_path = _candidate_goal(plan, index)
        return GoalDecision(reason=verdict.reason, changed=changed, goal=goal, base_goal=base_goal,
                            base_path=base_path, score=float(plan.scores.score[index]) if index >= 0 else math.nan,
                            index=index, committed=committed, held_score=held_score,
                            best_index=int(plan.chosen_index), best_score=best_score, person_moved_m=person_moved_m,
                            margin=margin)


def _candidate_goal(plan: Plan, index: int) -> Tuple[Optional[Frame], Optional[Frame], Optional[Array]]:
    """(camera view, base goal, base path) of the plan's candidate ``index``: the plan's own for its choice."""
    if index < 0:
        return None, None, None
    if index == plan.chosen_index:
        return plan.chosen_pose(), plan.base_goal, plan.base_path
    candidates = plan.candidates
    base_goal = base_goal_frame(candidates.foot_points[index], candidates.ring_center, plan.up)
    base_path = plan.reach.path_to(candidates.foot_points[index]) if plan.reach is not None else None
    return (candidates.rotations[index], candidates.positions[index]), base_goal, base_path
