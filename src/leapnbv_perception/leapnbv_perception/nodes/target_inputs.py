"""hmr_node's target tracking: its inputs (depth, depth camera_info, camera pose), the tracker, target_track.

Which detection is the target is decided by :class:`leapnbv_perception.target_tracking.TargetTracker` from the
frame's boxes, its depth frame (aligned to the colour image; the ``depth`` companion, nearest stamp within
``depth_slop_s``), that depth frame's camera_info and the frame's camera pose (the ``camera_pose`` companion,
from the shared camera-pose source: :mod:`leapnbv_common.camera_pose`). Depth frames and poses are pulled when
detections come (they do not wake the node) and waited for at most ``target_input_wait_s``, and only once
such inputs have come: a graph without them is not slowed, its frames are decided in the image only. Every
decided frame publishes a ``TargetTrack`` (topic ``target_track``), with a target or without one.
"""
from __future__ import annotations

from typing import Any, List, Optional, Tuple

import numpy as np
from geometry_msgs.msg import Point, Vector3
from sensor_msgs.msg import CameraInfo, Image
from std_msgs.msg import Header

from leapnbv_common.camera_pose import CameraPoseSource, StampedCameraPose, create_camera_pose_source
from leapnbv_common.conversions import ConversionError, camera_info_to_k, depth_to_metres, image_size, set_stamp
from leapnbv_common.pulled_input import PulledInput
from leapnbv_common.qos import camera_input_qos, stage_output_qos
from leapnbv_common.stage import NEAREST, SAME_OR_LATEST, Companion, Frame, Received
from leapnbv_common.stage_inputs import checked_camera_info, checked_depth_image
from leapnbv_common.topics import TARGET_TRACK
from leapnbv_msgs.msg import TargetTrack
from leapnbv_perception.params import HmrParams
from leapnbv_perception.target_tracking import MODE_IMAGE, TargetDecision, TargetTracker, TrackerConfig

__all__ = ["TargetInputs", "tracker_config", "target_track_msg", "POSE_CACHE"]

POSE_CACHE = 90  # camera poses remembered by stamp (3 s at 30 FPS)


def tracker_config(p: HmrParams) -> TrackerConfig:
    """The tracker's settings from hmr_node's parameters (read per frame: live)."""
    return TrackerConfig(fixed_frame=p.track_in_fixed_frame, follow=p.track_previous_target, gate_m=p.target_gate_m,
                         gate_growth_m_s=p.target_gate_growth_m_s, lost_after_s=p.target_lost_after_s,
                         min_track_iou=p.min_track_iou, central_share=p.target_depth_share,
                         ambiguity_m=p.target_ambiguity_m, reacquire_window_s=p.target_reacquire_window_s,
                         reacquire_radius_m=p.target_reacquire_radius_m,
                         max_person_extent_m=p.target_max_person_extent_m, coast_s=p.target_coast_s)


def target_track_msg(decision: TargetDecision, header: Header) -> TargetTrack:
    """The TargetTrack message of a decision, in the frame's header."""
    msg = TargetTrack(header=header, state=int(decision.state), detection_index=int(decision.detection_index),
                      track_id=int(decision.track_id), fixed_frame=decision.fixed_frame, reason=decision.reason,
                      position_sigma_m=float(decision.position_sigma_m))
    x, y, z = (float(v) for v in decision.position)
    msg.position = Point(x=x, y=y, z=z)
    vx, vy, vz = (float(v) for v in decision.velocity)
    msg.velocity = Vector3(x=vx, y=vy, z=vz)
    if decision.last_seen_ns > 0:
        set_stamp(msg.last_seen, decision.last_seen_ns)
    return msg


