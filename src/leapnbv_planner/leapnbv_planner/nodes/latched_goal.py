"""nbv_node's latched goal: next_best_view, base_goal, base_path and goal_status, and the goal's age.

No stale goal (docs/ARCHITECTURE.md, "Timing"): a goal goes out only from a frame younger than
``max_goal_age_s``; ``goal_status`` says whether the latched goal may be acted on (CURRENT); a timer,
running only while a goal is current, replaces a goal that ages out by an explicit "no goal" (STALE,
and next_best_view / base_goal / base_path re-published with an empty frame_id), as deactivating the
node does (NONE). Every status carries ``valid_until`` (the goal's stamp + its age limit while CURRENT, else
0), so a consumer checks the goal on its own clock also while this node is frozen, and ``planned_without``
(the optional inputs in use that the goal's frame lacked, their why in ``reason``). The rules themselves:
:mod:`leapnbv_planner.goal_age`.

The goal published is the commitment's (:mod:`leapnbv_planner.nodes.goal_commitment`), and each CURRENT status
says why it is what it is (``commitment``, ``goal_changed``, ``committed_since``, the scores weighed and the
margin; the decision's line in ``reason``). A committed goal that a plan drops without a feasible view to
take its place (infeasible, unreachable, the person moved) is withdrawn at once (NONE), not left to age out.

Every status carries the target as hmr_node tracks it (``target``: the newest TargetTrack, set by
:mod:`leapnbv_planner.nodes.target_status`); :meth:`LatchedGoal.target_changed` says a change of it at once
(the status restated, ``goal_changed`` false) and withdraws a CURRENT goal when the target is lost (STALE,
"target lost: ...").
"""
from __future__ import annotations

from typing import Any, Callable, Dict, Optional, Tuple

from geometry_msgs.msg import PoseStamped
from nav_msgs.msg import Path
from std_msgs.msg import Header

from leapnbv_common import topics
from leapnbv_common.conversions import path_msg, pose_msg, set_stamp
from leapnbv_common.qos import latched_goal_qos
from leapnbv_msgs.msg import GoalStatus, TargetTrack
from leapnbv_planner.commitment import GoalDecision
from leapnbv_planner.goal_age import expired_age_s, goal_age_limit_s, too_old, valid_until_ns

__all__ = ["LatchedGoal", "GOAL_AGE_CHECK_PERIOD_S"]

GOAL_AGE_CHECK_PERIOD_S = 0.1  # how often the latched goal's age is checked (only while a goal is current)


