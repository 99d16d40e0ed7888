"""The ground-truth backends: the simulator's truth in place of the detector and HMR engines.

A stand-in for evaluation and tests, never for a robot: the simulator publishes, per rendered frame,
a ``SceneGroundTruth`` (the target's box and SMPL-X parameters) and a ``ScenePeople`` (those of every
other person of the scene), both stamped like the frame. These backends read them as stage
companions (:class:`leapnbv_common.stage.Companion`), so the detector and HMR nodes only say which
backend they run; the simulator's topics and how their messages pair with a frame are declared
here, once. ScenePeople is waited for only while someone publishes it: a bag recorded before other
people existed has none, and its frames are one-person frames.

They know no more than a detector and an HMR would: the detector backend reports every visible
person (target and others alike, score 1) in an order that does not depend on who the target is
(largest box first, as a detector's confidence tends to follow a person's visible size), and the
mesh backend returns the mesh of the person whose box best matches the box it is given, so a
wrongly chosen person gives that person's mesh, as a learned HMR would.

This module is ROS glue (it declares subscriptions of message types); the math it calls (the body
model, the crop box) is in the ROS-free cores.
"""
from __future__ import annotations

import dataclasses
from typing import Any, Callable, List, Optional, Tuple

import numpy as np
from sensor_msgs.msg import CameraInfo

from leapnbv_common.contracts import check_boxes
from leapnbv_common.conversions import (
    HumanMeshArrays,
    SceneGroundTruthArrays,
    ScenePersonArrays,
    scene_ground_truth_to_arrays,
    scene_people_to_arrays,
)
from leapnbv_common.qos import camera_input_qos, stage_input_qos
from leapnbv_common.stage import DROP, REJECT, SAME_OR_LATEST, Companion, Frame
from leapnbv_common.stage_inputs import checked_camera_info
from leapnbv_common.topics import GROUND_TRUTH, SCENE_PEOPLE
from leapnbv_msgs.msg import SceneGroundTruth, ScenePeople
from leapnbv_perception.target_selection import box_iou
from leapnbv_perception.truth_corruption import (
    MESH_STREAM,
    NO_MESH_CORRUPTION,
    MeshCorruption,
    displaced_mesh,
    frame_rng,
    noisy_pose_and_shape,
)

__all__ = ["GROUND_TRUTH_BACKEND", "TRUTH_WAIT_S", "CAMERA_INFO_WAIT_S", "truth_companions", "people_published_on",
           "frame_truth",
           "GroundTruthMeshBackend", "ground_truth_boxes", "matched_person"]

#: The backend parameter value that selects these backends.
GROUND_TRUTH_BACKEND = "ground_truth"
#: How long a frame waits for the truth of its stamp (DDS does not order topics).
TRUTH_WAIT_S = 1.0
#: How long a ground-truth mesh waits for the camera_info of its stamp (then the latest: STATIC).
CAMERA_INFO_WAIT_S = 0.2


def truth_companions(capacity: int, people_published: Callable[[], bool],
                     wait_s: float = TRUTH_WAIT_S) -> List[Companion]:
    """The simulator's truth of the frame's stamp and its other people, checked on arrival.

    A frame whose truth does not come within ``wait_s`` is dropped (``dropped.ground_truth_unpaired``),
    never paired with another frame's truth; the same for its ScenePeople (``dropped.scene_people_unpaired``),
    which a frame needs only while ``people_published()`` (someone publishes the topic: the simulator
    does, a bag of one-person scenes does not). Read both with :func:`frame_truth`.
    """
    return [
        Companion("ground_truth", SceneGroundTruth, GROUND_TRUTH, scene_ground_truth_to_arrays,
                  stage_input_qos(capacity), wait_s=lambda frame: wait_s, when_missing=DROP,
                  missing_reason="ground_truth_unpaired", capacity=capacity, pulled=True),
        Companion(SCENE_PEOPLE, ScenePeople, SCENE_PEOPLE, scene_people_to_arrays, stage_input_qos(capacity),
                  wait_s=lambda frame: wait_s, when_missing=DROP, missing_reason="scene_people_unpaired",
                  needed=lambda frame: people_published(), capacity=capacity, pulled=True),
    ]


def people_published_on(node: Any) -> Callable[[], bool]:
    """Whether someone publishes the node's ScenePeople topic (its remapped name), asked per frame."""
    topic = node.resolve_topic_name(SCENE_PEOPLE)
    return lambda: node.count_publishers(topic) > 0


def frame_truth(frame: Frame) -> SceneGroundTruthArrays:
    """The frame's truth with its other people (none when the frame has no ScenePeople)."""
    truth: SceneGroundTruthArrays = frame["ground_truth"]
    people: Optional[List[ScenePersonArrays]] = frame[SCENE_PEOPLE]
    return truth if not people else dataclasses.replace(truth, others=list(people))


def _visible(box: np.ndarray) -> bool:
    return bool(box[2] > box[0] and box[3] > box[1])  # all zero when the person is not visible


