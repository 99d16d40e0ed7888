"""Message <-> numpy conversions: round trips, big-endian depth, and clear errors on bad input."""
from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("sensor_msgs.msg")
pytest.importorskip("leapnbv_msgs.msg")

from sensor_msgs.msg import Image, PointCloud2, PointField  # noqa: E402

from leapnbv_common import conversions as cv  # noqa: E402

pytestmark = pytest.mark.ros
rng = np.random.default_rng(3)


@pytest.mark.parametrize(
    "encoding, array",
    [
        ("rgb8", rng.integers(0, 255, (4, 5, 3), dtype=np.uint8)),
        ("bgr8", rng.integers(0, 255, (4, 5, 3), dtype=np.uint8)),
        ("mono8", rng.integers(0, 255, (4, 5), dtype=np.uint8)),
        ("16UC1", rng.integers(0, 65535, (4, 5), dtype=np.uint16)),
        ("32FC1", rng.normal(size=(4, 5)).astype(np.float32)),
    ],
)
def test_image_round_trip(encoding, array):
    msg = cv.numpy_to_image(array, encoding)
    assert msg.step == array.shape[1] * array.itemsize * (3 if array.ndim == 3 else 1)
    np.testing.assert_array_equal(cv.image_to_numpy(msg), array)


def test_bgr_becomes_rgb_and_mono_is_replicated():
    rgb = rng.integers(0, 255, (3, 4, 3), dtype=np.uint8)
    bgr_msg = cv.numpy_to_image(rgb[:, :, ::-1].copy(), "bgr8")
    np.testing.assert_array_equal(cv.image_to_rgb(bgr_msg), rgb)
    mono = rgb[:, :, 0].copy()
    np.testing.assert_array_equal(cv.image_to_rgb(cv.numpy_to_image(mono, "mono8"))[:, :, 2], mono)


def test_big_endian_16uc1_depth_in_metres():
    depth_mm = np.array([[1000, 2500], [0, 65535]], dtype=np.uint16)
    msg = Image(height=2, width=2, encoding="16UC1", is_bigendian=1, step=4)
    msg.data = depth_mm.astype(">u2").tobytes()
    np.testing.assert_allclose(cv.depth_to_metres(msg), [[1.0, 2.5], [0.0, 65.535]], rtol=1e-6)


def test_32fc1_nan_inf_and_negative_become_no_return():
    depth = np.array([[1.5, np.nan], [np.inf, 0.0], [-0.5, 2.0]], dtype=np.float32)
    out = cv.depth_to_metres(cv.numpy_to_image(depth, "32FC1"))
    np.testing.assert_array_equal(out, [[1.5, 0.0], [0.0, 0.0], [0.0, 2.0]])


def test_padded_rows_are_skipped():
    image = rng.integers(0, 255, (3, 4), dtype=np.uint8)
    padded = np.zeros((3, 8), dtype=np.uint8)
    padded[:, :4] = image
    msg = Image(height=3, width=4, encoding="mono8", step=8)
    msg.data = padded.tobytes()
    np.testing.assert_array_equal(cv.image_to_numpy(msg), image)


@pytest.mark.parametrize(
    "kwargs, data_len, message",
    [
        (dict(encoding="yuv422"), 12, "unsupported image encoding 'yuv422'"),
        (dict(encoding="rgb8", step=5), 10, "step 5 does not fit width 2"),
        (dict(encoding="16UC1", step=4), 7, "needs 8 bytes, got 7"),
        (dict(encoding="mono8", step=2, width=0), 0, "empty mono8 image"),
    ],
)
def test_bad_images_raise_clear_errors(kwargs, data_len, message):
    fields = dict(height=2, width=2, step=6)
    fields.update(kwargs)
    msg = Image(**fields)
    msg.data = bytes(data_len)
    with pytest.raises(cv.ConversionError, match=message):
        cv.image_to_numpy(msg)


def test_depth_from_colour_image_is_refused():
    with pytest.raises(cv.ConversionError, match="depth image expected"):
        cv.depth_to_metres(cv.numpy_to_image(np.zeros((2, 2, 3), np.uint8), "rgb8"))


def test_numpy_to_image_checks_dtype():
    with pytest.raises(cv.ConversionError, match="16UC1 needs a uint16"):
        cv.numpy_to_image(np.zeros((2, 2), np.float32), "16UC1")