class LatchedGoal:
    """The goal topics of a planner node and the state of the goal they latch.

    The publishers are plain ones, made with the object (in configure): ``start`` (activate) says "no goal
    yet" on them and ``stop`` (deactivate) withdraws the goal, at the edges of the active state, where a
    lifecycle publisher drops what it gets.

    Args:
        node: The node (its clock, ``params.value.max_goal_age_s``, ``diagnostics``).
    """

    def __init__(self, node: Any) -> None:
        self.node = node
        self.goal_pub = node.create_publisher(PoseStamped, topics.NEXT_BEST_VIEW, latched_goal_qos())
        self.base_goal_pub = node.create_publisher(PoseStamped, topics.BASE_GOAL, latched_goal_qos())
        self.status_pub = node.create_publisher(GoalStatus, topics.GOAL_STATUS, latched_goal_qos())
        self.base_path_pub = node.create_publisher(Path, topics.BASE_PATH, latched_goal_qos())
        self.stamp: Optional[int] = None  # frame stamp of the last goal published
        self.frame = ""
        self.state = GoalStatus.STATE_NONE
        self.planned_without: Dict[str, str] = {}  # of the latched goal: input name -> why
        self.decision: Optional[GoalDecision] = None  # the commitment's decision of the latched goal
        self.age_timer: Any = None
        self.reason = ""  # of the last status published
        self.target: Callable[[], TargetTrack] = TargetTrack  # the newest TargetTrack (the node sets its source)

    def now_ns(self) -> int:
        now: int = self.node.get_clock().now().nanoseconds
        return now

    def age_limit_s(self) -> float:
        """How old the latched goal may grow: max_goal_age_s, plus the hold while the target is NOT_SEEN."""
        p = self.node.params.value
        return goal_age_limit_s(p.max_goal_age_s, p.hidden_target_goal_hold_s,
                                self.target().state == TargetTrack.STATE_NOT_SEEN)

    def too_old(self, stamp_ns: int) -> bool:
        """Whether a frame of this stamp is older than max_goal_age_s now (never with a limit of 0)."""
        return too_old(self.now_ns(), stamp_ns, self.node.params.value.max_goal_age_s)

    def start(self) -> None:
        """Activate: the age timer (made here, runs only while a goal is current) and "no goal planned yet"."""
        self.age_timer = self.node.create_timer(GOAL_AGE_CHECK_PERIOD_S, self.check_age)
        self.age_timer.cancel()
        self.publish_status(GoalStatus.STATE_NONE, "no goal planned yet")

    def stop(self) -> None:
        """Deactivate: no goal from a planner that stopped (a motion stack must not keep acting on the last one)."""
        self.decision = None
        if self.state == GoalStatus.STATE_CURRENT:
            self.withdraw()
            self.publish_status(GoalStatus.STATE_NONE, "the planner was deactivated: the last goal was withdrawn")

    def limit_changed(self, max_goal_age_s: float) -> None:
        """A new max_goal_age_s: the next check applies it to the latched goal."""
        if self.state == GoalStatus.STATE_CURRENT and max_goal_age_s > 0 and self.age_timer is not None:
            self.age_timer.reset()

    def publish_decision(self, header: Header, stamp_ns: int, decision: GoalDecision,
                         planned_without: Dict[str, str]) -> bool:
        """Latch the goal a plan's commitment decided (or withdraw a dropped one); whether a goal went out."""
        if decision.goal is None or decision.base_goal is None:
            self.node.diagnostics.reject("no_feasible_view", "every candidate is infeasible: no goal published")
            if decision.changed and self.state == GoalStatus.STATE_CURRENT:
                self.decision = decision
                self.withdraw()
                self.publish_status(GoalStatus.STATE_NONE, "the committed goal was withdrawn: " + decision.describe())
            return False
        if self.too_old(stamp_ns):
            self.node.diagnostics.drop("goal_too_old")  # planning took it past the limit: no goal of it
            return False
        self.decision = decision
        self.publish(header, stamp_ns, decision.goal, decision.base_goal, planned_without)
        return True

    def publish(self, header: Header, stamp_ns: int, chosen: Tuple[Any, Any], base_goal: Tuple[Any, Any],
                planned_without: Optional[Dict[str, str]] = None) -> None:
        """Latch the goal of a frame: the camera's view and the base's goal, in the frame's header.

        ``planned_without``: the optional inputs in use that the frame was planned without, each with why.
        """
        self.goal_pub.publish(PoseStamped(header=header, pose=pose_msg(*chosen)))
        self.base_goal_pub.publish(PoseStamped(header=header, pose=pose_msg(*base_goal)))
        self.stamp, self.frame = stamp_ns, header.frame_id
        self.planned_without = dict(planned_without or {})
        why = "goal published" if self.decision is None else self.decision.describe()
        self.publish_status(GoalStatus.STATE_CURRENT, why + "".join(
            f"; planned without {name}: {why}" for name, why in self.planned_without.items()))
        if self.node.params.value.max_goal_age_s > 0 and self.age_timer.is_canceled():
            self.age_timer.reset()

    def publish_path(self, path: Optional[Tuple[Any, Any]], header: Header) -> None:
        """The base's path to the goal just published (a plan's ``base_path_frames()``), when it has one."""
        if path is not None:
            self.base_path_pub.publish(path_msg(path[0], path[1], header))

    def check_age(self) -> None:
        """The timer: a current goal whose frame is now older than max_goal_age_s is withdrawn."""
        limit = self.age_limit_s()
        if self.state != GoalStatus.STATE_CURRENT or self.stamp is None or limit <= 0:
            self.age_timer.cancel()
            return
        age_s = expired_age_s(self.now_ns(), self.stamp, limit)
        if age_s is None:
            return
        self.age_timer.cancel()
        self.decision = None
        self.withdraw()
        self.node.diagnostics.drop("goal_withdrawn_stale")
        self.publish_status(GoalStatus.STATE_STALE, f"no goal from a frame younger than {limit:g} s: the last one"
                            f" is {age_s:.2f} s old and was withdrawn")

    def target_changed(self, lost: str = "") -> None:
        """The target's state or id changed: restate the status now with it.

        ``lost`` (why the target was lost, or ""): a CURRENT goal is withdrawn (STALE) instead.
        """
        if lost and self.state == GoalStatus.STATE_CURRENT:
            if self.age_timer is not None:
                self.age_timer.cancel()
            self.decision = None
            self.withdraw()
            self.node.diagnostics.drop("goal_withdrawn_target_lost")
            self.publish_status(GoalStatus.STATE_STALE, f"target lost: the goal was withdrawn ({lost})")
            return
        self.publish_status(self.state, self.reason, restated=True)

    def withdraw(self) -> None:
        """Replace the latched goals by "no goal": a motion stack connecting later must not receive the old one."""
        cleared = Header(frame_id="", stamp=self.node.get_clock().now().to_msg())
        self.goal_pub.publish(PoseStamped(header=cleared))
        self.base_goal_pub.publish(PoseStamped(header=cleared))
        self.base_path_pub.publish(Path(header=cleared))  # an empty path: no way to a current goal

    def publish_status(self, state: int, reason: str, restated: bool = False) -> None:
        """Publish goal_status.

        ``restated``: the same goal and state said again (a change of the target only), so ``goal_changed`` is false.
        """
        now = self.now_ns()
        msg = GoalStatus(state=state, reason=reason, max_goal_age_s=float(self.node.params.value.max_goal_age_s))
        msg.header.stamp = self.node.get_clock().now().to_msg()
        msg.header.frame_id = self.frame if state == GoalStatus.STATE_CURRENT else ""
        if self.stamp is not None:
            set_stamp(msg.goal_stamp, self.stamp)
            msg.goal_age_s = float((now - self.stamp) * 1e-9)
        if self.stamp is not None and state == GoalStatus.STATE_CURRENT:
            set_stamp(msg.valid_until, valid_until_ns(self.stamp, self.age_limit_s()))
            msg.planned_without = list(self.planned_without)
        if self.decision is not None and (state == GoalStatus.STATE_CURRENT or self.decision.goal is None):
            commitment_fields(msg, self.decision, self.stamp)
            msg.goal_changed = msg.goal_changed and not restated
        msg.target = self.target()
        self.state, self.reason = state, reason
        self.status_pub.publish(msg)


def commitment_fields(msg: GoalStatus, decision: GoalDecision, stamp_ns: Optional[int]) -> None:
    """The commitment's fields of a goal status (GoalStatus.msg: commitment, goal_changed, committed_since, ...)."""
    msg.commitment = decision.reason.name
    msg.goal_changed = not decision.reason.keeps  # a goal chosen (or dropped) by this plan, not kept
    since = decision.committed.stamp_ns if decision.committed is not None else stamp_ns
    if since is not None and decision.goal is not None:
        set_stamp(msg.committed_since, since)
    msg.held_score, msg.best_score, msg.margin = (float(decision.held_score), float(decision.best_score),
                                                  float(decision.margin))
