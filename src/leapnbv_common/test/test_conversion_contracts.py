"""The conversion functions apply the message contracts: a message that breaks one never becomes arrays."""
from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("sensor_msgs.msg")
pytest.importorskip("leapnbv_msgs.msg")

from geometry_msgs.msg import PoseStamped  # noqa: E402
from sensor_msgs.msg import Image  # noqa: E402

from leapnbv_common import conversions as cv  # noqa: E402
from leapnbv_common.camera_pose import camera_pose_from_msg  # noqa: E402
from leapnbv_common.contracts import ContractError  # noqa: E402
from leapnbv_msgs.msg import GroundPlane, PersonDetection, PersonDetections, SceneGroundTruth  # noqa: E402

pytestmark = pytest.mark.ros
NAN = float("nan")
K = np.array([[615.0, 0.0, 320.0], [0.0, 615.0, 240.0], [0.0, 0.0, 1.0]])
HEADER = cv.header_with_stamp(1_700_000_000_000_000_000, "camera_color_optical_frame")


def plane_msg(normal, offset, valid=True, source=GroundPlane.SOURCE_RANSAC) -> GroundPlane:
    return cv.arrays_to_ground_plane(cv.GroundPlaneArrays(np.asarray(normal, float), offset, valid, source), HEADER)


def test_ground_plane_messages_are_checked():
    up = np.array([0.0, -0.96, -0.28]) / np.linalg.norm([0.0, -0.96, -0.28])
    plane = cv.ground_plane_to_arrays(plane_msg(up, 1.25))
    np.testing.assert_allclose(plane.normal, up)
    assert not cv.ground_plane_to_arrays(plane_msg([0.0, 0.0, 0.0], 0.0, valid=False)).valid
    for normal, offset, message in [(-up, 1.25, "points down"), (2 * up, 1.25, "not unit"),
                                    (up, -1.25, "below the floor"), ([NAN] * 3, 1.25, "not finite")]:
        with pytest.raises(cv.ConversionError, match=message):
            cv.ground_plane_to_arrays(plane_msg(normal, offset))
    with pytest.raises(cv.ConversionError, match="source 9"):
        cv.ground_plane_to_arrays(plane_msg(up, 1.25, source=9))
    assert issubclass(cv.ConversionError, ContractError) and issubclass(cv.ConversionError, ValueError)


def test_detections_are_checked_and_a_nan_score_refused():
    msg = PersonDetections(header=HEADER, image_width=640, image_height=480)
    msg.detections = [PersonDetection(x_min=10.0, y_min=20.0, x_max=200.0, y_max=400.0, score=0.9)]
    np.testing.assert_allclose(cv.detections_to_boxes(msg), [[10, 20, 200, 400, 0.9]], rtol=1e-6)
    for field, value, message in [("score", NAN, "not finite"), ("score", 1.2, r"outside \[0, 1\]"),
                                  ("x_max", 5.0, "inverted"), ("x_min", 900.0, "inverted"),
                                  ("y_max", float("inf"), "not finite")]:
        bad = PersonDetections(header=HEADER, image_width=640, image_height=480)
        det = PersonDetection(x_min=10.0, y_min=20.0, x_max=200.0, y_max=400.0, score=0.5)
        setattr(det, field, value)
        bad.detections = [msg.detections[0], det]
        with pytest.raises(cv.ConversionError, match=message):
            cv.detections_to_boxes(bad)
    with pytest.raises(cv.ConversionError, match="image size 0x480"):
        cv.detections_to_boxes(PersonDetections(header=HEADER, image_width=0, image_height=480))


