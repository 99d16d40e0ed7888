"""The messages a RealSense driver (plus the simulator's ground truth) publishes for one rendered frame.

The simulator node publishes them and the sample bags record them: both build them here. This
module is the simulator's ROS glue (messages and their serialization); the rest of leapnbv_sim
stays ROS-free.
"""
from __future__ import annotations

from typing import Dict, Iterable, Iterator, Optional, Tuple

import numpy as np
from geometry_msgs.msg import PoseStamped
from rclpy.serialization import serialize_message
from std_msgs.msg import Header
from tf2_msgs.msg import TFMessage

from leapnbv_common.camera_pose.tf_messages import tf_message
from leapnbv_common.conversions import (
    SceneGroundTruthArrays,
    ScenePersonArrays,
    arrays_to_scene_ground_truth,
    arrays_to_scene_people,
    header_with_stamp,
    make_camera_info,
    numpy_to_image,
    pose_msg,
)
from leapnbv_common.topics import (
    COLOR_IMAGE_TOPIC,
    COLOR_INFO_TOPIC,
    DEPTH_IMAGE_TOPIC,
    DEPTH_INFO_TOPIC,
    GROUND_TRUTH_TOPIC,
    SCENE_PEOPLE_TOPIC,
)
from leapnbv_msgs.msg import SceneGroundTruth, ScenePeople
from leapnbv_sim.poses import CameraPose
from leapnbv_sim.render import PersonGroundTruth, RenderedFrame
from leapnbv_sim.robot_frames import RobotFrameIds, dynamic_links, static_links


def _box_with_score(box_xyxy: Optional[Tuple[int, int, int, int]]) -> np.ndarray:
    """[x0, y0, x1, y1, 1] of a visible box; all zero (score 0) for None."""
    return np.zeros(5) if box_xyxy is None else np.array(list(box_xyxy) + [1.0])


def _scene_person(person: PersonGroundTruth) -> ScenePersonArrays:
    params = person.body_params_camera
    return ScenePersonArrays(object_id=person.object_id, person_box=_box_with_score(person.box_xyxy),
                             root_pose=params.root_pose, body_pose=params.body_pose, betas=params.betas,
                             translation=person.translation_camera, occlusion_share=person.occlusion_share)


def scene_ground_truth_msg(header: Header, frame: RenderedFrame, body_model_id: str) -> SceneGroundTruth:
    """leapnbv_msgs/SceneGroundTruth of a rendered frame: the target (an all-zero box, score 0, when it is not visible).

    Args:
        header: The frame's header.
        frame: The rendered frame (its ``ground_truth``).
        body_model_id: Which body model the parameters belong to.

    Returns:
        The message.
    """
    truth = frame.ground_truth
    params = truth.body_params_camera
    return arrays_to_scene_ground_truth(SceneGroundTruthArrays(
        person_box=_box_with_score(truth.person_box_xyxy), root_pose=params.root_pose, body_pose=params.body_pose,
        left_hand_pose=params.left_hand_pose, right_hand_pose=params.right_hand_pose, jaw_pose=params.jaw_pose,
        betas=params.betas, expression=params.expression, translation=truth.translation_camera,
        occlusion_share=truth.occlusion_share, body_model_id=body_model_id), header)


def scene_people_msg(header: Header, frame: RenderedFrame) -> ScenePeople:
    """leapnbv_msgs/ScenePeople of a rendered frame: every person but the target, visible or not.

    In object id order; empty in a one-person scene.
    """
    return arrays_to_scene_people([_scene_person(person) for person in frame.ground_truth.others], header)


def robot_tf_message(camera: CameraPose, stamp_ns: int, ids: RobotFrameIds) -> TFMessage:
    """/tf of one frame: the robot's moving links (world -> odom -> base -> camera link) at the frame's stamp."""
    return tf_message(dynamic_links(camera, stamp_ns, ids))


def robot_static_tf_message(ids: RobotFrameIds) -> TFMessage:
    """/tf_static: the robot's fixed links (camera link -> optical frame), one message for all of them."""
    return tf_message(static_links(ids))


def camera_frame_messages(frame: RenderedFrame, header: Header, body_model_id: str) -> Dict[str, object]:
    """Absolute topic -> message for one frame: both camera infos, the ground truth, the other people, colour and depth.

    In this order (the order the simulator publishes them: calibration before the images). The
    depth is aligned to colour, so both camera infos are the same message.
    """
    height, width = frame.depth_mm.shape
    info = make_camera_info(frame.K, width, height, header)
    return {
        COLOR_INFO_TOPIC: info,
        DEPTH_INFO_TOPIC: info,
        GROUND_TRUTH_TOPIC: scene_ground_truth_msg(header, frame, body_model_id),
        SCENE_PEOPLE_TOPIC: scene_people_msg(header, frame),
        COLOR_IMAGE_TOPIC: numpy_to_image(np.ascontiguousarray(frame.rgb), "rgb8", header),
        DEPTH_IMAGE_TOPIC: numpy_to_image(np.ascontiguousarray(frame.depth_mm), "16UC1", header),
    }


def camera_pose_message(camera: CameraPose, header: Header, world_frame_id: str) -> PoseStamped:
    """The camera pose topic's message of a frame, as the simulator publishes it.

    T_world_camera_optical in ``world_frame_id``, stamped with the frame's ``header``.
    """
    return PoseStamped(header=Header(frame_id=world_frame_id, stamp=header.stamp),
                       pose=pose_msg(camera.rotation, camera.position))


def serialized_camera_frames(
    frames: Iterable[Tuple[int, RenderedFrame]], frame_id: str, body_model_id: str, topics: Iterable[str],
    camera_pose: Optional[Tuple[str, str]] = None,
) -> Iterator[Tuple[str, int, bytes]]:
    """(topic, stamp, CDR bytes) of each frame's messages, as a bag records them.

    Args:
        frames: (stamp in nanoseconds, rendered frame) pairs; the stamp goes into every header.
        frame_id: Optical frame of the colour camera.
        body_model_id: Stored in each SceneGroundTruth.
        topics: Which of :func:`camera_frame_messages`' topics to serialize, in this order.
        camera_pose: (topic, world frame id): also each frame's camera pose (:func:`camera_pose_message`), after
            the frame's other messages (as the simulator publishes it); None: no camera pose.

    Yields:
        The serialized messages, frame by frame, ``topics`` in order within a frame.
    """
    order = list(topics)
    for stamp, frame in frames:
        messages = camera_frame_messages(frame, header_with_stamp(stamp, frame_id), body_model_id)
        for topic in order:
            yield topic, stamp, serialize_message(messages[topic])
        if camera_pose is not None:
            header = header_with_stamp(stamp, frame_id)
            yield camera_pose[0], stamp, serialize_message(camera_pose_message(frame.camera_pose, header,
                                                                               camera_pose[1]))