def test_pointcloud_round_trip_and_padded_layout():
    points = rng.normal(size=(100, 3)).astype(np.float32)
    np.testing.assert_array_equal(cv.pointcloud2_to_xyz(cv.xyz_to_pointcloud2(points)), points)
    # x, y, z with an intensity field and padding between them (16-byte points)
    records = np.zeros((100, 4), dtype=np.float32)
    records[:, [0, 1, 2]] = points
    msg = PointCloud2(height=1, width=100, point_step=16, row_step=1600)
    msg.fields = [PointField(name=n, offset=o, datatype=PointField.FLOAT32, count=1)
                  for n, o in (("x", 0), ("y", 4), ("z", 8), ("intensity", 12))]
    msg.data = records.tobytes()
    np.testing.assert_array_equal(cv.pointcloud2_to_xyz(msg), points)
    assert cv.pointcloud2_to_xyz(cv.xyz_to_pointcloud2(np.zeros((0, 3)))).shape == (0, 3)


def test_pointcloud_without_z_is_refused():
    msg = cv.xyz_to_pointcloud2(np.zeros((2, 3)))
    msg.fields = msg.fields[:2]
    with pytest.raises(cv.ConversionError, match="needs x, y, z fields"):
        cv.pointcloud2_to_xyz(msg)


def _mesh_arrays(num_vertices=5):
    return cv.HumanMeshArrays(
        vertices=rng.normal(size=(num_vertices, 3)).astype(np.float32),
        faces=np.array([[0, 1, 2], [2, 3, 4]], np.uint32),
        virtual_intrinsics=(500.0, 510.0, 300.0, 200.0), image_size=(640, 480),
        detection=np.array([1, 2, 30, 40, 0.9], np.float32), processed_box=np.array([0, 1, 2, 3]),
        root_pose=np.ones(3), body_pose=np.linspace(0, 1, 63), left_hand_pose=np.zeros(45),
        right_hand_pose=np.ones(45), jaw_pose=np.zeros(3), betas=np.arange(10),
        expression=np.zeros(10), cam_translation=np.array([0.1, -0.2, 28.19]), model_id="m")


def test_human_mesh_round_trip():
    mesh = _mesh_arrays()
    back = cv.human_mesh_to_arrays(cv.arrays_to_human_mesh(mesh, compute_time_ms=3.0))
    np.testing.assert_array_equal(back.vertices, mesh.vertices)
    np.testing.assert_array_equal(back.faces, mesh.faces)
    np.testing.assert_allclose(back.body_pose, mesh.body_pose, rtol=1e-6)
    np.testing.assert_allclose(back.detection, mesh.detection)
    assert back.virtual_intrinsics == (500.0, 510.0, 300.0, 200.0) and back.model_id == "m"


def test_human_mesh_with_out_of_range_face_is_refused():
    mesh = _mesh_arrays(num_vertices=4)
    with pytest.raises(cv.ConversionError, match="face index 4 out of range for 4 vertices"):
        cv.human_mesh_to_arrays(cv.arrays_to_human_mesh(mesh))


def test_camera_info_k_round_trip_and_validation():
    k = np.array([[615.0, 0, 320.5], [0, 616.0, 240.5], [0, 0, 1]])
    info = cv.make_camera_info(k, 640, 480)
    np.testing.assert_array_equal(cv.camera_info_to_k(info), k)
    info.k = [0.0] * 9
    with pytest.raises(cv.ConversionError, match="not a valid pinhole"):
        cv.camera_info_to_k(info)


def test_pose_round_trip_through_quaternion():
    from leapnbv_common.conversions import pose_msg, pose_to_numpy

    for seed in range(20):
        q, _ = np.linalg.qr(np.random.default_rng(seed).normal(size=(3, 3)))
        q *= np.sign(np.linalg.det(q))  # a proper rotation
        rot, pos = pose_to_numpy(pose_msg(q, np.array([1.0, -2.0, 3.0])))
        np.testing.assert_allclose(rot, q, atol=1e-12)
        np.testing.assert_array_equal(pos, [1.0, -2.0, 3.0])
    # 180 degrees about x: the w = 0 branch
    rot, _ = pose_to_numpy(pose_msg(np.diag([1.0, -1.0, -1.0]), np.zeros(3)))
    np.testing.assert_allclose(rot, np.diag([1.0, -1.0, -1.0]), atol=1e-12)


