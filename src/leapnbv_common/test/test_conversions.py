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


def test_32fc1_nan_and_inf_become_no_return():
    depth = np.array([[1.5, np.nan], [np.inf, 0.0]], dtype=np.float32)
    out = cv.depth_to_metres(cv.numpy_to_image(depth, "32FC1"))
    np.testing.assert_array_equal(out, [[1.5, 0.0], [0.0, 0.0]])


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