class TargetInputs:
    """The tracking companions of hmr_node's stage, the tracker and the target_track publisher.

    Args:
        node: The hmr node (its ``params.value``: HmrParams, ``diagnostics``, ``stage`` once made).
    """

    def __init__(self, node: Any) -> None:
        self.node = node
        self.tracker = TargetTracker(tracker_config(node.params.value))
        self.publisher = node.create_lifecycle_publisher(TargetTrack, TARGET_TRACK, stage_output_qos())
        self.source: Optional[CameraPoseSource] = None
        self.poses_seen = False  # a camera pose has come (frames wait for theirs from then on)

    def companions(self) -> List[Companion]:
        """The depth frame (nearest stamp), its camera_info (its own or the latest) and the camera pose."""
        p = self.node.params.value
        depth = Companion("depth", Image, "depth", checked_depth_image, camera_input_qos(p.cache_size),
                          match=NEAREST, slop_s=lambda f: self.node.params.value.depth_slop_s,
                          wait_s=lambda f: self.wait_s("depth" in self.node.stage.latest),
                          needed=lambda f: bool(self.node.params.value.track_in_fixed_frame),
                          capacity=p.cache_size, raw=True, pulled=True, consume=True, skip_older=True)
        info = Companion("depth/camera_info", CameraInfo, "depth/camera_info", checked_camera_info,
                         camera_input_qos(p.cache_size), match=SAME_OR_LATEST, stamp_from="depth",
                         needed=lambda f: f.has("depth"), capacity=p.cache_size, pulled=True,
                         bad_reason="bad_camera_info")
        pose = Companion("camera_pose", lookup=self.lookup, wait_s=lambda f: self.wait_s(self.poses_seen),
                         needed=lambda f: bool(self.node.params.value.track_in_fixed_frame), expect=self.expect)
        return [depth, info, pose]

    def attach(self) -> None:
        """Make the camera-pose source, after the stage (its poses wake frames waiting in it).

        It is released with the configure's entities on cleanup (ManagedNode.owned).
        """
        self.source = self.node.owned(create_camera_pose_source(self.node.params.value.camera_pose_source,
                                                                self.node, POSE_CACHE, self.on_pose))
        self.node.stage.add_pulled(PulledInput.adopt(self.node, self.source))  # None for a source without one

    def wait_s(self, flowing: bool) -> float:
        return float(self.node.params.value.target_input_wait_s) if flowing else 0.0

    def on_pose(self, pose: StampedCameraPose) -> None:
        self.poses_seen = True
        self.node.stage.companion_arrived("camera_pose")

    def lookup(self, frame: Frame) -> Optional[Received]:
        pose = None if self.source is None else self.source.pose_at(frame.stamp_ns, frame.header.frame_id)
        return None if pose is None else Received(pose.stamp_ns, frame.header, pose)

    def expect(self, frame: Frame) -> None:
        if self.source is not None:
            self.source.expect(frame.stamp_ns, frame.header.frame_id)

    def reset(self) -> None:
        """The stamps started over: forget the target (a replay from its start, a simulator reset)."""
        self.tracker.reset()

    # ------------------------------------------------------------------ the decision

    def depth_of(self, frame: Frame) -> Tuple[Optional[np.ndarray], Optional[np.ndarray], str]:
        """(depth in metres, its camera's K, "") of the frame, or (None, None, why not)."""
        depth, info = frame["depth"], frame["depth/camera_info"]
        if depth is None or info is None:
            return None, None, "no depth frame"
        if image_size(depth) != image_size(info) or depth.header.frame_id != info.header.frame_id:
            return None, None, "the depth frame disagrees with its camera_info"
        try:
            return depth_to_metres(depth), camera_info_to_k(info), ""
        except ConversionError as error:
            return None, None, str(error)

    def decide(self, frame: Frame, boxes: np.ndarray, size: Tuple[int, int]) -> TargetDecision:
        """The frame's target (published on target_track, counted on /diagnostics)."""
        p = self.node.params.value
        self.tracker.config = tracker_config(p)
        depth, k, why = self.depth_of(frame) if p.track_in_fixed_frame else (None, None, "")
        if why and frame.has("depth"):
            self.node.diagnostics.reject("bad_depth", f"target tracking without depth: {why}")
        pose: Optional[StampedCameraPose] = frame["camera_pose"]
        decision = self.tracker.update(frame.stamp_ns, boxes, size, depth, k, pose)
        self.node.diagnostics.count("target." + decision.state_name.lower())
        if decision.mode == MODE_IMAGE and p.track_in_fixed_frame:
            self.node.diagnostics.count("target.image_only")
        if decision.acquired:
            self.node.diagnostics.count("target.acquired")
        self.publisher.publish(target_track_msg(decision, frame.key.message.header))
        return decision