def test_rotations_to_quaternions_every_branch_and_the_message_list():
    from leapnbv_common.conversions import pose_msgs, poses_to_numpy, quaternion_to_rotation, rotations_to_quaternions

    rng = np.random.default_rng(7)
    quaternions = rng.normal(size=(400, 4))
    quaternions /= np.linalg.norm(quaternions, axis=1)[:, None]
    # 180-degree turns about x, y, z and the identity: the four formulas (largest of trace, m00, m11, m22)
    specials = [np.diag([1.0, -1.0, -1.0]), np.diag([-1.0, 1.0, -1.0]), np.diag([-1.0, -1.0, 1.0]), np.eye(3)]
    rotations = np.concatenate([[quaternion_to_rotation(q) for q in quaternions], specials])
    diagonal = np.stack([np.trace(rotations, axis1=1, axis2=2), *np.diagonal(rotations, axis1=1, axis2=2).T[:3]])
    assert set(np.argmax(diagonal, axis=0)) == {0, 1, 2, 3}  # every formula is exercised
    out = rotations_to_quaternions(rotations)
    assert np.all(out[:, 3] >= 0.0)
    np.testing.assert_allclose(np.linalg.norm(out, axis=1), 1.0, atol=1e-15)
    np.testing.assert_allclose(np.abs(np.sum(out[:400] * quaternions, axis=1)), 1.0, atol=1e-12)  # q or -q
    np.testing.assert_allclose([quaternion_to_rotation(q) for q in out], rotations, atol=1e-12)
    positions = rng.normal(size=(len(rotations), 3))
    back_rotations, back_positions = poses_to_numpy(pose_msgs(rotations, positions))
    np.testing.assert_allclose(back_rotations, rotations, atol=1e-12)
    np.testing.assert_array_equal(back_positions, positions)
    assert rotations_to_quaternions(np.zeros((0, 3, 3))).shape == (0, 4) and pose_msgs(np.zeros((0, 3, 3)),
                                                                                       np.zeros((0, 3))) == []


