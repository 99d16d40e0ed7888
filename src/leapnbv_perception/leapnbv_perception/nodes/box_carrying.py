"""detector_node's box carrying: the target's box carried into a frame instead of detected in it.

With ``detect_every_n_frames`` > 1 the detector runs on one admitted frame in n; in the others the
target's box is carried from the newest metric mesh (raster_node's ``human_mesh_metric``, of a frame
at most ``carry_max_age_s`` older) by its image motion between the camera poses of both frames
(:mod:`leapnbv_perception.box_tracking`), while the schedule allows and the carried box is trusted.
Each frame that could have been carried but was detected says why (``detected_instead.<reason>``).
"""
from __future__ import annotations

from typing import Any, List, Optional, Tuple

import numpy as np

from leapnbv_common.array_types import Float32Array
from leapnbv_common.camera_pose import create_camera_pose_source
from leapnbv_common.contracts import check_mesh_size, check_stamp_not_ahead, refused
from leapnbv_common.conversions import HumanMeshArrays, SerializedImage, human_mesh_to_arrays, stamp_to_ns
from leapnbv_common.diagnostics import rejects_bad_input
from leapnbv_common.pulled_input import PulledInput
from leapnbv_common.qos import stage_input_qos
from leapnbv_common.stage_inputs import human_mesh_face_count
from leapnbv_common.topics import CAMERA_POSE, HUMAN_MESH_METRIC
from leapnbv_msgs.msg import HumanMesh, InputStamp
from leapnbv_perception.box_tracking import CarriedBox, DetectionSchedule, camera_motion, carry_box

__all__ = ["BoxCarrier", "CARRY_POSE_CACHE"]

CARRY_POSE_CACHE = 90  # camera poses remembered for carrying boxes (3 s at 30 FPS)


class BoxCarrier:
    """The newest metric mesh, the camera poses and the detection schedule of a detector node.

    Args:
        node: The detector node (its ``params.value``: DetectorParams, ``diagnostics``, logger).
    """

    def __init__(self, node: Any) -> None:
        p = node.params.value
        self.node = node
        self.diagnostics = node.diagnostics
        self.get_logger = node.get_logger  # rejects_bad_input logs through it
        self.schedule = DetectionSchedule(p.detect_every_n_frames, p.carry_min_confidence)
        self.last_mesh: Optional[Tuple[int, str, HumanMeshArrays]] = None  # (stamp, frame_id, arrays)
        self.camera_poses: Any = None

    def start(self) -> None:
        """Activate: the mesh and camera-pose subscriptions, both pulled when a frame is decided.

        They do not wake the node; the base class releases both, and the source, on deactivate.
        """
        p = self.node.params.value
        self.mesh_input = PulledInput.create(self.node, HumanMesh, HUMAN_MESH_METRIC, self.on_mesh,
                                             stage_input_qos(1))
        self.camera_poses = self.node.owned(create_camera_pose_source(p.camera_pose_source, self.node,
                                                                      CARRY_POSE_CACHE))
        self.pose_input = PulledInput.adopt(self.node, self.camera_poses)
        self.node.get_logger().info(f"detecting one admitted frame in {p.detect_every_n_frames}; the target's box "
                                    f"is carried into the others (meshes up to {p.carry_max_age_s:g} s old)")

    @rejects_bad_input("bad_human_mesh")
    def on_mesh(self, msg: HumanMesh, info: Any) -> None:
        """The newest metric mesh of the target (raster_node), kept to carry its box into later frames."""
        self.diagnostics.input_seen("human_mesh_metric", info)
        stamp = stamp_to_ns(msg.header.stamp)
        # A mesh from the future would stay the newest for good; a mesh too large is refused before it is read.
        if refused(self.diagnostics, "bad_human_mesh", check_stamp_not_ahead, "human_mesh_metric", stamp,
                   self.node.get_clock().now().nanoseconds, self.node.params.value.max_stamp_ahead_s) or \
                refused(self.diagnostics, "bad_human_mesh", check_mesh_size, "human_mesh_metric",
                        len(msg.vertices) // 3, human_mesh_face_count(msg)):
            return
        if self.last_mesh is None or stamp > self.last_mesh[0]:  # the box comes from the vertices alone
            self.last_mesh = (stamp, msg.header.frame_id, human_mesh_to_arrays(msg, without_faces=True))

    def _carry(self, image: SerializedImage, stamp: int) -> Tuple[Optional[CarriedBox], str]:
        """The box carried from the newest mesh (or None) and, for None, why it was not."""
        if self.last_mesh is None:
            return None, "no_mesh"
        mesh_stamp, mesh_frame, mesh = self.last_mesh
        pose_a = self.camera_poses.pose_at(mesh_stamp, mesh_frame)
        pose_b = self.camera_poses.pose_at(stamp, image.header.frame_id)
        if not 0 < stamp - mesh_stamp <= self.node.params.value.carry_max_age_s * 1e9:
            return None, "mesh_too_old"
        if mesh_frame != image.header.frame_id or tuple(mesh.image_size) != (image.width, image.height):
            return None, "mesh_of_another_camera"
        if pose_a is None or pose_b is None:
            return None, "no_camera_pose"
        fx, fy, cx, cy = mesh.virtual_intrinsics  # the metric mesh carries the camera's intrinsics
        K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
        motion = camera_motion((pose_a.rotation, pose_a.position), (pose_b.rotation, pose_b.position))
        carried = carry_box(mesh.detection[:4], mesh.vertices, K, K, (image.width, image.height), motion)
        return carried, "mesh_not_in_view" if carried is None else "low_confidence"

    def carried_box(self, image: SerializedImage) -> Optional[Tuple[Float32Array, List[tuple]]]:
        """(boxes (1, 5), inputs) when this frame's target box is carried instead of detected; None: detect."""
        self.mesh_input.drain()
        if self.pose_input is not None:
            self.pose_input.drain()
        stamp = stamp_to_ns(image.header.stamp)
        carried, refused_because = self._carry(image, stamp)
        if carried is None or self.schedule.should_detect(carried):
            if not self.schedule.due():  # a frame that could have been carried: say why it was not
                self.diagnostics.count("detected_instead." + refused_because)
            self.schedule.record(True)
            return None
        assert self.last_mesh is not None  # (a box was carried from it)
        mesh_stamp, _, mesh = self.last_mesh
        self.schedule.record(False)
        self.diagnostics.count("boxes_carried")
        boxes = np.array([[*carried.box, mesh.detection[4]]], np.float32)
        inputs = [(HUMAN_MESH_METRIC, mesh_stamp, InputStamp.CARRIED), (CAMERA_POSE, stamp, InputStamp.SAME_FRAME),
                  (CAMERA_POSE, mesh_stamp, InputStamp.CARRIED)]
        return boxes, inputs
