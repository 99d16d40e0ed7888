"""The ground-truth backends: the simulator's truth in place of the detector and HMR engines.

A stand-in for evaluation and tests, never for a robot: the simulator publishes, per rendered frame,
a ``SceneGroundTruth`` (the person's box and SMPL-X parameters, stamped like the frame). These
backends read it as a stage companion (:class:`leapnbv_common.stage.Companion`), so the detector and
HMR nodes only say which backend they run; the simulator's topic and how its messages pair with a
frame are declared here, once.

This module is ROS glue (it declares subscriptions of message types); the math it calls (the body
model, the crop box) is in the ROS-free cores.
"""
from __future__ import annotations

from typing import Any, List, Tuple

import numpy as np
from sensor_msgs.msg import CameraInfo

from leapnbv_common.contracts import check_boxes
from leapnbv_common.conversions import HumanMeshArrays, SceneGroundTruthArrays, scene_ground_truth_to_arrays
from leapnbv_common.qos import camera_input_qos, stage_input_qos
from leapnbv_common.stage import DROP, REJECT, SAME_OR_LATEST, Companion, Frame
from leapnbv_common.stage_inputs import checked_camera_info
from leapnbv_common.topics import GROUND_TRUTH
from leapnbv_msgs.msg import SceneGroundTruth

__all__ = ["GROUND_TRUTH_BACKEND", "TRUTH_WAIT_S", "CAMERA_INFO_WAIT_S", "truth_companion", "GroundTruthMeshBackend",
           "ground_truth_boxes"]

#: The backend parameter value that selects these backends.
GROUND_TRUTH_BACKEND = "ground_truth"
#: How long a frame waits for the truth of its stamp (DDS does not order topics).
TRUTH_WAIT_S = 1.0
#: How long a ground-truth mesh waits for the camera_info of its stamp (then the latest: STATIC).
CAMERA_INFO_WAIT_S = 0.2


def truth_companion(capacity: int, wait_s: float = TRUTH_WAIT_S) -> Companion:
    """The simulator's truth of the frame's stamp, checked on arrival (finite values, a box or none).

    A frame whose truth does not come within ``wait_s`` is dropped (``detections_unpaired``-style:
    ``dropped.ground_truth_unpaired``), never paired with another frame's truth.
    """
    return Companion("ground_truth", SceneGroundTruth, GROUND_TRUTH, scene_ground_truth_to_arrays,
                     stage_input_qos(capacity), wait_s=lambda frame: wait_s, when_missing=DROP,
                     missing_reason="ground_truth_unpaired", capacity=capacity, pulled=True)


def ground_truth_boxes(truth: SceneGroundTruthArrays, image_size: Tuple[int, int]) -> np.ndarray:
    """(N, 5) person boxes of a frame from its truth: the visible person's box with score 1, or none.

    Raises:
        ContractError: a box outside the image (a truth that does not belong to this image).
    """
    box = truth.person_box  # all zero when no person is visible
    if not (box[2] > box[0] and box[3] > box[1]):
        return np.zeros((0, 5), np.float32)
    check_boxes(box, image_size, "ground-truth person box")
    return np.array([[box[0], box[1], box[2], box[3], 1.0]], np.float32)


class GroundTruthMeshBackend:
    """HMR from the simulator's truth: the body model posed with the true SMPL-X parameters, already
    metric in the real camera (its 'virtual' camera is the real one: the frame's camera_info K)."""

    name = GROUND_TRUTH_BACKEND

    @staticmethod
    def companions(capacity: int) -> List[Companion]:
        """What a frame takes besides its detections: its truth, then its colour camera_info."""
        return [
            truth_companion(capacity),
            Companion("camera_info", CameraInfo, "camera_info", checked_camera_info, camera_input_qos(capacity),
                      match=SAME_OR_LATEST, wait_s=lambda frame: CAMERA_INFO_WAIT_S, when_missing=REJECT,
                      missing_reason="bad_frame",
                      missing_detail=lambda frame: "no camera_info received yet (ground-truth meshes use the real"
                      " intrinsics)", capacity=capacity, pulled=True, bad_reason="bad_camera_info"),
        ]

    @staticmethod
    def reference(frame: Frame) -> Tuple[str, Any]:
        """The input the detections must agree with (frame_id, image size): the camera_info."""
        return "camera_info", frame["camera_info"]

    @staticmethod
    def mesh(body_model: object, frame: Frame, box: np.ndarray, box_scale: float) -> HumanMeshArrays:
        from leapnbv_common.conversions import camera_info_to_k
        from leapnbv_perception.hmr_crop import process_box, xyxy_to_xywh
        from leapnbv_perception.smplx_layer import SMPLXParams

        truth: SceneGroundTruthArrays = frame["ground_truth"]
        info: CameraInfo = frame["camera_info"]
        detections = frame.key.message
        image_size = (int(detections.image_width), int(detections.image_height))
        k = camera_info_to_k(info)
        params = SMPLXParams.from_axis_angle(truth.root_pose, truth.body_pose, truth.left_hand_pose,
                                             truth.right_hand_pose, truth.jaw_pose, truth.betas, truth.expression)
        vertices = body_model.forward(params).vertices + truth.translation  # type: ignore[attr-defined]
        return HumanMeshArrays(
            vertices=vertices, faces=body_model.faces,  # type: ignore[attr-defined]
            virtual_intrinsics=(k[0, 0], k[1, 1], k[0, 2], k[1, 2]), image_size=image_size, detection=box,
            processed_box=process_box(xyxy_to_xywh(box[:4]), image_size[0], image_size[1], scale=box_scale),
            root_pose=truth.root_pose, body_pose=truth.body_pose, left_hand_pose=truth.left_hand_pose,
            right_hand_pose=truth.right_hand_pose, jaw_pose=truth.jaw_pose, betas=truth.betas,
            expression=truth.expression, cam_translation=truth.translation, model_id="ground_truth")
