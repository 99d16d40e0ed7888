"""When nbv_node's goal is too old to act on: the no-stale-goal rules, ROS-free (docs/ARCHITECTURE.md, "Timing").

A frame older than ``max_goal_age_s`` by the node clock is not planned, its goal not published, and a
latched goal that ages past it is withdrawn (past it plus ``hidden_target_goal_hold_s`` while the target is
NOT_SEEN: :func:`goal_age_limit_s`); a limit of 0 turns the rules off. ``goal_status.valid_until``
(:func:`valid_until_ns`) carries the same limit to a consumer, to check on its own clock.
"""
from __future__ import annotations

from typing import Optional

__all__ = ["too_old", "expired_age_s", "valid_until_ns", "goal_age_limit_s"]


def goal_age_limit_s(max_age_s: float, hidden_hold_s: float, target_hidden: bool) -> float:
    """How old a latched goal may grow before it is withdrawn (0: no limit stays none).

    ``max_age_s``, plus ``hidden_hold_s`` while the target is out of view but not lost: no frame can be
    planned then, and driving on is what brings the person back.
    """
    if max_age_s <= 0:
        return 0.0
    return max_age_s + (max(0.0, hidden_hold_s) if target_hidden else 0.0)


def too_old(now_ns: int, stamp_ns: int, max_age_s: float) -> bool:
    """Whether a frame of this stamp is older than ``max_age_s`` at ``now_ns`` (never with a limit of 0)."""
    return max_age_s > 0 and now_ns - stamp_ns > max_age_s * 1e9


def expired_age_s(now_ns: int, goal_stamp_ns: int, max_age_s: float) -> Optional[float]:
    """The age in seconds of a goal past its limit (to be withdrawn), or None while it may be acted on."""
    age_s = (now_ns - goal_stamp_ns) * 1e-9
    return age_s if max_age_s > 0 and age_s > max_age_s else None


def valid_until_ns(goal_stamp_ns: int, max_age_s: float) -> int:
    """Until when (ns, the node clock) a goal of this frame stamp may be acted on: stamp + limit; 0 for no limit.

    The last instant at which :func:`expired_age_s` still lets the goal stand (an age equal to the limit is
    not past it).
    """
    return int(goal_stamp_ns) + int(round(max_age_s * 1e9)) if max_age_s > 0 else 0