def test_camera_info_target_geometry_and_ground_truth_are_checked():
    assert cv.camera_info_to_k(cv.make_camera_info(K, 640, 480)).shape == (3, 3)
    with pytest.raises(cv.ConversionError, match="principal point"):
        cv.camera_info_to_k(cv.make_camera_info(K, 200, 150))
    with pytest.raises(cv.ConversionError, match="empty"):
        cv.camera_info_to_k(cv.make_camera_info(K, 0, 0))

    points = np.array([[0.0, 0.5, 3.0], [0.1, 0.4, 3.1]], np.float32)
    target = cv.TargetGeometryArrays(points, np.zeros((0, 3), np.float32), points.mean(0), points.min(0),
                                     points.max(0), 10, 0.5, 0.0, True, K, 640, 480)
    msg = cv.arrays_to_target_geometry(target, HEADER)
    assert cv.target_geometry_to_arrays(msg).valid
    msg.centroid.x = NAN
    with pytest.raises(cv.ConversionError, match="centroid has 1 non-finite"):
        cv.target_geometry_to_arrays(msg)
    msg = cv.arrays_to_target_geometry(target, HEADER)
    msg.camera_info.header = cv.header_with_stamp(1_700_000_000_000_000_000, "camera_depth_optical_frame")
    with pytest.raises(cv.ConversionError, match="its camera_info in 'camera_depth_optical_frame'") as error:
        cv.target_geometry_to_arrays(msg)
    assert error.value.reason == "frame_id_mismatch"
    empty = cv.arrays_to_target_geometry(
        cv.TargetGeometryArrays(np.zeros((0, 3), np.float32), np.zeros((0, 3), np.float32), np.zeros(3),
                                np.zeros(3), np.zeros(3), 0, 0.0, 0.0, True, K, 640, 480), HEADER)
    with pytest.raises(cv.ConversionError, match="marked valid but has no target points"):
        cv.target_geometry_to_arrays(empty)

    truth = SceneGroundTruth(header=HEADER)
    truth.person_box = PersonDetection(x_min=10.0, y_min=20.0, x_max=200.0, y_max=400.0, score=1.0)
    assert cv.scene_ground_truth_to_arrays(truth).person_box[2] == 200.0
    assert not np.any(cv.scene_ground_truth_to_arrays(SceneGroundTruth(header=HEADER)).person_box)  # nobody
    truth.translation[2] = NAN
    with pytest.raises(cv.ConversionError, match="translation has 1 non-finite"):
        cv.scene_ground_truth_to_arrays(truth)
    truth.translation[2] = 3.0
    truth.person_box.x_max = 5.0
    with pytest.raises(cv.ConversionError, match="inverted"):
        cv.scene_ground_truth_to_arrays(truth)


def test_human_mesh_parameters_and_images_are_checked():
    vertices = np.array([[0.0, 0.0, 3.0], [0.1, 0.0, 3.0], [0.0, 0.1, 3.0]], np.float32)
    zeros = {name: np.zeros(size, np.float32) for name, size in cv._MESH_PARAM_SIZES.items()}
    mesh = cv.HumanMeshArrays(vertices=vertices, faces=np.array([[0, 1, 2]], np.uint32),
                              virtual_intrinsics=(615.0, 615.0, 320.0, 240.0), image_size=(640, 480),
                              detection=np.array([1, 1, 50, 50, 1.0], np.float32), **zeros)
    assert cv.human_mesh_to_arrays(cv.arrays_to_human_mesh(mesh, HEADER)).image_size == (640, 480)
    mesh.cam_translation = np.array([0.0, NAN, 3.0], np.float32)
    with pytest.raises(cv.ConversionError, match="cam_translation has 1 non-finite"):
        cv.human_mesh_to_arrays(cv.arrays_to_human_mesh(mesh, HEADER))

    depth = cv.numpy_to_image(np.zeros((4, 6), np.uint16), "16UC1", HEADER)
    assert cv.check_image(depth, cv.DEPTH_ENCODINGS, "depth") == (6, 4)
    with pytest.raises(cv.ConversionError, match="depth image expected"):
        cv.check_image(cv.numpy_to_image(np.zeros((4, 6, 3), np.uint8), "rgb8"), cv.DEPTH_ENCODINGS, "depth")
    short = Image(header=HEADER, height=4, width=6, encoding="16UC1", step=12, data=bytes(20))
    with pytest.raises(cv.ConversionError, match="needs 48 bytes"):
        cv.check_image(short, cv.DEPTH_ENCODINGS, "depth")


def test_a_camera_pose_below_the_floor_or_not_unit_is_refused_the_same_way_everywhere():
    def pose(position, quaternion=(0.0, 0.0, 0.0, 1.0)) -> PoseStamped:
        msg = PoseStamped(header=cv.header_with_stamp(5, "map"))
        msg.pose.position.x, msg.pose.position.y, msg.pose.position.z = position
        q = msg.pose.orientation
        q.x, q.y, q.z, q.w = quaternion
        return msg

    assert camera_pose_from_msg(pose((1.0, 2.0, 1.2))).position[2] == 1.2
    for msg, message in [(pose((1.0, 2.0, -0.1)), "not above the floor"), (pose((1.0, 2.0, 0.0)), "above the floor"),
                         (pose((1.0, 2.0, 1.2), (0.0, 0.0, 0.0, 2.0)), r"\|q\| = 2.0000"),
                         (pose((1.0, NAN, 1.2)), "not finite"),
                         (pose((1.0, 2.0, 1.2), (NAN, NAN, NAN, NAN)), "not a unit quaternion")]:
        with pytest.raises(cv.ConversionError, match=message):
            camera_pose_from_msg(msg)