def _rotation(angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def test_ground_plane_round_trip():
    plane = cv.GroundPlaneArrays(normal=np.array([0.0, -0.98, 0.2]), offset=1.25, valid=True, source=1,
                                 inlier_count=321, inlier_ratio=0.25, quality=0.75)
    msg = cv.arrays_to_ground_plane(plane, cv.header_with_stamp(1_500_000_123, "cam"), compute_time_ms=2.5)
    assert (msg.header.stamp.sec, msg.header.stamp.nanosec, msg.header.frame_id) == (1, 500_000_123, "cam")
    back = cv.ground_plane_to_arrays(msg)
    np.testing.assert_array_equal(back.normal, plane.normal)
    assert (back.offset, back.valid, back.source, back.inlier_count) == (1.25, True, 1, 321)
    assert back.inlier_ratio == pytest.approx(0.25)
    assert back.quality == pytest.approx(0.75)


def test_target_geometry_round_trip_carries_the_camera_of_the_frame():
    k = np.array([[500.0, 0.0, 320.0], [0.0, 510.0, 240.0], [0.0, 0.0, 1.0]])
    target = cv.TargetGeometryArrays(
        target_points=rng.normal(size=(7, 3)).astype(np.float32),
        background_points=rng.normal(size=(11, 3)).astype(np.float32),
        centroid=np.array([0.1, 0.2, 3.0]), bbox_min=np.array([-0.3, -0.9, 2.8]), bbox_max=np.array([0.3, 0.8, 3.2]),
        mask_pixel_count=123, visible_fraction=0.5, depth_offset=-0.02, valid=True, k=k, width=640, height=480)
    header = cv.header_with_stamp(7, "cam")
    msg = cv.arrays_to_target_geometry(target, header, 3.0)
    assert msg.camera_info.header.stamp == header.stamp and msg.target_points.header.frame_id == "cam"
    back = cv.target_geometry_to_arrays(msg)
    np.testing.assert_array_equal(back.target_points, target.target_points)
    np.testing.assert_array_equal(back.background_points, target.background_points)
    np.testing.assert_array_equal(back.k, k)
    assert (back.width, back.height, back.mask_pixel_count, back.valid) == (640, 480, 123, True)
    np.testing.assert_allclose(back.bbox_max, target.bbox_max)


def test_view_candidates_round_trip_keeps_terms_by_name():
    count, names = 5, ["visibility", "area", "occlusion"]
    term_scores = rng.uniform(size=(count, 3))
    weights = np.array([0.03, 0.14, 0.83])
    views = cv.ViewCandidatesArrays(
        rotations=np.array([_rotation(a) for a in np.linspace(0, 2, count)]),
        positions=rng.normal(size=(count, 3)), term_names=names, term_weights=weights, term_scores=term_scores,
        score=term_scores @ weights, feasible=np.array([True, False, True, True, False]),
        infeasible_reason=np.array([0, 1, 0, 0, 2], np.uint8), chosen_index=2, includes_current_view=True,
        ring_center=np.array([0.0, 1.3, 3.0]), ring_radius=2.5)
    back = cv.view_candidates_to_arrays(cv.arrays_to_view_candidates(views, cv.header_with_stamp(1, "cam")))
    assert back.term_names == names and len(back) == count
    np.testing.assert_allclose(back.term("area"), term_scores[:, 1].astype(np.float32))
    np.testing.assert_allclose(back.term("occlusion"), term_scores[:, 2].astype(np.float32))
    np.testing.assert_allclose(back.rotations, views.rotations, atol=1e-12)
    np.testing.assert_array_equal(back.feasible, views.feasible)
    np.testing.assert_array_equal(back.infeasible_reason, views.infeasible_reason)
    assert (back.chosen_index, back.includes_current_view, back.ring_radius) == (2, True, 2.5)
    with pytest.raises(KeyError, match="no score term 'height'"):
        back.term("height")


def test_view_candidates_with_inconsistent_lengths_are_refused():
    msg = cv.arrays_to_view_candidates(cv.ViewCandidatesArrays(
        rotations=np.array([np.eye(3)] * 2), positions=np.zeros((2, 3)), term_names=["a"],
        term_weights=np.array([1.0]), term_scores=np.zeros((2, 1)), score=np.zeros(2), feasible=np.ones(2, bool),
        infeasible_reason=np.zeros(2, np.uint8), chosen_index=0, includes_current_view=True,
        ring_center=np.zeros(3), ring_radius=1.0))
    msg.term_scores = msg.term_scores[:1]
    with pytest.raises(cv.ConversionError, match="2 poses and 1 terms"):
        cv.view_candidates_to_arrays(msg)


def test_scene_ground_truth_round_trip():
    truth = cv.SceneGroundTruthArrays(
        person_box=np.array([1.0, 2.0, 30.0, 40.0, 1.0]), root_pose=rng.normal(size=3), body_pose=rng.normal(size=63),
        left_hand_pose=rng.normal(size=45), right_hand_pose=rng.normal(size=45), jaw_pose=rng.normal(size=3),
        betas=rng.normal(size=10), expression=rng.normal(size=10), translation=np.array([0.1, 0.2, 3.0]),
        occlusion_share=0.4, body_model_id="stand_in_small")
    back = cv.scene_ground_truth_to_arrays(cv.arrays_to_scene_ground_truth(truth))
    for name in ("person_box", "root_pose", "body_pose", "left_hand_pose", "betas", "expression", "translation"):
        np.testing.assert_allclose(getattr(back, name), np.asarray(getattr(truth, name), np.float32), err_msg=name)
    assert back.body_model_id == "stand_in_small" and back.occlusion_share == pytest.approx(0.4)


def test_stage_outputs_carry_the_stamps_of_their_inputs():
    from leapnbv_msgs.msg import InputStamp

    inputs = [("human_mesh", 1_700_000_000_123_456_789), ("ground_plane", 1_699_999_999_900_000_000,
                                                           InputStamp.CARRIED)]
    header = cv.header_with_stamp(1_700_000_000_123_456_789, "cam")
    plane = cv.GroundPlaneArrays(normal=np.array([0.0, -1.0, 0.0]), offset=1.2, valid=True)
    messages = [cv.arrays_to_ground_plane(plane, header, inputs=inputs),
                cv.arrays_to_view_candidates(cv.ViewCandidatesArrays(
                    rotations=np.eye(3)[None], positions=np.zeros((1, 3)), term_names=["a"],
                    term_weights=np.ones(1), term_scores=np.zeros((1, 1)), score=np.zeros(1),
                    feasible=np.ones(1, bool), infeasible_reason=np.zeros(1, np.uint8), chosen_index=0,
                    includes_current_view=True, ring_center=np.zeros(3), ring_radius=1.0), header, inputs=inputs)]
    for msg in messages:
        assert cv.input_stamps(msg) == [("human_mesh", 1_700_000_000_123_456_789, InputStamp.SAME_FRAME),
                                        ("ground_plane", 1_699_999_999_900_000_000, InputStamp.CARRIED)]
    assert cv.input_stamps(cv.arrays_to_ground_plane(plane, header)) == []  # none given: an empty list


def test_serialized_header_and_image_size_are_read_without_deserializing():
    from rclpy.serialization import serialize_message

    for frame_id in ("", "c", "cam", "camera_color_optical_frame"):
        header = cv.header_with_stamp(12_000_000_345, frame_id)
        image = cv.numpy_to_image(np.zeros((48, 64, 3), np.uint8), "rgb8", header)
        cdr = serialize_message(image)
        assert cv.serialized_header_stamp_ns(cdr) == 12_000_000_345
        header, height, width = cv.serialized_image_header(cdr)
        assert (header.frame_id, header.stamp.sec, header.stamp.nanosec, height, width) == (frame_id, 12, 345, 48, 64)
    with pytest.raises(cv.ConversionError):
        cv.serialized_header_stamp_ns(b"\x00\x01\x00\x00")


def test_path_round_trip():
    rotations = np.stack([_rotation(0.1), _rotation(-0.4), np.eye(3)])
    positions = np.array([[0.0, 1.2, 0.0], [0.5, 1.2, 1.0], [1.0, 1.2, 2.0]])
    msg = cv.path_msg(rotations, positions, cv.header_with_stamp(5, "cam"))
    assert len(msg.poses) == 3 and msg.poses[1].header.frame_id == "cam" and msg.header.stamp.nanosec == 5
    back_r, back_p = cv.path_to_numpy(msg)
    np.testing.assert_allclose(back_r, rotations, atol=1e-12)
    np.testing.assert_array_equal(back_p, positions)
    with pytest.raises(cv.ConversionError, match="2 rotations for 3 positions"):
        cv.path_msg(rotations[:2], positions)


@pytest.mark.parametrize("stamp_ns", [0, 1, 999_999_999, 1_000_000_000, 1_700_000_000_123_456_789, -1, -1_500_000_000])
def test_ns_to_stamp_and_set_stamp_invert_stamp_to_ns(stamp_ns):
    from builtin_interfaces.msg import Time

    from leapnbv_msgs.msg import InputStamp

    stamp = cv.ns_to_stamp(stamp_ns)
    assert isinstance(stamp, Time) and 0 <= stamp.nanosec < 1_000_000_000
    assert cv.stamp_to_ns(stamp) == stamp_ns
    assert (stamp.sec, stamp.nanosec) == divmod(stamp_ns, 1_000_000_000)
    filled = InputStamp()
    cv.set_stamp(filled.stamp, stamp_ns)  # in place, in any message's Time field
    assert filled.stamp == stamp == cv.header_with_stamp(stamp_ns, "cam").stamp
    assert cv.input_stamp_msgs([("x", stamp_ns)])[0].stamp == stamp


def test_every_name_of_the_single_module_is_still_importable_from_the_package():
    # What `from leapnbv_common.conversions import X` gave when conversions was one module.
    names = """COLOUR_ENCODINGS ConversionError DEPTH_ENCODINGS GROUND_PLANE_SOURCES GroundPlaneArrays HumanMeshArrays
        IMAGE_ENCODINGS SceneGroundTruthArrays SerializedImage TargetGeometryArrays ViewCandidatesArrays
        arrays_to_ground_plane arrays_to_human_mesh arrays_to_scene_ground_truth arrays_to_target_geometry
        arrays_to_view_candidates box_to_detection camera_info_to_k check_image depth_to_metres detection_to_box
        detections_to_boxes float32_sequence ground_plane_to_arrays header_with_stamp human_mesh_to_arrays image_size
        image_to_numpy image_to_rgb input_stamp_msgs input_stamps make_camera_info numpy_to_image
        obstacle_map_to_points path_msg path_to_numpy point_msg point_to_numpy pointcloud2_to_xyz pose_msg pose_msgs
        pose_to_numpy poses_to_numpy quaternion_to_rotation rotations_to_quaternions scene_ground_truth_to_arrays
        serialized_header_stamp_ns serialized_image_header stamp_to_ns target_geometry_to_arrays uint32_sequence
        view_candidates_to_arrays xyz_to_pointcloud2""".split()
    assert set(names) <= set(cv.__all__)
    assert all(getattr(cv, name) is not None for name in cv.__all__)
    from leapnbv_common import rotations

    assert cv.rotations_to_quaternions is rotations.rotations_to_quaternions  # one definition of the math
