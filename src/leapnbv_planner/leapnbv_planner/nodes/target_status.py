"""nbv_node's view of the target: the newest TargetTrack of hmr_node, in every goal_status, and its changes.

hmr_node decides which person is the target and publishes a ``TargetTrack`` per detections frame (topic
``target_track``; :mod:`leapnbv_perception.target_tracking`). This node:

- copies the newest one (by stamp) into every ``goal_status`` (``GoalStatus.target``; state NONE with zeros
  before one came);
- re-publishes ``goal_status`` at once, with the latched goal's state unchanged and ``goal_changed`` false,
  when the target's state or ``track_id`` changes (TRACKED -> NOT_SEEN, a new target, ...): a motion stack
  learns that the target is out of view without waiting for the goal to age out;
- withdraws a CURRENT goal when the target is LOST (``STATE_STALE``, reason "target lost: ..."; "no goal"
  on the goal topics, as an aged-out goal): a goal planned around a person no longer followed must not be
  acted on, also where ``max_goal_age_s`` is 0 (offline runs) and would keep it for ever;
- forgets the committed goal when another person becomes the target (a new ``track_id``): it was planned
  around the previous one; the next plan commits afresh.

While the target is NOT_SEEN the goal stays CURRENT until it ages out, with ``hidden_target_goal_hold_s`` more
than ``max_goal_age_s`` (``valid_until`` says so): driving to it is what may bring the person back into view
(the path passes behind furniture that hides them, and no frame can be planned meanwhile), and
``goal_status.target`` says where the track predicts them.
"""
from __future__ import annotations

from typing import Any, Callable, Optional

from leapnbv_common.contracts import check_stamp_not_ahead
from leapnbv_common.conversions import stamp_to_ns
from leapnbv_common.diagnostics import rejects_bad_input
from leapnbv_common.qos import stage_input_qos
from leapnbv_common.stamp_cache import STAMP_RESTART_NS
from leapnbv_common.topics import TARGET_TRACK
from leapnbv_msgs.msg import TargetTrack

__all__ = ["TargetTrackInput", "STATE_NAMES", "describe"]

STATE_NAMES = {TargetTrack.STATE_NONE: "NONE", TargetTrack.STATE_TRACKED: "TRACKED",
               TargetTrack.STATE_NOT_SEEN: "NOT_SEEN", TargetTrack.STATE_LOST: "LOST"}


class TargetTrackInput:
    """The newest TargetTrack received and the callback that its changes call.

    Args:
        node: The nbv node (its ``diagnostics``, clock, ``params.value.max_stamp_ahead_s``).
        on_change: Called with (the new track, the previous one or None) when the state or track_id changed.
    """

    def __init__(self, node: Any, on_change: Callable[[TargetTrack, Optional[TargetTrack]], None]) -> None:
        self.node = node
        self.diagnostics = node.diagnostics
        self.get_logger = node.get_logger  # rejects_bad_input logs through it
        self.on_change = on_change
        self.latest: Optional[TargetTrack] = None

    def subscribe(self) -> None:
        """Subscribe (activate; the base class destroys the subscription on deactivate).

        A new activation starts without a target.
        """
        self.latest = None
        self.node.create_subscription(TargetTrack, TARGET_TRACK, self.on_message, stage_input_qos(5))

    def current(self) -> TargetTrack:
        """The newest TargetTrack, or one of state NONE with zeros before any came."""
        return self.latest if self.latest is not None else TargetTrack()

    @rejects_bad_input("bad_target_track")
    def on_message(self, msg: TargetTrack, info: Any) -> None:  # two arguments: rclpy passes the MessageInfo
        self.diagnostics.input_seen(TARGET_TRACK, info)
        if msg.state not in STATE_NAMES:
            raise ValueError(f"target_track state {msg.state} is not one of {sorted(STATE_NAMES)}")
        stamp = stamp_to_ns(msg.header.stamp)
        check_stamp_not_ahead(TARGET_TRACK, stamp, self.node.get_clock().now().nanoseconds,
                              self.node.params.value.max_stamp_ahead_s)
        previous = self.latest
        if previous is not None and 0 < stamp_to_ns(previous.header.stamp) - stamp < STAMP_RESTART_NS:
            self.diagnostics.drop("target_track_older_than_latest")  # (further back: the stamps started over)
            return
        self.latest = msg
        if previous is None or (previous.state, previous.track_id) != (msg.state, msg.track_id):
            self.on_change(msg, previous)


def describe(track: TargetTrack) -> str:
    """One line about a target: its state, id and why (for goal_status.reason)."""
    return f"target {STATE_NAMES.get(track.state, str(track.state))} (track {track.track_id}): {track.reason}"