def ground_truth_boxes(truth: SceneGroundTruthArrays, image_size: Tuple[int, int]) -> np.ndarray:
    """(N, 5) person boxes of a frame from its truth: every visible person's box (target and others), score 1.

    Ordered by box area, the largest first (ties: the leftmost first), which is how a detector's
    confidence tends to rank people (the bigger, the less occluded) and says nothing of which is the
    target.

    Raises:
        ContractError: a box outside the image (a truth that does not belong to this image).
    """
    boxes = [np.asarray(box, np.float64) for box in
             [truth.person_box] + [person.person_box for person in truth.others] if _visible(np.asarray(box))]
    if not boxes:
        return np.zeros((0, 5), np.float32)
    out = np.array([[b[0], b[1], b[2], b[3], 1.0] for b in boxes], np.float32)
    check_boxes(out, image_size, "ground-truth person box")
    area = (out[:, 2] - out[:, 0]).astype(np.float64) * (out[:, 3] - out[:, 1])
    return out[np.lexsort((out[:, 0], -area))]


def matched_person(truth: SceneGroundTruthArrays, box: np.ndarray) -> Optional[ScenePersonArrays]:
    """The person whose truth box best matches ``box``: None for the target, else the other person.

    The largest IoU with a visible person's box; when the box overlaps nobody's, the visible person
    whose box centre is nearest; the target when nobody is visible (then no mesh is right).
    """
    people: List[Tuple[Optional[ScenePersonArrays], np.ndarray]] = [(None, np.asarray(truth.person_box))]
    people += [(person, np.asarray(person.person_box)) for person in truth.others]
    visible = [(person, person_box) for person, person_box in people if _visible(person_box)]
    if not visible:
        return None
    overlaps = box_iou(np.asarray(box[:4], np.float64), np.array([b[:4] for _, b in visible], np.float64))
    best = int(np.argmax(overlaps))
    if overlaps[best] <= 0.0:
        centre = 0.5 * (np.asarray(box[:2], np.float64) + np.asarray(box[2:4], np.float64))
        distances = [float(np.linalg.norm(0.5 * (b[:2] + b[2:4]) - centre)) for _, b in visible]
        best = int(np.argmin(distances))
    return visible[best][0]


class GroundTruthMeshBackend:
    """HMR from the simulator's truth: the body model posed with the true SMPL-X parameters of the person
    the box shows (:func:`matched_person`: the target or another person), already metric in the real
    camera (its 'virtual' camera is the real one: the frame's camera_info K)."""

    name = GROUND_TRUTH_BACKEND

    @staticmethod
    def companions(capacity: int, people_published: Callable[[], bool]) -> List[Companion]:
        """What a frame takes besides its detections: its truth and other people, then its colour camera_info."""
        return [
            *truth_companions(capacity, people_published),
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
    def mesh(body_model: object, frame: Frame, box: np.ndarray, box_scale: float,
             corruption: MeshCorruption = NO_MESH_CORRUPTION) -> HumanMeshArrays:
        """The mesh of the person in ``box``; with a ``corruption`` (the error budget), as a worse model's
        (:mod:`leapnbv_perception.truth_corruption`: the frame's stamp seeds its draws)."""
        from leapnbv_common.conversions import camera_info_to_k
        from leapnbv_perception.hmr_crop import process_box, xyxy_to_xywh
        from leapnbv_perception.smplx_layer import SMPLXParams

        truth = frame_truth(frame)
        info: CameraInfo = frame["camera_info"]
        detections = frame.key.message
        image_size = (int(detections.image_width), int(detections.image_height))
        k = camera_info_to_k(info)
        person = matched_person(truth, box)
        if person is None:
            left, right, jaw, expression = (truth.left_hand_pose, truth.right_hand_pose, truth.jaw_pose,
                                            truth.expression)
            root, body, betas, translation = truth.root_pose, truth.body_pose, truth.betas, truth.translation
        else:  # another person: hands, jaw and expression neutral (ScenePerson carries none)
            left, right = np.zeros(45, np.float32), np.zeros(45, np.float32)
            jaw, expression = np.zeros(3, np.float32), np.zeros(10, np.float32)
            root, body, betas, translation = person.root_pose, person.body_pose, person.betas, person.translation
        if corruption.active:
            rng = frame_rng(corruption.seed, frame.stamp_ns, MESH_STREAM)

            def vertices_of(body_pose: np.ndarray, shape: np.ndarray) -> np.ndarray:
                posed = SMPLXParams.from_axis_angle(root, body_pose, left, right, jaw, shape, expression)
                return body_model.forward(posed).vertices  # type: ignore[attr-defined]

            body, betas, _ = noisy_pose_and_shape(body, betas, vertices_of, corruption.pa_mpvpe_mm, rng)
            body, betas = body.astype(np.float32), betas.astype(np.float32)
        params = SMPLXParams.from_axis_angle(root, body, left, right, jaw, betas, expression)
        vertices = body_model.forward(params).vertices + translation  # type: ignore[attr-defined]
        if corruption.active:
            vertices, translation = displaced_mesh(vertices, translation, box, k, corruption.shift,
                                                   corruption.depth, rng)
            vertices, translation = vertices.astype(np.float32), translation.astype(np.float32)
        return HumanMeshArrays(
            vertices=vertices, faces=body_model.faces,  # type: ignore[attr-defined]
            virtual_intrinsics=(k[0, 0], k[1, 1], k[0, 2], k[1, 2]), image_size=image_size, detection=box,
            processed_box=process_box(xyxy_to_xywh(box[:4]), image_size[0], image_size[1], scale=box_scale),
            root_pose=root, body_pose=body, left_hand_pose=left, right_hand_pose=right, jaw_pose=jaw, betas=betas,
            expression=expression, cam_translation=translation, model_id="ground_truth")
